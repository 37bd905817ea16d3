"""3D-GS training with the Inria recipe (Kerbl et al. 2023, arXiv:2308.04079, Sec. 5 and 7.1): the
ConcealGS teacher. `--config.mode=train`.

The train state is a `TrainState` pytree over a fixed-capacity buffer of Gaussians with an `alive` mask
(see densify.py); the step is built by `make_train_step`, jitted with the state donated, and compiled
once per (SH degree, capacity). Every random choice is derived from (seed, step), so a run resumed from a
checkpoint continues exactly as if it had not been interrupted. The loop itself is `core.loop.run`.

A step takes `train.views_per_step` views (1, as in 3D-GS, by default): its gradient is the mean of the views'
gradients, computed by the devices of a mesh that split the views (core.parallel), and every view counts once
in the densification statistics, as it does when the views come one per step.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from absl import logging
from flax import struct

from conceal_jax.core import checkpoint, fileio, loop, parallel, settings
from conceal_jax.data import datasets, ply
from conceal_jax.gs import capacity, densify, evaluate, init, losses, metrics, optimizer
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat import gaussians as gaussians_lib
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat import render as render_lib
from conceal_jax.splat.render import RenderOptions, render

TRAIN_FILE = "train.json"
INIT_KINDS = ("auto", "points", "random", "ply")


@dataclasses.dataclass(frozen=True)
class TrainSettings:
  """The `train` section besides the loop's fields: SH schedule (from sh_degree_start, +1 every
  sh_increase_every steps, up to sh_degree), loss weight, periodic test PSNR, views per step."""
  sh_degree: int = 3
  sh_degree_start: int = 0
  sh_increase_every: int = 1000
  ssim_weight: float = 0.2
  eval_every: int = 0
  eval_views: int = 4
  views_per_step: int = 1

  def __post_init__(self):
    if not 0 <= self.sh_degree <= 3:
      raise ValueError(f"train.sh_degree must be in 0..3, got {self.sh_degree}")
    if not 0 <= self.sh_degree_start <= self.sh_degree:
      raise ValueError(f"train.sh_degree_start must be in 0..train.sh_degree, got {self.sh_degree_start}")
    if self.sh_increase_every < 1 or self.eval_every < 0 or self.eval_views < 1 or self.views_per_step < 1:
      raise ValueError("train.sh_increase_every, eval_views and views_per_step must be >= 1, eval_every >= 0")
    if not 0 <= self.ssim_weight <= 1:
      raise ValueError(f"train.ssim_weight must be in [0, 1], got {self.ssim_weight}")

  def sh_degree_at(self, iteration: int) -> int:
    """Active SH degree at 1-based `iteration`: sh_degree_start, +1 every sh_increase_every, up to sh_degree."""
    return min(self.sh_degree, self.sh_degree_start + (iteration - 1) // self.sh_increase_every)


@dataclasses.dataclass(frozen=True)
class DensifySchedule:
  """When density control runs (3D-GS Sec. 5.2): densify every `every` steps in (start, until), reset
  opacities every `opacity_reset_every` steps before `until`."""
  start: int = 500
  until: int = 15_000
  every: int = 100
  opacity_reset_every: int = 3000

  def __post_init__(self):
    if self.every < 1 or self.opacity_reset_every < 1 or self.start < 0:
      raise ValueError("train.densify.every and opacity_reset_every must be >= 1, start >= 0")


@struct.dataclass
class TrainState:
  """step: int32; gaussians: the [capacity] buffer; opt_state: its Adam state; alive: [capacity] bool;
  grad_accum, grad_count, max_radii: [capacity] densification statistics since the last densify."""
  step: jax.Array
  gaussians: Gaussians
  opt_state: Any
  alive: jax.Array
  grad_accum: jax.Array
  grad_count: jax.Array
  max_radii: jax.Array


def validate(config: ml_collections.ConfigDict) -> None:
  """Every value the train job reads, checked before anything runs (ValueError naming the key)."""
  loop_settings(config)
  parallel.check_batch(settings.from_section(TrainSettings, config.train).views_per_step)
  settings.from_section(DensifySchedule, config.train.densify)
  settings.from_section(densify.DensifyParams, config.train.densify)
  snapshot_steps(config)
  optimizer.means_decay_steps(config.train.lr, config.train.iterations)
  evaluate.validate(config)
  if config.init.kind not in INIT_KINDS:
    raise ValueError(f"init.kind must be one of {INIT_KINDS}, got {config.init.kind!r}")
  if config.init.num_random_points < 1 or not config.init.box_half_extent > 0:
    raise ValueError("init.num_random_points and init.box_half_extent must be positive")
  if config.init.kind == "ply" and not os.path.isfile(config.init.ply):
    raise ValueError(f"init.kind='ply' needs init.ply, a 3D-GS .ply file; got {config.init.ply!r}")


def snapshot_steps(config: ml_collections.ConfigDict) -> tuple[int, ...]:
  """config.train.snapshots: steps after which the scene is also saved as point_cloud_<step>.ply; each a
  multiple of train.log_every (where the loop hands the state out) within the run."""
  steps = tuple(int(s) for s in config.train.snapshots)
  bad = [s for s in steps if s < 1 or s > config.train.iterations or s % config.train.log_every]
  if bad:
    raise ValueError(f"train.snapshots {bad}: each must be a multiple of train.log_every "
                     f"({config.train.log_every}) in 1..train.iterations ({config.train.iterations})")
  return steps


def snapshot_name(step: int) -> str:
  return f"point_cloud_{step:06d}.ply"


def check_resumable_snapshots(workdir: str, snapshots) -> None:
  """ValueError when the run in `workdir` has passed a step of `snapshots` (its newest checkpoint is at or after it)
  without that snapshot's file: it was begun with other train.snapshots, and resuming would never write it."""
  reached = checkpoint.list_steps(os.path.join(workdir, loop.CHECKPOINT_DIR))
  missing = [s for s in sorted(snapshots) if reached and s <= reached[-1]
             and not os.path.isfile(os.path.join(workdir, snapshot_name(s)))]
  if missing:
    raise ValueError(f"{workdir}: the run has reached step {reached[-1]} without the snapshots {missing} that "
                     "train.snapshots asks for (it was begun with other snapshots); start it in a new workdir, or "
                     "ask only for snapshots it has or has not reached yet")


def loop_settings(config: ml_collections.ConfigDict) -> loop.LoopSettings:
  return settings.from_section(loop.LoopSettings, config.train)


def initial_gaussians(config: ml_collections.ConfigDict, scene, rng: np.random.Generator) -> Gaussians:
  """init.kind 'points' (SfM / point file), 'random' (uniform in a box), 'auto' (points when the
  dataset has them) or 'ply' (a trained scene, init.ply, to train further: fine-tuning). 'points' on a
  capture without points starts randomly, with a logged note: the capture still trains. Random points
  fill the cube of half extent init.box_half_extent (synthetic scenes), or for an LLFF capture its cameras'
  frustums between their near and far bounds, with splats of a few pixels (gs.init.frustum_start_scales)."""
  kind = config.init.kind
  if kind == "ply":
    try:
      return gaussians_lib.with_sh_degree(ply.load_ply(config.init.ply), config.train.sh_degree)
    except ValueError as error:
      raise ValueError(f"init.ply {config.init.ply}: {error} (train.sh_degree)") from error
  if kind == "points" and scene.points is None:
    logging.warning("init.kind='points' but %s has no point cloud: starting from %d random points, as "
                    "init.kind='random' does", config.data.path, config.init.num_random_points)
  max_scales = None
  if kind == "random" or scene.points is None:
    if (config.data.path != "demo"
        and datasets.choose_format(config.data.path, **evaluate.scene_format(config)).kind == "llff"):
      points, footprints = datasets.llff_frustum_points(config.data.path, config.init.num_random_points, rng)
      colors, max_scales = rng.uniform(0.0, 1.0, points.shape), init.frustum_start_scales(footprints)
    else:
      points, colors = init.random_box_points(rng, config.init.num_random_points, config.init.box_half_extent)
  else:
    points, colors = scene.points, scene.point_colors
    colors = np.full_like(points, 0.5) if colors is None else colors
  return init.gaussians_from_points(points, colors, config.train.sh_degree, max_scales=max_scales)


def pad_to_capacity(live: Gaussians, capacity: int) -> Gaussians:
  """[M, ...] numpy Gaussians -> [capacity, ...] device arrays, zero rows appended."""
  return jax.tree.map(lambda x: jnp.asarray(densify.pad_rows(np.asarray(x), capacity)), live)


def buffer_state(gaussians: Gaussians, count: int, opt_state, step: int) -> TrainState:
  """A train state over the buffer `gaussians` whose first `count` rows are alive; statistics zeroed."""
  capacity = gaussians.num
  return TrainState(step=jnp.asarray(step, jnp.int32), gaussians=gaussians, opt_state=opt_state,
                    alive=jnp.asarray(np.arange(capacity) < count),
                    grad_accum=jnp.zeros(capacity, jnp.float32), grad_count=jnp.zeros(capacity, jnp.int32),
                    max_radii=jnp.zeros(capacity, jnp.int32))


def create_train_state(live: Gaussians, tx: optax.GradientTransformation, capacity: int | None = None) -> TrainState:
  """Step-0 state holding `live` ([M, ...]) in a buffer of `capacity` rows (default: its bucket)."""
  gaussians = pad_to_capacity(live, capacity or densify.capacity_for(live.num))
  return buffer_state(gaussians, live.num, tx.init(gaussians), 0)


def live_gaussians(state: TrainState) -> Gaussians:
  """The alive rows of the buffer as a numpy-backed Gaussians."""
  gaussians, alive = jax.device_get((state.gaussians, state.alive))  # not the optimizer state
  return densify.take(gaussians, np.asarray(alive))


def masked(gaussians: Gaussians, alive: jax.Array) -> Gaussians:
  """Dead buffer rows get NaN centres, which the projection culls with zero gradient."""
  return gaussians.replace(means=jnp.where(alive[:, None], gaussians.means, jnp.nan))


def make_train_step(tx: optax.GradientTransformation, options: RenderOptions, ssim_weight: float,
                    traces: loop.TraceCounter | None = None, mesh=None):
  """Builds step(state, images [V, H, W, 3], cameras (stacked), views) -> (state, stats), jitted with the state
  donated; `views` is one view's index or int32 [B] of them, whose renders are split over the devices of `mesh`
  (core.parallel; None: one device). The update is the mean of the B views' gradients. `options` must carry a
  pair capacity, and a step where a render overflowed it returns the state unchanged (see gs.capacity). It also
  accumulates the densification statistics (3D-GS Sec. 5.2) of every view: the NDC norm of each visible
  Gaussian's 2D-mean gradient of the view's own loss, its view count, and its largest screen radius."""

  def loss_fn(gaussians, offsets, alive, image, camera):
    out = render(masked(gaussians, alive), camera, options, means2d_offset=offsets)
    return losses.photometric_loss(out.rgb, image, ssim_weight), out

  def per_view(shared, view):
    gaussians, alive = shared
    image, camera = view
    offsets = jnp.zeros((alive.shape[0], 2), image.dtype)
    (loss, out), (grads, offset_grads) = jax.value_and_grad(loss_fn, argnums=(0, 1), has_aux=True)(
        gaussians, offsets, alive, image, camera)
    visible = out.radii > 0
    ndc_grads = offset_grads * jnp.array([camera.width / 2, camera.height / 2], image.dtype)
    sums = dict(grads=grads, loss=loss, psnr=metrics.psnr(jnp.clip(out.rgb, 0, 1), image),
                grad_norms=jnp.where(visible, jnp.linalg.norm(ndc_grads, axis=-1), 0.0),
                visible=visible.astype(jnp.int32), overflow=out.num_overflow_tiles,
                overflowed=out.overflowed.astype(jnp.int32))
    return sums, dict(radii=out.radii, num_pairs=out.num_pairs)

  def step(state: TrainState, images, cameras, views):
    views = jnp.atleast_1d(views)
    batch = (images[views], jax.tree.map(lambda x: x[views], cameras))
    sums, each = parallel.map_reduce_over_batch(per_view, (state.gaussians, state.alive), batch, mesh)
    count = views.shape[0]
    grads = jax.tree.map(lambda g: g / count, sums["grads"])
    updates, opt_state = tx.update(grads, state.opt_state, state.gaussians)
    new_state = state.replace(
        step=state.step + 1, gaussians=optax.apply_updates(state.gaussians, updates), opt_state=opt_state,
        grad_accum=state.grad_accum + sums["grad_norms"], grad_count=state.grad_count + sums["visible"],
        max_radii=jnp.maximum(state.max_radii, jnp.max(each["radii"], axis=0)))
    stats = dict(loss=sums["loss"] / count, psnr=sums["psnr"] / count, overflow=sums["overflow"],
                 num_gaussians=jnp.sum(state.alive), num_pairs=jnp.max(each["num_pairs"]))
    return capacity.keep_unless_overflowed(sums["overflowed"] > 0, new_state, state), stats

  if traces is not None:
    step = traces.wrap("train_step", step)
  return jax.jit(step, donate_argnums=0)


def densify_state(state: TrainState, extent: float, params: densify.DensifyParams, prune_large: bool,
                  rng: np.random.Generator) -> TrainState:
  """Clone / split / prune on the host; optimizer moments follow their Gaussians, new ones start at 0."""
  host = jax.device_get(state)
  rows = np.flatnonzero(host.alive)
  mean_grads = host.grad_accum[rows] / np.maximum(host.grad_count[rows], 1)
  live, source = densify.densify_and_prune(densify.take(host.gaussians, rows), mean_grads,
                                           host.max_radii[rows], extent, params, prune_large, rng)
  buffer_source = np.where(source == densify.FRESH, densify.FRESH, rows[np.maximum(source, 0)])
  capacity = densify.capacity_for(live.num, host.alive.shape[0], params.max_gaussians)
  moments = optimizer.adam_moments(host.opt_state)
  gather = lambda tree: jax.tree.map(lambda x: jnp.asarray(densify.gather_rows(x, buffer_source, capacity)), tree)
  opt_state = optimizer.with_adam_moments(host.opt_state, moments._replace(mu=gather(moments.mu),
                                                                           nu=gather(moments.nu)))
  return buffer_state(pad_to_capacity(live, capacity), live.num, jax.tree.map(jnp.asarray, opt_state),
                      int(host.step))


def reset_opacity_state(state: TrainState) -> TrainState:
  """3D-GS opacity reset; the opacity moments restart from zero as in the reference implementation."""
  logits = densify.reset_opacity(np.asarray(state.gaussians.opacity_logits))
  moments = optimizer.adam_moments(state.opt_state)
  zero = lambda tree: tree.replace(opacity_logits=jnp.zeros_like(tree.opacity_logits))
  opt_state = optimizer.with_adam_moments(state.opt_state, moments._replace(mu=zero(moments.mu),
                                                                            nu=zero(moments.nu)))
  return state.replace(gaussians=state.gaussians.replace(opacity_logits=jnp.asarray(logits)), opt_state=opt_state)


def view_order(seed: int, epoch: int, num_views: int) -> np.ndarray:
  """The training views of one epoch, shuffled from (seed, epoch) so a resumed run repeats them."""
  return np.random.default_rng([seed, epoch]).permutation(num_views)


def step_views(seed: int, iteration: int, views_per_step: int, num_views: int) -> np.ndarray:
  """The views of 1-based step `iteration` (int32 [views_per_step]): the next views of the epochs' shuffled
  orders (view_order), a step that ends an epoch taking the rest from the next."""
  positions = (iteration - 1) * views_per_step + np.arange(views_per_step)
  return np.array([view_order(seed, p // num_views, num_views)[p % num_views] for p in positions], np.int32)


def density_control(state: TrainState, iteration: int, schedule: DensifySchedule, params: densify.DensifyParams,
                    extent: float, white_background: bool, seed: int) -> TrainState:
  """The 3D-GS schedule: densify every `every` steps in (start, until); reset opacity every
  `opacity_reset_every` steps (and at `start` on a white background) before `until`."""
  if iteration >= schedule.until:
    return state
  if iteration > schedule.start and iteration % schedule.every == 0:
    rng = np.random.default_rng([seed, iteration])
    state = densify_state(state, extent, params, iteration > schedule.opacity_reset_every, rng)
  if iteration % schedule.opacity_reset_every == 0 or (white_background and iteration == schedule.start):
    state = reset_opacity_state(state)
  return state


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None = None,
                       scene: datasets.SceneData | None = None, score: bool = True) -> dict:
  """Trains on config.data, checkpointing into workdir/checkpoints (resumed if present), then writes
  point_cloud.ply, train.json, and the test metrics (metrics.json, test_renders/).

  max_steps: stop after this many steps (as if killed there), leaving the checkpoint to resume from.
  A run stopped by train.time_limit_min is saved and scored at the step it reached (train.json's
  `iterations`, with `planned_iterations` and `time_limit_reached`); the same call resumes it.
  scene: train on this scene instead of loading config.data (None), e.g. a baseline's containers: the
    training views with a hidden image in them (baselines.containers.container_scene). Its test split is
    the one scored. A resumed run must be given the same scene.
  score: False leaves out the test metrics (and `test` in the result), for a caller that scores the
    scene itself (the baselines, through conceal.evaluate_concealment).
  """
  validate(config)
  t = settings.from_section(TrainSettings, config.train)
  schedule = settings.from_section(DensifySchedule, config.train.densify)
  params = settings.from_section(densify.DensifyParams, config.train.densify)
  scene = evaluate.load_scene_data(config) if scene is None else scene
  extent = scene.scene_extent()
  tx = optimizer.gaussian_optimizer(config.train.lr, extent, config.train.iterations)
  mesh = parallel.batch_mesh(t.views_per_step)
  images = parallel.replicate(jnp.asarray(np.stack(scene.train_images)), mesh)
  cameras = parallel.replicate(camera_lib.stack(scene.train_cameras), mesh)
  base_options = evaluate.render_options(config, scene.background)
  white = tuple(scene.background) == (1.0, 1.0, 1.0)
  snapshots = set(snapshot_steps(config))
  check_resumable_snapshots(workdir, snapshots)
  traces = loop.TraceCounter()
  variants = set()  # (SH degree, buffer capacity, pair capacity): each compiles the step once
  # One jitted step per SH degree and pair capacity; the pair capacity grows when a render needs more. It
  # starts from the checkpoint's, or from a guess for the buffer size at the first step.
  build = lambda degree, options: make_train_step(tx, dataclasses.replace(options, sh_degree=degree),
                                                  t.ssim_weight, traces, mesh)
  steps = capacity.GrowingSteps(build, base_options)

  def step(state, iteration):
    if steps.capacity is None:
      steps.grow(render_lib.initial_capacity(int(state.alive.shape[0]), base_options))
    degree = t.sh_degree_at(iteration)
    views = step_views(config.seed, iteration, t.views_per_step, len(scene.train_images))
    buffer = int(state.alive.shape[0])
    # densification makes the state anew on the host: replicated again (a no-op for a state already placed)
    state, stats = steps(degree, parallel.replicate(state, mesh), images, cameras, parallel.replicate(views, mesh))
    variants.update((degree, buffer, tried) for tried in steps.last_capacities)  # an overflowed try compiled too
    return density_control(state, iteration, schedule, params, extent, white, config.seed), stats

  def after_window(state, iteration):
    if iteration in snapshots:  # e.g. the states of a fine-tuning attack after 1k and 3k steps
      ply.save_ply(os.path.join(workdir, snapshot_name(iteration)), live_gaussians(state))
    if not t.eval_every or iteration % t.eval_every or iteration == config.train.iterations:
      return None
    options = dataclasses.replace(base_options, sh_degree=t.sh_degree_at(iteration))
    placed = parallel.on_one_device((state.gaussians, state.alive), mesh)
    test_psnr = evaluate.mean_psnr(masked(*placed), scene, options, t.eval_views)
    logging.info("step %d: test PSNR %.2f on %d views", iteration, test_psnr, t.eval_views)
    return dict(test_psnr=test_psnr)

  def fresh():
    return create_train_state(initial_gaussians(config, scene, np.random.default_rng(config.seed)), tx)

  def template(meta):
    if meta.get("pair_capacity"):
      steps.grow(meta["pair_capacity"])
    return create_train_state(Gaussians.empty(t.sh_degree), tx, meta["capacity"])

  result = loop.run("train", loop_settings(config), workdir, init_state=fresh, restore_template=template,
                    step=step, after_window=after_window, postfix_keys=("num_gaussians",),
                    checkpoint_meta=lambda state: dict(capacity=int(state.alive.shape[0]),
                                                       pair_capacity=steps.capacity), max_steps=max_steps)
  if not (result.finished or result.timed_out):
    return dict(stopped_at=int(result.state.step))

  gaussians = live_gaussians(result.state)
  ply.save_ply(os.path.join(workdir, evaluate.SCENE_FILE), gaussians)
  reached = int(jax.device_get(result.state.step))
  summary = dict(iterations=reached, planned_iterations=config.train.iterations, time_limit_reached=result.timed_out,
                 resumed_from=result.start, num_gaussians=int(gaussians.num),
                 **result.timing(), compiled_step_variants=sorted(variants), traces=dict(traces.counts),
                 pair_capacity=steps.capacity, capacity_reruns=steps.reruns, capacity_shrinks=steps.shrinks,
                 history=result.history)
  fileio.write_json(os.path.join(workdir, TRAIN_FILE), summary)
  if not score:
    return summary
  scored = evaluate.evaluate_scene(jax.tree.map(jnp.asarray, gaussians), scene,
                                   evaluate.eval_options(config, scene.background), workdir,
                                   config.eval.lpips_net, config.eval.max_views)
  return dict(summary, test=scored["mean"])
