"""The 3D Gaussian scene as a pytree, and the activations that turn its raw parameters into geometry.

Raw parameters are stored unconstrained (log scales, opacity logits, unnormalised quaternions), as in
3D-GS (Kerbl et al. 2023, arXiv:2308.04079, Sec. 4 and 5.1), so that an optimiser can move them freely;
the functions here are its activations: scale = exp, opacity = sigmoid, rotation = normalised quaternion.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# A quaternion with squared norm below this is treated as the zero quaternion: it maps to the identity
# rotation (the rotation formula of a zero vector), and its gradient stays finite.
_QUAT_NORM_FLOOR = 1e-24


@struct.dataclass
class Gaussians:
  """N anisotropic 3D Gaussians.

  means: [N, 3] world-space centres.
  log_scales: [N, 3] log standard deviations along the principal axes.
  quats: [N, 4] rotation as (w, x, y, z), not necessarily normalised.
  opacity_logits: [N] logit of the peak opacity.
  sh: [N, (D+1)^2, 3] spherical-harmonic colour coefficients, DC first.
  """
  means: jax.Array
  log_scales: jax.Array
  quats: jax.Array
  opacity_logits: jax.Array
  sh: jax.Array

  @property
  def num(self) -> int:
    return self.means.shape[0]

  @property
  def sh_degree(self) -> int:
    """Largest SH degree the coefficients can represent."""
    return int(round(self.sh.shape[1] ** 0.5)) - 1

  @classmethod
  def empty(cls, sh_degree: int = 0, dtype=jnp.float32) -> "Gaussians":
    n_coeffs = (sh_degree + 1) ** 2
    return cls(means=jnp.zeros((0, 3), dtype), log_scales=jnp.zeros((0, 3), dtype),
               quats=jnp.zeros((0, 4), dtype), opacity_logits=jnp.zeros((0,), dtype),
               sh=jnp.zeros((0, n_coeffs, 3), dtype))


def scales(gaussians: Gaussians) -> jax.Array:
  """[N, 3] standard deviations: exp of the stored log scales."""
  return jnp.exp(gaussians.log_scales)


def opacities(gaussians: Gaussians) -> jax.Array:
  """[N] peak opacities in (0, 1): sigmoid of the stored logits."""
  return jax.nn.sigmoid(gaussians.opacity_logits)


def opacity_logit(opacity):
  """The stored logit of a peak opacity in (0, 1), the inverse of `opacities`' sigmoid: log(o) - log(1 - o) (a
  float or numpy array in, numpy out; a jax array or tracer in, one out)."""
  xp = jnp if isinstance(opacity, jax.Array) else np
  return xp.log(opacity) - xp.log1p(-opacity)


def normalize_quaternion(quats: jax.Array) -> jax.Array:
  """[N, 4] -> [N, 4] unit quaternions; the zero quaternion stays zero (finite value and gradient)."""
  sq_norm = jnp.sum(quats**2, axis=-1, keepdims=True)
  return quats * jax.lax.rsqrt(jnp.maximum(sq_norm, _QUAT_NORM_FLOOR))


def quaternion_to_rotation(quats: jax.Array) -> jax.Array:
  """[N, 4] (w, x, y, z) -> [N, 3, 3] rotation matrices (zero quaternion -> identity)."""
  w, x, y, z = jnp.moveaxis(normalize_quaternion(quats), -1, 0)
  return jnp.stack([
      jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
      jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
      jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
  ], -2)


def covariance_3d(gaussians: Gaussians) -> jax.Array:
  """[N, 3, 3] world-space covariances Sigma = R S S^T R^T (3D-GS eq. 6)."""
  rs = quaternion_to_rotation(gaussians.quats) * scales(gaussians)[..., None, :]
  return rs @ jnp.swapaxes(rs, -1, -2)


def with_sh_degree(gaussians: Gaussians, degree: int) -> Gaussians:
  """The same scene storing `degree` SH bands: missing bands are zero, which add nothing to a render.
  ValueError if the scene stores more bands than that (dropping bands changes its colours)."""
  if gaussians.sh_degree > degree:
    raise ValueError(f"the scene has SH degree {gaussians.sh_degree}, above {degree}")
  missing = (degree + 1) ** 2 - gaussians.sh.shape[1]
  return gaussians.replace(sh=jnp.pad(jnp.asarray(gaussians.sh), ((0, 0), (0, missing), (0, 0))))


def concatenate(parts: list[Gaussians]) -> Gaussians:
  """Joins several Gaussian sets along N."""
  return jax.tree.map(lambda *xs: jnp.concatenate(xs, axis=0), *parts)
