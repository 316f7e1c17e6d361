"""The lock of a run folder: one process at a time trains in it (``fcntl.flock`` on :data:`LOCK_FILE`).

The training loop (:func:`hsicam.engine.loop.fit`, rank 0) holds it while it writes into the run;
another process that would train there is refused with one line before it touches anything
(:meth:`RunLock.acquire`, :func:`check_not_locked`). The kernel releases the lock when its holder
exits, however it exits (``kill -9`` too). The file is removed on release; one left by a killed
process holds no lock and is taken over. Where ``fcntl`` is missing (Windows) nothing is locked.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

from hsicam.devices import dist_env
from hsicam.errors import InputError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

#: The lock file inside a run folder (hidden: never a user's file nor a sign of an interrupted run).
LOCK_FILE = ".hsicam-lock"

#: The locks this process holds, by (device, inode) of their file.
_HELD: dict[tuple[int, int], "RunLock"] = {}


def _other_rank() -> bool:
    """True in a process of a ``torchrun`` group other than rank 0: rank 0 locks for the group, and
    its lock is its peers' own, not another training's."""
    return dist_env()[0] != 0


def _key(fd: int) -> tuple[int, int]:
    st = os.fstat(fd)
    return st.st_dev, st.st_ino


def _is_file_of(fd: int, path: Path) -> bool:
    """True while ``path`` still names the file open as ``fd`` (a released lock's file is removed)."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) == _key(fd)


def _refusal(run_dir: Path, path: Path) -> InputError:
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
        holder = f"pid {int(info['pid'])}, since {info['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        holder = "pid unknown"
    return InputError(f"{run_dir}: being trained by another process ({holder}); wait for it or stop it")


def check_not_locked(run_dir: str | Path) -> None:
    """InputError when another process holds the lock of ``run_dir``. Creates nothing. In a DDP
    group only rank 0 checks (its peers see its own lock)."""
    if fcntl is None or _other_rank():
        return
    path = Path(run_dir) / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return  # no lock file: nobody trains there
    try:
        if _key(fd) in _HELD:
            return  # this process's own
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            raise _refusal(Path(run_dir), path) from None
        except OSError:
            return  # a file system without locks
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


class RunLock:
    """This process's lock of the run folder ``run_dir``: a context manager that releases it on
    exit; ``enabled=False`` locks nothing, nor does a DDP rank other than 0 (rank 0 locks for its
    group). Re-entrant: acquiring a lock this process already holds does nothing, and releasing that
    inner one keeps the outer."""

    def __init__(self, run_dir: str | Path, enabled: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.enabled = enabled and not _other_rank()
        self._fd: int | None = None
        self._path: Path | None = None
        self._nested = False  # this process already held the lock when acquire was called

    def acquire(self, folder: str | Path | None = None) -> None:
        """Take the lock in ``folder`` (default: the run folder; a new run: the temporary folder
        that becomes it, then :meth:`moved`). InputError when another process holds it; no lock
        (a debug log) where the file cannot be created or locked."""
        if not self.enabled or self._fd is not None or self._nested:
            return
        if fcntl is None:
            log.debug("%s: no file locking on this platform; the run folder is not locked", self.run_dir)
            return
        path = Path(folder if folder is not None else self.run_dir) / LOCK_FILE
        try:
            st = os.stat(path)
            if (st.st_dev, st.st_ino) in _HELD:  # held by this process (e.g. the loop, then the linear step's refit)
                self._nested = True
                return
        except OSError:
            pass
        for _ in range(10):  # a few tries: another process's check_not_locked lets go at once
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                log.debug("%s: not locked (%s)", path, exc)
                return
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                time.sleep(0.02)
                continue
            except OSError as exc:
                os.close(fd)
                log.debug("%s: not locked (%s)", path, exc)
                return
            if _is_file_of(fd, path):
                break
            os.close(fd)  # released and removed by its holder meanwhile: lock the new file
        else:
            raise _refusal(self.run_dir, path)
        self._fd, self._path = fd, path
        _HELD[_key(fd)] = self
        try:
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps({"pid": os.getpid(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}).encode())
        except OSError:  # only the refusal's details (e.g. a full disk)
            pass

    def moved(self) -> None:
        """The folder the lock was taken in has been renamed into place as the run folder."""
        if self._fd is not None:
            self._path = self.run_dir / LOCK_FILE

    def release(self) -> None:
        """Remove the lock file (while it is still this lock's) and let go (a nested lock: nothing)."""
        self._nested = False
        fd, self._fd = self._fd, None
        if fd is None:
            return
        _HELD.pop(_key(fd), None)
        try:
            if self._path is not None and _is_file_of(fd, self._path):
                self._path.unlink()
        except OSError:
            pass
        finally:
            os.close(fd)

    def __enter__(self) -> "RunLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
