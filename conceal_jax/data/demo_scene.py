"""The embedded demo scene: a small NeRF-Synthetic-style dataset the project renders itself.

A textured sphere and a textured box stand on a textured ground disc; textures are photographs that
ship with scikit-image, so nothing is downloaded. Images are ray cast analytically with numpy (no
Gaussian splatting involved, so the scene is an independent ground truth), supersampled for soft
alpha at silhouettes, lit by a fixed directional light (view-independent shading) and written as RGBA
PNGs with a transparent background, in Blender format (transforms_{train,val,test}.json,
camera_angle_x), loadable with `datasets.load_blender`. Cameras orbit the upper hemisphere looking at
the origin (world z is up).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from conceal_jax.core import fileio
from conceal_jax.splat.camera import look_at, opengl_camera_to_world, orbit_eye

# Bumped whenever the generated images change, so that stale caches are regenerated.
FORMAT_VERSION = 1
PARAMS_FILE = "demo_scene.json"

SPHERE_CENTER = np.array([0.45, -0.35, 0.45])
SPHERE_RADIUS = 0.45
BOX_CENTER = np.array([-0.4, 0.35, 0.35])
BOX_HALF_SIZE = np.array([0.35, 0.3, 0.35])
BOX_YAW = 0.5  # radians about world z
DISC_RADIUS = 1.25  # ground disc in the plane z = 0, centred on the origin

CAMERA_DISTANCE = 4.0
CAMERA_ANGLE_X = 0.75  # radians; frames the whole disc from every orbit position
ELEVATION_RANGE = (math.radians(15.0), math.radians(65.0))
SUPERSAMPLING = 3  # rays per pixel along each axis; alpha is the covered fraction of the 3x3 rays
_LIGHT = np.array([0.4, 0.3, 1.0]) / np.linalg.norm([0.4, 0.3, 1.0])
_AMBIENT = 0.35


def demo_scene_path(cache_dir: str | os.PathLike | None = None) -> Path:
  """Cache folder of the demo scene: cache_dir, else $CONCEAL_JAX_CACHE, else ~/.cache/conceal_jax;
  plus /demo_scene."""
  root = cache_dir or os.environ.get("CONCEAL_JAX_CACHE") or Path.home() / ".cache" / "conceal_jax"
  return Path(root).expanduser() / "demo_scene"


def generate_demo_scene(out_dir: str | os.PathLike, num_train: int = 50, num_test: int = 10,
                        size: int = 128, seed: int = 0) -> Path:
  """Writes the demo scene to out_dir (reused when already complete with the same parameters).

  The scene is built in a temporary folder next to out_dir and renamed into place, so a reader sees
  either nothing, an older complete scene, or the new complete scene. Returns out_dir.
  """
  out_dir = Path(out_dir)
  params = _params(num_train, num_test, size, seed)
  if _is_complete(out_dir, params):
    return out_dir
  out_dir.parent.mkdir(parents=True, exist_ok=True)
  tmp = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}-tmp-"))
  try:
    _write_scene(tmp, params)
    _move_into_place(tmp, out_dir, params)
  finally:
    shutil.rmtree(tmp, ignore_errors=True)
  return out_dir


def _params(num_train: int, num_test: int, size: int, seed: int) -> dict:
  if num_train < 1 or num_test < 1 or size < 1:
    raise ValueError(f"need num_train, num_test, size >= 1, got {num_train}, {num_test}, {size}")
  return {"num_train": int(num_train), "num_test": int(num_test), "size": int(size),
          "seed": int(seed), "version": FORMAT_VERSION}


def _is_complete(folder: Path, params: dict) -> bool:
  """The params file is written last, so its presence with equal content means a complete scene."""
  try:
    return json.loads((folder / PARAMS_FILE).read_text()) == params
  except (OSError, ValueError):
    return False


def _move_into_place(tmp: Path, out_dir: Path, params: dict) -> None:
  if out_dir.exists():
    if _is_complete(out_dir, params):  # a concurrent generator finished first: keep its copy
      return
    stale = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}-stale-"))
    os.replace(out_dir, stale / "old")  # rename cannot replace a non-empty folder: move it aside
    shutil.rmtree(stale, ignore_errors=True)
  try:
    os.replace(tmp, out_dir)
  except OSError:
    if not _is_complete(out_dir, params):
      raise


def _write_scene(folder: Path, params: dict) -> None:
  textures = _textures()
  rng = np.random.default_rng(params["seed"])
  size = params["size"]
  for split, count in (("train", params["num_train"]), ("test", params["num_test"])):
    frames = []
    for index, eye in enumerate(orbit_positions(rng, count)):
      w2c = look_at(eye, (0.0, 0.0, 0.0))
      rgba = render_rgba(w2c, size, textures)
      fileio.write_image(folder / split / f"r_{index}.png", rgba)
      frames.append({"file_path": f"./{split}/r_{index}",
                     "transform_matrix": opengl_camera_to_world(w2c).tolist()})
    meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
    fileio.write_json(folder / f"transforms_{split}.json", meta)
    if split == "test":
      fileio.write_json(folder / "transforms_val.json", meta)
  fileio.write_json(folder / PARAMS_FILE, params)


def orbit_positions(rng: np.random.Generator, count: int) -> np.ndarray:
  """[count, 3] camera positions at CAMERA_DISTANCE, uniform in area over the elevation band."""
  azimuth = rng.uniform(0.0, 2.0 * math.pi, count)
  low, high = (math.sin(e) for e in ELEVATION_RANGE)
  elevation = np.arcsin(rng.uniform(low, high, count))
  return orbit_eye((0.0, 0.0, 0.0), CAMERA_DISTANCE, azimuth, elevation)


def _textures() -> dict[str, np.ndarray]:
  """[H, W, 3] float32 textures; scikit-image bundles these photographs in its wheel."""
  from skimage import data
  as_float = lambda image: np.asarray(image, np.float32)[..., :3] / 255.0
  return {"sphere": as_float(data.coffee()), "disc": as_float(data.astronaut()),
          "box_x": as_float(data.chelsea()), "box_y": as_float(data.rocket()),
          "box_z": as_float(data.coffee())[::-1]}


# ---------------------------------------------------------------------------------------------------
# Ray casting


def render_rgba(world_to_camera: np.ndarray, size: int, textures: dict[str, np.ndarray]) -> np.ndarray:
  """[size, size, 4] straight-alpha RGBA of the scene seen by a square camera of CAMERA_ANGLE_X."""
  origin, directions = camera_rays(world_to_camera, size, SUPERSAMPLING)
  hit, color = cast_rays(origin, directions, textures)
  coverage = _pixel_mean(hit.astype(np.float32)[:, None], size, SUPERSAMPLING)[..., 0]
  premultiplied = _pixel_mean(color, size, SUPERSAMPLING)  # missed rays have colour 0
  rgb = premultiplied / np.maximum(coverage, 1e-6)[..., None]  # straight alpha, as PNG stores it
  return np.concatenate([rgb, coverage[..., None]], axis=-1).astype(np.float32)


def _pixel_mean(values: np.ndarray, size: int, s: int) -> np.ndarray:
  """Mean of [size*s * size*s, C] ray values over each pixel's s x s rays: [size, size, C]."""
  columns = values.reshape(size * s * size, s, -1).sum(axis=1)
  return columns.reshape(size, s, size, -1).sum(axis=1) / (s * s)


def camera_rays(world_to_camera: np.ndarray, size: int, supersampling: int) -> tuple[np.ndarray, np.ndarray]:
  """Camera centre [3] and unit world directions [3, size*s * size*s] (component-major: every
  per-ray operation then runs on contiguous rows) of s x s rays per pixel, ordered by (row,
  sub-row, column, sub-column); pixel (i, j) spans [j, j+1] x [i, i+1]."""
  focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
  offsets = (np.arange(size * supersampling, dtype=np.float32) + 0.5) / supersampling
  x = ((offsets - 0.5 * size) / focal)[None, :]  # camera x per column
  y = ((offsets - 0.5 * size) / focal)[:, None]  # camera y per row
  rotation = world_to_camera[:3, :3].astype(np.float32)
  # World direction R^T (x, y, 1), one world component at a time.
  directions = np.stack([(rotation[0, k] * x + rotation[1, k] * y + rotation[2, k]).reshape(-1)
                         for k in range(3)])
  directions /= np.sqrt((directions * directions).sum(axis=0))
  origin = -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]
  return origin, directions


def cast_rays(origin: np.ndarray, directions: np.ndarray,
              textures: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
  """Nearest hit of each ray (directions: [3, N] unit): hit [N] bool and shaded colour [N, 3]."""
  surfaces = ((_sphere_depth, _sphere_surface), (_box_depth, _box_surface),
              (_disc_depth, _disc_surface))
  depth = np.stack([depth_of(origin, directions) for depth_of, _ in surfaces])  # [P, N], inf: miss
  nearest = np.argmin(depth, axis=0)
  hit = np.isfinite(depth.min(axis=0))
  color = np.zeros((directions.shape[1], 3), np.float32)
  # Textures are looked up only where a primitive is the visible one: lookups dominate the cost.
  for index, (_, surface_of) in enumerate(surfaces):
    chosen = np.flatnonzero(hit & (nearest == index))
    points = origin + depth[index, chosen, None] * directions[:, chosen].T
    albedo, normal = surface_of(points, textures)
    shade = _AMBIENT + (1.0 - _AMBIENT) * np.clip(normal @ _LIGHT, 0.0, 1.0)
    color[chosen] = albedo * shade[:, None]
  return hit, color


def _sphere_depth(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
  """[N] distance to the sphere along unit directions [3, N], inf on a miss."""
  oc = origin - SPHERE_CENTER
  b = oc[0] * directions[0] + oc[1] * directions[1] + oc[2] * directions[2]
  discriminant = b * b - np.float32(oc @ oc - SPHERE_RADIUS ** 2)
  with np.errstate(invalid="ignore"):
    t = -b - np.sqrt(discriminant)  # the camera is outside: the first root is the visible one
  return np.where((discriminant >= 0) & (t > 0), t, np.inf)


def _sphere_surface(points: np.ndarray, textures) -> tuple[np.ndarray, np.ndarray]:
  """Albedo [K, 3] and normal [K, 3] at sphere points [K, 3]; equirectangular photograph."""
  normal = (points - SPHERE_CENTER) / SPHERE_RADIUS
  u = 0.5 + np.arctan2(normal[:, 1], normal[:, 0]) / (2 * math.pi)
  v = np.arccos(np.clip(normal[:, 2], -1.0, 1.0)) / math.pi
  return sample_texture(textures["sphere"], u, v), normal


def _box_rotation() -> np.ndarray:
  c, s = math.cos(BOX_YAW), math.sin(BOX_YAW)
  return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # box-local to world


def _box_depth(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
  """[N] distance to the box (slab test in box coordinates), inf on a miss."""
  rotation = _box_rotation()
  local_origin = rotation.T @ (origin - BOX_CENTER)
  count = directions.shape[1]
  t_near, t_far = np.full(count, -np.inf, np.float32), np.full(count, np.inf, np.float32)
  with np.errstate(divide="ignore", invalid="ignore"):
    for axis in range(3):
      local_dir = sum(np.float32(rotation[k, axis]) * directions[k] for k in range(3))
      inverse = 1.0 / local_dir
      t1 = np.float32(-BOX_HALF_SIZE[axis] - local_origin[axis]) * inverse
      t2 = np.float32(BOX_HALF_SIZE[axis] - local_origin[axis]) * inverse
      np.maximum(t_near, np.minimum(t1, t2), out=t_near)
      np.minimum(t_far, np.maximum(t1, t2), out=t_far)
  return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def _box_surface(points: np.ndarray, textures) -> tuple[np.ndarray, np.ndarray]:
  """Albedo and normal at box points [K, 3]; one photograph per face axis."""
  rotation = _box_rotation()
  local = (points - BOX_CENTER) @ rotation / BOX_HALF_SIZE  # in [-1, 1]^3, +-1 on the face hit
  axis = np.argmax(np.abs(local), axis=1)
  rows = np.arange(len(points))
  local_normal = np.zeros_like(local)
  local_normal[rows, axis] = np.sign(local[rows, axis])
  albedo = np.zeros_like(local, dtype=np.float32)
  for face_axis, name in enumerate(("box_x", "box_y", "box_z")):
    on_face = axis == face_axis
    u_axis, v_axis = [a for a in range(3) if a != face_axis]
    # Image rows run downwards, so v = 1 at the bottom of a face keeps the photographs upright.
    albedo[on_face] = sample_texture(textures[name], 0.5 + 0.5 * local[on_face, u_axis],
                                     0.5 - 0.5 * local[on_face, v_axis])
  return albedo, local_normal @ rotation.T


def _disc_depth(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
  """[N] distance to the ground disc z = 0, inf on a miss."""
  with np.errstate(divide="ignore", invalid="ignore"):
    t = np.float32(-origin[2]) / directions[2]
    t = np.where(t > 0, t, np.inf)
    x, y = origin[0] + t * directions[0], origin[1] + t * directions[1]
  return np.where(x * x + y * y <= DISC_RADIUS ** 2, t, np.inf)


def _disc_surface(points: np.ndarray, textures) -> tuple[np.ndarray, np.ndarray]:
  """Albedo and normal (+z: cameras are above) at disc points [K, 3]; photograph mapped planarly."""
  u = 0.5 + 0.5 * points[:, 0] / DISC_RADIUS
  v = 0.5 - 0.5 * points[:, 1] / DISC_RADIUS
  normal = np.broadcast_to(np.array([0.0, 0.0, 1.0]), points.shape)
  return sample_texture(textures["disc"], u, v), normal


def sample_texture(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
  """Bilinear lookup of texture [H, W, 3] at u (across) and v (down) in [0, 1] (clamped): [N, 3]."""
  height, width = texture.shape[:2]
  flat = texture.reshape(-1, texture.shape[-1])
  cols = np.clip(u, 0.0, 1.0) * (width - 1)
  rows = np.clip(v, 0.0, 1.0) * (height - 1)
  c0 = np.minimum(cols.astype(np.int64), width - 2)
  r0 = np.minimum(rows.astype(np.int64), height - 2)
  wc, wr = (cols - c0).astype(np.float32)[:, None], (rows - r0).astype(np.float32)[:, None]
  i00 = r0 * width + c0
  top = np.take(flat, i00, axis=0) * (1 - wc) + np.take(flat, i00 + 1, axis=0) * wc
  bottom = np.take(flat, i00 + width, axis=0) * (1 - wc) + np.take(flat, i00 + width + 1, axis=0) * wc
  return top * (1 - wr) + bottom * wr
