"""Training-loop items earlier sessions left alone (session 60): the learning-rate schedule where the
warm-up ends, the spectral-angle term's gradient at a zero estimate, the patch stream's seed."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hsicam.config import TrainConfig
from patch_streams import NPY_BANDS, assert_seeded_streams, write_scenes
from hsicam.engine.loop import lr_factor


# ------------------------------------------------------------------------------------------------
# 1. warm-up then cosine: continuous where the warm-up ends
# ------------------------------------------------------------------------------------------------
def _warmup_cosine(s: int, w: int, total: int) -> float:
    """Linear warm-up (s + 1)/W, then a cosine over the remaining T − W steps (the usual "linear warm-up then
    cosine decay", e.g. transformers' get_cosine_schedule_with_warmup, with the warm-up reaching 1 at its last step)."""
    if s < w:
        return (s + 1) / w
    return 0.5 * (1 + math.cos(math.pi * min((s - w) / max(total - w, 1), 1.0)))


@pytest.mark.parametrize("w, total", [(0, 1), (0, 10), (1, 10), (4, 100), (20, 640), (50, 100), (9, 10), (99, 100)])
def test_cosine_after_warm_up_runs_over_the_remaining_steps_without_a_drop(w, total):
    t = TrainConfig(lr_schedule="cosine", warmup_steps=w)
    run = [lr_factor(t, s, total, 10) for s in range(total + 1)]
    for s, f in enumerate(run):
        assert f == pytest.approx(_warmup_cosine(s, w, total), rel=1e-12, abs=1e-15), f"step {s}"
    # continuity where the warm-up ends: its last step and the first cosine step both run at the full rate
    if w:
        assert run[w - 1] == pytest.approx(1.0, abs=1e-15)
    assert run[w] == pytest.approx(1.0, abs=1e-15)
    # the cosine reaches its floor 0 at T, and decays monotonically to it; the warm-up never overshoots 1
    assert run[total] == pytest.approx(0.0, abs=1e-12) or w >= total
    assert all(b <= a + 1e-15 for a, b in zip(run[w:], run[w + 1:]))
    assert all(0 < f <= 1 for f in run[:total])
    # a resumed run at step k gets the uninterrupted run's factor: the schedule is a function of the step
    assert [lr_factor(t, s, total, 10) for s in reversed(range(total + 1))] == run[::-1]


# ------------------------------------------------------------------------------------------------
# 2. the spectral-angle term: a bounded gradient at a (near) zero estimate, the same angle elsewhere
# ------------------------------------------------------------------------------------------------
def _np_angles(r: np.ndarray, t: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """arccos of the normalised dot product, pixel by pixel (float64), over the kept pixels."""
    out = []
    for b, i, j in zip(*np.nonzero(keep)):
        x, y = r[b, :, i, j], t[b, :, i, j]
        out.append(np.arccos(np.clip(x @ y / (np.linalg.norm(x) * np.linalg.norm(y)), -1.0, 1.0)))
    return np.array(out)


def _bright_pair(seed: int, c: int = 8):
    g = torch.Generator().manual_seed(seed)
    truth = 0.2 + 0.6 * torch.rand(2, c, 5, 6, generator=g, dtype=torch.float64)
    recon = truth * (1 + 0.2 * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    return recon, truth


@pytest.mark.parametrize("level", [0.0, 1e-20, 1e-30])
def test_spectral_angle_gradient_is_bounded_at_a_near_zero_estimate_of_a_bright_pixel(level):
    """One bright pixel estimated as (near) zero: the angle's gradient 1/|x̂| was 1e11 at an exact zero (16 pixels),
    1e18 at 1e-20 of the truth, inf at 1e-30. With the floor δ = SAM_LOSS_FLOOR on |u|, u = x̂ / (peak(x) · s)
    (s = median over the kept pixels of peak(x̂)/peak(x)), the gradient in u is at most 2/δ, so at the pixel
    |∂L/∂x̂| ≤ 2 / (δ · peak(x) · s · K), K the kept pixels; at an exact zero it is that bound (u = 0: cos = u·y/(δ/2 |y|)),
    and the angle there is π/2."""
    from hsicam.engine.tasks import SAM_LOSS_FLOOR, spectral_angle_loss

    recon, truth = _bright_pair(1)
    recon[0, :, 2, 3] = level * truth[0, :, 2, 3] * torch.linspace(0.5, 1.5, truth.shape[1], dtype=torch.float64)
    recon.requires_grad_(True)
    loss = spectral_angle_loss(recon, truth, 0.01)
    loss.backward()
    r, t = recon.detach().numpy(), truth.numpy()
    k = t.shape[0] * t.shape[2] * t.shape[3]  # every pixel is bright
    ratios = np.sort((np.abs(r).max(axis=1) / np.abs(t).max(axis=1)).ravel())
    s = ratios[(ratios.size - 1) // 2]  # the lower middle, as torch.median
    bound = 2 / (SAM_LOSS_FLOOR * np.abs(t[0, :, 2, 3]).max() * s * k)
    g = recon.grad
    assert torch.isfinite(g).all()
    at = float(g[0, :, 2, 3].norm())
    assert at <= bound * (1 + 1e-9)
    others = np.ones((2, 5, 6), bool)
    others[0, 2, 3] = False
    if level == 0.0:
        assert at == pytest.approx(bound, rel=1e-9)
        assert float(loss.detach()) == pytest.approx((np.sum(_np_angles(r, t, others)) + np.pi / 2) / k, rel=1e-9)
    # every other pixel keeps its gradient 1/|x̂|-sized: far below the bound (no pixel under the floor but this one)
    assert float(g.norm(dim=1)[torch.from_numpy(others)].max()) < 0.01 * bound


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("scale", [1.0, 1e-12, 1e12])
def test_spectral_angle_value_is_unchanged_on_ordinary_spectra(dtype, scale):
    """Where every estimate is well above the floor (here each pixel's |u| is near its truth's, > 1e2 δ), the term is
    the mean of numpy's arccos of the normalised dot product (float64), to 1e-6, whatever the estimate's overall scale;
    dark pixels (truth's band mean below min_brightness) are left out."""
    from hsicam.engine.tasks import spectral_angle_loss

    recon, truth = _bright_pair(2, c=31)
    truth[1, :, :2] *= 0.01  # two dark rows, left out below min_brightness 0.05
    recon = recon * scale
    keep = truth.mean(dim=1).numpy() > 0.05
    ref = _np_angles(recon.numpy(), truth.numpy(), keep).mean()
    got = float(spectral_angle_loss(recon.to(dtype), truth.to(dtype), 0.05))
    assert got == pytest.approx(ref, abs=1e-6)


# ------------------------------------------------------------------------------------------------
# 3. train.seed and the training patches
# ------------------------------------------------------------------------------------------------
def test_train_seed_draws_its_own_patches_and_the_default_keeps_todays_stream(tmp_path):
    """train.seed changed the network's start and the noise but not the patches: runs "with two seeds" trained on
    one patch stream (seeds 0, 1 and 7 of the tiny preset drew byte-identical patches). Now a seed s ≠ 0 draws
    patch k of epoch e from (data.split_seed, e, k, s); the default 0 keeps the (split_seed, e, k) stream of every
    run before (the demo, the shipped weights), and the validation patches do not depend on the seed."""
    from hsicam.config import load_config
    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    cubes = write_scenes(tmp_path)

    def datasets(seed):
        cfg = load_config("tiny", [f"data.root={tmp_path}", f"train.seed={seed}", "data.split_seed=3", NPY_BANDS])
        return SystemTask(cfg, CameraSystem.from_config(cfg)).datasets()

    assert_seeded_streams(datasets, cubes, split_seed=3, what="seed")
