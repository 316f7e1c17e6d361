"""Lines of engine/ and runs/ that the default suite never ran (coverage of ``pytest -m "not slow"``):
the refusals of `pretrained pack` (results of another run found by its folder, references that are no
list, NaN weights, a fine-tuned run, a target that is a file or another command's output, a
``pretrained:`` spec), a run trained on a scene folder (its card, a torn data.json, held-out sources
asked of it), a spectral prior (resumed for more steps, a damaged prior.yaml, weights of other
settings), test DOE height noise on a run with measured PSFs, and the measured-PSF file's own checks."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from cli_helpers import in_process_error_line, tree_snapshot
from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import write_homogeneous_scenes
from hsicam.config import ChoiConfig, load_config
from hsicam.errors import InputError


# ------------------------------------------------------------------------------------------------
# A tiny run on synthetic data and its evaluation
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run(tmp_path_factory, cache_env) -> Path:
    """A finished tiny run (one epoch) with its evaluation beside it (``ev/results.json``)."""
    from hsicam.cli import main
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("gaps_engine")
    train(load_config("tiny", ["train.epochs=1"]), base / "A", progress=False)
    assert main(["evaluate", "--run", str(base / "A"), "--out", str(base / "ev")]) == 0
    return base / "A"


def _copy_run(run: Path, dest: Path) -> Path:
    return shutil.copytree(run, dest, ignore=shutil.ignore_patterns(".lock", ".complete"))


def _nan_weights(folder: Path) -> str:
    """Put a NaN into the first float tensor of ``folder``'s model.safetensors (metadata kept); its key."""
    path = folder / "model.safetensors"
    with safe_open(str(path), "pt") as fh:
        meta = fh.metadata()
    w = load_file(path)
    key = sorted(k for k, v in w.items() if v.is_floating_point())[0]
    w[key] = w[key].clone()
    w[key].view(-1)[0] = float("nan")
    save_file(w, path, metadata=meta)
    return key


def test_pack_refuses_results_whose_references_are_no_list(run, tmp_path, capsys):
    results = json.loads((run.parent / "ev" / "results.json").read_text())
    results["references"] = {"method": "x"}
    (tmp_path / "r.json").write_text(json.dumps(results))
    line = in_process_error_line(capsys, ["pretrained", "pack", run, "--name", "a", "--dest", tmp_path / "root",
                                          "--results", tmp_path / "r.json"])
    assert line == f"hsicam: error: {tmp_path / 'r.json'}: 'references' is not a list"
    assert not (tmp_path / "root").exists()


def test_pack_refuses_results_of_another_run_known_by_its_folder_only(run, tmp_path, capsys):
    """Results that record no weights sha256 but the folder of the run they evaluated: that folder's
    weights decide (missing there: another run), and a config hash of another config names both hashes."""
    from hsicam.engine.pretrained import run_config_hash

    other = _copy_run(run, tmp_path / "other")
    shutil.rmtree(other / "checkpoints")
    (other / "model.safetensors").unlink()
    results = json.loads((run.parent / "ev" / "results.json").read_text())
    results.pop("weights_sha256", None)
    results["run"] = str(other)
    (tmp_path / "r.json").write_text(json.dumps(results))
    argv = ["pretrained", "pack", run, "--name", "a", "--dest", tmp_path / "root", "--results", tmp_path / "r.json"]
    line = in_process_error_line(capsys, argv)
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256

    sha = file_sha256(root_weights_path(run))
    assert line == (f"hsicam: error: {tmp_path / 'r.json'}: results of another run ({other}, weights sha256 missing), "
                    f"not of {run} (weights sha256 {sha[:12]}…); evaluate this run (`hsicam evaluate --run {run} "
                    f"--out DIR`) and pass DIR/results.json as --results")
    results["config_hash"] = "0123456789ab"
    (tmp_path / "r.json").write_text(json.dumps(results))
    line = in_process_error_line(capsys, argv)
    assert line == (f"hsicam: error: {tmp_path / 'r.json'}: results of another run ({other}, config hash 0123456789ab), "
                    f"not of {run} (config hash {run_config_hash(run)}); evaluate this run (`hsicam evaluate --run "
                    f"{run} --out DIR`) and pass DIR/results.json as --results")
    assert not (tmp_path / "root").exists()


def test_pack_cites_results_that_name_this_run_by_its_folder(run, tmp_path):
    """Results recording no weights sha256 but this run's own folder (and its config hash) are of this run; a
    results.json without its held-out block leaves the held-out columns of the card's table empty ("–")."""
    from hsicam.engine.pretrained import pack_pretrained

    results = json.loads((run.parent / "ev" / "results.json").read_text())
    results.pop("weights_sha256", None)
    results.pop("heldout", None)
    results["run"] = str(run)
    (tmp_path / "r.json").write_text(json.dumps(results))
    cam = pack_pretrained(run, "z", tmp_path / "root", tmp_path / "r.json")
    m = results["mean"]
    row = f"| z | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['sam']:.2f} | – | – | – |"
    assert row in (cam / "card.md").read_text().splitlines()


def test_pack_refuses_nan_weights_a_fine_tuned_run_and_a_pretrained_spec(run, tmp_path, capsys):
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE

    root = tmp_path / "root"
    nan = _copy_run(run, tmp_path / "nan")  # no manifest: the root weights are the run's (no checkpoint to fall back on)
    (nan / "checkpoints.json").unlink()
    shutil.rmtree(nan / "checkpoints")
    key = _nan_weights(nan)
    line = in_process_error_line(capsys, ["pretrained", "pack", nan, "--name", "n", "--dest", root])
    # (refused as the run is loaded, before card_fields' own check of the weights, which no file reaches)
    assert line == (f"hsicam: error: {nan / 'model.safetensors'}: 1 NaN/Inf value(s) in {key}: the run's weights are "
                    "not finite (training diverged?); nothing was done with them")
    tuned = _copy_run(run, tmp_path / "tuned")
    (tuned / MEASURED_PSF_FILE).write_bytes(b"")
    line = in_process_error_line(capsys, ["pretrained", "pack", tuned, "--name", "t", "--dest", root])
    assert line == (f"hsicam: error: {tuned}: a fine-tuned run (measured PSFs) cannot be shipped; pack the run trained "
                    "on simulated optics")
    line = in_process_error_line(capsys, ["pretrained", "pack", "pretrained:standard", "--name", "s", "--dest", root])
    assert line == "hsicam: error: pretrained:standard: already a pre-trained camera; pack a run folder"
    assert not root.exists()


def test_pack_never_replaces_a_file_or_another_commands_output(run, tmp_path, capsys):
    (tmp_path / "f").write_text("mine")
    line = in_process_error_line(capsys, ["pretrained", "pack", run, "--name", "f", "--dest", tmp_path, "--force"])
    assert line == (f"hsicam: error: {tmp_path / 'f'}: not a packed camera (a file), and pack never replaces it, even "
                    "with --force; choose another --name or --dest")
    assert (tmp_path / "f").read_text() == "mine"
    ev = shutil.copytree(run.parent / "ev", tmp_path / "ev")
    before = tree_snapshot(ev)
    line = in_process_error_line(capsys, ["pretrained", "pack", run, "--name", "ev", "--dest", tmp_path, "--force"])
    assert line == (f"hsicam: error: {ev}: not a packed camera (the output of hsicam evaluate), and pack never "
                    "replaces it, even with --force; choose another --name or --dest")
    assert tree_snapshot(ev) == before


def test_test_height_noise_on_a_run_imaging_with_measured_psfs_is_refused(run, tmp_path, capsys):
    """A run with measured PSFs (a fine-tuned run) images with fixed PSFs: --sigma-height-nm cannot reach them."""
    from hsicam.runs.folder import load_run
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE, MeasuredPSF, save_measured_psf

    tuned = _copy_run(run, tmp_path / "tuned")
    _, model = load_run(run)
    psf = model.camera.psf().detach()
    psf = psf.reshape(psf.shape[-3:])  # (C, K, K): the camera's own simulated PSFs stand in for measured ones
    save_measured_psf(tuned / MEASURED_PSF_FILE, MeasuredPSF(psf.numpy().astype(np.float32), model.camera.bands, {}))
    assert load_run(tuned)[1].camera.kind == "measured_psf"
    line = in_process_error_line(capsys, ["evaluate", "--run", tuned, "--out", tmp_path / "ev", "--sigma-height-nm", "10"])
    assert line.startswith("hsicam: error: --sigma-height-nm 10: ")
    assert line.endswith(f"(run {tuned}): its camera images with fixed (measured) PSFs, which DOE height noise does not "
                         "change, so no height noise would be applied; drop --sigma-height-nm (it applies only to a "
                         "camera with a DOE)")
    assert not (tmp_path / "ev").exists()


def test_evaluate_of_a_config_without_validation_scenes_is_refused(run, tmp_path, capsys):
    line = in_process_error_line(capsys, ["evaluate", "--run", run, "--out", tmp_path / "ev", "--set",
                                          "data.val_fraction=0"])
    assert line == ("hsicam: error: the config has no validation scenes (data.val_fraction is 0): score a folder of "
                    "scenes instead, --data DIR")
    assert not (tmp_path / "ev").exists()


def test_a_fine_tuning_resume_needs_a_checkpoint(run, tmp_path):
    from hsicam.engine.calibration import check_finetune_resume
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE

    tuned = _copy_run(run, tmp_path / "tuned")
    (tuned / MEASURED_PSF_FILE).write_bytes(b"")
    check_finetune_resume(tuned)  # its checkpoint is there
    (tuned / "checkpoints.json").unlink()
    shutil.rmtree(tuned / "checkpoints")
    with pytest.raises(InputError) as exc:
        check_finetune_resume(tuned)
    assert str(exc.value) == (f"{tuned}: a fine-tuned run without a checkpoint: nothing to resume; fine-tune again "
                              "into a new folder (without --resume)")


def test_a_run_label_naming_no_installed_camera_is_not_this_run(run):
    from hsicam.engine.calibration import _same_run

    assert _same_run(str(run), run) and not _same_run("pretrained:no-such-camera", run)


def test_a_resume_whose_checkpoint_folders_are_gone_names_the_missing_checkpoint(cache_env, tmp_path, capsys):
    from hsicam.engine.train import train

    run = tmp_path / "r"
    assert train(load_config("tiny", ["train.epochs=3"]), run, progress=False, stop_after_steps=6) == {"stopped_at_step": 6}
    kept = json.loads((run / "checkpoints.json").read_text())["weights"]["dir"]
    shutil.rmtree(run / "checkpoints")
    before = tree_snapshot(run)
    line = in_process_error_line(capsys, ["train", "--out", run, "--resume"])
    assert line == (f"hsicam: error: {run / kept / 'model.safetensors'}: the checkpoint named by "
                    f"{run / 'checkpoints.json'} is missing (the run folder is incomplete); copy the run folder again "
                    "from its source, or train it again")
    assert tree_snapshot(run) == before


# ------------------------------------------------------------------------------------------------
# A run trained on a scene folder
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def folder_runs(tmp_path_factory, cache_env) -> dict[str, Path]:
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("gaps_engine_folder")
    data = write_homogeneous_scenes(base / "data", n=4, size=32)
    cfg = lambda epochs: load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}",  # noqa: E731
                                              f"train.epochs={epochs}"])
    assert train(cfg(3), base / "half", progress=False, stop_after_steps=2) == {"stopped_at_step": 2}
    assert train(cfg(1), base / "done", progress=False)["step"] == 4
    return {"data": data, "half": base / "half", "done": base / "done"}


@pytest.mark.parametrize("text, why", [("{not json", "Expecting property name enclosed in double quotes"),
                                       ("[]", "not a data record")])
def test_a_resume_with_an_unreadable_data_record_names_it(folder_runs, tmp_path, capsys, text, why):
    run = _copy_run(folder_runs["half"], tmp_path / "half")
    (run / "data.json").write_text(text)
    before = tree_snapshot(run)
    line = in_process_error_line(capsys, ["train", "--out", run, "--resume"])
    assert line == (f"hsicam: error: {run / 'data.json'}: unreadable ({why}); restore it from a copy of the run, or "
                    "delete it to go on without checking the data")
    assert tree_snapshot(run) == before


def test_held_out_sources_cannot_be_asked_of_a_run_trained_on_a_scene_folder(folder_runs, tmp_path, capsys):
    run = folder_runs["done"]
    line = in_process_error_line(capsys, ["evaluate", "--run", run, "--out", tmp_path / "ev", "--set", "data.root=null",
                                          "--set", "data.holdout_sources=cie-a"])
    assert line == (f"hsicam: error: {run}: data.holdout_sources=cie-a: the run trained on the scenes of "
                    f"{folder_runs['data']}, whose spectra are unknown, so no synthetic set is held out from it; add "
                    "--set data.holdout_sources=none")
    assert not (tmp_path / "ev").exists()


def test_the_card_of_a_run_trained_on_a_scene_folder_says_so(folder_runs, tmp_path):
    from hsicam.engine.pretrained import pack_pretrained

    cam = pack_pretrained(folder_runs["done"], "f", tmp_path)
    card = json.loads((cam / "card.json").read_text())
    assert card["training"]["data"] == {"kind": "folder", "root": str(folder_runs["data"]),
                                        "note": "the maintainer's own scene folder (data.root)"}
    assert "trained on the maintainer's own scene folder, not on real captures of this camera" in card["limits"]
    md = (cam / "card.md").read_text().splitlines()
    assert f"- data: the maintainer's own scene folder (data.root) ({folder_runs['data']})" in md


# ------------------------------------------------------------------------------------------------
# Spectral prior
# ------------------------------------------------------------------------------------------------
PRIOR = ChoiConfig(train_steps=2, features=4, latent=2, batch_size=4)


@pytest.fixture(scope="module")
def prior(tmp_path_factory, cache_env) -> Path:
    from hsicam.engine.prior import train_prior

    p = tmp_path_factory.mktemp("gaps_prior") / "p"
    train_prior(load_config("tiny"), PRIOR, p, progress=False)
    return p


def test_a_finished_prior_resumed_for_more_steps_trains_them_and_is_finished_again(prior, tmp_path):
    from hsicam.cli import main
    from hsicam.runs.checkpoint import CheckpointManager

    p = _copy_run(prior, tmp_path / "p")
    assert json.loads((p / "summary.json").read_text())["step"] == 2
    assert main(["baseline", "train-prior", "--out", str(p), "--resume", "--set", "baselines.choi.train_steps=4"]) == 0
    summary = json.loads((p / "summary.json").read_text())
    assert (summary["step"], summary["final"]) == (4, True)
    assert CheckpointManager(p, "prior.safetensors").state()["global_step"] == 4
    steps = [json.loads(x).get("step") for x in (p / "metrics.jsonl").read_text().splitlines()]
    assert max(s for s in steps if s is not None) == 4


def test_a_prior_with_a_damaged_prior_yaml(prior, tmp_path, capsys):
    """train-prior into it: still known as a trained prior (not "its training did not finish"); loading
    it names the file and the line."""
    from hsicam.engine.prior import load_prior

    p = _copy_run(prior, tmp_path / "p")
    (p / "prior.yaml").write_text("features: [1,\n")
    before = tree_snapshot(p)
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--config", "tiny", "--out", p])
    assert line == (f"hsicam: error: {p}: prior folder exists and is not empty: it holds a trained spectral prior (use "
                    f"it: --run {p}); choose another --out")
    assert tree_snapshot(p) == before
    with pytest.raises(InputError) as exc:
        load_prior(p, load_config("tiny").bands.to_bands())
    assert str(exc.value).startswith(f"{p / 'prior.yaml'}: invalid YAML at line 2")


def test_a_prior_without_summary_whose_settings_cannot_be_read_is_an_unfinished_training(prior, tmp_path, capsys):
    p = _copy_run(prior, tmp_path / "p")
    (p / "summary.json").unlink()
    (p / "prior.yaml").write_text("features: [1,\n")
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--config", "tiny", "--out", p])
    assert line == (f"hsicam: error: {p}: prior folder exists and is not empty: its training did not finish; continue it "
                    f"with `hsicam baseline train-prior --resume --out {p}`, or choose another --out")


def test_a_prior_whose_weights_do_not_fit_its_settings_is_refused_in_one_line(prior, tmp_path):
    import yaml

    from hsicam.engine.prior import load_prior

    p = _copy_run(prior, tmp_path / "p")
    settings = yaml.safe_load((p / "prior.yaml").read_text())
    settings["features"] = 8
    (p / "prior.yaml").write_text(yaml.safe_dump(settings))
    with pytest.raises(InputError) as exc:
        load_prior(p, load_config("tiny").bands.to_bands())
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(p / "prior.safetensors"))
    assert msg.endswith(": its prior.yaml says features: 8, but the weights were trained with features: 4 (prior.yaml "
                        "edited after the training?); put back features: 4 in prior.yaml, or train it again with "
                        "`hsicam baseline train-prior`")


def test_prior_progress_of_a_folder_with_an_unreadable_manifest_is_none(prior, tmp_path):
    from hsicam.engine.prior import prior_progress, unfinished_prior

    p = _copy_run(prior, tmp_path / "p")
    (p / "summary.json").unlink()
    (p / "checkpoints.json").write_text("{torn")
    assert prior_progress(p, PRIOR) is None and unfinished_prior(p, PRIOR) is None


# ------------------------------------------------------------------------------------------------
# Small pure functions
# ------------------------------------------------------------------------------------------------
def test_spectral_angle_loss_of_an_all_dark_truth_is_zero_with_a_zero_gradient():
    from hsicam.engine.tasks import spectral_angle_loss

    recon = torch.rand(2, 5, 4, 4, requires_grad=True)
    loss = spectral_angle_loss(recon, torch.full((2, 5, 4, 4), 0.01), min_brightness=0.05)
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.equal(recon.grad, torch.zeros_like(recon))


def test_measured_psf_file_checks(tmp_path):
    from hsicam.runs.checkpoint import save_safetensors
    from hsicam.runs.measured_psf import MeasuredPSF, load_measured_psf, psf_difference

    bands = load_config("tiny").bands.to_bands()
    n = len(bands)
    save_safetensors(tmp_path / "w.safetensors", {"weight": torch.zeros(3)}, {"format": "x"})
    with pytest.raises(InputError) as exc:
        load_measured_psf(tmp_path / "w.safetensors")
    assert str(exc.value) == f"{tmp_path / 'w.safetensors'}: not a measured-PSF file"
    meta = {"format": "hsicam-measured-psf-1", "bands": json.dumps(bands.to_dict()), "report": "{}"}
    save_safetensors(tmp_path / "i.safetensors", {"psf": torch.ones(n, 3, 3, dtype=torch.int32)}, meta)
    with pytest.raises(InputError) as exc:
        load_measured_psf(tmp_path / "i.safetensors")
    assert str(exc.value) == (f"{tmp_path / 'i.safetensors'}: the PSF stack holds int32 values, not floats: the file is "
                              "damaged; copy the run folder again from its source, or fine-tune it again (hsicam finetune)")
    psf = np.random.default_rng(0).random((n, 3, 3)).astype(np.float32)
    a = MeasuredPSF(psf, bands, {"psf_dir": str(tmp_path), "pixel_pitch_um": 2.0})
    b = MeasuredPSF(psf.copy(), bands, {"psf_dir": str(tmp_path), "pixel_pitch_um": 3.0})  # same PSFs: no difference
    assert psf_difference(a, b, tmp_path) is None


def test_run_label_of_a_pretrained_spec_is_the_spec():
    from hsicam.runs.pretrained import run_label

    assert run_label("pretrained:anything") == "pretrained:anything"


def test_a_disabled_or_already_acquired_run_lock_takes_nothing_more(tmp_path):
    from hsicam.runs.lock import LOCK_FILE, RunLock

    with RunLock(tmp_path, enabled=False) as off:
        off.acquire()
        assert not (tmp_path / LOCK_FILE).exists()
    with RunLock(tmp_path) as lock:
        lock.acquire()
        first = (tmp_path / LOCK_FILE).stat().st_ino
        lock.acquire()  # a second acquire of the same lock: the same file, still held
        assert (tmp_path / LOCK_FILE).stat().st_ino == first
    assert not (tmp_path / LOCK_FILE).exists()


# ------------------------------------------------------------------------------------------------
# train.tensorboard (tensorboard is an optional dependency)
# ------------------------------------------------------------------------------------------------
def test_tensorboard_without_the_package_warns_once_and_trains(cache_env, tmp_path, monkeypatch, caplog):
    import logging
    import sys

    from hsicam.engine.train import train

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # `import` of it raises ImportError
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert train(load_config("tiny", ["train.epochs=1", "train.tensorboard=true"]), tmp_path / "r",
                     progress=False)["step"] == 4
    warned = [r.getMessage() for r in caplog.records if "tensorboard" in r.getMessage()]
    assert warned == ["train.tensorboard=true but tensorboard is not installed (pip install tensorboard); continuing without it"]
    assert not (tmp_path / "r" / "tensorboard").exists()


def test_tensorboard_gets_the_scalars_of_metrics_jsonl_and_is_closed(cache_env, tmp_path, monkeypatch):
    """With the package (a stand-in SummaryWriter here): each train loss and validation metric of
    metrics.jsonl goes to the writer under its step, in the run's tensorboard/ folder; closed at the end."""
    import sys
    import types

    from hsicam.engine.train import train

    writers = []

    class Writer:
        def __init__(self, logdir):
            self.logdir, self.scalars, self.closed = logdir, [], False
            writers.append(self)

        def add_scalar(self, tag, value, step):
            self.scalars.append((tag, float(value), int(step)))

        def close(self):
            self.closed = True

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", types.SimpleNamespace(SummaryWriter=Writer))
    run = tmp_path / "r"
    train(load_config("tiny", ["train.epochs=1", "train.tensorboard=true"]), run, progress=False)
    assert len(writers) == 1 and writers[0].closed and Path(writers[0].logdir) == run / "tensorboard"
    want = []
    for line in (run / "metrics.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if "train_loss" in rec:
            want.append(("train/loss", rec["train_loss"], rec["step"]))
        want += [(f"val/{k[4:]}", v, rec["step"]) for k, v in rec.items() if k.startswith("val_") and "final" not in rec]
    assert any(t.startswith("val/") for t, _, _ in want) and any(t == "train/loss" for t, _, _ in want)
    assert writers[0].scalars == want
