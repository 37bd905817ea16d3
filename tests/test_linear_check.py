"""conceal.linear_check: a check render read through its linear map is the render, values and gradient in the
film's colours, in every geometry state (the student, each of the converter's merged levels); a step that draws
8-bit grids renders; which runs have fixed states; which state a step's check view reads."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import augment, grouping, linear_check, objective, perturb, subsets, train as conceal_train
from conceal_jax.conceal import settings as settings_lib, step, views as views_lib
from conceal_jax.splat import linear
from tests.test_conceal import tiny, tiny_config  # noqa: F401  (the module-scoped scene fixture)
from tests.test_subsets import OPTIONS, scene, view  # noqa: F401  (the module-scoped scene fixture)

ATTACKS = augment.Augmentation(quantize_fraction=0.5, merge_fraction=0.5, merge_groups="converter")


def test_which_runs_read_their_check_renders_through_fixed_maps():
  assert linear_check.states(ATTACKS) == 3  # the student, its 50% and 80% levels
  assert linear_check.states(augment.Augmentation()) == 1
  assert linear_check.states(dataclasses.replace(ATTACKS, merge_scales=(0.5, 1.0))) == 5
  for fresh in (dict(dropout_max=0.1), dict(param_noise_max=0.1), dict(prune_small_max=0.1), dict(reset_fraction=0.5),
                dict(merge_groups="nearest")):
    assert linear_check.states(dataclasses.replace(ATTACKS, **fresh)) == 0


def test_the_check_render_through_its_map_is_the_render_in_every_state(scene):
  student, offset, _, key, decoys = scene
  film = np.arange(student.num) >= offset
  cameras = [key, decoys[0]]
  rows = subsets.view_rows(student, cameras, OPTIONS, film, np.zeros(2, bool))
  merges = grouping.training_merges(jax.tree.map(np.asarray, student), offset, ATTACKS)
  check = linear_check.check_weights(student, cameras, rows, merges, OPTIONS, linear_check.states(ATTACKS))
  assert check.weights.shape == (6, linear_check.LENGTH_STEP) and check.num_pairs.shape == (6,)
  dc = student.sh[offset:, 0] * 0.5 + 0.1  # colours other than those the maps were read with
  weights = jax.random.uniform(jax.random.key(1), (32, 32, 3))

  @jax.jit
  def image(dc, distortion, camera, reading, state):
    moved = student.replace(sh=student.sh.at[offset:, 0].set(dc))
    perturbed = lambda g, rows: perturb.perturb_gaussians(g, distortion, ATTACKS, merges, rows)
    seen = view(camera, reading).replace(weights=jax.tree.map(lambda x: x[jnp.maximum(state, 0)], check),
                                        linear=state >= 0)
    out = objective.rendered(moved, seen, OPTIONS, perturbed)
    return out.rgb, out.num_pairs

  loss = lambda *args: jnp.sum(weights * image(*args)[0])
  grad = jax.jit(jax.grad(loss))
  for k, camera in enumerate(cameras):
    for level in range(3):
      for quantize in (0.0, 1.0):
        distortion = dict(augment.draw(np.random.default_rng(level), ATTACKS), merge=np.float32(level),
                          quantize=np.float32(quantize))
        args = (dc, distortion, camera, jnp.asarray(rows[k]))
        state = jnp.int32(k * 3 + level if quantize == 0 else -1)
        (want, pairs), (got, got_pairs) = image(*args, jnp.int32(-1)), image(*args, state)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=2e-6, rtol=0)
        assert int(got_pairs) == int(pairs) > 0
        want_grad, got_grad = np.asarray(grad(*args, jnp.int32(-1))), np.asarray(grad(*args, state))
        assert np.all(np.isfinite(got_grad)) and np.any(want_grad != 0)
        np.testing.assert_allclose(got_grad, want_grad, atol=1e-5 * np.abs(want_grad).max(), rtol=0)


def test_a_check_view_reads_its_keys_merged_level_unless_it_draws_8_bit_grids():
  data = views_lib.ConcealData(images=None, teacher=None, teacher_small=None, cameras=None,
                               keys=type("Keys", (), {"hidden": jnp.zeros((2, 8, 8, 3))})(),
                               check_weights=linear.ColourWeights(None, None, None, None, jnp.zeros(6, jnp.int32)))
  state = lambda key, merge, quantize: int(views_lib.check_state(data, key, dict(merge=np.float32(merge),
                                                                                 quantize=np.float32(quantize))))
  assert [state(0, 0, 0), state(0, 2, 0), state(1, 0, 0), state(1, 2, 0)] == [0, 2, 3, 5]
  assert state(1, 2, 1) == -1


def test_a_steps_gradients_through_the_maps_are_the_rendered_ones(tiny):
  """The step's gradients (the film's colours, both decoder pytrees) with the check views read through their maps are
  those of the renders, for a plain, a merged and an 8-bit check render, in a run whose film the key sees."""
  config = tiny_config(tiny, key_kind="unseen", **{"carrier.film": True, "carrier.spacing": 4.0,
                                                   "attacks.merge_fraction": 0.7, "attacks.quantize_fraction": 0.3,
                                                   "attacks.merge_groups": "converter"})
  plan = settings_lib.plan(config)
  run = conceal_train.prepare(config, plan)
  assert run.data.check_weights is not None
  s, film = plan.settings, run.data.colour_rows
  student = jax.tree.map(jnp.asarray, run.start)  # film colours of an image: a blank one standardizes to noise
  student = student.replace(sh=student.sh.at[film, 0].set(jax.random.normal(jax.random.key(0), (film.size, 3))))
  decoder = conceal_train.initial_decoder(config, s)

  @jax.jit
  def grads(data, distortion):
    views = views_lib.step_views(data, 0, 0, 0, distortion, s)
    return step.gradients(student, decoder, views, s, run.options, None, True, data.merges, data.colour_rows)[0]

  for merge, quantize in ((0, 0), (2, 0), (1, 1)):
    distortion = dict(augment.draw(np.random.default_rng(merge), s.augmentation), merge=np.float32(merge),
                      quantize=np.float32(quantize))
    want, got = grads(run.data.replace(check_weights=None), distortion), grads(run.data, distortion)
    for name in ("student", "plus", "minus"):
      for a, b in zip(jax.tree.leaves(got[name]), jax.tree.leaves(want[name])):
        b = np.asarray(b)
        assert np.all(np.isfinite(a)) and (name == "minus" or np.any(b != 0))
        np.testing.assert_allclose(np.asarray(a), b, atol=1e-4 * np.abs(b).max(), rtol=0, err_msg=name)


def test_the_normal_views_maps_cover_the_views_that_render_within_the_budget(scene):
  student, offset, cameras, key, decoys = scene
  film = np.arange(student.num) >= offset
  views = [cameras[0], decoys[0], decoys[1]]
  fixed = np.array([True, False, False])
  rows = subsets.view_rows(student, views, OPTIONS, film, fixed)
  weights, index = linear_check.normal_weights(student, views, rows, fixed, OPTIONS, 64.0)
  assert np.asarray(index).tolist() == [-1, 0, 1] and weights.weights.shape[0] == 2
  longer = linear_check.lengthened(weights, weights.weights.shape[1] + linear_check.LENGTH_STEP)
  assert longer.weights.shape == (2, weights.weights.shape[1] + linear_check.LENGTH_STEP)
  for camera, k in ((decoys[0], 0), (decoys[1], 1)):
    want = objective.rendered(student, view(camera, jnp.asarray(rows[k + 1])), OPTIONS).rgb
    for maps in (weights, longer):
      seen = view(camera, jnp.asarray(rows[k + 1])).replace(weights=jax.tree.map(lambda x, k=k: x[k], maps),
                                                            linear=jnp.bool_(True))
      np.testing.assert_allclose(np.asarray(objective.rendered(student, seen, OPTIONS).rgb), np.asarray(want),
                                 atol=2e-6, rtol=0)
  assert linear_check.normal_weights(student, views, rows, fixed, OPTIONS, 0.01) == (None, None)
  assert linear_check.normal_weights(student, views, rows, np.ones(3, bool), OPTIONS, 64.0) == (None, None)


def test_a_steps_gradients_through_the_normal_views_maps_are_the_rendered_ones(tiny):
  """With decoys, a step whose normal view is a decoy read through its map has the gradients of its render (the
  film's colours, both decoder pytrees), with its check view read through its map or rendered (8-bit); a training
  view's render stays the teacher's."""
  config = tiny_config(tiny, key_kind="unseen", decoy_views=3, decoy_fraction=0.9,
                       **{"carrier.film": True, "carrier.spacing": 4.0, "attacks.quantize_fraction": 0.3,
                          "identity_on_student": True})
  plan = settings_lib.plan(config)
  run = conceal_train.prepare(config, plan)
  data = run.data
  num_views = data.images.shape[0]
  assert data.normal_weights is not None and data.normal_weights.weights.shape[0] == 3
  assert np.asarray(data.normal_maps).tolist() == [-1] * num_views + [0, 1, 2]
  assert data.normal_weights.weights.shape[1] == data.check_weights.weights.shape[1]  # the two views stack
  s, film = plan.settings, data.colour_rows
  student = jax.tree.map(jnp.asarray, run.start)
  student = student.replace(sh=student.sh.at[film, 0].set(jax.random.normal(jax.random.key(0), (film.size, 3))))
  decoder = conceal_train.initial_decoder(config, s)

  @jax.jit
  def grads(data, normal, distortion):
    views = views_lib.step_views(data, normal, 0, 0, distortion, s)
    return step.gradients(student, decoder, views, s, run.options, None, True, data.merges, data.colour_rows)[0]

  rendered = data.replace(normal_weights=None, normal_maps=None, check_weights=None)
  for normal, quantize in ((num_views + 1, 0), (num_views + 2, 1), (0, 0)):
    distortion = dict(augment.draw(np.random.default_rng(normal), s.augmentation), quantize=np.float32(quantize))
    want, got = grads(rendered, normal, distortion), grads(data, normal, distortion)
    for name in ("student", "plus", "minus"):
      for a, b in zip(jax.tree.leaves(got[name]), jax.tree.leaves(want[name])):
        b = np.asarray(b)
        assert np.all(np.isfinite(a)) and (name == "minus" or np.any(b != 0))
        np.testing.assert_allclose(np.asarray(a), b, atol=1e-4 * np.abs(b).max(), rtol=0, err_msg=name)
