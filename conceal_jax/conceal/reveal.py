"""Revealing the hidden image: render the check view, resize it to the decoder size, decode.

`--config.mode=reveal` takes any standard 3D-GS .ply, a decoder file and a key.json, writes
revealed.png and, given a reference hidden image, its PSNR / SSIM (reveal.json). The render settings
are read from the key, so the check view is rendered exactly as during concealment.

A shared scene may have been turned, moved, resized or reordered on import (or re-saved by a converter that
does so), and its colours graded. Given the owner's own copy of the marked scene (reveal.owner), the reveal first
re-aligns the suspect onto it (conceal.align: the key moved into the suspect's frame, its renders mapped onto the
owner's tone) and renders there: the check view the key names, seen in the suspect's frame and tone.
reveal.json then reports the transform, the tone maps and how well they fit.
"""
from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any

from absl import logging
import flax.serialization
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.conceal import align, hidden as hidden_lib, key as key_lib, message as message_lib, unet
from conceal_jax.core import fileio, settings
from conceal_jax.data import ply
from conceal_jax.gs import metrics
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render

REVEAL_FILE = "reveal.json"
# Below this fraction of the suspect's Gaussians matched to the owner's copy after registration, the reveal logs
# that the transform found is doubtful (another scene, or one changed beyond re-alignment).
MIN_MATCHED_FRACTION = 0.5


@dataclasses.dataclass(frozen=True)
class Reading:
  """How a decoder reads a render, beyond the paper (both saved in key.json): `input_norm` (unet.UNet,
  conceal.decoder.input_norm) and `clip` (conceal.decoder.clip_input): the render clipped to [0, 1] first,
  as an image file holds it, so that no hidden signal can live in values outside it (a lego student trained
  without it hid its image in whites above 1, which any saved or attacked image loses:
  experiments/results/conceal_options.md)."""
  input_norm: str = "none"
  clip: bool = False
  reference: bool = False  # the decoder reads its reference image beside the render (unet.UNet.reference_size)

  @classmethod
  def from_key(cls, info: dict) -> "Reading":
    """The reading a key.json records; keys written before these options: the paper's. A key of a retired
    keyed decoder (one that read sign channels or a sign field: `RETIRED_READINGS`) is refused by name."""
    retired = {name: info[name] for name in RETIRED_READINGS if info.get(name, 0)}
    if retired:
      raise ValueError(f"the key was made with a retired decoder reading ({retired}); this version of "
                       "conceal_jax reveals only the paper's decoder with input_norm and clip_input")
    return cls(str(info.get("decoder_input_norm", "none")), bool(info.get("decoder_clip_input", False)),
               bool(info.get("decoder_reference", False)))

  def key_fields(self) -> dict:
    return dict(decoder_input_norm=self.input_norm, decoder_clip_input=self.clip, decoder_reference=self.reference)


# Key fields of decoder readings that were tried and retired (experiments/results/film_designs.md: the keyed and
# the modulated decoder); a key that sets one cannot be revealed by today's U-Net.
RETIRED_READINGS = ("decoder_pattern", "decoder_modulation")

PAPER_READING = Reading()


def resize_for_decoder(image: jax.Array, size: int, clip: bool = False) -> jax.Array:
  """[..., H, W, 3] render -> [..., size, size, 3] decoder input (antialiased bilinear, as the released
  code's resize to 64x64); `clip`: clipped to [0, 1] first (Reading.clip)."""
  image = jnp.clip(image, 0.0, 1.0) if clip else image
  return jax.image.resize(image, image.shape[:-3] + (size, size, image.shape[-1]), "linear")


def decode(decoder_params, base_channels: int, images: jax.Array, reading: Reading = PAPER_READING) -> jax.Array:
  """F: [..., S, S, C] -> [..., S, S, 3] with the U-Net decoder (C: the input channels its params were made
  for, 3 for a render), reading the images as `reading` says (its input_norm; its clip is resize_for_decoder's)."""
  if ("reference" in decoder_params) != reading.reference:
    raise ValueError("the key's reading and the decoder disagree on a reference image (key.json decoder_reference "
                     f"{reading.reference}): the decoder file belongs to another run")
  batch = images[None] if images.ndim == 3 else images
  model = unet.UNet(base_channels, reading.input_norm, decoder_params["reference"].shape[0] if reading.reference else 0)
  out = model.apply({"params": decoder_params}, batch)
  return out[0] if images.ndim == 3 else out


@functools.partial(jax.jit, static_argnames=("base_channels", "size", "reading"))
def reveal_renders(decoder_params, renders: jax.Array, base_channels: int, size: int,
                   reading: Reading = PAPER_READING) -> jax.Array:
  """[..., H, W, 3] renders -> [..., size, size, 3] revealed images clipped to [0, 1]; decoder_params
  None: the resized render itself (the "without decoder" ablation)."""
  small = resize_for_decoder(renders, size, reading.clip)
  out = small if decoder_params is None else decode(decoder_params, base_channels, small, reading)
  return jnp.clip(out, 0.0, 1.0)


def reveal_image(gaussians: Gaussians, camera: Camera, options: RenderOptions, decoder_params,
                 base_channels: int, size: int, reading: Reading = PAPER_READING) -> jax.Array:
  """[size, size, 3] revealed image at `camera`."""
  return reveal_renders(decoder_params, render(gaussians, camera, options).rgb, base_channels, size, reading)


def decoder_reveal(decoder_params, base_channels: int, size: int, reading: Reading = PAPER_READING):
  """The reveal function of a ConcealGS decoder: renders [V, H, W, 3] -> revealed images [V, size, size, 3]
  (decoder_params None: the resized renders). Scoring code takes such a function, so that a baseline with
  another way of reading the image out of a render is scored the same way."""
  return functools.partial(reveal_renders, decoder_params, base_channels=base_channels, size=size,
                           reading=reading)


def save_decoder(path: str, params) -> None:
  fileio.write_bytes(path, flax.serialization.msgpack_serialize(
      jax.tree.map(np.asarray, flax.serialization.to_state_dict(params))))


def load_decoder(path: str):
  """Decoder params from a file written by save_decoder; ValueError naming the file otherwise."""
  try:
    with open(path, "rb") as f:
      params = flax.serialization.msgpack_restore(f.read())
  except (OSError, ValueError, TypeError) as error:
    raise ValueError(f"cannot read decoder {path}: {error}") from error
  if not isinstance(params, dict) or "out" not in params:
    raise ValueError(f"{path} does not hold U-Net decoder parameters")
  return jax.tree.map(jnp.asarray, params)


def options_from_key(info: dict) -> RenderOptions:
  """The render options saved in a key (fields this version does not know are ignored)."""
  return settings.from_section(RenderOptions, info["render_options"])


def validate(config: ml_collections.ConfigDict) -> None:
  """The reveal job needs a scene and a key (the decoder is checked against the key when it is read)."""
  for name in ("ply", "key"):
    if not config.reveal[name]:
      raise ValueError(f"reveal.{name} is required")
  settings.check_count("reveal.key_number", config.reveal.key_number, minimum=0)


def toned(reveal_fn, tone: align.Tone):
  """reveal_fn reading renders [V, H, W, 3] after `tone` (align.Tone.apply)."""
  return lambda renders: reveal_fn(tone.apply(renders))


def readings(reveal_fn, tones: dict[str, align.Tone] | None = None) -> dict[str, Any]:
  """The ways a suspect's renders are read, by name: after each tone map of `tones` (re-alignment in tone, by its
  name: align.Realignment.tones) reveal_fn after the map, then "as_rendered", since a tone fitted to a blurred
  render also sharpens what the decoder reads; without tone maps, "as_rendered" alone."""
  return {**{name: toned(reveal_fn, tone) for name, tone in (tones or {}).items()}, "as_rendered": reveal_fn}


@dataclasses.dataclass(frozen=True)
class KeyedScene:
  """A suspect scene with what reveals it (load_keyed_scene): the Gaussians, the key camera and render options
  (moved into the scene's frame when re-aligned), `decoder_fn` (decoder_reveal: renders [V, H, W, 3] -> revealed
  [V, S, S, 3]), the alignment report or None, the tone maps onto the owner's copy by name
  (align.Realignment.tones) or None, and the registration onto the owner's copy or None."""
  gaussians: Gaussians
  camera: Camera
  options: RenderOptions
  decoder_fn: Any
  alignment: dict | None
  tones: dict[str, align.Tone] | None = None
  registration: align.register_lib.Registration | None = None

  @property
  def readings(self) -> dict[str, Any]:
    return readings(self.decoder_fn, self.tones)

  @property
  def reveal_fn(self):
    """The first of the readings: after the key's tone map where there is one."""
    return next(iter(self.readings.values()))

  def reveal_at(self, cameras: list[Camera]) -> np.ndarray:
    """[V, S, S, 3] images revealed from the scene's renders at `cameras` (same intrinsics as the key)."""
    renders = jnp.stack([render(self.gaussians, camera, self.options).rgb for camera in cameras])
    return np.asarray(self.reveal_fn(renders))


def load_keyed_scene(r: ml_collections.ConfigDict,
                     registration: align.register_lib.Registration | None = None) -> KeyedScene:
  """The scene r.ply, key number r.key_number of the key file r.key (0: its check view, k: its k-th extra key)
  and the decoder r.decoder (a `reveal` config section). With r.owner set, the suspect is re-aligned onto the
  owner's copy r.owner (align.realign; `registration`: r.ply's onto r.owner where already found, another key's
  KeyedScene.registration) and the alignment report is align.Realignment.report's with the tone maps."""
  camera, info = key_lib.load_key(r.key, r.key_number)
  if info.get("uses_decoder", True) and not r.decoder:
    raise ValueError("reveal.decoder is required: this key was made with a decoder")
  decoder = load_decoder(r.decoder) if info.get("uses_decoder", True) else None
  suspect, options = ply.load_ply(r.ply), options_from_key(info)
  reveal_fn = decoder_reveal(decoder, int(info.get("decoder_width", 0)), int(info["hidden_size"]),
                             Reading.from_key(info))
  alignment = tones = None
  if r.get("owner", ""):
    owner = ply.load_ply(r.owner)
    realigned = align.realign(owner, suspect, camera, options, registration=registration)
    camera, options, registration, tones = realigned.camera, realigned.options, realigned.registration, realigned.tones
    alignment = dict(owner=r.owner, **realigned.report(), tones={name: tone.report() for name, tone in tones.items()})
    if registration.matched_fraction < MIN_MATCHED_FRACTION:
      logging.warning("re-alignment of %s onto %s matched only %.0f%% of its Gaussians (residual %.2g radii): the "
                      "transform found is doubtful", r.ply, r.owner, 100 * registration.matched_fraction,
                      registration.residual)
  return KeyedScene(jax.tree.map(jnp.asarray, suspect), camera, options, reveal_fn, alignment, tones,
                    registration if alignment is not None else None)


def reveal_with_alignment(r: ml_collections.ConfigDict) -> tuple[np.ndarray, dict | None]:
  """([S, S, 3] image revealed at the key of load_keyed_scene(r), S the key's hidden size; the alignment report
  or None)."""
  scene = load_keyed_scene(r)
  return scene.reveal_at([scene.camera])[0], scene.alignment


def reveal_from_files(r: ml_collections.ConfigDict) -> np.ndarray:
  """The [S, S, 3] image of reveal_with_alignment (re-aligned when r.owner is set)."""
  return reveal_with_alignment(r)[0]


def reveal(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """The reveal job: writes revealed.png and reveal.json (similarity to config.reveal.hidden if set; the
  alignment found when config.reveal.owner is set; with a key of message mode, the message read back)."""
  validate(config)
  r = config.reveal
  revealed, alignment = reveal_with_alignment(r)
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed)
  result = dict(ply=r.ply, key=r.key, decoder=r.decoder)
  if alignment is not None:
    result["alignment"] = alignment
  if r.hidden:
    reference = hidden_lib.load_hidden_image(r.hidden, revealed.shape[0])
    result.update(psnr=float(metrics.psnr(revealed, reference)), ssim=float(metrics.ssim(revealed, reference)))
  hidden_message = message_lib.message_of_key(key_lib.load_key(r.key, r.key_number)[1])
  if hidden_message is not None:
    result["message"] = message_lib.read_message(revealed, hidden_message)
  fileio.write_json(os.path.join(workdir, REVEAL_FILE), result)
  return result
