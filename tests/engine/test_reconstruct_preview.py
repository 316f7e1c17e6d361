"""reconstruct's ``*_rgb.png`` is exposed for display, as simulate's sensor preview and data show's thumbnails are.

It was the cube's absolute render: the README's own example (a held-out scene through the shipped camera) gave a
preview of mean sRGB value 25 of 255, and a dim capture a nearly black one. Now the cube's luminance (CIE Y, a white
reflector's Y = 1) has its 99th percentile at PREVIEW_LEVEL of white; the gain is recorded in the PNG's text chunk,
the cube's metadata and the success line, and the cube itself is unchanged. References: the sRGB transfer function
inverted by hand (IEC 61966-2-1) and the sRGB → XYZ luminance row (0.2126, 0.7152, 0.0722)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from PIL import Image

from cli_helpers import assert_ok, run_cli_in_process
from hsicam.color import PREVIEW_EXPOSURE_KEY, PREVIEW_LEVEL, display_gain, preview_exposure, srgb_preview
from hsicam.errors import InputError
from hsicam.spectral import Bands

BANDS = Bands.uniform(420.0, 720.0, 10.0)


def _linear(srgb8: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's decoding of 8-bit sRGB values."""
    v = srgb8.astype(np.float64) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def test_the_exposure_puts_the_99th_percentile_of_a_grey_cubes_luminance_at_the_level():
    """Flat spectra of reflectance r have Y = r. 2 % of the pixels at 0.9, the rest at 0.1: the 99th percentile is
    0.9, whatever the chunking and with a NaN pixel; a black, all-NaN or denormal-dim cube keeps the gain 1."""
    cube = np.full((31, 50, 40), 0.1, np.float32)
    cube[:, :1, :] = 0.9  # 40 of 2000 px
    for chunk in (None, 40, 123):
        assert preview_exposure(cube, BANDS, chunk_px=chunk) == pytest.approx(PREVIEW_LEVEL / 0.9, rel=1e-5)
    assert preview_exposure(np.zeros((31, 8, 8), np.float32), BANDS) == 1.0
    assert preview_exposure(np.full((31, 8, 8), np.nan, np.float32), BANDS) == 1.0
    holed = cube.copy()
    holed[:, 10, 10] = np.nan  # one NaN pixel is left out, not a reason to leave the preview unexposed
    assert preview_exposure(holed, BANDS) == pytest.approx(PREVIEW_LEVEL / 0.9, rel=1e-5)
    # a luminance so small that its gain is no float32 (it became inf in the cube, a black preview): gain 1
    assert preview_exposure(np.full((31, 8, 8), 1e-40, np.float32), BANDS) == 1.0
    # the one rule of every preview's gain (simulate's sensor preview and data show's grey thumbnails too)
    assert [display_gain(v) for v in (0.4, 0.0, -1.0, float("nan"), float("inf"), 1e-40)] == [2.0, 1, 1, 1, 1, 1]


def test_an_exposed_preview_is_the_render_of_the_cube_times_the_exposure():
    cube = np.random.default_rng(0).uniform(0.0, 0.2, (31, 37, 29)).astype(np.float32)
    np.testing.assert_array_equal(srgb_preview(cube, BANDS, chunk_px=100, exposure=3.5),
                                  srgb_preview(cube * np.float32(3.5), BANDS))
    for bad in (0.0, -1.0, float("nan"), float("inf"), True, "2"):
        with pytest.raises(InputError, match="exposure must be a positive number"):
            srgb_preview(cube, BANDS, exposure=bad)


def test_reconstructs_preview_of_a_dim_capture_is_exposed_and_says_by_how_much(tmp_path):
    """A dim capture (a 0.03 grey field with a brighter square, through the shipped camera): the preview is the
    render of the cube read back times the recorded gain (> 5), its luminance, decoded from the PNG's 8-bit values,
    has its 99th percentile at PREVIEW_LEVEL (to the 8-bit step), where the absolute render's is below a fifth of
    it."""
    rng = np.random.default_rng(1)
    cap = np.full((96, 96), 0.03, np.float32) + rng.uniform(0, 0.004, (96, 96)).astype(np.float32)
    cap[30:60, 30:60] *= 2.0
    np.save(tmp_path / "dim.npy", cap)
    res = run_cli_in_process("reconstruct", str(tmp_path / "dim.npy"), "--run", "pretrained:standard",
                             "--out", str(tmp_path / "c.h5"), "--cfa-offset", "0,0")
    assert_ok(res)
    with h5py.File(tmp_path / "c.h5", "r") as f:
        cube = f["cube"][()]
        meta = json.loads(f.attrs["metadata_json"])
    with Image.open(tmp_path / "c_rgb.png") as im:
        text, png = dict(im.text), np.asarray(im.convert("RGB"))
    exposure = float(text[PREVIEW_EXPOSURE_KEY])
    assert exposure == pytest.approx(meta["preview_exposure"], rel=1e-5) and exposure > 5
    assert f"(sRGB preview c_rgb.png, exposed ×{meta['preview_exposure']:.3g} for display)" in res.stdout
    np.testing.assert_array_equal(png, srgb_preview(cube, BANDS, exposure=meta["preview_exposure"]))
    y = _linear(png) @ np.array([0.2126, 0.7152, 0.0722])
    assert np.percentile(y, 99) == pytest.approx(PREVIEW_LEVEL, abs=0.02)
    absolute = _linear(srgb_preview(cube, BANDS)) @ np.array([0.2126, 0.7152, 0.0722])
    assert np.percentile(absolute, 99) < PREVIEW_LEVEL / 5
