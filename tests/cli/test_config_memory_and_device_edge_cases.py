"""Guards found by mutation testing of the configuration (hsicam.config), the output helpers (hsicam.io), the memory
budget (hsicam.memory) and the device checks (hsicam.devices): each test kills a hand-made mutant (a bound moved by
one, a dropped check, a wrong key name, a skipped branch) that the rest of the suite let through. References are
independent of the code under test: the exact one-line error a user sees, values written out by hand, PyYAML's own
reading of a document, cgroup trees written here as the kernel lays them out.
"""

from __future__ import annotations

import re

import pytest

from hsicam.config import Config, identity_differences, load_config, training_differences
from hsicam.errors import ConfigError


def refused(overrides: list[str], message: str) -> None:
    """load_config with ``overrides`` over the defaults is a ConfigError whose text is exactly ``message``."""
    with pytest.raises(ConfigError) as exc:
        load_config(None, overrides)
    assert str(exc.value) == message


# --------------------------------------------------------------------------------------------
# config.py: ranges, each at its edge (the value just inside loads, the one just outside is refused)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides, message", [
    (["camera.doe.quantization_levels=1"],
     "camera.doe.quantization_levels must be in [2, 65536] (height levels of the lithography), got 1"),
    (["camera.doe.max_height_nm=2e6"],
     "camera.doe.max_height_nm must be at most 1000000 nm (1 mm, far beyond any DOE's relief), got 2e+06"),
    (["camera.cfa.period=0"], "camera.cfa.period must be >= 1, got 0"),
    (["camera.sensor.bit_depth=33"], "camera.sensor.bit_depth must be in 1..32, got 33"),
    (["camera.sensor.sigma=-0.01"], "camera.sensor.sigma must be in [0, 1] (σ of the image scaled to full scale 1; "
                                    "more buries any signal), got -0.01"),
    (["camera.cassi.mask_density=0"], "camera.cassi.mask_density must be in (0, 1], got 0.0"),
    (["camera.cassi.prism_apex_deg=90"], "camera.cassi.prism_apex_deg must be below 90, got 90.0"),
    (["train.sigma_height_nm=[20, 10]"], "train.sigma_height_nm must be [lo, hi] with 0 <= lo <= hi, got [20.0, 10.0]"),
    (["data.val_fraction=1"], "data.val_fraction must be in [0, 1), got 1.0"),
    (["data.val_pool=1"], "data.val_pool must be >= 2 scenes or null, got 1"),
    (["model.consistency.iterations=1", "model.consistency.kind=linear", "model.consistency.tv_weight=0.03"],
     "model.consistency.tv_weight=0.03 acts in the Landweber steps, and kind=linear takes none (landweber_after=0): "
     "set model.consistency.landweber_after, e.g. 24, or model.consistency.tv_weight=0 for the linear step alone"),
    (["camera.cfa.period=10", "model.consistency.iterations=1", "model.consistency.kind=linear",
      "model.consistency.window_px=9"],
     "model.consistency.window_px=9 is narrower than the CFA period 10: the linear step's filters must see every CFA "
     "phase (flat-field constraint); set it to at least 11"),
    (["train.freeze=doe"], "config key 'train.freeze' must be a list, got 'doe'"),
])
def test_a_value_just_outside_its_range_is_refused_with_its_one_line(overrides, message):
    refused(overrides, message)


def test_the_values_at_the_edges_of_those_ranges_still_load():
    cfg = load_config(None, ["camera.doe.quantization_levels=2", "camera.doe.max_height_nm=1e6", "camera.cfa.period=1",
                             "camera.sensor.bit_depth=32", "camera.sensor.sigma=0", "camera.cassi.mask_density=1",
                             "camera.cassi.prism_apex_deg=89.9", "train.sigma_height_nm=[10, 10]",
                             "data.val_fraction=0", "data.val_pool=2"])
    assert (cfg.camera.doe.quantization_levels, cfg.camera.cfa.period, cfg.camera.sensor.bit_depth) == (2, 1, 32)
    cfg = load_config(None, ["camera.cfa.period=10", "model.consistency.iterations=1", "model.consistency.kind=linear",
                             "model.consistency.window_px=11", "model.consistency.tv_weight=0.03",
                             "model.consistency.landweber_after=4"])
    assert cfg.model.consistency.window_px == 11


def test_a_group_frozen_twice_is_frozen_once():
    """train.freeze is a set of group names: a repeat counts once, in the order first given."""
    assert load_config(None, ["train.freeze=[doe, cfa, doe]"]).train.freeze == ["doe", "cfa"]


# --------------------------------------------------------------------------------------------
# config.py: YAML
# --------------------------------------------------------------------------------------------
def test_yaml_12_octal_integers_are_read_in_base_8():
    assert load_config(None, ["train.seed=0o17", "data.synthetic_n=0o1_0"]).train.seed == 15
    assert load_config(None, ["data.synthetic_n=0o1_0"]).data.synthetic_n == 8


@pytest.mark.parametrize("text", ["0x_", "0o_", "0x__", "0o__"])
def test_a_hex_or_octal_prefix_without_digits_is_a_config_error_not_a_traceback(text, tmp_path):
    """`seed: 0x_` matched the YAML 1.2 integer pattern (digits optional after the prefix) and PyYAML's int()
    raised a ValueError: a traceback from `hsicam train`, in a file or in --set alike."""
    refused([f"train.seed={text}"], f"config key 'train.seed' must be an integer, got '{text}'")
    path = tmp_path / "c.yaml"
    path.write_text(f"train:\n  seed: {text}\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value) == f"{path}: config key 'train.seed' must be an integer, got '{text}'"


def test_two_merge_keys_in_one_mapping_are_not_a_key_given_twice():
    """`<<:` twice merges both anchors (PyYAML's merge); only real keys given twice are refused."""
    import yaml

    from hsicam.config import strict_yaml

    text = "a: &a {epochs: 3}\nb: &b {batch_size: 2}\ntrain:\n  <<: *a\n  <<: *b\n  lr: 0.001\n"
    assert strict_yaml(text)["train"] == yaml.safe_load(text)["train"] == {"epochs": 3, "batch_size": 2, "lr": 0.001}


def test_an_empty_run_config_is_refused_with_the_callers_words(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("# nothing here\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path, empty="the run's config.yaml is damaged")
    assert str(exc.value) == f"{path}: empty config (no settings); the run's config.yaml is damaged"
    assert load_config(path) == Config()  # without `empty`: the defaults


# --------------------------------------------------------------------------------------------
# config.py: what a resumed run may change (RUN_IDENTITY_KEYS) and what a training is (RUNTIME_ONLY_KEYS)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("override, difference", [
    ("data.split_seed=1", "data.split_seed: 0 → 1"),
    ("data.synthetic_n=16", "data.synthetic_n: 32 → 16"),
    ("data.patch_px=32", "data.patch_px: 64 → 32"),
    ("data.holdout_sources=none", "data.holdout_sources: 'nist-philips,rawtoaces' → 'none'"),
    ("data.val_pool=8", "data.val_pool: None → 8"),
    ("data.root=/somewhere", "data.root: None → '/somewhere'"),
    ("camera.cfa.period=4", "camera.cfa.period: 9 → 4"),
])
def test_a_resume_may_not_change_the_runs_scenes_split_or_camera(override, difference):
    assert identity_differences(Config(), load_config(None, [override])) == [difference]


@pytest.mark.parametrize("override", ["train.epochs=3", "train.keep_weights=last", "data.num_workers=0",
                                      "model.consistency.iterations=2", "train.lr=0.001"])
def test_a_resume_may_change_how_the_run_goes_on(override):
    assert identity_differences(Config(), load_config(None, [override])) == []


@pytest.mark.parametrize("override", ["train.keep_weights=last", "train.device=cpu", "data.num_workers=0",
                                      "model.consistency.iterations=2"])
def test_runtime_only_keys_train_the_same_camera(override):
    assert training_differences(Config(), load_config(None, [override])) == []


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
    from hsicam.memory import MEMORY_BUDGET_ENV, machine_memory_bytes

    assert machine_memory_bytes() == 16 * 2**30
    machine["cgroup"] = 6 * 2**30
    assert machine_memory_bytes() == 6 * 2**30
    machine["left"] = 3 * 2**30
    assert machine_memory_bytes() == 3 * 2**30
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "512")
    assert machine_memory_bytes() == 512 * 2**20


def test_the_budget_falls_back_to_8_gib_when_no_memory_can_be_read(machine):
    from hsicam.memory import machine_memory_bytes, memory_budget_bytes

    machine["phys"] = None
    assert memory_budget_bytes() == 8 * 2**30
    assert machine_memory_bytes() is None
    machine["left"] = 2 * 2**30
    assert memory_budget_bytes() == 2**30  # half of what the address space has left


@pytest.mark.parametrize("nbytes, text", [(1023, "1023 B"), (1024, "1 KiB"), (2**20, "1 MiB"), (1536 * 2**30, "1.5 TiB")])
def test_format_bytes_switches_unit_at_each_power_of_1024(nbytes, text):
    from hsicam.memory import format_bytes

    assert format_bytes(nbytes) == text


def test_format_bytes_of_an_integer_beyond_float_is_still_in_pib():
    from hsicam.memory import format_bytes

    text = format_bytes(3 * 2**50 * 10**400)  # 3e400 PiB: float(n) overflows
    assert re.fullmatch(r"3(\.0*)?e\+400 PiB", text), text


# --------------------------------------------------------------------------------------------
# devices.py
# --------------------------------------------------------------------------------------------
def test_dist_env_reads_rank_world_and_local_rank(monkeypatch):
    from hsicam.devices import dist_env

    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert dist_env() == (0, 1, 0)
    monkeypatch.setenv("RANK", "5")
    monkeypatch.setenv("WORLD_SIZE", "8")
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert dist_env() == (5, 8, 1)


def test_a_cuda_index_beyond_the_machines_devices_is_named(monkeypatch):
    import torch

    from hsicam.devices import device_problem

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert device_problem("cuda:1") is None and device_problem("cuda") is None
    assert device_problem("cuda:2") == "this machine has 2 CUDA device(s), cuda:0 to cuda:1"


def test_mps_without_an_mps_device_is_refused(monkeypatch):
    import torch

    from hsicam.devices import device_problem

    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert device_problem("mps") == "no MPS device is available here; use cpu"
    assert device_problem("cpu") is None
    assert device_problem("meta") == "hsicam runs on cpu, cuda or mps"
    assert device_problem("banana") == "unknown device; use cpu, cuda, cuda:N or mps"


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
    assert mem.machine_memory_bytes() == 12 * 2**30
    kernel32.GlobalMemoryStatusEx = lambda ref: 0  # the call failed
    assert mem._physical_memory_bytes() is None
    assert mem.memory_budget_bytes() == 8 * 2**30
