"""The ownership statistic (robust.phase_statistic) against float64 references computed another way: z in the
image domain with explicit circular autocovariances (Bartlett's variance), the periodic component by its defining
Laplacian, the p-values against scipy's distributions and their asymptotic tails; its null by simulation."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

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
  with pytest.raises(ValueError, match="finite draws"):
    ps.log_p_empirical(5.0, [0.1, np.nan, 0.2])
  with pytest.raises(ValueError, match="square"):
    ps.dihedral(np.zeros((4, 5, 3)))


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


def test_z_surfaces_are_z_at_every_circular_shift():
  """Each surface value against z_scores of the whitened image rolled in the image domain and transformed back."""
  rng = np.random.default_rng(5)
  a = ps.whitened_spectra(np.stack([smooth_image(rng, 8) for _ in range(3)]))
  b = ps.whitened_spectra(np.stack([smooth_image(rng, 8) for _ in range(2)]))
  surfaces = ps.z_surfaces(a, b)
  assert surfaces.shape == (3, 2, 8, 8)
  for j in range(2):
    image = np.real(np.fft.ifft2(b[j]))
    for dy in range(8):
      for dx in range(8):
        shifted = np.fft.fft2(np.roll(image, (dy, dx), (0, 1)))[None]
        np.testing.assert_allclose(surfaces[:, j, dy, dx], ps.z_scores(a, shifted)[:, 0], rtol=1e-9, atol=1e-9)
  np.testing.assert_allclose(surfaces[:, :, 0, 0], ps.z_scores(a, b), rtol=1e-12, atol=1e-12)
  # Parseval: over the shifts z^2 averages to 1 for unit-modulus spectra
  np.testing.assert_allclose((surfaces ** 2).mean((-2, -1)), 1.0, rtol=1e-9)


def test_dihedral_gives_the_eight_turns_and_mirrors():
  image = np.arange(3 * 3 * 2, dtype=float).reshape(3, 3, 2)
  turned = ps.dihedral(image)
  assert turned.shape == (8, 3, 3, 2)
  np.testing.assert_array_equal(turned[0], image)
  np.testing.assert_array_equal(turned[1], np.rot90(image))
  np.testing.assert_array_equal(turned[4], image[:, ::-1])
  assert len({t.tobytes() for t in turned}) == 8
  np.testing.assert_array_equal(ps.dihedral(np.stack([image, -image]))[:, 1], -turned)


def test_empirical_log_p_counts_the_draws_reaching_z():
  null = np.random.default_rng(6).normal(size=999)
  for z in (-5.0, 0.0, 1.5, float(np.sort(null)[-3]), 10.0):
    expected = (1 + sum(1 for x in null if x >= z)) / (1 + len(null))
    assert np.exp(ps.log_p_empirical(z, null)) == pytest.approx(expected, rel=1e-12)
  assert np.exp(ps.log_p_empirical(10.0, null)) == pytest.approx(1e-3)
  # valid: a draw exchangeable with the null is at most alpha with probability at most alpha
  rng = np.random.default_rng(7)
  p = np.exp([ps.log_p_empirical(rng.normal(), rng.normal(size=99)) for _ in range(2000)])
  assert np.mean(p <= 0.05) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / 2000)
