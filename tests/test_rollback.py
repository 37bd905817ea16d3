"""The decoder's rollback guard (conceal/rollback.py): which snapshot it returns to, when, and inside the step."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import pytest

from conceal_jax.conceal import rollback, step as step_lib
from conceal_jax.configs import default
from conceal_jax.gs import optimizer
from tests.test_objective import OPTIONS, objective_inputs, settings

GUARD = rollback.Rollback(factor=4.0, every=3)


def run_guard(pluses, guard_settings=GUARD):
  """The guard over a scalar 'decoder' that each step's update raises by 1 and an 'optimiser state' that follows it
  (-decoder): the decoders after each step and the final guard."""
  decoder, opt = jnp.float32(0), jnp.float32(0)
  guard, out = rollback.init_guard(decoder, opt), []
  update = jax.jit(lambda g, d, o, p: rollback.guarded_update(guard_settings, g, d, o, p))
  for plus in pluses:
    decoder, opt, guard = update(guard, decoder + 1, -(decoder + 1), jnp.float32(plus))
    assert float(opt) == -float(decoder)  # returned together with its decoder
    out.append(float(decoder))
  return out, guard


def test_a_collapse_returns_to_the_snapshot_every_to_twice_every_steps_back():
  """Snapshots at steps 3, 6, 9 (every = 3), each the good one `every` steps later: the collapse at step 10 returns
  to step 6's decoder, and the run goes on from it; the collapsed step leaves the running mean alone."""
  pluses = [0.1] * 9 + [10.0] + [0.1] * 2
  decoders, guard = run_guard(pluses)
  assert decoders == [1, 2, 3, 4, 5, 6, 7, 8, 9, 6, 7, 8]
  assert int(guard.rollbacks) == 1
  np.testing.assert_allclose(float(guard.plus_mean), 0.1, rtol=1e-6)


def test_a_falling_loss_and_its_noise_never_roll_back():
  """L_d^+ falling from its start (the running mean starts at the first value) and noise within `factor` of the
  mean: no return."""
  rng = np.random.default_rng(0)
  pluses = list(0.5 * 0.9 ** np.arange(40)) + list(0.01 * rng.uniform(0.3, 3.0, 200))
  decoders, guard = run_guard(pluses)
  assert decoders == list(range(1, 241)) and int(guard.rollbacks) == 0


def test_repeated_collapses_return_to_the_last_good_snapshot_each_time():
  """Two collapses in a row go back to the same snapshot (the collapsed decoder is never taken as one)."""
  decoders, guard = run_guard([0.1] * 6 + [9.0, 9.0, 0.1])
  assert decoders == [1, 2, 3, 4, 5, 6, 3, 3, 4] and int(guard.rollbacks) == 2


@pytest.mark.parametrize("factor, every", [(1.0, 100), (0.5, 100), (4.0, 0), (4.0, 2.5)])
def test_bad_rollback_settings_name_their_keys(factor, every):
  section = ml_collections.ConfigDict(dict(rollback_factor=factor, rollback_every=every))
  with pytest.raises(ValueError, match="rollback_factor"):
    rollback.rollback_settings(section)


def test_the_default_has_no_guard():
  assert rollback.rollback_settings(default.get_config().conceal.decoder_opt) is None


def test_the_guarded_step_returns_a_collapsed_decoder_to_its_snapshot():
  """In the jitted step: with a guard whose running mean of L_d^+ lies far below this step's, the decoder and its
  Adam state come back as the snapshot (the student still takes its step); with the mean far above, the step is
  the unguarded step."""
  student, decoder, data = objective_inputs()
  s = settings(identity_on_student=True)
  student_tx = optimizer.gaussian_optimizer(default.get_config().conceal.lr, 1.0, 100)
  decoder_tx = optax.adam(1e-3)
  guard = rollback.Rollback(4.0, 10)
  fresh = lambda guarded: step_lib.create_state(*jax.tree.map(jnp.array, (student, decoder)), student_tx,
                                                decoder_tx, rollback=guard if guarded else None)
  plain, stats = step_lib.make_step(s, OPTIONS, student_tx, decoder_tx)(fresh(False), data, 1, 2)
  plain = jax.device_get(plain)
  guarded_step = step_lib.make_step(s, OPTIONS, student_tx, decoder_tx, rollback=guard)
  for mean, collapses in ((float(stats["plus"]) / 10, True), (float(stats["plus"]) * 10, False)):
    state = fresh(True)
    state = state.replace(guard=state.guard.replace(plus_mean=jnp.float32(mean)))
    new, guarded_stats = guarded_step(state, data, 1, 2)
    new = jax.device_get(new)
    assert int(guarded_stats["rollbacks"]) == int(collapses)
    expected = (decoder, jax.device_get(decoder_tx.init(decoder))) if collapses else (plain.decoder,
                                                                                       plain.decoder_opt)
    jax.tree.map(np.testing.assert_array_equal, (new.decoder, new.decoder_opt), expected)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-8), new.student, plain.student)
