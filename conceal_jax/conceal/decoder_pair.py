"""A view's two decoder reads (objective.l1_of_decoded_pair) as one batch of two, for speed.

objective.view_terms reads two images through F: its own render (with `decoder_plus` where the view carries
L_d^+, else `decoder_minus`) and the teacher's render (with `decoder_minus`). The step evaluates every view at
decoder_plus == decoder_minus (step.gradients), so one forward pass of F on the two images as a batch gives
both values; the gradient of each read is taken per image (a vmap over the batch) and handed to its own
decoder argument, so the L_d^+ and L_d^- gradient pytrees that the guided update compares stay apart. The
result equals l1_of_decoded_pair's, values and gradients, whenever the two decoders hold the same values;
with different values it would read both images with decoders[1].
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from conceal_jax.conceal.objective import l1_of_decoded, l1_of_decoded_pair
from conceal_jax.conceal.settings import ConcealSettings


def batched_l1_of_decoded_pair(decoders, images: jax.Array, targets: jax.Array,
                               settings: ConcealSettings) -> jax.Array:
  """[2] as objective.l1_of_decoded_pair (images, targets [2, S, S, 3]), F run once on the batch of two."""
  if not settings.use_decoder:
    return l1_of_decoded_pair(decoders, images, targets, settings)
  read = lambda params, image, target: l1_of_decoded(params, image, target, settings)
  per_image = jax.vmap(jax.value_and_grad(read, argnums=(0, 1, 2)), in_axes=(None, 0, 0))

  @jax.custom_vjp
  def pair(first, second, images, targets):
    del first
    return jax.vmap(read, in_axes=(None, 0, 0))(second, images, targets)

  def forward(first, second, images, targets):
    del first
    return per_image(second, images, targets)

  def backward(grads, cotangent):
    params, image, target = grads
    per = lambda g, i: jax.tree.map(lambda leaf: cotangent[i] * leaf[i], g)
    scale = cotangent[:, None, None, None]
    return per(params, 0), per(params, 1), scale * image, scale * target

  pair.defvjp(forward, backward)
  return pair(decoders[0], decoders[1], images, targets)
