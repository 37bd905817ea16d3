"""Distortions of the student's check render during training, so that the hidden image survives them.

An option beyond ConcealGS (arXiv:2501.03605), whose robustness figure (Sec. 3) only measures what blur and
JPEG of the check render cost: with conceal.check_blur_max / check_noise_max, every step blurs the check
render by a Gaussian of a standard deviation drawn from [0, check_blur_max] pixels and adds normal noise of
a standard deviation drawn from [0, check_noise_max] before the decoder reads it for L_d^+ (eq. 5), as
watermarking methods train through their attack layers. The draws are made on the host and enter the jitted
step as values, so they never retrace it.

Measured on the demo (configs/demo.py, 1300 steps; experiments/results/robust_bench_demo_augment.json) with
check_blur_max 1.5 and check_noise_max 0.02: the mean hidden-SSIM drop under the paper's mild blur and JPEG
fell from 0.036 to 0.003 (hidden 31.07 dB / 0.9727 against 31.20 / 0.9764), but a blur-tolerant decoder also
reveals more near the key (SSIM 0.23 against 0.17) and the student lost 0.96 dB against 0.62.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

# Below this a sigma is a point kernel: exp(-1 / (2 * 1e-3^2)) underflows to 0 off the centre.
_MIN_SIGMA = 1e-3
# Kernel half-width in standard deviations (skimage.filters.gaussian's default truncate).
TRUNCATE = 4.0


def blur_radius(sigma_max: float) -> int:
  """Static half-width in pixels of a kernel for every sigma up to sigma_max."""
  return max(1, math.ceil(TRUNCATE * sigma_max))


def gaussian_kernel(sigma: jax.Array, radius: int) -> jax.Array:
  """[2 radius + 1] normalised Gaussian weights of standard deviation `sigma` (traced) in pixels."""
  x = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
  sigma = jnp.maximum(sigma, _MIN_SIGMA)
  weights = jnp.exp(-0.5 * (x / sigma) ** 2)
  return weights / jnp.sum(weights)


def gaussian_blur(image: jax.Array, sigma: jax.Array, radius: int) -> jax.Array:
  """image [H, W, C] blurred by a separable Gaussian of `sigma` pixels, borders mirrored (scipy's 'reflect',
  as robust.image_attacks.gaussian_blur); sigma 0 returns the image. radius < H, W."""
  kernel = gaussian_kernel(sigma, radius)
  padded = jnp.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="symmetric")
  height, width = image.shape[:2]
  rows = sum(kernel[k] * padded[k:k + height] for k in range(2 * radius + 1))
  return sum(kernel[k] * rows[:, k:k + width] for k in range(2 * radius + 1))


def distort(image: jax.Array, distortion: dict, blur_max: float, noise_max: float) -> jax.Array:
  """image [H, W, 3] blurred by distortion["blur"] pixels and plus normal noise of standard deviation
  distortion["noise"] drawn from the PRNG seed distortion["seed"] (all traced; see `draw`). The static
  maxima leave out, at trace time, the blur or the noise a run never draws."""
  if blur_max > 0:
    image = gaussian_blur(image, distortion["blur"], blur_radius(blur_max))
  if noise_max > 0:
    image = image + distortion["noise"] * jax.random.normal(jax.random.key(distortion["seed"]), image.shape,
                                                            image.dtype)
  return image


def draw(rng: np.random.Generator, blur_max: float, noise_max: float) -> dict:
  """One step's distortion: blur sigma ~ U[0, blur_max], noise sigma ~ U[0, noise_max], a noise seed."""
  return dict(blur=np.float32(rng.uniform(0.0, blur_max)), noise=np.float32(rng.uniform(0.0, noise_max)),
              seed=np.uint32(rng.integers(2**32)))
