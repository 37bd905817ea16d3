"""3D-GS adaptive density control on a fixed-capacity buffer (3D-GS, Kerbl et al. 2023, arXiv:2308.04079, Sec. 5.2).

The train step is compiled for a buffer of `capacity` Gaussians with an `alive` mask, so clone, split
and prune only rewrite the buffer's contents; the capacity (and so the compiled step) changes only
when the live count leaves the current size bucket, which doubles at a time: a compile costs seconds, a
dead row of the buffer a fraction of a microsecond a step, and a growing scene leaves a bucket within a
few densification rounds. Everything here runs on the host in numpy, once every few hundred steps.

Rows are tracked by `source`: for every row of the new buffer, the row of the old buffer it continues
(its optimizer moments carry over), or -1 for a new Gaussian (fresh, zero moments), as 3D-GS does.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.splat import gaussians as gs
from conceal_jax.splat.gaussians import Gaussians, opacity_logit

FRESH = -1
CAPACITY_QUANTUM = 1024
CAPACITY_GROWTH = 2.0


@dataclasses.dataclass(frozen=True)
class DensifyParams:
  """grad_threshold: mean NDC 2D-mean gradient norm that triggers densification (2e-4);
  percent_dense: clone below, split above this fraction of the extent in max scale (0.01);
  split_factor: scale divisor of the two split children (1.6); min_opacity: prune below (0.005);
  max_screen_radius: prune above, pixels (20); max_world_scale: prune above, fraction of extent (0.1);
  max_gaussians: 0 (3D-GS: no limit), or the most live Gaussians densification may create."""
  grad_threshold: float = 2e-4
  percent_dense: float = 0.01
  split_factor: float = 1.6
  min_opacity: float = 0.005
  max_screen_radius: float = 20.0
  max_world_scale: float = 0.1
  max_gaussians: int = 0

  def __post_init__(self):
    if self.max_gaussians < 0:
      raise ValueError(f"train.densify.max_gaussians must be >= 0 (0: no limit), got {self.max_gaussians}")


def within_budget(selected: np.ndarray, mean_grads: np.ndarray, budget: int) -> np.ndarray:
  """[M] bool: `selected` reduced to its `budget` largest gradients (ties: lower index first)."""
  if selected.sum() <= budget:
    return selected
  candidates = np.flatnonzero(selected)
  strongest = candidates[np.argsort(-mean_grads[candidates], kind="stable")[:max(budget, 0)]]
  kept = np.zeros_like(selected)
  kept[strongest] = True
  return kept


def capacity_for(count: int, current: int = 0, limit: int = 0) -> int:
  """Buffer size for `count` live Gaussians: keeps `current` while count fits and is above a quarter
  of it, else the smallest bucket quantum * 2^k that holds count. With a Gaussian cap `limit` (max_gaussians)
  that count respects, no bucket exceeds it: the buffer's rows cost time in every step whether they are alive
  or not."""
  capped = 0 < count <= limit
  if 0 < current and current // 4 <= count <= current and not (capped and current > limit):
    return current
  capacity = CAPACITY_QUANTUM
  while capacity < count:
    capacity = int(math.ceil(capacity * CAPACITY_GROWTH / CAPACITY_QUANTUM)) * CAPACITY_QUANTUM
  return min(capacity, limit) if capped else capacity


def take(gaussians: Gaussians, rows: np.ndarray) -> Gaussians:
  """The Gaussians at `rows` (indices or a boolean mask) of a numpy-backed scene."""
  return jax.tree.map(lambda x: np.asarray(x)[rows], gaussians)


def concatenate(parts: list[Gaussians]) -> Gaussians:
  return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)


def split_children(parents: Gaussians, rng: np.random.Generator, factor: float,
                   num_children: int = 2) -> Gaussians:
  """Replaces each parent by `num_children` Gaussians with centres sampled from the parent's 3D
  Gaussian and scales divided by `factor` (3D-GS split: 2 children, factor 0.8 * 2 = 1.6)."""
  scales = np.exp(np.asarray(parents.log_scales, np.float64))
  rotations = np.asarray(gs.quaternion_to_rotation(gs.normalize_quaternion(parents.quats)), np.float64)
  children = []
  for _ in range(num_children):
    offsets = rng.normal(size=scales.shape) * scales
    means = np.asarray(parents.means) + np.einsum("nij,nj->ni", rotations, offsets)
    children.append(parents.replace(means=means.astype(np.asarray(parents.means).dtype),
                                    log_scales=np.asarray(parents.log_scales) - np.log(factor)))
  return concatenate(children)


def densify_and_prune(gaussians: Gaussians, mean_grads: np.ndarray, max_radii: np.ndarray, extent: float,
                      params: DensifyParams, prune_large: bool, rng: np.random.Generator
                      ) -> tuple[Gaussians, np.ndarray]:
  """One 3D-GS densification round on the live Gaussians (numpy, [M, ...]).

  mean_grads: [M] accumulated NDC 2D-mean gradient norms divided by their view counts;
  max_radii: [M] largest screen radius seen since the last round.
  Clones small Gaussians with large gradients, splits large ones (the parent is removed), then prunes
  near-transparent ones and, when `prune_large`, those too large on screen or in the world. Clone and split
  each add one Gaussian, so with params.max_gaussians only the strongest max_gaussians - M candidates act.
  Returns the new live Gaussians and `source` [M'] (the input row each continues, FRESH for new ones).
  """
  max_scale = np.exp(np.asarray(gaussians.log_scales)).max(-1)
  selected = mean_grads >= params.grad_threshold
  if params.max_gaussians:
    selected = within_budget(selected, mean_grads, params.max_gaussians - gaussians.num)
  small = max_scale <= params.percent_dense * extent
  clone, split = selected & small, selected & ~small
  parts = [take(gaussians, ~split), take(gaussians, clone),
           split_children(take(gaussians, split), rng, params.split_factor)]
  num_new = int(clone.sum()) + 2 * int(split.sum())
  source = np.concatenate([np.flatnonzero(~split), np.full(num_new, FRESH)])
  radii = np.concatenate([np.asarray(max_radii)[~split], np.zeros(num_new)])  # new ones: not seen yet
  result = concatenate(parts)

  prune = np.asarray(gs.opacities(result)) < params.min_opacity
  if prune_large:
    prune |= radii > params.max_screen_radius
    prune |= np.exp(np.asarray(result.log_scales)).max(-1) > params.max_world_scale * extent
  return take(result, ~prune), source[~prune]


# 3D-GS's opacity reset (Sec. 5.2): every opacity lowered to at most this.
RESET_CEILING = 0.01


def reset_opacity(opacity_logits, ceiling: float = RESET_CEILING):
  """3D-GS opacity reset: opacities become min(opacity, ceiling), as logits (numpy in, numpy out; a jax array or
  tracer in, one out)."""
  xp = jnp if isinstance(opacity_logits, jax.Array) else np
  return xp.minimum(opacity_logits, opacity_logit(ceiling)).astype(opacity_logits.dtype)


def gather_rows(x: np.ndarray, source: np.ndarray, capacity: int) -> np.ndarray:
  """[C, ...] -> [capacity, ...]: row i is x[source[i]], zero where source is FRESH and past the end."""
  out = np.zeros((capacity,) + x.shape[1:], x.dtype)
  rows = np.flatnonzero(source != FRESH)
  out[rows] = x[source[rows]]
  return out


def pad_rows(x: np.ndarray, capacity: int) -> np.ndarray:
  """[M, ...] -> [capacity, ...] with zero rows appended."""
  out = np.zeros((capacity,) + x.shape[1:], x.dtype)
  out[:x.shape[0]] = x
  return out
