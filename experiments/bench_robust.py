"""Robustness of concealment runs: image attacks on the check render, model attacks on the student, and
the tolerance of the check pose.

  make bench-robust                                     # the demo run and bench-conceal's lego run
  make bench-robust BENCH_ARGS="--runs=workdirs/demo/conceal --test-views=5"

Each run is a conceal workdir (student.ply, decoder.msgpack, key.json and the config.json its job wrote).
Writes robust_bench.json (per run: the unattacked hidden PSNR / SSIM, one row per image-attack level
with its SSIM drop, one row per model-attack level with the attacked scene's test PSNR, and the pose
curve) and robust_bench.png to --out. Runs whose workdir is missing are skipped with a note.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import jax
import ml_collections
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, reveal
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import evaluate
from conceal_jax.robust import image_attacks, robustness

DEFAULT_RUNS = "workdirs/demo/conceal,workdirs/bench/lego/conceal_full_w16"
# The paper's mild levels (blur sigma <= 1, JPEG quality >= 70) and its finding: mean SSIM drop ~0.02.
PAPER_MILD = (("blur", lambda s: s <= 1.0), ("jpeg", lambda q: q >= 70))


def load_run(run: pathlib.Path):
  """(config, student, owner) of a finished conceal workdir."""
  config = ml_collections.ConfigDict(json.loads((run / "config.json").read_text()))
  camera, info = key_lib.load_key(str(run / "key.json"))
  decoder = reveal.load_decoder(str(run / "decoder.msgpack")) if info.get("uses_decoder", True) else None
  hidden = hidden_lib.load_hidden_image(config.conceal.hidden, int(info["hidden_size"]))
  owner = robustness.Owner(decoder=decoder, decoder_width=int(info.get("decoder_width", 0)), hidden=hidden,
                           check_camera=camera, options=reveal.options_from_key(info))
  return config, ply.load_ply(str(run / "student.ply")), owner


def bench_run(run: pathlib.Path, test_views: int) -> dict:
  config, student, owner = load_run(run)
  scene = evaluate.load_scene_data(config)
  cameras, targets, _ = evaluate.held_out_views(scene, test_views)
  base, image_rows = robustness.image_attack_rows(student, owner)
  mild = [r["ssim_drop"] for r in image_rows for name, is_mild in PAPER_MILD
          if r["attack"] == name and is_mild(r["level"])]
  model_rows = robustness.model_attack_rows(student, owner, cameras, targets)
  pose_rows = robustness.pose_tolerance_rows(student, owner, scene.scene_extent())
  return dict(run=str(run), num_gaussians=int(student.num), test_views=len(cameras), **base,
              paper_mild_mean_ssim_drop=float(np.mean(mild)), image_attacks=image_rows,
              model_attacks=model_rows, pose=pose_rows)


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
    left.set_xlabel("attack level (mild to strong)")
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
    for kind, unit in (("translation", "% of extent"), ("rotation", "degrees")):
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
  args = parser.parse_args()
  results = []
  for run in (pathlib.Path(r) for r in args.runs.split(",") if r):
    if not (run / "student.ply").is_file() or not (run / "config.json").is_file():
      print(f"skipping {run}: no finished conceal run with a config.json there")
      continue
    results.append(bench_run(run, args.test_views))
    print(json.dumps({k: v for k, v in results[-1].items() if not isinstance(v, list)}))
  if not results:
    return
  out = pathlib.Path(args.out)
  fileio.write_json(out / "robust_bench.json", dict(device=str(jax.devices()[0]), image_attack_levels=[
      list(level) for level in image_attacks.LEVELS], runs=results))
  plot(results, out / "robust_bench.png")


if __name__ == "__main__":
  main()
