"""StegaNeRF (Li et al. 2023, ICCV, "StegaNeRF: Embedding Invisible Information within Neural Radiance
Fields", Sec. 3) on 3D-GS, the NeRF baseline of the ConcealGS paper (Yang et al. 2025, arXiv:2501.03605,
Tables 1-2), as pure functions of the trained colour, the networks and the cached initial renders.

StegaNeRF keeps the pre-trained scene's geometry and trains only its colour coefficients: here the
teacher's means, scales, rotations and opacities stay fixed and its SH coefficients sh [N, K, 3] are
trained, jointly with a U-Net decoder U and a small classifier C (watermarked vs initial renders):

  L = w_render MSE(R, R_0) + w_hidden MSE(U(R), I) + w_clean MSE(U(R_0), 0) + w_classifier BCE(C)

R is the student's render, R_0 the initial render (the teacher's) of the same view and I the hidden image.
The decoder reads the render at the decoder size with C's score as a 4th channel (`decoder_input`), and
the SH update is masked per basis function (`adaptive_mask_weights`). baseline.steganerf.protocol says
which render carries I:
  all_views   StegaNeRF's own: R of the step's training view (I is recovered from every view).
  check_view  only the student's render at the check view (the ConcealGS setting); R of the training view
              is held to R_0 and U(R_0) -> 0 as in StegaNeRF.
The training job is steganerf_train.py.
"""
from __future__ import annotations

import dataclasses
import functools

import flax.serialization
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from flax import linen as nn

from conceal_jax.conceal import reveal, unet
from conceal_jax.core import fileio, settings as settings_lib
from conceal_jax.gs import optimizer
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, render

PROTOCOLS = ("all_views", "check_view")
# Where the adaptive mask multiplies the SH step: on the gradient, as StegaNeRF states it, or on Adam's
# normalised update; Adam divides each coefficient's gradient by its own running scale, so a mask that
# changes slowly over the steps is undone on the gradient and acts only on the update.
MASK_PLACES = ("gradient", "update")
MASK_EXPONENT = 3
# E_k floor: a band the teacher never used (all zero) is the least important one, and no weight is 0 / 0.
MASK_FLOOR = 1e-12
DECODER_CHANNELS = 4  # the render's 3 and the classifier's score
CLASSIFIER_DEPTH = 3
# The classifier's targets for the two renders of a step: (carries I, initial render).
WATERMARK_LABELS = (1.0, 0.0)
# Adam eps of the decoder and classifier: torch's default, as StegaNeRF trains them. 3D-GS's 1e-15 turns the
# vanishing gradients of a classifier that already separates its two renders into full-size steps, so its
# logits grow without bound until one changed render flips them and the decoder, reading the score as its 4th
# channel, dies to a constant image (measured on lego: experiments/results/baseline_bench_rows.md). This eps
# alone does not keep the decoder alive at StegaNeRF's rate; bench-baselines also lowers and decays it.
NETWORKS_ADAM_EPS = 1e-8


@dataclasses.dataclass(frozen=True)
class StegaNerfSettings:
  """The static choices of one StegaNeRF run (hashable: they shape the traced step): the protocol, the loss
  weights, the widths and Adam learning rates of decoder and classifier, where the SH mask acts, and the
  decoder size S (mark.hidden_size)."""
  protocol: str = "all_views"
  weight_render: float = 1.0
  weight_hidden: float = 0.5
  weight_clean: float = 0.5
  weight_classifier: float = 0.01
  decoder_width: int = 16
  classifier_width: int = 16
  decoder_lr: float = 1e-3
  classifier_lr: float = 1e-3
  networks_lr_final_ratio: float = 1.0
  # Adam eps of the SH colour: torch's default, as StegaNeRF trains its scene's colour. At 3D-GS's 1e-15 the
  # lego check-view run's decoder died, and with 1e-8 it did not (experiments/results/baseline_bench_rows.md).
  sh_adam_eps: float = 1e-8
  mask_at: str = "gradient"
  hidden_size: int = 64

  def __post_init__(self):
    if self.protocol not in PROTOCOLS:
      raise ValueError(f"baseline.steganerf.protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
    if self.mask_at not in MASK_PLACES:
      raise ValueError(f"baseline.steganerf.mask_at must be one of {MASK_PLACES}, got {self.mask_at!r}")
    for name in ("weight_render", "weight_clean", "weight_classifier"):
      if not getattr(self, name) >= 0:
        raise ValueError(f"baseline.steganerf.{name} must be >= 0, got {getattr(self, name)!r}")
    for name in ("weight_hidden", "decoder_lr", "classifier_lr", "sh_adam_eps"):
      if not getattr(self, name) > 0:
        raise ValueError(f"baseline.steganerf.{name} must be positive, got {getattr(self, name)!r}")
    for name in ("decoder_width", "classifier_width"):
      settings_lib.check_count(f"baseline.steganerf.{name}", getattr(self, name))
    optimizer.check_final_ratio("baseline.steganerf.networks_lr_final_ratio", self.networks_lr_final_ratio)
    settings_lib.check_count("mark.hidden_size", self.hidden_size)
    if self.hidden_size % unet.DOWNSAMPLE:
      raise ValueError(f"mark.hidden_size must be a multiple of {unet.DOWNSAMPLE} for the StegaNeRF decoder, "
                       f"got {self.hidden_size}")


def settings_from_config(config: ml_collections.ConfigDict) -> StegaNerfSettings:
  return settings_lib.from_section(StegaNerfSettings, config.baseline.steganerf,
                                   hidden_size=config.mark.hidden_size)


class Classifier(nn.Module):
  """StegaNeRF's classifier of watermarked vs initial renders (Li et al. 2023, Sec. 3): images [B, S, S, 3]
  -> logits [B]. CLASSIFIER_DEPTH stride-2 conv3x3 + ReLU of width * (1, 2, 4) channels, a global mean
  pool, a dense layer to one logit."""
  width: int

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    x = images
    for i in range(CLASSIFIER_DEPTH):
      x = nn.relu(nn.Conv(self.width * 2**i, (3, 3), strides=(2, 2), padding="SAME",
                          kernel_init=nn.initializers.he_normal(), name=f"conv{i}")(x))
    return nn.Dense(1, name="logit")(jnp.mean(x, axis=(1, 2)))[:, 0]


def init_networks(rng: jax.Array, settings: StegaNerfSettings) -> dict:
  """Fresh {'decoder': U-Net params for [B, S, S, 4] input, 'classifier': Classifier params}."""
  decoder_key, classifier_key = jax.random.split(rng)
  s = settings
  dummy = jnp.zeros((1, s.hidden_size, s.hidden_size, 3), jnp.float32)
  return dict(decoder=unet.init_decoder(decoder_key, s.decoder_width, s.hidden_size, DECODER_CHANNELS),
              classifier=jax.jit(Classifier(s.classifier_width).init)(classifier_key, dummy)["params"])


def decoder_input(images: jax.Array, logits: jax.Array) -> jax.Array:
  """Classifier-guided recovery (StegaNeRF, Li et al. 2023, Sec. 3): images [B, S, S, 3] and the classifier's
  logits [B] -> [B, S, S, 4], the score sigmoid(logit) as a constant 4th image plane."""
  plane = jnp.broadcast_to(jax.nn.sigmoid(logits)[:, None, None, None], images.shape[:-1] + (1,))
  return jnp.concatenate([images, plane], axis=-1)


def recover(networks: dict, settings: StegaNerfSettings, images: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(U(images with the classifier's score) [B, S, S, 3] unclipped, the classifier's logits [B]) of
  decoder-size renders [B, S, S, 3]."""
  logits = Classifier(settings.classifier_width).apply({"params": networks["classifier"]}, images)
  return reveal.decode(networks["decoder"], settings.decoder_width, decoder_input(images, logits)), logits


def adaptive_mask_weights(sh: jax.Array) -> jax.Array:
  """StegaNeRF's adaptive gradient masking (Li et al. 2023, ICCV, Sec. 3.3): sh [N, K, 3] -> weights [K],
  w_k = (E_min / E_k)^3 with E_k = mean |sh[:, k, :]| over Gaussians and channels, the importance of basis
  function k. The most used bases (the DC term above all) get the smallest weights, so the hidden image
  goes into the colour coefficients a viewer notices least. E_k is floored at MASK_FLOOR (an unused band
  is the least important one, weight 1)."""
  energy = jnp.maximum(jnp.mean(jnp.abs(sh), axis=(0, 2)), MASK_FLOOR)
  return (jnp.min(energy) / energy)**MASK_EXPONENT


def adaptive_masking() -> optax.GradientTransformation:
  """Multiplies SH updates [N, K, 3] by `adaptive_mask_weights` of the current coefficients (`params`)."""

  def update(updates, state, params=None):
    if params is None:
      raise ValueError("adaptive_masking needs the SH coefficients (params) to weigh their bases")
    return updates * adaptive_mask_weights(params)[None, :, None], state

  return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def sh_optimizer(lr: ml_collections.ConfigDict, mask_at: str, eps: float) -> optax.GradientTransformation:
  """Adam (eps `eps`; StegaNerfSettings.sh_adam_eps) on sh [N, K, 3] with the per-basis rates of `lr` (sh_dc,
  sh_rest), the adaptive mask on the gradient or on Adam's update (`mask_at`, see MASK_PLACES)."""
  adam = optax.scale_by_adam(b1=0.9, b2=0.999, eps=eps)

  def scale_by_rates(updates, params=None):
    del params
    return -optimizer.sh_learning_rates(lr, updates.shape[1], updates.dtype)[None, :, None] * updates

  steps = (adaptive_masking(), adam) if mask_at == "gradient" else (adam, adaptive_masking())
  return optax.chain(*steps, optax.stateless(scale_by_rates))


def networks_optimizer(settings: StegaNerfSettings, iterations: int) -> optax.GradientTransformation:
  """Adam (eps NETWORKS_ADAM_EPS) on {'decoder', 'classifier'} with their own learning rates, each decaying to
  networks_lr_final_ratio of itself over the run's `iterations` steps."""
  adam = lambda rate: optimizer.decaying_adam(rate, settings.networks_lr_final_ratio, iterations, NETWORKS_ADAM_EPS,
                                              "baseline.steganerf.networks_lr_final_ratio")
  return optax.multi_transform(dict(decoder=adam(settings.decoder_lr), classifier=adam(settings.classifier_lr)),
                               dict(decoder="decoder", classifier="classifier"))


def steganerf_objective(sh: jax.Array, networks: dict, data: dict, teacher: Gaussians, view,
                        settings: StegaNerfSettings, options: RenderOptions) -> tuple[jax.Array, dict]:
  """StegaNeRF's loss (Li et al. 2023, Sec. 3) at training view `view` -> (total, aux).

  sh [N, K, 3]: the student's colour on the `teacher`'s frozen geometry. `data` is views.build_data's ConcealData:
  teacher renders [V, H, W, 3] (R_0) and at the decoder size [V, S, S, 3], stacked training cameras, the
  check camera and the hidden image [S, S, 3]. The render carrying I (see the protocols) and R_0 of `view`
  go through the classifier (labels WATERMARK_LABELS, BCE averaged over the two) and the decoder.
  aux: render, hidden, clean, classifier (the unweighted terms), rgb (the student's render of `view`),
  num_pairs and overflowed (of the step's renders, see gs.capacity).
  """
  s = settings
  student = teacher.replace(sh=sh)
  out = render(student, jax.tree.map(lambda x: x[view], data.cameras), options)
  render_term = jnp.mean((out.rgb - data.teacher[view])**2)
  marked, num_pairs, overflowed = out.rgb, out.num_pairs, out.overflowed
  if s.protocol == "check_view":
    check = render(student, data.keys.at(0).camera, options)
    marked, num_pairs, overflowed = check.rgb, jnp.maximum(num_pairs, check.num_pairs), overflowed | check.overflowed
  inputs = jnp.stack([reveal.resize_for_decoder(marked, s.hidden_size), data.teacher_small[view]])
  revealed, logits = recover(networks, s, inputs)
  hidden_term = jnp.mean((revealed[0] - data.keys.hidden[0])**2)
  clean_term = jnp.mean(revealed[1]**2)
  classifier_term = jnp.mean(optax.sigmoid_binary_cross_entropy(logits, jnp.asarray(WATERMARK_LABELS)))
  total = (s.weight_render * render_term + s.weight_hidden * hidden_term + s.weight_clean * clean_term
           + s.weight_classifier * classifier_term)
  return total, dict(render=render_term, hidden=hidden_term, clean=clean_term, classifier=classifier_term,
                     rgb=out.rgb, num_pairs=num_pairs, overflowed=overflowed)


@functools.partial(jax.jit, static_argnames="settings")
def reveal_renders(networks: dict, renders: jax.Array, settings: StegaNerfSettings) -> jax.Array:
  """renders [V, H, W, 3] -> revealed images [V, S, S, 3] in [0, 1]: resized to the decoder size, scored by
  the classifier, decoded with the score as the 4th channel."""
  return jnp.clip(recover(networks, settings, reveal.resize_for_decoder(renders, settings.hidden_size))[0], 0.0, 1.0)


def steganerf_reveal(networks: dict, settings: StegaNerfSettings):
  """The reveal function of StegaNeRF (renders [V, H, W, 3] -> [V, S, S, 3]), for
  conceal.evaluate_concealment."""
  return functools.partial(reveal_renders, networks, settings=settings)


def save_networks(path: str, networks: dict, settings: StegaNerfSettings) -> None:
  """Decoder and classifier params with the settings that shape them, as one msgpack file written
  atomically."""
  state = jax.tree.map(np.asarray, flax.serialization.to_state_dict(networks))
  fileio.write_bytes(path, flax.serialization.msgpack_serialize(
      dict(settings=dataclasses.asdict(settings), params=state)))
