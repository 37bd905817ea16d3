"""Does the mark survive what happens to a shared scene (issue 39)? Similarity transforms, publishing round trips,
fine-tuning and model extraction of marked students, each scored as the owner would: render PSNR of the attacked
scene on the test views, hidden PSNR / SSIM at the key, and the ownership decision.

  make bench-survive                                   # demo and lego (when its bench run exists), cheap attacks
  make bench-survive BENCH_ARGS="--scenes=demo --finetune-steps=30,100,300"
  make bench-survive BENCH_ARGS="--extraction --extraction-views=200 --extraction-steps=10000"

Scenes are finished conceal workdirs (student.ply, decoder.msgpack, key.json, config.json); one that is missing
is skipped with a note; `label=workdir+layered_workdir` reads workdir's mark from the student of layered_workdir, a
conceal run on workdir's student (two marks in one shared scene, each scored by its own rows). Attacks (`level` in
brackets):
- none: the student as shared;
- rotate (degrees about the up axis through the centroid), translate (fraction of the RMS radius), scale
  (factor), each with the Gaussians shuffled (robust.scene_attacks): hidden_* are revealed after re-alignment
  against the owner's copy (align.realign: registration, key moved with the similarity found),
  `unaligned` without it; `registration` reports the transform found and its error against the applied one;
- sog, spz, compressed_ply (the format), decimate (fraction kept), sh_bands (bands kept), floaters (floater
  filtering at the converter's defaults): round trips through @playcanvas/splat-transform (robust.converter;
  skipped without `make node_modules`, floaters without a WebGPU adapter: `make webgpu-cpu`), revealed as they
  come back (hidden_*) and after re-alignment (`aligned`); `moved`: the same round trip of the student moved by a
  random similarity first (any rotation, translation up to 10 radii, scale in [1/10, 10]), revealed after
  re-alignment;
- decimate_scaled (factor): the student resized by the factor about its centroid (Gaussians shuffled), then
  decimated to 50% by the converter, revealed after re-alignment: the converter's merges are not scale-free
  (conceal/grouping.py), so this is how a decimation survives at every size someone may give the scene;
- finetune, finetune_densify, finetune_gentle (steps): 3D-GS training continued from the student on the training
  views with the run's own training recipe, without and with densification, and at gentle rates without it
  (gentle_rates); snapshots of one run per schedule;
- extraction, extraction_sphere, extraction_unseen (views; `steps` in the row), with --extraction only: renders of
  the student at its training cameras and random poses on their orbit (or, --extraction-poses=sphere, poses spread
  over the whole sphere around it; unseen: random orbit poses only, none of the training cameras), a fresh 3D-GS
  trained on them from random points; `key_nearest_deg` how close to the key's pose the rendered views come.

`owned` and `log10_p` are verify's decision given the owner's copy (robust.ownership: the suspect re-aligned in
frame and tone, read after each tone map and as rendered, at --alpha; hidden_* of the strongest reading, as
verify reports it: ownership.strongest), `verify` each reading's figures; `decided` the
calibrated threshold's (hidden SSIM at or above the threshold chosen from --calibration, which `make bench-robust`
writes). Rows are merged into <out>/survive_bench.json ({"rows": [...]}, one per scene,
recipe, attack, level and steps) with survive_bench.md and survive_bench.png; finished rows are kept and not
recomputed (--redo recomputes them), and each attack's files are cached under --workdir/<scene>/ (a run given by
path: --workdir/<the folder of the run whose student is attacked>/, which both marks of one scene share).
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import pathlib

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from conceal_jax.conceal import align, key as key_lib, tolerance
from conceal_jax.configs import default, recipes
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import evaluate, similarity as sim, train
from conceal_jax.robust import converter, ownership, robustness, scene_attacks
from conceal_jax.splat.camera import opengl_camera_to_world
from conceal_jax.splat.render import RenderOptions
from experiments import bench_robust, results_io

NAME = "survive_bench"
# label -> (scene, conceal workdir, recipe): the demo's in_scene run is configs/demo.py's short in_scene recipe
# (make demo), lego's bench-conceal's in_scene row; the survival designs' runs are `make survive-runs`'
# (configs/demo.py's variants, lego_conceal.py:recommended)
SCENES = {"demo": ("demo", "workdirs/demo/conceal", "in_scene"),
          "demo_film": ("demo", "workdirs/survive_runs/demo_film", "film"),
          "demo_film_pub": ("demo", "workdirs/survive_runs/demo_film_pub", "film_pub"),
          "demo_film_web": ("demo", "workdirs/survive_runs/demo_film_web", "film_web"),
          "demo_film_watch": ("demo", "workdirs/survive_runs/demo_film_watch", "film_watch"),
          "demo_film_watch768_2600": ("demo", "workdirs/survive_runs/demo_film_watch768_2600", "film_watch768_2600"),
          "demo_film_long": ("demo", "workdirs/survive_runs/demo_film_long", "film_long"),
          "demo_film_deep": ("demo", "workdirs/survive_runs/demo_film_deep", "film_deep"),
          "demo_film_stack": ("demo", "workdirs/survive_runs/demo_film_stack", "film_stack"),
          "demo_film_faint": ("demo", "workdirs/survive_runs/demo_film_faint", "film_faint"),
          "demo_film_reset": ("demo", "workdirs/survive_runs/demo_film_reset", "film_reset"),
          "demo_film_far": ("demo", "workdirs/survive_runs/demo_film_far", "film_far"),
          "demo_drift": ("demo", "workdirs/survive_runs/demo_drift", "drift"),
          "demo_orbit": ("demo", "workdirs/survive_runs/demo_orbit", "orbit"),
          "demo_recommended_6k": ("demo", "workdirs/survive_runs/demo_recommended", "recommended_6k"),
          "demo_recommended": ("demo", "workdirs/survive_runs/demo_axes_polished_mf50_10k", "recommended"),
          "demo_thick": ("demo", "workdirs/survive_runs/demo_thick_mf20", "thick_mf20_6k"),
          "demo_thick_mf35": ("demo", "workdirs/survive_runs/demo_thick_mf35", "thick_mf35_6k"),
          "demo_thick_k50": ("demo", "workdirs/survive_runs/demo_thick_k50", "thick_k50_6k"),
          "demo_thick_10k": ("demo", "workdirs/survive_runs/demo_thick_mf20_10k", "thick_mf20_10k"),
          "lego": ("lego", "workdirs/bench/lego/conceal_in_scene_w16", "in_scene"),
          "lego_converter_wm25": ("lego", "workdirs/survive_runs/lego_converter_mf35_rot5_scales_wm25",
                                  "converter_mf35_rot5_scales_wm25"),
          "lego_thick": ("lego", "workdirs/survive_runs/lego_thick_mf20_wm25", "thick_mf20_wm25"),
          "lego_recommended": ("lego", "workdirs/bench/lego/conceal_recommended_w16", "recommended"),
          "lego_decoder_size": ("lego", "workdirs/bench/lego/conceal_recommended_decoder_size_w16", "decoder_size"),
          "lego_decoder_size_near": ("lego", "workdirs/bench/lego/conceal_recommended_decoder_size_near_w16",
                                     "decoder_size_near"),
          "lego_decoder_size_more_decoys": ("lego",
                                            "workdirs/bench/lego/conceal_recommended_decoder_size_more_decoys_w16",
                                            "decoder_size_more_decoys"),
          "lego_decoder_size_sparse": ("lego", "workdirs/bench/lego/conceal_recommended_decoder_size_sparse_w16",
                                       "decoder_size_sparse"),
          "lego_film": ("lego", "workdirs/survive_runs/lego_film", "film"),
          "lego_film_reset": ("lego", "workdirs/survive_runs/lego_film_reset", "film_reset")}
# Scene labels beyond the scenes' own names: runs given by path (label=workdir[@recipe][+layered_workdir]).
SCENE_NOTES = {
    "demo_in_scene": "make demo's in_scene student as concealed 2026-11-29 (workdirs/demo/conceal); the demo rows of "
                     "in_scene are an earlier make demo's",
    "demo_layered_film": "one demo scene carrying two marks: survive-runs' demo_thick_mf20 (thick_mf20_6k, concealed "
                         "2026-11-29), then demo.py's in_scene recipe concealed on its student "
                         "(workdirs/survive_runs/demo_thick_mf20_in_scene); the film's mark, read from that scene",
    "demo_layered_in_scene": "the same scene (demo_layered_film's); the in_scene mark, read at its own key with its "
                             "own decoder",
    "demo_layered_pruned": "demo_layered_in_scene with demo.py:pruned as the second mark "
                           "(workdirs/survive_runs/demo_thick_mf20_pruned): its key watched closely",
    "demo_layered_pruned_film": "demo_layered_pruned's scene; the film's mark, read from it",
    "lego_layered_in_scene": "lego's recommended student (bench-conceal's, "
                             "workdirs/bench/lego/conceal_recommended_w16) with lego_conceal.py:in_scene concealed on "
                             "it as a second mark (workdirs/survive_runs/lego_recommended_in_scene, 2026-11-29): the "
                             "in_scene mark, read at its own key with its own decoder",
    "lego_layered_film": "lego_layered_in_scene's scene; the film's mark, read from it",
    "lego_layered_close": "lego_layered_in_scene with lego_conceal.py:in_scene_close as the second mark "
                          "(workdirs/survive_runs/lego_recommended_in_scene_close, 2026-11-30)",
    "lego_layered_close_decoder": "lego_layered_in_scene with lego_conceal.py:in_scene_close_decoder as the second "
                                  "mark (workdirs/survive_runs/lego_recommended_in_scene_close_decoder, 2026-11-30)",
    "lego_layered_axes": "lego_layered_in_scene with lego_conceal.py:in_scene_axes as the second mark "
                         "(workdirs/survive_runs/lego_recommended_in_scene_axes, 2026-11-30)",
    "demo_layered_axes": "demo_layered_in_scene with demo.py:axes as the second mark "
                         "(workdirs/survive_runs/demo_thick_mf20_axial_strong_kd4, 2026-11-30)",
    "demo_layered_axes_kd16": "demo_layered_in_scene with demo.py:axes and conceal.weight_kd 16 as the second mark "
                              "(workdirs/survive_runs/demo_thick_mf20_axes_kd16, 2026-11-30)",
    "demo_layered_axes_kd16_film": "demo_layered_axes_kd16's scene; the film's mark, read from it",
    "lego_layered_tolerant": "lego_layered_in_scene with lego_conceal.py:in_scene_tolerant as the second mark "
                             "(workdirs/survive_runs/lego_recommended_in_scene_tolerant, 2026-11-30)",
    "demo_layered_tolerant": "demo_layered_in_scene with demo.py:tolerant as the second mark "
                             "(workdirs/survive_runs/demo_thick_mf20_tolerant, 2026-11-30)",
    "lego_layered_layer": "lego's recommended student with lego_conceal.py:in_scene_layer concealed on it as the "
                          "second mark (workdirs/survive_runs/lego_recommended_in_scene_layer, 2026-11-30): the "
                          "recommended film and layer; the layer's mark, read at its own key with its own decoder",
    "lego_layered_layer_film": "lego_layered_layer's scene; the film's mark, read from it",
    "demo_layered_layer": "the demo's recommended student (conceal.py, 10000 steps, concealed again 2026-11-30 "
                          "after make demo's teacher was trained again: workdirs/survive_runs/demo_thick_mf20_10k, "
                          "hidden 37.09 dB / 0.980) with conceal.py:in_scene_layer concealed on it as the second mark "
                          "(workdirs/survive_runs/demo_thick_mf20_10k_layer, 2026-11-30): the recommended film and "
                          "layer; the layer's mark, read at its own key with its own decoder",
    "demo_layered_layer_film": "demo_layered_layer's scene; the film's mark, read from it",
    "demo_axes_polish4k": "demo_axes_polished's run polished 2000 steps more (its last checkpoint continued with "
                          "--config.conceal.decoder_opt.polish_steps=4000, workdirs/trials/demo_polish4k, 2026-12-01)",
    "demo_axes_polish_mf80": "demo_axes_unpolished's run (step 10000) polished with the check renders merged on 80% "
                             "of the polish's steps (workdirs/trials/demo_polish_mf08, 2026-12-01)",
    "demo_axes_unpolished": "demo_recommended's command without the polish (conceal.py with "
                            "--config.conceal.decoder_opt.polish_steps=0, workdirs/survive_runs/demo_axes_10k, "
                            "2026-12-01): which part of the adopted recipe costs decimation"}
TRANSFORMS = ([("rotate", d) for d in (1.0, 5.0, 45.0, 180.0)] + [("translate", f) for f in (0.026, 1.0)]
              + [("scale", f) for f in (0.5, 1.1, 2.0)])
# attack, level -> converter.round_trip's arguments
CONVERSIONS = ([("sog", None, dict(fmt="sog")), ("spz", None, dict(fmt="spz")),
                ("compressed_ply", None, dict(fmt="compressed.ply"))]
               + [("decimate", k, dict(fmt="ply", decimate=k)) for k in (0.8, 0.5)]
               + [("sh_bands", d, dict(fmt="ply", sh_degree=d)) for d in (2, 1, 0)]
               + [("floaters", None, dict(fmt="ply", floaters=True))])
# the factors the student is resized by before a converter's decimation to SCALED_KEEP (decimate_scaled)
SCALED_FACTORS, SCALED_KEEP = (0.1, 0.15, 0.4, 1.6, 4.0), 0.5
CONVERTER_TIMEOUT_S = 3600  # per converter call: .sog clusters a lego scene for many minutes on a CPU
# What each recipe label of the rows is (the survival designs of issue 39 beside the in_scene recipe).
RECIPE_NOTES = {
    "in_scene_close": "recipes.in_scene_close: in_scene with 768 decoys turned 1-5 degrees on a quarter of the "
                      "steps, L_d^- weighted 2.5",
    "in_scene_close_decoder": "recipes.in_scene_close_decoder: in_scene_close with decoys that hold the decoder to "
                              "the identity but not the student to the teacher (conceal.leakage.decoys_hold_student)",
    "in_scene_axes": "recipes.in_scene_axes: in_scene with recipes.watched_axes: 192 decoys along and about the "
                     "key's own axes that watch the decoder alone, on half the steps, L_d^- weighted 2.5, L_kd 4",
    "axes": "demo.py:axes: the demo's in_scene recipe with recipes.watched_axes, 2600 steps",
    "axes_kd16": "demo.py:axes with L_kd weighted 16 (--config.conceal.weight_kd=16)",
    "in_scene_tolerant": "recipes.in_scene_tolerant: in_scene with a key tolerance radius of 10 degrees "
                         "(recipes.tolerant_key), its decoys beyond it",
    "tolerant": "demo.py:tolerant: the demo's in_scene recipe with recipes.tolerant_key",
    "in_scene": "the mark in the teacher's Gaussians, refined (recipes.in_scene; configs/demo.py; bench-conceal's "
                "in_scene lego row)",
    "recommended": "recipes.recommended: the carrier film with its key watched along and about its own axes and "
                   "its decoder polished alone 2000 steps, half of them on decimated copies of the film "
                   "(configs/conceal.py's default; the label of a run given by path); demo: make survive-runs' "
                   "demo_recommended (workdirs/survive_runs/demo_axes_polished_mf50_10k, conceal.py with "
                   "data.path=demo, 10000 steps); lego: bench-conceal's recommended row "
                   "(lego_conceal.py:recommended, workdirs/bench/lego/conceal_recommended_w16)",
    "axes_unpolished": "recipes.recommended without its decoder polish (decoys along and about the key's axes only)",
    "axes_polished": "recipes.recommended as adopted on 2026-12-01 before its polish read decimated copies more "
                     "often: the polish's check renders merged on a fifth of its steps, as the joint steps' "
                     "(conceal.decoder_opt.polish_merge_fraction unset; demo: workdirs/survive_runs/"
                     "demo_axes_polished_10k)",
    "axes_polish4k": "axes_polished with a polish of 4000 steps (--config.conceal.decoder_opt.polish_steps=4000)",
    "axes_polish_mf80": "recipes.recommended with the polish reading decimated copies on 80% of its steps "
                        "(--config.conceal.decoder_opt.polish_merge_fraction=0.8)",
    "recommended_random_decoys": "recipes.recommended until 2026-12-01: its decoys turned and moved in random "
                                 "directions about the key, the decoder not polished (bench-conceal's "
                                 "recommended_random_decoys; lego: lego_conceal.py:recommended, thick_mf20_wm25's "
                                 "settings, concealed 2026-11-29, the film of the lego_layered_layer scenes)",
    "recommended_6k": "recipes.recommended as it was before 2026-11-28 (bench-conceal's recommended_pairs) on the "
                      "demo for 6000 steps (bench-survive's demo_recommended_6k: conceal.py with data.path=demo; its "
                      "film grid every 4 pixels, where conceal.carrier.spacing 0 places it at 128 pixels), fine-tuned "
                      "with its config's training recipe, 3D-GS's defaults",
    "thick_mf20_6k": "recipes.recommended (since 2026-11-28 evening: the thick film through the converter's own "
                     "groups, thick_mf20_wm25's settings) on the demo for 6000 steps (make survive-runs' "
                     "demo_thick_mf20, concealed again 2026-11-29 on the current renderer: hidden 35.64 dB / 0.986)",
    "thick_mf35_6k": "thick_mf20_6k with 35% of the check renders merged in the converter's groups rather than 20% "
                     "(conceal.attacks.merge_fraction 0.35; workdirs/survive_runs/demo_thick_mf35, 2026-11-29)",
    "thick_mf20_10k": "thick_mf20_6k at the recipe's full 10000 steps (workdirs/survive_runs/demo_thick_mf20_10k; "
                      "scene demo: concealed 2026-11-29, hidden 38.92 dB / 0.992; demo_layered_layer_film: the same "
                      "command on 2026-11-30, see its scene note)",
    "in_scene_layer": "recipes.in_scene_layer (the Makefile's LAYER): in_scene_axes as the second mark of a "
                      "film-marked scene, in its own Gaussians, read from the owner's renders, L_kd weighted 32, its "
                      "decoder guarded; concealed on the recommended student (mark.teacher: its student.ply)",
    "thick_k50_6k": "thick_mf20_6k with every merging check render the converter's decimation to 50% (conceal.attacks."
                    "merge_keep (0.5,), not also 80%: twice the steps at each size of the 50% decimation; "
                    "workdirs/survive_runs/demo_thick_k50, 2026-11-29)",
    "thick_mf20_6k_1128": "thick_mf20_6k's first run (concealed 2026-11-28, its student since gone: hidden 33.41 dB / "
                          "0.974)",
    "film": "the faint carrier film (demo.py:film; the film recipe before it became film_watch's): the key looks "
            "where no camera looks, one camera distance out from their orbit target, and the film 0.1 camera distances "
            "before it, 22 grids of splats at opacity 0.01 (the opacity reset's ceiling); its base colours trained at "
            "rate 1e-2 through 8-bit colours a quarter of the steps, the decoder reading standardized renders, 64 "
            "decoys within 1-10 degrees of the key",
    "film_pub": "film trained through decimation too: a quarter of the check renders with a share ~ U[0, 1] of the "
                "film's neighbouring pairs merged as splat-transform's decimation merges them, and the 8-bit grids "
                "rounding at a point drawn per render (demo.py:film_pub)",
    "film_pub_grid": "film_pub with the film at opacity 2.001/255, a value every format's 8-bit opacity stores "
                     "unchanged (rounded or floored) and below the opacity reset's ceiling (demo.py:film_pub with "
                     "--config.conceal.carrier.opacity=0.0078471)",
    "film_web": "film_pub at the opacity 2.001/255 with the film's base colours held within .spz's range, |SH DC| "
                "<= 0.5 / 0.15 (recipes.publishable_film; demo.py:film_web)",
    "film_watch": "film_web with the key watched closely: 192 decoys, one the normal view on 90% of the steps, L_d^- "
                  "weighted 1.5 (recipes.watched_key at 192 decoys; demo.py:film_watch)",
    "film_watch768_2600": "film_watch with 768 decoys, concealed for 2600 steps (demo.py:film_watch with "
                          "--config.conceal.leakage.decoy_views=768 --config.conceal.iterations=2600)",
    "film_long": "recommended_pairs' design on the demo: film_watch with 768 decoys for 2600 steps, the check "
                 "render's 8-bit grids including .compressed.ply's of the higher SH bands (demo.py:film_long)",
    "film_long_epyc": "film_long concealed again (the same config and seed) on another 2-core CPU (AMD EPYC), where "
                      "the demo teacher, the same code and seed, trains to 30.85 dB rather than 30.53: a second "
                      "sample of the design (workdirs/survive_runs/demo_film_long, concealed 2026-11-26)",
    "film_epyc": "lego_conceal.py:recommended as it was before 2026-11-28 (recommended_pairs) concealed again for "
                 "10000 steps on the 2-core CPU (AMD EPYC), resumed from its checkpoint at 5000 "
                 "(workdirs/survive_runs/lego_film, 2026-11-27)",
    "converter_3k": "recommended_pairs with the check renders merged as the converter's own decimation "
                    "to 50% or 80% merges the film (conceal.attacks.merge_groups=converter: its groups reproduced "
                    "from the student every 500 steps, conceal/grouping.py), for 3000 steps (a design test; "
                    "workdirs/survive_runs/lego_converter_3k, 2026-11-28)",
    "converter_mf50": "recommended_pairs with the converter's own groups (as converter_3k) merged in half "
                      "the check renders (conceal.attacks.merge_fraction=0.5), for the recipe's 10000 steps "
                      "(workdirs/survive_runs/lego_converter_mf50, 2026-11-28)",
    "converter_mf50_rot5": "converter_mf50 with its decoys turned 1-5 degrees rather than 1-10 (conceal.leakage."
                           "decoy_rotation_deg), to hold the decoder to the identity at the 2-degree turns where "
                           "converter_mf50 leaked (workdirs/survive_runs/lego_converter_mf50_rot5)",
    "converter_mf35_rot5": "converter_mf50_rot5 with the converter's groups merged in 35% of the check renders "
                           "(conceal.attacks.merge_fraction=0.35): the near-key reading against decimation "
                           "(workdirs/survive_runs/lego_converter_mf35_rot5)",
    "converter_mf35_rot5_scales": "converter_mf35_rot5 with the converter's groups computed on copies of the student "
                                  "scaled by 0.1, 0.25, 0.6, 1 and 2.5 (conceal.attacks.merge_scales), regrouped "
                                  "every 1000 steps: a decimation of the scene at another size "
                                  "(workdirs/survive_runs/lego_converter_mf35_rot5_scales)",
    "converter_mf35_rot5_scales_wm25": "converter_mf35_rot5_scales with L_d^- weighted 2.5 rather than the watched "
                                       "key's 1.5 (conceal.weight_minus): the near-key reading at 2-degree turns; "
                                       "lego_conceal.py:recommended on 2026-11-28 afternoon, bench-conceal's "
                                       "recommended_flat (workdirs/survive_runs/lego_converter_mf35_rot5_scales_wm25)",
    "thick_wm25": "lego_conceal.py:recommended (converter_mf35_rot5_scales_wm25) with the film's splats as thick along "
                  "the key's axis as across it (conceal.carrier.thickness=1.0), so that the converter groups the "
                  "film alike at every size of the scene (workdirs/survive_runs/lego_thick_wm25)",
    "thick_mf20_wm25": "thick_wm25 with 20% of the check renders merged rather than 35% "
                       "(conceal.attacks.merge_fraction=0.2): the untouched reading against the merged ones; "
                       "lego_conceal.py:recommended since 2026-11-28 evening, bench-conceal's recommended "
                       "(workdirs/survive_runs/lego_thick_mf20_wm25)",
    "decoder_size": "thick_mf20_wm25 with the key and its decoys cameras of the decoder's input size, 64x64 "
                    "(conceal.carrier.at_decoder_size): bench-conceal's recommended_decoder_size "
                    "(workdirs/bench/lego/conceal_recommended_decoder_size_w16)",
    "decoder_size_near": "decoder_size with its decoys moved 0.5-6% of the key's depth rather than 1-10%: "
                         "bench-conceal's recommended_decoder_size_near "
                         "(workdirs/bench/lego/conceal_recommended_decoder_size_near_w16)",
    "decoder_size_more_decoys": "decoder_size_near with twice the decoys, 1536: bench-conceal's "
                                "recommended_decoder_size_more_decoys "
                                "(workdirs/bench/lego/conceal_recommended_decoder_size_more_decoys_w16: its rerun on "
                                "the faster renderer, cpu_speed.md)",
    "decoder_size_sparse": "decoder_size with a ninth of the film: a grid position every 18.75 pixels of the "
                           "200-pixel key (every 6 of the 64-pixel one) rather than every 6, its splats three times "
                           "as wide: bench-conceal's recommended_decoder_size_sparse "
                           "(workdirs/bench/lego/conceal_recommended_decoder_size_sparse_w16)",
    "nearest_3k": "recommended_pairs (merges of near pairs) for 3000 steps beside converter_3k "
                  "(workdirs/survive_runs/lego_nearest_3k, 2026-11-28)",
    "film_deep": "film_long trained through merges up to 1.5 rounds deep (recipes.DEEP_MERGE_DEPTH; demo.py:film_deep)",
    "film_stack": "film_long with the film's splats in stacks of two at each grid position, their colours trained as "
                  "one at half the rate, and half as many grids (recipes.stacked_film; demo.py:film_stack)",
    "film_faint": "film with its colours at the gentle student's rate, 6.25e-4 (demo.py:film_faint; concealed on an "
                  "H200, attacked on the CPU)",
    "film_reset": "the first film: one grid of splats at opacity 0.5, trained through 8-bit colours and opacity "
                  "resets a quarter of the steps each, a plain decoder reading standardized renders, decoys within "
                  "1-10 degrees (demo.py:film_reset; lego: cut to 1000 steps)",
    "film_faint_keyed": "film_faint with the decoder reading 4 fixed sign channels beside the render and decoys within "
                        "0.5-4 degrees (demo.py:film_faint_keyed at commit 38b0f42; retired: it raised leakage)",
    "film_keyed": "film_reset with the sign channels and near decoys (demo.py:film_keyed at commit 38b0f42; retired)",
    "film_far": "film_reset with the key half a camera distance out and the film as far again (demo.py:film_far)",
    "film_far_sh": "film_far with the film's SH bands above DC trained too (demo.py:film at commit faa029a; retired: "
                   "the mark went into those bands, which publishing formats drop or coarsen)",
    "drift": "in_scene, the check render drawn from students noised by up to 0.15 of each field's spread "
             "(demo.py:drift)",
    "orbit": "in_scene with the key a secret pose on the training orbit (demo.py:orbit)",
    "pruned": "in_scene trained through size pruning with the key watched closely (768 decoys, one the normal view "
              "on 90% of the steps, L_d^- weighted 1.5), for 2600 steps (demo.py:pruned)",
}
# The second figure: fine-tuning curves and the survival-against-render-loss frontier at this many steps.
CURVES_FIGURE, FRONTIER_STEPS = "survive_curves.png", 1000
EXTRACTION_POSES = ("orbit", "sphere", "unseen")  # extraction_cameras
CHEAP_ATTACKS = ("none", "transforms", "converter", "finetune", "finetune_densify")
# the random similarity that moves the student before a round trip (scene_attacks.random_similarity)
MOVED_MAX_SCALE, MOVED_SEED = 10.0, 7


def row_key(row: dict) -> tuple:
  return row["scene"], row["recipe"], row["attack"], json.dumps(row["level"]), row.get("steps")


@dataclasses.dataclass
class Scene:
  """A marked scene under test: its name and recipe label, conceal workdir, run config, student (numpy), owner
  (robustness.Owner), test cameras, images and render options, the decision's calibration, its cache folder, and
  how many Gaussians of the student are a carrier film (the last ones; conceal.carrier), the key's near_length, and
  the longest a converter call may take."""
  name: str
  recipe: str
  run: pathlib.Path  # the conceal workdir whose student is under test (load_scene's `layered` when given)
  config: ml_collections.ConfigDict
  student: object
  owner: robustness.Owner
  cameras: list
  targets: list
  view_options: RenderOptions  # the test views' (evaluate.eval_options), not the key's
  calibration: dict
  cache: pathlib.Path
  alpha: float
  null_views: int
  carrier: int = 0
  key_length: float | None = None  # the key's near_length (key.json; None in runs from before it was recorded)

  converter_timeout_s: float = CONVERTER_TIMEOUT_S

  def row(self, attack: str, level, scores: dict, test: dict, **extra) -> dict:
    """A result row: scores holds render_psnr, hidden_psnr and hidden_ssim; owned, log10_p and `verify` (each
    reading's figures) from `test`, verify's decision given the owner's copy (aligned); decided from hidden_ssim
    by the calibrated threshold."""
    test = dict(test)
    return dict(scene=self.name, recipe=self.recipe, attack=attack, level=level, **scores,
                owned=test.pop("owned"), log10_p=test.pop("log10_p"), verify=test,
                decided=ownership.decide(scores["hidden_ssim"], self.calibration), **extra)


def load_scene(name: str, run: pathlib.Path, recipe: str, test_views: int, calibration: dict,
               cache: pathlib.Path, alpha: float, null_views: int, layered: pathlib.Path | None = None) -> Scene:
  """The conceal run in `run` under test, its attacked scenes cached in `cache` (claimed for this run: ValueError if
  another run's attacks are there). `layered`: a conceal run that hid a second mark in run's student (its
  mark.teacher); run's mark is then read from layered's student, the scene shared."""
  student_run = run if layered is None else layered_on(run, layered)
  claim_cache(cache, student_run)
  config, _, owner = bench_robust.load_run(run)
  student = ply.load_ply(str(student_run / "student.ply"))
  data = evaluate.load_scene_data(config)
  cameras, targets, _ = evaluate.held_out_views(data, test_views)
  summary = json.loads((run / "conceal.json").read_text()) if (run / "conceal.json").is_file() else {}
  key_length = key_lib.load_key(str(run / "key.json"))[1].get("near_length")
  return Scene(name, recipe, student_run, config, jax.tree.map(np.asarray, student), owner, cameras, targets,
               evaluate.eval_options(config, data.background), calibration, cache, alpha, null_views,
               int(summary.get("num_carrier", 0)), key_length)


def layered_on(run: pathlib.Path, layered: pathlib.Path) -> pathlib.Path:
  """`layered`, checked to be a conceal run whose teacher (config mark.teacher) is run's student: ValueError naming
  both otherwise, so that a mark is never read from a scene that does not carry it."""
  teacher = json.loads((layered / "config.json").read_text())["mark"]["teacher"]
  if pathlib.Path(teacher).resolve() != (run / "student.ply").resolve():
    raise ValueError(f"{layered} was not concealed on {run / 'student.ply'} (its mark.teacher is {teacher})")
  return layered


def render_loss(run: pathlib.Path) -> float | None:
  """What the recipe cost the render: the teacher's test PSNR minus the student's, as the conceal job scored them
  (its metrics.json; None without)."""
  try:
    metrics = json.loads((run / "metrics.json").read_text())
    return metrics["teacher_vs_ground_truth"]["psnr"] - metrics["student_vs_ground_truth"]["psnr"]
  except (OSError, ValueError, KeyError):
    return None


def scores_of(scene: Scene, gaussians, similarity: sim.Similarity | None = None) -> dict:
  """render_psnr on the test views (cameras moved by `similarity`, the one applied to the scene, if given) with the
  scene's evaluation options (every SH band it has: a film's key reads it at degree 0), and hidden PSNR / SSIM at
  the key as saved (no re-alignment)."""
  g = jax.tree.map(jnp.asarray, gaussians)
  cameras, options = scene.cameras, scene.view_options
  if similarity is not None:
    moved = [align.moved_key(c, options, similarity) for c in cameras]
    cameras, options = [c for c, _ in moved], moved[0][1]
  return dict(render_psnr=evaluate.views_psnr(g, list(cameras), scene.targets, options),
              **scene.owner.check_scores(g), num_gaussians=int(np.asarray(gaussians.means).shape[0]))


def drop_compilations() -> None:
  """Frees the compiled programs of the scene just scored: each attacked scene has its own Gaussian count, and a
  process that keeps every size's CPU code runs out of memory mappings (vm.max_map_count) long before RAM."""
  jax.clear_caches()


def registration_errors(found: dict, applied: sim.Similarity, radius: float) -> dict:
  """The registration's error against the applied similarity: rotation (degrees), scale (relative),
  translation (owner radii, after the scale)."""
  rotation = np.asarray(found["rotation"]) @ applied.rotation.T
  angle = math.degrees(math.acos(float(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))
  return dict(rotation_error_deg=angle, scale_error=abs(found["scale"] / applied.scale - 1.0),
              translation_error=float(np.linalg.norm(np.asarray(found["translation"]) - applied.translation)
                                      / (radius * applied.scale)))


def aligned(scene: Scene, suspect, applied: sim.Similarity | None = None) -> dict:
  """hidden_psnr, hidden_ssim (of the strongest reading, ownership.strongest, named `reading`), decided,
  registration (with its errors against the applied similarity, identity if None) and `test` (verify's decision
  given the owner's copy) of `suspect` revealed after re-alignment."""
  scores = scene.owner.aligned_scores(scene.student, suspect, scene.alpha, scene.null_views)
  registration = scores["registration"]
  registration.update(registration_errors(registration, applied or sim.Similarity.identity(),
                                          registration["owner_radius"]))
  return dict(hidden_psnr=scores["hidden_psnr"], hidden_ssim=scores["hidden_ssim"], hidden_z=scores["hidden_z"],
              reading=scores["reading"], decided=ownership.decide(scores["hidden_ssim"], scene.calibration),
              registration=registration, test=scores["test"])


CACHE_SOURCE = "source.json"


def claim_cache(cache: pathlib.Path, run: pathlib.Path) -> None:
  """Records in `cache` which run's student its attacked scenes come from (the student's path, size and
  modification time); ValueError naming both when it holds another's, so that a cache never mixes two runs."""
  student = run / "student.ply"
  stat = student.stat()
  source = dict(student=str(student.resolve()), size=stat.st_size, mtime_ns=stat.st_mtime_ns)
  path = cache / CACHE_SOURCE
  if path.is_file():
    held = json.loads(path.read_text())
    if held != source:
      differ = ", ".join(k for k in sorted(source) if held.get(k) != source[k])
      raise ValueError(f"{cache} holds the attacks of {held['student']} (size {held['size']}), not of {student} "
                       f"(differing: {differ}): give this run another label, or remove the folder")
    return
  if cache.is_dir() and any(cache.iterdir()):  # attacks cached before the source was recorded
    print(f"note: {cache} has no {CACHE_SOURCE}; its cached attacks are taken to be {student}'s")
  cache.mkdir(parents=True, exist_ok=True)
  fileio.write_json(path, source)


def cached_ply(path: pathlib.Path, make):
  """The scene saved at `path`, made by make() and saved there first if missing (numpy arrays)."""
  if not path.is_file():
    path.parent.mkdir(parents=True, exist_ok=True)
    ply.save_ply(path, jax.tree.map(np.asarray, make()))
  return jax.tree.map(np.asarray, ply.load_ply(str(path)))


def realigned_row(scene: Scene, attack: str, level, suspect, applied: sim.Similarity, plain: dict, **extra) -> dict:
  """The row of `suspect` (the student moved by `applied`, then perhaps converted) revealed after re-alignment:
  `plain` (its scores_of) with the re-aligned hidden_*, verify's decision and the registration (`aligned`)."""
  realigned = aligned(scene, suspect, applied)
  registration, test = realigned.pop("registration"), realigned.pop("test")
  realigned.pop("decided")
  return scene.row(attack, level, dict(plain, **realigned), test, **extra, registration=registration)


def transform_rows(scene: Scene, todo) -> list[dict]:
  rows = []
  for attack, level in todo:
    moved, applied = scene_attacks.attack(jax.tree.map(jnp.asarray, scene.student), attack, level)
    moved = cached_ply(scene.cache / f"{attack}_{level:g}" / "scene.ply", lambda: moved)
    plain = scores_of(scene, moved, applied)
    unaligned = {name: plain.pop(name) for name in ("hidden_psnr", "hidden_ssim", "hidden_z")}
    unaligned["decided"] = ownership.decide(unaligned["hidden_ssim"], scene.calibration)
    rows.append(realigned_row(scene, attack, level, moved, applied, plain, unaligned=unaligned))
    print(json.dumps({k: v for k, v in rows[-1].items() if not isinstance(v, dict)}), flush=True)
  return rows


def converter_rows(scene: Scene, todo) -> list[dict]:
  """The round trips of `todo`; one the converter fails or times out on is skipped with a note (a later run
  tries it again), the others still run."""
  rows = []
  applied = scene_attacks.random_similarity(scene.student, MOVED_MAX_SCALE, MOVED_SEED)
  moved_student = None
  for attack, level, arguments in todo:
    folder = scene.cache / f"{attack}_{level}"
    if moved_student is None:
      moved_student, _ = scene_attacks.attack(jax.tree.map(jnp.asarray, scene.student), "similarity",
                                              MOVED_MAX_SCALE, seed=MOVED_SEED)
    try:
      published = cached_ply(folder / "scene.ply", lambda: converter.round_trip(
          scene.student, workdir=folder / "work", timeout_s=scene.converter_timeout_s, **arguments))
      moved = cached_ply(folder / "moved.ply", lambda: converter.round_trip(
          moved_student, workdir=folder / "moved_work", timeout_s=scene.converter_timeout_s, **arguments))
    except converter.ConverterError as e:
      print(f"skipping {attack} {level} of {scene.name} ({scene.recipe}): {e}", flush=True)
      continue
    padded = robustness.pad_like(published, max(scene.student.num, published.num), scene.student.sh_degree)
    scores = scores_of(scene, padded)
    scores["num_gaussians"] = int(published.num)
    realigned = aligned(scene, published)
    rows.append(scene.row(attack, level, scores, realigned.pop("test"), aligned=realigned,
                          moved=dict(aligned(scene, moved, applied), similarity=align.similarity_report(applied))))
    print(json.dumps({k: v for k, v in rows[-1].items() if not isinstance(v, dict)}), flush=True)
    drop_compilations()
  return rows


def scaled_decimation_rows(scene: Scene, factors) -> list[dict]:
  """decimate_scaled rows: the student resized by each of `factors` (scene_attacks' `scale`), decimated to
  SCALED_KEEP by the converter, scored re-aligned (hidden_*; `registration` against the resize); a factor the
  converter fails on is skipped with a note."""
  rows = []
  for factor in factors:
    folder = scene.cache / f"decimate_scaled_{factor:g}"
    resized, applied = scene_attacks.attack(jax.tree.map(jnp.asarray, scene.student), "scale", factor)
    try:
      published = cached_ply(folder / "scene.ply", lambda: converter.round_trip(
          resized, decimate=SCALED_KEEP, workdir=folder / "work", timeout_s=scene.converter_timeout_s))
    except converter.ConverterError as e:
      print(f"skipping decimate_scaled {factor:g} of {scene.name} ({scene.recipe}): {e}", flush=True)
      continue
    plain = scores_of(scene, robustness.pad_like(published, max(scene.student.num, published.num),
                                                 scene.student.sh_degree), applied)
    plain["num_gaussians"] = int(published.num)
    rows.append(realigned_row(scene, "decimate_scaled", factor, published, applied, plain))
    print(json.dumps({k: v for k, v in rows[-1].items() if not isinstance(v, dict)}), flush=True)
    drop_compilations()
  return rows


FINETUNE_SCHEDULES = ("finetune", "finetune_densify", "finetune_gentle")
SCHEDULE_LABELS = dict(finetune="", finetune_densify=" (densify)", finetune_gentle=" (gentle)")


def gentle_rates(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """`config` with the training rates of a gentle fine-tuning: the concealment's student rates made gentle
  (recipes.gentle_student: a warmup over a tenth of the run, a quarter of the 3D-GS rates for all but the
  positions, the positions at the concealment's rate), what an editor who only polishes a scene would use."""
  config.train.lr = recipes.gentle_student(default.get_config()).conceal.lr
  return config


def finetune_rows(scene: Scene, steps: list[int], attack: str, test_views: int) -> list[dict]:
  """3D-GS training continued from the student on the training views with the run's training recipe (attack
  finetune), with densification (finetune_densify), or at gentle_rates without it (finetune_gentle), scored at each
  of `steps` (snapshots of one run of max(steps), resumable in <cache>/<attack>_<max(steps)>; the first two in
  finetune_{fixed,densify}_<max(steps)>)."""
  densify = attack == "finetune_densify"
  config = ml_collections.ConfigDict(scene.config.to_dict())
  config.mode = "train"
  config.init.kind, config.init.ply = "ply", str(scene.run / "student.ply")
  config.train.sh_degree_start = config.train.sh_degree  # the student is trained: every band from the start
  if not densify:
    config.train.densify.until = 0  # no densification and no opacity reset
  if attack == "finetune_gentle":
    config = gentle_rates(config)
  folder = {"finetune": "finetune_fixed", "finetune_densify": "finetune_densify"}.get(attack, attack)
  workdir = scene.cache / f"{folder}_{max(steps)}"
  return [scene.row(attack, length, scores, test) for length, scores, test in snapshot_scores(scene, config, workdir,
                                                                                              steps, test_views)]


def snapshot_scores(scene: Scene, config, workdir: pathlib.Path, steps: list[int], test_views: int) -> list:
  """(length, scores, test: verify's decision given the owner's copy) at each of `steps` of one train run of
  `config` for max(steps) in `workdir` (resumable), its snapshots saved at the others."""
  config.train.iterations = max(steps)
  config.train.snapshots = tuple(sorted(set(steps) - {max(steps)}))
  config.train.log_every = math.gcd(int(config.train.log_every), *steps)  # snapshots fall on logged steps
  config.train.eval_every = 0
  config.eval.max_views = test_views
  claim_training(workdir, config)
  train.train_and_evaluate(config, str(workdir))
  out = []
  for length in sorted(steps):
    name = "point_cloud.ply" if length == max(steps) else train.snapshot_name(length)
    tuned = jax.tree.map(np.asarray, ply.load_ply(str(workdir / name)))
    out.append((length, dict(scores_of(scene, tuned), changed=change_profile(scene.student, tuned, scene.carrier)),
                aligned(scene, tuned)["test"]))
    print(json.dumps(dict(step=length, hidden_ssim=out[-1][1].get("hidden_ssim"), owned=out[-1][2]["owned"])),
          flush=True)
    drop_compilations()
  return out


# A config's sections that say how its mark was made, not how a scene trains: marks of one scene share its
# fine-tunings and extractions.
MARK_SECTIONS = ("baseline", "conceal", "mark", "reveal", "verify")


def training_settings(config: dict) -> dict:
  """A config's sections but MARK_SECTIONS, its scene folder (data.path) resolved where it is one."""
  settings = {k: v for k, v in config.items() if k not in MARK_SECTIONS}
  folder = pathlib.Path(settings.get("data", {}).get("path", ""))
  if str(folder) and folder.exists():
    settings["data"] = dict(settings["data"], path=str(folder.resolve()))
  return settings


def claim_training(workdir: pathlib.Path, config) -> None:
  """Writes `config` as the train run's in `workdir`; ValueError naming the differing sections when the run there
  trains otherwise (training_settings differ), so that a cached training never mixes two recipes."""
  path = workdir / "config.json"
  if path.is_file():
    held, ours = training_settings(json.loads(path.read_text())), training_settings(config.to_dict())
    differ = sorted(k for k in set(held) | set(ours) if held.get(k) != ours.get(k))
    if differ:
      raise ValueError(f"{workdir} holds a training with other {', '.join(differ)} settings: remove the folder to "
                       "train it again")
  workdir.mkdir(parents=True, exist_ok=True)
  fileio.write_json(path, config.to_dict())


FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def change_profile(before, after, carrier: int = 0) -> dict | None:
  """What training changed, per field of a scene whose Gaussians it kept in place (None where it added or removed
  some): the fraction of Gaussians whose field moved at all, and the RMS change over the field's spread (the
  standard deviation over the Gaussians, averaged over channels); with a carrier film (its `carrier` Gaussians
  last), `carrier_moved`: the fraction of those that moved in any field."""
  if after.num != before.num:
    return None
  bases = max(before.sh.shape[1], after.sh.shape[1])  # a lower SH degree is the higher one with empty bands

  def rows(g, f):
    x = np.asarray(getattr(g, f), np.float64)
    x = np.pad(x, ((0, 0), (0, bases - x.shape[1]), (0, 0))) if f == "sh" else x
    return x.reshape(before.num, -1)

  moved = {f: np.any(rows(before, f) != rows(after, f), axis=1) for f in FIELDS}
  profile = {f: dict(moved=float(np.mean(moved[f])),
                     relative_rms=float(np.mean(np.sqrt(np.mean((rows(after, f) - rows(before, f)) ** 2, axis=0)))
                                        / max(float(np.mean(rows(before, f).std(axis=0))), 1e-12)))
             for f in FIELDS}
  if carrier:
    profile["carrier_moved"] = float(np.mean(np.any(np.stack([moved[f][-carrier:] for f in FIELDS]), axis=0)))
  return profile


def extraction_cameras(scene: Scene, views: int, poses: str = "orbit", seed: int = 0) -> list:
  """`views` cameras: the scene's training cameras, then `poses`: random poses on their orbit (key.orbit_camera),
  or ("sphere") poses spread evenly over the whole sphere at the orbit's distance (similarity.fibonacci_sphere),
  every one looking at the orbit's target, below the training cameras and where the key lies included; or
  ("unseen") random poses on the orbit only, none of the training cameras: an attacker without the owner's."""
  if poses not in EXTRACTION_POSES:
    raise ValueError(f"unknown extraction poses {poses!r} ({', '.join(EXTRACTION_POSES)})")
  orbit = evaluate.load_scene_data(scene.config).train_cameras
  cameras = [] if poses == "unseen" else list(orbit)[:views]
  extra = views - len(cameras)
  if poses in ("orbit", "unseen"):
    return cameras + [key_lib.orbit_camera(orbit, 10_000 + seed * 100_000 + i) for i in range(extra)]
  target, distance, up = key_lib.orbit_target(orbit), key_lib.camera_distance(orbit), key_lib.orbit_up(orbit)
  return cameras + [key_lib.looking_at(orbit, target + distance * d, target, up)
                    for d in sim.fibonacci_sphere(max(extra, 0))]


def key_nearest_deg(scene: Scene, cameras: list) -> float:
  """How close to the key `cameras` come, in degrees of a turn about the point the key looks at: the least
  tolerance.angle_from_key_deg (at Scene.key_length, else the training orbit's distance); 0 where they include the
  key's pose; a key tolerance radius (conceal.leakage.tolerance_deg) in the same measure."""
  length = scene.key_length or key_lib.camera_distance(evaluate.load_scene_data(scene.config).train_cameras)
  return min(tolerance.angle_from_key_deg(camera, scene.owner.check_camera, length) for camera in cameras)


def write_blender_views(folder: pathlib.Path, gaussians, cameras, test_cameras, options) -> None:
  """The scene rendered at `cameras` (train split) and `test_cameras` (test split) as a Blender-format dataset
  (transforms_{train,test}.json, PNGs): what an extraction attacker trains on. Square pixels, centred
  principal points, one field of view (that of cameras[0])."""
  g = jax.tree.map(jnp.asarray, gaussians)
  for split, split_cameras in (("train", cameras), ("test", test_cameras)):
    frames = []
    for index, camera in enumerate(split_cameras):
      image = np.asarray(evaluate.render_images(g, [camera], options)[0])
      fileio.write_image(folder / split / f"r_{index}.png", np.clip(image, 0.0, 1.0))
      frames.append({"file_path": f"./{split}/r_{index}",
                     "transform_matrix": opengl_camera_to_world(np.asarray(camera.world_to_camera)).tolist()})
    fov_x = 2.0 * math.atan(0.5 * float(cameras[0].width) / float(cameras[0].fx))
    fileio.write_json(folder / f"transforms_{split}.json", {"camera_angle_x": fov_x, "frames": frames})


def extraction_rows(scene: Scene, views: int, steps: list[int], test_views: int, poses: str = "orbit") -> list[dict]:
  """A fresh 3D-GS (random points, the run's training recipe) trained for max(steps) on `views` renders of the
  student at extraction_cameras(poses), scored at each of `steps` (attack extraction, or extraction_<poses>)."""
  suffix = "" if poses == "orbit" else f"_{poses}"
  folder = scene.cache / f"extraction{suffix}_{views}"
  cameras = extraction_cameras(scene, views, poses)
  if not (folder / "views" / "transforms_test.json").is_file():
    write_blender_views(folder / "views", scene.student, cameras, scene.cameras, scene.owner.options)
  config = ml_collections.ConfigDict(scene.config.to_dict())
  config.mode = "train"
  config.data.path = str(folder / "views")
  config.data.downscale = 1
  config.init.kind = "random"
  nearest = key_nearest_deg(scene, cameras)
  return [scene.row(f"extraction{suffix}", views, scores, test, steps=length, key_nearest_deg=nearest)
          for length, scores, test in snapshot_scores(scene, config, folder / f"train_{max(steps)}", steps, test_views)]


def level_label(row: dict) -> str:
  level = row["level"]
  text = "" if level is None else f"{level:g}" if isinstance(level, (int, float)) else str(level)
  return text + (f" x{row['steps']}" if row.get("steps") is not None else "")


def owned(row: dict) -> bool:
  """The row's decision: verify's given the owner's copy, or the calibrated threshold's in rows measured before it."""
  return row["decided"] if row.get("owned") is None else row["owned"]


def owned_cell(row: dict) -> str:
  if row.get("owned") is None:
    return ""
  return f"{'yes' if row['owned'] else 'no'} ({row['log10_p']:.1f})"


def true_positive_lines(rows: list[dict]) -> list[str]:
  """Per scene and recipe, how many of its attacked rows verify decided owned (rows with the decision only)."""
  lines = []
  for name, recipe in dict.fromkeys((r["scene"], r["recipe"]) for r in rows):
    tested = [r for r in rows if (r["scene"], r["recipe"]) == (name, recipe) and r["attack"] != "none"
              and r.get("owned") is not None]
    if tested:
      lines.append(f"- {name} ({recipe}): owned at alpha in {sum(r['owned'] for r in tested)} of {len(tested)} "
                   f"attacked rows")
  return lines + [""] if lines else []


# The scenes that carry the recommended recipe's two marks: the film's label -> the layer's (one attacked scene,
# each mark read by its own rows).
TWO_MARKS = {"lego_layered_layer_film": "lego_layered_layer", "demo_layered_layer_film": "demo_layered_layer"}


def two_mark_lines(rows: list[dict], alpha: float = default.get_config().verify.alpha) -> list[str]:
  """Per scene of TWO_MARKS, each attack's readings of the film's and the layer's mark (hidden SSIM, * owned by that
  mark alone) and the decision on both (ownership.combined_log10_p of the two marks' p-values at `alpha`, as verify
  with verify.marks decides), for the attacks both marks' rows have."""
  lines = []
  for film_label, layer_label in TWO_MARKS.items():
    by_attack = lambda label: {row_key(r)[2:]: r for r in rows if r["scene"] == label and r.get("log10_p") is not None}
    film, layer = by_attack(film_label), by_attack(layer_label)
    both = [k for k in film if k in layer]
    if not both:
      continue
    lines += [f"The recommended recipe's two marks in one scene ({film_label}: the film; {layer_label}: the layer): "
              f"hidden SSIM of each (* owned by that mark alone) and verify's decision on both at alpha {alpha:g}:", "",
              "| attack | level | steps | render PSNR | film | layer | owned (log10 p) |",
              "|---|---|---|---|---|---|---|"]
    for k in both:
      f, l = film[k], layer[k]
      log10_p = float(ownership.combined_log10_p([f["log10_p"], l["log10_p"]]))
      mark = lambda r: f"{r['hidden_ssim']:.3f}{'*' if r['owned'] else ''}"
      lines.append(f"| {k[0]} | {'' if k[1] == 'null' else k[1]} | {k[2] or ''} | {l['render_psnr']:.2f} | "
                   f"{mark(f)} | {mark(l)} | {'yes' if log10_p <= math.log10(alpha) else 'no'} ({log10_p:.1f}) |")
    lines.append("")
  return lines


def note_lines(notes: dict[str, str], field: str, rows: list[dict]) -> list[str]:
  """'- name: note' for each of `notes` that some row's `field` names."""
  return [f"- {name}: {note}" for name, note in notes.items() if any(r[field] == name for r in rows)]


def table(rows: list[dict]) -> str:
  """survive_bench.md: one line per row."""
  lines = ["# Survival of the mark (make bench-survive)", "",
           "Hidden PSNR / SSIM at the key: after re-alignment against the owner's copy for the similarity transforms "
           "(rotate, translate, scale), as the scene comes back for the others. Unaligned: the transforms revealed at "
           "the key as saved; aligned: the round trips re-aligned first; moved: the round trip of the student moved by"
           " a random similarity (scale 1/10-10) first, re-aligned. Registration: its rotation error against the "
           "applied rotation (degrees) and residual (owner radii), for the round trips that of the moved variant, and "
           "(from 2026-11-28 evening) how far the key's refinement on the film turned the registered key "
           "(conceal/key_refine.py). decided: SSIM at or above the threshold chosen from the calibration file "
           "(robust/ownership.py; make bench-robust's, measured on other runs' decoders). Fine-tuning: the run's own "
           "training recipe continued on its training views; finetune_densify densifies from that recipe's "
           "densify.start, so its shorter rows equal finetune's; finetune_gentle: gentle rates (warmup over a tenth of"
           " the run, a quarter of 3D-GS's, the positions at the concealment's). z: the ownership test's statistic of "
           "the revealed image against I (robust/phase_statistic.py; N(0, 1) where the scene does not carry I, 4.75 is"
           " the one-sided 1e-6 level; rows measured before it have none). owned: verify's decision given the owner's "
           "copy (robust/ownership.py: re-aligned in frame and tone, read after each tone map and as rendered, at "
           "alpha --alpha), with its log10 p-value; rows measured before it have none. Re-aligned hidden figures are "
           "the strongest reading's (as verify reports them: smallest p-value, then from 2026-11-27 night largest "
           "SSIM, before largest z; from 2026-11-27 evening: the tone at the key, over the scene's views, or none; "
           "before: the tone at the key). Render PSNR: the attacked scene on --test-views test views at every SH band "
           "it has (rows of a film's recipes measured before 2026-11-30 evening: at the key's degree 0, some 3 dB "
           "lower on lego).", "", "Recipes:", "",
           *note_lines(RECIPE_NOTES, "recipe", rows), "", "Scenes by label:", "",
           *note_lines(SCENE_NOTES, "scene", rows), "",
           *true_positive_lines(rows), *two_mark_lines(rows),
           "| scene | recipe | attack | level | render PSNR | hidden PSNR | hidden SSIM | z | owned (log10 p) "
           "| decided | unaligned SSIM | aligned SSIM | moved SSIM | registration |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
  cell = lambda x, digits=3: "" if x is None else f"{x:.{digits}f}"
  for r in rows:
    registration = r.get("registration") or (r.get("moved") or {}).get("registration")
    refined = (registration or {}).get("refinement")
    reg = "" if registration is None else (f"{registration['rotation_error_deg']:.1e} deg, "
                                           f"{registration['residual']:.1e}"
                                           + (f"; key turned {refined['rotation_deg']:.1e} deg" if refined else ""))
    lines.append(f"| {r['scene']} | {r['recipe']} | {r['attack']} | {level_label(r)} | {r['render_psnr']:.2f} "
                 f"| {r['hidden_psnr']:.2f} | {r['hidden_ssim']:.3f} "
                 f"| {cell(r.get('hidden_z'), 1)} | {owned_cell(r)} | {'yes' if r['decided'] else 'no'} "
                 f"| {cell((r.get('unaligned') or {}).get('hidden_ssim'))} "
                 f"| {cell((r.get('aligned') or {}).get('hidden_ssim'))} "
                 f"| {cell((r.get('moved') or {}).get('hidden_ssim'))} | {reg} |")
  return "\n".join(lines) + "\n"


# survive_bench.png: a panel per scene and recipe, stacked (dozens of them), kept under the repository's 2 MB a file
# by its dpi and a palette of BAR_COLOURS (flat bars and text: a third of the full-colour bytes)
BAR_PANEL_HEIGHT, BAR_DPI, BAR_COLOURS = 3.2, 80, 256


def plot(rows: list[dict], path: pathlib.Path) -> None:
  """Hidden SSIM per attack and level, one panel per scene: bars as the table's hidden SSIM, dots without
  re-alignment (transforms) and moved first (round trips); the decision threshold dashed."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  scenes = list(dict.fromkeys((r["scene"], r["recipe"]) for r in rows))
  fig, axes = plt.subplots(len(scenes), 1, figsize=(max(8, 0.45 * len(rows) / max(1, len(scenes)) + 3),
                                                    BAR_PANEL_HEIGHT * len(scenes)), squeeze=False)
  for ax, (name, recipe) in zip(axes[:, 0], scenes):
    mine = [r for r in rows if (r["scene"], r["recipe"]) == (name, recipe)]
    x = np.arange(len(mine))
    ax.bar(x, [r["hidden_ssim"] for r in mine],
           color=["C0" if owned(r) else "C3" for r in mine])
    for field, marker, label in (("unaligned", "kx", "without re-alignment"),
                                 ("moved", "g^", "moved first, re-aligned")):
      points = [(i, r[field]["hidden_ssim"]) for i, r in enumerate(mine) if r.get(field)]
      if points:
        ax.plot(*zip(*points), marker, label=label)
    threshold = mine[0].get("threshold")
    if threshold is not None:
      ax.axhline(threshold, color="k", linestyle="--", linewidth=0.8, label="ownership threshold")
    ax.set_xticks(x, [f"{r['attack']}\n{level_label(r)}" for r in mine], fontsize=6, rotation=90)
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("hidden SSIM")
    ax.set_title(f"{name} ({recipe}): bars owned by verify (blue) or not (red); the threshold's decision where "
                 "measured before verify's test", fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
  fileio.save_figure(fig, path, dpi=BAR_DPI, palette=BAR_COLOURS)
  plot_curves(rows, path.with_name(CURVES_FIGURE))


def extraction_curves(rows: list[dict]) -> dict[tuple, list[tuple[int, float, bool]]]:
  """(scene, recipe, poses, views) -> [(training steps, hidden SSIM, owned)] of the model-extraction rows
  (attack extraction: poses orbit; extraction_<poses>), by steps: the curves of issue 39's extraction target."""
  curves = {}
  for r in rows:
    if r["attack"].startswith("extraction"):
      curves.setdefault(extraction_key(r), []).append((r["steps"], r["hidden_ssim"], owned(r)))
  return {key: sorted(points) for key, points in sorted(curves.items())}


def extraction_key(row: dict) -> tuple:
  """(scene, recipe, poses, views) of a model-extraction row (attack extraction: poses orbit; extraction_<poses>)."""
  poses = row["attack"].removeprefix("extraction").removeprefix("_") or "orbit"
  return row["scene"], row["recipe"], poses, row["level"]


PANEL_HEIGHT, LEGEND_LINE = 4.8, 0.16  # inches: survive_curves.png's panels, a line of their legends


def plot_curves(rows: list[dict], path: pathlib.Path) -> None:
  """Left: hidden SSIM against fine-tuning steps, one line per scene, recipe and schedule (dashed: with
  densification); middle: against the training steps of a model extraction, one line per scene, recipe and number
  of rendered views (filled: owned); right: the frontier, hidden SSIM after FRONTIER_STEPS steps of fine-tuning
  against what the recipe costs the render (the untouched student's test PSNR below its teacher's)."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig = plt.figure(figsize=(19, PANEL_HEIGHT))
  grid = fig.add_gridspec(2, 3)  # the panels, and their legends below them (one entry a line: many)
  curves, extracted, frontier = (fig.add_subplot(grid[0, k]) for k in range(3))
  groups = list(dict.fromkeys((r["scene"], r["recipe"]) for r in rows))
  for index, ((scene, recipe, poses, views), points) in enumerate(extraction_curves(rows).items()):
    steps, ssim, decided = zip(*points)
    line, = extracted.plot(steps, ssim, "-", color=f"C{index % 10}", label=f"{scene} {recipe}: {views} {poses} views")
    extracted.scatter(steps, ssim, color=[line.get_color() if o else "white" for o in decided],
                      edgecolors=line.get_color(), zorder=3)
  for index, (scene, recipe) in enumerate(groups):
    mine = [r for r in rows if (r["scene"], r["recipe"]) == (scene, recipe)]
    untouched = next((r for r in mine if r["attack"] == "none"), None)
    for attack, style in zip(FINETUNE_SCHEDULES, ("-o", "--s", ":^")):
      points = sorted((r["level"], r["hidden_ssim"]) for r in mine if r["attack"] == attack)
      if untouched and points:
        points = [(0.0, untouched["hidden_ssim"])] + points
      if points:
        curves.plot([max(x, 10.0) for x, _ in points], [y for _, y in points], style, color=f"C{index}",
                    label=f"{scene} {recipe}{SCHEDULE_LABELS[attack]}")
    tuned = next((r for r in mine if r["attack"] == "finetune" and r["level"] == FRONTIER_STEPS), None)
    if untouched and tuned and untouched.get("render_loss_db") is not None:
      frontier.plot(untouched["render_loss_db"], tuned["hidden_ssim"], "o", color=f"C{index}")
      frontier.annotate(f"{scene} {recipe}", (untouched["render_loss_db"], tuned["hidden_ssim"]), fontsize=7)
  threshold = next((r.get("threshold") for r in rows if r.get("threshold") is not None), None)
  for ax in (curves, extracted, frontier):
    if threshold is not None:
      ax.axhline(threshold, color="k", linestyle=":", linewidth=0.8, label="ownership threshold")
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("hidden SSIM")
    ax.grid(alpha=0.3)
  curves.set_xscale("log")
  curves.set_xlabel("fine-tuning steps on the training views (untouched at the left edge)")
  extracted.set_xscale("log")
  extracted.set_xlabel("training steps of a fresh 3D-GS on the marked scene's renders (model extraction)")
  extracted.set_title("model extraction: filled points owned by verify", fontsize=9)
  frontier.set_xlabel("render loss of the recipe, dB (teacher's test PSNR minus the student's)")
  frontier.set_title(f"hidden SSIM after {FRONTIER_STEPS} fine-tuning steps", fontsize=9)
  lines = 0
  for k, (panel, columns) in enumerate(((curves, 2), (extracted, 1))):
    handles, labels = panel.get_legend_handles_labels()
    key = fig.add_subplot(grid[1, k])
    key.axis("off")
    if len(handles) > 1:  # more than the threshold's line
      key.legend(handles, labels, fontsize=7, ncol=columns, loc="upper center", frameon=False)
      lines = max(lines, -(-len(handles) // columns))
  grid.set_height_ratios([PANEL_HEIGHT, LEGEND_LINE * lines + 0.01])
  fig.set_size_inches(19, PANEL_HEIGHT + LEGEND_LINE * lines)
  fileio.save_figure(fig, path)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", default="experiments/results")
  parser.add_argument("--workdir", default="workdirs/survive", help="each attack's files, per scene")
  parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated labels of {sorted(SCENES)}, "
                      "or scene=conceal_workdir[@recipe][+layered_workdir] (recipe: recommended unless given; "
                      "layered_workdir: a second mark concealed on conceal_workdir's student, read from its student)")
  parser.add_argument("--attacks", default=",".join(CHEAP_ATTACKS),
                      help=f"comma-separated groups of "
                           f"{CHEAP_ATTACKS + ('finetune_gentle', 'decimate_scaled', 'extraction')}, or round "
                           f"trips of the converter group by name ({', '.join(sorted({c[0] for c in CONVERSIONS}))})")
  parser.add_argument("--finetune-steps", default="30,100,300,1000", help="fine-tuning lengths (3000, 10000 too)")
  parser.add_argument("--extraction", action="store_true", help="also run model extraction (long)")
  parser.add_argument("--extraction-views", default="200", help="comma-separated numbers of rendered views")
  parser.add_argument("--extraction-steps", default="10000", help="comma-separated training lengths")
  parser.add_argument("--extraction-poses", default="orbit", help="comma-separated sets of rendered poses beyond "
                      "the training cameras: orbit (attack extraction), sphere (attack extraction_sphere); or unseen: "
                      "orbit poses without the training cameras (attack extraction_unseen)")
  parser.add_argument("--test-views", type=int, default=10, help="test views of render_psnr")
  parser.add_argument("--calibration", default="experiments/results/ownership_calibration.json")
  verify = default.get_config().verify
  parser.add_argument("--alpha", type=float, default=verify.alpha, help="verify's decision level (owned)")
  parser.add_argument("--null-views", type=int, default=verify.null_views, help="verify's turned views, at least")
  parser.add_argument("--redo", action="store_true", help="recompute rows already in the results")
  parser.add_argument("--converter-timeout-s", type=float, default=CONVERTER_TIMEOUT_S,
                      help="the longest one converter call may take (.sog of lego: most of an hour on 2 cores)")
  args = parser.parse_args(argv)
  out, workdir = pathlib.Path(args.out), pathlib.Path(args.workdir)
  calibration = ownership.load_calibration(args.calibration)
  groups = [g for g in args.attacks.split(",") if g] + (["extraction"] if args.extraction else [])
  try:
    done = {row_key(r) for r in json.loads((out / f"{NAME}.json").read_text())["rows"]}
  except (OSError, ValueError, KeyError):
    done = set()
  done = set() if args.redo else done
  finetune_steps = [int(n) for n in args.finetune_steps.split(",") if n]
  extraction_poses = [p for p in args.extraction_poses.split(",") if p]
  unknown = sorted(set(extraction_poses) - set(EXTRACTION_POSES))
  if unknown:
    parser.error(f"unknown --extraction-poses {', '.join(unknown)} (of {', '.join(EXTRACTION_POSES)})")

  def save(rows):
    if rows:
      for r in rows:
        r["threshold"] = calibration["threshold"]
      results_io.write_results(out, NAME, rows, row_key, table, plot, calibration=args.calibration)
    drop_compilations()

  for spec in (s for s in args.scenes.split(",") if s):
    label, _, path = spec.partition("=")
    path, _, layered = path.partition("+")
    if path:
      path, _, recipe = path.partition("@")
      name, run, recipe = label, pathlib.Path(path), recipe or "recommended"
    else:
      name, run, recipe = SCENES[label][0], pathlib.Path(SCENES[label][1]), SCENES[label][2]
    layered = pathlib.Path(layered) if layered else None
    runs = [run] + ([layered] if layered else [])
    if not all((r / f).is_file() for r in runs for f in ("student.ply", "decoder.msgpack", "key.json", "config.json")):
      print(f"skipping {label}: no finished conceal run in {' or '.join(map(str, runs))}")
      continue
    # a run given by path caches under the name of the run whose student is attacked (a label alone would share a
    # named scene's cache): the marks of one scene read the same attacked scenes, fine-tunings and extractions
    cache = workdir / (runs[-1].name if path else label)
    scene = load_scene(name, run, recipe, args.test_views, calibration, cache, args.alpha, args.null_views, layered)
    scene.converter_timeout_s = args.converter_timeout_s
    missing = lambda attack, level, steps=None: (name, recipe, attack, json.dumps(level), steps) not in done
    if "none" in groups and missing("none", None):
      save([scene.row("none", None, scores_of(scene, scene.student), aligned(scene, scene.student)["test"],
                      render_loss_db=render_loss(scene.run))])
    if "transforms" in groups:
      save(transform_rows(scene, [(a, l) for a, l in TRANSFORMS if missing(a, l)]))
    conversions = [c for c in CONVERSIONS if "converter" in groups or c[0] in groups]
    if conversions:
      if converter.available():
        save(converter_rows(scene, [c for c in conversions if missing(c[0], c[1])]))
      else:
        print("skipping the round trips: splat-transform is not installed (make node_modules)")
    todo = [f for f in SCALED_FACTORS if missing("decimate_scaled", f)]
    if "decimate_scaled" in groups and todo:
      if converter.available():
        save(scaled_decimation_rows(scene, todo))
      else:
        print("skipping decimate_scaled: splat-transform is not installed (make node_modules)")
    for attack in FINETUNE_SCHEDULES:
      todo = [n for n in finetune_steps if missing(attack, n)]
      if attack in groups and todo:
        save(finetune_rows(scene, todo, attack, args.test_views))
    if "extraction" in groups:
      steps = [int(n) for n in args.extraction_steps.split(",") if n]
      for poses, views in itertools.product(extraction_poses, args.extraction_views.split(",")):
        attack = "extraction" if poses == "orbit" else f"extraction_{poses}"
        todo = [n for n in steps if missing(attack, int(views), n)]
        if todo:
          save(extraction_rows(scene, int(views), todo, args.test_views, poses))


if __name__ == "__main__":
  main()
