"""conceal/decimate.py: the carrier film's pairs a converter's decimation merges, each merged against a float64
reference of the moment-matching merge, and applied to a share of the pairs in the check render."""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import augment, carrier, decimate, perturb
from conceal_jax.gs import similarity
from conceal_jax.splat.camera import Camera
from tests.test_augment import _random_gaussians


def _greedy_reference(points: np.ndarray) -> set[tuple[int, int]]:
  """Greedy matching over every edge of the complete graph, shortest first (NEIGHBOURS covers all of a small set)."""
  edges = sorted(itertools.combinations(range(len(points)), 2),
                 key=lambda e: np.linalg.norm(points[e[0]] - points[e[1]]))
  taken, pairs = set(), set()
  for i, j in edges:
    if i not in taken and j not in taken:
      taken |= {i, j}
      pairs.add((i, j))
  return pairs


def test_nearest_pairs_is_the_greedy_matching_closest_first():
  points = np.random.default_rng(0).normal(size=(9, 3))
  pairs = decimate.nearest_pairs(points)
  assert pairs.shape == (4, 2) and len(set(pairs.ravel())) == 8  # disjoint; one of nine is left out
  assert {tuple(sorted(p)) for p in pairs.tolist()} == _greedy_reference(points)
  assert decimate.nearest_pairs(points[:1]).shape == (0, 2)


@pytest.mark.parametrize("size", [2, 3, 4])
def test_moment_matched_keeps_the_groups_mass_and_first_two_moments(size):
  """Against float64 sums written out, for pairs and for groups of 3 and 4 padded with -1 (as the converter's
  groups come): the merged mean and covariance are the mass-weighted mixture's (law of total variance) plus the
  converter's regulariser 1e-8 I, read back
  from the merged log-scales and quaternion; the opacity keeps the mass (opacity times the ellipsoid's approximate
  area) where it stays below 1; the weights are each member's share of the mass, 0 for padding."""
  g = _random_gaussians(40, seed=1)
  g = g.replace(opacity_logits=g.opacity_logits - 3.0)  # faint splats: no opacity reaches the cap
  groups = -np.ones((40 // size, 4), np.int64)
  groups[:, :size] = np.random.default_rng(size).permutation(40)[:groups.shape[0] * size].reshape(-1, size)
  merged = decimate.moment_matched(g, groups if size > 2 else groups[:, :2])
  x = jax.tree.map(lambda a: np.asarray(a, np.float64), g)
  for k, group in enumerate(groups):
    cov, mass = [], []
    for n in group[:size]:
      q = x.quats[n] / np.linalg.norm(x.quats[n])
      r = similarity.quaternion_to_matrix(q)
      s = np.exp(x.log_scales[n])
      cov.append(r @ np.diag(s**2) @ r.T)
      a, b, c = s
      area = 4 * np.pi * (((a * b)**1.6075 + (a * c)**1.6075 + (b * c)**1.6075) / 3)**(1 / 1.6075)
      mass.append(area / (1 + np.exp(-x.opacity_logits[n])))
    w = np.array(mass) / np.sum(mass)
    mean = np.sum(w[:, None] * x.means[group[:size]], axis=0)
    expected = sum(w[m] * (cov[m] + np.outer(x.means[n] - mean, x.means[n] - mean))
                   for m, n in enumerate(group[:size])) + 1e-8 * np.eye(3)
    np.testing.assert_allclose(merged["weights"][k][:size], w, rtol=1e-9)
    assert np.all(merged["weights"][k][size:] == 0)
    np.testing.assert_allclose(merged["means"][k], mean, atol=1e-12)
    r = similarity.quaternion_to_matrix(merged["quats"][k])
    s = np.exp(merged["log_scales"][k])
    np.testing.assert_allclose(r @ np.diag(s**2) @ r.T, expected, rtol=1e-6, atol=1e-12)
    opacity = 1 / (1 + np.exp(-merged["opacity_logits"][k]))
    np.testing.assert_allclose(opacity * decimate.ellipsoid_area(s), np.sum(mass), rtol=1e-6)


def test_merge_groups_at_share_0_and_1_and_its_gradient_reaches_both_colours():
  g = _random_gaussians(30, seed=2)
  (merges,) = decimate.film_merges(jax.tree.map(lambda a: a[10:], g), offset=10)
  key = jax.random.key(0)
  same = decimate.merge_groups(g, merges, jnp.float32(0.0), key)
  for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(g)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  merged = decimate.merge_groups(g, merges, jnp.float32(1.0), key)
  first, second = np.asarray(merges.members).T
  w = np.asarray(merges.weights)[:, 0]
  assert first.min() >= 10 and second.min() >= 10  # only the film's rows
  np.testing.assert_allclose(np.asarray(merged.means)[first], np.asarray(merges.means))
  np.testing.assert_array_equal(np.asarray(merged.opacity_logits)[second], decimate.DROPPED_LOGIT)
  sh = np.asarray(g.sh, np.float64)
  np.testing.assert_allclose(np.asarray(merged.sh)[first], w[:, None, None] * sh[first]
                             + (1 - w[:, None, None]) * sh[second], rtol=1e-5, atol=1e-6)
  untouched = np.setdiff1d(np.arange(30), np.concatenate([first, second]))
  np.testing.assert_array_equal(np.asarray(merged.sh)[untouched], sh[untouched].astype(np.float32))
  # the merged Gaussians' colours (the first of each pair; the second is dropped) against both colours of the pair
  grad = jax.grad(lambda dc: jnp.sum(decimate.merge_groups(g.replace(sh=g.sh.at[:, 0].set(dc)), merges,
                                                           jnp.float32(1.0), key).sh[first, 0]))(g.sh[:, 0])
  grad = np.asarray(grad)[:, 0]
  np.testing.assert_allclose(grad[first], w, rtol=1e-5)
  np.testing.assert_allclose(grad[second], 1 - w, rtol=1e-5)
  assert np.all(np.isfinite(grad))


def test_the_check_render_merges_the_drawn_share_of_the_films_pairs():
  """The augmentation draws the depth of the merges on a merge_fraction of the steps, and perturb_gaussians merges
  that share of the film built by carrier.film (every pair at depth 1)."""
  camera = Camera.from_intrinsics(np.eye(4), 40.0, 40.0, 16.0, 16.0, 32, 32)
  film = carrier.film(camera, 2.0, 4.0, 0.01, (0.2, 0.6, 0.9), 0, layers=4)
  merges = decimate.film_merges(film, 0)
  assert len(merges) == 1 and len(np.asarray(merges[0].members)) == film.num // 2
  a = augment.Augmentation(merge_fraction=0.5)
  shares = np.array([augment.draw(np.random.default_rng(i), a)["merge"] for i in range(400)])
  assert abs(np.mean(shares > 0) - 0.5) < 0.1 and shares.max() < 1.0
  dropped = lambda share: np.sum(np.asarray(perturb.perturb_gaussians(
      film, dict(augment.draw(np.random.default_rng(0), a), merge=np.float32(share), model_seed=np.uint32(3)), a,
      merges).opacity_logits) == decimate.DROPPED_LOGIT)
  assert dropped(1.0) == film.num // 2 and dropped(0.0) == 0 and 0 < dropped(0.5) < film.num // 2


def test_a_second_round_merges_what_the_first_leaves_keeping_mass_and_colour():
  """Two rounds (merge_depth 1.5): round 1 pairs the Gaussians round 0 merged into, at their rows; at depth 2 a
  quarter of the film is left, each Gaussian of four splats' mass and the mass-weighted mean of their colours (the
  gradient reaches each of the four); depths up to 1 are the first round alone, depth 1.5 half the second's pairs;
  a depth beyond MAX_MERGE_DEPTH is refused."""
  camera = Camera.from_intrinsics(np.eye(4), 40.0, 40.0, 16.0, 16.0, 32, 32)
  film = carrier.film(camera, 2.0, 4.0, 0.01, (0.2, 0.6, 0.9), 0, layers=4)
  film = film.replace(sh=jax.random.normal(jax.random.key(1), film.sh.shape))
  a = augment.Augmentation(merge_fraction=1.0, merge_depth=2.0)
  first, second = decimate.film_merges(film, 0, a.merge_rounds)
  rounds = lambda depth: decimate.merge_rounds(film, (first, second), jnp.float32(depth), jax.random.key(0))
  alive = lambda g: np.asarray(g.opacity_logits) > decimate.DROPPED_LOGIT
  pairs_of_round_1 = np.asarray(second.members).ravel()
  assert np.all(alive(rounds(1.0))[pairs_of_round_1])  # what round 0 left
  assert alive(rounds(1.0)).sum() == film.num - len(np.asarray(first.members))
  assert alive(rounds(2.0)).sum() == film.num - len(np.asarray(first.members)) - len(np.asarray(second.members))
  assert alive(rounds(1.0)).sum() > alive(rounds(1.5)).sum() > alive(rounds(2.0)).sum()
  deep = rounds(2.0)
  opacity = lambda g: 1 / (1 + np.exp(-np.asarray(g.opacity_logits, np.float64)))
  mass = lambda g: opacity(g) * decimate.ellipsoid_area(np.exp(np.asarray(g.log_scales, np.float64)))
  np.testing.assert_allclose(np.sum(mass(deep)[alive(deep)]), np.sum(mass(film)), rtol=1e-4)
  colour = lambda g: np.sum((mass(g)[:, None] * np.asarray(g.sh[:, 0], np.float64))[alive(g)], axis=0)
  np.testing.assert_allclose(colour(deep), colour(film), rtol=1e-4, atol=1e-4)
  row = int(np.asarray(second.members)[0, 0])
  grad = np.asarray(jax.grad(lambda dc: decimate.merge_rounds(
      film.replace(sh=film.sh.at[:, 0].set(dc)), (first, second), jnp.float32(2.0),
      jax.random.key(0)).sh[row, 0, 0])(film.sh[:, 0]))[:, 0]
  assert np.sum(grad > 0) == 4 and np.isclose(grad.sum(), 1.0, rtol=1e-5)
  with pytest.raises(ValueError, match="merge_depth"):
    augment.Augmentation(merge_depth=2.5)
