"""Splat-tile pairs: every (splat, tile) the 3D-GS rasterizer can composite, sorted by tile then depth.

3D-GS (Kerbl et al. 2023, arXiv:2308.04079, s.6) duplicates each splat once per tile its 3-sigma square
touches and sorts the duplicates by a (tile, depth) key. The pairs built here are that list minus the
pairs that cannot colour any pixel, so the image is unchanged:
  - a splat of opacity o < 1/255 has alpha < 1/255 everywhere (3D-GS skips such alphas);
  - a pixel gets alpha >= 1/255 only inside the ellipse q(d) = d^T Sigma'^-1 d <= 2 ln(255 o); a pair is
    kept only where that ellipse meets the rectangle of the tile's pixel centres (an exact test).
The ellipse test is done row by row: the part of an ellipse inside a horizontal strip of tiles is convex,
so the tiles it meets in that row form one contiguous run whose ends have a closed form.

Binning is combinatorial, so it runs under stop_gradient; buffers have a static capacity and report the
number of pairs they needed (the caller grows the capacity when that is larger).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct

from conceal_jax.splat.composite import ALPHA_MIN

# The pair test is made slightly generous (relative and absolute slack on the ellipse level) so that float32
# rounding in it can never drop a pixel whose own alpha evaluation reaches 1/255.
_LEVEL_SLACK_REL = 1e-3
_LEVEL_SLACK_ABS = 1e-3


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
  """(tiles_x, tiles_y) covering the image; the last row/column of tiles may stick out of it."""
  return math.ceil(width / tile_size), math.ceil(height / tile_size)


def tile_rects(means2d: jax.Array, radii: jax.Array, tile_size: int,
               grid: tuple[int, int]) -> tuple[jax.Array, jax.Array]:
  """The range of tiles each splat's 3-sigma square touches, as in the 3D-GS rasterizer.

  means2d: [N, 2] (u, v) with pixel centres at +0.5; radii: [N] int (0 = culled).
  Returns rect_min, rect_max: [N, 2] int32 tile indices (x, y), max exclusive, clipped to the grid;
  an empty rect (min == max) means the splat touches no tile.
  """
  centre = means2d - 0.5  # 3D-GS measures from pixel centres at integer coordinates
  r = radii.astype(means2d.dtype)[:, None]
  limit = jnp.array(grid, means2d.dtype)
  # Clipping in floating point first keeps the int cast in range for splats far off screen.
  lo = jnp.clip(jnp.floor((centre - r) / tile_size), 0, limit)
  hi = jnp.clip(jnp.floor((centre + r + tile_size - 1) / tile_size), 0, limit)
  hi = jnp.where((radii > 0)[:, None], hi, lo)
  return lo.astype(jnp.int32), hi.astype(jnp.int32)


def on_tile_radii(means2d: jax.Array, radii: jax.Array, tile_size: int, grid: tuple[int, int]) -> jax.Array:
  """[N] `radii`, 0 for splats whose 3-sigma square touches no tile of the image (in front of the camera but
  beside its image): the screen radius the 3D-GS rasterizer reports (zero where its tile rectangle is empty),
  which binning then skips and densification reads as visibility and prunes screen-large splats by."""
  lo, hi = tile_rects(means2d, radii, tile_size, grid)
  return jnp.where(jnp.all(hi > lo, axis=-1), radii, 0)


def alpha_level(opacities: jax.Array) -> jax.Array:
  """[N] opacities -> [N] 2 ln(255 o): alpha = o exp(-q/2) >= 1/255 exactly where q <= this level.

  Negative where o < 1/255 (no pixel at all). 3D-GS eq. 2-3 with the 1/255 skip of its rasterizer.
  """
  return 2.0 * jnp.log(jnp.maximum(opacities / ALPHA_MIN, 1e-30))


def pair_test_level(opacities: jax.Array, radii: jax.Array) -> jax.Array:
  """[N] `alpha_level` made slightly generous for the pair tests; -1 (no pair) for culled splats."""
  level = alpha_level(opacities)
  return jnp.where((radii > 0) & (level >= 0), level * (1 + _LEVEL_SLACK_REL) + _LEVEL_SLACK_ABS, -1.0)


def ellipse_span(s_uu: jax.Array, s_uv: jax.Array, s_vv: jax.Array, level: jax.Array, v_lo: jax.Array,
                 v_hi: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Range [u_min, u_max] of u over {d = (u, v): d^T S^-1 d <= level, v_lo <= v <= v_hi}.

  S = [[s_uu, s_uv], [s_uv, s_vv]] is a 2D covariance (the EWA Sigma' of 3D-GS eq. 5), d is relative to
  the mean; all arguments broadcast. At fixed v the ellipse spans u = (s_uv / s_vv) v +- sqrt(c (level -
  v^2 / s_vv)) with c = s_uu - s_uv^2 / s_vv; the right end is concave in v, so over [v_lo, v_hi] it peaks
  at the v of the ellipse's rightmost point clamped into the range (left end: mirror image).
  Empty (u_min > u_max) where the range misses the ellipse or level < 0.
  """
  drawn = (level >= 0) & (s_uu > 0) & (s_vv > 0)
  s_uu, s_vv = jnp.where(drawn, s_uu, 1.0), jnp.where(drawn, s_vv, 1.0)  # culled lanes hold zeros
  level = jnp.where(drawn, level, 0.0)
  v_ext = jnp.sqrt(level * s_vv)
  lo, hi = jnp.maximum(v_lo, -v_ext), jnp.minimum(v_hi, v_ext)
  slope = s_uv / s_vv
  conditional = jnp.maximum(s_uu - s_uv * slope, 0.0)
  v_right = s_uv * jnp.sqrt(level / s_uu)  # v of the rightmost point; the leftmost is at -v_right
  half = lambda v: jnp.sqrt(conditional * jnp.maximum(level - v * v / s_vv, 0.0))
  v1, v2 = jnp.clip(v_right, lo, hi), jnp.clip(-v_right, lo, hi)
  u_max, u_min = slope * v1 + half(v1), slope * v2 - half(v2)
  empty = (lo > hi) | ~drawn
  return jnp.where(empty, jnp.inf, u_min), jnp.where(empty, -jnp.inf, u_max)


def tiles_meeting(lo: jax.Array, hi: jax.Array, tile_size: int, first: jax.Array,
                  last: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Tiles t in [first, last) whose pixel centres [t S + 0.5, t S + S - 0.5] meet the interval [lo, hi].

  Returns (start, count) int32; count 0 when none. Pixel centres follow the 3D-GS convention of camera.py.
  """
  dtype = lo.dtype
  # NaN can only come from overflow in the span of an enormous splat: keep the whole rect then.
  lo, hi = jnp.where(jnp.isnan(lo), -jnp.inf, lo), jnp.where(jnp.isnan(hi), jnp.inf, hi)
  start = jnp.ceil((lo - tile_size + 0.5) / tile_size)
  stop = jnp.floor((hi - 0.5) / tile_size) + 1
  start = jnp.clip(start, first.astype(dtype), last.astype(dtype))
  stop = jnp.clip(stop, start, last.astype(dtype))
  start = jnp.where(jnp.isfinite(start), start, 0).astype(jnp.int32)
  count = jnp.where(jnp.isfinite(stop), stop, 0).astype(jnp.int32) - start
  return start, jnp.maximum(count, 0)


def splat_rows(means2d: jax.Array, cov2d: jax.Array, level: jax.Array, rect_min: jax.Array,
               rect_max: jax.Array, tile_size: int) -> tuple[jax.Array, jax.Array]:
  """Rows of tiles in which a splat's alpha >= 1/255 ellipse meets its 3D-GS rect: (first row, count).

  means2d: [N, 2]; cov2d: [N, 3] (a, b, c) of Sigma'; level: [N] (alpha_level, slack included);
  rect_min/rect_max: [N, 2] the 3D-GS tile rects. The ellipse is first cut to the rect's columns of
  pixel centres; the rows meeting that convex piece are exactly the rows with at least one pair.
  """
  a, b, c = cov2d[:, 0], cov2d[:, 1], cov2d[:, 2]
  col_lo = rect_min[:, 0].astype(a.dtype) * tile_size + 0.5 - means2d[:, 0]
  col_hi = rect_max[:, 0].astype(a.dtype) * tile_size - 0.5 - means2d[:, 0]
  y_min, y_max = ellipse_span(c, b, a, level, col_lo, col_hi)
  return tiles_meeting(means2d[:, 1] + y_min, means2d[:, 1] + y_max, tile_size, rect_min[:, 1],
                       rect_max[:, 1])


def row_columns(means2d: jax.Array, cov2d: jax.Array, level: jax.Array, rect_min: jax.Array,
                rect_max: jax.Array, row: jax.Array, tile_size: int) -> tuple[jax.Array, jax.Array]:
  """Tiles of row `row` met by each splat's ellipse, within its 3D-GS rect: (first column, count).

  All inputs are per (splat, row) entry: means2d [R, 2], cov2d [R, 3], level [R], rects [R, 2], row [R].
  """
  a, b, c = cov2d[:, 0], cov2d[:, 1], cov2d[:, 2]
  top = row.astype(a.dtype) * tile_size + 0.5 - means2d[:, 1]
  x_min, x_max = ellipse_span(a, b, c, level, top, top + (tile_size - 1))
  return tiles_meeting(means2d[:, 0] + x_min, means2d[:, 0] + x_max, tile_size, rect_min[:, 0],
                       rect_max[:, 0])


def inclusive_sum(x: jax.Array) -> jax.Array:
  """[M] int32 -> [M] int32 running sum."""
  return jnp.cumsum(x, dtype=jnp.int32)


def expand(counts: jax.Array, capacity: int) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
  """Enumerates sum(counts) slots, item i owning counts[i] consecutive ones, into a static buffer.

  counts: [M] int32 >= 0. Returns owner [capacity] (the item of each slot), rank [capacity] (its index
  among the item's slots), valid [capacity] (slot < total, and total itself (int32, may exceed capacity).
  The owner of slot s is the last item starting at or before s, found by a running count of starts.
  """
  ends = inclusive_sum(counts)
  starts = ends - counts
  total = ends[-1] if counts.shape[0] else jnp.zeros((), jnp.int32)
  # Items with no slots share their start with the next one; counting every start keeps the last.
  marks = jnp.zeros((capacity,), jnp.int32).at[starts].add(1, mode="drop")
  owner = jnp.clip(inclusive_sum(marks) - 1, 0, max(counts.shape[0] - 1, 0))
  slot = jnp.arange(capacity, dtype=jnp.int32)
  valid = slot < total
  return owner, jnp.where(valid, slot - starts[owner], 0), valid, total


@struct.dataclass
class Pairs:
  """Splat-tile pairs sorted by (tile, depth), in a buffer of static capacity P.

  tiles: [P] int32 tile index (row-major), num_tiles in the unused tail; splats: [P] int32 splat index,
  N in the tail; tile_start / tile_count: [T] int32 where each tile's run begins and how long it is;
  num_pairs: int32 pairs the image needs (may exceed P: then the buffer holds only the first P).
  """
  tiles: jax.Array
  splats: jax.Array
  tile_start: jax.Array
  tile_count: jax.Array
  num_pairs: jax.Array


def bin_pairs(means2d: jax.Array, cov2d: jax.Array, depths: jax.Array, opacities: jax.Array,
              radii: jax.Array, tile_size: int, grid: tuple[int, int], capacity: int) -> Pairs:
  """All pairs of splats and the tiles where they can reach alpha >= 1/255, sorted by (tile, depth).

  means2d: [N, 2]; cov2d: [N, 3]; depths, opacities: [N]; radii: [N] int 3D-GS radius (0 = culled).
  Work and memory are O(N log N + P log P): splats are depth-sorted once, their rows of tiles and the
  runs of tiles in each row are enumerated into buffers of `capacity`, and one integer sort orders the
  pairs by tile (a stable order within a tile: the enumeration is already front to back).
  """
  means2d, cov2d, depths, opacities = jax.lax.stop_gradient((means2d, cov2d, depths, opacities))
  n = depths.shape[0]
  tiles_x, tiles_y = grid
  num_tiles = tiles_x * tiles_y
  order = depth_order(depths, radii)
  level = pair_test_level(opacities[order], radii[order])
  m2d, cov = means2d[order], cov2d[order]
  rect_min, rect_max = tile_rects(m2d, radii[order], tile_size, grid)
  row_first, row_count = splat_rows(m2d, cov, level, rect_min, rect_max, tile_size)

  # (splat, row) entries: every kept row holds at least one pair, so `capacity` entries suffice.
  owner, rank, valid_row, num_rows = expand(row_count, capacity)
  row = row_first[owner] + rank
  take = lambda x: x[owner]
  col_first, col_count = row_columns(take(m2d), take(cov), take(level), take(rect_min), take(rect_max),
                                     row, tile_size)
  col_count = jnp.where(valid_row, col_count, 0)
  row_of_pair, col_rank, valid_pair, num_pairs = expand(col_count, capacity)
  num_pairs = num_pairs + _pairs_beyond(m2d, cov, level, rect_min, rect_max, row_first, row_count,
                                        tile_size, capacity, num_rows)

  tile = row[row_of_pair] * tiles_x + col_first[row_of_pair] + col_rank
  depth_rank = owner[row_of_pair]
  tile = jnp.where(valid_pair, tile, num_tiles)
  tile, depth_rank = _sort_by_tile(tile, depth_rank, num_tiles, n)
  splats = jnp.where(tile < num_tiles, order[jnp.clip(depth_rank, 0, n - 1)], n)
  tile_count = jnp.zeros((num_tiles + 1,), jnp.int32).at[tile].add(1)[:num_tiles]
  tile_start = inclusive_sum(tile_count) - tile_count
  return Pairs(tiles=tile, splats=splats.astype(jnp.int32), tile_start=tile_start, tile_count=tile_count,
               num_pairs=num_pairs)


def depth_order(depths: jax.Array, radii: jax.Array) -> jax.Array:
  """[N] int32: the splats front to back, culled ones (radii 0) last, ties in index order, as
  argsort(where(radii > 0, depths, inf), stable=True). Drawn depths are positive (beyond the near plane), so
  their float bits order as unsigned integers (float32; other precisions take the argsort)."""
  if depths.dtype != jnp.float32:
    return jnp.argsort(jnp.where(radii > 0, depths, jnp.inf), stable=True).astype(jnp.int32)
  bits = jax.lax.bitcast_convert_type(depths, jnp.uint32)
  return stable_order(jnp.where(radii > 0, bits, jnp.uint32(0xFFFFFFFF)))


def stable_order(keys: jax.Array) -> jax.Array:
  """[N] uint32 keys -> [N] int32 indices that sort them stably (ties in index order).

  A least-significant-digit radix sort whose passes are single-operand sorts (several times faster on CPU than
  a sort carrying an index): with b = bits of N - 1, each pass sorts (digit << b) | position, the key's next
  32 - b bits above each element's position in the previous pass's order, all distinct, so every pass is
  stable and the last one orders by the whole key, then by index.
  """
  n = keys.shape[0]
  index_bits = max(1, (n - 1).bit_length())
  digit_bits = 32 - index_bits
  if n == 0 or digit_bits < 8:  # beyond 16M keys: more than four passes
    return jnp.argsort(keys, stable=True).astype(jnp.int32)
  position = jnp.arange(n, dtype=jnp.uint32)
  order = position
  for shift in range(0, 32, digit_bits):
    digit = (keys[order] >> shift) & jnp.uint32((1 << digit_bits) - 1)
    passed = jnp.sort((digit << index_bits) | position)
    order = order[passed & jnp.uint32((1 << index_bits) - 1)]
  return order.astype(jnp.int32)


def _sort_by_tile(tile: jax.Array, depth_rank: jax.Array, num_tiles: int, n: int):
  """Orders pairs by (tile, depth rank). One packed uint32 key when it fits (a single-operand sort is
  several times faster on CPU than a sort carrying a payload), else a two-key sort."""
  if (num_tiles + 1) * (n + 1) < 2**32:
    key = tile.astype(jnp.uint32) * jnp.uint32(n + 1) + depth_rank.astype(jnp.uint32)
    key = jnp.sort(key)
    return (key // jnp.uint32(n + 1)).astype(jnp.int32), (key % jnp.uint32(n + 1)).astype(jnp.int32)
  return jax.lax.sort((tile, depth_rank), num_keys=2)


def _pairs_beyond(m2d, cov, level, rect_min, rect_max, row_first, row_count, tile_size, capacity, num_rows):
  """Pairs in the (splat, row) entries past the first `capacity` (only when the row buffer overflowed):
  counted row by row over all splats, so that an overflowing render still reports exactly what it needs."""
  ends = inclusive_sum(row_count)
  beyond = ends - capacity  # how many of a splat's rows fall past the buffer

  def body(state):
    k, total = state
    row = row_first + row_count - 1 - k  # the k-th last row of every splat
    _, count = row_columns(m2d, cov, level, rect_min, rect_max, row, tile_size)
    return k + 1, total + jnp.sum(jnp.where(k < jnp.minimum(beyond, row_count), count, 0), dtype=jnp.int32)

  most = jnp.where(num_rows > capacity, jnp.max(jnp.minimum(beyond, row_count)), 0)
  return jax.lax.while_loop(lambda state: state[0] < most, body,
                            (jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32)))[1]


def pair_counts_by_rule(means2d: jax.Array, cov2d: jax.Array, opacities: jax.Array, radii: jax.Array,
                        tile_size: int, grid: tuple[int, int]) -> dict[str, jax.Array]:
  """How many pairs each culling step leaves (for the benchmark): the 3D-GS 3-sigma squares; without
  splats of opacity < 1/255; within the square of the opacity extent sqrt(2 ln(255 o) lambda_max) (tested
  against pixel centres); and after the exact ellipse-tile test. Returns int32 scalars."""
  rect_min, rect_max = tile_rects(means2d, radii, tile_size, grid)
  area = lambda lo, hi: jnp.sum(jnp.prod(jnp.maximum(hi - lo, 0), -1), dtype=jnp.int32)
  level = alpha_level(opacities)
  seen = level >= 0
  a, b, c = cov2d[:, 0], cov2d[:, 1], cov2d[:, 2]
  lambda_max = 0.5 * (a + c) + jnp.sqrt(jnp.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
  extent = jnp.sqrt(jnp.maximum(level, 0.0) * lambda_max)
  lo, hi = [], []
  for axis in range(2):
    start, count = tiles_meeting(means2d[:, axis] - extent, means2d[:, axis] + extent, tile_size,
                                 rect_min[:, axis], rect_max[:, axis])
    lo.append(start)
    hi.append(start + count)
  square = area(jnp.stack(lo, -1), jnp.stack(hi, -1) * seen[:, None] + jnp.stack(lo, -1) * ~seen[:, None])
  level = pair_test_level(opacities, radii)
  row_first, row_count = splat_rows(means2d, cov2d, level, rect_min, rect_max, tile_size)
  max_rows = grid[1]

  def per_row(k, total):
    row = row_first + k
    _, count = row_columns(means2d, cov2d, level, rect_min, rect_max, row, tile_size)
    return total + jnp.sum(jnp.where(k < row_count, count, 0), dtype=jnp.int32)

  ellipse = jax.lax.fori_loop(0, max_rows, per_row, jnp.zeros((), jnp.int32))
  return dict(inria_rect=area(rect_min, rect_max),
              opacity_cull=area(rect_min, jnp.where(seen[:, None], rect_max, rect_min)),
              opacity_extent=square, ellipse=ellipse)
