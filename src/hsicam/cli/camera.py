"""`hsicam psf` and `hsicam simulate`: look at a camera's PSFs and simulate a capture.

Both take the camera from ``--config`` (a preset or YAML file: the design, its DOE as initialised,
never trained) or from ``--run RUN`` (a trained run or ``pretrained:NAME``: the trained DOE heights
and CFA of its weights; a fine-tuned run's measured PSFs). A run folder's own config.yaml given as
``--config`` is refused (:func:`check_not_run_config`): it would silently give the untrained camera.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hsicam.cli import add_config_args, add_run_arg, config_from_args, prepare_output
from hsicam.config import dump_yaml
from hsicam.errors import InputError
from hsicam.io import atomic_open, atomic_output, write_json, write_npy, write_png8, write_png16

if TYPE_CHECKING:
    from hsicam.spectral import Bands

# torch and the cameras are imported by the commands that use them, not with this module: the parser of
# every command is built from the modules of hsicam.cli, and `hsicam --help` should not wait for torch.

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("psf", help="compute the camera's PSF stack: psf.npy, psf.json, psf.png")
    add_config_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_run_arg(p, "the PSFs of this trained run's camera (its trained DOE; a fine-tuned run's measured PSFs) "
                   "instead of --config's untrained design", required=False)
    from hsicam.cli.args import seed_arg
    p.add_argument("--seed", type=seed_arg(), default=0,
                   help="seed of torch's generator for the DOE height noise (a camera.doe.sigma_height_nm above 0 "
                        "draws one fabricated element per seed), an integer in [0, 2^32 - 1] (default 0)")
    p.set_defaults(func=cmd_psf)

    p = sub.add_parser("simulate", help="simulate the sensor image of a scene through the camera")
    add_config_args(p)
    p.add_argument("--scene", required=True, metavar="FILE", help="scene cube: .npy (bands, H, W) or a supported cube file")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--boundary", choices=("same", "valid"), default="same",
                   help="same (default): sensor as large as the scene (padded), whatever the config's camera.boundary; "
                        "valid: sensor smaller by the kernel margin (what training sees: the presets' camera.boundary); "
                        "a DOE camera's choice: a CASSI camera has no PSF kernel, so valid is refused for it")
    p.add_argument("--seed", type=seed_arg(), default=0,
                   help="seed of torch's generator for DOE height noise and sensor noise, an integer in [0, 2^32 - 1] "
                        "as every seed key (camera.doe.seed, train.seed, data synth --seed) (default 0)")
    add_run_arg(p, "use the trained optics of this run (its config.yaml; --set still applies)", required=False)
    p.set_defaults(func=cmd_simulate)


_REST = {"psf": "--out DIR", "simulate": "--scene FILE --out DIR"}


def check_not_run_config(config: str | Path | None, command: str) -> None:
    """One-line :class:`InputError` when ``--config`` is a trained run's own config.yaml (a file
    beside ``model.safetensors``), or the copy of it that ``hsicam psf --run`` or ``hsicam simulate --run`` wrote
    (their psf.json / simulate.json name the run): the config describes the camera before training, its trained DOE
    heights are in the weights, so ``--config`` would silently give another camera than the run's."""
    if config is None or not Path(config).is_file():
        return
    path = Path(config)
    folder = path.parent
    if (folder / "model.safetensors").is_file():
        run, what = folder, (f"the config.yaml of the trained run {folder}, whose DOE heights are in "
                             f"{folder / 'model.safetensors'}")
        where = "the run folder"
    else:
        source = _output_run(folder)
        if source is None:
            return
        writer, run = source
        what = (f"the config.yaml that hsicam {writer} wrote for the trained camera {run}, whose DOE heights are in "
                "that run's weights")
        where = "that folder"
    raise InputError(f"--config {path}: {what}; --config gives the untrained design's camera: use "
                     f"`hsicam {command} --run {run} {_REST[command]}` for the trained camera (the design before training: "
                     f"copy the config.yaml out of {where} first)")


def _output_run(folder: Path) -> tuple[str, str] | None:
    """(command, run label) when ``folder`` is the output of ``hsicam psf --run RUN`` or ``hsicam simulate --run RUN``
    (the ``source`` its psf.json or simulate.json records), else None."""
    import json

    from hsicam.data.images import SIMULATE_JSON

    for command, name in (("psf", "psf.json"), ("simulate", SIMULATE_JSON)):
        try:
            source = json.loads((folder / name).read_text(encoding="utf-8")).get("source")
        except (OSError, ValueError, AttributeError):
            continue
        run = source.get("run") if isinstance(source, dict) else None
        if isinstance(run, str) and run:
            return command, run
    return None


def camera_from_args(args: argparse.Namespace, extra_overrides: tuple[str, ...] = (), command: str = "psf"):
    """(camera, config) of the command line's config file and --set overrides (any camera kind). An unknown
    ``model.kind`` is refused here too, though no network is built: the command writes the config beside its
    outputs, and a config naming no network would only be refused by the ``train`` it was meant for."""
    from hsicam.cameras import build_camera
    from hsicam.models import check_network_kind

    check_not_run_config(args.config, command)
    cfg = config_from_args(args.config, [*args.overrides, *extra_overrides])
    check_network_kind(cfg.model.kind)
    return build_camera(cfg), cfg


def cmd_psf(args: argparse.Namespace) -> int:
    import torch

    from hsicam.report.camera import write_psf_outputs
    from hsicam.runs.pretrained import run_label

    out = prepare_output(args.out, "dir", replace=True, command="psf", run=args.run)
    if args.run:
        from hsicam.runs.folder import load_run

        if args.config:
            raise InputError("--run uses the run's config.yaml; drop --config")
        cfg, system = load_run(args.run, overrides=tuple(args.overrides))
        camera = system.camera
        source = {"run": run_label(args.run),
                  "optics": ("the run's measured PSFs (fine-tuned run)" if camera.kind == "measured_psf"
                             else "the run's trained DOE (model.safetensors)")}
    else:
        camera, cfg = camera_from_args(args, command="psf")
        source = {"config": str(args.config) if args.config else "paper (default)",
                  "optics": "the config's DOE as initialised (untrained; a trained camera: --run RUN)"}
    if camera.kind not in ("doe", "measured_psf"):
        raise InputError(f"hsicam psf needs a DOE camera (camera.kind=doe), not camera.kind={camera.kind}")
    with atomic_output(out, overwrite=True, marker={"command": "psf"}) as tmp:
        info = write_psf_outputs(camera, tmp, torch.Generator().manual_seed(args.seed))  # (was the global RNG's draw)
        noisy = camera.kind == "doe" and camera.optics.doe.sigma_height_m > 0
        write_json(tmp / "psf.json", {**info, "source": source, **({"height_noise_seed": args.seed} if noisy else {})})
        with atomic_open(tmp / "config.yaml", encoding="utf-8") as fh:
            fh.write(dump_yaml(cfg))
    e = np.asarray(info["energy_in_kernel"])
    what = (f"{run_label(args.run)}'s {'measured PSFs' if camera.kind == 'measured_psf' else 'trained camera'}" if args.run
            else "the config's camera, DOE as initialised")
    print(f"PSF stack ({what}): {len(camera.bands)} bands, {camera.kernel_px}×{camera.kernel_px} px, "
          f"energy in kernel {e.min():.4f}..{e.max():.4f} -> {out}")
    return 0


def load_scene(path: str | Path, bands: Bands, npy_bands: Bands | None = None, allow_negative: bool = False) -> np.ndarray:
    """A scene cube (C, H, W) float32 on the camera's band grid ``bands``.

    Every format goes through the one cube check (finite, real, non-negative, non-empty, band grid
    known) and the one band-grid policy (:func:`hsicam.data.cube.conform_bands`: a cube on another
    grid is resampled onto the camera's with a logged note; only extrapolation is refused). A ``.npy``
    file carries no wavelengths: its grid is ``npy_bands`` (the config's ``data.npy_bands``) when
    given, else it must have the camera's band count (its grid is then the camera's). ``allow_negative`` (the
    config's ``data.allow_negative``): negative values are clipped to 0 instead of refused.
    """
    from hsicam.data import read_cube
    from hsicam.data.cube import conform_bands
    from hsicam.data.formats import npy_header

    path = Path(path)
    if not path.exists():
        from hsicam.io import broken_link_problem

        raise InputError(f"{path}: {broken_link_problem(path) or 'no such scene file'}")
    if path.suffix.lower() == ".npy":
        if npy_bands is None:
            shape, _ = npy_header(path)
            if len(shape) == 3 and shape[0] != len(bands):
                raise InputError(f"{path}: a .npy scene carries no wavelengths, and its {shape[0]} bands are not the "
                                 f"camera's {len(bands)} ({bands!r}); save it as .h5 with its band list "
                                 "(hsicam.data.formats.write_cube_h5) or give its grid with data.npy_bands to have "
                                 "it resampled")
        cube, scene_bands, _ = read_cube(path, bands=bands if npy_bands is None else npy_bands,
                                         allow_negative=allow_negative)
    else:
        from hsicam.data.formats import assumed_bands_note

        cube, scene_bands, meta = read_cube(path, allow_negative=allow_negative)
        try:
            return conform_bands(cube, scene_bands, bands, path, axis=0)
        except InputError as exc:
            note = assumed_bands_note(meta)  # a MAT/HDF5 file without a band list: say the grid was assumed
            if note:
                raise InputError(f"{exc} ({note})") from None
            raise
    return conform_bands(cube, scene_bands, bands, path, axis=0)


def check_boundary_applies(camera, boundary: str) -> None:
    """One-line :class:`InputError` for ``--boundary valid`` on a camera without a PSF kernel (the CASSI
    cameras: the forward model codes and shears the scene, no blur, so their kernel margin is 0): there
    is no margin to crop, and the sensor image would silently be the default's (``same``)."""
    if boundary == "valid" and camera.margin == 0:  # as evaluate's scored_region tells a crop
        raise InputError(f"--boundary valid: the {camera.kind} camera images without a PSF (its forward model codes "
                         "and shears the scene, no blur), so it has no kernel margin to crop and its sensor image is "
                         "the default's; drop --boundary (it applies to a DOE camera)")


def cmd_simulate(args: argparse.Namespace) -> int:
    import torch

    from hsicam.color import PREVIEW_EXPOSURE_KEY, PREVIEW_LEVEL
    from hsicam.data.images import SENSOR_PREVIEW, SENSOR_SCALE_KEY, SIMULATE_JSON, SIMULATED_SENSOR_PNG, sensor_preview
    from hsicam.data.pipeline import npy_bands
    from hsicam.report.camera import write_optics_figures

    from hsicam.config import override_keys

    if "camera.boundary" in override_keys(args.overrides):  # (it was replaced by --boundary's default, silently)
        raise InputError("--set camera.boundary: simulate's sensor boundary is its option --boundary (same by default, "
                         "whatever the config says); give --boundary same or --boundary valid")
    out = prepare_output(args.out, "dir", replace=True, command="simulate", run=args.run)
    if args.run:
        from hsicam.runs.folder import load_run

        if args.config:
            raise InputError("--run uses the run's config.yaml; drop --config")
        from hsicam.runs.pretrained import run_label

        cfg, system = load_run(args.run, overrides=(*args.overrides, f"camera.boundary={args.boundary}"))
        camera = system.camera
        source = {"run": run_label(args.run)}  # its config.yaml below is then no design to simulate again with --config
    else:
        camera, cfg = camera_from_args(args, (f"camera.boundary={args.boundary}",), command="simulate")
        source = {"config": str(args.config) if args.config else "paper (default)"}
    check_boundary_applies(camera, args.boundary)
    scene = load_scene(args.scene, camera.bands, npy_bands(cfg.data), cfg.data.allow_negative)
    gen = torch.Generator().manual_seed(args.seed)
    sensor = camera.capture(torch.from_numpy(scene)[None], gen, source=str(args.scene))[0, 0].numpy()
    peak = float(sensor.max()) if sensor.size else 0.0
    png_scale = peak if peak > 1.0 else 1.0  # sensor.png holds sensor / png_scale
    with atomic_output(out, overwrite=True, marker={"command": "simulate"}) as tmp:
        write_npy(tmp / "sensor.npy", sensor.astype(np.float32))
        # the scale travels inside the PNG too: a copy taken away from simulate.json keeps its level
        write_png16(tmp / SIMULATED_SENSOR_PNG, sensor / png_scale, text={SENSOR_SCALE_KEY: repr(png_scale)})
        preview, exposure = sensor_preview(sensor)  # to look at: the data file of a dim scene looks black
        write_png8(tmp / SENSOR_PREVIEW, preview, text={PREVIEW_EXPOSURE_KEY: f"{exposure:.6g}"})
        if camera.kind == "doe":
            write_optics_figures(camera, tmp)
        write_json(tmp / SIMULATE_JSON, {
            "scene": str(args.scene),
            "scene_shape": list(scene.shape),
            "sensor_shape": list(sensor.shape),
            "boundary": args.boundary,
            "sensor_png_scale": png_scale,
            "sensor_preview_exposure": exposure,
            "bands_nm": camera.bands.centers_nm.tolist(),
            "seed": args.seed,
            "source": source,
        })
        with atomic_open(tmp / "config.yaml", encoding="utf-8") as fh:
            fh.write(dump_yaml(cfg))
    if Path(args.scene).suffix.lower() == ".npy" and npy_bands(cfg.data) is None:
        # a scene made for this camera; the data readers (train, evaluate --data) take a .npy as
        # 400-700 nm instead, so say which grid it was given (after the work: an error stays one line)
        b = camera.bands
        log.info("%s: a .npy scene carries no wavelengths; its %d bands were taken as the camera's (%g-%g nm): give "
                 "data.npy_bands if they are not", args.scene, len(b), b.min_nm, b.max_nm)
    # the preview on a line of its own: the first stays the line scripts read (its last word the output folder)
    print(f"sensor image {sensor.shape[0]}×{sensor.shape[1]} (min {sensor.min():.4g}, max {peak:.4g}) -> {out}\n"
          f"{SENSOR_PREVIEW}: a display preview (linear, ×{exposure:.3g}: its 99th percentile at "
          f"{PREVIEW_LEVEL:g} of white), not data")
    return 0
