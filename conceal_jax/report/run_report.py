"""report.html: the page an owner opens after a conceal or verify run, self-contained (page.py: no network).

A conceal run's report shows the hidden image and what the key reveals from the student, from the clean
teacher and from the student's most revealing normal view, the scores of metrics.json, the curves over
training of conceal.json, and the student in the browser. A verify run's report leads with the decision and
its evidence (verify.json) beside the hidden image and the image revealed from the scene verified, then the
concealment the key came from when the key's folder holds one, and the scene verified in the browser.

The browser view is splat-transform's self-contained viewer page (robust.converter), written as viewer.html
next to the report and linked from it (a WebGL viewer inside the report would make the report itself need a
GPU to open cleanly). It shows the scene's base colours: the higher SH bands are the converter's slow part on a
CPU (it fits them a palette by k-means), and a look at the scene does not need them. Without node and
splat-transform the report says so; the run never fails for it.
"""
from __future__ import annotations

import json
import os

import ml_collections

from conceal_jax.conceal import hidden as hidden_lib, train as conceal_train
from conceal_jax.core import fileio
from conceal_jax.gs import evaluate
from conceal_jax.report import page
from conceal_jax.robust import converter, ownership

REPORT_FILE = "report.html"
VIEWER_FILE = "viewer.html"
# (series of conceal.json's history, chart title): the curves over training, those the run recorded
CURVES = (("hidden_psnr", "hidden image PSNR at the key (dB)"), ("hidden_ssim", "hidden image SSIM at the key"),
          ("test_psnr", "student test PSNR (dB)"), ("loss", "training loss"),
          ("plus", "L_d+, the reveal at the key"), ("minus", "L_d-, the decoder off the key"),
          ("psnr", "normal view, student to teacher (dB)"))


def read_json(path: str) -> dict | None:
  """A JSON file's content, None when the file is absent."""
  if not os.path.isfile(path):
    return None
  with open(path) as f:
    return json.load(f)


def read_png(path: str) -> bytes | None:
  if not os.path.isfile(path):
    return None
  with open(path, "rb") as f:
    return f.read()


def viewer_section(scene_ply: str, workdir: str, what: str) -> tuple[str, str]:
  """Writes workdir/viewer.html, the scene `scene_ply` in splat-transform's viewer page; returns (the report's
  section, a one-line note for the job's summary). Without the converter, or when it fails, the section says
  why and no viewer.html is left behind."""
  out = os.path.join(workdir, VIEWER_FILE)
  reason = None
  if not converter.available():
    reason = "node and splat-transform are not installed (make node_modules)"
  else:
    try:
      with fileio.atomic_path(out) as tmp:
        converter.run([scene_ply, *converter.actions(sh_degree=0), tmp])
    except converter.ConverterError as error:
      reason = f"splat-transform failed: {error}"
  if reason is None:
    section = (f'<p><a href="{VIEWER_FILE}">Open {page.escape(what)} in the browser</a> ({VIEWER_FILE} beside this '
               "report: splat-transform's self-contained viewer page, base colours only, no network needed).</p>")
    return section, f"{out}: {what} in a browser"
  if os.path.isfile(out):
    os.remove(out)
  return (f'<p class="note">No browser view of {page.escape(what)}: {page.escape(reason)}.</p>',
          f"no browser view: {reason}")


def curve_charts(history: list[dict]) -> str:
  """The curves over training: one chart per CURVES series the history holds, against the step."""
  charts = []
  for name, title in CURVES:
    records = [h for h in history if name in h and "step" in h]
    charts.append(page.line_chart([h["step"] for h in records], [h[name] for h in records], title))
  charts = [chart for chart in charts if chart]
  return "".join(charts) if charts else '<p class="note">The run recorded no curves.</p>'


def score_tables(metrics: dict, level: int = 3) -> str:
  """metrics.json as tables, each under an <h`level`> heading: recovery, render quality, leakage and its floor,
  the poses near the key, and each key's row when there are several."""
  h = lambda title: page.heading(title, level)
  hidden, leakage, floor = metrics["hidden"], metrics["leakage"], metrics.get("leakage_floor", {})
  compared = [name for name in ("student_vs_ground_truth", "teacher_vs_ground_truth", "student_vs_teacher")
              if name in metrics]
  quality = [(name.replace("_", " "), *(metrics[name].get(m, float("nan")) for m in ("psnr", "ssim", "lpips")))
             for name in compared]
  parts = [h("The hidden image at the key"),
           page.table([("PSNR (dB)", hidden["psnr"]), ("SSIM", hidden["ssim"])]),
           h(f"Render quality ({metrics.get('num_test_views', '?')} test views)"),
           page.table(quality, ("", "PSNR (dB)", "SSIM", "LPIPS")),
           h("Leakage: the decoder's SSIM to the hidden image where it should show nothing"),
           page.table([(f"student's test views (worst: {metrics.get('leakage_worst_test_view', '?')})",
                        leakage["max_ssim_student_test_views"]),
                       ("clean teacher at the key", leakage["ssim_teacher_check_view"]),
                       ("student near the key (max)", leakage.get("max_ssim_near_check", float("nan"))),
                       ("floor: clean teacher's test views (max)", floor.get("max_ssim_teacher_test_views",
                                                                              float("nan")))])]
  if metrics.get("near_check"):
    parts += [h("Near the key"),
              page.table([(row["kind"], f"{row['value']:g} {row['unit']}", row["mean_ssim"], row["max_ssim"],
                           row["mean_psnr"]) for row in metrics["near_check"]],
                         ("moved by", "how far", "mean SSIM", "max SSIM", "mean PSNR (dB)"))]
  if "keys" in metrics:
    parts += [h("Each key"),
              page.table([(k, row["psnr"], row["ssim"], row["max_ssim_near_key"], row["ssim_teacher_at_key"])
                          for k, row in enumerate(metrics["keys"]["hidden"])],
                         ("key", "PSNR (dB)", "SSIM", "near the key (max SSIM)", "clean teacher (SSIM)"))]
  return "".join(parts)


def reveal_figures(folder: str, metrics: dict) -> str:
  """The conceal run's images in `folder`: each hidden image and what its key reveals from the student, then the
  clean teacher's and the worst normal view's reveals at the first key."""
  worst = metrics.get("leakage_worst_test_view", "?")
  shown = [("hidden.png", "the hidden image"), ("revealed.png", "revealed at the key from the student"),
           ("teacher_revealed.png", "revealed at the key from the clean teacher"),
           ("normal_revealed.png", f"revealed from the student's most revealing test view ({worst})")]
  k = 1
  while os.path.isfile(os.path.join(folder, f"revealed_key{k}.png")):
    shown += [(f"hidden_key{k}.png", f"hidden image {k}"), (f"revealed_key{k}.png", f"revealed at key {k}")]
    k += 1
  return "".join(page.figure(png, caption) for png, caption in
                 ((read_png(os.path.join(folder, name)), caption) for name, caption in shown) if png is not None)


def conceal_sections(folder: str, level: int = 2) -> list[str]:
  """The sections of a finished conceal run in `folder` (its metrics.json and, when present, conceal.json), each
  under an <h`level`> heading."""
  h = lambda title: page.heading(title, level)
  metrics = read_json(os.path.join(folder, evaluate.METRICS_FILE))
  run = read_json(os.path.join(folder, conceal_train.SUMMARY_FILE)) or {}
  config = read_json(os.path.join(folder, "config.json")) or {}
  about = [("scene", config.get("data", {}).get("path", "?")), ("teacher", config.get("mark", {}).get("teacher", "?")),
           ("hidden image", config.get("mark", {}).get("hidden", "?")),
           ("steps", run.get("iterations", "?")), ("Gaussians in the student", run.get("num_gaussians", "?")),
           ("training time (s)", run.get("wall_time_s", "?"))]
  return [h("What the key reveals"), reveal_figures(folder, metrics), h("Scores"), score_tables(metrics, level + 1),
          h("The run"), page.table(about), h("Curves over training"), curve_charts(run.get("history", []))]


def files_section(folder: str) -> str:
  """Which of a conceal run's files to share and which to keep."""
  rows = [("share", conceal_train.STUDENT_FILE, "the marked scene, an ordinary 3D-GS .ply"),
          ("keep secret", conceal_train.DECODER_FILE, "the decoder"),
          ("keep secret", conceal_train.KEY_FILE, "the key: the pose that reveals the image"),
          ("keep private", REPORT_FILE, "this report: it shows the hidden image")]
  return page.table([(what, os.path.join(folder, name), why) for what, name, why in rows])


def conceal_report(config: ml_collections.ConfigDict, workdir: str) -> tuple[str, str]:
  """(the page of the conceal run in workdir, the viewer's note)."""
  viewer, note = viewer_section(os.path.join(workdir, conceal_train.STUDENT_FILE), workdir, "the student scene")
  body = [*conceal_sections(workdir), page.heading("The student in the browser"), viewer, page.heading("Files"),
          files_section(workdir)]
  return page.document(f"Concealment in {config.data.path}", body), note


def verify_report(config: ml_collections.ConfigDict, workdir: str) -> tuple[str, str]:
  """(the page of the verify run in workdir, the viewer's note)."""
  r = config.reveal
  evidence = read_json(os.path.join(workdir, ownership.VERIFY_FILE))
  revealed = read_png(os.path.join(workdir, "revealed.png"))
  hidden = page.png_bytes(hidden_lib.load_hidden_image(r.hidden, page.png_shape(revealed)[0]))
  verdict = "owned: the scene carries the hidden image" if evidence["owned"] else "not owned: no mark found"
  body = [f'<p class="verdict">{page.escape(verdict)}</p>',
          f"<p>{page.escape(r.ply)}: {page.escape(evidence_figures(evidence))}.</p>",
          page.figure(hidden, "the hidden image"), page.figure(revealed, "revealed at the key from the scene verified"),
          page.heading("The evidence (verify.json)"), page.table(page.flat_items(evidence), ("", "value"))]
  key_folder = os.path.dirname(os.path.abspath(r.key))
  if os.path.isfile(os.path.join(key_folder, evaluate.METRICS_FILE)):
    body += [page.heading(f"The concealment this key comes from ({key_folder})"),
             *conceal_sections(key_folder, level=3)]
  viewer, note = viewer_section(r.ply, workdir, "the scene verified")
  body += [page.heading("The scene verified, in the browser"), viewer]
  return page.document(f"Ownership of {os.path.basename(r.ply)}", body), note


def evidence_figures(evidence: dict) -> str:
  """A verify run's figures in a line: the numbers at the top of verify.json (the statistic and what the decision
  rests on, as the verify job names them) and the calibrated threshold when a calibration was given."""
  figures = [f"{name} {value:.4g}" for name, value in evidence.items()
             if isinstance(value, (int, float)) and not isinstance(value, bool)]
  threshold = evidence.get("calibration", {}).get("threshold")
  return ", ".join(figures + ([f"calibrated threshold {threshold:.4g}"] if threshold is not None else []))


REPORTS = {"conceal": conceal_report, "verify": verify_report}


def write(config: ml_collections.ConfigDict, workdir: str) -> tuple[str, str]:
  """Writes workdir/report.html for a conceal or verify run; returns (its path, the viewer's note)."""
  text, note = REPORTS[config.mode](config, workdir)
  path = os.path.join(workdir, REPORT_FILE)
  fileio.write_text(path, text)
  return path, note
