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


#: :func:`hsicam.cli.args.text_arg`'s refusal.
EMPTY = "the value is empty (an unset variable?)"


@pytest.mark.parametrize("value", ["", "  "])
def test_data_synth_refuses_empty_holdout_sources(tmp_path, cache_env, value):
    """``--holdout-sources ""`` (an unset variable) generated a set with no held-out source at all (exit 0, 'held-out
    sources: none'), where the config holds some out and 'none' is the documented way to ask for that."""
    out = tmp_path / "DS"
    res = run_cli_in_process("data", "synth", "--config", "tiny", "--n", "1", "--size", "32", "--out", str(out),
                             "--holdout-sources", value, "--no-progress")
    assert error_line(res) == f"hsicam: error: argument --holdout-sources: {EMPTY}"
    assert not out.exists()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, cache_env) -> Path:
    """A finished tiny run (one epoch), as `pretrained pack` takes it."""
    run = tmp_path_factory.mktemp("runs") / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1")
    assert res.returncode == 0, res.stderr
    return run


@pytest.mark.slow  # the run's training: about 5 s
@pytest.mark.parametrize("option", ["--summary", "--preset"])
def test_pretrained_pack_refuses_an_empty_summary_or_preset(finished_run, tmp_path, option):
    """``pretrained pack --preset ""`` was taken as no --preset (the preset guessed from the config) and
    ``--summary ""`` wrote a card whose summary is empty (the `hsicam pretrained` line then starts with ': |'); both
    exit 0."""
    dest = tmp_path / "packs"
    res = run_cli_in_process("pretrained", "pack", str(finished_run), "--name", "mine", "--dest", str(dest), option, "")
    assert error_line(res) == f"hsicam: error: argument {option}: {EMPTY}"
    assert not dest.exists()
