"""PSF sampling plan and exact pixel integration (DESIGN.md §1, "Sampling", "Square cells").

The pupil is P×P square cells of pitch d (d = Δ/q with pupil oversampling q) with a constant
complex transmission u_c each. Its far field at the sensor, in units t = x·d/(λ z) (one period
L = λz/d of the cell grid per unit of t), is exactly

    I(t_x, t_y) = sinc²(t_x)·sinc²(t_y) · |Σ_c u_c e^{−2πi (t_x c_x + t_y c_y)}|²

(the cells' own transform times the periodic cell-grid sum). The periodic factor is a
trigonometric polynomial of degree P−1 per axis, so N ≥ 2P−1 samples per period (one N-point
FFT, N the same for every band) determine it exactly, every diffraction order included. A pixel
of width h = pixel·d/(λz) then integrates it exactly:

    ∫_pixel sinc²(t)·I_per(t) dt = Σ_a W[j, a] I_a,   W[j, a] = (1/N) ∫_pixel sinc²(t) D_N(t − a/N) dt

with the periodic (Dirichlet) interpolation kernel D_N. ``W`` (K, N) is computed once per
wavelength (Gauss–Legendre over each pixel, exact to float precision), so the kernel is
``W I Wᵀ``: every order that falls in the kernel, the cells' envelope, pixel integration and
the exact per-band pitch, with no rounding of FFT sizes and no supersampling. An explicit
``supersample`` s replaces the exact pixel integral by the s×s midpoint rule (s = 1: point
values at pixel centres), for comparisons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hsicam.errors import ConfigError


@dataclass(frozen=True)
class PSFSampling:
    """Sizes of the PSF computation, common to all bands."""

    pupil_samples: int  # P: cells × q across the pupil grid
    pupil_pitch_m: float  # d = Δ/q
    fft_size: int  # N ≥ 2P − 1: exact samples of one period of the intensity
    kernel_px: int  # K (odd)
    min_kernel_px: int  # smallest K holding one period λ_max·z/d of the cell grid's far field
    supersample: int | None  # None: exact pixel integration; s: s×s midpoint rule
    nyquist_supersample: int  # smallest odd s whose sub-pixel is below λ_min·z/(4a)

    @property
    def fft_sizes(self) -> tuple[int, ...]:
        """Kept for callers of the old per-band plan: one size, N, for all bands."""
        return (self.fft_size,)


def odd_ceil(x: float) -> int:
    """Smallest odd integer ≥ x (with a 1e-9 tolerance against round-off)."""
    k = int(math.ceil(x - 1e-9))
    return k if k % 2 == 1 else k + 1


def fast_fft_length(n: int) -> int:
    """Smallest 7-smooth integer ≥ n (2^a·3^b·5^c·7^d: a fast FFT length). Even lengths are
    allowed: with N ≥ 2P − 1 the intensity has no harmonic at N/2 (measured: 672 is 1.4× faster
    than the odd 675 for the paper pupil, P = 333)."""
    m = max(1, int(n))
    while True:
        r = m
        for f in (2, 3, 5, 7):
            while r % f == 0:
                r //= f
        if r == 1:
            return m
        m += 1


def plan_psf_sampling(
    wavelengths_m: np.ndarray,
    sensor_distance_m: float,
    pixel_m: float,
    cell_m: float,
    n_cells: int,
    pupil_oversample: int = 1,
    supersample: int | None = None,
    kernel_px: int | None = None,
    aperture_radius_m: float | None = None,
) -> PSFSampling:
    """Choose N and K (see module docstring). Raises :class:`ConfigError` for impossible choices.

    Args:
        wavelengths_m: wavelengths that are simulated (m), shape (C,).
        sensor_distance_m: z_i, rear principal plane to sensor (m).
        pixel_m: sensor pixel pitch (m).
        cell_m: DOE cell size Δ (m).
        n_cells: cells across the pupil grid.
        pupil_oversample: q samples per cell (finer aperture edge and defocus; same DOE cells).
        supersample: None for exact pixel integration, or an odd s for the s×s midpoint rule.
        kernel_px: odd K, or None for the smallest K that holds λ_max·z/Δ.
        aperture_radius_m: a, for the Nyquist supersampling reported (default: half the grid).
    """
    lam = np.asarray(wavelengths_m, dtype=np.float64).reshape(-1)
    for name, v in (("sensor distance", sensor_distance_m), ("pixel pitch", pixel_m), ("DOE cell", cell_m)):
        if not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"{name} must be positive, got {v}")
    q = int(pupil_oversample)
    n_pupil = n_cells * q
    n_fft = fast_fft_length(2 * n_pupil - 1)
    min_k = odd_ceil(lam.max() * sensor_distance_m / (cell_m * pixel_m))
    if kernel_px is None:
        k = min_k
    else:
        k = int(kernel_px)
        if k % 2 == 0 or k < 1:
            raise ConfigError(f"camera.psf.kernel_px must be a positive odd number, got {k}")
        if k < min_k:
            raise ConfigError(
                f"camera.psf.kernel_px={k} is smaller than the optics need: at least {min_k} px "
                f"(the FFT field λ_max·z/Δ = {lam.max() * sensor_distance_m / cell_m * 1e3:.3f} mm "
                f"at {pixel_m * 1e6:g} µm pixels)"
            )
    if supersample is not None and (int(supersample) < 1 or int(supersample) % 2 == 0):
        raise ConfigError(f"camera.psf.supersample must be a positive odd number, got {supersample}")
    a = n_cells * cell_m / 2 if aperture_radius_m is None else aperture_radius_m
    s_nyq = odd_ceil(4.0 * a * pixel_m / (lam.min() * sensor_distance_m))
    return PSFSampling(n_pupil, cell_m / q, n_fft, k, min_k, None if supersample is None else int(supersample), s_nyq)


def _gauss_legendre(h: float, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * h * x, 0.5 * h * w


def pixel_weights(period_px: float, kernel_px: int, fft_size: int, supersample: int | None = None,
                  envelope: bool = True) -> np.ndarray:
    """Exact pixel-integration matrix W (K, N) float64 of one wavelength and axis.

    Args:
        period_px: L/pixel = λ·z/(d·pixel), the far-field period of the cell grid in pixels.
        kernel_px: K (odd); pixel j (0..K−1) is centred at t_j = (j − K//2)/period_px.
        fft_size: N, the FFT length over one period (sample a sits at t = a/N mod 1); the intensity's
            harmonics are |k| ≤ P − 1 < N/2, so an even N has no Nyquist term (it is left out).
        supersample: None: exact integral over the pixel (Gauss–Legendre); s: s-point midpoint rule.
        envelope: multiply by the cell envelope sinc²(t) (False: point cells, for checks).
    Returns:
        W with pixel value = Σ_ab W[i, a] I[a, b] W[j, b] for I = |FFT_N(u)|² / Σ|u|²
        (the fraction of the pupil's power on that pixel).
    """
    k, n = int(kernel_px), int(fft_size)
    h = 1.0 / float(period_px)
    freqs = np.fft.fftfreq(n, d=1.0 / n)  # integers in FFT order: −(N−1)/2 .. (N−1)/2, or −N/2 .. N/2 − 1
    if supersample is None:
        # integrand sinc²(t)·e^{2πikt} over a pixel: at most |k|·h cycles; GL is exact far beyond that
        tau, w = _gauss_legendre(h, int(math.ceil(math.pi * (n / 2) * h)) + 16)
    else:
        s = int(supersample)
        tau, w = ((np.arange(s) + 0.5) / s - 0.5) * h, np.full(s, h / s)
    centres = (np.arange(k) - k // 2) * h
    t = centres[:, None] + tau[None, :]  # (K, G)
    ew = w[None, :] * (np.sinc(t) ** 2 if envelope else np.ones_like(t))  # (K, G)
    # J[j, k] = Σ_g ew[j, g] e^{2πi k (t_j + τ_g)};  W[j, a] = (1/N) Σ_k J[j, k] e^{−2πi k a/N}
    j_mat = np.exp(2j * np.pi * np.outer(centres, freqs)) * (ew @ np.exp(2j * np.pi * np.outer(tau, freqs)))
    if n % 2 == 0:
        j_mat[:, n // 2] = 0.0  # the Nyquist harmonic −N/2: absent from a band-limited intensity
    return np.fft.fft(j_mat, axis=1).real / n


def band_sample_wavelengths(centers_nm: np.ndarray, fwhm_nm: np.ndarray, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-wavelengths (nm) and weights, both (C, M), that average each band over its FWHM.

    M = ``samples`` points at the centres of M equal slices of [λ_c − FWHM/2, λ_c + FWHM/2],
    weighted by a Gaussian band shape of that FWHM (weights sum to 1 per band). M = 1: the centre.
    """
    c = np.asarray(centers_nm, dtype=np.float64).reshape(-1, 1)
    f = np.asarray(fwhm_nm, dtype=np.float64).reshape(-1, 1)
    m = int(samples)
    if m < 1:
        raise ValueError("band samples must be >= 1")
    off = ((np.arange(m) + 0.5) / m - 0.5)[None, :]  # in FWHM units
    lam = c + off * f
    w = np.exp(-4.0 * math.log(2.0) * off**2) * np.ones_like(lam)
    return lam, w / w.sum(axis=1, keepdims=True)
