"""Similarity transforms of a Gaussian scene and its cameras (gs/similarity.py): quaternions, the SH band
rotations against a float64 least-squares reference, renders unchanged when scene and camera move
together, and reordering."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax import RenderOptions, render
from conceal_jax.gs import similarity as sim
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import camera_center
from conceal_jax.splat.gaussians import covariance_3d
from tests.helpers import make_camera, random_gaussians

# Rotations that trip naive formulas: identity, 180 degrees about each axis and about a diagonal, near 180.
SPECIAL_ROTATIONS = [np.eye(3)] + [sim.rotation_from_axis_angle(a, np.pi) for a in np.eye(3)] + [
    sim.rotation_from_axis_angle([1.0, 1.0, 1.0], np.pi), sim.rotation_from_axis_angle([0.3, -1.0, 0.2], np.pi - 1e-7)]


def random_similarity(seed: int, scale: float) -> sim.Similarity:
  rng = np.random.default_rng(seed)
  return sim.Similarity(sim.random_rotation(rng), rng.normal(size=3) * 2.0, scale)


def test_quaternion_round_trip_for_random_and_special_rotations():
  rng = np.random.default_rng(0)
  for rotation in SPECIAL_ROTATIONS + [sim.random_rotation(rng) for _ in range(200)]:
    q = sim.matrix_to_quaternion(rotation)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(sim.quaternion_to_matrix(q), rotation, atol=1e-12)


def test_a_batch_of_rotations_reads_as_each_alone():
  rng = np.random.default_rng(2)
  rotations = np.stack(SPECIAL_ROTATIONS + [sim.random_rotation(rng) for _ in range(30)]).reshape(6, 6, 3, 3)
  batched = sim.matrix_to_quaternion(rotations)
  assert batched.shape == (6, 6, 4)
  np.testing.assert_array_equal(batched, [[sim.matrix_to_quaternion(r) for r in row] for row in rotations])


def test_host_quaternion_matches_the_renderers_convention():
  from conceal_jax.splat.gaussians import quaternion_to_rotation
  q = np.random.default_rng(1).normal(size=(20, 4))
  expected = np.stack([sim.quaternion_to_matrix(x) for x in q])
  np.testing.assert_allclose(np.asarray(quaternion_to_rotation(jnp.asarray(q, jnp.float32))), expected, atol=1e-6)


def test_quaternion_product_is_the_rotation_product():
  rng = np.random.default_rng(2)
  a, b = rng.normal(size=4), rng.normal(size=4)
  np.testing.assert_allclose(sim.quaternion_to_matrix(sim.quaternion_multiply(a, b)),
                             sim.quaternion_to_matrix(a) @ sim.quaternion_to_matrix(b), atol=1e-12)


def test_compose_and_inverse():
  a, b = random_similarity(3, 2.5), random_similarity(4, 0.3)
  x = np.random.default_rng(5).normal(size=(10, 3))
  np.testing.assert_allclose(sim.apply_to_points(sim.compose(a, b), x),
                             sim.apply_to_points(a, sim.apply_to_points(b, x)), atol=1e-12)
  np.testing.assert_allclose(sim.apply_to_points(sim.inverse(a), sim.apply_to_points(a, x)), x, atol=1e-12)
  np.testing.assert_allclose(sim.compose(a, sim.inverse(a)).matrix(), np.eye(4), atol=1e-12)
  np.testing.assert_allclose(a.matrix()[:3] @ np.c_[x, np.ones(10)].T, sim.apply_to_points(a, x).T, atol=1e-12)


@pytest.mark.parametrize("rotation, translation, scale, fragment", [
    (np.eye(3)[:2], np.zeros(3), 1.0, "[3, 3] rotation"),
    (np.diag([1.0, 1.0, -1.0]), np.zeros(3), 1.0, "proper rotation"),
    (2 * np.eye(3), np.zeros(3), 1.0, "proper rotation"),
    (np.eye(3), np.array([0.0, np.nan, 0.0]), 1.0, "finite"),
    (np.eye(3), np.zeros(3), 0.0, "scale must be positive"),
    (np.eye(3), np.zeros(3), np.inf, "scale must be positive"),
])
def test_bad_similarity(rotation, translation, scale, fragment):
  with pytest.raises(ValueError, match=fragment.replace("[", r"\[").replace("]", r"\]")):
    sim.Similarity(rotation, translation, scale)


def fitted_band_rotation(rotation: np.ndarray, degree: int, band: int, rng) -> np.ndarray:
  """Independent float64 reference: least-squares fit of M with Y_l(R d) = M Y_l(d) over 500 random
  directions (not the module's fixed Fibonacci directions)."""
  d = rng.normal(size=(500, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  rows = slice(band * band, (band + 1)**2)
  y = np.asarray(sh_lib.sh_basis(jnp.asarray(d), degree))[:, rows]
  y_turned = np.asarray(sh_lib.sh_basis(jnp.asarray(d @ rotation.T), degree))[:, rows]
  m_t, residual, *_ = np.linalg.lstsq(y, y_turned, rcond=None)
  assert np.all(residual < 1e-20)  # the relation is exactly linear within a band
  return m_t.T


def test_sh_band_rotations_match_a_float64_fit(x64):
  rng = np.random.default_rng(6)
  for rotation in SPECIAL_ROTATIONS + [sim.random_rotation(rng) for _ in range(5)]:
    for band, m in enumerate(sim.sh_band_rotations(rotation, 3), start=1):
      assert m.shape == (2 * band + 1, 2 * band + 1)
      np.testing.assert_allclose(m, fitted_band_rotation(rotation, 3, band, rng), atol=1e-12)
      np.testing.assert_allclose(m @ m.T, np.eye(2 * band + 1), atol=1e-12)
  # Band 1 of this basis is (-y, z, -x): its matrix is R itself with the axes relabelled and signed.
  rotation = sim.random_rotation(rng)
  relabel = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
  np.testing.assert_allclose(sim.sh_band_rotations(rotation, 1)[0], relabel @ rotation @ relabel.T, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_rotated_sh_seen_along_rotated_directions_is_the_original_colour(x64, degree):
  rng = np.random.default_rng(7 + degree)
  n = 30
  sh = jnp.asarray(rng.normal(size=(n, (degree + 1)**2, 3)))
  for rotation in SPECIAL_ROTATIONS[1:4] + [sim.random_rotation(rng) for _ in range(3)]:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    before = jnp.einsum("nk,nkc->nc", sh_lib.sh_basis(jnp.asarray(d), degree), sh)
    turned = sim.rotate_sh(sh, rotation)
    after = jnp.einsum("nk,nkc->nc", sh_lib.sh_basis(jnp.asarray(d @ rotation.T), degree), turned)
    np.testing.assert_allclose(np.asarray(after), np.asarray(before), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(turned[:, 0]), np.asarray(sh[:, 0]))  # DC is invariant


def test_rotate_sh_rejects_a_non_square_coefficient_count():
  with pytest.raises(ValueError, match="not a square"):
    sim.rotate_sh(jnp.zeros((2, 5, 3)), np.eye(3))


def test_transformed_gaussians_have_transformed_geometry(x64):
  g = random_gaussians(8, 40, degree=2, dtype=jnp.float64)
  s = random_similarity(9, 3.7)
  moved = sim.transform_gaussians(g, s)
  np.testing.assert_allclose(np.asarray(moved.means), np.asarray(g.means) @ (s.scale * s.rotation).T + s.translation,
                             atol=1e-12)
  expected_cov = s.scale**2 * s.rotation @ np.asarray(covariance_3d(g)) @ s.rotation.T
  np.testing.assert_allclose(np.asarray(covariance_3d(moved)), expected_cov, atol=1e-12)
  np.testing.assert_allclose(np.linalg.norm(moved.quats, axis=1), np.linalg.norm(g.quats, axis=1), rtol=1e-12)
  np.testing.assert_array_equal(np.asarray(moved.opacity_logits), np.asarray(g.opacity_logits))
  assert moved.sh.dtype == jnp.float64 and moved.sh.shape == g.sh.shape


def test_transformed_camera_sees_the_transformed_centre():
  camera, s = make_camera(), random_similarity(10, 0.4)
  moved = sim.transform_camera(camera, s)
  np.testing.assert_allclose(np.asarray(camera_center(moved)),
                             sim.apply_to_points(s, np.asarray(camera_center(camera), np.float64)), atol=1e-5)
  w2c = np.asarray(moved.world_to_camera, np.float64)
  np.testing.assert_allclose(w2c[:3, :3] @ w2c[:3, :3].T, np.eye(3), atol=1e-6)
  assert (moved.width, moved.height, float(moved.fx)) == (camera.width, camera.height, float(camera.fx))


# One program for every render below (same options, scene size and image size): compiled once. The near
# plane is far in front of the scene at every scale tested, so culling is the same before and after.
RENDER_OPTIONS = RenderOptions(with_depth=True, tile_size=8, near=0.01)


def render_scene():
  return random_gaussians(11, 60, degree=3), make_camera(32, 24, eye=(1.0, -3.5, 1.5))


@pytest.mark.parametrize("seed, scale, rotation", [(11, 1.0, None), (12, 0.1, SPECIAL_ROTATIONS[4]),
                                                   (13, 10.0, None), (14, 2.3, SPECIAL_ROTATIONS[2])])
def test_render_of_transformed_scene_from_transformed_camera_is_unchanged(seed, scale, rotation):
  g, camera = render_scene()
  s = random_similarity(seed, scale)
  if rotation is not None:  # 180-degree turns
    s = sim.Similarity(rotation, s.translation, scale)
  before = render(g, camera, RENDER_OPTIONS)
  after = render(sim.transform_gaussians(g, s), sim.transform_camera(camera, s), RENDER_OPTIONS)
  assert float(before.alpha.mean()) > 0.2  # the scene fills a good part of the image
  np.testing.assert_allclose(np.asarray(after.rgb), np.asarray(before.rgb), atol=2e-4)
  np.testing.assert_allclose(np.asarray(after.alpha), np.asarray(before.alpha), atol=2e-4)
  np.testing.assert_allclose(np.asarray(after.depth), scale * np.asarray(before.depth), rtol=1e-4, atol=1e-4 * scale)
  np.testing.assert_array_equal(np.asarray(after.radii), np.asarray(before.radii))


def test_shuffle_reorders_every_field_consistently_and_keeps_the_render():
  g, camera = render_scene()
  shuffled, order = sim.shuffle_gaussians(g, np.random.default_rng(0))
  assert sorted(order.tolist()) == list(range(g.num)) and not np.array_equal(order, np.arange(g.num))
  for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(shuffled)):
    np.testing.assert_array_equal(np.asarray(b), np.asarray(a)[order])
  np.testing.assert_allclose(np.asarray(render(shuffled, camera, RENDER_OPTIONS).rgb),
                             np.asarray(render(g, camera, RENDER_OPTIONS).rgb), atol=1e-6)
  kept = sim.permute_gaussians(g, order[:20])
  assert kept.num == 20
  np.testing.assert_array_equal(np.asarray(kept.means), np.asarray(g.means)[order[:20]])
