"""How well the hidden image survives: attacks on the check render, on the shared scene, and a check pose
that is only approximately known.

Everything is scored as the reveal job scores it: the check view rendered with the key's options,
resized to the decoder size, decoded, clipped, and compared with the hidden image I (PSNR, SSIM).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import align, reveal, scoring
from conceal_jax.gs import evaluate, train
from conceal_jax.robust import image_attacks, model_attacks, ownership, phase_statistic
from conceal_jax.splat import gaussians as gaussians_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render


@dataclasses.dataclass(frozen=True)
class Owner:
  """What the owner keeps: decoder params (None: the no-decoder ablation) of `decoder_width`, the hidden
  image I [S, S, 3], the check camera and the render options of the key; how the decoder reads a render as
  the key says (reveal.Reading.from_key)."""
  decoder: Any
  decoder_width: int
  hidden: np.ndarray
  check_camera: Camera
  options: RenderOptions
  reading: reveal.Reading = reveal.PAPER_READING

  @property
  def hidden_size(self) -> int:
    return int(self.hidden.shape[0])

  def reveal_renders(self, renders) -> jax.Array:
    """[V, H, W, 3] -> [V, S, S, 3] revealed images."""
    return reveal.reveal_renders(self.decoder, jnp.asarray(renders), self.decoder_width, self.hidden_size,
                                 self.reading)

  def scores(self, revealed) -> dict[str, np.ndarray]:
    """PSNR and SSIM [V] of revealed images [V, S, S, 3] to I."""
    return scoring.scores_to_hidden(revealed, self.hidden)

  def revealed_scores(self, revealed) -> dict[str, float]:
    """hidden_psnr, hidden_ssim and hidden_z (phase_statistic.z_scores of the revealed image itself, not less the
    decoder's mean output as the ownership test takes it) of one revealed image [1, S, S, 3]."""
    revealed = np.asarray(revealed)
    scores = self.scores(revealed)
    z = phase_statistic.z_scores(phase_statistic.whitened_spectra(revealed),
                                 phase_statistic.whitened_spectra(np.asarray(self.hidden)[None]))
    return dict(hidden_psnr=float(scores["psnr"][0]), hidden_ssim=float(scores["ssim"][0]), hidden_z=float(z[0, 0]))

  def check_scores(self, gaussians: Gaussians, camera: Camera | None = None,
                   options: RenderOptions | None = None) -> dict[str, float]:
    """revealed_scores of what `gaussians` reveal at the key (or at `camera` with `options`: the key moved into a
    transformed scene's frame, align.moved_key)."""
    camera = self.check_camera if camera is None else camera
    options = self.options if options is None else options
    return self.revealed_scores(self.reveal_renders(render(gaussians, camera, options).rgb[None]))

  def aligned_scores(self, marked: Gaussians, suspect: Gaussians, alpha: float, null_views: int) -> dict:
    """What `suspect` reveals at the key after re-alignment against the owner's copy `marked` (the scene the
    key was made for; align.realign), as verify reports it: revealed_scores of the strongest reading
    (ownership.strongest: smallest p-value, then largest SSIM; its name `reading`), `registration`, the
    transform found, its fit and the key's refinement (align.Realignment.report), `tones`, the colour maps
    found, and `test`, verify's decision at `alpha` given the owner's copy (ownership.decide_readings: read after
    each tone map and as rendered, the null outputs from the suspect at the moved key, at least `null_views` turned
    views): z, log10_p, owned, and each reading's."""
    realigned = align.realign(marked, suspect, self.check_camera, self.options)
    camera, options = realigned.camera, realigned.options
    suspect = jax.tree.map(jnp.asarray, suspect)
    readings = reveal.readings(self.reveal_renders, realigned.tones)
    views = ownership.turned_views_needed(alpha, self.hidden_size, len(ownership.unrelated_images(self.hidden)),
                                          null_views, len(readings))
    renders = ownership.null_renders(suspect, camera, options, views, self.hidden)
    by_name, both = ownership.decide_readings(readings, render(suspect, camera, options).rgb[None],
                                              self.hidden[None], renders, alpha)
    test = dict(ownership.summary(both), readings={name: ownership.summary(r.result) for name, r in by_name.items()})
    name = ownership.strongest(by_name, self.hidden)
    return dict(self.revealed_scores(by_name[name].revealed), reading=name,
                registration=realigned.report(),
                tones={n: tone.report() for n, tone in realigned.tones.items()}, test=test)


def scene_scores(gaussians: Gaussians, owner: Owner, test_cameras: Sequence[Camera], test_images) -> dict:
  """An (attacked) scene's mean test PSNR and what it reveals at the key."""
  return dict(render_psnr=evaluate.views_psnr(gaussians, list(test_cameras), test_images, owner.options),
              **owner.check_scores(gaussians))


def attacked_check_renders(gaussians: Gaussians, owner: Owner,
                           levels: Sequence[tuple] = image_attacks.LEVELS) -> np.ndarray:
  """[1 + len(levels), H, W, 3]: the check render, then it under each (attack, level, severity) of `levels`."""
  check = np.asarray(render(gaussians, owner.check_camera, owner.options).rgb)
  return np.stack([check] + [image_attacks.attack(check, name, level) for name, level, _ in levels])


def image_attack_rows(gaussians: Gaussians, owner: Owner,
                      levels: Sequence[tuple] = image_attacks.LEVELS) -> tuple[dict, list[dict]]:
  """Hidden PSNR / SSIM when the check render is attacked before decoding, per (attack, level).

  Returns (the unattacked scores, one row per level with `ssim_drop` relative to unattacked)."""
  scores = owner.scores(owner.reveal_renders(attacked_check_renders(gaussians, owner, levels)))
  base = dict(hidden_psnr=float(scores["psnr"][0]), hidden_ssim=float(scores["ssim"][0]))
  rows = [dict(attack=name, level=level, severity=severity, hidden_psnr=float(scores["psnr"][i + 1]),
               hidden_ssim=float(scores["ssim"][i + 1]), ssim_drop=base["hidden_ssim"] - float(scores["ssim"][i + 1]))
          for i, (name, level, severity) in enumerate(levels)]
  return base, rows


def pad_like(gaussians: Gaussians, num: int, sh_degree: int) -> Gaussians:
  """[M <= num] Gaussians as a [num] buffer with `sh_degree` bands, the way training holds a scene: dead
  rows get NaN centres (culled) and missing SH bands are zero, so the image is the same and every
  attacked scene shares one compiled render."""
  m = int(np.asarray(gaussians.means).shape[0])
  if m > num:
    raise ValueError(f"cannot pad {m} Gaussians to {num}")
  buffer = train.pad_to_capacity(gaussians_lib.with_sh_degree(gaussians, sh_degree), num)
  return train.masked(buffer, jnp.arange(num) < m)


def model_attack_rows(gaussians: Gaussians, owner: Owner, test_cameras: Sequence[Camera], test_images,
                      levels: Sequence[tuple] = model_attacks.LEVELS) -> list[dict]:
  """Render PSNR on the test views and hidden PSNR / SSIM of the attacked scene, per (attack, level);
  the first row ("none") is the scene as shared."""
  return [dict(attack=name, level=level, severity=severity, num_gaussians=count,
               **scene_scores(padded, owner, test_cameras, test_images))
          for name, level, severity, count, padded in attacked_scenes(gaussians, levels)]


def attacked_scenes(gaussians: Gaussians, levels: Sequence[tuple] = model_attacks.LEVELS):
  """Yields (attack, level, severity, Gaussians left, the attacked scene padded to `gaussians`' size: pad_like)
  for the scene as shared ("none") and then each of `levels`."""
  num = int(np.asarray(gaussians.means).shape[0])
  for name, level, severity in [("none", None, "none")] + list(levels):
    attacked = gaussians if name == "none" else model_attacks.attack(gaussians, name, level)
    yield name, level, severity, int(np.asarray(attacked.means).shape[0]), pad_like(attacked, num, gaussians.sh_degree)


def pose_tolerance_rows(gaussians: Gaussians, owner: Owner, length: float,
                        translations: Sequence[float] = (0.0, 0.002, 0.005, 0.01, 0.02, 0.05),
                        rotations_deg: Sequence[float] = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0),
                        directions: int = 4) -> list[dict]:
  """Hidden SSIM / PSNR with the check camera moved by fractions of `length` (the key's near.near_length, the
  depth of the scene as it sees it; rotation 0) and turned by a few degrees (translation 0), each along / about the
  key's own axes both ways and `directions` random directions or axes (near.nearby_cameras): how precisely the key
  must be kept, and how much a guessed nearby pose reveals."""
  return scoring.near_key_rows(gaussians, owner.check_camera, owner.options, owner.reveal_renders, owner.hidden,
                              length, translations, rotations_deg, directions)
