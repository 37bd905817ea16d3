"""The shared training loop on a toy state: resume, finiteness check, log windows, trace counts."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from flax import struct

from conceal_jax.core import loop


@struct.dataclass
class ToyState:
  step: jax.Array
  x: jax.Array


def _toy(traces: loop.TraceCounter, blow_up_at: int = 0):
  """A state (step, x) whose step adds the iteration to x; loss is x, NaN from `blow_up_at` on."""
  def body(state, iteration):
    x = state.x + iteration
    loss = jnp.where((iteration >= blow_up_at) & (blow_up_at > 0), jnp.nan, x)
    return ToyState(step=state.step + 1, x=x), dict(loss=loss, psnr=-x)
  step = jax.jit(traces.wrap("toy_step", body), donate_argnums=0)
  fresh = lambda: ToyState(step=jnp.zeros((), jnp.int32), x=jnp.zeros(()))
  return step, fresh


def _run(tmp_path, traces, max_steps=None, blow_up_at=0, iterations=10, time_limit_min=0.0):
  step, fresh = _toy(traces, blow_up_at)
  settings = loop.LoopSettings(iterations=iterations, log_every=3, checkpoint_every=4, progress_bar=False,
                               time_limit_min=time_limit_min)
  return loop.run("toy", settings, str(tmp_path), init_state=fresh, restore_template=lambda meta: fresh(),
                  step=step, max_steps=max_steps)


def test_resumed_run_equals_an_uninterrupted_one(tmp_path):
  straight = _run(tmp_path / "a", loop.TraceCounter())
  stopped = _run(tmp_path / "b", loop.TraceCounter(), max_steps=5)
  assert not stopped.finished and int(stopped.state.step) == 5
  traces = loop.TraceCounter()
  resumed = _run(tmp_path / "b", traces)  # a stop checkpoints where it stops
  assert resumed.finished and resumed.start == 5
  assert float(resumed.state.x) == float(straight.state.x) == sum(range(1, 11))
  # log windows end at multiples of 3, at checkpoints (multiples of 4) and at the last step
  assert [h["step"] for h in straight.history] == [3, 4, 6, 8, 9, 10]
  assert [h["step"] for h in resumed.history] == [3, 4, 5, 6, 8, 9, 10]
  losses = {h["step"]: h["loss"] for h in resumed.history}
  assert all(losses[h["step"]] == h["loss"] for h in straight.history)
  assert resumed.timing()["timed_steps"] == straight.timing()["timed_steps"] == 10
  elapsed = [h["elapsed_s"] for h in straight.history]
  assert elapsed == sorted(elapsed) and elapsed[0] > 0
  assert traces.counts == {"toy_step": 1}, "one trace for the whole run: no silent re-traces"


def test_a_time_limit_stops_at_the_next_checkpoint_and_the_run_resumes(tmp_path, monkeypatch):
  clock = iter(range(0, 10_000, 30))  # every reading of the clock is 30 s after the last
  monkeypatch.setattr(loop.time, "perf_counter", lambda: float(next(clock)))
  stopped = _run(tmp_path, loop.TraceCounter(), time_limit_min=1.0)
  # steps 1-3 and 4 are two log windows (4 readings, 2 min): the limit has passed at the checkpoint of step 4
  assert stopped.timed_out and not stopped.finished and int(stopped.state.step) == 4
  resumed = _run(tmp_path, loop.TraceCounter(), time_limit_min=1.0)  # the limit counts from the resume
  assert resumed.start == 4 and int(resumed.state.step) == 8 and resumed.timed_out
  done = _run(tmp_path, loop.TraceCounter(), time_limit_min=1.0)
  assert done.finished and not done.timed_out and float(done.state.x) == sum(range(1, 11))


def test_step_devices_name_each_machine_that_ran_steps_once(tmp_path, monkeypatch):
  here = loop.device_name()
  assert here == f"{jax.devices()[0].platform}: {jax.devices()[0].device_kind}"
  _run(tmp_path, loop.TraceCounter(), max_steps=5)
  assert _run(tmp_path, loop.TraceCounter()).timing()["step_devices"] == [here], "a resume on the same device"
  assert _run(tmp_path, loop.TraceCounter()).step_devices == [here], "a finished run runs no step: unchanged"
  # a run started on another machine and resumed here names both, in order
  monkeypatch.setattr(loop, "device_name", lambda: "gpu: elsewhere")
  _run(tmp_path / "moved", loop.TraceCounter(), max_steps=4)
  monkeypatch.setattr(loop, "device_name", lambda: here)
  assert _run(tmp_path / "moved", loop.TraceCounter()).step_devices == ["gpu: elsewhere", here]


def test_non_finite_stats_stop_the_run_naming_the_step(tmp_path):
  with pytest.raises(FloatingPointError, match="toy diverged at step 3"):
    _run(tmp_path, loop.TraceCounter(), blow_up_at=2)


def test_a_psnr_of_plus_inf_is_an_identical_render_not_a_divergence():
  assert not loop.diverged(dict(loss=0.1, psnr=np.inf))
  assert loop.diverged(dict(loss=0.1, psnr=np.nan)) and loop.diverged(dict(loss=0.1, psnr=-np.inf))
  assert loop.diverged(dict(loss=np.inf, psnr=30.0)) and loop.diverged(dict(loss=np.nan))


def test_bad_loop_settings_are_rejected():
  for bad in (dict(iterations=0), dict(iterations=5, log_every=0), dict(iterations=5, checkpoint_every=-1)):
    with pytest.raises(ValueError, match="iterations and log_every"):
      loop.LoopSettings(**bad)
  for bad in (dict(time_limit_min=-1.0), dict(time_limit_min=5.0, checkpoint_every=0)):
    with pytest.raises(ValueError, match="time_limit_min"):
      loop.LoopSettings(iterations=5, **bad)
