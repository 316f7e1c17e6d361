"""Lines of config, spectral, data/measured_psf, sensor and cameras that the default suite never ran: each test runs
one and checks what it does against an independent reference (the exact line a user sees, a closed form)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from hsicam.config import BandsConfig, ChoiConfig, ConfigError, LensConfig, TrainConfig, load_config
from hsicam.data.measured_psf import (centroid, find_centre, import_psf_dir, pedestal_level, resample_area,
                                      saturated_pixels)
from hsicam.errors import InputError
from hsicam.spectral import Bands, TabulatedMaterial

ONE_BAND = Bands(np.array([500.0]), np.array([10.0]))


def _table(path: Path, lo: float, hi: float) -> Path:
    path.write_text(f"wavelength_nm,n\n{lo:g},1.47\n{hi:g},1.45\n", encoding="utf-8")
    return path


# --- spectral/materials.py: a CSV table short of the wavelengths the camera needs -----------------------------------

def test_a_doe_material_table_short_of_the_bands_names_its_file_and_the_wavelengths(tmp_path):
    """config.py's range check leaves a CSV table to be read with the camera (_check_material_range returns); the
    camera then said only "material 'glass' is tabulated for 400-700 nm only", naming no file and no wavelength."""
    from hsicam.cameras import build_camera

    table = _table(tmp_path / "glass.csv", 400, 700)
    cfg = load_config("tiny", overrides=[f"camera.doe.material={table}"])  # accepted: the file is not opened here
    assert cfg.camera.psf.band_samples == 1  # the PSF is computed at the band centres
    centres = BandsConfig(**{k: getattr(cfg.bands, k) for k in ("start_nm", "stop_nm", "step_nm")}).to_bands().centers_nm
    assert centres.max() > 700
    with pytest.raises(InputError) as exc:
        build_camera(cfg)
    assert str(exc.value) == (f"camera.doe.material: {table}: material 'glass' is tabulated for 400-700 nm only, but "
                              f"its refractive index is needed at {centres.min():g}-{centres.max():g} nm")


def test_a_singlet_lens_table_short_of_its_design_wavelength_names_key_file_and_wavelength(tmp_path):
    table = _table(tmp_path / "lens.csv", 600, 700)
    cfg = load_config(overrides=["camera.lens.model=singlet", f"camera.lens.material={table}"])  # not opened yet
    with pytest.raises(ConfigError) as exc:
        cfg.camera.lens.design_focal_length_mm()
    assert str(exc.value) == (f"camera.lens.material: {table}: material 'lens' is tabulated for 600-700 nm only, but "
                              f"its refractive index is needed at {LensConfig().design_wavelength_nm:g} nm")


def test_a_table_built_in_memory_is_refused_by_its_name_and_shows_its_range():
    mat = TabulatedMaterial(np.array([400.0, 700.0]), np.array([1.5, 1.4]), name="mine")
    assert repr(mat) == "TabulatedMaterial('mine', 400-700 nm)"
    assert mat.n(550.0) == pytest.approx(1.45)  # linear between the two rows
    with pytest.raises(InputError) as exc:
        mat.n(np.array([380.0, 500.0]))
    assert str(exc.value) == "material 'mine' is tabulated for 400-700 nm only, but its refractive index is needed at 380-500 nm"


# --- config.py ----------------------------------------------------------------------------------------------------

def test_a_seed_set_in_python_that_is_no_integer_is_refused_with_its_key():
    """The YAML path refuses it in _coerce; a section built in Python reaches seed_problem's type check."""
    from hsicam.engine.tolerance import ToleranceSpec

    with pytest.raises(ConfigError) as exc:
        ChoiConfig(seed=1.5)
    assert str(exc.value) == "baselines.choi.seed must be an integer, got 1.5"
    with pytest.raises(ConfigError) as exc:
        TrainConfig(seed=True)  # a bool is no seed although Python counts it as an int
    assert str(exc.value) == "train.seed must be an integer, got True"
    with pytest.raises(InputError) as exc:
        ToleranceSpec(seed=2.0).check()
    assert str(exc.value) == "ToleranceSpec.seed must be an integer, got 2.0"


@pytest.mark.parametrize("overrides, text", [
    (["baselines.desci.sigmas=[1, 2]", "baselines.desci.iterations=[3]"], "baselines.desci: 2 sigmas but 1 iteration counts"),
    (["baselines.choi.train_noise=-1"], "baselines.choi.train_noise must be >= 0, got -1.0"),
    (["baselines.choi.prior_weight=-0.5"], "baselines.choi.prior_weight must be >= 0, got -0.5"),
    (["baselines.choi.tv_weight=-0.001"], "baselines.choi.tv_weight must be >= 0, got -0.001"),
])
def test_baseline_settings_refused_with_their_key(overrides, text):
    with pytest.raises(ConfigError) as exc:
        load_config(overrides=overrides)
    assert str(exc.value) == text


def test_a_config_file_with_a_control_character_is_one_line_naming_the_file(tmp_path):
    """PyYAML's reader error has no problem mark (yaml_error_text's branch without line:column)."""
    path = tmp_path / "bad.yaml"
    path.write_bytes(b"train:\n  lr: 1\x07\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value) == f"{path}: invalid YAML (unacceptable character #x0007: special characters are not allowed)"


def test_a_section_left_empty_in_a_file_takes_its_defaults(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("train:\nbands:\ndata: {synthetic_n: 7}\n", encoding="utf-8")
    cfg = load_config(path)
    assert cfg.train == TrainConfig() and cfg.bands == BandsConfig() and cfg.data.synthetic_n == 7


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


# --- spectral/bands.py, sensor.py, cameras ------------------------------------------------------------------------

def test_band_samples_below_one_and_a_one_band_source_kernel():
    from hsicam.spectral.bands import band_sample_wavelengths, resampling_matrix

    with pytest.raises(ValueError, match=r"^band samples must be >= 1$"):
        band_sample_wavelengths(np.array([500.0]), np.array([10.0]), 0)
    one = Bands(np.array([500.0]), np.array([10.0]))
    w = resampling_matrix(one, Bands(np.array([500.0]), np.array([30.0])))
    assert w.shape == (1, 1) and w[0, 0] == 1.0  # one source band: the target is that band, whatever its width


def test_sensor_modules_refuse_unknown_kinds_and_describe_themselves():
    from hsicam.sensor import ColorFilterArray as CFA, SensorNoise

    with pytest.raises(ValueError, match=r"^unknown CFA init 'random'; use 'uniform' or 'bandpass'$"):
        CFA(4, 3, init="random")
    with pytest.raises(ValueError, match=r"^unknown noise model 'shot'$"):
        SensorNoise("shot")
    assert repr(CFA(4, 3)) == "ColorFilterArray(n_bands=4, period=3, enabled=True)"
    assert repr(SensorNoise("gaussian", 0.01, bit_depth=8)) == "SensorNoise(model=gaussian, sigma=0.01, bit_depth=8)"
    noisy = SensorNoise("gaussian", 0.0, gain=torch.ones(4, 6), gain_origin=(2, 3))
    assert repr(noisy) == "SensorNoise(model=gaussian, sigma=0.0, bit_depth=None, gain=(4, 6) at (2, 3))"


def test_a_camera_kind_registered_twice_is_refused():
    from hsicam.cameras.registry import CAMERAS, register_camera

    existing = CAMERAS["doe"]

    class Other:
        pass

    with pytest.raises(ValueError, match=rf"^camera kind 'doe' is registered twice \({existing.__name__}, Other\)$"):
        register_camera("doe")(Other)
    assert CAMERAS["doe"] is existing
