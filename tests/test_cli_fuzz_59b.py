"""Hostile option values found by session 59's fuzzing of the commands that train or sweep (fuzz11a).

``reconstruct --full-well-e 1000 --read-noise-e 1e308`` (and ``--full-well-e 1e-300 --read-noise-e 2``) ended in an
OverflowError traceback of the noise variance (r/E)², after the run was loaded and the network had run; ``--full-well-e
1e-300`` alone reconstructed (exit 0) with an infinite noise variance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process, tree_snapshot


@pytest.fixture
def capture(tmp_path) -> Path:
    """A float capture on the simulator's scale (values in [0, 0.5]), in its real format (.npy)."""
    path = tmp_path / "cap.npy"
    np.save(path, (np.random.default_rng(0).random((48, 48)) * 0.5).astype(np.float32))
    return path


@pytest.mark.parametrize("options, said", [
    (("--full-well-e", "1000", "--read-noise-e", "1e308"),
     "--read-noise-e must be at most --full-well-e (1000 e-: read noise above the full scale buries any signal, as "
     "camera.sensor.read_noise_e), got 1e+308"),
    (("--full-well-e", "1e-300", "--read-noise-e", "2"),
     "--full-well-e must be a positive number of electrons in [1, 1e+12] (at the white level; sensors hold 10^3 to "
     "10^6, as camera.sensor.full_well_e), got 1e-300"),
    (("--full-well-e", "1e-300"),
     "--full-well-e must be a positive number of electrons in [1, 1e+12] (at the white level; sensors hold 10^3 to "
     "10^6, as camera.sensor.full_well_e), got 1e-300"),
    (("--full-well-e", "1e308"),
     "--full-well-e must be a positive number of electrons in [1, 1e+12] (at the white level; sensors hold 10^3 to "
     "10^6, as camera.sensor.full_well_e), got 1e+308"),
])
def test_reconstruct_refuses_capture_noise_outside_the_configs_range(capture, tmp_path, options, said):
    """The range camera.sensor takes (full well in [1, 1e12] e-, read noise at most the full well), in one line naming
    the option, before any work and without writing anything."""
    before = tree_snapshot(tmp_path)
    res = run_cli_in_process("reconstruct", str(capture), "--run", "pretrained:standard", "--out",
                             str(tmp_path / "est.h5"), *options)
    assert error_line(res) == f"hsicam: error: {said}"
    assert tree_snapshot(tmp_path) == before


def test_reconstruct_still_takes_a_read_noise_equal_to_the_full_well(capture, tmp_path):
    """The bound's edge (read noise = full well, as the config allows) reconstructs, the values in the cube's metadata."""
    import json

    import h5py

    out = tmp_path / "est.h5"
    res = run_cli_in_process("reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(out),
                             "--full-well-e", "50", "--read-noise-e", "50")
    assert res.returncode == 0, res.stderr
    with h5py.File(out, "r") as f:
        meta = json.loads(f.attrs["metadata_json"])
    assert meta["noise_full_well_e"] == 50.0 and meta["noise_read_noise_e"] == 50.0
