"""`make own-scene`: one command from a scene folder to a verified concealment and its report (issue 41)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conceal_jax.data import demo_scene
from tests import test_datasets, test_llff

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# a tiny run: 20 teacher steps from 500 random points, 10 concealment steps of a width-4 decoder at 16x16 and 2
# steps of its polish
TINY_ARGS = ("--config.init.kind=random --config.init.num_random_points=500 --config.mark.hidden_size=16 "
             "--config.conceal.decoder.width=4 --config.conceal.decoder_opt.polish_steps=2 "
             "--config.conceal.iterations=10 --config.conceal.log_every=5 --config.eval.max_views=1 "
             "--config.train.progress_bar=False --config.conceal.progress_bar=False")
needs_make = pytest.mark.skipif(shutil.which("make") is None, reason="make not installed")
WIDTH, HEIGHT = 32, 24  # each format's images


def write_scene(layout: str, root):
  """A small scene of 10 views in `layout` (the writers of test_datasets and test_llff): 'blender' (the demo
  scene, 32x32), 'colmap' (a text model, OPENCV lens), 'transforms' (a distorted lens) or 'llff' (as LLFF scenes
  are shared: poses_bounds.npy, images_8/ only, a partial COLMAP model of cameras without images)."""
  if layout == "blender":
    return demo_scene.generate_demo_scene(root, num_train=8, num_test=2, size=32)
  names = [f"view_{i:02d}.png" for i in range(10)]
  k1, k2, p1, p2 = test_datasets.COEFFICIENTS
  if layout == "colmap":
    return test_datasets._write_colmap_text(root, f"OPENCV {WIDTH} {HEIGHT} 30 31 15.5 11.5 {k1} {k2} {p1} {p2}",
                                            names, (WIDTH, HEIGHT))
  images = {f"images/{name}": test_datasets._gradient(HEIGHT, WIDTH, seed=i) for i, name in enumerate(names)}
  if layout == "transforms":
    meta = dict(fl_x=30.0, fl_y=31.0, cx=15.5, cy=11.5, w=WIDTH, h=HEIGHT, k1=k1, k2=k2, p1=p1, p2=p2)
    return test_datasets._write_transforms(root, meta, test_datasets._frames(list(images)), images)
  # LLFF: the rows describe the full-resolution images (8x), of which images_8/ holds the only copies
  rows = np.stack([test_llff._llff_row(i) for i in range(len(names))])
  rows[:, [4, 9, 14]] = [HEIGHT * 8, WIDTH * 8, 8 * 30.0]
  root.mkdir(parents=True)
  np.save(root / "poses_bounds.npy", rows)
  for i, name in enumerate(names):
    test_datasets._write_png(root / "images_8" / name, test_datasets._gradient(HEIGHT, WIDTH, seed=i))
  (root / "sparse").mkdir()
  (root / "sparse" / "cameras.txt").write_text(f"1 PINHOLE {WIDTH * 8} {HEIGHT * 8} 240 240 128 96\n")
  return root


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
  assert "--config=conceal_jax/configs/conceal.py:in_scene_layer" in commands  # the layer, unless LAYER= says none
  elsewhere = make_own_scene("SCENE=my/scene", f"WORKDIR={tmp_path}", dry_run=True).stdout
  assert f"--workdir={tmp_path}/conceal" in elsewhere and f"--config.mark.teacher={tmp_path}/teacher/" in elsewhere


@needs_make
@pytest.mark.parametrize("layer", ["", "in_scene_axes", "in_scene_layer"])
def test_own_scene_layers_a_second_mark_on_the_student_and_verifies_both(layer):
  commands = make_own_scene("SCENE=my/scene", "TEACHER=t.ply", f"LAYER={layer}", dry_run=True).stdout
  job = lambda name: [line for line in commands.splitlines() if f"--workdir=workdirs/own_scene/scene/{name}" in line]
  assert job("layer") == [f'test -z "{layer}" || {sys.executable} -m conceal_jax.main '
                          f"--config=conceal_jax/configs/conceal.py:{layer} "
                          "--config.data.path=my/scene  --workdir=workdirs/own_scene/scene/layer \\"]
  assert "--config.mark.teacher=workdirs/own_scene/scene/conceal/student.ply" in commands
  shared = f"--config.reveal.ply=workdirs/own_scene/scene/{'layer' if layer else 'conceal'}/student.ply"
  for name in ("reveal", "verify"):  # the film's key and decoder, read from the scene as shared
    assert shared in job(name)[0] and "--config.reveal.key=workdirs/own_scene/scene/conceal/key.json" in job(name)[0]
  assert ("--config.verify.marks=workdirs/own_scene/scene/layer" in commands) == bool(layer)


@needs_make
@pytest.mark.slow  # four jobs, each its own process and compilation
@pytest.mark.parametrize("layout,layer", [("blender", ""), ("colmap", ""), ("transforms", ""), ("llff", ""),
                                          ("blender", "in_scene_layer")])
def test_own_scene_trains_conceals_reveals_and_verifies(tmp_path, layout, layer):
  scene = write_scene(layout, tmp_path / "scene")
  work = tmp_path / "work"
  images = " --config.data.images=images_8" if layout == "llff" else ""
  result = make_own_scene(f"SCENE={scene}", f"WORKDIR={work}", "OWN_TRAIN_STEPS=20", "CURVE_EVERY=5",
                          f"ARGS={TINY_ARGS}{images}", f"LAYER={layer}")
  assert result.returncode == 0, result.stderr[-3000:]
  output = result.stdout + result.stderr
  assert "Unable to initialize backend" not in output and f"loading as {layout}" in output
  shared = work / ("layer" if layer else "conceal") / "student.ply"
  for line in ("trained 20 steps in", "concealed in 10 steps", f"revealed from {shared}: PSNR",
               f"{shared}: ", "  evidence: ", f"open {work}/verify/report.html"):
    assert line in result.stdout, line
  for path in ("teacher/point_cloud.ply", "conceal/student.ply", "conceal/report.html", "reveal/revealed.png",
               "verify/verify.json", "verify/report.html") + (("layer/student.ply", "layer/key.json") if layer else ()):
    assert (work / path).is_file(), path
  concealed = json.loads((work / "conceal" / "metrics.json").read_text())
  revealed = json.loads((work / "reveal" / "reveal.json").read_text())
  verified = json.loads((work / "verify" / "verify.json").read_text())
  if layer:  # the film's mark read from the layered scene, and both marks tested
    assert np.isfinite(revealed["psnr"]) and verified["ply"] == str(shared)
    assert [m["key"] for m in verified["marks"]] == [f"{work}/conceal/key.json", f"{work}/layer/key.json"]
  else:
    assert revealed["psnr"] == pytest.approx(concealed["hidden"]["psnr"], rel=1e-4) and "marks" not in verified
  curves = [h for h in json.loads((work / "conceal" / "conceal.json").read_text())["history"] if "hidden_psnr" in h]
  assert [h["step"] for h in curves] == [5, 10]
  assert "The concealment this key comes from" in (work / "verify" / "report.html").read_text()
