"""conceal.subsets: a view rendered from the rows that reach it is the whole student's render, bit for bit, with
the same gradient to the film's colours, through the check render's attacks too (8-bit colours, resets, the
converter's merges); a fixed view is its held image, not rendered."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import augment, carrier, grouping, key as key_lib, near, objective, perturb, subsets
from conceal_jax.conceal.views import NO_DISTORTION
from conceal_jax.gs import init
from conceal_jax.splat.camera import Camera, look_at
from conceal_jax.splat.gaussians import concatenate
from conceal_jax.splat.render import render
from tests.test_carrier import OPTIONS, hemisphere_cameras

OPTIONS = dataclasses.replace(OPTIONS, pair_capacity=1 << 14)
ATTACKS = augment.Augmentation(quantize_fraction=0.5, reset_fraction=0.5, merge_fraction=0.5, prune_small_max=0.3,
                               dropout_max=0.3, merge_groups="converter")


@pytest.fixture(scope="module")
def scene():
  """A random teacher, an unseen film with trained-looking colours, its training cameras, key and two decoys
  (which see the film alone)."""
  cameras = hemisphere_cameras()
  points, colors = init.random_box_points(np.random.default_rng(1), 400, 1.0)
  teacher = jax.tree.map(jnp.asarray, init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5))
  key = key_lib.unseen_camera(cameras, seed=1)
  film = carrier.unseen_film(teacher, key, cameras, OPTIONS, 0.1 * key_lib.camera_distance(cameras), 2.0, 0.5,
                             layers=2)
  film = film.replace(sh=film.sh.at[:, 0].set(jax.random.normal(jax.random.key(0), film.sh[:, 0].shape)))
  student = concatenate([teacher, film])
  decoys = near.decoy_cameras(key, 1.0, 2, (0.05, 0.3), (5.0, 30.0), seed=0)
  return student, teacher.num, cameras, key, decoys


def view(camera, rows, fixed=False, fixed_rgb=None, model=NO_DISTORTION):
  zero = jnp.float32(0.0)
  image = jnp.zeros((camera.height, camera.width, 3)) if fixed_rgb is None else fixed_rgb
  return objective.View(camera=camera, target=image, l1_weight=zero, photometric_weight=zero, model=model,
                        image=NO_DISTORTION, hidden=jnp.zeros((8, 8, 3)), plus_weight=zero, own_minus_weight=zero,
                        teacher_small=jnp.zeros((8, 8, 3)), teacher_minus_weight=zero, rows=rows,
                        fixed=None if rows is None else jnp.bool_(fixed), fixed_rgb=image)


def test_the_rows_that_reach_a_view_render_it_and_its_gradient_bit_for_bit(scene):
  student, offset, cameras, key, decoys = scene
  film = np.arange(student.num) >= offset
  narrow = Camera.from_fov(look_at([0.0, -4.0, 1.0], [0.6, 0.0, 0.3]), 0.25, 32, 32)  # sees part of the teacher
  views = [key, decoys[1], narrow]
  rows = subsets.view_rows(student, views, OPTIONS, film, np.zeros(len(views), bool))
  assert np.all(np.diff(rows, axis=1) >= 0) and 0 < np.sum(rows[2] < offset) < offset
  merges = grouping.training_merges(jax.tree.map(np.asarray, student), offset, ATTACKS)
  draws = [dict(augment.draw(np.random.default_rng(seed), ATTACKS), merge=np.float32(level))
           for seed, level in ((0, 0.0), (2, 2.0))]
  dc = student.sh[offset:, 0]

  @jax.jit
  def image(dc, distortion, camera, reading):
    moved = student.replace(sh=student.sh.at[offset:, 0].set(dc))
    perturbed = lambda g, rows: perturb.perturb_gaussians(g, distortion, ATTACKS, merges, rows)
    return objective.rendered(moved, view(camera, reading), OPTIONS, perturbed).rgb  # of its rows alone with them

  weights = jax.random.uniform(jax.random.key(1), (32, 32, 3))
  grad = jax.jit(jax.grad(lambda *args: jnp.sum(weights * image(*args))))
  for camera, reading in zip(views, jnp.asarray(rows)):
    for distortion in draws:
      whole, part = image(dc, distortion, camera, None), image(dc, distortion, camera, reading)
      np.testing.assert_array_equal(np.asarray(part), np.asarray(whole))
      whole_grad = np.asarray(grad(dc, distortion, camera, None))
      np.testing.assert_array_equal(np.asarray(grad(dc, distortion, camera, reading)), whole_grad)
      assert np.all(np.isfinite(whole_grad)) and np.any(whole_grad != 0) == (camera is not narrow)


def test_a_fixed_view_is_its_held_image_and_reads_no_row(scene):
  student, offset, cameras, _, _ = scene
  film = np.arange(student.num) >= offset
  rows = subsets.view_rows(student, cameras[:2], OPTIONS, film, np.array([True, False]))
  assert np.all(rows[0] == student.num) and np.any(rows[1] < student.num)
  held = render(student, cameras[0], OPTIONS).rgb
  out = objective.rendered(student, view(cameras[0], jnp.asarray(rows[0]), True, held), OPTIONS)
  np.testing.assert_array_equal(np.asarray(out.rgb), np.asarray(held))
  assert int(out.num_pairs) == 0
  gathered = subsets.gather(student, jnp.asarray(rows[0]))
  assert gathered.num == rows.shape[1] and np.all(np.isnan(np.asarray(gathered.means)))


@pytest.mark.parametrize("noise", [0.0, 0.2])
def test_a_perturbed_subset_is_those_rows_of_the_perturbed_student(scene, noise):
  """perturb_gaussians of `rows` alone: bit for bit those rows of the whole student perturbed (every attack drawn,
  merges at both levels and none), the rows past the end NaN; with parameter noise too (its spread is over all), to
  the last bit of the largest value (a multiply-add rounded once or twice, as the compiler fuses it)."""
  student, offset, _, key, _ = scene
  attacks = dataclasses.replace(ATTACKS, param_noise_max=noise)
  merges = grouping.training_merges(jax.tree.map(np.asarray, student), offset, attacks)
  rows = jnp.asarray(np.concatenate([np.arange(0, student.num, 3), [student.num] * 5]), jnp.int32)
  real = np.asarray(rows) < student.num
  both = jax.jit(lambda d: (perturb.perturb_gaussians(student, d, attacks, merges),
                            perturb.perturb_gaussians(student, d, attacks, merges, rows)))
  for seed, level in ((0, 0.0), (1, 1.0), (2, 2.0)):
    drawn = dict(augment.draw(np.random.default_rng(seed), attacks), merge=np.float32(level), quantize=np.float32(1),
                 reset=np.float32(seed % 2))
    whole, part = both(drawn)
    for field in perturb.MODEL_FIELDS:
      got, want = np.asarray(getattr(part, field)), np.asarray(getattr(whole, field))[np.asarray(rows)[real]]
      if noise:  # x + noise * spread: XLA may fuse it into one rounding (FMA) in one program and two in the other
        bound = 2 * np.finfo(np.float32).eps * np.abs(want).max()
        np.testing.assert_allclose(got[real], want, rtol=0, atol=bound, err_msg=field)
      else:
        np.testing.assert_array_equal(got[real], want, err_msg=field)
    assert np.all(np.isnan(np.asarray(part.means)[~real]))
