"""hsicam.io: output-path checks, atomic files and folders, completion markers, stale temporaries."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import hsicam.io as hio
from cli_helpers import unprivileged_prefix
from hsicam.errors import InputError
from hsicam.io import (
    COMPLETE_MARKER,
    atomic_open,
    atomic_output,
    atomic_path,
    check_output_path,
    cleanup_stale_temporaries,
    clear_complete,
    is_complete,
    is_temporary,
    mark_complete,
    write_json,
)

SRC = str(Path(hio.__file__).parents[1])


def one_line(exc: pytest.ExceptionInfo, *words: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    for w in words:
        assert w in msg, msg
    return msg


def python(code: str, *args: str, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([SRC, os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([*prefix, sys.executable, "-c", textwrap.dedent(code), *args],
                          capture_output=True, text=True, timeout=120, env=env)


def hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ------------------------------------------------------------------------------------------------
# No import-time side effects; permissions follow the umask
# ------------------------------------------------------------------------------------------------
def test_import_does_not_touch_the_umask(tmp_path):
    res = python("""
        import os, stat, sys
        def forbidden(*args):
            raise AssertionError("os.umask called")
        os.umask(0o027)
        real, os.umask = os.umask, forbidden
        import hsicam.io as hio
        hio.write_json(sys.argv[1] + "/a.json", {"x": 1})
        with hio.atomic_output(sys.argv[1] + "/d") as d:
            (d / "f.txt").write_text("x")
        print(oct(stat.S_IMODE(os.stat(sys.argv[1] + "/a.json").st_mode)),
              oct(stat.S_IMODE(os.stat(sys.argv[1] + "/d").st_mode)))
    """, str(tmp_path))
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["0o640", "0o750"]  # 0o666 / 0o777 under umask 027


def test_outputs_get_the_usual_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", [1])
        with atomic_output(tmp_path / "out") as d:
            (d / "x.txt").write_text("x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o755


def test_weights_files_get_the_usual_permissions_and_leave_no_temporary(tmp_path):
    """Checkpoint weights followed the umask as every other output does: safetensors' own writer made a
    0600 file (a group sharing the run could not read it) through a .tmpXXXXXX of its own that a kill left."""
    import torch
    from safetensors.torch import load_file

    from hsicam.runs.checkpoint import save_safetensors

    old = os.umask(0o002)
    try:
        save_safetensors(tmp_path / "w.safetensors", {"a": torch.arange(6.0), "b": torch.ones(2, 3)}, {"k": "v", "j": "u"})
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "w.safetensors").stat().st_mode) == 0o664
    assert [p.name for p in tmp_path.iterdir()] == ["w.safetensors"]
    assert torch.equal(load_file(tmp_path / "w.safetensors")["a"], torch.arange(6.0))


# ------------------------------------------------------------------------------------------------
# check_output_path
# ------------------------------------------------------------------------------------------------
def test_check_output_path_accepts_usable_paths(tmp_path):
    (tmp_path / "file.h5").write_bytes(b"x")
    (tmp_path / "dir").mkdir()
    assert check_output_path(tmp_path / "file.h5", "file") == tmp_path / "file.h5"  # replaced atomically
    assert check_output_path(tmp_path / "dir", "dir") == tmp_path / "dir"
    assert check_output_path(tmp_path / "new" / "deeper" / "x.h5", "file")
    assert check_output_path(tmp_path / "new" / "deeper", "dir")
    assert not (tmp_path / "new").exists()  # a check creates nothing
    with pytest.raises(ValueError):
        check_output_path(tmp_path, "folder")


def test_check_output_path_refuses(tmp_path):
    f = tmp_path / "results.json"
    f.write_text("{}")
    d = tmp_path / "out"
    d.mkdir()
    cases = [
        ((f, "dir"), [str(f), "existing file", "folder is needed"]),
        ((d, "file"), [str(d), "existing folder", "file is needed"]),
        ((f / "x.h5", "file"), [str(f / "x.h5"), f"inside {f}", "which is a file"]),
        ((f / "a" / "b", "dir"), [str(f / "a" / "b"), f"inside {f}"]),
        (("", "file"), ["empty"]),
    ]
    for args, words in cases:
        with pytest.raises(InputError) as exc:
            check_output_path(*args)
        one_line(exc, *words)


def test_atomic_writers_turn_os_errors_into_one_line(tmp_path):
    f = tmp_path / "plain.txt"
    f.write_text("x")
    with pytest.raises(InputError) as exc:
        write_json(f / "a.json", {})
    one_line(exc, str(f / "a.json"), "which is a file")
    with pytest.raises(InputError) as exc:
        with atomic_output(f / "d"):
            pass
    one_line(exc, "which is a file")
    assert f.read_text() == "x"


def test_unwritable_folders(tmp_path):
    prefix = unprivileged_prefix()
    if prefix is None:
        pytest.skip("running as root without setpriv: chmod cannot make a folder unwritable here")
    ro = tmp_path / "ro"
    ro.mkdir()
    (ro / "old.json").write_text("{}")
    ro.chmod(0o500)
    try:
        res = python("""
            import os, sys
            from pathlib import Path
            from hsicam.errors import InputError
            from hsicam.io import atomic_output, check_output_path, write_json
            ro = Path(sys.argv[1])
            assert not os.access(ro, os.W_OK), "permissions are not enforced in this process"
            checks = [lambda: check_output_path(ro, "dir"), lambda: check_output_path(ro / "new", "dir"),
                      lambda: check_output_path(ro / "a" / "b" / "x.h5", "file"),
                      lambda: check_output_path(ro / "old.json", "file"),
                      lambda: write_json(ro / "x.json", {}), lambda: atomic_output(ro / "d").__enter__()]
            for check in checks:
                try:
                    check()
                    print("accepted")
                except InputError as exc:
                    print(exc)
        """, str(ro), prefix=prefix)
    finally:
        ro.chmod(0o700)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 6, res.stdout
    assert "not writable" in lines[0] and lines[0].startswith(str(ro))
    for line in lines[1:]:
        assert f"the folder {ro} is not writable" in line, line
    assert sorted(p.name for p in ro.iterdir()) == ["old.json"]


# ------------------------------------------------------------------------------------------------
# Atomic files
# ------------------------------------------------------------------------------------------------
def test_atomic_path_success_and_failure(tmp_path):
    target = tmp_path / "a" / "b" / "x.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            assert is_temporary(tmp.name) and tmp.suffix == ".txt" and tmp.parent == target.parent
            tmp.write_text("half")
            raise RuntimeError("writer failed")
    assert not (tmp_path / "a").exists()  # the temporary and the folders made for it are gone
    with atomic_open(target) as fh:
        fh.write("whole")
    assert target.read_text() == "whole" and hidden(target.parent) == []
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(target) as fh:
            fh.write("new")
            raise KeyboardInterrupt
    assert target.read_text() == "whole" and hidden(target.parent) == []


def test_atomic_path_refuses_an_existing_folder_before_the_writer_runs(tmp_path):
    """An output file named like an existing folder: os.replace raised IsADirectoryError only after the writer had
    written the whole temporary file (Python's error, not one line naming the path). Refused now before the writer
    runs; the folder and what it holds are untouched."""
    folder = tmp_path / "cube.h5"
    folder.mkdir()
    (folder / "keep.txt").write_text("mine")
    wrote = []
    with pytest.raises(InputError, match=r"cube\.h5: is an existing folder; a file is needed here$"):
        with atomic_path(folder) as tmp:
            wrote.append(tmp)
    assert wrote == [] and sorted(p.name for p in tmp_path.iterdir()) == ["cube.h5"]
    assert [p.name for p in folder.iterdir()] == ["keep.txt"]
    (tmp_path / "link.h5").symlink_to("cube.h5")  # a link is written through: to a folder, the same refusal
    with pytest.raises(InputError, match="is an existing folder"):
        with atomic_open(tmp_path / "link.h5") as fh:
            fh.write("x")


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="reads which file an fd is from /proc/self/fd")
def test_atomic_files_are_fsynced_before_the_rename_and_their_folder_after_it(tmp_path, monkeypatch):
    """``atomic_path``'s promise, for the writers of checkpoints (safetensors weights) and of the run's
    manifest (JSON): the temporary file, whole, is fsynced before ``os.replace`` puts it in place, and the
    folder holding it is fsynced after the rename (a crash then finds the old file or the whole new one,
    never an empty new name). Recorded through os.fsync and os.replace, in order."""
    import torch

    from hsicam.runs.checkpoint import save_safetensors

    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        target = Path(os.readlink(f"/proc/self/fd/{fd}"))
        events.append(("fsync", target, target.read_bytes() if target.is_file() else None))
        return real_fsync(fd)

    def replace(src, dst, **kwargs):
        events.append(("replace", Path(src), Path(dst)))
        return real_replace(src, dst, **kwargs)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    folder = (tmp_path / "run").resolve()
    writers = {"checkpoints.json": lambda p: write_json(p, {"format": "m", "checkpoints": [1, 2]}),
               "model.safetensors": lambda p: save_safetensors(p, {"w": torch.arange(5.0)}, {"k": "v", "j": "u"})}
    for name, write in writers.items():
        for _ in range(2):  # a new file, then one replaced
            events.clear()
            write(folder / name)
            final = (folder / name).read_bytes()
            renames = [e for e in events if e[0] == "replace"]
            assert len(renames) == 1 and renames[0][2] == folder / name, events
            tmp = renames[0][1]
            assert tmp.parent == folder and is_temporary(tmp.name)
            i = events.index(renames[0])
            synced_tmp = [e for e in events[:i] if e[0] == "fsync" and e[1] == tmp]
            assert synced_tmp and synced_tmp[-1][2] == final, (name, events)  # the whole temporary, before the rename
            assert ("fsync", folder, None) in events[i + 1 :], (name, events)  # its folder, after the rename


# ------------------------------------------------------------------------------------------------
# Atomic folders and markers
# ------------------------------------------------------------------------------------------------
def test_atomic_output_folder(tmp_path):
    out = tmp_path / "new" / "eval"
    with atomic_output(out, marker={"command": "evaluate"}) as d:
        assert d.parent == out.parent and is_temporary(d.name) and not out.exists()
        (d / "results.json").write_text("{}")
    assert sorted(p.name for p in out.iterdir()) == [COMPLETE_MARKER, "results.json"]
    assert is_complete(out)
    assert json.loads((out / COMPLETE_MARKER).read_text()) == {"complete": True, "command": "evaluate",
                                                               "files": ["results.json"]}
    assert hidden(out.parent) == []
    with atomic_output(tmp_path / "plain", marker=False) as d:
        (d / "x").write_text("x")
    assert not is_complete(tmp_path / "plain")


def test_atomic_output_failure_leaves_nothing(tmp_path):
    out = tmp_path / "a" / "b" / "eval"
    for exc_type in (RuntimeError, KeyboardInterrupt):
        with pytest.raises(exc_type):
            with atomic_output(out) as d:
                (d / "results.json").write_text("{}")
                raise exc_type()
        assert not (tmp_path / "a").exists()


def test_atomic_output_replaces_only_what_it_may(tmp_path):
    out = tmp_path / "eval"
    out.mkdir()  # an empty folder is simply replaced
    with atomic_output(out) as d:
        (d / "v1.txt").write_text("1")
    with pytest.raises(InputError) as exc:  # a completed output: only with overwrite=True
        with atomic_output(out) as d:
            raise AssertionError("must not run")
    one_line(exc, str(out), "completed output")
    with atomic_output(out, overwrite=True) as d:
        (d / "v2.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [COMPLETE_MARKER, "v2.txt"] and hidden(tmp_path) == []
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("precious")
    with pytest.raises(InputError) as exc:  # a user's own folder is never deleted
        with atomic_output(mine, overwrite=True):
            raise AssertionError("must not run")
    one_line(exc, str(mine), "not empty")
    assert (mine / "thesis.tex").read_text() == "precious"
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="existing file"):
        with atomic_output(f):
            raise AssertionError("must not run")


def test_atomic_output_replaces_only_its_own_command_and_files(tmp_path):
    """A completed folder is replaced only by the command its marker names, and only while it holds
    nothing but the entries the marker lists (and a derived report/ or hidden temporaries)."""
    out = tmp_path / "ev"
    with atomic_output(out, marker={"command": "evaluate"}) as d:
        (d / "results.json").write_text("1")
    with pytest.raises(InputError) as exc:
        with atomic_output(out, overwrite=True, marker={"command": "psf"}):
            raise AssertionError("must not run")
    one_line(exc, str(out), "holds the output of hsicam evaluate, not of hsicam psf")
    with atomic_output(out / "report", marker={"command": "report"}) as d:  # derived: goes with the folder
        (d / "index.html").write_text("r")
    (out / ".results.abcd1234.tmp.json").write_text("")  # a killed writer's temporary
    (out / ".DS_Store").write_bytes(b"\0")  # a file browser's metadata: not the user's work
    (out / "._results.json").write_bytes(b"\0")
    with atomic_output(out, overwrite=True, marker={"command": "evaluate"}) as d:
        (d / "results.json").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [COMPLETE_MARKER, "results.json"]
    (out / "notes.txt").write_text("mine")
    (out / "myplots").mkdir()
    with pytest.raises(InputError) as exc:
        with atomic_output(out, overwrite=True, marker={"command": "evaluate"}):
            raise AssertionError("must not run")
    one_line(exc, str(out), "holds myplots, notes.txt, which hsicam evaluate did not write", "move them")
    assert (out / "notes.txt").read_text() == "mine" and (out / "results.json").read_text() == "2"
    old = tmp_path / "old"  # an older marker (no command, no files): replaced as before
    old.mkdir()
    (old / "a.txt").write_text("a")
    mark_complete(old)
    with atomic_output(old, overwrite=True, marker={"command": "psf"}) as d:
        (d / "b.txt").write_text("b")
    assert sorted(p.name for p in old.iterdir()) == [COMPLETE_MARKER, "b.txt"]


def test_atomic_output_restores_the_old_folder_if_the_swap_fails(tmp_path, monkeypatch):
    out = tmp_path / "eval"
    with atomic_output(out) as d:
        (d / "v1.txt").write_text("1")
    real, calls = os.rename, []

    def flaky(src, dst):
        calls.append((Path(src).name, Path(dst).name))
        if len(calls) == 2:  # old → aside worked; new → place fails
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "rename", flaky)
    with pytest.raises(OSError):
        with atomic_output(out, overwrite=True) as d:
            (d / "v2.txt").write_text("2")
    monkeypatch.undo()
    assert sorted(p.name for p in out.iterdir()) == [COMPLETE_MARKER, "v1.txt"] and hidden(tmp_path) == []


def test_atomic_file_output(tmp_path):
    with atomic_output(tmp_path / "x.h5", "file") as tmp:
        tmp.write_bytes(b"data")
    assert (tmp_path / "x.h5").read_bytes() == b"data" and hidden(tmp_path) == []


def test_markers(tmp_path):
    assert not is_complete(tmp_path)
    p = mark_complete(tmp_path, {"files": 3})
    assert p == tmp_path / COMPLETE_MARKER and is_complete(tmp_path)
    assert json.loads(p.read_text()) == {"complete": True, "files": 3}
    clear_complete(tmp_path)
    assert not is_complete(tmp_path)
    clear_complete(tmp_path)  # idempotent


# ------------------------------------------------------------------------------------------------
# A killed writer, then the cleanup
# ------------------------------------------------------------------------------------------------
def test_killed_writer_leaves_only_a_hidden_temporary_that_cleanup_removes(tmp_path):
    res = python("""
        import os, signal, sys
        from pathlib import Path
        from hsicam.io import atomic_output, atomic_open
        out = Path(sys.argv[1])
        with atomic_open(out / "model.safetensors", "wb") as fh:
            fh.write(b"half")
            with atomic_output(out / "eval") as d:
                (d / "results.json").write_text("{")
                os.kill(os.getpid(), signal.SIGKILL)
    """, str(tmp_path))
    assert res.returncode == -9
    assert not (tmp_path / "eval").exists() and not (tmp_path / "model.safetensors").exists()
    left = hidden(tmp_path)
    # the file's temporary, the folder's and the folder's lock file (.eval.hsicam-lock), all hidden temporaries
    assert len(left) == 3 and all(is_temporary(n) for n in left), left
    keep = [tmp_path / ".gitignore", tmp_path / COMPLETE_MARKER, tmp_path / ".a.tmp.h5", tmp_path / "x.12345678.tmp"]
    for k in keep:
        k.write_text("keep")
    assert cleanup_stale_temporaries(tmp_path, min_age_s=3600) == []  # too fresh: maybe still being written
    removed = cleanup_stale_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == left
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(k.name for k in keep)
    assert cleanup_stale_temporaries(tmp_path / "missing") == []


@pytest.mark.parametrize("next_command", ["prepare_output", "cleanup"])
def test_a_kill_between_the_two_renames_of_a_replacement_keeps_the_previous_output(tmp_path, next_command):
    """A replacement sets the old folder aside (.NAME.X.old), then renames the new one into place: a
    kill between the two renames used to leave no output, and the next command deleted the old one."""
    out = tmp_path / "ev"
    with atomic_output(out, marker={"command": "evaluate"}) as d:
        (d / "results.json").write_text('{"psnr": 40}')
    res = python("""
        import os, signal, sys
        from pathlib import Path
        from hsicam.io import atomic_output
        renames = []
        real = os.rename
        def rename(a, b):
            renames.append((a, b))
            if len(renames) == 2:  # the new folder onto the output: killed first
                os.kill(os.getpid(), signal.SIGKILL)
            real(a, b)
        os.rename = rename
        with atomic_output(Path(sys.argv[1]), overwrite=True, marker={"command": "evaluate"}) as d:
            (d / "results.json").write_text('{"psnr": 41}')
    """, str(out))
    assert res.returncode == -9, res.stderr
    assert not out.exists() and any(n.endswith(".old") for n in hidden(tmp_path))
    if next_command == "prepare_output":
        from hsicam.cli import prepare_output

        prepare_output(out, "dir", replace=True, command="evaluate")
    else:
        cleanup_stale_temporaries(tmp_path)
    assert json.loads((out / "results.json").read_text()) == {"psnr": 40}  # the previous output, restored
    assert is_complete(out) and hidden(tmp_path) == []  # the killed command's new folder is gone


def test_cleanup_recursive(tmp_path):
    (tmp_path / "ckpt" / "step_10").mkdir(parents=True)
    stale = tmp_path / "ckpt" / "step_10" / ".model.0a1b2c3d.tmp.safetensors"
    stale.write_bytes(b"")
    assert cleanup_stale_temporaries(tmp_path) == []
    assert cleanup_stale_temporaries(tmp_path, recursive=True) == [stale] and not stale.exists()


def test_same_path_follows_links_and_compares_missing_paths_resolved(tmp_path):
    from hsicam.io import same_path

    (tmp_path / "a").write_text("x")
    (tmp_path / "b").write_text("x")  # equal bytes, another file
    (tmp_path / "link").symlink_to(tmp_path / "a")
    assert same_path(tmp_path / "a", tmp_path / "link") and not same_path(tmp_path / "a", tmp_path / "b")
    assert same_path(tmp_path / "gone", tmp_path / "sub" / ".." / "gone")  # neither exists: by resolved path
    assert not same_path(tmp_path / "gone", tmp_path / "a")


# ------------------------------------------------------------------------------------------------
# Disk errors: one table (hsicam.io), read by the command line's line and a checkpoint's failure
# ------------------------------------------------------------------------------------------------
def test_the_disk_errors_have_one_table_that_the_cli_and_checkpoints_read(monkeypatch):
    import errno

    from hsicam.cli import error_line
    from hsicam.io import DISK_ERRNOS, DISK_HINTS, NO_SPACE_ERRNOS, OS_ERROR_HINTS
    from hsicam.runs.checkpoint import _resume_hint

    assert DISK_ERRNOS == set(DISK_HINTS) == {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS}
    assert NO_SPACE_ERRNOS < DISK_ERRNOS and DISK_HINTS.items() <= OS_ERROR_HINTS.items()
    for code, hint in OS_ERROR_HINTS.items():
        exc = OSError(code, os.strerror(code), "/d/x.npy")
        assert error_line(exc) == f"/d/x.npy: {os.strerror(code)} ({hint})"
        frees = "free some space" in hint  # the advice of the line and of a checkpoint's failure agree
        assert frees == (code in NO_SPACE_ERRNOS)
        assert _resume_hint(exc) == ("free some space, then resume the run" if frees else
                                     "resume the run once it can be written")
    monkeypatch.setitem(OS_ERROR_HINTS, errno.ENOSPC, "one place")  # the CLI has no copy of its own
    assert error_line(OSError(errno.ENOSPC, "x", "/d/x.npy")) == f"/d/x.npy: {os.strerror(errno.ENOSPC)} (one place)"


def test_free_space_short_looks_past_a_broken_link(tmp_path):
    """A path through a dangling symlink (e.g. a cache dir on an unmounted disk) is measured at the nearest
    folder that exists, as the three checks it replaced did, not refused with FileNotFoundError (review)."""
    from hsicam.io import free_space_short

    link = tmp_path / "cache"
    link.symlink_to(tmp_path / "gone" / "disk")
    assert free_space_short(link / "data", 1) is None
    assert free_space_short(link / "data", 1 << 62) == shutil.disk_usage(tmp_path).free


def test_json_number_is_a_finite_number_as_python_reads_json():
    """Python's json reads NaN/Infinity as floats and any integer at all; a bool is an int to isinstance."""
    import json

    from hsicam.io import json_number

    values = json.loads('[1, 2.5, -3e2, NaN, Infinity, -Infinity, true, "1", null, 1' + "0" * 400 + "]")
    assert [json_number(v) for v in values] == [True, True, True, False, False, False, False, False, False, False]
    assert [json_number(v, finite=False) for v in values] == [True, True, True, True, True, True, False, False, False,
                                                             True]


# ------------------------------------------------------------------------------------------------
# Session 56: guards for mutants of io that the suite let through (helper mut5a's I01-I03, I11, I12)
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("need, margin", [(10**9, 10**8), (10**7, 1 << 26)])
def test_free_space_short_keeps_a_tenth_of_the_need_or_64_mib_free_beyond_it(monkeypatch, tmp_path, need, margin):
    """Room means need + max(need / 10, 64 MiB) free: one byte less is short (the free bytes are returned), exactly
    that is enough; the refusal's text adds the two up."""
    from collections import namedtuple

    from hsicam.io import free_space_short, free_space_text
    from hsicam.memory import format_bytes

    usage = namedtuple("usage", "total used free")
    for free, short in ((need + margin - 1, True), (need + margin, False)):
        monkeypatch.setattr(shutil, "disk_usage", lambda path, free=free: usage(10**13, 10**13 - free, free))
        assert free_space_short(tmp_path, need) == (free if short else None)
    text = free_space_text(need, need)
    assert f"and {format_bytes(margin)} more is kept free beyond it ({format_bytes(need + margin)} in all)" in text


def test_a_file_system_of_no_size_is_said_to_be_virtual_not_a_full_disk(monkeypatch, tmp_path):
    """An output under /sys (sysfs: 0 B in all, 0 B free) was refused as if its disk were full ("that disk has 0 B
    free; free some space"; session 70's hunt); with the output's path the text says what it is. A real disk that is
    full keeps its wording."""
    from collections import namedtuple

    from hsicam.io import free_space_text

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(0, 0, 0))
    assert free_space_text(10**6, 0, path=tmp_path / "c.h5").endswith(
        "but that file system stores no files (0 B in all: a virtual one, such as /sys or /proc)")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**12, 10**12, 0))
    assert free_space_text(10**6, 0, path=tmp_path / "c.h5").endswith("but that disk has 0 B free")
    assert free_space_text(10**6, 0).endswith("but that disk has 0 B free")  # no path: as before


def test_8_and_16_bit_pngs_round_to_the_nearest_level(tmp_path):
    """A value 0.6 of a level above level k is stored as k + 1 (rounded, not truncated), read back with imageio."""
    import imageio.v3 as iio
    import numpy as np

    from hsicam.io import png8_values, write_png16

    levels = np.array([[0.0, 1.6, 300.6, 65534.6]])
    write_png16(tmp_path / "g.png", levels / 65535.0)
    np.testing.assert_array_equal(iio.imread(tmp_path / "g.png"), [[0, 2, 301, 65535]])
    np.testing.assert_array_equal(png8_values(np.array([0.0, 1.6, 100.4, 254.6]) / 255.0), [0, 2, 100, 255])


def test_written_entries_lists_files_and_folders_with_a_slash_and_leaves_out_temporaries(tmp_path):
    """A marker's "files": every entry as a sorted POSIX path, a folder's ending in "/", hidden temporaries (a
    ``.NAME.XXXXXXXX.tmp`` file, a ``.tmpdir`` folder) left out; compared with a listing made here by hand."""
    from hsicam.io import written_entries

    (tmp_path / "sub" / "deep").mkdir(parents=True)
    (tmp_path / "a.json").write_text("{}")
    (tmp_path / "sub" / "b.npy").write_bytes(b"x")
    (tmp_path / "sub" / "deep" / "c.png").write_bytes(b"x")
    (tmp_path / ".a.Ab3dE6gH.tmp.json").write_text("{}")
    (tmp_path / ".run.Zz9yY8xX.tmpdir").mkdir()
    (tmp_path / ".run.Zz9yY8xX.tmpdir" / "inside").write_text("x")
    assert written_entries(tmp_path) == ["a.json", "sub/", "sub/b.npy", "sub/deep/", "sub/deep/c.png"]


@pytest.mark.parametrize("command, says", [("train", "being trained by another process (pid 42, since T0)"),
                                           ("evaluate", "being written by another process (hsicam evaluate, pid 42, "
                                                        "since T0)")])
def test_a_lock_refusal_says_trained_for_a_training_and_names_any_other_command(tmp_path, command, says):
    from hsicam.io import lock_refusal

    lock = tmp_path / ".lock"
    lock.write_text(json.dumps({"pid": 42, "since": "T0", "command": command}))
    assert str(lock_refusal("RUN", lock)) == f"RUN: {says}; wait for it or stop it"


def test_a_set_aside_output_is_not_restored_over_one_in_its_place(tmp_path):
    """``.NAME.XXXXXXXX.old`` goes back to NAME only when NAME is missing: a folder in its place, even an empty one
    (which a rename would silently replace), stays as it is."""
    from hsicam.io import restore_set_aside

    old = tmp_path / ".out.Ab3dE6gH.old"
    old.mkdir()
    (old / "previous.txt").write_text("old")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "current.txt").write_text("new")
    assert restore_set_aside(old) is False
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["current.txt"] and old.is_dir()
    (tmp_path / "out" / "current.txt").unlink()
    assert restore_set_aside(old) is False  # an empty folder in its place
    assert not any((tmp_path / "out").iterdir()) and old.is_dir()
    (tmp_path / "out").rmdir()
    assert restore_set_aside(old) is True
    assert (tmp_path / "out" / "previous.txt").read_text() == "old" and not old.exists()


# --------------------------------------------------------------------------------------------
# io.py: a folder's disk error, derived outputs, the list of a user's files
# --------------------------------------------------------------------------------------------
def test_a_full_disk_while_a_folder_is_written_names_the_folder_and_keeps_its_errno(tmp_path):
    import errno

    from hsicam.io import atomic_output

    out = tmp_path / "eval"
    with pytest.raises(OSError) as exc:
        with atomic_output(out):
            raise OSError(errno.ENOSPC, "No space left on device")  # as a write() reports it: no file named
    assert (exc.value.errno, exc.value.strerror, exc.value.filename) == (errno.ENOSPC, "No space left on device", str(out))
    assert not out.exists() and list(tmp_path.iterdir()) == []
    # an error that is not the disk's and names no file is left as it was: the folder is not its cause
    with pytest.raises(OSError) as exc:
        with atomic_output(out):
            raise OSError(errno.EACCES, "Permission denied")
    assert (exc.value.errno, exc.value.filename) == (errno.EACCES, None)


def _report_folder(folder, listed, present):
    """``folder/report/`` as ``hsicam report`` leaves it: its marker lists ``listed``; ``present`` files exist."""
    import json

    report = folder / "report"
    report.mkdir(parents=True)
    for name in present:
        (report / name).write_text("x")
    (report / ".complete").write_text(json.dumps({"complete": True, "command": "report", "files": listed}))
    return report


def test_clearing_the_derived_report_refuses_one_holding_a_users_file_and_removes_nothing(tmp_path):
    from hsicam.errors import InputError
    from hsicam.io import clear_derived

    report = _report_folder(tmp_path / "demo", ["index.html"], ["index.html", "my_notes.txt"])
    with pytest.raises(InputError) as exc:
        clear_derived(tmp_path / "demo")
    assert str(exc.value) == (f"{report}: holds my_notes.txt, which hsicam report did not write; it is made from "
                              f"{tmp_path / 'demo'}'s results and would be removed as out of date: move them")
    assert sorted(p.name for p in report.iterdir()) == [".complete", "index.html", "my_notes.txt"]
    # one holding only what its marker lists is removed
    (report / "my_notes.txt").unlink()
    assert clear_derived(tmp_path / "demo") == [report] and not report.exists()


def test_replacing_a_folder_with_seven_unlisted_files_names_five_and_counts_the_rest(tmp_path):
    import json

    from hsicam.errors import InputError
    from hsicam.io import check_replaceable

    out = tmp_path / "eval"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    (out / ".complete").write_text(json.dumps({"complete": True, "command": "evaluate", "files": ["metrics.json"]}))
    names = [f"mine_{i}.txt" for i in range(7)]
    for n in names:
        (out / n).write_text("x")
    with pytest.raises(InputError) as exc:
        check_replaceable(out, True, "evaluate")
    assert str(exc.value) == (f"{out}: holds {', '.join(names[:5])} and 2 more, which hsicam evaluate did not write; "
                              "choose another folder or move them")


def test_a_temporarys_own_temporary_left_by_a_kill_is_removed_by_the_rerun(tmp_path):
    """A file written atomically into a temporary name (reconstruct's preview) has a temporary of its own,
    "..c_rgb.X.tmp.Y.tmp.png": a SIGKILL left it, and remove_stale_siblings, which globbed ".c_rgb.*" only, never
    removed it (session 73's hunt). A real writer killed there; the rerun's cleanup removes both."""
    from hsicam.io import remove_stale_siblings

    res = python("""
        import os, signal, sys
        from pathlib import Path
        from hsicam.io import atomic_open, atomic_path
        out = Path(sys.argv[1]) / "c_rgb.png"
        with atomic_path(out) as tmp:
            with atomic_open(tmp, "wb") as fh:
                fh.write(b"half a png")
                os.kill(os.getpid(), signal.SIGKILL)
    """, str(tmp_path))
    assert res.returncode == -9
    left = hidden(tmp_path)
    assert any(n.startswith("..c_rgb.") for n in left), left
    removed = remove_stale_siblings(tmp_path / "c_rgb.png", "file")
    assert sorted(p.name for p in removed) == sorted(left) and hidden(tmp_path) == []
