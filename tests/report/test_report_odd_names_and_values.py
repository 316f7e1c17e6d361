"""Review 55 (reports, progress): each test checks one measured defect against an independent reference."""

from __future__ import annotations

import json
import urllib.parse
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from html_helpers import PageParts
from hsicam.data.formats import write_cube_h5
from hsicam.io import mark_complete
from hsicam.report.html import build_report
from hsicam.spectral import Bands

MEAN = {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}


def _evaluation(tmp_path: Path, data: dict, cubes: tuple[str, ...] = ()) -> Path:
    """A complete evaluation folder holding ``data`` as results.json and, for each name of ``cubes``, the
    estimate and truth cubes `hsicam evaluate --save` writes (cubes/NAME_estimate.h5, NAME_truth.h5)."""
    d = tmp_path / "ev"
    d.mkdir()
    (d / "results.json").write_text(json.dumps(data), encoding="utf-8")
    bands = Bands.from_centers(data["bands_nm"]) if "bands_nm" in data else None
    rng = np.random.default_rng(0)
    for name in cubes:
        truth = rng.random((len(bands), 12, 12)).astype(np.float32)
        write_cube_h5(d / "cubes" / f"{name}_truth.h5", truth, bands)
        write_cube_h5(d / "cubes" / f"{name}_estimate.h5", 0.9 * truth, bands)
    mark_complete(d, {"command": "test"})
    return d


def test_report_images_of_scenes_named_with_url_characters_load(tmp_path):
    """A scene's file name with '#', '?' or '%' (``scene #1?v%41.h5``): every <img src> of the page, resolved
    as a browser resolves a relative URL against the page's, names a file that exists (the src was the raw
    name: '#' began a fragment, '?' a query, '%41' decoded to 'A', so all its figures were broken)."""
    name = "scene #1?v%41"
    data = {"method": "m", "scenes": [{"name": name, **MEAN}], "mean": MEAN, "conventions": {},
            "bands_nm": [500.0, 550.0, 600.0]}
    index = build_report(_evaluation(tmp_path, data, cubes=(name,)))
    images = PageParts(index.read_text(encoding="utf-8")).images
    assert len(images) == 2  # the scene's comparison and its error maps
    for src in images:
        url = urllib.parse.urljoin(index.resolve().as_uri(), src)
        assert Path(urllib.parse.unquote(urllib.parse.urlparse(url).path)).is_file(), src


def test_report_table_shows_a_score_without_value_as_n_a(tmp_path):
    """A scene whose SAM is undefined (NaN in results.json: its truth is zero at every scored pixel,
    ``sam_undefined``) and a null runtime read "n/a" in the report's table, not "nan" / "None"."""
    scenes = [{"name": "a", **MEAN, "runtime_s": 1.5}, {"name": "dark", **MEAN, "sam": float("nan"), "runtime_s": None}]
    data = {"method": "m", "scenes": scenes, "mean": {**MEAN, "runtime_s": 1.5}, "sam_undefined": ["dark"],
            "conventions": {}}
    text = build_report(_evaluation(tmp_path, data)).read_text(encoding="utf-8")
    assert "NaN" in (tmp_path / "ev" / "results.json").read_text()  # as json.dump writes a float('nan')
    cells = PageParts(text).cells
    cols = 5  # scene, PSNR, SSIM, SAM, runtime: ERGAS and PSNR MST, which no row records, are left out
    rows = [cells[i : i + cols] for i in range(0, len(cells), cols)]
    assert [r[0] for r in rows] == ["a", "dark", "mean"]
    assert [r[3] for r in rows] == ["5.00", "n/a", "5.00"]  # SAM
    assert [r[4] for r in rows] == ["1.500", "n/a", "1.500"]  # runtime (s)
    assert "<th>ERGAS</th>" not in text and "<th>runtime (s)</th>" in text


def test_report_table_shows_a_score_one_row_lacks_as_n_a(tmp_path):
    """A results.json edited so that one scene has no "psnr" key drew an empty cell (a helper's hunt, session 71):
    now "n/a", as a score without value; the column stays, since other rows have it."""
    scenes = [{"name": "a", **MEAN}, {"name": "b", "ssim": 0.8, "sam": 4.0}]
    data = {"method": "m", "scenes": scenes, "mean": MEAN, "conventions": {}}
    cells = PageParts(build_report(_evaluation(tmp_path, data)).read_text(encoding="utf-8")).cells
    rows = [cells[i : i + 4] for i in range(0, len(cells), 4)]  # scene, PSNR, SSIM, SAM
    assert rows == [["a", "30.00", "0.9000", "5.00"], ["b", "n/a", "0.8000", "4.00"], ["mean", "30.00", "0.9000", "5.00"]]


def test_report_writes_any_json_value_of_a_hand_edited_file_as_text(tmp_path):
    """experiment.json's 'seeds' and results.json's 'conventions' values, edited by hand: a markup string is
    shown as text (it was written into the page raw, a <script> element ran), a number is shown
    (``html.escape(1)`` raised AttributeError, a traceback instead of a report)."""
    markup = "<script>alert(1)</script>"
    d = tmp_path / "ex"
    d.mkdir()
    (d / "experiment.json").write_text(json.dumps(
        {"experiment": "compare", "scale": "tiny", "seeds": markup, "scenes": ["a"],
         "rows": [{"method": "x", **MEAN}], "conventions": {"psnr": 1}}))
    mark_complete(d, {"command": "test"})
    text = build_report(d).read_text(encoding="utf-8")

    class Text(HTMLParser):
        scripts, data = 0, ""

        def handle_starttag(self, tag, attrs):
            self.scripts += tag == "script"

        def handle_data(self, data):
            self.data += data

    page = Text()
    page.feed(text)
    assert page.scripts == 1  # the report's own image check only
    assert f"seeds {markup}" in page.data and "psnr: 1" in page.data


def test_the_cgroup_memory_limit_is_the_lowest_over_the_process_cgroup_and_its_ancestors(tmp_path):
    """A limit set on a nested cgroup (a systemd slice, a job scheduler's) bounds the process too; only the top
    files were read before, so such a limit was not seen. cgroup v2 and v1 layouts as the kernel writes them."""
    from hsicam.memory import _cgroup_memory_limit_bytes as limit

    def tree(files: dict[str, str], proc: str) -> tuple[Path, Path]:
        root = tmp_path / f"sys{len(list(tmp_path.iterdir()))}"
        for rel, text in files.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text(text + "\n")
        (root / "proc_cgroup").write_text(proc)
        return root / "proc_cgroup", root

    # v2: the job's cgroup sets 1 GiB, its parent and the top none ("max")
    assert limit(*tree({"memory.max": "max", "jobs/memory.max": "max", "jobs/42/memory.max": str(2**30)},
                       "0::/jobs/42\n")) == 2**30
    # v1: the parent's limit is the lower one; the own cgroup writes v1's huge "no limit"
    assert limit(*tree({"memory/memory.limit_in_bytes": "9223372036854771712",
                        "memory/slice/memory.limit_in_bytes": str(512 * 2**20),
                        "memory/slice/task/memory.limit_in_bytes": "9223372036854771712"},
                       "5:cpu,cpuacct:/slice/task\n4:memory:/slice/task\n0::/\n")) == 512 * 2**20
    # a container's own cgroup mounted at the top ("0::/" and the top file): as before
    assert limit(*tree({"memory.max": str(3 * 2**30)}, "0::/\n")) == 3 * 2**30
    # no limit anywhere, or nothing readable
    assert limit(*tree({"memory.max": "max"}, "0::/a\n")) is None
    assert limit(tmp_path / "none", tmp_path / "none") is None
