"""REPRODUCTION.md: the paper's numbers beside ours, read from the benchmarks' JSON; missing rows say so; one row
per recipe over its seeds in the tables, every other run in the appendix."""
import json
import shutil

import numpy as np

from conceal_jax.core import fileio
from experiments import reproduce, results_io, tradeoff


def _conceal_row(row, width, psnr, hidden_psnr):
  scores = lambda p: dict(psnr=p, ssim=0.97, lpips=0.03)
  return dict(scene="lego", row=row, decoder_width=width, iterations=10_000, student_vs_ground_truth=scores(psnr),
              teacher_vs_ground_truth=scores(33.1), student_vs_teacher=scores(40.0),
              hidden=dict(psnr=hidden_psnr, ssim=0.995), curve=[], student_psnr_loss=33.1 - psnr, max_leakage=0.13,
              wall_time_s=3000.0,
              leakage=dict(max_ssim_student_test_views=0.11, ssim_teacher_check_view=0.12, max_ssim_near_check=0.13))


def test_report_puts_ours_beside_the_paper_and_names_missing_rows(tmp_path):
  results, workdir = tmp_path / "results", tmp_path / "bench"
  fileio.write_json(results / "train_bench.json", dict(rows=[dict(scene="lego", test=dict(psnr=33.11, ssim=0.983,
                                                                                          lpips=0.0188))]))
  fileio.write_json(results / "conceal_bench.json", dict(rows=[_conceal_row("full", 16, 32.95, 35.25),
                                                               _conceal_row("no_guidance", 16, 32.5, 34.0)]))
  run = workdir / "lego" / "conceal_full_w16"
  for name in ("hidden.png", "revealed.png", "teacher_revealed.png", "normal_revealed.png"):
    fileio.write_image(str(run / name), np.full((8, 8, 3), 0.5, np.float32))

  text = reproduce.report(results, workdir)
  table1 = text[text.index("Table 1"):text.index("Table 2")]
  assert "| 3D-GS | 34.45 / 0.9732 / 0.0220 | - / - | 33.11 / 0.9830 / 0.0188 |" in table1
  # one ConcealGS row per recipe, in RECIPE_ORDER, the paper's cells on the first; `full` runs the paper recipe
  assert "| ConcealGS | 33.14 / 0.9717 / 0.0240 | 33.98 / 0.9942 | - | - | recommended: not run yet |" in table1
  assert ("| ConcealGS | |  | 32.95 / 0.9700 / 0.0300 | 35.25 / 0.9950 | paper (full), width 16, 10000 steps, "
          "1 seed (0) |") in table1
  assert "| ConcealGS | |  | - | - | released: not run yet |" in table1
  for method in reproduce.BASELINES:
    assert f"| {method} | " in table1 and f"| - | - | {reproduce.NOT_RUN} |" in table1
  assert table1.count(reproduce.NOT_RUN) == 7  # the three baselines, four recipes (the fifth, paper, ran)
  table3 = text[text.index("Table 3"):text.index("Leakage")]
  assert "| no_guidance | 26.93 / 0.9043 / 0.0812 | 37.43 / 0.9912 | 32.50 / 0.9700 / 0.0300 | 34.00 / 0.9950 | " \
      "16, 10000, 1 seed (0) |" in table3
  assert "| no_decoder | 26.25 / 0.8965 / 0.0884 | 37.56 / 0.9948 | - | - | not run yet |" in table3
  leakage = text[text.index("### Leakage"):text.index("### The recipes")]
  assert "| lego | paper (full) | 1 seed (0) | 0.110 | 0.120 | 0.130 | - |" in leakage
  assert "| lego | no_guidance | 1 seed (0) | 0.110 | 0.120 | 0.130 | - |" in leakage
  appendix = text[text.index("## Appendix"):]
  assert ("| lego | full | recipe: paper | 16 | 10000 | 32.95 / 0.9700 / 0.0300 | 35.25 / 0.9950 | 0.110 / 0.120 / "
          "0.130 | - | 50.0 |") in appendix
  assert "| lego | no_guidance | paper ablation | 16 |" in appendix
  assert "![lego](reproduction_lego.png)" in text and "beer: not run yet" in text
  assert (results / "reproduction_lego.png").is_file()
  ownership = text[text.index("### Ownership"):text.index("### Figures")]
  assert reproduce.NOT_RUN in ownership
  marked = [dict(run="a", trial="blur 0.5", score=0.97), dict(run="b", trial="brightness -0.1", score=0.35)]
  fileio.write_json(results / "ownership_calibration.json", dict(
      threshold=0.1818, false_positive_rate=9 / 938, num_clean=938, true_positive_rate=1.0, num_marked=2,
      marked_trials=marked))
  text = reproduce.report(results, workdir)
  assert "| 0.182 | 0.96% of 938 | 100.0% of 2 | b: brightness -0.1, 0.350 |" in text


def test_rows_run_on_an_accelerator_say_so_and_leakage_shows_its_floor(tmp_path):
  results = tmp_path / "results"
  gpu = ["gpu: NVIDIA H100 80GB HBM3"]
  floor = dict(leakage_floor=dict(max_ssim_teacher_test_views=0.101, ssim_teacher_at_worst_test_view=0.1))
  wide = dict(_conceal_row("full", 64, 32.9, 45.1), step_devices=gpu, **floor)
  recommended = dict(_conceal_row("recommended", 16, 33.0, 40.0), step_devices=gpu, **floor)
  rows = [wide, recommended, _conceal_row("leakage_control", 16, 32.9, 40.0)]
  fileio.write_json(results / "conceal_bench.json", dict(rows=rows))
  fileio.write_json(results / "train_bench.json", dict(rows=[dict(scene="lego", test=dict(psnr=33.1, ssim=0.98,
                                                                                          lpips=0.02),
                                                                  step_devices=["cpu: cpu"])]))
  text = reproduce.report(results, tmp_path / "bench")
  body, appendix = text[:text.index("## Appendix")], text[text.index("## Appendix"):]
  assert ("recommended, width 16, 10000 steps, 1 seed (0) (NVIDIA H100 80GB HBM3) |"
          in body)
  assert "teacher (bench-train) |" in body
  # a recipe's run at another decoder width, and a row that is no recipe, are in the appendix only
  assert "paper: not run yet" in body and "| lego | leakage_control |" not in body and "| paper (full)" not in body
  assert "| lego | recommended | 1 seed (0) | 0.110 | 0.120 | 0.130 | 0.101 |" in body
  assert ("| lego | full | recipe: paper | 64 | 10000 | 32.90 / 0.9700 / 0.0300 | 45.10 / 0.9950 | 0.110 / 0.120 / "
          "0.130 | 0.101 | 50.0 (NVIDIA H100 80GB HBM3) |") in appendix
  assert "| lego | leakage_control | experiment | 16 |" in appendix
  assert results_io.on_device(dict(step_devices=["gpu: elsewhere", "cpu: cpu"])) == " (elsewhere)"


def test_figure_reads_the_images_kept_beside_the_json_when_the_workdir_is_gone(tmp_path):
  results, workdir = tmp_path / "results", tmp_path / "bench"
  run = workdir / "lego" / "conceal_full_w16"
  for i, name in enumerate(results_io.CONCEAL_IMAGES.values()):
    fileio.write_image(str(run / name), np.full((8, 8, 3), 0.1 * i, np.float32))
  images = results_io.keep_images(results, run, results_io.CONCEAL_IMAGES)
  assert list(images) == list(results_io.CONCEAL_IMAGES)
  assert images["student, key"] == "revealed/lego/conceal_full_w16/revealed.png"
  shutil.rmtree(workdir)
  row = dict(_conceal_row("full", 16, 32.95, 35.25), images=images)
  fileio.write_json(results / "conceal_bench.json", dict(rows=[row]))
  row = json.loads((results / "conceal_bench.json").read_text())["rows"][0]  # the file holds the labels sorted
  kept = results_io.row_images(results, row, run, results_io.CONCEAL_IMAGES)
  assert [label for label, _ in kept] == list(results_io.CONCEAL_IMAGES)  # the figure's column order
  assert results_io.row_images(results, _conceal_row("full", 16, 32.95, 35.25), run, results_io.CONCEAL_IMAGES) == []
  assert "![lego](reproduction_lego.png)" in reproduce.report(results, workdir)
  # a run without images keeps none, and without any, the baselines' images make the figure alone
  no_images = workdir / "lego" / "conceal_leakage_control_w16"
  assert results_io.keep_images(results, no_images, results_io.CONCEAL_IMAGES) == {}
  assert reproduce.figure_grid("lego", dict(rows=[]), dict(rows=[]), results, workdir) is None
  baseline = dict(scene="lego", method="LSB", row="lsb4", label="LSB 4 bits", images=dict(revealed=images["hidden"]))
  assert reproduce.figure_grid("lego", dict(rows=[_conceal_row("full", 16, 32.95, 35.25)]), dict(rows=[baseline]),
                               results, workdir) == "reproduction_lego.png"
  # the recipes' runs only (`tensor` is no recipe), each baseline once in a row of its own below them; a baseline
  # run at another length is left out, another seed's says so
  bench = dict(rows=[row, dict(row, row="tensor")])
  baselines = [baseline, dict(baseline, row="lsb1", label="LSB 1 bit"),
               dict(baseline, row="lsb1_seed1", label="LSB 1 bit"),
               dict(baseline, row="lsb1_12k", iterations=12_000)]
  panels = reproduce.figure_panels("lego", bench, dict(rows=baselines), results, workdir)
  assert [label for label, _ in panels] == ["paper: full w16", "baselines"]
  assert [len(files) for _, files in panels] == [4, 3]
  assert [title for title, _ in panels[-1][1]] == ["LSB 4 bits", "LSB 1 bit", "LSB 1 bit, seed 1"]


def test_report_without_any_benchmark_says_not_run(tmp_path):
  text = reproduce.report(tmp_path, tmp_path)
  assert "ConcealGS" in text and text.count(reproduce.NOT_RUN) >= 10
  assert json.dumps(reproduce.PAPER_TABLE1["ConcealGS"]) == "[33.14, 0.9717, 0.024, 33.98, 0.9942]"


def test_a_rebuilt_row_keeps_its_place_and_new_rows_follow(tmp_path):
  path, key = tmp_path / "bench.json", lambda r: (r["row"],)
  fileio.write_json(path, dict(rows=[dict(row="a", v=1), dict(row="b", v=1), dict(row="c", v=1)]))
  merged = results_io.merged_rows(path, [dict(row="d", v=2), dict(row="b", v=2)], key)
  assert [(r["row"], r["v"]) for r in merged] == [("a", 1), ("b", 2), ("c", 1), ("d", 2)]
  assert results_io.merged_rows(tmp_path / "missing.json", [dict(row="x")], key) == [dict(row="x")]


def _steganerf_row(row, iterations, psnr, hidden_psnr, width=16):
  return dict(_conceal_row(row, width, psnr, hidden_psnr), method="StegaNeRF", iterations=iterations,
              steganerf=dict(settings=dict(decoder_width=width)),
              protocol=f"check_view, {iterations} steps; over the test views 5.00 dB / 0.0200")


def test_concealgs_is_ahead_of_a_steganerf_run_only_at_its_width_and_length_on_render_and_hidden(tmp_path):
  polish = dict(_conceal_row("polish", 16, 33.3, 44.0), decoder_polish_steps=2000)
  conceal_rows = [_conceal_row("joint", 16, 33.2, 42.0), polish, _conceal_row("wide", 64, 33.3, 46.0),
                  dict(_conceal_row("wide", 64, 33.3, 46.0), scene="beer"),
                  _conceal_row("no_guidance", 16, 33.5, 47.0)]  # an ablation: left out
  baseline_rows = [_steganerf_row("stega_10k", 10_000, 32.5, 41.7), _steganerf_row("stega_12k", 12_000, 32.8, 45.3),
                   _steganerf_row("stega_short", 10_000, 33.0, 42.0),
                   dict(_conceal_row("lsb1", 16, 33.0, 5.0), method="LSB")]
  runs = reproduce.tradeoff_points("lego", dict(rows=conceal_rows), dict(rows=baseline_rows))
  by_run = {p["run"]: p for p in runs}
  assert sorted(by_run) == ["joint", "polish", "stega_10k", "stega_12k", "stega_short", "wide"]
  assert (by_run["polish"]["steps"], by_run["polish"]["length"]) == (12_000, "10000 + 2000 polish")
  assert np.isclose(by_run["stega_10k"]["render_loss"], 0.6) and by_run["stega_10k"]["max_leakage"] == 0.13
  assert tradeoff.ahead(by_run["joint"], by_run["stega_10k"])
  assert not tradeoff.ahead(by_run["polish"], by_run["stega_10k"])  # more steps
  assert not tradeoff.ahead(by_run["wide"], by_run["stega_12k"])  # a wider decoder
  assert not tradeoff.ahead(by_run["polish"], by_run["stega_12k"])  # less hidden
  # equal hidden counts, equal render does not
  assert tradeoff.ahead(by_run["joint"], by_run["stega_short"])
  assert not tradeoff.ahead(dict(by_run["joint"], render_psnr=33.0), by_run["stega_short"])
  lines = tradeoff.table("lego", runs)
  assert "| StegaNeRF | stega_10k | 16 | 10000 | 32.50 (-0.60) | 41.70 | 0.130 | joint |" in lines
  assert "| StegaNeRF | stega_12k | 16 | 12000 | 32.80 (-0.30) | 45.30 | 0.130 | none |" in lines
  assert "| ConcealGS | polish | 16 | 10000 + 2000 polish | 33.30 (+0.20) | 44.00 | 0.130 |  |" in lines
  assert tradeoff.table("lego", [])[-2] == "| not run yet | | | | | | | |"
  assert tradeoff.figure("lego", [], tmp_path) is None

  results = tmp_path / "results"
  fileio.write_json(results / "conceal_bench.json", dict(rows=conceal_rows))
  fileio.write_json(results / "baseline_bench.json", dict(rows=baseline_rows))
  text = reproduce.report(results, tmp_path / "bench")
  # every run beside StegaNeRF in the appendix; the plot shows the recipes (none here) and StegaNeRF's rows
  assert "| StegaNeRF | stega_10k |" in text[text.index("## Appendix"):]
  assert "![The recipes beside StegaNeRF, lego](tradeoff_lego.png)" in text
  assert (results / "tradeoff_lego.png").is_file()


def test_recipes_from_several_seeds_are_compared_on_their_means():
  conceal_rows = [_conceal_row("joint", 16, 33.4, 42.5), _conceal_row("joint_seed1", 16, 33.4, 39.0),
                  _conceal_row("single", 16, 34.0, 50.0), _conceal_row("joint_seed1", 64, 33.0, 45.0)]
  baseline_rows = [_steganerf_row("stega", 10_000, 32.5, 41.7), _steganerf_row("stega_seed1", 10_000, 32.8, 41.0),
                   _steganerf_row("stega_seed1_12k", 12_000, 32.8, 45.3)]
  runs = reproduce.tradeoff_points("lego", dict(rows=conceal_rows), dict(rows=baseline_rows))
  assert tradeoff.recipe("stega_seed1_12k") == ("stega_12k", 1) and tradeoff.recipe("joint") == ("joint", 0)
  # single seeds, another width or length: not a recipe over seeds
  means = {m["run"]: m for m in tradeoff.over_seeds(runs)}
  assert sorted(means) == ["joint", "stega"]
  assert means["joint"]["seeds"] == [0, 1] and np.isclose(means["joint"]["hidden_psnr"], 40.75)
  assert means["joint"]["hidden_range"] == (39.0, 42.5) and np.isclose(means["stega"]["render_psnr"], 32.65)
  # run by run `joint` (seed 0) is ahead of both StegaNeRF seeds; on the means it is not
  by_run = {p["run"]: p for p in runs}
  assert tradeoff.ahead(by_run["joint"], by_run["stega"]) and tradeoff.ahead(by_run["joint"], by_run["stega_seed1"])
  assert not tradeoff.ahead(means["joint"], means["stega"])
  lines = tradeoff.seed_table("lego", runs)
  assert "| StegaNeRF | stega | 16 | 10000 | 0, 1 | 32.65 (-0.45) | 41.35 (41.00-41.70) | 0.130 | none |" in lines
  assert "| ConcealGS | joint | 16 | 10000 | 0, 1 | 33.40 (+0.30) | 40.75 (39.00-42.50) | 0.130 |  |" in lines
  assert tradeoff.seed_table("lego", runs[:1])[-2] == "| no recipe run from two seeds yet | | | | | | | | |"


def test_each_recipe_is_one_row_over_its_seeds_and_every_other_run_is_in_the_appendix(tmp_path):
  assert reproduce.recipe_of_row() == {"full": ("paper", 0), "released": ("released", 0),
                                       "released_seed1": ("released", 1),
                                       "in_scene": ("in_scene", 0), "recommended": ("recommended", 0),
                                       "recommended_at_decoder_size": ("recommended_at_decoder_size", 0)}
  conceal_rows = [_conceal_row("released", 16, 33.4, 42.5), _conceal_row("released_seed1", 16, 33.3, 39.0),
                  _conceal_row("recommended", 16, 33.0, 40.4),
                  _conceal_row("released_plus_weight2", 16, 33.3, 42.9),
                  _conceal_row("in_scene_no_update_clip_decoder_amsgrad", 16, 32.9, 37.1)]  # retired: not in ROWS
  baseline_rows = [_steganerf_row("steganerf_check_view", 10_000, 32.5, 41.7),
                   _steganerf_row("steganerf_check_view_seed1", 10_000, 32.8, 41.0),
                   _steganerf_row("steganerf_check_view_12k", 12_000, 32.8, 45.3)]
  results = tmp_path / "results"
  fileio.write_json(results / "conceal_bench.json", dict(rows=conceal_rows))
  fileio.write_json(results / "baseline_bench.json", dict(rows=baseline_rows))
  text = reproduce.report(results, tmp_path / "bench")
  body, appendix = text[:text.index("## Appendix")], text[text.index("## Appendix"):]
  table1 = body[body.index("Table 1"):body.index("Table 2")]
  assert ("| ConcealGS | 33.14 / 0.9717 / 0.0240 | 33.98 / 0.9942 | 33.00 / 0.9700 / 0.0300 | 40.40 / 0.9950 | "
          "recommended, width 16, 10000 steps, 1 seed (0) |") in table1
  assert ("| ConcealGS | |  | 33.35 (33.30-33.40) / 0.9700 / 0.0300 | 40.75 (39.00-42.50) / 0.9950 | "
          "released (released, released_seed1), width 16, 10000 steps, 2 seeds (0, 1) |") in table1
  assert ("| StegaNeRF | 30.33 / 0.9381 / 0.0787 | 24.60 / 0.9026 | 32.65 (32.50-32.80) / 0.9700 / 0.0300 | "
          "41.35 (41.00-41.70) / 0.9950 | check_view, 10000 steps, 2 seeds (0, 1) |") in table1
  for other in ("released_plus_weight2", "in_scene_no_update_clip_decoder_amsgrad", "steganerf_check_view_12k"):
    assert other not in body and f"| {other} |" in appendix
  assert "| lego | released_plus_weight2 | experiment | 16 |" in appendix
  assert "| lego | in_scene_no_update_clip_decoder_amsgrad | retired | 16 |" in appendix
  leakage = body[body.index("### Leakage"):]
  assert ("| lego | released (released, released_seed1) | 2 seeds (0, 1) | 0.110 (0.110-0.110) | 0.120 (0.120-0.120) "
          "| 0.130 (0.130-0.130) | - |") in leakage
  # the recipes beside StegaNeRF, on their means; the figure's points are those means
  means = {m["run"]: m for m in reproduce.recipe_points("lego", dict(rows=conceal_rows), dict(rows=baseline_rows))}
  assert sorted(means) == ["recommended", "released", "steganerf_check_view"]
  assert means["released"]["seeds"] == [0, 1]
  assert ("| ConcealGS | recommended | 16 | 10000 | 0 | 33.00 (-0.10) | 40.40 | 0.130 "
          "|  |") in body
  assert ("| StegaNeRF | steganerf_check_view | 16 | 10000 | 0, 1 | 32.65 (-0.45) | 41.35 (41.00-41.70) | 0.130 "
          "| none |") in body
  assert "| ConcealGS | released | 16 | 10000 | 0, 1 | 33.35 (+0.25) | 40.75 (39.00-42.50) | 0.130 |  |" in appendix


def test_the_ownership_test_table_counts_pairs_and_shows_message_mode():
  row = lambda run, accuracy: dict(run=run, code="BCH(125, 48), shortened from BCH(127, 50)", bit_accuracy=accuracy,
                                   message_exact=True, errors_corrected=1, render_psnr=30.1, teacher_psnr=30.5,
                                   attacked_exact="30 of 32", attacked_min_bit_accuracy=0.52,
                                   verify_clean=dict(bit_accuracy=0.48, owned=False))
  bench = dict(alpha=1e-6, clean_trials=190620, false_positives=1, false_positives_model=12,
               independent_pairs=dict(decoder_scene_pairs=15), tpr_at_alpha={"workdirs/demo/conceal": 1.0},
               tpr_at_alpha_unaligned={"workdirs/demo/conceal": 0.96875},
               message={"lego": {"48": row("w/lego_48", 1.0)}, "demo": {"48": row("w/demo_48", 0.992)}})
  text = "\n".join(reproduce.ownership_test_table(bench))
  assert "| 1e-06 | 190620 (15) | 1 (0.19; 12) | workdirs/demo/conceal | 100.0%; 96.9% |" in text
  assert ("| demo | 48 | BCH(125, 48), shortened from BCH(127, 50) | 99.20% | exact (1 corrected) | 30 of 32 (52.0%) | "
          "30.10 (30.50) | 48.0%, not owned | MarkSplatter 94.41% |") in text
  assert text.index("| demo | 48 |") < text.index("| lego | 48 | BCH(125, 48), shortened from BCH(127, 50) | 100.00%")
  assert "runs: w/demo_48, w/lego_48;" in text
  assert reproduce.NOT_RUN in "\n".join(reproduce.ownership_test_table(dict(bench, message={})))


def test_result_files_hold_one_row_per_line_and_merge_rebuilt_rows_in_place(tmp_path):
  key = lambda row: (row["scene"], row["level"])
  plot = lambda rows, path: path.write_text("plot")
  table = lambda rows: "\n".join(f"{r['scene']} {r['level']} {r['ssim']}" for r in rows)
  first = [dict(scene="demo", level=1.0, ssim=0.9, registration=dict(rotation=np.eye(3, dtype=np.float32))),
           dict(scene="demo", level=5.0, ssim=0.3)]
  results_io.write_results(tmp_path, "bench", first, key, table, plot, note="header")
  text = (tmp_path / "bench.json").read_text()
  data = json.loads(text)
  assert data["note"] == "header" and data["rows"][0]["registration"]["rotation"][1] == [0.0, 1.0, 0.0]
  rows = [line for line in text.splitlines() if line.startswith('    {"')]
  assert len(rows) == 2 and json.loads(rows[1].rstrip(",")) == first[1]
  merged = results_io.write_results(tmp_path, "bench", [dict(scene="lego", level=1.0, ssim=0.8),
                                                        dict(scene="demo", level=5.0, ssim=0.4)], key, table, plot)
  assert [(r["scene"], r["level"], r["ssim"]) for r in merged] == [("demo", 1.0, 0.9), ("demo", 5.0, 0.4),
                                                                    ("lego", 1.0, 0.8)]
  assert json.loads((tmp_path / "bench.json").read_text())["rows"] == merged
  assert (tmp_path / "bench.md").read_text() == "demo 1.0 0.9\ndemo 5.0 0.4\nlego 1.0 0.8"
  assert json.loads(results_io.results_json(dict(device="cpu"), [])) == dict(device="cpu", rows=[])
