"""Property-based tests (hypothesis) of the data the training reads: the patch sampler and its relighting, the
synthetic scene generator and the memory arithmetic of cubes and scenes. Each invariant is checked against an
independent reference: the scene's own pixels (each encodes where it came from), numpy's Legendre basis, a binomial
bound, numpy's byte counts. Moved from engine/test_properties_training.py, whose loss, schedule and clipping
properties stay there."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsicam.data.cube import check_memory_budget
from hsicam.data.datasets import RELIGHT_ORDER, PatchDataset, SceneInfo, relight
from hsicam.errors import InputError
from property_settings import TRAINING_FEW as FEW
from property_settings import TRAINING_PROPS as PROPS

pytestmark = pytest.mark.usefixtures("one_torch_thread")


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
