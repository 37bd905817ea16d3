"""Teacher training benchmark: lego at 200x200 (the paper's 1/4) and the real COLMAP capture at 1/4.

  make bench-train                                  # 10k iterations each, the paper's pre-training
  make bench-train BENCH_ARGS="--iterations=2000 --scenes=lego --eval-views=25"

Trains with conceal_jax/configs/nerf_synthetic.py and colmap.py into <workdir>/<scene>/teacher (a killed
run resumes from its checkpoint), then writes train_bench.json (iterations, wall time, median step
time, Gaussian count, test PSNR / SSIM / LPIPS-VGG) and train_bench.png (training PSNR curves) to
--out. Scenes whose data is missing under ../shared/data are skipped with a note.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import platform

import jax

from conceal_jax.core import fileio
from conceal_jax.gs import train
from conceal_jax.configs import beer, lego

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The benchmark scenes are named config variants (the configs' docstrings say why they differ from the recipe).
SCENES = {"lego": lego, "beer": beer}


def scene_config(name: str, iterations: int | None, eval_views: int = 0):
  config = SCENES[name].get_config()
  config.data.path = str(ROOT / config.data.path)  # the configs' paths are relative to the project root
  config.eval.max_views = eval_views
  config.train.progress_bar = True
  if iterations:
    config.train.iterations = iterations
  return config


def run(names, iterations, eval_views, workdir: pathlib.Path) -> list[dict]:
  rows = []
  for name in names:
    config = scene_config(name, iterations, eval_views)
    if not pathlib.Path(config.data.path).is_dir():
      print(f"skipping {name}: {config.data.path} not found")
      continue
    out = workdir / name / "teacher"
    out.mkdir(parents=True, exist_ok=True)
    result = train.train_and_evaluate(config, str(out))
    rows.append(dict(scene=name, downscale=config.data.downscale, iterations=result["iterations"],
                     resumed_from=result["resumed_from"], wall_time_s=result["wall_time_s"],
                     median_step_s=result["median_step_s"], num_gaussians=result["num_gaussians"],
                     test=result["test"], test_views=eval_views or "all",
                     curve=[(h["step"], h["psnr"]) for h in result["history"] if "psnr" in h]))
    print(json.dumps({k: v for k, v in rows[-1].items() if k != "curve"}))
  return rows


def plot(rows, path: pathlib.Path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(6, 4))
  for row in rows:
    steps, values = zip(*row["curve"]) if row["curve"] else ((), ())
    ax.plot(steps, values, label=f"{row['scene']} (test {row['test']['psnr']:.2f} dB)", alpha=0.8)
  ax.set_xlabel("iteration")
  ax.set_ylabel("training-view PSNR (dB)")
  ax.grid(alpha=0.3)
  ax.legend()
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--scenes", default="lego,beer")
  parser.add_argument("--iterations", type=int, default=0, help="0: the configs' 10k")
  parser.add_argument("--eval-views", type=int, default=0, help="test views scored (exact mode); 0: all")
  args = parser.parse_args()
  names = [n for n in args.scenes.split(",") if n]
  unknown = set(names) - set(SCENES)
  if unknown:
    parser.error(f"unknown scenes {sorted(unknown)}; choose from {sorted(SCENES)}")
  rows = run(names, args.iterations, args.eval_views, pathlib.Path(args.workdir))
  if not rows:
    return
  out = pathlib.Path(args.out)
  rows = merged_rows(out / "train_bench.json", rows)
  fileio.write_json(out / "train_bench.json", dict(device=str(jax.devices()[0]), cpu=platform.processor(),
                                                   rows=rows))
  plot(rows, out / "train_bench.png")


def merged_rows(path: pathlib.Path, rows: list[dict]) -> list[dict]:
  """The new rows plus the rows of other scenes already in `path` (so scenes can be run one at a time)."""
  try:
    old = json.loads(path.read_text())["rows"]
  except (OSError, ValueError, KeyError):
    old = []
  names = {row["scene"] for row in rows}
  return [row for row in old if row.get("scene") not in names] + rows


if __name__ == "__main__":
  main()
