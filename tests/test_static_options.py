""""Simulate only the effects a scene calls for": static options shrink the traced program."""
from __future__ import annotations

import jax
import jax.extend
import numpy as np
import pytest

from conceal_jax import RenderOptions, render
from conceal_jax.splat.camera import Camera
from tests.helpers import make_camera, random_gaussians

N = 37  # an odd count, so that [N, k] shapes in the program are recognisable


def _jaxpr(options: RenderOptions):
  return jax.make_jaxpr(lambda g, c: render(g, c, options))(random_gaussians(0, N, degree=3), make_camera())


def _count_eqns(jaxpr) -> int:
  total = 0
  for eqn in jaxpr.eqns:
    total += 1
    for sub in jax.extend.core.jaxprs_in_params(eqn.params):
      total += _count_eqns(sub)
  return total


def _shapes(jaxpr) -> set[tuple[int, ...]]:
  found = set()
  for eqn in jaxpr.eqns:
    found |= {tuple(v.aval.shape) for v in eqn.outvars if hasattr(v.aval, "shape")}
    for sub in jax.extend.core.jaxprs_in_params(eqn.params):
      found |= _shapes(sub)
  return found


def _primitives(jaxpr) -> list[str]:
  names = []
  for eqn in jaxpr.eqns:
    names.append(eqn.primitive.name)
    for sub in jax.extend.core.jaxprs_in_params(eqn.params):
      names += _primitives(sub)
  return names


def test_sh_degree_zero_evaluates_no_basis_beyond_dc():
  programs = {d: _jaxpr(RenderOptions(sh_degree=d)).jaxpr for d in range(4)}
  counts = [_count_eqns(programs[d]) for d in range(4)]
  assert counts == sorted(counts) and len(set(counts)) == 4, counts
  for d in range(1, 4):
    assert (N, (d + 1) ** 2) in _shapes(programs[d])  # the [N, (d+1)^2] basis matrix
  assert not any(len(s) == 2 and s[0] == N and s[1] in (9, 16) for s in _shapes(programs[0]))


def test_antialiasing_compensation_only_when_asked():
  plain = _jaxpr(RenderOptions(antialiased=False)).jaxpr
  aa = _jaxpr(RenderOptions(antialiased=True)).jaxpr
  assert _count_eqns(aa) > _count_eqns(plain)
  assert _primitives(aa).count("sqrt") > _primitives(plain).count("sqrt")


def test_depth_composited_only_when_asked():
  plain = _jaxpr(RenderOptions(with_depth=False)).jaxpr
  with_depth = _jaxpr(RenderOptions(with_depth=True)).jaxpr
  assert _count_eqns(with_depth) > _count_eqns(plain)
  # Colour is composited as [tiles + 1, pixels, 3]; with depth the accumulated values gain a 4th channel.
  cam, tile = make_camera(), RenderOptions().tile_size
  accumulated = (-(-cam.width // tile) * -(-cam.height // tile) + 1, tile * tile, 4)
  assert accumulated in _shapes(with_depth)
  assert accumulated not in _shapes(plain)


def test_default_is_exact_and_binning_never_builds_tiles_by_gaussians():
  assert RenderOptions().max_per_tile is None and RenderOptions().exact
  cam = make_camera(80, 48)  # 15 tiles of 16 px: a count no other axis has
  for options in (RenderOptions(), RenderOptions(max_per_tile=64)):
    tiles = -(-cam.width // options.tile_size) * -(-cam.height // options.tile_size)
    jaxpr = jax.make_jaxpr(lambda g, c: render(g, c, options))(random_gaussians(0, N, degree=3), cam)
    shapes = _shapes(jaxpr.jaxpr)
    # The old binning masked all N splats per tile; pairs now come from per-splat rows and one sort.
    assert not any(tiles in s and N in s for s in shapes), sorted(s for s in shapes if N in s)


def test_pair_capacity_is_static_and_reported():
  options = RenderOptions(pair_capacity=2048)
  out = render(random_gaussians(0, N, degree=3), make_camera(), options)
  assert out.pair_capacity == 2048 and not bool(out.overflowed) and 0 < int(out.num_pairs) <= 2048
  assert (2048,) in _shapes(_jaxpr(options).jaxpr)  # the pair buffer


@pytest.mark.parametrize("kwargs", [dict(sh_degree=4), dict(tile_size=0), dict(max_per_tile=0),
                                    dict(background=(1, 1)), dict(near=0.0), dict(segment_size=0),
                                    dict(pair_capacity=0)])
def test_bad_options_are_rejected(kwargs):
  with pytest.raises(ValueError):
    RenderOptions(**kwargs)


def test_sh_degree_above_the_scene_renders_at_the_scenes_own():
  """A scene storing fewer SH bands than render.sh_degree asks for (a degree-1 PLY under a degree-3 config) renders
  as at its own degree, not an error (issue 41)."""
  scene = random_gaussians(0, 3, degree=1)
  np.testing.assert_array_equal(np.asarray(render(scene, make_camera(), RenderOptions(sh_degree=3)).rgb),
                                np.asarray(render(scene, make_camera(), RenderOptions(sh_degree=1)).rgb))


def test_camera_constructors_agree():
  # NeRF-Synthetic style: a camera 4 units out on -y looking at the origin, in OpenGL axes.
  c2w_gl = np.array([[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]], np.float64)
  gl = Camera.from_opengl_camera_to_world(c2w_gl, 50.0, 50.0, 16.0, 12.0, 32, 24)
  origin_cam = np.asarray(gl.world_to_camera) @ np.array([0, 0, 0, 1.0])
  assert origin_cam[2] == pytest.approx(4.0) and abs(origin_cam[0]) < 1e-6 and abs(origin_cam[1]) < 1e-6
  up_cam = np.asarray(gl.world_to_camera) @ np.array([0, 0, 1, 1.0])
  assert up_cam[1] < 0, "world up (+z) must be image up (-y in OpenCV)"
  fov = Camera.from_fov(np.asarray(gl.world_to_camera), 2 * np.arctan(16 / 50), 32, 24)
  assert float(fov.fx) == pytest.approx(50.0) and float(fov.cy) == pytest.approx(12.0)
  half = fov.rescale(2)
  assert (half.width, half.height) == (16, 12) and float(half.fx) == pytest.approx(25.0)
