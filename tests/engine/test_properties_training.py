"""Property-based tests (hypothesis) of the training side's pure functions: the loss terms of
:func:`hsicam.engine.tasks.system_loss`, the learning-rate schedule and gradient clipping. Each invariant is checked
against an independent reference: brute-force numpy loops (angles, per-phase means, band differences), scipy's box
filter, scikit-image's SSIM, the closed-form schedule. The properties of the data the training reads (the patch
sampler and its relighting, the synthetic generator, the memory arithmetic) are in
data/test_properties_datasets.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import example, given
from hypothesis import strategies as st
from scipy.ndimage import uniform_filter
from skimage.metrics import structural_similarity

from hsicam.config import TrainConfig
from hsicam.engine.loop import lr_factor
from hsicam.engine.tasks import spectral_angle_loss, system_loss
from property_settings import TRAINING_PROPS as PROPS

pytestmark = pytest.mark.usefixtures("one_torch_thread")
TERMS = ("relative_l1", "ssim_loss", "sam_loss", "spectral_grad_loss", "phase_loss")


# ------------------------------------------------------------------------------------------------
# Brute-force references of the loss terms
# ------------------------------------------------------------------------------------------------
def _ref_relative_l1(r: np.ndarray, t: np.ndarray, eps: float) -> float:
    m = t.mean(axis=1)
    local = np.stack([uniform_filter(m[b], 9, mode="constant", cval=0.0) for b in range(m.shape[0])])[:, None] + eps
    return float((np.abs(r - t) / local).mean())


def _ref_ssim(r: np.ndarray, t: np.ndarray) -> float:
    return float(np.mean([structural_similarity(r[b, c], t[b, c], gaussian_weights=True, sigma=1.5,
                                                use_sample_covariance=False, data_range=1.0)
                          for b in range(r.shape[0]) for c in range(r.shape[1])]))


def _ref_sam(r: np.ndarray, t: np.ndarray, eps: float) -> float:
    """Mean angle (rad) over the pixels whose truth's band mean exceeds eps, the cosine kept within 1 − 1e-6 of ±1
    (the documented clamp: acos has no gradient at 1)."""
    angles = []
    for b in range(r.shape[0]):
        for y in range(r.shape[2]):
            for x in range(r.shape[3]):
                tv, rv = t[b, :, y, x].astype(np.float64), r[b, :, y, x].astype(np.float64)
                if tv.mean() > eps:
                    cos = rv @ tv / math.sqrt((rv @ rv) * (tv @ tv)) if rv @ rv > 0 else 0.0
                    angles.append(math.acos(min(max(cos, -1 + 1e-6), 1 - 1e-6)))
    return float(np.mean(angles)) if angles else 0.0


def _ref_phase(e: np.ndarray, m: int) -> float:
    b_, c_, h, w = e.shape
    hm, wm = h // m * m, w // m * m
    if m < 2 or hm == 0 or wm == 0:
        return 0.0
    out = []
    for b in range(b_):
        for c in range(c_):
            ph = np.array([[e[b, c, i:hm:m, j:wm:m].mean() for j in range(m)] for i in range(m)])
            out.append(np.abs(ph - ph.mean()).mean())
    return float(np.mean(out))


def _ref_term(name: str, r: np.ndarray, t: np.ndarray, eps: float, m: int) -> float:
    if name == "relative_l1":
        return _ref_relative_l1(r, t, eps)
    if name == "ssim_loss":
        return 1.0 - _ref_ssim(r, t)
    if name == "sam_loss":
        return _ref_sam(r, t, eps)
    if name == "spectral_grad_loss":
        return float(np.abs(np.diff(r, axis=1) - np.diff(t, axis=1)).mean()) if r.shape[1] > 1 else 0.0
    return _ref_phase(r - t, m)


@PROPS
@given(b=st.integers(1, 2), c=st.integers(1, 5), h=st.integers(11, 17), w=st.integers(11, 17), m=st.integers(1, 4),
       eps=st.sampled_from([1e-3, 0.01, 0.3]), noise=st.sampled_from([0.0, 0.05, 0.3]), seed=st.integers(0, 2**16))
def test_each_loss_term_is_its_brute_force_reference(b, c, h, w, m, eps, noise, seed):
    """system_loss = L1 + Σ weight × term, each term against its own reference (float64)."""
    rng = np.random.default_rng(seed)
    t = rng.random((b, c, h, w))
    r = t + noise * rng.standard_normal(t.shape)
    rt, tt = torch.from_numpy(r), torch.from_numpy(t)
    l1 = float(np.abs(r - t).mean())
    assert float(system_loss(rt, tt, TrainConfig(relative_eps=eps), m)) == pytest.approx(l1, rel=1e-12)
    for name in TERMS:
        weight = 0.7
        got = float(system_loss(rt, tt, TrainConfig(relative_eps=eps, **{name: weight}), m)) - l1
        assert got == pytest.approx(weight * _ref_term(name, r, t, eps, m), rel=1e-6, abs=1e-9), name


@PROPS
@given(scale_exp=st.integers(-9, 12), c=st.integers(2, 31), seed=st.integers(0, 2**16))
@example(scale_exp=-8, c=31, seed=0)
@example(scale_exp=10, c=31, seed=0)
def test_spectral_angle_loss_is_free_of_the_datas_scale(scale_exp, c, seed):
    """The angle between two spectra does not depend on their common scale: the float32 loss of k·x̂ and k·x (with
    the brightness threshold k·ε) is the float64 angle of x̂ and x for any k in 1e-9 … 1e12. Before the fix the
    product of squared norms fell under its 1e-24 floor for dim data (k = 1e-8: 1.57 rad instead of 0.07) and
    overflowed float32 for bright data (k = 1e10: π/2)."""
    rng = np.random.default_rng(seed)
    t = 0.1 + rng.random((1, c, 5, 6))
    r = t * (1 + 0.1 * rng.standard_normal(t.shape))
    k = 10.0 ** scale_exp
    ref = _ref_sam(r, t, 0.01)
    got = float(spectral_angle_loss(torch.from_numpy(r * k).float(), torch.from_numpy(t * k).float(), 0.01 * k))
    assert got == pytest.approx(ref, rel=2e-3, abs=2e-4)


@PROPS
@given(scale_exp=st.integers(-15, 15), c=st.integers(2, 31), seed=st.integers(0, 2**16))
@example(scale_exp=-13, c=31, seed=0)
def test_spectral_angle_loss_is_free_of_the_estimates_scale(scale_exp, c, seed):
    """The angle does not depend on the estimate's own level either (a network's output far below or above the
    truth, as early in training): the float32 loss of k·x̂ against x is the float64 angle of x̂ and x. Scaled by the
    truth's peak alone, an estimate at k = 1e-13 scored 0.069 rad for an angle of 0.0014 (its squared norm fell
    under the floor) and k = 1e15 overflowed."""
    rng = np.random.default_rng(seed)
    t = 0.1 + rng.random((1, c, 5, 6))
    r = t * (1 + 0.1 * rng.standard_normal(t.shape))
    k = 10.0 ** scale_exp
    ref = _ref_sam(r, t, 0.01)
    got = float(spectral_angle_loss(torch.from_numpy(r * k).float(), torch.from_numpy(t).float(), 0.01))
    assert got == pytest.approx(ref, rel=2e-3, abs=2e-4)


_ALL_TERMS = TrainConfig(relative_l1=1.0, ssim_loss=1.0, sam_loss=1.0, spectral_grad_loss=1.0, phase_loss=1.0,
                         relative_eps=0.01)


@PROPS
@given(c=st.integers(1, 4), h=st.integers(11, 14), m=st.integers(1, 3), value=st.sampled_from([0.0, 0.5, "rand"]),
       dtype=st.sampled_from([torch.float32, torch.float64]), seed=st.integers(0, 2**16))
def test_loss_gradient_is_finite_at_zero_images_and_equal_pixels(c, h, m, value, dtype, seed):
    """Every term on: the gradient at x̂ = x (zero, flat or random images) is finite and the loss is its floor (the
    SAM clamp's acos(1 − 1e-6) where any pixel is bright, else 0); a zero estimate of a bright truth has a finite
    gradient too."""
    g = torch.Generator().manual_seed(seed)
    truth = (torch.rand((2, c, h, h), generator=g, dtype=dtype) if value == "rand"
             else torch.full((2, c, h, h), float(value), dtype=dtype))
    for recon in (truth.clone(), torch.zeros_like(truth)):
        recon.requires_grad_(True)
        loss = system_loss(recon, truth, _ALL_TERMS, m)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(recon.grad).all()
    loss = system_loss(truth.clone(), truth, _ALL_TERMS, m)
    floor = math.acos(1 - 1e-6) if bool((truth.mean(dim=1) > 0.01).any()) else 0.0
    assert float(loss) == pytest.approx(floor, abs=1e-4 if dtype == torch.float32 else 1e-9)


@PROPS
@given(name=st.sampled_from(("l1",) + tuple(n for n in TERMS if n != "sam_loss")), c=st.integers(1, 4),
       m=st.integers(1, 3), seed=st.integers(0, 2**16))
def test_a_batch_items_gradient_is_its_own(name, c, m, seed):
    """Terms that average per item (L1, relative L1, SSIM, spectral gradient, CFA phase): the gradient on item 0
    does not change when item 1 changes (the SAM term pools its bright pixels over the batch instead)."""
    rng = np.random.default_rng(seed)
    t = torch.from_numpy(rng.random((2, c, 12, 13)))
    r = t + 0.1 * torch.from_numpy(rng.standard_normal(t.shape))
    cfg = TrainConfig() if name == "l1" else TrainConfig(**{name: 1.0})
    grads = []
    for other in (0.0, 1.0):
        rr, tt = r.clone(), t.clone()
        rr[1] += other * torch.from_numpy(rng.standard_normal(rr[1].shape))
        tt[1] = tt[1] * (1 - 0.5 * other)
        rr.requires_grad_(True)
        system_loss(rr, tt, cfg, m).backward()
        grads.append(rr.grad[0].clone())
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-14)


# ------------------------------------------------------------------------------------------------
# The learning-rate schedule and gradient clipping
# ------------------------------------------------------------------------------------------------
@PROPS
@given(total=st.integers(1, 400), warm=st.integers(0, 60), schedule=st.sampled_from(["constant", "cosine", "step"]),
       spe=st.integers(1, 50), step_epochs=st.integers(1, 5), gamma=st.floats(0.1, 1.0))
def test_lr_schedule_against_its_closed_form(total, warm, schedule, spe, step_epochs, gamma):
    """A function of the global step only (a resumed run at step k gets the uninterrupted run's rate): the warm-up
    climbs linearly (s + 1)/W to 1 at its last step; afterwards the schedule's closed form (cosine over the remaining
    steps ½(1 + cos(π (s − W)/(T − W))), non-increasing, its last step ½(1 + cos(π (T − 1 − W)/(T − W))) > 0; step
    γ^⌊⌊s/E⌋/k⌋), always in (0, 1]."""
    t = TrainConfig(lr_schedule=schedule, warmup_steps=warm, lr_step_epochs=step_epochs, lr_gamma=gamma)
    run = [lr_factor(t, s, total, spe) for s in range(total)]
    resumed = [lr_factor(t, s, total, spe) for s in range(total)[::-1]]
    assert run == resumed[::-1]
    for s, f in enumerate(run):
        if s < warm:
            ref = (s + 1) / warm
        elif schedule == "cosine":
            ref = 0.5 * (1 + math.cos(math.pi * (s - warm) / (total - warm)))
        elif schedule == "step":
            ref = gamma ** ((s // spe) // step_epochs)
        else:
            ref = 1.0
        assert f == pytest.approx(ref, rel=1e-12, abs=1e-15)
        assert 0 < f <= 1
    after = run[warm:]
    assert all(b <= a + 1e-15 for a, b in zip(after, after[1:]))  # monotone decay after the warm-up
    assert all(b > a for a, b in zip(run[:warm], run[1:warm]))  # a strictly rising warm-up
    if warm < total and schedule == "cosine":
        assert run[-1] == pytest.approx(0.5 * (1 + math.cos(math.pi * (total - 1 - warm) / (total - warm))), rel=1e-12)


@PROPS
@given(limit=st.floats(1e-3, 1e3), scales=st.lists(st.floats(1e-4, 1e4), min_size=1, max_size=4),
       seed=st.integers(0, 2**16))
def test_grad_clip_bounds_the_global_norm_and_keeps_the_direction(limit, scales, seed):
    """What the loop calls for ``train.grad_clip``: afterwards the global norm over every parameter is ≤ the limit
    (equal to it when it was above), each gradient a common positive multiple of the one before, frozen parameters
    (no gradient) left alone."""
    g = torch.Generator().manual_seed(seed)
    params = [torch.nn.Parameter(torch.zeros(3, 2)) for _ in scales] + [torch.nn.Parameter(torch.zeros(4))]
    for p, s in zip(params, scales):
        p.grad = s * torch.randn(p.shape, generator=g)
    before = [p.grad.clone() for p in params[:-1]]
    norm = math.sqrt(sum(float((x.double() ** 2).sum()) for x in before))
    torch.nn.utils.clip_grad_norm_(params, limit)
    after = [p.grad for p in params[:-1]]
    new_norm = math.sqrt(sum(float((x.double() ** 2).sum()) for x in after))
    assert new_norm <= limit * (1 + 1e-5)
    factor = min(1.0, limit / (norm + 1e-6))
    for a, b in zip(before, after):
        torch.testing.assert_close(b, a * factor, rtol=1e-5, atol=1e-12)
    assert params[-1].grad is None
