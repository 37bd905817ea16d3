"""make bench-survive (and bench-falloff) on a tiny marked scene: rows for every attack group asked for, with the
fields issue 39 names, re-alignment after the transforms, resumed without recomputing finished rows; the round trips
skip cleanly without splat-transform (make node_modules)."""
from __future__ import annotations

import dataclasses
import json
import math

import jax
import ml_collections
import numpy as np
import pytest

from conceal_jax.conceal import key as key_lib, near, reveal, unet
from conceal_jax.configs import demo
from conceal_jax.core import fileio
from conceal_jax.data import demo_scene, ply
from conceal_jax.gs import evaluate
from conceal_jax.robust import converter
from conceal_jax.splat.render import RenderOptions
from experiments import bench_survive
from tests.test_reveal_alignment import blobs

FIELDS = {"scene", "recipe", "attack", "level", "render_psnr", "hidden_psnr", "hidden_ssim", "owned", "log10_p",
          "verify", "decided"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
  """A conceal workdir of a 32x32 demo scene: a student of 8 coloured clusters (800 Gaussians), an untrained
  width-4 decoder, a key at a training camera; and a calibration file."""
  folder = tmp_path_factory.mktemp("survive")
  scene_path = demo_scene.generate_demo_scene(folder / "scene", num_train=4, num_test=2, size=32)
  ply.save_ply(folder / "run" / "student.ply", jax.tree.map(np.asarray, blobs(800)))
  config = demo.get_config()
  config.data.path = str(scene_path)
  config.init.num_random_points = 500
  from conceal_jax.data import datasets
  camera = datasets.load_scene(scene_path).train_cameras[1]
  reveal.save_decoder(str(folder / "run" / "decoder.msgpack"), unet.init_decoder(jax.random.key(0), 4, 16))
  key_lib.save_key(str(folder / "run" / "key.json"), camera, dict(
      hidden_size=16, uses_decoder=True, decoder_width=4, render_options=dict(background=[1.0, 1.0, 1.0])))
  # the hidden image: what the untouched student reveals at the key (an untrained decoder reveals no image)
  student = jax.tree.map(jax.numpy.asarray, ply.load_ply(folder / "run" / "student.ply"))
  revealed = reveal.reveal_image(student, camera, RenderOptions(background=(1.0, 1.0, 1.0)),
                                 reveal.load_decoder(str(folder / "run" / "decoder.msgpack")), 4, 16)
  fileio.write_image(folder / "hidden.png", np.asarray(revealed))
  config.mark.hidden = str(folder / "hidden.png")
  config.mark.teacher = str(folder / "run" / "student.ply")  # the clean scene (the student is untouched here)
  fileio.write_json(folder / "run" / "config.json", config.to_dict())
  # a threshold near 0.975: an untrained decoder's output varies little with what it is shown
  (folder / "cal.json").write_text(json.dumps(dict(clean=[0.95], marked=[0.999])))
  return folder


def bench(folder, monkeypatch, *arguments):
  monkeypatch.setattr(bench_survive, "TRANSFORMS", [("rotate", 180.0)])
  monkeypatch.setattr(bench_survive, "CONVERSIONS", [("decimate", 0.5, dict(fmt="ply", decimate=0.5))])
  bench_survive.main([f"--out={folder / 'out'}", f"--workdir={folder / 'work'}", f"--scenes=tiny={folder / 'run'}",
                      f"--calibration={folder / 'cal.json'}", "--test-views=1", "--alpha=1e-3", "--null-views=4",
                      *arguments])
  return json.loads((folder / "out" / "survive_bench.json").read_text())["rows"]


@pytest.mark.job
def test_transforms_and_round_trips_are_revealed_after_re_alignment(run, monkeypatch):
  # the decimations alone of the round trips: each format's round trip is tests/test_converter.py's
  rows = bench(run, monkeypatch, "--attacks=none,transforms,decimate")
  by = {(r["attack"], r["level"]): r for r in rows}
  none = by["none", None]
  assert all(FIELDS <= set(r) for r in rows) and {r["recipe"] for r in rows} == {"recommended"}
  assert none["hidden_ssim"] > 0.99 and none["decided"]
  for level in (("rotate", 180.0),):
    row = by[level]
    # re-aligned, the moved scene reveals what the untouched one does, and renders its test views as well
    assert row["hidden_ssim"] == pytest.approx(none["hidden_ssim"], abs=0.01)
    assert row["render_psnr"] == pytest.approx(none["render_psnr"], abs=0.1)
    assert row["registration"]["rotation_error_deg"] < 0.01 and row["registration"]["scale_error"] < 1e-4
    assert row["unaligned"]["hidden_ssim"] < row["hidden_ssim"] - 0.03 and row["decided"]
    assert not row["unaligned"]["decided"]
    # verify's test given the owner's copy: the moved scene re-aligned is tested as the untouched one is
    assert row["owned"] == none["owned"] and row["log10_p"] == pytest.approx(none["log10_p"], abs=0.05)
    assert set(row["verify"]["readings"]) == {"toned", "scene_toned", "as_rendered"}
  if converter.available():
    row = by["decimate", 0.5]
    # the converter merges Gaussians as it decimates: 400 left of 800 register to within a degree
    assert row["num_gaussians"] == 400 and row["aligned"]["registration"]["rotation_error_deg"] < 2.0
    # moved by a random similarity, then published: the re-aligned key reveals about as the published scene does
    assert row["moved"]["registration"]["rotation_error_deg"] < 2.0
    assert row["moved"]["hidden_ssim"] == pytest.approx(row["hidden_ssim"], abs=0.05)
  else:
    assert "decimate" not in {r["attack"] for r in rows}
  assert (run / "out" / "survive_bench.png").is_file()
  assert "| tiny | recommended | rotate | 180 |" in (run / "out" / "survive_bench.md").read_text()

  # a second invocation keeps the finished rows and computes nothing again
  def fail(*_):
    raise AssertionError("a finished row was recomputed")
  for name in ("transform_rows", "converter_rows", "scores_of"):
    monkeypatch.setattr(bench_survive, name, fail)
  again = bench(run, monkeypatch, "--attacks=none")
  assert [bench_survive.row_key(r) for r in again] == [bench_survive.row_key(r) for r in rows]


@pytest.mark.slow  # a training run's compilation: over a minute on two shared cores
def test_finetune_and_extraction_rows_at_each_length(run, monkeypatch):
  freed = []
  monkeypatch.setattr(bench_survive, "drop_compilations", lambda: freed.append(1))
  rows = bench(run, monkeypatch, "--attacks=finetune,finetune_gentle", "--finetune-steps=2,4", "--extraction",
               "--extraction-views=6", "--extraction-steps=2,4")
  assert len(freed) >= len(rows)  # each scored snapshot's compiled programs are freed
  extracted = [r for r in rows if r["attack"] == "extraction"]
  assert [(r["level"], r["steps"]) for r in extracted] == [(6, 2), (6, 4)] and all(FIELDS <= set(r) for r in extracted)
  assert all(r["key_nearest_deg"] == pytest.approx(0.0, abs=1e-3) for r in extracted)  # the key: training camera 1
  tuned = [r for r in rows if r["attack"] == "finetune"]
  assert [r["level"] for r in tuned] == [2, 4] and all(FIELDS <= set(r) for r in tuned)
  cache = run / "work" / "run"  # a scene given by path caches under the folder of the run it attacks
  assert (cache / "finetune_fixed_4" / "point_cloud.ply").is_file()
  gentle = [r for r in rows if r["attack"] == "finetune_gentle"]
  assert [r["level"] for r in gentle] == [2, 4] and (cache / "finetune_gentle_4" / "point_cloud.ply").is_file()
  assert all(r["changed"] is not None for r in tuned + gentle)  # the student's degree-1 SH against the tuned degree 3


def test_extraction_views_form_a_blender_dataset(run, tmp_path):
  from conceal_jax.data import datasets
  scene = bench_survive.load_scene("tiny", run / "run", "recommended", 1,
                                   dict(threshold=0.5), tmp_path, 1e-3, 4)
  cameras = bench_survive.extraction_cameras(scene, 7)
  assert len(cameras) == 7
  bench_survive.write_blender_views(tmp_path / "views", scene.student, cameras, scene.cameras, scene.owner.options)
  loaded = datasets.load_scene(tmp_path / "views")
  assert len(loaded.train_cameras) == 7 and len(loaded.test_cameras) == len(scene.cameras)
  np.testing.assert_allclose(np.asarray(loaded.train_cameras[5].world_to_camera),
                             np.asarray(cameras[5].world_to_camera), atol=1e-5)
  assert float(loaded.train_cameras[0].fx) == pytest.approx(float(cameras[0].fx), rel=1e-5)


def test_sphere_extraction_poses_cover_the_sphere_and_look_at_the_target(run, tmp_path):
  """After the training cameras, poses spread over the whole sphere at the orbit's distance, each looking at the
  orbit's target (its optical axis through it), far below the training cameras included."""
  from conceal_jax.splat.camera import camera_centers
  scene = bench_survive.load_scene("tiny", run / "run", "recommended", 1,
                                   dict(threshold=0.5), tmp_path, 1e-3, 4)
  train_cameras = bench_survive.extraction_cameras(scene, 4)
  cameras = bench_survive.extraction_cameras(scene, 60, "sphere")
  assert len(cameras) == 60
  for a, b in zip(cameras[:4], train_cameras):
    np.testing.assert_array_equal(np.asarray(a.world_to_camera), np.asarray(b.world_to_camera))
  target, distance = key_lib.orbit_target(train_cameras), key_lib.camera_distance(train_cameras)
  centers = camera_centers(cameras[4:])
  np.testing.assert_allclose(np.linalg.norm(centers - target, axis=1), distance, rtol=1e-6)
  forward = np.stack([np.asarray(c.world_to_camera, np.float64)[2, :3] for c in cameras[4:]])
  np.testing.assert_allclose(np.einsum("vi,vi->v", forward, target - centers), distance, rtol=1e-5)
  directions = (centers - target) / distance
  assert directions.mean(0) == pytest.approx(np.zeros(3), abs=0.05)  # evenly spread: no hemisphere favoured
  with pytest.raises(ValueError, match="unknown extraction poses"):
    bench_survive.extraction_cameras(scene, 6, "ring")


def test_unseen_extraction_poses_leave_out_the_training_cameras_and_the_key(run, tmp_path):
  """unseen: random poses on the orbit, none a training camera; key_nearest_deg is 0 for views that include the
  key's pose (a training camera here) and the angle, from the orbit's target, to the nearest view otherwise."""
  from conceal_jax.splat.camera import camera_centers
  scene = bench_survive.load_scene("tiny", run / "run", "recommended", 1,
                                   dict(threshold=0.5), tmp_path, 1e-3, 4)
  train_cameras = bench_survive.extraction_cameras(scene, 4)
  unseen = bench_survive.extraction_cameras(scene, 5, "unseen")
  assert len(unseen) == 5
  gaps = np.linalg.norm(camera_centers(unseen)[:, None] - camera_centers(train_cameras)[None], axis=-1)
  assert gaps.min() > 1e-3
  assert bench_survive.key_nearest_deg(scene, train_cameras) == pytest.approx(0.0, abs=1e-3)
  # the run's key.json records no near_length: the key's turns are about the point the orbit's distance ahead
  length = key_lib.camera_distance(train_cameras)
  key = np.asarray(scene.owner.check_camera.world_to_camera, np.float64)
  angles = []
  for camera in unseen:
    w2c = np.asarray(camera.world_to_camera, np.float64)
    chord = np.linalg.norm(camera_centers([camera])[0] - camera_centers([scene.owner.check_camera])[0])
    rotation = math.acos(np.clip((np.trace(key[:3, :3] @ w2c[:3, :3].T) - 1) / 2, -1, 1))
    angles.append(math.degrees(max(2 * math.asin(chord / (2 * length)), rotation)))
  assert bench_survive.key_nearest_deg(scene, unseen) == pytest.approx(min(angles), abs=1e-4)
  assert min(angles) > 0.1


def test_unknown_extraction_poses_are_refused_before_any_work(run, tmp_path, capsys):
  with pytest.raises(SystemExit) as exit_info:
    bench_survive.main([f"--out={tmp_path / 'out'}", f"--workdir={tmp_path / 'work'}",
                        f"--scenes=tiny={run / 'run'}", f"--calibration={run / 'cal.json'}", "--attacks=none",
                        "--extraction", "--extraction-poses=orbit,ring"])
  assert exit_info.value.code != 0 and "unknown --extraction-poses ring" in capsys.readouterr().err
  assert not (tmp_path / "out").exists() and not (tmp_path / "work").exists()


def test_dropping_compilations_frees_the_compiled_programs():
  """A program called again compiles again only after drop_compilations (jax.monitoring's backend-compile events;
  a program this small is under the persistent cache's threshold, so each compile is a real one)."""
  compiles = []
  listener = lambda name, _, **kw: compiles.append(name) if name.endswith("backend_compile_duration") else None
  jax.monitoring.register_event_duration_secs_listener(listener)
  try:
    twice = jax.jit(lambda x: 2 * x + 1)
    twice(np.ones(3))
    twice(np.ones(3))
    kept = len(compiles)
    bench_survive.drop_compilations()
    twice(np.ones(3))
  finally:
    jax.monitoring.unregister_event_duration_listener(listener)
  assert kept == 1 and len(compiles) == 2


def test_gentle_fine_tuning_moves_every_field_less_than_the_3dgs_recipe():
  """One Adam step of each recipe on the same gradient: the gentle one (a warmup, lower rates) moves each field of
  the scene by at most a quarter as much, and by something."""
  import optax
  from conceal_jax.gs import optimizer
  config = demo.get_config()
  scene = blobs(50)
  grads = jax.tree.map(lambda x: np.ones_like(x), scene)
  moved = []
  for lr in (config.train.lr, bench_survive.gentle_rates(demo.get_config()).train.lr):
    tx = optimizer.gaussian_optimizer(lr, 1.0, 1000)
    updates, _ = tx.update(grads, tx.init(scene), scene)
    moved.append({f: float(np.max(np.abs(getattr(updates, f)))) for f in ("means", "sh", "opacity_logits",
                                                                          "log_scales", "quats")})
  full, gentle = moved
  assert all(0 < gentle[f] <= full[f] / 4 for f in full), (full, gentle)


def test_the_change_profile_names_what_training_moved():
  """Per field: the share of Gaussians moved and the RMS change over the spread; with a carrier film (the last
  Gaussians), the share of it moved; None once training added or removed Gaussians."""
  before = jax.tree.map(np.asarray, blobs(10))
  before = before.replace(opacity_logits=np.random.default_rng(0).normal(size=10))
  after = before.replace(opacity_logits=before.opacity_logits.copy(), sh=before.sh.copy())
  after.opacity_logits[:4] += 0.5
  after.sh[2, 0, 0] += 1.0
  profile = bench_survive.change_profile(before, after, carrier=3)
  assert profile["opacity_logits"]["moved"] == 0.4 and profile["sh"]["moved"] == 0.1
  assert profile["means"] == dict(moved=0.0, relative_rms=0.0)
  expected = np.sqrt(0.4 * 0.25) / before.opacity_logits.std()
  np.testing.assert_allclose(profile["opacity_logits"]["relative_rms"], expected, rtol=1e-6)
  assert profile["carrier_moved"] == 0.0
  after.sh[-1, 3, 2] += 0.1
  assert bench_survive.change_profile(before, after, carrier=3)["carrier_moved"] == 1 / 3
  assert bench_survive.change_profile(before, jax.tree.map(lambda x: x[:9], before)) is None


def test_falloff_rows_start_at_the_key_and_skip_missing_runs(run, tmp_path, capsys):
  """make bench-falloff on the same run: a row per angle, the key's own reveal at 0 degrees, runs without their
  files skipped, the table and plot written."""
  from experiments import bench_falloff
  out = tmp_path / "out"
  bench_falloff.main([f"--out={out}", f"--scenes=tiny={run / 'run'},gone={tmp_path / 'missing'}", "--directions=2"])
  rows = json.loads((out / "falloff_bench.json").read_text())["rows"]
  assert [r["angle_deg"] for r in rows] == list(bench_falloff.ANGLES_DEG) and {r["scene"] for r in rows} == {"tiny"}
  at_key = rows[0]
  # the hidden image is what the untouched student reveals at the key: one pose, SSIM 1
  assert at_key["directions"] == 1 and at_key["mean_ssim"] > 0.99 and at_key["max_ssim"] == at_key["mean_ssim"]
  assert all(r["directions"] == 2 and r["key_axes"] == len(near.KEY_AXES) and r["max_ssim"] >= r["mean_ssim"]
             for r in rows[1:])
  assert "skipping gone" in capsys.readouterr().out
  assert (out / "falloff_bench.md").read_text().count("| tiny |") == 1 and (out / "falloff_bench.png").is_file()
  # the orbit turns: rows of their own beside the head turns', the key itself at 0 degrees
  bench_falloff.main([f"--out={out}", f"--scenes=tiny={run / 'run'}", "--directions=2", "--turn=orbit"])
  rows = json.loads((out / "falloff_bench.json").read_text())["rows"]
  orbit = [r for r in rows if r["turn"] == "orbit"]
  assert [r["angle_deg"] for r in orbit] == list(bench_falloff.ORBIT_ANGLES_DEG)
  assert len(rows) == len(orbit) + len(bench_falloff.ANGLES_DEG)
  assert orbit[0]["mean_ssim"] == pytest.approx(at_key["mean_ssim"], abs=1e-5)  # the key, its pose recomputed
  assert all(r["directions"] == 2 and r["max_ssim"] >= r["mean_ssim"] for r in orbit[1:])
  assert (out / "falloff_bench.md").read_text().count("| tiny |") == 2


def test_a_cache_of_attacked_scenes_belongs_to_one_run(tmp_path, capsys):
  """A run's attacked scenes are cached for that run only: another student in the same cache is refused by name."""
  for name, size in (("a", 10), ("b", 20)):
    (tmp_path / name).mkdir()
    (tmp_path / name / "student.ply").write_bytes(b"x" * size)
  cache = tmp_path / "cache"
  bench_survive.claim_cache(cache, tmp_path / "a")
  bench_survive.claim_cache(cache, tmp_path / "a")  # the same run again: fine
  with pytest.raises(ValueError, match="holds the attacks of .*a/student.ply"):
    bench_survive.claim_cache(cache, tmp_path / "b")
  old = tmp_path / "old_cache"  # cached before runs were recorded: taken to be the run's, with a note
  (old / "sog_None").mkdir(parents=True)
  bench_survive.claim_cache(old, tmp_path / "b")
  assert "no source.json" in capsys.readouterr().out
  assert json.loads((old / bench_survive.CACHE_SOURCE).read_text())["size"] == 20


def test_round_trips_can_be_asked_for_by_name(run, monkeypatch, tmp_path):
  """--attacks=decimate runs the converter group's decimations only (a scene's .sog can take the CPU an hour)."""
  asked = []
  monkeypatch.setattr(converter, "available", lambda: True)
  monkeypatch.setattr(bench_survive, "converter_rows", lambda scene, todo: asked.extend(todo) or [])
  monkeypatch.setattr(bench_survive, "CONVERSIONS", [("sog", None, dict(fmt="sog")),
                                                     ("decimate", 0.5, dict(fmt="ply", decimate=0.5))])
  bench_survive.main([f"--out={tmp_path / 'out'}", f"--workdir={tmp_path / 'work'}", f"--scenes=tiny={run / 'run'}",
                      f"--calibration={run / 'cal.json'}", "--test-views=1", "--attacks=decimate"])
  assert [(attack, level) for attack, level, _ in asked] == [("decimate", 0.5)]


def test_render_psnr_renders_every_sh_band_the_scene_has(run, tmp_path):
  """The attacked scene's render PSNR is the scene's as a viewer shows it, also where the key reads it at SH degree
  0 (a film's key)."""
  scene = bench_survive.load_scene("tiny", run / "run", "recommended", 1, dict(threshold=0.5), tmp_path / "cache",
                                   1e-3, 4)
  at_dc = dataclasses.replace(scene.owner.options, sh_degree=0)
  scene = dataclasses.replace(scene, owner=dataclasses.replace(scene.owner, options=at_dc))
  sh = np.array(scene.student.sh)
  sh[:, 1:] = np.random.default_rng(0).normal(size=sh[:, 1:].shape) * 0.3  # view-dependent colour
  tuned = scene.student.replace(sh=sh)
  full = evaluate.views_psnr(tuned, scene.cameras, scene.targets, dataclasses.replace(at_dc, sh_degree=None))
  assert abs(full - evaluate.views_psnr(tuned, scene.cameras, scene.targets, at_dc)) > 0.1
  assert bench_survive.scores_of(scene, tuned)["render_psnr"] == pytest.approx(full, abs=1e-4)


def test_marks_of_one_scene_share_its_trainings_and_other_recipes_are_refused(tmp_path, monkeypatch):
  """A cached fine-tuning is taken by a config that differs in how its mark was made (conceal, mark, ...) or in
  how its scene folder is spelled, and refused, by section, for another training recipe."""
  monkeypatch.chdir(tmp_path)
  (tmp_path / "scene").mkdir()
  config = ml_collections.ConfigDict(dict(data=dict(path="scene"), train=dict(iterations=4), conceal=dict(w=1.0)))
  folder = tmp_path / "work" / "finetune_fixed_4"
  bench_survive.claim_training(folder, config)
  other_mark = ml_collections.ConfigDict(config.to_dict())
  other_mark.conceal.w, other_mark.data.path = 2.0, str(tmp_path / "scene")
  bench_survive.claim_training(folder, other_mark)
  assert json.loads((folder / "config.json").read_text())["conceal"] == {"w": 2.0}
  other_training = ml_collections.ConfigDict(config.to_dict())
  other_training.train.iterations = 8
  with pytest.raises(ValueError, match="holds a training with other train settings"):
    bench_survive.claim_training(folder, other_training)


def test_true_positives_count_the_attacked_rows_verify_decided():
  """Per scene and recipe, the attacked rows verify decided owned; the untouched row and rows measured before
  verify's test (no `owned`) are left out, as is a scene without any."""
  rows = [dict(scene="demo", recipe="film", attack="none", owned=True),
          dict(scene="demo", recipe="film", attack="rotate", owned=True),
          dict(scene="demo", recipe="film", attack="finetune", owned=False),
          dict(scene="demo", recipe="film", attack="sog"),
          dict(scene="lego", recipe="recommended", attack="sog", decided=True)]
  assert bench_survive.true_positive_lines(rows) == ["- demo (film): owned at alpha in 1 of 2 attacked rows", ""]
  assert bench_survive.true_positive_lines(rows[-1:]) == []


def test_two_marks_are_decided_together_on_the_attacks_both_were_read_after(monkeypatch):
  """Each attack both marks' rows have: the two readings and the Bonferroni decision on both (the smaller p-value
  times two); an attack one mark was not read after, and rows without verify's test, are left out."""
  monkeypatch.setattr(bench_survive, "TWO_MARKS", {"s_film": "s_layer"})
  row = lambda scene, attack, level, ssim, log10_p, owned: dict(
      scene=scene, recipe="r", attack=attack, level=level, render_psnr=30.0, hidden_ssim=ssim, log10_p=log10_p,
      owned=owned)
  rows = [row("s_film", "none", None, 0.99, -7.0, True), row("s_layer", "none", None, 0.98, -6.5, True),
          row("s_film", "finetune", 1000, 0.99, -6.5, True), row("s_layer", "finetune", 1000, 0.2, -0.3, False),
          row("s_film", "rotate", 5.0, 0.9, -5.0, False), row("s_layer", "rotate", 5.0, 0.9, -5.5, False),
          row("s_film", "sog", None, 0.99, -7.0, True),
          dict(scene="s_layer", recipe="r", attack="sog", level=None, hidden_ssim=0.9, decided=True)]
  lines = bench_survive.two_mark_lines(rows, alpha=1e-6)
  body = [line for line in lines if line.startswith("| ") and not line.startswith("| attack")]
  assert body == ["| none |  |  | 30.00 | 0.990* | 0.980* | yes (-6.7) |",
                  "| finetune | 1000 |  | 30.00 | 0.990* | 0.200 | yes (-6.2) |",
                  "| rotate | 5.0 |  | 30.00 | 0.900 | 0.900 | no (-5.2) |"]
  assert bench_survive.two_mark_lines(rows[:1]) == []


def test_a_mark_is_read_from_the_student_of_a_run_layered_on_it(run, tmp_path):
  """scene=workdir+layered: workdir's owner and key, layered's student (a run concealed on workdir's student); a
  run concealed on another scene is refused by name."""
  layered = tmp_path / "layered"
  fileio.write_json(layered / "config.json", dict(mark=dict(teacher=str(run / "run" / "student.ply"))))
  student = jax.tree.map(np.asarray, ply.load_ply(run / "run" / "student.ply"))
  second = student.replace(sh=student.sh + 0.01)  # the second mark: the scene's colours changed
  ply.save_ply(layered / "student.ply", second)
  scene = bench_survive.load_scene("tiny", run / "run", "recommended", 1, dict(threshold=0.5), tmp_path / "cache",
                                   1e-3, 4, layered=layered)
  np.testing.assert_allclose(scene.student.sh, second.sh, rtol=1e-6)
  assert scene.run == layered and scene.owner.check_camera is not None
  other = tmp_path / "other"
  fileio.write_json(other / "config.json", dict(mark=dict(teacher=str(tmp_path / "elsewhere.ply"))))
  with pytest.raises(ValueError, match="was not concealed on .*run/student.ply"):
    bench_survive.load_scene("tiny", run / "run", "recommended", 1, dict(threshold=0.5), tmp_path / "cache2",
                             1e-3, 4, layered=other)


def test_extraction_rows_form_one_curve_per_scene_recipe_and_views():
  """The extraction target's curves: hidden SSIM by training steps per (scene, recipe, poses, views), owned by
  verify's decision where it was made; REPRODUCTION's extraction table reads them."""
  from experiments import reproduce
  row = lambda attack, views, steps, ssim, owned: dict(scene="demo", recipe="in_scene", attack=attack, level=views,
                                                      steps=steps, hidden_ssim=ssim, owned=owned, decided=False)
  rows = [row("extraction", 200, 3000, 0.97, True), row("extraction", 200, 1000, 0.83, True),
          row("extraction", 50, 1000, 0.2, False), row("extraction_sphere", 200, 1000, 0.5, None),
          dict(row("extraction_unseen", 200, 1000, 0.9, True), key_nearest_deg=6.34),
          dict(row("finetune", 30, None, 0.1, False), steps=None)]
  curves = bench_survive.extraction_curves(rows)
  assert curves == {("demo", "in_scene", "orbit", 50): [(1000, 0.2, False)],
                    ("demo", "in_scene", "orbit", 200): [(1000, 0.83, True), (3000, 0.97, True)],
                    ("demo", "in_scene", "sphere", 200): [(1000, 0.5, False)],
                    ("demo", "in_scene", "unseen", 200): [(1000, 0.9, True)]}
  table = "\n".join(reproduce.extraction_table(dict(rows=rows)))
  assert "| demo | in_scene | orbit | 200 | - | 0.830* | 0.970* |" in table
  assert "| demo | in_scene | sphere | 200 | - | 0.500 | - |" in table
  assert "| demo | in_scene | unseen | 200 | 6.3 | 0.900* | - |" in table
  assert reproduce.NOT_RUN in "\n".join(reproduce.extraction_table(dict(rows=[])))
