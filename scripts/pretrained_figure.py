"""Draw the README's picture of a shipped camera: held-out-sources scenes (spectra its training
never saw), ground truth | reconstruction | error | spectra.

    python scripts/pretrained_figure.py standard docs/img/standard_heldout.png [--scenes 2]

Maintainers run it after `hsicam pretrained pack`; the scenes are the demo's held-out-sources
set (seed 0), which no shipped camera trains on.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")

from hsicam.config import load_config  # noqa: E402
from hsicam.data.datasets import SceneDataset, list_scenes  # noqa: E402
from hsicam.data.pipeline import heldout_root  # noqa: E402
from hsicam.engine.evaluate import evaluate_scenes  # noqa: E402
from hsicam.report.reconstruction import plot_reconstructions  # noqa: E402
from hsicam.runs.folder import load_run  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("name")
    p.add_argument("out")
    p.add_argument("--scenes", type=int, default=2)
    p.add_argument("--first", type=int, default=0, help="index of the first held-out scene")
    args = p.parse_args()
    cfg, model = load_run(f"pretrained:{args.name}")
    demo = load_config("quick")  # the demo's data settings: its held-out-sources scenes
    bands = cfg.bands.to_bands()
    paths = list_scenes(heldout_root(demo.data, bands))[args.first : args.first + args.scenes]
    results = evaluate_scenes(model, SceneDataset(paths, bands), [f"held-out {p.stem}" for p in paths])
    plot_reconstructions(results, bands, args.out, max_rows=args.scenes)
    for r in results:
        print(f"{r.name}: PSNR {r.metrics['psnr']:.2f} dB, SSIM {r.metrics['ssim']:.4f}, SAM {r.metrics['sam']:.2f}°")


if __name__ == "__main__":
    main()
