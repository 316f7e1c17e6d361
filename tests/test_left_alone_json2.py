"""Follow-ups of the strict-JSON files (tests/test_strict_json.py): the JSON that hsicam embeds in other files (our
HDF5 cube's ``metadata_json``, the ENVI header's ``hsicam metadata`` line) is strict too, and both readers read the
new files and the older ones (``NaN``/``Infinity`` literals) alike; the metric conventions say what the files hold."""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import torch

from hsicam.data import read_cube
from hsicam.data.formats import ENVI_METADATA_KEY, write_cube_h5, write_envi
from hsicam.engine.cfa_offset import CfaOffsetEstimate
from hsicam.engine.evaluate import SceneResult, summarize, write_results
from hsicam.metrics import CONVENTIONS, all_metrics
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
