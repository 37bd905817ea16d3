"""Where a ConcealGS step spends its time: on the lego teacher of `make bench-train`, or any teacher.

  make profile-conceal                                    # bench-conceal's recommended row, widths 16 and 64
  make profile-conceal BENCH_ARGS="--widths=16 --repeats=9 --row=full"
  python -m experiments.profile_conceal --scene=demo --teacher=workdirs/demo/teacher/point_cloud.ply --widths=16
  python -m experiments.profile_conceal --widths=16 --set=conceal.attacks.merge_groups=converter \
      --set=conceal.attacks.merge_fraction=0.35 --name=conceal_step_profile_converter
  python -m experiments.profile_conceal --widths=16 --row=recommended_decoder_size \
      --name=conceal_step_profile_decoder_size

With the settings of a bench-conceal row, for each decoder width, the median of --repeats (each part jitted on its
own): one view's terms (objective.view_terms) with their gradient, for the normal view and for the check view, its
two decoder reads in turn and as the step runs them (batched: decoder_pair.py); the decoder alone (forward,
forward+backward, one image); the guided combination of the two decoder gradients; the two optimiser updates; and
the whole step with its two views on one device and split over two (core.parallel), taking turns, and where views
render from the rows that reach them (conceal/subsets.py) the same from the whole student beside it, and where only
the film's colours train the same with the gradient taken with respect to every parameter, and where the check
renders, or the normal views, are read through linear maps (conceal/linear_check.py) the same rendering them,
and where the keys and decoys are cameras of the decoder's size (conceal.carrier.at_decoder_size) the same at
the training size. The whole steps draw their distortions as a run does, one per step. --set overrides the row's
config (dotted key=value). Writes <--name>.json (conceal_step_profile.json) to --out. Run it on a quiet machine.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import itertools
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from conceal_jax.conceal import augment, carrier, decoder_pair, objective, reveal, step as step_lib
from conceal_jax.conceal import train as conceal_train
from conceal_jax.conceal import guidance, settings as settings_lib, views as views_lib
from conceal_jax.configs import demo
from conceal_jax.core import fileio, parallel
from conceal_jax.splat import render as render_lib
from experiments.bench_conceal import ROWS, run_config, set_dotted
from experiments.profile_step import median_ms


def row_config(scene: str, row: str, width: int, teacher: pathlib.Path):
  """bench-conceal's row on lego; on the demo scene, the demo config with the row's recipe and width."""
  if scene != "demo":
    return run_config(scene, teacher, row, width, 0, 0)
  config = run_config("lego", teacher, row, width, 0, 0)
  base = demo.get_config()
  base.mode, base.mark, base.conceal = "conceal", config.mark, config.conceal
  base.conceal.iterations = demo.get_config().conceal.iterations
  return base


def step_ms(run, settings, student_tx, decoder_tx, decoder, repeats: int, rounds: int = 3, others=None) -> dict:
  """Median ms of the whole jitted step (state donated) with its views on one device and, where there are two,
  split over two, after one warm-up each; normal views and distortions drawn as the run draws them (decoys at its
  decoy share); where the run reads check renders, or normal views, through linear maps, the same rendering them
  beside it.
  Where the run renders each view from the rows that reach it (subsets.py), the same with every view rendered
  from the whole student beside it (`_whole_renders`); `others` {suffix: run}: other runs of the same settings
  (prepared otherwise) beside it. They take turns, `rounds` times `repeats` steps."""
  meshes = {"conceal_step_1_device": None}
  if jax.local_device_count() >= 2:
    meshes["conceal_step_2_devices"] = parallel.batch_mesh(2)
  datas = {"": (run.start, run.data)}
  if run.data.rows is not None:
    datas["_whole_renders"] = (run.start, run.data.replace(rows=None, fixed=None))
  if run.data.colour_rows is not None:  # the time of a gradient with respect to every parameter (the whole trains)
    datas["_whole_gradient"] = (run.start, run.data.replace(colour_rows=None, ties=None))
  if run.data.check_weights is not None:
    datas["_rendered_checks"] = (run.start, run.data.replace(check_weights=None))
  if run.data.normal_weights is not None:
    datas["_rendered_normal_views"] = (run.start, run.data.replace(normal_weights=None, normal_maps=None))
  datas.update({suffix: (other.start, other.data) for suffix, other in (others or {}).items()})
  rng = np.random.default_rng(0)
  num_views, num_decoys = run.data.images.shape[0], len(run.decoys)
  normal = [views_lib.draw_normal_view(rng, num_views, num_decoys, settings.decoy_fraction) for _ in range(repeats)]
  a = settings.augmentation
  drawn = [augment.draw(rng, a) if a.draws else None for _ in range(repeats)]
  runs = {}
  for (name, mesh), (suffix, (start, data)) in itertools.product(meshes.items(), datas.items()):
    tx = student_tx(data.colour_rows is not None)
    step = step_lib.make_step(settings, run.options, tx, decoder_tx, mesh)
    state = step_lib.create_state(*jax.tree.map(jnp.copy, (start, decoder)), tx, decoder_tx, data.colour_rows)
    state, placed = parallel.replicate(state, mesh), parallel.replicate(data, mesh)
    state, _ = step(state, placed, normal[0], normal[-1], 0, drawn[0])
    runs[name + suffix] = [step, state, placed, []]
  for _ in range(rounds):
    for entry in runs.values():
      step, state, placed, times = entry
      for i in range(repeats):
        start = time.perf_counter()
        state, stats = step(state, placed, normal[i], normal[-1 - i], 0, drawn[i])
        jax.block_until_ready(stats)
        times.append(time.perf_counter() - start)
      entry[1] = state
  return {name: 1e3 * float(np.median(entry[3])) for name, entry in runs.items()}


def part_ms(run, settings, student_tx, decoder_tx, decoder, distortion, repeats: int) -> dict:
  """The parts of a step, each jitted alone."""
  s, times = settings, {}
  normal = run.data.images.shape[0] if run.decoys else 0  # a decoy, where the run has them, as most steps draw
  views = views_lib.step_views(run.data, normal, 1, 0, distortion, s)
  rows = run.data.colour_rows  # what the step differentiates: the trained colours where only they train
  place = lambda whole, g: carrier.with_trained(whole, rows, g)
  trained = carrier.trained_part(run.start, rows)
  for index, name in enumerate(("normal", "check")):
    view = jax.tree.map(lambda x, i=index: x[i], views)
    for suffix, read in (("", objective.l1_of_decoded_pair), ("_batched", decoder_pair.batched_l1_of_decoded_pair)):
      def loss(g, d, whole, v=view, read=read):
        terms = objective.view_terms(place(whole, g), d, d, v, s, run.options, run.data.merges, read_pair=read)
        return terms.student + terms.plus + terms.minus

      times[f"{name}_view_terms_fwd_bwd{suffix}"] = median_ms(jax.jit(jax.grad(loss, argnums=(0, 1))), trained,
                                                              decoder, run.start, repeats=repeats)
  image = run.data.teacher_small[0]
  apply = lambda d, x: reveal.decode(d, s.decoder_width, x)
  times["decoder_fwd"] = median_ms(jax.jit(apply), decoder, image, repeats=repeats)
  times["decoder_fwd_bwd"] = median_ms(jax.jit(jax.grad(lambda d, x: jnp.sum(apply(d, x)))), decoder, image,
                                       repeats=repeats)
  gradients = lambda g, d: step_lib.gradients(g, d, views, s, run.options, merges=run.data.merges, colour_rows=rows)
  grads, _ = jax.jit(gradients)(run.start, decoder)
  guided = jax.jit(lambda p, m: guidance.guided_decoder_gradient(p, m, 1.0, 1.0, s.granularity))
  times["guidance"] = median_ms(guided, grads["plus"], grads["minus"], repeats=repeats)
  tx = student_tx(rows is not None)
  times["student_adam"] = median_ms(jax.jit(tx.update), grads["student"], tx.init(trained), trained, repeats=repeats)
  times["decoder_adam"] = median_ms(jax.jit(decoder_tx.update), grads["plus"], decoder_tx.init(decoder), decoder,
                                    repeats=repeats)
  return times


def profile(scene: str, row: str, width: int, teacher: pathlib.Path, repeats: int, overrides=()) -> dict:
  """One profile row: the parts and the whole step of `row` at decoder `width`, its config changed by
  `overrides` (dotted key, value)."""
  config = row_config(scene, row, width, teacher)
  for key, value in overrides:
    set_dotted(config, key, value)
  plan = settings_lib.plan(config)
  s = plan.settings
  run = conceal_train.prepare(config, plan)
  others = {}
  if plan.film is not None and plan.film.at_decoder_size:  # beside it: the keys and decoys at the training size
    training_size = config.copy_and_resolve_references()
    set_dotted(training_size, "conceal.carrier.at_decoder_size", False)
    others["_training_size"] = conceal_train.prepare(training_size, settings_lib.plan(training_size))
  needed = max(int(render_lib.render(r.start, camera, r.options).num_pairs) for r in [run, *others.values()]
               for camera in (r.keys[0][0], r.scene.train_cameras[0]))
  run.options = render_lib.grow_capacity(run.options, needed)
  decoder = conceal_train.initial_decoder(config, s)
  # the parts of a row trained through distortions are timed at one fixed draw
  distortion = augment.draw(np.random.default_rng(0), s.augmentation) if s.augmentation.draws else None
  student_tx = lambda colours: settings_lib.student_optimizer(config, run.scene.scene_extent(), colours)
  decoder_tx = settings_lib.decoder_optimizer(config)
  times = part_ms(run, s, student_tx, decoder_tx, decoder, distortion, repeats)
  times.update(step_ms(run, s, student_tx, decoder_tx, decoder, repeats, others=others))
  camera = run.scene.train_cameras[0]
  return dict(scene=scene, row=row, decoder_width=width, num_gaussians=int(run.start.num),
              num_carrier=int(run.start.num - run.teacher.num),
              pair_capacity=run.options.pair_capacity, tile_size=run.options.tile_size,
              rows_per_view=None if run.data.rows is None else int(run.data.rows.shape[1]),
              image_size=[camera.width, camera.height], hidden_size=s.hidden_size,
              settings=dataclasses.asdict(s), overrides=dict(overrides), repeats=repeats, median_ms=times)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--scene", default="lego", help="lego (bench-train's scenes) or demo")
  parser.add_argument("--teacher", default="", help="the teacher .ply (default: bench-train's for --scene)")
  parser.add_argument("--widths", default="16,64")
  parser.add_argument("--repeats", type=int, default=7)
  parser.add_argument("--row", default="recommended", choices=sorted(ROWS),
                      help="a bench-conceal row's settings")
  parser.add_argument("--host_devices", type=int, default=min(2, os.cpu_count() or 1))
  parser.add_argument("--set", action="append", default=[], help="dotted.key=value overriding the row's config")
  parser.add_argument("--name", default="conceal_step_profile", help="the result file's stem")
  args = parser.parse_args()
  overrides = [(key, literal(value)) for key, _, value in (item.partition("=") for item in args.set)]
  parallel.host_devices_flag(args.host_devices)  # before JAX's backend starts
  teacher = pathlib.Path(args.teacher or pathlib.Path(args.workdir) / args.scene / "teacher" / "point_cloud.ply")
  if not teacher.is_file():
    raise SystemExit(f"no teacher at {teacher}: run make bench-train first, or pass --teacher")
  rows = []
  for width in (int(w) for w in args.widths.split(",") if w):
    rows.append(profile(args.scene, args.row, width, teacher, args.repeats, overrides))
    print(f"decoder width {width}:")
    for name, ms in rows[-1]["median_ms"].items():
      print(f"  {name:34s} {ms:8.1f} ms")
  fileio.write_json(pathlib.Path(args.out) / f"{args.name}.json", dict(device=str(jax.devices()[0]), rows=rows))


def literal(text: str):
  """A --set value: a Python literal (number, tuple, bool), else the text itself."""
  try:
    return ast.literal_eval(text)
  except (ValueError, SyntaxError):
    return text


if __name__ == "__main__":
  main()
