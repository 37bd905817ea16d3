"""Several hidden images in one student (issue 13, item 5): the demo scene with 1, 2, 3 and 4 hidden images,
each at its own key (mark.extra_hidden), one decoder for all.

  make bench-robust                                          # after bench_robust; MULTIKEY_ARGS pass here
  python -m experiments.bench_multikey --counts=1,2 --iterations=600
  python -m experiments.bench_multikey --reuse               # rebuild the JSON, table and plot

The demo configuration (configs/demo.py: its concealment settings, 1300 steps) on the demo teacher
(--teacher; trained there with configs/demo.py first if missing, as `make demo` does). Run n hides the
first n of --images at the training cameras key_index, key_index - 1, ... (see mark.extra_hidden) with
the same number of steps: the keys take turns, so each gets 1/n of the L_d^+ steps at the cost per step
of one key. Each run goes to <workdir>/demo/multikey_<n> (resumable). Writes multikey_bench.json (per n:
each image's PSNR / SSIM at its own key, the cross-talk matrix and its max, the hidden images' SSIM to
each other (the cross-talk of a perfect reveal), the three leakage figures over every image and key, the
student's test PSNR against the teacher's renders and its loss against ground truth, wall time),
multikey_bench.md and multikey_bench.png to --out. Rows of earlier invocations stay in the JSON.
Natural images are somewhat alike (SSIM ~0.1-0.25 between these four at 64x64), so a leakage or cross-talk
figure that is a max over more images rises by chance too: images_ssim gives that level.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from conceal_jax import main as main_lib
from conceal_jax.configs import demo
from conceal_jax.core import fileio
from conceal_jax.gs import evaluate
from experiments import results_io
from experiments.bench_conceal import finished_run

IMAGES = ("astronaut", "camera", "coffee", "chelsea")


def ensure_teacher(teacher: pathlib.Path) -> None:
  """Trains the demo teacher into teacher's folder (as `make demo`) unless it is there already."""
  if teacher.is_file():
    return
  if teacher.name != evaluate.SCENE_FILE:
    raise SystemExit(f"no teacher at {teacher} (to train one there, name a .../{evaluate.SCENE_FILE})")
  print(f"no teacher at {teacher}: training the demo teacher there first")
  main_lib.run(demo.get_config(), str(teacher.parent))


def run_config(teacher: pathlib.Path, images: list[str], iterations: int):
  config = demo.get_config()
  config.mode = "conceal"
  m = config.mark
  m.teacher, m.hidden, m.extra_hidden = str(teacher), images[0], tuple(images[1:])
  if iterations:
    config.conceal.iterations = iterations
  return config


def summary_row(images: list[str], result: dict) -> dict:
  """One row per number of images; a single image's metrics.json has no `keys`, its figures are the run's."""
  m = result["metrics"]
  keys = m.get("keys")
  own = keys["hidden"] if keys else [m["hidden"]]
  return dict(num_images=len(images), images=images, iterations=result["iterations"],
              wall_time_s=result["wall_time_s"], median_step_s=result["median_step_s"],
              num_decoys=result.get("num_decoys", 0),
              hidden=[dict(image=name, psnr=h["psnr"], ssim=h["ssim"]) for name, h in zip(images, own)],
              mean_hidden_psnr=float(np.mean([h["psnr"] for h in own])), min_hidden_ssim=min(h["ssim"] for h in own),
              max_cross_talk=keys["max_cross_talk"] if keys else None,
              cross_talk_ssim=keys["cross_talk_ssim"] if keys else None,
              images_ssim=keys["images_ssim"] if keys else None,
              leakage=m["leakage"], max_leakage=max(m["leakage"].values()),
              student_vs_teacher_psnr=m["student_vs_teacher"]["psnr"],
              student_psnr=m["student_vs_ground_truth"]["psnr"], teacher_psnr=m["teacher_vs_ground_truth"]["psnr"],
              student_psnr_loss=m["teacher_vs_ground_truth"]["psnr"] - m["student_vs_ground_truth"]["psnr"])


def row_key(r: dict) -> tuple:
  return (r["num_images"],)


def table(rows) -> str:
  lines = ["| images | steps | wall time (min) | median step (ms) | hidden PSNR / SSIM per image | max cross-talk | "
           "leakage: test views / clean teacher / near key | student vs teacher PSNR | loss (dB) |",
           "|---|---|---|---|---|---|---|---|---|"]
  for r in sorted(rows, key=row_key):
    hidden = ", ".join(f"{h['image']} {h['psnr']:.2f} / {h['ssim']:.4f}" for h in r["hidden"])
    cross = "-" if r["max_cross_talk"] is None else f"{r['max_cross_talk']:.3f}"
    lines.append(f"| {r['num_images']} | {r['iterations']} | {r['wall_time_s'] / 60:.1f} | "
                 f"{1e3 * r['median_step_s']:.0f} | {hidden} | {cross} | {results_io.leakage_cells(r['leakage'])} | "
                 f"{r['student_vs_teacher_psnr']:.2f} | {r['student_psnr_loss']:.2f} |")
  return "\n".join(lines) + "\n"


def plot(rows, path: pathlib.Path):
  """Each image's hidden PSNR at its key; SSIM of the worst image, cross-talk and leakage; the student's
  fidelity and the wall time; all against the number of hidden images."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  rows = sorted(rows, key=row_key)
  n = [r["num_images"] for r in rows]
  fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
  for image in dict.fromkeys(h["image"] for r in rows for h in r["hidden"]):
    points = [(r["num_images"], h["psnr"]) for r in rows for h in r["hidden"] if h["image"] == image]
    axes[0].plot(*zip(*points), marker="o", linestyle="none", label=image)
  axes[0].plot(n, [r["mean_hidden_psnr"] for r in rows], "k-", alpha=0.5, label="mean")
  axes[0].set_ylabel("hidden PSNR at its own key (dB)")
  axes[1].plot(n, [r["min_hidden_ssim"] for r in rows], marker="o", label="worst image's SSIM at its key")
  crossed = [(r["num_images"], r["max_cross_talk"], np.max(np.array(r["images_ssim"]) - np.eye(r["num_images"])))
             for r in rows if r["max_cross_talk"] is not None]
  if crossed:
    axes[1].plot([c[0] for c in crossed], [c[1] for c in crossed], marker="s", label="max cross-talk SSIM")
    axes[1].plot([c[0] for c in crossed], [c[2] for c in crossed], "kx:", label="cross-talk of a perfect reveal")
  axes[1].plot(n, [r["max_leakage"] for r in rows], marker="^", label="max leakage SSIM")
  axes[1].set_ylabel("SSIM")
  axes[2].plot(n, [r["student_vs_teacher_psnr"] for r in rows], marker="o", label="student vs teacher PSNR")
  axes[2].set_ylabel("student test PSNR vs the teacher's renders (dB)")
  twin = axes[2].twinx()
  twin.plot(n, [r["wall_time_s"] / 60 for r in rows], "k.--", label="wall time")
  twin.set_ylabel("wall time (min)")
  for ax in axes:
    ax.set_xlabel("hidden images (keys)")
    ax.set_xticks(n)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--teacher", default="workdirs/demo/teacher/point_cloud.ply",
                      help="the demo teacher (trained there if missing)")
  parser.add_argument("--images", default=",".join(IMAGES), help="hidden images, in key order")
  parser.add_argument("--counts", default="1,2,3,4", help="numbers of hidden images to run")
  parser.add_argument("--iterations", type=int, default=0, help="0: the demo config's")
  parser.add_argument("--reuse", action="store_true", help="read finished runs instead of running them")
  args = parser.parse_args()
  images = [name for name in args.images.split(",") if name]
  counts = [int(n) for n in args.counts.split(",") if n]
  if not counts or not all(1 <= n <= len(images) for n in counts):
    parser.error(f"--counts must lie in 1..{len(images)} (the number of --images)")
  teacher = pathlib.Path(args.teacher)
  if not args.reuse:
    ensure_teacher(teacher)
  results = []
  for n in counts:
    run_dir = pathlib.Path(args.workdir) / "demo" / f"multikey_{n}"
    config = run_config(teacher, images[:n], args.iterations)
    result = finished_run(run_dir)
    if result is None or not (args.reuse or result["iterations"] == config.conceal.iterations):
      if args.reuse:
        print(f"skipping {n} images: no finished run in {run_dir}")
        continue
      result = main_lib.run(config, str(run_dir))  # writes config.json as the command line would
    results.append(summary_row(images[:n], result))
    print(json.dumps({k: v for k, v in results[-1].items() if k not in ("cross_talk_ssim", "images_ssim")}))
    results_io.write_results(pathlib.Path(args.out), "multikey_bench", results, row_key, table, plot)


if __name__ == "__main__":
  main()
