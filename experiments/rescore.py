"""Scores finished concealments again with today's scoring (conceal.train.score_saved), for runs trained before
the scoring changed (the near-key poses, a leakage figure):

  python -m experiments.rescore workdirs/bench/lego/conceal_in_scene_w16 workdirs/demo/conceal

Each run's metrics.json is rewritten; the one it replaces is kept as metrics_previous.json (once: a second
rescore keeps the first original). Prints each run's hidden PSNR / SSIM and leakage before and after. `make
bench-conceal BENCH_ARGS=--reuse` then rebuilds the bench's JSON from the new files.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import ml_collections

from conceal_jax.conceal import train
from conceal_jax.configs import default
from conceal_jax.core import fileio, workdir as workdir_lib
from conceal_jax.gs import evaluate

PREVIOUS_FILE = "metrics_previous.json"
RUN_FILES = ("config.json", train.STUDENT_FILE, evaluate.METRICS_FILE)


def headline(metrics: dict) -> dict:
  return dict(hidden=metrics["hidden"], leakage=metrics["leakage"])


def rescore(run: pathlib.Path) -> dict:
  """{'before': ..., 'after': ...} headline figures of `run` (a finished conceal workdir) scored again (module
  doc)."""
  saved = json.loads((run / "config.json").read_text())
  config = ml_collections.ConfigDict(workdir_lib.with_defaults(saved, default.get_config().to_dict()))
  before = json.loads((run / evaluate.METRICS_FILE).read_text())
  if not (run / PREVIOUS_FILE).is_file():
    fileio.write_json(str(run / PREVIOUS_FILE), before)
  after = train.score_saved(config, str(run))
  return dict(run=str(run), before=headline(before), after=headline(after))


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("runs", nargs="+", help="finished conceal workdirs")
  args = parser.parse_args(argv)
  runs = [pathlib.Path(run) for run in args.runs]
  bad = [f"{run}: missing {name}" for run in runs for name in RUN_FILES if not (run / name).is_file()]
  if bad:
    sys.exit("rescore: not finished conceal runs: " + "; ".join(bad))
  for run in runs:
    print(json.dumps(rescore(run)))


if __name__ == "__main__":
  main()
