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

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from conceal_jax.splat import binning, composite
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera, camera_center
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, grow_capacity, render, sh_degree, tile_layout, untile_image


@struct.dataclass
class ColourWeights:
  """One view's image as a map of colours: pixels [K] int32 flat pixel index y * width + x, ascending; rows [K]
  int32 the Gaussian of each weight; weights [K] alpha_i T_i, nonzero but for `padded`'s; transmittance [H, W] the
  final T; num_pairs: int32, the splat-tile pairs the view's render composites."""
  pixels: jax.Array
  rows: jax.Array
  weights: jax.Array
  transmittance: jax.Array
  num_pairs: jax.Array


def colour_weights(gaussians: Gaussians, camera: Camera, options: RenderOptions = RenderOptions()) -> ColourWeights:
  """The weights of `gaussians`' colours in their render from `camera` with `options` (eager: the number of
  nonzero weights decides the arrays' length). Depth and SH options do not matter: the weights are geometry's.
  Several views of a kind read fastest with options.pair_capacity near their pair counts (render.grow_capacity to
  the most one needed so far: a view that needs more grows it)."""
  options = dataclasses.replace(options, with_depth=False, with_alpha=True)
  out = render(gaussians, camera, options)  # grows the pair capacity to what the view needs
  if gaussians.num == 0:
    nothing = jnp.zeros((0,), jnp.int32)
    return ColourWeights(nothing, nothing, jnp.zeros((0,), out.alpha.dtype), 1.0 - out.alpha, out.num_pairs)
  options = grow_capacity(options, out.num_pairs)  # the segments the view's pairs fill, not the render's buffer
  weights, splats, tiles, count = _segment_weights(gaussians, camera, options)
  weights, splats, tiles = (np.asarray(x)[:int(count)] for x in (weights, splats, tiles))
  seg, pixel, lane = np.nonzero(weights)
  flat = image_pixels(camera, options.tile_size)[tiles[seg], pixel]
  inside = flat >= 0
  flat = flat[inside]
  order = np.argsort(flat, kind="stable")
  pick = lambda a: jnp.asarray(a[inside][order])
  return ColourWeights(pixels=jnp.asarray(flat[order].astype(np.int32)),
                       rows=pick(splats[seg, lane].astype(np.int32)), weights=pick(weights[seg, pixel, lane]),
                       transmittance=1.0 - out.alpha, num_pairs=out.num_pairs)


def image_pixels(camera: Camera, tile_size: int) -> np.ndarray:
  """[T, S*S] the flat image index y * width + x of every tile pixel, -1 where its tile sticks out of the image:
  render.untile_image's layout, inverted (host-side)."""
  grid = binning.tile_grid(camera.width, camera.height, tile_size)
  num = grid[0] * grid[1] * tile_size * tile_size
  tile_pixel = np.asarray(untile_image(jnp.arange(num).reshape(-1, tile_size * tile_size), grid, tile_size, camera))
  index = np.full(num, -1, np.int64)
  index[tile_pixel.ravel()] = np.arange(tile_pixel.size)
  return index.reshape(-1, tile_size * tile_size)


@functools.partial(jax.jit, static_argnames=("options",))
def _segment_weights(gaussians: Gaussians, camera: Camera, options: RenderOptions):
  """Every segment's weights [S, P, L], splat indices [S, L], tiles [S] and the number of segments in use."""
  view = tile_layout(gaussians, camera, options, 0)
  s = view.segments
  weights = composite.pair_weights(view.splats.means2d, view.splats.conics, view.splats.opacities, s.splats,
                                   s.tiles, s.first, s.count, options.tile_size, view.grid, view.block)
  return weights, s.splats, s.tiles, s.count


def padded(weights: ColourWeights, length: int) -> ColourWeights:
  """`weights` with zero weights appended to `length` entries (on the last pixel, so pixels stay ascending, and
  row 0): the same image, in a shape several views' weights share."""
  pad = length - int(weights.weights.size)
  if pad < 0:
    raise ValueError(f"cannot pad {weights.weights.size} weights to {length}")
  last = weights.transmittance.size - 1
  extend = lambda x, value: jnp.concatenate([x, jnp.full((pad,), value, x.dtype)])
  return weights.replace(pixels=extend(weights.pixels, last), rows=extend(weights.rows, 0),
                         weights=extend(weights.weights, 0))


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
