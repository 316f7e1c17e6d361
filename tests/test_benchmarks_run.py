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


def test_bench_networks_times_a_preset_given_and_refuses_a_missing_device():
    """``bench_networks.py --config``: the given preset's camera, batch and own network are timed (the tiny preset
    here: a second of work); ``--device cuda`` where there is none is one clear usage error, not a traceback."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    script = str(BENCHMARKS / "bench_networks.py")
    proc = subprocess.run([sys.executable, script, "--config", "tiny", "--kinds", "quick", "--steps", "1", "--repeats",
                           "1"], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = json.loads(proc.stdout)
    assert (printed["preset"], printed["device"], printed["batch"], printed["patch_px"]) == ("tiny", "cpu", 4, 16)
    timed = printed["kinds"]["quick"]
    assert timed["step_s"] >= timed["network_s"] > 0 and timed["optics_s"] > 0 and timed["infer_512_s"] > 0
    assert timed["params_M"] < 0.01  # tiny's own network, not the quick preset's 1.7 M parameters
    import torch

    if not torch.cuda.is_available():
        proc = subprocess.run([sys.executable, script, "--device", "cuda"], capture_output=True, text=True, timeout=120,
                              env=env)
        assert proc.returncode == 2 and "no CUDA device" in proc.stderr and "Traceback" not in proc.stderr
