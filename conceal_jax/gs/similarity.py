"""Similarity transforms x -> s R x + t of a Gaussian scene and of its cameras, and reordering.

What an editor does to a shared scene on import (turn it, move it, resize it) and what a converter does to
its storage order, as pure functions. Transforming a scene moves every Gaussian's mean, multiplies its
scales by s, turns its orientation by R and turns its view-dependent colour with it: the SH coefficients of
band l are multiplied by the band's rotation matrix, so that the colour seen along R d afterwards is the
colour seen along d before. Transforming a camera the same way keeps every render identical (camera-space
coordinates are scaled by s, which a pinhole projection does not see; only the renderer's near plane, an
absolute depth, must be scaled by s too).

Transform parameters live on the host in float64 (numpy); scenes are transformed in their own dtype.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians

# Directions at which each band's rotation matrix is fitted: a Fibonacci sphere of this many points,
# several times more than the largest band's 2l + 1 = 7 functions, so the fit is well conditioned and exact.
_FIT_DIRECTIONS = 64


@dataclasses.dataclass(frozen=True)
class Similarity:
  """x -> scale * rotation @ x + translation. rotation: [3, 3] proper (det +1); translation: [3];
  scale: positive float. Host-side float64."""
  rotation: np.ndarray
  translation: np.ndarray
  scale: float

  def __post_init__(self):
    rotation = np.asarray(self.rotation, np.float64)
    translation = np.asarray(self.translation, np.float64)
    if rotation.shape != (3, 3) or translation.shape != (3,):
      raise ValueError(f"a similarity needs a [3, 3] rotation and a [3] translation, got {rotation.shape} "
                       f"and {translation.shape}")
    if not np.all(np.isfinite(rotation)) or not np.all(np.isfinite(translation)):
      raise ValueError("the similarity's rotation and translation must be finite")
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
      raise ValueError(f"rotation is not a proper rotation matrix (R R^T = I, det +1): {rotation.tolist()}")
    if not (np.isfinite(self.scale) and self.scale > 0):
      raise ValueError(f"scale must be positive and finite, got {self.scale}")
    object.__setattr__(self, "rotation", rotation)
    object.__setattr__(self, "translation", translation)
    object.__setattr__(self, "scale", float(self.scale))

  @classmethod
  def identity(cls) -> "Similarity":
    return cls(np.eye(3), np.zeros(3), 1.0)

  def matrix(self) -> np.ndarray:
    """[4, 4] homogeneous matrix [[s R, t], [0, 1]]."""
    out = np.eye(4)
    out[:3, :3] = self.scale * self.rotation
    out[:3, 3] = self.translation
    return out


def apply_to_points(similarity: Similarity, points):
  """[..., 3] -> [..., 3] s R x + t, in the points' dtype (numpy in, numpy out; jax likewise)."""
  xp = np if isinstance(points, np.ndarray) else jnp
  linear = xp.asarray(similarity.scale * similarity.rotation, points.dtype)
  return points @ linear.T + xp.asarray(similarity.translation, points.dtype)


def compose(outer: Similarity, inner: Similarity) -> Similarity:
  """The similarity x -> outer(inner(x))."""
  return Similarity(outer.rotation @ inner.rotation,
                    outer.scale * outer.rotation @ inner.translation + outer.translation,
                    outer.scale * inner.scale)


def inverse(similarity: Similarity) -> Similarity:
  """The similarity undoing `similarity`: x -> R^T (x - t) / s."""
  rotation_t = similarity.rotation.T
  return Similarity(rotation_t, -rotation_t @ similarity.translation / similarity.scale,
                    1.0 / similarity.scale)


def rotation_from_axis_angle(axis, angle: float) -> np.ndarray:
  """[3, 3] rotation by `angle` radians about `axis` (any non-zero length), Rodrigues' formula."""
  axis = np.asarray(axis, np.float64)
  norm = np.linalg.norm(axis)
  if not norm > 0:
    raise ValueError(f"rotation axis must be non-zero, got {axis.tolist()}")
  k = axis / norm
  cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
  return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def random_rotation(rng: np.random.Generator) -> np.ndarray:
  """[3, 3] rotation drawn uniformly (Haar measure) from a normalised Gaussian quaternion."""
  return quaternion_to_matrix(rng.normal(size=4))


def quaternion_to_matrix(quat) -> np.ndarray:
  """(w, x, y, z), any non-zero length -> [3, 3] float64 rotation (the formula of
  splat.gaussians.quaternion_to_rotation, on the host)."""
  w, x, y, z = np.asarray(quat, np.float64) / np.linalg.norm(quat)
  return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quaternion(rotation) -> np.ndarray:
  """[..., 3, 3] rotations -> [..., 4] unit quaternions (w, x, y, z) with w >= 0, the inverse of
  quaternion_to_matrix.

  Read off the largest of the four squared components (Shepperd's method), so it is accurate for every
  rotation, 180 degrees included."""
  r = np.asarray(rotation, np.float64)
  batch, r = r.shape[:-2], r.reshape(-1, 3, 3)
  trace = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
  squares = np.stack([1 + trace, 1 + 2 * r[:, 0, 0] - trace, 1 + 2 * r[:, 1, 1] - trace, 1 + 2 * r[:, 2, 2] - trace],
                     axis=-1)
  every = np.arange(len(r))
  i = np.argmax(squares, axis=-1)
  big = 0.5 * np.sqrt(squares[every, i])
  # Off-diagonal sums and differences: 4 w x, 4 w y, 4 w z, 4 x y, 4 x z, 4 y z.
  wx, wy, wz = r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]
  xy, xz, yz = r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1]
  zero = np.zeros_like(trace)
  # Row i: 4 q_i q_j for j = w, x, y, z (the diagonal entry is unused, replaced by q_i itself).
  products = np.stack([np.stack(row, axis=-1) for row in ([zero, wx, wy, wz], [wx, zero, xy, xz], [wy, xy, zero, yz],
                                                           [wz, xz, yz, zero])], axis=1)
  q = products[every, i] / (4 * big)[:, None]
  q[every, i] = big
  q = np.where(q[:, :1] >= 0, q, -q)
  return q.reshape(batch + (4,))


def quaternion_multiply(a, b):
  """Hamilton product a b of [..., 4] (w, x, y, z) quaternions: the rotation of b, then that of a."""
  aw, ax, ay, az = (a[..., i] for i in range(4))
  bw, bx, by, bz = (b[..., i] for i in range(4))
  xp = np if isinstance(a, np.ndarray) and isinstance(b, np.ndarray) else jnp
  return xp.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                   aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def fibonacci_sphere(n: int) -> np.ndarray:
  """[n, 3] float64 unit vectors spread evenly over the sphere."""
  i = np.arange(n) + 0.5
  z = 1 - 2 * i / n
  phi = np.pi * (1 + 5**0.5) * i
  r = np.sqrt(1 - z * z)
  return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def sh_band_rotations(rotation, degree: int) -> list[np.ndarray]:
  """[2l+1, 2l+1] float64 matrices M_l, l = 1..degree, in splat.sh's basis (3D-GS order and signs), with
  Y_l(R d) = M_l Y_l(d) for every direction d.

  Rotation maps each band onto itself, so Y_l(R d) is linear in Y_l(d): M_l is the exact least-squares
  solution of that identity over fixed directions d_i that span the band. It is orthogonal (the basis is
  orthonormal within a band)."""
  if not 0 <= degree <= sh_lib.MAX_DEGREE:
    raise ValueError(f"SH degree must be in 0..{sh_lib.MAX_DEGREE}, got {degree}")
  rotation = np.asarray(rotation, np.float64)
  directions = fibonacci_sphere(_FIT_DIRECTIONS)
  with jax.enable_x64(True):  # the basis of splat.sh itself, evaluated in float64
    basis = np.asarray(sh_lib.sh_basis(jnp.asarray(directions), degree))
    turned = np.asarray(sh_lib.sh_basis(jnp.asarray(directions @ rotation.T), degree))
  out = []
  for l in range(1, degree + 1):
    band = slice(l * l, (l + 1) * (l + 1))
    # turned_band = basis_band @ M^T, i.e. M^T = lstsq(basis_band, turned_band).
    m_t, *_ = np.linalg.lstsq(basis[:, band], turned[:, band], rcond=None)
    out.append(m_t.T)
  return out


def rotate_sh(sh: jnp.ndarray, rotation) -> jnp.ndarray:
  """[N, K, 3] SH coefficients of colours f(d) -> those of f(R^T d): the colour seen along R d afterwards
  is the colour seen along d before. DC is unchanged; band l becomes M_l c_l (M_l orthogonal)."""
  degree = int(round(sh.shape[1]**0.5)) - 1
  if (degree + 1)**2 != sh.shape[1]:
    raise ValueError(f"SH coefficient count {sh.shape[1]} is not a square (degree + 1)^2")
  # c'^T Y(R d) = c^T Y(d) for all d and Y(R d) = M Y(d) give M^T c' = c, so c' = M c (M orthogonal).
  blocks = [sh[:, :1, :]]
  for l, m in enumerate(sh_band_rotations(rotation, degree), start=1):
    band = sh[:, l * l:(l + 1) * (l + 1), :]
    blocks.append(jnp.einsum("ij,njc->nic", jnp.asarray(m, sh.dtype), band))
  return jnp.concatenate(blocks, axis=1)


def transform_gaussians(gaussians: Gaussians, similarity: Similarity) -> Gaussians:
  """The scene moved by x -> s R x + t: means transformed, log-scales + log s, orientations turned by R
  (its quaternion times each Gaussian's, lengths kept), SH colour turned with the scene; opacities kept.
  In the scene's dtype."""
  dtype = gaussians.means.dtype
  quat = jnp.asarray(matrix_to_quaternion(similarity.rotation), dtype)
  return Gaussians(
      means=apply_to_points(similarity, jnp.asarray(gaussians.means)),
      log_scales=gaussians.log_scales + jnp.asarray(np.log(similarity.scale), dtype),
      quats=quaternion_multiply(quat[None, :], jnp.asarray(gaussians.quats)),
      opacity_logits=gaussians.opacity_logits,
      sh=rotate_sh(jnp.asarray(gaussians.sh), similarity.rotation))


def transform_world_to_camera(world_to_camera, similarity: Similarity) -> np.ndarray:
  """[4, 4] OpenCV world-to-camera of the same camera after the world moved by `similarity`: camera
  rotation Rc R^T, translation s tc - Rc R^T t, so that camera-space points are s times the old ones."""
  w2c = np.asarray(world_to_camera, np.float64)
  rotation = w2c[:3, :3] @ similarity.rotation.T
  out = np.eye(4)
  out[:3, :3] = rotation
  out[:3, 3] = similarity.scale * w2c[:3, 3] - rotation @ similarity.translation
  return out


def transform_camera(camera: Camera, similarity: Similarity) -> Camera:
  """The camera that sees the transformed scene as `camera` saw the original (same intrinsics and size).
  Depths are s times the old ones: render with the near plane scaled by s for identical images."""
  w2c = transform_world_to_camera(camera.world_to_camera, similarity)
  return camera.replace(world_to_camera=jnp.asarray(w2c, camera.world_to_camera.dtype))


def permute_gaussians(gaussians: Gaussians, order) -> Gaussians:
  """The Gaussians in the order `order` ([N] permutation or any index array: a subset keeps those)."""
  order = np.asarray(order)
  return jax.tree.map(lambda x: jnp.asarray(x)[order], gaussians)


def shuffle_gaussians(gaussians: Gaussians, rng: np.random.Generator) -> tuple[Gaussians, np.ndarray]:
  """The same scene in a random order (renders are unchanged up to the order of equal-depth splats), and
  the [N] permutation used: shuffled Gaussian i is original Gaussian order[i]."""
  order = rng.permutation(gaussians.num)
  return permute_gaussians(gaussians, order), order
