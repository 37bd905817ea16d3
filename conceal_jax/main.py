"""Command line entry: `python -m conceal_jax.main --config=conceal_jax/configs/default.py --workdir=DIR`.

Only wires flags; the jobs live in their own modules. Config values are overridden with
`--config.key=value`; the final config is saved to DIR/config.json, and a workdir of a resumable mode run
again with settings that change its run is refused (core.workdir). `--host_devices=N` splits a CPU host
into N XLA devices before JAX starts (0, the default: one per core, at most 2), over which a step spreads its
views. `--coordinator_address`, `--num_processes` and `--process_id` (or JAX_COORDINATOR_ADDRESS,
JAX_NUM_PROCESSES, JAX_PROCESS_ID) run one job over several processes, on one machine or several
(core.parallel.start_processes); process 0 writes the workdir, process k its workdir/process_k.
"""
from __future__ import annotations

import logging
import os
import sys

from absl import app, flags
from ml_collections import config_flags

from conceal_jax.baselines import baseline
from conceal_jax.conceal import reveal, settings as conceal_settings, train as conceal_train
from conceal_jax.configs import default
from conceal_jax.core import parallel, workdir as workdir_lib
from conceal_jax.gs import evaluate, render_views, train
from conceal_jax.report import summary
from conceal_jax.robust import ownership

# mode -> (validate, job): validate checks every value the job reads before anything is written.
MODES = {"render": (render_views.validate, render_views.render_and_save),
         "train": (train.validate, train.train_and_evaluate),
         "eval": (evaluate.validate, evaluate.evaluate),
         "conceal": (conceal_settings.validate, conceal_train.train_and_evaluate),
         "baseline": (baseline.validate, baseline.baseline_and_evaluate),
         "reveal": (reveal.validate, reveal.reveal),
         "verify": (ownership.validate, ownership.verify)}

# Modes whose workdir holds checkpoints a later run resumes: one run per workdir (core.workdir.claim).
RESUMABLE = ("train", "conceal", "baseline")

FLAGS = flags.FLAGS
flags.DEFINE_string("workdir", None, "Directory for outputs, checkpoints and the saved config.")
flags.DEFINE_integer("host_devices", 0, "XLA devices a CPU host is split into (0: one per core, at most 2).")
flags.DEFINE_string("coordinator_address", None, "host:port of process 0, for a run over several processes "
                    "(default: $JAX_COORDINATOR_ADDRESS).")
flags.DEFINE_integer("num_processes", None, "Processes of the run (default: $JAX_NUM_PROCESSES, else 1).")
flags.DEFINE_integer("process_id", None, "This process's index, 0..num_processes-1 (default: $JAX_PROCESS_ID).")
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
  workdir_lib.claim(workdir, config.to_dict(), resumable=config.mode in RESUMABLE,
                    defaults=default.get_config().to_dict(), retired=default.RETIRED_SETTINGS)
  return job(config, workdir)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  parallel.host_devices_flag(FLAGS.host_devices or min(2, os.cpu_count() or 1))
  # JAX logs each accelerator platform it looks for and does not find ("Unable to initialize backend 'tpu'")
  logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)
  try:
    parallel.start_processes(FLAGS.coordinator_address, FLAGS.num_processes, FLAGS.process_id)
    workdir = parallel.process_workdir(FLAGS.workdir)
    closing = summary.after_job(FLAGS.config, workdir, run(FLAGS.config, workdir))
  except (ValueError, OSError) as error:  # bad input: one clear line, no traceback
    print(f"conceal_jax: error: {error}", file=sys.stderr)
    sys.exit(1)
  if closing:
    print(closing)


if __name__ == "__main__":
  app.run(main)
