"""The key tolerance radius (conceal.leakage.tolerance_*; issue 39's trade of the leakage radius for robustness):
poses within the radius of a key, the key turned about the point it looks at as a camera on its orbit sees the
scene, reveal the key's image too, and the training views within it are not held to F's identity, so that a copy
trained on views that come near the key, not onto it, can carry the mark."""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from conceal_jax.conceal.near import orbit_turn
from conceal_jax.splat.camera import Camera, camera_centers


TOLERANCE_SEED_BASE = 3_000_000  # seeds of the tolerance poses, apart from leakage's, the decoys' and the nulls'


@dataclasses.dataclass(frozen=True)
class Tolerance:
  """The key tolerance radius (conceal.leakage.tolerance_*): `views` poses within `deg` of each key that reveal its
  image, one of them the step's check view with probability `fraction`."""
  deg: float
  views: int
  fraction: float


def from_config(leakage) -> Tolerance | None:
  """conceal.leakage.tolerance_* checked: all three set (a radius in (0, 90) degrees, a positive number of poses, a
  share of the steps in (0, 1)) or none (None)."""
  deg, views, fraction = leakage.tolerance_deg, leakage.tolerance_views, leakage.tolerance_fraction
  if not deg and not views and not fraction:
    return None
  if not (0 < deg < 90 and isinstance(views, int) and views > 0 and 0 < fraction < 1):
    raise ValueError("conceal.leakage.tolerance_deg, tolerance_views and tolerance_fraction are set together: a "
                     "radius in (0, 90) degrees, a positive number of poses and a share of the steps in (0, 1), got "
                     f"{deg}, {views} and {fraction}")
  return Tolerance(float(deg), views, float(fraction))


def orbit_turns(camera: Camera, length: float, angles_deg: Sequence[float], seed: int = 0) -> list[Camera]:
  """near.orbit_turn by each of `angles_deg`, the k-th about an axis drawn from seed and k."""
  return [orbit_turn(camera, length, angle, np.random.default_rng([TOLERANCE_SEED_BASE + seed, k]))
          for k, angle in enumerate(angles_deg)]


def tolerance_cameras(camera: Camera, length: float, count: int, radius_deg: float, seed: int = 0) -> list[Camera]:
  """`count` poses within `radius_deg` of the key (conceal.leakage.tolerance_*): orbit_turns by angles drawn
  uniformly over the cap of that radius, which reveal the key's image too."""
  u = np.random.default_rng(TOLERANCE_SEED_BASE + seed).uniform(size=count)
  angles = np.degrees(np.arccos(1.0 - u * (1.0 - math.cos(math.radians(radius_deg)))))
  return orbit_turns(camera, length, angles, seed)


def angle_from_key_deg(camera: Camera, key: Camera, length: float) -> float:
  """How far (degrees) `camera` stands from the key, in the turns of tolerance_cameras about the point `length`
  ahead on the key's optical axis: the larger of the turn that moves the key's centre as far as `camera`'s is from
  it (2 asin(d / 2 length), d the distance between the centres) and the angle of the rotation between their
  orientations. A pose turned by t degrees about that point is t away; a camera at the key's place turned or rolled,
  or moved towards the scene, is as far as its turn or its move."""
  w2c, other = np.asarray(key.world_to_camera, np.float64), np.asarray(camera.world_to_camera, np.float64)
  moved = np.linalg.norm(camera_centers([camera])[0] - camera_centers([key])[0]) / (2.0 * length)
  turned = float(np.clip((np.trace(w2c[:3, :3] @ other[:3, :3].T) - 1.0) / 2.0, -1.0, 1.0))
  return math.degrees(max(2.0 * math.asin(min(moved, 1.0)), math.acos(turned)))


def check_views(tolerance: Tolerance | None, key_seed: int, keys: list, hiddens: list) -> tuple[list, list]:
  """The cameras a run's check view is drawn from and their hidden images: the keys `keys` [(camera, info)] with
  `hiddens`, then the poses within the key tolerance radius of each (tolerance_cameras, from the key's own seed
  key_seed + k), key by key, tolerance.views each, hiding their key's image."""
  cameras, images = [camera for camera, _ in keys], list(hiddens)
  for k, ((key, info), hidden) in enumerate(zip(keys, hiddens)):
    if tolerance is not None:
      cameras += tolerance_cameras(key, info["near_length"], tolerance.views, tolerance.deg, key_seed + k)
      images += [hidden] * tolerance.views
  return cameras, images


def held_to_identity(tolerance: Tolerance | None, keys: list, normal_cameras: list) -> np.ndarray | None:
  """bool [V + D]: the normal views whose student render L_d^- holds to F's identity: those beyond the key
  tolerance radius of every key (None: all, without a radius)."""
  if tolerance is None:
    return None
  return np.array([all(angle_from_key_deg(camera, key, info["near_length"]) > tolerance.deg for key, info in keys)
                   for camera in normal_cameras])
