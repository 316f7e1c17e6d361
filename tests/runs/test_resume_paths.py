"""Resuming and re-running into folders that hold something else: each refusal names the folder,
what it holds and the way out, and changes nothing in it.

- ``train --resume`` on a copied camera (weights, no checkpoint) used to train from random weights
  over the copied ones; on a fine-tuned run it printed a hint whose command then failed with an
  optimizer error.
- an interrupted ``baseline train-prior`` was used without a word and could not be continued.
- ``experiment B --out DIR`` on experiment A's folder replaced A's results (and a refused re-run
  took A's completion marker off); ``experiment cfa-period --scale quick`` could never start.
"""

from __future__ import annotations

import json
import re
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_helpers import in_process_error_line, tree_snapshot
from hsicam.cli import main
from hsicam.config import ChoiConfig, load_config


@pytest.fixture(scope="module")
def run(tmp_path_factory, cache_env):
    """A finished tiny run (1 epoch)."""
    d = tmp_path_factory.mktemp("run") / "run"
    assert main(["train", "--config", "tiny", "--out", str(d), "--set", "train.epochs=1"]) == 0
    return d


# ------------------------------------------------------------------------------------------------
# train --resume on a copied camera (weights, no checkpoint)
# ------------------------------------------------------------------------------------------------
def test_resume_refuses_a_copied_camera_and_changes_nothing(run, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("HSICAM_PRETRAINED_DIR", str(tmp_path / "pre"))
    assert main(["pretrained", "pack", "--name", "tinyA", str(run), "--dest", str(tmp_path / "pre")]) == 0
    copy = tmp_path / "copy"
    assert main(["pretrained", "copy", "tinyA", str(copy)]) == 0
    capsys.readouterr()
    assert (copy / "model.safetensors").is_file() and not (copy / "checkpoints.json").exists()
    before = tree_snapshot(copy)
    for extra in ([], ["--set", "train.epochs=3"]):
        line = in_process_error_line(capsys, ["train", "--out", str(copy), "--resume", *extra])
        assert line == (f"hsicam: error: {copy}: holds trained weights (model.safetensors) but no checkpoint to resume "
                        "(a copied or shipped camera, e.g. from `hsicam pretrained copy`); training cannot go on from "
                        "weights alone and nothing was changed: train a new run with another --out, or adapt this "
                        f"camera to measured PSFs with `hsicam finetune --run {copy} --psf-dir DIR --out NEW`")
        assert tree_snapshot(copy) == before  # config.yaml is not rewritten, the weights are kept
    # the same weights without the card files: --restart does not delete them either
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("config.yaml", "model.safetensors"):
        shutil.copy(copy / name, bare / name)
    before = tree_snapshot(bare)
    line = in_process_error_line(capsys, ["train", "--config", "tiny", "--out", str(bare), "--restart"])
    assert f"{bare}: holds trained weights (model.safetensors) but no checkpoint" in line
    assert "--restart would delete them" in line
    line = in_process_error_line(capsys, ["train", "--out", str(bare), "--resume"])
    assert "no checkpoint to resume" in line and tree_snapshot(bare) == before


def test_resume_of_a_copied_cassi_camera_suggests_what_a_cassi_camera_can_do(tmp_path, cache_env, capsys, monkeypatch):
    """A copied CASSI camera was told to `hsicam finetune` it, which refuses any camera but a DOE camera.
    Its refusal now offers a new run of its own settings, a command that trains."""
    run = tmp_path / "cassi"
    assert main(["train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1",
                 "--set", "camera.kind=dd_cassi"]) == 0
    monkeypatch.setenv("HSICAM_PRETRAINED_DIR", str(tmp_path / "pre"))
    assert main(["pretrained", "pack", "--name", "tinyC", str(run), "--dest", str(tmp_path / "pre")]) == 0
    copy = tmp_path / "copy"
    assert main(["pretrained", "copy", "tinyC", str(copy)]) == 0
    capsys.readouterr()
    before = tree_snapshot(copy)
    line = in_process_error_line(capsys, ["train", "--out", str(copy), "--resume"])
    assert line == (f"hsicam: error: {copy}: holds trained weights (model.safetensors) but no checkpoint to resume "
                    "(a copied or shipped camera, e.g. from `hsicam pretrained copy`); training cannot go on from "
                    "weights alone and nothing was changed: train a new run with another --out (`hsicam train "
                    f"--config {copy / 'config.yaml'} --out NEW`: the same settings from a random start), or use this "
                    f"camera as it is with --run {copy}")
    assert tree_snapshot(copy) == before
    # what the DOE camera is offered is refused for this one ...
    line = in_process_error_line(capsys, ["finetune", "--run", str(copy), "--psf-dir", str(tmp_path / "psfs"),
                                          "--out", str(tmp_path / "ft")])
    assert "measured PSFs need a DOE camera" in line
    # ... and what it is offered trains
    assert main(["train", "--config", str(copy / "config.yaml"), "--out", str(tmp_path / "new")]) == 0
    assert (tmp_path / "new" / "model.safetensors").is_file() and tree_snapshot(copy) == before


def test_resume_of_a_run_killed_before_its_first_checkpoint_still_starts(tmp_path, cache_env, capsys):
    """Only trained weights stop a resume: a folder with a config and nothing else resumes at step 0."""
    from hsicam.config import dump_yaml

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(dump_yaml(load_config("tiny")))
    assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=1"]) == 0
    assert (run / "checkpoints.json").is_file()


# ------------------------------------------------------------------------------------------------
# train --resume on a fine-tuned run
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def finetuned(run, tmp_path_factory):
    """(a run fine-tuned 1 epoch by `hsicam finetune` from ``run``, its measured-PSF folder)."""
    from cli_helpers import write_measured_psfs

    base = tmp_path_factory.mktemp("ft")
    psf_dir = write_measured_psfs(run, base / "measured")
    out = base / "ft"
    assert main(["finetune", "--run", str(run), "--psf-dir", str(psf_dir), "--out", str(out), "--epochs", "1"]) == 0
    return out, psf_dir


def test_train_resume_refuses_a_finetuned_run(finetuned, run, tmp_path, capsys):
    ft, psf_dir = finetuned
    capsys.readouterr()
    before = tree_snapshot(ft)
    for extra in ([], ["--set", "train.epochs=3"]):
        code = main(["train", "--out", str(ft), "--resume", *extra])
        out, err = capsys.readouterr()
        assert code == 2 and "To train on" not in out, (out, err)  # the hint whose command failed
        assert "optimizer" not in err
        assert err.strip() == (f"hsicam: error: {ft}: a fine-tuned run (made by `hsicam finetune` from {run}): `hsicam "
                               "train` cannot continue it (its optics are frozen to the measured PSFs); nothing was "
                               f"changed: continue it with hsicam finetune --resume --run {run} --psf-dir "
                               f"{psf_dir} --out {ft} (--epochs N for more epochs)")
        assert tree_snapshot(ft) == before
    # an interrupted fine-tune (no finetune.json yet): the source run comes from its weights
    killed = tmp_path / "killed"
    shutil.copytree(ft, killed)
    (killed / "finetune.json").unlink()
    line = in_process_error_line(capsys, ["train", "--out", str(killed), "--resume"])
    assert f"made by `hsicam finetune` from {run})" in line
    assert f"hsicam finetune --resume --run {run} --psf-dir {psf_dir} --out {killed}" in line  # from its weights


def test_finetune_resume_finishes_an_interrupted_finetuning_as_if_never_stopped(finetuned, run, tmp_path, capsys):
    """It could not be continued at all; now `finetune --resume` ends with the weights of an
    uninterrupted fine-tuning (same run, same measured PSFs), after a warning-worthy half-run."""
    from safetensors.torch import load_file

    from hsicam.engine.calibration import finetune
    from hsicam.runs.folder import unfinished_training

    ft, psf_dir = finetuned
    half = tmp_path / "half"
    args = dict(overrides=("train.epochs=2", "train.lr=3e-4"), progress=False)  # the source run trained 1 epoch
    assert finetune(run, psf_dir, half, stop_after_steps=1, **args) == {"stopped_at_step": 1}
    note = unfinished_training(half, load_config(half / "config.yaml"))
    assert note is not None and note.endswith(f"continue it with `hsicam finetune --resume --run {run} --psf-dir "
                                              f"{psf_dir} --out {half}`"), note
    # the same, started fresh again, is refused with the way to continue
    line = in_process_error_line(capsys, ["finetune", "--run", str(run), "--psf-dir", str(psf_dir), "--out", str(half)])
    assert line.endswith("fine-tuning writes a new run folder: choose another --out, or continue the fine-tuning "
                         "there with --resume"), line
    # it goes on with the epochs and rate it was started with (probe 23: it took the source run's)
    summary = finetune(run, psf_dir, half, resume=True, progress=False)
    assert load_config(half / "config.yaml").train.epochs == 2 and load_config(half / "config.yaml").train.lr == 3e-4
    whole = tmp_path / "whole"
    finetune(run, psf_dir, whole, **args)
    assert summary["steps"] == json.loads((whole / "finetune.json").read_text())["steps"] > 1
    a, b = load_file(half / "model.safetensors"), load_file(whole / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert unfinished_training(half, load_config(half / "config.yaml")) is None


def test_finetune_resume_refuses_other_psfs_another_run_and_nothing_to_resume(finetuned, run, tmp_path, capsys):
    ft, psf_dir = finetuned
    before = tree_snapshot(ft)
    other = shutil.copytree(psf_dir, tmp_path / "other")
    psf = np.load(other / "psf.npy")
    psf[:, psf.shape[1] // 2, psf.shape[2] // 2] *= 1.5  # another calibration of the same camera
    np.save(other / "psf.npy", psf)
    line = in_process_error_line(capsys, ["finetune", "--resume", "--run", str(run), "--psf-dir", str(other), "--out", str(ft)])
    assert line.startswith(f"hsicam: error: {ft}: was fine-tuned on other measured PSFs (those of {psf_dir}) than "
                           f"{other}"), line
    assert tree_snapshot(ft) == before
    # the same folder at another pitch: named as such (it said "other PSFs (those of DIR) than DIR")
    line = in_process_error_line(capsys, ["finetune", "--resume", "--run", str(run), "--psf-dir", str(psf_dir), "--out", str(ft),
                               "--psf-pitch-um", "5"])
    assert line.startswith(f"hsicam: error: {ft}: the PSFs of {psf_dir} as imported now differ from those it was "
                           "fine-tuned on (the pixel pitch differs: 5 µm now, 6 µm when it was fine-tuned)"), line
    elsewhere = shutil.copytree(run, tmp_path / "elsewhere")
    line = in_process_error_line(capsys, ["finetune", "--resume", "--run", str(elsewhere), "--psf-dir", str(psf_dir),
                               "--out", str(ft)])
    assert line == f"hsicam: error: {ft}: was fine-tuned from {run}, not {elsewhere}; resume it with --run {run}"
    assert tree_snapshot(ft) == before
    for out, why in ((tmp_path / "none", "no such folder"),
                     (run, "not a fine-tuned run (no config.yaml and measured PSFs)")):
        line = in_process_error_line(capsys, ["finetune", "--resume", "--run", str(ft), "--psf-dir", str(psf_dir),
                                   "--out", str(out)])
        assert line == (f"hsicam: error: {out}: nothing to resume ({why}); start the fine-tuning without --resume"), line
    assert not (tmp_path / "none").exists()


def test_finetune_resume_of_a_finished_finetuning_changes_nothing_and_says_so(finetuned, run, tmp_path, capsys):
    """`finetune --resume --epochs 1` (or fewer epochs than it ran) on a finished fine-tuning printed "fine-tuned N
    steps … -> OUT" and rewrote finetune.json with the new --epochs beside the steps of the old ones (a helper's hunt,
    session 71); now the words of `train --resume` on a finished run, exit 0, and the folder byte for byte as it was.
    A --run of another camera (the shipped 31-band one) is named as the wrong run before its bands are read against
    the PSFs (it was "no measured PSF for band(s) 430, 440, …")."""
    ft, psf_dir = shutil.copytree(finetuned[0], tmp_path / "ft"), finetuned[1]
    capsys.readouterr()
    before = tree_snapshot(ft)
    assert main(["finetune", "--resume", "--run", str(run), "--psf-dir", str(psf_dir), "--out", str(ft),
                 "--epochs", "1"]) == 0
    out = capsys.readouterr().out
    how = (f"To fine-tune on, raise --epochs: hsicam finetune --run {run} --psf-dir {psf_dir} --out {ft} --resume "
           "--epochs N (N > 1)")
    assert out.startswith(f"{ft}: fine-tuning already finished at step ") and out.rstrip().endswith(
        f"(1 epochs); nothing changed. {how}"), out
    assert tree_snapshot(ft) == before
    # an inference setting given to the resume is applied and said (it printed "nothing changed": a review)
    iterations = load_config(ft / "config.yaml").model.consistency.iterations
    assert main(["finetune", "--resume", "--run", str(run), "--psf-dir", str(psf_dir), "--out", str(ft),
                 "--set", f"model.consistency.iterations={iterations + 1}"]) == 0
    out = capsys.readouterr().out
    assert (f"model.consistency in config.yaml (iterations {iterations} → {iterations + 1}), nothing else changed. "
            f"{how}") in out, out
    assert load_config(ft / "config.yaml").model.consistency.iterations == iterations + 1
    before = tree_snapshot(ft)
    line = in_process_error_line(capsys, ["finetune", "--resume", "--run", "pretrained:standard", "--psf-dir",
                                          str(psf_dir), "--out", str(ft)])
    assert line == (f"hsicam: error: {ft}: was fine-tuned from {run}, not "
                    f"pretrained:standard; resume it with --run {run}"), line
    assert tree_snapshot(ft) == before


# ------------------------------------------------------------------------------------------------
# the spectral prior: an interrupted training warns when used, and --resume continues it
# ------------------------------------------------------------------------------------------------
def interrupted_prior(out: Path, steps: int, stop: int, settings: ChoiConfig | None = None) -> Path:
    """A prior folder whose training (``steps`` steps) was stopped at step ``stop``, as a kill leaves it."""
    from hsicam.engine.loop import FitOptions, fit
    from hsicam.engine.tasks import PriorTask

    cfg = load_config("tiny")
    settings = settings or ChoiConfig(train_steps=steps, features=4, latent=2, batch_size=4)
    torch.manual_seed(settings.seed)  # as train_prior
    task = PriorTask(cfg, settings)
    res = fit(task, FitOptions(task.loop_config(), 0, max_steps=steps, progress=False, stop_after_steps=stop), out)
    assert res == {"stopped_at_step": stop}
    assert not (out / "summary.json").exists() and (out / "prior.safetensors").is_file()
    return out


def test_an_interrupted_prior_warns_when_used_and_names_its_remedy(tmp_path, cache_env, capsys, caplog):
    from hsicam.engine.methods import build_method
    from hsicam.engine.prior import load_prior

    prior = interrupted_prior(tmp_path / "prior", steps=8, stop=4)
    note = (f"{prior}: its training did not finish: the last checkpoint is at step 4 of 8 and it has no summary.json; "
            "the weights are of a partly trained spectral prior: continue it with "
            f"`hsicam baseline train-prior --resume --out {prior}`")
    cfg = load_config("tiny")
    with caplog.at_level(logging.WARNING):
        load_prior(prior, cfg.bands.to_bands())
        build_method("dd-cassi-choi", cfg, prior)  # what `evaluate --method dd-cassi-choi --run PRIOR` loads
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [note, note]
    before = tree_snapshot(prior)
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--config", "tiny", "--out", str(prior)])
    assert line == (f"hsicam: error: {prior}: prior folder exists and is not empty: its training stopped at step 4 of 8; "
                    f"continue it with `hsicam baseline train-prior --resume --out {prior}`, or choose another --out")
    line = in_process_error_line(capsys, ["train", "--out", str(prior), "--resume"])
    assert line == (f"hsicam: error: {prior}: holds a spectral prior (hsicam baseline train-prior), not a camera run; "
                    f"continue it with `hsicam baseline train-prior --resume --out {prior}`")
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--out", str(prior), "--resume", "--set",
                               "baselines.choi.features=8"])
    assert "baselines.choi.features: 4 → 8 would make another prior" in line
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--out", str(prior), "--resume", "--config", "tiny"])
    assert "drop --config" in line
    assert tree_snapshot(prior) == before


def test_train_prior_resume_finishes_an_interrupted_prior(tmp_path, cache_env, capsys, caplog):
    from hsicam.engine.prior import is_prior_run, load_prior
    from hsicam.runs.checkpoint import read_weights

    steps = 8
    settings = ChoiConfig(train_steps=steps, features=4, latent=2, batch_size=4)
    whole = tmp_path / "whole"
    from hsicam.engine.prior import train_prior

    train_prior(load_config("tiny"), settings, whole, progress=False)
    prior = interrupted_prior(tmp_path / "prior", steps=steps, stop=4, settings=settings)
    assert main(["baseline", "train-prior", "--out", str(prior), "--resume"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"spectral prior trained: {steps} steps") and is_prior_run(prior)
    a, _ = read_weights(prior / "prior.safetensors")  # resumed exactly: the uninterrupted prior's weights
    b, _ = read_weights(whole / "prior.safetensors")
    assert all(torch.equal(a[k], b[k]) for k in b)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        load_prior(prior, load_config("tiny").bands.to_bands())
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]
    before = tree_snapshot(prior)
    assert main(["baseline", "train-prior", "--out", str(prior), "--resume"]) == 0
    assert f"{prior}: spectral prior already finished at step {steps}" in capsys.readouterr().out
    assert tree_snapshot(prior) == before
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--config", "tiny", "--out", str(prior)])
    assert line == (f"hsicam: error: {prior}: prior folder exists and is not empty: it holds a trained spectral prior "
                    f"(use it: --run {prior}); choose another --out")
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--out", str(tmp_path / "none"), "--resume"])
    assert "nothing to resume (no such folder)" in line and "hsicam baseline train-prior --config CONFIG" in line
    assert not (tmp_path / "none").exists()


def test_train_prior_resume_trains_a_default_prior_longer(tmp_path, cache_env, capsys):
    """A prior trained with the defaults (config.yaml: ``choi: null``) takes --set baselines.choi.* on resume."""
    prior = interrupted_prior(tmp_path / "prior", steps=ChoiConfig().train_steps, stop=2,
                              settings=ChoiConfig())
    assert main(["baseline", "train-prior", "--out", str(prior), "--resume", "--set", "baselines.choi.train_steps=4"]) == 0
    assert "spectral prior trained: 4 steps" in capsys.readouterr().out
    summary = json.loads((prior / "summary.json").read_text())
    assert summary["step"] == 4


# ------------------------------------------------------------------------------------------------
# experiments: one folder, one experiment
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ablation(tmp_path_factory, cache_env):
    out = tmp_path_factory.mktemp("exp") / "abl"
    assert main(["experiment", "ablation", "--scale", "tiny", "--out", str(out)]) == 0
    return out


def test_experiment_refuses_another_experiments_folder_and_keeps_its_marker(ablation, tmp_path, capsys):
    out = tmp_path / "abl"
    shutil.copytree(ablation, out)
    before = tree_snapshot(out)
    assert json.loads((out / ".complete").read_text())["experiment"] == "ablation"
    for name, scale in (("cfa-period", "tiny"), ("noise", "tiny"), ("ablation", "quick")):
        line = in_process_error_line(capsys, ["experiment", name, "--scale", scale, "--out", str(out)])
        assert line == (f"hsicam: error: {out}: holds the results of experiment ablation at tiny scale; experiment "
                        f"{name} --scale {scale} would replace them and mix its runs with theirs: choose another --out "
                        f"(e.g. runs/experiments/{name}-{scale})")
        assert tree_snapshot(out) == before  # the marker too: the finished experiment stays finished


def test_experiment_refuses_an_interrupted_folder_of_another_experiment(ablation, tmp_path, capsys):
    out = tmp_path / "abl"
    shutil.copytree(ablation, out)
    for name in (".complete", "experiment.json", "table.md"):  # as an interrupted first run leaves it
        (out / name).unlink()
    before = tree_snapshot(out)
    line = in_process_error_line(capsys, ["experiment", "cfa-period", "--scale", "tiny", "--out", str(out)])
    assert line == (f"hsicam: error: {out / 'runs'}: holds doe+cfa, no-cfa, no-doe, which experiment cfa-period does "
                    "not train (another experiment's runs); choose another --out (e.g. runs/experiments/cfa-period-tiny)")
    line = in_process_error_line(capsys, ["experiment", "ablation", "--scale", "quick", "--out", str(out)])
    assert line == (f"hsicam: error: {out / 'runs' / 'doe+cfa'} was trained at tiny scale: {out} holds experiment "
                    "ablation at tiny scale, not quick; choose another --out (e.g. runs/experiments/ablation-quick)")
    assert tree_snapshot(out) == before


# ------------------------------------------------------------------------------------------------
# experiment cfa-period at every scale
# ------------------------------------------------------------------------------------------------
def test_cfa_period_runs_build_at_quick_scale():
    """The quick preset's dispersed layout needs a power-of-two period, its mosaic network a factor
    that is a multiple of the period and its linear step filters as wide as the period: every run
    of the sweep is built (and images and reconstructs a patch) with the experiment's overrides."""
    from hsicam.engine.experiments import CFA_PERIODS, run_configs, run_specs
    from hsicam.models import CameraSystem

    preset = load_config("quick")
    assert preset.camera.cfa.layout == "dispersed" and preset.model.mosaic.factor == 8
    cfgs = run_configs("cfa-period", "quick")
    specs = run_specs("cfa-period", preset)
    assert [s.name for s in specs] == [f"period-{m}" for m in CFA_PERIODS] == list(cfgs)
    for spec, m in zip(specs, CFA_PERIODS):
        cfg = cfgs[spec.name]
        assert cfg == load_config("quick", list(spec.overrides))
        assert cfg.camera.cfa.period == m and cfg.camera.cfa.layout == "random"  # one layout across the sweep
        assert cfg.camera.cfa.init == preset.camera.cfa.init and cfg.model.kind == preset.model.kind
        assert cfg.model.mosaic.factor % m == 0 and abs(cfg.model.mosaic.factor - 8) <= m / 2 + 1e-9
        assert cfg.model.consistency.window_px == 15  # the same filters for every period
        assert "camera.cfa.layout=random" in spec.note and "model.consistency.window_px=15" in spec.note
        model = CameraSystem.from_config(cfg)
        assert model.camera.code_period == m
        k = model.camera.kernel_px
        with torch.no_grad():
            est, sensor = model(torch.rand(1, len(model.bands), 64 + k - 1, 64 + k - 1))
        assert sensor.shape[-2:] == (64, 64) and est.shape == (1, len(model.bands), 64, 64)
        assert torch.isfinite(est).all()
    # tiny and paper: the period alone, as before
    for scale in ("tiny", "paper"):
        assert [s.overrides for s in run_specs("cfa-period", load_config(scale))] == [
            (f"camera.cfa.period={m}",) for m in CFA_PERIODS]
        run_configs("cfa-period", scale)


def test_experiment_table_states_what_the_experiment_set():
    from hsicam.engine.evaluate import summarize
    from hsicam.engine.experiments import format_experiment_table

    result = {"experiment": "cfa-period", "scale": "quick", "seeds": [0], "scenes": ["a"],
              "conventions": summarize([])["conventions"],
              "rows": [{"method": "period-3", "psnr": 30.0, "ssim": 0.8, "sam": 5.0, "runtime_s": 0.1}],
              "notes": ["period-3: camera.cfa.layout=random (the preset's dispersed layout needs a power-of-two period)"]}
    table = format_experiment_table(result)
    assert table.endswith("Set by the experiment beyond the swept key:\n\n- period-3: camera.cfa.layout=random (the "
                          "preset's dispersed layout needs a power-of-two period)")


# ------------------------------------------------------------------------------------------------
# probe 23: what a resume goes on with
# ------------------------------------------------------------------------------------------------
def test_a_resume_trains_with_the_learning_rate_it_is_given(cache_env, tmp_path):
    """`train --resume --set train.lr=X` wrote X to config.yaml but went on with the checkpoint's
    rate (weights bit-identical to a resume without it)."""
    from safetensors.torch import load_file

    from hsicam.engine.train import train

    cfg = lambda *o: load_config("tiny", ["train.epochs=2", *o])  # noqa: E731
    assert train(cfg(), tmp_path / "a", progress=False, stop_after_steps=2) == {"stopped_at_step": 2}
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    train(cfg(), tmp_path / "a", resume=True, progress=False)
    train(cfg("train.lr=0.01"), tmp_path / "b", resume=True, progress=False)
    lrs = [[r["lr"] for r in map(json.loads, (tmp_path / n / "metrics.jsonl").read_text().splitlines()) if "lr" in r]
           for n in "ab"]
    base = load_config("tiny").train.lr
    assert lrs[1][-1] > 0 and lrs[0][-1] == pytest.approx(lrs[1][-1] * base / 0.01)  # the schedule, from the new rate
    a, b = load_file(tmp_path / "a" / "model.safetensors"), load_file(tmp_path / "b" / "model.safetensors")
    assert any(not torch.equal(a[k], b[k]) for k in a)


def test_a_resume_asking_for_fewer_steps_than_were_trained_is_refused(cache_env, tmp_path):
    """It ended the run where it stood and rewrote config.yaml with the lower length (3 epochs for
    a run that had trained 31); the same for a spectral prior's train_steps (one loop)."""
    from hsicam.engine.train import train
    from hsicam.errors import InputError

    run = tmp_path / "r"
    assert train(load_config("tiny", ["train.epochs=3"]), run, progress=False, stop_after_steps=6) == {"stopped_at_step": 6}
    before = tree_snapshot(run)
    with pytest.raises(InputError, match=r"has trained 6 steps \(1 epochs\), more than the 4 its config now asks for; "
                                         r"a resume cannot take training back"):
        train(load_config("tiny", ["train.epochs=1"]), run, resume=True, progress=False)
    assert tree_snapshot(run) == before
    assert train(load_config("tiny", ["train.epochs=3"]), run, resume=True, progress=False)["step"] == 12


@pytest.mark.parametrize("change", ["train.batch_size=8", "data.patches_per_epoch=128"])
def test_a_resume_with_another_batch_size_or_epoch_length_is_refused(cache_env, tmp_path, change):
    """The checkpoint's position (step in its epoch, steps done) counts batches of the size it trained with:
    read in another size the resume skipped the rest of the epoch and stopped early as finished (or was
    refused as "cannot take training back"). It is refused naming both, and nothing changes."""
    from hsicam.engine.train import train
    from hsicam.errors import InputError

    keys = ["train.epochs=3"]
    run = tmp_path / "r"
    full = train(load_config("tiny", keys), tmp_path / "full", progress=False)
    assert train(load_config("tiny", keys), run, progress=False, stop_after_steps=7) == {"stopped_at_step": 7}
    before = tree_snapshot(run)
    with pytest.raises(InputError, match=r"was trained in epochs of 4 steps of 4 patches, and its config now asks for "
                                         r"\d+ steps of \d+ .*keep the batch size and the patches per epoch"):
        train(load_config("tiny", [*keys, change]), run, resume=True, progress=False)
    assert tree_snapshot(run) == before
    assert train(load_config("tiny", keys), run, resume=True, progress=False)["step"] == full["step"]


def test_a_finished_run_resumed_with_a_larger_batch_and_more_epochs_is_refused(cache_env, tmp_path, capsys):
    """A finished run of 2 epochs of 4 steps, resumed with `--set train.batch_size=8 --set train.epochs=3`
    (3 epochs of 2 steps: 6 steps, fewer than the 8 done), was taken as finished: "already finished at step 8
    (2 epochs); nothing changed. To train on, raise train.epochs: … (N > 2)", which it had just done. It is
    refused naming the batch size, as for an unfinished run, and nothing changes."""
    run = tmp_path / "r"
    assert main(["train", "--config", "tiny", "--out", str(run)]) == 0
    before = tree_snapshot(run)
    capsys.readouterr()
    assert in_process_error_line(capsys, ["train", "--out", run, "--resume", "--set", "train.batch_size=8",
                                          "--set", "train.epochs=3"]) == (
        f"hsicam: error: {run}: was trained in epochs of 4 steps of 4 patches, and its config now asks for 2 steps of 8 "
        "(16 patches per epoch, train.batch_size=8): a resume would misplace where it stopped; keep the batch size "
        "and the patches per epoch as they were; nothing was changed")
    assert tree_snapshot(run) == before


@pytest.mark.parametrize("sets, fragment", [
    (["train.freeze=[net,doe,cfa]"], "train.freeze=[cfa, doe, net] leaves nothing to train"),
    (["train.freeze=[net]", "camera.doe.enabled=false", "camera.cfa.enabled=false"],
     "train.freeze=[net] leaves nothing to train (this doe camera's groups with parameters: net)"),
    (["train.freeze=[net]", "train.optics_steps=4"],
     "train.freeze=[net] with train.optics_steps=4: after step 4 only the network trains, and it is frozen"),
])
def test_a_freeze_that_leaves_nothing_to_train_is_refused_before_any_work(cache_env, tmp_path, sets, fragment):
    """It was a traceback from the optimizer, or (with optics_steps) a RuntimeError mid-training that
    left a run no resume could finish."""
    from hsicam.engine.train import train
    from hsicam.errors import ConfigError

    with pytest.raises(ConfigError, match=re.escape(fragment)):
        train(load_config("tiny", sets), tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()


def test_a_resume_with_other_frozen_groups_names_them(cache_env, tmp_path):
    """It said torch's "loaded state dict has a different number of parameter groups"."""
    from hsicam.engine.train import train
    from hsicam.errors import InputError

    run = tmp_path / "r"
    train(load_config("tiny", ["train.epochs=2"]), run, progress=False, stop_after_steps=2)
    before = tree_snapshot(run)
    with pytest.raises(InputError, match=r"the run trained the parameter groups net, doe, cfa, this config trains "
                                         r"net, cfa \(train.freeze, or a camera part switched on or off"):
        train(load_config("tiny", ["train.epochs=2", "train.freeze=[doe]"]), run, resume=True, progress=False)
    assert tree_snapshot(run) == before


def test_resume_of_a_users_own_folder_says_it_is_not_a_run(tmp_path, capsys):
    """`hsicam train --out MYFOLDER --resume` on a folder of the user's own files said the run "was interrupted
    before it started" and offered `--restart`, which refuses such a folder; it now says it is not a run folder,
    names what it holds, and changes nothing. An empty folder is named as one. The way to resume is --out with
    --resume (it said "give --resume the folder", but --resume takes no folder)."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    line = in_process_error_line(capsys, ["train", "--out", str(mine), "--resume"])
    assert line == (f"hsicam: error: {mine}: nothing to resume: not a run folder (no config.yaml, and it holds notes.txt, "
                    "which no training writes); resume the folder the run was started in (--out RUN --resume), or "
                    "start a new run with another --out"), line
    assert [p.name for p in mine.iterdir()] == ["notes.txt"] and (mine / "notes.txt").read_text() == "mine"
    empty = tmp_path / "empty"
    empty.mkdir()
    line = in_process_error_line(capsys, ["train", "--out", str(empty), "--resume"])
    assert line.startswith(f"hsicam: error: {empty}: nothing to resume (an empty folder: no training was started in "
                           "it); start it again with `hsicam train --restart"), line


def test_optics_steps_on_a_camera_without_trainable_optics_is_said_to_do_nothing(cache_env, tmp_path, caplog):
    """train.optics_steps with a camera without optics parameters (no DOE and no CFA here; a CASSI camera's fixed
    aperture) was accepted without a word though it changes nothing; now a warning says so. With optics, trained or
    frozen (their PSFs are then fixed from step N: faster), nothing is said."""
    import logging

    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    cfg = load_config("tiny", ["train.optics_steps=4", "camera.doe.enabled=false", "camera.cfa.enabled=false"])
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.tasks"):
        SystemTask(cfg, CameraSystem.from_config(cfg))
    said = [r.getMessage() for r in caplog.records if "optics_steps" in r.getMessage()]
    assert said == ["train.optics_steps=4 does nothing: this doe camera has no optics parameters (the network alone "
                    "trains, from the first step as after it)"], said
    caplog.clear()
    for sets in (["train.optics_steps=4"], ["train.optics_steps=4", "train.freeze=[doe,cfa]"]):
        cfg = load_config("tiny", sets)  # frozen optics: their PSFs are fixed from step 4 on (faster), not a no-op
        with caplog.at_level(logging.WARNING, logger="hsicam.engine.tasks"):
            SystemTask(cfg, CameraSystem.from_config(cfg))
        assert "optics_steps" not in caplog.text, sets


def test_spectral_terms_on_a_one_band_camera_are_said_to_do_nothing(cache_env, caplog):
    """A one-band camera trained with the spectral-gradient or spectral-angle loss terms, or relit patches: each is
    a no-op on one band (nothing to difference, an angle always 0, a relighting over one band only scales it,
    and the peak is kept), accepted without a word before."""
    import logging

    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    cfg = load_config("tiny", ["bands.start_nm=550", "bands.stop_nm=550", "train.spectral_grad_loss=0.1",
                               "train.sam_loss=0.05", "data.augment_relight=0.2"])
    assert len(cfg.bands.to_bands()) == 1
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.tasks"):
        SystemTask(cfg, CameraSystem.from_config(cfg))
    said = [r.getMessage() for r in caplog.records if "one band" in r.getMessage()]
    assert said == ["train.spectral_grad_loss=0.1, train.sam_loss=0.05, data.augment_relight=0.2 does nothing with one "
                    "band (a spectrum of one band has no shape: no band-to-band difference, angle or relighting)"], said
