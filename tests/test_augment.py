"""Training-time distortions of the check render and of the model it is rendered from (conceal/augment.py)
against the float64 attacks of robust/, and a concealment run that trains through them."""
from __future__ import annotations

import dataclasses
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import augment, perturb, train as conceal_train
from conceal_jax.gs import densify
from conceal_jax.robust import image_attacks, model_attacks
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.conceal.augment import Augmentation
from tests.test_conceal import tiny, tiny_config  # noqa: F401  (tiny is a fixture)

IMAGE = Augmentation(blur_max=1.5, noise_max=0.05)
BOTH = dataclasses.replace(IMAGE, dropout_max=0.3, param_noise_max=0.02)
ALL = dataclasses.replace(BOTH, brightness_max=0.1, contrast_max=0.2)
PHOTOMETRIC = Augmentation(brightness_max=0.1, contrast_max=0.2)
MODEL = Augmentation(dropout_max=0.5, param_noise_max=0.1)


@pytest.mark.parametrize("sigma", [0.4, 1.0, 2.5])
def test_blur_matches_the_float64_attack(sigma):
  image = np.random.default_rng(0).uniform(size=(23, 31, 3))
  ours = augment.gaussian_blur(jnp.asarray(image, jnp.float32), jnp.float32(sigma), augment.blur_radius(sigma))
  np.testing.assert_allclose(np.asarray(ours), image_attacks.gaussian_blur(image, sigma), atol=2e-6)


def test_blur_of_sigma_zero_is_the_identity_with_finite_gradients():
  image = jnp.asarray(np.random.default_rng(1).uniform(size=(12, 12, 3)), jnp.float32)
  np.testing.assert_array_equal(np.asarray(augment.gaussian_blur(image, jnp.float32(0.0), 4)), np.asarray(image))
  loss = lambda img, s: jnp.sum(augment.gaussian_blur(img, s, 4) ** 2)
  for sigma in (0.0, 1e-4, 1.5):
    g_image, g_sigma = jax.grad(loss, argnums=(0, 1))(image, jnp.float32(sigma))
    assert np.all(np.isfinite(np.asarray(g_image))) and np.isfinite(float(g_sigma))


def test_distort_adds_noise_of_the_drawn_level_and_draws_stay_in_range():
  rng = np.random.default_rng(2)
  draws = [augment.draw(rng, BOTH) for _ in range(200)]
  assert all(0 <= d["blur"] <= 1.5 and 0 <= d["noise"] <= 0.05 for d in draws)
  assert all(0 <= d["dropout"] <= 0.3 and 0 <= d["param_noise"] <= 0.02 for d in draws)
  # the image's draws come first: a run that adds the model's keeps its image distortions
  image_only = augment.draw(np.random.default_rng(7), IMAGE)
  with_model = augment.draw(np.random.default_rng(7), BOTH)
  assert all(image_only[k] == with_model[k] for k in ("blur", "noise", "seed"))
  image = jnp.full((64, 64, 3), 0.5, jnp.float32)
  drawn = dict(blur=np.float32(0.0), noise=np.float32(0.1), seed=np.uint32(3))
  out = augment.distort(image, drawn, Augmentation(noise_max=0.1))
  assert abs(float(jnp.std(out)) - 0.1) < 0.005 and abs(float(jnp.mean(out)) - 0.5) < 0.005
  # a run that never draws noise (noise_max 0) adds none
  np.testing.assert_array_equal(np.asarray(augment.distort(image, drawn, Augmentation())), np.asarray(image))


@pytest.mark.parametrize("brightness,contrast", [(-0.1, 1.0), (0.0, 0.8), (0.07, 1.2), (-0.05, 0.9)])
def test_photometric_matches_the_float64_attack_where_it_does_not_clip(brightness, contrast):
  # values in [0.2, 0.8] stay inside [0, 1] under every level here, so the attack's clip is idle
  image = np.random.default_rng(3).uniform(0.2, 0.8, size=(9, 11, 3))
  drawn = dict(brightness=np.float32(brightness), contrast=np.float32(contrast))
  ours = augment.distort(jnp.asarray(image, jnp.float32), drawn, PHOTOMETRIC)
  expected = image_attacks.brightness_contrast(image, brightness=brightness, contrast=contrast)
  np.testing.assert_allclose(np.asarray(ours), expected, atol=1e-6)


def test_photometric_draws_stay_in_range_keep_earlier_draws_and_level_zero_is_the_identity():
  rng = np.random.default_rng(5)
  draws = [augment.draw(rng, ALL) for _ in range(400)]
  assert all(-0.1 <= d["brightness"] <= 0.1 and 0.8 <= d["contrast"] <= 1.2 for d in draws)
  assert min(d["brightness"] for d in draws) < -0.09 and max(d["contrast"] for d in draws) > 1.18
  before = augment.draw(np.random.default_rng(7), BOTH)
  after = augment.draw(np.random.default_rng(7), ALL)
  assert all(before[k] == after[k] for k in ("blur", "noise", "seed", "dropout", "param_noise", "model_seed"))
  # a run without photometric draws gets brightness 0 and contrast 1: the identity, values and gradients
  plain = augment.draw(np.random.default_rng(7), IMAGE)
  image = jnp.asarray(np.random.default_rng(6).uniform(-0.2, 1.3, size=(8, 8, 3)), jnp.float32)
  np.testing.assert_array_equal(np.asarray(augment.photometric(image, plain["brightness"], plain["contrast"])),
                                np.asarray(image))
  grad = jax.grad(lambda x: jnp.sum(augment.photometric(x, jnp.float32(-0.1), jnp.float32(1.2)) ** 2))(image)
  assert np.all(np.isfinite(np.asarray(grad))) and np.all(np.asarray(grad) != 0)


def _random_gaussians(n, seed=0):
  rng = np.random.default_rng(seed)
  f32 = lambda *shape, scale=1.0: jnp.asarray(scale * rng.normal(size=shape), jnp.float32)
  return Gaussians(means=f32(n, 3, scale=2.0), log_scales=f32(n, 3, scale=0.5) - 4.0, quats=f32(n, 4),
                   opacity_logits=f32(n), sh=f32(n, 4, 3, scale=0.3))


def test_perturb_gaussians_noises_by_the_fields_spread_and_drops_at_the_drawn_rate():
  """Against float64 statistics: the noise of each field and channel, over its float64 spread, has standard
  deviation param_noise (as robust.model_attacks.parameter_noise's); a share `dropout` of the Gaussians is
  dropped (opacity logit DROPPED_LOGIT), the rest keep their noised logits."""
  g = _random_gaussians(20_000)
  level, rate = 0.05, 0.3
  drawn = dict(dropout=np.float32(0.0), param_noise=np.float32(level), model_seed=np.uint32(4))
  noised = perturb.perturb_gaussians(g, drawn, MODEL)
  for name in perturb.MODEL_FIELDS:
    x = np.asarray(getattr(g, name), np.float64)
    relative = (np.asarray(getattr(noised, name), np.float64) - x) / (level * x.std(axis=0, keepdims=True))
    assert np.all(np.abs(relative.reshape(len(x), -1).std(axis=0) - 1.0) < 0.03), name
    assert np.all(np.abs(relative.reshape(len(x), -1).mean(axis=0)) < 0.03), name
  both = perturb.perturb_gaussians(g, dict(drawn, dropout=np.float32(rate)), MODEL)
  dropped = np.asarray(both.opacity_logits) == perturb.DROPPED_LOGIT
  assert abs(dropped.mean() - rate) < 0.015
  np.testing.assert_array_equal(np.asarray(both.opacity_logits)[~dropped], np.asarray(noised.opacity_logits)[~dropped])
  np.testing.assert_array_equal(np.asarray(both.means), np.asarray(noised.means))


def test_perturb_gaussians_at_level_zero_is_the_identity_with_finite_gradients():
  g = _random_gaussians(500, seed=1)
  zero = dict(dropout=np.float32(0.0), param_noise=np.float32(0.0), model_seed=np.uint32(9))
  for a, b in zip(jax.tree.leaves(perturb.perturb_gaussians(g, zero, MODEL)), jax.tree.leaves(g)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  # the noise's scale is a constant and a dropped Gaussian's opacity gets no gradient
  drawn = dict(zero, dropout=np.float32(0.4), param_noise=np.float32(0.1))
  loss = lambda gs: sum(jnp.sum(x) for x in jax.tree.leaves(perturb.perturb_gaussians(gs, drawn, MODEL)))
  grads = jax.grad(loss)(g)
  kept = np.asarray(perturb.perturb_gaussians(g, drawn, MODEL).opacity_logits) != perturb.DROPPED_LOGIT
  np.testing.assert_array_equal(np.asarray(grads.opacity_logits), kept.astype(np.float32))
  for name in ("means", "log_scales", "quats", "sh"):
    np.testing.assert_array_equal(np.asarray(getattr(grads, name)), 1.0)


def test_quantize_8bit_matches_the_formats_bytes_and_passes_gradients_through():
  """Against float64 encoders of .spz's bytes (base colours, opacities) and .compressed.ply's (higher SH bands,
  a floor to 256 levels of [-4, 4) read back at the level's centre): the values land on those grids, the
  other fields stay, the gradient is the identity's; a step that does not quantize leaves the Gaussians."""
  g = _random_gaussians(2000, seed=3)
  q = perturb.quantize_8bit(g)
  dc = np.asarray(g.sh[:, 0], np.float64)
  byte = np.clip(np.round(255 * (0.15 * dc + 0.5)), 0, 255)
  np.testing.assert_allclose(np.asarray(q.sh[:, 0]), (byte / 255 - 0.5) / 0.15, atol=1e-5)
  opacity = np.clip(np.round(255 / (1 + np.exp(-np.asarray(g.opacity_logits, np.float64)))), 0.5, 254.5) / 255
  np.testing.assert_allclose(np.asarray(jax.nn.sigmoid(q.opacity_logits)), opacity, atol=1e-6)
  rest_byte = np.clip(np.floor(256 * (np.asarray(g.sh[:, 1:], np.float64) + 4) / 8), 0, 255)
  np.testing.assert_allclose(np.asarray(q.sh[:, 1:]), (rest_byte + 0.5) / 256 * 8 - 4, atol=1e-6)
  np.testing.assert_array_equal(np.asarray(q.means), np.asarray(g.means))
  grads = jax.grad(lambda gs: sum(jnp.sum(x) for x in jax.tree.leaves(perturb.quantize_8bit(gs))))(g)
  assert all(np.all(np.asarray(x) == 1.0) for x in jax.tree.leaves(grads))
  a = augment.Augmentation(quantize_fraction=0.5)
  draws = [augment.draw(np.random.default_rng(i), a)["quantize"] for i in range(400)]
  assert set(draws) == {0.0, 1.0} and abs(np.mean(draws) - 0.5) < 0.1
  drawn = dict(augment.draw(np.random.default_rng(0), a), quantize=np.float32(0.0))
  for x, y in zip(jax.tree.leaves(perturb.perturb_gaussians(g, drawn, a)), jax.tree.leaves(g)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  drawn.update(quantize=np.float32(1.0), rounding=np.float32(0.5))
  compiled = jax.jit(perturb.quantize_8bit)(g)  # as perturb_gaussians runs it (under lax.cond: compiled)
  for x, y in zip(jax.tree.leaves(perturb.perturb_gaussians(g, drawn, a)), jax.tree.leaves(compiled)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_quantize_8bit_rounds_where_it_is_told_as_the_formats_do():
  """Rounding 0 takes each value to the 8-bit step below (.sog's faint opacities come back a step lower than
  .spz's), 0.5 to the nearest; an opacity of 0.01 (2.55 steps) lands on 2/255 and 3/255, higher SH bands of
  zeros on the cells either side of 0 (+1/64 as .compressed.ply stores them, -1/64); each step draws its
  rounding point from [0, 1) when it quantizes, and a run without quantization draws none."""
  g = _random_gaussians(500, seed=4)
  logits = np.asarray(g.opacity_logits, np.float64)
  down = np.clip(np.floor(255 / (1 + np.exp(-logits))), 0.5, 254.5) / 255
  np.testing.assert_allclose(np.asarray(jax.nn.sigmoid(perturb.quantize_8bit(g, 0.0).opacity_logits)), down,
                             atol=1e-6)
  faint = g.replace(opacity_logits=jnp.full_like(g.opacity_logits, float(np.log(0.01 / 0.99))))
  opacity = lambda rounding: np.unique(np.asarray(jax.nn.sigmoid(
      perturb.quantize_8bit(faint, rounding).opacity_logits)))
  np.testing.assert_allclose(opacity(0.0), [2 / 255], rtol=1e-5)
  np.testing.assert_allclose(opacity(0.5), [3 / 255], rtol=1e-5)
  bands_of_zeros = g.replace(sh=g.sh.at[:, 1:].set(0.0))
  rest = lambda rounding: np.unique(np.asarray(perturb.quantize_8bit(bands_of_zeros, rounding).sh[:, 1:]))
  np.testing.assert_allclose(rest(0.5), [1 / 64], rtol=1e-6)  # .compressed.ply's converter writes this
  np.testing.assert_allclose(rest(0.0), [-1 / 64], rtol=1e-6)
  a = augment.Augmentation(quantize_fraction=0.5)
  points = np.array([augment.draw(np.random.default_rng(i), a)["rounding"] for i in range(400)])
  assert points.min() >= 0.0 and points.max() < 1.0 and abs(points.mean() - 0.5) < 0.05
  plain = [augment.draw(np.random.default_rng(i), augment.Augmentation(blur_max=1.0)) for i in range(3)]
  assert all(d["rounding"] == 0.5 for d in plain)


@pytest.mark.slow
def test_conceal_trains_through_distortions_in_one_trace(tiny, tmp_path):  # noqa: F811
  maxima = dict(blur_max=1.0, noise_max=0.02, dropout_max=0.2, param_noise_max=0.02, brightness_max=0.1,
                contrast_max=0.2, identity_distorted=True)
  attacks = {f"attacks.{k}": v for k, v in maxima.items()}
  config = tiny_config(tiny, iterations=4, identity_on_student=True, **attacks)
  result = conceal_train.train_and_evaluate(config, str(tmp_path))
  assert result["traces"] == dict(conceal_step=1) and np.isfinite(result["metrics"]["hidden"]["psnr"])


def test_bad_distortion_maxima_are_named(tiny, tmp_path):  # noqa: F811
  for key, bad in (("blur_max", -1.0), ("dropout_max", 1.0), ("param_noise_max", -0.1), ("brightness_max", -0.1),
                   ("contrast_max", 1.0), ("noise_max", float("nan"))):
    with pytest.raises(ValueError, match=f"conceal.attacks.{key}"):
      conceal_train.train_and_evaluate(tiny_config(tiny, **{f"attacks.{key}": bad}), str(tmp_path / "bad"))


def test_an_opacity_reset_caps_every_opacity_where_drawn():
  """reset 1: every opacity at most densify.RESET_CEILING (3D-GS's reset), the lower ones and the other fields as they
  were; reset 0: the Gaussians themselves."""
  g = _random_gaussians(500, seed=5)
  a = augment.Augmentation(reset_fraction=0.5)
  drawn = dict(augment.draw(np.random.default_rng(0), a), reset=np.float32(1.0))
  reset = perturb.perturb_gaussians(g, drawn, a)
  opacity, before = (np.asarray(jax.nn.sigmoid(x.opacity_logits), np.float64) for x in (reset, g))
  np.testing.assert_allclose(opacity, np.minimum(before, densify.RESET_CEILING), rtol=1e-5)
  np.testing.assert_array_equal(np.asarray(reset.sh), np.asarray(g.sh))
  drawn["reset"] = np.float32(0.0)
  for x, y in zip(jax.tree.leaves(perturb.perturb_gaussians(g, drawn, a)), jax.tree.leaves(g)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("share", [0.0, 0.1, 0.3, 0.55])
def test_size_pruning_drops_what_the_prune_attack_removes(share):
  """The Gaussians kept_by_size drops are those robust.model_attacks.prune_smallest removes (volume ties included,
  the lower index first), the rest keep their values, and a dropped Gaussian's opacity gets no gradient."""
  g = _random_gaussians(2_000, seed=3)
  scales = np.asarray(g.log_scales).copy()
  scales[:40] = scales[40:80]  # ties in volume
  g = g.replace(log_scales=jnp.asarray(scales))
  pruned = model_attacks.prune_smallest(g, share)
  survivors = {tuple(row) for row in np.asarray(pruned.means).tolist()}
  expected = np.array([tuple(row) in survivors for row in np.asarray(g.means).tolist()])
  drawn = dict(dropout=np.float32(0.0), param_noise=np.float32(0.0), model_seed=np.uint32(0),
               prune_small=np.float32(share))
  model = Augmentation(prune_small_max=0.6)
  out = perturb.perturb_gaussians(g, drawn, model)
  kept = np.asarray(out.opacity_logits) != perturb.DROPPED_LOGIT
  np.testing.assert_array_equal(kept, expected)
  np.testing.assert_array_equal(np.asarray(out.opacity_logits)[kept], np.asarray(g.opacity_logits)[kept])
  grads = jax.grad(lambda gs: jnp.sum(perturb.perturb_gaussians(gs, drawn, model).opacity_logits))(g)
  np.testing.assert_array_equal(np.asarray(grads.opacity_logits), kept.astype(np.float32))
  assert np.isfinite(np.asarray(grads.log_scales)).all()


def test_size_pruning_draws_stay_in_range_and_keep_earlier_draws():
  plain = augment.draw(np.random.default_rng(5), Augmentation(dropout_max=0.2, merge_fraction=0.5))
  with_pruning = augment.draw(np.random.default_rng(5), Augmentation(dropout_max=0.2, merge_fraction=0.5,
                                                                     prune_small_max=0.3))
  without = lambda drawn: {k: v for k, v in drawn.items() if k != "prune_small"}
  assert without(with_pruning) == without(plain) and plain["prune_small"] == 0.0
  pruning = Augmentation(prune_small_max=0.3)
  shares = [augment.draw(np.random.default_rng(s), pruning)["prune_small"] for s in range(200)]
  assert 0.0 <= min(shares) and max(shares) <= 0.3 and max(shares) > 0.25
  with pytest.raises(ValueError, match="prune_small_max"):
    Augmentation(prune_small_max=1.0)
