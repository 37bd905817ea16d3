"""The near-key length (near.near_length): the unit of the leakage figure's and the decoys' translations, the
depth of the scene as the key sees it, so that a fraction means about the same pixel motion on an orbit and on a
forward-facing capture."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conceal_jax.conceal import key as key_lib, near, scoring
from conceal_jax.data.scene import camera_extent
from conceal_jax.splat.camera import Camera, look_at
from tests.helpers import make_gaussians

WIDTH, HEIGHT, FOV = 64, 48, math.radians(60.0)


def camera(eye, target, up=(0.0, 0.0, 1.0)) -> Camera:
  return Camera.from_fov(look_at(eye, target, up), FOV, WIDTH, HEIGHT)


def gaussians(means, opacity_logits=None):
  n = len(means)
  return make_gaussians(means=np.asarray(means, np.float64), log_scales=np.full((n, 3), -3.0),
                        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
                        opacity_logits=np.full(n, 2.0) if opacity_logits is None else np.asarray(opacity_logits),
                        sh=np.full((n, 1, 3), 0.5))


def forward_facing():
  """A 3x3 grid of cameras 0.15 apart on the plane z = 0, all looking along +z at points 8 to 14 away."""
  rng = np.random.default_rng(0)
  cameras = [camera((x, y, 0.0), (x, y, 10.0), up=(0.0, -1.0, 0.0)) for x in (-0.15, 0.0, 0.15)
             for y in (-0.15, 0.0, 0.15)]
  points = np.column_stack([rng.uniform(-5, 5, 3000), rng.uniform(-4, 4, 3000), rng.uniform(8, 14, 3000)])
  return cameras, gaussians(points)


def orbit():
  """12 cameras on a circle of radius 4, 20 degrees up, looking at an object of about unit size at the origin."""
  rng = np.random.default_rng(1)
  elevation = math.radians(20.0)
  cameras = [camera((4 * math.cos(elevation) * math.cos(a), 4 * math.cos(elevation) * math.sin(a),
                     4 * math.sin(elevation)), (0.0, 0.0, 0.0))
             for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)]
  return cameras, gaussians(rng.normal(size=(3000, 3)) * 0.6)


def project(camera_: Camera, means: np.ndarray) -> np.ndarray:
  w2c = np.asarray(camera_.world_to_camera, np.float64)
  local = means @ w2c[:3, :3].T + w2c[:3, 3]
  return np.column_stack([float(camera_.fx) * local[:, 0] / local[:, 2] + float(camera_.cx),
                          float(camera_.fy) * local[:, 1] / local[:, 2] + float(camera_.cy)])


def pixel_motion(teacher, key: Camera, length: float, fraction: float) -> float:
  """Median pixel shift of the Gaussians the key sees, with the key moved by `fraction` of `length` in
  scoring.NEAR_DIRECTIONS random directions (the leakage figure's poses), averaged over the directions."""
  _, _, inside = near.view_depths(teacher, key)
  means = np.asarray(teacher.means, np.float64)[inside]
  before = project(key, means)
  moved = near.nearby_cameras(key, length, (fraction,), (), scoring.NEAR_DIRECTIONS)
  return float(np.mean([np.median(np.linalg.norm(project(c, means) - before, axis=1)) for _, _, c in moved]))


def test_a_fraction_of_the_near_length_moves_the_image_alike_on_both_geometries():
  motions, old = {}, {}
  for name, (cameras, teacher) in dict(forward=forward_facing(), orbit=orbit()).items():
    key = cameras[-2]
    length, source = near.near_length(teacher, key, cameras)
    assert source == "view_depth"
    fraction = scoring.NEAR_TRANSLATIONS[-1]
    motions[name] = pixel_motion(teacher, key, length, fraction)
    old[name] = pixel_motion(teacher, key, camera_extent(cameras), fraction)
    # about fraction * fx pixels: a sideways move of f * depth shifts what lies at that depth by f * fx
    assert 0.5 < motions[name] / (fraction * float(key.fx)) < 1.2, (name, motions[name])
  assert 0.67 < motions["forward"] / motions["orbit"] < 1.5, motions
  # the extent (the spread of the camera centres) moved the forward-facing key by a small share of the orbit's
  assert old["forward"] < 0.2 * old["orbit"], old


def test_near_length_is_the_opacity_weighted_median_depth_in_the_image():
  key = camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0))
  logit = lambda p: math.log(p / (1 - p))
  means = [(0.0, 0.0, 2.0), (0.1, 0.0, 3.0), (0.0, 0.1, 5.0), (0.2, 0.2, 9.0),
           (0.0, 0.0, -5.0),  # behind the camera
           (30.0, 0.0, 1.0)]  # outside the image
  opacities = [logit(0.9), -30.0, logit(0.2), logit(0.9), 10.0, 10.0]
  depth, opacity, inside = near.view_depths(gaussians(means, opacities), key)
  np.testing.assert_allclose(depth, [2, 3, 5, 9, -5, 1], atol=1e-5)
  assert inside.tolist() == [True, True, True, True, False, False]
  # the weights of the depths 2, 3, 5, 9 are 0.9, ~0, 0.2, 0.9: half of 2.0 is reached at depth 5
  length, source = near.near_length(gaussians(means, opacities), key, [key])
  assert source == "view_depth" and abs(length - 5.0) < 1e-5


def test_a_key_that_sees_no_gaussians_takes_the_camera_distance():
  cameras, teacher = orbit()
  centre = np.linalg.inv(np.asarray(cameras[0].world_to_camera, np.float64))[:3, 3]
  away = camera(centre, 2 * centre)  # looking out of the orbit, where no camera looks
  length, source = near.near_length(teacher, away, cameras)
  assert source == "camera_distance"
  assert length == key_lib.camera_distance(cameras) and abs(length - 4.0) < 1e-3


def test_the_ratio_script_reports_every_key_kind(tmp_path, capsys):
  """experiments/near_length.py on a generated demo scene and a teacher of random points around its centre: one row
  per key kind, the ratio the length over the extent, the unseen key on the camera distance; a scene without SfM
  points cannot stand in its points for a teacher."""
  from conceal_jax.data import demo_scene, ply
  from conceal_jax.gs import init
  from experiments import near_length
  scene = demo_scene.generate_demo_scene(tmp_path / "scene", num_train=6, num_test=1, size=32)
  points, colors = init.random_box_points(np.random.default_rng(0), 500, 1.0)
  ply.save_ply(tmp_path / "teacher.ply", init.gaussians_from_points(points, colors, sh_degree=0))
  rows = near_length.rows(str(scene), str(tmp_path / "teacher.ply"))
  assert [r["kind"] for r in rows] == list(key_lib.KEY_KINDS)
  assert [r["source"] for r in rows] == ["view_depth", "view_depth", "camera_distance"]
  assert all(abs(r["ratio"] - r["near_length"] / r["extent"]) < 1e-12 and 0.3 < r["ratio"] < 1.5 for r in rows)
  near_length.main([f"--scenes={scene}={tmp_path / 'teacher.ply'}"])
  assert capsys.readouterr().out.count("view_depth") == 2
  with pytest.raises(ValueError, match="no SfM points"):  # a generated demo scene holds no point cloud
    near_length.rows(str(scene), "points")
