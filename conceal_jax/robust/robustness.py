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

from conceal_jax.conceal import key as key_lib, reveal
from conceal_jax.gs import evaluate, metrics
from conceal_jax.robust import image_attacks, model_attacks
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render


@dataclasses.dataclass(frozen=True)
class Owner:
  """What the owner keeps: decoder params (None: the no-decoder ablation) of `decoder_width`, the hidden
  image I [S, S, 3], the check camera and the render options of the key."""
  decoder: Any
  decoder_width: int
  hidden: np.ndarray
  check_camera: Camera
  options: RenderOptions

  @property
  def hidden_size(self) -> int:
    return int(self.hidden.shape[0])

  def reveal_renders(self, renders) -> jax.Array:
    """[V, H, W, 3] -> [V, S, S, 3] revealed images."""
    return reveal.reveal_renders(self.decoder, jnp.asarray(renders), self.decoder_width, self.hidden_size)

  def scores(self, revealed) -> dict[str, np.ndarray]:
    """PSNR and SSIM [V] of revealed images [V, S, S, 3] to I."""
    revealed = jnp.asarray(revealed)
    hidden = jnp.broadcast_to(jnp.asarray(self.hidden), revealed.shape)
    return dict(psnr=np.asarray(jax.vmap(metrics.psnr)(revealed, hidden), np.float64),
                ssim=np.asarray(metrics.batched_ssim(revealed, hidden), np.float64))


def image_attack_rows(gaussians: Gaussians, owner: Owner,
                      levels: Sequence[tuple] = image_attacks.LEVELS) -> tuple[dict, list[dict]]:
  """Hidden PSNR / SSIM when the check render is attacked before decoding, per (attack, level).

  Returns (the unattacked scores, one row per level with `ssim_drop` relative to unattacked)."""
  check = np.asarray(render(gaussians, owner.check_camera, owner.options).rgb)
  attacked = np.stack([check] + [image_attacks.attack(check, name, level) for name, level, _ in levels])
  scores = owner.scores(owner.reveal_renders(attacked))
  base = dict(hidden_psnr=float(scores["psnr"][0]), hidden_ssim=float(scores["ssim"][0]))
  rows = [dict(attack=name, level=level, severity=severity, hidden_psnr=float(scores["psnr"][i + 1]),
               hidden_ssim=float(scores["ssim"][i + 1]), ssim_drop=base["hidden_ssim"] - float(scores["ssim"][i + 1]))
          for i, (name, level, severity) in enumerate(levels)]
  return base, rows


def pad_like(gaussians: Gaussians, num: int, sh_coeffs: int) -> Gaussians:
  """[M <= num] Gaussians as [num] rows with `sh_coeffs` SH coefficients: extra rows have NaN centres
  (culled by the projection) and missing SH bands are zero (they add nothing), so the image is the same
  and every attacked scene shares one compiled render."""
  m, coeffs = int(np.asarray(gaussians.means).shape[0]), int(np.asarray(gaussians.sh).shape[1])
  if m > num or coeffs > sh_coeffs:
    raise ValueError(f"cannot pad {m} Gaussians with {coeffs} SH coefficients to {num} and {sh_coeffs}")

  def pad(x, fill, width=None):
    x = np.asarray(x, np.float32)
    shape = (num,) + ((width,) + x.shape[2:] if width else x.shape[1:])
    out = np.full(shape, fill, np.float32)
    out[(slice(0, m),) + tuple(slice(0, n) for n in x.shape[1:])] = x
    return out
  return Gaussians(means=pad(gaussians.means, np.nan), log_scales=pad(gaussians.log_scales, 0.0),
                   quats=pad(gaussians.quats, 0.0), opacity_logits=pad(gaussians.opacity_logits, 0.0),
                   sh=pad(gaussians.sh, 0.0, sh_coeffs))


def model_attack_rows(gaussians: Gaussians, owner: Owner, test_cameras: Sequence[Camera], test_images,
                      levels: Sequence[tuple] = model_attacks.LEVELS) -> list[dict]:
  """Render PSNR on the test views and hidden PSNR / SSIM of the attacked scene, per (attack, level);
  the first row ("none") is the scene as shared."""
  num, coeffs = int(np.asarray(gaussians.means).shape[0]), int(np.asarray(gaussians.sh).shape[1])
  targets = jnp.asarray(np.stack(test_images))
  rows = []
  for name, level, severity in [("none", None, "none")] + list(levels):
    attacked = gaussians if name == "none" else model_attacks.attack(gaussians, name, level)
    kept = int(np.asarray(attacked.means).shape[0])
    padded = jax.tree.map(jnp.asarray, pad_like(attacked, num, coeffs))
    renders = jnp.clip(evaluate.render_images(padded, list(test_cameras), owner.options), 0, 1)
    render_psnr = float(jnp.mean(jax.vmap(metrics.psnr)(renders, targets)))
    check = render(padded, owner.check_camera, owner.options).rgb
    scores = owner.scores(owner.reveal_renders(check[None]))
    rows.append(dict(attack=name, level=level, severity=severity, num_gaussians=kept, render_psnr=render_psnr,
                     hidden_psnr=float(scores["psnr"][0]), hidden_ssim=float(scores["ssim"][0])))
  return rows


def pose_tolerance_rows(gaussians: Gaussians, owner: Owner, extent: float,
                        translations: Sequence[float] = (0.0, 0.002, 0.005, 0.01, 0.02, 0.05),
                        rotations_deg: Sequence[float] = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0),
                        directions: int = 4) -> list[dict]:
  """Hidden SSIM / PSNR with the check camera moved by fractions of the scene `extent` (rotation 0) and
  turned by a few degrees (translation 0), each over `directions` random directions or axes: how
  precisely the key must be kept, and how much a guessed nearby pose reveals."""
  poses = key_lib.nearby_cameras(owner.check_camera, extent, translations, rotations_deg, directions)
  renders = evaluate.render_images(gaussians, [camera for _, _, camera in poses], owner.options)
  scores = owner.scores(owner.reveal_renders(renders))
  rows = []
  for kind, value in dict.fromkeys((kind, value) for kind, value, _ in poses):
    mine = np.array([(k, v) == (kind, value) for k, v, _ in poses])
    rows.append(dict(kind=kind, value=value, unit="fraction of extent" if kind == "translation" else "degrees",
                     mean_ssim=float(scores["ssim"][mine].mean()), max_ssim=float(scores["ssim"][mine].max()),
                     mean_psnr=float(scores["psnr"][mine].mean())))
  return rows
