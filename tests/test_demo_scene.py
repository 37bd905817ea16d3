"""The generated demo scene: Blender format, geometry consistent with its cameras, caching."""
import json
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from conceal_jax.data import datasets, demo_scene

SMALL = dict(num_train=5, num_test=3, size=48, seed=0)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
  return demo_scene.generate_demo_scene(tmp_path_factory.mktemp("cache") / "demo_scene", **SMALL)


def _views(root):
  """(camera, alpha [H, W] in [0, 1]) for every train and test view, cameras from load_blender."""
  scene = datasets.load_blender(root)
  paths = ([root / "train" / name for name in scene.train_names]
           + [root / "test" / name for name in scene.test_names])
  alphas = [iio.imread(path)[..., 3] / 255.0 for path in paths]
  return list(zip(scene.train_cameras + scene.test_cameras, alphas))


def _pixel(camera, point):
  """(row, column) of the pixel that sees world `point`, or None when it is outside the frame."""
  w2c = np.asarray(camera.world_to_camera, np.float64)
  p = w2c[:3, :3] @ point + w2c[:3, 3]
  assert p[2] > 0
  u, v = float(camera.fx) * p[0] / p[2] + float(camera.cx), float(camera.fy) * p[1] / p[2] + float(camera.cy)
  if 0 <= u < camera.width and 0 <= v < camera.height:
    return int(v), int(u)
  return None


def test_scene_is_a_blender_dataset(scene_dir):
  scene = datasets.load_blender(scene_dir)
  assert len(scene.train_images) == 5 and len(scene.test_images) == 3
  assert all(image.shape == (48, 48, 3) for image in scene.train_images + scene.test_images)
  assert all((c.width, c.height) == (48, 48) for c in scene.train_cameras)
  val = json.loads((scene_dir / "transforms_val.json").read_text())
  assert val == json.loads((scene_dir / "transforms_test.json").read_text())
  rgba = iio.imread(scene_dir / "train" / "r_0.png")
  assert rgba.shape == (48, 48, 4) and rgba.dtype == np.uint8
  np.testing.assert_allclose(scene.scene_extent(), 1.1 * demo_scene.CAMERA_DISTANCE, rtol=0.5)


def test_cameras_orbit_the_upper_hemisphere(scene_dir):
  scene = datasets.load_blender(scene_dir)
  for camera in scene.train_cameras + scene.test_cameras:
    w2c = np.asarray(camera.world_to_camera, np.float64)
    center = -w2c[:3, :3].T @ w2c[:3, 3]
    assert np.linalg.norm(center) == pytest.approx(demo_scene.CAMERA_DISTANCE, rel=1e-5)
    assert center[2] > 0
    assert _pixel(camera, np.zeros(3)) in {(23, 23), (23, 24), (24, 23), (24, 24)}  # looks at the origin


def test_sphere_centre_projects_onto_covered_pixels(scene_dir):
  for camera, alpha in _views(scene_dir):
    pixel = _pixel(camera, demo_scene.SPHERE_CENTER)
    assert pixel is not None and alpha[pixel] > 0.5


def test_ground_beyond_the_disc_is_transparent(scene_dir):
  """A ground point outside the disc, on the camera's side, is seen by a ray that hits nothing."""
  seen = 0
  for camera, alpha in _views(scene_dir):
    w2c = np.asarray(camera.world_to_camera, np.float64)
    center = -w2c[:3, :3].T @ w2c[:3, 3]
    toward_camera = center[:2] / np.linalg.norm(center[:2])
    pixel = _pixel(camera, np.array([*(1.6 * toward_camera), 0.0]))
    if pixel is not None:
      seen += 1
      assert alpha[pixel] == 0.0
      # and the disc edge just inside it is covered
      assert alpha[_pixel(camera, np.array([*(1.0 * toward_camera), 0.0]))] == 1.0
  assert seen >= 4


def test_alpha_is_soft_only_at_silhouettes(scene_dir):
  alpha = iio.imread(scene_dir / "test" / "r_0.png")[..., 3] / 255.0
  fractional = (alpha > 0) & (alpha < 1)
  assert 0.1 < (alpha > 0.5).mean() < 0.9
  assert fractional.any() and fractional.mean() < 0.15
  # a fractional pixel always touches both a covered and an empty region
  padded = np.pad(alpha, 1, mode="edge")
  neighbourhood = np.lib.stride_tricks.sliding_window_view(padded, (3, 3))
  assert (neighbourhood.max((-1, -2))[fractional] > neighbourhood.min((-1, -2))[fractional]).all()


def test_generation_is_deterministic_and_seeded(scene_dir, tmp_path):
  again = demo_scene.generate_demo_scene(tmp_path / "again", **SMALL)
  for path in sorted(scene_dir.rglob("*")):
    if path.is_file():
      assert path.read_bytes() == (again / path.relative_to(scene_dir)).read_bytes(), path
  other = demo_scene.generate_demo_scene(tmp_path / "other", **dict(SMALL, seed=1))
  assert (other / "transforms_train.json").read_bytes() != (scene_dir / "transforms_train.json").read_bytes()


def test_complete_scene_is_reused_and_changed_parameters_regenerate(tmp_path):
  out = tmp_path / "demo"
  small = dict(num_train=2, num_test=1, size=16)
  demo_scene.generate_demo_scene(out, **small)
  stamp = os.stat(out / "train" / "r_0.png").st_mtime_ns
  demo_scene.generate_demo_scene(out, **small)
  assert os.stat(out / "train" / "r_0.png").st_mtime_ns == stamp
  demo_scene.generate_demo_scene(out, **dict(small, size=20))
  assert iio.imread(out / "train" / "r_0.png").shape == (20, 20, 4)
  (out / demo_scene.PARAMS_FILE).unlink()  # as if interrupted before completion
  demo_scene.generate_demo_scene(out, **dict(small, size=20))
  assert json.loads((out / demo_scene.PARAMS_FILE).read_text())["size"] == 20
  assert sorted(p.name for p in tmp_path.iterdir()) == ["demo"]  # no temporary folders left


def test_demo_scene_path(monkeypatch, tmp_path):
  monkeypatch.setenv("CONCEAL_JAX_CACHE", str(tmp_path / "env"))
  assert demo_scene.demo_scene_path() == tmp_path / "env" / "demo_scene"
  assert demo_scene.demo_scene_path(tmp_path / "arg") == tmp_path / "arg" / "demo_scene"
  monkeypatch.delenv("CONCEAL_JAX_CACHE")
  assert demo_scene.demo_scene_path() == Path.home() / ".cache" / "conceal_jax" / "demo_scene"


def test_load_scene_demo_generates_into_the_cache(monkeypatch, tmp_path):
  generate = demo_scene.generate_demo_scene
  monkeypatch.setattr(demo_scene, "generate_demo_scene",
                      lambda out: generate(out, num_train=2, num_test=1, size=16))
  monkeypatch.setenv("CONCEAL_JAX_CACHE", str(tmp_path))
  scene = datasets.load_scene("demo", downscale=2)
  assert (tmp_path / "demo_scene" / demo_scene.PARAMS_FILE).is_file()
  assert len(scene.train_images) == 2 and scene.train_images[0].shape == (8, 8, 3)
  assert scene.background == (1.0, 1.0, 1.0)
