"""A run whose root weights (model.safetensors) are missing and whose kept checkpoint (``train.keep_weights: best``)
is damaged, read by a command (``hsicam evaluate --run``, any reader through :func:`hsicam.runs.folder.load_run`).
It said "the run has no trained weights (model.safetensors is missing)", which hides the damaged checkpoint and the
intact last one; it now names the damaged file and the way out, as ``hsicam train`` does when a training ends so
(:func:`hsicam.engine.train.check_kept_weights`). The reference: the exact line a user sees, written out here."""

from __future__ import annotations

import json

import pytest
import torch

from cli_helpers import error_line, run_cli_in_process
from damage import flip_byte_in_place
from hsicam.config import dump_yaml, load_config
from hsicam.errors import InputError
from hsicam.runs import checkpoint as ck
from hsicam.runs.checkpoint import MANIFEST, RECOPY_HINT, CheckpointManager
from hsicam.runs.folder import load_run


def _run(tmp_path, damage_last: bool = False):
    """A tiny run's config.yaml and a manifest keeping its best (step 1) whose last is step 2 (weights of a small
    stand-in module: the refusal comes before any is loaded); the root weights deleted and the best damaged."""
    run = tmp_path / "run"
    mgr = CheckpointManager(run)
    cfg = load_config("tiny")
    for step, tags in ((1, ("last", "best")), (2, ("last",))):
        net = torch.nn.Linear(2, 3)
        mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": step, "best_psnr": 20.0},
                 cfg.bands.to_bands(), tags)
    (run / "config.yaml").write_text(dump_yaml(cfg))
    man = json.loads((run / MANIFEST).read_text())
    root, best, last = (run / "model.safetensors", run / man["best"]["dir"] / "model.safetensors",
                        run / man["last"]["dir"] / "model.safetensors")
    root.unlink()
    for f in (best, last) if damage_last else (best,):
        flip_byte_in_place(f, f.stat().st_size - 3)
    ck._HASHES.clear()
    return run, (f"{run}: the run has no readable weights: {root} is missing, and {best}, which should hold the "
                 f"weights {run / MANIFEST} records (sha256 {man['best']['weights_sha256'][:12]}…), differs from them: "
                 f"the run's weights are damaged (a copy cut short, a disk error, an edit); ")


def test_load_run_names_the_damaged_checkpoint_and_the_intact_last(tmp_path):
    run, said = _run(tmp_path)
    with pytest.raises(InputError) as err:
        load_run(run)
    assert str(err.value) == said + (f"keep the last checkpoint's weights (step 2, intact) instead: hsicam train --out "
                                     f"{run} --resume --set train.keep_weights=last; or {RECOPY_HINT}")


def test_with_the_last_damaged_too_only_a_new_copy_is_offered(tmp_path):
    run, said = _run(tmp_path, damage_last=True)
    with pytest.raises(InputError) as err:
        load_run(run)
    assert str(err.value) == said + RECOPY_HINT


def test_hsicam_evaluate_says_it_in_one_line(tmp_path):
    run, said = _run(tmp_path)
    res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev"))
    assert error_line(res) == "hsicam: error: " + said + (
        f"keep the last checkpoint's weights (step 2, intact) instead: hsicam train --out {run} --resume --set "
        f"train.keep_weights=last; or {RECOPY_HINT}")
    assert not (tmp_path / "ev").exists()
