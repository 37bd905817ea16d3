"""Training DeepStega's networks (Baluja 2017, NeurIPS, "Hiding Images in Plain Sight: Deep Steganography",
Sec. 2) on natural-image crops, and their own hide / reveal quality on held-out images.

Covers and secrets are random crops of `crop_size` (the decoder size, 64 in ConcealGS) from a pool of
squares of POOL_SCALE * crop_size: the scikit-image sample photographs (conceal.hidden.SAMPLE_NAMES) and
the scene's training views. The hidden image itself and HELD_OUT_SAMPLES are kept out of training, and
the held-out report hides those samples in crops of the scene's test views, so a DeepStega failure after
3D-GS training is the scene's, not the networks'. Batches and container noise are drawn from (seed, step),
so a run resumed from its checkpoint (core.loop) continues exactly.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from conceal_jax.baselines import containers as containers_lib
from conceal_jax.baselines import deepstega
from conceal_jax.conceal import hidden as hidden_lib
from conceal_jax.core import loop, settings as settings_lib
from conceal_jax.gs import metrics

HELD_OUT_SAMPLES = ("chelsea", "coffee", "rocket")
POOL_SCALE = 2  # pool squares are this many crops wide: a crop shows part of an image, as a view does


@dataclasses.dataclass(frozen=True)
class StegaTrainSettings:
  """The baseline.deepstega fields of training besides the loop's and the architecture's: loss weight beta,
  container noise (standard deviation, in [0, 1] image units), crop size, batch size, Adam learning rate,
  and the number of held-out (cover, secret) pairs the report scores."""
  beta: float = 1.0
  noise_std: float = 0.01
  crop_size: int = 64
  batch_size: int = 8
  learning_rate: float = 1e-3
  held_out_pairs: int = 16

  def __post_init__(self):
    for name in ("crop_size", "batch_size", "held_out_pairs"):
      settings_lib.check_count(f"baseline.deepstega.{name}", getattr(self, name))
    for name in ("beta", "learning_rate"):
      if not getattr(self, name) > 0:
        raise ValueError(f"baseline.deepstega.{name} must be positive, got {getattr(self, name)!r}")
    if not 0 <= self.noise_std < 1:
      raise ValueError(f"baseline.deepstega.noise_std must be in [0, 1), got {self.noise_std!r}")


@struct.dataclass
class StegaState:
  """step: int32; params: {'prep', 'hide', 'reveal'}; opt_state: their Adam state."""
  step: jax.Array
  params: Any
  opt_state: Any


def sample_split(hidden: str) -> tuple[list[str], list[str]]:
  """(training, held-out) scikit-image sample names; the hidden image is in neither."""
  names = [n for n in hidden_lib.SAMPLE_NAMES if n != hidden]
  return [n for n in names if n not in HELD_OUT_SAMPLES], [n for n in names if n in HELD_OUT_SAMPLES]


def image_pool(images: Sequence[np.ndarray], names: Sequence[str], side: int) -> np.ndarray:
  """[N, side, side, 3]: `images` ([H, W, 3] in [0, 1]) and the samples `names`, each as its centred square
  resized to side x side (conceal.hidden's conversion)."""
  squares = [hidden_lib.resize_square(np.asarray(image, np.float32), side) for image in images]
  squares += [hidden_lib.load_hidden_image(name, side) for name in names]
  return np.stack(squares)


def random_crops(pool: np.ndarray, count: int, crop: int, rng: np.random.Generator) -> np.ndarray:
  """[count, crop, crop, 3] crops of random images of `pool` [N, P, P, 3] at random places."""
  picks = rng.integers(len(pool), size=count)
  corners = rng.integers(pool.shape[1] - crop + 1, size=(count, 2))
  return np.stack([pool[i, y:y + crop, x:x + crop] for i, (y, x) in zip(picks, corners)])


def make_stega_step(arch: deepstega.Architecture, tx: optax.GradientTransformation, beta: float,
                    noise_std: float, seed: int, traces: loop.TraceCounter | None = None):
  """Builds step(state, covers, secrets [B, H, W, 3]) -> (state, stats), jitted with the state donated; the
  container noise is drawn from (seed, step)."""

  def step(state: StegaState, covers, secrets):
    noise = noise_std * jax.random.normal(jax.random.fold_in(jax.random.key(seed), state.step), covers.shape)
    (loss, aux), grads = jax.value_and_grad(deepstega.stega_loss, has_aux=True)(
        state.params, arch, covers, secrets, noise, beta)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    stats = dict(loss=loss, psnr=-10.0 * jnp.log10(aux["secret_mse"]), cover_psnr=-10.0 * jnp.log10(aux["cover_mse"]))
    return state.replace(step=state.step + 1, params=optax.apply_updates(state.params, updates),
                         opt_state=opt_state), stats

  if traces is not None:
    step = traces.wrap("stega_step", step)
  return jax.jit(step, donate_argnums=0)


def hide_and_reveal_quality(params: dict, arch: deepstega.Architecture, covers, secrets) -> dict:
  """Mean PSNR / SSIM of the 8-bit containers to their covers and of the secrets revealed from them to the
  secrets, over pairs [B, H, W, 3]: the networks' own quality, with no 3D-GS in between."""
  covers, secrets = jnp.asarray(covers, jnp.float32), jnp.asarray(secrets, jnp.float32)
  containers = containers_lib.from_levels(containers_lib.to_levels(deepstega.hide(params, arch, covers, secrets)))
  revealed = jnp.clip(deepstega.reveal_secret(params, arch, containers), 0.0, 1.0)
  mean = lambda scores: float(np.mean(np.asarray(scores)))
  return dict(cover_psnr=mean(jax.vmap(metrics.psnr)(containers, covers)),
              cover_ssim=mean(metrics.batched_ssim(containers, covers)),
              secret_psnr=mean(jax.vmap(metrics.psnr)(revealed, secrets)),
              secret_ssim=mean(metrics.batched_ssim(revealed, secrets)), pairs=int(covers.shape[0]))


def train_networks(arch: deepstega.Architecture, settings: StegaTrainSettings, loop_settings: loop.LoopSettings,
                   workdir: str, train_views: Sequence[np.ndarray], hidden: str, seed: int) -> tuple[dict, dict]:
  """Trains the networks through core.loop in workdir (checkpointed, resumable) on crops of the training
  samples of sample_split(hidden) and of `train_views` ([H, W, 3] each); returns (params, report of the
  run: timing, samples used, history)."""
  s = settings
  train_names, held_out_names = sample_split(hidden)
  pool = image_pool(train_views, train_names, POOL_SCALE * s.crop_size)
  tx = optax.adam(s.learning_rate)
  traces = loop.TraceCounter()
  step_fn = make_stega_step(arch, tx, s.beta, s.noise_std, seed, traces)

  def fresh():
    params = deepstega.init_networks(jax.random.key(seed), arch)
    return StegaState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params))

  def step(state, iteration):
    rng = np.random.default_rng([seed, iteration])
    covers, secrets = (random_crops(pool, s.batch_size, s.crop_size, rng) for _ in range(2))
    return step_fn(state, jnp.asarray(covers), jnp.asarray(secrets))

  result = loop.run("deepstega", loop_settings, workdir, init_state=fresh, restore_template=lambda _: fresh(),
                    step=step, postfix_keys=("cover_psnr",))
  report = dict(iterations=loop_settings.iterations, resumed_from=result.start, **result.timing(),
                traces=dict(traces.counts), training_samples=train_names, held_out_samples=held_out_names,
                history=result.history)
  return result.state.params, report


def held_out_quality(params: dict, arch: deepstega.Architecture, settings: StegaTrainSettings,
                     train_views: Sequence[np.ndarray], test_views: Sequence[np.ndarray], hidden: str,
                     seed: int) -> dict:
  """The networks' own quality (hide_and_reveal_quality) on settings.held_out_pairs crops: secrets from
  the held-out samples of sample_split(hidden), covers from `test_views` (the training views where there
  are none), drawn from `seed`."""
  s = settings
  train_names, held_out_names = sample_split(hidden)
  side = POOL_SCALE * s.crop_size
  rng = np.random.default_rng([seed, 1 << 20])  # apart from the training batches' (seed, step) streams
  covers = random_crops(image_pool(list(test_views) or list(train_views), [], side), s.held_out_pairs,
                        s.crop_size, rng)
  secrets = random_crops(image_pool([], held_out_names or train_names, side), s.held_out_pairs, s.crop_size, rng)
  return dict(hide_and_reveal_quality(params, arch, covers, secrets), crop_size=s.crop_size,
              secrets=held_out_names or train_names, covers="test views" if len(test_views) else "training views")
