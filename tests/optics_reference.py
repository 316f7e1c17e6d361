"""Independent reference for the PSF of a pupil of square cells (no code of the package used).

Fraunhofer integral written cell by cell: each square cell of side Δ, centred at (x_c, y_c) with
constant complex transmission u_c, contributes its analytic transform

    Δ² sinc(Δ f_x) sinc(Δ f_y) e^{−2πi (f_x x_c + f_y y_c)} u_c,      f = x / (λ z),

summed over all cells (every diffraction order kept), |·|² / (λ z)², and each sensor pixel is
integrated by the midpoint rule on ``sub``×``sub`` points. Normalised by the pupil power
Σ|u_c|² Δ² (the light through the pupil), so pixel values are energy fractions.

Also the band rule's Gaussian width by brute force (:func:`interpolant_gaussian_sigma`).
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


# --------------------------------------------------------------------------------------------
# The camera model written out: direct shift-and-add, no FFT, no code of the package
# (tests/cameras/test_camera.py's operator tests, tests/optics/test_coded_convolution.py and the command-line tests)
# --------------------------------------------------------------------------------------------
NP_PAD = {"zeros": "constant", "reflect": "reflect", "replicate": "edge", "circular": "wrap"}


def direct_valid_conv(x: np.ndarray, psf: np.ndarray) -> np.ndarray:
    """Per-band valid convolution by explicit shift-and-add (numpy float64), from the physics.

    PSF (C, K, K) with the optical axis on pixel (K//2, K//2); output pixel (i, j) is on the axis
    of scene pixel (i + K//2, j + K//2): out[i, j] = Σ_d p[d] · f[axis(i, j) − d]. Scene (B, C, H', W').
    """
    r = psf.shape[-1] // 2
    h, w = x.shape[-2] - 2 * r, x.shape[-1] - 2 * r
    out = np.zeros((x.shape[0], x.shape[1], h, w))
    for dy in range(-r, r + 1):  # displacement d = (dy, dx) of the light from the axis
        for dx in range(-r, r + 1):
            shifted = x[:, :, r - dy : r - dy + h, r - dx : r - dx + w]  # f[axis − d]
            out += psf[None, :, r + dy, r + dx, None, None] * shifted
    return out


def reference_measurement(x: np.ndarray, psf: np.ndarray, weights: np.ndarray | None, boundary: str,
                          padding: str) -> np.ndarray:
    """Direct (non-FFT) camera model: g = Σ_c κ_c ⊙ (f_c ⊛ p_c), (B, 1, H, W) float64.

    Scene x (B, C, H', W'); raw CFA weights (C, m, m) (ReLU, normalised over bands, tiled from
    sensor pixel (0, 0); every pixel needs a positive weight) or None for κ = 1. 'same' pads the
    scene by K//2 with numpy's modes (``padding``: zeros, reflect, replicate, circular).
    """
    r = psf.shape[-1] // 2
    x = np.asarray(x, dtype=np.float64)
    if boundary == "same":
        x = np.pad(x, ((0, 0), (0, 0), (r, r), (r, r)), mode=NP_PAD[padding])
    out = direct_valid_conv(x, np.asarray(psf, dtype=np.float64))
    h, w = out.shape[-2:]
    if weights is None:
        kappa = np.ones((x.shape[1], h, w))
    else:
        t = np.maximum(np.asarray(weights, dtype=np.float64), 0.0)
        t = t / t.sum(axis=0, keepdims=True)
        m = t.shape[-1]
        kappa = np.tile(t, (1, -(-h // m), -(-w // m)))[:, :h, :w]
    return (out * kappa[None]).sum(axis=1, keepdims=True)


def interpolant_gaussian_sigma(source_nm, centre: float, kernel_sigma: float) -> float:
    """σ' (nm) of the Gaussian whose average of the linear interpolant of samples at ``source_nm`` spreads a line at
    ``centre`` by ``kernel_sigma``² (session 74's band rule, :func:`hsicam.spectral.bands.resampling_matrix`): the
    σ' with E[(x − c)² + t(1 − t)h²] = kernel_sigma², x ~ N(centre, σ'²) cut at 3σ' or symmetrically at the nearer
    end of the data, h the data's step around x and t the place of x within it; 0 when the point sample at ``centre``,
    t(1 − t)h², spreads it more. Brute force, written here: bisection on a trapezoid expectation over 10 001
    uniform nodes of the cut Gaussian (the module's quadrature puts nodes at the data's samples instead)."""
    import math

    import numpy as np

    s = np.asarray(source_nm, dtype=np.float64)
    target = kernel_sigma * kernel_sigma

    def spread_at(x, w):
        j = np.clip(np.searchsorted(s, x, side="right") - 1, 0, len(s) - 2)
        h = s[j + 1] - s[j]
        t = np.clip((x - s[j]) / h, 0.0, 1.0)
        return float(np.trapezoid(w * ((x - centre) ** 2 + t * (1 - t) * h * h), x) / np.trapezoid(w, x))

    def spread(sig):
        reach = max(min(3 * sig, centre - s[0], s[-1] - centre), 0.0)
        if sig == 0:  # the point sample at the centre
            j = min(max(int(np.searchsorted(s, centre, side="right")) - 1, 0), len(s) - 2)
            t = (centre - s[j]) / (s[j + 1] - s[j])
            return t * (1 - t) * (s[j + 1] - s[j]) ** 2
        if reach == 0:
            return 0.0
        x = np.linspace(centre - reach, centre + reach, 10_001)
        return spread_at(x, np.exp(-0.5 * ((x - centre) / sig) ** 2))

    if spread(0.0) >= target:
        return 0.0
    lo, hi = 0.0, math.sqrt(target)
    for _ in range(30):
        mid = (lo + hi) / 2
        if spread(mid) < target:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2
