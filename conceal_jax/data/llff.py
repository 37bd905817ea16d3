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
  (`load_colmap` reads that); `llff_frustum_points` gives random points for initialisation instead.
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


def llff_frustum_points(root: PathLike, num: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
  """Random points inside the cameras' view frustums between their near and far bounds, for random
  initialisation where LLFF has no points: (points [num, 3], footprints [num]) float64.

  Each point picks a camera at random, a direction through a uniform point of its image, and a depth uniform
  in disparity between the camera's near and far bounds, so near and far depths get as many points per
  image-space layer; its footprint is the world width the camera's image spans at that depth (depth x
  width / focal), by which a start sizes splats to a share of the image whatever the scene's units. near,
  far are depths along the view axis, as LLFF's save_poses measures them (z of the SfM points in camera
  space). A box around the frustums would hold mostly space no camera sees.
  """
  source = Path(root) / POSES_FILE
  poses, bounds = read_poses_bounds(source)
  for index, (near, far) in enumerate(bounds):
    if not 0 < near <= far:
      raise DatasetError(f"{source}: row {index} has bounds near {near:g}, far {far:g}; LLFF needs "
                         f"0 < near <= far")
  if num < 1:
    raise ValueError(f"llff_frustum_points needs at least one point, got {num}")
  cameras = rng.integers(0, len(poses), num)
  near, far = bounds[cameras, 0], bounds[cameras, 1]
  depth = 1.0 / rng.uniform(1.0 / far, 1.0 / near)
  half = _half_fields(poses[cameras])  # [num, 2]
  # OpenGL camera space: x right, y up, looking down -z; an image point at depth d is (sx hx d, sy hy d, -d).
  directions = np.concatenate([rng.uniform(-1.0, 1.0, (num, 2)) * half, -np.ones((num, 1))], -1)
  c2w = llff_opengl_camera_to_world(poses[cameras])
  points = np.einsum("nij,nj->ni", c2w[:, :, :3], directions * depth[:, None]) + c2w[:, :, 3]
  return points, 2.0 * half[:, 0] * depth


def _half_fields(poses: np.ndarray) -> np.ndarray:
  """[N, 3, 5] LLFF poses -> [N, 2] tangents of the half fields of view across (x) and up (y)."""
  height, width, focal = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
  return np.stack([width, height], -1) / (2 * focal[:, None])
