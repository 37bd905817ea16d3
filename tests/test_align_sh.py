"""Re-alignment reads only the SH bands the owner's copy shows at the key (align.key_options): higher bands that
a converter returns filled with its quantization step (as .compressed.ply's 8 bits return zeros) are left out,
and a scene whose view-dependent colour the key sees keeps every band."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import align
from conceal_jax.gs import similarity as sim
from conceal_jax.splat.render import RenderOptions, render
from tests.helpers import make_camera
from tests.test_reveal_alignment import blobs


def with_rest(gaussians, rest):
  """`gaussians` with every higher SH coefficient set to `rest` (a scalar or [N, K-1, 3])."""
  return gaussians.replace(sh=gaussians.sh.at[:, 1:, :].set(rest))


def test_bands_the_owner_does_not_show_at_the_key_are_left_out_of_the_reading():
  owner = jax.tree.map(jnp.asarray, blobs(1500))  # higher bands all zero
  camera, options = make_camera(32, 32, eye=(0.5, -5.0, 1.5)), RenderOptions()
  assert align.key_options(owner, [camera], options).sh_degree == 0
  similarity = sim.Similarity(sim.rotation_from_axis_angle([0.2, 1.0, -0.4], 2.5), np.array([1.0, 0.5, -2.0]), 0.6)
  suspect = with_rest(sim.transform_gaussians(owner, similarity), 4.0 / 255)  # a quantizer's tint
  realigned = align.realign(owner, suspect, camera, options)
  moved, moved_options = realigned.camera, realigned.options
  expected = np.asarray(render(owner, camera, options).rgb)
  tinted = align.moved_key(camera, options, similarity)
  assert np.abs(np.asarray(render(suspect, *tinted).rgb) - expected).max() > 5e-3
  np.testing.assert_allclose(np.asarray(render(suspect, moved, moved_options).rgb), expected, atol=2e-3)


def test_a_view_dependent_owner_keeps_every_band():
  owner = blobs(1500)
  rest = np.random.default_rng(0).normal(0.0, 0.2, np.asarray(owner.sh)[:, 1:, :].shape)
  owner = jax.tree.map(jnp.asarray, with_rest(owner, rest))
  options = RenderOptions()
  assert align.key_options(owner, [make_camera(32, 32, eye=(0.5, -5.0, 1.5))], options) is options
