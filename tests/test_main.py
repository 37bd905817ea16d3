"""End to end: the real command line on a temp workdir, and clear errors for bad input."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import imageio.v3 as iio
import pytest

from conceal_jax import main as main_lib
from conceal_jax.data import ply
from conceal_jax.gs import scene_gen
from conceal_jax.configs import default
from tests.helpers import set_field

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def small_config():
  config = default.get_config()
  config.scene.num_points = 300
  config.scene.width, config.scene.height, config.scene.num_views = 40, 30, 2
  return config


def test_render_job_writes_views_and_config(tmp_path):
  main_lib.run(small_config(), str(tmp_path))
  saved = json.loads((tmp_path / "config.json").read_text())
  assert saved["mode"] == "render" and saved["scene"]["width"] == 40
  views = sorted(p.name for p in tmp_path.glob("view_*.png"))
  assert views == ["view_000.png", "view_001.png"]
  image = iio.imread(tmp_path / "view_000.png")
  assert image.shape == (30, 40, 3)
  assert image.std() > 10, "the scene must be visible, not a flat background"
  assert json.loads((tmp_path / "render.json").read_text())["num_gaussians"] == 300


def test_render_job_reads_a_ply(tmp_path):
  path = tmp_path / "scene.ply"
  ply.save_ply(path, scene_gen.sphere_and_ground(200, sh_degree=1))
  config = small_config()
  config.scene.ply = str(path)
  config.render.max_per_tile = None  # exact
  summary = main_lib.run(config, str(tmp_path / "out"))
  assert summary["num_gaussians"] == 200 and summary["views"][0]["overflow_tiles"] == 0


def _cli(tmp_path, *overrides):
  return subprocess.run([sys.executable, "-m", "conceal_jax.main", "--config=conceal_jax/configs/default.py",
                         f"--workdir={tmp_path}", "--config.scene.num_points=100", "--config.scene.num_views=1",
                         "--config.scene.width=16", "--config.scene.height=16", *overrides],
                        cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("override,message", [
    ("--config.mode=nope", "config.mode must be one of"),
    ("--config.render.tile_size=0", "tile_size must be positive"),
    ("--config.scene.ply=/does/not/exist.ply", "no such file"),
    ("--config.scene.fov_deg=0", "fov_deg"),
    ("--config.mode=conceal", "mark.teacher"),
    ("--config.mode=baseline", "mark.teacher"),
    ("--config.mode=baseline --config.baseline.lsb_bits=9", "baseline.lsb_bits"),
    ("--config.mode=reveal", "reveal.ply is required"),
    ("--config.mode=eval", "point_cloud.ply: no such file"),
])
def test_bad_input_gives_one_clear_error_and_nonzero_exit(tmp_path, override, message):
  result = _cli(tmp_path, *override.split())
  assert result.returncode != 0
  assert message in result.stderr
  assert "Traceback" not in result.stderr


@pytest.mark.parametrize("mode,field,value,message", [
    ("train", "train.sh_degree", 5, "train.sh_degree"), ("train", "train.densify.every", 0, "densify"),
    ("train", "render.tile_size", 0, "tile_size"), ("eval", "eval.lpips_net", "squeeze", "squeeze"),
    ("conceal", "conceal.variant", "mine", "conceal.variant"), ("conceal", "mark.key_kind", "x", "key_kind"),
    ("conceal", "conceal.decoder_opt.adam_eps", 0.0, "decoder_opt.adam_eps"),
    ("conceal", "conceal.decoder_opt.update_clip", -1.0, "decoder_opt.update_clip"),
    ("conceal", "conceal.leakage.decoy_views", 3, "conceal.leakage.decoy_views"),
    ("render", "scene.num_views", 0, "num_views"), ("reveal", "reveal.key", "", "reveal.ply"),
    ("verify", "reveal.hidden", "", "reveal.ply"), ("verify", "train.iterations", 1, "reveal.ply")])
def test_each_mode_validates_before_writing_anything(tmp_path, mode, field, value, message):
  """main.run checks the whole config for the mode first: a bad value leaves the workdir untouched."""
  config = default.get_config()
  config.mode = mode
  set_field(config, field, value)
  with pytest.raises(ValueError, match=message):
    main_lib.run(config, str(tmp_path / "out"))
  assert not (tmp_path / "out").exists()


def test_importing_the_library_leaves_xla_flags_alone():
  """Only the command line (--host_devices) asks XLA for host devices; importing any module does not."""
  code = ("import os; os.environ.pop('XLA_FLAGS', None); import conceal_jax, conceal_jax.main, "
          "conceal_jax.conceal.train; import jax; print(repr(os.environ.get('XLA_FLAGS')), jax.local_device_count())")
  env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
  assert out.split() == ["None", "1"]
