"""Crash safety: a process killed at any write leaves a folder that a later command either resumes
to the same result or does not accept.

The kill is injected: in a forked child, ``os.replace`` / ``os.rename`` (every atomic write of the
toolkit ends with one) call ``os._exit`` at their N-th call, before renaming: no ``finally`` block,
no cleanup runs, exactly as with SIGKILL. The parent then resumes (or reruns) the command and
compares with an uninterrupted run.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch
from cli_helpers import run_cli_in_process

from hsicam.config import load_config
from hsicam.runs.checkpoint import read_weights

KILLED = 77  # the child's exit code when the injected kill fired
TIME_KEYS = ("elapsed_s", "patches_per_s")


class Writes:
    """Counts the renames that ``fn`` makes (the parent's reference run)."""

    def __init__(self, monkeypatch) -> None:
        self.n = 0
        for name in ("replace", "rename"):
            real = getattr(os, name)

            def counted(*a, _real=real, **k):
                self.n += 1
                return _real(*a, **k)

            monkeypatch.setattr(os, name, counted)


def run_killed_at(n: int, fn) -> int:
    """Run ``fn`` in a forked child that dies (``os._exit``) at its ``n``-th rename; returns its exit code
    (``KILLED`` when the kill fired, 0 when ``fn`` finished with fewer renames)."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        code = 1
        try:
            count = [0]
            for name in ("replace", "rename"):
                real = getattr(os, name)

                def killing(*a, _real=real, **k):
                    count[0] += 1
                    if count[0] == n:
                        os._exit(KILLED)
                    return _real(*a, **k)

                setattr(os, name, killing)
            fn()
            code = 0
        except BaseException:  # noqa: BLE001
            code = 1
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def hidden(folder: Path) -> list[Path]:
    return [p for p in folder.rglob(".*") if p.name != ".complete"]


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------
def _tiny():
    return load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3"])


def _train(run: Path, resume: bool = False):
    from hsicam.engine.train import train

    return train(_tiny(), run, resume=resume, progress=False)


def _records(run: Path) -> list[dict]:
    out = []
    for line in (run / "metrics.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if "session" not in rec:  # a session's start (its time, versions): a recovered run has one per process
            out.append({k: v for k, v in rec.items() if k not in TIME_KEYS})
    return out


def _result(run: Path) -> dict:
    """What a finished run is: root, best and last weights, the manifest's best, the metrics."""
    man = json.loads((run / "checkpoints.json").read_text())
    return {
        "root": read_weights(run / "model.safetensors")[0],
        "best": read_weights(run / man["best"]["dir"] / "model.safetensors")[0],
        "last": read_weights(run / man["last"]["dir"] / "model.safetensors")[0],
        "best_step": man["best"]["step"], "best_psnr": man["best"]["psnr"], "state": man["state"],
        "metrics": _records(run),
        "files": sorted(p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file()),
    }


def _assert_same(a: dict, b: dict, where: str) -> None:
    for key in ("root", "best", "last"):
        assert a[key].keys() == b[key].keys(), (where, key)
        for k in a[key]:
            assert torch.equal(a[key][k], b[key][k]), (where, key, k)  # bit-identical
    for key in ("best_step", "best_psnr", "state", "metrics", "files"):
        assert a[key] == b[key], (where, key, a[key], b[key])


@pytest.fixture(scope="module")
def reference(cache_env, tmp_path_factory):
    """An uninterrupted tiny run (also generates the cached data) and the number of renames a run makes."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("ref")
    _train(root / "warm")  # generates and caches the dataset: the counted run only writes the run folder
    mp = pytest.MonkeyPatch()
    try:
        writes = Writes(mp)
        _train(root / "ref")
    finally:
        mp.undo()
    ref = _result(root / "ref")
    _assert_same(_result(root / "warm"), ref, "two uninterrupted runs")
    # the root weights are the best checkpoint's (the documented promise)
    assert all(torch.equal(ref["root"][k], ref["best"][k]) for k in ref["root"])
    return ref, writes.n


def _kill_and_recover(n: int, tmp_path: Path, ref: dict) -> None:
    run = tmp_path / f"run-{n}"
    code = run_killed_at(n, lambda: _train(run))
    assert code == KILLED, f"the run made fewer than {n} renames (exit {code})"
    # after the kill: either a run folder to resume, or no run folder at all (a fresh start works)
    if (run / "config.yaml").is_file():
        assert not run.exists() or (run / "config.yaml").is_file()
        _train(run, resume=True)
    else:
        assert not run.exists(), f"kill at rename {n} left a run folder without config.yaml: {list(run.iterdir())}"
        _train(run)
    _assert_same(_result(run), ref, f"killed at rename {n}")
    assert not hidden(run), hidden(run)
    assert not list(tmp_path.glob(f".run-{n}.*")), "temporary run folder left behind"


def test_training_killed_at_every_write_resumes_bit_identically(reference, tmp_path):
    """Kill the tiny run at each of its renames in turn (config.yaml, every file and folder of every
    checkpoint, the manifest, the root weights, the metrics); each resumes (or, killed before its
    folder existed, starts again) to bit-identical final, best and last weights, manifest and metrics."""
    ref, total = reference
    assert total >= 20, total  # config, checkpoints (weights, optimizer, state, folder, manifest, root)
    for n in range(1, total + 1):
        _kill_and_recover(n, tmp_path, ref)


def test_root_weights_follow_the_manifest(reference, tmp_path, cache_env):
    """A kill between the manifest's commit and the root file's rewrite: readers take the
    manifest's best; resume rewrites the root file."""
    from hsicam.runs.checkpoint import MANIFEST, CheckpointManager, root_weights_path

    ref, _ = reference
    run = tmp_path / "run"
    _train(run)
    man = json.loads((run / MANIFEST).read_text())
    last = run / man["last"]["dir"] / "model.safetensors"
    shutil.copyfile(last, run / "model.safetensors")  # the root file holds the last weights, not the best
    assert man["best"]["dir"] != man["last"]["dir"]
    assert root_weights_path(run) == run / man["best"]["dir"] / "model.safetensors"
    assert CheckpointManager(run).sync_root() is True
    assert root_weights_path(run) == run / "model.safetensors"
    assert all(torch.equal(read_weights(run / "model.safetensors")[0][k], ref["best"][k]) for k in ref["best"])


def _flip_a_byte(path: Path) -> None:
    """Damage a weights file as a disk error would: one byte of its tensor data changed (it still loads)."""
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF
    path.write_bytes(bytes(data))


def test_damaged_weights_are_named_not_used(reference, tmp_path, caplog):
    """Weights that differ from the sha256 the manifest records (session 37's hunt): a damaged root file is
    read from the checkpoint that holds the recorded weights, said once; with that checkpoint damaged too,
    every reader and --resume refuse in one line naming both, instead of using (and refitting onto) them."""
    import logging

    from hsicam.errors import InputError
    from hsicam.runs.checkpoint import MANIFEST, CheckpointManager, root_weights_path
    from hsicam.runs.folder import load_run

    run = tmp_path / "run"
    _train(run)
    man = json.loads((run / MANIFEST).read_text())
    kept = run / man["best"]["dir"] / "model.safetensors"
    _flip_a_byte(run / "model.safetensors")
    with caplog.at_level(logging.INFO, logger="hsicam.runs.checkpoint"):
        for _ in range(3):
            assert root_weights_path(run) == kept
    said = [r.getMessage() for r in caplog.records if "does not hold the weights" in r.getMessage()]
    assert said == [f"{run / 'model.safetensors'} does not hold the weights {MANIFEST} records (out of date, or "
                    f"damaged); using {kept}, which does"]
    load_run(run)  # the recorded weights, from the checkpoint
    _flip_a_byte(kept)
    with pytest.raises(InputError, match="both differ from the weights .* records .*the run's weights are damaged"):
        load_run(run)
    res = run_cli_in_process("psf", "--run", str(run), "--out", str(tmp_path / "psf"))
    assert res.returncode == 2 and "the run's weights are damaged" in res.stderr.strip().splitlines()[-1], res.stderr
    assert not (tmp_path / "psf").exists()
    # resuming trains on from the last checkpoint: refused when it is not the file the manifest records
    last = run / man["last"]["dir"] / "model.safetensors"
    if last != kept:
        _flip_a_byte(last)
    shutil.copyfile(kept, run / "model.safetensors")
    with pytest.raises(InputError, match="the checkpoint is damaged"):
        CheckpointManager(run).load("last", _model(run), None, load_config(run / "config.yaml").bands.to_bands())


def _model(run: Path):
    from hsicam.models import CameraSystem

    return CameraSystem.from_config(load_config(run / "config.yaml"))


def test_a_linear_step_fitted_through_other_weights_of_a_run_without_checkpoints(reference, tmp_path):
    """A run folder without its checkpoints (a copy of the root files only) whose weights changed after the
    linear step's fit: `--resume` cannot refit it, so the line does not send the user there."""
    from hsicam.errors import InputError
    from hsicam.runs.folder import load_run

    from hsicam.engine.train import train

    run = tmp_path / "run"
    cfg = load_config("tiny", ["train.epochs=1", "model.consistency.kind=linear", "model.consistency.iterations=1"])
    train(cfg, run, progress=False)
    assert (run / "linear_step.safetensors").is_file()
    shutil.rmtree(run / "checkpoints")
    (run / "checkpoints.json").unlink()
    _flip_a_byte(run / "model.safetensors")
    with pytest.raises(InputError) as err:
        load_run(run)
    line = str(err.value)
    assert "was fitted through other weights" in line and "changed or damaged" in line
    assert line.endswith("the run has no checkpoint to refit the filters from: copy the run folder again from its "
                         "source, or train it again"), line
    assert "--resume" not in line


def test_legacy_pointer_files_are_read(reference, tmp_path):
    """Runs written before the manifest (last.json / best.json) still load and resume."""
    from hsicam.runs.checkpoint import MANIFEST, CheckpointManager

    ref, _ = reference
    run = tmp_path / "run"
    from hsicam.engine.train import train

    train(_tiny(), run, progress=False, stop_after_steps=5)
    man = json.loads((run / MANIFEST).read_text())
    (run / MANIFEST).unlink()
    (run / "last.json").write_text(json.dumps({"dir": man["last"]["dir"], **man["state"]}))
    if man["best"]:
        (run / "best.json").write_text(json.dumps({"dir": man["best"]["dir"], **man["state"]}))
    assert CheckpointManager(run).state()["global_step"] == 5
    _train(run, resume=True)
    assert not (run / "last.json").exists() and (run / MANIFEST).is_file()
    res = _result(run)
    for key in ("root", "best", "last"):
        assert all(torch.equal(res[key][k], ref[key][k]) for k in ref[key]), key


def _snapshot(run: Path) -> dict[str, bytes | None]:
    """Every entry of a run folder: a file's bytes, None for a folder."""
    return {p.relative_to(run).as_posix(): p.read_bytes() if p.is_file() else None for p in sorted(run.rglob("*"))}


def test_resuming_a_finished_run_changes_nothing(reference, tmp_path):
    """`train --resume` on a finished run: exit 0, says so (and how to train on), every file stays
    byte-identical, however often it is repeated; the library call returns the run's final record."""
    run = tmp_path / "run"
    _train(run)
    before = _snapshot(run)
    final = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    for _ in range(2):
        proc = run_cli_in_process("train", "--out", str(run), "--resume")
        assert proc.returncode == 0, proc.stderr
        assert "Traceback" not in proc.stderr
        assert f"{run}: already finished at step 8 (2 epochs)" in proc.stdout
        assert "train.epochs" in proc.stdout
        assert _snapshot(run) == before
    assert _train(run, resume=True) == {**final, "already_finished": True}
    assert _snapshot(run) == before


def test_resuming_a_finished_run_with_more_epochs_trains_on(reference, tmp_path):
    """Raising train.epochs continues a finished run; then that longer run is finished in turn."""
    run = tmp_path / "run"
    _train(run)
    proc = run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.epochs=3")
    assert proc.returncode == 0, proc.stderr
    assert "trained 3 epochs (12 steps" in proc.stdout and "val PSNR" in proc.stdout
    man = json.loads((run / "checkpoints.json").read_text())
    assert man["state"]["global_step"] == 12 and man["state"]["epoch"] == 3
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    last = records[-1]
    assert last["final"] and last["step"] == 12 and "val_psnr" in last
    assert [r["step"] for r in records if r.get("final")] == [12]  # the 2-epoch summary is not left in the log
    before = _snapshot(run)
    proc = run_cli_in_process("train", "--out", str(run), "--resume")
    assert proc.returncode == 0 and "already finished at step 12 (3 epochs)" in proc.stdout, proc.stderr
    assert _snapshot(run) == before


def test_killed_before_the_final_record_resumes_to_the_same_record(reference, tmp_path):
    """A kill after the last checkpoint's commit but before the final metrics record: the resume
    writes the final record the uninterrupted run wrote (with the last validation's metrics)."""
    ref, _ = reference
    run = tmp_path / "run"
    _train(run)
    lines = (run / "metrics.jsonl").read_text().splitlines(keepends=True)
    (run / "metrics.jsonl").write_text("".join(lines[:-1]))
    summary = _train(run, resume=True)
    assert "already_finished" not in summary and summary["val_psnr"] == ref["metrics"][-1]["val_psnr"]
    _assert_same(_result(run), ref, "killed before the final record")


def test_resuming_a_run_without_validation(reference, tmp_path):
    """A run without validation scenes resumes to its end, then is finished."""
    from hsicam.engine.train import train
    run = tmp_path / "run"
    train(load_config("tiny", ["train.epochs=2", "data.val_fraction=0"]), run, progress=False, stop_after_steps=5)
    proc = run_cli_in_process("train", "--out", str(run), "--resume")
    assert proc.returncode == 0, proc.stderr
    assert "trained 2 epochs (8 steps" in proc.stdout and "PSNR" not in proc.stdout
    before = _snapshot(run)
    proc = run_cli_in_process("train", "--out", str(run), "--resume")
    assert proc.returncode == 0 and "already finished at step 8 (2 epochs)" in proc.stdout, proc.stderr
    assert _snapshot(run) == before


# ------------------------------------------------------------------------------------------------
# Commands: killed at each write → nothing a later command accepts; the rerun completes
# ------------------------------------------------------------------------------------------------
def _count_writes(fn) -> int:
    mp = pytest.MonkeyPatch()
    try:
        writes = Writes(mp)
        fn()
    finally:
        mp.undo()
    return writes.n


def _cli(*args: str) -> None:
    from hsicam.cli import main

    assert main(list(args)) == 0


def test_data_synth_killed_at_every_write(tmp_path, cache_env):
    from hsicam.data.synthetic import is_complete
    from hsicam.spectral import Bands

    args = ("data", "synth", "--config", "tiny", "--n", "2", "--size", "16", "--no-progress")
    cfg = load_config("tiny")
    bands = cfg.bands.to_bands()
    held = {"holdout_sources": cfg.data.holdout_sources}  # `data synth --config` holds out the config's sources

    def complete(folder):
        return is_complete(folder, 2, 16, 0, bands, **held)

    total = _count_writes(lambda: _cli(*args, "--out", str(tmp_path / "ref")))
    assert complete(tmp_path / "ref")
    assert total >= 3
    for n in range(1, total + 1):
        out = tmp_path / f"d{n}"
        assert run_killed_at(n, lambda: _cli(*args, "--out", str(out))) == KILLED
        assert not complete(out), n  # nothing a later command accepts
        _cli(*args, "--out", str(out))
        assert complete(out)
        for scene in sorted((tmp_path / "ref").glob("*.h5")):
            assert (out / scene.name).read_bytes() == scene.read_bytes() or scene.name == "manifest.json"
    assert isinstance(bands, Bands)


@pytest.fixture(scope="module")
def trained(reference, tmp_path_factory):
    run = tmp_path_factory.mktemp("trained") / "run"
    _train(run)
    return run


def _accepted_by_report(folder: Path) -> bool:
    from hsicam.errors import InputError
    from hsicam.report.html import build_report

    try:
        build_report(folder)
    except InputError:
        return False
    return True


def test_evaluate_save_killed_at_every_write(trained, tmp_path):
    args = ("evaluate", "--run", str(trained), "--save")
    _cli(*args, "--out", str(tmp_path / "warm"))  # caches the held-out validation set: not counted
    total = _count_writes(lambda: _cli(*args, "--out", str(tmp_path / "ref")))
    ref = json.loads((tmp_path / "ref" / "results.json").read_text())
    assert total >= 6 and (tmp_path / "ref" / ".complete").is_file()
    for n in range(1, total + 1):
        out = tmp_path / f"e{n}"
        assert run_killed_at(n, lambda: _cli(*args, "--out", str(out))) == KILLED
        assert not out.exists() or not _accepted_by_report(out), n
        assert not (out / "report").exists()
        _cli(*args, "--out", str(out))
        got = json.loads((out / "results.json").read_text())
        assert [(r["name"], r["psnr"]) for r in got["scenes"]] == [(r["name"], r["psnr"]) for r in ref["scenes"]]
        assert sorted(p.name for p in (out / "cubes").iterdir()) == sorted(p.name for p in (tmp_path / "ref" / "cubes").iterdir())
        assert not list(tmp_path.glob(f".e{n}.*"))
    assert _accepted_by_report(tmp_path / "ref")


@pytest.mark.parametrize("every", [pytest.param(1, marks=pytest.mark.slow), 4])
def test_export_optics_killed_at_every_write(trained, tmp_path, every):
    """Killed at every write (slow; the default suite kills at every 4th write, first and last included)."""
    args = ("export-optics", "--run", str(trained), "--levels", "4")
    total = _count_writes(lambda: _cli(*args, "--out", str(tmp_path / "ref")))
    ref = sorted(p.name for p in (tmp_path / "ref").iterdir())
    assert total >= 10 and ".complete" in ref
    for n in sorted({*range(1, total + 1, every), total}):
        out = tmp_path / f"x{n}"
        assert run_killed_at(n, lambda: _cli(*args, "--out", str(out))) == KILLED
        assert not out.exists() or not (out / ".complete").is_file(), n
        assert not (out / "spec.json").exists(), n  # nothing a later command (or a supplier) takes for the export
        _cli(*args, "--out", str(out))
        assert sorted(p.name for p in out.iterdir()) == ref
        assert (out / "doe_height_L4_nm.npy").read_bytes() == (tmp_path / "ref" / "doe_height_L4_nm.npy").read_bytes()
        assert not list(tmp_path.glob(f".x{n}.*"))


# ------------------------------------------------------------------------------------------------
# Starting, restarting and bad data
# ------------------------------------------------------------------------------------------------
def test_train_with_bad_data_root_leaves_nothing(tmp_path, cache_env, capsys):
    from hsicam.cli import main

    run = tmp_path / "run"
    empty = tmp_path / "nodata"
    empty.mkdir()
    code = main(["train", "--config", "tiny", "--out", str(run), "--set", f"data.root={empty}"])
    assert code == 2 and "hsicam: error:" in capsys.readouterr().err
    assert not run.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["nodata"]
    # the corrected command is not refused
    assert main(["train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1"]) == 0


def test_resume_without_config_says_how_to_restart_and_restart_works(tmp_path, cache_env, capsys):
    from hsicam.cli import main

    run = tmp_path / "run"
    run.mkdir()
    (run / ".config.abcd1234.tmp.yaml").write_text("half")  # a write killed before config.yaml was placed
    (run / "metrics.jsonl").write_text("")
    assert main(["train", "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "nothing to resume" in err and "--restart" in err and len(err.strip().splitlines()) == 1
    assert main(["train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1"]) == 2  # not empty
    assert "--restart" in capsys.readouterr().err
    assert main(["train", "--config", "tiny", "--out", str(run), "--restart", "--set", "train.epochs=1"]) == 0
    assert (run / "checkpoints.json").is_file() and not hidden(run)
    # a folder with a finished checkpoint is never wiped by --restart
    assert main(["train", "--config", "tiny", "--out", str(run), "--restart"]) == 2
    assert "finished checkpoint" in capsys.readouterr().err and (run / "checkpoints.json").is_file()
    # nor a folder holding files a run never writes
    other = tmp_path / "mine"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    assert main(["train", "--config", "tiny", "--out", str(other), "--restart"]) == 2
    assert (other / "thesis.tex").read_text() == "x"


def test_restart_without_config_starts_the_run_again_with_its_own_config(tmp_path, cache_env, capsys):
    """`train --out RUN --restart` without --config, on a tiny run killed before its first checkpoint, started the
    built-in paper config in its place (a 100-epoch paper camera), without a word (a helper's hunt, session 71).
    It starts again with the run's own config.yaml (and --set); with --config, that config, as before."""
    from hsicam.cli import main
    from hsicam.config import dump_yaml, load_config

    run = tmp_path / "run"
    run.mkdir()
    own = load_config("tiny", ["train.epochs=1", "data.synthetic_n=6", "data.synthetic_size=64"])
    (run / "config.yaml").write_text(dump_yaml(own))  # as a training killed before its first checkpoint left it
    (run / "metrics.jsonl").write_text("")
    assert main(["train", "--out", str(run), "--restart", "--set", "train.seed=3"]) == 0
    kept = load_config(run / "config.yaml")
    assert kept.camera == own.camera and kept.data == own.data and kept.train.epochs == 1 and kept.train.seed == 3
    assert (run / "checkpoints.json").is_file()


def test_simulate_resamples_a_scene_on_another_band_grid(trained, tmp_path, caplog):
    """One band-grid policy: a 31-band scene (420-720 nm, 10 nm) through the 7-band tiny camera."""
    import logging

    import numpy as np

    from hsicam.cli import main
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    rng = np.random.default_rng(0)
    scene = rng.uniform(0.1, 1, (31, 40, 40)).astype(np.float32)
    write_cube_h5(tmp_path / "s31.h5", scene, Bands.uniform(420, 720, 10))
    with caplog.at_level(logging.INFO):
        assert main(["simulate", "--run", str(trained), "--scene", str(tmp_path / "s31.h5"), "--out", str(tmp_path / "sim")]) == 0
    assert any("resampling 31 bands" in r.getMessage() for r in caplog.records)
    assert np.load(tmp_path / "sim" / "sensor.npy").shape == (40, 40)
    # extrapolation is refused with one clear line; a negative or complex .npy scene is refused
    write_cube_h5(tmp_path / "s400.h5", scene[:28], Bands.uniform(420, 690, 10))
    assert main(["simulate", "--run", str(trained), "--scene", str(tmp_path / "s400.h5"), "--out", str(tmp_path / "o")]) == 2
    bad = scene[::5][:7].copy()
    bad[0, 0, 0] = -1
    np.save(tmp_path / "neg.npy", bad)
    np.save(tmp_path / "cplx.npy", scene[:7].astype(np.complex64))
    for f in ("neg.npy", "cplx.npy"):
        assert main(["simulate", "--run", str(trained), "--scene", str(tmp_path / f), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
