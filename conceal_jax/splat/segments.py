"""Cutting each tile's depth-sorted run of pairs into segments of L pairs, the unit of compositing work.

A tile with n pairs gets ceil(n / L) segments, so the work is the number of pairs plus under L padding
pairs per tile, rather than tiles x the longest list. (3D-GS, Kerbl et al. 2023, arXiv:2308.04079, s.6
composites each tile's range of the sorted pair list; segments are that range in fixed-size pieces.)
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from conceal_jax.splat.binning import Pairs, expand


@struct.dataclass
class Segments:
  """splats: [S, L] int32 splat indices (N where empty); tiles: [S] int32 (T for unused slots);
  first: [S] bool, True where a segment opens its tile (and on unused slots); count: int32 segments used."""
  splats: jax.Array
  tiles: jax.Array
  first: jax.Array
  count: jax.Array


def segment_capacity(pair_capacity: int, num_tiles: int, length: int, block: int,
                     max_per_tile: int | None) -> int:
  """Static number of segment slots that can never overflow for `pair_capacity` pairs: sum over tiles of
  ceil(n_t / L) <= P / L + T (and <= T ceil(K / L) when tiles keep at most K), rounded up to `block`."""
  slots = -(-pair_capacity // length) + num_tiles
  if max_per_tile is not None:
    slots = min(slots, num_tiles * -(-max_per_tile // length))
  return max(block, -(-slots // block) * block)


def segment_layout(pairs: Pairs, num_splats: int, length: int, capacity: int,
                   max_per_tile: int | None) -> tuple[Segments, jax.Array]:
  """Segments of every tile's pairs, in tile order; with max_per_tile = K only the K nearest of each tile.

  Returns the segments and the number of tiles with more than K pairs (0 without K).
  """
  num_tiles = pairs.tile_count.shape[0]
  used = pairs.tile_count if max_per_tile is None else jnp.minimum(pairs.tile_count, max_per_tile)
  overflow = (jnp.zeros((), jnp.int32) if max_per_tile is None
              else jnp.sum(pairs.tile_count > max_per_tile, dtype=jnp.int32))
  tile, rank, valid, count = expand((used + length - 1) // length, capacity)
  within = rank[:, None] * length + jnp.arange(length, dtype=jnp.int32)  # position in the tile's run
  ok = valid[:, None] & (within < used[tile][:, None])
  where = jnp.clip(pairs.tile_start[tile][:, None] + within, 0, pairs.splats.shape[0] - 1)
  splats = jnp.where(ok, pairs.splats[where], num_splats)
  return Segments(splats=splats, tiles=jnp.where(valid, tile, num_tiles), first=(rank == 0) | ~valid,
                  count=count), overflow
