"""COLMAP scenes: a sparse model (binary or text, read with pycolmap) and its images, at full size or as a
downscaled copy (images_2, images_4, ...); every 8th image is held out, as 3D-GS does."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from conceal_jax.data import frames as frames_lib
from conceal_jax.data.distortion import Distortion
from conceal_jax.data.frames import Frame
from conceal_jax.data.scene import BLACK, DatasetError, PathLike, SceneData
from conceal_jax.splat.camera import Camera


# Parameter layout of the supported COLMAP camera models: the pinhole part, then distortion names.
_COLMAP_MODELS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), ()),
    "PINHOLE": (("fx", "fy", "cx", "cy"), ()),
    "SIMPLE_RADIAL": (("f", "cx", "cy"), ("k1",)),
    "RADIAL": (("f", "cx", "cy"), ("k1", "k2")),
    "OPENCV": (("fx", "fy", "cx", "cy"), ("k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (("fx", "fy", "cx", "cy"), ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}
# The files of a model, each as .bin or .txt; pycolmap reads a model only when all three are there.
MODEL_FILES = ("cameras", "images", "points3D")


def load_colmap(root: PathLike, downscale: float = 1, background: Sequence[float] = BLACK,
                images_dir: str = "images", test_every: int = 8) -> SceneData:
  """COLMAP scene: root/sparse/0 (or root/sparse) binary or text model, images in root/images_dir.

  images_dir may hold downscaled copies (Inria 3D-GS's convert.py writes images_2, _4, _8): each camera
  is resized to its image's actual size (`frames.downscaled_copy_size`). Images sorted by name; every
  `test_every`-th (index % test_every == 0) is a test image, as 3D-GS (0 puts every image in training).
  Distorted cameras are resampled to pinhole.
  """
  root = Path(root)
  frames_lib.require_dir(root, "COLMAP scene")
  background = frames_lib.check_background(background)
  sparse = model_dir(root)
  if sparse is None:
    raise DatasetError(f"no COLMAP model (cameras.bin or cameras.txt) in {root / 'sparse' / '0'} "
                       f"or {root / 'sparse'}")
  frames_lib.require_dir(root / images_dir, "COLMAP images")
  reconstruction = _read_colmap(sparse)
  cameras_file = _colmap_file(sparse, "cameras")
  frames = sorted((_colmap_frame(root / images_dir, cameras_file, image,
                                 reconstruction.cameras[image.camera_id])
                   for image in reconstruction.images.values()), key=lambda f: f.name)
  if not frames:
    raise DatasetError(f"COLMAP model {_colmap_file(sparse, 'images')} has no registered images")
  points, colors = _colmap_points(reconstruction)
  return frames_lib.load_scene_data(*frames_lib.hold_out_every(frames, test_every), downscale, background,
                                    points, colors)


def model_dir(root: Path) -> Path | None:
  """The model folder: root/sparse/0, else root/sparse, whichever first holds cameras.bin or .txt (None:
  neither)."""
  for folder in (root / "sparse" / "0", root / "sparse"):
    if _colmap_file(folder, "cameras").is_file():
      return folder
  return None


def missing_model_files(sparse: Path) -> list[str]:
  """The MODEL_FILES stems that `sparse` has neither as .bin nor as .txt."""
  return [stem for stem in MODEL_FILES if not _colmap_file(sparse, stem).is_file()]


def _colmap_file(sparse: Path, stem: str) -> Path:
  binary = sparse / f"{stem}.bin"
  return binary if binary.is_file() else sparse / f"{stem}.txt"


def _read_colmap(sparse: Path):
  import pycolmap
  missing = missing_model_files(sparse)
  if missing:
    raise DatasetError(f"COLMAP model file not found: {sparse / missing[0]}.bin (or .txt)")
  try:
    return pycolmap.Reconstruction(str(sparse))
  except Exception as e:  # pycolmap reports malformed files as ValueError or RuntimeError
    raise DatasetError(f"cannot read COLMAP model in {sparse}: {e}") from e


def _colmap_frame(images_dir: Path, cameras_file: Path, image, colmap_camera) -> Frame:
  pose = image.cam_from_world
  pose = pose() if callable(pose) else pose  # a method from pycolmap 3.12, a property before
  w2c = np.eye(4)
  w2c[:3] = np.asarray(pose.matrix(), np.float64)
  camera, distortion = _colmap_camera(colmap_camera, image.camera_id, cameras_file, w2c)
  path = images_dir / image.name
  size = frames_lib.downscaled_copy_size(path, (camera.width, camera.height),
                                         f"camera {image.camera_id} in {cameras_file}")
  # Lens distortion is in normalised image coordinates, so it holds for the resized camera unchanged.
  return Frame(path, cameras_file, camera.resized(*size), distortion, image.name)


def _colmap_camera(colmap_camera, camera_id: int, source: Path,
                   w2c: np.ndarray) -> tuple[Camera, Distortion]:
  model = colmap_camera.model.name
  if model not in _COLMAP_MODELS:
    raise DatasetError(f"camera {camera_id} in {source} has unsupported model {model}; supported: "
                       f"{', '.join(_COLMAP_MODELS)}")
  pinhole_names, distortion_names = _COLMAP_MODELS[model]
  params = [float(p) for p in colmap_camera.params]
  pinhole = dict(zip(pinhole_names, params))
  fx, fy = (pinhole["f"], pinhole["f"]) if "f" in pinhole else (pinhole["fx"], pinhole["fy"])
  camera = Camera.from_intrinsics(w2c, fx, fy, pinhole["cx"], pinhole["cy"], colmap_camera.width,
                                  colmap_camera.height)
  distortion = Distortion(**dict(zip(distortion_names, params[len(pinhole_names):])))
  return camera, distortion


def _colmap_points(reconstruction) -> tuple[np.ndarray | None, np.ndarray | None]:
  """SfM points [M, 3] and colours [M, 3] in [0, 1], in point-id order; None when there are none."""
  ids = sorted(reconstruction.points3D)
  if not ids:
    return None, None
  points = np.stack([reconstruction.points3D[i].xyz for i in ids]).astype(np.float32)
  colors = np.stack([reconstruction.points3D[i].color for i in ids]).astype(np.float32) / 255.0
  return points, colors
