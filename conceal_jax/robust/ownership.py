"""The ownership test: is this scene marked with my hidden image? `--config.mode=verify`.

The decoder reveals R from the scene's render at the owner's key; the statistic is the phase correlation z of R
with the hidden image I (robust.phase_statistic), and the p-value the larger of two: z under the random-phase
null (N(0, 1): R's Fourier phases independent of I's), and z against the null estimated from this decoder and
scene, the z of the decoder's outputs on unmarked inputs (null_reveals: the scene turned well away from the key,
unrelated pictures), as Student's t predictive. The scene is owned when that p-value is at most verify.alpha.
verify.json reports the statistic, both p-values, the decision, what the null rests on, and the SSIM; a
calibration file of measured SSIM scores (verify.calibration, `make bench-robust`) adds its threshold's
decision as further evidence. revealed.png, hidden.png and null_revealed.npz are kept.
With reveal.owner set (the owner's copy of the marked scene), the key is first moved into the suspect's
frame (conceal.reveal.aligned_key) and verify.json reports the transform found.
"""
from __future__ import annotations

import json
import os
from typing import Sequence

import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, reveal
from conceal_jax.core import fileio, settings
from conceal_jax.gs import evaluate, metrics
from conceal_jax.robust import phase_statistic
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.render import RenderOptions

VERIFY_FILE = "verify.json"
MAX_FALSE_POSITIVE_RATE = 0.01
# The null views turn the key camera about its centre by angles spread over this range (degrees): beyond the
# decoys leakage control trains near the key (conceal.leakage.decoy_rotation_deg, up to 10), so that a marked
# scene's own views there are as unmarked as another scene's.
NULL_TURN_DEG = (15.0, 45.0)
NULL_SEED_BASE = 2_000_000  # seeds of the null views' turn axes, apart from leakage's and the decoys'
NULL_RESTS_ON = (
    "z is the phase correlation of the revealed image with the hidden image over its standard deviation under "
    "the random-phase model (the revealed image's Fourier phases independent of the hidden image's: z ~ N(0, 1) "
    "over effective_samples independent terms); the estimated null is z of this decoder's outputs on inputs "
    "that do not carry the mark (the scene turned away from the key, unrelated pictures), a new draw of which "
    "is Student's t predictive; the p-value is the larger of the two")


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


def null_cameras(camera: Camera, count: int) -> list[Camera]:
  """`count` cameras at the key's position turned by angles spread evenly over NULL_TURN_DEG about random axes."""
  angles = np.linspace(*NULL_TURN_DEG, count) if count > 1 else np.full(count, np.mean(NULL_TURN_DEG))
  return [key_lib.nearby_camera(camera, 0.0, float(angle), NULL_SEED_BASE + k) for k, angle in enumerate(angles)]


def unrelated_images(hidden: np.ndarray) -> np.ndarray:
  """[8 * n, S, S, 3] the eight flips and quarter turns of each scikit-image sample picture (hidden.SAMPLE_NAMES)
  at the size of the hidden image [S, S, 3], less any that is the hidden image itself (within 1/255 on average):
  pictures the scene was not marked with."""
  pictures = [hidden_lib.load_hidden_image(name, hidden.shape[0]) for name in hidden_lib.SAMPLE_NAMES]
  pictures = [p for p in pictures if np.abs(p - hidden).mean() >= 1.0 / 255]
  return np.stack([np.rot90(p[:, ::-1] if flip else p, turns) for p in pictures for flip in (False, True)
                   for turns in range(4)])


def null_reveals(gaussians, camera: Camera, options: RenderOptions, reveal_fn, views: int,
                 hidden: np.ndarray) -> dict[str, np.ndarray]:
  """What a decoder (reveal_fn: renders [V, H, W, 3] -> [V, S, S, 3]) reveals from inputs that do not carry the
  hidden image [S, S, 3]: "unrelated_images" [K, S, S, 3], unrelated_images read as renders, and "turned_views"
  [views, S, S, 3], the scene `gaussians` rendered with `options` at null_cameras of the key `camera`."""
  out = dict(unrelated_images=np.asarray(reveal_fn(jnp.asarray(unrelated_images(hidden)))))
  if views:
    renders = evaluate.render_images(gaussians, null_cameras(camera, views), options)
    out["turned_views"] = np.asarray(reveal_fn(renders))
  return out


def decisions(revealed: np.ndarray, hidden: np.ndarray, null_revealed: np.ndarray, alpha: float) -> dict:
  """Revealed images [R, S, S, 3] against hidden images [J, S, S, 3], with the decoder's outputs on inputs that do
  not carry them [K, S, S, 3] (K >= 3): z [R, J] (phase_statistic.z_scores), log10 of the model p-value, of the
  estimated null's (the K outputs' z against each hidden image) and of the p-value decided on, the larger of the
  two [R, J], the decision at `alpha` [R, J] and the null's z [K, J]."""
  target = phase_statistic.whitened_spectra(hidden)
  z = phase_statistic.z_scores(phase_statistic.whitened_spectra(revealed), target)
  null_z = phase_statistic.z_scores(phase_statistic.whitened_spectra(null_revealed), target)
  log_model = phase_statistic.log_p_model(z) / np.log(10)
  log_fit = np.stack([phase_statistic.log_p_predictive(z[:, j], null_z[:, j]) for j in range(z.shape[1])], 1)
  log_p = np.maximum(log_model, log_fit / np.log(10))
  return dict(z=z, log10_p_model=log_model, log10_p_null_fit=log_fit / np.log(10), log10_p=log_p,
              owned=log_p <= np.log10(alpha), null_z=null_z)


def ownership_test(revealed: np.ndarray, hidden: np.ndarray, null_revealed: np.ndarray, alpha: float) -> dict:
  """The decision for one revealed image [S, S, 3] against the hidden image [S, S, 3] (decisions), with the
  number of independent terms z sums, the p-value and what the null rests on: its estimate's mean, sd and
  largest z."""
  d = decisions(revealed[None], hidden[None], null_revealed, alpha)
  null_z = d["null_z"][:, 0]
  samples = phase_statistic.effective_samples(phase_statistic.whitened_spectra(revealed[None]),
                                              phase_statistic.whitened_spectra(hidden[None]))
  return dict(z=float(d["z"][0, 0]), effective_samples=float(samples[0, 0]),
              log10_p_model=float(d["log10_p_model"][0, 0]), log10_p_null_fit=float(d["log10_p_null_fit"][0, 0]),
              log10_p=float(d["log10_p"][0, 0]), p_value=float(10.0 ** d["log10_p"][0, 0]), alpha=float(alpha),
              owned=bool(d["owned"][0, 0]),
              null=dict(rests_on=NULL_RESTS_ON, count=int(null_z.size), mean=float(null_z.mean()),
                        sd=float(np.std(null_z, ddof=1)), max=float(null_z.max())))


def validate(config: ml_collections.ConfigDict) -> None:
  for name in ("ply", "key", "hidden"):
    if not config.reveal[name]:
      raise ValueError(f"reveal.{name} is required for verify")
  alpha = config.verify.alpha
  if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 < alpha < 1.0:
    raise ValueError(f"verify.alpha must be a probability strictly between 0 and 1, got {alpha!r}")
  settings.check_count("verify.null_views", config.verify.null_views, minimum=0)


def verify(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """The verify job: reveal at the key, test against the hidden image at verify.alpha (ownership_test), and
  the SSIM, with the calibrated threshold's decision when verify.calibration names a file."""
  validate(config)
  r = config.reveal
  scene = reveal.load_keyed_scene(r)
  revealed = scene.reveal_at([scene.camera])[0]
  size = revealed.shape[0]
  hidden = hidden_lib.load_hidden_image(r.hidden, size)
  nulls = null_reveals(scene.gaussians, scene.camera, scene.options, scene.reveal_fn, config.verify.null_views,
                       hidden)
  null_revealed = np.concatenate(list(nulls.values()))
  test = ownership_test(revealed, hidden, null_revealed, config.verify.alpha)
  test["null"]["sources"] = {name: int(images.shape[0]) for name, images in nulls.items()}
  score = float(metrics.ssim(revealed, hidden))
  result = dict(ply=r.ply, key=r.key, decoder=r.decoder, hidden=r.hidden, **test, ssim=score)
  if config.verify.calibration:
    calibration = load_calibration(config.verify.calibration)
    result["calibration"] = dict(calibration, owned=decide(score, calibration))
  if scene.alignment is not None:
    result["alignment"] = scene.alignment
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed)
  fileio.write_image(os.path.join(workdir, "hidden.png"), hidden)
  with fileio.atomic_path(os.path.join(workdir, "null_revealed.npz")) as path:
    with open(path, "wb") as f:
      np.savez_compressed(f, **nulls)
  fileio.write_json(os.path.join(workdir, VERIFY_FILE), result)
  return result
