"""Scene loaders: NeRF-Synthetic (Blender), COLMAP, instant-ngp/nerfstudio transforms.json and LLFF
forward-facing scenes (poses_bounds.npy).

Every loader returns a `SceneData` of float32 images in [0, 1] and pinhole `Camera`s in OpenCV axes.
Images with lens distortion are resampled to the pinhole camera of the same intrinsics, images with an
alpha channel are composited on the scene background, and a `downscale` factor shrinks images (area
filter) and intrinsics (`Camera.rescale`) together. Any problem with the files raises one
`DatasetError` naming the file; a loader never returns a partial scene.

Which loader reads a folder: `choose_format` takes the first format, in FORMATS order, whose files are all
there (`format_check`), or checks the one named; `load_scene` logs the choice, why, and what was passed over.
"""
from __future__ import annotations

import os
from pathlib import Path, PurePath
from typing import Callable, NamedTuple, Sequence

from absl import logging

from conceal_jax.data import colmap
from conceal_jax.data.blender import load_blender
from conceal_jax.data.colmap import load_colmap
from conceal_jax.data.frames import image_folders, require_dir
from conceal_jax.data.llff import POSES_FILE, llff_frustum_points, load_llff
from conceal_jax.data.scene import BLACK, WHITE, DatasetError, PathLike, SceneData
from conceal_jax.data.transforms import load_transforms

__all__ = ["AUTO", "BLACK", "DEFAULT_IMAGES", "FOLDER_FORMATS", "FORMATS", "WHITE", "DatasetError", "FormatCheck",
           "FormatChoice", "LOADERS", "SceneData", "choose_format", "detect_format", "format_check",
           "images_folder_problem", "llff_frustum_points", "load_blender", "load_colmap", "load_llff", "load_scene",
           "load_transforms", "log_choice"]

LOADERS: dict[str, Callable[..., SceneData]] = {
    "blender": load_blender, "colmap": load_colmap, "transforms": load_transforms,
    "llff": load_llff}
# Detection order (see choose_format).
FORMATS = ("blender", "colmap", "transforms", "llff")
AUTO = "auto"
DEFAULT_IMAGES = "images"
# Folders of downscaled copies: images_<factor>.
DOWNSCALED_PREFIX = "images_"
# Formats whose images are found by folder (`images`); the others' json names every image file.
FOLDER_FORMATS = ("colmap", "llff")


class FormatCheck(NamedTuple):
  """Whether a folder is a complete capture of one format; reason: what shows it is, or what it lacks; images:
  the images folder it reads (FOLDER_FORMATS)."""
  complete: bool
  reason: str
  images: str = DEFAULT_IMAGES


class FormatChoice(NamedTuple):
  """The format a folder is loaded as. reason: what makes it complete; detected: chosen by detection (not
  named); skipped: (format, what it lacks) for each format detection tried before it; images: the images
  folder a FOLDER_FORMATS loader reads."""
  kind: str
  reason: str
  detected: bool
  skipped: tuple[tuple[str, str], ...] = ()
  images: str = DEFAULT_IMAGES


def images_folder_problem(images: object) -> str | None:
  """What is wrong with `images` as the name of an images folder inside a scene folder (None: nothing)."""
  if not isinstance(images, str) or not images.strip():
    return f"must be a folder name such as 'images' or 'images_4', got {images!r}"
  path = PurePath(images)
  if path.is_absolute() or ".." in path.parts:
    return f"must be a folder inside the scene folder, such as 'images_4', got {images!r}"
  return None


def format_check(root: PathLike, kind: str, images: str = DEFAULT_IMAGES) -> FormatCheck:
  """Whether `root` holds every file the `kind` loader reads, with images in root/`images` for the
  FOLDER_FORMATS; the others' json names each image, so they take only the default `images`."""
  root = Path(root)
  if kind == "blender":
    return _json_check(root, ("transforms_train.json", "transforms_test.json"), images)
  if kind == "transforms":
    return _json_check(root, ("transforms.json",), images)
  if kind == "colmap":
    return _colmap_check(root, images)
  if kind == "llff":
    if not (root / POSES_FILE).is_file():
      return FormatCheck(False, f"no {POSES_FILE}")
    return _folder_check(root, images, POSES_FILE)
  raise DatasetError(f"unknown scene format {kind!r}; known: {', '.join(FORMATS)}")


def _json_check(root: Path, names: tuple[str, ...], images: str) -> FormatCheck:
  missing = [name for name in names if not (root / name).is_file()]
  if missing:
    return FormatCheck(False, "no " + " and no ".join(missing))
  files = " and ".join(names)
  if images != DEFAULT_IMAGES:
    return FormatCheck(False, f"the images are named in {files}, so the images folder {images!r} does not apply")
  return FormatCheck(True, f"the images are named in {files}")


def _colmap_check(root: Path, images: str) -> FormatCheck:
  sparse = colmap.model_dir(root)
  if sparse is None:
    return FormatCheck(False, "no COLMAP model (cameras.bin or .txt in sparse/0 or sparse)")
  where = sparse.relative_to(root).as_posix()
  missing = colmap.missing_model_files(sparse)
  if missing:
    return FormatCheck(False, f"the COLMAP model in {where} has no " + " and no ".join(
        f"{stem}.bin or .txt" for stem in missing))
  return _folder_check(root, images, f"a COLMAP model in {where} (cameras, images, points3D)")


def _folder_check(root: Path, images: str, found: str) -> FormatCheck:
  if (root / images).is_dir():
    return FormatCheck(True, f"{found}, images in {images}/", images)
  copies = sorted((int(name[len(DOWNSCALED_PREFIX):]), name) for name in image_folders(root)
                  if name.startswith(DOWNSCALED_PREFIX) and name[len(DOWNSCALED_PREFIX):].isdigit())
  if images == DEFAULT_IMAGES and copies:  # captures are often shared with their downscaled copies only
    finest = copies[0][1]
    return FormatCheck(True, f"{found}, no {images}/ folder: images in {finest}/, the least downscaled copy "
                       "(data.images names another)", finest)
  return FormatCheck(False, f"{found}, but no images folder {images}/")


def choose_format(root: PathLike, data_format: str = AUTO, images: str = DEFAULT_IMAGES) -> FormatChoice:
  """The format to load `root` as: `data_format` when named (checked to be complete), or for 'auto' the
  first complete one in the order blender, colmap, transforms, llff.

  The order goes from the most specific files to the least: Blender's per-split json before a single
  transforms.json, and COLMAP before LLFF because LLFF captures often keep the COLMAP model their poses_bounds.npy was
  made from, which has the full cameras (per-image focal lengths, distortion) and the SfM points; a
  partial model (no images file, say) is passed over, and the LLFF poses are used. DatasetError, naming
  what each format tried lacks and the folders that do hold images, when none is complete.
  """
  root = Path(root)
  require_dir(root, "scene")
  if data_format != AUTO and data_format not in FORMATS:
    raise DatasetError(f"unknown scene format {data_format!r}; known: {AUTO}, {', '.join(FORMATS)}")
  problem = images_folder_problem(images)
  if problem:
    raise DatasetError(f"images folder {problem}")
  skipped = []
  for kind in FORMATS if data_format == AUTO else (data_format,):
    check = format_check(root, kind, images)
    if check.complete:
      return FormatChoice(kind, check.reason, data_format == AUTO, tuple(skipped), check.images)
    skipped.append((kind, check.reason))
  what = "holds no complete scene format" if data_format == AUTO else f"is not a complete {data_format} scene"
  folders = ", ".join(f"{name}/" for name in image_folders(root)) or "none"
  raise DatasetError(f"{root} {what}: " + "; ".join(f"{kind}: {reason}" for kind, reason in skipped)
                     + f". Folders holding images: {folders}")


def detect_format(root: PathLike, images: str = DEFAULT_IMAGES) -> str:
  """'blender', 'colmap', 'transforms' or 'llff': the first complete format of `root` (`choose_format`)."""
  return choose_format(root, AUTO, images).kind


def log_choice(root: PathLike, choice: FormatChoice) -> None:
  """Logs the formats passed over and why, then the format chosen and why."""
  for kind, reason in choice.skipped:
    logging.info("scene %s: not %s: %s", root, kind, reason)
  how = f"the first complete format of {', '.join(FORMATS)}" if choice.detected else "the format asked for"
  logging.info("scene %s: loading as %s (%s): %s", root, choice.kind, how, choice.reason)


def load_scene(kind_or_path: PathLike, downscale: float = 1, background: Sequence[float] | None = None,
               root: PathLike | None = None, images: str = DEFAULT_IMAGES, data_format: str = AUTO,
               **kwargs) -> SceneData:
  """Loads a scene folder as `data_format` ('auto': `choose_format` detects it), 'demo' (the embedded demo
  scene, generated into the cache on first use), or a format name with `root`. images: the images folder
  for COLMAP and LLFF (images_2, images_4, ... hold downscaled copies). background None: the loader's
  default (white for Blender and the demo, black otherwise); kwargs go to the loader."""
  name = os.fspath(kind_or_path)
  if name == "demo":
    from conceal_jax.data import demo_scene
    root = demo_scene.generate_demo_scene(root or demo_scene.demo_scene_path())
    data_format = "blender" if data_format == AUTO else data_format
  elif name in LOADERS:
    if root is None:
      raise DatasetError(f"load_scene({name!r}) needs a root folder")
    if data_format not in (AUTO, name):
      raise DatasetError(f"load_scene({name!r}) was also given the format {data_format!r}")
    data_format = name
  else:
    root = Path(name)
  choice = choose_format(root, data_format, images)
  log_choice(root, choice)
  if choice.kind in FOLDER_FORMATS:
    kwargs["images_dir"] = choice.images
  if background is not None:
    kwargs["background"] = background
  return LOADERS[choice.kind](root, downscale, **kwargs)
