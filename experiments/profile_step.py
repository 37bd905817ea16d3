"""Where a teacher train step spends its time, measured on a benchmark run's latest checkpoint.

  make profile-train                                     # lego, from workdirs/bench/lego/teacher
  make profile-train BENCH_ARGS="--scene=beer --repeats=9"

Loads the newest checkpoint of `make bench-train`'s run for --scene, renders one training view with the
run's options, and times (median of --repeats, each stage jitted on its own): projection, binning,
segment layout, compositing (forward and forward+backward), the whole render (forward and
forward+backward), the photometric loss with its gradient, the Adam update, the whole train step, and
one host-side densification round. Writes train_step_profile_<scene>.json to --out. Run it on a quiet
machine: a second process on the CPU doubles these times.
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.core import checkpoint, fileio
from conceal_jax.core import settings as settings_lib
from conceal_jax.gs import densify, evaluate, losses, optimizer, train
from conceal_jax.splat import binning, composite, projection
from conceal_jax.splat import render as render_lib
from conceal_jax.splat import segments as segments_lib
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat.gaussians import Gaussians
from experiments.bench_train import SCENES, scene_config


def median_ms(fn, *args, repeats: int) -> float:
  """Median wall time of fn(*args) in ms after one warm-up call (which compiles)."""
  jax.block_until_ready(fn(*args))
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - start)
  return 1e3 * float(np.median(times))


def restore_state(config, workdir: pathlib.Path, extent: float):
  latest = checkpoint.load_latest(str(workdir / "checkpoints"))
  if latest is None:
    raise SystemExit(f"no checkpoint in {workdir}/checkpoints: run make bench-train first")
  path, meta, leaves = latest
  tx = optimizer.gaussian_optimizer(config.train.lr, extent, config.train.iterations)
  template = train.create_train_state(Gaussians.empty(config.train.sh_degree), tx, meta["capacity"])
  state = jax.tree.map(jnp.asarray, checkpoint.restore(template, leaves, path))
  return state, meta, tx


def profile(scene_name: str, workdir: pathlib.Path, repeats: int) -> dict:
  config = scene_config(scene_name, None)
  scene = evaluate.load_scene_data(config)
  extent = scene.scene_extent()
  state, meta, tx = restore_state(config, workdir, extent)
  settings = settings_lib.from_section(train.TrainSettings, config.train)
  degree = settings.sh_degree_at(int(meta["step"]))
  options = dataclasses.replace(evaluate.render_options(config, scene.background), sh_degree=degree)
  gaussians = train.masked(state.gaussians, state.alive)
  camera, image = scene.train_cameras[0], jnp.asarray(scene.train_images[0])
  options = render_lib.grow_capacity(options, render_lib.render(gaussians, camera, options).num_pairs)
  times = {}

  project = jax.jit(lambda g: projection.project(g, camera, degree, options.near, options.antialiased))
  times["project_fwd"] = median_ms(project, gaussians, repeats=repeats)
  project_sum = lambda g: sum(jnp.sum(jnp.where(jnp.isfinite(x), x, 0.0)) for x in jax.tree.leaves(
      project(g).replace(radii=None)) if x.dtype.kind == "f")
  times["project_fwd_bwd"] = median_ms(jax.jit(jax.grad(project_sum)), gaussians, repeats=repeats)

  splats = project(gaussians)
  ts, length = options.tile_size, options.segment_size
  grid = binning.tile_grid(camera.width, camera.height, ts)
  bin_fn = jax.jit(lambda s: binning.bin_pairs(s.means2d, s.cov2d, s.depths, s.opacities, s.radii, ts, grid,
                                               options.pair_capacity))
  times["bin_pairs"] = median_ms(bin_fn, splats, repeats=repeats)
  pairs = bin_fn(splats)
  block, slots = render_lib.segment_blocks(options, grid[0] * grid[1])
  layout = jax.jit(lambda p: segments_lib.segment_layout(p, gaussians.num, length, slots, None)[0])
  times["segment_layout"] = median_ms(layout, pairs, repeats=repeats)
  segs = layout(pairs)

  def composited(m, c, o, v):
    values, log_t = composite.composite(m, c, o, v, segs.splats, segs.tiles, segs.first, segs.count, ts,
                                        grid, block)
    return jnp.sum(values**2) + jnp.sum(log_t)
  args = (splats.means2d, splats.conics, splats.opacities, splats.colors)
  times["composite_fwd"] = median_ms(jax.jit(composited), *args, repeats=repeats)
  times["composite_fwd_bwd"] = median_ms(jax.jit(jax.grad(composited, argnums=(0, 1, 2, 3))), *args,
                                         repeats=repeats)

  rendered = lambda g: render_lib.render(g, camera, options).rgb
  loss = lambda g: losses.photometric_loss(rendered(g), image, config.train.ssim_weight)
  times["render_fwd"] = median_ms(jax.jit(rendered), gaussians, repeats=repeats)
  times["render_fwd_bwd"] = median_ms(jax.jit(jax.grad(lambda g: jnp.sum(rendered(g)))), gaussians,
                                      repeats=repeats)
  times["loss_fwd_bwd"] = median_ms(jax.jit(jax.grad(
      lambda x: losses.photometric_loss(x, image, config.train.ssim_weight))), image * 0.9, repeats=repeats)
  times["render_and_loss_fwd_bwd"] = median_ms(jax.jit(jax.grad(loss)), gaussians, repeats=repeats)
  times["adam_update"] = median_ms(jax.jit(tx.update), state.gaussians, state.opt_state, state.gaussians,
                                   repeats=repeats)

  step = train.make_train_step(tx, options, config.train.ssim_weight)
  images, cameras = image[None], camera_lib.stack([camera])
  copy = lambda: jax.tree.map(jnp.copy, state)  # the step donates its state
  step_state = copy()
  step_state, _ = step(step_state, images, cameras, 0)
  step_times = []
  for _ in range(repeats):
    start = time.perf_counter()
    step_state, stats = step(step_state, images, cameras, 0)
    jax.block_until_ready(stats)
    step_times.append(time.perf_counter() - start)
  times["train_step"] = 1e3 * float(np.median(step_times))
  params = densify.DensifyParams(max_gaussians=config.train.densify.max_gaussians)
  start = time.perf_counter()
  jax.block_until_ready(train.densify_state(copy(), extent, params, True, np.random.default_rng(0)))
  times["densify_round_host"] = 1e3 * (time.perf_counter() - start)
  return dict(scene=scene_name, checkpoint_step=int(meta["step"]), num_gaussians=int(state.alive.sum()),
              buffer_capacity=int(state.alive.shape[0]), num_pairs=int(pairs.num_pairs),
              pair_capacity=options.pair_capacity, tile_size=ts, segment_size=length, sh_degree=degree,
              image_size=[camera.width, camera.height], repeats=repeats, device=str(jax.devices()[0]),
              median_ms=times)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scene", default="lego", choices=sorted(SCENES))
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--repeats", type=int, default=7)
  args = parser.parse_args()
  result = profile(args.scene, pathlib.Path(args.workdir) / args.scene / "teacher", args.repeats)
  fileio.write_json(pathlib.Path(args.out) / f"train_step_profile_{args.scene}.json", result)
  for name, ms in result["median_ms"].items():
    print(f"{name:28s} {ms:8.1f} ms")


if __name__ == "__main__":
  main()
