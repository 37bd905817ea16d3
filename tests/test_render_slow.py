"""Slow checks on the real garden point cloud (`make test-slow`; skipped without ../shared/data)."""
from __future__ import annotations

import numpy as np
import pytest

from conceal_jax import RenderOptions
from conceal_jax import render
from experiments.bench_render import garden_camera, garden_scene
from tests.helpers import DATA_DIR, reference

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def garden():
  path = DATA_DIR / "garden_points.npz"
  if not path.exists():
    pytest.skip(f"{path} not found: real data lives in ../shared/data")
  return dict(np.load(path))


def test_exact_mode_matches_reference_on_real_points(garden):
  g = garden_scene(garden["means3d"], garden["colors"], 1500, degree=3)
  cam = garden_camera(garden, (48, 40))
  options = RenderOptions(max_per_tile=None, background=(1.0, 1.0, 1.0), antialiased=True)
  out = render(g, cam, options)
  rgb, alpha, _, ambiguous = reference(g, cam, options)
  assert alpha.max() > 0.5
  np.testing.assert_allclose(np.asarray(out.rgb)[~ambiguous], rgb[~ambiguous], atol=1e-5, rtol=0)


def test_truncation_without_overflow_equals_exact_mode(garden):
  g = garden_scene(garden["means3d"], garden["colors"], 20000, degree=3)
  cam = garden_camera(garden, (256, 256))
  exact = render(g, cam, RenderOptions(max_per_tile=None))
  wide = render(g, cam, RenderOptions(max_per_tile=1024))
  narrow = render(g, cam, RenderOptions(max_per_tile=64))
  assert int(wide.num_overflow_tiles) == 0 and int(narrow.num_overflow_tiles) > 0
  np.testing.assert_allclose(wide.rgb, exact.rgb, atol=1e-5)
  assert float(np.max(np.abs(narrow.rgb - exact.rgb))) > 1e-3


def test_default_options_are_exact_on_20k_points_at_256x166(garden):
  """The issue's accuracy target: default options against the float64 render of the same scene."""
  from experiments.bench_render import float64_reference
  g = garden_scene(garden["means3d"], garden["colors"], 20000, degree=3)
  options = RenderOptions(sh_degree=3, background=(1.0, 1.0, 1.0))
  out = render(g, garden_camera(garden, (256, 166)), options)
  assert not bool(out.overflowed) and int(out.num_overflow_tiles) == 0
  err = np.abs(np.asarray(out.rgb, np.float64) - float64_reference(g, garden, (256, 166), options))
  assert err.mean() <= 1e-4 and np.quantile(err, 0.999) <= 2e-3
