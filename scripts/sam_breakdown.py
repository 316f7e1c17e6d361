"""Where a trained camera's spectral angle comes from: per validation scene, SAM over all pixels,
the dark ones (truth's band mean below 1 % of full scale) and the bright ones, split into edges
(top 20 % of the truth's brightness gradient) and flat regions (hsicam.metrics.sam_breakdown).

    python scripts/sam_breakdown.py RUN [--heldout] [--set KEY=VALUE ...]

RUN is a run folder or pretrained:NAME; ``--set`` changes the run's data settings (e.g. the demo's
scenes for a shipped camera: data.synthetic_n=64 data.synthetic_seed=0 data.val_fraction=0.125).
Prints a Markdown table (degrees; the dark fraction in %).
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import torch

from hsicam.engine.experiments import scored_scenes
from hsicam.errors import HsicamError
from hsicam.metrics import sam_breakdown
from hsicam.runs.folder import load_run

COLUMNS = ("all", "dark_fraction", "dark", "bright", "edges", "flat")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="run folder or pretrained:NAME")
    p.add_argument("--heldout", action="store_true", help="the held-out-sources scenes instead of the validation split")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    try:
        cfg, model = load_run(args.run, overrides=tuple(args.overrides))
        scenes, names = scored_scenes(cfg, args.heldout)
    except HsicamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print("| scene | SAM | dark pixels | SAM dark | SAM bright | bright edges | bright flat |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    with torch.no_grad():
        for i, name in enumerate(names):
            scene = scenes[i][None]
            sensor = model.camera(scene, torch.Generator().manual_seed(cfg.train.seed))
            est = model.reconstructor()(sensor).float().clamp(0, 1)
            got = sam_breakdown(est, model.target(scene))
            rows.append([got[k][0] for k in COLUMNS])
            print(f"| {name} | " + " | ".join(_fmt(k, v) for k, v in zip(COLUMNS, rows[-1])) + " |")
    mean = np.nanmean(np.array(rows, dtype=np.float64), axis=0)
    print("| **mean** | " + " | ".join(_fmt(k, v) for k, v in zip(COLUMNS, mean)) + " |")
    return 0


def _fmt(key: str, v: float) -> str:
    if math.isnan(v):
        return "–"
    return f"{100 * v:.0f} %" if key == "dark_fraction" else f"{v:.2f}°"


if __name__ == "__main__":
    sys.exit(main())
