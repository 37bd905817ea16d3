"""Reading and writing the standard 3D-GS `.ply` point cloud (as the 3D-GS reference implementation,
graphdeco-inria/gaussian-splatting, writes it).

The file has one `vertex` element with float32 properties
  x y z nx ny nz f_dc_0..2 f_rest_0..(3 * ((D+1)^2 - 1) - 1) opacity scale_0..2 rot_0..3
holding the raw (pre-activation) parameters: opacity as a logit, scale as a log, rotation as
(w, x, y, z).
f_rest is channel-major: all higher-order coefficients of R, then those of G, then those of B. The
normals are unused by 3D-GS and written as zeros.

The other trainers' exports read the same way, as properties are found by name, not position: gsplat's
exporter writes the same properties without the normals, nerfstudio's splatfacto export (ns-export
gaussian-splat) writes Inria's layout, or with ply_color_mode='rgb' 8-bit red, green, blue in place of the
SH (read as degree-0 colours). Unknown extra properties are ignored.
"""
from __future__ import annotations

import math
import os
import re
import warnings

import jax.numpy as jnp
import numpy as np
import plyfile

from conceal_jax.core.fileio import atomic_path
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.sh import rgb_to_sh_dc

_POSITION = ("x", "y", "z")
_NORMAL = ("nx", "ny", "nz")
_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
_OPACITY = ("opacity",)
_SCALE = ("scale_0", "scale_1", "scale_2")
_ROTATION = ("rot_0", "rot_1", "rot_2", "rot_3")
_RGB = ("red", "green", "blue")
_REST_PATTERN = re.compile(r"f_rest_(\d+)")
# Properties of the PlayCanvas/SuperSplat compressed ply, whose quantised chunks need decoding first.
_COMPRESSED_MARKERS = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
# Logit of an opacity 1e-6 from 0 or 1: an opacity of exactly 1 (or 0) read from a file becomes this finite
# logit, practically opaque (transparent: far below the renderer's 1/255 alpha cut), whose sigmoid and its
# gradient stay finite in float32 so that the scene can still be rendered and trained.
OPACITY_LOGIT_LIMIT = math.log((1.0 - 1e-6) / 1e-6)


class PlyError(ValueError):
  """A file that is not a readable 3D-GS point cloud."""


class PlyWarning(UserWarning):
  """A file that was read with values changed to what the renderer needs (infinite opacity logits)."""


def rest_names(sh_degree: int) -> list[str]:
  """Names of the f_rest properties for SH degree D: 3 * ((D+1)^2 - 1) of them."""
  return [f"f_rest_{i}" for i in range(3 * ((sh_degree + 1)**2 - 1))]


def property_names(sh_degree: int) -> list[str]:
  """All vertex property names, in the order 3D-GS writes them."""
  return [*_POSITION, *_NORMAL, *_DC, *rest_names(sh_degree), *_OPACITY, *_SCALE, *_ROTATION]


def gaussians_to_vertices(gaussians: Gaussians) -> np.ndarray:
  """[N] structured float32 array with the fields of `property_names(gaussians.sh_degree)`."""
  n = gaussians.num
  sh = np.asarray(gaussians.sh, np.float32)
  # [N, K-1, 3] -> [N, 3, K-1] -> [N, 3 (K-1)]: channel-major, as 3D-GS stores f_rest.
  rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(n, 3 * (sh.shape[1] - 1))
  columns = np.concatenate([
      np.asarray(gaussians.means, np.float32),
      np.zeros((n, 3), np.float32),
      sh[:, 0, :],
      rest,
      np.asarray(gaussians.opacity_logits, np.float32).reshape(n, 1),
      np.asarray(gaussians.log_scales, np.float32),
      np.asarray(gaussians.quats, np.float32),
  ], axis=1)
  names = property_names(gaussians.sh_degree)
  vertices = np.empty(n, dtype=[(name, "<f4") for name in names])
  for i, name in enumerate(names):
    vertices[name] = columns[:, i]
  return vertices


def save_ply(path: str | os.PathLike, gaussians: Gaussians) -> None:
  """Writes `gaussians` as a binary little-endian 3D-GS ply; atomic: a crash never leaves half a file."""
  element = plyfile.PlyElement.describe(gaussians_to_vertices(gaussians), "vertex")
  data = plyfile.PlyData([element], text=False, byte_order="<")
  with atomic_path(path) as tmp, open(tmp, "wb") as f:
    data.write(f)


def load_ply(path: str | os.PathLike) -> Gaussians:
  """Reads any standard 3D-GS ply (SH degree inferred from the f_rest count) into float32 Gaussians.

  A file without f_dc but with red, green, blue (nerfstudio's rgb export) gets the DC coefficient of
  those colours (integers scaled by their type's maximum, floats taken as [0, 1]). Infinite opacity
  logits (opacities of exactly 0 or 1) are clipped to +-OPACITY_LOGIT_LIMIT with a PlyWarning that says
  how many. Raises PlyError, naming the file, when it is missing, is not a well-formed ply, is a
  compressed ply, lacks a required property, has an f_rest count that is no SH degree, or holds any
  other non-finite value (NaN anywhere, an infinity outside the opacities).
  """
  path = os.fspath(path)
  vertices = _read_vertices(path)
  names = vertices.dtype.names or ()
  if any(name in names for name in _COMPRESSED_MARKERS):
    raise PlyError(f"{path}: a compressed ply (packed_* properties); decompress it first, e.g. with "
                   "splat-transform (conceal_jax.robust.converter)")
  colour = _colour_fields(names)
  required = _POSITION + colour + _OPACITY + _SCALE + _ROTATION
  missing = [name for name in required if name not in names]
  if missing:
    raise PlyError(f"{path}: missing vertex properties {', '.join(missing)}")
  sh_degree = _sh_degree_from_rest(path, names)
  used = required + tuple(rest_names(sh_degree))
  non_numeric = [name for name in used if vertices.dtype[name].kind not in "fiu"]
  if non_numeric:
    raise PlyError(f"{path}: vertex properties {', '.join(non_numeric)} are not scalars")
  n = len(vertices)
  # Doubles beyond the float32 range become inf here on purpose: the finiteness check rejects them (and
  # an opacity logit that large is an opacity of 0 or 1, clipped as an infinite one).
  with np.errstate(over="ignore"):
    values = {name: np.asarray(vertices[name], np.float32) for name in used}
  values["opacity"] = _clip_infinite_logits(path, values["opacity"])
  bad = [name for name in used if not np.all(np.isfinite(values[name]))]
  if bad:
    raise PlyError(f"{path}: non-finite values in vertex properties {', '.join(bad)}")

  def columns(fields) -> np.ndarray:
    """[N, len(fields)] float32."""
    return np.stack([values[name] for name in fields], axis=1) if fields else np.zeros((n, 0), np.float32)

  rest = columns(rest_names(sh_degree)).reshape(n, 3, (sh_degree + 1)**2 - 1)
  dc = columns(_DC) if colour == _DC else _dc_of_colours(columns(_RGB), vertices.dtype["red"])
  sh = np.concatenate([dc[:, None, :], np.transpose(rest, (0, 2, 1))], axis=1)
  return Gaussians(means=jnp.asarray(columns(_POSITION)), log_scales=jnp.asarray(columns(_SCALE)),
                   quats=jnp.asarray(columns(_ROTATION)), opacity_logits=jnp.asarray(values["opacity"]),
                   sh=jnp.asarray(sh))


def _colour_fields(names: tuple[str, ...]) -> tuple[str, ...]:
  """Where the DC colour comes from: f_dc_0..2, or red, green, blue in a file with no f_dc at all."""
  if not any(name in names for name in _DC) and all(name in names for name in _RGB):
    return _RGB
  return _DC


def _dc_of_colours(rgb: np.ndarray, dtype: np.dtype) -> np.ndarray:
  """[N, 3] SH DC coefficients rendering as the colours `rgb` ([N, 3], stored as `dtype`)."""
  scale = np.iinfo(dtype).max if dtype.kind in "iu" else 1.0
  return np.asarray(rgb_to_sh_dc(rgb / np.float32(scale)), np.float32)


def _read_vertices(path: str) -> np.ndarray:
  """[N] structured array of the `vertex` element, or PlyError for an unreadable file."""
  if not os.path.isfile(path):
    raise PlyError(f"{path}: no such file")
  try:
    with open(path, "rb") as f:
      # mmap=False reads everything now, so that a truncated body fails here rather than on first use.
      data = plyfile.PlyData.read(f, mmap=False)
  except (plyfile.PlyParseError, ValueError, EOFError, IndexError, KeyError, TypeError) as e:
    raise PlyError(f"{path}: not a valid PLY file ({type(e).__name__}: {e})") from e
  except OSError as e:
    raise PlyError(f"{path}: cannot read ({e})") from e
  if "vertex" not in data:
    raise PlyError(f"{path}: no 'vertex' element")
  return data["vertex"].data


def _clip_infinite_logits(path: str, logits: np.ndarray) -> np.ndarray:
  """[N] opacity logits with +-inf clipped to +-OPACITY_LOGIT_LIMIT (NaN kept for the finiteness check);
  a PlyWarning naming the file says how many were clipped."""
  infinite = np.isinf(logits)
  count = int(np.sum(infinite))
  if not count:
    return logits
  warnings.warn(f"{path}: {count} opacity logits were infinite (opacity exactly 0 or 1); clipped to "
                f"+-{OPACITY_LOGIT_LIMIT:.2f}", PlyWarning, stacklevel=3)
  return np.where(infinite, np.sign(logits) * np.float32(OPACITY_LOGIT_LIMIT), logits).astype(np.float32)


def _sh_degree_from_rest(path: str, names: tuple[str, ...]) -> int:
  """SH degree D from the f_rest properties: they must be exactly f_rest_0 .. f_rest_{3((D+1)^2-1)-1}."""
  indices = sorted(int(m.group(1)) for m in map(_REST_PATTERN.fullmatch, names) if m)
  count = len(indices)
  if indices != list(range(count)):
    raise PlyError(f"{path}: f_rest properties are not numbered 0..{count - 1} without gaps")
  degree = int(round((count / 3 + 1)**0.5)) - 1
  if count != 3 * ((degree + 1)**2 - 1):
    raise PlyError(f"{path}: {count} f_rest properties match no SH degree (expected 0, 9, 24, 45, ...)")
  return degree
