"""The ownership test: is this scene marked with my hidden image? `--config.mode=verify`.

The decoder reveals R from the scene's render at the owner's key. The decoder's outputs on inputs that do not
carry the hidden image I (null_renders: the scene turned well away from the key, unrelated pictures) are its null
behaviour; decisions (the one formulation verify and `make bench-ownership` decide with) correlates what R holds
beyond their mean with I (robust.phase_statistic) and takes the larger of two p-values: the random-phase
model's and the Monte-Carlo p-value against those outputs correlated with I at every shift and turn. The scene
is owned when that p-value is at most verify.alpha. verify.json reports the statistic, both p-values, the
decision, what the null rests on, and the SSIM; a calibration file of measured SSIM scores (verify.calibration,
`make bench-robust`) adds its threshold's decision as further evidence. revealed.png, hidden.png and
null_revealed.npz are kept.
With reveal.owner set (the owner's copy of the marked scene), the suspect is first re-aligned onto it (conceal.align:
the key moved into its frame, its renders, the key's and the null views', mapped onto the owner's tone), tested
after each tone map and as rendered and decided on k times the smallest p-value of its k readings
(combined_log10_p); verify.json reports the transform, the tone maps and each reading's figures.
A scene may carry several of the owner's marks (verify.marks: conceal runs made one on the other's student, e.g. a
film that fine-tuning cannot reach beside a mark in the scene's own Gaussians that an extraction copies): each
is read, and the decision is on the best of all their readings, by the same correction.
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, message as message_lib, near, reveal
from conceal_jax.conceal import train as conceal_train
from conceal_jax.core import fileio, settings
from conceal_jax.gs import evaluate, metrics
from conceal_jax.robust import phase_statistic
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.render import RenderOptions, render

VERIFY_FILE = "verify.json"
MAX_FALSE_POSITIVE_RATE = 0.01
# The null views turn the key camera about its centre by angles spread over this range (degrees): beyond the
# decoys leakage control trains near the key (conceal.leakage.decoy_rotation_deg, up to 10), so that a marked
# scene's own views there are as unmarked as another scene's.
NULL_TURN_DEG = (15.0, 45.0)
NULL_SEED_BASE = 2_000_000  # seeds of the null views' turn axes, apart from leakage's and the decoys'
NULL_RESTS_ON = (
    "z is the phase correlation with the hidden image of the revealed image less the decoder's mean output on "
    "inputs that do not carry the mark (the scene turned away from the key, unrelated pictures), over its "
    "standard deviation under the random-phase model (N(0, 1)); the empirical null is z of those outputs, less "
    "the same mean, against the hidden image at every circular shift and in its 8 turns and mirrors, and its "
    "Monte-Carlo p-value; the p-value is the larger of the two")


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
  return [near.nearby_camera(camera, 0.0, float(angle), NULL_SEED_BASE + k) for k, angle in enumerate(angles)]


def unrelated_images(hidden: np.ndarray) -> np.ndarray:
  """[8 * n, S, S, 3] the eight flips and quarter turns of each scikit-image sample picture (hidden.SAMPLE_NAMES)
  at the size of the hidden image [S, S, 3], less any that is the hidden image itself (within 1/255 on average):
  pictures the scene was not marked with."""
  pictures = [hidden_lib.load_hidden_image(name, hidden.shape[0]) for name in hidden_lib.SAMPLE_NAMES]
  pictures = [p for p in pictures if np.abs(p - hidden).mean() >= 1.0 / 255]
  return np.stack([np.rot90(p[:, ::-1] if flip else p, turns) for p in pictures for flip in (False, True)
                   for turns in range(4)])


def null_renders(gaussians, camera: Camera, options: RenderOptions, views: int,
                 hidden: np.ndarray) -> dict[str, np.ndarray]:
  """The inputs a decoder reads for its null behaviour, none of which carries the hidden image [S, S, 3]:
  "unrelated_images" [K, S, S, 3] (unrelated_images, read as renders) and "turned_views" [views, H, W, 3], the
  scene `gaussians` rendered with `options` at null_cameras of the key `camera`."""
  out = dict(unrelated_images=unrelated_images(hidden))
  if views:
    out["turned_views"] = np.asarray(evaluate.render_images(gaussians, null_cameras(camera, views), options))
  return out


def read_nulls(reveal_fn, renders: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  """What a decoder (reveal_fn: renders [V, H, W, 3] -> [V, S, S, 3]) reveals from null_renders' inputs, by name."""
  return {name: np.asarray(reveal_fn(jnp.asarray(images))) for name, images in renders.items()}


def combined_log10_p(log10_ps) -> np.ndarray:
  """log10 of the p-value of a decision on the best of k readings of one scene [k, ...], each with its own valid
  p-value: k times the smallest (Bonferroni), at most 1. A scene re-aligned in tone is read after each tone map
  and as rendered, since a tone fitted to a blurred render also sharpens what the decoder reads."""
  log10_ps = np.asarray(log10_ps, np.float64)
  return np.minimum(log10_ps.min(0) + np.log10(len(log10_ps)), 0.0)


@dataclasses.dataclass(frozen=True)
class Reading:
  """One reading's test: the revealed images [V, S, S, 3], the null outputs by source ({name: [K, S, S, 3]}) and
  decisions' result against the hidden images."""
  revealed: np.ndarray
  nulls: dict
  result: dict


def read_and_decide(reveal_fn, checks, hidden: np.ndarray, renders: dict, alpha: float,
                    resolve: float = 1.0) -> Reading:
  """The check renders [V, H, W, 3] revealed through reveal_fn (renders -> [V, S, S, 3]) and decided against the
  hidden images [J, S, S, 3] (decisions), with the null outputs reveal_fn gives of `renders` (null_renders)."""
  revealed = np.asarray(reveal_fn(jnp.asarray(checks)))
  nulls = read_nulls(reveal_fn, renders)
  return Reading(revealed, nulls, decisions(revealed, hidden, np.concatenate(list(nulls.values())), alpha, resolve))


def decide_readings(readings: dict, checks, hidden: np.ndarray, renders: dict, alpha: float,
                    resolve: float = 1.0) -> tuple[dict, dict]:
  """The test as verify takes it of a scene with several readings ({name: reveal_fn}, reveal.KeyedScene.readings):
  each reading's read_and_decide, and their combination, one decision [V, J] on combined_log10_p: z (the largest),
  log10_p_model and log10_p (combined), owned (log10_p at most log10 alpha). ValueError where the null draws are
  too few for the combined p-value ever to reach alpha."""
  by_name = {name: read_and_decide(fn, checks, hidden, renders, alpha, resolve) for name, fn in readings.items()}
  draws = next(iter(by_name.values())).result["null_draws"]
  if len(readings) / (1 + draws) > alpha:
    raise ValueError(f"{draws} null draws cannot decide on the best of {len(readings)} readings at alpha {alpha} "
                     f"(its smallest p-value is {len(readings)}/{draws + 1}): more null outputs are needed "
                     f"(turned_views_needed with readings={len(readings)})")
  results = [reading.result for reading in by_name.values()]
  log_p = combined_log10_p([r["log10_p"] for r in results])
  return by_name, dict(z=np.max([r["z"] for r in results], axis=0), log10_p=log_p, owned=log_p <= np.log10(alpha),
                       log10_p_model=combined_log10_p([r["log10_p_model"] for r in results]))


def strongest(by_name: dict, hidden: np.ndarray) -> str:
  """The name of the reading of smallest p-value among decide_readings' readings of one image against one hidden
  image `hidden` [S, S, 3], and among those of equal p-value (a marked scene's readings all reach the Monte-Carlo
  p-value's floor) the one whose revealed image is closest to it (SSIM): the phase correlation z is blind to the
  contrast a tone map restores, which is what tells the readings of a faded film apart."""
  p_value = lambda name: by_name[name].result["log10_p"][0, 0]
  return min(by_name, key=lambda name: (p_value(name), -metrics.ssim(by_name[name].revealed[0], hidden)))


def summary(result: dict) -> dict:
  """z, log10_p and owned of one revealed image against one hidden image (a decisions or decide_readings
  result [1, 1]), as Python numbers."""
  return {name: result[name][0, 0].item() for name in ("z", "log10_p", "owned")}


def turned_views_needed(alpha: float, size: int, unrelated: int, null_views: int, readings: int = 1) -> int:
  """How many turned views verify renders: null_views, or more where the null outputs (`unrelated` pictures and
  the turned views) would give too few draws (8 K size^2, decisions) for a Monte-Carlo p-value at most alpha /
  readings, so that a decision on the best of `readings` readings (combined_log10_p) can still reach alpha."""
  return max(null_views, int(np.ceil((readings / alpha - 1.0) / (8 * size * size))) - unrelated)


def decisions(revealed: np.ndarray, hidden: np.ndarray, null_revealed: np.ndarray, alpha: float,
              resolve: float = 1.0) -> dict:
  """The ownership test of revealed images R [R, S, S, 3] against hidden images I [J, S, S, 3], given the
  decoder's outputs on K inputs that do not carry them, null_revealed [K, S, S, 3].

  What: m, the mean of the K outputs, is taken from R and from each output; z [R, J] is the phase correlation
  (phase_statistic.z_scores) of R - m with I. Its p-value is the larger of the random-phase model's, N(0, 1), and
  the Monte-Carlo p-value (phase_statistic.log_p_empirical) against the K outputs less m correlated with I
  circularly shifted by every (dy, dx) and in each of its 8 turns and mirrors (phase_statistic.z_surfaces,
  K * 8 * S^2 draws, enough that their smallest p-value 1 / (1 + draws) is at most alpha, else ValueError). Owned
  where that p-value is at most alpha.
  Why: taking m away leaves what the decoder reveals beyond what it emits whatever it reads, so a decoder whose
  fixed output resembles I scores nothing by it. The shifted and turned correlations are this decoder's and this
  scene's own null: z of R against I is exchangeable with them when R is one more output of the same kind placed
  at random against I, and they carry the heavy tail the random-phase model leaves out, where R and I both hold
  long edges (the scene's outlines passed through the decoder, a picture's contours) that happen to align.
  resolve: the empirical p-value is computed for the hidden images against which some R has a model p-value at
  most `resolve` (1: all); elsewhere log10_p_null is NaN and log10_p the model's, at most the decision's
  p-value, and the decision, needing both at most alpha, is exact while resolve >= alpha.
  Returns z, log10_p_model, log10_p_null, log10_p [R, J], owned [R, J], null_draws (n) and null_max [J] (the
  largest null draw, NaN where not computed)."""
  if not alpha <= resolve <= 1.0:
    raise ValueError(f"resolve must lie in [alpha, 1] for the decision to be exact, got {resolve} (alpha {alpha})")
  draws = 8 * len(null_revealed) * hidden.shape[1] * hidden.shape[2]
  if 1.0 / (1 + draws) > alpha:
    raise ValueError(f"{len(null_revealed)} null outputs give {draws} draws, whose smallest Monte-Carlo p-value "
                     f"1/{draws + 1} is above alpha {alpha}: more null outputs (verify.null_views) are needed")
  mean = np.asarray(null_revealed, np.float64).mean(0)
  target = phase_statistic.whitened_spectra(hidden)
  z = phase_statistic.z_scores(phase_statistic.whitened_spectra(revealed - mean), target)
  log_model = phase_statistic.log_p_model(z) / np.log(10)
  null_spectra = phase_statistic.whitened_spectra(null_revealed - mean)
  log_null = np.full(z.shape, np.nan)
  null_max = np.full(z.shape[1], np.nan)
  for j in np.nonzero((log_model <= np.log10(resolve)).any(0))[0]:
    null_z = phase_statistic.z_surfaces(null_spectra, phase_statistic.whitened_spectra(phase_statistic.dihedral(
        hidden[j])))
    log_null[:, j] = phase_statistic.log_p_empirical(z[:, j], null_z) / np.log(10)
    null_max[j] = null_z.max()
  log_p = np.fmax(log_model, log_null)
  return dict(z=z, log10_p_model=log_model, log10_p_null=log_null, log10_p=log_p, owned=log_p <= np.log10(alpha),
              null_draws=draws, null_max=null_max)


def ownership_test(reading: Reading, hidden: np.ndarray, alpha: float) -> dict:
  """The report of a reading of one revealed image against the hidden image [S, S, 3] (read_and_decide): the
  statistic, the number of independent terms it sums, the p-values, the decision and what the null rests on:
  how many outputs and draws, and the largest draw."""
  d, null_revealed = reading.result, np.concatenate(list(reading.nulls.values()))
  mean = np.asarray(null_revealed, np.float64).mean(0)
  samples = phase_statistic.effective_samples(phase_statistic.whitened_spectra(reading.revealed[:1] - mean),
                                              phase_statistic.whitened_spectra(hidden[None]))
  return dict(z=float(d["z"][0, 0]), effective_samples=float(samples[0, 0]),
              log10_p_model=float(d["log10_p_model"][0, 0]), log10_p_null=float(d["log10_p_null"][0, 0]),
              log10_p=float(d["log10_p"][0, 0]), p_value=float(10.0 ** d["log10_p"][0, 0]), alpha=float(alpha),
              owned=bool(d["owned"][0, 0]),
              null=dict(rests_on=NULL_RESTS_ON, count=int(len(null_revealed)), draws=int(d["null_draws"]),
                        max=float(d["null_max"][0]),
                        sources={name: int(images.shape[0]) for name, images in reading.nulls.items()}))


def mark_sections(config: ml_collections.ConfigDict) -> list[ml_collections.ConfigDict]:
  """The reveal section of each mark verify tests the scene for: config.reveal's, then one per conceal run folder of
  verify.marks (comma-separated), reveal's with that run's key.json, decoder.msgpack (where it has one) and
  hidden.png. ValueError naming a folder without its key or hidden image."""
  sections = [config.reveal]
  for folder in filter(None, (name.strip() for name in config.verify.marks.split(","))):
    r = ml_collections.ConfigDict(config.reveal.to_dict())
    r.key, r.hidden, r.key_number = (os.path.join(folder, conceal_train.KEY_FILE),
                                     os.path.join(folder, conceal_train.HIDDEN_FILE), 0)
    missing = [path for path in (r.key, r.hidden) if not os.path.isfile(path)]
    if missing:
      raise ValueError(f"verify.marks: {folder} is not the folder of a conceal run (no {' or '.join(missing)})")
    decoder = os.path.join(folder, conceal_train.DECODER_FILE)
    r.decoder = decoder if os.path.isfile(decoder) else ""
    sections.append(r)
  return sections


def validate(config: ml_collections.ConfigDict) -> None:
  for name in ("ply", "key", "hidden"):
    if not config.reveal[name]:
      raise ValueError(f"reveal.{name} is required for verify")
  alpha = config.verify.alpha
  if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 < alpha < 1.0:
    raise ValueError(f"verify.alpha must be a probability strictly between 0 and 1, got {alpha!r}")
  settings.check_count("verify.null_views", config.verify.null_views, minimum=0)
  if not isinstance(config.verify.marks, str):
    raise ValueError(f"verify.marks must be comma-separated folders of conceal runs, got {config.verify.marks!r}")
  mark_sections(config)


@dataclasses.dataclass(frozen=True)
class MarkTest:
  """One mark's test (decide_mark): its reveal section, the keyed scene (reveal.KeyedScene), the hidden image
  [S, S, 3], each reading's Reading by name and their combination (decide_readings)."""
  section: ml_collections.ConfigDict
  scene: reveal.KeyedScene
  hidden: np.ndarray
  by_name: dict
  both: dict

  @property
  def log10_p(self) -> float:
    """The p-value of a decision on this mark alone (its readings combined), log10."""
    return float(self.both["log10_p"][0, 0])

  @property
  def strongest(self) -> Reading:
    return self.by_name[strongest(self.by_name, self.hidden)]

  @property
  def ssim(self) -> float:
    """SSIM of the strongest reading's revealed image to the hidden image."""
    return float(metrics.ssim(self.strongest.revealed[0], self.hidden))


def decide_mark(section: ml_collections.ConfigDict, scene, alpha: float, null_views: int, readings: int) -> MarkTest:
  """The ownership test of one mark (its reveal `section`, its keyed `scene`): its check render revealed in each
  reading and decided against the hidden image with null outputs enough for a decision on the best of `readings`
  readings in all (turned_views_needed)."""
  check = render(scene.gaussians, scene.camera, scene.options).rgb[None]
  size = jax.eval_shape(scene.reveal_fn, check).shape[1]  # the decoder's output size, without decoding
  hidden = hidden_lib.load_hidden_image(section.hidden, size)
  views = turned_views_needed(alpha, size, len(unrelated_images(hidden)), null_views, readings)
  renders = null_renders(scene.gaussians, scene.camera, scene.options, views, hidden)
  by_name, both = decide_readings(scene.readings, check, hidden[None], renders, alpha)
  return MarkTest(section, scene, hidden, by_name, both)


def verify(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """The verify job: reveal at the key, test against the hidden image at verify.alpha (ownership_test), and
  the SSIM, with the calibrated threshold's decision when verify.calibration names a file; with a key of
  message mode, the message read back (bit accuracy, binomial p-value, the corrected message). A scene re-aligned
  in tone is tested in every reading (reveal.KeyedScene.readings); with verify.marks, every mark is tested
  (mark_sections, decide_mark). The decision is on combined_log10_p of all the readings of all the marks, reported
  with the images and figures of the mark and reading of smallest p-value (then largest SSIM), and with each
  mark's own figures under `marks` where there are several."""
  validate(config)
  alpha = config.verify.alpha
  sections = mark_sections(config)
  scenes = []
  for r in sections:  # every section reads reveal's ply with reveal's owner: one registration serves every key
    scenes.append(reveal.load_keyed_scene(r, scenes[0].registration if scenes else None))
  count = sum(len(scene.readings) for scene in scenes)
  tests = [decide_mark(r, scene, alpha, config.verify.null_views, count) for r, scene in zip(sections, scenes)]
  mark = min(tests, key=lambda t: (t.log10_p, -t.ssim))
  r, best, hidden = mark.section, mark.strongest, mark.hidden
  revealed, nulls, test = best.revealed[0], best.nulls, ownership_test(best, hidden, alpha)
  log10_p = float(combined_log10_p([reading.result["log10_p"][0, 0] for t in tests for reading in t.by_name.values()]))
  test.update(log10_p=log10_p, p_value=10.0 ** log10_p, owned=bool(log10_p <= np.log10(alpha)),
              readings={name: summary(reading.result) for name, reading in mark.by_name.items()})
  score = mark.ssim
  result = dict(ply=r.ply, key=r.key, decoder=r.decoder, hidden=r.hidden, **test, ssim=score)
  if len(tests) > 1:
    result["marks"] = [dict(key=t.section.key, decoder=t.section.decoder, hidden=t.section.hidden,
                            log10_p=t.log10_p, ssim=t.ssim) for t in tests]
  if config.verify.calibration:
    calibration = load_calibration(config.verify.calibration)
    result["calibration"] = dict(calibration, owned=decide(score, calibration))
  if mark.scene.alignment is not None:
    result["alignment"] = mark.scene.alignment
  hidden_message = message_lib.message_of_key(key_lib.load_key(r.key, r.key_number)[1])
  if hidden_message is not None:  # message mode: the bits read back, beside the test of their image
    result["message"] = message_lib.read_message(revealed, hidden_message)
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed)
  fileio.write_image(os.path.join(workdir, "hidden.png"), hidden)
  with fileio.atomic_path(os.path.join(workdir, "null_revealed.npz")) as path:
    with open(path, "wb") as f:
      np.savez_compressed(f, **nulls)
  fileio.write_json(os.path.join(workdir, VERIFY_FILE), result)
  return result
