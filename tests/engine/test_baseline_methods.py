"""The baseline methods and the experiments' CASSI rows: every baseline through ``build_method`` on the tiny
dataset (GAP-TV and DeSCI above 25 dB), the method's refusals, the Choi prior's folder (written, reused, refused when
trained with other settings, never relit, ``hsicam baseline train-prior``), the CASSI rows of a DOE config scored on
its camera's sensor area (against the metrics of the cropped cube) and how ``experiment compare`` hands them that
border. Moved from models/test_solvers.py, whose solver tests stay there; the module fixture trains a tiny
learned-CASSI run, a tiny unrolled run and a tiny prior once for the file."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil

import numpy as np
import pytest
import torch
import yaml

from cli_helpers import assert_clean_error, run_cli_in_process
from hsicam.config import ChoiConfig, load_config
from hsicam.engine.methods import baseline_names, build_method
from hsicam.engine.prior import ensure_choi_prior, is_prior_run, load_prior, train_prior
from hsicam.errors import InputError
from hsicam.metrics import psnr_per_band


# --------------------------------------------------------------------------------------------
# Methods on the tiny dataset (tiny preset: 7 bands, 64 px synthetic scenes)
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_env(tmp_path_factory):
    """Private cache with the tiny synthetic dataset, a tiny learned-CASSI run and a tiny prior."""
    from hsicam.engine.train import train

    root = tmp_path_factory.mktemp("baselines")
    old = os.environ.get("HSICAM_CACHE")
    os.environ["HSICAM_CACHE"] = str(root / "cache")
    try:
        cfg = load_config("tiny")
        train(load_config("tiny", ["camera.kind=dd_cassi"]), root / "rdn", progress=False)
        from hsicam.engine.experiments import CASSI_UNROLLED_OVERRIDES

        train(load_config("tiny", [*CASSI_UNROLLED_OVERRIDES, "train.epochs=1"]), root / "unrolled", progress=False)
        prior = ensure_choi_prior(root / "prior", "tiny")
        yield {"cfg": cfg, "rdn": root / "rdn", "unrolled": root / "unrolled", "prior": prior, "root": root}
    finally:
        if old is None:
            os.environ.pop("HSICAM_CACHE", None)
        else:
            os.environ["HSICAM_CACHE"] = old

def _validation_scenes(cfg):
    from hsicam.data.datasets import SceneDataset
    from hsicam.data.pipeline import split_dataset

    bands = cfg.bands.to_bands()
    _, val = split_dataset(cfg.data, bands)
    return SceneDataset(val, bands)

FAST = ("baselines.desci.iterations=[2, 2, 2, 2]", "baselines.desci.init_iterations=10",
        "baselines.gaptv.iterations=20", "baselines.choi.iterations=5", "baselines.choi.init_iterations=5")

@pytest.mark.parametrize("name", baseline_names())
def test_each_baseline_through_build_method(tiny_env, name):
    cfg = load_config("tiny", FAST)
    run = {"dd-cassi-choi": tiny_env["prior"], "dd-cassi-rdn": tiny_env["rdn"],
           "dd-cassi-unrolled": tiny_env["unrolled"]}.get(name)
    method = build_method(name, cfg, run)
    assert method.name == name and method.camera.kind == "dd_cassi"
    scenes = _validation_scenes(cfg)
    scene = scenes[0][None]
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        y = method.camera(scene, g)
        est = method.reconstruct(y)
    truth = method.target(scene)
    assert y.shape == (1, 1, 64, 64)
    assert est.shape == truth.shape == scene.shape
    assert torch.isfinite(est).all()
    if name in ("dd-cassi-gaptv", "dd-cassi-desci"):
        assert float(psnr_per_band(est.clamp(0, 1), truth)) > 25
    evaluate = pytest.importorskip("hsicam.engine.evaluate")
    if hasattr(evaluate, "evaluate_method"):
        res = evaluate.evaluate_method(method, scenes, ["a", "b"], keep_arrays=False)
        assert len(res) == 2 and all(np.isfinite(r.metrics["psnr"]) for r in res)

def test_build_baseline_errors(tiny_env):
    cfg = tiny_env["cfg"]
    with pytest.raises(InputError, match="needs --run"):
        build_method("dd-cassi-choi", cfg)
    with pytest.raises(InputError, match="needs --run"):
        build_method("dd-cassi-rdn", cfg)
    with pytest.raises(InputError, match="camera.kind=dd_cassi"):
        build_method("dd-cassi-rdn", cfg, tiny_env["prior"])  # a prior folder is not a dd_cassi run
    with pytest.raises(InputError, match="not a spectral-prior"):
        build_method("dd-cassi-choi", cfg, tiny_env["rdn"])
    other = load_config("tiny", ["bands.step_nm=100"])
    with pytest.raises(InputError, match="trained on"):
        build_method("dd-cassi-choi", other, tiny_env["prior"])
    # a key of the prior's architecture or training was accepted and ignored (probe 23); ADMM keys apply
    latent = load_prior(tiny_env["prior"], cfg.bands.to_bands())[1].latent
    asked = load_config("tiny", [f"baselines.choi.latent={latent - 1}", "baselines.choi.rho=0.7"])
    with pytest.raises(InputError, match=rf"baselines.choi.latent={latent - 1} \(the prior's: {latent}\): the prior's "
                                         r"architecture and training are fixed"):
        build_method("dd-cassi-choi", asked, tiny_env["prior"])
    assert build_method("dd-cassi-choi", load_config("tiny", ["baselines.choi.rho=0.7"]),
                        tiny_env["prior"]).info["rho"] == 0.7


# --------------------------------------------------------------------------------------------
# The Choi prior's folder
# --------------------------------------------------------------------------------------------
def test_evaluate_refuses_a_prior_key_set_to_its_default(tiny_env, tmp_path):
    """`--set baselines.choi.latent=64` (the default) on a prior trained with latent 16 was taken as
    "not set" and ignored (session 22's rule); given by --set, it is now refused like any other value."""
    from hsicam.engine.methods import check_prior_overrides

    prior, default = tiny_env["prior"], ChoiConfig()
    trained = load_prior(prior, tiny_env["cfg"].bands.to_bands())[1]
    assert trained.latent != default.latent
    out = tmp_path / "ev"
    assert_clean_error(run_cli_in_process("evaluate", "--method", "dd-cassi-choi", "--run", str(prior), "--out", str(out),
                                          "--set", f"baselines.choi.latent={default.latent}"),
                       f"baselines.choi.latent={default.latent} (the prior's: {trained.latent})",
                       "the prior's architecture and training are fixed")
    assert not out.exists()
    own = [f"baselines.choi.latent={trained.latent}", "baselines.choi.rho=0.7"]  # the prior's own value: accepted
    check_prior_overrides(prior, load_config(prior / "config.yaml", own), own)
    # the section given as a mapping names its keys too (probe 25, F1: it got past the check)
    for mapping in (f"baselines.choi={{latent: {default.latent}, rho: 0.7}}",
                    f"baselines={{choi: {{latent: {default.latent}}}}}"):
        with pytest.raises(InputError, match=rf"baselines.choi.latent={default.latent} \(the prior's: {trained.latent}\)"):
            check_prior_overrides(prior, load_config(prior / "config.yaml", [mapping]), [mapping])

def test_prior_folder_and_reuse(tiny_env):
    prior = tiny_env["prior"]
    assert is_prior_run(prior)
    for f in ("config.yaml", "prior.yaml", "prior.safetensors", "metrics.jsonl", "summary.json"):
        assert (prior / f).is_file()
    ae, settings = load_prior(prior, tiny_env["cfg"].bands.to_bands())
    assert settings.features == 16 and settings.latent == 16 and not any(p.requires_grad for p in ae.parameters())
    before = (prior / "prior.safetensors").stat().st_mtime_ns
    assert ensure_choi_prior(prior, "tiny") == prior
    assert (prior / "prior.safetensors").stat().st_mtime_ns == before
    with pytest.raises(InputError, match="not empty"):
        train_prior(tiny_env["cfg"], ChoiConfig(train_steps=1), prior)
    fresh = tiny_env["root"] / "too-big-batch"
    with pytest.raises(InputError, match="batch_size"):
        train_prior(tiny_env["cfg"], ChoiConfig(train_steps=1, batch_size=1000), fresh)
    assert not fresh.exists()  # nothing written: the same --out works after fixing the config

def test_a_prior_trained_with_other_settings_is_not_reused(tiny_env, tmp_path):
    """ensure_choi_prior (the experiments' Choi row) reuses a prior folder only when it was trained
    on the scale's bands and data with its prior settings; otherwise one error, nothing touched."""
    for name, edit, key in (("steps", lambda c, p: p.update(train_steps=p["train_steps"] + 1), "baselines.choi.train_steps"),
                            ("bands", lambda c, p: c["bands"].update(step_nm=100.0), "bands.step_nm")):
        run = tmp_path / name
        shutil.copytree(tiny_env["prior"], run)
        cfg_yaml, prior_yaml = yaml.safe_load((run / "config.yaml").read_text()), yaml.safe_load((run / "prior.yaml").read_text())
        edit(cfg_yaml, prior_yaml)
        (run / "config.yaml").write_text(yaml.safe_dump(cfg_yaml, sort_keys=False))
        (run / "prior.yaml").write_text(yaml.safe_dump(prior_yaml, sort_keys=False))
        before = {f.name: f.stat().st_mtime_ns for f in run.iterdir()}
        with pytest.raises(InputError, match=rf"trained with other settings \({re.escape(key)}: .*delete it"):
            ensure_choi_prior(run, "tiny")
        assert {f.name: f.stat().st_mtime_ns for f in run.iterdir()} == before

def test_the_prior_never_relights_and_a_prior_from_before_relighting_is_reused(tiny_env, tmp_path):
    """Relit training patches (data.augment_relight) are the camera's recipe, not the published
    prior's: PriorTask serves plain patches whatever the config says, and a prior folder whose
    config has other relighting settings is the same prior (reused, not refused)."""
    from hsicam.engine.tasks import PriorTask

    cfg = load_config("tiny", ["data.augment_relight=0.8", "data.augment_relight_prob=1.0"])
    train, _ = PriorTask(cfg, ChoiConfig(train_steps=1, features=4, latent=2)).datasets()
    assert train.relight_sigma == 0.0
    run = tmp_path / "relit"
    shutil.copytree(tiny_env["prior"], run)
    cfg_yaml = yaml.safe_load((run / "config.yaml").read_text())
    cfg_yaml["data"].update(augment_relight=0.8, augment_relight_prob=1.0)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg_yaml, sort_keys=False))
    assert ensure_choi_prior(run, "tiny") == run  # reused as it is
    cfg_yaml["data"].update(augment_flips=False)  # a data setting it does read: refused
    (run / "config.yaml").write_text(yaml.safe_dump(cfg_yaml, sort_keys=False))
    with pytest.raises(InputError, match=r"trained with other settings \(data.augment_flips: False → True"):
        ensure_choi_prior(run, "tiny")

def test_cli_train_prior(tiny_env, capsys):
    from hsicam.cli import main

    out = tiny_env["root"] / "cli-prior"
    assert main(["baseline", "train-prior", "--config", "tiny", "--out", str(out), "--set",
                 "baselines.choi.train_steps=3", "--set", "baselines.choi.features=4"]) == 0
    assert "spectral prior trained" in capsys.readouterr().out and is_prior_run(out)
    assert load_prior(out, tiny_env["cfg"].bands.to_bands())[1].features == 4
    assert main(["baseline", "train-prior", "--config", "tiny", "--out", str(out)]) == 2
    assert "not empty" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# The CASSI rows beside a DOE camera: classical methods on a DOE preset, scored on its sensor area;
# experiment compare refusing a stale prior first, scoring one seed without test noise
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["dd-cassi-gaptv", "dd-cassi-desci"])
def test_classical_cassi_methods_take_a_doe_preset(name):
    """`hsicam evaluate --config quick --method dd-cassi-gaptv` (docs/training_log.md's command) failed:
    the quick preset's linear consistency step is a config error on a DD-CASSI camera, though a
    classical solver has no network to follow it."""
    cfg = load_config("quick")
    assert cfg.model.consistency.kind == "linear" and cfg.model.consistency.iterations > 0
    method = build_method(name, cfg)
    assert method.camera.kind == "dd_cassi" and len(method.camera.bands) == 31
    if name == "dd-cassi-gaptv":
        assert method.info["iterations"] == 400 and method.reconstruct.keywords["iterations"] == 400

def test_cassi_methods_of_a_doe_config_are_scored_on_its_sensor_area(tiny_env):
    """`hsicam evaluate --config quick --method dd-cassi-gaptv` is how the CASSI rows beside the DOE camera are
    measured: the DOE camera scores its sensor area (the scene less its kernel margin, 20 px at the tiny preset),
    so the CASSI method, which reconstructs the whole scene, is scored on the same pixels (it was scored on the
    whole scene, borders the DOE camera's sensor never sees included). A CASSI config or a `same` DOE config:
    the whole scene."""
    from hsicam.cameras import build_camera
    from hsicam.engine.evaluate import evaluate_method, scored_region
    from hsicam.metrics import all_metrics

    cfg = load_config("tiny", FAST)
    assert build_camera(cfg).margin == 20
    method = build_method("dd-cassi-gaptv", cfg)
    assert method.border_px == 10 and method.info["scored_border_px"] == 10
    assert build_method("dd-cassi-gaptv", load_config("tiny", [*FAST, "camera.boundary=same"])).border_px == 0
    assert build_method("dd-cassi-gaptv", load_config("tiny", [*FAST, "camera.kind=dd_cassi"])).border_px == 0
    assert "less 10 px a side" in scored_region(method.camera, method.border_px)
    scenes = _validation_scenes(cfg)
    whole = evaluate_method(dataclasses.replace(method, border_px=0), scenes, ["a", "b"])
    inner = evaluate_method(method, scenes, ["a", "b"])
    for w, i, k in zip(whole, inner, range(2)):
        assert w.truth.shape == scenes[k].shape and i.truth.shape == (scenes[k].shape[0], 44, 44)
        np.testing.assert_array_equal(i.truth, scenes[k].numpy()[:, 10:-10, 10:-10])
        np.testing.assert_array_equal(i.estimate, w.estimate[:, 10:-10, 10:-10])  # the same reconstruction
        want = all_metrics(torch.from_numpy(w.estimate[None, :, 10:-10, 10:-10]),
                           torch.from_numpy(w.truth[None, :, 10:-10, 10:-10]))
        for name in ("psnr", "ssim", "sam"):
            assert i.metrics[name] == pytest.approx(want[name][0], rel=1e-12), name
        assert i.metrics["psnr"] != pytest.approx(w.metrics["psnr"], abs=1e-6)  # the border did count before

def test_compare_refuses_a_stale_choi_prior_before_it_changes_its_folder(tiny_env, tmp_path, monkeypatch):
    """`experiment compare` found a Choi prior trained with other settings only after scoring every other row, having
    already taken its folder's marker and report away; now refused first, the folder as it was."""
    from hsicam.engine import experiments

    out = tmp_path / "compare-tiny"
    run = out / "runs" / "dd-cassi-choi"
    shutil.copytree(tiny_env["prior"], run)
    prior_yaml = yaml.safe_load((run / "prior.yaml").read_text())
    prior_yaml["lr"] = prior_yaml["lr"] * 2
    (run / "prior.yaml").write_text(yaml.safe_dump(prior_yaml, sort_keys=False))
    (out / "experiment.json").write_text("{}")
    (out / "report").mkdir()
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))

    def never(*a, **k):
        raise AssertionError("trained or scored before the prior was checked")

    monkeypatch.setattr(experiments, "ensure_trained", never)
    monkeypatch.setattr(experiments, "evaluate_method", never)
    with pytest.raises(InputError, match=r"dd-cassi-choi was trained with other settings \(baselines.choi.lr: "):
        experiments.run_experiment("compare", "tiny", out)
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before

def test_seeds_without_test_noise_score_one_seed(caplog):
    """`experiment ablation --seeds 3` on a noise-free preset scored the same captures three times (std 0.0), a table
    that read as replication; one seed is scored, with a warning. The noise experiment, or a preset with camera noise,
    keeps its seeds."""
    import logging

    from hsicam.engine.experiments import has_test_noise, scored_seeds

    tiny = load_config("tiny")
    assert not has_test_noise(tiny)
    noisy = [load_config("tiny", [o]) for o in ("camera.sensor.sigma=0.01", "camera.sensor.noise=poisson_gaussian",
                                                "camera.doe.sigma_height_nm=10")]
    assert all(has_test_noise(c) for c in noisy)
    assert not has_test_noise(load_config("tiny", ["camera.sensor.noise=none", "camera.sensor.sigma=0.01"]))  # unapplied
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert scored_seeds("ablation", "tiny", tiny, (0, 1, 2)) == (0,)
    assert "has no test noise" in caplog.text and "scoring seed 0 only" in caplog.text
    assert scored_seeds("noise", "tiny", tiny, (0, 1, 2)) == (0, 1, 2)
    assert all(scored_seeds("compare", "tiny", c, (0, 1)) == (0, 1) for c in noisy)

def test_compare_scores_every_cassi_row_on_the_doe_cameras_area(monkeypatch, tmp_path):
    """`hsicam experiment compare`: the learned CASSI rows (whose own configs are CASSI configs) and the
    iterative ones are all scored without the DOE camera's border."""
    from hsicam.engine import experiments
    from hsicam.engine.experiments import LEARNED_CASSI
    from hsicam.engine.methods import Method

    class Scored(Exception):
        pass

    scored = {}
    monkeypatch.setattr(experiments, "ensure_trained", lambda *a, **k: None)
    monkeypatch.setattr(experiments, "ensure_choi_prior", lambda *a, **k: None)
    monkeypatch.setattr(experiments, "build_method", lambda name, cfg, run=None, device="cpu": Method(
        name, None, None, None))

    def fake_evaluate(method, scenes, names, noise, **kw):
        scored[method.name] = method.border_px
        raise Scored

    monkeypatch.setattr(experiments, "evaluate_method", fake_evaluate)
    for name in (*LEARNED_CASSI, "dd-cassi-gaptv"):
        with pytest.raises(Scored):
            experiments._baseline_rows(load_config("quick"), "quick", tmp_path, [], [], (0,), [name], 70)
    assert scored == {name: 70 for name in (*LEARNED_CASSI, "dd-cassi-gaptv")}

def test_compare_gives_the_cassi_rows_the_border_of_its_own_doe_camera(monkeypatch, tmp_path):
    """run_experiment("compare") hands the CASSI rows the px a side by which its DOE camera's sensor image falls
    short of the scene (measured here by imaging a scene), not 0 (the whole scene)."""
    from hsicam.cameras import DOECamera
    from hsicam.engine import experiments
    from hsicam.engine.methods import Method

    class Handed(Exception):
        pass

    cam = DOECamera.from_config(load_config("tiny"))
    with torch.no_grad():
        sensor = cam.A(torch.rand(1, len(cam.bands), 64, 64))
    expected = (64 - sensor.shape[-1]) // 2
    assert expected > 0 and sensor.shape[-2] == sensor.shape[-1]
    monkeypatch.setattr(experiments, "ensure_trained", lambda *a, **k: None)
    monkeypatch.setattr(experiments, "validation_scenes", lambda cfg: ([], []))
    monkeypatch.setattr(experiments, "build_method", lambda name, cfg, run=None, device="cpu": Method(name, cam, None, None))
    monkeypatch.setattr(experiments, "evaluate_method", lambda *a, **k: [])
    monkeypatch.setattr(experiments, "summarize", lambda res: {"mean": dict.fromkeys(("psnr", "ssim", "sam", "runtime_s"), 0.0),
                                                               "scenes": []})
    handed = []

    def baseline_rows(*args, border_px=0, figures=None):
        handed.append(border_px)
        raise Handed

    monkeypatch.setattr(experiments, "_baseline_rows", baseline_rows)
    with pytest.raises(Handed):
        experiments.run_experiment("compare", "tiny", tmp_path / "out")
    assert handed == [expected]
