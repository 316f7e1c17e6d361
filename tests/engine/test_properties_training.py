"""Property-based tests (hypothesis) of the training side's pure functions: the loss terms of
:func:`hsicam.engine.tasks.system_loss`, the learning-rate schedule, gradient clipping, the patch sampler and its
relighting, the synthetic scene generator and the memory arithmetic. Each invariant is checked against an
independent reference: brute-force numpy loops (angles, per-phase means, band differences), scipy's box filter,
scikit-image's SSIM, the closed-form schedule, the scene's own pixels, numpy's byte counts."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from scipy.ndimage import uniform_filter
from skimage.metrics import structural_similarity

from hsicam.config import TrainConfig
from hsicam.data.cube import check_memory_budget
from hsicam.data.datasets import RELIGHT_ORDER, PatchDataset, SceneInfo, relight
from hsicam.engine.loop import lr_factor
from hsicam.engine.tasks import spectral_angle_loss, system_loss
from hsicam.errors import InputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PROPS = settings(max_examples=30, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
FEW = settings(PROPS, max_examples=10)
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


# ------------------------------------------------------------------------------------------------
# The patch sampler and its relighting
# ------------------------------------------------------------------------------------------------
class _Scenes:
    """A stand-in SceneDataset: scene i's pixel (c, y, x) holds 1e6·i + 1e4·c + 100·y + x, so a patch says where
    it came from."""

    def __init__(self, sizes: list[tuple[int, int]], c: int = 2) -> None:
        self.sizes, self.c = sizes, c
        self.paths = [Path(f"scene_{i}.h5") for i in range(len(sizes))]
        self.cubes = [(1e6 * i + 1e4 * np.arange(c)[:, None, None] + 100 * np.arange(h)[None, :, None]
                       + np.arange(w)[None, None, :]) for i, (h, w) in enumerate(sizes)]

    def __len__(self) -> int:
        return len(self.sizes)

    def info(self, i: int) -> SceneInfo:
        return SceneInfo(self.paths[i], *self.sizes[i], 1.0)

    def window(self, i: int, y: int, x: int, h: int, w: int) -> np.ndarray:
        assert 0 <= y and y + h <= self.sizes[i][0] and 0 <= x and x + w <= self.sizes[i][1]
        return self.cubes[i][:, y:y + h, x:x + w].copy()


def _dihedral(cube: np.ndarray) -> list[np.ndarray]:
    return [f(np.rot90(cube, k, axes=(1, 2))) for k in range(4) for f in (lambda a: a, lambda a: a[:, :, ::-1])]


@FEW
@given(sizes=st.lists(st.tuples(st.integers(5, 30), st.integers(5, 30)), min_size=1, max_size=3),
       patch=st.integers(1, 4), margin=st.integers(0, 3), seed=st.integers(0, 2**16), flips=st.booleans())
def test_patches_are_windows_of_their_scene_and_deterministic(sizes, patch, margin, seed, flips):
    """Each patch (patch_px + margin) is a whole window inside the scene it names, under one of the dihedral
    transforms allowed; the same (seed, epoch, k) gives the same bytes in a new dataset; another epoch draws
    other patches (a training set), while a fixed (validation) set ignores the epoch."""
    scenes = _Scenes(sizes)
    s = patch + margin
    if min(min(sz) for sz in sizes) < s:
        with pytest.raises(InputError):
            PatchDataset(scenes, patch, margin, patches_per_epoch=4, seed=seed)
        return
    ds = PatchDataset(scenes, patch, margin, patches_per_epoch=24, flips=flips, rot90=flips, seed=seed)
    again = PatchDataset(scenes, patch, margin, patches_per_epoch=24, flips=flips, rot90=flips, seed=seed)
    epoch0 = [ds[k].numpy() for k in range(len(ds))]
    for k, p in enumerate(epoch0):
        assert p.shape == (2, s, s) and p.dtype == np.float32
        i = int(round(float(p.min()))) // 1_000_000  # the scene index encoded in the pixels
        assert scenes.paths[i] == ds.scene_of(k)
        y0, x0 = (int(round(v)) for v in divmod(float(p.min()) - 1e6 * i, 100))
        window = scenes.cubes[i][:, y0:y0 + s, x0:x0 + s].astype(np.float32)
        allowed = _dihedral(window) if flips else [window]
        assert any(a.shape == p.shape and np.array_equal(a, p) for a in allowed)
        assert np.array_equal(again[k].numpy(), p)
    ds.set_epoch(1)
    epoch1 = [ds[k].numpy() for k in range(len(ds))]
    total_positions = sum((h - s + 1) * (w - s + 1) for h, w in sizes)
    if total_positions > 1:  # 24 draws agreeing by chance: ≤ (1/2)^24
        assert any(not np.array_equal(a, b) for a, b in zip(epoch0, epoch1))
    fixed = PatchDataset(scenes, patch, margin, patches_per_epoch=5, seed=seed, fixed=True)
    first = [fixed[k].numpy() for k in range(5)]
    fixed.set_epoch(7)
    assert all(np.array_equal(fixed[k].numpy(), a) for k, a in enumerate(first))


@PROPS
@given(c=st.integers(1, 12), sigma=st.floats(0.0, 5.0), seed=st.integers(0, 2**16))
def test_relight_is_one_smooth_positive_spectral_factor_keeping_the_peak(c, sigma, seed):
    """relight(x) = x · s_c · κ with s = exp(Σ_k a_k P_k(band index on [−1, 1])) (Legendre, numpy's legendre
    module as the reference), the same at every pixel; κ > 0 keeps the patch's peak; values stay in [0, peak]."""
    rng = np.random.default_rng(seed)
    patch = rng.random((c, 6, 7)).astype(np.float32)
    coeffs = rng.normal(0.0, sigma, RELIGHT_ORDER)
    out = relight(patch, coeffs)
    assert out.dtype == np.float32 and out.shape == patch.shape
    x = np.linspace(-1, 1, c) if c > 1 else np.zeros(1)
    log_s = sum(a * np.polynomial.Legendre.basis(k + 1)(x) for k, a in enumerate(coeffs))
    ratio = out.astype(np.float64) / patch
    expected = np.exp(log_s - log_s.max())
    kappa = ratio[:, 0, 0] / expected
    assert np.all(kappa > 0) and np.ptp(kappa) <= 1e-5 * kappa.max()
    np.testing.assert_allclose(ratio, np.broadcast_to((kappa.mean() * expected)[:, None, None], ratio.shape),
                               rtol=1e-5, atol=0)
    assert float(out.max()) == pytest.approx(float(patch.max()), rel=1e-6)
    assert out.min() >= 0 and out.max() <= patch.max() * (1 + 1e-6)


@pytest.mark.parametrize("prob", [0.0, 0.3, 1.0])
def test_relight_is_applied_with_its_probability(prob):
    """Over 400 patches, the share relit is the binomial p within 5 standard deviations (0 and 1 exactly)."""
    scenes = _Scenes([(12, 12)], c=4)
    plain = PatchDataset(scenes, 4, 0, patches_per_epoch=400, seed=3)
    lit = PatchDataset(scenes, 4, 0, patches_per_epoch=400, seed=3, relight_sigma=0.5, relight_prob=prob)
    n = sum(not np.array_equal(plain[k].numpy(), lit[k].numpy()) for k in range(400))
    if prob in (0.0, 1.0):
        assert n == 400 * prob
    else:
        assert abs(n - 400 * prob) <= 5 * math.sqrt(400 * prob * (1 - prob))


# ------------------------------------------------------------------------------------------------
# The synthetic generator
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def library():
    from hsicam.data.spectral_sources import spectral_library
    from hsicam.spectral import Bands

    return spectral_library(Bands.uniform(420, 720, 50))


@settings(FEW, max_examples=8)
@given(index=st.integers(0, 40), seed=st.integers(0, 2**31 - 1), size=st.integers(16, 27))
def test_generated_scenes_are_in_range_and_a_function_of_their_seed(library, index, seed, size):
    """generate_scene / unseen_layout_scene at any size from the minimum (16 px, odd ones too): float32 (C, size,
    size), finite, in [0, 1] with maximum exactly 1; the same (index, seed) gives the same bytes, another seed
    another scene."""
    from hsicam.data.synthetic import generate_scene, unseen_layout_scene

    for make in (generate_scene, unseen_layout_scene):
        cube, _ = make(index, seed, size, library)
        assert cube.dtype == np.float32 and cube.shape == (len(library.illuminants[0]), size, size)
        assert np.isfinite(cube).all() and cube.min() >= 0 and cube.max() == 1.0
        assert make(index, seed, size, library)[0].tobytes() == cube.tobytes()
        assert make(index, seed + 1, size, library)[0].tobytes() != cube.tobytes()


# ------------------------------------------------------------------------------------------------
# Memory arithmetic
# ------------------------------------------------------------------------------------------------
@PROPS
@given(shape=st.lists(st.integers(0, 9), min_size=1, max_size=4),
       dtype=st.sampled_from(["uint8", "uint16", "float32", "float64", ">f4", "int32"]), budget_kib=st.integers(1, 64))
def test_cube_memory_estimate_counts_the_stored_array_and_its_float32_copy(shape, dtype, budget_kib):
    """check_memory_budget's estimate is the bytes numpy allocates for the array as stored plus its float32 copy;
    it refuses exactly the shapes over the budget."""
    a = np.zeros(shape, dtype=dtype)
    need = a.nbytes + a.astype(np.float32).nbytes
    budget_mb = budget_kib / 1024
    if need > budget_kib * 1024:
        with pytest.raises(InputError, match="over the memory budget"):
            check_memory_budget("x", shape, dtype, budget_mb=budget_mb)
    else:
        assert check_memory_budget("x", shape, dtype, budget_mb=budget_mb) == need


@PROPS
@given(size=st.integers(1, 64), bands=st.integers(1, 40), budget_kib=st.integers(1, 512))
def test_scene_memory_check_refuses_exactly_the_cubes_over_the_budget(size, bands, budget_kib):
    """A scene's float32 cube (numpy's bytes) over the budget is refused, naming the largest size that fits (by
    search); the generation's estimate is SCENE_MEMORY_FACTOR cubes."""
    from hsicam.data.synthetic import SCENE_MEMORY_FACTOR, check_scene_memory, scene_memory_bytes

    cube = np.zeros((bands, size, size), np.float32).nbytes
    assert scene_memory_bytes(size, bands) == SCENE_MEMORY_FACTOR * cube
    budget = budget_kib * 1024
    if cube <= budget:
        check_scene_memory(size, bands, budget_mb=budget_kib / 1024)
        return
    largest = max(s for s in range(0, size) if np.zeros((bands, s, s), np.float32).nbytes <= budget)
    with pytest.raises(InputError, match=f"give data.synthetic_size {largest} or less"):
        check_scene_memory(size, bands, budget_mb=budget_kib / 1024)
