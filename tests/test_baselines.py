"""The LSB and DeepStega baselines: the pure hiding functions, the DeepStega networks and their training, and
the baseline job end to end on a tiny generated scene (outputs, resume, reuse of trained networks, clear
errors)."""
from __future__ import annotations

import dataclasses
import json
import pathlib
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from conceal_jax import main as main_lib
from conceal_jax.baselines import baseline, containers, deepstega, deepstega_train, lsb
from conceal_jax.conceal import hidden as hidden_lib
from conceal_jax.configs import demo
from conceal_jax.core import fileio
from conceal_jax.data import datasets
from conceal_jax.configs import recipes
from experiments import bench_baselines, bench_conceal, reproduce
from tests.helpers import set_field
from tests.test_conceal import tiny  # noqa: F401  (the 32x32 demo scene and random teacher)


def _exact_8bit(rng, shape):
  return rng.integers(0, 256, size=shape).astype(np.float32) / 255


@pytest.mark.parametrize("bits", [1, 2, 3, 4])
def test_lsb_round_trip_recovers_the_secret_and_changes_only_the_low_bits(bits):
  rng = np.random.default_rng(bits)
  views, secret = _exact_8bit(rng, (3, 16, 20, 3)), rng.uniform(0, 1, (16, 20, 3)).astype(np.float32)
  stego = np.asarray(lsb.embed(views, secret, bits))
  levels, cover_levels = np.round(stego * 255).astype(int), np.round(views * 255).astype(int)
  np.testing.assert_allclose(stego * 255, levels, atol=1e-4)  # containers are 8-bit images
  assert np.abs(levels - cover_levels).max() <= 2**bits - 1
  np.testing.assert_array_equal(levels >> bits, cover_levels >> bits)
  recovered = np.asarray(lsb.extract(stego, bits))
  assert np.abs(recovered - secret[None]).max() <= 0.5 / (2**bits - 1) + 1e-6
  revealed = np.asarray(lsb.reveal_lsb(stego[:, :16, :16], bits=bits, size=16))
  np.testing.assert_allclose(revealed, recovered[:, :16, :16], atol=1e-6)  # same size: no resampling


def test_lsb_reveal_reads_noise_from_a_clean_image_and_rejects_bad_bits():
  """Low bits of an image that hides nothing are unrelated to the secret; bits outside 1..4 are named."""
  rng = np.random.default_rng(0)
  secret = rng.uniform(0, 1, (16, 16, 3)).astype(np.float32)
  clean = np.asarray(lsb.lsb_reveal(2, 16)(_exact_8bit(rng, (1, 16, 16, 3))))[0]
  assert float(np.mean((clean - secret)**2)) > 0.05
  for bits in (0, 5, 2.0, True):
    with pytest.raises(ValueError, match="baseline.lsb_bits"):
      lsb.embed(np.zeros((1, 4, 4, 3)), np.zeros((4, 4, 3)), bits)
  with pytest.raises(ValueError, match="shape"):
    lsb.embed(np.zeros((1, 4, 4, 3)), np.zeros((4, 5, 3)), 1)


def test_hidden_image_at_view_size_and_container_scene():
  assert np.array_equal(containers.hidden_at_view("astronaut", 24, 24), hidden_lib.load_hidden_image("astronaut", 24))
  wide = containers.hidden_at_view("astronaut", 12, 30)
  assert wide.shape == (12, 30, 3) and wide.dtype == np.float32 and 0 <= wide.min() and wide.max() <= 1
  views = [np.zeros((4, 6, 3), np.float32)] * 2
  scene = datasets.SceneData(train_images=views, test_images=views[:1], train_cameras=[None, None],
                             test_cameras=[None], points=None, point_colors=None, background=(1.0, 1.0, 1.0))
  replaced = containers.container_scene(scene, np.ones((2, 4, 6, 3)))
  assert len(replaced.train_images) == 2 and replaced.train_images[1].max() == 1.0
  assert replaced.test_images is scene.test_images and replaced.train_cameras is scene.train_cameras
  with pytest.raises(ValueError, match="containers"):
    containers.container_scene(scene, np.ones((3, 4, 6, 3)))


ARCH = deepstega.Architecture(width=2, prep_depth=1, hide_depth=2, reveal_depth=1)


def test_deepstega_networks_are_fully_convolutional_and_the_loss_is_balujas():
  params = deepstega.init_networks(jax.random.key(0), ARCH)
  rng = np.random.default_rng(0)
  covers, secrets, noise = (jnp.asarray(rng.uniform(0, 1, (2, 12, 20, 3)), jnp.float32) for _ in range(3))
  hide, reveal = (jax.jit(f, static_argnums=1) for f in (deepstega.hide, deepstega.reveal_secret))
  stego = hide(params, ARCH, covers, secrets)
  assert stego.shape == covers.shape and reveal(params, ARCH, stego).shape == covers.shape
  loss, aux = jax.jit(deepstega.stega_loss, static_argnums=1)(params, ARCH, covers, secrets, 0.01 * noise, 0.5)
  revealed = reveal(params, ARCH, stego + 0.01 * noise)
  expected = jnp.mean((stego - covers)**2) + 0.5 * jnp.mean((revealed - secrets)**2)
  np.testing.assert_allclose(float(loss), float(expected), rtol=1e-5)
  # the reveal network learns from the secret term only; the hiding networks from both
  cover_term = lambda p: deepstega.stega_loss(p, ARCH, covers, secrets, noise, 1.0)[1]["cover_mse"]
  cover_grads = jax.jit(jax.grad(cover_term))(params)
  assert all(float(jnp.abs(g).max()) == 0 for g in jax.tree.leaves(cover_grads["reveal"]))
  assert any(float(jnp.abs(g).max()) > 0 for g in jax.tree.leaves(cover_grads["hide"]))


def test_deepstega_cover_skip_adds_the_hiding_output_to_the_cover_and_round_trips(tmp_path):
  skip = dataclasses.replace(ARCH, cover_skip=True)
  params = deepstega.init_networks(jax.random.key(2), skip)  # the same params as without the skip
  jax.tree.map(lambda a, b: np.testing.assert_array_equal(a.shape, b.shape), params,
               deepstega.init_networks(jax.random.key(2), ARCH))
  rng = np.random.default_rng(1)
  covers, secrets = (jnp.asarray(rng.uniform(0, 1, (2, 10, 14, 3)), jnp.float32) for _ in range(2))
  np.testing.assert_allclose(deepstega.hide(params, skip, covers, secrets),
                             covers + deepstega.hide(params, ARCH, covers, secrets), rtol=1e-6, atol=1e-6)
  deepstega.save_networks(str(tmp_path / "skip.msgpack"), params, skip)
  assert deepstega.load_networks(str(tmp_path / "skip.msgpack"))[1] == skip
  with pytest.raises(ValueError, match="baseline.deepstega.cover_skip"):
    deepstega.Architecture(cover_skip=1)


def test_deepstega_views_are_8bit_containers_and_reveal_resizes(tmp_path):
  params = deepstega.init_networks(jax.random.key(1), ARCH)
  views = np.random.default_rng(0).uniform(0, 1, (5, 16, 24, 3)).astype(np.float32)  # more than one chunk
  stego = np.asarray(deepstega.hide_in_views(params, ARCH, views, views[0]))
  assert stego.shape == views.shape and 0 <= stego.min() and stego.max() <= 1
  np.testing.assert_allclose(stego * 255, np.round(stego * 255), atol=1e-4)
  one_by_one = np.asarray(deepstega.hide(params, ARCH, jnp.asarray(views[3:4]), jnp.asarray(views[:1])))
  np.testing.assert_allclose(stego[3], np.round(np.clip(one_by_one[0], 0, 1) * 255) / 255, atol=1.5 / 255)
  revealed = np.asarray(deepstega.stega_reveal(params, ARCH, 8)(stego))
  assert revealed.shape == (5, 8, 8, 3) and 0 <= revealed.min() and revealed.max() <= 1

  deepstega.save_networks(str(tmp_path / "nets.msgpack"), params, ARCH)
  loaded, arch = deepstega.load_networks(str(tmp_path / "nets.msgpack"))
  assert arch == ARCH
  jax.tree.map(np.testing.assert_array_equal, loaded, params)
  (tmp_path / "bad.msgpack").write_bytes(b"\x00garbage")
  other = deepstega.Architecture(width=3, prep_depth=1, hide_depth=2, reveal_depth=1)
  deepstega.save_networks(str(tmp_path / "mismatch.msgpack"), params, other)
  for name in ("bad.msgpack", "missing.msgpack", "mismatch.msgpack"):
    with pytest.raises(ValueError, match=name):
      deepstega.load_networks(str(tmp_path / name))


def test_deepstega_training_step_fits_a_batch():
  """Adam steps on one batch of covers and secrets lower the loss, deterministically from the seed."""
  tx = optax.adam(3e-3)
  step = deepstega_train.make_stega_step(ARCH, tx, 1.0, 0.01, seed=0)
  rng = np.random.default_rng(0)
  pool = rng.uniform(0, 1, (4, 24, 24, 3)).astype(np.float32)
  covers, secrets = (jnp.asarray(deepstega_train.random_crops(pool, 4, 12, rng)) for _ in range(2))
  losses = []
  for _ in range(2):
    params = deepstega.init_networks(jax.random.key(0), ARCH)
    state = deepstega_train.StegaState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params))
    for _ in range(60):
      state, stats = step(state, covers, secrets)
    losses.append(float(stats["loss"]))
  first = float(deepstega.stega_loss(deepstega.init_networks(jax.random.key(0), ARCH), ARCH, covers, secrets,
                                     jnp.zeros_like(covers), 1.0)[0])
  assert losses[0] == losses[1] and losses[0] < 0.5 * first


def test_sample_split_keeps_the_hidden_image_out_of_training():
  train_names, held_out = deepstega_train.sample_split("coffee")
  assert "coffee" not in train_names + held_out and set(held_out) == {"chelsea", "rocket"}
  assert not set(train_names) & set(deepstega_train.HELD_OUT_SAMPLES)
  crops = deepstega_train.random_crops(np.zeros((3, 10, 10, 3)), 5, 4, np.random.default_rng(0))
  assert crops.shape == (5, 4, 4, 3)


def tiny_config(tiny, method, **baseline_overrides):
  scene_path, teacher = tiny
  config = demo.get_config()
  config.mode = "baseline"
  config.data.path = str(scene_path)
  config.render.tile_size = 8
  config.eval.max_views = 1
  config.mark.teacher, config.conceal.iterations, config.mark.hidden_size = str(teacher), 6, 16
  config.train.log_every, config.train.checkpoint_every, config.train.progress_bar = 2, 3, False
  config.baseline.method = method
  d = config.baseline.deepstega
  d.width, d.prep_depth, d.hide_depth, d.reveal_depth = 2, 1, 1, 1
  d.crop_size, d.batch_size, d.held_out_pairs, d.iterations = 16, 2, 2, 4
  d.log_every, d.checkpoint_every, d.progress_bar = 2, 2, False
  for name, value in baseline_overrides.items():
    if name.startswith("deepstega_"):
      d[name[len("deepstega_"):]] = value
    else:
      config.baseline[name] = value
  return config


def _check_outputs(workdir, result, method):
  for name in ("metrics.json", "baseline.json", "revealed.png", "teacher_revealed.png", "normal_revealed.png",
               "hidden.png", "container_revealed.png", "train/point_cloud.ply", "train/train.json"):
    assert (workdir / name).is_file(), name
  metrics = json.loads((workdir / "metrics.json").read_text())
  saved = json.loads((workdir / "baseline.json").read_text())
  assert (saved["method"], saved["seed"], saved["iterations"]) == (method, 0, 6)
  assert saved["key"] == dict(kind="train_index", index=4)
  train_json = json.loads((workdir / "train" / "train.json").read_text())
  assert saved["wall_time_s"] == train_json["wall_time_s"] > 0 and train_json["num_gaussians"] == 1200
  for section in ("student_vs_ground_truth", "teacher_vs_ground_truth", "student_vs_teacher", "hidden", "leakage"):
    assert all(np.isfinite(v) for v in metrics[section].values()), section
  assert result["metrics"]["hidden"] == metrics["hidden"]
  return saved, metrics


@pytest.fixture(scope="module")
def lsb_run(tiny, tmp_path_factory):
  """A 4-bit LSB run of 6 steps, stopped after 3 and resumed: (workdir, first result, final result)."""
  workdir = tmp_path_factory.mktemp("lsb")
  config = tiny_config(tiny, "lsb", lsb_bits=4)
  stopped = baseline.baseline_and_evaluate(config, str(workdir), max_steps=3)
  return workdir, stopped, main_lib.run(config, str(workdir))


@pytest.mark.job
def test_lsb_job_trains_on_containers_scores_and_resumes(lsb_run):
  workdir, stopped, result = lsb_run
  assert stopped == dict(stopped_at=3)
  saved, metrics = _check_outputs(workdir, result, "LSB")
  assert saved["resumed_from"] == 3 and saved["lsb_bits"] == 4
  # the image is in the check view's container, and 4 low bits are a visible change to the views
  check = saved["containers"]["check_view_hidden"]
  assert check["psnr"] > 25 and check["ssim"] > 0.8
  assert 25 < saved["containers"]["psnr_to_views"] < 40
  # six steps from a random teacher are far from reproducing the low bits
  assert metrics["hidden"]["psnr"] < check["psnr"] - 10


@pytest.mark.job
def test_bench_rows_feed_the_reproduction(lsb_run, deepstega_run, tiny, tmp_path, capsys, monkeypatch):
  """bench-baselines reads finished runs into baseline_bench.json (keeping another method's rows), and
  make reproduce puts them beside the paper's numbers (the tiny runs' length standing for the recipes'); a row
  without a run or a scene without a teacher is skipped, and a row's config is the one the job validates."""
  monkeypatch.setattr(reproduce, "RECIPE_STEPS", 6)
  workdir, _, _ = lsb_run
  bench, out = tmp_path / "bench", tmp_path / "results"
  shutil.copytree(workdir, bench / "lego" / "baseline_lsb4")
  shutil.copytree(deepstega_run[1], bench / "lego" / "baseline_deepstega")
  (bench / "lego" / "teacher").mkdir()
  shutil.copy(tiny[1], bench / "lego" / "teacher" / "point_cloud.ply")
  metrics = json.loads((workdir / "metrics.json").read_text())
  other = dict(metrics, method="StegaNeRF", scene="lego", row="steganerf_check_view", iterations=6,
               steganerf=dict(settings=dict(decoder_width=2)), protocol="theirs", wall_time_s=1.0, revealed="",
               student_psnr_loss=0.5, max_leakage=0.1)
  fileio.write_json(out / "baseline_bench.json", dict(rows=[other]))

  rows = bench_baselines.run("lego", ["lsb1", "lsb4", "deepstega"], 0, 0, bench, out, reuse=True)
  assert [r["row"] for r in rows] == ["lsb4", "deepstega"] and "no finished run" in capsys.readouterr().out
  saved = json.loads((out / "baseline_bench.json").read_text())["rows"]
  assert [r["method"] for r in saved] == ["StegaNeRF", "LSB", "DeepStega"]
  assert saved[2]["protocol"].startswith("networks width 2, layers 1/1/1, held-out cover")
  assert saved[2]["deepstega"]["held_out"] == deepstega_run[2]["deepstega"]["held_out"]
  row = saved[1]
  for key in ("student_vs_ground_truth", "teacher_vs_ground_truth", "student_vs_teacher", "hidden", "leakage"):
    assert row[key] == metrics[key], key
  assert row["scene"] == "lego" and row["label"] == "LSB 4 bits" and row["protocol"].startswith("4 low bit")
  # the revealed image is kept beside the JSON: the figure outlives the workdir
  assert row["wall_time_s"] > 0 and row["images"] == dict(revealed="revealed/lego/baseline_lsb4/revealed.png")
  assert (out / row["images"]["revealed"]).read_bytes() == (workdir / "revealed.png").read_bytes()
  assert (out / "baseline_bench.md").is_file() and (out / "baseline_bench.png").is_file()

  table1 = reproduce.report(out, bench)
  table1 = table1[table1.index("Table 1"):table1.index("Table 2")]
  h = metrics["hidden"]
  assert "| LSB | 33.05 / 0.9704 / 0.0253 | 6.13 / 0.1218 | " in table1
  assert f"{h['psnr']:.2f} / {h['ssim']:.4f} | {row['protocol']}, 1 seed (0) |" in table1
  assert f"| DeepStega | 33.06 / 0.9702 / 0.0253 | 11.13 / 0.2265 | " in table1 and reproduce.NOT_RUN not in \
      table1[table1.index("| DeepStega"):table1.index("| StegaNeRF")]
  assert "| StegaNeRF | 30.33" in table1 and "| theirs, 1 seed (0) |" in table1
  assert "| StegaNeRF | steganerf_check_view | 2 | 6 |" in reproduce.report(out, bench)  # beside ConcealGS's runs

  assert bench_baselines.run("lego", ["lsb1"], 0, 0, tmp_path / "empty", out, reuse=False) == []
  assert "no teacher" in capsys.readouterr().out
  config = bench_baselines.run_config("lego", tiny[1], "lsb3", 100, 5)
  baseline.validate(config)
  assert (config.mode, config.baseline.method, config.baseline.lsb_bits) == ("baseline", "lsb", 3)
  assert (config.baseline.iterations, config.eval.max_views, config.mark.hidden) == (100, 5, "astronaut")
  # containers train with the rates of the ConcealGS row beside them; StegaNeRF keeps its own
  gentle = recipes.gentle_student(bench_conceal.run_config("lego", tiny[1], "full", 16, 100, 5)).conceal.lr
  assert config.conceal.lr.to_dict() == gentle.to_dict()
  stega = bench_baselines.run_config("lego", tiny[1], "steganerf_all_views", 100, 5)
  assert stega.conceal.lr.sh_dc != gentle.sh_dc and stega.conceal.lr.warmup_steps == 0
  # a row's own length (StegaNeRF given ConcealGS's polish steps too), which --iterations still shortens
  long_row = lambda iterations: bench_baselines.run_config("lego", tiny[1], "steganerf_check_view_12k", iterations, 5)
  assert (long_row(0).baseline.iterations, long_row(100).baseline.iterations) == (12_000, 100)
  assert long_row(0).baseline.steganerf.protocol == "check_view"
  assert long_row(0).baseline.steganerf.decoder_lr == long_row(0).baseline.steganerf.classifier_lr == 3e-4
  seeded = bench_baselines.run_config("lego", tiny[1], "steganerf_check_view_seed1", 100, 5)
  assert (seeded.seed, stega.seed, seeded.baseline.steganerf.protocol) == (1, 0, "check_view")
  assert "seed" not in seeded.baseline
  skip = bench_baselines.run_config("lego", tiny[1], "deepstega_skip", 100, 5)
  baseline.validate(skip)
  assert baseline.deepstega_settings(skip)[0].cover_skip and skip.conceal.lr.to_dict() == gentle.to_dict()
  skip_result = dict(saved[2], deepstega=dict(saved[2]["deepstega"], architecture=dict(
      saved[2]["deepstega"]["architecture"], cover_skip=True)))
  assert bench_baselines.label(skip_result) == "DeepStega (cover skip)"
  assert "layers 1/1/1 with the cover skip, held-out" in bench_baselines.protocol(skip_result)
  # a seed other than 0 is named; runs written before the seed was recorded read as seed 0
  assert ", seed 2, no densification" in bench_baselines.protocol(dict(skip_result, seed=2))
  assert "seed" not in bench_baselines.protocol({k: v for k, v in skip_result.items() if k != "seed"})


@pytest.fixture(scope="module")
def deepstega_run(tiny, tmp_path_factory):
  """A DeepStega run (4 network steps, 6 scene steps): (config, workdir, result)."""
  workdir = tmp_path_factory.mktemp("deepstega")
  config = tiny_config(tiny, "deepstega")
  return config, workdir, main_lib.run(config, str(workdir))


@pytest.mark.job
def test_deepstega_job_trains_saves_and_reuses_its_networks(deepstega_run):
  config, tmp_path, result = deepstega_run
  saved, _ = _check_outputs(tmp_path, result, "DeepStega")
  report = saved["deepstega"]
  assert report["reused"] is False and report["training"]["timed_steps"] == 4
  assert report["architecture"] == dict(width=2, prep_depth=1, hide_depth=1, reveal_depth=1, cover_skip=False)
  held_out = report["held_out"]
  assert held_out["pairs"] == 2 and held_out["covers"] == "test views" and "astronaut" not in held_out["secrets"]
  assert all(np.isfinite(held_out[k]) for k in ("cover_psnr", "secret_psnr", "cover_ssim", "secret_ssim"))
  for name in ("networks.msgpack", "deepstega.json", "checkpoints"):
    assert (tmp_path / "deepstega" / name).exists(), name
  scene = datasets.load_scene(config.data.path)
  params, arch, again = baseline.deepstega_networks(config, scene, str(tmp_path))
  assert again["reused"] is True and again["held_out"] == held_out
  saved_params, _ = deepstega.load_networks(str(tmp_path / "deepstega" / "networks.msgpack"))
  jax.tree.map(np.testing.assert_array_equal, params, saved_params)


@pytest.mark.parametrize("field,value,message", [
    ("baseline.method", "stega", "baseline.method"), ("baseline.lsb_bits", 0, "baseline.lsb_bits"),
    ("baseline.lsb_bits", 5, "baseline.lsb_bits"), ("baseline.iterations", -1, "baseline.iterations"),
    ("baseline.deepstega.width", 0, "baseline.deepstega.width"),
    ("baseline.deepstega.noise_std", 1.5, "baseline.deepstega.noise_std"),
    ("baseline.deepstega.crop_size", 0, "baseline.deepstega.crop_size"),
    ("baseline.deepstega.iterations", 0, "iterations"),
    ("baseline.deepstega.networks", "/no/such.msgpack", "baseline.deepstega.networks"),
    ("mark.teacher", "", "mark.teacher"), ("mark.teacher", "/no/such.ply", "no such file"),
    ("mark.key_kind", "random", "mark.key_kind"), ("mark.hidden_size", 0, "mark.hidden_size"),
    ("conceal.lr.means_steps", -1, "means_steps"), ("mark.extra_hidden", ("camera",), "mark.extra_hidden")])
def test_bad_baseline_config_is_named_before_anything_is_written(tiny, tmp_path, field, value, message):
  config = tiny_config(tiny, "deepstega")
  set_field(config, field, value)
  with pytest.raises(ValueError, match=message):
    main_lib.run(config, str(tmp_path / "out"))
  assert not (tmp_path / "out").exists()


def test_bad_hidden_image_is_named(tiny, tmp_path):
  config = tiny_config(tiny, "lsb")
  config.mark.hidden = "no_such_sample"
  with pytest.raises(ValueError, match="no_such_sample"):
    baseline.baseline_and_evaluate(config, str(tmp_path))
