"""How much of a CFA camera's error is spectral and how much spatial: the spectral oracle.

The oracle knows every CFA filter's image at every pixel (no mosaic, no PSF: the sensor's spatial
sampling is perfect) and maps the F filter values of a pixel to the C bands with the best linear
map, ridge regression fitted on the run's training scenes:

    f = K x     (K: the run's F×C filter transmissions, the CFA tile's distinct phases)
    x̂ = W f     W = argmin Σ‖x − W K x‖² + λ‖W‖²  over sampled training pixels

Its scores bound what spectral coding alone allows this CFA (for a linear decoder; a learned prior
may do better on spectra it knows): what a camera loses below them is the mosaic's spatial
sampling and the optics' blur, i.e. demosaicking.

    python scripts/spectral_oracle.py RUN [--heldout] [--pixels N] [--ridge L] [--set KEY=VALUE ...]

RUN is a run folder or pretrained:NAME. Prints a Markdown table per scene (per-band PSNR peak 1,
SSIM, SAM in degrees: hsicam.metrics) over the area the camera's own scores cover (`valid`: the
scene minus the kernel margin), so the two compare pixel for pixel.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from hsicam.errors import HsicamError


def filter_matrix(tile: torch.Tensor) -> torch.Tensor:
    """The distinct filters of a CFA tile (C, m, m) as rows: (m², C)."""
    c = tile.shape[0]
    return tile.reshape(c, -1).T


def fit_linear_decoder(filters: torch.Tensor, pixels: torch.Tensor, ridge: float) -> torch.Tensor:
    """Ridge map W (C, F) from filter values to spectra, fitted on ``pixels`` (C, N) of spectra.

    W = X Fᵀ (F Fᵀ + λ·tr(F Fᵀ)/F · I)⁻¹ with F = K X: λ is relative to the mean filter energy."""
    resp = filters @ pixels  # (F, N)
    gram = resp @ resp.T
    reg = ridge * torch.trace(gram) / gram.shape[0]
    system = gram + reg * torch.eye(gram.shape[0], dtype=gram.dtype)
    return torch.linalg.solve(system, resp @ pixels.T).T  # (gram + λ)⁻¹ symmetric: W = (solve)ᵀ


def oracle_estimate(filters: torch.Tensor, decoder: torch.Tensor, cube: torch.Tensor) -> torch.Tensor:
    """x̂ = W K x per pixel for a cube (B, C, H, W): the oracle's reconstruction, clipped to [0, 1]."""
    resp = torch.einsum("fc,bchw->bfhw", filters.to(cube.dtype), cube)
    return torch.einsum("cf,bfhw->bchw", decoder.to(cube.dtype), resp).clamp(0, 1)


def training_pixels(cfg, per_scene: int, seed: int = 0) -> torch.Tensor:
    """``per_scene`` random pixels of every training scene of the run's data config (on the run's
    band grid), (C, N) float64."""
    from hsicam.data.pipeline import scene_dataset, split_dataset

    bands = cfg.bands.to_bands()
    train, _ = split_dataset(cfg.data, bands)
    if not train:
        raise HsicamError("the run's data config has no training scenes")
    rng = np.random.default_rng(seed)
    cols = []
    scenes = scene_dataset(cfg.data, train, bands)
    for i in range(len(train)):
        flat = scenes[i].double().reshape(len(bands), -1)
        cols.append(flat[:, torch.from_numpy(rng.choice(flat.shape[1], min(per_scene, flat.shape[1]), replace=False))])
    return torch.cat(cols, dim=1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="run folder or pretrained:NAME")
    p.add_argument("--heldout", action="store_true", help="the held-out-sources scenes instead of the validation split")
    p.add_argument("--pixels", type=int, default=4000, help="training pixels drawn per scene (default 4000)")
    p.add_argument("--ridge", type=float, default=1e-6, help="ridge weight relative to the mean filter energy")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    from hsicam.engine.experiments import scored_scenes
    from hsicam.metrics import psnr_per_band, sam_degrees, ssim
    from hsicam.runs.folder import load_run

    try:
        if args.pixels < 1 or args.ridge < 0:
            raise HsicamError("--pixels must be >= 1 and --ridge >= 0")
        cfg, model = load_run(args.run, overrides=tuple(args.overrides))
        if not getattr(getattr(model.camera, "cfa", None), "enabled", False):
            raise HsicamError("the spectral oracle needs a camera with a colour filter array")
        filters = filter_matrix(model.camera.cfa.tile().detach().double())
        decoder = fit_linear_decoder(filters, training_pixels(cfg, args.pixels), args.ridge)
        scenes, names = scored_scenes(cfg, args.heldout)
    except HsicamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"spectral oracle: {filters.shape[0]} filters -> {filters.shape[1]} bands, linear, full resolution")
    print("| scene | PSNR | SSIM | SAM |")
    print("|---|---|---|---|")
    rows = []
    with torch.no_grad():
        for i, name in enumerate(names):
            truth = model.target(scenes[i][None].float())  # the camera's scored area (valid: minus the margin)
            est = oracle_estimate(filters, decoder, truth.double()).float()
            rows.append([psnr_per_band(est, truth).item(), ssim(est, truth).item(), sam_degrees(est, truth).item()])
            print(f"| {name} | {rows[-1][0]:.2f} | {rows[-1][1]:.4f} | {rows[-1][2]:.2f} |")
    mean = np.mean(np.array(rows), axis=0)
    print(f"| **mean** | {mean[0]:.2f} | {mean[1]:.4f} | {mean[2]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
