"""Per-pixel alpha of a 2D Gaussian and front-to-back alpha compositing (3D-GS eq. 3, REFERENCE s.4).

Transmittance is tracked as a log (a running sum of log(1 - alpha)), which is finite for every alpha
<= ALPHA_MAX and turns the front-to-back product into a cumulative sum that batches over a chunk of
splats. The 3D-GS rules are kept exactly: alpha is clamped at 0.99, splats with alpha < 1/255 are
skipped, and a pixel stops before the first splat that would take its transmittance below 1e-4.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)


@struct.dataclass
class Accumulator:
  """Running front-to-back state of P pixels.

  log_t_seen: [P] sum of log(1 - alpha) over every splat met so far, stopped or not; monotone, so the
    stop test "would T fall below 1e-4" is a comparison of its running value with log(1e-4).
  log_t: [P] log transmittance over the splats actually composited.
  values: [P, C] colour (and optionally depth) accumulated so far.
  """
  log_t_seen: jax.Array
  log_t: jax.Array
  values: jax.Array

  @classmethod
  def empty(cls, pixel_shape: tuple[int, ...], channels: int, dtype) -> "Accumulator":
    zeros = jnp.zeros(pixel_shape, dtype)
    return cls(log_t_seen=zeros, log_t=zeros, values=jnp.zeros(pixel_shape + (channels,), dtype))


def gaussian_alpha(pixels: jax.Array, means2d: jax.Array, conics: jax.Array,
                   opacities: jax.Array) -> jax.Array:
  """alpha = min(0.99, o exp(-0.5 d^T Sigma'^-1 d)), 0 where skipped (3D-GS eq. 2-3).

  pixels: [P, 2]; means2d: [K, 2]; conics: [K, 3] (A, B, C); opacities: [K] -> alpha [P, K].
  A positive exponent can only come from rounding in a near-singular conic; it is skipped, as in 3D-GS.
  """
  d = pixels[:, None, :] - means2d[None, :, :]
  dx, dy = d[..., 0], d[..., 1]
  power = -0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) - conics[:, 1] * dx * dy
  alpha = jnp.minimum(ALPHA_MAX, opacities * jnp.exp(jnp.minimum(power, 0.0)))
  return jnp.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)


def composite_chunk(acc: Accumulator, alpha: jax.Array, values: jax.Array) -> Accumulator:
  """Composites K depth-sorted splats behind what `acc` holds.

  alpha: [P, K] (0 for skipped splats); values: [K, C] per-splat values (colour, optionally depth).
  """
  log_1m = jnp.log1p(-alpha)
  seen = acc.log_t_seen[:, None] + jnp.cumsum(log_1m, axis=-1)
  # T only decreases, so "not stopped yet" is the prefix where T after this splat stays >= 1e-4. Every
  # splat before a kept one was kept too, so its transmittance is the seen one: one prefix sum suffices.
  keep = seen >= LOG_T_MIN
  weights = jnp.where(keep, alpha * jnp.exp(seen - log_1m), 0.0)
  return Accumulator(log_t_seen=seen[:, -1], log_t=acc.log_t + jnp.sum(jnp.where(keep, log_1m, 0.0), -1),
                     values=acc.values + weights @ values)
