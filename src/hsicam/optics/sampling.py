"""PSF sampling plan (DESIGN.md §1, "the classic pitfall").

A single FFT of a pupil sampled at Δ, zero-padded to N, gives an output pitch λ·z/(N·Δ) that
changes with λ. Per band we choose N_λ = round(λ·z·s/(pixel·Δ)) so that the output pitch is
pixel/s for an odd integer s, then sum-pool s×s onto the pixel (area integration). The kernel is
odd, the optical axis sits on the centre pixel, and it must span the FFT field of view λ_max·z/Δ,
otherwise light aliases back in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hsicam.errors import ConfigError


@dataclass(frozen=True)
class PSFSampling:
    """The per-band FFT sizes and the common supersampling and kernel size."""

    pupil_samples: int  # samples across the pupil: cells × q
    pupil_pitch_m: float  # Δ/q
    supersample: int  # s (odd): FFT output pitch = pixel / s
    fft_sizes: tuple[int, ...]  # N_λ per band
    kernel_px: int  # K (odd)
    min_kernel_px: int  # smallest K holding the zeroth-order FFT field λ_max·z/Δ
    pitch_rel_error: tuple[float, ...]  # (actual FFT pitch)/(pixel/s) − 1 per band, from rounding N_λ


def odd_ceil(x: float) -> int:
    """Smallest odd integer ≥ x (with a 1e-9 tolerance against round-off)."""
    k = int(math.ceil(x - 1e-9))
    return k if k % 2 == 1 else k + 1


def plan_psf_sampling(
    wavelengths_m: np.ndarray,
    sensor_distance_m: float,
    pixel_m: float,
    cell_m: float,
    n_cells: int,
    pupil_oversample: int = 1,
    supersample: int | None = None,
    kernel_px: int | None = None,
) -> PSFSampling:
    """Choose s, N_λ and K (see module docstring). Raises :class:`ConfigError` for impossible choices.

    Args:
        wavelengths_m: band centres (m), shape (C,).
        sensor_distance_m: z_i, lens-to-sensor distance (m).
        pixel_m: sensor pixel pitch (m).
        cell_m: DOE cell size Δ (m).
        n_cells: cells across the pupil grid.
        pupil_oversample: q samples per cell; the FFT field widens q×, showing higher orders.
        supersample: odd s, or None for the smallest s with N_λ ≥ pupil samples in every band.
        kernel_px: odd K, or None for the smallest K that holds λ_max·z/Δ.
    """
    lam = np.asarray(wavelengths_m, dtype=np.float64).reshape(-1)
    for name, v in (("sensor distance", sensor_distance_m), ("pixel pitch", pixel_m), ("DOE cell", cell_m)):
        if not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"{name} must be positive, got {v}")
    q = int(pupil_oversample)
    pupil_pitch = cell_m / q
    n_pupil = n_cells * q
    base = lam * sensor_distance_m / (pixel_m * pupil_pitch)  # N_λ for s = 1
    s_min = odd_ceil(n_pupil / base.min())
    if supersample is None:
        s = s_min
    else:
        s = int(supersample)
        if s < s_min:
            raise ConfigError(
                f"camera.psf.supersample={s} is too small: the FFT must hold the {n_pupil}-sample pupil at "
                f"{lam.min() * 1e9:g} nm, which needs supersample >= {s_min}"
            )
    sizes = tuple(int(round(b * s)) for b in base)
    min_k = odd_ceil(max(sizes) / (s * q))
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
    err = tuple(float(b * s / n - 1.0) for b, n in zip(base, sizes))
    return PSFSampling(n_pupil, pupil_pitch, s, sizes, k, min_k, err)
