"""How a capture starts: the time of a 3D-GS step over the first steps of a teacher, per pixel, lego against the
real capture "beer" read through its LLFF poses (poses_bounds.npy, no points: random start in its
cameras' frustums).

  make bench-start                                   # the first 1000 steps of each, then the table and plot
  make bench-start BENCH_ARGS="--steps=300"

A forward-facing capture's background fills every image, so its splats cover more tiles than an object's and its
first steps cost more per pixel than lego's; the start (random points in the cameras' frustums, splats of a few
pixels) sets how many more. Each scene trains its config (lego.py; beer_llff.py) for --steps iterations into
<workdir>/first<steps>/<scene> (resumable), then scores 5 test views. Merges its rows into start_bench.json (per
scene and length: image size, median step and step time per pixel over the run's log windows, the first window's,
pairs and Gaussians; beer's time per pixel over lego's of as many steps, against the target) and rewrites
start_bench.md and start_bench.png (time per pixel and pairs against the step) in --out. Scenes whose data is
missing are skipped with a note. A run of N steps uses N as its schedule's length (learning-rate decay,
densification stop), so its first steps are those of an N-step teacher.
"""
from __future__ import annotations

import argparse
import pathlib

import numpy as np

from conceal_jax.core import fileio
from conceal_jax.gs import evaluate, train
from experiments import bench_train, results_io

# The scenes: bench_train's config of each, beer read through its LLFF poses (configs/beer_llff.py).
SCENES = ("lego", "beer_llff")
NAME = "start_bench"
REFERENCE = "lego"
TARGET_RATIO = 2.0  # the capture issue's bound: a step on beer costs at most 2x lego's per pixel
EVAL_VIEWS = 5


def scene_config(name: str, steps: int):
  config = bench_train.scene_config(name, steps, EVAL_VIEWS)
  config.train.eval_every = 0
  return config


def window_times(history: list[dict]) -> list[tuple[int, float, float]]:
  """(step, seconds per step since the previous log entry, pairs) of each log window of a train history."""
  rows, last_step, last_s = [], 0, 0.0
  for entry in history:
    if "elapsed_s" not in entry or "num_pairs" not in entry:
      continue
    steps = entry["step"] - last_step
    if steps > 0:
      rows.append((entry["step"], (entry["elapsed_s"] - last_s) / steps, entry["num_pairs"]))
    last_step, last_s = entry["step"], entry["elapsed_s"]
  return rows


def run_scene(name: str, steps: int, workdir: pathlib.Path) -> dict | None:
  config = scene_config(name, steps)
  if not pathlib.Path(config.data.path).is_dir():
    print(f"skipping {name}: {config.data.path} not found")
    return None
  scene = evaluate.load_scene_data(config)
  camera = scene.train_cameras[0]
  out = workdir / name
  out.mkdir(parents=True, exist_ok=True)
  result = bench_train.finished_run(out) or train.train_and_evaluate(config, str(out), scene=scene)
  pixels = camera.width * camera.height
  windows = window_times(result["history"])
  return dict(scene=name, format=config.data.format, width=camera.width, height=camera.height, pixels=pixels,
              steps=result["iterations"], median_step_s=result["median_step_s"],
              step_us_per_pixel=1e6 * result["median_step_s"] / pixels,
              first_window_step_s=windows[0][1] if windows else None,
              median_pairs=float(np.median([p for _, _, p in windows])) if windows else None,
              num_gaussians=result["num_gaussians"], step_devices=result.get("step_devices", []),
              test_psnr=result["test"]["psnr"], windows=windows)


def row_key(row: dict) -> tuple:
  return row["scene"], row["steps"]


def with_ratios(rows: list[dict]) -> list[dict]:
  """The rows, each but the reference's with `ratio_per_pixel` (its step time per pixel over the reference
  scene's of as many steps) and `target_met` (that ratio at most TARGET_RATIO) where that reference row exists."""
  reference = {r["steps"]: r["step_us_per_pixel"] for r in rows if r["scene"] == REFERENCE}
  out = []
  for r in rows:
    r = {k: v for k, v in r.items() if k not in ("ratio_per_pixel", "target_met")}
    if r["scene"] != REFERENCE and r["steps"] in reference:
      r["ratio_per_pixel"] = r["step_us_per_pixel"] / reference[r["steps"]]
      r["target_met"] = r["ratio_per_pixel"] <= TARGET_RATIO
    out.append(r)
  return out


def table(rows: list[dict]) -> str:
  lines = ["| scene | format | image | steps | median step (ms) | step per pixel (us) | first window step (ms) | "
           "median pairs | Gaussians at the end | test PSNR (5 views) | per pixel / lego's |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    ratio = r.get("ratio_per_pixel")
    first = "-" if r["first_window_step_s"] is None else f"{1e3 * r['first_window_step_s']:.0f}"
    pairs = "-" if r["median_pairs"] is None else f"{r['median_pairs']:.0f}"
    lines.append(f"| {r['scene']} | {r['format']} | {r['width']}x{r['height']} | {r['steps']} | "
                 f"{1e3 * r['median_step_s']:.0f}{results_io.on_device(r)} | {r['step_us_per_pixel']:.2f} | {first} | "
                 f"{pairs} | {r['num_gaussians']} | {r['test_psnr']:.2f} | "
                 f"{'-' if ratio is None else f'{ratio:.2f} (target <= {TARGET_RATIO:g})'} |")
  return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: pathlib.Path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
  for r in rows:
    steps = [s for s, _, _ in r["windows"]]
    left.plot(steps, [1e6 * t / r["pixels"] for _, t, _ in r["windows"]], label=f"{r['scene']} ({r['width']}x"
              f"{r['height']})")
    right.plot(steps, [p for _, _, p in r["windows"]], label=r["scene"])
  left.set_ylabel("step time per pixel (us)")
  left.set_yscale("log")
  right.set_ylabel("Gaussian-tile pairs")
  for ax in (left, right):
    ax.set_xlabel("step")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench_start")
  parser.add_argument("--steps", type=int, default=1000)
  parser.add_argument("--scenes", default=",".join(SCENES))
  args = parser.parse_args()
  names = [n for n in args.scenes.split(",") if n]
  unknown = set(names) - set(SCENES)
  if unknown:
    parser.error(f"unknown scenes {sorted(unknown)}; choose from {sorted(SCENES)}")
  rows = [row for row in (run_scene(n, args.steps, pathlib.Path(args.workdir) / f"first{args.steps}")
                          for n in names) if row]
  if not rows:
    return
  out = pathlib.Path(args.out)
  rows = with_ratios(results_io.merged_rows(out / f"{NAME}.json", rows, row_key))
  print(table(results_io.write_results(out, NAME, rows, row_key, table, plot, reference=REFERENCE,
                                       target_ratio=TARGET_RATIO)))


if __name__ == "__main__":
  main()
