"""The carrier film (conceal/carrier.py): placed before an unseen key, no normal view depends on it, concealing into
it leaves the teacher's Gaussians exactly as they were, and fine-tuning on the training views leaves it exactly."""
from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import carrier, key as key_lib, subsets, train as conceal_train
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, init, optimizer, train as gs_train
from conceal_jax.splat.camera import Camera, look_at, orbit_eye
from conceal_jax.splat.gaussians import concatenate, quaternion_to_rotation
from conceal_jax.splat.render import RenderOptions, render
from tests import helpers
from tests.test_conceal import tiny, tiny_config  # noqa: F401  (the module-scoped scene fixture)

OPTIONS = RenderOptions(background=(1.0, 1.0, 1.0), tile_size=8)


def hemisphere_cameras(count=12, size=32):
  """Cameras on the upper hemisphere (elevations 15-65 degrees) looking at the origin."""
  rng = np.random.default_rng(0)
  eyes = orbit_eye((0.0, 0.0, 0.0), 4.0, rng.uniform(0, 2 * np.pi, count), np.radians(rng.uniform(15, 65, count)))
  return [Camera.from_fov(look_at(eye, np.zeros(3)), 0.75, size, size) for eye in eyes]


def test_the_unseen_key_looks_away_from_every_camera():
  cameras = hemisphere_cameras()
  direction = key_lib.unseen_direction(cameras)
  assert direction[2] > 0.95  # up, where cameras looking down do not look
  key = key_lib.unseen_camera(cameras, seed=3)
  forward = np.asarray(key.world_to_camera, np.float64)[2, :3]
  np.testing.assert_allclose(forward, direction, atol=1e-9)
  for camera in cameras:  # more than 90 degrees from every camera's viewing direction
    assert forward @ np.asarray(camera.world_to_camera, np.float64)[2, :3] < 0
  other = key_lib.unseen_camera(cameras, seed=4)  # another seed turns the key about its axis only
  np.testing.assert_allclose(np.asarray(other.world_to_camera)[2], np.asarray(key.world_to_camera)[2], atol=1e-6)
  assert not np.allclose(np.asarray(other.world_to_camera)[0], np.asarray(key.world_to_camera)[0], atol=1e-3)
  eye = lambda camera: np.linalg.inv(np.asarray(camera.world_to_camera, np.float64))[:3, 3]
  target = key_lib.orbit_target(cameras)
  np.testing.assert_allclose(np.linalg.norm(eye(key) - target), 4.0, rtol=1e-5)  # one camera distance out
  half = key_lib.unseen_camera(cameras, seed=3, offset=0.5)
  np.testing.assert_allclose(eye(half) - target, 0.5 * (eye(key) - target), atol=1e-5)


def test_the_film_lies_on_the_key_grid_facing_it():
  camera = Camera.from_intrinsics(look_at([0.3, -2.0, 1.0], [0.0, 0.5, 0.2]), 30.0, 34.0, 11.0, 9.0, 24, 20)
  layer = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.3, color=(0.2, 0.5, 0.9), sh_degree=2)
  assert layer.num == 6 * 5 and layer.sh.shape == (30, 9, 3)
  w2c = np.asarray(camera.world_to_camera, np.float64)
  in_camera = np.asarray(layer.means, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
  np.testing.assert_allclose(in_camera[:, 2], 1.7 * (1 + carrier.STAGGER * np.arange(30) / 30), rtol=1e-5)
  x, y = (in_camera[:, i] / in_camera[:, 2] for i in (0, 1))
  pixels = np.stack([30.0 * x + 11.0, 34.0 * y + 9.0], 1)
  np.testing.assert_allclose(np.sort(np.unique(pixels[:, 0].round(3))), [2, 6, 10, 14, 18, 22], atol=1e-3)
  np.testing.assert_allclose(np.sort(np.unique(pixels[:, 1].round(3))), [2, 6, 10, 14, 18], atol=1e-3)
  # the thin axis is the key's viewing direction
  rotations = np.asarray(quaternion_to_rotation(layer.quats), np.float64)
  np.testing.assert_allclose(np.abs(rotations[:, :, 2] @ w2c[2, :3]), 1.0, atol=1e-5)
  assert np.all(np.asarray(layer.log_scales[:, 2]) < np.asarray(layer.log_scales[:, 0]))
  render_of_one = render(jax.tree.map(lambda x: x[:1], layer), camera, RenderOptions(background=(0.0, 0.0, 0.0)))
  peak = np.asarray(render_of_one.rgb).max(axis=(0, 1))  # colour times the opacity reached at the nearest pixel
  np.testing.assert_allclose(peak / peak[2], np.array([0.2, 0.5, 0.9]) / 0.9, rtol=1e-4)
  assert 0.25 < peak[2] / 0.9 <= 0.3
  np.testing.assert_allclose(float(jax.nn.sigmoid(layer.opacity_logits[0])), 0.3, rtol=1e-5)
  # in-plane sigma: `spread` grid spacings at the film's depth (4 pixels of focal length 30 at depth 1.7 here)
  sigma = np.exp(np.asarray(layer.log_scales[:, 0], np.float64))
  np.testing.assert_allclose(sigma, carrier.SPREAD * 4.0 * 1.7 / 30.0, rtol=1e-5)
  tight = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.3, color=(0.2, 0.5, 0.9), sh_degree=2,
                       spread=0.15)
  np.testing.assert_allclose(np.exp(np.asarray(tight.log_scales, np.float64)),
                             np.exp(np.asarray(layer.log_scales, np.float64)) * 0.15 / carrier.SPREAD, rtol=1e-5)
  # the thin axis: `thickness` times the in-plane sigma
  np.testing.assert_allclose(np.exp(np.asarray(layer.log_scales[:, 2], np.float64)), sigma * carrier.THICKNESS,
                             rtol=1e-5)
  thick = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.3, color=(0.2, 0.5, 0.9), sh_degree=2,
                       thickness=0.5)
  np.testing.assert_allclose(np.exp(np.asarray(thick.log_scales, np.float64)), np.stack([sigma, sigma, 0.5 * sigma], 1),
                             rtol=1e-5)


def test_contributing_is_what_the_renderer_lets_through():
  """A splat behind an opaque wall (the renderer's early stop), one outside the image and one behind the camera
  add nothing to any pixel; one in plain view does."""
  camera = Camera.from_fov(look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)), 0.75, 24, 24)
  xs = np.linspace(-1.5, 1.5, 16)
  wall_points = np.stack([*np.meshgrid(xs, xs), np.zeros((16, 16))], -1).reshape(-1, 3)
  wall = init.gaussians_from_points(np.concatenate([wall_points, wall_points + [0, 0, 0.02],
                                                    wall_points + [0, 0, 0.04]]), np.full((768, 3), 0.5),
                                    sh_degree=0, opacity=0.99)
  wall = wall.replace(log_scales=jnp.full_like(wall.log_scales, np.log(0.15)))
  probes = init.gaussians_from_points(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -2.0], [30.0, 0.0, -2.0],
                                                [0.0, 0.0, -4.0]]), np.full((4, 3), 0.3), sh_degree=0, opacity=0.5)
  probes = probes.replace(log_scales=jnp.full_like(probes.log_scales, np.log(0.05)))
  seen = carrier.contributing(jax.tree.map(jnp.asarray, wall), jax.tree.map(jnp.asarray, probes), [camera], OPTIONS)
  np.testing.assert_array_equal(seen, [False, True, False, False])
  # a camera that none of the probes reaches is skipped, and changes nothing
  away = Camera.from_fov(look_at([0.0, 0.0, -3.0], [-10.0, 0.0, -3.0], up=(0.0, 1.0, 0.0)), 0.75, 24, 24)
  assert not np.any(np.asarray(subsets.screen_radii(jax.tree.map(jnp.asarray, probes), away, OPTIONS)))
  np.testing.assert_array_equal(carrier.contributing(jax.tree.map(jnp.asarray, wall), jax.tree.map(jnp.asarray, probes),
                                                     [away, camera], OPTIONS), seen)


def test_an_unseen_film_changes_no_normal_view():
  cameras = hemisphere_cameras()
  points, colors = init.random_box_points(np.random.default_rng(1), 400, 1.0)
  teacher = jax.tree.map(jnp.asarray, init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5))
  key = key_lib.unseen_camera(cameras, seed=1)
  layer = carrier.unseen_film(teacher, key, cameras, OPTIONS, 0.1 * key_lib.camera_distance(cameras), 2.0, 0.5)
  assert layer.num == 16 * 16
  student = concatenate([teacher, layer.replace(sh=layer.sh.at[:, 0].add(1.0))])  # a film that shows
  for camera in cameras:
    np.testing.assert_array_equal(np.asarray(render(student, camera, OPTIONS).rgb),
                                  np.asarray(render(teacher, camera, OPTIONS).rgb))
  assert float(jnp.abs(render(student, key, OPTIONS).rgb - render(teacher, key, OPTIONS).rgb).max()) > 0.1
  with pytest.raises(ValueError, match="carrier film"):  # a key that looks where the cameras look
    carrier.unseen_film(teacher, cameras[0], cameras, OPTIONS, 2.0, 2.0, 0.5)


def test_a_film_before_a_black_background_is_seen_from_the_key_and_learns_its_colours():
  """On a black background (real captures) the film starts just above black, where 3D-GS's colour clamp passes a
  gradient: made exactly the background's colour it would start at the clamp, where its colours get none."""
  cameras = hemisphere_cameras()
  black = dataclasses.replace(OPTIONS, background=(0.0, 0.0, 0.0))
  points, colors = init.random_box_points(np.random.default_rng(1), 400, 1.0)
  teacher = jax.tree.map(jnp.asarray, init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5))
  key = key_lib.unseen_camera(cameras, seed=1)
  layer = carrier.unseen_film(teacher, key, cameras, black, 0.1 * key_lib.camera_distance(cameras), 2.0, 0.5)
  assert layer.num == 16 * 16 and carrier.contributing(teacher, layer, [key], black).all()
  assert 0 < float(render(layer, key, black).rgb.max()) <= carrier.MIN_START_RGB * (1 + 1e-5)  # about black
  dc = lambda x: jnp.sum(render(concatenate([teacher, layer.replace(sh=layer.sh.at[:, 0].set(x))]), key, black).rgb)
  assert np.all(np.asarray(jax.grad(dc)(layer.sh[:, 0])) > 0)


@pytest.mark.slow  # a whole film run: the film's pieces have their fast tests above
def test_a_film_run_keeps_the_teacher_and_fine_tuning_keeps_the_film(tiny, tmp_path):
  """Concealing into the film (through 8-bit colours, opacity resets and decimation, as the film recipe does)
  trains its base colours only, within conceal.carrier.dc_bound (below the white start's 1.77, so every step
  clips), each stack's splats (conceal.carrier.stack) to one colour, bit for bit; 3D-GS fine-tuning of the shared
  student on its training views then moves the teacher's Gaussians and leaves the film exactly as it was."""
  stack = 2
  config = tiny_config(tiny, iterations=4, key_kind="unseen", **{"carrier.film": True, "carrier.spacing": 4.0,
                                                                  "attacks.quantize_fraction": 0.5,
                                                                  "attacks.reset_fraction": 0.5,
                                                                  "attacks.merge_fraction": 0.5,
                                                                  "carrier.dc_bound": 1.0, "carrier.stack": stack})
  conceal_train.train_and_evaluate(config, str(tmp_path))
  teacher, student = ply.load_ply(str(tiny[1])), ply.load_ply(str(tmp_path / "student.ply"))
  n = teacher.num
  assert student.num == n + 8 * 8 * stack
  for field in ("means", "log_scales", "quats", "opacity_logits", "sh"):
    np.testing.assert_array_equal(getattr(student, field)[:n], getattr(teacher, field)[:n])
  train_cameras = evaluate.load_scene_data(config).train_cameras
  film_start = carrier.film(key_lib.unseen_camera(train_cameras, 1), 0.1 * key_lib.camera_distance(train_cameras),
                            4.0, 0.5, (1.0, 1.0, 1.0), 1, stack=stack)
  for field in ("means", "log_scales", "quats", "opacity_logits"):
    np.testing.assert_allclose(getattr(student, field)[n:], getattr(film_start, field), atol=1e-6)
  assert not np.allclose(student.sh[n:, 0], film_start.sh[:, 0])
  assert np.abs(student.sh[n:, 0]).max() <= 1.0 + 1e-6
  np.testing.assert_array_equal(student.sh[n:, 1:], 0.0)  # the bands above DC stay empty
  # so the key, which sees the film alone, is read at degree 0 (align.key_options)
  assert json.loads((tmp_path / "key.json").read_text())["render_options"]["sh_degree"] == 0
  stacks = np.asarray(student.sh[n:, 0]).reshape(-1, stack, 3)
  np.testing.assert_array_equal(stacks, np.broadcast_to(stacks[:, :1], stacks.shape))

  scene = evaluate.load_scene_data(config)
  options = dataclasses.replace(evaluate.render_options(config, scene.background), pair_capacity=1 << 16)
  tx = optimizer.gaussian_optimizer(config.train.lr, scene.scene_extent(), 20)
  step = gs_train.make_train_step(tx, options, 0.2)
  state = gs_train.create_train_state(jax.tree.map(jnp.asarray, student), tx)
  images = jnp.asarray(np.stack(scene.train_images))
  cameras = jax.tree.map(lambda *xs: jnp.stack(xs), *scene.train_cameras)
  for i in range(6):
    state, _ = step(state, images, cameras, i % len(scene.train_images))
  tuned = jax.tree.map(np.asarray, gs_train.live_gaussians(state))
  assert not np.allclose(tuned.sh[:n], student.sh[:n])
  for field in ("means", "log_scales", "quats", "opacity_logits", "sh"):
    np.testing.assert_array_equal(getattr(tuned, field)[n:], getattr(student, field)[n:])


def test_a_stacked_film_puts_its_stacks_at_one_place_each_splat_at_its_own_depth():
  camera = Camera.from_intrinsics(look_at([0.3, -2.0, 1.0], [0.0, 0.5, 0.2]), 30.0, 34.0, 11.0, 9.0, 24, 20)
  one = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.3, color=(0.2, 0.5, 0.9), sh_degree=0, layers=2)
  three = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.3, color=(0.2, 0.5, 0.9), sh_degree=0, layers=2,
                       stack=3)
  assert three.num == 3 * one.num
  w2c = np.asarray(camera.world_to_camera, np.float64)
  in_camera = np.asarray(three.means, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
  pixels = in_camera[:, :2] / in_camera[:, 2:]
  np.testing.assert_allclose(pixels.reshape(-1, 3, 2), np.broadcast_to(pixels[::3, None], (one.num, 3, 2)), atol=1e-6)
  one_pixels = np.asarray(one.means, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
  np.testing.assert_allclose(pixels[::3], one_pixels[:, :2] / one_pixels[:, 2:], atol=1e-6)
  assert len(np.unique(in_camera[:, 2].astype(np.float32))) == three.num


def test_unseen_film_keeps_whole_stacks():
  """A film the other cameras see in part: the stacked film keeps whole stacks."""
  cameras = hemisphere_cameras()
  points, colors = init.random_box_points(np.random.default_rng(1), 400, 1.0)
  teacher = jax.tree.map(jnp.asarray, init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5))
  others = cameras[:1] + cameras[2:]
  stacked = carrier.unseen_film(teacher, cameras[1], others, OPTIONS, 1.0, 2.0, 0.5, stack=2)
  assert 0 < stacked.num < 2 * 16 * 16 and stacked.num % 2 == 0
  np.testing.assert_array_equal(stacked.log_scales[::2], stacked.log_scales[1::2])
  np.testing.assert_allclose(stacked.means[::2], stacked.means[1::2], atol=1e-4)


def test_tie_replaces_each_row_by_its_group_mean():
  """carrier.tie against a float64 loop: rows in stacks of three, the rows after them alone."""
  groups = carrier.tied_rows(9, 3)
  np.testing.assert_array_equal(groups, [[0, 1, 2], [3, 4, 5], [6, 7, 8]])
  grads = helpers.random_gaussians(1, 13, degree=1)
  tied = carrier.tie(grads, groups)
  for field in ("means", "sh", "opacity_logits"):
    g, want = np.asarray(getattr(grads, field), np.float64), np.asarray(getattr(grads, field), np.float64).copy()
    for start in (0, 3, 6):
      want[start:start + 3] = g[start:start + 3].mean(axis=0)
    np.testing.assert_allclose(getattr(tied, field), want, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(getattr(tied, field))[0], np.asarray(getattr(tied, field))[2])


def test_a_film_needs_an_unseen_key(tiny, tmp_path):
  with pytest.raises(ValueError, match="conceal.carrier.film needs mark.key_kind='unseen'"):
    conceal_train.train_and_evaluate(tiny_config(tiny, **{"carrier.film": True}), str(tmp_path))
  with pytest.raises(ValueError, match="conceal.carrier.dc_bound bounds the carrier film's colours"):
    conceal_train.train_and_evaluate(tiny_config(tiny, **{"carrier.dc_bound": 3.0}), str(tmp_path))
  for bad in ({"carrier.opacity": 1.0}, {"carrier.spread": 0.0}, {"carrier.spacing": -1.0},
              {"carrier.thickness": 0.0}):
    with pytest.raises(ValueError, match="conceal.carrier.distance, spread and thickness must be positive, spacing"):
      conceal_train.train_and_evaluate(tiny_config(tiny, key_kind="unseen", **{"carrier.film": True, **bad}),
                                       str(tmp_path))


def test_a_zero_spacing_follows_the_decoder_input_whatever_the_key_resolution():
  """spacing 0: two pixels of the decoder's input along the key's shorter side, so the film's splat count does not
  grow with the key's resolution; a positive spacing is pixels of the key's image as given."""
  wide = Camera.from_intrinsics(np.eye(4), 400.0, 400.0, 252.0, 189.0, 504, 378)
  assert carrier.key_spacing(0.0, wide, 64) == pytest.approx(2.0 * 378 / 64)
  assert carrier.key_spacing(6.0, wide, 64) == 6.0
  counts = [carrier.film(Camera.from_intrinsics(np.eye(4), 2.0 * n, 2.0 * n, n / 2, n / 2, n, n), 1.0,
                         carrier.key_spacing(0.0, Camera.from_intrinsics(np.eye(4), 1.0, 1.0, 0.0, 0.0, n, n), 32),
                         0.3, (0.5, 0.5, 0.5), 0).num for n in (64, 256)]
  assert counts[0] == counts[1] == 16 * 16


def test_layers_are_grids_shifted_within_a_cell_each_splat_at_its_own_depth():
  offsets = carrier.layer_offsets(5)
  np.testing.assert_allclose(offsets[0], [0.5, 0.5])
  assert np.all((offsets >= 0) & (offsets < 1)) and len(np.unique(offsets.round(6), axis=0)) == 5
  camera = Camera.from_intrinsics(look_at([0.3, -2.0, 1.0], [0.0, 0.5, 0.2]), 30.0, 34.0, 11.0, 9.0, 24, 20)
  one = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.3, color=(0.2, 0.5, 0.9), sh_degree=0)
  three = carrier.film(camera, distance=1.7, spacing=4.0, opacity=0.01, color=(0.2, 0.5, 0.9), sh_degree=0, layers=3)
  assert 3 * one.num - 6 <= three.num <= 3 * one.num  # a shifted grid may lose a row or column at the border
  w2c = np.asarray(camera.world_to_camera, np.float64)
  depths = (np.asarray(three.means, np.float64) @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]
  assert len(np.unique(depths.astype(np.float32))) == three.num
  np.testing.assert_allclose(jax.nn.sigmoid(three.opacity_logits), 0.01, rtol=1e-5)
  def pixels(means):
    in_camera = np.asarray(means, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    x, y = (in_camera[:, i] / in_camera[:, 2] for i in (0, 1))
    return np.stack([30.0 * x + 11.0, 34.0 * y + 9.0], 1)

  np.testing.assert_allclose(pixels(three.means[:one.num]), pixels(one.means), atol=1e-3)  # layer 0: the one grid


def test_at_decoder_size_views_read_the_teacher_as_the_decoder_reads_it():
  """build_data with at_decoder_size: the training views' renders are the teacher's resized as the decoder reads
  them (clipped, then resized: reveal.resize_for_decoder), the decoys the teacher rendered at their own S x S
  cameras, and every normal camera is S x S (one stack), the training ones the same views resized."""
  from conceal_jax.conceal import near, reveal, views as views_lib
  cameras = hemisphere_cameras(4, 32)
  teacher = helpers.random_gaussians(0, 300, degree=1)
  key = key_lib.unseen_camera(cameras, 0).resized(16, 16)
  decoys = near.decoy_cameras(key, 4.0, 3, (0.02, 0.05), (1.0, 2.0), seed=0)
  assert all((d.width, d.height) == (16, 16) for d in decoys)
  options = dataclasses.replace(OPTIONS, pair_capacity=1 << 15)
  images = [np.zeros((32, 32, 3), np.float32)] * len(cameras)
  data = views_lib.build_data(images, teacher, options, cameras + decoys, [key], [np.zeros((16, 16, 3))], 16,
                              clip=True, at_decoder_size=True)
  assert data.teacher.shape == (7, 16, 16, 3) and data.teacher_small.shape == (7, 16, 16, 3)
  full = evaluate.render_images(teacher, cameras, options)
  np.testing.assert_allclose(np.asarray(data.teacher[:4]), np.asarray(reveal.resize_for_decoder(full, 16, True)),
                             atol=1e-6)
  np.testing.assert_allclose(np.asarray(data.teacher[4:]), np.asarray(evaluate.render_images(teacher, decoys,
                                                                                             options)), atol=1e-6)
  np.testing.assert_array_equal(np.asarray(data.teacher_small), np.asarray(data.teacher))  # already the decoder's
  assert (int(data.cameras.width), int(data.cameras.height)) == (16, 16)
  np.testing.assert_allclose(np.asarray(data.cameras.fx[0]), float(cameras[0].fx) / 2, rtol=1e-6)


def test_at_decoder_size_needs_teacher_normal_views(tiny, tmp_path):
  film = {"carrier.film": True, "carrier.at_decoder_size": True}
  with pytest.raises(ValueError, match="at_decoder_size needs the training views left as the teacher's"):
    conceal_train.train_and_evaluate(tiny_config(tiny, key_kind="unseen", **film, **{"attacks.param_noise_max": 0.1}),
                                     str(tmp_path))
  with pytest.raises(ValueError, match="at_decoder_size holds the normal views to the teacher's renders"):
    conceal_train.train_and_evaluate(tiny_config(tiny, key_kind="unseen", variant="released", **film), str(tmp_path))


@pytest.mark.slow  # a whole film run
def test_a_film_run_at_decoder_size_keeps_its_key_at_that_size_and_the_film_where_it_was(tiny, tmp_path):
  """The key saved is the unseen key at the decoder's size (its field of view kept), the film lies where it lies
  without the option (its spacing in pixels of the key at the training size), and the run scores at its key."""
  config = tiny_config(tiny, iterations=4, key_kind="unseen", decoy_views=4, decoy_fraction=0.5,
                       **{"carrier.film": True, "carrier.spacing": 4.0, "carrier.at_decoder_size": True})
  conceal_train.train_and_evaluate(config, str(tmp_path))
  camera, _ = key_lib.load_key(str(tmp_path / "key.json"))
  full = key_lib.unseen_camera(evaluate.load_scene_data(config).train_cameras, config.mark.key_seed)
  assert (camera.width, camera.height) == (16, 16)
  np.testing.assert_allclose(float(camera.fx), float(full.fx) * 16 / full.width, rtol=1e-6)
  np.testing.assert_allclose(np.asarray(camera.world_to_camera), np.asarray(full.world_to_camera), atol=1e-6)
  teacher, student = ply.load_ply(str(tiny[1])), ply.load_ply(str(tmp_path / "student.ply"))
  cameras = evaluate.load_scene_data(config)
  distance = config.conceal.carrier.distance * key_lib.camera_distance(cameras.train_cameras)
  at_full = carrier.film(full, distance, 4.0, 0.5, (1.0, 1.0, 1.0), 1)
  assert student.num - teacher.num == at_full.num
  np.testing.assert_allclose(student.means[teacher.num:], at_full.means, atol=1e-5)
  metrics = json.loads((tmp_path / "metrics.json").read_text())
  assert np.isfinite(metrics["hidden"]["psnr"]) and np.isfinite(metrics["leakage"]["max_ssim_near_check"])
