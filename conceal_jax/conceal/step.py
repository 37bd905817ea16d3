"""The ConcealGS train state and step (Sec. 2.2-2.3): the objective's gradients, the student's Adam update
and the decoder's gradient-guided update.

One gradient of the summed loss (objective.view_terms, F entering once per decoder term) gives the
student's gradient of L_kd + lambda+ L_d^+ and the decoder's of lambda+ L_d^+ and of lambda- L_d^- as two
separate pytrees; the guidance weighs every decoder layer by the sigmoid of their cosine, and one optax
update applies the result. The views of a step are split over the devices of a mesh (core.parallel) where
there are several; the values are the same with one.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from conceal_jax.conceal import carrier, decoder_pair, guidance, objective, rollback as rollback_lib
from conceal_jax.conceal.settings import ConcealSettings
from conceal_jax.conceal.views import ConcealData, step_views
from conceal_jax.core import loop, parallel
from conceal_jax.gs import capacity
from conceal_jax.splat.render import RenderOptions


@struct.dataclass
class ConcealState:
  """step: int32; student: Gaussians [N]; decoder: U-Net params ({} without a decoder); their optimiser states (the
  student's of what trains: the whole student, or the base colours [F, 3] of views.ConcealData.colour_rows); guard:
  the decoder's rollback.Guard (() without one)."""
  step: jax.Array
  student: Any
  decoder: Any
  student_opt: Any
  decoder_opt: Any
  guard: Any = ()

  def weights_only(self) -> ConcealState:
    """The state without its optimiser states and guard (what scoring reads, moved cheaply)."""
    return self.replace(student_opt=(), decoder_opt=(), guard=())


def create_state(student, decoder, student_tx, decoder_tx, colour_rows=None,
                 rollback: rollback_lib.Rollback | None = None) -> ConcealState:
  """The step-0 state; with `colour_rows` [F], student_tx optimises their base colours alone; with a `rollback`
  (make_step's), a rollback.Guard of the decoder."""
  decoder_opt = decoder_tx.init(decoder)
  return ConcealState(step=jnp.zeros((), jnp.int32), student=student, decoder=decoder,
                      student_opt=student_tx.init(carrier.trained_part(student, colour_rows)),
                      decoder_opt=decoder_opt, guard=rollback_lib.init_guard(decoder, decoder_opt) if rollback else ())


def gradients(student, decoder, views: objective.View, settings: ConcealSettings, options: RenderOptions, mesh=None,
              train_student: bool = True, merges=None, colour_rows=None):
  """({'student': ..., 'plus': ..., 'minus': ...} gradients summed over the stacked views [B], their Terms [B]).
  'student' is the gradient of every term with respect to the student, or where `colour_rows` [F] name the rows
  whose base colours alone train (views.ConcealData), with respect to those colours [F, 3] (the rest of the
  student is then a constant, and nothing else is differentiated); None without `train_student` (the renders
  are not differentiated). 'plus' and 'minus' are the decoder's gradients of lambda+ L_d^+ and of lambda- L_d^-.
  `merges`: the film pairs a decimation merges (views.ConcealData).
  A view's two decoder reads run as one batch (decoder_pair.py: exact here, where both decoder arguments are
  `decoder`)."""
  argnums = (0, 1, 2) if train_student else (1, 2)

  def per_view(shared, view):
    whole, decoder, merges, rows = shared

    def loss(trained, decoder_plus, decoder_minus):
      student = carrier.with_trained(whole, rows, trained)
      terms = objective.view_terms(student, decoder_plus, decoder_minus, view, settings, options, merges,
                                   read_pair=decoder_pair.batched_l1_of_decoded_pair)
      return terms.student + terms.plus + terms.minus, terms

    grads, terms = jax.grad(loss, argnums, has_aux=True)(carrier.trained_part(whole, rows), decoder, decoder)
    named = dict(zip(("student", "plus", "minus")[3 - len(argnums):], grads))
    return named, terms.replace(overflowed=terms.overflowed.astype(jnp.int32))

  grads, terms = parallel.map_reduce_over_batch(per_view, (student, decoder, merges, colour_rows), views, mesh)
  return dict(grads, student=grads.get("student")), terms


def decoder_gradient(plus, minus, settings: ConcealSettings):
  """The decoder's update direction: the guided combination of Sec. 2.3 (eqs. 6-7), or the plain sum of the
  two gradients without guidance (the ablation). Both already carry their loss weights; cosines ignore scale."""
  if not settings.guidance:
    return jax.tree.map(jnp.add, plus, minus), None
  return guidance.guided_decoder_gradient(plus, minus, 1.0, 1.0, settings.granularity)


def make_step(settings: ConcealSettings, options: RenderOptions, student_tx, decoder_tx, mesh=None,
              train_student: bool = True, traces: loop.TraceCounter | None = None,
              rollback: rollback_lib.Rollback | None = None):
  """step(state, data, view, normal_view, key_number, distortion) -> (state, stats), jitted with the state
  donated (views.step_views says what the indices pick; `distortion` is augment.draw's, or None). `options`
  carry a pair capacity: a step whose renders overflowed it returns the state unchanged (gs.capacity).
  Without `train_student` (the decoder polish) the student and its optimiser state stay as they are. With
  `rollback` (the state made `guarded`) a collapsed decoder returns to its guard's snapshot (rollback.py)."""
  s = settings

  def step(state: ConcealState, data: ConcealData, view, normal_view, key_number=0, distortion=None):
    views = step_views(data, view, normal_view, key_number, distortion, s)
    grads, terms = gradients(state.student, state.decoder, views, s, options, mesh, train_student, data.merges,
                             data.colour_rows)
    new = state.replace(step=state.step + 1)
    if train_student:
      rows, student_grads = data.colour_rows, grads["student"]
      trained = carrier.trained_part(state.student, rows)
      if data.ties is not None:  # a film's stacks take one gradient, so they keep one colour
        student_grads = carrier.tie(student_grads, data.ties)
      updates, student_opt = student_tx.update(student_grads, state.student_opt, trained)
      trained = optax.apply_updates(trained, updates)
      if s.film_dc_bound > 0 and rows is not None:  # the film's colours inside what a format stores
        trained = jnp.clip(trained, -s.film_dc_bound, s.film_dc_bound)
      new = new.replace(student=carrier.with_trained(state.student, rows, trained), student_opt=student_opt)
    stats = dict(loss=jnp.sum(terms.student + terms.plus + terms.minus), normal=terms.student[0],
                 plus=terms.plus[1] / s.weight_plus, minus=jnp.sum(terms.minus), psnr=terms.psnr[0],
                 num_pairs=jnp.max(terms.num_pairs))
    if s.use_decoder:
      direction, weights = decoder_gradient(grads["plus"], grads["minus"], s)
      if weights is not None:
        stats["mean_guidance_weight"] = jnp.mean(jnp.stack(jax.tree.leaves(weights)))
      updates, decoder_opt = decoder_tx.update(direction, state.decoder_opt, state.decoder)
      # the sizes of the decoder's gradient and step: a run whose L_d^+ jumps back to its start shows its burst here
      stats["decoder_grad_norm"], stats["decoder_step_norm"] = optax.global_norm(direction), optax.global_norm(updates)
      decoder, guard = optax.apply_updates(state.decoder, updates), state.guard
      if rollback is not None:
        decoder, decoder_opt, guard = rollback_lib.guarded_update(rollback, guard, decoder, decoder_opt, stats["plus"])
        stats["rollbacks"] = guard.rollbacks
      new = new.replace(decoder=decoder, decoder_opt=decoder_opt, guard=guard)
    return capacity.keep_unless_overflowed(jnp.max(terms.overflowed) > 0, new, state), stats

  if traces is not None:
    step = traces.wrap("conceal_step" if train_student else "polish_step", step)
  return jax.jit(step, donate_argnums=0)
