"""Training-time distortions of the check render (conceal/augment.py) against the float64 attacks of
robust/image_attacks.py, and a concealment run that trains through them."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import augment, conceal
from conceal_jax.robust import image_attacks
from tests.test_conceal import tiny, tiny_config  # noqa: F401  (tiny is a fixture)


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
  draws = [augment.draw(rng, 1.5, 0.05) for _ in range(200)]
  assert all(0 <= d["blur"] <= 1.5 and 0 <= d["noise"] <= 0.05 for d in draws)
  image = jnp.full((64, 64, 3), 0.5, jnp.float32)
  drawn = dict(blur=np.float32(0.0), noise=np.float32(0.1), seed=np.uint32(3))
  out = augment.distort(image, drawn, 0.0, 0.1)
  assert abs(float(jnp.std(out)) - 0.1) < 0.005 and abs(float(jnp.mean(out)) - 0.5) < 0.005
  # a run that never draws noise (noise_max 0) adds none
  np.testing.assert_array_equal(np.asarray(augment.distort(image, drawn, 0.0, 0.0)), np.asarray(image))


def test_conceal_trains_through_distortions_in_one_trace(tiny, tmp_path):  # noqa: F811
  config = tiny_config(tiny, iterations=4, check_blur_max=1.0, check_noise_max=0.02)
  result = conceal.conceal_and_evaluate(config, str(tmp_path))
  assert result["traces"] == dict(conceal_step=1) and np.isfinite(result["metrics"]["hidden"]["psnr"])
  with pytest.raises(ValueError, match="check_blur_max"):
    conceal.conceal_and_evaluate(tiny_config(tiny, check_blur_max=-1.0), str(tmp_path / "bad"))
