"""A converter's decimation of the carrier film, as the check render sees it (beyond the paper).

Publishing tools shrink a scene by merging neighbouring Gaussians: @playcanvas/splat-transform's `--decimate`
merges the pairs whose merge changes the scene least into one Gaussian that keeps their mass (opacity times
surface area) and their first two moments, its colour their mass-weighted mean (a moment-matching merge). A film of
many faint splats side by side merges first and loses the detail between the two splats of each pair.

The film's geometry is fixed during concealment (carrier.colour_rows), so its groups and what each group merges
into are computed on the host (`film_merges`: each splat paired with a near neighbour, round after round; or
grouping.converter_merges: the converter's own groups of 2 to 4, recomputed as the colours train): the merged
Gaussian's mean, scales, rotation and opacity (`moment_matched`). Only the colours train, and a merged colour is a
fixed mix of its members' trained ones, so `merge_groups` renders a share of the groups merged at no more cost than
the film itself, with the gradient reaching every member's colour (conceal.attacks.merge_fraction).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.spatial import cKDTree

from conceal_jax.gs import similarity
from conceal_jax.splat.gaussians import Gaussians, covariance_3d, opacity_logit

# Knud Thomsen's approximation of an ellipsoid's surface area, the one splat-transform weighs a splat's mass by.
ELLIPSOID_P = 1.6075
# The neighbours each splat's pair is chosen among.
NEIGHBOURS = 8
# A decimation to a quarter of the film is two rounds of merges; deeper than that a film keeps no image.
MAX_MERGE_DEPTH = 2.0
# How a merging check render groups the film: near pairs merge_depth rounds deep, or the converter's groups
# (grouping.py), one level of conceal.attacks.merge_keep.
MERGE_GROUPS = ("nearest", "converter")
# The converter's covariance regulariser, added to every merged covariance (and to the variances its costs read).
EPS_COV = 1e-8
# A merged-away splat's opacity logit: sigmoid(-30) ~ 1e-13, nothing the renderer composites.
DROPPED_LOGIT = -30.0


@struct.dataclass
class Merges:
  """P disjoint groups of up to M of the student's Gaussians and what each merges into: members [P, M] int32
  (indices into the student, its first member where the merged Gaussian goes; padding: an index past the student's
  last, which no gather or scatter reaches); weights [P, M]: each member's share of its group's mass (0 for
  padding), which mixes the colours; means [P, 3], log_scales [P, 3], quats [P, 4], opacity_logits [P] of the
  merged Gaussian."""
  members: jax.Array
  weights: jax.Array
  means: jax.Array
  log_scales: jax.Array
  quats: jax.Array
  opacity_logits: jax.Array


def ellipsoid_area(scales: np.ndarray) -> np.ndarray:
  """[...] the surface area of ellipsoids of semi-axes scales [..., 3] (ELLIPSOID_P's approximation)."""
  a, b, c = (scales[..., k] for k in range(3))
  p = ELLIPSOID_P
  return 4.0 * np.pi * (((a * b)**p + (a * c)**p + (b * c)**p) / 3.0)**(1.0 / p)


def masses(gaussians: Gaussians) -> np.ndarray:
  """[N] float64 each Gaussian's merge weight: its opacity times its ellipsoid's surface area (ellipsoid_area)."""
  opacity = 1.0 / (1.0 + np.exp(-np.asarray(gaussians.opacity_logits, np.float64)))
  return opacity * ellipsoid_area(np.exp(np.asarray(gaussians.log_scales, np.float64)))


def nearest_pairs(means: np.ndarray, neighbours: int = NEIGHBOURS) -> np.ndarray:
  """[P, 2] disjoint pairs of rows of means [N, 3], closest first: among each point's `neighbours` nearest, the
  shortest edge whose two ends are both unpaired is taken next (greedy matching). Unpaired points are left out."""
  if len(means) < 2:
    return np.zeros((0, 2), np.int64)
  distances, indices = cKDTree(means).query(means, k=min(neighbours, len(means) - 1) + 1)
  rows = np.repeat(np.arange(len(means)), indices.shape[1] - 1)
  edges = np.stack([rows, indices[:, 1:].ravel()], -1)
  order = np.argsort(distances[:, 1:].ravel(), kind="stable")
  taken = np.zeros(len(means), bool)
  pairs = []
  for i, j in edges[order]:
    if not (taken[i] or taken[j]):
      taken[i] = taken[j] = True
      pairs.append((i, j))
  return np.asarray(pairs, np.int64).reshape(-1, 2)


def moment_matched(gaussians: Gaussians, groups: np.ndarray) -> dict[str, np.ndarray]:
  """What each group [P, M] of `gaussians` (rows; -1 pads a group of fewer than M) merges into (float64): the
  mass-weighted mean, the covariance that keeps the group's second moment (law of total variance) plus EPS_COV as
  log_scales and a unit quaternion, the opacity that keeps the group's mass (capped at 1), and `weights` [P, M],
  each member's share of the mass (0 for padding). splat-transform's n-ary merge (mergeGroup) computes the same:
  its regulariser makes a merge depend on the scene's scale where variances approach EPS_COV."""
  valid = groups >= 0
  rows = np.where(valid, groups, 0)
  mass = np.where(valid, masses(gaussians)[rows], 0.0)
  with jax.enable_x64(True):
    covariances = np.asarray(covariance_3d(jax.tree.map(lambda x: np.asarray(x, np.float64), gaussians)))[rows]
  means = np.asarray(gaussians.means, np.float64)[rows]
  total = mass.sum(axis=1)
  weights = mass / total[:, None]
  mean = np.einsum("pm,pmi->pi", weights, means)
  d = means - mean[:, None]
  covariance = np.einsum("pm,pmij->pij", weights, covariances + d[..., :, None] * d[..., None, :])
  covariance = covariance + EPS_COV * np.eye(3)
  variances, axes = np.linalg.eigh(covariance)
  axes = axes * np.where(np.linalg.det(axes) < 0, -1.0, 1.0)[:, None, None]  # a rotation, not a reflection
  merged_scales = np.sqrt(np.maximum(variances, 1e-18))
  merged_opacity = np.minimum(1.0, total / ellipsoid_area(merged_scales))
  return dict(means=mean, log_scales=np.log(merged_scales),
              quats=similarity.matrix_to_quaternion(axes).reshape(-1, 4),
              opacity_logits=np.asarray(opacity_logit(np.clip(merged_opacity, 1e-7, 1.0 - 1e-7))), weights=weights)


def as_merges(merged: dict[str, np.ndarray], members: np.ndarray) -> Merges:
  """Merges of groups `members` [P, M] (student rows, padding already past the last) and `moment_matched`'s
  `merged` values, as float32 / int32 device arrays."""
  f32 = lambda name: jnp.asarray(merged[name], jnp.float32)
  return Merges(members=jnp.asarray(members, jnp.int32), weights=f32("weights"), means=f32("means"),
                log_scales=f32("log_scales"), quats=f32("quats"), opacity_logits=f32("opacity_logits"))


def film_merges(film: Gaussians, offset: int, levels: int = 1) -> tuple[Merges, ...]:
  """The Merges of `levels` rounds of decimation of the film, its indices shifted by `offset` (the film's first row
  in the student: the teacher's Gaussian count): round 0 pairs the film's splats with near neighbours
  (`nearest_pairs`); each later round pairs what the one before leaves once every one of its pairs has merged
  (a converter decimating deeper than half merges some groups of three or four), its pairs indexing the student's
  rows where the merged Gaussians live (each pair's first)."""
  rounds, rows = [], np.arange(film.num)
  for _ in range(levels):
    pairs = nearest_pairs(np.asarray(film.means, np.float64))
    merged = moment_matched(film, pairs)
    rounds.append(as_merges(merged, rows[pairs] + offset))
    unpaired = np.setdiff1d(np.arange(film.num), pairs.ravel())
    fields = {name: np.concatenate([merged[name], np.asarray(getattr(film, name), np.float64)[unpaired]])
              for name in ("means", "log_scales", "quats", "opacity_logits")}
    film = film.replace(**fields, sh=np.zeros((len(fields["means"]),) + film.sh.shape[1:], np.float32))
    rows = np.concatenate([rows[pairs[:, 0]], rows[unpaired]])
  return tuple(rounds)


def merge_film(gaussians: Gaussians, merges: tuple[Merges, ...], value: jax.Array, levels: bool,
               key: jax.Array) -> Gaussians:
  """gaussians [N] decimated by `merges` at `value` (traced): the level numbered `value` (`merge_levels`) where
  `merges` are the converter's levels (`levels`), else `value` rounds deep (`merge_rounds`, drawn from `key`). At
  value 0, most steps, nothing is computed."""
  merge = (lambda g: merge_levels(g, merges, value)) if levels else (lambda g: merge_rounds(g, merges, value, key))
  return jax.lax.cond(value > 0, merge, lambda g: g, gaussians)


def merge_rounds(gaussians: Gaussians, merges: tuple[Merges, ...], depth: jax.Array, key: jax.Array) -> Gaussians:
  """gaussians [N] decimated `depth` (traced) rounds deep by the rounds of `film_merges`: round k merges a share
  clip(depth - k, 0, 1) of its pairs (`merge_groups`), so a round only starts once the one before has merged
  every pair. At depth 0 the Gaussians themselves, values and gradients."""
  for k, merges_k in enumerate(merges):
    gaussians = merge_groups(gaussians, merges_k, jnp.clip(depth - k, 0.0, 1.0),
                             key if k == 0 else jax.random.fold_in(key, k))
  return gaussians


def merge_levels(gaussians: Gaussians, merges: tuple[Merges, ...], level: jax.Array) -> Gaussians:
  """gaussians [N] decimated as the one of `merges` (Merges of one shape, grouping.converter_merges) numbered
  `level` (traced; 1-based, 0: none) decimates them, every one of its groups merged; only that level is gathered.
  At level 0 the Gaussians themselves, values and gradients."""
  chosen = jax.tree.map(lambda *levels: jnp.stack(levels)[jnp.clip(level.astype(jnp.int32) - 1, 0, len(merges) - 1)],
                        *merges)
  return merge_groups(gaussians, chosen, (level > 0).astype(jnp.float32), jax.random.key(0))  # a share of 0 or 1


def merge_groups(gaussians: Gaussians, merges: Merges, share: jax.Array, key: jax.Array) -> Gaussians:
  """gaussians [N] with each group of `merges` merged with probability `share` (drawn per group from the PRNG `key`;
  both traced): its first member becomes the merged Gaussian, of the members' colours mixed by mass (all SH bands),
  the others are dropped (DROPPED_LOGIT). At share 0 the Gaussians themselves, values and gradients."""
  gaussians = jax.tree.map(jnp.asarray, gaussians)
  members, first = merges.members, merges.members[:, 0]
  merged = jax.random.uniform(key, first.shape) < share
  mixed = jnp.einsum("pm,pm...->p...", merges.weights, gaussians.sh.at[members].get(mode="fill", fill_value=0.0))

  def at_first(field, value):
    current = field.at[first].get(mode="fill", fill_value=0.0)
    mask = merged.reshape((-1,) + (1,) * (current.ndim - 1))
    return field.at[first].set(jnp.where(mask, value.astype(field.dtype), current), mode="drop")

  logits = at_first(gaussians.opacity_logits, merges.opacity_logits)
  others = members[:, 1:]
  current = logits.at[others].get(mode="fill", fill_value=0.0)
  logits = logits.at[others].set(jnp.where(merged[:, None], DROPPED_LOGIT, current), mode="drop")
  return gaussians.replace(means=at_first(gaussians.means, merges.means),
                           log_scales=at_first(gaussians.log_scales, merges.log_scales),
                           quats=at_first(gaussians.quats, merges.quats), opacity_logits=logits,
                           sh=at_first(gaussians.sh, mixed))
