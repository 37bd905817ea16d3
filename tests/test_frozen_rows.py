"""Every benchmark row and dataset config still resolves to the settings its stored results were measured with.

tests/data/frozen_row_configs.json holds each row's resolved config from before the presets redesign (the
config sections that shape a run). Under today's layout a row must resolve to the same values, its keys
renamed by OLD_TO_NEW; options removed since may appear in a frozen row only at the value the method now
always has (REMOVED), options added since only at the value that leaves a run as it was (ADDED); rows that
used a removed option are retired (RETIRED_ROWS): their stored numbers stay
in the results files.
"""
from __future__ import annotations

import importlib
import json
import pathlib

import pytest

from conceal_jax.core import workdir
from experiments import bench_baselines, bench_conceal

FROZEN = json.loads((pathlib.Path(__file__).parent / "data" / "frozen_row_configs.json").read_text())
TEACHER = pathlib.Path("TEACHER.ply")
REPO = str(pathlib.Path(__file__).resolve().parents[1])  # the frozen rows' absolute data paths start with <repo>

OLD_TO_NEW = {
    "conceal.teacher": "mark.teacher", "conceal.hidden": "mark.hidden", "conceal.hidden_size": "mark.hidden_size",
    "conceal.extra_hidden": "mark.extra_hidden", "conceal.key_kind": "mark.key_kind",
    "conceal.key_index": "mark.key_index", "conceal.key_seed": "mark.key_seed",
    "conceal.decoder_width": "conceal.decoder.width", "conceal.decoder_vgg_init": "conceal.decoder.vgg_init",
    "conceal.decoder_input_norm": "conceal.decoder.input_norm",
    "conceal.decoder_clip_input": "conceal.decoder.clip_input", "conceal.decoder_lr": "conceal.decoder_opt.lr",
    "conceal.decoder_adam_eps": "conceal.decoder_opt.adam_eps",
    "conceal.decoder_lr_final_ratio": "conceal.decoder_opt.lr_final_ratio",
    "conceal.decoder_update_clip": "conceal.decoder_opt.update_clip",
    "conceal.decoder_polish_steps": "conceal.decoder_opt.polish_steps",
    "conceal.identity_distorted": "conceal.attacks.identity_distorted",
    **{f"conceal.{k}": f"conceal.leakage.{k}" for k in ("identity_on_student", "identity_on_teacher_check",
                                                         "decoy_views", "decoy_fraction", "decoy_translation",
                                                         "decoy_rotation_deg")},
    **{f"conceal.check_{k}_max": f"conceal.attacks.{k}_max" for k in ("blur", "noise", "brightness", "contrast",
                                                                       "dropout", "param_noise")},
}
# Options removed by the redesign, at the one value every kept row ran with.
REMOVED = {"conceal.key_at_decoder_size": False, "conceal.decoder_amsgrad": False, "conceal.decoder_average": 0.0,
           "conceal.identity_perturbed": False, "conceal.trained_fields": "all", "conceal.lanes": 0}
# Options added since, at the value that leaves a run as it was (the carrier film off).
ADDED = {"conceal.carrier.film": False, "conceal.carrier.distance": 0.1, "conceal.carrier.spacing": 2.0,
         "conceal.carrier.opacity": 0.5, "mark.key_offset": 1.0, "data.format": "auto", "data.images": "images",
         "conceal.attacks.quantize_fraction": 0.0, "conceal.attacks.reset_fraction": 0.0,
         "conceal.carrier.layers": 1,
         "conceal.attacks.merge_fraction": 0.0, "train.views_per_step": 1, "mark.message_bits": 0, "mark.message": "",
         "conceal.carrier.dc_bound": 0.0, "conceal.attacks.merge_depth": 1.0,
         "conceal.carrier.stack": 1, "conceal.carrier.spread": 0.6, "train.time_limit_min": 0.0,
         "conceal.attacks.prune_small_max": 0.0, "conceal.leakage.decoy_key_axes": False,
         "conceal.attacks.merge_groups": "nearest", "conceal.attacks.merge_keep": [0.5, 0.8],
         "conceal.attacks.regroup_every": 500, "conceal.attacks.merge_scales": [1.0],
         "conceal.carrier.thickness": 0.01, "conceal.carrier.at_decoder_size": False,
         "conceal.carrier.linear_maps_mb": 4096.0, "conceal.leakage.tolerance_deg": 0.0,
         "conceal.leakage.tolerance_views": 0, "conceal.leakage.tolerance_fraction": 0.0,
         "conceal.leakage.decoys_hold_student": True, "conceal.decoder.reference": False,
         "conceal.leakage.decoy_orbit_turns": False, "conceal.decoder_opt.rollback_factor": 0.0,
         "conceal.decoder_opt.rollback_every": 100, "conceal.decoder_opt.polish_merge_fraction": None}
# Rows that used a removed option (their results stay in conceal_bench.json and REPRODUCTION's appendix).
RETIRED_ROWS = {"in_scene_no_update_clip_decoder_amsgrad", "in_scene_polished_running_average",
                "in_scene_colour_only_student", "in_scene_colour_only_student_polished"}
SECTIONS = ("seed", "mode", "data", "render", "eval", "conceal", "mark", "baseline", "train", "init")


def renamed(frozen: dict) -> dict:
  """A frozen config, flattened, in today's key names and without the removed options (checked at their value)."""
  flat = {}
  for key, value in workdir.flatten(frozen).items():
    if key in REMOVED:
      assert value == REMOVED[key], f"{key}={value!r}: a row that used a removed option must be retired"
      continue
    flat[OLD_TO_NEW.get(key, key)] = value
  return flat


def resolved(config, frozen: dict) -> dict:
  """Today's config, flattened, restricted to the sections the frozen one holds, without the options added since
  (checked at the value that leaves a run as it was)."""
  sections = {key.split(".")[0] for key in workdir.flatten(frozen)} | ({"mark"} if "conceal" in frozen else set())
  plain = json.loads(json.dumps(config.to_dict()))
  flat = {k: v for k, v in workdir.flatten(plain).items() if k.split(".")[0] in sections}
  for key, value in ADDED.items():
    if key in flat:
      assert flat.pop(key) == value, f"{key}: a frozen row must resolve to {value!r}"
  if flat.get("data.path", "").startswith(REPO + "/"):
    flat["data.path"] = "<repo>" + flat["data.path"][len(REPO):]
  return flat


def conceal_row(name: str):
  row, width = name.rsplit("_w", 1)
  return row, int(width)


@pytest.mark.parametrize("name", sorted(FROZEN["conceal"]))
def test_bench_conceal_rows_resolve_as_frozen(name):
  row, width = conceal_row(name)
  if row in RETIRED_ROWS:
    assert row not in bench_conceal.ROWS
    return
  frozen = FROZEN["conceal"][name]
  assert resolved(bench_conceal.run_config("lego", TEACHER, row, width, 0, 0), frozen) == renamed(frozen)


@pytest.mark.parametrize("row", sorted(FROZEN["baselines"]))
def test_bench_baselines_rows_resolve_as_frozen(row):
  frozen = FROZEN["baselines"][row]
  assert resolved(bench_baselines.run_config("lego", TEACHER, row, 0, 0), frozen) == renamed(frozen)


@pytest.mark.parametrize("name", ["demo", "demo_robust", "lego", "beer", "colmap", "nerf_synthetic"])
def test_dataset_configs_resolve_as_frozen(name):
  frozen = {k: v for k, v in FROZEN["configs"][name].items() if k in SECTIONS}
  config = importlib.import_module(f"conceal_jax.configs.{name}").get_config()
  assert resolved(config, frozen) == renamed(frozen)


def test_recipes_are_the_rows_they_are_measured_by():
  """configs/lego_conceal.py's recipes are bench-conceal's rows at width 16: recommended, in_scene and released are
  the rows of their names, paper is full (the decoder's width and rate aside)."""
  lego_conceal = importlib.import_module("conceal_jax.configs.lego_conceal")
  for recipe, row in (("recommended", "recommended"), ("in_scene", "in_scene"), ("paper", "full"),
                      ("released", "released")):
    config = lego_conceal.get_config(recipe)
    narrow = recipe in ("recommended", "in_scene")
    expected = bench_conceal.run_config("lego", TEACHER, row, 16 if narrow else 64, 0, 0)
    # the bench's paths are absolute and it scores every test view
    config.mark.teacher, config.data.path, config.eval.max_views = str(TEACHER), expected.data.path, 0
    assert workdir.differing_keys(expected.to_dict(), config.to_dict()) == []


def test_the_generic_conceal_config_takes_a_scene_and_a_teacher(tmp_path):
  """configs/conceal.py:<recipe> conceals with that recipe once data.path and mark.teacher are given; without them,
  or with an unknown recipe, one clear error."""
  from conceal_jax import main as main_lib
  from conceal_jax.conceal import settings as conceal_settings
  conceal = importlib.import_module("conceal_jax.configs.conceal")
  lego_conceal = importlib.import_module("conceal_jax.configs.lego_conceal")
  teacher = tmp_path / "teacher.ply"
  teacher.write_bytes(b"ply")  # validation checks that the file exists; the job reads it
  for recipe in ("recommended", "in_scene", "paper", "released"):
    config = conceal.get_config(recipe)
    assert config.mode == "conceal" and config.data.path == ""
    with pytest.raises(ValueError, match="mark.teacher"):
      main_lib.MODES["conceal"][0](config)
    config.data.path, config.mark.teacher = "demo", str(teacher)
    conceal_settings.validate(config)
    # the same recipe as lego's, which records its curves besides and sets its film's grid in lego's pixels
    expected = lego_conceal.get_config(recipe).conceal.to_dict()
    film = ["carrier.spacing"] if config.conceal.carrier.film else []
    assert workdir.differing_keys(expected, config.conceal.to_dict()) == film + ["eval_every", "eval_views"]
  assert conceal.get_config().conceal.to_dict() == conceal.get_config("recommended").conceal.to_dict()
  with pytest.raises(ValueError, match="unknown concealment recipe 'best'"):
    conceal.get_config("best")
