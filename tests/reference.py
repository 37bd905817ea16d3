"""An independent float64 reference splatting renderer: a plain per-pixel loop (tests only).

Written from the 3D-GS rasterizer's rules (REFERENCE s.4) without sharing code with conceal_jax:
explicit matrix inverses instead of the closed-form conic, Python int() truncation for tile rects, a
scalar SH evaluation, and a sequential compositing loop with the early stop of the CUDA kernel.

Tile lists follow the culling rule of REFERENCE s.7 (the renderer's rule, so truncated lists agree too):
a splat is listed in a tile of its 3-sigma rect unless its opacity is < 1/255 or its largest alpha over
the tile's pixel-centre rectangle is < 1/255 (tested per tile, from the minimum of the quadratic form on
the rectangle's edges). Neither changes a pixel of the untruncated image.
"""
from __future__ import annotations

import math

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def _rotation(q):
  n = math.sqrt(sum(v * v for v in q))
  if n == 0.0:
    return np.eye(3)
  w, x, y, z = (v / n for v in q)
  return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _sh_colour(coeffs, d, degree):
  x, y, z = d
  basis = [C0]
  if degree >= 1:
    basis += [-C1 * y, C1 * z, -C1 * x]
  if degree >= 2:
    basis += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y), C2[3] * x * z,
              C2[4] * (x * x - y * y)]
  if degree >= 3:
    basis += [C3[0] * y * (3 * x * x - y * y), C3[1] * x * y * z, C3[2] * y * (4 * z * z - x * x - y * y),
              C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), C3[4] * x * (4 * z * z - x * x - y * y),
              C3[5] * z * (x * x - y * y), C3[6] * x * (x * x - 3 * y * y)]
  rgb = sum(b * coeffs[k] for k, b in enumerate(basis)) + 0.5
  return np.maximum(rgb, 0.0)


def project_one(mean, log_scale, quat, opacity_logit, sh, w2c, fx, fy, cx, cy, width, height, degree,
                near, antialiased):
  """One Gaussian -> dict(mean2d, conic (A, B, C), depth, opacity, colour, radius) or None if culled."""
  params = [mean, quat, [opacity_logit], sh[: (degree + 1) ** 2]]
  if not all(np.all(np.isfinite(p)) for p in params) or np.any(np.isnan(log_scale) | (log_scale == np.inf)):
    return None  # a log scale of -inf is a zero scale, which is allowed
  rot, trans = w2c[:3, :3], w2c[:3, 3]
  p = rot @ mean + trans
  if p[2] <= near:
    return None
  scale = np.exp(np.minimum(log_scale, 20.0))
  m = _rotation(quat) @ np.diag(scale)
  sigma = m @ m.T
  lim_x_lo, lim_x_hi = -cx / fx - 0.15 * width / fx, (width - cx) / fx + 0.15 * width / fx
  lim_y_lo, lim_y_hi = -cy / fy - 0.15 * height / fy, (height - cy) / fy + 0.15 * height / fy
  tx = min(max(p[0] / p[2], lim_x_lo), lim_x_hi) * p[2]
  ty = min(max(p[1] / p[2], lim_y_lo), lim_y_hi) * p[2]
  jac = np.array([[fx / p[2], 0.0, -fx * tx / p[2] ** 2], [0.0, fy / p[2], -fy * ty / p[2] ** 2]])
  cov = jac @ rot @ sigma @ rot.T @ jac.T
  det0 = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
  cov = cov + 0.3 * np.eye(2)
  det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
  if not (det > 0) or not np.all(np.isfinite(cov)):
    return None
  inv = np.linalg.inv(cov)
  opacity = 1.0 / (1.0 + math.exp(-opacity_logit))
  if antialiased:
    opacity *= math.sqrt(max(0.005**2, det0 / det))
  mid = 0.5 * (cov[0, 0] + cov[1, 1])
  lam = mid + math.sqrt(max(0.1, mid * mid - det))
  radius = math.ceil(3.0 * math.sqrt(lam))
  cam_centre = -rot.T @ trans
  d = mean - cam_centre
  n = np.linalg.norm(d)
  d = d / n if n > 0 else d
  return dict(mean2d=np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy]),
              conic=(inv[0, 0], inv[0, 1], inv[1, 1]), depth=p[2], opacity=opacity,
              colour=_sh_colour(sh, d, degree), radius=radius)


def _rect(mean2d, radius, tile_size, grid):
  px, py = mean2d[0] - 0.5, mean2d[1] - 0.5
  lo = (min(grid[0], max(0, int((px - radius) / tile_size))), min(grid[1], max(0, int((py - radius) / tile_size))))
  hi = (min(grid[0], max(0, int((px + radius + tile_size - 1) / tile_size))),
        min(grid[1], max(0, int((py + radius + tile_size - 1) / tile_size))))
  return lo, hi


def _min_quadratic_on_rect(conic, mean, x0, x1, y0, y1):
  """min over the rectangle [x0, x1] x [y0, y1] of q(d) = A dx^2 + 2 B dx dy + C dy^2, d = p - mean."""
  a, b, c = conic
  mx, my = mean
  if x0 <= mx <= x1 and y0 <= my <= y1:
    return 0.0
  q = lambda dx, dy: a * dx * dx + 2 * b * dx * dy + c * dy * dy
  best = math.inf
  for x in (x0, x1):  # on a vertical edge q is a parabola in dy: its clamped vertex is the minimum
    dx = x - mx
    best = min(best, q(dx, min(max(-b * dx / c, y0 - my), y1 - my)))
  for y in (y0, y1):
    dy = y - my
    best = min(best, q(min(max(-b * dy / a, x0 - mx), x1 - mx), dy))
  return best


def _reaches_tile(s, tx, ty, tile_size):
  """Does the splat reach alpha >= 1/255 at some pixel centre of tile (tx, ty)? (REFERENCE s.7)"""
  if s["opacity"] < 1.0 / 255.0:
    return False
  x0, y0 = tx * tile_size + 0.5, ty * tile_size + 0.5
  m = _min_quadratic_on_rect(s["conic"], s["mean2d"], x0, x0 + tile_size - 1, y0, y0 + tile_size - 1)
  return s["opacity"] * math.exp(-0.5 * m) >= 1.0 / 255.0


def render_reference(means, log_scales, quats, opacity_logits, sh, w2c, fx, fy, cx, cy, width, height,
                     degree=None, background=(0.0, 0.0, 0.0), tile_size=16, max_per_tile=None,
                     near=0.2, antialiased=False):
  """Returns rgb [H, W, 3], alpha [H, W], depth [H, W] (expected z) in float64, and ambiguous [H, W]:
  pixels where a stop test T (1 - alpha) < 1e-4 was decided within rounding (relative 1e-5) of the
  threshold, so float32 and float64 may legitimately take different branches there."""
  as64 = lambda a: np.asarray(a, np.float64)
  means, log_scales, quats, opacity_logits, sh, w2c = map(as64, (means, log_scales, quats, opacity_logits, sh, w2c))
  fx, fy, cx, cy = (float(v) for v in (fx, fy, cx, cy))
  if degree is None:
    degree = int(round(math.sqrt(sh.shape[1]))) - 1
  grid = (-(-width // tile_size), -(-height // tile_size))
  splats = []
  for i in range(means.shape[0]):
    s = project_one(means[i], log_scales[i], quats[i], opacity_logits[i], sh[i], w2c, fx, fy, cx, cy,
                    width, height, degree, near, antialiased)
    if s is None:
      continue
    s["rect"] = _rect(s["mean2d"], s["radius"], tile_size, grid)
    s["index"] = i
    splats.append(s)
  splats.sort(key=lambda s: (s["depth"], s["index"]))
  # Per tile, the (optionally truncated) depth-ordered list of splats whose rect contains it.
  lists = {}
  for ty in range(grid[1]):
    for tx in range(grid[0]):
      hits = [s for s in splats if s["rect"][0][0] <= tx < s["rect"][1][0] and s["rect"][0][1] <= ty < s["rect"][1][1]
              and _reaches_tile(s, tx, ty, tile_size)]
      lists[tx, ty] = hits if max_per_tile is None else hits[:max_per_tile]
  rgb = np.zeros((height, width, 3))
  alpha = np.zeros((height, width))
  depth = np.zeros((height, width))
  ambiguous = np.zeros((height, width), bool)
  for i in range(height):
    for j in range(width):
      u, v = j + 0.5, i + 0.5
      t, colour, z = 1.0, np.zeros(3), 0.0
      for s in lists[j // tile_size, i // tile_size]:
        du, dv = u - s["mean2d"][0], v - s["mean2d"][1]
        a_, b_, c_ = s["conic"]
        power = -0.5 * (a_ * du * du + c_ * dv * dv) - b_ * du * dv
        if power > 0:
          continue
        a = min(0.99, s["opacity"] * math.exp(power))
        if a < 1.0 / 255.0:
          continue
        test_t = t * (1 - a)
        ambiguous[i, j] |= abs(test_t / 1e-4 - 1) < 1e-5
        if test_t < 1e-4:
          break
        colour += s["colour"] * a * t
        z += s["depth"] * a * t
        t = test_t
      rgb[i, j] = colour + t * np.asarray(background)
      alpha[i, j] = 1 - t
      depth[i, j] = z / (1 - t) if t < 1 else 0.0
  return rgb, alpha, depth, ambiguous
