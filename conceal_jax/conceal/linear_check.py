"""The check render, and the normal views' renders, as linear maps of the film's colours (beyond the paper; a
speed-up that changes no value).

Where only the carrier film's colours train (carrier.colour_rows) and the check render's attacks leave the geometry
in one of a few fixed states, the key's image is linear in the colours (splat/linear.py): C = W c + T b, one W per
state. The states are the student as it is and, with conceal.attacks.merge_groups 'converter', each of its merged
levels (decimate.merge_levels). `check_weights` reads every key's W of every state once (and again when a run
regroups); a step whose check render draws no 8-bit grid then renders through its W (objective.rendered, with
linear.render_through) instead of the renderer. Attacks that move a Gaussian's geometry or opacity by a fresh draw
each step (dropout, parameter noise, size pruning, opacity resets, merges of near pairs at a drawn share) leave no
fixed W: those runs render.

A normal view renders the student as it is (its attacks are the check render's), so where only the film's colours
train each normal view that renders has one fixed W too: `normal_weights` reads them once, within a memory budget
(conceal.carrier.linear_maps_mb: the decoys of a 64 x 64 key fit, those of a 200 x 200 one take about ten times
as much), and a step's normal view is read through its W.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import decimate, subsets
from conceal_jax.conceal.augment import Augmentation
from conceal_jax.splat import linear, render
from conceal_jax.splat.render import RenderOptions

# The weights' length is a multiple of this many entries, so that a regrouped run seldom changes the step's shapes.
LENGTH_STEP = 1 << 16


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
                  length: int = 0) -> linear.ColourWeights:
  """linear.ColourWeights [K * L] of `student` at each of `key_cameras` (key k's state l at k * L + l; state 0 the
  student as it is, state l >= 1 merged level l of `merges`), each key's render reading its rows `key_rows` [K, M]
  (subsets.view_rows), in L = `num_states` states; `stacked` to at least `length` entries. Eager."""
  student = jax.tree.map(jnp.asarray, student)
  views = ((subsets.gather(student if state == 0 else decimate.merge_levels(student, merges, jnp.float32(state)),
                           jnp.asarray(rows)), camera)
           for camera, rows in zip(key_cameras, key_rows) for state in range(num_states))
  return stacked(list(read_maps(views, options)), length)


def normal_weights(student, cameras, rows, fixed, options: RenderOptions, budget_mb: float):
  """(linear.ColourWeights [R], int32 [C]): the maps of `student`'s renders at the `cameras` [C] that are not
  `fixed` ([C] bool: their render is held), each reading its `rows` [C, M] (subsets.view_rows), `stacked`; and each
  camera's index among them, -1 for the fixed ones. (None, None) where no camera renders or the stacked maps would
  take more than `budget_mb` MB, given up as soon as the maps read so far and the rest at the size of the last
  would. Eager."""
  student, budget = jax.tree.map(jnp.asarray, student), budget_mb * 2**20
  rendering = np.flatnonzero(~np.asarray(fixed, bool))
  maps, used = [], 0
  for m in read_maps(((subsets.gather(student, jnp.asarray(rows[c])), cameras[c]) for c in rendering), options):
    maps.append(m)
    used += map_bytes(m)
    if used + map_bytes(m) * (len(rendering) - len(maps)) > budget:
      return None, None
  if not maps:
    return None, None
  weights = host_stacked(maps)
  if map_bytes(weights) > budget:
    return None, None
  weights = jax.tree.map(jnp.asarray, weights)
  index = np.full(len(cameras), -1, np.int32)
  index[rendering] = np.arange(len(rendering), dtype=np.int32)
  return weights, jnp.asarray(index)


def read_maps(views, options: RenderOptions):
  """linear.colour_weights of each (gaussians, camera) of `views` in turn (a generator), each rendered into a pair
  buffer of the most pairs a view before it needed (a view needing more grows it), not the largest render's."""
  fitted, most = options, 0
  for gaussians, camera in views:
    weights = linear.colour_weights(gaussians, camera, fitted)
    most = max(most, int(weights.num_pairs))
    fitted = render.grow_capacity(options, most)
    yield weights


def stacked(maps, length: int = 0) -> linear.ColourWeights:
  """linear.ColourWeights [len(maps)] on the device: `maps` padded (linear.stacked_maps) to `length` entries or the
  next multiple of LENGTH_STEP above the most any holds, where that is more."""
  return jax.tree.map(jnp.asarray, host_stacked(maps, length))


def host_stacked(maps, length: int = 0) -> linear.ColourWeights:
  """`stacked`, in host arrays."""
  longest = max(int(m.weights.size) for m in maps)
  return linear.stacked_maps(maps, max(length, -(-max(longest, 1) // LENGTH_STEP) * LENGTH_STEP))


def lengthened(maps: linear.ColourWeights, length: int) -> linear.ColourWeights:
  """Stacked `maps` [R] padded to `length` entries each (at least theirs)."""
  host = jax.tree.map(np.asarray, maps)
  return stacked([jax.tree.map(lambda x: x[r], host) for r in range(host.weights.shape[0])], length)


def map_bytes(weights: linear.ColourWeights) -> int:
  """The memory a map (or a stack of them) takes: its pixel, row and weight entries and its final transmittance."""
  return sum(int(x.size) * x.dtype.itemsize for x in (weights.pixels, weights.rows, weights.weights,
                                                        weights.transmittance))
