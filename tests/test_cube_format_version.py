"""Our HDF5 cube's ``version`` attribute: one below 1 (no hsicam ever wrote one; files from before
the attribute have none) is refused naming the version, by the readers and the command line alike,
as a newer version is (tests/test_cli_bad_paths.py); version 1 is still read."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from cli_helpers import assert_clean_error, run_cli_in_process
from hsicam.data.formats import read_cube, read_window, write_cube_h5
from hsicam.errors import InputError
from hsicam.spectral import Bands


def _cube_file(path: Path, version) -> Path:
    """Our HDF5 cube (3 bands on 500/550/600 nm, 12×12 px) with its ``version`` attribute set."""
    write_cube_h5(path, np.random.default_rng(1).random((3, 12, 12)).astype(np.float32), Bands.uniform(500, 600, 50))
    with h5py.File(path, "a") as f:
        f.attrs["version"] = version
    return path


@pytest.mark.parametrize("version", [0, -3])
def test_a_cube_file_of_a_version_below_one_is_refused(tmp_path, version):
    path = _cube_file(tmp_path / "old.h5", version)
    expected = (rf"^{path}: unknown hsicam cube format version {version} \(versions start at 1; this hsicam reads "
                r"version 1\): not a file that hsicam wrote, or a damaged one$")
    with pytest.raises(InputError, match=expected):
        read_cube(path)
    with pytest.raises(InputError, match=expected):
        read_window(path, 0, 0, 4, 4)
    out = tmp_path / "show"
    res = run_cli_in_process("data", "show", str(path), "--out", str(out))
    assert_clean_error(res, f"{path}: unknown hsicam cube format version {version}")
    assert not out.exists()


def test_a_cube_file_of_version_one_is_still_read(tmp_path):
    cube, bands, meta = read_cube(_cube_file(tmp_path / "v1.h5", 1))
    assert cube.shape == (3, 12, 12) and meta["file_version"] == 1
    assert bands.centers_nm.tolist() == [500.0, 550.0, 600.0]
    window, _ = read_window(tmp_path / "v1.h5", 0, 0, 4, 4)
    np.testing.assert_array_equal(window, cube[:, :4, :4])
