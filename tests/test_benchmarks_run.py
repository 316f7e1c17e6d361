"""The benchmark scripts run: a small size of ``benchmarks/bench_baselines.py`` end to end (its DOE row crashed for
sessions unnoticed, since nothing ran it, when the quick preset took the linear consistency step)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_bench_baselines_times_every_method_on_a_small_scene(tmp_path):
    out = tmp_path / "baselines.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "bench_baselines.py"), "--size", "32", "--repeats", "1",
                           "--out", str(out)], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = json.loads(proc.stdout)
    assert json.loads(out.read_text()) == printed
    seconds = printed["seconds_per_scene"]
    assert set(seconds) == {"dd-cassi-gaptv", "dd-cassi-desci", "dd-cassi-choi", "dd-cassi-rdn", "doe-rdn"}
    assert all(v > 0 for v in seconds.values())
    assert printed["scene"] == [31, 32, 32]
    assert set(printed["doe_rdn_speedup"]) == set(seconds) - {"doe-rdn"}
