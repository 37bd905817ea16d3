"""A converter's decimation of the carrier film, as the check render sees it (beyond the paper).

Publishing tools shrink a scene by merging neighbouring Gaussians: @playcanvas/splat-transform's `--decimate`
merges the pairs whose merge changes the scene least into one Gaussian that keeps their mass (opacity times
surface area) and their first two moments, its colour their mass-weighted mean (a moment-matching merge). A film of
many faint splats side by side merges first and loses the detail between the two splats of each pair.

The film's geometry is fixed during concealment (carrier.trainable_fields), so its pairs and what each pair merges
into are computed once (`film_merges`): each splat paired with a near neighbour, and the merged Gaussian's mean,
scales, rotation and opacity. Only the colours train, and a merged colour is a fixed mix of two trained ones, so
`merge_pairs` renders a share of the pairs merged at no more cost than the film itself, with the gradient reaching
both colours (conceal.attacks.merge_fraction).
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
# A merged-away splat's opacity logit: sigmoid(-30) ~ 1e-13, nothing the renderer composites.
DROPPED_LOGIT = -30.0


@struct.dataclass
class Merges:
  """P disjoint pairs of the student's Gaussians and what each merges into: first, second [P] int32 (indices into
  the student); means [P, 3], log_scales [P, 3], quats [P, 4], opacity_logits [P] of the merged Gaussian; weight
  [P]: the first's share of the pair's mass, which mixes the colours."""
  first: jax.Array
  second: jax.Array
  means: jax.Array
  log_scales: jax.Array
  quats: jax.Array
  opacity_logits: jax.Array
  weight: jax.Array


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


def moment_matched(gaussians: Gaussians, pairs: np.ndarray) -> dict[str, np.ndarray]:
  """What each pair [P, 2] of `gaussians` merges into (float64): the mass-weighted mean, the covariance that keeps
  the pair's second moment (law of total variance) as log_scales and a unit quaternion, the opacity that keeps the
  pair's mass (capped at 1), and `weight` [P], the first's share of the mass."""
  mass = masses(gaussians)
  with jax.enable_x64(True):
    covariances = np.asarray(covariance_3d(jax.tree.map(lambda x: np.asarray(x, np.float64), gaussians)))
  means = np.asarray(gaussians.means, np.float64)
  i, j = pairs[:, 0], pairs[:, 1]
  weight = mass[i] / (mass[i] + mass[j])
  w = weight[:, None]
  mean = w * means[i] + (1.0 - w) * means[j]
  di, dj = means[i] - mean, means[j] - mean
  outer = lambda d: d[:, :, None] * d[:, None, :]
  covariance = (w[:, :, None] * (covariances[i] + outer(di)) + (1.0 - w)[:, :, None] * (covariances[j] + outer(dj)))
  variances, axes = np.linalg.eigh(covariance)
  axes = axes * np.where(np.linalg.det(axes) < 0, -1.0, 1.0)[:, None, None]  # a rotation, not a reflection
  merged_scales = np.sqrt(np.maximum(variances, 1e-18))
  merged_opacity = np.minimum(1.0, (mass[i] + mass[j]) / ellipsoid_area(merged_scales))
  return dict(means=mean, log_scales=np.log(merged_scales),
              quats=np.stack([similarity.matrix_to_quaternion(a) for a in axes]),
              opacity_logits=np.asarray(opacity_logit(np.clip(merged_opacity, 1e-7, 1.0 - 1e-7))), weight=weight)


def film_merges(film: Gaussians, offset: int, levels: int = 1) -> tuple[Merges, ...]:
  """The Merges of `levels` rounds of decimation of the film, its indices shifted by `offset` (the film's first row
  in the student: the teacher's Gaussian count): round 0 pairs the film's splats with near neighbours
  (`nearest_pairs`); each later round pairs what the one before leaves once every one of its pairs has merged
  (a converter decimating deeper than half merges some groups of three or four), its pairs indexing the student's
  rows where the merged Gaussians live (each pair's first)."""
  rounds, rows = [], np.arange(film.num)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  for _ in range(levels):
    pairs = nearest_pairs(np.asarray(film.means, np.float64))
    merged = moment_matched(film, pairs)
    rounds.append(Merges(first=jnp.asarray(rows[pairs[:, 0]] + offset, jnp.int32),
                         second=jnp.asarray(rows[pairs[:, 1]] + offset, jnp.int32), means=f32(merged["means"]),
                         log_scales=f32(merged["log_scales"]), quats=f32(merged["quats"]),
                         opacity_logits=f32(merged["opacity_logits"]), weight=f32(merged["weight"])))
    unpaired = np.setdiff1d(np.arange(film.num), pairs.ravel())
    fields = {name: np.concatenate([merged[name], np.asarray(getattr(film, name), np.float64)[unpaired]])
              for name in ("means", "log_scales", "quats", "opacity_logits")}
    film = film.replace(**fields, sh=np.zeros((len(fields["means"]),) + film.sh.shape[1:], np.float32))
    rows = np.concatenate([rows[pairs[:, 0]], rows[unpaired]])
  return tuple(rounds)


def merge_rounds(gaussians: Gaussians, merges: tuple[Merges, ...], depth: jax.Array, key: jax.Array) -> Gaussians:
  """gaussians [N] decimated `depth` (traced) rounds deep by the rounds of `film_merges`: round k merges a share
  clip(depth - k, 0, 1) of its pairs (`merge_pairs`), so a round only starts once the one before has merged
  every pair. At depth 0 the Gaussians themselves, values and gradients."""
  for k, merges_k in enumerate(merges):
    gaussians = merge_pairs(gaussians, merges_k, jnp.clip(depth - k, 0.0, 1.0),
                            key if k == 0 else jax.random.fold_in(key, k))
  return gaussians


def merge_pairs(gaussians: Gaussians, merges: Merges, share: jax.Array, key: jax.Array) -> Gaussians:
  """gaussians [N] with each pair of `merges` merged with probability `share` (drawn per pair from the PRNG `key`;
  both traced): the first becomes the merged Gaussian, of the pair's colours mixed by mass (all SH bands), the
  second is dropped (DROPPED_LOGIT). At share 0 the Gaussians themselves, values and gradients."""
  merged = jax.random.uniform(key, merges.first.shape) < share
  w = merges.weight[:, None, None]
  mixed = w * gaussians.sh[merges.first] + (1.0 - w) * gaussians.sh[merges.second]

  def at_first(field, value):
    current = field[merges.first]
    mask = merged.reshape((-1,) + (1,) * (current.ndim - 1))
    return field.at[merges.first].set(jnp.where(mask, value.astype(field.dtype), current))

  logits = at_first(gaussians.opacity_logits, merges.opacity_logits)
  logits = logits.at[merges.second].set(jnp.where(merged, DROPPED_LOGIT, logits[merges.second]))
  return gaussians.replace(means=at_first(gaussians.means, merges.means),
                           log_scales=at_first(gaussians.log_scales, merges.log_scales),
                           quats=at_first(gaussians.quats, merges.quats), opacity_logits=logits,
                           sh=at_first(gaussians.sh, mixed))
