"""Jitted steps over renders with a static pair capacity (splat.render's capacity contract).

A step built for pair capacity C returns its input state unchanged when one of its renders needed more
than C splat-tile pairs (`keep_unless_overflowed`), and reports `num_pairs`. `GrowingSteps` reads that
one scalar after every step; on overflow it grows C to the next bucket, builds (traces) the step again
and re-runs the same iteration, so no update ever comes from a truncated image. The capacity is shared by
every variant of the step (e.g. one per SH degree). It also shrinks: binning sorts the whole buffer, so a
capacity far above what the scene needs costs time on every step (a 5k-point random start needs 3x the
pairs that the trained scene does). Shrinking never changes an update, only the time it takes.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Hashable

import jax
import jax.numpy as jnp

from conceal_jax.splat import render as render_lib

# Every SHRINK_WINDOW steps, a capacity at least two buckets (a factor 2) above the window's largest need
# times SHRINK_HEADROOM shrinks to that bucket; the headroom keeps a growing scene from re-running often.
SHRINK_WINDOW = 200
SHRINK_HEADROOM = 1.25


def keep_unless_overflowed(overflowed: jax.Array, new_state: Any, old_state: Any) -> Any:
  """new_state, or old_state where a render overflowed its pair capacity (traced; a select per leaf)."""
  return jax.tree.map(lambda new, old: jnp.where(overflowed, old, new), new_state, old_state)


class GrowingSteps:
  """build(key, options) -> jitted step(state, *args) -> (state, stats with `num_pairs`); one built
  step per (key, pair capacity), re-run with a grown capacity when the pairs did not fit.

  options: the render options every step is built with; their pair_capacity may start as None, to be
  set by `grow` before the first call (e.g. from the first state's size, or a checkpoint's capacity).
  shrink_window: steps between shrink checks (see SHRINK_WINDOW); 0 never shrinks.
  """

  def __init__(self, build: Callable[[Hashable, render_lib.RenderOptions], Callable],
               options: render_lib.RenderOptions, shrink_window: int = SHRINK_WINDOW):
    self._build = build
    self.options = options
    self.shrink_window = shrink_window
    self._steps: dict = {}
    self.reruns = 0
    self.shrinks = 0
    self.last_capacities: list[int] = []  # the capacities the last call ran with (more than one on overflow)
    self._window_need, self._window_steps = 0, 0

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
    self.last_capacities = []
    while True:
      self.last_capacities.append(self.capacity)
      cache_key = (key, self.capacity)
      if cache_key not in self._steps:
        self._steps[cache_key] = self._build(key, self.options)
      state, stats = self._steps[cache_key](state, *args)
      needed = int(jax.device_get(stats["num_pairs"]))  # the one value read after every step
      if needed <= self.capacity:
        self._note(needed)
        return state, stats
      self.reruns += 1
      self.grow(needed)

  def _note(self, needed: int) -> None:
    self._window_need, self._window_steps = max(self._window_need, needed), self._window_steps + 1
    if not self.shrink_window or self._window_steps < self.shrink_window:
      return
    target = render_lib.capacity_bucket(int(self._window_need * SHRINK_HEADROOM))
    if 2 * target <= self.capacity:
      self.options = dataclasses.replace(self.options, pair_capacity=target)
      self.shrinks += 1
    self._window_need, self._window_steps = 0, 0
