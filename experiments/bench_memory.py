"""Memory per million Gaussians of a render's forward+backward and of a teacher step (issue 42 item 3).

  python -m experiments.bench_memory --out=experiments/results [--counts=250000,500000,1000000] [--size=native]

The scene is bench_render's garden point cloud (kNN scales, opacity 0.5, SH degree 3), thinned to a count below
its 138,766 points or made denser above it (each point copied with a jitter of a third of its neighbour spacing,
so that a denser cloud has smaller splats, as a densified scene does), rendered from the first garden camera.
Each count runs in a fresh process, which reports:

- the pairs the view needs and the pair capacity the render is compiled for;
- XLA's buffer estimate of the jitted forward+backward (value_and_grad of the image's sum): arguments, outputs
  and temporaries, what the device must hold at once; and of a teacher step (gs.train.make_train_step on one
  view, the train state donated, so its aliased buffers count once);
- on a CPU, the measured peak resident memory of compiling and running that forward+backward twice, above the
  process's resident memory before (the scene and the runtime already loaded): Linux's VmHWM after resetting it.

A line fitted to the estimates against the count gives bytes per Gaussian at this view's pairs per Gaussian: the
memory per million Gaussians, and with it the largest scene a device of a given memory renders and trains; a fit
against the count and the pair capacity separates what each costs, for views with more or fewer pairs per
Gaussian. Writes memory_bench.json (`--refit` fits its rows again); skips cleanly without
../shared/data/garden_points.npz.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

import numpy as np

DATA = pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "garden_points.npz"
SIZES = {"256x166": (256, 166), "native": (648, 420)}
COUNTS = (125_000, 250_000, 500_000, 1_000_000)
JITTER = 1 / 3  # of a point's neighbour spacing, for the copies that make the cloud denser


def scene_points(points: np.ndarray, colors: np.ndarray, count: int, seed: int = 0):
  """`count` garden points: a random subset, or every point and jittered copies of random ones."""
  from conceal_jax.gs.init import nearest_neighbour_scale
  rng = np.random.default_rng(seed)
  if count <= points.shape[0]:
    keep = rng.choice(points.shape[0], count, replace=False)
    return points[keep], colors[keep]
  source = rng.choice(points.shape[0], count - points.shape[0])
  spacing = nearest_neighbour_scale(np.asarray(points, np.float64))[source, None]
  copies = points[source] + rng.normal(size=(source.size, 3)) * spacing * JITTER
  return np.concatenate([points, copies]), np.concatenate([colors, colors[source]])


def rss_bytes(field: str) -> int:
  """A /proc/self/status memory field (VmRSS, VmHWM) in bytes."""
  with open("/proc/self/status") as f:
    for line in f:
      if line.startswith(field + ":"):
        return int(line.split()[1]) * 1024
  raise ValueError(f"no {field} in /proc/self/status")


def buffer_bytes(compiled) -> dict | None:
  """XLA's estimate of what a compiled program holds at once: arguments + outputs + temporaries - aliased."""
  memory = compiled.memory_analysis()
  if memory is None:
    return None
  parts = dict(arguments=memory.argument_size_in_bytes, outputs=memory.output_size_in_bytes,
               temporaries=memory.temp_size_in_bytes, aliased=memory.alias_size_in_bytes)
  return dict({k: int(v) for k, v in parts.items()},
              total=int(parts["arguments"] + parts["outputs"] + parts["temporaries"] - parts["aliased"]))


def measure_one(count: int, size_name: str) -> dict:
  """One count's row, measured in this process (a fresh one: see run)."""
  import jax
  import jax.numpy as jnp

  from conceal_jax.configs import default
  from conceal_jax.gs import optimizer, train
  from conceal_jax.gs.init import gaussians_from_points
  from conceal_jax.splat import camera as camera_lib
  from conceal_jax.splat import render as render_lib
  from conceal_jax.splat.render import RenderOptions, render
  from experiments.bench_render import garden_camera

  data = np.load(DATA)
  points, colors = scene_points(data["means3d"], data["colors"] / 255.0, count)
  g = gaussians_from_points(points, colors, sh_degree=3, opacity=0.5)
  rng = np.random.default_rng(1)  # view-dependent colour, as bench_render's scene has
  g = g.replace(sh=g.sh.at[:, 1:].set(jnp.asarray(rng.normal(0.0, 0.1, g.sh[:, 1:].shape), g.sh.dtype)))
  cam = garden_camera(data, SIZES[size_name])
  options = RenderOptions(sh_degree=3, background=(1.0, 1.0, 1.0))
  first = dataclasses.replace(options, pair_capacity=render_lib.initial_capacity(count, options))
  pairs = int(jax.jit(lambda g: render(g, cam, first).num_pairs)(g))
  options = render_lib.grow_capacity(options, pairs)

  before = rss_bytes("VmRSS")
  with open("/proc/self/clear_refs", "w") as f:  # resets VmHWM to the current resident size
    f.write("5")
  loss = lambda g: jnp.sum(render(g, cam, options).rgb)
  start = time.perf_counter()
  compiled = jax.jit(jax.value_and_grad(loss)).lower(g).compile()
  compile_s = time.perf_counter() - start
  jax.block_until_ready(compiled(g))
  start = time.perf_counter()
  jax.block_until_ready(compiled(g))
  forward_backward_s = time.perf_counter() - start
  measured = rss_bytes("VmHWM") - before

  tx = optimizer.gaussian_optimizer(default.get_config().train.lr, 1.0, 30_000)
  state = train.create_train_state(g, tx, capacity=count)
  images = jnp.zeros((1, cam.height, cam.width, 3), jnp.float32)
  step = train.make_train_step(tx, options, 0.2)
  step_memory = buffer_bytes(step.lower(state, images, camera_lib.stack([cam]), np.int32(0)).compile())
  device = jax.devices()[0]
  return dict(num_gaussians=count, size=size_name, width=cam.width, height=cam.height, sh_degree=3, pairs=pairs,
              pair_capacity=options.pair_capacity, render_forward_backward=buffer_bytes(compiled),
              train_step=step_memory,
              measured_peak_rss_above_start_bytes=int(measured) if device.platform == "cpu" else None,
              forward_backward_s=forward_backward_s, compile_s=compile_s,
              device=f"{device.platform}: {device.device_kind}")


def fit(rows: list[dict], key: str) -> dict | None:
  """Least squares of the rows' `key` estimates: total = fixed + per_gaussian * count, and (with 4 rows or more)
  total = fixed + per_gaussian * count + per_pair * pair capacity, the two sizes a render's buffers scale with."""
  usable = [(r["num_gaussians"], r["pair_capacity"], r[key]["total"]) for r in rows if r.get(key)]
  if len(usable) < 2:
    return None
  counts, capacities, totals = (np.asarray(column, np.float64) for column in zip(*usable))
  per_gaussian, fixed = np.polyfit(counts, totals, 1)
  result = dict(fixed_bytes=float(fixed), bytes_per_gaussian=float(per_gaussian),
                gib_per_million_gaussians=float(per_gaussian * 1e6 / 2**30),
                max_relative_residual=float(np.max(np.abs(fixed + per_gaussian * counts - totals) / totals)))
  if len(usable) >= 4:
    design = np.stack([np.ones_like(counts), counts, capacities], axis=1)
    (fixed2, per_gaussian2, per_pair), *_ = np.linalg.lstsq(design, totals, rcond=None)
    result["with_pairs"] = dict(fixed_bytes=float(fixed2), bytes_per_gaussian=float(per_gaussian2),
                                bytes_per_pair_of_capacity=float(per_pair),
                                max_relative_residual=float(np.max(np.abs(design @ [fixed2, per_gaussian2, per_pair]
                                                                          - totals) / totals)))
  return result


def report(rows: list[dict]) -> dict:
  """memory_bench.json: the machine, what was measured, the rows and the fits."""
  import jax
  return dict(machine=dict(platform=platform.platform(), cpus=os.cpu_count(), jax=jax.__version__),
              scene="garden points, made denser above 138,766 by copies jittered by a third of the neighbour "
                    "spacing; SH degree 3; the first garden camera",
              estimate="XLA's memory_analysis of the compiled program: arguments + outputs + temporaries - aliased "
                       "(the train step donates its state)",
              measured="peak resident memory (VmHWM) of compiling and running the forward+backward twice, above the "
                       "resident memory before, in a fresh process per row (CPU only)",
              rows=rows, fit_render_forward_backward=fit(rows, "render_forward_backward"),
              fit_train_step=fit(rows, "train_step"))


def run(counts, size_name: str, out_dir: pathlib.Path) -> dict:
  """Every count in a fresh process (`--one`), the rows and the fits written to memory_bench.json as they come."""
  from conceal_jax.core import fileio
  rows = []
  for count in counts:
    done = subprocess.run([sys.executable, "-m", "experiments.bench_memory", f"--one={count}", f"--size={size_name}"],
                          capture_output=True, text=True, cwd=pathlib.Path(__file__).resolve().parents[1])
    if done.returncode:
      raise RuntimeError(f"count {count} failed:\n{done.stderr[-3000:]}")
    rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print(json.dumps(rows[-1]), flush=True)
    fileio.write_json(out_dir / "memory_bench.json", report(rows))
  return report(rows)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--counts", default=",".join(str(c) for c in COUNTS))
  parser.add_argument("--size", default="native", choices=sorted(SIZES))
  parser.add_argument("--one", type=int, default=0, help="measure this count in this process and print its row")
  parser.add_argument("--refit", action="store_true", help="only fit memory_bench.json's rows again")
  args = parser.parse_args(argv)
  if args.refit:
    from conceal_jax.core import fileio
    path = pathlib.Path(args.out) / "memory_bench.json"
    fileio.write_json(path, report(json.loads(path.read_text())["rows"]))
    return
  if not DATA.exists():
    print(f"bench_memory: skipped, {DATA} not found")
    return
  if args.one:
    print(json.dumps(measure_one(args.one, args.size)))
    return
  written = run([int(c) for c in args.counts.split(",")], args.size, pathlib.Path(args.out))
  print(json.dumps(dict(render=written["fit_render_forward_backward"], train=written["fit_train_step"]), indent=1))


if __name__ == "__main__":
  main()
