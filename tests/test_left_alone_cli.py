"""Command-line and config values that were accepted and then gave nonsense (session 60, left10c).

``reconstruct --cfa-offset 2**70,0`` reconstructed as 0,0 on a CFA camera and ended in a traceback on a CASSI camera;
``train.epochs`` / ``finetune --epochs`` 2^70 trained for ever; ``finetune --lr 1e308`` ended in torch's overflow
traceback at the first step; ``camera.cassi.mask_density=1e-300`` trained on an all-zero sensor."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process


def test_cfa_offset_beyond_any_sensor_is_a_usage_error(tmp_path):
    """``--cfa-offset 2**70,0`` was taken modulo the camera's cells (exit 0, the cube of 0,0); it is the sensor row
    and column of the capture's first pixel, and no sensor has 65536 of them."""
    from hsicam.cli.reconstruct import cfa_offset_arg

    capture = tmp_path / "cap.npy"
    np.save(capture, np.full((16, 16), 0.25, np.float32))
    out = tmp_path / "est.h5"
    res = run_cli_in_process("reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(out),
                             "--cfa-offset", f"{2**70},0")
    assert error_line(res) == ("hsicam: error: argument --cfa-offset: Y and X must be at most 65535 (the sensor row "
                               "and column of the capture's first pixel; no sensor is that large), got "
                               f"'{2**70},0'")
    assert not out.exists()
    assert cfa_offset_arg("65535,65535") == (65535, 65535)  # the largest taken
    with pytest.raises(argparse.ArgumentTypeError, match="at most 65535"):
        cfa_offset_arg("0,65536")
