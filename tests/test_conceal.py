"""ConcealGS: the losses, the check-view key, and the conceal -> reveal pipeline end to end on a tiny
generated scene (resume, ablation switches, clear errors). The objective and step: tests/test_objective.py."""
from __future__ import annotations

import dataclasses
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import key, near, reveal, scoring, settings as settings_lib, tolerance, train as conceal_train
from conceal_jax.conceal import views as views_lib
from conceal_jax.data import demo_scene, ply
from conceal_jax.gs import init, losses
from conceal_jax import main as main_lib
from conceal_jax.splat.camera import Camera, camera_centers, look_at
from conceal_jax.configs import demo, demo_robust
from conceal_jax.core import fileio, workdir as workdir_lib
from experiments import bench_baselines, bench_conceal, rescore, results_io, tradeoff


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
  """A 32x32 demo scene and a teacher made of random points (concealment only needs a scene)."""
  folder = tmp_path_factory.mktemp("conceal")
  scene_path = demo_scene.generate_demo_scene(folder / "scene", num_train=6, num_test=2, size=32)
  points, colors = init.random_box_points(np.random.default_rng(0), 1200, 1.0)
  teacher = init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5)
  ply.save_ply(folder / "teacher.ply", teacher)
  return scene_path, folder / "teacher.ply"


# tiny_config's short names for settings outside conceal.*'s top level
PATHS = dict(**{name: f"mark.{name}" for name in ("teacher", "hidden", "hidden_size", "key_kind", "key_index",
                                                  "key_seed", "extra_hidden")},
             **{name: f"conceal.leakage.{name}" for name in ("identity_on_student", "identity_on_teacher_check",
                                                             "decoy_views", "decoy_fraction", "decoy_translation",
                                                             "decoy_rotation_deg", "tolerance_deg",
                                                             "tolerance_views", "tolerance_fraction",
                                                             "decoys_hold_student")},
             **{f"decoder_{name}": f"conceal.decoder.{name}" for name in ("width", "input_norm", "clip_input")},
             **{f"decoder_{name}": f"conceal.decoder_opt.{name}" for name in ("lr_final_ratio", "update_clip",
                                                                              "polish_steps", "adam_eps")},
             decoder_lr="conceal.decoder_opt.lr")


def tiny_config(tiny, iterations=40, **overrides):
  """The demo config on the tiny scene, with the paper's method (the demo's leakage control off), a width-4
  decoder at 16x16; `overrides` by their conceal.* name or PATHS' short name."""
  scene_path, teacher = tiny
  config = demo.get_config()
  config.mode = "conceal"
  config.data.path = str(scene_path)
  config.render.tile_size = 8
  config.eval.max_views = 1
  settings = dict(teacher=str(teacher), hidden_size=16, decoder_width=4, identity_on_student=False,
                  identity_on_teacher_check=False, decoy_views=0, decoy_fraction=0.0, decoder_lr=1e-3)
  config.conceal.decoder.vgg_init = False
  config.conceal.iterations, config.conceal.checkpoint_every = iterations, 20
  config.conceal.log_every, config.conceal.progress_bar = 5, False
  for name, value in dict(settings, **overrides).items():
    bench_conceal.set_dotted(config, PATHS.get(name, f"conceal.{name}"), value)
  return config


def test_losses_are_mean_absolute_errors():
  a, b = jnp.zeros((4, 4, 3)), jnp.full((4, 4, 3), 0.25).at[0, 0, 0].set(1.25)
  expected = (0.25 * 47 + 1.25) / 48
  for loss in (losses.distillation_loss, losses.decoder_identity_loss, losses.hidden_image_loss):
    np.testing.assert_allclose(loss(a, b), expected, rtol=1e-6)


def test_extra_keys_are_further_cameras_of_the_kind():
  cameras = [Camera.from_intrinsics(look_at([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0]), 40.0, 40.0, 16.0,
                                    16.0, 32, 32) for a in np.linspace(0, 5, 5)]
  keys = key.key_cameras(cameras, "train_index", -2, 1, 3)
  assert [info for _, info in keys] == [dict(kind="train_index", index=i) for i in (3, 2, 1, 0)]
  assert keys[2][0] is cameras[1]
  orbit = key.key_cameras(cameras, "orbit", 0, 7, 2)
  assert [info["seed"] for _, info in orbit] == [7, 8, 9]
  np.testing.assert_array_equal(np.asarray(orbit[2][0].world_to_camera),
                                np.asarray(key.orbit_camera(cameras, 9).world_to_camera))
  with pytest.raises(ValueError, match="extra_hidden.*out of range"):
    key.key_cameras(cameras, "train_index", -4, 1, 2)
  with pytest.raises(ValueError, match="extra_hidden: keys 0 and 2 are the same pose"):
    key.key_cameras(cameras[:2], "train_index", 0, 1, 2)


def test_decoys_lie_near_the_key_within_their_ranges():
  check = Camera.from_intrinsics(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
  decoys = near.decoy_cameras(check, 2.0, 9, (0.05, 0.1), (3.0, 6.0), seed=1)
  center = camera_centers([check])[0]
  forward = np.asarray(check.world_to_camera)[2, :3]
  for k, decoy in enumerate(decoys):
    moved = np.linalg.norm(camera_centers([decoy])[0] - center) / 2.0
    turned = np.degrees(np.arccos(np.clip(np.asarray(decoy.world_to_camera)[2, :3] @ forward, -1, 1)))
    if k % 3 == 1:
      assert moved < 1e-6
    else:
      assert 0.05 - 1e-6 <= moved <= 0.1 + 1e-6
    if k % 3 == 0:  # moved only: the same orientation
      np.testing.assert_allclose(np.asarray(decoy.world_to_camera)[:3, :3], np.asarray(check.world_to_camera)[:3, :3],
                                 atol=1e-6)
    else:  # the optical axis turns by at most the rotation angle (less when the axis is near the view direction)
      assert 0.1 < turned <= 6.0 + 1e-3
  nearby = near.nearby_cameras(check, 2.0, (0.05,), (), 4)
  assert not any(np.allclose(np.asarray(d.world_to_camera), np.asarray(n.world_to_camera))
                 for d in decoys for _, _, n in nearby)
  again = near.decoy_cameras(check, 2.0, 9, (0.05, 0.1), (3.0, 6.0), seed=1)
  np.testing.assert_array_equal(np.asarray(again[4].world_to_camera), np.asarray(decoys[4].world_to_camera))


def test_near_poses_move_along_and_turn_about_the_keys_own_axes_then_random_ones():
  """The leakage figure's poses: per value, the six moves along (turns about) the key's axes both ways, forward along
  the optical axis among them (a zoom, the move the image changes least under), then the random ones."""
  check = Camera.from_intrinsics(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
  w2c = np.asarray(check.world_to_camera, np.float64)
  center = camera_centers([check])[0]
  poses = near.nearby_cameras(check, 2.0, (0.0, 0.05), (3.0,), 4)
  kinds = [("translation", 0.0)] + [("translation", 0.05)] * 10 + [("rotation", 3.0)] * 10
  assert [(k, v) for k, v, _ in poses] == kinds
  np.testing.assert_allclose(np.asarray(poses[0][2].world_to_camera), w2c, atol=1e-12)
  moved = [camera_centers([c])[0] - center for _, _, c in poses[1:11]]
  for axis, move in zip(near.KEY_AXES, moved):
    np.testing.assert_allclose(move, 0.1 * w2c[:3, :3].T @ np.asarray(axis), atol=1e-6)
  np.testing.assert_allclose(moved[4], 0.1 * w2c[2, :3], atol=1e-6)  # forward along the optical axis
  assert all(abs(np.linalg.norm(m) - 0.1) < 1e-6 for m in moved[6:])
  assert max(abs(m @ w2c[2, :3]) / 0.1 for m in moved[6:]) < 0.999  # the random ones are not the axes
  pitched = np.asarray(poses[11][2].world_to_camera, np.float64)  # turned about x by 3 degrees, not moved
  np.testing.assert_allclose(pitched[:3, :3], key.rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(3.0))
                             @ w2c[:3, :3], atol=1e-9)
  np.testing.assert_allclose(camera_centers([poses[11][2]])[0], center, atol=1e-6)
  roll = np.asarray(poses[15][2].world_to_camera, np.float64)[:3, :3]  # about the optical axis: the same view axis
  np.testing.assert_allclose(roll[2], w2c[2, :3], atol=1e-9)


def test_orbit_turn_decoys_stand_on_the_keys_orbit_and_the_others_are_unchanged():
  """decoy_orbit_turns: the decoys both moved and turned become the key turned about the point its depth ahead, by
  the degrees drawn (angle_from_key_deg measures exactly that turn), still looking at that point; the others are
  the plain decoys."""
  check = Camera.from_intrinsics(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
  length = 4.0
  plain = near.decoy_cameras(check, length, 12, (0.05, 0.1), (3.0, 6.0), seed=1, key_axes=True)
  decoys = near.decoy_cameras(check, length, 12, (0.05, 0.1), (3.0, 6.0), seed=1, key_axes=True, orbit_turns=True)
  w2c = np.asarray(check.world_to_camera, np.float64)
  pivot = camera_centers([check])[0] + length * w2c[2, :3]
  for k, (decoy, other) in enumerate(zip(decoys, plain)):
    if k % 3 != 2:
      np.testing.assert_array_equal(np.asarray(decoy.world_to_camera), np.asarray(other.world_to_camera))
      continue
    angle = tolerance.angle_from_key_deg(decoy, check, length)
    assert 3.0 - 1e-4 <= angle <= 6.0 + 1e-4
    d2c = np.asarray(decoy.world_to_camera, np.float64)
    ahead = d2c[:3, :3] @ pivot + d2c[:3, 3]  # the pivot in the decoy's frame: straight ahead at the same depth
    np.testing.assert_allclose(ahead, [0.0, 0.0, length], atol=1e-5)


def test_decoys_moved_along_or_turned_about_the_keys_axes_take_each_axis_in_turn():
  check = Camera.from_intrinsics(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
  w2c = np.asarray(check.world_to_camera, np.float64)
  center = camera_centers([check])[0]
  plain = near.decoy_cameras(check, 2.0, 24, (0.05, 0.1), (3.0, 6.0), seed=1)
  decoys = near.decoy_cameras(check, 2.0, 24, (0.05, 0.1), (3.0, 6.0), seed=1, key_axes=True)
  for k, (decoy, other) in enumerate(zip(decoys, plain)):
    move = camera_centers([decoy])[0] - center
    axis = np.asarray(near.KEY_AXES[(k // 3) % 6])
    if k % 3 == 2:  # moved and turned: as without key_axes
      np.testing.assert_array_equal(np.asarray(decoy.world_to_camera), np.asarray(other.world_to_camera))
      continue
    if k % 3 == 1:  # turned about the axis by the plain decoy's angle, not moved
      r0, r1 = w2c[:3, :3], np.asarray(other.world_to_camera, np.float64)[:3, :3]
      angle = np.arccos(np.clip((np.trace(r1 @ r0.T) - 1) / 2, -1, 1))
      np.testing.assert_allclose(np.asarray(decoy.world_to_camera)[:3, :3], key.rotation_about(axis, angle) @ r0,
                                 atol=1e-5)
      assert np.linalg.norm(move) < 1e-5
      continue
    np.testing.assert_allclose(move / np.linalg.norm(move), w2c[:3, :3].T @ axis, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(move), np.linalg.norm(camera_centers([other])[0] - center), atol=1e-6)
    np.testing.assert_allclose(np.asarray(decoy.world_to_camera)[:3, :3], w2c[:3, :3], atol=1e-6)


def test_bench_conceal_marks_rows_scored_before_the_key_axes():
  scores = dict(psnr=30.0, ssim=0.9, lpips=0.1)
  row = dict(scene="lego", row="recommended", decoder_width=16, iterations=10, wall_time_s=60.0, median_step_s=0.1,
             student_vs_ground_truth=scores, teacher_vs_ground_truth=scores, student_vs_teacher=scores, hidden=scores,
             student_psnr_loss=0.0, leakage=dict(max_ssim_student_test_views=0.1, ssim_teacher_check_view=0.1,
                                                 max_ssim_near_check=0.1))
  new = bench_conceal.table([dict(row, near_poses=dict(key_axes=6, random_directions=4))])
  old = bench_conceal.table([row, dict(row, near_poses=dict(key_axes=6, random_directions=4))])
  assert " *" not in new and "4 random directions only" not in new
  assert old.count("0.100 / 0.100 / 0.100 * |") == 1 and "4 random directions only" in old


def test_decoys_that_watch_the_decoder_alone_leave_the_student_free(tiny):
  """decoys_hold_student False: a decoy's render takes no L_kd, so the student gets no gradient from a decoy view
  (L_d^- reads the student's render as a constant) while F is still held to the identity there; a training view
  keeps L_kd."""
  from conceal_jax.conceal import objective
  config = tiny_config(tiny, identity_on_student=True, decoy_views=3, decoy_fraction=0.5, decoys_hold_student=False)
  plan = settings_lib.plan(config)
  run = conceal_train.prepare(config, plan)
  s, num_views = plan.settings, len(run.scene.train_cameras)
  decoy = jax.tree.map(lambda x: x[0], views_lib.step_views(run.data, num_views + 1, num_views + 1, 0, None, s))
  trained = jax.tree.map(lambda x: x[0], views_lib.step_views(run.data, 0, 0, 0, None, s))
  assert float(decoy.l1_weight) == 0.0 and float(decoy.own_minus_weight) > 0
  assert float(trained.l1_weight) == s.weight_kd
  decoder = conceal_train.initial_decoder(config, s)
  student = jax.tree.map(jnp.asarray, run.start)
  total = lambda g, view: (lambda t: t.student + t.minus)(objective.view_terms(g, decoder, decoder, view, s,
                                                                              run.options))
  free = jax.grad(lambda g: total(g, decoy))(student)
  assert all(float(jnp.max(jnp.abs(leaf))) == 0.0 for leaf in jax.tree.leaves(free))
  held = jax.grad(lambda g: total(g, trained))(student)
  assert any(float(jnp.max(jnp.abs(leaf))) > 0.0 for leaf in jax.tree.leaves(held))


def test_polish_draws_its_own_share_of_merged_check_renders(tiny):
  """conceal.decoder_opt.polish_merge_fraction: the polish's steps draw merges at their own share, the joint steps at
  conceal.attacks.merge_fraction; unset, every step draws as the joint ones; set without a polish or without the
  joint steps' merges (whose kind the step leaves out at trace time), one error naming it."""
  film = {"carrier.film": True, "attacks.merge_fraction": 0.2, "key_kind": "unseen"}
  config = tiny_config(tiny, iterations=10, decoder_polish_steps=5, **film)
  plan = settings_lib.plan(config)
  assert plan.phase(15) == (False, plan.settings.augmentation) and plan.phase(15)[1] is plan.settings.augmentation
  config.conceal.decoder_opt.polish_merge_fraction = 0.6
  plan = settings_lib.plan(config)
  assert plan.phase(10) == (True, plan.settings.augmentation) and plan.settings.augmentation.merge_fraction == 0.2
  joint, polish = plan.phase(11)
  assert not joint and polish.merge_fraction == 0.6
  assert polish == dataclasses.replace(plan.settings.augmentation, merge_fraction=0.6)
  for changes in (dict(decoder_polish_steps=0), {"attacks.merge_fraction": 0.0}):
    bad = tiny_config(tiny, iterations=10, **{**film, "decoder_polish_steps": 5, **changes})
    bad.conceal.decoder_opt.polish_merge_fraction = 0.6
    with pytest.raises(ValueError, match="polish_merge_fraction"):
      settings_lib.plan(bad)


def test_normal_views_draw_decoys_at_their_rate():
  rng = np.random.default_rng(0)
  views = np.array([views_lib.draw_normal_view(rng, 10, 5, 0.3) for _ in range(4000)])
  assert views.min() == 0 and views.max() == 14
  np.testing.assert_allclose(np.mean(views >= 10), 0.3, atol=0.03)
  assert all(views_lib.draw_normal_view(rng, 10, 0, 0.3) < 10 for _ in range(100))


@pytest.mark.job
def test_conceal_writes_outputs_resumes_and_reveals(tiny, tmp_path):
  config = tiny_config(tiny, eval_every=20)
  straight = conceal_train.train_and_evaluate(config, str(tmp_path / "a"))
  assert conceal_train.train_and_evaluate(config, str(tmp_path / "b"), max_steps=20) == dict(stopped_at=20)
  resumed = conceal_train.train_and_evaluate(config, str(tmp_path / "b"))
  assert resumed["timed_steps"] == straight["timed_steps"] == 40
  assert straight["traces"] == dict(conceal_step=1) and resumed["traces"] == dict(conceal_step=1)
  for name in ("decoder.msgpack", "student.ply"):
    assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name

  a = tmp_path / "a"
  for name in ("key.json", "hidden.png", "revealed.png", "teacher_revealed.png", "normal_revealed.png", "metrics.json"):
    assert (a / name).is_file(), name
  metrics = json.loads((a / "metrics.json").read_text())
  assert set(metrics["leakage"]) == {"max_ssim_student_test_views", "ssim_teacher_check_view", "max_ssim_near_check"}
  assert [(r["kind"], r["value"]) for r in metrics["near_check"]] == [
      ("translation", 0.02), ("translation", 0.05), ("rotation", 2.0), ("rotation", 5.0)]
  assert metrics["leakage"]["max_ssim_near_check"] == max(r["max_ssim"] for r in metrics["near_check"])
  assert metrics["near_poses"] == dict(key_axes=len(near.KEY_AXES), random_directions=scoring.NEAR_DIRECTIONS)
  floor = metrics["leakage_floor"]
  assert -1 <= floor["ssim_teacher_at_worst_test_view"] <= floor["max_ssim_teacher_test_views"] <= 1
  assert np.isfinite(metrics["hidden"]["psnr"]) and "VGG16" in metrics["lpips_net"]
  windows = [h for h in straight["history"] if "loss" in h]
  assert all(np.isfinite(h["loss"]) and 0 < h["mean_guidance_weight"] < 1 for h in windows)
  assert all(0 < h["decoder_step_norm"] < np.inf and 0 < h["decoder_grad_norm"] < np.inf for h in windows)
  curve = [h for h in straight["history"] if "hidden_psnr" in h]
  assert [h["step"] for h in curve] == [20, 40] and all(np.isfinite(h["test_psnr"]) for h in curve)
  np.testing.assert_allclose(curve[-1]["hidden_psnr"], metrics["hidden"]["psnr"], rtol=1e-4)
  assert ply.load_ply(a / "student.ply").num == 1200

  # the reveal job reproduces the concealment's revealed image from the shared files alone
  result = reveal_from_files(a, tmp_path / "reveal")
  np.testing.assert_allclose(result["psnr"], metrics["hidden"]["psnr"], rtol=1e-4)
  assert (tmp_path / "reveal" / "revealed.png").read_bytes() == (a / "revealed.png").read_bytes()


def reveal_from_files(run, workdir) -> dict:
  """The reveal job's result on a conceal run's shared files (student.ply, key.json, decoder.msgpack)."""
  reveal_config = demo.get_config()
  reveal_config.mode = "reveal"
  reveal_config.reveal.ply, reveal_config.reveal.key = str(run / "student.ply"), str(run / "key.json")
  reveal_config.reveal.decoder, reveal_config.reveal.hidden = str(run / "decoder.msgpack"), "astronaut"
  return main_lib.run(reveal_config, str(workdir))


@pytest.fixture(scope="module")
def joint_run(tiny, tmp_path_factory):
  """(result, folder) of a finished 20-step run of the paper's method."""
  folder = tmp_path_factory.mktemp("joint") / "run"
  return conceal_train.train_and_evaluate(tiny_config(tiny, iterations=20), str(folder)), folder


def finished_copy(tiny, joint_run, run):
  """A copy of joint_run's folder with the config.json that main writes beside it."""
  shutil.copytree(joint_run[1], run)
  (run / "config.json").write_text(tiny_config(tiny, iterations=20).to_json())
  return run


@pytest.mark.job
def test_rescore_reproduces_a_finished_runs_metrics_and_keeps_the_old_file(tiny, joint_run, tmp_path):
  """experiments/rescore.py: a finished run scored again from its saved files gives the figures its own scoring
  wrote, and keeps the metrics.json it replaces."""
  run = finished_copy(tiny, joint_run, tmp_path / "run")
  original = json.loads((run / "metrics.json").read_text())
  (run / "metrics.json").write_text(json.dumps(dict(original, hidden=dict(psnr=1.0, ssim=0.0))))
  result = rescore.rescore(run)
  assert result["before"]["hidden"] == dict(psnr=1.0, ssim=0.0)
  assert result["after"]["hidden"] == pytest.approx(original["hidden"], abs=1e-4)
  assert result["after"]["leakage"] == pytest.approx(original["leakage"], abs=1e-4)
  assert json.loads((run / "metrics.json").read_text())["hidden"] == result["after"]["hidden"]
  assert json.loads((run / rescore.PREVIOUS_FILE).read_text())["hidden"] == dict(psnr=1.0, ssim=0.0)


@pytest.mark.job
def test_rescore_refuses_an_unfinished_run_before_writing(tiny, joint_run, tmp_path):
  finished = finished_copy(tiny, joint_run, tmp_path / "finished")
  unfinished = finished_copy(tiny, joint_run, tmp_path / "unfinished")
  (unfinished / "student.ply").unlink()
  with pytest.raises(SystemExit, match="unfinished: missing student.ply"):
    rescore.main([str(finished), str(unfinished)])
  assert not (finished / rescore.PREVIOUS_FILE).exists()


@pytest.mark.job
def test_a_checkpoint_is_scored_as_the_finished_run_and_the_run_is_left_alone(tiny, joint_run, tmp_path):
  """rescore --checkpoint: the last checkpoint of a finished run holds its final student and decoder, so it scores
  to the run's own figures, into checkpoint_scores/step_<N>/, and no file of the run changes."""
  run = finished_copy(tiny, joint_run, tmp_path / "run")
  before = {path: path.read_bytes() for path in run.rglob("*") if path.is_file()}
  result = rescore.score_checkpoint(run)
  original = json.loads((run / "metrics.json").read_text())
  assert result["step"] == 20
  assert result["hidden"] == pytest.approx(original["hidden"], abs=1e-4)
  assert result["leakage"] == pytest.approx(original["leakage"], abs=1e-4)
  assert result["student"] == pytest.approx(original["student_vs_ground_truth"], abs=1e-4)
  scored = json.loads((run / rescore.CHECKPOINT_SCORES / "step_20" / "metrics.json").read_text())
  assert scored["hidden"] == result["hidden"] and result["views"] == 1
  both = rescore.score_checkpoint(run, views=2)  # every test view of the tiny scene, beside the run's own read
  assert both["views"] == 2 and both["hidden"] == result["hidden"]
  scored = json.loads((run / rescore.CHECKPOINT_SCORES / "step_20_views_2" / "metrics.json").read_text())
  assert scored["num_test_views"] == 2 and original["num_test_views"] == 1
  assert {path: path.read_bytes() for path in before} == before


@pytest.mark.slow  # a film run of 4 steps
def test_a_film_runs_checkpoint_restores_its_film(tiny, tmp_path):
  """A film run's state has the teacher and its planned film as the student and Adam over the film's colours:
  rescore --checkpoint rebuilds that template (carrier.student_start) and scores the run's figures."""
  config = tiny_config(tiny, iterations=4, key_kind="unseen", **{"carrier.film": True, "carrier.spacing": 4.0})
  conceal_train.train_and_evaluate(config, str(tmp_path))
  (tmp_path / "config.json").write_text(config.to_json())
  result = rescore.score_checkpoint(tmp_path)
  original = json.loads((tmp_path / "metrics.json").read_text())
  assert result["step"] == 4 and result["hidden"] == pytest.approx(original["hidden"], abs=1e-4)


@pytest.mark.job
def test_rescore_refuses_a_run_without_a_checkpoint(tiny, joint_run, tmp_path):
  run = finished_copy(tiny, joint_run, tmp_path / "run")
  shutil.rmtree(run / "checkpoints")
  with pytest.raises(SystemExit, match="run: no checkpoint"):
    rescore.main(["--checkpoint", str(run)])
  with pytest.raises(SystemExit, match="--views must be a positive count of test views, given with --checkpoint"):
    rescore.main(["--views=3", str(run)])
  assert not (run / rescore.CHECKPOINT_SCORES).exists()


@pytest.mark.job
def test_a_reference_decoder_run_is_revealed_from_its_shared_files(tiny, tmp_path):
  """conceal.decoder.reference: the decoder file carries its reference image (trained from the clean teacher's
  check render), the key records the reading, and the reveal job reproduces the run's figures from the files."""
  config = tiny_config(tiny, iterations=4, **{"decoder.reference": True})
  metrics = conceal_train.train_and_evaluate(config, str(tmp_path / "run"))["metrics"]
  run = tmp_path / "run"
  assert reveal.load_decoder(str(run / "decoder.msgpack"))["reference"].shape == (16, 16, 3)
  assert json.loads((run / "key.json").read_text())["decoder_reference"] is True
  np.testing.assert_allclose(reveal_from_files(run, tmp_path / "reveal")["psnr"], metrics["hidden"]["psnr"], rtol=1e-4)


@pytest.mark.slow  # two runs of 40 steps; no recipe polishes (conceal.decoder_opt.polish_steps is 0 in each)
def test_decoder_polish_trains_the_decoder_alone_and_resumes_across_phases(tiny, joint_run, tmp_path):
  joint, joint_dir = joint_run
  config = tiny_config(tiny, iterations=20, decoder_polish_steps=20)
  straight = conceal_train.train_and_evaluate(config, str(tmp_path / "straight"))
  # a polish started from the joint run's last checkpoint (as bench-conceal's continued rows are)
  (tmp_path / "resumed").mkdir()
  shutil.copytree(joint_dir / "checkpoints", tmp_path / "resumed" / "checkpoints")
  resumed = conceal_train.train_and_evaluate(config, str(tmp_path / "resumed"))
  assert straight["traces"] == dict(conceal_step=1, polish_step=1) and resumed["traces"] == dict(polish_step=1)
  assert straight["timed_steps"] == resumed["timed_steps"] == 40 and resumed["decoder_polish_steps"] == 20
  for name in ("decoder.msgpack", "student.ply"):
    assert (tmp_path / "straight" / name).read_bytes() == (tmp_path / "resumed" / name).read_bytes(), name
  # the student is the joint run's, bit for bit; the decoder fits it better
  assert (joint_dir / "student.ply").read_bytes() == (tmp_path / "straight" / "student.ply").read_bytes()
  assert straight["metrics"]["hidden"]["psnr"] > joint["metrics"]["hidden"]["psnr"] + 0.1
  plus = [h["plus"] for h in straight["history"] if "plus" in h]
  assert all(np.isfinite(plus)) and plus[-1] < plus[len(plus) // 2 - 1]


def test_bench_row_continues_only_the_run_it_extends(tiny, tmp_path):
  joint, polish = tiny_config(tiny, iterations=20), tiny_config(tiny, iterations=20, decoder_polish_steps=20)
  source, row = tmp_path / "source", tmp_path / "row"
  fileio.write_json(source / "config.json", joint.to_dict())
  fileio.write_bytes(source / "checkpoints" / "ckpt_00000020.npz", b"step 20")
  other = tiny_config(tiny, iterations=20, decoder_polish_steps=20, weight_minus=0.5)
  assert not bench_conceal.continue_from(source, row, other)  # another config: trains from step 0
  assert bench_conceal.continue_from(source, row, polish)
  assert (row / "checkpoints" / "ckpt_00000020.npz").read_bytes() == b"step 20"
  assert not bench_conceal.continue_from(source, row, polish)  # its own checkpoints are kept


@pytest.mark.job
def test_bench_reads_a_finished_run_and_keeps_its_images_beside_the_json(tiny, joint_run, tmp_path):
  bench, out = tmp_path / "bench", tmp_path / "results"
  run = bench / "lego" / "conceal_full_w16"
  shutil.copytree(joint_run[1], run)
  (bench / "lego" / "teacher").mkdir()
  shutil.copy(tiny[1], bench / "lego" / "teacher" / "point_cloud.ply")
  [row] = bench_conceal.run("lego", ["full", "leakage_control"], [16], 0, 0, bench, out, reuse=True)
  assert row["row"] == "full" and set(row["images"]) == set(results_io.CONCEAL_IMAGES)
  for label, name in results_io.CONCEAL_IMAGES.items():
    assert (out / row["images"][label]).read_bytes() == (run / name).read_bytes(), label
  saved = json.loads((out / "conceal_bench.json").read_text())["rows"]
  assert saved == [json.loads(json.dumps(row))] and (out / "conceal_bench.png").is_file()


def test_a_bench_row_may_set_the_seed_beside_its_conceal_overrides(tmp_path):
  teacher = tmp_path / "point_cloud.ply"
  released, seeded = (bench_conceal.run_config("lego", teacher, row, 16, 0, 0)
                      for row in ("released", "released_seed1"))
  assert (released.seed, seeded.seed, seeded.conceal.variant) == (0, 1, "released")
  assert seeded.conceal.to_dict() == released.conceal.to_dict()


def test_the_12k_released_row_is_released_trained_longer(tmp_path):
  teacher = tmp_path / "point_cloud.ply"
  released, longer = (bench_conceal.run_config("lego", teacher, row, 16, 0, 0).conceal.to_dict()
                      for row in ("released", "released_12k_steps"))
  assert longer.pop("iterations") == 12_000 and released.pop("iterations") == 10_000
  assert longer == released
  assert bench_conceal.run_config("lego", teacher, "released_12k_steps", 16, 100, 0).conceal.iterations == 100


def test_a_bench_row_from_another_seed_is_named_for_it(tmp_path):
  """tradeoff.recipe reads a row's seed from its name in both benches: `<row>_seed<N>` runs <row> from seed N."""
  teacher = tmp_path / "point_cloud.ply"
  for row in bench_conceal.ROWS:
    name, seed = tradeoff.recipe(row)
    config = bench_conceal.run_config("lego", teacher, row, 16, 0, 0)
    assert config.seed == seed, row
    if seed and name in bench_conceal.ROWS:
      assert config.conceal.to_dict() == bench_conceal.run_config("lego", teacher, name, 16, 0, 0).conceal.to_dict()
  for row in bench_baselines.ROWS:
    name, seed = tradeoff.recipe(row)
    assert bench_baselines.run_config("lego", teacher, row, 0, 0).seed == seed, row
    if seed:
      assert dict(bench_baselines.ROWS[row], seed=0) == dict(bench_baselines.ROWS[name], seed=0)


def test_demo_robust_config_is_the_demo_trained_through_attacks():
  """configs/demo_robust.py changes only the conceal settings that train through attacks and clip the reading,
  so its teacher is the demo's."""
  changed = workdir_lib.differing_keys(demo.get_config().to_dict(), demo_robust.get_config().to_dict())
  assert changed == ["conceal.attacks.blur_max", "conceal.attacks.identity_distorted", "conceal.attacks.noise_max",
                     "conceal.decoder.clip_input"]
  robust = demo_robust.get_config().conceal
  assert robust.decoder.clip_input and robust.decoder_opt.lr_final_ratio == 1.0


@pytest.mark.slow  # a run of its own compiled for two keys
def test_two_hidden_images_each_at_its_own_key(tiny, tmp_path):
  """Two images, two training-camera keys, one decoder: the steps alternate keys without a retrace,
  key.json lists the second key, metrics.json scores each image at its key and the cross-talk, leakage
  covers both images and keys, and the reveal job reproduces the second image from the shared files."""
  config = tiny_config(tiny, iterations=10, eval_every=10, extra_hidden=("camera",), identity_on_teacher_check=True,
                       decoy_views=2, decoy_fraction=0.5)
  result = conceal_train.train_and_evaluate(config, str(tmp_path))
  assert result["traces"] == dict(conceal_step=1) and result["num_keys"] == 2 and result["num_decoys"] == 4
  saved = json.loads((tmp_path / "key.json").read_text())
  assert saved["index"] == 4 and len(saved["camera"]["world_to_camera"]) == 4
  assert [(k["number"], k["kind"], k["index"], k["hidden"]) for k in saved["extra_keys"]] == [
      (1, "train_index", 3, "camera")]
  # each key records its near-key length, the unit of its decoys' and its leakage figure's translations
  lengths = [saved["near_length"], saved["extra_keys"][0]["near_length"]]
  assert saved["near_length_from"] == "view_depth" and all(length > 0 for length in lengths)
  for name in ("hidden.png", "hidden_key1.png", "revealed.png", "revealed_key1.png"):
    assert (tmp_path / name).is_file(), name

  m = result["metrics"]
  keys = m["keys"]
  assert [sorted(h) for h in keys["hidden"]] == [["max_ssim_near_key", "psnr", "ssim", "ssim_teacher_at_key"]] * 2
  assert keys["hidden"][0]["psnr"] == m["hidden"]["psnr"] and keys["hidden"][0]["ssim"] == m["hidden"]["ssim"]
  cross = np.array(keys["cross_talk_ssim"])
  assert cross.shape == (2, 2) and keys["max_cross_talk"] == max(cross[0, 1], cross[1, 0])
  np.testing.assert_array_equal(np.diag(cross), [h["ssim"] for h in keys["hidden"]])
  images = np.array(keys["images_ssim"])
  np.testing.assert_allclose(np.diag(images), 1.0, atol=1e-4)
  assert images[0, 1] < 0.9
  leakage = m["leakage"]
  assert leakage["ssim_teacher_check_view"] == max(h["ssim_teacher_at_key"] for h in keys["hidden"])
  assert leakage["max_ssim_near_check"] == max(h["max_ssim_near_key"] for h in keys["hidden"])
  assert [(r["kind"], r["value"]) for r in m["near_check"]] == [
      ("translation", 0.02), ("translation", 0.05), ("rotation", 2.0), ("rotation", 5.0)]
  assert [entry["length"] for entry in m["near_key_length"]] == lengths
  curve = [h for h in result["history"] if "hidden_psnr_keys" in h]
  np.testing.assert_allclose(curve[-1]["hidden_psnr_keys"], [h["psnr"] for h in keys["hidden"]], rtol=1e-4)

  reveal_config = demo.get_config()
  reveal_config.mode = "reveal"
  reveal_config.reveal.ply, reveal_config.reveal.key = str(tmp_path / "student.ply"), str(tmp_path / "key.json")
  reveal_config.reveal.decoder, reveal_config.reveal.hidden = str(tmp_path / "decoder.msgpack"), "camera"
  reveal_config.reveal.key_number = 1
  revealed = main_lib.run(reveal_config, str(tmp_path / "reveal"))
  np.testing.assert_allclose(revealed["psnr"], keys["hidden"][1]["psnr"], rtol=1e-4)
  assert (tmp_path / "reveal" / "revealed.png").read_bytes() == (tmp_path / "revealed_key1.png").read_bytes()
  reveal_config.reveal.key_number = 2
  with pytest.raises(ValueError, match="no key number 2"):
    main_lib.run(reveal_config, str(tmp_path / "reveal"))


@pytest.mark.parametrize("overrides", [
    pytest.param(dict(use_decoder=False), marks=pytest.mark.job),
    pytest.param(dict(consistency=False, guidance=False), marks=pytest.mark.slow),
    pytest.param(dict(variant="released", granularity="tensor", key_kind="orbit"), marks=pytest.mark.slow),
    pytest.param(dict(identity_on_student=True, identity_on_teacher_check=True, decoy_views=3, decoy_fraction=0.5),
                 marks=pytest.mark.slow),
    pytest.param(dict(identity_on_student=True, tolerance_deg=20.0, tolerance_views=2, tolerance_fraction=0.9),
                 marks=pytest.mark.slow),
    pytest.param(dict(decoder_input_norm="center", decoder_clip_input=True, decoder_lr_final_ratio=0.3,
                      decoder_update_clip=1.0), marks=pytest.mark.slow)])
def test_ablations_and_variants_run(tiny, tmp_path, overrides):
  result = conceal_train.train_and_evaluate(tiny_config(tiny, iterations=3, **overrides), str(tmp_path))
  assert np.isfinite(result["metrics"]["hidden"]["psnr"])
  saved_key = json.loads((tmp_path / "key.json").read_text())
  assert saved_key["uses_decoder"] == overrides.get("use_decoder", True)
  assert saved_key["decoder_input_norm"] == overrides.get("decoder_input_norm", "none")
  assert saved_key["decoder_clip_input"] == overrides.get("decoder_clip_input", False)
  if saved_key["decoder_input_norm"] != "none":  # the reveal job reads the decoder as it was trained, from the key
    reveal_config = demo.get_config()
    reveal_config.mode = "reveal"
    reveal_config.reveal.ply, reveal_config.reveal.key = str(tmp_path / "student.ply"), str(tmp_path / "key.json")
    reveal_config.reveal.decoder, reveal_config.reveal.hidden = str(tmp_path / "decoder.msgpack"), "astronaut"
    revealed = main_lib.run(reveal_config, str(tmp_path / "reveal"))
    np.testing.assert_allclose(revealed["psnr"], result["metrics"]["hidden"]["psnr"], rtol=1e-4)
  assert (tmp_path / "decoder.msgpack").exists() == overrides.get("use_decoder", True)


def test_resized_camera_keeps_the_field_of_view():
  camera = Camera.from_intrinsics(look_at([1.0, -3.0, 1.5], [0.0, 0.0, 0.0]), 40.0, 42.0, 15.5, 12.0, 31, 24)
  small = camera.resized(16, 8)
  point = np.array([0.2, 0.1, -0.3, 1.0])
  pixel = lambda cam: (lambda p: np.array([cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy]))(
      np.asarray(cam.world_to_camera, np.float64) @ point)
  np.testing.assert_allclose(pixel(small), pixel(camera) * [16 / 31, 8 / 24], rtol=1e-5)
  assert (small.width, small.height) == (16, 8)
  with pytest.raises(ValueError, match="positive"):
    camera.resized(0, 8)


@pytest.mark.parametrize("overrides,message", [
    (dict(teacher=""), "mark.teacher"), (dict(teacher="/no/such.ply"), "no such file"),
    (dict(variant="mine"), "conceal.variant"), (dict(hidden="no_such_sample"), "no_such_sample"),
    (dict(key_index=99), "key_index"), (dict(key_kind="random"), "key_kind"),
    (dict(granularity="model"), "granularity"), (dict(hidden_size=20), "hidden_size"),
    (dict(decoy_views=4), "decoy_fraction"), (dict(decoy_views=4, decoy_fraction=1.0), "decoy_fraction"),
    (dict(decoy_views=4, decoy_fraction=0.2, variant="released"), "decoy_fraction"),
    (dict(decoy_translation=(0.2, 0.1)), "decoy_translation"), (dict(eval_views=0), "eval_views"),
    (dict(tolerance_views=4), "tolerance_deg, tolerance_views and tolerance_fraction"),
    (dict(decoys_hold_student=False), "decoys_hold_student=False"),
    (dict(decoder_lr_final_ratio=2.0), "decoder_opt.lr_final_ratio"),
    (dict(decoder_update_clip=-1.0), "decoder_opt.update_clip"),
    (dict(decoder_polish_steps=-1), "polish_steps must be"),
    (dict(decoder_polish_steps=5, use_decoder=False), "polish_steps needs a decoder"),
    (dict(decoder_input_norm="max"), "decoder.input_norm"),
    (dict(identity_on_student=True, consistency=False), "identity_on_student"),
    (dict(identity_on_teacher_check=True, use_decoder=False), "identity_on_teacher_check"),
    (dict(extra_hidden=("camera", "coffee", "chelsea", "moon")), "extra_hidden holds at most 3"),
    (dict(extra_hidden=("camera",), use_decoder=False), "extra_hidden needs a decoder"),
    (dict(extra_hidden=("",)), "extra_hidden must be"), (dict(extra_hidden=("no_such_sample",)), "no_such_sample"),
    (dict(extra_hidden=("camera", "coffee"), key_index=-5), "extra_hidden.*out of range")])
def test_bad_conceal_config_is_named(tiny, tmp_path, overrides, message):
  with pytest.raises((ValueError, OSError), match=message):
    conceal_train.train_and_evaluate(tiny_config(tiny, **overrides), str(tmp_path))


def test_reveal_rejects_missing_and_malformed_files(tmp_path):
  (tmp_path / "bad.json").write_text("{not json")
  (tmp_path / "bad.msgpack").write_bytes(b"\x00garbage")
  with pytest.raises(ValueError, match="bad.json"):
    key.load_key(str(tmp_path / "bad.json"))
  with pytest.raises(ValueError, match="bad.msgpack"):
    reveal.load_decoder(str(tmp_path / "bad.msgpack"))
  with pytest.raises(ValueError, match="missing.json"):
    key.load_key(str(tmp_path / "missing.json"))


def test_orbit_key_is_on_the_camera_orbit():
  target = np.array([0.3, -0.2, 0.5])
  cameras = []
  for azimuth, elevation in [(0.1, 0.3), (1.5, 0.5), (3.0, 0.4), (4.4, 0.6)]:
    eye = target + 3.0 * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                   np.sin(elevation)])
    cameras.append(Camera.from_intrinsics(look_at(eye, target), 50.0, 50.0, 16.0, 16.0, 32, 32))
  np.testing.assert_allclose(key.orbit_target(cameras), target, atol=1e-9)
  secret = key.orbit_camera(cameras, seed=7)
  center = camera_centers([secret])[0]
  np.testing.assert_allclose(np.linalg.norm(center - target), 3.0, rtol=1e-6)
  elevation = np.arcsin((center - target)[2] / 3.0)
  assert 0.3 - 1e-6 <= elevation <= 0.6 + 1e-6
  forward = np.asarray(secret.world_to_camera)[2, :3]
  np.testing.assert_allclose(forward, (target - center) / 3.0, atol=1e-6)
  again = key.orbit_camera(cameras, seed=7)
  np.testing.assert_array_equal(np.asarray(again.world_to_camera), np.asarray(secret.world_to_camera))
  assert not np.allclose(np.asarray(key.orbit_camera(cameras, seed=8).world_to_camera),
                         np.asarray(secret.world_to_camera))


def test_key_round_trip(tmp_path):
  camera = Camera.from_intrinsics(look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]), 40.0, 41.0, 15.5, 16.5, 31, 33)
  key.save_key(str(tmp_path / "key.json"), camera, dict(kind="orbit", seed=3))
  loaded, info = key.load_key(str(tmp_path / "key.json"))
  assert info == dict(kind="orbit", seed=3) and (loaded.width, loaded.height) == (31, 33)
  jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), loaded, camera)


@pytest.mark.slow
def test_concealed_image_is_revealed_only_by_the_student(tiny, tmp_path):
  """A few hundred steps hide a 16x16 image well enough to tell: the student's check view reveals it, while the
  clean teacher's check view and the student's test views read no more of it than the decoder reads from the clean
  teacher's test views (leakage_floor, itself far from the image: the decoder is no constant). Both are trained here
  (L_d^- on the student's normal renders and the teacher's check render, recipes.leakage_control) and the key is the
  training camera farthest from the two test views: under the paper's L_d^- alone, or with a test view a few
  degrees from the key, whether they hold is the decoder's generalisation, which flips with the seed."""
  config = tiny_config(tiny, iterations=400, checkpoint_every=0, decoder_width=16, key_index=1,
                       identity_on_student=True, identity_on_teacher_check=True)
  metrics = conceal_train.train_and_evaluate(config, str(tmp_path))["metrics"]
  floor = metrics["leakage_floor"]["max_ssim_teacher_test_views"]
  assert metrics["hidden"]["ssim"] > 0.8 and floor < 0.5
  assert metrics["leakage"]["ssim_teacher_check_view"] < min(0.4, floor + 0.02)
  assert metrics["leakage"]["max_ssim_student_test_views"] < min(0.4, floor + 0.02)


def test_decoder_optimizer_uses_the_configured_eps():
  """conceal.decoder_opt.adam_eps: at the released 1e-15 a vanishing gradient still takes a step of the full rate;
  at torch's 1e-8 it takes a negligible one."""
  config = demo.get_config()
  grads = dict(w=jnp.full((3,), 1e-12))
  for eps, lo, hi in ((1e-15, 0.99, 1.0), (1e-8, 0.0, 1e-3)):
    config.conceal.decoder_opt.adam_eps = eps
    tx = settings_lib.decoder_optimizer(config)
    step = float(jnp.max(jnp.abs(tx.update(grads, tx.init(grads))[0]["w"]))) / config.conceal.decoder_opt.lr
    assert lo <= step <= hi * 1.0001
