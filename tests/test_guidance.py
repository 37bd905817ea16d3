"""Tests of the gradient-guided decoder step (per-layer cosine weights) on hand-made pytrees."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax.conceal import guidance

SIG = lambda s: 1.0 / (1.0 + np.exp(-s))


def tree(a_kernel, a_bias, b_kernel):
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  return {"a": {"kernel": f32(a_kernel), "bias": f32(a_bias)}, "b": {"kernel": f32(b_kernel)}}


def random_tree(rng, scale=1.0):
  return {"a": {"kernel": rng.normal(size=(3, 3, 2, 4)) * scale, "bias": rng.normal(size=4) * scale},
          "b": {"kernel": rng.normal(size=(5, 2)) * scale, "bias": rng.normal(size=2) * scale},
          "c": {"kernel": rng.normal(size=(7,)) * scale}}


def reference_weights(plus, minus, granularity):
  """float64 numpy weights, grouped by walking the dicts by hand."""
  out = {}
  for module in plus:
    groups = [list(plus[module])] if granularity == "layer" else [[leaf] for leaf in plus[module]]
    out[module] = {}
    for group in groups:
      p = np.concatenate([np.ravel(np.asarray(plus[module][k], np.float64)) for k in group])
      m = np.concatenate([np.ravel(np.asarray(minus[module][k], np.float64)) for k in group])
      w = SIG(p @ m / (np.linalg.norm(p) * np.linalg.norm(m)))
      out[module].update({k: w for k in group})
  return out


def weights_np(weights):
  return jax.tree.map(lambda w: float(w), weights)


def test_layer_groups():
  params = tree(np.ones((2, 2)), np.ones(2), np.ones(3))
  assert guidance.layer_groups(params, "layer") == {"a": {"bias": 0, "kernel": 0}, "b": {"kernel": 1}}
  assert guidance.layer_groups(params, "tensor") == {"a": {"bias": 0, "kernel": 1}, "b": {"kernel": 2}}
  with pytest.raises(ValueError, match="granularity"):
    guidance.layer_groups(params, "module")


@pytest.mark.parametrize("granularity", guidance.GRANULARITIES)
def test_parallel_opposite_orthogonal(granularity):
  plus = tree([[1.0, 2.0], [3.0, 4.0]], [1.0, -1.0], [1.0, 0.0, 0.0])
  for minus, expected in [(jax.tree.map(lambda x: 2.5 * x, plus), SIG(1.0)),
                          (jax.tree.map(lambda x: -0.1 * x, plus), SIG(-1.0))]:
    w = guidance.cosine_weights(plus, minus, granularity)
    for leaf in jax.tree.leaves(w):
      assert leaf.shape == ()
      assert float(leaf) == pytest.approx(expected, abs=1e-6)
  orthogonal = tree([[2.0, -1.0], [0.0, 0.0]], [1.0, 1.0], [0.0, 3.0, 0.0])
  w = guidance.cosine_weights(plus, orthogonal, granularity)
  for leaf in jax.tree.leaves(w):
    assert float(leaf) == pytest.approx(0.5, abs=1e-6)


def test_layer_and_tensor_differ_when_kernel_and_bias_disagree():
  plus = tree([[1.0, 0.0], [0.0, 0.0]], [1.0, 0.0], [1.0, 1.0, 1.0])
  minus = tree([[3.0, 0.0], [0.0, 0.0]], [-1.0, 0.0], [1.0, 1.0, 1.0])
  per_tensor = weights_np(guidance.cosine_weights(plus, minus, "tensor"))
  per_layer = weights_np(guidance.cosine_weights(plus, minus, "layer"))
  assert per_tensor["a"]["kernel"] == pytest.approx(SIG(1.0), abs=1e-6)
  assert per_tensor["a"]["bias"] == pytest.approx(SIG(-1.0), abs=1e-6)
  # Concatenated: <p, m> = 3 - 1 = 2, |p| = sqrt 2, |m| = sqrt 10.
  layer_cos = 2.0 / np.sqrt(20.0)
  assert per_layer["a"]["kernel"] == per_layer["a"]["bias"] == pytest.approx(SIG(layer_cos), abs=1e-6)
  assert per_layer["b"]["kernel"] == per_tensor["b"]["kernel"] == pytest.approx(SIG(1.0), abs=1e-6)


@pytest.mark.parametrize("granularity", guidance.GRANULARITIES)
@pytest.mark.parametrize("bad", [0.0, np.nan, np.inf, -np.inf])
def test_zero_and_nonfinite_give_half(granularity, bad):
  plus = tree([[1.0, 2.0], [3.0, 4.0]], [1.0, -1.0], [1.0, 2.0, 3.0])
  minus = tree(np.full((2, 2), bad), np.full(2, bad), [1.0, 2.0, 3.0])
  if not np.isfinite(bad):
    minus["a"]["kernel"] = minus["a"]["kernel"].at[0, 0].set(5.0)  # a single bad entry is enough
  for p, m in [(plus, minus), (minus, plus)]:
    w = weights_np(guidance.cosine_weights(p, m, granularity))
    assert w["a"]["kernel"] == w["a"]["bias"] == 0.5
    assert w["b"]["kernel"] == pytest.approx(SIG(1.0), abs=1e-6)  # other groups unaffected
    total, w2 = guidance.guided_decoder_gradient(p, m, 1.0, 1.0, granularity)
    assert all(np.isfinite(x) for x in jax.tree.leaves(weights_np(w2)))
    np.testing.assert_allclose(total["b"]["kernel"], SIG(1.0) * 2 * np.array([1.0, 2.0, 3.0]), rtol=1e-6)


def test_extreme_magnitudes_do_not_overflow():
  rng = np.random.default_rng(4)
  plus, minus = random_tree(rng), random_tree(rng)
  expected = reference_weights(plus, minus, "layer")
  for scale_p, scale_m in [(1e-30, 1e25), (1e25, 1e25), (1e-30, 1e-30)]:
    p = jax.tree.map(lambda x: jnp.asarray(x * scale_p, jnp.float32), plus)
    m = jax.tree.map(lambda x: jnp.asarray(x * scale_m, jnp.float32), minus)
    got = weights_np(guidance.cosine_weights(p, m, "layer"))
    jax.tree.map(lambda g, e: np.testing.assert_allclose(g, e, atol=1e-6), got, expected)


def test_scale_gradients_is_exact():
  rng = np.random.default_rng(5)
  grads = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), random_tree(rng))
  weights = jax.tree.map(lambda x: jnp.float32(rng.uniform(0.2, 0.8)), grads)
  scaled = guidance.scale_gradients(grads, weights)
  jax.tree.map(lambda s, g, w: np.testing.assert_array_equal(s, np.asarray(g) * np.float32(w)),
               scaled, grads, weights)


@pytest.mark.parametrize("granularity", guidance.GRANULARITIES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_float64_numpy(granularity, seed):
  rng = np.random.default_rng(seed)
  plus, minus = random_tree(rng), random_tree(rng)
  # Make some groups strongly (anti-)aligned so the weights span the sigmoid's range.
  minus["b"] = jax.tree.map(lambda x: -x + 0.1 * rng.normal(size=x.shape), plus["b"])
  expected = reference_weights(plus, minus, granularity)
  w_plus, w_minus = 1.0, 0.7
  f32 = lambda t: jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), t)
  step = jax.jit(functools.partial(guidance.guided_decoder_gradient, granularity=granularity))
  total, weights = step(f32(plus), f32(minus), w_plus, w_minus)
  jax.tree.map(lambda g, e: np.testing.assert_allclose(float(g), e, atol=1e-6), weights, expected)
  expected_total = jax.tree.map(lambda p, m, w: w * (w_plus * p + w_minus * m), plus, minus, expected)
  jax.tree.map(lambda g, e: np.testing.assert_allclose(g, e, rtol=1e-5, atol=1e-6), total, expected_total)


def test_jit_and_float64(x64):
  rng = np.random.default_rng(6)
  plus, minus = random_tree(rng), random_tree(rng)
  f64 = lambda t: jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), t)
  weights = jax.jit(guidance.cosine_weights, static_argnames="granularity")(f64(plus), f64(minus), "tensor")
  expected = reference_weights(plus, minus, "tensor")
  for got, want in zip(jax.tree.leaves(weights), jax.tree.leaves(expected)):
    assert got.dtype == jnp.float64
    np.testing.assert_allclose(float(got), want, rtol=1e-13)
