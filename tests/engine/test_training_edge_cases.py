"""Guards found by mutation testing of the training engine (the losses and validation of the tasks, the loop's
schedule, clipping, cadences and sampler, tiled reconstruction, checkpoints, the spectral prior's folder): each
test kills a hand-made mutant (a flipped bound, an off-by-one, a dropped normalisation, a skipped branch) that the
rest of the suite let through, and checks the behaviour against a reference computed here (numpy loops, closed
forms, Adam's first step, a whole-image pass), not against the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hsicam.config import TrainConfig


class _Patches(torch.utils.data.Dataset):
    """``n`` fixed random 7-band 8×8 patches from ``seed`` (no scene generation), for the loop's tests."""

    def __init__(self, n, seed):
        self.x = torch.rand(n, 7, 8, 8, generator=torch.Generator().manual_seed(seed))

    def set_epoch(self, epoch):
        pass

    def __len__(self):
        return len(self.x)

    def __getitem__(self, i):
        return self.x[i]


def _angles_deg_free(r: np.ndarray, t: np.ndarray, min_brightness: float) -> list[float]:
    """Spectral angles (rad) of the pixels of (B, C, H, W) arrays whose truth's band mean exceeds ``min_brightness``
    (a numpy loop, float64)."""
    out = []
    for b in range(t.shape[0]):
        for i in range(t.shape[2]):
            for j in range(t.shape[3]):
                if t[b, :, i, j].mean() > min_brightness:
                    cos = np.dot(r[b, :, i, j], t[b, :, i, j]) / (np.linalg.norm(r[b, :, i, j]) * np.linalg.norm(t[b, :, i, j]))
                    out.append(float(np.arccos(np.clip(cos, -1.0, 1.0))))
    return out


# --------------------------------------------------------------------------------------------
# engine/tasks.py: the loss terms
# --------------------------------------------------------------------------------------------
def test_spectral_angle_loss_reaches_past_a_right_angle_for_opposed_spectra():
    """A network may output negative values: an estimate pointing away from the truth has an angle up to π, not
    capped at π/2 (a clamp of the cosine to [0, 1) made every anti-correlated spectrum cost a right angle and
    gave it no gradient)."""
    from hsicam.engine.tasks import spectral_angle_loss

    g = torch.Generator().manual_seed(1)
    truth = 0.2 + torch.rand(1, 5, 4, 6, generator=g, dtype=torch.float64)
    recon = -truth * torch.linspace(0.5, 1.5, 5, dtype=torch.float64)[None, :, None, None]  # obtuse, not exactly −truth
    recon[0, :, 0, :] = truth[0, :, 0, :]  # one row right, for a mean of unequal angles
    ref = np.mean(_angles_deg_free(recon.numpy(), truth.numpy(), 0.01))
    assert ref > 2.0  # most pixels are well past a right angle
    assert float(spectral_angle_loss(recon, truth, 0.01)) == pytest.approx(ref, abs=2e-3)  # (the clamp at ±(1 − 1e-6))


def test_spectral_angle_loss_of_dim_spectra_is_their_angle():
    """With a low ``min_brightness`` (train.relative_eps), dim pixels (band mean 2e-3) count with their true angle:
    the floor under |x̂|²·|x|² must stay far below such products (1e-12 here), or it shrinks their cosine."""
    from hsicam.engine.tasks import spectral_angle_loss

    g = torch.Generator().manual_seed(2)
    truth = 2e-3 * (0.5 + torch.rand(2, 4, 5, 5, generator=g, dtype=torch.float64))
    recon = truth * (1 + 0.3 * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    ref = np.mean(_angles_deg_free(recon.numpy(), truth.numpy(), 1e-4))
    assert float(spectral_angle_loss(recon, truth, 1e-4)) == pytest.approx(ref, rel=1e-6)


def test_spectral_gradient_loss_of_two_bands_is_its_one_step():
    """Two bands have one band step: mean |(x̂₁ − x̂₀) − (x₁ − x₀)|, not 0 (only one band has no step)."""
    from hsicam.engine.tasks import spectral_gradient_loss

    g = torch.Generator().manual_seed(4)
    truth = torch.rand(2, 2, 5, 7, generator=g, dtype=torch.float64)
    recon = truth + 0.1 * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    r, t = recon.numpy(), truth.numpy()
    ref = np.abs((r[:, 1] - r[:, 0]) - (t[:, 1] - t[:, 0])).mean()
    assert ref > 0.01
    assert float(spectral_gradient_loss(recon, truth)) == pytest.approx(ref, rel=1e-12)


@pytest.mark.parametrize("shape", [(1, 2, 2, 9), (1, 2, 9, 2), (1, 2, 2, 2)])
def test_phase_trace_loss_of_a_patch_narrower_than_the_period_is_zero_not_nan(shape):
    """A patch less than one period high or wide holds no whole period: no phase trace, 0 (and a gradient),
    not the NaN of a mean over an empty window."""
    from hsicam.engine.tasks import phase_trace_loss

    err = torch.rand(shape, dtype=torch.float64, requires_grad=True)
    loss = phase_trace_loss(err, 3)
    assert float(loss.detach()) == 0.0
    loss.backward()
    assert torch.isfinite(err.grad).all()


class _StubSystem:
    """What :func:`validate_system` calls: ``model(scene, g) -> (estimate, _)`` and ``model.target(scene)``; the
    estimate overshoots the truth (×1.3 + 0.05), so that clipping to [0, 1] matters."""

    def __call__(self, scene, g):
        return scene * 1.3 + 0.05, None

    def target(self, scene):
        return scene


def test_validation_scores_are_means_over_patches_of_the_clipped_estimate():
    """validate_system: PSNR (mean over bands, peak 1), SSIM (scikit-image) and SAM (°) of each patch, the estimate
    clipped to [0, 1], averaged over patches (batches of 2 and 1), SAM over the patches whose truth is not black."""
    from skimage.metrics import structural_similarity

    from hsicam.engine.tasks import validate_system

    g = torch.Generator().manual_seed(7)
    patches = torch.rand(3, 3, 12, 12, generator=g)
    patches[2] = 0.0  # a black patch: no spectral angle
    loader = [patches[:2], patches[2:]]
    psnr, ssim, sam = [], [], []
    for x in patches.double().numpy():
        y = np.clip(x * 1.3 + 0.05, 0.0, 1.0)
        psnr.append(np.mean([10 * np.log10(1.0 / np.mean((y[c] - x[c]) ** 2)) for c in range(3)]))
        ssim.append(np.mean([structural_similarity(x[c], y[c], gaussian_weights=True, sigma=1.5,
                                                   use_sample_covariance=False, data_range=1.0) for c in range(3)]))
        if x.any():
            sam.append(np.degrees(np.mean(_angles_deg_free(y[None], x[None], -1.0))))
    got = validate_system(_StubSystem(), loader, torch.device("cpu"), seed=0)
    assert got["psnr"] == pytest.approx(np.mean(psnr), rel=1e-5)
    assert got["ssim"] == pytest.approx(np.mean(ssim), rel=1e-5)
    assert got["sam"] == pytest.approx(np.mean(sam), rel=1e-4)


# --------------------------------------------------------------------------------------------
# engine/loop.py: schedule, clipping, cadences, running loss, sampler
# --------------------------------------------------------------------------------------------
def test_warm_up_ends_at_the_schedules_own_value():
    """The step right after a warm-up of W steps is the schedule's value there (cosine: its start, 1, then
    ½(1 + cos(π (s − W) / (T − W))) over the remaining steps), not (W + 1) / W > 1: the warm-up covers steps
    0 … W − 1 only."""
    from hsicam.engine.loop import lr_factor

    for w in (1, 4, 10):
        t = TrainConfig(lr_schedule="cosine", warmup_steps=w)
        assert lr_factor(t, w - 1, 100, 10) == pytest.approx(1.0, abs=1e-15)
        assert lr_factor(t, w, 100, 10) == pytest.approx(1.0, abs=1e-15)
        assert lr_factor(t, w + 1, 100, 10) == pytest.approx(0.5 * (1 + math.cos(math.pi / (100 - w))), abs=1e-15)
    t = TrainConfig(lr_schedule="constant", warmup_steps=4)
    assert [lr_factor(t, s, 100, 10) for s in range(7)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0, 1.0]


def test_the_loop_steps_adam_at_the_scheduled_rate_with_clipped_gradients_and_logs_and_saves_on_its_cadence(
        tmp_path, monkeypatch):
    """One run of the loop (the spectral prior's task: 3 epochs of 4 steps), watched from outside:

    - each Adam step uses base lr × (warm-up (s + 1)/W for s < W, then ½(1 + cos(π (s − W) / (T − W)))), closed form here;
    - the gradient Adam steps with has a global norm of at most train.grad_clip (clipping is active here);
    - metrics.jsonl has a train record every log_every_steps steps, whose ``lr`` is the rate of the step just
      taken and whose ``train_loss`` is the mean of this epoch's step losses so far (recorded here);
    - validations at the epochs divisible by eval_every_epochs and at the last epoch (2 and 3 of 3);
    - checkpoints every checkpoint_every_steps steps and at every epoch's end."""
    import dataclasses
    import json

    from hsicam.config import ChoiConfig, load_config
    from hsicam.engine.loop import FitOptions, fit
    from hsicam.engine.tasks import PriorTask
    from hsicam.runs.checkpoint import CheckpointManager

    losses: list[float] = []

    class Watched(PriorTask):
        def data_record(self):
            return None

        def datasets(self):
            return _Patches(16, 0), _Patches(4, 1)

        def training_step(self, trainable, clean, generator):
            loss = super().training_step(trainable, clean, generator)
            losses.append(float(loss.detach()))
            return loss

    steps: list[tuple[list[float], float]] = []
    adam_step = torch.optim.Adam.step

    def watched_step(self, *args, **kwargs):
        grads = [p.grad for g in self.param_groups for p in g["params"] if p.grad is not None]
        steps.append(([g["lr"] for g in self.param_groups], float(torch.sqrt(sum((x.double() ** 2).sum() for x in grads)))))
        return adam_step(self, *args, **kwargs)

    saves: list[int] = []
    save = CheckpointManager.save

    def watched_save(self, model, optimizer, state, *args, **kwargs):
        saves.append(int(state["global_step"]))
        return save(self, model, optimizer, state, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", watched_step)
    monkeypatch.setattr(CheckpointManager, "save", watched_save)
    cfg = load_config("tiny")  # 7 bands
    settings = ChoiConfig(train_steps=12, batch_size=4, features=8, latent=3, lr=3e-3)
    torch.manual_seed(0)
    task = Watched(cfg, settings)
    lr, w, total, clip = 3e-3, 3, 12, 1e-4
    loop = dataclasses.replace(task.loop_config(), epochs=3, warmup_steps=w, grad_clip=clip, log_every_steps=2,
                               eval_every_epochs=2, checkpoint_every_steps=5)
    fit(task, FitOptions(loop, 0, progress=False), tmp_path / "run")

    factor = [(s + 1) / w if s < w else 0.5 * (1 + math.cos(math.pi * (s - w) / (total - w))) for s in range(total)]
    assert len(steps) == len(losses) == total
    for s, (lrs, _) in enumerate(steps):
        assert lrs == [pytest.approx(lr * factor[s], rel=1e-12)], f"step {s}"
    norms = [n for _, n in steps]
    # the raw norms are 5e-4 … 1e-3 here: each step's is brought down to the clip (× 1/(1 + 1e-6/norm), torch's guard)
    assert norms == [pytest.approx(clip, rel=1e-2)] * total

    recs = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in recs if "train_loss" in r]
    assert [r["step"] for r in train] == [2, 4, 6, 8, 10, 12]
    for r in train:
        k = r["step"]
        epoch_start = (k - 1) // 4 * 4
        assert r["lr"] == pytest.approx(lr * factor[k - 1], rel=1e-12)
        assert r["train_loss"] == pytest.approx(np.mean(losses[epoch_start:k]), rel=1e-9), f"step {k}"
    assert [r["step"] for r in recs if "val_psnr" in r and not r.get("final")] == [8, 12]
    assert saves == [4, 5, 8, 10, 12]


@pytest.mark.parametrize("world", [1, 2, 4])
@pytest.mark.parametrize("start", [0, 2])
def test_sharded_batches_give_each_rank_its_slice_of_the_remaining_global_batches(world, start):
    """Global batch b holds items b·B … b·B + B − 1 (brute force: the item list cut into B-sized batches); rank r takes
    its r-th contiguous B/world of each batch from ``start_batch`` on, the ranks together each item once, and the
    sampler's length is what it yields."""
    from hsicam.engine.loop import ShardedBatches

    n_batches, batch = 5, 8
    items = list(range(n_batches * batch))
    global_batches = [items[i:i + batch] for i in range(0, len(items), batch)]
    per = batch // world
    union = []
    for rank in range(world):
        sampler = ShardedBatches(n_batches, batch, rank, world, start)
        got = list(sampler)
        ref = [x for gb in global_batches[start:] for x in gb[rank * per:(rank + 1) * per]]
        assert got == ref
        assert len(sampler) == len(ref)
        union += got
    assert sorted(union) == [x for gb in global_batches[start:] for x in gb]


# --------------------------------------------------------------------------------------------
# engine/inference.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("h, w", [(10, 3), (3, 10), (10, 10)])
def test_tiling_an_image_taller_or_wider_than_a_tile_needs_a_halo(h, w):
    """A reconstruction that declares no context_px, on an image larger than one tile in either direction (not
    only in both), is refused with the message that names the halo; with a halo given it is tiled (window sides at
    most tile + 2 halos) and equals the whole-image pass of a pixel-wise map."""
    from hsicam.engine.inference import reconstruct_tiled
    from hsicam.errors import InputError

    sensor = torch.rand(1, 1, h, w, dtype=torch.float64)
    windows = []

    def rec(x):
        windows.append(tuple(x.shape[-2:]))
        return torch.cat([x, 2 * x], dim=1)

    with pytest.raises(InputError, match=rf"^halo_px is needed: function declares no context_px, and the {h}×{w} px "
                                         r"image is cut into 4 px tiles"):
        reconstruct_tiled(rec, sensor, tile_px=4)
    assert windows == []
    out = reconstruct_tiled(rec, sensor, tile_px=4, halo_px=1)
    torch.testing.assert_close(out, torch.cat([sensor, 2 * sensor], dim=1), rtol=0, atol=0)
    assert len(windows) == math.ceil(h / 4) * math.ceil(w / 4) and max(max(s) for s in windows) <= 4 + 2


def test_the_memory_estimate_counts_the_largest_window_the_tiling_cuts():
    """reconstruction_memory_bytes = base + fixed + 4 B · C · (1 whole-image cube + 13 cubes of one window): the window being
    the largest one reconstruct_tiled actually cuts (a tile and a halo on each side, measured here), not a tile and
    one halo."""
    from hsicam.engine.inference import (RECONSTRUCT_BASE_BYTES, RECONSTRUCT_FIXED_BYTES, WINDOW_CUBES,
                                         reconstruct_tiled, reconstruction_memory_bytes)

    class Local:
        context_px = 5

        def __init__(self):
            self.areas = []

        def __call__(self, x):
            self.areas.append(x.shape[-2] * x.shape[-1])
            return x.expand(-1, 3, -1, -1)

    rec, (h, w, tile) = Local(), (40, 37, 16)
    reconstruct_tiled(rec, torch.rand(1, 1, h, w), tile_px=tile)
    assert max(rec.areas) == (tile + 10) ** 2  # an inner tile
    expect = RECONSTRUCT_BASE_BYTES + RECONSTRUCT_FIXED_BYTES + 4 * 3 * (h * w + WINDOW_CUBES * max(rec.areas))
    assert reconstruction_memory_bytes(rec, 3, h, w, tile_px=tile) == expect


def test_step_generators_differ_by_rank_and_repeat_for_the_same_seed_step_and_rank():
    """The random numbers of step n depend on (seed, n, rank): the DDP ranks' shares of a batch draw their own noise
    (the same draws on every rank would correlate the noise of the global batch), and a resume repeats them."""
    from hsicam.engine.loop import step_generator

    def first(seed, step, rank):
        return float(torch.rand((), generator=step_generator(seed, step, rank, "cpu")))

    draws = [first(0, 5, r) for r in range(4)]
    assert len(set(draws)) == 4
    assert draws == [first(0, 5, r) for r in range(4)]
    assert first(0, 5, 0) != first(0, 6, 0) and first(0, 5, 0) != first(1, 5, 0)


# --------------------------------------------------------------------------------------------
# engine/tasks.py: the system task's noise and frozen groups, the prior's task
# --------------------------------------------------------------------------------------------
def test_validation_and_the_end_of_training_use_the_cameras_own_noise_not_the_last_steps_draw():
    """Each training step sets the noise drawn from the train ranges (here σ_s = 0.05, σ_p = 7 nm); the validation and
    the weights left after training use the camera's configured levels (σ_s = 0.01, σ_p = 3 nm) again."""
    from hsicam.config import load_config
    from hsicam.engine.loop import step_generator
    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    cfg = load_config("tiny", ["camera.sensor.sigma=0.01", "camera.doe.sigma_height_nm=3", "train.sensor_sigma=[0.05, 0.05]",
                               "train.sigma_height_nm=[7, 7]"])
    task = SystemTask(cfg, CameraSystem.from_config(cfg))
    own = {"sensor_sigma": pytest.approx(0.01, rel=1e-6), "sigma_height_nm": pytest.approx(3.0, rel=1e-6)}
    drawn = {"sensor_sigma": pytest.approx(0.05, rel=1e-6), "sigma_height_nm": pytest.approx(7.0, rel=1e-6)}
    for end in (lambda: task.validate([], torch.device("cpu")), lambda: task.on_fit_end(None, {})):
        task.on_step_start(0, step_generator(0, 0, 0, "cpu"))
        assert task.model.camera.noise_levels() == drawn
        end()
        assert task.model.camera.noise_levels() == own


def test_a_frozen_groups_parameters_get_no_gradient():
    """train.freeze=[doe]: the DOE heights are left out of the optimizer and get no gradient from a training step
    (no backward pass through them), while the CFA and the network do."""
    from hsicam.config import load_config
    from hsicam.engine.loop import step_generator
    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    cfg = load_config("tiny", ["train.freeze=[doe]"])
    torch.manual_seed(0)
    model = CameraSystem.from_config(cfg)
    task = SystemTask(cfg, model)
    groups = task.param_groups()
    assert [g["name"] for g in groups] == ["net", "cfa"]
    g = step_generator(0, 0, 0, "cpu")
    scene = torch.rand(2, len(model.bands), 16 + model.camera.margin * 2, 16 + model.camera.margin * 2, generator=g)
    task.training_step(model, scene, g).backward()
    assert model.camera.optics.doe.height_m.grad is None
    assert model.camera.cfa.weights.grad is not None and any(p.grad is not None for p in model.net.parameters())


def test_the_priors_training_noise_is_drawn_per_patch_uniform_in_zero_to_train_noise():
    """PriorTask.training_step corrupts each patch with Gaussian noise of its own σ ~ U[0, train_noise]: through an
    identity network the loss is mean(σ² n²), whose expectation is train_noise² / 3 (a fixed σ = train_noise: 3×
    that); 4000 patches bring the mean within a few %."""
    from hsicam.config import ChoiConfig, load_config
    from hsicam.engine.tasks import PriorTask

    task = PriorTask(load_config("tiny"), ChoiConfig(features=8, latent=3, train_noise=0.2))
    clean = torch.rand(4000, 3, 2, 2, dtype=torch.float64)
    loss = float(task.training_step(lambda x: x, clean, torch.Generator().manual_seed(0)))
    assert loss == pytest.approx(0.2**2 / 3, rel=0.05)


def test_the_priors_validation_psnr_is_over_every_value_of_the_validation_patches():
    """PriorTask.validate: −10 log10 of the mean squared error over all values of all validation patches (peak 1),
    computed here in numpy from the autoencoder's outputs."""
    from hsicam.config import ChoiConfig, load_config
    from hsicam.engine.tasks import PriorTask

    torch.manual_seed(0)
    task = PriorTask(load_config("tiny"), ChoiConfig(features=8, latent=3))
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():  # (the untrained autoencoder is the identity)
        for p in task.model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    c = len(task.bands)
    loader = [torch.rand(3, c, 5, 4, generator=g), torch.rand(1, c, 5, 4, generator=g)]
    with torch.no_grad():
        err = np.concatenate([(task.model(x) - x).double().numpy().ravel() for x in loader])
    got = task.validate(loader, torch.device("cpu"))
    assert got["psnr"] == pytest.approx(-10 * np.log10(np.mean(err**2)), rel=1e-5)


# --------------------------------------------------------------------------------------------
# runs/checkpoint.py
# --------------------------------------------------------------------------------------------
def test_a_checkpoint_at_step_zero_is_a_readable_last_and_best(tmp_path):
    """A fine-tuning validates its starting weights and saves them as step 0 (last and best): the manifest's
    entries with step 0 are read back (not refused as corrupt), and the run's weights are that checkpoint's."""
    from hsicam.runs.checkpoint import CheckpointManager, kept_checkpoint, read_weights
    from hsicam.spectral import Bands

    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    mgr = CheckpointManager(tmp_path)
    mgr.save(model, opt, {"global_step": 0, "best_psnr": 20.0}, Bands.uniform(500, 600, 50), ("last", "best"))
    assert CheckpointManager(tmp_path).state()["global_step"] == 0
    kept = kept_checkpoint(tmp_path)
    assert (kept["checkpoint"], kept["step"], kept["last_step"]) == ("best", 0, 0)
    saved, _ = read_weights(tmp_path / "model.safetensors")
    torch.testing.assert_close(saved["weight"], model.weight.detach(), rtol=0, atol=0)


def test_a_later_validation_that_only_ties_the_best_keeps_the_earlier_checkpoint_as_best(tmp_path):
    """"The checkpoint of the highest validation PSNR so far" (docs/training.md): a later validation that
    equals it is not higher, so best stays at the first step that reached it (in checkpoints.json, read back as
    JSON, and in the final record) while last moves on."""
    import dataclasses
    import json

    from hsicam.config import ChoiConfig, load_config
    from hsicam.engine.loop import FitOptions, fit
    from hsicam.engine.tasks import PriorTask

    class Flat(PriorTask):
        """Every validation scores the same PSNR (a tie each epoch)."""

        def data_record(self):
            return None

        def datasets(self):
            return _Patches(8, 0), _Patches(4, 1)

        def validate(self, loader, device):
            return {"psnr": 30.0}

    torch.manual_seed(0)
    task = Flat(load_config("tiny"), ChoiConfig(train_steps=6, batch_size=4, features=8, latent=3, lr=1e-3))
    loop = dataclasses.replace(task.loop_config(), epochs=3, eval_every_epochs=1, checkpoint_every_steps=1000)
    final = fit(task, FitOptions(loop, 0, progress=False), tmp_path / "run")
    man = json.loads((tmp_path / "run" / "checkpoints.json").read_text())
    assert (man["last"]["step"], man["best"]["step"]) == (6, 2)
    assert final["best_psnr"] == 30.0


def test_a_run_keeping_its_last_weights_roots_them_from_the_last_checkpoint_even_when_an_earlier_was_best(tmp_path):
    """keep="last": after a best at step 1 and a later last at step 2, checkpoints.json (read back as JSON) says the
    root weights come from the last, and RUN/model.safetensors holds the step-2 weights, not the best's."""
    import json

    from hsicam.runs.checkpoint import CheckpointManager, read_weights
    from hsicam.spectral import Bands

    bands = Bands.uniform(500, 600, 50)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    mgr = CheckpointManager(tmp_path, keep="last")
    mgr.save(model, opt, {"global_step": 1, "best_psnr": 20.0}, bands, ("last", "best"))
    with torch.no_grad():
        model.weight.add_(1.0)
    mgr.save(model, opt, {"global_step": 2, "best_psnr": 20.0}, bands, ("last",))
    mgr.sync_root()
    man = json.loads((tmp_path / "checkpoints.json").read_text())
    assert (man["weights"]["from"], man["best"]["step"], man["last"]["step"]) == ("last", 1, 2)
    saved, _ = read_weights(tmp_path / "model.safetensors")
    torch.testing.assert_close(saved["weight"], model.weight.detach(), rtol=0, atol=0)


def test_weights_of_another_band_grid_or_an_optimizer_of_other_groups_are_refused(tmp_path):
    """Weights saved for 500–600 nm in 50 nm steps do not load into a model of 10 nm steps; an optimizer state of the
    groups ["net"] does not load into one training ["net", "doe"]: each one line naming the file."""
    from hsicam.errors import InputError
    from hsicam.runs.checkpoint import load_optimizer, load_weights, save_optimizer, save_weights
    from hsicam.spectral import Bands

    model = torch.nn.Linear(3, 2)
    save_weights(tmp_path / "w.safetensors", model, Bands.uniform(500, 600, 50))
    with pytest.raises(InputError, match=r"w\.safetensors: checkpoint was trained on .*, but the model has "):
        load_weights(tmp_path / "w.safetensors", model, Bands.uniform(500, 600, 10))
    doe = torch.nn.Parameter(torch.zeros(2))
    saved = torch.optim.Adam([{"params": model.parameters(), "name": "net"}])
    save_optimizer(tmp_path / "opt.safetensors", saved)
    now = torch.optim.Adam([{"params": model.parameters(), "name": "net"}, {"params": [doe], "name": "doe"}])
    with pytest.raises(InputError) as exc:
        load_optimizer(tmp_path / "opt.safetensors", now)
    assert str(exc.value) == (
        f"{tmp_path / 'opt.safetensors'}: the run trained the parameter groups net, this config trains net, doe "
        "(train.freeze, or a camera part switched on or off, differs from the run's config.yaml); resume with the "
        "run's own settings, or start a new run")


def test_a_prior_whose_last_checkpoint_reached_its_steps_is_not_in_progress(tmp_path):
    """prior_progress: a checkpoint at step 10 of 10 (no summary.json yet) is done, at step 9 it is (9, 10)."""
    from hsicam.config import ChoiConfig
    from hsicam.engine.prior import PRIOR_WEIGHTS, prior_progress
    from hsicam.runs.checkpoint import CheckpointManager
    from hsicam.spectral import Bands

    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    settings = ChoiConfig(train_steps=10)
    for step, want in ((9, (9, 10)), (10, None)):
        CheckpointManager(tmp_path, PRIOR_WEIGHTS).save(model, opt, {"global_step": step}, Bands.uniform(500, 600, 50),
                                                        ("last",))
        assert prior_progress(tmp_path, settings) == want


def test_a_prior_folder_is_finished_only_with_its_summary_and_its_weights(tmp_path):
    from hsicam.engine.prior import PRIOR_WEIGHTS, is_prior_run

    (tmp_path / "summary.json").write_text("{}")
    assert not is_prior_run(tmp_path)  # weights deleted or never written
    (tmp_path / PRIOR_WEIGHTS).write_bytes(b"")
    assert is_prior_run(tmp_path)
    (tmp_path / "summary.json").unlink()
    assert not is_prior_run(tmp_path)


@pytest.mark.parametrize("key, value", [("features", 16), ("latent", 8), ("train_steps", 7), ("batch_size", 3),
                                        ("lr", 2e-3), ("train_noise", 0.1), ("seed", 5)])
def test_a_prior_trained_with_another_autoencoder_setting_is_named_and_an_admm_setting_is_not(tmp_path, key, value):
    """prior_differences: every setting that changes the trained autoencoder (its sizes, its training and its seed)
    is named as "baselines.choi.KEY: have → want"; the ADMM settings, applied at evaluation, are not."""
    import dataclasses

    import yaml

    from hsicam.config import ChoiConfig, dump_yaml, load_config
    from hsicam.engine.prior import PRIOR_SETTINGS, prior_differences

    cfg = load_config("tiny")
    (tmp_path / "config.yaml").write_text(dump_yaml(cfg))
    have = ChoiConfig()
    (tmp_path / PRIOR_SETTINGS).write_text(yaml.safe_dump(dataclasses.asdict(have)))
    assert prior_differences(tmp_path, cfg, have) == []
    assert prior_differences(tmp_path, cfg, dataclasses.replace(have, iterations=3, rho=0.25)) == []
    want = dataclasses.replace(have, **{key: value})
    assert prior_differences(tmp_path, cfg, want) == [f"baselines.choi.{key}: {getattr(have, key)!r} → {value!r}"]
