"""The ConcealGS decoder F: a VGG16-style U-Net from a render [B, H, W, C] (C = 3; StegaNeRF's decoder takes a
4th channel) to an image [B, H, W, 3].

Shaped like the decoder of the authors' released ConcealGS code (github.com/zxk1212/ConcealGS): a VGG16
encoder cut after conv4_3 (stages of base * (1, 2, 4, 8) channels with 2, 2, 3, 3 conv3x3+ReLU, 2x2 max
pools between stages), three decoder blocks (stride-2 transposed conv, concatenate the skip, two
conv3x3+ReLU) and a 1x1 conv to 3 channels. The output has no activation, so the identity on normal views
(L_d^-) is not squashed near 0 and 1.
base_channels = 64 is the paper width, the only one ImageNet VGG16 weights fit.

`input_norm` (an option beyond the paper, conceal.decoder.input_norm) makes F equivariant to a brightness
shift, or to brightness and contrast, of what it reads, so that such a change of the check render changes
the revealed image alike instead of unsettling the decoder, while the identity on normal views (L_d^-)
stays reachable (reversible instance normalisation, `standardize_images` / `unstandardize_images`):
- 'center': the U-Net reads each image less its mean and its output gets the mean back: F(x + b) = F(x) + b;
- 'standardize': also divided by, and scaled back by, the image's standard deviation: F(a x + b) = a F(x) + b
  for every a > 0.
The statistics are constants to the gradient: differentiated, they would let L_d^+ move the whole check render.
Dividing by the spread turns a local change (holes where Gaussians were removed) into a global one. What each
mode gains and loses under the attacks is in experiments/results/conceal_options.md.

`reference_size` (beyond the paper, conceal.decoder.reference) gives F a learned image [S, S, 3] of its own, the
`reference` parameter, read beside every input as three more channels (normalised with the input's statistics):
started from the clean teacher's render at the key, it lets the first convolution compare what it reads with the
key's exact framing pixel by pixel, so that a mark F reads in the scene's own Gaussians need not be read from the
key zoomed or rolled a little, where that mark looks the same but the framing does not.
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


INPUT_NORMS = ("none", "center", "standardize")
# The smallest standard deviation an image is divided by: a flat image is not blown up into noise, and the
# gradient of the square root stays finite.
STD_FLOOR = 1e-2


def image_statistics(images: jax.Array, input_norm: str) -> tuple[jax.Array, jax.Array]:
  """(mean, std) [B, 1, 1, 1] of each image [B, H, W, C] over its pixels and channels, as `input_norm` uses
  them: std is sqrt(variance + STD_FLOOR^2) for 'standardize', 1 for 'center'."""
  mean = jnp.mean(images, axis=(1, 2, 3), keepdims=True)
  if input_norm == "center":
    return mean, jnp.ones_like(mean)
  variance = jnp.mean(jnp.square(images - mean), axis=(1, 2, 3), keepdims=True)
  return mean, jnp.sqrt(variance + STD_FLOOR**2)


def standardize_images(images: jax.Array, mean: jax.Array, std: jax.Array) -> jax.Array:
  """images [B, H, W, C] with each image's mean removed and divided by its std (`image_statistics`)."""
  return (images - mean) / std


def unstandardize_images(images: jax.Array, mean: jax.Array, std: jax.Array) -> jax.Array:
  """The inverse of `standardize_images`: images [B, H, W, C] scaled by std and shifted by mean."""
  return images * std + mean


def _conv_relu(x: jax.Array, features: int, name: str) -> jax.Array:
  # He init: every such conv feeds a ReLU, and the default LeCun init halves the signal each layer.
  conv = nn.Conv(features, (3, 3), padding="SAME", kernel_init=nn.initializers.he_normal(), name=name)
  return nn.relu(conv(x))


class UNet(nn.Module):
  """images [B, H, W, C] -> [B, H, W, 3], H and W multiples of 8 (64 x 64 in ConcealGS). The input channel
  count C is the input's (3: a render; the params fix it through enc1_1's kernel [3, 3, C, base]).

  Modules: enc{stage}_{conv} (VGG16 conv{stage}_{conv}), up{stage} (transposed conv to that stage's
  resolution), dec{stage}_1, dec{stage}_2, out (the 1x1 conv). `input_norm` (one of INPUT_NORMS, see the
  module doc) adds no parameters, so the same params file serves any; the key records the one it was
  trained with.
  """
  base_channels: int = PAPER_WIDTH
  input_norm: str = "none"
  reference_size: int = 0  # S of the `reference` image read beside the input (module doc); 0: none

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    if images.ndim != 4:
      raise ValueError(f"UNet expects images [B, H, W, C], got shape {images.shape}")
    if images.shape[1] % DOWNSAMPLE or images.shape[2] % DOWNSAMPLE:
      raise ValueError(f"UNet needs H and W divisible by {DOWNSAMPLE}, got {images.shape[1:3]}")
    if self.input_norm not in INPUT_NORMS:
      raise ValueError(f"input_norm must be one of {INPUT_NORMS}, got {self.input_norm!r}")
    reference = None
    if self.reference_size:
      size = (self.reference_size, self.reference_size)
      if images.shape[1:3] != size:
        raise ValueError(f"a decoder with a {size} reference reads images of that size, got {images.shape[1:3]}")
      reference = self.param("reference", nn.initializers.zeros, size + (3,))
    if self.input_norm == "none":
      return _encode_decode(with_reference(images, reference), self.base_channels)
    # The statistics are constants of the image: through them the student could reach I by brightening or
    # scaling the whole check render, a global change that every normal view pays for.
    mean, std = jax.lax.stop_gradient(image_statistics(images, self.input_norm))
    read = with_reference(standardize_images(images, mean, std),
                          None if reference is None else standardize_images(reference, mean, std))
    return unstandardize_images(_encode_decode(read, self.base_channels), mean, std)


def with_reference(images: jax.Array, reference: jax.Array | None) -> jax.Array:
  """images [B, H, W, C] with `reference` [H, W, 3] (or [B, H, W, 3]) as three more channels (None: as they are)."""
  if reference is None:
    return images
  return jnp.concatenate([images, jnp.broadcast_to(reference, images.shape[:3] + (3,))], axis=-1)


def _encode_decode(images: jax.Array, base_channels: int) -> jax.Array:
  # Called inside UNet.__call__ (compact): the modules made here are UNet's, named as in the class doc.
  channels = stage_channels(base_channels)
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
                 in_channels: int = 3, reference=None) -> dict[str, Any]:
  """Freshly initialised UNet params (the 'params' collection) for [B, image_size, image_size, in_channels]
  input (3: a render; 4: StegaNeRF's render and classifier score); with `reference` [image_size, image_size, 3]
  also the reference image read beside it (UNet.reference_size), started there."""
  if image_size <= 0 or image_size % DOWNSAMPLE:
    raise ValueError(f"image_size must be a positive multiple of {DOWNSAMPLE}, got {image_size}")
  if in_channels < 1:
    raise ValueError(f"in_channels must be positive, got {in_channels}")
  # The params do not depend on the image size, so the smallest valid input keeps init's forward pass
  # cheap.
  # One jitted program initialises every kernel: much faster than one eager dispatch per initialiser.
  if reference is None:
    dummy = jnp.zeros((1, DOWNSAMPLE, DOWNSAMPLE, in_channels), jnp.float32)
    return jax.jit(UNet(base_channels).init)(rng, dummy)["params"]
  reference = jnp.asarray(reference, jnp.float32)
  if reference.shape != (image_size, image_size, 3):
    raise ValueError(f"the reference must be [{image_size}, {image_size}, 3], got {list(reference.shape)}")
  dummy = jnp.zeros((1, image_size, image_size, in_channels), jnp.float32)
  params = jax.jit(UNet(base_channels, reference_size=image_size).init)(rng, dummy)["params"]
  return dict(params, reference=reference)


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
