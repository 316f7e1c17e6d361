"""Run folders whose kept checkpoint is damaged (the root weights missing; the end of a training; a change of
``train.keep_weights``) and the bounds of the per-group learning rates."""

from __future__ import annotations

import json

import pytest
import torch

from hsicam.errors import InputError
from hsicam.runs import checkpoint as ck
from hsicam.runs.checkpoint import MANIFEST, RECOPY_HINT, CheckpointManager, root_weights_path
from hsicam.spectral import Bands

BANDS = Bands.uniform(500, 600, 50)


def _flip_byte_in_place(path, offset: int) -> None:
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x01]))


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
    _flip_byte_in_place(kept, kept.stat().st_size - 3)
    ck._HASHES.clear()
    with pytest.raises(InputError) as err:
        root_weights_path(run)
    assert str(err.value) == (f"{root} is missing, and {kept}, which should hold the weights {run / MANIFEST} records "
                              f"(sha256 {sha[:12]}…), differs from them: the run's weights are damaged (a copy cut "
                              f"short, a disk error, an edit); {RECOPY_HINT}")
