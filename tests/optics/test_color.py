"""Colour rendering against colour-science (an independent implementation of the CIE pipeline)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsicam.color import (
    cmf_d65_table,
    cube_to_srgb,
    spectra_to_linear_srgb,
    spectra_to_srgb,
    spectra_to_xyz,
    srgb_encode,
    xyz_to_linear_srgb_matrix,
)
from hsicam.errors import InputError
from hsicam.spectral import Bands

colour = pytest.importorskip("colour")
pytestmark = pytest.mark.filterwarnings("ignore:Aligning")

CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
D65 = colour.SDS_ILLUMINANTS["D65"]
CHECKER = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]


def reference_srgb(sd) -> np.ndarray:
    """colour-science: reflectance under D65 → XYZ (CIE 1931 2°) → sRGB (gamma), clipped."""
    xyz = colour.sd_to_XYZ(sd, CMFS, D65, method="Integration") / 100.0
    return np.clip(colour.XYZ_to_sRGB(xyz), 0.0, 1.0)


def sample(sd, bands: Bands) -> np.ndarray:
    return sd.copy().align(colour.SpectralShape(380, 780, 1))[bands.centers_nm]


def test_table_matches_colour_science():
    t = cmf_d65_table()
    assert t[0, 0] == 380 and t[-1, 0] == 780 and np.all(np.diff(t[:, 0]) == 5)
    np.testing.assert_allclose(t[:, 1:4], CMFS[t[:, 0]], rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(t[:, 4], D65[t[:, 0]], rtol=1e-5)


def test_srgb_matrix_matches_standard():
    space = colour.models.RGB_COLOURSPACE_sRGB
    npm = colour.normalised_primary_matrix(space.primaries, space.whitepoint)
    np.testing.assert_allclose(xyz_to_linear_srgb_matrix(), np.linalg.inv(npm), atol=1e-9)
    np.testing.assert_allclose(xyz_to_linear_srgb_matrix(), space.matrix_XYZ_to_RGB, atol=5e-4)  # IEC's 4 digits


@pytest.mark.parametrize("bands,tol", [(Bands.uniform(380, 780, 5), 0.005), (Bands.uniform(400, 700, 10), 0.01),
                                       (Bands.paper(), 0.01)])
def test_colorchecker_matches_colour_science(bands, tol):
    ours = spectra_to_srgb(np.stack([sample(sd, bands) for sd in CHECKER.values()]), bands)
    ref = np.stack([reference_srgb(sd) for sd in CHECKER.values()])
    assert ours.shape == (24, 3)
    np.testing.assert_allclose(ours, ref, atol=tol)


def test_white_maps_to_one_and_black_to_zero():
    for bands in (Bands.paper(), Bands.uniform(400, 700, 10), Bands.from_centers([453.3, 500.0, 551.4, 648.1])):
        np.testing.assert_allclose(spectra_to_srgb(np.ones(len(bands)), bands), [1, 1, 1], atol=1e-12)
        np.testing.assert_allclose(spectra_to_srgb(np.zeros(len(bands)), bands), [0, 0, 0], atol=1e-12)
        assert spectra_to_xyz(np.ones(len(bands)), bands)[1] == pytest.approx(1.0)


def test_xyz_of_colorchecker_close_to_colour_science():
    bands = Bands.uniform(380, 780, 5)
    for sd in list(CHECKER.values())[:6]:
        ref = colour.sd_to_XYZ(sd, CMFS, D65, method="Integration") / 100.0
        np.testing.assert_allclose(spectra_to_xyz(sample(sd, bands), bands), ref, atol=2e-3)


def test_srgb_encode_matches_standard_curve():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_encode(x), colour.cctf_encoding(x, function="sRGB"), atol=1e-12)


def test_cube_shapes_torch_and_numpy_agree():
    bands = Bands.paper()
    rng = np.random.default_rng(0)
    cube = rng.random((2, 31, 4, 5))
    t = cube_to_srgb(torch.from_numpy(cube), bands)
    n = cube_to_srgb(cube, bands)
    assert t.shape == (2, 3, 4, 5) and isinstance(t, torch.Tensor) and t.dtype == torch.float64
    np.testing.assert_allclose(t.numpy(), n, atol=1e-12)
    single = cube_to_srgb(cube[0], bands)
    assert single.shape == (3, 4, 5)
    np.testing.assert_allclose(single, n[0])
    # pixel (0, 0) equals spectra_to_srgb of its spectrum
    np.testing.assert_allclose(n[1, :, 2, 3], spectra_to_srgb(cube[1, :, 2, 3], bands))
    assert 0.0 <= n.min() and n.max() <= 1.0


def test_gradients_flow():
    bands = Bands.paper()
    x = (torch.rand(1, 31, 3, 3, dtype=torch.float64) * 0.6 + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: cube_to_srgb(t, bands), (x,))
    s = torch.rand(4, 31, dtype=torch.float32, requires_grad=True)
    spectra_to_srgb(s, bands).sum().backward()
    assert s.grad is not None and torch.isfinite(s.grad).all()
    z = torch.zeros(31, requires_grad=True)  # black: gradient finite (linear segment of the curve)
    spectra_to_srgb(z, bands).sum().backward()
    assert torch.isfinite(z.grad).all()


def reference_linear_srgb_of_grid(centers: np.ndarray, values: np.ndarray) -> np.ndarray:
    """colour-science: the piecewise-linear spectrum between band centres (zero beyond the grid) under D65
    → XYZ → linear sRGB, unnormalised (for comparisons up to one scale)."""
    wl = np.arange(380.0, 781.0, 1.0)
    sd = colour.SpectralDistribution(dict(zip(wl, np.interp(wl, centers, values, left=0.0, right=0.0))))
    xyz = colour.sd_to_XYZ(sd, CMFS, D65, method="Integration") / 100.0
    return colour.XYZ_to_RGB(xyz, colour.models.RGB_COLOURSPACE_sRGB, apply_cctf_encoding=False)


@pytest.mark.parametrize("lo,hi,peak", [(600.0, 700.0, 620.0), (550.0, 700.0, 560.0), (400.0, 550.0, 470.0),
                                        (500.0, 900.0, 620.0), (300.0, 600.0, 450.0)])
def test_a_grid_over_part_of_the_visible_range_keeps_its_hues(lo, hi, peak):
    """A grid missing a primary's part of the spectrum (or reaching past 380-780 nm) renders the colours
    colour-science gives the same spectrum, up to one brightness scale. A per-channel white balance divided
    by near-zero or negative whites there: a 620 nm line on 600-700 nm rendered near white (0.73, 0.69, 0.74);
    bands beyond the table were refused, which stopped `simulate` and `reconstruct` of a VIS-NIR camera."""
    bands = Bands.uniform(lo, hi, 10.0)
    spectra = np.stack([np.exp(-0.5 * ((bands.centers_nm - p) / 10.0) ** 2) for p in (peak, peak + 40.0)]
                       + [np.ones(len(bands))])
    ours = spectra_to_linear_srgb(spectra, bands)
    ref = np.stack([reference_linear_srgb_of_grid(bands.centers_nm, s) for s in spectra])
    scale = float(np.sum(ours * ref) / np.sum(ref * ref))
    np.testing.assert_allclose(ours, scale * ref, atol=0.02 * np.abs(ours).max())  # 1 nm rectangle vs trapezoid at the grid edges
    assert spectra_to_xyz(np.ones(len(bands)), bands)[1] == pytest.approx(1.0)  # white reflector: Y = 1 on its grid
    if (lo, hi) == (600.0, 700.0):  # the line is a saturated red
        r, g, b = spectra_to_srgb(spectra[0], bands)
        # (its red below the white reflector's, whose brightest channel is 1: the line reflects less light)
        assert 0.5 < r < 1.0 and g < 0.01 and b < 0.01


def test_a_grid_with_no_visible_band_renders_grey():
    """800-1000 nm: nothing to render in colour; grey, the mean over the bands (as data.preview's thumbnails)."""
    bands = Bands.uniform(800.0, 1000.0, 20.0)
    spectra = np.random.default_rng(0).uniform(0.0, 1.0, (5, len(bands)))
    np.testing.assert_allclose(spectra_to_linear_srgb(spectra, bands), np.repeat(spectra.mean(-1, keepdims=True), 3, -1),
                               atol=1e-12)
    np.testing.assert_allclose(spectra_to_srgb(np.ones(len(bands)), bands), [1, 1, 1], atol=1e-12)


def test_errors():
    with pytest.raises(InputError, match="31 bands"):
        spectra_to_srgb(np.ones((2, 30)), Bands.paper())
    with pytest.raises(InputError, match="B, C, H, W"):
        cube_to_srgb(np.ones((31, 4)), Bands.paper())


def test_srgb_encode_at_the_linear_segments_end_matches_colour_science_in_numpy_and_torch():
    """IEC 61966-2-1: 12.92·L for L ≤ 0.0031308 (the threshold itself included), 1.055·L^(1/2.4) − 0.055 above
    (the two differ by 2.9e-8 at the threshold), dense over the first 1 % of the range, where the two pieces
    meet; numpy and torch alike, against colour-science's curve."""
    x = np.concatenate([np.linspace(0.0, 0.01, 1001), [0.0031308, np.nextafter(0.0031308, 1.0)]])
    ref = colour.cctf_encoding(x, function="sRGB")
    np.testing.assert_allclose(srgb_encode(x), ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(srgb_encode(torch.from_numpy(x)).numpy(), ref, rtol=0, atol=1e-12)


def reference_xyz_on_1nm_grid(centers: np.ndarray, spectrum: np.ndarray) -> np.ndarray:
    """The module docstring's XYZ written out with numpy: the piecewise-linear spectrum between band centres times
    x̄ȳz̄ and D65 (the shipped 5 nm table, linearly interpolated: checked against colour-science above), trapezoid
    rule on the 1 nm grid over the part of the bands' range inside 380-780 nm (its ends included), scaled so that
    the white reflector has Y = 1."""
    table = cmf_d65_table()
    lo, hi = max(centers[0], 380.0), min(centers[-1], 780.0)
    lam = np.union1d([lo, hi], np.arange(np.ceil(lo), np.floor(hi) + 1.0))
    kernel = np.stack([np.interp(lam, table[:, 0], table[:, k]) * np.interp(lam, table[:, 0], table[:, 4])
                       for k in (1, 2, 3)])
    xyz = np.trapezoid(kernel * np.interp(lam, centers, spectrum), lam, axis=1)
    return xyz / np.trapezoid(kernel[1], lam)


@pytest.mark.parametrize("centers", [Bands.paper().centers_nm, np.array([402.5, 447.3, 510.0, 598.7, 603.2]),
                                     np.arange(300.0, 601.0, 15.0), np.arange(700.0, 901.0, 20.0)])
def test_xyz_is_the_1nm_trapezoid_integral_of_the_interpolated_spectrum(centers):
    """XYZ of a spectrum on a band grid (uniform, non-uniform with fractional ends, across 380 nm, across 780 nm)
    = the 1 nm trapezoid integral of its interpolant that the module docstring describes, to rounding (a step of
    2 nm instead of 1 at one end of the grid changes it by ~1e-6)."""
    spectrum = np.random.default_rng(len(centers)).uniform(0.1, 1.0, len(centers))
    bands = Bands.from_centers(centers)
    np.testing.assert_allclose(spectra_to_xyz(spectrum, bands), reference_xyz_on_1nm_grid(centers, spectrum),
                               rtol=1e-11, atol=1e-14)


@pytest.mark.parametrize("centers, end", [(np.arange(300.0, 381.0, 20.0), 380), (np.arange(780.0, 901.0, 20.0), 780)])
def test_a_grid_touching_the_table_at_one_end_renders_that_wavelength(centers, end):
    """A grid that meets 380-780 nm at one end only has colour at that one wavelength: XYZ = the interpolant's value
    there (the end band's value) × (x̄, ȳ, z̄)/ȳ at that wavelength (colour-science's CIE 1931 2° values)."""
    bands = Bands.from_centers(centers)
    spectrum = np.linspace(0.2, 0.9, len(centers))
    at_end = spectrum[-1] if end == 380 else spectrum[0]
    cmf = CMFS[end]
    np.testing.assert_allclose(spectra_to_xyz(spectrum, bands), at_end * cmf / cmf[1], rtol=1e-5)


def test_a_grid_just_beyond_780nm_renders_grey():
    """A grid starting 1 nm past the table's end (781-901 nm, or a single band at 780.5 nm) has nothing to render in
    colour: grey, the mean over its bands."""
    for bands in (Bands.from_centers(np.arange(781.0, 902.0, 20.0)), Bands.from_centers([780.5])):
        spectra = np.random.default_rng(1).uniform(0.0, 1.0, (4, len(bands)))
        np.testing.assert_allclose(spectra_to_linear_srgb(spectra, bands),
                                   np.repeat(spectra.mean(-1, keepdims=True), 3, -1), atol=1e-12)


@pytest.mark.parametrize("chunk_px", [10, 23, None])
def test_srgb_preview_rendered_in_bands_of_rows_puts_every_row_in_its_place(chunk_px):
    """A grey ramp down the rows (reflectance k constant over the bands: linear sRGB (k, k, k), the white balance
    maps white to (1, 1, 1)) previewed a few rows at a time (chunks of 2 and 4 rows for 5 px wide, the last one
    short) or whole: each row holds round(255 · sRGB(k)) of its own k (colour-science's curve)."""
    from hsicam.color import srgb_preview

    bands = Bands.paper()
    k = np.linspace(0.05, 0.95, 22)
    cube = np.broadcast_to(k[None, :, None], (len(bands), 22, 5)).astype(np.float32)
    got = srgb_preview(cube, bands, chunk_px=chunk_px)
    want = 255.0 * colour.cctf_encoding(k.astype(np.float32).astype(np.float64), function="sRGB")
    assert got.shape == (22, 5, 3) and got.dtype == np.uint8
    assert np.abs(got.astype(np.float64) - want[:, None, None]).max() <= 0.5 + 1e-3  # rounding (float32 render)


@pytest.mark.parametrize("lo,hi,step", [(600.0, 900.0, 10.0), (650.0, 950.0, 5.0), (550.0, 700.0, 10.0)])
def test_a_red_or_near_infrared_grid_keeps_its_structure_in_previews(lo, hi, step):
    """A grid missing primaries is rendered unbalanced (hues right) with its white's brightest channel at 1, and a
    preview is exposed by that channel: a grey ramp stays a ramp. With Y = 1 a 650-950 nm white had R = 7.2, and the
    preview's exposure (Y's 99th percentile at 0.8) put every pixel of the ramp at R = 255 (session 75's hunt: truth
    and reconstruction rendered as the same flat red square)."""
    from hsicam.color import PREVIEW_LEVEL, preview_exposure, srgb_preview, srgb_weights, white_balanced

    bands = Bands.uniform(lo, hi, step)
    assert not white_balanced(bands) and white_balanced(Bands.uniform(420.0, 720.0, 10.0))
    white = srgb_weights(bands).sum(axis=1)
    assert white.max() == pytest.approx(1.0) and white[0] == pytest.approx(1.0)  # red is the brightest
    ramp = np.linspace(0.05, 1.0, 64, dtype=np.float32)
    cube = np.broadcast_to(ramp[None, None, :], (len(bands), 4, 64)).copy()
    exposure = preview_exposure(cube, bands)
    red_p99 = float(np.percentile(np.broadcast_to(ramp, (4, 64)), 99))  # the ramp's red channel: ramp × white's R
    assert exposure == pytest.approx(PREVIEW_LEVEL / red_p99, rel=1e-5)
    red = srgb_preview(cube, bands, exposure=exposure)[0, :, 0].astype(int)
    assert np.all(np.diff(red) >= 0) and len(np.unique(red)) > 40 and red.max() < 255
