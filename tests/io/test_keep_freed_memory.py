"""The hsicam command keeps freed memory for the next tensor (:func:`hsicam.memory.keep_freed_memory`).

What is measured is the kernel's own count of the pages a process touched for the first time (minor page
faults, ``getrusage``) while element-wise operations on a 532 × 512 × 31 float32 cube (32.2 MiB, just above glibc's
largest mmap threshold) make and free their results: under glibc's defaults every result is a fresh mapping, all of
its ~8 250 pages faulted in again; with the memory kept, the results reuse the freed heap (a few hundred faults per
operation while the heap settles). (One reallocation alone is no test: glibc's aligned allocations leave slack that
can keep a freed block from the very next one, depending on the threads' start-up.)
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

import hsicam.cli as cli
import hsicam.memory as memory_mod

ROOT = Path(__file__).resolve().parents[2]


def _glibc() -> bool:
    try:
        return bool(os.confstr("CS_GNU_LIBC_VERSION"))
    except (AttributeError, ValueError, OSError):
        return False


_OPERATIONS = textwrap.dedent("""
    import resource, torch
    from hsicam.memory import keep_freed_memory
    applied = keep_freed_memory()
    faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = torch.rand(1, 31, 532, 512)
    before = faults()
    for _ in range(30):
        y = x + x
        z = y * 2
        del y, z
    print(applied, (faults() - before) / 60)
""")
_PAGES = 31 * 532 * 512 * 4 // 4096  # 8 246 pages of 4 KiB per result


def _child(code: str, env_value: str | None) -> list[str]:
    """What a fresh Python process running ``code`` prints (split), ``HSICAM_KEEP_FREED_MEMORY`` set to
    ``env_value`` (None: unset)."""
    env = {k: v for k, v in os.environ.items() if k != memory_mod.KEEP_FREED_MEMORY_ENV}
    if env_value is not None:
        env[memory_mod.KEEP_FREED_MEMORY_ENV] = env_value
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def _faults_per_operation(env_value: str | None) -> tuple[bool, float]:
    applied, faults = _child(_OPERATIONS, env_value)
    return applied == "True", float(faults)


@pytest.mark.skipif(not _glibc(), reason="glibc's allocator only")
def test_freed_memory_is_reused_instead_of_faulted_in_again():
    applied, faults = _faults_per_operation(None)
    assert applied
    assert faults < 0.25 * _PAGES, faults  # measured: 340 to 1 400 (the heap settles in a few operations)
    # the opt-out: glibc as it is, every page of every result faulted in again
    applied, faults = _faults_per_operation("0")
    assert not applied
    assert faults > 0.95 * _PAGES, faults


_RELEASE = textwrap.dedent("""
    import os, torch
    from hsicam.memory import keep_freed_memory, release_freed_memory
    applied = keep_freed_memory()
    rss = lambda: int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    x = torch.rand(1, 31, 532, 512)
    start = rss()
    for _ in range(10):
        ys = [x * k for k in range(4)]
        del ys
    kept = rss()
    release_freed_memory()
    print(applied, kept - start, rss() - start)
""")


@pytest.mark.skipif(not _glibc() or not Path("/proc/self/statm").is_file(), reason="glibc and Linux's /proc only")
@pytest.mark.parametrize("env_value", [None, "0"])
def test_release_hands_the_kept_memory_back(env_value):
    """After four 32 MiB results were made and freed ten times the kept heap holds about them (~130 MiB resident
    beyond the start); :func:`release_freed_memory` gives it back. Under glibc's defaults nothing was kept and the
    release does nothing."""
    applied, kept_mib, after_mib = printed = _child(_RELEASE, env_value)
    if env_value is None:
        assert applied == "True" and float(kept_mib) > 30 and float(after_mib) < 0.3 * float(kept_mib), printed
    else:
        assert applied == "False" and abs(float(kept_mib)) < 16 and abs(float(after_mib)) < 16, printed


def test_tiles_release_the_kept_memory_between_them(monkeypatch):
    """reconstruct_tiled hands the kept heap back after each tile (peak of a 2048² capture 4.8 → 3.6–3.8 GiB)."""
    import torch

    import hsicam.engine.inference as inference

    calls = []
    monkeypatch.setattr(inference, "release_freed_memory", lambda: calls.append(1))
    sensor = torch.rand(1, 1, 40, 30)
    out = inference.reconstruct_tiled(lambda s: s.repeat(1, 2, 1, 1), sensor, tile_px=16, halo_px=2)
    assert len(calls) == 3 * 2 and torch.equal(out, sensor.repeat(1, 2, 1, 1))


def test_the_hsicam_command_keeps_freed_memory_and_main_alone_does_not(monkeypatch):
    calls = []
    monkeypatch.setattr(memory_mod, "keep_freed_memory", lambda: calls.append(1) or True)
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0 and not calls
    monkeypatch.setattr(sys, "argv", ["hsicam", "--help"])
    with pytest.raises(SystemExit) as exc:
        cli.entry()
    assert exc.value.code == 0 and calls == [1]
    # the console script and `python -m hsicam` both go through entry()
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["hsicam"] == "hsicam.cli:entry"
    assert "entry()" in (ROOT / "src/hsicam/__main__.py").read_text()
