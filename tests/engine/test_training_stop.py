"""Stopping a training cleanly (hsicam.engine.stopping): SIGTERM, Ctrl-C and the budget
train.max_minutes save the checkpoint of the step they stop at, and a resume goes on exactly."""

from __future__ import annotations

import json
import logging
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

from conftest import KEEP_THE_GROUP, torchrun_tmp
from cli_helpers import run_cli, signal_a_training
from hsicam.config import load_config
from hsicam.engine.stopping import BUDGET_EXIT_CODE, StopRequests
from hsicam.engine.train import train
from hsicam.errors import ConfigError, TrainingInterrupted, TrainingStopped
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
    assert stop.reason(next_step_s=1.0) == "train.max_minutes=1 reached, the budget of each session"
    assert stop.exit_code() == BUDGET_EXIT_CODE == 75
    assert StopRequests(None, start=start - 1e6, signals=False).reason(1e6) is None  # no budget


def test_sigint_armed_stops_once_then_interrupts_and_handlers_are_restored():
    # as in a terminal: Python's Ctrl-C handler (a test run started with `&`, e.g. by a CI runner, ignores SIGINT)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _sigint_armed_stops_once_then_interrupts()
    finally:
        signal.signal(signal.SIGINT, outer)


def _sigint_armed_stops_once_then_interrupts():
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


def test_under_torchrun_a_second_sigterm_is_the_forwarded_echo_not_a_kill(monkeypatch, caplog):
    """A scheduler's SIGTERM reaches the workers and torchrun, which forwards one more to each: the second one killed a
    worker mid-step before it saved the step it stopped at. Under torchrun it is ignored (torchrun's SIGKILL after its
    grace period is the hard stop); a second Ctrl-C still stops at once."""
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "test")
    with caplog.at_level(logging.WARNING, logger="hsicam"), StopRequests() as stop:
        stop.armed = True
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGTERM)  # killed this process before
        time.sleep(0.01)
        assert stop.reason() == "SIGTERM" and stop.exit_code() == 128 + signal.SIGTERM
    assert "its SIGKILL after the grace period stops at once" in caplog.text


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


def test_a_signal_stop_is_not_swallowed_by_except_exception():
    """A notebook sweep's `except Exception: continue` must not eat a Ctrl-C (probe 27 F02); the
    budget's stop is an ordinary error."""
    assert issubclass(TrainingInterrupted, KeyboardInterrupt) and not issubclass(TrainingInterrupted, Exception)
    assert issubclass(TrainingStopped, Exception)
    stop = TrainingInterrupted("RUN", 3, 8, "SIGINT", 130)
    assert (str(stop), stop.exit_code, stop.finished) == (
        "RUN: training stopped at step 3 of 8 (SIGINT); the checkpoint of step 3 is saved", 130, False)


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
    assert last == (f"hsicam: {run}: training stopped at step 1 of 8 (train.max_minutes=1e-09 reached, the budget of each "
                    "session); the checkpoint "
                    f"of step 1 is saved; go on with: hsicam train --out {run} --resume")
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_saves_the_step_it_stops_at(tmp_path, cache_env, sig):
    """A scheduler's SIGTERM (or Ctrl-C) mid-training: the process ends with 128 + the signal's
    number after saving the checkpoint of the step it stopped at (not the last periodic one), and
    the resume finishes the run."""
    run = tmp_path / "run"
    code, err = signal_a_training(run, cache_env, lambda proc: proc.send_signal(sig),
                                   "--set", "train.checkpoint_every_steps=1000")
    assert code == 128 + sig, err
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


DDP_BUDGET_SCRIPT = KEEP_THE_GROUP + """
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
open(sys.argv[1] + ".rank" + os.environ.get("RANK", "0"), "w").write(
    f"{stopped} {torch.distributed.is_initialized()} {group_references()}")
release_the_group()
"""


def test_ddp_ranks_stop_at_the_same_step_and_resume_under_torchrun(tmp_path, cache_env):
    script = tmp_path / "ddp_budget.py"
    script.write_text(DDP_BUDGET_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env),
           "TMPDIR": str(torchrun_tmp(tmp_path))}
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    run = tmp_path / "ddp"
    res = subprocess.run([*torchrun, str(script), str(run)], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    # both ranks stopped after step 1, and the group fit created was destroyed and is referenced no more
    # (torch._dynamo, imported after the group existed by the deterministic setting or the optimizer, kept 10)
    assert [(tmp_path / f"ddp.rank{r}").read_text() for r in (0, 1)] == ["1 False 0", "1 False 0"]
    assert _manifest(run)["last"]["step"] == 1
    # the documented resume: the same torchrun with `hsicam train --resume` (rank 1 used to be refused
    # as "another process" holding rank 0's lock, probe 27 F03)
    res = subprocess.run([*torchrun, "-m", "hsicam", "train", "--out", str(run), "--resume", "--set",
                          "train.max_minutes=null"], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 8
    assert not (run / ".hsicam-lock").exists()


FINISH_THEN_SIGNAL = """
import os, signal, sys
from hsicam.cli import main
from hsicam.engine.tasks import SystemTask
ends = SystemTask.on_fit_end
def on_fit_end(self, run_dir, summary):  # a SIGTERM while the training's last files are written
    os.kill(os.getpid(), signal.SIGTERM)
    return ends(self, run_dir, summary)
SystemTask.on_fit_end = on_fit_end
sys.exit(main(sys.argv[1:]))
"""


def test_a_signal_after_the_last_step_lets_the_run_finish_then_says_so(tmp_path, cache_env):
    """Probe 27 F05/F06: a signal during the last step or the files after it (the final record, the
    linear step's filters) was dropped (exit 0) or killed the process with no line."""
    run = tmp_path / "run"
    script = tmp_path / "finish.py"
    script.write_text(FINISH_THEN_SIGNAL)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env)}
    res = subprocess.run([sys.executable, str(script), "train", "--config", "tiny", "--out", str(run),
                          "--set", "model.consistency.kind=linear", "--set", "model.consistency.iterations=1"],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 143, res.stderr
    assert res.stderr.strip().splitlines()[-1] == f"hsicam: {run}: training finished (step 8 of 8) before stopping on SIGTERM"
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 8
    assert (run / "linear_step.safetensors").is_file()  # the files after the last step were written


def test_finetune_stopped_during_its_start_validation_resumes(tmp_path, cache_env):
    """Probe 27 F01: a stop while fine-tuning validated its starting weights left a folder that neither
    the command nor --resume accepted; now the step-0 checkpoint is saved and --resume goes on."""
    env = {"HSICAM_CACHE": str(cache_env)}
    run, psf, ft = tmp_path / "run", tmp_path / "psf", tmp_path / "ft"
    assert run_cli("train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1", env=env).returncode == 0
    assert run_cli("psf", "--run", str(run), "--out", str(psf), env=env).returncode == 0
    args = ["finetune", "--run", str(run), "--psf-dir", str(psf), "--out", str(ft), "--epochs", "2"]
    res = run_cli(*args, "--set", "train.max_minutes=1e-9", env=env)  # spent before the start validation ends
    assert res.returncode == BUDGET_EXIT_CODE, res.stderr
    assert "training stopped at step 0 of 8" in res.stderr and "--resume" in res.stderr.splitlines()[-1]
    assert _manifest(ft)["last"]["step"] == 0
    res = run_cli(*args, "--resume", "--set", "train.max_minutes=null", env=env)
    assert res.returncode == 0, res.stderr
    records = [json.loads(x) for x in (ft / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 8


def test_sigterm_to_the_process_group_with_dataloader_workers(tmp_path, cache_env):
    """A scheduler's SIGTERM reaches every process of the job, the DataLoader workers too: they end
    quietly (status 0), the main process stops cleanly at the step's end, and nothing hangs; a
    worker's own crash still ends the command (tests/cli/test_cli_errors.py)."""
    run = tmp_path / "run"
    code, err = signal_a_training(run, cache_env, lambda proc: os.killpg(proc.pid, signal.SIGTERM),
                                   "--set", "data.num_workers=2", "--set", "data.preload=false")
    assert code == 143, err
    assert "(SIGTERM); the checkpoint of step" in err.strip().splitlines()[-1], err
    assert "Traceback" not in err and "exited unexpectedly" not in err
    step = _manifest(run)["last"]["step"]
    res = run_cli("train", "--out", str(run), "--resume", env={"HSICAM_CACHE": str(cache_env)})
    assert res.returncode == 0, res.stderr
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 160 > step


def _signalled_during_start(worker_id: int) -> None:
    """A worker_init_fn: SIGTERM reaches the worker before its handlers exist (a scheduler's signal to the
    process group while an epoch's workers start), then the usual set-up."""
    from hsicam.data.pipeline import leave_stop_signals_to_main

    os.kill(os.getpid(), signal.SIGTERM)
    leave_stop_signals_to_main(worker_id)


class _Numbers(torch.utils.data.Dataset):
    def __len__(self):
        return 4

    def __getitem__(self, i):
        return torch.tensor(i)


def test_a_stop_signal_while_workers_start_does_not_kill_them():
    """The loader's workers start with the stop signals blocked: a SIGTERM sent before their handlers are
    installed waits for them (the worker then serves its batches and ends quietly), where the default action
    would kill it and abort the training on "worker exited unexpectedly". The main process's mask is as before."""
    from hsicam.data.pipeline import _StopSafeLoader

    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    loader = _StopSafeLoader(_Numbers(), batch_size=2, num_workers=1, worker_init_fn=_signalled_during_start)
    assert [b.tolist() for b in loader] == [[0, 1], [2, 3]]
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before


def test_a_signal_during_a_long_validation_stops_it_at_its_next_batch(tmp_path, cache_env, monkeypatch):
    """A validation of many patches used to run to its end after a scheduler's SIGTERM (its notice
    lost); now it ends at its next batch, unrecorded, the step's checkpoint is saved, and the resume
    goes on from that step to the weights and last validation of a run never stopped."""
    from hsicam.engine.tasks import SystemTask

    keys = ["train.epochs=2", "data.val_patches=40", "train.batch_size=4"]  # 10 validation batches
    full = train(load_config("tiny", keys), tmp_path / "full", progress=False)
    real_validate, seen = SystemTask.validate, []

    def sigterm_at_validation_batch(n: int):
        """SystemTask.validate that sends SIGTERM as it hands out the n-th validation batch of the run."""
        def validate(self, loader, device):
            def batches():
                for batch in loader:
                    seen.append(len(batch))
                    if len(seen) == n:
                        os.kill(os.getpid(), signal.SIGTERM)
                    yield batch

            return real_validate(self, batches(), device)

        return validate

    monkeypatch.setattr(SystemTask, "validate", sigterm_at_validation_batch(2))  # mid-way through the first
    run = tmp_path / "run"
    with pytest.raises(TrainingInterrupted) as info:
        train(load_config("tiny", keys), run, progress=False)
    assert info.value.exit_code == 128 + signal.SIGTERM
    assert len(seen) == 2  # it did not score the 8 batches left
    step = info.value.step
    assert step == full["step"] // 2  # the end of epoch 1, where it validated
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert not any("val_psnr" in r for r in records)  # the cut validation is not recorded
    assert _manifest(run)["last"]["step"] == step and _manifest(run)["best"] is None
    monkeypatch.setattr(SystemTask, "validate", real_validate)
    resumed = train(load_config("tiny", keys), run, resume=True, progress=False)
    assert resumed["step"] == full["step"] and resumed["val_psnr"] == pytest.approx(full["val_psnr"], abs=1e-4)
    wa, wb = _last_weights(tmp_path / "full"), _last_weights(run)
    for k in wa:
        torch.testing.assert_close(wb[k], wa[k], rtol=0, atol=1e-6, msg=k)
    # the cut validation is taken again on resume: the history holds both epochs' validations, as the
    # uninterrupted run's does, and the best checkpoint is the same step (it was lost for good: the
    # checkpoint had counted the epoch as done)

    def validations(r):
        return [(x["step"], x["epoch"], round(x["val_psnr"], 4)) for x in map(json.loads, (r / "metrics.jsonl").read_text().splitlines())
                if "val_psnr" in x and not x.get("final")]

    assert validations(run) == validations(tmp_path / "full") and len(validations(run)) == 2
    assert _manifest(run)["best"]["step"] == _manifest(tmp_path / "full")["best"]["step"]

    # in the last epoch's validation a signal lets the training finish, that validation whole: the
    # final record holds its scores, not the previous epoch's (a cut there recorded a finished run
    # with stale scores, which a resume never validated again)
    seen.clear()
    monkeypatch.setattr(SystemTask, "validate", sigterm_at_validation_batch(10 + 2))  # the second (last), mid-way
    last = tmp_path / "last"
    with pytest.raises(TrainingInterrupted) as info:
        train(load_config("tiny", keys), last, progress=False)
    assert info.value.finished and len(seen) == 20  # both validations scored every batch
    final = [json.loads(x) for x in (last / "metrics.jsonl").read_text().splitlines()][-1]
    assert final["final"] and final["step"] == full["step"]
    assert final["val_psnr"] == pytest.approx(full["val_psnr"], abs=1e-6)


def test_a_diverged_training_says_what_its_folder_keeps_and_the_advice_works(tmp_path, cache_env, monkeypatch):
    """A divergence leaves the run folder behind. Its one error line says what the folder keeps (no checkpoint yet;
    later the last checkpoint, from before the divergence) and the command that goes on from it with a lower rate;
    that command, as said, then trains. Before, the line said only "lower the learning rates", and running the same
    command with a lower rate was refused: the folder is not empty. The divergence: a training step's loss is NaN
    after the first of a process at any learning rate above 0.5 (1e308 made it real until session 60 bounded
    train.lr at 1; the tiny preset trains on at 1)."""
    from cli_helpers import run_cli_in_process
    from hsicam.engine.tasks import SystemTask

    step = SystemTask.training_step

    def diverging(self, trainable, scene, generator):  # as 1e308 did: the first step's loss finite, the next NaN
        loss = step(self, trainable, scene, generator)
        self.steps_taken = getattr(self, "steps_taken", 0) + 1
        return loss * float("nan") if self.cfg.train.lr > 0.5 and self.steps_taken > 1 else loss

    monkeypatch.setattr(SystemTask, "training_step", diverging)

    def error_line(res) -> str:  # the last line: the training's progress lines come before it
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
        return res.stderr.strip().splitlines()[-1]

    env = {"HSICAM_CACHE": str(cache_env)}
    run = tmp_path / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(run), "--set", "train.lr=0.9", env=env)
    assert res.returncode == 2
    assert error_line(res) == (f"hsicam: error: training diverged at step 1 (loss nan); lower the learning rates; {run} "
                               f"holds no checkpoint yet; continue with a lower rate: hsicam train --out {run} --resume "
                               "--set train.lr=LR (or start over with --restart)")
    # the advice, with a rate that trains: one epoch (4 steps), then a second epoch at 0.9 diverges at its first step
    ok = run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.lr=1e-3", "--set", "train.epochs=1",
                            env=env)
    assert ok.returncode == 0, ok.stderr
    res = run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.lr=0.9", "--set",
                             "train.epochs=2", env=env)
    assert res.returncode == 2
    assert error_line(res).startswith(f"hsicam: error: training diverged at step 5 (loss nan); lower the learning rates; "
                                      f"{run} keeps the checkpoint of step 4, from before the divergence; continue")
    assert _manifest(run)["last"]["step"] == 4
    ok = run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.lr=1e-3", "--set", "train.epochs=2",
                            env=env)
    assert ok.returncode == 0, ok.stderr
    assert _manifest(run)["last"]["step"] == 8
    # diverged at step 0, before any update: the lower rate it advised changed nothing (a helper's hunt, session 71)
    first = tmp_path / "first"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(first), "--set", "train.ssim_loss=1e30", env=env)
    assert error_line(res).endswith(f"{first} holds no checkpoint yet; it diverged before any update, so no lower rate "
                                    f"changes it: resume it with other settings (hsicam train --out {first} --resume, "
                                    "with --set of the keys named above) or start over with --restart"), error_line(res)
    assert "diverged at step 0" in error_line(res)
