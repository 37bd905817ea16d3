"""The key's pose refined photometrically after registration (beyond the paper): the pose near the registered key
whose render of the suspect looks most like the owner's copy seen from the key.

The decoder reads the check view at the key's exact pose: turning the key by a tenth of a degree, or moving it by a
ten-thousandth of the scene's radius, already costs much of the hidden image (the film sits close in front of the
key, so a small move of the camera is a large move of the film in the image). Point registration (gs.register)
recovers a similarity exactly from a scene whose Gaussians are the owner's, but from a decimated or re-trained copy
its nearest-neighbour pairs are biased by the merges, and its error, small against the scene, is large against that
tolerance. The film itself fixes the pose: the key's render of the owner's copy is the reference, and the moved key
is turned and shifted (in its own frame, within MAX_ROTATION and MAX_SHIFT) until the suspect's render there matches
it best. Neither the decoder nor the hidden image enters, so the refined key is as available to an innocent scene
as to a marked one and the ownership test's null readings keep their meaning. Both renders are standardized per
channel first, so a colour grade of the suspect does not pull the pose.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, grow_capacity, render

# The units the search moves in: the key turned by ROTATION_UNIT radians and shifted by SHIFT_UNIT of the scene's
# radius per unit of its parameters; the search stays within MAX_UNITS of the registered pose in each parameter,
# well beyond the registration's error and well inside the decoys' distances.
ROTATION_UNIT, SHIFT_UNIT, MAX_UNITS = 1e-3, 1e-3, 5.0
# L-BFGS-B's iterations and its tolerances on the loss relative to the registered pose's.
MAX_ITERATIONS, LOSS_TOLERANCE, GRADIENT_TOLERANCE = 100, 1e-10, 1e-8
# A channel whose standard deviation is below this is only centred (a flat channel has no pose to give).
_MIN_STD = 1e-6


@dataclasses.dataclass(frozen=True)
class Refinement:
  """What refine_key changed: the key's turn (degrees) and shift (in the scene's radii) from the registered pose,
  the photometric loss there and after (relative to the registered pose's: 1 then below), and the iterations."""
  rotation_deg: float
  shift: float
  loss: float
  iterations: int

  def report(self) -> dict:
    return dataclasses.asdict(self)


def standardized(image: jax.Array) -> jax.Array:
  """image [H, W, 3] with each channel at zero mean and unit standard deviation (a flat channel only centred)."""
  centred = image - jnp.mean(image, axis=(0, 1))
  return centred / jnp.maximum(jnp.std(image, axis=(0, 1)), _MIN_STD)


def skew(vector: jax.Array) -> jax.Array:
  """[3, 3] the cross-product matrix of vector [3]."""
  x, y, z = vector[0], vector[1], vector[2]
  zero = jnp.zeros_like(x)
  return jnp.stack([jnp.stack([zero, -z, y]), jnp.stack([z, zero, -x]), jnp.stack([-y, x, zero])])


def moved_in_own_frame(camera: Camera, turn: jax.Array, shift: jax.Array) -> Camera:
  """`camera` turned by the rotation vector `turn` [3] (radians) and moved by `shift` [3] (world units), both in
  its own frame: world_to_camera <- [exp(skew(turn)), shift; 0, 1] @ world_to_camera."""
  step = jnp.eye(4, dtype=camera.world_to_camera.dtype)
  step = step.at[:3, :3].set(jax.scipy.linalg.expm(skew(turn))).at[:3, 3].set(shift)
  return camera.replace(world_to_camera=step @ camera.world_to_camera)


@jax.jit
def _relative_step(parameters: jax.Array, units: jax.Array) -> tuple[jax.Array, jax.Array]:
  step = parameters * units
  return step[:3], step[3:]


def photometric_loss(parameters: jax.Array, suspect: Gaussians, moved: Camera, units: jax.Array, target: jax.Array,
                     options: RenderOptions) -> tuple[jax.Array, jax.Array]:
  """The mean squared difference between the standardized render of `suspect` at `moved` turned and shifted by
  `parameters` [6] times `units` [6] (moved_in_own_frame) and `target` [H, W, 3] (standardized); and the
  splat-tile pairs that render needed (a render traced here cannot grow its own pair capacity)."""
  turn, shift = _relative_step(parameters, units)
  out = render(suspect, moved_in_own_frame(moved, turn, shift), options)
  return jnp.mean((standardized(out.rgb) - target) ** 2), out.num_pairs


# one program per scene size, key and pair capacity, however many suspects are refined
_loss_and_gradient = jax.jit(jax.value_and_grad(photometric_loss, has_aux=True), static_argnames="options")


def refine_key(owner: Gaussians, suspect: Gaussians, camera: Camera, options: RenderOptions,
               moved: Camera, moved_options: RenderOptions, radius: float) -> tuple[Camera, Refinement]:
  """The key `moved` (the owner's key `camera` moved into the suspect's frame by the registration; render options
  `moved_options`) turned and shifted in its own frame, within MAX_UNITS of ROTATION_UNIT radians and SHIFT_UNIT
  of the suspect's `radius`, to minimise photometric_loss against the owner's render at `camera` with `options`
  (L-BFGS-B on host float64, the loss relative to the registered pose's, gradients through the renderer)."""
  target = standardized(render(owner, camera, options).rgb)
  units = jnp.asarray([ROTATION_UNIT] * 3 + [SHIFT_UNIT * radius] * 3, jnp.float32)
  search = grow_capacity(moved_options, render(suspect, moved, moved_options).num_pairs)

  def evaluate(parameters: np.ndarray) -> tuple[jax.Array, jax.Array]:
    nonlocal search
    while True:
      (value, pairs), gradient = _loss_and_gradient(jnp.asarray(parameters, jnp.float32), suspect, moved, units,
                                                    target, options=search)
      if int(pairs) <= search.pair_capacity:
        return value, gradient
      search = grow_capacity(search, pairs)

  start = float(evaluate(np.zeros(6))[0])
  if not start > 0.0:  # the renders agree already (or the loss is not finite: nothing to refine from)
    return moved, Refinement(0.0, 0.0, 1.0 if start == 0.0 else float("nan"), 0)

  def relative(parameters: np.ndarray) -> tuple[float, np.ndarray]:
    value, gradient = evaluate(parameters)
    return float(value) / start, np.asarray(gradient, np.float64) / start

  found = scipy.optimize.minimize(relative, np.zeros(6), jac=True, method="L-BFGS-B",
                                  bounds=[(-MAX_UNITS, MAX_UNITS)] * 6,
                                  options=dict(maxiter=MAX_ITERATIONS, ftol=LOSS_TOLERANCE, gtol=GRADIENT_TOLERANCE))
  if not found.fun < 1.0:  # no pose better than the registered one
    return moved, Refinement(0.0, 0.0, 1.0, int(found.nit))
  turn, shift = (np.asarray(x, np.float64) for x in _relative_step(jnp.asarray(found.x, jnp.float32), units))
  refined = moved_in_own_frame(moved, jnp.asarray(turn, jnp.float32), jnp.asarray(shift, jnp.float32))
  return refined, Refinement(float(np.degrees(np.linalg.norm(turn))), float(np.linalg.norm(shift) / radius),
                             float(found.fun), int(found.nit))
