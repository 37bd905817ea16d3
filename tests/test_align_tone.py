"""The tone half of re-alignment (conceal.align.fit_tone): the per-channel gain and offset that map a suspect's
render onto the owner's, against an independent float64 least-squares fit, with clipped pixels, bounds and
degenerate channels; fitted over views of the whole scene (scene_tone), a grade of the scene's colours undone."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import align
from conceal_jax.gs import similarity as sim
from conceal_jax.robust import image_attacks
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import center_of
from conceal_jax.splat.render import RenderOptions
from tests.helpers import make_camera
from tests.test_reveal_alignment import blobs


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


def graded_scene(gaussians, gain):
  """`gaussians` with every colour, in every direction, multiplied by `gain` [3] (DC and higher SH bands alike)."""
  gain = np.asarray(gain, np.float32)
  sh = np.asarray(gaussians.sh).copy()
  colour = sh[:, 0, :] * sh_lib.SH_C0 + 0.5
  sh[:, 0, :] = (gain * colour - 0.5) / sh_lib.SH_C0
  sh[:, 1:, :] *= gain
  return gaussians.replace(sh=jnp.asarray(sh))


def test_survey_cameras_look_at_the_scene_from_around_it():
  scene = jax.tree.map(jnp.asarray, blobs(500))
  key = make_camera(40, 30)
  cameras = align.survey_cameras(scene, key, 6)
  centre = np.median(np.asarray(scene.means, np.float64), axis=0)
  eyes = np.stack([center_of(np.asarray(c.world_to_camera, np.float64)) for c in cameras])
  for camera in cameras:
    w2c = np.asarray(camera.world_to_camera, np.float64)
    x, y, z = w2c[:3, :3] @ centre + w2c[:3, 3]
    assert z > 0 and abs(x / z) < 1e-6 and abs(y / z) < 1e-6  # the centre on the optical axis
    assert (camera.width, camera.height, float(camera.fx)) == (40, 30, float(key.fx))
  directions = (eyes - centre) / np.linalg.norm(eyes - centre, axis=1, keepdims=True)
  assert np.linalg.norm(directions.mean(0)) < 0.3  # spread around it, not from one side


def test_a_graded_and_moved_scene_gives_back_its_grade_and_an_untouched_one_the_identity():
  """On a black background a grade of the Gaussians' colours is exactly a gain of every render: scene_tone finds
  its inverse through a similarity; the key's view alone (here the scene's edge) is not needed for it."""
  scene = jax.tree.map(jnp.asarray, blobs(2000))
  key, options = make_camera(32, 32, eye=(0.5, -5.0, 1.5)), RenderOptions()
  similarity = sim.Similarity(sim.rotation_from_axis_angle([0.3, -0.5, 1.0], 0.7), np.array([0.4, -1.0, 2.0]), 1.7)
  moved = sim.transform_gaussians(scene, similarity)
  tone = align.scene_tone(scene, moved, key, options, similarity)
  np.testing.assert_allclose(tone.gain, 1.0, atol=2e-3)
  np.testing.assert_allclose(tone.offset, 0.0, atol=2e-3)
  gain = np.array([0.8, 0.9, 0.7])
  tone = align.scene_tone(scene, graded_scene(moved, gain), key, options, similarity)
  np.testing.assert_allclose(tone.gain, 1.0 / gain, rtol=5e-3)
  np.testing.assert_allclose(tone.offset, 0.0, atol=3e-3)
