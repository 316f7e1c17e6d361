"""Lines of runs/checkpoint.py, runs/folder.py and some engine modules that the default suite never
executed (coverage audit, second pass): each test asserts what a user meets there (the exact one-line
error, the file read back, the value returned), not only that the line runs."""

from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from cli_helpers import in_process_error_line
from hsicam.config import load_config
from hsicam.errors import InputError
from hsicam.runs import checkpoint
from hsicam.runs.checkpoint import MANIFEST, MANIFEST_FORMAT, CheckpointManager, read_weights, root_weights_path
from hsicam.spectral import Bands

BANDS = Bands.uniform(500, 600, 50)


def _saved(run: Path, steps=(2,), best: int | None = None) -> CheckpointManager:
    """A run folder with checkpoints of a Linear(3, 2) at ``steps`` (the last one's weights differ)."""
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    mgr = CheckpointManager(run)
    for s in steps:
        with torch.no_grad():
            model.weight.fill_(float(s))
        mgr.save(model, opt, {"global_step": s, "best_psnr": float(s)}, BANDS, ("last", "best") if s == best else ("last",))
    return mgr


# ------------------------------------------------------------------------------------------------
# runs/checkpoint.py
# ------------------------------------------------------------------------------------------------
AGAIN = "copy the run folder again from its source, or train it again"


@pytest.mark.parametrize("text, why", [
    (json.dumps({"format": "hsicam-run-manifest-2", "last": {"dir": "checkpoints/step-00000001"}}),
     f"not a checkpoint manifest this hsicam reads (format 'hsicam-run-manifest-2', expected '{MANIFEST_FORMAT}': "
     f"written by another hsicam version, or damaged); use the hsicam that trained the run, or {AGAIN}"),
    (json.dumps({"format": MANIFEST_FORMAT, "last": "checkpoints/step-00000001"}),
     f"corrupt checkpoint manifest ('last' is not an entry {{dir, step, …}}); {AGAIN}"),
    (json.dumps({"format": MANIFEST_FORMAT, "last": {"step": 1}}),
     f"corrupt checkpoint manifest ('last' is not an entry {{dir, step, …}}); {AGAIN}"),
    ('{"format": "hsicam-run-', f"corrupt checkpoint manifest (not readable JSON); {AGAIN}"),
    ("[1]", f"corrupt checkpoint manifest (not a JSON object); {AGAIN}"),
])
def test_a_manifest_of_another_format_or_without_a_last_entry_is_one_line_with_its_reason(tmp_path, text, why):
    """Each of these said only 'corrupt checkpoint manifest': no reason, no remedy (a newer hsicam's manifest read as
    damaged)."""
    (tmp_path / MANIFEST).write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as err:
        CheckpointManager(tmp_path).manifest()
    assert str(err.value) == f"{tmp_path / MANIFEST}: {why}"


def test_a_manifest_whose_best_is_no_entry_names_it(tmp_path):
    man = {"format": MANIFEST_FORMAT, "last": {"dir": "checkpoints/step-00000001", "step": 1}, "best": 5, "state": {}}
    (tmp_path / MANIFEST).write_text(json.dumps(man), encoding="utf-8")
    with pytest.raises(InputError) as err:
        CheckpointManager(tmp_path).manifest()
    assert str(err.value) == (f"{tmp_path / MANIFEST}: corrupt checkpoint manifest ('best' is not an entry "
                              "{dir, step, …}); copy the run folder again from its source, or train it again")


def test_a_save_interrupted_while_writing_leaves_no_temporary_and_commits_nothing(tmp_path, monkeypatch):
    """Ctrl-C (not an OSError) during a checkpoint's optimizer write: raised as it is, its temporary folder
    removed, the manifest and root weights still those of the previous step."""
    mgr = _saved(tmp_path, steps=(2,))
    before = (tmp_path / MANIFEST).read_bytes(), (tmp_path / "model.safetensors").read_bytes()

    def interrupted(path, optimizer):
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save_optimizer", interrupted)
    model = torch.nn.Linear(3, 2)
    with pytest.raises(KeyboardInterrupt):
        mgr.save(model, torch.optim.Adam(model.parameters()), {"global_step": 4}, BANDS)
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step-00000002"]
    assert ((tmp_path / MANIFEST).read_bytes(), (tmp_path / "model.safetensors").read_bytes()) == before


@pytest.mark.parametrize("exc, reason, hint", [
    (OSError(errno.ENOSPC, "No space left on device"), "No space left on device", "free some space, then resume the run"),
    (OSError("quota of the project exceeded"), "quota of the project exceeded",  # no errno: its own words
     "resume the run once it can be written")])
def test_root_weights_that_cannot_be_rewritten_after_the_commit_say_the_step_was_committed(tmp_path, monkeypatch, exc,
                                                                                          reason, hint):
    mgr = _saved(tmp_path, steps=(2,))
    old_root = (tmp_path / "model.safetensors").read_bytes()

    def copyfile(src, dst):
        raise exc

    monkeypatch.setattr(checkpoint.shutil, "copyfile", copyfile)
    model = torch.nn.Linear(3, 2)
    with pytest.raises(InputError) as err:
        mgr.save(model, torch.optim.Adam(model.parameters()), {"global_step": 4}, BANDS)
    assert str(err.value) == (f"{tmp_path / 'model.safetensors'}: {reason}; checkpoint step 4 was committed, but "
                              "model.safetensors still holds earlier weights (readers take the checkpoint's; a resume "
                              f"rewrites it): {hint}")
    man = json.loads((tmp_path / MANIFEST).read_text())
    assert man["last"]["dir"] == "checkpoints/step-00000004" and man["state"]["global_step"] == 4
    assert (tmp_path / "model.safetensors").read_bytes() == old_root
    # what readers take: the committed checkpoint's weights, not the stale root file
    assert root_weights_path(tmp_path) == tmp_path / "checkpoints/step-00000004/model.safetensors"
    assert torch.equal(read_weights(root_weights_path(tmp_path))[0]["weight"], model.weight.detach())


def test_load_of_the_best_checkpoint_returns_its_own_state(tmp_path):
    mgr = _saved(tmp_path, steps=(2, 4), best=2)
    model = torch.nn.Linear(3, 2)
    state = mgr.load("best", model, torch.optim.Adam(model.parameters()), BANDS)
    assert state == json.loads((tmp_path / "checkpoints/step-00000002/state.json").read_text())
    assert state["global_step"] == 2 and torch.equal(model.weight.detach(), torch.full((2, 3), 2.0))
    (tmp_path / "checkpoints/step-00000002/state.json").write_text("{torn")
    with pytest.raises(InputError) as err:
        mgr.load("best", model, None, BANDS)
    assert str(err.value) == f"{tmp_path / 'checkpoints/step-00000002/state.json'}: corrupt checkpoint state"


def test_root_weights_path_keeps_the_root_file_when_the_named_checkpoint_is_gone(tmp_path):
    _saved(tmp_path, steps=(2,))
    shutil.rmtree(tmp_path / "checkpoints")
    assert root_weights_path(tmp_path) == tmp_path / "model.safetensors"


# ------------------------------------------------------------------------------------------------
# runs/folder.py
# ------------------------------------------------------------------------------------------------
def test_refit_command_of_a_fine_tuned_run_with_a_torn_finetune_json_has_placeholders(tmp_path):
    from hsicam.runs.folder import refit_command
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE

    (tmp_path / MEASURED_PSF_FILE).write_bytes(b"")
    (tmp_path / "finetune.json").write_text('{"source_run": "runs/a"')  # cut short
    assert refit_command(tmp_path, ["model.consistency.iterations=2"]) == (
        f"hsicam finetune --run SOURCE_RUN --psf-dir PSF_DIR --out {tmp_path} --resume --set model.consistency.iterations=2")
    (tmp_path / "finetune.json").write_text(json.dumps({"source_run": "runs/a", "psf_dir": "psfs"}))
    assert refit_command(tmp_path) == f"hsicam finetune --run runs/a --psf-dir psfs --out {tmp_path} --resume"


def test_finetune_source_without_finetune_json_or_readable_weights_is_unknown(tmp_path):
    from hsicam.runs.folder import finetune_source

    assert finetune_source(tmp_path) == (None, None)
    (tmp_path / "model.safetensors").write_bytes(b"not safetensors")
    assert finetune_source(tmp_path) == (None, None)


def test_resuming_a_copied_camera_whose_config_does_not_load_offers_a_new_run(tmp_path):
    from hsicam.runs.folder import check_run_dir

    (tmp_path / "config.yaml").write_text("camera: [1, 2\n")  # not YAML
    checkpoint.save_safetensors(tmp_path / "model.safetensors", {"w": torch.zeros(1)}, {"format": checkpoint.FORMAT})
    with pytest.raises(InputError) as err:
        check_run_dir(tmp_path, True)
    assert str(err.value).endswith("training cannot go on from weights alone and nothing was changed: train a new "
                                   "run with another --out"), str(err.value)


def test_restart_names_a_file_it_cannot_remove(tmp_path, monkeypatch):
    """--restart meets a file it may not delete (a folder it may not write): one line naming the file and
    the permission hint, as for an entry inside a subfolder (test_cli_errors, run unprivileged)."""
    from hsicam.runs.folder import restart_run_dir

    (tmp_path / "config.yaml").write_text("x")
    (tmp_path / "metrics.jsonl").write_text("")
    real = Path.unlink

    def unlink(self, missing_ok=False):
        if self.name == "metrics.jsonl":
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real(self, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", unlink)
    with pytest.raises(InputError) as err:
        restart_run_dir(tmp_path)
    assert str(err.value) == (f"{tmp_path / 'metrics.jsonl'}: cannot be removed for --restart (Permission denied; check "
                              "its permissions and its folder's); the rest of the unfinished run may be gone already: "
                              "fix that, then run the same command again")


def test_a_disabled_metrics_log_writes_nothing(tmp_path):
    from hsicam.runs.folder import MetricsLog

    log = MetricsLog(tmp_path / "metrics.jsonl", enabled=False)
    log.write({"step": 1})
    assert not (tmp_path / "metrics.jsonl").exists()
    MetricsLog(tmp_path / "metrics.jsonl").write({"step": 2})
    assert [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()] == [{"step": 2}]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, cache_env) -> Path:
    from hsicam.engine.train import train

    run = tmp_path_factory.mktemp("gaps_runs2") / "A"
    train(load_config("tiny", ["train.epochs=1"]), run, progress=False)
    return run


@pytest.mark.parametrize("other", ["kernel", "bands"])
def test_a_run_with_measured_psfs_of_another_camera_names_the_file(tiny_run, tmp_path, capsys, other):
    """A fine-tuned run's measured_psf.safetensors that is another camera's (a file copied in): the refusal
    names that file and the remedy, not only the two grids."""
    from hsicam.runs.folder import load_run
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE, MeasuredPSF, save_measured_psf

    run = shutil.copytree(tiny_run, tmp_path / "T", ignore=shutil.ignore_patterns(".lock", ".complete"))
    _, model = load_run(run)
    with torch.no_grad():
        psf = model.camera.psf().float().numpy()
    k, bands = psf.shape[-1], model.bands
    if other == "kernel":
        psf, why = psf[:, 1:-1, 1:-1].copy(), (f"measured PSFs are {len(bands)}×{k - 2}×{k - 2} (bands × px × px), "
                                             f"the camera's kernels {len(bands)}×{k}×{k}")
    else:
        shifted = Bands.from_dict({**bands.to_dict(), "centers_nm": [c + 3.0 for c in bands.centers_nm.tolist()]})
        bands, why = shifted, f"measured PSFs are on {shifted!r}, the camera on {model.bands!r}"
    save_measured_psf(run / MEASURED_PSF_FILE, MeasuredPSF(psf, bands, {}))
    line = in_process_error_line(capsys, ["evaluate", "--run", run, "--out", tmp_path / "ev"])
    assert line == (f"hsicam: error: {run / MEASURED_PSF_FILE}: {why}: the file is not this run's; copy the run "
                    "folder again from its source, or fine-tune it again (hsicam finetune)")
    assert not (tmp_path / "ev").exists()


# ------------------------------------------------------------------------------------------------
# engine
# ------------------------------------------------------------------------------------------------
def test_tolerance_of_a_cassi_run_names_the_run_and_its_camera(cache_env, tmp_path, capsys):
    from hsicam.cli import main

    run = tmp_path / "C"
    assert main(["train", "--config", "tiny", "--set", "camera.kind=dd_cassi", "--set", "train.epochs=1",
                 "--out", str(run)]) == 0
    capsys.readouterr()
    line = in_process_error_line(capsys, ["tolerance", "--run", run, "--out", tmp_path / "tol"])
    assert line == (f"hsicam: error: {run}: tolerance analysis needs a DOE camera (camera.kind: doe), got "
                    "camera.kind: dd_cassi")
    assert not (tmp_path / "tol").exists()


def test_cfa_offset_estimation_refuses_a_camera_without_cfa_and_a_capture_of_other_shape():
    from hsicam.engine.cfa_offset import estimate_cfa_offset

    with pytest.raises(InputError) as err:
        estimate_cfa_offset(SimpleNamespace(camera=SimpleNamespace(code_period=1)), torch.zeros(1, 1, 64, 64))
    assert str(err.value) == "the camera has no colour filter array: there is no CFA offset to estimate"
    with pytest.raises(InputError) as err:
        estimate_cfa_offset(SimpleNamespace(camera=SimpleNamespace(code_period=4)), torch.zeros(1, 3, 64, 64))
    assert str(err.value) == "sensor image must be (1, 1, H, W), got (1, 3, 64, 64)"


def test_prior_progress_of_a_folder_without_or_with_a_damaged_checkpoint_is_none(tmp_path):
    from hsicam.config import ChoiConfig
    from hsicam.engine.prior import prior_progress

    assert prior_progress(tmp_path, ChoiConfig()) is None  # no checkpoint: weights from elsewhere record no training
    (tmp_path / MANIFEST).write_text("{torn")
    assert prior_progress(tmp_path, ChoiConfig()) is None
