"""Guards found by mutation testing of the numerical core: each test kills a hand-made mutant (a flipped sign, a
dropped bound, a skipped branch) that the rest of the suite let through, and checks the behaviour against a reference
computed here (thin-lens equation and the square-cell Fraunhofer integral, brute-force area fractions, the DOE's phase
modulo 2π, closed forms), not against the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hsicam.optics.doe import DOE, crossed_grating_heights_m
from hsicam.optics.lens import AchromaticLens
from hsicam.optics.psf import PSFModel
from hsicam.spectral import Bands, FusedSilica
from optics_reference import relative_l1, sellmeier_fused_silica, square_cell_psf

H2PI_587 = 587.6e-9 / (sellmeier_fused_silica(587.6) - 1.0)


# --------------------------------------------------------------------------------------------
# optics/psf.py
# --------------------------------------------------------------------------------------------
def test_an_object_at_a_finite_distance_is_in_focus_at_its_thin_lens_conjugate():
    """Object at z_o = 2 m, sensor at the conjugate z_i = 1/(1/f − 1/z_o) (Gaussian lens equation): no residual
    defocus, so the PSF is the aperture's Fraunhofer pattern at z_i (independent square-cell integral). A sign error
    on 1/z_o puts 2 waves of defocus at the pupil's edge (relative L1 far above 2 %)."""
    f, zo, radius, cell, pixel, lam = 35e-3, 2.0, 1.5e-3, 30e-6, 12e-6, 550.0
    zi = 1.0 / (1.0 / f - 1.0 / zo)
    n = 2 * int(radius / cell + 1e-9) + 1
    doe = DOE(n, FusedSilica(), 587.6, enabled=False)
    model = PSFModel(Bands.from_centers([lam]), AchromaticLens(f), doe, radius, cell, pixel,
                     sensor_distance_m=zi, object_distance_m=zo).double()
    with torch.no_grad():
        psf = model().psf[0].numpy()
    k = psf.shape[-1]
    ref = square_cell_psf(model.amplitude.numpy().astype(complex), cell, lam * 1e-9, zi, pixel, np.arange(k) - k // 2,
                          sub=15)
    assert relative_l1(psf, ref) < 0.02


def test_aperture_per_cell_is_the_area_fraction_of_each_cell_inside_the_circle():
    """With pupil oversampling the per-cell transmission (export, reports) is the area of each DOE cell inside the
    aperture circle over the cell's area: brute force on 96×96 points per cell, and Σ Δ² × fraction ≈ πR²."""
    radius, cell, q = 0.25e-3, 50e-6, 3
    n = 2 * int(radius / cell + 1e-9) + 1
    doe = DOE(n, FusedSilica(), 587.6, enabled=False)
    model = PSFModel(Bands.from_centers([550.0]), AchromaticLens(5e-3), doe, radius, cell, 10e-6, pupil_oversample=q)
    got = model.aperture_per_cell()
    sub = 96
    centres = (np.arange(n) - (n - 1) / 2) * cell
    pts = ((np.arange(sub) + 0.5) / sub - 0.5) * cell
    xs = (centres[:, None] + pts[None, :]).reshape(-1)
    ref = ((xs[:, None] ** 2 + xs[None, :] ** 2) <= radius**2).reshape(n, sub, n, sub).mean(axis=(1, 3))
    assert got.shape == (n, n)
    np.testing.assert_allclose(got, ref, atol=0.03)
    assert got.sum() * cell**2 == pytest.approx(math.pi * radius**2, rel=0.01)


# --------------------------------------------------------------------------------------------
# optics/doe.py
# --------------------------------------------------------------------------------------------
def test_crossed_grating_is_centred_on_the_middle_cell():
    """h = range/4 · (2 + sin(2πx/Λ) + sin(2πy/Λ)) with x, y measured from the grid's centre cell: that cell is at
    range/2, and the map is point-antisymmetric about it (h(−x, −y) = range − h(x, y))."""
    n, period, top = 21, 7.0, 1e-6
    h = crossed_grating_heights_m(n, period, top).numpy()
    assert h[n // 2, n // 2] == pytest.approx(top / 2, abs=1e-18)
    np.testing.assert_allclose(h + h[::-1, ::-1], top, atol=1e-18)
    x = np.arange(n) - n // 2
    np.testing.assert_allclose(h[n // 2], top / 4 * (2 + np.sin(2 * np.pi * x / period)), atol=1e-18)


def test_height_clamp_bounds_both_ends():
    """``max_height_m`` clamps the effective heights to [0, max] (numpy's clip), negative values included."""
    top = 0.8 * H2PI_587
    doe = DOE(9, FusedSilica(), 587.6, init="zeros", max_height_m=top)
    raw = torch.from_numpy(np.random.default_rng(1).uniform(-top, 2 * top, size=(9, 9)))
    with torch.no_grad():
        doe.height_m.copy_(raw)
    np.testing.assert_allclose(doe.heights().detach().double().numpy(), np.clip(doe.height_m.detach().double().numpy(), 0, top),
                               rtol=1e-6, atol=1e-15)


def test_wrapped_heights_lie_in_one_phase_period_with_the_same_phase_at_the_design_wavelength():
    """``wrap``: heights are reduced modulo h_2π into [0, h_2π), which leaves the phase exp(iφ) at the design
    wavelength unchanged (φ = 2π (n − 1) h / λ0, Sellmeier written out in the test helpers)."""
    doe = DOE(9, FusedSilica(), 587.6, init="zeros", wrap=True)
    raw = np.random.default_rng(2).uniform(-H2PI_587, 3 * H2PI_587, size=(9, 9))
    with torch.no_grad():
        doe.height_m.copy_(torch.from_numpy(raw))
    raw = doe.height_m.detach().double().numpy()
    h = doe.heights().detach().double().numpy()
    assert h.min() >= 0 and h.max() < H2PI_587 * (1 + 1e-6)
    per_height = 2 * np.pi * (sellmeier_fused_silica(587.6) - 1.0) / 587.6e-9
    np.testing.assert_allclose(np.exp(1j * per_height * h), np.exp(1j * per_height * raw), atol=2e-5)


def test_quantisation_of_a_wrapped_and_clamped_doe_uses_the_phase_levels():
    """With ``wrap`` the L levels are those of a phase period, k·h_2π/L, even when a height clamp is set too (the
    levels of a clamp range k·max/L apply only without wrapping: :meth:`DOE.level_grid`)."""
    levels = 4
    doe = DOE(15, FusedSilica(), 587.6, init="random", seed=3, wrap=True, max_height_m=0.6 * H2PI_587,
              quantization_levels=levels)
    k = doe.heights().detach().double().numpy() / (H2PI_587 / levels)
    np.testing.assert_allclose(k, np.round(k), atol=1e-4)
    assert set(np.round(k).astype(int).ravel()) <= {0, 1, 2, 3}
    assert len(set(np.round(k).astype(int).ravel())) >= 3


@pytest.mark.parametrize("init_range_m", [None, 0.7e-6])
def test_a_smooth_init_spans_zero_to_its_range_exactly(init_range_m):
    """``init="smooth"``: the low-passed random field is rescaled to span [0, range] exactly, the range being
    ``init_range_m`` or by default h_2π = λ0/(n(λ0) − 1) at the design wavelength (Sellmeier written out here)."""
    top = H2PI_587 if init_range_m is None else init_range_m
    doe = DOE(31, FusedSilica(), 587.6, init="smooth", seed=4, init_range_m=init_range_m, init_correlation_cells=3.0)
    h = doe.height_m.detach().double().numpy()
    assert h.min() == pytest.approx(0.0, abs=1e-6 * top)
    assert h.max() == pytest.approx(top, rel=1e-6)
    assert np.unique(h).size > 100  # a structured field, not a few levels


def test_the_default_grating_depth_puts_equal_light_into_the_0th_and_1st_orders():
    """``init="grating"`` without a range: along a row through the centre the phase at λ0 is φ0 + m·sin(2πx/Λ),
    whose orders carry J_p(m)² (Jacobi–Anger); the default depth is the one with J0(m) = J1(m) (scipy's Bessel
    functions), about 30 % of the light in each of the 0th and ±1st orders per axis."""
    from scipy.special import jv

    n, period = 17, 8.0  # the centre row's cells at x = ±2 sit on the sine's extremes
    h = DOE(n, FusedSilica(), 587.6, init="grating", init_grating_period_cells=period).height_m.detach().double()
    phase = 2 * np.pi * (sellmeier_fused_silica(587.6) - 1.0) * h.numpy()[n // 2] / 587.6e-9
    m = (phase.max() - phase.min()) / 2
    assert jv(0, m) == pytest.approx(jv(1, m), abs=1e-5)
    assert jv(0, m) ** 2 == pytest.approx(0.30, abs=0.005)


# --------------------------------------------------------------------------------------------
# sensor.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("origin", [(1, 2), (4, 0), (2, 3)])
def test_a_cfa_window_at_an_origin_is_that_window_of_the_sensors_pattern(origin):
    """``pattern(h, w, origin)`` is the CFA over the sensor pixels [oy, oy + h) × [ox, ox + w): the same values as
    the pattern from pixel (0, 0), cut there."""
    from hsicam.sensor import ColorFilterArray

    cfa = ColorFilterArray(3, period=5, seed=2)
    oy, ox = origin
    with torch.no_grad():
        whole = cfa.pattern(oy + 7, ox + 8)
        window = cfa.pattern(7, 8, origin)
    torch.testing.assert_close(window, whole[:, oy:, ox:], rtol=0, atol=0)


def test_bandpass_weights_are_gaussians_plus_a_one_percent_floor():
    """One filter (period 1) centred mid-range: w(λ) = exp(−(λ − c)² / (2σ²)) + 0.01, σ = FWHM / (2√(2 ln 2))."""
    from hsicam.sensor import bandpass_weights

    lam = np.array([450.0, 500.0, 550.0, 600.0, 650.0])
    w = bandpass_weights(torch.from_numpy(lam), 1, 80.0).double().numpy()[:, 0, 0]
    sigma = 80.0 / (2 * np.sqrt(2 * np.log(2)))
    np.testing.assert_allclose(w, np.exp(-0.5 * ((lam - 550.0) / sigma) ** 2) + 0.01, rtol=1e-6)


# --------------------------------------------------------------------------------------------
# color.py
# --------------------------------------------------------------------------------------------
def test_xyz_of_a_spectrum_is_the_integral_of_its_piecewise_linear_interpolant():
    """XYZ of a reflectance that is 1 at the first band of a 500–600 nm grid and 0 at the others: its piecewise-linear
    hat times x̄, ȳ, z̄ and D65 (the shipped table, linearly interpolated), integrated on a 0.01 nm grid and divided by
    the white reflector's Y over the grid's range."""
    from hsicam.color import cmf_d65_table, spectra_to_xyz
    from hsicam.spectral import Bands

    centers = np.arange(500.0, 601.0, 10.0)
    spectrum = np.zeros(centers.size)
    spectrum[0] = 1.0
    got = spectra_to_xyz(spectrum, Bands.from_centers(centers))
    table = cmf_d65_table()
    lam = np.linspace(500.0, 600.0, 10001)
    cmf = np.stack([np.interp(lam, table[:, 0], table[:, k]) for k in (1, 2, 3)])
    d65 = np.interp(lam, table[:, 0], table[:, 4])
    hat = np.clip(1.0 - (lam - 500.0) / 10.0, 0.0, None)
    trap = lambda f: float(np.sum((f[1:] + f[:-1]) / 2 * np.diff(lam)))  # noqa: E731
    white_y = trap(cmf[1] * d65)
    ref = np.array([trap(hat * cmf[k] * d65) for k in range(3)]) / white_y
    np.testing.assert_allclose(got, ref, rtol=1e-2)  # the package sums on a 1 nm grid: 0.4 % off
