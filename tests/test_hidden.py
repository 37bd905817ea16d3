"""Tests of loading the hidden image from files and scikit-image samples."""
import imageio.v3 as iio
import numpy as np
import pytest

from conceal_jax.conceal.hidden import SAMPLE_NAMES, HiddenImageError, load_hidden_image, to_rgb01


def check_image(image, size=64):
  assert image.shape == (size, size, 3) and image.dtype == np.float32
  assert image.min() >= 0.0 and image.max() <= 1.0


def test_error_is_a_value_error():
  assert issubclass(HiddenImageError, ValueError)


def test_rgba_png_composited_on_white(tmp_path):
  rgba = np.zeros((32, 32, 4), np.uint8)
  rgba[..., 0] = 255                      # pure red everywhere ...
  rgba[:16, :, 3] = 255                   # ... opaque in the top half,
  rgba[16:, :, 3] = 0                     # transparent in the bottom half.
  path = tmp_path / "logo.png"
  iio.imwrite(path, rgba)
  image = load_hidden_image(str(path), size=32)
  check_image(image, 32)
  np.testing.assert_allclose(image[:8], np.broadcast_to([1.0, 0.0, 0.0], (8, 32, 3)), atol=1e-6)
  np.testing.assert_allclose(image[-8:], 1.0, atol=1e-6)


def test_half_alpha_and_grey_alpha():
  grey_alpha = np.stack([np.zeros((4, 4)), np.full((4, 4), 0.25)], -1)
  np.testing.assert_allclose(to_rgb01(grey_alpha), 0.75)
  rgba = np.concatenate([np.full((4, 4, 3), 0.2), np.full((4, 4, 1), 0.5)], -1)
  np.testing.assert_allclose(to_rgb01(rgba), 0.6, rtol=1e-6)


@pytest.mark.parametrize("dtype, peak", [(np.uint8, 255), (np.uint16, 65535)])
def test_grey_png(tmp_path, dtype, peak):
  ramp = np.tile(np.linspace(0, peak, 48).astype(dtype), (48, 1))
  path = tmp_path / "grey.png"
  iio.imwrite(path, ramp)
  image = load_hidden_image(str(path), size=48)
  check_image(image, 48)
  np.testing.assert_array_equal(image[..., 0], image[..., 1])
  np.testing.assert_array_equal(image[..., 0], image[..., 2])
  # Same size: the resize is the identity, so the values are the file's divided by the type's maximum.
  np.testing.assert_allclose(image[..., 0], ramp / peak, atol=1e-6)


def test_value_types():
  np.testing.assert_array_equal(to_rgb01(np.array([[True, False]])), [[[1, 1, 1], [0, 0, 0]]])
  np.testing.assert_allclose(to_rgb01(np.array([[[-0.5, 0.5, 1.5]]])), [[[0.0, 0.5, 1.0]]])
  with pytest.raises(HiddenImageError, match="NaN"):
    to_rgb01(np.array([[np.nan]]), "img")
  with pytest.raises(HiddenImageError, match="int16"):
    to_rgb01(np.zeros((2, 2), np.int16), "img")
  with pytest.raises(HiddenImageError, match="shape"):
    to_rgb01(np.zeros((2, 2, 5), np.uint8), "img")


def test_non_square_is_centre_cropped(tmp_path):
  wide = np.zeros((20, 60, 3), np.uint8)
  wide[:, 20:40] = 255                    # the centred 20 x 20 square is white, the sides black
  path = tmp_path / "wide.png"
  iio.imwrite(path, wide)
  np.testing.assert_allclose(load_hidden_image(str(path), size=10), 1.0)


@pytest.mark.parametrize("name", ["astronaut", "coffee", "camera"])
def test_sample_names(name):
  image = load_hidden_image(name)
  check_image(image)
  assert image.std() > 0.05  # a real picture, not a constant
  if name == "camera":
    np.testing.assert_array_equal(image[..., 0], image[..., 2])


def test_samples_are_all_loadable():
  for name in SAMPLE_NAMES:
    check_image(load_hidden_image(name))


def test_missing_file(tmp_path):
  path = str(tmp_path / "nothing.png")
  with pytest.raises(HiddenImageError, match="nothing.png"):
    load_hidden_image(path)


def test_corrupt_file(tmp_path):
  path = tmp_path / "broken.png"
  path.write_bytes(b"this is not a PNG")
  with pytest.raises(HiddenImageError, match="broken.png"):
    load_hidden_image(str(path))


@pytest.mark.parametrize("name", ["not_a_sample", "download_all", "data_dir", "binary_blobs"])
def test_unknown_sample_name(name):
  with pytest.raises(HiddenImageError, match=name):
    load_hidden_image(name)


@pytest.mark.parametrize("size", [0, -3, 2.5, True])
def test_bad_size(size):
  with pytest.raises(HiddenImageError, match="astronaut"):
    load_hidden_image("astronaut", size=size)
