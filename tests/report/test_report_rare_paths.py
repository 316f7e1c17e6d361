"""Lines of the report modules that the default suite never ran (coverage round 11, cov11a; those of the DOE export
and the dataset modules are in export/test_export_rare_paths.py and data/test_data_sources_rare_paths.py)."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import entries
from hsicam.data.formats import write_cube_h5
from hsicam.errors import InputError
from hsicam.io import mark_complete
from hsicam.report.html import build_report
from hsicam.spectral import Bands
from report_files import MEAN, evaluation, experiment, folder_with

B3 = [500.0, 550.0, 600.0]


# ------------------------------------------------------------------------------------------------
# report/html.py
# ------------------------------------------------------------------------------------------------
def test_report_of_a_folder_that_does_not_exist(tmp_path):
    with pytest.raises(InputError) as info:
        build_report(tmp_path / "nowhere")
    assert str(info.value) == f"{tmp_path / 'nowhere'}: no such folder"
    assert entries(tmp_path) == []


@pytest.mark.parametrize("name, data, field", [
    ("results.json", evaluation(scenes=[{"name": "a", **MEAN}, 3]), "scenes"),
    ("experiment.json", {"experiment": "compare", "scale": "tiny", "seeds": [0], "scenes": ["a"],
                         "rows": ["doe-learned"], "conventions": {}}, "rows"),
])
def test_report_names_a_row_that_is_not_an_object(tmp_path, name, data, field):
    d = folder_with(tmp_path, name, data)
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == f"{d / name}: corrupt {name} (an entry of '{field}' is not an object)"
    assert entries(d) == [".complete", name]


def test_report_of_an_evaluation_whose_run_is_gone_says_so_on_the_page(tmp_path):
    gone = tmp_path / "run-moved-away"
    d = folder_with(tmp_path, "results.json", evaluation(run=str(gone)))
    page = build_report(d).read_text(encoding="utf-8")
    assert f"<p class='note'>camera figures unavailable: {html.escape(str(gone))}: no such run folder</p>" in page
    assert "<h2>Camera" not in page and entries(d / "report") == [".complete", "index.html"]


@pytest.mark.parametrize("weights, sentence", [
    ({"checkpoint": "best"}, None),  # no step: a results.json from elsewhere, left unsaid
    (["last"], None),
    ({"checkpoint": "last", "step": 7}, "Weights: the last step&#x27;s (7), no checkpoint selection."),
])
def test_report_weights_sentence_only_from_a_well_formed_entry(tmp_path, weights, sentence):
    page = build_report(folder_with(tmp_path, "results.json", evaluation(weights=weights))).read_text(encoding="utf-8")
    if sentence is None:
        assert "Weights:" not in page and "<table>" in page
    else:
        assert f"<p class='note'>{sentence}</p>" in page


def test_report_refuses_unordered_bands_naming_the_field(tmp_path):
    d = folder_with(tmp_path, "results.json", evaluation(bands_nm=[600.0, 500.0, 550.0]))
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == f"{d / 'results.json'}: corrupt results.json ('bands_nm' is not in strictly ascending order)"
    assert entries(d) == [".complete", "results.json"]


def _with_cubes(tmp_path: Path, truth: np.ndarray, truth_bands: list[float], est: np.ndarray | None) -> Path:
    d = tmp_path / "ev"
    d.mkdir()
    (d / "results.json").write_text(json.dumps(evaluation()))
    (d / "cubes").mkdir()
    write_cube_h5(d / "cubes" / "a_truth.h5", truth, Bands.from_centers(truth_bands))
    if est is None:
        (d / "cubes" / "a_estimate.h5").write_bytes(b"not a cube")
    else:
        write_cube_h5(d / "cubes" / "a_estimate.h5", est, Bands.from_centers(B3))
    mark_complete(d, {"command": "evaluate"})
    return d


@pytest.mark.parametrize("shape, bands, text", [
    ((3, 12, 12), B3, "a 3-band (500-600 nm) 12×12 cube, but a_estimate.h5 holds a 3-band (500-600 nm) 16×16 one"),
    ((4, 16, 16), B3 + [650.0], "a 4-band (500-650 nm) 16×16 cube, but a_estimate.h5 holds a 3-band (500-600 nm) "
                                "16×16 one"),
    ((3, 16, 16), [510.0, 550.0, 600.0], "a 3-band (510-600 nm) 16×16 cube, but a_estimate.h5 holds a 3-band "
                                         "(500-600 nm) 16×16 one"),
])
def test_report_names_a_truth_cube_that_is_not_its_estimates_pair(tmp_path, shape, bands, text):
    """It said 'corrupt results.json (a field holds a value of the wrong kind: operands could not be broadcast …)'
    (or nothing at all for another band grid of the same size, plotting the truth on the estimate's wavelengths)."""
    rng = np.random.default_rng(0)
    d = _with_cubes(tmp_path, rng.random(shape, dtype=np.float32), bands, rng.random((3, 16, 16), dtype=np.float32))
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == (f"{d / 'cubes' / 'a_truth.h5'}: {text}: not the same scene's pair (cubes/ of two "
                               "evaluations?)")
    assert entries(d) == [".complete", "cubes", "results.json"]


def test_report_names_an_unreadable_cube_not_results_json(tmp_path):
    d = _with_cubes(tmp_path, np.ones((3, 8, 8), np.float32), B3, None)
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value).startswith(f"{d / 'cubes' / 'a_estimate.h5'}: unknown format")
    assert "results.json" not in str(info.value)
    assert entries(d) == [".complete", "cubes", "results.json"]


def test_report_of_a_matching_pair_draws_it(tmp_path):
    """The reference pair for the refusals above: same grid and size, both figures written."""
    rng = np.random.default_rng(1)
    d = _with_cubes(tmp_path, rng.random((3, 16, 16), dtype=np.float32), B3, rng.random((3, 16, 16), dtype=np.float32))
    build_report(d)
    assert entries(d / "report") == [".complete", "errors_a.png", "index.html", "recon_a.png"]


# ------------------------------------------------------------------------------------------------
# report/camera.py (session 58, cov12a: moved from data/test_data_sources_rare_paths.py)
# ------------------------------------------------------------------------------------------------
def test_a_psf_band_without_light_makes_the_crop_the_whole_kernel():
    """A band holding no light never reaches the fraction in any crop: the whole kernel, not an error."""
    from hsicam.report.camera import psf_crop_px

    psf = np.zeros((2, 21, 21))
    psf[0, 10, 10] = 1.0  # a point: 15 px (the minimum) holds it
    assert psf_crop_px(psf[:1]) == 15
    assert psf_crop_px(psf) == 21


def test_report_of_an_evaluation_whose_run_has_a_damaged_config_says_so_on_the_page(tmp_path):
    """A run whose config.yaml is broken YAML (a ConfigError) failed the whole report with "results.json: corrupt
    results.json (a field holds a value of the wrong kind: …config.yaml: invalid YAML …)": the results file blamed
    for the run's damage (an experiment's report the same, naming experiment.json). Now the camera section is a note
    naming the run's config.yaml, and the results are drawn, as for a missing run or damaged weights."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("model: [unclosed\n", encoding="utf-8")
    d = folder_with(tmp_path, "results.json", evaluation(run=str(run)))
    page = build_report(d).read_text(encoding="utf-8")
    assert f"<p class='note'>camera figures unavailable: {html.escape(str(run / 'config.yaml'))}: invalid YAML" in page
    assert "<h2>Results" in page and "<h2>Camera" not in page


@pytest.mark.parametrize("value, text", [(True, "true"), (False, "false"), (30.0, "30.00")])
def test_report_cell_of_a_boolean_score_is_not_a_number(tmp_path, value, text):
    """An edited results.json's "psnr": true was drawn as 1.00 dB (bool is an int to Python)."""
    d = folder_with(tmp_path, "results.json", evaluation(scenes=[{"name": "a", **{**MEAN, "psnr": value}}]))
    page = build_report(d).read_text(encoding="utf-8")
    assert f"<tr><td>a</td><td>{text}</td>" in page


def test_an_experiment_report_orders_its_cameras_as_its_table_and_says_which_figures_are_missing(tmp_path,
                                                                                                  monkeypatch):
    """The camera sections of an experiment came in sorted-name order (period-12, period-15, period-3, …), each headed
    by its absolute path, and a figure experiment.json lists but the folder lacks was left out without a word (a
    helper's hunt, session 71). Now the table's order (then names with their numbers as numbers), each headed
    runs/NAME, and a note names the missing figure."""
    import hsicam.report.html as report

    rows = [{"method": f"period-{p}", **MEAN} for p in (3, 6, 12)]
    figures = [{"file": "comparison_a.png", "scene": "a", "role": "median", "methods": ["period-3"]}]
    d = folder_with(tmp_path, "experiment.json", experiment(experiment="cfa-period", rows=rows, figures=figures))
    for name in ("period-12", "period-3", "period-6", "extra-10", "extra-9"):
        (d / "runs" / name).mkdir(parents=True)
        (d / "runs" / name / "model.safetensors").write_bytes(b"")
    seen = []
    monkeypatch.setattr(report, "_camera_section", lambda run, out, prefix="", label=None, **kw: seen.append(label) or "")
    page = build_report(d).read_text(encoding="utf-8")
    assert seen == ["runs/period-3", "runs/period-6", "runs/period-12", "runs/extra-9", "runs/extra-10"]
    assert ("<p class='note'>figures listed in experiment.json but missing from the folder: comparison_a.png</p>"
            in page)


def test_report_reads_a_results_json_saved_with_a_byte_order_mark(tmp_path):
    """A results.json edited and saved by an editor that writes a UTF-8 byte-order mark was refused with Python's
    "Unexpected UTF-8 BOM (decode using utf-8-sig)", advice for a programmer (a helper's hunt, session 71); the
    mark is skipped, as RFC 8259 lets a reader do."""
    d = folder_with(tmp_path, "results.json", evaluation())
    (d / "results.json").write_bytes(b"\xef\xbb\xbf" + (d / "results.json").read_bytes())
    page = build_report(d).read_text(encoding="utf-8")
    assert "<h2>Results" in page and "<tr><td>a</td><td>30.00</td>" in page


def test_report_of_results_listing_no_scene_says_so(tmp_path):
    """An edited results.json with "scenes": [] drew a table of its mean row alone, without a word (a helper's hunt,
    session 71): a note says the file lists no scene."""
    d = folder_with(tmp_path, "results.json", evaluation(scenes=[]))
    page = build_report(d).read_text(encoding="utf-8")
    assert "<p class='note'>results.json lists no scene: the mean above is the file's own" in page
    page = build_report(folder_with(tmp_path / "b", "results.json", evaluation())).read_text(encoding="utf-8")
    assert "lists no scene" not in page


def test_an_evaluation_of_other_weights_than_the_runs_now_gets_no_camera_figures(tmp_path):
    """The report drew the run's camera as it is now beside scores of the weights evaluate read (results.json's
    weights_sha256): a run trained on (or replaced) since showed another DOE, CFA and PSFs than those scored, without
    a word (session 73's hunt). With the scored weights the figures are drawn; with others a note says why not."""
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256
    from hsicam.runs.pretrained import resolve_run

    sha = file_sha256(root_weights_path(resolve_run("pretrained:standard")))
    same = folder_with(tmp_path / "same", "results.json", evaluation(run="pretrained:standard", weights_sha256=sha))
    page = build_report(same).read_text(encoding="utf-8")
    assert "<h2>Camera (pretrained:standard)</h2>" in page and "left out" not in page
    other = folder_with(tmp_path / "other", "results.json",
                        evaluation(run="pretrained:standard", weights_sha256="0" * 64))
    page = build_report(other).read_text(encoding="utf-8")
    assert "<h2>Camera" not in page
    assert ("camera figures left out: the weights of pretrained:standard changed since these results were scored "
            f"(sha256 000000000000… then, {sha[:12]}… now") in html.unescape(page)


def test_an_experiment_report_draws_a_runs_camera_only_while_its_weights_are_the_ones_scored(tmp_path):
    """An experiment's report drew each run's camera as it is now: a run trained on or replaced since the experiment
    showed other optics beside its row (session 73, noticed). experiment.json's rows record the weights scored
    (``weights_sha256``); a run whose weights are others now gets a note instead of figures, a row recording none (an
    older experiment.json) its camera now."""
    import shutil

    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256
    from hsicam.runs.pretrained import resolve_run

    src = resolve_run("pretrained:standard")
    sha = file_sha256(root_weights_path(src))
    rows = [{"method": "doe+cfa", **MEAN, "weights_sha256": sha}, {"method": "no-doe", **MEAN, "weights_sha256": "0" * 64},
            {"method": "no-cfa", **MEAN}]
    d = folder_with(tmp_path, "experiment.json", experiment(experiment="ablation", rows=rows))
    for name in ("doe+cfa", "no-doe", "no-cfa"):
        shutil.copytree(src, d / "runs" / name)
    page = html.unescape(build_report(d).read_text(encoding="utf-8"))
    assert "<h2>Camera (runs/doe+cfa)</h2>" in page and "<h2>Camera (runs/no-cfa)</h2>" in page
    assert "<h2>Camera (runs/no-doe)</h2>" not in page
    assert ("camera figures left out: the weights of runs/no-doe changed since these results were scored (sha256 "
            f"000000000000… then, {sha[:12]}… now: trained on, or replaced), so its camera now is not the one scored; "
            f"score it as it is now with `hsicam evaluate --run {d / 'runs' / 'no-doe'}`, or delete it and run `hsicam "
            "experiment ablation` into this folder again (a run trained on since is not the experiment's and is "
            "refused) for its current camera") in page
    assert page.count("camera figures left out") == 1


def test_a_cfa_period_sweeps_report_draws_the_scores_against_the_period(tmp_path, monkeypatch):
    """The paper's CFA period sweep is a figure (DESIGN.md §5); the report gave the sweep a table only (session 74's
    figure hunt). A figure of PSNR, SSIM and SAM against the period, its points the rows' (in period order, whatever
    the rows' order), and none for an experiment of other rows."""
    import hsicam.report.html as report

    figs = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: figs.append((fig, path)))
    rows = [{"method": f"period-{p}", "psnr": 30.0 + p / 10, "ssim": 0.8 + p / 100, "sam": 10.0 - p / 3}
            for p in (12, 3, 6)]
    d = folder_with(tmp_path, "experiment.json", experiment(experiment="cfa-period", rows=rows))
    page = build_report(d).read_text(encoding="utf-8")
    assert "period_sweep.png" in page
    (fig, path), = [(f, p) for f, p in figs if p.name == "period_sweep.png"]
    for ax, key in zip(fig.axes, ("psnr", "ssim", "sam")):
        (line,) = ax.get_lines()
        assert list(line.get_xdata()) == [3, 6, 12]
        np.testing.assert_allclose(line.get_ydata(), [next(r[key] for r in rows if r["method"] == f"period-{p}")
                                                      for p in (3, 6, 12)])
    figs.clear()
    d2 = folder_with(tmp_path / "b", "experiment.json", experiment(experiment="ablation", rows=[{"method": "doe+cfa", **MEAN}]))
    assert "period_sweep.png" not in build_report(d2).read_text(encoding="utf-8")
