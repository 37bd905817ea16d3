"""The ownership statistic: the phase correlation of the revealed image R with the hidden image I, and its null.

Both images are reduced to their luminance, made periodic (periodic_component: the edge of a non-periodic image
would otherwise put the same cross of frequencies into every spectrum), and whitened: every Fourier coefficient
is set to unit modulus (the phase-only transform of phase correlation; Kuglin & Hines 1975), and the mean and
lowest ring of frequencies (radius <= MIN_RADIUS cycles per image) are left out, where unrelated pictures of
centred content share their phases. z_scores is the correlation of the whitened images divided by its standard
deviation under the null "the phases of R are independent of I's" (the random-phase model): with the
coefficient products Re(A_f conj(B_f)) independent over the half spectrum, their sum has variance
sum_f |A_f|^2 |B_f|^2 whatever the spectra (Bartlett's variance of a cross-correlation, 1935, with circular
autocovariances), so z is a sum of about M independent terms of unit total variance, M the number of
frequencies both images carry (effective_samples), and tends to N(0, 1) (log_p_model). The null estimated
from a decoder's own outputs on unmarked inputs enters through log_p_predictive (Student's t predictive
distribution of a new draw from a normal sample).

Everything here is float64 numpy; spectra are [..., H, W] complex, images [..., H, W, C] in [0, 1].
"""
from __future__ import annotations

import numpy as np
from scipy import special

MIN_RADIUS = 1.5
# Fourier coefficients below this fraction of an image's largest are rounding, not content: left out (a grey
# image's colour channels, a constant image).
NUMERICAL_ZERO = 1e-9


def periodic_component(images: np.ndarray) -> np.ndarray:
  """[..., H, W] -> the periodic component p of the periodic-plus-smooth decomposition u = p + s (Moisan,
  "Periodic plus smooth image decomposition", J. Math. Imaging Vis. 2011, eq. 12): s is the smooth image whose
  periodic Laplacian is the jump across the image's opposite edges, with mean 0, so p is periodic, has u's mean
  and u's Laplacian inside."""
  u = np.asarray(images, np.float64)
  h, w = u.shape[-2:]
  v = np.zeros_like(u)  # the boundary image: the jumps across opposite edges
  v[..., 0, :] += u[..., -1, :] - u[..., 0, :]
  v[..., -1, :] += u[..., 0, :] - u[..., -1, :]
  v[..., :, 0] += u[..., :, -1] - u[..., :, 0]
  v[..., :, -1] += u[..., :, 0] - u[..., :, -1]
  q, r = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
  denominator = 2 * np.cos(2 * np.pi * q / h) + 2 * np.cos(2 * np.pi * r / w) - 4
  denominator[0, 0] = 1.0
  s_hat = np.fft.fft2(v) / denominator
  s_hat[..., 0, 0] = 0.0
  return u - np.real(np.fft.ifft2(s_hat))


def kept_frequencies(h: int, w: int) -> np.ndarray:
  """[H, W] bool: the frequencies the statistic uses, those of radius > MIN_RADIUS cycles per image."""
  fy, fx = np.fft.fftfreq(h) * h, np.fft.fftfreq(w) * w
  return np.hypot(fy[:, None], fx[None, :]) > MIN_RADIUS


def whitened_spectra(images: np.ndarray) -> np.ndarray:
  """[..., H, W, C] images -> [..., H, W] complex spectra of unit modulus where kept (kept_frequencies) and
  not numerically zero, 0 elsewhere: luminance (the channel mean), periodic component, FFT, phase only."""
  images = np.asarray(images, np.float64)
  if images.ndim < 3 or min(images.shape[-3:-1]) < 4:
    raise ValueError(f"the ownership statistic takes images [..., H, W, C] of at least 4x4, got {images.shape}")
  spectra = np.fft.fft2(periodic_component(images.mean(-1)))
  modulus = np.abs(spectra)
  largest = modulus.max(axis=(-2, -1), keepdims=True)
  carried = (modulus > NUMERICAL_ZERO * largest) & kept_frequencies(*images.shape[-3:-1])
  return np.where(carried, spectra / np.where(carried, modulus, 1.0), 0.0)


def _flat(spectra: np.ndarray) -> np.ndarray:
  spectra = np.asarray(spectra)
  return spectra.reshape((-1,) + spectra.shape[-2:]).reshape(-1, spectra.shape[-2] * spectra.shape[-1])


def effective_samples(a: np.ndarray, b: np.ndarray) -> np.ndarray:
  """[A, H, W], [B, H, W] whitened spectra -> [A, B] the number of independent terms z sums,
  (sum_f w_f)^2 / sum_f w_f^2 with w_f = |A_f|^2 |B_f|^2 (for unit-modulus spectra: the frequencies both carry)."""
  wa, wb = np.abs(_flat(a)) ** 2, np.abs(_flat(b)) ** 2
  return (wa @ wb.T) ** 2 / np.maximum((wa ** 2) @ (wb ** 2).T, 1e-300)


def z_scores(a: np.ndarray, b: np.ndarray) -> np.ndarray:
  """[A, H, W], [B, H, W] whitened spectra -> [A, B] z = sum_f Re(A_f conj(B_f)) / sqrt(sum_f |A_f|^2 |B_f|^2),
  the correlation of the whitened images over its standard deviation under the random-phase null (module
  doc); 0 where the two share no frequency (a constant image)."""
  fa, fb = _flat(a), _flat(b)
  numerator = np.real(fa @ np.conj(fb).T)
  variance = (np.abs(fa) ** 2) @ (np.abs(fb) ** 2).T
  return np.where(variance > 0, numerator / np.sqrt(np.where(variance > 0, variance, 1.0)), 0.0)


def log_p_model(z) -> np.ndarray:
  """Natural log of the one-sided p-value P(Z >= z), Z ~ N(0, 1): the random-phase null of z_scores (finite
  far into the tail: scipy's log_ndtr)."""
  return special.log_ndtr(-np.asarray(z, np.float64))


def log_p_predictive(z, null_z) -> np.ndarray:
  """Natural log of the one-sided p-value of z under the null estimated from K >= 3 scores `null_z` of
  unmarked inputs: a new draw from the normal sample's population is (z - mean) / (sd sqrt(1 + 1/K)) ~ t with
  K - 1 degrees of freedom (the prediction interval of a normal sample; e.g. Geisser, Predictive Inference,
  1993, sec. 2.1). Far in the tail, where the regularised incomplete beta function underflows, its leading
  term x^a / (a B(a, 1/2)) (x = nu / (nu + t^2), a = nu / 2) replaces it (relative error O(x))."""
  null_z = np.asarray(null_z, np.float64).ravel()
  if null_z.size < 3 or not np.all(np.isfinite(null_z)):
    raise ValueError(f"the estimated null needs at least 3 finite scores, got {null_z.size}")
  k = null_z.size
  spread = max(float(np.std(null_z, ddof=1)), 1e-12)
  t = (np.asarray(z, np.float64) - null_z.mean()) / (spread * np.sqrt(1.0 + 1.0 / k))
  nu = k - 1.0
  x = nu / (nu + t * t)
  half = 0.5 * special.betainc(nu / 2, 0.5, x)  # P(T >= |t|)
  with np.errstate(divide="ignore"):
    tail = np.where(half > 0, np.log(np.maximum(half, 1e-320)),
                    np.log(0.5) + nu / 2 * np.log(x) - np.log(nu / 2) - special.betaln(nu / 2, 0.5))
  return np.where(t >= 0, tail, np.log1p(-np.exp(tail)))
