"""The hsicam command keeps freed memory for the next tensor (:func:`hsicam.memory.keep_freed_memory`).

What is measured is the kernel's own count of the pages a process touched for the first time (minor page
faults, ``getrusage``): a 64 MiB tensor allocated again right after the last one was freed needs ~16 000
new pages under glibc's defaults (it gets a fresh mapping each time) and none once the memory is kept.
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

ROOT = Path(__file__).resolve().parents[1]


def _glibc() -> bool:
    try:
        return bool(os.confstr("CS_GNU_LIBC_VERSION"))
    except (AttributeError, ValueError, OSError):
        return False


_REALLOCATE = textwrap.dedent("""
    import resource, torch
    from hsicam.memory import keep_freed_memory
    applied = keep_freed_memory()
    faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = torch.empty(1 << 24); a.fill_(1.0); del a          # 64 MiB, written, freed
    before = faults()
    b = torch.empty(1 << 24); b.fill_(1.0)                  # the same size again
    print(applied, faults() - before)
""")
_PAGES = (1 << 24) * 4 // 4096  # 16 384 pages of 4 KiB


def _reallocate(env_value: str | None) -> tuple[bool, int]:
    env = {k: v for k, v in os.environ.items() if k != memory_mod.KEEP_FREED_MEMORY_ENV}
    if env_value is not None:
        env[memory_mod.KEEP_FREED_MEMORY_ENV] = env_value
    out = subprocess.run([sys.executable, "-c", _REALLOCATE], env=env, capture_output=True, text=True, check=True)
    applied, faults = out.stdout.split()
    return applied == "True", int(faults)


@pytest.mark.skipif(not _glibc(), reason="glibc's allocator only")
def test_freed_memory_is_reused_instead_of_faulted_in_again():
    applied, faults = _reallocate(None)
    assert applied
    assert faults < 0.05 * _PAGES, faults
    # the opt-out: glibc as it is, every page of the new tensor faulted in again
    applied, faults = _reallocate("0")
    assert not applied
    assert faults > 0.9 * _PAGES, faults


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
