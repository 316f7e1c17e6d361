"""`hsicam train` and `hsicam reconstruct`."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch

from hsicam.cli import add_config_args
from hsicam.errors import InputError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train optics + reconstruction network jointly")
    add_config_args(p)
    p.add_argument("--out", required=True, metavar="RUN", help="run folder")
    p.add_argument("--resume", action="store_true", help="continue the run from its last checkpoint")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("reconstruct", help="reconstruct a hyperspectral cube from a sensor image")
    p.add_argument("sensor", metavar="SENSOR", help="sensor image: .npy, 16-bit PNG or TIFF")
    p.add_argument("--run", required=True, metavar="RUN", help="trained run folder")
    p.add_argument("--out", required=True, metavar="FILE", help="output cube: .h5 (ours) or .hdr (ENVI)")
    p.add_argument("--scale", type=float, default=None, help="multiply the image after normalising to [0, 1]")
    p.add_argument("--tile", type=int, default=512, metavar="PX", help="tile side for large images")
    p.add_argument("--device", default="cpu")
    p.set_defaults(func=cmd_reconstruct)


def cmd_train(args: argparse.Namespace) -> int:
    from hsicam.config import load_config
    from hsicam.engine.train import train

    run = Path(args.out)
    if args.resume:
        if args.config:
            raise InputError("--resume continues with the run's own config.yaml; drop --config (use --set to change keys)")
        if not (run / "config.yaml").is_file():
            raise InputError(f"{run}: nothing to resume (no config.yaml)")
        cfg = load_config(run / "config.yaml", args.overrides)
    else:
        cfg = load_config(args.config, args.overrides)
    summary = train(cfg, run, resume=args.resume)
    if summary.get("best_psnr") is not None:
        print(f"trained {summary['epoch']} epochs ({summary['step']} steps, {summary['patches_per_s']:.1f} patches/s): "
              f"val PSNR {summary['val_psnr']:.2f} dB, SSIM {summary['val_ssim']:.4f}, SAM {summary['val_sam']:.2f}° -> {run}")
    else:
        print(f"trained {summary['epoch']} epochs ({summary['step']} steps) -> {run}")
    return 0


def write_cube_file(path: Path, cube: np.ndarray, bands, metadata: dict) -> None:
    """Our HDF5 (.h5) or ENVI (.hdr) by extension, plus an sRGB preview ``<stem>_rgb.png``."""
    from hsicam.color import cube_to_srgb
    from hsicam.data.formats import write_cube_h5, write_envi
    from hsicam.io import write_png8

    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        write_cube_h5(path, cube, bands, metadata)
    elif suffix in (".hdr", ".img", ".raw"):
        write_envi(path, cube, bands)
    else:
        raise InputError(f"{path}: output must end in .h5 (HDF5) or .hdr (ENVI)")
    rgb = cube_to_srgb(torch.from_numpy(cube), bands).numpy()
    write_png8(path.with_name(f"{path.stem}_rgb.png"), np.moveaxis(rgb, 0, -1))


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from hsicam.engine.checkpoint import load_run
    from hsicam.engine.inference import read_sensor_image, receptive_radius, reconstruct_tiled

    if args.tile < 16:
        raise InputError("--tile must be at least 16 px")
    cfg, model = load_run(args.run, args.device)
    img = read_sensor_image(args.sensor, args.scale)
    sensor = torch.from_numpy(img)[None, None].to(args.device)
    halo = receptive_radius(model.net)
    cube = reconstruct_tiled(model.reconstruct, sensor, args.tile, halo, progress=sys.stderr.isatty())[0]
    # Radiance is non-negative: the network's small negative excursions are clipped at 0.
    cube = cube.float().clamp_min(0).cpu().numpy()
    out = Path(args.out)
    write_cube_file(out, cube, model.bands, {"source": str(args.sensor), "run": str(args.run)})
    print(f"reconstructed {cube.shape[0]} bands × {cube.shape[1]}×{cube.shape[2]} -> {out}")
    return 0
