"""Lines of the data readers and previews that the default suite never ran (coverage round 10, cov10a)."""

from __future__ import annotations

import json
import logging
import struct

import numpy as np
import pytest
import tifffile

from hsicam.data.images import read_image_2d
from hsicam.errors import InputError
from hsicam.spectral import Bands


# ------------------------------------------------------------------------------------------------
# TIFF pages that tifffile decodes only with imagecodecs (LZW) or not at all (JPEG): Pillow's path
# ------------------------------------------------------------------------------------------------
def _lzw_literal(data: bytes) -> bytes:
    """TIFF LZW of ``data`` with literal codes only (a Clear code every 250 bytes keeps them 9 bits wide)."""
    codes = []
    for i in range(0, len(data), 250):
        codes += [256] + list(data[i:i + 250])
    codes.append(257)  # end of information
    bits = "".join(format(c, "09b") for c in codes)
    bits += "0" * (-len(bits) % 8)
    return int(bits, 2).to_bytes(len(bits) // 8, "big")


def _lzw_tiff(path, image: np.ndarray, order: str) -> None:
    """A single-strip grey TIFF of ``image``, LZW-compressed, in byte order ``order`` ("<" II, ">" MM), written
    field by field after the TIFF 6.0 specification (tifffile writes LZW only with imagecodecs)."""
    h, w = image.shape
    dt = image.dtype
    strip = _lzw_literal(image.astype(dt.newbyteorder(order)).tobytes())
    fmt = {"u": 1, "i": 2, "f": 3}[dt.kind]
    tags = [(256, 3, w), (257, 3, h), (258, 3, 8 * dt.itemsize), (259, 3, 5), (262, 3, 1), (273, 4, 0),
            (277, 3, 1), (278, 3, h), (279, 4, len(strip)), (339, 3, fmt)]
    offset = 8 + 2 + 12 * len(tags) + 4
    out = (b"MM\x00*" if order == ">" else b"II*\x00") + struct.pack(order + "IH", 8, len(tags))
    for tag, typ, value in tags:
        value = offset if tag == 273 else value
        field = struct.pack(order + "H", value) + b"\0\0" if typ == 3 else struct.pack(order + "I", value)
        out += struct.pack(order + "HHI", tag, typ, 1) + field
    path.write_bytes(out + struct.pack(order + "I", 0) + strip)


@pytest.mark.parametrize("order", ["<", ">"])
def test_a_big_endian_lzw_tiff_reads_as_the_little_endian_one(tmp_path, order):
    """A 16-bit LZW TIFF in Motorola byte order ("MM", big-endian) was refused: "TIFF compressed with LZW, which
    neither tifffile without the imagecodecs package nor Pillow decodes here ... (Pillow decodes it as >u2 (20, 30),
    not uint16 (20, 30))" although Pillow had decoded it right; only its byte order differed from tifffile's."""
    image = (np.random.default_rng(5).random((20, 30)) * 4000).astype(np.uint16)
    _lzw_tiff(tmp_path / "lzw.tif", image, order)
    with tifffile.TiffFile(tmp_path / "lzw.tif") as tf:
        assert tf.byteorder == order and tf.pages[0].compression == 5
    got = read_image_2d(tmp_path / "lzw.tif", "sensor image")
    np.testing.assert_array_equal(got.data, image.astype(np.float32))
    assert got.full_scale == 65535.0 and got.dtype == "uint16" and got.format == "tiff"


def test_an_lzw_tiff_that_pillow_decodes_as_another_type_is_refused_naming_both(tmp_path):
    """A uint32 LZW page comes back from Pillow as int32 (its mode "I"): refused, not read with int32's scale."""
    image = (np.random.default_rng(6).random((8, 9)) * 4000).astype(np.uint32)
    _lzw_tiff(tmp_path / "u32.tif", image, "<")
    with pytest.raises(InputError) as err:
        read_image_2d(tmp_path / "u32.tif", "sensor image")
    assert str(err.value) == (
        f"{tmp_path / 'u32.tif'}: TIFF compressed with LZW, which neither tifffile without the imagecodecs package nor "
        "Pillow decodes here: `pip install imagecodecs`, or save the capture uncompressed (Pillow decodes it as int32 "
        "(8, 9), not uint32 (8, 9))")


def test_a_jpeg_compressed_tiff_is_read_by_pillow_with_a_lossy_warning(tmp_path, caplog):
    from PIL import Image

    image = (np.random.default_rng(7).random((24, 32)) * 200 + 20).astype(np.uint8)
    Image.fromarray(image).save(tmp_path / "jpeg.tif", compression="jpeg")
    with tifffile.TiffFile(tmp_path / "jpeg.tif") as tf:
        assert tf.pages[0].compression == 7  # JPEG
    with Image.open(tmp_path / "jpeg.tif") as im:
        decoded = np.array(im)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        got = read_image_2d(tmp_path / "jpeg.tif", "sensor image")
    np.testing.assert_array_equal(got.data, decoded.astype(np.float32))
    assert got.full_scale == 255.0 and np.abs(got.data - image).mean() < 20  # lossy, but the same picture
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'jpeg.tif'}: JPEG-compressed TIFF: lossy, its values are not the sensor's as captured"]


def test_a_tiff_whose_header_points_to_no_image_is_refused(tmp_path):
    (tmp_path / "empty.tif").write_bytes(b"II*\x00" + struct.pack("<I", 0))  # first IFD offset 0: no page
    with pytest.raises(InputError) as err:
        read_image_2d(tmp_path / "empty.tif", "dark frame")
    assert str(err.value) == f"{tmp_path / 'empty.tif'}: TIFF without images"


# ------------------------------------------------------------------------------------------------
# data show: a cube without visible bands, no scenes, the held-out companion of a cached set
# ------------------------------------------------------------------------------------------------
def test_contact_sheet_shows_a_near_infrared_cube_in_grey(tmp_path):
    from hsicam.data.formats import write_cube_h5
    from hsicam.data.preview import _scene_figures

    nir = Bands.uniform(750.0, 950.0, 50.0)  # 5 bands, one of them (750 nm) in the colour-matching table (380-780 nm)
    rows = np.linspace(0.1, 1.0, 12)[:, None] * np.ones((12, 16))  # a vertical ramp, the same in every band
    cube = np.repeat(rows[None], len(nir), axis=0).astype(np.float32)
    write_cube_h5(tmp_path / "nir.h5", cube, nir)
    sheet, _ = _scene_figures(tmp_path, [tmp_path / "nir.h5"])
    [ax] = sheet.axes
    assert ax.get_title() == "nir.h5 (grey)"
    shown = np.asarray(ax.images[0].get_array())
    assert shown.shape == (12, 16, 3) and np.ptp(shown, axis=-1).max() == 0  # grey: R = G = B
    expect = rows * 0.8 / np.percentile(rows, 99)  # the band mean, exposed with its 99th percentile at 0.8
    np.testing.assert_allclose(shown[..., 0], np.clip(expect, 0, 1), rtol=1e-5)
    assert " ".join(sheet.get_suptitle().split()).endswith("; (grey): mean over bands, fewer than 2 bands in 380-780 nm")


def test_pixel_spectra_of_no_scenes_is_refused_naming_the_folder(tmp_path):
    from hsicam.data.preview import pixel_spectra

    with pytest.raises(InputError) as err:
        pixel_spectra([], source=tmp_path)
    assert str(err.value) == f"{tmp_path}: no scenes to sample spectra from"


def test_a_cached_training_set_finds_the_held_out_set_drawn_with_its_parameters(tmp_path):
    """Its companion: the held-out folder of the same parameters (seed and size too); a held-out set has none."""
    from hsicam.data.preview import _find_heldout

    params = {"generator_version": 3, "size": 24, "seed": 1, "bands": {"centers_nm": [400, 500]},
              "holdout_sources": ["cie-tcs"], "split": "train"}

    def folder(name, **change):
        d = tmp_path / name
        d.mkdir()
        (d / "manifest.json").write_text(json.dumps({"parameters": {**params, **change}}), encoding="utf-8")
        return d

    train = folder("train-n2")
    assert _find_heldout(train) is None  # no companion yet
    folder("heldout-a-other-seed", seed=2, split="heldout")
    folder("heldout-a-other-size", size=48, split="heldout")
    (tmp_path / "heldout-b-no-manifest").mkdir()
    assert _find_heldout(train) is None
    mine = folder("heldout-c", split="heldout")
    assert _find_heldout(train) == mine
    assert _find_heldout(folder("train-no-holdout", holdout_sources=[])) is None
    assert _find_heldout(folder("held-as-input", split="heldout")) is None  # a held-out set has no companion


def test_a_gain_that_fits_float32_but_not_times_the_image_names_both():
    """A float capture of 1e30 DN at --scale 1e10: the factor fits float32, its product with the pixels does not. The
    refusal names the factor and the brightest pixel and says to lower --scale (it said only 'the corrections
    produced NaN or Inf values'); NaN already in the capture is still that line."""
    from hsicam.data.images import RawCorrection, preprocess_raw

    raw = np.full((8, 8), 1e30, np.float32)
    raw[0, 0] = 0.0
    with pytest.raises(InputError) as exc:
        preprocess_raw(raw, 1.0, RawCorrection(scale=1e10), "cap.npy", check_saturation=False)
    assert str(exc.value) == ("cap.npy: the exposure × auto-level × --scale factor 1e+10 times the brightest corrected "
                              f"pixel {float(np.float32(1e30)):g} exceeds float32; lower --scale")
    img, _ = preprocess_raw(raw, 1.0, RawCorrection(scale=1e8), "cap.npy", check_saturation=False, check_level=False)
    assert np.isfinite(img).all() and img.max() == np.float32(1e30) * np.float32(1e8)  # 1e38 fits: no refusal
