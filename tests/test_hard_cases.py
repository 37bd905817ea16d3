"""Hard cases of REFERENCE s.4: finite values and gradients, and agreement with the float64 reference."""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax import Camera, RenderOptions, render, render_batch
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat import binning, projection, sh as sh_lib
from conceal_jax.splat import render as render_lib
from tests.helpers import assert_finite_tree, make_camera, make_gaussians, random_gaussians, reference

EXACT = RenderOptions(background=(0.2, 0.4, 0.6), with_depth=True)
# A camera at the origin looking down +z: depths equal the world z coordinate exactly.
AXIS_CAMERA = Camera.from_fov(np.eye(4), 0.8, 24, 20)


def one_gaussian(mean, log_scale=(-1.0, -1.0, -1.0), quat=(1.0, 0.0, 0.0, 0.0), logit=2.0,
                 dc=(0.5, 0.3, -0.2), degree=0, dtype=jnp.float32):
  sh = np.zeros((1, (degree + 1) ** 2, 3))
  sh[0, 0] = dc
  return make_gaussians([mean], [log_scale], [quat], [logit], sh, dtype=dtype)


def stack(parts):
  from conceal_jax.splat.gaussians import concatenate
  return concatenate(parts)


def padded(g, multiple=16):
  """g with Gaussians appended up to a multiple of `multiple`, each below the 1/255 opacity cut and so culled:
  every image is unchanged, and the small scenes of these cases share one compiled render, gradient and camera
  gradient (the cost of this module on a cold compilation cache is its compilations)."""
  extra = -g.num % multiple
  if extra == 0:
    return g
  sh = np.zeros((extra,) + g.sh.shape[1:])
  pad = make_gaussians(np.tile([0.0, 0.0, 3.0], (extra, 1)), np.full((extra, 3), -1.0),
                       np.tile([1.0, 0.0, 0.0, 0.0], (extra, 1)), np.full(extra, -30.0), sh, dtype=g.means.dtype)
  return stack([g, pad])


def check(g, cam, options=EXACT, atol=1e-5):
  """Renders `g` padded with culled Gaussians (`padded`), checks finiteness of values and gradients and agreement
  with the reference; returns the output."""
  g = padded(g)
  out = render(g, cam, options)
  assert_finite_tree(out, "value")
  weights = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, out.rgb.shape), out.rgb.dtype)

  def loss(g):
    o = render(g, cam, options)
    extra = jnp.sum(o.depth) * 1e-2 if o.depth is not None else 0.0
    return jnp.sum(o.rgb * weights) + jnp.sum(o.alpha) + extra

  assert_finite_tree(jax.grad(loss)(g), "gradient")
  assert_finite_tree(jax.grad(lambda c: loss_cam(g, c, options, weights))(cam), "camera gradient")
  rgb, alpha, _, ambiguous = reference(g, cam, options)
  defined = ~ambiguous  # where the stop test sits on 1e-4 within rounding, either branch is right
  np.testing.assert_allclose(np.asarray(out.rgb)[defined], rgb[defined], atol=atol, rtol=0)
  np.testing.assert_allclose(np.asarray(out.alpha)[defined], alpha[defined], atol=atol, rtol=0)
  return out


def loss_cam(g, cam, options, weights):
  return jnp.sum(render(g, cam, options).rgb * weights)


def background_image(cam, options):
  return np.broadcast_to(np.asarray(options.background), (cam.height, cam.width, 3))


@pytest.mark.parametrize("z", [-2.0, 0.0, 0.1, 0.19])
def test_behind_camera_at_zero_and_inside_near_plane_are_culled(z):
  g = stack([one_gaussian([0.1, 0.0, z]), one_gaussian([0.0, 0.0, 3.0], logit=0.0)])
  out = check(g, AXIS_CAMERA)
  alone = render(one_gaussian([0.0, 0.0, 3.0], logit=0.0), AXIS_CAMERA, EXACT)
  np.testing.assert_allclose(out.rgb, alone.rgb, atol=1e-6)


def test_far_outside_frustum_is_culled_and_has_clamped_jacobian():
  g = stack([one_gaussian([400.0, -300.0, 2.0]), one_gaussian([0.0, 0.0, 3.0])])
  check(g, AXIS_CAMERA)
  grads = jax.grad(lambda g: jnp.sum(render(g, AXIS_CAMERA, EXACT).rgb))(g)
  assert np.all(np.asarray(grads.means[0]) == 0) and np.all(np.asarray(grads.log_scales[0]) == 0)
  # Where x/z, y/z are clamped, the EWA Jacobian does not depend on x or y.
  p_cam = jnp.array([[400.0, -300.0, 2.0]])
  d_jac = jax.jacobian(lambda p: projection.perspective_jacobian(p, AXIS_CAMERA))(p_cam)
  assert np.all(np.asarray(d_jac)[..., :2] == 0)
  assert np.any(np.asarray(d_jac)[..., 2] != 0)


@pytest.mark.parametrize("c", [3.7, -0.5, 1e-3, 1e3])
def test_unnormalised_quaternions_render_invariant_under_scaling(c):
  g = random_gaussians(4, 12, degree=3)
  a = render(g, make_camera(), EXACT).rgb
  b = render(g.replace(quats=g.quats * c), make_camera(), EXACT).rgb
  np.testing.assert_allclose(a, b, atol=2e-6)
  check(g.replace(quats=g.quats * c), make_camera())


def test_zero_quaternion_is_identity_rotation_with_finite_gradient():
  anisotropic = dict(log_scale=(-0.5, -1.5, -1.0))
  zero = check(one_gaussian([0.2, 0.1, 3.0], quat=(0.0, 0.0, 0.0, 0.0), **anisotropic), AXIS_CAMERA)
  identity = render(one_gaussian([0.2, 0.1, 3.0], **anisotropic), AXIS_CAMERA, EXACT)
  np.testing.assert_allclose(zero.rgb, identity.rgb, atol=1e-6)


@pytest.mark.parametrize("log_scale", [
    (-np.inf, -1.0, -1.0),            # one zero scale axis: a flat disc
    (-np.inf, -np.inf, -np.inf),      # all scales zero: only the dilation remains
    (math.log(1e-4), 0.0, math.log(1e-4)),  # needle, axis ratio 1e4
])
def test_degenerate_scales(log_scale):
  degenerate = one_gaussian([0.1, 0.0, 3.0], log_scale=log_scale, quat=(0.9, 0.2, 0.3, 0.1))
  assert float(jnp.max(check(degenerate, AXIS_CAMERA, atol=2e-5).alpha)) > 0.1, "it must be drawn"
  check(stack([degenerate, one_gaussian([-0.3, 0.2, 4.0], logit=0.5)]), AXIS_CAMERA, atol=2e-5)


def test_huge_scales_and_gaussian_enclosing_the_camera():
  huge = one_gaussian([0.0, 0.0, 5.0], log_scale=(12.0, 12.0, 12.0), logit=-2.0)
  enclosing = one_gaussian([0.3, -0.2, 0.5], log_scale=(3.0, 3.0, 3.0), logit=-1.0)  # camera is inside
  out = check(stack([huge, enclosing, one_gaussian([0.0, 0.0, 3.0])]), AXIS_CAMERA)
  assert float(jnp.min(out.alpha)) > 0.1, "huge splats cover the whole view"


def test_isotropic_covariance_has_finite_radius_and_gradients():
  g = one_gaussian([0.0, 0.0, 3.0], log_scale=(-1.0, -1.0, -1.0))
  check(g, AXIS_CAMERA)
  # On the optical axis an isotropic Gaussian projects to a circle: mid^2 - det = 0 exactly.
  splats = projection.project(g, AXIS_CAMERA, 0, 0.2, False)
  assert int(splats.radii[0]) > 0
  conic = np.asarray(splats.conics[0])
  assert abs(conic[1]) < 1e-6 and abs(conic[0] - conic[2]) < 1e-6 * conic[0]


def test_edge_on_flat_gaussian_with_antialiasing():
  flat = one_gaussian([0.0, 0.0, 3.0], log_scale=(-0.5, -0.5, -np.inf), logit=3.0)
  # Rotate the disc 90 degrees about x: its normal lies in the image plane, we see it edge-on.
  edge_on = flat.replace(quats=jnp.array([[math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]]))
  options = RenderOptions(max_per_tile=None, antialiased=True, background=(1.0, 1.0, 1.0))
  out = check(edge_on, AXIS_CAMERA, options)
  splats = projection.project(edge_on, AXIS_CAMERA, 0, 0.2, True)
  expected = 0.005 / (1 + math.exp(-3.0))  # det of the undilated covariance is ~0: compensation floor
  assert float(splats.opacities[0]) == pytest.approx(expected, rel=0.05)
  assert float(jnp.max(out.alpha)) < 0.02


def test_sixteen_stacked_opaque_gaussians_stop_early():
  parts = [one_gaussian([0.0, 0.0, 2.0 + 0.1 * k], log_scale=(-0.3, -0.3, -0.3), logit=30.0,
                        dc=(k / 8.0 - 1.0, 0.5, 0.0)) for k in range(16)]
  out = check(stack(parts), AXIS_CAMERA)
  # Wherever two clamped 0.99 layers overlap, T reaches 1e-4 and the pixel stops: alpha <= 1 - 1e-4.
  assert 0.9998 <= float(jnp.max(out.alpha)) <= 1 - 1e-4 + 1e-6


def test_two_099_layers_on_the_transmittance_boundary():
  front = one_gaussian([0.0, 0.0, 2.0], log_scale=(1.0, 1.0, -2.0), logit=30.0, dc=(1.0, 0.0, 0.0))
  back = one_gaussian([0.0, 0.0, 3.0], log_scale=(1.0, 1.0, -2.0), logit=30.0, dc=(0.0, 1.0, 0.0))
  g = stack([front, back])
  out = render(g, AXIS_CAMERA, EXACT)
  assert_finite_tree(out)
  assert_finite_tree(jax.grad(lambda g: jnp.sum(render(g, AXIS_CAMERA, EXACT).rgb))(g), "gradient")
  # T after both layers is 0.01 * 0.01 = 1e-4, exactly the stop threshold: rounding may go either
  # way, so the pixel must be one of the two well-defined outcomes.
  c_front = np.maximum(np.array([1.0, 0.0, 0.0]) * sh_lib.SH_C0 + 0.5, 0)
  c_back = np.maximum(np.array([0.0, 1.0, 0.0]) * sh_lib.SH_C0 + 0.5, 0)
  bg = np.asarray(EXACT.background)
  one_layer = 0.99 * c_front + 0.01 * bg
  two_layers = 0.99 * c_front + 0.01 * 0.99 * c_back + 1e-4 * bg
  centre = np.asarray(out.rgb[10, 12], np.float64)
  assert min(np.max(np.abs(centre - one_layer)), np.max(np.abs(centre - two_layers))) < 1e-5


@pytest.mark.parametrize("offset", [-1e-5, 1e-5])
def test_alpha_just_under_and_over_the_skip_threshold(offset):
  logit = math.log((1 / 255 + offset) / (1 - (1 / 255 + offset)))
  z = 3.0  # placed so that it projects onto the centre of pixel (10, 12): its peak alpha is sampled
  half_pixel = 0.5 * z / float(AXIS_CAMERA.fx)
  g = one_gaussian([half_pixel, half_pixel, z], log_scale=(0.0, 0.0, 0.0), logit=logit)
  out = check(g, AXIS_CAMERA)
  assert (float(jnp.max(out.alpha)) > 0) == (offset > 0)


def test_gaussian_at_the_camera_centre():
  cam = make_camera()
  centre = camera_lib.camera_center(cam)
  g = stack([one_gaussian(np.asarray(centre), degree=3), one_gaussian([0.0, 0.0, 0.0], degree=3)])
  check(g, cam)
  # Its SH direction has norm 0: colour and gradients stay finite.
  fn = lambda sh, means: jnp.sum(sh_lib.sh_to_rgb(sh, means, centre, 3))
  assert_finite_tree(jax.grad(fn, argnums=(0, 1))(g.sh, g.means), "gradient")


def test_negative_sh_colour_is_clamped_with_zero_gradient():
  g = one_gaussian([0.0, 0.0, 3.0], dc=(-5.0, 0.5, -3.0), logit=3.0)
  out = check(g, AXIS_CAMERA)
  assert float(jnp.max(out.rgb[..., 0] - (1 - out.alpha) * EXACT.background[0])) < 1e-6
  grad = jax.grad(lambda g: jnp.sum(render(g, AXIS_CAMERA, EXACT).rgb))(g)
  assert float(grad.sh[0, 0, 0]) == 0.0 and float(grad.sh[0, 0, 1]) != 0.0


def test_exact_depth_ties_resolve_by_index():
  red = one_gaussian([0.0, 0.0, 3.0], dc=(2.0, -2.0, -2.0))
  green = one_gaussian([0.05, 0.0, 3.0], dc=(-2.0, 2.0, -2.0))
  first = check(stack([red, green]), AXIS_CAMERA)
  second = check(stack([green, red]), AXIS_CAMERA)
  assert float(first.rgb[10, 12, 0]) > float(first.rgb[10, 12, 1])   # index 0 (red) in front
  assert float(second.rgb[10, 12, 1]) > float(second.rgb[10, 12, 0])
  np.testing.assert_array_equal(first.rgb, render(stack([red, green]), AXIS_CAMERA, EXACT).rgb)


def test_no_gaussians_gives_background():
  from conceal_jax.splat.gaussians import Gaussians
  out = render(Gaussians.empty(), AXIS_CAMERA, EXACT)
  np.testing.assert_allclose(out.rgb, background_image(AXIS_CAMERA, EXACT), atol=1e-7)
  np.testing.assert_array_equal(out.alpha, 0)


def test_all_culled_gives_background():
  g = stack([one_gaussian([0.0, 0.0, -1.0]), one_gaussian([50.0, 0.0, 1.0]),
             one_gaussian([np.nan, 0.0, 3.0])])
  out = check(g, AXIS_CAMERA)
  np.testing.assert_allclose(out.rgb, background_image(AXIS_CAMERA, EXACT), atol=1e-7)


def test_non_finite_parameters_are_culled_with_finite_gradients():
  g = stack([one_gaussian([0.0, 0.0, 3.0], log_scale=(np.nan, 0.0, 0.0)),
             one_gaussian([0.0, 0.0, 3.0], logit=np.inf), one_gaussian([0.1, 0.0, 4.0])])
  alone = render(one_gaussian([0.1, 0.0, 4.0]), AXIS_CAMERA, EXACT)
  np.testing.assert_allclose(check(g, AXIS_CAMERA).rgb, alone.rgb, atol=1e-6)


def test_more_than_k_per_tile_reports_overflow_and_exact_mode_stays_exact():
  g = random_gaussians(7, 50, degree=0, spread=0.3)
  cam = make_camera(32, 32)
  truncated = render(g, cam, RenderOptions(max_per_tile=4))
  assert int(truncated.num_overflow_tiles) > 0
  assert int(render(g, cam, RenderOptions(max_per_tile=64)).num_overflow_tiles) == 0
  exact = check(g, cam, RenderOptions(max_per_tile=None))
  assert int(exact.num_overflow_tiles) == 0
  np.testing.assert_allclose(render(g, cam, RenderOptions(max_per_tile=64)).rgb, exact.rgb, atol=1e-6)


def test_jit_vmap_and_repeated_calls_are_deterministic():
  g = random_gaussians(8, 30, degree=2)
  cams = [make_camera(eye=eye) for eye in [(0, -4, 1), (3, -3, 0.5), (-4, 0.5, 1.5)]]
  options = RenderOptions(max_per_tile=32)
  singles = [render(g, c, options) for c in cams]
  batched = render_batch(g, camera_lib.stack(cams), options)
  for k, single in enumerate(singles):
    np.testing.assert_allclose(batched.rgb[k], single.rgb, atol=1e-6)
  again = render_batch(g, camera_lib.stack(cams), options)
  np.testing.assert_array_equal(again.rgb, batched.rgb)
  grad = lambda: jax.grad(lambda g: jnp.sum(render(g, cams[0], options).rgb))(g)
  jax.tree.map(np.testing.assert_array_equal, grad(), grad())


# --- Renderer v2: pair buffers of static capacity, culled pairs, degenerate image shapes ---------------


def test_capacity_overflow_is_reported_when_traced_and_regrown_eagerly():
  g = random_gaussians(7, 200, degree=0, spread=0.3)
  cam = make_camera(48, 40)
  small = RenderOptions(pair_capacity=1024, tile_size=4, background=(0.2, 0.4, 0.6))
  traces = render_lib._render._cache_size()
  eager = render(g, cam, small)  # an eager call never truncates: it re-runs with the grown capacity
  assert render_lib._render._cache_size() - traces == 2, "one trace at 1024 and one re-trace"
  needed = int(eager.num_pairs)
  assert needed > 1024 and not bool(eager.overflowed) and eager.pair_capacity >= needed
  rgb, alpha, _, ambiguous = reference(g, cam, small)
  assert not ambiguous.any()
  np.testing.assert_allclose(eager.rgb, rgb, atol=1e-5, rtol=0)
  np.testing.assert_allclose(eager.alpha, alpha, atol=1e-5, rtol=0)
  # Traced inside a caller's jit it cannot re-run: it reports the overflow, the caller grows the options.
  traced = jax.jit(lambda g: render(g, cam, small))(g)
  assert bool(traced.overflowed) and int(traced.num_pairs) == needed and traced.pair_capacity == 1024
  assert float(np.max(np.abs(np.asarray(traced.rgb) - rgb))) > 1e-2, "the truncated image differs"
  grown = render_lib.grow_capacity(small, traced.num_pairs)
  assert grown == dataclasses.replace(small, pair_capacity=eager.pair_capacity)
  # Gradients of an eager call use the grown capacity too.
  assert_finite_tree(jax.grad(lambda g: jnp.sum(render(g, cam, small).rgb))(g), "gradient")
  # A batch grows to what its largest view needs.
  cams = camera_lib.stack([cam, make_camera(48, 40, eye=(0.5, -3.0, 0.5))])
  batch = render_batch(g, cams, small)
  assert not np.any(np.asarray(batch.overflowed)) and batch.pair_capacity >= int(np.max(batch.num_pairs))
  np.testing.assert_allclose(batch.rgb[0], eager.rgb, atol=1e-6)


def _points_in_pixel_box(rng, n, box, depth=(2.0, 6.0), cam=AXIS_CAMERA):
  """n world points on the axis camera that project inside the pixel box (u0, u1, v0, v1)."""
  u = rng.uniform(box[0], box[1], n)
  v = rng.uniform(box[2], box[3], n)
  z = rng.uniform(*depth, n)
  x = (u - float(cam.cx)) / float(cam.fx) * z
  y = (v - float(cam.cy)) / float(cam.fy) * z
  return np.stack([x, y, z], -1)


def _small_splats(rng, means, logit_range=(-4.0, -1.0), log_scale=-4.0):
  n = means.shape[0]
  sh = np.zeros((n, 1, 3))
  sh[:, 0] = rng.normal(size=(n, 3))
  return make_gaussians(means, np.full((n, 3), log_scale), rng.normal(size=(n, 4)),
                        rng.uniform(*logit_range, n), sh)


def test_one_tile_touched_by_5000_splats():
  rng = np.random.default_rng(11)
  cam = Camera.from_fov(np.eye(4), 0.8, 32, 32)
  crowd = _small_splats(rng, _points_in_pixel_box(rng, 5000, (3, 13, 3, 13), cam=cam), logit_range=(-4, -2.5),
                        log_scale=-2.5)
  g = stack([crowd, one_gaussian([0.3, 0.3, 8.0], log_scale=(-0.5, -0.5, -0.5))])
  out = check(g, cam)
  assert int(out.num_pairs) >= 5000
  assert float(jnp.max(out.alpha[:16, :16])) > 0.9


def test_every_splat_in_one_tile():
  rng = np.random.default_rng(12)
  cam = Camera.from_fov(np.eye(4), 0.8, 64, 48)
  options = dataclasses.replace(EXACT, tile_size=8)
  g = _small_splats(rng, _points_in_pixel_box(rng, 400, (27, 29, 19, 21), depth=(4.0, 6.0), cam=cam),
                    logit_range=(-3, 1))
  out = check(g, cam, options)
  assert int(out.num_pairs) == 400, "each splat stays inside tile (3, 2)"
  alpha = np.asarray(out.alpha)
  assert alpha[16:24, 24:32].max() > 0.5 and alpha[:16].max() == 0 and alpha[:, :24].max() == 0


@pytest.mark.parametrize("size", [(1, 1), pytest.param((1, 1000), marks=pytest.mark.slow),
                                  pytest.param((1000, 3), marks=pytest.mark.slow)])
def test_degenerate_image_sizes(size):
  width, height = size
  focal = max(width, height) / (2 * math.tan(0.35))
  w2c = camera_lib.look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.0))
  cam = Camera.from_intrinsics(w2c, focal, focal, width / 2, height / 2, width, height)
  g = random_gaussians(9, 30, degree=1, log_scale=(-1.5, -0.8) if size == (1, 1) else (-2.3, -1.2))
  out = check(g, cam)
  assert out.rgb.shape == (height, width, 3)
  assert float(jnp.max(out.alpha)) > 0.1, "the image must show something"


@pytest.mark.parametrize("relative", [-1e-3, 1e-3])
def test_opacities_just_below_and_above_the_cull_threshold(relative):
  rng = np.random.default_rng(13)
  opacity = (1 / 255) * (1 + relative)
  logit = math.log(opacity / (1 - opacity))
  half_pixel = 0.5 * 3.0 / float(AXIS_CAMERA.fx)  # peak on the centre of pixel (10, 12)
  faint = [one_gaussian([half_pixel, half_pixel, 3.0], log_scale=(0.0, 0.0, 0.0), logit=logit)]
  faint += [one_gaussian(list(p), log_scale=(-1.0, -1.0, -1.0), logit=logit)
            for p in _points_in_pixel_box(rng, 5, (2, 22, 2, 18), depth=(2.0, 4.0))]
  behind = one_gaussian([0.2, -0.1, 6.0], log_scale=(-0.3, -0.3, -0.3), logit=0.0)
  out = check(stack(faint + [behind]), AXIS_CAMERA)
  alone = render(behind, AXIS_CAMERA, EXACT)
  changed = float(jnp.max(jnp.abs(out.rgb - alone.rgb)))
  assert (changed > 0) == (relative > 0), "faint splats below 1/255 are culled, above it they show"


@pytest.mark.parametrize("n", [1, 2, 300, 70_000])
def test_depth_order_is_the_stable_argsort(n):
  # Many exact ties (depths on a coarse grid) and culled splats; 70k splats need three radix passes.
  rng = np.random.default_rng(n)
  depths = jnp.asarray(rng.integers(1, 50, n).astype(np.float32) * 0.125)
  radii = jnp.asarray(rng.integers(0, 3, n).astype(np.int32))
  expected = np.argsort(np.where(np.asarray(radii) > 0, np.asarray(depths), np.inf), kind="stable")
  np.testing.assert_array_equal(np.asarray(binning.depth_order(depths, radii)), expected)
