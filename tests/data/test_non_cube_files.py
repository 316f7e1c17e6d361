"""A dataset folder's MAT/HDF5 files that hold no cube (a download's ``meta.mat``, a calibration ``.h5`` of 2-D
frames, a v7.3 ``.mat`` of labels) are skipped with one warning that counts and names them; a file that may hold a
cube under another name, one of two such arrays, or that cannot be read still stops the command (session 75).
Every file here is written in its real format: scipy.io.savemat (MAT v5), h5py (HDF5, and MAT v7.3 = HDF5 with
MATLAB's 512-byte header)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from cli_helpers import assert_clean_error, assert_ok, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from hsicam.data.datasets import list_scenes
from hsicam.data.formats import read_cube, write_cube_h5
from hsicam.errors import InputError
from hsicam.spectral import Bands

BANDS = Bands.uniform(500, 600, 50)  # the tiny camera's (TINY_CAMERA_OVERRIDES)
SETS = [x for o in (*TINY_CAMERA_OVERRIDES, "train.epochs=1") for x in ("--set", o)]


def _cube(seed: int, size: int = 40) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.1, 1.0, (3, size, size)).astype(np.float32)


def write_mat73(path: Path, variables: dict[str, np.ndarray], classes: dict[str, str] | None = None) -> None:
    """MATLAB v7.3: HDF5 with MATLAB's 512-byte header in the user block, arrays transposed (column-major)."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            ds = f.create_dataset(name, data=np.ascontiguousarray(np.asarray(value).T))
            ds.attrs["MATLAB_class"] = np.bytes_((classes or {}).get(name, "double"))
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write((text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM").ljust(512, b"\x00"))


def write_folder(folder: Path) -> Path:
    """2 cubes (our HDF5; a MAT v5 ``cube`` H×W×C with its band list) beside 3 files of no cube: a meta.mat of
    text, numbers and a struct, a calibration .h5 of 2-D frames (and a 3×3×1 stack), a v7.3 .mat of labels."""
    folder.mkdir(parents=True, exist_ok=True)
    write_cube_h5(folder / "a.h5", _cube(0), BANDS)
    scipy.io.savemat(folder / "b.mat", {"cube": np.transpose(_cube(1), (1, 2, 0)).astype(np.float64),
                                        "bands": BANDS.centers_nm[None]})
    scipy.io.savemat(folder / "meta.mat", {"title": "scenes of day 1", "n_scenes": 2, "exposure_s": [[0.01, 0.02]],
                                           "camera": {"model": "X-100", "gain": 1.5}})
    with h5py.File(folder / "calibration.h5", "w") as f:
        f["dark"] = np.zeros((40, 40), np.float32)
        f["flat"] = np.ones((40, 40), np.float32)
        f["lens/distortion"] = np.ones((3, 3, 1))  # 3 axes, but one of 1: a 3×3 matrix, no cube
    write_mat73(folder / "labels.mat", {"labels": np.zeros((40, 40), np.uint8), "names": np.array([[115, 107, 121]])},
                {"labels": "uint8", "names": "char"})
    return folder


def test_a_folder_lists_its_two_cubes_and_says_once_which_files_it_skipped(tmp_path, caplog):
    data = write_folder(tmp_path / "data")
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert [p.name for p in list_scenes(data)] == ["a.h5", "b.mat"]
        assert [p.name for p in list_scenes(data)] == ["a.h5", "b.mat"]  # listed again: not said again
    said = [r.getMessage() for r in caplog.records if "no hyperspectral cube" in r.getMessage()]
    assert said == [f"data: {data}: skipped 3 MAT/HDF5 file(s) that hold no hyperspectral cube (calibration.h5, "
                    "labels.mat, meta.mat: no variable of a cube's name (cube, rad, img, img_expand, HSI, ref) and no "
                    "numeric array with 3 or more axes longer than 1)"]
    from hsicam.data.formats import holds_no_cube

    assert [holds_no_cube(data / n) for n in ("a.h5", "b.mat", "meta.mat", "calibration.h5", "labels.mat")] == [
        False, False, True, True, True]


def test_hundreds_of_such_files_are_counted_in_one_line(tmp_path, caplog):
    data = tmp_path / "data"
    write_cube_h5(data / "a.h5", _cube(0), BANDS)
    for i in range(120):
        scipy.io.savemat(data / f"label_{i:03d}.mat", {"label": np.full((8, 8), i, np.uint8)})
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert [p.name for p in list_scenes(data)] == ["a.h5"]
    said = [r.getMessage() for r in caplog.records if "no hyperspectral cube" in r.getMessage()]
    assert len(said) == 1 and "skipped 120 MAT/HDF5 file(s)" in said[0]
    assert "(label_000.mat, label_001.mat, label_002.mat and 117 more:" in said[0]


def test_a_folder_of_no_cube_at_all_is_still_refused_saying_what_it_skipped(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    scipy.io.savemat(data / "meta.mat", {"title": "nothing here"})
    with h5py.File(data / "calibration.h5", "w") as f:
        f["dark"] = np.zeros((8, 8))
    with pytest.raises(InputError) as exc:
        list_scenes(data)
    assert str(exc.value).startswith(f"{data}: no hyperspectral scenes found (supported: ")
    assert "skipped 2 MAT/HDF5 file(s) that hold no hyperspectral cube (calibration.h5, meta.mat:" in str(exc.value)


@pytest.mark.parametrize("case", ["unknown-name", "two-arrays", "in-a-struct", "v73-unknown-name", "truncated",
                                  "cube-of-2-axes"])
def test_a_file_that_may_hold_a_cube_is_listed_and_refused_when_read(tmp_path, case):
    """Not skipped: a cube-like array under a name no reader takes (v5, v7.3, inside a struct), two of them
    (ambiguous), a file cut short (cannot be told), a variable of a cube's name that is no cube."""
    data = tmp_path / "data"
    write_cube_h5(data / "a.h5", _cube(0), BANDS)
    hwc = np.transpose(_cube(2), (1, 2, 0)).astype(np.float64)
    p = data / ("x.h5" if case == "truncated" else "x.mat")
    if case == "unknown-name":
        scipy.io.savemat(p, {"radiance": hwc, "bands": BANDS.centers_nm[None]})
        words = ["'radiance' 40×40×3 may be the cube", "rename the cube's variable"]
    elif case == "two-arrays":
        scipy.io.savemat(p, {"radiance": hwc, "reflectance": hwc})
        words = ["2 arrays may be the cube, which is ambiguous: 'radiance' 40×40×3, 'reflectance' 40×40×3"]
    elif case == "in-a-struct":
        scipy.io.savemat(p, {"scene": {"data": hwc, "name": "x"}})
        words = ["'scene.data' 40×40×3 may be the cube"]
    elif case == "v73-unknown-name":
        write_mat73(p, {"radiance": hwc})
        words = ["'radiance' 3×40×40 may be the cube"]  # (its shape as stored: HDF5 keeps MATLAB's axes reversed)
    elif case == "truncated":
        write_cube_h5(p, _cube(2), BANDS)
        p.write_bytes(p.read_bytes()[:700])
        words = ["cannot read"]
    else:
        scipy.io.savemat(p, {"cube": np.ones((40, 40))})
        words = ["'cube' must be a 3-D array"]
    assert p in list_scenes(data)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert str(exc.value).startswith(str(p)) and all(w in str(exc.value) for w in words), str(exc.value)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, cache_env):
    """A tiny camera trained one epoch on the folder of 2 cubes and 3 other files."""
    base = tmp_path_factory.mktemp("noncube")
    data = write_folder(base / "data")
    res = run_cli_in_process("train", "--config", "tiny", *SETS, "--set", f"data.root={data}", "--out",
                             str(base / "run"))
    assert_ok(res)
    return base, res


def test_train_and_evaluate_use_the_two_cubes_and_say_once_what_they_skipped(trained, tmp_path, monkeypatch):
    from hsicam.data import datasets

    base, res = trained
    data, run = base / "data", base / "run"
    assert res.stderr.count("that hold no hyperspectral cube") == 1, res.stderr
    rec = json.loads((run / "data.json").read_text())
    assert [e["path"] for e in rec["scenes"]] == ["a.h5", "b.mat"]
    assert sorted(rec["train"] + rec["validation"]) == ["a.h5", "b.mat"] and len(rec["validation"]) == 1
    monkeypatch.setattr(datasets, "_NO_CUBE_LOGGED", set())  # each command is a process of its own: said again
    ev = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "ev"))
    assert_ok(ev)
    assert ev.stderr.count("that hold no hyperspectral cube") == 1, ev.stderr
    scored = json.loads((tmp_path / "ev" / "results.json").read_text())["scenes"]
    assert sorted(r["path"] for r in scored) == ["a.h5", "b.mat"]
    # the resume compares the folder with data.json: the same 2 scenes, the other files left out as before
    assert_ok(run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.epochs=2"))
    show = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "show"))
    assert_ok(show)
    assert "contact_sheet.png" in show.stdout


def test_a_cube_like_file_under_another_name_still_stops_training(tmp_path, cache_env):
    data = write_folder(tmp_path / "data")
    scipy.io.savemat(data / "c.mat", {"radiance": np.transpose(_cube(3), (1, 2, 0)).astype(np.float64)})
    res = run_cli_in_process("train", "--config", "tiny", *SETS, "--set", f"data.root={data}", "--out",
                             str(tmp_path / "run"))
    assert_clean_error(res, f"{data / 'c.mat'}: MAT file with no known hyperspectral variable",
                       "'radiance' 40×40×3 may be the cube")
