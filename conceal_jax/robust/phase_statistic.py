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
frequencies both images carry (effective_samples), and tends to N(0, 1) (log_p_model). That model misses the
tail where both images hold long edges: whitened, an edge is a line of pixels of one sign, and two such lines
that happen to lie along each other add up to a large z however unrelated the pictures. z_surfaces gives z at
every circular shift of one image against the other (the whole phase-correlation surface, by one inverse FFT),
from which a null with the images' own edges in it is drawn; log_p_empirical is the Monte-Carlo p-value of a
statistic against such draws.

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


def dihedral(images: np.ndarray) -> np.ndarray:
  """[..., S, S, C] square images -> [8, ..., S, S, C]: their quarter turns (0 to 3) and those of their mirror
  images (left-right flipped), the identity first."""
  images = np.asarray(images)
  if images.ndim < 3 or images.shape[-3] != images.shape[-2]:
    raise ValueError(f"dihedral takes square images [..., S, S, C], got {images.shape}")
  return np.stack([np.rot90(images[..., ::-1, :] if flip else images, turns, axes=(-3, -2))
                   for flip in (False, True) for turns in range(4)])


def z_surfaces(a: np.ndarray, b: np.ndarray) -> np.ndarray:
  """[A, H, W], [B, H, W] whitened spectra -> [A, B, H, W]: z_scores of a against b's image circularly shifted by
  (dy, dx), for every shift. A shift turns b's coefficients, not their moduli, so the deviation stays and the
  numerator is H W times the inverse FFT of a conj(b) (the phase-correlation surface; both spectra are of real
  images, so the real inverse FFT of the half spectrum, one b at a time to bound memory)."""
  fa, fb = _flat(a), _flat(b)
  h, w = np.shape(a)[-2:]
  variance = (np.abs(fa) ** 2) @ (np.abs(fb) ** 2).T
  scale = np.where(variance > 0, (h * w) / np.sqrt(np.where(variance > 0, variance, 1.0)), 0.0)
  half = fa.reshape(-1, h, w)[..., :w // 2 + 1]
  return np.stack([np.fft.irfft2(half * np.conj(row.reshape(h, w)[:, :w // 2 + 1]), s=(h, w))
                   * scale[:, j, None, None] for j, row in enumerate(fb)], 1)


def log_p_empirical(z, null) -> np.ndarray:
  """Natural log of the Monte-Carlo p-value (1 + #{null >= z}) / (1 + n) of each z against n null draws (Davison &
  Hinkley, Bootstrap Methods, 1997, eq. 4.11): where z and the draws are exchangeable under the null, P(p <= a)
  <= a at any n; the smallest it can give is 1 / (1 + n)."""
  null = np.sort(np.asarray(null, np.float64).ravel())
  if null.size == 0 or not np.all(np.isfinite(null)):
    raise ValueError(f"the empirical null needs finite draws, got {null.size}")
  reach = null.size - np.searchsorted(null, np.asarray(z, np.float64), side="left")
  return np.log1p(reach) - np.log1p(null.size)
