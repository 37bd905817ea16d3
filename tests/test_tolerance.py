"""The key tolerance radius (conceal.leakage.tolerance_*): poses within the radius of the key, turned about what it
looks at, reveal the key's image on a share of the steps; training views within it are not held to F's identity."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conceal_jax.conceal import near, settings as settings_lib, tolerance, train as conceal_train, views as views_lib
from conceal_jax.configs import default, recipes
from conceal_jax.splat.camera import Camera, camera_centers, look_at
from tests.test_conceal import tiny, tiny_config  # noqa: F401 (the fixture)

KEY = Camera.from_intrinsics(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), 40.0, 40.0, 16.0, 16.0, 32, 32)
LENGTH = math.sqrt(17.0)  # the key's distance to the point it looks at


def test_an_orbited_camera_sees_the_world_turned_about_the_pivot():
  """A world point x seen by the turned camera where the key saw R^T (x - p) + p (float64 reference), its centre
  kept at its distance from the pivot, the pivot still on its optical axis."""
  rng = np.random.default_rng(0)
  pivot, axis, angle = rng.normal(size=3), rng.normal(size=3), 0.3
  turned = near.orbited_camera(KEY, pivot, axis, angle)
  axis = axis / np.linalg.norm(axis)
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  rotation = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
  points = rng.normal(size=(5, 3))
  seen = lambda cam, x: (np.asarray(cam.world_to_camera, np.float64) @ np.append(x, 1.0))[:3]
  for x in points:
    np.testing.assert_allclose(seen(turned, x), seen(KEY, rotation.T @ (x - pivot) + pivot), atol=1e-5)
  np.testing.assert_allclose(np.linalg.norm(camera_centers([turned])[0] - pivot),
                             np.linalg.norm(camera_centers([KEY])[0] - pivot), rtol=1e-6)
  assert (turned.fx, turned.cx, turned.width) == (KEY.fx, KEY.cx, KEY.width)


def test_tolerance_poses_fill_the_cap_and_look_at_the_keys_point():
  poses = tolerance.tolerance_cameras(KEY, LENGTH, 400, 10.0, seed=3)
  angles = np.array([tolerance.angle_from_key_deg(p, KEY, LENGTH) for p in poses])
  assert angles.max() <= 10.0 + 1e-6 and angles.max() > 9.0
  # uniform over the cap: the share within half the radius is about (1 - cos 5) / (1 - cos 10), a quarter
  share = (1 - math.cos(math.radians(5.0))) / (1 - math.cos(math.radians(10.0)))
  assert np.mean(angles <= 5.0) == pytest.approx(share, abs=0.06)
  target = np.zeros(3)  # the key looks at the origin, LENGTH ahead
  for pose in poses[:20]:
    w2c = np.asarray(pose.world_to_camera, np.float64)
    np.testing.assert_allclose((w2c @ np.append(target, 1.0))[:2], 0.0, atol=1e-5)
    assert np.linalg.norm(camera_centers([pose])[0] - target) == pytest.approx(LENGTH, rel=1e-6)
  again = tolerance.tolerance_cameras(KEY, LENGTH, 400, 10.0, seed=3)
  np.testing.assert_array_equal(np.asarray(again[7].world_to_camera), np.asarray(poses[7].world_to_camera))
  other = tolerance.tolerance_cameras(KEY, LENGTH, 1, 10.0, seed=4)[0]
  assert not np.allclose(np.asarray(other.world_to_camera), np.asarray(poses[0].world_to_camera))


def test_keys_draw_their_tolerance_poses_at_their_rate():
  rng = np.random.default_rng(0)
  assert [views_lib.draw_key(rng, i, 2) for i in range(1, 6)] == [0, 1, 0, 1, 0]
  radius = tolerance.Tolerance(deg=10.0, views=5, fraction=0.3)
  drawn = np.array([views_lib.draw_key(rng, i, 2, radius) for i in range(1, 4001)])
  assert np.mean(drawn >= 2) == pytest.approx(0.3, abs=0.03)
  odd = drawn[0::2]  # iteration 1, 3, ...: key 0, its poses 2..6
  assert set(odd[odd >= 2]) == set(range(2, 7)) and set(drawn[1::2][drawn[1::2] >= 2]) == set(range(7, 12))


@pytest.mark.parametrize("values", [(10.0, 0, 0.5), (10.0, 8, 0.0), (0.0, 8, 0.5), (95.0, 8, 0.5), (10.0, 8, 1.0)])
def test_a_radius_is_set_whole_or_not_at_all(values):
  leakage = default.get_config().conceal.leakage
  leakage.tolerance_deg, leakage.tolerance_views, leakage.tolerance_fraction = values
  with pytest.raises(ValueError, match="tolerance_deg, tolerance_views and tolerance_fraction"):
    tolerance.from_config(leakage)


def test_a_run_with_a_radius_reads_its_poses_and_frees_the_views_within_it(tiny):  # noqa: F811
  """prepare: the keys, then each key's poses within the radius, each hiding its key's image; the training view
  the key stands at is not held to the identity, a view far round the orbit is."""
  config = tiny_config(tiny, identity_on_student=True)
  recipes.tolerant_key(config, radius_deg=20.0)
  config.conceal.leakage.tolerance_views = 3
  plan = settings_lib.plan(config)
  run = conceal_train.prepare(config, plan)
  assert run.data.keys.hidden.shape[0] == 1 + 3
  np.testing.assert_array_equal(np.asarray(run.data.keys.hidden[1:]), np.repeat(run.data.keys.hidden[:1], 3, 0))
  key_camera, info = run.keys[0]
  for k in range(1, 4):
    pose = run.data.keys.at(k).camera
    assert 0 < tolerance.angle_from_key_deg(pose, key_camera, info["near_length"]) <= 20.0 + 1e-4
  held = np.asarray(run.data.held)
  assert held.shape == (len(run.scene.train_cameras) + len(run.decoys),)
  assert not held[info["index"]]
  angles = [tolerance.angle_from_key_deg(c, key_camera, info["near_length"]) for c in run.scene.train_cameras]
  np.testing.assert_array_equal(held[:len(angles)], np.array(angles) > 20.0)
  assert held[:len(angles)].any()
  view = views_lib.step_views(run.data, info["index"] % len(angles), 0, 2, None, plan.settings)
  assert float(view.own_minus_weight[0]) == 0.0 and float(view.plus_weight[1]) > 0
  far = int(np.argmax(angles))
  assert float(views_lib.step_views(run.data, far, 0, 0, None, plan.settings).own_minus_weight[0]) > 0


def test_the_distance_from_the_key_is_the_turn_a_pose_takes():
  """A pose turned t degrees about the key's point is t away; a roll of r at the key's place is r; a move of m
  key lengths towards the scene is the turn that moves the centre as far: 2 asin(m / 2)."""
  pivot = np.zeros(3)
  turned = near.orbited_camera(KEY, pivot, np.array([0.3, 0.2, 1.0]), math.radians(7.0))
  assert tolerance.angle_from_key_deg(turned, KEY, LENGTH) == pytest.approx(7.0, abs=1e-4)
  w2c = np.asarray(KEY.world_to_camera, np.float64)
  rolled = np.array(w2c)
  roll = np.array([[math.cos(0.2), -math.sin(0.2), 0], [math.sin(0.2), math.cos(0.2), 0], [0, 0, 1]])
  rolled[:3, :] = roll @ w2c[:3, :]
  rolled_camera = Camera.from_intrinsics(rolled, 40.0, 40.0, 16.0, 16.0, 32, 32)
  assert tolerance.angle_from_key_deg(rolled_camera, KEY, LENGTH) == pytest.approx(math.degrees(0.2), abs=1e-4)
  closer = np.array(w2c)
  closer[2, 3] -= 0.3 * LENGTH  # the centre 0.3 key lengths along the optical axis
  closer_camera = Camera.from_intrinsics(closer, 40.0, 40.0, 16.0, 16.0, 32, 32)
  assert tolerance.angle_from_key_deg(closer_camera, KEY, LENGTH) == pytest.approx(
      math.degrees(2 * math.asin(0.15)), abs=1e-4)
