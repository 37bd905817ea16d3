"""Reading images as float RGB in [0, 1] (alpha composited on a background) and area downscaling."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from conceal_jax.data.scene import DatasetError, PathLike


def read_image(path: PathLike, background: Sequence[float]) -> np.ndarray:
  """[H, W, 3] float32 in [0, 1]; grey images are expanded and alpha is composited on `background`."""
  import imageio.v3 as iio
  path = Path(path)
  if not path.is_file():
    raise DatasetError(f"image file not found: {path}")
  try:
    pixels = np.asarray(iio.imread(path))
  except Exception as e:  # imageio raises a zoo of types for corrupt or unknown files
    raise DatasetError(f"cannot read image {path}: {e}") from e
  image = _to_float(pixels, path)
  if image.ndim == 2:
    image = image[..., None]
  channels = image.shape[-1]
  if channels in (2, 4):  # grey + alpha or RGBA
    # rgb * a + bg * (1 - a), written as bg + a * (rgb - bg) to make one fewer full-size temporary.
    bg = np.asarray(background, np.float32)
    out = np.broadcast_to(image[..., :-1], image.shape[:2] + (3,)) - bg
    out *= image[..., -1:]
    out += bg
    return out
  if channels == 1:
    return np.repeat(image, 3, axis=-1)
  if channels == 3:
    return image
  raise DatasetError(f"image {path} has {channels} channels, expected 1 to 4")


def _to_float(pixels: np.ndarray, path: Path) -> np.ndarray:
  if pixels.dtype == np.uint8:
    return pixels.astype(np.float32) / 255.0
  if pixels.dtype == np.uint16:
    return pixels.astype(np.float32) / 65535.0
  if np.issubdtype(pixels.dtype, np.floating):
    return np.clip(pixels.astype(np.float32), 0.0, 1.0)
  raise DatasetError(f"image {path} has unsupported pixel type {pixels.dtype}")


def downscaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
  """(width, height) after `downscale`, rounded as `Camera.rescale` does."""
  return max(1, round(width / downscale)), max(1, round(height / downscale))


def resize_image(image: np.ndarray, downscale: float) -> np.ndarray:
  """[H, W, C] -> [h, w, C] of `downscaled_size`: block mean for exact integer factors, else an
  anti-aliased resize (both approximate an area filter)."""
  height, width = image.shape[:2]
  new_width, new_height = downscaled_size(width, height, downscale)
  if (new_width, new_height) == (width, height):
    return image
  fy, fx = height // new_height, width // new_width
  if fy == fx and fy * new_height == height and fx * new_width == width:
    # Two single-axis sums over contiguous blocks are several times faster than one 2-axis mean.
    rows = image.reshape(height, new_width, fx, -1).sum(axis=2, dtype=np.float32)
    blocks = rows.reshape(new_height, fy, new_width, -1).sum(axis=1)
    return (blocks / (fx * fy)).astype(np.float32)
  from skimage.transform import resize
  resized = resize(image, (new_height, new_width) + image.shape[2:], order=1,
                   anti_aliasing=new_height < height, preserve_range=True)
  return np.clip(resized, 0.0, 1.0).astype(np.float32)
