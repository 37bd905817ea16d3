"""`make own-scene`: one command from a scene folder to a verified concealment and its report (issue 41)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from conceal_jax.data import demo_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# a tiny run: 20 teacher steps from 500 random points, 10 concealment steps of a width-4 decoder at 16x16
TINY_ARGS = ("--config.init.num_random_points=500 --config.mark.hidden_size=16 --config.conceal.decoder.width=4 "
             "--config.conceal.iterations=10 --config.conceal.log_every=5 --config.eval.max_views=1 "
             "--config.train.progress_bar=False --config.conceal.progress_bar=False")
needs_make = pytest.mark.skipif(shutil.which("make") is None, reason="make not installed")


def make_own_scene(*variables: str, dry_run: bool = False) -> subprocess.CompletedProcess:
  """`make own-scene VARIABLES...` with this interpreter, the virtual environment taken as installed."""
  return subprocess.run(["make", "-s" if not dry_run else "-n", "-o", ".venv/.installed", "own-scene",
                         f"PY={sys.executable}", *variables], cwd=ROOT, capture_output=True, text=True, timeout=1800)


@needs_make
@pytest.mark.parametrize("variables,message", [((), "SCENE=<scene folder> is required"),
                                               (("SCENE=demo", "TEACHER=/no/such.ply"), "/no/such.ply: no such file")])
def test_own_scene_names_what_is_missing(variables, message):
  result = make_own_scene(*variables)
  assert result.returncode != 0 and message in result.stderr


@needs_make
def test_own_scene_with_a_teacher_conceals_it_and_trains_none(tmp_path):
  commands = make_own_scene("SCENE=my/scene/", "TEACHER=t.ply", dry_run=True).stdout
  conceal = [line for line in commands.splitlines() if "--workdir=workdirs/own_scene/scene/conceal" in line]
  assert len(conceal) == 1 and "--config.mark.teacher=t.ply" in conceal[0]
  assert "--config.data.path=my/scene/" in conceal[0] and "configs/conceal.py" in conceal[0]
  assert "--workdir=workdirs/own_scene/scene/teacher" in commands  # behind `test -n "t.ply" ||`
  assert 'test -n "t.ply" ||' in commands
  elsewhere = make_own_scene("SCENE=my/scene", f"WORKDIR={tmp_path}", dry_run=True).stdout
  assert f"--workdir={tmp_path}/conceal" in elsewhere and f"--config.mark.teacher={tmp_path}/teacher/" in elsewhere


@needs_make
@pytest.mark.slow  # four jobs, each its own process and compilation
def test_own_scene_trains_conceals_reveals_and_verifies(tmp_path):
  scene = demo_scene.generate_demo_scene(tmp_path / "scene", num_train=6, num_test=2, size=32)
  work = tmp_path / "work"
  result = make_own_scene(f"SCENE={scene}", f"WORKDIR={work}", "OWN_TRAIN_STEPS=20", "CURVE_EVERY=5",
                          f"ARGS={TINY_ARGS}")
  assert result.returncode == 0, result.stderr[-3000:]
  output = result.stdout + result.stderr
  assert "Unable to initialize backend" not in output
  for line in ("trained 20 steps in", "concealed in 10 steps", f"revealed from {work}/conceal/student.ply: PSNR",
               f"{work}/conceal/student.ply: ", "  evidence: ", f"open {work}/verify/report.html"):
    assert line in result.stdout, line
  for path in ("teacher/point_cloud.ply", "conceal/student.ply", "conceal/report.html", "reveal/revealed.png",
               "verify/verify.json", "verify/report.html"):
    assert (work / path).is_file(), path
  concealed = json.loads((work / "conceal" / "metrics.json").read_text())
  revealed = json.loads((work / "reveal" / "reveal.json").read_text())
  assert revealed["psnr"] == pytest.approx(concealed["hidden"]["psnr"], rel=1e-4)
  curves = [h for h in json.loads((work / "conceal" / "conceal.json").read_text())["history"] if "hidden_psnr" in h]
  assert [h["step"] for h in curves] == [5, 10]
  assert "The concealment this key comes from" in (work / "verify" / "report.html").read_text()
