"""Mutation guards of the reconstruction and tolerance reports (report/reconstruction.py, report/tolerance.py), probe
mut8b, moved here from the models floor's camera-system file: each test kills a hand-made mutant that the rest of the
suite let through, asserting against a figure's plotted data or text read back from its axes and values worked out
by hand.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

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
