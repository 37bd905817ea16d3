"""Message mode (mark.message_bits): an N-bit message hidden as the hidden image, error-corrected, read back as bits.

Encoding: the message's N bits are the information bits of a binary BCH code of length CODE_LENGTH (galois.BCH;
of the codes with k >= N the one correcting the most errors t), shortened to N information bits, so a codeword of
n = CODE_LENGTH - (k - N) bits corrects any t bit errors. Layout: the S x S hidden image is a GRID x GRID board
of square cells, black for 0 and white for 1; the codeword's bits fill the cells cyclically in a fixed
pseudo-random order (LAYOUT_SEED), so every bit appears in GRID^2 / n cells or one more, scattered over the image
(a damaged region costs many bits a little, not a few bits all). Reading: each cell's mean luminance less 0.5,
summed over the cells of its bit, is the bit's soft value; its sign the raw bit; BCH decoding corrects up to t raw
errors into the message. The raw bits, compared with the codeword hidden, give the bit accuracy and the one-sided
binomial p-value of that many matches among n fair coin flips (what a scene not carrying the message scores).
"""
from __future__ import annotations

import functools

import numpy as np
from scipy import stats

CODE_LENGTH = 127  # the BCH code's primitive length 2^7 - 1
GRID = 16          # cells per side of the message image
LAYOUT_SEED = 40   # the cells' order


@functools.lru_cache(maxsize=None)
def code(bits: int):
  """The galois.BCH code of length CODE_LENGTH with the largest correcting power t whose k >= bits (its
  shortened form carries exactly `bits`)."""
  import galois  # a numba-compiled library: imported where a message is encoded or read
  if not 1 <= bits <= CODE_LENGTH - 7:
    raise ValueError(f"mark.message_bits must lie in [1, {CODE_LENGTH - 7}], got {bits}")
  best = None
  for d in range(3, CODE_LENGTH + 1, 2):  # designed distances; k falls as d grows
    bch = galois.BCH(CODE_LENGTH, d=d)
    if bch.k < bits:
      break
    best = bch
  return best


def codeword_length(bits: int) -> int:
  """n: the shortened codeword's length for a message of `bits`."""
  bch = code(bits)
  return bch.n - (bch.k - bits)


def cell_bits(n: int) -> np.ndarray:
  """[GRID * GRID] the codeword bit each cell carries, cells in row-major order: bits 0..n-1 cyclically along a
  fixed random permutation of the cells."""
  if n > GRID * GRID:
    raise ValueError(f"a codeword of {n} bits does not fit {GRID * GRID} cells")
  order = np.random.default_rng(LAYOUT_SEED).permutation(GRID * GRID)
  owner = np.empty(GRID * GRID, np.int64)
  owner[order] = np.arange(GRID * GRID) % n
  return owner


def encode(message: np.ndarray) -> np.ndarray:
  """[N] bits (0 / 1) -> [n] the shortened BCH codeword (systematic: the message first)."""
  import galois
  message = np.asarray(message, np.uint8)
  return np.asarray(code(message.size).encode(galois.GF2(message)), np.uint8)


def codeword_image(codeword: np.ndarray, size: int) -> np.ndarray:
  """[n] bits -> [size, size, 3] float32 image in {0, 1}: the cells of the layout (module doc)."""
  if size % GRID:
    raise ValueError(f"a message image needs mark.hidden_size a multiple of {GRID}, got {size}")
  cells = np.asarray(codeword, np.float32)[cell_bits(len(codeword))].reshape(GRID, GRID)
  board = np.kron(cells, np.ones((size // GRID, size // GRID), np.float32))
  return np.repeat(board[..., None], 3, -1)


def message_image(message: np.ndarray, size: int) -> np.ndarray:
  """The hidden image of a message: codeword_image(encode(message))."""
  return codeword_image(encode(message), size)


def soft_bits(image: np.ndarray, n: int) -> np.ndarray:
  """[S, S, 3] image -> [n] soft values, the cells' mean luminance less 0.5 summed over each bit's cells
  (positive: 1)."""
  image = np.asarray(image, np.float64)
  size = image.shape[0]
  if image.shape[:2] != (size, size) or size % GRID:
    raise ValueError(f"a message image is square with a side a multiple of {GRID}, got {image.shape}")
  cells = image.mean(-1).reshape(GRID, size // GRID, GRID, size // GRID).mean((1, 3)).ravel() - 0.5
  return np.bincount(cell_bits(n), weights=cells, minlength=n)


def random_message(bits: int, seed: int) -> np.ndarray:
  """[bits] a message drawn from `seed` (mark.message left empty)."""
  return np.random.default_rng([seed, bits]).integers(0, 2, bits).astype(np.uint8)


def from_hex(text: str, bits: int) -> np.ndarray:
  """[bits] the message written as hexadecimal (most significant bit first, exactly ceil(bits / 4) digits, the
  unused high bits of the first digit zero)."""
  digits = -(-bits // 4)
  try:
    value = int(text, 16)
  except ValueError as error:
    raise ValueError(f"mark.message must be hexadecimal, got {text!r}") from error
  if len(text) != digits or value >> bits:
    raise ValueError(f"mark.message must be {digits} hex digits holding {bits} bits, got {text!r}")
  return np.array([(value >> (bits - 1 - i)) & 1 for i in range(bits)], np.uint8)


def to_hex(message: np.ndarray) -> str:
  """from_hex's inverse."""
  bits = len(message)
  value = int("".join(str(int(b)) for b in message), 2) if bits else 0
  return f"{value:0{-(-bits // 4)}x}"


def read_message(revealed: np.ndarray, hidden_message: np.ndarray) -> dict:
  """What a revealed image [S, S, 3] says of the message hidden (hidden_message [N] bits): the code, the raw
  codeword bits' accuracy against the codeword hidden, the one-sided binomial p-value (log10) of that many matches
  among n fair coin flips, the message after BCH decoding (hex; None where decoding failed: more than t raw
  errors detected), how many errors it corrected, and whether it is the message hidden."""
  import galois
  hidden_message = np.asarray(hidden_message, np.uint8)
  bits = hidden_message.size
  bch, codeword = code(bits), encode(hidden_message)
  n = codeword.size
  raw = (soft_bits(revealed, n) > 0).astype(np.uint8)
  matches = int(np.sum(raw == codeword))
  decoded, corrected = bch.decode(galois.GF2(raw), errors=True)
  corrected = int(corrected)
  decoded = np.asarray(decoded, np.uint8) if corrected >= 0 else None
  return dict(bits=bits, code=f"BCH({n}, {bits}), shortened from BCH({bch.n}, {bch.k})", corrects=int(bch.t),
              codeword_bits=n, raw_bit_matches=matches, raw_bit_accuracy=matches / n,
              log10_p_binomial=float(stats.binom.logsf(matches - 1, n, 0.5) / np.log(10)),
              message=to_hex(hidden_message), decoded=None if decoded is None else to_hex(decoded),
              errors_corrected=corrected,
              message_exact=bool(decoded is not None and np.array_equal(decoded, hidden_message)))


def configured_message(mark, seed: int) -> np.ndarray | None:
  """The message a conceal run hides: None with mark.message_bits 0 (mark.hidden is hidden); else
  mark.message_bits bits, from mark.message (hex) or, left empty, drawn from `seed` (random_message)."""
  bits = mark.get("message_bits", 0)
  if isinstance(bits, bool) or not isinstance(bits, int) or bits < 0:
    raise ValueError(f"mark.message_bits must be a non-negative integer, got {bits!r}")
  if not bits:
    if mark.get("message", ""):
      raise ValueError("mark.message is set but mark.message_bits is 0")
    return None
  code(bits)  # checks the length
  return from_hex(mark.message, bits) if mark.get("message", "") else random_message(bits, seed)


def key_fields(message: np.ndarray) -> dict:
  """What key.json records of a hidden message (the owner's, like the key): its length and its bits in hex."""
  return dict(message=dict(bits=int(message.size), hex=to_hex(message)))


def message_of_key(info: dict) -> np.ndarray | None:
  """The message a key's info records (key_fields), None where the key hides an image."""
  if "message" not in info:
    return None
  return from_hex(info["message"]["hex"], int(info["message"]["bits"]))
