"""Paths of the run folder, checkpoint, loop and progress code that the default suite did not execute
(coverage audit): each asserts the behaviour a user meets there (the exact one-line error, the value
returned, the file read back), not only that the line runs."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch

from hsicam.errors import InputError
from hsicam.runs.checkpoint import MANIFEST, MANIFEST_FORMAT, CheckpointManager, load_optimizer, read_weights, \
    save_safetensors


def _manifest(run: Path, **extra) -> None:
    man = {"format": MANIFEST_FORMAT, "last": {"dir": "checkpoints/step-00000001", "step": 1}, "best": None,
           "state": {}, **extra}
    (run / MANIFEST).write_text(json.dumps(man), encoding="utf-8")


# ------------------------------------------------------------------------------------------------
# runs/checkpoint.py
# ------------------------------------------------------------------------------------------------
def test_read_weights_of_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(InputError) as err:
        read_weights(tmp_path / "none.safetensors")
    assert str(err.value) == f"{tmp_path / 'none.safetensors'}: no such weights file"


def test_load_without_any_checkpoint_names_the_tag(tmp_path):
    with pytest.raises(InputError) as err:
        CheckpointManager(tmp_path).load("best", torch.nn.Linear(1, 1), None, None)
    assert str(err.value) == f"{tmp_path}: no 'best' checkpoint to resume from"


@pytest.mark.parametrize("weights, why", [([1], "'weights' is not an entry {file, from, sha256}: [1]"),
                                          ({"sha256": 3}, "'weights.sha256' is not a hash: 3")])
def test_a_manifest_with_a_malformed_weights_entry_is_refused_with_its_reason(tmp_path, weights, why):
    _manifest(tmp_path, weights=weights)
    with pytest.raises(InputError) as err:
        CheckpointManager(tmp_path).manifest()
    assert str(err.value) == (f"{tmp_path / MANIFEST}: corrupt checkpoint manifest ({why}); copy the run folder "
                              "again from its source, or train it again")


@pytest.mark.parametrize("text", ["[1, 2]", '{"global_step": 3}', "{"])
def test_a_corrupt_legacy_last_pointer_is_one_line(tmp_path, text):
    (tmp_path / "last.json").write_text(text)
    with pytest.raises(InputError) as err:
        CheckpointManager(tmp_path).manifest()
    assert str(err.value) == f"{tmp_path / 'last.json'}: corrupt checkpoint pointer"


def test_a_legacy_run_with_only_a_best_pointer_has_no_checkpoint(tmp_path):
    (tmp_path / "best.json").write_text('{"dir": "checkpoints/a", "global_step": 2}')
    assert CheckpointManager(tmp_path).manifest() is None


def test_an_optimizer_file_without_its_metadata_is_not_an_optimizer_state(tmp_path):
    path = tmp_path / "optimizer.safetensors"
    save_safetensors(path, {"0.exp_avg": torch.zeros(1)}, {"format": "x"})
    opt = torch.optim.Adam(torch.nn.Linear(1, 1).parameters())
    with pytest.raises(InputError) as err:
        load_optimizer(path, opt)
    assert str(err.value) == f"{path}: not an hsicam optimizer state"
    assert not opt.state  # nothing loaded


def test_an_optimizer_file_whose_groups_torch_refuses_is_one_line(tmp_path):
    path = tmp_path / "optimizer.safetensors"
    save_safetensors(path, {}, {"param_groups": json.dumps([{"lr": 1.0}]), "scalars": "{}"})  # no 'params'
    with pytest.raises(InputError) as err:
        load_optimizer(path, torch.optim.Adam(torch.nn.Linear(1, 1).parameters()))
    assert str(err.value) == (f"{path}: not an hsicam optimizer state (a parameter group has no 'params' entry); "
                              "copy the run folder again from its source, or train it again")


# ------------------------------------------------------------------------------------------------
# runs/folder.py
# ------------------------------------------------------------------------------------------------
def test_not_a_run_message_for_an_empty_folder(tmp_path):
    from hsicam.runs.folder import not_a_run_message

    assert not_a_run_message(tmp_path) == f"{tmp_path}: not a run folder (config.yaml is missing)"


def test_a_new_run_over_a_file_is_refused(tmp_path):
    from hsicam.runs.folder import check_run_dir, restart_run_dir

    f = tmp_path / "out"
    f.write_text("mine")
    for call in (lambda: check_run_dir(f, False), lambda: restart_run_dir(f)):
        with pytest.raises(InputError) as err:
            call()
        assert str(err.value) == f"{f}: exists and is not a folder; choose another --out"
    assert f.read_text() == "mine"


def test_restart_of_a_missing_or_empty_folder_removes_nothing(tmp_path):
    from hsicam.runs.folder import restart_run_dir

    assert restart_run_dir(tmp_path / "none") is False and not (tmp_path / "none").exists()
    (tmp_path / "empty").mkdir()
    assert restart_run_dir(tmp_path / "empty") is False and (tmp_path / "empty").is_dir()


def test_resume_of_a_folder_with_prior_weights_but_no_checkpoint_is_refused(tmp_path):
    from hsicam.runs.folder import check_run_dir

    (tmp_path / "config.yaml").write_text("x: 1\n")
    (tmp_path / "prior.safetensors").write_bytes(b"weights")
    with pytest.raises(InputError) as err:
        check_run_dir(tmp_path, True)
    assert str(err.value) == (f"{tmp_path}: holds trained weights (prior.safetensors) but no checkpoint to resume; "
                              "training cannot go on from weights alone and nothing was changed: train a new one "
                              "with another --out")
    assert (tmp_path / "prior.safetensors").read_bytes() == b"weights"


def test_finished_checkpoint_step_of_a_corrupt_manifest_is_none(tmp_path):
    from hsicam.runs.folder import finished_checkpoint_step

    (tmp_path / MANIFEST).write_text("{")
    assert finished_checkpoint_step(tmp_path) is None


# ------------------------------------------------------------------------------------------------
# engine/loop.py
# ------------------------------------------------------------------------------------------------
def test_resolve_device_named_cpu_and_a_device_this_machine_lacks():
    from hsicam.engine.loop import resolve_device

    assert resolve_device("cpu", 0) == torch.device("cpu")
    with pytest.raises(InputError) as err:
        resolve_device("tpu", 0)
    assert str(err.value) == "train.device=tpu: unknown device; use cpu, cuda, cuda:N or mps"
    if not torch.cuda.is_available():
        with pytest.raises(InputError) as err:
            resolve_device("cuda", 0)
        assert str(err.value) == f"train.device=cuda: no CUDA device is available here (torch {torch.__version__}); use cpu"


# ------------------------------------------------------------------------------------------------
# engine/prior.py, engine/pretrained.py, engine/calibration.py
# ------------------------------------------------------------------------------------------------
def test_load_prior_of_a_missing_folder_or_one_without_weights(tmp_path):
    from hsicam.engine.prior import PRIOR_SETTINGS, PRIOR_WEIGHTS, load_prior
    from hsicam.spectral import Bands

    bands = Bands.uniform(450, 650, 50)
    (tmp_path / PRIOR_SETTINGS).write_text("{}\n")  # the defaults
    with pytest.raises(InputError) as err:
        load_prior(tmp_path / "none", bands)
    assert str(err.value) == f"{tmp_path / 'none'}: no such spectral-prior folder"
    with pytest.raises(InputError) as err:
        load_prior(tmp_path, bands)
    assert str(err.value) == f"{tmp_path}: the spectral prior has no trained weights ({PRIOR_WEIGHTS} is missing)"


@pytest.mark.parametrize("text, why", [(None, "no such results file"),
                                       ("{", "unreadable results.json (Expecting property name enclosed in double quotes)"),
                                       ("[1]", "unreadable results.json (not a JSON object)")])
def test_read_results_errors(tmp_path, text, why):
    from hsicam.engine.pretrained import _read_results

    path = tmp_path / "results.json"
    if text is not None:
        path.write_text(text)
    with pytest.raises(InputError) as err:
        _read_results(path)
    assert str(err.value) == f"{path}: {why}"


def test_training_seconds_of_a_folder_without_metrics(tmp_path):
    from hsicam.engine.pretrained import training_seconds

    with pytest.raises(InputError) as err:
        training_seconds(tmp_path)
    assert str(err.value) == f"{tmp_path}: no metrics.jsonl: not a finished run (train it first)"


def test_finetune_into_the_run_itself_is_refused_before_anything_is_read(tmp_path):
    from hsicam.engine.calibration import finetune

    (tmp_path / "run").mkdir()
    with pytest.raises(InputError) as err:
        finetune(tmp_path / "run", tmp_path / "psfs", tmp_path / "run" / "." )
    assert str(err.value) == "--out must be a new run folder, not the run being fine-tuned"
    assert list((tmp_path / "run").iterdir()) == []


# ------------------------------------------------------------------------------------------------
# progress.py
# ------------------------------------------------------------------------------------------------
def test_progress_bar_when_asked_counts_to_the_total(capsys, caplog):
    from hsicam.progress import Progress

    with caplog.at_level(logging.INFO, logger="hsicam.progress"), Progress(3, "tiles", unit="tile", show=True) as p:
        for _ in range(3):
            p.update()
    err = capsys.readouterr().err
    assert "tiles" in err and "3/3" in err  # tqdm's bar on stderr
    assert p._bar is None and p.done == 3
    assert not caplog.records  # the bar, not the log lines


@pytest.mark.parametrize("body, why", [({"dir": "checkpoints/step-00000002", "global_step": "abc"},
                                        "'last.step' is not a step number: 'abc'"),
                                       ({"dir": 5, "global_step": 2}, "'last.dir' is not a checkpoint folder inside the run: 5"),
                                       ({"dir": "/etc", "global_step": 2},
                                        "'last.dir' is not a checkpoint folder inside the run: '/etc'")])
def test_a_damaged_legacy_last_pointer_is_one_line_for_every_reader(tmp_path, body, why):
    """An older run's last.json is checked as a manifest's entries are: a step that is no number was a ValueError
    traceback from `hsicam train --restart` (finished_checkpoint_step's int()), a dir that is no string a TypeError
    from CheckpointManager.path, and an absolute dir was followed outside the run."""
    from hsicam.runs.folder import finished_checkpoint_step, restart_run_dir

    (tmp_path / "last.json").write_text(json.dumps(body))
    expected = (f"{tmp_path / 'last.json'}: corrupt checkpoint pointer ({why}); copy the run folder again from its "
                "source, or train it again")
    for call in (lambda: CheckpointManager(tmp_path).path("last"), CheckpointManager(tmp_path).manifest):
        with pytest.raises(InputError) as err:
            call()
        assert str(err.value) == expected
    # as for a corrupt checkpoints.json: no finished checkpoint, so --restart starts the run again
    assert finished_checkpoint_step(tmp_path) is None
    assert restart_run_dir(tmp_path) is True and not (tmp_path / "last.json").exists()


# --- engine/experiments.py: the refusals and small decisions the default suite never reached (session 57) ----------

def test_an_unknown_experiment_is_refused_naming_every_experiment_the_cli_offers():
    from hsicam.engine.experiments import run_specs

    with pytest.raises(InputError) as exc:
        run_specs("sweep")
    assert str(exc.value) == "unknown experiment 'sweep'; choose one of compare, ablation, noise, cfa-period"


def test_the_cfa_period_sweep_without_a_preset_is_one_run_per_period_setting_only_the_period():
    from hsicam.engine.experiments import cfa_period_specs

    specs = cfa_period_specs(None, (2, 3, 5))
    assert [(s.name, tuple(s.overrides)) for s in specs] == [
        ("period-2", ("camera.cfa.period=2",)), ("period-3", ("camera.cfa.period=3",)),
        ("period-5", ("camera.cfa.period=5",))]


def test_a_run_whose_metrics_log_ends_in_a_torn_line_is_not_finished(tmp_path):
    """A kill mid-write leaves half a JSON line at the end of metrics.jsonl: the run is unfinished (resumed), not an
    error, and the same run with its final record whole is finished."""
    from hsicam.engine.experiments import is_finished

    (tmp_path / "model.safetensors").write_bytes(b"w")
    (tmp_path / "config.yaml").write_text("train: {}\n")
    (tmp_path / "metrics.jsonl").write_text('{"step": 1}\n{"step": 2, "final": tr')
    assert not is_finished(tmp_path)
    (tmp_path / "metrics.jsonl").write_text('{"step": 1}\n{"step": 2, "final": true}\n')
    assert is_finished(tmp_path)


def test_scoring_the_held_out_sources_of_a_config_that_holds_none_out_is_one_line():
    from hsicam.config import load_config
    from hsicam.engine.experiments import scored_scenes

    cfg = load_config("tiny", ["data.holdout_sources=none"])
    with pytest.raises(InputError) as exc:
        scored_scenes(cfg, heldout=True)
    assert str(exc.value) == "the run holds out no spectral sources (data.holdout_sources)"


@pytest.mark.parametrize("stale", ["file", "folder"])
def test_a_stale_step_entry_no_manifest_names_is_replaced_by_the_checkpoint(tmp_path, stale):
    """A file (or a half-written folder, left by a killed process) in the place of the step folder that no manifest
    names is replaced: the checkpoint is written and committed, its weights read back equal the model's."""
    from hsicam.spectral import Bands

    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    place = tmp_path / "checkpoints" / "step-00000004"
    if stale == "file":
        place.parent.mkdir(parents=True)
        place.write_text("not a checkpoint")
    else:
        place.mkdir(parents=True)
        (place / "model.safetensors").write_bytes(b"torn")
    manager = CheckpointManager(tmp_path)
    manager.save(model, opt, {"global_step": 4}, Bands.uniform(500, 600, 50), ("last",))
    assert manager.manifest()["last"]["dir"] == "checkpoints/step-00000004"
    tensors, _ = read_weights(place / "model.safetensors")
    assert torch.equal(tensors["weight"], model.weight.detach())
