"""instant-ngp / nerfstudio scenes: one transforms.json with OpenGL poses and (optionally) lens distortion."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from conceal_jax.data import frames as frames_lib
from conceal_jax.data.distortion import Distortion
from conceal_jax.data.frames import Frame
from conceal_jax.data.scene import BLACK, DatasetError, PathLike, SceneData
from conceal_jax.splat.camera import Camera, fov_to_focal


_TRANSFORMS_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


def load_transforms(root: PathLike, downscale: float = 1, background: Sequence[float] = BLACK,
                    test_every: int = 8, filename: str = "transforms.json") -> SceneData:
  """instant-ngp / nerfstudio scene: one transforms.json with OpenGL camera-to-world poses.

  Intrinsics fl_x, fl_y, cx, cy, w, h and distortion k1, k2, k3, p1, p2 may be global or per frame
  (a frame's value wins); camera_angle_x (and _y) stand in for missing focal lengths, the image
  size for missing w, h. Frames sorted by file_path; every `test_every`-th is a test image. Points
  come from nerfstudio's ply_file_path when present.
  """
  root = Path(root)
  frames_lib.require_dir(root, "transforms.json scene")
  background = frames_lib.check_background(background)
  source = root / filename
  meta = frames_lib.read_json(source)
  entries = meta.get("frames") if isinstance(meta, dict) else None
  if not isinstance(entries, list) or not entries:
    raise DatasetError(f"{source}: needs a non-empty frames list")
  frames = sorted((_transforms_frame(root, source, meta, entry, i) for i, entry in enumerate(entries)),
                  key=lambda f: str(f.image_path))
  points, colors = (_read_ply_points(root / meta["ply_file_path"]) if meta.get("ply_file_path")
                    else (None, None))
  return frames_lib.load_scene_data(*frames_lib.hold_out_every(frames, test_every), downscale, background,
                                    points, colors)


def _transforms_frame(root: Path, source: Path, meta: dict, entry: Any, index: int) -> Frame:
  if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
    raise DatasetError(f"{source}: frame {index} needs file_path and transform_matrix")
  lookup = lambda key, default=None: entry.get(key, meta.get(key, default))
  model = lookup("camera_model", "OPENCV")
  if model not in _TRANSFORMS_MODELS:
    raise DatasetError(f"{source}: frame {index} has unsupported camera_model {model}; supported: "
                       f"{', '.join(_TRANSFORMS_MODELS)}")
  image_path = frames_lib.frame_image_path(root, entry["file_path"])
  c2w = frames_lib.matrix(entry["transform_matrix"], source, f"frame {index} transform_matrix")
  try:
    if lookup("w") is not None and lookup("h") is not None:
      width, height = int(lookup("w")), int(lookup("h"))
    else:
      width, height = frames_lib.image_size(image_path)
    fx = _focal(lookup("fl_x"), lookup("camera_angle_x"), width)
    fy = _focal(lookup("fl_y"), lookup("camera_angle_y"), height, fallback=fx)
    cx, cy = float(lookup("cx", width / 2)), float(lookup("cy", height / 2))
    coefficients = {k: float(lookup(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
  except (TypeError, ValueError) as e:
    raise DatasetError(f"{source}: frame {index} has invalid intrinsics ({e})") from e
  if fx is None:
    raise DatasetError(f"{source}: frame {index} has no fl_x or camera_angle_x")
  # nerfstudio's perspective k4 is an r^8 term, unlike OpenCV's rational k4: refuse it, not misuse it.
  if coefficients.pop("k4"):
    raise DatasetError(f"{source}: frame {index} has a non-zero k4, which is not supported")
  camera = Camera.from_opengl_camera_to_world(c2w, fx, fy, cx, cy, width, height)
  return Frame(image_path, source, camera, Distortion(**coefficients), image_path.name)


def _focal(focal: Any, angle: Any, pixels: int, fallback: float | None = None) -> float | None:
  if focal is not None:
    return float(focal)
  if angle is not None:
    return fov_to_focal(float(angle), pixels)
  return fallback


def _read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
  """Vertex positions [M, 3] and colours [M, 3] in [0, 1] (None when the PLY has none)."""
  from plyfile import PlyData
  if not path.is_file():
    raise DatasetError(f"point cloud file not found: {path}")
  try:
    vertex = PlyData.read(str(path))["vertex"]
    points = np.stack([vertex[k] for k in ("x", "y", "z")], axis=-1).astype(np.float32)
  except Exception as e:
    raise DatasetError(f"cannot read vertex positions from {path}: {e}") from e
  names = vertex.data.dtype.names
  if not all(k in names for k in ("red", "green", "blue")):
    return points, None
  colors = np.stack([vertex[k] for k in ("red", "green", "blue")], axis=-1).astype(np.float32)
  scale = 65535.0 if vertex["red"].dtype == np.uint16 else 255.0
  return points, colors / scale
