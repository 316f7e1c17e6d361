"""`hsicam data synth` / `hsicam data show` through the installed entry point."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from hsicam.data import read_cube
from hsicam.data.synthetic import generate_dataset
from hsicam.spectral import Bands

HSICAM = Path(sys.executable).parent / "hsicam"

pytestmark = pytest.mark.skipif(not HSICAM.exists(), reason="hsicam entry point not installed")


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(HSICAM), *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_synth_then_show(tmp_path):
    r = run("data", "synth", "--n", "3", "--size", "40", "--seed", "11", "--out", "ds", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "ds"
    files = sorted(p.name for p in out.iterdir())
    assert files == ["manifest.json", "scene_0000.h5", "scene_0001.h5", "scene_0002.h5"]
    cube, bands, _ = read_cube(out / "scene_0001.h5")
    assert cube.shape == (31, 40, 40) and bands.matches(Bands.paper())

    # a second process draws the same bytes as this one (determinism across processes)
    generate_dataset(tmp_path / "here", n=3, size=40, seed=11, progress=False)
    for name in files:
        assert (out / name).read_bytes() == (tmp_path / "here" / name).read_bytes(), name

    again = run("data", "synth", "--n", "3", "--size", "40", "--seed", "11", "--out", "ds", cwd=tmp_path)
    assert again.returncode == 0 and "already" in again.stdout

    r = run("data", "synth", "--n", "2", "--size", "40", "--seed", "11", "--split", "heldout", "--out", "ho",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "held-out scenes" in r.stdout and "nist-philips, rawtoaces" in r.stdout
    _, _, meta = read_cube(tmp_path / "ho" / "scene_0000.h5")
    assert meta["split"] == "heldout" and meta["holdout_sources"] == ["nist-philips", "rawtoaces"]

    r = run("data", "show", "ds", "--out", "preview", "--heldout", "ho", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    sheet, plot = tmp_path / "preview" / "contact_sheet.png", tmp_path / "preview" / "mean_spectra.png"
    gamut = tmp_path / "preview" / "spectral_gamut.png"
    assert "preview/spectral_gamut.png" in r.stdout
    for png in (sheet, plot, gamut):
        img = iio.imread(png)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
        assert np.asarray(img[..., :3]).std() > 5  # not blank
    assert not [p for p in (tmp_path / "preview").iterdir() if p.name.startswith(".")]  # atomic: no leftovers


def test_synth_holdout_flag_and_sources(tmp_path):
    r = run("data", "synth", "--n", "1", "--size", "24", "--holdout-sources", "cie-tcs,rawtoaces", "--out", "a",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _, _, meta = read_cube(tmp_path / "a" / "scene_0000.h5")
    assert meta["holdout_sources"] == ["cie-tcs", "rawtoaces"] and meta["split"] == "train"
    r = run("data", "sources", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    ids = [ln.split()[0] for ln in r.stdout.splitlines()]
    assert {"rawtoaces", "cie-tcs", "nist-philips", "led-model", "otsu2018"} <= set(ids)


@pytest.mark.parametrize("args,words", [
    (("data", "show", "missing_dir"), ["missing_dir", "no such"]),
    (("data", "synth", "--n", "0", "--out", "x"), ["--n"]),
    (("data", "synth", "--n", "1", "--holdout-sources", "rawtoaces,bogus", "--out", "x"),
     ["bogus", "valid ids", "cie-tcs"]),
    (("data", "synth", "--n", "1", "--holdout-sources", "none", "--split", "heldout", "--out", "x"),
     ["held-out source"]),
])
def test_bad_input_is_one_line_exit_2(tmp_path, args, words):
    r = run(*args, cwd=tmp_path)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("hsicam: error:"), r.stderr
    assert "Traceback" not in r.stderr
    for w in words:
        assert w in lines[0]


def test_show_corrupt_file_is_one_line(tmp_path):
    (tmp_path / "bad.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    r = run("data", "show", "bad.h5", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "bad.h5" in r.stderr
