"""Fabrication export: round trips of every file (GDSII via gdstk, CSV exact, TIFF to its scale),
independent references for quantisation, masks and filter fits, spec.json contents."""

from __future__ import annotations

import csv
import json
import math
import sys

import numpy as np
import pytest
import torch

from cli_helpers import assert_clean_error, run_cli_in_process
from fab_runs import fab_run  # noqa: F401 - shared fixture
from hsicam.errors import InputError
from hsicam.export.cfa import fit_filter
from hsicam.export.doe import phase_error, quantize_levels
from hsicam.export.gds import write_gds
from hsicam.optics.doe import height_2pi_m
from hsicam.optics.pupil import aperture_amplitude
from hsicam.spectral import Bands, get_material

gdstk = pytest.importorskip("gdstk")


def _read_csv(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _rasterise_gds(path, n: int, cell_um: float, layers: int) -> np.ndarray:
    """Etch count per cell from the GDS rectangles (independent of hsicam's reader): each layer's
    rectangles are turned back into cell index ranges from their bounding boxes."""
    lib = gdstk.read_gds(str(path))
    (cell,) = [c for c in lib.cells if c.name == "DOE"]
    etch = np.zeros((n, n), dtype=np.int64)
    c = (n - 1) / 2
    for poly in cell.polygons:
        if not 1 <= poly.layer <= layers:
            continue
        assert len(poly.points) == 4  # rectangles only
        (x0, y0), (x1, y1) = poly.bounding_box()
        j0, j1 = int(round(x0 / cell_um + c + 0.5)), int(round(x1 / cell_um + c + 0.5))
        i0, i1 = int(round(c - y1 / cell_um + 0.5)), int(round(c - y0 / cell_um + 0.5))
        etch[i0:i1, j0:j1] += 1 << (poly.layer - 1)
    return etch


def test_export_round_trip(fab_run, tmp_path):
    from hsicam.runs.folder import load_run

    out = tmp_path / "fab"
    res = run_cli_in_process("export-optics", "--run", str(fab_run), "--out", str(out), "--levels", "8")
    assert res.returncode == 0, res.stderr
    assert "doe_L8.gds" in res.stdout
    cfg, model = load_run(fab_run)
    n = model.camera.optics.doe.n_cells
    cell_um = cfg.camera.doe.cell_size_um
    # independent heights: the raw parameter (no wrap/clamp/quantisation configured), piston removed
    aperture = aperture_amplitude(n, cell_um * 1e-6, cfg.camera.aperture_radius_mm * 1e-3)
    inside = aperture > 0
    h = model.camera.optics.doe.height_m.detach().double().numpy()
    h_ref = np.where(inside, h - h[inside].min(), 0.0) * 1e9
    h_npy = np.load(out / "doe_height_nm.npy")
    assert h_npy.dtype == np.float32 and h_npy.shape == (n, n)
    np.testing.assert_allclose(h_npy, h_ref, atol=1e-3)
    np.testing.assert_array_equal(np.load(out / "doe_aperture.npy"), aperture.astype(np.float32))
    # L-level heights: round to h_2π/8 steps, wrap
    step = height_2pi_m(get_material("fused_silica"), 587.6) * 1e9 / 8
    level_ref = np.where(inside, np.mod(np.round(h_npy.astype(np.float64) / step), 8), 0).astype(int)
    level = np.load(out / "doe_level_L8.npy")
    np.testing.assert_array_equal(level, level_ref)
    hq = np.load(out / "doe_height_L8_nm.npy")
    np.testing.assert_allclose(hq, level_ref * step, rtol=1e-6)
    # GDSII read back with gdstk: etch count (L − 1 − level) per cell, and the layers' depths
    spec = json.loads((out / "spec.json").read_text())
    layers = spec["doe"]["quantized"]["gds"]["layers"]
    assert [la["etch_depth_nm"] for la in layers] == pytest.approx([step, 2 * step, 4 * step])
    etch = _rasterise_gds(out / "doe_L8.gds", n, cell_um, 3)
    np.testing.assert_array_equal(7 - etch, level)  # the surround too: level 0 (etched by every mask), as the files
    assert (etch[~inside] == 7).all() and (~inside).any()
    assert spec["doe"]["quantized"]["gds"]["surround"]["level"] == 0
    lib = gdstk.read_gds(str(out / "doe_L8.gds"))
    assert lib.unit == pytest.approx(1e-6)
    # CSVs read back exactly
    rows = _read_csv(out / "doe_height_nm.csv")
    assert len(rows) == int(inside.sum())
    for r in rows:
        i, j = int(r["row"]), int(r["col"])
        assert np.float32(float(r["height_nm"])) == h_npy[i, j]
        assert np.float32(float(r["aperture_fraction"])) == np.float32(aperture[i, j])
        assert float(r["x_um"]) == pytest.approx((j - (n - 1) / 2) * cell_um)
        assert float(r["y_um"]) == pytest.approx(-(i - (n - 1) / 2) * cell_um)
    for r in _read_csv(out / "doe_height_L8_nm.csv"):
        i, j = int(r["row"]), int(r["col"])
        assert np.float32(float(r["height_nm"])) == hq[i, j] and int(r["level"]) == level[i, j]
    tile = np.load(out / "cfa_tile.npy")
    with torch.no_grad():
        np.testing.assert_array_equal(tile, model.camera.cfa.tile().numpy())
    rows = _read_csv(out / "cfa_transmission.csv")
    assert [float(r["wavelength_nm"]) for r in rows] == [500.0, 550.0, 600.0]
    m = tile.shape[-1]
    for b, r in enumerate(rows):
        for i in range(m):
            for j in range(m):
                assert np.float32(float(r[f"r{i}c{j}"])) == tile[b, i, j]
    # the placement spec.json states: filter r{i}c{j} at the sensor image's pixels (row ≡ i, column ≡ j mod m),
    # checked on the camera's own measurement: a scene lit in band b only images κ_b's tile
    assert f"row mod {m} = i" in spec["cfa"]["placement"] and "pixel (0, 0)" in spec["cfa"]["placement"]
    hw = model.camera.min_scene_size()
    for b in range(tile.shape[0]):
        scene = torch.zeros(1, tile.shape[0], *hw)
        scene[0, b] = 1.0
        with torch.no_grad():
            y = model.camera.A(scene)[0, 0].numpy()
        ratio = y / np.tile(tile[b], (-(-y.shape[0] // m), -(-y.shape[1] // m)))[: y.shape[0], : y.shape[1]]
        assert ratio.std() < 1e-3 * ratio.mean(), b
    # 16-bit TIFF: the scale is in the description; values within half a count
    import tifffile

    with tifffile.TiffFile(out / "doe_height_nm.tif") as tf:
        page = tf.pages[0]
        desc = json.loads(page.description)
        data = page.asarray()
    assert data.dtype == np.uint16 and desc["unit"] == "nm"
    np.testing.assert_allclose(data * desc["scale_nm_per_count"], h_npy, atol=desc["scale_nm_per_count"] / 2 + 1e-4)
    assert page.tags["XResolution"].value[0] / page.tags["XResolution"].value[1] == pytest.approx(1e4 / cell_um)
    # spec.json
    assert spec["lens"]["focal_length_mm"] == pytest.approx(5.0)
    assert spec["aperture"]["radius_mm"] == pytest.approx(0.25)
    assert spec["doe"]["cell_size_um"] == pytest.approx(cell_um) and spec["doe"]["material"] == "fused_silica"
    assert spec["doe"]["design_wavelength_nm"] == 587.6 and spec["sensor"]["pixel_pitch_um"] == pytest.approx(10.0)
    assert spec["bands"]["centers_nm"] == [500.0, 550.0, 600.0]
    assert "tolerances" in spec and "trained_with" in spec["tolerances"]
    err0 = spec["doe"]["quantized"]["phase_error_design_wavelength_rad"]
    assert err0["max"] <= math.pi / 8 + 1e-6
    for name in ("doe.png", "cfa.png", "cfa_fit.png", "cfa_fit.csv", "doe_phase_error_L8.csv", "doe_height_L8_nm.tif"):
        assert (out / name).is_file(), name
    assert set(spec["files"]) == {p.name for p in out.iterdir()} - {".complete"}  # + the completion marker
    assert (out / ".complete").is_file()


def test_quantisation_and_phase_error_reference():
    top = 1000.0
    h = np.array([[0.0, 60.0, 130.0], [990.0, 500.0, 1240.0]])
    level, hq = quantize_levels(h, 8, top)
    np.testing.assert_array_equal(level, [[0, 0, 1], [0, 4, 2]])  # 990 rounds up to 8 → wraps to 0; 1240 → 10 → 2
    np.testing.assert_allclose(hq, level * 125.0)
    # phase at the design wavelength: k·h_2π = 2π, so the wrapped error is |k·(hq − h)| mod 2π ≤ π/8
    k0 = 2 * np.pi / top
    err = phase_error(h, hq, np.array([k0]), np.ones_like(h))
    d = np.angle(np.exp(1j * k0 * (hq - h)))
    assert err["max_rad"][0] == pytest.approx(np.abs(d).max())
    assert err["rms_rad"][0] == pytest.approx(np.sqrt(np.mean(d**2)))
    assert err["max_rad"][0] <= np.pi / 8 + 1e-12
    with pytest.raises(InputError):
        quantize_levels(h, 1, top)


def test_gds_masks_are_binary_weighted(tmp_path):
    from hsicam.export.gds import SURROUND_FRAME_CELLS

    level = np.arange(16).reshape(4, 4) % 8
    aperture = np.ones((4, 4))
    aperture[0, 0] = 0.0  # outside: level 0, etched by every mask (whatever level the array holds there)
    write_gds(tmp_path / "m.gds", level, 8, 30.0, aperture, 100.0, 60.0)
    lib = gdstk.read_gds(str(tmp_path / "m.gds"))
    (cell,) = lib.cells
    etch = np.where(aperture > 0, 7 - level, 7)
    frame_cells = (4 + 2 * SURROUND_FRAME_CELLS) ** 2 - 4**2  # the ring around the 4 × 4 grid, in cells
    for j in range(3):
        area = sum(p.area() for p in cell.polygons if p.layer == j + 1)
        assert area == pytest.approx((np.count_nonzero((etch >> j) & 1) + frame_cells) * 30.0**2)
    assert any(p.layer == 100 for p in cell.polygons)  # the aperture circle
    # identical designs give identical files (fixed timestamp)
    write_gds(tmp_path / "m2.gds", level, 8, 30.0, aperture, 100.0, 60.0)
    assert (tmp_path / "m.gds").read_bytes() == (tmp_path / "m2.gds").read_bytes()
    with pytest.raises(InputError, match="2\\^k"):
        write_gds(tmp_path / "x.gds", level, 6, 30.0, aperture, 100.0, 60.0)
    assert not (tmp_path / "x.gds").exists()


@pytest.mark.parametrize("cell_um", [30.0, 1.001, 0.333, 25.001, 2.5005])
def test_gds_rows_and_runs_share_their_edges_on_the_1nm_grid(tmp_path, cell_um, caplog):
    """Every rectangle's corners lie on the n + 1 cell edges of the 1 nm grid, so the rows of one mask
    tile the aperture with neither slivers nor overlaps (each rectangle rounded on its own left 1 nm
    gaps for a cell of an odd number of nm, whose edges fall on half nanometres)."""
    n = 21
    level = np.zeros((n, n), int)  # every cell etched by every mask: one rectangle per row and layer
    level[:, 10] = 7  # ... but the middle column unetched: two runs per row
    write_gds(tmp_path / "g.gds", level, 8, cell_um, np.ones((n, n)), 100.0, n * cell_um / 2)
    lib = gdstk.read_gds(str(tmp_path / "g.gds"))
    assert lib.unit == pytest.approx(1e-6) and lib.precision == pytest.approx(1e-9)
    layer1 = [p for p in lib.cells[0].polygons if p.layer == 1]
    grid_edge = n * cell_um / 2 + 1e-3  # the frame's 4 rectangles (level 0 around the grid) reach beyond it
    polys = [p for p in layer1 if np.abs(p.points).max() <= grid_edge]
    assert len(polys) == 2 * n and len(layer1) == 2 * n + 4
    nm = np.round(np.concatenate([p.points for p in polys]) * 1000).astype(np.int64)
    edges = np.round((np.arange(n + 1) - n / 2) * cell_um * 1000).astype(np.int64)  # independent of the writer
    assert set(nm[:, 0]) <= set(edges) and set(-nm[:, 1]) <= set(edges)
    area = sum(abs(p.area()) for p in polys) * 1e6  # nm²: rows abut exactly, so the areas add to the union's
    whole = (edges[-1] - edges[0]) * ((edges[-1] - edges[0]) - (edges[11] - edges[10]))
    assert area == pytest.approx(whole, rel=1e-12)
    odd = abs(cell_um * 1000 - round(cell_um * 1000)) > 1e-6
    assert any("not a whole number of nm" in r.getMessage() for r in caplog.records) == odd


def test_cfa_fit_recovers_gaussian_filters():
    lam = Bands.paper().centers_nm
    single = 0.05 + 0.8 * np.exp(-0.5 * ((lam - 553.0) / (62.0 / 2.3548200450309493)) ** 2)
    f = fit_filter(lam, single)
    assert f["n_gaussians"] == 1
    c = f["components"][0]
    assert c["centre_nm"] == pytest.approx(553.0, abs=0.2) and c["fwhm_nm"] == pytest.approx(62.0, abs=0.3)
    assert f["rms_error"] < 1e-4 and f["offset"] == pytest.approx(0.05 / single.max(), abs=1e-3)
    double = np.exp(-0.5 * ((lam - 470.0) / 15.0) ** 2) + 0.6 * np.exp(-0.5 * ((lam - 650.0) / 25.0) ** 2)
    f2 = fit_filter(lam, double)
    assert f2["n_gaussians"] == 2
    centres = [c["centre_nm"] for c in f2["components"]]
    assert centres == pytest.approx([470.0, 650.0], abs=0.5)
    assert f2["rms_error"] < 1e-3


def test_the_model_filter_is_the_cameras_response_to_monochromatic_light(tiny_config, tmp_path):
    """cfa_transmission_1nm_peak1.csv: each filter as the camera model applies it, continuous. The model weighs
    band values x_c, each the spectrum averaged over band c's Gaussian response (FWHM, cut at 3σ, on the 1 nm grid),
    so its sensor value for monochromatic light at λ is Σ_c κ_c x_c(λ): computed here from the Gaussians directly, at
    every nm of the file, for a camera of 31 bands (the band table alone cannot say where within a band the light
    passes: the shipped camera's filters hold most of their κ in one or two bands). The curve also integrates to
    Σ κ = 1 (the model's convention) before its scaling to a peak of 1, and a lamp line between two band centres
    gives the sensor value the camera model gives it."""
    from hsicam.cameras import DOECamera
    from hsicam.export.cfa import export_cfa, model_filter_curves

    cam = DOECamera.from_config(tiny_config("bands.step_nm=10"))
    with torch.no_grad():
        tile = cam.cfa.tile().double().numpy()  # (31, m, m), each filter summing to 1 over the bands
    c, m, _ = tile.shape
    kappa = tile.reshape(c, m * m)
    info = export_cfa(cam, tmp_path)
    rows = _read_csv(tmp_path / "cfa_transmission_1nm_peak1.csv")
    lam = np.array([float(r["wavelength_nm"]) for r in rows])
    table = np.array([[float(r[f"r{i}c{j}"]) for i in range(m) for j in range(m)] for r in rows])
    centres, fwhm = cam.bands.centers_nm, cam.bands.fwhm_nm
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    assert np.all(np.diff(lam) == 1.0) and lam[0] <= centres[0] - 3 * sigma[0] and lam[-1] >= centres[-1] + 3 * sigma[-1]

    def band_values(spectrum):  # x_c = Σ_λ w_c(λ) s(λ) / Σ_λ w_c(λ), w_c the band's Gaussian cut at 3σ, on lam
        w = np.exp(-0.5 * ((lam[None, :] - centres[:, None]) / sigma[:, None]) ** 2)
        w[np.abs(lam[None, :] - centres[:, None]) > 3 * sigma[:, None]] = 0.0
        return (w @ spectrum) / w.sum(axis=1)

    response = np.stack([kappa.T @ band_values(np.eye(lam.size)[k]) for k in range(lam.size)])  # (F, m·m)
    np.testing.assert_allclose(table, (response / response.max(axis=0)).astype(np.float32), rtol=0, atol=1e-6)
    grid, curves = model_filter_curves(tile, cam.bands)
    np.testing.assert_array_equal(grid, lam)
    np.testing.assert_allclose(curves, response, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(curves.sum(axis=0), kappa.sum(axis=0), rtol=1e-9)  # ∫ T dλ (1 nm steps) = Σ κ = 1
    line = np.exp(-0.5 * ((lam - 554.0) / 1.0) ** 2)  # a lamp line 2 nm wide between two band centres
    np.testing.assert_allclose(line @ curves, kappa.T @ band_values(line), rtol=1e-9)
    assert info["model_filter"].startswith("cfa_transmission_1nm_peak1.csv")
    # the blocking filters a camera built to the model needs, at the ends of T's grid (not "an IR-cut filter" for any
    # range: a near-infrared camera's would block its own band)
    assert f"long-pass filter at {lam[0]:g} nm and a short-pass at {lam[-1]:g} nm" in info["model_filter"]
    # cfa_fit.csv's Gaussians are fits of that filter, and their errors are measured against it on its 1 nm grid
    for k, r in enumerate(_read_csv(tmp_path / "cfa_fit.csv")):
        fit = float(r["offset"]) + sum(
            float(r[f"amplitude_{g}"]) * np.exp(-0.5 * ((lam - float(r[f"centre_{g}_nm"]))
                                                         / (float(r[f"fwhm_{g}_nm"]) / (2 * math.sqrt(2 * math.log(2))))) ** 2)
            for g in (1, 2) if r[f"amplitude_{g}"])
        err = fit - table[:, k]
        assert float(r["rms_error"]) == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-3, abs=1e-6)
        assert float(r["max_abs_error"]) == pytest.approx(float(np.abs(err).max()), rel=1e-3, abs=1e-6)
        assert float(r["peak_kappa"]) == pytest.approx(float(kappa[:, k].max()), rel=1e-5)
        # a term at its bound 0 is written 0, not the solver's denormal (4.94066e-324 on the shipped camera)
        assert all(float(v) == 0 or abs(float(v)) >= 1e-12 for v in (r["offset"], r["amplitude_1"], r["amplitude_2"]) if v)


def test_export_without_gdstk(fab_run, tmp_path, monkeypatch):
    from hsicam.export import export_optics

    monkeypatch.setitem(sys.modules, "gdstk", None)  # `import gdstk` now raises ImportError
    with pytest.raises(ImportError, match=r"hsicam\[fab\]"):
        write_gds(tmp_path / "x.gds", np.zeros((3, 3), int), 4, 30.0, np.ones((3, 3)), 100.0, 40.0)
    spec = export_optics(fab_run, tmp_path / "out", 4)
    assert spec["doe"]["quantized"]["gds"]["file"] is None
    assert "hsicam[fab]" in spec["doe"]["quantized"]["gds"]["skipped"]
    assert (tmp_path / "out" / "doe_height_L4_nm.npy").is_file()
    assert not list((tmp_path / "out").glob("*.gds")) and [p.name for p in (tmp_path / "out").glob(".*")] == [".complete"]


def test_export_cli_errors_and_non_binary_levels(fab_run, tmp_path):
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(tmp_path / "nope"), "--out", str(tmp_path / "o")), "no such run folder")
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(fab_run), "--out", str(tmp_path / "o"), "--levels", "1"), "levels")
    # the command line takes powers of 2 only (its help says so); the library also exports other counts
    for bad in ("3", "6"):
        assert_clean_error(run_cli_in_process("export-optics", "--run", str(fab_run), "--out", str(tmp_path / "o"), "--levels", bad),
                           "power of 2")
    assert not (tmp_path / "o").exists()
    from hsicam.export import export_optics

    spec = export_optics(fab_run, tmp_path / "six", 6)
    assert spec["doe"]["quantized"]["gds"]["file"] is None and "power of 2" in spec["doe"]["quantized"]["gds"]["skipped"]
    assert spec["doe"]["quantized"]["phase_error_design_wavelength_rad"]["max"] <= math.pi / 6 + 1e-6


def test_a_run_trained_with_more_than_256_levels_is_exported_with_its_levels(fab_run, tmp_path):
    """Training takes camera.doe.quantization_levels up to 2^16; the export used to refuse such a run
    ("--levels must be in 2..256", an option the user never passed). 512 levels: 16-bit level
    indices, 9 GDS masks, the quantised TIFF resolving every level."""
    import shutil

    from hsicam.config import MAX_HEIGHT_LEVELS
    from hsicam.export.doe import read_height_tiff
    from hsicam.runs.folder import load_run

    run = tmp_path / "run512"
    shutil.copytree(fab_run, run, ignore=shutil.ignore_patterns("checkpoints*"))
    text = (run / "config.yaml").read_text()
    assert text.count("quantization_levels: null") == 1
    (run / "config.yaml").write_text(text.replace("quantization_levels: null", "quantization_levels: 512"))
    out = tmp_path / "fab"
    res = run_cli_in_process("export-optics", "--run", str(run), "--out", str(out))  # the run's own levels
    assert res.returncode == 0, res.stderr
    assert "512 levels" in res.stdout and "doe_L512.gds" in res.stdout
    cfg, model = load_run(run)
    n, cell_um = model.camera.optics.doe.n_cells, cfg.camera.doe.cell_size_um
    inside = aperture_amplitude(n, cell_um * 1e-6, cfg.camera.aperture_radius_mm * 1e-3) > 0
    step = height_2pi_m(get_material("fused_silica"), 587.6) * 1e9 / 512
    h_npy = np.load(out / "doe_height_nm.npy").astype(np.float64)
    level_ref = np.where(inside, np.mod(np.round(h_npy / step), 512), 0).astype(int)
    level = np.load(out / "doe_level_L512.npy")
    assert level.dtype == np.uint16 and level.max() > 255  # the levels above 8 bits are kept
    np.testing.assert_array_equal(level, level_ref)
    etch = _rasterise_gds(out / "doe_L512.gds", n, cell_um, 9)
    np.testing.assert_array_equal(np.where(inside, 511 - etch, 0), level)
    tif, desc = read_height_tiff(out / "doe_height_L512_nm.tif")
    assert desc["levels"] == 512
    np.testing.assert_array_equal(np.where(inside, np.mod(np.round(tif / step), 512), 0), level)
    spec = json.loads((out / "spec.json").read_text())
    assert spec["doe"]["quantized"]["levels"] == 512 and len(spec["doe"]["quantized"]["gds"]["layers"]) == 9
    # --levels takes the same range as the config; beyond it the refusal names the option and the value
    res = run_cli_in_process("export-optics", "--run", str(fab_run), "--out", str(tmp_path / "o"), "--levels", str(2 * MAX_HEIGHT_LEVELS))
    assert_clean_error(res, f"--levels: must be a power of 2 in 2..{MAX_HEIGHT_LEVELS}", f"got {2 * MAX_HEIGHT_LEVELS}")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value,shown", [("3", "3"), ("1", "1"), ("0", "0"), ("-8", "-8"), ("131072", "131072"),
                                         ("4.0", "'4.0'"), ("eight", "'eight'")])
def test_export_levels_that_it_cannot_export_are_a_usage_error_before_any_work(tmp_path, capsys, monkeypatch, value,
                                                                                shown):
    """``export-optics --levels 3`` passed the parser (``type=int``) and was refused by the command after it had
    prepared its output folder (and the rule, a power of 2 in 2..2^16, was written out again there); now the option's
    type refuses it as a usage error of the option, before any work."""
    import hsicam.cli
    from hsicam.cli import main
    from hsicam.config import MAX_HEIGHT_LEVELS

    def no_work(*a, **k):
        raise AssertionError("export-optics started its work before --levels was checked")

    monkeypatch.setattr(hsicam.cli, "prepare_output", no_work)
    out = tmp_path / "o"
    with pytest.raises(SystemExit) as exc:
        main(["export-optics", "--run", "pretrained:standard", "--out", str(out), f"--levels={value}"])
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"hsicam: error: argument --levels: must be a power of 2 in 2..{MAX_HEIGHT_LEVELS} (binary-weighted "
        f"lithography), got {shown}")
    assert not out.exists()


def test_the_level_counts_export_optics_takes_are_those_tolerance_sweeps():
    """One rule of the level counts (hsicam.config.levels_problem): export-optics
    --levels, tolerance --levels and the tolerance study's check take exactly the powers of 2 in 2..2^16."""
    import argparse

    from hsicam.cli.args import levels_arg, levels_list_arg
    from hsicam.config import LEVELS_RANGE, MAX_HEIGHT_LEVELS, levels_problem
    from hsicam.engine.tolerance import check_levels

    powers = {2**k for k in range(1, 17)}
    assert max(powers) == MAX_HEIGHT_LEVELS and LEVELS_RANGE == (2, MAX_HEIGHT_LEVELS)
    values = {*range(-3, 1100), *(p + d for p in powers for d in (-1, 0, 1)), 2**17, 3 * 2**15}

    def takes(check, v) -> bool:
        try:
            check(v)
        except (argparse.ArgumentTypeError, InputError):
            return False
        return True

    for name, check in (("export-optics --levels", lambda v: levels_arg(str(v))),
                        ("tolerance --levels", lambda v: levels_list_arg(f"2,{v}")), ("check_levels", check_levels)):
        assert {v for v in values if takes(check, v)} == powers, name
    assert {v for v in values if levels_problem(v) is None} == powers


def test_the_quantised_tiff_resolves_every_level_up_to_2_16(tiny_config, tmp_path):
    """With 2^16 levels no nice nm-per-count scale resolves the level step within 16 bits: the
    quantised TIFF then counts in steps (count = level index), so it reads back level for level."""
    from hsicam.export.doe import export_doe, nice_scale, read_height_tiff, tiff_scale

    assert tiff_scale(1000.0, 100.0) == nice_scale(1000.0)  # a few levels: the nice scale, as before
    assert tiff_scale(1000.0, 1000.0 / 65536) == 1000.0 / 65536
    cam = _doe_camera(tiny_config, "camera.doe.quantization_levels=65536")
    out = tmp_path / "fab"
    out.mkdir()
    facts = export_doe(cam, out, 65536, cam.bands.centers_nm)
    level = np.load(out / "doe_level_L65536.npy")
    assert level.dtype == np.uint16
    tif, desc = read_height_tiff(out / "doe_height_L65536_nm.tif")
    step = facts["quantized"]["step_nm"]
    assert desc["scale_nm_per_count"] == pytest.approx(step)
    np.testing.assert_array_equal(np.round(tif / step).astype(np.int64), level.astype(np.int64))
    assert len(facts["quantized"]["gds"]["layers"]) == 16


def test_spec_names_the_run_by_its_label(fab_run, tmp_path, monkeypatch):
    """spec.json's run is run_label's, as every other output's: a run folder given relative to the
    working folder is named by its absolute path (it was recorded as typed, meaningless elsewhere)."""
    from hsicam.export import export_optics
    from hsicam.runs.pretrained import run_label

    monkeypatch.chdir(fab_run.parent)
    spec = export_optics(fab_run.name, tmp_path / "o", 4)
    assert spec["run"] == run_label(fab_run) == str(fab_run.resolve())


def test_export_cites_only_a_tolerance_study_of_this_run(fab_run, tmp_path):
    """tolerance.json records the studied run (folder, weights file and its sha256, as the pretrained
    card hashes it); export-optics refuses any other JSON and a study of another run, and cites a
    study written before the run was recorded with a warning that it cannot be checked."""
    import shutil

    from hsicam.runs.checkpoint import root_weights_path, save_weights
    from hsicam.io import file_sha256
    from hsicam.runs.folder import load_run

    tol = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(tol), "--max-scenes", "1", "--draws", "1",
                  "--sigma-height-nm", "0", "--levels", "8", "--shift-cells", "0", "--sensor-distance-um", "0")
    assert res.returncode == 0, res.stderr
    study = json.loads((tol / "tolerance.json").read_text())
    assert study["run"] == {"path": str(fab_run.resolve()), "weights": "model.safetensors",
                            "weights_sha256": file_sha256(root_weights_path(fab_run))}

    def export(run, tolerance, name):
        return run_cli_in_process("export-optics", "--run", str(run), "--out", str(tmp_path / name), "--tolerance", str(tolerance))

    res = export(fab_run, tol, "ok")
    assert res.returncode == 0, res.stderr
    studied = json.loads((tmp_path / "ok" / "spec.json").read_text())["tolerances"]["studied"]
    assert studied["run_checked"] is True and studied["run"] == study["run"]
    assert studied["nominal_psnr_db"] == pytest.approx(study["nominal"]["psnr"])
    # an evaluate results.json is JSON but no tolerance study
    results = tmp_path / "results.json"
    results.write_text(json.dumps({"method": "doe-rdn", "scenes": [{"name": "s", "psnr": 30.0}], "mean": {"psnr": 30.0}}))
    assert_clean_error(export(fab_run, results, "r"), "results.json: not an hsicam tolerance study",
                       "no format, expected 'hsicam-tolerance-1'")
    broken = tmp_path / "broken" / "tolerance.json"
    broken.parent.mkdir()
    broken.write_text(json.dumps({**study, "nominal": {"psnr": None}}))
    assert_clean_error(export(fab_run, broken.parent, "b"), "no finite nominal PSNR")
    # the same camera with other weights: another run
    other = tmp_path / "other"
    shutil.copytree(fab_run, other, ignore=shutil.ignore_patterns("checkpoints*"))
    cfg, model = load_run(other)
    with torch.no_grad():
        model.camera.optics.doe.height_m.add_(1e-9)
    save_weights(other / "model.safetensors", model, model.bands)
    assert_clean_error(export(other, tol, "x"), "a tolerance study of another run", str(fab_run.resolve()),
                       f"weights sha256 {study['run']['weights_sha256'][:12]}", "hsicam tolerance --run")
    assert not any((tmp_path / n).exists() for n in ("r", "b", "x"))
    # the same stale study found by itself in RUN/tolerance (the run changed after its study): the export
    # goes on, does not cite it, and says why (it was refused, with no option to leave it out)
    shutil.copytree(tol, other / "tolerance")
    res = run_cli_in_process("export-optics", "--run", str(other), "--out", str(tmp_path / "stale"))
    assert res.returncode == 0, res.stderr
    assert "not cited" in res.stderr and "a tolerance study of another run" in res.stderr
    tolerances = json.loads((tmp_path / "stale" / "spec.json").read_text())["tolerances"]
    assert tolerances["studied"] is None and "not cited" in tolerances["note"]
    shutil.rmtree(other / "tolerance")
    # a study written before the run was recorded: cited, with a warning that it cannot be checked
    old = tmp_path / "old" / "tolerance.json"
    old.parent.mkdir()
    old.write_text(json.dumps({k: v for k, v in study.items() if k != "run"}))
    res = run_cli_in_process("export-optics", "--run", str(other), "--out", str(tmp_path / "old_out"), "--tolerance", str(old))
    assert res.returncode == 0, res.stderr
    assert "does not record which run it studied" in res.stderr and "cannot check" in res.stderr
    studied = json.loads((tmp_path / "old_out" / "spec.json").read_text())["tolerances"]["studied"]
    assert studied["run_checked"] is False and studied["nominal_psnr_db"] == pytest.approx(study["nominal"]["psnr"])


# ------------------------------------------------------------------------------------------------
# Read-back helpers (for users who check the files a supplier will get): round trips
# ------------------------------------------------------------------------------------------------
def test_transmission_csv_round_trip(tmp_path):
    from hsicam.export.cfa import filter_names, read_transmission_csv, write_transmission_csv

    rng = np.random.default_rng(1)
    tile = rng.random((5, 2, 3)).astype(np.float32) * np.float32(0.3)
    bands = Bands.from_centers([450.0, 487.5, 530.0, 601.25, 700.0])
    write_transmission_csv(tmp_path / "t.csv", tile, bands)
    lam, vals, names = read_transmission_csv(tmp_path / "t.csv")
    np.testing.assert_array_equal(lam, bands.centers_nm)
    np.testing.assert_array_equal(vals, tile.reshape(5, 6))  # exact float32
    assert names == filter_names(2, 3) == ["r0c0", "r0c1", "r0c2", "r1c0", "r1c1", "r1c2"]
    write_transmission_csv(tmp_path / "p.csv", tile, bands, peak_normalised=True)
    _, peak, _ = read_transmission_csv(tmp_path / "p.csv")
    np.testing.assert_allclose(peak.max(axis=0), 1.0, rtol=1e-6)
    np.testing.assert_allclose(peak, tile.reshape(5, 6) / tile.reshape(5, 6).max(axis=0), rtol=1e-6)


def test_height_tiff_round_trip(tmp_path):
    from hsicam.export.doe import read_height_tiff, write_height_tiff

    rng = np.random.default_rng(2)
    h = rng.random((9, 9)) * 1234.5
    scale = write_height_tiff(tmp_path / "h.tif", h, 30.0, {"levels": None})
    back, desc = read_height_tiff(tmp_path / "h.tif")
    assert desc["scale_nm_per_count"] == scale == 0.02 and desc["cell_size_um"] == 30.0 and desc["levels"] is None
    assert back.shape == h.shape and np.abs(back - h).max() <= scale / 2 + 1e-9


def test_height_csv_round_trip(tmp_path):
    from hsicam.export.doe import read_height_csv, write_height_csv

    n = 7
    rng = np.random.default_rng(3)
    h = (rng.random((n, n)) * 900).astype(np.float32)
    aperture = aperture_amplitude(n, 30e-6, 90e-6)
    write_height_csv(tmp_path / "h.csv", h, aperture, 30.0, level=np.arange(n * n).reshape(n, n) % 4)
    back, ap = read_height_csv(tmp_path / "h.csv", n)
    inside = aperture > 0
    assert 0 < inside.sum() < n * n
    np.testing.assert_array_equal(back, np.where(inside, h, 0))  # exact inside, 0 outside
    np.testing.assert_array_equal(ap, aperture.astype(np.float32))


def test_gds_levels_round_trip(tmp_path):
    from hsicam.export.gds import read_gds_levels

    n, levels = 12, 8
    rng = np.random.default_rng(4)
    level = rng.integers(0, levels, (n, n))
    aperture = aperture_amplitude(n, 30e-6, 170e-6)
    inside = aperture > 0
    level[~inside] = levels - 1  # what the array holds outside does not matter: the surround is level 0
    write_gds(tmp_path / "d.gds", level, levels, 30.0, aperture, 150.0, 170.0)
    back = read_gds_levels(tmp_path / "d.gds", n, 30.0, levels)
    np.testing.assert_array_equal(back, np.where(inside, level, 0))
    lib = gdstk.Library()
    lib.new_cell("OTHER")
    lib.write_gds(str(tmp_path / "other.gds"))
    with pytest.raises(InputError, match="no 'DOE' cell"):
        read_gds_levels(tmp_path / "other.gds", n, 30.0, levels)


def test_gds_surround_is_level_0_as_the_height_files_and_the_shift_study_assume(tmp_path):
    """Outside the aperture the height files hold 0 and the tolerance study's shifted relief reads height 0: the GDS
    etches the grid's outer cells and a frame of SURROUND_FRAME_CELLS cells around the grid by every mask (level 0),
    so a DOE shifted against its stop by up to the frame shows the fabricated element the study scored. Points are
    tested against the written polygons, cell by cell, beyond the grid's edge."""
    from hsicam.export.gds import SURROUND_FRAME_CELLS

    n, levels, cell_um = 9, 4, 30.0
    level = np.full((n, n), levels - 1)  # the aperture's cells unetched (top level)
    aperture = aperture_amplitude(n, cell_um * 1e-6, 100e-6)
    write_gds(tmp_path / "s.gds", level, levels, cell_um, aperture, 150.0, 100.0)
    (cell,) = gdstk.read_gds(str(tmp_path / "s.gds")).cells
    # cell centres from 3 cells beyond the frame on one side to the other: along the middle row, and along the
    # diagonal (through the frame's corners)
    m = n // 2 + SURROUND_FRAME_CELLS + 3
    k = np.arange(-m, m + 1)
    r = np.abs(k)
    in_grid = r <= n // 2
    in_frame = (r > n // 2) & (r <= n // 2 + SURROUND_FRAME_CELLS)
    idx = n // 2 + np.clip(k, -(n // 2), n // 2)  # the grid cell of each point (meaningful in the grid only)
    lines = {"row": (np.stack([k * cell_um, 0 * k], axis=1), aperture[n // 2, idx] > 0),
             "diagonal": (np.stack([k * cell_um, -k * cell_um], axis=1), aperture[idx, idx] > 0)}
    for j in range(2):
        polys = [p for p in cell.polygons if p.layer == j + 1]
        for pts, lit in lines.values():
            hit = np.asarray(gdstk.inside(pts, polys), dtype=bool)
            inside_ap = in_grid & lit
            assert inside_ap.any() and (in_grid & ~lit).any()
            np.testing.assert_array_equal(hit[inside_ap], False)  # top level: no mask opens it
            np.testing.assert_array_equal(hit[in_grid & ~inside_ap], True)  # the grid's surround: every mask
            np.testing.assert_array_equal(hit[in_frame], True)  # the frame: every mask
            np.testing.assert_array_equal(hit[r > n // 2 + SURROUND_FRAME_CELLS], False)  # beyond: untouched


def _doe_camera(tiny_config, *overrides):
    from hsicam.cameras import DOECamera

    return DOECamera.from_config(tiny_config(*overrides))


def test_an_element_trained_with_a_clamp_range_and_l_levels_is_exported_as_trained(tiny_config, tmp_path):
    """max_height 1000 nm, 4 levels, no wrap: the DOE simulates heights k·250 nm, k = 0..3 (its
    level_grid); the export used to re-quantise them onto k·h_2π/4 = k·320 nm, wrapped, and
    fabricate another element (1163 of 1329 cells changed, PSFs 35–42 % L1 apart: probe 29 F1)."""
    from hsicam.export.doe import design_heights, export_doe

    cam = _doe_camera(tiny_config, "camera.doe.max_height_nm=1000", "camera.doe.quantization_levels=4",
                      "camera.doe.wrap=false")
    doe = cam.optics.doe
    assert doe.level_grid() == (pytest.approx(1e-6), False)
    with torch.no_grad():
        trained_nm = doe.heights().double().numpy() * 1e9
    assert set(np.unique(np.round(trained_nm, 3))) <= {0.0, 250.0, 500.0, 750.0}  # the simulated element
    out = tmp_path / "fab"
    out.mkdir()
    facts = export_doe(cam, out, 4, cam.bands.centers_nm)
    h_m, aperture, piston = design_heights(cam)
    inside = aperture > 0
    exported = np.load(out / "doe_height_L4_nm.npy").astype(np.float64)
    np.testing.assert_allclose(exported[inside], (trained_nm - piston * 1e9)[inside], atol=1e-3)  # cell for cell
    levels = np.load(out / "doe_level_L4.npy")
    np.testing.assert_array_equal(levels[inside], np.round(exported[inside] / 250.0))
    q = facts["quantized"]
    assert q["step_nm"] == pytest.approx(250.0) and "clamp range" in q["grid"]
    assert q["phase_error_design_wavelength_rad"]["max"] < 1e-5 and q["phase_error_design_wavelength_rad"]["bound_pi_over_L"] is None
    assert facts["height_2pi_nm"] == pytest.approx(doe.h2pi_m * 1e9)
    # the phase-level default keeps its grid: a wrapped 4-level element comes out unchanged too
    cam = _doe_camera(tiny_config, "camera.doe.quantization_levels=4")
    with torch.no_grad():
        trained_nm = cam.optics.doe.heights().double().numpy() * 1e9
    out2 = tmp_path / "fab2"
    out2.mkdir()
    export_doe(cam, out2, 4, cam.bands.centers_nm)
    h_m, aperture, piston = design_heights(cam)
    inside = aperture > 0
    np.testing.assert_allclose(np.load(out2 / "doe_height_L4_nm.npy")[inside], (trained_nm - piston * 1e9)[inside],
                               atol=1e-3)


def test_heights_above_h2pi_are_warned_about_when_the_export_wraps_them(tiny_config, tmp_path, caplog):
    import logging

    from hsicam.export.doe import export_doe

    cam = _doe_camera(tiny_config, "camera.doe.init_range_nm=2000")  # a multi-order start, not quantised
    out = tmp_path / "fab"
    out.mkdir()
    with caplog.at_level(logging.WARNING, logger="hsicam.export.doe"):
        export_doe(cam, out, 8, cam.bands.centers_nm)
    assert any("above h_2π" in r.getMessage() and "wraps them" in r.getMessage() for r in caplog.records), caplog.text
    caplog.clear()
    cam = _doe_camera(tiny_config)  # heights within [0, h_2π]: no warning
    with caplog.at_level(logging.WARNING, logger="hsicam.export.doe"):
        export_doe(cam, tmp_path, 8, cam.bands.centers_nm)
    assert not [r for r in caplog.records if "above h_2π" in r.getMessage()], caplog.text
