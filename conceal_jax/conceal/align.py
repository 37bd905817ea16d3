"""Re-alignment of a suspect scene onto the owner's copy of the marked scene (reveal.owner), before the key reads it.

A shared scene may have been turned, moved, resized or reordered on import, and its colours graded (brighter,
darker, more or less contrast), by an editor or a converter. Its frame: the suspect is registered onto the owner's
copy (gs.register: the similarity owner -> suspect from the Gaussians alone), the key camera is moved with that
similarity and its pose refined on the film (key_refine), so that it sees the suspect as the key saw the marked
scene, reading only the SH bands the owner's copy shows there (key_options: a converter that quantizes zero higher
bands, as .compressed.ply's 8 bits do, returns them as a small tint that depends on the view's direction in the
scene's frame). Its tone: the suspect's renders are mapped channel by channel onto the owner's by the gain and
offset that fit them best (fit_tone), within what a colour grade does (MAX_TONE_GAIN, MAX_TONE_OFFSET), in two ways:
at the key alone (tone_at_key), which restores the film's own statistics where thinning it faded it, and over the
key's view and views of the whole scene at SH degree 0 (scene_tone), which a grade of the scene fits and thinning
does not pull; where the key sees a film of nearly one colour, either can be the one that reads it (the other
mistakes a change of the film for a grade), so verify reads both and the render as it is, and decides on the best
(robust.ownership). Every render the decoder then reads of that suspect, the key's and the null views', passes
through the same map (Tone.apply).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import key_refine
from conceal_jax.gs import register as register_lib, similarity as similarity_lib
from conceal_jax.splat.camera import Camera, look_at
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render, sh_degree

# The tone map's bounds: a gain in [1 / MAX_TONE_GAIN, MAX_TONE_GAIN] and an offset within +-MAX_TONE_OFFSET per
# channel, beyond any brightness or contrast change that leaves a scene worth sharing.
MAX_TONE_GAIN, MAX_TONE_OFFSET = 2.0, 0.5
# Pixels within this of 0 or 1 in either render are left out of the fit (a clipped value says nothing of the map),
# and a channel with fewer than MIN_TONE_PIXELS others, or of no spread, keeps gain 1 and offset 0.
TONE_CLIP_MARGIN, MIN_TONE_PIXELS = 1e-3, 16
# The owner's render at the key at a lower SH degree counts as the same within this (far below an 8-bit level).
KEY_SH_TOLERANCE = 1e-4
# The views of the whole scene the tone is fitted over besides the key's: TONE_VIEWS cameras with the key's
# intrinsics spread over a sphere around the Gaussians' median centre, at TONE_VIEW_DISTANCE times the distance
# within which 80% of the centres lie, looking at it.
TONE_VIEWS, TONE_VIEW_DISTANCE = 6, 2.5


@dataclasses.dataclass(frozen=True)
class Tone:
  """A per-channel colour map x -> gain * x + offset (gain, offset [3]) of renders [..., 3]."""
  gain: np.ndarray
  offset: np.ndarray

  @classmethod
  def identity(cls) -> "Tone":
    return cls(np.ones(3), np.zeros(3))

  def apply(self, renders):
    """[..., 3] renders mapped channel by channel (not clipped: the decoder's reading clips where it reads so)."""
    return renders * jnp.asarray(self.gain, jnp.float32) + jnp.asarray(self.offset, jnp.float32)

  def report(self) -> dict:
    return dict(gain=[float(g) for g in self.gain], offset=[float(o) for o in self.offset])


def fit_tone(image: np.ndarray, reference: np.ndarray) -> Tone:
  """The Tone taking `image` [H, W, 3] closest to `reference` [H, W, 3] in least squares, channel by channel,
  over the pixels clipped in neither (TONE_CLIP_MARGIN); the gain bounded by MAX_TONE_GAIN, the offset then the
  best for it, bounded by MAX_TONE_OFFSET. A channel with too few such pixels or no spread keeps the identity."""
  image, reference = np.asarray(image, np.float64), np.asarray(reference, np.float64)
  if image.shape != reference.shape or image.shape[-1] != 3:
    raise ValueError(f"a tone is fitted between two renders of one shape [H, W, 3], got {image.shape} and "
                     f"{reference.shape}")
  gain, offset = np.ones(3), np.zeros(3)
  inside = lambda v: (v > TONE_CLIP_MARGIN) & (v < 1.0 - TONE_CLIP_MARGIN)
  for c in range(3):
    x, y = image[..., c].ravel(), reference[..., c].ravel()
    used = inside(x) & inside(y)
    x, y = x[used], y[used]
    if x.size < MIN_TONE_PIXELS or x.var() <= 1e-12:
      continue
    gain[c] = np.clip(np.mean((x - x.mean()) * (y - y.mean())) / x.var(), 1.0 / MAX_TONE_GAIN, MAX_TONE_GAIN)
    offset[c] = np.clip(y.mean() - gain[c] * x.mean(), -MAX_TONE_OFFSET, MAX_TONE_OFFSET)
  return Tone(gain, offset)


def tone_at_key(owner: Gaussians, suspect: Gaussians, camera: Camera, options: RenderOptions,
                suspect_camera: Camera, suspect_options: RenderOptions) -> Tone:
  """fit_tone of the suspect's render at its (moved) key onto the owner's copy's render at the key."""
  return fit_tone(np.asarray(render(suspect, suspect_camera, suspect_options).rgb),
                  np.asarray(render(owner, camera, options).rgb))


def survey_cameras(gaussians: Gaussians, camera: Camera, count: int = TONE_VIEWS) -> list[Camera]:
  """`count` cameras with `camera`'s intrinsics looking at the median centre of `gaussians` from directions
  spread over the sphere (similarity.fibonacci_sphere), at TONE_VIEW_DISTANCE times the 80th percentile of the
  centres' distances from it: views of the whole scene."""
  means = np.asarray(gaussians.means, np.float64)
  centre = np.median(means, axis=0)
  distance = TONE_VIEW_DISTANCE * max(float(np.quantile(np.linalg.norm(means - centre, axis=1), 0.8)), 1e-6)
  return [camera.replace(world_to_camera=jnp.asarray(look_at(centre + distance * d, centre), jnp.float32))
          for d in similarity_lib.fibonacci_sphere(count)]


def scene_tone(owner: Gaussians, suspect: Gaussians, camera: Camera, options: RenderOptions,
               similarity: similarity_lib.Similarity) -> Tone:
  """fit_tone of the suspect's renders onto the owner's copy's over the key `camera` and survey_cameras of the
  owner, each moved into the suspect's frame by `similarity` (owner -> suspect, moved_key), all at SH degree 0: a
  grade maps the base colours, and the higher bands are what converters quantize coarsest (.compressed.ply's 8
  bits return a scene's every band tinted), which would enter the fit as a grade."""
  options = dataclasses.replace(options, sh_degree=0)
  cameras = [camera] + survey_cameras(owner, camera)
  moved = [moved_key(c, options, similarity) for c in cameras]
  stacked = lambda scene, views: np.concatenate([np.asarray(render(scene, c, o).rgb) for c, o in views], axis=0)
  return fit_tone(stacked(suspect, moved), stacked(owner, [(c, options) for c in cameras]))


def moved_key(camera: Camera, options: RenderOptions,
              similarity: similarity_lib.Similarity) -> tuple[Camera, RenderOptions]:
  """The key camera and render options that see the scene moved by `similarity` as `camera` saw the
  original: the camera transformed with it, and the near plane (an absolute camera-space depth, which the
  scale multiplies) scaled by its scale, so that the same splats are culled and the render is the same (the near
  plane is a static render option: each value compiles the render anew)."""
  # rounded to 6 significant digits: a scale of 1 found to float precision keeps the compiled render
  return (similarity_lib.transform_camera(camera, similarity),
          dataclasses.replace(options, near=float(f"{float(options.near) * similarity.scale:.6g}")))


@dataclasses.dataclass(frozen=True)
class Realignment:
  """A suspect scene re-aligned onto the owner's copy (realign): the key `camera` and render `options` moved into
  its frame (reading the key's SH degree), the `registration` (similarity owner -> suspect, residual, matched
  fraction), the key's `refinement` from the registered pose (key_refine) and the tone maps by name, `tones`
  ("toned": tone_at_key; "scene_toned": scene_tone)."""
  camera: Camera
  options: RenderOptions
  registration: register_lib.Registration
  refinement: key_refine.Refinement
  tones: dict[str, Tone]

  def report(self) -> dict:
    """The transform found with its fit (registration_report) and the key's refinement (key_refine.Refinement)."""
    return dict(registration_report(self.registration), refinement=self.refinement.report())


def realign(owner: Gaussians, suspect: Gaussians, camera: Camera, options: RenderOptions, seed: int = 0,
            registration: register_lib.Registration | None = None) -> Realignment:
  """The key moved into the suspect scene's frame: registers `suspect` onto the owner's copy `owner` (the scene
  the key was made for; any order, size or count of Gaussians in either), moves `camera` and `options` at the SH
  degree key_options finds with the similarity found (moved_key), refines the moved key's pose on the owner's render
  at the key (key_refine.refine_key, the suspect's renders through their fit_tone onto it) and fits the suspect's
  tone maps onto the owner's (tone_at_key at the refined key, scene_tone). `registration`: these two scenes'
  registration where already found (a suspect read at several keys registers once). ValueError from register for
  scenes too small or not finite."""
  owner, suspect = jax.tree.map(jnp.asarray, owner), jax.tree.map(jnp.asarray, suspect)
  if registration is None:
    registration = register_lib.register(owner, suspect, seed=seed)
  options = key_options(owner, [camera], options)
  moved, moved_options = moved_key(camera, options, registration.similarity)
  moved, refinement = key_refine.refine_key(owner, suspect, camera, options, moved, moved_options,
                                            registration.owner_radius * registration.similarity.scale, fit_tone)
  tones = dict(toned=tone_at_key(owner, suspect, camera, options, moved, moved_options),
               scene_toned=scene_tone(owner, suspect, camera, options, registration.similarity))
  return Realignment(moved, moved_options, registration, refinement, tones)


def key_options(owner: Gaussians, cameras: Sequence[Camera], options: RenderOptions) -> RenderOptions:
  """`options` reading the lowest SH degree at which the owner's copy renders at every key of `cameras` as with
  `options` (within KEY_SH_TOLERANCE; `options` itself where none lower does): where the marked scene shows no
  view-dependent colour at its keys (the carrier film's), higher bands in a suspect can only be what a converter
  or an editor added."""
  top = sh_degree(owner, options)
  full = [np.asarray(render(owner, camera, options).rgb) for camera in cameras]
  for degree in range(top):
    lower = dataclasses.replace(options, sh_degree=degree)
    if all(np.max(np.abs(np.asarray(render(owner, camera, lower).rgb) - f)) <= KEY_SH_TOLERANCE
           for camera, f in zip(cameras, full)):
      return lower
  return options


def similarity_report(similarity: similarity_lib.Similarity) -> dict:
  """A similarity as reveal.json reports it: rotation [3, 3] and as an axis (unit [3]) and angle in degrees
  (axis +z for no turn), translation [3], scale."""
  quat = similarity_lib.matrix_to_quaternion(similarity.rotation)  # w >= 0: angle in [0, 180]
  sin_half = float(np.linalg.norm(quat[1:]))
  axis = quat[1:] / sin_half if sin_half > 1e-12 else np.array([0.0, 0.0, 1.0])
  return dict(rotation=similarity.rotation.tolist(), axis=axis.tolist(),
              angle_deg=float(np.degrees(2.0 * np.arctan2(sin_half, quat[0]))),
              translation=similarity.translation.tolist(), scale=similarity.scale)


def registration_report(registration: register_lib.Registration) -> dict:
  """The transform found (similarity_report) with its fit: residual (trimmed RMS nearest-neighbour distance
  / owner radius), matched_fraction and owner_radius (gs.register.Registration)."""
  return dict(similarity_report(registration.similarity), residual=float(registration.residual),
              matched_fraction=float(registration.matched_fraction), owner_radius=float(registration.owner_radius))
