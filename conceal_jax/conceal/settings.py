"""The settings of one concealment run, read from the config once and checked there.

`ConcealSettings` holds what shapes the traced step (hashable, static); `RunPlan` adds what the job reads besides
(the loop, the optimisers' settings, the decoys, the keys). Both are built by `plan(config)`, which `validate` calls
before anything runs and the job calls again to run: one reading of the config, each bad value one ValueError
naming its key."""
from __future__ import annotations

import dataclasses
import os

import ml_collections
import optax

from conceal_jax.conceal import augment, carrier, guidance, key as key_lib, reveal, rollback as rollback_lib
from conceal_jax.conceal import tolerance as tolerance_lib, unet
from conceal_jax.core import loop, settings as settings_lib
from conceal_jax.gs import evaluate, optimizer

VARIANTS = ("paper", "released")
# mark.extra_hidden: 2-4 hidden images in all
MAX_EXTRA_HIDDEN = 3


@dataclasses.dataclass(frozen=True)
class ConcealSettings:
  """The static choices of the ConcealGS step (conceal.* and mark.hidden_size).

  variant: 'paper' (L_kd on the teacher's renders) or 'released' (the authors' code: the normal view against
  ground truth, L_d^- on the teacher's check render, an L1 of the check render to its image);
  use_decoder / consistency / guidance: the paper's ablations (Table 3); granularity: what the guidance
  calls a layer (guidance.py); the four loss weights (lambda's); leakage control and training through
  attacks, our extensions (configs/default.py, conceal.leakage and conceal.attacks); film_dc_bound: the bound the
  carrier film's base colours are clipped to after each update (conceal.carrier.dc_bound; 0: none).
  """
  variant: str = "paper"
  use_decoder: bool = True
  consistency: bool = True
  guidance: bool = True
  granularity: str = "layer"
  decoder_width: int = unet.PAPER_WIDTH
  reading: reveal.Reading = reveal.PAPER_READING
  hidden_size: int = 64
  weight_kd: float = 1.0
  weight_plus: float = 1.0
  weight_minus: float = 1.0
  weight_check: float = 1.0
  identity_on_student: bool = False
  identity_on_teacher_check: bool = False
  decoy_fraction: float = 0.0
  decoys_hold_student: bool = True
  augmentation: augment.Augmentation = augment.Augmentation()
  identity_distorted: bool = False
  film_dc_bound: float = 0.0

  def __post_init__(self):
    if self.variant not in VARIANTS:
      raise ValueError(f"conceal.variant must be one of {VARIANTS}, got {self.variant!r}")
    if self.granularity not in guidance.GRANULARITIES:
      raise ValueError(f"conceal.granularity must be one of {guidance.GRANULARITIES}, got {self.granularity!r}")
    if self.reading.input_norm not in unet.INPUT_NORMS:
      raise ValueError(f"conceal.decoder.input_norm must be one of {unet.INPUT_NORMS}, got "
                       f"{self.reading.input_norm!r}")
    if self.decoder_width < 1 or self.hidden_size < 8 or self.hidden_size % unet.DOWNSAMPLE:
      raise ValueError("conceal.decoder.width must be positive and mark.hidden_size a multiple of "
                       f"{unet.DOWNSAMPLE} (at least 8)")
    if min(self.weight_kd, self.weight_plus, self.weight_minus, self.weight_check) < 0 or not self.weight_plus > 0:
      raise ValueError("conceal weights must be non-negative and weight_plus positive")
    if not 0.0 <= self.decoy_fraction < 1.0:
      raise ValueError(f"conceal.leakage.decoy_fraction must be in [0, 1), got {self.decoy_fraction}")
    if not self.decoys_hold_student and not (self.decoy_fraction and self.identity_on_student):
      raise ValueError("conceal.leakage.decoys_hold_student=False leaves the decoys to the decoder, which reads the "
                       "student's render there: it needs decoys (decoy_fraction) and identity_on_student")
    if self.decoy_fraction and not self.distill:
      raise ValueError("conceal.leakage.decoy_fraction needs L_kd (variant 'paper' with consistency): decoy poses "
                       "have no ground truth, only the teacher's renders")
    if self.film_dc_bound < 0:
      raise ValueError(f"conceal.carrier.dc_bound must not be negative, got {self.film_dc_bound}")
    if self.identity_distorted and not (self.identity_on_student and self.augmentation.distorts_image):
      raise ValueError("conceal.attacks.identity_distorted needs conceal.leakage.identity_on_student and an image "
                       "distortion (conceal.attacks blur_max, noise_max, brightness_max or contrast_max > 0)")
    if (self.identity_on_student or self.identity_on_teacher_check) and not self.identity_loss:
      raise ValueError("conceal.leakage.identity_on_student and identity_on_teacher_check need L_d^- (a decoder "
                       "and consistency)")

  @property
  def distill(self) -> bool:
    """Normal views supervised by the teacher (L_kd) rather than by ground truth."""
    return self.variant == "paper" and self.consistency

  @property
  def identity_loss(self) -> bool:
    """Whether L_d^- trains the decoder."""
    return self.use_decoder and self.consistency

  def identity_sources(self) -> tuple[str, ...]:
    """The renders on which L_d^- asks F to be the identity: 'teacher_normal', the teacher's render of the
    step's normal view (the paper), or 'teacher_check', its check render (the released code); with
    identity_on_teacher_check (paper), also 'teacher_check'; with identity_on_student, also 'student', the
    student's render of the normal view. Empty without L_d^-."""
    if not self.identity_loss:
      return ()
    paper = self.variant == "paper"
    sources = ["teacher_normal" if paper else "teacher_check"]
    if self.identity_on_teacher_check and paper:
      sources.append("teacher_check")
    if self.identity_on_student:
      sources.append("student")
    return tuple(sources)


@dataclasses.dataclass(frozen=True)
class RunPlan:
  """What a concealment job reads from its config, checked: the step's settings, the loop (the joint
  iterations then conceal.decoder_opt.polish_steps decoder-only steps), the sources of the hidden images
  (mark.hidden then mark.extra_hidden), the key's kind, the decoys' (count, ranges, key axes, orbit turns), the
  carrier film's (None: the student is the teacher's Gaussians), the key tolerance radius (None: the key alone),
  the decoder's rollback guard (None: none) and the distortions the polish's steps draw from."""
  settings: ConcealSettings
  loop: loop.LoopSettings
  iterations: int
  polish_steps: int
  sources: tuple[str, ...]
  key_kind: str
  key_index: int
  key_seed: int
  key_offset: float
  decoy_views: int
  decoy_translation: tuple[float, float]
  decoy_rotation_deg: tuple[float, float]
  film: carrier.Film | None = None
  decoy_key_axes: bool = False
  tolerance: tolerance_lib.Tolerance | None = None
  decoy_orbit_turns: bool = False
  rollback: rollback_lib.Rollback | None = None
  polish_augmentation: augment.Augmentation = augment.Augmentation()

  def phase(self, iteration: int) -> tuple[bool, augment.Augmentation]:
    """Whether step `iteration` (1-based) is a joint step (else the decoder polish's), and the distortions it draws
    from (settings.augmentation, then polish_augmentation)."""
    joint = iteration <= self.iterations
    return joint, self.settings.augmentation if joint else self.polish_augmentation


def key_offset(config: ml_collections.ConfigDict) -> float:
  """mark.key_offset checked (positive: an unseen key stands beyond the orbit target)."""
  if not config.mark.key_offset > 0:
    raise ValueError(f"mark.key_offset must be positive, got {config.mark.key_offset}")
  return float(config.mark.key_offset)


def step_settings(config: ml_collections.ConfigDict) -> ConcealSettings:
  """ConcealSettings from conceal.*, conceal.leakage.*, conceal.attacks.* and mark.hidden_size."""
  c = config.conceal
  reading = reveal.Reading(c.decoder.input_norm, bool(c.decoder.clip_input), bool(c.decoder.reference))
  augmentation = settings_lib.from_section(augment.Augmentation, c.attacks)
  leakage = {k: c.leakage[k] for k in ("identity_on_student", "identity_on_teacher_check", "decoy_fraction",
                                        "decoys_hold_student")}
  return settings_lib.from_section(ConcealSettings, c, decoder_width=c.decoder.width, reading=reading,
                                   hidden_size=config.mark.hidden_size, augmentation=augmentation,
                                   identity_distorted=c.attacks.identity_distorted,
                                   film_dc_bound=c.carrier.dc_bound, **leakage)


def plan(config: ml_collections.ConfigDict) -> RunPlan:
  """Every value the conceal job reads, checked (ValueError naming the key)."""
  c, m = config.conceal, config.mark
  settings = step_settings(config)
  polish = settings_lib.check_count("conceal.decoder_opt.polish_steps", c.decoder_opt.polish_steps, minimum=0)
  joint = settings_lib.from_section(loop.LoopSettings, c)
  decoder_optimizer(config)  # checks the decoder optimiser's keys
  optimizer.means_decay_steps(c.lr, c.iterations)
  evaluate.validate(config)
  if m.key_kind not in key_lib.KEY_KINDS:
    raise ValueError(f"mark.key_kind must be one of {key_lib.KEY_KINDS}, got {m.key_kind!r}")
  if not c.lr.means_init > 0:
    raise ValueError("conceal.lr.means_init must be positive")
  lk = c.leakage
  if lk.decoy_views < 0 or (lk.decoy_fraction > 0) != (lk.decoy_views > 0):
    raise ValueError("conceal.leakage.decoy_views must be positive exactly when conceal.leakage.decoy_fraction "
                     f"is, got {lk.decoy_views} and {lk.decoy_fraction}")
  ranges = {name: tuple(lk[name]) for name in ("decoy_translation", "decoy_rotation_deg")}
  for name, (lo, hi) in ranges.items():
    if not 0 <= lo <= hi:
      raise ValueError(f"conceal.leakage.{name} must be a range (lo, hi) with 0 <= lo <= hi, got {(lo, hi)}")
  if c.eval_every < 0 or c.eval_views < 1:
    raise ValueError("conceal.eval_every must be >= 0 and conceal.eval_views >= 1")
  if not m.teacher or not os.path.isfile(m.teacher):
    raise ValueError(f"mark.teacher (the teacher's .ply) is required: no such file {m.teacher!r}")
  sources = (m.hidden,) + extra_hidden(m.extra_hidden, settings.use_decoder)
  if polish and not settings.use_decoder:
    raise ValueError("conceal.decoder_opt.polish_steps needs a decoder (conceal.use_decoder)")
  if settings.augmentation.merge_fraction > 0 and not c.carrier.film:
    raise ValueError("conceal.attacks.merge_fraction merges the carrier film's pairs: it needs conceal.carrier.film")
  if settings.film_dc_bound > 0 and not c.carrier.film:
    raise ValueError("conceal.carrier.dc_bound bounds the carrier film's colours: it needs conceal.carrier.film")
  return RunPlan(settings, dataclasses.replace(joint, iterations=joint.iterations + polish), c.iterations, polish,
                 sources, m.key_kind, m.key_index, m.key_seed, key_offset(config), lk.decoy_views,
                 ranges["decoy_translation"], ranges["decoy_rotation_deg"], carrier.film_plan(config),
                 bool(lk.decoy_key_axes), tolerance_lib.from_config(lk), bool(lk.decoy_orbit_turns),
                 rollback_lib.rollback_settings(c.decoder_opt),
                 augment.polish_draws(settings.augmentation, c.decoder_opt.polish_merge_fraction, polish))


def extra_hidden(extra, use_decoder: bool) -> tuple[str, ...]:
  """mark.extra_hidden checked: at most MAX_EXTRA_HIDDEN image paths or sample names, and a decoder to read
  them."""
  if isinstance(extra, str) or not all(isinstance(source, str) and source for source in extra):
    raise ValueError(f"mark.extra_hidden must be a tuple of image paths or sample names, got {extra!r}")
  if len(extra) > MAX_EXTRA_HIDDEN:
    raise ValueError(f"mark.extra_hidden holds at most {MAX_EXTRA_HIDDEN} images ({MAX_EXTRA_HIDDEN + 1} "
                     f"hidden images in all), got {len(extra)}")
  if extra and not use_decoder:
    raise ValueError("mark.extra_hidden needs a decoder (conceal.use_decoder): one decoder reads every key's image")
  return tuple(extra)


def validate(config: ml_collections.ConfigDict) -> None:
  plan(config)  # the conceal mode's check before anything runs (main.MODES)


def decoder_optimizer(config: ml_collections.ConfigDict) -> optax.GradientTransformation:
  """Adam on the decoder (conceal.decoder_opt): lr decaying log-linearly to lr * lr_final_ratio over the joint
  iterations (1: constant, as released), eps adam_eps (1e-15 as the released code: a weight whose gradient
  has all but vanished still takes steps of the full rate), each tensor's step clipped to RMS update_clip
  (0: off; beyond the paper, against the bursts that follow)."""
  d = config.conceal.decoder_opt
  if not (d.lr > 0 and d.adam_eps > 0):
    raise ValueError("conceal.decoder_opt.lr and conceal.decoder_opt.adam_eps must be positive")
  return optimizer.decaying_adam(d.lr, d.lr_final_ratio, config.conceal.iterations, d.adam_eps,
                                 "conceal.decoder_opt.lr_final_ratio", update_rms_clip=d.update_clip,
                                 clip_name="conceal.decoder_opt.update_clip")


def student_optimizer(config: ml_collections.ConfigDict, extent: float, colours=False) -> optax.GradientTransformation:
  """The student's Adam at conceal.lr (means in units of the scene `extent`; of base colours alone with `colours`)."""
  return optimizer.gaussian_optimizer(config.conceal.lr, extent, config.conceal.iterations, colours)
