"""Training datasets: scene listing, scene-level split, normalisation policy, patches with margin."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch

from hsicam.config import ConfigError, load_config
from hsicam.data import (
    PatchDataset,
    SceneDataset,
    build_datasets,
    list_scenes,
    make_loader,
    normalize_per_cube_max,
    split_scenes,
    write_cube_h5,
)
from hsicam.data.datasets import RELIGHT_ORDER, augment, relight, relighting_exponent
from hsicam.errors import InputError
from hsicam.spectral import Bands

PAPER = Bands.paper()


def make_scene(path: Path, seed: int, size: tuple[int, int] = (40, 48), bands: Bands = PAPER, scale: float = 3.0) -> np.ndarray:
    cube = (np.random.default_rng(seed).random((len(bands), *size)) * scale).astype(np.float32)
    write_cube_h5(path, cube, bands)
    return cube


@pytest.fixture
def folder(tmp_path):
    cubes = {f"s{i}.h5": make_scene(tmp_path / f"s{i}.h5", i) for i in range(5)}
    return tmp_path, cubes


def test_list_scenes_mixed_folder(tmp_path):
    make_scene(tmp_path / "a.h5", 0)
    np.save(tmp_path / "b.npy", np.ones((31, 4, 4), np.float32))
    (tmp_path / "sub").mkdir()
    scipy.io.savemat(tmp_path / "sub" / "c.mat", {"ref": np.ones((4, 4, 31))})
    cave = tmp_path / "cave" / "flowers_ms" / "flowers_ms"
    cave.mkdir(parents=True)
    for i in range(1, 32):
        (cave / f"flowers_ms_{i:02d}.png").write_bytes(b"")  # listing does not read the files
    (tmp_path / "e.hdr").write_text("ENVI\n")
    (tmp_path / "e.img").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / ".a.tmp.h5").write_bytes(b"")  # atomic-write leftover: hidden
    (tmp_path / "manifest.json").write_text("{}")
    found = [p.relative_to(tmp_path).as_posix() for p in list_scenes(tmp_path)]
    assert found == ["a.h5", "b.npy", "cave/flowers_ms", "e.hdr", "sub/c.mat"]


def test_list_scenes_errors(tmp_path):
    with pytest.raises(InputError, match="no hyperspectral scenes"):
        list_scenes(tmp_path)
    with pytest.raises(InputError, match="no such"):
        list_scenes(tmp_path / "nope")


def test_split_is_scene_level_and_deterministic(tmp_path):
    scenes = [tmp_path / f"s{i:02d}.h5" for i in range(20)]
    train, val = split_scenes(scenes, 0.25, seed=3)
    assert len(val) == 5 and len(train) == 15
    assert set(train).isdisjoint(val) and set(train) | set(val) == set(scenes)
    assert split_scenes(list(reversed(scenes)), 0.25, seed=3) == (train, val)  # order of listing irrelevant
    assert split_scenes(scenes, 0.25, seed=4)[1] != val
    assert split_scenes(scenes[:2], 0.01, seed=0)[1] != []  # at least one validation scene
    assert split_scenes(scenes, 0.0)[1] == []
    with pytest.raises(InputError):
        split_scenes(scenes, 1.0)


def test_a_validation_pool_keeps_the_validation_scenes_when_the_dataset_grows(tmp_path):
    scenes = [tmp_path / f"s{i:03d}.h5" for i in range(60)]
    train20, val20 = split_scenes(scenes[:20], 0.25, seed=3)
    train, val = split_scenes(list(reversed(scenes)), 0.25, seed=3, pool=20)
    assert val == val20  # the split of the first 20, whatever follows
    assert train == train20 + scenes[20:]  # every later scene trains
    assert split_scenes(scenes[:20], 0.25, seed=3, pool=20) == (train20, val20)
    assert split_scenes(scenes[:20], 0.25, seed=3, pool=50) == (train20, val20)  # a pool beyond n: all scenes


def test_the_config_split_uses_the_pool(tiny_config, tmp_path):
    from hsicam.data.pipeline import split_dataset
    from hsicam.errors import ConfigError

    for i in range(12):
        (tmp_path / f"s{i:02d}.npy").write_bytes(b"")  # listed by name only
    cfg = tiny_config(f"data.root={tmp_path}", "data.val_fraction=0.25", "data.val_pool=8")
    train, val = split_dataset(cfg.data, cfg.bands.to_bands())
    assert [p.name for p in val] == [p.name for p in split_scenes(sorted(tmp_path.iterdir())[:8], 0.25)[1]]
    assert len(val) == 2 and len(train) == 10
    with pytest.raises(ConfigError, match="val_pool"):
        tiny_config("data.val_pool=1")


def test_normalisation_policy():
    cube = np.array([[[1.0, 2.0]], [[4.0, 0.5]]], np.float32)
    out, peak = normalize_per_cube_max(cube)
    assert peak == 4.0
    np.testing.assert_allclose(out, cube / 4.0)
    with pytest.raises(InputError, match="all zeros"):
        normalize_per_cube_max(np.zeros((2, 2, 2), np.float32), source="black.h5")


@pytest.mark.parametrize("preload", [True, False])
def test_scene_dataset_normalises_on_target_bands(folder, preload):
    root, cubes = folder
    ds = SceneDataset(list_scenes(root), PAPER, preload=preload, cache_size=2)
    assert len(ds) == 5
    for i, name in enumerate(sorted(cubes)):
        t = ds[i]
        assert t.dtype == torch.float32 and t.shape == (31, 40, 48)
        np.testing.assert_allclose(t.numpy(), cubes[name] / cubes[name].max(), rtol=1e-6)
        assert float(t.max()) == 1.0
        assert ds.info(i).peak == pytest.approx(float(cubes[name].max()))


def test_scene_dataset_resamples_and_refuses_extrapolation(tmp_path):
    src = Bands.uniform(400, 700, 10)
    lam = src.centers_nm
    cube = np.broadcast_to((1.0 + (lam - 400) / 300.0)[:, None, None], (31, 20, 20)).astype(np.float32)
    write_cube_h5(tmp_path / "lin.h5", cube, src)
    target = Bands.uniform(420, 700, 5)
    ds = SceneDataset([tmp_path / "lin.h5"], target)
    expected = (1.0 + (target.centers_nm - 400) / 300.0) / 2.0  # normalised by the max (700 nm → 2)
    np.testing.assert_allclose(ds[0][:, 3, 4].numpy(), expected, rtol=1e-6)
    with pytest.raises(InputError, match=r"lin\.h5.*420-720 nm"):
        SceneDataset([tmp_path / "lin.h5"], PAPER)[0]


def test_patches_have_margin_and_come_from_the_scene(folder):
    root, cubes = folder
    scenes = SceneDataset(list_scenes(root), PAPER)
    patch, margin = 8, 6
    ds = PatchDataset(scenes, patch, margin, patches_per_epoch=12, flips=False, rot90=False, seed=1)
    names = sorted(cubes)
    for k in range(len(ds)):
        p = ds[k].numpy()
        assert p.shape == (31, patch + margin, patch + margin) and p.dtype == np.float32
        assert 0.0 <= p.min() and p.max() <= 1.0
        # the patch is a crop of one normalised scene: find it by brute force
        found = False
        for name in names:
            scene = cubes[name] / cubes[name].max()
            hits = np.argwhere(np.isclose(scene[0], p[0, 0, 0], rtol=0, atol=1e-7))
            for y, x in hits:
                crop = scene[:, y:y + 14, x:x + 14]
                if crop.shape == p.shape and np.allclose(crop, p, atol=1e-6):
                    found = True
        assert found


def test_patches_deterministic_per_epoch_and_fixed_mode(folder):
    root, _ = folder
    scenes = SceneDataset(list_scenes(root), PAPER)
    ds = PatchDataset(scenes, 8, 0, patches_per_epoch=4, seed=7)
    first = [ds[k] for k in range(4)]
    assert all(torch.equal(a, ds[k]) for k, a in enumerate(first))
    ds.set_epoch(1)
    assert not all(torch.equal(a, ds[k]) for k, a in enumerate(first))
    other = PatchDataset(SceneDataset(list_scenes(root), PAPER, preload=True), 8, 0, patches_per_epoch=4, seed=7)
    assert all(torch.equal(a, other[k]) for k, a in enumerate(first))  # h5 windows == preloaded cubes
    val = PatchDataset(scenes, 8, 0, patches_per_epoch=4, seed=7, fixed=True, flips=False, rot90=False)
    a = [val[k] for k in range(4)]
    val.set_epoch(5)
    assert all(torch.equal(x, val[k]) for k, x in enumerate(a))
    with pytest.raises(IndexError):
        ds[4]


def test_augment_is_the_dihedral_group():
    x = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    t = torch.from_numpy(x)
    seen = set()
    for turns in range(4):
        for flip in (False, True):
            ours = np.ascontiguousarray(augment(x, turns, flip))
            ref = torch.rot90(t, turns, dims=(1, 2))
            ref = torch.flip(ref, dims=(2,)) if flip else ref
            np.testing.assert_array_equal(ours, ref.numpy())
            seen.add(ours.tobytes())
    assert len(seen) == 8


def test_augmentations_used_when_enabled(folder):
    root, _ = folder
    scenes = SceneDataset(list_scenes(root), PAPER)
    plain = PatchDataset(scenes, 10, 0, patches_per_epoch=32, flips=False, rot90=False, seed=2)
    aug = PatchDataset(scenes, 10, 0, patches_per_epoch=32, flips=True, rot90=True, seed=2)
    differ = sum(not torch.equal(plain[k], aug[k]) for k in range(32))
    assert differ > 16  # same positions, transformed in most of the 7/8 non-identity cases


def test_the_relighting_exponent_is_the_legendre_series():
    """s_c = exp(Σ a_k P_k(x_c)) with P1 = x, P2 = (3x² − 1)/2, P3 = (5x³ − 3x)/2 written out."""
    x = np.linspace(-1, 1, 31)
    a = np.array([0.4, -0.3, 0.2])
    want = np.exp(a[0] * x + a[1] * (3 * x**2 - 1) / 2 + a[2] * (5 * x**3 - 3 * x) / 2)
    np.testing.assert_allclose(np.exp(relighting_exponent(31, a)), want, rtol=1e-12)
    np.testing.assert_array_equal(relighting_exponent(31, np.zeros(3)), np.zeros(31))
    assert relighting_exponent(1, a).shape == (1,)


def test_relight_multiplies_every_spectrum_by_one_factor_and_keeps_the_peak():
    rng = np.random.default_rng(0)
    patch = rng.random((31, 6, 7)).astype(np.float32)
    a = np.array([0.5, 0.2, -0.1])
    out = relight(patch, a)
    assert out.dtype == np.float32 and out.shape == patch.shape
    assert np.isclose(out.max(), patch.max(), rtol=1e-6)
    ratio = out / patch  # the same spectral factor at every pixel, up to one exposure
    np.testing.assert_allclose(ratio, ratio[:, :1, :1] * np.ones_like(ratio), rtol=1e-5)
    s = np.exp(relighting_exponent(31, a))
    np.testing.assert_allclose(ratio[:, 0, 0] / ratio[0, 0, 0], s / s[0], rtol=1e-5)
    np.testing.assert_array_equal(relight(np.zeros_like(patch), a), np.zeros_like(patch))  # black stays black
    steep = relight(patch, np.array([800.0, 0.0, 0.0]))  # exp(±800) overflows float64: computed in the exponent
    assert np.isfinite(steep).all() and np.isclose(steep.max(), patch.max(), rtol=1e-6)
    assert steep[-1].max() == steep.max() and steep[0].max() == 0.0  # all the light in the last band


def test_relit_patches_keep_their_geometry_and_are_deterministic(folder):
    """With relighting on, item k is the plain item k (same scene, place and dihedral turn) under a
    spectral factor in about relight_prob of the items; the same item twice is the same patch;
    relight_prob 0 is the plain dataset, bit for bit."""
    root, _ = folder
    scenes = SceneDataset(list_scenes(root), PAPER)
    plain = PatchDataset(scenes, 10, 2, patches_per_epoch=64, seed=3)
    lit = PatchDataset(scenes, 10, 2, patches_per_epoch=64, seed=3, relight_sigma=0.4, relight_prob=0.5)
    never = PatchDataset(scenes, 10, 2, patches_per_epoch=64, seed=3, relight_sigma=0.4, relight_prob=0.0)
    relit = 0
    for k in range(64):
        p, q = plain[k].numpy().astype(np.float64), lit[k].numpy().astype(np.float64)
        np.testing.assert_array_equal(never[k].numpy(), p)
        torch.testing.assert_close(lit[k], torch.from_numpy(q.astype(np.float32)), rtol=0, atol=0)
        ratio = q / p
        np.testing.assert_allclose(ratio, ratio[:, :1, :1] * np.ones_like(ratio), rtol=1e-4)  # one factor per band
        assert np.isclose(q.max(), p.max(), rtol=1e-6)
        relit += not np.allclose(ratio, 1.0, rtol=1e-6)
    assert 20 <= relit <= 44  # Binomial(64, 0.5): 32 ± 12
    always = PatchDataset(scenes, 10, 2, patches_per_epoch=64, seed=3, relight_sigma=0.4, relight_prob=1.0)
    assert all(not torch.equal(always[k], plain[k]) for k in range(64))
    assert RELIGHT_ORDER == 3
    with pytest.raises(InputError, match="relight"):
        PatchDataset(scenes, 10, 2, relight_sigma=-0.1)


def test_only_training_patches_are_relit(folder):
    root, _ = folder
    cfg = load_config(overrides=[f"data.root={root}", "data.patch_px=16", "data.val_fraction=0.2",
                                 "data.patches_per_epoch=10", "data.val_patches=3", "data.augment_relight=0.5",
                                 "data.augment_relight_prob=0.7"])
    train, val = build_datasets(cfg.data, cfg.bands.to_bands(), margin_px=4)
    assert (train.relight_sigma, train.relight_prob) == (0.5, 0.7) and val.relight_sigma == 0.0
    assert load_config().data.augment_relight == 0.0  # off unless a preset or --set asks


def test_scene_smaller_than_patch_plus_margin(folder):
    root, _ = folder
    with pytest.raises(InputError, match=r"40x48 px.*30 px.*margin of 12 px"):
        PatchDataset(SceneDataset(list_scenes(root), PAPER), 30, 12)


def test_loader_with_two_workers(folder):
    root, _ = folder
    ds = PatchDataset(SceneDataset(list_scenes(root), PAPER), 8, 2, patches_per_epoch=16, seed=0)
    first = ds[0].clone()  # the parent opens HDF5 handles before the workers fork
    batches = list(make_loader(ds, batch_size=8, num_workers=2, shuffle=False))
    np.testing.assert_array_equal(batches[0][0].numpy(), first.numpy())
    assert len(batches) == 2 and batches[0].shape == (8, 31, 10, 10)
    np.testing.assert_array_equal(batches[1][3].numpy(), ds[11].numpy())  # worker-independent


def test_build_datasets_from_config_folder(folder):
    root, _ = folder
    cfg = load_config(overrides=[f"data.root={root}", "data.patch_px=16", "data.val_fraction=0.2",
                                 "data.patches_per_epoch=10", "data.val_patches=3"])
    train, val = build_datasets(cfg.data, cfg.bands.to_bands(), margin_px=4)
    assert len(train) == 10 and len(val) == 3
    assert train[0].shape == (31, 20, 20)
    assert set(train.scenes.paths).isdisjoint(val.scenes.paths)
    assert len(val.scenes) == 1 and len(train.scenes) == 4


def test_npy_cubes_take_the_band_grid_of_the_config(tmp_path):
    """A .npy cube carries no wavelengths: with ``data.npy_bands`` the training and validation
    scenes are those of the same cube written as our HDF5 with that grid (resampled, not relabelled);
    without it 400-700 nm is assumed, which does not cover 420-720 nm: one error naming the key;
    a grid of the wrong length is one error too."""
    fine = Bands.uniform(410, 730, 20)  # 17 bands around the camera's 420-720 nm
    rng = np.random.default_rng(0)
    for i in range(2):
        cube = rng.random((len(fine), 30, 34)).astype(np.float32)
        (tmp_path / "npy").mkdir(exist_ok=True)
        (tmp_path / "h5").mkdir(exist_ok=True)
        np.save(tmp_path / "npy" / f"s{i}.npy", cube)
        write_cube_h5(tmp_path / "h5" / f"s{i}.h5", cube, fine)
    common = ["data.patch_px=12", "data.val_fraction=0.5", "data.patches_per_epoch=4", "data.val_patches=2"]
    grid = "data.npy_bands={start_nm: 410, stop_nm: 730, step_nm: 20}"
    cfg_npy = load_config(overrides=[f"data.root={tmp_path / 'npy'}", grid, *common])
    cfg_h5 = load_config(overrides=[f"data.root={tmp_path / 'h5'}", *common])
    assert cfg_npy.data.npy_bands.to_bands() == fine and cfg_h5.data.npy_bands is None
    bands = cfg_npy.bands.to_bands()
    got, want = (build_datasets(c.data, bands, margin_px=2) for c in (cfg_npy, cfg_h5))
    for a, b in zip(got, want):
        for k in range(len(a)):
            torch.testing.assert_close(a[k], b[k])
    plain = load_config(overrides=[f"data.root={tmp_path / 'npy'}", *common])
    with pytest.raises(InputError, match="data.npy_bands"):  # read at construction (preloaded) or first use
        build_datasets(plain.data, bands, margin_px=2)[0][0]
    short = load_config(overrides=[f"data.root={tmp_path / 'npy'}", "data.npy_bands={start_nm: 420, stop_nm: 720, step_nm: 10}", *common])
    with pytest.raises(InputError, match="17 bands .* has 31"):
        build_datasets(short.data, bands, margin_px=2)[0][0]
    with pytest.raises(ConfigError, match=r"data\.npy_bands\.stop_nm"):  # names its own key, not `bands`
        load_config(overrides=["data.npy_bands={start_nm: 700, stop_nm: 420, step_nm: 10}"])


@pytest.mark.parametrize("override", ["data.val_fraction=1.0", "data.patch_px=0", "data.synthetic_size=8",
                                      "data.num_workers=-1", "data.preload_max_mb=0", "data.synthetic_n=yes",
                                      "data.augment_relight=-0.1", "data.augment_relight_prob=1.5"])
def test_data_config_validation(override):
    with pytest.raises(ConfigError, match="data"):
        load_config(overrides=[override])


def test_data_config_defaults():
    d = load_config().data
    assert d.root is None and d.synthetic_size == 256 and 0 < d.val_fraction < 1


@pytest.mark.filterwarnings("ignore:This DataLoader will create:UserWarning")  # torch's own, above the CPUs
def test_a_worker_count_beyond_the_machine_is_capped_once_with_a_warning(monkeypatch, caplog):
    """``data.num_workers=1000000000`` went to the DataLoader as given (a process per worker: a fork
    bomb on the first epoch); it is capped at twice the CPUs this process may use (at least 4), said once."""
    import logging

    import hsicam.data.pipeline as pipeline

    monkeypatch.setattr(pipeline.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    monkeypatch.setattr(pipeline, "_CAPPED_SAID", set())
    assert pipeline.max_workers() == 6
    monkeypatch.setattr(pipeline.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert pipeline.max_workers() == 4  # the default of 2 is never capped
    monkeypatch.setattr(pipeline.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    data = torch.utils.data.TensorDataset(torch.arange(8.0))
    with caplog.at_level(logging.WARNING, logger="hsicam.data.pipeline"):
        loaders = [pipeline.make_loader(data, 2, num_workers=10**9, shuffle=False) for _ in range(2)]
        kept = pipeline.make_loader(data, 2, num_workers=6, shuffle=False)
    assert [loader.num_workers for loader in loaders] == [6, 6] and kept.num_workers == 6
    said = [r.getMessage() for r in caplog.records if "num_workers" in r.getMessage()]
    assert said == ["data.num_workers=1000000000 is more processes than this machine's CPUs can keep busy; using 6"]


# --------------------------------------------------------------------------------------------
# Guards found by mutation testing (data/datasets.py): brute force over scenes and positions
# --------------------------------------------------------------------------------------------
def _scene_files(tmp_path, sizes, seed=0):
    from hsicam.data import write_cube_h5

    bands = Bands.uniform(420, 720, 30)
    rng = np.random.default_rng(seed)
    paths, cubes = [], []
    for i, (h, w) in enumerate(sizes):
        cube = (rng.random((len(bands), h, w)) + 0.1).astype(np.float32)
        write_cube_h5(tmp_path / f"s{i}.h5", cube, bands)
        paths.append(tmp_path / f"s{i}.h5")
        cubes.append(cube / cube.max())
    return paths, cubes, bands


@pytest.mark.parametrize("n, fraction", [(1, 0.9), (2, 0.9), (3, 0.95), (10, 0.99)])
def test_a_split_always_keeps_a_training_scene(tmp_path, n, fraction):
    """round(fraction · n) may be all n scenes (0.9 of 2 is 2): the split still leaves one to train on, and the two
    sets are a partition of the scenes."""
    from hsicam.data import split_scenes

    scenes = [tmp_path / f"s{i}.h5" for i in range(n)]
    train, val = split_scenes(scenes, fraction, seed=3)
    assert len(train) >= 1 and sorted(train + val) == sorted(scenes) and not set(train) & set(val)
    assert len(val) >= (1 if n >= 2 else 0)


def test_patches_reach_every_position_and_every_scene(tmp_path):
    """Patch positions are uniform over all placements, the last row and column included, and scenes uniform over
    all scenes: with scenes one pixel larger than a patch each patch is found by brute force in its scene, and all
    (scene, y, x) of the 3 × 2 × 2 come up among 96 patches."""
    from hsicam.data import PatchDataset, SceneDataset

    paths, cubes, bands = _scene_files(tmp_path, [(9, 9)] * 3)
    ds = PatchDataset(SceneDataset(paths, bands), 8, 0, patches_per_epoch=96, flips=False, rot90=False, seed=5)
    seen = set()
    for k in range(len(ds)):
        p = ds[k].numpy()
        hits = [(i, y, x) for i, c in enumerate(cubes) for y in range(2) for x in range(2)
                if np.allclose(c[:, y:y + 8, x:x + 8], p, rtol=0, atol=1e-6)]
        assert len(hits) == 1
        assert ds.scene_of(k) == paths[hits[0][0]]
        seen.add(hits[0])
    assert seen == {(i, y, x) for i in range(3) for y in range(2) for x in range(2)}


def test_a_window_one_pixel_past_the_edge_of_a_windowed_scene_is_refused(tmp_path):
    """A window read straight from an hsicam HDF5 file (no full load) that reaches one pixel past the right or
    bottom edge is one clear error; h5py would return it a pixel narrower without a word. Windows that end on the
    edge are the normalised crop of the cube."""
    from hsicam.data import SceneDataset

    paths, cubes, bands = _scene_files(tmp_path, [(12, 10)])
    ds = SceneDataset(paths, bands)
    np.testing.assert_allclose(ds.window(0, 4, 2, 8, 8), cubes[0][:, 4:12, 2:10], rtol=1e-6)
    for y, x in ((4, 3), (5, 2)):
        with pytest.raises(InputError, match=r"window 8x8 at \(%d, %d\) is outside the cube" % (y, x)):
            ds.window(0, y, x, 8, 8)


def test_scene_and_patch_dataset_refusals(tmp_path):
    from hsicam.data.datasets import PatchDataset, SceneDataset

    with pytest.raises(InputError) as exc:
        SceneDataset([], Bands.paper())
    assert str(exc.value) == "SceneDataset: no scenes"
    for kwargs, text in (({"patch_px": 0}, "PatchDataset: need patch_px >= 1 and margin_px >= 0, got 0, 0"),
                         ({"patch_px": 8, "patches_per_epoch": 0}, "PatchDataset: patches_per_epoch must be >= 1, got 0")):
        with pytest.raises(InputError) as exc:
            PatchDataset(None, **kwargs)
        assert str(exc.value) == text


def test_a_file_on_the_camera_centres_with_narrower_bands_is_the_same_truth_read_whole_or_by_windows(tmp_path):
    """(A real-format dataset hunt, session 72.) An hsicam HDF5 file with the camera's band centres but 10 nm bands
    under 50 nm camera bands is integrated by a whole read; read window by window (no preload: the default above
    data.preload_max_mb) it was taken as stored, other ground truth (validation PSNR 2 dB apart on one dataset)."""
    from hsicam.data import write_cube_h5
    from hsicam.data.datasets import probe_hsicam

    camera = Bands.uniform(420, 720, 50)
    narrow = Bands(camera.centers_nm, np.full(len(camera), 10.0))
    cube = np.random.default_rng(0).random((len(camera), 32, 32)).astype(np.float32)
    path = write_cube_h5(tmp_path / "narrow.h5", cube, narrow)
    assert probe_hsicam(path, camera) is None  # not read by windows: its bands are integrated
    whole = SceneDataset([path], camera, preload=True).cube(0)
    windowed = SceneDataset([path], camera, preload=False).window(0, 3, 5, 20, 20)
    np.testing.assert_array_equal(windowed, whole[:, 3:23, 5:25])
    assert not np.allclose(whole, cube / cube.max(), atol=1e-3)  # the integration changed the values
    same = write_cube_h5(tmp_path / "same.h5", cube, camera)  # the camera's own bands: still read by windows
    assert probe_hsicam(same, camera) is not None
    np.testing.assert_array_equal(SceneDataset([same], camera, preload=False).window(0, 3, 5, 20, 20),
                                  SceneDataset([same], camera, preload=True).cube(0)[:, 3:23, 5:25])
