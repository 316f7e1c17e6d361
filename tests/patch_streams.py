"""The training patch stream as documented (docs/training.md, "Determinism"), for tests of how seeds select it."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

NPY_BANDS = "data.npy_bands={start_nm: 420, stop_nm: 720, step_nm: 50}"  # the tiny preset's 7 bands


def write_scenes(folder: Path, n: int = 6) -> list[np.ndarray]:
    """``n`` random 7-band 40×44 scenes as folder/scene_{i}.npy; returns the cubes."""
    rng = np.random.default_rng(0)
    cubes = [rng.uniform(0.1, 1.0, (7, 40, 44)).astype(np.float32) for _ in range(n)]
    for i, cube in enumerate(cubes):
        np.save(folder / f"scene_{i}.npy", cube)
    return cubes


def stream_reference(cubes: list[np.ndarray], size: int, key: list[int]) -> np.ndarray:
    """The patch that the documented draw gives: from numpy.random.default_rng(key) a scene (uniform), a
    position, 90° turns and a left-right flip, cut from the scene over its peak."""
    rng = np.random.default_rng(key)
    cube = cubes[int(rng.integers(len(cubes)))]
    y, x = int(rng.integers(cube.shape[1] - size + 1)), int(rng.integers(cube.shape[2] - size + 1))
    patch = np.rot90(cube[:, y:y + size, x:x + size] / cube.max(), k=int(rng.integers(4)), axes=(1, 2))
    return patch[:, :, ::-1] if bool(rng.integers(2)) else patch


def assert_seeded_streams(datasets: Callable[[int], tuple], cubes: list[np.ndarray], split_seed: int,
                          what: str) -> None:
    """``datasets(seed)`` → (train, val) for seeds 0, 1 and 7: patch k of epoch e is the documented draw from
    (split_seed, e, k) for seed 0 (every run before the seed mixed in) and (split_seed, e, k, s) for s ≠ 0, three
    seeds give three streams, and the validation patches do not depend on the seed."""
    streams, vals = {}, {}
    for seed in (0, 1, 7):
        train, val = datasets(seed)
        mine = [cubes[int(p.name[6:-4])] for p in train.scenes.paths]  # the training scenes, in the dataset's order
        for epoch in (0, 2):
            train.set_epoch(epoch)
            got = [train[k].numpy() for k in range(6)]
            streams[seed, epoch] = got
            for k, patch in enumerate(got):
                key = [split_seed, epoch, k] + ([seed] if seed else [])
                np.testing.assert_allclose(patch, stream_reference(mine, train.size_px, key), rtol=1e-6,
                                           err_msg=f"{what} {seed}, epoch {epoch}, patch {k}")
        vals[seed] = [val[k].numpy() for k in range(len(val))]
    for epoch in (0, 2):  # three seeds, three streams
        for a, b in ((0, 1), (0, 7), (1, 7)):
            assert not all(np.array_equal(p, q) for p, q in zip(streams[a, epoch], streams[b, epoch])), (a, b, epoch)
    assert all(np.array_equal(p, q) for s in (1, 7) for p, q in zip(vals[0], vals[s]))
