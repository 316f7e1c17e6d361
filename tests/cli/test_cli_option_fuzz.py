"""Hostile option values found by session 59's option-by-option fuzzing of the command line (fuzz10d, fuzz11a).

A raw-capture gain or level far out of range was refused in one line that told the user to change an option
they had not given: ``reconstruct --auto-level 1e308`` (a gain past float32) said "lower --scale", and
``--white-level 1e308`` (the image divided below float32's smallest numbers) said "the exposure × auto-level ×
--scale factor 1 … raise --scale". The line now names the option that did it.

``reconstruct --full-well-e 1000 --read-noise-e 1e308`` (and ``--full-well-e 1e-300 --read-noise-e 2``) ended in an
OverflowError traceback of the noise variance (r/E)², after the run was loaded and the network had run; ``--full-well-e
1e-300`` alone reconstructed (exit 0) with an infinite noise variance. ``tolerance --shift-subsamples 1000000000000``
(or 2**70) never came back: the FFT length of its pupil was searched by trying n, n + 1, … for a 7-smooth number,
in the very check that refuses that pupil for its memory (the FFT length itself: tests/optics/test_optics_psf.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process, tree_snapshot
from hang_guard import guarded


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


@pytest.mark.parametrize("q", [str(10**12), str(2**70)])
def test_tolerance_refuses_a_huge_shift_subsampling_at_once(tmp_path, q):
    """The memory check refuses such a pupil in one line naming the option; it used to search its FFT length for
    hours first."""
    data = tmp_path / "scene.npy"
    np.save(data, np.random.default_rng(0).random((7, 32, 32)).astype(np.float32))
    out = tmp_path / "tol"
    res = guarded(run_cli_in_process, "tolerance", "--run", "pretrained:standard", "--out", str(out), "--data",
                  str(data), "--shift-cells", "0.5", "--shift-subsamples", q, "--sigma-height-nm", "0", "--levels", "2",
                  "--sensor-distance-um", "0")
    line = error_line(res)
    assert line.startswith(f"hsicam: error: --shift-subsamples {q}: the misalignment study's pupil of {q} samples per "
                           "DOE cell cannot be simulated here (the PSF sampling plan needs at least "), line
    assert not out.exists()
