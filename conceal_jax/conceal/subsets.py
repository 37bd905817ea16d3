"""The Gaussians each view of a concealment step reaches: render a view from those alone, the same image for less.

A speed-up beyond the paper that changes no value. Where only the carrier film's colours train (carrier.py) the
geometry of every Gaussian is fixed, so the Gaussians whose 3D-GS screen square touches a view's image (its radius
as the renderer computes it, > 0) are fixed too, and the rest add no splat-tile pair to its render: rendering the
film and the Gaussians reaching the view, in their order in the student, composites the same pairs in the same
order (the depth sort is stable in that order) into the same image, and its gradient reaches the same colours.
What a check render's attacks change keeps that true: 8-bit colours and opacities, opacity resets and drops
change no screen square, and the film's merges land on film rows (grouping.group_members puts them first). Views
that no Gaussian that trains reaches (the training views: the film is unseen from every one of them) render the
teacher's image, which the step already holds, and are not rendered at all (`fixed`).
"""
from __future__ import annotations

import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.splat import binning
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.projection import project
from conceal_jax.splat.render import RenderOptions


@functools.partial(jax.jit, static_argnames="options")
def screen_radii(gaussians: Gaussians, camera: Camera, options: RenderOptions) -> jax.Array:
  """[N] int32 the renderer's screen radius of each Gaussian at `camera` (render.RenderOutput.radii without the
  render): 0 where it is culled or touches no tile of the image."""
  splats = project(gaussians, camera, 0, options.near, options.antialiased)  # radii do not depend on colours
  grid = binning.tile_grid(camera.width, camera.height, options.tile_size)
  return binning.on_tile_radii(splats.means2d, splats.radii, options.tile_size, grid)


def view_rows(gaussians: Gaussians, cameras: Sequence[Camera], options: RenderOptions, always: np.ndarray,
              fixed: np.ndarray) -> np.ndarray:
  """[C, M] int32 the rows of `gaussians` each camera's render reads, ascending: those whose screen square
  touches its image and the rows `always` ([N] bool: the film) read; none for the `fixed` cameras ([C] bool).
  Padded with N (no row) to M, the most any camera reads."""
  rows = [np.zeros(0, np.int64) if still else np.flatnonzero((np.asarray(screen_radii(gaussians, camera, options)) > 0)
                                                              | always)
          for camera, still in zip(cameras, fixed)]
  width = max(1, max(len(r) for r in rows))
  padded = np.full((len(rows), width), gaussians.num, np.int32)
  for c, r in enumerate(rows):
    padded[c, :len(r)] = r
  return padded


def gather(gaussians: Gaussians, rows: jax.Array, fill=jnp.nan) -> Gaussians:
  """Gaussians [M] (or any pytree of [N, ...] rows): the `rows` [M] of `gaussians`; a row past the last is `fill`,
  for Gaussians NaN parameters, which the renderer culls (projection.project) and whose gradient is dropped."""
  return jax.tree.map(lambda x: x.at[rows].get(mode="fill", fill_value=fill), gaussians)


def rows_of(gaussians: Gaussians, rows: jax.Array | None, fill=jnp.nan) -> Gaussians:
  """The Gaussians a render of `rows` ([M], or None: all) reads: `gather`'s, or all of them."""
  return gaussians if rows is None else gather(gaussians, rows, fill)
