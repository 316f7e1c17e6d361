"""Readers and writers: every format written by the test in its exact on-disk layout, read back.

The fixtures below write files the way the original tools do (MATLAB v7.3 = HDF5 with a 512-byte
MAT header and column-major arrays that h5py sees reversed; MAT v5 via scipy; CAVE's nested
folders of 16-bit PNGs; ENVI raw bytes with numpy), never through our own writers.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from hsicam.data import (
    detect_format,
    read_arad,
    read_cave,
    read_cube,
    read_envi,
    read_harvard,
    read_hsicam_h5,
    read_icvl,
    read_kaist_exr,
    read_kaist_mat,
    read_npy,
    resample_cube,
    write_cube_h5,
    write_envi,
)
from hsicam.data.formats import exr_bare_micrometres, exr_channel_wavelength, parse_envi_header, read_window
from hsicam.data.images import read_sensor_image
from hsicam.errors import InputError
from hsicam.spectral import Bands, resample_spectra

H, W = 5, 7  # deliberately non-square so that any transposition error shows
#: The 28 band centres (nm) of the KAIST scenes as TSA-Net and MST distribute them, written out here from
#: the published list (not imported from hsicam.data.formats, whose copy this checks).
MST_28_NM = (453.3, 457.6, 462.1, 466.8, 471.6, 476.5, 481.6, 486.9, 492.4, 498.0, 503.9, 509.9, 516.2, 522.7,
             529.5, 536.5, 543.8, 551.4, 558.6, 567.5, 575.3, 584.3, 594.4, 604.2, 614.4, 625.1, 636.3, 648.1)


def cube_hwc(c: int, seed: int = 0, dtype=np.float64) -> np.ndarray:
    """A (H, W, C) cube as MATLAB holds it, with distinct values everywhere."""
    rng = np.random.default_rng(seed)
    return (rng.random((H, W, c)) + 0.01).astype(dtype)


def write_mat73(path: Path, variables: dict[str, np.ndarray]) -> None:
    """Write a MATLAB v7.3 MAT-file: HDF5 with a 512-byte MAT header in the user block.

    MATLAB stores arrays column-major; HDF5 records the dimensions in reverse, so an H×W×C
    MATLAB array is an HDF5 dataset of shape (C, W, H) whose C-order data is the MATLAB data.
    """
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            value = np.asarray(value)
            ds = f.create_dataset(name, data=np.ascontiguousarray(value.T))
            ds.attrs["MATLAB_class"] = np.bytes_("double" if value.dtype == np.float64 else "single")
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    header = text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"
    with open(path, "r+b") as fh:
        fh.write(header.ljust(512, b"\x00"))


def assert_one_line_error(exc: pytest.ExceptionInfo, path: Path, *words: str) -> None:
    msg = str(exc.value)
    assert "\n" not in msg
    assert str(path) in msg or path.name in msg, msg
    for w in words:
        assert w.lower() in msg.lower(), msg


# ------------------------------------------------------------------------------------------------
# Round trips
# ------------------------------------------------------------------------------------------------
def test_icvl_mat73_roundtrip(tmp_path):
    data = cube_hwc(31)
    bands = np.arange(400.0, 701.0, 10.0)[None, :]  # MATLAB row vector 1×31
    path = tmp_path / "BGU_0403-1419-1.mat"
    write_mat73(path, {"rad": data, "bands": bands, "rgb": data[..., :3]})
    with h5py.File(path, "r") as f:  # the layout really is reversed in HDF5
        assert f["rad"].shape == (31, W, H)
    assert detect_format(path) == "icvl"
    cube, b, meta = read_cube(path)
    assert cube.dtype == np.float32 and cube.shape == (31, H, W)
    np.testing.assert_allclose(cube, np.transpose(data, (2, 0, 1)), rtol=1e-6)
    np.testing.assert_allclose(b.centers_nm, bands.ravel())
    assert meta["format"] == "icvl" and meta["mat_version"] == "7.3"
    cube2, _, _ = read_icvl(path)
    np.testing.assert_array_equal(cube, cube2)


def test_arad_mat73_roundtrip(tmp_path):
    data = cube_hwc(31, seed=1).astype(np.float32)
    bands = np.linspace(400, 700, 31)[None, :]
    path = tmp_path / "ARAD_1K_0001.mat"
    write_mat73(path, {"cube": data, "bands": bands, "norm_factor": np.array([[4095.0]])})
    assert detect_format(path) == "arad"
    cube, b, meta = read_arad(path)
    np.testing.assert_array_equal(cube, np.transpose(data, (2, 0, 1)))
    np.testing.assert_allclose(b.centers_nm, bands.ravel())
    assert meta["key"] == "cube"


def test_harvard_mat5_roundtrip(tmp_path):
    data = cube_hwc(31, seed=2)
    path = tmp_path / "img1.mat"
    scipy.io.savemat(path, {"ref": data, "lbl": np.ones((H, W), dtype=np.uint8)})
    assert detect_format(path) == "harvard"
    cube, b, meta = read_cube(path)
    np.testing.assert_allclose(cube, np.transpose(data, (2, 0, 1)), rtol=1e-6)
    np.testing.assert_allclose(b.centers_nm, np.arange(420, 721, 10))
    assert meta["mat_version"] == "5"
    read_harvard(path)


@pytest.mark.parametrize("key", ["img", "HSI"])  # HSI: MST's KAIST_CVPR2021 release
@pytest.mark.parametrize("version", ["5", "7.3"])
def test_kaist_mst_mat_roundtrip(tmp_path, version, key):
    data = cube_hwc(28, seed=3)
    path = tmp_path / "scene01.mat"
    if version == "5":
        scipy.io.savemat(path, {key: data})
    else:
        write_mat73(path, {key: data})
    assert detect_format(path) == "kaist-mat"
    cube, b, _ = read_kaist_mat(path)
    np.testing.assert_allclose(cube, np.transpose(data, (2, 0, 1)), rtol=1e-6)
    np.testing.assert_allclose(b.centers_nm, MST_28_NM, rtol=0, atol=1e-9)


def test_kaist_mat_img_expand_31_bands(tmp_path):
    data = cube_hwc(31, seed=4)
    path = tmp_path / "cave_scene.mat"
    scipy.io.savemat(path, {"img_expand": data})
    cube, b, _ = read_cube(path)
    np.testing.assert_allclose(cube, np.transpose(data, (2, 0, 1)), rtol=1e-6)
    np.testing.assert_allclose(b.centers_nm, np.arange(400, 701, 10))


def write_cave(root: Path, name: str, data16: np.ndarray) -> Path:
    """CAVE layout: <name>_ms/<name>_ms/<name>_ms_01.png … _31.png (16-bit) plus the RGB bmp."""
    import imageio.v3 as iio

    inner = root / f"{name}_ms" / f"{name}_ms"
    inner.mkdir(parents=True)
    for i in range(31):
        iio.imwrite(inner / f"{name}_ms_{i + 1:02d}.png", data16[i])
    iio.imwrite(inner / f"{name}_RGB.bmp", np.zeros((H, W, 3), np.uint8))
    return root / f"{name}_ms"


def test_cave_folder_roundtrip(tmp_path):
    rng = np.random.default_rng(5)
    data16 = rng.integers(0, 65536, size=(31, H, W), dtype=np.uint16)
    folder = write_cave(tmp_path, "balloons", data16)
    assert detect_format(folder) == "cave"
    cube, b, meta = read_cube(folder)
    np.testing.assert_allclose(cube, data16.astype(np.float64) / 65535.0, rtol=1e-6)
    np.testing.assert_allclose(b.centers_nm, np.arange(400, 701, 10))
    assert meta["scene"] == "balloons"
    cube2, _, _ = read_cave(folder / "balloons_ms")  # the inner folder works too
    np.testing.assert_array_equal(cube, cube2)


@pytest.mark.parametrize("naming", ["w{:d}nm", "S0.{:d},000000nm", "{:d}",
                                    "{:.2f}"])  # µm without a unit (dropped as < 200 nm before session 23)
def test_kaist_exr_roundtrip(tmp_path, naming):
    OpenEXR = pytest.importorskip("OpenEXR")
    if not hasattr(OpenEXR, "File"):
        pytest.skip("openexr < 3.3")
    rng = np.random.default_rng(6)
    waves = list(range(400, 701, 10))
    name = (lambda w: naming.format(w / 1000)) if naming.endswith("f}") else naming.format
    planes = {name(w): rng.random((H, W)).astype(np.float32) for w in waves}
    channels = {n: OpenEXR.Channel(p) for n, p in planes.items()}
    channels["R"] = OpenEXR.Channel(np.zeros((H, W), np.float32))  # non-spectral channels are ignored
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = tmp_path / "scene01_reflectance.exr"
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))
    assert detect_format(path) == "kaist-exr"
    cube, b, _ = read_kaist_exr(path)
    np.testing.assert_array_equal(cube, np.stack([planes[name(w)] for w in waves]))
    np.testing.assert_allclose(b.centers_nm, waves)


def test_exr_channel_names():
    assert exr_channel_wavelength("w550nm") == 550.0
    assert exr_channel_wavelength("S0.412,500000nm") == 412.5
    assert exr_channel_wavelength("T.700nm") == 700.0
    assert exr_channel_wavelength("0.55um") == pytest.approx(550.0)
    assert exr_channel_wavelength("S1.550nm") is None  # polarisation, not a band
    assert exr_channel_wavelength("R") is None
    assert exr_channel_wavelength("band_03") is None  # 3 nm is not a wavelength
    # a band named by its edges (RenderToolbox3-style spectral EXR): its centre, not the upper edge
    assert exr_channel_wavelength("415-425nm") == 420.0
    assert exr_channel_wavelength("415.00-425.00nm") == 420.0
    assert exr_channel_wavelength("S0.415,0-425,0nm") == 420.0
    assert exr_channel_wavelength("0.415-0.425um") == pytest.approx(420.0)
    assert exr_channel_wavelength("0.55") is None and exr_channel_wavelength("0.55", True) == pytest.approx(550.0)
    assert exr_bare_micrometres(["0.40", "0.55", "R", "0.7nm"]) and not exr_bare_micrometres(["0.4", "550"])
    assert not exr_bare_micrometres([str(i) for i in range(31)])  # band numbers: not a wavelength in µm
    assert not exr_bare_micrometres(["R", "G", "B"])


def envi_header(samples, lines, bands, dtype_code, interleave, byte_order=0, offset=0, waves="", extra="") -> str:
    return (f"ENVI\ndescription = {{test\n  cube}}\nsamples = {samples}\nlines   = {lines}\nbands = {bands}\n"
            f"header offset = {offset}\nfile type = ENVI Standard\ndata type = {dtype_code}\n"
            f"interleave = {interleave}\nbyte order = {byte_order}\n{waves}{extra}")


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("dtype,code,order", [("<f4", 4, 0), (">u2", 12, 1), ("<i2", 2, 0), (">f8", 5, 1)])
def test_envi_layouts(tmp_path, interleave, dtype, code, order):
    c = 6
    rng = np.random.default_rng(7)
    chw = (rng.random((c, H, W)) * 1000).astype(np.dtype(dtype).newbyteorder("="))
    disk = {"bsq": chw, "bil": chw.transpose(1, 0, 2), "bip": chw.transpose(1, 2, 0)}[interleave]
    offset = 32
    waves = "wavelength units = Nanometers\nwavelength = {\n 450.0, 460.0, 470.0,\n 480.0, 490.0, 500.0}\n"
    hdr = tmp_path / "scene.hdr"
    hdr.write_text(envi_header(W, H, c, code, interleave, order, offset, waves, "fwhm = {5,5,5,5,5,5}\n"))
    (tmp_path / "scene.img").write_bytes(b"\x00" * offset + np.ascontiguousarray(disk).astype(dtype).tobytes())
    for p in (hdr, tmp_path / "scene.img"):  # either file of the pair can be given
        assert detect_format(p) == "envi"
        cube, b, meta = read_envi(p)
        np.testing.assert_allclose(cube, chw.astype(np.float32), rtol=1e-6)
        np.testing.assert_allclose(b.centers_nm, [450, 460, 470, 480, 490, 500])
        np.testing.assert_allclose(b.fwhm_nm, 5.0)
        assert meta["interleave"] == interleave


def test_envi_micrometres_descending_and_scale(tmp_path):
    chw = np.arange(3 * H * W, dtype=np.float32).reshape(3, H, W)
    waves = "wavelength units = Micrometers\nwavelength = {0.70, 0.55, 0.40}\nreflectance scale factor = 100\n"
    hdr = tmp_path / "x.img.hdr"
    hdr.write_text(envi_header(W, H, 3, 4, "bsq", 0, 0, waves))
    chw.tofile(tmp_path / "x.img")
    cube, b, _ = read_cube(hdr)
    np.testing.assert_allclose(b.centers_nm, [400, 550, 700])
    np.testing.assert_allclose(cube, chw[::-1] / 100.0, rtol=1e-6)  # stored ascending


def test_envi_wavelengths_printed_from_float32_cover_the_round_grid(tmp_path):
    """A header that prints float32 centres (420.00002 … 719.99997) is read at 0.001 nm, so it covers a
    420-720 nm camera grid (it was refused: 719.99997 < 720)."""
    chw = np.random.default_rng(9).random((31, H, W)).astype(np.float32)
    listed = ", ".join(["420.00002", *(f"{w:.5f}" for w in range(430, 720, 10)), "719.99997"])
    hdr = tmp_path / "f32.hdr"
    hdr.write_text(envi_header(W, H, 31, 4, "bsq", 0, 0, f"wavelength units = nm\nwavelength = {{{listed}}}\n"))
    chw.tofile(tmp_path / "f32.img")
    cube, b, _ = read_cube(hdr)
    np.testing.assert_array_equal(b.centers_nm, np.arange(420, 721, 10))
    assert b.covers(Bands.uniform(420, 720, 10))
    np.testing.assert_array_equal(cube, chw)


def test_envi_header_in_latin1_with_micrometres(tmp_path):
    chw = np.ones((3, H, W), np.float32)
    text = envi_header(W, H, 3, 4, "bsq", 0, 0, "wavelength units = µm\nwavelength = {0.45, 0.55, 0.65}\n")
    hdr = tmp_path / "lat.hdr"
    hdr.write_bytes(text.encode("latin-1"))  # 'µ' is one byte 0xB5: not UTF-8
    chw.tofile(tmp_path / "lat.img")
    _, b, _ = read_cube(hdr)
    np.testing.assert_allclose(b.centers_nm, [450, 550, 650])


@pytest.mark.parametrize("units, listed", [("Micrometres", "0.45, 0.55, 0.65"), ("micrometre", "0.45, 0.55, 0.65"),
                                           ("\u03bcm", "0.45, 0.55, 0.65"), ("Nanometres", "450, 550, 650"),
                                           ("nanometre", "450, 550, 650")])
def test_envi_wavelength_units_in_british_spelling_or_with_a_greek_mu(tmp_path, units, listed):
    """'Micrometres', 'Nanometres' and 'μm' (Greek mu, U+03BC, beside the micro sign U+00B5) are the units they name;
    they were refused as unsupported units."""
    chw = np.ones((3, H, W), np.float32)
    hdr = tmp_path / "u.hdr"
    hdr.write_text(envi_header(W, H, 3, 4, "bsq", 0, 0, f"wavelength units = {units}\nwavelength = {{{listed}}}\n"),
                   encoding="utf-8")
    chw.tofile(tmp_path / "u.img")
    _, b, _ = read_cube(hdr)
    np.testing.assert_allclose(b.centers_nm, [450, 550, 650])


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
def test_envi_writer_roundtrip(tmp_path, interleave):
    rng = np.random.default_rng(8)
    chw = rng.random((4, H, W)).astype(np.float32)
    bands = Bands.from_centers([410.0, 500.5, 600.0, 700.0], [8.0, 9.0, 10.0, 11.0])
    hdr, data = write_envi(tmp_path / "out.hdr", chw, bands, interleave=interleave, byte_order="big")
    assert hdr.is_file() and data.is_file() and data.stat().st_size == chw.nbytes
    h = parse_envi_header(hdr)
    assert h["interleave"] == interleave and h["byte order"] == "1"
    cube, b, _ = read_cube(hdr)
    np.testing.assert_array_equal(cube, chw)
    np.testing.assert_allclose(b.centers_nm, bands.centers_nm)
    np.testing.assert_allclose(b.fwhm_nm, bands.fwhm_nm)


def test_envi_writer_integer_types_keep_a_cube_of_fractions(tmp_path):
    """`write_envi(..., dtype="uint16")` of a [0, 1] cube rounded every value to 0 or 1 without a word. With
    reflectance_scale the data are scaled and the header's reflectance scale factor says so (read_envi divides it
    out, to within the integer step); without it such a cube is refused. Counts (peak > 1) are rounded as before."""
    chw = np.random.default_rng(10).random((4, H, W)).astype(np.float32)
    bands = Bands.from_centers([410.0, 500.5, 600.0, 700.0])
    with pytest.raises(InputError, match=r"would be rounded to 0s and 1s; pass reflectance_scale"):
        write_envi(tmp_path / "frac.hdr", chw, bands, dtype="uint16")
    assert not (tmp_path / "frac.hdr").exists() and not (tmp_path / "frac.img").exists()
    hdr, _ = write_envi(tmp_path / "scaled.hdr", chw, bands, dtype="uint16", reflectance_scale=10000)
    assert parse_envi_header(hdr)["reflectance scale factor"] == "10000"
    cube, _, _ = read_cube(hdr)
    np.testing.assert_allclose(cube, chw, atol=0.5e-4 + 1e-7)
    counts = np.round(chw * 4000.0)
    write_envi(tmp_path / "counts.hdr", counts, bands, dtype="uint16")
    np.testing.assert_array_equal(read_cube(tmp_path / "counts.hdr")[0], counts)
    with pytest.raises(InputError, match="reflectance_scale must be a positive number"):
        write_envi(tmp_path / "bad.hdr", chw, bands, dtype="uint16", reflectance_scale=-1)


def test_envi_writer_refuses_a_boolean_reflectance_scale(tmp_path):
    """`reflectance_scale=True` passed the number check (a bool is an int) as a scale of 1, which also skipped the
    refusal of a cube of fractions: the [0, 1] cube was written as uint16 0s and 1s without a word. Refused now,
    before any file, as the other values that are not a positive number."""
    chw = np.random.default_rng(11).random((4, H, W)).astype(np.float32)
    bands = Bands.from_centers([410.0, 500.5, 600.0, 700.0])
    with pytest.raises(InputError, match=r"^write_envi: reflectance_scale must be a positive number, got True$"):
        write_envi(tmp_path / "flag.hdr", chw, bands, dtype="uint16", reflectance_scale=True)
    assert not list(tmp_path.iterdir())


def test_envi_writer_takes_numpy_scalars_as_reflectance_scale(tmp_path):
    """A scale read from a file or computed with numpy (np.float32, np.int64) was refused as "not a positive number"
    while np.float64 (a float subclass) was taken. Every real numpy scalar is taken now, and writes what a Python
    number of the same value writes; numpy's boolean is refused as Python's is."""
    chw = np.random.default_rng(12).random((4, H, W)).astype(np.float32)
    bands = Bands.from_centers([410.0, 500.5, 600.0, 700.0])
    ref_hdr, ref_img = write_envi(tmp_path / "ref.hdr", chw, bands, dtype="uint16", reflectance_scale=10000)
    for i, scale in enumerate((np.float32(10000), np.int64(10000), np.uint16(10000), np.float64(10000))):
        hdr, img = write_envi(tmp_path / f"s{i}.hdr", chw, bands, dtype="uint16", reflectance_scale=scale)
        assert img.read_bytes() == ref_img.read_bytes()
        assert parse_envi_header(hdr)["reflectance scale factor"] == "10000"
        np.testing.assert_array_equal(read_cube(hdr)[0], read_cube(ref_hdr)[0])
    with pytest.raises(InputError, match=r"reflectance_scale must be a positive number, got (np\.)?True_?$"):
        write_envi(tmp_path / "flag.hdr", chw, bands, dtype="uint16", reflectance_scale=np.True_)
    with pytest.raises(InputError, match="reflectance_scale must be a positive number"):
        write_envi(tmp_path / "neg.hdr", chw, bands, dtype="uint16", reflectance_scale=np.float32(-2))


@pytest.mark.parametrize("folder_is", ["hdr", "img"])
def test_envi_writer_refuses_a_folder_in_place_of_either_file_and_writes_neither(tmp_path, folder_is):
    """write_envi to a name whose header or data file is an existing folder ended in Python's IsADirectoryError
    (the data file written first, then removed). One line naming the folder now, before either file is written;
    write_cube_h5 to a folder likewise (both write through hsicam.io.atomic_path)."""
    chw = np.random.default_rng(13).random((4, H, W)).astype(np.float32)
    bands = Bands.from_centers([410.0, 500.5, 600.0, 700.0])
    (tmp_path / f"pair.{folder_is}").mkdir()
    with pytest.raises(InputError, match=rf"pair\.{folder_is}: is an existing folder"):
        write_envi(tmp_path / "pair.hdr", chw, bands)
    assert [p.name for p in tmp_path.iterdir()] == [f"pair.{folder_is}"]
    assert not list((tmp_path / f"pair.{folder_is}").iterdir())
    (tmp_path / "cube.h5").mkdir()
    with pytest.raises(InputError, match=r"cube\.h5: is an existing folder; a file is needed here$"):
        write_cube_h5(tmp_path / "cube.h5", chw, bands)


def test_npy_roundtrip_with_and_without_bands(tmp_path):
    data = np.random.default_rng(9).random((31, H, W)).astype(np.float32)
    path = tmp_path / "cube.npy"
    np.save(path, data)
    cube, b, meta = read_cube(path)
    np.testing.assert_array_equal(cube, data)
    np.testing.assert_allclose(b.centers_nm, np.arange(400, 701, 10))  # documented default grid
    assert meta["bands_assumed"] is True
    given = Bands.paper()
    _, b2, meta2 = read_npy(path, bands=given)
    assert b2.matches(given) and meta2["bands_assumed"] is False


def test_npy_without_bands_warns_once_per_file_of_the_grid_it_assumes(tmp_path, caplog):
    """read_cube of a .npy without ``bands`` took 400-700 nm with an INFO line only, which a library user does not
    see (Python shows WARNING and above by default): a 420-720 nm cube was resampled from the wrong wavelengths
    without a word. Now a warning, once per file (a dataset reads its scenes again), none when bands are given."""
    paths = [tmp_path / "a.npy", tmp_path / "b.npy"]
    for p, c in zip(paths, (31, 1)):
        np.save(p, np.random.default_rng(9).random((c, H, W)).astype(np.float32))
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        for p in [*paths, *paths]:
            read_cube(p)
        read_npy(paths[0], bands=Bands.paper())
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"{paths[0]}: the file carries no wavelengths and none were given for it; assuming 31 bands evenly spaced "
        "over 400-700 nm",
        f"{paths[1]}: the file carries no wavelengths and none were given for it; assuming one band at 550 nm"]


def test_npy_stored_bands_last_is_named_with_the_move(tmp_path, caplog):
    """A (height, width, bands) .npy was read as (bands, height, width) with only the assumed grid said (40 "bands"
    for a 40×48×31 cube: a helper's hunt, session 71); the warning, and the refusal of a given grid that matches
    its last axis, now say how to move the bands first. A cube whose last axis is not its shortest: not said."""
    hwc = tmp_path / "hwc.npy"
    np.save(hwc, np.random.default_rng(1).random((40, 48, 31)).astype(np.float32))
    move = "np.save(path, np.moveaxis(cube, -1, 0))"
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        read_cube(hwc)
    [msg] = [r.getMessage() for r in caplog.records]
    assert msg == (f"{hwc}: the file carries no wavelengths and none were given for it; assuming 40 bands evenly "
                   f"spaced over 400-700 nm; its last axis, the shortest, has 31: a cube stored bands last (height, "
                   f"width, bands) is {move}")
    with pytest.raises(InputError) as exc:
        read_npy(hwc, bands=Bands.paper())
    assert str(exc.value) == (f"{hwc}: the cube has 40 bands (axis 0 of a (bands, height, width) array) but the band "
                              f"grid given for it has 31; its last axis has 31: a cube stored bands last (height, "
                              f"width, bands) is {move}")
    chw = tmp_path / "chw.npy"
    np.save(chw, np.random.default_rng(1).random((31, 20, 24)).astype(np.float32))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        read_cube(chw)
    assert "moveaxis" not in caplog.records[0].getMessage()


def test_hsicam_h5_layout_written_by_hand(tmp_path):
    data = np.random.default_rng(10).random((3, H, W)).astype(np.float32)
    path = tmp_path / "mine.h5"
    with h5py.File(path, "w") as f:
        f["cube"] = data
        f["bands_nm"] = np.array([450.0, 550.0, 650.0])
        f["fwhm_nm"] = np.array([20.0, 20.0, 20.0])
        f.attrs["format"] = "hsicam-cube"
    assert detect_format(path) == "hsicam"
    cube, b, _ = read_cube(path)
    np.testing.assert_array_equal(cube, data)
    np.testing.assert_allclose(b.centers_nm, [450, 550, 650])
    np.testing.assert_allclose(b.fwhm_nm, 20.0)


def test_hsicam_h5_writer_roundtrip_and_determinism(tmp_path):
    data = np.random.default_rng(11).random((31, H, W)).astype(np.float32)
    meta = {"scene": "x", "values": [1, 2.5], "nested": {"a": True}}
    p1 = write_cube_h5(tmp_path / "a.h5", data, Bands.paper(), meta)
    p2 = write_cube_h5(tmp_path / "b.h5", data, Bands.paper(), meta)
    assert p1.read_bytes() == p2.read_bytes()  # no timestamps in the file
    cube, b, m = read_hsicam_h5(p1)
    np.testing.assert_array_equal(cube, data)
    assert b.matches(Bands.paper())
    assert m["scene"] == "x" and m["values"] == [1, 2.5] and m["nested"] == {"a": True}
    win, wb = read_window(p1, 1, 2, 3, 4)
    np.testing.assert_array_equal(win, data[:, 1:4, 2:6])
    assert not list(tmp_path.glob(".*"))  # no temporary files left


# ------------------------------------------------------------------------------------------------
# Resampling
# ------------------------------------------------------------------------------------------------
def test_resampling_is_exact_on_linear_spectra():
    src = Bands.from_centers([400.0, 405.0, 421.0, 450.0, 500.0, 610.0, 700.0, 730.0])
    dst = Bands.uniform(420.0, 720.0, 10.0)
    a, slope = 0.2, 0.003
    spectrum = a + slope * (src.centers_nm - 400.0)
    cube = np.broadcast_to(spectrum[:, None, None], (len(src), 2, 3)) * np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    out = resample_cube(cube, src, dst)
    expected = (a + slope * (dst.centers_nm - 400.0))[:, None, None] * np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    assert out.dtype == np.float32


def test_resampling_refuses_to_extrapolate():
    cube = np.ones((31, 2, 2), np.float32)
    with pytest.raises(InputError, match=r"scene\.mat.*420-720 nm.*400-700 nm"):
        resample_cube(cube, Bands.uniform(400, 700, 10), Bands.paper(), source="scene.mat")
    out = resample_cube(cube, Bands.uniform(400, 700, 10), Bands.uniform(420, 700, 10))
    assert out.shape == (29, 2, 2)


def test_resample_spectra_matches_numpy_interp():
    src = Bands.uniform(400, 700, 10)
    # bands as wide as the data's (10 nm): point samples (wider bands integrate: tests/data/test_data_band_response.py)
    dst = Bands.from_centers(np.linspace(401.3, 699.1, 17), 10.0)
    rng = np.random.default_rng(0)
    s = rng.random(len(src))
    np.testing.assert_allclose(resample_spectra(s, src, dst), np.interp(dst.centers_nm, src.centers_nm, s))


# ------------------------------------------------------------------------------------------------
# Bad input: one clear InputError naming the file and the problem
# ------------------------------------------------------------------------------------------------
def test_truncated_hdf5(tmp_path):
    p = write_cube_h5(tmp_path / "t.h5", np.ones((31, 40, 40), np.float32), Bands.paper())
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "truncated")


def test_truncated_mat73(tmp_path):
    p = tmp_path / "icvl.mat"
    write_mat73(p, {"rad": cube_hwc(31), "bands": np.arange(400.0, 701.0, 10.0)[None]})
    p.write_bytes(p.read_bytes()[:1500])
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p)


def test_corrupt_hdf5(tmp_path):
    p = tmp_path / "c.h5"
    p.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)) * 8)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "corrupt")


def test_truncated_mat5(tmp_path):
    p = tmp_path / "h.mat"
    scipy.io.savemat(p, {"ref": cube_hwc(31)})
    p.write_bytes(p.read_bytes()[:400])
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p)


def test_truncated_npy(tmp_path):
    p = tmp_path / "t.npy"
    np.save(p, np.ones((31, 8, 8), np.float32))
    p.write_bytes(p.read_bytes()[:300])
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p)


def test_truncated_envi(tmp_path):
    hdr = tmp_path / "e.hdr"
    hdr.write_text(envi_header(W, H, 3, 4, "bsq", waves="wavelength = {400, 500, 600}\n"))
    np.ones((2, H, W), np.float32).tofile(tmp_path / "e.img")
    with pytest.raises(InputError) as exc:
        read_cube(hdr)
    assert_one_line_error(exc, tmp_path / "e.img", "truncated")


def test_envi_header_mistakes_are_named(tmp_path):
    """A negative header offset, nanometre values labelled micrometres, and the wrong byte order (which
    turns floats into NaN/Inf) each get a message saying what to fix in the header."""
    chw = np.full((3, H, W), np.frombuffer(b"\xff\xff\x80\x3f", "<f4")[0], np.float32)  # NaN read big-endian
    chw.astype("<f4").tofile(tmp_path / "e.img")
    nm = "wavelength = {450, 550, 650}\n"
    cases = [(envi_header(W, H, 3, 4, "bsq", 0, -100, nm), "header offset must be >= 0"),
             (envi_header(W, H, 3, 4, "bsq", 0, 0, "wavelength units = Micrometers\n" + nm), "are nanometres"),
             (envi_header(W, H, 3, 4, "bsq", 1, 0, nm), "fix 'byte order'")]
    for text, fragment in cases:
        (tmp_path / "e.hdr").write_text(text)
        with pytest.raises(InputError) as exc:
            read_cube(tmp_path / "e.hdr")
        assert_one_line_error(exc, tmp_path / "e", fragment)
    (tmp_path / "e.hdr").write_text(envi_header(W, H, 3, 4, "bsq", 0, 0, nm))  # the right byte order reads
    np.testing.assert_allclose(read_cube(tmp_path / "e.hdr")[0], chw)


def test_truncated_exr(tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    p = tmp_path / "t.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"w500nm": OpenEXR.Channel(np.ones((64, 64), np.float32))}) as f:
        f.write(str(p))
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p)


def test_missing_keys(tmp_path):
    p = tmp_path / "nobands.h5"
    with h5py.File(p, "w") as f:
        f["cube"] = np.ones((3, 4, 4), np.float32)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "bands_nm")

    m = tmp_path / "other.mat"
    scipy.io.savemat(m, {"something": np.ones((3, 3))})
    with pytest.raises(InputError) as exc:
        read_cube(m)
    assert_one_line_error(exc, m, "something", "HSI", "rename the cube's variable", "write_cube_h5")

    i = tmp_path / "icvl.mat"
    write_mat73(i, {"cube": cube_hwc(31), "bands": np.arange(400.0, 701.0, 10.0)[None]})
    with pytest.raises(InputError) as exc:
        read_icvl(i)  # the explicit reader insists on its key
    assert_one_line_error(exc, i, "missing key 'rad'")

    hdr = tmp_path / "e.hdr"
    hdr.write_text("ENVI\nlines = 5\nbands = 3\ndata type = 4\n")
    (tmp_path / "e.img").write_bytes(b"\x00" * 1000)
    with pytest.raises(InputError) as exc:
        read_cube(hdr)
    assert_one_line_error(exc, hdr, "samples")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_inf(tmp_path, bad):
    data = np.ones((31, 4, 4), np.float32)
    data[3, 1, 2] = bad
    p = tmp_path / "bad.npy"
    np.save(p, data)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "NaN/Inf")

    m = tmp_path / "bad.mat"
    scipy.io.savemat(m, {"ref": np.moveaxis(data, 0, -1)})
    with pytest.raises(InputError) as exc:
        read_cube(m)
    assert_one_line_error(exc, m, "NaN/Inf")


def test_negative_radiance(tmp_path):
    data = np.ones((31, 4, 4), np.float32)
    data[0, 0, 0] = -0.5
    p = tmp_path / "neg.npy"
    np.save(p, data)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "negative")
    cube, _, _ = read_cube(p, allow_negative=True)
    assert cube.min() == 0.0


def test_wrong_ndim(tmp_path):
    p = tmp_path / "flat.npy"
    np.save(p, np.ones((4, 4), np.float32))
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "3-D")
    m = tmp_path / "flat.mat"
    scipy.io.savemat(m, {"ref": np.ones((4, 4))})
    with pytest.raises(InputError) as exc:
        read_cube(m)
    assert_one_line_error(exc, m, "3-D")


def test_unknown_formats(tmp_path):
    t = tmp_path / "notes.txt"
    t.write_text("hello")
    with pytest.raises(InputError) as exc:
        read_cube(t)
    assert_one_line_error(exc, t, "unknown format")
    e = tmp_path / "empty.h5"
    e.write_bytes(b"")
    with pytest.raises(InputError) as exc:
        read_cube(e)
    assert_one_line_error(exc, e, "empty")
    d = tmp_path / "folder"
    d.mkdir()
    with pytest.raises(InputError) as exc:
        read_cube(d)
    assert_one_line_error(exc, d, "unknown format")
    with pytest.raises(InputError) as exc:
        read_cube(tmp_path / "missing.h5")
    assert_one_line_error(exc, tmp_path / "missing.h5", "no such file")


def test_cave_missing_band(tmp_path):
    data16 = np.ones((31, H, W), np.uint16)
    folder = write_cave(tmp_path, "flowers", data16)
    next(folder.rglob("flowers_ms_07.png")).unlink()
    with pytest.raises(InputError) as exc:
        read_cube(folder)
    assert_one_line_error(exc, folder, "07")
    assert re.search(r"missing band image", str(exc.value))


def test_band_count_mismatch(tmp_path):
    p = tmp_path / "arad.mat"
    write_mat73(p, {"cube": cube_hwc(31), "bands": np.arange(400.0, 701.0, 20.0)[None]})
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert_one_line_error(exc, p, "31 bands")


# ------------------------------------------------------------------------------------------------
# Band lists and axis order of MAT / HDF5 files (probe 28): files written with scipy.io.savemat,
# h5py and numpy in the real layouts, holding an analytic scene whose value depends on the
# wavelength, the row and the column, so a relabelled band, a flip or a transpose shows.
# ------------------------------------------------------------------------------------------------
NM_400_700 = np.arange(400.0, 701.0, 10.0)


def scene(lam_nm, h: int = H, w: int = W) -> np.ndarray:
    """(len(lam), h, w): lam/1000 + row/100 + col/10 (every value distinct, all positive)."""
    lam = np.asarray(lam_nm, dtype=np.float64)
    return lam[:, None, None] / 1000 + np.arange(h)[None, :, None] / 100 + np.arange(w)[None, None, :] / 10


def write_mat(path: Path, version: str, variables: dict[str, np.ndarray]) -> Path:
    """A MAT file: v5 through scipy.io.savemat, v7.3 through :func:`write_mat73` (MATLAB's layout)."""
    if version == "5":
        scipy.io.savemat(path, variables)
    else:
        write_mat73(path, variables)
    return path


def check_scene(cube: np.ndarray, b: Bands, h: int = H, w: int = W) -> None:
    assert cube.shape == (len(b), h, w)
    np.testing.assert_allclose(cube, scene(b.centers_nm, h, w), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("key, name, version", [
    ("ref", "bands", "5"),  # Harvard's key with the file's own 400-700 nm: not relabelled 420-720
    ("ref", "wavelength", "7.3"),
    ("cube", "wavelength", "5"),
    ("rad", "lambda", "7.3"),
    ("img", "wl", "5"),
    ("cube", "Wavelengths", "7.3"),
])
def test_mat_band_list_is_used_whatever_the_cube_key_and_name(tmp_path, key, name, version):
    grid = NM_400_700 if key == "ref" else NM_400_700 + 20.0  # never the grid the key would assume
    path = write_mat(tmp_path / "s.mat", version, {key: np.transpose(scene(grid), (1, 2, 0)), name: grid[None, :]})
    cube, b, meta = read_cube(path)
    np.testing.assert_array_equal(b.centers_nm, grid)
    check_scene(cube, b)
    assert meta["bands_key"] == name and meta["assumed_grid"] is None and meta["mat_version"] == version


@pytest.mark.parametrize("variables, grid, said", [
    ({"ref": scene(np.arange(420.0, 721.0, 10.0)), "lbl": np.ones((H, W), np.uint8)}, np.arange(420.0, 721.0, 10.0),
     "Harvard's 31 bands, 420-720 nm in 10 nm steps"),
    ({"rad": scene(NM_400_700)}, NM_400_700, "31 bands, 400-700 nm in 10 nm steps"),
    ({"img": scene(MST_28_NM)}, np.array(MST_28_NM), "MST's 28 KAIST bands, 453.3-648.1 nm"),
    ({"img": scene(NM_400_700)}, NM_400_700, "31 bands, 400-700 nm in 10 nm steps (CAVE's grid; KAIST's own 31 bands "
                                             "span 420-720 nm: a KAIST file needs its band list)"),
], ids=["harvard", "icvl", "kaist-28", "kaist-31"])
def test_mat_without_band_list_assumes_the_grid_and_says_so(tmp_path, caplog, variables, grid, said):
    key = next(iter(variables))
    variables = {k: np.transpose(v, (1, 2, 0)) if k == key else v for k, v in variables.items()}
    path = write_mat(tmp_path / "s.mat", "5", variables)
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        cube, b, meta = read_cube(path)
    np.testing.assert_allclose(b.centers_nm, grid)
    check_scene(cube, b)
    assert meta["assumed_grid"] == said and meta["bands_key"] is None
    notes = [r.getMessage() for r in caplog.records]
    assert len(notes) == 1 and str(path) in notes[0] and f"assuming {said}" in notes[0], notes
    # a 31-band MST-style file may be CAVE's (400-700 nm) or KAIST's (420-720 nm): the guess is a warning
    assert caplog.records[0].levelno == (logging.WARNING if "KAIST's own" in said else logging.INFO)


def test_assumed_grid_note_for_a_range_refusal(tmp_path):
    """The words a coverage refusal appends (datasets, simulate): the grid was assumed, and which."""
    from hsicam.data.formats import assumed_bands_note

    rad = write_mat(tmp_path / "r.mat", "5", {"rad": np.transpose(scene(NM_400_700), (1, 2, 0))})
    cube, b, meta = read_cube(rad)
    with pytest.raises(InputError) as exc:
        resample_cube(cube, b, Bands.paper(), source=rad)
    text = f"{exc.value} ({assumed_bands_note(meta)})"
    assert "not covered by the data's 400-700 nm" in text
    assert text.endswith("(the file lists no wavelengths, so its bands were assumed to be 31 bands, 400-700 nm in 10 nm "
                         "steps; add its band list as a variable 'bands' (nm))")
    listed = write_mat(tmp_path / "l.mat", "5", {"rad": np.transpose(scene(NM_400_700), (1, 2, 0)), "bands": NM_400_700})
    assert assumed_bands_note(read_cube(listed)[2]) is None
    np.save(tmp_path / "c.npy", scene(NM_400_700).astype(np.float32))
    assert assumed_bands_note(read_cube(tmp_path / "c.npy")[2]) == ("the file carries no wavelengths, so its bands "
                                                                   "were taken as 31 bands evenly spaced over 400-700 nm")


def test_an_unknown_vector_of_the_band_count_is_pointed_at(tmp_path, caplog):
    path = write_mat(tmp_path / "s.mat", "5", {"rad": np.transpose(scene(NM_400_700), (1, 2, 0)),
                                              "lam_nm": NM_400_700 + 20})
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        read_cube(path)
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "assuming 31 bands, 400-700 nm" in caplog.text and "if 'lam_nm' holds the wavelengths, name it 'bands'" in caplog.text


def test_two_different_band_lists_are_refused(tmp_path):
    path = write_mat(tmp_path / "s.mat", "5", {"cube": np.transpose(scene(NM_400_700), (1, 2, 0)),
                                              "bands": NM_400_700, "wavelength": NM_400_700 + 20})
    with pytest.raises(InputError) as exc:
        read_cube(path)
    assert_one_line_error(exc, path, "two different band lists", "'bands' (31 values, 400-700 nm)",
                          "'wavelength' (31 values, 420-720 nm)")
    same = write_mat(tmp_path / "t.mat", "5", {"cube": np.transpose(scene(NM_400_700), (1, 2, 0)),
                                              "bands": NM_400_700, "wavelength": NM_400_700 / 1000})  # µm, equal
    np.testing.assert_array_equal(read_cube(same)[1].centers_nm, NM_400_700)


def write_plain_h5(path: Path, variables: dict[str, np.ndarray]) -> Path:
    """A Python user's HDF5 file: h5py, C order, no MATLAB user block or attributes."""
    with h5py.File(path, "w") as f:
        for name, value in variables.items():
            f[name] = value
    return path


@pytest.mark.parametrize("key", ["cube", "rad", "img", "ref"])
@pytest.mark.parametrize("order", ["chw", "hwc"])
def test_plain_hdf5_is_read_in_c_order(tmp_path, caplog, key, order):
    grid = NM_400_700 + 20.0
    chw = scene(grid)
    stored = chw if order == "chw" else np.transpose(chw, (1, 2, 0))
    path = write_plain_h5(tmp_path / "plain.h5", {key: stored, "bands": grid})
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        cube, b, meta = read_cube(path)
    np.testing.assert_array_equal(b.centers_nm, grid)
    check_scene(cube, b)
    assert "mat_version" not in meta and meta["container"] == "HDF5"
    said = "(C, H, W)" if order == "chw" else "(H, W, C)"
    assert f"read in C order (as h5py and NumPy write it) as {said}" in caplog.text


def test_plain_hdf5_without_band_list_uses_the_axis_with_the_grid_count(tmp_path):
    path = write_plain_h5(tmp_path / "h.h5", {"ref": np.transpose(scene(np.arange(420.0, 721.0, 10.0)), (1, 2, 0))})
    cube, b, meta = read_cube(path)
    np.testing.assert_array_equal(b.centers_nm, np.arange(420.0, 721.0, 10.0))
    check_scene(cube, b)
    assert meta["assumed_grid"].startswith("Harvard's")


def test_hdf5_with_matlab_marks_is_read_column_major(tmp_path):
    """A MATLAB v7.3 file is H×W×C whether it is told by its user block or only by the datasets'
    MATLAB_class attributes (a copy that lost the user block)."""
    grid = NM_400_700
    hwc = np.transpose(scene(grid), (1, 2, 0))
    path = tmp_path / "m.mat"
    write_mat73(path, {"cube": hwc, "bands": grid[None, :]})
    stripped = tmp_path / "stripped.h5"
    with h5py.File(path, "r") as src, h5py.File(stripped, "w") as dst:
        for name in src:
            src.copy(name, dst)
    assert not stripped.read_bytes().startswith(b"MATLAB")
    for p in (path, stripped):
        cube, b, meta = read_cube(p)
        check_scene(cube, b)
        assert meta["mat_version"] == "7.3"


def test_plain_hdf5_with_an_ambiguous_axis_order_is_refused(tmp_path):
    data = np.ones((31, 6, 31))
    path = write_plain_h5(tmp_path / "amb.h5", {"cube": data, "bands": NM_400_700})
    with pytest.raises(InputError) as exc:
        read_cube(path)
    assert_one_line_error(exc, path, "without a MATLAB 7.3 header", "cannot tell whether it is stored (C, H, W) or (H, W, C)")
    odd = write_plain_h5(tmp_path / "odd.h5", {"cube": np.ones((5, 31, 6)), "bands": NM_400_700})
    with pytest.raises(InputError) as exc:
        read_cube(odd)
    assert_one_line_error(exc, odd, "5×31×6", "neither its first nor its last axis")


def test_micrometre_band_lists_in_float32_land_on_whole_nanometres(tmp_path):
    """float32 0.70 µm × 1000 is 699.99998 nm: a 420-700 nm camera refused the file (probe 28)."""
    um32 = (NM_400_700 / 1000).astype(np.float32)
    assert float(um32[-1]) * 1000 < 700 - 1e-6  # the trap
    path = tmp_path / "icvl.mat"
    write_mat73(path, {"rad": np.transpose(scene(NM_400_700), (1, 2, 0)), "bands": um32[None, :]})
    cube, b, _ = read_cube(path)
    np.testing.assert_array_equal(b.centers_nm, NM_400_700)
    camera = Bands.uniform(420.0, 700.0, 10.0)
    np.testing.assert_allclose(resample_cube(cube, b, camera), scene(camera.centers_nm), rtol=1e-6)
    # float32 in nm: the decimal written, not its float32 neighbour (MST's grid matches exactly)
    mst = tmp_path / "mst.mat"
    scipy.io.savemat(mst, {"img": np.transpose(scene(MST_28_NM), (1, 2, 0)), "bands": np.float32(MST_28_NM)})
    np.testing.assert_array_equal(read_cube(mst)[1].centers_nm, MST_28_NM)
    # ENVI text in µm and EXR names in µm are rounded the same way
    hdr = tmp_path / "e.hdr"
    hdr.write_text(envi_header(W, H, 3, 5, "bsq", waves="wavelength units = Micrometers\nwavelength = {0.4201, 0.55, 0.7}\n"))
    scene([420.1, 550, 700]).astype("<f8").tofile(tmp_path / "e.img")
    assert 0.4201 * 1000 != 420.1  # the float64 trap of a text list
    np.testing.assert_array_equal(read_cube(hdr)[1].centers_nm, [420.1, 550.0, 700.0])
    assert exr_channel_wavelength("0.4201um") == 420.1 and exr_channel_wavelength("0.4201", True) == 420.1


def write_hsicam_by_hand(path: Path, cube: np.ndarray, centres, fwhm) -> Path:
    with h5py.File(path, "w") as f:
        f["cube"] = cube.astype(np.float32)
        f["bands_nm"] = np.asarray(centres, dtype=np.float64)
        f["fwhm_nm"] = np.asarray(fwhm, dtype=np.float64)
        f.attrs["format"] = "hsicam-cube"
        f.attrs["max_value"] = float(cube.max())
    return path


@pytest.mark.parametrize("fmt", ["mat5", "mat73", "plain-h5", "hsicam"])
def test_descending_band_lists_are_read_ascending_with_the_cube(tmp_path, fmt):
    desc = NM_400_700[::-1] + 30.0  # 730 … 430
    chw = scene(desc)  # plane k holds wavelength desc[k]
    hwc = np.transpose(chw, (1, 2, 0))
    path = {"mat5": lambda p: write_mat(p, "5", {"cube": hwc, "bands": desc}),
            "mat73": lambda p: write_mat(p, "7.3", {"cube": hwc, "bands": desc[None, :]}),
            "plain-h5": lambda p: write_plain_h5(p, {"cube": chw, "bands": desc}),
            "hsicam": lambda p: write_hsicam_by_hand(p, chw, desc, np.linspace(5, 8, desc.size)),
            }[fmt](tmp_path / ("desc.mat" if fmt.startswith("mat") else "desc.h5"))
    cube, b, _ = read_cube(path)
    np.testing.assert_array_equal(b.centers_nm, desc[::-1])
    check_scene(cube, b)
    if fmt == "hsicam":
        np.testing.assert_array_equal(b.fwhm_nm, np.linspace(5, 8, desc.size)[::-1])  # each width with its band
        win, wb = read_window(path, 1, 2, 3, 4)
        assert wb.matches(b)
        np.testing.assert_allclose(win, scene(wb.centers_nm)[:, 1:4, 2:6], rtol=1e-6)


@pytest.mark.parametrize("centres, words", [
    ([400.0, 420.0, 410.0, 430.0], ("neither ascending nor descending", "band 3 of 4: 420, 410, … nm")),
    ([400.0, 410.0, 410.0, 430.0], ("names 410 nm twice",)),
])
def test_band_lists_in_no_order_are_refused(tmp_path, centres, words):
    chw = np.ones((4, H, W))
    for path in (write_mat(tmp_path / "s.mat", "5", {"cube": np.transpose(chw, (1, 2, 0)), "bands": centres}),
                 write_hsicam_by_hand(tmp_path / "s.h5", chw, centres, 10.0 * np.ones(4))):
        with pytest.raises(InputError) as exc:
            read_cube(path)
        assert_one_line_error(exc, path, *words)


@pytest.mark.parametrize("variables, words", [
    ({"cube": scene(NM_400_700, 6, 8), "bands": NM_400_700}, ("'cube' is 31×6×8", "31 wavelengths of 'bands'")),
    ({"ref": scene(np.arange(420.0, 721.0, 10.0), 6, 8)}, ("'ref' is 31×6×8", "Harvard's 31 bands")),
], ids=["cube-bands", "ref"])
def test_mat_cube_saved_as_chw_names_the_axis_order(tmp_path, variables, words):
    """scipy.io.savemat of NumPy's (C, H, W): refused (a MAT file is H×W×C by definition, and which
    spatial order such a file holds cannot be checked), with the order and the fix in the message."""
    path = write_mat(tmp_path / "chw.mat", "5", variables)
    with pytest.raises(InputError) as exc:
        read_cube(path)
    assert_one_line_error(exc, path, *words, "look like (C, H, W)", "a MATLAB file holds H×W×C",
                          "np.transpose(cube, (1, 2, 0))")


def test_the_data_package_loads_its_names_on_first_use():
    """`hsicam.data` gives each public name of its modules (PEP 562), imported when first asked for, so a
    light module of the package (`hsicam.data.estimates`, read by the command line's parser) loads without
    torch; every name is its home module's own object, and an unknown name is an AttributeError."""
    import importlib
    import subprocess
    import sys

    import hsicam.data as data

    for name in data.__all__:
        home = importlib.import_module(data._HOME_OF[name])
        assert name in vars(home) and getattr(data, name) is vars(home)[name], name
    assert set(data.__all__) <= set(dir(data)) and "read_cube" in data.__all__ and "PatchDataset" in data.__all__
    with pytest.raises(AttributeError, match="has no attribute 'read_cubes'"):
        data.read_cubes  # noqa: B018
    from hsicam.data import formats, read_cube  # a sub-module and a name, as other modules import them

    assert read_cube is formats.read_cube
    loaded = subprocess.run([sys.executable, "-c", "import sys, hsicam.data.estimates; print('torch' in sys.modules)"],
                            capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "False"
    # a sub-module as an attribute of the package, in a fresh process (nothing imported it before)
    script = "import hsicam.data as d; print(d.formats.__name__, d.datasets.__name__, hasattr(d, 'no_such_module'))"
    names = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout.split()
    assert names == ["hsicam.data.formats", "hsicam.data.datasets", "False"]


def test_envi_writer_keeps_metadata_in_one_header_line_that_envi_readers_take_whole(tmp_path, caplog):
    """write_envi kept no metadata (reconstruct's --out X.hdr lost the capture, run and CFA offset that its .h5
    records; session 54 review). It is one header line now, ``hsicam metadata = {JSON}``, that read_envi returns in
    the cube's meta as read_hsicam_h5 does; braces and commas inside its strings are JSON escapes, so a reader that
    counts braces sees them balanced and one that splits a braced value at its commas (the spectral package)
    joins the pieces back into the same JSON."""
    import json

    from hsicam.data.formats import ENVI_METADATA_KEY

    meta = {"source": 'scan{1}, "a"\\b,\n\u00e9\u2028.npy', "run": "pretrained:standard", "cfa_offset": [1, 2],
            "cfa_offset_estimate": {"residuals": {"0,0": 0.5, "1,2": 0.01}, "ambiguous": False},
            "list": [" a", "b ", {"x": "}{"}], "empty": "", "format": "not the file's"}
    chw = np.random.default_rng(3).random((3, 4, 5)).astype(np.float32)
    hdr, _ = write_envi(tmp_path / "c.hdr", chw, Bands.uniform(450, 550, 50), metadata=meta)
    text = hdr.read_text(encoding="utf-8")
    assert text.isascii()
    line = [x for x in text.splitlines() if x.startswith(ENVI_METADATA_KEY)]
    assert len(line) == 1 and len(text.splitlines()) == len(text.split("\n")) - 1  # one line, whatever splits lines
    value = parse_envi_header(hdr)[ENVI_METADATA_KEY]
    assert value.count("{") == value.count("}") and json.loads(value[1:-1]) == meta
    # the spectral package's split of a braced value: the text between the outer braces, at every comma, stripped
    assert json.loads(",".join(v.strip() for v in value[1:-1].split(","))) == meta
    cube, _, got = read_cube(hdr)
    np.testing.assert_array_equal(cube, chw)
    assert {k: got[k] for k in meta if k != "format"} == {k: v for k, v in meta.items() if k != "format"}
    assert got["format"] == "envi"  # the file's own facts win
    # a value that is not a JSON object: read without it, with a warning
    hdr.write_text(text.replace(line[0], f"{ENVI_METADATA_KEY} = {{not json}}"), encoding="utf-8")
    with caplog.at_level(logging.WARNING):
        _, _, got = read_cube(hdr)
    assert "run" not in got and f"ignoring its unreadable '{ENVI_METADATA_KEY}'" in caplog.text


# ------------------------------------------------------------------------------------------------
# Sensor images (2-D): a 16-bit PNG at its scale; a cube, an unknown suffix, a missing file refused
# (moved from engine/test_inference.py)
# ------------------------------------------------------------------------------------------------
def test_read_sensor_png16_and_scale(tmp_path):
    import imageio.v3 as iio

    data = np.array([[0, 65535], [32768, 1000]], dtype=np.uint16)
    iio.imwrite(tmp_path / "s.png", data)
    img = read_sensor_image(tmp_path / "s.png", scale=2.0)
    np.testing.assert_allclose(img, data / 65535.0 * 2.0, rtol=1e-6)


def test_read_sensor_errors(tmp_path):
    np.save(tmp_path / "s.npy", np.ones((2, 3, 4)))
    with pytest.raises(InputError, match="2-D"):
        read_sensor_image(tmp_path / "s.npy")
    (tmp_path / "x.jpg").write_bytes(b"123")
    with pytest.raises(InputError, match="unsupported"):
        read_sensor_image(tmp_path / "x.jpg")
    with pytest.raises(InputError, match="no such"):
        read_sensor_image(tmp_path / "missing.npy")


def test_a_files_warning_is_logged_once_however_often_it_is_read(tmp_path, caplog):
    """A dataset reads its scenes again and again: a tolerance study logged one ENVI file's "reading them as
    micrometres" warning 38 times (a real-format dataset hunt, session 72). Each text, which names its file, is
    logged once per process; another file's is its own."""
    waves = "wavelength = {0.40, 0.55, 0.70}\n"  # no unit, values below 30: micrometres, with a warning
    for name in ("a", "b"):
        (tmp_path / f"{name}.hdr").write_text(envi_header(W, H, 3, 4, "bsq", 0, 0, waves))
        np.ones((3, H, W), np.float32).tofile(tmp_path / f"{name}.img")
    with caplog.at_level(logging.INFO, logger="hsicam.data.formats"):
        for _ in range(3):
            read_cube(tmp_path / "a.hdr")
        read_cube(tmp_path / "b.hdr")
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "micrometres" in r.getMessage()]
    assert len(said) == 2 and str(tmp_path / "a.hdr") in said[0] and str(tmp_path / "b.hdr") in said[1], said
