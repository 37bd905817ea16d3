"""Scoring the hidden image under attacks and near-key poses (robust/robustness.py, conceal/key.py)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax import RenderOptions, render
from conceal_jax.conceal import near, reveal
from conceal_jax.robust import model_attacks, robustness
from conceal_jax.splat.camera import camera_centers
from tests.helpers import make_camera, random_gaussians

OPTIONS = RenderOptions(background=(1.0, 1.0, 1.0))


def scene():
  return random_gaussians(5, 400, degree=2, spread=0.5, log_scale=(-2.5, -1.8))


def no_decoder_owner(gaussians, camera, size=16):
  """The no-decoder ablation with I = the check view itself: unattacked SSIM is exactly 1."""
  hidden = np.asarray(reveal.reveal_renders(None, render(gaussians, camera, OPTIONS).rgb, 0, size))
  return robustness.Owner(decoder=None, decoder_width=0, hidden=hidden, check_camera=camera, options=OPTIONS)


def test_nearby_camera_moves_and_turns_by_the_asked_amount():
  camera = make_camera(32, 24)
  moved = near.nearby_camera(camera, 0.3, 0.0, seed=1)
  np.testing.assert_allclose(np.linalg.norm(camera_centers([moved])[0] - camera_centers([camera])[0]), 0.3,
                             rtol=1e-5)
  turned = near.nearby_camera(camera, 0.0, 4.0, seed=2)
  r0 = np.asarray(camera.world_to_camera, np.float64)[:3, :3]
  r1 = np.asarray(turned.world_to_camera, np.float64)[:3, :3]
  angle = np.degrees(np.arccos(np.clip((np.trace(r1 @ r0.T) - 1) / 2, -1, 1)))
  np.testing.assert_allclose(angle, 4.0, rtol=1e-3)
  np.testing.assert_allclose(camera_centers([turned])[0], camera_centers([camera])[0], atol=1e-5)
  np.testing.assert_allclose(r1 @ r1.T, np.eye(3), atol=1e-6)


def test_padding_an_attacked_scene_leaves_its_image_unchanged():
  g = scene()
  camera = make_camera(40, 32)
  for name, level in (("prune_transparent", 0.5), ("sh_degree", 0), ("subsample", 0.7)):
    attacked = model_attacks.attack(g, name, level)
    padded = robustness.pad_like(attacked, g.num, g.sh_degree)
    assert padded.means.shape == (400, 3) and padded.sh.shape == g.sh.shape
    expected = render(jax.tree.map(jnp.asarray, attacked), camera, OPTIONS).rgb
    np.testing.assert_allclose(render(jax.tree.map(jnp.asarray, padded), camera, OPTIONS).rgb, expected,
                               atol=1e-6)


def test_image_attacks_lower_a_perfect_score():
  g = scene()
  owner = no_decoder_owner(g, make_camera(48, 48))
  base, rows = robustness.image_attack_rows(g, owner, [("blur", 0.5, "mild"), ("blur", 3.0, "strong"),
                                                       ("jpeg", 95, "mild")])
  np.testing.assert_allclose(base["hidden_ssim"], 1.0, atol=1e-5)
  drops = [row["ssim_drop"] for row in rows]
  assert all(np.isfinite(drops)) and 0 <= drops[0] < drops[1]
  assert [row["attack"] for row in rows] == ["blur", "blur", "jpeg"]


def test_model_attack_rows_start_with_the_scene_as_shared():
  g = scene()
  camera = make_camera(32, 32)
  owner = no_decoder_owner(g, camera)
  targets = [np.clip(render(g, c, OPTIONS).rgb, 0, 1) for c in (camera, make_camera(32, 32, eye=(1.0, -4.0, 1.0)))]
  rows = robustness.model_attack_rows(g, owner, [camera, make_camera(32, 32, eye=(1.0, -4.0, 1.0))], targets,
                                      [("prune_transparent", 0.5, "strong"), ("float16", None, "mild")])
  assert [r["attack"] for r in rows] == ["none", "prune_transparent", "float16"]
  np.testing.assert_allclose(rows[0]["hidden_ssim"], 1.0, atol=1e-5)
  assert rows[0]["render_psnr"] > 60 and rows[1]["num_gaussians"] == 200
  assert rows[1]["render_psnr"] < rows[2]["render_psnr"] and rows[1]["hidden_ssim"] < rows[2]["hidden_ssim"]


def test_pose_tolerance_falls_with_distance():
  g = scene()
  owner = no_decoder_owner(g, make_camera(48, 48))
  rows = robustness.pose_tolerance_rows(g, owner, length=2.0, translations=(0.0, 0.05), rotations_deg=(0.0, 5.0),
                                        directions=2)
  by = {(r["kind"], r["value"]): r for r in rows}
  np.testing.assert_allclose(by[("translation", 0.0)]["mean_ssim"], 1.0, atol=1e-5)
  assert by[("translation", 0.05)]["mean_ssim"] < 0.999 and by[("rotation", 5.0)]["mean_ssim"] < 0.999
