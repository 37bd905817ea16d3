"""The step's gradients as two lanes of one program: lane 0 the normal view, lane 1 the check view.

The ConcealGS step (Sec. 2.2-2.3) needs the student's gradient of L_kd + lambda+ L_d^+ and, for the guided
decoder update, the decoder's gradients of lambda+ L_d^+ and of lambda- L_d^- as two separate pytrees (see
objective.py, the same objective written as plain functions). Here they are computed as two lanes
(core.lanes) so that a CPU host runs them on its two cores at once. A lane renders one camera and decodes
two images at the decoder size, its own render and one cached teacher render:

  lane   camera       pixel loss on the render              own render, decoded     teacher render, decoded
  0      normal view  L_kd (or the 3D-GS photometric loss)  L_d^- (identity_on_     L_d^- on the normal view
                                                            student), no gradient   (paper variant)
                                                            to the render
  1      check view   released variant: L1 to the check     L_d^+: to the hidden     L_d^- on the check view
                      image                                 image I                  (identity_on_teacher_check,
                                                                                     or the released variant)

What differs between the lanes is data (`lane_inputs`: cameras, targets, per-image loss weights, zero where
a term is off), never code, so both lanes are one program. Per image, the decoder's gradient is taken on
its own (a vmap over the lane's two images), so that the lane's L_d^+ and L_d^- gradients stay apart; the
render's gradient is chained by hand (jax.vjp) from the pixel loss and from the L_d^+ image's input gradient.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import augment, objective
from conceal_jax.conceal.objective import ConcealSettings
from conceal_jax.core import lanes
from conceal_jax.gs import losses, metrics
from conceal_jax.splat.render import RenderOptions, render

# augment.distort and perturb_gaussians with these are the identity (a point kernel, zero noise, no dropout,
# brightness 0, contrast 1):
# lane 0's render is not distorted
NO_DISTORTION = dict(blur=np.float32(0.0), noise=np.float32(0.0), seed=np.uint32(0), dropout=np.float32(0.0),
                     param_noise=np.float32(0.0), model_seed=np.uint32(0), brightness=np.float32(0.0),
                     contrast=np.float32(1.0))


def identity_weights(settings: ConcealSettings) -> dict:
  """Per image weight of lambda- L_d^- (eq. 4, the mean over its B inputs) on the student's normal render,
  the teacher's normal-view render and the teacher's check render: lambda- / B on objective.identity_sources,
  0 elsewhere and without L_d^-."""
  sources = objective.identity_sources(settings) if settings.identity_loss else ()
  return {name: settings.weight_minus / len(sources) if name in sources else 0.0
          for name in ("student", "teacher_normal", "teacher_check")}


def lane_inputs(data: dict, view, normal_view, settings: ConcealSettings, distortion=None) -> list[dict]:
  """The two lanes' data (objective.key_data already applied): camera, pixel target [H, W, 3] with its L1
  and photometric weights, the distortion (augment.draw's) of the own render's image (lane 0's only with
  identity_distorted) and of the model it is rendered from (the check lane's only), the own render's decoded
  target and weights (plus: lambda+ of L_d^+, minus: its L_d^- share, target_is_input: 1 for an identity
  target, which with identity_perturbed is read from a second render, of the model perturbed by
  identity_model), and the teacher render decoded beside it with its L_d^- share."""
  s = settings
  w = identity_weights(s)
  distortion = NO_DISTORTION if distortion is None else distortion
  check = data["check_camera"]
  check_target = data["check_image"] if s.variant == "released" else jnp.zeros((check.height, check.width, 3))
  normal_target = data["teacher"][view] if s.distill else data["images"][view]
  f32 = jnp.float32
  normal = dict(camera=jax.tree.map(lambda x: x[view], data["cameras"]), pixel_target=normal_target,
                l1=f32(s.weight_kd if s.distill else 0.0), photometric=f32(0.0 if s.distill else 1.0),
                distortion=distortion if s.identity_distorted else NO_DISTORTION, model=NO_DISTORTION,
                identity_model=distortion, own_target=data["hidden"], own_plus=f32(0.0), own_minus=f32(w["student"]),
                target_is_input=f32(1.0), teacher_small=data["teacher_small"][normal_view],
                teacher_minus=f32(w["teacher_normal"]))
  check = dict(camera=check, pixel_target=check_target, l1=f32(s.weight_check if s.variant == "released" else 0.0),
               photometric=f32(0.0), distortion=distortion, model=distortion, identity_model=NO_DISTORTION,
               own_target=data["hidden"], own_plus=f32(s.weight_plus), own_minus=f32(0.0), target_is_input=f32(0.0),
               teacher_small=data["teacher_check_small"], teacher_minus=f32(w["teacher_check"]))
  return [normal, check]


def lane_gradients(shared, lane: dict, settings: ConcealSettings, options: RenderOptions,
                   student_grad: bool = True) -> dict:
  """One lane: values and gradients of its terms. shared = (student, decoder); see the module doc. Without
  `student_grad` (static: the decoder polish) the render's backward pass is not taken and the result has no
  student_grad."""
  s = settings
  student, decoder = shared

  def rendered(g):
    out = render(augment.perturb_gaussians(g, lane["model"], s.augmentation), lane["camera"], options)
    return out.rgb, (out.num_pairs, out.overflowed)

  rgb, render_vjp, (num_pairs, overflowed) = jax.vjp(rendered, student, has_aux=True)

  def pixel_loss(image):
    value = lane["l1"] * losses.l1(image, lane["pixel_target"])
    if not s.distill:  # the photometric loss (SSIM) only where a lane may need it
      value = value + lane["photometric"] * losses.photometric_loss(image, lane["pixel_target"])
    return value

  pixel, pixel_ct = jax.value_and_grad(pixel_loss)(rgb)

  identity = lane["target_is_input"]
  if s.identity_perturbed:
    # the identity target's image is a constant second render, of the perturbed student (identity_rgb); only
    # the lane with that target renders it (a cond: on the mesh each device takes its own branch)
    def perturbed():
      out = render(augment.perturb_gaussians(student, lane["identity_model"], s.augmentation), lane["camera"], options)
      return jax.lax.stop_gradient(out.rgb), out.num_pairs, out.overflowed

    second, second_pairs, second_overflowed = jax.lax.cond(
        identity > 0, perturbed, lambda: (jax.lax.stop_gradient(rgb), num_pairs, overflowed))
    num_pairs, overflowed = jnp.maximum(num_pairs, second_pairs), overflowed | second_overflowed
    decoded_render = lambda image: identity * second + (1 - identity) * image
  else:
    decoded_render = lambda image: image
  small, prepared_vjp = jax.vjp(
      lambda image: objective.check_decoder_input(decoded_render(image), lane["distortion"], s), rgb)
  images = jnp.stack([small, lane["teacher_small"]])
  own_target = identity * jax.lax.stop_gradient(small) + (1 - identity) * lane["own_target"]
  targets = jnp.stack([own_target, lane["teacher_small"]])

  def image_loss(params, image, target):
    return losses.l1(objective.decoded(params, image, s), target)

  values, (params_grads, image_grads) = jax.vmap(jax.value_and_grad(image_loss, argnums=(0, 1)),
                                                 in_axes=(None, 0, 0))(decoder, images, targets)
  plus_w = jnp.stack([lane["own_plus"], 0.0])
  minus_w = jnp.stack([lane["own_minus"], lane["teacher_minus"]])
  weigh = lambda w: jax.tree.map(lambda g: jnp.tensordot(w, g, axes=1), params_grads)
  # only L_d^+ reaches the render: L_d^- trains the decoder alone (its own-render input is a constant)
  out = dict(pixel=pixel, plus=jnp.sum(plus_w * values), plus_raw=(lane["own_plus"] > 0) * values[0],
             minus=jnp.sum(minus_w * values), psnr=metrics.psnr(jnp.clip(rgb, 0, 1), lane["pixel_target"]),
             num_pairs=num_pairs, overflowed=overflowed.astype(jnp.int32), plus_grad=weigh(plus_w),
             minus_grad=weigh(minus_w))
  if student_grad:
    (small_ct,) = prepared_vjp(lane["own_plus"] * image_grads[0])
    (out["student_grad"],) = render_vjp(pixel_ct + small_ct)
  return out


def gradients(student, decoder, data: dict, view, normal_view, settings: ConcealSettings, options: RenderOptions,
              distortion=None, mesh=None, student_grad: bool = True) -> dict:
  """The step's values and gradients from both lanes (side by side on `mesh`, in turn without):
  student_grad (of L_kd + lambda+ L_d^+ [+ the released check L1]; None without `student_grad`, whose lanes
  skip the renders' backward: the lanes' outputs travel as one vector, so an unused gradient would still be
  computed and gathered), plus_grad (lambda+ grad L_d^+) and minus_grad (lambda- grad L_d^-) for the
  decoder; normal (the pixel term of the normal view), check (the
  check view's terms), plus (L_d^+ unweighted), minus (lambda- L_d^-), psnr of the normal render,
  num_pairs (the larger of the two renders) and overflowed."""
  normal, check = lanes.map_lanes(lambda shared, lane: lane_gradients(shared, lane, settings, options, student_grad),
                                  (student, decoder), lane_inputs(data, view, normal_view, settings, distortion), mesh)
  both = lambda name: jax.tree.map(jnp.add, normal[name], check[name])
  return dict(student_grad=both("student_grad") if student_grad else None, plus_grad=both("plus_grad"),
              minus_grad=both("minus_grad"),
              normal=normal["pixel"], check=check["pixel"] + both("plus"), plus=both("plus_raw"), minus=both("minus"),
              psnr=normal["psnr"], num_pairs=jnp.maximum(normal["num_pairs"], check["num_pairs"]),
              overflowed=(normal["overflowed"] + check["overflowed"]) > 0)
