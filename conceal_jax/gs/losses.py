"""Image losses: the 3D-GS photometric loss and the ConcealGS losses (arXiv:2501.03605, Sec. 2.2, eqs. 3-5).

Every loss is a scalar mean over pixels, so gradients do not grow with image size.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from conceal_jax.gs import metrics


def l1(a: jax.Array, b: jax.Array) -> jax.Array:
  """Mean absolute difference of two images [..., H, W, C]."""
  return jnp.mean(jnp.abs(a - b))


def photometric_loss(rendered: jax.Array, target: jax.Array, ssim_weight: float = 0.2) -> jax.Array:
  """3D-GS training loss (1 - lambda) L1 + lambda (1 - SSIM), lambda = 0.2 (Kerbl et al. 2023,
  arXiv:2308.04079, Sec. 5.1, eq. 7).

  rendered, target: [H, W, 3].
  """
  return (1.0 - ssim_weight) * l1(rendered, target) + ssim_weight * (1.0 - metrics.ssim(rendered, target))


def distillation_loss(student: jax.Array, teacher: jax.Array) -> jax.Array:
  """L_kd = |G_w(P_m) - G_o(P_m)| (ConcealGS eq. 3): the student's render stays the teacher's.

  student, teacher: [H, W, 3] renders of one training pose P_m.
  """
  return l1(student, teacher)


def decoder_identity_loss(decoded: jax.Array, teacher: jax.Array) -> jax.Array:
  """L_d^- = |F(G_o(P_n)) - G_o(P_n)| (ConcealGS eq. 4): the decoder is the identity on normal views.

  decoded: F of the teacher render, teacher: that render, both [S, S, 3] at the decoder size.
  """
  return l1(decoded, teacher)


def hidden_image_loss(decoded: jax.Array, hidden: jax.Array) -> jax.Array:
  """L_d^+ = |F(G_w(P_c)) - I| (ConcealGS eq. 5): the decoder reveals I from the student's check view.

  decoded: F of the student's check-view render, hidden: I, both [S, S, 3].
  """
  return l1(decoded, hidden)
