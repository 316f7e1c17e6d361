"""``train.keep_weights``: which checkpoint a run's root weights hold (the best validation's, a
selection on the validation scenes, or the last step's), and that readers, results files and the
demo say which one was scored."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from cli_helpers import run_cli_in_process

from hsicam.config import load_config
from hsicam.errors import ConfigError, InputError
from hsicam.runs.checkpoint import (MANIFEST, CheckpointManager, kept_checkpoint, kept_entry, read_weights,
                                    root_weights_path)


def _train(run: Path, *sets: str) -> None:
    from hsicam.engine.train import train

    train(load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3", *sets]), run, progress=False)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return read_weights(path)[0]


def _equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def runs(cache_env, tmp_path_factory):
    """Two tiny runs, identical but for ``train.keep_weights`` (best: the default; last)."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("keep")
    _train(root / "best")
    _train(root / "last", "train.keep_weights=last")
    return root / "best", root / "last"


def test_keep_last_holds_the_last_step_and_trains_the_same(runs):
    best_run, last_run = runs
    man_b = json.loads((best_run / MANIFEST).read_text())
    man_l = json.loads((last_run / MANIFEST).read_text())
    # the choice changes nothing in training: the same checkpoints, the same best
    for tag in ("last", "best"):
        assert man_b[tag]["step"] == man_l[tag]["step"]
        assert _equal(_weights(best_run / man_b[tag]["dir"] / "model.safetensors"),
                      _weights(last_run / man_l[tag]["dir"] / "model.safetensors"))
    assert man_b["best"]["psnr"] == man_l["best"]["psnr"]
    assert man_b["best"]["dir"] != man_b["last"]["dir"], "the tiny run's best must not be its last step"
    # the root weights: the best validation's, or the last step's
    assert man_b["weights"]["from"] == "best" and man_l["weights"]["from"] == "last"
    assert _equal(_weights(best_run / "model.safetensors"), _weights(best_run / man_b["best"]["dir"] / "model.safetensors"))
    assert _equal(_weights(last_run / "model.safetensors"), _weights(last_run / man_l["last"]["dir"] / "model.safetensors"))
    assert not _equal(_weights(last_run / "model.safetensors"), _weights(best_run / "model.safetensors"))
    # the best checkpoint is still kept (and named) in a run that keeps its last
    assert (last_run / man_l["best"]["dir"] / "model.safetensors").is_file()
    assert kept_entry(man_l) == ("last", man_l["last"])
    assert kept_entry(man_b) == ("best", man_b["best"])


def test_readers_follow_the_manifest_not_their_own_default(runs, tmp_path):
    """A kill between the manifest's commit and the root file's rewrite left other weights in the
    root file: readers take the checkpoint the manifest keeps (here the last), and a manager made
    with the default keep ("best") rewrites the root file to that same checkpoint."""
    _, last_run = runs
    run = tmp_path / "run"
    shutil.copytree(last_run, run)
    man = json.loads((run / MANIFEST).read_text())
    shutil.copyfile(run / man["best"]["dir"] / "model.safetensors", run / "model.safetensors")
    assert root_weights_path(run) == run / man["last"]["dir"] / "model.safetensors"
    assert CheckpointManager(run).sync_root() is True
    assert root_weights_path(run) == run / "model.safetensors"
    assert _equal(_weights(run / "model.safetensors"), _weights(run / man["last"]["dir"] / "model.safetensors"))


def _to_legacy(run: Path) -> dict:
    """Turn ``run`` into the layout before the manifest (last.json / best.json pointers); its manifest."""
    man = json.loads((run / MANIFEST).read_text())
    (run / MANIFEST).unlink()
    (run / "last.json").write_text(json.dumps({"dir": man["last"]["dir"], **man["state"]}))
    (run / "best.json").write_text(json.dumps({"dir": man["best"]["dir"], **man["state"]}))
    return man


def test_a_run_of_the_older_layout_keeps_its_best_until_told(runs, tmp_path):
    """Pointer-file runs (no manifest, no ``weights`` entry) keep their best; reused with keep "last"
    they get their manifest, the pointers go, and the root weights are the last step's."""
    from hsicam.engine.experiments import ensure_trained

    best_run, _ = runs
    run = tmp_path / "run"
    shutil.copytree(best_run, run)
    man = _to_legacy(run)
    assert kept_checkpoint(run)["checkpoint"] == "best"
    assert root_weights_path(run) == run / "model.safetensors"  # it holds the best: no manifest to contradict it
    entry = {"dir": "d", "step": 1}
    assert kept_entry({"last": entry, "best": None}) == ("last", entry)  # no validation: the last
    cfg = load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3", "train.keep_weights=last"])
    assert ensure_trained(run, cfg) == "reused"
    assert not (run / "last.json").exists() and not (run / "best.json").exists()
    after = json.loads((run / MANIFEST).read_text())
    assert after["weights"]["from"] == "last" and "legacy" not in after
    assert after["best"]["dir"] == man["best"]["dir"] and after["last"]["dir"] == man["last"]["dir"]
    assert _equal(_weights(run / "model.safetensors"), _weights(run / man["last"]["dir"] / "model.safetensors"))
    assert load_config(run / "config.yaml").train.keep_weights == "last"


def test_apply_keep_refuses_a_missing_checkpoint(runs, tmp_path):
    best_run, _ = runs
    run = tmp_path / "run"
    shutil.copytree(best_run, run)
    man = json.loads((run / MANIFEST).read_text())
    shutil.rmtree(run / man["last"]["dir"])
    before = (run / MANIFEST).read_bytes()
    with pytest.raises(InputError, match="the last checkpoint named by .* is missing"):
        CheckpointManager(run, keep="last").apply_keep()
    assert (run / MANIFEST).read_bytes() == before


def test_kept_checkpoint_says_which_weights(runs, tmp_path):
    best_run, last_run = runs
    man = json.loads((best_run / MANIFEST).read_text())
    b, la = kept_checkpoint(best_run), kept_checkpoint(last_run)
    assert b["checkpoint"] == "best" and b["step"] == man["best"]["step"] and b["last_step"] == man["last"]["step"]
    assert "validation" in b["selected_on"]
    assert la == {"checkpoint": "last", "step": man["last"]["step"], "last_step": man["last"]["step"]}
    assert kept_checkpoint(tmp_path) is None  # no manifest (e.g. a shipped camera's folder)


def test_evaluate_records_the_scored_checkpoint(runs, tmp_path):
    best_run, last_run = runs
    for run, tag in ((best_run, "best"), (last_run, "last")):
        out = tmp_path / tag
        res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(out))
        assert res.returncode == 0, res.stderr
        data = json.loads((out / "results.json").read_text())
        assert data["weights"]["checkpoint"] == tag
        assert data["weights"] == kept_checkpoint(run)
        # and the recorded hash is that checkpoint's weights
        man = json.loads((run / MANIFEST).read_text())
        assert data["weights_sha256"] == man[tag]["weights_sha256"]


def test_demo_sentence_names_the_selection():
    from hsicam.runs.checkpoint import weights_text

    assert weights_text(None) == ""
    last = weights_text({"checkpoint": "last", "step": 640, "last_step": 640})
    assert "last" in last and "640" in last and "no checkpoint selection" in last
    best = weights_text({"checkpoint": "best", "step": 448, "last_step": 640, "selected_on": "…"})
    assert "448 of 640" in best and "optimistic" in best
    at_end = weights_text({"checkpoint": "best", "step": 640, "last_step": 640, "selected_on": "…"})
    assert "changed nothing" in at_end and "optimistic" not in at_end


def test_bad_keep_weights_is_one_clear_error():
    with pytest.raises(ConfigError, match="train.keep_weights.*'best', 'last'"):
        load_config("tiny", ["train.keep_weights=final"])
    with pytest.raises(ValueError, match="keep must be one of"):
        CheckpointManager(".", keep="final")


def test_quick_preset_scores_its_last_step():
    """The demo's preset keeps the last step: its validation figures carry no checkpoint selection."""
    assert load_config("quick").train.keep_weights == "last"
    assert load_config("paper").train.keep_weights == "best"  # the paper's protocol


def test_a_finished_run_reused_with_the_other_choice_switches_its_weights(runs, tmp_path):
    """train.keep_weights is no training difference: a demo or experiment reusing a finished run trained
    with "best" under a config asking for "last" keeps the run and switches its root weights (and
    config.yaml); and back."""
    from hsicam.engine.experiments import ensure_trained

    best_run, _ = runs
    run = tmp_path / "run"
    shutil.copytree(best_run, run)
    man = json.loads((run / MANIFEST).read_text())
    last_w = _weights(run / man["last"]["dir"] / "model.safetensors")
    best_w = _weights(run / man["best"]["dir"] / "model.safetensors")
    cfg = load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3", "train.keep_weights=last"])
    assert ensure_trained(run, cfg) == "reused"
    assert json.loads((run / MANIFEST).read_text())["weights"]["from"] == "last"
    assert _equal(_weights(run / "model.safetensors"), last_w)
    assert load_config(run / "config.yaml").train.keep_weights == "last"
    assert kept_checkpoint(run)["checkpoint"] == "last"
    # the manifest's other entries are untouched: the best is still named and on disk
    after = json.loads((run / MANIFEST).read_text())
    assert after["best"] == man["best"] and after["last"] == man["last"] and after["state"] == man["state"]
    cfg_best = load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3"])
    assert ensure_trained(run, cfg_best) == "reused"
    assert _equal(_weights(run / "model.safetensors"), best_w)
    assert load_config(run / "config.yaml").train.keep_weights == "best"


def test_resume_of_a_finished_run_with_another_keep_says_so(runs, tmp_path):
    _, last_run = runs
    run = tmp_path / "run"
    shutil.copytree(last_run, run)
    res = run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.keep_weights=best")
    assert res.returncode == 0, res.stderr
    man = json.loads((run / MANIFEST).read_text())
    assert man["weights"]["from"] == "best"
    assert _equal(_weights(run / "model.safetensors"), _weights(run / man["best"]["dir"] / "model.safetensors"))
    assert "kept weights: the best checkpoint's" in res.stdout + res.stderr


def test_apply_keep(runs, tmp_path):
    best_run, _ = runs
    run = tmp_path / "run"
    shutil.copytree(best_run, run)
    assert CheckpointManager(run, keep="best").apply_keep() is False  # already so: nothing written
    assert CheckpointManager(run, keep="last").apply_keep() is True
    assert CheckpointManager(run, keep="last").apply_keep() is False
    man = json.loads((run / MANIFEST).read_text())
    man["best"] = None  # a run without validation keeps its last whatever it asks for
    (run / MANIFEST).write_text(json.dumps(man))
    assert CheckpointManager(run, keep="best").apply_keep() is False
    assert kept_checkpoint(run)["checkpoint"] == "last"
    assert CheckpointManager(tmp_path / "nothing", keep="last").apply_keep() is False


@pytest.mark.parametrize("scores, best_at", [((20.0, 25.0, 22.0), 1), ((25.0, 20.0, 22.0), 0), ((20.0, 22.0, 25.0), 2)])
def test_the_best_checkpoint_is_the_validation_with_the_highest_score(cache_env, tmp_path, monkeypatch, scores,
                                                                      best_at):
    """The run keeps the checkpoint of its highest validation score, wherever it falls: a scripted
    validation (the argmax of ``scores`` is the independent reference) over three epochs. (The tiny
    run's real scores peak at its first validation, so a loop that never replaced its first "best"
    passed every other test.)"""
    from hsicam.engine.tasks import SystemTask

    scripted = iter(scores)
    real_validate = SystemTask.validate

    def validate(self, loader, device):
        val = real_validate(self, loader, device)
        return {**val, "psnr": next(scripted)}

    monkeypatch.setattr(SystemTask, "validate", validate)
    run = tmp_path / "run"
    _train(run, "train.epochs=3")
    vals = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    vals = [r for r in vals if "val_psnr" in r and not r.get("final")]
    assert [r["val_psnr"] for r in vals] == list(scores)
    man = json.loads((run / MANIFEST).read_text())
    assert man["best"]["psnr"] == max(scores) and man["best"]["step"] == vals[best_at]["step"]
    assert man["last"]["step"] == vals[-1]["step"]
    assert man["weights"]["from"] == "best"
    best = _weights(run / man["best"]["dir"] / "model.safetensors")
    assert _equal(_weights(run / "model.safetensors"), best)
    if best_at != len(scores) - 1:  # training moved the weights after the best validation
        assert man["best"]["dir"] != man["last"]["dir"]
        assert not _equal(best, _weights(run / man["last"]["dir"] / "model.safetensors"))
    else:
        assert man["best"]["step"] == man["last"]["step"]
