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

from hang_guard import guarded
from hsicam.cameras import DOECamera
from hsicam.config import load_config
from hsicam.errors import ConfigError, InputError
from hsicam.optics.doe import DOE
from hsicam.optics.lens import AchromaticLens, SingletLens
from hsicam.optics.psf import PSFModel, psf_stack
from hsicam.optics.pupil import aperture_amplitude, cells_across, sample_coordinates_m
from hsicam.optics.sampling import defocus_aliasing, fast_fft_length, pixel_weights, plan_psf_sampling
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
    cam, psf, energy = airy_point_samples
    np.testing.assert_allclose(psf.sum(axis=(-2, -1)), energy, rtol=1e-5)
    # the whole sensor plane is normalised to 1 (Parseval); the kernel misses the Airy tails:
    # 1 − EE(v) ≈ 2/(π v) for a disc of the kernel's area (v = 2π R r/(λ z)). (Before the
    # square-cell model the periodic far field put all light in the kernel: energy 1.)
    half = psf.shape[-1] / 2 * AIRY_PIXEL_M
    r_eq = 2 * half / math.sqrt(math.pi)
    for band, lam_nm in enumerate(cam.bands.centers_nm):
        v = 2 * math.pi * FINE_R_M * r_eq / (lam_nm * 1e-9 * FINE_F_M)
        disc = 1 - 2 / (math.pi * v)
        # outside a square of half-width X the asymptotic Airy tail holds 2√2 λz/(π³ R X); the
        # area-fraction aperture edge (a soft edge, docs/optics.md) diffracts ~30 % less far out
        square = 1 - 2 * math.sqrt(2) * lam_nm * 1e-9 * FINE_F_M / (math.pi**3 * FINE_R_M * half)
        assert square - 2e-4 < energy[band] < 1 - 0.6 * (1 - square) and energy[band] == pytest.approx(disc, abs=1.5e-3)


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
    # the blur fits in the 141-px kernel. Known approximation of the square-cell model (docs/optics.md):
    # the residual defocus (~20 waves at 420 nm) is constant over each 30 µm cell, so the cells'
    # envelope is not steered with the local ray and ~5 % of the light at 420 nm lands in the
    # neighbouring orders (q = 2: 1.9 %, q = 3: 0.9 %); the point-pupil model had 1.0 here.
    assert energy[1] == pytest.approx(1.0, abs=1e-3)
    assert energy[0] > 0.94 and energy[2] > 0.99
    peaks = psf.max(axis=(-2, -1))
    # rms over the central 71 px (the blur disc is ≤ 17 px): the ~5 % that the cell-constant
    # defocus sends to the neighbouring orders (≥ 60 px away) would otherwise dominate it
    c = psf.shape[-1] // 2
    rms = [rms_radius(p[c - 35 : c + 36, c - 35 : c + 36], PAPER_PIXEL_M) for p in psf]
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
# (5) Sampling plan, energy outside the kernel
# --------------------------------------------------------------------------------------------
def _odd_ceil(x: float) -> int:
    k = math.ceil(x - 1e-9)
    return k if k % 2 else k + 1


def test_paper_sampling_plan():
    cam = DOECamera.from_config(load_config())
    smp = cam.optics.sampling
    lam = np.arange(420.0, 721.0, 10.0) * 1e-9
    z, p, d, a = 35e-3, 6e-6, 30e-6, 5e-3
    cells = 2 * int(a / d) + 1
    assert cells == 333 and smp.pupil_samples == 333
    # one FFT length for all bands: ≥ 2P − 1 (an exact period of the intensity), 7-smooth
    assert smp.fft_size == 672 and smp.fft_size >= 2 * cells - 1
    assert smp.supersample is None  # exact pixel integration
    assert smp.nyquist_supersample == 9 == _odd_ceil(4 * a * p / (lam[0] * z))
    assert smp.kernel_px == cam.kernel_px == 141 == _odd_ceil(lam[-1] * z / (d * p))
    assert cam.optics.pixel_weights.shape == (31, 141, 672)


def test_psf_plan_and_cube_readers_share_one_memory_budget(monkeypatch):
    """The PSF plan checks against the project's one budget (hsicam.memory), the one the cube readers
    use: HSICAM_MEMORY_BUDGET_MB moves both, and a bad value is the same one-line error."""
    from hsicam.data.cube import check_memory_budget
    from hsicam.memory import MEMORY_BUDGET_ENV, memory_budget_bytes
    from hsicam.optics import sampling

    assert sampling.memory_budget_bytes is memory_budget_bytes
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "123.5")
    assert memory_budget_bytes() == int(123.5 * 2**20)
    with pytest.raises(InputError, match="memory budget of 124 MiB"):
        check_memory_budget("x.h5", (31, 4096, 4096), "float32")
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "abc")
    with pytest.raises(ConfigError, match=MEMORY_BUDGET_ENV):
        memory_budget_bytes()


def test_sampling_plan_reports_its_memory_and_refuses_over_budget():
    """The plan's estimate is a lower bound of what the PSF stack takes (the paper plan's pixel
    weights (31, 141, 672) float32 alone are 11.8 MB); over a budget the plan is refused."""
    from hsicam.optics.sampling import check_psf_memory, plan_psf_sampling, psf_memory_estimate

    lam = np.arange(420.0, 721.0, 10.0) * 1e-9
    smp = plan_psf_sampling(lam, 35e-3, 6e-6, 30e-6, 333)
    assert 31 * 141 * 672 * 4 < smp.memory_bytes < 1 << 30
    smp2 = plan_psf_sampling(lam, 35e-3, 6e-6, 30e-6, 333, pupil_oversample=2)
    mem = psf_memory_estimate(smp2, lam, 35e-3, 6e-6)
    assert mem.total == smp2.memory_bytes > smp.memory_bytes
    check_psf_memory(mem, smp2, lam, 35e-3, 6e-6, 30e-6, 333, budget_bytes=mem.total)
    # 2× oversampled, what the DOE's gradient keeps of its 31 wavelengths is the largest part
    with pytest.raises(ConfigError, match=r"each of its 31 wavelengths \(bands × camera.psf.band_samples\) keeps its "
                                          r"1344×1344 spectrum and 666×666 pupil field for the DOE's gradient"):
        check_psf_memory(mem, smp2, lam, 35e-3, 6e-6, 30e-6, 333, budget_bytes=mem.total - 1)


@pytest.mark.parametrize("band_samples", [1, 3])
def test_the_memory_plan_counts_what_the_doe_gradient_keeps(band_samples):
    """The tensors autograd saves for the backward pass of the PSF stack, counted by a
    saved-tensors hook, are within the plan's ``saved`` term (before it, a paper camera with 32
    wavelengths per band took 2.9 GB against a 2.04 GiB estimate): at least all of them, at most
    1.5× (the term adds the phase stack's transient products)."""
    from hsicam.optics.sampling import psf_memory_estimate

    optics = DOECamera.from_config(load_config("tiny", [f"camera.psf.band_samples={band_samples}"])).optics
    storages: dict[int, int] = {}

    def pack(t):
        storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        optics().psf.sum().backward()
    mem = psf_memory_estimate(optics.sampling, optics.line_wavelengths_nm * 1e-9, optics.sensor_distance_m,
                              optics.pixel_m)
    kept = sum(storages.values())
    assert kept <= mem.saved <= 1.5 * kept, (kept, mem.saved)
    assert mem.total == optics.sampling.memory_bytes


def test_kernel_below_the_optics_minimum_is_a_config_error():
    with pytest.raises(ConfigError, match=r"\b141\b"):
        DOECamera.from_config(load_config(overrides=["camera.psf.kernel_px=139"]))
    with pytest.raises(ConfigError, match="band_samples"):
        load_config(overrides=["camera.psf.band_samples=0"])
    # a larger kernel and an explicit (midpoint) supersampling are accepted
    cam = DOECamera.from_config(load_config(overrides=["camera.psf.kernel_px=151", "camera.psf.supersample=7"]))
    assert cam.kernel_px == 151 and cam.optics.sampling.supersample == 7


def _sinc2_fraction(nu_k: float) -> float:
    """Fraction of ∫ sinc²(ν) dν = 1 within |ν| < ν_k (the square cell's envelope, 1-D)."""
    return quad(lambda v: np.sinc(v) ** 2, -nu_k, nu_k, limit=400)[0]


def _diffuser_energy_prediction(lam_nm: float, kernel_px: int = 141) -> float:
    """Energy in the kernel for i.i.d. uniform heights in [0, h_2π(587.6 nm)] on 30 µm cells:
    a specular part |E e^{iφ}|² (kept) plus a diffuse part under the cells' sinc² envelope
    (separable in x and y)."""
    n, n0 = sellmeier_fused_silica(lam_nm), sellmeier_fused_silica(587.6)
    alpha = (n - 1.0) * 587.6 / ((n0 - 1.0) * lam_nm)  # phase range in waves
    specular = np.sinc(alpha) ** 2
    nu_k = kernel_px * PAPER_PIXEL_M / 2 * PAPER_CELL_M / (lam_nm * 1e-9 * 35e-3)
    return float(specular + (1 - specular) * _sinc2_fraction(nu_k) ** 2)


@pytest.mark.parametrize("q", [1, 3])
def test_diffuser_sends_light_outside_the_kernel(q):
    """The random DOE cells diffract under their sinc² envelope beyond λz/Δ, outside the minimal
    kernel: the light lost is reported (2 mm aperture, 133 cells: the paper's statistics)."""
    common = ["bands.start_nm=420", "bands.stop_nm=720", "bands.step_nm=300", "camera.aperture_radius_mm=2.0",
              f"camera.psf.pupil_oversample={q}"]
    cam = DOECamera.from_config(load_config(overrides=common))
    assert cam.kernel_px == 141  # the minimum is set by the zeroth-order field λ_max·z/Δ
    smooth = DOECamera.from_config(load_config(overrides=[*common, "camera.doe.enabled=false"]))
    with torch.no_grad():
        energy = _np(cam.psf_result().energy)
        energy_smooth = _np(smooth.psf_result().energy)
    for band, lam_nm in enumerate([420.0, 720.0]):
        assert energy[band] == pytest.approx(_diffuser_energy_prediction(lam_nm), abs=0.02)
        assert energy[band] < 0.9
    np.testing.assert_allclose(energy_smooth, 1.0, atol=5e-3)  # a smooth pupil: only Airy tails leave


def test_paper_psf_energy_in_kernel_is_physical():
    cam = DOECamera.from_config(load_config())  # 31 bands, random DOE
    with torch.no_grad():
        res = cam.psf_result()
    assert res.psf.shape == (31, 141, 141)
    energy = _np(res.energy)
    np.testing.assert_allclose(_np(res.psf).sum(axis=(-2, -1)), energy, rtol=1e-5)
    assert (res.psf >= 0).all()
    # issue 13: 0.82 at 420 nm and 0.62 at 720 nm inside the 141 px kernel (not 1)
    for band in (0, 15, 30):
        lam_nm = float(cam.bands.centers_nm[band])
        assert energy[band] == pytest.approx(_diffuser_energy_prediction(lam_nm), abs=0.015)
    assert energy[0] == pytest.approx(0.82, abs=0.01) and energy[-1] == pytest.approx(0.62, abs=0.01)


# --------------------------------------------------------------------------------------------
# (6) The pure functions: pixel weights, centring, Parseval, gradients
# --------------------------------------------------------------------------------------------
def _sinc2_integral(x):
    """∫_0^x sinc²(t) dt (numpy's sinc), in closed form through the sine integral Si."""
    from scipy.special import sici

    x = np.asarray(x, dtype=np.float64)
    xs = np.where(x == 0, 1.0, x)
    val = (sici(2 * np.pi * xs)[0] - np.sin(np.pi * xs) ** 2 / (np.pi * xs)) / np.pi
    return np.where(x == 0, 0.0, val)


@pytest.mark.parametrize("period_px, k, n", [(81.6, 141, 675), (81.6, 141, 672), (3.3, 41, 81), (3.3, 41, 84), (0.7, 21, 11)])
def test_single_cell_is_the_integrated_sinc2(period_px, k, n):
    """One cell (P = 1): the PSF is ∫∫_pixel sinc²(t_x) sinc²(t_y), t in periods λz/Δ."""
    w = torch.from_numpy(pixel_weights(period_px, k, n))[None]
    one = torch.ones(1, 1, dtype=torch.float64)
    zero = torch.zeros(1, dtype=torch.float64)
    psf = psf_stack(one * 0, one, one * 0, zero, zero, w).psf[0].numpy()
    h = 1.0 / period_px
    c = (np.arange(k) - k // 2) * h
    ref1 = _sinc2_integral(c + h / 2) - _sinc2_integral(c - h / 2)
    np.testing.assert_allclose(psf, np.outer(ref1, ref1), rtol=1e-9, atol=1e-15)


def _weights(period_px, k, p, s=None, lines=1):
    n = fast_fft_length(2 * p - 1)
    w = [pixel_weights(period_px * (1 + 0.07 * i), k, n, s) for i in range(lines)]
    return torch.from_numpy(np.stack(w))


@pytest.mark.parametrize("period_px, k, s", [(9.0, 9, None), (2.5, 5, None), (1.3, 7, 3), (0.6, 3, 1)])
def test_psf_stack_is_centred_on_the_axis(period_px, k, s):
    """A symmetric pupil without phase gives a point-symmetric PSF peaked on the centre pixel."""
    p = 5
    amp = torch.as_tensor(aperture_amplitude(p, 1.0, 2.4), dtype=torch.float64)
    zeros = torch.zeros(p, p, dtype=torch.float64)
    w = _weights(period_px, k, p, s, lines=2)
    psf = psf_stack(zeros, amp, zeros, torch.ones(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), w).psf
    assert psf.shape == (2, k, k)
    torch.testing.assert_close(psf, torch.flip(psf, (-2, -1)), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(psf, psf.transpose(-2, -1), rtol=1e-10, atol=1e-12)
    for band in range(2):
        assert int(torch.argmax(psf[band])) == (k // 2) * k + k // 2


def test_psf_stack_parseval_over_a_wide_kernel():
    """A kernel ±100 px wide with 4 periods per pixel holds all but the far sinc² tails."""
    inputs = _psf_inputs(4)
    res = psf_stack(**inputs, weights=_weights(0.25, 201, 4, lines=2))
    torch.testing.assert_close(res.energy, res.psf.sum(dim=(-2, -1)))
    assert (res.energy > 0.997).all() and (res.energy < 1).all()


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


@pytest.mark.parametrize(
    "p, period_px, k, s, banded",
    [
        (5, 3.0, 9, None, False),  # kernel wider than a period: tiled orders
        (6, 7.0, 3, None, True),  # kernel smaller than a period; 2 wavelengths averaged into 1 band
        (5, 2.0, 5, 3, False),  # midpoint rule
    ],
)
def test_psf_stack_gradcheck(p, period_px, k, s, banded):
    inputs = _psf_inputs(p)
    names = list(inputs)
    tensors = tuple(t.clone().requires_grad_(True) for t in inputs.values())
    w = _weights(period_px, k, p, s, lines=2)
    line_w = torch.tensor([[0.3, 0.7]], dtype=torch.float64) if banded else None

    def fn(*args):
        res = psf_stack(**dict(zip(names, args)), weights=w, line_weights=line_w)
        return res.psf, res.energy

    assert torch.autograd.gradcheck(fn, tensors, eps=1e-6, atol=1e-7, rtol=1e-4)


@pytest.mark.parametrize("banded", [False, True])
def test_psf_stack_differentiates_twice(banded):
    """Second-order gradients of the PSF stack (backward with create_graph=True: a penalty on the DOE's gradient,
    a Hessian-vector product) are the finite differences of its first-order ones (torch's gradgradcheck, float64).
    The PSF batch's backward was once-differentiable: gradgradcheck failed."""
    inputs = _psf_inputs(4)
    names = list(inputs)
    tensors = tuple(t.clone().requires_grad_(True) for t in inputs.values())
    w = _weights(2.0, 3, 4, lines=2)
    line_w = torch.tensor([[0.3, 0.7]], dtype=torch.float64) if banded else None

    def fn(*args):
        res = psf_stack(**dict(zip(names, args)), weights=w, line_weights=line_w)
        return res.psf, res.energy

    assert torch.autograd.gradgradcheck(fn, tensors, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_a_penalty_on_the_doe_gradient_reaches_heights_and_aperture():
    """‖∂⟨p, c⟩/∂h‖² (a smoothness or robustness penalty on the DOE's gradient) differentiated with respect to the
    heights and the aperture: the gradients of the same penalty through W·|FFT_N×N(A·e^{iφ})|²·Wᵀ written out here
    with torch's FFTs (session 76's hunt: both were silently 0 through the once-differentiable backward)."""
    inputs = _psf_inputs(5)
    w = _weights(2.5, 5, 5, lines=2)
    n = w.shape[-1]
    c = torch.rand(2, 5, 5, generator=torch.Generator().manual_seed(76), dtype=torch.float64)

    def written_out(height_m, amplitude, r2_m2, doe_phase_per_m, defocus_per_m2):
        phase = doe_phase_per_m[:, None, None] * height_m + defocus_per_m2[:, None, None] * r2_m2
        spec = torch.fft.fft(torch.fft.fft(torch.polar(amplitude.expand_as(phase), phase), n=n, dim=-1), n=n, dim=-2)
        return w @ (spec.real.square() + spec.imag.square()) @ w.transpose(-1, -2) / amplitude.square().sum()

    grads = []
    for op in (lambda **kw: psf_stack(**kw, weights=w).psf, written_out):
        args = {k: v.clone().requires_grad_(k in ("height_m", "amplitude")) for k, v in inputs.items()}
        (gh,) = torch.autograd.grad((op(**args) * c).sum(), args["height_m"], create_graph=True)
        penalty = gh.square().sum() + 0.0 * (args["height_m"].sum() + args["amplitude"].sum())
        grads.append(torch.autograd.grad(penalty, (args["height_m"], args["amplitude"])))
    for got, want in zip(*grads):
        assert want.abs().max() > 1e-6
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9 * want.abs().max().item())


def test_a_float64_camera_computes_its_psfs_from_float64_optics_constants(tiny_camera):
    """A float64 camera (``.double()``) images with the optics constants in float64: its PSFs are psf_stack's of the
    pupil, DOE phase, defocus (π/λ·(1/z − 1/f), written out here), pixel-integration and band-weight arrays computed
    here in float64, to ~1e-15 (they were float32-rounded constants cast up: ~5e-8 relative off). A float32 camera
    keeps the float32 rounding of the same arrays, bit for bit, also after a round trip through float64."""
    from hsicam.optics.doe import phase_per_height
    from hsicam.optics.sampling import far_field_period_px
    from hsicam.spectral.bands import band_sample_wavelengths

    cam = tiny_camera("camera.lens.model=singlet", "camera.psf.band_samples=2")
    o = cam.optics
    smp, n, q = o.sampling, o.doe.n_cells, o.pupil_oversample
    lam_nm, line_w = band_sample_wavelengths(o.bands.centers_nm, o.bands.fwhm_nm, 2)
    lam_nm = lam_nm.reshape(-1)
    z = o.line_sensor_distances_m
    x = sample_coordinates_m(n, o.cell_m, q)
    period = far_field_period_px(lam_nm * 1e-9, z, smp.pupil_pitch_m, o.pixel_m)
    exact = {"amplitude": aperture_amplitude(n, o.cell_m, o.aperture_radius_m, q),
             "r2_m2": x[:, None] ** 2 + x[None, :] ** 2,
             "doe_phase_per_m": phase_per_height(o.doe.material, lam_nm),
             "defocus_per_m2": np.pi / (lam_nm * 1e-9) * (1.0 / z - 1.0 / o.lens.focal_lengths_m(lam_nm)),
             "pixel_weights": np.stack([pixel_weights(p, smp.kernel_px, smp.fft_size, smp.supersample) for p in period]),
             "line_weights": line_w}
    assert np.abs(exact["defocus_per_m2"]).max() > 1e3  # the singlet's focus shift: a defocus to get right
    for name, value in exact.items():
        assert torch.equal(getattr(o, name), torch.from_numpy(value).float()), name
    heights = o.pupil_heights().detach().double()
    cam.double()
    for name, value in exact.items():
        torch.testing.assert_close(getattr(o, name), torch.from_numpy(value), rtol=1e-15, atol=0.0, msg=name)
    ref = psf_stack(heights, *(torch.from_numpy(exact[k]) for k in ("amplitude", "r2_m2", "doe_phase_per_m",
                                                                     "defocus_per_m2", "pixel_weights", "line_weights")))
    with torch.no_grad():
        got = o.psf_from_pupil(heights).psf
    assert float((got - ref.psf).abs().max() / ref.psf.abs().max()) < 1e-14
    cam.float()
    for name, value in exact.items():
        assert torch.equal(getattr(o, name), torch.from_numpy(value).float()), name
    for low in (torch.bfloat16, torch.float16):  # back from a low precision: the fresh float32 constants again (a
        cam.to(low).float()  # .half().float() camera kept inf DOE phases and imaged NaN PSFs; session 76's review)
        for name, value in exact.items():
            assert torch.equal(getattr(o, name), torch.from_numpy(value).float()), (low, name)


def test_psf_batch_copies_no_full_spectrum_and_is_the_padded_fft():
    """The PSF batch's FFT stages copy no (L, N, N) array (review 64: two such copies per batch, 14 in a quick
    training step, ~10 % of the PSF's time on 2 CPU cores): the forward's column transforms run on a transposed
    canvas that holds the P non-zero rows only (not a padded copy that fft(dim=-2) copied again to transpose), and
    the backward multiplies the complex spectrum by the real g as real pairs (not after copying g to complex).
    Reference: W·|FFT_N×N(zero-padded A·e^{iφ})|²·Wᵀ written out here, bit for bit the same; the gradient as
    autograd takes it through that reference."""
    from torch.profiler import ProfilerActivity, profile

    from hsicam.optics.psf import _PSFBatch

    p, lines = 6, 3
    w = _weights(2.5, 5, p, lines=lines).float()
    n = w.shape[-1]
    g = torch.Generator().manual_seed(3)
    phase = (torch.rand(lines, p, p, generator=g) * 20.0).requires_grad_(True)
    amp = 0.3 + torch.rand(p, p, generator=g)
    grad_out = torch.rand(lines, w.shape[1], w.shape[1], generator=g)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        out = _PSFBatch.apply(phase, amp, w)
        out.backward(grad_out)
    full = [e.name for e in prof.events() if e.name in ("aten::copy_", "aten::fill_", "aten::clone")
            and e.input_shapes and list(e.input_shapes[0]) == [lines, n, n]]
    assert full == []
    ref_phase = phase.detach().clone().requires_grad_(True)
    field = torch.polar(amp.expand(lines, p, p), ref_phase)
    spec = torch.fft.fft(torch.fft.fft(field, n=n, dim=-1), n=n, dim=-2)
    ref = w @ (spec.real.square() + spec.imag.square()) @ w.transpose(-1, -2)
    assert torch.equal(out.detach(), ref.detach())
    ref.backward(grad_out)
    torch.testing.assert_close(phase.grad, ref_phase.grad, rtol=1e-4, atol=1e-4 * ref_phase.grad.abs().max().item())


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


def test_singlet_sensor_distance_from_its_rear_principal_plane():
    """Convex face first: H' sits t/n(λ) in front of the flat rear vertex. The sensor plane is
    fixed at f(587.6 nm) behind H'(587.6 nm), so band λ sees z + t/n(λ) − t/n(587.6)."""
    t = 2e-3
    lens = SingletLens(SINGLET_R_M, t, FusedSilica())
    lams = np.array([420.0, 587.6, 720.0])
    np.testing.assert_allclose(lens.rear_principal_plane_m(lams), -t / sellmeier_fused_silica(lams), rtol=1e-12)
    model = paper_psf_model(list(lams), lens)
    z = SINGLET_R_M / (sellmeier_fused_silica(587.6) - 1.0)
    expected = z + t / sellmeier_fused_silica(lams) - t / sellmeier_fused_silica(587.6)
    np.testing.assert_allclose(model.line_sensor_distances_m, expected, rtol=1e-12)
    assert (expected[0] - z) * 1e6 == pytest.approx(-9.0, abs=0.2)  # µm, against a ~1 mm focus shift
    desc = model.describe()["lens"]
    assert desc["rear_principal_plane_mm"] == pytest.approx(-t / sellmeier_fused_silica(587.6) * 1e3)
    assert "rear principal plane" in desc["sensor_distance_from"]


def test_a_singlet_from_the_config_takes_its_radius_and_thickness_in_mm():
    """``camera.lens`` (mm) → the lens model (m): f(λ) = R/(n(λ) − 1) and H' at −t/n(λ) from the rear vertex
    (Sellmeier written out here), for a thickness other than the 2 mm default."""
    from hsicam.config import LensConfig
    from hsicam.optics.lens import lens_from_config

    lens = lens_from_config(LensConfig(model="singlet", radius_of_curvature_mm=20.0, center_thickness_mm=3.5))
    lams = np.array([420.0, 587.6, 720.0])
    n = sellmeier_fused_silica(lams)
    np.testing.assert_allclose(lens.focal_lengths_m(lams), 20e-3 / (n - 1.0), rtol=1e-12)
    np.testing.assert_allclose(lens.rear_principal_plane_m(lams), -3.5e-3 / n, rtol=1e-12)


_S = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))  # σ of a Gaussian per unit FWHM


@pytest.mark.parametrize("m, offsets, weights", [(2, (-_S, _S), (0.5, 0.5)),
                                                 (3, (-math.sqrt(3) * _S, 0, math.sqrt(3) * _S), (1 / 6, 2 / 3, 1 / 6))])
def test_band_samples_average_sub_wavelengths_over_the_fwhm(tiny_config, m, offsets, weights):
    """band_samples = M: each band is the weighted mean of the PSFs at the M Gauss–Hermite nodes of its Gaussian of
    its FWHM (σ = FWHM / 2√(2 ln 2)): λ_c ± σ, weights ½, for M = 2; λ_c and λ_c ± √3·σ, weights 2/3 and 1/6, for
    M = 3 (the closed forms). M = 2 too: an even count has no centre line (and only M = 1 skips the averaging).
    Session 74: the band the data's resampling and the generator use, where M slices of ±FWHM/2 never reached it."""
    cam = DOECamera.from_config(tiny_config(f"camera.psf.band_samples={m}")).double()
    with torch.no_grad():
        banded = cam.psf_result()
    assert banded.psf.shape == (3, cam.kernel_px, cam.kernel_px)
    fwhm = cam.bands.fwhm_nm
    w = np.array(weights)
    expected = 0
    for off, wi in zip(offsets, w):
        shifted = [f"bands.start_nm={500 + off * fwhm[0]}", f"bands.stop_nm={600 + off * fwhm[0]}", "bands.step_nm=50"]
        single = DOECamera.from_config(tiny_config(*shifted, f"camera.psf.kernel_px={cam.kernel_px}")).double()
        single.load_state_dict(cam.state_dict())
        with torch.no_grad():
            expected = expected + wi * single.psf().numpy()
    np.testing.assert_allclose(banded.psf.numpy(), expected, rtol=1e-6, atol=1e-12)  # buffers built in float32
    np.testing.assert_allclose(banded.energy.numpy(), expected.sum(axis=(1, 2)), rtol=1e-6)


def test_an_explicit_supersample_below_nyquist_is_warned_about_once(caplog):
    """The paper optics need s = 9 sub-pixels per pixel (λ_min·z/(4a) = 4.4 µm under 6 µm pixels: 4·5 mm·6 µm /
    (420 nm·35 mm) = 8.2 → odd 9); s = 1 (point values) aliases: said once, in one line; s = 9 and the
    exact integral (None) say nothing (probe 29 F7)."""
    import logging

    from hsicam.optics import sampling

    lam = np.arange(420.0, 721.0, 10.0) * 1e-9
    sampling._BELOW_NYQUIST_WARNED.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.optics.sampling"):
        for s in (None, 9, 1, 1):
            smp = sampling.plan_psf_sampling(lam, 35e-3, 6e-6, 30e-6, 333, supersample=s, aperture_radius_m=5e-3)
            assert smp.nyquist_supersample == 9
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith("camera.psf.supersample=1 is below these optics' Nyquist rate (9"), said


def test_a_supersample_far_finer_than_the_exact_integral_is_refused():
    """supersample=1000001 computed a midpoint rule of 10¹² points per pixel for minutes (session 38's fuzz). The exact
    integral of the paper optics uses G = ⌈π·(N/2)/P⌉ + 16 Gauss–Legendre nodes per pixel and axis, P = λ_min·z/(Δ·p)
    = 420 nm · 35 mm / (30 µm · 6 µm) = 81.7 px the far field's period and N = 672 the FFT length: G = 29. Up to 4·G
    (odd: 115) stays allowed, for convergence comparisons; above, refused before anything is computed."""
    from hsicam.optics import sampling

    lam = np.arange(420.0, 721.0, 10.0) * 1e-9
    plan = dict(wavelengths_m=lam, sensor_distance_m=35e-3, pixel_m=6e-6, cell_m=30e-6, n_cells=333,
                aperture_radius_m=5e-3)
    assert sampling.plan_psf_sampling(**plan).fft_size == 672
    g = math.ceil(math.pi * 336 / (420e-9 * 35e-3 / (30e-6 * 6e-6))) + 16
    assert g == 29
    assert sampling.plan_psf_sampling(**plan, supersample=115).supersample == 115  # the old presets' 5, 31, 45 too
    for s in (117, 1000001):
        with pytest.raises(ConfigError, match=rf"camera\.psf\.supersample={s} takes over 4× the points .* \(29 "
                                              r"Gauss–Legendre nodes\).* odd value up to 115 "):
            sampling.plan_psf_sampling(**plan, supersample=s)
    with pytest.raises(ConfigError, match=r"camera\.psf\.supersample=1000001"):  # through the config as well
        DOECamera.from_config(load_config("tiny", ["camera.psf.supersample=1000001"]))


# --------------------------------------------------------------------------------------------
# The sampling plan's guards, found by mutation testing (optics/pupil.py, optics/sampling.py): brute-force
# counts and phase steps on the pupil grid, the Nyquist condition λ_min·z/(4a) by hand
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ratio", [0.3, 0.5, 0.75, 0.99, 1.0, 1.5, 2.0, 2.5, 7.3])
def test_cells_across_counts_the_cell_centres_inside_the_aperture(ratio):
    """Cells j·Δ with |j·Δ| ≤ R, counted by brute force; a cell up to the aperture's diameter gives one cell, a
    larger one is refused."""
    radius = 1e-3
    cell = radius / ratio
    if cell > 2 * radius:
        with pytest.raises(InputError, match="larger than the aperture diameter"):
            cells_across(radius, cell)
        return
    brute = sum(1 for j in range(-100, 101) if abs(j) * cell <= radius * (1 + 1e-12))
    assert cells_across(radius, cell) == brute


def test_nyquist_supersample_of_the_plan_is_the_smallest_odd_s_below_lambda_z_over_4a():
    """s_nyq: smallest odd s with pixel/s ≤ λ_min·z/(4a), a = half the grid by default (a brute-force search)."""
    lam = np.array([450e-9, 520e-9, 610e-9])
    z, pixel, cell, n_cells = 8e-3, 7e-6, 40e-6, 21
    for a in (None, 0.3e-3):
        radius = n_cells * cell / 2 if a is None else a
        s = next(s for s in range(1, 999, 2) if pixel / s <= lam.min() * z / (4 * radius))
        smp = plan_psf_sampling(lam, z, pixel, cell, n_cells, aperture_radius_m=a)
        assert smp.nyquist_supersample == s


def test_defocus_aliasing_is_the_largest_phase_step_between_pupil_samples_in_units_of_pi():
    """Brute force on the pupil samples inside the aperture: max |c·x_{j+1}² − c·x_j²| / π."""
    n_cells, cell, q = 41, 30e-6, 3
    radius = n_cells * cell / 2
    x = sample_coordinates_m(n_cells, cell, q)
    x = x[np.abs(x) <= radius]
    for c in (2e5, -7e5, 3e6):
        brute = np.max(np.abs(np.diff(c * x**2))) / math.pi
        got = float(defocus_aliasing(np.array([c]), radius, cell / q)[0])
        assert got == pytest.approx(brute, rel=0.03)


# --------------------------------------------------------------------------------------------
# The FFT length (session 59's fuzzing: tolerance --shift-subsamples 10**12 searched it for hours)
# --------------------------------------------------------------------------------------------
def smooth7_reference(n: int) -> int:
    """The smallest 2^a·3^b·5^c·7^d >= n, from the sorted set of every such number up to the power of 2 >= n."""
    top = 1 << max(0, n - 1).bit_length()  # a power of 2 >= n: the answer is at most it
    found = {1}
    for p in (2, 3, 5, 7):
        grown = set()
        for v in found:
            while v <= top:
                grown.add(v)
                v *= p
        found = grown
    return min(v for v in found if v >= n)


@pytest.mark.parametrize("n", [1, 2, 11, 13, 665, 2 * 333 - 1, 10007, 2 * 41 * 10**12 - 1, 2 * 41 * 2**70 - 1,
                               10**30 + 1])
def test_fast_fft_length_is_the_smallest_7_smooth_length(n):
    from hsicam.optics.sampling import fast_fft_length

    assert guarded(fast_fft_length, n) == smooth7_reference(n)


def _bare_lens_psf(object_m: float, q: int) -> tuple[np.ndarray, np.ndarray]:
    """The tiny optics without a DOE, an object at ``object_m``, pupil oversampling ``q``: (PSF (C, K, K) float64,
    the defocus phase step per band in π)."""
    cfg = load_config("tiny", ["camera.doe.enabled=false", f"camera.object_distance_m={object_m}",
                               f"camera.psf.pupil_oversample={q}"])
    cam = DOECamera.from_config(cfg).double()
    m = cam.optics
    step = defocus_aliasing(m.defocus_per_m2.double().numpy(), m.aperture_radius_m, m.cell_m / m.pupil_oversample)
    with torch.no_grad():
        return cam.psf().numpy(), step


def test_a_defocus_below_aliasing_but_coarsely_sampled_is_warned_about_with_its_error_and_fix(caplog):
    """An object at 0.1 m before the tiny optics' bare lens: the defocus steps 0.86π between pupil samples at the
    aperture edge (420 nm), accepted (below aliasing's 1) though its PSF is a third off (it used to be accepted
    without a word; hunt of session 73). The warning's error estimate is checked against the PSF of a 6× finer pupil
    grid, and its advice (pupil_oversample 2) brings the step to ≤ 0.45π; at 0.4 m (0.21π) nothing is said."""
    import logging

    from hsicam.optics import psf as psf_mod

    psf_mod._COARSE_DEFOCUS_WARNED.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.optics.psf"):
        coarse, step = _bare_lens_psf(0.1, 1)
    fine, _ = _bare_lens_psf(0.1, 6)
    k = min(coarse.shape[-1], fine.shape[-1])
    crop = lambda p: p[..., (p.shape[-1] - k) // 2:(p.shape[-1] + k) // 2, (p.shape[-1] - k) // 2:(p.shape[-1] + k) // 2]  # noqa: E731
    l1 = np.abs(crop(coarse) - crop(fine)).sum((-1, -2)) / crop(fine).sum((-1, -2))
    assert step[0] == pytest.approx(0.86, abs=0.01) and l1[0] > 0.25
    said = [r.getMessage() for r in caplog.records]
    est = 100 * psf_mod.DEFOCUS_L1_PER_STEP2 * step[0] ** 2
    assert len(said) == 1 and "camera.object_distance_m=0.1" in said[0] and "0.86π" in said[0], said
    assert f"about {est:.0f} % off" in said[0] and "pupil_oversample to 2" in said[0]
    assert est == pytest.approx(100 * l1[0], rel=0.15)  # the estimate is the measured error
    _, step2 = _bare_lens_psf(0.1, 2)
    assert step2.max() <= psf_mod.DEFOCUS_STEP_GOOD
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.optics.psf"):
        _, step_far = _bare_lens_psf(0.4, 1)
    assert step_far.max() < psf_mod.DEFOCUS_STEP_WARN and not caplog.records
