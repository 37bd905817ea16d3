"""The ConcealGS objective (objective.py), the views of a step (views.py) and the guided step (step.py):
each term against the paper's equations assembled by hand, the gradients against those of the
pre-redesign step (tests/data/conceal_step_golden.npz), and the views split over two devices against one."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from conceal_jax import RenderOptions, render
from conceal_jax.conceal import augment, carrier, decoder_pair, key as key_lib, objective, reveal, step as step_lib
from conceal_jax.conceal import unet, views as views_lib
from conceal_jax.conceal.augment import Augmentation
from conceal_jax.conceal.settings import ConcealSettings
from conceal_jax.configs import default
from conceal_jax.core import parallel
from conceal_jax.gs import init, losses, optimizer
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat.camera import Camera, look_at
from tests.helpers import golden_arrays, sketch

OPTIONS = RenderOptions(tile_size=8, pair_capacity=4096, background=(1.0, 1.0, 1.0))
needs_two = pytest.mark.skipif(jax.local_device_count() < 2, reason="needs two devices (tests/conftest.py)")


def objective_inputs(size=16, width=4, views=3, hw=(20, 24)):
  """A random student, decoder and ConcealData with one key, the last camera (the shapes build_data makes)."""
  rng = np.random.default_rng(0)
  student = init.gaussians_from_points(rng.uniform(-0.5, 0.5, (60, 3)), rng.uniform(0, 1, (60, 3)), sh_degree=0,
                                       opacity=0.6)
  cameras = [Camera.from_fov(look_at([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0]), 0.8, hw[1], hw[0])
             for a in np.linspace(0, 2, views)]
  images = jnp.asarray(rng.uniform(0, 1, (views,) + hw + (3,)), jnp.float32)
  teacher = jnp.asarray(rng.uniform(0, 1, (views,) + hw + (3,)), jnp.float32)
  hidden = jnp.asarray(rng.uniform(0, 1, (size, size, 3)), jnp.float32)
  keys = key_lib.stack_keys([cameras[-1]], [hidden], [images[-1]], [reveal.resize_for_decoder(teacher[-1], size)])
  data = views_lib.ConcealData(images=images, teacher=teacher, teacher_small=reveal.resize_for_decoder(teacher, size),
                               cameras=camera_lib.stack(cameras), keys=keys)
  return student, unet.init_decoder(jax.random.key(0), width, size), data


@functools.partial(jax.jit, static_argnames=("s", "options"))  # one program, not one per operation
def terms_of(student, decoder, views, s, options=OPTIONS):
  return jax.vmap(objective.view_terms, in_axes=(None, None, None, 0, None, None))(student, decoder, decoder, views, s,
                                                                                   options)


def settings(**kw):
  return ConcealSettings(decoder_width=4, hidden_size=16, **kw)


@pytest.mark.parametrize("variant", ["paper", "released"])
def test_view_terms_are_the_papers_terms(variant):
  """The normal view: L_kd (eq. 3) against the teacher's render, or the 3D-GS loss against ground truth; the
  check view: lambda+ L_d^+ (eq. 5) and the released L1 to its image; lambda- L_d^- (eq. 4) on the teacher's
  render of the step's other normal view (paper) or on its check render (released)."""
  student, decoder, data = objective_inputs()
  s = settings(variant=variant, weight_kd=0.7, weight_plus=2.0, weight_check=0.5, weight_minus=3.0)
  terms = terms_of(student, decoder, views_lib.step_views(data, 1, 2, 0, None, s), s)
  rgb = render(student, jax.tree.map(lambda x: x[1], data.cameras), OPTIONS).rgb
  check = render(student, data.keys.at(0).camera, OPTIONS).rgb
  plus = jnp.mean(jnp.abs(reveal.decode(decoder, 4, reveal.resize_for_decoder(check, 16)) - data.keys.hidden[0]))
  teacher = data.teacher_small[2] if variant == "paper" else data.keys.teacher_check[0]
  minus = 3.0 * jnp.mean(jnp.abs(reveal.decode(decoder, 4, teacher) - teacher))
  if variant == "paper":
    normal, check_pixel = 0.7 * jnp.mean(jnp.abs(rgb - data.teacher[1])), 0.0
  else:
    normal = losses.photometric_loss(rgb, data.images[1])
    check_pixel = 0.5 * jnp.mean(jnp.abs(check - data.keys.check_image[0]))
  np.testing.assert_allclose(terms.student, [normal, check_pixel], rtol=1e-5, atol=1e-7)
  np.testing.assert_allclose(terms.plus, [0.0, 2.0 * plus], rtol=1e-5)
  np.testing.assert_allclose(jnp.sum(terms.minus), minus, rtol=1e-5)


def test_identity_on_student_adds_the_students_render_as_a_constant():
  """With identity_on_student, L_d^- is the mean of the teacher's and the student's identity errors, and no
  gradient reaches the student through it."""
  student, decoder, data = objective_inputs()
  s = settings(identity_on_student=True)
  views = views_lib.step_views(data, 1, 2, 0, None, s)
  minus_of = lambda g: jnp.sum(terms_of(g, decoder, views, s).minus)
  small = reveal.resize_for_decoder(render(student, jax.tree.map(lambda x: x[1], data.cameras), OPTIONS).rgb, 16)
  teacher = data.teacher_small[2]
  expected = 0.5 * (jnp.mean(jnp.abs(reveal.decode(decoder, 4, teacher) - teacher))
                    + jnp.mean(jnp.abs(reveal.decode(decoder, 4, small) - small)))
  np.testing.assert_allclose(minus_of(student), expected, rtol=1e-5)
  assert all(float(jnp.abs(g).max()) == 0 for g in jax.tree.leaves(jax.grad(minus_of)(student)))


def test_views_carry_each_terms_weight_and_distortion():
  """identity_on_teacher_check adds the teacher's check render to L_d^- (paper; the released variant reads only
  it); identity_distorted reads the normal render through the step's distortion, which always reaches the check
  view, as the model perturbation does."""
  _, _, data = objective_inputs()
  both = views_lib.step_views(data, 1, 2, 0, None, settings(identity_on_teacher_check=True, weight_minus=2.0))
  np.testing.assert_allclose(both.teacher_minus_weight, [1.0, 1.0])
  released = views_lib.step_views(data, 1, 2, 0, None, settings(variant="released", identity_on_teacher_check=True))
  np.testing.assert_allclose(released.teacher_minus_weight, [0.0, 1.0])
  distortion = augment.draw(np.random.default_rng(0), Augmentation(blur_max=1.5, dropout_max=0.3))
  for distorted in (False, True):
    s = settings(identity_on_student=True, augmentation=Augmentation(blur_max=1.5, dropout_max=0.3),
                 identity_distorted=distorted)
    views = views_lib.step_views(data, 1, 2, 0, distortion, s)
    assert float(views.image["blur"][0]) == (float(distortion["blur"]) if distorted else 0.0)
    assert float(views.image["blur"][1]) == float(distortion["blur"]) and float(views.model["dropout"][0]) == 0.0
    assert float(views.model["dropout"][1]) == float(distortion["dropout"])
  with pytest.raises(ValueError, match="identity_distorted"):
    settings(identity_on_student=True, identity_distorted=True)


def test_a_step_trains_the_key_it_is_given():
  """With two keys, step_views at key k (traced: one trace for both) gives the views of a run whose only key
  is k."""
  student, decoder, data = objective_inputs()
  other = key_lib.stack_keys([jax.tree.map(lambda x: x[0], data.cameras)], [1.0 - data.keys.hidden[0]],
                             [data.images[0]], [data.teacher_small[0]])
  two = data.replace(keys=jax.tree.map(lambda a, b: jnp.concatenate([a, b]), data.keys, other))
  s = settings(variant="released", identity_on_teacher_check=True)
  traced = []

  @jax.jit
  def at_key(k):
    traced.append(k)
    return terms_of(student, decoder, views_lib.step_views(two, 1, 2, k, None, s), s)

  for k, single in ((0, data), (1, data.replace(keys=other))):
    expected = terms_of(student, decoder, views_lib.step_views(single, 1, 2, 0, None, s), s)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7), at_key(k), expected)
  assert len(traced) == 1


# The pre-redesign step's rows (tests/data/conceal_step_golden.npz): its gradients at views (1, 2), and its state
# and statistics after two guided steps at views (0, 1) and (1, 2).
GOLDEN_ROWS = {
    "ours": dict(identity_on_student=True, identity_on_teacher_check=True),
    "paper": dict(),
    "released": dict(variant="released", identity_on_student=True),
    "no_consistency": dict(consistency=False),
    "no_decoder": dict(use_decoder=False),
    "distorted": dict(identity_on_student=True, augmentation=Augmentation(blur_max=1.5, noise_max=0.05)),
    "identity_distorted": dict(identity_on_student=True, augmentation=Augmentation(blur_max=1.5, noise_max=0.05),
                               identity_distorted=True),
    "photometric": dict(identity_on_student=True, augmentation=Augmentation(brightness_max=0.1, contrast_max=0.2),
                        identity_distorted=True),
    "standardized": dict(identity_on_student=True, identity_on_teacher_check=True,
                         reading=reveal.Reading("standardize", True), augmentation=Augmentation(blur_max=1.5),
                         identity_distorted=True),
    "perturbed": dict(identity_on_student=True, identity_distorted=True,
                      augmentation=Augmentation(blur_max=1.5, noise_max=0.05, dropout_max=0.5, param_noise_max=0.1)),
}
DISTORTION = dict(blur=np.float32(0.8), noise=np.float32(0.03), seed=np.uint32(7), dropout=np.float32(0.3),
                  param_noise=np.float32(0.05), model_seed=np.uint32(11), brightness=np.float32(-0.08),
                  contrast=np.float32(1.15))


def golden_settings(row):
  return settings(weight_kd=0.7, weight_plus=2.0, weight_minus=1.5, weight_check=0.5, **GOLDEN_ROWS[row])


# Rows whose code paths the others cover too: compiled only by `make test-slow`.
SLOW_ROWS = ("paper", "distorted", "identity_distorted", "no_consistency", "photometric", "released", "no_decoder")


@pytest.mark.parametrize("row", [pytest.param(r, marks=pytest.mark.slow) if r in SLOW_ROWS else r
                                 for r in sorted(GOLDEN_ROWS)])
def test_gradients_are_the_pre_redesign_steps(row):
  """The student's gradient and the two decoder gradient pytrees, and the loss values, as the step computed
  them before the objective was written once; finite."""
  golden = golden_arrays(row)
  student, decoder, data = objective_inputs()
  s = golden_settings(row)
  decoder = decoder if s.use_decoder else {}
  distortion = DISTORTION if s.augmentation.draws else None
  views = views_lib.step_views(data, 1, 2, 0, distortion, s)
  grads, terms = jax.jit(lambda st, d, v: step_lib.gradients(st, d, v, s, OPTIONS))(student, decoder, views)
  np.testing.assert_allclose(jnp.sum(terms.student + terms.plus + terms.minus), golden["loss"], rtol=1e-5)
  np.testing.assert_allclose(terms.plus[1] / s.weight_plus, golden["plus"], rtol=1e-5)
  np.testing.assert_allclose(jnp.sum(terms.minus), golden["minus"], rtol=1e-5, atol=1e-8)
  for name in ("student", "plus", "minus"):
    got, want = jax.tree.leaves(grads[name]), golden[f"{name}_grad"]
    assert len(got) == len(want), name
    for i, (a, b) in enumerate(zip(got, want)):
      assert np.all(np.isfinite(a)), name
      np.testing.assert_allclose(sketch(a, i), b, rtol=2e-4, atol=1e-6 * float(b[0]) + 1e-12, err_msg=name)


def test_the_gradient_of_the_trained_colours_alone_is_the_whole_gradients():
  """With colour_rows, the student's gradient is taken with respect to those rows' base colours only: the same
  values as those entries of the gradient with respect to the whole student, and the same decoder gradients."""
  student, decoder, data = objective_inputs()
  s = golden_settings("ours")
  views = views_lib.step_views(data, 1, 2, 0, None, s)
  rows = carrier.colour_rows(40, 20)
  run = jax.jit(lambda st, d, v, r: step_lib.gradients(st, d, v, s, OPTIONS, colour_rows=r))
  (whole, whole_terms), (part, part_terms) = run(student, decoder, views, None), run(student, decoder, views, rows)
  assert part["student"].shape == (20, 3) and np.any(np.asarray(part["student"]) != 0)
  np.testing.assert_allclose(part["student"], whole["student"].sh[40:, 0], rtol=1e-6, atol=1e-12)
  for name in ("plus", "minus"):
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(np.max(np.abs(b))))
    jax.tree.map(close, part[name], whole[name])  # the same sums, up to float order (cancelling entries)
  np.testing.assert_allclose(part_terms.student, whole_terms.student, rtol=1e-6)


def test_adam_of_the_colours_alone_moves_them_as_over_the_whole_student():
  """gaussian_optimizer(colours_only): three updates of base colours [F, 3] bit for bit those of the same rows'
  DC terms under the whole student's Adam, given no gradient elsewhere (warm-up included)."""
  student, _, _ = objective_inputs()
  rows = carrier.colour_rows(40, 20)
  lr, rng = default.get_config().conceal.lr, np.random.default_rng(3)
  whole_tx, colour_tx = (optimizer.gaussian_optimizer(lr, 2.0, 100, colours) for colours in (False, True))
  whole, colours = student, student.sh[rows, 0]
  whole_state, colour_state = whole_tx.init(whole), colour_tx.init(colours)
  for _ in range(3):
    g = jnp.asarray(rng.normal(size=(20, 3)), jnp.float32)
    full = carrier.with_colours(jax.tree.map(jnp.zeros_like, whole), rows, g)
    updates, whole_state = jax.jit(whole_tx.update)(full, whole_state, whole)
    whole = optax.apply_updates(whole, updates)
    updates, colour_state = jax.jit(colour_tx.update)(g, colour_state, colours)
    colours = optax.apply_updates(colours, updates)
  np.testing.assert_array_equal(np.asarray(colours), np.asarray(whole.sh[rows, 0]))
  assert not np.array_equal(np.asarray(colours), np.asarray(student.sh[rows, 0]))


@pytest.mark.parametrize("row", ["ours", pytest.param("released", marks=pytest.mark.slow),
                                 pytest.param("perturbed", marks=pytest.mark.slow)])
def test_two_guided_steps_are_the_pre_redesign_steps(row):
  """Two steps of the guided update (state donated): the student, decoder and statistics the step gave before.
  Row 'ours' also runs the step's two views on two devices: the same state and statistics as on one."""
  golden = golden_arrays(row)
  student, decoder, data = objective_inputs()
  s = golden_settings(row)
  student_tx = optimizer.gaussian_optimizer(default.get_config().conceal.lr, 1.0, 100)
  decoder_tx = optax.adam(1e-3)
  distortion = DISTORTION if s.augmentation.draws else None
  results = []
  two = row == "ours" and jax.local_device_count() >= 2
  for mesh in (None, parallel.batch_mesh(2)) if two else (None,):
    step = step_lib.make_step(s, OPTIONS, student_tx, decoder_tx, mesh)
    state = parallel.replicate(step_lib.create_state(*jax.tree.map(jnp.array, (student, decoder)), student_tx,
                                                     decoder_tx), mesh)
    placed = parallel.replicate(data, mesh)
    for view, normal_view in ((0, 1), (1, 2)):
      state, stats = step(state, placed, view, normal_view, 0, distortion)
    results.append(jax.device_get((state.student, state.decoder, stats)))
  state_leaves, stats = jax.tree.leaves(results[0][:2]), results[0][2]
  for i, (a, b) in enumerate(zip(state_leaves, golden["state"])):
    np.testing.assert_allclose(sketch(a, i), b, rtol=1e-4, atol=1e-6 * float(b[0]) + 1e-9)
  for name in ("loss", "normal", "plus", "minus", "psnr", "num_pairs", "mean_guidance_weight"):
    np.testing.assert_allclose(stats[name], golden["stats"][name], rtol=1e-5, err_msg=name)
  for other in results[1:]:
    jax.tree.map(lambda a, b: np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-7), results[0], other)


@pytest.mark.parametrize("reading", [reveal.PAPER_READING, reveal.Reading("center", False)])
def test_batched_decoder_pair_is_the_two_reads(reading):
  """The step's batch of two decoder reads: the values of l1_of_decoded_pair and, under unequal cotangents, the
  gradient of each read in its own decoder argument, and those of the images and targets."""
  rng = np.random.default_rng(3)
  images, targets = (jnp.asarray(rng.uniform(0, 1, (2, 16, 16, 3)), jnp.float32) for _ in range(2))
  decoder = unet.init_decoder(jax.random.key(1), 4, 16)
  weights = jnp.asarray([2.0, -0.7])
  for use_decoder in (True, False):
    s = settings(reading=reading, use_decoder=use_decoder)
    params = decoder if use_decoder else {}
    each = [objective.l1_of_decoded(params, images[i], targets[i], s) for i in range(2)]
    for read in (objective.l1_of_decoded_pair, decoder_pair.batched_l1_of_decoded_pair):
      np.testing.assert_allclose(read((params, params), images, targets, s), each, rtol=1e-6)
    loss = lambda read: lambda a, b, i, t: jnp.sum(weights * read((a, b), i, t, s))
    want = jax.grad(loss(objective.l1_of_decoded_pair), argnums=(0, 1, 2, 3))(params, params, images, targets)
    got = jax.jit(jax.grad(loss(decoder_pair.batched_l1_of_decoded_pair), argnums=(0, 1, 2, 3)))(
        params, params, images, targets)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-8), got, want)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(got))


@needs_two
def test_map_reduce_over_two_devices_is_the_one_device_result():
  """Sums add up and kept values come back in batch order, of every dtype, with gradients through the sum."""
  fn = lambda w, x: ((jnp.sum(jnp.sin(w * x["a"])), w * x["a"]), dict(n=x["n"] * 3, v=jnp.sum(x["a"])))
  batch = dict(a=jnp.arange(6.0).reshape(2, 3), n=jnp.array([2**24 + 1, 5], jnp.int32))
  w = jnp.linspace(0.1, 0.9, 3)
  mesh = parallel.batch_mesh(2)
  one, two = (jax.jit(lambda w, b, m=m: parallel.map_reduce_over_batch(fn, w, b, m))(w, batch) for m in (None, mesh))
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), one, two)
  assert two[1]["n"].dtype == jnp.int32 and list(two[1]["n"]) == [3 * (2**24 + 1), 15]
  grad = lambda m: jax.grad(lambda w: parallel.map_reduce_over_batch(fn, w, batch, m)[0][0])(w)
  np.testing.assert_allclose(jax.jit(lambda w: grad(mesh))(w), grad(None), rtol=1e-6)
