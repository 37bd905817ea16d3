"""The one training loop every job that steps a state runs through (3D-GS teachers, concealment, and
later baselines and fine-tuning attacks): resume from the newest checkpoint, a tqdm bar with loss and
PSNR, periodic logging with a finiteness check, checkpoints, `max_steps`, and step timing measured over
each log window (the device is synchronised only where stats are read, not after every step).

A job supplies what differs: a fresh state, the template a checkpoint fills, the step, and optional
hooks. Trace counting (`TraceCounter`) lets jobs record how often each jitted step was traced.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import time
from typing import Any, Callable

import jax
import numpy as np
from absl import logging
from tqdm import tqdm

from conceal_jax.core import checkpoint

CHECKPOINT_DIR = "checkpoints"
State = Any  # a pytree with an int32 `step` field (a flax.struct dataclass)


@dataclasses.dataclass(frozen=True)
class LoopSettings:
  """iterations: total steps of the run; log_every: steps per log window (stats read, timing taken);
  checkpoint_every: steps between checkpoints (0: none); progress_bar: show tqdm;
  time_limit_min: stop at the first checkpoint after this many minutes of this process's loop (0: no limit),
    for a machine lent for a fixed time; running again resumes there."""
  iterations: int
  log_every: int = 10
  checkpoint_every: int = 1000
  progress_bar: bool = True
  time_limit_min: float = 0.0

  def __post_init__(self):
    if self.iterations < 1 or self.log_every < 1 or self.checkpoint_every < 0:
      raise ValueError(f"iterations and log_every must be >= 1 and checkpoint_every >= 0, got {self}")
    if self.time_limit_min < 0 or (self.time_limit_min and not self.checkpoint_every):
      raise ValueError(f"time_limit_min must be >= 0 and needs checkpoints (checkpoint_every > 0), got {self}")


@dataclasses.dataclass
class LoopResult:
  """state: after the last step run; history: one dict per log window (and per hook result), each with
  the step and `elapsed_s`, the step time up to it;
  start: the step the run resumed from; finished: whether all iterations are done;
  timed_out: whether it stopped at a checkpoint because time_limit_min had passed;
  windows: [(steps, seconds)] of every log window, over resumes too;
  step_devices: the devices that ran steps, in order, over resumes too (`device_name`; a run resumed on another
    machine has two), so a wall time is read against the device that took it."""
  state: State
  history: list[dict]
  start: int
  finished: bool
  windows: list[tuple[int, float]]
  step_devices: list[str] = dataclasses.field(default_factory=list)
  timed_out: bool = False

  def timing(self) -> dict:
    """Timed steps, wall time of the steps, the median over log windows of the mean step time, and the
    devices that took them."""
    steps = sum(n for n, _ in self.windows)
    return dict(timed_steps=steps, wall_time_s=float(sum(s for _, s in self.windows)),
                median_step_s=median_step_s(self.windows), step_devices=self.step_devices)


def median_step_s(windows) -> float | None:
  """The median over log windows [(steps, seconds)] (LoopResult.windows, a checkpoint's meta) of the mean step
  time; None without a timed step."""
  per_step = [s / n for n, s in windows if n]
  return float(np.median(per_step)) if per_step else None


def device_name() -> str:
  """'platform: kind' of the default device, e.g. 'cpu: cpu' or 'gpu: NVIDIA H100 80GB HBM3'."""
  device = jax.devices()[0]
  return f"{device.platform}: {device.device_kind}"


class TraceCounter:
  """Counts how many times each named function is traced (its Python body runs only when jax traces)."""

  def __init__(self):
    self.counts: collections.Counter = collections.Counter()

  def wrap(self, name: str, fn: Callable) -> Callable:
    def counted(*args, **kwargs):
      self.counts[name] += 1
      return fn(*args, **kwargs)
    return counted


def diverged(stats: dict[str, float]) -> bool:
  """Whether a window's stats show a diverged run: a NaN, or an infinite value other than a PSNR of +inf (a render
  identical to its target, as a carrier film run's normal views are to the teacher's)."""
  return any(np.isnan(v) or (np.isinf(v) and not (k == "psnr" and v > 0)) for k, v in stats.items())


def run(name: str, settings: LoopSettings, workdir: str, *, init_state: Callable[[], State],
        restore_template: Callable[[dict], State], step: Callable[[State, int], tuple[State, dict]],
        after_window: Callable[[State, int], dict | None] | None = None,
        checkpoint_meta: Callable[[State], dict] | None = None, postfix_keys: tuple[str, ...] = (),
        max_steps: int | None = None, after_restore: Callable[[State], State] | None = None) -> LoopResult:
  """Runs steps start+1 .. min(iterations, max_steps) (1-based iterations) of `step(state, iteration)`.

  init_state: the step-0 state, built only when there is no checkpoint.
  restore_template: a state of the right structure for a checkpoint's meta (the job's own meta keys).
  step: returns (state, stats); stats must hold scalar `loss` and `psnr`; every value is checked finite
    at the end of each log window.
  after_window: called after log windows (outside the timing) with (state, iteration); a returned dict
    is added to the history (e.g. a periodic test PSNR).
  checkpoint_meta: extra JSON meta to save with a checkpoint (e.g. the buffer capacity).
  postfix_keys: stats besides loss and psnr to show on the bar.
  after_restore: applied once to a state restored from a checkpoint (e.g. to start state that checkpoint lacks).
  """
  ckpt_dir = os.path.join(workdir, CHECKPOINT_DIR)
  latest = checkpoint.load_latest(ckpt_dir)
  if latest is None:
    state, history, windows, step_devices = init_state(), [], [], []
  else:
    path, meta, leaves = latest
    logging.info("%s: resuming from %s", name, path)
    state = jax.tree.map(jax.numpy.asarray, checkpoint.restore(restore_template(meta), leaves, path))
    state = after_restore(state) if after_restore else state
    history, windows = meta["history"], [tuple(w) for w in meta.get("windows", [])]
    step_devices = list(meta.get("step_devices", []))  # absent from checkpoints written before it was kept
  start = int(jax.device_get(state.step))
  end = settings.iterations if max_steps is None else min(settings.iterations, max_steps)
  if end > start and step_devices[-1:] != [device_name()]:
    step_devices.append(device_name())
  bar = tqdm(total=settings.iterations, initial=start, desc=name, dynamic_ncols=True,
             disable=not settings.progress_bar)
  began = window_start = time.perf_counter()
  window_steps, timed_out, last = 0, False, start
  for iteration in range(start + 1, end + 1):
    state, stats = step(state, iteration)
    last = iteration
    window_steps += 1
    bar.update(1)
    checkpoint_now = settings.checkpoint_every and (iteration % settings.checkpoint_every == 0 or iteration == end)
    if iteration % settings.log_every and iteration != end and not checkpoint_now:
      continue
    stats = {k: float(v) for k, v in jax.device_get(stats).items()}  # waits for the window's steps
    windows.append((window_steps, time.perf_counter() - window_start))
    if diverged(stats):
      raise FloatingPointError(f"{name} diverged at step {iteration}: {stats}")
    # elapsed_s: step time so far (over resumes, without hooks and checkpoints), for accuracy-vs-time curves
    elapsed = float(sum(s for _, s in windows))
    history.append(dict(step=iteration, elapsed_s=elapsed, **stats))
    bar.set_postfix({k: f"{stats[k]:.4g}" for k in ("loss", "psnr") + tuple(postfix_keys) if k in stats})
    extra = after_window(state, iteration) if after_window else None
    if extra:
      history.append(dict(step=iteration, elapsed_s=elapsed, **extra))
    if checkpoint_now:
      meta = dict(history=history, windows=windows, step_devices=step_devices,
                  **(checkpoint_meta(state) if checkpoint_meta else {}))
      checkpoint.save(ckpt_dir, iteration, state, meta)
      timed_out = iteration < end and time_up(settings, began)
      if timed_out:
        logging.info("%s: time limit of %g min reached at step %d", name, settings.time_limit_min, iteration)
        break
    window_start, window_steps = time.perf_counter(), 0
  bar.close()
  return LoopResult(state=state, history=history, start=start, finished=last == settings.iterations, windows=windows,
                    step_devices=step_devices, timed_out=timed_out)


def time_up(settings: LoopSettings, began: float) -> bool:
  """Whether the loop has run past settings.time_limit_min since `began` (a perf_counter reading)."""
  return bool(settings.time_limit_min) and time.perf_counter() - began > 60.0 * settings.time_limit_min

