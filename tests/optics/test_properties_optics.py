"""Property-based tests (hypothesis) of the optics and of the cameras' forward models on unusual inputs:
odd and prime sizes, 1-px images, one band and many, non-uniform band grids, extreme but legal geometry,
float64, non-contiguous tensors, batches whose items differ, every CFA phase and window origin.

Every property is checked against an independent reference: a closed form (a binary phase grating's
orders, Parseval), a brute-force computation in numpy (shift-and-add convolution, explicit operator
matrices, a high-order quadrature of the square-cell far field), or the definition (⟨Ax, y⟩ = ⟨x, Aᵀy⟩).
"""

from __future__ import annotations

import functools
import math
import weakref
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hsicam.cameras import DOECamera
from hsicam.cameras.cassi import (
    CASSISnapshot,
    CodedAperture,
    DDCASSICamera,
    SDCASSICamera,
    linear_dispersion,
)
from hsicam.cameras.measured import FixedPSFCamera
from hsicam.optics import convolution as cv
from hsicam.optics.doe import DOE, crossed_grating_heights_m, gaussian_lowpass_periodic, quantize_heights
from hsicam.optics.lens import AchromaticLens, SingletLens
from hsicam.optics.perturb import (
    defocus_delta_per_m2,
    rebuilt_optics,
    sensor_distance_aliasing,
    sensor_distance_limits_m,
    shift_fill,
)
from hsicam.optics.psf import PSFModel, psf_stack
from hsicam.optics.pupil import aperture_amplitude, cells_across
from hsicam.optics.sampling import fast_fft_length, odd_ceil, pixel_weights
from hsicam.sensor import ColorFilterArray, SensorNoise
from hsicam.spectral import Bands, get_material
from optics_reference import direct_valid_conv

#: Reproducible in CI: the same examples on every run, no example database.
PROP = dict(deadline=None, derandomize=True, database=None)


def _inner(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() * b.double()).sum())


def _adjoint_gap(a_x, y, x, at_y) -> float:
    return abs(_inner(a_x, y) - _inner(x, at_y)) / max(float(a_x.norm() * y.norm()), 1e-300)


# ------------------------------------------------------------------------------------------------
# Square-cell far field: pixel_weights against an independent quadrature, Parseval, closed-form grating
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=2)
def _legendre(nodes: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(nodes)


def _cell_pixel_integrals(period_px: float, kernel_px: int, max_lag: int, nodes: int = 1500) -> np.ndarray:
    """M[j, l] = ∫_pixel j sinc²(t) e^{−2πi t l} dt for lags l = −max_lag..max_lag (t in far-field periods,
    pixel j of width 1/period_px centred at (j − K//2)/period_px): the exact far field of square cells is
    Σ_{c,c'} u_c ū_c' M_y[·, c_y − c'_y] M_x[·, c_x − c'_x]. Dense Gauss–Legendre, written here."""
    h = 1.0 / period_px
    x, w = _legendre(nodes)  # exact far beyond the ≤ 50·(max_lag + 1) cycles of the integrand over a pixel
    centres = (np.arange(kernel_px) - kernel_px // 2) * h
    t = centres[:, None] + 0.5 * h * x[None, :]  # (K, G) nodes inside each pixel
    lags = np.arange(-max_lag, max_lag + 1)
    integrand = (0.5 * h * w) * np.sinc(t) ** 2  # (K, G)
    return np.einsum("jg,jgl->jl", integrand, np.exp(-2j * np.pi * t[:, :, None] * lags[None, None, :]))


def _square_cell_reference(u: np.ndarray, period_px: float, kernel_px: int) -> np.ndarray:
    """Pixel-integrated far field (K, K) of the cells u (P, P), as energy fractions."""
    p = u.shape[0]
    m = _cell_pixel_integrals(period_px, kernel_px, p - 1)  # (K, 2P−1), lag index l + P − 1
    idx = np.arange(p)[:, None] - np.arange(p)[None, :] + p - 1  # (c, c') → c − c'
    my, mx = m[:, idx], m[:, idx]  # (K, P, P)
    # psf[jy, jx] = Σ u[cy, cx] ū[cy', cx'] My[jy, cy, cy'] Mx[jx, cx, cx']
    out = np.einsum("ab,cd,jac,kbd->jk", u, u.conj(), my, mx, optimize=True)
    return out.real / np.sum(np.abs(u) ** 2)


@settings(max_examples=30, **PROP)
@given(p=st.integers(1, 6), extra=st.integers(0, 3), log_period=st.floats(math.log(0.02), math.log(300.0)),
       k=st.integers(0, 4), seed=st.integers(0, 2**16))
def test_pixel_weights_equal_a_high_order_quadrature_of_the_square_cell_far_field(p, extra, log_period, k, seed):
    """W I Wᵀ is the exact pixel integral of sinc² × the cell-grid sum, for any N ≥ 2P − 1 (odd or even), pixels of
    1/50 to 300 far-field periods, any odd K: compared with the separable integral written out here."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(p, p)) + 1j * rng.normal(size=(p, p))
    n, period, kpx = 2 * p - 1 + extra, math.exp(log_period), 2 * k + 1
    w = pixel_weights(period, kpx, n)
    inten = np.abs(np.fft.fft2(u, s=(n, n))) ** 2 / np.sum(np.abs(u) ** 2)
    got = w @ inten @ w.T
    ref = _square_cell_reference(u, period, kpx)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * max(ref.max(), 1e-12) + 1e-12)


@settings(max_examples=30, **PROP)
@given(p=st.integers(1, 7), extra=st.integers(0, 3), period=st.sampled_from([1, 3, 5, 7, 9, 11, 13]),
       seed=st.integers(0, 2**16))
def test_point_cells_over_one_whole_period_hold_all_the_light(p, extra, period, seed):
    """Parseval: without the cell envelope the far field is periodic; K = L pixels of 1/L period tile one period
    exactly, so the kernel sums to 1 whatever the pupil."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(p, p)) + 1j * rng.normal(size=(p, p))
    n = 2 * p - 1 + extra
    w = pixel_weights(float(period), period, n, envelope=False)
    inten = np.abs(np.fft.fft2(u, s=(n, n))) ** 2 / np.sum(np.abs(u) ** 2)
    assert abs((w @ inten @ w.T).sum() - 1.0) < 1e-10


@settings(max_examples=40, **PROP)
@given(period=st.integers(2, 9), high=st.integers(1, 8), reps=st.integers(1, 4), phase=st.floats(0.05, 2 * math.pi - 0.05),
       orders=st.integers(1, 12))
def test_two_level_grating_puts_the_closed_form_energy_into_each_order(period, high, reps, phase, orders):
    """A 2-level phase grating (period p cells, a of them raised by phase φ) over a square pupil of whole periods:
    the continuous grating's Fourier coefficients give order m ≠ 0 relative to order 0 as
    4 sin²(φ/2) sin²(π m a/p) / ((π m)² |1 + (a/p)(e^{iφ} − 1)|²), every m, the cells' sinc envelope included (the
    far field of square cells is exact). Point values at pixel centres (supersample 1), one pixel per order."""
    a = min(high, period - 1)
    n_cells = period * reps
    x = np.arange(n_cells) % period < a  # cells raised along x
    h = torch.tensor(np.broadcast_to(x.astype(np.float64), (n_cells, n_cells)).copy())
    kpx = 2 * orders + 1
    n = fast_fft_length(2 * n_cells - 1)
    w = torch.from_numpy(pixel_weights(float(period), kpx, n, supersample=1))[None]
    res = psf_stack(h, torch.ones(n_cells, n_cells, dtype=torch.float64), torch.zeros(n_cells, n_cells, dtype=torch.float64),
                    torch.tensor([phase], dtype=torch.float64), torch.zeros(1, dtype=torch.float64), w)
    row = res.psf[0, orders].numpy()  # the y order 0
    m = np.arange(-orders, orders + 1)
    d = a / period
    c0 = abs(1 + d * (np.exp(1j * phase) - 1)) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(m == 0, 1.0, 4 * math.sin(phase / 2) ** 2 * np.sin(np.pi * m * d) ** 2 / (np.pi * m) ** 2 / c0)
    np.testing.assert_allclose(row / row[orders], ratio, rtol=1e-6, atol=1e-9)


# ------------------------------------------------------------------------------------------------
# PSFModel: a constant DOE is the lens alone, float64 = float32, bands alone = bands together
# ------------------------------------------------------------------------------------------------
def _optics(centers_nm, fwhm=10.0, lens="achromatic", radius_mm=0.25, cell_um=50.0, f_mm=5.0, pixel_um=10.0,
            band_samples=1, q=1, supersample=None, doe_init="random", seed=0, **kw) -> PSFModel:
    bands = Bands(np.asarray(centers_nm, dtype=np.float64), np.full(len(centers_nm), fwhm))
    n_cells = cells_across(radius_mm * 1e-3, cell_um * 1e-6)
    silica = get_material("fused_silica")
    doe = DOE(n_cells, silica, 550.0, init=doe_init, seed=seed)
    if lens == "achromatic":
        lens_m = AchromaticLens(f_mm * 1e-3)
    else:  # a singlet of focal length ≈ f_mm at 587.6 nm
        lens_m = SingletLens(f_mm * 1e-3 * (float(silica.n(587.6)) - 1.0), 0.2e-3, silica)
    return PSFModel(bands, lens_m, doe, radius_mm * 1e-3, cell_um * 1e-6, pixel_um * 1e-6,
                    supersample=supersample, pupil_oversample=q, band_samples=band_samples, **kw)


bands_strategy = st.lists(st.floats(420.0, 720.0), min_size=1, max_size=6, unique=True).map(sorted).filter(
    lambda c: len(c) == 1 or min(np.diff(c)) > 1e-3)


@settings(max_examples=20, **PROP)
@given(centers=bands_strategy, lens=st.sampled_from(["achromatic", "singlet"]), height_nm=st.floats(0.0, 5000.0),
       q=st.integers(1, 2), m=st.integers(1, 3), zo=st.sampled_from([None, 0.5, 3.0]))
def test_a_doe_of_constant_height_gives_the_lens_only_psf(centers, lens, height_nm, q, m, zo):
    """A constant height only adds a phase that is constant over the pupil: the PSF is the lens's alone (h = 0),
    for any band grid, lens, pupil oversampling, band sampling and object distance."""
    optics = _optics(centers, lens=lens, q=q, band_samples=m, object_distance_m=zo)
    n = optics.doe.n_cells
    flat = optics.psf_from_pupil(optics.expand_cells(torch.full((n, n), height_nm * 1e-9)))
    lens_only = optics.psf_from_pupil(optics.expand_cells(torch.zeros(n, n)))
    torch.testing.assert_close(flat.psf, lens_only.psf, rtol=0, atol=2e-5 * float(lens_only.psf.max()))
    assert torch.all(flat.energy <= 1.0 + 1e-5) and torch.all(flat.energy > 0)


@settings(max_examples=15, **PROP)
@given(centers=bands_strategy, m=st.integers(1, 3), seed=st.integers(0, 1000), lens=st.sampled_from(["achromatic", "singlet"]))
def test_each_band_alone_equals_the_stack_and_float64_equals_float32(centers, m, seed, lens):
    """psf_from_pupil(bands=slice(c, c+1)) is band c of the whole stack (wavelength batches of 4 split anywhere),
    and the optics in float64 give the float32 stack within float32 rounding."""
    optics = _optics(centers, band_samples=m, seed=seed, lens=lens)
    h = optics.pupil_heights()
    whole = optics.psf_from_pupil(h)
    for c in range(len(centers)):
        one = optics.psf_from_pupil(h, bands=slice(c, c + 1))
        torch.testing.assert_close(one.psf[0], whole.psf[c], rtol=1e-5, atol=1e-7)
    o64 = _optics(centers, band_samples=m, seed=seed, lens=lens).double()
    r64 = o64.psf_from_pupil(o64.pupil_heights())
    assert r64.psf.dtype == torch.float64
    torch.testing.assert_close(r64.psf.float(), whole.psf, rtol=0, atol=2e-5 * float(whole.psf.detach().max()))


@settings(max_examples=12, **PROP)
@given(centers=bands_strategy, lens=st.sampled_from(["achromatic", "singlet"]), dz_um=st.floats(-50.0, 50.0),
       zo=st.sampled_from([None, 2.0]))
def test_defocus_delta_is_the_defocus_of_the_optics_rebuilt_at_the_moved_sensor(centers, lens, dz_um, zo):
    """perturb.defocus_delta_per_m2 added to the optics' defocus equals the defocus of the optics built with the
    sensor Δz farther (its docstring's promise), wavelength by wavelength."""
    optics = _optics(centers, lens=lens, object_distance_m=zo, band_samples=2)
    dz = dz_um * 1e-6
    moved = rebuilt_optics(optics, sensor_distance_m=optics.sensor_distance_m + dz)
    got = optics.defocus_per_m2.double() + defocus_delta_per_m2(optics, dz)
    ref = moved.defocus_per_m2.double()
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-3 * float(ref.abs().max()) + 1.0)


@settings(max_examples=12, **PROP)
@given(centers=bands_strategy, lens=st.sampled_from(["achromatic", "singlet"]), zo=st.sampled_from([None, 0.2, 1.0]))
def test_sensor_distance_limits_bound_the_aliasing_of_the_moved_sensor(centers, lens, zo):
    """sensor_distance_limits_m's closed form against the criterion it solves: just inside each finite limit the
    aliasing measure is ≤ 1 at every wavelength, just outside it exceeds 1 somewhere."""
    optics = _optics(centers, lens=lens, object_distance_m=zo, cell_um=50.0)
    lo, hi = sensor_distance_limits_m(optics)
    assert lo <= 0 <= hi
    for lim in (lo, hi):
        if math.isfinite(lim) and lim != 0:
            assert sensor_distance_aliasing(optics, lim * (1 - 1e-6)).max() <= 1.0 + 1e-9
            assert sensor_distance_aliasing(optics, lim * (1 + 1e-6)).max() > 1.0 - 1e-9


# ------------------------------------------------------------------------------------------------
# Pure helpers: pupil, DOE height maps, shifts, FFT sizes
# ------------------------------------------------------------------------------------------------
@settings(max_examples=60, **PROP)
@given(radius_cells=st.integers(0, 400), frac=st.floats(0.0, 0.999), cell_um=st.sampled_from([0.5, 3.0, 7.0, 30.0, 50.0, 123.0]))
def test_cells_across_is_twice_the_whole_cells_in_the_radius_plus_one(radius_cells, frac, cell_um):
    """cells_across = 2·floor(R/Δ) + 1 (odd), R/Δ given as an exact integer plus a fraction (a radius of a whole
    number of cells is not lost to float rounding)."""
    r = (radius_cells + frac) * cell_um * 1e-6
    if r <= cell_um * 1e-6 / 2:
        return
    assert cells_across(r, cell_um * 1e-6) == 2 * radius_cells + 1


@settings(max_examples=25, **PROP)
@given(n=st.integers(1, 40), q=st.integers(1, 3), r_frac=st.floats(0.05, 0.75), aa=st.integers(1, 6))
def test_aperture_is_symmetric_and_its_area_is_the_circle(n, q, r_frac, aa):
    """The antialiased aperture is symmetric under both flips and the transpose, within [0, 1], and its
    area Σ·pitch² is πR² within the antialiasing grid's edge error (≤ perimeter × pitch/aa)."""
    cell = 1.0
    radius = r_frac * n * cell
    a = aperture_amplitude(n, cell, radius, q, aa)
    assert a.shape == (n * q, n * q) and a.min() >= 0 and a.max() <= 1
    np.testing.assert_array_equal(a, a.T)
    np.testing.assert_array_equal(a, a[::-1, :])
    np.testing.assert_array_equal(a, a[:, ::-1])
    pitch = cell / q
    area_in_grid = a.sum() * pitch**2
    half = n * cell / 2
    if radius <= half:  # the circle is inside the grid
        assert abs(area_in_grid - math.pi * radius**2) <= 2 * math.pi * radius * pitch / aa * 2 + 2 * pitch**2


@settings(max_examples=40, **PROP)
@given(levels=st.integers(2, 16), wrap=st.booleans(), seed=st.integers(0, 1000), span=st.floats(-2.0, 3.0))
def test_quantized_heights_are_levels_and_nearest_in_phase(levels, wrap, seed, span):
    """quantize_heights returns one of the L levels k·top/L; with wrap the circular distance to h (mod top) is
    ≤ half a step (the π/L phase error), without wrap a height inside [0, top − step] is within half a step."""
    top = 1.0e-6
    g = torch.Generator().manual_seed(seed)
    h = (torch.rand(50, generator=g, dtype=torch.float64) * span) * top
    q = quantize_heights(h, levels, top, wrap=wrap)
    k = q / (top / levels)
    assert torch.allclose(k, k.round(), atol=1e-9) and k.min() >= -1e-9 and k.max() <= levels - 1 + 1e-9
    step = top / levels
    if wrap:
        d = torch.remainder(q - h, top)
        d = torch.minimum(d, top - d)
        assert float(d.max()) <= step / 2 + 1e-15
    else:
        inside = (h >= 0) & (h <= top - step)
        if inside.any():
            assert float((q - h)[inside].abs().max()) <= step / 2 + 1e-15


@settings(max_examples=30, **PROP)
@given(hh=st.integers(1, 13), ww=st.integers(1, 13), sigma=st.floats(0.0, 6.0), seed=st.integers(0, 1000))
def test_periodic_gaussian_lowpass_equals_the_full_complex_fft_filter(hh, ww, sigma, seed):
    """gaussian_lowpass_periodic (real FFT, odd or even sizes) equals the same transfer exp(−2π²σ²f²) applied with
    numpy's complex FFT; the mean is kept."""
    x = torch.rand(hh, ww, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    got = gaussian_lowpass_periodic(x, sigma).numpy()
    fy, fx = np.fft.fftfreq(hh)[:, None], np.fft.fftfreq(ww)[None, :]
    ref = np.fft.ifft2(np.fft.fft2(x.numpy()) * np.exp(-2 * np.pi**2 * sigma**2 * (fy**2 + fx**2)))
    # the even-size Nyquist column: rfftfreq says +1/2, fftfreq −1/2, the same f²
    np.testing.assert_allclose(got, ref.real, atol=1e-12)
    assert abs(got.mean() - float(x.mean())) < 1e-12


@settings(max_examples=30, **PROP)
@given(n=st.integers(1, 40), period=st.floats(2.01, 100.0), top=st.floats(1e-9, 1e-5))
def test_crossed_grating_stays_in_range_and_is_symmetric(n, period, top):
    """Heights within [0, range] and h(x, y) = h(y, x) (a crossed grating of one period on both axes)."""
    h = crossed_grating_heights_m(n, period, top)
    assert h.shape == (n, n) and float(h.min()) >= -1e-18 and float(h.max()) <= top * (1 + 1e-12)
    torch.testing.assert_close(h, h.T, rtol=0, atol=1e-14 * top)  # (2 + s_i) + s_j vs (2 + s_j) + s_i: rounding


@settings(max_examples=60, **PROP)
@given(hh=st.integers(1, 9), ww=st.integers(1, 9), dy=st.integers(-11, 11), dx=st.integers(-11, 11))
def test_shift_fill_equals_a_brute_force_shift(hh, ww, dy, dx):
    """out[i, j] = x[i − dy, j − dx] where that is inside, else 0, for every shift (past the edge too)."""
    x = torch.arange(1, hh * ww + 1, dtype=torch.float64).reshape(hh, ww)
    ref = torch.zeros_like(x)
    for i in range(hh):
        for j in range(ww):
            if 0 <= i - dy < hh and 0 <= j - dx < ww:
                ref[i, j] = x[i - dy, j - dx]
    assert torch.equal(shift_fill(x, dy, dx), ref)


@settings(max_examples=60, **PROP)
@given(n=st.integers(1, 3000), x=st.floats(-3.0, 1e4))
def test_fft_lengths_and_odd_ceil_are_the_smallest_of_their_kind(n, x):
    """fast_fft_length: the smallest 7-smooth m ≥ n (brute force); odd_ceil: the smallest odd k ≥ x."""
    def smooth(m):
        for f in (2, 3, 5, 7):
            while m % f == 0:
                m //= f
        return m == 1
    ref = next(m for m in range(n, 2 * n + 8) if smooth(m))
    assert fast_fft_length(n) == ref
    k = odd_ceil(x)
    assert k % 2 == 1 and k >= x - 1e-9 and k - 2 < x - 1e-9


# ------------------------------------------------------------------------------------------------
# Convolutions: brute force, adjoints, batch items, memory layout
# ------------------------------------------------------------------------------------------------
sizes = dict(b=st.integers(1, 3), c=st.integers(1, 5), k=st.integers(0, 4), h=st.integers(1, 11), w=st.integers(1, 11),
             seed=st.integers(0, 2**16))


@settings(max_examples=40, **PROP)
@given(**sizes, layout=st.sampled_from(["contiguous", "transposed", "channels_last"]),
       chunk=st.sampled_from([1, 3000, 40000, cv.CHUNK_BYTES]))
def test_coded_convolutions_equal_shift_and_add_and_their_adjoints(b, c, k, h, w, seed, layout, chunk):
    """coded_conv_valid / coded_conv_same against numpy shift-and-add, for any sizes (1 px, prime, K wider than the
    image), any memory layout and any chunking of (batch, band) (one image at a time up to all at once);
    ⟨Ax, y⟩ = ⟨x, Aᵀy⟩ for both; batch item i = the call on item i alone; the fused op's gradients (x, psf, κ) are
    the adjoint's and the brute-force correlations."""
    saved = cv.CHUNK_BYTES
    cv.CHUNK_BYTES = chunk
    try:
        _check_coded_convolutions(b, c, k, h, w, seed, layout)
    finally:
        cv.CHUNK_BYTES = saved


def _check_coded_convolutions(b, c, k, h, w, seed, layout):
    g = torch.Generator().manual_seed(seed)
    kpx = 2 * k + 1
    psf = torch.rand(c, kpx, kpx, generator=g, dtype=torch.float64)
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64)

    def arrange(t):
        if layout == "transposed":
            return t.transpose(-1, -2).contiguous().transpose(-1, -2)
        if layout == "channels_last":
            return t.contiguous(memory_format=torch.channels_last)
        return t

    x = arrange(torch.randn(b, c, h + kpx - 1, w + kpx - 1, generator=g, dtype=torch.float64))
    xs = arrange(torch.randn(b, c, h, w, generator=g, dtype=torch.float64))
    y = torch.randn(b, 1, h, w, generator=g, dtype=torch.float64)
    ref_valid = (direct_valid_conv(x.numpy(), psf.numpy()) * kappa.numpy()).sum(1, keepdims=True)
    ref_same = (direct_valid_conv(np.pad(xs.numpy(), ((0, 0), (0, 0), (k, k), (k, k))), psf.numpy())
                * kappa.numpy()).sum(1, keepdims=True)
    got_valid = cv.coded_conv_valid(x, psf, kappa)
    got_same = cv.coded_conv_same(xs, psf, kappa)
    np.testing.assert_allclose(got_valid.numpy(), ref_valid, atol=1e-10)
    np.testing.assert_allclose(got_same.numpy(), ref_same, atol=1e-10)
    assert _adjoint_gap(got_valid, y, x, cv.coded_conv_valid_adjoint(y, psf, kappa)) < 1e-12
    assert _adjoint_gap(got_same, y, xs, cv.coded_conv_same_adjoint(y, psf, kappa)) < 1e-12
    for i in range(b):
        torch.testing.assert_close(cv.coded_conv_same(xs[i : i + 1], psf, kappa), got_same[i : i + 1])
        torch.testing.assert_close(cv.coded_conv_same_adjoint(y[i : i + 1], psf, kappa),
                                   cv.coded_conv_same_adjoint(y, psf, kappa)[i : i + 1])
    xg, pg, kg = (t.clone().requires_grad_(True) for t in (x, psf, kappa))
    (cv.coded_conv_valid(xg, pg, kg) * y).sum().backward()
    torch.testing.assert_close(xg.grad, cv.coded_conv_valid_adjoint(y, psf, kappa), rtol=0, atol=1e-10)
    conv = direct_valid_conv(x.detach().numpy(), psf.numpy())
    np.testing.assert_allclose(kg.grad.numpy(), (y.numpy() * conv).sum(0), atol=1e-10)
    coded_y, xn = (y * kappa).numpy(), x.detach().numpy()
    ref_psf = np.zeros((c, kpx, kpx))
    for dy in range(kpx):
        for dx in range(kpx):
            ref_psf[:, dy, dx] = (coded_y * xn[:, :, kpx - 1 - dy : kpx - 1 - dy + h, kpx - 1 - dx : kpx - 1 - dx + w]).sum((0, 2, 3))
    np.testing.assert_allclose(pg.grad.numpy(), ref_psf, atol=1e-10)


@settings(max_examples=40, **PROP)
@given(**sizes, mode=st.sampled_from(cv.PAD_MODES))
def test_pad_same_equals_numpy_pad_and_has_its_exact_adjoint(b, c, k, h, w, seed, mode):
    """pad_same against numpy.pad's modes, pad_same_adjoint by the definition, for every size the mode allows."""
    r = k
    kpx = 2 * k + 1
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(b, c, h, w, generator=g, dtype=torch.float64)
    np_mode = {"zeros": "constant", "reflect": "reflect", "replicate": "edge", "circular": "wrap"}[mode]
    if mode == "reflect" and (h <= r or w <= r):
        with pytest.raises(ValueError):
            cv.pad_same(x, kpx, mode)
        return
    if mode == "circular" and (h < r or w < r):
        return  # torch refuses a circular pad wider than the image (numpy wraps again)
    p = cv.pad_same(x, kpx, mode)
    np.testing.assert_array_equal(p.numpy(), np.pad(x.numpy(), ((0, 0), (0, 0), (r, r), (r, r)), mode=np_mode))
    yy = torch.randn(p.shape, generator=g, dtype=torch.float64)
    assert _adjoint_gap(p, yy, x, cv.pad_same_adjoint(yy, kpx, mode)) < 1e-12


# ------------------------------------------------------------------------------------------------
# DOE camera: adjoint for random band grids, sizes, CFA periods, boundaries; snapshot windows
# ------------------------------------------------------------------------------------------------
def _camera(centers, period, boundary="valid", padding="zeros", cfa=True, seed=0) -> DOECamera:
    optics = _optics(centers, seed=seed)
    cfa_m = ColorFilterArray(len(centers), period, cfa, seed)
    return DOECamera(optics.bands, optics, cfa_m, SensorNoise("none"), boundary, padding)


@settings(max_examples=20, **PROP)
@given(centers=bands_strategy, period=st.integers(1, 6), boundary=st.sampled_from(["valid", "same"]),
       padding=st.sampled_from(cv.PAD_MODES), b=st.integers(1, 2), h=st.integers(1, 13), w=st.integers(1, 13),
       cfa=st.booleans(), seed=st.integers(0, 1000))
def test_doe_camera_adjoint_and_reference_for_any_bands_and_sizes(centers, period, boundary, padding, b, h, w, cfa, seed):
    """DOECamera.A against the shift-and-add reference with its own PSFs and CFA (float64), ⟨Ax, y⟩ = ⟨x, Aᵀy⟩ for
    any band grid (1..6 bands, non-uniform), CFA period, boundary and padding the size allows."""
    cam = _camera(centers, period, boundary, padding, cfa, seed).double()
    kpx, r = cam.kernel_px, cam.kernel_px // 2
    if boundary == "same" and ((padding == "reflect" and min(h, w) <= r) or (padding == "circular" and min(h, w) < r)):
        return
    margin = 0 if boundary == "same" else kpx - 1
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(b, len(centers), h + margin, w + margin, generator=g, dtype=torch.float64)
    with torch.no_grad():
        psf = cam.psf()
        ax = cam.A(x, psf)
        y = torch.randn(ax.shape, generator=g, dtype=torch.float64)
        aty = cam.A_adjoint(y, psf)
    xin = x.numpy()
    if boundary == "same":
        np_mode = {"zeros": "constant", "reflect": "reflect", "replicate": "edge", "circular": "wrap"}[padding]
        xin = np.pad(xin, ((0, 0), (0, 0), (r, r), (r, r)), mode=np_mode)
    kappa = cam.cfa.pattern(h, w).detach().double().numpy()
    ref = (direct_valid_conv(xin, psf.numpy()) * kappa).sum(1, keepdims=True)
    np.testing.assert_allclose(ax.numpy(), ref, atol=1e-12)
    assert _adjoint_gap(ax, y, x, aty) < 1e-12


@settings(max_examples=20, **PROP)
@given(centers=bands_strategy, period=st.integers(1, 5), hh=st.integers(8, 20), ww=st.integers(8, 20),
       r0=st.integers(0, 7), c0=st.integers(0, 7), th=st.integers(1, 12), tw=st.integers(1, 12), seed=st.integers(0, 99))
def test_doe_snapshot_window_at_any_origin_is_the_whole_image_there(centers, period, hh, ww, r0, c0, th, tw, seed):
    """DOESnapshot.A on a window at ``origin`` sees the CFA phase of the whole sensor there: the window's pixels at
    least K//2 from its edges equal the whole image's (zero padding changes only the border); and Aᵀ is its
    adjoint at that origin."""
    cam = _camera(centers, period, seed=seed).double()
    with torch.no_grad():
        snap = cam.snapshot()
        th, tw = min(th, hh - r0), min(tw, ww - c0)
        if th < 1 or tw < 1:
            return
        g = torch.Generator().manual_seed(seed)
        x = torch.rand(1, len(centers), hh, ww, generator=g, dtype=torch.float64)
        whole = snap.A(x)
        tile = snap.A(x[..., r0 : r0 + th, c0 : c0 + tw], origin=(r0, c0))
        r = snap.kernel_px // 2
        if th > 2 * r and tw > 2 * r:  # a window with pixels K//2 from its edges
            inner = whole[..., r0 + r : r0 + th - r, c0 + r : c0 + tw - r]
            torch.testing.assert_close(tile[..., r : th - r, r : tw - r], inner, rtol=1e-12, atol=1e-12)
        y = torch.randn(tile.shape, generator=g, dtype=torch.float64)
        xt = x[..., r0 : r0 + th, c0 : c0 + tw]
        assert _adjoint_gap(tile, y, xt, snap.A_adjoint(y, origin=(r0, c0))) < 1e-12


@settings(max_examples=10, **PROP)
@given(centers=bands_strategy, period=st.integers(1, 4), h=st.integers(1, 9), w=st.integers(1, 9), seed=st.integers(0, 99))
def test_fixed_psf_camera_images_with_its_psf_and_float32_follows_float64(centers, period, h, w, seed):
    """FixedPSFCamera images with the stack it was given (brute-force reference), and the float32 camera gives the
    float64 image within float32 rounding (the PSF kept in float32 either way)."""
    cam = _camera(centers, period, seed=seed)
    k = cam.kernel_px
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(len(centers), k, k, generator=g)
    fixed = FixedPSFCamera.from_camera(cam, psf)
    x = torch.rand(2, len(centers), h + k - 1, w + k - 1, generator=g)
    with torch.no_grad():
        y32 = fixed.A(x)
        y64 = fixed.A(x.double())
    kappa = cam.cfa.pattern(h, w).detach().double().numpy()
    ref = (direct_valid_conv(x.double().numpy(), psf.double().numpy()) * kappa).sum(1, keepdims=True)
    np.testing.assert_allclose(y64.numpy(), ref, atol=1e-10)
    np.testing.assert_allclose(y32.double().numpy(), ref, rtol=1e-5, atol=1e-5 * float(np.abs(ref).max()))


# ------------------------------------------------------------------------------------------------
# CASSI: explicit operator matrices, windows, dispersion rounding
# ------------------------------------------------------------------------------------------------
@settings(max_examples=30, **PROP)
@given(kind=st.sampled_from(["dd", "sd"]), c=st.integers(1, 6), h=st.integers(1, 5), w=st.integers(1, 6),
       shift=st.floats(0.3, 3.0), convention=st.sampled_from(["sum", "mean"]), seed=st.integers(0, 999),
       density=st.floats(0.1, 1.0))
def test_cassi_operator_matrix_is_the_definition_and_gram_diagonal_is_its_diagonal(kind, c, h, w, shift, convention,
                                                                                     seed, density):
    """CASSI A built column by column equals the module docstring's sums written out; Aᵀ is its transpose (exact
    matrices); gram_diagonal = diag(A Aᵀ) and A Aᵀ is diagonal; lipschitz ≥ ‖A‖²."""
    bands = Bands.uniform(450.0, 450.0 + 10 * (c - 1), 10.0) if c > 1 else Bands(np.array([500.0]), np.array([10.0]))
    shifts = linear_dispersion(c, shift)
    ap = CodedAperture(seed, density)
    cam = (DDCASSICamera if kind == "dd" else SDCASSICamera)(bands, ap, shifts, convention=convention).double()
    d = max(shifts)
    s = 1.0 / c if convention == "mean" else 1.0
    wy = w if kind == "dd" else w + d
    pat = ap.pattern(h, w + d, dtype=torch.float64).numpy()
    n_in, n_out = c * h * w, h * wy
    a_ref = np.zeros((n_out, n_in))
    for cc in range(c):
        for i in range(h):
            for j in range(w):
                col = (cc * h + i) * w + j
                if kind == "dd":
                    a_ref[i * wy + j, col] += s * pat[i, j + shifts[cc]]
                else:
                    a_ref[i * wy + j + shifts[cc], col] += s * pat[i, j]
    eye = torch.eye(n_in, dtype=torch.float64).reshape(n_in, c, h, w)
    with torch.no_grad():
        a = cam.A(eye).reshape(n_in, n_out).T.numpy()
        at = cam.A_adjoint(torch.eye(n_out, dtype=torch.float64).reshape(n_out, 1, h, wy)).reshape(n_out, n_in).numpy()
        snap = CASSISnapshot(cam)
        gd = snap.gram_diagonal(torch.zeros(1, 1, h, wy, dtype=torch.float64)).reshape(-1).numpy()
    np.testing.assert_allclose(a, a_ref, atol=1e-15)
    np.testing.assert_allclose(at, a_ref, atol=1e-15)
    gram = a_ref @ a_ref.T
    np.testing.assert_allclose(gram, np.diag(np.diag(gram)), atol=1e-15)
    np.testing.assert_allclose(gd, np.diag(gram), atol=1e-15)
    assert snap.lipschitz >= np.linalg.norm(a_ref, 2) ** 2 - 1e-12


@settings(max_examples=30, **PROP)
@given(kind=st.sampled_from(["dd", "sd"]), c=st.integers(1, 5), hh=st.integers(1, 9), ww=st.integers(1, 12),
       r0=st.integers(0, 6), c0=st.integers(0, 8), th=st.integers(1, 9), tw=st.integers(1, 12), shift=st.floats(0.5, 2.5),
       off=st.tuples(st.integers(0, 5), st.integers(0, 5)), b=st.integers(1, 3))
def test_cassi_window_at_any_origin_is_the_whole_measurement_there(kind, c, hh, ww, r0, c0, th, tw, shift, off, b):
    """CASSISnapshot.A of a scene window at ``origin`` equals the whole measurement's window (DD: all of it; SD: the
    sensor columns whose every band comes from inside the window), at any aperture offset; batch items apart."""
    th, tw = min(th, hh - r0), min(tw, ww - c0)
    if th < 1 or tw < 1:
        return
    bands = Bands.uniform(450.0, 450.0 + 10 * (c - 1), 10.0) if c > 1 else Bands(np.array([500.0]), np.array([10.0]))
    shifts = linear_dispersion(c, shift)
    cam = (DDCASSICamera if kind == "dd" else SDCASSICamera)(bands, CodedAperture(3), shifts).double()
    snap = CASSISnapshot(cam, offset=off)
    x = torch.rand(b, c, hh, ww, generator=torch.Generator().manual_seed(r0 * 31 + c0), dtype=torch.float64)
    with torch.no_grad():
        whole = snap.A(x)
        tile = snap.A(x[..., r0 : r0 + th, c0 : c0 + tw], origin=(r0, c0))
        one = snap.A(x[1:2, ..., r0 : r0 + th, c0 : c0 + tw], origin=(r0, c0)) if b > 1 else None
    d = max(shifts)
    if kind == "dd":
        torch.testing.assert_close(tile, whole[..., r0 : r0 + th, c0 : c0 + tw], rtol=0, atol=1e-15)
    elif tw > d:
        torch.testing.assert_close(tile[..., d:tw], whole[..., r0 : r0 + th, c0 + d : c0 + tw], rtol=0, atol=1e-15)
    if one is not None:
        torch.testing.assert_close(one, tile[1:2], rtol=0, atol=0)


@settings(max_examples=60, **PROP)
@given(c=st.integers(1, 80), num=st.integers(1, 500), den=st.sampled_from([2, 4, 10, 100, 1000]))
def test_linear_dispersion_rounds_exact_halves_up(c, num, den):
    """d_c = ⌊shift·c + ½⌋ computed exactly (shift = num/den px, a decimal as a config gives it): a product that is
    a half rounds up, as the docstring says, whatever the float rounding of shift·c."""
    ref = [math.floor(Fraction(num, den) * i + Fraction(1, 2)) for i in range(c)]
    assert linear_dispersion(c, num / den) == ref


def test_linear_dispersion_of_a_decimal_shift_rounds_its_halves_up():
    """0.7 px × band 45 = 31.5 px and 0.29 px × band 50 = 14.5 px round up to 32 and 15 (binary 0.7 and 0.29 are a
    hair below: the products came out 31.499… and 14.499…, rounded down to 31 and 14)."""
    assert linear_dispersion(46, 0.7)[45] == 32
    assert linear_dispersion(51, 0.29)[50] == 15
    assert linear_dispersion(46, 0.7) == [math.floor(Fraction(7, 10) * i + Fraction(1, 2)) for i in range(46)]


def test_psf_gradient_of_a_training_batch_reuses_the_scene_spectra_and_equals_brute_force(monkeypatch):
    """A scene without a gradient (a training batch) and PSFs with one: the PSF gradient equals the brute-force
    correlation of the coded gradient with the scene, and the backward transforms no scene again (the forward's
    spectra are kept; it made one rFFT a chunk of (batch, band), 0.1 s of the quick camera's step on 1 thread)."""
    g = torch.Generator().manual_seed(3)
    b, c, kpx, h, w = 2, 3, 5, 7, 6
    x = torch.randn(b, c, h + kpx - 1, w + kpx - 1, generator=g, dtype=torch.float64)
    psf = torch.rand(c, kpx, kpx, generator=g, dtype=torch.float64, requires_grad=True)
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.randn(b, 1, h, w, generator=g, dtype=torch.float64)
    monkeypatch.setattr(cv, "CHUNK_BYTES", 1)  # one image a chunk: the most chunks
    out = cv.coded_conv_valid(x, psf, kappa)
    calls = []
    rfft2 = torch.fft.rfft2
    monkeypatch.setattr(torch.fft, "rfft2", lambda *a, **k: calls.append(a[0].shape) or rfft2(*a, **k))
    (out * y).sum().backward()
    assert calls == []
    coded_y, xn = (y * kappa.detach()).numpy(), x.numpy()
    ref_psf = np.zeros((c, kpx, kpx))
    for dy in range(kpx):
        for dx in range(kpx):
            ref_psf[:, dy, dx] = (coded_y * xn[:, :, kpx - 1 - dy : kpx - 1 - dy + h, kpx - 1 - dx : kpx - 1 - dx + w]).sum((0, 2, 3))
    np.testing.assert_allclose(psf.grad.numpy(), ref_psf, atol=1e-10)
    np.testing.assert_allclose(kappa.grad.numpy(), (y.numpy() * direct_valid_conv(xn, psf.detach().numpy())).sum(0),
                               atol=1e-10)


def test_the_coded_convolution_keeps_nothing_for_a_backward_under_no_grad(monkeypatch):
    """PSFs and CFA made with a gradient, then imaged under no_grad (an evaluation): no backward will come, so the
    forward holds one scene spectrum at a time, as in a recorded call whose scene needs a gradient, not every chunk's
    (ctx.needs_input_grad follows requires_grad alone, whatever the grad mode); the image is the recorded call's."""
    g = torch.Generator().manual_seed(4)
    b, c, kpx, h, w = 2, 3, 5, 7, 6
    x = torch.randn(b, c, h + kpx - 1, w + kpx - 1, generator=g, dtype=torch.float64)
    psf = torch.rand(c, kpx, kpx, generator=g, dtype=torch.float64, requires_grad=True)
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    monkeypatch.setattr(cv, "CHUNK_BYTES", 1)  # one image a chunk: b * c = 6 chunks
    spectra, alive = [], []
    rfft2, add_coded = torch.fft.rfft2, cv._add_coded

    def kept_rfft2(*a, **k):
        out = rfft2(*a, **k)
        if a[0].shape[-3] == 1 and a[0].dim() == 4:  # a scene chunk (1, 1, Lh, Lw); the PSFs' are (1, Lh, Lw)
            spectra.append(weakref.ref(out))
        return out

    def counting_add_coded(*a, **k):
        alive.append(sum(r() is not None for r in spectra))
        return add_coded(*a, **k)

    monkeypatch.setattr(torch.fft, "rfft2", kept_rfft2)
    monkeypatch.setattr(cv, "_add_coded", counting_add_coded)
    with torch.no_grad():
        evaluated = cv.coded_conv_valid(x, psf, kappa)
    assert len(alive) == b * c and max(alive) == 1
    spectra.clear(); alive.clear()
    recorded = cv.coded_conv_valid(x, psf, kappa)  # a training batch: every chunk's spectrum kept for the backward
    assert alive == list(range(1, b * c + 1))
    torch.testing.assert_close(evaluated, recorded.detach(), rtol=0, atol=0)


@pytest.mark.parametrize("m", [1, 3])
def test_a_stepped_band_slice_is_refused_not_read_as_a_contiguous_one(m):
    """psf_from_pupil(bands=slice(0, 6, 2)) dropped the step: with one sample a band it returned bands 0-5 (six, not
    0, 2, 4), with three a torch shape error (session 74's docstring hunt). A contiguous slice is band for band the
    stack's, a stepped one one clear error."""
    optics = _optics([450.0, 480.0, 510.0, 540.0, 570.0, 600.0], band_samples=m)
    h = optics.pupil_heights()
    whole = optics.psf_from_pupil(h)
    part = optics.psf_from_pupil(h, bands=slice(1, 4))
    torch.testing.assert_close(part.psf, whole.psf[1:4], rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match=r"contiguous slice \(step 1\)"):
        optics.psf_from_pupil(h, bands=slice(0, 6, 2))
