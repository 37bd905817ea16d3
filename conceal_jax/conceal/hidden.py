"""The hidden image I of ConcealGS: an image file or a scikit-image sample as [size, size, 3] in [0, 1].

Conversion, in order:
  - pixel values: uint8 / uint16 divided by their maximum, bool as 0 / 1, floats taken as already in
    [0, 1] (clipped; NaN or inf rejected); signed integers are rejected as ambiguous;
  - channels: greyscale (with or without alpha) repeated to RGB; an alpha channel is composited on white,
    the background of the NeRF-Synthetic renders the image hides in, and how transparent logos display;
  - geometry: the largest centred square is cropped (so nothing is stretched), then resized to
    size x size with anti-aliasing (a Gaussian prefilter when shrinking) and bilinear interpolation.
Channel order is RGB (the released ConcealGS code reads BGR with OpenCV; only its files differ).
"""
from __future__ import annotations

import os
import warnings

import numpy as np

# 2D still images bundled with scikit-image (no download needed), the names `skimage.data.<name>()` takes.
SAMPLE_NAMES = (
    "astronaut", "brick", "camera", "cat", "checkerboard", "chelsea", "clock", "coffee", "coins",
    "colorwheel", "grass", "gravel", "horse", "hubble_deep_field", "immunohistochemistry", "logo",
    "microaneurysms", "moon", "page", "retina", "rocket", "text",
)


class HiddenImageError(ValueError):
  """A hidden image source that cannot be read or converted; the message names the source."""


def load_hidden_image(source: str, size: int = 64) -> np.ndarray:
  """[size, size, 3] float32 in [0, 1] from an image file path or a scikit-image sample name.

  An existing file wins over a sample of the same name. Raises HiddenImageError (a ValueError) for a
  missing or unreadable file, an unknown sample name, an unusable image or size <= 0.
  """
  if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size <= 0:
    raise HiddenImageError(f"hidden image {source!r}: size must be a positive integer, got {size!r}")
  image = _read(os.fspath(source))
  return resize_square(to_rgb01(image, source), size)


def _read(source: str) -> np.ndarray:
  if os.path.isfile(source):
    import imageio.v3 as iio
    try:
      # imageio probes its legacy plugins on files pillow cannot read; their deprecation notices are noise.
      with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return np.asarray(iio.imread(source))
    # Image plugins raise assorted exception types for corrupt files; all of them mean "unreadable".
    except Exception as err:
      raise HiddenImageError(f"hidden image {source!r}: cannot read the file ({err})") from err
  if source in SAMPLE_NAMES:
    import skimage.data
    try:
      return np.asarray(getattr(skimage.data, source)())
    except Exception as err:  # a scikit-image install without its data files
      raise HiddenImageError(f"hidden image {source!r}: cannot load the sample ({err})") from err
  if os.sep in source or os.path.splitext(source)[1] or os.path.exists(source):
    raise HiddenImageError(f"hidden image {source!r}: not an existing image file")
  raise HiddenImageError(f"hidden image {source!r}: neither a file nor a scikit-image sample name "
                         f"(one of {', '.join(SAMPLE_NAMES)})")


def to_rgb01(image: np.ndarray, source: str = "<array>") -> np.ndarray:
  """[H, W], [H, W, 1 | 2 | 3 | 4] -> [H, W, 3] float32 in [0, 1], alpha composited on white."""
  image = np.asarray(image)
  if image.ndim == 2:
    image = image[..., None]
  if image.ndim != 3 or image.shape[-1] not in (1, 2, 3, 4) or image.size == 0:
    raise HiddenImageError(f"hidden image {source!r}: expected a 2D greyscale or colour image, "
                           f"got shape {image.shape}")
  if image.dtype == bool:
    values = image.astype(np.float32)
  elif np.issubdtype(image.dtype, np.unsignedinteger):
    values = image.astype(np.float32) / np.iinfo(image.dtype).max
  elif np.issubdtype(image.dtype, np.floating):
    if not np.all(np.isfinite(image)):
      raise HiddenImageError(f"hidden image {source!r}: contains NaN or inf")
    values = np.clip(image, 0.0, 1.0).astype(np.float32)
  else:
    raise HiddenImageError(f"hidden image {source!r}: unsupported pixel type {image.dtype}")
  has_alpha = values.shape[-1] in (2, 4)
  colour = values[..., :-1] if has_alpha else values
  if colour.shape[-1] == 1:
    colour = np.repeat(colour, 3, axis=-1)
  if has_alpha:
    alpha = values[..., -1:]
    colour = colour * alpha + (1.0 - alpha)
  return colour.astype(np.float32)


def resize_square(image: np.ndarray, size: int) -> np.ndarray:
  """[H, W, 3] -> [size, size, 3] float32: centred square crop, then anti-aliased bilinear resize."""
  import skimage.transform
  h, w = image.shape[:2]
  side = min(h, w)
  top, left = (h - side) // 2, (w - side) // 2
  square = image[top:top + side, left:left + side]
  resized = skimage.transform.resize(square, (size, size), order=1, anti_aliasing=True)
  return np.clip(resized, 0.0, 1.0).astype(np.float32)
