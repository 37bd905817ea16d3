"""Scene loaders: NeRF-Synthetic (Blender), COLMAP and instant-ngp/nerfstudio transforms.json.

Every loader returns a `SceneData` of float32 images in [0, 1] and pinhole `Camera`s in OpenCV axes.
Images with lens distortion are resampled to the pinhole camera of the same intrinsics, images with an
alpha channel are composited on the scene background, and a `downscale` factor shrinks images (area
filter) and intrinsics (`Camera.rescale`) together. Any problem with the files raises one
`DatasetError` naming the file; a loader never returns a partial scene.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from conceal_jax.splat.camera import Camera, camera_centers, fov_to_focal

PathLike = str | os.PathLike
Color = tuple[float, float, float]

WHITE: Color = (1.0, 1.0, 1.0)
BLACK: Color = (0.0, 0.0, 0.0)

# Image decoding releases the GIL, so a few threads hide most of the file and PNG/JPEG cost.
_MAX_IO_THREADS = 8


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


@dataclasses.dataclass(frozen=True)
class Distortion:
  """OpenCV lens distortion of normalised image coordinates (COLMAP FULL_OPENCV is the general case).

  k1, k2, k3 / k4, k5, k6: rational radial numerator / denominator polynomials in r^2, r^4, r^6.
  p1, p2: tangential (decentring) coefficients.
  """
  k1: float = 0.0
  k2: float = 0.0
  k3: float = 0.0
  k4: float = 0.0
  k5: float = 0.0
  k6: float = 0.0
  p1: float = 0.0
  p2: float = 0.0

  @property
  def is_identity(self) -> bool:
    return not any(dataclasses.astuple(self))


def camera_extent(cameras: Sequence[Camera]) -> float:
  """1.1 x max distance of a camera centre from the mean centre (0 for fewer than two cameras)."""
  if not cameras:
    return 0.0
  centers = camera_centers(cameras)
  return float(1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max())


# ---------------------------------------------------------------------------------------------------
# Images


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


# ---------------------------------------------------------------------------------------------------
# Lens distortion


def distort(x: np.ndarray, y: np.ndarray, d: Distortion) -> tuple[np.ndarray, np.ndarray]:
  """Distorted normalised coordinates of undistorted ones (x, y: same shape), OpenCV's model."""
  r2 = x * x + y * y
  radial = (1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))) / (1.0 + r2 * (d.k4 + r2 * (d.k5 + r2 * d.k6)))
  xy = x * y
  xd = x * radial + 2.0 * d.p1 * xy + d.p2 * (r2 + 2.0 * x * x)
  yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * xy
  return xd, yd


def undistortion_sampler(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                         distortion: Distortion) -> Callable[[np.ndarray], np.ndarray]:
  """A function mapping a distorted [height, width, C] image to the pinhole image of the same
  intrinsics, sampling bilinearly (edge pixels repeat where the pinhole view sees past the lens)."""
  # float32 keeps sub-pixel precision up to ~10^4 pixels and halves the cost of large images.
  u = (np.arange(width, dtype=np.float32) + 0.5 - np.float32(cx)) / np.float32(fx)
  v = (np.arange(height, dtype=np.float32) + 0.5 - np.float32(cy)) / np.float32(fy)
  xd, yd = distort(u[None, :], v[:, None], distortion)
  # Pixel (i, j) is centred at (j + 0.5, i + 0.5), so array coordinates are image coordinates - 0.5.
  return bilinear_sampler(yd * np.float32(fy) + np.float32(cy - 0.5),
                          xd * np.float32(fx) + np.float32(cx - 0.5), height, width)


def bilinear_sampler(rows: np.ndarray, cols: np.ndarray, height: int,
                     width: int) -> Callable[[np.ndarray], np.ndarray]:
  """Precomputed bilinear lookup at fractional array coordinates (rows, cols: [h, w]) of a
  [height, width, C] image, clamped to its edges; returns image -> [h, w, C]."""
  def axis(coords, size):
    coords = np.clip(coords, 0.0, size - 1.0)
    lo = np.minimum(np.floor(coords), max(size - 2, 0)).astype(np.int32)
    frac = (coords - lo).astype(np.float32).reshape(-1, 1)
    return lo, np.minimum(lo + 1, size - 1), frac

  shape = np.broadcast_shapes(np.shape(rows), np.shape(cols))
  r0, r1, wr = axis(np.broadcast_to(rows, shape), height)
  c0, c1, wc = axis(np.broadcast_to(cols, shape), width)
  flat = [(r * width + c).reshape(-1) for r in (r0, r1) for c in (c0, c1)]
  weights = [(1 - wr) * (1 - wc), (1 - wr) * wc, wr * (1 - wc), wr * wc]

  def sample(image: np.ndarray) -> np.ndarray:
    if image.shape[:2] != (height, width):
      raise ValueError(f"sampler built for {width}x{height}, got image {image.shape}")
    pixels = image.reshape(height * width, -1)
    out = sum(w * np.take(pixels, i, axis=0) for w, i in zip(weights, flat))
    return out.reshape(shape + image.shape[2:]).astype(np.float32)

  return sample


# ---------------------------------------------------------------------------------------------------
# Shared loading steps


@dataclasses.dataclass(frozen=True)
class _Frame:
  """One image to load: its file, where its description came from, and its full-size camera."""
  image_path: Path
  source: Path  # the file that describes the camera, for error messages
  camera: Camera
  distortion: Distortion = Distortion()
  name: str = ""


def _load_frames(frames: Sequence[_Frame], downscale: float,
                 background: Sequence[float]) -> tuple[list[np.ndarray], list[Camera]]:
  """Reads, checks, downscales and undistorts every frame; [h, w, 3] images and their cameras.

  Undistortion runs after the area downscale, at the output resolution: its cost then shrinks with
  the image, and the lens warp is smooth enough that the order barely changes the pixels.
  """
  _check_downscale(downscale)
  cameras = [f.camera if downscale == 1 else f.camera.rescale(downscale) for f in frames]
  samplers: dict[tuple, Callable] = {}

  def load(frame: _Frame, camera: Camera) -> np.ndarray:
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


def _check_downscale(downscale: float) -> None:
  if not (isinstance(downscale, (int, float)) and math.isfinite(downscale) and downscale > 0):
    raise DatasetError(f"downscale must be a positive number, got {downscale!r}")


def _check_background(background: Sequence[float]) -> Color:
  values = tuple(float(v) for v in background)
  if len(values) != 3:
    raise DatasetError(f"background must be 3 floats (RGB), got {background!r}")
  return values  # type: ignore[return-value]


def _require_dir(path: Path, what: str) -> None:
  if not path.is_dir():
    raise DatasetError(f"{what} folder not found: {path}")


def _read_json(path: Path) -> Any:
  if not path.is_file():
    raise DatasetError(f"file not found: {path}")
  try:
    return json.loads(path.read_text())
  except (OSError, ValueError) as e:
    raise DatasetError(f"cannot parse {path}: {e}") from e


def _frame_image_path(root: Path, file_path: str) -> Path:
  """NeRF-style file_path, relative to the json folder; PNG when it has no extension."""
  path = root / file_path
  png = path.with_name(path.name + ".png")
  return png if not path.suffix or (not path.is_file() and png.is_file()) else path


def _matrix(value: Any, source: Path, what: str) -> np.ndarray:
  try:
    matrix = np.asarray(value, np.float64)
  except (TypeError, ValueError) as e:
    raise DatasetError(f"{source}: {what} is not a numeric matrix") from e
  if matrix.shape not in ((3, 4), (4, 4)) or not np.isfinite(matrix).all():
    raise DatasetError(f"{source}: {what} must be a finite [3, 4] or [4, 4] matrix, got {matrix.shape}")
  return matrix


def _image_size(path: Path) -> tuple[int, int]:
  """(width, height) read from the file header only."""
  from PIL import Image
  if not path.is_file():
    raise DatasetError(f"image file not found: {path}")
  try:
    with Image.open(path) as image:
      return image.size
  except Exception as e:
    raise DatasetError(f"cannot read image {path}: {e}") from e


# ---------------------------------------------------------------------------------------------------
# NeRF-Synthetic / Blender


def load_blender(root: PathLike, downscale: float = 1, background: Sequence[float] = WHITE,
                 splits: tuple[str | Sequence[str], str | Sequence[str]] = ("train", "test")
                 ) -> SceneData:
  """NeRF-Synthetic scene: transforms_{split}.json with camera_angle_x and OpenGL camera-to-world
  poses, RGBA PNGs composited on `background`.

  splits: (train split(s), test split(s)); e.g. (("train", "val"), "test") trains on val as well,
    and an empty test tuple skips the test images.
  """
  root = Path(root)
  _require_dir(root, "Blender scene")
  background = _check_background(background)
  train_frames, test_frames = ([f for s in _as_tuple(names) for f in _blender_frames(root, s)]
                               for names in splits)
  train_images, train_cameras = _load_frames(train_frames, downscale, background)
  test_images, test_cameras = _load_frames(test_frames, downscale, background)
  return SceneData(train_images, test_images, train_cameras, test_cameras, None, None, background,
                   [f.name for f in train_frames], [f.name for f in test_frames])


def _as_tuple(names: str | Sequence[str]) -> tuple[str, ...]:
  return (names,) if isinstance(names, str) else tuple(names)


def _blender_frames(root: Path, split: str) -> list[_Frame]:
  source = root / f"transforms_{split}.json"
  meta = _read_json(source)
  try:
    fov_x = float(meta["camera_angle_x"])
    entries = list(meta["frames"])
  except (KeyError, TypeError, ValueError) as e:
    raise DatasetError(f"{source}: needs a numeric camera_angle_x and a frames list ({e!r})") from e
  frames = []
  for index, entry in enumerate(entries):
    if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
      raise DatasetError(f"{source}: frame {index} needs file_path and transform_matrix")
    image_path = _frame_image_path(root, entry["file_path"])
    c2w = _matrix(entry["transform_matrix"], source, f"frame {index} transform_matrix")
    width, height = _image_size(image_path)
    focal = fov_to_focal(fov_x, width)
    camera = Camera.from_opengl_camera_to_world(c2w, focal, focal, width / 2, height / 2, width, height)
    frames.append(_Frame(image_path, source, camera, name=image_path.name))
  return frames


# ---------------------------------------------------------------------------------------------------
# COLMAP

# Parameter layout of the supported COLMAP camera models: the pinhole part, then distortion names.
_COLMAP_MODELS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), ()),
    "PINHOLE": (("fx", "fy", "cx", "cy"), ()),
    "SIMPLE_RADIAL": (("f", "cx", "cy"), ("k1",)),
    "RADIAL": (("f", "cx", "cy"), ("k1", "k2")),
    "OPENCV": (("fx", "fy", "cx", "cy"), ("k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (("fx", "fy", "cx", "cy"), ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}


def load_colmap(root: PathLike, downscale: float = 1, background: Sequence[float] = BLACK,
                images_dir: str = "images", test_every: int = 8) -> SceneData:
  """COLMAP scene: root/sparse/0 (or root/sparse) binary or text model, images in root/images_dir.

  Images sorted by name; every `test_every`-th (index % test_every == 0) is a test image, as 3D-GS
  (0 puts every image in training). Distorted cameras are resampled to pinhole.
  """
  root = Path(root)
  _require_dir(root, "COLMAP scene")
  background = _check_background(background)
  sparse = _colmap_sparse_dir(root)
  _require_dir(root / images_dir, "COLMAP images")
  reconstruction = _read_colmap(sparse)
  cameras_file = _colmap_file(sparse, "cameras")
  frames = sorted((_colmap_frame(root / images_dir, cameras_file, image,
                                 reconstruction.cameras[image.camera_id])
                   for image in reconstruction.images.values()), key=lambda f: f.name)
  if not frames:
    raise DatasetError(f"COLMAP model {_colmap_file(sparse, 'images')} has no registered images")
  is_test = [test_every > 0 and i % test_every == 0 for i in range(len(frames))]
  train_frames = [f for f, t in zip(frames, is_test) if not t]
  test_frames = [f for f, t in zip(frames, is_test) if t]
  train_images, train_cameras = _load_frames(train_frames, downscale, background)
  test_images, test_cameras = _load_frames(test_frames, downscale, background)
  points, colors = _colmap_points(reconstruction)
  return SceneData(train_images, test_images, train_cameras, test_cameras, points, colors, background,
                   [f.name for f in train_frames], [f.name for f in test_frames])


def _colmap_sparse_dir(root: Path) -> Path:
  for folder in (root / "sparse" / "0", root / "sparse"):
    if any((folder / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
      return folder
  raise DatasetError(f"no COLMAP model (cameras.bin or cameras.txt) in {root / 'sparse' / '0'} "
                     f"or {root / 'sparse'}")


def _colmap_file(sparse: Path, stem: str) -> Path:
  binary = sparse / f"{stem}.bin"
  return binary if binary.is_file() else sparse / f"{stem}.txt"


def _read_colmap(sparse: Path):
  import pycolmap
  for stem in ("cameras", "images", "points3D"):
    if not _colmap_file(sparse, stem).is_file():
      raise DatasetError(f"COLMAP model file not found: {sparse / stem}.bin (or .txt)")
  try:
    return pycolmap.Reconstruction(str(sparse))
  except Exception as e:  # pycolmap reports malformed files as ValueError or RuntimeError
    raise DatasetError(f"cannot read COLMAP model in {sparse}: {e}") from e


def _colmap_frame(images_dir: Path, cameras_file: Path, image, colmap_camera) -> _Frame:
  pose = image.cam_from_world
  pose = pose() if callable(pose) else pose  # a method from pycolmap 3.12, a property before
  w2c = np.eye(4)
  w2c[:3] = np.asarray(pose.matrix(), np.float64)
  camera, distortion = _colmap_camera(colmap_camera, image.camera_id, cameras_file, w2c)
  return _Frame(images_dir / image.name, cameras_file, camera, distortion, image.name)


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


# ---------------------------------------------------------------------------------------------------
# instant-ngp / nerfstudio transforms.json

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
  _require_dir(root, "transforms.json scene")
  background = _check_background(background)
  source = root / filename
  meta = _read_json(source)
  entries = meta.get("frames") if isinstance(meta, dict) else None
  if not isinstance(entries, list) or not entries:
    raise DatasetError(f"{source}: needs a non-empty frames list")
  frames = sorted((_transforms_frame(root, source, meta, entry, i) for i, entry in enumerate(entries)),
                  key=lambda f: str(f.image_path))
  is_test = [test_every > 0 and i % test_every == 0 for i in range(len(frames))]
  train_frames = [f for f, t in zip(frames, is_test) if not t]
  test_frames = [f for f, t in zip(frames, is_test) if t]
  train_images, train_cameras = _load_frames(train_frames, downscale, background)
  test_images, test_cameras = _load_frames(test_frames, downscale, background)
  points, colors = (_read_ply_points(root / meta["ply_file_path"]) if meta.get("ply_file_path")
                    else (None, None))
  return SceneData(train_images, test_images, train_cameras, test_cameras, points, colors, background,
                   [f.name for f in train_frames], [f.name for f in test_frames])


def _transforms_frame(root: Path, source: Path, meta: dict, entry: Any, index: int) -> _Frame:
  if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
    raise DatasetError(f"{source}: frame {index} needs file_path and transform_matrix")
  lookup = lambda key, default=None: entry.get(key, meta.get(key, default))
  model = lookup("camera_model", "OPENCV")
  if model not in _TRANSFORMS_MODELS:
    raise DatasetError(f"{source}: frame {index} has unsupported camera_model {model}; supported: "
                       f"{', '.join(_TRANSFORMS_MODELS)}")
  image_path = _frame_image_path(root, entry["file_path"])
  c2w = _matrix(entry["transform_matrix"], source, f"frame {index} transform_matrix")
  try:
    if lookup("w") is not None and lookup("h") is not None:
      width, height = int(lookup("w")), int(lookup("h"))
    else:
      width, height = _image_size(image_path)
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
  return _Frame(image_path, source, camera, Distortion(**coefficients), image_path.name)


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


# ---------------------------------------------------------------------------------------------------
# Dispatch

LOADERS: dict[str, Callable[..., SceneData]] = {
    "blender": load_blender, "colmap": load_colmap, "transforms": load_transforms}


def detect_format(root: PathLike) -> str:
  """'blender', 'colmap' or 'transforms', from the files in `root`."""
  root = Path(root)
  _require_dir(root, "scene")
  if (root / "transforms_train.json").is_file():
    return "blender"
  if any((root / s / f"cameras{ext}").is_file() for s in ("sparse/0", "sparse") for ext in (".bin", ".txt")):
    return "colmap"
  if (root / "transforms.json").is_file():
    return "transforms"
  raise DatasetError(f"cannot tell the format of {root}: expected transforms_train.json (Blender), "
                     f"sparse/0/cameras.bin or .txt (COLMAP) or transforms.json")


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
