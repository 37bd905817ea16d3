"""ConcealGS (Yang et al. 2025, arXiv:2501.03605, Sec. 2.2-2.3): hide an image in a 3D-GS scene.
`--config.mode=conceal`.

A student scene G_w (initialised from the teacher G_o, `conceal.teacher`) and a U-Net decoder F are
trained together so that F reveals the hidden image I from the student's render at the secret check
view P_c, while F is the identity on normal views and the student's renders stay the teacher's.

conceal.variant, side by side:
                        'paper' (default)                    'released' (the authors' code)
  normal views          L_kd: student vs cached teacher      0.8 L1 + 0.2 D-SSIM vs ground truth
                        renders (eq. 3)
  L_d^- (eq. 4)         teacher renders of normal views      the teacher's check-view render only
  check view, extra     -                                    L1(student check render, its image)
  guidance granularity  conceal.granularity ('layer' as in the paper; the released code uses 'tensor')

Ablations (the paper's Table 3): conceal.use_decoder=False (the resized check render itself must show
I), conceal.consistency=False (no consistency strategy of Sec. 2.2: no L_kd, the student is supervised
by ground truth, and no L_d^-), conceal.guidance=False (plain summed decoder gradient).

Leakage control, an option beyond the paper (off by default, so `variant=paper` is the method as written):
  conceal.identity_on_student  L_d^- also on the student's own render of the step's normal view: F learns
                               to be the identity on what a viewer of the shared scene sees, not only on
                               the teacher's renders.
  conceal.identity_on_teacher_check
                               L_d^- also on the clean teacher's check render (the released code's only
                               L_d^- input): the key reveals only the student's change, not the pose.
  conceal.decoy_views / decoy_fraction / decoy_translation / decoy_rotation_deg
                               decoy_views cameras near the key (moved by a fraction of the scene extent,
                               turned by degrees, within the given ranges) join the normal views with the
                               teacher's renders cached: a step draws a decoy as its normal view with
                               probability decoy_fraction, so L_kd holds the student to the teacher there
                               and L_d^- keeps F the identity there. Only the exact key reveals.
Why it is needed, on lego (200x200, 10k steps, width 16; make bench-conceal): the method as written (row
`full`) reaches hidden 42.96 dB / SSIM 0.9983 with the student 1.10 dB below its teacher, but F also reveals
I from the student's test views (SSIM up to 0.884) and from poses near the key (0.843); with the three
options and configs/conceal_ours.py's rates (row `ours`), leakage is at most 0.188, hidden 37.28 dB / 0.9941
and the student 0.11 dB below its teacher.

Robustness, an option beyond the paper: conceal.check_blur_max / check_noise_max distort the student's check
render (a blur and a noise level drawn per step, augment.py) before the decoder reads it for L_d^+, so that
the hidden image survives blur, JPEG and noise of the check render; conceal.identity_distorted puts the student's
normal render (decoy poses included) through the same distortion for L_d^-, so that the decoder stays the identity
on distorted views near the key. conceal.check_dropout_max / check_param_noise_max render the check view from a
perturbed student (Gaussians dropped, parameters noised; augment.perturb_gaussians), against the model attacks.

A colour-only student, an option beyond the paper: conceal.trained_fields 'sh' trains the SH colour alone and
keeps the teacher's geometry, as StegaNeRF does (gs/optimizer.frozen_geometry; 'all' is the paper's student).

conceal.key_at_decoder_size (off: as the paper) renders the key directly at the decoder's size (hidden_size
squared) with the check pose's field of view, instead of rendering it at the training resolution and resizing.
It is a cheaper key (on lego, 200x200 -> 64x64 cuts the check render's fwd+bwd from 191 to 124 ms and the
step from 493 to 439 ms); key.json stores that camera, so the reveal renders it the same way. Measured on the
demo (configs/demo.py, 1300 steps) it costs quality: hidden 30.48 dB against 31.20, and the poses near the
key, rendered at the key's 64x64, reveal up to SSIM 0.30 against 0.17, because the decoys that teach F to be
the identity there are rendered at the training resolution and resized, a slightly different image.

Speed without changing the method: conceal.lanes (0: automatic) computes a step's gradients as two lanes,
the normal view's render with its decoder images and the check view's with its own (lanes_objective.py),
which a CPU host runs side by side on its two cores (core.lanes); the values are those of the plain
objective (tests/test_lanes.py). Profiled on lego width 16 (experiments/profile_conceal.py), the whole step
takes 357 ms on two lanes against 424 ms on one; the 10k-step bench-conceal `ours` run took 67.9 min (median
step 404 ms) against 89.2 min (487 ms) before, and 60.8 min (365 ms) once the lanes met in one all-gather per
step instead of 103 collectives (core.lanes.map_lanes).

Several hidden images, an option beyond the paper: conceal.extra_hidden holds up to MAX_EXTRA_HIDDEN
more images, each at its own key of key_kind's kind (key.key_cameras: the next training cameras down
from key_index, or the orbit poses of the next seeds after key_seed), all read by the one decoder. Step t
trains key (t - 1) mod K (round-robin: each key gets the same number of L_d^+ steps, and a step still
renders one check view, so K keys cost no more per step than one); with identity_on_teacher_check, L_d^-
sees the teacher's render at that same key, and decoy_views are made around every key. key.json lists the
extra keys, metrics.json scores each image at its key and the cross-talk (see evaluate_concealment).

Decoder polish, an option beyond the paper: conceal.decoder_polish_steps more steps after the iterations, in
which only the decoder trains (the same L_d^+ and L_d^- with their distortions, the same guided update, at
the decoder's final rate), on the finished student, which they leave unchanged. The joint steps end with a
decoder fitted to a student that kept moving; the polish fits it to the student that is shared, and costs
the decoder's passes and two forward renders a step (on lego, 0.63x a joint step). Lego, width 16, 2000
steps after ours_robust_clip_dec03's 10k (seed 1): hidden 39.37 -> 39.57 dB, SSIM 0.9958 -> 0.9962, leakage
unchanged: a small gain, so the joint steps' hidden PSNR is not held back by the student's last moves. After
ours_robust_clip_dec03_clip's 10k (the decoder's steps clipped): 40.43 -> 41.57 dB, SSIM 0.9966 -> 0.9970.

Decoder average, an option beyond the paper: with conceal.decoder_average = d > 0 the state also holds an
exponential moving average of the decoder's weights (Polyak averaging), a <- a + (1 - d) (F - a) after every
decoder update, and that average is the decoder the curve scores and the run saves and evaluates. Training
never reads it. The live decoder's hidden PSNR swings between curve points (lego: 39.1-40.4 dB over the last
1500 of 10k steps), as each step draws its own distortion and view; the average smooths those swings. A run
continued from a checkpoint without the average (a bench row extending another run) starts it at the restored
decoder. Measured on lego (2000 polish steps after ours_robust_clip_dec03_clip, d = 0.999): 41.43 dB against the
live decoder's 41.57 at the end; the average did not dip where the live one did (41.04 against 40.37 at step
11000), but it trails a decoder that is still improving. Off by default.

The number of Gaussians is fixed (no densification): the student is the teacher's set, refined. The
objective is in objective.py, the guidance in guidance.py; this module builds the step and runs the job
through the shared loop (core.loop). With conceal.eval_every, the history records the hidden image's
PSNR / SSIM at the check view and the student's test PSNR over time (the accuracy-vs-time curves).
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from flax import struct

from conceal_jax.conceal import augment, guidance, hidden as hidden_lib, key as key_lib, lanes_objective, reveal, unet
from conceal_jax.conceal.objective import ConcealSettings, key_data
from conceal_jax.core import fileio, lanes, loop, settings as settings_lib
from conceal_jax.data import ply
from conceal_jax.gs import capacity, evaluate, metrics, optimizer
from conceal_jax.splat import camera as camera_lib
from conceal_jax.splat import render as render_lib
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.render import RenderOptions, render

STUDENT_FILE = "student.ply"
DECODER_FILE = "decoder.msgpack"
KEY_FILE = "key.json"
SUMMARY_FILE = "conceal.json"
# Leakage near the key: the student at the check pose moved by these fractions of the scene extent, or
# turned by these degrees, each in NEAR_DIRECTIONS random directions (issue: a guessed pose must not reveal).
NEAR_TRANSLATIONS = (0.02, 0.05)
NEAR_ROTATIONS_DEG = (2.0, 5.0)
NEAR_DIRECTIONS = 4
# conceal.extra_hidden: 2-4 hidden images in all
MAX_EXTRA_HIDDEN = 3


@struct.dataclass
class ConcealState:
  """step: int32; student: Gaussians [N]; decoder: U-Net params ({} without a decoder); their Adam states;
  decoder_average: the decoder's weights averaged (conceal.decoder_average; {} without)."""
  step: jax.Array
  student: Any
  decoder: Any
  student_opt: Any
  decoder_opt: Any
  decoder_average: Any = struct.field(default_factory=dict)

  def scored_decoder(self, settings: ConcealSettings):
    """The decoder the run scores and saves: the average where conceal.decoder_average is set."""
    return self.decoder_average if settings.decoder_average else self.decoder


def settings_from_config(config: ml_collections.ConfigDict) -> ConcealSettings:
  return settings_lib.from_section(ConcealSettings, config.conceal,
                                   augmentation=augment.Augmentation.from_section(config.conceal))


def loop_settings(config: ml_collections.ConfigDict) -> loop.LoopSettings:
  """conceal.iterations joint steps, then conceal.decoder_polish_steps that train the decoder alone."""
  c = config.conceal
  polish = settings_lib.check_count("conceal.decoder_polish_steps", c.decoder_polish_steps, minimum=0)
  joint = settings_lib.from_section(loop.LoopSettings, c)
  return dataclasses.replace(joint, iterations=joint.iterations + polish)


def decoder_optimizer(config: ml_collections.ConfigDict) -> optax.GradientTransformation:
  """Adam on the decoder at conceal.decoder_lr, decaying to decoder_lr * conceal.decoder_lr_final_ratio over
  the run (1: constant, as released), with eps conceal.decoder_adam_eps: 1e-15 as the released code, where a
  weight whose gradient has all but vanished still takes steps of the full rate; AMSGrad with
  conceal.decoder_amsgrad or each tensor's step clipped with conceal.decoder_update_clip (both beyond the paper),
  against the bursts that follow."""
  c = config.conceal
  return optimizer.decaying_adam(c.decoder_lr, c.decoder_lr_final_ratio, c.iterations, c.decoder_adam_eps,
                                 "conceal.decoder_lr_final_ratio", amsgrad=c.decoder_amsgrad,
                                 update_rms_clip=c.decoder_update_clip, clip_name="conceal.decoder_update_clip")


def validate(config: ml_collections.ConfigDict) -> None:
  """Every value the conceal job reads, checked before anything runs (ValueError naming the key)."""
  c = config.conceal
  settings_from_config(config)
  loop_settings(config)
  optimizer.means_decay_steps(c.lr, c.iterations)
  evaluate.validate(config)
  lanes.resolve(c.lanes)
  if c.key_kind not in key_lib.KEY_KINDS:
    raise ValueError(f"conceal.key_kind must be one of {key_lib.KEY_KINDS}, got {c.key_kind!r}")
  if not (c.lr.means_init > 0 and c.decoder_lr > 0 and c.decoder_adam_eps > 0):
    raise ValueError("conceal.lr.means_init, conceal.decoder_lr and conceal.decoder_adam_eps must be positive")
  decoder_optimizer(config)  # checks the decoder's final ratio and update clip, naming their keys
  optimizer.trained_fields_optimizer(c.trained_fields, c.lr, 1.0, c.iterations, "conceal.trained_fields")
  if c.decoy_views < 0 or (c.decoy_fraction > 0) != (c.decoy_views > 0):
    raise ValueError("conceal.decoy_views must be positive exactly when conceal.decoy_fraction is, got "
                     f"{c.decoy_views} and {c.decoy_fraction}")
  for name in ("decoy_translation", "decoy_rotation_deg"):
    lo, hi = tuple(c[name])
    if not 0 <= lo <= hi:
      raise ValueError(f"conceal.{name} must be a range (lo, hi) with 0 <= lo <= hi, got {tuple(c[name])}")
  if c.eval_every < 0 or c.eval_views < 1:
    raise ValueError("conceal.eval_every must be >= 0 and conceal.eval_views >= 1")
  if not c.teacher:
    raise ValueError("conceal.teacher (the teacher's .ply) is required")
  if not os.path.isfile(c.teacher):
    raise ValueError(f"conceal.teacher: no such file {c.teacher}")
  extra = c.extra_hidden
  if isinstance(extra, str) or not all(isinstance(source, str) and source for source in extra):
    raise ValueError(f"conceal.extra_hidden must be a tuple of image paths or sample names, got {extra!r}")
  if len(extra) > MAX_EXTRA_HIDDEN:
    raise ValueError(f"conceal.extra_hidden holds at most {MAX_EXTRA_HIDDEN} images ({MAX_EXTRA_HIDDEN + 1} "
                     f"hidden images in all), got {len(extra)}")
  if c.decoder_polish_steps and not c.use_decoder:
    raise ValueError("conceal.decoder_polish_steps needs a decoder (conceal.use_decoder)")
  if extra and not c.use_decoder:
    raise ValueError("conceal.extra_hidden needs a decoder (conceal.use_decoder): one decoder reads every key's "
                     "image")


def make_conceal_step(settings: ConcealSettings, options: RenderOptions, student_tx, decoder_tx,
                      traces: loop.TraceCounter | None = None, mesh=None, train_student: bool = True):
  """Builds step(state, data, view, normal_view, key, distortion) -> (state, stats), jitted with the state
  donated; `key` picks the check view (and its hidden image) of a run with several (objective.key_data;
  unused with one); `distortion` (augment.draw) is applied to the check render when settings.augmentation draws.
  `options` carry a pair capacity; a step whose renders overflowed it returns the state unchanged (gs.capacity).
  Without `train_student` (conceal.decoder_polish_steps, see the module doc) the student and its Adam state
  stay as they are, and the renders' backward pass is not taken (lanes_objective.gradients' student_grad).

  The gradients come from lanes_objective.gradients: the student's of `student_objective`, and the
  decoder's of lambda+ L_d^+ and of lambda- L_d^- apart, two lanes (one per render) that run side by side on
  the two devices of `mesh` (core.lanes) and in turn without. The decoder update is the guided one of
  Sec. 2.3: per-layer cosine of the two decoder gradients, sigmoid weight, one optax update.
  """
  s = settings

  def step(state: ConcealState, data, view, normal_view, key=0, distortion=None):
    data = key_data(data, key)
    t = lanes_objective.gradients(state.student, state.decoder, data, view, normal_view, s, options, distortion,
                                  mesh, student_grad=train_student)
    total = t["normal"] + t["check"]
    new_state = state.replace(step=state.step + 1)
    if train_student:
      updates, student_opt = student_tx.update(t["student_grad"], state.student_opt, state.student)
      new_state = new_state.replace(student=optax.apply_updates(state.student, updates), student_opt=student_opt)
    stats = dict(loss=total, normal=t["normal"], plus=t["plus"], num_pairs=t["num_pairs"], psnr=t["psnr"])
    if s.use_decoder:
      plus_grad, minus_grad = t["plus_grad"], t["minus_grad"]
      if s.guidance:  # plus_grad and minus_grad already carry their loss weights; cosines ignore scale
        decoder_grad, weights = guidance.guided_decoder_gradient(plus_grad, minus_grad, 1.0, 1.0, s.granularity)
        stats["mean_guidance_weight"] = jnp.mean(jnp.stack(jax.tree.leaves(weights)))
      else:
        decoder_grad = jax.tree.map(jnp.add, plus_grad, minus_grad)
      updates, decoder_opt = decoder_tx.update(decoder_grad, state.decoder_opt, state.decoder)
      new_state = new_state.replace(decoder=optax.apply_updates(state.decoder, updates), decoder_opt=decoder_opt)
      if s.decoder_average:
        new_state = new_state.replace(decoder_average=jax.tree.map(
            lambda a, w: a + (1.0 - s.decoder_average) * (w - a), state.decoder_average, new_state.decoder))
      stats["minus"] = t["minus"]
      stats["loss"] = total + t["minus"]
    return capacity.keep_unless_overflowed(t["overflowed"], new_state, state), stats

  if traces is not None:
    step = traces.wrap("conceal_step" if train_student else "polish_step", step)
  return jax.jit(step, donate_argnums=0)


def create_conceal_state(student, decoder, student_tx, decoder_tx, average: bool = False) -> ConcealState:
  """The step-0 state; with `average`, the decoder's running average starts at the decoder."""
  return ConcealState(step=jnp.zeros((), jnp.int32), student=student, decoder=decoder,
                      student_opt=student_tx.init(student), decoder_opt=decoder_tx.init(decoder),
                      decoder_average=jax.tree.map(jnp.copy, decoder) if average else {})


def initial_decoder(config: ml_collections.ConfigDict, settings: ConcealSettings):
  """A fresh decoder (a placeholder {} without one), the VGG16 encoder loaded if asked for."""
  if not settings.use_decoder:
    return {}
  params = unet.init_decoder(jax.random.key(config.seed), settings.decoder_width, settings.hidden_size)
  if config.conceal.decoder_vgg_init:
    params = unet.load_vgg16_encoder(params)
  return params


def build_data(scene, teacher, options: RenderOptions, check_camera, check_image, hidden: np.ndarray,
               size: int, decoys=(), extra_keys=(), clip: bool = False) -> dict:
  """The device-resident inputs of the step; the teacher renders are computed here once, on the device.

  Normal views are the V training cameras followed by the D `decoys` (cameras, see key.decoy_cameras):
  cameras and teacher renders [V + D, ...], ground-truth images [V, H, W, 3] of the training views only.
  `extra_keys`: (camera, check image, hidden image [S, S, 3]) of further keys (conceal.extra_hidden); with
  any, data["keys"] stacks objective.KEY_FIELDS over all K keys, this check view first (check_camera [K],
  check_image [K, H, W, 3] or None, hidden and teacher_check_small [K, S, S, 3]). `clip`: the teacher renders
  at the decoder size are clipped to [0, 1] first (reveal.Reading.clip).
  """
  normal_cameras = list(scene.train_cameras) + list(decoys)
  teacher_renders = evaluate.render_images(teacher, normal_cameras, options)
  keys = [(check_camera, check_image, hidden)] + list(extra_keys)
  teacher_checks = [reveal.resize_for_decoder(render(teacher, camera, options).rgb, size, clip)
                    for camera, _, _ in keys]
  data = dict(images=jnp.asarray(np.stack(scene.train_images)), teacher=teacher_renders,
              teacher_small=reveal.resize_for_decoder(teacher_renders, size, clip),
              cameras=camera_lib.stack(normal_cameras), check_camera=check_camera, check_image=check_image,
              teacher_check_small=teacher_checks[0], hidden=jnp.asarray(hidden))
  if extra_keys:
    data["keys"] = dict(check_camera=camera_lib.stack([camera for camera, _, _ in keys]),
                        check_image=None if check_image is None else jnp.stack([image for _, image, _ in keys]),
                        hidden=jnp.stack([jnp.asarray(image) for _, _, image in keys]),
                        teacher_check_small=jnp.stack(teacher_checks))
  return data


def key_camera(check_pose: Camera, at_decoder_size: bool, size: int) -> Camera:
  """The camera the key renders with: the check pose at its own resolution (the paper: the render is then
  resized for the decoder), or with `at_decoder_size` (conceal.key_at_decoder_size) the same view rendered
  directly at size x size, the decoder's input, so that the check render costs fewer splat-tile pairs."""
  return check_pose.resized(size, size) if at_decoder_size else check_pose


def normal_view(rng: np.random.Generator, num_views: int, num_decoys: int, decoy_fraction: float) -> int:
  """A step's normal view: a decoy (index num_views + k) with probability decoy_fraction, else a training
  view, each uniformly."""
  if num_decoys and rng.random() < decoy_fraction:
    return num_views + int(rng.integers(num_decoys))
  return int(rng.integers(num_views))


def conceal_and_evaluate(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None = None) -> dict:
  """Trains student + decoder (checkpointed, resumable), then writes student.ply, decoder.msgpack,
  key.json, hidden.png, revealed.png, conceal.json and metrics.json into workdir; with extra hidden images
  also hidden_key<k>.png and revealed_key<k>.png for the k-th extra key (k = 1 .. K-1)."""
  validate(config)
  c = config.conceal
  settings = settings_from_config(config)
  teacher = ply.load_ply(c.teacher)
  sources = [c.hidden] + list(c.extra_hidden)
  hiddens = [hidden_lib.load_hidden_image(source, settings.hidden_size) for source in sources]
  scene = evaluate.load_scene_data(config)
  poses = key_lib.key_cameras(scene.train_cameras, c.key_kind, c.key_index, c.key_seed, len(c.extra_hidden))
  keys = [(key_camera(pose, c.key_at_decoder_size, settings.hidden_size), info) for pose, info in poses]
  check_camera, key_info = keys[0]
  options = evaluate.render_options(config, scene.background)

  def key_image(camera, info):
    """What the released variant's extra L1 holds the check render to: the training image at a training
    camera key, the teacher's render at an orbit key (which has no image)."""
    if c.key_kind != "train_index":
      return render(teacher, camera, options).rgb
    image = jnp.asarray(scene.train_images[info["index"]])
    return reveal.resize_for_decoder(image, settings.hidden_size) if c.key_at_decoder_size else image

  check_images = [key_image(camera, info) for camera, info in keys]
  # Decoys surround every key, each key's from its own seed (the first key's is key_seed, as with one image),
  # at the training views' resolution: what a viewer near the key sees.
  decoys = [decoy for k, (pose, _) in enumerate(poses)
            for decoy in key_lib.decoy_cameras(pose, scene.scene_extent(), c.decoy_views, tuple(c.decoy_translation),
                                               tuple(c.decoy_rotation_deg), c.key_seed + k)]
  extra_keys = [(camera, image, hidden) for (camera, _), image, hidden in zip(keys[1:], check_images[1:], hiddens[1:])]
  mesh = lanes.lane_mesh(lanes.resolve(c.lanes))
  data = lanes.replicate(build_data(scene, teacher, options, check_camera, check_images[0], hiddens[0],
                                    settings.hidden_size, decoys, extra_keys, settings.decoder_clip_input), mesh)

  student_tx = optimizer.trained_fields_optimizer(c.trained_fields, c.lr, scene.scene_extent(), c.iterations,
                                                  "conceal.trained_fields")
  decoder_tx = decoder_optimizer(config)
  traces = loop.TraceCounter()
  # GrowingSteps' key is the phase: the joint steps, then the decoder polish's (train_student False)
  steps = capacity.GrowingSteps(lambda joint, opts: make_conceal_step(settings, opts, student_tx, decoder_tx, traces,
                                                                      mesh, train_student=joint), options)
  steps.grow(render_lib.initial_capacity(teacher.num, options))
  num_views, num_keys = len(scene.train_cameras), len(keys)

  averaging = bool(settings.decoder_average)

  def fresh(average: bool = averaging):
    student = jax.tree.map(lambda x: jnp.array(x, copy=True), teacher)  # the step donates the student's buffers
    return create_conceal_state(student, initial_decoder(config, settings), student_tx, decoder_tx, average)

  def restored(state):
    """A checkpoint written without the average (a run continued with it) starts it at the restored decoder."""
    if averaging and not jax.tree.leaves(state.decoder_average):
      return state.replace(decoder_average=jax.tree.map(jnp.copy, state.decoder))
    return state

  def step(state, iteration):
    rng = np.random.default_rng([config.seed, iteration])
    views = [normal_view(rng, num_views, len(decoys), settings.decoy_fraction) for _ in range(2)]
    distortion = augment.draw(rng, settings.augmentation) if settings.augmentation.draws else None
    return steps(iteration <= c.iterations, lanes.replicate(state, mesh), data, *views, (iteration - 1) % num_keys,
                 distortion)

  eval_cameras, eval_targets, _ = evaluate.held_out_views(scene, c.eval_views)

  def after_window(state, iteration):
    if not c.eval_every or iteration % c.eval_every:
      return None
    one = lanes.on_one_device(state.replace(student_opt=(), decoder_opt=()), mesh)  # not the Adam moments
    student, live = one.student, one.decoder
    decoder = one.scored_decoder(settings) if settings.use_decoder else None
    key_renders = [render(student, camera, options).rgb for camera, _ in keys]
    reveal_with = lambda params, rgb: reveal.reveal_renders(params, rgb, settings.decoder_width, settings.hidden_size,
                                                            settings.reading)
    revealed = [reveal_with(decoder, rgb) for rgb in key_renders]
    record = dict(hidden_psnr=float(metrics.psnr(revealed[0], hiddens[0])),
                  hidden_ssim=float(metrics.ssim(revealed[0], hiddens[0])),
                  test_psnr=evaluate.views_psnr(student, eval_cameras, eval_targets, options))
    if averaging:  # the live decoder beside its average, on the same key render
      record["hidden_psnr_live"] = float(metrics.psnr(reveal_with(live, key_renders[0]), hiddens[0]))
    if num_keys > 1:
      record.update(hidden_psnr_keys=[float(metrics.psnr(r, h)) for r, h in zip(revealed, hiddens)],
                    hidden_ssim_keys=[float(metrics.ssim(r, h)) for r, h in zip(revealed, hiddens)])
    return record

  result = loop.run("conceal", loop_settings(config), workdir, init_state=fresh,
                    restore_template=lambda meta: fresh(meta.get("decoder_average", False)), step=step,
                    after_window=after_window, checkpoint_meta=lambda _: dict(decoder_average=averaging),
                    postfix_keys=("plus",), max_steps=max_steps, after_restore=restored)
  if not result.finished:
    return dict(stopped_at=int(result.state.step))

  state = lanes.on_one_device(result.state, mesh)
  decoder = state.scored_decoder(settings) if settings.use_decoder else None
  ply.save_ply(os.path.join(workdir, STUDENT_FILE), jax.device_get(state.student))
  if decoder is not None:
    reveal.save_decoder(os.path.join(workdir, DECODER_FILE), decoder)
  key_info.update(hidden_size=settings.hidden_size, uses_decoder=settings.use_decoder,
                  decoder_width=settings.decoder_width, **settings.reading.key_fields(),
                  render_options=dataclasses.asdict(options))
  # reveal.key_number k reveals the k-th extra image
  key_lib.save_key(os.path.join(workdir, KEY_FILE), check_camera, key_info,
                   [(camera, dict(info, number=k, hidden=source))
                    for k, ((camera, info), source) in enumerate(zip(keys[1:], sources[1:]), 1)])
  fileio.write_image(os.path.join(workdir, "hidden.png"), hiddens[0])
  for k, image in enumerate(hiddens[1:], 1):
    fileio.write_image(os.path.join(workdir, f"hidden_key{k}.png"), image)
  summary = dict(iterations=c.iterations, decoder_polish_steps=c.decoder_polish_steps, resumed_from=result.start,
                 settings=dataclasses.asdict(settings), num_gaussians=int(teacher.num), num_keys=num_keys,
                 num_decoys=len(decoys), **result.timing(), traces=dict(traces.counts), pair_capacity=steps.capacity,
                 capacity_reruns=steps.reruns, capacity_shrinks=steps.shrinks, history=result.history)
  fileio.write_json(os.path.join(workdir, SUMMARY_FILE), summary)
  reveal_fn = reveal.decoder_reveal(decoder, settings.decoder_width, settings.hidden_size,
                                    settings.reading)
  scored = evaluate_concealment(config, workdir, scene, teacher, state.student, reveal_fn, check_camera, options,
                                hiddens[0], [(camera, hidden) for (camera, _), hidden in zip(keys[1:], hiddens[1:])])
  return dict(summary, metrics=scored)


def evaluate_concealment(config, workdir, scene, teacher, student, reveal_fn, check_camera, options: RenderOptions,
                         hidden: np.ndarray, extra_keys=()) -> dict:
  """metrics.json: render quality of student and teacher on the test split (vs ground truth, and the
  student vs the teacher), hidden-image recovery at the check view, and leakage: the best SSIM to the
  hidden image of the decoder output over the student's test views, at the clean teacher's check view
  and at the student's poses near the check view (near_check: the best SSIM per distance); and its floor: the
  same over the clean teacher's test renders (max, and at the student's worst view). `reveal_fn`
  maps renders [V, H, W, 3] to revealed images [V, S, S, 3] (reveal.decoder_reveal; baselines have their
  own). Images:
  revealed.png (student, check view), teacher_revealed.png (clean teacher, check view) and
  normal_revealed.png (student, the test view of the highest SSIM).

  `extra_keys`: (camera, hidden image [S, S, 3]) of further hidden images (conceal.extra_hidden), K keys in
  all. With them, each leakage figure is the worst over every hidden image, and over the clean teacher at
  every key and the poses near every key (near_check pools the K keys' poses); revealed_key<k>.png shows
  the k-th extra key, and metrics.json gains `keys`: see `key_scores`.
  """
  eval_opts = evaluate.eval_options(config, scene.background)
  cameras, targets, names = evaluate.held_out_views(scene, config.eval.max_views)
  student_renders = evaluate.render_images(student, cameras, eval_opts)
  teacher_renders = evaluate.render_images(teacher, cameras, eval_opts)
  evaluate.write_images(os.path.join(workdir, "test_renders"), names, student_renders)
  net = config.eval.lpips_net
  keys = [(check_camera, hidden)] + list(extra_keys)
  hiddens = np.stack([np.asarray(image) for _, image in keys])  # [K, S, S, 3]
  # The key views are rendered alone, exactly as the reveal job renders them.
  revealed = [np.asarray(reveal_fn(render(student, camera, options).rgb[None])[0]) for camera, _ in keys]
  teacher_revealed = [np.asarray(reveal_fn(render(teacher, camera, options).rgb[None])[0]) for camera, _ in keys]
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed[0])
  fileio.write_image(os.path.join(workdir, "teacher_revealed.png"), teacher_revealed[0])
  for k, image in enumerate(revealed[1:], 1):
    fileio.write_image(os.path.join(workdir, f"revealed_key{k}.png"), image)
  # Leakage is scored on the student's own test renders, as a viewer of the shared scene would see them,
  # and at poses near the key, as someone guessing it would.
  normal_revealed = reveal_fn(student_renders)
  ssim_to_hidden = reveal.scores_to_hidden(normal_revealed, hiddens)["ssim"]
  worst = int(np.argmax(ssim_to_hidden))  # the test view whose decoder output looks most like a hidden image
  fileio.write_image(os.path.join(workdir, "normal_revealed.png"), np.asarray(normal_revealed[worst]))
  # What the same decoder makes of the clean teacher's test renders: the SSIM an unmarked scene scores on these
  # views, the floor a leakage figure is read against (a bright image shares some structure with any hidden one).
  floor_ssim = reveal.scores_to_hidden(reveal_fn(teacher_renders), hiddens)["ssim"]
  near_rows = [reveal.near_key_rows(student, camera, options, reveal_fn, hiddens, scene.scene_extent(),
                                    NEAR_TRANSLATIONS, NEAR_ROTATIONS_DEG, NEAR_DIRECTIONS) for camera, _ in keys]
  near_check = pooled_near_rows(near_rows)
  teacher_ssim = [[float(metrics.ssim(image, h)) for h in hiddens] for image in teacher_revealed]
  result = dict(
      student_vs_ground_truth=evaluate.image_metrics(student_renders, targets, names, net)["mean"],
      teacher_vs_ground_truth=evaluate.image_metrics(teacher_renders, targets, names, net)["mean"],
      student_vs_teacher=evaluate.image_metrics(student_renders, teacher_renders, names, net)["mean"],
      hidden=dict(psnr=float(metrics.psnr(revealed[0], hidden)), ssim=float(metrics.ssim(revealed[0], hidden))),
      leakage_worst_test_view=names[worst],
      leakage=dict(max_ssim_student_test_views=float(ssim_to_hidden.max()),
                   ssim_teacher_check_view=max(max(row) for row in teacher_ssim),
                   max_ssim_near_check=max(row["max_ssim"] for row in near_check)),
      leakage_floor=dict(max_ssim_teacher_test_views=float(floor_ssim.max()),
                         ssim_teacher_at_worst_test_view=float(floor_ssim[worst])),
      near_check=near_check,
      num_test_views=len(names), lpips_net=metrics.LPIPS_NET_NAME[net], eval_render_options=repr(eval_opts))
  if extra_keys:
    result["keys"] = key_scores(revealed, hiddens, near_rows, teacher_ssim)
  fileio.write_json(os.path.join(workdir, evaluate.METRICS_FILE), result)
  return result


def pooled_near_rows(rows_per_key: list[list[dict]]) -> list[dict]:
  """reveal.near_key_rows of K keys (same poses relative to each key) as one list: per (kind, value), the
  mean over keys of mean_ssim and mean_psnr (every key has as many directions) and the max of max_ssim."""
  return [dict(rows[0], mean_ssim=float(np.mean([r["mean_ssim"] for r in rows])),
               max_ssim=max(r["max_ssim"] for r in rows), mean_psnr=float(np.mean([r["mean_psnr"] for r in rows])))
          for rows in zip(*rows_per_key)]


def key_scores(revealed, hiddens: np.ndarray, near_rows: list[list[dict]], teacher_ssim) -> dict:
  """metrics.json's `keys` for K keys, from the images revealed at them [K][S, S, 3], the hidden images
  [K, S, S, 3], the near-key rows of each key and the SSIM [K][K] of the clean teacher's reveal at key i to
  image j: `hidden` (per key: PSNR / SSIM of what key i reveals to its own image, and its leakage near the
  key and at the clean teacher, over every image), `cross_talk_ssim` [K][K] (row i: revealed at key i,
  column j: SSIM to image j; the diagonal is each key's own image), `max_cross_talk` (its largest
  off-diagonal entry) and `images_ssim` [K][K] (the hidden images' SSIM to each other: the cross-talk of a
  perfect reveal)."""
  cross = [[float(metrics.ssim(image, h)) for h in hiddens] for image in revealed]
  num = len(hiddens)
  return dict(hidden=[dict(psnr=float(metrics.psnr(image, hiddens[i])), ssim=cross[i][i],
                           max_ssim_near_key=max(row["max_ssim"] for row in near_rows[i]),
                           ssim_teacher_at_key=max(teacher_ssim[i])) for i, image in enumerate(revealed)],
              cross_talk_ssim=cross, max_cross_talk=max(cross[i][j] for i in range(num) for j in range(num) if i != j),
              images_ssim=[[float(metrics.ssim(a, b)) for b in hiddens] for a in hiddens])
