"""Data pipeline benchmark: prints one JSON object.

- ``loader_patches_per_s``: training patches (64×64×31, plus the margin given) served per second by
  a DataLoader with 2 worker processes (batch 16), after one warm-up batch; target ≥ 200.
- ``synth_s_per_scene``: seconds to generate one 256×256×31 synthetic training scene (spectral
  library built beforehand; its one-off build time is reported separately), also per scene kind
  and for held-out scenes.
- ``demo_dataset_*``: the demo's data (quick preset: 64 training scenes of 256² and the 8-scene
  held-out set, default held-out sources) generated into a temporary cache: seconds and bytes.

Usage: python benchmarks/bench_data.py [--scenes 10] [--batches 40] [--demo-n 64]
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
from hsicam.data.synthetic import (
    DEFAULT_HOLDOUT,
    HELDOUT_N,
    SCHEDULE,
    generate_dataset,
    generate_scene,
    heldout_dataset,
    spectral_library,
    synthetic_dataset,
)
from hsicam.spectral import Bands
from timing import positive_int


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
    ap.add_argument("--scenes", type=positive_int, default=len(SCHEDULE))
    ap.add_argument("--batches", type=positive_int, default=40)
    ap.add_argument("--demo-n", type=int, default=64, help="training scenes of the demo's dataset (0: skip)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    bands = Bands.paper()
    t0 = time.perf_counter()
    spectral_library(bands)
    library_s = time.perf_counter() - t0
    train = spectral_library(bands, DEFAULT_HOLDOUT, "train")
    held = spectral_library(bands, DEFAULT_HOLDOUT, "heldout")
    times, held_times, by_kind = [], [], {}
    for i in range(args.scenes):
        t0 = time.perf_counter()
        _, info = generate_scene(i, 123, 256, train)
        dt = time.perf_counter() - t0
        times.append(dt)
        by_kind.setdefault(info["kind"], []).append(dt)
        t0 = time.perf_counter()
        generate_scene(i, 123, 256, held)
        held_times.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "syn"
        t0 = time.perf_counter()
        generate_dataset(root, n=args.scenes, size=256, seed=0, bands=bands, progress=False)
        write_s = (time.perf_counter() - t0) / args.scenes
        result = {
            "device": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
            "synth_s_per_scene": round(sum(times) / len(times), 4),
            "synth_s_per_scene_max": round(max(times), 4),
            "synth_s_per_scene_by_kind": {k: round(sum(v) / len(v), 4) for k, v in sorted(by_kind.items())},
            "synth_heldout_s_per_scene": round(sum(held_times) / len(held_times), 4),
            "synth_s_per_scene_with_write": round(write_s, 4),
            "synth_library_build_s": round(library_s, 3),
            "synth_scenes_timed": args.scenes,
            "holdout_sources": list(DEFAULT_HOLDOUT),
        }
        if args.demo_n > 0:
            cache = Path(tmp) / "cache"
            t0 = time.perf_counter()
            tr = synthetic_dataset(args.demo_n, 256, 0, bands, cache_dir=cache, progress=False)
            ho = heldout_dataset(HELDOUT_N, 256, 0, bands, cache_dir=cache, progress=False)
            result["demo_dataset_generate_s"] = round(time.perf_counter() - t0, 2)
            result["demo_dataset_scenes"] = {"train": args.demo_n, "heldout": HELDOUT_N}
            result["demo_dataset_bytes"] = {
                "train": sum(f.stat().st_size for f in tr.iterdir()),
                "heldout": sum(f.stat().st_size for f in ho.iterdir()),
            }
            result["demo_dataset_mib_total"] = round(sum(result["demo_dataset_bytes"].values()) / 2**20, 1)
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
