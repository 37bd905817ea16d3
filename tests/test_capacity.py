"""Steps over a static pair capacity: an overflowing step keeps its state, and GrowingSteps re-runs it with
the next bucket, so the update equals one computed with ample capacity."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax import RenderOptions, render
from conceal_jax.configs import demo
from conceal_jax.gs import capacity, optimizer, train
from conceal_jax.splat import camera as camera_lib
from tests.helpers import make_camera, random_gaussians


def _setup():
  g = jax.tree.map(np.asarray, random_gaussians(3, 300, degree=0, log_scale=(-0.8, -0.5), spread=0.4))
  camera = make_camera(64, 48)
  options = RenderOptions(tile_size=8, background=(1.0, 1.0, 1.0))
  needed = int(render(jax.tree.map(jnp.asarray, g), camera, options).num_pairs)
  image = jnp.full((1, 48, 64, 3), 0.3)
  tx = optimizer.gaussian_optimizer(demo.get_config().train.lr, 1.0)
  return g, camera, options, needed, image, tx


def test_overflowing_step_is_re_run_with_a_grown_capacity():
  g, camera, options, needed, image, tx = _setup()
  small = dataclasses.replace(options, pair_capacity=1024)
  assert needed > 1024, "the scene must need more pairs than the smallest bucket"
  cameras = camera_lib.stack([camera])
  built = []

  def build(key, opts):
    built.append(opts.pair_capacity)
    return train.make_train_step(tx, opts, 0.2)

  steps = capacity.GrowingSteps(build, small)
  state, stats = steps(0, train.create_train_state(g, tx), image, cameras, 0)
  assert steps.reruns == 1 and built == [1024, steps.capacity] and steps.capacity >= needed
  assert steps.last_capacities == [1024, steps.capacity]
  assert int(state.step) == 1 and int(stats["num_pairs"]) == needed

  ample = dataclasses.replace(options, pair_capacity=steps.capacity * 2)
  reference, _ = train.make_train_step(tx, ample, 0.2)(train.create_train_state(g, tx), image, cameras, 0)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7), state.gaussians,
               reference.gaussians)


def test_capacity_shrinks_to_what_a_window_needed_and_grows_back():
  """A fake step reporting a chosen need: the capacity falls once a window needed far less, and an
  overflow after that re-runs the step with a grown capacity as before."""
  built = []

  def build(key, opts):
    built.append(opts.pair_capacity)
    return lambda state, need: (state + 1, dict(num_pairs=jnp.asarray(need)))

  steps = capacity.GrowingSteps(build, RenderOptions(pair_capacity=65536), shrink_window=3)
  state = 0
  for need in (5000, 6000, 4000):
    state, _ = steps(None, state, need)
  # 6000 * 1.25 = 7500 -> bucket 8192, at least two sqrt(2) buckets below 65536
  assert steps.capacity == 8192 and steps.shrinks == 1 and steps.reruns == 0
  state, stats = steps(None, state, 10_000)
  assert steps.reruns == 1 and steps.capacity >= 10_000 and state == 5  # the overflowing call ran twice
  assert steps.last_capacities == [8192, steps.capacity]
  for need in (9000, 9000):
    state, _ = steps(None, state, need)
  assert steps.shrinks == 1  # 9000 * 1.25 needs about the current bucket: no thrashing
  assert built == [65536, 8192, steps.capacity]


def test_a_step_that_overflows_returns_its_state_unchanged():
  g, camera, options, needed, image, tx = _setup()
  step = train.make_train_step(tx, dataclasses.replace(options, pair_capacity=1024), 0.2)
  before = train.create_train_state(g, tx)
  expected = jax.tree.map(np.array, before)  # the step donates `before`
  after, stats = step(before, image, camera_lib.stack([camera]), 0)
  assert int(stats["num_pairs"]) == needed > 1024
  jax.tree.map(np.testing.assert_array_equal, jax.tree.map(np.asarray, after), expected)
