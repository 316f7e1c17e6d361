"""Tune GAP-TV's run settings (iterations, TV weight) on *training* scenes, never on the scored ones.

    python scripts/tune_gaptv.py [--config quick] [--scenes 8] [--iterations 80,160,320]
                                 [--weights 0.01,0.02,0.03,0.05] [--set KEY=VALUE ...]

Runs DD-CASSI + GAP-TV (``hsicam.solvers.gaptv``) on the first ``--scenes`` scenes of the config's
training split for every (iterations, tv_weight) pair, each scene captured as the evaluation captures
it, and prints one JSON line per setting (mean per-band PSNR, SSIM, SAM, seconds per scene), then a
Markdown table. The weights may also be a falling schedule ``a>b`` (geometric from a to b over the
iterations). The config's ``baselines.gaptv`` defaults were chosen with this script (docs/training_log.md).
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time

import numpy as np

from hsicam.cli.args import count_arg, list_arg
from hsicam.config import load_config
from hsicam.data.pipeline import scene_dataset, split_dataset
from hsicam.engine.evaluate import evaluate_method
from hsicam.engine.methods import build_method
from hsicam.errors import HsicamError


def weight_values(text: str, iterations: int) -> float | list[float]:
    """``0.02`` → 0.02; ``0.1>0.01`` → a geometric schedule from 0.1 to 0.01 over ``iterations``."""
    if ">" not in text:
        return float(text)
    a, b = (float(v) for v in text.split(">"))
    return [float(v) for v in np.geomspace(a, b, max(iterations, 1))]


def _weights(text: str) -> list[str]:
    """argparse ``type`` of ``--weights``: the comma-separated weights or ``a>b`` schedules as written (the JSON's
    ``tv_weight``), each checked here, before the scenes are loaded."""
    items = text.split(",")
    for item in items:
        try:
            weight_values(item, 1)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected numbers or schedules a>b, got {item!r}") from None
    return items


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="quick")
    p.add_argument("--scenes", type=count_arg, default=8, help="training scenes used (the first N of the split)")
    p.add_argument("--iterations", type=list_arg(int, "integers", lambda v: v >= 1, ">= 1"), default="80,160,320")
    p.add_argument("--weights", type=_weights, default="0.01,0.02,0.03,0.05")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    try:
        cfg = load_config(args.config, ["model.consistency.iterations=0", *args.overrides])  # a DOE-camera step
        bands = cfg.bands.to_bands()
        train_paths, _ = split_dataset(cfg.data, bands)
        paths = train_paths[: args.scenes]
        scenes = scene_dataset(cfg.data, paths, bands)
        names = [q.stem for q in paths]
        rows = []
        for iterations in args.iterations:
            for weight in args.weights:
                method = build_method("dd-cassi-gaptv", cfg)
                base = method.reconstruct  # functools.partial(gap_tv, camera, **the config's settings)
                method.reconstruct = functools.partial(base.func, *base.args, **{
                    **base.keywords, "iterations": iterations, "tv_weight": weight_values(weight, iterations)})
                t0 = time.perf_counter()
                results = evaluate_method(method, scenes, names, keep_arrays=False)
                row = {"iterations": iterations, "tv_weight": weight,
                       **{k: float(np.mean([r.metrics[k] for r in results])) for k in ("psnr", "ssim", "sam")},
                       "min_psnr": float(min(r.metrics["psnr"] for r in results)),
                       "s_per_scene": (time.perf_counter() - t0) / len(names)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    except (HsicamError, OSError) as exc:  # a bad config or --set, unreadable scenes: one line, not a traceback
        p.error(str(exc))
    print(f"\nDD-CASSI + GAP-TV on {len(names)} training scenes ({', '.join(names)}):\n")
    print("| iterations | TV weight | PSNR | SSIM | SAM | worst PSNR | s per scene |\n|---|---|---|---|---|---|---|")
    for r in sorted(rows, key=lambda r: -r["psnr"]):
        print(f"| {r['iterations']} | {r['tv_weight']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['sam']:.2f} | "
              f"{r['min_psnr']:.2f} | {r['s_per_scene']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
