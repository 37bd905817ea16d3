"""Publishing round trips through splat-transform (robust/converter.py). The round trips skip cleanly when
`make node_modules` has not been run; argument checks and the missing-converter error always run."""
from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from conceal_jax.gs import register as reg
from conceal_jax.gs import similarity as sim
from conceal_jax.gs.scene_gen import sphere_and_ground
from conceal_jax.robust import converter as cv
from conceal_jax.data import ply

needs_converter = pytest.mark.skipif(not cv.available(), reason="splat-transform not installed (make node_modules)")


@pytest.fixture(scope="module")
def scene():
  """2000 Gaussians with SH degree 3, some fully opaque and some fully transparent (logits +-20, stored
  by the compressed formats as opacities of exactly 1 and 0)."""
  g = sphere_and_ground(2000, sh_degree=3)
  rng = np.random.default_rng(0)
  return g.replace(opacity_logits=g.opacity_logits.at[:100].set(20.0).at[100:200].set(-20.0),
                   sh=g.sh.at[:, 1:].set(rng.normal(size=g.sh[:, 1:].shape).astype(np.float32) * 0.05))


def assert_same_scene_up_to_order(original, converted, position_tol: float, colour_tol: float):
  """Every converted Gaussian sits within position_tol (scene units) of an original one whose DC colour
  is within colour_tol where it can be seen (opacity above 1%; .sog keeps no colour for opacity 0): the
  formats may reorder (Morton order) and quantise."""
  means = np.asarray(original.means)
  distances, index = cKDTree(means).query(np.asarray(converted.means))
  assert distances.max() < position_tol, distances.max()
  visible = np.asarray(converted.opacity_logits) > np.log(0.01 / 0.99)
  assert visible.sum() >= 0.9 * original.num
  dc = np.asarray(converted.sh)[visible, 0] - np.asarray(original.sh)[index[visible], 0]
  assert np.abs(dc).max() < colour_tol, np.abs(dc).max()


@needs_converter
@pytest.mark.parametrize("fmt, position_tol, colour_tol", [("ply", 1e-7, 1e-7), ("spz", 2e-3, 0.1),
                                                           ("sog", 2e-2, 0.1), ("compressed.ply", 2e-2, 0.1)])
def test_round_trip_through_each_format(scene, fmt, position_tol, colour_tol, tmp_path):
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    back = cv.round_trip(scene, fmt, workdir=tmp_path)
  clipped = [str(w.message) for w in caught if issubclass(w.category, ply.PlyWarning)]
  # Only .compressed.ply writes the 200 saturated opacities as exactly 0 and 1 (logits of -inf and +inf).
  if fmt == "compressed.ply":
    assert len(clipped) == 1 and "200 opacity logits were infinite" in clipped[0], clipped
  else:
    assert not clipped, clipped
  assert back.num == scene.num and back.sh_degree == 3
  assert (tmp_path / f"out.{fmt}").is_file()
  assert_same_scene_up_to_order(scene, back, position_tol, colour_tol)
  assert np.all(np.isfinite(np.asarray(back.opacity_logits)))


@needs_converter
def test_decimation_and_sh_cut(scene):
  decimated = cv.round_trip(scene, "ply", decimate=0.5)
  assert decimated.num == scene.num // 2 and decimated.sh_degree == 3
  cut = cv.round_trip(scene, "ply", sh_degree=1)
  assert cut.num == scene.num and cut.sh_degree == 1
  np.testing.assert_array_equal(np.asarray(cut.sh), np.asarray(scene.sh)[:, :4])


@needs_converter
def test_floater_filtering_drops_faint_specks_far_from_the_scene_and_keeps_the_scene(scene):
  """20 faint, tiny Gaussians 3-13 units beyond the scene's corner (each alone in its voxel, too faint to make it
  solid) are removed; every other Gaussian comes back where it was."""
  if not cv.adapters():  # asked here, not at collection: listing the adapters starts the converter
    pytest.skip("no WebGPU adapter for floater filtering (make webgpu-cpu)")
  means = np.asarray(scene.means).copy()
  means[:20] = means.max(axis=0) + 3.0 + 0.5 * np.arange(20)[:, None]
  specks = scene.replace(means=jnp.asarray(means), opacity_logits=scene.opacity_logits.at[:20].set(-4.0),
                         log_scales=scene.log_scales.at[:20].set(np.log(0.01)))
  back = cv.round_trip(specks, "ply", floaters=True)
  assert back.num == scene.num - 20
  distances, _ = cKDTree(np.asarray(back.means)).query(means[20:])
  assert distances.max() < 1e-6


def test_floater_filtering_without_an_adapter_is_one_clear_error(scene, monkeypatch, tmp_path):
  monkeypatch.setattr(cv, "adapters", lambda: [])
  with pytest.raises(cv.ConverterError, match="make webgpu-cpu"):
    cv.round_trip(scene, "ply", floaters=True)
  with pytest.raises(cv.ConverterError, match="make webgpu-cpu"):
    cv.round_trip(scene, "ply", floaters=True, workdir=tmp_path / "work")
  assert not (tmp_path / "work").exists()


def test_an_adapter_index_not_listed_is_one_clear_error(scene, monkeypatch, tmp_path):
  monkeypatch.setattr(cv, "adapters", lambda: ["llvmpipe"])
  monkeypatch.setenv(cv.GPU_ENV_VAR, "0")
  assert cv.gpu_device() == "0"
  for device in ("1", "cpu", "-1"):
    monkeypatch.setenv(cv.GPU_ENV_VAR, device)
    with pytest.raises(cv.ConverterError, match=f"{cv.GPU_ENV_VAR}='{device}'.*0: llvmpipe"):
      cv.round_trip(scene, "ply", floaters=True, workdir=tmp_path / "work")
  assert not (tmp_path / "work").exists()


def test_adapters_are_read_from_the_converters_listing(monkeypatch, tmp_path):
  fake = tmp_path / "splat-transform"
  fake.write_text("#!/bin/sh\necho 'Detecting GPU adapters...'\necho '[0] llvmpipe (LLVM 15.0.6, 256 bits)'\n"
                  "echo '[1] NVIDIA H200'\necho 'Use -g <index> to select a specific GPU adapter.'\n")
  fake.chmod(0o755)
  monkeypatch.setenv(cv.ENV_VAR, str(fake))
  assert cv.adapters() == ["llvmpipe (LLVM 15.0.6, 256 bits)", "NVIDIA H200"]
  monkeypatch.setenv(cv.ENV_VAR, str(tmp_path / "missing"))
  monkeypatch.setattr(cv, "_REPO_ROOT", tmp_path)
  assert cv.adapters() == []


@pytest.mark.parametrize("kwargs, fragment", [(dict(fmt="splat"), "unknown format"),
                                              (dict(decimate=0.0), "decimate must be"),
                                              (dict(decimate=1.5), "decimate must be"),
                                              (dict(sh_degree=4), "sh_degree must be")])
def test_bad_arguments(scene, kwargs, fragment):
  with pytest.raises(ValueError, match=fragment):
    cv.round_trip(scene, **kwargs)


def test_missing_converter_is_one_clear_error(scene, monkeypatch, tmp_path):
  monkeypatch.delenv(cv.ENV_VAR, raising=False)
  monkeypatch.setattr(cv, "_REPO_ROOT", tmp_path)
  assert cv.executable() is None and not cv.available()
  with pytest.raises(cv.ConverterError, match="make node_modules"):
    cv.round_trip(scene, "spz")


def test_failing_converter_reports_its_output(scene, monkeypatch, tmp_path):
  fake = tmp_path / "splat-transform"
  fake.write_text("#!/bin/sh\necho 'unsupported input' >&2\nexit 3\n")
  fake.chmod(0o755)
  monkeypatch.setenv(cv.ENV_VAR, str(fake))
  with pytest.raises(cv.ConverterError, match=r"failed \(3\): unsupported input"):
    cv.round_trip(scene, "sog")


@needs_converter
def test_our_similarity_transform_matches_splat_transforms(scene, tmp_path):
  """An independent implementation of the same transform: splat-transform turns, resizes and moves the
  scene (its own SH rotation); registration recovers the similarity from the centres, and our transform
  with it reproduces splat-transform's centres, scales, orientations and SH coefficients."""
  rng = np.random.default_rng(1)
  g = scene.replace(quats=jnp.asarray(rng.normal(size=(scene.num, 4)), jnp.float32))
  ply.save_ply(tmp_path / "in.ply", g)
  cv.run([tmp_path / "in.ply", "-r", "30,60,150", "-s", "2.5", "-t", "1,2,3", tmp_path / "moved.ply"])
  theirs = ply.load_ply(tmp_path / "moved.ply")
  found = reg.register(g, theirs)
  assert found.residual < 1e-6 and abs(found.similarity.scale - 2.5) < 1e-6
  ours = sim.transform_gaussians(g, found.similarity)
  np.testing.assert_allclose(np.asarray(ours.means), np.asarray(theirs.means), atol=2e-6)
  np.testing.assert_allclose(np.asarray(ours.log_scales), np.asarray(theirs.log_scales), atol=1e-6)
  np.testing.assert_allclose(np.asarray(ours.sh), np.asarray(theirs.sh), atol=1e-6)
  unit = lambda q: np.asarray(q) / np.linalg.norm(np.asarray(q), axis=1, keepdims=True)
  np.testing.assert_allclose(np.abs(np.sum(unit(ours.quats) * unit(theirs.quats), axis=1)), 1.0, atol=1e-6)
