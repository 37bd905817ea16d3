"""The ownership test: threshold choice from measured scores, and the verify job end to end."""
from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from conceal_jax import RenderOptions
from conceal_jax import main as main_lib
from conceal_jax.conceal import key as key_lib, reveal, unet
from conceal_jax.configs import default
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.robust import ownership
from tests.helpers import make_camera, random_gaussians


def brute_force(clean, marked, max_fpr):
  """Best true-positive rate over every threshold between consecutive scores with FPR < max_fpr."""
  scores = np.unique(np.concatenate([clean, marked, [-1.0, 2.0]]))
  best = 0.0
  for t in (scores[:-1] + scores[1:]) / 2:
    r = ownership.rates(clean, marked, t)
    if r["false_positive_rate"] < max_fpr:
      best = max(best, r["true_positive_rate"])
  return best


def test_separable_scores_get_the_midpoint_threshold():
  choice = ownership.choose_threshold([0.1, 0.3, 0.2], [0.9, 0.7, 0.95])
  assert choice["threshold"] == pytest.approx(0.5)
  assert choice["false_positive_rate"] == 0.0 and choice["true_positive_rate"] == 1.0


@pytest.mark.parametrize("seed", range(4))
def test_threshold_maximises_true_positives_below_the_false_positive_bound(seed):
  rng = np.random.default_rng(seed)
  clean = np.concatenate([rng.uniform(0.0, 0.3, 197), rng.uniform(0.5, 0.9, 3)])  # three lucky clean models
  marked = rng.uniform(0.4, 1.0, 150)
  choice = ownership.choose_threshold(clean, marked, 0.01)
  assert choice["false_positive_rate"] < 0.01
  assert choice["true_positive_rate"] == pytest.approx(brute_force(clean, marked, 0.01))
  assert choice["num_clean"] == 200 and choice["num_marked"] == 150


def test_bad_calibration_names_the_file(tmp_path):
  path = tmp_path / "cal.json"
  path.write_text('{"clean": [0.1]}')
  with pytest.raises(ValueError, match="cal.json"):
    ownership.load_calibration(str(path))
  with pytest.raises(ValueError, match="clean and marked"):
    ownership.choose_threshold([], [0.5])


def test_verify_decides_with_the_calibrated_threshold(tmp_path):
  """A scene whose revealed image is the reference scores SSIM 1 (owned); another image does not."""
  g = jax.tree.map(np.asarray, random_gaussians(2, 300, degree=1, spread=0.5, log_scale=(-2.5, -1.8)))
  ply.save_ply(tmp_path / "scene.ply", g)
  camera = make_camera(32, 32)
  options = RenderOptions(background=(1.0, 1.0, 1.0))
  decoder = unet.init_decoder(jax.random.key(0), 4, 16)
  reveal.save_decoder(str(tmp_path / "decoder.msgpack"), decoder)
  key_lib.save_key(str(tmp_path / "key.json"), camera, dict(hidden_size=16, uses_decoder=True, decoder_width=4,
                                                           render_options=dict(background=[1.0, 1.0, 1.0])))
  revealed = np.asarray(reveal.reveal_image(jax.tree.map(jax.numpy.asarray, g), camera, options, decoder, 4, 16))
  fileio.write_image(tmp_path / "mine.png", revealed)
  (tmp_path / "cal.json").write_text(json.dumps(dict(clean=[0.1, 0.2, 0.3], marked=[0.9, 0.95])))
  config = default.get_config()
  config.mode = "verify"
  config.reveal.ply, config.reveal.key = str(tmp_path / "scene.ply"), str(tmp_path / "key.json")
  config.reveal.decoder, config.verify.calibration = str(tmp_path / "decoder.msgpack"), str(tmp_path / "cal.json")
  config.reveal.hidden = str(tmp_path / "mine.png")
  result = main_lib.run(config, str(tmp_path / "out"))
  assert result["owned"] and result["score"] > 0.98 and result["calibration"]["threshold"] == pytest.approx(0.6)
  saved = json.loads((tmp_path / "out" / "verify.json").read_text())
  assert saved["owned"] and saved["calibration"]["false_positive_rate"] == 0.0
  config.reveal.hidden = "astronaut"
  assert not main_lib.run(config, str(tmp_path / "other"))["owned"]


def test_verify_requires_a_calibration(tmp_path):
  config = default.get_config()
  config.mode = "verify"
  config.reveal.ply = config.reveal.key = config.reveal.hidden = "x"
  with pytest.raises(ValueError, match="verify.calibration is required"):
    main_lib.run(config, str(tmp_path / "out"))
  assert not (tmp_path / "out").exists()
