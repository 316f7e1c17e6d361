"""Three silent-wrong paths of the readers (audit items 07a, 07c, and ENVI gains/offsets).

1. ENVI ``data gain values`` / ``data offset values`` (value = gain · stored + offset per band) are
   applied; ``data ignore value`` is compared with the *stored* value, flagged values stay 0.
   Headers and raw bytes are written by hand, as ENVI software does.
2. A camera band wider than the data's own bands integrates the data (their linear interpolant over
   a Gaussian of the width they lack, √(f_band² − f_data²), cut symmetrically) instead of
   point-sampling them at its centre; bands no wider than the data's are interpolated exactly as
   before. References: the integral and ``np.interp`` computed here with numpy.
3. ``hsicam data show`` takes ``--set data.npy_bands...`` like the other commands.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_helpers import assert_clean_error, assert_ok, run_cli_in_process
from envi_files import write_envi_pair
from hsicam.data import read_cube, read_envi, resample_cube
from hsicam.data.cube import conform_bands
from hsicam.errors import InputError
from hsicam.spectral import Bands, interpolation_matrix, resample_spectra, resolved_bands

PAPER = Bands.paper()  # 31 bands, 420-720 nm, FWHM 10 nm


# ------------------------------------------------------------------------------------------------
# 1. ENVI gains and offsets
# ------------------------------------------------------------------------------------------------
WAVES = (420.0, 470.0, 520.0, 570.0, 620.0, 670.0, 720.0)


def envi_pair(folder: Path, chw: np.ndarray, extra: str, waves=WAVES, dtype: str = "<u2", code: int = 12,
              interleave: str = "bil") -> Path:
    return write_envi_pair(folder, chw, extra, waves, dtype, code, interleave)


def stored(seed=0, h=6, w=5) -> np.ndarray:
    return np.round(np.random.default_rng(seed).random((7, h, w)) * 3900 + 100)


GAINS = np.array([0.01, 0.02, 0.5, 1.0, 2.0, 0.25, 0.125])
OFFSETS = np.array([0.5, 0.0, 3.0, 10.0, 0.25, 1.0, 7.0])


def listed(values) -> str:
    return "{" + ", ".join(repr(float(v)) for v in values) + "}"


def test_envi_gains_and_offsets_are_applied_per_band(tmp_path, caplog):
    raw = stored()
    hdr = envi_pair(tmp_path, raw, f"data gain values = {listed(GAINS)}\ndata offset values = {listed(OFFSETS)}\n")
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        cube, bands, meta = read_cube(hdr)
    expected = GAINS[:, None, None] * raw + OFFSETS[:, None, None]
    np.testing.assert_allclose(cube, expected, rtol=1e-6)
    assert cube.dtype == np.float32
    assert meta["data_gain_offset_applied"] is True
    assert meta["data_gain_values"] == GAINS.tolist() and meta["data_offset_values"] == OFFSETS.tolist()
    said = [r.getMessage() for r in caplog.records if "gain" in r.getMessage()]
    assert len(said) == 1 and "data gain values and data offset values" in said[0] and "scene.hdr" in said[0]


def test_envi_gains_alone_or_offsets_alone(tmp_path):
    raw = stored(1)
    (tmp_path / "g").mkdir()
    (tmp_path / "o").mkdir()
    cube, _, meta = read_envi(envi_pair(tmp_path / "g", raw, f"data gain values = {listed(GAINS)}\n"))
    np.testing.assert_allclose(cube, GAINS[:, None, None] * raw, rtol=1e-6)
    assert meta["data_offset_values"] == [0.0] * 7
    cube, _, meta = read_envi(envi_pair(tmp_path / "o", raw, f"data offset values = {listed(OFFSETS)}\n"))
    np.testing.assert_allclose(cube, raw + OFFSETS[:, None, None], rtol=1e-6)
    assert meta["data_gain_values"] == [1.0] * 7


def test_envi_ignore_value_is_the_stored_value_and_flagged_values_stay_zero(tmp_path):
    raw = stored(2)
    raw[:, 0, :] = 100  # a no-data row (stored 100)
    raw[4, 3, 2] = 100  # one no-data value; the pixel's other bands keep their data
    raw[1, 2, 2] = 50   # stored 50 × gain 2 = 100: physically 100, but not flagged (the flag is on stored values)
    gains = np.array([1.0, 2.0, 1.0, 1.0, 3.0, 1.0, 1.0])
    hdr = envi_pair(tmp_path, raw, f"data ignore value = 100\ndata gain values = {listed(gains)}\n"
                                   f"data offset values = {listed(OFFSETS)}\n", interleave="bsq")
    cube, _, meta = read_cube(hdr)
    flagged = raw == 100
    expected = np.where(flagged, 0.0, gains[:, None, None] * raw + OFFSETS[:, None, None])
    np.testing.assert_allclose(cube, expected, rtol=1e-6)
    assert np.all(cube[:, 0, :] == 0) and cube[4, 3, 2] == 0  # not the offset
    assert cube[1, 2, 2] == pytest.approx(2.0 * 50 + OFFSETS[1])
    assert meta["ignored_pixels"] == 5 + 1 and meta["data_gain_offset_applied"] is True


def test_envi_gains_follow_their_bands_through_bbl_and_band_sorting(tmp_path):
    raw = stored(3)
    waves = (720.0, 670.0, 620.0, 570.0, 520.0, 470.0, 420.0)  # descending in the file
    hdr = envi_pair(tmp_path, raw, f"bbl = {{1, 1, 0, 1, 1, 1, 1}}\ndata gain values = {listed(GAINS)}\n"
                                   f"data offset values = {listed(OFFSETS)}\n", waves=waves, interleave="bip")
    cube, bands, meta = read_cube(hdr)
    keep = [6, 5, 4, 3, 1, 0]  # file bands in ascending wavelength, 620 nm (file band 2) dropped
    np.testing.assert_allclose(bands.centers_nm, [waves[k] for k in keep])
    np.testing.assert_allclose(cube, GAINS[keep, None, None] * raw[keep] + OFFSETS[keep, None, None], rtol=1e-6)
    assert meta["data_gain_values"] == GAINS[keep].tolist() and meta["data_offset_values"] == OFFSETS[keep].tolist()


def test_envi_reflectance_scale_factor_divides_after_gains_and_offsets(tmp_path):
    raw = stored(4)
    hdr = envi_pair(tmp_path, raw, f"data gain values = {listed(GAINS)}\ndata offset values = {listed(OFFSETS)}\n"
                                   "reflectance scale factor = 4\n")
    cube, _, _ = read_envi(hdr)
    np.testing.assert_allclose(cube, (GAINS[:, None, None] * raw + OFFSETS[:, None, None]) / 4.0, rtol=1e-6)


@pytest.mark.parametrize("key", ["data gain values", "data offset values"])
def test_envi_gain_or_offset_list_of_the_wrong_length_is_one_error(tmp_path, key):
    hdr = envi_pair(tmp_path, stored(), f"{key} = {{1, 2, 3, 4, 5}}\n")
    with pytest.raises(InputError) as exc:
        read_cube(hdr)
    msg = str(exc.value)
    assert "\n" not in msg and "scene.hdr" in msg and f"'{key}'" in msg and "5 values for 7 bands" in msg


def test_envi_non_numeric_or_non_finite_gains_are_refused(tmp_path):
    hdr = envi_pair(tmp_path, stored(), "data gain values = {1, 1, 1, nan, 1, 1, 1}\n")
    with pytest.raises(InputError, match="'data gain values' holds 1 value"):
        read_cube(hdr)
    hdr = envi_pair(tmp_path, stored(), "data offset values = {1, 1, x, 1, 1, 1, 1}\n")
    with pytest.raises(InputError, match="'data offset values' must be a list of numbers"):
        read_cube(hdr)


def test_envi_without_gains_is_read_as_before(tmp_path):
    raw = stored(5)
    cube, _, meta = read_envi(envi_pair(tmp_path, raw, ""))
    np.testing.assert_array_equal(cube, raw.astype(np.float32))
    assert "data_gain_offset_applied" not in meta


# ------------------------------------------------------------------------------------------------
# 2. Band response: finer data are integrated over each band's FWHM
# ------------------------------------------------------------------------------------------------
def band_reference(source_nm: np.ndarray, values: np.ndarray, centre: float, fwhm: float,
                   source_fwhm: float) -> float:
    """The reference, written out here: the source's linear interpolant (``np.interp``) integrated
    (trapezoid, 40 001 nodes) over a Gaussian whose average of the interpolant spreads a line by the width the
    source's own bands lack, √(fwhm² − source_fwhm²) (tests/optics_reference.py; session 74: the Gaussian itself
    had that width, and the bands came out wider than declared), cut at 3 σ or at the centre's distance to the
    nearer end of the data (symmetric); the point sample where no Gaussian is left."""
    from optics_reference import interpolant_gaussian_sigma

    sigma = interpolant_gaussian_sigma(source_nm, centre,
                                       math.sqrt(fwhm**2 - source_fwhm**2) / (2.0 * math.sqrt(2.0 * math.log(2.0))))
    if sigma < 1e-6:
        return float(np.interp(centre, source_nm, values))
    r = min(3.0 * sigma, centre - source_nm[0], source_nm[-1] - centre)
    x = np.linspace(centre - r, centre + r, 40001)
    g = np.exp(-0.5 * ((x - centre) / sigma) ** 2)
    return float(np.trapezoid(g * np.interp(x, source_nm, values), x) / np.trapezoid(g, x))


@pytest.mark.parametrize("step", [1.0, 5.0])
def test_a_narrow_line_reaches_the_bands_whose_response_covers_it(step):
    src = Bands.uniform(400.0, 740.0, step)  # FWHM = the step
    line = 555.0 if step == 1.0 else 545.0  # one source sample: a spike at 555 nm (5 nm: at 545 nm)
    cube = np.zeros((len(src), 2, 3))
    k = int(np.flatnonzero(np.isclose(src.centers_nm, line))[0])
    cube[k] = 1.0
    out = resample_cube(cube, src, PAPER)
    # the point sample at the band centres (the old behaviour) misses the line altogether
    old = np.einsum("ij,jhw->ihw", interpolation_matrix(src, PAPER), cube)
    assert np.all(old == 0.0)
    expected = np.array([band_reference(src.centers_nm, cube[:, 0, 0], c, 10.0, step) for c in PAPER.centers_nm])
    np.testing.assert_allclose(out[:, 0, 0], expected, rtol=1e-4, atol=1e-7)
    assert np.all(out == out[:, :1, :1])
    j = int(np.flatnonzero(PAPER.centers_nm == line - 5.0)[0])
    assert out[j, 0, 0] > 0.04 and out[j + 1, 0, 0] == pytest.approx(out[j, 0, 0], rel=1e-6)
    far = np.abs(PAPER.centers_nm - line) > 20.0  # beyond 3 σ plus the interpolant's reach
    assert np.all(out[far] == 0.0)


def test_fine_resampling_is_the_integrated_interpolant_on_every_band():
    src = Bands.uniform(410.0, 730.0, 1.0)
    spectra = np.random.default_rng(0).random((len(src), 4))
    out = resample_spectra(spectra, src, PAPER, axis=0)
    ref = np.array([[band_reference(src.centers_nm, spectra[:, j], c, 10.0, 1.0) for j in range(4)]
                    for c in PAPER.centers_nm])
    np.testing.assert_allclose(out, ref, rtol=1e-4)


def test_bands_wider_than_the_data_integrate_them_with_the_width_the_data_lack():
    """10 nm data onto 20 nm bands (the default FWHM: the step) add √(20² − 10²) nm of width; the same
    samples declared 2 nm wide add √(20² − 2²) nm: the source's own FWHM counts."""
    values = np.random.default_rng(4).random(33)
    dst = Bands.uniform(420.0, 700.0, 20.0)
    for source_fwhm in (10.0, 2.0):
        src = Bands.uniform(400.0, 720.0, 10.0, fwhm_nm=source_fwhm)
        out = resample_spectra(values, src, dst)
        ref = [band_reference(src.centers_nm, values, c, 20.0, source_fwhm) for c in dst.centers_nm]
        np.testing.assert_allclose(out, ref, rtol=1e-4)
        assert np.abs(out - np.interp(dst.centers_nm, src.centers_nm, values)).max() > 0.01  # not the point sample


@pytest.mark.parametrize("src,dst", [(Bands.uniform(400.0, 720.0, 1.0), PAPER),  # the 720 nm band on the data's end
                                     (Bands.uniform(420.0, 720.0, 10.0), Bands.uniform(420.0, 720.0, 50.0)),
                                     (Bands.uniform(400.0, 700.0, 10.0),
                                      Bands.from_centers([403.0, 455.5, 512.25, 600.0, 699.9]))],
                         ids=["1nm-onto-paper", "10nm-onto-50nm", "off-grid-centres"])
def test_a_straight_spectrum_is_kept_exactly_up_to_the_data_edges(src, dst):
    """The symmetric cut: a band near the end of the data is not pulled inwards (a one-sided cut
    moved the 720 nm band to 716.9 nm and the 50 nm bands' ends to 433.9 / 706.1 nm)."""
    assert resolved_bands(src, dst).all()
    out = resample_spectra(0.2 + 3e-3 * src.centers_nm, src, dst)
    np.testing.assert_allclose(out, 0.2 + 3e-3 * dst.centers_nm, rtol=1e-12)


def test_a_smooth_spectrum_on_1nm_gives_nearly_the_point_samples():
    src = Bands.uniform(400.0, 740.0, 1.0)
    lam = src.centers_nm
    spectrum = 1.0 + 0.5 * np.sin(2 * np.pi * (lam - 400.0) / 200.0) + 1e-3 * (lam - 400.0)
    out = resample_cube(np.broadcast_to(spectrum[:, None, None], (len(src), 2, 2)), src, PAPER)[:, 0, 0]
    point = np.interp(PAPER.centers_nm, lam, spectrum)
    np.testing.assert_allclose(out, point, atol=5e-3)  # a 200 nm period loses < 1 % of its amplitude


@pytest.mark.parametrize("dst", [PAPER, Bands.uniform(405.0, 695.0, 10.0), Bands.uniform(420.0, 700.0, 5.0),
                                 Bands.from_centers([403.0, 455.5, 512.25, 699.9], 10.0)],
                         ids=["paper", "shifted", "5nm-bands", "irregular"])
def test_a_10nm_source_is_interpolated_bit_for_bit_as_before(dst):
    src = Bands.uniform(400.0, 720.0, 10.0)
    cube = np.random.default_rng(1).random((len(src), 3, 4)).astype(np.float32)
    out = resample_cube(cube, src, dst)
    # the code before: the interpolation matrix applied along the band axis in float64, then float32
    moved = np.moveaxis(cube.astype(np.float64), 0, -1) @ interpolation_matrix(src, dst).T
    before = np.ascontiguousarray(np.moveaxis(moved, -1, 0), dtype=np.float32)
    np.testing.assert_array_equal(out, before)
    ref = np.apply_along_axis(lambda s: np.interp(dst.centers_nm, src.centers_nm, s), 0, cube.astype(np.float64))
    np.testing.assert_allclose(out, ref, rtol=1e-6)


def test_a_10nm_grid_with_rounding_in_its_steps_is_interpolated():
    centres = np.array([float(f"{400.3 + 10 * k:.1f}") for k in range(33)])  # steps of 9.99999999999994 nm
    assert np.diff(centres).min() < 10.0
    src = Bands.from_centers(centres, 10.0)
    dst = Bands.uniform(420.0, 700.0, 10.0)
    v = np.random.default_rng(2).random(len(src))
    np.testing.assert_allclose(resample_spectra(v, src, dst), np.interp(dst.centers_nm, centres, v), rtol=1e-12)


def test_a_nonuniform_fine_source_is_not_pulled_to_its_dense_side():
    """Dense samples on one side of a band must not pull it: a straight line comes out at the band
    centre's value, where the Gaussian weights of the samples alone are biased to the dense side."""
    centres = np.concatenate([np.arange(500.0, 550.0, 0.5), np.arange(550.0, 601.0, 2.0)])
    src = Bands.from_centers(centres, 1.0)
    dst = Bands.from_centers([550.0], 10.0)
    out = float(resample_spectra(centres - 500.0, src, dst)[0])
    sigma = math.sqrt(10.0**2 - 1.0) / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    g = np.exp(-0.5 * ((centres - 550.0) / sigma) ** 2) * (np.abs(centres - 550.0) <= 3 * sigma)
    plain = (g / g.sum()) @ (centres - 500.0)
    assert abs(plain - 50.0) > 0.5  # the trap: sample weights biased towards the dense side
    assert out == pytest.approx(50.0, abs=1e-9)


def test_torch_resampling_uses_the_same_rule_and_stays_differentiable():
    src = Bands.uniform(400.0, 740.0, 1.0)
    x = torch.rand(2, len(src), 3, 3, dtype=torch.float64, requires_grad=True)
    out = conform_bands(x, src, PAPER, "batch", note=False)
    np.testing.assert_allclose(out.detach().numpy(), resample_spectra(x.detach().numpy(), src, PAPER, axis=1),
                               rtol=1e-12)
    out.sum().backward()
    torch.testing.assert_close(x.grad.sum(), torch.tensor(2 * 31 * 9.0, dtype=torch.float64))  # rows sum to 1


def test_the_resampling_note_says_which_rule(caplog):
    mixed = Bands.from_centers(np.arange(420.0, 721.0, 10.0), np.where(np.arange(31) < 10, 5.0, 10.0))
    with caplog.at_level(logging.INFO, logger="hsicam.data.cube"):
        conform_bands(np.ones((341, 2, 2), np.float32), Bands.uniform(400, 740, 1), PAPER, "fine.h5")
        conform_bands(np.ones((33, 2, 2), np.float32), Bands.uniform(400, 720, 10), Bands.uniform(405, 715, 10), "c.h5")
        conform_bands(np.ones((33, 2, 2), np.float32), Bands.uniform(400, 720, 10, fwhm_nm=7.0), mixed, "m.h5")
    fine, coarse, both = (r.getMessage() for r in caplog.records)
    assert fine.startswith("fine.h5: resampling 341 bands") and "over each band's FWHM" in fine
    assert coarse.startswith("c.h5: resampling 33 bands") and coarse.endswith("by band centre")
    assert both.startswith("m.h5: resampling 33 bands") and "over the FWHM of the 21 bands" in both
    assert both.endswith("by band centre for the others")


def test_the_generator_band_model_is_unchanged():
    """The synthetic generator's band model (the cache must not change): its weights on its 1 nm grid
    are the Gaussian of each band's FWHM, cut at 3 σ, normalised."""
    from hsicam.spectral import band_matrix, fine_grid

    for bands in (PAPER, Bands.uniform(420, 720, 50)):
        fine = fine_grid(bands)
        g = band_matrix(bands, fine)
        sigma = bands.fwhm_nm[:, None] / (2.0 * math.sqrt(2.0 * math.log(2.0)))
        d = fine[None, :] - bands.centers_nm[:, None]
        ref = np.exp(-0.5 * (d / sigma) ** 2) * (np.abs(d) <= 3.0 * sigma)
        np.testing.assert_allclose(g, ref / ref.sum(axis=1, keepdims=True), rtol=1e-13, atol=1e-16)
    # and the demo's cached dataset keeps its key (a change here regenerates every user's cache; generator
    # version 3 changed it on purpose: it was f7f34bfd803d for version 2)
    from hsicam.data.synthetic import cache_key

    assert cache_key(64, 256, 0, PAPER) == "0300b54261d7"


# ------------------------------------------------------------------------------------------------
# 3. `hsicam data show` takes data.npy_bands
# ------------------------------------------------------------------------------------------------
PNGS = ("contact_sheet.png", "mean_spectra.png", "spectral_gamut.png")


@pytest.fixture
def grids_read(monkeypatch):
    """The band grid of every cube ``data show`` reads (a spy on the preview's reader)."""
    import hsicam.data.preview as preview

    seen: list[tuple[str, Bands]] = []
    real = preview.read_cube

    def spy(path, **kwargs):
        cube, bands, meta = real(path, **kwargs)
        seen.append((Path(path).name, bands))
        return cube, bands, meta

    monkeypatch.setattr(preview, "read_cube", spy)
    return seen


def test_data_show_reads_npy_cubes_on_the_grid_of_data_npy_bands(tmp_path, grids_read):
    grid = Bands.uniform(520.0, 720.0, 10.0)  # 21 bands; without a grid they would be taken as 400-700 nm
    data = tmp_path / "data"
    data.mkdir()
    np.save(data / "scene.npy", np.random.default_rng(0).uniform(0.05, 1, (len(grid), 20, 20)).astype(np.float32))
    res = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "a"),
                             "--set", "data.npy_bands={start_nm: 520, stop_nm: 720, step_nm: 10}")
    assert_ok(res)
    assert {p.name for p in (tmp_path / "a").glob("*.png")} == set(PNGS)
    assert grids_read and all(name == "scene.npy" and b.matches(grid) for name, b in grids_read)
    # the dotted form of one key, as `--set data.npy_bands.start_nm=...` elsewhere
    grids_read.clear()
    res = run_cli_in_process("data", "show", str(data / "scene.npy"), "--out", str(tmp_path / "b"),
                             "--set", "data.npy_bands.start_nm=520")
    assert_ok(res)
    assert grids_read and all(b.matches(grid) for _, b in grids_read)
    # without it: the documented 400-700 nm assumption, as before
    grids_read.clear()
    assert_ok(run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "c")))
    assert grids_read and all(b.matches(Bands.uniform(400.0, 700.0, 15.0)) for _, b in grids_read)


def test_data_show_refuses_an_npy_grid_of_the_wrong_length_in_one_line(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    np.save(data / "scene.npy", np.ones((21, 20, 20), np.float32))
    res = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "o"),
                             "--set", "data.npy_bands={start_nm: 420, stop_nm: 720, step_nm: 10}")
    assert_clean_error(res, "scene.npy", "21 bands", "has 31")
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
    res = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "o"),
                             "--set", "data.npy_bands={start_nm: 700, stop_nm: 420, step_nm: 10}")
    assert_clean_error(res, "data.npy_bands.stop_nm")


def test_a_band_narrower_than_the_fine_grid_samples_its_centre():
    """0.3 nm bands centred between the 1 nm samples had no sample within ±3σ: 0/0 rows, NaN spectra, and the
    generator blamed the illuminants' range. Such a band is a point sample: linear interpolation at its centre."""
    from hsicam.spectral.bands import band_matrix

    fine = np.arange(400.0, 731.0, 1.0)
    bands = Bands(np.array([420.5, 430.6, 600.0]), np.array([0.3, 0.3, 10.0]))
    g = band_matrix(bands, fine)
    assert np.isfinite(g).all() and np.allclose(g.sum(axis=1), 1.0)
    f = np.sin(fine / 17.0) + fine / 300.0
    np.testing.assert_allclose((g @ f)[:2], np.interp([420.5, 430.6], fine, f), rtol=1e-12)
    wide = np.exp(-0.5 * ((fine - 600.0) / (10.0 / 2.3548200450309493)) ** 2)
    wide[np.abs(fine - 600.0) > 3 * 10.0 / 2.3548200450309493] = 0.0
    np.testing.assert_allclose(g[2], wide / wide.sum(), rtol=1e-12)  # a band wider than the grid: unchanged
    # the same in the first and the last interval of the grid (and of a short, non-uniform one)
    for grid in (fine, np.array([400.0, 401.0, 403.0, 404.0, 406.0, 408.0, 409.0, 410.0])):
        ends = Bands(np.array([400.5, grid[-1] - 0.6]), np.array([0.3, 0.3]))
        h = grid / 9.0 + np.cos(grid / 3.0)
        np.testing.assert_allclose(band_matrix(ends, grid) @ h, np.interp(ends.centers_nm, grid, h), rtol=1e-12)


@pytest.mark.parametrize("data, flagged", [
    (Bands.uniform(420, 720, 50), [c for c in range(420, 721, 10) if (c - 420) % 50]),  # 7 bands: 24 made up
    (Bands.uniform(420, 720, 20), [c for c in range(420, 721, 10) if (c - 420) % 20]),  # 20 nm apart > 1.5 × 10
    (Bands.uniform(415, 725, 10), []),  # the same step, shifted half a band: 10 nm gaps, not more than 15
    (Bands.uniform(400, 730, 1), []),  # finer: integrated, never interpolated across a gap
    (Bands.uniform(420, 720, 10), []),  # the camera's own
    (Bands.from_centers([420.0, 430.0, 700.0, 720.0]), [*range(440, 700, 10), 710]),  # a hole; 700-720 is 20 nm
])
def test_interpolated_bands_are_the_camera_bands_between_data_bands_wider_apart_than_1_5_fwhm(data, flagged):
    """interpolated_bands: the camera's bands whose resampled value is a linear interpolation across a gap they would
    resolve, listed here by hand for the 31-band paper grid (FWHM 10 nm)."""
    from hsicam.spectral import interpolated_bands

    cam = Bands.uniform(420, 720, 10)
    got = cam.centers_nm[interpolated_bands(data, cam)]
    np.testing.assert_array_equal(got, np.asarray(flagged, dtype=np.float64))
    assert not interpolated_bands(Bands.from_centers([550.0]), Bands.from_centers([550.0])).any()
    # outside the data's range: not between two of its bands (resampling refuses it), whatever the edge gap
    assert not interpolated_bands(Bands.from_centers([500.0, 600.0]), Bands.from_centers([400.0, 700.0])).any()


def test_the_band_model_constants_are_a_gaussian_s_half_maximum_and_its_three_sigma_cut():
    """FWHM_PER_SIGMA against the half-maximum found numerically (scipy's root finder on the unit Gaussian), and
    band_matrix's support: a 10 nm band's nonzero weights on a 0.01 nm grid end within one step of ±3σ."""
    from scipy.optimize import brentq

    from hsicam.spectral import BAND_REACH_SIGMA, FWHM_PER_SIGMA, band_matrix

    half = brentq(lambda x: math.exp(-0.5 * x * x) - 0.5, 0.0, 5.0, xtol=1e-14)
    assert FWHM_PER_SIGMA == pytest.approx(2.0 * half, rel=1e-12)
    assert BAND_REACH_SIGMA == 3.0
    fine = np.round(np.arange(530.0, 570.0 + 1e-9, 0.01), 2)
    g = band_matrix(Bands([550.0], [10.0]), fine)[0]
    support = fine[g > 0]
    three_sigma = 3.0 * 10.0 / (2.0 * half)  # 12.74 nm
    assert support.min() == pytest.approx(550.0 - three_sigma, abs=0.011)
    assert support.max() == pytest.approx(550.0 + three_sigma, abs=0.011)
