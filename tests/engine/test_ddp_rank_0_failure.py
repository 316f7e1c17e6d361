"""An error of rank 0 in the work it does alone between two collectives under torchrun (2 CPU processes, gloo):
the run folder's checks and the data before the first barrier, the run's first files, the metrics log and the
checkpoints of a step, the validation at an epoch's end, the files that end the training, the checkpoint of a stop,
and ``fit``'s ``then`` (the refresh of the linear consistency step, the check of the run's kept weights:
:func:`hsicam.engine.train.check_kept_weights`). Rank 0 ended its side of the process group with its error while
the other rank waited in its next collective: that rank then failed with gloo's traceback ("Connection closed by
peer", 26 lines or more; NCCL's collectives wait for their timeout instead), or, for the check run after ``fit``
returned, exited 0. Now every rank ends with one line (exit 2), rank 0's its own error, the others' that rank 0
failed and when (:class:`hsicam.engine.loop.SoloWork`), and neither keeps the group. The reference: the exact lines
a user sees, read per rank; a hang fails on the subprocess's timeout."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import KEEP_THE_GROUP, torchrun_tmp

SCRIPT = KEEP_THE_GROUP + """
import io, os, sys, torch
import hsicam.engine.linear_step as linear_step
import hsicam.engine.tasks as tasks
import hsicam.engine.train as engine_train
import hsicam.runs.checkpoint as checkpoint
import hsicam.runs.folder as folder
from hsicam.cli import main
from hsicam.errors import InputError

where = sys.argv[2]

def fail(*args, **kwargs):
    raise InputError(f"rank 0's own work failed ({where})")

def failing(method, when):
    def wrapped(self, *args, **kwargs):
        if when(*args):
            fail()
        return method(self, *args, **kwargs)
    return wrapped

save = checkpoint.CheckpointManager.save
settings = {"refresh": ["data.val_fraction=0.0"], "check": ["data.val_fraction=0.0"], "exists": [],
            "session": ["data.val_fraction=0.0"], "step": ["data.val_fraction=0.0", "train.checkpoint_every_steps=1"],
            "last_step": ["train.checkpoint_every_steps=1"], "validate": [], "end": [],
            "stop": ["data.val_fraction=0.0", "train.max_minutes=0.00001"]}[where]
if os.environ["RANK"] == "0":  # rank 0 alone fails
    if where == "refresh":
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
torch.set_num_threads(1)
err, sys.stderr = sys.stderr, io.StringIO()
try:
    outcome = str(main(["train", "--config", "tiny", "--out", sys.argv[1], "--set", "train.epochs=1",
                        *[x for s in settings for x in ("--set", s)]]))
except BaseException as exc:
    outcome = "raised " + type(exc).__name__
lines = [x for x in sys.stderr.getvalue().splitlines() if x.startswith("hsicam: ")]
sys.stderr = err
open(sys.argv[1] + ".rank" + os.environ.get("RANK", "0"), "w").write(
    "\\n".join([outcome, f"{torch.distributed.is_initialized()} {group_references()}", *lines]))
release_the_group()
"""

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
    script = tmp_path / "ddp_rank_0.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env),
           "TMPDIR": str(torchrun_tmp(tmp_path))}
    subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                    str(script), str(run), where], env=env, capture_output=True, text=True, timeout=300)
    ranks = [(tmp_path / f"run.rank{r}").read_text().splitlines() for r in (0, 1)]
    assert ranks[0] == ["2", "False 0", own]
    assert ranks[1] == ["2", "False 0",
                        f"hsicam: error: rank 0 failed {WHEN[where]} (its own error says why); rank 1 stops with it"]
    if where == "last_step":  # rank 0 did nothing more alone after its failure: no validation of the epoch
        records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        assert [r["step"] for r in records if "train_loss" in r] == [1, 2, 3, 4]
        assert not [r for r in records if any(k.startswith("val_") for k in r)]
