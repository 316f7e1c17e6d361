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

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from hsicam.errors import ConfigError
from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes

log = logging.getLogger(__name__)

#: (supersample, Nyquist supersample) pairs already warned about in this process.
_BELOW_NYQUIST_WARNED: set[tuple[int, int]] = set()

#: Wavelengths per FFT batch of the PSF stack (:func:`hsicam.optics.psf.psf_stack`): a few at once
#: amortise the per-call overhead (measured: 4 per batch takes the 31-band paper stack from 0.40 to
#: 0.37 s forward + backward at N = 675) while each batch's complex spectra stay small
#: (4 × 672² × 8 B = 14 MB), which avoids fresh memory maps.
WAVELENGTHS_PER_BATCH = 4


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
    memory_bytes: int = 0  # at least this much memory is needed (:func:`psf_memory_estimate`)


def odd_ceil(x: float) -> int:
    """Smallest odd integer ≥ x (with a 1e-9 tolerance against round-off)."""
    k = int(math.ceil(x - 1e-9))
    return k if k % 2 == 1 else k + 1


def smallest_kernel_px(max_wavelength_m: float, sensor_distance_m: float, cell_m: float, pixel_m: float) -> int:
    """Smallest odd kernel (px) holding one period λ_max·z/Δ of the DOE cell grid's far field."""
    return odd_ceil(max_wavelength_m * sensor_distance_m / (cell_m * pixel_m))


def fast_fft_length(n: int) -> int:
    """Smallest 7-smooth integer ≥ n (2^a·3^b·5^c·7^d: a fast FFT length). Even lengths are
    allowed: with N ≥ 2P − 1 the intensity has no harmonic at N/2 (measured: 672 is 1.4× faster
    than the odd 675 for the paper pupil, P = 333). Found among the 7-smooth numbers themselves (each 7^d·5^c·3^b
    times the least power of 2 that reaches n), not by trying n, n + 1, …: their gaps grow with n, and that search
    did not come back for the pupil of a huge oversampling (``tolerance --shift-subsamples 10**12``: 3.7e9
    candidates), before the memory check that refuses it."""
    m = max(1, int(n))
    odd_parts = (odd for p7 in _powers(1, 7, m) for p5 in _powers(p7, 5, m) for odd in _powers(p5, 3, m))
    # each odd part 7^d·5^c·3^b times the least power of 2 that brings it to ≥ m
    return min(odd << (-(-m // odd) - 1).bit_length() for odd in odd_parts)


def _powers(start: int, factor: int, limit: int):
    """start, start·factor, start·factor², … up to and including the first one ≥ ``limit``."""
    value = start
    while True:
        yield value
        if value >= limit:
            return
        value *= factor


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
    """Choose N and K (see module docstring). Raises :class:`ConfigError` for impossible choices
    and, before anything is allocated, for a plan that needs more memory than the budget
    (:func:`psf_memory_estimate`, :func:`check_psf_memory`).

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
    min_k = smallest_kernel_px(float(lam.max()), sensor_distance_m, cell_m, pixel_m)
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
    if supersample is not None:
        # the exact integral's Gauss–Legendre nodes per pixel and axis: a midpoint rule of many times more costs many
        # times more and is still approximate (supersample=1000001 computed for minutes); up to
        # MAX_SUPERSAMPLE_FACTOR times more stays allowed, for convergence comparisons
        g_exact = quadrature_nodes(far_field_period_px(float(lam.min()), sensor_distance_m, cell_m / q, pixel_m), n_fft)
        top = max(MAX_SUPERSAMPLE_FACTOR * g_exact, s_nyq)
        top -= 1 - top % 2
        if int(supersample) > top:
            raise ConfigError(f"camera.psf.supersample={int(supersample)} takes over {MAX_SUPERSAMPLE_FACTOR}× the "
                              f"points per pixel and axis of the exact pixel integral of these optics ({g_exact} "
                              f"Gauss–Legendre nodes), which is cheaper and exact: leave camera.psf.supersample unset "
                              f"(null), or use an odd value up to {top} for the midpoint rule")
    if supersample is not None and int(supersample) < s_nyq and (int(supersample), s_nyq) not in _BELOW_NYQUIST_WARNED:
        _BELOW_NYQUIST_WARNED.add((int(supersample), s_nyq))
        log.warning("camera.psf.supersample=%d is below these optics' Nyquist rate (%d: sub-pixels finer than "
                    "λ_min·z/(4a)): the %d×%d midpoint rule aliases the PSF's finest fringes (a comparison mode); "
                    "leave it unset for the exact pixel integral", int(supersample), s_nyq, int(supersample),
                    int(supersample))
    smp = PSFSampling(n_pupil, cell_m / q, n_fft, k, min_k, None if supersample is None else int(supersample), s_nyq)
    mem = psf_memory_estimate(smp, lam, sensor_distance_m, pixel_m)
    smp = replace(smp, memory_bytes=mem.total)
    check_psf_memory(mem, smp, lam, sensor_distance_m, pixel_m, cell_m, n_cells)
    return smp


# ------------------------------------------------------------------------------------------------
# Memory of a sampling plan (checked before anything is allocated)
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PSFMemory:
    """Bytes a PSF sampling plan needs at least (lower bounds; the largest temporaries only).

    ``quadrature``: building one wavelength's W with exact pixel integration (the Gauss–Legendre
    nodes, whose count grows with the pixel size in far-field periods, and their (K, G), (G, N)
    tables); ``weights``: the (L, K, N) pixel-weight matrices (float64 while built, float32 kept);
    ``fft``: one batch of :data:`WAVELENGTHS_PER_BATCH` wavelengths' N×N FFT arrays, forward and
    backward; ``kernels``: the (L, K, K) output stack; ``saved``: what the DOE's gradient keeps of
    every wavelength until the backward pass (its (N, N) complex spectrum, (P, P) complex field and
    phase; training is the plan's largest use, so it is counted whether or not a caller trains),
    and the phase stack's two products while it is built.
    """

    quadrature: int
    weights: int
    fft: int
    kernels: int
    quadrature_nodes: int
    batch: int
    saved: int = 0

    @property
    def total(self) -> int:
        return self.quadrature + self.weights + self.fft + self.kernels + self.saved


#: ``camera.psf.supersample`` may take up to this many times the exact integral's nodes (per pixel and axis).
MAX_SUPERSAMPLE_FACTOR = 4


def far_field_period_px(wavelength_m: float | np.ndarray, sensor_distance_m: float | np.ndarray, pupil_pitch_m: float,
                        pixel_m: float) -> float | np.ndarray:
    """The period (in pixels) of the far field of a pupil sampled at ``pupil_pitch_m``: λz/(Δ·pixel); elementwise
    for arrays of wavelengths and distances (one period per line of a spectrum, :class:`~hsicam.optics.psf.PSFModel`)."""
    return wavelength_m * sensor_distance_m / (pupil_pitch_m * pixel_m)


def quadrature_nodes(period_px: float, fft_size: int, supersample: int | None = None) -> int:
    """Nodes per pixel that :func:`pixel_weights` integrates with (s for the midpoint rule)."""
    if supersample is not None:
        return int(supersample)
    h = 1.0 / float(period_px)
    return int(math.ceil(math.pi * (int(fft_size) / 2) * h)) + 16


def psf_memory_estimate(sampling: PSFSampling, wavelengths_m: np.ndarray, sensor_distance_m: float,
                        pixel_m: float) -> PSFMemory:
    """Lower bound of the memory that :class:`~hsicam.optics.psf.PSFModel` needs for ``sampling``
    (see :class:`PSFMemory`); pure arithmetic on the plan's sizes (Python ints, no overflow)."""
    lam = np.asarray(wavelengths_m, dtype=np.float64).reshape(-1)
    n_lines = int(lam.size)
    p, n, k = int(sampling.pupil_samples), int(sampling.fft_size), int(sampling.kernel_px)
    min_period = far_field_period_px(float(lam.min()), sensor_distance_m, sampling.pupil_pitch_m, pixel_m)
    g = quadrature_nodes(min_period, n, sampling.supersample)
    # Gauss–Legendre: a G×G companion matrix and the eigen-solver's copy (float64), then
    # t, ew (K, G) float64 and the (G, N) complex128 exponentials
    quad = (24 * g * g if sampling.supersample is None else 0) + 16 * k * g + 32 * g * n
    # W of every wavelength: float64 list and its stack, the float32 buffer, one line's (K, N) complex temporaries
    weights = 20 * n_lines * k * n + 80 * k * n
    b = min(WAVELENGTHS_PER_BATCH, max(n_lines, 1))
    # field (P, P) c64, row FFT (P, N) c64, then N×N: spectrum c64, intensity and its squares f32;
    # backward: the gradient f32, the product and its inverse FFT c64; (K, N) and (K, K) f32
    fft = b * (8 * p * p + 8 * p * n + 28 * n * n + 4 * k * n + 4 * k * k)
    kernels = 12 * n_lines * k * k
    # kept for the backward pass, per wavelength: spectrum (N, N) c64, field (P, P) c64, phase (P, P) f32;
    # and two (P, P) f32 products per wavelength while the phase stack is formed
    saved = n_lines * (8 * n * n + 8 * p * p + 4 * p * p + 8 * p * p)
    return PSFMemory(quad, weights, fft, kernels, g, b, saved)


def check_psf_memory(mem: PSFMemory, sampling: PSFSampling, wavelengths_m: np.ndarray, sensor_distance_m: float,
                     pixel_m: float, cell_m: float, n_cells: int, budget_bytes: int | None = None) -> None:
    """Refuse a plan that needs more than the memory budget
    (:func:`memory_budget_bytes`), with one :class:`ConfigError` that names the
    largest cost, the geometry that implies it and the settings to check."""
    if budget_bytes is None:
        budget_bytes = memory_budget_bytes()
    if mem.total <= budget_bytes:
        return
    lam = np.asarray(wavelengths_m, dtype=np.float64).reshape(-1)
    z_mm, pix_um, cell_um = sensor_distance_m * 1e3, pixel_m * 1e6, cell_m * 1e6
    p, n, k = sampling.pupil_samples, sampling.fft_size, sampling.kernel_px
    q = max(1, round(cell_m / sampling.pupil_pitch_m))
    parts = {"quadrature": mem.quadrature, "fft": mem.fft, "kernel": mem.weights + mem.kernels, "saved": mem.saved}
    worst = max(parts, key=parts.get)
    if worst == "quadrature":
        field_um = lam.min() * sensor_distance_m / sampling.pupil_pitch_m * 1e6
        cause = (f"at sensor distance z = {z_mm:.4g} mm a {pix_um:.4g} µm pixel spans {pix_um / field_um:.3g} periods of "
                 f"the DOE cells' far field (λz/Δ = {field_um:.3g} µm at {lam.min() * 1e9:.4g} nm), so its exact "
                 f"integration needs {mem.quadrature_nodes} quadrature nodes ({format_bytes(mem.quadrature)})")
        check = ("camera.sensor_distance_mm (normally the focal length), camera.sensor.pixel_pitch_um and "
                 "camera.doe.cell_size_um, or set camera.psf.supersample=1")
    elif worst == "fft":
        cause = (f"the {p}-sample pupil ({n_cells} DOE cells of {cell_um:.4g} µm across"
                 f"{f', {q}× oversampled' if q > 1 else ''}) needs FFTs of {n} points per axis "
                 f"({format_bytes(mem.fft)} per batch of {mem.batch} wavelengths)")
        check = "camera.aperture_radius_mm, camera.doe.cell_size_um and camera.psf.pupil_oversample"
    elif worst == "saved":
        cause = (f"each of its {lam.size} wavelengths (bands × camera.psf.band_samples) keeps its {n}×{n} spectrum and "
                 f"{p}×{p} pupil field for the DOE's gradient ({format_bytes(mem.saved)} in all)")
        check = "camera.psf.band_samples, camera.aperture_radius_mm, camera.doe.cell_size_um and camera.psf.pupil_oversample"
    else:
        why = ("camera.psf.kernel_px" if k > sampling.min_kernel_px else
               f"λ_max·z/Δ = {lam.max() * sensor_distance_m / cell_m * 1e3:.4g} mm at z = {z_mm:.4g} mm "
               f"over {pix_um:.4g} µm pixels")
        cause = (f"the {k}×{k} px kernel ({why}) for {lam.size} wavelengths needs "
                 f"{format_bytes(mem.weights)} of pixel-weight matrices and {format_bytes(mem.kernels)} of kernels")
        check = ("camera.sensor_distance_mm (normally the focal length), camera.sensor.pixel_pitch_um, "
                 "camera.doe.cell_size_um, camera.psf.kernel_px and camera.psf.band_samples")
    raise ConfigError(
        f"the PSF sampling plan needs at least {format_bytes(mem.total)} of memory, over the memory budget of "
        f"{format_bytes(budget_bytes)} ({MEMORY_BUDGET_ENV}): {cause}; check {check}"
    )


# ------------------------------------------------------------------------------------------------
# Residual defocus on the pupil grid
# ------------------------------------------------------------------------------------------------
def defocus_aliasing(defocus_per_m2: np.ndarray, aperture_radius_m: float, pupil_pitch_m: float) -> np.ndarray:
    """Residual-defocus phase step between neighbouring pupil samples at the aperture edge, in
    units of π, per wavelength (float64). Above 1 the sampled defocus aliases: equivalently, the
    geometric blur 2a·z·|1/z_o + 1/z − 1/f| is wider than the field λz/d that the pupil grid can
    represent, and the computed PSF belongs to another lens. The phase is c·r², so the step at
    r = a is about 2·a·d·|c|."""
    c = np.abs(np.asarray(defocus_per_m2, dtype=np.float64))
    return c * 2.0 * aperture_radius_m * pupil_pitch_m / math.pi


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
        tau, w = _gauss_legendre(h, quadrature_nodes(period_px, n))
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
