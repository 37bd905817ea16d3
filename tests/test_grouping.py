"""conceal.grouping: the converter's groups as training merges them. Merging every group of a level reproduces the
converter's own decimation of a random scene (positions, colours and opacities of its output; skips without node);
groups are padded to a capacity that only grows; the film's groups only; the regrouping schedule resumes where it
left off."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from conceal_jax.conceal import augment, decimate, grouping, merge_costs, train as conceal_train
from conceal_jax.data import ply
from conceal_jax.robust import converter
from tests.helpers import random_gaussians
from tests.test_conceal import tiny, tiny_config  # noqa: F401  (the module-scoped scene fixture)


def scene(n: int = 300):
  return jax.tree.map(np.asarray, random_gaussians(4, n, degree=1))


def alive(g) -> np.ndarray:
  return np.asarray(g.opacity_logits) > decimate.DROPPED_LOGIT


def test_group_members_lists_the_groups_holding_the_rows_in_descending_order():
  group = np.array([0, 1, 0, -1, 1, 2, 2, 0, 3, 3])
  members = grouping.group_members(group, np.array([2, 5]))
  np.testing.assert_array_equal(members, [[7, 2, 0, -1], [6, 5, -1, -1]])
  assert grouping.group_members(group, np.array([3])).shape == (0, grouping.MAX_GROUP)


def test_merging_a_level_keeps_its_count_mass_and_colour_and_pads_to_capacity():
  g = scene()
  g = g.replace(opacity_logits=g.opacity_logits - 3.0)  # faint splats: no merged opacity reaches the cap
  merges = grouping.converter_merges(g, np.arange(g.num), (0.5, 0.8))
  assert all(m.members.shape == (grouping.CAPACITY_STEP, grouping.MAX_GROUP) for m in merges)  # 150 groups at most
  wider = grouping.converter_merges(g, np.arange(g.num), (0.5,), capacity=3 * grouping.CAPACITY_STEP)
  assert wider[0].members.shape[0] == 3 * grouping.CAPACITY_STEP
  none = decimate.merge_levels(g, merges, jnp.float32(0.0))
  for a, b in zip(jax.tree.leaves(none), jax.tree.leaves(g)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  mass = lambda x: decimate.masses(jax.tree.map(np.asarray, x))
  for level, keep in enumerate((0.5, 0.8), 1):
    out = decimate.merge_levels(g, merges, jnp.float32(level))
    kept = alive(out)
    assert kept.sum() == round(keep * g.num)
    np.testing.assert_allclose(mass(out)[kept].sum(), mass(g).sum(), rtol=1e-4)
    colour = lambda x, rows: np.sum((mass(x)[:, None] * np.asarray(x.sh[:, 0], np.float64))[rows], axis=0)
    np.testing.assert_allclose(colour(out, kept), colour(g, np.arange(g.num)), rtol=1e-4)


def test_only_the_films_groups_merge_and_the_gradient_reaches_every_member():
  g = scene()
  rows = np.arange(200, 300)
  (merges,) = grouping.converter_merges(g, rows, (0.5,))
  members = np.asarray(merges.members)
  real = members[members < g.num]
  assert np.isin(rows, real).sum() > 0.8 * rows.size
  out = decimate.merge_levels(g, (merges,), jnp.float32(1.0))
  untouched = np.setdiff1d(np.arange(g.num), real)
  np.testing.assert_array_equal(np.asarray(out.sh)[untouched], np.asarray(g.sh)[untouched])
  first = members[:, 0][members[:, 0] < g.num]
  grad = jax.grad(lambda dc: jnp.sum(decimate.merge_levels(g.replace(sh=jnp.asarray(g.sh).at[:, 0].set(dc)),
                                                           (merges,), jnp.float32(1.0)).sh[first, 0]))(
      jnp.asarray(g.sh[:, 0]))
  grad = np.asarray(grad)[:, 0]
  assert np.all(np.isfinite(grad)) and np.all(grad[real] > 0) and np.all(grad[untouched] == 0)


def test_regrouping_is_due_every_few_steps_at_checkpoints_and_after_a_resume():
  a = augment.Augmentation(merge_fraction=0.25, merge_groups="converter", regroup_every=300)
  fresh = grouping.Regrouping(0, a, checkpoint_every=1000)
  assert [i for i in range(1, 2002) if fresh.due(i)] == [301, 601, 901, 1001, 1201, 1501, 1801, 2001]
  resumed = grouping.Regrouping(0, a, checkpoint_every=1000)
  assert [i for i in range(1001, 1400) if resumed.due(i)] == [1001, 1201]
  draws = [augment.draw(np.random.default_rng(i), a)["merge"] for i in range(400)]
  assert set(np.unique(draws)) == {0.0, 1.0, 2.0} and abs(np.mean(np.asarray(draws) > 0) - 0.25) < 0.08
  with pytest.raises(ValueError, match="merge_groups"):
    augment.Augmentation(merge_groups="random")
  with pytest.raises(ValueError, match="merge_keep"):
    augment.Augmentation(merge_keep=(0.4,))
  scales = augment.Augmentation(merge_fraction=1.0, merge_groups="converter", merge_scales=(0.1, 1.0, 10.0))
  assert scales.merge_levels == 6
  draws = [augment.draw(np.random.default_rng(i), scales)["merge"] for i in range(300)]
  assert set(np.unique(draws)) == {1.0, 2.0, 3.0, 4.0, 5.0, 6.0}
  for bad in ((), (0.0,), (1.0, float("nan")), (float("inf"),)):
    with pytest.raises(ValueError, match="merge_scales"):
      augment.Augmentation(merge_scales=bad)


def test_a_level_at_another_scale_is_the_scaled_copys_grouping_merged_in_the_scenes_own_frame():
  """A level at scale s groups as the converter does the scene scaled by s, which differs from its grouping of the
  scene itself where the splats' variances approach EPS_COV; merged, then scaled by s, it is the scaled copy's own
  level at scale 1 (positions, sizes, opacities, colours)."""
  g, factor, rows = scene(), 1e-3, np.arange(300)
  copy = grouping.scaled(g, factor)
  assert np.mean(grouping.converter_groups(copy, 0.5) == grouping.converter_groups(g, 0.5)) < 0.5
  own, at_scale = grouping.converter_merges(g, rows, (0.5,), scales=(1.0, factor))
  (of_copy,) = grouping.converter_merges(copy, rows, (0.5,))
  np.testing.assert_array_equal(np.asarray(at_scale.members), np.asarray(of_copy.members))
  assert not np.array_equal(np.asarray(own.members), np.asarray(at_scale.members))
  merged = jax.tree.map(np.asarray, decimate.merge_levels(g, (at_scale,), jnp.float32(1.0)))
  expected = jax.tree.map(np.asarray, decimate.merge_levels(copy, (of_copy,), jnp.float32(1.0)))
  np.testing.assert_allclose(merged.means * factor, expected.means, rtol=1e-5, atol=1e-9)
  np.testing.assert_allclose(merged.log_scales + np.log(factor), expected.log_scales, atol=1e-4)
  for field in ("opacity_logits", "sh"):
    np.testing.assert_allclose(getattr(merged, field), getattr(expected, field), rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(not converter.available(), reason="splat-transform not installed (make node_modules)")
@pytest.mark.parametrize("keep,factor", [(0.5, 1.0), (0.8, 1.0), (0.5, 1e-3)])
def test_merging_a_level_is_the_converters_decimation(tmp_path, keep, factor):
  """Every Gaussian the converter writes is one the merged scene keeps: same position, base colour and opacity;
  for a level at another scale, of the converter's decimation of the scene scaled by it."""
  g = scene()
  returned = converter.round_trip(grouping.scaled(g, factor), decimate=keep, workdir=tmp_path)
  merges = grouping.converter_merges(g, np.arange(g.num), (keep,), scales=(factor,))
  out = jax.tree.map(np.asarray, decimate.merge_levels(g, merges, jnp.float32(1.0)))
  out = out.replace(means=out.means * factor)
  kept = alive(out)
  assert kept.sum() == returned.num
  distance, index = cKDTree(out.means[kept]).query(np.asarray(returned.means))
  assert np.all(distance < 1e-5 * factor) and np.unique(index).size == returned.num
  np.testing.assert_allclose(np.asarray(returned.sh[:, 0]), out.sh[kept][index, 0], atol=1e-4)
  opacity = lambda x: 1 / (1 + np.exp(-np.asarray(x.opacity_logits, np.float64)))
  np.testing.assert_allclose(opacity(returned), opacity(out)[kept][index], atol=1e-5)


@pytest.mark.slow  # two film runs: the grouping's pieces have their fast tests above
def test_a_film_run_through_the_converters_groups_regroups_and_resumes_exactly(tiny, tmp_path):
  """Every check render merges the film's converter groups (merge_fraction 1, regrouped every 2 steps from the
  trained colours); a run stopped at its checkpoint after 3 steps and resumed ends bit for bit where one that never
  stopped does."""
  config = tiny_config(tiny, iterations=5, key_kind="unseen", **{
      "carrier.film": True, "carrier.spacing": 4.0, "attacks.merge_fraction": 1.0 - 1e-9,
      "attacks.merge_groups": "converter", "attacks.regroup_every": 2, "checkpoint_every": 3})
  conceal_train.train_and_evaluate(config, str(tmp_path / "whole"))
  conceal_train.train_and_evaluate(config, str(tmp_path / "resumed"), max_steps=3)
  conceal_train.train_and_evaluate(config, str(tmp_path / "resumed"))
  whole, resumed = (ply.load_ply(str(tmp_path / name / "student.ply")) for name in ("whole", "resumed"))
  teacher = ply.load_ply(str(tiny[1]))
  assert not np.allclose(whole.sh[teacher.num:, 0], whole.sh[teacher.num, 0])  # the film's colours trained
  for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed)):
    np.testing.assert_array_equal(a, b)


def test_kept_neighbourhoods_walk_as_a_fresh_one_after_colours_change_and_are_redone_when_geometry_does():
  g = scene()
  kept = merge_costs.Neighbourhoods()
  before = kept(g, 1.0)
  recoloured = g.replace(sh=np.asarray(g.sh) + np.random.default_rng(3).normal(0.0, 0.3, g.sh.shape))
  assert kept(recoloured, 1.0) is before  # geometry unchanged: the k-d tree and shape costs are reused
  for fresh, reused in zip(grouping.candidate_edges(recoloured), grouping.candidate_edges(recoloured, before)):
    np.testing.assert_array_equal(fresh, reused)
  moved = g.replace(means=np.asarray(g.means) + 0.01)
  np.testing.assert_array_equal(kept(moved, 1.0).shape, merge_costs.neighbourhood(moved).shape)
  assert kept(moved, 1.0) is not before
  np.testing.assert_array_equal(grouping.candidate_edges(moved, kept(moved, 1.0))[1],
                                grouping.candidate_edges(moved)[1])


def test_several_sizes_merge_as_each_size_alone():
  g = scene()
  together = grouping.converter_merges(g, np.arange(g.num), (0.5,), scales=(0.5, 1.0, 2.0))
  capacity = together[0].members.shape[0]
  for merges, factor in zip(together, (0.5, 1.0, 2.0)):
    alone = grouping.converter_merges(g, np.arange(g.num), (0.5,), capacity, scales=(factor,))[0]
    for a, b in zip(jax.tree.leaves(merges), jax.tree.leaves(alone)):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
