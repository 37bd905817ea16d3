"""Pinhole cameras in OpenCV axes (x right, y down, z forward), as a pytree.

A camera-space point (x, y, z) projects to u = fx x / z + cx, v = fy y / z + cy, and pixel (row i,
column j) is sampled at (u, v) = (j + 0.5, i + 0.5), the COLMAP convention.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# OpenGL/Blender camera axes are (x right, y up, z backward); OpenCV flips y and z.
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@struct.dataclass
class Camera:
  """world_to_camera: [4, 4] rigid transform; fx, fy, cx, cy: scalars in pixels; width, height static."""
  world_to_camera: jax.Array
  fx: jax.Array
  fy: jax.Array
  cx: jax.Array
  cy: jax.Array
  width: int = struct.field(pytree_node=False)
  height: int = struct.field(pytree_node=False)

  @classmethod
  def from_intrinsics(cls, world_to_camera, fx, fy, cx, cy, width: int, height: int,
                      dtype=jnp.float32) -> "Camera":
    if int(width) <= 0 or int(height) <= 0:
      raise ValueError(f"camera size must be positive, got {width}x{height}")
    w2c = np.asarray(world_to_camera, np.float64)
    if w2c.shape != (4, 4):
      raise ValueError(f"world_to_camera must be [4, 4], got {w2c.shape}")
    as_array = lambda v: jnp.asarray(v, dtype)
    return cls(world_to_camera=as_array(w2c), fx=as_array(fx), fy=as_array(fy), cx=as_array(cx),
               cy=as_array(cy), width=int(width), height=int(height))

  @classmethod
  def from_opengl_camera_to_world(cls, camera_to_world, fx, fy, cx, cy, width: int, height: int,
                                  dtype=jnp.float32) -> "Camera":
    """From an OpenGL/Blender camera-to-world matrix ([3, 4] or [4, 4]), e.g. NeRF-Synthetic poses."""
    c2w = np.eye(4)
    c2w[:3] = np.asarray(camera_to_world, np.float64)[:3]
    w2c = np.linalg.inv(c2w @ _OPENGL_TO_OPENCV)
    return cls.from_intrinsics(w2c, fx, fy, cx, cy, width, height, dtype)

  @classmethod
  def from_fov(cls, world_to_camera, fov_x: float, width: int, height: int, fov_y: float | None = None,
               dtype=jnp.float32) -> "Camera":
    """Centred principal point; fov in radians; square pixels unless fov_y is given."""
    fx = fov_to_focal(fov_x, width)
    fy = fx if fov_y is None else fov_to_focal(fov_y, height)
    return cls.from_intrinsics(world_to_camera, fx, fy, width / 2, height / 2, width, height, dtype)

  def rescale(self, factor: float) -> "Camera":
    """The same camera with an image `factor` times smaller (intrinsics and size divided)."""
    return self.resized(max(1, round(self.width / factor)), max(1, round(self.height / factor)))

  def resized(self, width: int, height: int) -> "Camera":
    """The same view on an image of width x height pixels: each axis' intrinsics scaled by its own factor,
    so the image covers the same field of view (what resizing this camera's image to that size shows)."""
    if int(width) <= 0 or int(height) <= 0:
      raise ValueError(f"camera size must be positive, got {width}x{height}")
    sx, sy = width / self.width, height / self.height
    return Camera(self.world_to_camera, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                  int(width), int(height))


def fov_to_focal(fov: float, pixels: int) -> float:
  return 0.5 * pixels / math.tan(0.5 * fov)


def center_of(world_to_camera):
  """[..., 4, 4] world-to-camera -> [..., 3] camera positions -R^T t (numpy in, numpy out; jax likewise)."""
  rotation, translation = world_to_camera[..., :3, :3], world_to_camera[..., :3, 3]
  return -(rotation.swapaxes(-1, -2) @ translation[..., None])[..., 0]


def camera_center(camera: Camera) -> jax.Array:
  """[3] world-space position of the camera."""
  return center_of(camera.world_to_camera)


def camera_centers(cameras) -> np.ndarray:
  """[V, 3] float64 world positions of a list of cameras."""
  return center_of(np.stack([np.asarray(c.world_to_camera, np.float64) for c in cameras]))


def opengl_camera_to_world(world_to_camera) -> np.ndarray:
  """[4, 4] OpenGL/Blender camera-to-world of an OpenCV world-to-camera (the inverse of what
  `Camera.from_opengl_camera_to_world` reads)."""
  return np.linalg.inv(np.asarray(world_to_camera, np.float64)) @ _OPENGL_TO_OPENCV


def orbit_eye(target, radius: float, azimuth, elevation, up=(0.0, 0.0, 1.0)) -> np.ndarray:
  """[..., 3] points at `radius` from `target`, at `elevation` above the plane normal to `up` and
  `azimuth` around it (radians), azimuth 0 lying towards world x (or y when `up` is along x)."""
  up = np.asarray(up, np.float64) / np.linalg.norm(up)
  reference = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
  east = reference - (reference @ up) * up
  east /= np.linalg.norm(east)
  north = np.cross(up, east)
  azimuth, elevation = np.asarray(azimuth, np.float64)[..., None], np.asarray(elevation, np.float64)[..., None]
  direction = np.cos(elevation) * (np.cos(azimuth) * east + np.sin(azimuth) * north) + np.sin(elevation) * up
  return np.asarray(target, np.float64) + radius * direction


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
  """[4, 4] OpenCV world-to-camera matrix of a camera at `eye` looking at `target`."""
  eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
  forward = target - eye
  forward /= np.linalg.norm(forward)
  right = np.cross(forward, up)
  if np.linalg.norm(right) < 1e-9:  # looking along `up`: any perpendicular will do
    right = np.cross(forward, np.roll(up, 1))
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  w2c = np.eye(4)
  w2c[:3, :3] = np.stack([right, down, forward])
  w2c[:3, 3] = -w2c[:3, :3] @ eye
  return w2c


def stack(cameras: list[Camera]) -> Camera:
  """Stacks cameras of one image size into a batched Camera (leading axis) for vmap."""
  sizes = {(c.width, c.height) for c in cameras}
  if len(sizes) != 1:
    raise ValueError(f"cameras to stack must share one image size, got {sorted(sizes)}")
  return jax.tree.map(lambda *xs: jnp.stack(xs), *cameras)
