"""Lines of the data readers (formats, images, preview, estimates) and of export that the default suite never
ran: each user-facing refusal checked against the exact text a user sees, each edge case against a file read
back in its real format or a closed form."""
from __future__ import annotations

import json
import logging
import sys
import types

import h5py
import numpy as np
import pytest
import scipy.io

from hsicam.errors import InputError
from hsicam.spectral.bands import Bands


def _msg(exc) -> str:
    return str(exc.value)


# ---- data/formats.py: band lists -----------------------------------------------------------------------
def test_one_band_npy_is_read_at_550_nm(tmp_path):
    """A (1, H, W) .npy without a band grid: its one band at the middle of 400-700 nm, 10 nm wide (the
    'evenly spaced' grid of one band), the cube as stored."""
    from hsicam.data.formats import read_cube

    arr = np.random.default_rng(0).random((1, 5, 6)).astype(np.float32)
    np.save(tmp_path / "one.npy", arr)
    cube, bands, meta = read_cube(tmp_path / "one.npy")
    np.testing.assert_array_equal(cube, arr)
    assert bands.centers_nm.tolist() == [(400.0 + 700.0) / 2] and bands.fwhm_nm.tolist() == [10.0]
    assert meta["bands_assumed"] is True
    assert meta["assumed_grid"] == "one band at 550 nm"  # not "1 bands evenly spaced over 400-700 nm"


def test_a_mat_file_of_one_band_with_its_band_list_reads_that_band(tmp_path):
    """A single-band MAT cube (H×W×1) with 'bands': no order to check, the listed wavelength kept."""
    from hsicam.data.formats import read_cube

    img = np.random.default_rng(1).random((4, 5, 1))
    scipy.io.savemat(tmp_path / "one.mat", {"cube": img, "bands": np.array([612.5])})
    cube, bands, meta = read_cube(tmp_path / "one.mat")
    np.testing.assert_allclose(cube, img.transpose(2, 0, 1).astype(np.float32))
    assert bands.centers_nm.tolist() == [612.5] and meta["format"] == "arad"


@pytest.mark.parametrize("edit, tail", [
    ({"fwhm_nm": [-1.0, 10.0, 10.0]}, "invalid band list: Bands: FWHM must be finite and positive"),
    ({"fwhm_nm": [10.0, 10.0]}, "invalid band list: Bands: 3 centres but 2 FWHM values"),
    ({"bands_nm": [500.0, np.nan, 520.0]},
     "invalid band list: Bands: band centres must be finite and positive, got 1 that are not (e.g. [nan]) among 3"),
])
def test_our_h5_with_a_bad_band_list_is_refused_naming_the_file(tmp_path, edit, tail):
    from hsicam.data.formats import read_cube, write_cube_h5

    p = write_cube_h5(tmp_path / "c.h5", np.ones((3, 4, 4), np.float32), Bands.from_centers([500.0, 510.0, 520.0]))
    with h5py.File(p, "a") as f:
        for key, values in edit.items():
            if key in f:
                del f[key]
            f[key] = np.array(values)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert _msg(exc) == f"{p}: {tail}"


def test_our_h5_with_a_descending_band_list_flips_its_fwhm_with_it(tmp_path):
    from hsicam.data.formats import read_cube, write_cube_h5

    cube = np.random.default_rng(2).random((3, 4, 4)).astype(np.float32)
    p = write_cube_h5(tmp_path / "c.h5", cube, Bands.from_centers([500.0, 510.0, 520.0]))
    with h5py.File(p, "a") as f:
        del f["bands_nm"], f["cube"]
        if "fwhm_nm" in f:
            del f["fwhm_nm"]
        f["bands_nm"], f["fwhm_nm"], f["cube"] = np.array([520.0, 510.0, 500.0]), np.array([5.0, 10.0, 20.0]), cube
    got, bands, _ = read_cube(p)
    np.testing.assert_array_equal(got, cube[::-1])
    assert bands.centers_nm.tolist() == [500.0, 510.0, 520.0] and bands.fwhm_nm.tolist() == [20.0, 10.0, 5.0]


# ---- data/formats.py: files that are not what the reader was asked for ------------------------------
def test_hdf5_without_any_known_variable_names_what_it_holds(tmp_path):
    from hsicam.data.formats import read_cube

    p = tmp_path / "foo.h5"
    with h5py.File(p, "w") as f:
        f["foo"] = np.ones(3)
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert _msg(exc) == (f"{p}: HDF5/MAT file with no known hyperspectral variable (expected one of cube, rad, img, "
                         "img_expand, HSI, ref; found foo): rename the cube's variable to one of these (with its band "
                         "list as 'bands', in nm), or rewrite it with hsicam.data.formats.write_cube_h5")


def test_explicit_readers_refuse_files_of_another_kind(tmp_path):
    from hsicam.data.formats import read_hsicam_h5, read_icvl

    rad = tmp_path / "rad.h5"
    with h5py.File(rad, "w") as f:
        f["rad"] = np.ones((3, 4, 4), np.float32)
    with pytest.raises(InputError) as exc:
        read_hsicam_h5(rad)
    assert _msg(exc) == f"{rad}: missing key 'cube' (not an hsicam cube file)"

    m5 = tmp_path / "m5.mat"
    scipy.io.savemat(m5, {"foo": np.ones((4, 4, 3))})
    with pytest.raises(InputError) as exc:
        read_icvl(m5)
    assert _msg(exc) == f"{m5}: missing key 'rad' (found: foo)"

    txt = tmp_path / "t.mat"
    txt.write_text("hello")
    with pytest.raises(InputError) as exc:
        read_icvl(txt)
    assert _msg(exc) == f"{txt}: not a MAT file (no MATLAB 5.0 header and not HDF5/MAT v7.3)"

    with pytest.raises(InputError) as exc:
        read_icvl(tmp_path)  # a folder given to a file reader
    assert _msg(exc) == f"{tmp_path}: a folder, not a file"
    from hsicam.data.formats import read_hsicam_h5

    with pytest.raises(InputError) as exc:  # h5py's own words were read as a corrupt file
        read_hsicam_h5(tmp_path)
    assert _msg(exc) == f"{tmp_path}: a folder, not a file (HDF5 expected)"


def test_a_group_where_the_cube_variable_goes_is_refused(tmp_path):
    from hsicam.data.formats import read_cube

    p = tmp_path / "g.h5"
    with h5py.File(p, "w") as f:
        f.create_group("rad")
    with pytest.raises(InputError) as exc:
        read_cube(p)
    assert _msg(exc) == f"{p}: 'rad' is not a numeric array"


def test_read_window_of_an_hdf5_that_is_not_ours_is_none(tmp_path):
    """Not our HDF5 (an ICVL-style file): no window; the caller reads the whole cube through its reader."""
    from hsicam.data.formats import read_window

    p = tmp_path / "rad.h5"
    with h5py.File(p, "w") as f:
        f["rad"] = np.ones((3, 4, 4), np.float32)
    assert read_window(p, 0, 0, 2, 2) is None


# ---- data/formats.py: OpenEXR -------------------------------------------------------------------------
def _exr(path, channels):
    OpenEXR = pytest.importorskip("OpenEXR")
    if not hasattr(OpenEXR, "File"):
        pytest.skip("openexr < 3.3")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {n: OpenEXR.Channel(a) for n, a in channels.items()}) as f:
        f.write(str(path))
    return path


def test_exr_refusals_name_the_file_and_the_channels(tmp_path):
    from hsicam.data.formats import read_kaist_exr

    plane = np.ones((4, 4), np.float32)
    p = _exr(tmp_path / "rgb.exr", {"R": plane, "G": plane})
    with pytest.raises(InputError) as exc:
        read_kaist_exr(p)
    assert _msg(exc) == f"{p}: no EXR channel name carries a wavelength (channels: G, R)"

    p = _exr(tmp_path / "twice.exr", {"w500nm": plane, "w500.0nm": plane, "w510nm": plane})
    with pytest.raises(InputError) as exc:
        read_kaist_exr(p)
    assert _msg(exc) == f"{p}: two EXR channels name the same wavelength"


def test_exr_reader_without_openexr_or_with_an_old_one_says_what_to_install(tmp_path, monkeypatch):
    from hsicam.data.formats import read_kaist_exr

    p = tmp_path / "s.exr"
    p.write_bytes(b"\x76\x2f\x31\x01")
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # import OpenEXR: ImportError
    with pytest.raises(InputError) as exc:
        read_kaist_exr(p)
    assert _msg(exc) == f"{p}: reading OpenEXR needs the 'openexr' package (pip install 'hsicam[exr]')"
    monkeypatch.setitem(sys.modules, "OpenEXR", types.ModuleType("OpenEXR"))  # openexr < 3.3: no OpenEXR.File
    with pytest.raises(InputError) as exc:
        read_kaist_exr(p)
    assert _msg(exc) == f"{p}: reading OpenEXR needs openexr >= 3.3 (the OpenEXR.File API)"


# ---- data/formats.py: ENVI ----------------------------------------------------------------------------
def test_envi_wrong_byte_order_is_named_with_a_data_ignore_value_too(tmp_path):
    """A float32 file whose header says byte order 0 but whose bytes are big-endian: a value that reads NaN
    little-endian and finite big-endian is blamed on the header's byte order, also when the header gives a
    data ignore value (the no-data values are left out of the other order's check)."""
    from envi_files import write_envi_pair

    from hsicam.data.formats import read_cube

    le = np.full((2, 3, 3), 1.0, "<f4")
    le[0, 0, 0] = np.frombuffer(bytes([0, 0, 0xC0, 0x7F]), "<f4")[0]  # NaN read little-endian
    le[1, 2, 2] = -1.0  # the ignore value as read little-endian
    assert np.isnan(le[0, 0, 0]) and np.isfinite(le.view(">f4")).all()  # big-endian: all finite
    hdr = write_envi_pair(tmp_path, le, "data ignore value = -1\n", [500, 600], dtype="<f4", code=4, interleave="bsq")
    with pytest.raises(InputError) as exc:
        read_cube(hdr)
    assert _msg(exc) == (f"{tmp_path / 'scene.img'}: 1 NaN/Inf value(s) with byte order 0, none with byte order 1: "
                         "fix 'byte order' in scene.hdr")


def test_envi_hsicam_metadata_not_in_braces_is_ignored_with_a_warning(tmp_path, caplog):
    from envi_files import write_envi_pair

    from hsicam.data.formats import read_cube

    chw = np.random.default_rng(3).random((2, 3, 3)).astype(np.float32)
    hdr = write_envi_pair(tmp_path, chw, 'hsicam metadata = "{}"\n', [500, 600], dtype="<f4", code=4)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"):
        cube, _, meta = read_cube(hdr)
    np.testing.assert_array_equal(cube, chw)
    assert f"{hdr}: ignoring its unreadable 'hsicam metadata' (not a JSON object in braces)" in caplog.messages
    assert "command" not in meta


# ---- data/images.py -----------------------------------------------------------------------------------
def test_an_older_simulations_png_beside_an_unreadable_simulate_json_names_that_file(tmp_path):
    """(Only simulate's own sensor.png reads simulate.json: a TIFF beside it is a capture of its own, session 72.)"""
    import tifffile
    from PIL import Image

    from hsicam.data.images import read_capture

    Image.fromarray(np.full((8, 8), 30000, np.uint16)).save(tmp_path / "sensor.png")
    tifffile.imwrite(tmp_path / "sensor.tif", np.full((8, 8), 30000, np.uint16))
    (tmp_path / "simulate.json").write_text("{not json")
    with pytest.raises(InputError) as exc:
        read_capture(tmp_path / "sensor.png")
    assert _msg(exc) == f"{tmp_path / 'simulate.json'}: unreadable simulate.json"
    assert read_capture(tmp_path / "sensor.tif")[0] == pytest.approx(np.full((8, 8), 30000 / 65535))


def test_raw_correction_flat_period_below_one_is_refused():
    from hsicam.data.images import RawCorrection

    with pytest.raises(InputError) as exc:
        RawCorrection(flat_period=0)
    assert _msg(exc) == "flat period must be >= 1, got 0"


def test_dark_frame_brighter_than_most_pixels_warns_naming_the_dark_frame(caplog):
    """60 % of the pixels below a dark frame of 800 DN: a warning naming the dark frame (its median), not a black
    level; the image is (raw - dark) / (white - black) with black = the dark frame's median."""
    from hsicam.data.images import RawCorrection, preprocess_raw

    raw = np.full((10, 10), 1000.0, np.float32)
    raw[:6] = 700.0
    dark = np.full((10, 10), 800.0, np.float32)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        img, report = preprocess_raw(raw, 4095.0, RawCorrection(dark=dark), "cap.npy", check_bit_depth=False)
    np.testing.assert_allclose(img, (raw - 800.0) / (4095.0 - 800.0), rtol=1e-6)
    assert report["black_level_dn"] == 800.0
    assert any(m.startswith("cap.npy: 60 % of the pixels are below 0 after subtracting the dark frame (median 800 DN); ")
               for m in caplog.messages), caplog.messages


@pytest.mark.parametrize("top, at_top, warned", [(1.0, 30, True), (1.0, 1, False), (0.9, 30, False)])
def test_a_float_capture_clipped_at_one_is_said(caplog, top, at_top, warned):
    """A float .npy capture with 28 % of its pixels at exactly 1.0 (clipped at full scale) was reconstructed without a
    word, those pixels read as measured light (session 74's hunt); the same at 63 % was refused as over-exposed given
    --white-level 1. Three or more pixels at exactly 1.0, the brightest value, are now said, naming the option; a
    single brightest pixel or a plateau below 1.0 (a simulated flat field) is not."""
    from hsicam.data.images import RawCorrection, preprocess_raw

    raw = np.linspace(0.1, 0.5, 100, dtype=np.float32).reshape(10, 10)
    raw.flat[:at_top] = top
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        preprocess_raw(raw, 1.0, RawCorrection(), "cap.npy", check_bit_depth=False)
    said = [m for m in caplog.messages if "sit at exactly 1.0" in m]
    assert bool(said) is warned, caplog.messages
    if warned:
        assert said[0].startswith(f"cap.npy: {at_top} pixel(s) ({at_top:.2g} %) sit at exactly 1.0, the capture's")
        assert "give --white-level 1 to read them as clipped" in said[0]


@pytest.mark.parametrize("low, warned", [(-1e-8, False), (-1e-3, True)])
def test_round_off_below_zero_is_no_offset(caplog, low, warned):
    """A float capture from `hsicam simulate` (FFT convolutions) holds round-off negatives of ~1e-7 of its peak on dark
    pixels: 35 % of a point's capture "below 0 ... a signed or mean-subtracted image?" (session 74's hunt). Values
    within 1e-6 of the peak below 0 are round-off, not counted; -1e-3 of it still is an offset."""
    from hsicam.data.images import RawCorrection, preprocess_raw

    raw = np.full((10, 10), low, np.float32)
    raw[:4] = 1.0
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        preprocess_raw(raw, 1.0, RawCorrection(), "cap.npy", check_bit_depth=False)
    assert any("60 % of the pixels are below 0" in m for m in caplog.messages) is warned, caplog.messages


@pytest.mark.parametrize("raw", [np.zeros((0, 0), np.uint16), np.zeros((4, 0), np.uint16), np.arange(5.0),
                                 np.zeros((2, 3, 3), np.float32), np.array([["a", "b"]])],
                         ids=["0x0", "4x0", "1-D", "3-D", "strings"])
def test_preprocess_raw_refuses_what_is_no_capture_in_one_line(raw):
    """From Python (the readers refuse these first): an empty image reached numpy's "zero-size array to reduction
    operation maximum", a 1-D one an unpacking error."""
    from hsicam.data.images import RawCorrection, preprocess_raw

    with pytest.raises(InputError) as exc:
        preprocess_raw(raw, 4095.0, RawCorrection(), "cap.npy")
    assert _msg(exc) == (f"cap.npy: a capture is a non-empty (H, W) array of numbers, got shape {raw.shape} of "
                         f"{raw.dtype}")


# ---- data/estimates.py: files that are not reconstruct's ----------------------------------------------
def test_is_reconstruct_h5_is_false_for_hdf5_that_reconstruct_did_not_write(tmp_path):
    from hsicam.data.estimates import is_reconstruct_h5
    from hsicam.data.formats import write_cube_h5

    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:  # another tool's HDF5
        f["cube"] = np.ones((2, 3, 3), np.float32)
    assert not is_reconstruct_h5(plain)
    listed = write_cube_h5(tmp_path / "list.h5", np.ones((2, 3, 3), np.float32), Bands.from_centers([500.0, 600.0]))
    with h5py.File(listed, "a") as f:
        f.attrs["metadata_json"] = json.dumps(["command", "reconstruct"])  # JSON, but not an object
    assert not is_reconstruct_h5(listed)
    mine = write_cube_h5(tmp_path / "mine.h5", np.ones((2, 3, 3), np.float32), Bands.from_centers([500.0, 600.0]),
                         {"command": "reconstruct"})
    assert is_reconstruct_h5(mine)  # the same file with reconstruct's metadata: True


def test_reconstruct_envi_header_is_none_for_a_large_or_unparseable_envi_file(tmp_path):
    from hsicam.data.estimates import reconstruct_envi_header

    big = tmp_path / "big.hdr"
    big.write_bytes(b"ENVI\ndescription = {hsicam reconstruct}\n" + b" " * (1 << 20))
    assert reconstruct_envi_header(big) is None  # over 1 MiB: not a header reconstruct wrote
    bad = tmp_path / "bad.hdr"
    bad.write_text("ENVI\ndescription = {hsicam reconstruct\n")  # an unclosed brace
    assert reconstruct_envi_header(bad) is None


# ---- export: the default number of DOE levels ----------------------------------------------------------
def test_export_default_levels_are_the_runs_own_whatever_their_count():
    """A run trained with 6 levels was refused ("pass --levels explicitly", an option that takes powers of 2 only):
    the default is the run's own count (exported without GDS masks when not a power of 2), 8 without one."""
    from hsicam.export import default_levels

    def cfg(levels):
        return types.SimpleNamespace(camera=types.SimpleNamespace(doe=types.SimpleNamespace(quantization_levels=levels)))

    assert default_levels(cfg(None)) == 8 and default_levels(cfg(16)) == 16 and default_levels(cfg(6)) == 6
