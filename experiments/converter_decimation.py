"""Which Gaussians @playcanvas/splat-transform's decimation merges (issue 39): its grouping reproduced from the
scene alone, checked against the converter's own output, and set beside conceal.decimate's simulated pairs.

  make converter-decimation                      # lego's recommended run (make survive-runs), to 50% and 80%
  python -m experiments.converter_decimation --run=workdirs/survive_runs/demo_recommended --keep=0.5

The converter (3.7.0, read in its dist/index.mjs: computeEdgeCostView, selectMerges) scores each Gaussian's 16
nearest neighbours by an edge cost: a KL-style term between the pair's mixture and its moment-matched merge (the
mixture's log-density at one fixed standard-normal sample per splat, seed 0 of mulberry32) plus the squared
difference of every colour coefficient; keeps each Gaussian's CANDIDATES cheapest; walks the candidate edges in
COST_BUCKETS buckets over the scene's whole cost range, cheapest bucket first and by edge index within one, pairing
free endpoints; then attaches Gaussians still free to a candidate's group (at most 3, then 4) until the target
count. A merged group lands on its members' mass-weighted mean (mass: opacity times ellipsoid area), so a group is
the converter's exactly when its mean is one of the output's positions. Writes converter_decimation.json: per
level, the share of the carrier film's groups found among the converter's output, and the share of
conceal.decimate's simulated pairs that lie in one converter group.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from conceal_jax.conceal import decimate
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.robust import converter
from conceal_jax.splat.gaussians import Gaussians, quaternion_to_rotation

NEIGHBOURS, CANDIDATES, COST_BUCKETS, GROUP_CAPS = 16, 4, 1024, (3, 4)
EPS_COV = 1e-8  # the converter's covariance regulariser
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


def edge_costs(g: Gaussians, first: np.ndarray, second: np.ndarray) -> np.ndarray:
  """[E] float32 the converter's cost of merging each pair (first[e], second[e]) of `g`."""
  pos = np.asarray(g.means, np.float64)
  var = np.maximum(np.exp(np.asarray(g.log_scales, np.float64)), 1e-12) ** 2 + EPS_COV
  rot = np.asarray(quaternion_to_rotation(jnp.asarray(g.quats)), np.float64)  # float32, as the converter's
  sigma = np.einsum("nij,nj,nkj->nik", rot, var, rot)
  logdet = np.log(var).sum(axis=1)
  colours = np.asarray(g.sh, np.float64).reshape(g.num, -1)
  mass = masses(g)
  p = np.clip(mass[first] / (mass[first] + mass[second]), 1e-12, 1 - 1e-12)[:, None]
  mean = p * pos[first] + (1 - p) * pos[second]
  d1, d2 = pos[first] - mean, pos[second] - mean
  merged = (p[:, :, None] * (sigma[first] + np.einsum("ei,ej->eij", d1, d1))
            + (1 - p[:, :, None]) * (sigma[second] + np.einsum("ei,ej->eij", d2, d2)) + EPS_COV * np.eye(3))
  neg_log_q = 0.5 * (3 * LOG_2PI + np.log(np.maximum(np.linalg.det(merged), 1e-30)) + 3)
  z = mulberry32_normal(0)

  def log_density(x, rows):
    local = np.einsum("eji,ej->ei", rot[rows], x - pos[rows])
    return -0.5 * (3 * LOG_2PI + logdet[rows] + np.sum(local**2 / var[rows], axis=1))

  log_p = 0.0
  for rows, weight in ((first, p[:, 0]), (second, 1 - p[:, 0])):
    sample = pos[rows] + np.einsum("eij,ej->ei", rot[rows], z * np.sqrt(var[rows]))
    log_p = log_p + weight * np.logaddexp(np.log(p[:, 0]) + log_density(sample, first),
                                          np.log(1 - p[:, 0]) + log_density(sample, second))
  return (log_p + neg_log_q + np.sum((colours[first] - colours[second]) ** 2, axis=1)).astype(np.float32)


def converter_groups(g: Gaussians, keep: float) -> np.ndarray:
  """[N] int: the group each Gaussian of `g` joins in the converter's decimation to round(keep * N) Gaussians
  (-1: left as it is). One generation only: keep in [0.5, 1)."""
  if not 0.5 <= keep < 1.0:
    raise ValueError(f"one generation of the converter's decimation keeps between half and all, got {keep}")
  n = g.num
  _, near = cKDTree(np.asarray(g.means, np.float64)).query(np.asarray(g.means, np.float64), k=NEIGHBOURS + 1)
  near = near[:, 1:]
  cost = edge_costs(g, np.repeat(np.arange(n), NEIGHBOURS), near.ravel()).reshape(n, NEIGHBOURS)
  best = np.argsort(cost, axis=1, kind="stable")[:, :CANDIDATES]
  target = np.take_along_axis(near, best, 1).ravel()
  cost = np.take_along_axis(cost, best, 1).ravel()
  finite = np.isfinite(cost)
  lo, hi = cost[finite].min(), cost[finite].max()
  bucket = np.minimum(COST_BUCKETS - 1, np.floor((cost - lo) / (hi - lo if hi > lo else 1) * COST_BUCKETS))
  order = np.lexsort((np.arange(cost.size), bucket))
  order = order[finite[order]]
  needed = n - int(round(keep * n))
  group, sizes = -np.ones(n, np.int64), []
  for e in order:
    i, j = e // CANDIDATES, target[e]
    if len(sizes) >= needed:
      break
    if group[i] == -1 and group[j] == -1:
      group[i] = group[j] = len(sizes)
      sizes.append(2)
  removed = len(sizes)
  for cap in GROUP_CAPS:
    for e in order:
      if removed >= needed:
        break
      i, j = e // CANDIDATES, target[e]
      if group[i] == -1 and group[j] != -1 and sizes[group[j]] < cap:
        group[i] = group[j]
        sizes[group[j]] += 1
        removed += 1
  return group


def group_means(g: Gaussians, group: np.ndarray) -> np.ndarray:
  """[G, 3] each group's mass-weighted mean (where the converter puts the merged Gaussian)."""
  merged = group >= 0
  mass = masses(g)[merged]
  pos = np.asarray(g.means, np.float64)[merged]
  weight = np.bincount(group[merged], weights=mass)
  return np.stack([np.bincount(group[merged], weights=mass * pos[:, c]) for c in range(3)], axis=1) / weight[:, None]


def compare(g: Gaussians, keep: float, returned: Gaussians, rows: np.ndarray, tolerance: float = 1e-5) -> dict:
  """How the reproduced grouping of `g` matches the converter's output `returned` over the Gaussians `rows` (the
  film): the share of their groups whose mean is an output position, group sizes, and the share of
  conceal.decimate's simulated pairs of those rows that lie in one reproduced group."""
  group = converter_groups(g, keep)
  mine = np.unique(group[rows][group[rows] >= 0])
  distance, _ = cKDTree(np.asarray(returned.means, np.float64)).query(group_means(g, group)[mine])
  simulated = decimate.nearest_pairs(np.asarray(g.means, np.float64)[rows]) + rows[0]
  together = (group[simulated[:, 0]] >= 0) & (group[simulated[:, 0]] == group[simulated[:, 1]])
  sizes = np.bincount(np.bincount(group[group >= 0]))
  return dict(keep=keep, gaussians=int(g.num), returned=int(returned.num), rows=int(rows.size), groups=int(mine.size),
              groups_found=float(np.mean(distance < tolerance)), group_sizes={int(k): int(v) for k, v in
                                                                                enumerate(sizes) if v},
              simulated_pairs=int(len(simulated)), simulated_pairs_in_one_group=float(np.mean(together)))


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--run", default="workdirs/survive_runs/lego_film")
  parser.add_argument("--keep", default="0.5,0.8", help="comma-separated fractions kept")
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/converter_decimation")
  args = parser.parse_args()
  if not converter.available():
    raise SystemExit("the converter is not installed: make node_modules")
  run = pathlib.Path(args.run)
  student = ply.load_ply(str(run / "student.ply"))
  carrier = int(json.loads((run / "conceal.json").read_text()).get("num_carrier", 0)) or student.num
  rows = np.arange(student.num - carrier, student.num)
  levels = []
  for keep in (float(k) for k in args.keep.split(",")):
    returned = converter.round_trip(student, decimate=keep, workdir=pathlib.Path(args.workdir) / f"keep_{keep:g}")
    levels.append(compare(student, keep, returned, rows))
    print(json.dumps(levels[-1]), flush=True)
  fileio.write_json(pathlib.Path(args.out) / "converter_decimation.json", dict(run=str(run), levels=levels))


if __name__ == "__main__":
  main()
