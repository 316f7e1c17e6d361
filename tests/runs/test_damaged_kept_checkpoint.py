"""Run folders whose kept checkpoint is damaged (the root weights missing; the end of a training; a change of
``train.keep_weights``) and the bounds of the per-group learning rates."""

from __future__ import annotations

import json

import pytest
import torch

from damage import flip_byte_in_place
from hsicam.errors import InputError
from hsicam.runs import checkpoint as ck
from hsicam.runs.checkpoint import MANIFEST, RECOPY_HINT, CheckpointManager, root_weights_path
from hsicam.spectral import Bands

BANDS = Bands.uniform(500, 600, 50)


def _saved_run(tmp_path, keep: str = "best"):
    """A run folder with one committed checkpoint of a tiny network: (run, manager, network)."""
    run = tmp_path / "run"
    net = torch.nn.Linear(2, 3)
    mgr = CheckpointManager(run, keep=keep)
    mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": 1, "best_psnr": None}, BANDS)
    return run, mgr, net


def test_root_weights_path_says_the_root_is_missing_not_that_it_differs(tmp_path):
    """The root weights deleted and the kept checkpoint damaged: the refusal said the root "differs" from the manifest's
    weights, although there was no root file at all."""
    run, _, _ = _saved_run(tmp_path)
    root, kept = run / "model.safetensors", run / "checkpoints" / "step-00000001" / "model.safetensors"
    sha = json.loads((run / MANIFEST).read_text())["weights"]["sha256"]
    root.unlink()
    flip_byte_in_place(kept, kept.stat().st_size - 3)
    ck._HASHES.clear()
    with pytest.raises(InputError) as err:
        root_weights_path(run)
    assert str(err.value) == (f"{root} is missing, and {kept}, which should hold the weights {run / MANIFEST} records "
                              f"(sha256 {sha[:12]}…), differs from them: the run's weights are damaged (a copy cut "
                              f"short, a disk error, an edit); {RECOPY_HINT}")


def test_fit_does_not_write_its_final_weights_as_the_root_when_the_kept_checkpoint_is_damaged(cache_env, tmp_path,
                                                                                                caplog):
    """Tiny run, 2 epochs, best after epoch 1 (step 4), stopped at step 5; the root weights deleted and the best
    checkpoint given a flipped byte; then resumed to the end. The end of fit wrote the final model's weights (step 8's)
    as the root, which the manifest does not record (readers refused them as "differing"). The root now stays missing,
    the warning naming the damaged checkpoint, and the readers' refusal says the root is missing."""
    import hashlib
    import logging

    from hsicam.config import load_config
    from hsicam.engine.train import train

    torch.set_num_threads(1)
    run = tmp_path / "run"
    cfg = load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3"])
    train(cfg, run, progress=False, stop_after_steps=5)
    man = json.loads((run / MANIFEST).read_text())
    assert man["weights"]["from"] == "best" and man["best"]["step"] < man["last"]["step"], man  # the case
    root, kept, sha = run / "model.safetensors", run / man["best"]["dir"] / "model.safetensors", man["best"]["weights_sha256"]
    root.unlink()
    flip_byte_in_place(kept, kept.stat().st_size - 3)
    ck._HASHES.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.runs.checkpoint"):
        with pytest.raises(InputError, match="^training ended, but the run has no readable weights: "):  # (test_damaged_kept_weights.py)
            train(cfg, run, resume=True, progress=False)
    final = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    man = json.loads((run / MANIFEST).read_text())
    assert final["final"] and final["step"] == man["last"]["step"] > 5 and man["weights"]["dir"] == man["best"]["dir"]  # best unchanged
    assert hashlib.sha256(kept.read_bytes()).hexdigest() != sha
    assert not root.exists()
    said = {r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "hsicam.runs.checkpoint"}
    assert said == {f"{kept} differs from the weights {run / MANIFEST} records (sha256 {sha[:12]}…): the checkpoint is "
                    f"damaged (a copy cut short, a disk error, an edit), so {root} was not rewritten from it; {RECOPY_HINT}"}
    with pytest.raises(InputError, match=r" is missing, and .* differs from them: the run's weights are damaged"):
        root_weights_path(run)


def test_apply_keep_refuses_a_damaged_checkpoint_before_committing_it(tmp_path):
    """A run keeping its best (step 1), its last checkpoint (step 2) given a flipped byte, then asked to keep its last
    (train.keep_weights: last): apply_keep committed the manifest to the damaged checkpoint, sync_root then left the
    root alone, and a run that readers took became one they refused. Now one refusal, the manifest and root unchanged."""
    import hashlib

    run = tmp_path / "run"
    mgr = CheckpointManager(run)
    for step, tags in ((1, ("last", "best")), (2, ("last",))):
        net = torch.nn.Linear(2, 3)
        mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": step, "best_psnr": 20.0}, BANDS, tags)
    root, last = run / "model.safetensors", run / "checkpoints" / "step-00000002" / "model.safetensors"
    sha = json.loads((run / MANIFEST).read_text())["last"]["weights_sha256"]
    flip_byte_in_place(last, last.stat().st_size - 3)
    ck._HASHES.clear()
    assert hashlib.sha256(last.read_bytes()).hexdigest() != sha
    before = {p: p.read_bytes() for p in (run / MANIFEST, root)}
    with pytest.raises(InputError) as err:
        CheckpointManager(run, keep="last").apply_keep()
    assert str(err.value) == (f"{last} differs from the weights {run / MANIFEST} records (sha256 {sha[:12]}…): the "
                              "last checkpoint is damaged (a copy cut short, a disk error, an edit), so the run cannot "
                              f"keep it (train.keep_weights: last); nothing was changed; {RECOPY_HINT}")
    assert {p: p.read_bytes() for p in before} == before
    assert root_weights_path(run) == root  # still the run's recorded (best) weights
