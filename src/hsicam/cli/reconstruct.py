"""`hsicam reconstruct`: a hyperspectral cube from a sensor image, through a trained run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from hsicam.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="reconstruct a hyperspectral cube from a sensor image")
    p.add_argument("sensor", metavar="SENSOR", help="sensor image: .npy, 16-bit PNG or TIFF")
    p.add_argument("--run", required=True, metavar="RUN", help="trained run folder")
    p.add_argument("--out", required=True, metavar="FILE", help="output cube: .h5 (ours) or .hdr (ENVI)")
    p.add_argument("--scale", type=float, default=None, help="multiply the image after normalising to [0, 1]")
    p.add_argument("--tile", type=int, default=512, metavar="PX", help="tile side for large images")
    p.add_argument("--device", default="cpu")
    p.set_defaults(func=cmd_reconstruct)


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
