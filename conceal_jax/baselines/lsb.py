"""LSB steganography, the ConcealGS paper's "LSB" baseline (Yang et al. 2025, arXiv:2501.03605, Tables 1-2):
the hidden image is written into the `bits` least significant bits of every 8-bit channel of the training
views and read back from the low bits of a render.

With b bits, a channel of the hidden image is stored as one of 2^b levels, so the round trip on exact 8-bit
images recovers it to within 1 / (2 (2^b - 1)), and a container differs from its cover by at most 2^b - 1
levels of 255. Pure functions, jittable.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from conceal_jax.baselines import containers as containers_lib
from conceal_jax.conceal import reveal

BITS_RANGE = (1, 4)


def check_bits(bits: int) -> int:
  """`bits` if it is an int in BITS_RANGE; ValueError naming baseline.lsb_bits otherwise."""
  if isinstance(bits, bool) or not isinstance(bits, int) or not BITS_RANGE[0] <= bits <= BITS_RANGE[1]:
    raise ValueError(f"baseline.lsb_bits must be an integer in {BITS_RANGE[0]}..{BITS_RANGE[1]}, got {bits!r}")
  return bits


def embed(images, secret, bits: int) -> jax.Array:
  """Containers [V, H, W, 3] float32 on 8-bit levels: each of `images` ([V, H, W, 3] in [0, 1], quantised
  to 8 bits first) with its low `bits` bits replaced by `secret` ([H, W, 3] in [0, 1]) quantised to
  2^bits levels."""
  check_bits(bits)
  top = 2**bits - 1
  covers = containers_lib.to_levels(images)
  payload = jnp.round(jnp.clip(jnp.asarray(secret, jnp.float32), 0.0, 1.0) * top).astype(jnp.int32)
  if payload.shape != covers.shape[1:]:
    raise ValueError(f"secret {payload.shape} must have the views' shape {covers.shape[1:]}")
  return containers_lib.from_levels((covers & ~top) | payload[None])


def extract(renders, bits: int) -> jax.Array:
  """[..., H, W, 3] images in [0, 1] -> [..., H, W, 3]: their low `bits` bits after 8-bit quantisation,
  rescaled to [0, 1]."""
  top = 2**check_bits(bits) - 1
  return (containers_lib.to_levels(renders) & top).astype(jnp.float32) / top


@functools.partial(jax.jit, static_argnames=("bits", "size"))
def reveal_lsb(renders: jax.Array, bits: int, size: int) -> jax.Array:
  """Renders [V, H, W, 3] -> revealed images [V, size, size, 3] in [0, 1]: the low bits, resized as the
  ConcealGS decoder's input is (reveal.resize_for_decoder)."""
  return jnp.clip(reveal.resize_for_decoder(extract(renders, bits), size), 0.0, 1.0)


def lsb_reveal(bits: int, size: int):
  """The reveal function of LSB with `bits` bits (renders [V, H, W, 3] -> [V, size, size, 3]), for
  conceal.evaluate_concealment."""
  return functools.partial(reveal_lsb, bits=check_bits(bits), size=size)
