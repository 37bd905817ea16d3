"""Training StegaNeRF (Li et al. 2023, ICCV, Sec. 3) on 3D-GS: the student's SH colour, the decoder and the
classifier trained jointly from the teacher (steganerf.py has the objective), through the shared loop
(core.loop: checkpoints in <workdir>/checkpoints, resume, finiteness check).

The initial renders R_0 are the teacher's renders of the training views, computed once on the device
(conceal.views.build_data). A step draws one training view from (seed, step), so a resumed run continues
exactly. The baseline job (baseline.py) scores the result like every other row.
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
from flax import struct

from conceal_jax.baselines import steganerf
from conceal_jax.conceal import views as views_lib
from conceal_jax.core import fileio, loop, settings as settings_lib
from conceal_jax.data import datasets, ply
from conceal_jax.gs import capacity, metrics
from conceal_jax.splat import render as render_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions

STUDENT_FILE = "student.ply"
NETWORKS_FILE = "steganerf_networks.msgpack"
SUMMARY_FILE = "steganerf.json"


@struct.dataclass
class StegaNerfState:
  """step: int32; sh: the student's SH coefficients [N, K, 3] (its geometry is the teacher's, never trained);
  networks: {'decoder', 'classifier'} params; sh_opt, networks_opt: their optimizer states."""
  step: jax.Array
  sh: jax.Array
  networks: Any
  sh_opt: Any
  networks_opt: Any


def loop_settings(config: ml_collections.ConfigDict, iterations: int) -> loop.LoopSettings:
  """The loop of a run of `iterations` steps with baseline.steganerf's log_every, checkpoint_every and
  progress_bar (ValueError naming a bad one)."""
  d = config.baseline.steganerf
  settings_lib.check_count("baseline.steganerf.log_every", d.log_every)
  settings_lib.check_count("baseline.steganerf.checkpoint_every", d.checkpoint_every, minimum=0)
  return settings_lib.from_section(loop.LoopSettings, d, iterations=iterations)


def make_steganerf_step(settings: steganerf.StegaNerfSettings, options: RenderOptions, sh_tx, networks_tx,
                        traces: loop.TraceCounter | None = None):
  """Builds step(state, data, teacher, view) -> (state, stats), jitted with the state donated: one backward
  pass of steganerf_objective for the SH and both networks, the SH update masked (steganerf.sh_optimizer).
  `options` carry a pair capacity; a step whose renders overflowed it returns the state unchanged."""

  def step(state: StegaNerfState, data, teacher: Gaussians, view):
    (total, aux), (sh_grad, networks_grad) = jax.value_and_grad(
        steganerf.steganerf_objective, argnums=(0, 1), has_aux=True)(state.sh, state.networks, data, teacher, view,
                                                                     settings, options)
    sh_updates, sh_opt = sh_tx.update(sh_grad, state.sh_opt, state.sh)
    networks_updates, networks_opt = networks_tx.update(networks_grad, state.networks_opt, state.networks)
    new_state = state.replace(step=state.step + 1, sh=optax.apply_updates(state.sh, sh_updates), sh_opt=sh_opt,
                              networks=optax.apply_updates(state.networks, networks_updates),
                              networks_opt=networks_opt)
    stats = dict(loss=total, psnr=metrics.psnr(jnp.clip(aux["rgb"], 0, 1), data.teacher[view]),
                 num_pairs=aux["num_pairs"], **{k: aux[k] for k in ("render", "hidden", "clean", "classifier")})
    return capacity.keep_unless_overflowed(aux["overflowed"], new_state, state), stats

  if traces is not None:
    step = traces.wrap("steganerf_step", step)
  return jax.jit(step, donate_argnums=0)


def create_state(sh: jax.Array, networks: dict, sh_tx, networks_tx) -> StegaNerfState:
  return StegaNerfState(step=jnp.zeros((), jnp.int32), sh=sh, networks=networks, sh_opt=sh_tx.init(sh),
                        networks_opt=networks_tx.init(networks))


def train_steganerf(config: ml_collections.ConfigDict, workdir: str, iterations: int, teacher: Gaussians,
                    hidden: np.ndarray, scene: datasets.SceneData, check_camera: Camera, options: RenderOptions,
                    max_steps: int | None = None) -> dict:
  """Trains `iterations` steps from `teacher` (max_steps: stop there, as if killed, leaving the checkpoint to
  resume from). Returns dict(stopped_at=step) when stopped; else writes student.ply,
  steganerf_networks.msgpack and steganerf.json (settings, timing, capacity, history) into workdir and
  returns dict(gaussians: the student, reveal_fn, student: its .ply, iterations, num_gaussians, wall_time_s,
  median_step_s, resumed_from, steganerf: the summary without its history)."""
  s = steganerf.settings_from_config(config)
  data = views_lib.build_data(scene.train_images, teacher, options, list(scene.train_cameras), [check_camera], [hidden],
                              s.hidden_size)
  sh_tx = steganerf.sh_optimizer(config.conceal.lr, s.mask_at, s.sh_adam_eps)
  networks_tx = steganerf.networks_optimizer(s, iterations)
  traces = loop.TraceCounter()
  steps = capacity.GrowingSteps(lambda _, opts: make_steganerf_step(s, opts, sh_tx, networks_tx, traces), options)
  steps.grow(render_lib.initial_capacity(teacher.num, options))
  num_views = len(scene.train_cameras)

  def fresh():
    # the step donates the state's buffers; the teacher's own SH must survive as R_0's scene
    sh = jnp.array(teacher.sh, copy=True)
    return create_state(sh, steganerf.init_networks(jax.random.key(config.seed), s), sh_tx, networks_tx)

  def step(state, iteration):
    view = int(np.random.default_rng([config.seed, iteration]).integers(num_views))
    return steps(None, state, data, teacher, view)

  result = loop.run("steganerf", loop_settings(config, iterations), workdir, init_state=fresh,
                    restore_template=lambda _: fresh(), step=step, postfix_keys=("hidden",), max_steps=max_steps)
  if not result.finished:
    return dict(stopped_at=int(result.state.step))

  student = teacher.replace(sh=result.state.sh)
  student_path = os.path.join(workdir, STUDENT_FILE)
  ply.save_ply(student_path, jax.device_get(student))
  steganerf.save_networks(os.path.join(workdir, NETWORKS_FILE), result.state.networks, s)
  summary = dict(settings=dataclasses.asdict(s), iterations=iterations, resumed_from=result.start,
                 **result.timing(), traces=dict(traces.counts), pair_capacity=steps.capacity,
                 capacity_reruns=steps.reruns, capacity_shrinks=steps.shrinks, student=student_path,
                 networks=os.path.join(workdir, NETWORKS_FILE))
  fileio.write_json(os.path.join(workdir, SUMMARY_FILE), dict(summary, history=result.history))
  return dict(gaussians=student, reveal_fn=steganerf.steganerf_reveal(result.state.networks, s), student=student_path,
              iterations=iterations, num_gaussians=int(teacher.num), wall_time_s=summary["wall_time_s"],
              median_step_s=summary["median_step_s"], resumed_from=result.start, steganerf=summary)
