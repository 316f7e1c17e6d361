"""Which images ``hsicam simulate``'s scale applies to, how a gain on top of it is checked, and captures whose light is
stored inverted (a reconstruct hunt, session 72). References: the stored values themselves (numpy), the scale
written beside them, and the level check's own messages on the same image as a ``.npy``."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import tifffile
from PIL import Image, PngImagePlugin

from hsicam.data.images import SENSOR_SCALE_KEY, read_capture
from hsicam.data.images import RawCorrection
from hsicam.errors import InputError

SCALE = 1.4527  # a scene brighter than full scale: simulate stored its sensor image divided by its peak


def _level_image() -> np.ndarray:
    """A sensor image at its simulated level, peak SCALE (> 1)."""
    img = np.random.default_rng(0).uniform(0.05, 1.0, (40, 40)).astype(np.float32)
    img[7, 9] = 1.0
    return img * np.float32(SCALE)


def _simulated_folder(tmp_path, chunk: bool = True):
    """A simulate output: sensor.png (16 bit, the image / its peak, the scale in its text chunk when ``chunk``) and
    simulate.json recording the scale."""
    folder = tmp_path / "sim"
    folder.mkdir()
    level = _level_image()
    info = PngImagePlugin.PngInfo()
    if chunk:
        info.add_text(SENSOR_SCALE_KEY, repr(SCALE))
    Image.fromarray(np.round(level / SCALE * 65535).astype(np.uint16)).save(folder / "sensor.png", pnginfo=info)
    (folder / "simulate.json").write_text(json.dumps({"sensor_png_scale": SCALE}))
    return folder, level


@pytest.mark.parametrize("chunk", [True, False], ids=["scale-in-png", "older-simulation"])
def test_only_simulates_own_png_is_brought_back_to_its_level(tmp_path, chunk):
    """A float TIFF copied into a simulate folder holds its level already: it was multiplied by the folder's
    sensor_png_scale again (1.45× too bright, silently)."""
    folder, level = _simulated_folder(tmp_path, chunk)
    png, _ = read_capture(folder / "sensor.png")
    np.testing.assert_allclose(png, level, atol=SCALE / 65535)
    for name in ("capture.tif", "other.png"):
        if name.endswith(".tif"):
            tifffile.imwrite(folder / name, level)
            want = level
        else:  # another 16-bit PNG there, without the chunk: a capture of its own, read at its own full scale
            Image.fromarray(np.round(level / SCALE * 65535).astype(np.uint16)).save(folder / name)
            want = np.round(level / SCALE * 65535) / 65535
        img, report = read_capture(folder / name)
        np.testing.assert_allclose(img, want, rtol=1e-6)
        assert report["gain"] == pytest.approx(1.0 if name.endswith(".tif") else 1 / 65535)
        assert "simulated_scale" not in report


def test_a_gain_on_a_stretched_png_is_checked_as_on_its_npy(tmp_path, caplog):
    """The scale that restores the stretched PNG is no gain, but a --scale on top of it is: --scale 100 was taken
    silently (the same image as a .npy is refused), 1e-6 left it dark without a word."""
    folder, level = _simulated_folder(tmp_path)
    np.save(tmp_path / "level.npy", level)
    for source in (folder / "sensor.png", tmp_path / "level.npy"):
        with pytest.raises(InputError, match=r"--scale 100 puts the image far past the sensor's full scale \(1\): its "
                                             r"99.9th percentile is 14\d and its brightest pixel 145 .*: --scale 0.689 "
                                             r"puts it at 1$"):  # 100 / 145: the --scale to give, not the product
            read_capture(source, RawCorrection(scale=100.0))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
            img, report = read_capture(source, RawCorrection(scale=1e-6))
        assert "--scale 1e-06 leaves the image very dark" in caplog.text
        np.testing.assert_allclose(img, level * 1e-6, rtol=0, atol=1e-6 * SCALE / 65535)  # the PNG: 16 bits
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
            img, report = read_capture(source)  # no gain: the stretched level (peak 1.45) is what was simulated
        assert "full scale" not in caplog.text, caplog.text
    assert report.get("simulated_scale") is None  # (the .npy's report)
    assert read_capture(folder / "sensor.png")[1]["simulated_scale"] == pytest.approx(SCALE)


def test_auto_level_on_a_stretched_png_marks_no_pixel_clipped(tmp_path, caplog):
    """Its peak is full scale by design: with --auto-level it was warned about as saturated and taken as a lower
    bound by the consistency steps."""
    folder, level = _simulated_folder(tmp_path)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        img, report, saturated = read_capture(folder / "sensor.png", RawCorrection(auto_level=0.5),
                                              return_saturated=True)
    assert report["saturated_px"] == 0 and not saturated.any() and "saturated" not in caplog.text
    assert float(np.percentile(img, 99.9)) == pytest.approx(0.5, rel=1e-4)


@pytest.mark.parametrize("compression", [None, "tiff_lzw"])
def test_a_white_is_zero_tiff_is_refused_whatever_its_compression(tmp_path, compression):
    """tifffile returned a MINISWHITE page's stored values (light inverted: a dark scene read as white), Pillow (an
    LZW page) inverted them: the same capture read two ways by its compression. Refused."""
    u8 = np.random.default_rng(1).integers(0, 200, (24, 24), dtype=np.uint8)
    path = tmp_path / "mw.tif"
    if compression is None:
        tifffile.imwrite(path, 255 - u8, photometric="miniswhite")
    else:
        Image.fromarray(255 - u8).save(path, compression=compression)
        with tifffile.TiffFile(path) as tf:
            offset = tf.pages[0].tags[262].valueoffset
        data = bytearray(path.read_bytes())
        data[offset:offset + 2] = (0).to_bytes(2, "little" if data[:2] == b"II" else "big")
        path.write_bytes(bytes(data))
    with tifffile.TiffFile(path) as tf:
        assert tf.pages[0].tags[262].value == 0  # the file is what the test says
    with pytest.raises(InputError) as exc:
        read_capture(path)
    assert str(exc.value) == (f"{path}: a WhiteIsZero (MINISWHITE) TIFF stores light inverted (0 = white), as no "
                              "sensor records it: save the capture as BlackIsZero (MINISBLACK, 0 = black)")
    tifffile.imwrite(tmp_path / "mb.tif", u8, photometric="minisblack")
    np.testing.assert_allclose(read_capture(tmp_path / "mb.tif")[0], u8 / 255.0, rtol=1e-6)
