"""A converter's decimation grouping, reproduced from the scene alone (beyond the paper): which Gaussians
@playcanvas/splat-transform's `--decimate` merges, so that training can merge exactly those (conceal.attacks.
merge_groups 'converter').

The converter (3.7.0, read in its dist/index.mjs: computeEdgeCostView, selectMerges) scores each Gaussian's
NEIGHBOURS nearest neighbours by an edge cost (merge_costs.py); keeps each Gaussian's CANDIDATES cheapest; walks the
candidate edges in COST_BUCKETS buckets over the scene's whole cost range, cheapest bucket first and by edge index
within one, pairing free endpoints; then attaches Gaussians still free to a candidate's group (at most 3, then 4)
until the target count. Each group merges as decimate.moment_matched says. The colour term depends on the trained
colours, so a run regroups as they train (conceal.attacks.regroup_every).
"""
from __future__ import annotations

import jax
import numpy as np

from conceal_jax.conceal import decimate
from conceal_jax.conceal.merge_costs import Neighbourhood, Neighbourhoods, edge_costs, neighbour_colours, neighbourhood
from conceal_jax.splat.gaussians import Gaussians

CANDIDATES, COST_BUCKETS, GROUP_CAPS = 4, 1024, (3, 4)
MAX_GROUP = GROUP_CAPS[-1]
# The training merges' capacities are multiples of this many groups.
CAPACITY_STEP = 1024


def candidate_edges(g: Gaussians, around: Neighbourhood | None = None,
                    colour: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
  """The converter's walk over candidate merges of `g`: ([E] source, [E] target) rows, in the order it takes them
  (each Gaussian's CANDIDATES cheapest of its NEIGHBOURS nearest, by cost bucket, then by edge index). `around`:
  g's Neighbourhood where known (a scene whose colours alone changed since it was computed); `colour`: the
  neighbour_colours of g at around.near where known (a copy of another size has the same)."""
  near, shape = around if around is not None else neighbourhood(g)
  cost = edge_costs(shape, neighbour_colours(g, near) if colour is None else colour)
  best = np.argsort(cost, axis=1, kind="stable")[:, :CANDIDATES]
  target = np.take_along_axis(near, best, 1).ravel()
  cost = np.take_along_axis(cost, best, 1).ravel()
  finite = np.isfinite(cost)
  lo, hi = cost[finite].min(), cost[finite].max()
  bucket = np.minimum(COST_BUCKETS - 1, np.floor((cost - lo) / (hi - lo if hi > lo else 1) * COST_BUCKETS))
  order = np.lexsort((np.arange(cost.size), bucket))
  order = order[finite[order]]
  return order // CANDIDATES, target[order]


def converter_groups(g: Gaussians, keep: float, edges: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
  """[N] int: the group each Gaussian of `g` joins in the converter's decimation to round(keep * N) Gaussians
  (-1: left as it is): free pairs along the walk `edges` (candidate_edges of `g` unless given) until enough are
  removed, then free Gaussians attached to a group of at most 3, then 4. One generation only: keep in [0.5, 1)."""
  if not 0.5 <= keep < 1.0:
    raise ValueError(f"one generation of the converter's decimation keeps between half and all, got {keep}")
  n = g.num
  sources, targets = (x.tolist() for x in (edges if edges is not None else candidate_edges(g)))
  needed = n - int(round(keep * n))
  group, sizes = [-1] * n, []
  for i, j in zip(sources, targets):
    if len(sizes) >= needed:
      break
    if group[i] == -1 and group[j] == -1:
      group[i] = group[j] = len(sizes)
      sizes.append(2)
  removed = len(sizes)
  for cap in GROUP_CAPS:
    for i, j in zip(sources, targets):
      if removed >= needed:
        break
      if group[i] == -1 and group[j] != -1 and sizes[group[j]] < cap:
        group[i] = group[j]
        sizes[group[j]] += 1
        removed += 1
  return np.asarray(group, np.int64)


def group_members(group: np.ndarray, rows: np.ndarray) -> np.ndarray:
  """[P, MAX_GROUP] the groups of `group` (converter_groups' labels) that hold any of `rows`, each as its members
  in descending order (-1 pads a group of fewer): a group's merged Gaussian goes to its first member, a film row
  where the group holds one (the film's rows come last in the student; subsets.py relies on it)."""
  labels = np.unique(group[rows][group[rows] >= 0])
  members = -np.ones((labels.size, MAX_GROUP), np.int64)
  if labels.size == 0:
    return members
  index = np.full(group.max() + 1, -1, np.int64)
  index[labels] = np.arange(labels.size)
  where = np.flatnonzero((group >= 0) & (index[np.maximum(group, 0)] >= 0))[::-1]  # descending rows
  slot = index[group[where]]
  order = np.argsort(slot, kind="stable")
  slot, where = slot[order], where[order]
  position = np.arange(slot.size) - np.searchsorted(slot, slot)
  members[slot, position] = where
  return members


def scaled(gaussians: Gaussians, factor: float) -> Gaussians:
  """`gaussians` scaled by `factor` about the origin (positions and sizes): the copy a scene's scale is tried on,
  since the converter's costs are not scale-free (decimate.EPS_COV against the splats' variances)."""
  return gaussians.replace(means=np.asarray(gaussians.means) * factor,
                           log_scales=np.asarray(gaussians.log_scales) + np.log(factor))


def converter_merges(gaussians: Gaussians, rows: np.ndarray, keeps, capacity: int = 0, scales=(1.0,),
                     neighbourhoods: Neighbourhoods | None = None) -> tuple[decimate.Merges, ...]:
  """One decimate.Merges per scale of `scales` and kept fraction of `keeps` (scale-major): the converter's groups
  (converter_groups) of `gaussians` scaled by that factor (`scaled`: what it merges in a copy someone resized)
  that hold any of `rows` (the film), merged in that copy as the converter merges them and scaled back to
  `gaussians`' own frame; every level padded with members past the last Gaussian to the same number of groups:
  `capacity`, or the next multiple of CAPACITY_STEP above the most any level has, where that is more (a regrouped
  run keeps its capacity, so its step keeps its shapes). `neighbourhoods`: the copies' Neighbourhoods kept from
  an earlier call."""
  levels, colours = [], []  # colours: (neighbours, their colour costs); resizing changes neither colour
  for factor in scales:
    copy = scaled(gaussians, factor)
    around = neighbourhoods(copy, factor) if neighbourhoods is not None else neighbourhood(copy)
    colour = next((cost for near, cost in colours if np.array_equal(near, around.near)), None)
    if colour is None:
      colour = neighbour_colours(copy, around.near)
      colours.append((around.near, colour))
    edges = candidate_edges(copy, around, colour)
    levels += [(factor, copy, group_members(converter_groups(copy, keep, edges), rows)) for keep in keeps]
  most = max(len(members) for _, _, members in levels)
  capacity = max(capacity, -(-most // CAPACITY_STEP) * CAPACITY_STEP)
  merges = []
  for factor, copy, members in levels:
    merged = decimate.moment_matched(copy, members)
    merged.update(means=merged["means"] / factor, log_scales=merged["log_scales"] - np.log(factor))
    pad = capacity - len(members)
    merged = {name: np.concatenate([value, np.zeros((pad,) + value.shape[1:])]) for name, value in merged.items()}
    members = np.concatenate([members, -np.ones((pad, MAX_GROUP), np.int64)])
    merges.append(decimate.as_merges(merged, np.where(members >= 0, members, gaussians.num)))
  return tuple(merges)


def training_merges(student: Gaussians, offset: int, augmentation, capacity: int = 0,
                    neighbourhoods: Neighbourhoods | None = None) -> tuple[decimate.Merges, ...]:
  """What a run's merging check renders merge (conceal.attacks.merge_groups, augment.Augmentation
  `augmentation`) of the film, the rows of `student` from `offset` on: the converter's groups at each of merge_keep
  and merge_scales (`converter_merges`, at least `capacity` groups), or merge_rounds rounds of near pairs
  (decimate.film_merges)."""
  student = jax.tree.map(np.asarray, student)
  if augmentation.merge_groups == "converter":
    return converter_merges(student, np.arange(offset, student.num), augmentation.merge_keep, capacity,
                            augmentation.merge_scales, neighbourhoods)
  return decimate.film_merges(jax.tree.map(lambda x: x[offset:], student), offset, augmentation.merge_rounds)


class Regrouping:
  """When a run merging the converter's groups computes them anew from the student (`due`): every
  augmentation.regroup_every steps and at each checkpoint (so a resumed run regroups where the first did), and at a
  process's first step unless its groups are the student's at `grouped_at` (a fresh run's, from the start); each
  time from the scaled copies' `neighbourhoods` while their geometry holds."""

  def __init__(self, offset: int, augmentation, checkpoint_every: int, grouped_at: int = 0,
               neighbourhoods: Neighbourhoods | None = None):
    self.offset, self.augmentation = offset, augmentation
    self.checkpoint_every, self.grouped_at, self.first = checkpoint_every, grouped_at, True
    self.neighbourhoods = Neighbourhoods() if neighbourhoods is None else neighbourhoods

  def due(self, iteration: int) -> bool:
    """Whether step `iteration` (1-based) reads groups computed from the student it starts from."""
    done = iteration - 1
    at_boundary = done % self.augmentation.regroup_every == 0 or bool(self.checkpoint_every and
                                                                      done % self.checkpoint_every == 0)
    due = done != self.grouped_at and (self.first or at_boundary)
    self.first = False
    return due

  def __call__(self, student: Gaussians, iteration: int, capacity: int) -> tuple[decimate.Merges, ...]:
    """training_merges of `student`, the state before step `iteration`, in at least `capacity` groups (the run's
    merges so far: a capacity that only grows recompiles the step only when it grows)."""
    self.grouped_at = iteration - 1
    return training_merges(student, self.offset, self.augmentation, capacity, self.neighbourhoods)


def regrouping(offset: int, augmentation, checkpoint_every: int,
               neighbourhoods: Neighbourhoods | None = None) -> Regrouping | None:
  """A run's Regrouping (from the scaled copies' `neighbourhoods` kept so far) where its check renders merge the
  converter's groups of the film (rows from `offset` on), else None (near pairs are computed once)."""
  if augmentation.merge_fraction > 0 and augmentation.merge_groups == "converter":
    return Regrouping(offset, augmentation, checkpoint_every, neighbourhoods=neighbourhoods)
  return None
