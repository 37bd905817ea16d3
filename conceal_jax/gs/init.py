"""Initial Gaussians from a point cloud, as 3D-GS initialises from SfM or random points (Kerbl et al. 2023,
arXiv:2308.04079, Sec. 5.1 and 7.1)."""
from __future__ import annotations

import numpy as np
import jax.numpy as jnp
from scipy.spatial import cKDTree

from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.gaussians import Gaussians, opacity_logit

INIT_OPACITY = 0.1
# 3D-GS floors the mean squared neighbour distance so coincident points still get a positive scale.
_MIN_SQ_DIST = 1e-7
# A random start in a capture's frustums caps each splat's scale at this share of the image width at its depth:
# sparse random points would otherwise get neighbour scales of a tenth of the image, splats that each cover
# dozens of tiles and set the cost of every early step, where a few pixels each still cover the image many
# times over from thousands of points.
FRUSTUM_START_SCREEN_FRACTION = 0.01


def nearest_neighbour_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
  """[M, 3] -> [M] sqrt of the mean squared distance to the k nearest other points (3D-GS init)."""
  if points.shape[0] <= 1:
    return np.ones(points.shape[0])
  k = min(k, points.shape[0] - 1)
  dist, _ = cKDTree(points).query(points, k=k + 1)  # the nearest hit is the point itself
  return np.sqrt(np.maximum(np.mean(dist[:, 1:] ** 2, axis=1), _MIN_SQ_DIST))


def gaussians_from_points(points: np.ndarray, colors: np.ndarray, sh_degree: int = 3,
                          opacity: float = INIT_OPACITY, dtype=jnp.float32,
                          max_scales: np.ndarray | None = None) -> Gaussians:
  """Isotropic Gaussians at `points` [M, 3] with colours `colors` [M, 3] in [0, 1] as the DC term, each of
  the nearest-neighbour scale, at most `max_scales` [M] where given."""
  points = np.asarray(points, np.float64)
  sh = np.zeros((points.shape[0], sh_lib.num_coefficients(sh_degree), 3))
  sh[:, 0] = np.asarray(sh_lib.rgb_to_sh_dc(np.asarray(colors, np.float64)))
  scale = nearest_neighbour_scale(points)
  log_scale = np.log(scale if max_scales is None else np.minimum(scale, max_scales))
  quats = np.zeros((points.shape[0], 4))
  quats[:, 0] = 1.0
  as_array = lambda x: jnp.asarray(x, dtype)
  return Gaussians(means=as_array(points), log_scales=as_array(np.repeat(log_scale[:, None], 3, 1)),
                   quats=as_array(quats),
                   opacity_logits=as_array(np.full(points.shape[0], opacity_logit(opacity))),
                   sh=as_array(sh))


def frustum_start_scales(footprints: np.ndarray) -> np.ndarray:
  """[M] world width of the image at each start point's depth -> [M] largest scale of its splat."""
  return FRUSTUM_START_SCREEN_FRACTION * np.asarray(footprints, np.float64)


def random_box_points(rng: np.random.Generator, num: int, half_extent: float) -> tuple[np.ndarray, np.ndarray]:
  """Uniform random points in the cube [-half_extent, half_extent]^3 with random colours (3D-GS's start for
  synthetic scenes): points [num, 3] and colours [num, 3] in [0, 1]."""
  return rng.uniform(-half_extent, half_extent, (num, 3)), rng.uniform(0.0, 1.0, (num, 3))
