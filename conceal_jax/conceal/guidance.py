"""Gradient-guided decoder update of ConcealGS (arXiv:2501.03605, Sec. 2.3, eqs. 6 and 7) on gradient pytrees.

For every decoder layer i, s_i is the cosine between that layer's gradients of L_d^+ (Eq. 5, reveal the
hidden image on the check view) and L_d^- (Eq. 4, identity on normal views); w_i = sigmoid(s_i), in
[0.27, 0.73], scales the layer's gradient of the total loss. Layers where the two tasks pull the same way
are updated almost fully, layers where they conflict are damped.

What counts as a layer is the `granularity`:
  "layer": the paper's f_i, one Flax module; its leaves (a conv's kernel and bias) share one weight,
    computed from the cosine of their concatenated gradients.
  "tensor": the choice of the authors' released code (github.com/zxk1212/ConcealGS): every parameter tensor
    weighted on its own.
All functions are jittable with `granularity` static; grouping depends only on the tree structure.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

GRANULARITIES = ("layer", "tensor")

PyTree = Any


def layer_groups(params: PyTree, granularity: str = "layer") -> PyTree:
  """A pytree shaped like `params` whose leaves are int group ids 0 .. G-1, numbered in leaf order.

  "layer": leaves with the same parent path share an id (all parameters of one module);
  "tensor": every leaf has its own id.
  """
  if granularity not in GRANULARITIES:
    raise ValueError(f"granularity must be one of {GRANULARITIES}, got {granularity!r}")
  leaves_with_paths, treedef = jax.tree_util.tree_flatten_with_path(params)
  ids: dict[str, int] = {}
  group_of_leaf = []
  for path, _ in leaves_with_paths:
    key = jax.tree_util.keystr(path[:-1] if granularity == "layer" else path)
    group_of_leaf.append(ids.setdefault(key, len(ids)))
  return jax.tree_util.tree_unflatten(treedef, group_of_leaf)


def _group_cosine(a_leaves: list[jax.Array], b_leaves: list[jax.Array]) -> jax.Array:
  """Scalar cosine of the concatenations of a_leaves and b_leaves; 0 where it is undefined.

  A zero gradient has no direction, and a non-finite one (overflow in the loss, a NaN render) has none
  we can trust; cos = 0 gives w = 0.5, the weight of unrelated (orthogonal) gradients, instead of a NaN
  that would poison the Adam moments for good. torch's eps-clamped cosine_similarity, as in the released
  code, also gives 0 for a zero gradient.
  """
  up = lambda x: x.astype(jnp.promote_types(x.dtype, jnp.float32))
  a_leaves, b_leaves = [up(x) for x in a_leaves], [up(x) for x in b_leaves]
  finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in a_leaves + b_leaves]))
  # The cosine is scale invariant: dividing by the largest entry keeps the sums of squares of very
  # small or very large gradients from under- or overflowing.
  scale_a = jnp.max(jnp.stack([jnp.max(jnp.abs(x), initial=0.0) for x in a_leaves]))
  scale_b = jnp.max(jnp.stack([jnp.max(jnp.abs(x), initial=0.0) for x in b_leaves]))
  defined = finite & (scale_a > 0) & (scale_b > 0)
  scale_a = jnp.where(defined, scale_a, 1.0)
  scale_b = jnp.where(defined, scale_b, 1.0)
  a_leaves = [x / scale_a for x in a_leaves]
  b_leaves = [x / scale_b for x in b_leaves]
  # Elementwise products, not jnp.vdot: a dot may run in reduced (TF32) precision on GPUs.
  dot = sum(jnp.sum(x * y) for x, y in zip(a_leaves, b_leaves))
  norm_a = jnp.sqrt(sum(jnp.sum(x * x) for x in a_leaves))
  norm_b = jnp.sqrt(sum(jnp.sum(y * y) for y in b_leaves))
  cos = dot / jnp.where(defined, norm_a * norm_b, 1.0)
  return jnp.where(defined, jnp.clip(cos, -1.0, 1.0), 0.0)


def cosine_weights(grad_plus: PyTree, grad_minus: PyTree, granularity: str = "layer") -> PyTree:
  """w_i = sigmoid(cos(grad_i L_d^+, grad_i L_d^-)) of Eq. 6, as a pytree shaped like the gradients.

  grad_plus, grad_minus: decoder gradients of L_d^+ and L_d^- (same structure).
  Returns one float scalar per leaf, equal within a group of `layer_groups`; always finite (0.5 where the
  cosine is undefined, see `_group_cosine`).
  """
  groups = jax.tree.leaves(layer_groups(grad_plus, granularity))
  plus, treedef = jax.tree.flatten(grad_plus)
  minus = treedef.flatten_up_to(grad_minus)
  members: dict[int, list[int]] = {}
  for leaf_index, group in enumerate(groups):
    members.setdefault(group, []).append(leaf_index)
  weights = {group: jax.nn.sigmoid(_group_cosine([plus[i] for i in idx], [minus[i] for i in idx]))
             for group, idx in members.items()}
  return jax.tree.unflatten(treedef, [weights[group] for group in groups])


def scale_gradients(grads: PyTree, weights: PyTree) -> PyTree:
  """Eq. 7: every gradient leaf times its scalar weight (in the leaf's dtype)."""
  return jax.tree.map(lambda g, w: g * jnp.asarray(w, g.dtype), grads, weights)


def guided_decoder_gradient(grad_plus: PyTree, grad_minus: PyTree, weight_plus: float | jax.Array,
                            weight_minus: float | jax.Array,
                            granularity: str = "layer") -> tuple[PyTree, PyTree]:
  """(guided decoder gradient of the total loss, weights of Eq. 6).

  The total loss's decoder gradient is weight_plus * grad_plus + weight_minus * grad_minus: L_kd reads
  only the Gaussians, so the two backward passes that the cosines need already give it (no third one).
  It is then scaled layer by layer (Eq. 7).
  """
  total = jax.tree.map(lambda p, m: weight_plus * p + weight_minus * m, grad_plus, grad_minus)
  weights = cosine_weights(grad_plus, grad_minus, granularity)
  return scale_gradients(total, weights), weights
