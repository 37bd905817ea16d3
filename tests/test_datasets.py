"""Scene loaders: tiny self-made Blender / COLMAP-text / transforms.json scenes, and the real scenes
under ../shared/data when present (skipped otherwise)."""
import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conceal_jax.data import datasets
from conceal_jax.splat.camera import look_at
from conceal_jax.data.datasets import DatasetError
from tests.helpers import DATA_DIR

DATA = DATA_DIR
LEGO = DATA / "nerf_synthetic" / "lego"
BEER = DATA / "colmap" / "beer"
GL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def _project(camera, points):
  """Pixel coordinates [M, 2] and depths [M] of world points [M, 3] through a pinhole Camera."""
  w2c = np.asarray(camera.world_to_camera, np.float64)
  p = points @ w2c[:3, :3].T + w2c[:3, 3]
  z = p[:, 2]
  u = float(camera.fx) * p[:, 0] / z + float(camera.cx)
  v = float(camera.fy) * p[:, 1] / z + float(camera.cy)
  return np.stack([u, v], -1), z


def _inside(uv, camera):
  return (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)


def _orbit_w2c(count, radius=3.0):
  """[count] OpenCV world-to-camera matrices around the origin."""
  return [look_at((radius * math.cos(a), radius * math.sin(a), 1.0), (0, 0, 0))
          for a in np.linspace(0, 2 * math.pi, count, endpoint=False)]


def _write_png(path, pixels):
  path.parent.mkdir(parents=True, exist_ok=True)
  iio.imwrite(path, np.round(np.clip(pixels, 0, 1) * 255).astype(np.uint8))


def _gradient(height, width, channels=3, seed=0):
  """A smooth, non-constant [H, W, C] image in [0.1, 0.9]."""
  rng = np.random.default_rng(seed)
  rows, cols = np.mgrid[:height, :width]
  phase = rng.uniform(0, 3, channels)
  return 0.5 + 0.4 * np.sin(rows[..., None] * 0.3 + cols[..., None] * 0.2 + phase)


# ---------------------------------------------------------------------------------------------------
# Blender


def _write_blender(root, width=8, height=6, counts=None, fov=0.8, rgba=None, ext=""):
  counts = counts or {"train": 3, "test": 2}
  for split, count in counts.items():
    frames = []
    for i, w2c in enumerate(_orbit_w2c(count)):
      image = rgba if rgba is not None else np.concatenate(
          [_gradient(height, width, seed=i), np.ones((height, width, 1))], -1)
      _write_png(root / split / f"r_{i}.png", image)
      c2w = np.linalg.inv(w2c) @ GL_FLIP
      frames.append({"file_path": f"./{split}/r_{i}{ext}", "transform_matrix": c2w.tolist()})
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
  return root


def test_blender_cameras_match_the_written_poses_and_fov(tmp_path):
  root = _write_blender(tmp_path, width=8, height=6, fov=0.8)
  scene = datasets.load_blender(root)
  assert len(scene.train_images) == 3 and len(scene.test_images) == 2
  assert scene.train_names == ["r_0.png", "r_1.png", "r_2.png"]
  camera = scene.train_cameras[1]
  assert (camera.width, camera.height) == (8, 6)
  np.testing.assert_allclose(float(camera.fx), 4 / math.tan(0.4), rtol=1e-6)
  np.testing.assert_allclose(float(camera.fy), float(camera.fx))
  assert (float(camera.cx), float(camera.cy)) == (4.0, 3.0)
  np.testing.assert_allclose(np.asarray(camera.world_to_camera), _orbit_w2c(3)[1], atol=1e-6)
  # The origin is the look-at target: it projects to the principal point.
  uv, z = _project(camera, np.zeros((1, 3)))
  np.testing.assert_allclose(uv[0], [4.0, 3.0], atol=1e-4)
  assert z[0] > 0


def test_blender_composites_alpha_on_the_background(tmp_path):
  rgba = np.zeros((4, 4, 4))
  rgba[..., 0] = 1.0  # red everywhere; alpha 0 / 1 / 0.4 in three bands
  rgba[:, :2, 3] = 0.0
  rgba[:, 2, 3] = 1.0
  rgba[:, 3, 3] = 0.4
  root = _write_blender(tmp_path, width=4, height=4, rgba=rgba)
  for background in ((1.0, 1.0, 1.0), (0.0, 0.2, 0.0)):
    image = datasets.load_blender(root, background=background).train_images[0]
    assert image.dtype == np.float32 and image.shape == (4, 4, 3)
    np.testing.assert_allclose(image[:, 0], np.broadcast_to(background, (4, 3)), atol=1e-6)
    np.testing.assert_allclose(image[:, 2], np.broadcast_to((1, 0, 0), (4, 3)), atol=1e-6)
    alpha = 102 / 255  # 0.4 as stored in 8 bits
    expected = alpha * np.array([1, 0, 0]) + (1 - alpha) * np.array(background)
    np.testing.assert_allclose(image[:, 3], np.broadcast_to(expected, (4, 3)), atol=1e-6)


def test_blender_downscale_block_means_and_rescales_intrinsics(tmp_path):
  root = _write_blender(tmp_path, width=8, height=6)
  full = datasets.load_blender(root)
  half = datasets.load_blender(root, downscale=2)
  image = full.train_images[0]
  np.testing.assert_allclose(half.train_images[0], image.reshape(3, 2, 4, 2, 3).mean((1, 3)), atol=1e-6)
  camera = half.train_cameras[0]
  assert (camera.width, camera.height) == (4, 3)
  np.testing.assert_allclose(float(camera.fx), float(full.train_cameras[0].fx) / 2, rtol=1e-6)
  odd = datasets.load_blender(root, downscale=1.5)
  assert odd.train_images[0].shape == (4, 5, 3)  # round(6 / 1.5), round(8 / 1.5)
  assert (odd.train_cameras[0].width, odd.train_cameras[0].height) == (5, 4)
  assert 0.0 <= odd.train_images[0].min() and odd.train_images[0].max() <= 1.0
  np.testing.assert_allclose(odd.train_images[0].mean(), image.mean(), atol=0.03)


def test_blender_file_path_with_extension_and_split_choice(tmp_path):
  root = _write_blender(tmp_path, counts={"train": 2, "val": 1, "test": 3}, ext=".png")
  scene = datasets.load_blender(root, splits=(("train", "val"), ()))
  assert len(scene.train_images) == 3 and scene.test_images == [] and scene.test_cameras == []


def test_blender_missing_image_names_the_file(tmp_path):
  root = _write_blender(tmp_path)
  (root / "test" / "r_1.png").unlink()
  with pytest.raises(DatasetError, match=r"test/r_1\.png"):
    datasets.load_blender(root)


def test_blender_missing_folder_json_and_bad_json(tmp_path):
  with pytest.raises(DatasetError, match="nowhere"):
    datasets.load_blender(tmp_path / "nowhere")
  root = _write_blender(tmp_path / "scene")
  (root / "transforms_test.json").unlink()
  with pytest.raises(DatasetError, match="transforms_test.json"):
    datasets.load_blender(root)
  (root / "transforms_test.json").write_text('{"frames": []}')
  with pytest.raises(DatasetError, match="camera_angle_x"):
    datasets.load_blender(root)


def test_corrupt_image_names_the_file(tmp_path):
  root = _write_blender(tmp_path)
  (root / "train" / "r_2.png").write_bytes(b"not a png")
  with pytest.raises(DatasetError, match=r"r_2\.png"):
    datasets.load_blender(root)


def test_bad_downscale_and_background_are_rejected(tmp_path):
  root = _write_blender(tmp_path)
  with pytest.raises(DatasetError, match="downscale"):
    datasets.load_blender(root, downscale=0)
  with pytest.raises(DatasetError, match="background"):
    datasets.load_blender(root, background=(1.0, 1.0))


def test_scene_extent_is_11_tenths_of_the_largest_centre_distance(tmp_path):
  root = _write_blender(tmp_path, counts={"train": 4, "test": 1})
  scene = datasets.load_blender(root)
  # Four cameras on a circle of radius 3 at height 1: mean centre (0, 0, 1), all 3 away.
  assert scene.scene_extent() == pytest.approx(3.3, rel=1e-5)


# ---------------------------------------------------------------------------------------------------
# Lens distortion, checked against an independent OpenCV formula


def _opencv_distort(x, y, k1, k2, p1, p2):
  r2 = x * x + y * y
  radial = 1 + k1 * r2 + k2 * r2 * r2
  return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
          y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def _opencv_undistort(xd, yd, coefficients):
  x, y = xd.copy(), yd.copy()
  for _ in range(100):  # fixed point x = xd - (distort(x) - x); converges for mild lenses
    dx, dy = _opencv_distort(x, y, *coefficients)
    x, y = x - (dx - xd), y - (dy - yd)
  return x, y


def _pattern(x, y):
  """A smooth colour function of normalised camera coordinates: [..., 3]."""
  return np.stack([0.5 + 0.4 * np.sin(6.0 * x + c) * np.cos(5.0 * y - c) for c in (0.0, 1.0, 2.0)], -1)


LENS = dict(width=64, height=48, fx=50.0, fy=52.0, cx=31.0, cy=25.0)
COEFFICIENTS = (-0.3, 0.08, 0.01, -0.008)  # k1, k2, p1, p2: a strong barrel lens


def _distorted_photo():
  """What a lens with COEFFICIENTS photographs of _pattern: [H, W, 3]."""
  cols, rows = np.meshgrid(np.arange(LENS["width"]) + 0.5, np.arange(LENS["height"]) + 0.5)
  x, y = _opencv_undistort((cols - LENS["cx"]) / LENS["fx"], (rows - LENS["cy"]) / LENS["fy"],
                           COEFFICIENTS)
  return _pattern(x, y)


def _pinhole_truth(width, height, fx, fy, cx, cy):
  cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
  return _pattern((cols - cx) / fx, (rows - cy) / fy)


def _assert_undistorted(image, camera, tolerance):
  truth = _pinhole_truth(camera.width, camera.height, float(camera.fx), float(camera.fy),
                         float(camera.cx), float(camera.cy))
  border = max(2, camera.width // 8)  # the corners see past the lens, where edge pixels repeat
  inner = (slice(border, -border), slice(border, -border))
  assert np.abs(image[inner] - truth[inner]).max() < tolerance


def test_distorted_photo_differs_from_pinhole_truth():
  # Makes the undistortion tests meaningful: skipping undistortion would fail them.
  truth = _pinhole_truth(**{k: LENS[k] for k in ("width", "height", "fx", "fy", "cx", "cy")})
  assert np.abs(_distorted_photo() - truth)[8:-8, 8:-8].max() > 0.1


# ---------------------------------------------------------------------------------------------------
# COLMAP (text model written by hand)


def _write_colmap_text(root, camera_line, names, size, image=None, points=True, subdir="sparse/0"):
  """One shared camera; images named `names` on an orbit; two 3D points."""
  sparse = root / subdir
  sparse.mkdir(parents=True)
  (sparse / "cameras.txt").write_text(f"# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n1 {camera_line}\n")
  lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
  for i, (name, w2c) in enumerate(zip(names, _orbit_w2c(len(names)))):
    qx, qy, qz, qw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
    tx, ty, tz = w2c[:3, 3]
    lines += [f"{i + 1} {qw} {qx} {qy} {qz} {tx} {ty} {tz} 1 {name}", ""]
    _write_png(root / "images" / name, image if image is not None else _gradient(size[1], size[0], seed=i))
  (sparse / "images.txt").write_text("\n".join(lines) + "\n")
  (sparse / "points3D.txt").write_text(
      "1 0.1 0.2 0.3 255 0 51 0.5\n2 -0.5 0.0 0.25 0 255 0 0.7\n" if points else "")
  return root


def test_colmap_text_poses_split_and_points(tmp_path):
  names = [f"img_{i:02d}.png" for i in (9, 3, 0, 7, 1, 8, 2, 4, 6, 5)]  # deliberately unsorted
  root = _write_colmap_text(tmp_path, "PINHOLE 16 12 20 21 8.5 6.5", names, (16, 12))
  scene = datasets.load_colmap(root)
  assert scene.test_names == ["img_00.png", "img_08.png"]
  assert scene.train_names == [f"img_{i:02d}.png" for i in (1, 2, 3, 4, 5, 6, 7, 9)]
  camera = scene.test_cameras[1]
  assert (camera.width, camera.height) == (16, 12)
  assert [float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy)] == [20, 21, 8.5, 6.5]
  w2c = _orbit_w2c(len(names))[names.index("img_08.png")]
  np.testing.assert_allclose(np.asarray(camera.world_to_camera), w2c, atol=1e-5)
  image = iio.imread(root / "images" / "img_08.png") / 255.0
  np.testing.assert_allclose(scene.test_images[1], image, atol=1e-6)
  np.testing.assert_allclose(scene.points, [[0.1, 0.2, 0.3], [-0.5, 0.0, 0.25]], atol=1e-6)
  np.testing.assert_allclose(scene.point_colors, [[1.0, 0.0, 0.2], [0.0, 1.0, 0.0]], atol=1e-6)
  assert scene.points.dtype == np.float32 and scene.background == (0.0, 0.0, 0.0)


def test_colmap_without_points_and_sparse_folder_without_0(tmp_path):
  root = _write_colmap_text(tmp_path, "SIMPLE_PINHOLE 8 6 9 4 3", ["a.png", "b.png"], (8, 6),
                            points=False, subdir="sparse")
  scene = datasets.load_colmap(root, test_every=0)
  assert scene.points is None and scene.point_colors is None
  assert len(scene.train_images) == 2 and scene.test_images == []
  assert float(scene.train_cameras[0].fy) == 9.0


@pytest.mark.parametrize("downscale, tolerance", [(1, 0.01), (2, 0.02)])
def test_colmap_opencv_camera_is_undistorted(tmp_path, downscale, tolerance):
  lens = LENS
  params = " ".join(str(v) for v in (lens["fx"], lens["fy"], lens["cx"], lens["cy"]) + COEFFICIENTS)
  root = _write_colmap_text(tmp_path, f"OPENCV {lens['width']} {lens['height']} {params}",
                            ["a.png"], (lens["width"], lens["height"]), image=_distorted_photo())
  scene = datasets.load_colmap(root, downscale=downscale, test_every=0)
  camera = scene.train_cameras[0]
  assert camera.width == lens["width"] // downscale
  np.testing.assert_allclose(float(camera.fx), lens["fx"] / downscale, rtol=1e-6)
  _assert_undistorted(scene.train_images[0], camera, tolerance)


def test_colmap_image_size_mismatch_names_the_image(tmp_path):
  root = _write_colmap_text(tmp_path, "PINHOLE 16 12 20 20 8 6", ["a.png", "b.png"], (16, 12))
  _write_png(root / "images" / "b.png", _gradient(12, 15))
  with pytest.raises(DatasetError, match=r"b\.png is 15x12, not a downscaled copy of the 16x12 .*cameras\.txt"):
    datasets.load_colmap(root)


def test_colmap_downscaled_copies_resize_the_cameras(tmp_path):
  """images_2 as Inria's convert.py writes it: the cameras follow each copy's size, whatever the folder name."""
  names = ["a.png", "b.png"]
  root = _write_colmap_text(tmp_path, "PINHOLE 16 12 20 21 8.5 6.5", names, (16, 12))
  for i, name in enumerate(names):
    _write_png(root / "images_2" / name, _gradient(6, 8, seed=i))
  full = datasets.load_scene(root, test_every=0).train_cameras[1]
  for downscale, size in ((1, 2), (2, 4)):
    scene = datasets.load_scene(root, downscale, images="images_2", test_every=0)
    camera = scene.train_cameras[1]
    assert (camera.width, camera.height) == (16 // size, 12 // size)
    np.testing.assert_allclose([float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy)],
                               np.array([20, 21, 8.5, 6.5]) / size, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(camera.world_to_camera), np.asarray(full.world_to_camera))
    assert scene.train_images[1].shape == (12 // size, 16 // size, 3)
  _write_png(root / "images_2" / "b.png", _gradient(3, 8))
  with pytest.raises(DatasetError, match=r"b\.png is 8x3, not a downscaled copy of the 16x12"):
    datasets.load_scene(root, images="images_2")


def test_colmap_unsupported_and_unknown_camera_models(tmp_path):
  fisheye = _write_colmap_text(tmp_path / "f", "SIMPLE_RADIAL_FISHEYE 8 6 9 4 3 0.1", ["a.png"], (8, 6))
  with pytest.raises(DatasetError, match=r"cameras\.txt.*SIMPLE_RADIAL_FISHEYE"):
    datasets.load_colmap(fisheye)
  unknown = _write_colmap_text(tmp_path / "u", "NO_SUCH_MODEL 8 6 9 4 3", ["a.png"], (8, 6))
  with pytest.raises(DatasetError, match="sparse/0"):
    datasets.load_colmap(unknown)


def test_colmap_missing_files(tmp_path):
  root = _write_colmap_text(tmp_path, "PINHOLE 8 6 9 9 4 3", ["a.png", "b.png"], (8, 6))
  (root / "images" / "b.png").unlink()
  with pytest.raises(DatasetError, match=r"images/b\.png"):
    datasets.load_colmap(root)
  (root / "sparse" / "0" / "points3D.txt").unlink()
  with pytest.raises(DatasetError, match="points3D"):
    datasets.load_colmap(root)
  with pytest.raises(DatasetError, match="cameras.bin or cameras.txt"):
    datasets.load_colmap(tmp_path / "images")


# ---------------------------------------------------------------------------------------------------
# instant-ngp / nerfstudio transforms.json


def _write_transforms(root, meta, frames, images):
  for name, image in images.items():
    _write_png(root / name, image)
  (root / "transforms.json").write_text(json.dumps(dict(meta, frames=frames)))
  return root


def _frames(names, **extra):
  return [dict({"file_path": name, "transform_matrix": (np.linalg.inv(w2c) @ GL_FLIP).tolist()}, **extra)
          for name, w2c in zip(names, _orbit_w2c(len(names)))]


def test_transforms_global_and_per_frame_intrinsics(tmp_path):
  names = [f"images/f{i}.png" for i in range(9)]
  frames = _frames(names)
  frames[3].update(fl_x=30.0, cx=5.0)  # per-frame values win over the global ones
  meta = {"fl_x": 20.0, "fl_y": 22.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6}
  root = _write_transforms(tmp_path, meta, frames, {n: _gradient(6, 8) for n in names})
  scene = datasets.load_transforms(root)
  assert scene.test_names == ["f0.png", "f8.png"] and len(scene.train_images) == 7
  by_name = dict(zip(scene.train_names, scene.train_cameras))
  assert [float(v) for v in (by_name["f3.png"].fx, by_name["f3.png"].fy, by_name["f3.png"].cx)] == [30, 22, 5]
  assert [float(v) for v in (by_name["f1.png"].fx, by_name["f1.png"].cx, by_name["f1.png"].cy)] == [20, 4, 3]
  np.testing.assert_allclose(np.asarray(by_name["f2.png"].world_to_camera), _orbit_w2c(9)[2], atol=1e-6)
  assert scene.points is None


def test_transforms_camera_angle_fallback_and_image_size(tmp_path):
  names = ["a.png", "b"]  # the second has no extension: .png is implied
  images = {"a.png": _gradient(6, 10), "b.png": _gradient(6, 10)}
  root = _write_transforms(tmp_path, {"camera_angle_x": 1.0}, _frames(names), images)
  scene = datasets.load_transforms(root, test_every=0)
  camera = scene.train_cameras[1]
  assert (camera.width, camera.height) == (10, 6)
  np.testing.assert_allclose(float(camera.fx), 5 / math.tan(0.5), rtol=1e-6)
  assert float(camera.fy) == pytest.approx(float(camera.fx)) and float(camera.cy) == 3.0


@pytest.mark.parametrize("downscale, tolerance", [(1, 0.01), (2, 0.02)])
def test_transforms_distortion_is_undistorted(tmp_path, downscale, tolerance):
  k1, k2, p1, p2 = COEFFICIENTS
  meta = {"fl_x": LENS["fx"], "fl_y": LENS["fy"], "cx": LENS["cx"], "cy": LENS["cy"],
          "w": LENS["width"], "h": LENS["height"], "k1": k1, "k2": k2, "p1": p1, "p2": p2}
  root = _write_transforms(tmp_path, meta, _frames(["a.png"]), {"a.png": _distorted_photo()})
  scene = datasets.load_transforms(root, downscale=downscale, test_every=0)
  _assert_undistorted(scene.train_images[0], scene.train_cameras[0], tolerance)


def test_transforms_reads_the_point_cloud(tmp_path):
  from plyfile import PlyData, PlyElement
  vertices = np.array([(0.5, 1.0, -2.0, 255, 128, 0)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                                              ("red", "u1"), ("green", "u1"), ("blue", "u1")])
  PlyData([PlyElement.describe(vertices, "vertex")]).write(str(tmp_path / "sparse_pc.ply"))
  meta = {"fl_x": 10.0, "ply_file_path": "sparse_pc.ply"}
  root = _write_transforms(tmp_path, meta, _frames(["a.png"]), {"a.png": _gradient(6, 8)})
  scene = datasets.load_transforms(root, test_every=0)
  np.testing.assert_allclose(scene.points, [[0.5, 1.0, -2.0]])
  np.testing.assert_allclose(scene.point_colors, [[1.0, 128 / 255, 0.0]], atol=1e-6)


def test_transforms_errors_name_the_file(tmp_path):
  root = _write_transforms(tmp_path / "size", {"fl_x": 10.0, "w": 9, "h": 6}, _frames(["a.png"]),
                           {"a.png": _gradient(6, 8)})
  with pytest.raises(DatasetError, match=r"a\.png is 8x6 .*transforms\.json is 9x6"):
    datasets.load_transforms(root)
  root = _write_transforms(tmp_path / "fisheye", {"fl_x": 10.0, "camera_model": "OPENCV_FISHEYE"},
                           _frames(["a.png"]), {"a.png": _gradient(6, 8)})
  with pytest.raises(DatasetError, match=r"transforms\.json.*OPENCV_FISHEYE"):
    datasets.load_transforms(root)
  root = _write_transforms(tmp_path / "focal", {}, _frames(["a.png"]), {"a.png": _gradient(6, 8)})
  with pytest.raises(DatasetError, match=r"transforms\.json.*fl_x"):
    datasets.load_transforms(root)


# ---------------------------------------------------------------------------------------------------
# Dispatch


def test_load_scene_detects_the_format(tmp_path):
  blender = _write_blender(tmp_path / "b")
  colmap = _write_colmap_text(tmp_path / "c", "PINHOLE 8 6 9 9 4 3", ["a.png"], (8, 6))
  transforms = _write_transforms(tmp_path / "t", {"fl_x": 10.0}, _frames(["a.png"]),
                                 {"a.png": _gradient(6, 8)})
  assert datasets.detect_format(blender) == "blender"
  assert datasets.detect_format(colmap) == "colmap"
  assert datasets.detect_format(transforms) == "transforms"
  assert datasets.load_scene(blender).background == (1.0, 1.0, 1.0)
  assert len(datasets.load_scene(str(colmap), background=(0, 0, 1)).test_images) == 1
  assert datasets.load_scene("colmap", root=colmap, test_every=0).test_images == []
  assert datasets.load_scene(transforms, downscale=2).test_images[0].shape == (3, 4, 3)
  (tmp_path / "empty").mkdir()
  with pytest.raises(DatasetError, match="empty"):
    datasets.load_scene(tmp_path / "empty")
  with pytest.raises(DatasetError, match="root"):
    datasets.load_scene("blender")


def test_a_format_is_complete_only_with_every_file_its_loader_reads(tmp_path):
  blender = _write_blender(tmp_path / "b")
  colmap = _write_colmap_text(tmp_path / "c", "PINHOLE 8 6 9 9 4 3", ["a.png"], (8, 6))
  transforms = _write_transforms(tmp_path / "t", {"fl_x": 10.0}, _frames(["a.png"]), {"a.png": _gradient(6, 8)})
  assert datasets.format_check(blender, "blender").complete
  assert datasets.format_check(colmap, "colmap") == (True, "a COLMAP model in sparse/0 (cameras, images, "
                                                         "points3D), images in images/", "images")
  (blender / "transforms_test.json").unlink()
  assert datasets.format_check(blender, "blender")[:2] == (False, "no transforms_test.json")
  (colmap / "images").rename(colmap / "images_2")  # only a downscaled copy: read by default, and said
  assert datasets.format_check(colmap, "colmap").images == "images_2"
  (colmap / "images_2").rename(colmap / "pictures")
  assert datasets.format_check(colmap, "colmap").reason.endswith("but no images folder images/")
  assert datasets.detect_format(colmap, images="pictures") == "colmap"
  with pytest.raises(DatasetError, match=r"colmap: [^;]*no images folder images/;.* holding images: pictures/$"):
    datasets.load_scene(colmap)
  # A json that names each image leaves nothing for an images folder to choose.
  check = datasets.format_check(transforms, "transforms", images="images_2")
  assert check[:2] == (False, "the images are named in transforms.json, so the images folder 'images_2' does not "
                       "apply")
  with pytest.raises(DatasetError, match="the images folder 'images_2' does not apply"):
    datasets.load_scene(transforms, images="images_2")
  with pytest.raises(DatasetError, match="also given the format 'llff'"):
    datasets.load_scene("colmap", root=colmap, data_format="llff")
  with pytest.raises(DatasetError, match="unknown scene format 'nerf'"):
    datasets.load_scene(colmap, data_format="nerf")


# ---------------------------------------------------------------------------------------------------
# Real data (../shared/data; absent on a user's machine)


@pytest.mark.skipif(not LEGO.is_dir(), reason=f"real data not available at {LEGO}")
def test_lego_loads_at_half_resolution():
  scene = datasets.load_blender(LEGO, downscale=2, splits=("train", ()))
  assert len(scene.train_images) == 100 and len(scene.train_cameras) == 100
  assert all(image.shape == (200, 200, 3) and image.dtype == np.float32 for image in scene.train_images)
  fov = json.loads((LEGO / "transforms_train.json").read_text())["camera_angle_x"]
  for camera in scene.train_cameras:
    assert (camera.width, camera.height) == (200, 200)
    assert float(camera.fx) == pytest.approx(100 / math.tan(fov / 2), rel=1e-5)
    uv, z = _project(camera, np.zeros((1, 3)))  # the model sits around the origin
    assert z[0] > 0 and _inside(uv, camera)[0]
    assert np.linalg.norm(uv[0] - 100) < 40
  image = scene.train_images[0]
  np.testing.assert_allclose(image[0, 0], 1.0, atol=1e-6)  # white background in the corner
  assert 0.05 < (image < 0.99).any(-1).mean() < 0.9  # but the model covers part of the frame
  assert 4.0 < scene.scene_extent() < 6.0  # cameras on a sphere of radius ~4 around the model


@pytest.fixture(scope="module")
def beer():
  if not BEER.is_dir():
    pytest.skip(f"real data not available at {BEER}")
  return datasets.load_colmap(BEER, downscale=4)


def test_beer_colmap_split_sizes_and_images(beer):
  names = sorted(p.name for p in (BEER / "images").iterdir())
  assert len(names) == 71
  assert beer.test_names == names[::8] and len(beer.test_names) == 9
  assert sorted(beer.train_names + beer.test_names) == names
  for image, camera in zip(beer.train_images + beer.test_images, beer.train_cameras + beer.test_cameras):
    assert image.shape == (320, 180, 3) and (camera.width, camera.height) == (180, 320)
    assert 0.0 <= image.min() and image.max() <= 1.0
  assert beer.points.shape == (4414, 3) and beer.point_colors.shape == (4414, 3)
  assert 0.0 <= beer.point_colors.min() and beer.point_colors.max() <= 1.0
  assert beer.scene_extent() > 0


def test_beer_sfm_points_project_into_the_frames(beer):
  for camera in beer.train_cameras + beer.test_cameras:
    uv, z = _project(camera, beer.points)
    in_front = z > 0
    assert in_front.mean() > 0.5
    assert _inside(uv[in_front], camera).mean() > 0.7


def test_beer_cameras_reproject_colmap_observations(beer):
  """Pose and intrinsics agree with the keypoints COLMAP observed (distorted, full-resolution)."""
  import pycolmap
  reconstruction = pycolmap.Reconstruction(str(BEER / "sparse" / "0"))
  images = {image.name: image for image in reconstruction.images.values()}
  errors = []
  names, cameras = beer.train_names[::5] + beer.test_names, beer.train_cameras[::5] + beer.test_cameras
  for name, camera in zip(names, cameras):
    image = images[name]
    observed = [(p.xy, reconstruction.points3D[p.point3D_id].xyz) for p in image.points2D
                if p.has_point3D()]
    keypoints, points = (np.array(v) for v in zip(*observed))
    uv, _ = _project(camera, points)
    scale = 720 / camera.width  # back to the distorted full-resolution frame of the keypoints
    f, cx, cy, k = image.camera.params
    x, y = (uv[:, 0] * scale - cx) / f, (uv[:, 1] * scale - cy) / f
    xd, yd = _opencv_distort(x, y, k, 0.0, 0.0, 0.0)
    errors.append(np.median(np.hypot(xd * f + cx - keypoints[:, 0], yd * f + cy - keypoints[:, 1])))
  assert np.median(errors) < 1.0  # COLMAP's own mean reprojection error here is 0.75 px
