"""An error of rank 0 in the work it does alone between two collectives under torchrun (2 CPU processes, gloo):
the run folder's checks and the data before the first barrier, the run's first files, the metrics log and the
checkpoints of a step, the validation at an epoch's end, the files that end the training, the checkpoint of a stop,
and ``fit``'s ``then`` (the refresh of the linear consistency step, the check of the run's kept weights:
:func:`hsicam.engine.train.check_kept_weights`). Rank 0 ended its side of the process group with its error while
the other rank waited in its next collective: that rank then failed with gloo's traceback ("Connection closed by
peer", 26 lines or more; NCCL's collectives wait for their timeout instead), or, for the check run after ``fit``
returned, exited 0. Now every rank ends with one line (exit 2), rank 0's its own error, the others' that rank 0
failed and when (:class:`hsicam.engine.loop.SoloWork`), and neither keeps the group. The reference: the exact lines
a user sees, read per rank; a hang fails on the subprocess's timeout.

Any rank's own work, too: every rank reads its data (``task.datasets``: a file only that rank reads) and, on
``--resume``, the checkpoint; an error of rank 1 there ended rank 1 in one line while rank 0 died in its next
collective with gloo's traceback (exit 1), or, on resume, rank 0 first rewrote the run's config.yaml and metrics
log. And a stop signal that reaches rank 0 alone while the last epoch's validation runs (its loader's workers ended):
rank 0 stopped alone, the other rank waited in its next collective, and both hung."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys

import pytest
import torch

from conftest import KEEP_THE_GROUP, torchrun_tmp

SCRIPT = KEEP_THE_GROUP + """
import io, os, signal, sys, torch
import hsicam.engine.linear_step as linear_step
import hsicam.engine.tasks as tasks
import hsicam.engine.train as engine_train
import hsicam.runs.checkpoint as checkpoint
import hsicam.runs.folder as folder
from hsicam.cli import main
from hsicam.errors import InputError

where, failing_rank = sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "0"

def fail(*args, **kwargs):
    raise InputError(f"rank {failing_rank}'s own work failed ({where})")

def failing(method, when):
    def wrapped(self, *args, **kwargs):
        if when(*args):
            fail()
        return method(self, *args, **kwargs)
    return wrapped

save = checkpoint.CheckpointManager.save
settings = {"datasets": [], "load": ["train.epochs=2"], "validation_cut": [],
            "refresh": ["data.val_fraction=0.0"], "check": ["data.val_fraction=0.0"], "exists": [],
            "session": ["data.val_fraction=0.0"], "step": ["data.val_fraction=0.0", "train.checkpoint_every_steps=1"],
            "last_step": ["train.checkpoint_every_steps=1"], "validate": [], "end": [],
            "stop": ["data.val_fraction=0.0", "train.max_minutes=0.00001"], "step_data": [], "last_step_signal": []}[where]
def cut_validation(self, loader, device):  # a SIGTERM to this rank's process group: its loader's workers end
    os.kill(os.getpid(), signal.SIGTERM)
    raise RuntimeError("DataLoader worker (pid 12345) exited unexpectedly")

if os.environ["RANK"] == failing_rank:  # this rank alone fails
    if where == "datasets":  # e.g. a scene file only this rank reads
        tasks.SystemTask.datasets = fail
    elif where == "load":  # the checkpoint of a resume
        checkpoint.CheckpointManager.load = fail
    elif where == "validation_cut":  # the last epoch's (not cut by a signal itself: only by its workers ending)
        tasks.SystemTask.validate = cut_validation
    elif where == "refresh":
        linear_step.refresh_linear_step = fail
    elif where == "check":
        engine_train.check_kept_weights = fail
    elif where == "session":  # the run's first record, after its folder is in place
        folder.MetricsLog.write = failing(folder.MetricsLog.write, lambda rec: "session" in rec)
    elif where == "step":  # the checkpoint of step 2 of 4 (mid-epoch)
        checkpoint.CheckpointManager.save = failing(save, lambda model, opt, state, *a: state["global_step"] == 2)
    elif where == "last_step":  # the checkpoint of the epoch's last step, before the epoch's validation
        checkpoint.CheckpointManager.save = failing(save, lambda model, opt, state, *a: state["step_in_epoch"] == 4)
    elif where == "validate":
        tasks.SystemTask.validate = fail
    elif where == "end":
        tasks.SystemTask.on_fit_end = fail
    elif where == "stop":  # the checkpoint of the step the budget stops at
        checkpoint.CheckpointManager.save = fail
    elif where == "step_data":  # a scene file only this rank reads, mid-epoch: its first patch of step 2 (of 0..3)
        datasets = tasks.SystemTask.datasets
        def bad_datasets(self):
            train, val = datasets(self)
            kind, first = type(train), 2 * 4 + int(failing_rank) * 2  # global batch 2 of 4 patches, 2 per rank
            class BadScene(kind):
                def __getitem__(self, i):
                    if i == first:
                        fail()
                    return kind.__getitem__(self, i)
            train.__class__ = BadScene
            return train, val
        tasks.SystemTask.datasets = bad_datasets
    elif where == "last_step_signal":  # SIGTERM to this rank alone during the last step (3 of 0..3)
        step_start = tasks.SystemTask.on_step_start
        def signalled(self, step, g):
            if step == 3:
                os.kill(os.getpid(), signal.SIGTERM)
            return step_start(self, step, g)
        tasks.SystemTask.on_step_start = signalled
torch.set_num_threads(1)
err, sys.stderr = sys.stderr, io.StringIO()
try:
    start = ["--resume"] if where == "load" else ["--config", "tiny", "--set", "train.epochs=1"]
    outcome = str(main(["train", "--out", sys.argv[1], *start, *[x for s in settings for x in ("--set", s)]]))
except BaseException as exc:
    outcome = "raised " + type(exc).__name__
lines = [x for x in sys.stderr.getvalue().splitlines() if x.startswith("hsicam: ")]
sys.stderr = err
open(sys.argv[1] + ".rank" + os.environ.get("RANK", "0"), "w").write(
    "\\n".join([outcome, f"{torch.distributed.is_initialized()} {group_references()}", *lines]))
release_the_group()
"""

def run_two_ranks(tmp_path, cache_env, run, where: str, failing_rank: int) -> list[list[str]]:
    """What each of the 2 ranks recorded (its outcome, whether it kept a group, its `hsicam:` lines); a training
    that does not end in 300 s fails the test (its process group killed, so no rank is left behind)."""
    script = tmp_path / "ddp_one_rank.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env),
           "TMPDIR": str(torchrun_tmp(tmp_path))}
    with open(tmp_path / "torchrun.log", "w") as log:  # (not a pipe: a worker left behind would hold it open)
        proc = subprocess.Popen([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                                 str(script), str(run), where, str(failing_rank)], env=env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            proc.wait(timeout=300)
        except subprocess.TimeoutExpired:
            proc.terminate()  # torchrun ends its workers (each in a session of its own): SIGTERM, then SIGKILL
            try:
                proc.wait(timeout=90)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            pytest.fail(f"the 2-process training ({where} failing on rank {failing_rank}) hung")
    return [(tmp_path / f"run.rank{r}").read_text().splitlines() for r in (0, 1)]


WHEN = {"refresh": "at the end of the training", "check": "at the end of the training",
        "exists": "before the training started", "session": "before the training started",
        "step": "at step 2 of the training", "last_step": "at step 4 of the training",
        "validate": "at step 4 of the training", "end": "at the end of the training", "stop": "at step 1 of the training"}


@pytest.mark.slow
@pytest.mark.parametrize("where", list(WHEN))
def test_rank_0_failing_alone_ends_every_rank_in_one_line(tmp_path, cache_env, where):
    run = tmp_path / "run"
    if where == "exists":  # a user's mistake, no failure injected: training into another run's folder
        from hsicam.errors import InputError
        from hsicam.runs.folder import check_run_dir

        run.mkdir()
        (run / "notes.txt").write_text("mine")
        with pytest.raises(InputError) as refused:  # what one process says
            check_run_dir(run, resume=False)
        own = f"hsicam: error: {refused.value}"
    else:
        own = f"hsicam: error: rank 0's own work failed ({where})"
    ranks = run_two_ranks(tmp_path, cache_env, run, where, 0)
    assert ranks[0] == ["2", "False 0", own]
    assert ranks[1] == ["2", "False 0",
                        f"hsicam: error: rank 0 failed {WHEN[where]} (its own error says why); rank 1 stops with it"]
    if where == "last_step":  # rank 0 did nothing more alone after its failure: no validation of the epoch
        records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        assert [r["step"] for r in records if "train_loss" in r] == [1, 2, 3, 4]
        assert not [r for r in records if any(k.startswith("val_") for k in r)]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, cache_env):
    """A finished 1-epoch run of the tiny preset (one process), to resume under torchrun."""
    from hsicam.cli import main

    run = tmp_path_factory.mktemp("finished") / "run"
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1"]) == 0
    finally:
        torch.set_num_threads(n)
    return run


def files_of(run) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


@pytest.mark.slow
@pytest.mark.parametrize("failing_rank", [0, 1])
@pytest.mark.parametrize("where", ["datasets", "load"])
def test_any_rank_failing_alone_in_its_own_reading_ends_every_rank_in_one_line(tmp_path, cache_env, finished_run,
                                                                               where, failing_rank):
    run = tmp_path / "run"
    if where == "load":  # a resume (to 2 epochs): every rank loads the checkpoint
        shutil.copytree(finished_run, run)
    before = files_of(run) if where == "load" else None
    ranks = run_two_ranks(tmp_path, cache_env, run, where, failing_rank)
    other = 1 - failing_rank
    assert ranks[failing_rank] == ["2", "False 0", f"hsicam: error: rank {failing_rank}'s own work failed ({where})"]
    assert ranks[other] == ["2", "False 0", f"hsicam: error: rank {failing_rank} failed before the training started "
                                            f"(its own error says why); rank {other} stops with it"]
    if where == "load":  # nothing of the run changed (config.yaml, the metrics log's final record)
        assert files_of(run) == before
    else:  # nothing was made
        assert not run.exists()


@pytest.mark.slow
def test_a_signal_to_rank_0_alone_cutting_the_last_validation_stops_every_rank(tmp_path, cache_env):
    run = tmp_path / "run"
    ranks = run_two_ranks(tmp_path, cache_env, run, "validation_cut", 0)
    code = str(128 + signal.SIGTERM)
    assert ranks[0] == [code, "False 0", f"hsicam: {run}: training stopped at step 4 of 4 (SIGTERM); the checkpoint of "
                                         f"step 4 is saved; go on with: hsicam train --out {run} --resume"]
    assert ranks[1] == [code, "False 0"]  # (the line once, from rank 0)
    from hsicam.runs.checkpoint import CheckpointManager

    state = CheckpointManager(run).state()  # the epoch uncounted: a resume validates it again
    assert (state["global_step"], state["epoch"]) == (4, 0)


@pytest.mark.slow
@pytest.mark.parametrize("failing_rank", [0, 1])
def test_any_rank_failing_alone_in_a_training_step_ends_every_rank_in_one_line(tmp_path, cache_env, failing_rank):
    """A scene file that one rank alone reads mid-epoch (step 2 of 4): that rank ended with its error, the other died
    in the step's collective (DDP's buffers or gradients) with gloo's traceback ("Connection reset by peer", exit 1).
    Now it says which rank failed, in one line (exit 2), and the run resumes from its last checkpoint."""
    from hsicam.cli import main
    from hsicam.runs.checkpoint import CheckpointManager

    run = tmp_path / "run"
    ranks = run_two_ranks(tmp_path, cache_env, run, "step_data", failing_rank)
    other = 1 - failing_rank
    assert ranks[failing_rank] == ["2", "False 0", f"hsicam: error: rank {failing_rank}'s own work failed (step_data)"]
    assert ranks[other] == ["2", "False 0", f"hsicam: error: rank {failing_rank} failed at step 2 of the training (its "
                                            f"own error says why); rank {other} stops with it"]
    assert CheckpointManager(run).state()["global_step"] == 2  # nothing of step 2 kept: the checkpoint before it
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", "--out", str(run), "--resume"]) == 0
    finally:
        torch.set_num_threads(n)
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "train_loss" in r] == [1, 2, 3, 4]
    assert records[-1]["final"] and records[-1]["step"] == 4


@pytest.mark.slow
@pytest.mark.parametrize("failing_rank", [0, 1])
def test_a_signal_to_one_rank_during_the_last_step_ends_every_rank_alike(tmp_path, cache_env, failing_rank):
    """SIGTERM to one rank alone during the last step: the training finishes (its final files written), then the
    signalled rank exited 143 and the other 0 (rank 1 signalled: no line at all). Now every rank exits 143, as one
    process does, and rank 0 says it once."""
    run = tmp_path / "run"
    ranks = run_two_ranks(tmp_path, cache_env, run, "last_step_signal", failing_rank)
    code = str(128 + signal.SIGTERM)
    assert ranks[0] == [code, "False 0", f"hsicam: {run}: training finished (step 4 of 4) before stopping on SIGTERM"]
    assert ranks[1] == [code, "False 0"]  # (the line once, from rank 0)
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 4  # finished: nothing to resume
