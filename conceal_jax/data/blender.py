"""NeRF-Synthetic (Blender) scenes: transforms_{split}.json with camera_angle_x and OpenGL poses, RGBA PNGs."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

from conceal_jax.data import frames as frames_lib
from conceal_jax.data.frames import Frame
from conceal_jax.data.scene import WHITE, DatasetError, PathLike, SceneData
from conceal_jax.splat.camera import Camera, fov_to_focal


def load_blender(root: PathLike, downscale: float = 1, background: Sequence[float] = WHITE,
                 splits: tuple[str | Sequence[str], str | Sequence[str]] = ("train", "test")
                 ) -> SceneData:
  """NeRF-Synthetic scene: transforms_{split}.json with camera_angle_x and OpenGL camera-to-world
  poses, RGBA PNGs composited on `background`.

  splits: (train split(s), test split(s)); e.g. (("train", "val"), "test") trains on val as well,
    and an empty test tuple skips the test images.
  """
  root = Path(root)
  frames_lib.require_dir(root, "Blender scene")
  background = frames_lib.check_background(background)
  train_frames, test_frames = ([f for s in _as_tuple(names) for f in _blender_frames(root, s)]
                               for names in splits)
  return frames_lib.load_scene_data(train_frames, test_frames, downscale, background)


def _as_tuple(names: str | Sequence[str]) -> tuple[str, ...]:
  return (names,) if isinstance(names, str) else tuple(names)


def _blender_frames(root: Path, split: str) -> list[Frame]:
  source = root / f"transforms_{split}.json"
  meta = frames_lib.read_json(source)
  try:
    fov_x = float(meta["camera_angle_x"])
    entries = list(meta["frames"])
  except (KeyError, TypeError, ValueError) as e:
    raise DatasetError(f"{source}: needs a numeric camera_angle_x and a frames list ({e!r})") from e
  frames = []
  for index, entry in enumerate(entries):
    if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
      raise DatasetError(f"{source}: frame {index} needs file_path and transform_matrix")
    image_path = frames_lib.frame_image_path(root, entry["file_path"])
    c2w = frames_lib.matrix(entry["transform_matrix"], source, f"frame {index} transform_matrix")
    width, height = frames_lib.image_size(image_path)
    focal = fov_to_focal(fov_x, width)
    camera = Camera.from_opengl_camera_to_world(c2w, focal, focal, width / 2, height / 2, width, height)
    frames.append(Frame(image_path, source, camera, name=image_path.name))
  return frames
