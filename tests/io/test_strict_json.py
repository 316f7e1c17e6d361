"""hsicam's JSON files are strict JSON (RFC 8259, what JavaScript's ``JSON.parse`` takes): a score that is not a
finite number (the NaN SAM of a scene whose truth is zero at every scored pixel) is written as null (a score of
±inf as "inf"/"-inf": a value, the worst, not undefined), not as the
``NaN`` / ``Infinity`` that Python's json writes and strict parsers refuse; hsicam's readers take that null as NaN
again, so the report, ``pretrained pack``, cards and resumes say what they said before, and files of older
versions (``NaN`` literals) still read."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from html_helpers import PageParts
from hsicam.engine.evaluate import SceneResult, summarize, write_results
from hsicam.engine.loop import last_validation
from hsicam.engine.pretrained import results_metrics
from hsicam.errors import InputError
from hsicam.io import mark_complete, write_json
from hsicam.metrics import all_metrics
from hsicam.report.html import build_report
from hsicam.runs.folder import MetricsLog
from hsicam.runs.pretrained import CARD_JSON, REQUIRED, parse_card


def _refuse(constant: str):
    raise ValueError(f"not strict JSON: {constant}")


def strict(text: str):
    """``text`` parsed as a strict parser does (JSON.parse): NaN, Infinity and -Infinity are refused."""
    return json.loads(text, parse_constant=_refuse)


def _results(scenes: dict[str, tuple[np.ndarray, np.ndarray]], **facts) -> dict:
    """summarize() of the scenes {name: (estimate, truth)} scored by all_metrics, as evaluate scores them."""
    rows = []
    for name, (est, truth) in scenes.items():
        m = {k: v[0] for k, v in all_metrics(torch.from_numpy(est)[None], torch.from_numpy(truth)[None]).items()}
        rows.append(SceneResult(name, m, None, None, 0.5, sam_excluded_px=int((truth == 0).all(axis=0).sum())))
    return summarize(rows, **facts)


def _dark_and_lit():
    """A scene dark everywhere (SAM undefined) with a constant 0.1 estimate: per-band MSE 0.01, PSNR 20 dB; and a
    lit scene estimated exactly up to a factor 0.5 (spectral angle 0°)."""
    rng = np.random.default_rng(0)
    dark = (np.full((3, 16, 16), 0.1, np.float32), np.zeros((3, 16, 16), np.float32))
    truth = rng.uniform(0.2, 1.0, (3, 16, 16)).astype(np.float32)
    return {"dark": dark, "lit": (0.5 * truth, truth)}


def test_results_json_of_an_undefined_sam_is_strict_and_reports_as_before(tmp_path):
    """evaluate's results.json with a scene whose SAM is undefined: a strict parser reads it (it held ``NaN``), the
    SAM is null there; hsicam's report reads it as NaN again, and its table says "n/a", as for the NaN before."""
    out = tmp_path / "ev"
    out.mkdir()
    write_results(out, _results(_dark_and_lit()))
    mark_complete(out, {"command": "evaluate"})
    data = strict((out / "results.json").read_text(encoding="utf-8"))
    rows = {r["name"]: r for r in data["scenes"]}
    assert rows["dark"]["sam"] is None and data["sam_undefined"] == ["dark"]
    assert rows["dark"]["psnr"] == pytest.approx(20.0, abs=1e-4)  # 10 log10(1 / 0.01): the other scores are numbers
    assert rows["lit"]["sam"] == pytest.approx(0.0, abs=0.05) and data["mean"]["sam"] == rows["lit"]["sam"]
    # results.csv and results.md still say nan (they are no JSON)
    assert "nan" in (out / "results.csv").read_text().splitlines()[1].split(",")
    assert "| dark | 20.00 | " in (out / "results.md").read_text() and " | nan | " in (out / "results.md").read_text()
    cells = PageParts(build_report(out).read_text(encoding="utf-8")).cells
    table = [cells[i : i + 7] for i in range(0, 21, 7)]  # scene, PSNR, SSIM, SAM, ERGAS, PSNR MST, runtime
    assert [r[0] for r in table] == ["dark", "lit", "mean"]
    lit = f"{rows['lit']['sam']:.2f}"
    assert table[0][1] == "20.00" and [r[3] for r in table] == ["n/a", lit, lit]  # SAM


def test_pack_reads_a_null_mean_sam_as_the_undefined_sam_it_was(tmp_path):
    """`pretrained pack --results` of an evaluation where no scene has a spectral angle: the mean SAM, null in the
    strict file, is refused with the same line as the NaN of older files (not "no mean PSNR/SSIM/SAM as numbers")."""
    scenes = _dark_and_lit()
    del scenes["lit"]
    out = tmp_path / "ev"
    out.mkdir()
    write_results(out, _results(scenes))
    path = out / "results.json"
    assert strict(path.read_text(encoding="utf-8"))["mean"]["sam"] is None
    want = "has no mean SAM: the spectral angle is undefined on every scene (the truth is zero at every scored pixel: dark)"
    with pytest.raises(InputError, match=want.replace("(", r"\(").replace(")", r"\)")):
        results_metrics(path)
    old = tmp_path / "old.json"  # the same file as older hsicam wrote it: NaN literals
    old.write_text(path.read_text(encoding="utf-8").replace("null", "NaN"), encoding="utf-8")
    with pytest.raises(InputError, match=want.replace("(", r"\(").replace(")", r"\)")):
        results_metrics(old)


def test_noise_grid_with_a_non_finite_score_is_strict_and_still_reported(tmp_path):
    """experiment.json (written by write_json, as `hsicam experiment` does) with a NaN point in its noise grid: strict
    JSON with null there; `hsicam report` reads it as the NaN it was (a null failed its numeric check) and shows n/a."""
    grid = [{"sigma_height_nm": 0.0, "sensor_sigma": s, "psnr": p, "ssim": 0.5} for s, p in ((0.0, 30.0), (0.01, math.nan))]
    exp = {"experiment": "noise", "scale": "tiny", "seeds": [0], "scenes": ["a"], "conventions": {},
           "rows": [{"method": "cam", "psnr": 30.0, "ssim": 0.5, "psnr_worst": math.nan, "ssim_worst": 0.5}],
           "noise_grid": {"sigma_height_nm": [0.0], "sensor_sigma": [0.0, 0.01], "results": {"cam": grid}}}
    d = tmp_path / "ex"
    d.mkdir()
    write_json(d / "experiment.json", exp)
    mark_complete(d, {"command": "experiment"})
    data = strict((d / "experiment.json").read_text(encoding="utf-8"))
    assert data["noise_grid"]["results"]["cam"][1]["psnr"] is None and data["rows"][0]["psnr_worst"] is None
    cells = PageParts(build_report(d).read_text(encoding="utf-8")).cells
    assert cells == ["cam", "30.00", "0.5000", "n/a", "0.5000"]
    assert (d / "report" / "noise_grid.png").is_file()


def test_metrics_jsonl_is_strict_and_a_resume_reads_the_nan_again(tmp_path):
    """A validation whose SAM is NaN (every validation patch black): its metrics.jsonl line is strict JSON (null),
    and MetricsLog.read (resume's last_validation, the final record a card cites) gives NaN again; a rewrite by
    truncate_after stays strict; an old line with NaN reads as before."""
    log = MetricsLog(tmp_path / "metrics.jsonl")
    log.write({"step": 4, "epoch": 0, "train_loss": 0.1})
    log.write({"step": 4, "epoch": 0, "val_psnr": 27.5, "val_ssim": 0.4, "val_sam": float("nan")})
    log.write({"step": 4, "epoch": 1, "final": True, "best_psnr": None, "val_psnr": 27.5, "val_sam": float("nan")})
    lines = [strict(x) for x in log.path.read_text(encoding="utf-8").splitlines()]
    assert lines[1]["val_sam"] is None and lines[2]["val_sam"] is None
    recs = log.read()
    assert math.isnan(recs[1]["val_sam"]) and math.isnan(recs[2]["val_sam"]) and recs[2]["best_psnr"] is None
    val = last_validation(recs)
    assert val["psnr"] == 27.5 and math.isnan(val["sam"])
    log.truncate_after(4, 0)  # the final record goes, the rest is written again
    assert [strict(x) for x in log.path.read_text(encoding="utf-8").splitlines()] == lines[:2]
    with log.path.open("a", encoding="utf-8") as fh:  # a line older hsicam wrote
        fh.write('{"step": 8, "epoch": 1, "val_psnr": 28.0, "val_sam": NaN}\n')
    assert math.isnan(last_validation(log.read())["sam"])


def test_card_training_log_null_sam_reads_as_nan_and_an_unvalidated_run_as_none(tmp_path):
    """card.json (write_json, as pack writes it) whose training log has a NaN SAM: strict JSON, null there; the card
    as read (`hsicam pretrained`'s line) says "SAM nan°" as before. A run without validation (all three None) keeps
    None: its line says "val –" as before."""
    from hsicam.cli.pretrained import _metrics

    for name, log, want in (("nan", {"psnr": 27.5, "ssim": 0.4, "sam": math.nan},
                             "its validation patches: PSNR 27.50 dB, SSIM 0.4000, SAM nan°"),
                            ("none", {"psnr": None, "ssim": None, "sam": None}, "val –")):
        folder = tmp_path / name
        folder.mkdir()
        for f in REQUIRED:
            (folder / f).write_text("x")
        write_json(folder / CARD_JSON, {"name": name, "metrics": {"training_log": {"what": "patches", **log,
                                                                                    "best_psnr": None}}})
        assert strict((folder / CARD_JSON).read_text(encoding="utf-8"))["metrics"]["training_log"]["sam"] is None
        card, why = parse_card(folder)
        assert why is None and _metrics(card) == want


def test_write_json_writes_every_non_finite_number_as_null(tmp_path):
    """psf.json, checkpoints.json and the others go through write_json: NaN, ±inf (Python's and numpy's, in arrays
    too) are null, finite values are kept exactly; a file of older hsicam (NaN literals) is unchanged in meaning."""
    obj = {"a": float("inf"), "b": [np.float32("-inf"), 1.5, np.float64("nan")], "c": np.array([[0.25, np.nan]]),
           "d": (np.int64(3), True, None, "NaN"), "e": {"f": 0.1}}
    write_json(tmp_path / "x.json", obj)
    assert strict((tmp_path / "x.json").read_text(encoding="utf-8")) == {
        "a": None, "b": [None, 1.5, None], "c": [[0.25, None]], "d": [3, True, None, "NaN"], "e": {"f": 0.1}}


def test_an_infinite_score_round_trips_as_inf_not_as_an_undefined_nan(tmp_path):
    """A score of ±inf (all_metrics' worst: -inf dB, +inf SAM/ERGAS/RMSE for a broken estimate with a NaN pixel) is a
    value, not undefined: results.json holds "-inf"/"inf" (strict JSON has no Infinity; it was null, read back as NaN
    and shown "n/a" as an undefined SAM is), hsicam's readers take ±inf again, the mean over scenes with an infinite
    score is that infinity (NaN, undefined, scenes are left out of a mean; ±inf are not), and results.csv, results.md
    and the report say -inf / inf, while the dark scene's undefined SAM stays null / nan / "n/a"."""
    scenes = _dark_and_lit()
    est, truth = scenes["lit"]
    broken = est.copy()
    broken[1, 3, 4] = np.nan
    scenes["broken"] = (broken, truth)
    out = tmp_path / "ev"
    out.mkdir()
    write_results(out, _results(scenes))
    mark_complete(out, {"command": "evaluate"})
    data = strict((out / "results.json").read_text(encoding="utf-8"))
    rows = {r["name"]: r for r in data["scenes"]}
    assert {k: rows["broken"][k] for k in ("psnr", "ssim", "sam", "ergas", "rmse")} == {
        "psnr": "-inf", "ssim": "-inf", "sam": "inf", "ergas": "inf", "rmse": "inf"}
    assert rows["dark"]["sam"] is None and data["sam_undefined"] == ["dark"]  # NaN stays null, apart from inf
    assert data["mean"]["psnr"] == "-inf" and data["mean"]["sam"] == "inf"  # over lit and broken (dark: undefined)
    with pytest.raises(InputError, match=r"has a mean PSNR/SSIM/SAM that is not a finite number \(psnr: -inf, "
                                         r"ssim: -inf, sam: inf\)"):
        results_metrics(out / "results.json")
    csv_rows = {line.split(",")[0]: line.split(",") for line in (out / "results.csv").read_text().splitlines()}
    assert csv_rows["broken"][2:5] == ["-inf", "-inf", "inf"] and csv_rows["mean"][2] == "-inf"  # psnr, ssim, sam
    assert csv_rows["dark"][4] == "nan"
    md = (out / "results.md").read_text(encoding="utf-8")
    assert "| broken | -inf | -inf | inf | inf |" in md and "| **mean** | -inf | -inf | inf |" in md
    cells = PageParts(build_report(out).read_text(encoding="utf-8")).cells
    table = {r[0]: r for r in (cells[i : i + 7] for i in range(0, len(cells), 7))}  # scene, PSNR, SSIM, SAM, ERGAS ...
    assert table["broken"][1:5] == ["-inf", "-inf", "inf", "inf"] and table["mean"][1] == "-inf"
    assert table["dark"][3] == "n/a" and table["mean"][3] == "inf"


def test_metrics_jsonl_keeps_an_infinite_score_apart_from_nan(tmp_path):
    """metrics.jsonl (MetricsLog): a val_psnr of +inf is written "inf" (strict JSON) and read back +inf, a NaN SAM
    null and read back NaN; a line an older hsicam wrote with Infinity reads as +inf too."""
    log = MetricsLog(tmp_path / "metrics.jsonl")
    log.write({"step": 1, "epoch": 0, "val_psnr": math.inf, "val_ssim": 1.0, "val_sam": math.nan})
    line = strict(log.path.read_text(encoding="utf-8").splitlines()[0])
    assert line["val_psnr"] == "inf" and line["val_sam"] is None
    with log.path.open("a", encoding="utf-8") as fh:
        fh.write('{"step": 2, "epoch": 0, "val_psnr": Infinity, "val_ssim": 1.0, "val_sam": NaN}\n')
    for rec in log.read():
        assert rec["val_psnr"] == math.inf and math.isnan(rec["val_sam"])


def test_a_list_of_scores_keeps_its_infinities_apart_from_nan(tmp_path):
    """A list under a score key (a tolerance sweep's PSNRs) is written item by item as a single score is: ±inf as
    "inf"/"-inf", NaN as null; read back, ±inf and NaN again (it wrote every non-finite item as null)."""
    from hsicam.io import nan_for_null, write_json

    obj = {"sweeps": {"dz": {"psnr": [30.0, -math.inf, math.nan], "offset_um": [0.0, math.inf]}},
           "rows": [{"psnr": np.float32(-np.inf)}], "ssim": np.array([0.5, np.inf])}
    write_json(tmp_path / "t.json", obj)
    data = strict((tmp_path / "t.json").read_text(encoding="utf-8"))
    assert data["sweeps"]["dz"]["psnr"] == [30.0, "-inf", None] and data["rows"] == [{"psnr": "-inf"}]
    assert data["sweeps"]["dz"]["offset_um"] == [0.0, None]  # not a score key: null, as every non-finite value
    assert data["ssim"] == [0.5, "inf"]
    back = nan_for_null(data)
    assert back["sweeps"]["dz"]["psnr"][:2] == [30.0, -math.inf] and math.isnan(back["sweeps"]["dz"]["psnr"][2])
    assert back["ssim"] == [0.5, math.inf] and back["rows"][0]["psnr"] == -math.inf
