"""Scores finished concealments again with today's scoring (score_saved), for runs trained before
the scoring changed (the near-key poses, a leakage figure), or a run's latest checkpoint, finished or not:

  python -m experiments.rescore workdirs/bench/lego/conceal_in_scene_w16 workdirs/demo/conceal
  python -m experiments.rescore --checkpoint workdirs/survive_runs/lego_recommended_in_scene_axial
  python -m experiments.rescore --checkpoint --views=20 RUN  # a quicker interim read: 20 of the test views

Each run's metrics.json is rewritten; the one it replaces is kept as metrics_previous.json (once: a second
rescore keeps the first original). Prints each run's hidden PSNR / SSIM and leakage before and after. `make
bench-conceal BENCH_ARGS=--reuse` then rebuilds the bench's JSON from the new files. With --checkpoint the run's
own files are left alone: the checkpoint's student and decoder are scored as a finished run's are, into
<run>/checkpoint_scores/step_<N>/ (metrics.json and the revealed images), and its headline figures printed.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import ml_collections

from conceal_jax.conceal import carrier, reveal, settings as settings_lib, train
from conceal_jax.conceal.step import create_state
from conceal_jax.configs import default
from conceal_jax.core import checkpoint, fileio, loop, workdir as workdir_lib
from conceal_jax.data import ply
from conceal_jax.gs import evaluate

PREVIOUS_FILE = "metrics_previous.json"
RUN_FILES = ("config.json", train.STUDENT_FILE, evaluate.METRICS_FILE)
CHECKPOINT_SCORES = "checkpoint_scores"


def headline(metrics: dict) -> dict:
  return dict(hidden=metrics["hidden"], leakage=metrics["leakage"])


def saved_config(run: pathlib.Path) -> ml_collections.ConfigDict:
  """The run's config.json, completed with today's defaults (core.workdir.with_defaults)."""
  saved = json.loads((run / "config.json").read_text())
  return ml_collections.ConfigDict(workdir_lib.with_defaults(saved, default.get_config().to_dict()))


def score_saved(config: ml_collections.ConfigDict, run: pathlib.Path) -> dict:
  """metrics.json of a finished run scored again from its saved student.ply and decoder.msgpack, at the keys
  train.marking chooses for `config` (the run's config.json)."""
  plan = settings_lib.plan(config)
  student = ply.load_ply(str(run / train.STUDENT_FILE))
  decoder = reveal.load_decoder(str(run / train.DECODER_FILE)) if plan.settings.use_decoder else {}
  return train.score_student(config, str(run), train.marking(config, plan), plan.settings, student, decoder)


def rescore(run: pathlib.Path) -> dict:
  """{'before': ..., 'after': ...} headline figures of `run` (a finished conceal workdir) scored again (module
  doc)."""
  config = saved_config(run)
  before = json.loads((run / evaluate.METRICS_FILE).read_text())
  if not (run / PREVIOUS_FILE).is_file():
    fileio.write_json(str(run / PREVIOUS_FILE), before)
  after = score_saved(config, run)
  return dict(run=str(run), before=headline(before), after=headline(after))


def score_checkpoint(run: pathlib.Path, views: int = 0) -> dict:
  """The headline figures and step of `run`'s latest conceal checkpoint, scored as a finished run's student and
  decoder are (train.score_student) into <run>/checkpoint_scores/step_<N>/ (on `views` evenly spaced test views,
  0: the run's own eval.max_views); the run's own files are not touched. The state's template is the run's own
  first state: the teacher, or the teacher and its planned film."""
  config = saved_config(run)
  if views:
    config.eval.max_views = views
  plan = settings_lib.plan(config)
  marked = train.marking(config, plan)
  start, rows = carrier.student_start(plan.film, marked.teacher, marked.keys[0][0], marked.scene.train_cameras,
                                      marked.scene.test_cameras, marked.options, plan.settings.hidden_size)
  template = create_state(start, train.initial_decoder(config, plan.settings),
                          settings_lib.student_optimizer(config, marked.scene.scene_extent(), rows is not None),
                          settings_lib.decoder_optimizer(config), rows, plan.rollback)
  path, _, leaves = checkpoint.load_latest(str(run / loop.CHECKPOINT_DIR))
  state = checkpoint.restore(template, leaves, source=path)
  out = run / CHECKPOINT_SCORES / (f"step_{int(state.step)}" + (f"_views_{views}" if views else ""))
  out.mkdir(parents=True, exist_ok=True)
  scored = train.score_student(config, str(out), marked, plan.settings, state.student, state.decoder)
  return dict(run=str(run), step=int(state.step), views=config.eval.max_views, **headline(scored),
              student=scored["student_vs_ground_truth"], teacher=scored["teacher_vs_ground_truth"])


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("runs", nargs="+", help="conceal workdirs: finished ones, or with --checkpoint any with one")
  parser.add_argument("--checkpoint", action="store_true",
                      help="score each run's latest checkpoint into <run>/checkpoint_scores/step_<N>/")
  parser.add_argument("--views", type=int, default=0,
                      help="with --checkpoint: score on this many evenly spaced test views (0: the run's own count)")
  args = parser.parse_args(argv)
  if args.views < 0 or (args.views and not args.checkpoint):
    sys.exit(f"rescore: --views must be a positive count of test views, given with --checkpoint (got {args.views})")
  runs = [pathlib.Path(run) for run in args.runs]
  if args.checkpoint:
    bad = [f"{run}: no config.json" for run in runs if not (run / "config.json").is_file()]
    bad += [f"{run}: no checkpoint" for run in runs if not checkpoint.list_steps(str(run / loop.CHECKPOINT_DIR))]
    if bad:
      sys.exit("rescore: not conceal runs with a checkpoint: " + "; ".join(bad))
    for run in runs:
      print(json.dumps(score_checkpoint(run, args.views)))
    return
  bad = [f"{run}: missing {name}" for run in runs for name in RUN_FILES if not (run / name).is_file()]
  if bad:
    sys.exit("rescore: not finished conceal runs: " + "; ".join(bad))
  for run in runs:
    print(json.dumps(rescore(run)))


if __name__ == "__main__":
  main()
