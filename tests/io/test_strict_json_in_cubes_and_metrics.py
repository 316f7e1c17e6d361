"""Follow-ups of the strict-JSON files (tests/io/test_strict_json.py): the JSON that hsicam embeds in other files (our
HDF5 cube's ``metadata_json``, the ENVI header's ``hsicam metadata`` line) is strict too, and both readers read the
new files and the older ones (``NaN``/``Infinity`` literals) alike; the metric conventions say what the files hold;
ERGAS is undefined (NaN, as an undefined SAM) for a truth with a band whose mean is 0, where the floor of that mean
at 1e-12 gave values of 10¹¹ and more."""

from __future__ import annotations

import csv
import json
import math

import h5py
import numpy as np
import pytest
import torch

from html_helpers import PageParts
from hsicam.data import read_cube
from hsicam.data.formats import ENVI_METADATA_KEY, write_cube_h5, write_envi
from hsicam.engine.cfa_offset import CfaOffsetEstimate
from hsicam.engine.evaluate import SceneResult, summarize, write_results
from hsicam.io import mark_complete
from hsicam.metrics import CONVENTIONS, all_metrics, ergas
from hsicam.report.html import build_report
from hsicam.spectral import Bands


def _refuse(constant: str):
    raise ValueError(f"not strict JSON: {constant}")


def strict(text: str):
    """``text`` parsed as a strict parser does (JavaScript's JSON.parse): NaN, Infinity and -Infinity refused."""
    return json.loads(text, parse_constant=_refuse)


BANDS = Bands.from_centers([450.0, 550.0, 650.0])


def _cube() -> np.ndarray:
    return np.random.default_rng(0).uniform(0.1, 1.0, (3, 6, 5)).astype(np.float32)


def _metadata() -> dict:
    """A cube's metadata with values that are not finite: a NaN score, and reconstruct's record of a --cfa-offset auto
    estimate whose chosen phase explains the capture exactly (residual 0: the contrast (median − best) / best is inf)."""
    est = CfaOffsetEstimate((0, 1), {"0,0": 0.5, "0,1": 0.0, "1,0": 0.25, "1,1": 0.5}, (0, 0, 64, 64), 8)
    assert est.contrast == math.inf
    return {"command": "reconstruct", "sam": float("nan"), "psnr": np.float32(31.5), "cfa_offset": [0, 1],
            "cfa_offset_estimate": est.as_dict()}


def _check_read(meta: dict, contrast) -> None:
    """What read_cube returns of :func:`_metadata`: the NaN score as NaN (null read back), the rest as written."""
    assert math.isnan(meta["sam"]) and meta["psnr"] == 31.5 and meta["cfa_offset"] == [0, 1]
    rec = meta["cfa_offset_estimate"]
    assert rec["offset"] == [0, 1] and rec["residuals"]["0,1"] == 0.0 and rec["ambiguous"] is False
    assert rec["contrast"] == contrast


def test_cube_h5_metadata_json_is_strict_json_and_old_files_still_read(tmp_path):
    """write_cube_h5 kept the metadata with Python's ``NaN``/``Infinity``, which a strict parser (h5py + JSON.parse,
    jq, serde) refuses: now null there. read_cube reads the new file and one as older hsicam wrote it alike."""
    path = write_cube_h5(tmp_path / "c.h5", _cube(), BANDS, _metadata())
    with h5py.File(path, "r") as f:  # the attribute as any HDF5 tool reads it
        raw = f.attrs["metadata_json"]
    data = strict(raw.decode() if isinstance(raw, bytes) else str(raw))
    assert data["sam"] is None and data["cfa_offset_estimate"]["contrast"] is None and data["psnr"] == 31.5
    cube, bands, meta = read_cube(path)
    np.testing.assert_array_equal(cube, _cube())
    _check_read(meta, None)
    with h5py.File(path, "a") as f:  # the same file as older hsicam wrote it: NaN and Infinity literals
        rec = {**data["cfa_offset_estimate"], "contrast": math.inf}
        f.attrs["metadata_json"] = json.dumps({**data, "sam": math.nan, "cfa_offset_estimate": rec}, sort_keys=True)
    with h5py.File(path, "r") as f:
        assert "NaN" in str(f.attrs["metadata_json"]) and "Infinity" in str(f.attrs["metadata_json"])
    _check_read(read_cube(path)[2], math.inf)


def _header_metadata(hdr) -> str:
    """The JSON of the header's ``hsicam metadata = {...}`` line, read as plain text (ENVI's braces taken off)."""
    lines = [x for x in hdr.read_text(encoding="utf-8").splitlines() if x.startswith(f"{ENVI_METADATA_KEY} = ")]
    assert len(lines) == 1
    value = lines[0].split(" = ", 1)[1].strip()
    assert value.startswith("{") and value.endswith("}")
    return value[1:-1]


def test_envi_metadata_line_is_strict_json_and_old_headers_still_read(tmp_path):
    """write_envi's ``hsicam metadata`` header line held ``NaN``/``Infinity`` too: now null; read_cube reads it, and a
    header as older hsicam wrote it, alike."""
    hdr, _ = write_envi(tmp_path / "c.hdr", _cube(), BANDS, metadata=_metadata())
    text = _header_metadata(hdr)
    data = strict(text)
    assert data["sam"] is None and data["cfa_offset_estimate"]["contrast"] is None and data["psnr"] == 31.5
    cube, _, meta = read_cube(hdr)
    np.testing.assert_array_equal(cube, _cube())
    _check_read(meta, None)
    old = text.replace('"sam":null', '"sam":NaN').replace('"contrast":null', '"contrast":Infinity')
    assert old != text
    hdr.write_text(hdr.read_text(encoding="utf-8").replace(text, old), encoding="utf-8")  # the CRC is the data's
    _check_read(read_cube(hdr)[2], math.inf)


def _ergas_numpy(est: np.ndarray, truth: np.ndarray) -> float:
    """ERGAS of one (C, H, W) pair, resolution ratio 1: 100·sqrt(mean_b (RMSE_b / μ_b)²), NaN when a μ_b is 0."""
    rmse_b = np.sqrt(((est - truth) ** 2).mean(axis=(1, 2)))
    mu = truth.mean(axis=(1, 2))
    return float("nan") if np.any(mu == 0) else float(100 * np.sqrt(np.mean((rmse_b / mu) ** 2)))


def test_ergas_on_cubes_whose_band_means_are_positive_is_the_formula():
    """Unchanged where every band's truth mean is > 0 (small ones too): the formula, computed with numpy."""
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.0, 1.0, (3, 5, 13, 12))
    truth[1, 2] *= 1e-6  # a dim band, not a dark one
    truth[2, 0, 1:, :] = 0.0  # a band dark but for one row
    est = np.clip(truth + rng.normal(0, 0.05, truth.shape), 0, 1)
    got = ergas(torch.from_numpy(est), torch.from_numpy(truth))
    for i in range(3):
        assert got[i].item() == pytest.approx(_ergas_numpy(est[i], truth[i]), rel=1e-12)
    assert all(map(math.isfinite, all_metrics(torch.from_numpy(est), torch.from_numpy(truth))["ergas"]))


def _scenes():
    """A lit scene (estimate 0.9 × truth) and one whose first band is dark (zero) in the truth, with an error of
    0.01 there: ERGAS divided it by the floor 1e-12 (5.8·10¹¹)."""
    rng = np.random.default_rng(2)
    lit = rng.uniform(0.2, 1.0, (3, 16, 16))
    dark = rng.uniform(0.2, 1.0, (3, 16, 16))
    dark[0] = 0.0
    est_dark = 0.9 * dark
    est_dark[0] = 0.01
    return {"lit": (0.9 * lit, lit), "dark": (est_dark, dark)}


def test_ergas_of_a_truth_with_a_dark_band_is_undefined_through_all_metrics_and_the_results_files(tmp_path):
    """A truth with a band zero at every pixel has no ERGAS: NaN from all_metrics (not the worst score, as a broken
    estimate's), listed in ergas_undefined, null in results.json, nan in results.csv and results.md, "n/a" in the
    report, and the means over the other scenes, as for an undefined SAM; the other metrics are as before."""
    scenes = _scenes()
    rows = []
    for name, (est, truth) in scenes.items():
        m = {k: v[0] for k, v in all_metrics(torch.from_numpy(est)[None], torch.from_numpy(truth)[None]).items()}
        rows.append(SceneResult(name, m, None, None, 0.5, sam_excluded_px=0))
    by = {r.name: r.metrics for r in rows}
    assert by["lit"]["ergas"] == pytest.approx(_ergas_numpy(*scenes["lit"]), rel=1e-9)
    assert math.isnan(by["dark"]["ergas"]) and math.isnan(_ergas_numpy(*scenes["dark"]))
    assert math.isfinite(by["dark"]["psnr"]) and math.isfinite(by["dark"]["sam"])
    # a broken estimate (a NaN pixel) of a lit truth is still the worst ERGAS; of the dark-band truth undefined
    broken = torch.from_numpy(scenes["lit"][0]).clone()[None]
    broken[0, 1, 2, 2] = math.nan
    assert all_metrics(broken, torch.from_numpy(scenes["lit"][1])[None])["ergas"] == [math.inf]
    out = tmp_path / "ev"
    out.mkdir()
    write_results(out, summarize(rows, method="doe-learned"))
    mark_complete(out, {"command": "evaluate"})
    data = strict((out / "results.json").read_text(encoding="utf-8"))
    js = {r["name"]: r for r in data["scenes"]}
    assert js["dark"]["ergas"] is None and data["ergas_undefined"] == ["dark"] and "sam_undefined" not in data
    assert data["mean"]["ergas"] == pytest.approx(by["lit"]["ergas"], rel=1e-12)  # over the scenes that have one
    assert data["mean"]["psnr"] == pytest.approx((by["lit"]["psnr"] + by["dark"]["psnr"]) / 2)
    with open(out / "results.csv", newline="", encoding="utf-8") as fh:
        table = {r["name"]: r for r in csv.DictReader(fh)}
    assert table["dark"]["ergas"] == "nan" and float(table["mean"]["ergas"]) == pytest.approx(by["lit"]["ergas"], rel=1e-5)
    md = (out / "results.md").read_text(encoding="utf-8")
    assert "- ERGAS undefined (a band of the truth is zero at every scored pixel) for dark" in md
    # its dark band is estimated 0.01, not exactly 0: no band scored 300 dB, so no note says one did (session 76's hunt;
    # the note for a band estimated exactly 0: tests/engine/test_scoring_and_linear_step_edge_cases.py)
    assert "300 dB where the estimate" not in md and "exact_zero_bands" not in data
    dark_row = next(line for line in md.splitlines() if line.startswith("| dark |"))
    assert dark_row.split("|")[5].strip() == "nan"  # | scene | psnr | ssim | sam | ergas | runtime_s |
    cells = PageParts(build_report(out).read_text(encoding="utf-8")).cells
    ergas_col = [cells[i + 4] for i in range(0, len(cells), 7)]  # scene, PSNR, SSIM, SAM, ERGAS, PSNR MST, runtime
    assert ergas_col == [f"{by['lit']['ergas']:.2f}", "n/a", f"{by['lit']['ergas']:.2f}"]
    text = data["conventions"]["ergas"]  # the conventions say so
    assert text == CONVENTIONS["ergas"] and "undefined when a band's mean_b is 0" in text
    assert "NaN (null in the JSON files, nan in results.csv and results.md; results.json lists such scenes in " \
           "ergas_undefined" in text


def test_sam_convention_says_what_memory_and_results_json_hold(tmp_path):
    """CONVENTIONS["sam"] (copied into results.json) said "NaN when the truth is zero at every pixel", while the file
    holds null there: the text now names both, NaN as all_metrics returns it and null as results.json holds it."""
    est, truth = np.full((3, 16, 16), 0.1), np.zeros((3, 16, 16))
    m = {k: v[0] for k, v in all_metrics(torch.from_numpy(est)[None], torch.from_numpy(truth)[None]).items()}
    assert math.isnan(m["sam"])  # in memory: NaN
    write_results(tmp_path, summarize([SceneResult("dark", m, None, None, 0.5, sam_excluded_px=256)]))
    data = strict((tmp_path / "results.json").read_text(encoding="utf-8"))
    assert data["scenes"][0]["sam"] is None and data["sam_undefined"] == ["dark"]  # in the file: null
    text = data["conventions"]["sam"]
    assert text == CONVENTIONS["sam"]
    assert "undefined when the truth is zero at every pixel: NaN (null in the JSON files, nan in results.csv and " \
           "results.md; results.json lists such scenes in sam_undefined" in text
    assert "NaN when" not in text
    assert "nan" in (tmp_path / "results.csv").read_text(encoding="utf-8").splitlines()[1].split(",")
