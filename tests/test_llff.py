"""LLFF loader: a tiny self-made forward-facing capture (poses_bounds.npy, images/, images_2/), the layout
LLFF captures are shared in (images_8/ only, a partial COLMAP model) through data.format and data.images, and
the real capture under ../shared/data when present (skipped otherwise)."""

import logging
import re

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.spatial import cKDTree

from conceal_jax.configs import colmap as colmap_config
from conceal_jax.configs import default
from conceal_jax.data import datasets
from conceal_jax.data.datasets import DatasetError
from conceal_jax.data.llff import llff_frustum_points, load_llff
from conceal_jax.gs import evaluate, init, train
from conceal_jax.splat.camera import camera_centers, look_at
from tests.helpers import DATA_DIR

BEER = DATA_DIR / "colmap" / "beer"
WIDTH, HEIGHT, COUNT = 16, 12, 9
TARGET = np.array([0.0, 0.0, 0.0])


def _w2c(index):
  """[4, 4] OpenCV world-to-camera of camera `index`: a 3x3 grid of eyes facing the target."""
  eye = (0.5 * (index % 3 - 1), 0.4 * (index // 3 - 1), 4.0 + 0.1 * index)
  return look_at(eye, TARGET, up=(0.0, 1.0, 0.0))


def _focal(index):
  return 14.0 + 0.5 * index  # per-row focal lengths catch a loader that reads only row 0


def _bounds(index):
  distance = np.linalg.norm(np.linalg.inv(_w2c(index))[:3, 3] - TARGET)
  return distance - 1.0, distance + 1.5


def _llff_row(index):
  """[17] row as LLFF's save_poses writes it (github.com/Fyusion/LLFF, llff/poses/pose_utils.py): COLMAP's
  camera-to-world columns reordered to [c1, c0, -c2], then hwf, then near, far."""
  c2w = np.linalg.inv(_w2c(index))[:3]
  pose = np.stack([c2w[:, 1], c2w[:, 0], -c2w[:, 2], c2w[:, 3], [HEIGHT, WIDTH, _focal(index)]], -1)
  return np.concatenate([pose.ravel(), _bounds(index)])


def _image(index, height, width):
  rows, cols = np.mgrid[:height, :width]
  return (0.5 + 0.4 * np.sin(rows[..., None] * 0.5 + cols[..., None] * 0.3 + index + np.arange(3))).astype(
      np.float32)


def _write_images(folder, height, width, count=COUNT):
  folder.mkdir(parents=True)
  for i in range(count):
    iio.imwrite(folder / f"{i:03d}.png", np.round(_image(i, height, width) * 255).astype(np.uint8))


@pytest.fixture
def llff_root(tmp_path):
  root = tmp_path / "llff"
  _write_images(root / "images", HEIGHT, WIDTH)
  np.save(root / "poses_bounds.npy", np.stack([_llff_row(i) for i in range(COUNT)]))
  return root


def _all_cameras(scene):
  """(names, cameras) of both splits, in file-name order."""
  pairs = sorted(zip(scene.train_names + scene.test_names, scene.train_cameras + scene.test_cameras),
                 key=lambda pair: pair[0])
  return [name for name, _ in pairs], [camera for _, camera in pairs]


def test_cameras_round_trip_and_intrinsics(llff_root):
  scene = load_llff(llff_root)
  names, cameras = _all_cameras(scene)
  assert names == [f"{i:03d}.png" for i in range(COUNT)]
  for i, camera in enumerate(cameras):
    np.testing.assert_allclose(np.asarray(camera.world_to_camera), _w2c(i), atol=1e-6)
    assert (camera.width, camera.height) == (WIDTH, HEIGHT)
    np.testing.assert_allclose([camera.fx, camera.fy, camera.cx, camera.cy],
                               [_focal(i), _focal(i), WIDTH / 2, HEIGHT / 2], rtol=1e-6)
  assert scene.points is None and scene.point_colors is None and scene.background == (0.0, 0.0, 0.0)
  image = scene.test_images[0]
  assert image.shape == (HEIGHT, WIDTH, 3)
  np.testing.assert_allclose(image, _image(0, HEIGHT, WIDTH), atol=1 / 255)


def test_the_target_projects_to_the_image_centre(llff_root):
  """Checks the axis conversion end to end: every camera looks at the target."""
  for camera in _all_cameras(load_llff(llff_root))[1]:
    p = np.asarray(camera.world_to_camera, np.float64)[:3] @ np.r_[TARGET, 1.0]
    assert p[2] > 0
    np.testing.assert_allclose([float(camera.fx) * p[0] / p[2] + float(camera.cx),
                                float(camera.fy) * p[1] / p[2] + float(camera.cy)],
                               [WIDTH / 2, HEIGHT / 2], atol=1e-4)


def test_downscaled_folder_and_downscale(llff_root):
  _write_images(llff_root / "images_2", HEIGHT // 2, WIDTH // 2)
  for downscale, size in ((1, 2), (2, 4)):
    scene = load_llff(llff_root, downscale=downscale, images_dir="images_2")
    for i, camera in enumerate(_all_cameras(scene)[1]):
      assert (camera.width, camera.height) == (WIDTH // size, HEIGHT // size)
      np.testing.assert_allclose([camera.fx, camera.fy, camera.cx, camera.cy],
                                 [_focal(i) / size, _focal(i) / size, WIDTH / 2 / size, HEIGHT / 2 / size],
                                 rtol=1e-6)
      np.testing.assert_allclose(np.asarray(camera.world_to_camera), _w2c(i), atol=1e-6)
    assert scene.train_images[0].shape == (HEIGHT // size, WIDTH // size, 3)


def test_every_eighth_image_is_held_out(llff_root):
  scene = load_llff(llff_root)
  assert scene.test_names == ["000.png", "008.png"]
  assert scene.train_names == [f"{i:03d}.png" for i in range(1, 8)]
  assert len(scene.train_images) == len(scene.train_cameras) == 7
  assert load_llff(llff_root, test_every=0).test_names == []


def _image_coordinates(points, w2c, focal):
  """[M, 3] world points -> [M] u, v (pixels) and depth through the OpenCV camera that generated a row."""
  camera = points @ w2c[:3, :3].T + w2c[:3, 3]
  depth = camera[:, 2]
  return focal * camera[:, 0] / depth + WIDTH / 2, focal * camera[:, 1] / depth + HEIGHT / 2, depth


def _seen(points, index, slack=1e-6):
  """[M] bool: the points inside camera `index`'s image between its near and far bounds."""
  u, v, depth = _image_coordinates(points, _w2c(index), _focal(index))
  near, far = _bounds(index)
  return ((-slack <= u) & (u <= WIDTH + slack) & (-slack <= v) & (v <= HEIGHT + slack)
          & (near - slack <= depth) & (depth <= far + slack))


def test_frustum_points_fill_one_cameras_frustum_uniformly_in_disparity(tmp_path):
  """One camera: every point lies in its image between near and far, uniform across the image and in
  disparity, with the image's world width at its depth as its footprint."""
  np.save(tmp_path / "poses_bounds.npy", _llff_row(4)[None])
  points, footprints = llff_frustum_points(tmp_path, 4000, np.random.default_rng(0))
  assert points.shape == (4000, 3) and footprints.shape == (4000,)
  assert _seen(points, 4).all()
  u, v, depth = _image_coordinates(points, _w2c(4), _focal(4))
  np.testing.assert_allclose(footprints, depth * WIDTH / _focal(4), rtol=1e-9)
  near, far = _bounds(4)
  disparity = (1 / depth - 1 / far) / (1 / near - 1 / far)  # uniform on [0, 1]
  for values in (disparity, u / WIDTH, v / HEIGHT):
    np.testing.assert_allclose(np.quantile(values, [0.1, 0.5, 0.9]), [0.1, 0.5, 0.9], atol=0.03)


def test_frustum_points_spread_over_every_camera(llff_root):
  points, _ = llff_frustum_points(llff_root, 900, np.random.default_rng(1))
  seen = np.stack([_seen(points, i) for i in range(COUNT)])  # [cameras, points]
  assert seen.any(0).all()
  # each camera's own draws (about 100) are all in its frustum; its frustum holds more, the others' overlap
  assert (seen.sum(1) >= 60).all()


def test_random_init_starts_in_the_frustums_with_splats_of_a_few_pixels(llff_root):
  """Without a point cloud the teacher starts from random points in the cameras' frustums, each splat at most
  gs.init.FRUSTUM_START_SCREEN_FRACTION of the image wide at its depth in the camera whose frustum holds it."""
  config = default.get_config()
  config.data.path, config.init.num_random_points = str(llff_root), 500
  scene = datasets.load_scene(llff_root)
  gaussians = train.initial_gaussians(config, scene, np.random.default_rng(0))
  means, scales = np.asarray(gaussians.means, np.float64), np.exp(np.asarray(gaussians.log_scales, np.float64))
  seen = np.stack([_seen(means, i, slack=1e-4) for i in range(COUNT)])
  assert means.shape == (500, 3) and seen.any(0).all()
  width_in_pixels = []  # each splat's scale in image widths, in the cameras whose frustum holds it
  for i in range(COUNT):
    depth = _image_coordinates(means, _w2c(i), _focal(i))[2]
    width_in_pixels.append(np.where(seen[i], scales[:, 0] * _focal(i) / (depth * WIDTH), np.inf))
  smallest = np.min(width_in_pixels, 0)
  assert smallest.max() <= init.FRUSTUM_START_SCREEN_FRACTION * 1.2  # the cameras' focal lengths differ by 4%
  assert smallest.max() >= init.FRUSTUM_START_SCREEN_FRACTION * 0.8  # sparse points: the cap holds


def test_detect_format_prefers_a_complete_colmap_model(llff_root):
  assert datasets.detect_format(llff_root) == "llff"
  assert datasets.load_scene(llff_root, downscale=2).train_images[0].shape == (HEIGHT // 2, WIDTH // 2, 3)
  assert datasets.load_scene("llff", root=llff_root, test_every=0).test_images == []
  sparse = llff_root / "sparse" / "0"
  sparse.mkdir(parents=True)
  (sparse / "cameras.txt").write_text("")
  assert datasets.detect_format(llff_root) == "llff"  # a partial model is passed over
  (sparse / "images.txt").write_text("")
  (sparse / "points3D.txt").write_text("")
  assert datasets.detect_format(llff_root) == "colmap"


def _start(root):
  return llff_frustum_points(root, 10, np.random.default_rng(0))


def test_errors_name_the_file(llff_root, tmp_path):
  poses = llff_root / "poses_bounds.npy"
  rows = np.load(poses)
  with pytest.raises(DatasetError, match="images_4"):
    load_llff(llff_root, images_dir="images_4")
  (llff_root / "images" / "008.png").unlink()
  with pytest.raises(DatasetError, match=r"images has 8 images but .*poses_bounds.npy has 9"):
    load_llff(llff_root)
  np.save(poses, rows[:, :16])
  for call in (load_llff, _start):
    with pytest.raises(DatasetError, match=r"poses_bounds.npy must hold a numeric \[N, 17\] array.*\[9, 16\]"):
      call(llff_root)
  poses.unlink()
  for call in (load_llff, _start):
    with pytest.raises(DatasetError, match="poses_bounds.npy"):
      call(llff_root)


def test_bad_rows_name_the_row(llff_root):
  poses = llff_root / "poses_bounds.npy"
  rows = np.load(poses)
  mirrored = rows.copy()
  mirrored[3, [0, 5, 10]] *= -1  # flips one camera axis: a reflection
  np.save(poses, mirrored)
  with pytest.raises(DatasetError, match="row 3 .*not a rotation"):
    load_llff(llff_root)
  swapped = rows.copy()
  swapped[2, 15:] = swapped[2, 15:][::-1]
  np.save(poses, swapped)
  with pytest.raises(DatasetError, match="row 2 has bounds near .*0 < near <= far"):
    _start(llff_root)


def test_image_of_another_aspect_ratio_names_the_image(llff_root):
  _write_images(llff_root / "images_2", HEIGHT // 2, WIDTH // 2)
  iio.imwrite(llff_root / "images_2" / "004.png", np.zeros((HEIGHT // 2, WIDTH // 2 + 2, 3), np.uint8))
  with pytest.raises(DatasetError, match=r"004.png is 10x6, not a downscaled copy .* row 4"):
    load_llff(llff_root, images_dir="images_2")


# ---------------------------------------------------------------------------------------------------
# The layout LLFF captures are commonly shared in, through the config keys data.format and data.images


@pytest.fixture
def shared_llff(tmp_path):
  """poses_bounds.npy, only images_8/ and a partial COLMAP model: sparse/cameras.bin and points3D.bin, no
  images.bin. The copies are half size (the loader reads the size, not the folder name)."""
  root = tmp_path / "shared"
  _write_images(root / "images_8", HEIGHT // 2, WIDTH // 2)
  np.save(root / "poses_bounds.npy", np.stack([_llff_row(i) for i in range(COUNT)]))
  (root / "sparse").mkdir()
  for name in ("cameras.bin", "points3D.bin"):
    (root / "sparse" / name).write_bytes(b"\0" * 8)  # detection reads no model file
  return root


def _config(root, **data):
  config = default.get_config()
  config.data.path = str(root)
  for key, value in data.items():
    setattr(config.data, key, value)
  return config


def test_shared_layout_loads_as_llff_from_the_folder_named(shared_llff, caplog):
  caplog.set_level(logging.INFO, logger="absl")
  scene = evaluate.load_scene_data(_config(shared_llff, images="images_8"))
  camera = scene.train_cameras[0]
  assert (camera.width, camera.height) == (WIDTH // 2, HEIGHT // 2)
  np.testing.assert_allclose(float(camera.fx), _focal(1) / 2, rtol=1e-6)
  log = caplog.text
  assert "not colmap: the COLMAP model in sparse has no images.bin or .txt" in log
  assert "loading as llff (the first complete format of blender, colmap, transforms, llff)" in log
  assert "images in images_8/" in log


def test_without_an_images_folder_the_least_downscaled_copy_is_read_and_said(shared_llff, caplog):
  """data.images left at 'images' in a capture shared without images/: its least downscaled copy (images_8/
  before images_16/) is read, and the log says so."""
  _write_images(shared_llff / "images_16", HEIGHT // 4, WIDTH // 4)
  caplog.set_level(logging.INFO, logger="absl")
  scene = evaluate.load_scene_data(_config(shared_llff))
  assert (scene.train_cameras[0].width, scene.train_cameras[0].height) == (WIDTH // 2, HEIGHT // 2)
  assert "no images/ folder: images in images_8/, the least downscaled copy" in caplog.text


def test_a_missing_images_folder_is_one_error_listing_the_folders_there(shared_llff):
  with pytest.raises(DatasetError) as info:
    evaluate.load_scene_data(_config(shared_llff, images="images_2"))
  message = str(info.value)
  assert "holds no complete scene format" in message
  assert "colmap: the COLMAP model in sparse has no images.bin or .txt" in message
  assert "llff: poses_bounds.npy, but no images folder images_2/" in message
  assert message.endswith("Folders holding images: images_8/")


def test_a_named_format_is_checked_and_used(shared_llff, llff_root):
  with pytest.raises(DatasetError, match=r"is not a complete colmap scene: colmap: .* no images\.bin"):
    evaluate.load_scene_data(_config(shared_llff, format="colmap", images="images_8"))
  with pytest.raises(DatasetError, match="blender: no transforms_train.json"):
    evaluate.load_scene_data(_config(llff_root, format="blender"))
  sparse = llff_root / "sparse" / "0"  # a complete model (detection picks it), passed over by the name
  sparse.mkdir(parents=True)
  for stem in ("cameras", "images", "points3D"):
    (sparse / f"{stem}.txt").write_text("")
  assert datasets.detect_format(llff_root) == "colmap"
  assert len(evaluate.load_scene_data(_config(llff_root, format="llff")).test_images) == 2


@pytest.mark.parametrize("key, value, message", [
    ("format", "nerf", "data.format must be one of auto, blender, colmap, transforms, llff, got 'nerf'"),
    ("images", "", "data.images must be a folder name"),
    ("images", "../images", "data.images must be a folder inside the scene folder"),
    ("images", "/data/images", "data.images must be a folder inside the scene folder")])
def test_bad_data_keys_are_named(key, value, message):
  config = _config("demo", **{key: value})
  for call in (evaluate.validate, evaluate.load_scene_data):
    with pytest.raises(ValueError, match=re.escape(message)):
      call(config)


def test_points_init_on_a_capture_without_points_starts_in_its_frustums(shared_llff, caplog):
  """configs/colmap.py asks for SfM points; an LLFF capture has none, so it starts randomly in its cameras'
  frustums, with a note."""
  config = colmap_config.get_config()
  config.data.path, config.data.images, config.data.downscale = str(shared_llff), "images_8", 1.0
  config.init.num_random_points = 300
  train.validate(config)
  caplog.set_level(logging.WARNING, logger="absl")
  means = np.asarray(train.initial_gaussians(config, evaluate.load_scene_data(config),
                                             np.random.default_rng(0)).means)
  assert means.shape == (300, 3) and np.stack([_seen(means, i, slack=1e-4) for i in range(COUNT)]).any(0).all()
  assert "init.kind='points' but" in caplog.text and "has no point cloud" in caplog.text


# ---------------------------------------------------------------------------------------------------
# Real data (../shared/data; absent on a user's machine)


def _similarity(source, target):
  """(scale, rotation [3, 3], translation [3]) minimising |scale R source + t - target|^2 (Umeyama, IEEE
  TPAMI 13(4), 1991)."""
  mu_s, mu_t = source.mean(0), target.mean(0)
  s, t = source - mu_s, target - mu_t
  u, sigma, vt = np.linalg.svd(t.T @ s / len(source))
  d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
  rotation = u @ d @ vt
  scale = float(np.trace(np.diag(sigma) @ d) / (s ** 2).sum(1).mean())
  return scale, rotation, mu_t - scale * rotation @ mu_s


def test_beer_llff_cameras_are_the_colmap_cameras():
  if not BEER.is_dir():
    pytest.skip(f"real data not available at {BEER}")
  llff = load_llff(BEER, downscale=8)
  colmap = datasets.load_colmap(BEER, downscale=8)
  names = sorted(p.name for p in (BEER / "images").iterdir())
  assert llff.test_names == colmap.test_names == names[::8] and llff.train_names == colmap.train_names
  llff_cameras = llff.train_cameras + llff.test_cameras
  colmap_cameras = colmap.train_cameras + colmap.test_cameras
  assert all((c.width, c.height) == (90, 160) for c in llff_cameras)

  llff_centres, colmap_centres = camera_centers(llff_cameras), camera_centers(colmap_cameras)
  scale, rotation, translation = _similarity(colmap_centres, llff_centres)
  fitted = scale * colmap_centres @ rotation.T + translation
  extent = np.linalg.norm(llff_centres - llff_centres.mean(0), axis=1).max()
  assert np.abs(fitted - llff_centres).max() < 1e-5 * extent
  for llff_camera, colmap_camera in zip(llff_cameras, colmap_cameras):  # orientations agree as well
    np.testing.assert_allclose(np.asarray(llff_camera.world_to_camera)[:3, :3],
                               np.asarray(colmap_camera.world_to_camera)[:3, :3] @ rotation.T, atol=1e-5)
    # LLFF stores one focal length (the model's first camera's) for all rows; this capture's COLMAP
    # model has a camera per image, whose focal lengths spread by ~5%.
    assert float(llff_camera.fx) == pytest.approx(float(colmap_camera.fx), rel=0.05)

  # The bounds came from the depths of the SfM points, so the frustums the random start fills hold those points:
  # nearly every SfM point has a start point close by, as close as start points are to each other.
  start, _ = llff_frustum_points(BEER, 20_000, np.random.default_rng(0))
  points = (scale * colmap.points @ rotation.T + translation)
  to_start = cKDTree(start).query(points)[0]
  spacing = cKDTree(start).query(start, k=2)[0][:, 1]
  assert np.mean(to_start <= np.quantile(spacing, 0.99)) > 0.99
