"""Adaptive density control: clone / split / prune decisions, the row bookkeeping, capacity buckets."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.gs import densify
from conceal_jax.gs.densify import DensifyParams
from conceal_jax.splat.gaussians import Gaussians

EXTENT = 2.0  # clone below 0.02 max scale, prune above 0.2 world scale


def scene(log_scales, opacities, quats=None) -> Gaussians:
  n = len(opacities)
  opacities = np.asarray(opacities, np.float64)
  quats = np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else np.asarray(quats, np.float64)
  return Gaussians(means=np.arange(3 * n, dtype=np.float32).reshape(n, 3),
                   log_scales=np.asarray(log_scales, np.float32), quats=quats.astype(np.float32),
                   opacity_logits=np.log(opacities / (1 - opacities)).astype(np.float32),
                   sh=np.arange(n * 4 * 3, dtype=np.float32).reshape(n, 4, 3))


def test_clone_split_and_keep():
  small, large = np.log([0.01] * 3), np.log([0.05, 0.1, 0.02])
  g = scene([small, small, large, large], [0.5, 0.5, 0.5, 0.5])
  grads = np.array([3e-4, 1e-4, 3e-4, 1e-4])  # 0: clone, 1: keep, 2: split, 3: keep
  out, source = densify.densify_and_prune(g, grads, np.zeros(4), EXTENT, DensifyParams(), False,
                                          np.random.default_rng(0))
  # survivors first (the split parent 2 is gone), then the clone of 0, then two children of 2
  np.testing.assert_array_equal(source, [0, 1, 3, -1, -1, -1])
  np.testing.assert_array_equal(out.means[3], g.means[0])
  np.testing.assert_array_equal(out.sh[4], g.sh[2])
  np.testing.assert_allclose(np.exp(out.log_scales[4:]), np.exp(g.log_scales[[2, 2]]) / 1.6, rtol=1e-6)


@pytest.mark.parametrize("cap, expected_source", [
    (0, [0, 1, 3, -1, -1, -1]),  # no limit: as above
    (6, [0, 1, 3, -1, -1, -1]),  # 4 live + 2 candidates fit exactly
    (5, [0, 1, 2, 3, -1]),       # room for one: the larger gradient (the clone of 0, 5e-4) wins
    (4, [0, 1, 2, 3]),           # full: nothing is densified
    (3, [0, 1, 2, 3])])          # over the cap already: nothing is densified, nothing removed for it
def test_max_gaussians_keeps_the_strongest_candidates(cap, expected_source):
  small, large = np.log([0.01] * 3), np.log([0.05, 0.1, 0.02])
  g = scene([small, small, large, large], [0.5, 0.5, 0.5, 0.5])
  grads = np.array([5e-4, 1e-4, 3e-4, 1e-4])
  out, source = densify.densify_and_prune(g, grads, np.zeros(4), EXTENT, DensifyParams(max_gaussians=cap),
                                          False, np.random.default_rng(0))
  np.testing.assert_array_equal(source, expected_source)
  assert out.num == len(expected_source)


def test_max_gaussians_must_not_be_negative():
  with pytest.raises(ValueError, match="max_gaussians"):
    DensifyParams(max_gaussians=-1)


def test_split_samples_children_from_the_parent_gaussian():
  """Children centres = parent + R (s * z), z ~ N(0, I): check against an independent float64 draw."""
  angle = 0.7
  quat = [np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]  # rotation by `angle` about z
  parent = scene([np.log([0.3, 0.05, 0.1])], [0.5], [quat])
  children = densify.split_children(parent, np.random.default_rng(3), 1.6)
  rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
  rng = np.random.default_rng(3)
  expected = [parent.means[0] + rotation @ (rng.normal(size=(1, 3))[0] * [0.3, 0.05, 0.1]) for _ in range(2)]
  np.testing.assert_allclose(children.means, np.array(expected), rtol=1e-5, atol=1e-6)


def test_prune_transparent_and_large():
  size = np.log([0.01] * 3)
  g = scene([size, size, size, np.log([0.3, 0.01, 0.01])], [0.001, 0.5, 0.5, 0.5])
  radii = np.array([1, 30, 5, 5])
  rng = np.random.default_rng(0)
  _, kept = densify.densify_and_prune(g, np.zeros(4), radii, EXTENT, DensifyParams(), False, rng)
  np.testing.assert_array_equal(kept, [1, 2, 3])  # only the transparent one goes before the first reset
  _, kept = densify.densify_and_prune(g, np.zeros(4), radii, EXTENT, DensifyParams(), True, rng)
  np.testing.assert_array_equal(kept, [2])  # then also 30 px > 20 px on screen and 0.3 > 0.1 * extent


def test_new_gaussians_escape_the_screen_size_prune():
  """Clones have not been seen on screen yet: they inherit no radius (3D-GS zero-pads max_radii2D)."""
  g = scene([np.log([0.01] * 3)], [0.5])
  _, source = densify.densify_and_prune(g, np.array([1.0]), np.array([30]), EXTENT, DensifyParams(), True,
                                        np.random.default_rng(0))
  np.testing.assert_array_equal(source, [-1])


@pytest.mark.parametrize("count,current,expected", [
    (10, 0, 1024), (1024, 0, 1024), (1025, 0, 2048), (3000, 0, 4096),
    (1500, 2048, 2048), (2049, 2048, 4096), (300, 2048, 1024), (600, 2048, 2048)])
def test_capacity_buckets(count, current, expected):
  assert densify.capacity_for(count, current) == expected


@pytest.mark.parametrize("count,current,limit,expected", [
    (3000, 0, 2500, 4096),       # above the cap (e.g. a large start): the cap does not apply
    (2500, 0, 2500, 2500),       # the bucket would be 4096: the cap is the most ever needed
    (2049, 2048, 2500, 2500),
    (1500, 2048, 2500, 2048),    # fits the current buffer: kept
    (36000, 131072, 40000, 40000)])  # a buffer above the cap shrinks once the count is under the cap
def test_capacity_never_exceeds_the_gaussian_cap(count, current, limit, expected):
  assert densify.capacity_for(count, current, limit) == expected


def test_capacity_grows_geometrically():
  buckets = [densify.capacity_for(1)]
  while buckets[-1] < 500_000:
    buckets.append(densify.capacity_for(buckets[-1] + 1))
  ratios = np.array(buckets[1:]) / np.array(buckets[:-1])
  assert np.all(ratios >= 1.4) and np.all(ratios <= 2.0)
  assert all(b % densify.CAPACITY_QUANTUM == 0 for b in buckets)
  for count in (5000, 99_999, 300_001):
    capacity = densify.capacity_for(count)
    assert capacity >= count and capacity in buckets and buckets[buckets.index(capacity) - 1] < count


def test_gather_rows_moves_moments_and_zeroes_fresh_rows():
  x = np.arange(8, dtype=np.float32).reshape(4, 2) + 1
  out = densify.gather_rows(x, np.array([2, -1, 0]), 5)
  np.testing.assert_array_equal(out, [[5, 6], [0, 0], [1, 2], [0, 0], [0, 0]])


def test_reset_opacity_caps_at_one_percent():
  logits = np.log(np.array([0.5, 0.001]) / (1 - np.array([0.5, 0.001]))).astype(np.float32)
  out = 1 / (1 + np.exp(-densify.reset_opacity(logits).astype(np.float64)))
  np.testing.assert_allclose(out, [0.01, 0.001], rtol=1e-5)


def test_opacity_logit_inverts_the_sigmoid_in_float64_and_in_jax():
  """splat.gaussians.opacity_logit, the one home of opacity -> logit (init, densify's reset, the carrier film,
  .spz quantization): the inverse of the sigmoid against float64, finite near 0 and 1, numpy and jax alike."""
  from conceal_jax.splat.gaussians import opacity_logit
  p = np.array([1e-7, 0.01, 0.5, 0.9, 1 - 1e-7])
  logit = opacity_logit(p)
  assert isinstance(logit, np.ndarray) and np.all(np.isfinite(logit))
  np.testing.assert_allclose(1.0 / (1.0 + np.exp(-logit)), p, rtol=1e-12)
  p32 = np.float32(p)  # 1 - 1e-7 rounds in float32: the reference is the logit of what jax is given
  np.testing.assert_allclose(np.asarray(opacity_logit(jnp.asarray(p32))), opacity_logit(p32.astype(np.float64)),
                             rtol=1e-5, atol=1e-5)
  assert float(opacity_logit(0.5)) == 0.0
  grad = jax.grad(lambda x: jnp.sum(opacity_logit(x)))(jnp.asarray(p[1:-1], jnp.float32))
  np.testing.assert_allclose(grad, 1.0 / (p[1:-1] * (1 - p[1:-1])), rtol=1e-4)
