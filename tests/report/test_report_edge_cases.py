"""Mutation guards of the reconstruction and tolerance reports (report/reconstruction.py, report/tolerance.py), probe
mut8b, moved here from the models floor's camera-system file: each test kills a hand-made mutant that the rest of the
suite let through, asserting against a figure's plotted data or text read back from its axes and values worked out
by hand.

Then those of the report pages and the camera files and figures (report/html.py, report/camera.py), session 56,
mut5c, moved here from engine/test_experiments_and_demo_edge_cases.py: against a page's table read back, a file read
back, brute-force sums over a PSF's pixels, the exact line a user sees.
"""

from __future__ import annotations

import html
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hsicam.errors import InputError
from hsicam.spectral import Bands


# ------------------------------------------------------------------------------------------------
# report/reconstruction.py, report/tolerance.py
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("peak", [0.05, 0.0099, 0.005, 0.00125, 3e-7, 0.5, 2.0])
def test_spectra_exponent_divides_only_spectra_peaking_below_one_percent(peak):
    """Spectra peaking below 0.01 are divided by 10^e so that their peak lies in [1, 10) (e = ⌊log10 peak⌋); a peak
    of 0.01 or more keeps e = 0 (the ticks of 0.05 are short already)."""
    from hsicam.report.reconstruction import spectra_exponent

    spectra = [np.array([0.0, -peak / 3, peak / 2]), np.array([peak, 0.0])]
    e = spectra_exponent(spectra)
    if peak >= 0.01:
        assert e == 0
    else:
        assert 1 <= peak / 10.0**e < 10


def _scene_result(name, seed, c=3, h=8, w=12):
    g = np.random.default_rng(seed)
    truth = g.random((c, h, w))
    return SimpleNamespace(name=name, truth=truth, estimate=truth + 0.1 * g.standard_normal((c, h, w)),
                           metrics={"psnr": 30.0, "ssim": 0.9})


def test_reconstruction_figure_plots_the_mean_error_and_the_spectra_at_its_marked_pixels(monkeypatch, tmp_path):
    """The figure's data, read back from its axes: the error map is mean_c |est − gt| (computed here), the spectra
    panel plots gt[:, y, x] and est[:, y, x] at (h/4, w/4), (h/2, w/2), (3h/4, 3w/4) of a non-square scene, and only
    ``max_rows`` rows are drawn, the title naming the total."""
    import hsicam.report.reconstruction as rec

    figs = []
    monkeypatch.setattr(rec, "save_figure", lambda fig, path: figs.append(fig))
    bands = Bands.uniform(500, 600, 50)
    results = [_scene_result(f"s{i}", i) for i in range(3)]
    rec.plot_reconstructions(results, bands, tmp_path / "r.png", max_rows=2)
    (fig,) = figs
    rows = np.array(fig.axes[: 8]).reshape(2, 4)  # the 2 × 4 grid first, then the colour bars
    assert fig._suptitle.get_text().startswith("the first 2 of 3 scenes")
    for r, row in zip(results, rows):
        gt, est = r.truth, r.estimate
        np.testing.assert_allclose(row[2].images[0].get_array(), np.abs(est - gt).mean(axis=0), rtol=1e-12)
        h, w = gt.shape[1:]
        lines = row[3].get_lines()
        pts = [(h // 4, w // 4), (h // 2, w // 2), (3 * h // 4, 3 * w // 4)]
        assert len(lines) == 6
        for k, (y, x) in enumerate(pts):
            np.testing.assert_allclose(lines[2 * k].get_ydata(), gt[:, y, x])
            np.testing.assert_allclose(lines[2 * k + 1].get_ydata(), est[:, y, x])
            np.testing.assert_allclose(lines[2 * k].get_xdata(), bands.centers_nm)


def test_training_curves_plot_the_validations_during_training_not_the_final_record(monkeypatch, tmp_path):
    """metrics.jsonl read back: the loss panel plots every train_loss, the validation panel the val_psnr / val_ssim
    of the records without ``final`` (the final record repeats the best step's scores, not a point of the curve)."""
    import hsicam.report.reconstruction as rec

    recs = [{"step": 1, "train_loss": 0.5}, {"step": 2, "train_loss": 0.25},
            {"step": 2, "val_psnr": 20.0, "val_ssim": 0.5},
            {"step": 4, "train_loss": 0.125}, {"step": 4, "val_psnr": 22.0, "val_ssim": 0.6},
            {"step": 4, "val_psnr": 99.0, "val_ssim": 0.99, "final": True}]
    path = tmp_path / "metrics.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    figs = []
    monkeypatch.setattr(rec, "save_figure", lambda fig, p: figs.append(fig))
    rec.plot_training_curves(path, tmp_path / "c.png")
    a0, a1, b = figs[0].axes
    np.testing.assert_array_equal(a0.get_lines()[0].get_xdata(), [1, 2, 4])
    np.testing.assert_array_equal(a0.get_lines()[0].get_ydata(), [0.5, 0.25, 0.125])
    np.testing.assert_array_equal(a1.get_lines()[0].get_xdata(), [2, 4])
    np.testing.assert_array_equal(a1.get_lines()[0].get_ydata(), [20.0, 22.0])
    np.testing.assert_array_equal(b.get_lines()[0].get_ydata(), [0.5, 0.6])


def test_levels_text_of_a_study_that_does_not_record_bracketing_states_the_requirement():
    """A tolerance.json written before ``levels_bracketed`` was recorded: its levels within 1 dB are the requirement
    (as then); the key only ever withholds it when recorded False."""
    from hsicam.report.tolerance import levels_text

    assert levels_text({"sweeps": {"levels": {}}, "summary": {"min_levels_within_1db": 8}}) == "levels ≥ 8"
    assert levels_text({"sweeps": {"levels": {}}, "summary": {"min_levels_within_1db": 8, "levels_bracketed": False}}) \
        == "levels: 8 within 1 dB, not bracketed"
    assert levels_text({"sweeps": {"sigma_height_nm": {}}, "summary": {"min_levels_within_1db": 8}}) == ""


def _sweep(values, psnr):
    return {"values": values, "psnr": psnr, "psnr_std": [0.0] * len(values)}


def _tolerance_figure(monkeypatch, tmp_path, result):
    import hsicam.io
    from hsicam.report.tolerance import plot_tolerance

    figs = []
    monkeypatch.setattr(hsicam.io, "save_figure", lambda fig, p: figs.append(fig))
    plot_tolerance(result, tmp_path / "t.png")
    return figs[0].axes


def _hline(ax, label):
    (line,) = [ln for ln in ax.get_lines() if ln.get_label() == label]
    return float(line.get_ydata()[0])


def test_tolerance_figure_draws_the_one_db_line_below_each_panels_reference(monkeypatch, tmp_path):
    """The −1 dB line lies 1 dB below the panel's reference: the nominal PSNR, or for the shift panel the no-shift
    reference model's (``shift_reference``), drawn with the nominal as a separate line."""
    result = {"metric": "PSNR, per band", "nominal": {"psnr": 30.0},
              "shift_reference": {"psnr": 31.5, "pupil_oversample": 3},
              "sweeps": {"sigma_height_nm": _sweep([0, 10], [30.0, 29.0]), "levels": _sweep([4, 8], [28.0, 29.9]),
                         "shift_x_cells": _sweep([0, 0.5], [31.5, 30.0]),
                         "sensor_distance_um": _sweep([0, 5], [30.0, 29.5])}}
    ax = _tolerance_figure(monkeypatch, tmp_path, result)
    for i in (0, 1, 3):
        assert _hline(ax[i], "−1 dB") == 29.0 and _hline(ax[i], "nominal") == 30.0
    assert _hline(ax[2], "−1 dB") == 30.5
    assert _hline(ax[2], "nominal (trained model)") == 30.0
    assert _hline(ax[2], "no shift, 3 samples/cell") == 31.5


def test_tolerance_figure_draws_a_diagonal_shift_at_its_distance(monkeypatch, tmp_path):
    """A diagonal shift of s cells per axis (tolerance.json's value, applied_cells [s, s]) moves the DOE s·√2 cells; it
    was drawn at s beside the x shifts on one "lateral shift" axis, √2 times more tolerant-looking than it is (session
    74's figure hunt)."""
    result = {"metric": "PSNR", "nominal": {"psnr": 30.0},
              "sweeps": {"shift_x_cells": _sweep([0, 1, 2], [30.0, 29.5, 28.0]),
                         "shift_diag_cells": _sweep([0, 1, 2], [30.0, 29.0, 27.0])}}
    ax = _tolerance_figure(monkeypatch, tmp_path, result)[2]
    curves = {c.get_label(): c.lines[0] for c in ax.containers}  # (errorbar containers: their data line first)
    x_line = curves["along x"]
    d_line = next(line for label, line in curves.items() if label.startswith("along the diagonal"))
    np.testing.assert_allclose(np.asarray(x_line.get_xdata(), dtype=float), [0, 1, 2])
    np.testing.assert_allclose(np.asarray(d_line.get_xdata(), dtype=float), [0, np.hypot(1, 1), np.hypot(2, 2)])
    assert "distance" in ax.get_xlabel()


def test_tolerance_figure_says_why_a_skipped_shift_sweep_was_not_studied(monkeypatch, tmp_path):
    """tolerance.json records a camera without a DOE under ``skipped`` by sweep family (``shift`` for both shift
    sweeps): the panel says "not studied:" and the reason, and plots nothing."""
    why = "the camera has no DOE"
    result = {"metric": "PSNR", "nominal": {"psnr": 30.0},
              "skipped": {"sigma_height_nm": why, "levels": why, "shift": why},
              "sweeps": {"sensor_distance_um": _sweep([0, 5], [30.0, 29.5])}}
    ax = _tolerance_figure(monkeypatch, tmp_path, result)
    for i in (0, 1, 2):
        assert [t.get_text() for t in ax[i].texts] == ["not studied:\n" + why]
        assert len(ax[i].get_lines()) == 0
    assert len(ax[3].texts) == 0 and _hline(ax[3], "−1 dB") == 29.0


# ------------------------------------------------------------------------------------------------
# report: pages read back
# ------------------------------------------------------------------------------------------------
MEAN = {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}


def _complete_folder(tmp_path, name: str, data: dict):
    from hsicam.io import mark_complete

    d = tmp_path / "ev"
    d.mkdir()
    (d / name).write_text(json.dumps(data))
    mark_complete(d, {"command": "test"})
    return d


def _cells(page: str) -> list[list[str]]:
    """The table rows of a report page, as lists of cell texts (an independent read of the HTML)."""
    import re

    return [re.findall(r"<t[dh]>(.*?)</t[dh]>", row) for row in re.findall(r"<tr>(.*?)</tr>", page)]


def test_an_empty_band_list_is_a_corrupt_field(tmp_path):
    from hsicam.report.html import build_report

    d = _complete_folder(tmp_path, "results.json", {"method": "x", "scenes": [{"name": "a", **MEAN}], "mean": MEAN,
                                                     "conventions": {}, "bands_nm": []})
    with pytest.raises(InputError) as err:
        build_report(d)
    assert str(err.value) == f"{d / 'results.json'}: corrupt results.json ('bands_nm' is not a list of wavelengths in nm)"


def test_an_ablation_page_lists_missing_rows_apart_and_claims_no_cassi_rows(tmp_path):
    from hsicam.report.html import build_report

    d = _complete_folder(tmp_path, "experiment.json", {
        "experiment": "ablation", "scale": "tiny", "seeds": [0], "scenes": ["a"], "conventions": {},
        "region": "central 10x10 px", "rows": [{"method": "doe+cfa", **MEAN, "runtime_s": 0.5},
                                               {"method": "no-doe", "missing": True}]})
    page = build_report(d).read_text(encoding="utf-8")
    rows = _cells(page)
    assert rows == [["method", "PSNR (dB)", "SSIM", "SAM (°)", "runtime (s/scene)"],
                    ["doe+cfa", "30.00", "0.9000", "5.00", "0.500"]]
    assert "not available in this installation: no-doe" in page
    assert "scored area: the DOE cameras' central 10x10 px</p>" in page  # no CASSI row in an ablation


def test_the_references_of_a_demo_are_tabled_in_its_report(tmp_path):
    from hsicam.report.html import build_report

    d = _complete_folder(tmp_path, "results.json", {
        "method": "doe-learned", "scenes": [{"name": "a", **MEAN}], "mean": MEAN, "conventions": {},
        "references": [{"method": "CFA box demosaic (no network)", "mean": {"psnr": 25.125, "ssim": 0.5, "sam": 9.0}}]})
    rows = _cells(build_report(d).read_text(encoding="utf-8"))
    assert ["CFA box demosaic (no network)", "25.12", "0.5000", "9.00"] in rows


def test_a_run_path_no_longer_there_falls_back_to_the_run_label(tmp_path):
    from pathlib import Path

    from hsicam.report.html import _evaluated_run

    assert _evaluated_run({"run_path": str(tmp_path / "gone"), "run": "pretrained:x"}, tmp_path) == Path("pretrained:x")
    assert _evaluated_run({"run_path": str(tmp_path), "run": "pretrained:x"}, tmp_path) == tmp_path


def test_a_moved_demo_folders_report_draws_the_camera_of_the_run_beside_its_results(tmp_path, monkeypatch):
    """The demo's results.json names its run relative to where it ran (runs/demo/run) and by its absolute run_path: a
    demo folder copied or moved elsewhere lost every camera figure ("runs/demo/run: no such run folder") with the run
    beside results.json (session 74's figure hunt). The results folder's own run/ is read, its weights' hash checked."""
    import shutil

    from hsicam.report.html import build_report
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256
    from hsicam.runs.pretrained import resolve_run

    src = resolve_run("pretrained:standard")
    sha = file_sha256(root_weights_path(src))
    monkeypatch.chdir(tmp_path)
    # and a new demo's run at the old place, other weights: the scored one beside results.json is read (the review)
    from safetensors.torch import load_file, save_file

    new = shutil.copytree(src, tmp_path / "runs" / "demo" / "run")
    tensors = load_file(new / "model.safetensors")
    key = next(iter(tensors))
    tensors[key] = tensors[key] + 1e-3
    save_file(tensors, new / "model.safetensors")
    pages = {}
    for name, recorded in (("same", sha), ("other", "0" * 64)):
        (tmp_path / name).mkdir()
        d = _complete_folder(tmp_path / name, "results.json", {
            "method": "doe-learned", "run": "runs/demo/run", "run_path": "/nowhere/runs/demo/run",
            "weights_sha256": recorded, "scenes": [{"name": "a", **MEAN}], "mean": MEAN, "conventions": {}})
        shutil.copytree(src, d / "run")
        pages[name] = html.unescape(build_report(d).read_text(encoding="utf-8"))
    assert "<h2>Camera (runs/demo/run)</h2>" in pages["same"] and "unavailable" not in pages["same"]
    # no run with the recorded weights: none drawn (the new run at the old place, whose weights are others and whose
    # linear step was fitted through the old ones, is said to be unavailable)
    assert "<h2>Camera" not in pages["other"]
    assert "camera figures unavailable: runs/demo/run/linear_step.safetensors was fitted through other weights" \
        in pages["other"]


# ------------------------------------------------------------------------------------------------
# report: camera files and figures
# ------------------------------------------------------------------------------------------------
def test_a_flat_filter_is_drawn_as_the_white_of_a_perfect_reflector():
    """Each filter is peak-normalised before rendering: a flat κ = 1/C is the colour of a reflectance of 1."""
    from hsicam.color import spectra_to_srgb
    from hsicam.report.camera import cfa_tile_rgb
    from hsicam.spectral import Bands

    bands = Bands.from_centers([450.0 + 10 * i for i in range(21)])
    tile = np.full((21, 2, 2), 1 / 21)
    white = spectra_to_srgb(torch.ones(21, dtype=torch.float64), bands).numpy()
    np.testing.assert_allclose(cfa_tile_rgb(tile, bands), np.broadcast_to(white, (2, 2, 3)), atol=1e-9)


def test_psf_files_read_back_hold_the_psf_its_energy_and_the_exact_heights(tmp_path, tiny_camera):
    from hsicam.report.camera import write_psf_outputs

    cam = tiny_camera()
    info = write_psf_outputs(cam, tmp_path)
    psf = np.load(tmp_path / "psf.npy")
    meta = json.loads((tmp_path / "psf.json").read_text())
    assert meta == json.loads(json.dumps(info))
    assert psf.shape == (len(cam.bands), cam.kernel_px, cam.kernel_px)
    # the energy in the kernel is the light the kernel holds: the PSF's sum per band (less than 1: some falls outside)
    np.testing.assert_allclose(meta["energy_in_kernel"], psf.astype(np.float64).sum(axis=(1, 2)), rtol=1e-5)
    heights = np.load(tmp_path / "doe_height_m.npy")
    assert heights.dtype == np.float64
    np.testing.assert_array_equal(heights, cam.optics.doe.heights().detach().double().numpy())


def test_psf_of_a_camera_with_height_noise_is_one_element_per_seed(tmp_path):
    """`hsicam psf --set camera.doe.sigma_height_nm=50` drew the fabrication noise from torch's global generator:
    two runs wrote different PSFs (and fingerprints for `finetune --psf-dir`), a helper's hunt, session 71. Now
    --seed (default 0) draws it: the same seed, the same files; another, another element; doe_height_m.npy holds
    the nominal heights plus σ times the seed's normal draws (recomputed here)."""
    import torch

    from hsicam.cameras import build_camera
    from hsicam.cli import main
    from hsicam.config import load_config

    noise = ["--set", "camera.doe.sigma_height_nm=50"]
    for name, seed in (("a", []), ("b", []), ("c", ["--seed", "3"])):
        assert main(["psf", "--config", "tiny", *noise, "--out", str(tmp_path / name), *seed]) == 0
    read = lambda name, f: np.load(tmp_path / name / f)  # noqa: E731
    np.testing.assert_array_equal(read("a", "psf.npy"), read("b", "psf.npy"))
    assert not np.array_equal(read("a", "psf.npy"), read("c", "psf.npy"))
    doe = build_camera(load_config("tiny", ["camera.doe.sigma_height_nm=50"])).optics.doe
    with torch.no_grad():
        nominal = doe.height_m.double().numpy()  # (the tiny DOE: no wrap, clamp or levels)
        draws = torch.randn(doe.height_m.shape, generator=torch.Generator().manual_seed(3), dtype=doe.height_m.dtype)
    # (float32 heights: 1e-6 relative or 1e-13 m, where another draw moves them by ~5e-8 m)
    np.testing.assert_allclose(read("c", "doe_height_m.npy"), nominal + 50e-9 * draws.double().numpy(), rtol=1e-6,
                               atol=1e-13)
    assert json.loads((tmp_path / "c" / "psf.json").read_text())["height_noise_seed"] == 3
    assert main(["psf", "--config", "tiny", "--out", str(tmp_path / "d")]) == 0
    assert "height_noise_seed" not in json.loads((tmp_path / "d" / "psf.json").read_text())  # no noise: no seed


def test_the_camera_figures_draw_a_psf_only_when_asked(tmp_path, tiny_camera):
    from hsicam.report.camera import write_optics_figures

    cam = tiny_camera()
    (tmp_path / "a").mkdir()
    assert sorted(write_optics_figures(cam, tmp_path / "a")) == ["cfa.png", "doe.png"]
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["cfa.png", "doe.png"]
    (tmp_path / "b").mkdir()
    assert sorted(write_optics_figures(cam, tmp_path / "b", "x_", psf=True)) == ["x_cfa.png", "x_doe.png", "x_psf.png"]


# ------------------------------------------------------------------------------------------------
# report: more pages and figures
# ------------------------------------------------------------------------------------------------
def test_a_report_of_a_folder_without_its_completion_marker_is_refused(tmp_path):
    from hsicam.report.html import build_report

    d = tmp_path / "ev"
    d.mkdir()
    (d / "results.json").write_text(json.dumps({"method": "x", "scenes": [{"name": "a", **MEAN}], "mean": MEAN,
                                                "conventions": {}}))
    with pytest.raises(InputError) as err:
        build_report(d)
    assert str(err.value) == (f"{d}: incomplete evaluation folder (no completion marker: the command that wrote it "
                              "failed or was interrupted); run `hsicam evaluate` again")


def test_a_noise_experiment_without_its_noise_grid_is_a_corrupt_field(tmp_path):
    from hsicam.report.html import build_report

    d = _complete_folder(tmp_path, "experiment.json", {"experiment": "noise", "scale": "tiny", "seeds": [0],
                                                        "scenes": ["a"], "conventions": {}, "rows": []})
    with pytest.raises(InputError) as err:
        build_report(d)
    assert str(err.value) == f"{d / 'experiment.json'}: corrupt experiment.json ('noise_grid' is missing)"


def test_a_demo_report_shows_its_reconstructions_and_its_held_out_table(tmp_path):
    from hsicam.report.html import build_report

    other = {"psnr": 20.5, "ssim": 0.25, "sam": 7.0}
    d = _complete_folder(tmp_path, "results.json", {
        "method": "doe-learned", "scenes": [{"name": "a", **MEAN}], "mean": MEAN, "conventions": {},
        "heldout": {"data": "held-out sources", "scenes": [{"name": "h", **other}], "mean": other}})
    (d / "reconstructions.png").write_bytes(b"\x89PNG")
    page = build_report(d).read_text(encoding="utf-8")
    assert "<img src='../reconstructions.png'" in page
    assert "<h2>Held-out spectral sources</h2>" in page and ["h", "20.50", "0.2500", "7.00"] == _cells(page)[-2][:4]


def _random_psf(k: int = 9, c: int = 2) -> np.ndarray:
    return np.random.default_rng(4).random((c, k, k))


def test_rms_radius_and_central_square_fraction_against_a_brute_force_sum():
    """A PSF with light off the axis in x only: RMS radius sqrt(Σ p (x² + y²) / Σ p) and the light in the central
    3×3 and 5×5 squares, by explicit loops over the pixels."""
    from hsicam.report.camera import encircled_fraction_in_square, rms_radius_px

    psf = np.zeros((2, 9, 9))
    psf[0, 4, 7] = 1.0  # 3 px right of the axis
    psf[1] = _random_psf(c=1)[0]
    r2 = [sum(p[i, j] * ((i - 4) ** 2 + (j - 4) ** 2) for i in range(9) for j in range(9)) / p.sum() for p in psf]
    np.testing.assert_allclose(rms_radius_px(psf), np.sqrt(r2), rtol=1e-12)
    for size in (3, 5):
        lo = 4 - size // 2
        want = [sum(p[i, j] for i in range(lo, lo + size) for j in range(lo, lo + size)) / p.sum() for p in psf]
        np.testing.assert_allclose(encircled_fraction_in_square(psf, size), want, rtol=1e-12)


def test_the_psf_crop_holds_the_fraction_of_every_band_not_of_their_mean(tmp_path):
    """Nine bands a point on the axis, the tenth spread 4 px out: the 90 % crop is the one that holds the tenth's
    (9 px, brute force over odd sizes), not 1 px, where the mean over bands already reaches 90 %; a montage asked
    for a crop beyond the kernel shows the whole kernel."""
    from hsicam.report.camera import plot_psf_montage, psf_crop_px
    from hsicam.spectral import Bands

    psf = np.zeros((10, 11, 11))
    psf[:9, 5, 5] = 1.0
    psf[9, 5, [1, 9]] = 0.5
    psf[9, 5, 5] = 1e-3
    fits = [s for s in range(1, 12, 2)
            if all(p[5 - s // 2:5 + s // 2 + 1, 5 - s // 2:5 + s // 2 + 1].sum() / p.sum() >= 0.9 for p in psf)]
    assert psf_crop_px(psf, 0.9, minimum=1) == fits[0] == 9
    assert plot_psf_montage(psf, Bands.uniform(400, 490, 10), tmp_path / "psf.png", crop_px=99) == 11


def test_the_doe_figure_shows_the_whole_centred_aperture_of_an_oversampled_pupil(tmp_path, tiny_camera, monkeypatch):
    """With 2 pupil samples per cell the DOE figure's aperture is one value per cell over the whole centred disc:
    open at the centre, shut in all four corners (not the top-left quarter of the oversampled pupil, whose far
    corner is the disc's centre)."""
    from hsicam.report import camera as figures

    drawn = []
    monkeypatch.setattr(figures, "plot_doe_heights", lambda h, aperture, cell_um, path: drawn.append((h, aperture)))
    cam = tiny_camera("camera.psf.pupil_oversample=2")
    figures.write_optics_figures(cam, tmp_path)
    (h, aperture), = drawn
    n = cam.optics.doe.n_cells
    assert h.shape == aperture.shape == (n, n)
    assert aperture[n // 2, n // 2] > 0
    assert [aperture[0, 0], aperture[0, -1], aperture[-1, 0], aperture[-1, -1]] == [0, 0, 0, 0]
    # the open area fraction per cell, symmetric as the disc is (each cell's top-left sample lost its top and left
    # rim: 44 of 1329 cells at q = 2, session 74's figure hunt)
    np.testing.assert_array_equal(aperture, cam.optics.aperture_per_cell())
    np.testing.assert_array_equal(aperture > 0, (aperture > 0)[::-1, ::-1])
    assert float(h[aperture > 0].min()) == 0.0  # above its lowest cell, as exported (no negative "heights")


def test_camera_figures_draw_the_designed_doe_not_a_draw_of_its_fabrication_noise(tmp_path, tiny_camera, monkeypatch):
    """With σ_p > 0 the DOE and PSF figures drew an unseeded noise draw each (another element at every call, neither
    the one simulated nor the one scored, and the two figures of one report showing two elements: session 74's figure
    hunt). They draw the design (the exported heights, the PSFs of those) and their captions say σ_p is left out."""
    from hsicam.optics.perturb import design_heights
    from hsicam.optics.perturb import nominal_heights, psf_for_heights
    from hsicam.report import camera as figures

    drawn = {"h": [], "psf": []}
    monkeypatch.setattr(figures, "plot_doe_heights", lambda h, aperture, cell_um, path: drawn["h"].append(h))
    monkeypatch.setattr(figures, "plot_psf_montage", lambda psf, bands, path: drawn["psf"].append(psf) or 5)
    cam = tiny_camera("camera.doe.sigma_height_nm=40")
    captions = [figures.write_optics_figures(cam, tmp_path, psf=True) for _ in range(2)]
    np.testing.assert_array_equal(drawn["h"][0], drawn["h"][1])
    np.testing.assert_array_equal(drawn["h"][0], design_heights(cam)[0])
    np.testing.assert_array_equal(drawn["psf"][0], drawn["psf"][1])
    design_psf = psf_for_heights(cam.optics, nominal_heights(cam)).psf.float().numpy()
    np.testing.assert_allclose(drawn["psf"][0], design_psf, rtol=0, atol=1e-7)
    noisy = cam.psf_result().psf.detach().float().numpy()
    assert np.abs(noisy - design_psf).max() > 100 * 1e-7  # (the noise does move the PSF: the test can fail)
    assert "without the fabrication noise σ_p = 40 nm" in captions[0]["psf.png"]
    assert "without the fabrication noise σ_p = 40 nm" in captions[0]["doe.png"]
    clean = figures.write_optics_figures(tiny_camera(), tmp_path, psf=True)
    assert "fabrication noise" not in clean["psf.png"] + clean["doe.png"]
    # the demo's psf.npy / doe_height_m.npy beside them: the same design (a fresh draw each before; the review)
    for k in (1, 2):
        (tmp_path / str(k)).mkdir()
        info = figures.write_psf_outputs(cam, tmp_path / str(k), design=True)
    assert info["heights"] == "the design, without the fabrication noise σ_p = 40 nm"
    np.testing.assert_array_equal(np.load(tmp_path / "1" / "psf.npy"), np.load(tmp_path / "2" / "psf.npy"))
    np.testing.assert_array_equal(np.load(tmp_path / "1" / "doe_height_m.npy"), nominal_heights(cam).numpy())
    np.testing.assert_allclose(np.load(tmp_path / "1" / "psf.npy"), design_psf, rtol=0, atol=1e-7)
    drawn_once = figures.write_psf_outputs(cam, tmp_path / "1", torch.Generator().manual_seed(0))
    assert drawn_once["heights"] == "one draw of the fabrication noise σ_p = 40 nm"


def test_an_experiment_report_draws_cameras_only_of_runs_with_weights(tmp_path):
    """runs/ of an experiment may hold a folder without weights (the compare's Choi prior, a run never started):
    no camera section for it, the page is still written."""
    from hsicam.report.html import build_report

    d = _complete_folder(tmp_path, "experiment.json", {
        "experiment": "ablation", "scale": "tiny", "seeds": [0], "scenes": ["a"], "conventions": {},
        "rows": [{"method": "doe+cfa", **MEAN, "runtime_s": 0.5}]})
    (d / "runs" / "dd-cassi-choi").mkdir(parents=True)
    (d / "runs" / "dd-cassi-choi" / "summary.json").write_text("{}")
    page = build_report(d).read_text(encoding="utf-8")
    assert "dd-cassi-choi" not in page


def test_an_evaluation_report_draws_the_first_six_scenes_of_its_cubes_and_says_what_it_left_out(tmp_path):
    """`hsicam report` of an evaluation whose cubes/ hold eight scenes: a comparison and an error figure for each of
    the first six scenes in name order that have both cubes, no more; a note says how many were saved and which
    estimates lack their truth (before session 71 a scene without truth took one of the six places and neither was
    said). The cubes carry their own bands: a results.json without bands_nm still draws them."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.io import mark_complete
    from hsicam.report.html import build_report
    from hsicam.spectral import Bands

    bands = Bands.uniform(500, 600, 50)
    mean = {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}
    names = [f"s{i}" for i in range(8)]
    ev = tmp_path / "ev"
    (ev / "cubes").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for n in names:
        truth = rng.random((3, 16, 16)).astype(np.float32)
        write_cube_h5(ev / "cubes" / f"{n}_estimate.h5", truth * 0.9, bands)
        if n != "s2":
            write_cube_h5(ev / "cubes" / f"{n}_truth.h5", truth, bands)
    (ev / "results.json").write_text(json.dumps({
        "method": "doe-learned", "scenes": [{"name": n, **mean} for n in names], "mean": mean,
        "conventions": {"psnr": "per band, peak 1"}}))  # (no bands_nm)
    mark_complete(ev, {"command": "test"})
    page = build_report(ev)
    six = ("s0", "s1", "s3", "s4", "s5", "s6")
    assert sorted(p.name for p in page.parent.glob("recon_*.png")) == [f"recon_{n}.png" for n in six]
    assert sorted(p.name for p in page.parent.glob("errors_*.png")) == [f"errors_{n}.png" for n in six]
    text = page.read_text()
    assert all(f"recon_{n}.png" in text for n in six)
    assert "recon_s7.png" not in text and "recon_s2.png" not in text
    assert ("<p class='note'>the first 6 by name of the 7 scenes saved with their ground truth (each scene&#x27;s "
            "cubes are in cubes/); not shown, their ground truth missing from cubes/: s2_estimate.h5</p>") in text


@pytest.mark.parametrize("n_bands, shown", [(31, 16), (10, 10)])
def test_the_band_error_figure_spreads_its_bands_from_the_first_to_the_last(tmp_path, monkeypatch, n_bands, shown):
    """The per-band error figure shows up to 16 bands chosen over the whole range: the first and the last band among
    them, no gap wider than twice the grid's mean spacing, each panel the |error| of the band it names."""
    import hsicam.report.html as report
    from hsicam.spectral import Bands

    bands = Bands.uniform(420, 420 + 10 * (n_bands - 1), 10)
    truth = np.zeros((n_bands, 8, 8), np.float32)
    est = truth + np.arange(n_bands, dtype=np.float32)[:, None, None] / 100  # band c's error is c / 100 everywhere
    figs = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: figs.append(fig))
    report.plot_band_errors(truth, est, bands, tmp_path / "e.png")
    panels = [(float(ax.get_title().split()[0]), ax.images[0].get_array()) for ax in figs[0].axes if ax.images]
    nm = [p[0] for p in panels]
    assert len(nm) == shown and nm[0] == 420 and nm[-1] == 420 + 10 * (n_bands - 1)
    assert np.all(np.diff(nm) > 0) and np.max(np.diff(nm)) <= 2 * (nm[-1] - nm[0]) / (shown - 1)
    for wl, img in panels:
        np.testing.assert_allclose(np.asarray(img), (wl - 420) / 10 / 100, rtol=1e-5)


@pytest.mark.parametrize("m", [4, 15])
def test_the_cfa_figures_tile_title_keeps_clear_of_the_curves_axis_label(tmp_path, monkeypatch, m):
    """cfa.png's tile title ran into the transmission panel's y label (a 15×15 tile; just touching at 4×4: session 74's
    figure hunt): their boxes, as drawn, do not overlap."""
    import hsicam.report.camera as figures
    from hsicam.spectral import Bands

    figs = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path: figs.append(fig))
    bands = Bands.uniform(420, 720, 50)  # (the tiny preset's 7 bands, whose figure it was)
    tile = np.random.default_rng(0).random((len(bands), m, m))
    figures.plot_cfa(tile / tile.sum(axis=0), bands, tmp_path / "cfa.png")
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(figs[0])  # drawn as savefig draws it (hsicam's figures carry no pyplot canvas)
    canvas.draw()
    renderer = canvas.get_renderer()
    fig = figs[0]
    a0, a1 = fig.axes[:2]
    title, label = a0.title.get_window_extent(renderer), a1.yaxis.label.get_window_extent(renderer)
    assert title.x1 < label.x0, (title, label)  # the title stays over its own panel, left of the label's column
