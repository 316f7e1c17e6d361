"""scripts/calibrate_epochs.py (gpu_session.sh's time box): the step time is read per step, not per logged line —
session 49's lease sized its demos from a calibration that divided by the lines of a run logging every 20th step."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))
from calibrate_epochs import seconds_per_step_and_validation  # noqa: E402


def _records(steps_per_epoch: int, step_s: float, val_s: float, start_s: float, log_every: int) -> list[dict]:
    """A 2-epoch calibration run's metrics.jsonl: steps of ``step_s`` after ``start_s`` of start-up, a validation of
    ``val_s`` after each epoch, the train loss logged every ``log_every`` steps, the final record."""
    out, t = [], start_s
    for epoch in range(2):
        for i in range(steps_per_epoch):
            t += step_s
            step = epoch * steps_per_epoch + i + 1
            if step % log_every == 0:
                out.append({"step": step, "epoch": epoch, "train_loss": 0.1, "lr": 1e-4, "elapsed_s": t})
        t += val_s
        out.append({"step": (epoch + 1) * steps_per_epoch, "epoch": epoch + 1, "val_psnr": 30.0})
    out.append({"step": 2 * steps_per_epoch, "epoch": 2, "final": True, "elapsed_s": t})
    return out


@pytest.mark.parametrize("log_every", [1, 3, 20])
def test_step_and_validation_times_whatever_the_logging(log_every):
    per_step, val_s = seconds_per_step_and_validation(_records(60, 0.15, 10.0, 30.0, log_every))
    assert per_step == pytest.approx(0.15)
    assert val_s == pytest.approx(10.0)  # the last logged step is the epoch's last here (60 is a multiple of each)


def test_a_run_logging_one_line_an_epoch_falls_back_to_its_whole_time():
    per_step, _ = seconds_per_step_and_validation(_records(20, 0.2, 1.0, 0.0, 20))
    assert per_step == pytest.approx((40 * 0.2 + 2 * 1.0) / 40)  # start-up-free run: every second of it over 40 steps


def test_the_epochs_are_the_presets_own(tmp_path):
    """Calibrated on 8-patch epochs of tiny (2 steps of 4), sized for tiny's own 16-patch epochs (4 steps)."""
    metrics = tmp_path / "metrics.jsonl"
    metrics.write_text("".join(json.dumps(r) + "\n" for r in _records(2, 0.5, 1.0, 5.0, 1)))
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "calibrate_epochs.py"), str(metrics), "1", "tiny",
                          "--set", "train.device=cpu"], capture_output=True, text=True,
                         env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    assert int(run.stdout) == int(60 / (0.5 * 4 + 1.0))  # 20 epochs of 4 steps and a validation in a minute
    assert "4 steps per epoch" in run.stderr
