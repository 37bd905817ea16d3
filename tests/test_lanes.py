"""Lanes (core.lanes, conceal.lanes_objective): the step's gradients computed as two lanes, side by side on
two host devices or in turn, are the gradients of the plain objective (objective.py)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from conceal_jax.conceal import conceal, lanes_objective, objective
from conceal_jax.conceal.augment import Augmentation
from conceal_jax.configs import default
from conceal_jax.core import lanes
from conceal_jax.gs import optimizer
from conceal_jax import RenderOptions
from tests.test_conceal import _objective_inputs

needs_two = pytest.mark.skipif(jax.local_device_count() < 2, reason="needs two devices (a host with >= 2 cores)")
OPTIONS = RenderOptions(tile_size=8, pair_capacity=4096, background=(1.0, 1.0, 1.0))


def test_resolve_checks_the_setting():
  assert lanes.resolve(1) == 1
  assert lanes.resolve(lanes.AUTO) == (2 if jax.default_backend() == "cpu" and jax.local_device_count() >= 2 else 1)
  for bad in (-1, 3, "2", 1.5):
    with pytest.raises(ValueError, match="conceal.lanes"):
      lanes.resolve(bad)
  assert lanes.lane_mesh(1) is None


@needs_two
def test_map_lanes_gives_each_lane_its_input_and_differentiates():
  """Lane i computes fn(shared, x_i) on device i; gradients flow to `shared` from both lanes."""
  mesh = lanes.lane_mesh(2)
  fn = lambda w, x: jnp.sum(jnp.sin(w * x))
  total = lambda w, m: sum(lanes.map_lanes(fn, w, [jnp.arange(3.0), jnp.arange(3.0) + 5], m))
  w = jnp.linspace(0.1, 0.9, 3)
  expected = jax.value_and_grad(total)(w, None)
  got = jax.jit(jax.value_and_grad(total), static_argnums=1)(lanes.replicate(w, mesh), mesh)
  np.testing.assert_allclose(got[0], expected[0], rtol=1e-6)
  np.testing.assert_allclose(got[1], expected[1], rtol=1e-6)


@needs_two
def test_map_lanes_returns_each_lanes_outputs_of_every_dtype_and_shape():
  """Outputs of mixed dtypes and shapes come back per lane, exactly (integers stay integers); the gradient
  reaches each lane's own input."""
  mesh = lanes.lane_mesh(2)
  fn = lambda w, x: dict(value=jnp.sum(w * x["a"]), image=jnp.outer(w, x["a"]), count=x["n"] * 3,
                         flag=(x["n"] > 4).astype(jnp.int32))
  inputs = [dict(a=jnp.arange(3.0), n=jnp.int32(2**24 + 1)), dict(a=jnp.arange(3.0) - 7, n=jnp.int32(5))]
  w = jnp.linspace(0.1, 0.9, 3)
  expected = [fn(w, x) for x in inputs]
  got = jax.jit(lambda w, xs: lanes.map_lanes(fn, w, xs, mesh))(lanes.replicate(w, mesh), inputs)
  for e, g in zip(expected, got):
    for name in e:
      assert g[name].dtype == e[name].dtype and g[name].shape == e[name].shape
      np.testing.assert_array_equal(np.asarray(g[name]), np.asarray(e[name]))
  second = lambda a, m: lanes.map_lanes(fn, w, [inputs[0], dict(inputs[1], a=a)], m)[1]["value"]
  np.testing.assert_allclose(jax.jit(jax.grad(second), static_argnums=1)(inputs[1]["a"], mesh), w, rtol=1e-6)


def reference_gradients(student, decoder, data, view, normal_view, s, distortion):
  """Student and L_d^+ decoder gradients of objective.student_objective, L_d^- gradient of
  decoder_identity_objective: the plain statement of what the lanes compute."""
  (total, aux), (g_student, g_plus) = jax.value_and_grad(objective.student_objective, argnums=(0, 1), has_aux=True)(
      student, decoder, data, view, s, OPTIONS, distortion)
  if s.identity_loss:
    inputs = objective.identity_inputs(data, normal_view, s, aux["identity_rgb"], distortion)
    minus, g_minus = jax.value_and_grad(objective.decoder_identity_objective)(decoder, inputs, s)
  else:
    minus, g_minus = 0.0, jax.tree.map(jnp.zeros_like, decoder)
  return dict(loss=total + minus, plus=aux["plus"], minus=minus, student_grad=g_student, plus_grad=g_plus,
              minus_grad=g_minus)


SETTINGS = {
    "ours": dict(identity_on_student=True, identity_on_teacher_check=True),
    "paper": dict(),
    "released": dict(variant="released", identity_on_student=True),
    "no_consistency": dict(consistency=False),
    "no_decoder": dict(use_decoder=False),
    "distorted": dict(identity_on_student=True, augmentation=Augmentation(blur_max=1.5, noise_max=0.05)),
    "identity_distorted": dict(identity_on_student=True, augmentation=Augmentation(blur_max=1.5, noise_max=0.05),
                               identity_distorted=True),
    # brightness and contrast alone are a distortion of both lanes' images
    "photometric": dict(identity_on_student=True, augmentation=Augmentation(brightness_max=0.1, contrast_max=0.2),
                        identity_distorted=True),
    # the decoder normalises what it reads, clipped to [0, 1], in both lanes
    "standardized": dict(identity_on_student=True, identity_on_teacher_check=True, decoder_input_norm="standardize",
                         decoder_clip_input=True,
                         augmentation=Augmentation(blur_max=1.5), identity_distorted=True),
    # the model perturbation reaches the check lane only, also where lane 0's image is distorted
    "perturbed": dict(identity_on_student=True, identity_distorted=True,
                      augmentation=Augmentation(blur_max=1.5, noise_max=0.05, dropout_max=0.5, param_noise_max=0.1)),
    # ... and lane 0's L_d^- reads a second render, of the perturbed student
    "identity_perturbed": dict(identity_on_student=True, identity_on_teacher_check=True, identity_distorted=True,
                               augmentation=Augmentation(blur_max=1.5, dropout_max=0.5, param_noise_max=0.1),
                               identity_perturbed=True),
}
DISTORTION = dict(blur=np.float32(0.8), noise=np.float32(0.03), seed=np.uint32(7), dropout=np.float32(0.3),
                  param_noise=np.float32(0.05), model_seed=np.uint32(11), brightness=np.float32(-0.08),
                  contrast=np.float32(1.15))


@pytest.mark.parametrize("row", sorted(SETTINGS))
def test_lane_gradients_are_the_objectives(row):
  student, decoder, data = _objective_inputs()
  s = objective.ConcealSettings(decoder_width=4, hidden_size=16, weight_kd=0.7, weight_plus=2.0, weight_minus=1.5,
                                weight_check=0.5, **SETTINGS[row])
  decoder = decoder if s.use_decoder else {}
  distortion = DISTORTION if s.augmentation.draws else None
  expected = reference_gradients(student, decoder, data, 1, 2, s, distortion)
  # Side by side only where the lanes' data differ most (the program is the same for every row).
  two = jax.local_device_count() >= 2 and row in ("ours", "identity_perturbed")
  meshes = [None] + ([lanes.lane_mesh(2)] if two else [])
  for mesh in meshes:
    fn = jax.jit(lambda *a: lanes_objective.gradients(*a, s, OPTIONS, distortion, mesh))
    got = fn(*lanes.replicate((student, decoder, data), mesh), 1, 2)
    np.testing.assert_allclose(got["normal"] + got["check"] + got["minus"], expected["loss"], rtol=1e-5)
    np.testing.assert_allclose(got["plus"], expected["plus"], rtol=1e-5)
    np.testing.assert_allclose(got["minus"], expected["minus"], rtol=1e-5)
    # the decoder polish's lanes (no render backward) give the same decoder gradients and values
    polish = jax.jit(lambda *a: lanes_objective.gradients(*a, s, OPTIONS, distortion, mesh, student_grad=False))
    decoder_only = polish(*lanes.replicate((student, decoder, data), mesh), 1, 2)
    assert decoder_only["student_grad"] is None
    np.testing.assert_allclose(decoder_only["minus"], got["minus"], rtol=1e-6)
    for name in ("student_grad", "plus_grad", "minus_grad"):
      for a, b in zip(jax.tree.leaves(got[name]), jax.tree.leaves(expected[name])):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6 * float(np.max(np.abs(b)) + 1e-12), err_msg=name)
    for name in ("plus_grad", "minus_grad"):
      jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-9), decoder_only[name], got[name])


@needs_two
def test_conceal_step_on_two_lanes_matches_one():
  """Two steps of the guided ConcealGS update (state donated) on two lanes and on one: the same student,
  decoder and statistics."""
  student, decoder, data = _objective_inputs()
  s = objective.ConcealSettings(decoder_width=4, hidden_size=16, identity_on_student=True,
                                identity_on_teacher_check=True)
  student_tx = optimizer.gaussian_optimizer(default.get_config().conceal.lr, 1.0, 100)
  decoder_tx = optax.adam(1e-3)
  results = []
  for mesh in (None, lanes.lane_mesh(2)):
    step = conceal.make_conceal_step(s, OPTIONS, student_tx, decoder_tx, mesh=mesh)
    fresh = jax.tree.map(jnp.array, (student, decoder))  # the step donates its buffers
    state = lanes.replicate(conceal.create_conceal_state(*fresh, student_tx, decoder_tx), mesh)
    placed = lanes.replicate(data, mesh)
    for view, normal_view in ((0, 1), (1, 2)):
      state, stats = step(state, placed, view, normal_view)
    results.append((jax.device_get(state), jax.device_get(stats)))
  (one, one_stats), (two, two_stats) = results
  assert int(two.step) == 2 and np.isfinite(two_stats["loss"])
  for a, b in zip(jax.tree.leaves((one.student, one.decoder)), jax.tree.leaves((two.student, two.decoder))):
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-7)
  for name in one_stats:
    np.testing.assert_allclose(two_stats[name], one_stats[name], rtol=1e-5, atol=1e-7)
