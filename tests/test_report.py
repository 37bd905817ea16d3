"""What a job leaves its user: the closing summary, and the report.html of a conceal or verify run, which must be
self-contained (every image embedded) and open in headless Chromium without console errors, its images shown."""
from __future__ import annotations

import base64
import json
import os
import re
import subprocess
import sys

import jax
import numpy as np
import pytest

from conceal_jax import main as main_lib
from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, reveal, unet
from conceal_jax.configs import default
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.report import page, run_report, summary
from conceal_jax.robust import converter
from tests import chromium
from tests.helpers import make_camera, random_gaussians

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
needs_chromium = pytest.mark.skipif(chromium.EXECUTABLE is None, reason="chromium not installed (make chromium)")
needs_converter = pytest.mark.skipif(not converter.available(),
                                     reason="splat-transform not installed (make node_modules)")
IMAGES = ("hidden.png", "revealed.png", "teacher_revealed.png", "normal_revealed.png")
# the history's series, as a conceal run records them: loss windows every 5 steps, curve records every 10
HISTORY = ([dict(step=s, elapsed_s=0.1 * s, loss=1.0 / s, plus=0.5 / s, minus=0.2, psnr=40.0 + s)
            for s in (5, 10, 15, 20)]
           + [dict(step=s, elapsed_s=0.1 * s, hidden_psnr=10.0 + s, hidden_ssim=0.01 * s, test_psnr=25.0)
              for s in (10, 20)])
METRICS = dict(hidden=dict(psnr=30.5, ssim=0.97), leakage=dict(max_ssim_student_test_views=0.15,
                                                               ssim_teacher_check_view=0.12, max_ssim_near_check=0.17),
               leakage_floor=dict(max_ssim_teacher_test_views=0.14, ssim_teacher_at_worst_test_view=0.13),
               leakage_worst_test_view="r_1.png", num_test_views=2,
               near_check=[dict(kind="translation", value=0.02, unit="fraction of key depth", mean_ssim=0.1,
                                max_ssim=0.17, mean_psnr=6.0)],
               **{name: dict(psnr=p, ssim=0.9, lpips=0.05) for name, p in
                  (("student_vs_ground_truth", 29.0), ("teacher_vs_ground_truth", 29.2), ("student_vs_teacher", 41.0))})


@pytest.fixture(scope="module")
def concealed(tmp_path_factory):
  """A conceal workdir as the conceal job leaves it (its files, its figures made up): a 300-Gaussian student, an
  untrained width-4 decoder at 16x16 and its key, the four reveal images, metrics.json, conceal.json, config.json."""
  folder = tmp_path_factory.mktemp("conceal")
  ply.save_ply(folder / "student.ply", jax.tree.map(np.asarray, random_gaussians(2, 300, degree=1, spread=0.5)))
  reveal.save_decoder(str(folder / "decoder.msgpack"), unet.init_decoder(jax.random.key(0), 4, 16))
  key_lib.save_key(str(folder / "key.json"), make_camera(32, 32),
                   dict(hidden_size=16, uses_decoder=True, decoder_width=4,
                        render_options=dict(background=[1.0, 1.0, 1.0])))
  fileio.write_image(folder / "hidden.png", hidden_lib.load_hidden_image("astronaut", 16))
  rng = np.random.default_rng(0)
  for name in IMAGES[1:]:
    fileio.write_image(folder / name, rng.uniform(size=(16, 16, 3)))
  fileio.write_json(folder / "metrics.json", METRICS)
  fileio.write_json(folder / "conceal.json", dict(iterations=20, num_gaussians=300, wall_time_s=2.0, history=HISTORY))
  fileio.write_json(folder / "config.json", dict(data=dict(path="my_scene"), mark=dict(teacher="t.ply",
                                                                                        hidden="astronaut")))
  return folder


def conceal_config():
  config = default.get_config()
  config.mode, config.data.path = "conceal", "my_scene"
  return config


def embedded_images(text: str) -> list[bytes]:
  """The PNG bytes of every <img> in the page; fails on an image that is not a data URI."""
  sources = re.findall(r'<img src="([^"]*)"', text)
  assert all(source.startswith("data:image/png;base64,") for source in sources), sources
  return [base64.b64decode(source.split(",", 1)[1]) for source in sources]


def external_references(text: str) -> list[str]:
  return [ref for ref in re.findall(r'(?:src|href)="([^"]*)"', text) if not ref.startswith("data:")
          and ref != run_report.VIEWER_FILE]


def test_a_line_chart_draws_its_finite_points():
  chart = page.line_chart([0, 10, 20, 30], [1.0, float("nan"), 3.0, 2.0], "loss")
  [points] = re.findall(r'<polyline[^>]* points="([^"]*)"', chart)
  xy = np.array([p.split(",") for p in points.split()], float)
  assert len(xy) == 3 and np.all(np.diff(xy[:, 0]) > 0)
  assert xy[1, 1] < xy[2, 1] < xy[0, 1]  # SVG's y grows downwards: 3.0 highest, 1.0 lowest
  assert "(last: 2)" in chart and "<circle" in page.line_chart([5], [0.5], "one")
  labels = re.findall(r'text-anchor="end">([^<]*)<', page.line_chart([1, 2, 3], [21.351, 21.352, 21.3535], "close"))
  assert labels == ["21.351", "21.352", "21.353"]  # the decimals a narrow range needs
  assert page.line_chart([1, 2], [float("inf"), float("nan")], "none") == ""


@pytest.mark.job
def test_the_conceal_report_embeds_the_run_and_says_when_there_is_no_viewer(concealed, tmp_path, monkeypatch):
  folder = tmp_path / "run"
  fileio.write_bytes(folder / run_report.VIEWER_FILE, b"a viewer of an earlier run")
  for name in os.listdir(concealed):
    fileio.copy_file(concealed / name, folder / name)
  monkeypatch.setattr(converter, "available", lambda: False)
  result = dict(iterations=20, num_gaussians=300, wall_time_s=2.0, median_step_s=0.1, metrics=METRICS)
  text = summary.after_job(conceal_config(), str(folder), result)
  assert "hidden image at the key: PSNR 30.50 dB, SSIM 0.9700" in text
  assert "near the key 0.170" in text and f"report: {folder / 'report.html'}" in text
  assert "no browser view: node and splat-transform are not installed" in text
  page_text = (folder / "report.html").read_text()
  assert embedded_images(page_text) == [(folder / name).read_bytes() for name in IMAGES]
  assert external_references(page_text) == [] and "<script" not in page_text
  assert len(re.findall("<svg", page_text)) == len(run_report.CURVES)  # every series of the history
  assert "No browser view of the student scene" in page_text and not (folder / run_report.VIEWER_FILE).exists()
  for figure in ("30.5", "0.17", "r_1.png", "my_scene", "41"):
    assert f">{figure}<" in page_text or figure in page_text, figure


@pytest.mark.job
@needs_converter
def test_the_report_links_the_viewer_page_splat_transform_writes(concealed, tmp_path):
  for name in os.listdir(concealed):
    fileio.copy_file(concealed / name, tmp_path / name)
  _, note = run_report.write(conceal_config(), str(tmp_path))
  viewer = (tmp_path / run_report.VIEWER_FILE).read_text()
  assert viewer.lstrip().lower().startswith("<!doctype html") and len(viewer) > 100_000
  assert f'<a href="{run_report.VIEWER_FILE}">' in (tmp_path / "report.html").read_text()
  assert note.endswith("the student scene in a browser")


def verify_config(concealed, calibration: str):
  config = default.get_config()
  config.mode = "verify"
  config.reveal.ply, config.reveal.key = str(concealed / "student.ply"), str(concealed / "key.json")
  config.reveal.decoder, config.reveal.hidden = str(concealed / "decoder.msgpack"), "astronaut"
  config.verify.calibration = calibration
  return config


@pytest.fixture(scope="module")
def verified(concealed, tmp_path_factory):
  """(workdir, summary) of a verify run on the concealed fixture (its untrained decoder: not owned) with its
  report, the converter left as installed."""
  folder = tmp_path_factory.mktemp("verify")
  fileio.write_json(folder / "cal.json", dict(clean=[0.1, 0.2, 0.3], marked=[0.9, 0.95]))
  config = verify_config(concealed, str(folder / "cal.json"))
  result = main_lib.run(config, str(folder / "out"))
  return folder / "out", summary.after_job(config, str(folder / "out"), result)


@pytest.mark.job
def test_the_verify_report_leads_with_the_decision_and_holds_the_concealment(concealed, verified):
  folder, text = verified
  evidence = json.loads((folder / "verify.json").read_text())
  assert evidence["owned"] is False and f"{concealed / 'student.ply'}: not owned\n" in text
  assert "calibrated threshold 0.6" in text
  assert f"wrote {folder / 'verify.json'}" in text and f"report: {folder / 'report.html'}" in text
  page_text = (folder / "report.html").read_text()
  assert "not owned: no mark found" in page_text and "calibration.threshold" in page_text
  images = embedded_images(page_text)
  assert images[0] == page.png_bytes(hidden_lib.load_hidden_image("astronaut", 16))
  assert images[1] == (folder / "revealed.png").read_bytes()
  assert images[2:] == [(concealed / name).read_bytes() for name in IMAGES]  # the concealment the key came from
  assert external_references(page_text) == []


def test_the_chromium_check_sees_errors_and_images_that_do_not_show(tmp_path):
  """The check the report tests rely on fails a page that logs an error, fetches from the network or holds an
  image that does not decode."""
  if chromium.EXECUTABLE is None:
    pytest.skip("chromium not installed (make chromium)")
  (tmp_path / "bad.html").write_text('<!DOCTYPE html><html><body><img src="data:image/png;base64,AAAA" alt="broken">'
                                     '<img src="https://example.com/x.png" alt="fetched">'
                                     '<script>console.error("an error")</script></body></html>')
  opened = chromium.open_page(tmp_path / "bad.html")
  assert [decoded for decoded, _, _ in opened["images"]] == [False, False]
  assert "an error" in opened["errors"] and any("example.com" in error for error in opened["errors"])


@pytest.mark.job
@needs_chromium
def test_the_reports_open_in_chromium_without_errors_and_show_their_images(concealed, verified, tmp_path):
  for name in os.listdir(concealed):
    fileio.copy_file(concealed / name, tmp_path / name)
  run_report.write(conceal_config(), str(tmp_path))
  for report, num_images in ((tmp_path / "report.html", 4), (verified[0] / "report.html", 6)):
    opened = chromium.open_page(report)
    assert opened["errors"] == [], report
    assert len(opened["images"]) == num_images and all(decoded and width == 16
                                                       for decoded, width, _ in opened["images"]), opened["images"]
    assert opened["marks"] == len(run_report.CURVES)
    assert opened["links"] == ([run_report.VIEWER_FILE] if converter.available() else [])
  if converter.available():  # the page the report links to opens cleanly too
    assert chromium.open_page(tmp_path / run_report.VIEWER_FILE)["errors"] == []


def test_the_train_and_reveal_summaries_name_their_files_and_figures(tmp_path):
  train = summary.train_lines("w", dict(iterations=100, num_gaussians=1234, wall_time_s=20.0, median_step_s=0.2,
                                        test=dict(psnr=28.123, ssim=0.91, lpips=0.1)))
  assert train[0] == "trained 100 steps in 20 s (0.2 s a step): 1234 Gaussians"
  assert "PSNR 28.12 dB" in train[1] and os.path.join("w", "point_cloud.ply") in train[2]
  revealed = summary.reveal_lines("w", dict(ply="s.ply", psnr=31.0, ssim=0.95))
  assert revealed[0] == "revealed from s.ply: PSNR 31.00 dB, SSIM 0.9500 to the hidden image"
  assert summary.reveal_lines("w", dict(ply="s.ply"))[0] == "revealed from s.ply"


@pytest.mark.job
def test_the_command_line_ends_with_the_summary_and_no_backend_probing(concealed, tmp_path):
  """No line of XLA looking for accelerators it does not find ('Unable to initialize backend'), and the job's
  summary last."""
  result = subprocess.run(
      [sys.executable, "-m", "conceal_jax.main", "--config=conceal_jax/configs/default.py", f"--workdir={tmp_path}",
       "--config.mode=reveal", f"--config.reveal.ply={concealed / 'student.ply'}",
       f"--config.reveal.key={concealed / 'key.json'}", f"--config.reveal.decoder={concealed / 'decoder.msgpack'}"],
      cwd=ROOT, capture_output=True, text=True, timeout=300)
  assert result.returncode == 0, result.stderr
  assert "Unable to initialize backend" not in result.stdout + result.stderr
  assert result.stdout.splitlines()[-2:] == [f"revealed from {concealed / 'student.ply'}",
                                             f"  wrote {tmp_path / 'revealed.png'}, reveal.json"]
