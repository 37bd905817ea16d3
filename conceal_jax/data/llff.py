"""LLFF forward-facing scenes: poses_bounds.npy plus images/ (or a downscaled images_N/).

The format of Local Light Field Fusion (Mildenhall et al., arXiv:1905.00889), written by
`save_poses` in github.com/Fyusion/LLFF (llff/poses/pose_utils.py) and read by NeRF's `load_llff_data`
(github.com/bmild/nerf, load_llff.py): one row of 17 values per image, in sorted file-name order, a
row-major 3x5 [R | t | hwf] camera-to-world matrix then the near and far depth bounds.

The poses stay in the capture's world frame: NeRF's recentring and bounds rescaling serve its NDC ray
sampling, while 3D-GS (arXiv:2308.04079) trains in the SfM frame, and keeping it lets LLFF cameras be
compared with (and mixed with) the COLMAP model they were made from.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from conceal_jax.data import frames as frames_lib
from conceal_jax.data.frames import Frame
from conceal_jax.data.scene import BLACK, DatasetError, PathLike, SceneData
from conceal_jax.splat.camera import Camera

POSES_FILE = "poses_bounds.npy"
_ROTATION_TOLERANCE = 1e-3


def load_llff(root: PathLike, downscale: float = 1, background: Sequence[float] = BLACK,
              images_dir: str | None = None, test_every: int = 8) -> SceneData:
  """LLFF scene: root/poses_bounds.npy and the images in root/images_dir (None: root/images).

  images_dir may be a downscaled copy such as "images_4": the intrinsics follow each image's actual
  size against the full-resolution hwf, so the folder name is never trusted. `downscale` shrinks
  further, as in the other loaders. Every `test_every`-th image (index % test_every == 0) in file-name
  order is a test image (0: none). points stay None even when a COLMAP model sits beside the file
  (`load_colmap` reads that); `llff_bounds_box` gives a box for random initialisation instead.
  """
  root = Path(root)
  frames_lib.require_dir(root, "LLFF scene")
  background = frames_lib.check_background(background)
  source = root / POSES_FILE
  poses, _ = read_poses_bounds(source)
  folder = root / (images_dir or "images")
  frames_lib.require_dir(folder, "LLFF images")
  paths = llff_image_paths(folder)
  if len(paths) != len(poses):
    raise DatasetError(f"{folder} has {len(paths)} images but {source} has {len(poses)} poses; LLFF "
                       f"matches them one to one in file-name order")
  frames = [_llff_frame(path, source, index, pose) for index, (path, pose) in enumerate(zip(paths, poses))]
  return frames_lib.load_scene_data(*frames_lib.hold_out_every(frames, test_every), downscale, background)


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray]:
  """poses [N, 3, 5] float64 ([R | t | hwf], R's columns down, right, backwards) and bounds [N, 2]
  (near, far), checked to be finite, with proper rotations and a positive hwf."""
  if not path.is_file():
    raise DatasetError(f"LLFF poses file not found: {path}")
  try:
    array = np.load(path, allow_pickle=False)
  except (OSError, ValueError) as e:
    raise DatasetError(f"cannot read {path}: {e}") from e
  if (array.ndim != 2 or array.shape[0] < 1 or array.shape[1] != 17
      or not np.issubdtype(array.dtype, np.number)):
    raise DatasetError(f"{path} must hold a numeric [N, 17] array (3x5 pose and near, far per image), "
                       f"got {array.dtype} {list(array.shape)}")
  array = array.astype(np.float64)
  if not np.isfinite(array).all():
    raise DatasetError(f"{path} holds non-finite values (row {int(np.argmin(np.isfinite(array).all(1)))})")
  poses, bounds = array[:, :15].reshape(-1, 3, 5), array[:, 15:]
  for index, pose in enumerate(poses):
    _check_pose(pose, path, index)
  return poses, bounds


def _check_pose(pose: np.ndarray, source: Path, index: int) -> None:
  # A reflection or a scaled R would still render, mirrored or distorted: refuse it instead.
  rotation = pose[:, :3]
  if (np.abs(rotation.T @ rotation - np.eye(3)).max() > _ROTATION_TOLERANCE
      or np.linalg.det(rotation) <= 0):
    raise DatasetError(f"{source}: row {index} has a 3x3 part that is not a rotation")
  if (pose[:, 4] <= 0).any():
    raise DatasetError(f"{source}: row {index} has a non-positive height, width or focal "
                       f"{pose[:, 4].tolist()}")


def llff_image_paths(folder: Path) -> list[Path]:
  """Image files of `folder` in sorted name order, the order LLFF wrote the poses in."""
  return sorted((p for p in folder.iterdir()
                 if p.suffix.lower() in frames_lib.IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()),
                key=lambda p: p.name)


def llff_opengl_camera_to_world(pose: np.ndarray) -> np.ndarray:
  """[..., 3, 5] LLFF pose -> [..., 3, 4] OpenGL (right, up, backwards) camera-to-world.

  LLFF's save_poses stores COLMAP's OpenCV axes (right, down, forwards) as (down, right, backwards);
  NeRF's load_llff_data undoes it as [col1, -col0, col2]."""
  return np.stack([pose[..., :, 1], -pose[..., :, 0], pose[..., :, 2], pose[..., :, 3]], axis=-1)


def _llff_frame(path: Path, source: Path, index: int, pose: np.ndarray) -> Frame:
  height, width, focal = pose[:, 4]
  actual_width, actual_height = frames_lib.downscaled_copy_size(path, (width, height), f"row {index} in {source}")
  scale_x, scale_y = actual_width / width, actual_height / height
  # LLFF (and NeRF) assume a centred principal point and square pixels at full resolution.
  camera = Camera.from_opengl_camera_to_world(llff_opengl_camera_to_world(pose), focal * scale_x,
                                              focal * scale_y, actual_width / 2, actual_height / 2,
                                              actual_width, actual_height)
  return Frame(path, source, camera, name=path.name)


def llff_bounds_box(root: PathLike) -> tuple[np.ndarray, np.ndarray]:
  """(lo [3], hi [3]) float64: the axis-aligned world box holding every camera centre and each camera's
  view frustum between its near and far bounds, for random initialisation where LLFF has no points.

  The frustum segment is the convex hull of its 8 corners (image corners at the near and far depths),
  so the box of those corners and the centres is the smallest box holding it all; near, far are depths
  along the view axis, as LLFF's save_poses measures them (z of the SfM points in camera space).
  """
  source = Path(root) / POSES_FILE
  poses, bounds = read_poses_bounds(source)
  for index, (near, far) in enumerate(bounds):
    if near > far:
      raise DatasetError(f"{source}: row {index} has near bound {near:g} beyond far bound {far:g}")
  points = np.concatenate([poses[:, :, 3], _frustum_corners(poses, bounds).reshape(-1, 3)])
  return points.min(0), points.max(0)


def _frustum_corners(poses: np.ndarray, bounds: np.ndarray) -> np.ndarray:
  """[N, 2, 4, 3] world positions of the image corners at the near and far depths of each camera."""
  c2w = llff_opengl_camera_to_world(poses)
  height, width, focal = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
  signs = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]], np.float64)  # [4, 2] corner (x, y) signs
  half = np.stack([width, height], -1) / (2 * focal[:, None])  # [N, 2] tan of the half fields of view
  # OpenGL camera space: x right, y up, looking down -z; a corner at depth d is (sx hx d, sy hy d, -d).
  directions = np.concatenate([signs[None] * half[:, None], -np.ones((len(poses), 4, 1))], -1)  # [N,4,3]
  camera_points = bounds[:, :, None, None] * directions[:, None]  # [N, 2, 4, 3]
  return np.einsum("nij,nkcj->nkci", c2w[:, :, :3], camera_points) + c2w[:, None, None, :, 3]
