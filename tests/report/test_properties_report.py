"""Property tests of the result writers and the metrics: scene names of any text and scores of any value are
written so that each format reads them back (results.json by json, results.csv by csv, results.md's table by
the GitHub-flavoured Markdown cell rule, the report's table by an HTML parser); PSNR, RMSE, ERGAS, SSIM and SAM on
odd and 1-px sizes, one band or many, float64, batches whose items differ, against their formulas, scikit-image
and brute force (moved from optics/test_properties_spectral_sensor_metrics.py). The previews' properties are in
data/test_properties_formats.py."""

from __future__ import annotations

import csv
import html.parser
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from hsicam import metrics
from hsicam.engine.evaluate import SceneResult, summarize, write_results
from hsicam.io import mark_complete, nan_for_null
from hsicam.report.html import build_report
from property_settings import CORE_FEW, CORE_PROP, OUTPUT_PROPS, seeds

METRICS = ("psnr", "ssim", "sam", "ergas", "psnr_cube", "psnr_mst", "rmse")

NAMES = st.one_of(st.text(min_size=1, max_size=30),
                  st.sampled_from(["<script>alert(1)</script>", "a & b", "a|b", "a\\|b", "x\ny", "x\r\ny", "con",
                                   "'\"q\"'", " ", "mean", "é" * 300, "day1__scene", "**bold**"]))
SCORES = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                   st.sampled_from([float("nan"), float("inf"), -float("inf"), -0.0, 1e-300, 1e300, -12.5]))


def _gfm_cells(line: str) -> list[str]:
    """The cells of a GitHub-flavoured Markdown table row (the reference rule: a backslash escapes the character
    after it, an unescaped ``|`` separates cells; the leading and trailing pipes open and close the row)."""
    cells, cur, i = [], "", 0
    body = line.strip()
    assert body.startswith("|") and body.endswith("|"), line
    body = body[1:]
    while i < len(body):
        ch = body[i]
        if ch == "\\" and i + 1 < len(body):
            cur += body[i : i + 2]
            i += 2
            continue
        if ch == "|":
            cells.append(cur.strip())
            cur = ""
        else:
            cur += ch
        i += 1
    return cells


def _md_unescape(cell: str) -> str:
    return re.sub(r"\\(.)", r"\1", cell)


class _Tables(html.parser.HTMLParser):
    """Every table's cell texts, and the number of <script> elements."""

    def __init__(self):
        super().__init__()
        self.tables, self.scripts, self.cell = [], 0, None

    def handle_starttag(self, tag, attrs):
        if tag == "script":
            self.scripts += 1
        elif tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self.cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.tables[-1][-1].append(self.cell)
            self.cell = None

    def handle_data(self, data):
        if self.cell is not None:
            self.cell += data


def _refuse(constant: str):
    raise ValueError(f"not strict JSON: {constant}")


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def _folder(tmp_path_factory, names, scores, method="doe-learned") -> tuple[Path, dict]:
    d = tmp_path_factory.mktemp("ev")
    results = [SceneResult(n, {k: v for k in METRICS}, None, None, 0.25) for n, v in zip(names, scores)]
    summary = summarize(results, method=method, bands_nm=[500.0, 550.0, 600.0])
    write_results(d, summary)
    mark_complete(d, {"command": "test"})
    return d, summary


@OUTPUT_PROPS
@given(rows=st.lists(st.tuples(NAMES, SCORES), min_size=1, max_size=3), method=NAMES)
def test_results_files_and_report_read_back_any_name_and_score(tmp_path_factory, rows, method):
    names, scores = [n for n, _ in rows], [v for _, v in rows]
    d, summary = _folder(tmp_path_factory, names, scores, method)
    # results.json: strict JSON (a NaN score is null, ±inf "inf"/"-inf", as the docs say), which hsicam's readers
    # take as NaN and ±inf again (nan_for_null)
    data = nan_for_null(json.loads((d / "results.json").read_text(encoding="utf-8"), parse_constant=_refuse))
    assert [r["name"] for r in data["scenes"]] == names and data["method"] == method
    assert all(_same(r[k], v) for r, v in zip(data["scenes"], scores) for k in METRICS)
    # results.csv: the csv module reads the names back, and every score equals the one scored to %.6g
    with open(d / "results.csv", newline="", encoding="utf-8") as fh:
        table = list(csv.DictReader(fh))
    assert [r["name"] for r in table[:-1]] == names
    for row, v in zip(table, scores):
        assert all(_same(float(row[k]), float(f"{v:.6g}")) for k in METRICS)
    # results.md: every table row has the header's cell count, and its first cell is the name
    md = (d / "results.md").read_text(encoding="utf-8")
    lines = re.split(r"\r\n?|\n", md)
    start = lines.index("| scene | psnr | ssim | sam | ergas | runtime_s |")
    rows_md = lines[start : start + len(names) + 3]
    assert all(len(_gfm_cells(line)) == 6 for line in rows_md), rows_md
    assert [_md_unescape(_gfm_cells(line)[0]) for line in rows_md[2:-1]] == [re.sub(r"\r\n?|\n", " ", n).strip()
                                                                           for n in names]
    # the report: names escaped (the parser's text equals each name; the page's one script is its own),
    # a score shown in the table's format (±inf as inf / -inf), "n/a" when it has no value (NaN)
    page = _Tables()
    page.feed(build_report(d).read_text(encoding="utf-8"))
    assert page.scripts == 1
    body = page.tables[0][1:-1]
    assert [r[0] for r in body] == [re.sub(r"\r\n?", "\n", n) for n in names]  # HTML reads CR LF and CR as LF
    assert [r[1] for r in body] == [format(v, ".2f") if not math.isnan(v) else "n/a" for v in scores]


def test_a_pipe_or_line_break_in_a_scene_name_keeps_the_markdown_table_whole(tmp_path_factory):
    """Scene files may be named ``a|b.h5`` (a legal name on Linux and macOS): results.md's table held an extra
    cell in that row (7 instead of 6), and a line break ended the row half-way."""
    d, _ = _folder(tmp_path_factory, ["a|b", "x\ny", "c\\|d"], [30.0, 31.0, 32.0])
    lines = (d / "results.md").read_text(encoding="utf-8").split("\n")
    start = lines.index("| scene | psnr | ssim | sam | ergas | runtime_s |")
    rows = lines[start + 2 : start + 5]
    assert [len(_gfm_cells(r)) for r in rows] == [6, 6, 6]
    assert [_md_unescape(_gfm_cells(r)[0]) for r in rows] == ["a|b", "x y", "c\\|d"]
    assert [_gfm_cells(r)[1] for r in rows] == ["30.00", "31.00", "32.00"]


def test_a_scene_file_name_that_is_not_utf8_is_scored_and_named_by_its_escaped_bytes(tmp_path):
    """An old Latin-1 file name (b"sc\\xe8ne.h5", held by Python as a lone surrogate) stopped `hsicam evaluate
    --data` with "UnicodeEncodeError: surrogates not allowed" (the capture-noise seed, then the results writers)."""
    import os

    from cli_helpers import assert_ok, run_cli_in_process
    from hsicam.config import load_config
    from hsicam.data.datasets import displayable_name, scene_names
    from hsicam.data.formats import write_cube_h5

    assert displayable_name(os.fsdecode(b"sc\xe8ne")) == "sc\\xe8ne" and displayable_name("scène") == "scène"
    assert displayable_name("a\udc00b") == "a\\udc00b"  # a surrogate no byte maps to
    data = tmp_path / "data"
    data.mkdir()
    bands = load_config("tiny").bands.to_bands()
    cube = np.random.default_rng(0).random((len(bands), 48, 48)).astype(np.float32)
    latin1 = os.path.join(os.fsencode(data), b"sc\xe8ne.h5")
    try:
        write_cube_h5(os.fsdecode(latin1), cube, bands)
    except (OSError, UnicodeError):
        pytest.skip("this file system refuses a file name that is not UTF-8")
    assert scene_names([os.fsdecode(latin1)], data) == ["sc\\xe8ne"]
    out = tmp_path / "ev"
    assert_ok(run_cli_in_process("evaluate", "--config", "tiny", "--method", "dd-cassi-gaptv", "--set",
                                 "baselines.gaptv.iterations=2", "--data", str(data), "--out", str(out), "--save"))
    row = json.loads((out / "results.json").read_text(encoding="utf-8"))["scenes"][0]
    assert (row["name"], row["path"]) == ("sc\\xe8ne", "sc\\xe8ne.h5")
    with open(out / "results.csv", newline="", encoding="utf-8") as f:
        assert next(csv.DictReader(f))["name"] == "sc\\xe8ne"
    assert sorted(p.name for p in (out / "cubes").iterdir()) == ["sc\\xe8ne_estimate.h5", "sc\\xe8ne_truth.h5"]


# ------------------------------------------------------------------------------------------------
# Metrics
# ------------------------------------------------------------------------------------------------
def _pair(seed, b, c, h, w, dtype=torch.float32, noise=0.1):
    g = torch.Generator().manual_seed(seed)
    y = torch.rand(b, c, h, w, generator=g, dtype=torch.float64)
    x = (y + noise * torch.randn(b, c, h, w, generator=g, dtype=torch.float64)).clamp(0, 1)
    return x.to(dtype), y.to(dtype)


@CORE_PROP
@given(seed=seeds, b=st.integers(1, 3), c=st.integers(1, 7), h=st.integers(1, 13), w=st.integers(1, 13),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_psnr_rmse_ergas_are_the_formulas(seed, b, c, h, w, dtype):
    """PSNR per band / cube, RMSE and ERGAS against scikit-image and numpy, per batch item."""
    from skimage.metrics import peak_signal_noise_ratio as sk_psnr

    x, y = _pair(seed, b, c, h, w, dtype)
    xn, yn = x.double().numpy(), y.double().numpy()
    for i in range(b):
        bands = [sk_psnr(yn[i, k], xn[i, k], data_range=1.0) for k in range(c)]
        bands = [min(v, 300.0) for v in bands]
        assert float(metrics.psnr_per_band(x, y)[i]) == pytest.approx(np.mean(bands), rel=1e-9)
        assert float(metrics.psnr_cube(x, y)[i]) == pytest.approx(min(sk_psnr(yn[i], xn[i], data_range=1.0), 300.0), rel=1e-9)
        assert float(metrics.rmse(x, y)[i]) == pytest.approx(np.sqrt(np.mean((xn[i] - yn[i]) ** 2)), rel=1e-9, abs=1e-15)
        rb = np.sqrt(((xn[i] - yn[i]) ** 2).mean(axis=(1, 2)))
        mb = np.maximum(np.abs(yn[i].mean(axis=(1, 2))), 1e-12)
        assert float(metrics.ergas(x, y)[i]) == pytest.approx(100 * np.sqrt(np.mean((rb / mb) ** 2)), rel=1e-9)
        # batch item i of the batched call is the call on item i alone
        assert float(metrics.psnr_per_band(x[i], y[i])[0]) == float(metrics.psnr_per_band(x, y)[i])


@CORE_FEW
@given(seed=seeds, b=st.integers(1, 2), c=st.integers(1, 3), h=st.integers(11, 23), w=st.integers(11, 23),
       dtype=st.sampled_from([torch.float32, torch.float64]), noise=st.sampled_from([0.0, 0.02, 0.3]))
def test_ssim_is_scikit_image(seed, b, c, h, w, dtype, noise):
    """SSIM = skimage structural_similarity(gaussian_weights, σ 1.5, population covariance, range 1), mean over
    bands, for odd, prime and non-square sizes down to the 11-px window."""
    from skimage.metrics import structural_similarity

    x, y = _pair(seed, b, c, h, w, dtype, noise)
    got = metrics.ssim(x, y)
    for i in range(b):
        ref = np.mean([structural_similarity(y[i, k].double().numpy(), x[i, k].double().numpy(), gaussian_weights=True,
                                             sigma=1.5, use_sample_covariance=False, data_range=1.0)
                       for k in range(c)])
        assert float(got[i]) == pytest.approx(ref, abs=1e-6)


@CORE_FEW
@given(seed=seeds, h=st.integers(11, 20), w=st.integers(11, 20))
def test_ssim_chunked_path_equals_matrix_path(seed, h, w):
    """The large-image path (shifted multiply-adds, bands in chunks) gives the matrix path's value."""
    x, y = _pair(seed, 2, 5, h, w, torch.float64)
    ref = metrics.ssim(x, y)
    old = (metrics._SSIM_MATRIX_MAX_PX, metrics._SSIM_CHUNK_BYTES)
    try:
        metrics._SSIM_MATRIX_MAX_PX, metrics._SSIM_CHUNK_BYTES = 1, 5 * 2 * h * w * 8 * 2  # 2 bands per chunk
        got = metrics.ssim(x, y)
    finally:
        metrics._SSIM_MATRIX_MAX_PX, metrics._SSIM_CHUNK_BYTES = old
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


@CORE_PROP
@given(seed=seeds, b=st.integers(1, 3), c=st.integers(1, 8), h=st.integers(1, 6), w=st.integers(1, 6),
       zero_frac=st.sampled_from([0.0, 0.3, 1.0]), scale=st.sampled_from([1e-30, 1.0, 1e30]),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_sam_is_the_angle_brute_force(seed, b, c, h, w, zero_frac, scale, dtype):
    """SAM per pixel = arccos(<x, y> / |x||y|) in degrees (numpy, long double not needed at these scales after
    scaling), all-zero truth excluded, all-zero estimate 90°; mean per cube; NaN when nothing is defined."""
    rng = np.random.default_rng(seed)
    y = rng.random((b, c, h, w)) * (rng.random((b, 1, h, w)) >= zero_frac)
    x = np.abs(y + 0.2 * rng.normal(size=y.shape)) * (rng.random((b, 1, h, w)) > 0.2)
    x, y = x * scale, y * scale
    xt, yt = torch.tensor(x, dtype=dtype), torch.tensor(y, dtype=dtype)
    xs, ys = xt.double().numpy() / scale, yt.double().numpy() / scale  # what the metric sees, rescaled
    got = metrics.sam_degrees(xt, yt).numpy()
    for i in range(b):
        angles = []
        for r in range(h):
            for s in range(w):
                u, v = xs[i, :, r, s], ys[i, :, r, s]
                if not np.any(v != 0):
                    continue
                if not np.any(u != 0):
                    angles.append(90.0)
                    continue
                cos = np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))
                angles.append(math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
        if not angles:
            assert math.isnan(got[i])
        else:
            assert got[i] == pytest.approx(np.mean(angles), abs=1e-5)


@CORE_FEW
@given(seed=seeds, b=st.integers(1, 3), h=st.integers(11, 15), w=st.integers(11, 15), c=st.integers(1, 4))
def test_all_metrics_per_item_equals_alone(seed, b, h, w, c):
    """all_metrics of a batch whose items differ (one item's truth all zero) = all_metrics of each item alone."""
    x, y = _pair(seed, b, c, h, w)
    y[0] = 0
    batch = metrics.all_metrics(x, y)
    for i in range(b):
        alone = metrics.all_metrics(x[i : i + 1], y[i : i + 1])
        for k, v in batch.items():
            assert v[i] == pytest.approx(alone[k][0], rel=1e-12, nan_ok=True), k


@CORE_PROP
@given(seed=seeds, n=st.integers(1, 300), q=st.floats(0.0, 1.0), ties=st.booleans())
def test_sam_breakdown_quantile_is_torch_quantile(seed, n, q, ties):
    """The edge threshold of sam_breakdown = torch.quantile (linear interpolation) where torch's applies."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.rand(n, generator=gen, dtype=torch.float64)
    if ties:
        t = (t * 4).floor()
    torch.testing.assert_close(metrics._quantile(t, q), torch.quantile(t, q), rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_sam_breakdown_of_an_image_beyond_2_24_pixels():
    """A 4097×4096 image (2²⁴ + 4096 px): torch.quantile refused it ("quantile() input tensor is too large") and
    sam_breakdown stopped with a RuntimeError. A vertical step edge: the top 20 % of the gradient are its two
    columns' neighbours (numpy's quantile as the reference), SAM 0 for an estimate equal to the truth."""
    h, w = 4097, 4096
    y = torch.full((1, 1, h, w), 0.5)
    y[..., w // 2 :] = 1.0
    y[..., : h // 3, :] += torch.linspace(0, 0.1, w)  # a ramp over the top third: gradients of several sizes
    got = metrics.sam_breakdown(y, y)
    assert got["all"] == [0.0] and got["edges"] == [0.0] and got["dark_fraction"] == [0.0]
    gy, gx = np.gradient(y[0, 0].double().numpy())
    grad = np.sqrt(gx * gx + gy * gy)
    assert float(metrics._quantile(torch.from_numpy(grad).flatten(), 0.8)) == pytest.approx(np.quantile(grad, 0.8),
                                                                                             rel=1e-12)
