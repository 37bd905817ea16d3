"""The converter's cost of merging two Gaussians (beyond the paper; grouping.py walks the pairs by it).

@playcanvas/splat-transform 3.7.0 (its dist/index.mjs: computeEdgeCostView) scores each Gaussian's NEIGHBOURS
nearest neighbours by a KL-style term between the pair's mixture and its moment-matched merge (the mixture's
log-density at one fixed standard-normal sample per splat, seed 0 of mulberry32) plus the squared difference of
every colour coefficient. The first term reads geometry and opacity alone, so a run that trains colours alone keeps
it (Neighbourhoods) and recomputes only the colour term when it regroups.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from conceal_jax.conceal import decimate
from conceal_jax.splat.gaussians import Gaussians, quaternion_to_rotation

NEIGHBOURS = 16
LOG_2PI = np.log(2.0 * np.pi)


def mulberry32_normal(seed: int = 0) -> np.ndarray:
  """[3] the converter's one standard-normal sample (Box-Muller on mulberry32(seed), its first four draws)."""
  state = seed & 0xFFFFFFFF

  def draw() -> float:
    nonlocal state
    state = (state + 0x6D2B79F5) & 0xFFFFFFFF
    t = ((state ^ (state >> 15)) * (state | 1)) & 0xFFFFFFFF
    t ^= (t + (((t ^ (t >> 7)) * (t | 61)) & 0xFFFFFFFF)) & 0xFFFFFFFF
    return ((t ^ (t >> 14)) & 0xFFFFFFFF) / 4294967296

  u1, u2, u3, u4 = max(draw(), 1e-12), draw(), max(draw(), 1e-12), draw()
  r1, r2 = np.sqrt(-2.0 * np.log(u1)), np.sqrt(-2.0 * np.log(u3))
  return np.array([r1 * np.cos(2 * np.pi * u2), r1 * np.sin(2 * np.pi * u2), r2 * np.cos(2 * np.pi * u4)])


def masses(g: Gaussians) -> np.ndarray:
  """[N] the converter's merge weight: decimate.masses (opacity times ellipsoid area) and its 1e-12 floor."""
  return decimate.masses(g) + 1e-12


def edge_costs(shape: np.ndarray, colour: np.ndarray) -> np.ndarray:
  """float32 the converter's cost of merging pairs from its two float64 terms of one shape: `shape_costs` plus
  `colour_costs` (kept apart so that a run training colours alone recomputes only the second)."""
  return (shape + colour).astype(np.float32)


def colour_costs(g: Gaussians, first: np.ndarray, second: np.ndarray) -> np.ndarray:
  """[E] float64 the colour term of edge_costs: the squared difference of every SH coefficient of each pair."""
  colours = np.asarray(g.sh, np.float64).reshape(g.num, -1)
  return np.sum((colours[first] - colours[second]) ** 2, axis=1)


def neighbour_colours(g: Gaussians, near: np.ndarray) -> np.ndarray:
  """[N, K] float64 the colour_costs of each Gaussian of `g` with each of its neighbours `near` [N, K]."""
  return per_neighbour(colour_costs, g, near)


def per_neighbour(costs, g: Gaussians, near: np.ndarray) -> np.ndarray:
  """[N, K] `costs`(g, first, second) of each Gaussian of `g` (first) with each of its neighbours `near` [N, K]."""
  n, k = near.shape
  return costs(g, np.repeat(np.arange(n), k), near.ravel()).reshape(n, k)


def shape_costs(g: Gaussians, first: np.ndarray, second: np.ndarray) -> np.ndarray:
  """[E] float64 the geometric term of edge_costs (positions, sizes, turns and opacities alone): the pair's
  mixture's log-density at the converter's sample minus its moment-matched merge's."""
  pos = np.asarray(g.means, np.float64)
  var = np.maximum(np.exp(np.asarray(g.log_scales, np.float64)), 1e-12) ** 2 + decimate.EPS_COV
  rot = np.asarray(quaternion_to_rotation(jnp.asarray(g.quats)), np.float64)  # float32, as the converter's
  sigma = (rot * var[:, None, :]) @ rot.transpose(0, 2, 1)
  logdet = np.log(var).sum(axis=1)
  mass = masses(g)
  p = np.clip(mass[first] / (mass[first] + mass[second]), 1e-12, 1 - 1e-12)[:, None]
  mean = p * pos[first] + (1 - p) * pos[second]
  d1, d2 = pos[first] - mean, pos[second] - mean
  outer = lambda d: d[:, :, None] * d[:, None, :]
  merged = (p[:, :, None] * (sigma[first] + outer(d1)) + (1 - p[:, :, None]) * (sigma[second] + outer(d2))
            + decimate.EPS_COV * np.eye(3))
  neg_log_q = 0.5 * (3 * LOG_2PI + np.log(np.maximum(np.linalg.det(merged), 1e-30)) + 3)
  z = mulberry32_normal(0)

  def log_density(x, rows):
    local = np.sum(rot[rows] * (x - pos[rows])[:, :, None], axis=1)  # R^T (x - mean)
    return -0.5 * (3 * LOG_2PI + logdet[rows] + np.sum(local**2 / var[rows], axis=1))

  log_p = 0.0
  for rows, weight in ((first, p[:, 0]), (second, 1 - p[:, 0])):
    sample = pos[rows] + np.sum(rot[rows] * (z * np.sqrt(var[rows]))[:, None, :], axis=2)
    log_p = log_p + weight * np.logaddexp(np.log(p[:, 0]) + log_density(sample, first),
                                          np.log(1 - p[:, 0]) + log_density(sample, second))
  return log_p + neg_log_q


class Neighbourhood(NamedTuple):
  """A scene's NEIGHBOURS nearest neighbours of every Gaussian, near [N, NEIGHBOURS] rows, and the shape_costs
  [N, NEIGHBOURS] of merging with each: what the converter's walk reads that its colours do not change."""
  near: np.ndarray
  shape: np.ndarray


def neighbourhood(g: Gaussians) -> Neighbourhood:
  """The Neighbourhood of `g` (a k-d tree over its centres)."""
  _, near = cKDTree(np.asarray(g.means, np.float64)).query(np.asarray(g.means, np.float64), k=NEIGHBOURS + 1)
  return Neighbourhood(near[:, 1:], per_neighbour(shape_costs, g, near[:, 1:]))


class Neighbourhoods:
  """Each scaled copy's Neighbourhood by its scale factor, kept while the copy's geometry (centres, sizes, turns,
  opacities) stays what it was: a run that trains colours alone regroups from them without a k-d tree or a
  shape cost."""

  def __init__(self):
    self._kept: dict = {}

  def __call__(self, copy: Gaussians, factor: float) -> Neighbourhood:
    shape = tuple(np.asarray(x) for x in (copy.means, copy.log_scales, copy.quats, copy.opacity_logits))
    kept = self._kept.get(factor)
    if kept is None or not all(np.array_equal(a, b) for a, b in zip(kept[0], shape)):
      kept = self._kept[factor] = (tuple(np.array(x, copy=True) for x in shape), neighbourhood(copy))
    return kept[1]
