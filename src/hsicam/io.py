"""Safe outputs: atomic files and folders, completion markers, output-path checks.

Every output is written to a hidden temporary sibling and renamed into place, so a killed process
never leaves a half-written file (or folder) where a later command would take it for a result:

- :func:`atomic_path` / :func:`atomic_open`: one file (``.NAME.XXXXXXXX.tmp.SUFFIX`` → ``NAME``).
- :func:`atomic_output`: a file or a whole folder (``.NAME.XXXXXXXX.tmpdir`` → ``NAME``); a
  folder gets its completion marker (:data:`COMPLETE_MARKER`) before it is renamed into place. The
  marker names the command that wrote the folder (``"command"``) and the entries it wrote
  (``"files"``: every file and sub-folder, as paths relative to it, a folder's ending in ``/``):
  :func:`check_replaceable` lets a command replace only its own output, and only while the folder
  holds nothing else, at any depth (a user's files added to it are never deleted).
- :func:`mark_complete` / :func:`is_complete` / :func:`read_marker` / :func:`clear_complete`: the
  marker for folders that are filled in place, file by file (write files, then mark; readers check
  the marker).
- :func:`cleanup_stale_temporaries` / :func:`remove_stale_siblings` / :func:`remove_if_stale`: remove
  the hidden temporaries a killed process left behind, never those a process is writing now (below).
- :class:`OutputLock`: one process at a time writes a folder output; :func:`lock_file` /
  :func:`unlock_file` / :func:`lock_refusal`: the ``fcntl.flock`` lock files it (and
  :class:`hsicam.runs.lock.RunLock`) is made of.
- :func:`check_output_path`: one-line :class:`~hsicam.errors.InputError` for an output path that
  cannot work (existing file where a folder is needed and vice versa, inside a file, not
  writable, a symbolic link that points nowhere or loops), to be called before any work starts.

An output given as a symbolic link is written in what the link leads to (:func:`follow_link`): the
link is kept, never replaced by a file or folder. An ``OSError`` raised while a file is written
(disk full, quota, read-only file system …) names the file it was to become, never the temporary.

**Temporaries in use.** A process writing a temporary holds an ``fcntl.flock`` lock that tells
it from the leftover of a killed process (the kernel lets go of a lock when its holder exits,
``kill -9`` too): a temporary file is locked itself while it is written; a folder output's
temporaries (``.tmpdir``, ``.old``) are covered by its lock file ``.NAME.hsicam-lock``
(:class:`OutputLock`), held from before the temporary folder is made until it is in place, so a
second writer of the folder is refused with one line naming the first. A cleanup locks what it
removes, so a writer never starts in a temporary that is being removed. Where ``fcntl`` is missing
(Windows) or the file system cannot lock, nothing is locked and a cleanup removes every temporary.

Importing this module has no side effects (the process umask is never touched: temporary files
are created with mode 0o666 and folders with 0o777, and the kernel applies the umask).
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import json
import logging
import math
import os
import re
import secrets
import shutil
import sys
import time
from pathlib import Path
from typing import IO, Any, Callable, Iterator

import numpy as np

from hsicam.errors import InputError

log = logging.getLogger(__name__)

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: nothing is locked
    fcntl = None  # type: ignore[assignment]

#: Name of the completion marker of an output folder.
COMPLETE_MARKER = ".complete"

#: The end of the lock file ``.NAME.hsicam-lock`` next to a folder output being written (:class:`OutputLock`).
OUTPUT_LOCK_SUFFIX = ".hsicam-lock"

# Hidden temporaries written by this module (and by the former mkstemp-based version, whose random
# part was also 8 characters): ".NAME.XXXXXXXX.tmp[.SUFFIX]", ".NAME.XXXXXXXX.tmpdir", ".NAME.XXXXXXXX.old",
# and the lock files of folder outputs ".NAME.hsicam-lock" (a run folder's own ".hsicam-lock" is none).
_TEMP_RE = re.compile(r"^\..*\.[A-Za-z0-9_]{8}\.(?:tmp(?:\..*)?|tmpdir|old)$|^\..+\.hsicam-lock$")
# The parts of a temporary's name: the output's stem, a file's suffix, "tmpdir" or "old" for a folder's.
_TEMP_PARTS = re.compile(r"^\.(?P<stem>.*)\.[A-Za-z0-9_]{8}\.(?:tmp(?P<suffix>\..*)?|(?P<folder>tmpdir|old))$")


# ------------------------------------------------------------------------------------------------
# Reading .npy files
# ------------------------------------------------------------------------------------------------
#: The first bytes of every ``.npy`` file.
NPY_MAGIC = b"\x93NUMPY"


def npy_content_problem(path: str | os.PathLike) -> str | None:
    """Why the file ``path`` is not a ``.npy`` file, judged by its first bytes ("an empty file", "a .npz archive",
    "no NumPy header"), or None when it starts as one. Checked before ``np.load``, which opens a zip archive
    and calls any other content "pickled data", advising ``allow_pickle``. An OSError reading it propagates."""
    with open(path, "rb") as fh:
        head = fh.read(len(NPY_MAGIC))
    if head == NPY_MAGIC:
        return None
    return "an empty file" if not head else "a .npz archive" if head.startswith(b"PK") else "no NumPy header"


# ------------------------------------------------------------------------------------------------
# Output-path check
# ------------------------------------------------------------------------------------------------
def _nearest_existing(p: Path, broken_links: bool = True) -> Path:
    """The nearest ancestor of ``p`` (or ``p`` itself) that exists in any form (``broken_links=False``: a
    link whose target is missing does not count, e.g. to measure the file system it would write on)."""
    for a in (p, *p.parents):
        try:
            if a.exists() or (broken_links and a.is_symlink()):
                return a
        except OSError:
            continue
    return Path(p.anchor or ".")


def free_space_short(path: str | os.PathLike, need_bytes: int, min_margin_bytes: int = 1 << 26) -> int | None:
    """The free bytes of the file system that ``path`` (or its nearest existing ancestor) is on, when
    they are fewer than ``need_bytes`` plus a margin (:func:`free_space_margin`); None when there is room. The
    one home of the free-space checks made before long work (dataset generation, ``evaluate --save``,
    ``reconstruct``): each caller words its own refusal, with :func:`free_space_text`."""
    free = shutil.disk_usage(_nearest_existing(Path(path).absolute(), broken_links=False)).free
    return free if free < need_bytes + free_space_margin(need_bytes, min_margin_bytes) else None


def free_space_margin(need_bytes: int, min_margin_bytes: int = 1 << 26) -> int:
    """The bytes :func:`free_space_short` keeps free beyond ``need_bytes``: a tenth of it, at least
    ``min_margin_bytes`` (other writers, the file system's own blocks)."""
    return max(need_bytes // 10, min_margin_bytes)


def free_space_text(need_bytes: int, free_bytes: int, min_margin_bytes: int = 1 << 26,
                    path: str | os.PathLike | None = None) -> str:
    """How a refusal of :func:`free_space_short` states the numbers: what the output needs, the margin kept
    free beyond it, and what the disk has (which may exceed the output alone: the margin is the difference). With
    the output's ``path``, a file system of no size at all (a virtual one: /sys, /proc) is said to be one, not a
    full disk."""
    from hsicam.memory import format_bytes

    margin = free_space_margin(need_bytes, min_margin_bytes)
    text = (f"about {format_bytes(need_bytes)}, and {format_bytes(margin)} more is kept free beyond it "
            f"({format_bytes(need_bytes + margin)} in all), but ")
    if path is not None and _file_system_size(path) == 0:
        return text + "that file system stores no files (0 B in all: a virtual one, such as /sys or /proc)"
    return text + f"that disk has {format_bytes(free_bytes)} free"


def _file_system_size(path: str | os.PathLike) -> int | None:
    """The size in bytes of the file system that ``path`` (or its nearest existing ancestor) is on; None when it
    cannot be read."""
    try:
        return shutil.disk_usage(_nearest_existing(Path(path).absolute(), broken_links=False)).total
    except OSError:
        return None


def _writable_dir(d: Path) -> bool:
    return os.access(d, os.W_OK | os.X_OK)


def broken_link_problem(path: str | os.PathLike) -> str | None:
    """Why the symbolic link ``path`` cannot be followed (it points nowhere, or round a loop), or None
    (a link that works, or no link)."""
    try:
        target = os.readlink(path)
    except OSError:
        return None
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ENOENT:
            return f"is a symbolic link to {target}, which does not exist"
        if exc.errno == errno.ELOOP:
            return f"is a symbolic link to {target}, which leads back to itself (a symbolic link loop)"
        return f"is a symbolic link to {target}, which cannot be followed ({exc.strerror or exc})"
    return None


def follow_link(path: str | os.PathLike) -> Path:
    """``path``, or for a symbolic link the path it leads to (through a chain of links), so that an
    output given as a link is written in its target and the link is kept. One-line
    :class:`InputError` for a link that points nowhere or loops."""
    p = Path(path)
    problem = broken_link_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {problem}")
    while p.is_symlink():  # it can be followed (os.stat worked), so the chain ends
        p = p.parent / os.readlink(p)
    return p


def output_path_problem(path: str | os.PathLike, kind: str = "file") -> str | None:
    """Why ``path`` cannot be written as a ``kind`` ("file" or "dir") output, or None when it can."""
    if kind not in ("file", "dir"):
        raise ValueError(f"kind must be 'file' or 'dir', got {kind!r}")
    if str(path) == "":
        return "the output path is empty"
    full = Path(os.path.abspath(Path(path)))
    link = broken_link_problem(full)
    if link is not None:
        return link
    full = follow_link(full)
    try:
        exists = full.exists() or full.is_symlink()
        is_dir = full.is_dir()
    except OSError as exc:
        return f"cannot be used as an output ({exc.strerror or exc})"
    if exists:
        if kind == "file" and is_dir:
            return "is an existing folder; a file is needed here"
        if kind == "dir" and not is_dir:
            return "is an existing file; a folder is needed here"
        if kind == "dir":
            return None if _writable_dir(full) else "folder is not writable (permission denied or read-only file system)"
        parent = full.parent
        return None if _writable_dir(parent) else f"cannot be replaced: the folder {parent} is not writable"
    anchor = _nearest_existing(full.parent)
    link = broken_link_problem(anchor)
    if link is not None:
        return f"cannot be created inside {anchor}: it {link}"
    if not anchor.is_dir():
        return f"cannot be created inside {anchor}, which is a file"
    if not _writable_dir(anchor):
        return f"cannot be created: the folder {anchor} is not writable (permission denied or read-only file system)"
    return None


def check_output_path(path: str | os.PathLike, kind: str = "file") -> Path:
    """Check, before any work starts, that ``path`` can receive a ``kind`` ("file" or "dir") output.

    Creates nothing. Raises one-line :class:`InputError` naming the path and the problem when it
    is an existing folder where a file is needed (or an existing file where a folder is needed),
    lies inside a file, or cannot be created or written for lack of permission. Returns the path.
    """
    problem = output_path_problem(path, kind)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    return Path(path)


def _os_error(path: Path, kind: str, exc: OSError) -> InputError:
    problem = output_path_problem(path, kind) or f"cannot be written ({exc.strerror or exc})"
    return InputError(f"{path}: {problem}")


# ------------------------------------------------------------------------------------------------
# Disk errors: the one table of them
# ------------------------------------------------------------------------------------------------
#: A write that the disk refused whatever the file, by errno: what to do about it. A folder's writer
#: names the folder when such an error names no file (:func:`atomic_output`); the command line adds
#: the advice to its one line (:data:`OS_ERROR_HINTS`).
DISK_HINTS: dict[int, str] = {
    errno.ENOSPC: "the disk is full: free some space, or write to another disk",
    errno.EDQUOT: "the disk quota is used up: free some space, or write elsewhere",
    errno.EFBIG: "over the file-size limit of the file system or of the shell, ulimit -f: write elsewhere",
    errno.EROFS: "write to a writable file system",
}

#: The errno values of :data:`DISK_HINTS`.
DISK_ERRNOS = frozenset(DISK_HINTS)

#: Of :data:`DISK_ERRNOS`, those that freeing space cures (a full disk, a used-up quota): e.g. a
#: checkpoint's failure says "free some space, then resume the run".
NO_SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})

#: What to do about an OSError, by errno: a write the disk refused (:data:`DISK_HINTS`), a failed
#: disk, or a file without permission. The command line's one line gives it, with the system's own
#: text of the error (not a library's multi-line one).
OS_ERROR_HINTS: dict[int, str] = {
    **DISK_HINTS,
    errno.EIO: "the disk or its connection failed",
    errno.EACCES: "check its permissions and its folder's",
    errno.EPERM: "check its permissions and its folder's",
}


def _naming_output(exc: OSError, final: Path, tmp: Path, kind: str) -> OSError:
    """``exc``, raised while ``final`` was written through its temporary ``tmp``, naming the path the
    failed file was to have: ``final`` for an error naming no file (a file's writer; a folder's,
    for :data:`DISK_ERRNOS`) or naming the temporary, ``final/REL`` for ``tmp/REL``. ``exc`` itself
    when it names another file."""
    name = None
    if exc.filename is None:
        if kind == "file" or exc.errno in DISK_ERRNOS:
            name = final
    else:
        try:
            rel = Path(os.path.abspath(os.fsdecode(exc.filename))).relative_to(os.path.abspath(tmp))
        except (TypeError, ValueError):
            return exc
        name = final / rel if rel.parts else final
    if name is None:
        return exc
    what = exc.strerror or (str(exc).splitlines() or [type(exc).__name__])[0]
    return OSError(exc.errno, what, str(name))


# ------------------------------------------------------------------------------------------------
# Lock files
# ------------------------------------------------------------------------------------------------
#: The lock files this process holds (:class:`OutputLock`, :class:`hsicam.runs.lock.RunLock`), by
#: (device, inode): this process's own lock is never a refusal.
_HELD: dict[tuple[int, int], Path] = {}
#: Their descriptors, closed in a forked child (:func:`_forget_locks_in_child`).
_HELD_FDS: set[int] = set()

#: How long a writer waits for a cleanup that holds its lock file while it removes a killed
#: process's temporaries (they may be large); another writer is a refusal at once.
_CLEANUP_WAIT_S = 60.0
#: The temporary folders this process is writing now (:func:`atomic_output`), absolute: under a folder lock this
#: process holds, a cleanup removes the folder's other temporaries (a killed run's) but never these.
_WRITING: set[str] = set()


def _forget_locks_in_child() -> None:
    """In a process forked from a lock's holder (a DataLoader worker): close its copies of the lock descriptors. An
    flock lock lasts while any descriptor of its open file does, so a worker orphaned by a ``kill -9`` of its parent
    held the run's lock until it noticed (~5 s) and an immediate ``--resume`` was refused. Closing a copy (not
    ``LOCK_UN``, which would release the parent's lock too) leaves the parent's lock as it is."""
    for fd in _HELD_FDS:
        try:
            os.close(fd)
        except OSError:
            pass
    _HELD_FDS.clear()
    _HELD.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_locks_in_child)


class LockHeld(Exception):
    """Another process holds the lock file (:func:`lock_file`)."""


def _file_key(fd: int) -> tuple[int, int]:
    st = os.fstat(fd)
    return st.st_dev, st.st_ino


def names_open_file(path: str | os.PathLike, fd: int) -> bool:
    """True while ``path`` still names the file open as ``fd`` (a released lock's file is removed)."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) == _file_key(fd)


def held_here(path: str | os.PathLike) -> bool:
    """True when this process holds the lock file ``path``."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) in _HELD


def held_elsewhere(path: str | os.PathLike) -> bool:
    """True when another process holds the lock file ``path`` (tried with a shared lock, let go at
    once). Creates nothing; False where nothing can be locked."""
    if fcntl is None:
        return False
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False  # no lock file: nobody holds it
    try:
        if _file_key(fd) in _HELD:
            return False  # this process's own
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        except OSError:
            return False  # a file system without locks
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def _lock_info(path: str | os.PathLike) -> dict[str, Any]:
    try:
        info = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def lock_file(path: str | os.PathLike, info: dict[str, Any] | None = None, tries: int = 10) -> int | None:
    """Take the exclusive ``fcntl.flock`` lock of the file ``path`` (created when missing) and write
    ``{"pid", "since", **info}`` in it; returns its descriptor, for :func:`unlock_file`.

    :class:`LockHeld` when another process holds it (``tries`` tries 20 ms apart; while the holder is
    a cleanup, up to a minute). None, nothing locked (a debug log), where this platform or file system
    cannot lock or the file cannot be created. A file that its holder removed meanwhile is not taken:
    the new one is."""
    if fcntl is None:
        log.debug("%s: no file locking on this platform; not locked", path)
        return None
    start = time.monotonic()
    for n in range(1, 1 << 30):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            log.debug("%s: not locked (%s)", path, exc)
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if n >= tries and not (_lock_info(path).get("cleaning") and time.monotonic() - start < _CLEANUP_WAIT_S):
                raise LockHeld(str(path)) from None
            time.sleep(0.02)
            continue
        except OSError as exc:
            os.close(fd)
            log.debug("%s: not locked (%s)", path, exc)
            return None
        if names_open_file(path, fd):
            break
        os.close(fd)  # released and removed by its holder meanwhile: lock the new file
        if n >= tries:
            raise LockHeld(str(path))
    _HELD[_file_key(fd)] = Path(path)
    _HELD_FDS.add(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps({"pid": os.getpid(), "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                                 **(info or {})}).encode())
    except OSError:  # only a refusal's details (e.g. a full disk)
        pass
    return fd


def unlock_file(fd: int, path: str | os.PathLike | None) -> None:
    """Remove the lock file ``path`` (while it is still the one open as ``fd``) and let go of it."""
    _HELD.pop(_file_key(fd), None)
    _HELD_FDS.discard(fd)
    try:
        if path is not None and names_open_file(path, fd):
            os.unlink(path)
    except OSError:
        pass
    finally:
        os.close(fd)


def lock_holder_text(path: str | os.PathLike, command: str | None = None) -> str:
    """Who holds the lock file ``path``: "being trained by another process (pid N, since T)" when the holder trains
    (its file or ``command`` says "train"), else "being written by another process (hsicam CMD, pid N, since T)"."""
    info = _lock_info(path)
    try:
        holder = f"pid {int(info['pid'])}, since {info['since']}"
    except (KeyError, TypeError, ValueError):
        holder = "pid unknown"
    command = info.get("command") if isinstance(info.get("command"), str) else command
    if command == "train":
        return f"being trained by another process ({holder})"
    by = f"hsicam {command}, " if command else ""
    return f"being written by another process ({by}{holder})"


def lock_refusal(what: str | os.PathLike, path: str | os.PathLike, command: str | None = None) -> InputError:
    """The one line for ``what``, whose lock file ``path`` another process holds (:func:`lock_holder_text`);
    "wait for it or stop it"."""
    return InputError(f"{what}: {lock_holder_text(path, command)}; wait for it or stop it")


def output_lock_path(path: str | os.PathLike) -> Path:
    """The lock file ``.NAME.hsicam-lock`` of the folder output ``path``, next to it (``path`` made absolute first:
    ``.`` or ``ev/..`` named a lock file inside the folder, which another command writing it did not see)."""
    p = Path(os.path.abspath(path))
    return p.parent / f".{p.name}{OUTPUT_LOCK_SUFFIX}"


class OutputLock:
    """This process's lock of the folder output ``path`` (through a symbolic link: of what it leads
    to): held while the folder is written under a temporary name and renamed into place
    (:func:`atomic_output`), or from earlier to keep a new output for this process (a training holds
    its new run's from before its data are prepared). Another process that would write the folder is
    refused with one line (:func:`lock_refusal`, ``command`` naming this one), and cleanups leave its
    temporaries. A context manager that lets go on exit; re-entrant (an inner acquire does nothing,
    its release keeps the outer lock); ``enabled=False`` (a DDP rank other than 0) locks nothing."""

    def __init__(self, path: str | os.PathLike, command: str | None = None, enabled: bool = True) -> None:
        try:
            target = follow_link(path)
        except InputError:  # a broken link: its own error comes from the output check
            target = Path(path)
        self.path = Path(path)
        self.lock_path = output_lock_path(target)
        self.command = command
        self.enabled = enabled
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock; InputError when another process holds it, nothing where nothing can be locked."""
        if not self.enabled or self._fd is not None or held_here(self.lock_path):
            return
        try:
            self._fd = lock_file(self.lock_path, {"command": self.command} if self.command else None)
        except LockHeld:
            raise lock_refusal(self.path, self.lock_path) from None

    def release(self) -> None:
        """Let go (removing the lock file); an inner (re-entrant) lock: nothing."""
        fd, self._fd = self._fd, None
        if fd is not None:
            unlock_file(fd, self.lock_path)

    def __enter__(self) -> "OutputLock":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


# ------------------------------------------------------------------------------------------------
# Temporaries
# ------------------------------------------------------------------------------------------------
def _make_parents(folder: Path) -> list[Path]:
    """``mkdir -p folder``; returns the folders it created (outermost first)."""
    missing = []
    for a in (folder, *folder.parents):
        if a.exists():
            break
        missing.append(a)
    folder.mkdir(parents=True, exist_ok=True)
    return missing[::-1]


def _remove_created(created: list[Path]) -> None:
    for d in reversed(created):
        with contextlib.suppress(OSError):
            d.rmdir()  # only when still empty


def _temp_sibling(path: Path, kind: str) -> Path:
    token = secrets.token_hex(4)
    if kind == "tmp":
        return path.with_name(f".{path.stem}.{token}.tmp{path.suffix}")
    return path.with_name(f".{path.name}.{token}.{kind}")


def _new_temp_file(path: Path) -> tuple[Path, int | None]:
    """A new empty temporary file next to ``path`` and the descriptor holding its lock while it is
    written (None where nothing can be locked): a cleanup leaves a locked temporary."""
    for _ in range(100):
        tmp = _temp_sibling(path, "tmp")
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies
        except FileExistsError:
            continue
        if fcntl is None:
            os.close(fd)  # (Windows cannot rename a file that is open)
            return tmp, None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # a cleanup took it first, to remove it: another name
            os.close(fd)
            continue
        except OSError:  # a file system without locks
            return tmp, fd
        if names_open_file(tmp, fd):
            return tmp, fd
        os.close(fd)  # removed by a cleanup before it was locked: another name
    raise FileExistsError(f"no free temporary name next to {path}")


def _new_temp_dir(path: Path) -> Path:
    for _ in range(100):
        tmp = _temp_sibling(path, "tmpdir")
        try:
            os.mkdir(tmp, 0o777)  # the umask applies
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"no free temporary name next to {path}")


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _fsync_dir(folder: Path) -> None:
    """Make a rename inside ``folder`` durable (best effort: not every platform can open a folder)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def output_name(path: str | os.PathLike) -> Path:
    """The output a folder or file temporary of :func:`atomic_output` becomes (``DIR/.NAME.XXXXXXXX.tmpdir`` →
    ``DIR/NAME``), for messages that name what the user asked for; any other path as it is."""
    p = Path(path)
    parts = _TEMP_PARTS.match(p.name)
    if parts is None or parts["folder"] == "old":
        return p
    return p.with_name(parts["stem"] + (parts["suffix"] or ""))


def is_temporary(name: str) -> bool:
    """True for the name of a hidden temporary written by this module."""
    return bool(_TEMP_RE.match(name))


def cleanup_stale_temporaries(folder: str | os.PathLike, *, recursive: bool = False, min_age_s: float = 0.0) -> list[Path]:
    """Remove the hidden temporaries (files and folders) that a killed process left in ``folder``.

    Only names this module creates are touched (:func:`is_temporary`), and never one that a process
    (this one included) is writing now: a temporary file that is locked, a folder output's
    temporary while its :class:`OutputLock` is held. ``min_age_s`` spares temporaries modified more
    recently too. ``recursive``: in sub-folders as well (never inside a temporary folder). Returns
    the removed paths (a missing folder: [])."""
    root = Path(folder)
    if not root.is_dir():
        return []
    removed = []
    now = time.time()
    for p in _temporaries(root, recursive):
        try:
            if min_age_s > 0 and now - p.lstat().st_mtime < min_age_s:
                continue
        except OSError:
            continue
        if remove_if_stale(p):
            removed.append(p)
            log.info("removed a stale temporary left by an interrupted run: %s", p)
    return removed


def remove_stale_siblings(path: str | os.PathLike, kind: str = "dir") -> list[Path]:
    """Before a command writes the output ``path`` (``kind`` "file" or "dir"): remove the hidden
    temporaries a killed process left next to it (for a file, every ``.STEM.*`` one, and ``..STEM.*``: a
    temporary's own).

    One-line :class:`InputError` (:func:`lock_refusal`) when another process is writing the folder
    ``path`` now (its :class:`OutputLock`); a folder's temporaries are removed under that lock. A
    temporary file that another process is writing is left (two writers of one file each rename a
    whole file into place), and so is whatever this process is writing. Returns the removed paths."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    lock, fd = output_lock_path(path), None
    if kind == "dir" and not held_here(lock):
        try:
            fd = lock_file(lock, {"cleaning": True})  # waits for another cleanup, not for a writer
        except LockHeld:
            raise lock_refusal(path, lock) from None
    stem = path.stem if kind == "file" else path.name
    removed = []
    try:
        # a temporary's own temporary too (a file written atomically into a temporary name: "..STEM.x.tmp.y.tmp.png",
        # which a rerun never removed)
        found = {*path.parent.glob(f".{glob.escape(stem)}.*"), *path.parent.glob(f"..{glob.escape(stem)}.*")}
        for p in sorted(found):
            if not is_temporary(p.name) or Path(os.path.abspath(p)) == lock:
                continue
            parts = _TEMP_PARTS.match(p.name)
            # the folder's own temporaries, its lock held here: taken for this cleanup, or by this command from its
            # start (evaluate, experiment), when this process is not writing them
            ours = fd is not None or (kind == "dir" and held_here(lock) and os.path.abspath(p) not in _WRITING)
            if ours and parts is not None and parts["folder"] and parts["stem"] == path.name:
                if not restore_set_aside(p):
                    _remove(p)
            elif not remove_if_stale(p):
                continue
            removed.append(p)
            log.debug("removed a stale temporary left by an interrupted run: %s", p)
    finally:
        if fd is not None:
            unlock_file(fd, lock)  # a killed writer's lock file too
    return removed


def restore_set_aside(p: Path) -> bool:
    """Rename ``p`` back into place when it is a finished output that a replacement set aside
    (``.NAME.XXXXXXXX.old``) and a kill between :func:`_swap_in`'s two renames left without its
    successor: ``NAME`` is missing. True when restored (a warning names it); call under the
    output's lock."""
    parts = _TEMP_PARTS.match(p.name)
    if parts is None or parts["folder"] != "old" or not p.is_dir() or p.is_symlink():
        return False
    final = p.with_name(parts["stem"])
    if final.exists() or final.is_symlink():
        return False
    try:
        os.rename(p, final)
    except OSError:
        return False
    log.warning("%s: restored the previous output, which a killed command had set aside while replacing it", final)
    return True


def _temporaries(folder: Path, recursive: bool) -> list[Path]:
    """The hidden temporaries in ``folder``, sorted; ``recursive``: in its sub-folders too (links not
    followed), never inside a temporary."""
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return []
    found = []
    for p in entries:
        if is_temporary(p.name):
            found.append(p)
        elif recursive and p.is_dir() and not p.is_symlink():
            found += _temporaries(p, True)
    return found


def remove_if_stale(p: Path) -> bool:
    """Remove the hidden temporary ``p`` unless a process is writing it now; True when removed. A
    folder output's temporary (and its lock file) is removed under its :class:`OutputLock`, so that
    no writer starts in it meanwhile; a temporary file under its own lock. Any other name: False."""
    if not is_temporary(p.name):
        return False
    parts = _TEMP_PARTS.match(p.name)
    if parts is not None and not parts["folder"]:
        return _remove_file_if_stale(p)
    lock = p if parts is None else output_lock_path(p.with_name(parts["stem"]))
    if held_here(lock):
        return False
    try:
        fd = lock_file(lock, {"cleaning": True}, tries=1)
    except LockHeld:
        return False
    try:
        if lock != p and not restore_set_aside(p):
            _remove(p)
    finally:
        if fd is not None:
            unlock_file(fd, lock)  # removes the lock file too
        elif lock == p:
            p.unlink(missing_ok=True)  # nothing can be locked here: a leftover
    return True


def _remove_file_if_stale(p: Path) -> bool:
    """Remove the temporary file ``p`` unless its writer holds its lock (:func:`_new_temp_file`)."""
    if fcntl is None:
        _remove(p)
        return True
    fd = None
    for flags in (os.O_RDWR, os.O_RDONLY):
        try:
            fd = os.open(p, flags | getattr(os, "O_NOFOLLOW", 0))
            break
        except OSError:
            continue
    if fd is None:  # gone meanwhile, or not a file that opens (a link …): as it is
        if not (p.exists() or p.is_symlink()):
            return False
        _remove(p)
        return True
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False  # being written
        except OSError:
            pass  # a file system without locks
        if not names_open_file(p, fd):
            return False  # renamed into place or removed meanwhile
        _remove(p)
        return True
    finally:
        os.close(fd)


# ------------------------------------------------------------------------------------------------
# Atomic files and folders
# ------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is fsynced and renamed onto ``path``.

    The temporary file keeps ``path``'s suffix so that writers choosing a format by extension
    (imageio, matplotlib) still work. On error the temporary file (and any parent folder created
    for it) is removed; an ``OSError`` of the write names ``path``. A parent that cannot be
    created or written, or a ``path`` that is an existing folder, is one :class:`InputError` before anything is
    written. A symbolic link ``path`` is written through (:func:`follow_link`).
    """
    path = follow_link(path)
    if path.is_dir():  # os.replace would refuse it only after the whole file was written
        raise InputError(f"{path}: is an existing folder; a file is needed here")
    try:
        created = _make_parents(path.parent)
        tmp_path, fd = _new_temp_file(path)
    except OSError as exc:
        raise _os_error(path, "file", exc) from None
    try:
        yield tmp_path
        _fsync_file(tmp_path)
        os.replace(tmp_path, path)
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        _remove_created(created)
        named = _naming_output(exc, path, tmp_path, "file") if isinstance(exc, OSError) else exc
        if named is not exc:
            raise named from exc
        raise
    finally:
        if fd is not None:
            os.close(fd)  # lets go of the temporary's lock
    _fsync_dir(path.parent)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs: Any) -> Iterator[IO]:
    """``open()`` that writes to a temporary file and renames it onto ``path`` when closed."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, kind: str = "dir", *, overwrite: bool = False,
                  marker: dict[str, Any] | bool = True) -> Iterator[Path]:
    """Write a whole output — a folder (``kind="dir"``) or a file — under a temporary sibling and
    rename it into place only when the ``with`` block succeeds.

    Yields the temporary path (for a folder: an existing empty folder to fill). On success a
    folder gets its completion marker (``marker``: True, or a dict of extra JSON fields; False for
    none) and replaces ``path``: an absent or empty folder always, a non-empty one only with
    ``overwrite=True`` and only when it carries the marker (a folder this toolkit completed; a
    user's own folder is never deleted). On any error or interruption the temporary is removed and
    ``path`` is left as it was. Unusable paths raise one-line :class:`InputError` before the block,
    and so does a folder that another process is writing now: the block runs under the folder's
    :class:`OutputLock` (its temporaries are in use, no cleanup removes them).
    A symbolic link ``path`` leads to the folder that is replaced (:func:`follow_link`); the link is
    kept. An ``OSError`` naming a file in the temporary names it under ``path``.
    """
    if kind == "file":
        with atomic_path(path) as tmp:
            yield tmp
        return
    if kind != "dir":
        raise ValueError(f"kind must be 'file' or 'dir', got {kind!r}")
    path = follow_link(path)
    command = marker.get("command") if isinstance(marker, dict) else None
    check_output_path(path, "dir")
    check_replaceable(path, overwrite, command)
    lock = OutputLock(path, command)
    try:
        created = _make_parents(path.parent)
    except OSError as exc:
        raise _os_error(path, "dir", exc) from None
    try:
        lock.acquire()  # another process writing this folder: refused, before any temporary
        tmp = _new_temp_dir(path)
        _WRITING.add(os.path.abspath(tmp))
    except BaseException as exc:
        lock.release()
        _remove_created(created)
        if isinstance(exc, OSError):
            raise _os_error(path, "dir", exc) from None
        raise
    try:
        yield tmp
        if marker:
            mark_complete(tmp, {**(marker if isinstance(marker, dict) else {}), "files": written_entries(tmp)})
        check_replaceable(path, overwrite, command)  # the block may have run for hours
        _swap_in(tmp, path)
    except BaseException as exc:
        _WRITING.discard(os.path.abspath(tmp))
        _remove(tmp)
        lock.release()
        _remove_created(created)
        named = _naming_output(exc, path, tmp, "dir") if isinstance(exc, OSError) else exc
        if named is not exc:
            raise named from exc
        raise
    _WRITING.discard(os.path.abspath(tmp))
    lock.release()
    _fsync_dir(path.parent)


#: Sub-folders that another command writes inside a completed output, from it (``hsicam report``'s
#: ``report/`` in an evaluation folder), by name → the command in their own marker. They go stale
#: with the output they were made from, so replacing that output may remove them (while they hold
#: only what their own marker lists).
DERIVED_OUTPUTS = {"report": "report"}

#: Files that file browsers and notebooks put in any folder they open: never a user's work, so they
#: do not stop a command from replacing its own output (AppleDouble ``._*`` files too).
OS_METADATA = frozenset({".DS_Store", "Thumbs.db", "desktop.ini", ".ipynb_checkpoints"})


def check_replaceable(path: Path, overwrite: bool, command: str | None = None) -> None:
    """InputError unless :func:`atomic_output` may put a folder at ``path``: absent, empty, or (with
    ``overwrite``) a completed hsicam output written by ``command`` (when given and named in the
    marker) that holds only the entries its marker lists (when it lists them), at any depth (a
    derived ``report/``: those its own marker lists), named relative to ``path`` when it does not.
    Commands call it before their work too (:func:`hsicam.cli.prepare_output` with
    ``replace=True``), so a user's own folder is refused at once, not after hours of work."""
    if not path.is_dir():
        if path.exists():
            raise InputError(f"{path}: is an existing file; a folder is needed here")
        return
    if not any(path.iterdir()):
        return
    if not is_complete(path):
        raise InputError(f"{path}: folder exists and is not empty (and is not a completed hsicam output); "
                         "choose another output folder")
    if not overwrite:
        raise InputError(f"{path}: folder already holds a completed output; choose another folder or allow overwriting")
    info = read_marker(path)
    written_by = info.get("command") if isinstance(info.get("command"), str) else None
    if command is not None and written_by is not None and written_by != command:
        raise InputError(f"{path}: holds the output of hsicam {written_by}, not of hsicam {command}; "
                         "choose another output folder")
    files = info.get("files")
    if isinstance(files, list):
        writer = f"hsicam {command or written_by}" if (command or written_by) else "the command that wrote it"
        extra, unlisted_dirs = _unlisted(path, {str(f) for f in files})
        if unlisted_dirs:
            d = unlisted_dirs[0]
            raise InputError(f"{path}: cannot tell which files in {d}/ {writer} wrote (its marker is from an older "
                             f"hsicam and lists the folder only); move your files out of {path / d} and delete it, "
                             "or choose another folder")
        if extra:
            shown = ", ".join(_entry_text(path, e) for e in extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5 else "")
            raise InputError(f"{path}: holds {shown}, which {writer} did not write; choose another folder or "
                             "move them")


def _entry_text(folder: Path, entry: str) -> str:
    """``entry`` of ``folder`` as a refusal names it: a symbolic link says where it leads (e.g. a
    report written through it) and that removing it keeps its target."""
    p = folder / entry.rstrip("/")
    if not p.is_symlink():
        return entry
    return f"{entry} (a symbolic link to {os.readlink(p)}: remove the link, its target is kept)"


def written_entries(folder: Path) -> list[str]:
    """Every file and sub-folder in ``folder`` as a sorted POSIX path relative to it (a folder's ends
    in ``/``; links are not followed), hidden temporaries left out: a marker's ``"files"``."""
    out = []
    for dirpath, dirnames, filenames in os.walk(folder):
        rel = Path(dirpath).relative_to(folder)
        dirnames[:] = [d for d in dirnames if not is_temporary(d)]
        out += [(rel / d).as_posix() + "/" for d in dirnames]
        out += [(rel / f).as_posix() for f in filenames if not is_temporary(f)]
    return sorted(out)


def _ignorable(name: str) -> bool:
    """A hidden temporary or a file browser's metadata: never a user's work."""
    return is_temporary(name) or name in OS_METADATA or name.startswith("._")


def _unlisted(base: Path, listed: set[str], rel: str = "") -> tuple[list[str], list[str]]:
    """(entries under ``base/rel`` that a marker's ``files`` ``listed`` does not name, sub-folders it
    names without their contents (an older marker) that are not empty), as sorted paths relative to
    ``base``. Listed sub-folders are checked entry by entry; a derived output (:func:`_is_derived`)
    at the top against its own marker, as the command that writes it checks it."""
    extra: list[str] = []
    unknown: list[str] = []
    for p in sorted((base / rel).iterdir()):
        name = f"{rel}{p.name}"
        if _ignorable(p.name) or name == COMPLETE_MARKER:
            continue
        if not (p.is_dir() and not p.is_symlink()):
            if name not in listed:
                extra.append(name)
        elif f"{name}/" in listed:
            more, old = _unlisted(base, listed, f"{name}/")
            extra, unknown = extra + more, unknown + old
        elif name in listed:
            if any(not _ignorable(q.name) for q in p.iterdir()):
                unknown.append(name)
        elif not rel and _is_derived(p):
            more = _derived_unlisted(p)
            extra += [f"{name}/{x}" for x in more]
        else:
            extra.append(name)
    return sorted(extra), sorted(unknown)


def _derived_unlisted(folder: Path) -> list[str]:
    """Entries of a derived output that its own marker's ``files`` do not name (none when it lists none)."""
    files = read_marker(folder).get("files")
    if not isinstance(files, list):
        return []
    extra, unknown = _unlisted(folder, {str(f) for f in files})
    return sorted(extra + unknown)


def _is_derived(p: Path) -> bool:
    """True for a completed sub-output named in :data:`DERIVED_OUTPUTS` (e.g. ``report/``)."""
    want = DERIVED_OUTPUTS.get(p.name)
    return want is not None and p.is_dir() and not p.is_symlink() and read_marker(p).get("command") == want


def _swap_in(tmp: Path, path: Path) -> None:
    """Rename the finished temporary folder onto ``path`` (an old folder is set aside, then removed)."""
    old = None
    if path.exists():
        old = _temp_sibling(path, "old")
        os.rename(path, old)
    try:
        os.rename(tmp, path)
    except BaseException:
        if old is not None:
            os.rename(old, path)
        raise
    if old is not None:
        _remove(old)


# ------------------------------------------------------------------------------------------------
# Completion markers
# ------------------------------------------------------------------------------------------------
def mark_complete(folder: str | os.PathLike, info: dict[str, Any] | None = None) -> Path:
    """Write ``folder/.complete`` (atomically, JSON: ``{"complete": true, ...info}``) as the last
    step of filling ``folder``; returns the marker's path."""
    p = Path(folder) / COMPLETE_MARKER
    write_json(p, {"complete": True, **(info or {})})
    return p


def same_path(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` name one file or folder: through links (``os.path.samefile``), or by
    their resolved paths when either does not exist."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def is_complete(folder: str | os.PathLike) -> bool:
    """True when ``folder`` carries the completion marker written by :func:`mark_complete`."""
    return (Path(folder) / COMPLETE_MARKER).is_file()


def read_marker(folder: str | os.PathLike) -> dict[str, Any]:
    """The fields of ``folder``'s completion marker ({} when it has none or it cannot be read)."""
    try:
        info = json.loads((Path(folder) / COMPLETE_MARKER).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return info if isinstance(info, dict) else {}


def output_description(folder: str | os.PathLike) -> str:
    """"the output of hsicam CMD" for a folder whose marker names its command, else "a completed hsicam output"."""
    command = read_marker(folder).get("command")
    return f"the output of hsicam {command}" if isinstance(command, str) and command else "a completed hsicam output"


def clear_derived(folder: str | os.PathLike) -> list[Path]:
    """Before a folder filled in place (a demo, an experiment) is filled again: remove the derived
    outputs made from its old results (``report/``, :data:`DERIVED_OUTPUTS`), which would stand beside
    the new ones out of date; InputError, with nothing removed, when one holds files its own marker
    does not list (a user's). Returns the removed folders."""
    import shutil

    folder = Path(folder)
    derived = [folder / name for name in DERIVED_OUTPUTS if _is_derived(folder / name)]
    for d in derived:
        extra = _derived_unlisted(d)
        if extra:
            raise InputError(f"{d}: holds {', '.join(extra[:5])}, which hsicam {DERIVED_OUTPUTS[d.name]} did not write; "
                             f"it is made from {folder}'s results and would be removed as out of date: move them")
    for d in derived:
        shutil.rmtree(d)
    return derived


def clear_complete(folder: str | os.PathLike) -> None:
    """Remove the marker before a folder is filled again in place (so it never looks complete half-way)."""
    p = Path(folder) / COMPLETE_MARKER
    p.unlink(missing_ok=True)
    _fsync_dir(p.parent)


# ------------------------------------------------------------------------------------------------
# Writers
# ------------------------------------------------------------------------------------------------
def read_record(path: str | os.PathLike, valid: Callable[[Any], bool], advice: str) -> dict[str, Any] | None:
    """A JSON record a command wrote (a run's data.json, camera_files.json): None when ``path`` is no file; one-line
    :class:`InputError` ``"PATH: unreadable (why); " + advice`` when it cannot be read, is no JSON, or ``valid``
    (the record's expected shape) says no."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        if not valid(record):
            raise ValueError(f"not a {path.stem.replace('_', ' ')} record")
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: unreadable ({getattr(exc, 'msg', None) or exc}); {advice}") from None
    return record


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented, strict JSON (:func:`json_text`), atomically."""
    text = json_text(obj, indent=2)  # before the file is opened: a value JSON cannot hold leaves no file
    with atomic_open(path, "w", encoding="utf-8") as fh:
        fh.write(text + "\n")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write a ``.npy`` file atomically."""
    with atomic_open(path, "wb") as fh:
        np.save(fh, np.asarray(array), allow_pickle=False)


def copy_file(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Copy the (small) file ``src`` to ``dst``, read whole and then written, so that a failed write
    (a full disk …) names ``dst`` (``shutil.copyfile``'s error names the source). Inside
    :func:`atomic_output`, ``dst`` is then named under the final folder."""
    data = Path(src).read_bytes()
    try:
        with open(dst, "wb") as fh:
            fh.write(data)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(dst)) from None


def write_png16(path: str | os.PathLike, image01: np.ndarray, text: dict[str, str] | None = None) -> None:
    """Write a single-channel image in [0, 1] as a 16-bit grayscale PNG (values are clipped);
    ``text``: PNG text chunks (key → value) that travel with the file."""
    img = np.asarray(image01, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"write_png16 expects a 2-D image, got shape {img.shape}")
    data = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
    with atomic_path(path) as tmp:  # encoded in memory: imageio never sees (nor expands "~" in) the path
        tmp.write_bytes(_png_bytes(data, text))


def _png_bytes(data: np.ndarray, text: dict[str, str] | None) -> bytes:
    """``data`` (uint8 or uint16) encoded as PNG, with ``text`` as PNG text chunks (key → value) when given."""
    if not text:
        import imageio.v3 as iio

        return iio.imwrite("<bytes>", data, extension=".png")
    import io as _io

    from PIL import Image, PngImagePlugin

    info = PngImagePlugin.PngInfo()
    for key, value in text.items():
        info.add_text(key, value)
    buf = _io.BytesIO()
    Image.fromarray(data).save(buf, format="PNG", pnginfo=info)
    return buf.getvalue()


def png8_values(rgb01: np.ndarray) -> np.ndarray:
    """The 8-bit values (uint8, same shape) that :func:`write_png8` stores for an image in [0, 1]:
    clipped, times 255, rounded; NaN pixels 0 (black: casting NaN to uint8 is undefined and warned about by NumPy)
    (float64 temporaries of the input's size: pass large images in parts)."""
    v = np.clip(np.asarray(rgb01, dtype=np.float64), 0.0, 1.0)
    np.nan_to_num(v, copy=False, nan=0.0)
    return np.round(v * 255.0).astype(np.uint8)


def write_png8(path: str | os.PathLike, rgb01: np.ndarray, text: dict[str, str] | None = None) -> None:
    """Write an (H, W, 3) or (H, W) image in [0, 1] as an 8-bit PNG (values are clipped); a uint8
    image is taken as those 8-bit values (:func:`png8_values`) and written as is; ``text`` as in :func:`write_png16`."""
    data = rgb01 if isinstance(rgb01, np.ndarray) and rgb01.dtype == np.uint8 else png8_values(rgb01)
    with atomic_path(path) as tmp:  # encoded in memory, as in write_png16
        tmp.write_bytes(_png_bytes(data, text))


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 120) -> None:
    """Save a matplotlib figure atomically and close it. hsicam draws on ``matplotlib.figure.Figure`` objects, which
    need neither pyplot nor a backend (the user's backend is left as it is, headless or not); a figure of the
    user's own pyplot is closed there too, without importing pyplot."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    pyplot = sys.modules.get("matplotlib.pyplot")
    if pyplot is not None:
        pyplot.close(fig)


def json_default(obj: Any) -> Any:
    """``json.dumps(default=...)`` for numpy scalars/arrays and paths."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def json_ready(obj: Any, keys: frozenset[str] | None = None) -> Any:
    """``obj`` as strict JSON (RFC 8259) can hold it: a non-finite float (NaN, ±inf, numpy's too) becomes None
    (null), numpy scalars and arrays Python numbers and lists, tuples lists; other values as they are (a path is
    left to :func:`json_default`). Python's ``json`` writes ``NaN``/``Infinity``, which strict parsers refuse.
    A score (a value under one of ``keys``, default :data:`SCORE_KEYS`) that is ±inf becomes the string
    ``"inf"``/``"-inf"`` instead (:data:`INF_TEXT`): a score of ±inf is the best or the worst, not undefined
    (null, NaN), and :func:`nan_for_null` reads it back as ±inf."""
    keys = SCORE_KEYS if keys is None else keys
    if isinstance(obj, dict):
        return {k: _score_ready(v, keys) if k in keys else json_ready(v, keys) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v, keys) for v in obj]
    if isinstance(obj, (np.generic, np.ndarray)):
        obj = obj.tolist()
        if isinstance(obj, list):
            return json_ready(obj, keys)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _score_ready(value: Any, keys: frozenset[str]) -> Any:
    """A score for strict JSON: ±inf as ``"inf"``/``"-inf"``, NaN as null, a list of scores (a sweep's) item by
    item, anything else as :func:`json_ready`."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [_score_ready(v, keys) for v in value]
    if isinstance(value, (float, np.floating)) and math.isinf(value):
        return INF_TEXT[1 if value > 0 else -1]
    return json_ready(value, keys)


def json_text(obj: Any, **kwargs: Any) -> str:
    """``obj`` as strict JSON text: non-finite floats written as null, an infinite score as ``"inf"``/``"-inf"``
    (:func:`json_ready`), and ``allow_nan=False`` the guard that nothing else slips through as ``NaN``/``Infinity``.
    A reader of a score takes null back as NaN and ``"inf"``/``"-inf"`` as ±inf (:func:`nan_for_null`).
    ``kwargs``: ``json.dumps``'s (indent, separators …)."""
    return json.dumps(json_ready(obj), allow_nan=False, default=json_default, **kwargs)


#: The scores of hsicam's JSON files (results.json, experiment.json, card.json, metrics.jsonl: ``psnr``,
#: ``val_psnr`` …): a float each. Strict JSON has no NaN nor infinity: a NaN score (undefined, e.g. the SAM of a
#: scene whose truth is zero at every scored pixel) is written as null, a score of ±inf (the best or the worst:
#: :func:`hsicam.metrics.all_metrics` scores a broken estimate -inf dB, +inf for an error) as the string ``"inf"``
#: or ``"-inf"``; :func:`nan_for_null` reads them back as NaN and ±inf.
SCORE_KEYS = frozenset(p + k for k in ("psnr", "ssim", "sam", "ergas", "psnr_cube", "psnr_mst", "rmse",
                                       "psnr_worst", "ssim_worst") for p in ("", "val_"))

#: How an infinite score is written in hsicam's JSON files (:func:`json_ready`), by its sign.
INF_TEXT = {1: "inf", -1: "-inf"}
_INF_OF_TEXT = {text: math.inf * sign for sign, text in INF_TEXT.items()}


def nan_for_null(obj: Any, keys: frozenset[str] = SCORE_KEYS) -> Any:
    """``obj`` as read from JSON with a null under any of ``keys`` (at any depth) read as NaN and ``"inf"`` /
    ``"-inf"`` as ±inf: the non-finite scores :func:`json_text` wrote so. A file of an older hsicam (``NaN`` or
    ``Infinity`` literals, which Python's json reads as floats) reads the same; an older hsicam wrote an infinite
    score as null too, which reads as NaN."""
    if isinstance(obj, dict):
        return {k: _score_of_json(v, keys) if k in keys else nan_for_null(v, keys) for k, v in obj.items()}
    if isinstance(obj, list):
        return [nan_for_null(v, keys) for v in obj]
    return obj


def _score_of_json(value: Any, keys: frozenset[str]) -> Any:
    """A score as read from JSON: null → NaN, ``"inf"``/``"-inf"`` → ±inf, anything else as
    :func:`nan_for_null`."""
    if value is None:
        return math.nan
    if isinstance(value, str) and value in _INF_OF_TEXT:
        return _INF_OF_TEXT[value]
    if isinstance(value, list):  # a list of scores (a sweep's), item by item
        return [_score_of_json(v, keys) for v in value]
    return nan_for_null(value, keys)


def json_number(value: Any, finite: bool = True) -> bool:
    """Whether ``value``, as read from JSON, is a number (a bool is not) and, with ``finite``, a finite one:
    NaN and Infinity, which Python's json reads as floats, are not, nor an integer too large for a float."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return not finite or math.isfinite(value)
    except OverflowError:  # an integer of hundreds of digits
        return False


#: SHA-256 of the files already hashed in this process, by (path, inode, size, mtime, ctime) in ns.
_HASHES: dict[tuple[str, int, int, int, int], str] = {}


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex), read once per process while the file's path, inode, size and
    modification and change times (ns) stay the same (e.g. a shipped camera's weights, checked and then
    recorded). The change time moves on any write and cannot be set back (``os.utime`` sets the modification
    time only): a byte changed in place, its mtime restored, is hashed again."""
    st = os.stat(path)
    key = (str(Path(path).resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    if key not in _HASHES:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        _HASHES[key] = h.hexdigest()
    return _HASHES[key]
