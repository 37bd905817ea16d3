"""The ConcealGS objective, written once, as a pure function of one view's render.

ConcealGS (Yang et al. 2025, arXiv:2501.03605, Sec. 2.2) trains a student scene G_w and a decoder F on
L = L_kd (eq. 3) + L_d^- (eq. 4) + L_d^+ (eq. 5). A step renders two views: a normal view P_m (L_kd, and
L_d^- on the teacher's render of it) and the check view P_c (L_d^+). Both are a `View`: what differs
between them is data (targets and per-term weights, zero where a term does not apply), so one function
serves both and the views stack on a leading axis (in turn, or split over devices by the step).

`view_terms` returns the terms grouped by what they train: `student` (the render's pixel loss), `plus`
(lambda+ L_d^+, which trains the student and the decoder) and `minus` (lambda- L_d^-, the decoder only).
F enters it twice, as `decoder_plus` in L_d^+ and as `decoder_minus` in L_d^-, so that one gradient of
the summed loss with respect to (student, decoder, decoder) yields the two decoder gradient pytrees that
the guided update compares (guidance.py, Sec. 2.3).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from conceal_jax.conceal import augment, perturb, reveal, subsets
from conceal_jax.conceal.settings import ConcealSettings
from conceal_jax.gs import losses, metrics
from conceal_jax.splat import linear
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.render import RenderOptions, RenderOutput, render


@struct.dataclass
class View:
  """One rendered view of a step and the targets of its terms (all traced; stacked views gain an axis).

  camera: where the student renders; target [H, W, 3] and l1_weight / photometric_weight: the pixel loss
  (L_kd against the teacher's render with weight_kd, the 3D-GS photometric loss against ground truth, or
  the released variant's check-view L1 to its image with weight_check); model: the distortion
  (augment.draw) the student is rendered through, image: the one its render is read through by F;
  hidden [S, S, 3] and plus_weight: L_d^+'s target and lambda+ (the check view's); own_minus_weight:
  L_d^-'s share on this render (the student's normal view with identity_on_student); teacher_small
  [S, S, 3] and teacher_minus_weight: a teacher render at the decoder size and its L_d^- share; rows: None, or
  int32 [M] the student rows its render reads (subsets.py: the same image), and fixed: whether its render is
  fixed_rgb [H, W, 3] (the teacher's: no row that trains reaches it), not rendered; weights: None, or its render
  as a linear map of the colours (linear.ColourWeights, of linear_check's maps), which it is read through where
  `linear` (bool) holds, else rendered.
  """
  camera: Camera
  target: jax.Array
  l1_weight: jax.Array
  photometric_weight: jax.Array
  model: dict
  image: dict
  hidden: jax.Array
  plus_weight: jax.Array
  own_minus_weight: jax.Array
  teacher_small: jax.Array
  teacher_minus_weight: jax.Array
  rows: jax.Array | None = None
  fixed: jax.Array | None = None
  fixed_rgb: jax.Array | None = None
  weights: linear.ColourWeights | None = None
  linear: jax.Array | None = None


@struct.dataclass
class Terms:
  """A view's loss terms (scalars, or [B] for stacked views) grouped by what they train, and what the step
  reports: psnr of the render against its target, num_pairs and overflowed (gs.capacity)."""
  student: jax.Array
  plus: jax.Array
  minus: jax.Array
  psnr: jax.Array
  num_pairs: jax.Array
  overflowed: jax.Array


def decoder_view(rgb: jax.Array, settings: ConcealSettings) -> jax.Array:
  """[S, S, 3] a render [H, W, 3] as the decoder is given it (reveal.Reading's clip, resized)."""
  return reveal.resize_for_decoder(rgb, settings.hidden_size, settings.reading.clip)


def decoded(decoder, images: jax.Array, settings: ConcealSettings) -> jax.Array:
  """F(images) [..., S, S, 3]; the images themselves without a decoder (the "w/o decoder" ablation)."""
  s = settings
  if not s.use_decoder:
    return images
  return reveal.decode(decoder, s.decoder_width, images, s.reading)


def pixel_loss(rgb: jax.Array, view: View, settings: ConcealSettings) -> jax.Array:
  """The render's own term: l1_weight |rgb - target| (L_kd, eq. 3, on a normal view of the paper variant) plus,
  where ground truth supervises the normal view, photometric_weight times the 3D-GS loss."""
  value = view.l1_weight * losses.distillation_loss(rgb, view.target)
  if not settings.distill:  # the SSIM term only where a view may need it
    value = value + view.photometric_weight * losses.photometric_loss(rgb, view.target)
  return value


def l1_of_decoded_pair(decoders, images: jax.Array, targets: jax.Array, settings: ConcealSettings) -> jax.Array:
  """[2] l1_of_decoded of images [2, S, S, 3] against targets [2, S, S, 3], image i read by decoders[i]."""
  return jnp.stack([l1_of_decoded(d, images[i], targets[i], settings) for i, d in enumerate(decoders)])


def view_terms(student, decoder_plus, decoder_minus, view: View, settings: ConcealSettings,
               options: RenderOptions, merges=None, read_pair=l1_of_decoded_pair) -> Terms:
  """The terms of one view: the student rendered through view.model (with `merges`, the film pairs a decimation
  merges: perturb.perturb_gaussians; through view.weights where view.linear holds) and its pixel loss;
  the render read by F at the decoder size (through view.image), once: against I where the view carries L_d^+
  (lambda+ L_d^+, eq. 5, through the render, F as `decoder_plus`), else against itself as a constant (its L_d^-
  share, eq. 4, F as `decoder_minus`); and the teacher render against itself (its L_d^- share). A view carries L_d^+ or
  holds F to the identity on its own render, never both (views.step_views). `read_pair` computes the two reads
  (l1_of_decoded_pair, or decoder_pair.py's batch of two)."""
  s = settings
  perturbed = lambda g, rows: perturb.perturb_gaussians(g, view.model, s.augmentation, merges, rows)
  out = rendered(student, view, options, perturbed)
  seen = decoder_view(augment.distort(out.rgb, view.image, s.augmentation), s)
  reads_hidden = view.plus_weight > 0
  own_decoder = jax.tree.map(lambda p, m: jnp.where(reads_hidden, p, m), decoder_plus, decoder_minus)
  constant = jax.lax.stop_gradient(seen)
  images = jnp.stack([jnp.where(reads_hidden, seen, constant), view.teacher_small])
  targets = jnp.stack([jnp.where(reads_hidden, view.hidden, constant), view.teacher_small])
  own, teacher = read_pair((own_decoder, decoder_minus), images, targets, s)
  return Terms(student=pixel_loss(out.rgb, view, s), plus=view.plus_weight * own,
               minus=view.own_minus_weight * own + view.teacher_minus_weight * teacher,
               psnr=metrics.psnr(jnp.clip(out.rgb, 0.0, 1.0), view.target), num_pairs=out.num_pairs,
               overflowed=out.overflowed)


def rendered(gaussians, view: View, options: RenderOptions, perturbed=subsets.rows_of) -> RenderOutput:
  """The view's render of `gaussians` (its rgb and pair counts), as `perturbed(gaussians, rows)` gives them (the
  rows [M] it reads, or None: all; default: as they are): of its rows alone where it has them (the same image:
  subsets.py); where it is fixed its fixed image, neither perturbed nor rendered (no pairs); where view.linear
  holds, the same image through its linear map view.weights (linear.render_through), with the pairs its render
  would need."""
  if view.rows is None:
    return render(perturbed(gaussians, None), view.camera, options)

  def draw():
    out = render(perturbed(gaussians, view.rows), view.camera, options)
    return out.replace(radii=jnp.zeros((), jnp.int32))  # the subset's, not the student's

  blank = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(draw))
  held = lambda: blank.replace(rgb=view.fixed_rgb)
  if view.weights is None:
    return jax.lax.cond(view.fixed, held, draw)

  def through():
    rgb = linear.render_through(view.weights, perturbed(gaussians, view.rows), view.camera, options)
    pairs = view.weights.num_pairs.astype(blank.num_pairs.dtype)
    return blank.replace(rgb=rgb.astype(blank.rgb.dtype), num_pairs=pairs)

  return jax.lax.switch(jnp.where(view.fixed, 1, jnp.where(view.linear, 2, 0)), (draw, held, through))


def l1_of_decoded(decoder, image: jax.Array, target: jax.Array, settings: ConcealSettings) -> jax.Array:
  """|F(image) - target| for one image [S, S, 3]: L_d^+ (eq. 5, losses.hidden_image_loss) with target I, L_d^-
  (eq. 4, losses.decoder_identity_loss) with target the image itself; the two are the same mean absolute error."""
  return losses.hidden_image_loss(decoded(decoder, image, settings), target)
