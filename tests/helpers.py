"""Helpers several test files share: small random scenes, cameras, a bridge to the float64 reference
renderer, and a finiteness check over pytrees."""
from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax import Camera, Gaussians, RenderOptions
from conceal_jax.splat.camera import look_at
from tests.reference import render_reference

DATA_DIR = pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def make_gaussians(means, log_scales, quats, opacity_logits, sh, dtype=jnp.float32) -> Gaussians:
  arr = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype)
  return Gaussians(means=arr(means), log_scales=arr(log_scales), quats=arr(quats),
                   opacity_logits=arr(opacity_logits), sh=arr(sh))


def random_gaussians(seed: int, n: int, degree: int = 3, spread: float = 0.8, log_scale=(-2.3, -1.2),
                     dtype=jnp.float32) -> Gaussians:
  rng = np.random.default_rng(seed)
  return make_gaussians(
      means=rng.normal(size=(n, 3)) * spread,
      log_scales=rng.uniform(*log_scale, size=(n, 3)),
      quats=rng.normal(size=(n, 4)),
      opacity_logits=rng.uniform(-1.0, 3.0, size=n),
      sh=rng.normal(size=(n, (degree + 1) ** 2, 3)) * np.r_[1.0, np.full((degree + 1) ** 2 - 1, 0.3)][:, None],
      dtype=dtype)


def make_camera(width: int = 32, height: int = 24, eye=(0.0, -4.0, 1.0), fov: float = 0.7,
                dtype=jnp.float32) -> Camera:
  return Camera.from_fov(look_at(eye, (0.0, 0.0, 0.0)), fov, width, height, dtype=dtype)


def reference(g: Gaussians, cam: Camera, options: RenderOptions):
  """The float64 reference render of the same scene with the same options: (rgb, alpha, depth, ambiguous)."""
  return render_reference(g.means, g.log_scales, g.quats, g.opacity_logits, g.sh, cam.world_to_camera,
                          cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, degree=options.sh_degree,
                          background=options.background, tile_size=options.tile_size,
                          max_per_tile=options.max_per_tile, near=options.near,
                          antialiased=options.antialiased)


def assert_finite_tree(tree, what: str = "value"):
  for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
    if leaf is None:
      continue
    assert np.all(np.isfinite(np.asarray(leaf))), f"non-finite {what} at {jax.tree_util.keystr(path)}"


def set_field(config, field: str, value) -> None:
  """config.<field> = value for a dotted field such as 'conceal.lr.means_steps'."""
  *sections, key = field.split(".")
  for name in sections:
    config = config[name]
  config[key] = value


GOLDEN_FILE = pathlib.Path(__file__).parent / "data" / "conceal_step_golden.npz"


def sketch(leaf, index: int) -> np.ndarray:
  """[6] a float64 fingerprint of an array: its L2 norm, its largest magnitude, and its dot products with four
  fixed random vectors (seeded by the leaf's index and size), so that two arrays can be compared without
  storing either."""
  x = np.asarray(leaf, np.float64).ravel()
  r = np.random.default_rng([7, index, x.size]).standard_normal((4, x.size))
  return np.concatenate([[np.linalg.norm(x), np.abs(x).max(initial=0.0)], r @ x])


def golden_arrays(row: str) -> dict:
  """The pre-redesign conceal step's values for one row of tests/test_objective.GOLDEN_ROWS: loss, plus, minus;
  the sketches [leaves, 6] (see `sketch`) of student_grad, plus_grad, minus_grad and of the state after two
  steps (tree order); stats, a dict."""
  with np.load(GOLDEN_FILE) as z:
    flat = {name[len(row) + 1:]: z[name] for name in z.files if name.startswith(row + "/")}
  loss, plus, minus = flat["values"]
  return dict(loss=loss, plus=plus, minus=minus, stats={n[6:]: flat[n] for n in flat if n.startswith("stats/")},
              **{group: flat[group] for group in ("student_grad", "plus_grad", "minus_grad", "state")})
