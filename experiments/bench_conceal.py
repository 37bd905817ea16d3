"""ConcealGS benchmark on lego (200x200) with the teacher of `make bench-train`, hidden image astronaut
at 64x64: the full method and the paper's three ablations, at one or more decoder widths.

  make bench-conceal                                   # 10k iterations, widths 64 and 16
  make bench-conceal BENCH_ARGS="--iterations=1000 --widths=16 --rows=full --eval-views=20"

Each run goes to <workdir>/lego/conceal_<row>_w<width> (resumable). Writes conceal_bench.json (render
PSNR/SSIM/LPIPS vs ground truth and vs teacher, hidden PSNR/SSIM, leakage, wall time, median step
time) and conceal_bench.png to --out.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import jax

from conceal_jax.conceal import conceal
from conceal_jax.core import fileio
from experiments.bench_train import scene_config

ROWS = {"full": {}, "no_decoder": dict(use_decoder=False), "no_consistency": dict(consistency=False),
        "no_guidance": dict(guidance=False)}


def run(rows, widths, iterations, eval_views, workdir: pathlib.Path, out: pathlib.Path) -> list[dict]:
  """Runs every (width, row); rewrites the JSON and plot after each, so a stopped bench keeps its rows."""
  teacher = workdir / "lego" / "teacher" / "point_cloud.ply"
  if not teacher.is_file():
    print(f"skipping: no teacher at {teacher}; run `make bench-train` first")
    return []
  results = []
  for width in widths:
    for row in rows:
      if row == "no_decoder" and width != widths[0]:
        continue  # no decoder: the width does not matter
      config = scene_config("lego", None)  # the teacher's data and render settings
      config.mode = "conceal"
      c = config.conceal
      c.teacher, c.hidden, c.decoder_width, c.decoder_vgg_init = str(teacher), "astronaut", width, width == 64
      if iterations:
        c.iterations = iterations
      config.eval.max_views = eval_views
      for name, value in ROWS[row].items():
        c[name] = value
      run_dir = workdir / "lego" / f"conceal_{row}_w{width}"
      run_dir.mkdir(parents=True, exist_ok=True)
      fileio.write_json(run_dir / "config.json", config.to_dict())  # as the command line would (bench-robust reads it)
      result = conceal.conceal_and_evaluate(config, str(run_dir))
      results.append(dict(row=row, decoder_width=width, iterations=result["iterations"],
                          wall_time_s=result["wall_time_s"], median_step_s=result["median_step_s"],
                          **result["metrics"]))
      print(json.dumps(results[-1]))
      fileio.write_json(out / "conceal_bench.json", dict(device=str(jax.devices()[0]), rows=results))
      plot(results, out / "conceal_bench.png")
  return results


def plot(results, path: pathlib.Path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 2, figsize=(10, 4))
  labels = [f"{r['row']}\nw{r['decoder_width']}" for r in results]
  axes[0].bar(labels, [r["student_vs_ground_truth"]["psnr"] for r in results], label="student")
  axes[0].plot(labels, [r["teacher_vs_ground_truth"]["psnr"] for r in results], "k_", markersize=30,
               label="teacher")
  axes[0].set_ylabel("test PSNR vs ground truth (dB)")
  axes[0].legend()
  axes[1].bar(labels, [r["hidden"]["psnr"] for r in results])
  axes[1].set_ylabel("hidden image PSNR at the check view (dB)")
  for ax in axes:
    ax.tick_params(axis="x", labelsize=7)
    ax.grid(alpha=0.3, axis="y")
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--rows", default=",".join(ROWS))
  parser.add_argument("--widths", default="64,16")
  parser.add_argument("--iterations", type=int, default=0, help="0: the config's 10k")
  parser.add_argument("--eval-views", type=int, default=0, help="test views scored per run; 0: all 200")
  args = parser.parse_args()
  rows = [r for r in args.rows.split(",") if r]
  if set(rows) - set(ROWS):
    parser.error(f"unknown rows {sorted(set(rows) - set(ROWS))}; choose from {sorted(ROWS)}")
  run(rows, [int(w) for w in args.widths.split(",")], args.iterations, args.eval_views, pathlib.Path(args.workdir),
      pathlib.Path(args.out))


if __name__ == "__main__":
  main()
