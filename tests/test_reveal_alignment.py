"""Re-alignment in reveal and verify (reveal.owner): a marked scene turned by a large angle, resized, moved
and reordered reveals, after registration onto the owner's copy, the image the untouched scene reveals;
without it, it does not."""
from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from conceal_jax import main as main_lib
from conceal_jax.conceal import align, key as key_lib, reveal, unet
from conceal_jax.configs import default
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import similarity as sim
from conceal_jax.gs.init import gaussians_from_points
from conceal_jax.robust import ownership, scene_attacks
from conceal_jax.splat.render import RenderOptions
from tests.helpers import make_camera


def blobs(n: int = 3000, seed: int = 0):
  """Eight anisotropic clusters of distinct colours around the origin (about 2 units across), SH degree 1."""
  rng = np.random.default_rng(seed)
  centres = rng.normal(size=(8, 3)) * np.array([1.0, 0.6, 0.4])
  label = rng.integers(8, size=n)
  points = centres[label] + rng.normal(size=(n, 3)) * 0.15
  colours = np.clip(rng.uniform(size=(8, 3))[label] + rng.normal(size=(n, 3)) * 0.05, 0, 1)
  return gaussians_from_points(points, colours, sh_degree=1, opacity=0.7)


@pytest.fixture(scope="module")
def marked(tmp_path_factory):
  """(folder, scene): owner.ply, an untrained width-4 decoder, a key at a 32x32 camera (white background, as
  the demo's) and expected.png, what the untouched scene reveals there."""
  folder = tmp_path_factory.mktemp("aligned")
  scene = jax.tree.map(np.asarray, blobs())
  ply.save_ply(folder / "owner.ply", scene)
  camera = make_camera(32, 32, eye=(0.5, -5.0, 1.5))
  reveal.save_decoder(str(folder / "decoder.msgpack"), unet.init_decoder(jax.random.key(0), 4, 16))
  key_lib.save_key(str(folder / "key.json"), camera, dict(hidden_size=16, uses_decoder=True, decoder_width=4,
                                                          render_options=dict(background=[1.0, 1.0, 1.0])))
  config = config_for(folder, folder / "owner.ply")
  config.reveal.hidden = ""
  plain = reveal.reveal(config, str(folder / "plain"))
  assert "alignment" not in plain and "psnr" not in plain
  fileio.copy_file(folder / "plain" / "revealed.png", folder / "expected.png")
  return folder, scene


def config_for(folder, scene_path, owner: str = ""):
  config = default.get_config()
  config.mode = "reveal"
  config.reveal.ply, config.reveal.key = str(scene_path), str(folder / "key.json")
  config.reveal.decoder, config.reveal.owner = str(folder / "decoder.msgpack"), owner
  config.reveal.hidden = str(folder / "expected.png")  # scored against what the untouched scene reveals
  return config


def attacked(scene, attack: str, level, folder, seed: int = 1):
  """The scene attacked (scene_attacks: moved and shuffled) and saved; its path and the applied similarity."""
  moved, applied = scene_attacks.attack(jax.tree.map(jax.numpy.asarray, scene), attack, level, seed=seed)
  path = folder / f"{attack}_{level}.ply"
  ply.save_ply(path, jax.tree.map(np.asarray, moved))
  return path, applied


@pytest.mark.parametrize("attack,level", [("rotate", 180.0), ("similarity", 10.0)])
def test_reveal_with_the_owner_copy_recovers_the_untouched_reveal(marked, attack, level, tmp_path):
  folder, scene = marked
  path, applied = attacked(scene, attack, level, tmp_path)
  result = main_lib.run(config_for(folder, path, str(folder / "owner.ply")), str(tmp_path / "aligned"))
  assert result["psnr"] > 40.0 and result["ssim"] > 0.999
  found = result["alignment"]
  assert np.allclose(found["rotation"], applied.rotation, atol=1e-4)
  assert found["scale"] == pytest.approx(applied.scale, rel=1e-4)
  assert np.allclose(found["translation"], applied.translation, atol=1e-3 * max(1.0, applied.scale))
  assert found["residual"] < 1e-3 and found["matched_fraction"] > 0.99
  # moved, not graded: the tone map found is the identity
  for tone in found["tones"].values():
    np.testing.assert_allclose(tone["gain"], 1.0, atol=1e-3)
    np.testing.assert_allclose(tone["offset"], 0.0, atol=1e-3)
  angle = np.degrees(np.arccos(np.clip((np.trace(applied.rotation) - 1) / 2, -1, 1)))
  assert found["angle_deg"] == pytest.approx(angle, abs=1e-3)
  saved = json.loads((tmp_path / "aligned" / reveal.REVEAL_FILE).read_text())
  assert saved["alignment"]["owner"] == str(folder / "owner.ply") and saved["psnr"] == result["psnr"]
  # the same scene without re-alignment: the key sees something else
  unaligned = reveal.reveal(config_for(folder, path), str(tmp_path / "unaligned"))
  assert unaligned["psnr"] < 30.0 and "alignment" not in unaligned


def test_moved_key_scales_the_near_plane():
  similarity = sim.Similarity(sim.rotation_from_axis_angle((1.0, 2.0, 3.0), 2.0), np.array([1.0, -2.0, 0.5]), 0.25)
  camera, options = align.moved_key(make_camera(), RenderOptions(near=0.2), similarity)
  assert options.near == pytest.approx(0.05)
  w2c = sim.transform_world_to_camera(make_camera().world_to_camera, similarity)
  np.testing.assert_allclose(np.asarray(camera.world_to_camera), w2c, atol=1e-6)
  report = align.similarity_report(similarity)
  assert report["angle_deg"] == pytest.approx(np.degrees(2.0))
  np.testing.assert_allclose(report["axis"], np.array([1.0, 2.0, 3.0]) / np.sqrt(14), atol=1e-9)
  assert align.similarity_report(sim.Similarity.identity())["angle_deg"] == 0.0


@pytest.mark.slow  # verify renders its null views of a moved scene: about a minute on two cores
def test_verify_decides_after_re_alignment(marked, tmp_path):
  """The re-aligned key reveals what the untouched scene did: the calibrated SSIM threshold decides it owned and
  z is far higher than at the key as saved. (The untrained decoder's output varies little whatever it reads, so
  the null estimated from its outputs keeps the statistical test from deciding either way: the SSIM decides.)"""
  # a threshold of SSIM 0.95 to what the untouched scene reveals
  (tmp_path / "cal.json").write_text(json.dumps(dict(clean=[0.9], marked=[0.999])))
  path, _ = attacked(marked[1], "rotate", 90.0, tmp_path)
  folder = marked[0]
  z = {}
  for owner, owned in ((str(folder / "owner.ply"), True), ("", False)):
    config = config_for(folder, path, owner)
    config.mode, config.verify.calibration, config.verify.null_views = "verify", str(tmp_path / "cal.json"), 4
    result = main_lib.run(config, str(tmp_path / f"verify_{owned}"))
    assert result["calibration"]["owned"] is owned and ("alignment" in result) is owned
    assert set(result["readings"]) == ({"toned", "scene_toned", "as_rendered"} if owned else {"as_rendered"})
    assert result["log10_p"] >= min(reading["log10_p"] for reading in result["readings"].values())
    saved = json.loads((tmp_path / f"verify_{owned}" / ownership.VERIFY_FILE).read_text())
    assert saved["calibration"]["owned"] is owned
    z[owned] = result["z"]
  assert z[True] > z[False] + 3


def test_an_unrelated_scene_is_reported_as_a_doubtful_alignment(marked, tmp_path, caplog):
  folder, _ = marked
  ply.save_ply(tmp_path / "other.ply", jax.tree.map(np.asarray, blobs(seed=5)))
  with caplog.at_level("WARNING"):
    result = reveal.reveal(config_for(folder, tmp_path / "other.ply", str(folder / "owner.ply")), str(tmp_path / "o"))
  assert result["alignment"]["matched_fraction"] < reveal.MIN_MATCHED_FRACTION
  assert "doubtful" in caplog.text
