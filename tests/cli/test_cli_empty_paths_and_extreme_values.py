"""Hostile command lines found by session 55's fuzzing that used to pass or to do something else than asked.

An empty path (``--dark "$DARK"`` with the variable unset) was taken as no option at all (``reconstruct --dark``
and ``--flat``: exit 0 without the correction) or as the current folder (``data show --out``: its PNGs written
there; ``finetune --psf-dir``: the folder's files read as PSF images) or as the default (``evaluate --data``:
the config's own validation scenes scored; ``experiment --out``: the whole experiment run into its default folder): every path argument refuses it now, as a
usage error naming the option, before any work and without writing anything."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process, tree_snapshot

EMPTY = "the path is empty (an unset variable?)"


@pytest.fixture
def files(tmp_path, monkeypatch) -> dict[str, Path]:
    """A capture and a cube in their real format (``.npy``) outside an empty working folder ``cwd`` (the one
    the commands run in)."""
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    rng = np.random.default_rng(0)
    np.save(inputs / "cap.npy", (rng.random((48, 48)) * 0.5).astype(np.float32))
    np.save(inputs / "cube.npy", rng.random((7, 24, 24)).astype(np.float32))
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    return {"cap": inputs / "cap.npy", "cube": inputs / "cube.npy", "cwd": cwd, "root": tmp_path}


@pytest.mark.parametrize("option", ["--dark", "--flat", "--psf-dir"])
def test_reconstruct_refuses_an_empty_correction_path(files, option):
    out = files["root"] / "est.h5"
    res = run_cli_in_process("reconstruct", option, "", str(files["cap"]), "--run", "pretrained:standard",
                             "--out", str(out))
    assert error_line(res) == f"hsicam: error: argument {option}: {EMPTY}"
    assert not out.exists() and not (files["root"] / "est_rgb.png").exists()


def test_data_show_refuses_an_empty_out_and_writes_nothing_in_the_working_folder(files):
    res = run_cli_in_process("data", "show", str(files["cube"]), "--out", "")
    assert error_line(res) == f"hsicam: error: argument --out: {EMPTY}"
    assert tree_snapshot(files["cwd"]) == {}


@pytest.mark.parametrize("argv", [
    ("finetune", "--psf-dir", "", "--run", "pretrained:standard", "--out", "RUN2"),
    ("evaluate", "--data", "", "--config", "tiny", "--method", "doe-box-demosaic", "--out", "EV"),
    ("simulate", "--scene", "", "--config", "tiny", "--out", "SIM"),
])
def test_every_path_option_refuses_an_empty_path_naming_it(files, cache_env, argv):
    (files["cwd"] / "psf_450nm.npy").write_bytes(b"")  # what an empty --psf-dir read as the current folder
    before = tree_snapshot(files["cwd"])
    res = run_cli_in_process(*argv)
    option = argv[argv.index("") - 1]
    assert error_line(res) == f"hsicam: error: argument {option}: {EMPTY}"
    assert tree_snapshot(files["cwd"]) == before


@pytest.mark.parametrize("setting,said", [
    ("camera.lens.focal_length_mm=1e300", r"the PSF sampling plan needs at least [\d.e+]+ PiB of memory"),
    ("camera.sensor.pixel_pitch_um=1e-300", r"the PSF sampling plan needs at least [\d.e+]+ PiB of memory"),
    ("camera.sensor_distance_mm=1e-300", r"camera.sensor_distance_mm=1e-300 is implausible for this lens .*"
                                         r"no pupil oversampling can represent a defocus this large"),
    ("camera.doe.max_height_nm=1e300", r"camera.doe.max_height_nm must be at most 1000000 nm .*got 1e\+300"),
    ("camera.doe.init_range_nm=1e300", r"camera.doe.init_range_nm must be at most 1000000 nm .*got 1e\+300"),
])
def test_absurd_optics_are_one_error_line(tmp_path, setting, said):
    """Optics values far out of range are refused in one line naming the problem. Before, the memory refusal's own
    message overflowed (a 1e300 mm lens: 'integer division result too large for a float'), a sensor at 1e-300 mm
    overflowed the defocus check (int of infinity), and 1e300 nm heights overflowed float32 in torch (a
    RuntimeError, or NaN PSFs and a ValueError in their plot): all tracebacks."""
    import re

    out = tmp_path / "psf"
    res = run_cli_in_process("psf", "--config", "tiny", "--set", setting, "--out", str(out))
    line = error_line(res)
    assert res.returncode != 0 and re.fullmatch(rf"hsicam: error: {said}.*", line), line
    assert "Traceback" not in res.stderr and not out.exists()


def test_a_float64_capture_beyond_float32_is_one_line_naming_it(files):
    """A float64 capture holding values float32 cannot (1e300) is refused for what it is. Before, numpy's overflow
    warning (2 lines) came first, then "the corrections produced NaN or Inf values", though no correction was asked."""
    cap = files["root"] / "huge.npy"
    values = np.full((48, 48), 0.25)
    values[:2, :3] = 1e300
    np.save(cap, values)
    out = files["root"] / "est.h5"
    res = run_cli_in_process("reconstruct", str(cap), "--run", "pretrained:standard", "--out", str(out))
    assert error_line(res) == (f"hsicam: error: {cap}: 6 value(s) beyond float32's range (largest 1e+300); a capture "
                               "is processed in float32: scale it, or check the file")
    assert not out.exists()


def test_a_white_level_beyond_float32_is_refused_without_numpys_warning(files):
    """--white-level 1e39 on a [0, 1] capture: the refusal alone (error_line: one line), no RuntimeWarning before it."""
    out = files["root"] / "est.h5"
    res = run_cli_in_process("reconstruct", str(files["cap"]), "--white-level", "1e39", "--run", "pretrained:standard",
                             "--out", str(out))
    assert "--white-level 1e+39 is far above this float capture's values" in error_line(res)
    assert not out.exists()
