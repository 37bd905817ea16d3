"""What accuracy costs in time: the renderer on the real garden point cloud (issue: renderer benchmark).

  make bench-render            # or: python -m experiments.bench_render --out=experiments/results

For every Gaussian count (20k, 50k, all 139k points), image size (128^2, 256^2, native 420x648), SH degree
(0, 3) and mode (K in {64, 128, 256, 512} nearest per tile, or exact), it records the median forward and
forward+backward times, compile time, XLA's peak buffer size, the max abs error against exact mode and
the number of overflowing tiles. Writes render_bench.json and render_bench.png. Skips cleanly without
../shared/data/garden_points.npz.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax import Camera, RenderOptions
from conceal_jax import render
from conceal_jax.core import fileio
from conceal_jax.gs.init import gaussians_from_points

DATA = pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "garden_points.npz"
SIZES = {"128": (128, 128), "256": (256, 256), "native": (648, 420)}
MODES = [64, 128, 256, 512, None]  # None = exact


def garden_scene(points: np.ndarray, colors: np.ndarray, count: int, degree: int, seed: int = 0):
  """A 3D-GS-style initialisation of `count` garden points: kNN scales, opacity 0.5, random higher SH."""
  rng = np.random.default_rng(seed)
  idx = rng.choice(points.shape[0], count, replace=False) if count < points.shape[0] else np.arange(points.shape[0])
  g = gaussians_from_points(points[idx], colors[idx] / 255.0, sh_degree=degree, opacity=0.5)
  if degree > 0:  # view-dependent colour, so the degree-3 path has real work to do
    rest = rng.normal(0.0, 0.1, g.sh[:, 1:].shape)
    g = g.replace(sh=g.sh.at[:, 1:].set(jnp.asarray(rest, g.sh.dtype)))
  return g


def garden_camera(data, size: tuple[int, int]) -> Camera:
  """The first garden camera, its focal length scaled so the image height keeps the native field of view."""
  width, height = size
  k = data["Ks"][0]
  s = height / float(data["height"])
  cx = k[0, 2] * s if size == (int(data["width"]), int(data["height"])) else width / 2
  cy = k[1, 2] * s if size == (int(data["width"]), int(data["height"])) else height / 2
  return Camera.from_intrinsics(data["viewmats"][0], k[0, 0] * s, k[1, 1] * s, cx, cy, width, height)


def _median_time(fn, arg, repeats: int) -> float:
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(arg))
    times.append(time.perf_counter() - start)
  return float(np.median(times))


def measure(g, cam, options: RenderOptions, repeats: int, reference_rgb=None) -> dict:
  forward = jax.jit(lambda g: render(g, cam, options))
  loss = lambda g: jnp.sum(render(g, cam, options).rgb)
  backward = jax.jit(jax.value_and_grad(loss))
  start = time.perf_counter()
  compiled = backward.lower(g).compile()
  out = forward(g)
  jax.block_until_ready(out)
  compile_s = time.perf_counter() - start
  memory = compiled.memory_analysis()
  peak = None if memory is None else int(memory.temp_size_in_bytes + memory.argument_size_in_bytes
                                         + memory.output_size_in_bytes)
  jax.block_until_ready(compiled(g))
  result = dict(forward_s=_median_time(forward, g, repeats), forward_backward_s=_median_time(compiled, g, repeats),
                compile_s=compile_s, peak_bytes=peak, overflow_tiles=int(out.num_overflow_tiles))
  if reference_rgb is not None:
    result["max_abs_error_vs_exact"] = float(jnp.max(jnp.abs(out.rgb - reference_rgb)))
  return result, out.rgb


def run(counts, sizes, degrees, modes, repeats, out_dir: pathlib.Path, quiet=False) -> list[dict]:
  data = np.load(DATA)
  rows = []
  json_path = out_dir / "render_bench.json"
  for count in counts:
    for degree in degrees:
      g = garden_scene(data["means3d"], data["colors"], count, degree)
      for size_name in sizes:
        cam = garden_camera(data, SIZES[size_name])
        exact_rgb = None
        for k in sorted(modes, key=lambda m: m is not None):  # exact first: it is the reference
          options = RenderOptions(sh_degree=degree, max_per_tile=k, background=(1.0, 1.0, 1.0))
          result, rgb = measure(g, cam, options, repeats, exact_rgb)
          if k is None:
            exact_rgb = rgb
            result["max_abs_error_vs_exact"] = 0.0
          row = dict(num_gaussians=int(g.num), size=size_name, width=cam.width, height=cam.height,
                     sh_degree=degree, mode="exact" if k is None else f"K={k}", max_per_tile=k, **result)
          rows.append(row)
          if not quiet:
            print(json.dumps(row), flush=True)
          fileio.write_json(json_path, _report(rows, repeats))  # partial results survive an interruption
  return rows


def _report(rows, repeats):
  return dict(machine=dict(platform=platform.platform(), devices=[str(d) for d in jax.devices()],
                           jax=jax.__version__),
              timing=f"median of {repeats} runs after one warm-up; compile_s includes tracing", rows=rows)


def plot(rows, path: pathlib.Path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
  for ax, degree in zip(axes, (0, 3)):
    for (count, size), marker in zip(sorted({(r["num_gaussians"], r["size"]) for r in rows}), "osD^v<>ph*"):
      sel = [r for r in rows if r["sh_degree"] == degree and r["num_gaussians"] == count and r["size"] == size]
      if not sel:
        continue
      xs = [r["forward_backward_s"] * 1e3 for r in sel]
      ys = [max(r["max_abs_error_vs_exact"], 1e-7) for r in sel]
      ax.plot(xs, ys, marker=marker, linestyle=":", label=f"{count // 1000}k @ {size}")
      for x, y, r in zip(xs, ys, sel):
        ax.annotate(r["mode"].replace("K=", ""), (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward+backward median (ms)")
    ax.set_ylabel("max abs error vs exact (1e-7 = exact)")
    ax.set_title(f"SH degree {degree}")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
      ax.legend(fontsize=7)
  fileio.save_figure(fig, path)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--counts", default="20000,50000,138766")
  parser.add_argument("--sizes", default="128,256,native")
  parser.add_argument("--degrees", default="0,3")
  parser.add_argument("--modes", default="64,128,256,512,exact")
  parser.add_argument("--repeats", type=int, default=5)
  args = parser.parse_args(argv)
  if not DATA.exists():
    print(f"skipped: {DATA} not found (the garden point cloud lives in ../shared/data)")
    return 0
  out = pathlib.Path(args.out)
  modes = [None if m == "exact" else int(m) for m in args.modes.split(",")]
  rows = run([int(c) for c in args.counts.split(",")], args.sizes.split(","),
             [int(d) for d in args.degrees.split(",")], modes, args.repeats, out)
  plot(rows, out / "render_bench.png")
  print(f"wrote {out / 'render_bench.json'} and {out / 'render_bench.png'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
