"""Readers that must not go silently wrong on a user's own data (probe 31, findings 03, 04, 05, 07b).

Linked sub-folders and linked files of a dataset folder; ENVI ``data ignore value`` and ``bbl``
(headers and raw bytes written by hand, as ENVI software does); our HDF5 read window by window
(files written, then edited with h5py as a user writing the documented layout would); scenes
whose maximum is one hot pixel.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from envi_files import write_envi_pair
from hsicam.data import PatchDataset, SceneDataset, list_scenes, read_cube, read_envi, split_scenes, write_cube_h5
from hsicam.data import datasets as ds_mod
from hsicam.data.datasets import check_windowed_pixels, near_black_percentile, _TopValues
from hsicam.errors import InputError
from hsicam.spectral import Bands

B7 = Bands.uniform(420, 720, 50)  # 7 bands
needs_links = pytest.mark.skipif(not hasattr(os, "symlink") or os.name == "nt", reason="symbolic links")


def scene(path: Path, seed: int, size=(24, 24), scale: float = 3.0) -> np.ndarray:
    path.parent.mkdir(parents=True, exist_ok=True)
    cube = (np.random.default_rng(seed).random((len(B7), *size)) * scale + 0.1).astype(np.float32)
    write_cube_h5(path, cube, B7)
    return cube


def rel(paths, root):
    return [Path(p).relative_to(root).as_posix() for p in paths]


# ------------------------------------------------------------------------------------------------
# 03: links in a dataset folder
# ------------------------------------------------------------------------------------------------
@needs_links
def test_linked_folder_is_followed_and_an_alias_is_listed_once(tmp_path, caplog):
    d = tmp_path / "d"
    for i in range(3):
        scene(d / "day1" / f"a{i}.h5", i)
        scene(tmp_path / "elsewhere" / "day2" / f"b{i}.h5", 10 + i)
    (d / "day2").symlink_to(tmp_path / "elsewhere" / "day2")  # a second disk linked in
    (d / "a0_alias.h5").symlink_to(Path("day1") / "a0.h5")  # the same scene under another name
    (d / "day1" / "loop").symlink_to("..")  # a loop
    (d / "self").symlink_to(".")
    with caplog.at_level(logging.WARNING, logger="hsicam.data.datasets"):
        scenes = list_scenes(d)
    assert rel(scenes, d) == ["day1/a0.h5", "day1/a1.h5", "day1/a2.h5", "day2/b0.h5", "day2/b1.h5", "day2/b2.h5"]
    lines = [r.getMessage() for r in caplog.records if "link(s)" in r.getMessage()]
    assert len(lines) == 1 and "\n" not in lines[0], lines
    assert "a0_alias.h5 (= day1/a0.h5)" in lines[0] and "day1/loop (= .)" in lines[0] and "self (= .)" in lines[0]
    train, val = split_scenes(scenes, 0.34, 3)  # no scene can be in both sets under two names
    assert not {os.path.realpath(p) for p in train} & {os.path.realpath(p) for p in val}
    list_scenes(d)  # said once per process
    assert sum("link(s)" in r.getMessage() for r in caplog.records) == 1


@needs_links
def test_the_path_without_links_is_kept_and_links_to_outside_stay(tmp_path):
    d = tmp_path / "d"
    scene(d / "z_real" / "s.h5", 0)
    (d / "a_link").symlink_to("z_real")  # sorts first, but is the alias
    scene(tmp_path / "outside.h5", 1)
    (d / "o.h5").symlink_to(tmp_path / "outside.h5")  # a linked file alone is a scene, as before
    assert rel(list_scenes(d), d) == ["o.h5", "z_real/s.h5"]
    nested = d / "z_real" / "inner"
    scene(tmp_path / "far" / "f.h5", 2)
    (tmp_path / "far" / "back").symlink_to(d)  # a link inside a linked folder, back to the root
    nested.symlink_to(tmp_path / "far")
    assert rel(list_scenes(d), d) == ["o.h5", "z_real/inner/f.h5", "z_real/s.h5"]


@needs_links
def test_a_scene_link_that_points_nowhere_is_refused_naming_its_target(tmp_path):
    """A scene file that is a dangling link (its disk not mounted) was listed as a scene, and the dataset failed
    later with "no such file or folder", which named the link but not what it pointed to. The listing refuses it
    now, naming the target; a link round a loop likewise."""
    d = tmp_path / "d"
    scene(d / "a.h5", 0)
    (d / "b.h5").symlink_to(tmp_path / "unmounted" / "b.h5")
    with pytest.raises(InputError, match=r"b\.h5: is a symbolic link to .*unmounted/b\.h5, which does not exist "
                                         r"\(remove the link, or restore what it points to\)$"):
        list_scenes(d)
    (d / "b.h5").unlink()
    (d / "c.h5").symlink_to("c.h5")
    with pytest.raises(InputError, match=r"c\.h5: is a symbolic link to c\.h5, which leads back to itself"):
        list_scenes(d)
    (d / "c.h5").unlink()
    (d / "notes.txt").symlink_to(tmp_path / "gone.txt")  # not a scene's name: not read, not refused
    assert rel(list_scenes(d), d) == ["a.h5"]


def test_a_folder_without_links_lists_as_before(tmp_path):
    for name in ("b/x.h5", "a/y.h5", "a/c/z.h5", "top.h5", "B/q.h5"):
        scene(tmp_path / name, len(name))
    scenes = list_scenes(tmp_path)
    assert scenes == sorted(tmp_path.rglob("*.h5"))  # sorted paths: the split is unchanged
    assert split_scenes(scenes, 0.4, 1) == split_scenes(sorted(tmp_path.rglob("*.h5")), 0.4, 1)


# ------------------------------------------------------------------------------------------------
# 04: ENVI data ignore value and bbl
# ------------------------------------------------------------------------------------------------
WAVES = np.arange(420.0, 721.0, 50.0)


def envi_pair(folder: Path, chw: np.ndarray, dtype: str, code: int, extra: str, interleave: str = "bil") -> Path:
    return write_envi_pair(folder, chw, extra, WAVES, dtype, code, interleave)


def counts(seed=0, h=20, w=16) -> np.ndarray:
    return np.round(np.random.default_rng(seed).random((7, h, w)) * 3900 + 100)


def test_envi_no_data_values_become_zero(tmp_path, caplog):
    raw = counts()
    raw[:, :3, :] = 65535  # a no-data border
    raw[4, 10, 5] = 65535  # one no-data value: the pixel's other bands keep their data
    hdr = envi_pair(tmp_path, raw, "<u2", 12, "data ignore value = 65535\n")
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        cube, bands, meta = read_cube(hdr)
    nodata = np.zeros((20, 16), bool)
    nodata[:3] = True
    assert np.all(cube[:, nodata] == 0) and cube[4, 10, 5] == 0
    keep = np.ones(raw.shape, bool)
    keep[:, nodata] = False
    keep[4, 10, 5] = False
    np.testing.assert_array_equal(cube[keep], raw[keep].astype(np.float32))
    assert cube.max() <= 4000 and meta["data_ignore_value"] == 65535 and meta["ignored_pixels"] == 3 * 16 + 1
    said = [r.getMessage() for r in caplog.records if "data ignore value" in r.getMessage()]
    assert len(said) == 1 and "49 of 320 pixels" in said[0] and "scene.img" in said[0]
    # the training cube: the real scene reaches 1 after normalisation (was 0.06 with 65535 as its max)
    x = SceneDataset([hdr], bands).cube(0)
    assert x[:, ~nodata].max() == pytest.approx(1.0) and x[:, nodata].max() == 0 and x[4, 10, 5] == 0


def test_envi_float_no_data_values(tmp_path):
    for value, flag in (("-9999", -9999.0), ("nan", np.nan)):  # -9999: a negative radiance unless flagged
        chw = counts(1).astype(np.float32) / 4000
        chw[:, 0, 0] = flag
        folder = tmp_path / value
        folder.mkdir()
        cube, _, meta = read_envi(envi_pair(folder, chw, "<f4", 4, f"data ignore value = {value}\n", "bsq"))
        assert np.all(cube[:, 0, 0] == 0) and meta["ignored_pixels"] == 1
        np.testing.assert_array_equal(cube[:, 1:], chw[:, 1:])


def test_envi_all_no_data_and_bad_headers_are_refused(tmp_path):
    raw = np.full((7, 6, 5), 65535.0)
    hdr = envi_pair(tmp_path, raw, "<u2", 12, "data ignore value = 65535\n")
    with pytest.raises(InputError, match=r"every value \(210\) is the data ignore value 65535") as exc:
        read_envi(hdr)
    assert "\n" not in str(exc.value)
    good = counts(2, 6, 5)
    for extra, words in (("bbl = {1, 0, 0, 0, 0, 0, 0}\n", "leaves 1 of 7 bands good"),
                         ("bbl = {1, 1, 0}\n", "lists 3 values for 7 bands"),
                         ("bbl = {1, 1, 2, 1, 1, 1, 1}\n", "1 (good band) or 0 (bad band)"),
                         ("data ignore value = {1, 2}\n", "must be one number")):
        hdr = envi_pair(tmp_path, good, "<u2", 12, extra)
        with pytest.raises(InputError, match=re.escape(words)) as exc:
            read_envi(hdr)
        assert "\n" not in str(exc.value) and "scene.hdr" in str(exc.value)


def test_envi_bad_bands_are_dropped_and_interpolated_across(tmp_path, caplog):
    raw = counts(3)
    raw[3] = 65535  # a bad band full of junk, flagged by bbl: it must not mark pixels as no-data either
    hdr = envi_pair(tmp_path, raw, "<u2", 12, "bbl = {1, 1, 1, 0, 1, 1, 1}\ndata ignore value = 65535\n"
                    "fwhm = {50, 50, 50, 50, 50, 50, 50}\n", "bip")
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        cube, bands, meta = read_envi(hdr)
    np.testing.assert_allclose(bands.centers_nm, [420, 470, 520, 620, 670, 720])
    assert len(bands.fwhm_nm) == 6
    np.testing.assert_array_equal(cube, raw[[0, 1, 2, 4, 5, 6]].astype(np.float32))
    assert meta["bad_bands_nm"] == [570.0] and meta["ignored_pixels"] == 0
    said = [r.getMessage() for r in caplog.records if "bbl" in r.getMessage()]
    assert len(said) == 1 and "570 nm" in said[0]
    x = SceneDataset([hdr], B7).cube(0)  # the camera's 570 nm band: halfway between 520 and 620 nm
    peak = cube.max()
    np.testing.assert_allclose(x[3], (cube[2] + cube[3]) / 2 / peak, rtol=1e-5)


# ------------------------------------------------------------------------------------------------
# 05: our HDF5 read window by window is checked like a preloaded read
# ------------------------------------------------------------------------------------------------
def edited(path: Path, edit) -> Path:
    scene(path, 5, size=(32, 32), scale=4000.0)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def errors_both_ways(path: Path, **kwargs) -> tuple[str, str]:
    msgs = []
    for preload in (True, False):
        with pytest.raises(InputError) as exc:
            PatchDataset(SceneDataset([path], B7, preload=preload, **kwargs), 8, 4, patches_per_epoch=4)
        msgs.append(str(exc.value))
    return msgs[0], msgs[1]


def test_windowed_reads_refuse_nan_and_negative_values_as_a_preloaded_read_does(tmp_path):
    def nan(f):
        f["cube"][2, 10:20, 10:20] = np.nan
        f["cube"][3, 0, 0] = -5.0

    def neg(f):
        f["cube"][3, :, :] = -5.0

    pre, win = errors_both_ways(edited(tmp_path / "nan.h5", nan))
    assert pre == win and "100 NaN/Inf value(s) in the cube" in win
    pre, win = errors_both_ways(edited(tmp_path / "neg.h5", neg))
    assert pre == win and "1024 negative radiance value(s) (minimum -5)" in win
    # allow_negative: clipped to 0, as a preloaded read clips them
    a = SceneDataset([tmp_path / "neg.h5"], B7, preload=True, allow_negative=True).cube(0)
    w = SceneDataset([tmp_path / "neg.h5"], B7, allow_negative=True)
    np.testing.assert_array_equal(w.window(0, 3, 5, 8, 8), a[:, 3:11, 5:13])
    assert w.window(0, 3, 5, 8, 8)[3].max() == 0


def test_a_wrong_max_value_is_not_trusted(tmp_path, caplog):
    def wrong(f):
        f.attrs["max_value"] = 1.0  # written by hand; the data peak ~4000

    path = edited(tmp_path / "max.h5", wrong)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.datasets"):
        w = SceneDataset([path], B7)
        win = w.window(0, 0, 0, 32, 32)
    a = SceneDataset([path], B7, preload=True).cube(0)
    np.testing.assert_allclose(win, a, rtol=1e-6)
    assert win.max() == pytest.approx(1.0)
    said = [r.getMessage() for r in caplog.records if "max_value" in r.getMessage()]
    assert len(said) == 1 and "max.h5" in said[0]


def test_the_windowed_check_reads_in_pieces_once_per_process(tmp_path, monkeypatch):
    path = edited(tmp_path / "pieces.h5", lambda f: f["cube"].__setitem__((slice(1, 6), 7, slice(None)), np.inf))
    for chunk in (4, 32 * 4 * 3, 32 * 32 * 4 * 2, 2**26):  # rows of a band … whole cube
        with pytest.raises(InputError, match=r": 160 NaN/Inf value\(s\) in the cube"):
            check_windowed_pixels(path, chunk_bytes=chunk)
    good = tmp_path / "good.h5"
    cube = scene(good, 6, size=(32, 32))
    reads = []
    real = ds_mod._chunks
    monkeypatch.setattr(ds_mod, "_chunks", lambda d, n: (reads.append(1), real(d, n))[1])
    assert check_windowed_pixels(good, chunk_bytes=32 * 4 * 5) == cube.max()
    assert check_windowed_pixels(good) == cube.max() and len(reads) == 1
    info = SceneDataset([good], B7).info(0)  # what evaluate's up-front check asks
    assert info.peak == cube.max() and len(reads) == 1
    with pytest.raises(InputError, match="NaN/Inf"):  # a bad file fails at info(), before any scene is scored
        SceneDataset([good, path], B7).info(1)


# ------------------------------------------------------------------------------------------------
# 07b: a scene normalised by one hot pixel
# ------------------------------------------------------------------------------------------------
def test_percentile_by_pieces_is_numpys():
    rng = np.random.default_rng(0)
    for n in (1, 2, 999, 1000, 1001, 12345):
        x = rng.random(n).astype(np.float32) ** 3
        top = _TopValues(n)
        for part in np.array_split(x, 7):
            top.add(part)
        assert top.percentile() == pytest.approx(float(np.percentile(x, 99.9)), rel=1e-6)


def test_a_hot_pixel_scene_is_warned_about_once(tmp_path, caplog):
    hot = (np.random.default_rng(1).random((7, 40, 40)) + 0.5).astype(np.float32)
    hot[:, 20, 20] = 500.0
    write_cube_h5(tmp_path / "hot.h5", hot, B7)
    np.save(tmp_path / "hot.npy", hot)  # not windowable: loaded whole
    scene(tmp_path / "fine.h5", 2, size=(40, 40))
    assert near_black_percentile(hot / hot.max()) == pytest.approx(np.percentile(hot / hot.max(), 99.9), rel=1e-6)
    assert near_black_percentile(np.load(tmp_path / "hot.npy") * 0 + 1) is None
    with caplog.at_level(logging.WARNING, logger="hsicam.data.datasets"):
        for preload in (True, False):
            d = SceneDataset([tmp_path / "hot.h5", tmp_path / "hot.npy", tmp_path / "fine.h5"], B7, preload=preload,
                             cache_size=1, source_bands=B7)
            for i in (0, 1, 2, 1, 0):
                d.info(i)
                d.window(i, 0, 0, 8, 8)
    said = [r.getMessage() for r in caplog.records if "percentile" in r.getMessage()]
    assert len(said) == 2, said  # once per scene, both loading paths
    assert any("hot.h5" in s for s in said) and any("hot.npy" in s for s in said)
    assert all("99.9th percentile" in s and "maximum 500" in s and "\n" not in s for s in said)


def test_cube_files_of_a_format_not_read_as_scenes_are_said_not_skipped_silently(tmp_path, caplog):
    """A multi-page TIFF or .npz cube beside the folder's .h5 scenes was left out of the training set without a
    word (a folder of only such files was refused, naming the formats read): one warning names them and how to
    convert one; the refusal of a folder of only such files names them too. Other files (notes, RGB previews) and
    an ENVI pair's data file are not named."""
    data = tmp_path / "data"
    for i in range(2):
        write_cube_h5(data / f"s{i}.h5", np.full((7, 16, 16), 0.5, np.float32), B7)
    import tifffile

    tifffile.imwrite(data / "c.tif", np.zeros((7, 16, 16), np.float32))
    (data / "sub").mkdir()
    np.savez(data / "sub" / "d.npz", cube=np.zeros((7, 16, 16)))
    from hsicam.data.formats import write_envi

    write_envi(data / "e.hdr", np.full((7, 16, 16), 0.5, np.float32), B7)
    (data / "notes.txt").write_text("x")
    (data / "preview.png").write_bytes(b"\x89PNG")
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        got = list_scenes(data)
    assert [p.name for p in got] == ["e.hdr", "s0.h5", "s1.h5"]
    said = [r.getMessage() for r in caplog.records if "not read as scenes" in r.getMessage()]
    assert said == [f"data: {data}: skipped 2 file(s) of a format not read as scenes (c.tif, sub/d.npz; a cube in one: "
                    "save it as .h5 with its band list, hsicam.data.formats.write_cube_h5)"]
    only = tmp_path / "only"
    only.mkdir()
    (data / "c.tif").rename(only / "c.TIFF")
    with pytest.raises(InputError, match=r"no hyperspectral scenes found .*\(skipped 1 file\(s\) of a format not read "
                                         r"as scenes \(c\.TIFF;"):
        list_scenes(only)
