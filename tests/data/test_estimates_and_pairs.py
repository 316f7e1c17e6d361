"""Reconstructions never pass for scenes, and a half-replaced output is never read (probe 24,
findings 1, 2 and 15).

- An ENVI pair is two renames: an interruption between them left the new ``.img`` beside the old
  ``.hdr``; readers took the first bytes of the larger cube as the old shape, and a re-run of
  reconstruct refused to repair it.
- A cube that reconstruct wrote into a data folder became a training/validation/test scene (and
  reshuffled the split); in a generated dataset, any file beside the manifest's scenes did too.
- An interrupted reconstruction kept the older preview beside the newer cube.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cli_helpers import run_cli_in_process
from hsicam.data import read_cube
from hsicam.data.datasets import list_scenes
from hsicam.data.formats import ENVI_CRC_KEY, read_envi, write_cube_h5, write_envi
from hsicam.errors import InputError
from hsicam.spectral import Bands

BANDS = Bands.uniform(420, 720, 50)  # the tiny preset's 7 bands


def cube(h: int, w: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((len(BANDS), h, w)).astype(np.float32)


@pytest.fixture(scope="module")
def run(tmp_path_factory, cache_env):
    d = tmp_path_factory.mktemp("est") / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(d), "--set", "train.epochs=1")
    assert res.returncode == 0, res.stderr
    return d


# ------------------------------------------------------------------------------------------------
# 1. ENVI pairs
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("byte_order", ["little", "big"])
def test_a_pair_records_its_datas_crc_and_reads_back(tmp_path, byte_order):
    import zlib

    a = cube(16, 12, 0)
    hdr, data = write_envi(tmp_path / "e.hdr", a, BANDS, byte_order=byte_order)
    line = [x for x in hdr.read_text().splitlines() if x.startswith(ENVI_CRC_KEY)]
    assert line == [f"{ENVI_CRC_KEY} = {zlib.crc32(data.read_bytes()):08x}"]
    np.testing.assert_array_equal(read_envi(hdr)[0], a)


def test_new_data_beside_an_old_header_is_refused(tmp_path):
    """The state an interruption between the two renames leaves: new data, old header."""
    hdr, data = write_envi(tmp_path / "e.hdr", cube(16, 16, 0), BANDS)
    other = tmp_path / "other"
    other.mkdir()
    shutil.copyfile(write_envi(other / "big.hdr", cube(40, 40, 1), BANDS)[1], data)  # a larger cube's data
    with pytest.raises(InputError, match=rf"{data}: {40 * 40 * 7 * 4} bytes of ENVI data, but e.hdr describes "
                                         rf"{16 * 16 * 7 * 4} \(16×16×7 float32\): the header and the data do not belong"):
        read_cube(hdr)
    shutil.copyfile(write_envi(other / "same.hdr", cube(16, 16, 2), BANDS)[1], data)  # same size, other data
    with pytest.raises(InputError, match=rf"{data}: not the data e.hdr was written for \(CRC-32 [0-9a-f]{{8}}, the "
                                         r"header records [0-9a-f]{8}\): an interrupted write .*, or the data were edited "
                                         rf"since \(to keep them, remove the '{ENVI_CRC_KEY}' line from e.hdr\)"):
        read_cube(hdr)


def test_a_user_envi_file_without_the_crc_still_reads(tmp_path):
    hdr, _ = write_envi(tmp_path / "e.hdr", cube(8, 8, 0), BANDS)
    hdr.write_text("".join(x for x in hdr.read_text().splitlines(keepends=True) if not x.startswith(ENVI_CRC_KEY)))
    assert read_cube(hdr)[0].shape == (7, 8, 8)


def test_reconstruct_repairs_a_half_replaced_pair_of_its_own(run, tmp_path):
    np.save(tmp_path / "small.npy", np.full((48, 48), 0.2, np.float32))
    np.save(tmp_path / "big.npy", np.random.default_rng(3).random((64, 64)).astype(np.float32) * 0.3)
    out = tmp_path / "e.hdr"
    assert run_cli_in_process("reconstruct", str(tmp_path / "small.npy"), "--run", str(run), "--out", str(out)).returncode == 0
    ref = tmp_path / "ref"
    ref.mkdir()
    res = run_cli_in_process("reconstruct", str(tmp_path / "big.npy"), "--run", str(run), "--out", str(ref / "e.hdr"))
    assert res.returncode == 0, res.stderr
    shutil.copyfile(ref / "e.img", tmp_path / "e.img")  # interrupted before the header's rename
    with pytest.raises(InputError, match="do not belong together"):
        read_cube(out)
    res = run_cli_in_process("reconstruct", str(tmp_path / "big.npy"), "--run", str(run), "--out", str(out))
    assert res.returncode == 0, res.stderr  # refused before: "is not the ENVI data of a cube that reconstruct wrote"
    np.testing.assert_array_equal(read_cube(out)[0], read_cube(ref / "e.hdr")[0])


# ------------------------------------------------------------------------------------------------
# 15. the preview never stands beside a newer cube
# ------------------------------------------------------------------------------------------------
def test_an_interrupted_reconstruction_leaves_the_earlier_cube_with_its_own_preview(tmp_path, monkeypatch):
    """Stopped while the new cube is written, the earlier cube and the earlier preview stay as they were, a pair
    (before session 70 the earlier preview was deleted first, so that it never stood beside a newer cube; the new
    preview now waits in a hidden temporary until the new cube has taken its place)."""
    from hsicam.cli.reconstruct import write_cube_file
    from hsicam.data import formats

    path = tmp_path / "c.h5"
    write_cube_file(path, cube(16, 16, 0), BANDS, {"source": "x", "run": "y"})
    preview = tmp_path / "c_rgb.png"
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(before) == {"c.h5", "c_rgb.png"}

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(formats, "write_cube_h5", killed)
    with pytest.raises(KeyboardInterrupt):
        write_cube_file(path, cube(16, 16, 1), BANDS, {"source": "x", "run": "y"})
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no temporary either
    monkeypatch.undo()
    write_cube_file(path, cube(16, 16, 1), BANDS, {"source": "x", "run": "y"})
    assert preview.read_bytes() != before["c_rgb.png"] and path.read_bytes() != before["c.h5"]


# ------------------------------------------------------------------------------------------------
# 2. estimates are not scenes
# ------------------------------------------------------------------------------------------------
def test_a_reconstruction_in_a_data_folder_is_not_a_scene(run, tmp_path, caplog):
    data = tmp_path / "data"
    data.mkdir()
    for i in range(2):
        write_cube_h5(data / f"s{i}.h5", cube(32, 32, i), BANDS)
    np.save(tmp_path / "cap.npy", np.full((48, 48), 0.2, np.float32))
    for name in ("estimate.h5", "estimate_envi.hdr"):
        res = run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(run), "--out", str(data / name))
        assert res.returncode == 0, res.stderr
    with caplog.at_level("WARNING"):
        assert list_scenes(data) == [data / "s0.h5", data / "s1.h5"]
    assert ("skipped 2 cube file(s) that hsicam reconstruct wrote (estimates, not scenes): estimate.h5, "
            "estimate_envi.hdr") in caplog.text
    only = tmp_path / "only"
    only.mkdir()
    shutil.move(data / "estimate.h5", only / "estimate.h5")
    with pytest.raises(InputError, match="no hyperspectral scenes found .* \\(skipped 1 cube file\\(s\\) that hsicam "
                                         "reconstruct wrote"):
        list_scenes(only)


def test_a_generated_dataset_lists_the_scenes_of_its_manifest(tmp_path, caplog):
    from hsicam.data.synthetic import generate_dataset

    ds = tmp_path / "ds"
    generate_dataset(ds, n=3, size=32, seed=5, progress=False)
    listed = [ds / s["file"] for s in json.loads((ds / "manifest.json").read_text())["scenes"]]
    write_cube_h5(ds / "scene_0099.h5", cube(32, 32, 0), BANDS)  # a file put there by hand
    write_cube_h5(ds / "mine" / "a.h5", cube(32, 32, 1), BANDS)  # a folder of one's own scenes put inside it
    with caplog.at_level("WARNING"):
        assert list_scenes(ds) == sorted(listed)
    assert "its 3 scenes are those its manifest.json lists; not mine/a.h5, scene_0099.h5" in caplog.text
    listed[1].unlink()
    with pytest.raises(InputError, match=rf"{ds}: 1 scene\(s\) its manifest.json lists are missing \({listed[1].name}\)"):
        list_scenes(ds)


def test_a_users_write_envi_scene_with_a_quick_look_is_a_scene(tmp_path):
    """write_envi's default description was reconstruct's older one: with a <stem>_rgb.png beside it,
    a user's scene was skipped as an estimate (probe 25, F2). Only what reconstruct alone writes
    counts now, and write_envi's default is its own."""
    from hsicam.data.estimates import ENVI_DESCRIPTIONS, is_estimate
    from hsicam.io import write_png8

    data = tmp_path / "d"
    data.mkdir()
    for i, description in enumerate((None, "hsicam cube")):  # today's default, and the old one
        kwargs = {} if description is None else {"description": description}
        hdr, _ = write_envi(data / f"s{i}.hdr", cube(16, 16, i), BANDS, **kwargs)
        write_png8(data / f"s{i}_rgb.png", np.zeros((16, 16, 3)))
        assert not is_estimate(hdr)
    assert "hsicam write_envi" in (data / "s0.hdr").read_text() and ENVI_DESCRIPTIONS[0] != "hsicam write_envi"
    write_cube_h5(data / "s2.h5", cube(16, 16, 2), BANDS, {"source": "cap.npy", "run": "a run"})  # reconstruct-like
    write_png8(data / "s2_rgb.png", np.zeros((16, 16, 3)))
    assert list_scenes(data) == [data / "s0.hdr", data / "s1.hdr", data / "s2.h5"]


@pytest.mark.parametrize("text", ['[{"file": "s0.h5"}]', '"notes"', '{"format": "mine", "scenes": 3}', "{"])
def test_a_manifest_that_is_not_hsicams_is_scanned_past(tmp_path, text):
    """A manifest.json that is a list or a string gave an AttributeError traceback (probe 25, F3)."""
    for i in range(2):
        write_cube_h5(tmp_path / f"s{i}.h5", cube(16, 16, i), BANDS)
    (tmp_path / "manifest.json").write_text(text)
    assert list_scenes(tmp_path) == [tmp_path / "s0.h5", tmp_path / "s1.h5"]


def test_another_writers_envi_data_with_trailing_bytes_is_read_with_a_warning(tmp_path, caplog):
    """Only a pair hsicam wrote (its CRC line) must be exactly its header's size (review, session 23)."""
    a = cube(8, 8, 0)
    hdr, data = write_envi(tmp_path / "e.hdr", a, BANDS)
    hdr.write_text("".join(x for x in hdr.read_text().splitlines(keepends=True) if not x.startswith(ENVI_CRC_KEY)))
    data.write_bytes(data.read_bytes() + b"\0" * 512)
    with caplog.at_level("WARNING"):
        np.testing.assert_array_equal(read_envi(hdr)[0], a)
    assert f"{data}: {a.nbytes + 512} bytes of ENVI data, but e.hdr describes {a.nbytes}" in caplog.text


def test_reconstruct_to_envi_records_the_metadata_its_hdf5_records(tmp_path, capsys):
    """`reconstruct --out X.hdr` wrote none of the metadata that --out X.h5 records (source, run, preprocessing,
    cfa_offset and --cfa-offset auto's cfa_offset_estimate, the consistency steps; session 54 review): the header
    keeps it now (write_envi's ``hsicam metadata`` line), and read_cube returns the same as from the .h5."""
    import h5py

    from hsicam.cli import main

    sensor = tmp_path / "capture.npy"
    np.save(sensor, np.random.default_rng(0).uniform(0.2, 0.8, (48, 48)).astype(np.float32))
    for name in ("c.hdr", "d.h5"):
        argv = ["reconstruct", str(sensor), "--run", "pretrained:standard", "--cfa-offset", "auto",
                "--out", str(tmp_path / name)]
        assert main(argv) == 0, capsys.readouterr().err
    with h5py.File(tmp_path / "d.h5") as f:
        recorded = json.loads(f.attrs["metadata_json"])
    assert {"command", "source", "run", "preprocessing", "cfa_offset", "cfa_offset_estimate",
            "consistency_steps"} <= recorded.keys()
    meta = read_cube(tmp_path / "c.hdr")[2]
    assert {k: meta.get(k) for k in recorded} == recorded
    assert meta["format"] == "envi" and meta["command"] == "reconstruct"
    assert main(argv[:-1] + [str(tmp_path / "c.hdr")]) == 0  # its own earlier output: replaced


def test_evaluate_estimates_copied_into_a_data_folder_are_no_scenes(tmp_path, caplog):
    """`hsicam evaluate --save` writes cubes/NAME_estimate.h5 and NAME_truth.h5; copied out of the evaluation (a
    real-format dataset hunt, session 72) the estimates became training scenes. They are listed as estimates now,
    by the command and role they carry (and, written before, by the keys only they hold); the truth cubes are scenes."""
    from hsicam.data.estimates import is_estimate

    data = tmp_path / "d"
    data.mkdir()
    scene = {"scene": "a", "scene_path": "a.h5", "source": "/x/a.h5", "normalization_peak": 1.0}
    write_cube_h5(data / "a_estimate.h5", cube(16, 16, 0), BANDS, {"command": "evaluate", "role": "estimate",
                                                                  "method": "doe-learned", **scene, "run": "r",
                                                                  "seed": 0, "seeds_scored": 1, "noise": {}})
    write_cube_h5(data / "b_estimate.h5", cube(16, 16, 1), BANDS, {"method": "doe-learned", **scene, "run": "r",
                                                                  "seed": 0, "seeds_scored": 1})  # before session 72
    write_cube_h5(data / "a_truth.h5", cube(16, 16, 2), BANDS, {"role": "ground truth", **scene})
    write_cube_h5(data / "mine.h5", cube(16, 16, 3), BANDS, {"method": "my own", "run": "field day 2"})
    assert [is_estimate(data / n) for n in ("a_estimate.h5", "b_estimate.h5", "a_truth.h5", "mine.h5")] == \
        [True, True, False, False]
    assert list_scenes(data) == [data / "a_truth.h5", data / "mine.h5"]


def test_a_link_to_a_folder_that_is_gone_is_said_not_skipped_silently(tmp_path, caplog):
    """A dataset spread over disks by links: with one disk unmounted, its linked folder's scenes were left out
    without a word (os.walk lists a dangling link among the files; a real-format dataset hunt, session 72)."""
    import os

    data = tmp_path / "d"
    data.mkdir()
    write_cube_h5(data / "a.h5", cube(16, 16, 0), BANDS)
    (tmp_path / "disk2").mkdir()
    write_cube_h5(tmp_path / "disk2" / "b.h5", cube(16, 16, 1), BANDS)
    os.symlink(tmp_path / "disk2", data / "linked")
    assert list_scenes(data) == [data / "a.h5", data / "linked" / "b.h5"]
    (tmp_path / "disk2").rename(tmp_path / "unmounted")
    with caplog.at_level("WARNING"):
        assert list_scenes(data) == [data / "a.h5"]
    assert (f"{data / 'linked'}: is a symbolic link to {tmp_path / 'disk2'}, which does not exist: skipped (if it led "
            "to scenes, restore what it points to)") in caplog.text
