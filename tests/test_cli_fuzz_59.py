"""Hostile option values found by session 59's option-by-option fuzzing of the command line (fuzz10d).

A raw-capture gain or level far out of range was refused in one line that told the user to change an option
they had not given: ``reconstruct --auto-level 1e308`` (a gain past float32) said "lower --scale", and
``--white-level 1e308`` (the image divided below float32's smallest numbers) said "the exposure × auto-level ×
--scale factor 1 … raise --scale". The line now names the option that did it."""

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


@pytest.mark.parametrize("options, said, remedy", [
    (("--auto-level", "1e308"), "factor inf exceeds float32", "lower --auto-level"),
    (("--exposure-s", "1e-300", "--reference-exposure-s", "1e300"), "factor inf exceeds float32",
     "lower --reference-exposure-s / --exposure-s"),
    (("--auto-level", "1e-300"), "takes the image below float32's smallest numbers", "raise --auto-level"),
    (("--white-level", "1e308"), "the white level 1e+308 DN (--white-level) takes the image below float32's "
                                 "smallest numbers (its brightest pixel becomes 0)", "as --white-level"),
])
def test_a_level_out_of_float32_names_the_option_that_set_it(capture, tmp_path, options, said, remedy):
    before = tree_snapshot(tmp_path)
    res = run_cli_in_process("reconstruct", str(capture), "--run", "pretrained:standard", "--out",
                             str(tmp_path / "est.h5"), *options)
    line = error_line(res)
    assert said in line and remedy in line, line
    assert "--scale" not in line.split(";")[-1], line  # no --scale was given: not the remedy
    assert tree_snapshot(tmp_path) == before
