"""Two processes and one output: a second command never deletes the temporaries of a process that is
writing them now (:mod:`hsicam.io`: a temporary file is locked while it is written, a folder output by
its :class:`~hsicam.io.OutputLock`), while a killed process's temporaries are still removed (the kernel
lets go of its locks). A second writer of a folder is refused with one line naming the first; a second
training into a new run that the first is still making gets the line of a locked run.

Each test starts a real writer process that stops at a point of its work until the test tells it to go
on (marker files: ``ready`` holds what it is writing, ``go`` lets it finish).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from cli_helpers import assert_ok, cli_env, error_line, module_cache, run_cli_in_process

fcntl = pytest.importorskip("fcntl")  # POSIX: where it is missing nothing is locked (last test)

import hsicam.io as hio  # noqa: E402
from hsicam.cli import prepare_output  # noqa: E402
from hsicam.io import atomic_output, atomic_path, cleanup_stale_temporaries, is_temporary, read_marker  # noqa: E402

# The child's pause: "ready" says what it is writing, then it waits for "go".
PAUSE = """
import sys, time
from pathlib import Path

def pause(what):
    ready = Path(sys.argv[1])
    ready.with_name("ready.part").write_text(str(what))
    ready.with_name("ready.part").replace(ready)  # atomic: the test never reads a half-written "ready"
    deadline = time.time() + 60
    while not Path(sys.argv[2]).exists():
        if time.time() > deadline:
            sys.exit("never told to go on")
        time.sleep(0.01)
"""

WRITE_FOLDER = """
from hsicam.io import atomic_output

with atomic_output(sys.argv[3], overwrite=True, marker={"command": "simulate"}) as tmp:
    (tmp / "first.txt").write_text("first")
    pause(tmp)
    (tmp / "second.txt").write_text("second")
"""

WRITE_FILE = """
from hsicam.io import atomic_open

with atomic_open(sys.argv[3], "w") as fh:
    fh.write("first")
    fh.flush()
    pause(fh.name)
    fh.write(" second")
"""

# `hsicam train` stopped while its new run is a hidden temporary folder, or before its data are made
TRAIN = """
import hsicam.engine.loop as loop
from hsicam.cli import main
from hsicam.runs.lock import RunLock

if sys.argv[3] == "temporary":
    acquire = RunLock.acquire

    def paused_acquire(self, folder=None):
        acquire(self, folder)
        if folder is not None:  # the run's temporary folder, locked
            pause(folder)

    RunLock.acquire = paused_acquire
else:
    check_run_dir = loop.check_run_dir

    def paused_check(run_dir, *args, **kwargs):
        pause(run_dir)
        return check_run_dir(run_dir, *args, **kwargs)

    loop.check_run_dir = paused_check
sys.exit(main(["train", "--config", "tiny", "--out", sys.argv[4], "--set", "train.epochs=1"]))
"""


class Writer:
    """A child process running ``PAUSE + code`` that stops in ``pause(what)``."""

    def __init__(self, sync: Path, code: str, *args: str) -> None:
        sync.mkdir(parents=True)
        self.ready, self.go_file = sync / "ready", sync / "go"
        script = PAUSE + textwrap.dedent(code)
        self.proc = subprocess.Popen([sys.executable, "-c", script, str(self.ready), str(self.go_file), *args],
                                     env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.pid = self.proc.pid
        deadline = time.time() + 120
        while not self.ready.exists():
            assert self.proc.poll() is None, self.proc.communicate()
            assert time.time() < deadline, "the writer never got to its pause"
            time.sleep(0.01)
        self.what = Path(self.ready.read_text())

    def go(self) -> subprocess.CompletedProcess:
        """Let it finish; its completed process."""
        self.go_file.write_text("")
        out, err = self.proc.communicate(timeout=120)
        return subprocess.CompletedProcess(self.proc.args, self.proc.returncode, out, err)

    def kill(self) -> None:
        """``kill -9`` while it pauses."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.communicate(timeout=60)
        assert self.proc.returncode == -signal.SIGKILL


@pytest.fixture
def start(tmp_path):
    """``start(code, *args)``: a :class:`Writer` at its pause (killed at the end if still running)."""
    writers: list[Writer] = []

    def make(code: str, *args: str | Path) -> Writer:
        w = Writer(tmp_path / "sync" / str(len(writers)), code, *map(str, args))
        writers.append(w)
        return w

    yield make
    for w in writers:
        if w.proc.poll() is None:
            w.proc.kill()
            w.proc.communicate()


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


def simulate(scene: Path, out: Path) -> subprocess.CompletedProcess:
    return run_cli_in_process("simulate", "--config", "tiny", "--scene", str(scene), "--out", str(out))


def hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ------------------------------------------------------------------------------------------------
# A folder output
# ------------------------------------------------------------------------------------------------
def test_a_folder_being_written_is_kept_and_a_second_writer_refused(tmp_path, start, env, scene):
    out = tmp_path / "out" / "sim"
    out.parent.mkdir()
    w = start(WRITE_FOLDER, out)
    tmp = w.what
    assert is_temporary(tmp.name) and tmp.parent == out.parent
    line = error_line(simulate(scene, out))  # used to delete the first one's temporary folder
    assert re.fullmatch(rf"hsicam: error: {re.escape(str(out))}: being written by another process \(hsicam simulate, "
                        rf"pid {w.pid}, since [0-9-]+ [0-9:]+\); wait for it or stop it", line), line
    with pytest.raises(hio.InputError, match=rf"being written by another process \(hsicam simulate, pid {w.pid}"):
        with atomic_output(out, overwrite=True, marker={"command": "simulate"}):
            pass
    old = out.parent / ".sim.0a1b2c3d.old"  # what a swap sets aside while it renames the new folder in
    old.mkdir()
    assert cleanup_stale_temporaries(out.parent, recursive=True) == []
    assert (tmp / "first.txt").read_text() == "first" and old.is_dir()
    old.rmdir()
    assert_ok(w.go())
    assert sorted(p.name for p in out.iterdir()) == [".complete", "first.txt", "second.txt"]
    assert read_marker(out)["command"] == "simulate" and hidden(out.parent) == []


def test_a_killed_writers_temporaries_are_removed_by_the_next_command(tmp_path, start, env, scene):
    out = tmp_path / "out" / "sim"
    out.parent.mkdir()
    w = start(WRITE_FOLDER, out)
    w.kill()
    assert hidden(out.parent) == sorted([w.what.name, ".sim.hsicam-lock"])  # its lock file: no longer locked
    assert_ok(simulate(scene, out))
    assert read_marker(out)["command"] == "simulate" and hidden(out.parent) == []
    w = start(WRITE_FOLDER, out)  # and by a cleanup
    w.kill()
    assert sorted(p.name for p in cleanup_stale_temporaries(out.parent)) == sorted([w.what.name, ".sim.hsicam-lock"])
    assert hidden(out.parent) == []


# ------------------------------------------------------------------------------------------------
# A file output
# ------------------------------------------------------------------------------------------------
def test_a_file_being_written_keeps_its_temporary_and_a_killed_ones_is_removed(tmp_path, start):
    out = tmp_path / "out" / "recon.txt"
    out.parent.mkdir()
    w = start(WRITE_FILE, out)
    tmp = w.what
    assert is_temporary(tmp.name) and tmp.parent == out.parent
    assert cleanup_stale_temporaries(out.parent, recursive=True) == []
    assert prepare_output(out, "file") == out  # no refusal: two writers of a file each rename a whole file in
    assert tmp.read_text() == "first"
    assert_ok(w.go())
    assert out.read_text() == "first second" and hidden(out.parent) == []
    w = start(WRITE_FILE, out)
    w.kill()
    assert hidden(out.parent) == [w.what.name]
    prepare_output(out, "file")
    assert hidden(out.parent) == [] and out.read_text() == "first second"


def test_this_processs_own_temporaries_are_in_use_too(tmp_path):
    with atomic_output(tmp_path / "out") as tmp:
        with atomic_path(tmp_path / "f.json") as ftmp:
            assert cleanup_stale_temporaries(tmp_path) == []
            assert tmp.is_dir() and ftmp.is_file()
            prepare_output(tmp_path / "out", "dir")  # its own folder: no refusal, nothing removed
            prepare_output(tmp_path / "f.json", "file")
            assert tmp.is_dir() and ftmp.is_file()
            ftmp.write_text("{}")
    assert hidden(tmp_path) == [] and (tmp_path / "out").is_dir() and (tmp_path / "f.json").is_file()


# ------------------------------------------------------------------------------------------------
# A new training run
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["temporary", "before its data"])
def test_a_second_training_into_a_new_run_being_made_is_refused(tmp_path, start, env, where):
    run = tmp_path / "runs" / "run"
    run.parent.mkdir()
    w = start(TRAIN, "temporary" if where == "temporary" else "data", run)
    second = ("train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1")
    line = error_line(run_cli_in_process(*second))  # used to delete the first one's temporary and train itself
    assert re.fullmatch(rf"hsicam: error: {re.escape(str(run))}: being trained by another process \(pid {w.pid}, "
                        rf"since [0-9-]+ [0-9:]+\); wait for it or stop it", line), line
    if where == "temporary":
        assert w.what.is_dir() and (w.what / ".hsicam-lock").is_file()
        assert_ok(w.go())  # used to fail: "folder exists and is not empty"
    else:
        assert not run.exists()
        w.kill()
        assert hidden(run.parent) == [".run.hsicam-lock"]  # a killed process's: taken over
        assert_ok(run_cli_in_process(*second))
    assert (run / "config.yaml").is_file() and (run / "model.safetensors").is_file()
    assert not (run / ".hsicam-lock").exists() and hidden(run.parent) == []


# ------------------------------------------------------------------------------------------------
# torchrun; no fcntl
# ------------------------------------------------------------------------------------------------
def test_in_a_torchrun_group_rank_0_removes_the_temporaries(tmp_path, monkeypatch):
    stale = tmp_path / ".sim.0a1b2c3d.tmpdir"
    stale.mkdir()
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    prepare_output(tmp_path / "sim", "dir")
    assert stale.is_dir()  # rank 0's, maybe being written
    monkeypatch.setenv("RANK", "0")
    prepare_output(tmp_path / "sim", "dir")
    assert hidden(tmp_path) == []


def test_without_fcntl_nothing_is_locked_and_every_temporary_is_removed(tmp_path, monkeypatch):
    monkeypatch.setattr(hio, "fcntl", None)  # Windows
    with atomic_output(tmp_path / "out") as tmp, atomic_path(tmp_path / "f.json") as ftmp:
        ftmp.write_text("{}")
        assert hidden(tmp_path) == sorted([tmp.name, ftmp.name])  # no lock file
    assert hidden(tmp_path) == [] and (tmp_path / "out").is_dir() and (tmp_path / "f.json").is_file()
    stale = [tmp_path / ".out.0a1b2c3d.tmpdir", tmp_path / ".f.0a1b2c3d.tmp.json"]
    stale[0].mkdir()
    stale[1].write_text("{")
    assert cleanup_stale_temporaries(tmp_path) == sorted(stale)
    stale[0].mkdir()
    prepare_output(tmp_path / "out", "dir")
    assert hidden(tmp_path) == []


def test_a_run_folders_temporary_in_use_is_not_removed_by_a_run_check(tmp_path, start):
    """check_run_dir / restart_run_dir clear the temporaries a killed process left around a run folder,
    never the temporary of a folder that another process is writing now (under its OutputLock); where
    this process holds that lock (a training making its new run), a killed writer's go."""
    from hsicam.io import OutputLock
    from hsicam.runs.folder import remove_run_temporaries

    run = tmp_path / "run"
    w = start(WRITE_FOLDER, run)
    assert remove_run_temporaries(run) == []  # used to delete the writer's temporary folder
    assert (w.what / "first.txt").read_text() == "first"
    assert_ok(w.go())
    assert sorted(p.name for p in run.iterdir()) == [".complete", "first.txt", "second.txt"]
    stale = tmp_path / ".run.0a1b2c3d.tmpdir"
    stale.mkdir()
    assert remove_run_temporaries(run) == [stale] and hidden(tmp_path) == []
    new = tmp_path / "new"
    w = start(WRITE_FOLDER, new)
    w.kill()
    with OutputLock(new, "train") as lock:
        lock.acquire()
        assert remove_run_temporaries(new) == [w.what]
    assert hidden(tmp_path) == []


def test_a_run_check_under_its_own_lock_restores_an_output_a_killed_replacement_set_aside(tmp_path):
    """A replacement of the folder RUN sets the finished one aside (.RUN.X.old) and renames its
    successor in; killed between the two, RUN is missing and the set-aside folder is the only copy.
    The training's check of RUN (under RUN's lock, held by this process) puts it back instead of
    deleting it, and the check then refuses the folder as not empty: nothing is lost."""
    from hsicam.errors import InputError
    from hsicam.io import OutputLock
    from hsicam.runs.folder import check_run_dir, remove_run_temporaries

    run = tmp_path / "run"
    aside = tmp_path / ".run.0a1b2c3d.old"
    aside.mkdir()
    (aside / "config.yaml").write_text("seed: 3\n")
    killed_tmp = tmp_path / ".run.0a1b2c3d.tmpdir"  # the successor, half written
    killed_tmp.mkdir()
    with OutputLock(run, "train") as lock:
        lock.acquire()
        assert remove_run_temporaries(run) == [killed_tmp]
        assert (run / "config.yaml").read_text() == "seed: 3\n" and not aside.exists()
        with pytest.raises(InputError, match="not empty|holds"):
            check_run_dir(run, resume=False)
    assert (run / "config.yaml").read_text() == "seed: 3\n"
    # RUN present: a set-aside copy is a leftover of a finished replacement, and goes
    aside.mkdir()
    with OutputLock(run, "train") as lock:
        lock.acquire()
        assert remove_run_temporaries(run) == [aside]
    assert hidden(tmp_path) == [] and (run / "config.yaml").is_file()


# ------------------------------------------------------------------------------------------------
# An experiment's folder (session 54 review: `hsicam experiment` held no lock on it)
# ------------------------------------------------------------------------------------------------
HOLD_EXPERIMENT = """
from hsicam.io import OutputLock

with OutputLock(sys.argv[3], "experiment") as lock:
    lock.acquire()
    pause(sys.argv[3])
"""

LOCK_PROBE = ("import sys\nfrom hsicam.io import OutputLock\ntry:\n    OutputLock(sys.argv[1], 'experiment').acquire()\n"
              "    print('free')\nexcept Exception as exc:\n    print(exc)")


def test_an_experiment_holds_its_folder_from_its_checks_to_its_marker(tmp_path, monkeypatch, capsys):
    """Two `hsicam experiment` into one folder both ran (experiment.json from one, table.md maybe from the other,
    marked complete all the same): while one trains, another process taking the folder is refused, naming it."""
    import hsicam.engine.experiments as experiments
    from hsicam.cli import main

    out = tmp_path / "new" / "exp"  # its parent too is new (as runs/experiments/ is at first): locked all the same
    seen = []

    def training(run, cfg, *a, **k):  # while the experiment trains: can another process take its folder?
        seen.append(subprocess.run([sys.executable, "-c", LOCK_PROBE, str(out)], capture_output=True, text=True,
                                   env=cli_env()).stdout.strip())
        raise KeyboardInterrupt  # enough: nothing is trained

    monkeypatch.setattr(experiments, "ensure_trained", training)
    assert main(["experiment", "ablation", "--scale", "tiny", "--out", str(out)]) == 130
    assert seen and seen[0].startswith(f"{out}: being written by another process (hsicam experiment, pid "
                                       f"{os.getpid()}, since "), seen
    # let go on the way out (the lock file removed), and the folders it made, empty, removed with it
    assert not out.parent.exists()


def test_an_experiment_is_refused_while_another_process_writes_its_folder(tmp_path, start, monkeypatch):
    """run_experiment (the library call that `hsicam experiment` makes) took no lock: with the folder held by
    another process it cleared the folder's marker and trained into it. Now one line naming that process, before
    the folder is touched."""
    import hsicam.engine.experiments as experiments

    out = tmp_path / "exp"
    (out / "runs").mkdir(parents=True)
    (out / ".complete").write_text('{"complete": true, "command": "experiment"}')
    before = sorted(p.name for p in out.rglob("*"))

    def training(*a, **k):
        raise AssertionError("the experiment started in a folder another process writes")

    monkeypatch.setattr(experiments, "ensure_trained", training)
    w = start(HOLD_EXPERIMENT, out)
    with pytest.raises(hio.InputError) as exc:
        experiments.run_experiment("ablation", "tiny", out)
    assert re.fullmatch(rf"{re.escape(str(out))}: being written by another process \(hsicam experiment, pid {w.pid}, "
                        rf"since [0-9-]+ [0-9:]+\); wait for it or stop it", str(exc.value)), str(exc.value)
    assert sorted(p.name for p in out.rglob("*")) == before and (out / ".complete").is_file()
    assert_ok(w.go())


def test_a_demo_under_a_new_parent_holds_its_folder(tmp_path, monkeypatch):
    """The demo's lock file lies beside its folder: under a parent that did not exist yet (runs/ in a fresh clone)
    nothing was locked, and a second demo could run into the same folder."""
    import hsicam.engine.demo as demo
    from hsicam.config import load_config

    out = tmp_path / "runs" / "demo"
    seen = []

    def training(run, cfg, *a, **k):  # while the demo trains: can another process take its folder?
        seen.append(subprocess.run([sys.executable, "-c", LOCK_PROBE, str(out)], capture_output=True, text=True,
                                   env=cli_env()).stdout.strip())
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "ensure_trained", training)
    with pytest.raises(KeyboardInterrupt):
        demo.run_demo(load_config("tiny"), out)
    assert seen and seen[0].startswith(f"{out}: being written by another process (hsicam demo, pid {os.getpid()}"), seen
    assert hidden(out.parent) == []


def test_a_report_is_refused_while_another_process_rewrites_its_evaluation_folder(start, tmp_path):
    """`hsicam report DIR` while `evaluate --out DIR` replaced DIR took no lock: its report was lost with the old
    folder, failed naming its own PNG, or showed the old scores beside the new results.json, by the moment it ran
    (session 73's hunt). It takes DIR's output lock: refused in one line naming the writer while one holds it, and
    it goes on once it has let go."""
    from report_files import evaluation, folder_with

    ev = folder_with(tmp_path, "results.json", evaluation())
    writer = start("""
from hsicam.io import OutputLock

with OutputLock(sys.argv[3], "evaluate") as lock:
    lock.acquire()
    pause(sys.argv[3])
""", ev)
    res = run_cli_in_process("report", str(ev))
    assert res.returncode == 2 and f"pid {writer.pid}" in error_line(res), res.stderr
    assert not (ev / "report").exists()
    assert_ok(writer.go())
    assert_ok(run_cli_in_process("report", str(ev)))
    assert (ev / "report" / "index.html").is_file()


def test_an_evaluate_is_refused_at_its_start_while_a_report_reads_its_folder_and_dot_is_the_folder(start, tmp_path,
                                                                                                    monkeypatch):
    """evaluate took its --out folder's lock only for its last write: a report holding it then (since it locks the
    folder it reads) made the evaluation fail after all its scoring (the review of session 73). evaluate holds it from
    its start, so it is refused at once. And `report .` from inside the folder locked ".", a lock file inside the
    folder that an evaluate did not see: the lock is the folder's, whatever path names it."""
    from report_files import evaluation, folder_with

    ev = folder_with(tmp_path, "results.json", evaluation())
    reporter = start("""
from hsicam.io import OutputLock

with OutputLock(sys.argv[3], "report") as lock:
    lock.acquire()
    pause(sys.argv[3])
""", ev)
    res = run_cli_in_process("evaluate", "--config", "tiny", "--method", "dd-cassi-gaptv", "--out", str(ev))
    assert res.returncode == 2 and f"hsicam report, pid {reporter.pid}" in error_line(res), res.stderr
    assert "[1/" not in res.stdout + res.stderr  # refused before any scene was scored
    assert_ok(reporter.go())
    writer = start("""
from hsicam.io import OutputLock

with OutputLock(sys.argv[3], "evaluate") as lock:
    lock.acquire()
    pause(sys.argv[3])
""", ev)
    monkeypatch.chdir(ev)
    res = run_cli_in_process("report", ".")
    assert res.returncode == 2 and f"pid {writer.pid}" in error_line(res), res.stderr
    assert not list(ev.glob("*hsicam-lock"))  # no lock file of its own inside the folder
    assert_ok(writer.go())
