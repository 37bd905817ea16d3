"""The secret check view P_c: the key that, with the decoder, reveals the hidden image.

A training camera by index (the released ConcealGS code uses the second to last), a secret pose sampled
from a seed on the orbit of the training cameras (a view nobody trains or tests on), or (beyond the paper) a
pose looking where no camera of the scene looks, into the space carrier.py's film fills.
Saved as key.json: the camera and what the reveal needs to know (hidden size, decoder width); a run with
further hidden images (mark.extra_hidden) adds their keys, of the same kind, as `extra_keys`. Poses near the
key (leakage, decoys) are near.py's.
"""
from __future__ import annotations

import json
import math
from typing import Sequence

import jax
import numpy as np
from flax import struct

from conceal_jax.core import fileio
from conceal_jax.gs import similarity
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat.camera import Camera, camera_centers, look_at, orbit_eye

KEY_KINDS = ("train_index", "orbit", "unseen")


@struct.dataclass
class Key:
  """The secret keys of a run, stacked [K] (K = 1 + len(mark.extra_hidden)), and what each hides: camera,
  the check view P_c; hidden [K, S, S, 3], the image I it reveals; check_image [K, H, W, 3], what the
  released variant's check-view L1 holds its render to (the training image at a training camera, the
  teacher's render at an orbit pose); teacher_check [K, S, S, 3], the clean teacher's check render at the
  decoder size (L_d^- of the released variant and of identity_on_teacher_check)."""
  camera: Camera
  hidden: jax.Array
  check_image: jax.Array
  teacher_check: jax.Array

  def at(self, number) -> "Key":
    """Key `number` (0: the check view, k: the k-th extra; may be traced) without the leading axis."""
    return jax.tree.map(lambda x: x[number], self)


def stack_keys(cameras, hiddens, check_images, teacher_checks) -> Key:
  """A Key [K] from K cameras and their images."""
  stack = lambda xs: jax.numpy.stack([jax.numpy.asarray(x) for x in xs])
  return Key(camera=camera_lib.stack(list(cameras)), hidden=stack(hiddens), check_image=stack(check_images),
             teacher_check=stack(teacher_checks))


def orbit_target(cameras: Sequence[Camera]) -> np.ndarray:
  """[3] the point closest (least squares) to every camera's optical axis: what the orbit looks at."""
  centers = camera_centers(cameras)
  forward = np.stack([np.asarray(c.world_to_camera, np.float64)[2, :3] for c in cameras])
  projectors = np.eye(3) - forward[:, :, None] * forward[:, None, :]  # onto each axis' normal plane
  return np.linalg.lstsq(projectors.sum(0), np.einsum("vij,vj->i", projectors, centers), rcond=None)[0]


def orbit_up(cameras: Sequence[Camera]) -> np.ndarray:
  """[3] the cameras' mean up direction (each camera's -y), unit length."""
  up = -np.mean([np.asarray(c.world_to_camera, np.float64)[1, :3] for c in cameras], axis=0)
  return up / np.linalg.norm(up)


def looking_at(cameras: Sequence[Camera], eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> Camera:
  """A camera at `eye` looking at `target`, upright along `up`, with the intrinsics of cameras[0]."""
  c = cameras[0]
  return Camera.from_intrinsics(look_at(eye, target, up), float(c.fx), float(c.fy), float(c.cx), float(c.cy),
                                c.width, c.height)


def orbit_camera(cameras: Sequence[Camera], seed: int) -> Camera:
  """A secret camera on the training orbit: same intrinsics as cameras[0], at the median distance from
  the orbit target, elevation drawn within the cameras' elevation range and azimuth uniformly."""
  target, up = orbit_target(cameras), orbit_up(cameras)
  offsets = camera_centers(cameras) - target
  distances = np.linalg.norm(offsets, axis=1)
  elevations = np.arcsin(np.clip(offsets @ up / distances, -1, 1))
  rng = np.random.default_rng(seed)
  elevation = rng.uniform(elevations.min(), elevations.max())
  azimuth = rng.uniform(0.0, 2 * math.pi)
  return looking_at(cameras, orbit_eye(target, float(np.median(distances)), azimuth, elevation, up), target, up)


def unseen_direction(cameras: Sequence[Camera], samples: int = 4096) -> np.ndarray:
  """[3] the unit direction farthest in angle from every camera's viewing direction (of `samples` spread evenly)."""
  forward = np.stack([np.asarray(c.world_to_camera, np.float64)[2, :3] for c in cameras])
  candidates = similarity.fibonacci_sphere(samples)
  return candidates[np.argmin(np.max(candidates @ forward.T, axis=1))]


def camera_distance(cameras: Sequence[Camera]) -> float:
  """The median distance of `cameras` from their orbit target: the unit of an unseen key's offset."""
  return float(np.median(np.linalg.norm(camera_centers(cameras) - orbit_target(cameras), axis=1)))


def unseen_camera(cameras: Sequence[Camera], seed: int, offset: float = 1.0) -> Camera:
  """A secret camera looking where none of `cameras` looks: `offset` camera distances from the orbit target
  along unseen_direction, looking further along it, turned about its axis by an angle drawn from `seed`;
  intrinsics of cameras[0]. What it sees beyond the scene is what carrier.py's film fills."""
  target = orbit_target(cameras)
  direction = unseen_direction(cameras)
  eye = target + offset * camera_distance(cameras) * direction
  helper = np.eye(3)[int(np.argmin(np.abs(direction)))]
  up = rotation_about(direction, np.random.default_rng(seed).uniform(0, 2 * math.pi)) @ np.cross(direction, helper)
  return looking_at(cameras, eye, eye + direction, up)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
  """[3, 3] rotation by `angle` radians about the unit vector `axis` (Rodrigues)."""
  x, y, z = np.asarray(axis, np.float64) / np.linalg.norm(axis)
  k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
  return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def check_camera(cameras: Sequence[Camera], kind: str, index: int, seed: int,
                 offset: float = 1.0) -> tuple[Camera, dict]:
  """The check view and a description of how it was chosen (`offset`: an unseen key's, unseen_camera)."""
  if kind == "train_index":
    if not -len(cameras) <= index < len(cameras):
      raise ValueError(f"mark.key_index {index} is out of range for {len(cameras)} training cameras")
    return cameras[index], dict(kind=kind, index=index % len(cameras))
  if kind == "orbit":
    return orbit_camera(cameras, seed), dict(kind=kind, seed=seed)
  if kind == "unseen":
    return unseen_camera(cameras, seed, offset), dict(kind=kind, seed=seed, offset=offset)
  raise ValueError(f"mark.key_kind must be one of {KEY_KINDS}, got {kind!r}")


def key_cameras(cameras: Sequence[Camera], kind: str, index: int, seed: int, extra: int,
                offset: float = 1.0) -> list[tuple[Camera, dict]]:
  """(camera, description) of the check view and of `extra` further keys of the same kind, one per extra
  hidden image (mark.extra_hidden): the k-th extra (0-based) is training camera index - 1 - k, or the
  orbit pose of seed seed + 1 + k. Neighbouring indices suffice: the training cameras of a capture are
  not ordered by pose (the demo scene draws them at random). ValueError naming mark.extra_hidden if an
  extra index is out of range or two keys are the same pose (a scene with fewer cameras than keys)."""
  keys = [check_camera(cameras, kind, index, seed, offset)]
  for k in range(extra):
    if kind == "train_index" and not -len(cameras) <= index - 1 - k < len(cameras):
      raise ValueError(f"mark.extra_hidden: the key of extra image {k}, training camera mark.key_index - "
                       f"{k + 1} = {index - 1 - k}, is out of range for {len(cameras)} training cameras")
    keys.append(check_camera(cameras, kind, index - 1 - k, seed + 1 + k, offset))
  poses = [np.asarray(camera.world_to_camera) for camera, _ in keys]
  for i in range(len(keys)):
    for j in range(i):
      if np.allclose(poses[i], poses[j]):
        raise ValueError(f"mark.extra_hidden: keys {j} and {i} are the same pose ({keys[i][1]}); each hidden "
                         "image needs its own key")
  return keys


def camera_dict(camera: Camera) -> dict:
  """A camera as key.json stores it (plain floats)."""
  return dict(world_to_camera=np.asarray(camera.world_to_camera, np.float64).tolist(), fx=float(camera.fx),
              fy=float(camera.fy), cx=float(camera.cx), cy=float(camera.cy), width=camera.width, height=camera.height)


def camera_from_dict(c: dict) -> Camera:
  return Camera.from_intrinsics(np.asarray(c["world_to_camera"], np.float64).reshape(4, 4), c["fx"], c["fy"],
                                c["cx"], c["cy"], int(c["width"]), int(c["height"]))


def save_key(path: str, camera: Camera, info: dict, extra_keys: Sequence[tuple[Camera, dict]] = ()) -> None:
  """key.json: `info` with the check `camera`; `extra_keys` (camera, description) of further hidden images
  as the list `extra_keys`, each its description with its camera (absent without any)."""
  extra = dict(extra_keys=[dict(more, camera=camera_dict(c)) for c, more in extra_keys]) if extra_keys else {}
  fileio.write_json(path, dict(info, camera=camera_dict(camera), **extra))


def load_key(path: str, number: int = 0) -> tuple[Camera, dict]:
  """(camera of key `number`, the rest of key.json): 0 the check view, k >= 1 the k-th of its `extra_keys`.
  ValueError naming the file if it is missing or malformed, or has no key `number`."""
  try:
    with open(path) as f:
      info = json.load(f)
    c = info.pop("camera")
    if number:
      extra = info.get("extra_keys", [])
      if not 0 < number <= len(extra):
        raise ValueError(f"no key number {number}: it holds keys 0 to {len(extra)}")
      c = extra[number - 1]["camera"]
    camera = camera_from_dict(c)
  except (OSError, ValueError, KeyError, TypeError) as error:
    raise ValueError(f"cannot read key {path}: {error}") from error
  return camera, info
