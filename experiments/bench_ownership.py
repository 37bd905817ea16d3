"""Ownership as a statistical test (issue 40): the false-positive rate of verify's decision measured over clean
trials, the clean statistics against the null the test predicts, and the true-positive rate under attacks.

  make bench-ownership
  make bench-ownership BENCH_ARGS="--poses=10"      # fewer clean renders per scene

Decoders: every finished conceal run of --runs (its decoder, key and hidden image I; missing runs are skipped
with a note). Clean scenes: the teachers of --clean (train workdirs never marked: other seeds, other scenes). A
clean trial pairs what a decoder reveals from a clean scene (at the decoder's key, at --poses orbit poses and at
the scene's test views) with a hidden image the scene was not marked with: the decoder's own I, circular shifts
of I, and crops of the scikit-image pictures, turned and flipped. Each trial is decided as verify decides given
the owner's copy of the marked scene (reveal.owner: the clean render mapped onto the tone of the marked student's
render at the same camera, conceal.align.fit_tone; robust.ownership.decisions at --alpha, with the decoder's
outputs on the unrelated pictures and on the clean scene turned away from the decoder's key, through the same map,
as its null), the empirical p-value computed where the model's is at most
RESOLVE (below it, the decision's p-value is exact; above, the model's stands in, a lower bound). Trials of one
(decoder, scene) pair share the decoder and the renders, and every demo decoder passes much of the render through:
they are not independent, and the JSON counts the pairs and the false positives per pair. Marked trials: the
student of each --marked run under every mild and medium attack of the robustness harness (image attacks on the
check render, model attacks on the scene), each with the null verify would draw from that attacked scene, decided
with the owner's copy (the untouched student) and without it (`unaligned`, tpr_at_alpha_unaligned).

Each (decoder, scene) pair's trials are kept in --cache (an .npz per pair, keyed by the settings), so a run
stopped part way resumes where it was.

Message mode: each finished message-mode run of --message-runs (conceal/message.py) gives, per scene and message
length, the raw bit accuracy, whether the corrected message is exact, the render PSNR beside the teacher's, and
verify on the student and on a clean scene (its own teacher) read with the same key.

Writes ownership_bench.json (clean_trials, false_positives, alpha, tpr_at_alpha per marked run, message rows per
scene and length, the rows behind them), ownership_bench.png (the clean trials' p-values against the uniform, log
scale; their z against N(0, 1)) and ownership_tpr.png (the marked trials' z against the threshold) to --out.
--messages-only and --marked-only refresh those rows alone, keeping the rest of the JSON; a full run replaces the
clean trials and keeps the stored marked and message rows of runs it does not find.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import pathlib

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from scipy import stats

from conceal_jax.conceal import align, hidden as hidden_lib, key as key_lib, message, reveal
from conceal_jax.configs import default
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, metrics
from conceal_jax.robust import image_attacks, model_attacks, ownership, robustness
from experiments import bench_robust

DEFAULT_RUNS = ("workdirs/demo/conceal,workdirs/survive_runs/demo_film,workdirs/survive_runs/demo_film_far_sh,"
                "workdirs/survive_runs/demo_drift,workdirs/survive_runs/demo_orbit,workdirs/survive_runs/lego_film,"
                "workdirs/bench/lego/conceal_in_scene_w16")
DEFAULT_MARKED = ("workdirs/demo/conceal,workdirs/survive_runs/demo_pruned,workdirs/survive_runs/lego_film,"
                  "workdirs/bench/lego/conceal_in_scene_w16")
DEFAULT_CLEAN = "workdirs/demo/teacher,workdirs/demo_seed1/teacher,workdirs/bench/lego/teacher"
# message mode (mark.message_bits): demo concealments of 32 and 48 bits and lego's of 48, e.g.
#   python -m conceal_jax.main --config=conceal_jax/configs/demo.py --workdir=workdirs/message/demo_32 \
#     --config.mode=conceal --config.mark.teacher=workdirs/demo/teacher/point_cloud.ply --config.mark.message_bits=32
#   python -m conceal_jax.main --config=conceal_jax/configs/lego_conceal.py --workdir=workdirs/message/lego_48_10k \
#     --config.mark.teacher=workdirs/bench/lego/teacher/point_cloud.ply --config.mark.message_bits=48
# (lego_48: the same shortened to --config.conceal.iterations=3000). Of two runs of one scene and length, the later
# in the list gives the row.
DEFAULT_MESSAGE_RUNS = ("workdirs/message/demo_32,workdirs/message/demo_48,workdirs/message/lego_32,"
                        "workdirs/message/lego_48,workdirs/message/lego_32_10k,workdirs/message/lego_48_10k")
MARKED_SEVERITIES = bench_robust.MARKED_SEVERITIES
SHIFTS = 16  # circular shifts of each decoder's I among the hidden images of its clean trials
CROPS = 16  # crops of each scikit-image picture among them
RESOLVE = 1e-3  # clean trials get the empirical p-value where the model's is at most this (ownership.decisions)
TOP = 20  # the clean trials of highest z kept in the JSON, with what they were


def saved_config(workdir: pathlib.Path) -> ml_collections.ConfigDict:
  """The config a run saved, over today's defaults (keys added since take the values that leave it as it was)."""
  config = default.get_config()
  config.update(json.loads((workdir / "config.json").read_text()))
  return config


def clean_hidden_images(hidden: np.ndarray, seed: int = 0) -> tuple[np.ndarray, list[str]]:
  """[1 + SHIFTS + CROPS * n, S, S, 3] hidden images no clean scene was marked with, and their names: I itself,
  its circular shifts (each by at least S/8 in some direction) and crops (40 to 75% of the side, at random
  places, turned and flipped, resized to S) of the scikit-image pictures other than I."""
  rng = np.random.default_rng(seed)
  size = hidden.shape[0]
  images, names = [hidden], ["I"]
  for k in range(SHIFTS):
    shift = rng.integers(size // 8, size - size // 8, 2)
    images.append(np.roll(hidden, tuple(shift), (0, 1)))
    names.append(f"I shifted {tuple(int(s) for s in shift)}")
  for name in hidden_lib.SAMPLE_NAMES:
    picture = hidden_lib.load_hidden_image(name, 4 * size)
    if np.abs(hidden_lib.resize_square(picture, size) - hidden).mean() < 1.0 / 255:
      continue
    for k in range(CROPS):
      side = int(rng.uniform(0.4, 0.75) * picture.shape[0])
      y, x = rng.integers(0, picture.shape[0] - side + 1, 2)
      crop = np.rot90(picture[y:y + side, x:x + side][:, ::-1] if k % 2 else picture[y:y + side, x:x + side], k // 2)
      images.append(hidden_lib.resize_square(np.ascontiguousarray(crop), size))
      names.append(f"{name} crop {k}")
  return np.stack(images).astype(np.float32), names


def clean_scene(workdir: pathlib.Path, poses: int, test_views: int) -> dict:
  """A clean teacher: its Gaussians and the cameras its trials render (orbit poses, test views)."""
  config = saved_config(workdir)
  scene = evaluate.load_scene_data(config)
  cameras = [key_lib.orbit_camera(scene.train_cameras, 5000 + seed) for seed in range(poses)]
  cameras += list(evaluate.held_out_views(scene, test_views)[0])
  return dict(name=str(workdir), gaussians=jax.tree.map(jnp.asarray, ply.load_ply(str(workdir / "point_cloud.ply"))),
              cameras=cameras)


def pair_trials(owner, hidden: np.ndarray, scene: dict, alpha: float, null_views: int, marked=None) -> dict:
  """The clean trials of one decoder (owner) on one clean scene: revealed at the decoder's key and at the scene's
  cameras [V], against the hidden images [J] (ownership.decisions, resolved at RESOLVE): z, log10_p_model,
  log10_p (the decision's), owned, each [V, J]. With `marked` (the owner's copy of the marked scene), each view is
  read as verify with reveal.owner reads a suspect at its key: mapped onto the tone of the marked scene's render at
  its camera (align.fit_tone, its null outputs through the same map) and as rendered, decided on both (combined)."""
  fields = ("z", "log10_p_model", "log10_p", "owned")
  # the key may be another scene's (another image size): rendered apart from the scene's own cameras
  groups = ([owner.check_camera], scene["cameras"])
  renders = [np.asarray(evaluate.render_images(scene["gaussians"], cameras, owner.options)) for cameras in groups]
  nulls = ownership.null_renders(scene["gaussians"], owner.check_camera, owner.options, null_views, owner.hidden)
  if marked is None:
    results = [ownership.read_and_decide(owner.reveal_renders, group, hidden, nulls, alpha, RESOLVE).result
               for group in renders]
  else:
    references = [np.asarray(evaluate.render_images(marked, cameras, owner.options)) for cameras in groups]
    pairs = [(image, reference) for group, refs in zip(renders, references) for image, reference in zip(group, refs)]
    readings = lambda image, ref: reveal.readings(owner.reveal_renders, dict(toned=align.fit_tone(image, ref)))
    results = [ownership.decide_readings(readings(image, reference), image[None], hidden, nulls, alpha, RESOLVE)[1]
               for image, reference in pairs]
  return {name: np.concatenate([result[name] for result in results]) for name in fields}


def cached_pair_trials(cache: pathlib.Path, run: pathlib.Path, owner, hidden: np.ndarray, scene: dict, alpha: float,
                       null_views: int, settings: str, marked=None) -> dict:
  """pair_trials, read from `cache` when this pair was run with the same settings, else run and saved there."""
  tag = hashlib.sha1(f"{run.resolve()}|{scene['name']}|{settings}".encode()).hexdigest()[:16]
  path = cache / f"{run.name}_{pathlib.Path(scene['name']).parent.name}_{tag}.npz"
  if path.is_file():
    with np.load(path) as saved:
      return {name: saved[name] for name in saved.files}
  result = pair_trials(owner, hidden, scene, alpha, null_views, marked)
  cache.mkdir(parents=True, exist_ok=True)
  with fileio.atomic_path(str(path)) as tmp:
    with open(tmp, "wb") as f:
      np.savez_compressed(f, **result)
  return result


def clean_trials(run: pathlib.Path, scenes: list[dict], alpha: float, null_views: int, cache: pathlib.Path,
                 settings: str) -> dict:
  """Every clean trial of one decoder: each clean scene at the decoder's key and at the scene's own cameras, against
  clean_hidden_images; returns the z and p-values flattened, per scene its count and false positives, the trials
  of highest z, and the own-I trials apart."""
  _, student, owner = bench_robust.load_run(run)
  hidden, names = clean_hidden_images(owner.hidden)
  z, log_model, log_p, owned, own, pairs, top = [], [], [], [], [], [], []
  for scene in scenes:
    result = cached_pair_trials(cache, run, owner, hidden, scene, alpha, null_views, settings,
                                jax.tree.map(jnp.asarray, student))
    z.append(result["z"].ravel())
    log_model.append(result["log10_p_model"].ravel())
    log_p.append(result["log10_p"].ravel())
    owned.append(result["owned"].ravel())

    def row(v, j):
      return dict(scene=scene["name"], view="key" if v == 0 else f"view {v}", hidden=names[j],
                  z=float(result["z"][v, j]), log10_p_model=float(result["log10_p_model"][v, j]),
                  log10_p=float(result["log10_p"][v, j]), owned=bool(result["owned"][v, j]))

    own += [row(v, 0) for v in range(result["z"].shape[0])]
    order = np.argsort(result["z"], axis=None)[::-1][:TOP]
    top += [dict(row(*np.unravel_index(i, result["z"].shape)), decoder=str(run)) for i in order]
    pairs.append(dict(decoder=str(run), scene=scene["name"], trials=int(result["z"].size),
                      false_positives=int(result["owned"].sum()),
                      false_positives_model=int(np.sum(result["log10_p_model"] <= np.log10(alpha))),
                      max_z=float(result["z"].max())))
    print(f"{run} x {scene['name']}: {result['z'].size} trials, {int(result['owned'].sum())} decided owned, "
          f"max z {result['z'].max():.2f} (own I: {result['z'][:, 0].max():.2f})", flush=True)
  return dict(z=np.concatenate(z), log10_p_model=np.concatenate(log_model), log10_p=np.concatenate(log_p),
              owned=np.concatenate(owned), own=own, pairs=pairs, top=top, hidden_names=names)


def attacked_checks(student, owner):
  """(kind, attack, level, severity, check render [H, W, 3], scene) for the student untouched ("none") and under
  each mild and medium attack: image attacks on its check render (scene: the student), model attacks on the scene."""
  levels = [level for level in image_attacks.LEVELS if level[2] in MARKED_SEVERITIES]
  checks = robustness.attacked_check_renders(student, owner, levels)
  yield "none", "none", None, "none", checks[0], student
  for (name, level, severity), image in zip(levels, checks[1:]):
    yield "image", name, level, severity, image, student
  levels = [level for level in model_attacks.LEVELS if level[2] in MARKED_SEVERITIES]
  for name, level, severity, _, scene in robustness.attacked_scenes(student, levels):
    if name != "none":
      yield "model", name, level, severity, np.asarray(evaluate.render_images(scene, [owner.check_camera],
                                                                              owner.options))[0], scene


def decision_row(reading: ownership.Reading, hidden: np.ndarray) -> dict:
  """z, p-values, the decision and the SSIM of a reading of one revealed image (ownership.read_and_decide)."""
  revealed, result = reading.revealed, reading.result
  return dict(z=float(result["z"][0, 0]), log10_p=float(result["log10_p"][0, 0]),
              log10_p_model=float(result["log10_p_model"][0, 0]), log10_p_null=float(result["log10_p_null"][0, 0]),
              owned=bool(result["owned"][0, 0]), ssim=float(metrics.ssim(revealed[0], hidden)))


def marked_trials(run: pathlib.Path, alpha: float, null_views: int) -> list[dict]:
  """The student of `run` under each mild and medium attack (attacked_checks), decided as verify decides given the
  owner's copy (the untouched student): read toned (each check render mapped onto its tone, align.fit_tone, the
  null outputs through the same map) and as rendered, on the combined p-value, with the figures of the reading of
  smaller p; with the null verify would draw from the (attacked) scene. `toned` and `unaligned` (as rendered: what
  verify decides without the owner's copy) are each reading alone. One row per attack level."""
  _, student, owner = bench_robust.load_run(run)
  student = jax.tree.map(jnp.asarray, student)
  hidden = owner.hidden
  rows, nulls, reference = [], None, None
  for kind, name, level, severity, check, scene in attacked_checks(student, owner):
    reference = check if reference is None else reference
    if kind != "image" or nulls is None:  # image attacks leave the scene, and so its null, as it is
      nulls = ownership.null_renders(scene, owner.check_camera, owner.options, null_views, hidden)
    tone = align.fit_tone(check, reference)
    by_name, both = ownership.decide_readings(reveal.readings(owner.reveal_renders, dict(toned=tone)), check[None],
                                              hidden[None], nulls, alpha)
    best = by_name[ownership.strongest(by_name, hidden)]
    rows.append(dict(kind=kind, attack=name, level=level, severity=severity,
                     **dict(decision_row(best, hidden), log10_p=float(both["log10_p"][0, 0]),
                            owned=bool(both["owned"][0, 0])),
                     tone=tone.report(), toned=decision_row(by_name["toned"], hidden),
                     unaligned=decision_row(by_name["as_rendered"], hidden)))
  print(f"{run}: {sum(r['owned'] for r in rows[1:])} of {len(rows) - 1} attacked trials decided owned, lowest z "
        f"{min(r['z'] for r in rows[1:]):.2f} (without the owner's copy: "
        f"{sum(r['unaligned']['owned'] for r in rows[1:])})", flush=True)
  return rows


def true_positive_rates(marked: dict, unaligned: bool = False) -> dict:
  """{run: the share of its attacked trials decided owned} of marked_trials' rows per run (`unaligned`: decided
  without the owner's copy, for the runs whose rows hold it)."""
  return {run: float(np.mean([(r["unaligned"] if unaligned else r)["owned"] for r in rows if r["kind"] != "none"]))
          for run, rows in marked.items() if not unaligned or all("unaligned" in r for r in rows)}


def message_row(run: pathlib.Path, clean_ply: str | None, alpha: float, scratch: pathlib.Path) -> dict:
  """A message-mode concealment: the message read from the student at the key (message.json), the render against
  the teacher's (metrics.json), the message read under each mild and medium attack (attacked_checks, without
  re-alignment), and verify (ownership test + message) on the student and on a clean scene read with the same key
  and decoder: `clean_ply`, or the run's own teacher, which was never marked."""
  metrics = json.loads((run / "metrics.json").read_text())
  read = json.loads((run / "message.json").read_text())
  config = saved_config(run)
  clean_ply = clean_ply or config.mark.teacher
  row = dict(run=str(run), scene=pathlib.Path(config.data.path).name, bits=read["bits"], code=read["code"],
             corrects=read["corrects"],
             bit_accuracy=read["raw_bit_accuracy"], message_exact=read["message_exact"],
             errors_corrected=read["errors_corrected"], log10_p_binomial=read["log10_p_binomial"],
             render_psnr=metrics["student_vs_ground_truth"]["psnr"],
             teacher_psnr=metrics["teacher_vs_ground_truth"]["psnr"], hidden_ssim=metrics["hidden"]["ssim"],
             leakage=metrics["leakage"])
  _, student, owner = bench_robust.load_run(run)
  hidden_message = message.message_of_key(key_lib.load_key(str(run / "key.json"))[1])
  row["attacks"] = []
  for kind, name, level, severity, check, _ in attacked_checks(jax.tree.map(jnp.asarray, student), owner):
    read_back = message.read_message(np.asarray(owner.reveal_renders(jnp.asarray(check[None])))[0], hidden_message)
    row["attacks"].append(dict(kind=kind, attack=name, level=level, severity=severity,
                               bit_accuracy=read_back["raw_bit_accuracy"], message_exact=read_back["message_exact"]))
  attacked = [a for a in row["attacks"] if a["kind"] != "none"]
  row["attacked_exact"] = f"{sum(a['message_exact'] for a in attacked)} of {len(attacked)}"
  row["attacked_min_bit_accuracy"] = min(a["bit_accuracy"] for a in attacked)
  for name, scene in (("verify_student", str(run / "student.ply")), ("verify_clean", clean_ply)):
    if not pathlib.Path(scene).is_file():
      continue
    config = default.get_config()
    config.mode, config.verify.alpha = "verify", alpha
    config.reveal.ply, config.reveal.key, config.reveal.decoder = scene, str(run / "key.json"), str(
        run / "decoder.msgpack")
    config.reveal.hidden = str(run / "hidden.png")
    (scratch / f"{run.name}_{name}").mkdir(parents=True, exist_ok=True)
    verified = ownership.verify(config, str(scratch / f"{run.name}_{name}"))
    row[name] = dict(scene=scene, owned=verified["owned"], log10_p=verified["log10_p"], z=verified["z"],
                     bit_accuracy=verified["message"]["raw_bit_accuracy"],
                     log10_p_binomial=verified["message"]["log10_p_binomial"],
                     decoded=verified["message"]["decoded"], message_exact=verified["message"]["message_exact"])
  print(f"{run}: {row['bits']} bits, raw bit accuracy {row['bit_accuracy']:.4f}, exact {row['message_exact']}, "
        f"render {row['render_psnr']:.2f} dB (teacher {row['teacher_psnr']:.2f}), exact under attacks "
        f"{row['attacked_exact']}", flush=True)
  return row


def merged_messages(stored: dict, found: dict) -> dict:
  """Message rows by scene and length: the runs found replace their (scene, length) rows; the others' rows stay."""
  return {scene: dict(stored.get(scene, {}), **found.get(scene, {})) for scene in sorted(set(stored) | set(found))}


def tail_counts(log10_p: np.ndarray) -> list[dict]:
  """Clean trials with a p-value at most 10^-k against the count the null predicts, k = 1 .. 6."""
  return [dict(p_at_most=10.0 ** -k, observed=int(np.sum(log10_p <= -k)), predicted=float(log10_p.size * 10.0 ** -k))
          for k in range(1, 7)]


def _pyplot():
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  return plt


def plot(clean_log_model: np.ndarray, clean_log_p: np.ndarray, clean_z: np.ndarray, own_z: np.ndarray, alpha: float,
         path: pathlib.Path):
  """The clean trials: their p-values against the uniform (QQ, log scale) and their z against N(0, 1)."""
  fig, (qq, hist) = _pyplot().subplots(1, 2, figsize=(12, 5))
  n = clean_log_p.size
  ranks = np.arange(n, 0, -1)  # the largest -log10 p has rank 1
  expected = -np.log10(ranks / (n + 1))
  band = -np.log10(stats.beta.ppf([[0.025], [0.975]], ranks, n - ranks + 1))
  qq.fill_between(expected, band[1], band[0], color="0.85", label="95% band of the null's order statistics")
  qq.plot(expected, np.sort(-clean_log_model), ".", ms=2, label=f"{n} clean trials, random-phase model's p")
  qq.plot(expected, np.sort(-clean_log_p), ".", ms=2,
          label=f"the decision's p (exact below {RESOLVE:g}; above, the model's)")
  qq.plot([0, expected.max()], [0, expected.max()], "k--", lw=1, label="predicted null (uniform p)")
  qq.axhline(-np.log10(alpha), color="r", lw=1, label=f"alpha = {alpha:g}")
  qq.set_xlabel("predicted -log10 p (uniform order statistics)")
  qq.set_ylabel("observed -log10 p")
  qq.set_title("clean trials against the predicted null")
  qq.legend(fontsize=7)
  bins = np.linspace(min(-6.0, clean_z.min()), max(6.0, clean_z.max()), 121)
  hist.hist(clean_z, bins=bins, density=True, log=True, alpha=0.6, label="clean trials, every hidden image")
  hist.hist(own_z, bins=bins, density=True, log=True, alpha=0.6, label="clean trials, the decoder's own I")
  grid = np.linspace(bins[0], bins[-1], 400)
  hist.plot(grid, stats.norm.pdf(grid), "k", lw=1, label="N(0, 1)")
  hist.axvline(stats.norm.isf(alpha), color="r", lw=1, label=f"z at alpha = {alpha:g}")
  hist.set_ylim(0.1 / clean_z.size, 1)
  hist.set_xlabel("z")
  hist.legend(fontsize=7)
  hist.set_title("clean z")
  fileio.save_figure(fig, path)


def plot_marked(marked: dict, alpha: float, path: pathlib.Path):
  """The marked trials: each run's attacked students' z against the threshold."""
  fig, bars = _pyplot().subplots(1, 1, figsize=(7, 1.5 + 0.6 * len(marked)))
  for i, (run, rows) in enumerate(marked.items()):
    rows = [r for r in rows if r["kind"] != "none"]
    bars.plot([r["z"] for r in rows], [i + 0.3 * (k / max(len(rows) - 1, 1) - 0.5) for k in range(len(rows))],
              "o", ms=3, label=run)
  bars.axvline(stats.norm.isf(alpha), color="r", lw=1, label=f"z at alpha = {alpha:g} (model)")
  bars.set_yticks(range(len(marked)), [pathlib.Path(r).name for r in marked], fontsize=7)
  bars.set_xscale("symlog")
  bars.set_xlabel("z of the attacked student (mild and medium attacks; decided on the p-value, not z)")
  bars.legend(fontsize=7)
  bars.set_title("marked trials")
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--runs", default=DEFAULT_RUNS, help="comma-separated conceal workdirs: the decoders")
  parser.add_argument("--marked", default=DEFAULT_MARKED,
                      help="comma-separated conceal workdirs attacked for the true-positive rate")
  parser.add_argument("--clean", default=DEFAULT_CLEAN, help="comma-separated teacher workdirs never marked")
  parser.add_argument("--poses", type=int, default=25, help="orbit poses rendered per clean scene")
  parser.add_argument("--test-views", type=int, default=10, help="test views rendered per clean scene")
  parser.add_argument("--alpha", type=float, default=default.get_config().verify.alpha)
  parser.add_argument("--null-views", type=int, default=default.get_config().verify.null_views)
  parser.add_argument("--cache", default="workdirs/bench/ownership_cache",
                      help="where each (decoder, scene) pair's trials are kept, to resume")
  parser.add_argument("--message-runs", default=DEFAULT_MESSAGE_RUNS,
                      help="comma-separated conceal workdirs of message mode")
  parser.add_argument("--message-clean", default="",
                      help="a clean scene's .ply the message runs' keys are also read from (default: each run's "
                           "own teacher, never marked)")
  parser.add_argument("--messages-only", action="store_true",
                      help="refresh only the message rows of the --message-runs found in --out's ownership_bench.json, "
                           "keeping the other scenes' and lengths' rows (the message runs finish apart from the clean "
                           "trials)")
  parser.add_argument("--marked-only", action="store_true",
                      help="refresh only the marked trials and true-positive rates of the --marked runs found, "
                           "keeping the other runs' rows of --out's ownership_bench.json (and ownership_tpr.png)")
  args = parser.parse_args()
  if not 0 < args.alpha < 1:
    raise SystemExit(f"--alpha must be strictly between 0 and 1, got {args.alpha}")
  out = pathlib.Path(args.out)

  def message_rows() -> dict:
    runs = [pathlib.Path(p) for p in args.message_runs.split(",")
            if p and (pathlib.Path(p) / "message.json").is_file()]
    rows = [message_row(run, args.message_clean or None, args.alpha, pathlib.Path(args.cache) / "message_verify")
            for run in runs]
    return {scene: {str(row["bits"]): row for row in rows if row["scene"] == scene}
            for scene in sorted({row["scene"] for row in rows})}

  def present(paths: str, files: tuple[str, ...]) -> list[pathlib.Path]:
    found = []
    for path in (pathlib.Path(p) for p in paths.split(",") if p):
      if all((path / f).is_file() for f in files):
        found.append(path)
      else:
        print(f"skipping {path}: no {' / '.join(files)} there")
    return found

  run_files = ("student.ply", "decoder.msgpack", "key.json", "config.json")
  if args.messages_only or args.marked_only:
    result = json.loads((out / "ownership_bench.json").read_text())
    if args.messages_only:
      result["message"] = merged_messages(result.get("message", {}), message_rows())
    if args.marked_only:
      found = {str(run): marked_trials(run, args.alpha, args.null_views) for run in present(args.marked, run_files)}
      result["marked"] = dict(result["marked"], **found)
      result["tpr_at_alpha"] = true_positive_rates(result["marked"])
      result["tpr_at_alpha_unaligned"] = true_positive_rates(result["marked"], unaligned=True)
      plot_marked(result["marked"], args.alpha, out / "ownership_tpr.png")
    fileio.write_json(out / "ownership_bench.json", result)
    return
  runs, marked = present(args.runs, run_files), present(args.marked, run_files)
  stored = out / "ownership_bench.json"  # the marked and message rows of runs not found here stay
  stored_result = json.loads(stored.read_text()) if stored.is_file() else {}
  teachers = present(args.clean, ("point_cloud.ply", "config.json"))
  scenes = [clean_scene(path, args.poses, args.test_views) for path in teachers]
  if not runs or not scenes:
    raise SystemExit("bench-ownership needs at least one conceal run and one clean teacher")
  settings = (f"poses={args.poses} test_views={args.test_views} alpha={args.alpha} null_views={args.null_views} "
              f"resolve={RESOLVE} shifts={SHIFTS} crops={CROPS} owner_copy=toned+as_rendered")
  per_run = {str(run): clean_trials(run, scenes, args.alpha, args.null_views, pathlib.Path(args.cache), settings)
             for run in runs}
  z = np.concatenate([t["z"] for t in per_run.values()])
  log_model = np.concatenate([t["log10_p_model"] for t in per_run.values()])
  log_p = np.concatenate([t["log10_p"] for t in per_run.values()])
  owned = np.concatenate([t["owned"] for t in per_run.values()])
  own_z = np.array([o["z"] for t in per_run.values() for o in t["own"]])
  pairs = [pair for t in per_run.values() for pair in t["pairs"]]
  top = sorted((row for t in per_run.values() for row in t["top"]), key=lambda row: -row["z"])[:TOP]
  marked_rows = dict(stored_result.get("marked", {}),
                     **{str(run): marked_trials(run, args.alpha, args.null_views) for run in marked})
  tpr = true_positive_rates(marked_rows)
  result = dict(
      device=str(jax.devices()[0]), alpha=args.alpha, clean_trials=int(z.size), false_positives=int(owned.sum()),
      false_positives_model=int(np.sum(log_model <= np.log10(args.alpha))),
      predicted_false_positive_rate=args.alpha, z_threshold_model=float(stats.norm.isf(args.alpha)),
      tpr_at_alpha=tpr, tpr_at_alpha_unaligned=true_positive_rates(marked_rows, unaligned=True),
      decoders=[str(r) for r in runs], clean_scenes=[s["name"] for s in scenes],
      independent_pairs=dict(
          decoder_scene_pairs=len(pairs), decoders=len(runs), clean_scenes=len(scenes),
          note="trials of one (decoder, scene) pair share the decoder, the renders and the null; the demo teachers "
               "of seeds 0 and 1 are one scene trained twice and render alike, and every demo decoder passes much "
               "of the render through, so one coincidence of a view and a hidden image recurs across decoders"),
      pairs=pairs, resolve=RESOLVE, settings=settings,
      hidden_images_per_decoder=len(next(iter(per_run.values()))["hidden_names"]),
      clean_z=dict(mean=float(z.mean()), sd=float(z.std()), max=float(z.max()), kurtosis=float(stats.kurtosis(z))),
      tail_counts_model=tail_counts(log_model), tail_counts=tail_counts(log_p), top_clean_trials=top,
      own_hidden=dict(trials=int(own_z.size), mean_z=float(own_z.mean()), sd_z=float(own_z.std()),
                      max_z=float(own_z.max()), decided_owned=int(sum(o["owned"] for t in per_run.values()
                                                                       for o in t["own"])),
                      rows={run: t["own"] for run, t in per_run.items()}),
      marked=marked_rows, message=merged_messages(stored_result.get("message", {}), message_rows()))
  fileio.write_json(out / "ownership_bench.json", result)
  plot(log_model, log_p, z, own_z, args.alpha, out / "ownership_bench.png")
  plot_marked(marked_rows, args.alpha, out / "ownership_tpr.png")
  print(json.dumps({k: v for k, v in result.items() if k not in ("marked", "own_hidden", "pairs", "top_clean_trials")},
                   indent=1))


if __name__ == "__main__":
  main()
