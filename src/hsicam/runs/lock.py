"""The lock of a run folder: one process at a time trains in it (``fcntl.flock`` on :data:`LOCK_FILE`).

The training loop (:func:`hsicam.engine.loop.fit`, rank 0) holds it while it writes into the run;
another process that would train there is refused with one line before it touches anything
(:meth:`RunLock.acquire`, :func:`check_not_locked`). The kernel releases the lock when its holder
exits, however it exits (``kill -9`` too). The file is removed on release; one left by a killed
process holds no lock and is taken over. Where ``fcntl`` is missing (Windows) nothing is locked.
The lock files themselves (taking, testing, the refusal's line) are :mod:`hsicam.io`'s, shared
with the lock of a folder output being written (:class:`hsicam.io.OutputLock`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from hsicam.devices import dist_env
from hsicam.io import LockHeld, held_elsewhere, held_here, lock_file, lock_refusal, unlock_file

log = logging.getLogger(__name__)

#: The lock file inside a run folder (hidden: never a user's file nor a sign of an interrupted run).
LOCK_FILE = ".hsicam-lock"


def _other_rank() -> bool:
    """True in a process of a ``torchrun`` group other than rank 0: rank 0 locks for the group, and
    its lock is its peers' own, not another training's."""
    return dist_env()[0] != 0


def _refusal(run_dir: Path, path: Path):
    return lock_refusal(run_dir, path, "train")


def check_not_locked(run_dir: str | Path) -> None:
    """InputError when another process holds the lock of ``run_dir``. Creates nothing. In a DDP
    group only rank 0 checks (its peers see its own lock)."""
    if _other_rank():
        return
    path = Path(run_dir) / LOCK_FILE
    if held_elsewhere(path):
        raise _refusal(Path(run_dir), path)


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
        path = Path(folder if folder is not None else self.run_dir) / LOCK_FILE
        if held_here(path):  # held by this process (e.g. the loop, then the linear step's refit)
            self._nested = True
            return
        try:
            fd = lock_file(path)  # a few tries: another process's check_not_locked lets go at once
        except LockHeld:
            raise _refusal(self.run_dir, path) from None
        if fd is not None:
            self._fd, self._path = fd, path

    def moved(self) -> None:
        """The folder the lock was taken in has been renamed into place as the run folder."""
        if self._fd is not None:
            self._path = self.run_dir / LOCK_FILE

    def release(self) -> None:
        """Remove the lock file (while it is still this lock's) and let go (a nested lock: nothing)."""
        self._nested = False
        fd, self._fd = self._fd, None
        if fd is not None:
            unlock_file(fd, self._path)

    def __enter__(self) -> "RunLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
