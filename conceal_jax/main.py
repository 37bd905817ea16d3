"""Command line entry: `python -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=DIR`.

Only wires flags; the jobs live in their own modules. Config values are overridden with
`--config.key=value`; the final config is saved to DIR/config.json.
"""
from __future__ import annotations

import os
import sys

from absl import app, flags
from ml_collections import config_flags

from conceal_jax.baselines import baseline
from conceal_jax.conceal import conceal, reveal
from conceal_jax.core import fileio
from conceal_jax.gs import evaluate, render_views, train
from conceal_jax.robust import ownership

# mode -> (validate, job): validate checks every value the job reads before anything is written.
MODES = {"render": (render_views.validate, render_views.render_and_save),
         "train": (train.validate, train.train_and_evaluate),
         "eval": (evaluate.validate, evaluate.evaluate),
         "conceal": (conceal.validate, conceal.conceal_and_evaluate),
         "baseline": (baseline.validate, baseline.baseline_and_evaluate),
         "reveal": (reveal.validate, reveal.reveal),
         "verify": (ownership.validate, ownership.verify)}

FLAGS = flags.FLAGS
flags.DEFINE_string("workdir", None, "Directory for outputs, checkpoints and the saved config.")
config_flags.DEFINE_config_file("config", None, "Path to a config file (a get_config() module).",
                                lock_config=True)
flags.mark_flags_as_required(["config", "workdir"])


def run(config, workdir: str):
  """Validates the config for its mode, saves it into workdir and runs the job."""
  if config.mode not in MODES:
    raise ValueError(f"config.mode must be one of {sorted(MODES)}, got {config.mode!r}")
  validate, job = MODES[config.mode]
  validate(config)
  os.makedirs(workdir, exist_ok=True)
  fileio.write_json(os.path.join(workdir, "config.json"), config.to_dict())
  return job(config, workdir)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  try:
    run(FLAGS.config, FLAGS.workdir)
  except (ValueError, OSError) as error:  # bad input: one clear line, no traceback
    print(f"conceal_jax: error: {error}", file=sys.stderr)
    sys.exit(1)


if __name__ == "__main__":
  app.run(main)
