"""Property-based tests (hypothesis) of the fabrication exports on unusual inputs: 2-2^16 levels, heights up to
three times the top, 1-cell and odd apertures, cell sizes off the 1 nm grid, one band or many, non-uniform band
grids, CFA periods 1-4. Each invariant is checked against an independent reference: training's quantisation rule,
the file read back in its real format (TIFF, CSV, GDSII by polygon area). Moved from
engine/test_properties_pipeline.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from hsicam.export.cfa import fit_filter, read_transmission_csv, write_transmission_csv
from hsicam.export.doe import quantize_levels, read_height_csv, read_height_tiff, write_height_csv, write_height_tiff
from hsicam.optics.doe import quantize_heights
from hsicam.spectral import Bands
from property_settings import PIPELINE_FEW, PIPELINE_PROPS, one_torch_thread

pytestmark = one_torch_thread


# ------------------------------------------------------------------------------------------------
# DOE export: L-level quantisation and the files
# ------------------------------------------------------------------------------------------------
@PIPELINE_PROPS
@given(k=st.integers(1, 16), wrap=st.booleans(), top_nm=st.floats(1.0, 1e5), n=st.integers(1, 9),
       span=st.floats(0.0, 3.0), seed=st.integers(0, 999))
def test_quantized_levels_are_within_half_a_level_and_the_trainings_rule(k, wrap, top_nm, n, span, seed):
    """L = 2^k levels: index in [0, L), height index·top/L; within half a step of the height modulo top (wrap)
    or of the height clamped to [0, (L−1)·top/L]; the same indices as training's torch rule (float64)."""
    levels = 2**k
    top = top_nm * 1e-9
    h = np.random.default_rng(seed).random((n, n)) * span * top
    idx, hq = quantize_levels(h, levels, top, wrap)
    step = top / levels
    assert idx.min() >= 0 and idx.max() <= levels - 1
    np.testing.assert_allclose(hq, idx * step, rtol=0, atol=1e-12 * top)
    if wrap:
        err = np.mod(hq - h + top / 2, top) - top / 2
    else:
        err = hq - np.clip(h, 0, (levels - 1) * step)
    assert np.abs(err).max() <= step / 2 * (1 + 1e-9)
    torch_q = quantize_heights(torch.from_numpy(h), levels, top, wrap=wrap).numpy()
    np.testing.assert_allclose(torch_q, hq, rtol=0, atol=1e-9 * step)


@PIPELINE_PROPS
@given(k=st.integers(1, 16), top_nm=st.floats(1.0, 1e5), n=st.integers(1, 9), cell_um=st.floats(0.5, 200.0),
       seed=st.integers(0, 999))
def test_height_files_read_back(tmp_path_factory, k, top_nm, n, cell_um, seed):
    """The 16-bit TIFF reads back within half its scale of each height and every level as itself; the CSV reads
    back the float32 heights and aperture exactly, with each cell's centre."""
    import csv

    d = tmp_path_factory.mktemp("h")
    levels = 2**k
    rng = np.random.default_rng(seed)
    h = rng.random((n, n)) * top_nm * 1e-9
    idx, hq = quantize_levels(h, levels, top_nm * 1e-9, True)
    aperture = (rng.random((n, n)) > 0.3) * rng.random((n, n))
    h_nm, hq_nm = (h * 1e9).astype(np.float32), (hq * 1e9).astype(np.float32)
    scale = write_height_tiff(d / "h.tif", h_nm, cell_um, {})
    back, desc = read_height_tiff(d / "h.tif")
    assert desc["scale_nm_per_count"] == scale and desc["cell_size_um"] == cell_um
    assert np.abs(back - h_nm).max() <= scale / 2 * (1 + 1e-6)
    step = top_nm / levels
    write_height_tiff(d / "q.tif", hq_nm, cell_um, {}, step_nm=step)
    back_q, _ = read_height_tiff(d / "q.tif")
    np.testing.assert_array_equal(np.round(back_q / step).astype(np.int64), idx)
    write_height_csv(d / "q.csv", hq_nm, aperture, cell_um, idx)
    h_back, a_back = read_height_csv(d / "q.csv", n)
    inside = aperture > 0
    np.testing.assert_array_equal(h_back, np.where(inside, hq_nm, 0))
    np.testing.assert_array_equal(a_back, np.where(inside, aperture.astype(np.float32), 0))
    with open(d / "q.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == int(inside.sum())
    for rec in rows:
        i, j = int(rec["row"]), int(rec["col"])
        assert int(rec["level"]) == idx[i, j]
        assert np.float32(float(rec["x_um"])) == np.float32((j - (n - 1) / 2) * cell_um)
        assert np.float32(float(rec["y_um"])) == np.float32(-(i - (n - 1) / 2) * cell_um)


@PIPELINE_FEW
@given(k=st.integers(1, 4), n=st.integers(1, 12), cell_um=st.sampled_from([30.0, 7.0, 0.5, 12.3455, 1.0005, 250.0]),
       seed=st.integers(0, 999))
def test_gds_masks_cover_exactly_the_cells_of_each_bit(tmp_path_factory, k, n, cell_um, seed):
    """Within the grid, layer j + 1's polygons cover, by area and without overlap, exactly the cells whose etch count
    L − 1 − level has bit j set (the aperture's cells by their level, the others at level 0: every bit set), each
    cell (its square on the 1 nm grid) in or out whole; the frame beyond the grid is tested in test_export.py."""
    gdstk = pytest.importorskip("gdstk")
    from hsicam.export.gds import cell_edges_um, write_gds

    levels = 2**k
    rng = np.random.default_rng(seed)
    level = rng.integers(0, levels, (n, n))
    aperture = (rng.random((n, n)) > 0.2).astype(float)
    path = tmp_path_factory.mktemp("g") / "d.gds"
    write_gds(path, level, levels, cell_um, aperture, 10.0, n * cell_um / 2)
    cell = {c.name: c for c in gdstk.read_gds(str(path)).cells}["DOE"]
    edges = cell_edges_um(n, cell_um)
    for j in range(k):
        want = (((levels - 1 - np.where(aperture > 0, level, 0)) >> j) & 1).astype(bool)
        grid = gdstk.rectangle((edges[0], -edges[-1]), (edges[-1], -edges[0]))
        polys = gdstk.boolean([p for p in cell.polygons if p.layer == j + 1], grid, "and", precision=1e-4)
        assert math.isclose(sum(p.area() for p in polys), float(sum(
            (edges[b + 1] - edges[b]) * (edges[a + 1] - edges[a]) for a, b in zip(*np.nonzero(want)))),
            rel_tol=1e-9, abs_tol=1e-9)
        for i in range(n):
            for jj in range(n):  # each cell: inside its polygons by area (the union of the cell and the masks)
                sq = gdstk.rectangle((edges[jj], -edges[i + 1]), (edges[jj + 1], -edges[i]))
                common = gdstk.boolean(sq, polys, "and", precision=1e-4) if polys else []
                area = sum(p.area() for p in common)
                assert math.isclose(area, sq.area() if want[i, jj] else 0.0, abs_tol=1e-6 * sq.area()), (j, i, jj)


# ------------------------------------------------------------------------------------------------
# CFA export
# ------------------------------------------------------------------------------------------------
@PIPELINE_PROPS
@given(c=st.integers(1, 12), m=st.integers(1, 4), seed=st.integers(0, 999), uniform=st.booleans())
def test_transmission_table_reads_back_and_every_filter_is_fitted(tmp_path_factory, c, m, seed, uniform):
    """On any band grid (one band, non-uniform steps): the CSV reads back the float32 tile exactly (and its
    peak-normalised version has maximum 1 per filter); each filter gets a fit within its bounds."""
    rng = np.random.default_rng(seed)
    centres = 400 + (np.arange(c) * 25.0 if uniform else np.cumsum(rng.uniform(0.5, 60, c)))
    bands = Bands(centres, np.full(c, 10.0))
    tile = rng.random((c, m, m)).astype(np.float32)
    tile /= tile.sum(0, keepdims=True)
    d = tmp_path_factory.mktemp("cfa")
    write_transmission_csv(d / "t.csv", tile, bands)
    write_transmission_csv(d / "p.csv", tile, bands, peak_normalised=True)
    lam, vals, names = read_transmission_csv(d / "t.csv")
    np.testing.assert_allclose(lam, centres, rtol=1e-11)  # written with 12 significant digits (%.12g)
    np.testing.assert_array_equal(vals, tile.reshape(c, m * m))
    assert names == [f"r{i}c{j}" for i in range(m) for j in range(m)]
    _, peak, _ = read_transmission_csv(d / "p.csv")
    np.testing.assert_allclose(peak.max(0), 1.0, rtol=1e-6)
    for curve in vals.T:
        f = fit_filter(lam, curve)
        assert f["rms_error"] <= 1.0 and math.isfinite(f["rms_error"])
        assert all(centres[0] - 1e3 <= g["centre_nm"] <= centres[-1] + 1e3 and g["fwhm_nm"] > 0
                   for g in f["components"])


def test_cfa_export_of_a_one_band_camera(tiny_config, tmp_path):
    """A camera of one band (bands.start_nm = stop_nm) has a CFA of all ones: its export fitted the flat curve
    with a Gaussian whose width bounds were crossed (lower 4.2 > upper 0.85 nm: scipy's ValueError 'Each lower
    bound must be strictly less than each upper bound'); now the filter is fitted: as the model applies it, the
    band's own Gaussian response."""
    from hsicam.cameras import DOECamera
    from hsicam.export.cfa import export_cfa

    cam = DOECamera.from_config(tiny_config("bands.start_nm=550", "bands.stop_nm=550"))
    info = export_cfa(cam, tmp_path)
    lam, vals, _ = read_transmission_csv(tmp_path / "cfa_transmission.csv")
    np.testing.assert_array_equal(lam, [550.0])
    np.testing.assert_array_equal(vals, np.ones((1, cam.code_period**2), np.float32))
    assert info["filters"] == cam.code_period**2
    fwhm = float(cam.bands.fwhm_nm[0])  # the band's own (50 nm: the tiny config's step)
    for f in info["fits"]:  # the filter the model applies: the band's Gaussian response (cut at 3σ)
        main = max(f["components"], key=lambda c: c["amplitude"])
        assert main["centre_nm"] == pytest.approx(550.0, abs=0.05) and main["fwhm_nm"] == pytest.approx(fwhm, rel=0.03)
        assert f["rms_error"] < 5e-3
