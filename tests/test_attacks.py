"""Image attacks on the check render and model attacks on the shared scene (robust/)."""
from __future__ import annotations

import numpy as np
import pytest

from conceal_jax.robust import image_attacks as ia
from conceal_jax.robust import model_attacks as ma
from conceal_jax.splat.gaussians import Gaussians


def smooth(h=24, w=32, seed=0):
  y, x = np.mgrid[0:h, 0:w] / max(h, w)
  phase = np.random.default_rng(seed).uniform(0, 6, 3)
  return (0.5 + 0.4 * np.sin(4 * x[..., None] + 3 * y[..., None] + phase)).astype(np.float32)


def reference_blur(image, sigma):
  """float64 2D convolution with the sampled Gaussian, radius 4 sigma, symmetric (reflect) borders."""
  radius = int(4.0 * sigma + 0.5)
  t = np.arange(-radius, radius + 1)
  k = np.exp(-t**2 / (2 * sigma**2))
  k /= k.sum()
  padded = np.pad(image.astype(np.float64), ((radius, radius), (radius, radius), (0, 0)), mode="symmetric")
  out = np.zeros(image.shape)
  for i, ki in enumerate(k):
    for j, kj in enumerate(k):
      out += ki * kj * padded[i:i + image.shape[0], j:j + image.shape[1]]
  return out


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_blur_matches_a_float64_convolution(sigma):
  image = np.random.default_rng(1).uniform(size=(20, 17, 3))
  np.testing.assert_allclose(ia.gaussian_blur(image, sigma), reference_blur(image, sigma), atol=1e-5)


def test_blur_zero_is_identity_and_constants_survive_every_attack():
  image = smooth()
  np.testing.assert_allclose(ia.gaussian_blur(image, 0), image)
  flat = np.full((16, 16, 3), 0.25, np.float32)
  for name, level, _ in ia.LEVELS:
    if name in ("blur", "resize"):
      np.testing.assert_allclose(ia.attack(flat, name, level), flat, atol=1e-6)


def test_jpeg_degrades_with_quality():
  image = smooth(48, 48)
  error = {q: np.abs(ia.jpeg(image, q) - image).mean() for q in (95, 50, 10)}
  assert error[95] < 0.01 and error[95] < error[50] < error[10]
  with pytest.raises(ValueError, match="quality"):
    ia.jpeg(image, 0)


def test_noise_brightness_contrast_and_resize():
  grey = np.full((64, 64, 3), 0.5, np.float32)
  noisy = ia.gaussian_noise(grey, 0.05, seed=3)
  np.testing.assert_array_equal(noisy, ia.gaussian_noise(grey, 0.05, seed=3))
  assert abs(noisy.std() - 0.05) < 0.003
  image = smooth()
  np.testing.assert_allclose(ia.brightness_contrast(image, 0.1, 1.0), np.clip(image + 0.1, 0, 1), atol=1e-6)
  np.testing.assert_allclose(ia.brightness_contrast(image, 0.0, 1.2), np.clip((image - 0.5) * 1.2 + 0.5, 0, 1),
                             atol=1e-6)
  np.testing.assert_allclose(ia.resize_down_up(image, 1.0), image, atol=1e-6)
  assert np.abs(ia.resize_down_up(image, 0.5) - image).mean() < 0.02  # a smooth image survives halving
  with pytest.raises(ValueError, match="shape"):
    ia.gaussian_blur(image[..., 0], 1.0)


@pytest.mark.parametrize("name, level, severity", ia.LEVELS)
def test_every_image_attack_level_runs(name, level, severity):
  out = ia.attack(smooth(), name, level)
  assert out.shape == (24, 32, 3) and out.dtype == np.float32 and np.all((out >= 0) & (out <= 1))
  assert severity in (ia.MILD, ia.MEDIUM, ia.STRONG)


def scene(n=200, degree=2, seed=0) -> Gaussians:
  rng = np.random.default_rng(seed)
  return Gaussians(means=rng.normal(size=(n, 3)).astype(np.float32),
                   log_scales=rng.uniform(-4, -1, (n, 3)).astype(np.float32),
                   quats=rng.normal(size=(n, 4)).astype(np.float32),
                   opacity_logits=rng.normal(0, 2, n).astype(np.float32),
                   sh=rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)).astype(np.float32))


def test_parameter_noise_is_relative_to_each_fields_spread():
  g = scene(5000)
  assert all(np.array_equal(getattr(ma.parameter_noise(g, 0.0), f), getattr(g, f)) for f in ma.FIELDS)
  noisy = ma.parameter_noise(g, 0.1, seed=1)
  for f in ma.FIELDS:
    ratio = (getattr(noisy, f) - getattr(g, f)).std(0) / getattr(g, f).std(0)
    np.testing.assert_allclose(ratio, 0.1, rtol=0.08)


def test_model_attack_levels_run_mild_to_strong_and_each_attack_has_a_marked_level():
  """The ownership calibration's marked trials are the mild and medium levels: every attack has one, and along
  each attack's levels the class never falls back (parameter noise: 0.002 mild, 0.01 medium, 0.05 strong)."""
  order = {ma.MILD: 0, ma.MEDIUM: 1, ma.STRONG: 2}
  for name in ma.ATTACKS:
    classes = [order[severity] for attack, _, severity in ma.LEVELS if attack == name]
    assert classes == sorted(classes) and classes[0] <= 1, name
  assert [(level, severity) for attack, level, severity in ma.LEVELS if attack == "noise"] == [
      (0.002, ma.MILD), (0.01, ma.MEDIUM), (0.05, ma.STRONG), (0.2, ma.STRONG)]


def test_pruning_removes_the_lowest_scores():
  g = scene()
  pruned = ma.prune_transparent(g, 0.3)
  assert pruned.num == 140
  assert pruned.opacity_logits.min() >= np.sort(g.opacity_logits)[60]
  small = ma.prune_smallest(g, 0.5)
  assert small.num == 100
  assert small.log_scales.sum(-1).min() >= np.median(g.log_scales.sum(-1))
  assert ma.prune_transparent(g, 0.0).num == 200 and ma.prune_transparent(g, 1.0).num == 0


def test_sh_truncation_float16_and_quantisation():
  g = scene()
  assert ma.truncate_sh(g, 0).sh.shape == (200, 1, 3) and ma.truncate_sh(g, 1).sh.shape == (200, 4, 3)
  np.testing.assert_array_equal(ma.truncate_sh(g, 1).sh, g.sh[:, :4])
  with pytest.raises(ValueError, match="SH degree"):
    ma.truncate_sh(g, 3)
  half = ma.to_float16(g)
  np.testing.assert_allclose(half.means, g.means, rtol=1e-3, atol=1e-4)
  for bits in (8, 4):
    q = ma.quantize(g, bits)
    for f in ma.FIELDS:
      x, y = getattr(g, f).astype(np.float64), getattr(q, f).astype(np.float64)
      step = (x.max(0) - x.min(0)) / (2**bits - 1)
      assert np.all(np.abs(y - x) <= step / 2 + 1e-6)
      assert all(len(np.unique(col)) <= 2**bits for col in y.reshape(len(y), -1).T)


def test_subsample_keeps_a_random_subset_in_order():
  g = scene()
  sub = ma.subsample(g, 0.7, seed=2)
  assert sub.num == 140
  rows = [int(np.flatnonzero(np.all(g.means == m, axis=1))[0]) for m in sub.means]
  assert rows == sorted(rows) and len(set(rows)) == 140


@pytest.mark.parametrize("name, level, severity", ma.LEVELS)
def test_every_model_attack_level_runs(name, level, severity):
  out = ma.attack(scene(), name, level)
  assert out.means.dtype == np.float32 and out.num <= 200 and np.all(np.isfinite(out.means))
  assert severity in (ma.MILD, ma.MEDIUM, ma.STRONG)
