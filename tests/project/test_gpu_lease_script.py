"""scripts/gpu_lease.sh (two time-boxed demos side by side and the CUDA checks, in one call on a lent GPU
machine) runs end to end here on the CPU with the tiny preset: what comes back is the six files it names, each
demo calibrated on short epochs but sized for the preset's own, and the cores shared out."""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import re
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_gpu_lease_script_on_cpu(tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "DEVICE": "cpu", "A_PRESET": "tiny", "B_PRESET": "tiny", "A_MINUTES": "0.15",
           "B_MINUTES": "0.15", "A_CALIB_PATCHES": "8", "B_SETS": "data.synthetic_n=24 data.val_pool=12",
           "LIMIT": "300", "OUT": str(out), "PYTHON": sys.executable, "TMPDIR": str(tmp_path)}
    run = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_lease.sh")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert {p.name for p in out.iterdir()} == {"a.log", "b.log", "a_demo.tar.gz", "b_demo.tar.gz", "gpu_checks.log",
                                               "logs.tar.gz"}
    assert "threads and" in run.stdout and "DataLoader workers for each demo" in run.stdout
    # the CUDA tests ran (skipped only on a machine without CUDA: where there is one, all 9 pass, whatever DEVICE
    # says) and so did the smoke training through bf16/channels_last/compile
    checks = (out / "gpu_checks.log").read_text()
    import torch

    outcome = "passed" if torch.cuda.is_available() else "skipped"
    summary = re.search(r"^=* ?(\d+ (?:passed|skipped|failed|errors?|deselected)\b.*) in [0-9.]+s", checks, re.M)
    assert summary and summary.group(1).startswith(f"9 {outcome}"), checks[-3000:]  # all 9, none failed
    assert not re.search(r"failed|error", summary.group(1)), checks[-3000:]
    assert "smoke training: exit 0" in checks, checks[-3000:]
    for name in ("a", "b"):
        log = (out / f"{name}.log").read_text()
        # a calibration of 8-patch epochs (2 steps) still sizes the demo's epochs of tiny's own 16 patches (4 steps)
        assert re.search(r"calibration: [0-9.]+ s per step, [0-9.]+ s per validation, 4 steps per epoch", log), log
        status = int(re.search(rf"gpu_session.sh {name} \(tiny\): exit (\d+)", log).group(1))
        assert status in (0, 75), log  # 75: the time budget stopped it, the partly trained run scored
        with tarfile.open(out / f"{name}_demo.tar.gz") as tar:
            scored = "results.json" if status == 0 else "eval-partial/results.json"
            assert json.load(tar.extractfile(f"./{scored}"))["mean"]["psnr"] > 0
    assert "PRESET=tiny" in (out / "a.log").read_text()
    with tarfile.open(out / "logs.tar.gz") as tar:
        names = set(tar.getnames())
    assert {"./a/demo.log", "./b/demo.log", "./gpu_checks.log"} <= names
    assert sum(n.endswith("/calib.log") for n in names) == 2  # both calibrations' logs, from their work folders


@pytest.mark.slow
def test_gpu_lease_script_brings_back_a_demo_stopped_at_its_limit(tmp_path):
    """A demo that LIMIT stops before it packs (the first lease's fate) still comes back: its demo folder as it was,
    the run's config and metrics in it (LIMIT 90 s: past the tiny calibration on a busy 2-core machine, well before a
    3-minute demo ends)."""
    out = tmp_path / "out"
    env = {**os.environ, "DEVICE": "cpu", "A_PRESET": "tiny", "B_PRESET": "tiny", "A_MINUTES": "3", "B_MINUTES": "3",
           "LIMIT": "90", "OUT": str(out), "PYTHON": sys.executable, "TMPDIR": str(tmp_path)}
    run = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_lease.sh")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    for name in ("a", "b"):
        log = (out / f"{name}.log").read_text()
        assert f"gpu_session.sh {name} (tiny): exit 124" in log, log[-2000:]
        assert "packed the demo folder as it was at the stop (exit 124)" in log
        with tarfile.open(out / f"{name}_demo.tar.gz") as tar:
            names = set(tar.getnames())
        assert {"./run/config.yaml", "./run/metrics.jsonl"} <= names
        assert not any(n.startswith("./run/checkpoints/") for n in names)


def test_the_cuda_tests_the_lease_names_are_the_ones_gpu_session_selects():
    """gpu_lease.sh names its CUDA tests by node id; gpu_session.sh selects them by ``-m "cuda and not slow"``:
    every test the lease names must carry the ``cuda`` mark (registered in pyproject.toml) and not ``slow``
    (test_cpu_equals_cuda had no mark, so the session ran 2 of the 9 CUDA tests)."""
    assert '-m "cuda and not slow"' in (ROOT / "scripts" / "gpu_session.sh").read_text()
    assert '"cuda: ' in (ROOT / "pyproject.toml").read_text()
    named = re.findall(r'"tests/((?:\w+/)*test_\w+)\.py::(\w+)"', (ROOT / "scripts" / "gpu_lease.sh").read_text())
    assert {name for _, name in named} == {"test_cpu_equals_cuda", "test_cpu_and_cuda_agree"}, named
    for module, name in named:
        marks = {m.name for m in getattr(getattr(_test_module(module), name), "pytestmark", [])}
        assert "cuda" in marks and "slow" not in marks, (module, name, marks)


def _test_module(path: str):
    """The test file tests/PATH.py as a module, by its path: a sub-folder of tests/ is on sys.path only once pytest has
    collected a file there."""
    spec = importlib.util.spec_from_file_location(Path(path).name, ROOT / "tests" / f"{path}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_gpu_session_script_says_when_its_python_has_no_torch(tmp_path):
    """docs/training.md's CPU try of scripts/gpu_session.sh, run with a python that has no torch (the script's default
    python3 on this machine), exited 1 with nothing said: the import error went into env.txt only. Now one line naming
    the python and PYTHON, before any work folder is made."""
    no_torch = tmp_path / "python"
    no_torch.write_text('#!/bin/sh\nexit 1\n')  # a python whose `import torch` fails
    no_torch.chmod(0o755)
    work = tmp_path / "tmp"
    work.mkdir()
    env = {**os.environ, "DEVICE": "cpu", "PRESET": "tiny", "PYTHON": str(no_torch), "TMPDIR": str(work)}
    run = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_session.sh")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 1
    assert run.stderr.strip() == (f"gpu_session.sh: {no_torch} cannot import torch; set PYTHON to the project's python "
                                  "(e.g. PYTHON=.venv/bin/python)")
    assert list(work.iterdir()) == []  # no work folder left behind
