"""Which Gaussians @playcanvas/splat-transform's decimation merges (issue 39): its grouping reproduced from the
scene alone, checked against the converter's own output, and set beside conceal.decimate's simulated pairs.

  make converter-decimation                      # lego's recommended run (make survive-runs), to 50% and 80%
  python -m experiments.converter_decimation --run=workdirs/survive_runs/demo_recommended --keep=0.5

The grouping is conceal.grouping.converter_groups (its docstring says what the converter does). A merged group
lands on its members' mass-weighted mean (mass: opacity times ellipsoid area), so a group is the converter's exactly
when its mean is one of the output's positions. Writes converter_decimation.json: per
level, the share of the carrier film's groups found among the converter's output, and the share of
conceal.decimate's simulated pairs that lie in one converter group.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np
from scipy.spatial import cKDTree

from conceal_jax.conceal import decimate, grouping, merge_costs
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.robust import converter
from conceal_jax.splat.gaussians import Gaussians


def group_means(g: Gaussians, group: np.ndarray) -> np.ndarray:
  """[G, 3] each group's mass-weighted mean (where the converter puts the merged Gaussian)."""
  merged = group >= 0
  mass = merge_costs.masses(g)[merged]
  pos = np.asarray(g.means, np.float64)[merged]
  weight = np.bincount(group[merged], weights=mass)
  return np.stack([np.bincount(group[merged], weights=mass * pos[:, c]) for c in range(3)], axis=1) / weight[:, None]


def compare(g: Gaussians, keep: float, returned: Gaussians, rows: np.ndarray, tolerance: float = 1e-5) -> dict:
  """How the reproduced grouping of `g` matches the converter's output `returned` over the Gaussians `rows` (the
  film): the share of their groups whose mean is an output position, group sizes, and the share of
  conceal.decimate's simulated pairs of those rows that lie in one reproduced group."""
  group = grouping.converter_groups(g, keep)
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
  parser.add_argument("--run", default="workdirs/survive_runs/lego_converter_mf35_rot5_scales_wm25")
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
