"""The scene as the check render sees it during training: the model attacks a shared scene meets, drawn by augment.

An option beyond ConcealGS (arXiv:2501.03605), as augment.py's image distortions are: the model attacks of
robust/model_attacks.py, each Gaussian dropped with a drawn probability, every stored parameter moved by relative
normal noise (model_attacks.parameter_noise's), a drawn share of the smallest Gaussians dropped (`kept_by_size`, a
size pruning); on a share of the steps the base colours and opacities on the 8-bit grids of .spz and the higher SH
bands on .compressed.ply's (`quantize_8bit`, rounding at a point drawn anew, since the formats round to the nearest
or down; the gradient passes straight through), every opacity at most densify.RESET_CEILING (3D-GS's opacity
reset), or the carrier film's neighbouring splats merged as a converter's decimation merges them
(decimate.merge_film). A render that reads some rows alone (subsets.py) perturbs those alone, with the same values.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from conceal_jax.conceal import decimate, subsets
from conceal_jax.conceal.augment import Augmentation
from conceal_jax.gs import densify
from conceal_jax.splat.gaussians import opacity_logit

# A dropped Gaussian's opacity logit (the one a merged-away splat gets too).
DROPPED_LOGIT = decimate.DROPPED_LOGIT
# .spz's 8-bit base colour: byte = round(255 (0.15 dc + 0.5)), the SH DC term scaled by this before the offset.
SPZ_COLOR_SCALE = 0.15
# .compressed.ply's higher SH bands: byte = floor(256 (v + 4) / 8), read back as the centre of its cell of this width.
REST_CELL = 8.0 / 256.0

# Gaussians fields that parameter noise moves: all of them (robust.model_attacks.FIELDS).
MODEL_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def quantize_8bit(gaussians, rounding=0.5):
  """Gaussians with their base colours (SH DC) and opacities on .spz's 8-bit grids (SPZ_COLOR_SCALE; opacity in
  steps of 1/255), each value taken to the step below value + `rounding` steps (0.5: the nearest, as .spz; 0: the
  one below; traced), and their higher SH bands on .compressed.ply's 8-bit grid (REST_CELL-wide cells of
  [-4, 4), each read back at its centre, so a band of zeros comes back at +-REST_CELL / 2: the cell below
  value + `rounding` - 1/2 cells; 0.5 is the converter's floor); the rounding passed straight through by the
  gradient."""
  straight_through = lambda x, rounded: x + jax.lax.stop_gradient(rounded - x)
  dc = gaussians.sh[:, 0]
  byte = jnp.clip(jnp.floor(255.0 * (SPZ_COLOR_SCALE * dc + 0.5) + rounding), 0.0, 255.0)
  dc_8bit = (byte / 255.0 - 0.5) / SPZ_COLOR_SCALE
  rest = gaussians.sh[:, 1:]
  cell = jnp.clip(jnp.floor(rest / REST_CELL + rounding - 0.5), -128.0, 127.0)
  sh_8bit = jnp.concatenate([dc_8bit[:, None], (cell + 0.5) * REST_CELL], axis=1)
  opacity = jnp.clip(jnp.floor(255.0 * jax.nn.sigmoid(gaussians.opacity_logits) + rounding), 0.5, 254.5) / 255.0
  return gaussians.replace(sh=straight_through(gaussians.sh, sh_8bit),
                           opacity_logits=straight_through(gaussians.opacity_logits, opacity_logit(opacity)))


def kept_by_size(log_scales: jax.Array, share) -> jax.Array:
  """[N] bool: False for the floor(share N) of N Gaussians of smallest volume (the sum of their log scales [N, 3],
  robust.model_attacks.prune_smallest's order, ties to the lower index), as a size pruning leaves them. `share` in
  [0, 1) may be traced; 0 keeps all."""
  volume = jax.lax.stop_gradient(jnp.sum(log_scales, -1))
  n = volume.shape[0]
  rank = jnp.zeros((n,), jnp.int32).at[jnp.argsort(volume, stable=True)].set(jnp.arange(n, dtype=jnp.int32))
  return rank >= jnp.floor(share * n).astype(jnp.int32)


def perturb_gaussians(gaussians, distortion: dict | None, augmentation: Augmentation,
                      merges: tuple[decimate.Merges, ...] | None = None, rows=None):
  """Gaussians [N] as the check render sees them: every field of MODEL_FIELDS plus normal noise of
  distortion["param_noise"] times that field's per-channel standard deviation over the N Gaussians (a constant:
  the noise's scale is not trained), then each Gaussian dropped (opacity logit DROPPED_LOGIT, no gradient) with
  probability distortion["dropout"]; drawn from the PRNG seed distortion["model_seed"]; then the share
  distortion["prune_small"] of smallest Gaussians dropped (`kept_by_size`, by the volumes before the noise).
  First, where distortion["quantize"] is 1, the 8-bit colours and opacities (`quantize_8bit`, rounding at
  distortion["rounding"]), and where distortion["reset"] is 1, every opacity at most densify.RESET_CEILING; before
  all, the film decimated distortion["merge"] rounds deep by the rounds of `merges` (decimate.merge_rounds, from
  the PRNG seed distortion["model_seed"]; with merge_groups 'converter', decimate.merge_levels' level). A kind whose
  maximum in `augmentation` is 0 is left out at trace time (without any, the Gaussians themselves, and
  `distortion` may be None); at level 0 each is the identity, values and gradients. With `rows` (int32 [M],
  subsets.view_rows), Gaussians [M]: those rows of the result (subsets.gather), the same values for less work:
  what depends on every row (the merges, the random draws, the size ranks; with parameter noise, everything) is
  done over all N first, the rest over the M rows alone."""
  a = augmentation
  if not a.perturbs_model:
    return subsets.rows_of(gaussians, rows)
  if rows is not None and a.param_noise_max > 0:  # the noise's spread is over every row
    return subsets.rows_of(perturb_gaussians(gaussians, distortion, a, merges), rows)
  model_key = jax.random.key(distortion["model_seed"])
  if a.merge_fraction > 0:
    gaussians = decimate.merge_film(gaussians, merges, distortion["merge"], a.merge_groups == "converter",
                                    jax.random.fold_in(model_key, 2))
  noise_key, drop_key = jax.random.split(model_key)
  pick = lambda mask: subsets.rows_of(mask, rows, fill=True)
  kept = (pick(jax.random.uniform(drop_key, gaussians.opacity_logits.shape) >= distortion["dropout"])
          if a.dropout_max > 0 else None)
  sized = pick(kept_by_size(gaussians.log_scales, distortion["prune_small"])) if a.prune_small_max > 0 else None
  gaussians = subsets.rows_of(gaussians, rows)
  if a.quantize_fraction > 0:  # computed on the steps that quantize alone
    gaussians = jax.lax.cond(distortion["quantize"] > 0, lambda g: quantize_8bit(g, distortion["rounding"]),
                             lambda g: g, gaussians)
  if a.reset_fraction > 0:
    reset = densify.reset_opacity(gaussians.opacity_logits)
    gaussians = gaussians.replace(opacity_logits=jnp.where(distortion["reset"] > 0, reset,
                                                           gaussians.opacity_logits))
  if a.param_noise_max > 0:
    keys = dict(zip(MODEL_FIELDS, jax.random.split(noise_key, len(MODEL_FIELDS))))
    level = distortion["param_noise"]

    def noisy(name):
      x = getattr(gaussians, name)
      spread = jax.lax.stop_gradient(jnp.std(x, axis=0, keepdims=True))
      return x + level * spread * jax.random.normal(keys[name], x.shape, x.dtype)

    gaussians = gaussians.replace(**{name: noisy(name) for name in MODEL_FIELDS})
  if kept is not None:
    gaussians = gaussians.replace(opacity_logits=jnp.where(kept, gaussians.opacity_logits, DROPPED_LOGIT))
  if sized is not None:
    gaussians = gaussians.replace(opacity_logits=jnp.where(sized, gaussians.opacity_logits, DROPPED_LOGIT))
  return gaussians
