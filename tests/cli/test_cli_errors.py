"""One error boundary: every writing command, given an output path that cannot work (an existing
file, a path inside a file, an unwritable folder) or a corrupt JSON/YAML input, answers one line
``hsicam: error: …`` with exit code 2, no traceback, and leaves nothing behind.

Most cases call :func:`hsicam.cli.main` in-process (the same boundary the console script runs,
without a Python start-up per case); the unwritable-folder cases and a sample of the others run
the real console script in a subprocess.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_helpers import (HSICAM, assert_clean_error, cli_env, module_cache, run_cli, run_cli_in_process,
                         unprivileged_prefix)
from hsicam.cli import main
from hsicam.data.formats import write_cube_h5
from hsicam.errors import ConfigError, HsicamError, InputError
from hsicam.spectral import Bands


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, env):
    """A trained tiny run, a scene, a capture and a small dataset folder."""
    d = tmp_path_factory.mktemp("inputs")
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(d / "run"), "--set", "train.epochs=1", env=env)
    assert res.returncode == 0, res.stderr
    rng = np.random.default_rng(0)
    np.save(d / "scene.npy", rng.uniform(0.1, 1, (7, 40, 40)).astype(np.float32))
    np.save(d / "cap.npy", rng.uniform(0.1, 1, (24, 24)).astype(np.float32))
    write_cube_h5(d / "data" / "a.h5", rng.uniform(0.1, 1, (7, 24, 24)).astype(np.float32), Bands.uniform(420, 720, 50))
    return d


def commands(i: Path, out: Path) -> dict[str, list[str]]:
    """Every writing command, writing to ``out`` (a folder; ``reconstruct``: ``out/r.h5``)."""
    run = str(i / "run")
    return {
        "psf": ["psf", "--config", "tiny", "--out", str(out)],
        "simulate": ["simulate", "--config", "tiny", "--scene", str(i / "scene.npy"), "--out", str(out)],
        "evaluate": ["evaluate", "--run", run, "--out", str(out)],
        "data synth": ["data", "synth", "--config", "tiny", "--n", "1", "--size", "16", "--out", str(out)],
        "data show": ["data", "show", str(i / "data"), "--out", str(out)],
        "train": ["train", "--config", "tiny", "--out", str(out)],
        "reconstruct": ["reconstruct", str(i / "cap.npy"), "--run", run, "--out", str(out / "r.h5")],
        "export-optics": ["export-optics", "--run", run, "--out", str(out)],
        "experiment": ["experiment", "ablation", "--scale", "tiny", "--out", str(out)],
        "tolerance": ["tolerance", "--run", run, "--out", str(out)],
        "finetune": ["finetune", "--run", run, "--psf-dir", str(i / "nope"), "--out", str(out)],
        "baseline train-prior": ["baseline", "train-prior", "--config", "tiny", "--out", str(out)],
    }


def call(capsys, args: list[str]) -> tuple[int, str]:
    code = main(args)
    err = capsys.readouterr().err
    return code, err


def assert_one_line(code: int, err: str, *fragments: str) -> None:
    assert code == 2, (code, err)
    lines = [x for x in err.strip().splitlines() if x.startswith("hsicam:") or "Traceback" in x or "Error" in x]
    assert len(lines) == 1 and lines[0].startswith("hsicam: error:"), err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


def snapshot(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


@pytest.mark.parametrize("case", ["existing file", "inside a file"])
def test_every_writing_command_refuses_a_bad_output_path(inputs, tmp_path, capsys, case):
    inputs_before = snapshot(inputs)
    f = tmp_path / "taken"
    f.write_text("user data")
    out = f if case == "existing file" else f / "sub"
    for name, args in commands(inputs, out).items():
        before = snapshot(tmp_path)
        code, err = call(capsys, args)
        expected = "which is a file" if (case == "inside a file" or name == "reconstruct") else "existing file"
        assert_one_line(code, err, str(f), expected)
        assert snapshot(tmp_path) == before, name  # nothing left behind
        assert f.read_text() == "user data"
    assert snapshot(inputs) == inputs_before


def test_reconstruct_out_naming_a_folder(inputs, tmp_path, capsys):
    (tmp_path / "r.h5").mkdir()
    code, err = call(capsys, ["reconstruct", str(inputs / "cap.npy"), "--run", str(inputs / "run"), "--out", str(tmp_path / "r.h5")])
    assert_one_line(code, err, "existing folder")
    assert snapshot(tmp_path) == ["r.h5"]


def test_report_output_problems(inputs, tmp_path, capsys, env):
    ev = tmp_path / "ev"
    code, err = call(capsys, ["evaluate", "--run", str(inputs / "run"), "--out", str(ev)])
    assert code == 0, err
    (ev / "report").write_text("x")  # the report folder's place is taken by a file
    assert_one_line(*call(capsys, ["report", str(ev)]), "existing file")
    (ev / "report").unlink()
    assert snapshot(ev) == sorted([".complete", "results.csv", "results.json", "results.md"])
    # a file given for the folder is named as a file (it was "no such folder"), with the folder to give
    code, err = call(capsys, ["report", str(ev / "results.json")])
    assert_one_line(code, err, f"{ev / 'results.json'}: a file, not a folder", f"e.g. {ev})")


# In the child: {name: [args]} -> {name: [exit code, stderr]} of hsicam.cli.main, one command after another.
EACH_IN_PROCESS = """
import contextlib, io, json, logging, sys
from hsicam.cli import main
out = {}
for name, args in json.loads(sys.argv[1]).items():
    logging.root.handlers.clear()  # main's logging.basicConfig then writes log lines to this command's stderr
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(args)
        except SystemExit as exc:
            code = exc.code
    out[name] = [code, err.getvalue()]
print(json.dumps(out))
"""


def test_every_writing_command_refuses_an_unwritable_folder(inputs, tmp_path, env):
    prefix = unprivileged_prefix()
    if prefix is None:
        pytest.skip("running as root without setpriv: chmod cannot make a folder unwritable here")
    ro = tmp_path / "ro"
    ro.mkdir()
    ev = ro / "ev"  # for `report`: an evaluation folder in which report/ cannot be created
    assert run_cli_in_process("evaluate", "--run", str(inputs / "run"), "--out", str(ev), env=env).returncode == 0
    cmds = {**commands(inputs, ro / "out"), "report": ["report", str(ev)]}
    ro.chmod(0o500)
    ev.chmod(0o500)
    try:
        # the console script itself for one command; the others in one unprivileged child calling
        # hsicam.cli.main per command (the same boundary, one interpreter start instead of one each)
        proc = subprocess.run([*prefix, str(HSICAM), *cmds.pop("psf")], capture_output=True, text=True, timeout=300,
                              env=cli_env(env))
        assert_clean_error(proc, "not writable")
        child = subprocess.run([*prefix, sys.executable, "-c", EACH_IN_PROCESS, json.dumps(cmds)], capture_output=True,
                               text=True, timeout=600, env=cli_env(env))
        assert child.returncode == 0, child.stderr
        results = json.loads(child.stdout.strip().splitlines()[-1])
        assert sorted(results) == sorted(cmds)
        for name, (code, err) in results.items():
            assert_clean_error(subprocess.CompletedProcess(cmds[name], code, "", err), "not writable")
    finally:
        ev.chmod(0o700)
        ro.chmod(0o700)
    assert snapshot(ro) == sorted(["ev", *[f"ev/{n}" for n in (".complete", "results.csv", "results.json", "results.md")]])


def test_corrupt_config_and_json_inputs(inputs, tmp_path, capsys, env):
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("camera: [unclosed\n")
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing\n")
    for cfg, fragment in ((bad_yaml, "invalid YAML"), (empty, "empty config")):
        for name, args in commands(inputs, tmp_path / "o").items():
            if "--config" not in args:
                continue
            args = [*args]
            args[args.index("--config") + 1] = str(cfg)
            code, err = call(capsys, args)
            assert_one_line(code, err, str(cfg), fragment)
            assert not (tmp_path / "o").exists(), name
    # a run whose config.yaml is corrupt: every command reading the run
    run = tmp_path / "run"
    shutil.copytree(inputs / "run", run)
    (run / "config.yaml").write_text("train: {epochs: [\n")
    for name, args in commands(inputs, tmp_path / "o").items():
        if "--run" not in args:
            continue
        args = [str(run) if a == str(inputs / "run") else a for a in args]
        code, err = call(capsys, args)
        assert_one_line(code, err, "config.yaml")
        assert not (tmp_path / "o").exists(), name
    assert_one_line(*call(capsys, ["train", "--out", str(run), "--resume"]), "config.yaml")
    # corrupt results.json / experiment.json given to report: one line, no report/ left
    for k, (fname, text) in enumerate((("results.json", "{\"scenes\": [1, "), ("results.json", "{\"scenes\": []}"),
                        ("results.json", "[]"), ("experiment.json", "{\"experiment\": \"noise\"}"),
                        ("results.json", "\xff\xfe"))):
        d = tmp_path / f"rep-{k}"
        d.mkdir()
        (d / fname).write_bytes(text.encode("latin-1"))
        (d / ".complete").write_text("{\"complete\": true}")
        assert_one_line(*call(capsys, ["report", str(d)]), fname, "corrupt")
        assert not (d / "report").exists() and not [p for p in d.iterdir() if p.name.startswith(".report")]
    # a tolerance file that is not JSON: export-optics names it and writes nothing
    tol = tmp_path / "tolerance.json"
    tol.write_text("{not json")
    assert_one_line(*call(capsys, ["export-optics", "--run", str(inputs / "run"), "--out", str(tmp_path / "fab"),
                                   "--tolerance", str(tol)]), str(tol))
    assert not (tmp_path / "fab").exists()
    # the real console script, once: no traceback, one line
    assert_clean_error(run_cli("psf", "--config", str(bad_yaml), "--out", str(tmp_path / "o"), env=env), "invalid YAML")


def test_export_refuses_nan_weights_naming_the_file(inputs, tmp_path, capsys):
    import torch
    from safetensors.torch import load_file, save_file
    from safetensors import safe_open

    run = tmp_path / "run"
    shutil.copytree(inputs / "run", run)
    for w in run.rglob("model.safetensors"):  # the root file and the checkpoints it is derived from
        with safe_open(str(w), framework="pt") as fh:
            meta = fh.metadata()
        t = load_file(str(w))
        key = next(k for k in t if k.endswith("height_m"))
        t[key] = torch.full_like(t[key], float("nan"))
        save_file(t, str(w), metadata=meta)
    man = json.loads((run / "checkpoints.json").read_text())
    from hsicam.io import file_sha256

    for tag in ("last", "best"):  # keep the manifest consistent with the edited files
        if man[tag]:
            man[tag]["weights_sha256"] = file_sha256(run / man[tag]["dir"] / "model.safetensors")
    man["weights"]["sha256"] = (man["best"] or man["last"])["weights_sha256"]
    (run / "checkpoints.json").write_text(json.dumps(man))
    code, err = call(capsys, ["export-optics", "--run", str(run), "--out", str(tmp_path / "fab")])
    assert_one_line(code, err, "model.safetensors", "NaN", "height_m")
    assert not (tmp_path / "fab").exists() and not list(tmp_path.glob(".fab*"))
    # every reader of the run refuses the same way, naming the weights, not its output (psf wrote an
    # all-NaN PSF stack with exit 0; reconstruct blamed the cube it was about to write)
    for args in (["psf", "--run", str(run), "--out", str(tmp_path / "psf")],
                 ["reconstruct", str(inputs / "cap.npy"), "--run", str(run), "--out", str(tmp_path / "r.h5")],
                 ["evaluate", "--run", str(run), "--out", str(tmp_path / "ev")]):
        code, err = call(capsys, args)
        assert_one_line(code, err, "model.safetensors", "NaN", "height_m", "diverged")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_readers_refuse_an_empty_run_config(inputs, tmp_path, capsys):
    """A run whose config.yaml lost its settings: one line naming the file, never the built-in paper
    camera (whose band grid the weights then did not fit: the error named the weights instead)."""
    run = tmp_path / "run"
    shutil.copytree(inputs / "run", run)
    (run / "config.yaml").write_text("# nothing\n")
    for args in (["psf", "--run", str(run), "--out", str(tmp_path / "psf")],
                 ["reconstruct", str(inputs / "cap.npy"), "--run", str(run), "--out", str(tmp_path / "r.h5")],
                 ["export-optics", "--run", str(run), "--out", str(tmp_path / "fab")],
                 ["evaluate", "--run", str(run), "--out", str(tmp_path / "ev")]):
        code, err = call(capsys, args)
        assert_one_line(code, err, str(run / "config.yaml"), "empty config")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_evaluate_data_through_a_symlink_loop(inputs, tmp_path, capsys):
    (tmp_path / "loop2").symlink_to("loop1")
    (tmp_path / "loop1").symlink_to("loop2")
    for data in (tmp_path / "loop1", tmp_path / "loop1" / "scenes"):
        code, err = call(capsys, ["evaluate", "--run", str(inputs / "run"), "--out", str(tmp_path / "ev"),
                                  "--data", str(data)])
        assert_one_line(code, err, str(tmp_path / "loop1"), "symbolic link loop")
    assert not (tmp_path / "ev").exists()


def test_restart_names_the_entry_it_cannot_remove(inputs, tmp_path, env):
    prefix = unprivileged_prefix()
    if prefix is None:
        pytest.skip("running as root without setpriv: chmod cannot make a folder unwritable here")
    run = tmp_path / "run"
    (run / "checkpoints" / "sub").mkdir(parents=True)
    (run / "checkpoints" / "sub" / "f").write_text("x")
    (run / "config.yaml").write_text((inputs / "run" / "config.yaml").read_text())
    (run / "checkpoints" / "sub").chmod(0o500)
    try:
        proc = subprocess.run([*prefix, str(HSICAM), "train", "--config", "tiny", "--out", "run", "--restart"],
                              capture_output=True, text=True, timeout=300, env=cli_env(env), cwd=tmp_path)
    finally:
        (run / "checkpoints" / "sub").chmod(0o700)
    assert_clean_error(proc, "run/checkpoints/sub/f: cannot be removed for --restart", "Permission denied",
                       "check its permissions")


def test_demo_refuses_a_run_trained_with_other_settings(inputs, tmp_path, capsys):
    """`hsicam demo --out DIR` whose DIR/run was trained with other settings: one line naming the
    difference; the run is neither reused for the table nor retrained."""
    out = tmp_path / "demo"
    shutil.copytree(inputs / "run", out / "run")
    before = snapshot(out)
    code = main(["demo", "--config", "tiny", "--out", str(out), "--set", "train.lr=0.0123"])
    captured = capsys.readouterr()
    assert_one_line(code, captured.err, "trained with another config", "→", "delete it")
    assert "reusing" not in captured.out and "training" not in captured.out, captured.out  # nothing announced
    assert snapshot(out) == before and not (out / "results.json").exists()


def test_a_users_own_folder_is_refused_before_the_work(inputs, tmp_path, capsys, monkeypatch):
    """psf, simulate, evaluate and tolerance write their folder whole; a non-empty folder that is not
    a completed hsicam output is refused before any scene is imaged or scored, and stays untouched."""
    import hsicam.engine.evaluate as ev
    import hsicam.engine.tolerance as tol

    def no_work(*a, **k):  # any scoring would be work done before the refusal
        raise AssertionError("work started before the output folder was checked")

    monkeypatch.setattr(ev, "evaluate_method", no_work)
    monkeypatch.setattr(tol, "evaluation_scenes", no_work)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("user data")
    for name in ("psf", "simulate", "evaluate", "tolerance"):
        code, err = call(capsys, commands(inputs, out)[name])
        assert_one_line(code, err, str(out), "not empty")
        assert snapshot(tmp_path) == ["mine", "mine/notes.txt"], name
    assert (out / "notes.txt").read_text() == "user data"


@pytest.mark.parametrize("device, fragment", [("cuda", "no CUDA device"), ("cuda:7", "no CUDA device"),
                                              ("banana", "unknown device"), ("meta", "cpu, cuda or mps")])
def test_a_device_this_machine_lacks_is_a_usage_error(inputs, tmp_path, capsys, device, fragment):
    import torch

    if torch.cuda.is_available() and device.startswith("cuda"):
        pytest.skip("this machine has CUDA")
    run = str(inputs / "run")
    for args in (["evaluate", "--run", run, "--method", "doe-box-demosaic"], ["tolerance", "--run", run],
                 ["reconstruct", str(inputs / "cap.npy"), "--run", run]):
        out = tmp_path / "o.h5" if args[0] == "reconstruct" else tmp_path / "o"
        with pytest.raises(SystemExit) as exc:
            main([*args, "--out", str(out), "--device", device])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1 and fragment in err and "--device" in err, err
        assert not out.exists()


def test_evaluate_refuses_settings_a_trained_run_would_ignore(inputs, tmp_path, capsys):
    """camera, band and network keys cannot change a trained run: refused (they used to be recorded
    in the results' config hash though nothing changed); capture and inference keys still apply."""
    run = str(inputs / "run")
    # the pixel pitch too (probe 22: it was accepted and hashed, but the run's camera kept its own)
    for kv in ("camera.cfa.period=4", "bands.step_nm=100", "model.rdn.features=16", "camera.aperture_radius_mm=0.3",
               "camera.sensor.pixel_pitch_um=3"):
        code, err = call(capsys, ["evaluate", "--run", run, "--out", str(tmp_path / "o"), "--set", kv])
        assert_one_line(code, err, f"--set {kv.split('=')[0]}", "fixed by its training")
        assert not (tmp_path / "o").exists()
    # a key no config has is said as such (it was "fixed by its training" too), whatever its section
    for kv in ("bogus=1", "camera.no_such_key=2", "model.consistency.nope=3"):
        code, err = call(capsys, ["evaluate", "--run", run, "--out", str(tmp_path / "o"), "--set", kv])
        assert_one_line(code, err, f"unknown config key '{kv.split('=')[0]}'")
        assert "fixed by its training" not in err and not (tmp_path / "o").exists()
    code, err = call(capsys, ["evaluate", "--run", run, "--out", str(tmp_path / "ok"), "--set", "camera.boundary=same",
                              "--set", "model.consistency.iterations=1", "--set", "camera.sensor.noise=gaussian"])
    assert code == 0, err
    # the capture noise it was scored with is recorded beside the test noise
    assert json.loads((tmp_path / "ok" / "results.json").read_text())["noise"]["camera_sensor"] == {
        "noise": "gaussian", "sigma": 0.0, "full_well_e": 10000.0, "read_noise_e": 2.0, "bit_depth": None}
    hashes = json.loads((tmp_path / "ok" / "results.json").read_text())["config_hash"]
    code, err = call(capsys, ["evaluate", "--run", run, "--out", str(tmp_path / "ok2"), "--set", "camera.boundary=same"])
    assert code == 0 and json.loads((tmp_path / "ok2" / "results.json").read_text())["config_hash"] != hashes


def test_tolerance_refuses_impossible_sweeps_before_scoring(inputs, tmp_path, capsys, monkeypatch):
    import hsicam.engine.tolerance as tol

    monkeypatch.setattr(tol, "evaluation_scenes", lambda *a, **k: (_ for _ in ()).throw(AssertionError("scored")))
    run = str(inputs / "run")
    code, err = call(capsys, ["tolerance", "--run", run, "--out", str(tmp_path / "t"), "--sensor-distance-um=-1e9"])
    assert_one_line(code, err, "behind the lens")
    code, err = call(capsys, ["tolerance", "--run", run, "--out", str(tmp_path / "t"), "--shift-cells", "1e6"])
    assert_one_line(code, err, "exceeds the aperture")
    # a shift between the study's sub-samples was rounded while the table showed it as asked (probe 23)
    code, err = call(capsys, ["tolerance", "--run", run, "--out", str(tmp_path / "t"), "--shift-cells", "0.1",
                              "--shift-subsamples", "4"])
    assert_one_line(code, err, "--shift-cells 0.1: the misalignment study moves the relief by whole sub-samples of "
                               "1/4 cell, so 0.1 would be applied as 0; give multiples of 0.25")
    assert not (tmp_path / "t").exists()


def test_absurd_doe_cell_sizes_and_consistency_steps_are_one_line_errors(inputs, tmp_path, capsys):
    code, err = call(capsys, ["psf", "--config", "tiny", "--set", "camera.doe.cell_size_um=1e-9", "--out", str(tmp_path / "p")])
    assert_one_line(code, err, "cells across", "camera.doe.cell_size_um")
    code, err = call(capsys, ["reconstruct", str(inputs / "cap.npy"), "--run", str(inputs / "run"), "--out",
                              str(tmp_path / "r.h5"), "--consistency-steps", "1000000"])
    assert_one_line(code, err, "--consistency-steps must be")
    assert not (tmp_path / "p").exists() and not (tmp_path / "r.h5").exists()


def test_a_capture_smaller_than_a_cfa_period_and_an_all_zero_cube_are_named(inputs, tmp_path, capsys):
    from hsicam.config import load_config

    period = load_config(inputs / "run" / "config.yaml").camera.cfa.period
    for shape in ((period - 1, 40), (1, 500)):
        np.save(tmp_path / "small.npy", np.random.default_rng(0).random(shape).astype(np.float32))
        code, err = call(capsys, ["reconstruct", str(tmp_path / "small.npy"), "--run", str(inputs / "run"), "--out",
                                  str(tmp_path / "r.h5")])
        assert_one_line(code, err, str(tmp_path / "small.npy"), "smaller than one CFA period")
        assert not (tmp_path / "r.h5").exists()
    write_cube_h5(tmp_path / "zero" / "z.h5", np.zeros((7, 16, 16), np.float32), Bands.uniform(420, 720, 50))
    code, err = call(capsys, ["data", "show", str(tmp_path / "zero"), "--out", str(tmp_path / "show")])
    assert_one_line(code, err, str(tmp_path / "zero" / "z.h5"), "all zeros")
    assert not (tmp_path / "show").exists()


def write_cube_with_a_corrupt_chunk(path: Path, bands: Bands) -> None:
    """An hsicam cube file whose header is sound (it passes the start-up probe) but whose pixel data
    (one gzip chunk) is not: the damage shows only when patches are read from it."""
    import h5py

    from hsicam.data.formats import HSICAM_FORMAT, HSICAM_FORMAT_VERSION

    cube = np.random.default_rng(1).uniform(0.1, 1, (len(bands), 40, 40)).astype(np.float32)
    with h5py.File(path, "w") as f:
        f.create_dataset("cube", data=cube, chunks=cube.shape, compression="gzip")
        f.create_dataset("bands_nm", data=np.asarray(bands.centers_nm, np.float64))
        f.attrs.update(format=HSICAM_FORMAT, version=HSICAM_FORMAT_VERSION, max_value=float(cube.max()))
    with h5py.File(path, "r") as f:
        chunk = f["cube"].id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    raw[chunk.byte_offset + 8:chunk.byte_offset + chunk.size - 8] = bytes(chunk.size - 16)
    path.write_bytes(bytes(raw))


def test_a_corrupt_chunk_is_one_line_before_training_starts(env, tmp_path):
    """A file whose header is sound but one of whose pixel chunks is damaged: read window by window
    (``data.preload=false``), it is now checked whole when first probed (probe 31 #05), so the error
    comes from the main process before any step, one line naming the file (``-v``: the traceback)."""
    data = tmp_path / "data"
    data.mkdir()
    write_cube_with_a_corrupt_chunk(data / "b.h5", Bands.uniform(420, 720, 50))
    args = ["train", "--config", "tiny", "--set", f"data.root={data}", "--set", "data.preload=false",
            "--set", "data.num_workers=1", "--set", "data.val_fraction=0", "--set", "train.epochs=1"]
    proc = run_cli_in_process(*args, "--out", str(tmp_path / "run"), env=env)
    assert_clean_error(proc, str(data / "b.h5"), "corrupt")
    assert "DataLoader worker" not in proc.stderr
    verbose = run_cli_in_process("-v", *args, "--out", str(tmp_path / "run2"), env=env)
    assert verbose.returncode == 2 and "Traceback" in verbose.stderr, verbose.stderr
    assert verbose.stderr.strip().splitlines()[-1] == proc.stderr.strip().splitlines()[-1], verbose.stderr


class _FailingInWorker(torch.utils.data.Dataset):
    """Raises an InputError naming a file in whatever process reads item 0."""

    def __len__(self) -> int:
        return 2

    def __getitem__(self, i: int):
        from hsicam.errors import InputError

        raise InputError("/data/b.h5: the file's pixel data are corrupt (HDF5 could not read them)")


def test_an_error_in_a_dataloader_worker_is_the_workers_one_line():
    """torch re-raises a worker's exception in the main process with its message replaced by the
    worker's traceback; the user sees the worker's own line (the real DataLoader, one worker)."""
    from hsicam.cli import error_line

    loader = torch.utils.data.DataLoader(_FailingInWorker(), batch_size=1, num_workers=1)
    with pytest.raises(Exception) as exc:
        next(iter(loader))
    assert "Original Traceback" in str(exc.value)  # torch's wrapping
    assert error_line(exc.value) == "/data/b.h5: the file's pixel data are corrupt (HDF5 could not read them)"


def usage_error(capsys, args: list[str]) -> str:
    """The one line of an argparse usage error (exit code 2) of ``hsicam ARGS``, in-process."""
    with pytest.raises(SystemExit) as exc:
        main(args)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and err.startswith("hsicam: error: "), err
    return err


def test_a_patch_smaller_than_the_ssim_window_is_refused_before_a_run_folder_exists(env, tmp_path, capsys):
    """data.patch_px below SSIM's window crashed after the first epoch (the validation SSIM) and left a
    run folder neither --resume nor --restart recovered: the config refuses it; at the window it trains,
    train.ssim_loss included (the same SSIM)."""
    from hsicam.metrics import SSIM_WINDOW_PX

    run = tmp_path / "run"
    proc = run_cli_in_process("train", "--config", "tiny", "--set", "data.patch_px=3", "--out", str(run), env=env)
    assert_clean_error(proc, f"data.patch_px must be >= {SSIM_WINDOW_PX} px", "SSIM", "got 3")
    for n in (1, SSIM_WINDOW_PX - 1):
        code, err = call(capsys, ["train", "--config", "tiny", "--set", f"data.patch_px={n}", "--set",
                                  "train.ssim_loss=0.5", "--out", str(run)])
        assert_one_line(code, err, f"data.patch_px must be >= {SSIM_WINDOW_PX} px", f"got {n}")
    assert not run.exists()
    code, err = call(capsys, ["train", "--config", "tiny", "--set", f"data.patch_px={SSIM_WINDOW_PX}", "--set",
                              "train.ssim_loss=0.5", "--set", "train.epochs=1", "--out", str(run)])
    assert code == 0, err
    assert any("val_ssim" in json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines())


def test_seeds_outside_what_their_generator_takes_are_one_line_errors(inputs, env, tmp_path, capsys):
    """Every seed, of the config or of a --seed option, is one clear error outside [0, 2^32 - 1], where distinct
    seeds give distinct draws (tolerance seeds its height-noise draws with seed·1000 + draw, so its --seed stops
    1000 times lower), never a traceback."""
    from hsicam.cli import build_parser
    from hsicam.config import TOLERANCE_SEED_MAX

    out = tmp_path / "o"
    proc = run_cli_in_process("data", "synth", "--n", "1", "--size", "64", "--seed", "-1", "--out", str(out), env=env)
    assert_clean_error(proc, "argument --seed: must be an integer in [0, 2^32 - 1], got -1")
    huge = "99999999999999999999"
    for kv, fragment in (("data.synthetic_seed=-1", "data.synthetic_seed must be an integer in [0, 2^32 - 1], got -1"),
                         ("data.split_seed=-1", "data.split_seed must be an integer in [0, 2^32 - 1], got -1"),
                         ("train.seed=-1", "train.seed must be an integer in [0, 2^32 - 1], got -1"),
                         (f"camera.doe.seed={2**32}", f"camera.doe.seed must be an integer in [0, 2^32 - 1], got {2**32}"),
                         (f"train.seed={huge}", f"train.seed must be an integer in [0, 2^32 - 1], got {huge}")):
        assert_one_line(*call(capsys, ["train", "--config", "tiny", "--set", kv, "--out", str(out)]), fragment)
    scene, run = str(inputs / "scene.npy"), str(inputs / "run")
    err = usage_error(capsys, ["simulate", "--config", "tiny", "--scene", scene, "--out", str(out), "--seed", huge])
    assert f"argument --seed: must be an integer in [0, 2^32 - 1], got {huge}" in err
    for bad in ("-3", str(TOLERANCE_SEED_MAX + 1)):
        err = usage_error(capsys, ["tolerance", "--run", run, "--out", str(out), "--seed", bad])
        assert f"argument --seed: must be an integer in [0, {TOLERANCE_SEED_MAX}], got {bad}" in err
    err = usage_error(capsys, ["simulate", "--config", "tiny", "--scene", scene, "--out", str(out), "--seed", "1.5"])
    assert "argument --seed: must be an integer, got '1.5'" in err
    assert not out.exists()
    parser = build_parser()
    assert parser.parse_args(["tolerance", "--run", run, "--out", str(out), "--seed", str(TOLERANCE_SEED_MAX)]).seed \
        == TOLERANCE_SEED_MAX
    assert parser.parse_args(["data", "synth", "--seed", str(2**32 - 1)]).seed == 2**32 - 1
    code, err = call(capsys, ["simulate", "--config", "tiny", "--scene", scene, "--out", str(out), "--seed", "7"])
    assert code == 0 and json.loads((out / "simulate.json").read_text())["seed"] == 7, err


def test_tolerance_draw_seeds_stay_distinct_seeds():
    """Draw d of --seed S seeds torch with S·1000 + d: at the largest --seed and draw that is still below 2^32, so no
    two (seed, draw) pairs share a generator state."""
    from hsicam.config import SEED_MAX, TOLERANCE_DRAW_STRIDE, TOLERANCE_SEED_MAX
    from hsicam.engine.tolerance import ToleranceSpec
    from hsicam.errors import InputError

    assert TOLERANCE_SEED_MAX * TOLERANCE_DRAW_STRIDE + TOLERANCE_DRAW_STRIDE - 1 <= SEED_MAX
    assert (TOLERANCE_SEED_MAX + 1) * TOLERANCE_DRAW_STRIDE + TOLERANCE_DRAW_STRIDE - 1 > SEED_MAX
    ToleranceSpec(seed=TOLERANCE_SEED_MAX, height_draws=TOLERANCE_DRAW_STRIDE).check()
    for spec, what in ((ToleranceSpec(seed=TOLERANCE_SEED_MAX + 1), "ToleranceSpec.seed must be an integer in"),
                       (ToleranceSpec(seed=-1), "ToleranceSpec.seed must be an integer in"),
                       (ToleranceSpec(height_draws=TOLERANCE_DRAW_STRIDE + 1), "ToleranceSpec.height_draws must be at most")):
        with pytest.raises(InputError, match=re.escape(what)):
            spec.check()


def test_finetune_errors_name_its_own_options(inputs, tmp_path, capsys):
    """A non-empty --out that is no fine-tuned run says to choose another (no --resume there); --lr inf/nan is a
    usage error of --lr itself (it was reported as config key 'train.lr', "must be a number")."""
    run = str(inputs / "run")
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("user data")
    code, err = call(capsys, ["finetune", "--run", run, "--psf-dir", str(inputs / "nope"), "--out", str(out)])
    assert_one_line(code, err, str(out), "not empty", "fine-tuning writes a new run folder: choose another --out")
    assert "--resume" not in err and "--restart" not in err
    assert snapshot(tmp_path) == ["mine", "mine/notes.txt"]
    new = tmp_path / "new"
    for bad in ("inf", "nan", "-inf", "0", "-1e-4", "abc"):
        err = usage_error(capsys, ["finetune", "--run", run, "--psf-dir", str(inputs / "nope"), "--out", str(new),
                                   f"--lr={bad}"])
        assert f"argument --lr: must be a finite number > 0, got '{bad}'" in err and "train.lr" not in err
    code, err = call(capsys, ["finetune", "--run", run, "--psf-dir", str(inputs / "nope"), "--out", str(new),
                              "--set", "train.lr=inf"])
    assert_one_line(code, err, "config key 'train.lr' must be a finite number, got 'inf'")
    assert not new.exists()


def test_simulate_refuses_an_overflowing_scene_and_warns_of_an_unnormalised_one(inputs, env, tmp_path):
    """A scene of huge finite values gave exit 0 and an all-NaN sensor marked complete (with a numpy
    RuntimeWarning); one of 1e6 gave a sensor far past full scale without a word."""
    from hsicam.cameras.base import SCENE_PEAK_WARN

    cube = np.load(inputs / "scene.npy")
    cube[0, 0, 0] = 1.0
    np.save(tmp_path / "huge.npy", cube * np.float32(1e37))
    np.save(tmp_path / "bright.npy", cube * np.float32(1e6))
    out = tmp_path / "o"
    # a process of its own: numpy's RuntimeWarning would reach its stderr there (in-process, pytest takes it)
    proc = run_cli("simulate", "--config", "tiny", "--scene", str(tmp_path / "huge.npy"), "--out", str(out), env=env)
    assert_clean_error(proc, str(tmp_path / "huge.npy"), "not finite", "peak value is 1e+37", "[0, 1]")
    assert "RuntimeWarning" not in proc.stderr and not out.exists()
    proc = run_cli_in_process("simulate", "--config", "tiny", "--scene", str(tmp_path / "bright.npy"), "--out", str(out),
                              env=env)
    assert proc.returncode == 0 and f"{tmp_path / 'bright.npy'}: the scene's peak value is 1e+06" in proc.stderr
    assert "saturates" in proc.stderr and 1e6 > SCENE_PEAK_WARN
    proc = run_cli_in_process("simulate", "--config", "tiny", "--scene", str(inputs / "scene.npy"), "--out", str(out),
                              env=env)
    assert proc.returncode == 0 and "peak value" not in proc.stderr, proc.stderr


def test_train_prior_into_a_non_empty_folder_names_its_own_remedy(tmp_path):
    """`baseline train-prior` into a non-empty folder that holds no prior says to choose another
    folder (it used to offer options the command does not have; its --resume only continues a prior
    folder), before any data or training."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = run_cli_in_process("baseline", "train-prior", "--config", "tiny", "--out", str(out),
                             env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert_clean_error(res, "run folder exists and is not empty", "train-prior writes a new prior folder")
    assert "--resume" not in res.stderr and not (tmp_path / "cache").exists()
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_train_into_a_folder_of_other_files_offers_only_another_out(tmp_path):
    """A folder of the user's own files holds no run to --resume and nothing --restart may wipe: the
    refusal used to offer both (each then refused in turn); it names the files and another --out."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(out),
                             env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert_clean_error(res, f"{out}: run folder exists and is not empty: it holds other files than a run's (notes.txt); "
                            "nothing there is resumed or wiped: choose another --out")
    assert "--resume" not in res.stderr and "--restart" not in res.stderr
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_an_interruption_during_start_up_is_one_line(capsys, monkeypatch):
    """Ctrl-C while the commands' modules load (about a second) printed a KeyboardInterrupt
    traceback (probe 22); importing the command line no longer loads numpy or torch, and an
    interruption in build_parser is reported like one during a command."""
    import subprocess
    import sys

    import hsicam.cli as cli

    loaded = subprocess.run([sys.executable, "-c", "import sys, hsicam.cli; print(sorted({'numpy', 'torch'} & set(sys.modules)))"],
                            capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]"

    def interrupted(name):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.importlib, "import_module", interrupted)
    assert cli.main(["psf", "--out", "x"]) == 130
    assert capsys.readouterr().err == "hsicam: interrupted\n"


def test_an_interruption_while_the_options_are_read_is_one_line(monkeypatch, capsys, tmp_path):
    """`--run`'s type checks the run's weights, importing torch: a Ctrl-C in that second printed a traceback
    (probe of session 51); now the one line of an interruption anywhere else."""
    import hsicam.cli as cli

    def interrupted(spec):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "run_folder", interrupted)
    assert cli.main(["reconstruct", str(tmp_path / "c.npy"), "--run", "pretrained:standard",
                     "--out", str(tmp_path / "c.h5")]) == 130
    assert capsys.readouterr().err == "hsicam: interrupted\n"
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("command", ["evaluate", "reconstruct", "export-optics", "tolerance", "finetune", "pretrained pack"])
def test_a_demo_folder_as_the_run_names_the_run_inside_it(inputs, tmp_path, capsys, command):
    """`--run runs/demo` (the README's demo output, not a run): the one line names its run/ folder."""
    demo = tmp_path / "demo"
    demo.mkdir()
    shutil.copytree(inputs / "run", demo / "run")
    (demo / "results.json").write_text("{}")
    out = tmp_path / "out"
    if command == "pretrained pack":
        args = ["pretrained", "pack", str(demo), "--name", "mine", "--dest", str(out)]
    else:
        args = [a if a != str(inputs / "run") else str(demo) for a in commands(inputs, out)[command]]
    code, err = call(capsys, args)
    assert_one_line(code, err, f"{demo}: not a run folder (config.yaml is missing); it holds the run folder "
                               f"{demo / 'run'}: give that as the run")
    experiment = tmp_path / "exp"  # an experiment's folder: its runs are named
    for name in ("full", "no-doe"):
        shutil.copytree(inputs / "run", experiment / "runs" / name)
    args = [a if a != str(demo) else str(experiment) for a in args]
    code, err = call(capsys, args)
    assert_one_line(code, err, f"it holds the run folders {experiment / 'runs' / 'full'}, "
                               f"{experiment / 'runs' / 'no-doe'}: give one as the run")


def test_bad_inputs_found_by_session_31s_audit(inputs, tmp_path, capsys, recwarn):
    """A gain that overflows float32 is the one line without numpy's overflow warning before it; an
    HDF5 scene whose 'cube' is a group, and a scene path round a symbolic-link loop, are named as such."""
    import h5py

    code, err = call(capsys, ["reconstruct", str(inputs / "cap.npy"), "--run", str(inputs / "run"), "--out",
                              str(tmp_path / "r.h5"), "--scale", "1e39"])
    assert_one_line(code, err, "--scale factor 1e+39 exceeds float32", "lower --scale")
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in recwarn]
    # the other end (session 57): a gain below float32's smallest numbers left an all-zero image, reconstructed with
    # only a "very dark" warning, where an all-zero capture is refused
    code, err = call(capsys, ["reconstruct", str(inputs / "cap.npy"), "--run", str(inputs / "run"), "--out",
                              str(tmp_path / "r.h5"), "--scale", "1e-300"])
    assert_one_line(code, err, "--scale factor 1e-300 takes the image below float32's smallest numbers (its brightest "
                               "pixel becomes 0)", "raise --scale")
    assert not (tmp_path / "r.h5").exists()
    scene = tmp_path / "group.h5"
    with h5py.File(scene, "w") as f:
        f.create_group("cube")
        f["bands_nm"] = np.linspace(420, 720, 7)
    code, err = call(capsys, ["simulate", "--config", "tiny", "--scene", str(scene), "--out", str(tmp_path / "sim")])
    assert_one_line(code, err, str(scene), "'cube' is a group, not an array")
    (tmp_path / "loop2").symlink_to("loop1")
    (tmp_path / "loop1").symlink_to("loop2")
    code, err = call(capsys, ["simulate", "--config", "tiny", "--scene", str(tmp_path / "loop1"), "--out",
                              str(tmp_path / "sim")])
    assert_one_line(code, err, str(tmp_path / "loop1"), "symbolic link loop")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["group.h5", "loop1", "loop2"]


# ------------------------------------------------------------------------------------------------
# Session 37's hunt: lines that named the wrong thing
# ------------------------------------------------------------------------------------------------
@pytest.fixture
def small_capture(tmp_path) -> Path:
    path = tmp_path / "cap.npy"
    np.save(path, np.random.default_rng(0).uniform(0.1, 0.6, (48, 48)).astype(np.float32))
    return path


def test_a_run_given_as_a_file_and_a_folder_given_as_the_sensor_are_named_so(small_capture, tmp_path):
    from hsicam.runs.pretrained import root

    card = root() / "standard" / "config.yaml"
    res = run_cli_in_process("reconstruct", str(small_capture), "--run", str(card), "--out", str(tmp_path / "a.h5"))
    assert_one_line(res.returncode, res.stderr, f"{card}: a file, not a run folder (give the folder that holds "
                                                "config.yaml and model.safetensors)")
    res = run_cli_in_process("reconstruct", str(tmp_path), "--run", "pretrained:standard", "--out", str(tmp_path / "b.h5"))
    assert_one_line(res.returncode, res.stderr, f"{tmp_path}: a folder, not a sensor image (give one .npy, .png or .tif file)")
    assert not list(tmp_path.glob("[ab]*"))


@pytest.mark.parametrize("option, value, line", [
    ("--black-level", "nan", "black_level (--black-level) must be a finite number, got nan"),
    ("--auto-level", "-1", "auto_level (--auto-level) must be positive, got -1.0"),
    ("--black-level", "-3", "black_level (--black-level) must be >= 0, got -3.0"),
])
def test_a_bad_correction_names_its_option(small_capture, tmp_path, option, value, line):
    res = run_cli_in_process("reconstruct", str(small_capture), "--run", "pretrained:standard", "--out",
                             str(tmp_path / "c.h5"), option, value)
    assert_one_line(res.returncode, res.stderr, line)


def test_pretrained_show_and_copy_take_the_name_as_run_does(tmp_path, capsys):
    """`--run pretrained:standard` works everywhere; `pretrained show/copy pretrained:standard` was refused."""
    assert main(["pretrained", "show", "pretrained:standard"]) == 0
    assert capsys.readouterr().out.startswith("# Pre-trained camera `standard`")
    assert main(["pretrained", "copy", "pretrained:standard", str(tmp_path / "mine")]) == 0
    assert "copied pre-trained camera standard ->" in capsys.readouterr().out
    assert (tmp_path / "mine" / "model.safetensors").is_file()


def test_a_cube_stored_band_last_is_told_to_move_its_band_axis(tmp_path):
    import h5py

    from hsicam.data.formats import read_cube
    from hsicam.errors import InputError

    path = tmp_path / "hwb.h5"
    with h5py.File(path, "w") as f:
        f["cube"] = np.random.default_rng(0).random((40, 40, 31)).astype(np.float32)
        f["bands_nm"] = np.arange(420.0, 730.0, 10.0)
    with pytest.raises(InputError, match=r"the cube has 40 bands but the file lists 31 wavelengths \(its last axis has "
                                         r"31: the band axis must come first, \(bands, height, width\); transpose"):
        read_cube(path)


@pytest.mark.parametrize("kind", ["png", "npy", "tif"])
def test_a_two_level_image_is_no_capture(tmp_path, kind):
    """A 1-bit PNG was read as 0 and 1 of 255 DN and reconstructed behind a misleading "very dark" warning; a
    bool .npy was taken as it was (session 37's hunt)."""
    import tifffile
    from PIL import Image

    mask = np.random.default_rng(0).random((48, 48)) > 0.5
    path = tmp_path / f"mask.{kind}"
    if kind == "png":
        Image.fromarray(mask).convert("1").save(path)
    elif kind == "npy":
        np.save(path, mask)
    else:
        tifffile.imwrite(path, mask)
    res = run_cli_in_process("reconstruct", str(path), "--run", "pretrained:standard", "--out", str(tmp_path / "m.h5"))
    assert_one_line(res.returncode, res.stderr, f"{path}: a ", "holds two levels, not the values of a sensor image")
    assert not (tmp_path / "m.h5").exists()


# --- errors.py: a user's error is an HsicamError, the one line the CLI prints (moved from data/) ------------------
def test_input_error_is_an_hsicam_error():
    """The CLI prints HsicamError as one line; InputError is one."""
    assert issubclass(InputError, HsicamError)


def test_input_and_config_errors_are_hsicam_errors():
    assert issubclass(InputError, HsicamError) and issubclass(ConfigError, HsicamError)


def _wrapped_stop(stop: BaseException, chained: bool):
    """What a Ctrl-C inside a lazy import of torch looked like (Python 3.11): another error, the stop its cause (or only
    its context)."""
    def command(args):
        try:
            raise stop
        except BaseException as exc:
            if chained:
                raise RuntimeError("Error calling __set_name__ on 'Field' instance 'freevar_name'") from exc
            raise RuntimeError("Error calling __set_name__ on 'Field' instance 'freevar_name'")  # noqa: B904
    return command


@pytest.mark.parametrize("chained", [True, False])
@pytest.mark.parametrize("how", ["int", "term"])
def test_a_stop_that_an_import_wrapped_in_another_error_is_still_a_stop(monkeypatch, capsys, tmp_path, chained, how):
    """A Ctrl-C that arrived while torch imported its inductor was raised as "RuntimeError: Error calling __set_name__
    …" and printed a whole traceback, exit code 1 (a helper's interrupted `experiment compare`, session 71); now the
    one line of any other stop and its exit code (130, or 143 for SIGTERM); a RuntimeError of its own stays an error."""
    import hsicam.cli.camera as camera_cli
    from hsicam.cli import interrupt_behind, main
    from hsicam.errors import Terminated

    stop = KeyboardInterrupt() if how == "int" else Terminated()
    monkeypatch.setattr(camera_cli, "cmd_psf", _wrapped_stop(stop, chained))
    code = main(["psf", "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    if how == "int":
        assert (code, err) == (130, "hsicam: interrupted\n")
    else:
        assert (code, err) == (143, "hsicam: terminated (SIGTERM); nothing half-written was left\n")
    assert not (tmp_path / "p").exists()
    assert interrupt_behind(RuntimeError("its own")) is None
    loop = RuntimeError("a")
    loop.__context__ = ValueError("b")
    loop.__context__.__context__ = loop  # a cycle of contexts ends
    assert interrupt_behind(loop) is None


def test_a_wrapped_stop_while_the_options_are_read_is_one_line(monkeypatch, capsys, tmp_path):
    """The same while `--run`'s type imports torch (before the command runs)."""
    import hsicam.cli as cli

    def wrapped(spec):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise RuntimeError("Error calling __set_name__") from exc

    monkeypatch.setattr(cli, "run_folder", wrapped)
    assert cli.main(["reconstruct", str(tmp_path / "c.npy"), "--run", "pretrained:standard",
                     "--out", str(tmp_path / "c.h5")]) == 130
    assert capsys.readouterr().err == "hsicam: interrupted\n"


def test_the_clean_up_after_a_stop_does_not_import_torch(tmp_path):
    """A Ctrl-C in a command's first second lands inside torch's import; the clean-up then imported hsicam.devices,
    hence torch again, half-initialised: a double traceback ("partially initialized module 'torch' has no attribute
    'cuda'"), an abort (exit 134) or a segfault (139) instead of "hsicam: interrupted" (a helper's hunt, session 71).
    The clean-up of a failed command (and the output checks before it, short of a run folder's) imports no torch (a
    fresh process, looked at in sys.modules), and with torch unimportable a stopped command still ends as one."""
    import subprocess
    import sys

    code = f"""
import sys
import hsicam.cli as cli
out = cli.prepare_output({str(tmp_path / 'new' / 'out')!r}, "dir")
cli._remove_unused_outputs()
print(sorted({{'torch'}} & set(sys.modules)))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"
    assert not (tmp_path / "new").exists()  # the folder made for the output, removed again
    stopped = f"""
import sys
sys.modules["torch"] = None  # any import of torch now fails, as a half-imported one does
import hsicam.cli as cli
import hsicam.cli.camera as camera_cli

def cmd(args):
    cli.prepare_output(args.out, "dir")
    raise KeyboardInterrupt

camera_cli.cmd_psf = cmd
sys.exit(cli.main(["psf", "--out", {str(tmp_path / 'p')!r}]))
"""
    res = subprocess.run([sys.executable, "-c", stopped], capture_output=True, text=True)
    assert (res.returncode, res.stderr) == (130, "hsicam: interrupted\n")
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("stop_kind", ["interrupted", "stopped"])
def test_a_training_stop_behind_another_error_keeps_its_resume_line_and_exit_code(monkeypatch, capsys, tmp_path,
                                                                                  stop_kind):
    """A training stopped by a signal (or its time budget) whose stop surfaced as the context of another error (a
    clean-up that failed while it was handled) would have been a plain "interrupted" / 130, losing the run's resume
    line and exit code (a review, session 71): it is said as the stop itself is."""
    import hsicam.cli.camera as camera_cli
    from hsicam.cli import main
    from hsicam.errors import TrainingInterrupted, TrainingStopped

    run = tmp_path / "run"
    stop = (TrainingInterrupted(run, 3, 10, "SIGTERM", 143) if stop_kind == "interrupted"
            else TrainingStopped(run, 3, 10, "train.max_minutes", 75))
    monkeypatch.setattr(camera_cli, "cmd_psf", _wrapped_stop(stop, chained=False))
    code = main(["psf", "--out", str(tmp_path / "p")])
    assert code == stop.exit_code
    assert capsys.readouterr().err == (f"hsicam: {run}: training stopped at step 3 of 10 ({stop.reason}); the "
                                       "checkpoint of step 3 is saved; run the same command with --resume to go on\n")


@pytest.mark.parametrize("setting", ["camera.boundary=valid", "camera={boundary: valid}"])
def test_simulate_refuses_a_boundary_given_by_set_and_names_its_option(tmp_path, capsys, setting):
    """`simulate --set camera.boundary=valid` was replaced by --boundary's default (same) without a word: a 48×48
    sensor where 28×28 was asked (a helper's hunt, session 71). One line naming --boundary; nothing is written."""
    from hsicam.cli import main

    out = tmp_path / "sim"
    assert main(["simulate", "--config", "tiny", "--scene", str(tmp_path / "s.npy"), "--set", setting,
                 "--out", str(out)]) == 2
    assert capsys.readouterr().err == ("hsicam: error: --set camera.boundary: simulate's sensor boundary is its option "
                                       "--boundary (same by default, whatever the config says); give --boundary same "
                                       "or --boundary valid\n")
    assert not out.exists()
