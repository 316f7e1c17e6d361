"""Draw the README's picture of a shipped camera: held-out-sources scenes (spectra its training
never saw), ground truth | reconstruction | error | spectra.

    python scripts/pretrained_figure.py standard docs/img/standard_heldout.png [--scenes 2]

Maintainers run it after `hsicam pretrained pack`; the scenes are the demo's held-out-sources
set (seed 0), which no shipped camera trains on.
"""

from __future__ import annotations

import argparse
import sys

import matplotlib

matplotlib.use("Agg")

from hsicam.config import load_config  # noqa: E402
from hsicam.data.datasets import SceneDataset, list_scenes  # noqa: E402
from hsicam.data.pipeline import heldout_root  # noqa: E402
from hsicam.engine.evaluate import evaluate_scenes  # noqa: E402
from hsicam.errors import HsicamError  # noqa: E402
from hsicam.report.reconstruction import plot_reconstructions  # noqa: E402
from hsicam.runs.folder import load_run  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("name", help="a shipped camera (hsicam pretrained list)")
    p.add_argument("out", help="the PNG to write")
    p.add_argument("--scenes", type=int, default=2)
    p.add_argument("--first", type=int, default=0, help="index of the first held-out scene")
    args = p.parse_args(argv)
    if args.scenes < 1 or args.first < 0:
        p.error(f"--scenes must be >= 1 and --first >= 0, got {args.scenes} and {args.first}")
    try:  # an unknown camera, a damaged one, an output that cannot be written: one line, not a traceback
        cfg, model = load_run(f"pretrained:{args.name}")
        demo = load_config("quick")  # the demo's data settings: its held-out-sources scenes
        bands = cfg.bands.to_bands()
        paths = list_scenes(heldout_root(demo.data, bands))[args.first : args.first + args.scenes]
        if not paths:
            raise HsicamError(f"--first {args.first}: there are fewer held-out scenes")
        results = evaluate_scenes(model, SceneDataset(paths, bands), [f"held-out {p.stem}" for p in paths])
        plot_reconstructions(results, bands, args.out, max_rows=args.scenes)
    except (HsicamError, OSError) as e:
        p.error(str(e))
    for r in results:
        print(f"{r.name}: PSNR {r.metrics['psnr']:.2f} dB, SSIM {r.metrics['ssim']:.4f}, SAM {r.metrics['sam']:.2f}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
