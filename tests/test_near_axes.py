"""Hidden SSIM along and about the key's own axes, output and input (experiments/near_axes.py)."""
from __future__ import annotations

import dataclasses

import jax
import numpy as np

from conceal_jax.conceal import unet
from experiments import near_axes
from tests.test_robustness import no_decoder_owner, scene
from tests.helpers import make_camera


def test_an_identity_reader_scores_its_input_and_the_key_reads_its_own_render():
  """With no decoder the output is the input; I is the key's own render, so the key scores 1 on every axis and
  a turn of 20 degrees, which moves the image, scores less."""
  owner = no_decoder_owner(scene(), make_camera(32, 32))
  rows = near_axes.axis_rows(scene(), owner, 4.0, "turn", [0.0, 20.0])
  assert [(r["value"], r["axis"]) for r in rows] == [(v, a) for v in (0.0, 20.0) for a in near_axes.AXIS_NAMES]
  for r in rows:
    assert r["output_ssim"] == r["input_ssim"]
  np.testing.assert_allclose([r["input_ssim"] for r in rows[:6]], 1.0, atol=1e-5)
  assert max(r["input_ssim"] for r in rows[6:]) < 0.99


def test_a_decoders_output_is_scored_apart_from_its_input():
  """At the key (move 0) the output's SSIM is what the owner's own check reads; the input's is the render's."""
  gaussians = scene()
  plain = no_decoder_owner(gaussians, make_camera(32, 32))
  owner = dataclasses.replace(plain, decoder=unet.init_decoder(jax.random.key(0), 4, 16), decoder_width=4)
  rows = near_axes.axis_rows(gaussians, owner, 4.0, "move", [0.0])
  np.testing.assert_allclose([r["output_ssim"] for r in rows], owner.check_scores(gaussians)["hidden_ssim"],
                             rtol=1e-5)
  np.testing.assert_allclose([r["input_ssim"] for r in rows], 1.0, atol=1e-5)
  assert near_axes.axis_rows(gaussians, owner, 4.0, "move", []) == []


def test_table_has_a_line_per_pose_and_a_column_per_axis():
  rows = [dict(kind=kind, value=value, axis=axis, output_ssim=0.5, input_ssim=0.25)
          for kind, value in (("move", 0.02), ("turn", 2.0)) for axis in near_axes.AXIS_NAMES]
  lines = near_axes.table("RUN", rows)
  assert lines[2] == "| pose | +x | -x | +y | -y | +z | -z |"
  assert lines[4] == "| move 0.02 of the depth |" + " 0.500 (0.250) |" * 6
  assert lines[5].startswith("| turn 2 deg |") and len(lines) == 7
