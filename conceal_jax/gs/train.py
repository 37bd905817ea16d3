"""3D-GS training with the Inria recipe (REFERENCE s.5): the ConcealGS teacher. `--config.mode=train`.

The train state is a plain pytree (dict) over a fixed-capacity buffer of Gaussians with an `alive`
mask (see densify.py); the step is built by `make_train_step`, jitted with the state donated, and
compiled once per (SH degree, capacity). Every random choice is derived from (seed, step), so a run
resumed from a checkpoint continues exactly as if it had not been interrupted.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import time

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from absl import logging
from tqdm import tqdm

from conceal_jax.splat import camera as camera_lib
from conceal_jax.core import checkpoint, fileio
from conceal_jax.data import ply
from conceal_jax.gs import densify, evaluate, init, losses, metrics, optimizer
from conceal_jax.gs import render_views
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render

TRAIN_FILE = "train.json"


def initial_gaussians(config: ml_collections.ConfigDict, scene, rng: np.random.Generator) -> Gaussians:
  """init.kind 'points' (SfM / point file), 'random' (uniform in a box, synthetic scenes) or 'auto'
  (points when the dataset has them)."""
  kind = config.init.kind
  if kind not in ("auto", "points", "random"):
    raise ValueError(f"init.kind must be 'auto', 'points' or 'random', got {kind!r}")
  if kind == "points" and scene.points is None:
    raise ValueError("init.kind='points' but the dataset has no point cloud")
  if kind == "random" or (kind == "auto" and scene.points is None):
    if config.init.num_random_points < 1 or not config.init.box_half_extent > 0:
      raise ValueError("init.num_random_points and init.box_half_extent must be positive")
    points, colors = init.random_box_points(rng, config.init.num_random_points, config.init.box_half_extent)
  else:
    points, colors = scene.points, scene.point_colors
    colors = np.full_like(points, 0.5) if colors is None else colors
  return init.gaussians_from_points(points, colors, config.train.sh_degree)


def sh_degree_at(config: ml_collections.ConfigDict, iteration: int) -> int:
  """Active SH degree at 1-based `iteration`: +1 every sh_increase_every, up to train.sh_degree."""
  return min(config.train.sh_degree, (iteration - 1) // config.train.sh_increase_every)


def densify_params(config: ml_collections.ConfigDict) -> densify.DensifyParams:
  fields = {f.name for f in dataclasses.fields(densify.DensifyParams)}
  return densify.DensifyParams(**{k: v for k, v in config.train.densify.items() if k in fields})


def pad_to_capacity(live: Gaussians, capacity: int) -> Gaussians:
  """[M, ...] numpy Gaussians -> [capacity, ...] device arrays, zero rows appended."""
  return jax.tree.map(lambda x: jnp.asarray(densify.pad_rows(np.asarray(x), capacity)), live)


def buffer_state(gaussians: Gaussians, count: int, opt_state, step: int) -> dict:
  """A train state over the buffer `gaussians` whose first `count` rows are alive; statistics zeroed."""
  capacity = gaussians.num
  return dict(step=jnp.asarray(step, jnp.int32), gaussians=gaussians, opt_state=opt_state,
              alive=jnp.asarray(np.arange(capacity) < count),
              grad_accum=jnp.zeros(capacity, jnp.float32), grad_count=jnp.zeros(capacity, jnp.int32),
              max_radii=jnp.zeros(capacity, jnp.int32))


def create_train_state(live: Gaussians, tx: optax.GradientTransformation, capacity: int | None = None) -> dict:
  """Step-0 state holding `live` ([M, ...]) in a buffer of `capacity` rows (default: its bucket)."""
  gaussians = pad_to_capacity(live, capacity or densify.capacity_for(live.num))
  return buffer_state(gaussians, live.num, tx.init(gaussians), 0)


def live_gaussians(state: dict) -> Gaussians:
  """The alive rows of the buffer as a numpy-backed Gaussians."""
  gaussians, alive = jax.device_get((state["gaussians"], state["alive"]))  # not the optimizer state
  return densify.take(gaussians, np.asarray(alive))


def masked(gaussians: Gaussians, alive: jax.Array) -> Gaussians:
  """Dead buffer rows get NaN centres, which the projection culls with zero gradient."""
  return gaussians.replace(means=jnp.where(alive[:, None], gaussians.means, jnp.nan))


def make_train_step(tx: optax.GradientTransformation, options: RenderOptions, ssim_weight: float):
  """Builds step(state, images [V, H, W, 3], cameras (stacked), view) -> (state, metrics), jitted with the
  state donated. It also accumulates the densification statistics: the NDC norm of each visible
  Gaussian's 2D-mean gradient, its view count, and its largest screen radius."""

  def loss_fn(gaussians, offsets, alive, image, camera):
    out = render(masked(gaussians, alive), camera, options, means2d_offset=offsets)
    return losses.photometric_loss(out.rgb, image, ssim_weight), out

  @functools.partial(jax.jit, donate_argnums=0)
  def step(state, images, cameras, view):
    image = images[view]
    camera = jax.tree.map(lambda x: x[view], cameras)
    offsets = jnp.zeros((state["alive"].shape[0], 2), image.dtype)
    (loss, out), (grads, offset_grads) = jax.value_and_grad(loss_fn, argnums=(0, 1), has_aux=True)(
        state["gaussians"], offsets, state["alive"], image, camera)
    updates, opt_state = tx.update(grads, state["opt_state"], state["gaussians"])
    visible = out.radii > 0
    ndc_grads = offset_grads * jnp.array([camera.width / 2, camera.height / 2], image.dtype)
    new_state = dict(
        step=state["step"] + 1, gaussians=optax.apply_updates(state["gaussians"], updates), opt_state=opt_state,
        alive=state["alive"],
        grad_accum=state["grad_accum"] + jnp.where(visible, jnp.linalg.norm(ndc_grads, axis=-1), 0.0),
        grad_count=state["grad_count"] + visible.astype(jnp.int32),
        max_radii=jnp.where(visible, jnp.maximum(state["max_radii"], out.radii), state["max_radii"]))
    stats = dict(loss=loss, psnr=metrics.psnr(jnp.clip(out.rgb, 0, 1), image), overflow=out.num_overflow_tiles)
    return new_state, stats

  return step


def densify_state(state: dict, extent: float, params: densify.DensifyParams, prune_large: bool,
                  rng: np.random.Generator) -> dict:
  """Clone / split / prune on the host; optimizer moments follow their Gaussians, new ones start at 0."""
  host = jax.device_get(state)
  rows = np.flatnonzero(host["alive"])
  mean_grads = host["grad_accum"][rows] / np.maximum(host["grad_count"][rows], 1)
  live, source = densify.densify_and_prune(densify.take(host["gaussians"], rows), mean_grads,
                                           host["max_radii"][rows], extent, params, prune_large, rng)
  buffer_source = np.where(source == densify.FRESH, densify.FRESH, rows[np.maximum(source, 0)])
  capacity = densify.capacity_for(live.num, host["alive"].shape[0])
  moments = optimizer.adam_moments(host["opt_state"])
  gather = lambda tree: jax.tree.map(lambda x: jnp.asarray(densify.gather_rows(x, buffer_source, capacity)), tree)
  opt_state = optimizer.with_adam_moments(host["opt_state"], moments._replace(mu=gather(moments.mu),
                                                                              nu=gather(moments.nu)))
  return buffer_state(pad_to_capacity(live, capacity), live.num, jax.tree.map(jnp.asarray, opt_state),
                      int(host["step"]))


def reset_opacity_state(state: dict) -> dict:
  """3D-GS opacity reset; the opacity moments restart from zero as in the reference implementation."""
  logits = densify.reset_opacity(np.asarray(state["gaussians"].opacity_logits))
  moments = optimizer.adam_moments(state["opt_state"])
  zero = lambda tree: tree.replace(opacity_logits=jnp.zeros_like(tree.opacity_logits))
  opt_state = optimizer.with_adam_moments(state["opt_state"], moments._replace(mu=zero(moments.mu),
                                                                               nu=zero(moments.nu)))
  return dict(state, gaussians=state["gaussians"].replace(opacity_logits=jnp.asarray(logits)), opt_state=opt_state)


def view_order(seed: int, epoch: int, num_views: int) -> np.ndarray:
  """The training views of one epoch, shuffled from (seed, epoch) so a resumed run repeats them."""
  return np.random.default_rng([seed, epoch]).permutation(num_views)


def validate(config: ml_collections.ConfigDict) -> None:
  t = config.train
  if t.iterations < 1 or t.sh_increase_every < 1 or t.densify.every < 1 or t.checkpoint_every < 0:
    raise ValueError("train.iterations, sh_increase_every and densify.every must be >= 1, "
                     "checkpoint_every >= 0")
  if not 0 <= t.sh_degree <= 3:
    raise ValueError(f"train.sh_degree must be in 0..3, got {t.sh_degree}")
  if not 0 <= t.ssim_weight <= 1:
    raise ValueError(f"train.ssim_weight must be in [0, 1], got {t.ssim_weight}")


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None = None) -> dict:
  """Trains on config.data, checkpointing into workdir/checkpoints (resumed if present), then writes
  point_cloud.ply, train.json, and the test metrics (metrics.json, test_renders/).

  max_steps: stop after this many steps (as if killed there), leaving the checkpoint to resume from.
  """
  validate(config)
  t = config.train
  scene = evaluate.load_scene_data(config)
  extent = scene.scene_extent()
  tx = optimizer.gaussian_optimizer(t.lr, extent)
  images = jnp.asarray(np.stack(scene.train_images))
  cameras = camera_lib.stack(scene.train_cameras)
  base_options = dataclasses.replace(render_views.render_options(config), background=tuple(scene.background))
  steps = {}  # one compiled step per SH degree

  ckpt_dir = os.path.join(workdir, "checkpoints")
  state, history, step_times = _restore_or_create(config, scene, tx, ckpt_dir)
  start = int(state["step"])
  end = t.iterations if max_steps is None else min(t.iterations, max_steps)
  params = densify_params(config)
  variants = set()
  bar = tqdm(total=t.iterations, initial=start, desc="train", dynamic_ncols=True, disable=not t.progress_bar)
  for step in range(start, end):
    iteration = step + 1  # 1-based, as the reference schedule is written
    degree = sh_degree_at(config, iteration)
    if degree not in steps:
      steps[degree] = make_train_step(tx, dataclasses.replace(base_options, sh_degree=degree), t.ssim_weight)
    view = view_order(config.seed, step // len(scene.train_images), len(scene.train_images))[
        step % len(scene.train_images)]
    started = time.perf_counter()
    variants.add((degree, int(state["alive"].shape[0])))  # each (SH degree, capacity) compiles once
    state, stats = steps[degree](state, images, cameras, view)
    state = _density_control(config, state, iteration, extent, params, scene.background)
    if iteration % t.log_every == 0 or iteration == end:
      stats = jax.device_get(stats)
      if not np.isfinite(stats["loss"]):
        raise FloatingPointError(f"training diverged at step {iteration}: loss {stats['loss']}")
      history.append(dict(step=iteration, loss=float(stats["loss"]), psnr=float(stats["psnr"]),
                          overflow_tiles=int(stats["overflow"]), num_gaussians=int(np.sum(state["alive"]))))
      bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}", n=history[-1]["num_gaussians"])
    else:
      jax.block_until_ready(state["step"])
    step_times.append(time.perf_counter() - started)
    bar.update(1)
    if t.eval_every and iteration % t.eval_every == 0 and iteration < t.iterations:
      test_psnr = _quick_test_psnr(state, scene, dataclasses.replace(base_options, sh_degree=degree), t.eval_views)
      history.append(dict(step=iteration, test_psnr=test_psnr))
      logging.info("step %d: test PSNR %.2f on %d views", iteration, test_psnr, t.eval_views)
    if t.checkpoint_every and (iteration % t.checkpoint_every == 0 or iteration == end):
      checkpoint.save(ckpt_dir, iteration, state, dict(capacity=int(state["alive"].shape[0]), history=history,
                                                       step_times=step_times))
  bar.close()
  if end < t.iterations:
    return dict(stopped_at=end)

  gaussians = live_gaussians(state)
  ply.save_ply(os.path.join(workdir, evaluate.SCENE_FILE), gaussians)
  summary = dict(iterations=t.iterations, resumed_from=start, num_gaussians=int(gaussians.num),
                 timed_steps=len(step_times), wall_time_s=float(np.sum(step_times)),
                 median_step_s=float(np.median(step_times)) if step_times else None,
                 compiled_step_variants=sorted(variants), history=history)
  fileio.write_json(os.path.join(workdir, TRAIN_FILE), summary)
  result = evaluate.evaluate_scene(jax.tree.map(jnp.asarray, gaussians), scene,
                                   evaluate.eval_options(config, scene.background), workdir,
                                   config.eval.lpips_net, config.eval.max_views)
  return dict(summary, test=result["mean"])


def _density_control(config, state, iteration, extent, params, background):
  """The 3D-GS schedule: densify every `every` steps in (from, until); reset opacity every
  `opacity_reset_every` steps (and at `from` on a white background) before `until`."""
  d = config.train.densify
  if iteration >= d.until:
    return state
  if iteration > d.start and iteration % d.every == 0:
    rng = np.random.default_rng([config.seed, iteration])
    state = densify_state(state, extent, params, iteration > d.opacity_reset_every, rng)
  if iteration % d.opacity_reset_every == 0 or (tuple(background) == (1.0, 1.0, 1.0) and iteration == d.start):
    state = reset_opacity_state(state)
  return state


def _quick_test_psnr(state, scene, options, max_views) -> float:
  cameras, targets, _ = evaluate.held_out_views(scene, max_views)
  rendered = evaluate.render_images(masked(state["gaussians"], state["alive"]), cameras, options)
  return float(np.mean([metrics.psnr(np.clip(r, 0, 1), t) for r, t in zip(rendered, targets)]))


def _restore_or_create(config, scene, tx, ckpt_dir) -> tuple[dict, list, list]:
  """(state, history, step times so far): a resumed run reports the time of all its steps."""
  latest = checkpoint.load_latest(ckpt_dir)
  if latest is None:
    live = initial_gaussians(config, scene, np.random.default_rng(config.seed))
    return create_train_state(live, tx), [], []
  path, meta, leaves = latest
  template = create_train_state(Gaussians.empty(config.train.sh_degree), tx, meta["capacity"])
  logging.info("resuming from %s", path)
  state = jax.tree.map(jnp.asarray, checkpoint.restore(template, leaves, path))
  return state, meta["history"], meta.get("step_times", [])
