"""bench-robust end to end on a tiny concealment run: attack rows, the fine-tuning attack and the ownership
calibration with clean models (experiments/bench_robust.py)."""
from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conceal_jax import main as main_lib
from conceal_jax.conceal import reveal
from experiments import bench_robust
from tests.test_conceal import tiny, tiny_config  # noqa: F401  (tiny is a fixture)


@pytest.fixture(scope="module")
def run(tiny, tmp_path_factory):  # noqa: F811
  """A finished 3-step concealment workdir (with the config.json the job writes)."""
  workdir = tmp_path_factory.mktemp("robust") / "conceal"
  main_lib.run(tiny_config(tiny, iterations=3), str(workdir))
  return workdir


@pytest.mark.slow  # the module's `run` fixture conceals and attacks for minutes
def test_bench_run_scores_every_attack_and_pose(run):
  result = bench_robust.bench_run(run, test_views=1)
  assert result["test_views"] == 1 and np.isfinite(result["hidden_ssim"])
  assert {r["attack"] for r in result["image_attacks"]} >= {"blur", "jpeg"}
  assert result["model_attacks"][0]["attack"] == "none" and len(result["model_attacks"]) > 1
  assert all(np.isfinite(r["hidden_ssim"]) for r in result["image_attacks"] + result["model_attacks"])
  assert {r["kind"] for r in result["pose"]} == {"translation", "rotation"}


@pytest.mark.slow  # the module's `run` fixture conceals and attacks for minutes
def test_finetune_rows_score_each_snapshot(run, tiny):  # noqa: F811
  rows = bench_robust.finetune_rows(run, [10, 20], densify=False, test_views=1)
  assert [r["steps"] for r in rows] == [10, 20] and all(not r["densify"] for r in rows)
  assert all(np.isfinite(r["hidden_ssim"]) and np.isfinite(r["render_psnr"]) for r in rows)


@pytest.mark.slow  # the module's `run` fixture conceals and attacks for minutes
def test_calibration_counts_clean_models_at_the_key_and_orbit_poses(run, tiny):  # noqa: F811
  result = bench_robust.bench_run(run, test_views=1)
  teacher = tiny[1]
  plain = bench_robust.calibration_trials([run], [result], poses=2, test_views=1)
  more = bench_robust.calibration_trials([run], [result], poses=2, test_views=1, clean_models=[teacher])
  added = [t for t in more["clean_trials"] if t["trial"].startswith("clean model")]
  assert len(added) == 1 + 2 and len(more["clean"]) == len(plain["clean"]) + 3  # the key and 2 orbit poses
  # the clean model is the run's own teacher: its scores equal the "teacher at ..." trials'
  teacher_scores = [t["score"] for t in plain["clean_trials"] if t["trial"].startswith("teacher at")]
  np.testing.assert_allclose(sorted(t["score"] for t in added), sorted(teacher_scores), rtol=1e-5)
  assert more["num_clean"] == len(more["clean"]) and more["marked"] == plain["marked"]
  assert 0.0 <= more["false_positive_rate"] <= 1.0


@pytest.mark.slow  # the module's `run` fixture conceals and attacks for minutes
def test_runs_of_one_mark_are_not_each_others_clean_trials(run, tmp_path):
  """A second run that hid the same image in the same teacher (here a copy of the run) adds no cross-run
  clean trials: its student carries I."""
  result = bench_robust.bench_run(run, test_views=1)
  twin = tmp_path / "twin"
  shutil.copytree(run, twin)
  one = bench_robust.calibration_trials([run], [result], poses=2, test_views=1)
  both = bench_robust.calibration_trials([run, twin], [result, result], poses=2, test_views=1)
  assert len(both["clean"]) == 2 * len(one["clean"])
  assert not any(t["trial"].startswith(str(twin)) for t in both["clean_trials"])


@pytest.mark.slow  # a concealment compiled for this reading alone; the key's fields: tests/test_unet.py
def test_owner_reads_the_decoders_input_norm_from_the_key(tiny, tmp_path):  # noqa: F811
  """A run whose decoder centres its clipped input is scored as its own job scored it (the reading comes from
  key.json; the whole bench row on such a run: the slow tests)."""
  workdir = tmp_path / "conceal"
  result = main_lib.run(tiny_config(tiny, iterations=3, decoder_input_norm="center", decoder_clip_input=True),
                        str(workdir))
  _, _, owner = bench_robust.load_run(workdir)
  assert owner.reading == reveal.Reading("center", clip=True)
  _, student, _ = bench_robust.load_run(workdir)
  np.testing.assert_allclose(owner.check_scores(jax.tree.map(jnp.asarray, student))["hidden_ssim"],
                             result["metrics"]["hidden"]["ssim"], rtol=1e-4)
