"""Robustness of concealment runs: image attacks on the check render, model attacks on the student, and
the tolerance of the check pose.

  make bench-robust                                     # the robust demo run and bench-conceal's lego run
  make bench-robust BENCH_ARGS="--runs=workdirs/demo/conceal --test-views=5 --finetune="

Each run is a conceal workdir (student.ply, decoder.msgpack, key.json and the config.json its job wrote).
Writes robust_bench.json (per run: the unattacked hidden PSNR / SSIM, one row per image-attack level
with its SSIM drop, one row per model-attack level with the attacked scene's test PSNR, and the pose
curve) and robust_bench.png to --out. Runs whose workdir is missing are skipped with a note.

It also writes ownership_calibration.json for `--config.mode=verify`: scores (SSIM of the revealed image
to the run's hidden image I) of `marked` trials, the student under every mild and medium attack, and of
`clean` trials, scenes never marked with I at that key: the clean teacher at the key and at --poses
random orbit poses, the student at those poses and at every test view, and every other run's student and
teacher seen through this run's decoder at their own keys and test views, and every --clean-models scene
(teachers trained with other seeds, other scenes) at this run's key and orbit poses. The chosen threshold keeps the
measured false-positive rate below 1%.

`make bench-robust` then runs experiments/bench_multikey.py (several hidden images at their own keys in
one demo student: each image's quality at its key, the cross-talk between keys, leakage; arguments in
MULTIKEY_ARGS, since BENCH_ARGS are this script's).
"""
from __future__ import annotations

import argparse
import json
import pathlib

import jax
import ml_collections
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, near, reveal
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, train
from conceal_jax.robust import image_attacks, ownership, robustness

# The demo trained through attacks (configs/demo_robust.py; the Makefile trains it when missing) and bench-conceal's
# lego run of the best student, which reads clipped renders too
DEFAULT_RUNS = "workdirs/demo_robust/conceal,workdirs/bench/lego/conceal_in_scene_w16"
# The paper's mild levels (blur sigma <= 1, JPEG quality >= 70) and its finding: mean SSIM drop ~0.02.
PAPER_MILD = (("blur", lambda s: s <= 1.0), ("jpeg", lambda q: q >= 70))


MARKED_SEVERITIES = (image_attacks.MILD, image_attacks.MEDIUM)


def load_run(run: pathlib.Path):
  """(config, student, owner) of a finished conceal workdir."""
  config = ml_collections.ConfigDict(json.loads((run / "config.json").read_text()))
  camera, info = key_lib.load_key(str(run / "key.json"))
  decoder = reveal.load_decoder(str(run / "decoder.msgpack")) if info.get("uses_decoder", True) else None
  hidden = hidden_lib.load_hidden_image(config.mark.hidden, int(info["hidden_size"]))
  owner = robustness.Owner(decoder=decoder, decoder_width=int(info.get("decoder_width", 0)), hidden=hidden,
                           check_camera=camera, options=reveal.options_from_key(info),
                           reading=reveal.Reading.from_key(info))
  return config, ply.load_ply(str(run / "student.ply")), owner


def near_length(config, scene, owner: robustness.Owner) -> float:
  """The run's near-key length (near.near_length of its clean teacher, config.mark.teacher, at its key): the unit
  of the pose rows' translations, as in the conceal job's leakage figure and the run's decoys."""
  return near.near_length(ply.load_ply(config.mark.teacher), owner.check_camera, scene.train_cameras)[0]


def bench_run(run: pathlib.Path, test_views: int) -> dict:
  config, student, owner = load_run(run)
  scene = evaluate.load_scene_data(config)
  cameras, targets, _ = evaluate.held_out_views(scene, test_views)
  base, image_rows = robustness.image_attack_rows(student, owner)
  mild = [r["ssim_drop"] for r in image_rows for name, is_mild in PAPER_MILD
          if r["attack"] == name and is_mild(r["level"])]
  model_rows = robustness.model_attack_rows(student, owner, cameras, targets)
  pose_rows = robustness.pose_tolerance_rows(student, owner, near_length(config, scene, owner))
  return dict(run=str(run), num_gaussians=int(student.num), test_views=len(cameras), **base,
              paper_mild_mean_ssim_drop=float(np.mean(mild)), image_attacks=image_rows,
              model_attacks=model_rows, pose=pose_rows)


def finetune_rows(run: pathlib.Path, lengths: list[int], densify: bool, test_views: int) -> list[dict]:
  """The fine-tuning attack (ConcealGS's research question 3): 3D-GS training continued from the student
  on the scene's training views (with the run's own recipe, with or without densification), scored after
  each of `lengths` steps (snapshots of one run of max(lengths) steps, resumable in
  run/finetune_{fixed,densify}_<max(lengths)>)."""
  config, student, owner = load_run(run)
  config.mode = "train"
  config.init.kind, config.init.ply = "ply", str(run / "student.ply")
  config.train.iterations = max(lengths)
  config.train.snapshots = tuple(sorted(set(lengths) - {max(lengths)}))
  config.train.sh_degree_start = config.train.sh_degree  # the student is trained: every band from the start
  config.train.eval_every = 0
  config.eval.max_views = test_views
  if not densify:
    config.train.densify.until = 0  # no densification and no opacity reset
  # one workdir per schedule: a run of another length must not resume this one's checkpoints
  workdir = run / f"finetune_{'densify' if densify else 'fixed'}_{max(lengths)}"
  workdir.mkdir(exist_ok=True)
  fileio.write_json(workdir / "config.json", config.to_dict())
  train.train_and_evaluate(config, str(workdir))
  scene = evaluate.load_scene_data(config)
  cameras, targets, _ = evaluate.held_out_views(scene, test_views)
  rows = []
  for length in sorted(lengths):
    name = "point_cloud.ply" if length == max(lengths) else train.snapshot_name(length)
    attacked = jax.tree.map(jax.numpy.asarray, ply.load_ply(str(workdir / name)))
    rows.append(dict(steps=length, densify=densify, num_gaussians=int(attacked.num),
                     **robustness.scene_scores(attacked, owner, cameras, targets)))
  return rows


def views_of(run: pathlib.Path, poses: int, test_views: int) -> dict:
  """What a clean trial renders from run's scene: its teacher and student, its key, its test cameras and
  `poses` random cameras on its training orbit (wrong keys); `mark` names its teacher and hidden image."""
  config, student, owner = load_run(run)
  scene = evaluate.load_scene_data(config)
  cameras, _, _ = evaluate.held_out_views(scene, test_views)
  orbit = [key_lib.orbit_camera(scene.train_cameras, 1000 + seed) for seed in range(poses)]
  return dict(student=student, teacher=ply.load_ply(config.mark.teacher), owner=owner, test=cameras,
              orbit=orbit, mark=(config.mark.teacher, config.mark.hidden))


def scores_of(owner: robustness.Owner, gaussians, cameras) -> list[float]:
  renders = evaluate.render_images(jax.tree.map(jax.numpy.asarray, gaussians), list(cameras), owner.options)
  return owner.scores(owner.reveal_renders(renders))["ssim"].tolist()


def calibration_trials(runs: list[pathlib.Path], results: list[dict], poses: int, test_views: int,
                       clean_models: list[pathlib.Path] = ()) -> dict:
  """Labelled clean and marked scores over every run (see the module doc); each of `clean_models` (scenes
  never marked: teachers trained with other seeds, other scenes) is also seen through every run's decoder at
  its key and its orbit poses. Runs that share a teacher and a hidden image are not each other's clean trials."""
  views = {run: views_of(run, poses, test_views) for run in runs}
  models = {path: ply.load_ply(str(path)) for path in clean_models}
  clean, marked = [], []
  for run, result in zip(runs, results):
    mine = views[run]
    owner = mine["owner"]
    for rows in (result["image_attacks"], result["model_attacks"]):
      marked += [dict(run=str(run), trial=f"{r['attack']} {r['level']}", score=r["hidden_ssim"]) for r in rows
                 if r["severity"] in MARKED_SEVERITIES]
    trials = [("teacher at the key", mine["teacher"], [owner.check_camera]),
              ("teacher at orbit poses", mine["teacher"], mine["orbit"]),
              ("student at orbit poses", mine["student"], mine["orbit"]),
              ("student at test views", mine["student"], mine["test"])]
    trials += [(f"clean model {path}", gaussians, [owner.check_camera] + mine["orbit"])
               for path, gaussians in models.items()]
    for other, theirs in views.items():
      # a run that hid the same image in the same teacher is no clean model for this one: its student may
      # well reveal I through this decoder, and its teacher is this run's own
      if other != run and theirs["mark"] != mine["mark"]:
        cameras = [theirs["owner"].check_camera] + list(theirs["test"])
        trials += [(f"{other} student", theirs["student"], cameras), (f"{other} teacher", theirs["teacher"], cameras)]
    for name, gaussians, cameras in trials:
      clean += [dict(run=str(run), trial=name, score=s) for s in scores_of(owner, gaussians, cameras)]
  choice = ownership.choose_threshold([t["score"] for t in clean], [t["score"] for t in marked])
  return dict(choice, clean=[t["score"] for t in clean], marked=[t["score"] for t in marked],
              clean_trials=clean, marked_trials=marked)


def plot(results, path: pathlib.Path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(len(results), 3, figsize=(15, 4 * len(results)), squeeze=False)
  for (left, middle, right), result in zip(axes, results):
    name = pathlib.Path(result["run"]).parent.name + "/" + pathlib.Path(result["run"]).name
    for attack in dict.fromkeys(r["attack"] for r in result["image_attacks"]):
      rows = [r for r in result["image_attacks"] if r["attack"] == attack]
      left.plot(range(1, len(rows) + 1), [r["hidden_ssim"] for r in rows], marker="o", label=attack)
    left.axhline(result["hidden_ssim"], color="k", linestyle=":", label="no attack")
    # the order of image_attacks.LEVELS: brightness and contrast run by signed value, not by strength
    left.set_xlabel("attack level (mild to strong; brightness, contrast: lowest to highest value)")
    left.set_ylabel("hidden SSIM")
    left.set_title(f"{name}: check render attacked", fontsize=9)
    rows = result["model_attacks"]
    labels = [f"{r['attack']}\n{r['level']}" if r["level"] is not None else r["attack"] for r in rows]
    middle.bar(labels, [r["hidden_ssim"] for r in rows])
    middle.set_ylabel("hidden SSIM")
    middle.tick_params(axis="x", labelsize=6, rotation=90)
    twin = middle.twinx()
    twin.plot(labels, [r["render_psnr"] for r in rows], "k.", label="test PSNR")
    twin.set_ylabel("attacked scene test PSNR (dB)")
    middle.set_title(f"{name}: scene attacked", fontsize=9)
    for kind, unit in (("translation", "% of key depth"), ("rotation", "degrees")):
      rows = [r for r in result["pose"] if r["kind"] == kind]
      scale = 100 if kind == "translation" else 1
      right.plot([scale * r["value"] for r in rows], [r["mean_ssim"] for r in rows], marker="o",
                 label=f"{kind} ({unit})")
    right.set_xlabel("distance from the key")
    right.set_ylabel("hidden SSIM (mean over directions)")
    right.set_title(f"{name}: check pose moved", fontsize=9)
    for ax in (left, right):
      ax.grid(alpha=0.3)
      ax.legend(fontsize=7)
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--runs", default=DEFAULT_RUNS, help="comma-separated conceal workdirs")
  parser.add_argument("--test-views", type=int, default=10, help="test views scored per attacked scene")
  parser.add_argument("--poses", type=int, default=50, help="random orbit poses per scene for clean trials")
  parser.add_argument("--finetune", default="1000,3000,10000",
                      help="fine-tuning attack lengths (steps), with and without densification; empty: skip")
  parser.add_argument("--clean-models", default="",
                      help="comma-separated .ply files never marked (other seeds, other scenes): more clean trials")
  args = parser.parse_args()
  clean_models = [pathlib.Path(p) for p in args.clean_models.split(",") if p]
  for path in clean_models:
    if not path.is_file():
      raise SystemExit(f"--clean-models: no such file {path}")
  results, runs = [], []
  for run in (pathlib.Path(r) for r in args.runs.split(",") if r):
    if not (run / "student.ply").is_file() or not (run / "config.json").is_file():
      print(f"skipping {run}: no finished conceal run with a config.json there")
      continue
    runs.append(run)
    results.append(bench_run(run, args.test_views))
    lengths = [int(n) for n in args.finetune.split(",") if n]
    if lengths:
      results[-1]["finetune"] = [row for densify in (False, True)
                                 for row in finetune_rows(run, lengths, densify, args.test_views)]
    print(json.dumps({k: v for k, v in results[-1].items() if not isinstance(v, list)}))
  if not results:
    return
  out = pathlib.Path(args.out)
  fileio.write_json(out / "robust_bench.json", dict(device=str(jax.devices()[0]), image_attack_levels=[
      list(level) for level in image_attacks.LEVELS], runs=results))
  plot(results, out / "robust_bench.png")
  calibration = calibration_trials(runs, results, args.poses, 0, clean_models)
  fileio.write_json(out / "ownership_calibration.json", calibration)
  print(json.dumps({k: v for k, v in calibration.items() if not isinstance(v, list)}))


if __name__ == "__main__":
  main()
