"""The ownership statistic (robust.phase_statistic) against float64 references computed another way: z in the
image domain with explicit circular autocovariances (Bartlett's variance), the periodic component by its defining
Laplacian, the p-values against scipy's distributions and their asymptotic tails; its null by simulation."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import special, stats

from conceal_jax.robust import phase_statistic as ps


def smooth_image(rng, size=16, channels=3):
  """[size, size, channels] a random smooth picture with a bright corner (far from periodic)."""
  noise = rng.normal(size=(size + 4, size + 4, channels))
  kernel = np.ones(5) / 5
  noise = np.apply_along_axis(np.convolve, 0, noise, kernel, "valid")
  noise = np.apply_along_axis(np.convolve, 1, noise, kernel, "valid")
  ramp = np.linspace(0, 1, size)[:, None, None] * np.linspace(0, 1, size)[None, :, None]
  return np.clip(0.5 + 0.3 * noise + 0.4 * ramp, 0, 1)


def circular_autocovariance(x: np.ndarray) -> np.ndarray:
  """[H, W] -> [H, W] C(h) = sum_i x_i x_{i+h} over circular lags, by explicit shifts."""
  h, w = x.shape
  return np.array([[np.sum(x * np.roll(x, (-dy, -dx), (0, 1))) for dx in range(w)] for dy in range(h)])


def reference_z(a: np.ndarray, b: np.ndarray) -> float:
  """z in the image domain: sum_i x_i y_i / sqrt(sum_h C_x(h) C_y(h) / N), x and y the whitened images."""
  x, y = np.real(np.fft.ifft2(a)), np.real(np.fft.ifft2(b))
  return float(np.sum(x * y) / np.sqrt(np.sum(circular_autocovariance(x) * circular_autocovariance(y)) / x.size))


def test_z_equals_the_image_domain_correlation_over_bartletts_deviation():
  rng = np.random.default_rng(0)
  images = np.stack([smooth_image(rng) for _ in range(3)])
  spectra = ps.whitened_spectra(images)
  z = ps.z_scores(spectra, spectra[:2])
  for i in range(3):
    for j in range(2):
      assert z[i, j] == pytest.approx(reference_z(spectra[i], spectra[j]), rel=1e-9, abs=1e-9)
  # an image against itself: every term counts, z = sqrt(M)
  assert z[0, 0] == pytest.approx(np.sqrt(ps.effective_samples(spectra[:1], spectra[:1])[0, 0]), rel=1e-9)


def test_whitened_spectra_keep_unit_phases_above_the_lowest_ring():
  rng = np.random.default_rng(1)
  spectra = ps.whitened_spectra(smooth_image(rng, 12)[None])[0]
  kept = ps.kept_frequencies(12, 12)
  assert not kept[0, 0] and not kept[1, 0] and not kept[1, 1] and kept[2, 0]
  np.testing.assert_allclose(np.abs(spectra[kept]), 1.0, atol=1e-12)
  assert np.all(spectra[~kept] == 0)
  assert ps.effective_samples(spectra[None], spectra[None])[0, 0] == pytest.approx(kept.sum())


def test_periodic_component_has_the_images_interior_laplacian_and_mean():
  rng = np.random.default_rng(2)
  u = smooth_image(rng, 10, 1)[..., 0] + np.linspace(0, 3, 10)[:, None]  # a strong jump across the edges
  p = ps.periodic_component(u)
  periodic_laplacian = sum(np.roll(p, s, a) for s in (1, -1) for a in (0, 1)) - 4 * p
  interior = np.zeros_like(u)  # sum over the neighbours inside the image of (neighbour - pixel)
  for i in range(10):
    for j in range(10):
      for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        if 0 <= i + di < 10 and 0 <= j + dj < 10:
          interior[i, j] += u[i + di, j + dj] - u[i, j]
  np.testing.assert_allclose(periodic_laplacian, interior, atol=1e-10)
  assert p.mean() == pytest.approx(u.mean(), abs=1e-12)
  # batched over leading axes
  np.testing.assert_allclose(ps.periodic_component(np.stack([u, 2 * u]))[1], 2 * p, atol=1e-10)


def test_constant_and_grey_images_are_finite():
  constant = np.full((1, 16, 16, 3), 0.5)
  rng = np.random.default_rng(3)
  other = ps.whitened_spectra(smooth_image(rng)[None])
  flat = ps.whitened_spectra(constant)
  assert np.all(flat == 0)
  assert ps.z_scores(flat, other)[0, 0] == 0.0 and ps.effective_samples(flat, other)[0, 0] == 0.0
  grey = np.repeat(smooth_image(rng, 16, 1), 3, -1)[None]
  assert np.isfinite(ps.z_scores(ps.whitened_spectra(grey), other)).all()


def test_bad_images_are_refused():
  with pytest.raises(ValueError, match="at least 4x4"):
    ps.whitened_spectra(np.zeros((16, 3)))
  with pytest.raises(ValueError, match="at least 3 finite"):
    ps.log_p_predictive(5.0, [0.1, np.nan, 0.2])


def test_z_follows_n01_under_the_random_phase_null():
  """Fixed hidden image, revealed images with the same amplitudes and random phases: z ~ N(0, 1)."""
  rng = np.random.default_rng(4)
  hidden = ps.whitened_spectra(smooth_image(rng, 32)[None])
  revealed = smooth_image(rng, 32)
  amplitude = np.abs(np.fft.fft2(revealed.mean(-1)))
  phases = np.angle(np.fft.fft2(rng.normal(size=(2000, 32, 32))))  # Hermitian: real images
  surrogates = np.real(np.fft.ifft2(amplitude * np.exp(1j * phases)))
  z = ps.z_scores(ps.whitened_spectra(np.repeat(surrogates[..., None], 3, -1)), hidden)[:, 0]
  assert abs(z.mean()) < 4 / np.sqrt(z.size) and abs(z.std() - 1) < 0.05
  assert stats.kstest(z, "norm").pvalue > 1e-3


@pytest.mark.parametrize("z", [-3.0, 0.0, 1.0, 4.75, 8.0, 20.0])
def test_model_log_p_matches_scipy(z):
  assert ps.log_p_model(z) == pytest.approx(stats.norm.logsf(z), rel=1e-10)


@pytest.mark.parametrize("z", [40.0, 300.0, 1e4])
def test_model_log_p_far_in_the_tail_matches_the_mills_series(z):
  """log P(Z >= z) = -z^2/2 - log(z sqrt(2 pi)) + log(1 - 1/z^2 + 3/z^4 - ...)."""
  series = -z * z / 2 - np.log(z * np.sqrt(2 * np.pi)) + np.log1p(-1 / z ** 2 + 3 / z ** 4 - 15 / z ** 6)
  assert ps.log_p_model(z) == pytest.approx(series, rel=1e-12)


@pytest.mark.parametrize("z", [-2.0, 0.3, 3.0, 6.0, 15.0])
def test_predictive_log_p_matches_scipys_student_t(z):
  null = np.random.default_rng(5).normal(0.2, 1.1, 40)
  k = null.size
  t = (z - null.mean()) / (null.std(ddof=1) * np.sqrt(1 + 1 / k))
  assert ps.log_p_predictive(z, null) == pytest.approx(stats.t.logsf(t, k - 1), rel=1e-9)


@pytest.mark.parametrize("t", [1e3, 1e8, 1e40])
def test_predictive_log_p_far_in_the_tail_matches_the_student_t_asymptote(t):
  """Past betainc's underflow: log P(T >= t) -> log(c nu^((nu-1)/2)) - nu log t, c the t density's constant."""
  null = np.array([-1.0, 0.0, 1.0, 0.5, -0.5])  # mean 0, sd sqrt(0.625)
  k = null.size
  nu = k - 1.0
  z = t * null.std(ddof=1) * np.sqrt(1 + 1 / k)
  log_c = special.gammaln((nu + 1) / 2) - special.gammaln(nu / 2) - 0.5 * np.log(nu * np.pi)
  asymptote = log_c + (nu - 1) / 2 * np.log(nu) - nu * np.log(t)
  got = float(ps.log_p_predictive(z, null))
  assert np.isfinite(got) and got == pytest.approx(asymptote, rel=1e-6)
