"""Full-resolution benchmark (issue 42), meant for an accelerator: lego at the 400x400 the shared copy holds.

  make bench-full BENCH_ARGS="--minutes=5"    # the teacher gets at most 5 minutes of steps

1. teacher: configs/lego_full.py (the 3D-GS recipe, 30k steps) for at most --minutes of steps
   (train.time_limit_min): a run stopped there is scored on every test view at the step it reached, and
   the same command resumes it towards 30k;
2. render: forward and forward+backward time, compile time and XLA's buffer estimate of that teacher on
   the first test view at 400x400 and at 800x800 (the same camera, intrinsics doubled: the original
   NeRF-Synthetic size);
3. conceal: lego_full.py:in_scene in that teacher for --conceal-steps steps: the median step time, and
   the 10k-step run it implies.
gsplat's CUDA rasterizer is not compared: it builds its kernels on install, and the machines this runs on
reach no package index. Writes full_bench.json and full_bench.md to --out, every row naming its device.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import train as conceal_train
from conceal_jax.configs import lego_full
from conceal_jax.core import checkpoint, fileio, loop
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, train
from experiments import bench_render, bench_train, results_io

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data" / "nerf_synthetic" / "lego"
TARGETS = dict(psnr=35.78)  # Inria's published 3D-GS figure for lego at 800x800, 30k steps


def full_config(recipe: str, data: pathlib.Path, lpips_net: str):
  config = lego_full.get_config(recipe)
  config.data.path = str(data)
  config.eval.lpips_net = lpips_net
  return config


def teacher_row(data: pathlib.Path, workdir: pathlib.Path, minutes: float, lpips_net: str) -> dict:
  """Trains (or resumes) the full-resolution teacher for at most `minutes` of steps and scores it."""
  config = full_config("", data, lpips_net)
  config.train.time_limit_min = minutes
  workdir.mkdir(parents=True, exist_ok=True)
  result = train.train_and_evaluate(config, str(workdir))
  row = bench_train.summary_row("lego_full", config, result, eval_views=0)
  return dict(row, kind="teacher", planned_iterations=result["planned_iterations"],
              time_limit_reached=result["time_limit_reached"], lpips_net=lpips_net, targets=TARGETS)


def render_rows(config, scene_ply: pathlib.Path, repeats: int) -> list[dict]:
  """Render timings of the teacher on the first test view, at its size and at twice its size."""
  scene = evaluate.load_scene_data(config)
  gaussians = jax.tree.map(jnp.asarray, ply.load_ply(str(scene_ply)))
  options = dataclasses.replace(evaluate.eval_options(config, scene.background), sh_degree=gaussians.sh_degree)
  rows = []
  for factor in (1, 2):
    first = scene.test_cameras[0]
    camera = first.resized(first.width * factor, first.height * factor)
    timing, _ = bench_render.measure(gaussians, camera, options, repeats)
    rows.append(dict(kind="render", scene="lego_full", size=f"{camera.width}x{camera.height}",
                     num_gaussians=int(gaussians.num), tile_size=options.tile_size,
                     step_devices=[loop.device_name()], **timing))
  return rows


def conceal_row(data: pathlib.Path, scene_ply: pathlib.Path, workdir: pathlib.Path, steps: int,
                lpips_net: str) -> dict:
  """`steps` steps of the in_scene recipe at full resolution: the median step time from the loop's
  windows (the checkpoint written at the last step holds them)."""
  config = full_config("in_scene", data, lpips_net)
  config.mark.teacher = str(scene_ply)
  workdir.mkdir(parents=True, exist_ok=True)
  conceal_train.train_and_evaluate(config, str(workdir), max_steps=steps)
  _, meta, _ = checkpoint.load_latest(str(workdir / loop.CHECKPOINT_DIR))
  median = loop.median_step_s(meta["windows"])
  teacher = json.loads((scene_ply.parent / train.TRAIN_FILE).read_text())
  return dict(kind="conceal", scene="lego_full", recipe="in_scene", steps=sum(n for n, _ in meta["windows"]),
              teacher_iterations=teacher["iterations"], teacher_gaussians=teacher["num_gaussians"],
              median_step_s=median, implied_minutes=median * config.conceal.iterations / 60,
              planned_iterations=config.conceal.iterations, step_devices=meta["step_devices"])


def table(rows) -> str:
  lines = []
  for r in rows:
    device = results_io.on_device(r)
    if r["kind"] == "teacher":
      t = r["test"]
      lines.append(f"- teacher: {r['iterations']} of {r['planned_iterations']} steps in {r['wall_time_s'] / 60:.1f} min"
                   f"{device} ({1e3 * r['median_step_s']:.0f} ms median step), {r['num_gaussians']} Gaussians; "
                   f"test {t['psnr']:.2f} dB / {t['ssim']:.4f} / LPIPS-{r['lpips_net']} {t['lpips']:.4f} on every "
                   f"test view (Inria 3D-GS, 800x800, 30k: {TARGETS['psnr']} dB)")
    elif r["kind"] == "render":
      lines.append(f"- render {r['size']}, {r['num_gaussians']} Gaussians{device}: forward "
                   f"{1e3 * r['forward_s']:.1f} ms, forward+backward {1e3 * r['forward_backward_s']:.1f} ms, "
                   f"compile {r['compile_s']:.1f} s, "
                   f"XLA buffers {(r['peak_bytes'] or 0) / 2**20:.0f} MiB, {r['pairs']} pairs")
    else:
      teacher = f" in the teacher of step {r['teacher_iterations']}" if "teacher_iterations" in r else ""
      lines.append(f"- conceal ({r['recipe']}){teacher}, {r['steps']} steps{device}: {1e3 * r['median_step_s']:.0f} ms "
                   f"median step, {r['implied_minutes']:.1f} min for {r['planned_iterations']} steps")
  return "\n".join(lines) + "\n"


def plot(rows, path: pathlib.Path):
  """Left: the teacher's test PSNR (10 views) against training minutes, Inria's figure dotted. Right: render
  forward and forward+backward times per image size."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
  for r in (r for r in rows if r["kind"] == "teacher"):
    curve = r.get("test_curve") or []
    left.plot([t / 60 for _, t, _ in curve], [p for _, _, p in curve], marker=".",
              label=f"lego 400x400{results_io.on_device(r)}")
  left.axhline(TARGETS["psnr"], linestyle=":", color="gray", label="Inria 3D-GS, 800x800, 30k steps")
  left.set_xlabel("training wall time (min)")
  left.set_ylabel("test PSNR (dB)")
  renders = [r for r in rows if r["kind"] == "render"]
  x = np.arange(len(renders))
  right.bar(x - 0.2, [1e3 * r["forward_s"] for r in renders], 0.4, label="forward")
  right.bar(x + 0.2, [1e3 * r["forward_backward_s"] for r in renders], 0.4, label="forward+backward")
  right.set_xticks(x, [r["size"] + results_io.on_device(r) for r in renders], fontsize=7)
  right.set_ylabel("ms per image")
  for ax in (left, right):
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
  fileio.save_figure(fig, path)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/full")
  parser.add_argument("--data", default=str(DATA))
  parser.add_argument("--minutes", type=float, default=0.0, help="teacher time limit (0: the whole 30k steps)")
  parser.add_argument("--conceal-steps", type=int, default=200)
  parser.add_argument("--repeats", type=int, default=5, help="timed render runs (the median is kept)")
  parser.add_argument("--lpips", default="vgg", help="LPIPS network of the teacher's scores")
  args = parser.parse_args(argv)
  data, workdir = pathlib.Path(args.data), pathlib.Path(args.workdir)
  if not data.is_dir():
    print(f"skipping: {data} not found")
    return
  keys = lambda row: (row["kind"], row.get("size", ""), row.get("recipe", ""))
  # written after each part: a lent machine's time may run out before the last
  write = lambda rows: results_io.write_results(pathlib.Path(args.out), "full_bench", rows, keys, table, plot)
  write([teacher_row(data, workdir / "teacher", args.minutes, args.lpips)])
  scene_ply = workdir / "teacher" / evaluate.SCENE_FILE
  rows = write(render_rows(full_config("", data, args.lpips), scene_ply, args.repeats))
  if args.conceal_steps:
    rows = write([conceal_row(data, scene_ply, workdir / "conceal", args.conceal_steps, args.lpips)])
  print(table(rows))


if __name__ == "__main__":
  main()
