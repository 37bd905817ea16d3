"""Teachers from the trainers people use, in the jobs: a scene of SH degree 1, written in gsplat's or
nerfstudio's layout, rendered and concealed under a config of degree 3 (it renders at its own degree).
The layouts themselves: tests/test_ply.py; folders and the data keys: tests/test_datasets.py, test_llff.py."""
from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from conceal_jax import main as main_lib
from conceal_jax.configs import default
from conceal_jax.data import demo_scene, ply
from conceal_jax.gs import init, render_views
from conceal_jax.splat.gaussians import with_sh_degree
from conceal_jax.splat.render import RenderOptions, render
from tests import helpers
from tests.test_ply import write_trainer_ply


def test_a_scene_renders_at_its_own_degree_under_a_higher_one():
  scene = helpers.random_gaussians(1, 30, degree=1)
  camera = helpers.make_camera(width=16, height=12)
  at_own = np.asarray(render(scene, camera, RenderOptions(sh_degree=1)).rgb)
  np.testing.assert_array_equal(np.asarray(render(scene, camera, RenderOptions(sh_degree=3)).rgb), at_own)
  padded = render(with_sh_degree(scene, 3), camera, RenderOptions(sh_degree=3)).rgb
  np.testing.assert_allclose(np.asarray(padded), at_own, atol=1e-6)  # the missing bands would add nothing


def test_render_job_shows_a_gsplat_file_of_lower_degree(tmp_path):
  scene = helpers.random_gaussians(2, 30, degree=1)
  write_trainer_ply(tmp_path / "splat.ply", "gsplat", scene)
  config = default.get_config()
  config.scene.ply, config.render.sh_degree = str(tmp_path / "splat.ply"), 3
  config.scene.width, config.scene.height, config.scene.num_views = 16, 12, 1
  main_lib.run(config, str(tmp_path / "render"))
  written = iio.imread(tmp_path / "render" / "view_000.png")[..., :3] / 255.0
  camera = render_views.orbit_cameras(config)[0]
  expected = np.asarray(render(scene, camera, RenderOptions(sh_degree=1, background=(1.0, 1.0, 1.0))).rgb)
  np.testing.assert_allclose(written, np.clip(expected, 0, 1), atol=1 / 255 + 1e-6)


@pytest.mark.slow
def test_conceal_a_nerfstudio_teacher_of_lower_degree(tmp_path):
  """The concealment job end to end on a degree-1 teacher in nerfstudio's layout, render.sh_degree=3."""
  from tests.test_conceal import tiny_config
  scene_path = demo_scene.generate_demo_scene(tmp_path / "scene", num_train=4, num_test=1, size=32)
  points, colors = init.random_box_points(np.random.default_rng(0), 600, 1.0)
  teacher = init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5)
  write_trainer_ply(tmp_path / "teacher.ply", "nerfstudio", teacher)
  config = tiny_config((scene_path, tmp_path / "teacher.ply"), iterations=2)
  config.render.sh_degree = 3
  result = main_lib.run(config, str(tmp_path / "conceal"))
  assert np.isfinite(result["metrics"]["hidden"]["psnr"])
  assert ply.load_ply(tmp_path / "conceal" / "student.ply").sh_degree == 1
