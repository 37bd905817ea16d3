"""Tile binning: which splats touch which screen tile, in depth order (3D-GS tile rasterizer).

Binning is combinatorial (integer rects, sorting), so it runs under stop_gradient: gradients flow only
through the splat parameters gathered with the lists it returns.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

# Upper bound on [tiles x Gaussians] overlap entries materialised at once while building the lists.
_MAX_MASK_ENTRIES = 1 << 24


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


def depth_order(depths: jax.Array, radii: jax.Array) -> jax.Array:
  """[N] indices sorting visible splats front to back; exact ties keep index order (stable sort)."""
  key = jnp.where(radii > 0, depths, jnp.inf)
  return jnp.argsort(key, stable=True)


def tile_lists(means2d: jax.Array, depths: jax.Array, radii: jax.Array, tile_size: int,
               grid: tuple[int, int], length: int) -> tuple[jax.Array, jax.Array]:
  """For every tile, the first `length` splats touching it in depth order.

  Returns lists: [T, length] int32 splat indices, padded with N (a sentinel for "no splat"), tiles in
  row-major order (T = tiles_x * tiles_y); and counts: [T] int32, the number of splats touching each
  tile (counts > length means the list was truncated).
  """
  means2d, depths, radii = jax.lax.stop_gradient((means2d, depths, radii))
  n = depths.shape[0]
  order = depth_order(depths, radii)
  rect_min, rect_max = tile_rects(means2d[order], radii[order], tile_size, grid)
  tiles_x, tiles_y = grid
  tile_xy = jnp.stack(jnp.meshgrid(jnp.arange(tiles_x), jnp.arange(tiles_y), indexing="xy"), -1)
  tile_xy = tile_xy.reshape(-1, 2).astype(jnp.int32)
  ranks = jnp.arange(1, length + 1, dtype=jnp.float32)
  sorted_with_sentinel = jnp.concatenate([order.astype(jnp.int32), jnp.array([n], jnp.int32)])

  def one_tile(xy):
    touches = jnp.all((rect_min <= xy) & (xy < rect_max), axis=-1)  # [N] in depth order
    seen = prefix_count(touches)
    # The k-th touching splat sits where the running count first reaches k (N when there is none).
    position = jnp.searchsorted(seen, ranks, side="left", method="scan_unrolled")
    return sorted_with_sentinel[position], seen[-1].astype(jnp.int32)

  batch = max(1, min(tile_xy.shape[0], _MAX_MASK_ENTRIES // max(n, 1)))
  return jax.lax.map(one_tile, tile_xy, batch_size=batch)


def prefix_count(mask: jax.Array, block: int = 128) -> jax.Array:
  """[N] bool -> [N] float32 running count of True (inclusive); exact for N < 2^24.

  A blocked prefix sum: a small triangular matmul inside blocks of `block` and a short cumsum across
  blocks. On CPU this is several times faster than jnp.cumsum, which XLA lowers to a reduce_window.
  """
  n = mask.shape[0]
  padded = -(-n // block) * block
  x = jnp.pad(mask.astype(jnp.float32), (0, padded - n)).reshape(-1, block)
  within = x @ jnp.triu(jnp.ones((block, block), jnp.float32))
  totals = within[:, -1]
  return (within + (jnp.cumsum(totals) - totals)[:, None]).reshape(-1)[:n]
