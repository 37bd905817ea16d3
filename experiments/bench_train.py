"""Teacher training benchmark: lego at 200x200 (the paper's 1/4) and the real COLMAP capture at 1/4.

  make bench-train                                  # 10k iterations each, the paper's pre-training
  make bench-train BENCH_ARGS="--iterations=2000 --scenes=lego --eval-views=25"

Trains with conceal_jax/configs/nerf_synthetic.py and colmap.py into <workdir>/<scene>/teacher (a killed
run resumes from its checkpoint), then writes train_bench.json and train_bench.md (iterations,
training wall time, median step time, Gaussian count, test PSNR / SSIM / LPIPS-VGG on every test view)
and train_bench.png (test PSNR against training minutes, training PSNR against iterations) to --out. Scenes
whose data is missing under ../shared/data are skipped with a note.
"""
from __future__ import annotations

import argparse
import json
import pathlib


from conceal_jax.core import fileio
from conceal_jax.gs import evaluate, train
from conceal_jax.configs import beer, beer_llff, lego
from experiments import results_io

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The benchmark scenes are named config variants (the configs' docstrings say why they differ from the recipe).
SCENES = {"lego": lego, "beer": beer, "beer_llff": beer_llff}


def scene_config(name: str, iterations: int | None, eval_views: int = 0):
  config = SCENES[name].get_config()
  config.data.path = str(ROOT / config.data.path)  # the configs' paths are relative to the project root
  config.eval.max_views = eval_views
  config.train.progress_bar = True
  if iterations:
    config.train.iterations = iterations
  return config


# Targets: mean test PSNR over every test view (the teacher issue), and the training wall time on a 2-core CPU (the
# scale issue: 10k lego steps in at most 20 minutes).
TARGETS = {"lego": dict(psnr=33.0, minutes=20.0), "beer": dict(psnr=24.0)}


def run(names, iterations, eval_views, workdir: pathlib.Path, reuse: bool = False) -> list[dict]:
  """Trains (or resumes) each scene; with `reuse`, a finished run's train.json and metrics.json are read
  instead of evaluating it again."""
  rows = []
  for name in names:
    config = scene_config(name, iterations, eval_views)
    if not pathlib.Path(config.data.path).is_dir():
      print(f"skipping {name}: {config.data.path} not found")
      continue
    out = workdir / name / "teacher"
    out.mkdir(parents=True, exist_ok=True)
    result = finished_run(out) if reuse else None
    result = result or train.train_and_evaluate(config, str(out))
    rows.append(summary_row(name, config, result, eval_views))
    print(json.dumps({k: v for k, v in rows[-1].items() if not k.endswith("curve")}))
  return rows


def finished_run(out: pathlib.Path) -> dict | None:
  """train_and_evaluate's result of a finished run in `out`, from its train.json and metrics.json."""
  try:
    summary = json.loads((out / train.TRAIN_FILE).read_text())
    test = json.loads((out / evaluate.METRICS_FILE).read_text())["mean"]
  except (OSError, ValueError, KeyError):
    return None
  return dict(summary, test=test)


def summary_row(name: str, config, result: dict, eval_views: int) -> dict:
  """One table row: the run's length, time and size, its scores on the test views, and its curves
  (test PSNR on the quick subset against training minutes; training-view PSNR every 100 steps)."""
  history = result["history"]
  return dict(scene=name, downscale=config.data.downscale, iterations=result["iterations"],
              resumed_from=result["resumed_from"], wall_time_s=result["wall_time_s"],
              median_step_s=result["median_step_s"], step_devices=result.get("step_devices", []),
              num_gaussians=result["num_gaussians"],
              max_gaussians=config.train.densify.max_gaussians, tile_size=config.render.tile_size,
              compiled_step_variants=len(result["compiled_step_variants"]),
              capacity_reruns=result["capacity_reruns"], capacity_shrinks=result.get("capacity_shrinks", 0),
              test=result["test"], test_views=eval_views or "all",
              targets=TARGETS.get(name, {}),
              test_curve=[(h["step"], h["elapsed_s"], h["test_psnr"]) for h in history if "test_psnr" in h],
              train_curve=[(h["step"], h["elapsed_s"], h["psnr"]) for h in history
                           if "psnr" in h and h["step"] % 100 == 0])


def plot(rows, path: pathlib.Path):
  """Left: test PSNR against training minutes (quick subset; the star is every test view at the end).
  Right: training-view PSNR against iterations."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
  for row in rows:
    curve = row.get("test_curve") or []
    line, = left.plot([t / 60 for _, t, _ in curve], [p for _, _, p in curve], marker=".",
                      label=row["scene"] + results_io.on_device(row))
    left.plot(row["wall_time_s"] / 60, row["test"]["psnr"], marker="*", markersize=12, color=line.get_color(),
              label=f"{row['scene']}: {row['test']['psnr']:.2f} dB, all test views")
    target = row.get("targets", {})
    if "psnr" in target:
      left.axhline(target["psnr"], color=line.get_color(), linestyle=":", alpha=0.6)
    if "minutes" in target:
      left.axvline(target["minutes"], color=line.get_color(), linestyle=":", alpha=0.6)
    steps = [s for s, _, _ in row.get("train_curve") or []]
    right.plot(steps, [p for _, _, p in row.get("train_curve") or []], label=row["scene"], alpha=0.8)
  left.set_xlabel("training wall time (min)")
  left.set_ylabel("test PSNR (dB)")
  right.set_xlabel("iteration")
  right.set_ylabel("training-view PSNR (dB)")
  for ax in (left, right):
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
  fileio.save_figure(fig, path)


def table(rows) -> str:
  """The rows as a Markdown table."""
  lines = ["| scene | downscale | iterations | wall time (min) | median step (ms) | Gaussians (cap) | tile | "
           "test PSNR | SSIM | LPIPS-VGG | test views | target |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    target = ", ".join(f"{k} {v:g}" for k, v in r.get("targets", {}).items())
    lines.append(f"| {r['scene']} | {r['downscale']:g} | {r['iterations']} | "
                 f"{r['wall_time_s'] / 60:.1f}{results_io.on_device(r)} | {1e3 * r['median_step_s']:.0f} | "
                 f"{r['num_gaussians']} "
                 f"({r.get('max_gaussians') or 'none'}) | {r.get('tile_size', '')} | {r['test']['psnr']:.2f} | "
                 f"{r['test']['ssim']:.4f} | {r['test']['lpips']:.4f} | {r['test_views']} | {target} |")
  return "\n".join(lines) + "\n"


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--scenes", default="lego,beer")
  parser.add_argument("--iterations", type=int, default=0, help="0: the configs' 10k")
  parser.add_argument("--eval-views", type=int, default=0, help="test views scored (exact mode); 0: all")
  parser.add_argument("--reuse", action="store_true", help="read finished runs instead of evaluating again")
  args = parser.parse_args()
  names = [n for n in args.scenes.split(",") if n]
  unknown = set(names) - set(SCENES)
  if unknown:
    parser.error(f"unknown scenes {sorted(unknown)}; choose from {sorted(SCENES)}")
  rows = run(names, args.iterations, args.eval_views, pathlib.Path(args.workdir), args.reuse)
  if not rows:
    return
  out = pathlib.Path(args.out)
  results_io.write_results(out, "train_bench", rows, lambda row: row["scene"], table, plot)


if __name__ == "__main__":
  main()
