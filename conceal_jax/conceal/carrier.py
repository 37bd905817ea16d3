"""A carrier for the mark that re-training cannot reach: a film of Gaussians no normal view sees (beyond the paper).

Fine-tuning a shared scene on its training views moves every Gaussian some training pixel depends on (Adam's
first steps move each parameter by its full rate, however small its gradient) and no other: a Gaussian no
training pixel depends on has an exactly zero gradient, so Adam leaves it where it is. The film is a grid of
flat Gaussians facing a key that looks where no camera of the scene looks (key.unseen_camera); the concealment
trains the film's base colours alone (its geometry frozen, so it cannot move into sight) and leaves
the teacher's Gaussians as they are, so the normal views render exactly the teacher's images.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.conceal import key as key_lib, subsets
from conceal_jax.gs import similarity
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians, concatenate, opacity_logit
from conceal_jax.splat.render import RenderOptions, render

# The film's thickness along the key's axis, as a fraction of its in-plane sigma (conceal.carrier.thickness's
# default): a flat splat.
THICKNESS = 0.01
# Film splats overlap their neighbours: in-plane sigma as a fraction of the grid spacing (conceal.carrier.spread's
# default).
SPREAD = 0.6
# The film's grid spacing where conceal.carrier.spacing is 0, in pixels of the decoder's input (the key's render is
# resized to mark.hidden_size square): a grid position every other decoder pixel, whatever the key's resolution.
DECODER_SPACING = 2.0
# The film's least start colour per channel: a film made the colour of a black background would start where 3D-GS
# clamps colours (at 0, sh.view_dependent_colour), which passes no gradient, so it could never learn its image.
MIN_START_RGB = 1.0 / 255
# Each splat a little deeper than the one before (this fraction of the distance across the film), so that no two
# are at the same depth: the renderer would blend a tie in storage order, which a reordering of the file changes.
STAGGER = 0.01


def layer_offsets(layers: int) -> np.ndarray:
  """[layers, 2] in [0, 1): where each layer's grid starts within a grid cell, spread evenly over the cell (the
  R2 low-discrepancy sequence, Roberts 2018), the first at the cell's centre."""
  plastic = 1.32471795724474602596  # the real root of x^3 = x + 1
  steps = np.arange(layers)[:, None] / np.array([plastic, plastic**2])
  return (0.5 + steps) % 1.0


@dataclasses.dataclass(frozen=True)
class Film:
  """conceal.carrier with film on: the film's distance from the key (median camera distances from the orbit target),
  grid spacing (key pixels; 0: carrier.key_spacing's), opacity, in-plane sigma (grid spacings), grids, splats per
  grid position, thickness along the key's axis (fraction of the in-plane sigma) (carrier.film), and whether the
  keys and decoys are cameras of the decoder's input size (at_decoder_size)."""
  distance: float
  spacing: float
  opacity: float
  spread: float
  layers: int
  stack: int
  thickness: float
  at_decoder_size: bool = False


def film_plan(config: ml_collections.ConfigDict) -> Film | None:
  """conceal.carrier checked: None with film off; a film needs mark.key_kind 'unseen' (it fills what it sees)."""
  c = config.conceal.carrier
  if not c.film:
    return None
  if config.mark.key_kind != "unseen":
    raise ValueError(f"conceal.carrier.film needs mark.key_kind='unseen', got {config.mark.key_kind!r}")
  if not (min(c.distance, c.spread, c.thickness) > 0 <= c.spacing and 0 < c.opacity < 1 <= min(c.layers, c.stack)):
    raise ValueError("conceal.carrier.distance, spread and thickness must be positive, spacing not negative, opacity "
                     f"in (0, 1), layers and stack at least 1, got {c.distance}, {c.spread}, {c.thickness}, "
                     f"{c.spacing}, {c.opacity}, {c.layers}, {c.stack}")
  if c.at_decoder_size and not (config.conceal.variant == "paper" and config.conceal.consistency):
    raise ValueError("conceal.carrier.at_decoder_size holds the normal views to the teacher's renders (L_kd): it "
                     "needs conceal.variant='paper' with conceal.consistency")
  if c.at_decoder_size and config.conceal.attacks.param_noise_max > 0:
    raise ValueError("conceal.carrier.at_decoder_size needs the training views left as the teacher's: parameter "
                     "noise (conceal.attacks.param_noise_max) moves every Gaussian")
  return Film(distance=float(c.distance), spacing=float(c.spacing), opacity=float(c.opacity), spread=float(c.spread),
              layers=int(c.layers), stack=int(c.stack), thickness=float(c.thickness),
              at_decoder_size=bool(c.at_decoder_size))


def film(camera: Camera, distance: float, spacing: float, opacity: float, color: Sequence[float],
         sh_degree: int, layers: int = 1, stack: int = 1, spread: float = SPREAD,
         thickness: float = THICKNESS) -> Gaussians:
  """[F] flat Gaussians `distance` in front of `camera` (each STAGGER-deeper than the last), `layers` grids of one
  position every `spacing` pixels of its image, each grid shifted within a cell (`layer_offsets`), `stack`
  consecutive splats at each position (F ~ stack * layers * W * H / spacing^2), facing it, each of `opacity` and
  `color` (RGB in [0, 1], raised to MIN_START_RGB) seen from any direction (SH of `sh_degree`, bands above DC zero),
  of in-plane sigma `spread` grid spacings and `thickness` times that along the key's axis. Many layers of faint
  splats make a film as opaque as one layer of dense ones, out of splats each below an opacity ceiling (3D-GS's
  opacity reset). A stack of splats small against their neighbours' distance (`spread`) is the cheapest merge a
  decimating converter finds (the same place, and with tied colours, `tied_rows`, the same colour), so decimation
  down to 1/stack of the film merges stacks."""
  grids = [np.meshgrid(np.arange(du * spacing, camera.width, spacing), np.arange(dv * spacing, camera.height, spacing))
           for du, dv in layer_offsets(layers)]
  u, v = (np.repeat(np.concatenate([grid[axis].ravel() for grid in grids]), stack) for axis in (0, 1))
  fx, fy, cx, cy = (float(x) for x in (camera.fx, camera.fy, camera.cx, camera.cy))
  depth = distance * (1.0 + STAGGER * np.arange(len(u)) / len(u))
  in_camera = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], -1)
  w2c = np.asarray(camera.world_to_camera, np.float64)
  rotation = w2c[:3, :3].T  # camera axes in the world
  means = (in_camera - w2c[:3, 3]) @ w2c[:3, :3]  # x_world = R^T (x_cam - t)
  sigma = spread * spacing * distance / min(fx, fy)  # the stagger's 1% aside, `spacing` pixels apart
  count = len(u)
  sh = np.zeros((count, (sh_degree + 1) ** 2, 3))
  sh[:, 0] = sh_lib.rgb_to_sh_dc(np.maximum(np.asarray(color, np.float64), MIN_START_RGB))
  logit = opacity_logit(opacity)
  as_f32 = lambda x: jnp.asarray(x, jnp.float32)
  log_scales = np.tile(np.log([sigma, sigma, sigma * thickness]), (count, 1))
  return Gaussians(means=as_f32(means), log_scales=as_f32(log_scales),
                   quats=as_f32(np.tile(similarity.matrix_to_quaternion(rotation), (count, 1))),
                   opacity_logits=as_f32(np.full(count, logit)), sh=as_f32(sh))


def contributing(scene: Gaussians, extra: Gaussians, cameras: Sequence[Camera], options: RenderOptions) -> np.ndarray:
  """[F] bool: whether any pixel of any of `cameras` depends on each Gaussian of `extra`, rendered together with
  `scene` (the renderer's own culling, 1/255 skip and early stop decide): the derivative of the image sum with
  respect to its colour is non-zero exactly there (every pixel a splat reaches gains from a brighter splat). The
  derivative is taken at grey (SH DC 0), where no colour clamp stops it: what a splat reaches does not depend on
  its colour. A camera none of `extra` reaches (each splat culled or beside its image, as the render bins them) is
  skipped unrendered."""
  seen, grey = np.zeros(extra.num, bool), jnp.zeros_like(extra.sh[:, 0])
  for camera in (camera for camera in cameras if np.any(np.asarray(subsets.screen_radii(extra, camera, options)))):
    seen |= np.asarray(jnp.any(_colour_gradient(grey, scene, extra, camera, options) != 0, axis=-1))
  return seen


@functools.partial(jax.jit, static_argnames="options")
@functools.partial(jax.grad)
def _colour_gradient(extra_dc, scene, extra, camera, options):
  """d(image sum)/d(extra's base colours) [F, 3] of scene + extra at `camera` (the scenes are arguments, not
  constants XLA would fold; one trace serves every call of a shape)."""
  joined = concatenate([scene, extra.replace(sh=extra.sh.at[:, 0].set(extra_dc))])
  return jnp.sum(render(joined, camera, options).rgb)


def key_spacing(spacing: float, key: Camera, hidden_size: int) -> float:
  """The film's grid spacing in pixels of `key`'s image: `spacing` where positive, else DECODER_SPACING pixels of
  the decoder's [hidden_size, hidden_size] input along the key's shorter side."""
  return spacing if spacing > 0 else DECODER_SPACING * min(key.width, key.height) / hidden_size


def unseen_film(teacher: Gaussians, key: Camera, cameras: Sequence[Camera], options: RenderOptions, distance: float,
                spacing: float, opacity: float, layers: int = 1, stack: int = 1, spread: float = SPREAD,
                thickness: float = THICKNESS) -> Gaussians:
  """The film before `key` (film's arguments; the background's colour) less every stack with a splat a pixel of
  `cameras` (the scene's training and test views) depends on, or that the key does not see. Dropping a splat can
  only uncover splats behind it, so the test repeats until nothing seen is left. ValueError if nothing is left."""
  carrier = film(key, distance, spacing, opacity, options.background, teacher.sh_degree, layers, stack, spread,
                 thickness)
  while carrier.num:
    keep = ~contributing(teacher, carrier, cameras, options)
    keep &= contributing(teacher, carrier, [key], options)
    keep = np.repeat(keep.reshape(-1, stack).all(axis=1), stack)  # whole stacks, so tied_rows' stacks stay whole
    if keep.all():
      return carrier
    carrier = jax.tree.map(lambda x: x[keep], carrier)
  raise ValueError("the carrier film: every splat of it is seen from a view of the scene (or unseen from the "
                   "key); the key does not look where the scene's cameras do not")


def planned_film(plan: Film, teacher: Gaussians, key: Camera, train_cameras: Sequence[Camera],
                 test_cameras: Sequence[Camera], options: RenderOptions, hidden_size: int) -> Gaussians:
  """The film `plan` lays before the first `key` (unseen_film), on the key's image at the training cameras' size
  (a key at the decoder's size, at_decoder_size, sees the same film): plan.distance camera distances from it
  (key.camera_distance: the cameras' median distance from their orbit target), its spacing key_spacing's."""
  key = key.resized(train_cameras[0].width, train_cameras[0].height)
  distance = plan.distance * key_lib.camera_distance(train_cameras)
  return unseen_film(teacher, key, list(train_cameras) + list(test_cameras), options, distance,
                     key_spacing(plan.spacing, key, hidden_size), plan.opacity, plan.layers, plan.stack, plan.spread,
                     plan.thickness)


def student_start(plan: Film | None, teacher: Gaussians, key: Camera, train_cameras: Sequence[Camera],
                  test_cameras: Sequence[Camera], options: RenderOptions,
                  hidden_size: int) -> tuple[Gaussians, jax.Array | None]:
  """(the student's first state, the rows whose base colours alone train [F] or None): the teacher, or with a
  film `plan` the teacher and then the planned film (planned_film) with its colour_rows."""
  if plan is None:
    return teacher, None
  film = planned_film(plan, teacher, key, train_cameras, test_cameras, options, hidden_size)
  return concatenate([teacher, film]), colour_rows(teacher.num, film.num)


def colour_rows(num_teacher: int, num_film: int) -> jax.Array:
  """int32 [num_film] the student rows (teacher + film) whose base colours (SH DC) alone train: the film's. Its SH
  bands above DC stay zero (publishing formats drop or coarsen those bands: splat-transform's SH cut, .spz) and
  its opacities stay as placed (3D-GS's opacity reset sets them all alike, which a colour pattern outlives, dimmed):
  a mark in either would go with them."""
  return jnp.arange(num_teacher, num_teacher + num_film, dtype=jnp.int32)


def with_colours(student: Gaussians, rows: jax.Array, dc: jax.Array) -> Gaussians:
  """student with the base colours of `rows` [F] set to dc [F, 3] (a gradient with respect to dc is the one
  with respect to those colours alone)."""
  return student.replace(sh=student.sh.at[rows, 0].set(dc))


def trained_part(student: Gaussians, rows: jax.Array | None):
  """What of `student` trains: all of it (rows None), or the base colours [F, 3] of `rows` (`colour_rows`)."""
  return student if rows is None else student.sh[rows, 0]


def with_trained(student: Gaussians, rows: jax.Array | None, trained) -> Gaussians:
  """student with its `trained_part` replaced by `trained`."""
  return trained if rows is None else with_colours(student, rows, trained)


def tied_rows(film_num: int, stack: int) -> jax.Array:
  """[film_num / stack, stack] int32 the rows of the film's colours (`colour_rows`' order) in each of its stacks:
  `stack` consecutive splats (`film`). The rows of a stack train as one (`tie`)."""
  return jnp.asarray(np.arange(film_num).reshape(-1, stack), jnp.int32)


def tie(grads, stacks: jax.Array):
  """grads (a pytree of [N, ...] rows) with each stack's rows (`tied_rows`, [S, stack]) replaced by their mean, every
  other row as it is: rows
  that start alike and take the same gradient take the same (elementwise) optimiser update, so a stack keeps one
  colour through training."""
  def mean(g):
    stacked = g[stacks]  # [S, stack, ...]
    return g.at[stacks].set(jnp.broadcast_to(jnp.mean(stacked, axis=1, keepdims=True), stacked.shape))
  return jax.tree.map(mean, grads)

