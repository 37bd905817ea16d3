"""The check render as a linear map of the film's colours (beyond the paper; a speed-up that changes no value).

Where only the carrier film's colours train (carrier.colour_rows) and the check render's attacks leave the geometry
in one of a few fixed states, the key's image is linear in the colours (splat/linear.py): C = W c + T b, one W per
state. The states are the student as it is and, with conceal.attacks.merge_groups 'converter', each of its merged
levels (decimate.merge_levels). `check_weights` reads every key's W of every state once (and again when a run
regroups); a step whose check render draws no 8-bit grid then renders through its W (`linear_render`) instead of
the renderer. Attacks that move a Gaussian's geometry or opacity by a fresh draw each step (dropout, parameter
noise, size pruning, opacity resets, merges of near pairs at a drawn share) leave no fixed W: those runs render.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from conceal_jax.conceal import decimate, subsets
from conceal_jax.conceal.augment import Augmentation
from conceal_jax.splat import linear
from conceal_jax.splat.render import RenderOptions, RenderOutput, render

# The weights' length is a multiple of this many entries, so that a regrouped run seldom changes the step's shapes.
LENGTH_STEP = 1 << 16


@struct.dataclass
class CheckWeights:
  """Every key's check render as a linear map, in each geometry state: weights (linear.ColourWeights with a leading
  [K * L] axis: key k's state l at k * L + l; state 0 the student as it is, state l >= 1 merged level l), each
  padded to one length with zero weights; num_pairs [K * L] int32: the splat-tile pairs its render needs."""
  weights: linear.ColourWeights
  num_pairs: jax.Array

  def at(self, index) -> linear.ColourWeights:
    """The ColourWeights of state `index` (traced)."""
    return jax.tree.map(lambda x: x[index], self.weights)


def applies(augmentation: Augmentation) -> bool:
  """Whether every check render whose model draws no 8-bit grid has one of the fixed geometries `check_weights`
  reads: no dropout, parameter noise, size pruning or opacity reset, and merges (if any) of the converter's groups."""
  a = augmentation
  fresh = max(a.dropout_max, a.param_noise_max, a.prune_small_max, a.reset_fraction) > 0
  return not fresh and (a.merge_fraction == 0 or a.merge_groups == "converter")


def states(augmentation: Augmentation) -> int:
  """L: the geometry states of a check render (the student, then each merged level) where `applies`, else 0 (the
  check renders are rendered)."""
  if not applies(augmentation):
    return 0
  return 1 + (augmentation.merge_levels if augmentation.merge_fraction > 0 else 0)


def check_weights(student, key_cameras, key_rows, merges, options: RenderOptions, num_states: int,
                  length: int = 0) -> CheckWeights:
  """CheckWeights of `student` at each of `key_cameras`, each key's render reading its rows `key_rows` [K, M]
  (subsets.view_rows), in `num_states` states (merged by `merges` from state 1 on), padded to `length` entries or
  the next multiple of LENGTH_STEP above the most any needs, where that is more. Eager."""
  student = jax.tree.map(jnp.asarray, student)
  maps, pairs = [], []
  for camera, rows in zip(key_cameras, key_rows):
    for state in range(num_states):
      g = student if state == 0 else decimate.merge_levels(student, merges, jnp.float32(state))
      g = subsets.gather(g, jnp.asarray(rows))
      maps.append(linear.colour_weights(g, camera, options))
      pairs.append(int(render(g, camera, options).num_pairs))
  longest = max(int(m.weights.size) for m in maps)
  length = max(length, -(-max(longest, 1) // LENGTH_STEP) * LENGTH_STEP)
  padded = [linear.padded(m, length) for m in maps]
  return CheckWeights(weights=jax.tree.map(lambda *xs: jnp.stack(xs), *padded),
                      num_pairs=jnp.asarray(np.asarray(pairs, np.int32)))


def linear_render(gaussians, weights: linear.ColourWeights, num_pairs: jax.Array, camera, options: RenderOptions,
                  like: RenderOutput) -> RenderOutput:
  """The render of `gaussians` [M] (the rows `weights` was read from, colours changed at will) from `camera` through
  `weights`: `like` (a RenderOutput of that render's shapes) with its rgb, alpha and num_pairs; no radii."""
  degree = gaussians.sh_degree if options.sh_degree is None else min(options.sh_degree, gaussians.sh_degree)
  background = jnp.asarray(options.background, gaussians.means.dtype)
  rgb = linear.linear_image(weights, linear.view_colours(gaussians, camera, degree), background)
  zeros = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), like)
  alpha = None if like.alpha is None else 1.0 - weights.transmittance
  return zeros.replace(rgb=rgb.astype(like.rgb.dtype), alpha=alpha, num_pairs=num_pairs.astype(like.num_pairs.dtype))
