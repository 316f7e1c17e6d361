"""Paths on which a command used to destroy or silently misuse the user's data (session 21 probe,
F10-F12): ``reconstruct`` writing its cube or preview over its own capture, dark or flat frame, or
over a file it did not write; ``evaluate --out`` replacing the ``--data`` folder it reads; a saved
evaluation scored as ground truth; hsicam outputs kept inside a data folder taken for scenes.

Real files on disk: a real run (``hsicam.engine.train`` on four small scenes, the tiny optics of
conftest), captures in their real formats, the commands through :func:`hsicam.cli.main` in-process
(``test_calibration.run_cli``) and, once per kind of refusal, the console script."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import assert_clean_error, assert_ok, error_line, run_cli, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import write_homogeneous_scenes
from hsicam.config import load_config
from hsicam.data.datasets import list_scenes
from hsicam.data.formats import read_cube, write_cube_h5, write_envi
from hsicam.errors import InputError
from hsicam.io import mark_complete, write_png8
from hsicam.spectral import Bands


def _error(res) -> str:
    """The one line of a refused command, without its ``hsicam: error: `` prefix."""
    return error_line(res)[len("hsicam: error: "):]


_ok = assert_ok


def _md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def setup(tmp_path_factory, cache_env) -> dict[str, Path]:
    """{"run": a finished 1-epoch run, "data": its 4 scenes (32×32, 500/550/600 nm)}."""
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("loss")
    data = write_homogeneous_scenes(base / "data", n=4, size=32)
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}", "train.epochs=1"])
    train(cfg, base / "run", progress=False)
    return {"run": base / "run", "data": data}


def _png8(path: Path, rgb: bool = False) -> Path:
    """An 8-bit PNG capture (mono), or an 8-bit RGB image, 48×48."""
    import imageio.v3 as iio

    rng = np.random.default_rng(0)
    iio.imwrite(path, (rng.random((48, 48, 3) if rgb else (48, 48)) * 120).astype(np.uint8), extension=".png")
    return path


def _reconstruct(capture: Path, run: Path, out: Path, *extra: str):
    return run_cli_in_process("reconstruct", str(capture), "--run", str(run), "--out", str(out), "--tile", "16", *extra)


# ------------------------------------------------------------------------------------------------
# F12. reconstruct: an output path is one of its inputs, or a file it did not write
# ------------------------------------------------------------------------------------------------
def test_reconstruct_refuses_to_write_its_preview_over_its_own_capture(setup, tmp_path):
    """``u/cap_rgb.png`` reconstructed to ``u/cap.h5``: the preview path is the capture (the console script)."""
    cap = _png8(tmp_path / "cap_rgb.png")
    before = _md5(cap)
    res = run_cli("reconstruct", str(cap), "--run", str(setup["run"]), "--out", str(tmp_path / "cap.h5"))
    assert_clean_error(res, f"{cap}: is the capture SENSOR, which reconstruct reads; the preview of --out "
                            f"{tmp_path / 'cap.h5'} would be written over it: choose another --out name")
    assert _md5(cap) == before
    assert not (tmp_path / "cap.h5").exists()


@pytest.mark.parametrize("option, label", [("--flat", "the --flat frame"), ("--dark", "the --dark frame")])
def test_reconstruct_refuses_to_write_over_its_flat_or_dark_frame(setup, tmp_path, option, label):
    frame = _png8(tmp_path / "f_rgb.png")
    before = _md5(frame)
    line = _error(_reconstruct(_png8(tmp_path / "cap.png"), setup["run"], tmp_path / "f.h5", option, str(frame)))
    assert line == (f"{frame}: is {label}, which reconstruct reads; the preview of --out {tmp_path / 'f.h5'} would be "
                    "written over it: choose another --out name")
    assert _md5(frame) == before and not (tmp_path / "f.h5").exists()


def test_reconstruct_refuses_an_output_that_links_to_an_input(setup, tmp_path):
    """The same file under another name (a symbolic or a hard link) is the same file."""
    cap = _png8(tmp_path / "cap.png")
    (tmp_path / "s_rgb.png").symlink_to(cap)
    line = _error(_reconstruct(cap, setup["run"], tmp_path / "s.h5"))
    assert line.startswith(f"{tmp_path / 's_rgb.png'}: is the capture SENSOR {cap} (the same file), which reconstruct reads")
    np.save(tmp_path / "raw.npy", np.full((48, 48), 0.2, np.float32))
    os.link(tmp_path / "raw.npy", tmp_path / "h.img")  # ENVI data file of --out h.hdr
    line = _error(_reconstruct(tmp_path / "raw.npy", setup["run"], tmp_path / "h.hdr"))
    assert line.startswith(f"{tmp_path / 'h.img'}: is the capture SENSOR {tmp_path / 'raw.npy'} (the same file)")
    assert "the cube of --out" in line
    assert np.load(tmp_path / "raw.npy").shape == (48, 48)


def _user_files(d: Path) -> dict[str, tuple[str, ...]]:
    """--out name -> the user's files at its output paths (written here, each not hsicam reconstruct's)."""
    (d / "e.h5").write_text("mine\n")  # not HDF5 at all
    bands = Bands.uniform(500, 600, 50)
    cube = np.random.default_rng(1).random((3, 48, 48)).astype(np.float32)
    write_cube_h5(d / "s.h5", cube, bands, {"generator": "a scene of the user's data"})  # our format, not reconstruct's
    (d / "c.img").write_text("MY IMPORTANT IMAGE\n")  # ENVI data path of --out c.hdr, no header
    write_envi(d / "v.hdr", cube, bands, description="my own ENVI cube")
    write_png8(d / "p_rgb.png", np.zeros((48, 48, 3)))  # a preview-looking PNG with no cube beside it
    write_envi(d / "w.hdr", cube, bands, description="hsicam cube")  # write_envi's old default: no preview beside it
    write_cube_h5(d / "r.h5", cube, bands, {"source": "cap.npy", "run": "a run"})  # reconstruct-like metadata, no preview
    return {"e.h5": ("e.h5",), "s.h5": ("s.h5",), "c.hdr": ("c.img",), "v.hdr": ("v.hdr", "v.img"), "p.h5": ("p_rgb.png",),
            "w.hdr": ("w.hdr", "w.img"), "r.h5": ("r.h5",)}


@pytest.mark.parametrize("name, refused, why", [
    ("e.h5", "e.h5", "exists and is not a cube that hsicam reconstruct wrote"),
    ("s.h5", "s.h5", "exists and is not a cube that hsicam reconstruct wrote"),
    ("c.hdr", "c.img", "exists and is not the ENVI data of a cube that hsicam reconstruct wrote (its header c.hdr is missing)"),
    ("v.hdr", "v.hdr", "exists and is not an ENVI header that hsicam reconstruct wrote"),
    ("p.h5", "p_rgb.png", "exists, but no cube p.h5 that hsicam reconstruct wrote lies beside it"),
    ("w.hdr", "w.hdr", "exists and is not an ENVI header that hsicam reconstruct wrote"),
    ("r.h5", "r.h5", "exists and is not a cube that hsicam reconstruct wrote"),
])
def test_reconstruct_never_replaces_a_file_it_did_not_write(setup, tmp_path, name, refused, why):
    files = _user_files(tmp_path)[name]
    before = {f: _md5(tmp_path / f) for f in files}
    np.save(tmp_path / "cap.npy", np.full((48, 48), 0.2, np.float32))
    line = _error(_reconstruct(tmp_path / "cap.npy", setup["run"], tmp_path / name))
    assert line.startswith(f"{tmp_path / refused}: {why}"), line
    assert line.endswith(f"choose another --out name or move {refused} away"), line
    assert {f: _md5(tmp_path / f) for f in files} == before
    written = {p.name for p in tmp_path.iterdir()} - set(files) - {"cap.npy"}
    assert written <= {"e.h5", "s.h5", "c.img", "v.hdr", "v.img", "p_rgb.png", "w.hdr", "w.img", "r.h5"}, written


def test_reconstruct_replaces_its_own_earlier_output_only(setup, tmp_path):
    """Its earlier cube (HDF5; ENVI, also one whose header still says ``hsicam cube``) and preview are
    replaced; a preview beside it that is not an 8-bit RGB PNG, or ENVI data of another size, is not."""
    np.save(tmp_path / "cap.npy", np.full((48, 48), 0.2, np.float32))
    cap = tmp_path / "cap.npy"
    for name in ("a.h5", "b.hdr"):
        _ok(_reconstruct(cap, setup["run"], tmp_path / name))
        first = read_cube(tmp_path / name)[0]
        _ok(_reconstruct(cap, setup["run"], tmp_path / name, "--scale", "2"))  # replaced: a new cube
        assert not np.allclose(read_cube(tmp_path / name)[0], first)
    text = (tmp_path / "b.hdr").read_text()
    assert "description = {hsicam reconstruct}" in text
    older = "".join(x for x in text.splitlines(keepends=True) if not x.startswith("hsicam data crc32"))
    (tmp_path / "b.hdr").write_text(older.replace("{hsicam reconstruct}", "{hsicam cube}"))  # an older reconstruct's
    _ok(_reconstruct(cap, setup["run"], tmp_path / "b.hdr"))
    (tmp_path / "b.hdr").write_text(older.replace("{hsicam reconstruct}", "{hsicam cube}"))  # its data's size: checked
    (tmp_path / "b.img").write_bytes((tmp_path / "b.img").read_bytes()[:-4])
    line = _error(_reconstruct(cap, setup["run"], tmp_path / "b.hdr"))
    assert line.startswith(f"{tmp_path / 'b.img'}: exists and is not the ENVI data of a cube that hsicam reconstruct "
                           f"wrote (its size ({3 * 48 * 48 * 4 - 4} bytes) is not the {3 * 48 * 48 * 4} bytes that b.hdr describes)")
    _png8(tmp_path / "a_rgb.png")  # a mono PNG (a capture, say) where a.h5's preview was
    before = _md5(tmp_path / "a_rgb.png")
    line = _error(_reconstruct(cap, setup["run"], tmp_path / "a.h5"))
    assert line == (f"{tmp_path / 'a_rgb.png'}: exists and is not an sRGB preview (an 8-bit RGB PNG) that hsicam "
                    "reconstruct wrote; choose another --out name or move a_rgb.png away")
    assert _md5(tmp_path / "a_rgb.png") == before
    assert read_cube(tmp_path / "a.h5")[2]["command"] == "reconstruct"


# ------------------------------------------------------------------------------------------------
# F10. evaluate: --out is, holds or lies inside --data; an evaluation's saved cubes as data
# ------------------------------------------------------------------------------------------------
def _saved_evaluation(setup, out: Path) -> Path:
    _ok(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(setup["data"]), "--out", str(out), "--save"))
    assert sorted(p.name for p in (out / "cubes").iterdir())[:2] == ["s00_estimate.h5", "s00_truth.h5"]
    return out


def test_evaluate_refuses_an_out_that_is_its_data(setup, tmp_path):
    """The probe's case: ``--data ev --out ev`` on a --save evaluation deleted its cubes (the console script)."""
    ev = _saved_evaluation(setup, tmp_path / "ev")
    cubes = sorted((ev / "cubes").iterdir())
    res = run_cli("evaluate", "--run", str(setup["run"]), "--data", str(ev), "--out", str(ev))
    assert_clean_error(res, f"{ev}: is the --data folder; evaluate replaces its --out folder whole, which would delete "
                            f"the scenes it reads: give --out a folder outside {ev}")
    assert sorted((ev / "cubes").iterdir()) == cubes
    line = _error(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(ev / "cubes"), "--out", str(ev)))
    assert line == (f"{ev}: holds the --data {ev / 'cubes'}; evaluate replaces its --out folder whole, which would "
                    f"delete the scenes it reads: give --out a folder outside {ev / 'cubes'}")
    link = tmp_path / "link"
    link.symlink_to(ev)
    assert _error(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(link), "--out", str(ev))).startswith(
        f"{ev}: is the --data folder")
    assert sorted((ev / "cubes").iterdir()) == cubes


def test_an_evaluation_kept_inside_its_data_is_not_scored_as_data(setup, tmp_path):
    """--out inside --data is allowed (results next to the data): the next evaluation of that folder
    skips it and scores the same scenes."""
    data = shutil.copytree(setup["data"], tmp_path / "data")
    _ok(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(data), "--out", str(data / "eval"), "--save"))
    _ok(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(data), "--out", str(tmp_path / "again")))
    first, again = (json.loads((p / "results.json").read_text()) for p in (data / "eval", tmp_path / "again"))
    assert [s["name"] for s in again["scenes"]] == [s["name"] for s in first["scenes"]]
    assert len(again["scenes"]) == 4 and (data / "eval" / "cubes").is_dir()


def test_an_evaluation_is_not_taken_for_ground_truth(setup, tmp_path):
    """Its cubes/*_estimate.h5 used to be scored as scenes; one *_truth.h5 file named alone is scored."""
    ev = _saved_evaluation(setup, tmp_path / "ev")
    scored = f"which scored {Path(setup['data']).resolve()}"
    for data, where in ((ev, "is"), (ev / "cubes", f"lies inside {ev}, which is"),
                        (ev / "cubes" / "s00_estimate.h5", f"lies inside {ev}, which is")):
        line = _error(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(data), "--out", str(tmp_path / "o")))
        assert line == (f"{data}: {where} the output of hsicam evaluate ({scored}); its cubes/*_estimate.h5 are a "
                        "method's reconstructions, not scenes: use the scenes it scored as the data, or copy its "
                        "*_truth.h5 files into a folder of their own")
        assert not (tmp_path / "o").exists()
    _ok(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(ev / "cubes" / "s00_truth.h5"),
                "--out", str(tmp_path / "o")))
    assert [s["name"] for s in json.loads((tmp_path / "o" / "results.json").read_text())["scenes"]] == ["s00_truth"]


# ------------------------------------------------------------------------------------------------
# F11. a data folder holding hsicam outputs: they are skipped, and said so once
# ------------------------------------------------------------------------------------------------
def _data_with_outputs(setup, tmp_path) -> Path:
    """The 4 scenes, plus an evaluation saved (elsewhere, then moved) into eval/ and a simulation in sim/."""
    data = shutil.copytree(setup["data"], tmp_path / "mydata")
    shutil.move(_saved_evaluation(setup, tmp_path / "ev"), data / "eval")
    _ok(run_cli_in_process("simulate", "--run", str(setup["run"]), "--scene", str(data / "s00.h5"), "--out", str(data / "sim")))
    return data


def test_a_data_folder_skips_the_hsicam_outputs_inside_it(setup, tmp_path, caplog):
    data = _data_with_outputs(setup, tmp_path)
    with caplog.at_level(logging.INFO, logger="hsicam.data.datasets"):
        res = run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(data), "--out", str(tmp_path / "o"))
        _ok(res)
        list_scenes(data)  # a second scan of the same folder says nothing more
    names = [s["name"] for s in json.loads((tmp_path / "o" / "results.json").read_text())["scenes"]]
    assert names == ["s00", "s01", "s02", "s03"]  # not the saved estimates and truths, no sensor.npy
    said = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert said == [f"data: {data}: skipped 2 sub-folder(s) holding hsicam outputs, not scenes: eval (evaluate), "
                    "sim (simulate)"]
    assert _error(run_cli_in_process("evaluate", "--run", str(setup["run"]), "--data", str(data / "sim"),
                          "--out", str(tmp_path / "o2"))) == (
        f"{data / 'sim'}: is the output of hsicam simulate, not a folder of scenes; use a folder of cube files as the data")


def test_a_folder_of_hsicam_outputs_only_has_no_scenes(tmp_path):
    (tmp_path / "d" / "sim").mkdir(parents=True)
    np.save(tmp_path / "d" / "sim" / "sensor.npy", np.zeros((8, 8), np.float32))
    mark_complete(tmp_path / "d" / "sim", {"command": "simulate", "files": ["sensor.npy"]})
    with pytest.raises(InputError) as err:
        list_scenes(tmp_path / "d")
    assert str(err.value) == (f"{tmp_path / 'd'}: no hyperspectral scenes found (supported: .h5, .hdf5, .mat, .npy, "
                              ".exr, .hdr, CAVE folders) (skipped 1 sub-folder(s) holding hsicam outputs, not scenes: "
                              "sim (simulate))")


def test_training_on_a_data_folder_holding_an_evaluation_uses_its_scenes_only(setup, tmp_path):
    from hsicam.data.pipeline import build_datasets

    data = shutil.copytree(setup["data"], tmp_path / "mydata")
    ev = data / "ev"
    (ev / "cubes").mkdir(parents=True)
    write_cube_h5(ev / "cubes" / "s00_estimate.h5", np.ones((3, 32, 32), np.float32), Bands.uniform(500, 600, 50))
    mark_complete(ev, {"command": "evaluate", "files": ["cubes"]})
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}"])
    train, val = build_datasets(cfg.data, cfg.bands.to_bands(), margin_px=0)
    used = {p.name for p in train.scenes.paths} | {p.name for p in val.scenes.paths}
    assert used == {"s00.h5", "s01.h5", "s02.h5", "s03.h5"}
