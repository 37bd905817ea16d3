"""The key's pose refined photometrically after registration (beyond the paper): the pose near the registered key
whose render of the suspect looks most like the owner's copy seen from the key.

The decoder reads the check view at the key's exact pose: the key turned with the scene by a tenth of a degree about
its centre loses most of the hidden image, and moved by a two-thousandth of the scene's radius a few hundredths of
its SSIM (the film sits close in front of the key, so a small move of the camera is a large move of the film in the
image). Point registration (gs.register) recovers a similarity exactly from a scene whose Gaussians are the owner's,
but from a decimated or re-trained copy its nearest-neighbour pairs are biased by the merges, and its error, small
against the scene, is large against that tolerance. The film itself fixes the pose: the key's render of the owner's
copy is the reference, and the moved key is turned and shifted (in its own frame, within MAX_UNITS of its units)
until the suspect's render there matches it best. Neither the decoder nor the hidden image enters, so the refined
key is as available to an innocent scene as to a marked one and the ownership test's null readings keep their
meaning. The suspect's renders pass through a colour map (align.fit_tone's) held fixed while the pose is searched,
so that a colour grade of the suspect does not pull the pose, and fitted again where the search ends; a map fitted
anew at every pose of the search (or renders standardized per image) would trade pose for tone.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

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
# Renders whose mean squared difference is below this already agree (a fortieth of an 8-bit level, root mean
# square): a suspect that is the owner's Gaussians moved is registered exactly, and nothing is searched.
AGREEMENT = 1e-8
# Rounds of the search, each after fitting the suspect's colour map anew at the pose the one before found: a map
# fitted on misaligned renders is too flat (its gain regresses towards 0) and pulls the pose.
TONE_ROUNDS = 2


@dataclasses.dataclass(frozen=True)
class Refinement:
  """What refine_key changed: the key's turn (degrees) and shift (in the scene's radii) from the registered pose,
  the photometric loss at the pose found relative to the registered pose's (through the last tone; 1: kept, as where
  the renders already agree), and the search's iterations."""
  rotation_deg: float
  shift: float
  loss: float
  iterations: int

  def report(self) -> dict:
    return dataclasses.asdict(self)


# The registered key kept as it was.
KEPT = Refinement(0.0, 0.0, 1.0, 0)


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


def photometric_loss(parameters: jax.Array, suspect: Gaussians, moved: Camera, units: jax.Array, tone: jax.Array,
                     target: jax.Array, options: RenderOptions) -> tuple[jax.Array, jax.Array]:
  """The mean squared difference between the render of `suspect` at `moved` turned and shifted by `parameters` [6]
  times `units` [6] (moved_in_own_frame), mapped by `tone` [2, 3] (gain, offset per channel), and `target`
  [H, W, 3]; and the splat-tile pairs that render needed (a render traced here cannot grow its own capacity)."""
  turn, shift = _relative_step(parameters, units)
  out = render(suspect, moved_in_own_frame(moved, turn, shift), options)
  return jnp.mean((out.rgb * tone[0] + tone[1] - target) ** 2), out.num_pairs


# one program per scene size, key and pair capacity, however many suspects are refined
_loss_and_gradient = jax.jit(jax.value_and_grad(photometric_loss, has_aux=True), static_argnames="options")


def refine_key(owner: Gaussians, suspect: Gaussians, camera: Camera, options: RenderOptions,
               moved: Camera, moved_options: RenderOptions, radius: float,
               fit_tone: Callable[[jax.Array, jax.Array], Any] | None = None) -> tuple[Camera, Refinement]:
  """The key `moved` (the owner's key `camera` moved into the suspect's frame by the registration; render options
  `moved_options`) turned and shifted in its own frame, within MAX_UNITS of ROTATION_UNIT radians and SHIFT_UNIT
  of the suspect's `radius`, to minimise photometric_loss against the owner's render at `camera` with `options`
  (L-BFGS-B on host float64, the loss relative to the registered pose's, gradients through the renderer). The
  suspect's renders are mapped by the gain [3] and offset [3] of `fit_tone(its render, the owner's)` (align.fit_tone;
  the identity if None) at the registered pose, then TONE_ROUNDS - 1 times again at the pose found, each round searching
  on from the last. The key as it was (KEPT) where the renders already agree there."""
  target = render(owner, camera, options).rgb
  units = jnp.asarray([ROTATION_UNIT] * 3 + [SHIFT_UNIT * radius] * 3, jnp.float32)
  registered = render(suspect, moved, moved_options)
  search = grow_capacity(moved_options, registered.num_pairs)
  at = lambda parameters: moved_in_own_frame(moved, *_relative_step(jnp.asarray(parameters, jnp.float32), units))

  def evaluate(parameters: np.ndarray, tone: jax.Array) -> tuple[jax.Array, jax.Array]:
    nonlocal search
    while True:
      (value, pairs), gradient = _loss_and_gradient(jnp.asarray(parameters, jnp.float32), suspect, moved, units,
                                                    tone, target, options=search)
      if int(pairs) <= search.pair_capacity:
        return value, gradient
      search = grow_capacity(search, pairs)

  parameters, loss, iterations = np.zeros(6), 1.0, 0
  for round_ in range(TONE_ROUNDS if fit_tone is not None else 1):
    image = registered.rgb if round_ == 0 else render(suspect, at(parameters), search).rgb
    fitted = fit_tone(image, target) if fit_tone is not None else None
    tone = jnp.asarray((fitted.gain, fitted.offset) if fitted is not None else ((1.0,) * 3, (0.0,) * 3), jnp.float32)
    agreement = float(jnp.mean((image * tone[0] + tone[1] - target) ** 2))
    start = float(evaluate(np.zeros(6), tone)[0]) if agreement > AGREEMENT else 0.0
    if not start > 0.0:  # the renders agree already (or do not compare: not finite): nothing to search
      break

    def relative(x: np.ndarray, tone=tone, start=start) -> tuple[float, np.ndarray]:
      value, gradient = evaluate(x, tone)
      return float(value) / start, np.asarray(gradient, np.float64) / start

    found = scipy.optimize.minimize(relative, parameters, jac=True, method="L-BFGS-B",
                                    bounds=[(-MAX_UNITS, MAX_UNITS)] * 6,
                                    options=dict(maxiter=MAX_ITERATIONS, ftol=LOSS_TOLERANCE, gtol=GRADIENT_TOLERANCE))
    parameters, loss, iterations = np.asarray(found.x), float(found.fun), iterations + int(found.nit)
  if not loss < 1.0:  # no pose better than the registered one
    return moved, dataclasses.replace(KEPT, iterations=iterations)
  turn, shift = (np.asarray(x, np.float64) for x in _relative_step(jnp.asarray(parameters, jnp.float32), units))
  return at(parameters), Refinement(float(np.degrees(np.linalg.norm(turn))), float(np.linalg.norm(shift) / radius),
                                    loss, iterations)
