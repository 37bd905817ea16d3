"""Scene attacks (robust/scene_attacks.py): turns, moves and resizes with the order shuffled, each returning
the similarity it applied, which registration recovers."""
from __future__ import annotations

import numpy as np
import pytest

from conceal_jax.gs import register as reg
from conceal_jax.gs import similarity as sim
from conceal_jax.gs.scene_gen import sphere_and_ground
from conceal_jax.robust import scene_attacks as sa
from conceal_jax.robust.image_attacks import MEDIUM, MILD, STRONG


@pytest.fixture(scope="module")
def scene():
  return sphere_and_ground(3000, sh_degree=1)


def centre_of(g) -> np.ndarray:
  return np.asarray(g.means, np.float64).mean(0)


@pytest.mark.parametrize("name, level, severity", sa.LEVELS)
def test_every_level_applies_its_similarity_and_shuffles(scene, name, level, severity):
  assert severity in (MILD, MEDIUM, STRONG)
  attacked, similarity = sa.attack(scene, name, level, seed=3)
  assert attacked.num == scene.num
  moved = np.asarray(sim.transform_gaussians(scene, similarity).means, np.float64)
  # Shuffled: not in the original order, but the same set of transformed centres.
  assert not np.allclose(np.asarray(attacked.means), moved, atol=1e-5)
  np.testing.assert_array_equal(np.sort(np.asarray(attacked.means, np.float64), axis=0), np.sort(moved, axis=0))


def test_levels_mean_what_they_say(scene):
  centre = centre_of(scene)
  _, radius, _, _ = reg.principal_frame(np.asarray(scene.means, np.float64))
  rotated, r = sa.attack(scene, "rotate", 90.0)
  np.testing.assert_allclose(r.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
  np.testing.assert_allclose(centre_of(rotated), centre, atol=1e-5)  # turned about the centroid
  moved, t = sa.attack(scene, "translate", 0.026, seed=5)
  np.testing.assert_allclose(np.linalg.norm(centre_of(moved) - centre), 0.026 * radius, rtol=1e-4)
  resized, s = sa.attack(scene, "scale", 1.1)
  assert s.scale == 1.1
  np.testing.assert_allclose(reg.principal_frame(np.asarray(resized.means, np.float64))[1], 1.1 * radius, rtol=1e-5)
  _, a = sa.attack(scene, "similarity", 10.0, seed=1)
  _, b = sa.attack(scene, "similarity", 10.0, seed=2)
  assert 0.1 <= a.scale <= 10 and not np.allclose(a.rotation, b.rotation)


@pytest.mark.parametrize("name, level", [("rotate", 180.0), ("similarity", 10.0)])
def test_registration_undoes_the_attack(scene, name, level):
  attacked, truth = sa.attack(scene, name, level, seed=7)
  found = reg.register(scene, attacked).similarity
  # Exact up to the attacked scene's float32 storage (its centres lie up to ~10 radii * scale away).
  np.testing.assert_allclose(found.rotation, truth.rotation, atol=1e-6)
  np.testing.assert_allclose(found.scale, truth.scale, rtol=1e-6)
  np.testing.assert_allclose(found.translation, truth.translation, atol=1e-5 * max(1.0, truth.scale) * 10)


@pytest.mark.parametrize("name, level, fragment", [("warp", 1.0, "unknown scene attack"),
                                                   ("scale", 0.0, "positive"), ("similarity", 0.5, "at least 1")])
def test_bad_attack(scene, name, level, fragment):
  with pytest.raises(ValueError, match=fragment):
    sa.attack(scene, name, level)
