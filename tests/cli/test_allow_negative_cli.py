"""A measured cube with negative values (dark noise after a background subtraction) is refused by every command
that reads scenes, and the refusal names the way out that the command takes: ``--set data.allow_negative=true``,
which clips them to 0 as ``read_cube(..., allow_negative=True)`` does (session 75: the refusal named none, and no
command could lift it)."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from fab_runs import fab_run  # noqa: F401 - the shared fixture
from cli_helpers import assert_clean_error, assert_ok, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from hsicam.data.formats import HSICAM_FORMAT, write_cube_h5
from hsicam.spectral import Bands

BANDS = Bands.uniform(500, 600, 50)  # the tiny camera's (TINY_CAMERA_OVERRIDES)
CAMERA = [x for o in TINY_CAMERA_OVERRIDES for x in ("--set", o)]
CLIP = ("--set", "data.allow_negative=true")
WAY_OUT = "--set data.allow_negative=true clips them to 0"


def _cube(seed: int, size: int = 40) -> np.ndarray:
    """A (3, size, size) cube of values in [0.1, 1] with 5 negative values (down to -0.02) in band 0."""
    c = np.random.default_rng(seed).uniform(0.1, 1.0, (3, size, size)).astype(np.float32)
    c[0, 3, :5] = np.linspace(-0.02, -0.004, 5)
    return c


def write_hsicam_h5(path: Path, cube: np.ndarray) -> None:
    """Our HDF5 layout written by h5py (write_cube_h5 refuses negative values), so a dataset reads it window by
    window (its pixels checked by the windowed check, not by read_cube)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f["cube"] = cube
        f["bands_nm"] = BANDS.centers_nm
        f["fwhm_nm"] = BANDS.fwhm_nm
        f.attrs["format"], f.attrs["version"], f.attrs["max_value"] = HSICAM_FORMAT, 1, float(cube.max())


def write_folder(folder: Path) -> Path:
    """2 scenes with negative values: our HDF5 (read window by window) and a MAT v5 H×W×C (read whole)."""
    write_hsicam_h5(folder / "a.h5", _cube(0))
    scipy.io.savemat(folder / "b.mat", {"cube": np.transpose(_cube(1), (1, 2, 0)).astype(np.float64),
                                        "bands": BANDS.centers_nm[None]})
    return folder


def test_train_refuses_negative_scenes_naming_the_option_and_trains_with_it(tmp_path, cache_env):
    data = write_folder(tmp_path / "data")
    args = ("train", "--config", "tiny", *CAMERA, "--set", "train.epochs=1", "--set", f"data.root={data}",
            "--set", "data.preload=false")  # the HDF5 scene read window by window: the windowed check's refusal
    res = run_cli_in_process(*args, "--out", str(tmp_path / "run"))
    assert_clean_error(res, f"{data / 'a.h5'}: 5 negative radiance value(s) (minimum -0.02)", WAY_OUT)
    assert_ok(run_cli_in_process(*args, *CLIP, "--out", str(tmp_path / "run2")))
    assert json.loads((tmp_path / "run2" / "data.json").read_text())["train"]  # it trained on the folder


def test_data_show_refuses_and_then_clips(tmp_path):
    data = write_folder(tmp_path / "data")
    res = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "show"))
    assert_clean_error(res, f"{data / 'a.h5'}: 5 negative radiance value(s)", WAY_OUT)
    assert not (tmp_path / "show" / "contact_sheet.png").exists()
    assert_ok(run_cli_in_process("data", "show", str(data), *CLIP, "--out", str(tmp_path / "show")))
    assert (tmp_path / "show" / "contact_sheet.png").is_file()


@pytest.mark.parametrize("suffix", [".h5", ".mat"])
def test_simulate_with_the_option_images_the_scene_clipped_at_zero(tmp_path, suffix):
    """The sensor image of the negative scene with the option is, to the bit, that of the same scene whose negative
    values were set to 0 by hand (written by write_cube_h5, which checks them)."""
    cube = _cube(2)
    scene = tmp_path / f"neg{suffix}"
    if suffix == ".h5":
        write_hsicam_h5(scene, cube)
    else:
        scipy.io.savemat(scene, {"cube": np.transpose(cube, (1, 2, 0)).astype(np.float64),
                                 "bands": BANDS.centers_nm[None]})
    clipped = write_cube_h5(tmp_path / "clipped.h5", np.maximum(cube, 0.0), BANDS)
    sim = ("simulate", *CAMERA)  # the same seed: the same noise draws
    res = run_cli_in_process(*sim, "--scene", str(scene), "--out", str(tmp_path / "sim"))
    assert_clean_error(res, f"{scene}: 5 negative radiance value(s)", WAY_OUT)
    assert_ok(run_cli_in_process(*sim, *CLIP, "--scene", str(scene), "--out", str(tmp_path / "sim")))
    assert_ok(run_cli_in_process(*sim, "--scene", str(clipped), "--out", str(tmp_path / "ref")))
    got, want = (np.load(tmp_path / d / "sensor.npy") for d in ("sim", "ref"))
    assert got.shape == want.shape and np.array_equal(got, want)


def test_tolerance_refuses_negative_scenes_naming_its_own_flag_and_clips_with_it(fab_run, tmp_path):  # noqa: F811
    """`hsicam tolerance` takes no --set: the refusal names its --allow-negative, which clips them (the study's
    identity then differs: its config hash holds the setting)."""
    data = tmp_path / "neg"
    write_hsicam_h5(data / "a.h5", _cube(0, size=64))
    study = ("tolerance", "--run", str(fab_run), "--data", str(data), "--max-scenes", "1", "--draws", "1",
             "--sigma-height-nm", "0", "--levels", "2", "--shift-cells", "0", "--sensor-distance-um=0")
    res = run_cli_in_process(*study, "--out", str(tmp_path / "t1"))
    assert_clean_error(res, f"{data / 'a.h5'}: 5 negative radiance value(s)", "(hsicam tolerance: --allow-negative)")
    res = run_cli_in_process(*study, "--out", str(tmp_path / "t2"), "--allow-negative")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "t2" / "tolerance.json").is_file()
