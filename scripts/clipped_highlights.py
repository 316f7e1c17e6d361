"""What taking clipped pixels as lower bounds is worth: each validation scene exposed so that a share of its pixels
passes full scale, clipped there (noise-free), reconstructed with the measurement-consistency steps plain and with
the map of clipped pixels (hsicam.models.consistency.clipped_residual), scored against the exposed truth.

    python scripts/clipped_highlights.py RUN [--share 0.03] [--heldout] [--set KEY=VALUE ...]

RUN is a run folder or pretrained:NAME (its steps: model.consistency). PSNR (dB, the mean of the bands' PSNRs, peak:
the exposed truth's maximum) over the whole scene, the pixels within 8 px of a clipped one ("near"), the clipped
pixels themselves and the rest ("far"). Prints one JSON line per scene, then the mean, least and largest gain of the
map per region.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch
import torch.nn.functional as F

from hsicam.engine.experiments import scored_scenes
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import HsicamError
from hsicam.runs.folder import load_run

NEAR_PX = 8
REGIONS = ("all", "near", "clipped", "far")


def _psnr(err: torch.Tensor, where: torch.Tensor, peak: float) -> float:
    """The mean over bands of each band's PSNR (dB, the project's convention, DESIGN.md §5) over the pixels
    ``where`` (H, W) of the squared error ``err`` (C, H, W); NaN where no pixel is."""
    if not bool(where.any()):
        return float("nan")
    mse = err[:, where].double().mean(dim=1).clamp_min(1e-30)
    return float((10 * torch.log10(peak**2 / mse)).mean())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="run folder or pretrained:NAME")
    p.add_argument("--share", type=float, default=0.03, help="share of the pixels clipped (default 0.03)")
    p.add_argument("--heldout", action="store_true", help="the held-out-sources scenes instead of the validation split")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    if not 0 < args.share < 0.5:
        print("error: --share must be in (0, 0.5)", file=sys.stderr)
        return 2
    try:
        cfg, model = load_run(args.run, overrides=tuple(args.overrides))
        scenes, names = scored_scenes(cfg, args.heldout)
    except HsicamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    model.eval()
    gains: dict[str, list[float]] = {r: [] for r in REGIONS}
    for i, name in enumerate(names):
        scene = scenes[i][None]
        with torch.no_grad():
            clean = model.camera.A(scene)
        k = 1.0 / float(torch.quantile(clean.flatten(), 1 - args.share))
        truth = model.target(scene)[0] * k
        clipped = (clean * k >= 1.0)[0, 0]
        near = F.max_pool2d(clipped[None, None].float(), 2 * NEAR_PX + 1, 1, NEAR_PX)[0, 0] > 0
        where = {"all": torch.ones_like(clipped), "near": near, "clipped": clipped, "far": ~near}
        row: dict = {"scene": name, "exposure": k, "clipped_share": float(clipped.float().mean())}
        for label, saturated in (("plain", None), ("lower_bounds", clipped)):
            model.camera.noise.mark_saturated(saturated, (0, 0))
            with torch.no_grad():
                x = reconstruct_tiled(model.reconstructor(), (clean * k).clamp(max=1.0))[0].clamp_min(0)
            err = (x - truth) ** 2
            row[label] = {r: _psnr(err, where[r], float(truth.max())) for r in REGIONS}
        for r in REGIONS:
            gains[r].append(row["lower_bounds"][r] - row["plain"][r])
        print(json.dumps(row), flush=True)
    for r in REGIONS:
        g = np.array(gains[r])
        print(json.dumps({"region": r, "mean_gain_db": float(np.nanmean(g)), "min_gain_db": float(np.nanmin(g)),
                          "max_gain_db": float(np.nanmax(g)), "scenes_gained": int(np.sum(g > 0))}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
