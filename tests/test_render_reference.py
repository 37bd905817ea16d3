"""The renderer against the independent float64 reference: values and gradients."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax import RenderOptions
from conceal_jax import render
from conceal_jax.splat import composite
from tests.helpers import make_camera, random_gaussians, reference


@pytest.mark.parametrize("seed,degree,antialiased,background,size", [
    (0, 0, False, (0.0, 0.0, 0.0), (32, 24)),
    (1, 3, False, (1.0, 1.0, 1.0), (37, 29)),   # not a multiple of the tile size
    (2, 3, True, (0.2, 0.5, 0.9), (40, 16)),
    (3, 1, False, (0.0, 0.0, 0.0), (21, 21)),
])
def test_exact_mode_matches_reference(seed, degree, antialiased, background, size):
  g = random_gaussians(seed, 40, degree=degree)
  cam = make_camera(*size)
  options = RenderOptions(sh_degree=degree, background=background, antialiased=antialiased,
                          max_per_tile=None, with_depth=True)
  out = render(g, cam, options)
  rgb, alpha, depth, ambiguous = reference(g, cam, options)
  assert not ambiguous.any()
  assert out.rgb.shape == (size[1], size[0], 3)
  np.testing.assert_allclose(out.rgb, rgb, atol=1e-5, rtol=0)
  np.testing.assert_allclose(out.alpha, alpha, atol=1e-5, rtol=0)
  assert np.max(alpha) > 0.5, "scene must actually cover pixels"
  covered = alpha > 1e-2  # expected depth is z-weighted by coverage; compare where it is meaningful
  np.testing.assert_allclose(np.asarray(out.depth)[covered], depth[covered], rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("tile_size", [8, 16])
def test_truncated_mode_matches_truncated_reference(tile_size):
  g = random_gaussians(5, 60, degree=2)
  cam = make_camera(32, 32)
  options = RenderOptions(max_per_tile=5, tile_size=tile_size, background=(0.3, 0.3, 0.3))
  out = render(g, cam, options)
  rgb, _, _, _ = reference(g, cam, options)
  np.testing.assert_allclose(out.rgb, rgb, atol=1e-5, rtol=0)
  assert int(out.num_overflow_tiles) > 0
  exact, _, _, _ = reference(g, cam, RenderOptions(max_per_tile=None, tile_size=tile_size,
                                                background=(0.3, 0.3, 0.3)))
  assert np.max(np.abs(exact - rgb)) > 1e-3, "truncation to 5 per tile should change this scene"


def _reference_loss(params, weights, cam, options):
  means, log_scales, quats, opacity_logits, sh = params
  from tests.reference import render_reference
  rgb, alpha, _, _ = render_reference(means, log_scales, quats, opacity_logits, sh, cam.world_to_camera,
                                   cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
                                   background=options.background, antialiased=options.antialiased,
                                   tile_size=options.tile_size)
  return float(np.sum(rgb * weights) + np.sum(alpha * weights[..., 0]))


@pytest.mark.parametrize("n,antialiased", [(1, False), (2, True), (3, False)])
def test_gradients_match_central_differences(x64, n, antialiased):
  g = random_gaussians(10 + n, n, degree=3, spread=0.25, log_scale=(-1.4, -0.9), dtype=jnp.float64)
  g = g.replace(opacity_logits=jnp.clip(g.opacity_logits, -0.5, 1.5))
  cam = make_camera(8, 8, fov=0.8, dtype=jnp.float64)
  options = RenderOptions(max_per_tile=None, background=(0.1, 0.2, 0.3), antialiased=antialiased, tile_size=4)
  weights = np.random.default_rng(n).uniform(-1, 1, size=(8, 8, 3))

  def loss(g):
    out = render(g, cam, options)
    return jnp.sum(out.rgb * weights) + jnp.sum(out.alpha * weights[..., 0])

  grads = jax.grad(loss)(g)
  leaves = [np.asarray(x, np.float64) for x in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)]
  grad_leaves = [grads.means, grads.log_scales, grads.quats, grads.opacity_logits, grads.sh]
  h = 1e-6
  for k, (leaf, grad) in enumerate(zip(leaves, grad_leaves)):
    fd = np.zeros_like(leaf)
    for idx in np.ndindex(leaf.shape):
      plus, minus = [list(map(np.copy, leaves)) for _ in range(2)]
      plus[k][idx] += h
      minus[k][idx] -= h
      fd[idx] = (_reference_loss(plus, weights, cam, options) - _reference_loss(minus, weights, cam, options)) / (2 * h)
    assert np.max(np.abs(fd)) > 1e-3, f"leaf {k}: the scene must depend on these parameters"
    np.testing.assert_allclose(np.asarray(grad), fd, rtol=1e-3, atol=1e-3 * np.max(np.abs(fd)))


@pytest.mark.parametrize("tile_size", [4, 16])
def test_splats_beside_the_image_report_radius_zero_and_render_nothing(tile_size):
  """A splat in front of the camera whose 3-sigma square touches no tile reports radius 0, as the 3D-GS
  rasterizer does (densification reads radii as visibility and screen size); the image is the same with and
  without it, and splats on the image keep their radii."""
  camera = make_camera(32, 24)
  scene = random_gaussians(3, 20, degree=1)
  w2c = np.asarray(camera.world_to_camera, np.float64)
  beside = w2c[:3, :3].T @ (np.array([6.0, 0.0, 4.0]) - w2c[:3, 3])  # 6 units right of the axis at depth 4
  lone = random_gaussians(4, 1, degree=1).replace(means=jnp.asarray(beside[None], jnp.float32),
                                                 log_scales=jnp.full((1, 3), -2.3))
  joined = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), scene, lone)
  options = RenderOptions(tile_size=tile_size)
  alone, together = render(scene, camera, options), render(joined, camera, options)
  assert int(together.radii[-1]) == 0
  np.testing.assert_array_equal(np.asarray(together.radii[:-1]), np.asarray(alone.radii))
  assert int(jnp.sum(alone.radii > 0)) > 10
  np.testing.assert_allclose(np.asarray(together.rgb), np.asarray(alone.rgb), atol=1e-6)


@pytest.mark.parametrize("length", [1, 8, 12, 32, 64])
def test_running_sum_is_the_prefix_sum(length):
  # Lengths that split into chunks take the two-level path; the others the single triangular product.
  x = np.random.default_rng(length).normal(size=(3, 5, length)).astype(np.float32)
  np.testing.assert_allclose(np.asarray(composite.running_sum(jnp.asarray(x))),
                             np.cumsum(x.astype(np.float64), -1), rtol=1e-5, atol=1e-5)
