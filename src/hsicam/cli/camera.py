"""`hsicam psf` and `hsicam simulate`: look at a camera's PSFs and simulate a capture."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

from hsicam.cameras import DOECamera
from hsicam.cli import add_config_args
from hsicam.config import dump_yaml, load_config
from hsicam.errors import InputError
from hsicam.io import atomic_open, write_json, write_npy, write_png16
from hsicam.spectral import Bands

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("psf", help="compute the camera's PSF stack: psf.npy, psf.json, psf.png")
    add_config_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.set_defaults(func=cmd_psf)

    p = sub.add_parser("simulate", help="simulate the sensor image of a scene through the camera")
    add_config_args(p)
    p.add_argument("--scene", required=True, metavar="FILE", help="scene cube: .npy (bands, H, W) or a supported cube file")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--boundary", choices=("same", "valid"), default="same",
                   help="same: sensor as large as the scene (padded); valid: sensor smaller by the kernel margin")
    p.add_argument("--seed", type=int, default=0, help="seed for DOE height noise and sensor noise")
    p.add_argument("--run", metavar="RUN", help="use the trained optics of this run (its config.yaml; --set still applies)")
    p.set_defaults(func=cmd_simulate)


def build_camera(args: argparse.Namespace, extra_overrides: tuple[str, ...] = ()) -> tuple[DOECamera, object]:
    """Config (file + --set overrides) and the DOE camera it describes."""
    cfg = load_config(args.config, [*args.overrides, *extra_overrides])
    return DOECamera.from_config(cfg), cfg


def write_psf_outputs(camera: DOECamera, out: Path) -> dict:
    """psf.npy (C, K, K float32), psf.json (geometry, model, energy per band), psf.png (montage),
    and what is needed to recompute the PSFs independently: doe_height_m.npy (heights per DOE
    cell, m, (n, n) float64, exactly those used, fabrication noise included when enabled) and
    aperture.npy (transmission per pupil cell, (n·q, n·q) float64, area fraction in the circle)."""
    from hsicam.report.camera import plot_psf_montage

    optics = camera.optics
    with torch.no_grad():
        heights = optics.doe.heights()
        res = optics.psf_from_pupil(optics.expand_cells(heights))
    psf = res.psf.float().cpu().numpy()
    desc = optics.describe()
    info = {
        "bands_nm": camera.bands.centers_nm.tolist(),
        "fwhm_nm": camera.bands.fwhm_nm.tolist(),
        "pixel_pitch_um": camera.optics.pixel_m * 1e6,
        "kernel_px": camera.kernel_px,
        "energy_in_kernel": res.energy.double().cpu().numpy().tolist(),
        "lens": desc["lens"],
        "doe": desc["doe"],
        "aperture_radius_mm": desc["aperture_radius_mm"],
        "sampling": desc["sampling"],
        "model": desc["model"],
        "files": {
            "doe_height_m.npy": f"DOE heights (m) per {optics.cell_m * 1e6:g} µm cell, {optics.doe.n_cells}x{optics.doe.n_cells}, "
                                "row = y, column = x, centre cell on the optical axis",
            "aperture.npy": f"aperture transmission per {optics.sampling.pupil_pitch_m * 1e6:g} µm pupil cell "
                            "(area fraction inside the circle)",
        },
    }
    write_npy(out / "psf.npy", psf)
    write_npy(out / "doe_height_m.npy", heights.detach().double().cpu().numpy())
    write_npy(out / "aperture.npy", optics.amplitude.detach().double().cpu().numpy())
    write_json(out / "psf.json", info)
    plot_psf_montage(psf, camera.bands, out / "psf.png")
    return info


def cmd_psf(args: argparse.Namespace) -> int:
    camera, cfg = build_camera(args)
    out = Path(args.out)
    info = write_psf_outputs(camera, out)
    with atomic_open(out / "config.yaml") as fh:
        fh.write(dump_yaml(cfg))
    e = np.asarray(info["energy_in_kernel"])
    print(f"PSF stack: {len(camera.bands)} bands, {camera.kernel_px}×{camera.kernel_px} px, "
          f"energy in kernel {e.min():.4f}..{e.max():.4f} -> {out}")
    return 0


def load_scene(path: str | Path, bands: Bands) -> np.ndarray:
    """A scene cube (C, H, W) float32 on the camera's band grid.

    ``.npy`` files hold (bands, H, W) with no wavelength metadata: their band count must equal the
    camera's. Other formats carry their band centres and must match the camera's grid exactly.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such scene file")
    if path.suffix.lower() == ".npy":
        try:
            cube = np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - any numpy load failure is a bad file
            raise InputError(f"{path}: not a readable .npy file ({exc})") from None
        if cube.ndim != 3:
            raise InputError(f"{path}: scene must be a (bands, H, W) array, got shape {cube.shape}")
        if cube.shape[0] != len(bands):
            raise InputError(f"{path}: scene has {cube.shape[0]} bands but the camera has {len(bands)} ({bands!r})")
    else:
        from hsicam.data import read_cube

        cube, scene_bands, _ = read_cube(path)
        bands.require_match(scene_bands, what=str(path))
    cube = np.asarray(cube, dtype=np.float32)
    if not np.all(np.isfinite(cube)):
        raise InputError(f"{path}: scene contains NaN or Inf values")
    return cube


def cmd_simulate(args: argparse.Namespace) -> int:
    from hsicam.report.camera import plot_cfa, plot_doe_heights

    if args.run:
        from hsicam.engine.checkpoint import load_run

        if args.config:
            raise InputError("--run uses the run's config.yaml; drop --config")
        cfg, system = load_run(args.run, overrides=(*args.overrides, f"camera.boundary={args.boundary}"))
        camera = system.camera
    else:
        camera, cfg = build_camera(args, (f"camera.boundary={args.boundary}",))
    out = Path(args.out)
    scene = load_scene(args.scene, camera.bands)
    gen = torch.Generator().manual_seed(args.seed)
    with torch.no_grad():
        sensor = camera(torch.from_numpy(scene)[None], generator=gen)[0, 0].numpy()
    peak = float(sensor.max()) if sensor.size else 0.0
    png_scale = peak if peak > 1.0 else 1.0  # sensor.png holds sensor / png_scale
    write_npy(out / "sensor.npy", sensor.astype(np.float32))
    write_png16(out / "sensor.png", sensor / png_scale)
    plot_cfa(camera.cfa.tile().detach().numpy(), camera.bands, out / "cfa.png")
    optics = camera.optics
    plot_doe_heights(optics.doe.heights().detach().numpy(), optics.amplitude[:: optics.pupil_oversample, :: optics.pupil_oversample].numpy(),
                     optics.cell_m * 1e6, out / "doe.png")
    write_json(out / "simulate.json", {
        "scene": str(args.scene),
        "scene_shape": list(scene.shape),
        "sensor_shape": list(sensor.shape),
        "boundary": args.boundary,
        "sensor_png_scale": png_scale,
        "bands_nm": camera.bands.centers_nm.tolist(),
        "seed": args.seed,
    })
    with atomic_open(out / "config.yaml") as fh:
        fh.write(dump_yaml(cfg))
    print(f"sensor image {sensor.shape[0]}×{sensor.shape[1]} (min {sensor.min():.4g}, max {peak:.4g}) -> {out}")
    return 0
