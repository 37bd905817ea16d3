"""Registration of a suspect scene onto the owner's (gs/register.py): any rotation (180 degrees included),
scale 0.1-10 and translation, recovered from the Gaussians alone after shuffling, decimation (uniform and
by importance), subsampling with noise and densification; its building blocks against closed forms."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.data import demo_scene
from conceal_jax.gs import register as reg
from conceal_jax.gs import similarity as sim
from conceal_jax.gs.init import gaussians_from_points
from conceal_jax.gs.scene_gen import sphere_and_ground
from conceal_jax.splat.camera import look_at


@functools.lru_cache(maxsize=None)
def demo_gaussians() -> "sim.Gaussians":
  """The embedded demo scene's surfaces (sphere, box, textured ground disc) as its own ray caster sees them
  from 8 orbit views at 48 px: one Gaussian per hit, coloured by the shaded texture (about 6700)."""
  rng = np.random.default_rng(0)
  textures = demo_scene._textures()
  points, colours = [], []
  for eye in demo_scene.orbit_positions(rng, 8):
    origin, directions = demo_scene.camera_rays(look_at(eye, (0.0, 0.0, 0.0)), 48, 1)
    hit, colour = demo_scene.cast_rays(origin, directions, textures)
    depth = np.min([f(origin, directions) for f in (demo_scene._sphere_depth, demo_scene._box_depth,
                                                    demo_scene._disc_depth)], axis=0)
    points.append((origin + depth[:, None] * directions.T)[hit])
    colours.append(colour[hit])
  return gaussians_from_points(np.concatenate(points), np.clip(np.concatenate(colours), 0, 1), sh_degree=1,
                               opacity=0.8)


@functools.lru_cache(maxsize=None)
def blob_gaussians(seed: int, single_colour: bool = False, n: int = 5000):
  """Eight anisotropic coloured clusters; with single_colour, every Gaussian has the same colour, so only
  geometry (the principal-axes candidates) can register it."""
  rng = np.random.default_rng(seed)
  centres = rng.normal(size=(8, 3)) * np.array([2.0, 1.0, 0.5])
  label = rng.integers(8, size=n)
  points = centres[label] + rng.normal(size=(n, 3)) * 0.3
  colours = np.full((n, 3), 0.4) if single_colour else np.clip(
      rng.uniform(size=(8, 3))[label] + rng.normal(size=(n, 3)) * 0.05, 0, 1)
  return gaussians_from_points(points, colours, sh_degree=2, opacity=0.5)


@functools.lru_cache(maxsize=None)
def colour_ball(seed: int = 3, n: int = 4000):
  """A round shell coloured by direction: its geometry has no preferred axes, so only colour (the
  colour-cluster candidates) can register it."""
  rng = np.random.default_rng(seed)
  d = rng.normal(size=(n, 3))
  d /= np.linalg.norm(d, axis=1, keepdims=True)
  return gaussians_from_points(d * rng.uniform(0.9, 1.0, (n, 1)), 0.5 + 0.5 * d, sh_degree=0, opacity=0.6)


SCENES = {"demo": demo_gaussians, "blobs": lambda: blob_gaussians(1), "single_colour": lambda: blob_gaussians(2, True),
          "colour_ball": colour_ball, "sphere_and_ground": lambda: sphere_and_ground(5000, 1)}


def decimate(g, keep: float, rng, by_importance: bool = False):
  """keep a fraction of the Gaussians: at random, or those of largest opacity times volume (as pruning
  tools rank them)."""
  if by_importance:
    importance = np.asarray(jax.nn.sigmoid(g.opacity_logits)) * np.exp(np.asarray(g.log_scales).sum(1))
    return sim.permute_gaussians(g, np.argsort(-importance)[:int(keep * g.num)])
  return sim.permute_gaussians(g, rng.choice(g.num, int(keep * g.num), replace=False))


def densify(g, fraction: float, rng):
  """Adds fraction * N copies of random Gaussians moved by a sample of their own Gaussian (3D-GS split)."""
  extra = rng.choice(g.num, int(fraction * g.num))
  grown = sim.permute_gaussians(g, np.concatenate([np.arange(g.num), extra]))
  means = np.asarray(grown.means).copy()
  means[g.num:] += rng.normal(size=(len(extra), 3)) * np.exp(np.asarray(grown.log_scales)[g.num:])
  return grown.replace(means=jnp.asarray(means, jnp.float32))


def perturb(g, position_noise: float, sh_noise: float, rng):
  """Parameter noise: centres by position_noise times the scene's RMS radius, SH by sh_noise."""
  radius = float(np.sqrt(np.var(np.asarray(g.means), 0).sum()))
  return g.replace(means=g.means + jnp.asarray(rng.normal(size=g.means.shape) * position_noise * radius, jnp.float32),
                   sh=g.sh + jnp.asarray(rng.normal(size=g.sh.shape) * sh_noise, jnp.float32))


ATTACKS = {
    "decimate_50": lambda g, rng: decimate(g, 0.5, rng),
    "importance_50": lambda g, rng: decimate(g, 0.5, rng, by_importance=True),
    "subsample_10_noise": lambda g, rng: perturb(decimate(g, 0.1, rng), 0.002, 0.05, rng),
    "densify_50": lambda g, rng: decimate(densify(g, 0.5, rng), 0.9, rng),
}


def errors(estimate: sim.Similarity, truth: sim.Similarity, radius: float) -> tuple[float, float, float]:
  """Rotation error in degrees, relative scale error, translation error in suspect-scene radii."""
  relative = estimate.rotation @ truth.rotation.T
  angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
  return (float(angle), abs(estimate.scale / truth.scale - 1),
          float(np.linalg.norm(estimate.translation - truth.translation) / (truth.scale * radius)))


def truth_for(seed: int) -> sim.Similarity:
  """A random similarity; seeds 0 and 1 turn by exactly 180 degrees, and the scales span 0.1 to 10."""
  rng = np.random.default_rng(1000 + seed)
  rotation = (sim.rotation_from_axis_angle(rng.normal(size=3), np.pi) if seed < 2 else sim.random_rotation(rng))
  scale = [0.1, 10.0, 0.37, 3.3, 1.0, 6.0][seed % 6]
  return sim.Similarity(rotation, rng.normal(size=3) * 5.0, scale)


CASES = [("demo", "decimate_50", 0), ("demo", "importance_50", 1), ("demo", "subsample_10_noise", 2),
         ("demo", "densify_50", 3), ("blobs", "decimate_50", 4), ("blobs", "subsample_10_noise", 1),
         ("single_colour", "importance_50", 0), ("single_colour", "decimate_50", 5),
         ("colour_ball", "decimate_50", 2), ("sphere_and_ground", "importance_50", 3),
         ("sphere_and_ground", "densify_50", 4)]


@pytest.mark.parametrize("scene, attack, seed", CASES)
def test_register_recovers_the_similarity(scene, attack, seed):
  owner = SCENES[scene]()
  truth = truth_for(seed)
  rng = np.random.default_rng(seed)
  suspect, _ = sim.shuffle_gaussians(sim.transform_gaussians(ATTACKS[attack](owner, rng), truth), rng)
  result = reg.register(owner, suspect)
  rotation, scale, translation = errors(result.similarity, truth, result.owner_radius)
  if attack in ("decimate_50", "importance_50"):
    # Every suspect Gaussian is an owner Gaussian: exact up to the suspect's float32 storage (its means, up
    # to 5 + 10 radii from the origin, are rounded to 6e-8 of that).
    assert rotation < 1e-3 and scale < 1e-5 and translation < 2e-5, (rotation, scale, translation)
    assert result.residual < 1e-5 and result.matched_fraction == 1.0
  else:
    assert rotation < 0.1 and scale < 1e-3 and translation < 1e-3, (rotation, scale, translation)
    assert result.residual < 1e-2 and result.matched_fraction > 0.7


def test_register_of_identical_scenes_is_the_identity():
  owner = blob_gaussians(1)
  result = reg.register(owner, owner)
  np.testing.assert_allclose(result.similarity.matrix(), np.eye(4), atol=1e-9)
  assert result.residual < 1e-9 and result.matched_fraction == 1.0


def test_unrelated_scene_leaves_a_large_residual():
  result = reg.register(blob_gaussians(1), blob_gaussians(7))
  assert result.residual > 0.03 and result.matched_fraction < 0.5


def test_umeyama_recovers_an_exact_similarity_and_excludes_reflections():
  rng = np.random.default_rng(0)
  truth = sim.Similarity(sim.rotation_from_axis_angle([1.0, 2.0, -1.0], np.pi), [1.0, -2.0, 3.0], 0.2)
  source = rng.normal(size=(30, 3))
  fit = reg.umeyama(source, sim.apply_to_points(truth, source))
  np.testing.assert_allclose(fit.matrix(), truth.matrix(), atol=1e-12)
  mirrored = source * np.array([1.0, 1.0, -1.0])
  assert np.linalg.det(reg.umeyama(source, mirrored).rotation) > 0


def test_proper_signed_permutations_are_the_24_cube_rotations():
  rotations = reg.proper_signed_permutations()
  assert rotations.shape == (24, 3, 3)
  assert len({r.tobytes() for r in rotations}) == 24
  for r in rotations:
    np.testing.assert_allclose(r @ r.T, np.eye(3))
    assert np.isclose(np.linalg.det(r), 1.0)


def test_principal_frame_is_right_handed_and_sorted():
  points = np.random.default_rng(1).normal(size=(500, 3)) * np.array([3.0, 0.5, 1.5]) + 4.0
  centre, radius, axes, variances = reg.principal_frame(points)
  assert np.all(np.diff(variances) < 0) and np.isclose(np.linalg.det(axes), 1.0)
  np.testing.assert_allclose(radius, np.sqrt(np.sum(np.var(points, 0))), rtol=1e-12)
  assert abs(axes[0, 0]) > 0.99 and abs(axes[2, 1]) > 0.99  # x has the largest variance, then z


@pytest.mark.parametrize("make, fragment", [
    (lambda g: sim.permute_gaussians(g, np.arange(10)), "at least 16 Gaussians"),
    (lambda g: g.replace(means=g.means.at[3, 1].set(jnp.nan)), "finite means"),
])
def test_bad_input(make, fragment):
  good = blob_gaussians(1)
  with pytest.raises(ValueError, match=fragment):
    reg.register(good, make(good))
  with pytest.raises(ValueError, match=fragment):
    reg.register(make(good), good)


def test_owner_at_one_point_is_refused():
  g = blob_gaussians(1)
  with pytest.raises(ValueError, match="one point"):
    reg.register(g.replace(means=jnp.zeros_like(g.means)), g)
