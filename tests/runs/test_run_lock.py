"""One process at a time trains in a run folder (:mod:`hsicam.runs.lock`): a second one is refused
with one line before it touches anything; the lock goes with its holder however it ends."""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import pytest
from cli_helpers import error_line, module_cache, run_cli

fcntl = pytest.importorskip("fcntl")  # POSIX: where it is missing, nothing is locked

from hsicam.config import load_config
from hsicam.engine.train import train
from hsicam.runs.checkpoint import CheckpointManager
from hsicam.runs.folder import RUN_ENTRIES
from hsicam.runs.lock import LOCK_FILE, RunLock, check_not_locked


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


def _cfg():
    return load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3"])


def _snapshot(folder: Path) -> dict[str, tuple[str, int]]:
    """Every entry under ``folder`` (hidden ones too): content hash (files) and modification time."""
    out = {}
    for p in sorted(folder.rglob("*")):
        digest = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
        out[p.relative_to(folder).as_posix()] = (digest, p.stat().st_mtime_ns)
    return out


def _held_elsewhere(run: Path) -> bool:
    """True when a lock on ``run``'s lock file is held (tried through a new open file: flock locks
    of two open files conflict even within one process)."""
    fd = os.open(run / LOCK_FILE, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


@pytest.fixture(scope="module")
def stopped(env, tmp_path_factory):
    """A run stopped at step 5 of 8 (a resume would train on and write)."""
    run = tmp_path_factory.mktemp("runs") / "run"
    train(_cfg(), run, progress=False, stop_after_steps=5)
    return run


def test_a_second_process_is_refused_before_it_touches_anything(stopped, env):
    run = stopped
    # the in-flight checkpoint of the process that holds the lock: a second process used to delete it
    inflight = run / "checkpoints" / ".step-00000006.abcd1234.tmpdir"
    inflight.mkdir()
    (inflight / "model.safetensors").write_bytes(b"being written")
    try:
        with RunLock(run) as lock:
            lock.acquire()
            info = json.loads((run / LOCK_FILE).read_text())
            assert info["pid"] == os.getpid()
            before = _snapshot(run)
            want = re.compile(rf"hsicam: error: {re.escape(str(run))}: being trained by another process \(pid "
                              rf"{os.getpid()}, since {re.escape(info['since'])}\); wait for it or stop it")
            for args in (("--resume",), ("--restart", "--config", "tiny"), ("--config", "tiny")):
                res = run_cli("train", "--out", str(run), *args, env=env)
                assert want.fullmatch(error_line(res)), (args, res.stderr)
                assert _snapshot(run) == before, args
        assert not (run / LOCK_FILE).exists()  # removed on release
    finally:
        (inflight / "model.safetensors").unlink()
        inflight.rmdir()


def test_training_holds_the_lock_and_lets_go(env, tmp_path, monkeypatch):
    run = tmp_path / "run"
    seen = []
    real = CheckpointManager.save

    def save(self, *a, **k):
        seen.append(_held_elsewhere(self.run_dir))
        check_not_locked(self.run_dir)  # this process's own lock: no refusal
        return real(self, *a, **k)

    monkeypatch.setattr(CheckpointManager, "save", save)
    train(_cfg(), run, progress=False)  # a new run: locked in its temporary folder, then in place
    assert seen and all(seen)
    assert not (run / LOCK_FILE).exists()
    n = len(seen)
    train(_cfg(), run, resume=True, progress=False)  # finished: nothing to write, the lock comes and goes
    train(load_config(run / "config.yaml", ["train.epochs=3"]), run, resume=True, progress=False)
    assert len(seen) > n and all(seen)
    assert not (run / LOCK_FILE).exists()


def test_an_interrupted_training_lets_go_and_a_stale_lock_file_is_taken_over(env, tmp_path, monkeypatch):
    run = tmp_path / "run"
    train(_cfg(), run, progress=False, stop_after_steps=3)
    real = CheckpointManager.save

    def interrupted(self, *a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(CheckpointManager, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg(), run, resume=True, progress=False)
    assert not (run / LOCK_FILE).exists()
    monkeypatch.setattr(CheckpointManager, "save", real)
    # a lock file left by a killed process (kill -9) holds no lock: neither a refusal nor a user's file
    (run / LOCK_FILE).write_text(json.dumps({"pid": 999999, "since": "2000-01-01 00:00:00"}))
    check_not_locked(run)
    assert LOCK_FILE in RUN_ENTRIES and LOCK_FILE.startswith(".")
    summary = train(_cfg(), run, resume=True, progress=False)
    assert summary["step"] == 8
    assert not (run / LOCK_FILE).exists()


def test_the_lock_is_re_entrant_within_a_process(tmp_path):
    """The training loop holds it, then the linear step's refit acquires it again (session 23 review):
    an inner acquire does nothing and its release keeps the outer lock."""
    run = tmp_path / "run"
    run.mkdir()
    with RunLock(run) as outer:
        outer.acquire()
        with RunLock(run) as inner:
            inner.acquire()
        assert (run / LOCK_FILE).is_file()
        fd = os.open(run / LOCK_FILE, os.O_RDONLY)
        try:
            with pytest.raises(BlockingIOError):  # still held: another open file description cannot take it
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            os.close(fd)
    assert not (run / LOCK_FILE).exists()


def test_a_resume_and_a_restart_hold_the_lock_from_their_first_change(stopped, tmp_path, monkeypatch):
    """`train --resume` removes a killed run's temporaries and `--restart` the run's files before the
    loop starts: the command holds the lock from then on (review of session 23), not only the loop."""
    import shutil

    from hsicam.cli import main
    from hsicam.runs import folder

    seen = []
    for name in ("check_run_dir", "restart_run_dir"):
        real = getattr(folder, name)

        def spy(run_dir, *args, _real=real, _name=name, **kwargs):
            seen.append((_name, (Path(run_dir) / LOCK_FILE).is_file() and _held_elsewhere(Path(run_dir))))
            return _real(run_dir, *args, **kwargs)

        monkeypatch.setattr(folder, name, spy)
    run = shutil.copytree(stopped, tmp_path / "run")
    assert main(["train", "--out", str(run), "--resume"]) == 0
    killed = tmp_path / "killed"  # a run killed before its first checkpoint: --restart starts it again
    killed.mkdir()
    shutil.copyfile(stopped / "config.yaml", killed / "config.yaml")
    assert main(["train", "--config", "tiny", "--out", str(killed), "--restart", "--set", "train.epochs=1"]) == 0
    assert {name for name, _ in seen} == {"check_run_dir", "restart_run_dir"} and all(held for _, held in seen), seen
    assert not (run / LOCK_FILE).exists() and not (killed / LOCK_FILE).exists()


def test_a_forked_child_does_not_keep_the_lock_of_its_killed_parent(tmp_path):
    """A DataLoader worker is a fork of the training: it must not hold the run's lock once the training is killed
    (an flock lock lasts while any copy of its descriptor is open, and an orphaned worker lives on ~5 s, so an
    immediate --resume was refused). The parent's lock itself stays while the parent lives."""
    import signal
    import subprocess
    import sys
    import time

    from hsicam.io import held_elsewhere

    run = tmp_path / "run"
    run.mkdir()
    script = (
        "import os, sys, time\n"
        "from hsicam.runs.lock import RunLock\n"
        f"lock = RunLock({str(run)!r}); lock.acquire()\n"
        "child = os.fork()\n"
        "if child == 0:\n"
        f"    open({str(tmp_path / 'forked')!r}, 'w').close(); time.sleep(30); os._exit(0)\n"
        "print(child, flush=True); time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    child = int(proc.stdout.readline())
    # the child's file says its fork hooks have run (on a busy machine the parent could be killed before the child
    # was first scheduled, its copy of the lock still open: a flaky failure in a fresh clone, session 72)
    deadline = time.monotonic() + 20
    while not (tmp_path / "forked").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert (tmp_path / "forked").exists()
    try:
        assert held_elsewhere(run / LOCK_FILE)  # the parent holds it while it lives
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        os.kill(child, 0)  # the orphan lives on
        assert not held_elsewhere(run / LOCK_FILE)
        with RunLock(run) as lock:
            lock.acquire()  # a resume now takes it at once
    finally:
        proc.kill()
        try:
            os.kill(child, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_a_nested_run_lock_once_released_takes_the_lock_when_acquired_again(tmp_path):
    """(A mutation guard.) A nested RunLock takes nothing while the outer one holds the lock; released by both, the
    same object acquired again must really take the lock (an flock through another open file sees it)."""
    outer, inner = RunLock(tmp_path), RunLock(tmp_path)
    outer.acquire()
    inner.acquire()  # held by this process already: nested, takes nothing
    inner.release()  # keeps the outer
    assert _held_elsewhere(tmp_path)
    outer.release()
    assert not (tmp_path / LOCK_FILE).exists()
    inner.acquire()  # nobody holds it now: this one must take it
    try:
        assert (tmp_path / LOCK_FILE).is_file() and _held_elsewhere(tmp_path)
    finally:
        inner.release()
    assert not (tmp_path / LOCK_FILE).exists()
