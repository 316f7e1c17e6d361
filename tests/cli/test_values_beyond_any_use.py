"""Command-line and config values that were accepted and then gave nonsense (session 60, left10c).

``reconstruct --cfa-offset 2**70,0`` reconstructed as 0,0 on a CFA camera and ended in a traceback on a CASSI camera;
``train.epochs`` / ``finetune --epochs`` 2^70 trained for ever; ``finetune --lr 1e308`` ended in torch's overflow
traceback at the first step; ``camera.cassi.mask_density=1e-300`` trained on an all-zero sensor."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process
from hsicam.config import load_config
from hsicam.errors import ConfigError


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


def test_epochs_beyond_any_budget_are_refused():
    """``train.epochs=2**70`` trained for ever (a progress line promising an end in 10^18 s)."""
    with pytest.raises(ConfigError, match=rf"^train.epochs must be at most 1000000 \(the paper trains 100\), "
                                          rf"got {2**70}$"):
        load_config("tiny", [f"train.epochs={2**70}"])
    assert load_config("tiny", ["train.epochs=1000000"]).train.epochs == 10**6


def test_learning_rate_beyond_one_is_refused():
    """``train.lr=1e308`` passed the config; its first Adam step overflowed float32 (a traceback in fine-tuning)."""
    with pytest.raises(ConfigError, match=r"^train.lr must be at most 1 \(Adam's step per weight; the presets take "
                                          r"1e-4 to 1e-3\), got 1e\+308$"):
        load_config("tiny", ["train.lr=1e308"])
    assert load_config("tiny", ["train.lr=1"]).train.lr == 1.0


@pytest.mark.parametrize("option, value, said", [
    ("--epochs", str(2**70), f"--epochs must be at most 1000000 (as train.epochs), got {2**70}"),
    ("--lr", "1e308", "--lr must be at most 1 (as train.lr), got 1e+308"),
])
def test_finetune_refuses_epochs_and_rates_beyond_train_keys(tmp_path, monkeypatch, option, value, said):
    """``finetune --epochs 2**70`` trained for ever, ``--lr 1e308`` ended in torch's "value cannot be converted to type
    float without overflow" traceback at its first step: both are refused before the fine-tuning, naming the option."""
    import hsicam.engine.calibration as cal

    def reached(*args, **kwargs):
        raise AssertionError(f"the fine-tuning started with {option} {value}")

    monkeypatch.setattr(cal, "finetune", reached)
    out = tmp_path / "ft"
    res = run_cli_in_process("finetune", "--run", "pretrained:standard", "--psf-dir", str(tmp_path), "--out", str(out),
                             option, value)
    assert error_line(res) == f"hsicam: error: {said}"
    assert not out.exists()


def test_a_coded_aperture_closed_everywhere_is_refused():
    """``camera.cassi.mask_density=1e-300`` opened no cell of the random aperture (its uniform values are multiples of
    2^-32) and CASSI trained on an all-zero sensor, exit 0."""
    from hsicam.cameras.cassi import random_aperture

    assert float(random_aperture(256, 256, 0, 1e-300).sum()) == 0.0  # what the density did
    for d in ("1e-300", "0.0009"):
        with pytest.raises(ConfigError, match=rf"^camera.cassi.mask_density={d} leaves the coded aperture \(almost\) "
                                              r"closed: it must be at least 0.001 \(the fraction of open cells; 0.5 is "
                                              r"usual\)$"):
            load_config("tiny", ["camera.kind=dd_cassi", f"camera.cassi.mask_density={d}"])
    assert load_config("tiny", ["camera.kind=dd_cassi", "camera.cassi.mask_density=0.001"]).camera.cassi.mask_density == 1e-3
