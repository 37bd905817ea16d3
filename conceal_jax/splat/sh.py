"""Real spherical harmonics up to degree 3: view-dependent colour of a Gaussian (3D-GS, Kerbl et al. 2023,
arXiv:2308.04079, Sec. 4)."""
from __future__ import annotations

import jax
import jax.numpy as jnp

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_DEGREE = 3

# A direction shorter than this (a Gaussian at the camera centre) is read as the zero vector, whose
# higher-order basis values are 0; the floor keeps the normalisation's gradient finite.
_DIR_NORM_FLOOR = 1e-24


def num_coefficients(degree: int) -> int:
  return (degree + 1) ** 2


def sh_basis(directions: jax.Array, degree: int) -> jax.Array:
  """[N, 3] unit directions -> [N, (degree+1)^2] real SH basis values.

  `degree` is static: a degree-0 scene evaluates the constant DC term only.
  """
  if not 0 <= degree <= MAX_DEGREE:
    raise ValueError(f"SH degree must be in 0..{MAX_DEGREE}, got {degree}")
  terms = [jnp.full(directions.shape[:-1], SH_C0, directions.dtype)]
  if degree >= 1:
    x, y, z = directions[..., 0], directions[..., 1], directions[..., 2]
    terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
  if degree >= 2:
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    terms += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
              SH_C2[4] * (xx - yy)]
  if degree >= 3:
    terms += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
              SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
              SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
  return jnp.stack(terms, axis=-1)


def safe_normalize(vectors: jax.Array) -> jax.Array:
  """[..., 3] -> unit vectors; the zero vector maps to zero with a finite gradient."""
  sq_norm = jnp.sum(vectors**2, axis=-1, keepdims=True)
  return vectors * jax.lax.rsqrt(jnp.maximum(sq_norm, _DIR_NORM_FLOOR))


def sh_to_rgb(sh: jax.Array, means: jax.Array, camera_center: jax.Array, degree: int) -> jax.Array:
  """View-dependent colour: SH(dir) + 0.5, clamped at 0 from below (3D-GS); [N, 3].

  sh: [N, >=(degree+1)^2, 3]; means: [N, 3]; camera_center: [3]. Only the first (degree+1)^2
  coefficients are read, so unused higher bands cost nothing.
  """
  n_coeffs = num_coefficients(degree)
  if sh.shape[-2] < n_coeffs:
    raise ValueError(f"SH degree {degree} needs {n_coeffs} coefficients, the scene has {sh.shape[-2]}")
  if degree == 0:
    colour = SH_C0 * sh[:, 0, :]
  else:
    basis = sh_basis(safe_normalize(means - camera_center), degree)
    colour = jnp.einsum("nk,nkc->nc", basis, sh[:, :n_coeffs, :])
  return jnp.maximum(colour + 0.5, 0.0)


def rgb_to_sh_dc(rgb: jax.Array) -> jax.Array:
  """Inverse of the degree-0 colour map (before clamping): the DC coefficient giving colour `rgb`."""
  return (rgb - 0.5) / SH_C0
