"""The memory budget (bytes) that readers and the optics check sizes against before they allocate.

In order of precedence: the caller's ``budget_mb``; the environment variable
``HSICAM_MEMORY_BUDGET_MB``; else a quarter of the machine's memory (physical RAM, or the cgroup
limit when lower), and at most half of the address space left under a ``ulimit -v`` /
``prlimit --as`` limit. Sizes are in MiB. One home for every layer: the cube readers
(:func:`hsicam.data.cube.check_memory_budget`), the PSF sampling plan
(:func:`hsicam.optics.sampling.check_psf_memory`), the DOE's cell grid
(:func:`hsicam.cameras.doe_camera.check_doe_memory`), the CFA's weights
(:func:`hsicam.cameras.doe_camera.check_cfa_memory`), a CASSI sensor's dispersed width
(:func:`hsicam.cameras.cassi.check_dispersion_span`), a network's weights or training
(:func:`hsicam.models.registry.check_network_memory`) and the Choi prior's
(:func:`hsicam.models.priors.build_prior`; both through
:func:`hsicam.models.registry.check_parameter_memory`) all use :func:`memory_budget_bytes`, so
``HSICAM_MEMORY_BUDGET_MB`` governs them all.

What ``HSICAM_MEMORY_BUDGET_MB`` bounds: one number, the memory this process may take (MiB), checked two ways.
Every allocation the layers above check (a cube read, a PSF plan, the DOE's cells, the CFA's weights, a CASSI
sensor's width, a network's weights or training, a synthetic scene) must fit in it alone
(:func:`memory_budget_bytes`; unset: a quarter of the machine's memory). A whole command's estimated peak must fit
in it where the command estimates one: ``reconstruct`` (the capture's reconstruction) and ``evaluate`` (each scene
of a learned method) (:func:`process_memory_limit`; unset: the machine's memory, its cgroup limit or the address
space left under ``ulimit -v``, the lowest). The other commands (``simulate``, ``train``, ``tolerance``, …) estimate
no whole peak: their process can take more than the budget (``simulate`` of a 1024² scene under a budget of 400 MiB
peaked at 0.87 GB; of a 2048² scene under 1000 MiB, at 2.17 GB; session 76), never one allocation beyond it.

Also here: :func:`keep_freed_memory`, which the ``hsicam`` command calls first so that glibc reuses the memory of
freed tensors instead of handing it back to the system and faulting it in again.
"""

from __future__ import annotations

import ctypes
import decimal
import math
import os
from pathlib import Path, PurePosixPath
from typing import Any

from hsicam.errors import ConfigError

#: Environment variable: the memory this process may take (MiB), which each checked allocation and, in
#: ``reconstruct`` and ``evaluate``, the whole command's estimated peak must fit (the module docstring).
MEMORY_BUDGET_ENV = "HSICAM_MEMORY_BUDGET_MB"
#: Fraction of the machine's memory that one cube may take by default.
DEFAULT_MEMORY_FRACTION = 0.25
_FALLBACK_MEMORY_BYTES = 8 * 2**30  # when the machine's memory cannot be read


def _physical_memory_bytes() -> int | None:
    """The machine's physical RAM (bytes): ``sysconf`` on POSIX, ``GlobalMemoryStatusEx`` on Windows (which has no
    ``os.sysconf``: before session 62 the budget there was the fixed 8 GiB fallback, a whole machine's RAM on an
    8 GiB laptop); None when neither answers."""
    try:
        n = int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        n = _windows_physical_memory_bytes() or 0
    return n if n > 0 else None


class _MemoryStatusEx(ctypes.Structure):
    """Win32 ``MEMORYSTATUSEX`` (sysinfoapi.h), the argument of ``GlobalMemoryStatusEx``."""

    _fields_ = [("dwLength", ctypes.c_uint32), ("dwMemoryLoad", ctypes.c_uint32),
                ("ullTotalPhys", ctypes.c_uint64), ("ullAvailPhys", ctypes.c_uint64),
                ("ullTotalPageFile", ctypes.c_uint64), ("ullAvailPageFile", ctypes.c_uint64),
                ("ullTotalVirtual", ctypes.c_uint64), ("ullAvailVirtual", ctypes.c_uint64),
                ("ullAvailExtendedVirtual", ctypes.c_uint64)]


def _windows_physical_memory_bytes() -> int | None:
    """Physical RAM (bytes) by kernel32's ``GlobalMemoryStatusEx``; None off Windows or when the call fails."""
    windll = getattr(ctypes, "windll", None)
    if windll is None:
        return None
    status = _MemoryStatusEx()
    status.dwLength = ctypes.sizeof(_MemoryStatusEx)
    try:
        ok = windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status))
    except (AttributeError, OSError):
        return None
    if not ok:
        return None
    return int(status.ullTotalPhys) or None


def _cgroup_memory_limit_bytes(proc_cgroup: str | Path = "/proc/self/cgroup",
                               root: str | Path = "/sys/fs/cgroup") -> int | None:
    """The lowest memory limit (bytes) over this process's cgroup and its ancestors, or None when none is set.

    cgroup v2 (``0::/PATH`` in ``proc_cgroup``): ``root/PATH/memory.max``; v1 (``N:memory:/PATH``):
    ``root/memory/PATH/memory.limit_in_bytes``; each up to the top, whose files count too (a container's own
    cgroup is mounted there). Before session 55 only the top files were read: a limit set on a nested cgroup
    (a systemd slice, a job scheduler's) was not seen."""
    root = Path(root)
    files = [root / "memory.max", root / "memory" / "memory.limit_in_bytes"]
    try:
        lines = Path(proc_cgroup).read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError):
        lines = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":
            base, name = root, "memory.max"
        elif "memory" in controllers.split(","):
            base, name = root / "memory", "memory.limit_in_bytes"
        else:
            continue
        rel = PurePosixPath(path.strip() or "/")
        files += [base / str(p).lstrip("/") / name for p in (rel, *rel.parents)]
    limits = []
    for f in files:
        try:
            text = f.read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError):
            continue
        if text.isdigit() and 0 < int(text) < 1 << 60:  # "max" (v2) or a huge number (v1) is no limit
            limits.append(int(text))
    return min(limits) if limits else None


def _address_space_left_bytes() -> int | None:
    """Bytes of virtual address space left under RLIMIT_AS (``ulimit -v``), or None when unlimited."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY or soft < 0:
            return None
    except (ImportError, ValueError, OSError):
        return None
    used = 0
    try:
        for line in Path("/proc/self/status").read_text(encoding="ascii", errors="replace").splitlines():
            if line.startswith("VmSize:"):
                used = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        pass
    return max(int(soft) - used, 0)


def _parse_budget_mb(value: Any, what: str) -> float:
    try:
        mb = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be a positive number of MiB, got {value!r}") from None
    if not math.isfinite(mb) or mb <= 0:
        raise ConfigError(f"{what} must be a positive number of MiB, got {value!r}")
    return mb


def memory_budget_bytes(budget_mb: float | None = None) -> int:
    """The memory one allocation of the program (a cube, a PSF plan, a network's training…) may take, in
    bytes: ``budget_mb``, else ``HSICAM_MEMORY_BUDGET_MB`` (the whole process's limit: no one allocation may exceed
    it; this bounds no command's total, :func:`process_memory_limit` does where a command estimates it), else a
    quarter of the machine's memory (see the module docstring for the precedence and its users).

    Raises :class:`ConfigError` for a budget (argument or ``HSICAM_MEMORY_BUDGET_MB``) that is not
    a positive number.
    """
    if budget_mb is not None:
        return int(_parse_budget_mb(budget_mb, "memory_budget_mb") * 2**20)
    env = os.environ.get(MEMORY_BUDGET_ENV, "").strip()
    if env:
        return int(_parse_budget_mb(env, MEMORY_BUDGET_ENV) * 2**20)
    known = [n for n in (_physical_memory_bytes(), _cgroup_memory_limit_bytes()) if n]
    budget = int(min(known) * DEFAULT_MEMORY_FRACTION) if known else _FALLBACK_MEMORY_BYTES
    left = _address_space_left_bytes()
    if left is not None:
        budget = min(budget, left // 2)
    return budget


def process_memory_limit() -> tuple[int | None, str]:
    """(bytes, which limit they are) of the memory one process may take in all: ``HSICAM_MEMORY_BUDGET_MB`` when set,
    else the lowest of the machine's physical RAM, its cgroup (container) limit and the address space left under a
    ``ulimit -v``; (None, "") when none of them can be read. The words name the limit that bites, for a refusal's
    "more than ...": under ``ulimit -v`` reconstruct said "this machine's memory (2.95 GiB)" on a 23 GB machine."""
    env = os.environ.get(MEMORY_BUDGET_ENV, "").strip()
    if env:
        return int(_parse_budget_mb(env, MEMORY_BUDGET_ENV) * 2**20), f"the limit {MEMORY_BUDGET_ENV} sets"
    known = [(n, what) for n, what in ((_physical_memory_bytes(), "this machine's memory"),
                                       (_cgroup_memory_limit_bytes(), "the memory limit of this process's cgroup "
                                                                      "(its container or job)"),
                                       (_address_space_left_bytes(), "the address space this process has left under "
                                                                     "its ulimit -v"))
             if n is not None]
    return min(known, key=lambda k: k[0]) if known else (None, "")


def format_bytes(nbytes: float) -> str:
    """``nbytes`` in B, KiB, MiB, GiB, TiB or PiB (3 significant digits; 1000–1023 of a unit as an integer, not
    ``1e+03``)."""
    for unit, size in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= size:
            try:
                value = nbytes / size
                return f"{value:.0f} {unit}" if 999.5 <= value < 1024 else f"{value:.3g} {unit}"
            except OverflowError:  # an int beyond float (a memory estimate from absurd optics, e.g. a 1e300 mm lens)
                return f"{decimal.Decimal(int(nbytes)) / size:.3g} {unit}"
    return f"{int(nbytes)} B"


#: Environment variable: ``0`` leaves the C allocator as it is (:func:`keep_freed_memory`).
KEEP_FREED_MEMORY_ENV = "HSICAM_KEEP_FREED_MEMORY"
#: Free memory at the top of the heap that glibc keeps for the next allocation instead of returning it (bytes).
KEEP_FREED_TOP_BYTES = 1 << 30
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # mallopt's parameters (<malloc.h>)
_kept = False  # whether keep_freed_memory() was applied in this process


def keep_freed_memory() -> bool:
    """Make glibc keep the memory that PyTorch frees for the next tensor instead of returning it to the system;
    True when applied (False: not glibc, or ``HSICAM_KEEP_FREED_MEMORY=0``). Process-wide; the ``hsicam``
    command calls it first, importing hsicam does not.

    glibc serves every allocation above its mmap threshold (at most 32 MiB) with a mapping of its own and unmaps it
    on free, so each 512 × 512 × 31 float32 tensor (32.5 MiB, more with a halo) comes back as new pages that the
    kernel must zero at first touch: an element-wise operation then costs ~13 ms of page faults for ~2 ms of
    arithmetic. With every allocation served from the heap (``M_MMAP_MAX`` 0) and up to
    :data:`KEEP_FREED_TOP_BYTES` of free heap kept (``M_TRIM_THRESHOLD``), on this project's 2-core CPU: the quick
    camera's 512² reconstruction 2.2 → 1.3 s, with 24 TV steps 19.6 → 8.2 s, the paper RDN's network 11 → 4.7 s; a
    training step (tensors under the threshold) the same. The price: the process keeps what it freed, and the heap
    fragments (peak resident memory with the 24 TV steps 0.93 → 1.43 GB; a 2048² capture through the shipped camera
    3.2 → 4.5 GB, 4.1 GB with :func:`release_freed_memory` between its tiles, in 69 s instead of 97 s). The
    arithmetic, and so every result, is unchanged."""
    if os.environ.get(KEEP_FREED_MEMORY_ENV, "").strip() == "0":
        return False
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION"):  # glibc only: other C libraries ignore or lack mallopt
            return False
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError, TypeError, ValueError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    global _kept
    _kept = mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_TOP_BYTES) == 1
    return _kept


def release_freed_memory() -> None:
    """Where :func:`keep_freed_memory` was applied: hand the heap's free pages back to the system (glibc's
    ``malloc_trim``), e.g. between the tiles of a large image, so that what one tile's tensors left fragmented is
    not carried into the next; else nothing. A 2048² capture (``benchmarks/bench_capture.py``): peak 4.8 GiB
    without it, 3.6 GiB with it (2.9 GiB under glibc's defaults), in 147 s (119 s without it; 254 s under the
    defaults)."""
    if _kept:
        ctypes.CDLL(None).malloc_trim(0)


__all__ = ["DEFAULT_MEMORY_FRACTION", "KEEP_FREED_MEMORY_ENV", "KEEP_FREED_TOP_BYTES", "MEMORY_BUDGET_ENV",
           "format_bytes", "keep_freed_memory", "memory_budget_bytes",
           "process_memory_limit", "release_freed_memory"]
