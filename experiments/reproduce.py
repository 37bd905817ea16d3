"""`make reproduce`: the paper's tables with its numbers beside ours, as experiments/results/REPRODUCTION.md.

  make reproduce            # runs bench-train, bench-conceal, bench-baselines, bench-robust, then this
  make reproduce REUSE=1    # only this: reads the JSON those benchmarks wrote

Ours are read from train_bench.json, conceal_bench.json, baseline_bench.json, robust_bench.json,
ownership_calibration.json and ownership_bench.json in --results; a row whose benchmark has not produced it yet
says so. The paper's numbers
are constants below (ConcealGS, Yang et al. 2025, arXiv:2501.03605, Tables 1-3; its NeRF-Synthetic rows average
lego, drums, chair and ship, its T&T/DB rows playroom, drjohnson, truck and train; ours are lego and the real
capture beer).

The report is written for a reader: the paper's tables carry one ConcealGS row per recipe of
conceal_jax/configs/recipes.py (recommended, in_scene, paper, released), each the mean and range over the seeds run
(`recipe_runs`), the paper's ablations and the baselines at the recipes' length; every other experiment is in
the appendix (every bench-conceal run, retired rows included, every baseline run, every run beside StegaNeRF).
The figures show the recipes' runs and the baselines only: one grid per scene (reproduction_<scene>.png: the
hidden image and what the decoder reveals from the student at the key, from the clean teacher at the key and from
the student's most revealing test view; below, what each baseline's scene reveals at the key) and on lego the
recipes beside StegaNeRF (tradeoff_lego.png, see experiments/tradeoff.py).
"""
from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from conceal_jax.configs import default, recipes
from conceal_jax.core import fileio
from experiments import bench_conceal, bench_full, bench_survive, results_io, tradeoff

# (render PSNR, SSIM, LPIPS, hidden PSNR, hidden SSIM); None where the paper has no number.
PAPER_TABLE1 = {  # NeRF-Synthetic
    "3D-GS": (34.45, 0.9732, 0.0220, None, None),
    "LSB": (33.05, 0.9704, 0.0253, 6.13, 0.1218),
    "DeepStega": (33.06, 0.9702, 0.0253, 11.13, 0.2265),
    "StegaNeRF": (30.33, 0.9381, 0.0787, 24.60, 0.9026),
    "ConcealGS": (33.14, 0.9717, 0.0240, 33.98, 0.9942),
}
PAPER_TABLE2 = {  # Tanks&Temples / Deep Blending
    "3D-GS": (27.43, 0.9190, 0.0779, None, None),
    "LSB": (26.11, 0.8994, 0.1048, 5.98, 0.0826),
    "DeepStega": (26.17, 0.9000, 0.1047, 6.27, 0.1532),
    "StegaNeRF": (23.48, 0.7462, 0.6067, 32.33, 0.9918),
    "ConcealGS": (27.26, 0.9177, 0.0796, 37.53, 0.9935),
}
PAPER_TABLE3 = {  # ablation on T&T
    "full": PAPER_TABLE2["ConcealGS"],
    "no_decoder": (26.25, 0.8965, 0.0884, 37.56, 0.9948),
    "no_consistency": (25.74, 0.8542, 0.1265, 37.13, 0.9924),
    "no_guidance": (26.93, 0.9043, 0.0812, 37.43, 0.9912),
}
PAPER_MILD_SSIM_DROP = 0.02  # the robustness figure: blur and JPEG, mean hidden-SSIM drop about 0.02
BASELINES = ("LSB", "DeepStega", "StegaNeRF")
# The tables' ConcealGS rows: the recipes a user chooses between, in this order, at the decoder width bench-conceal
# trains on a CPU (a width-16 decoder from scratch; the width-64 runs are in the appendix).
RECIPE_ORDER = ("recommended", "recommended_at_decoder_size", "in_scene", "paper", "released")
RECIPE_WIDTH = recipes.NARROW_DECODER_WIDTH
# The length every recipe runs (conceal.iterations); baseline runs of another length are in the appendix.
RECIPE_STEPS = default.get_config().conceal.iterations
NOT_RUN = "not run yet"
APPENDIX = "Appendix"


def load(results: pathlib.Path, name: str) -> dict:
  try:
    return json.loads((results / name).read_text())
  except (OSError, ValueError):
    return {}


def recipe_of_row() -> dict[str, tuple[str, int]]:
  """{bench-conceal row: (the recipe of configs/recipes.py it runs unchanged, its seed)}: the rows of
  bench_conceal.ROWS whose recipe is named and whose overrides set at most the seed."""
  return {row: (recipe, int(overrides.get("seed", 0))) for row, (recipe, overrides) in bench_conceal.ROWS.items()
          if isinstance(recipe, str) and set(overrides) <= {"seed"}}


def row_kind(row: str) -> str:
  """What a bench-conceal row is, in the appendix's words: a recipe, a paper ablation, a kept experiment, or a
  retired row (one no longer in bench_conceal.ROWS: it used an option since removed; its stored numbers stay)."""
  if row in recipe_of_row():
    return f"recipe: {recipe_of_row()[row][0]}"
  if row in PAPER_TABLE3:
    return "paper ablation"
  return "experiment" if row in bench_conceal.ROWS else "retired"


def spread(values: list[float], spec: str) -> str:
  """The mean of `values` formatted with `spec`, and where there are two or more their range: '40.75 (38.98-42.52)'."""
  mean = format(float(np.mean(values)), spec)
  return mean if len(values) < 2 else f"{mean} ({format(min(values), spec)}-{format(max(values), spec)})"


def cells(values) -> str:
  """PSNR / SSIM / LPIPS | hidden PSNR / SSIM as two Markdown cells ('-' for a missing number)."""
  fmt = lambda v, spec: "-" if v is None else format(v, spec)
  psnr, ssim, lpips, hidden_psnr, hidden_ssim = values
  return (f"{fmt(psnr, '.2f')} / {fmt(ssim, '.4f')} / {fmt(lpips, '.4f')} | "
          f"{fmt(hidden_psnr, '.2f')} / {fmt(hidden_ssim, '.4f')}")


def mean_cells(runs: list) -> str:
  """`cells` of the mean over runs' values; the PSNRs with their range where there are two or more runs."""
  if len(runs) == 1:
    return cells(runs[0])
  column = lambda i: [v[i] for v in runs]
  return (f"{spread(column(0), '.2f')} / {np.mean(column(1)):.4f} / {np.mean(column(2)):.4f} | "
          f"{spread(column(3), '.2f')} / {np.mean(column(4)):.4f}")


def seed_words(seeds: list[int]) -> str:
  """'1 seed (0)', '2 seeds (0, 1)'."""
  return f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''} ({', '.join(map(str, sorted(seeds)))})"


def teacher_row(train_bench: dict, scene: str) -> dict | None:
  return next((row for row in train_bench.get("rows", []) if row["scene"] == scene), None)


def teacher_values(row: dict):
  t = row["test"]
  return t["psnr"], t["ssim"], t["lpips"], None, None


def conceal_values(row: dict):
  s, h = row["student_vs_ground_truth"], row["hidden"]
  return s["psnr"], s["ssim"], s["lpips"], h["psnr"], h["ssim"]


def conceal_rows(conceal_bench: dict, scene: str) -> list[dict]:
  return [r for r in conceal_bench.get("rows", []) if r.get("scene", "lego") == scene]


def recipe_runs(conceal_bench: dict, scene: str) -> dict[str, list[dict]]:
  """{recipe: its runs on `scene` at RECIPE_WIDTH (one per seed)}, in RECIPE_ORDER; a recipe not run has none."""
  rows = recipe_of_row()
  runs = {name: [] for name in RECIPE_ORDER}
  for r in conceal_rows(conceal_bench, scene):
    if r["row"] in rows and r["decoder_width"] == RECIPE_WIDTH:
      runs[rows[r["row"]][0]].append(r)
  return runs


def recipe_label(name: str, row_names) -> str:
  """'released (released, released_seed1)': a recipe and the bench rows that ran it; the recipe's name alone where
  its one row bears that name."""
  rows = list(dict.fromkeys(row_names))
  return name if rows == [name] else f"{name} ({', '.join(rows)})"


def recipe_note(name: str, runs: list[dict]) -> str:
  """'paper (full), width 16, 10000 steps, 1 seed (0)' for a recipe's runs."""
  rows = recipe_of_row()
  devices = "".join(dict.fromkeys(results_io.on_device(r) for r in runs))
  return (f"{recipe_label(name, (r['row'] for r in runs))}, width {runs[0]['decoder_width']}, "
          f"{results_io.conceal_steps(runs[0])} steps, {seed_words([rows[r['row']][1] for r in runs])}{devices}")


def baseline_groups(baseline_bench: dict, scene: str, method: str) -> list[list[dict]]:
  """The baseline rows of `method` on `scene` at RECIPE_STEPS, grouped by the row they rerun from other seeds
  (`<row>_seed<N>`, tradeoff.recipe), in the order of those rows' names."""
  groups: dict[str, list[dict]] = {}
  for r in baseline_bench.get("rows", []):
    if r.get("method") == method and r.get("scene", "lego") == scene and r.get("iterations") == RECIPE_STEPS:
      groups.setdefault(tradeoff.recipe(r.get("row", method))[0], []).append(r)
  return [groups[name] for name in sorted(groups)]


def baseline_note(runs: list[dict]) -> str:
  """A baseline group's 'ours: run' cell: its protocol; over several seeds without a run's own figures."""
  seeds = seed_words([tradeoff.recipe(r.get("row", ""))[1] for r in runs])
  return f"{runs[0].get('protocol', '')}, {seeds}" if len(runs) == 1 else \
      f"{runs[0].get('protocol', '').split('; ')[0]}, {seeds}"


def method_table(title: str, paper: dict, scene: str, train_bench: dict, conceal_bench: dict,
                 baseline_bench: dict) -> list[str]:
  """One comparison table: each method's paper cells beside ours on `scene`: the teacher, each baseline group and
  each recipe as the mean (range) over its seeds."""
  lines = [f"### {title}", "",
           f"| method | paper: PSNR / SSIM / LPIPS | paper: hidden PSNR / SSIM | ours ({scene}): PSNR / SSIM / LPIPS | "
           "ours: hidden PSNR / SSIM | ours: run, seeds |", "|---|---|---|---|---|---|"]
  teacher = teacher_row(train_bench, scene)
  ours = {"3D-GS": [(cells(teacher_values(teacher)), f"teacher (bench-train){results_io.on_device(teacher)}")]
                   if teacher else []}
  ours["ConcealGS"] = [(mean_cells([conceal_values(r) for r in runs]) if runs else "- | -",
                        recipe_note(name, runs) if runs else f"{name}: {NOT_RUN}")
                       for name, runs in recipe_runs(conceal_bench, scene).items()]
  for b in BASELINES:
    ours[b] = [(mean_cells([conceal_values(r) for r in runs]), baseline_note(runs))
               for runs in baseline_groups(baseline_bench, scene, b)]
  for method, values in paper.items():
    for i, (mine, note) in enumerate(ours.get(method) or [("- | -", NOT_RUN)]):
      paper_cells = cells(values) if i == 0 else "| "
      lines.append(f"| {method} | {paper_cells} | {mine} | {note} |")
  return lines + [""]


def ablation_table(conceal_bench: dict) -> list[str]:
  """The paper's Table 3 rows beside ours on lego at RECIPE_WIDTH; each row over the seeds it was run from."""
  lines = ["### Table 3: ablation (paper: T&T; ours: lego)", "",
           "| row | paper: PSNR / SSIM / LPIPS | paper: hidden PSNR / SSIM | ours: PSNR / SSIM / LPIPS | "
           "ours: hidden PSNR / SSIM | ours: width, steps, seeds |", "|---|---|---|---|---|---|"]
  rows = conceal_rows(conceal_bench, "lego")
  for name, values in PAPER_TABLE3.items():
    mine = [r for r in rows if r["row"] == name and r["decoder_width"] == RECIPE_WIDTH]
    mine_cells = (f"{mean_cells([conceal_values(r) for r in mine])} | {mine[0]['decoder_width']}, "
                  f"{results_io.conceal_steps(mine[0])}, {seed_words([0] * len(mine))}") if mine else \
        f"- | - | {NOT_RUN}"
    lines.append(f"| {name} | {cells(values)} | {mine_cells} |")
  return lines + [""]


def leakage_table(conceal_bench: dict) -> list[str]:
  """Leakage of each recipe (mean and range over its seeds) and of the paper's ablations, per scene."""
  lines = ["### Leakage (max SSIM of the decoder output to I; the paper reports none; the floor is what the same "
           "decoder scores on the clean teacher's test views)", "",
           "| scene | recipe or ablation | seeds | student test views | clean teacher at the key | near the key | "
           "floor: clean teacher's test views |", "|---|---|---|---|---|---|---|"]
  rows = recipe_of_row()
  for scene in dict.fromkeys(r.get("scene", "lego") for r in conceal_bench.get("rows", [])):
    groups = [(recipe_label(name, (r["row"] for r in runs)), runs,
               [rows[r["row"]][1] for r in runs]) for name, runs in recipe_runs(conceal_bench, scene).items() if runs]
    groups += [(r["row"], [r], [0]) for r in conceal_rows(conceal_bench, scene)
               if r["row"] in PAPER_TABLE3 and r["row"] != "full" and r["decoder_width"] == RECIPE_WIDTH]
    for label, runs, seeds in groups:
      leak = [spread([r["leakage"].get(k, float("nan")) for r in runs], ".3f") for k in results_io.LEAKAGE_KEYS]
      floors = [r["leakage_floor"]["max_ssim_teacher_test_views"] for r in runs if "leakage_floor" in r]
      lines.append(f"| {scene} | {label} | {seed_words(seeds)} | {' | '.join(leak)} | "
                   f"{spread(floors, '.3f') if floors else '-'} |")
  if len(lines) == 4:
    lines.append(f"| {NOT_RUN} | | | | | | | |")
  return lines + [""]


def tradeoff_points(scene: str, conceal_bench: dict, baseline_bench: dict) -> list[dict]:
  """tradeoff.points of `scene`: every ConcealGS run but the paper's ablations (the full method stays) and every
  StegaNeRF run."""
  ablations = set(PAPER_TABLE3) - {"full"}
  return tradeoff.points([r for r in conceal_rows(conceal_bench, scene) if r["row"] not in ablations],
                         [r for r in baseline_bench.get("rows", []) if r.get("scene", "lego") == scene])


def recipe_points(scene: str, conceal_bench: dict, baseline_bench: dict) -> list[dict]:
  """The recipes and StegaNeRF's rows at RECIPE_STEPS on `scene`, each the mean over its seeds
  (tradeoff.over_seeds, one seed enough); a recipe's run is named by recipe_label."""
  runs = recipe_runs(conceal_bench, scene)
  label = {r["row"]: name for name, group in runs.items() for r in group}
  ours = tradeoff.points([r for group in runs.values() for r in group],
                         [r for r in baseline_bench.get("rows", []) if r.get("scene", "lego") == scene
                          and r.get("iterations") == RECIPE_STEPS])
  for p in ours:
    if p["method"] == "ConcealGS":
      p["recipe"] = recipe_label(label[p["recipe"]], [p["recipe"]])
  return tradeoff.over_seeds(ours, min_seeds=1)


def robustness_table(robust_bench: dict) -> list[str]:
  lines = ["### Robustness: mean hidden-SSIM drop under blur (sigma <= 1) and JPEG (quality >= 70)", "",
           "| run | paper | ours |", "|---|---|---|"]
  for run in robust_bench.get("runs", []):
    lines.append(f"| {run['run']} | about {PAPER_MILD_SSIM_DROP} | {run['paper_mild_mean_ssim_drop']:.4f} |")
  if len(lines) == 4:
    lines.append(f"| {NOT_RUN} | about {PAPER_MILD_SSIM_DROP} | - |")
  return lines + [""]


def ownership_table(calibration: dict) -> list[str]:
  """The verify job's threshold and the false- and true-positive rates measured at it (bench-robust's
  ownership_calibration.json), with the marked trial closest to failing."""
  lines = ["### Ownership: the verify threshold and its measured rates (no paper number: the paper has no test)",
           "", "| threshold | false positives (clean trials) | true positives (mild and medium attacks) | "
           "lowest marked trial |", "|---|---|---|---|"]
  if not calibration:
    return lines + [f"| {NOT_RUN} | | | |", ""]
  lowest = min(calibration["marked_trials"], key=lambda t: t["score"])
  lines.append(f"| {calibration['threshold']:.3f} | {100 * calibration['false_positive_rate']:.2f}% of "
               f"{calibration['num_clean']} | {100 * calibration['true_positive_rate']:.1f}% of "
               f"{calibration['num_marked']} | {lowest['run']}: {lowest['trial']}, {lowest['score']:.3f} |")
  return lines + [""]


# bit accuracy and render quality the 3D-GS watermarking papers report for their message lengths (their own scenes,
# not ours): GuardSplat 99.04% at 32 bits (render 39.40 dB), 3D-GSW 97.37% at 32 bits (35.08 dB), MarkSplatter
# 94.41% at 48 bits
MESSAGE_PAPERS = {32: "GuardSplat 99.04% (39.40 dB); 3D-GSW 97.37% (35.08 dB)", 48: "MarkSplatter 94.41%"}


def message_rows(ownership_bench: dict) -> list[tuple[str, int, dict]]:
  """(scene, bits, row) of bench-ownership's message mode ({scene: {bits: row}}), by scene and length."""
  return sorted((scene, int(bits), row) for scene, by_bits in (ownership_bench.get("message") or {}).items()
                for bits, row in by_bits.items())


def ownership_test_table(ownership_bench: dict) -> list[str]:
  """verify's decision as a statistical test (bench-ownership's ownership_bench.json): false positives measured over
  the clean trials at alpha beside the rate the null predicts (and with the random-phase model's p-value alone),
  the (decoder, scene) pairs they come from, the true-positive rate per marked run (given the owner's copy, and
  without it where measured), and message mode per length."""
  lines = ["### Ownership as a statistical test: false positives at alpha and true positives under the mild and "
           "medium attacks (the paper and the 3D-GS watermarking papers report no false-positive rate)", "",
           "| alpha | clean trials ((decoder, scene) pairs) | false positives (predicted; model p alone) | marked run "
           "| true positives (verify given the owner's copy; without it) |",
           "|---|---|---|---|---|"]
  if not ownership_bench:
    return lines + [f"| {NOT_RUN} | | | | |", ""]
  alpha, trials = ownership_bench["alpha"], ownership_bench["clean_trials"]
  pairs = ownership_bench.get("independent_pairs", {}).get("decoder_scene_pairs", "-")
  fp = (f"{ownership_bench['false_positives']} ({alpha * trials:.2g}; "
        f"{ownership_bench.get('false_positives_model', '-')})")
  tpr = ownership_bench["tpr_at_alpha"] or {NOT_RUN: None}
  unaligned = ownership_bench.get("tpr_at_alpha_unaligned", {})
  percent = lambda rate: "-" if rate is None else f"{100 * rate:.1f}%"
  for k, (run, rate) in enumerate(tpr.items()):
    head = f"| {alpha:g} | {trials} ({pairs}) | {fp} " if k == 0 else "| | | "
    lines.append(head + f"| {run} | {percent(rate)}; {percent(unaligned.get(run))} |")
  tail = ", ".join(f"<= {row['p_at_most']:g}: {row['observed']} ({row['predicted']:.3g})"
                   for row in ownership_bench.get("tail_counts", [])[2:])
  top = (ownership_bench.get("top_clean_trials") or [None])[0]
  lines += ["", "The clean trials' p-values against the null: [ownership_bench.png](ownership_bench.png); the attacked "
            "students' z: [ownership_tpr.png](ownership_tpr.png)."
            + (f" Clean trials whose decision p-value is at most p, observed (predicted): {tail}." if tail else "")
            + (f" The highest clean z, {top['z']:.2f} (p 1e{top['log10_p']:.2f}): decoder {top['decoder']} on "
               f"{top['scene']}, {top['view']}, hidden image '{top['hidden']}'." if top else ""), "",
            "Message mode (BCH-coded bits laid out as the hidden image; raw bit accuracy before correction, render "
            "PSNR of the student on the test views beside the teacher's; runs: "
            + (", ".join(row["run"] for _, _, row in message_rows(ownership_bench)) or "none")
            + "; the papers' figures are on their own scenes):", "",
            "| scene | bits | code | raw bit accuracy | message after correction | exact under the mild and medium "
            "attacks (lowest raw bit accuracy) | render PSNR (teacher) | clean scene: bit accuracy, decided "
            "| papers |",
            "|---|---|---|---|---|---|---|---|---|"]
  messages = message_rows(ownership_bench)
  if not messages:
    lines.append(f"| {NOT_RUN} | | | | | | | | |")
  for scene, bits, row in messages:
    clean = row.get("verify_clean")
    clean_text = (f"{100 * clean['bit_accuracy']:.1f}%, {'owned' if clean['owned'] else 'not owned'}" if clean
                  else "-")
    lines.append(f"| {scene} | {bits} | {row['code']} | {100 * row['bit_accuracy']:.2f}% | "
                 f"{'exact' if row['message_exact'] else 'wrong'} ({row['errors_corrected']} corrected) | "
                 f"{row.get('attacked_exact', '-')} ({100 * row.get('attacked_min_bit_accuracy', float('nan')):.1f}%)"
                 f" | {row['render_psnr']:.2f} ({row['teacher_psnr']:.2f}) | {clean_text} | "
                 f"{MESSAGE_PAPERS.get(bits, '-')} |")
  return lines + [""]


SURVIVAL_STEPS = (30, 100, 300, 1000, 3000, 10000)


def survival_table(survive_bench: dict) -> list[str]:
  """The paper's research question 3 (is the mark retained after re-training?), which it leaves open: hidden SSIM
  at the key after fine-tuning on the training views for each number of steps (bench-survive: the 3D-GS recipe
  without and with densification, and gentle rates), per scene and recipe, with the decision (*: owned, by
  verify's test given the owner's copy, or by the calibrated threshold in rows measured before it), the untouched
  scene's SSIM and what the recipe cost the render, per scene and recipe how many attacked rows verify decided
  owned (bench_survive.true_positive_lines), and each attack's readings of the recommended recipe's two marks
  (bench_survive.two_mark_lines)."""
  rows = survive_bench.get("rows", [])
  lines = ["### Research question 3: is the mark retained after re-training? (hidden SSIM at the key after "
           "fine-tuning on the training views; * owned: by verify at alpha given the owner's copy, by the calibrated "
           "SSIM threshold in rows measured before it; the paper asks and reports none)", "",
           "| scene | recipe | render loss (dB) | attack | untouched | "
           + " | ".join(f"{n} steps" for n in SURVIVAL_STEPS) + " |",
           "|---|---|---|---|---|" + "---|" * len(SURVIVAL_STEPS)]
  cell = lambda r: f"{r['hidden_ssim']:.3f}{'*' if bench_survive.owned(r) else ''}" if r else "-"
  groups = sorted({(r["scene"], r["recipe"]) for r in rows})
  for scene, recipe in groups:
    mine = [r for r in rows if (r["scene"], r["recipe"]) == (scene, recipe)]
    untouched = next((r for r in mine if r["attack"] == "none"), None)
    for attack in bench_survive.FINETUNE_SCHEDULES:
      by_steps = {r["level"]: r for r in mine if r["attack"] == attack}
      if by_steps:
        loss = (untouched or {}).get("render_loss_db")
        loss = "-" if loss is None else f"{loss:.2f}"
        lines.append(f"| {scene} | {recipe} | {loss} | {attack} | {cell(untouched)} | "
                     + " | ".join(cell(by_steps.get(n)) for n in SURVIVAL_STEPS) + " |")
  if not groups:
    lines.append(f"| {NOT_RUN} | | | | |" + " |" * len(SURVIVAL_STEPS))
  tested = bench_survive.true_positive_lines(rows)
  verified = " Verify's decision at alpha over each scene's attacks, given the owner's copy:" if tested else ""
  return lines + ["", "Every attack of a shared scene (transforms, publishing round trips) is in "
                  "[survive_bench.md](survive_bench.md)." + verified, "", *tested, *bench_survive.two_mark_lines(rows)]


def extraction_table(survive_bench: dict) -> list[str]:
  """Model extraction (bench-survive --extraction): hidden SSIM at the key of a fresh 3D-GS trained on `views`
  renders of the marked scene, per scene, recipe, poses and views, at each length of its training (*: owned by
  verify given the owner's copy)."""
  rows = survive_bench.get("rows", [])
  curves = bench_survive.extraction_curves(rows)
  nearest = {bench_survive.extraction_key(r): r["key_nearest_deg"] for r in rows
             if r["attack"].startswith("extraction") and r.get("key_nearest_deg") is not None}
  lengths = sorted({steps for points in curves.values() for steps, _, _ in points})
  lines = ["### Model extraction: is the mark in a copy trained on the scene's renders? (hidden SSIM at the key of a "
           "fresh 3D-GS trained from random points on renders of the marked scene: its training cameras, then poses "
           "on their orbit or over the sphere, or (unseen) orbit poses only; * owned by verify given the owner's "
           "copy; nearest: how far from the key the closest rendered view stands, degrees of a turn about what the "
           "key looks at, - where not recorded)", "",
           "| scene | recipe | poses | views | nearest | " + " | ".join(f"{n} steps" for n in lengths) + " |",
           "|---|---|---|---|---|" + "---|" * len(lengths)]
  for key, points in curves.items():
    scene, recipe, poses, views = key
    by_steps = {steps: f"{ssim:.3f}{'*' if owned else ''}" for steps, ssim, owned in points}
    near = f"{nearest[key]:.1f}" if key in nearest else "-"
    lines.append(f"| {scene} | {recipe} | {poses} | {views} | {near} | "
                 + " | ".join(by_steps.get(n, "-") for n in lengths) + " |")
  return lines + ([] if curves else [f"| {NOT_RUN} | | | | |"]) + [""]


def full_resolution_section(full_bench: dict) -> list[str]:
  """bench-full's rows: lego at the full size of the shared copy with the unmodified 3D-GS recipe, on the
  accelerator each row names."""
  lines = ["### Full resolution: lego at 400x400 with the 3D-GS recipe (bench-full; the paper trains at 1/4)", ""]
  rows = full_bench.get("rows", [])
  return lines + ([bench_full.table(rows)] if rows else [NOT_RUN, ""])


def appendix_conceal_table(conceal_bench: dict) -> list[str]:
  """Every bench-conceal run, recipes and retired rows included, with what the row is."""
  lines = [f"### {APPENDIX} A: every bench-conceal run", "",
           "What each row is, what it measured and why it was tried: [conceal_bench_rows.md](conceal_bench_rows.md). "
           "`retired`: a row that used an option the redesign removed; its stored numbers stay.", "",
           "| scene | row | kind | width | steps | student PSNR / SSIM / LPIPS | hidden PSNR / SSIM | "
           "leakage: test views / clean teacher / near key | floor | wall time (min) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
  for r in conceal_bench.get("rows", []):
    floor = r.get("leakage_floor", {}).get("max_ssim_teacher_test_views")  # rows scored before it was kept lack it
    lines.append(f"| {r.get('scene', 'lego')} | {r['row']} | {row_kind(r['row'])} | {r['decoder_width']} | "
                 f"{results_io.conceal_steps(r)} | {cells(conceal_values(r))} | "
                 f"{results_io.leakage_cells(r['leakage'])} | {'-' if floor is None else f'{floor:.3f}'} | "
                 f"{r['wall_time_s'] / 60:.1f}{results_io.on_device(r)} |")
  if len(lines) == 6:
    lines.append(f"| {NOT_RUN} | | | | | | | | | |")
  return lines + [""]


def appendix_baseline_table(baseline_bench: dict) -> list[str]:
  """Every bench-baselines run, one line each."""
  lines = [f"### {APPENDIX} B: every baseline run", "",
           "| scene | method | row | PSNR / SSIM / LPIPS | hidden PSNR / SSIM | leakage: test views / clean teacher "
           "/ near key | run |", "|---|---|---|---|---|---|---|"]
  for r in baseline_bench.get("rows", []):
    lines.append(f"| {r.get('scene', 'lego')} | {r.get('method', '')} | {r.get('row', '')} | "
                 f"{cells(conceal_values(r))} | {results_io.leakage_cells(r['leakage'])} | {r.get('protocol', '')} |")
  if len(lines) == 4:
    lines.append(f"| {NOT_RUN} | | | | | | | |")
  return lines + [""]


def figure_panels(scene: str, conceal_bench: dict, baseline_bench: dict, results: pathlib.Path,
                  workdir: pathlib.Path) -> list[tuple[str, list[tuple[str, str]]]]:
  """The figure's rows as (label, [(title, image file)]): per run of a recipe on `scene` (`recipe_runs`) with
  images, hidden | revealed: student at the key | clean teacher at the key | student's most revealing test view;
  then one row 'baselines' with the revealed image of each baseline run at RECIPE_STEPS, once. The images are
  those the benches kept under `results` (or, for older rows, their runs under `workdir`)."""
  panels = []
  for name, runs in recipe_runs(conceal_bench, scene).items():
    for r in runs:
      run = workdir / scene / f"conceal_{r['row']}_w{r['decoder_width']}"
      own = results_io.row_images(results, r, run, results_io.CONCEAL_IMAGES)
      if own:
        panels.append((f"{name}: {r['row']} w{r['decoder_width']}", own))
  seed = lambda b: tradeoff.recipe(b.get("row", ""))[1]
  baselines = [(b.get("label", b["method"]) + (f", seed {seed(b)}" if seed(b) else ""), path)
               for b in baseline_bench.get("rows", [])
               if b.get("scene", "lego") == scene and b.get("iterations", RECIPE_STEPS) == RECIPE_STEPS
               for _, path in results_io.row_images(results, b, workdir / scene / f"baseline_{b.get('row', '')}",
                                                    results_io.BASELINE_IMAGES)]
  return panels + ([("baselines", baselines)] if baselines else [])


def figure_grid(scene: str, conceal_bench: dict, baseline_bench: dict, results: pathlib.Path,
                workdir: pathlib.Path) -> str | None:
  """Draws `figure_panels` as a grid, one panel per row, to reproduction_<scene>.png in `results`; its name, or
  None if there is nothing to show."""
  import imageio.v3 as iio
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  panels = figure_panels(scene, conceal_bench, baseline_bench, results, workdir)
  if not panels:
    return None
  columns = max(len(files) for _, files in panels)
  fig, axes = plt.subplots(len(panels), columns, figsize=(2.2 * columns, 2.4 * len(panels)), squeeze=False)
  for i, (label, files) in enumerate(panels):
    for j in range(columns):
      ax = axes[i][j]
      ax.axis("off")
      if j < len(files):
        ax.imshow(iio.imread(files[j][1]))
        ax.set_title(files[j][0] if j else f"{label}\n{files[j][0]}", fontsize=8)
  name = f"reproduction_{scene}.png"
  fileio.save_figure(fig, results / name)
  plt.close(fig)
  return name


INTRO = [
    "Written by `make reproduce` from the benchmarks' JSON. Paper numbers are the paper's averages over four scenes",
    "per dataset; ours are one scene each (lego 200x200 for NeRF-Synthetic, the real capture beer at 1/4 for the",
    "real-scene table) on the teachers of `make bench-train`. Render quality is the student's test PSNR / SSIM /",
    "LPIPS-VGG against ground truth; hidden is the image revealed at the key.",
    "",
    "ConcealGS appears as the four recipes of `conceal_jax/configs/recipes.py`: **recommended** (ours: the mark in a",
    "carrier film that only the key sees, which re-training cannot reach), **in_scene** (ours: the mark in the",
    "teacher's Gaussians as the paper keeps it, with leakage control, a gentle student, training through attacks and",
    "a steadier decoder), **paper** (as written) and **released** (the authors' code). Each is bench-conceal's row",
    f"that runs the recipe unchanged, with a width-{RECIPE_WIDTH} decoder trained from scratch (what a CPU affords;",
    "the paper's width 64 appears in the appendix), shown as the mean over the seeds it was run from, with the range",
    "(lowest-highest) of the PSNRs where there are two or more; the `seeds` count says how many. Baselines alike, at",
    "the recipes' length.",
    f"Every other experiment, retired rows included, is in the {APPENDIX.lower()}.",
    "",
]


def report(results: pathlib.Path, workdir: pathlib.Path) -> str:
  train_bench, conceal_bench = load(results, "train_bench.json"), load(results, "conceal_bench.json")
  baseline_bench, robust_bench = load(results, "baseline_bench.json"), load(results, "robust_bench.json")
  lines = ["# Reproduction of ConcealGS (arXiv:2501.03605) on this machine", ""] + INTRO
  lines += method_table("Table 1: NeRF-Synthetic (ours: lego)", PAPER_TABLE1, "lego", train_bench, conceal_bench,
                        baseline_bench)
  lines += method_table("Table 2: real scenes (paper: T&T/DB; ours: beer)", PAPER_TABLE2, "beer", train_bench,
                        conceal_bench, baseline_bench)
  lines += full_resolution_section(load(results, "full_bench.json"))
  lines += ablation_table(conceal_bench) + leakage_table(conceal_bench)
  recipe_means = recipe_points("lego", conceal_bench, baseline_bench)
  lines += tradeoff.recipe_table("lego", recipe_means)
  plot = tradeoff.figure("lego", recipe_means, results)
  lines += [f"![The recipes beside StegaNeRF, lego]({plot})", ""] if plot else []
  lines += robustness_table(robust_bench)
  lines += ownership_table(load(results, "ownership_calibration.json"))
  lines += ownership_test_table(load(results, "ownership_bench.json"))
  lines += survival_table(load(results, "survive_bench.json"))
  lines += extraction_table(load(results, "survive_bench.json"))
  lines += ["### Figures", ""]
  for scene in ("lego", "beer"):
    name = figure_grid(scene, conceal_bench, baseline_bench, results, workdir)
    lines += [f"![{scene}]({name})" if name else f"{scene}: {NOT_RUN}", ""]
  lines += [f"## {APPENDIX}: every other experiment", ""]
  lines += appendix_conceal_table(conceal_bench) + appendix_baseline_table(baseline_bench)
  every_run = tradeoff_points("lego", conceal_bench, baseline_bench)
  lines += tradeoff.table("lego", every_run, title=f"{APPENDIX} C: every run beside StegaNeRF (lego)")
  lines += tradeoff.seed_table("lego", every_run, title=f"{APPENDIX} D: rows run from several seeds (lego)")
  return "\n".join(lines).rstrip("\n") + "\n"


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--results", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/bench")
  args = parser.parse_args()
  results = pathlib.Path(args.results)
  text = report(results, pathlib.Path(args.workdir))
  fileio.write_text(results / "REPRODUCTION.md", text)
  print(text)


if __name__ == "__main__":
  main()
