"""splat/linear.py: a view's image as a linear map of the splats' colours, against the renderer and the float64
reference, values and gradients."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.splat import linear
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render
from tests.helpers import make_camera, random_gaussians, reference

OPTIONS = RenderOptions(background=(0.2, 0.4, 0.6))


def opaque_scene(dtype=jnp.float32):
  """Random splats with some nearly opaque ones, so that pixels stop before their last splat; degree 1."""
  g = random_gaussians(3, 60, degree=1, dtype=dtype)
  logits = jnp.asarray(np.random.default_rng(1).uniform(-2.0, 6.0, 60), dtype)
  return g.replace(opacity_logits=logits)


def test_the_linear_image_is_the_render_on_an_image_of_partial_tiles():
  g, cam = opaque_scene(), make_camera(30, 22)  # 8-pixel tiles stick out of a 30x22 image
  weights = linear.colour_weights(g, cam, OPTIONS)
  assert weights.weights.size > 0 and np.all(np.asarray(weights.weights) != 0)
  assert np.all(np.diff(np.asarray(weights.pixels)) >= 0) and int(jnp.max(weights.pixels)) < 30 * 22
  image = linear.linear_image(weights, linear.view_colours(g, cam, 1), jnp.asarray(OPTIONS.background))
  np.testing.assert_allclose(image, render(g, cam, OPTIONS).rgb, atol=2e-6, rtol=0)
  # other colours, the same weights: the render of the scene with those colours
  other = g.replace(sh=g.sh * -0.7 + 0.1)
  image = linear.linear_image(weights, linear.view_colours(other, cam, 1), jnp.asarray(OPTIONS.background))
  np.testing.assert_allclose(image, render(other, cam, OPTIONS).rgb, atol=2e-6, rtol=0)
  np.testing.assert_allclose(linear.render_through(weights, other, cam, OPTIONS), render(other, cam, OPTIONS).rgb,
                             atol=2e-6, rtol=0)
  assert int(weights.num_pairs) == int(render(g, cam, OPTIONS).num_pairs) > 0


def test_float64_weights_give_the_reference_image_where_pixels_stop(x64):
  g, cam = opaque_scene(jnp.float64), make_camera(24, 16, dtype=jnp.float64)
  weights = linear.colour_weights(g, cam, OPTIONS)
  assert weights.weights.dtype == jnp.float64
  image = linear.linear_image(weights, linear.view_colours(g, cam, 1), jnp.asarray(OPTIONS.background))
  rgb, _, _, ambiguous = reference(g, cam, OPTIONS)
  assert float(np.max(1 - np.asarray(weights.transmittance))) > 0.999, "some pixels stop on opaque splats"
  np.testing.assert_allclose(np.asarray(image)[~ambiguous], rgb[~ambiguous], atol=1e-10, rtol=0)


def test_the_gradient_in_the_colours_is_the_renders():
  g, cam = opaque_scene(), make_camera(30, 22)
  weights = linear.colour_weights(g, cam, OPTIONS)
  w = jnp.asarray(np.random.default_rng(2).normal(size=(22, 30, 3)), jnp.float32)
  background = jnp.asarray(OPTIONS.background)

  def through_render(sh):
    return jnp.sum(render(g.replace(sh=sh), cam, OPTIONS).rgb * w)

  def through_weights(sh):
    return jnp.sum(linear.linear_image(weights, linear.view_colours(g.replace(sh=sh), cam, 1), background) * w)

  want, got = jax.grad(through_render)(g.sh), jax.jit(jax.grad(through_weights))(g.sh)
  assert np.all(np.isfinite(got)) and np.any(np.asarray(got) != 0)
  np.testing.assert_allclose(got, want, atol=1e-5 * float(jnp.max(jnp.abs(want))), rtol=0)


def test_no_gaussians_give_the_background():
  cam = make_camera(16, 8)
  weights = linear.colour_weights(Gaussians.empty(1), cam, OPTIONS)
  image = linear.linear_image(weights, jnp.zeros((0, 3)), jnp.asarray(OPTIONS.background))
  np.testing.assert_allclose(image, np.broadcast_to(OPTIONS.background, (8, 16, 3)))
