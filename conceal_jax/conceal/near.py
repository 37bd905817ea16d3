"""Poses near the key: what "near" means for a scene, the poses the leakage figure scores, and the decoys.

"Near the key" (the poses the leakage figure scores, and the decoys the decoder is trained to the identity at)
means the key turned by degrees about its centre, or moved by a fraction of near_length: the depth of the
scene as the key sees it, so that a fraction means about the same pixel motion on an object-centred orbit
and on a forward-facing capture. The leakage figure scores the moves along and turns about the key's own axes
(KEY_AXES: forward along the optical axis is the move the image changes least under) and random ones.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from absl import logging

from conceal_jax.conceal.key import camera_distance, rotation_about
from conceal_jax.splat.camera import Camera, camera_centers


# The key's own axes both ways, in its camera frame (x right, y down, z the optical axis): the leakage figure moves
# and turns the key along / about each besides its random directions, since a move along the optical axis (a zoom)
# changes the image least, and a few random directions seldom come close to it.
KEY_AXES = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0))


def nearby_camera(camera: Camera, translation: float, rotation_deg: float, seed: int,
                  key_axis: Sequence[float] | None = None) -> Camera:
  """`camera` moved by `translation` (world units) in a random direction and turned by `rotation_deg`
  about a random axis through its centre, both drawn from `seed`; with `key_axis` (a unit vector in the camera's
  frame, one of KEY_AXES) moved along it and turned about it instead. Same intrinsics. A pose an attacker might
  guess near the key."""
  rng = np.random.default_rng(seed)
  direction, axis = rng.normal(size=3), rng.normal(size=3)  # world frame; camera frame
  w2c = np.asarray(camera.world_to_camera, np.float64)
  if key_axis is not None:
    axis = np.asarray(key_axis, np.float64)
    direction = w2c[:3, :3].T @ axis
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
  """(kind, value, camera) per translation (a fraction of the key's near-key `length`, near_length; not turned)
  and per rotation (degrees about the camera centre, which mean the same on any geometry; not moved): the six
  along / about the key's own axes (KEY_AXES), then `directions` random ones; a zero value gives the key itself
  once."""
  poses = [("translation", t) for t in translations] + [("rotation", r) for r in rotations_deg]
  ways = [dict(seed=0, key_axis=axis) for axis in KEY_AXES] + [dict(seed=seed) for seed in range(directions)]
  return [(kind, value, nearby_camera(camera, value * length if kind == "translation" else 0.0,
                                      value if kind == "rotation" else 0.0, **way))
          for kind, value in poses for way in (ways if value else ways[:1])]


# Decoy directions come from seeds far from the 0 .. directions-1 that `nearby_cameras` scores leakage
# with, so the near-key leakage is measured at poses no decoy trained on.
DECOY_SEED_BASE = 1_000_000


def orbited_camera(camera: Camera, pivot: np.ndarray, axis: np.ndarray, angle: float) -> Camera:
  """`camera` turned rigidly by `angle` radians about the world `axis` through the world point `pivot` [3]: where
  it stands moves about the pivot and it turns with it, looking at the pivot as before. Same intrinsics."""
  rotation = rotation_about(axis, angle)
  w2c = np.asarray(camera.world_to_camera, np.float64)
  center = pivot + rotation @ (camera_centers([camera])[0] - pivot)
  moved = np.eye(4)
  moved[:3, :3] = w2c[:3, :3] @ rotation.T
  moved[:3, 3] = -moved[:3, :3] @ center
  return Camera.from_intrinsics(moved, float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                                camera.width, camera.height)


def orbit_turn(camera: Camera, length: float, angle_deg: float, rng: np.random.Generator) -> Camera:
  """The key turned by `angle_deg` about the point `length` ahead on its optical axis (near_length: the scene's
  depth as the key sees it), about an axis across its optical axis drawn from `rng`: the pose a camera on the key's
  orbit takes that far from it, which sees what the key sees at its centre almost unmoved."""
  forward = np.asarray(camera.world_to_camera, np.float64)[2, :3]
  pivot = camera_centers([camera])[0] + length * forward
  axis = np.cross(forward, rng.normal(size=3))
  return orbited_camera(camera, pivot, axis / np.linalg.norm(axis), math.radians(angle_deg))


def decoy_cameras(camera: Camera, length: float, count: int, translation: Sequence[float],
                  rotation_deg: Sequence[float], seed: int = 0, key_axes: bool = False,
                  orbit_turns: bool = False) -> list[Camera]:
  """`count` cameras near the key, for training the decoder to stay the identity there (conceal.leakage.decoy_*).

  Each is moved by a fraction of the key's near-key `length` (near_length, the unit the leakage figure's
  translations use) drawn uniformly from `translation` (lo, hi), turned by degrees drawn from `rotation_deg`
  (lo, hi), or both, the three kinds in turn; directions are random, except with `key_axes`, where the decoys
  that are only moved go along, and those only turned turn about, the key's own axes in turn (KEY_AXES: a move
  along the optical axis and a roll about it among them, the poses a decoder trained on random directions reveals
  its image at). With `orbit_turns` those both moved and turned are orbit turns instead (orbit_turn, by the
  degrees drawn): the key turned about the point its depth ahead, the other pose that barely moves its image.
  """
  cameras = []
  for k in range(count):
    rng = np.random.default_rng([seed, k])
    kind = k % 3  # 0: moved, 1: turned, 2: both
    moved = rng.uniform(*translation) * length if kind in (0, 2) else 0.0
    turned = rng.uniform(*rotation_deg) if kind in (1, 2) else 0.0
    axis = KEY_AXES[(k // 3) % len(KEY_AXES)] if key_axes and kind in (0, 1) else None
    pose_seed = DECOY_SEED_BASE + seed * count + k
    if orbit_turns and kind == 2:
      cameras.append(orbit_turn(camera, length, turned, np.random.default_rng(pose_seed)))
    else:
      cameras.append(nearby_camera(camera, moved, turned, pose_seed, key_axis=axis))
  return cameras


def keys_decoys(keys: list, count: int, translation: Sequence[float], rotation_deg: Sequence[float], seed: int,
                key_axes: bool = False, orbit_turns: bool = False) -> list[Camera]:
  """decoy_cameras around each key of `keys` [(camera, info)] in turn, at its near_length, from its own seed
  seed + k: `count` per key."""
  return [decoy for k, (camera, info) in enumerate(keys)
          for decoy in decoy_cameras(camera, info["near_length"], count, translation, rotation_deg, seed + k, key_axes,
                                     orbit_turns)]
