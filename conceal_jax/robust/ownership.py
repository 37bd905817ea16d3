"""The ownership test: is this scene marked with my hidden image? `--config.mode=verify`.

The score of a scene is the SSIM between the hidden image I and what the owner's decoder reveals from the
scene's render at the owner's key (the reveal job's output). The decision is score >= threshold, where
the threshold comes from a calibration file of measured scores: `clean` (scenes that were never marked
with this image and key: other teachers and scenes, the student under wrong keys, another run's decoder)
and `marked` (the student under mild and medium attacks). verify.json reports the score and decision
with the false- and true-positive rates measured at that threshold, and how many trials they rest on.
With reveal.owner set (the owner's copy of the marked scene), the key is first moved into the suspect's
frame (conceal.reveal.aligned_key) and verify.json reports the transform found.
"""
from __future__ import annotations

import json
import os
from typing import Sequence

import ml_collections
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib, reveal
from conceal_jax.core import fileio
from conceal_jax.gs import metrics

VERIFY_FILE = "verify.json"
MAX_FALSE_POSITIVE_RATE = 0.01


def rates(clean: Sequence[float], marked: Sequence[float], threshold: float) -> dict:
  """False-positive rate (clean scores >= threshold) and true-positive rate (marked scores >= threshold)."""
  clean, marked = np.asarray(clean, np.float64), np.asarray(marked, np.float64)
  return dict(false_positive_rate=float(np.mean(clean >= threshold)) if clean.size else float("nan"),
              true_positive_rate=float(np.mean(marked >= threshold)) if marked.size else float("nan"))


def choose_threshold(clean: Sequence[float], marked: Sequence[float],
                     max_false_positive_rate: float = MAX_FALSE_POSITIVE_RATE) -> dict:
  """The threshold with the highest true-positive rate whose false-positive rate stays below
  `max_false_positive_rate`; within the gap between the clean score it must exceed and the next score
  up, the midpoint (the widest margin on both sides). Returns threshold and both rates."""
  clean = np.sort(np.asarray(clean, np.float64))
  marked = np.asarray(marked, np.float64)
  if clean.size == 0 or marked.size == 0:
    raise ValueError("choosing a threshold needs clean and marked scores")
  allowed = int(np.ceil(max_false_positive_rate * clean.size)) - 1  # clean scores allowed at or above it
  floor = clean[clean.size - 1 - allowed] if allowed < clean.size else -np.inf  # must be strictly above this
  above = np.concatenate([clean[clean > floor], marked[marked > floor]])
  ceiling = above.min() if above.size else floor + 1e-6
  threshold = float(0.5 * (floor + ceiling)) if np.isfinite(floor) else float(ceiling)
  return dict(threshold=threshold, **rates(clean, marked, threshold), num_clean=int(clean.size),
              num_marked=int(marked.size), max_false_positive_rate=max_false_positive_rate)


def load_calibration(path: str) -> dict:
  """A calibration file: {"clean": [scores], "marked": [scores], ...}; the threshold is chosen here from
  them (a stored threshold is not trusted). ValueError naming the file if it is missing or malformed."""
  try:
    with open(path) as f:
      data = json.load(f)
    clean, marked = [float(x) for x in data["clean"]], [float(x) for x in data["marked"]]
  except (OSError, ValueError, KeyError, TypeError) as error:
    raise ValueError(f"cannot read calibration {path}: {error}") from error
  return dict(choose_threshold(clean, marked), source=path)


def decide(score: float, calibration: dict) -> bool:
  """The ownership decision: the score reaches the calibrated threshold (load_calibration)."""
  return bool(score >= calibration["threshold"])


def validate(config: ml_collections.ConfigDict) -> None:
  for name in ("ply", "key", "hidden"):
    if not config.reveal[name]:
      raise ValueError(f"reveal.{name} is required for verify")
  if not config.verify.calibration:
    raise ValueError("verify.calibration is required (make bench-robust writes "
                     "experiments/results/ownership_calibration.json)")


def verify(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """The verify job: reveal at the key, score against the hidden image, decide at the calibrated threshold."""
  validate(config)
  r = config.reveal
  calibration = load_calibration(config.verify.calibration)
  revealed, alignment = reveal.reveal_with_alignment(r)
  score = float(metrics.ssim(revealed, hidden_lib.load_hidden_image(r.hidden, revealed.shape[0])))
  result = dict(ply=r.ply, key=r.key, decoder=r.decoder, hidden=r.hidden, score=score,
                owned=decide(score, calibration), calibration=calibration)
  if alignment is not None:
    result["alignment"] = alignment
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed)
  fileio.write_json(os.path.join(workdir, VERIFY_FILE), result)
  return result
