"""A view's image as a linear map of the splats' colours (beyond the paper: what a concealment that trains colours
alone renders).

With every Gaussian's geometry and opacity fixed, a view's image is C(p) = sum_i w_i(p) c_i + T(p) b (Kerbl et al.
2023, arXiv:2308.04079, eq. 3, with w_i = alpha_i T_i): linear in the splats' colours c_i, with weights and final
transmittance T that depend on geometry and opacity alone. `colour_weights` reads them once from the renderer's own
compositing (composite.pair_weights) and keeps the nonzero ones; `linear_image` then gives the image of any colours
as one sparse product, and its gradient is the transpose: the renderer's image and gradient up to the order of
float sums, without its projection, sorting and compositing.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from conceal_jax.splat import binning, composite
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera, camera_center
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, sh_degree, tile_layout, untile_image, with_capacity


@struct.dataclass
class ColourWeights:
  """One view's image as a map of colours: pixels [K] int32 flat pixel index y * width + x, ascending; rows [K]
  int32 the Gaussian of each weight; weights [K] alpha_i T_i, nonzero but for `stacked_maps`' padding;
  transmittance [H, W] the final T; num_pairs: int32, the splat-tile pairs the view's render composites."""
  pixels: jax.Array
  rows: jax.Array
  weights: jax.Array
  transmittance: jax.Array
  num_pairs: jax.Array


def colour_weights(gaussians: Gaussians, camera: Camera, options: RenderOptions = RenderOptions()) -> ColourWeights:
  """The weights of `gaussians`' colours in their render from `camera` with `options` (eager: the number of
  nonzero weights decides the arrays' length), and the final transmittance 1 - sum_i w_i (eq. 3's T, which the
  render's alpha is up to float rounding). Depth and SH options do not matter: the weights are geometry's. Several
  views of a kind read fastest with options.pair_capacity near their pair counts (render.grow_capacity to the most
  one needed so far: a view that needs more grows it)."""
  options = dataclasses.replace(options, with_depth=False, with_alpha=True)
  height, width = camera.height, camera.width
  if gaussians.num == 0:
    nothing = jnp.zeros((0,), jnp.int32)
    return ColourWeights(nothing, nothing, jnp.zeros((0,), gaussians.means.dtype),
                         jnp.ones((height, width), gaussians.means.dtype), jnp.int32(0))
  # the segments the view's pairs fill, grown (and re-run) where it needs more than the options hold
  out = with_capacity(lambda opts: _segment_weights(gaussians, camera, opts), options,
                      (gaussians.num, width, height))
  weights, splats, tiles = (np.asarray(x)[:int(out.count)] for x in (out.weights, out.splats, out.tiles))
  seg, pixel, lane = np.nonzero(weights)
  flat = image_pixels(camera, options.tile_size)[tiles[seg], pixel]
  inside = flat >= 0
  flat = flat[inside]
  order = np.argsort(flat, kind="stable")
  values = weights[seg, pixel, lane][inside]
  covered = np.bincount(flat, weights=values.astype(np.float64), minlength=height * width)
  return ColourWeights(pixels=jnp.asarray(flat[order].astype(np.int32)),
                       rows=jnp.asarray(splats[seg, lane][inside][order].astype(np.int32)),
                       weights=jnp.asarray(values[order]),
                       transmittance=jnp.asarray((1.0 - covered).reshape(height, width).astype(values.dtype)),
                       num_pairs=out.num_pairs)


def image_pixels(camera: Camera, tile_size: int) -> np.ndarray:
  """[T, S*S] the flat image index y * width + x of every tile pixel, -1 where its tile sticks out of the image:
  render.untile_image's layout, inverted (host-side)."""
  grid = binning.tile_grid(camera.width, camera.height, tile_size)
  num = grid[0] * grid[1] * tile_size * tile_size
  tile_pixel = np.asarray(untile_image(jnp.arange(num).reshape(-1, tile_size * tile_size), grid, tile_size, camera))
  index = np.full(num, -1, np.int64)
  index[tile_pixel.ravel()] = np.arange(tile_pixel.size)
  return index.reshape(-1, tile_size * tile_size)


class _Segments(NamedTuple):
  weights: jax.Array
  splats: jax.Array
  tiles: jax.Array
  count: jax.Array
  num_pairs: jax.Array


@functools.partial(jax.jit, static_argnames=("options",))
def _segment_weights(gaussians: Gaussians, camera: Camera, options: RenderOptions) -> _Segments:
  """Every segment's weights [S, P, L], splat indices [S, L], tiles [S], the number of segments in use and the
  splat-tile pairs the view needs (more than options.pair_capacity: the rest were dropped)."""
  view = tile_layout(gaussians, camera, options, 0)
  s = view.segments
  weights = composite.pair_weights(view.splats.means2d, view.splats.conics, view.splats.opacities, s.splats,
                                   s.tiles, s.first, s.count, options.tile_size, view.grid, view.block)
  return _Segments(weights, s.splats, s.tiles, s.count, view.num_pairs)


def stacked_maps(maps, length: int) -> ColourWeights:
  """ColourWeights [R] of `maps` (each [K_r] with K_r <= `length`) in host arrays, each padded to `length` entries
  with zero weights on its image's last pixel (pixels stay ascending) and row 0: the same images, in one shape.
  Host-side (numpy: an eager jnp concatenate compiles anew for every length), each map copied once."""
  pixels = np.empty((len(maps), length), np.int32)
  rows = np.zeros((len(maps), length), np.int32)
  weights = np.zeros((len(maps), length), np.asarray(maps[0].weights).dtype)
  for r, m in enumerate(maps):
    k = int(m.weights.shape[0])
    if k > length:
      raise ValueError(f"cannot pad {k} weights to {length}")
    pixels[r, :k], rows[r, :k], weights[r, :k] = np.asarray(m.pixels), np.asarray(m.rows), np.asarray(m.weights)
    pixels[r, k:] = m.transmittance.size - 1
  return ColourWeights(pixels=pixels, rows=rows, weights=weights,
                       transmittance=np.stack([np.asarray(m.transmittance) for m in maps]),
                       num_pairs=np.stack([np.asarray(m.num_pairs) for m in maps]))


def view_colours(gaussians: Gaussians, camera: Camera, degree: int) -> jax.Array:
  """[N, 3] each Gaussian's colour seen from `camera` (SH up to `degree`, clamped at 0 as the renderer does)."""
  return sh_lib.sh_to_rgb(gaussians.sh, gaussians.means, camera_center(camera), degree)


def linear_image(weights: ColourWeights, colours: jax.Array, background: jax.Array) -> jax.Array:
  """[H, W, 3] the image whose colours are `colours` [N, 3] over `background` [3]: sum_i w_i c_i + T b."""
  height, width = weights.transmittance.shape
  per_pixel = weights.weights[:, None] * colours[weights.rows]
  image = jax.ops.segment_sum(per_pixel, weights.pixels, num_segments=height * width, indices_are_sorted=True)
  return image.reshape(height, width, -1) + weights.transmittance[..., None] * background


def render_through(weights: ColourWeights, gaussians: Gaussians, camera: Camera,
                   options: RenderOptions = RenderOptions()) -> jax.Array:
  """[H, W, 3] the render of `gaussians` (the ones `weights` was read from, any colours) from `camera` with
  `options`, through `weights`: their view colours (`view_colours`, the render's SH degree) as `linear_image`."""
  colours = view_colours(gaussians, camera, sh_degree(gaussians, options))
  return linear_image(weights, colours, jnp.asarray(options.background, gaussians.means.dtype))
