"""ConcealGS (paper Sec. 2.2-2.3): hide an image in a 3D-GS scene. `--config.mode=conceal`.

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

Ablations (the paper's Table): conceal.use_decoder=False (the resized check render itself must show
I), conceal.consistency=False (no consistency strategy of Sec. 2.2: no L_kd, the student is supervised
by ground truth, and no L_d^-), conceal.guidance=False (plain summed decoder gradient).

The number of Gaussians is fixed (no densification): the student is the teacher's set, refined.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import time

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from absl import logging
from tqdm import tqdm

from conceal_jax.splat import camera as camera_lib
from conceal_jax.conceal import guidance, hidden as hidden_lib, key as key_lib
from conceal_jax.core import checkpoint, fileio
from conceal_jax.gs import evaluate
from conceal_jax.conceal import reveal, unet
from conceal_jax.data import ply
from conceal_jax.gs import losses, metrics, optimizer, render_views
from conceal_jax.splat.render import RenderOptions, render

VARIANTS = ("paper", "released")
STUDENT_FILE = "student.ply"
DECODER_FILE = "decoder.msgpack"
KEY_FILE = "key.json"
SUMMARY_FILE = "conceal.json"


@dataclasses.dataclass(frozen=True)
class ConcealSettings:
  """The static choices of one concealment run (hashable: they shape the traced step)."""
  variant: str = "paper"
  use_decoder: bool = True
  consistency: bool = True
  guidance: bool = True
  granularity: str = "layer"
  decoder_width: int = unet.PAPER_WIDTH
  hidden_size: int = 64
  weight_kd: float = 1.0
  weight_plus: float = 1.0
  weight_minus: float = 1.0
  weight_check: float = 1.0

  def __post_init__(self):
    if self.variant not in VARIANTS:
      raise ValueError(f"conceal.variant must be one of {VARIANTS}, got {self.variant!r}")
    if self.granularity not in guidance.GRANULARITIES:
      raise ValueError(f"conceal.granularity must be one of {guidance.GRANULARITIES}, got {self.granularity!r}")
    if self.decoder_width < 1 or self.hidden_size < 8 or self.hidden_size % unet.DOWNSAMPLE:
      raise ValueError("conceal.decoder_width must be positive and conceal.hidden_size a multiple of "
                       f"{unet.DOWNSAMPLE} (at least 8)")
    if min(self.weight_kd, self.weight_plus, self.weight_minus, self.weight_check) < 0 or not self.weight_plus > 0:
      raise ValueError("conceal weights must be non-negative and weight_plus positive")

  @property
  def distill(self) -> bool:
    """Normal views supervised by the teacher (L_kd) rather than by ground truth."""
    return self.variant == "paper" and self.consistency

  @property
  def identity_loss(self) -> bool:
    """Whether L_d^- trains the decoder."""
    return self.use_decoder and self.consistency


def settings_from_config(config: ml_collections.ConfigDict) -> ConcealSettings:
  c = config.conceal
  return ConcealSettings(variant=c.variant, use_decoder=c.use_decoder, consistency=c.consistency,
                         guidance=c.guidance, granularity=c.granularity, decoder_width=c.decoder_width,
                         hidden_size=c.hidden_size, weight_kd=c.weight_kd, weight_plus=c.weight_plus,
                         weight_minus=c.weight_minus, weight_check=c.weight_check)


def make_conceal_step(settings: ConcealSettings, options: RenderOptions, student_tx, decoder_tx):
  """Builds step(state, data, view, normal_view) -> (state, stats), jitted with the state donated.

  data: train images / cached teacher renders [V, H, W, 3], teacher renders at the decoder size
  [V, S, S, 3], stacked train cameras, the check camera, its target image, the teacher's check render at
  the decoder size, and the hidden image [S, S, 3]. The student and the decoder share one backward pass
  for L_kd + L_d^+ (L_kd does not read the decoder, so the decoder part is grad L_d^+); L_d^- has its own.
  """
  s = settings
  size = s.hidden_size

  def student_objective(student, decoder, data, view):
    camera = jax.tree.map(lambda x: x[view], data["cameras"])
    rgb = render(student, camera, options).rgb
    if s.distill:
      normal = s.weight_kd * losses.distillation_loss(rgb, data["teacher"][view])
    else:
      normal = losses.photometric_loss(rgb, data["images"][view])
    check_rgb = render(student, data["check_camera"], options).rgb
    small = reveal.resize_for_decoder(check_rgb, size)
    revealed = reveal.decode(decoder, s.decoder_width, small) if s.use_decoder else small
    plus = losses.hidden_image_loss(revealed, data["hidden"])
    total = normal + s.weight_plus * plus
    if s.variant == "released":
      total = total + s.weight_check * losses.l1(check_rgb, data["check_image"])
    return total, dict(normal=normal, plus=plus, rgb=rgb)

  def identity_objective(decoder, data, normal_view):
    teacher = data["teacher_small"][normal_view] if s.variant == "paper" else data["teacher_check_small"]
    return s.weight_minus * losses.decoder_identity_loss(reveal.decode(decoder, s.decoder_width, teacher), teacher)

  @functools.partial(jax.jit, donate_argnums=0)
  def step(state, data, view, normal_view):
    (total, aux), (student_grad, plus_grad) = jax.value_and_grad(student_objective, argnums=(0, 1), has_aux=True)(
        state["student"], state["decoder"], data, view)
    updates, student_opt = student_tx.update(student_grad, state["student_opt"], state["student"])
    new_state = dict(state, step=state["step"] + 1, student=optax.apply_updates(state["student"], updates),
                     student_opt=student_opt)
    stats = dict(loss=total, normal=aux["normal"], plus=aux["plus"],
                 psnr=metrics.psnr(jnp.clip(aux["rgb"], 0, 1),
                                   data["teacher"][view] if s.distill else data["images"][view]))
    if s.use_decoder:
      if s.identity_loss:
        minus, minus_grad = jax.value_and_grad(identity_objective)(state["decoder"], data, normal_view)
      else:
        minus, minus_grad = jnp.zeros(()), jax.tree.map(jnp.zeros_like, plus_grad)
      if s.guidance:  # plus_grad and minus_grad already carry their loss weights; cosines ignore scale
        decoder_grad, weights = guidance.guided_decoder_gradient(plus_grad, minus_grad, 1.0, 1.0, s.granularity)
        stats["mean_guidance_weight"] = jnp.mean(jnp.stack(jax.tree.leaves(weights)))
      else:
        decoder_grad = jax.tree.map(jnp.add, plus_grad, minus_grad)
      updates, decoder_opt = decoder_tx.update(decoder_grad, state["decoder_opt"], state["decoder"])
      new_state.update(decoder=optax.apply_updates(state["decoder"], updates), decoder_opt=decoder_opt)
      stats["minus"] = minus
      stats["loss"] = total + minus
    return new_state, stats

  return step


def create_conceal_state(student, decoder, student_tx, decoder_tx) -> dict:
  return dict(step=jnp.zeros((), jnp.int32), student=student, decoder=decoder,
              student_opt=student_tx.init(student), decoder_opt=decoder_tx.init(decoder))


def initial_decoder(config: ml_collections.ConfigDict, settings: ConcealSettings):
  """A fresh decoder (a placeholder {} without one), the VGG16 encoder loaded if asked for."""
  if not settings.use_decoder:
    return {}
  params = unet.init_decoder(jax.random.key(config.seed), settings.decoder_width, settings.hidden_size)
  if config.conceal.decoder_vgg_init:
    params = unet.load_vgg16_encoder(params)
  return params


def build_data(scene, teacher, options: RenderOptions, check_camera, check_image, hidden: np.ndarray,
               size: int) -> dict:
  """The device-resident inputs of the step; the teacher renders are computed here once and cached."""
  teacher_renders = jnp.stack(evaluate.render_images(teacher, scene.train_cameras, options))
  teacher_check = render(teacher, check_camera, options).rgb
  small = jax.vmap(lambda x: reveal.resize_for_decoder(x, size))
  return dict(images=jnp.asarray(np.stack(scene.train_images)), teacher=teacher_renders,
              teacher_small=small(teacher_renders), cameras=camera_lib.stack(scene.train_cameras),
              check_camera=check_camera, check_image=check_image,
              teacher_check_small=reveal.resize_for_decoder(teacher_check, size), hidden=jnp.asarray(hidden))


def conceal_and_evaluate(config: ml_collections.ConfigDict, workdir: str, max_steps: int | None = None) -> dict:
  """Trains student + decoder (checkpointed, resumable), then writes student.ply, decoder.msgpack,
  key.json, hidden.png, revealed.png, conceal.json and metrics.json into workdir."""
  c = config.conceal
  settings = settings_from_config(config)
  if c.iterations < 1:
    raise ValueError(f"conceal.iterations must be >= 1, got {c.iterations}")
  if not c.teacher:
    raise ValueError("conceal.teacher (the teacher's .ply) is required")
  teacher = ply.load_ply(c.teacher)
  hidden = hidden_lib.load_hidden_image(c.hidden, settings.hidden_size)
  scene = evaluate.load_scene_data(config)
  check_camera, key_info = key_lib.check_camera(scene.train_cameras, c.key_kind, c.key_index, c.key_seed)
  # With a training camera the check view has a ground-truth image; an orbit key has none, so the
  # released variant's extra L1 uses the teacher's render there.
  options = dataclasses.replace(render_views.render_options(config), background=tuple(scene.background))
  check_image = (jnp.asarray(scene.train_images[key_info["index"]]) if c.key_kind == "train_index"
                 else render(teacher, check_camera, options).rgb)
  data = build_data(scene, teacher, options, check_camera, check_image, hidden, settings.hidden_size)

  student_tx = optimizer.gaussian_optimizer(c.lr, scene.scene_extent())
  decoder_tx = optax.adam(c.decoder_lr, eps=optimizer.ADAM_EPS)
  student = jax.tree.map(lambda x: jnp.array(x, copy=True), teacher)  # the step donates the student's buffers
  state = create_conceal_state(student, initial_decoder(config, settings), student_tx, decoder_tx)
  ckpt_dir = os.path.join(workdir, "checkpoints")
  history, step_times = [], []  # a resumed run keeps both, so it reports the time of all its steps
  latest = checkpoint.load_latest(ckpt_dir)
  if latest:
    path, meta, leaves = latest
    state = jax.tree.map(jnp.asarray, checkpoint.restore(state, leaves, path))
    history, step_times = meta["history"], meta.get("step_times", [])
    logging.info("resuming from %s", path)
  step_fn = make_conceal_step(settings, options, student_tx, decoder_tx)
  start = int(state["step"])
  end = c.iterations if max_steps is None else min(c.iterations, max_steps)
  num_views = len(scene.train_cameras)
  bar = tqdm(total=c.iterations, initial=start, desc="conceal", dynamic_ncols=True, disable=not c.progress_bar)
  for step in range(start, end):
    iteration = step + 1
    rng = np.random.default_rng([config.seed, iteration])
    started = time.perf_counter()
    state, stats = step_fn(state, data, rng.integers(num_views), rng.integers(num_views))
    if iteration % c.log_every == 0 or iteration == end:
      stats = {k: float(v) for k, v in jax.device_get(stats).items()}
      if not np.isfinite(stats["loss"]):
        raise FloatingPointError(f"concealment diverged at step {iteration}: {stats}")
      history.append(dict(step=iteration, **stats))
      bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}", hidden=f"{stats['plus']:.4f}")
    else:
      jax.block_until_ready(state["step"])
    step_times.append(time.perf_counter() - started)
    bar.update(1)
    if c.checkpoint_every and (iteration % c.checkpoint_every == 0 or iteration == end):
      checkpoint.save(ckpt_dir, iteration, state, dict(history=history, step_times=step_times))
  bar.close()
  if end < c.iterations:
    return dict(stopped_at=end)

  decoder = state["decoder"] if settings.use_decoder else None
  ply.save_ply(os.path.join(workdir, STUDENT_FILE), jax.device_get(state["student"]))
  if decoder is not None:
    reveal.save_decoder(os.path.join(workdir, DECODER_FILE), decoder)
  key_info.update(hidden_size=settings.hidden_size, uses_decoder=settings.use_decoder,
                  decoder_width=settings.decoder_width, render_options=dataclasses.asdict(options))
  key_lib.save_key(os.path.join(workdir, KEY_FILE), check_camera, key_info)
  fileio.write_image(os.path.join(workdir, "hidden.png"), hidden)
  summary = dict(iterations=c.iterations, resumed_from=start, settings=dataclasses.asdict(settings),
                 num_gaussians=int(teacher.num), timed_steps=len(step_times),
                 wall_time_s=float(np.sum(step_times)),
                 median_step_s=float(np.median(step_times)) if step_times else None, history=history)
  fileio.write_json(os.path.join(workdir, SUMMARY_FILE), summary)
  result = evaluate_concealment(config, workdir, scene, teacher, state["student"], decoder, settings,
                                check_camera, options, hidden)
  return dict(summary, metrics=result)


def evaluate_concealment(config, workdir, scene, teacher, student, decoder, settings: ConcealSettings,
                         check_camera, options: RenderOptions, hidden: np.ndarray) -> dict:
  """metrics.json: render quality of student and teacher on the test split (vs ground truth, and the
  student vs the teacher), hidden-image recovery at the check view, and leakage: the best SSIM to the
  hidden image of the decoder output over the student's test views and at the clean teacher's check view."""
  eval_opts = evaluate.eval_options(config, scene.background)
  cameras, targets, names = evaluate.held_out_views(scene, config.eval.max_views)
  student_renders = evaluate.render_images(student, cameras, eval_opts)
  teacher_renders = evaluate.render_images(teacher, cameras, eval_opts)
  evaluate.write_images(os.path.join(workdir, "test_renders"), names, student_renders)
  net = config.eval.lpips_net
  size, width = settings.hidden_size, settings.decoder_width
  revealed = np.asarray(reveal.reveal_image(student, check_camera, options, decoder, width, size))
  fileio.write_image(os.path.join(workdir, "revealed.png"), revealed)
  teacher_revealed = np.asarray(reveal.reveal_image(teacher, check_camera, options, decoder, width, size))
  fileio.write_image(os.path.join(workdir, "teacher_revealed.png"), teacher_revealed)
  decoded_tests = [np.asarray(reveal.reveal_image(student, cam, options, decoder, width, size)) for cam in cameras]
  ssim_to_hidden = [float(metrics.ssim(x, hidden)) for x in decoded_tests]
  result = dict(
      student_vs_ground_truth=evaluate.image_metrics(student_renders, targets, names, net)["mean"],
      teacher_vs_ground_truth=evaluate.image_metrics(teacher_renders, targets, names, net)["mean"],
      student_vs_teacher=evaluate.image_metrics(student_renders, teacher_renders, names, net)["mean"],
      hidden=dict(psnr=float(metrics.psnr(revealed, hidden)), ssim=float(metrics.ssim(revealed, hidden))),
      leakage=dict(max_ssim_student_test_views=max(ssim_to_hidden),
                   ssim_teacher_check_view=float(metrics.ssim(teacher_revealed, hidden))),
      num_test_views=len(names), lpips_net=metrics.LPIPS_NET_NAME[net], eval_render_options=repr(eval_opts))
  fileio.write_json(os.path.join(workdir, evaluate.METRICS_FILE), result)
  return result
