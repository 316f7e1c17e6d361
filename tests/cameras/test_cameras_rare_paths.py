"""Lines of data/measured_psf and of the camera registry that the default suite never ran: each test runs one and
checks what it does against an independent reference (the exact line a user sees, a closed form)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hsicam.data.measured_psf import (centroid, find_centre, import_psf_dir, pedestal_level, resample_area,
                                      saturated_pixels)
from hsicam.errors import InputError
from hsicam.spectral import Bands

ONE_BAND = Bands(np.array([500.0]), np.array([10.0]))


# --- data/measured_psf.py -----------------------------------------------------------------------------------------

def test_saturation_of_integer_images_below_the_type_and_sensor_maxima_is_none():
    assert saturated_pixels(np.array([[3000, 5, 3000]], np.uint16), 65535.0) == (0, 65535.0, "the file type's maximum")
    assert saturated_pixels(np.array([[200, 7]], np.uint8), 255.0) == (0, 255.0, "the file type's maximum")
    # the reference cases either side: at a 12-bit sensor's maximum, and at the type's own
    assert saturated_pixels(np.array([[4095, 4095, 3]], np.uint16), 65535.0) == (2, 4095.0, "a 12-bit sensor's maximum")
    assert saturated_pixels(np.array([[255, 3]], np.uint8), 255.0) == (1, 255.0, "the file type's maximum")


def test_an_unsaturated_8_bit_psf_imports_without_a_clipping_warning(tmp_path, caplog):
    d = tmp_path / "psfs"
    d.mkdir()
    img = np.zeros((31, 31), np.uint8)
    img[14:17, 14:17] = 200  # a 3×3 spot, well below 255
    np.save(d / "psf_500nm.npy", img)
    with caplog.at_level("WARNING"):
        m = import_psf_dir(d, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert not [r for r in caplog.records if "clipped" in r.getMessage() or "saturat" in r.getMessage()]
    kernel = np.asarray(m.psf)[0]
    assert kernel.sum() == pytest.approx(1.0)  # the spot lies wholly inside the kernel, same pitch
    expected = np.zeros((15, 15))
    expected[6:9, 6:9] = 1 / 9  # same pitch, centroid on the frame's centre pixel: the spot itself, unblurred
    np.testing.assert_allclose(kernel, expected, atol=1e-7)


def test_psf_images_without_signal_past_the_saturation_check_and_with_normalize_none_name_the_file(tmp_path):
    """An all-255 frame: 961 clipped pixels, nothing left over its border level: refused as clipped (it was 'no
    positive signal', which sends the user looking for a dark frame); an empty image with normalize: none and the
    centre on a given axis: no signal."""
    sat = tmp_path / "sat"
    sat.mkdir()
    np.save(sat / "psf_500nm.npy", np.full((31, 31), 255, np.uint8))
    (sat / "psf.json").write_text(json.dumps({"background": "border"}))
    zero = tmp_path / "zero"
    zero.mkdir()
    np.save(zero / "psf_500nm.npy", np.zeros((31, 31)))
    (zero / "psf.json").write_text(json.dumps({"normalize": "none", "centre": "axis", "axis_px": [15, 15]}))
    with pytest.raises(InputError) as exc:
        import_psf_dir(sat, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == (f"{sat}/psf_500nm.npy (500 nm): a clipped (over-exposed) PSF image: 961 of its 961 pixels "
                              "are at 255 (the file type's maximum), its border too, so nothing is left above the "
                              "background: measure it again with a shorter exposure (brightest pixel below 255)")
    with pytest.raises(InputError) as exc:
        import_psf_dir(zero, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == f"{zero}/psf_500nm.npy (500 nm): PSF image has no positive signal (after background subtraction)"


def test_measured_psf_helpers_refuse_what_the_import_never_passes():
    with pytest.raises(InputError, match=r"^PSF image has no positive signal \(after background subtraction\)$"):
        centroid(np.zeros((3, 3)))
    assert centroid(np.array([[0.0, 1.0], [0.0, 3.0]])) == (0.75, 1.0)  # rows weighted 1:3, all in column 1
    with pytest.raises(ValueError, match=r"^size_out must be odd, got 4$"):
        resample_area(np.ones((3, 3)), 1.0, 1.0, (1.0, 1.0), 4)
    with pytest.raises(InputError, match=r"^PSF centre 'axis' needs axis_px \[row, col\]$"):
        find_centre(np.ones((3, 3)), "axis")
    assert find_centre(np.ones((3, 3)), "axis", (0.5, 2.0)) == (0.5, 2.0)
    assert pedestal_level(np.full((4, 4), 10.0)) is None  # too small to have a frame
    assert pedestal_level(np.full((5, 5), 10.0)) == 10.0  # a flat frame: its median


# --- cameras/registry.py -----------------------------------------------------------------------------------------

def test_a_camera_kind_registered_twice_is_refused():
    from hsicam.cameras.registry import CAMERAS, register_camera

    existing = CAMERAS["doe"]

    class Other:
        pass

    with pytest.raises(ValueError, match=rf"^camera kind 'doe' is registered twice \({existing.__name__}, Other\)$"):
        register_camera("doe")(Other)
    assert CAMERAS["doe"] is existing
