"""Lines of spectral (material tables, band sampling) and sensor that the default suite never ran: each test runs
one and checks what it does against an independent reference (the exact line a user sees, a closed form)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from hsicam.config import BandsConfig, ConfigError, LensConfig, load_config
from hsicam.errors import InputError
from hsicam.spectral import Bands, TabulatedMaterial


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


# --- spectral/bands.py, sensor.py -----------------------------------------------------------------------------------
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
