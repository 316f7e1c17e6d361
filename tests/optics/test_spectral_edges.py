"""Edge cases of the spectral rules (review 54): equal centres of unequal width, the generator's range edges,
band averaging on non-uniform grids, Bands' hash, and material tables written with a byte-order mark."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from hsicam.data.cube import conform_bands
from hsicam.errors import InputError
from hsicam.spectral import Bands, band_matrix, get_material, resample_spectra, resampling_matrix


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
    assert want[13] < 0.7  # spread over the neighbours by the wider bands
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
    with caplog.at_level(logging.WARNING, logger=logger):
        lib = spectral_library(edge)
        spectral_library(edge)  # cached: no second warning
    said = [r.getMessage() for r in caplog.records if r.name == logger and r.levelno == logging.WARNING]
    assert len(said) == 1, said
    kept = sum(lib.counts()["reflectances"].values())
    assert kept < 100 and f"{460 - kept} of 460 reflectance spectra" in said[0], said[0]
    assert "reflectance spectra (rawtoaces 190" in said[0] and "illuminant spectra (" in said[0], said[0]
    t = 3.0 * 9.75 / 2.3548  # the widest band's 3σ: the stated range is ALL_SOURCES_RANGE_NM (370-740) less it
    assert f"not_used_out_of_range); at this FWHM all but the PMC and Smits sets are used for band centres within " \
           f"{round(370 + t, 1):g}-{round(740 - t, 1):g} nm" in said[0], said[0]
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
