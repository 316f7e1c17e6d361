"""Mutation guards of the memory budget (hsicam.memory), moved here from the cli floor's configuration file: each test
kills a hand-made mutant (a bound moved by one, a dropped check, a skipped branch) that the rest of the suite let
through. References are independent of the code under test: cgroup trees written here as the kernel lays them out,
values written out by hand, the documented 64-byte MEMORYSTATUSEX of Windows.
"""

from __future__ import annotations

import re

import pytest


# --------------------------------------------------------------------------------------------
# memory.py
# --------------------------------------------------------------------------------------------
def _cgroup_tree(root, files: dict[str, str], proc: str):
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text + "\n")
    (root / "proc_cgroup").write_text(proc)
    return root / "proc_cgroup", root


def test_cgroup_v1s_no_limit_number_alone_is_no_limit(tmp_path):
    """v1 writes 'no limit' as a page-rounded 2^63 - 1 (9223372036854771712); a tree holding only that has no limit."""
    from hsicam.memory import _cgroup_memory_limit_bytes as limit

    huge = str(2**63 - 4096)
    assert limit(*_cgroup_tree(tmp_path, {"memory/memory.limit_in_bytes": huge,
                                          "memory/job/memory.limit_in_bytes": huge}, "4:memory:/job\n0::/\n")) is None


def test_the_lowest_of_two_nested_cgroup_limits_is_the_limit(tmp_path):
    """A slice of 1 GiB holding a job of 2 GiB: the job gets at most 1 GiB."""
    from hsicam.memory import _cgroup_memory_limit_bytes as limit

    assert limit(*_cgroup_tree(tmp_path, {"memory.max": "max", "slice/memory.max": str(2**30),
                                          "slice/job/memory.max": str(2 * 2**30)}, "0::/slice/job\n")) == 2**30


def test_a_v1_memory_controller_mounted_with_others_is_read(tmp_path):
    """/proc/self/cgroup lists every controller of a v1 hierarchy ('7:hugetlb,memory:/job'): memory among them."""
    from hsicam.memory import _cgroup_memory_limit_bytes as limit

    assert limit(*_cgroup_tree(tmp_path, {"memory/job/memory.limit_in_bytes": str(700 * 2**20)},
                               "7:hugetlb,memory:/job\n")) == 700 * 2**20


def _vm_size_bytes() -> int:
    for line in open("/proc/self/status", encoding="ascii"):
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    pytest.skip("no VmSize in /proc/self/status")


def test_the_address_space_left_is_the_limit_less_what_the_process_maps(monkeypatch):
    """Under `ulimit -v` the process's own mappings (VmSize, not its resident memory) count against the limit."""
    import resource

    from hsicam.memory import _address_space_left_bytes

    if not hasattr(resource, "RLIMIT_AS"):
        pytest.skip("no RLIMIT_AS here")
    soft = _vm_size_bytes() + 2**30
    monkeypatch.setattr(resource, "getrlimit", lambda which: (soft, resource.RLIM_INFINITY))
    left = _address_space_left_bytes()
    assert 2**30 - 2**26 <= left <= 2**30  # 1 GiB less whatever was mapped between the two reads


@pytest.fixture
def machine(monkeypatch):
    """A machine of 16 GiB, with the cgroup limit and the address space left set per test."""
    import hsicam.memory as mem

    monkeypatch.delenv(mem.MEMORY_BUDGET_ENV, raising=False)
    state = {"phys": 16 * 2**30, "cgroup": None, "left": None}
    monkeypatch.setattr(mem, "_physical_memory_bytes", lambda: state["phys"])
    monkeypatch.setattr(mem, "_cgroup_memory_limit_bytes", lambda: state["cgroup"])
    monkeypatch.setattr(mem, "_address_space_left_bytes", lambda: state["left"])
    return state


def test_a_whole_commands_memory_is_the_lowest_of_ram_cgroup_and_address_space(machine, monkeypatch):
    from hsicam.memory import MEMORY_BUDGET_ENV, process_memory_limit

    assert process_memory_limit()[0] == 16 * 2**30
    machine["cgroup"] = 6 * 2**30
    assert process_memory_limit()[0] == 6 * 2**30
    machine["left"] = 3 * 2**30
    assert process_memory_limit()[0] == 3 * 2**30
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "512")
    assert process_memory_limit()[0] == 512 * 2**20


def test_the_process_limit_names_the_limit_that_bites(machine, monkeypatch):
    """Under ``ulimit -v`` reconstruct refused with "more than this machine's memory (2.95 GiB)" on a 23 GB machine:
    the words now name the lowest limit, the one that bites."""
    from hsicam.memory import MEMORY_BUDGET_ENV, process_memory_limit

    assert process_memory_limit() == (16 * 2**30, "this machine's memory")
    machine["left"] = 3 * 2**30
    assert process_memory_limit() == (3 * 2**30, "the address space this process has left under its ulimit -v")
    machine["cgroup"] = 2 * 2**30
    n, what = process_memory_limit()
    assert n == 2 * 2**30 and "cgroup" in what
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "512")
    assert process_memory_limit() == (512 * 2**20, f"the limit {MEMORY_BUDGET_ENV} sets")
    monkeypatch.delenv(MEMORY_BUDGET_ENV)
    machine.update(phys=None, cgroup=None, left=None)
    assert process_memory_limit() == (None, "")


def test_the_budget_falls_back_to_8_gib_when_no_memory_can_be_read(machine):
    from hsicam.memory import memory_budget_bytes, process_memory_limit

    machine["phys"] = None
    assert memory_budget_bytes() == 8 * 2**30
    assert process_memory_limit()[0] is None
    machine["left"] = 2 * 2**30
    assert memory_budget_bytes() == 2**30  # half of what the address space has left


@pytest.mark.parametrize("nbytes, text", [(1023, "1023 B"), (1024, "1 KiB"), (2**20, "1 MiB"), (1536 * 2**30, "1.5 TiB"),
                                         (1000 * 2**20, "1000 MiB"), (1023 * 2**30, "1023 GiB"), (999 * 2**20, "999 MiB")])
def test_format_bytes_switches_unit_at_each_power_of_1024(nbytes, text):
    from hsicam.memory import format_bytes

    assert format_bytes(nbytes) == text


def test_format_bytes_of_an_integer_beyond_float_is_still_in_pib():
    from hsicam.memory import format_bytes

    text = format_bytes(3 * 2**50 * 10**400)  # 3e400 PiB: float(n) overflows
    assert re.fullmatch(r"3(\.0*)?e\+400 PiB", text), text


def test_windows_reads_its_ram_by_global_memory_status_ex(monkeypatch):
    """Windows has no os.sysconf: the RAM comes from kernel32's GlobalMemoryStatusEx (simulated here, with the
    struct's documented 64-byte layout), not the fixed 8 GiB fallback that let one allocation take a whole 8 GiB
    laptop's memory; a failing call still falls back."""
    import ctypes
    import types

    import hsicam.memory as mem

    calls = []

    def global_memory_status_ex(ref, total=12 * 2**30):
        status = ref._obj
        calls.append(status.dwLength)
        status.ullTotalPhys = total
        return 1

    kernel32 = types.SimpleNamespace(GlobalMemoryStatusEx=global_memory_status_ex)
    monkeypatch.delattr(mem.os, "sysconf", raising=False)
    monkeypatch.setattr(ctypes, "windll", types.SimpleNamespace(kernel32=kernel32), raising=False)
    monkeypatch.delenv(mem.MEMORY_BUDGET_ENV, raising=False)
    monkeypatch.setattr(mem, "_cgroup_memory_limit_bytes", lambda: None)
    monkeypatch.setattr(mem, "_address_space_left_bytes", lambda: None)
    assert ctypes.sizeof(mem._MemoryStatusEx) == 64  # MEMORYSTATUSEX, sysinfoapi.h
    assert mem._physical_memory_bytes() == 12 * 2**30
    assert calls == [64]  # dwLength set before the call, as the API requires
    assert mem.memory_budget_bytes() == 3 * 2**30  # a quarter of the RAM
    assert mem.process_memory_limit()[0] == 12 * 2**30
    kernel32.GlobalMemoryStatusEx = lambda ref: 0  # the call failed
    assert mem._physical_memory_bytes() is None
    assert mem.memory_budget_bytes() == 8 * 2**30
