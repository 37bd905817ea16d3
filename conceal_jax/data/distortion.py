"""OpenCV lens distortion and its removal: resampling a distorted image to the pinhole camera of the same
intrinsics (COLMAP and transforms.json captures)."""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np


@dataclasses.dataclass(frozen=True)
class Distortion:
  """OpenCV lens distortion of normalised image coordinates (COLMAP FULL_OPENCV is the general case).

  k1, k2, k3 / k4, k5, k6: rational radial numerator / denominator polynomials in r^2, r^4, r^6.
  p1, p2: tangential (decentring) coefficients.
  """
  k1: float = 0.0
  k2: float = 0.0
  k3: float = 0.0
  k4: float = 0.0
  k5: float = 0.0
  k6: float = 0.0
  p1: float = 0.0
  p2: float = 0.0

  @property
  def is_identity(self) -> bool:
    return not any(dataclasses.astuple(self))


def distort(x: np.ndarray, y: np.ndarray, d: Distortion) -> tuple[np.ndarray, np.ndarray]:
  """Distorted normalised coordinates of undistorted ones (x, y: same shape), OpenCV's model."""
  r2 = x * x + y * y
  radial = (1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))) / (1.0 + r2 * (d.k4 + r2 * (d.k5 + r2 * d.k6)))
  xy = x * y
  xd = x * radial + 2.0 * d.p1 * xy + d.p2 * (r2 + 2.0 * x * x)
  yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * xy
  return xd, yd


def undistortion_sampler(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                         distortion: Distortion) -> Callable[[np.ndarray], np.ndarray]:
  """A function mapping a distorted [height, width, C] image to the pinhole image of the same
  intrinsics, sampling bilinearly (edge pixels repeat where the pinhole view sees past the lens)."""
  # float32 keeps sub-pixel precision up to ~10^4 pixels and halves the cost of large images.
  u = (np.arange(width, dtype=np.float32) + 0.5 - np.float32(cx)) / np.float32(fx)
  v = (np.arange(height, dtype=np.float32) + 0.5 - np.float32(cy)) / np.float32(fy)
  xd, yd = distort(u[None, :], v[:, None], distortion)
  # Pixel (i, j) is centred at (j + 0.5, i + 0.5), so array coordinates are image coordinates - 0.5.
  return bilinear_sampler(yd * np.float32(fy) + np.float32(cy - 0.5),
                          xd * np.float32(fx) + np.float32(cx - 0.5), height, width)


def bilinear_sampler(rows: np.ndarray, cols: np.ndarray, height: int,
                     width: int) -> Callable[[np.ndarray], np.ndarray]:
  """Precomputed bilinear lookup at fractional array coordinates (rows, cols: [h, w]) of a
  [height, width, C] image, clamped to its edges; returns image -> [h, w, C]."""
  def axis(coords, size):
    coords = np.clip(coords, 0.0, size - 1.0)
    lo = np.minimum(np.floor(coords), max(size - 2, 0)).astype(np.int32)
    frac = (coords - lo).astype(np.float32).reshape(-1, 1)
    return lo, np.minimum(lo + 1, size - 1), frac

  shape = np.broadcast_shapes(np.shape(rows), np.shape(cols))
  r0, r1, wr = axis(np.broadcast_to(rows, shape), height)
  c0, c1, wc = axis(np.broadcast_to(cols, shape), width)
  flat = [(r * width + c).reshape(-1) for r in (r0, r1) for c in (c0, c1)]
  weights = [(1 - wr) * (1 - wc), (1 - wr) * wc, wr * (1 - wc), wr * wc]

  def sample(image: np.ndarray) -> np.ndarray:
    if image.shape[:2] != (height, width):
      raise ValueError(f"sampler built for {width}x{height}, got image {image.shape}")
    pixels = image.reshape(height * width, -1)
    out = sum(w * np.take(pixels, i, axis=0) for w, i in zip(weights, flat))
    return out.reshape(shape + image.shape[2:]).astype(np.float32)

  return sample
