"""Scene loaders: NeRF-Synthetic (Blender), COLMAP, instant-ngp/nerfstudio transforms.json and LLFF
forward-facing scenes (poses_bounds.npy).

Every loader returns a `SceneData` of float32 images in [0, 1] and pinhole `Camera`s in OpenCV axes.
Images with lens distortion are resampled to the pinhole camera of the same intrinsics, images with an
alpha channel are composited on the scene background, and a `downscale` factor shrinks images (area
filter) and intrinsics (`Camera.rescale`) together. Any problem with the files raises one
`DatasetError` naming the file; a loader never returns a partial scene.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

from conceal_jax.data.blender import load_blender
from conceal_jax.data.colmap import load_colmap
from conceal_jax.data.frames import require_dir
from conceal_jax.data.llff import llff_bounds_box, load_llff
from conceal_jax.data.scene import BLACK, WHITE, DatasetError, PathLike, SceneData
from conceal_jax.data.transforms import load_transforms

__all__ = ["BLACK", "WHITE", "DatasetError", "LOADERS", "SceneData", "detect_format", "llff_bounds_box",
           "load_blender", "load_colmap", "load_llff", "load_scene", "load_transforms"]

LOADERS: dict[str, Callable[..., SceneData]] = {
    "blender": load_blender, "colmap": load_colmap, "transforms": load_transforms,
    "llff": load_llff}


def detect_format(root: PathLike) -> str:
  """'blender', 'colmap', 'transforms' or 'llff', from the files in `root`.

  LLFF comes last: LLFF captures often keep the COLMAP model their poses_bounds.npy was made from,
  and that model has the full cameras (per-image focal lengths, distortion) and the SfM points.
  """
  root = Path(root)
  require_dir(root, "scene")
  if (root / "transforms_train.json").is_file():
    return "blender"
  if any((root / s / f"cameras{ext}").is_file() for s in ("sparse/0", "sparse") for ext in (".bin", ".txt")):
    return "colmap"
  if (root / "transforms.json").is_file():
    return "transforms"
  if (root / "poses_bounds.npy").is_file():
    return "llff"
  raise DatasetError(f"cannot tell the format of {root}: expected transforms_train.json (Blender), "
                     f"sparse/0/cameras.bin or .txt (COLMAP), transforms.json or poses_bounds.npy (LLFF)")


def load_scene(kind_or_path: PathLike, downscale: float = 1, background: Sequence[float] | None = None,
               root: PathLike | None = None, **kwargs) -> SceneData:
  """Loads a scene by format name with `root`, by folder (format detected), or 'demo' (the embedded
  demo scene, generated into the cache on first use). background None: the loader's default (white
  for Blender and the demo, black otherwise); kwargs go to the loader."""
  kind = os.fspath(kind_or_path)
  if kind == "demo":
    from conceal_jax.data import demo_scene
    kind, root = "blender", demo_scene.generate_demo_scene(root or demo_scene.demo_scene_path())
  elif kind in LOADERS:
    if root is None:
      raise DatasetError(f"load_scene({kind!r}) needs a root folder")
  else:
    root = Path(kind)
    kind = detect_format(root)
  if background is not None:
    kwargs["background"] = background
  return LOADERS[kind](root, downscale, **kwargs)
