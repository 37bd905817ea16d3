"""Attacks on a rendered check view before it is decoded: blur, JPEG, noise, brightness/contrast, resize.

ConcealGS (arXiv:2501.03605, Sec. 3, robustness figure) blurs and JPEG-compresses the check render and
reports the hidden image's SSIM; the other attacks are the usual image-space distortions of the
watermarking literature. Every attack is a function image [H, W, 3] in [0, 1] -> same shape in [0, 1]
(numpy, float32), deterministic given its level (and seed for noise). `LEVELS` lists each attack's levels
from mild to strong with the severity class used by the ownership test.
"""
from __future__ import annotations

import io

import numpy as np

MILD, MEDIUM, STRONG = "mild", "medium", "strong"


def _check(image) -> np.ndarray:
  image = np.asarray(image, np.float64)
  if image.ndim != 3 or image.shape[-1] != 3:
    raise ValueError(f"an attack takes an image [H, W, 3], got shape {image.shape}")
  return image


def _out(image: np.ndarray) -> np.ndarray:
  return np.clip(image, 0.0, 1.0).astype(np.float32)


def gaussian_blur(image, sigma: float) -> np.ndarray:
  """Gaussian blur of standard deviation `sigma` pixels (reflected borders); sigma 0 is the identity."""
  import skimage.filters
  image = _check(image)
  if sigma <= 0:
    return _out(image)
  return _out(skimage.filters.gaussian(image, sigma=sigma, channel_axis=-1, mode="reflect", truncate=4.0,
                                       preserve_range=True))


def jpeg(image, quality: int) -> np.ndarray:
  """Encodes as 8-bit JPEG at `quality` (1-100) with imageio (pillow) and decodes it again."""
  import imageio.v3 as iio
  image = _check(image)
  if not 1 <= quality <= 100:
    raise ValueError(f"JPEG quality must be in 1..100, got {quality}")
  pixels = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
  buffer = io.BytesIO()
  iio.imwrite(buffer, pixels, extension=".jpeg", quality=int(quality))
  return _out(iio.imread(buffer.getvalue(), extension=".jpeg").astype(np.float64) / 255.0)


def gaussian_noise(image, sigma: float, seed: int = 0) -> np.ndarray:
  """Adds i.i.d. normal noise of standard deviation `sigma` (image units) to every value, then clips."""
  image = _check(image)
  return _out(image + sigma * np.random.default_rng(seed).normal(size=image.shape))


def brightness_contrast(image, brightness: float = 0.0, contrast: float = 1.0) -> np.ndarray:
  """(image - 0.5) * contrast + 0.5 + brightness, clipped."""
  return _out((_check(image) - 0.5) * contrast + 0.5 + brightness)


def resize_down_up(image, factor: float) -> np.ndarray:
  """Shrinks by `factor` (0 < factor <= 1, antialiased) and enlarges back to the original size (bilinear)."""
  import skimage.transform
  image = _check(image)
  if not 0 < factor <= 1:
    raise ValueError(f"resize factor must be in (0, 1], got {factor}")
  h, w = image.shape[:2]
  small = skimage.transform.resize(image, (max(1, round(h * factor)), max(1, round(w * factor))), order=1,
                                   anti_aliasing=factor < 1)
  return _out(skimage.transform.resize(small, (h, w), order=1, anti_aliasing=False))


ATTACKS = {"blur": gaussian_blur, "jpeg": jpeg, "noise": gaussian_noise,
           "brightness": lambda image, level: brightness_contrast(image, brightness=level),
           "contrast": lambda image, level: brightness_contrast(image, contrast=level),
           "resize": resize_down_up}

# (attack, level, severity), mild to strong. The paper's mild levels: blur sigma <= 1, JPEG quality >= 70.
LEVELS = (
    [("blur", s, MILD if s <= 1 else MEDIUM if s <= 2 else STRONG) for s in (0.5, 1.0, 2.0, 3.0)]
    + [("jpeg", q, MILD if q >= 70 else MEDIUM if q >= 30 else STRONG) for q in (95, 90, 70, 50, 30, 10)]
    + [("noise", s, MILD if s <= 0.01 else MEDIUM if s <= 0.03 else STRONG) for s in (0.01, 0.03, 0.1)]
    + [("brightness", b, MILD if abs(b) <= 0.05 else MEDIUM) for b in (-0.1, -0.05, 0.05, 0.1)]
    + [("contrast", c, MILD if abs(c - 1) <= 0.1 else MEDIUM) for c in (0.8, 0.9, 1.1, 1.2)]
    + [("resize", f, MILD if f >= 0.75 else MEDIUM if f >= 0.5 else STRONG) for f in (0.75, 0.5, 0.25)])


def attack(image, name: str, level) -> np.ndarray:
  """The attack `name` (a key of ATTACKS) at `level`."""
  if name not in ATTACKS:
    raise ValueError(f"unknown image attack {name!r}; choose from {sorted(ATTACKS)}")
  return ATTACKS[name](image, level)
