"""The key's photometric refinement (conceal.key_refine): the camera step against an independent float64
composition, and a registered key off by a few thousandths of a radian and of the scene's radius brought back onto
the pose that sees a colour-graded copy as the owner's key sees the scene."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import align, key_refine
from conceal_jax.gs import similarity as sim
from conceal_jax.gs.init import gaussians_from_points
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.render import RenderOptions, render
from tests.helpers import make_camera
from tests.test_reveal_alignment import blobs


def rodrigues64(vector: np.ndarray) -> np.ndarray:
  angle = np.linalg.norm(vector)
  x, y, z = vector / angle
  k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
  return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def test_moving_a_camera_in_its_own_frame_matches_a_float64_composition():
  camera = make_camera(16, 16, eye=(0.5, -5.0, 1.5))
  turn, shift = np.array([0.3, -0.2, 0.5]), np.array([0.1, -0.4, 0.25])
  moved = key_refine.moved_in_own_frame(camera, jnp.asarray(turn, jnp.float32), jnp.asarray(shift, jnp.float32))
  step = np.eye(4)
  step[:3, :3], step[:3, 3] = rodrigues64(turn), shift
  expected = step @ np.asarray(camera.world_to_camera, np.float64)
  np.testing.assert_allclose(np.asarray(moved.world_to_camera), expected, atol=2e-6)
  same = key_refine.moved_in_own_frame(camera, jnp.zeros(3), jnp.zeros(3))
  np.testing.assert_allclose(np.asarray(same.world_to_camera), np.asarray(camera.world_to_camera), atol=1e-7)


def pose_error(camera, reference) -> tuple[float, float]:
  """(turn in radians, camera-centre distance) between two cameras' poses."""
  a, b = (np.asarray(c.world_to_camera, np.float64) for c in (camera, reference))
  relative = a[:3, :3] @ b[:3, :3].T
  angle = np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0))
  centre = lambda m: -m[:3, :3].T @ m[:3, 3]
  return float(angle), float(np.linalg.norm(centre(a) - centre(b)))


def filmed_scene(camera, count: int = 300, depth: float = 0.6):
  """blobs with a textured film of `count` small splats `depth` in front of `camera`, filling its view (as a
  carrier film sits before its key): the film's parallax against the scene pins the key's pose."""
  rng = np.random.default_rng(1)
  half = 0.4 * depth  # beyond the view's half-width at that depth (fov 0.7)
  # depths spread a little, as no two of a trained film's splats are level (equal depths would blend in an order
  # that rounding decides)
  in_camera = np.concatenate([rng.uniform(-half, half, (count, 2)), depth + rng.uniform(0, 0.1, (count, 1))], axis=1)
  to_world = np.linalg.inv(np.asarray(camera.world_to_camera, np.float64))
  film = gaussians_from_points(in_camera @ to_world[:3, :3].T + to_world[:3, 3], rng.uniform(size=(count, 3)),
                               sh_degree=1, opacity=0.3)
  return jax.tree.map(lambda a, b: jnp.concatenate([jnp.asarray(a), jnp.asarray(b)]), blobs(1500), film)


def test_a_key_registered_slightly_off_is_refined_onto_the_owners_view_of_a_graded_copy():
  # 64x64 pixels: at 32x32 a splat crossing the 1/255 alpha cut moves the loss about as much as the pose error left
  # to find, so where the search stalled depended on the renderer's float order (3.6 to 5 times closer).
  camera, options = make_camera(64, 64, eye=(0.5, -5.0, 1.5)), RenderOptions()
  owner = filmed_scene(camera)
  similarity = sim.Similarity(sim.rotation_from_axis_angle([0.2, 1.0, -0.4], 2.5), np.array([1.0, 0.5, -2.0]), 0.6)
  suspect = sim.transform_gaussians(owner, similarity)
  # the copy's colours darkened by a fifth (on the black background, every pixel of its render by a fifth)
  suspect = suspect.replace(sh=suspect.sh.at[:, 0, :].set(0.8 * suspect.sh[:, 0, :] - 0.1 / sh_lib.SH_C0))
  exact, exact_options = align.moved_key(camera, options, similarity)
  radius = 0.6 * 2.0
  off = key_refine.moved_in_own_frame(exact, jnp.asarray([2e-3, -1.5e-3, 1e-3]),
                                      jnp.asarray([1.5e-3, -2e-3, 2e-3]) * radius)
  before = pose_error(off, exact)
  refined, refinement = key_refine.refine_key(owner, suspect, camera, options, off, exact_options, radius,
                                              align.fit_tone)
  after = pose_error(refined, exact)
  assert refinement.loss < 1e-3 and refinement.iterations > 0, refinement
  assert after[0] < before[0] / 5 and after[1] < before[1] / 5, (before, after)
  np.testing.assert_allclose(np.asarray(render(suspect, refined, exact_options).rgb) / 0.8,
                             np.asarray(render(owner, camera, options).rgb), atol=2e-3)
  assert refinement.rotation_deg > np.degrees(before[0]) / 2


def test_a_copy_whose_renders_already_agree_keeps_its_registered_key():
  camera, options = make_camera(32, 32, eye=(0.5, -5.0, 1.5)), RenderOptions()
  owner = filmed_scene(camera)
  similarity = sim.Similarity(sim.rotation_from_axis_angle([0.2, 1.0, -0.4], 2.5), np.array([1.0, 0.5, -2.0]), 0.6)
  exact, exact_options = align.moved_key(camera, options, similarity)
  kept, refinement = key_refine.refine_key(owner, sim.transform_gaussians(owner, similarity), camera, options, exact,
                                           exact_options, 1.2)
  assert refinement == key_refine.Refinement(0.0, 0.0, 1.0, 0)
  np.testing.assert_array_equal(np.asarray(kept.world_to_camera), np.asarray(exact.world_to_camera))
