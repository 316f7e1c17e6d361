"""Output folders holding a user's results are never destroyed or absorbed by another command.

A command replaces only a completed folder that it wrote itself and that holds nothing else (the
``command`` and ``files`` of its ``.complete`` marker); ``train --resume/--restart``,
``experiment``, ``data synth`` and ``demo`` refuse folders that another command (or the user) filled,
with one line, before any work. Through the console script, or :func:`hsicam.cli.main` in-process
where the test must see that no work started.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import assert_clean_error, module_cache, run_cli, run_cli_in_process
from hsicam.cli import main


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


@pytest.fixture(scope="module")
def outputs(tmp_path_factory, env):
    """A trained tiny run (``run``), its evaluation (``ev``) and a simulation (``sim``)."""
    d = tmp_path_factory.mktemp("outputs")
    np.save(d / "scene.npy", np.random.default_rng(0).uniform(0.1, 1, (7, 40, 40)).astype(np.float32))
    for args in (("train", "--config", "tiny", "--out", str(d / "run"), "--set", "train.epochs=1"),
                 ("evaluate", "--run", str(d / "run"), "--out", str(d / "ev")),
                 ("simulate", "--config", "tiny", "--scene", str(d / "scene.npy"), "--out", str(d / "sim"))):
        res = run_cli_in_process(*args, env=env)
        assert res.returncode == 0, res.stderr
    return d


def copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder`` with its bytes (None for a folder)."""
    return {p.relative_to(folder).as_posix(): (None if p.is_dir() else p.read_bytes()) for p in sorted(folder.rglob("*"))}


def test_another_commands_completed_folder_is_never_replaced(outputs, tmp_path, env):
    ev = copy(outputs / "ev", tmp_path / "ev1")
    (ev / "notes.txt").write_text("my notes")
    before = snapshot(ev)
    run = str(outputs / "run")
    for name, args in {"psf": ("psf", "--config", "tiny"),
                       "simulate": ("simulate", "--config", "tiny", "--scene", str(outputs / "scene.npy")),
                       "export-optics": ("export-optics", "--run", run),
                       "tolerance": ("tolerance", "--run", run)}.items():
        assert_clean_error(run_cli_in_process(*args, "--out", str(ev), env=env), str(ev),
                           f"holds the output of hsicam evaluate, not of hsicam {name}")
        assert snapshot(ev) == before, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ev1"]  # no temporary left either


def test_a_commands_own_folder_is_refreshed_but_never_with_a_users_files(outputs, tmp_path, env):
    ev = copy(outputs / "ev", tmp_path / "ev1")
    again = ("evaluate", "--run", str(outputs / "run"), "--out", str(ev))
    assert run_cli_in_process(*again, env=env).returncode == 0  # refreshing one's own results
    assert run_cli_in_process("report", str(ev), env=env).returncode == 0
    res = run_cli_in_process(*again, env=env)  # report/ is derived from the results: it goes with them
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in ev.iterdir()) == [".complete", "results.csv", "results.json", "results.md"]
    (ev / "notes.txt").write_text("my notes")
    (ev / "myplots").mkdir()
    (ev / "myplots" / "fig.png").write_bytes(b"png")
    before = snapshot(ev)
    assert_clean_error(run_cli_in_process(*again, env=env),
                       f"{ev}: holds myplots, notes.txt, which hsicam evaluate did not write", "move them")
    assert snapshot(ev) == before


@pytest.mark.parametrize("mode", ["--resume", "--restart", ""])
def test_train_does_not_resume_or_restart_in_another_commands_output(outputs, tmp_path, env, mode):
    sim = copy(outputs / "sim", tmp_path / "sim")
    before = snapshot(sim)
    config = ("--config", "tiny") if mode != "--resume" else ()
    res = run_cli_in_process("train", *config, "--out", str(sim), *([mode] if mode else []), env=env)
    assert_clean_error(res, f"{sim}: holds the output of hsicam simulate, not a training run",
                       f"nothing to {mode[2:]}" if mode else "a run needs its own folder")
    assert "--resume" not in res.stderr.split("error:")[-1]  # no remedy the folder cannot take
    assert snapshot(sim) == before


def test_experiment_refuses_another_commands_output_before_any_work(outputs, tmp_path, capsys, monkeypatch):
    import hsicam.engine.experiments as experiments

    def no_work(*a, **k):
        raise AssertionError("the experiment started in a folder it must refuse")

    monkeypatch.setattr(experiments, "run_experiment", no_work)
    for name in ("ev", "sim"):
        out = copy(outputs / name, tmp_path / name)
        before = snapshot(out)
        assert main(["experiment", "ablation", "--scale", "tiny", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("hsicam: error:") and len(err.splitlines()) == 1, err
        assert "not an experiment" in err and str(out) in err, err
        assert snapshot(out) == before


def test_data_synth_refuses_a_folder_that_is_not_its_dataset(outputs, tmp_path, env):
    synth = ("data", "synth", "--config", "tiny", "--n", "1", "--size", "16", "--no-progress", "--out")
    for name in ("run", "ev"):
        out = copy(outputs / name, tmp_path / name)
        before = snapshot(out)
        assert_clean_error(run_cli_in_process(*synth, str(out), env=env), str(out),
                           "holds no dataset of hsicam data synth", "choose an empty or new --out")
        assert snapshot(out) == before, name
    data = tmp_path / "data"
    assert run_cli_in_process(*synth, str(data), env=env).returncode == 0
    res = run_cli_in_process(*synth, str(data), env=env)  # its own dataset: recognised
    assert res.returncode == 0 and "already holds this dataset" in res.stdout, res.stderr
    (data / "manifest.json").unlink()  # a generation killed before its manifest: completed
    res = run_cli_in_process(*synth, str(data), env=env)
    assert res.returncode == 0 and (data / "manifest.json").is_file(), res.stderr


def test_demo_checks_its_output_folder_before_any_work(outputs, tmp_path, capsys, monkeypatch, env):
    import hsicam.engine.demo as demo

    def no_work(*a, **k):
        raise AssertionError("the demo started before its output folder was checked")

    monkeypatch.setattr(demo, "ensure_trained", no_work)
    taken = tmp_path / "afile"
    taken.write_text("user data")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "x.h5").write_bytes(b"cube")
    (mine / "x_rgb.png").write_bytes(b"png")
    ev = copy(outputs / "ev", tmp_path / "ev")
    for out, fragment in ((taken, "existing file"), (mine, "not a demo folder"),
                          (ev, "holds the output of hsicam evaluate, not a demo")):
        before = snapshot(tmp_path)
        assert main(["demo", "--config", "tiny", "--out", str(out)]) == 2
        captured = capsys.readouterr()
        err = captured.err.strip()
        assert err.startswith("hsicam: error:") and len(err.splitlines()) == 1, err
        assert str(out) in err and fragment in err, err
        assert "[demo]" not in captured.out and snapshot(tmp_path) == before
    # the console script, once (a process of its own: the entry point, without this test's monkeypatch):
    # one line, nothing generated first
    proc = run_cli("demo", "--config", "tiny", "--out", str(taken), env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert_clean_error(proc, str(taken), "existing file")
    assert not (tmp_path / "cache").exists() and taken.read_text() == "user data"
