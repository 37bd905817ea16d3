"""The converter's decimation grouping reproduced from the scene (experiments/converter_decimation.py): every group's
mass-weighted mean is a Gaussian of the converter's own output, and the grouping removes exactly what the target
asks, in groups of 2 to 4."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from conceal_jax.robust import converter
from conceal_jax.conceal import grouping, merge_costs
from experiments import converter_decimation
from tests.helpers import random_gaussians


def scene(n: int = 300):
  return jax.tree.map(np.asarray, random_gaussians(4, n, degree=1))


def test_the_grouping_removes_what_the_target_asks_in_groups_of_two_to_four():
  g = scene()
  for keep in (0.5, 0.8):
    group = grouping.converter_groups(g, keep)
    sizes = np.bincount(group[group >= 0])
    assert g.num - int(np.sum(sizes - 1)) == round(keep * g.num)
    assert sizes.min() >= 2 and sizes.max() <= 4
  with pytest.raises(ValueError, match="one generation"):
    grouping.converter_groups(g, 0.4)


def test_the_sample_is_a_standard_normal_draw_and_costs_are_finite():
  z = merge_costs.mulberry32_normal(0)
  assert z.shape == (3,) and np.all(np.abs(z) < 5) and not np.allclose(z, merge_costs.mulberry32_normal(1))
  g = scene(50)
  first, second = np.arange(49), np.arange(1, 50)
  cost = merge_costs.edge_costs(merge_costs.shape_costs(g, first, second), merge_costs.colour_costs(g, first, second))
  assert cost.dtype == np.float32 and np.all(np.isfinite(cost))


@pytest.mark.skipif(not converter.available(), reason="splat-transform not installed (make node_modules)")
def test_the_reproduced_groups_are_the_converters(tmp_path):
  g = scene()
  returned = converter.round_trip(g, decimate=0.5, workdir=tmp_path)
  result = converter_decimation.compare(g, 0.5, returned, np.arange(g.num))
  assert result["returned"] == 150 and result["groups_found"] == 1.0
