"""A small generated Gaussian scene for the render job and notebooks (no data needed).

Points on a sphere and on a ground disc, coloured by position, initialised as 3D-GS does from a point
cloud; deterministic for a given seed.
"""
from __future__ import annotations

import numpy as np

from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.gs.init import gaussians_from_points


def sphere_and_ground(num_points: int, sh_degree: int = 3, seed: int = 0) -> Gaussians:
  """num_points Gaussians: 60% on a unit sphere at height 0.2, 40% on a disc of radius 2 at z = -0.8."""
  if num_points < 2:
    raise ValueError(f"the generated scene needs at least 2 points, got {num_points}")
  rng = np.random.default_rng(seed)
  n_sphere = int(0.6 * num_points)
  direction = rng.normal(size=(n_sphere, 3))
  direction /= np.linalg.norm(direction, axis=1, keepdims=True)
  sphere = direction * 0.8 + np.array([0.0, 0.0, 0.2])
  sphere_rgb = 0.5 + 0.5 * direction  # a colour wheel over the normal directions
  n_disc = num_points - n_sphere
  radius, angle = 2.0 * np.sqrt(rng.uniform(size=n_disc)), rng.uniform(0, 2 * np.pi, n_disc)
  disc = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.full(n_disc, -0.8)], 1)
  checker = ((np.floor(disc[:, 0] * 2) + np.floor(disc[:, 1] * 2)) % 2)[:, None]
  disc_rgb = 0.25 + 0.5 * checker * np.array([[1.0, 0.9, 0.6]])
  return gaussians_from_points(np.concatenate([sphere, disc]), np.concatenate([sphere_rgb, disc_rgb]),
                               sh_degree=sh_degree, opacity=0.9)
