"""Per-parameter Adam of 3D-GS (Kerbl et al. 2023, arXiv:2308.04079, Sec. 5.1 and 7.1): one Adam (eps 1e-15),
one learning rate per field.

Adam is element-wise, so a single `scale_by_adam` over the whole `Gaussians` pytree followed by a
per-field learning rate equals the per-parameter-group Adam of the reference implementation.
"""
from __future__ import annotations

import jax.numpy as jnp
import ml_collections
import optax

from conceal_jax.splat.gaussians import Gaussians

ADAM_EPS = 1e-15


def log_linear_schedule(init: float, final: float, max_steps: int) -> optax.Schedule:
  """lr(t) = exp((1 - t/T) log init + (t/T) log final), held at `final` after T steps (3D-GS means)."""
  log_init, log_final = jnp.log(init), jnp.log(final)

  def schedule(step):
    t = jnp.clip(step / max(int(max_steps), 1), 0.0, 1.0)
    return jnp.exp((1.0 - t) * log_init + t * log_final)
  return schedule


def check_final_ratio(name: str, final_ratio: float) -> None:
  """ValueError naming the config key `name` unless the decay's final ratio is in (0, 1]."""
  if not 0 < final_ratio <= 1:
    raise ValueError(f"{name} must be in (0, 1], got {final_ratio!r}")


def check_update_clip(name: str, update_rms_clip: float) -> None:
  """ValueError naming the config key `name` unless the update clip is >= 0 (0: off)."""
  if not update_rms_clip >= 0:
    raise ValueError(f"{name} must be >= 0 (0: off), got {update_rms_clip!r}")


def decaying_adam(lr: float, final_ratio: float, steps: int, eps: float, name: str = "final_ratio",
                  update_rms_clip: float = 0.0, clip_name: str = "update_rms_clip") -> optax.GradientTransformation:
  """Adam at rate `lr` decaying log-linearly to lr * final_ratio over `steps` (then held); a constant rate,
  with no schedule state, when final_ratio is 1. Late large steps kill an unnormalised conv+ReLU U-Net
  (every unit dead, one constant image out), which a decayed rate avoids; a weight whose gradient vanished
  and returns then steps up to ~3x the rate at a tiny eps. `update_rms_clip` > 0: Adafactor's update clipping
  (Shazeer and Stern 2018, Sec. 6): each tensor's Adam direction is scaled down to this root-mean-square
  before the rate, so a tensor whose gradients all return at once steps at most the rate's worth on average.
  `name`, `clip_name`: the config keys of final_ratio and update_rms_clip, for the error messages."""
  check_final_ratio(name, final_ratio)
  check_update_clip(clip_name, update_rms_clip)
  rate = lr if final_ratio == 1 else log_linear_schedule(lr, lr * final_ratio, steps)
  if not update_rms_clip:
    return optax.adam(rate, eps=eps)
  return optax.chain(optax.scale_by_adam(eps=eps), optax.clip_by_block_rms(update_rms_clip),
                     optax.scale_by_learning_rate(rate))


def means_decay_steps(lr: ml_collections.ConfigDict, run_steps: int) -> int:
  """lr.means_steps, or the run's length `run_steps` where it is 0 (3D-GS decays the position learning
  rate over the whole run: position_lr_max_steps = iterations = 30k)."""
  steps = int(lr.means_steps) or int(run_steps)
  if steps < 1 or lr.means_steps < 0:
    raise ValueError(f"lr.means_steps must be >= 1, or 0 for the run's length; got {lr.means_steps} "
                     f"with a run of {run_steps} steps")
  return steps


def sh_learning_rates(lr: ml_collections.ConfigDict, num_bases: int, dtype=jnp.float32) -> jnp.ndarray:
  """[K] learning rate per SH basis function: lr.sh_dc for the DC term (k = 0), lr.sh_rest for the higher
  bands (3D-GS trains the view-dependent colour 20x slower)."""
  return jnp.full((num_bases,), lr.sh_rest, dtype).at[0].set(lr.sh_dc)


def scale_by_gaussian_learning_rates(lr: ml_collections.ConfigDict, extent: float,
                                     run_steps: int = 0) -> optax.GradientTransformation:
  """Multiplies each `Gaussians` field's update by minus its learning rate.

  Means decay log-linearly from lr.means_init * extent to lr.means_final * extent over
  `means_decay_steps`; SH coefficient 0 (DC) uses lr.sh_dc and the higher bands lr.sh_rest.
  """
  means_lr = log_linear_schedule(lr.means_init * extent, lr.means_final * extent,
                                 means_decay_steps(lr, run_steps))

  def init(params):
    del params
    return optax.ScaleByScheduleState(count=jnp.zeros([], jnp.int32))

  def update(updates: Gaussians, state, params=None):
    del params
    sh_lr = sh_learning_rates(lr, updates.sh.shape[1], updates.sh.dtype)[:, None]
    scaled = Gaussians(means=-means_lr(state.count) * updates.means, log_scales=-lr.scales * updates.log_scales,
                       quats=-lr.quats * updates.quats, opacity_logits=-lr.opacity * updates.opacity_logits,
                       sh=-sh_lr * updates.sh)
    return scaled, optax.ScaleByScheduleState(count=optax.safe_increment(state.count))

  return optax.GradientTransformation(init, update)


def warmup_length(lr: ml_collections.ConfigDict, run_steps: int) -> int:
  """lr.warmup_steps, or lr.warmup_fraction of the run's `run_steps` where that is longer."""
  steps, fraction = int(lr.get("warmup_steps", 0)), float(lr.get("warmup_fraction", 0.0))
  if steps < 0:
    raise ValueError(f"lr.warmup_steps must be >= 0, got {steps}")
  if not 0 <= fraction <= 1:
    raise ValueError(f"lr.warmup_fraction must be in [0, 1], got {fraction}")
  return max(steps, int(fraction * run_steps))


def linear_warmup(steps: int) -> optax.Schedule:
  """Factor min(1, (t + 1) / steps) on the t-th update (t from 0)."""
  return lambda count: jnp.minimum(1.0, (count + 1) / steps)


def gaussian_optimizer(lr: ml_collections.ConfigDict, extent: float, run_steps: int = 0,
                       colours_only: bool = False) -> optax.GradientTransformation:
  """Adam (b1 0.9, b2 0.999, eps 1e-15) with the 3D-GS learning rates of `lr`, scaled by scene extent;
  run_steps: the run's length, over which the means decay when lr.means_steps is 0. With `colours_only`, of base
  colours alone ([F, 3] SH DC terms, at lr.sh_dc): the same updates of them as over whole `Gaussians` whose
  other entries have no gradient (Adam is element-wise).

  A warmup (not in 3D-GS; `warmup_length`: lr.warmup_steps, or lr.warmup_fraction of run_steps where
  longer) ramps every update linearly from 1/warmup to full size. Fresh
  Adam on a converged scene moves every parameter that has a gradient by about its learning rate at once
  (the first moment over the root of the second is +-1), which costs a trained scene several dB in the
  first steps of concealment.
  """
  warmup = warmup_length(lr, run_steps)
  rates = optax.scale(-lr.sh_dc) if colours_only else scale_by_gaussian_learning_rates(lr, extent, run_steps)
  chain = [optax.scale_by_adam(b1=0.9, b2=0.999, eps=ADAM_EPS), rates]
  if warmup:
    chain.append(optax.scale_by_schedule(linear_warmup(warmup)))
  return optax.chain(*chain)


def adam_moments(opt_state) -> optax.ScaleByAdamState:
  """The Adam state of a `gaussian_optimizer` state (its mu and nu are `Gaussians` pytrees)."""
  return opt_state[0]


def with_adam_moments(opt_state, moments: optax.ScaleByAdamState):
  return (moments,) + tuple(opt_state[1:])

