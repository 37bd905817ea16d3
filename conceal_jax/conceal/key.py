"""The secret check view P_c: the key that, with the decoder, reveals the hidden image.

A training camera by index (the released ConcealGS code uses the second to last), a secret pose sampled
from a seed on the orbit of the training cameras (a view nobody trains or tests on), or (beyond the paper) a
pose looking where no camera of the scene looks, into the space carrier.py's film fills.
Saved as key.json: the camera and what the reveal needs to know (hidden size, decoder width); a run with
further hidden images (mark.extra_hidden) adds their keys, of the same kind, as `extra_keys`.

"Near the key" (the poses the leakage figure scores, and the decoys the decoder is trained to the identity at)
means the key turned by degrees about its centre, or moved by a fraction of near_length: the depth of the
scene as the key sees it, so that a fraction means about the same pixel motion on an object-centred orbit
and on a forward-facing capture.
"""
from __future__ import annotations

import json
import math
from typing import Sequence

import jax
import numpy as np
from absl import logging
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


def orbit_camera(cameras: Sequence[Camera], seed: int) -> Camera:
  """A secret camera on the training orbit: same intrinsics as cameras[0], at the median distance from
  the orbit target, elevation drawn within the cameras' elevation range and azimuth uniformly."""
  target = orbit_target(cameras)
  offsets = camera_centers(cameras) - target
  up = -np.mean([np.asarray(c.world_to_camera, np.float64)[1, :3] for c in cameras], axis=0)  # -y is up
  up /= np.linalg.norm(up)
  distances = np.linalg.norm(offsets, axis=1)
  elevations = np.arcsin(np.clip(offsets @ up / distances, -1, 1))
  rng = np.random.default_rng(seed)
  elevation = rng.uniform(elevations.min(), elevations.max())
  azimuth = rng.uniform(0.0, 2 * math.pi)
  eye = orbit_eye(target, float(np.median(distances)), azimuth, elevation, up)
  c = cameras[0]
  return Camera.from_intrinsics(look_at(eye, target, up), float(c.fx), float(c.fy), float(c.cx), float(c.cy),
                                c.width, c.height)


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
  c = cameras[0]
  return Camera.from_intrinsics(look_at(eye, eye + direction, up), float(c.fx), float(c.fy), float(c.cx),
                                float(c.cy), c.width, c.height)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
  """[3, 3] rotation by `angle` radians about the unit vector `axis` (Rodrigues)."""
  x, y, z = np.asarray(axis, np.float64) / np.linalg.norm(axis)
  k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
  return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def nearby_camera(camera: Camera, translation: float, rotation_deg: float, seed: int) -> Camera:
  """`camera` moved by `translation` (world units) in a random direction and turned by `rotation_deg`
  about a random axis through its centre; same intrinsics. A pose an attacker might guess near the key."""
  rng = np.random.default_rng(seed)
  direction, axis = rng.normal(size=3), rng.normal(size=3)
  w2c = np.asarray(camera.world_to_camera, np.float64)
  rotation = rotation_about(axis, math.radians(rotation_deg)) @ w2c[:3, :3]  # turned in the camera frame
  center = camera_centers([camera])[0] + translation * direction / np.linalg.norm(direction)
  moved = np.eye(4)
  moved[:3, :3], moved[:3, 3] = rotation, -rotation @ center
  return Camera.from_intrinsics(moved, float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                                camera.width, camera.height)


# A key sees the teacher when the Gaussians in its image hold at least this share of the teacher's opacity;
# below it (an 'unseen' key looks where no camera looks) its near-key length falls back to camera_distance.
MIN_SEEN_SHARE = 0.01


def view_depths(gaussians, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """(depth [N], opacity [N], inside [N] bool) of `gaussians`' centres seen from `camera`: camera-space z, the
  peak opacity, and whether the centre lies in front of the camera and projects into its image."""
  means = np.asarray(gaussians.means, np.float64)
  w2c = np.asarray(camera.world_to_camera, np.float64)
  local = means @ w2c[:3, :3].T + w2c[:3, 3]
  depth = local[:, 2]
  with np.errstate(divide="ignore", invalid="ignore"):
    u = float(camera.fx) * local[:, 0] / depth + float(camera.cx)
    v = float(camera.fy) * local[:, 1] / depth + float(camera.cy)
  inside = (depth > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
  opacity = 1.0 / (1.0 + np.exp(-np.asarray(gaussians.opacity_logits, np.float64)))
  return depth, opacity, inside


def near_length(teacher, camera: Camera, cameras: Sequence[Camera]) -> tuple[float, str]:
  """(length, what it is) that near-key translations are fractions of, for the key `camera` of a scene whose
  clean 3D-GS is `teacher` and whose training cameras are `cameras`.

  The length is the depth of the scene as the key sees it: the opacity-weighted median camera-space depth of
  the teacher's Gaussian centres that project into the key's image ('view_depth'). A sideways move by a
  fraction f of it shifts what lies at that depth by f * fx pixels, whatever the capture's geometry: on an
  object-centred orbit it is about the camera's distance to the object (close to the 3D-GS extent, the
  spread of the camera centres, which the length replaces), while on a forward-facing capture, whose cameras
  spread little against the depth they look at, the extent is far smaller and its fractions barely change
  the view. A key that sees under MIN_SEEN_SHARE of the teacher's opacity (the 'unseen' key, whose image the
  carrier film fills at a multiple of the camera distance) takes camera_distance(cameras) instead
  ('camera_distance'), with a logged note. The student is not used: a carrier film in the key's view would
  make the length depend on the mark."""
  depth, opacity, inside = view_depths(teacher, camera)
  total = float(opacity.sum())
  seen = float(opacity[inside].sum())
  if total <= 0 or seen < MIN_SEEN_SHARE * total:
    distance = camera_distance(cameras)
    logging.info("near-key length: the key sees %.2f%% of the teacher's opacity (under %g%%); using the camera "
                 "distance %.4g", 100 * seen / max(total, 1e-30), 100 * MIN_SEEN_SHARE, distance)
    return distance, "camera_distance"
  order = np.argsort(depth[inside])
  depths, weights = depth[inside][order], opacity[inside][order]
  cumulative = np.cumsum(weights)
  return float(depths[np.searchsorted(cumulative, 0.5 * cumulative[-1])]), "view_depth"


def nearby_cameras(camera: Camera, length: float, translations: Sequence[float], rotations_deg: Sequence[float],
                   directions: int) -> list[tuple[str, float, Camera]]:
  """(kind, value, camera) for `directions` random cameras per translation (a fraction of the key's near-key
  `length`, near_length; not turned) and per rotation (degrees about the camera centre, which mean the same
  on any geometry; not moved); a zero value gives the key itself once."""
  poses = [("translation", t) for t in translations] + [("rotation", r) for r in rotations_deg]
  return [(kind, value, nearby_camera(camera, value * length if kind == "translation" else 0.0,
                                      value if kind == "rotation" else 0.0, seed))
          for kind, value in poses for seed in range(directions if value else 1)]


# Decoy directions come from seeds far from the 0 .. directions-1 that `nearby_cameras` scores leakage
# with, so the near-key leakage is measured at poses no decoy trained on.
DECOY_SEED_BASE = 1_000_000


def decoy_cameras(camera: Camera, length: float, count: int, translation: Sequence[float],
                  rotation_deg: Sequence[float], seed: int = 0) -> list[Camera]:
  """`count` cameras near the key, for training the decoder to stay the identity there (conceal.leakage.decoy_*).

  Each is moved by a fraction of the key's near-key `length` (near_length, the unit the leakage figure's
  translations use) drawn uniformly from `translation` (lo, hi), turned by degrees drawn from `rotation_deg`
  (lo, hi), or both, the three kinds in turn; directions are random.
  """
  cameras = []
  for k in range(count):
    rng = np.random.default_rng([seed, k])
    kind = k % 3  # 0: moved, 1: turned, 2: both
    moved = rng.uniform(*translation) * length if kind in (0, 2) else 0.0
    turned = rng.uniform(*rotation_deg) if kind in (1, 2) else 0.0
    cameras.append(nearby_camera(camera, moved, turned, DECOY_SEED_BASE + seed * count + k))
  return cameras


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
