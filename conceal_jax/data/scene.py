"""What every loader returns: `SceneData`, its error type, and the 3D-GS scene extent."""
from __future__ import annotations

import dataclasses
import os
from typing import Sequence

import numpy as np

from conceal_jax.splat.camera import Camera, camera_centers


PathLike = str | os.PathLike
Color = tuple[float, float, float]

WHITE: Color = (1.0, 1.0, 1.0)
BLACK: Color = (0.0, 0.0, 0.0)


class DatasetError(ValueError):
  """A scene folder that cannot be loaded: missing or malformed files, unsupported cameras."""


@dataclasses.dataclass(frozen=True, eq=False)  # array fields: == would be ambiguous
class SceneData:
  """A loaded scene.

  train_images, test_images: lists of [H, W, 3] float32 in [0, 1], composited on `background`.
  train_cameras, test_cameras: one `Camera` per image, of the image's size.
  points: [M, 3] float32 initialisation points (SfM or a point cloud file) or None.
  point_colors: [M, 3] float32 in [0, 1] or None.
  background: the RGB colour transparent pixels were composited on.
  train_names, test_names: the image file names, for reports and outputs.
  """
  train_images: list[np.ndarray]
  test_images: list[np.ndarray]
  train_cameras: list[Camera]
  test_cameras: list[Camera]
  points: np.ndarray | None
  point_colors: np.ndarray | None
  background: Color
  train_names: list[str] = dataclasses.field(default_factory=list)
  test_names: list[str] = dataclasses.field(default_factory=list)

  def scene_extent(self) -> float:
    """3D-GS scene scale: 1.1 x the largest distance of a training camera centre from their mean."""
    return camera_extent(self.train_cameras)


def camera_extent(cameras: Sequence[Camera]) -> float:
  """1.1 x max distance of a camera centre from the mean centre (0 for fewer than two cameras)."""
  if not cameras:
    return 0.0
  centers = camera_centers(cameras)
  return float(1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max())
