"""Stopping a training cleanly (hsicam.engine.stopping): SIGTERM, Ctrl-C and the budget
train.max_minutes save the checkpoint of the step they stop at, and a resume goes on exactly."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from cli_helpers import HSICAM, run_cli
from hsicam.config import load_config
from hsicam.engine.stopping import BUDGET_EXIT_CODE, StopRequests
from hsicam.engine.train import train
from hsicam.errors import ConfigError, TrainingStopped
from hsicam.runs.checkpoint import read_weights


def _manifest(run: Path) -> dict:
    return json.loads((run / "checkpoints.json").read_text())


def _last_weights(run: Path) -> dict[str, torch.Tensor]:
    return read_weights(run / _manifest(run)["last"]["dir"] / "model.safetensors")[0]


# ------------------------------------------------------------------------------------------------
# StopRequests alone
# ------------------------------------------------------------------------------------------------
def test_budget_counts_the_next_step():
    start = time.monotonic() - 59.5  # 59.5 s of a 1-minute budget spent
    stop = StopRequests(max_minutes=1.0, start=start, signals=False)
    assert stop.reason(next_step_s=0.1) is None
    assert stop.reason(next_step_s=1.0) == "train.max_minutes=1 reached"
    assert stop.exit_code() == BUDGET_EXIT_CODE == 75
    assert StopRequests(None, start=start - 1e6, signals=False).reason(1e6) is None  # no budget


def test_sigint_armed_stops_once_then_interrupts_and_handlers_are_restored():
    before = signal.getsignal(signal.SIGINT)
    with StopRequests() as stop:
        with pytest.raises(KeyboardInterrupt):  # not armed (data preparation): Ctrl-C interrupts at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        stop.armed = True
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.01)
        assert stop.reason() == "SIGINT" and stop.exit_code() == 130
        with pytest.raises(KeyboardInterrupt):  # a second Ctrl-C: at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
    assert signal.getsignal(signal.SIGINT) is before


def test_an_ignored_signal_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with StopRequests() as stop:
            stop.armed = True
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
            assert stop.reason() is None
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_second_sigterm_ends_the_process():
    code = textwrap.dedent("""
        import os, signal, time
        from hsicam.engine.stopping import StopRequests
        with StopRequests() as stop:
            stop.armed = True
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            print(stop.reason(), stop.exit_code(), flush=True)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
            print("still running", flush=True)
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.stdout.split() == ["SIGTERM", "143"]
    assert res.returncode == -signal.SIGTERM


@pytest.mark.parametrize("value", ["0", "-1", ".inf", ".nan"])
def test_bad_budget_is_a_config_error(value):
    with pytest.raises(ConfigError, match="train.max_minutes"):
        load_config("tiny", [f"train.max_minutes={value}"])


# ------------------------------------------------------------------------------------------------
# The loop
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["mid-epoch", "epoch-end"])
def test_budget_stop_then_resume_matches_uninterrupted_run(tmp_path, cache_env, where):
    """A budget spent before the first step ends stops after step 1 — inside an epoch (4 steps per
    epoch) or at its end (1 step per epoch) — with that step's checkpoint; the resume without a
    budget ends with the weights of a run never stopped."""
    keys = ["train.epochs=3"] + (["data.patches_per_epoch=4", "train.batch_size=4"] if where == "epoch-end" else [])
    full = train(load_config("tiny", keys), tmp_path / "full", progress=False)
    with pytest.raises(TrainingStopped) as info:
        train(load_config("tiny", [*keys, "train.max_minutes=1e-9"]), tmp_path / "part", progress=False)
    stopped = info.value
    assert (stopped.step, stopped.exit_code) == (1, BUDGET_EXIT_CODE)
    assert stopped.total_steps == full["step"] and "max_minutes" in stopped.reason
    assert _manifest(tmp_path / "part")["last"]["step"] == 1  # the step it stopped at, saved
    assert not (tmp_path / "part" / "linear_step.safetensors").exists()  # written only when training ends
    resumed = train(load_config("tiny", keys), tmp_path / "part", resume=True, progress=False)
    assert resumed["step"] == full["step"]
    wa, wb = _last_weights(tmp_path / "full"), _last_weights(tmp_path / "part")
    for k in wa:
        torch.testing.assert_close(wb[k], wa[k], rtol=0, atol=1e-6, msg=k)


def test_budget_stop_on_the_command_line(tmp_path, cache_env):
    run = tmp_path / "run"
    res = run_cli("train", "--config", "tiny", "--out", str(run), "--set", "train.max_minutes=1e-9",
                  env={"HSICAM_CACHE": str(cache_env)})
    assert res.returncode == BUDGET_EXIT_CODE, res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last == (f"hsicam: {run}: training stopped at step 1 of 8 (train.max_minutes=1e-09 reached); the checkpoint "
                    f"of step 1 is saved; go on with: hsicam train --out {run} --resume")
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_saves_the_step_it_stops_at(tmp_path, cache_env, sig):
    """A scheduler's SIGTERM (or Ctrl-C) mid-training: the process ends with 128 + the signal's
    number after saving the checkpoint of the step it stopped at (not the last periodic one), and
    the resume finishes the run."""
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env)}
    args = [str(HSICAM), "train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=40",
            "--set", "train.checkpoint_every_steps=1000"]
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 300
        while time.time() < deadline and not (run / "metrics.jsonl").exists():
            time.sleep(0.05)
        time.sleep(0.5)
        assert proc.poll() is None, "training finished before it could be stopped; make it longer"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, err
    found = re.search(rf"training stopped at step (\d+) of 160 \({sig.name}\); the checkpoint of step \1 is saved; "
                      rf"go on with: hsicam train --out {re.escape(str(run))} --resume", err)
    assert found, err
    step = int(found.group(1))
    assert _manifest(run)["last"]["step"] == _manifest(run)["state"]["global_step"] == step > 0
    assert "Traceback" not in err
    res = run_cli("train", "--out", str(run), "--resume", env={"HSICAM_CACHE": str(cache_env)})
    assert res.returncode == 0, res.stderr
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 160


DDP_BUDGET_SCRIPT = """
import os, sys, torch
from hsicam.config import load_config
from hsicam.engine.train import train
from hsicam.errors import TrainingStopped
torch.set_num_threads(1)
cfg = load_config("tiny", ["train.epochs=2", "data.val_fraction=0.0", "train.max_minutes=1e-9"])
try:
    train(cfg, sys.argv[1], progress=False)
    stopped = "finished"
except TrainingStopped as exc:
    stopped = str(exc.step)
open(sys.argv[1] + ".rank" + os.environ.get("RANK", "0"), "w").write(f"{stopped} {torch.distributed.is_initialized()}")
"""


def test_ddp_ranks_stop_at_the_same_step(tmp_path, cache_env):
    script = tmp_path / "ddp_budget.py"
    script.write_text(DDP_BUDGET_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env)}
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                          str(script), str(tmp_path / "ddp")], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    # both ranks stopped after step 1, and the group fit created was destroyed
    assert [(tmp_path / f"ddp.rank{r}").read_text() for r in (0, 1)] == ["1 False", "1 False"]
    assert _manifest(tmp_path / "ddp")["last"]["step"] == 1
