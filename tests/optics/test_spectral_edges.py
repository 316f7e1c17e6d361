"""Edge cases of the spectral rules (review 54): equal centres of unequal width, the generator's range edges,
band averaging on non-uniform grids, Bands' hash, and material tables written with a byte-order mark."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from hsicam.data.cube import conform_bands
from hsicam.errors import InputError
from hsicam.spectral import (Bands, band_matrix, fine_grid, get_material, interpolation_matrix, resample_spectra,
                             resampling_matrix, resolved_bands)
from hsicam.spectral.bands import band_sample_wavelengths, kernel_fwhm


def test_same_centres_of_wider_bands_are_integrated_not_passed_through():
    """2 nm-wide data on the 10 nm camera's centres: the camera's bands are integrated (the one rule), as for
    centres 2e-6 nm off; the shortcut returned the data unchanged (a line kept its full height)."""
    src = Bands.uniform(420, 720, 10, fwhm_nm=2.0)
    cam = Bands.uniform(420, 720, 10)
    c = cam.centers_nm.copy()
    c[1:-1] += 2e-6
    shifted = Bands(c, cam.fwhm_nm)
    x = np.zeros(len(src))
    x[13] = 1.0  # a line at 550 nm
    want = resampling_matrix(src, cam) @ x
    # spread over the neighbours by the wider bands, as wide as declared: the source's 2 nm and the spread add to 10 nm
    # (variance about the line's centre; session 74: the interpolant's own spread is counted)
    fwhm2 = 8 * math.log(2)
    spread = float(want @ (cam.centers_nm - 550.0) ** 2)
    assert want[13] < 0.9 and math.sqrt(fwhm2 * (spread + 2.0**2 / fwhm2)) == pytest.approx(10.0, rel=0.02)
    np.testing.assert_allclose(resample_spectra(x, src, cam), want, atol=1e-12)
    np.testing.assert_allclose(resample_spectra(x, src, cam), resample_spectra(x, src, shifted), atol=1e-5)
    got_t = resample_spectra(torch.from_numpy(x), src, cam)
    np.testing.assert_allclose(got_t.numpy(), want, atol=1e-12)
    cube = np.broadcast_to(x[:, None, None], (31, 2, 2)).astype(np.float32)
    out = conform_bands(cube, src, cam, note=False)
    np.testing.assert_allclose(out[:, 0, 0], want, atol=1e-6)
    np.testing.assert_allclose(out, conform_bands(cube, src, shifted, note=False), atol=1e-5)
    # nothing to average (same centres, bands no wider): still the values themselves
    assert resample_spectra(x, cam, src) is x and conform_bands(cube, cam, src) is cube


def test_generator_warns_once_when_the_range_edges_drop_spectra(caplog):
    """380-730 nm bands (inside SUPPORTED_RANGE_NM) kept 43 of 423 reflectances with no message: one WARNING per
    library build names the counts and sources; a grid inside the full-use range gives none; the refusal names it."""
    pytest.importorskip("colour")
    from hsicam.data.spectral_sources import check_bands, spectral_library

    logger = "hsicam.data.spectral_sources"
    edge = Bands.uniform(380, 730, 10, fwhm_nm=9.75)  # a width of its own: a fresh build, not a cached library
    with caplog.at_level(logging.DEBUG, logger=logger):
        lib = spectral_library(edge)
        spectral_library(edge)  # cached: no second warning
    said = [r.getMessage() for r in caplog.records if r.name == logger and r.levelno == logging.WARNING]
    detail = [r.getMessage() for r in caplog.records if r.name == logger and r.levelno == logging.DEBUG
              and "not used for bands" in r.getMessage()]
    assert len(said) == 1 and len(detail) == 1, (said, detail)
    kept = sum(lib.counts()["reflectances"].values())
    unused = {k: len(v) for k, v in lib.sources["not_used_out_of_range"].items() if k != "cie (not used)"}
    assert kept < 100 and said[0].startswith(f"synthetic: {sum(unused.values())} of "), said[0]
    assert "(rawtoaces 190, " in said[0] and len(said[0]) <= 250, said[0]  # the largest source first; one short line
    assert f"{460 - kept} of 460 reflectance spectra (rawtoaces 190" in detail[0], detail[0]  # the full count at -v
    assert "illuminant spectra (" in detail[0], detail[0]
    t = 3.0 * 9.75 / 2.3548  # the widest band's 3σ: the stated range is ALL_SOURCES_RANGE_NM (370-740) less it
    assert f"band centres within {round(370 + t, 1):g}-{round(740 - t, 1):g} nm would use all but PMC and Smits" \
           in said[0], said[0]
    caplog.clear()
    inside = Bands.uniform(390, 720, 10, fwhm_nm=9.75)
    with caplog.at_level(logging.WARNING, logger=logger):
        spectral_library(inside)
    assert not [r for r in caplog.records if r.name == logger], caplog.text
    with pytest.raises(InputError, match="used only for bands whose centre ± 1.27 FWHM stays inside 370-740 nm"):
        check_bands(Bands.uniform(370, 730, 10))


def test_band_matrix_averages_per_nm_on_a_non_uniform_grid():
    """Samples 0.5 nm apart below 550 nm and 2 nm above: a spectrum linear in λ came out 47.98, not ~50 (the
    dense side weighed 4× per nm); a uniform grid keeps its equal weights (its ends are not halved)."""
    fine = np.concatenate([np.arange(500.0, 550.0, 0.5), np.arange(550.0, 601.0, 2.0)])
    g = band_matrix(Bands(np.array([550.0]), np.array([10.0])), fine)[0]
    s = 10.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    w = np.exp(-0.5 * ((fine - 550.0) / s) ** 2) * (np.abs(fine - 550.0) <= 3 * s)
    ref = np.trapezoid(w * (fine - 500.0), fine) / np.trapezoid(w, fine)
    assert g @ (fine - 500.0) == pytest.approx(ref, abs=1e-12)
    assert g @ (fine - 500.0) == pytest.approx(50.0, abs=0.05)
    uniform = np.arange(400.0, 461.0, 1.0)
    bands = Bands(np.array([405.0, 430.0, 453.0]), np.array([10.0, 10.0, 10.0]))  # two reach the grid's ends
    per_sample = np.exp(-0.5 * ((uniform[None, :] - bands.centers_nm[:, None]) / s) ** 2)
    per_sample[np.abs(uniform[None, :] - bands.centers_nm[:, None]) > 3 * s] = 0.0
    per_sample /= per_sample.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(band_matrix(bands, uniform), per_sample, rtol=0, atol=1e-12)


def test_the_fine_grid_holds_every_band_response_out_to_three_sigma_on_both_sides():
    """fine_grid spans the lowest centre − 3σ to the highest + 3σ (σ = FWHM / 2√(2 ln 2) of the widest band),
    whole nm, 1 nm apart: so band_matrix on it keeps each band's whole response, and a band at either end of
    the grid averages a symmetric window (its row's mean wavelength is its centre, as a Gaussian's is)."""
    bands = Bands(np.array([420.0, 500.0, 613.0, 700.0]), np.array([10.0, 30.0, 12.0, 25.0]))
    sigma_max = 30.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))  # 12.74 nm: 3σ = 38.2 nm
    fine = fine_grid(bands)
    assert fine[0] == math.floor(420.0 - 3 * sigma_max) and fine[-1] == math.ceil(700.0 + 3 * sigma_max)
    np.testing.assert_array_equal(np.diff(fine), 1.0)
    g = band_matrix(bands, fine)
    np.testing.assert_allclose(g @ fine, bands.centers_nm, rtol=0, atol=1e-9)  # symmetric about each centre
    for c, f in zip(bands.centers_nm, bands.fwhm_nm):  # every sample within 3σ of a centre is on the grid
        s = f / (2.0 * math.sqrt(2.0 * math.log(2.0)))
        inside = np.arange(math.ceil(c - 3 * s), math.floor(c + 3 * s) + 1.0)
        assert np.isin(inside, fine).all()


def test_equal_bands_hash_equal():
    """== allows 1e-6 nm per centre; the hash rounded centres to 6 decimals, so equal grids fell into two set slots."""
    a, b = Bands.from_centers([500.0000004]), Bands.from_centers([500.0000006])
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    c = Bands.uniform(420, 720, 10)
    d = Bands(c.centers_nm + 0.9e-6, c.fwhm_nm)
    assert c == d and hash(c) == hash(d)


def test_material_csv_with_a_byte_order_mark(tmp_path):
    """Excel's "CSV UTF-8" starts with a BOM, which glued onto 'wavelength_nm' and read as a missing column."""
    p = tmp_path / "glass.csv"
    p.write_text("wavelength_nm,n\n400,1.47\n700,1.455\n", encoding="utf-8-sig")
    assert float(get_material(str(p)).n(550.0)) == pytest.approx(1.4625)


# --------------------------------------------------------------------------------------------
# Guards found by mutation testing (spectral/bands.py, spectral/materials.py): closed forms, numerical
# integrals (scipy quad), brute force
# --------------------------------------------------------------------------------------------
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def test_band_sub_wavelengths_are_the_gauss_hermite_nodes_of_the_bands_gaussian():
    """M sub-wavelengths and weights of the band's Gaussian of FWHM f (σ = f·FWHM_TO_SIGMA): for M = 2 the nodes
    c ± σ, weights ½; for M = 3 c and c ± √3·σ, weights 2/3 and 1/6 (the closed forms of Gauss–Hermite quadrature);
    they average a line's response as the band that resampling and the generator use (session 74: the midpoints of
    M slices of ±f/2 never reached it)."""
    c, f = np.array([450.0, 600.0]), np.array([10.0, 24.0])
    s = f * FWHM_TO_SIGMA
    lam, w = band_sample_wavelengths(c, f, 2)
    np.testing.assert_allclose(lam, np.stack([c - s, c + s], axis=1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(w, 0.5, rtol=1e-12)
    lam, w = band_sample_wavelengths(c, f, 3)
    np.testing.assert_allclose(lam, np.stack([c - math.sqrt(3) * s, c, c + math.sqrt(3) * s], axis=1), atol=1e-9)
    np.testing.assert_allclose(w, np.tile([1 / 6, 2 / 3, 1 / 6], (2, 1)), rtol=1e-12)


def test_a_target_band_beyond_the_source_by_a_fraction_of_a_nm_is_refused():
    """No extrapolation: a grid ending 0.01 nm past the data's last centre is refused (only 1e-6 nm of rounding
    is forgiven); a tolerance of a nm would clip it onto the last band silently."""
    src = Bands.uniform(420, 720, 10)
    for end in (720.01, 720.5):
        dst = Bands.from_centers([500.0, end], 10.0)
        assert not src.covers(dst)
        with pytest.raises(InputError, match="not covered"):
            interpolation_matrix(src, dst)
    assert src.covers(Bands.from_centers([420.0 - 5e-7, 720.0 + 5e-7], 10.0))


def test_default_fwhm_of_given_centres_is_the_local_spacing():
    """from_centers without FWHM: each band is as wide as its local spacing, (c[i+1] − c[i−1]) / 2 inside and the
    one-sided step at the ends (10 nm for a single band)."""
    c = np.array([400.0, 410.0, 430.0, 460.0, 465.0])
    got = Bands.from_centers(c).fwhm_nm
    ref = np.concatenate([[c[1] - c[0]], (c[2:] - c[:-2]) / 2, [c[-1] - c[-2]]])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert Bands.from_centers([550.0]).fwhm_nm.tolist() == [10.0]


def test_bands_a_fraction_of_a_nm_wider_than_the_data_integrate_it():
    """Same centres, camera bands √(10² + 0.5²) nm wide over 10 nm data: 0.5 nm of averaging is left, so the bands
    are resolved (kernel FWHM > 0), but a line at one band may lose no more of its height to the neighbours than keeps
    the band's response at its declared width: its variance about the line at most σ_k² (FWHM 0.5 nm) more than the
    data's (session 74: the linear interpolant integrated over a Gaussian of FWHM 0.5 nm spread the line by ~20 times
    that, the band ~1.6 nm wider than declared)."""
    src = Bands.uniform(420, 720, 10)
    k = 0.5
    dst = Bands(src.centers_nm, np.full(len(src), math.hypot(10.0, k)))
    np.testing.assert_allclose(kernel_fwhm(src, dst), k, rtol=1e-9)
    assert resolved_bands(src, dst).all()
    x = np.zeros(len(src))
    x[13] = 1.0
    s = k * FWHM_TO_SIGMA
    got = resample_spectra(x, src, dst)
    assert got is not x
    # the spread the band asks for (σ_k² = 0.045 nm²) is what the interpolant gives a Gaussian of σ' ~0.006 nm: the
    # line keeps its height but for σ_k²/h² of it, shared by the neighbours, as wide as declared
    np.testing.assert_allclose(float(got @ (src.centers_nm - 550.0) ** 2), s * s, rtol=0.02)
    np.testing.assert_allclose(got, x, atol=s * s / 100.0)
    np.testing.assert_allclose(got[12] + got[13] + got[14], 1.0, atol=1e-9)  # the line's area is kept


def test_the_remaining_width_uses_the_source_fwhm_at_each_band():
    """Source bands whose FWHM changes along the grid (4 nm at the blue end to 9 nm at the red): the kernel left
    for a 10 nm band is √(10² − f_src(c)²) with f_src read at that band's centre (Gaussians compose in quadrature),
    not one width for all."""
    c = np.arange(420.0, 721.0, 5.0)
    f_src = np.linspace(4.0, 9.0, len(c))
    src = Bands(c, f_src)
    dst = Bands.uniform(430, 710, 10)
    ref = np.sqrt(10.0 ** 2 - np.interp(dst.centers_nm, c, f_src) ** 2)
    np.testing.assert_allclose(kernel_fwhm(src, dst), ref, rtol=1e-12)


def test_fused_silica_is_refused_beyond_both_ends_of_malitsons_fit():
    """The Sellmeier fit holds for 0.21–3.71 µm: a wavelength past either end is one clear error (past 3.71 µm
    the third term's pole at 9.9 µm is near, and the formula is no longer the glass)."""
    from hsicam.spectral import FusedSilica

    fs = FusedSilica()
    for lam in (200.0, 3800.0, [500.0, 5000.0]):
        with pytest.raises(InputError, match="valid for 210-3710 nm only"):
            fs.n(lam)
    assert np.isfinite(fs.n([210.0, 3710.0])).all()


def test_a_material_table_is_refused_a_fraction_of_a_nm_past_its_ends():
    """A table from 400 to 700 nm answers inside (linear interpolation) and refuses 700.5 nm and 399.5 nm: no
    extrapolation, not even by a few nm."""
    from hsicam.spectral import TabulatedMaterial

    mat = TabulatedMaterial(np.array([400.0, 550.0, 700.0]), np.array([1.47, 1.46, 1.455]), name="glass")
    np.testing.assert_allclose(mat.n([400.0, 475.0, 700.0]), [1.47, 1.465, 1.455], rtol=0, atol=1e-12)
    for lam in (700.5, 399.5, 705.0):
        with pytest.raises(InputError, match="tabulated for 400-700 nm only"):
            mat.n(lam)
