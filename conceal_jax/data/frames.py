"""The loading steps every format shares: frames (image file + camera), parallel reading, checks that
name the offending file."""
from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from conceal_jax.data.distortion import Distortion, undistortion_sampler
from conceal_jax.data.images import read_image, resize_image
from conceal_jax.data.scene import Color, DatasetError, SceneData
from conceal_jax.splat.camera import Camera


# Image decoding releases the GIL, so a few threads hide most of the file and PNG/JPEG cost.
_MAX_IO_THREADS = 8
# Image files found by folder (LLFF, and the folders an error lists): NeRF's load_llff_data reads JPG, jpg and
# png; JPEG spellings cost nothing to accept as well. Compared in lower case.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# Downscaled copies (images_4, ...) are resized with whole-pixel sizes (LLFF's minify uses ImageMagick).
_SIZE_TOLERANCE_PX = 1.0


@dataclasses.dataclass(frozen=True)
class Frame:
  """One image to load: its file, where its description came from, and its full-size camera."""
  image_path: Path
  source: Path  # the file that describes the camera, for error messages
  camera: Camera
  distortion: Distortion = Distortion()
  name: str = ""


def load_frames(frames: Sequence[Frame], downscale: float,
                 background: Sequence[float]) -> tuple[list[np.ndarray], list[Camera]]:
  """Reads, checks, downscales and undistorts every frame; [h, w, 3] images and their cameras.

  Undistortion runs after the area downscale, at the output resolution: its cost then shrinks with
  the image, and the lens warp is smooth enough that the order barely changes the pixels.
  """
  check_downscale(downscale)
  cameras = [f.camera if downscale == 1 else f.camera.rescale(downscale) for f in frames]
  samplers: dict[tuple, Callable] = {}

  def load(frame: Frame, camera: Camera) -> np.ndarray:
    image = read_image(frame.image_path, background)
    if image.shape[:2] != (frame.camera.height, frame.camera.width):
      raise DatasetError(
          f"image {frame.image_path} is {image.shape[1]}x{image.shape[0]} but its camera in "
          f"{frame.source} is {frame.camera.width}x{frame.camera.height}")
    image = resize_image(image, downscale)
    if frame.distortion.is_identity:
      return image
    intrinsics = tuple(float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    key = intrinsics + (camera.width, camera.height, frame.distortion)
    if key not in samplers:  # dict writes are atomic under the GIL; a duplicate build is harmless
      samplers[key] = undistortion_sampler(*intrinsics, camera.width, camera.height, frame.distortion)
    return samplers[key](image)

  workers = min(_MAX_IO_THREADS, os.cpu_count() or 1, max(1, len(frames)))
  with concurrent.futures.ThreadPoolExecutor(workers) as pool:
    images = list(pool.map(load, frames, cameras))
  return images, cameras


def hold_out_every(frames: Sequence[Frame], test_every: int) -> tuple[list[Frame], list[Frame]]:
  """(train, test): every `test_every`-th frame (index % test_every == 0) is a test frame, as 3D-GS holds
  out real captures; 0 puts every frame in training."""
  is_test = [test_every > 0 and i % test_every == 0 for i in range(len(frames))]
  return [f for f, t in zip(frames, is_test) if not t], [f for f, t in zip(frames, is_test) if t]


def load_scene_data(train_frames: Sequence[Frame], test_frames: Sequence[Frame], downscale: float,
                    background: Color, points: np.ndarray | None = None,
                    point_colors: np.ndarray | None = None) -> SceneData:
  """Loads both splits into a SceneData (names from the frames)."""
  train_images, train_cameras = load_frames(train_frames, downscale, background)
  test_images, test_cameras = load_frames(test_frames, downscale, background)
  return SceneData(train_images, test_images, train_cameras, test_cameras, points, point_colors, background,
                   [f.name for f in train_frames], [f.name for f in test_frames])


def check_downscale(downscale: float) -> None:
  if not (isinstance(downscale, (int, float)) and math.isfinite(downscale) and downscale > 0):
    raise DatasetError(f"downscale must be a positive number, got {downscale!r}")


def check_background(background: Sequence[float]) -> Color:
  values = tuple(float(v) for v in background)
  if len(values) != 3:
    raise DatasetError(f"background must be 3 floats (RGB), got {background!r}")
  return values  # type: ignore[return-value]


def require_dir(path: Path, what: str) -> None:
  if not path.is_dir():
    raise DatasetError(f"{what} folder not found: {path}")


def image_folders(root: Path) -> list[str]:
  """Names of the folders directly in `root` that hold at least one image file, sorted: what an error about a
  missing images folder offers instead."""
  return sorted(child.name for child in root.iterdir()
                if child.is_dir() and not child.name.startswith(".") and _holds_images(child))


def _holds_images(folder: Path) -> bool:
  return any(p.suffix.lower() in IMAGE_SUFFIXES and p.is_file() for p in folder.iterdir())


def downscaled_copy_size(path: Path, full_size: tuple[float, float], what: str) -> tuple[int, int]:
  """(width, height) of the image at `path`: `full_size` (width, height) itself, or a copy smaller on both
  sides by one factor up to whole-pixel rounding, as folders such as images_4 hold. The folder name is
  never trusted; the intrinsics follow the actual size. DatasetError naming the image and `what` (where
  the full size comes from) otherwise."""
  actual_width, actual_height = image_size(path)
  width, height = full_size
  same = (actual_width, actual_height) == (width, height)
  smaller = actual_width < width and actual_height < height
  # One factor must explain both sides: each side predicted from the other's factor.
  consistent = (abs(width * actual_height / height - actual_width) <= _SIZE_TOLERANCE_PX
                and abs(height * actual_width / width - actual_height) <= _SIZE_TOLERANCE_PX)
  if not (same or (smaller and consistent)):
    raise DatasetError(f"image {path} is {actual_width}x{actual_height}, not a downscaled copy of the "
                       f"{width:g}x{height:g} (width x height) of {what}")
  return actual_width, actual_height


def read_json(path: Path) -> Any:
  if not path.is_file():
    raise DatasetError(f"file not found: {path}")
  try:
    return json.loads(path.read_text())
  except (OSError, ValueError) as e:
    raise DatasetError(f"cannot parse {path}: {e}") from e


def frame_image_path(root: Path, file_path: str) -> Path:
  """NeRF-style file_path, relative to the json folder; PNG when it has no extension."""
  path = root / file_path
  png = path.with_name(path.name + ".png")
  return png if not path.suffix or (not path.is_file() and png.is_file()) else path


def matrix(value: Any, source: Path, what: str) -> np.ndarray:
  try:
    matrix = np.asarray(value, np.float64)
  except (TypeError, ValueError) as e:
    raise DatasetError(f"{source}: {what} is not a numeric matrix") from e
  if matrix.shape not in ((3, 4), (4, 4)) or not np.isfinite(matrix).all():
    raise DatasetError(f"{source}: {what} must be a finite [3, 4] or [4, 4] matrix, got {matrix.shape}")
  return matrix


def image_size(path: Path) -> tuple[int, int]:
  """(width, height) read from the file header only."""
  from PIL import Image
  if not path.is_file():
    raise DatasetError(f"image file not found: {path}")
  try:
    with Image.open(path) as image:
      return image.size
  except Exception as e:
    raise DatasetError(f"cannot read image {path}: {e}") from e
