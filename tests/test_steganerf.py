"""The StegaNeRF baseline (Li et al. 2023) on 3D-GS: the adaptive gradient mask, the objective assembled by
hand from its terms, the step, and the baseline job end to end on a tiny generated scene for both protocols
(frozen geometry, resume, bench rows, clear errors)."""
from __future__ import annotations

import json
import shutil

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import pytest

from conceal_jax import main as main_lib
from conceal_jax.baselines import baseline, steganerf, steganerf_train
from conceal_jax.conceal import reveal, unet
from conceal_jax.data import ply
from conceal_jax.gs import optimizer
from conceal_jax.splat.render import RenderOptions, render
from experiments import bench_baselines, reproduce
from tests.test_baselines import tiny_config
from tests.test_conceal import tiny  # noqa: F401  (tiny: the 32x32 demo scene and teacher)
from tests.test_objective import objective_inputs

LR = ml_collections.ConfigDict(dict(sh_dc=0.01, sh_rest=0.002))


def test_adaptive_mask_weights_by_hand():
  """w_k = (E_min / E_k)^3, E_k the mean |coefficient| of basis k over Gaussians and channels."""
  sh = np.zeros((2, 4, 3), np.float32)
  sh[:, 0] = [[2.0, -2.0, 2.0], [-2.0, 2.0, 2.0]]  # E_0 = 2
  sh[:, 1] = [[1.0, -1.0, 1.0], [-2.0, 0.0, -2.0]]  # E_1 = 7 / 6
  sh[:, 2] = [[0.5, 0.5, -0.5], [0.5, -0.5, 0.5]]  # E_2 = 0.5
  sh[:, 3] = [[0.25, 0.0, 0.0], [0.0, 0.0, 0.5]]  # E_3 = 0.125, the least used basis
  expected = [(0.125 / 2.0)**3, (0.125 / (7 / 6))**3, (0.125 / 0.5)**3, 1.0]
  np.testing.assert_allclose(steganerf.adaptive_mask_weights(jnp.asarray(sh)), expected, rtol=1e-6)
  # a band the scene never used is the least important: weight 1, the others about 0, nothing undefined
  sh[:, 3] = 0.0
  weights = np.asarray(steganerf.adaptive_mask_weights(jnp.asarray(sh)))
  assert weights[3] == 1.0 and np.all(np.isfinite(weights)) and weights[:3].max() < 1e-20


def _first_sh_step(tx, sh, grad):
  return np.asarray(tx.update(grad, tx.init(sh), sh)[0])


def test_the_mask_scales_adams_update_but_not_through_its_gradient():
  """mask_at='update' multiplies each basis' step by its weight; on the gradient, Adam's per-coefficient
  normalisation undoes a constant weight, so the first step equals the unmasked one."""
  rng = np.random.default_rng(0)
  sh = jnp.asarray(rng.normal(size=(5, 4, 3)) * np.array([1.0, 0.5, 0.3, 0.1])[:, None], jnp.float32)
  grad = jnp.asarray(rng.normal(size=(5, 4, 3)), jnp.float32)
  weights = np.asarray(steganerf.adaptive_mask_weights(sh))
  assert weights.min() < 0.01 and weights.max() == 1.0
  unmasked = optax.chain(optax.scale_by_adam(eps=optimizer.ADAM_EPS),
                         optax.stateless(lambda u, p=None: -optimizer.sh_learning_rates(LR, 4)[None, :, None] * u))
  plain = _first_sh_step(unmasked, sh, grad)
  np.testing.assert_allclose(plain[:, 0], -0.01 * np.sign(grad[:, 0]), rtol=1e-5)  # Adam's first step: lr sign(g)
  np.testing.assert_allclose(_first_sh_step(steganerf.sh_optimizer(LR, "update", optimizer.ADAM_EPS), sh, grad),
                             plain * weights[None, :, None], rtol=1e-5)
  np.testing.assert_allclose(_first_sh_step(steganerf.sh_optimizer(LR, "gradient", optimizer.ADAM_EPS), sh, grad),
                             plain, rtol=1e-5)
  # at eps 1e-8 (StegaNerfSettings' default) a gradient far below eps takes a step shrunk with it, not lr-sized
  tiny_grad = grad * 1e-12
  step = _first_sh_step(steganerf.sh_optimizer(LR, "gradient", 1e-8), sh, tiny_grad)
  assert np.abs(step).max() < 1e-3 * np.abs(plain).max()
  np.testing.assert_allclose(_first_sh_step(steganerf.sh_optimizer(LR, "gradient", 1e-8), sh, grad), plain, rtol=1e-4)


def test_networks_take_small_steps_on_vanishing_gradients():
  """A classifier that already separates its renders gets gradients far below Adam's eps; its steps must
  shrink with them (not stay lr-sized, which grows the logits without bound), while ordinary gradients
  still take lr-sized first steps."""
  s = _settings(decoder_lr=1e-3, classifier_lr=1e-3)
  networks = steganerf.init_networks(jax.random.key(0), s)
  tx = steganerf.networks_optimizer(s, 100)

  @jax.jit  # one program, rather than one per operation and leaf shape
  def largest_step(scale):
    grads = jax.tree.map(lambda p: jnp.full_like(p, scale), networks)
    updates = tx.update(grads, tx.init(networks), networks)[0]
    return jnp.max(jnp.stack([jnp.max(jnp.abs(u)) for u in jax.tree.leaves(updates)]))

  for scale, bound in ((1e-12, 1e-3), (1e-2, 1.0)):
    step = float(largest_step(jnp.float32(scale)))
    assert step <= bound * 1e-3 * 1.0001 and (scale < 1e-6 or step > 0.99e-3)


def _settings(**overrides):
  values = dict(decoder_width=4, classifier_width=4, hidden_size=16)
  values.update(overrides)
  return steganerf.StegaNerfSettings(**values)


@pytest.mark.parametrize("protocol", ["all_views", "check_view"])
def test_objective_is_the_sum_of_stega_nerfs_terms(protocol):
  """w_render MSE(R, R_0) + w_hidden MSE(U(R), I) + w_clean MSE(U(R_0), 0) + w_classifier BCE, assembled by
  hand; R carries I at the step's view (all_views) or at the check view (check_view)."""
  teacher, _, data = objective_inputs()
  s = _settings(protocol=protocol, weight_render=0.7, weight_hidden=0.3, weight_clean=0.2, weight_classifier=0.05)
  networks = steganerf.init_networks(jax.random.key(1), s)
  options = RenderOptions(max_per_tile=None)
  sh = teacher.sh + 0.1
  # value and gradients from one compiled program
  objective = jax.jit(jax.value_and_grad(steganerf.steganerf_objective, argnums=(0, 1), has_aux=True),
                      static_argnums=(5, 6))
  (total, aux), grads = objective(sh, networks, data, teacher, 1, s, options)

  student = teacher.replace(sh=sh)
  rgb = render(student, jax.tree.map(lambda x: x[1], data.cameras), options).rgb
  marked = rgb if protocol == "all_views" else render(student, data.keys.at(0).camera, options).rgb
  images = jnp.stack([reveal.resize_for_decoder(marked, 16), data.teacher_small[1]])
  logits = steganerf.Classifier(4).apply({"params": networks["classifier"]}, images)
  score = 1 / (1 + jnp.exp(-logits))
  planes = jnp.concatenate([images, jnp.ones(images.shape[:-1] + (1,)) * score[:, None, None, None]], axis=-1)
  revealed = unet.UNet(4).apply({"params": networks["decoder"]}, planes)
  terms = dict(render=jnp.mean((rgb - data.teacher[1])**2), hidden=jnp.mean((revealed[0] - data.keys.hidden[0])**2),
               clean=jnp.mean(revealed[1]**2), classifier=-(jnp.log(score[0]) + jnp.log(1 - score[1])) / 2)
  for name, value in terms.items():
    np.testing.assert_allclose(float(aux[name]), float(value), rtol=1e-5, err_msg=name)
  expected = 0.7 * terms["render"] + 0.3 * terms["hidden"] + 0.2 * terms["clean"] + 0.05 * terms["classifier"]
  np.testing.assert_allclose(float(total), float(expected), rtol=1e-5)
  for part in (grads[0], grads[1]["decoder"], grads[1]["classifier"]):
    assert any(float(jnp.abs(g).max()) > 0 for g in jax.tree.leaves(part))


def test_step_lowers_the_loss_and_keeps_the_state_on_overflow():
  teacher, _, data = objective_inputs()
  s = _settings(decoder_lr=3e-3, classifier_lr=3e-3, mask_at="update")
  sh_tx, networks_tx = steganerf.sh_optimizer(LR, s.mask_at, s.sh_adam_eps), steganerf.networks_optimizer(s, 100)
  fresh = lambda: steganerf_train.create_state(jnp.array(teacher.sh, copy=True),
                                                steganerf.init_networks(jax.random.key(0), s), sh_tx, networks_tx)
  step = steganerf_train.make_steganerf_step(s, RenderOptions(max_per_tile=None, pair_capacity=4096), sh_tx,
                                             networks_tx)
  state, first = step(fresh(), data, teacher, 0)
  first = {k: float(v) for k, v in first.items()}
  for i in range(40):
    state, stats = step(state, data, teacher, i % 3)
  assert int(state.step) == 41 and float(stats["hidden"]) < 0.5 * first["hidden"]
  assert not np.array_equal(np.asarray(state.sh), np.asarray(teacher.sh))

  tight = steganerf_train.make_steganerf_step(s, RenderOptions(max_per_tile=None, pair_capacity=1), sh_tx, networks_tx)
  before = fresh()
  kept, stats = tight(jax.tree.map(jnp.copy, before), data, teacher, 0)
  assert int(stats["num_pairs"]) > 1 and int(kept.step) == 0
  jax.tree.map(np.testing.assert_array_equal, kept, before)


def stega_config(tiny, protocol):
  config = tiny_config(tiny, "steganerf")
  d = config.baseline.steganerf
  d.protocol, d.decoder_width, d.classifier_width, d.decoder_lr, d.classifier_lr = protocol, 4, 4, 1e-3, 1e-3
  d.log_every, d.checkpoint_every, d.progress_bar = 2, 3, False
  return config


@pytest.fixture(scope="module")
def all_views_runs(tiny, tmp_path_factory):
  """An all_views run of 6 steps straight, and one stopped after 3 and resumed: (straight dir, its result,
  resumed dir, its result, the stopped call's result)."""
  config = stega_config(tiny, "all_views")
  straight, resumed = tmp_path_factory.mktemp("stega_a"), tmp_path_factory.mktemp("stega_b")
  first = main_lib.run(config, str(straight))
  stopped = baseline.baseline_and_evaluate(config, str(resumed), max_steps=3)
  return straight, first, resumed, baseline.baseline_and_evaluate(config, str(resumed)), stopped


@pytest.fixture(scope="module")
def check_view_run(tiny, tmp_path_factory):
  workdir = tmp_path_factory.mktemp("stega_check")
  return workdir, main_lib.run(stega_config(tiny, "check_view"), str(workdir))


def _check_run(workdir, result, tiny, protocol):
  """The files and summary of a finished run; the student is the teacher with new colours only."""
  for name in ("metrics.json", "baseline.json", "revealed.png", "teacher_revealed.png", "normal_revealed.png",
               "hidden.png", "student.ply", "steganerf_networks.msgpack", "steganerf.json"):
    assert (workdir / name).is_file(), name
  saved = json.loads((workdir / "baseline.json").read_text())
  metrics = json.loads((workdir / "metrics.json").read_text())
  assert saved["method"] == "StegaNeRF" and saved["iterations"] == 6 and saved["key"] == dict(kind="train_index",
                                                                                               index=4)
  assert saved["steganerf"]["settings"]["protocol"] == protocol and saved["wall_time_s"] > 0
  views = saved["test_views_hidden"]
  assert views["num_views"] == 1 and all(np.isfinite(v) for v in views.values())
  for section in ("student_vs_ground_truth", "teacher_vs_ground_truth", "student_vs_teacher", "hidden", "leakage"):
    assert all(np.isfinite(v) for v in metrics[section].values()), section
  assert result["metrics"]["hidden"] == metrics["hidden"]
  history = json.loads((workdir / "steganerf.json").read_text())["history"]
  assert [h["step"] for h in history] == [2, 3, 4, 6] and all(np.isfinite(h["classifier"]) for h in history)

  teacher, student = ply.load_ply(tiny[1]), ply.load_ply(workdir / "student.ply")
  for field in ("means", "log_scales", "quats", "opacity_logits"):
    np.testing.assert_array_equal(np.asarray(getattr(student, field)), np.asarray(getattr(teacher, field)), field)
  assert not np.array_equal(np.asarray(student.sh), np.asarray(teacher.sh))
  return saved, metrics


@pytest.mark.job
def test_all_views_run_freezes_geometry_scores_and_resumes_exactly(all_views_runs, tiny):
  straight, first, resumed, again, stopped = all_views_runs
  assert stopped == dict(stopped_at=3)
  saved, _ = _check_run(straight, first, tiny, "all_views")
  resaved, _ = _check_run(resumed, again, tiny, "all_views")
  assert saved["resumed_from"] == 0 and resaved["resumed_from"] == 3
  assert saved["steganerf"]["traces"] == dict(steganerf_step=1)
  for name in ("student.ply", "steganerf_networks.msgpack"):
    assert (straight / name).read_bytes() == (resumed / name).read_bytes(), name


@pytest.mark.job
def test_check_view_run_freezes_geometry_and_scores(check_view_run, tiny):
  workdir, result = check_view_run
  saved, _ = _check_run(workdir, result, tiny, "check_view")
  assert saved["steganerf"]["settings"]["mask_at"] == "gradient" and saved["resumed_from"] == 0


@pytest.mark.job
def test_bench_rows_of_both_protocols_feed_the_reproduction(all_views_runs, check_view_run, tiny, tmp_path,
                                                            monkeypatch):
  monkeypatch.setattr(reproduce, "RECIPE_STEPS", 6)  # the tiny runs' length stands for the recipes'
  bench, out = tmp_path / "bench", tmp_path / "results"
  shutil.copytree(all_views_runs[0], bench / "lego" / "baseline_steganerf_all_views")
  shutil.copytree(check_view_run[0], bench / "lego" / "baseline_steganerf_check_view")
  (bench / "lego" / "teacher").mkdir()
  shutil.copy(tiny[1], bench / "lego" / "teacher" / "point_cloud.ply")
  rows = bench_baselines.run("lego", ["steganerf_all_views", "steganerf_check_view"], 0, 0, bench, out, reuse=True)
  assert [r["label"] for r in rows] == ["StegaNeRF (all views)", "StegaNeRF (check view)"]
  saved = json.loads((out / "baseline_bench.json").read_text())["rows"]
  for row, run_dir in zip(saved, (all_views_runs[0], check_view_run[0])):
    metrics = json.loads((run_dir / "metrics.json").read_text())
    summary = json.loads((run_dir / "baseline.json").read_text())
    for key in ("student_vs_ground_truth", "teacher_vs_ground_truth", "student_vs_teacher", "hidden", "leakage"):
      assert row[key] == metrics[key], key
    assert row["method"] == "StegaNeRF" and row["wall_time_s"] == summary["wall_time_s"] > 0
    assert row["test_views_hidden"] == summary["test_views_hidden"]
  assert saved[0]["protocol"].startswith("all_views") and saved[1]["protocol"].startswith("check_view")
  assert "StegaNeRF (all views)" in (out / "baseline_bench.md").read_text() and (out / "baseline_bench.png").is_file()
  config = bench_baselines.run_config("lego", tiny[1], "steganerf_check_view", 100, 5)
  baseline.validate(config)
  assert (config.baseline.method, config.baseline.steganerf.protocol) == ("steganerf", "check_view")
  assert config.baseline.steganerf.decoder_lr == config.baseline.steganerf.classifier_lr == 3e-4
  st = saved[1]["steganerf"]["settings"]  # the run's own rates, in words
  assert f"classifier width {st['classifier_width']} at {st['decoder_lr']:g} / {st['classifier_lr']:g}," in saved[1][
      "protocol"]

  table1 = reproduce.report(out, bench)
  table1 = table1[table1.index("Table 1"):table1.index("Table 2")]
  h = saved[1]["hidden"]
  assert f"{h['psnr']:.2f} / {h['ssim']:.4f} | {saved[1]['protocol']}, 1 seed (0) |" in table1
  assert reproduce.NOT_RUN not in table1[table1.index("| StegaNeRF"):table1.index("| ConcealGS")]


@pytest.mark.parametrize("field,value,message", [
    ("protocol", "every_view", "baseline.steganerf.protocol"), ("mask_at", "weights", "baseline.steganerf.mask_at"),
    ("weight_render", -1.0, "baseline.steganerf.weight_render"),
    ("weight_hidden", 0.0, "baseline.steganerf.weight_hidden"),
    ("weight_classifier", -0.1, "baseline.steganerf.weight_classifier"),
    ("decoder_width", 0, "baseline.steganerf.decoder_width"),
    ("classifier_width", 0, "baseline.steganerf.classifier_width"),
    ("decoder_lr", 0.0, "baseline.steganerf.decoder_lr"), ("classifier_lr", -1e-3, "baseline.steganerf.classifier_lr"),
    ("log_every", 0, "baseline.steganerf.log_every"), ("checkpoint_every", -1, "baseline.steganerf.checkpoint_every"),
    ("networks_lr_final_ratio", 0.0, "baseline.steganerf.networks_lr_final_ratio"),
    ("sh_adam_eps", 0.0, "baseline.steganerf.sh_adam_eps"),
    ("hidden_size", 12, "mark.hidden_size")])
def test_bad_steganerf_config_is_named_before_anything_is_written(tiny, tmp_path, field, value, message):
  config = stega_config(tiny, "all_views")
  if field == "hidden_size":
    config.mark.hidden_size = value
  else:
    config.baseline.steganerf[field] = value
  with pytest.raises(ValueError, match=message):
    main_lib.run(config, str(tmp_path / "out"))
  assert not (tmp_path / "out").exists()
