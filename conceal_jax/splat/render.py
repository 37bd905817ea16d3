"""The differentiable tile renderer: project -> bin pairs -> cut into segments -> composite.

`render` composites, by default, every splat the 3D-GS rasterizer composites (Kerbl et al. 2023,
arXiv:2308.04079, s.6) on every image: the work is proportional to the splat-tile pairs that exist, held in
buffers of a static capacity. Options are static (a change retraces): a degree-0 scene evaluates no SH
basis beyond DC, the non-antialiased path computes no compensation, and depth is composited only when
asked for.

Capacity contract. `RenderOptions.pair_capacity` sizes the pair buffer (None: automatic). Every output
reports `num_pairs`, the pairs the image needed, and `overflowed` (num_pairs > pair_capacity, the static
capacity used). Called eagerly (concrete inputs, also under jax.grad without jit), `render` and
`render_batch` never return a truncated image: on overflow they re-run once with `grow_capacity` and
remember the capacity for the next call with the same scene size and options. Traced inside a caller's
jit, they cannot re-run: the caller checks `overflowed` and re-runs its step with
`grow_capacity(options, num_pairs)` (for a batch, the max over views).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from conceal_jax.splat import binning
from conceal_jax.splat import composite
from conceal_jax.splat import segments as segments_lib
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.projection import project

# Pixels whose coverage is below this get depth 0 instead of a division by ~0.
_DEPTH_ALPHA_FLOOR = 1e-10
# Capacity buckets: a geometric series with ratio sqrt(2) from _MIN_CAPACITY, rounded up to 256.
_MIN_CAPACITY = 1024
# Images whose every splat-tile pair fits this many start at that capacity (initial_capacity): small buffers, and a
# first eager render that never compiles a second program at a grown capacity.
_SMALL_IMAGE_PAIRS = 1 << 16
# Pixel-pairs evaluated per loop iteration of the compositor, at most: on CPU each iteration's few dozen operations
# cost a fixed overhead, so few large iterations beat many cache-sized ones (experiments/results/cpu_speed.md).
_BLOCK_PIXEL_PAIRS = 1 << 17
# ... and at most this fraction of the image's segment slots, so that a small image's last block is mostly work.
_BLOCKS_PER_IMAGE = 8
# Last capacity that sufficed, per (options, number of Gaussians, image size), for eager calls.
_capacity_cache: dict = {}


@dataclasses.dataclass(frozen=True)
class RenderOptions:
  """Static rendering options (hashable; a change retraces `render`).

  sh_degree: SH bands to evaluate, 0..3; None uses every band the scene stores, and so does a scene storing
    fewer (a degree-1 file under a degree-3 config renders at degree 1: its missing bands would add zero).
  background: RGB composited behind the splats, weighted by the final transmittance.
  tile_size: square tile edge in pixels.
  max_per_tile: None (default): exact, every splat 3D-GS composites. An int K is an APPROXIMATION: each
    tile composites only its K nearest splats (`num_overflow_tiles` counts the tiles that lost some).
  segment_size: pairs per compositing segment (work is pairs plus < segment_size padding per tile).
  pair_capacity: static size of the splat-tile pair buffer; None picks one automatically (see module doc).
  antialiased: Mip-Splatting style opacity compensation for the 2D dilation.
  near: camera-space z at or below which splats are culled.
  with_alpha / with_depth: also return coverage [H, W] / expected depth [H, W].
  """
  sh_degree: int | None = None
  background: tuple[float, float, float] = (0.0, 0.0, 0.0)
  tile_size: int = 8
  max_per_tile: int | None = None
  segment_size: int = 32
  pair_capacity: int | None = None
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
    if self.segment_size < 1:
      raise ValueError(f"segment_size must be positive, got {self.segment_size}")
    if self.pair_capacity is not None and self.pair_capacity < 1:
      raise ValueError(f"pair_capacity must be positive or None (automatic), got {self.pair_capacity}")
    if not self.near > 0:
      raise ValueError(f"near must be positive, got {self.near}")

  @property
  def exact(self) -> bool:
    return self.max_per_tile is None


@struct.dataclass
class RenderOutput:
  """rgb: [H, W, 3]; alpha: [H, W] or None; depth: [H, W] or None (expected z of the visible splats);
  num_overflow_tiles: int32, tiles with more than max_per_tile pairs (0 in the exact default);
  radii: [N] int32 3D-GS screen radius (3 sigma) of every Gaussian in pixels, 0 where culled or beside the image;
  num_pairs: int32 splat-tile pairs the image needs; pair_capacity: static int, the capacity used."""
  rgb: jax.Array
  alpha: jax.Array | None
  depth: jax.Array | None
  num_overflow_tiles: jax.Array
  radii: jax.Array
  num_pairs: jax.Array
  pair_capacity: int = struct.field(pytree_node=False, default=0)

  @property
  def overflowed(self) -> jax.Array:
    """bool (batched like num_pairs): the image needed more pairs than the buffer holds, so it is missing
    some; re-run with grow_capacity."""
    return self.num_pairs > self.pair_capacity


def round_capacity(needed: int) -> int:
  """`needed` pairs rounded up to a multiple of 256, the granularity of every pair capacity (host-side)."""
  return -(-math.ceil(needed) // 256) * 256


def capacity_bucket(needed: int) -> int:
  """The smallest bucket >= needed: 1024 * sqrt(2)^k rounded up to a multiple of 256 (pure, host-side)."""
  k = max(0, math.ceil(2 * math.log2(max(needed, 1) / _MIN_CAPACITY) - 1e-9))
  while True:
    bucket = round_capacity(math.ceil(_MIN_CAPACITY * 2 ** (k / 2)))
    if bucket >= needed:
      return bucket
    k += 1


def grow_capacity(options: RenderOptions, needed) -> RenderOptions:
  """Options whose pair_capacity is the next bucket >= needed (an int, or a concrete array such as
  RenderOutput.num_pairs, batched or not: the max is taken). Pure and host-side."""
  needed = int(jnp.max(jnp.asarray(needed)))
  return dataclasses.replace(options, pair_capacity=capacity_bucket(needed))


def initial_capacity(num_gaussians: int, options: RenderOptions, num_tiles: int | None = None) -> int:
  """The automatic capacity before anything is known about the scene: a few tiles per Gaussian, more for
  smaller tiles (the pair counts it is set from: experiments/results/train_configs.md). Given the image's
  `num_tiles`, an image that can need at most _SMALL_IMAGE_PAIRS pairs (every splat on every tile) gets them
  all at once, so that its first render never re-runs (and compiles) at a grown capacity."""
  per_gaussian = 2 + 48 / options.tile_size
  estimate = capacity_bucket(int(num_gaussians * per_gaussian))
  if num_tiles is None:
    return estimate
  most = capacity_bucket(num_gaussians * num_tiles)
  return most if most <= max(estimate, _SMALL_IMAGE_PAIRS) else estimate


def render(gaussians: Gaussians, camera: Camera, options: RenderOptions = RenderOptions(),
           means2d_offset: jax.Array | None = None) -> RenderOutput:
  """Renders `gaussians` from `camera`; differentiable with respect to both (except binning).

  means2d_offset: optional [N, 2] pixel offsets added to the projected means. Passing zeros and
  differentiating with respect to them gives the loss gradient at the 2D means, which 3D-GS
  densification accumulates (the offsets do not move the tile binning).
  """
  return with_capacity(lambda opts: _render(gaussians, camera, opts, means2d_offset), options,
                       (gaussians.num, camera.width, camera.height))


def render_batch(gaussians: Gaussians, cameras: Camera,
                 options: RenderOptions = RenderOptions()) -> RenderOutput:
  """`render` vmapped over a stacked Camera (see camera.stack): every output gains a leading axis.
  One capacity serves every view; eagerly it grows to the max over views."""
  batched = lambda opts: jax.vmap(_render, in_axes=(None, 0, None))(gaussians, cameras, opts)
  return with_capacity(batched, options, (gaussians.num, cameras.width, cameras.height))


def with_capacity(run, options: RenderOptions, scene_key):
  """Runs `run(options)` (a RenderOutput, or any output with the `num_pairs` a render needed) with a concrete
  capacity (where `options` hold none, the one last found for `scene_key`: N, width, height); re-runs with a grown
  one while it reports overflow and its outputs are concrete (an eager call). Traced outputs are returned as they
  are."""
  key = (dataclasses.replace(options, pair_capacity=None),) + tuple(scene_key)
  opts = options
  if opts.pair_capacity is None:
    num, width, height = scene_key
    tiles_x, tiles_y = binning.tile_grid(width, height, opts.tile_size)
    opts = dataclasses.replace(opts, pair_capacity=_capacity_cache.get(key, initial_capacity(num, opts,
                                                                                             tiles_x * tiles_y)))
  out = run(opts)
  needed = _concrete_max(out.num_pairs)
  while needed is not None and needed > opts.pair_capacity:
    opts = grow_capacity(opts, needed)
    out = run(opts)
    needed = _concrete_max(out.num_pairs)
  if needed is not None and options.pair_capacity is None:
    if len(_capacity_cache) > 256:
      _capacity_cache.clear()
    _capacity_cache[key] = opts.pair_capacity
  return out


def _concrete_max(x: jax.Array) -> int | None:
  """max(x) as a Python int when x is concrete, None when it is traced."""
  try:
    return int(jnp.max(x))
  except (jax.errors.ConcretizationTypeError, jax.errors.TracerIntegerConversionError, TypeError):
    return None


def sh_degree(gaussians: Gaussians, options: RenderOptions) -> int:
  """The SH degree a render of `gaussians` evaluates: options.sh_degree, at most the scene's (all of the scene's
  bands where it is None)."""
  return gaussians.sh_degree if options.sh_degree is None else min(options.sh_degree, gaussians.sh_degree)


@functools.partial(jax.jit, static_argnames=("options",))
def _render(gaussians: Gaussians, camera: Camera, options: RenderOptions,
            means2d_offset: jax.Array | None = None) -> RenderOutput:
  degree = sh_degree(gaussians, options)
  dtype = gaussians.means.dtype
  background = jnp.asarray(options.background, dtype)
  capacity = options.pair_capacity
  if gaussians.num == 0:
    return _background_only(camera, background, options)
  view = tile_layout(gaussians, camera, options, degree, means2d_offset)
  splats, segs, grid, ts = view.splats, view.segments, view.grid, options.tile_size
  values = splats.colors
  if options.with_depth:
    values = jnp.concatenate([values, splats.depths[:, None]], -1)
  tile_values, log_t = composite.composite(splats.means2d, splats.conics, splats.opacities, values,
                                           segs.splats, segs.tiles, segs.first, segs.count, ts, grid, view.block)
  t_final = jnp.exp(log_t)
  rgb = tile_values[..., :3] + t_final[..., None] * background
  alpha = 1.0 - t_final
  depth = tile_values[..., 3] / jnp.maximum(alpha, _DEPTH_ALPHA_FLOOR) if options.with_depth else None
  untile = lambda x: untile_image(x, grid, ts, camera) if x is not None else None
  return RenderOutput(rgb=untile(rgb), alpha=untile(alpha) if options.with_alpha else None,
                      depth=untile(depth), num_overflow_tiles=view.num_overflow_tiles, radii=splats.radii,
                      num_pairs=view.num_pairs, pair_capacity=capacity)


class TileLayout(NamedTuple):
  """One view's splats cut into the compositor's tile segments: splats (projection.Splats, radii on the tiles),
  segments (segments.Segments), grid (tiles across, down), block (segments a compositing iteration takes),
  num_pairs and num_overflow_tiles (int32)."""
  splats: Any
  segments: Any
  grid: tuple[int, int]
  block: int
  num_pairs: jax.Array
  num_overflow_tiles: jax.Array


def tile_layout(gaussians: Gaussians, camera: Camera, options: RenderOptions, degree: int,
                means2d_offset: jax.Array | None = None) -> TileLayout:
  """Projects `gaussians` (SH up to `degree`) into `camera`, bins the splat-tile pairs into `options`' static
  pair capacity and cuts each tile's depth-sorted run into segments: everything a view's compositing reads."""
  splats = project(gaussians, camera, degree, options.near, options.antialiased)
  if means2d_offset is not None:
    splats = splats.replace(means2d=splats.means2d + jnp.where(splats.radii[:, None] > 0, means2d_offset, 0))
  ts = options.tile_size
  grid = binning.tile_grid(camera.width, camera.height, ts)
  splats = splats.replace(radii=binning.on_tile_radii(splats.means2d, splats.radii, ts, grid))
  pairs = binning.bin_pairs(splats.means2d, splats.cov2d, splats.depths, splats.opacities, splats.radii, ts,
                            grid, options.pair_capacity)
  block, slots = segment_blocks(options, grid[0] * grid[1])
  segs, overflow_tiles = segments_lib.segment_layout(pairs, gaussians.num, options.segment_size, slots,
                                                     options.max_per_tile)
  return TileLayout(splats, segs, grid, block, pairs.num_pairs, overflow_tiles)


def segment_blocks(options: RenderOptions, num_tiles: int) -> tuple[int, int]:
  """(segments per compositing loop iteration, static segment slots) for `options` (with a pair capacity)
  on an image of `num_tiles` tiles."""
  length = options.segment_size
  slots = segments_lib.segment_capacity(options.pair_capacity, num_tiles, length, 1, options.max_per_tile)
  block = max(1, min(_BLOCK_PIXEL_PAIRS // (options.tile_size ** 2 * length), -(-slots // _BLOCKS_PER_IMAGE)))
  return block, segments_lib.segment_capacity(options.pair_capacity, num_tiles, length, block, options.max_per_tile)


def untile_image(per_tile: jax.Array, grid: tuple[int, int], tile_size: int, camera: Camera) -> jax.Array:
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
                      num_overflow_tiles=jnp.zeros((), jnp.int32), radii=jnp.zeros((0,), jnp.int32),
                      num_pairs=jnp.zeros((), jnp.int32), pair_capacity=options.pair_capacity)
