"""Registration of a suspect Gaussian scene onto the owner's copy: the similarity x -> s R x + t that maps the
owner's scene onto the suspect's, from the Gaussians alone.

A shared scene may have been turned, moved and resized by any amount, its Gaussians reordered, pruned or
decimated, densified, re-quantised or slightly retrained; there are no correspondences. Registration runs
in two stages, both on host float64:

1. Global candidates that do not depend on the unknown rotation. (a) Colour clusters: the DC colour of a
   Gaussian is invariant under similarity transforms, so k-means clusters of the owner's colours, found
   again in the suspect by nearest colour centre, give corresponding centroids; a similarity fitted to
   every triple of cluster centroids (RANSAC over the triples) and to all of them proposes transforms
   for any rotation and scale. (b) Principal axes: centroid, RMS radius and the covariance's eigenvectors
   of both scenes, with the 24 proper signed permutations of the axes (the eigenvectors' signs and order
   are ambiguous), and turns about an axis whose two eigenvalues are close (a near-symmetric scene).
2. Each candidate is scored by the trimmed mean nearest-neighbour distance of the suspect's Gaussians,
   mapped back into the owner's frame, in a joint space of position and colour; the best few are refined
   by trimmed ICP with scale (Umeyama's closed form on the closest fraction of nearest-neighbour pairs),
   and the one with the smallest trimmed residual wins; it is refined on more Gaussians, with a tight and
   then a loose trim.

The residual reported is the trimmed RMS nearest-neighbour distance of the suspect's Gaussians to the
owner's, in the owner's frame, relative to the owner scene's RMS radius.
"""
from __future__ import annotations

import dataclasses
import itertools

import numpy as np
from scipy.spatial import cKDTree

from conceal_jax.gs.similarity import Similarity, apply_to_points, inverse, rotation_from_axis_angle
from conceal_jax.splat import sh as sh_lib
from conceal_jax.splat.gaussians import Gaussians

# Fewest Gaussians a scene needs for a similarity to be determined robustly.
MIN_GAUSSIANS = 16
# Weight of RGB colour (in [0, 1]) against position (in owner radii) in the nearest-neighbour space: a
# colour difference of 0.1 counts as a position difference of 0.5% of the radius, enough to tell apart
# parts of a symmetric shape that differ in colour, little enough that re-quantised colours still match.
COLOUR_WEIGHT = 0.05
# Fraction of nearest-neighbour pairs, the closest ones, that scoring and the ICP fits use: the rest may
# be Gaussians the other scene lacks (densified, pruned, floaters).
KEEP_FRACTION = 0.7
# The looser trim of the final ICP stage.
_LOOSE_KEEP_FRACTION = 0.9
# A suspect Gaussian within this many owner radii of an owner Gaussian counts as matched; the final
# stages are compared by their mean squared distance truncated here.
MATCH_DISTANCE = 0.02
# Two principal variances closer than this ratio leave the axes between them undetermined.
_DEGENERATE_RATIO = 1.5
# Turns about a principal axis tried when its two companions are undetermined.
_AXIS_TURNS = 12
# Colour clusters, and the fewest members a cluster needs in each scene to propose a centroid.
_CLUSTERS = 12
_MIN_CLUSTER = 8
# Candidates are scored with nearest-neighbour distances capped at this many owner radii.
_SCORE_BOUND = 0.25


@dataclasses.dataclass(frozen=True)
class Registration:
  """similarity: owner -> suspect. residual: trimmed RMS nearest-neighbour distance of the suspect's
  Gaussians to the owner's (owner frame) / owner RMS radius. matched_fraction: fraction of the suspect's
  Gaussians within MATCH_DISTANCE owner radii of an owner Gaussian. owner_radius: that radius."""
  similarity: Similarity
  residual: float
  matched_fraction: float
  owner_radius: float


def scene_points(gaussians: Gaussians) -> tuple[np.ndarray, np.ndarray]:
  """[N, 3] float64 centres and [N, 3] DC colours (the colour seen from every side, clipped to [0, 1]).
  ValueError for fewer than MIN_GAUSSIANS Gaussians or non-finite centres or colours."""
  means = np.asarray(gaussians.means, np.float64)
  colours = np.clip(np.asarray(gaussians.sh, np.float64)[:, 0, :] * sh_lib.SH_C0 + 0.5, 0.0, 1.0)
  if means.shape[0] < MIN_GAUSSIANS:
    raise ValueError(f"registration needs at least {MIN_GAUSSIANS} Gaussians, got {means.shape[0]}")
  if not (np.all(np.isfinite(means)) and np.all(np.isfinite(np.asarray(gaussians.sh)[:, 0]))):
    raise ValueError("registration needs finite means and SH DC coefficients")
  return means, colours


def umeyama(source: np.ndarray, target: np.ndarray) -> Similarity:
  """The least-squares similarity with target ~ s R source + t (Umeyama 1991) for [M, 3] pairs, M >= 3.
  Reflections are excluded (det R = +1)."""
  mu_s, mu_t = source.mean(0), target.mean(0)
  src, tgt = source - mu_s, target - mu_t
  cov = tgt.T @ src / len(source)
  u, d, vt = np.linalg.svd(cov)
  sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
  rotation = u @ sign @ vt
  variance = np.mean(np.sum(src * src, axis=1))
  scale = float(np.sum(d * np.diag(sign)) / variance) if variance > 0 else 1.0
  scale = scale if scale > 0 else 1.0
  return Similarity(rotation, mu_t - scale * rotation @ mu_s, scale)


def principal_frame(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
  """[N, 3] -> centroid [3], RMS radius, principal axes [3, 3] (columns, variance descending, right-handed)
  and the variances [3]."""
  centre = points.mean(0)
  centred = points - centre
  variances, axes = np.linalg.eigh(centred.T @ centred / len(points))
  variances, axes = variances[::-1], axes[:, ::-1]
  if np.linalg.det(axes) < 0:
    axes[:, 2] = -axes[:, 2]
  return centre, float(np.sqrt(np.sum(variances))), axes, variances


def proper_signed_permutations() -> np.ndarray:
  """[24, 3, 3] the rotations that map coordinate axes onto coordinate axes (the cube's symmetries)."""
  out = []
  for perm in itertools.permutations(range(3)):
    for signs in itertools.product((1.0, -1.0), repeat=3):
      m = np.zeros((3, 3))
      m[np.arange(3), perm] = signs
      if np.linalg.det(m) > 0:
        out.append(m)
  return np.stack(out)


def principal_axes_candidates(owner: np.ndarray, suspect: np.ndarray) -> list[Similarity]:
  """Similarities that map the owner's principal frame onto the suspect's, for every proper signed
  permutation of the axes, and for axes whose variances are within _DEGENERATE_RATIO of a neighbour's,
  every turn by 2 pi k / _AXIS_TURNS about the distinct axis (about each axis if all three are close)."""
  c_o, r_o, a_o, v_o = principal_frame(owner)
  c_s, r_s, a_s, _ = principal_frame(suspect)
  scale = r_s / r_o
  close = [v_o[i] < _DEGENERATE_RATIO * v_o[i + 1] for i in range(2)]
  turn_axes = {(True, True): [0, 1, 2], (True, False): [2], (False, True): [0], (False, False): []}[tuple(close)]
  turns = [np.eye(3)] + [rotation_from_axis_angle(np.eye(3)[axis], 2 * np.pi * k / _AXIS_TURNS)
                         for axis in turn_axes for k in range(1, _AXIS_TURNS)]
  # Signed permutations and turns overlap (a quarter turn is both): each distinct rotation is tried once.
  in_frame = {np.round(perm @ turn, 6).tobytes(): perm @ turn for perm in proper_signed_permutations()
              for turn in turns}
  out = []
  for relative in in_frame.values():
    rotation = a_s @ relative @ a_o.T
    out.append(Similarity(rotation, c_s - scale * rotation @ c_o, scale))
  return out


def colour_clusters(colours: np.ndarray, rng: np.random.Generator, k: int = _CLUSTERS,
                    iterations: int = 20) -> np.ndarray:
  """[k', 3] k-means centres of [N, 3] colours (k' <= k: empty clusters dropped), seeded by k-means++."""
  sample = colours[rng.choice(len(colours), min(len(colours), 4000), replace=False)]
  centres = [sample[rng.integers(len(sample))]]
  for _ in range(1, k):
    d2 = np.min(np.sum((sample[:, None] - np.asarray(centres)[None]) ** 2, -1), 1)
    if d2.sum() <= 0:
      break
    centres.append(sample[rng.choice(len(sample), p=d2 / d2.sum())])
  centres = np.asarray(centres)
  for _ in range(iterations):
    label = np.argmin(np.sum((sample[:, None] - centres[None]) ** 2, -1), 1)
    centres = np.stack([sample[label == j].mean(0) for j in range(len(centres)) if np.any(label == j)])
  return centres


def colour_cluster_candidates(owner: np.ndarray, owner_colours: np.ndarray, suspect: np.ndarray,
                              suspect_colours: np.ndarray, rng: np.random.Generator,
                              max_candidates: int = 16) -> list[Similarity]:
  """Similarities fitted to corresponding colour-cluster centroids: to all of them, and to each triple
  (RANSAC), keeping the triples' fits with most centroids within 10% of the suspect's radius."""
  centres = colour_clusters(owner_colours, rng)
  label_o = np.argmin(np.sum((owner_colours[:, None] - centres[None]) ** 2, -1), 1)
  label_s = np.argmin(np.sum((suspect_colours[:, None] - centres[None]) ** 2, -1), 1)
  kept = [j for j in range(len(centres))
          if np.sum(label_o == j) >= _MIN_CLUSTER and np.sum(label_s == j) >= _MIN_CLUSTER]
  if len(kept) < 3:
    return []
  c_o = np.stack([owner[label_o == j].mean(0) for j in kept])
  c_s = np.stack([suspect[label_s == j].mean(0) for j in kept])
  tolerance = 0.1 * principal_frame(suspect)[1]
  fits = [umeyama(c_o, c_s)]
  scored = []
  for triple in itertools.combinations(range(len(kept)), 3):
    idx = list(triple)
    if np.linalg.matrix_rank(c_o[idx] - c_o[idx].mean(0), tol=1e-9 * (1 + np.abs(c_o).max())) < 2:
      continue
    fit = umeyama(c_o[idx], c_s[idx])
    inliers = np.linalg.norm(apply_to_points(fit, c_o) - c_s, axis=1) < tolerance
    scored.append((int(inliers.sum()), fit, inliers))
  scored.sort(key=lambda item: -item[0])
  for count, fit, inliers in scored[:max_candidates]:
    fits.append(umeyama(c_o[inliers], c_s[inliers]) if count >= 3 else fit)
  return fits


def joint_features(points: np.ndarray, colours: np.ndarray, radius: float) -> np.ndarray:
  """[N, 6] nearest-neighbour space: position in owner radii, colour times COLOUR_WEIGHT."""
  return np.concatenate([points / radius, COLOUR_WEIGHT * colours], axis=1)


def trimmed_distances(tree: cKDTree, owner_radius: float, suspect: np.ndarray, suspect_colours: np.ndarray,
                      owner_to_suspect: Similarity, bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
  """Joint-space distances [M] of the suspect's points, mapped into the owner's frame, to their nearest
  owner Gaussian, and that Gaussian's index [M]. Distances beyond `bound` are returned as `bound` (the
  search stops there, which makes scoring a far-off candidate cheap); their indices are meaningless."""
  back = apply_to_points(inverse(owner_to_suspect), suspect)
  distances, index = tree.query(joint_features(back, suspect_colours, owner_radius), distance_upper_bound=bound)
  return np.minimum(distances, bound), np.minimum(index, tree.n - 1)


def trimmed_mean_square(distances: np.ndarray, keep: float = KEEP_FRACTION) -> float:
  """Mean square of the closest `keep` fraction of [M] distances: what trimmed ICP decreases at every step
  (Chetverikov et al. 2002), since Umeyama minimises it over the kept pairs and re-pairing and re-trimming
  can only lower it."""
  count = max(1, int(round(keep * len(distances))))
  return float(np.mean(np.partition(distances, count - 1)[:count] ** 2))


def icp(tree: cKDTree, owner: np.ndarray, owner_radius: float, suspect: np.ndarray, suspect_colours: np.ndarray,
        start: Similarity, iterations: int = 30, keep: float = KEEP_FRACTION, tolerance: float = 1e-6
        ) -> tuple[Similarity, float]:
  """Trimmed ICP with scale from `start`: pair each suspect point with its nearest owner Gaussian (joint
  space), fit owner -> suspect by Umeyama on the closest `keep` fraction of pairs, repeat until the trimmed
  mean square stops falling by more than `tolerance` times its value. Returns the fit and that value."""
  current = start
  distances, index = trimmed_distances(tree, owner_radius, suspect, suspect_colours, current)
  score = trimmed_mean_square(distances, keep)
  count = max(3, int(round(keep * len(distances))))
  for _ in range(iterations):
    closest = np.argpartition(distances, count - 1)[:count]
    fit = umeyama(owner[index[closest]], suspect[closest])
    new_distances, new_index = trimmed_distances(tree, owner_radius, suspect, suspect_colours, fit)
    new_score = trimmed_mean_square(new_distances, keep)
    if new_score < score:
      current, distances, index = fit, new_distances, new_index
    if new_score > score * (1 - tolerance):
      score = min(score, new_score)
      break
    score = new_score
  return current, score


def register(owner: Gaussians, suspect: Gaussians, *, score_points: int = 800, icp_points: int = 3000,
             refine_points: int = 20000, refine_candidates: int = 6, seed: int = 0) -> Registration:
  """The similarity owner -> suspect (see the module docstring) and its residual.

  Random subsets of the suspect's Gaussians: score_points score every candidate, icp_points refine the
  best refine_candidates of them, refine_points refine the winner.
  Deterministic for a given seed. ValueError for scenes too small or not finite."""
  rng = np.random.default_rng(seed)
  owner_points, owner_colours = scene_points(owner)
  suspect_points, suspect_colours = scene_points(suspect)
  owner_radius = principal_frame(owner_points)[1]
  if not owner_radius > 0:
    raise ValueError("the owner's Gaussians all sit at one point: no transform is determined")
  tree = cKDTree(joint_features(owner_points, owner_colours, owner_radius))
  subset = lambda count: rng.choice(len(suspect_points), min(count, len(suspect_points)), replace=False)

  candidates = (colour_cluster_candidates(owner_points, owner_colours, suspect_points, suspect_colours, rng)
                + principal_axes_candidates(owner_points, suspect_points))
  few = subset(score_points)
  scores = [trimmed_mean_square(trimmed_distances(tree, owner_radius, suspect_points[few], suspect_colours[few], c,
                                           bound=_SCORE_BOUND)[0]) for c in candidates]
  some = subset(icp_points)
  refined = [icp(tree, owner_points, owner_radius, suspect_points[some], suspect_colours[some], candidates[i])
             for i in np.argsort(scores)[:refine_candidates]]
  best = min(refined, key=lambda item: item[1])[0]

  # Trimming at KEEP_FRACTION tolerates Gaussians the owner lacks but can settle on a slightly shrunk fit
  # that pairs most points with wrong close neighbours; continuing with a looser trim releases it. The
  # stage whose truncated error is smaller wins.
  many = subset(refine_points)
  stages = []
  for keep in (KEEP_FRACTION, _LOOSE_KEEP_FRACTION):
    best, _ = icp(tree, owner_points, owner_radius, suspect_points[many], suspect_colours[many], best,
                  iterations=100, keep=keep)
    distances, _ = trimmed_distances(tree, owner_radius, suspect_points[many], suspect_colours[many], best)
    stages.append((float(np.mean(np.minimum(distances, MATCH_DISTANCE)**2)), best))
  best = min(stages, key=lambda item: item[0])[1]
  return _report(owner_points, owner_radius, suspect_points[many], best)


def _report(owner_points: np.ndarray, owner_radius: float, suspect_points: np.ndarray,
            similarity: Similarity) -> Registration:
  """The Registration of `similarity`, with position-only nearest-neighbour distances."""
  back = apply_to_points(inverse(similarity), suspect_points)
  distances, _ = cKDTree(owner_points).query(back)
  relative = distances / owner_radius
  count = max(1, int(round(KEEP_FRACTION * len(relative))))
  trimmed = np.partition(relative, count - 1)[:count]
  return Registration(similarity=similarity, residual=float(np.sqrt(np.mean(trimmed**2))),
                      matched_fraction=float(np.mean(relative < MATCH_DISTANCE)), owner_radius=owner_radius)
