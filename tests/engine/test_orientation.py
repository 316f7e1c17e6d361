"""``reconstruct --orientation``: a capture stored mirrored or rotated against the sensor's readout.

Every pixel of such a capture is read through another filter than its own, and the CFA phases cannot fix it (session
73: a held-out scene, 32.9 dB aligned, came back at 15-16 dB, SAM 51-60°, silently). The camera is the shipped
``pretrained:standard`` (a trained network behind a 4×4 CFA), the scene procedural, as in test_cfa_offset.py."""

from __future__ import annotations

import json
import logging

import h5py
import numpy as np
import pytest
import torch

from cli_helpers import assert_ok, error_line, run_cli_in_process
from procedural_scenes import procedural_scene
from hsicam.engine.orientation import ORIENTATIONS, to_capture, to_sensor
from hsicam.errors import InputError
from hsicam.runs.folder import load_run

RUN = "pretrained:standard"


def test_each_orientation_is_the_transform_its_name_says_and_to_sensor_undoes_it():
    a = np.arange(12).reshape(3, 4)  # not square: a transpose and a rotation are told from the others
    h, w = a.shape
    expected = {"as-read": a, "flip-lr": a[:, ::-1], "flip-ud": a[::-1], "rot90": np.rot90(a), "rot180": a[::-1, ::-1],
                "rot270": np.rot90(a, -1), "transpose": a.T,
                "antitranspose": np.array([[a[h - 1 - c, w - 1 - r] for c in range(h)] for r in range(w)])}
    assert set(expected) == set(ORIENTATIONS)
    assert np.array_equal(expected["rot90"][0], a[:, -1])  # counter-clockwise: the last column on top
    for name, stored in expected.items():
        np.testing.assert_array_equal(to_capture(a, name), stored, err_msg=name)
        np.testing.assert_array_equal(to_sensor(stored, name), a, err_msg=name)
        t = torch.from_numpy(np.ascontiguousarray(a))[None, None]
        np.testing.assert_array_equal(to_capture(t, name)[0, 0].numpy(), stored, err_msg=name)
        np.testing.assert_array_equal(to_sensor(to_capture(t, name), name).numpy(), t.numpy(), err_msg=name)
    with pytest.raises(InputError, match="unknown orientation 'flipx': use one of as-read, flip-lr"):
        to_sensor(a, "flipx")


@pytest.fixture(scope="module")
def sensor():
    """The whole noisy sensor image (200, 200) of the pre-trained camera (the fixture of test_cfa_offset.py)."""
    _, system = load_run(RUN, overrides=("camera.boundary=same",))
    system.eval()
    scene = torch.from_numpy(procedural_scene(system.camera.bands.centers_nm))[None]
    with torch.no_grad():
        y = system.camera.capture(scene, torch.Generator().manual_seed(0))
    y = y + 0.005 * torch.randn(y.shape, generator=torch.Generator().manual_seed(1))
    return y.clamp(0, 1)[0, 0].numpy()


def _cube(path):
    with h5py.File(path, "r") as f:
        return f["cube"][()], json.loads(f.attrs["metadata_json"])


@pytest.mark.parametrize("name", ["flip-lr", "rot90", "antitranspose"])
def test_a_turned_capture_with_its_orientation_reconstructs_as_the_aligned_one_turned(sensor, tmp_path, name):
    """The capture is brought back to the readout before anything else, and the cube turned into the capture's
    frame: bit for bit the aligned capture's cube, turned. A clipped pixel, marked in the capture as stored, is
    where the readout's is (the steps take it as a lower bound there)."""
    crop = sensor[:72, :96].copy()  # not square
    crop[30, 40] = 1.0  # clipped (a float capture's white level is 1)
    np.save(tmp_path / "aligned.npy", crop)
    np.save(tmp_path / "turned.npy", np.ascontiguousarray(to_capture(crop, name)))
    for stem, extra in (("aligned", []), ("turned", ["--orientation", name])):
        assert_ok(run_cli_in_process("reconstruct", str(tmp_path / f"{stem}.npy"), "--run", RUN, "--out",
                                     str(tmp_path / f"{stem}.h5"), "--cfa-offset", "0,0", "--white-level", "1", *extra))
    (aligned, meta_a), (turned, meta_t) = _cube(tmp_path / "aligned.h5"), _cube(tmp_path / "turned.h5")
    assert turned.shape == (aligned.shape[0], *to_capture(crop, name).shape)
    np.testing.assert_array_equal(turned, to_capture(aligned, name))
    assert meta_t["orientation"] == name and meta_a["orientation"] == "as-read"
    assert meta_t["clipped_px_as_lower_bounds"] == meta_a["clipped_px_as_lower_bounds"] == 1


def test_the_check_warns_of_a_mirrored_capture_and_not_of_an_aligned_one(sensor, tmp_path, caplog):
    """No --orientation: a capture mirrored left-right (its best CFA phase as read is not 0,0) is scored in the 7 other
    orientations at phase 0,0, and flip-lr explains it clearly better: warned, naming --orientation flip-lr and auto.
    The aligned capture's best phase is 0,0: nothing more is scored, nothing said."""
    np.save(tmp_path / "aligned.npy", sensor)
    np.save(tmp_path / "mirrored.npy", np.ascontiguousarray(sensor[:, ::-1]))
    with caplog.at_level(logging.WARNING):
        assert_ok(run_cli_in_process("reconstruct", str(tmp_path / "aligned.npy"), "--run", RUN, "--out",
                                     str(tmp_path / "aligned.h5")))
    assert not caplog.records, caplog.text
    check = _cube(tmp_path / "aligned.h5")[1]["cfa_offset_check"]
    assert check["offset"] == [0, 0] and "orientation_check" not in check
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert_ok(run_cli_in_process("reconstruct", str(tmp_path / "mirrored.npy"), "--run", RUN, "--out",
                                     str(tmp_path / "mirrored.h5")))
    [warning] = [r.getMessage() for r in caplog.records]
    assert warning.startswith(f"{tmp_path / 'mirrored.npy'}: the capture does not look as if it were stored as the "
                              "sensor reads it out: read as flip-lr"), warning
    assert "give --orientation flip-lr, or --orientation auto" in warning
    turned = _cube(tmp_path / "mirrored.h5")[1]["cfa_offset_check"]["orientation_check"]
    assert turned["warned"] is True and turned["orientation"] == "flip-lr"
    assert turned["residual"] * 1.5 <= turned["as_read_best"] == min(
        _cube(tmp_path / "mirrored.h5")[1]["cfa_offset_check"]["residuals"].values())


def test_auto_finds_the_orientation_and_reconstructs_as_given(sensor, tmp_path):
    """--orientation auto scores the 8 orientations × 16 phases: a capture turned by 90° is found (rot90), and the
    cube is the one --orientation rot90 gives."""
    crop = sensor[:160, :160]
    np.save(tmp_path / "turned.npy", np.ascontiguousarray(np.rot90(crop)))
    for stem, value in (("auto", "auto"), ("given", "rot90")):
        assert_ok(run_cli_in_process("reconstruct", str(tmp_path / "turned.npy"), "--run", RUN, "--out",
                                     str(tmp_path / f"{stem}.h5"), "--orientation", value))
    (auto, meta), (given, _) = _cube(tmp_path / "auto.h5"), _cube(tmp_path / "given.h5")
    assert meta["orientation"] == "rot90" and meta["orientation_estimate"]["orientation"] == "rot90"
    assert len(meta["orientation_estimate"]["residuals"]) == 8
    np.testing.assert_array_equal(auto, given)


def test_bad_orientations_are_one_clear_error(sensor, tmp_path):
    np.save(tmp_path / "c.npy", sensor[:64, :64])
    res = run_cli_in_process("reconstruct", str(tmp_path / "c.npy"), "--run", RUN, "--out", str(tmp_path / "c.h5"),
                             "--orientation", "mirror")
    assert res.returncode == 2
    assert "expected one of as-read, flip-lr, flip-ud, rot90, rot180, rot270, transpose, antitranspose" in error_line(res)
    assert "or auto, got 'mirror'" in error_line(res)
    assert not (tmp_path / "c.h5").exists()
