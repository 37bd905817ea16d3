"""What accuracy costs in time: the renderer on the real garden point cloud (issue: renderer v2).

  make bench-render            # or: python -m experiments.bench_render --out=experiments/results [--quick]

For every Gaussian count (20k, 50k, all 138,766 points) and image size (256x166, native 648x420), SH degree 3,
it times the default (exact) renderer and variants: 16 px tiles, segment sizes 16 and 64, and the approximate
K-nearest truncation with K in {64, 128, 256}. Columns: median forward and forward+backward times (>= 5 runs
after a warm-up), compile time, XLA's peak buffer estimate, pairs, evaluated pixel-pairs and ns per evaluated
pixel-pair (forward+backward), and the error against a float64 render (the same renderer in float64, and for
the 20k/256 row also the independent per-pixel reference of tests/reference.py). Per scene it also reports the
pairs left by each culling step. Writes render_bench.json and render_bench.png; skips cleanly without
../shared/data/garden_points.npz.
"""
from __future__ import annotations

import argparse
import dataclasses
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
from conceal_jax.splat import binning
from conceal_jax.splat import render as render_lib
from conceal_jax.splat.projection import project

DATA = pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "garden_points.npz"
SIZES = {"256x166": (256, 166), "native": (648, 420)}
DEFAULT = RenderOptions(sh_degree=3, background=(1.0, 1.0, 1.0))
VARIANTS = {
    "exact (default)": DEFAULT,
    "exact 16px tiles": dataclasses.replace(DEFAULT, tile_size=16),
    "exact L=16": dataclasses.replace(DEFAULT, segment_size=16),
    "exact L=64": dataclasses.replace(DEFAULT, segment_size=64),
    "K=64": dataclasses.replace(DEFAULT, max_per_tile=64),
    "K=128": dataclasses.replace(DEFAULT, max_per_tile=128),
    "K=256": dataclasses.replace(DEFAULT, max_per_tile=256),
}
QUICK_VARIANTS = ["exact (default)", "exact 16px tiles", "K=256"]


def garden_scene(points: np.ndarray, colors: np.ndarray, count: int, degree: int, seed: int = 0):
  """A 3D-GS-style initialisation of `count` garden points: kNN scales, opacity 0.5, random higher SH."""
  rng = np.random.default_rng(seed)
  idx = rng.choice(points.shape[0], count, replace=False) if count < points.shape[0] else np.arange(points.shape[0])
  g = gaussians_from_points(points[idx], colors[idx] / 255.0, sh_degree=degree, opacity=0.5)
  if degree > 0:  # view-dependent colour, so the degree-3 path has real work to do
    rest = rng.normal(0.0, 0.1, g.sh[:, 1:].shape)
    g = g.replace(sh=g.sh.at[:, 1:].set(jnp.asarray(rest, g.sh.dtype)))
  return g


def garden_camera(data, size: tuple[int, int], dtype=jnp.float32) -> Camera:
  """The first garden camera, its focal length scaled so the image height keeps the native field of view."""
  width, height = size
  k = data["Ks"][0]
  s = height / float(data["height"])
  native = size == (int(data["width"]), int(data["height"]))
  cx = k[0, 2] * s if native else width / 2
  cy = k[1, 2] * s if native else height / 2
  return Camera.from_intrinsics(data["viewmats"][0], k[0, 0] * s, k[1, 1] * s, cx, cy, width, height, dtype=dtype)


def _median_time(fn, arg, repeats: int) -> float:
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(arg))
    times.append(time.perf_counter() - start)
  return float(np.median(times))


def evaluated_pixel_pairs(g, cam, options: RenderOptions, capacity: int) -> int:
  """Pixel-pairs the compositor evaluates: every segment (pairs plus padding) times the tile's pixels."""
  degree = options.sh_degree
  splats = project(g, cam, degree, options.near, options.antialiased)
  grid = binning.tile_grid(cam.width, cam.height, options.tile_size)
  pairs = binning.bin_pairs(splats.means2d, splats.cov2d, splats.depths, splats.opacities, splats.radii,
                            options.tile_size, grid, capacity)
  used = np.asarray(pairs.tile_count)
  if options.max_per_tile is not None:
    used = np.minimum(used, options.max_per_tile)
  segments = int(np.sum(-(-used // options.segment_size)))
  return segments * options.segment_size * options.tile_size**2


def culling_counts(g, cam, options: RenderOptions) -> dict:
  """Pairs left by each culling step (binning.pair_counts_by_rule) for tile sizes 8 and 16."""
  splats = project(g, cam, options.sh_degree, options.near, options.antialiased)
  result = {}
  for tile_size in (8, 16):
    grid = binning.tile_grid(cam.width, cam.height, tile_size)
    counts = binning.pair_counts_by_rule(splats.means2d, splats.cov2d, splats.opacities, splats.radii,
                                         tile_size, grid)
    result[f"tile_{tile_size}"] = {k: int(v) for k, v in counts.items()}
  return result


def float64_reference(g, data, size, options: RenderOptions) -> np.ndarray:
  """The same renderer in float64 (exact mode, the options' tile size): the accuracy yardstick."""
  with jax.enable_x64(True):
    g64 = jax.tree.map(lambda x: jnp.asarray(np.asarray(x), jnp.float64), g)
    cam64 = garden_camera(data, size, dtype=jnp.float64)
    return np.asarray(render(g64, cam64, dataclasses.replace(options, max_per_tile=None)).rgb, np.float64)


def python_reference(g, cam, options: RenderOptions) -> np.ndarray:
  """The independent per-pixel float64 reference of the tests (slow: minutes at 20k points)."""
  sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
  from tests.reference import render_reference
  rgb, _, _, _ = render_reference(g.means, g.log_scales, g.quats, g.opacity_logits, g.sh, cam.world_to_camera,
                                  cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, degree=options.sh_degree,
                                  background=options.background, tile_size=options.tile_size, near=options.near)
  return rgb


def errors(rgb, reference) -> dict:
  err = np.abs(np.asarray(rgb, np.float64) - reference)
  return dict(mean_abs=float(err.mean()), p99_9=float(np.quantile(err, 0.999)), max_abs=float(err.max()))


def measure(g, cam, options: RenderOptions, repeats: int) -> tuple[dict, np.ndarray]:
  out = render(g, cam, options)  # eager: finds the capacity this view needs
  options = render_lib.grow_capacity(options, out.num_pairs)
  forward = jax.jit(lambda g: render(g, cam, options).rgb)
  loss = lambda g: jnp.sum(render(g, cam, options).rgb)
  start = time.perf_counter()
  compiled = jax.jit(jax.value_and_grad(loss)).lower(g).compile()
  compile_s = time.perf_counter() - start
  rgb = forward(g)
  jax.block_until_ready(compiled(g))
  memory = compiled.memory_analysis()
  peak = None if memory is None else int(memory.temp_size_in_bytes + memory.argument_size_in_bytes
                                         + memory.output_size_in_bytes)
  fb = _median_time(compiled, g, repeats)
  evaluated = evaluated_pixel_pairs(g, cam, options, options.pair_capacity)
  result = dict(forward_s=_median_time(forward, g, repeats), forward_backward_s=fb, compile_s=compile_s,
                peak_bytes=peak, pairs=int(out.num_pairs), pair_capacity=options.pair_capacity,
                overflow_tiles=int(out.num_overflow_tiles), evaluated_pixel_pairs=evaluated,
                ns_per_pixel_pair=fb / evaluated * 1e9)
  return result, np.asarray(rgb)


def run(combos, variants, repeats, out_dir: pathlib.Path, python_ref: bool) -> list[dict]:
  """combos: (Gaussian count, size name) pairs to measure."""
  data = np.load(DATA)
  rows, scenes = [], []
  json_path = out_dir / "render_bench.json"
  for count in sorted({c for c, _ in combos}):
    g = garden_scene(data["means3d"], data["colors"], count, 3)
    for size_name in [s for c, s in combos if c == count]:
      cam = garden_camera(data, SIZES[size_name])
      # 3D-GS images depend on the tile size (its tile rects are not pixel-exact): one reference per size.
      references = {ts: float64_reference(g, data, SIZES[size_name], dataclasses.replace(DEFAULT, tile_size=ts))
                    for ts in sorted({VARIANTS[name].tile_size for name in variants})}
      scene = dict(num_gaussians=int(g.num), size=size_name, pairs_by_culling_step=culling_counts(g, cam, DEFAULT))
      print(json.dumps(scene), flush=True)
      scenes.append(scene)
      py_ref = None
      if python_ref and count == 20000 and size_name == "256x166":
        start = time.perf_counter()
        py_ref = python_reference(g, cam, DEFAULT)
        scene["python_reference_s"] = time.perf_counter() - start
        scene["float64_renderer_vs_python_reference"] = errors(references[DEFAULT.tile_size], py_ref)
      for name in variants:
        result, rgb = measure(g, cam, VARIANTS[name], repeats)
        row = dict(num_gaussians=int(g.num), size=size_name, width=cam.width, height=cam.height, sh_degree=3,
                   variant=name, tile_size=VARIANTS[name].tile_size, segment_size=VARIANTS[name].segment_size,
                   max_per_tile=VARIANTS[name].max_per_tile, **result,
                   error_vs_float64=errors(rgb, references[VARIANTS[name].tile_size]))
        if py_ref is not None and VARIANTS[name].tile_size == DEFAULT.tile_size:
          row["error_vs_python_reference"] = errors(rgb, py_ref)
        rows.append(row)
        print(json.dumps(row), flush=True)
        fileio.write_json(json_path, _report(rows, scenes, repeats))  # partial results survive an interruption
  return rows


def _report(rows, scenes, repeats):
  return dict(machine=dict(platform=platform.platform(), devices=[str(d) for d in jax.devices()],
                           jax=jax.__version__, cpus=len(jax.devices("cpu"))),
              timing=f"median of {repeats} runs after one warm-up; compile_s is the forward+backward program",
              error="against the float64 exact render of the same scene (mean abs, 99.9th percentile, max)",
              scenes=scenes, rows=rows)


def plot(rows, path: pathlib.Path):
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  sizes = sorted({r["size"] for r in rows})
  fig, axes = plt.subplots(1, len(sizes), figsize=(5.5 * len(sizes), 4.2), squeeze=False)
  for ax, size in zip(axes[0], sizes):
    for count, marker in zip(sorted({r["num_gaussians"] for r in rows}), "osD^v"):
      sel = [r for r in rows if r["size"] == size and r["num_gaussians"] == count]
      xs = [r["forward_backward_s"] * 1e3 for r in sel]
      ys = [max(r["error_vs_float64"]["p99_9"], 1e-7) for r in sel]
      ax.plot(xs, ys, marker=marker, linestyle="none", label=f"{count // 1000}k points")
      for x, y, r in zip(xs, ys, sel):
        ax.annotate(r["variant"].replace("exact", "ex"), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward+backward median (ms)")
    ax.set_ylabel("p99.9 abs error vs float64 (floor 1e-7)")
    ax.set_title(f"garden, SH degree 3, {size}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
  fileio.save_figure(fig, path)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--counts", default="20000,50000,138766")
  parser.add_argument("--sizes", default=",".join(SIZES))
  parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated names from VARIANTS")
  parser.add_argument("--repeats", type=int, default=5)
  parser.add_argument("--quick", action="store_true",
                      help="20k points at 256x166 and all points at native size, three variants")
  parser.add_argument("--no-python-reference", action="store_true")
  args = parser.parse_args(argv)
  if not DATA.exists():
    print(f"skipped: {DATA} not found (the garden point cloud lives in ../shared/data)")
    return 0
  out = pathlib.Path(args.out)
  combos = [(int(c), s) for c in args.counts.split(",") for s in args.sizes.split(",")]
  variants = args.variants.split(",")
  if args.quick:
    combos, variants = [(20000, "256x166"), (138766, "native")], QUICK_VARIANTS
  rows = run(combos, variants, args.repeats, out, not args.no_python_reference)
  plot(rows, out / "render_bench.png")
  print(f"wrote {out / 'render_bench.json'} and {out / 'render_bench.png'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
