"""Data pipeline benchmark: prints one JSON object.

- ``loader_patches_per_s``: training patches (64×64×31, plus the margin given) served per second by
  a DataLoader with 2 worker processes (batch 16), after one warm-up batch; target ≥ 200.
- ``synth_s_per_scene``: seconds to generate one 256×256×31 synthetic scene (spectral library
  built beforehand; its one-off build time is reported separately).

Usage: python benchmarks/bench_data.py [--scenes 8] [--batches 40]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

from hsicam.data.datasets import PatchDataset, SceneDataset, list_scenes
from hsicam.data.pipeline import make_loader
from hsicam.data.synthetic import generate_dataset, generate_scene, spectral_library
from hsicam.spectral import Bands


def loader_rate(root: Path, bands: Bands, patch: int, margin: int, batches: int, workers: int, preload: bool) -> float:
    scenes = SceneDataset(list_scenes(root), bands, preload=preload)
    ds = PatchDataset(scenes, patch, margin, patches_per_epoch=16 * (batches + 1), seed=0)
    loader = make_loader(ds, batch_size=16, num_workers=workers, shuffle=True)
    it = iter(loader)
    next(it)  # warm-up: worker start-up
    t0 = time.perf_counter()
    n = 0
    for batch in it:
        n += batch.shape[0]
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--batches", type=int, default=40)
    args = ap.parse_args()
    torch.set_num_threads(1)
    bands = Bands.paper()
    t0 = time.perf_counter()
    lib = spectral_library(bands)
    library_s = time.perf_counter() - t0
    times = []
    for i in range(args.scenes):
        t0 = time.perf_counter()
        generate_scene(i, 123, 256, lib)
        times.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "syn"
        t0 = time.perf_counter()
        generate_dataset(root, n=args.scenes, size=256, seed=0, bands=bands, progress=False)
        write_s = (time.perf_counter() - t0) / args.scenes
        result = {
            "device": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
            "synth_s_per_scene": round(sum(times) / len(times), 4),
            "synth_s_per_scene_max": round(max(times), 4),
            "synth_s_per_scene_with_write": round(write_s, 4),
            "synth_library_build_s": round(library_s, 3),
            "synth_kinds_timed": args.scenes,
        }
        for margin in (0, 140):
            for preload in (True, False):
                key = f"loader_patches_per_s_64px_margin{margin}_{'preload' if preload else 'h5window'}"
                result[key] = round(loader_rate(root, bands, 64, margin, args.batches, 2, preload), 1)
        result["loader_workers"] = 2
        result["loader_batch"] = 16
        result["loader_target_patches_per_s"] = 200
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
