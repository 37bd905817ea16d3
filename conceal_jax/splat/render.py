"""The differentiable tile renderer: project -> bin -> composite, specialised by static options.

`render` is jit-compiled with `RenderOptions` as a static argument, so every option below changes the
traced program rather than adding runtime branches: a degree-0 scene evaluates no SH basis beyond DC,
the non-antialiased path computes no compensation, depth is composited only when asked for, and the
default (truncated) mode never traces the exact mode's loop.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from flax import struct

from conceal_jax.splat import binning
from conceal_jax.splat import composite
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.projection import Splats2D, project

# Pixels whose coverage is below this get depth 0 instead of a division by ~0.
_DEPTH_ALPHA_FLOOR = 1e-10


@dataclasses.dataclass(frozen=True)
class RenderOptions:
  """Static rendering options (hashable; a change retraces `render`).

  sh_degree: SH bands to evaluate, 0..3; None uses every band the scene stores.
  background: RGB composited behind the splats, weighted by the final transmittance.
  tile_size: square tile edge in pixels.
  max_per_tile: K, the number of nearest splats composited per tile; None selects the exact mode, which
    walks every overlapping splat in chunks of `exact_chunk` (slower, never truncates).
  antialiased: Mip-Splatting style opacity compensation for the 2D dilation.
  near: camera-space z at or below which splats are culled.
  with_alpha / with_depth: also return coverage [H, W] / expected depth [H, W].
  """
  sh_degree: int | None = None
  background: tuple[float, float, float] = (0.0, 0.0, 0.0)
  tile_size: int = 16
  max_per_tile: int | None = 256
  exact_chunk: int = 128
  antialiased: bool = False
  near: float = 0.2
  with_alpha: bool = True
  with_depth: bool = False

  def __post_init__(self):
    object.__setattr__(self, "background", tuple(float(c) for c in self.background))
    if len(self.background) != 3:
      raise ValueError(f"background must have 3 values (RGB), got {self.background}")
    if self.sh_degree is not None and not 0 <= self.sh_degree <= sh_lib.MAX_DEGREE:
      raise ValueError(f"sh_degree must be in 0..{sh_lib.MAX_DEGREE} or None, got {self.sh_degree}")
    if self.tile_size < 1:
      raise ValueError(f"tile_size must be positive, got {self.tile_size}")
    if self.max_per_tile is not None and self.max_per_tile < 1:
      raise ValueError(f"max_per_tile must be positive or None (exact), got {self.max_per_tile}")
    if self.exact_chunk < 1:
      raise ValueError(f"exact_chunk must be positive, got {self.exact_chunk}")
    if not self.near > 0:
      raise ValueError(f"near must be positive, got {self.near}")

  @property
  def exact(self) -> bool:
    return self.max_per_tile is None


@struct.dataclass
class RenderOutput:
  """rgb: [H, W, 3]; alpha: [H, W] or None; depth: [H, W] or None (expected z of the visible splats);
  num_overflow_tiles: int32, tiles touched by more than max_per_tile splats (0 in exact mode);
  radii: [N] int32 screen radius of every Gaussian in pixels, 0 where culled (for densification)."""
  rgb: jax.Array
  alpha: jax.Array | None
  depth: jax.Array | None
  num_overflow_tiles: jax.Array
  radii: jax.Array


@functools.partial(jax.jit, static_argnames=("options",))
def render(gaussians: Gaussians, camera: Camera, options: RenderOptions = RenderOptions(),
           means2d_offset: jax.Array | None = None) -> RenderOutput:
  """Renders `gaussians` from `camera`; differentiable with respect to both (except binning).

  means2d_offset: optional [N, 2] pixel offsets added to the projected means. Passing zeros and
  differentiating with respect to them gives the loss gradient at the 2D means, which 3D-GS
  densification accumulates (the offsets do not move the tile binning).
  """
  degree = gaussians.sh_degree if options.sh_degree is None else options.sh_degree
  dtype = gaussians.means.dtype
  background = jnp.asarray(options.background, dtype)
  if gaussians.num == 0:
    return _background_only(camera, background, options)
  splats = project(gaussians, camera, degree, options.near, options.antialiased)
  if means2d_offset is not None:
    splats = splats.replace(means2d=splats.means2d + jnp.where(splats.radii[:, None] > 0, means2d_offset, 0))
  grid = binning.tile_grid(camera.width, camera.height, options.tile_size)
  length = gaussians.num if options.exact else options.max_per_tile
  lists, counts = binning.tile_lists(splats.means2d, splats.depths, splats.radii, options.tile_size,
                                     grid, length)
  acc = _rasterize(splats, lists, counts, grid, options)
  t_final = jnp.exp(acc.log_t)
  rgb = acc.values[..., :3] + t_final[..., None] * background
  alpha = 1.0 - t_final
  depth = acc.values[..., 3] / jnp.maximum(alpha, _DEPTH_ALPHA_FLOOR) if options.with_depth else None
  untile = lambda x: _untile(x, grid, options.tile_size, camera) if x is not None else None
  overflow = jnp.zeros((), jnp.int32) if options.exact else jnp.sum(counts > options.max_per_tile,
                                                                     dtype=jnp.int32)
  return RenderOutput(rgb=untile(rgb), alpha=untile(alpha) if options.with_alpha else None,
                      depth=untile(depth), num_overflow_tiles=overflow, radii=splats.radii)


def render_batch(gaussians: Gaussians, cameras: Camera,
                 options: RenderOptions = RenderOptions()) -> RenderOutput:
  """`render` vmapped over a stacked Camera (see camera.stack): every output gains a leading axis."""
  return jax.vmap(render, in_axes=(None, 0, None))(gaussians, cameras, options)


def _rasterize(splats: Splats2D, lists: jax.Array, counts: jax.Array, grid: tuple[int, int],
               options: RenderOptions) -> composite.Accumulator:
  """Composites each tile's list of splats over its pixels; returns per-tile accumulators [T, S*S]."""
  ts = options.tile_size
  pixels = _tile_pixel_centres(grid, ts, splats.means2d.dtype)  # [T, S*S, 2]
  values = splats.colors
  if options.with_depth:
    values = jnp.concatenate([values, splats.depths[:, None]], -1)
  # Index N is the "no splat" sentinel of the lists: zero opacity never composites.
  pad = lambda x: jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])
  means2d, conics, opacities, values = map(pad, (splats.means2d, splats.conics, splats.opacities, values))

  def composite_lists(acc, idx):  # idx: [T, C] splat indices, one chunk of every tile's list
    alpha = jax.vmap(composite.gaussian_alpha)(pixels, means2d[idx], conics[idx], opacities[idx])
    return jax.vmap(composite.composite_chunk)(acc, alpha, values[idx])

  acc = composite.Accumulator.empty((lists.shape[0], ts * ts), values.shape[-1], values.dtype)
  if not options.exact:
    return composite_lists(acc, lists)
  sentinel = splats.radii.shape[0]
  return _composite_in_chunks(composite_lists, acc, lists, jnp.max(counts), options.exact_chunk, sentinel)


def _composite_in_chunks(composite_lists, acc, lists, max_count, chunk, sentinel):
  """Exact mode: a scan over chunks of the full depth-sorted lists.

  A chunk past every tile's count, or after every pixel has stopped, is skipped by lax.cond; the body is
  rematerialised in the backward pass so memory stays at one chunk's worth of intermediates.
  """
  num_tiles, length = lists.shape
  num_chunks = -(-length // chunk)
  lists = jnp.pad(lists, ((0, 0), (0, num_chunks * chunk - length)), constant_values=sentinel)
  chunks = jnp.moveaxis(lists.reshape(num_tiles, num_chunks, chunk), 1, 0)  # [chunks, T, C]

  @jax.checkpoint
  def step(acc, inputs):
    start, idx = inputs
    live = (start < max_count) & jnp.any(acc.log_t_seen >= composite.LOG_T_MIN)
    return jax.lax.cond(live, composite_lists, lambda a, _: a, acc, idx), None

  acc, _ = jax.lax.scan(step, acc, (jnp.arange(num_chunks) * chunk, chunks))
  return acc


def _tile_pixel_centres(grid: tuple[int, int], tile_size: int, dtype) -> jax.Array:
  """[T, S*S, 2] (u, v) pixel centres of every tile, tiles row-major, pixels row-major inside a tile."""
  tiles_x, tiles_y = grid
  local = jnp.stack(jnp.meshgrid(jnp.arange(tile_size), jnp.arange(tile_size), indexing="xy"), -1)
  origin = jnp.stack(jnp.meshgrid(jnp.arange(tiles_x), jnp.arange(tiles_y), indexing="xy"), -1)
  centres = origin.reshape(-1, 1, 2) * tile_size + local.reshape(1, -1, 2) + 0.5
  return centres.astype(dtype)


def _untile(per_tile: jax.Array, grid: tuple[int, int], tile_size: int, camera: Camera) -> jax.Array:
  """[T, S*S, ...] per-tile pixels -> [H, W, ...] image, cropping tiles that stick out of the image."""
  tiles_x, tiles_y = grid
  rest = per_tile.shape[2:]
  image = per_tile.reshape((tiles_y, tiles_x, tile_size, tile_size) + rest)
  image = jnp.swapaxes(image, 1, 2).reshape((tiles_y * tile_size, tiles_x * tile_size) + rest)
  return image[:camera.height, :camera.width]


def _background_only(camera: Camera, background: jax.Array, options: RenderOptions) -> RenderOutput:
  shape = (camera.height, camera.width)
  zeros = jnp.zeros(shape, background.dtype)
  return RenderOutput(rgb=jnp.broadcast_to(background, shape + (3,)),
                      alpha=zeros if options.with_alpha else None,
                      depth=zeros if options.with_depth else None,
                      num_overflow_tiles=jnp.zeros((), jnp.int32), radii=jnp.zeros((0,), jnp.int32))
