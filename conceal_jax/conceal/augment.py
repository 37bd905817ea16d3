"""Distortions of the student's check render during training, so that the hidden image survives them.

An option beyond ConcealGS (arXiv:2501.03605), whose robustness figure (Sec. 3) only measures what blur and
JPEG of the check render cost. Each step draws a distortion on the host (`draw`; values, so the jitted step
never retraces) within the maxima of conceal.attacks, as watermarking methods train through attack layers:
- of the image (`distort`): brightness and contrast (`photometric`), a Gaussian blur, normal noise, before the
  decoder reads the render for L_d^+ (eq. 5); identity_distorted shows L_d^- the student's normal render alike;
- of the scene (perturb.py): Gaussians dropped, parameter noise, size pruning, 8-bit colours, opacity resets,
  the carrier film's splats merged.
What each distortion gained and cost is in experiments/results/conceal_options.md.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import decimate


# Below this a sigma is a point kernel: exp(-1 / (2 * 1e-3^2)) underflows to 0 off the centre.
_MIN_SIGMA = 1e-3
# Kernel half-width in standard deviations (skimage.filters.gaussian's default truncate).
TRUNCATE = 4.0
# An Augmentation field f is config key conceal.attacks.<f>; a contrast factor and a dropout probability stay below 1.
UPPER_BOUNDS = dict(contrast_max=1.0, dropout_max=1.0, quantize_fraction=1.0 + 1e-9, reset_fraction=1.0 + 1e-9,
                    merge_fraction=1.0 + 1e-9, prune_small_max=1.0)


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


def photometric(image: jax.Array, brightness: jax.Array, contrast: jax.Array) -> jax.Array:
  """(image - 0.5) * contrast + 0.5 + brightness (robust.image_attacks.brightness_contrast), unclipped: the
  gradient reaches every pixel, and brightness 0 and contrast 1 give the image back to the bit (hence the
  offset is gathered into one term: (x - 0.5) + 0.5 rounds)."""
  return image * contrast + (0.5 * (1.0 - contrast) + brightness)


@dataclasses.dataclass(frozen=True)
class Augmentation:
  """The maxima of a run's distortions of its check render (config conceal.attacks.<field>). Static: a kind
  whose maximum is 0 is left out of the step at trace time, and never drawn from."""
  blur_max: float = 0.0         # blur sigma ~ U[0, max] pixels
  noise_max: float = 0.0        # noise sigma ~ U[0, max]
  brightness_max: float = 0.0   # offset ~ U[-max, max] (`photometric`)
  contrast_max: float = 0.0     # factor ~ 1 + U[-max, max]
  dropout_max: float = 0.0      # each Gaussian dropped with probability ~ U[0, max] (perturb.perturb_gaussians)
  param_noise_max: float = 0.0  # relative parameter noise ~ U[0, max]
  quantize_fraction: float = 0.0  # the share of steps whose check render is of 8-bit colours and opacities
  reset_fraction: float = 0.0  # the share of steps whose check render is of opacities reset to densify.RESET_CEILING
  merge_fraction: float = 0.0  # the share of steps whose check render merges film pairs (decimate.merge_rounds)
  merge_depth: float = 1.0  # the rounds of merges such a render goes up to: its depth ~ U[0, merge_depth]
  prune_small_max: float = 0.0  # the share ~ U[0, max] of smallest Gaussians dropped (perturb.kept_by_size)
  merge_groups: str = "nearest"  # 'nearest': merge_depth rounds of near pairs; 'converter': the converter's groups
  merge_keep: tuple = (0.5, 0.8)  # with 'converter': the fractions kept, one drawn per merging step
  regroup_every: int = 500  # with 'converter': the steps between groupings from the trained colours
  merge_scales: tuple = (1.0,)  # with 'converter': the scales of the scene copies its groups are computed on

  def __post_init__(self):
    for f in dataclasses.fields(self)[:-4]:
      value, below = getattr(self, f.name), UPPER_BOUNDS.get(f.name, math.inf)
      if not 0 <= value < below:  # NaN fails too
        raise ValueError(f"conceal.attacks.{f.name} must be in [0, {below:g}), got {value}")
    if not 1 <= self.merge_depth <= decimate.MAX_MERGE_DEPTH:
      raise ValueError(f"conceal.attacks.merge_depth must be in [1, {decimate.MAX_MERGE_DEPTH}], "
                       f"got {self.merge_depth}")
    keeps = bool(self.merge_keep) and all(0.5 <= k < 1.0 for k in self.merge_keep)
    if self.merge_groups not in decimate.MERGE_GROUPS or not keeps or self.regroup_every < 1:
      raise ValueError(f"conceal.attacks.merge_groups must be one of {decimate.MERGE_GROUPS}, merge_keep fractions "
                       "in [0.5, 1) (one generation of the converter's decimation) and regroup_every >= 1, got "
                       f"{self.merge_groups!r}, {self.merge_keep}, {self.regroup_every}")
    if not self.merge_scales or not all(0 < s < math.inf for s in self.merge_scales):
      raise ValueError(f"conceal.attacks.merge_scales must be positive finite factors, got {self.merge_scales}")

  @property
  def merge_levels(self) -> int:
    """With merge_groups 'converter', the levels a merging step draws one of: each fraction of merge_keep at each
    scale of merge_scales (grouping.converter_merges)."""
    return len(self.merge_keep) * len(self.merge_scales)

  @property
  def merge_rounds(self) -> int:
    """The rounds of film merges a step may draw (decimate.film_merges' levels)."""
    return math.ceil(self.merge_depth)

  @property
  def distorts_image(self) -> bool:
    """Whether a step changes the check render's image (`distort`)."""
    return max(self.blur_max, self.noise_max, self.brightness_max, self.contrast_max) > 0

  @property
  def perturbs_model(self) -> bool:
    """Whether a step renders the check view from a perturbed student (perturb.perturb_gaussians)."""
    return max(self.dropout_max, self.param_noise_max, self.quantize_fraction, self.reset_fraction,
               self.merge_fraction, self.prune_small_max) > 0

  @property
  def draws(self) -> bool:
    """Whether a step draws a distortion (`draw`), of the image or of the model."""
    return self.distorts_image or self.perturbs_model


def distort(image: jax.Array, distortion: dict | None, augmentation: Augmentation) -> jax.Array:
  """image [H, W, 3] with brightness and contrast changed by distortion["brightness"] and ["contrast"], then
  blurred by distortion["blur"] pixels and plus normal noise of standard deviation distortion["noise"] drawn
  from the PRNG seed distortion["seed"] (all traced; see `draw`). The kinds whose maximum in `augmentation`
  is 0 are left out at trace time; without any, the image itself (and `distortion` may be None)."""
  a = augmentation
  if a.brightness_max > 0 or a.contrast_max > 0:
    image = photometric(image, distortion["brightness"], distortion["contrast"])
  if a.blur_max > 0:
    image = gaussian_blur(image, distortion["blur"], blur_radius(a.blur_max))
  if a.noise_max > 0:
    image = image + distortion["noise"] * jax.random.normal(jax.random.key(distortion["seed"]), image.shape,
                                                            image.dtype)
  return image


def draw(rng: np.random.Generator, augmentation: Augmentation) -> dict:
  """One step's distortion within `augmentation`'s maxima: blur sigma ~ U[0, blur_max], noise sigma ~ U[0, noise_max],
  a noise seed; of the model (perturb.perturb_gaussians) a dropout probability ~ U[0, dropout_max], a relative parameter
  noise ~ U[0, param_noise_max] and their seed; brightness ~ U[-brightness_max, brightness_max] and contrast ~ 1 +
  U[-contrast_max, contrast_max]; whether the step quantizes (1 with probability quantize_fraction) and resets the
  opacities (1 with probability reset_fraction); with quantize_fraction, the point its grids round at ~ U[0, 1)
  (perturb.quantize_8bit); the depth of the film's merges (~ U[0, merge_depth] with probability merge_fraction, else 0:
  decimate.merge_rounds; with merge_groups 'converter' the number of one of its merge_levels); the share of
  smallest Gaussians dropped ~ U[0, prune_small_max]. Later kinds are drawn after earlier ones, so a run without
  them sees the distortions it always did."""
  a = augmentation
  image = dict(blur=np.float32(rng.uniform(0.0, a.blur_max)), noise=np.float32(rng.uniform(0.0, a.noise_max)),
               seed=np.uint32(rng.integers(2**32)))
  model = dict(dropout=np.float32(rng.uniform(0.0, a.dropout_max)),
               param_noise=np.float32(rng.uniform(0.0, a.param_noise_max)), model_seed=np.uint32(rng.integers(2**32)))
  drawn = dict(image, **model, brightness=np.float32(rng.uniform(-a.brightness_max, a.brightness_max)),
               contrast=np.float32(1.0 + rng.uniform(-a.contrast_max, a.contrast_max)))
  drawn["quantize"] = np.float32(a.quantize_fraction > 0 and rng.random() < a.quantize_fraction)
  drawn["reset"] = np.float32(a.reset_fraction > 0 and rng.random() < a.reset_fraction)
  drawn["rounding"] = np.float32(rng.random() if a.quantize_fraction > 0 else 0.5)
  depth = rng.random() if a.merge_fraction > 0 and rng.random() < a.merge_fraction else None
  converter = a.merge_groups == "converter"  # then the number of a level (1-based), each equally likely
  drawn["merge"] = np.float32(0.0 if depth is None else 1 + math.floor(depth * a.merge_levels) if converter
                              else depth * a.merge_depth)
  drawn["prune_small"] = np.float32(rng.uniform(0.0, a.prune_small_max) if a.prune_small_max > 0 else 0.0)
  return drawn


def polish_draws(augmentation: Augmentation, merge_share: float | None, polish_steps: int) -> Augmentation:
  """What the decoder polish's steps draw from: `augmentation` (the joint steps') with merge_share of merged check
  renders (conceal.decoder_opt.polish_merge_fraction; None: unset, `augmentation` itself). The step merges only
  where the joint steps do (the kind is left out at trace time otherwise), and only a polish draws it."""
  if merge_share is None:
    return augmentation
  if not (polish_steps > 0 and augmentation.merge_fraction > 0):
    raise ValueError("conceal.decoder_opt.polish_merge_fraction needs conceal.decoder_opt.polish_steps and "
                     f"conceal.attacks.merge_fraction above 0, got {polish_steps} and {augmentation.merge_fraction}")
  return dataclasses.replace(augmentation, merge_fraction=merge_share)
