"""Jitted steps over renders with a static pair capacity (splat.render's capacity contract).

A step built for pair capacity C returns its input state unchanged when one of its renders needed more
than C splat-tile pairs (`keep_unless_overflowed`), and reports `num_pairs`. `GrowingSteps` reads that
one scalar after every step; on overflow it grows C to the next bucket, builds (traces) the step again
and re-runs the same iteration, so no update ever comes from a truncated image. The capacity only grows,
and is shared by every variant of the step (e.g. one per SH degree).
"""
from __future__ import annotations

from typing import Any, Callable, Hashable

import jax
import jax.numpy as jnp

from conceal_jax.splat import render as render_lib


def keep_unless_overflowed(overflowed: jax.Array, new_state: Any, old_state: Any) -> Any:
  """new_state, or old_state where a render overflowed its pair capacity (traced; a select per leaf)."""
  return jax.tree.map(lambda new, old: jnp.where(overflowed, old, new), new_state, old_state)


class GrowingSteps:
  """build(key, options) -> jitted step(state, *args) -> (state, stats with `num_pairs`); one built
  step per (key, pair capacity), re-run with a grown capacity when the pairs did not fit.

  options: the render options every step is built with; their pair_capacity may start as None, to be
  set by `grow` before the first call (e.g. from the first state's size, or a checkpoint's capacity).
  """

  def __init__(self, build: Callable[[Hashable, render_lib.RenderOptions], Callable],
               options: render_lib.RenderOptions):
    self._build = build
    self.options = options
    self._steps: dict = {}
    self.reruns = 0

  @property
  def capacity(self) -> int | None:
    return self.options.pair_capacity

  def grow(self, needed: int) -> None:
    """Makes the capacity at least the bucket holding `needed` pairs (never shrinks it)."""
    if self.capacity is None or needed > self.capacity:
      self.options = render_lib.grow_capacity(self.options, max(needed, self.capacity or 0, 1))

  def __call__(self, key: Hashable, state, *args):
    if self.capacity is None:
      raise ValueError("GrowingSteps: call grow() with a first capacity before running a step")
    while True:
      cache_key = (key, self.capacity)
      if cache_key not in self._steps:
        self._steps[cache_key] = self._build(key, self.options)
      state, stats = self._steps[cache_key](state, *args)
      needed = int(jax.device_get(stats["num_pairs"]))  # the one value read after every step
      if needed <= self.capacity:
        return state, stats
      self.reruns += 1
      self.grow(needed)
