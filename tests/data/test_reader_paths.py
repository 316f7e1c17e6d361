"""Bad paths of the readers (probe 22, findings 3, 8, 9 and 13): a dark or flat frame stored in
other units than the capture, an ENVI ``reflectance scale factor`` that is empty or not positive, a
MAT ``bands`` variable that holds text instead of numbers, and MAT ``bands`` in micrometres.

Every input is written in its real format (16-bit PNG, float/uint16 ``.npy``, ENVI, MAT v7.3 via
h5py, MAT v5 via scipy); the reconstructions use a real 1-epoch run of the tiny config."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import imageio.v3 as iio
import numpy as np
import pytest
import scipy.io

from cli_helpers import assert_clean_error, assert_ok, run_cli_in_process
from hsicam.config import load_config
from hsicam.data.formats import read_cube, read_envi
from hsicam.data.images import RawCorrection, read_capture, read_image_2d
from hsicam.errors import InputError

NM = np.arange(420.0, 721.0, 10.0)  # 31 bands


# ------------------------------------------------------------------------------------------------
# 3. Dark and flat frames stored in other units than the capture
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run(tmp_path_factory, cache_env) -> Path:
    """A finished 1-epoch run of the tiny config."""
    from hsicam.engine.train import train

    path = tmp_path_factory.mktemp("run") / "run"
    train(load_config("tiny", ["train.epochs=1"]), path, progress=False)
    return path


@pytest.fixture
def frames(tmp_path) -> Path:
    """A 16-bit capture with an offset of 1000 DN, and its dark frame as uint16 DN, as float in
    [0, 1] and as an 8-bit export."""
    rng = np.random.default_rng(0)
    iio.imwrite(tmp_path / "c16.png", (rng.random((48, 48)) * 30000 + 1000).astype(np.uint16))
    np.save(tmp_path / "dark_dn.npy", np.full((48, 48), 1000, np.uint16))
    np.save(tmp_path / "dark_f.npy", np.full((48, 48), 1000 / 65535, np.float32))
    iio.imwrite(tmp_path / "dark8.png", np.full((48, 48), 4, np.uint8))
    return tmp_path


def _reconstruct(folder: Path, run: Path, out: str, *extra: str):
    return run_cli_in_process("reconstruct", str(folder / "c16.png"), "--run", str(run), "--out", str(folder / out),
                              "--tile", "16", *extra)


def test_reconstruct_takes_a_dark_frame_in_the_captures_dn_and_refuses_one_in_other_units(frames, run):
    assert_ok(_reconstruct(frames, run, "dark.h5", "--dark", str(frames / "dark_dn.npy")))
    assert_ok(_reconstruct(frames, run, "black.h5", "--black-level", "1000"))
    assert_ok(_reconstruct(frames, run, "none.h5"))
    dark, black, none = (read_cube(frames / f"{n}.h5")[0] for n in ("dark", "black", "none"))
    np.testing.assert_allclose(dark, black, rtol=1e-5, atol=1e-6)  # 1000 DN off, as the black level
    assert np.abs(dark - none).max() > 1e-3
    for name, stored in (("dark_f.npy", "float32 (full scale 1)"), ("dark8.png", "uint8 (full scale 255)")):
        res = _reconstruct(frames, run, "rec.h5", "--dark", str(frames / name))
        assert_clean_error(res, f"{name}: the dark frame is stored as {stored}",
                           "c16.png is stored as uint16 (full scale 65535)", "save the dark frame as uint16")
        assert not list(frames.glob("rec*")), "nothing is written"


def test_flat_in_other_units_is_refused_when_a_black_level_is_subtracted(tmp_path):
    rng = np.random.default_rng(1)
    vignette = 0.6 + 0.4 * rng.random((32, 32))
    iio.imwrite(tmp_path / "c16.png", (vignette * 30000 + 64).astype(np.uint16))
    iio.imwrite(tmp_path / "flat8.png", np.round(vignette * 250).astype(np.uint8))
    flat = read_image_2d(tmp_path / "flat8.png", "flat field")  # the frame as read: it knows its stored type
    with pytest.raises(InputError, match=r"flat8.png: the flat field is stored as uint8 \(full scale 255\) but the "
                                         r"capture .*c16.png is stored as uint16 .*black level 64 DN"):
        read_capture(tmp_path / "c16.png", RawCorrection(black_level=64.0, flat=flat))
    img, _ = read_capture(tmp_path / "c16.png", RawCorrection(flat=flat))  # no black level: its units do not matter
    assert np.std(img) / np.mean(img) < 0.02  # the vignetting is divided out


def test_a_bare_dark_array_is_still_taken_in_the_captures_dn(tmp_path):
    """A caller who converts a frame passes an array: taken in the capture's DN; the frame as read
    (a RawImage) is checked."""
    iio.imwrite(tmp_path / "c16.png", np.full((16, 16), 3000, np.uint16))
    read = read_image_2d(_saved(tmp_path / "d.npy", np.full((16, 16), 1000 / 65535, np.float32)))
    img, report = read_capture(tmp_path / "c16.png", RawCorrection(dark=read.data * 65535))  # converted: DN
    np.testing.assert_allclose(img, 2000 / (65535 - 1000), rtol=1e-5)
    assert report["black_level_dn"] == pytest.approx(1000, rel=1e-5)
    with pytest.raises(InputError, match="d.npy: the dark frame is stored as float32"):
        read_capture(tmp_path / "c16.png", RawCorrection(dark=read))


def _saved(path: Path, arr: np.ndarray) -> Path:
    np.save(path, arr)
    return path


# ------------------------------------------------------------------------------------------------
# 8. ENVI reflectance scale factor
# ------------------------------------------------------------------------------------------------
def _envi(tmp_path: Path, extra: str, waves: str = "420,470,520", nbands: int = 3) -> Path:
    (np.random.default_rng(2).random((nbands, 8, 8)) * 10000).astype("<f4").tofile(tmp_path / "e.img")
    (tmp_path / "e.hdr").write_text(f"ENVI\nsamples = 8\nlines = 8\nbands = {nbands}\ndata type = 4\n"
                                    f"interleave = bsq\nbyte order = 0\nwavelength = {{{waves}}}\n{extra}")
    return tmp_path / "e.hdr"


def test_envi_empty_reflectance_scale_factor_is_one_line(tmp_path):
    with pytest.raises(InputError, match=r"e.hdr: ENVI header key 'reflectance scale factor' is empty"):
        read_envi(_envi(tmp_path, "reflectance scale factor = {}\n"))


@pytest.mark.parametrize("value, shown", [("0", "0"), ("-2", "-2"), ("nan", "nan"), ("inf", "inf")])
def test_envi_reflectance_scale_factor_must_be_positive(tmp_path, value, shown):
    with pytest.raises(InputError, match=rf"e.hdr: ENVI header key 'reflectance scale factor' must be a positive "
                                         rf"number, got {shown} "):
        read_envi(_envi(tmp_path, f"reflectance scale factor = {value}\n"))


def test_envi_reflectance_scale_factor_list_one_value_or_refused(tmp_path):
    """ENVI defines one factor per file: a list of equal values is that value; unequal values were
    read as the first one for every band (session 23), now refused."""
    data = (np.random.default_rng(2).random((3, 8, 8)) * 10000).astype("<f4")
    arr, _, _ = read_envi(_envi(tmp_path, "reflectance scale factor = {10000, 10000, 10000}\n"))
    np.testing.assert_allclose(arr, data / 10000, rtol=1e-6)
    with pytest.raises(InputError, match=r"e.hdr: ENVI header key 'reflectance scale factor' holds 3 different values "
                                         r"\(100 to 10000\); ENVI defines one factor for the whole file"):
        read_envi(_envi(tmp_path, "reflectance scale factor = {10000, 100, 1000}\n"))


# ------------------------------------------------------------------------------------------------
# 9. MAT 'bands' that is not a list of numbers
# ------------------------------------------------------------------------------------------------
def _mat73(path: Path, key: str, bands) -> Path:
    with h5py.File(path, "w") as f:
        f[key] = np.random.default_rng(3).random((31, 8, 8)).astype("f4")
        if callable(bands):
            bands(f)
        else:
            f["bands"] = bands
    return path


def _matlab_char(f: h5py.File) -> None:
    """``bands = '420:10:720'`` as MATLAB saves it in v7.3: uint16 character codes, class char."""
    codes = np.array([ord(c) for c in "420:10:720"], np.uint16).reshape(-1, 1)
    f.create_dataset("bands", data=codes).attrs["MATLAB_class"] = np.bytes_("char")


@pytest.mark.parametrize("make, got", [
    (lambda p: _mat73(p, "cube", "420:10:720"), "the text '420:10:720'"),  # ARAD, an HDF5 string
    (lambda p: _mat73(p, "rad", _matlab_char), "the text '420:10:720'"),  # ICVL, MATLAB's char array
    (lambda p: _mat73(p, "rad", lambda f: f.create_group("bands")), "a cell array or struct"),
    (lambda p: scipy.io.savemat(p, {"rad": np.ones((8, 8, 31)), "bands": "420:10:720"}), "the text '420:10:720'"),
    (lambda p: scipy.io.savemat(p, {"rad": np.ones((8, 8, 31)), "bands": {"start": 420}}), "a struct"),
], ids=["v73-string", "v73-char", "v73-group", "v5-string", "v5-struct"])
def test_mat_bands_that_are_not_numbers_are_one_line(tmp_path, make, got):
    make(tmp_path / "b.mat")
    with pytest.raises(InputError, match=rf"b.mat: 'bands' must be a list of numbers \(nm\), got {got}$"):
        read_cube(tmp_path / "b.mat")


# ------------------------------------------------------------------------------------------------
# 13. Band centres in micrometres (no unit in the file): the ENVI rule for every reader
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make", [
    lambda p: _mat73(p, "rad", NM / 1000),  # ICVL v7.3
    lambda p: _mat73(p, "cube", NM / 1000),  # ARAD v7.3
    lambda p: scipy.io.savemat(p, {"rad": np.ones((8, 8, 31)), "bands": NM / 1000}),  # MAT v5
], ids=["icvl-v73", "arad-v73", "v5"])
def test_mat_bands_in_micrometres_are_read_as_nm_and_said(tmp_path, caplog, make):
    make(tmp_path / "um.mat")
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"):
        _, bands, _ = read_cube(tmp_path / "um.mat")
    np.testing.assert_allclose(bands.centers_nm, NM)
    notes = [r.getMessage() for r in caplog.records]
    assert notes == [f"{tmp_path / 'um.mat'}: 'bands' units not given and values < 30; reading them as micrometres"]


_UM3 = ",".join(f"{w / 1000:g}" for w in NM[:3])
#: format -> (a file in µm with one wavelength too few, the same file right)
_UM_FILES = {
    "envi": (lambda p: _envi(p, "", waves=_UM3, nbands=4), lambda p: _envi(p, "", waves=_UM3)),
    "mat": (lambda p: _mat73(p / "um.mat", "rad", NM[:30] / 1000), lambda p: _mat73(p / "um.mat", "rad", NM / 1000)),
}


@pytest.mark.parametrize("fmt", sorted(_UM_FILES))
def test_micrometre_note_is_logged_only_for_a_file_read_without_error(tmp_path, caplog, fmt):
    bad, good = _UM_FILES[fmt]
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"), pytest.raises(InputError, match="listed|lists"):
        read_cube(bad(tmp_path))
    assert not caplog.records, [r.getMessage() for r in caplog.records]  # the error is the one line
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"):
        _, bands, _ = read_cube(good(tmp_path))
    assert bands.centers_nm[0] == pytest.approx(420.0)
    assert [r.getMessage().endswith("units not given and values < 30; reading them as micrometres")
            for r in caplog.records] == [True]
