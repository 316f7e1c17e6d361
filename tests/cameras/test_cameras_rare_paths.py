"""Lines of data/measured_psf and the camera registry that the default suite never ran, and the cameras' defocus
and coded-aperture refusals (moved from models/test_models_rare_paths.py and data/test_data_sources_rare_paths.py):
each test runs one and checks what it does against an independent reference (the exact line a user sees, a closed
form, a file read back)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import TINY_CAMERA_OVERRIDES
from hsicam.cameras import DOECamera, build_camera
from hsicam.config import ConfigError, load_config
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


def _clipped_refusal(d, n: int) -> str:
    """The one line that refuses ``d``'s psf_500nm.npy, 31×31 px of 8 bits, ``n`` of them clipped, border too."""
    return (f"{d}/psf_500nm.npy (500 nm): a clipped (over-exposed) PSF image: {n} of its 961 pixels are at 255 (the "
            "file type's maximum), the median of its border too, so nothing is left above the background: measure it "
            "again with a shorter exposure (brightest pixel below 255)")


def _psf_folder(d, img: np.ndarray, **meta):
    d.mkdir()
    np.save(d / "psf_500nm.npy", img)
    (d / "psf.json").write_text(json.dumps(meta))
    return d


def test_psf_images_without_signal_past_the_saturation_check_and_with_normalize_none_name_the_file(tmp_path):
    """An all-255 frame: 961 clipped pixels, nothing left over its border level: refused as clipped (it was 'no
    positive signal', which sends the user looking for a dark frame); an empty image with normalize: none and the
    centre on a given axis: no signal."""
    sat = _psf_folder(tmp_path / "sat", np.full((31, 31), 255, np.uint8), background="border")
    zero = _psf_folder(tmp_path / "zero", np.zeros((31, 31)), normalize="none", centre="axis", axis_px=[15, 15])
    with pytest.raises(InputError) as exc:
        import_psf_dir(sat, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == _clipped_refusal(sat, 961)
    with pytest.raises(InputError) as exc:
        import_psf_dir(zero, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == f"{zero}/psf_500nm.npy (500 nm): PSF image has no positive signal (after background subtraction)"


def test_a_psf_clipped_over_its_frame_but_its_first_row_is_refused_as_clipped(tmp_path):
    """The frame's median (what `background: border` subtracts) at 255 leaves nothing above it: refused as clipped,
    whatever the first row holds (the check read the first row only, and this image was 'no positive signal')."""
    img = np.full((31, 31), 255, np.uint8)
    img[0] = 0  # 31 of the frame's 232 pixels: its median stays 255
    d = _psf_folder(tmp_path / "sat", img, background="border")
    with pytest.raises(InputError) as exc:
        import_psf_dir(d, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == _clipped_refusal(d, 930)


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


def _sellmeier_fused_silica(lam_nm: float) -> float:
    """Malitson (1965), written out here (not the library's table)."""
    x = (lam_nm / 1000.0) ** 2
    return math.sqrt(1 + 0.6961663 * x / (x - 0.0684043**2) + 0.4079426 * x / (x - 0.1162414**2)
                     + 0.8974794 * x / (x - 9.896161**2))


# --- optics/psf.py: the defocus refusal names the option that caused it -----------------------------------------
def test_object_distance_defocus_refusal_names_the_object_distance_and_where_the_sensor_belongs():
    # tiny optics: f = 5 mm, aperture radius 0.25 mm, 50 µm cells; an object at 5.1 mm images at
    # 1 / (1/5 − 1/5.1) = 255 mm, the sensor stays at f: geometric blur 2a · z_i / z_o = 0.5 · 5 / 5.1 mm
    blur_mm = 0.5 * 5.0 / 5.1
    field_mm = 500e-9 * 5e-3 / 50e-6 * 1e3  # λ z / d at 500 nm (the band that aliases most: the shortest)
    with pytest.raises(ConfigError) as err:
        DOECamera.from_config(load_config(overrides=[*TINY_CAMERA_OVERRIDES, "camera.object_distance_m=0.0051"]))
    msg = str(err.value)
    assert msg.startswith("camera.object_distance_m=0.0051 defocuses the lens more than the pupil sampling can "
                          "represent (focal length 5 mm at 587.6 nm, object at 0.0051 m: the sensor belongs near "
                          f"{1 / (1 / 5 - 1 / 5.1):.4g} mm)")
    assert f"blurs a point over {blur_mm:.3g} mm at 500 nm, wider than the {field_mm:.3g} mm field" in msg
    assert msg.endswith(f"focus on the object (camera.sensor_distance_mm={1 / (1 / 5 - 1 / 5.1):.4g}), or for a "
                        f"deliberate defocus raise camera.psf.pupil_oversample to at least "
                        f"{math.ceil(blur_mm / field_mm)}")


def test_singlet_focus_shift_refusal_blames_the_lens_not_an_option():
    # the paper's singlet (R = 16 mm, t = 2 mm, f = R/(n−1)) on 100 µm cells: at 420 nm the sensor, placed at f(587.6 nm)
    # from the rear principal plane H' (t/n behind the curved vertex, so it moves with n), sits off that band's focus
    n0, n1 = _sellmeier_fused_silica(587.6), _sellmeier_fused_silica(420.0)
    f0, f1 = 16.0 / (n0 - 1), 16.0 / (n1 - 1)
    z = f0 - 2.0 / n0 + 2.0 / n1  # the sensor's distance from H'(420 nm)
    blur_mm = 2 * 5.0 * abs(1 - z / f1)  # aperture diameter 10 mm
    field_mm = 420e-9 * z * 1e-3 / 100e-6 * 1e3
    with pytest.raises(ConfigError) as err:
        DOECamera.from_config(load_config(overrides=["camera.lens.model=singlet", "camera.doe.cell_size_um=100"]))
    msg = str(err.value)
    assert msg.startswith("the singlet lens's focus shift defocuses the lens more than the pupil sampling can represent "
                          f"(focal length {f0:.4g} mm at 587.6 nm, object at infinity: the sensor belongs near {f0:.4g} mm)")
    assert f"blurs a point over {blur_mm:.3g} mm at 420 nm, wider than the {field_mm:.3g} mm field" in msg
    assert msg.endswith(f"; for a deliberate defocus raise camera.psf.pupil_oversample to at least "
                        f"{math.ceil(blur_mm / field_mm)}")


# --- cameras/cassi.py: coded-aperture files --------------------------------------------------------------------
def _cassi(tmp_path, mask_name: str):
    cfg = load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50",
                                 "camera.kind=dd_cassi", f"camera.cassi.mask_file={tmp_path / mask_name}"])
    return build_camera(cfg).double()


def test_a_boolean_mask_file_is_a_binary_coded_aperture(tmp_path):
    mask = np.random.default_rng(0).random((12, 30)) > 0.5  # np.save of a thresholded pattern: dtype bool
    np.save(tmp_path / "mask.npy", mask)
    cam = _cassi(tmp_path, "mask.npy")
    np.testing.assert_array_equal(cam.aperture.pattern(12, 18).numpy(), mask[:, :18].astype(np.float64))


@pytest.mark.parametrize("content, what", [(b"0 1 1 0\n1 0 0 1\n", "no NumPy header"), (None, "a .npz archive"),
                                           (b"", "an empty file")])
def test_a_mask_file_that_is_not_npy_is_named_as_such_without_pickle_advice(tmp_path, content, what):
    path = tmp_path / "mask.npy"
    if content is None:  # np.savez to a file object keeps the .npy name
        with open(path, "wb") as fh:
            np.savez(fh, mask=np.ones((4, 4)))
    else:
        path.write_bytes(content)
    with pytest.raises(InputError) as err:
        _cassi(tmp_path, "mask.npy")
    assert str(err.value) == f"{path}: not a .npy file ({what}); save the coded aperture (H, W) with numpy.save"


@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 64), (3, 4, 5), (0, 6)])
def test_a_mask_of_the_wrong_shape_is_refused_naming_the_shape_stored(tmp_path, shape):
    """The message names the array's shape as the file stores it ((1, 64) was said to be (64,) once squeezed)."""
    np.save(tmp_path / "mask.npy", np.ones(shape))
    with pytest.raises(InputError) as err:
        _cassi(tmp_path, "mask.npy")
    assert str(err.value) == (f"{tmp_path / 'mask.npy'}: a coded aperture must be a 2-D (H, W) array of at least 1×1 "
                              f"after dropping axes of length 1, got shape {shape}")


def test_a_folder_given_as_the_mask_is_said_to_be_one(tmp_path):
    (tmp_path / "masks.npy").mkdir()
    with pytest.raises(InputError) as err:
        _cassi(tmp_path, "masks.npy")
    assert str(err.value) == f"{tmp_path / 'masks.npy'}: is a folder, not a coded-aperture file (a .npy array (H, W))"
