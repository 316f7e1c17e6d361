"""Property tests of the result and preview writers: scene names of any text and scores of any value are
written so that each format reads them back (results.json by json, results.csv by csv, results.md's table by
the GitHub-flavoured Markdown cell rule, the report's table by an HTML parser), and previews of cubes of any
band count and size render to finite images of the documented size."""

from __future__ import annotations

import csv
import html.parser
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hsicam.engine.evaluate import SceneResult, summarize, write_results
from hsicam.errors import InputError
from hsicam.io import mark_complete, nan_for_null
from hsicam.report.html import build_report
from hsicam.spectral import Bands

SETTINGS = settings(derandomize=True, database=None, deadline=None, max_examples=30,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
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


@SETTINGS
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


# -- previews ---------------------------------------------------------------------------------------------
def _preview_side(side: int, longest: int, max_side: int) -> int:
    """The documented preview size of one side: step×step blocks (step = ceil(longest / max_side)), at least
    one block (the whole side) when the side is shorter than a step."""
    step = max(1, math.ceil(longest / max_side))
    return max(1, side // step)


CUBES = st.tuples(st.integers(1, 8), st.integers(1, 70), st.integers(1, 70),
                  st.sampled_from(["random", "zero", "hot", "tiny", "huge"]))


@SETTINGS
@given(spec=CUBES)
def test_previews_of_any_cube_are_finite_images_of_the_documented_size(spec):
    from hsicam.data.preview import preview_grey, preview_rgb, renderable

    c, h, w, kind = spec
    rng = np.random.default_rng(c * 1000 + h * 10 + w)
    cube = {"random": lambda: rng.random((c, h, w)), "zero": lambda: np.zeros((c, h, w)),
            "tiny": lambda: rng.random((c, h, w)) * 1e-37, "huge": lambda: rng.random((c, h, w)) * 3e38,
            "hot": lambda: np.zeros((c, h, w))}[kind]().astype(np.float32)
    if kind == "hot":
        cube[rng.integers(c), rng.integers(h), rng.integers(w)] = 1.0
    bands = Bands.from_centers(np.linspace(420.0, 720.0, c)) if c > 1 else Bands.from_centers([550.0])
    max_side = 16
    shape = (_preview_side(h, max(h, w), max_side), _preview_side(w, max(h, w), max_side), 3)
    grey = preview_grey(cube, max_side)
    assert grey.shape == shape and np.isfinite(grey).all() and grey.min() >= 0 and grey.max() <= 1
    if not renderable(bands):
        with pytest.raises(InputError, match="fewer than 2 bands"):
            preview_rgb(cube, bands, max_side)
        return
    if not cube.any():
        with pytest.raises(InputError, match="all zeros"):
            preview_rgb(cube, bands, max_side)
        return
    rgb = preview_rgb(cube, bands, max_side)
    assert rgb.shape == shape and np.isfinite(rgb).all()


def test_a_strip_cube_is_previewed(tmp_path):
    """A 4×1000 px cube (shorter than one 6-px block on its short side) crashed ``hsicam data show`` with
    numpy's "zero-size array to reduction operation maximum"; its contact sheet now holds a 1×166 render."""
    from PIL import Image

    from hsicam.data.preview import CONTACT_SHEET, preview_rgb, write_preview

    cube = np.random.default_rng(0).random((31, 4, 1000)).astype(np.float32)
    rgb = preview_rgb(cube, Bands.from_centers(np.linspace(400.0, 700.0, 31)))
    assert rgb.shape == (1, 166, 3) and np.isfinite(rgb).all()
    np.save(tmp_path / "strip.npy", cube)
    written = write_preview(tmp_path / "strip.npy", tmp_path / "out")
    assert (tmp_path / "out" / CONTACT_SHEET) in written
    for p in written:
        with Image.open(p) as im:
            im.load()
            assert min(im.size) > 0 and np.isfinite(np.asarray(im, dtype=np.float64)).all()


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
