"""The one training loop (hsicam.engine.loop.fit) with each of its tasks: running loss across a
mid-epoch resume, the spectral prior resumes exactly, frozen parameter groups stay fixed.
(Resume after SIGKILL and DDP with two processes are in test_train.py: `train` is `fit`.)"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from hsicam.config import ChoiConfig, load_config
from hsicam.engine.loop import FitOptions, LoopState, fit, lr_factor
from hsicam.engine.tasks import PriorTask, SystemTask
from hsicam.engine.train import train
from hsicam.errors import ConfigError, InputError
from hsicam.models import CameraSystem
from hsicam.runs.checkpoint import read_weights


def _records(run: Path, key: str) -> list[tuple[int, float]]:
    recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    return [(r["step"], r[key]) for r in recs if key in r]


def test_running_train_loss_survives_a_mid_epoch_resume(tmp_path, cache_env):
    cfg = load_config("tiny", ["train.epochs=2"])
    train(cfg, tmp_path / "full", progress=False)
    assert train(cfg, tmp_path / "part", progress=False, stop_after_steps=3) == {"stopped_at_step": 3}
    train(cfg, tmp_path / "part", resume=True, progress=False)
    full, part = _records(tmp_path / "full", "train_loss"), _records(tmp_path / "part", "train_loss")
    assert [s for s, _ in part] == list(range(1, 9))
    for (s, a), (_, b) in zip(full, part):
        assert a == pytest.approx(b, rel=1e-6), f"step {s}: running loss {b} after resume, {a} uninterrupted"


def test_prior_task_resumes_to_the_same_weights(tmp_path, cache_env):
    cfg = load_config("tiny")
    settings = ChoiConfig(train_steps=6, batch_size=4, features=8, latent=3, lr=3e-3)

    def run(out, **kw):
        torch.manual_seed(settings.seed)
        task = PriorTask(cfg, settings)
        resume = (out / "config.yaml").is_file()
        return fit(task, FitOptions(task.loop_config(), 0, max_steps=settings.train_steps, progress=False, **kw),
                   out, resume)

    full = run(tmp_path / "full")
    assert run(tmp_path / "part", stop_after_steps=4) == {"stopped_at_step": 4}
    resumed = run(tmp_path / "part")
    assert resumed["step"] == full["step"] == 6
    a, _ = read_weights(tmp_path / "full" / "prior.safetensors")
    b, _ = read_weights(tmp_path / "part" / "prior.safetensors")
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    assert (tmp_path / "part" / "summary.json").is_file() and "val_psnr_autoencoder" in resumed


def test_frozen_groups_stay_fixed_and_unknown_groups_are_errors(tmp_path, cache_env):
    cfg = load_config("tiny", ["train.epochs=1", "train.freeze=[doe]"])
    torch.manual_seed(0)
    start = CameraSystem.from_config(cfg).state_dict()
    train(cfg, tmp_path / "run", progress=False)
    end, _ = read_weights(tmp_path / "run" / "model.safetensors")
    height = "camera.optics.doe.height_m"
    cfa = "camera.cfa.weights"
    torch.testing.assert_close(end[height], start[height], rtol=0, atol=0)
    assert not torch.equal(end[cfa], start[cfa])
    with pytest.raises(ConfigError, match="unknown parameter group.*lens"):
        SystemTask(load_config("tiny", ["train.freeze=[lens]"]), CameraSystem.from_config(load_config("tiny")))
    cassi = load_config("tiny", ["camera.kind=dd_cassi", "train.freeze=[doe]"])
    with pytest.raises(ConfigError, match="unknown parameter group.*doe for the dd_cassi camera"):
        SystemTask(cassi, CameraSystem.from_config(cassi))  # a CASSI camera has no DOE to freeze
    # a DOE camera whose DOE (or CFA) is switched off: the refusal says why there is none (a config hunt, session 72)
    for group in ("doe", "cfa"):
        off = load_config("tiny", [f"camera.{group}.enabled=false", f"train.freeze=[{group}]"])
        with pytest.raises(ConfigError) as exc:
            SystemTask(off, CameraSystem.from_config(off))
        assert str(exc.value).startswith(f"train.freeze: unknown parameter group(s) {group} for the doe camera; it has ")
        assert str(exc.value).endswith(f"; camera.{group}.enabled is false, so there is no {group.upper()} to freeze")


def test_loop_state_round_trip_and_old_checkpoints():
    s = LoopState(epoch=2, step_in_epoch=3, global_step=11, best_psnr=30.5, best_step=8, loss_sum=1.5, loss_n=3)
    assert LoopState.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    old = {"epoch": 1, "step_in_epoch": 0, "global_step": 4, "best_psnr": None, "best_step": None, "dir": "x"}
    assert LoopState.from_dict(old) == LoopState(epoch=1, global_step=4)


def test_lr_schedule():
    t = load_config("tiny", ["train.lr_schedule=cosine", "train.warmup_steps=4"]).train
    assert [lr_factor(t, s, 100, 10) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    # after the warm-up the cosine runs over the remaining T − W = 96 steps: 1 at step W, ½ half-way, 0 at T
    assert lr_factor(t, 4, 100, 10) == pytest.approx(1.0, abs=1e-15)
    assert lr_factor(t, 52, 100, 10) == pytest.approx(0.5)
    assert lr_factor(t, 100, 100, 10) == pytest.approx(0.0, abs=1e-12)
    # the cosine's shape, not only its ends and middle (a linear decay also gives 0.5 there): cos²(π (s − W) / 2(T − W))
    for s in (25, 75, 90):
        assert lr_factor(t, s, 100, 10) == pytest.approx(math.cos(math.pi * (s - 4) / 192) ** 2, abs=1e-12)
    # step decay: γ^(epoch // lr_step_epochs), after the warm-up
    t = load_config("tiny", ["train.lr_schedule=step", "train.warmup_steps=0", "train.lr_gamma=0.5",
                             "train.lr_step_epochs=2"]).train
    assert [lr_factor(t, s, 100, 10) for s in (0, 19, 20, 39, 40, 99)] == [1.0, 1.0, 0.5, 0.5, 0.25, 0.0625]


def test_training_with_poisson_gaussian_sensor_noise(tmp_path, cache_env):
    """The realistic-noise option of every preset: the camera's Poisson-Gaussian noise is applied
    in training and validation (a low photon count costs PSNR against the noise-free run)."""
    clean = train(load_config("tiny", ["train.epochs=1"]), tmp_path / "clean", progress=False)
    noisy_cfg = load_config("tiny", ["train.epochs=1", "camera.sensor.noise=poisson_gaussian",
                                     "camera.sensor.full_well_e=30", "camera.sensor.read_noise_e=2"])
    noisy = train(noisy_cfg, tmp_path / "noisy", progress=False)
    assert noisy["val_psnr"] < clean["val_psnr"] - 1.0
    cam = CameraSystem.from_config(noisy_cfg).camera
    x = torch.rand(1, len(cam.bands), 40, 40)
    with torch.no_grad():
        assert float((cam(x, torch.Generator().manual_seed(0)) - cam.A(x)).abs().mean()) > 0.01


def test_dd_cassi_unrolled_method(tmp_path, cache_env):
    """The learned CASSI control with the unrolled network (GAP steps with the CASSI operator)."""
    from hsicam.engine.experiments import CASSI_UNROLLED_OVERRIDES, ensure_trained
    from hsicam.engine.methods import build_method
    from hsicam.errors import InputError

    run = tmp_path / "dd-unrolled"
    assert ensure_trained(run, "tiny", (*CASSI_UNROLLED_OVERRIDES, "train.epochs=1")) == "trained"
    cfg = load_config("tiny")
    method = build_method("dd-cassi-unrolled", cfg, run)
    assert method.camera.kind == "dd_cassi" and method.model.net.__class__.__name__ == "UnrolledNet"
    scene = torch.rand(1, len(method.camera.bands), 48, 48)
    with torch.no_grad():
        est = method.reconstruct(method.camera(scene, torch.Generator().manual_seed(0)))
    assert est.shape == method.target(scene).shape and torch.isfinite(est).all()
    with pytest.raises(InputError, match="model.kind=rdn"):
        build_method("dd-cassi-rdn", cfg, run)


def test_ensure_trained_reuses_or_resumes_only_a_run_of_the_same_config(tmp_path, cache_env):
    """An experiment's run folder is reused (finished) or resumed (partial) only when it was started
    with the config asked for, up to how it runs; otherwise one clear error, and nothing is touched."""
    from hsicam.engine.experiments import ensure_trained, is_finished
    from hsicam.errors import InputError

    run = tmp_path / "run"
    asked = ("train.epochs=1",)
    assert ensure_trained(run, "tiny", asked) == "trained"
    weights = (run / "model.safetensors").read_bytes()
    # device, logging cadence, evaluation-only settings: the same camera
    assert ensure_trained(run, "tiny", (*asked, "train.device=cpu", "train.log_every_steps=7",
                                        "baselines.desci.preset=full")) == "reused"
    with pytest.raises(InputError, match=r"train\.lr: 0\.001 → 0\.01\): delete it") as err:
        ensure_trained(run, "tiny", (*asked, "train.lr=0.01", "camera.doe.enabled=false"))
    assert "camera.doe.enabled: True → False" in str(err.value)
    assert ensure_trained(run, "tiny", asked) == "reused"
    # a partial run (no final record) is not resumed with another config either
    metrics = run / "metrics.jsonl"
    metrics.write_text("".join(x + "\n" for x in metrics.read_text().splitlines()[:-1]))
    assert not is_finished(run)
    with pytest.raises(InputError, match="train.epochs: 1 → 2"):
        ensure_trained(run, "tiny", ("train.epochs=2",))
    assert (run / "model.safetensors").read_bytes() == weights


def test_optics_steps_train_the_optics_first_then_the_network_alone(tmp_path, cache_env):
    """train.optics_steps=5 of 12: the first 5 steps are plain joint training (same weights as a
    joint run stopped there), then the optics stay fixed while the network keeps learning; a run
    resumed in the fixed phase ends where the uninterrupted one does."""
    ov = ["train.epochs=3", "train.lr_schedule=constant"]
    fixed_cfg = load_config("tiny", [*ov, "train.optics_steps=5"])
    train(load_config("tiny", ov), tmp_path / "joint", progress=False, stop_after_steps=5)
    train(fixed_cfg, tmp_path / "at5", progress=False, stop_after_steps=5)
    train(fixed_cfg, tmp_path / "full", progress=False)
    train(fixed_cfg, tmp_path / "part", progress=False, stop_after_steps=7)
    train(fixed_cfg, tmp_path / "part", resume=True, progress=False)

    def last(run):
        return read_weights(run / json.loads((run / "checkpoints.json").read_text())["last"]["dir"] / "model.safetensors")[0]

    torch.manual_seed(0)
    init = CameraSystem.from_config(fixed_cfg).state_dict()
    joint, at5, full, part = (last(tmp_path / n) for n in ("joint", "at5", "full", "part"))
    optics = ("camera.optics.doe.height_m", "camera.cfa.weights")
    for k in optics:
        assert not torch.equal(at5[k], init[k]), f"{k} did not learn in the optics steps"
        torch.testing.assert_close(at5[k], joint[k], rtol=0, atol=0, msg=k)
        torch.testing.assert_close(full[k], at5[k], rtol=0, atol=0, msg=k)  # fixed after step 5
    net = [k for k in full if k.startswith("net.")]
    assert max(float((full[k] - at5[k]).abs().max()) for k in net) > 1e-4  # the network went on learning
    for k in full:
        torch.testing.assert_close(part[k], full[k], rtol=0, atol=1e-6, msg=k)
    with pytest.raises(ConfigError, match="optics_steps"):
        load_config("tiny", ["train.optics_steps=-1"])


def test_a_warm_up_longer_than_the_run_is_said(tmp_path, cache_env, caplog):
    """``train.warmup_steps`` beyond the run's steps kept the learning rate below train.lr for
    the whole run, silently (the fuzzed 2^70 never left the first step's lr); now a warning says so."""
    import logging

    with caplog.at_level(logging.WARNING, logger="hsicam.engine.loop"):
        train(load_config("tiny", ["train.epochs=1", "train.warmup_steps=8"]), tmp_path / "long", progress=False)
    said = [r.getMessage() for r in caplog.records if "warmup_steps" in r.getMessage()]
    assert said == ["train.warmup_steps=8 is more than the run's 4 steps: the learning rate never reaches train.lr "
                    "(it climbs to 0.5 of it)"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.loop"):  # 4 of 4: its last step is at train.lr
        train(load_config("tiny", ["train.epochs=1", "train.warmup_steps=4"]), tmp_path / "short", progress=False)
    assert not [r for r in caplog.records if "warmup_steps" in r.getMessage()]


def _fused_silica_h2pi_nm(wavelength_nm: float) -> float:
    """λ / (n(λ) − 1) from Malitson's (1965) Sellmeier coefficients for fused silica, written out here."""
    l2 = (wavelength_nm * 1e-3) ** 2
    n2 = 1 + sum(b * l2 / (l2 - c * c) for b, c in ((0.6961663, 0.0684043), (0.4079426, 0.1162414),
                                                      (0.8974794, 9.896161)))
    return wavelength_nm / (n2**0.5 - 1)


def test_camera_learning_rates_as_large_as_the_parameters_span_are_refused():
    """A DOE rate of a whole phase period per step (or a CFA rate of the weights' whole range) throws the
    parameters across their span at every step; it trained on silently before (e.g. doe_lr_nm=1e30)."""
    h2pi = _fused_silica_h2pi_nm(587.6)  # the tiny preset's DOE: fused silica, designed at 587.6 nm
    for rate, ok in ((0.99 * h2pi, True), (1.01 * h2pi, False), (1e30, False)):
        cfg = load_config("tiny", [f"train.doe_lr_nm={rate!r}"])
        if ok:
            SystemTask(cfg, CameraSystem.from_config(cfg))
        else:
            with pytest.raises(ConfigError, match=r"train\.doe_lr_nm=.*whole phase period.*h_2π = 12\d\d nm.*"
                                                  r"freeze=\[doe\]"):
                SystemTask(cfg, CameraSystem.from_config(cfg))
    for rate, ok in ((0.5, True), (1.0, False), (5.0, False)):
        cfg = load_config("tiny", [f"train.cfa_lr={rate}"])
        if ok:
            SystemTask(cfg, CameraSystem.from_config(cfg))
        else:
            with pytest.raises(ConfigError, match=r"train\.cfa_lr=.*range \[0, 1\]"):
                SystemTask(cfg, CameraSystem.from_config(cfg))
    # a frozen group's rate is not used, so it is not checked
    frozen = load_config("tiny", ["train.doe_lr_nm=1e30", "train.cfa_lr=5", "train.freeze=[doe, cfa]"])
    SystemTask(frozen, CameraSystem.from_config(frozen))


def test_freeze_lists_each_group_once_and_a_repeat_counts_once(tmp_path):
    """``train.freeze`` is a set of group names: a repeat is dropped at load (the config a run writes names each once),
    and a run folder whose config.yaml repeats one still loads (refusing it made such a run unreadable)."""
    from hsicam.config import dump_yaml

    cfg = load_config("tiny", ["train.freeze=[doe, cfa, doe]"])
    assert cfg.train.freeze == ["doe", "cfa"]
    text = dump_yaml(cfg).replace("- cfa", "- cfa\n  - doe")
    assert text.count("- doe") == 2
    (tmp_path / "config.yaml").write_text(text)
    assert load_config(tmp_path / "config.yaml").train.freeze == ["doe", "cfa"]


def test_a_gradient_that_overflows_is_a_divergence_not_a_flat_run(tmp_path, cache_env):
    """A loss weight of 1e30 keeps the loss finite (8e29) but its gradient's norm overflows float32: clipping by an
    infinite norm multiplied every gradient by 0, and the run trained on, flat, without an error (session 38)."""
    cfg = load_config("tiny", ["train.epochs=1", "train.ssim_loss=1e30"])
    with pytest.raises(InputError, match=r"diverged at step 0: the loss is .*e\+29 but its gradient's norm is inf"):
        train(cfg, tmp_path / "run", progress=False)


def test_a_clamped_doe_is_checked_against_its_clamp_range():
    """Heights clamped (not wrapped) to [0, max] span max, not h_2π: a DOE rate of 1000 nm on a 300 nm clamp range
    throws them across it at every step; a multi-order DOE clamped at 5 periods takes rates above one period."""
    h2pi = _fused_silica_h2pi_nm(587.6)
    clamped = load_config("tiny", ["camera.doe.max_height_nm=300", "train.doe_lr_nm=1000"])
    with pytest.raises(ConfigError, match=r"train\.doe_lr_nm=1000 nm: .*clamp range camera\.doe\.max_height_nm = 300 nm"):
        SystemTask(clamped, CameraSystem.from_config(clamped))
    deep = load_config("tiny", [f"camera.doe.max_height_nm={5 * h2pi}", f"train.doe_lr_nm={1.5 * h2pi}"])
    SystemTask(deep, CameraSystem.from_config(deep))
    wrapped = load_config("tiny", ["camera.doe.max_height_nm=300", "camera.doe.wrap=true", "train.doe_lr_nm=1000"])
    SystemTask(wrapped, CameraSystem.from_config(wrapped))  # wrapped heights span a phase period (h_2π ≈ 1282 nm)



def test_clearing_an_errors_frames_reaches_the_errors_it_was_raised_from():
    """fit's error path under torchrun clears the traceback's frame locals so the DDP wrapper (and the
    process group it holds) dies with them; a frame reachable only through ``__cause__`` or ``__context__``
    (an error raised while another was handled) is cleared too (review, session 41)."""
    import traceback
    import weakref

    from hsicam.engine.loop import _clear_traceback_frames

    class Held:  # stands for the DDP wrapper a training step's frame holds
        pass

    refs = []

    def step(obj):
        refs.append(weakref.ref(obj))
        raise RuntimeError("inside the step")

    def run(how):
        try:
            step(Held())  # the object is a local of step's frame only
        except RuntimeError as e:
            if how == "cause":
                raise ValueError("from it") from e
            raise ValueError("while handling it")

    for how in ("cause", "context"):
        for clear in (lambda err: traceback.clear_frames(err.__traceback__), _clear_traceback_frames):
            refs.clear()
            try:
                run(how)
            except ValueError as err:
                clear(err)
                alive = refs[0]() is not None
            # the top traceback alone does not reach the step's frame; the chain does
            assert alive is (clear is not _clear_traceback_frames), how


def test_a_failed_rank_told_in_an_earlier_fit_is_not_named_for_a_later_fits_own_error(tmp_path, monkeypatch):
    """A rank that fails on its own leaves its number in the group's store for the other ranks' failed collective
    (PeerFailed names it). The key was one for the whole group: in a group a script made itself and trained in twice,
    a second fit's own error of rank 0 was put on the rank that failed in the first (measured with two gloo processes:
    `_failed_peer(0)` returned 1). Reference: a real in-process c10d store, and what it holds after each fit starts."""
    import torch.distributed as dist

    from hsicam.config import TrainConfig
    from hsicam.engine import loop

    store = dist.HashStore()
    monkeypatch.setattr(dist.distributed_c10d, "_get_default_store", lambda: store)

    class FailsAtOnce(loop.Task):
        def data_record(self):
            raise InputError("this rank's own error")

    def a_fit_ending_in_its_own_error(name):
        with pytest.raises(InputError, match="this rank's own error"):
            fit(FailsAtOnce(), FitOptions(loop=TrainConfig()), tmp_path / name)

    a_fit_ending_in_its_own_error("first")
    loop._tell_failure(1)  # in that fit, rank 1 failed on its own
    assert loop._failed_peer(0) == 1 and loop._failed_peer(1) is None
    a_fit_ending_in_its_own_error("second")  # the next fit: rank 0's error is its own
    assert loop._failed_peer(0) is None
    loop._tell_failure(1)
    assert loop._failed_peer(0) == 1
