"""Wave-optics PSF against closed-form optics (Airy pattern, grating equation, Sellmeier focus,
thin-lens power of a Fresnel DOE, sinc² envelope of DOE cells) and its sampling plan and gradients.

References are computed here, independently of the code under test (scipy's Bessel J1, our own
Sellmeier evaluation of Malitson's coefficients, grating and lens equations).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import quad
from scipy.special import j1, jn_zeros

from hsicam.cameras import DOECamera
from hsicam.config import load_config
from hsicam.errors import ConfigError
from hsicam.optics.doe import DOE
from hsicam.optics.lens import AchromaticLens, SingletLens
from hsicam.optics.psf import PSFModel, psf_stack
from hsicam.optics.pupil import aperture_amplitude, sample_coordinates_m
from hsicam.spectral import Bands, FusedSilica

# --------------------------------------------------------------------------------------------
# Independent references
# --------------------------------------------------------------------------------------------
AIRY_FIRST_ZERO = float(jn_zeros(1, 1)[0]) / math.pi  # 1.2197: first zero at 1.22·λ·F#


def sellmeier_fused_silica(lam_nm):
    """n(λ) of fused silica, Malitson (1965), written out here (not taken from the package)."""
    l2 = (np.asarray(lam_nm, dtype=np.float64) * 1e-3) ** 2
    terms = [(0.6961663, 0.0684043), (0.4079426, 0.1162414), (0.8974794, 9.896161)]
    return np.sqrt(1.0 + sum(b * l2 / (l2 - c * c) for b, c in terms))


def airy(r_m, lam_m, radius_m, z_m):
    """Normalised Airy intensity [2 J1(v)/v]², v = 2π R r / (λ z)."""
    v = 2.0 * np.pi * radius_m * np.asarray(r_m) / (lam_m * z_m)
    vs = np.where(v == 0, 1.0, v)
    return np.where(v == 0, 1.0, 2.0 * j1(vs) / vs) ** 2


def airy_peak_energy(pixel_m, lam_m, radius_m, z_m):
    """Energy fraction that lands on a pixel of area p² at the Airy peak: p²·πR²/(λz)²."""
    return pixel_m**2 * np.pi * radius_m**2 / (lam_m * z_m) ** 2


def centroid_px(img: np.ndarray, half: int = 6, rel_threshold: float = 0.05) -> tuple[float, float]:
    """Sub-pixel (row, col) centroid of the main lobe around the maximum."""
    iy, ix = np.unravel_index(np.argmax(img), img.shape)
    win = img[iy - half : iy + half + 1, ix - half : ix + half + 1]
    win = np.where(win > rel_threshold * win.max(), win, 0.0)
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1]
    return iy + (win * yy).sum() / win.sum(), ix + (win * xx).sum() / win.sum()


def rms_radius(psf: np.ndarray, pixel_m: float) -> float:
    c = psf.shape[-1] // 2
    yy, xx = (np.mgrid[: psf.shape[0], : psf.shape[1]] - c) * pixel_m
    w = psf / psf.sum()
    return float(np.sqrt((w * (xx**2 + yy**2)).sum()))


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().double().cpu().numpy()


# A finely sampled camera (R = 0.5 mm, 10 µm cells, f = 35 mm): F# = 35, 50 cells per radius.
FINE_R_M, FINE_CELL_M, FINE_F_M = 0.5e-3, 10e-6, 35e-3


def fine_camera(pixel_um: float, bands: tuple[float, float, float], *extra: str) -> DOECamera:
    cfg = load_config(overrides=[
        "camera.cfa.enabled=false",
        f"camera.aperture_radius_mm={FINE_R_M * 1e3}",
        f"camera.doe.cell_size_um={FINE_CELL_M * 1e6}",
        f"camera.lens.focal_length_mm={FINE_F_M * 1e3}",
        f"camera.sensor.pixel_pitch_um={pixel_um}",
        f"bands.start_nm={bands[0]}", f"bands.stop_nm={bands[1]}", f"bands.step_nm={bands[2]}",
        *extra,
    ])
    return DOECamera.from_config(cfg)


# --------------------------------------------------------------------------------------------
# (1) No DOE, achromatic lens: the Airy pattern
# --------------------------------------------------------------------------------------------
AIRY_PIXEL_M = 2.5e-6  # ~8.5 px per Airy radius at 500 nm; λz/(pΔ) is an integer for every band
AIRY_BANDS = (450.0, 600.0, 50.0)


@pytest.fixture(scope="module")
def airy_point_samples():
    """(camera, psf (C,K,K) float64, energy (C,)) with supersample=1 (point samples of the PSF)."""
    cam = fine_camera(AIRY_PIXEL_M * 1e6, AIRY_BANDS, "camera.doe.enabled=false", "camera.psf.supersample=1")
    with torch.no_grad():
        res = cam.psf_result()
    return cam, _np(res.psf), _np(res.energy)


@pytest.mark.parametrize("band", range(4))
def test_airy_pattern_absolute_values(airy_point_samples, band):
    cam, psf, _ = airy_point_samples
    lam = cam.bands.centers_nm[band] * 1e-9
    k = psf.shape[-1]
    c = k // 2
    yy, xx = (np.mgrid[:k, :k] - c) * AIRY_PIXEL_M
    peak = airy_peak_energy(AIRY_PIXEL_M, lam, FINE_R_M, FINE_F_M)
    ref = peak * airy(np.hypot(xx, yy), lam, FINE_R_M, FINE_F_M)
    assert np.unravel_index(np.argmax(psf[band]), psf[band].shape) == (c, c)  # axis on the centre pixel
    assert psf[band, c, c] == pytest.approx(peak, rel=0.015)
    # whole kernel, absolute: within 1.5 % of the peak (the residual is the Parseval normalisation
    # over the anti-aliased aperture edge, ~0.7 % for 50 cells per radius)
    assert np.abs(psf[band] - ref).max() < 0.015 * peak


@pytest.mark.parametrize("band", range(4))
def test_airy_first_zero_at_1_22_lambda_fnumber(airy_point_samples, band):
    cam, psf, _ = airy_point_samples
    lam = cam.bands.centers_nm[band] * 1e-9
    f_number = FINE_F_M / (2 * FINE_R_M)
    r0_px = AIRY_FIRST_ZERO * lam * f_number / AIRY_PIXEL_M
    k = psf.shape[-1]
    c = k // 2
    r = np.hypot(*(np.mgrid[:k, :k] - c))
    img = psf[band] / psf[band, c, c]
    # locate the dark ring from the PSF alone: signed amplitude (+ inside the darkest pixel's
    # radius, − outside) is smooth through the zero; fit a quadratic in r and take its root
    ring = (r > 0.6 * r0_px) & (r < 1.4 * r0_px)
    r_min = r[ring][np.argmin(img[ring])]
    sel = np.abs(r - r_min) < 1.2
    amp = np.sqrt(img[sel]) * np.where(r[sel] < r_min, 1.0, -1.0)
    coef = np.polyfit(r[sel] - r_min, amp, 2)
    roots = np.roots(coef)
    zero = r_min + roots[np.argmin(np.abs(roots))].real
    assert zero == pytest.approx(r0_px, rel=0.015)
    assert img[np.abs(r - r0_px) < 0.3].max() < 2e-3  # dark ring: < 0.2 % of the peak


def test_psf_sums_to_reported_energy_and_parseval(airy_point_samples):
    _, psf, energy = airy_point_samples
    np.testing.assert_allclose(psf.sum(axis=(-2, -1)), energy, rtol=1e-5)
    # the kernel holds the whole FFT plane here, and the plane is normalised to 1 (Parseval)
    np.testing.assert_allclose(energy, 1.0, atol=1e-5)


def test_airy_supersampled_matches_pixel_integrated_airy():
    """supersample=3: each pixel holds the Airy pattern integrated over its area."""
    pixel = 7.5e-6  # 2.8 px per Airy radius at 500 nm: pixel integration matters
    cam = fine_camera(pixel * 1e6, (500.0, 600.0, 100.0), "camera.doe.enabled=false", "camera.psf.supersample=3")
    assert cam.optics.sampling.supersample == 3
    with torch.no_grad():
        psf = _np(cam.psf())
    c, w, n = psf.shape[-1] // 2, 30, 15  # compare a 61×61 window; 15×15 quadrature per pixel
    sub = (np.arange(n) + 0.5) / n - 0.5
    g = (np.arange(-w, w + 1)[:, None] + sub[None, :]).reshape(-1) * pixel
    yy, xx = np.mgrid[-w : w + 1, -w : w + 1] * pixel
    for band, lam_nm in enumerate(cam.bands.centers_nm):
        lam = lam_nm * 1e-9
        peak = airy_peak_energy(pixel, lam, FINE_R_M, FINE_F_M)
        integrated = peak * airy(np.hypot(g[:, None], g[None, :]), lam, FINE_R_M, FINE_F_M)
        integrated = integrated.reshape(2 * w + 1, n, 2 * w + 1, n).mean(axis=(1, 3))
        point = peak * airy(np.hypot(xx, yy), lam, FINE_R_M, FINE_F_M)
        got = psf[band, c - w : c + w + 1, c - w : c + w + 1]
        err_integrated = np.abs(got - integrated).max() / integrated.max()
        err_point = np.abs(got - point).max() / integrated.max()
        assert err_integrated < 0.02  # 3×3 midpoint pooling + edge normalisation
        assert err_point > 2 * err_integrated  # and it is the integral, not the point value


# --------------------------------------------------------------------------------------------
# (2) Blazed grating: the PSF moves to z·λ/period
# --------------------------------------------------------------------------------------------
GRATING_PIXEL_M = 5e-6


@pytest.fixture(scope="module")
def grating_camera():
    return fine_camera(GRATING_PIXEL_M * 1e6, (450.0, 600.0, 50.0), "camera.doe.init=zeros", "camera.psf.supersample=1")


@pytest.mark.parametrize("axis, period_cells", [(1, 8), (0, 12)])
def test_blazed_grating_moves_psf_by_z_lambda_over_period(grating_camera, axis, period_cells):
    cam = grating_camera
    doe = cam.optics.doe
    lam0 = doe.design_wavelength_nm
    h2pi = lam0 * 1e-9 / (sellmeier_fused_silica(lam0) - 1.0)
    j = np.arange(doe.n_cells)
    ramp = h2pi * (j % period_cells) / period_cells  # sawtooth, thicker towards +index
    h = np.broadcast_to(ramp[None, :] if axis == 1 else ramp[:, None], (doe.n_cells, doe.n_cells))
    with torch.no_grad():
        doe.height_m.copy_(torch.from_numpy(np.ascontiguousarray(h)))
        psf = _np(cam.psf())
    c = psf.shape[-1] // 2
    period_m = period_cells * FINE_CELL_M
    for band, lam_nm in enumerate(cam.bands.centers_nm):
        expected_px = FINE_F_M * lam_nm * 1e-9 / period_m / GRATING_PIXEL_M
        row, col = centroid_px(psf[band])
        along, across = (col - c, row - c) if axis == 1 else (row - c, col - c)
        # first order towards the thick side of the ramp (as a prism bends light to its base)
        assert along == pytest.approx(expected_px, abs=0.25), (lam_nm, along, expected_px)
        assert abs(across) < 0.05


# --------------------------------------------------------------------------------------------
# (3) 2π steps at the design wavelength; zero heights
# --------------------------------------------------------------------------------------------
def test_2pi_step_is_invisible_only_at_design_wavelength():
    # bands 487.6, 587.6 (= λ0, the DOE design wavelength), 687.6 nm
    extra = ("camera.psf.supersample=1",)
    cam = fine_camera(5.0, (487.6, 687.6, 100.0), "camera.doe.init=zeros", *extra)
    lens_only = fine_camera(5.0, (487.6, 687.6, 100.0), "camera.doe.enabled=false", *extra)
    doe = cam.optics.doe
    lam0 = doe.design_wavelength_nm
    assert cam.bands.centers_nm[1] == pytest.approx(lam0)
    h2pi = lam0 * 1e-9 / (sellmeier_fused_silica(lam0) - 1.0)
    assert doe.h2pi_m == pytest.approx(h2pi, rel=1e-9)
    with torch.no_grad():
        ref = _np(lens_only.psf())
        zero = _np(cam.psf())
        np.testing.assert_allclose(zero, ref, rtol=0, atol=1e-7 * ref.max())  # h = 0 ≡ no DOE
        step = torch.zeros(doe.n_cells, doe.n_cells)
        step[:, doe.n_cells // 2 :] = h2pi  # half the pupil one 2π step higher
        doe.height_m.copy_(step)
        stepped = _np(cam.psf())
    peak = ref.max(axis=(-2, -1))
    assert np.abs(stepped[1] - ref[1]).max() < 1e-4 * peak[1]
    for band in (0, 2):  # ~0.2 and ~0.15 waves of residual step: clearly visible
        assert np.abs(stepped[band] - ref[band]).max() > 0.05 * peak[band]
    # on axis the two parts of the pupil add as phasors: |(1 − w) + w·e^{iδ}|², with the stepped
    # area fraction w (columns x ≥ −Δ/2 of the disc) and δ = 2π(n(λ) − 1)h/λ (DOE dispersion)
    c = ref.shape[-1] // 2
    w = 0.5 + FINE_CELL_M / (np.pi * FINE_R_M)
    for band, lam_nm in enumerate(cam.bands.centers_nm):
        delta = 2 * np.pi * (sellmeier_fused_silica(lam_nm) - 1.0) * h2pi / (lam_nm * 1e-9)
        expected = 1.0 - 2.0 * w * (1.0 - w) * (1.0 - np.cos(delta))
        assert stepped[band, c, c] / ref[band, c, c] == pytest.approx(expected, abs=5e-4)


# --------------------------------------------------------------------------------------------
# (4) Singlet lens: dispersion, focus shift, wider PSFs off the design wavelength
# --------------------------------------------------------------------------------------------
PAPER_R_M, PAPER_CELL_M, PAPER_PIXEL_M = 5e-3, 30e-6, 6e-6
SINGLET_R_M = 16e-3


def paper_psf_model(lams_nm, lens, sensor_distance_m=None, doe=None) -> PSFModel:
    mat = FusedSilica()
    doe = DOE(333, mat, enabled=False) if doe is None else doe
    return PSFModel(Bands.from_centers(lams_nm), lens, doe, PAPER_R_M, PAPER_CELL_M, PAPER_PIXEL_M,
                    587.6, sensor_distance_m)


def test_singlet_focal_length_follows_sellmeier():
    cam = DOECamera.from_config(load_config(overrides=["camera.lens.model=singlet"]))
    lam = cam.bands.centers_nm
    expected = SINGLET_R_M / (sellmeier_fused_silica(lam) - 1.0)
    np.testing.assert_allclose(cam.optics.focal_lengths_m, expected, rtol=1e-9)
    # the sensor sits at f(587.6 nm)
    assert cam.optics.sensor_distance_m == pytest.approx(SINGLET_R_M / (sellmeier_fused_silica(587.6) - 1.0), rel=1e-9)
    assert cam.optics.sensor_distance_m == pytest.approx(35e-3, rel=0.005)  # "EFL 35 mm" of the paper
    shift = expected[-1] - expected[0]  # 420 → 720 nm
    assert shift == pytest.approx(1.0e-3, rel=0.05)  # the focus moves by ≈ 1 mm


def test_singlet_psfs_are_wider_off_the_design_wavelength():
    lams = [420.0, 587.6, 720.0]
    lens = SingletLens(SINGLET_R_M, 2e-3, FusedSilica())
    model = paper_psf_model(lams, lens)
    with torch.no_grad():
        res = model()
    psf, energy = _np(res.psf), _np(res.energy)
    np.testing.assert_allclose(energy, 1.0, atol=1e-4)  # the blur fits in the 141-px kernel
    peaks = psf.max(axis=(-2, -1))
    rms = [rms_radius(p, PAPER_PIXEL_M) for p in psf]
    assert peaks[0] < 0.1 * peaks[1] and peaks[2] < 0.1 * peaks[1]
    assert rms[0] > 2 * rms[1] and rms[2] > 2 * rms[1]
    # ~20 waves of defocus: geometric blur disc of radius ρ = R·|z − f_λ|/f_λ (rms ρ/√2),
    # added in quadrature to the in-focus rms (the diffraction tails inside the kernel)
    z = SINGLET_R_M / (sellmeier_fused_silica(587.6) - 1.0)
    for band in (0, 2):
        f_lam = SINGLET_R_M / (sellmeier_fused_silica(lams[band]) - 1.0)
        rho = PAPER_R_M * abs(z - f_lam) / f_lam
        predicted = math.hypot(rho / math.sqrt(2.0), rms[1])
        assert rms[band] == pytest.approx(predicted, rel=0.08)


@pytest.mark.parametrize("lam_nm", [420.0, 720.0])
def test_singlet_best_focus_at_its_sellmeier_focal_length(lam_nm):
    lens = SingletLens(SINGLET_R_M, 2e-3, FusedSilica())
    f_lam = SINGLET_R_M / (sellmeier_fused_silica(lam_nm) - 1.0)
    peaks = []
    with torch.no_grad():
        for dz in (-50e-6, 0.0, 50e-6):
            peaks.append(paper_psf_model([lam_nm], lens, f_lam + dz)().psf.max().item())
    assert peaks[1] > 2 * max(peaks[0], peaks[2])


def test_fresnel_doe_adds_the_power_of_a_positive_lens():
    """A DOE thicker at the centre (like glass lens) with focal length f_d shortens the focus to
    1/(1/f + 1/f_d): checks the sign of the DOE phase against the lens/defocus convention."""
    f, f_d, lam0 = 35e-3, 2.0, 587.6
    n0 = sellmeier_fused_silica(lam0)
    h2pi = lam0 * 1e-9 / (n0 - 1.0)
    x = sample_coordinates_m(333, PAPER_CELL_M)
    r2 = x[:, None] ** 2 + x[None, :] ** 2
    heights = np.mod(10 * h2pi - r2 / (2 * f_d * (n0 - 1.0)), h2pi)  # wrapped Fresnel lens
    peaks = {}
    with torch.no_grad():
        for name, z in (("converging", 1 / (1 / f + 1 / f_d)), ("diverging", 1 / (1 / f - 1 / f_d)), ("lens", f)):
            doe = DOE(333, FusedSilica(), lam0, init="zeros")
            doe.height_m.copy_(torch.from_numpy(heights))
            peaks[name] = paper_psf_model([lam0], AchromaticLens(f), z, doe)().psf.max().item()
        in_focus = paper_psf_model([lam0], AchromaticLens(f))().psf.max().item()  # no DOE, z = f
    assert peaks["converging"] > 0.8 * in_focus
    assert peaks["diverging"] < 0.1 * in_focus and peaks["lens"] < 0.1 * in_focus


# --------------------------------------------------------------------------------------------
# (5) Sampling plan
# --------------------------------------------------------------------------------------------
def _odd_ceil(x: float) -> int:
    k = math.ceil(x - 1e-9)
    return k if k % 2 else k + 1


def test_paper_sampling_plan():
    cam = DOECamera.from_config(load_config())
    smp = cam.optics.sampling
    lam = np.arange(420.0, 721.0, 10.0) * 1e-9
    z, p, d = 35e-3, 6e-6, 30e-6
    cells = 2 * int(5e-3 / d) + 1
    assert cells == 333 and smp.pupil_samples == 333
    # smallest odd s whose FFT holds the 333-cell pupil at 420 nm
    s = next(s for s in range(1, 99, 2) if round(lam[0] * z * s / (p * d)) >= cells)
    sizes = [round(l * z * s / (p * d)) for l in lam]
    assert s == 5 and smp.supersample == 5
    assert list(smp.fft_sizes) == sizes and sizes[0] == 408 and sizes[-1] == 700
    assert smp.kernel_px == cam.kernel_px == 141 == _odd_ceil(lam[-1] * z / (d * p))
    # the FFT pitch λz/(NΔ) equals pixel/s up to the rounding of N
    pitch = lam * z / (np.array(smp.fft_sizes) * d)
    np.testing.assert_allclose(pitch, p / s, rtol=1.0 / (2 * 408))


def test_kernel_below_the_optics_minimum_is_a_config_error():
    with pytest.raises(ConfigError, match=r"\b141\b"):
        DOECamera.from_config(load_config(overrides=["camera.psf.kernel_px=139"]))
    with pytest.raises(ConfigError, match=r"\b5\b"):
        DOECamera.from_config(load_config(overrides=["camera.psf.supersample=3"]))
    # a larger kernel and supersampling are accepted
    cam = DOECamera.from_config(load_config(overrides=["camera.psf.kernel_px=151", "camera.psf.supersample=7"]))
    assert cam.kernel_px == 151 and cam.optics.sampling.supersample == 7


def test_paper_psf_energy_in_kernel_is_one():
    cam = DOECamera.from_config(load_config())  # 31 bands, random DOE, q = 1
    with torch.no_grad():
        res = cam.psf_result()
    assert res.psf.shape == (31, 141, 141)
    energy = _np(res.energy)
    np.testing.assert_allclose(energy, 1.0, atol=1e-4)
    np.testing.assert_allclose(_np(res.psf).sum(axis=(-2, -1)), energy, rtol=1e-5)
    assert (res.psf >= 0).all()


def _dirichlet_fraction(nu_k: float, q: int) -> float:
    """Fraction of the 1-D power of a random cell pattern, sampled q times per cell, that falls
    within |ν| < ν_k cycles per cell (envelope sin²(πν)/(q sin²(πν/q)), period q)."""
    env = lambda v: 1.0 if abs(math.sin(math.pi * v / q)) < 1e-12 else math.sin(math.pi * v) ** 2 / (q * math.sin(math.pi * v / q) ** 2)
    return quad(env, -min(nu_k, q / 2), min(nu_k, q / 2), limit=200)[0] / q


@pytest.mark.parametrize("aperture_mm", [2.0, pytest.param(5.0, marks=pytest.mark.slow)])
def test_pupil_oversampling_shows_higher_orders_outside_the_kernel(aperture_mm):
    """q = 3: the random DOE cells diffract into higher orders beyond λz/Δ, outside the minimal
    kernel. Prediction for i.i.d. uniform heights in [0, h_2π(λ0)]: a specular part |E e^{iφ}|²
    (kept) plus a diffuse part with the cell envelope (separable in x and y). The paper's 5 mm
    aperture is the slow variant; 2 mm (133 cells) has the same statistics."""
    common = ["bands.start_nm=420", "bands.stop_nm=720", "bands.step_nm=300", f"camera.aperture_radius_mm={aperture_mm}"]
    cam = DOECamera.from_config(load_config(overrides=[*common, "camera.psf.pupil_oversample=3"]))
    assert cam.kernel_px == 141  # the minimum is set by the zeroth-order field λ_max·z/Δ
    smooth = DOECamera.from_config(load_config(overrides=[*common, "camera.psf.pupil_oversample=3", "camera.doe.enabled=false"]))
    with torch.no_grad():
        energy = _np(cam.psf_result().energy)
        energy_smooth = _np(smooth.psf_result().energy)
    n = sellmeier_fused_silica(np.array([420.0, 720.0]))
    n0 = sellmeier_fused_silica(587.6)
    for band, lam_nm in enumerate([420.0, 720.0]):
        alpha = (n[band] - 1.0) * 587.6 / ((n0 - 1.0) * lam_nm)  # phase range in waves
        specular = np.sinc(alpha) ** 2
        nu_k = 141 * PAPER_PIXEL_M / 2 * PAPER_CELL_M / (lam_nm * 1e-9 * 35e-3)
        predicted = specular + (1 - specular) * _dirichlet_fraction(nu_k, 3) ** 2
        assert energy[band] == pytest.approx(predicted, abs=0.02)
        assert energy[band] < 0.95
    np.testing.assert_allclose(energy_smooth, 1.0, atol=5e-3)  # a smooth pupil has no higher orders


# --------------------------------------------------------------------------------------------
# (6) The pure function: centring, Parseval, gradients
# --------------------------------------------------------------------------------------------
def _psf_inputs(p: int, dtype=torch.float64, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.as_tensor(sample_coordinates_m(p, 1.0), dtype=dtype)
    return dict(
        height_m=torch.rand(p, p, generator=g, dtype=dtype) * 2.0,
        amplitude=0.3 + torch.rand(p, p, generator=g, dtype=dtype),
        r2_m2=x[:, None] ** 2 + x[None, :] ** 2,
        doe_phase_per_m=torch.tensor([1.3, 0.9], dtype=dtype),
        defocus_per_m2=torch.tensor([0.2, -0.1], dtype=dtype),
    )


def _symmetric_pupil_psf(fft_sizes, s, k):
    p = 5
    amp = torch.as_tensor(aperture_amplitude(p, 1.0, 2.4), dtype=torch.float64)
    zeros = torch.zeros(p, p, dtype=torch.float64)
    c = len(fft_sizes)
    return psf_stack(zeros, amp, zeros, torch.ones(c, dtype=torch.float64), torch.zeros(c, dtype=torch.float64),
                     fft_sizes, s, k).psf


@pytest.mark.parametrize(
    "fft_sizes, s, k",
    [((7, 9), 1, 9), ((13, 15), 3, 5), ((15, 21), 3, 3), ((10, 12), 1, 5), ((14, 16), 3, 3)],
)
def test_psf_stack_is_centred_on_the_axis(fft_sizes, s, k):
    """A symmetric pupil without phase gives a point-symmetric PSF peaked on the centre pixel
    (odd FFT sizes; even ones where the kernel crops the Nyquist line away)."""
    psf = _symmetric_pupil_psf(fft_sizes, s, k)
    assert psf.shape == (len(fft_sizes), k, k)
    torch.testing.assert_close(psf, torch.flip(psf, (-2, -1)), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(psf, psf.transpose(-2, -1), rtol=1e-10, atol=1e-12)
    for band in range(len(fft_sizes)):
        assert int(torch.argmax(psf[band])) == (k // 2) * k + k // 2


def test_psf_stack_even_fft_size_centre_and_nyquist_line():
    """Even N, kernel wider than the FFT plane: the N samples −N/2..N/2−1 land on the kernel with
    DC on the centre pixel; everything but the (one-sided) Nyquist line is point-symmetric."""
    k = 11
    psf = _symmetric_pupil_psf((8, 10), 1, k)
    c = k // 2
    for band, n in enumerate((8, 10)):
        assert int(torch.argmax(psf[band])) == c * k + c
        inner = psf[band, c - n // 2 + 1 : c + n // 2, c - n // 2 + 1 : c + n // 2]
        torch.testing.assert_close(inner, torch.flip(inner, (-2, -1)), rtol=1e-10, atol=1e-12)
        assert psf[band, c - n // 2].abs().sum() > 0  # the Nyquist row, on the −x side
        assert psf[band, c + n // 2 :].abs().sum() == 0 and psf[band, : c - n // 2].abs().sum() == 0


@pytest.mark.parametrize("fft_sizes, s, k, crops", [((7, 8), 1, 9, False), ((13, 16), 3, 3, True)])
def test_psf_stack_parseval(fft_sizes, s, k, crops):
    res = psf_stack(**_psf_inputs(6), fft_sizes=fft_sizes, supersample=s, kernel_px=k)
    assert (res.psf >= 0).all()
    torch.testing.assert_close(res.energy, res.psf.sum(dim=(-2, -1)))
    if crops:
        assert (res.energy < 1 - 1e-3).all()
    else:
        torch.testing.assert_close(res.energy, torch.ones(2, dtype=torch.float64))


@pytest.mark.parametrize(
    "p, fft_sizes, s, k",
    [
        (5, (7, 8), 1, 9),  # K·s > N: the whole FFT plane lands in the kernel
        (6, (13, 16), 3, 3),  # K·s = 9 < N: the kernel crops the FFT plane
        (5, (9, 10), 1, 5),  # cropped, s = 1
    ],
)
def test_psf_stack_gradcheck(p, fft_sizes, s, k):
    inputs = _psf_inputs(p)
    names = list(inputs)
    tensors = tuple(t.clone().requires_grad_(True) for t in inputs.values())

    def fn(*args):
        res = psf_stack(**dict(zip(names, args)), fft_sizes=fft_sizes, supersample=s, kernel_px=k)
        return res.psf, res.energy

    assert torch.autograd.gradcheck(fn, tensors, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_gradients_reach_doe_heights(tiny_camera):
    cam = tiny_camera()
    res = cam.psf_result()
    c = cam.kernel_px // 2
    w = torch.rand(res.psf.shape, generator=torch.Generator().manual_seed(1))
    ((res.psf * w).sum() + res.psf[:, c, c].sum()).backward()
    g = cam.optics.doe.height_m.grad
    assert g is not None and g.shape == (11, 11)
    assert torch.isfinite(g).all() and g.abs().max() > 0
    # cells outside the circular aperture get no light and no gradient
    amp = cam.optics.amplitude
    assert torch.all(g[amp == 0] == 0) and (g[amp > 0] != 0).float().mean() > 0.9
