"""Which poses near its key a finished run's decoder reads its image from: hidden SSIM with the key moved along and
turned about the key's own axes (near.KEY_AXES: x right, y down, z forward; a turn about z is a roll), both ways,
of the decoder's output and of its input (the render resized as the decoder reads it: what a decoder that is the
identity there would score, the render's own likeness to I). experiments/results/near_key_axes.md holds the tables.

  python -m experiments.near_axes workdirs/survive_runs/demo_thick_mf20_10k --turns=1,2,3,5 --moves=
  python -m experiments.near_axes RUN... --moves=0.01,0.02,0.05 --turns=

Moves are fractions of the key's near-key length (near.near_length of the run's clean teacher), as the conceal
job's near-key leakage figure takes them.
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib

from conceal_jax.conceal import near
from conceal_jax.gs import evaluate
from conceal_jax.robust import robustness
from experiments import bench_robust

AXIS_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")


def axis_rows(student, owner: robustness.Owner, length: float, kind: str, values) -> list[dict]:
  """Per value (a move: fraction of `length`; a turn: degrees) and key axis: hidden SSIM of the decoder's output
  and of its input there (module doc); value 0 is the key itself."""
  poses = [(value, axis) for value in values for axis in range(len(near.KEY_AXES))]
  if not poses:
    return []
  cameras = [near.nearby_camera(owner.check_camera, value * length if kind == "move" else 0.0,
                                value if kind == "turn" else 0.0, 0, key_axis=near.KEY_AXES[axis])
             for value, axis in poses]
  renders = evaluate.render_images(student, cameras, owner.options)
  output = owner.scores(owner.reveal_renders(renders))["ssim"]
  identity = dataclasses.replace(owner, decoder=None)
  inputs = identity.scores(identity.reveal_renders(renders))["ssim"]
  return [dict(kind=kind, value=value, axis=AXIS_NAMES[axis], output_ssim=float(out), input_ssim=float(inp))
          for (value, axis), out, inp in zip(poses, output, inputs)]


def table(run: str, rows: list[dict]) -> list[str]:
  """Markdown: one line per (kind, value), the axes as columns, each cell 'output (input)'."""
  lines = [f"{run}", "", "| pose | " + " | ".join(AXIS_NAMES) + " |", "|---" * (len(AXIS_NAMES) + 1) + "|"]
  for kind, value in dict.fromkeys((r["kind"], r["value"]) for r in rows):
    cells = {r["axis"]: f"{r['output_ssim']:.3f} ({r['input_ssim']:.3f})" for r in rows
             if (r["kind"], r["value"]) == (kind, value)}
    unit = "deg" if kind == "turn" else "of the depth"
    lines.append(f"| {kind} {value:g} {unit} | " + " | ".join(cells[a] for a in AXIS_NAMES) + " |")
  return lines + [""]


def values(text: str) -> list[float]:
  return [float(v) for v in text.split(",") if v.strip()]


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("runs", nargs="+", help="finished conceal workdirs")
  parser.add_argument("--moves", default="0.01,0.02,0.05", help="fractions of the key's near-key length")
  parser.add_argument("--turns", default="1,2,3,5", help="degrees")
  args = parser.parse_args(argv)
  for run in args.runs:
    config, student, owner = bench_robust.load_run(pathlib.Path(run))
    length = bench_robust.near_length(config, evaluate.load_scene_data(config), owner)
    rows = (axis_rows(student, owner, length, "move", values(args.moves))
            + axis_rows(student, owner, length, "turn", values(args.turns)))
    print("\n".join(table(run, rows)), flush=True)


if __name__ == "__main__":
  main()
