"""Where a ConcealGS step spends its time, on the lego teacher of `make bench-train`.

  make profile-conceal                                   # decoder widths 16 and 64
  make profile-conceal BENCH_ARGS="--widths=16 --repeats=9 --row=full"
  make profile-conceal BENCH_ARGS="--widths=16 --key-at-decoder-size=0,1"   # the key at 200x200 and at 64x64

With the settings of a bench-conceal row (default ours), for each decoder width, times (median of
--repeats, each part jitted on its own): the student's render of a normal view with L_kd and its
gradient, `student_objective` with its gradient (the normal render, the check render and the decoder on
it), the decoder alone (forward, forward+backward, for one image and for a batch of two),
`decoder_identity_objective` with its gradient, the guided combination of the two decoder gradients, the
two Adam updates, the decoder's two passes run separately or fused into one
batch, and the whole step on one lane and on two (core.lanes: the two renders side by side). Writes
conceal_step_profile.json to --out.
Run it on a quiet machine.
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import augment, conceal, guidance, hidden as hidden_lib, key as key_lib, reveal
from conceal_jax.conceal.objective import decoder_identity_objective, identity_inputs, student_objective
from conceal_jax.core import fileio, lanes
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, losses, optimizer
from conceal_jax.splat import render as render_lib
from experiments.bench_conceal import ROWS, run_config
from experiments.profile_step import median_ms


def decoder_pass_times(decoder, width: int, data: dict, settings, repeats: int, distortion: dict | None = None) -> dict:
  """The decoder's share of a step, two ways, each giving the two gradient pytrees the guidance compares:
  `separate`: L_d^+ on the check render (gradients for the decoder and the render) and L_d^- on B identity
  inputs (decoder gradient), two forward+backward passes as the step runs them; `fused`: one forward of
  the batch of 1 + B images and the two gradients as the Jacobian rows of (L_d^+, L_d^-) (jax.jacrev, a
  backward pass batched over the two losses)."""
  check = data["teacher_small"][0]
  minus_inputs = identity_inputs(data, 1, settings, data["teacher"][0], distortion)
  hidden = data["hidden"]
  plus_loss = lambda d, x: losses.hidden_image_loss(reveal.decode(d, width, x), hidden)
  minus_loss = lambda d: losses.decoder_identity_loss(reveal.decode(d, width, minus_inputs), minus_inputs)

  def separate(d, x):
    plus_grads = jax.grad(plus_loss, argnums=(0, 1))(d, x)
    return plus_grads, jax.grad(minus_loss)(d)

  def both_losses(d, x):
    out = reveal.decode(d, width, jnp.concatenate([x[None], minus_inputs]))
    return jnp.stack([losses.hidden_image_loss(out[0], hidden), losses.decoder_identity_loss(out[1:], minus_inputs)])

  fused = lambda d, x: jax.jacrev(both_losses, argnums=(0, 1))(d, x)
  batch = len(minus_inputs)
  return {f"decoder_passes_separate_b{batch}": median_ms(jax.jit(separate), decoder, check, repeats=repeats),
          f"decoder_passes_fused_b{batch}": median_ms(jax.jit(fused), decoder, check, repeats=repeats)}


def step_ms(settings, variants: dict, student_tx, decoder_tx, gaussians, decoder, data, num_views: int,
            repeats: int, distortion: dict | None = None, rounds: int = 3) -> dict:
  """Median ms of the whole jitted step (state donated) for each variant, name -> (render options, number of
  lanes (core.lanes)), after one warm-up each; the variants take turns, `rounds` times `repeats` steps, so
  that a slower stretch of the machine does not fall on one of them only."""
  runs = {}
  for name, (options, count) in variants.items():
    mesh = lanes.lane_mesh(count)
    step = conceal.make_conceal_step(settings, options, student_tx, decoder_tx, mesh=mesh)
    fresh = jax.tree.map(jnp.copy, (gaussians, decoder))
    state = lanes.replicate(conceal.create_conceal_state(*fresh, student_tx, decoder_tx), mesh)
    placed = lanes.replicate(data, mesh)
    state, _ = step(state, placed, 0, 1, 0, distortion)
    runs[name] = [step, state, placed, []]
  for _ in range(rounds):
    for name, run in runs.items():
      step, state, placed, times = run
      for i in range(repeats):
        start = time.perf_counter()
        state, stats = step(state, placed, i % num_views, (i + 1) % num_views, 0, distortion)
        jax.block_until_ready(stats)
        times.append(time.perf_counter() - start)
      run[1] = state
  return {name: 1e3 * float(np.median(run[3])) for name, run in runs.items()}


def profile(row: str, width: int, teacher: pathlib.Path, repeats: int, key_at_decoder_size: bool,
            headrooms: tuple[float, ...] = ()) -> dict:
  """One profile row; `headrooms`: also time the whole step (on the most lanes) at pair capacities of
  these multiples of the largest need over the training views, instead of the bucket above the need."""
  config = run_config("lego", teacher, row, width, 0, 0)
  c = config.conceal
  c.key_at_decoder_size = key_at_decoder_size
  settings = conceal.settings_from_config(config)
  gaussians = jax.tree.map(jnp.asarray, ply.load_ply(c.teacher))
  scene = evaluate.load_scene_data(config)
  check_pose, _ = key_lib.check_camera(scene.train_cameras, c.key_kind, c.key_index, c.key_seed)
  check_camera = conceal.key_camera(check_pose, key_at_decoder_size, settings.hidden_size)
  options = evaluate.render_options(config, scene.background)
  needed = max(int(render_lib.render(gaussians, cam, options).num_pairs)
               for cam in (check_camera, scene.train_cameras[0]))
  options = render_lib.grow_capacity(options, needed)
  # the largest need over every training view, for the headroom variants only (a render per view)
  views_need = max(int(render_lib.render(gaussians, cam, options).num_pairs)
                   for cam in scene.train_cameras) if headrooms else None
  hidden = hidden_lib.load_hidden_image(c.hidden, settings.hidden_size)
  data = conceal.build_data(scene, gaussians, options, check_camera, jnp.asarray(scene.train_images[0]), hidden,
                            settings.hidden_size)
  decoder = conceal.initial_decoder(config, settings)
  # rows trained through distortions (conceal_ours.robust) take one each step; a fixed draw times the same work
  distortion = augment.draw(np.random.default_rng(0), settings.augmentation) if settings.augmentation.draws else None
  times = {}

  camera = jax.tree.map(lambda x: x[0], data["cameras"])
  kd = lambda g: losses.distillation_loss(render_lib.render(g, camera, options).rgb, data["teacher"][0])
  times["normal_render_kd_fwd_bwd"] = median_ms(jax.jit(jax.grad(kd)), gaussians, repeats=repeats)
  student = jax.jit(jax.value_and_grad(
      lambda g, d: student_objective(g, d, data, 0, settings, options, distortion), argnums=(0, 1), has_aux=True))
  times["student_objective_fwd_bwd"] = median_ms(student, gaussians, decoder, repeats=repeats)

  apply = lambda d, x: reveal.decode(d, width, x)
  for batch in (1, 2):
    images = data["teacher_small"][:batch]
    times[f"decoder_fwd_batch{batch}"] = median_ms(jax.jit(apply), decoder, images, repeats=repeats)
    times[f"decoder_fwd_bwd_batch{batch}"] = median_ms(
        jax.jit(jax.grad(lambda d, x: jnp.sum(apply(d, x)))), decoder, images, repeats=repeats)
  inputs = identity_inputs(data, 1, settings, data["teacher"][0], distortion)  # a teacher render as the student's
  identity = jax.jit(jax.value_and_grad(lambda d: decoder_identity_objective(d, inputs, settings)))
  times["decoder_identity_fwd_bwd"] = median_ms(identity, decoder, repeats=repeats)

  times.update(decoder_pass_times(decoder, width, data, settings, repeats, distortion))

  (_, _), (_, plus_grad) = student(gaussians, decoder)
  _, minus_grad = identity(decoder)
  guided = jax.jit(lambda p, m: guidance.guided_decoder_gradient(p, m, 1.0, 1.0, settings.granularity))
  times["guidance"] = median_ms(guided, plus_grad, minus_grad, repeats=repeats)
  student_tx = optimizer.gaussian_optimizer(c.lr, scene.scene_extent(), c.iterations)
  decoder_tx = conceal.decoder_optimizer(config)
  times["student_adam"] = median_ms(jax.jit(student_tx.update), gaussians, student_tx.init(gaussians), gaussians,
                                    repeats=repeats)
  times["decoder_adam"] = median_ms(jax.jit(decoder_tx.update), plus_grad, decoder_tx.init(decoder), decoder,
                                    repeats=repeats)

  counts = (1, 2) if jax.local_device_count() >= 2 else (1,)
  variants = {f"conceal_step_lanes{count}": (options, count) for count in counts}
  variants.update({f"conceal_step_lanes{counts[-1]}_headroom{h:g}": (
      dataclasses.replace(options, pair_capacity=render_lib.round_capacity(views_need * h)), counts[-1])
      for h in headrooms})
  times.update(step_ms(settings, variants, student_tx, decoder_tx, gaussians, decoder, data, len(scene.train_cameras),
                       repeats, distortion))
  return dict(row=row, key_at_decoder_size=key_at_decoder_size, decoder_width=width, num_gaussians=int(gaussians.num),
              pair_capacity=options.pair_capacity,
              views_pair_need=views_need,
              tile_size=options.tile_size, image_size=[camera.width, camera.height],
              hidden_size=settings.hidden_size, settings=dataclasses.asdict(settings), repeats=repeats,
              median_ms=times)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--widths", default="16,64")
  parser.add_argument("--repeats", type=int, default=7)
  parser.add_argument("--row", default="ours", choices=sorted(ROWS), help="a bench-conceal row's settings")
  parser.add_argument("--headrooms", default="",
                      help="comma-separated multiples of the training views' largest pair need to time the step at")
  parser.add_argument("--key-at-decoder-size", default="0",
                      help="comma-separated 0/1: profile with the key rendered at the decoder size, or not")
  args = parser.parse_args()
  teacher = pathlib.Path(args.workdir) / "lego" / "teacher" / "point_cloud.ply"
  if not teacher.is_file():
    raise SystemExit(f"no teacher at {teacher}: run make bench-train first")
  rows = []
  for width in (int(w) for w in args.widths.split(",") if w):
    for small_key in (bool(int(k)) for k in args.key_at_decoder_size.split(",")):
      rows.append(profile(args.row, width, teacher, args.repeats, small_key,
                          tuple(float(h) for h in args.headrooms.split(",") if h)))
      print(f"decoder width {width}, key at the decoder size {small_key}:")
      for name, ms in rows[-1]["median_ms"].items():
        print(f"  {name:28s} {ms:8.1f} ms")
  fileio.write_json(pathlib.Path(args.out) / "conceal_step_profile.json", dict(device=str(jax.devices()[0]),
                                                                                rows=rows))


if __name__ == "__main__":
  main()
