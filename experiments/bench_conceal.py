"""ConcealGS benchmark on lego (200x200; or beer at 1/4, --scenes) with the teacher of `make bench-train`,
hidden image astronaut at 64x64: the paper's method, its ablations (paper Table 3), the released code's
choices and the leakage control, at one or more decoder widths.

  make bench-conceal                                            # every row, 10k steps, widths 16 and 64
  make bench-conceal BENCH_ARGS="--rows=full,leakage_control --widths=16"
  make bench-conceal BENCH_ARGS="--iterations=1000 --widths=16 --rows=full --eval-views=20"
  make bench-conceal BENCH_ARGS=--reuse                         # rebuild the JSON, table and plot

Each run goes to <workdir>/<scene>/conceal_<row>_w<width> (resumable; a killed bench picks up where it
stopped). Writes conceal_bench.json (per row: render PSNR / SSIM / LPIPS of student and teacher against
ground truth and of the student against the teacher, hidden PSNR / SSIM at the check view, leakage, wall
time, median step time, and the curves of hidden PSNR / SSIM and student test PSNR against minutes),
conceal_bench.md and conceal_bench.png to --out, and a copy of each run's revealed images under
<out>/revealed/ (make reproduce's figure). Rows of earlier invocations stay in the JSON.
"""
from __future__ import annotations

import argparse
import json
import pathlib

from conceal_jax.conceal import train as conceal_train
from conceal_jax.configs import lego_conceal, recipes
from conceal_jax.core import checkpoint, fileio, loop, workdir as workdir_lib
from conceal_jax.gs import evaluate
from experiments import results_io
from experiments.bench_train import scene_config


def leakage_control(config):
  """The paper with leakage control and the gentle student: the in_scene recipe's first steps."""
  return recipes.gentle_student(recipes.leakage_control(recipes.paper(config), recipes.DECOY_VIEWS))


def through_attacks(clip_input: bool):
  """leakage_control trained through attacks, the decoder reading renders clipped to [0, 1] (`clip_input`) or as
  they are. With the clip it is the in_scene recipe before its decoder schedule (the rate decaying to 0.3x, each
  tensor's step clipped to RMS 1)."""
  return lambda config: recipes.through_attacks(leakage_control(config), clip_input=clip_input)


# A row: the recipe it starts from (configs/recipes.py, or a function of the config) and dotted overrides below
# the config (conceal.*, seed). What each row is, what it measured and why it was tried:
# experiments/results/conceal_bench_rows.md; its figures: conceal_bench.md and REPRODUCTION.md.
DECODER_DECAY = "conceal.decoder_opt.lr_final_ratio"  # the decoder's rate decays to this share of its start
UPDATE_CLIP = {"conceal.decoder_opt.update_clip": 1.0}
POLISHED = {"conceal.decoder_opt.polish_steps": 2000}
PLUS_WEIGHT2 = {"conceal.weight_plus": 2.0}
# The recommended recipe of 2026-11-28 afternoon: the film flat along the key's axis, through the converter's groups
# in a third of the check renders.
RECOMMENDED_FLAT = {"conceal.carrier.thickness": 0.01, "conceal.attacks.merge_fraction": 0.35}
# The recommended recipe until 2026-11-28: the flat film's neighbouring pairs merged, decoys turned 1-10 degrees,
# the watched key's L_d^- weight.
RECOMMENDED_PAIRS = {"conceal.attacks.merge_groups": "nearest", "conceal.attacks.merge_scales": (1.0,),
                     "conceal.attacks.merge_fraction": recipes.MERGE_FRACTION, "conceal.attacks.regroup_every": 500,
                     "conceal.leakage.decoy_rotation_deg": (1.0, 10.0),
                     "conceal.weight_minus": recipes.WATCH_WEIGHT_MINUS, "conceal.carrier.thickness": 0.01}
# A film grid every 6 pixels of a 64-pixel key (lego's film grid, lego_conceal.FILM_SPACING, read at the decoder's
# size), in pixels of lego's 200-pixel key: a ninth of its splats.
SPARSE_FILM_SPACING = 18.75
# The recommended recipe until 2026-12-01: its decoys in random directions about the key, the decoder not polished
# (every row built on it before then ran so).
RANDOM_DECOYS = {"conceal.leakage.decoy_key_axes": False, "conceal.decoder_opt.polish_steps": 0,
                 "conceal.decoder_opt.polish_merge_fraction": None}
ROWS = {
    "full": ("paper", {}),
    "no_decoder": ("paper", {"conceal.use_decoder": False}),
    "no_consistency": ("paper", {"conceal.consistency": False}),
    "no_guidance": ("paper", {"conceal.guidance": False}),
    "released": ("released", {}),
    "tensor": ("paper", {"conceal.granularity": "tensor"}),
    "leakage_control": (leakage_control, {DECODER_DECAY: 0.1}),
    "leakage_control_through_attacks": (through_attacks(False), {DECODER_DECAY: 0.1}),
    "leakage_control_through_attacks_centered_input": (through_attacks(False),
                                                       {DECODER_DECAY: 0.1, "conceal.decoder.input_norm": "center"}),
    "leakage_control_through_attacks_clipped_input": (through_attacks(True), {DECODER_DECAY: 0.1}),
    "in_scene_steganerf_decoder_schedule": (through_attacks(True), {DECODER_DECAY: 0.1,
                                                                    "conceal.decoder_opt.lr": 1e-3,
                                                                    "conceal.decoder_opt.adam_eps": 1e-8}),
    "in_scene_no_update_clip": (through_attacks(True), {DECODER_DECAY: 0.3}),
    "in_scene_no_update_clip_decoder_decay05": (through_attacks(True), {DECODER_DECAY: 0.5}),
    "in_scene": ("in_scene", {}),
    "recommended": ("recommended", {}),
    "recommended_random_decoys": ("recommended", RANDOM_DECOYS),
    "recommended_flat": ("recommended", {**RANDOM_DECOYS, **RECOMMENDED_FLAT}),
    "recommended_pairs": ("recommended", {**RANDOM_DECOYS, **RECOMMENDED_PAIRS}),
    "recommended_decoder_size": ("recommended", {**RANDOM_DECOYS, "conceal.carrier.at_decoder_size": True}),
    "recommended_decoder_size_near": ("recommended", {**RANDOM_DECOYS, "conceal.carrier.at_decoder_size": True,
                                                      "conceal.leakage.decoy_translation":
                                                          recipes.DECODER_SIZE_DECOY_TRANSLATION}),
    "recommended_at_decoder_size": ("recommended_at_decoder_size", {}),
    "recommended_decoder_size_more_decoys": ("recommended_at_decoder_size", RANDOM_DECOYS),
    "recommended_decoder_size_sparse": ("recommended", {**RANDOM_DECOYS, "conceal.carrier.at_decoder_size": True,
                                                        "conceal.carrier.spacing": SPARSE_FILM_SPACING}),
    "in_scene_decoder_decay05": ("in_scene", {DECODER_DECAY: 0.5}),
    "in_scene_polished": ("in_scene", POLISHED),
    "in_scene_decoder_lr3e4": ("in_scene", {"conceal.decoder_opt.lr": 3e-4}),
    "in_scene_no_update_clip_seed1": (through_attacks(True), {DECODER_DECAY: 0.3, "seed": 1}),
    "in_scene_no_update_clip_seed1_polished": (through_attacks(True), {DECODER_DECAY: 0.3, "seed": 1, **POLISHED}),
    "released_polished": ("released", POLISHED),
    "released_seed1": ("released", {"seed": 1}),
    "released_decoder_decay03_update_clip": ("released", {DECODER_DECAY: 0.3, **UPDATE_CLIP}),
    "released_12k_steps": ("released", {"conceal.iterations": 12_000}),
    "released_plus_weight2": ("released", PLUS_WEIGHT2),
    "released_decoder_decay03_update_clip_seed1": ("released", {DECODER_DECAY: 0.3, "seed": 1, **UPDATE_CLIP}),
    "released_plus_weight2_seed1": ("released", {**PLUS_WEIGHT2, "seed": 1}),
    "released_plus_weight2_update_clip": ("released", {**UPDATE_CLIP, **PLUS_WEIGHT2}),
    "released_plus_weight2_update_clip_seed1": ("released", {**UPDATE_CLIP, "seed": 1, **PLUS_WEIGHT2}),
}
# A row that continues another's run starts from that run's checkpoint at the end of its joint steps, where its
# config is the other's up to the continuation (the polish steps), so it costs only its extra steps.
CONTINUES = dict(released_polished="released", in_scene_polished="in_scene",
                 in_scene_no_update_clip_seed1_polished="in_scene_no_update_clip_seed1")
CONTINUATION_KEY = "conceal.decoder_opt.polish_steps"
# The released decoder (width 64) starts from VGG16 with lr 1e-4; a narrow one starts from scratch at
# recipes.NARROW_DECODER_LR.
DECODER_LR = {64: 1e-4, recipes.NARROW_DECODER_WIDTH: recipes.NARROW_DECODER_LR}
# A scene's own carrier-film grid, as its conceal config sets it.
FILM_GRIDS = dict(lego=lego_conceal.film_grid)
WIDTH_FREE_ROWS = ("no_decoder",)  # without a decoder the width does not matter: run once
# The concealment issue's targets (lego: widths 16 and 64; the time for width 16).
TARGETS = dict(lego=dict(hidden_psnr=34.0, hidden_ssim=0.99, student_psnr_loss=0.3, leakage=0.2, minutes_width16=60.0),
               beer=dict(hidden_psnr=37.5, hidden_ssim=0.99, student_psnr_loss=0.2),
               beer_llff=dict(hidden_psnr=37.5, hidden_ssim=0.99, student_psnr_loss=0.2, leakage=0.2))
CURVE_EVERY, CURVE_VIEWS = lego_conceal.EVAL_EVERY, lego_conceal.EVAL_VIEWS


def set_dotted(config, dotted: str, value) -> None:
  """config[a][b][c] = value for dotted 'a.b.c'."""
  *sections, name = dotted.split(".")
  for part in sections:
    config = config[part]
  config[name] = value


def continue_from(source_dir: pathlib.Path, run_dir: pathlib.Path, config) -> bool:
  """Copies the checkpoint of `source_dir`'s run at conceal.iterations into `run_dir` (which has none), if that
  run's config.json is `config` but for CONTINUATION_KEY; whether it did (if not, the row trains from step 0)."""
  ckpt_dir = run_dir / loop.CHECKPOINT_DIR
  source = pathlib.Path(checkpoint.checkpoint_path(str(source_dir / loop.CHECKPOINT_DIR), config.conceal.iterations))
  if checkpoint.list_steps(str(ckpt_dir)) or not source.is_file():
    return False
  try:
    differ = workdir_lib.differing_keys(json.loads((source_dir / "config.json").read_text()), config.to_dict())
  except (OSError, ValueError):
    differ = ["config.json"]
  if set(differ) - {CONTINUATION_KEY}:
    print(f"not continuing {source_dir}: its config.json differs from this row's in {differ}")
    return False
  fileio.copy_file(source, ckpt_dir / source.name)
  return True


def run_config(scene: str, teacher: pathlib.Path, row: str, width: int, iterations: int, eval_views: int):
  config = scene_config(scene, None)  # the teacher's data and render settings
  config.mode = "conceal"
  config.mark.teacher, config.mark.hidden = str(teacher), "astronaut"
  config.conceal.eval_every, config.conceal.eval_views = CURVE_EVERY, CURVE_VIEWS
  config.eval.max_views = eval_views
  recipe, overrides = ROWS[row]
  config = recipes.apply(config, recipe) if isinstance(recipe, str) else recipe(config)
  config = FILM_GRIDS.get(scene, lambda c: c)(config)
  d = config.conceal.decoder
  d.width, d.vgg_init = width, width == 64
  config.conceal.decoder_opt.lr = DECODER_LR.get(width, config.conceal.decoder_opt.lr)
  for name, value in overrides.items():
    set_dotted(config, name, value)
  if iterations:  # --iterations shortens every row, its own length included
    config.conceal.iterations = iterations
  return config


def finished_run(run_dir: pathlib.Path) -> dict | None:
  """conceal_and_evaluate's result of a finished run, from its conceal.json and metrics.json."""
  try:
    summary = json.loads((run_dir / conceal_train.SUMMARY_FILE).read_text())
    return dict(summary, metrics=json.loads((run_dir / evaluate.METRICS_FILE).read_text()))
  except (OSError, ValueError):
    return None


def summary_row(scene: str, row: str, width: int, result: dict) -> dict:
  m = result["metrics"]
  history = result["history"]
  recipe, overrides = ROWS[row]
  overrides = dict(overrides, recipe=recipe if isinstance(recipe, str) else f"experiments/bench_conceal.py ({row})")
  return dict(scene=scene, row=row, decoder_width=width, overrides=overrides, iterations=result["iterations"],
              decoder_polish_steps=result.get("decoder_polish_steps", 0),
              wall_time_s=result["wall_time_s"], median_step_s=result["median_step_s"],
              step_devices=result.get("step_devices", []), num_decoys=result.get("num_decoys", 0), **m,
              student_psnr_loss=m["teacher_vs_ground_truth"]["psnr"] - m["student_vs_ground_truth"]["psnr"],
              max_leakage=max(m["leakage"].values()),
              curve=[(h["step"], h["elapsed_s"], h["hidden_psnr"], h["hidden_ssim"], h["test_psnr"])
                     for h in history if "hidden_psnr" in h])


def run(scene, rows, widths, iterations, eval_views, workdir: pathlib.Path, out: pathlib.Path,
        reuse: bool) -> list[dict]:
  """Runs (or resumes, or with `reuse` reads) every (row, width) on `scene`; rewrites the JSON, table and
  plot after each, so a stopped bench keeps its rows."""
  teacher = workdir / scene / "teacher" / "point_cloud.ply"
  if not teacher.is_file():
    print(f"skipping {scene}: no teacher at {teacher}; run `make bench-train` first")
    return []
  results = []
  for width in widths:
    for row in rows:
      if row in WIDTH_FREE_ROWS and width != widths[0]:
        continue
      run_dir = workdir / scene / f"conceal_{row}_w{width}"
      result = finished_run(run_dir) if reuse else None
      if result is None:
        if reuse:
          print(f"skipping {scene} {row} w{width}: no finished run in {run_dir}")
          continue
        config = run_config(scene, teacher, row, width, iterations, eval_views)
        run_dir.mkdir(parents=True, exist_ok=True)
        # as the command line would write it (bench-robust reads it); refused if the workdir ran other settings
        workdir_lib.claim(str(run_dir), config.to_dict())
        if row in CONTINUES and continue_from(workdir / scene / f"conceal_{CONTINUES[row]}_w{width}", run_dir, config):
          print(f"{row}: continuing {CONTINUES[row]}'s run from step {config.conceal.iterations}")
        result = conceal_train.train_and_evaluate(config, str(run_dir))
      results.append(dict(summary_row(scene, row, width, result),
                          images=results_io.keep_images(out, run_dir, results_io.CONCEAL_IMAGES)))
      print(json.dumps({k: v for k, v in results[-1].items() if k not in ("curve", "near_check")}))
      results_io.write_results(out, "conceal_bench", results, row_key, table, plot, targets=TARGETS)
  return results


def row_key(r: dict) -> tuple:
  return r.get("scene", "lego"), r.get("row"), r.get("decoder_width")


def table(rows) -> str:
  lines = ["| scene | row | width | steps | wall time (min) | median step (ms) | student PSNR / SSIM / LPIPS | "
           "teacher PSNR | loss (dB) | vs teacher PSNR | hidden PSNR / SSIM | "
           "leakage: test views / clean teacher / near key |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    s, t, v, h = r["student_vs_ground_truth"], r["teacher_vs_ground_truth"], r["student_vs_teacher"], r["hidden"]
    lines.append(f"| {r['scene']} | {r['row']} | {r['decoder_width']} | {results_io.conceal_steps(r)} | "
                 f"{r['wall_time_s'] / 60:.1f}{results_io.on_device(r)} | {1e3 * r['median_step_s']:.0f} | "
                 f"{s['psnr']:.2f} / {s['ssim']:.4f} / {s['lpips']:.4f} | {t['psnr']:.2f} | "
                 f"{r['student_psnr_loss']:.2f} | {v['psnr']:.2f} | {h['psnr']:.2f} / {h['ssim']:.4f} | "
                 f"{results_io.leakage_cells(r['leakage'])}{'' if 'near_poses' in r else ' *'} |")
  if any("near_poses" not in r for r in rows):
    lines += ["", "*: near the key in 4 random directions only, scored before the key's own axes were added "
              "(near.KEY_AXES; experiments/results/near_key_axes.md): a lower bound of today's figure."]
  return "\n".join(lines) + "\n"


def plot(rows, path: pathlib.Path):
  """Hidden PSNR and student test PSNR (quick subset) against minutes, and the final leakage per row. Minutes are
  on a log axis, so that a run on an accelerator (dashed) and one on this CPU both show their shape; one legend
  below the axes names every curve."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
  colours = plt.get_cmap("tab20")
  for i, r in enumerate(rows):
    label = f"{r['scene']} {r['row']} w{r['decoder_width']}{results_io.on_device(r)}"
    style = dict(marker=".", color=colours(i % 20), linestyle="--" if results_io.on_device(r) else "-", label=label)
    minutes = [t / 60 for _, t, *_ in r["curve"]]
    axes[0].plot(minutes, [p for *_, p, _, _ in r["curve"]], **style)
    axes[1].plot(minutes, [p for *_, p in r["curve"]], **dict(style, label=None))
  for scene in sorted({r["scene"] for r in rows} & set(TARGETS)):
    axes[0].axhline(TARGETS[scene]["hidden_psnr"], color="k", linestyle=":", alpha=0.6)
  axes[0].set_ylabel("hidden PSNR at the check view (dB)")
  axes[1].set_ylabel(f"student test PSNR, {CURVE_VIEWS} views (dB)")
  timed = any(t > 0 for r in rows for _, t, *_ in r["curve"])  # a log axis needs a positive minute
  for ax in axes[:2]:
    ax.set_xscale("log" if timed else "linear")
    ax.set_xlabel("training wall time (min, log scale)" if timed else "training wall time (min)")
  labels = [f"{r['scene']} {r['row']} w{r['decoder_width']}" for r in rows]
  kinds = (("max_ssim_student_test_views", "student test views"), ("ssim_teacher_check_view", "clean teacher"),
           ("max_ssim_near_check", "near the key"))
  for j, (key, name) in enumerate(kinds):
    axes[2].bar([i + 0.27 * (j - 1) for i in range(len(rows))], [r["leakage"].get(key, 0.0) for r in rows],
                width=0.27, label=name)
  axes[2].axhline(TARGETS["lego"]["leakage"], color="k", linestyle=":", alpha=0.6)
  axes[2].set_xticks(range(len(rows)), labels, fontsize=6, rotation=90)
  axes[2].set_ylabel("leakage: max SSIM of F(view) to I")
  axes[2].legend(fontsize=7)
  for ax in axes:
    ax.grid(alpha=0.3)
  fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=3, fontsize=7)
  fileio.save_figure(fig, path)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench")
  parser.add_argument("--scenes", default="lego", help="comma-separated bench-train scenes (lego, beer, beer_llff)")
  parser.add_argument("--rows", default=",".join(ROWS))
  parser.add_argument("--widths", default="16,64")
  parser.add_argument("--iterations", type=int, default=0, help="0: the config's 10k")
  parser.add_argument("--eval-views", type=int, default=0, help="test views scored per run; 0: all 200")
  parser.add_argument("--reuse", action="store_true", help="read finished runs instead of running them")
  args = parser.parse_args()
  rows = [r for r in args.rows.split(",") if r]
  if set(rows) - set(ROWS):
    parser.error(f"unknown rows {sorted(set(rows) - set(ROWS))}; choose from {sorted(ROWS)}")
  for scene in (s for s in args.scenes.split(",") if s):
    run(scene, rows, [int(w) for w in args.widths.split(",")], args.iterations, args.eval_views,
        pathlib.Path(args.workdir), pathlib.Path(args.out), args.reuse)


if __name__ == "__main__":
  main()
