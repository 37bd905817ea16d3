"""The ConcealGS decoder F: a VGG16-style U-Net from a render [B, H, W, C] (C = 3; StegaNeRF's decoder takes a
4th channel) to an image [B, H, W, 3].

Shaped like the decoder of the authors' released ConcealGS code (github.com/zxk1212/ConcealGS): a VGG16
encoder cut after conv4_3 (stages of base * (1, 2, 4, 8) channels with 2, 2, 3, 3 conv3x3+ReLU, 2x2 max
pools between stages), three decoder blocks (stride-2 transposed conv, concatenate the skip, two
conv3x3+ReLU) and a 1x1 conv to 3 channels. The output has no activation, so the identity on normal views
(L_d^-) is not squashed near 0 and 1.
base_channels = 64 is the paper width, the only one ImageNet VGG16 weights fit.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import linen as nn

PAPER_WIDTH = 64
ENCODER_DEPTHS = (2, 2, 3, 3)  # conv3x3+ReLU per stage: VGG16 conv1_1 .. conv4_3
CHANNEL_MULTIPLIERS = (1, 2, 4, 8)
DOWNSAMPLE = 2**(len(ENCODER_DEPTHS) - 1)  # H and W must be multiples of this

# Encoder module names in VGG16 order; ENCODER_NAMES[k] takes VGG16 conv k (0 = conv1_1).
ENCODER_NAMES = tuple(f"enc{s}_{j}" for s, depth in enumerate(ENCODER_DEPTHS, 1)
                      for j in range(1, depth + 1))


def stage_channels(base_channels: int) -> tuple[int, ...]:
  """Channels of the encoder stages, base_channels * (1, 2, 4, 8)."""
  return tuple(base_channels * m for m in CHANNEL_MULTIPLIERS)


def _conv_relu(x: jax.Array, features: int, name: str) -> jax.Array:
  # He init: every such conv feeds a ReLU, and the default LeCun init halves the signal each layer.
  conv = nn.Conv(features, (3, 3), padding="SAME", kernel_init=nn.initializers.he_normal(), name=name)
  return nn.relu(conv(x))


class UNet(nn.Module):
  """images [B, H, W, C] -> [B, H, W, 3], H and W multiples of 8 (64 x 64 in ConcealGS). The input channel
  count C is the input's (3: a render; the params fix it through enc1_1's kernel [3, 3, C, base]).

  Modules: enc{stage}_{conv} (VGG16 conv{stage}_{conv}), up{stage} (transposed conv to that stage's
  resolution), dec{stage}_1, dec{stage}_2, out (the 1x1 conv).
  """
  base_channels: int = PAPER_WIDTH

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    if images.ndim != 4:
      raise ValueError(f"UNet expects images [B, H, W, C], got shape {images.shape}")
    if images.shape[1] % DOWNSAMPLE or images.shape[2] % DOWNSAMPLE:
      raise ValueError(f"UNet needs H and W divisible by {DOWNSAMPLE}, got {images.shape[1:3]}")
    channels = stage_channels(self.base_channels)
    x, skips = images, []
    for stage, (depth, features) in enumerate(zip(ENCODER_DEPTHS, channels), 1):
      if stage > 1:
        x = nn.max_pool(x, (2, 2), strides=(2, 2))
      for j in range(1, depth + 1):
        x = _conv_relu(x, features, f"enc{stage}_{j}")
      skips.append(x)
    for stage in range(len(channels) - 1, 0, -1):
      features = channels[stage - 1]
      x = nn.ConvTranspose(features, (2, 2), strides=(2, 2), padding="VALID", name=f"up{stage}")(x)
      x = jnp.concatenate([skips[stage - 1], x], axis=-1)
      x = _conv_relu(x, features, f"dec{stage}_1")
      x = _conv_relu(x, features, f"dec{stage}_2")
    return nn.Conv(3, (1, 1), name="out")(x)


def init_decoder(rng: jax.Array, base_channels: int = PAPER_WIDTH, image_size: int = 64,
                 in_channels: int = 3) -> dict[str, Any]:
  """Freshly initialised UNet params (the 'params' collection) for [B, image_size, image_size, in_channels]
  input (3: a render; 4: StegaNeRF's render and classifier score)."""
  if image_size <= 0 or image_size % DOWNSAMPLE:
    raise ValueError(f"image_size must be a positive multiple of {DOWNSAMPLE}, got {image_size}")
  if in_channels < 1:
    raise ValueError(f"in_channels must be positive, got {in_channels}")
  # The params do not depend on the image size, so the smallest valid input keeps init's forward pass
  # cheap.
  dummy = jnp.zeros((1, DOWNSAMPLE, DOWNSAMPLE, in_channels), jnp.float32)
  # One jitted program initialises every kernel: much faster than one eager dispatch per initialiser.
  return jax.jit(UNet(base_channels).init)(rng, dummy)["params"]


def load_vgg16_encoder(params: dict[str, Any]) -> dict[str, Any]:
  """A copy of paper-width `params` with ImageNet VGG16 conv1_2 .. conv4_3 in enc1_2 .. enc4_3.

  enc1_1 keeps its fresh weights, as in the authors' released code (github.com/zxk1212/ConcealGS). The
  weights come from
  `metrics.vgg16_conv_params`, already in Flax [kh, kw, Cin, Cout] layout. Decoder modules are unchanged.
  Raises ValueError unless params are of a base_channels == 64 UNet.
  """
  from conceal_jax.gs.metrics import vgg16_conv_params
  width = params["enc1_1"]["kernel"].shape[-1]
  if width != PAPER_WIDTH:
    raise ValueError(f"VGG16 weights need a UNet with base_channels={PAPER_WIDTH}, got {width}")
  out = dict(params)
  for name, (kernel, bias) in list(zip(ENCODER_NAMES, vgg16_conv_params()))[1:]:
    if params[name]["kernel"].shape != kernel.shape:
      raise ValueError(f"{name}: kernel shape {params[name]['kernel'].shape} != VGG16 {kernel.shape}")
    out[name] = {"kernel": jnp.asarray(kernel), "bias": jnp.asarray(bias)}
  return out


def count_flops(base_channels: int = PAPER_WIDTH, image_size: int = 64) -> float:
  """Forward FLOPs (2 x multiply-adds) of the convolutions for one image_size x image_size image.

  Biases, ReLUs, pools and concatenations are left out (well under 1% of the total), and taps on the
  zero padding are counted, the usual convention; XLA's cost analysis skips those and reports about 6%
  less at 64 x 64. A backward pass costs about twice the forward (input and weight gradients).
  """
  channels = stage_channels(base_channels)
  macs, c_in = 0, 3
  for stage, (depth, features) in enumerate(zip(ENCODER_DEPTHS, channels)):
    pixels = (image_size // 2**stage)**2
    for _ in range(depth):
      macs += pixels * 9 * c_in * features
      c_in = features
  for stage in range(len(channels) - 1, 0, -1):
    features = channels[stage - 1]
    pixels = (image_size // 2**(stage - 1))**2
    # A 2x2 stride-2 transposed conv touches each output pixel with exactly one kernel tap.
    macs += pixels * c_in * features
    macs += pixels * 9 * (2 * features) * features + pixels * 9 * features * features
    c_in = features
  macs += image_size**2 * c_in * 3
  return 2.0 * float(macs)


def count_params(params: dict[str, Any]) -> int:
  """Number of scalars in a params pytree."""
  return int(sum(np.prod(leaf.shape) for leaf in jax.tree.leaves(params)))
