"""An error of rank 0 in the work that ends a training under torchrun (2 CPU processes, gloo): the files written
after the last step (``fit``'s ``then``: the refresh of the linear consistency step) or the check of the run's
kept weights (:func:`hsicam.engine.train.check_kept_weights`). Rank 0 ended its side of the process group with its
error while rank 1 waited in the end-of-training barrier: rank 1 then failed with gloo's traceback ("Connection
closed by peer"; NCCL's barrier waits for its timeout instead), or, for the check run after ``fit`` returned, exited
0. Now every rank ends with one line (exit 2), rank 0's its own error, the others' that rank 0 failed, and neither
keeps the group. The reference: the exact lines a user sees, read per rank; a hang fails on the subprocess's
timeout."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from conftest import KEEP_THE_GROUP, torchrun_tmp

SCRIPT = KEEP_THE_GROUP + """
import io, os, sys, torch
import hsicam.engine.linear_step as linear_step
import hsicam.engine.train as engine_train
from hsicam.cli import main
from hsicam.errors import InputError

def fail(*args, **kwargs):
    raise InputError("the end-of-training work failed")

if sys.argv[2] == "refresh":
    linear_step.refresh_linear_step = fail
else:
    engine_train.check_kept_weights = fail
torch.set_num_threads(1)
err, sys.stderr = sys.stderr, io.StringIO()
try:
    outcome = str(main(["train", "--config", "tiny", "--out", sys.argv[1], "--set", "train.epochs=1",
                        "--set", "data.val_fraction=0.0"]))
except BaseException as exc:
    outcome = "raised " + type(exc).__name__
lines = [x for x in sys.stderr.getvalue().splitlines() if x.startswith("hsicam: ")]
sys.stderr = err
open(sys.argv[1] + ".rank" + os.environ.get("RANK", "0"), "w").write(
    "\\n".join([outcome, f"{torch.distributed.is_initialized()} {group_references()}", *lines]))
release_the_group()
"""


@pytest.mark.slow
@pytest.mark.parametrize("where", ["refresh", "check"])
def test_rank_0_failing_at_the_end_of_training_ends_every_rank_in_one_line(tmp_path, cache_env, where):
    script = tmp_path / "ddp_end.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env),
           "TMPDIR": str(torchrun_tmp(tmp_path))}
    subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                    str(script), str(tmp_path / "run"), where], env=env, capture_output=True, text=True, timeout=300)
    ranks = [(tmp_path / f"run.rank{r}").read_text().splitlines() for r in (0, 1)]
    assert ranks[0] == ["2", "False 0", "hsicam: error: the end-of-training work failed"]
    assert ranks[1] == ["2", "False 0",
                        "hsicam: error: rank 0 failed at the end of the training (its own error says why); rank 1 stops "
                        "with it"]
