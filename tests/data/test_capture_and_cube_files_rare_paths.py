"""Lines of io / data formats / images / colour that the default suite never ran: user-facing errors and
edge cases, each checked against the text a user sees or an independent reference."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from hsicam.errors import InputError


def _sensor_png(folder, value):
    folder.mkdir()
    img = (np.random.default_rng(0).random((16, 16)) * 60000).astype(np.uint16)
    Image.fromarray(img).save(folder / "sensor.png")
    (folder / "simulate.json").write_text(json.dumps({"sensor_png_scale": value}))
    return folder / "sensor.png"


@pytest.mark.parametrize("value", [0, -1, "nan", "inf"])
def test_simulate_json_with_a_non_positive_scale_is_named_not_blamed_on_scale(tmp_path, value):
    """A simulate.json whose sensor_png_scale is 0, negative, NaN or Inf: the error names that file, not
    `--scale`, which the user never passed (it read "scale (--scale) must be positive, got 0.0")."""
    from hsicam.data.images import read_capture

    png = _sensor_png(tmp_path / "sim", value)
    with pytest.raises(InputError) as exc:
        read_capture(png)
    msg = str(exc.value)
    assert msg.startswith(f"{tmp_path / 'sim' / 'simulate.json'}: its sensor_png_scale is ")
    assert msg.endswith("not a positive scale") and "--scale" not in msg


# ---- data/images.py: the refusals a user sees for captures of the wrong kind --------------------------
def _read2d(path):
    from hsicam.data.images import read_image_2d

    return read_image_2d(path, "sensor image")


@pytest.mark.parametrize("mode", ["RGB", "P", "LA"])
def test_png_with_colour_channels_is_refused_with_its_mode(tmp_path, mode):
    arr = np.zeros((8, 8, {"RGB": 3, "P": 1, "LA": 2}[mode]), np.uint8)
    im = Image.fromarray(arr[..., 0]).convert("P") if mode == "P" else Image.fromarray(arr, mode)
    im.save(tmp_path / "c.png")
    with Image.open(tmp_path / "c.png") as back:
        assert back.mode == mode  # the file really holds that mode
    with pytest.raises(InputError, match=rf"^{tmp_path / 'c.png'}: expected a single-channel \(monochrome\) "
                                         rf"sensor image, got PNG mode {mode}$"):
        _read2d(tmp_path / "c.png")


def test_animated_png_is_refused(tmp_path):
    frames = [Image.fromarray(np.full((8, 8), v, np.uint8)) for v in (10, 200)]
    frames[0].save(tmp_path / "a.png", save_all=True, append_images=frames[1:])
    with Image.open(tmp_path / "a.png") as back:
        assert back.n_frames == 2
    with pytest.raises(InputError, match=rf"^{tmp_path / 'a.png'}: animated PNG; expected one sensor image$"):
        _read2d(tmp_path / "a.png")


def test_a_folder_named_like_an_image_is_not_a_file(tmp_path):
    (tmp_path / "x.npy").mkdir()
    with pytest.raises(InputError, match=rf"^{tmp_path / 'x.npy'}: not a file$"):
        _read2d(tmp_path / "x.npy")


@pytest.mark.parametrize("arr, kind", [(np.array([["a", "b"], ["c", "d"]]), "<U1"),
                                       (np.zeros((4, 4), complex), "complex128")])
def test_npy_of_strings_or_complex_is_refused_naming_its_type(tmp_path, arr, kind):
    np.save(tmp_path / "s.npy", arr)
    assert np.load(tmp_path / "s.npy").dtype == np.dtype(kind)
    with pytest.raises(InputError, match=rf"^{tmp_path / 's.npy'}: unsupported data type {kind} "
                                         r"\(expected integers or floats\)$"):
        _read2d(tmp_path / "s.npy")


def test_complex_tiff_is_refused_naming_its_type(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "c.tif", np.zeros((4, 4), np.complex64))
    with pytest.raises(InputError, match=rf"^{tmp_path / 'c.tif'}: unsupported TIFF data type complex64$"):
        _read2d(tmp_path / "c.tif")


@pytest.mark.parametrize("text", ["abc", "-2", "0", "inf"])
def test_png_sensor_scale_chunk_that_is_not_a_positive_number_is_refused(tmp_path, text):
    from PIL import PngImagePlugin

    from hsicam.data.images import SENSOR_SCALE_KEY, read_capture

    info = PngImagePlugin.PngInfo()
    info.add_text(SENSOR_SCALE_KEY, text)
    Image.fromarray(np.full((16, 16), 30000, np.uint16)).save(tmp_path / "s.png", pnginfo=info)
    with pytest.raises(InputError) as exc:
        read_capture(tmp_path / "s.png")
    assert str(exc.value) == f"{tmp_path / 's.png'}: its {SENSOR_SCALE_KEY} text chunk is {text!r}, not a positive scale"


# ---- data/formats.py ------------------------------------------------------------------------------------
def _cave(folder, names, shape=(8, 8)):
    folder.mkdir()
    for n in names:
        Image.fromarray(np.full(shape if not callable(shape) else shape(n), 100, np.uint16)).save(folder / n)
    return folder


def test_a_single_cave_band_png_asks_for_its_folder(tmp_path):
    from hsicam.data.formats import read_cube

    Image.fromarray(np.zeros((8, 8), np.uint16)).save(tmp_path / "x_ms_01.png")
    with pytest.raises(InputError, match=rf"^{tmp_path / 'x_ms_01.png'}: a single CAVE band image; pass the scene "
                                         "folder that holds all 31 PNGs$"):
        read_cube(tmp_path / "x_ms_01.png")


def test_cave_folder_errors(tmp_path):
    from hsicam.data.formats import read_cave, read_cube

    two = _cave(tmp_path / "two", [f"{p}_ms_{i:02d}.png" for p in "ab" for i in range(1, 32)])
    with pytest.raises(InputError, match=rf"^{two}: holds several CAVE scenes \(two/a, two/b\); pass one scene folder$"):
        read_cube(two)
    extra = _cave(tmp_path / "extra", [f"a_ms_{i:02d}.png" for i in range(1, 33)])
    with pytest.raises(InputError, match=rf"^{extra}: CAVE scene has unexpected band index\(es\) \[32\] \(expected 01..31\)$"):
        read_cube(extra)
    sizes = _cave(tmp_path / "sizes", [f"a_ms_{i:02d}.png" for i in range(1, 32)],
                  shape=lambda n: (8, 9) if n == "a_ms_03.png" else (8, 8))
    with pytest.raises(InputError, match=rf"^{sizes}: CAVE band images have different sizes$"):
        read_cube(sizes)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"no CAVE band images '\*_ms_01.png' … '\*_ms_31.png' found$"):
        read_cave(tmp_path / "empty")
    with pytest.raises(InputError, match=r": a CAVE scene is a folder of 31 PNGs$"):
        read_cave(tmp_path / "two" / "a_ms_01.png")


_ENVI = ("ENVI\nsamples = 4\nlines = 3\nbands = 2\nheader offset = 0\nfile type = ENVI Standard\ndata type = 4\n"
         "interleave = bsq\nbyte order = 0\n")


@pytest.mark.parametrize("edit, extra, message", [
    (("data type = 4", "data type = 7"), "wavelength = {500, 600}\n",
     r"unsupported ENVI data type 7 \(supported: \[1, 2, 3, 4, 5, 12, 13, 14, 15\]\)"),
    (("byte order = 0", "byte order = 2"), "wavelength = {500, 600}\n", "ENVI byte order must be 0 or 1, got 2"),
    (("bands = 2", "bands = 0"), "wavelength = {500, 600}\n",
     r"ENVI dimensions must be positive \(samples=4, lines=3, bands=0\)"),
    (None, "wavelength units = furlongs\nwavelength = {500, 600}\n",
     r"unsupported wavelength units 'furlongs' \(nm or µm\)"),
    (None, "wavelength = {500, 600}\nfwhm = {10}\n", "1 FWHM values listed for 2 bands"),
    (None, "", "ENVI header has no 'wavelength' list; cannot tell the bands"),
    (None, "wavelength = {500,\n 600\n", "ENVI header value of 'wavelength' has no closing brace"),
])
def test_envi_header_refusals(tmp_path, edit, extra, message):
    from hsicam.data.formats import read_cube

    text = _ENVI.replace(*edit) if edit else _ENVI
    (tmp_path / "c.hdr").write_text(text + extra)
    (tmp_path / "c.img").write_bytes(np.zeros((2, 3, 4), np.float32).tobytes())
    with pytest.raises(InputError, match=rf"^{tmp_path / 'c.hdr'}: {message}$"):
        read_cube(tmp_path / "c.hdr")


def test_envi_comments_blank_lines_and_an_all_good_bbl_read_the_cube_as_written(tmp_path):
    from hsicam.data.formats import read_cube

    cube = np.arange(24, dtype=np.float32).reshape(2, 3, 4) / 24
    (tmp_path / "c.hdr").write_text(_ENVI + "; a comment\n\nwavelength = {500, 600}\nbbl = {1, 1}\n")
    (tmp_path / "c.img").write_bytes(cube.astype("<f4").tobytes())
    got, bands, _ = read_cube(tmp_path / "c.hdr")
    np.testing.assert_array_equal(got, cube)
    np.testing.assert_array_equal(bands.centers_nm, [500.0, 600.0])


def test_envi_missing_partner_files(tmp_path):
    from hsicam.data.formats import read_cube, read_envi, parse_envi_header

    (tmp_path / "h.hdr").write_text(_ENVI + "wavelength = {500, 600}\n")
    with pytest.raises(InputError, match=rf"^{tmp_path / 'h.hdr'}: ENVI data file not found next to the header "
                                         r"\(tried h\{\.img,"):
        read_cube(tmp_path / "h.hdr")
    (tmp_path / "lone.img").write_bytes(b"\0" * 96)
    with pytest.raises(InputError, match=rf"^{tmp_path / 'lone.img'}: no ENVI header \(.hdr\) next to this file$"):
        read_envi(tmp_path / "lone.img")
    (tmp_path / "x.hdr").write_text("hello\n")
    with pytest.raises(InputError, match=r": not an ENVI header \(first line must be 'ENVI'\)$"):
        parse_envi_header(tmp_path / "x.hdr")


def test_write_envi_and_h5_refuse_bad_arguments(tmp_path):
    from hsicam.data.formats import write_cube_h5, write_envi
    from hsicam.spectral.bands import Bands

    two, cube = Bands.from_centers([500.0, 600.0]), np.ones((2, 4, 4), np.float32)
    for kw, msg in [({"dtype": np.complex64}, "write_envi: unsupported data type complex64"),
                    ({"interleave": "xx"}, "write_envi: interleave must be bsq, bil or bip, got 'xx'"),
                    ({"byte_order": "middle"}, "write_envi: byte_order must be 'little' or 'big', got 'middle'")]:
        with pytest.raises(InputError) as exc:
            write_envi(tmp_path / "w.hdr", cube, two, **kw)
        assert str(exc.value) == msg
    for write, name in [(write_envi, "w.hdr"), (write_cube_h5, "w.h5")]:
        with pytest.raises(InputError) as exc:
            write(tmp_path / name, np.ones((3, 4, 4), np.float32), two)
        assert str(exc.value) == f"{tmp_path / name}: the cube has 3 bands but 2 band centres were given"
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing left behind


def test_h5_with_unreadable_metadata_json_reads_its_cube(tmp_path, caplog):
    import h5py

    from hsicam.data.formats import HSICAM_FORMAT, read_cube

    cube = np.random.default_rng(1).random((2, 4, 4)).astype(np.float32)
    with h5py.File(tmp_path / "c.h5", "w") as f:
        f["cube"], f["bands_nm"] = cube, np.array([500.0, 600.0])
        f.attrs["format"], f.attrs["metadata_json"] = HSICAM_FORMAT, "{not json"
    got, _, _ = read_cube(tmp_path / "c.h5")
    np.testing.assert_array_equal(got, cube)
    assert "ignoring unreadable metadata_json attribute" in caplog.text


def test_npy_header_reads_a_version_2_file(tmp_path):
    from hsicam.data.formats import npy_header

    with open(tmp_path / "v2.npy", "wb") as fh:
        np.lib.format.write_array(fh, np.ones((2, 3, 4), np.float32), version=(2, 0))
    assert (tmp_path / "v2.npy").read_bytes()[6:8] == b"\x02\x00"  # the file's own version bytes
    assert npy_header(tmp_path / "v2.npy") == ((2, 3, 4), np.dtype(np.float32))


def test_read_window_outside_the_cube_is_refused(tmp_path):
    from hsicam.data.formats import read_window, write_cube_h5
    from hsicam.spectral.bands import Bands

    write_cube_h5(tmp_path / "c.h5", np.ones((2, 4, 4), np.float32), Bands.from_centers([500.0, 600.0]))
    with pytest.raises(InputError, match=r": window 10x10 at \(0, 0\) is outside the cube 4x4$"):
        read_window(tmp_path / "c.h5", 0, 0, 10, 10)
    (tmp_path / "n.npy").write_bytes(b"x")
    assert read_window(tmp_path / "n.npy", 0, 0, 1, 1) is None  # not our HDF5: the caller loads the whole cube


# ---- color.py: one band, and a grid touching the table at one end ----------------------------------------
def _cmf_at(nm):
    from hsicam.color import cmf_d65_table

    t = cmf_d65_table()
    return np.array([np.interp(nm, t[:, 0], t[:, k]) for k in (1, 2, 3)])


def test_xyz_weights_of_one_band_are_the_cmf_at_that_wavelength_with_y_one():
    from hsicam.color import xyz_weights
    from hsicam.spectral.bands import Bands

    w = xyz_weights(Bands.from_centers([550.0]))
    ref = _cmf_at(550.0)
    np.testing.assert_allclose(w[:, 0], ref / ref[1], rtol=1e-12)  # D65 cancels in the normalisation to Y = 1


def test_xyz_weights_of_a_grid_ending_at_380_nm_see_only_that_wavelength():
    from hsicam.color import xyz_weights
    from hsicam.spectral.bands import Bands

    w = xyz_weights(Bands.from_centers([370.0, 380.0]))
    ref = _cmf_at(380.0)
    np.testing.assert_array_equal(w[:, 0], 0.0)
    np.testing.assert_allclose(w[:, 1], ref / ref[1], rtol=1e-12)


# ---- io.py / data/preview.py -------------------------------------------------------------------------------
def test_a_file_where_a_folder_output_goes_is_refused(tmp_path):
    from hsicam.io import check_replaceable

    (tmp_path / "f").write_text("mine")
    with pytest.raises(InputError, match=rf"^{tmp_path / 'f'}: is an existing file; a folder is needed here$"):
        check_replaceable(tmp_path / "f", True, None)
    assert (tmp_path / "f").read_text() == "mine"


def test_json_default_writes_numpy_and_paths_as_plain_json(tmp_path):
    from pathlib import Path

    from hsicam.io import json_default

    text = json.dumps({"a": np.float32(1.5), "b": np.arange(3), "c": Path("/x/y")}, default=json_default)
    assert json.loads(text) == {"a": 1.5, "b": [0, 1, 2], "c": "/x/y"}
    with pytest.raises(TypeError, match="^not JSON serializable: object$"):
        json.dumps(object(), default=json_default)


def test_preview_of_bands_outside_the_visible_is_refused_and_a_large_cube_is_block_averaged():
    from hsicam.data.preview import _downsample, preview_rgb
    from hsicam.spectral.bands import Bands

    with pytest.raises(InputError, match=r"^cannot render bands 800-1000 nm: fewer than 2 bands in 380-780 nm$"):
        preview_rgb(np.ones((3, 4, 4), np.float32), Bands.from_centers([800.0, 900.0, 1000.0]))
    c = np.arange(2 * 9 * 7, dtype=np.float64).reshape(2, 9, 7)
    got = _downsample(c, 4)  # step ceil(9/4) = 3: 3×2 blocks of 3×3 (the last row/column of 7 dropped)
    ref = np.array([[[c[k, 3 * i:3 * i + 3, 3 * j:3 * j + 3].mean() for j in range(2)] for i in range(3)] for k in range(2)])
    np.testing.assert_allclose(got, ref)
