"""Front-to-back alpha compositing of depth-sorted splat-tile pairs cut into segments (3D-GS eq. 3).

Each tile's run of pairs is cut into segments of L pairs (segments.py). Transmittance is tracked as a log,
a running sum of log(1 - alpha), finite for every alpha <= ALPHA_MAX, so a segment's effect on a pixel is
one sum and a tile's segments chain by a prefix sum: the log transmittance in front of a segment is the sum
over the tile's earlier segments. The 3D-GS rules are kept exactly (Kerbl et al. 2023, arXiv:2308.04079,
s.6 and its rasterizer): alpha = min(0.99, o exp(power)), skipped where < 1/255 or where power > 0, and a
pixel stops before the first splat that would take its transmittance below 1e-4. The sum of log(1 - alpha)
over every splat met, composited or not, is monotone, so "not stopped" is a prefix test on it.

`composite` has a hand-written backward pass (3D-GS s.6): it recomputes alpha, walks each pixel's pairs with
the transmittance in front of each segment and the colour composited before it (O(segments x pixels)
residuals, none per pixel-pair) and obtains the "colour behind" of every pair as the final colour minus
the colour up to it. Segments are processed in blocks by loops whose trip count is the number of
segments the image needs, so buffer capacity costs memory but not time.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)
# Chunk length of `running_sum`'s two-level prefix sum.
_CHUNK = 8


def pair_alpha(pixels: jax.Array, means2d: jax.Array, conics: jax.Array,
               opacities: jax.Array) -> tuple[jax.Array, jax.Array]:
  """alpha = min(0.99, o exp(-0.5 d^T Sigma'^-1 d)), 0 where skipped (3D-GS eq. 2-3), for segments.

  pixels: [P, 2] pixel centres relative to each segment's tile origin; means2d: [S, L, 2] (same frame);
  conics: [S, L, 3] (A, B, C); opacities: [S, L]. Returns alpha [S, P, L] and the exponentiated power
  exp(min(power, 0)) [S, P, L]. A positive power can only come from rounding in a
  near-singular conic; it is skipped, as in 3D-GS.
  """
  dx = pixels[None, :, 0, None] - means2d[:, None, :, 0]
  dy = pixels[None, :, 1, None] - means2d[:, None, :, 1]
  a, b, c = (conics[:, None, :, k] for k in range(3))
  power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
  falloff = jnp.exp(jnp.minimum(power, 0.0))
  alpha = jnp.minimum(ALPHA_MAX, opacities[:, None, :] * falloff)
  alpha = jnp.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
  return alpha, falloff


def running_sum(x: jax.Array) -> jax.Array:
  """Inclusive prefix sum over the last axis (length L) as products with triangular matrices: on CPU a small
  dense product is much faster than the reduce_window that jnp.cumsum lowers to. Where L splits into chunks
  of 8, the sums run within each chunk and the chunks' totals are carried over (two 8x8 products: 16
  multiply-adds a value rather than L)."""
  n = x.shape[-1]
  if n % _CHUNK or n == _CHUNK:
    return x @ jnp.triu(jnp.ones((n, n), x.dtype))
  within = x.reshape(x.shape[:-1] + (n // _CHUNK, _CHUNK)) @ jnp.triu(jnp.ones((_CHUNK, _CHUNK), x.dtype))
  before = within[..., -1] @ jnp.triu(jnp.ones((n // _CHUNK,) * 2, x.dtype), 1)
  return (within + before[..., None]).reshape(x.shape)


def chain_segments(totals: jax.Array, first: jax.Array, carry: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Exclusive prefix of per-segment sums within each tile: what lies in front of each segment.

  totals: [B, ...] per-segment sums in tile order; first: [B] True where a segment opens its tile;
  carry: [...] the running sum of the tile the previous block ended in (it continues into the segments
  before the block's first opening). Returns (in_front [B, ...], running sum after the last segment [...]).
  Segments b' < b share b's tile exactly when no segment in (b', b] opens a tile, i.e. when the running
  counts of openings agree; the sums are one [B, B] x [B, ...] product that never adds across tiles
  (no cancellation between tiles).
  """
  opened = jnp.cumsum(first.astype(jnp.int32))
  earlier = jnp.arange(first.shape[0])[None, :] < jnp.arange(first.shape[0])[:, None]
  same_tile = (earlier & (opened[:, None] == opened[None, :])).astype(totals.dtype)
  flat = totals.reshape(totals.shape[0], -1)
  continues = (opened == 0).astype(totals.dtype)[:, None]
  in_front = same_tile @ flat + continues * carry.reshape(1, -1)
  last = in_front[-1] + flat[-1]
  return in_front.reshape(totals.shape), last.reshape(carry.shape)


def _power_gradients(g_power: jax.Array, pixels: jax.Array, means2d: jax.Array,
                     conics: jax.Array) -> tuple[jax.Array, jax.Array]:
  """dL/dmeans2d [S, L, 2] and dL/dconics [S, L, 3] from dL/dpower [S, P, L] (power of `pair_alpha`).

  dpower/dmean = (A dx + B dy, C dy + B dx) and dpower/d(A, B, C) = (-dx^2 / 2, -dx dy, -dy^2 / 2), summed
  over the pixels. With d = pixel - mean, every sum expands into moments of dL/dpower against 1, x, y, x^2,
  y^2, xy of the tile's pixel centres: one [S, L, P] x [P, 6] product instead of five reductions. The
  pixels are centred on the tile so the expansion stays well conditioned.
  """
  centre = jnp.mean(pixels, 0)
  x, y = pixels[:, 0] - centre[0], pixels[:, 1] - centre[1]
  basis = jnp.stack([jnp.ones_like(x), x, y, x * x, y * y, x * y], -1)
  m0, mx_, my_, mxx, myy, mxy = jnp.moveaxis(jnp.einsum("bpl,pk->blk", g_power, basis), -1, 0)
  ux, uy = means2d[..., 0] - centre[0], means2d[..., 1] - centre[1]
  sx, sy = mx_ - ux * m0, my_ - uy * m0  # sums of g dx, g dy
  sxx = mxx - 2 * ux * mx_ + ux * ux * m0
  syy = myy - 2 * uy * my_ + uy * uy * m0
  sxy = mxy - ux * my_ - uy * mx_ + ux * uy * m0
  a, b, c = conics[..., 0], conics[..., 1], conics[..., 2]
  g_mean = jnp.stack([a * sx + b * sy, c * sy + b * sx], -1)
  g_conic = jnp.stack([-0.5 * sxx, -sxy, -0.5 * syy], -1)
  return g_mean, g_conic


def _block_inputs(b, block, seg_splats, seg_tiles, seg_first, origins, means2d, conics, opacities, values):
  """Gathers block b of segments: splat indices [B, L] and their parameters, tile-relative means."""
  take = lambda x: jax.lax.dynamic_slice_in_dim(x, b * block, block)
  idx, tiles, first = take(seg_splats), take(seg_tiles), take(seg_first)
  m = means2d[idx] - origins[tiles][:, None, :]
  return idx, tiles, first, m, conics[idx], opacities[idx], values[idx]


def _num_blocks(count, block):
  return (count + block - 1) // block


def _block_weights(pixels, means2d, conics, opacities, first, carry_log_t):
  """A block's compositing weights alpha_i T_i [B, P, L] (0 where a pixel has stopped) with what the forward pass
  keeps of them: (weights, keep [B, P, L], log(1 - alpha) [B, P, L], log T in front of each segment [B, P], log T
  running on after the block [P])."""
  alpha, _ = pair_alpha(pixels, means2d, conics, opacities)
  log_1m = jnp.log1p(-alpha)
  cum = running_sum(log_1m)
  start, carry_log_t = chain_segments(cum[..., -1], first, carry_log_t)
  seen = start[..., None] + cum
  # T only decreases, so "not stopped yet" is the prefix where T after this splat stays >= 1e-4. Every
  # splat before a kept one was kept too, so its transmittance is the seen one: one prefix sum suffices.
  keep = seen >= LOG_T_MIN
  weights = jnp.where(keep, alpha * jnp.exp(seen - log_1m), 0.0)
  return weights, keep, log_1m, start, carry_log_t


def pair_weights(means2d, conics, opacities, seg_splats, seg_tiles, seg_first, num_segments,
                 tile_size: int, grid: tuple[int, int], block: int) -> jax.Array:
  """The weight alpha_i T_i of every segment's splat at every pixel of its tile, [S, S*S, L] (0 for padding and
  where a pixel has stopped), as `composite` composites them: its values are sum_i c_i alpha_i T_i. The
  arguments are `composite`'s but the values."""
  pixels, origins = _geometry(tile_size, grid, means2d.dtype)
  padded = tuple(map(_pad, (means2d, conics, opacities, jnp.zeros((means2d.shape[0], 0), means2d.dtype))))

  def body(b, state):
    out, carry_log_t = state
    _, _, first, m, con, op, _ = _block_inputs(b, block, seg_splats, seg_tiles, seg_first, origins, *padded)
    weights, _, _, _, carry_log_t = _block_weights(pixels, m, con, op, first, carry_log_t)
    return jax.lax.dynamic_update_slice_in_dim(out, weights, b * block, 0), carry_log_t

  out = jnp.zeros(seg_splats.shape[:1] + (tile_size * tile_size, seg_splats.shape[1]), means2d.dtype)
  carry = jnp.zeros((tile_size * tile_size,), means2d.dtype)
  return jax.lax.fori_loop(0, _num_blocks(num_segments, block), body, (out, carry))[0]


@functools.partial(jax.custom_vjp, nondiff_argnums=(8, 9, 10))
def composite(means2d, conics, opacities, values, seg_splats, seg_tiles, seg_first, num_segments,
              tile_size: int, grid: tuple[int, int], block: int):
  """Composites every segment into its tile's pixels.

  means2d: [N, 2]; conics: [N, 3]; opacities: [N]; values: [N, C] per-splat values (colour, optionally
  depth); seg_splats: [S, L] int32 splat indices (N = empty); seg_tiles: [S] int32 (T = padding);
  seg_first: [S] bool; num_segments: int32 segments in use. S must be a multiple of `block`.
  Returns values [T, S*S, C] = sum_i c_i alpha_i T_i and log transmittance [T, S*S] over the composited
  splats of every tile pixel (tiles row-major, pixels row-major inside a tile).
  """
  return _composite_fwd(means2d, conics, opacities, values, seg_splats, seg_tiles, seg_first, num_segments,
                        tile_size, grid, block)[0]


def _geometry(tile_size, grid, dtype):
  """Pixel centres inside a tile [S*S, 2] and tile origins [T + 1, 2] (a padding tile last)."""
  tiles_x, tiles_y = grid
  local = jnp.stack(jnp.meshgrid(jnp.arange(tile_size), jnp.arange(tile_size), indexing="xy"), -1)
  origin = jnp.stack(jnp.meshgrid(jnp.arange(tiles_x), jnp.arange(tiles_y), indexing="xy"), -1)
  origin = jnp.concatenate([origin.reshape(-1, 2), jnp.zeros((1, 2), origin.dtype)])
  return (local.reshape(-1, 2) + 0.5).astype(dtype), (origin * tile_size).astype(dtype)


def _pad(x):
  """Appends a zero row: index N is the "no splat" sentinel of the segments (zero opacity)."""
  return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])


def _composite_fwd(means2d, conics, opacities, values, seg_splats, seg_tiles, seg_first, num_segments,
                   tile_size, grid, block):
  dtype = values.dtype
  pixels, origins = _geometry(tile_size, grid, dtype)
  num_tiles, num_pixels, channels = grid[0] * grid[1], tile_size * tile_size, values.shape[-1]
  padded = tuple(map(_pad, (means2d, conics, opacities, values)))
  num_seg_slots = seg_splats.shape[0]

  def body(b, state):
    out_values, out_log_t, in_front_log_t, in_front_values, carry_log_t, carry_values = state
    idx, tiles, first, m, con, op, val = _block_inputs(b, block, seg_splats, seg_tiles, seg_first, origins,
                                                       *padded)
    weights, keep, log_1m, start, carry_log_t = _block_weights(pixels, m, con, op, first, carry_log_t)
    seg_values = jnp.einsum("bpl,blc->bpc", weights, val)
    seg_log_t = jnp.sum(jnp.where(keep, log_1m, 0.0), -1)
    front_values, carry_values = chain_segments(seg_values, first, carry_values)
    put = lambda buf, x: jax.lax.dynamic_update_slice_in_dim(buf, x, b * block, 0)
    return (out_values.at[tiles].add(seg_values), out_log_t.at[tiles].add(seg_log_t),
            put(in_front_log_t, start), put(in_front_values, front_values), carry_log_t, carry_values)

  state = (jnp.zeros((num_tiles + 1, num_pixels, channels), dtype), jnp.zeros((num_tiles + 1, num_pixels), dtype),
           jnp.zeros((num_seg_slots, num_pixels), dtype), jnp.zeros((num_seg_slots, num_pixels, channels), dtype),
           jnp.zeros((num_pixels,), dtype), jnp.zeros((num_pixels, channels), dtype))
  state = jax.lax.fori_loop(0, _num_blocks(num_segments, block), body, state)
  out_values, out_log_t, in_front_log_t, in_front_values = state[:4]
  result = (out_values[:num_tiles], out_log_t[:num_tiles])
  residuals = (means2d, conics, opacities, values, seg_splats, seg_tiles, seg_first, num_segments,
               in_front_log_t, in_front_values, out_values)
  return result, residuals


def _composite_bwd(tile_size, grid, block, residuals, cotangents):
  (means2d, conics, opacities, values, seg_splats, seg_tiles, seg_first, num_segments, in_front_log_t,
   in_front_values, out_values) = residuals
  g_values, g_log_t = cotangents
  dtype = values.dtype
  pixels, origins = _geometry(tile_size, grid, dtype)
  padded = tuple(map(_pad, (means2d, conics, opacities, values)))
  g_values, g_log_t = _pad(g_values), _pad(g_log_t)

  def body(b, grads):
    idx, tiles, first, m, con, op, val = _block_inputs(b, block, seg_splats, seg_tiles, seg_first, origins,
                                                       *padded)
    alpha, falloff = pair_alpha(pixels, m, con, op)
    log_1m = jnp.log1p(-alpha)
    start = jax.lax.dynamic_slice_in_dim(in_front_log_t, b * block, block)
    front_values = jax.lax.dynamic_slice_in_dim(in_front_values, b * block, block)
    seen = start[..., None] + running_sum(log_1m)
    keep = seen >= LOG_T_MIN
    t_before = jnp.exp(seen - log_1m)
    weights = jnp.where(keep, alpha * t_before, 0.0)
    g, g_t = g_values[tiles], g_log_t[tiles]  # [B, P, C], [B, P]
    g_colour = jnp.einsum("bpc,blc->bpl", g, val)  # dL/dvalues . c_i per pixel and pair
    # dL/dalpha_i = T_i g.c_i - (g.(colour behind i) + dL/dlogT) / (1 - alpha_i) (3D-GS backward), the colour
    # behind i being the tile's final colour minus everything composited up to and including i.
    after_front = jnp.sum(g * (out_values[tiles] - front_values), -1)
    g_behind = after_front[..., None] - running_sum(weights * g_colour)
    g_alpha = jnp.where(keep, t_before * g_colour - (g_behind + g_t[..., None]) / (1.0 - alpha), 0.0)
    # alpha = min(0.99, o exp(power)): no gradient where clamped or skipped.
    live = keep & (alpha > 0) & (op[:, None, :] * falloff < ALPHA_MAX)
    g_power = jnp.where(live, g_alpha * alpha, 0.0)
    g_opacity = jnp.sum(jnp.where(live, g_alpha * falloff, 0.0), 1)
    g_mean, g_conic = _power_gradients(g_power, pixels, m, con)
    # Sums over the tile's pixels one channel at a time: a batched [L, P] x [P, C] product is slow on CPU.
    g_val = jnp.stack([jnp.sum(weights * g[:, :, None, k], 1) for k in range(g.shape[-1])], -1)
    gm, gc, go, gv = grads
    return gm.at[idx].add(g_mean), gc.at[idx].add(g_conic), go.at[idx].add(g_opacity), gv.at[idx].add(g_val)

  grads = tuple(jnp.zeros_like(x) for x in padded)
  grads = jax.lax.fori_loop(0, _num_blocks(num_segments, block), body, grads)
  gm, gc, go, gv = (x[:-1] for x in grads)
  return gm, gc, go, gv, None, None, None, None


composite.defvjp(_composite_fwd, _composite_bwd)
