"""ConcealGS benchmark on lego (200x200) with the teacher of `make bench-train`, hidden image astronaut
at 64x64: the full method and the paper's three ablations, at one or more decoder widths.

  make bench-conceal                                   # 10k iterations, widths 64 and 16
  make bench-conceal BENCH_ARGS="--iterations=1000 --widths=16 --rows=full"

Each run goes to <workdir>/lego/conceal_<row>_w<width> (resumable). Writes conceal_bench.json (render
PSNR/SSIM/LPIPS vs ground truth and vs teacher, hidden PSNR/SSIM, leakage, wall time, median step
time) and conceal_bench.png to --out.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import jax

from conceal_jax import conceal, fileio
from conceal_jax.configs import nerf_synthetic
from experiments.bench_train import SCENES

ROWS = {"full": {}, "no_decoder": dict(use_decoder=False), "no_consistency": dict(consistency=False),
        "no_guidance": dict(guidance=False)}


def run(rows, widths, iterations, workdir: pathlib.Path) -> list[dict]:
  teacher = workdir / "lego" / "teacher" / "point_cloud.ply"
  if not teacher.is_file():
    print(f"skipping: no teacher at {teacher}; run `make bench-train` first")
    return []
  results = []
  for width in widths:
    for row in rows:
      if row == "no_decoder" and width != widths[0]:
        continue  # no decoder: the width does not matter
      config = nerf_synthetic.get_config()
      config.mode = "conceal"
      config.data.path = str(SCENES["lego"][1])
      c = config.conceal
      c.teacher, c.hidden, c.decoder_width, c.decoder_vgg_init = str(teacher), "astronaut", width, width == 64
      if iterations:
        c.iterations = iterations
      for name, value in ROWS[row].items():
        c[name] = value
      out = workdir / "lego" / f"conceal_{row}_w{width}"
      out.mkdir(parents=True, exist_ok=True)
      result = conceal.conceal_and_evaluate(config, str(out))
      results.append(dict(row=row, decoder_width=width, iterations=result["iterations"],
                          wall_time_s=result["wall_time_s"], median_step_s=result["median_step_s"],
                          **result["metrics"]))
      print(json.dumps(results[-1]))
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
  args = parser.parse_args()
  rows = [r for r in args.rows.split(",") if r]
  if set(rows) - set(ROWS):
    parser.error(f"unknown rows {sorted(set(rows) - set(ROWS))}; choose from {sorted(ROWS)}")
  results = run(rows, [int(w) for w in args.widths.split(",")], args.iterations, pathlib.Path(args.workdir))
  if results:
    out = pathlib.Path(args.out)
    fileio.write_json(out / "conceal_bench.json", dict(device=str(jax.devices()[0]), rows=results))
    plot(results, out / "conceal_bench.png")


if __name__ == "__main__":
  main()
