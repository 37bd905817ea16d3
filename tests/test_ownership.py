"""The ownership test: the verify job end to end (decision at alpha, its evidence, bad input), its batched decisions,
and the optional calibration threshold chosen from measured scores."""
from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest

from conceal_jax import RenderOptions
from conceal_jax import main as main_lib
from conceal_jax.conceal import hidden as hidden_lib, key as key_lib, reveal, unet
from conceal_jax.configs import default
from conceal_jax.core import fileio
from conceal_jax.data import ply
from conceal_jax.gs import register as register_lib
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


def write_scene(tmp_path, uses_decoder: bool):
  """A random scene, a key at a 32x32 camera (hidden size 16) and, with a decoder, a random one; returns what the
  key reveals from the scene, saved as mine.png."""
  g = jax.tree.map(np.asarray, random_gaussians(2, 300, degree=1, spread=0.5, log_scale=(-2.5, -1.8)))
  ply.save_ply(tmp_path / "scene.ply", g)
  camera = make_camera(32, 32)
  options = RenderOptions(background=(1.0, 1.0, 1.0))
  decoder = unet.init_decoder(jax.random.key(0), 4, 16) if uses_decoder else None
  if uses_decoder:
    reveal.save_decoder(str(tmp_path / "decoder.msgpack"), decoder)
  key_lib.save_key(str(tmp_path / "key.json"), camera, dict(hidden_size=16, uses_decoder=uses_decoder,
                                                           decoder_width=4,
                                                           render_options=dict(background=[1.0, 1.0, 1.0])))
  revealed = np.asarray(reveal.reveal_image(jax.tree.map(jax.numpy.asarray, g), camera, options, decoder, 4, 16))
  fileio.write_image(tmp_path / "mine.png", revealed)
  config = default.get_config()
  config.mode = "verify"
  config.reveal.ply, config.reveal.key = str(tmp_path / "scene.ply"), str(tmp_path / "key.json")
  config.reveal.decoder = str(tmp_path / "decoder.msgpack") if uses_decoder else ""
  config.reveal.hidden = str(tmp_path / "mine.png")
  config.verify.null_views = 8
  return config


@pytest.mark.job
def test_verify_decides_at_alpha_with_the_evidence(tmp_path):
  """The key's own view as the hidden image (no decoder): owned with a tiny p-value; another picture is not;
  the images are kept and a calibration file adds its threshold's decision."""
  config = write_scene(tmp_path, uses_decoder=False)
  config.verify.alpha = 1e-5  # 176 null outputs of 16x16 give 360,448 draws: p-values down to 2.8e-6
  result = main_lib.run(config, str(tmp_path / "out"))
  assert result["owned"] and result["log10_p"] < -5 and result["p_value"] <= config.verify.alpha
  assert result["log10_p"] == max(result["log10_p_model"], result["log10_p_null"])
  assert result["null"]["sources"] == {"unrelated_images": 8 * (len(hidden_lib.SAMPLE_NAMES)), "turned_views": 8}
  assert result["null"]["count"] == 8 * len(hidden_lib.SAMPLE_NAMES) + 8
  assert result["null"]["draws"] == 8 * result["null"]["count"] * 16 * 16
  assert "random-phase" in result["null"]["rests_on"]
  assert result["ssim"] > 0.95 and "calibration" not in result
  saved = json.loads((tmp_path / "out" / "verify.json").read_text())
  assert saved["owned"] and saved["z"] == pytest.approx(result["z"])
  for name in ("revealed.png", "hidden.png"):
    assert (tmp_path / "out" / name).is_file()
  with np.load(tmp_path / "out" / "null_revealed.npz") as nulls:
    assert nulls["turned_views"].shape == (8, 16, 16, 3)
  config.reveal.hidden = "astronaut"
  (tmp_path / "cal.json").write_text(json.dumps(dict(clean=[0.1, 0.2, 0.3], marked=[0.9, 0.95])))
  config.verify.calibration = str(tmp_path / "cal.json")
  other = main_lib.run(config, str(tmp_path / "other"))
  assert not other["owned"] and other["log10_p"] > -3
  assert other["calibration"]["threshold"] == pytest.approx(0.6) and not other["calibration"]["owned"]


@pytest.mark.job
def test_verify_decides_on_the_best_of_the_scenes_marks(tmp_path):
  """A scene with two marks (verify.marks): reveal's hidden image is another picture, the further mark's is the
  key's own view; owned on the better, its p-value twice its own (two readings in all), reported with its key."""
  config = write_scene(tmp_path, uses_decoder=False)
  config.verify.alpha = 1e-3  # the unrelated pictures' null draws alone suffice: no more turned views to render
  second = tmp_path / "second"
  second.mkdir()
  shutil.copy(tmp_path / "key.json", second / "key.json")
  shutil.copy(tmp_path / "mine.png", second / "hidden.png")
  alone = main_lib.run(config, str(tmp_path / "alone"))
  config.reveal.hidden, config.verify.marks = "astronaut", str(second)
  result = main_lib.run(config, str(tmp_path / "out"))
  assert result["owned"] and result["key"] == str(second / "key.json")
  assert [m["hidden"] for m in result["marks"]] == ["astronaut", str(second / "hidden.png")]
  assert result["log10_p"] == pytest.approx(min(m["log10_p"] for m in result["marks"]) + np.log10(2))
  assert result["marks"][1]["ssim"] == pytest.approx(alone["ssim"]) and result["marks"][0]["log10_p"] > -2
  assert result["marks"][1]["log10_p"] == pytest.approx(alone["log10_p"])


@pytest.mark.job
def test_verify_registers_the_suspect_once_for_all_its_marks(tmp_path, monkeypatch):
  """Re-aligned onto the owner's copy (here the scene itself), a scene tested for two marks is registered once and
  both keys are read through that registration."""
  config = write_scene(tmp_path, uses_decoder=False)
  config.verify.alpha = 1e-3
  second = tmp_path / "second"
  second.mkdir()
  shutil.copy(tmp_path / "key.json", second / "key.json")
  shutil.copy(tmp_path / "mine.png", second / "hidden.png")
  config.reveal.owner, config.verify.marks = config.reveal.ply, str(second)
  calls, register = [], register_lib.register
  monkeypatch.setattr(register_lib, "register", lambda *args, **kwargs: calls.append(1) or register(*args, **kwargs))
  result = main_lib.run(config, str(tmp_path / "out"))
  assert len(calls) == 1
  assert result["owned"] and result["alignment"]["residual"] < 1e-3
  assert [m["ssim"] for m in result["marks"]] == pytest.approx([result["ssim"]] * 2)


def test_verify_refuses_a_mark_folder_without_its_key(tmp_path):
  config = write_scene(tmp_path, uses_decoder=False)
  config.verify.marks = str(tmp_path / "nowhere")
  with pytest.raises(ValueError, match="nowhere is not the folder of a conceal run"):
    ownership.validate(config)


@pytest.mark.slow
def test_verify_with_a_decoder_reveals_through_it(tmp_path):
  """A random decoder outputs much the same image whatever it reads, but not quite: with the hidden image its own
  output at the key, what that output holds beyond the decoder's mean output is this render's alone, and verify
  decides owned; another picture is not."""
  config = write_scene(tmp_path, uses_decoder=True)
  config.verify.alpha = 1e-5
  result = main_lib.run(config, str(tmp_path / "out"))
  assert result["owned"] and result["log10_p"] <= -5 and result["null"]["max"] < result["z"]
  config.reveal.hidden = "astronaut"
  other = main_lib.run(config, str(tmp_path / "other"))
  assert not other["owned"] and other["log10_p"] > -3


def test_decisions_are_batched_over_revealed_and_hidden_images():
  rng = np.random.default_rng(0)
  hidden = np.stack([hidden_lib.load_hidden_image(name, 32) for name in ("astronaut", "camera")])
  revealed = np.clip(hidden + rng.normal(0, 0.1, hidden.shape), 0, 1)
  nulls = np.stack([hidden_lib.load_hidden_image(name, 32) for name in hidden_lib.SAMPLE_NAMES
                    if name not in ("astronaut", "camera")])
  d = ownership.decisions(revealed, hidden, nulls, 1e-5)
  assert d["z"].shape == d["log10_p"].shape == d["owned"].shape == (2, 2) and d["null_max"].shape == (2,)
  assert d["owned"][0, 0] and d["owned"][1, 1] and not d["owned"][0, 1] and not d["owned"][1, 0]
  reading = ownership.read_and_decide(lambda images: images, revealed[:1], hidden[:1], dict(pictures=nulls), 1e-5)
  single = ownership.ownership_test(reading, hidden[0], 1e-5)
  assert single["z"] == pytest.approx(d["z"][0, 0]) and single["log10_p"] == pytest.approx(d["log10_p"][0, 0])
  # resolve: the empirical p-value only where the model's is at most resolve; the decisions stay the same
  partial = ownership.decisions(revealed, hidden, nulls, 1e-5, resolve=1e-3)
  np.testing.assert_array_equal(partial["owned"], d["owned"])
  assert np.isnan(partial["log10_p_null"][0, 1]) == (d["log10_p_model"][:, 1].min() > -3)
  with pytest.raises(ValueError, match="resolve"):
    ownership.decisions(revealed, hidden, nulls, 1e-5, resolve=1e-6)
  with pytest.raises(ValueError, match="null_views"):
    ownership.decisions(revealed, hidden, nulls, 1e-7)


def reference_log10_p_null(revealed, hidden, nulls):
  """The empirical p-value by brute force: every null output less the mean, whitened, against the hidden image
  turned by np.rot90 / mirrored and rolled in the image domain by every shift, each z by phase_statistic.z_scores."""
  from conceal_jax.robust import phase_statistic as ps
  mean = nulls.mean(0)
  z = ps.z_scores(ps.whitened_spectra((revealed - mean)[None]), ps.whitened_spectra(hidden[None]))[0, 0]
  outputs = ps.whitened_spectra(nulls - mean)
  draws = []
  for image in (np.rot90(h, t) for h in (hidden, hidden[:, ::-1]) for t in range(4)):
    whitened = np.real(np.fft.ifft2(ps.whitened_spectra(np.ascontiguousarray(image)[None])[0]))
    for dy in range(hidden.shape[0]):
      for dx in range(hidden.shape[1]):
        draws.append(ps.z_scores(outputs, np.fft.fft2(np.roll(whitened, (dy, dx), (0, 1)))[None])[:, 0])
  draws = np.concatenate(draws)
  return z, np.log10((1 + np.sum(draws >= z)) / (1 + draws.size))


def test_decisions_empirical_null_against_a_brute_force_reference():
  rng = np.random.default_rng(1)
  hidden = hidden_lib.load_hidden_image("astronaut", 8)
  nulls = np.clip(0.5 + rng.normal(0, 0.2, (4, 8, 8, 3)), 0, 1)
  for revealed in (np.clip(hidden + rng.normal(0, 0.05, hidden.shape), 0, 1), nulls[0]):
    d = ownership.decisions(revealed[None], hidden[None], nulls, 0.01)
    z, log10_p = reference_log10_p_null(revealed, hidden, nulls)
    assert d["z"][0, 0] == pytest.approx(z, rel=1e-9, abs=1e-9)
    assert d["log10_p_null"][0, 0] == pytest.approx(log10_p, rel=1e-12)
    assert d["log10_p"][0, 0] == pytest.approx(max(log10_p, d["log10_p_model"][0, 0]), rel=1e-12)


def test_a_decoder_emitting_a_fixed_image_like_i_does_not_own_a_clean_scene():
  """The decoder's output is one fixed image much like I (plus noise) whatever it reads: against I it scores a
  z far in the random-phase tail, but less the decoder's mean output it is noise, not owned; a scene from which
  the decoder reveals I itself is owned."""
  from conceal_jax.robust import phase_statistic as ps
  rng = np.random.default_rng(2)
  hidden = hidden_lib.load_hidden_image("astronaut", 32)
  fixed = 0.6 * hidden + 0.4 * hidden_lib.load_hidden_image("camera", 32)

  def output(image):
    return np.clip(image + rng.normal(0, 0.03, image.shape), 0, 1)

  nulls = np.stack([output(fixed) for _ in range(128)])  # 128 * 8 * 32^2 draws: p-values down to 9.5e-7
  clean, marked = output(fixed), output(hidden)
  raw = ps.z_scores(ps.whitened_spectra(clean[None]), ps.whitened_spectra(hidden[None]))[0, 0]
  assert raw > 10 and ps.log_p_model(raw) < np.log(1e-6)
  d = ownership.decisions(np.stack([clean, marked]), hidden[None], nulls, 1e-6)
  assert abs(d["z"][0, 0]) < 4 and not d["owned"][0, 0]
  assert d["z"][1, 0] > 10 and d["owned"][1, 0]


@pytest.mark.parametrize("alpha", [0.0, 1.0, -1e-6, True])
def test_verify_refuses_a_bad_alpha(tmp_path, alpha):
  config = default.get_config()
  config.mode = "verify"
  config.reveal.ply = config.reveal.key = config.reveal.hidden = "x"
  with config.unlocked():
    config.verify.alpha = alpha
  with pytest.raises(ValueError, match="verify.alpha"):
    main_lib.run(config, str(tmp_path / "out"))
  assert not (tmp_path / "out").exists()


def test_verify_requires_a_hidden_image(tmp_path):
  config = default.get_config()
  config.mode = "verify"
  config.reveal.ply = config.reveal.key = "x"
  with pytest.raises(ValueError, match="reveal.hidden is required"):
    main_lib.run(config, str(tmp_path / "out"))
  assert not (tmp_path / "out").exists()


def test_verify_renders_enough_turned_views_for_alpha():
  """verify.null_views is a floor: a small hidden image gets the turned views its null needs for p <= alpha."""
  assert ownership.turned_views_needed(1e-6, 64, 168, 32) == 32  # 200 * 8 * 64^2 draws already suffice
  views = ownership.turned_views_needed(1e-6, 16, 168, 32)
  assert 1 / (1 + 8 * (168 + views) * 16 ** 2) <= 1e-6 < 1 / (1 + 8 * (168 + views - 1) * 16 ** 2)
  # decided on the best of two readings (twice the smaller p-value): enough draws for the pair to reach alpha
  two = ownership.turned_views_needed(1e-6, 16, 168, 32, readings=2)
  assert 2 / (1 + 8 * (168 + two) * 16 ** 2) <= 1e-6 < 2 / (1 + 8 * (168 + two - 1) * 16 ** 2)


def test_a_decision_on_the_best_of_two_readings_pays_a_factor_of_two():
  log10_ps = np.array([[-7.0, -2.0, -0.1], [-3.0, -5.0, -0.1]])
  np.testing.assert_allclose(ownership.combined_log10_p(log10_ps), [-7.0 + np.log10(2), -5.0 + np.log10(2), 0.0])
  np.testing.assert_allclose(ownership.combined_log10_p(log10_ps[:1]), log10_ps[0])


def test_decide_readings_combines_each_reading_and_refuses_too_few_draws_for_the_pair():
  """Each reading is read_and_decide's; the decision is on combined_log10_p of theirs; a null that lets one reading
  reach alpha but not the best of two (2 / (1 + draws) > alpha) is refused rather than never deciding owned."""
  hidden = hidden_lib.load_hidden_image("astronaut", 16)[None]
  nulls = dict(pictures=hidden_lib.load_hidden_image("camera", 16)[None])  # 8 * 16^2 = 2048 draws
  readings = dict(plain=lambda images: images, mirrored=lambda images: images[:, :, ::-1])
  by_name, both = ownership.decide_readings(readings, hidden, hidden, nulls, 1e-3)
  for name, fn in readings.items():
    alone = ownership.read_and_decide(fn, hidden, hidden, nulls, 1e-3)
    np.testing.assert_array_equal(by_name[name].result["log10_p"], alone.result["log10_p"])
  np.testing.assert_allclose(both["log10_p"], ownership.combined_log10_p([r.result["log10_p"]
                                                                          for r in by_name.values()]))
  assert both["owned"][0, 0] and ownership.strongest(by_name, hidden[0]) == "plain"
  ownership.read_and_decide(readings["plain"], hidden, hidden, nulls, 6e-4)  # one reading: 1/2049 <= 6e-4
  with pytest.raises(ValueError, match="best of 2 readings"):
    ownership.decide_readings(readings, hidden, hidden, nulls, 6e-4)


def test_among_readings_at_the_p_value_floor_the_strongest_is_the_one_closest_to_the_hidden_image():
  """A marked scene's readings all reach the Monte-Carlo floor 1 / (1 + draws): the reading reported is then the
  one whose revealed image is closest to the hidden one (SSIM), whatever the readings' order, even where z (blind
  to contrast) cannot tell a faded reading from a restored one."""
  hidden = hidden_lib.load_hidden_image("astronaut", 16)[None]
  nulls = dict(pictures=hidden_lib.load_hidden_image("camera", 16)[None])
  noise = np.random.default_rng(0).normal(0.0, 0.15, hidden.shape).astype(np.float32)
  for readings in (dict(noisy=lambda images: images + noise, faded=lambda images: 0.5 * images + 0.25,
                        plain=lambda images: images),
                   dict(plain=lambda images: images, faded=lambda images: 0.5 * images + 0.25)):
    by_name, _ = ownership.decide_readings(readings, hidden, hidden, nulls, 1e-2)
    floor = {r.result["log10_p"][0, 0] for r in by_name.values()}
    assert len(floor) == 1
    assert by_name["faded"].result["z"][0, 0] == pytest.approx(by_name["plain"].result["z"][0, 0], rel=1e-3)
    assert ownership.strongest(by_name, hidden[0]) == "plain"
