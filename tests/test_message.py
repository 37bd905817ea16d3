"""Message mode (conceal.message): the BCH code chosen against published tables, the layout, decoding through up
to t bit errors and failing past them, the binomial p-value against an exact sum, the config and key plumbing,
and the reveal job reading a message-mode key."""
from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from conceal_jax import RenderOptions
from conceal_jax import main as main_lib
from conceal_jax.conceal import key as key_lib, message
from conceal_jax.configs import default
from conceal_jax.data import ply
from tests.helpers import make_camera, random_gaussians

# primitive binary BCH codes of length 127 (Lin & Costello, Error Control Coding, 2nd ed., Appendix C): (k, t)
BCH_127 = ((36, 15), (43, 14), (50, 13), (57, 11), (64, 10))


# each code is built once per process, about 11 s of galois' compiled construction: beyond 32 bits, slow tests
@pytest.mark.parametrize("bits, k, t", [(32, 36, 15)] + [pytest.param(*case, marks=pytest.mark.slow) for case in
                                                         ((36, 36, 15), (48, 50, 13), (50, 50, 13), (64, 64, 10))])
def test_the_code_corrects_the_most_errors_among_those_carrying_the_bits(bits, k, t):
  bch = message.code(bits)
  assert (bch.n, bch.k, bch.t) == (127, k, t)
  assert t == max(tt for kk, tt in BCH_127 if kk >= bits)
  assert message.codeword_length(bits) == 127 - (k - bits)


def test_the_layout_spreads_each_bit_over_its_share_of_cells():
  for n in (123, 125, 127):
    owner = message.cell_bits(n)
    counts = np.bincount(owner, minlength=n)
    assert counts.min() == message.GRID ** 2 // n and counts.max() == -(-message.GRID ** 2 // n)
  bits = message.random_message(48, 0)
  image = message.message_image(bits, 64)
  assert image.shape == (64, 64, 3) and set(np.unique(image)) <= {0.0, 1.0}
  codeword = message.encode(bits)
  np.testing.assert_array_equal(codeword[:48], bits)  # systematic
  soft = message.soft_bits(image, codeword.size)
  np.testing.assert_array_equal(soft > 0, codeword.astype(bool))
  np.testing.assert_allclose(np.abs(soft), 0.5 * np.bincount(message.cell_bits(codeword.size)))


def flip_bits(image: np.ndarray, n: int, which) -> np.ndarray:
  """The image with every cell of the codeword bits `which` inverted."""
  cells = np.isin(message.cell_bits(n), list(which)).reshape(message.GRID, message.GRID)
  side = image.shape[0] // message.GRID
  mask = np.kron(cells, np.ones((side, side), bool))[..., None]
  return np.where(mask, 1.0 - image, image)


@pytest.mark.parametrize("bits", [32, pytest.param(48, marks=pytest.mark.slow)])
def test_decoding_corrects_up_to_t_raw_errors_and_no_more(bits):
  rng = np.random.default_rng(bits)
  hidden = message.random_message(bits, 3)
  image = message.message_image(hidden, 64)
  n, t = message.codeword_length(bits), message.code(bits).t
  noisy = np.clip(image + rng.normal(0, 0.3, image.shape), 0, 1)
  read = message.read_message(flip_bits(noisy, n, rng.choice(n, t, replace=False)), hidden)
  assert read["message_exact"] and read["decoded"] == message.to_hex(hidden) and read["errors_corrected"] == t
  assert read["raw_bit_matches"] == n - t and read["raw_bit_accuracy"] == pytest.approx((n - t) / n)
  beyond = message.read_message(flip_bits(image, n, rng.choice(n, 3 * t, replace=False)), hidden)
  assert not beyond["message_exact"] and beyond["raw_bit_matches"] == n - 3 * t


@pytest.mark.parametrize("matches", [0, 60, 62, 90, 125])
def test_binomial_p_value_matches_the_exact_sum(matches):
  n = 125
  exact = math.log10(sum(math.comb(n, i) for i in range(matches, n + 1))) - n * math.log10(2)
  hidden = message.random_message(48, 1)
  codeword = message.encode(hidden)
  image = flip_bits(message.message_image(hidden, 64), n, range(n - matches))
  read = message.read_message(image, hidden)
  assert read["raw_bit_matches"] == matches
  assert read["log10_p_binomial"] == pytest.approx(exact, rel=1e-9, abs=1e-12)
  assert codeword.size == n


def test_hex_and_config():
  bits = np.array([1, 0, 1, 1, 0, 0, 0, 1, 1], np.uint8)
  assert message.to_hex(bits) == "163"
  np.testing.assert_array_equal(message.from_hex("163", 9), bits)
  for bad in ("0163", "363", "xyz"):
    with pytest.raises(ValueError, match="mark.message"):
      message.from_hex(bad, 9)
  mark = default.get_config().mark
  assert message.configured_message(mark, 0) is None
  mark.message_bits = 32
  np.testing.assert_array_equal(message.configured_message(mark, 5), message.random_message(32, 5))
  mark.message = "deadbeef"
  assert message.to_hex(message.configured_message(mark, 5)) == "deadbeef"
  mark.message_bits = 200
  with pytest.raises(ValueError, match="message_bits"):
    message.configured_message(mark, 0)
  mark.message_bits, mark.message = 0, "ab"
  with pytest.raises(ValueError, match="message_bits is 0"):
    message.configured_message(mark, 0)
  with pytest.raises(ValueError, match="multiple of"):
    message.message_image(bits, 40)


def test_reveal_reads_the_message_a_key_records(tmp_path):
  """A key of message mode: reveal.json and verify.json carry the message read back from what the key reveals
  (here a random scene without a decoder, which holds no message: accuracy near chance, not the message)."""
  g = jax.tree.map(np.asarray, random_gaussians(2, 300, degree=1, spread=0.5, log_scale=(-2.5, -1.8)))
  ply.save_ply(tmp_path / "scene.ply", g)
  hidden = message.random_message(32, 0)
  key_lib.save_key(str(tmp_path / "key.json"), make_camera(32, 32),
                   dict(hidden_size=16, uses_decoder=False, render_options=dict(background=[1.0, 1.0, 1.0]),
                        **message.key_fields(hidden)))
  assert message.to_hex(message.message_of_key(key_lib.load_key(str(tmp_path / "key.json"))[1])) == \
      message.to_hex(hidden)
  config = default.get_config()
  config.mode = "reveal"
  config.reveal.ply, config.reveal.key = str(tmp_path / "scene.ply"), str(tmp_path / "key.json")
  result = main_lib.run(config, str(tmp_path / "out"))
  read = result["message"]
  assert read["bits"] == 32 and read["message"] == message.to_hex(hidden) and read["codeword_bits"] == 123
  assert not read["message_exact"] and 0.25 < read["raw_bit_accuracy"] < 0.75 and read["log10_p_binomial"] > -3


@pytest.mark.job
def test_a_message_mode_concealment_hides_the_message_image_and_records_the_message(tmp_path):
  """A few steps of conceal with mark.message_bits: hidden.png is the message's image, key.json records the
  message, message.json and the metrics read it back, and reveal reads the same from the student."""
  import json

  from conceal_jax.conceal import hidden as hidden_lib, train as conceal_train
  from conceal_jax.data import demo_scene
  from conceal_jax.gs import init
  from tests.test_conceal import tiny_config

  scene_path = demo_scene.generate_demo_scene(tmp_path / "scene", num_train=6, num_test=2, size=32)
  points, colors = init.random_box_points(np.random.default_rng(0), 1200, 1.0)
  ply.save_ply(tmp_path / "teacher.ply", init.gaussians_from_points(points, colors, sh_degree=1, opacity=0.5))
  config = tiny_config((scene_path, tmp_path / "teacher.ply"), iterations=3)
  config.mark.message_bits, config.mark.message = 32, "c0ffee42"
  out = tmp_path / "conceal"
  result = conceal_train.train_and_evaluate(config, str(out))
  hidden = message.from_hex("c0ffee42", 32)
  np.testing.assert_array_equal(hidden_lib.load_hidden_image(str(out / "hidden.png"), 16),
                                message.message_image(hidden, 16))
  assert json.loads((out / "key.json").read_text())["message"] == dict(bits=32, hex="c0ffee42")
  read = json.loads((out / "message.json").read_text())
  assert read == result["metrics"]["message"] and read["message"] == "c0ffee42" and read["codeword_bits"] == 123
  config = default.get_config()
  config.mode = "reveal"
  config.reveal.ply, config.reveal.key = str(out / "student.ply"), str(out / "key.json")
  config.reveal.decoder = str(out / "decoder.msgpack")
  revealed = main_lib.run(config, str(tmp_path / "reveal"))
  assert revealed["message"]["raw_bit_matches"] == read["raw_bit_matches"]


def test_the_closing_summary_says_what_the_message_read():
  from conceal_jax.report import summary
  hidden = message.random_message(48, 2)
  read = message.read_message(message.message_image(hidden, 64), hidden)
  lines = summary.reveal_lines("w", dict(ply="s.ply", message=read))
  assert len(lines) == 3 and "raw bit accuracy 1.0000" in lines[1] and f"decoded {message.to_hex(hidden)}" in lines[1]
  assert "the message hidden" in lines[1] and summary.message_lines(dict(ply="s.ply")) == []
