"""A guard against the decoder's collapse (beyond the paper; conceal.decoder_opt.rollback_*).

The U-Net decoder has no normalisation layers; trained with Adam it can die late in a run: within a few steps its
updates grow several times over, its ReLUs stop passing signal, L_d^+ returns to its value for a constant output,
and the vanishing gradient of a dead network does not bring it back (while the student, pulled by L_d^+, loses
render quality). The guard needs no cause: it keeps a copy of the decoder and its optimiser state taken at least
`every` steps back while L_d^+ stayed near its running mean, and returns to it at the first step whose L_d^+
exceeds `factor` times that mean. The run goes on from there with the next steps' draws.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
from flax import struct


@dataclasses.dataclass(frozen=True)
class Rollback:
  """factor: an L_d^+ above factor times its running mean is a collapse; every: steps between snapshots (the one
  returned to is every to 2 * every steps old); decay: the running mean's per-step decay."""
  factor: float
  every: int
  decay: float = 0.99


def rollback_settings(decoder_opt: ml_collections.ConfigDict) -> Rollback | None:
  """conceal.decoder_opt.rollback_factor (0: no guard, else > 1) and rollback_every (a positive count), checked."""
  factor, every = decoder_opt.rollback_factor, decoder_opt.rollback_every
  if not factor:
    return None
  if not (factor > 1 and isinstance(every, int) and every > 0):
    raise ValueError("conceal.decoder_opt.rollback_factor must be 0 (off) or > 1, and rollback_every a positive "
                     f"number of steps, got {factor} and {every}")
  return Rollback(float(factor), every)


@struct.dataclass
class Guard:
  """good: the (decoder, decoder_opt) returned to at a collapse; candidate: the snapshot that becomes `good` once
  `every` steps have passed without one; plus_mean: the running mean of L_d^+ (inf before the first step); since:
  steps since the candidate was taken; rollbacks: int32 count of the returns so far."""
  good: Any
  candidate: Any
  plus_mean: jax.Array
  since: jax.Array
  rollbacks: jax.Array


def init_guard(decoder, decoder_opt) -> Guard:
  """The step-0 guard: both snapshots the starting decoder and optimiser state (copies: the step donates its
  buffers)."""
  snapshot = lambda: jax.tree.map(jnp.copy, (decoder, decoder_opt))
  return Guard(good=snapshot(), candidate=snapshot(), plus_mean=jnp.asarray(jnp.inf, jnp.float32),
               since=jnp.zeros((), jnp.int32), rollbacks=jnp.zeros((), jnp.int32))


def collapsed(rollback: Rollback, guard: Guard, plus: jax.Array) -> jax.Array:
  """Whether a step's L_d^+ `plus` (a scalar) marks a collapse: above `factor` times the running mean."""
  return plus > rollback.factor * guard.plus_mean


def guarded_update(rollback: Rollback, guard: Guard, decoder, decoder_opt, plus: jax.Array):
  """(decoder, decoder_opt, guard) after a step: the step's updated decoder and optimiser state, or at a collapse
  (`plus`, the step's L_d^+, read with the decoder before its update) the good snapshot's. Traced: no branch."""
  bad = collapsed(rollback, guard, plus)
  pick = lambda flag, a, b: jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)
  current = pick(bad, guard.good, (decoder, decoder_opt))
  mean = jnp.where(jnp.isinf(guard.plus_mean), plus, rollback.decay * guard.plus_mean + (1 - rollback.decay) * plus)
  since = jnp.where(bad, 0, guard.since + 1)
  promote = since >= rollback.every
  guard = Guard(good=pick(promote, guard.candidate, guard.good),
                candidate=pick(bad | promote, current, guard.candidate),
                plus_mean=jnp.where(bad, guard.plus_mean, mean).astype(jnp.float32),
                since=jnp.where(promote, 0, since).astype(jnp.int32),
                rollbacks=guard.rollbacks + bad.astype(jnp.int32))
  return (*current, guard)
