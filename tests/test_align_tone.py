"""The tone half of re-alignment (conceal.align.fit_tone): the per-channel gain and offset that map a suspect's
render onto the owner's, against an independent float64 least-squares fit, with clipped pixels, bounds and
degenerate channels."""
from __future__ import annotations

import numpy as np
import pytest

from conceal_jax.conceal import align
from conceal_jax.robust import image_attacks


def render_like(seed: int = 0, size: int = 48) -> np.ndarray:
  """[size, size, 3] a smooth picture in (0.05, 0.95) with a white border (a background at 1, as lego's)."""
  rng = np.random.default_rng(seed)
  y, x = np.mgrid[0:size, 0:size] / size
  image = np.stack([0.5 + 0.4 * np.sin(6 * x + c + rng.uniform()) * np.cos(4 * y - c) for c in range(3)], -1)
  image[:6], image[:, :6] = 1.0, 1.0
  return image


def reference_fit(image, reference, channel):
  """np.polyfit over the pixels inside (0, 1) in both, one channel."""
  x, y = image[..., channel].ravel(), reference[..., channel].ravel()
  inside = (x > 1e-3) & (x < 1 - 1e-3) & (y > 1e-3) & (y < 1 - 1e-3)
  gain, offset = np.polyfit(x[inside], y[inside], 1)
  return gain, offset


def test_fit_tone_matches_a_float64_least_squares_fit():
  reference = render_like()
  rng = np.random.default_rng(1)
  image = np.clip(reference * np.array([0.8, 1.1, 0.95]) + np.array([0.05, -0.04, 0.02])
                  + rng.normal(0.0, 0.01, reference.shape), 0.0, 1.0)
  tone = align.fit_tone(image, reference)
  for c in range(3):
    np.testing.assert_allclose((tone.gain[c], tone.offset[c]), reference_fit(image, reference, c), rtol=1e-9,
                               atol=1e-12)


@pytest.mark.parametrize("brightness,contrast", [(-0.1, 1.0), (0.1, 1.0), (0.0, 1.2), (0.0, 0.8)])
def test_a_brightness_or_contrast_attack_is_undone_where_nothing_was_clipped(brightness, contrast):
  """The robustness harness's medium levels: clipped pixels (the white border, saturated highlights) are left out
  of the fit, so the map found is the attack's inverse and the rest of the render comes back exactly."""
  check = render_like()
  attacked = image_attacks.brightness_contrast(check, brightness, contrast)
  tone = align.fit_tone(attacked, check)
  np.testing.assert_allclose(tone.gain, np.full(3, 1.0 / contrast), rtol=1e-6)  # the attack rounds to float32
  restored = np.asarray(tone.apply(attacked.astype(np.float32)))
  inside = (attacked > 1e-3) & (attacked < 1 - 1e-3)
  np.testing.assert_allclose(restored[inside], check[inside], atol=1e-5)
  assert np.all(np.isfinite(restored))


def test_the_map_is_bounded_and_degenerate_channels_keep_the_identity():
  reference = render_like()
  flat = reference.copy()
  flat[..., 0] = 0.5  # no spread in red: nothing to fit
  flat[..., 1] = 0.5 + 0.01 * (reference[..., 1] - 0.5)  # a 100x gain would be needed in green
  flat[..., 2] = 1.0  # blue all clipped
  tone = align.fit_tone(flat, reference)
  assert tone.gain[0] == 1.0 and tone.offset[0] == 0.0
  assert tone.gain[1] == align.MAX_TONE_GAIN and abs(tone.offset[1]) <= align.MAX_TONE_OFFSET
  assert tone.gain[2] == 1.0 and tone.offset[2] == 0.0


def test_identical_renders_give_the_identity_and_shapes_are_checked():
  check = render_like()
  tone = align.fit_tone(check, check)
  np.testing.assert_allclose(tone.gain, 1.0, atol=1e-12)
  np.testing.assert_allclose(tone.offset, 0.0, atol=1e-12)
  assert align.Tone.identity().report() == dict(gain=[1.0, 1.0, 1.0], offset=[0.0, 0.0, 0.0])
  with pytest.raises(ValueError, match="one shape"):
    align.fit_tone(check, check[:10])
