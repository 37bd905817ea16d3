"""EWA splatting: project 3D Gaussians to screen-space 2D Gaussians (3D-GS, Kerbl et al. 2023,
arXiv:2308.04079, Sec. 4, eq. 5).

Every function works on all N Gaussians at once and keeps values and gradients finite for any input:
Gaussians that cannot be drawn (behind the near plane, degenerate or non-finite) are culled by
masking, and the culled lanes are fed harmless stand-in values *before* any division so that no NaN
can leak into the backward pass (the "double where" pattern).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from conceal_jax.splat import gaussians as gs
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera, camera_center

# Low-pass filter added to the 2D covariance so every splat covers at least about a pixel (3D-GS).
DILATION = 0.3
# Antialiased mode keeps at least this fraction (0.005^2 under the square root) of the opacity.
MIN_AA_COMPENSATION_SQ = 0.005**2
# The Jacobian is evaluated at x/z, y/z clamped this far beyond the image edge (3D-GS uses 1.3 tan(fov/2)).
FRUSTUM_MARGIN = 0.3
# exp(LOG_SCALE_MAX) is larger than any scene; clamping keeps S S^T J^2 finite in float32.
LOG_SCALE_MAX = 20.0


@struct.dataclass
class Splats2D:
  """N projected Gaussians; lanes with radii == 0 are culled and hold zeros.

  means2d: [N, 2] pixel coordinates (u, v); conics: [N, 3] inverse 2D covariance (A, B, C);
  depths: [N] camera-space z; opacities: [N]; colors: [N, 3]; radii: [N] int32 3-sigma pixel radius;
  cov2d: [N, 3] (a, b, c) of the dilated screen covariance [[a, b], [b, c]] (for the pair tests of binning).
  """
  means2d: jax.Array
  conics: jax.Array
  depths: jax.Array
  opacities: jax.Array
  colors: jax.Array
  radii: jax.Array
  cov2d: jax.Array


def to_camera_frame(points: jax.Array, world_to_camera: jax.Array) -> jax.Array:
  """[N, 3] world points -> [N, 3] camera-space points (OpenCV axes)."""
  return points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]


def perspective_jacobian(p_cam: jax.Array, camera: Camera) -> jax.Array:
  """[N, 3] camera-space points (z > 0) -> [N, 2, 3] Jacobian of the pinhole projection (EWA).

  x/z and y/z are clamped to the frustum widened by FRUSTUM_MARGIN, as in 3D-GS, so splats far
  outside the view do not blow up; where clamped, the Jacobian no longer depends on x or y.
  """
  x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
  margin_x = FRUSTUM_MARGIN * 0.5 * camera.width / camera.fx
  margin_y = FRUSTUM_MARGIN * 0.5 * camera.height / camera.fy
  tx = jnp.clip(x / z, -camera.cx / camera.fx - margin_x, (camera.width - camera.cx) / camera.fx + margin_x)
  ty = jnp.clip(y / z, -camera.cy / camera.fy - margin_y, (camera.height - camera.cy) / camera.fy + margin_y)
  zero = jnp.zeros_like(z)
  inv_z = 1.0 / z
  return jnp.stack([
      jnp.stack([camera.fx * inv_z, zero, -camera.fx * tx * inv_z], -1),
      jnp.stack([zero, camera.fy * inv_z, -camera.fy * ty * inv_z], -1),
  ], -2)


def project_covariance(cov3d: jax.Array, jacobian: jax.Array, world_to_camera: jax.Array) -> jax.Array:
  """Sigma' = J W Sigma W^T J^T (3D-GS eq. 5): [N, 3, 3] world covariances -> [N, 2, 2] pixel covariances."""
  jw = jacobian @ world_to_camera[:3, :3]
  return jw @ cov3d @ jnp.swapaxes(jw, -1, -2)


def dilate(cov2d: jax.Array, antialiased: bool) -> tuple[jax.Array, jax.Array | None]:
  """Adds the DILATION low-pass filter to [N, 2, 2] covariances.

  Returns the dilated covariances and, when `antialiased` (static), the opacity compensation
  sqrt(max(0.005^2, det(Sigma) / det(Sigma + 0.3 I))) that keeps a splat's integrated energy (Mip-Splatting);
  otherwise None, and nothing is computed for it.
  """
  eye = jnp.eye(2, dtype=cov2d.dtype)
  dilated = cov2d + DILATION * eye
  if not antialiased:
    return dilated, None
  # Normalised by the trace so that the determinants stay finite for huge splats.
  trace = dilated[:, 0, 0] + dilated[:, 1, 1]
  det_ratio = normalized_det(cov2d, trace) / normalized_det(dilated, trace)
  return dilated, jnp.sqrt(jnp.maximum(MIN_AA_COMPENSATION_SQ, det_ratio))


def normalized_det(cov2d: jax.Array, trace: jax.Array) -> jax.Array:
  """det(cov2d) / trace^2 for [N, 2, 2] symmetric matrices: scale-free, so it cannot overflow."""
  a, b, c = cov2d[:, 0, 0] / trace, cov2d[:, 0, 1] / trace, cov2d[:, 1, 1] / trace
  return a * c - b * b


def conic_and_radius(cov2d: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
  """[N, 2, 2] dilated covariances -> conic [N, 3] = (c, -b, a) / det, radius [N], and an ok mask [N].

  radius = ceil(3 sqrt(lambda_max)), lambda_max = mid + sqrt(max(0.1, mid^2 - det)) (3D-GS). Computed
  relative to the trace so huge splats keep a finite determinant. ok is False where det <= 0.
  """
  trace = cov2d[:, 0, 0] + cov2d[:, 1, 1]
  det_n = normalized_det(cov2d, trace)
  ok = det_n > 0
  safe_det_n = jnp.where(ok, det_n, 1.0)
  a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
  conic = jnp.stack([c, -b, a], -1) / (safe_det_n * trace * trace)[:, None]
  # mid^2 - det = trace^2 (1/4 - det_n); lambda_max is only used for the (non-differentiable) radius.
  lambda_max = trace * (0.5 + jnp.sqrt(jnp.maximum(0.1 / (trace * trace), 0.25 - det_n)))
  radius = jnp.ceil(3.0 * jnp.sqrt(jax.lax.stop_gradient(lambda_max)))
  return conic, radius, ok


def project(gaussians: gs.Gaussians, camera: Camera, sh_degree: int, near: float,
            antialiased: bool) -> Splats2D:
  """Projects N Gaussians into `camera`: EWA covariance, conic, 3-sigma radius, SH colour, opacity.

  sh_degree and antialiased are static: lower degrees evaluate fewer SH bands, and the antialiasing
  compensation is only traced when asked for.
  """
  # log scale -inf is a legitimate zero scale (a flat or point-like Gaussian); NaN and +inf are not.
  valid_log_scales = ~jnp.isnan(gaussians.log_scales) & (gaussians.log_scales < jnp.inf)
  finite_params = jnp.all(jnp.isfinite(gaussians.means), -1) & jnp.all(valid_log_scales, -1)
  finite_params &= jnp.all(jnp.isfinite(gaussians.quats), -1) & jnp.isfinite(gaussians.opacity_logits)
  finite_params &= jnp.all(jnp.isfinite(gaussians.sh[:, :sh_lib.num_coefficients(sh_degree)]), (-1, -2))
  # Stand-ins for culled lanes: a unit Gaussian in front of the camera keeps every formula finite.
  safe = _sanitize(gaussians, finite_params)

  p_cam = to_camera_frame(safe.means, camera.world_to_camera)
  in_front = p_cam[:, 2] > near
  visible = finite_params & in_front
  p_cam = jnp.where(visible[:, None], p_cam, jnp.array([0.0, 0.0, 1.0], p_cam.dtype))
  z = p_cam[:, 2]
  means2d = jnp.stack([camera.fx * p_cam[:, 0] / z + camera.cx, camera.fy * p_cam[:, 1] / z + camera.cy], -1)

  bounded = safe.replace(log_scales=jnp.minimum(safe.log_scales, LOG_SCALE_MAX))
  cov2d = project_covariance(gs.covariance_3d(bounded), perspective_jacobian(p_cam, camera),
                             camera.world_to_camera)
  cov2d, compensation = dilate(cov2d, antialiased)
  conics, radii, det_ok = conic_and_radius(cov2d)

  opacities = gs.opacities(safe)
  if compensation is not None:
    opacities = opacities * compensation
  colors = sh_lib.sh_to_rgb(safe.sh, safe.means, camera_center(camera), sh_degree)

  keep = visible & det_ok & jnp.all(jnp.isfinite(means2d), -1) & jnp.all(jnp.isfinite(conics), -1)
  keep &= jnp.isfinite(radii) & (radii > 0)
  zeros = lambda x: jnp.where(keep.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0)
  # Radii are clipped before the integer cast: a splat wider than any image needs no exact radius.
  radii = jnp.where(keep, jnp.minimum(radii, 2.0**30), 0).astype(jnp.int32)
  return Splats2D(means2d=zeros(means2d), conics=zeros(conics), depths=zeros(z),
                  opacities=zeros(opacities), colors=zeros(colors), radii=radii,
                  cov2d=zeros(jnp.stack([cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]], -1)))


def _sanitize(gaussians: gs.Gaussians, finite: jax.Array) -> gs.Gaussians:
  """Replaces the parameters of non-finite lanes by a harmless unit Gaussian (for finite gradients)."""
  def fill(x, value):
    return jnp.where(finite.reshape((-1,) + (1,) * (x.ndim - 1)), x, value)
  return gs.Gaussians(means=fill(gaussians.means, 0.0), log_scales=fill(gaussians.log_scales, 0.0),
                      quats=fill(gaussians.quats, jnp.array([1.0, 0, 0, 0], gaussians.quats.dtype)),
                      opacity_logits=fill(gaussians.opacity_logits, 0.0), sh=fill(gaussians.sh, 0.0))
