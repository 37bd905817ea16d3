"""The concealment job, `--config.mode=conceal`: ConcealGS (Yang et al. 2025, arXiv:2501.03605, Sec. 2.2-2.3)
hides an image in a trained 3D-GS scene.

A student scene G_w, initialised from the teacher G_o (mark.teacher), and a U-Net decoder F are trained
together so that F reveals the hidden image I from the student's render at the secret check view P_c, while
F is the identity on normal views and the student's renders stay the teacher's. The objective is in
objective.py, the step in step.py; the recipes a user chooses between are config files (configs/conceal.py).
The number of Gaussians is fixed: the student is the teacher's set, refined, or (conceal.carrier) the teacher's
set unchanged and a carrier film that only the key sees.
"""
from __future__ import annotations

import dataclasses
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, reveal, scoring, settings as settings_lib
from conceal_jax.conceal import align, carrier, grouping, linear_check, merge_costs, message as message_lib, near, unet
from conceal_jax.conceal import tolerance as tolerance_lib, views as views_lib
from conceal_jax.conceal.step import create_state, make_step
from conceal_jax.core import fileio, loop, parallel
from conceal_jax.data import ply
from conceal_jax.gs import capacity, evaluate, metrics
from conceal_jax.splat import render as render_lib

STUDENT_FILE = "student.ply"
DECODER_FILE = "decoder.msgpack"
KEY_FILE = "key.json"
HIDDEN_FILE = "hidden.png"  # the key's hidden image; an extra key k's is hidden_key{k}.png
SUMMARY_FILE = "conceal.json"
MESSAGE_FILE = "message.json"


@dataclasses.dataclass
class Run:
  """A concealment run's fixed inputs: the plan, teacher, the student's start (the teacher, with the carrier
  film after it when there is one), scene, hidden images [K][S, S, 3], key cameras [K] with their key.json
  descriptions, decoy cameras, render options and the step's device data."""
  plan: settings_lib.RunPlan
  teacher: object
  start: object
  scene: object
  hiddens: list
  keys: list
  decoys: list
  options: render_lib.RenderOptions
  data: views_lib.ConcealData
  message: np.ndarray | None = None  # the bits hidden in message mode (mark.message_bits), hiddens[0] their image
  neighbourhoods: merge_costs.Neighbourhoods = dataclasses.field(default_factory=merge_costs.Neighbourhoods)


class Marking(NamedTuple):
  """What a concealment hides where, and what it is scored against: the teacher, the scene, the hidden images
  [K][S, S, 3], the key cameras [K] with their key.json descriptions, the render options, and the bits hidden in
  message mode (mark.message_bits; hiddens[0] their image)."""
  teacher: object
  scene: object
  hiddens: list
  keys: list
  options: render_lib.RenderOptions
  message: np.ndarray | None


def marking(config: ml_collections.ConfigDict, plan: settings_lib.RunPlan) -> Marking:
  """Loads the teacher, the scene and the hidden images and chooses the keys (nothing rendered)."""
  teacher = ply.load_ply(config.mark.teacher)
  hiddens = [hidden_lib.load_hidden_image(source, plan.settings.hidden_size) for source in plan.sources]
  message = message_lib.configured_message(config.mark, config.seed)
  if message is not None:
    hiddens[0] = message_lib.message_image(message, plan.settings.hidden_size)
  scene = evaluate.load_scene_data(config)
  keys = key_lib.key_cameras(scene.train_cameras, plan.key_kind, plan.key_index, plan.key_seed, len(hiddens) - 1,
                             plan.key_offset)
  # each key records the length its decoys' (and the leakage figure's) translations are fractions of
  lengths = [near.near_length(teacher, camera, scene.train_cameras) for camera, _ in keys]
  keys = [(camera, dict(info, near_length=length, near_length_from=source))
          for (camera, info), (length, source) in zip(keys, lengths)]
  if plan.film is not None and plan.film.at_decoder_size:  # the decoder's input rendered, not resized
    keys = [(camera.resized(plan.settings.hidden_size, plan.settings.hidden_size), info) for camera, info in keys]
  return Marking(teacher, scene, hiddens, keys, evaluate.render_options(config, scene.background), message)


def prepare(config: ml_collections.ConfigDict, plan: settings_lib.RunPlan) -> Run:
  """The marking, decoys around each key (from its own seed), the carrier film, and what the step reads of the
  teacher, rendered."""
  s = plan.settings
  teacher, scene, hiddens, keys, options, message = marking(config, plan)
  decoys = near.keys_decoys(keys, plan.decoy_views, plan.decoy_translation, plan.decoy_rotation_deg, plan.key_seed,
                            plan.decoy_key_axes, plan.decoy_orbit_turns)
  check_cameras, check_hiddens = tolerance_lib.check_views(plan.tolerance, plan.key_seed, keys, hiddens)
  # the released variant's check-view L1 target: a training-camera key's image (elsewhere the teacher's render)
  key_images = [scene.train_images[info["index"]] for _, info in keys] if plan.key_kind == "train_index" else None
  start, colour_rows = carrier.student_start(plan.film, teacher, keys[0][0], scene.train_cameras, scene.test_cameras,
                                             options, s.hidden_size)
  merges, ties, neighbourhoods = None, None, merge_costs.Neighbourhoods()
  if plan.film is not None:
    ties = carrier.tied_rows(start.num - teacher.num, plan.film.stack) if plan.film.stack > 1 else None
    if s.augmentation.merge_fraction > 0:
      merges = grouping.training_merges(start, teacher.num, s.augmentation, neighbourhoods=neighbourhoods)
  # with only the film's colours trained, each view renders the rows that reach it (subsets.py); not where
  # parameter noise moves every Gaussian's geometry
  reach = (dict(student=start, check_states=linear_check.states(s.augmentation),
                linear_maps_mb=config.conceal.carrier.linear_maps_mb)
           if plan.film is not None and s.augmentation.param_noise_max == 0 else {})
  normal_cameras = list(scene.train_cameras) + decoys
  data = views_lib.build_data(scene.train_images, teacher, options, normal_cameras, check_cameras, check_hiddens,
                              s.hidden_size, s.reading.clip, key_images, colour_rows, merges, ties,
                              plan.film is not None and plan.film.at_decoder_size,
                              tolerance_lib.held_to_identity(plan.tolerance, keys, normal_cameras), **reach)
  return Run(plan, teacher, start, scene, hiddens, keys, decoys, options, data, message, neighbourhoods)


def initial_decoder(config: ml_collections.ConfigDict, settings: settings_lib.ConcealSettings, keys=None):
  """A fresh decoder ({} without one), the VGG16 encoder loaded with conceal.decoder.vgg_init; a reading with a
  reference starts it at the clean teacher's check render of the first of `keys` (views.ConcealData.keys; None:
  zeros, a template of the shapes)."""
  if not settings.use_decoder:
    return {}
  size, reference = settings.hidden_size, None
  if settings.reading.reference:
    reference = jnp.zeros((size, size, 3)) if keys is None else keys.teacher_check[0]
  params = unet.init_decoder(jax.random.key(config.seed), settings.decoder_width, size, reference=reference)
  return unet.load_vgg16_encoder(params) if config.conceal.decoder.vgg_init else params


def reveal_fn(settings: settings_lib.ConcealSettings, decoder):
  """The run's reveal function (reveal.decoder_reveal) with `decoder` (ignored without one)."""
  return reveal.decoder_reveal(decoder if settings.use_decoder else None, settings.decoder_width,
                               settings.hidden_size, settings.reading)


def curve_record(run: Run, state, eval_views) -> dict:
  """One point of the curves over training: the hidden image's PSNR / SSIM at the check view (and at each
  key with several) and the student's test PSNR on `eval_views` (cameras, targets)."""
  revealed = scoring.reveal_at_keys(state.student, [camera for camera, _ in run.keys], run.options,
                                    reveal_fn(run.plan.settings, state.decoder))
  record = dict(hidden_psnr=float(metrics.psnr(revealed[0], run.hiddens[0])),
                hidden_ssim=float(metrics.ssim(revealed[0], run.hiddens[0])),
                test_psnr=evaluate.views_psnr(state.student, *eval_views, run.options))
  if len(run.keys) > 1:
    record.update(hidden_psnr_keys=[float(metrics.psnr(r, h)) for r, h in zip(revealed, run.hiddens)],
                  hidden_ssim_keys=[float(metrics.ssim(r, h)) for r, h in zip(revealed, run.hiddens)])
  return record


def save_outputs(run: Run, workdir: str, state) -> None:
  """student.ply, decoder.msgpack, key.json (each extra key numbered, with its image's source; its render options
  the run's, reading the SH bands the student shows at the keys: align.key_options) and the hidden images."""
  s = run.plan.settings
  ply.save_ply(os.path.join(workdir, STUDENT_FILE), jax.device_get(state.student))
  if s.use_decoder:
    reveal.save_decoder(os.path.join(workdir, DECODER_FILE), state.decoder)
  (check_camera, info), extra = run.keys[0], run.keys[1:]
  options = align.key_options(state.student, [camera for camera, _ in run.keys], run.options)
  info = dict(info, hidden_size=s.hidden_size, uses_decoder=s.use_decoder, decoder_width=s.decoder_width,
              **s.reading.key_fields(), render_options=dataclasses.asdict(options),
              **(message_lib.key_fields(run.message) if run.message is not None else {}))
  key_lib.save_key(os.path.join(workdir, KEY_FILE), check_camera, info,
                   [(camera, dict(more, number=k, hidden=source))
                    for k, ((camera, more), source) in enumerate(zip(extra, run.plan.sources[1:]), 1)])
  for k, image in enumerate(run.hiddens):
    fileio.write_image(os.path.join(workdir, f"hidden_key{k}.png" if k else HIDDEN_FILE), image)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None = None) -> dict:
  """Trains student + decoder (checkpointed, resumable), then writes the student, decoder, key, hidden
  images, conceal.json (settings, timing, curves) and metrics.json (scoring.evaluate_concealment); in message
  mode also message.json, the message read from the key's reveal (message.read_message)."""
  plan = settings_lib.plan(config)
  s, c = plan.settings, config.conceal
  run = prepare(config, plan)
  mesh = parallel.batch_mesh(2)  # a step renders two views
  data = parallel.replicate(run.data, mesh)
  student_tx = settings_lib.student_optimizer(config, run.scene.scene_extent(), run.data.colour_rows is not None)
  decoder_tx = settings_lib.decoder_optimizer(config)
  traces = loop.TraceCounter()
  # GrowingSteps' key is the phase: the joint steps (True), then the decoder polish's
  steps = capacity.GrowingSteps(lambda joint, options: make_step(s, options, student_tx, decoder_tx, mesh, joint,
                                                                 traces, plan.rollback), run.options)
  steps.grow(render_lib.initial_capacity(run.start.num, run.options))
  num_views, num_keys = len(run.scene.train_cameras), len(run.keys)

  def fresh(_meta=None):
    student = jax.tree.map(lambda x: jnp.array(x, copy=True), run.start)  # the step donates its buffers
    return create_state(student, initial_decoder(config, s, run.data.keys), student_tx, decoder_tx,
                        run.data.colour_rows, plan.rollback)

  regroup = grouping.regrouping(run.teacher.num, s.augmentation, c.checkpoint_every, run.neighbourhoods)

  def step(state, iteration):
    nonlocal data
    if regroup is not None and regroup.due(iteration):
      data = regrouped(run, data, jax.device_get(state.student), iteration, regroup, mesh)
    joint, views, distortion, key = views_lib.step_draws(plan, np.random.default_rng([config.seed, iteration]),
                                                         iteration, num_views, len(run.decoys), num_keys)
    return steps(joint, parallel.replicate(state, mesh), data, *views, key, distortion)

  eval_views = evaluate.held_out_views(run.scene, c.eval_views)[:2]
  def after_window(state, iteration):
    if not c.eval_every or iteration % c.eval_every:
      return None
    return curve_record(run, parallel.on_one_device(state.weights_only(), mesh), eval_views)

  result = loop.run("conceal", plan.loop, workdir, init_state=fresh, restore_template=fresh, step=step,
                    after_window=after_window, postfix_keys=("plus",), max_steps=max_steps)
  if not result.finished:
    return dict(stopped_at=int(result.state.step))
  state = parallel.on_one_device(result.state, mesh)
  save_outputs(run, workdir, state)
  summary = dict(iterations=plan.iterations, decoder_polish_steps=plan.polish_steps, resumed_from=result.start,
                 settings=dataclasses.asdict(s), num_gaussians=int(run.start.num),
                 num_carrier=int(run.start.num - run.teacher.num), num_keys=num_keys,
                 num_decoys=len(run.decoys), **result.timing(), traces=dict(traces.counts),
                 pair_capacity=steps.capacity, capacity_reruns=steps.reruns, capacity_shrinks=steps.shrinks,
                 history=result.history)
  fileio.write_json(os.path.join(workdir, SUMMARY_FILE), summary)
  scored = score_student(config, workdir, run, s, state.student, state.decoder)
  if run.message is not None:  # what the key reveals from the student, read as the message (message.json)
    revealed = scoring.reveal_at_keys(state.student, [run.keys[0][0]], run.options, reveal_fn(s, state.decoder))[0]
    scored = dict(scored, message=message_lib.read_message(np.asarray(revealed), run.message))
    fileio.write_json(os.path.join(workdir, MESSAGE_FILE), scored["message"])
  return dict(summary, metrics=scored)


def regrouped(run: Run, data: views_lib.ConcealData, student, iteration: int, regroup: grouping.Regrouping, mesh):
  """`data` with the converter's groups of the film of `student` (the state before step `iteration`) and the check
  renders' linear maps through them (views.regrouped), on `mesh`."""
  merges = regroup(student, iteration, data.merges[0].members.shape[0])
  states = linear_check.states(run.plan.settings.augmentation)
  return views_lib.regrouped(data, student, merges, run.options, states, mesh)


def score_student(config: ml_collections.ConfigDict, workdir: str, marked: Marking | Run,
                  settings: settings_lib.ConcealSettings, student, decoder) -> dict:
  """metrics.json (scoring.evaluate_concealment) of `student` read with `decoder` at the keys of `marked`."""
  return scoring.evaluate_concealment(config, workdir, marked.scene, marked.teacher, student,
                                      reveal_fn(settings, decoder), [camera for camera, _ in marked.keys],
                                      marked.hiddens, marked.options)

