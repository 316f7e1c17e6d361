"""Independent reference for the PSF of a pupil of square cells (no code of the package used).

Fraunhofer integral written cell by cell: each square cell of side Δ, centred at (x_c, y_c) with
constant complex transmission u_c, contributes its analytic transform

    Δ² sinc(Δ f_x) sinc(Δ f_y) e^{−2πi (f_x x_c + f_y y_c)} u_c,      f = x / (λ z),

summed over all cells (every diffraction order kept), |·|² / (λ z)², and each sensor pixel is
integrated by the midpoint rule on ``sub``×``sub`` points. Normalised by the pupil power
Σ|u_c|² Δ² (the light through the pupil), so pixel values are energy fractions.
"""

from __future__ import annotations

import numpy as np


def sellmeier_fused_silica(lam_nm):
    """n(λ) of fused silica, Malitson (1965), written out here."""
    l2 = (np.asarray(lam_nm, dtype=np.float64) * 1e-3) ** 2
    terms = [(0.6961663, 0.0684043), (0.4079426, 0.1162414), (0.8974794, 9.896161)]
    return np.sqrt(1.0 + sum(b * l2 / (l2 - c * c) for b, c in terms))


def doe_field(heights_m: np.ndarray, aperture: np.ndarray, lam_nm: float, pupil_oversample: int = 1) -> np.ndarray:
    """u = A·exp(2πi (n(λ)−1) h / λ) on the pupil cells; heights per DOE cell repeated q×q."""
    h = np.kron(np.asarray(heights_m, dtype=np.float64), np.ones((pupil_oversample, pupil_oversample)))
    phase = 2 * np.pi * (sellmeier_fused_silica(lam_nm) - 1.0) * h / (lam_nm * 1e-9)
    return np.asarray(aperture, dtype=np.float64) * np.exp(1j * phase)


def square_cell_psf(u: np.ndarray, cell_m: float, lam_m: float, z_m: float, pixel_m: float,
                    pixels: np.ndarray, sub: int = 11, pixels_y: np.ndarray | None = None) -> np.ndarray:
    """Pixel-integrated PSF on pixels ``pixels`` (offsets from the axis, in pixels) along both axes.

    Args:
        u: (P, P) complex cell transmissions, row = y, centre cell on the axis.
        cell_m, lam_m, z_m, pixel_m: Δ, λ, z (rear principal plane to sensor), pixel pitch (m).
        pixels: integer pixel offsets along x (and y unless ``pixels_y``), shape (J,).
        sub: midpoint points per pixel and axis.
    Returns:
        (Jy, J) float64 energy fractions (row = y).
    """
    p = u.shape[-1]
    xc = (np.arange(p) - (p - 1) / 2) * cell_m
    off = ((np.arange(sub) + 0.5) / sub - 0.5)

    def cells_to_points(pix):
        x = ((np.asarray(pix, dtype=np.float64)[:, None] + off[None, :]) * pixel_m).reshape(-1)
        f = x / (lam_m * z_m)
        return cell_m * np.sinc(cell_m * f)[:, None] * np.exp(-2j * np.pi * f[:, None] * xc[None, :])  # (J·sub, P)

    ex = cells_to_points(pixels)
    ey = ex if pixels_y is None else cells_to_points(pixels_y)
    field = ey @ u @ ex.T  # (y, x)
    inten = np.abs(field) ** 2 / (lam_m * z_m) ** 2
    jy, jx = ey.shape[0] // sub, ex.shape[0] // sub
    pooled = inten.reshape(jy, sub, jx, sub).mean(axis=(1, 3)) * pixel_m**2
    return pooled / (np.sum(np.abs(u) ** 2) * cell_m**2)


def relative_l1(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(a - ref).sum() / np.abs(ref).sum())
