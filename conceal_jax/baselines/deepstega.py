"""DeepStega (Baluja 2017, NeurIPS, "Hiding Images in Plain Sight: Deep Steganography", Sec. 2), the
ConcealGS paper's "DeepStega" baseline: three convolutional networks that hide a secret image in a cover.

  preparation network  secret [B, H, W, 3] -> features [B, H, W, 3 * width]
  hiding network       cover, prepared secret -> container C' [B, H, W, 3]
  reveal network       container -> secret S' [B, H, W, 3]

Each layer is Baluja's: three parallel convolutions (3x3, 4x4, 5x5, `width` filters each) concatenated,
ReLU; a 1x1 convolution gives the 3-channel outputs. Every network is fully convolutional, so networks
trained on small crops hide and reveal on whole views of any size. Training is in deepstega_train.py.
"""
from __future__ import annotations

import dataclasses
import functools

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
from flax import linen as nn

from conceal_jax.baselines import containers as containers_lib
from conceal_jax.conceal import reveal as reveal_lib
from conceal_jax.core import fileio, settings as settings_lib

KERNEL_SIZES = (3, 4, 5)
# Views per forward pass when hiding in or revealing from whole views: bounds the activations' memory.
VIEW_CHUNK = 4


@dataclasses.dataclass(frozen=True)
class Architecture:
  """Sizes of the three networks (hashable: static under jit): `width` filters per kernel size in every
  layer, and the layers of the preparation, hiding and reveal networks (Baluja: 50 filters; 2, 5, 5).

  cover_skip: the hiding network outputs the change to the cover (C' = C + net) rather than C' itself (Baluja).
  Not Baluja's design: it spares the network learning to copy the cover through its ReLU layers, so that
  networks trained briefly on this CPU hide well; a stronger baseline only makes its failure after 3D-GS
  training more telling."""
  width: int = 16
  prep_depth: int = 2
  hide_depth: int = 4
  reveal_depth: int = 4
  cover_skip: bool = False

  def __post_init__(self):
    for name in ("width", "prep_depth", "hide_depth", "reveal_depth"):
      settings_lib.check_count(f"baseline.deepstega.{name}", getattr(self, name))
    if not isinstance(self.cover_skip, bool):
      raise ValueError(f"baseline.deepstega.cover_skip must be true or false, got {self.cover_skip!r}")


class BranchStack(nn.Module):
  """`depth` layers of three parallel convolutions (KERNEL_SIZES, `width` filters each) + ReLU, then a 1x1
  convolution to `out_channels` (none when 0): [B, H, W, C] -> [B, H, W, out_channels or 3 * width]."""
  width: int
  depth: int
  out_channels: int = 0

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    for layer in range(self.depth):
      # He init: every branch feeds a ReLU, and LeCun init would shrink the signal layer by layer.
      x = nn.relu(jnp.concatenate([
          nn.Conv(self.width, (k, k), padding="SAME", kernel_init=nn.initializers.he_normal(),
                  name=f"layer{layer}_k{k}")(x) for k in KERNEL_SIZES], axis=-1))
    return nn.Conv(self.out_channels, (1, 1), name="out")(x) if self.out_channels else x


def _networks(arch: Architecture) -> dict[str, BranchStack]:
  return dict(prep=BranchStack(arch.width, arch.prep_depth), hide=BranchStack(arch.width, arch.hide_depth, 3),
              reveal=BranchStack(arch.width, arch.reveal_depth, 3))


def init_networks(rng: jax.Array, arch: Architecture) -> dict:
  """Fresh params {'prep', 'hide', 'reveal'} of the three networks."""
  nets = _networks(arch)
  image = jnp.zeros((1, 8, 8, 3), jnp.float32)  # the params do not depend on the image size
  prepared = jnp.zeros((1, 8, 8, 3 + len(KERNEL_SIZES) * arch.width), jnp.float32)
  keys = jax.random.split(rng, 3)
  return dict(prep=nets["prep"].init(keys[0], image)["params"],
              hide=nets["hide"].init(keys[1], prepared)["params"],
              reveal=nets["reveal"].init(keys[2], image)["params"])


def hide(params: dict, arch: Architecture, covers: jax.Array, secrets: jax.Array) -> jax.Array:
  """Containers C' [B, H, W, 3] (not clipped) of covers and secrets [B, H, W, 3] (arch.cover_skip: the cover
  plus the hiding network's output)."""
  nets = _networks(arch)
  prepared = nets["prep"].apply({"params": params["prep"]}, secrets)
  hidden = nets["hide"].apply({"params": params["hide"]}, jnp.concatenate([covers, prepared], axis=-1))
  return covers + hidden if arch.cover_skip else hidden


def reveal_secret(params: dict, arch: Architecture, containers: jax.Array) -> jax.Array:
  """Revealed secrets S' [B, H, W, 3] (not clipped) of containers [B, H, W, 3]."""
  return _networks(arch)["reveal"].apply({"params": params["reveal"]}, containers)


def stega_loss(params: dict, arch: Architecture, covers: jax.Array, secrets: jax.Array, noise: jax.Array,
               beta: float) -> tuple[jax.Array, dict]:
  """Baluja's loss ||C - C'|| + beta ||S - S'|| (mean squared errors) on covers, secrets and `noise`
  [B, H, W, 3] added to the containers before the reveal, so that the networks cannot rely on bits a
  small change destroys. The reveal network's gradient comes from the secret term only."""
  containers = hide(params, arch, covers, secrets)
  revealed = reveal_secret(params, arch, containers + noise)
  cover_mse = jnp.mean((containers - covers)**2)
  secret_mse = jnp.mean((revealed - secrets)**2)
  return cover_mse + beta * secret_mse, dict(cover_mse=cover_mse, secret_mse=secret_mse)


@functools.partial(jax.jit, static_argnames="arch")
def _hide_in_views(params, arch: Architecture, views: jax.Array, secret: jax.Array) -> jax.Array:
  containers = hide(params, arch, views, jnp.broadcast_to(secret, views.shape))
  return containers_lib.from_levels(containers_lib.to_levels(containers))


def hide_in_views(params: dict, arch: Architecture, views, secret) -> jax.Array:
  """Containers [V, H, W, 3] on 8-bit levels (as shared images are) of the views [V, H, W, 3], each
  hiding `secret` [H, W, 3]."""
  views, secret = jnp.asarray(views, jnp.float32), jnp.asarray(secret, jnp.float32)
  if secret.shape != views.shape[1:]:
    raise ValueError(f"secret {secret.shape} must have the views' shape {views.shape[1:]}")
  return jnp.concatenate([_hide_in_views(params, arch, views[i:i + VIEW_CHUNK], secret)
                          for i in range(0, len(views), VIEW_CHUNK)])


@functools.partial(jax.jit, static_argnames=("arch", "size"))
def _reveal_renders(params, arch: Architecture, renders: jax.Array, size: int) -> jax.Array:
  return jnp.clip(reveal_lib.resize_for_decoder(reveal_secret(params, arch, renders), size), 0.0, 1.0)


def reveal_renders(params: dict, arch: Architecture, renders, size: int) -> jax.Array:
  """Renders [V, H, W, 3] -> revealed images [V, size, size, 3] in [0, 1]: the reveal network on the whole
  render, then resized as the ConcealGS decoder's input is (reveal.resize_for_decoder)."""
  renders = jnp.asarray(renders, jnp.float32)
  return jnp.concatenate([_reveal_renders(params, arch, renders[i:i + VIEW_CHUNK], size)
                          for i in range(0, len(renders), VIEW_CHUNK)])


def stega_reveal(params: dict, arch: Architecture, size: int):
  """The reveal function of DeepStega (renders [V, H, W, 3] -> [V, size, size, 3]), for
  conceal.evaluate_concealment."""
  return functools.partial(reveal_renders, params, arch, size=size)


def save_networks(path: str, params: dict, arch: Architecture) -> None:
  """The three networks' params and their architecture, as one msgpack file written atomically."""
  state = jax.tree.map(np.asarray, flax.serialization.to_state_dict(params))
  fileio.write_bytes(path, flax.serialization.msgpack_serialize(
      dict(architecture=dataclasses.asdict(arch), params=state)))


def load_networks(path: str) -> tuple[dict, Architecture]:
  """(params, architecture) from a file written by save_networks; ValueError naming the file otherwise."""
  try:
    with open(path, "rb") as f:
      saved = flax.serialization.msgpack_restore(f.read())
    arch = Architecture(**saved["architecture"])
    params = saved["params"]
    expected = jax.eval_shape(lambda: init_networks(jax.random.key(0), arch))
    if jax.tree.structure(params) != jax.tree.structure(expected) or any(
        np.shape(a) != b.shape for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(expected))):
      raise ValueError("the parameters do not fit the saved architecture")
  except (OSError, ValueError, TypeError, KeyError) as error:
    raise ValueError(f"cannot read DeepStega networks {path}: {error}") from error
  return jax.tree.map(jnp.asarray, params), arch
