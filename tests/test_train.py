"""Training: one short run end to end in a temp workdir, exact resume after a stop, and the pieces of
the step (learning rates, densification statistic, optimizer bookkeeping)."""
from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.data import datasets, demo_scene, ply
from conceal_jax.gs import densify, optimizer, train
from conceal_jax.configs import demo
from conceal_jax.splat.render import RenderOptions, render
from tests.helpers import make_camera, random_gaussians


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
  return demo_scene.generate_demo_scene(tmp_path_factory.mktemp("scene") / "demo", num_train=6, num_test=2,
                                        size=48)


def tiny_config(scene_path, iterations=8):
  config = demo.get_config()
  config.data.path = str(scene_path)
  config.init.num_random_points = 1500
  config.train.iterations = iterations
  config.train.sh_increase_every = 3
  config.train.densify.start = 2
  config.train.densify.every = 3
  config.train.densify.until = iterations
  config.train.densify.opacity_reset_every = 5
  config.train.densify.grad_threshold = 2e-5  # low, so the short run does clone and split
  config.train.checkpoint_every = 4
  config.train.log_every = 1
  config.train.eval_every = 4
  config.train.progress_bar = False
  config.eval.max_views = 1
  return config


@pytest.mark.job
def test_train_writes_scene_metrics_and_resumes_exactly(tiny_scene, tmp_path):
  config = tiny_config(tiny_scene)
  config.train.snapshots = (4,)
  straight = train.train_and_evaluate(config, str(tmp_path / "a"))
  assert ply.load_ply(tmp_path / "a" / train.snapshot_name(4)).num > 0
  assert train.train_and_evaluate(config, str(tmp_path / "b"), max_steps=4) == dict(stopped_at=4)
  resumed = train.train_and_evaluate(config, str(tmp_path / "b"))
  assert resumed["resumed_from"] == 4 and resumed["timed_steps"] == straight["timed_steps"] == 8
  a, b = ply.load_ply(tmp_path / "a" / "point_cloud.ply"), ply.load_ply(tmp_path / "b" / "point_cloud.ply")
  assert a.num == b.num != 1500, "densification must have changed the count"
  jax.tree.map(np.testing.assert_array_equal, a, b)
  assert [h["loss"] for h in straight["history"] if "loss" in h] == \
      [h["loss"] for h in resumed["history"] if "loss" in h]
  # a time limit stops at the first checkpoint past it, saves and scores the scene there, and resumes to the end
  config.train.time_limit_min = 1e-9
  timed = train.train_and_evaluate(config, str(tmp_path / "c"))
  assert (timed["iterations"], timed["planned_iterations"], timed["time_limit_reached"]) == (4, 8, True)
  assert np.isfinite(timed["test"]["psnr"])
  jax.tree.map(np.testing.assert_array_equal, ply.load_ply(tmp_path / "c" / "point_cloud.ply"),
               ply.load_ply(tmp_path / "a" / train.snapshot_name(4)))
  config.train.time_limit_min = 0.0
  finished = train.train_and_evaluate(config, str(tmp_path / "c"))
  assert (finished["iterations"], finished["time_limit_reached"]) == (8, False)
  jax.tree.map(np.testing.assert_array_equal, a, ply.load_ply(tmp_path / "c" / "point_cloud.ply"))

  metrics = json.loads((tmp_path / "a" / "metrics.json").read_text())
  assert "VGG16" in metrics["lpips_net"] and metrics["num_views"] == 1
  assert 0 < metrics["mean"]["ssim"] <= 1 and np.isfinite(metrics["mean"]["psnr"])
  assert len(list((tmp_path / "a" / "test_renders").glob("*.png"))) == 1
  summary = json.loads((tmp_path / "a" / "train.json").read_text())
  assert summary["iterations"] == 8 and summary["median_step_s"] > 0
  assert [h["step"] for h in summary["history"] if "test_psnr" in h] == [4]
  # three SH degrees in 8 steps; densification ran twice without changing the compiled buffer size
  assert sorted({d for d, *_ in summary["compiled_step_variants"]}) == [0, 1, 2]
  # one trace per compiled variant, none silently repeated
  assert summary["traces"] == dict(train_step=len(summary["compiled_step_variants"]))


@pytest.mark.job
def test_train_on_a_given_scene(tiny_scene, tmp_path):
  """scene= replaces the scene of config.data (a baseline's containers): its training views are fitted and
  its test split is scored."""
  config = tiny_config(tiny_scene, iterations=2)
  config.eval.max_views = 0
  scene = datasets.load_scene(str(tiny_scene))
  given = dataclasses.replace(scene, train_images=[1.0 - image for image in scene.train_images],
                              test_images=scene.test_images[:1], test_cameras=scene.test_cameras[:1],
                              test_names=["given_view"])
  loaded = train.train_and_evaluate(config, str(tmp_path / "loaded"))
  trained = train.train_and_evaluate(config, str(tmp_path / "given"), scene=given)
  assert loaded["test"] != trained["test"]
  assert [h["psnr"] for h in loaded["history"] if "psnr" in h][0] != \
      [h["psnr"] for h in trained["history"] if "psnr" in h][0]
  views = json.loads((tmp_path / "given" / "metrics.json").read_text())["views"]
  assert [v["name"] for v in views] == ["given_view"]
  unscored = train.train_and_evaluate(config, str(tmp_path / "unscored"), scene=given, score=False)
  assert "test" not in unscored and not (tmp_path / "unscored" / "metrics.json").exists()
  scene_file = lambda name: (tmp_path / name / "point_cloud.ply").read_bytes()
  assert scene_file("unscored") == scene_file("given")


@pytest.mark.parametrize("field,value,message", [
    ("train.iterations", 0, "iterations"), ("train.sh_degree", 4, "sh_degree"),
    ("data.background", "pink", "data.background"), ("init.kind", "sfm", "init.kind")])
def test_bad_config_values_are_named(tiny_scene, tmp_path, field, value, message):
  config = tiny_config(tiny_scene)
  section, key = field.split(".")
  config[section][key] = value
  with pytest.raises(ValueError, match=message):
    train.train_and_evaluate(config, str(tmp_path))


def test_sh_degree_schedule():
  schedule = train.TrainSettings(sh_degree=3, sh_increase_every=1000)
  assert [schedule.sh_degree_at(i) for i in (1, 1000, 1001, 2001, 3001, 9000)] == [0, 0, 1, 2, 3, 3]
  fine_tune = train.TrainSettings(sh_degree=3, sh_degree_start=2, sh_increase_every=1000)
  assert [fine_tune.sh_degree_at(i) for i in (1, 1001, 5000)] == [2, 3, 3]
  with pytest.raises(ValueError, match="sh_degree_start"):
    train.TrainSettings(sh_degree=1, sh_degree_start=2)


def test_training_can_start_from_a_trained_scene(tiny_scene, tmp_path):
  """init.kind='ply' starts from the scene's own Gaussians, SH bands padded with zeros to train.sh_degree."""
  start = jax.tree.map(np.asarray, random_gaussians(3, 50, degree=1))
  ply.save_ply(tmp_path / "start.ply", start)
  config = tiny_config(tiny_scene)
  config.init.kind, config.init.ply = "ply", str(tmp_path / "start.ply")
  train.validate(config)
  g = train.initial_gaussians(config, None, np.random.default_rng(0))
  assert g.sh.shape == (50, 16, 3) and not np.any(g.sh[:, 4:])
  np.testing.assert_allclose(g.sh[:, :4], start.sh, rtol=1e-6)
  np.testing.assert_allclose(g.means, start.means, rtol=1e-6)
  config.train.sh_degree = 0
  with pytest.raises(ValueError, match="SH degree 1"):
    train.initial_gaussians(config, None, np.random.default_rng(0))
  config.init.ply = str(tmp_path / "missing.ply")
  with pytest.raises(ValueError, match="init.ply"):
    train.validate(config)


def test_snapshots_must_fall_on_log_windows(tiny_scene):
  config = tiny_config(tiny_scene)
  config.train.log_every = 2
  config.train.snapshots = (4, 8)
  assert train.snapshot_steps(config) == (4, 8)
  config.train.snapshots = (3,)
  with pytest.raises(ValueError, match="train.snapshots"):
    train.validate(config)


@pytest.mark.job
def test_a_resumed_run_must_have_the_snapshots_it_passed(tiny_scene, tmp_path):
  """A run stopped at step 4 without snapshots cannot be resumed asking for one at step 4 (it would never be
  written); asking for one at step 8, not reached yet, resumes and writes it."""
  config = tiny_config(tiny_scene)
  assert train.train_and_evaluate(config, str(tmp_path), max_steps=4) == dict(stopped_at=4)
  config.train.snapshots = (4, 8)
  with pytest.raises(ValueError, match=r"reached step 4 without the snapshots \[4\]"):
    train.train_and_evaluate(config, str(tmp_path))
  config.train.snapshots = (8,)
  train.train_and_evaluate(config, str(tmp_path), max_steps=8)
  assert (tmp_path / train.snapshot_name(8)).is_file()


def test_position_learning_rate_is_log_linear():
  schedule = optimizer.log_linear_schedule(1e-2, 1e-4, 100)
  np.testing.assert_allclose([schedule(0), schedule(50), schedule(100), schedule(500)],
                             [1e-2, 1e-3, 1e-4, 1e-4], rtol=1e-5)


def test_position_learning_rate_decays_over_the_run_unless_given_a_length():
  lr = demo.get_config().train.lr
  lr.means_init, lr.means_final = 1e-2, 1e-4
  lr.means_steps = 0
  assert optimizer.means_decay_steps(lr, 400) == 400
  lr.means_steps = 100
  assert optimizer.means_decay_steps(lr, 400) == 100
  lr.means_steps = 0
  with pytest.raises(ValueError, match="means_steps"):
    optimizer.gaussian_optimizer(lr, 1.0, run_steps=0)


def test_decaying_adam_steps_follow_the_schedule():
  """With a constant gradient Adam's normalised step is 1, so each update is -lr(t): 1e-3 decaying to 1e-4 over
  10 steps and held there; ratio 1 keeps lr (with no schedule state) and a ratio outside (0, 1] is named."""
  params = dict(w=jnp.zeros(2))
  grads = dict(w=jnp.ones(2))
  for ratio, expected in ((0.1, [1e-3 * 0.1**(min(t, 10) / 10) for t in (0, 5, 10, 20)]), (1.0, [1e-3] * 4)):
    tx = optimizer.decaying_adam(1e-3, ratio, 10, 1e-15)
    state, steps = tx.init(params), []
    for t in range(21):
      update, state = tx.update(grads, state, params)
      if t in (0, 5, 10, 20):
        steps.append(-float(update["w"][0]))
    np.testing.assert_allclose(steps, expected, rtol=1e-4)
  assert len(jax.tree.leaves(optimizer.decaying_adam(1e-3, 1.0, 10, 1e-15).init(params))) == 3
  for ratio in (0.0, 1.5, float("nan")):
    with pytest.raises(ValueError, match="my.ratio"):
      optimizer.decaying_adam(1e-3, ratio, 10, 1e-15, "my.ratio")


def test_update_clip_bounds_the_step_of_a_gradient_that_returns():
  """A weight trained with gradient 1, then silent for 5000 steps, then given gradient 1 again: Adam (eps 1e-15)
  has forgotten the scale and steps well over the rate; with the update clip (update_rms_clip) at most the rate."""
  params = dict(w=jnp.zeros(()))
  grads = jnp.concatenate([jnp.ones(100), jnp.zeros(5000), jnp.ones(1)])

  def steps(clip=0.0):
    tx = optimizer.decaying_adam(1e-3, 1.0, 10, 1e-15, update_rms_clip=clip)

    def body(state, g):
      update, state = tx.update(dict(w=g), state, params)
      return state, update["w"]

    return -np.asarray(jax.lax.scan(body, tx.init(params), grads)[1])

  adam, clipped = steps(), steps(1.0)
  assert adam[-1] > 1.5e-3, adam[-1]
  # Adafactor's update clip (update_rms_clip) bounds the returning step, and leaves the steady steps alone
  assert 0 < clipped[-1] <= 1.0001e-3 and clipped[-1] < adam[-1] / 1.5, (clipped[-1], adam[-1])
  np.testing.assert_allclose(clipped[:100], adam[:100], rtol=1e-5)
  with pytest.raises(ValueError, match="update_rms_clip must be >= 0"):
    optimizer.decaying_adam(1e-3, 1.0, 10, 1e-15, update_rms_clip=-1.0)


def test_learning_rates_per_field():
  """After one Adam step from zero moments each update is -lr * sign(grad) (up to eps)."""
  config = demo.get_config()
  lr = config.train.lr
  g = random_gaussians(0, 4, degree=1)
  tx = optimizer.gaussian_optimizer(lr, extent=2.0)
  grads = jax.tree.map(lambda x: jnp.full_like(x, -0.3), g)
  updates, _ = tx.update(grads, tx.init(g), g)
  np.testing.assert_allclose(updates.means, lr.means_init * 2.0, rtol=1e-5)
  np.testing.assert_allclose(updates.sh[:, 0], lr.sh_dc, rtol=1e-5)
  np.testing.assert_allclose(updates.sh[:, 1:], lr.sh_rest, rtol=1e-5)
  np.testing.assert_allclose(updates.opacity_logits, lr.opacity, rtol=1e-5)
  np.testing.assert_allclose(updates.log_scales, lr.scales, rtol=1e-5)
  np.testing.assert_allclose(updates.quats, lr.quats, rtol=1e-5)


def test_means2d_offset_gradient_is_the_screen_space_gradient(x64):
  """The densification statistic differentiates the loss at the projected means: compare with float64
  central differences in the offsets (a smooth loss, so the differences converge)."""
  g, camera = random_gaussians(1, 6, degree=0, dtype=jnp.float64), make_camera(24, 20, dtype=jnp.float64)
  target = jnp.full((20, 24, 3), 0.3)
  options = RenderOptions(max_per_tile=None)

  def loss(offsets):
    return jnp.mean((render(g, camera, options, means2d_offset=offsets).rgb - target) ** 2)
  offsets = jnp.zeros((6, 2))
  grad = jax.grad(loss)(offsets)
  visible = np.flatnonzero(np.asarray(render(g, camera, options).radii) > 0)
  assert visible.size >= 3
  for i in visible[:3]:
    for axis in range(2):
      delta = jnp.zeros((6, 2)).at[i, axis].set(1e-6)
      numeric = (loss(delta) - loss(-delta)) / 2e-6
      np.testing.assert_allclose(grad[i, axis], numeric, rtol=1e-4, atol=1e-10)


def test_densify_state_keeps_moments_with_their_gaussians():
  config = demo.get_config()
  tx = optimizer.gaussian_optimizer(config.train.lr, 1.0)
  g = random_gaussians(2, 5, degree=0, log_scale=(-6, -5))
  live = jax.tree.map(np.asarray, g)
  state = train.create_train_state(live, tx)
  moments = optimizer.adam_moments(state.opt_state)
  marked = jax.tree.map(lambda x: x.at[:5].set(jnp.arange(1.0, 6.0).reshape((5,) + (1,) * (x.ndim - 1))),
                        moments.mu)
  state = state.replace(opt_state=optimizer.with_adam_moments(state.opt_state, moments._replace(mu=marked)),
                        grad_accum=state.grad_accum.at[1].set(1.0),  # row 1 is cloned
                        grad_count=state.grad_count.at[1].set(1))
  out = train.densify_state(state, 1.0, densify.DensifyParams(), False, np.random.default_rng(0))
  assert int(out.alive.sum()) == 6 and out.alive.shape[0] == state.alive.shape[0]
  mu = optimizer.adam_moments(out.opt_state).mu
  np.testing.assert_array_equal(mu.means[:6, 0], [1, 2, 3, 4, 5, 0])  # the clone starts from zero
  np.testing.assert_array_equal(out.gaussians.means[5], g.means[1])
  assert float(out.grad_accum.sum()) == 0


def test_warmup_ramps_every_update_linearly():
  """lr.warmup_steps = 4: the t-th update is (t + 1) / 4 of the unwarmed one, then equal to it."""
  lr = demo.get_config().train.lr
  g = random_gaussians(0, 4, degree=1)
  grads = jax.tree.map(lambda x: jnp.full_like(x, 0.7), g)
  plain = optimizer.gaussian_optimizer(lr, extent=2.0, run_steps=100)
  lr.warmup_steps = 4
  warm = optimizer.gaussian_optimizer(lr, extent=2.0, run_steps=100)
  plain_state, warm_state = plain.init(g), warm.init(g)
  for t in range(6):
    expected, plain_state = plain.update(grads, plain_state, g)
    got, warm_state = warm.update(grads, warm_state, g)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, min(1.0, (t + 1) / 4) * b, rtol=1e-6), got, expected)
  lr.warmup_steps = -1
  with pytest.raises(ValueError, match="warmup_steps"):
    optimizer.gaussian_optimizer(lr, 1.0, run_steps=10)


def test_warmup_fraction_takes_the_longer_of_the_two_lengths():
  """lr.warmup_fraction of the run's length, unless lr.warmup_steps is longer; a fraction outside [0, 1] is
  named."""
  lr = demo.get_config().train.lr
  lr.warmup_steps, lr.warmup_fraction = 200, 0.1
  assert optimizer.warmup_length(lr, 10_000) == 1000
  assert optimizer.warmup_length(lr, 1300) == 200
  lr.warmup_steps = 0
  assert optimizer.warmup_length(lr, 1300) == 130
  for fraction in (-0.1, 1.5, float("nan")):
    lr.warmup_fraction = fraction
    with pytest.raises(ValueError, match="warmup_fraction"):
      optimizer.gaussian_optimizer(lr, 1.0, run_steps=10)
