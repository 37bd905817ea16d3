"""The ConcealGS objective as pure functions of (student, decoder, data, views).

ConcealGS (Yang et al. 2025, arXiv:2501.03605) trains a student scene G_w and a decoder F on the total
loss of Sec. 2.2: L = L_kd (eq. 3) + L_d^- (eq. 4) + L_d^+ (eq. 5), with the decoder's share of the
gradient reweighted layer by layer (Sec. 2.3, eqs. 6-7; see guidance.py). Only L_kd and L_d^+ read the
student, and only L_d^+ and L_d^- read the decoder, so the objective splits into two functions whose
gradients are the two pytrees the guided step compares:
- `student_objective`: L_kd + lambda+ L_d^+ (and the released variant's extras), differentiated with
  respect to (student, decoder); its decoder gradient is exactly lambda+ grad L_d^+.
- `decoder_identity_objective`: lambda- L_d^-, differentiated with respect to the decoder.

`data` is the device-resident dict built once per run (conceal.build_data): train images [V, H, W, 3],
cached teacher renders [V, H, W, 3] and at the decoder size [V, S, S, 3], stacked train cameras, the
check camera, its target image, the teacher's check render at the decoder size, and the hidden image
[S, S, 3]. With further hidden images (conceal.extra_hidden) it also holds those four per key, stacked
[K, ...] under data["keys"]; a step trains one key, and `key_data` puts that key's in their place, so the
objective below is written for one key.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from conceal_jax.conceal import augment, guidance, reveal, unet
from conceal_jax.gs import losses
from conceal_jax.splat.render import RenderOptions, render

VARIANTS = ("paper", "released")


@dataclasses.dataclass(frozen=True)
class ConcealSettings:
  """The static choices of one concealment run (hashable: they shape the traced step)."""
  variant: str = "paper"
  use_decoder: bool = True
  consistency: bool = True
  guidance: bool = True
  granularity: str = "layer"
  decoder_width: int = unet.PAPER_WIDTH
  decoder_input_norm: str = "none"  # (unet.UNet, beyond the paper)
  decoder_clip_input: bool = False  # (reveal.Reading, beyond the paper)
  hidden_size: int = 64
  weight_kd: float = 1.0
  weight_plus: float = 1.0
  weight_minus: float = 1.0
  weight_check: float = 1.0
  # Leakage control (an option beyond the paper, see conceal.py): L_d^- also on the student's own render
  # of the step's normal view and on the teacher's check render, and the share of steps whose normal views
  # are decoy poses near the key.
  identity_on_student: bool = False
  identity_on_teacher_check: bool = False
  decoy_fraction: float = 0.0
  # Robustness, an option beyond the paper (augment.py): the check render blurred, noised, its brightness and
  # contrast changed for L_d^+, and rendered from a perturbed student (Gaussians dropped, parameters noised).
  augmentation: augment.Augmentation = augment.Augmentation()
  # L_d^- also reads the student's normal render through the step's distortion, so that a decoder taught to
  # see through blur and noise at the key still gives the identity on blurred views near it.
  identity_distorted: bool = False
  # ... and that render made from the step's perturbed student (a second, forward-only render), so that a
  # decoder taught to see through dropped and noised Gaussians at the key still gives the identity near it.
  identity_perturbed: bool = False
  # The decoder that is scored and saved: an exponential moving average of its weights with this decay (conceal.py)
  decoder_average: float = 0.0

  def __post_init__(self):
    if self.variant not in VARIANTS:
      raise ValueError(f"conceal.variant must be one of {VARIANTS}, got {self.variant!r}")
    if self.granularity not in guidance.GRANULARITIES:
      raise ValueError(f"conceal.granularity must be one of {guidance.GRANULARITIES}, got {self.granularity!r}")
    if self.decoder_input_norm not in unet.INPUT_NORMS:
      raise ValueError(f"conceal.decoder_input_norm must be one of {unet.INPUT_NORMS}, got {self.decoder_input_norm!r}")
    if self.decoder_width < 1 or self.hidden_size < 8 or self.hidden_size % unet.DOWNSAMPLE:
      raise ValueError("conceal.decoder_width must be positive and conceal.hidden_size a multiple of "
                       f"{unet.DOWNSAMPLE} (at least 8)")
    if min(self.weight_kd, self.weight_plus, self.weight_minus, self.weight_check) < 0 or not self.weight_plus > 0:
      raise ValueError("conceal weights must be non-negative and weight_plus positive")
    if not 0.0 <= self.decoy_fraction < 1.0:
      raise ValueError(f"conceal.decoy_fraction must be in [0, 1), got {self.decoy_fraction}")
    if self.decoy_fraction and not self.distill:
      raise ValueError("conceal.decoy_fraction needs L_kd (variant 'paper' with consistency): decoy poses have "
                       "no ground truth, only the teacher's renders")
    if self.identity_distorted and not (self.identity_on_student and self.augmentation.distorts_image):
      raise ValueError("conceal.identity_distorted needs identity_on_student and a distortion (check_blur_max, "
                       "check_noise_max, check_brightness_max or check_contrast_max > 0)")
    if self.identity_perturbed and not (self.identity_on_student and self.augmentation.perturbs_model):
      raise ValueError("conceal.identity_perturbed needs identity_on_student and a model perturbation "
                       "(check_dropout_max or check_param_noise_max > 0)")
    if not 0.0 <= self.decoder_average < 1.0:
      raise ValueError(f"conceal.decoder_average must be in [0, 1) (0: off), got {self.decoder_average!r}")
    if self.decoder_average and not self.use_decoder:
      raise ValueError("conceal.decoder_average needs a decoder")
    if (self.identity_on_student or self.identity_on_teacher_check) and not self.identity_loss:
      raise ValueError("conceal.identity_on_student and identity_on_teacher_check need L_d^- (a decoder and "
                       "consistency)")

  @property
  def reading(self) -> reveal.Reading:
    """How the decoder reads a render (saved in the key)."""
    return reveal.Reading(self.decoder_input_norm, self.decoder_clip_input)

  @property
  def distill(self) -> bool:
    """Normal views supervised by the teacher (L_kd) rather than by ground truth."""
    return self.variant == "paper" and self.consistency

  @property
  def identity_loss(self) -> bool:
    """Whether L_d^- trains the decoder."""
    return self.use_decoder and self.consistency


KEY_FIELDS = ("check_camera", "check_image", "hidden", "teacher_check_small")


def key_data(data: dict, key) -> dict:
  """`data` with the KEY_FIELDS of key `key` (an int, traced in the step: no retrace per key) taken from
  data["keys"] (cameras [K], check images [K, H, W, 3], hidden images and teacher check renders
  [K, S, S, 3]); `data` itself when it holds one key, so a single-image run traces what it always did."""
  if "keys" not in data:
    return data
  return dict(data, **jax.tree.map(lambda x: x[key], data["keys"]))


def student_objective(student, decoder, data: dict, view, settings: ConcealSettings,
                      options: RenderOptions, distortion: dict | None = None) -> tuple[jax.Array, dict]:
  """L_kd (eq. 3) at training view `view` + lambda+ L_d^+ (eq. 5) at the check view -> (total, aux).

  `distortion` (augment.draw, when settings.augmentation draws): L_d^+ decodes the check render, made from the
  student perturbed by it and then changed in image by it (augment.distort). The step computes the gradients of this
  objective and of `decoder_identity_objective` as two lanes (lanes_objective.py); these functions are their
  plain statement.

  Without consistency, or in the released variant, the normal view is supervised by its ground-truth
  image with the 3D-GS photometric loss instead of L_kd; the released variant adds an L1 between the
  student's check render and the check view's image. aux: normal (the normal-view term), plus (L_d^+),
  rgb (the student's normal render [H, W, 3]), identity_rgb (the render of the normal view that L_d^- reads:
  `rgb`, or with identity_perturbed, a constant render of the perturbed student), num_pairs and overflowed
  (the largest need of the renders and whether any exceeded its static pair capacity; see gs.capacity).
  """
  s = settings
  camera = jax.tree.map(lambda x: x[view], data["cameras"])
  normal_out = render(student, camera, options)
  rgb = normal_out.rgb
  if s.distill:
    normal = s.weight_kd * losses.distillation_loss(rgb, data["teacher"][view])
  else:
    normal = losses.photometric_loss(rgb, data["images"][view])
  perturbed = augment.perturb_gaussians(student, distortion, s.augmentation)
  check_out = render(perturbed, data["check_camera"], options)
  check_rgb = check_out.rgb
  plus = losses.hidden_image_loss(decoded(decoder, check_decoder_input(check_rgb, distortion, s), s), data["hidden"])
  total = normal + s.weight_plus * plus
  if s.variant == "released":
    total = total + s.weight_check * losses.l1(check_rgb, data["check_image"])
  identity_out = render(perturbed, camera, options) if s.identity_perturbed else normal_out
  outs = (normal_out, check_out, identity_out)
  return total, dict(normal=normal, plus=plus, rgb=rgb, identity_rgb=jax.lax.stop_gradient(identity_out.rgb),
                     num_pairs=jnp.max(jnp.stack([o.num_pairs for o in outs])),
                     overflowed=jnp.any(jnp.stack([o.overflowed for o in outs])))


def decoder_view(rgb: jax.Array, settings: ConcealSettings) -> jax.Array:
  """[S, S, 3] a render [H, W, 3] as the decoder is given it: clipped to [0, 1] with decoder_clip_input
  (reveal.Reading), resized to the decoder's size."""
  return reveal.resize_for_decoder(rgb, settings.hidden_size, settings.decoder_clip_input)


def check_decoder_input(check_rgb: jax.Array, distortion: dict | None, settings: ConcealSettings) -> jax.Array:
  """[S, S, 3] the student's check render [H, W, 3] as F reads it for L_d^+: distorted by `distortion`
  (augment.distort: brightness, contrast, blur, noise) as far as settings.augmentation distorts images,
  resized to the decoder's size."""
  return decoder_view(augment.distort(check_rgb, distortion, settings.augmentation), settings)


def decoded(decoder, images: jax.Array, settings: ConcealSettings) -> jax.Array:
  """F(images) [..., S, S, 3]; the images themselves without a decoder (the "w/o decoder" ablation)."""
  s = settings
  return reveal.decode(decoder, s.decoder_width, images, s.decoder_input_norm) if s.use_decoder else images


def identity_sources(settings: ConcealSettings) -> tuple[str, ...]:
  """The renders on which L_d^- asks F to be the identity, in order: 'teacher_normal', the teacher's render
  of the step's normal view (the paper), or 'teacher_check', its check render (the released code); with
  `identity_on_teacher_check` (paper), also 'teacher_check'; with `identity_on_student`, also 'student',
  the student's render of the step's normal view."""
  s = settings
  paper = s.variant == "paper"
  sources = ["teacher_normal" if paper else "teacher_check"]
  if s.identity_on_teacher_check and paper:
    sources.append("teacher_check")
  if s.identity_on_student:
    sources.append("student")
  return tuple(sources)


def identity_inputs(data: dict, normal_view, settings: ConcealSettings, student_rgb=None,
                    distortion: dict | None = None) -> jax.Array:
  """[B, S, S, 3] the `identity_sources` at the decoder size; the student's render `student_rgb` [H, W, 3]
  (student_objective's identity_rgb) enters as a constant (L_d^- trains F only), distorted as the check render
  is with identity_distorted."""
  s = settings
  student = lambda: (check_decoder_input(student_rgb, distortion, s) if s.identity_distorted
                     else decoder_view(student_rgb, s))
  images = dict(teacher_normal=lambda: data["teacher_small"][normal_view],
                teacher_check=lambda: data["teacher_check_small"],
                student=lambda: jax.lax.stop_gradient(student()))
  return jnp.stack([images[name]() for name in identity_sources(settings)])


def decoder_identity_objective(decoder, inputs: jax.Array, settings: ConcealSettings) -> jax.Array:
  """lambda- L_d^- (eq. 4): F is the identity on `inputs` [B, S, S, 3] (see `identity_inputs`), the L1
  averaged over them."""
  s = settings
  return s.weight_minus * losses.decoder_identity_loss(decoded(decoder, inputs, s), inputs)
