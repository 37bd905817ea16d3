"""What an editor does to a shared scene on import: turn it, move it, resize it, each with the Gaussians'
storage order shuffled. Pure functions Gaussians -> (Gaussians, Similarity): the transformed scene and the
similarity that maps the owner's scene onto it (what registration must recover before revealing).

Levels follow issue 39's bench rows: `rotate` in degrees about world z (the up axis of the demo scene and
of NeRF-Synthetic) through the scene's centroid, `translate` in fractions of the scene's RMS radius along a
seeded random direction, `scale` as a factor about the centroid, `similarity` a seeded random rotation,
translation and scale of every size at once (its level: the largest scale factor, drawn log-uniformly in
[1 / level, level]).
"""
from __future__ import annotations

import numpy as np

from conceal_jax.gs import similarity as sim
from conceal_jax.robust.image_attacks import MEDIUM, MILD, STRONG
from conceal_jax.splat.gaussians import Gaussians

UP = (0.0, 0.0, 1.0)


def _centre_and_radius(gaussians: Gaussians) -> tuple[np.ndarray, float]:
  """Centroid [3] and RMS radius of the Gaussians' centres (float64)."""
  means = np.asarray(gaussians.means, np.float64)
  if means.shape[0] == 0:
    raise ValueError("cannot transform an empty scene")
  centre = means.mean(0)
  return centre, float(np.sqrt(np.mean(np.sum((means - centre)**2, axis=1))))


def about_point(rotation: np.ndarray, scale: float, point: np.ndarray) -> sim.Similarity:
  """x -> s R (x - p) + p: a turn and resize that keep `point` in place."""
  return sim.Similarity(rotation, point - scale * rotation @ point, scale)


def rotation_similarity(gaussians: Gaussians, degrees: float, seed: int = 0) -> sim.Similarity:
  """A turn by `degrees` about world z through the scene's centroid (seed unused: the turn is fixed)."""
  del seed
  centre, _ = _centre_and_radius(gaussians)
  return about_point(sim.rotation_from_axis_angle(UP, np.radians(degrees)), 1.0, centre)


def translation_similarity(gaussians: Gaussians, fraction: float, seed: int = 0) -> sim.Similarity:
  """A move by `fraction` of the scene's RMS radius along a random direction drawn from `seed`."""
  _, radius = _centre_and_radius(gaussians)
  direction = np.random.default_rng(seed).normal(size=3)
  return sim.Similarity(np.eye(3), fraction * radius * direction / np.linalg.norm(direction), 1.0)


def scale_similarity(gaussians: Gaussians, factor: float, seed: int = 0) -> sim.Similarity:
  """A resize by `factor` about the scene's centroid (seed unused)."""
  del seed
  if not factor > 0:
    raise ValueError(f"scale factor must be positive, got {factor}")
  centre, _ = _centre_and_radius(gaussians)
  return about_point(np.eye(3), factor, centre)


def random_similarity(gaussians: Gaussians, max_factor: float, seed: int = 0) -> sim.Similarity:
  """A uniformly random rotation, a move by up to 10 RMS radii and a scale log-uniform in
  [1 / max_factor, max_factor], drawn from `seed`."""
  if not max_factor >= 1:
    raise ValueError(f"the largest scale factor must be at least 1, got {max_factor}")
  _, radius = _centre_and_radius(gaussians)
  rng = np.random.default_rng(seed)
  rotation = sim.random_rotation(rng)
  scale = float(np.exp(rng.uniform(-np.log(max_factor), np.log(max_factor))))
  return sim.Similarity(rotation, rng.uniform(-10.0, 10.0, size=3) * radius, scale)


SIMILARITIES = {"rotate": rotation_similarity, "translate": translation_similarity, "scale": scale_similarity,
                "similarity": random_similarity}

LEVELS = ([("rotate", d, MILD if d <= 1 else MEDIUM if d <= 5 else STRONG) for d in (1.0, 5.0, 90.0, 180.0)]
          + [("translate", f, MILD if f <= 0.01 else MEDIUM if f <= 0.05 else STRONG) for f in (0.01, 0.026, 1.0)]
          + [("scale", f, MILD if abs(np.log(f)) <= np.log(1.02) else MEDIUM if abs(np.log(f)) <= np.log(1.1)
              else STRONG) for f in (1.02, 1.1, 0.5, 3.0)]
          + [("similarity", 10.0, STRONG)])


def attack(gaussians: Gaussians, name: str, level, seed: int = 0) -> tuple[Gaussians, sim.Similarity]:
  """The scene transformed by the similarity `name` (a key of SIMILARITIES) at `level`, its Gaussians in a
  random order drawn from `seed`; and that similarity (owner -> attacked)."""
  if name not in SIMILARITIES:
    raise ValueError(f"unknown scene attack {name!r}; choose from {sorted(SIMILARITIES)}")
  similarity = SIMILARITIES[name](gaussians, level, seed)
  moved = sim.transform_gaussians(gaussians, similarity)
  shuffled, _ = sim.shuffle_gaussians(moved, np.random.default_rng(seed))
  return shuffled, similarity
