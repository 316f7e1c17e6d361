"""`hsicam reconstruct`: a hyperspectral cube from a sensor image (simulated or a raw capture)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hsicam.data.estimates import ENVI_DESCRIPTIONS, head, is_reconstruct_h5, reconstruct_envi_header
from hsicam.errors import InputError

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from hsicam.cli import add_run_arg
    from hsicam.cli.args import MIN_TILE_PX, device_arg, tv_weight_arg
    from hsicam.config import MAX_CONSISTENCY_ITERATIONS, MAX_TV_WEIGHT, MIN_TV_WEIGHT, RECOMMENDED_TV_WEIGHT

    p = sub.add_parser("reconstruct", help="reconstruct a hyperspectral cube from a sensor image or raw capture")
    p.add_argument("sensor", metavar="SENSOR", help="sensor image / raw capture: .npy, 8/16-bit PNG or TIFF")
    add_run_arg(p, "trained (or fine-tuned) run folder")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="output cube: .h5 (ours) or .hdr (ENVI), plus its sRGB preview STEM_rgb.png; a folder holds "
                        "one cube per name (c.h5 and c.hdr would share c_rgb.png: the second is refused); existing "
                        "files are replaced only when they are an earlier reconstruct's output, never an input")
    p.add_argument("--scale", type=float, default=None, help="multiply the image after normalising to [0, 1], > 0")
    p.add_argument("--tile", type=int, default=None, metavar="PX",
                   help=f"tile side for large images, >= {MIN_TILE_PX} (default: 4× the context of the reconstruction "
                        "up to its consistency steps, which then go over the whole image, within 512-1024 px, so that "
                        "a tile's window, its halo included, holds at most 2.25× its own pixels where that fits)")
    p.add_argument("--cfa-offset", type=cfa_offset_arg, default=None, metavar="Y,X|auto",
                   help="the sensor row and column of the capture's first pixel (a crop or a region-of-interest "
                        "readout of the camera's sensor): the CFA phase of every pixel follows from it (default: "
                        "0,0, the capture starts where the sensor does, checked: a warning names the phase when "
                        "another one clearly explains the capture better, since a crop off the CFA period "
                        "reconstructs wrong spectra; give 0,0 to skip the check; a CASSI camera's coded aperture is "
                        "placed the same way); auto: estimated "
                        "from the capture (the CFA phase whose reconstruction the camera images back closest to it; "
                        "not for CASSI), logged and recorded in the cube's metadata")
    p.add_argument("--orientation", type=orientation_arg, default=None, metavar="NAME|auto",
                   help="how the capture as stored relates to the sensor's readout: as-read, flip-lr, flip-ud, rot90 "
                        "(turned 90° counter-clockwise), rot180, rot270, transpose, antitranspose; undone before "
                        "anything else (a --cfa-offset is then the sensor's), and the cube is turned back into the "
                        "capture's frame; dark and flat frames are stored as the capture is (default: as-read, "
                        "checked when no --cfa-offset is given: a warning names an orientation that clearly explains "
                        "the capture better, which catches some misorientations only: docs/hardware.md); auto: the orientation (and CFA phase) whose reconstruction the camera "
                        "images back closest to the capture, 8× the cost of --cfa-offset auto")
    p.add_argument("--device", default="cpu", type=device_arg, help="torch device (default cpu)")
    p.add_argument("--consistency-steps", type=int, default=None, metavar="N",
                   help=f"measurement-consistency steps after the network, 0 to {MAX_CONSISTENCY_ITERATIONS} (default: "
                        "the run's model.consistency.iterations; 0: the network alone)")
    p.add_argument("--tv-steps", type=int, default=None, metavar="N",
                   help=f"N Landweber steps with a total-variation prior, 1 to {MAX_CONSISTENCY_ITERATIONS}, instead of "
                        "the run's own (after its linear step; "
                        "the quick and standard presets take 12): fewer blotches on flat regions, edges kept; against "
                        "two plain steps, 12 steps +0.3 to +1.0 dB on the demo camera in and out of distribution (24: "
                        "+0.4 to +1.4 dB), about 0.11-0.15 s per step for a 512² image on a 2-core CPU (docs/results.md); fewer for "
                        "speed (docs/networks.md, 'A TV prior in the steps')")
    p.add_argument("--tv-weight", type=tv_weight_arg, default=None, metavar="W",
                   help=f"weight of that prior, relative to the local brightness, in [{MIN_TV_WEIGHT:g}, "
                        f"{MAX_TV_WEIGHT:g}]; needs --tv-steps (default {RECOMMENDED_TV_WEIGHT}, chosen on the demo "
                        "camera's training scenes)")
    raw = p.add_argument_group("raw capture corrections (values in the file's digital numbers, DN)")
    raw.add_argument("--black-level", type=float, default=None, metavar="DN",
                     help="sensor black level, >= 0 (default: the dark frame's median, else 0)")
    raw.add_argument("--white-level", type=float, default=None, metavar="DN",
                     help="full-scale value (default: the file type's maximum, e.g. 65535; 1 for float files); "
                          "pixels at or above it (an integer file's, or any file's when given) were clipped: the "
                          "consistency steps take them as lower bounds")
    raw.add_argument("--dark", metavar="FILE", help="dark frame (same exposure and size), subtracted pixel by pixel")
    raw.add_argument("--flat", metavar="FILE", help="flat-field frame (same size), normalised to mean 1")
    raw.add_argument("--flat-mode", choices=("pixel", "cfa"), default="pixel",
                     help="pixel (default): divide pixel by pixel (a flat of the bare sensor); cfa: average the flat "
                          "over the CFA period first (a flat taken through the CFA: corrects vignetting, keeps the CFA "
                          "pattern; needs --flat)")
    raw.add_argument("--exposure-s", type=float, default=None,
                     help="exposure time of the capture (s), > 0; needs --reference-exposure-s")
    raw.add_argument("--reference-exposure-s", type=float, default=None,
                     help="exposure the network's scale corresponds to (s), > 0: the image is multiplied by "
                          "reference/exposure; needs --exposure-s")
    raw.add_argument("--auto-level", type=float, default=None, metavar="V",
                     help="scale so the 99.9th percentile equals V, > 0 (captures of unknown radiometric scale); not "
                          "with --scale, --exposure-s or --reference-exposure-s")
    noise = p.add_argument_group(
        "capture noise (the measurement-consistency steps weigh each residual against it; default: the run's "
        "camera.sensor model, noise-free for the presets)")
    noise.add_argument("--full-well-e", type=float, default=None, metavar="E",
                       help="electrons at the white level (the capture's photon level): shot noise g/E plus read noise "
                            "on the image as reconstructed, after any --scale, exposure or --auto-level gain")
    noise.add_argument("--read-noise-e", type=float, default=None, metavar="R",
                       help="read noise, electrons rms (needs --full-well-e; default 0)")
    p.add_argument("--psf-dir", metavar="DIR", help="measured PSFs of the camera (checked against the run; see hsicam finetune)")
    p.add_argument("--psf-pitch-um", type=float, default=None,
                   help="pixel pitch of the measured PSF images of --psf-dir (else psf.json); needs --psf-dir")
    p.set_defaults(func=cmd_reconstruct)


#: The largest row or column ``--cfa-offset Y,X`` takes: the sensor position of a capture's first pixel, and no sensor
#: has 65536 rows or columns (the largest have about 14 000). Beyond it an offset was accepted whatever its size: a
#: CFA camera took it modulo its cells (2^70,0 reconstructed as 0,0), a CASSI camera drew its coded aperture up to it
#: (an out-of-memory error, or an OverflowError traceback).
MAX_CFA_OFFSET = 2**16 - 1


def cfa_offset_arg(text: str) -> tuple[int, int] | str:
    """argparse ``type`` of ``--cfa-offset Y,X``: two integers in [0, :data:`MAX_CFA_OFFSET`], or ``"auto"``."""
    if text.strip().lower() == "auto":
        return "auto"
    parts = text.replace(" ", "").split(",")
    try:
        y, x = (int(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected Y,X (two integers >= 0, the sensor row and column of the "
                                         f"capture's first pixel) or auto, got {text!r}") from None
    if y < 0 or x < 0:
        raise argparse.ArgumentTypeError(f"Y and X must be >= 0, got {text!r}")
    if max(y, x) > MAX_CFA_OFFSET:
        raise argparse.ArgumentTypeError(f"Y and X must be at most {MAX_CFA_OFFSET} (the sensor row and column of the "
                                         f"capture's first pixel; no sensor is that large), got {text!r}")
    return y, x


def orientation_arg(text: str) -> str:
    """argparse ``type`` of ``--orientation``: one of :data:`hsicam.engine.orientation.ORIENTATIONS`, or ``"auto"``."""
    from hsicam.engine.orientation import ORIENTATIONS

    name = text.strip().lower()
    if name != "auto" and name not in ORIENTATIONS:
        raise argparse.ArgumentTypeError(f"expected one of {', '.join(ORIENTATIONS)} (how the capture as stored "
                                         f"relates to the sensor's readout) or auto, got {text!r}")
    return name


def estimated_cfa_offset(model, sensor: torch.Tensor, est=None) -> tuple[tuple[int, int], dict]:
    """``--cfa-offset auto``: (Y, X) estimated from the capture, logged (a warning when ambiguous),
    and the estimate's record for the cube's metadata. ``est``: the estimate when already made (``--orientation
    auto`` scores the phases of each orientation)."""
    from hsicam.engine.cfa_offset import MIN_SCORED_PX, estimate_cfa_offset

    from hsicam.engine.cfa_offset import NarrowBandCapture

    try:
        # asked for: however long it takes, counted
        est = estimate_cfa_offset(model, sensor, progress=None) if est is None else est
    except NarrowBandCapture as e:  # its phase scores are meaningless: the best one made 660 nm light read as 420 nm
        raise InputError(f"--cfa-offset auto: {e}; give the sensor row and column of the capture's first pixel with "
                         "--cfa-offset Y,X (0,0 where the sensor starts), e.g. measured on a capture of a broadband, "
                         "textured target") from None
    (oy, ox), best = est.offset, est.residuals[f"{est.offset[0]},{est.offset[1]}"]
    second, r2 = est.runner_up
    log.info("--cfa-offset auto: %d,%d (relative residual %.3g; next best %s: %.3g; scored on the central %d×%d px)",
             oy, ox, best, second, r2, *est.scored_px)
    if est.ambiguous:
        log.warning("--cfa-offset auto: %d,%d is barely better than the other phases (residual %.4g; the median "
                    "candidate's is only %.0f%% higher): the capture may be too dark, noisy or featureless to tell; if "
                    "its spectra look wrong, measure the offset (e.g. on a capture of a textured, colourful target) and "
                    "give it with --cfa-offset Y,X", oy, ox, best, 100 * min(est.contrast, 99.0))
    elif est.close_runner_up:  # two phases apart from the rest: the median does not see it
        log.warning("--cfa-offset auto: %d,%d explains the capture barely better than %s (residual %.4g against "
                    "%.4g): check the reconstruction's spectra, or measure the offset and give it with "
                    "--cfa-offset Y,X", oy, ox, second, best, r2)
    if est.small:  # both when both (docs/hardware.md: a small capture "is warned about too")
        log.warning("--cfa-offset auto: %d,%d was scored on only %d×%d px (the capture less the camera's PSF reach), "
                    "under the %d px a side on which it was reliable in tests: check the reconstruction's spectra, or "
                    "give the offset with --cfa-offset Y,X", oy, ox, *est.scored_px, MIN_SCORED_PX)
    return est.offset, est.as_dict()


def checked_sensor_origin(model, sensor: torch.Tensor, source, check_orientation: bool = False) -> dict | None:
    """No ``--cfa-offset``: the capture is taken to start where the sensor does (CFA phase 0,0), and checked.
    The phases are scored as ``auto`` does, on the central :data:`~hsicam.engine.cfa_offset.CHECK_WINDOW_PX` px
    (wider where the camera's PSF reach leaves fewer than ``MIN_SCORED_PX`` px to score);
    when another phase clearly explains the capture better (:attr:`~hsicam.engine.cfa_offset.CfaOffsetEstimate.
    rules_out_origin`) a warning names it (a crop reconstructed at the wrong phase has wrong spectra, without a
    word before). Returns the check's record for the cube's metadata; None when the capture is too small or dark
    to tell (an INFO line says so: 0,0 is taken, as before); ``{"checked": False, "projected_s": …}`` when the check would
    take longer than :data:`~hsicam.engine.cfa_offset.CHECK_TIME_BUDGET_S` (stopped after its first phase; an INFO
    line says so and what to give instead). ``check_orientation`` (no ``--orientation`` given): the capture's
    orientation is checked too, when its best phase is not 0,0
    (:func:`~hsicam.engine.orientation.check_orientation_at_origin`): a warning names an orientation that explains it
    clearly better (``orientation_check`` in the record)."""
    from hsicam.engine.cfa_offset import (CHECK_TIME_BUDGET_S, CHECK_WINDOW_PX, MIN_SCORED_PX, EstimateTooSlow,
                                          NarrowBandCapture, estimate_cfa_offset)

    try:
        est = estimate_cfa_offset(model, sensor, CHECK_WINDOW_PX, min_scored_px=MIN_SCORED_PX,
                                  time_budget_s=CHECK_TIME_BUDGET_S)
    except EstimateTooSlow as e:  # a check the user did not ask for must not cost minutes
        log.info("CFA phase 0,0 (no --cfa-offset) not checked: %s, over the check's %.0f s; give the sensor row and "
                 "column of the capture's first pixel with --cfa-offset Y,X (0,0 where the sensor starts), or "
                 "--cfa-offset auto to estimate it", e, CHECK_TIME_BUDGET_S)
        return {"checked": False, "projected_s": round(e.projected_s, 1)}
    except NarrowBandCapture as e:  # no phase score means anything there (aligned monochromatic fields were "clearly" off)
        log.info("CFA phase 0,0 (no --cfa-offset) not checked: %s; if the capture is a crop or a region-of-interest "
                 "readout, give the sensor row and column of its first pixel with --cfa-offset Y,X", e)
        return {"checked": False, "narrow_band": True, "phase_ratio": e.phase_ratio}
    except InputError as e:  # too small or black to tell: the reconstruction goes on at 0,0, said (it was a debug line)
        log.info("CFA phase 0,0 (no --cfa-offset) not checked: %s; if the capture is a crop or a region-of-interest "
                 "readout, give the sensor row and column of its first pixel with --cfa-offset Y,X", e)
        return None
    turned = misorientation_check(model, sensor, source, est) if check_orientation else None
    if turned is not None and turned["warned"]:  # said by that warning (the phase alone would not fix it)
        return {**est.as_dict(), "warned": est.rules_out_origin, "orientation_check": turned}
    if not est.rules_out_origin:  # quiet: a line on every reconstruction would say nothing to act on
        log.debug("CFA phase 0,0 (no --cfa-offset): %s (scored on the central %d×%d px)",
                  "the capture was too featureless or small to tell" if est.ambiguous or est.small else
                  "no other phase explains the capture clearly better", *est.scored_px)
    else:
        warn_phase_off_origin(source, est)
    record = {**est.as_dict(), "warned": est.rules_out_origin}
    return record if turned is None else {**record, "orientation_check": turned}


def warn_phase_off_origin(source, est, read_as: str | None = None) -> None:
    """The warning of a capture taken at CFA phase 0,0 (no ``--cfa-offset``) whose check ``est`` found another phase
    explaining it clearly better; ``read_as``: the orientation it was read in (``--orientation``). When a second phase
    explains it nearly as well (:attr:`~hsicam.engine.cfa_offset.CfaOffsetEstimate.close_runner_up`) the warning names
    both and asks for the offset itself: the camera cannot read the phase from this capture, and ``auto`` would only
    take the first (session 76's hunt: the demo camera's crop at 2,2 was "clearly" at 0,1, next best 3,1 within 8 %,
    and following the advice took 34.8 dB to 28.8 dB; 2,2 given: 41.1 dB)."""
    oy, ox = est.offset
    best, origin = est.residuals[f"{oy},{ox}"], est.residuals["0,0"]
    start = (f"{source}: {f'read as {read_as}, ' if read_as else ''}the capture does not look as if it started where "
             "the sensor does (CFA phase 0,0, taken without --cfa-offset): ")
    if est.close_runner_up:
        second, r2 = est.runner_up
        log.warning("%sthe phases %d,%d and %s explain it clearly better than 0,0 but about equally (relative residual "
                    "%.3g and %.3g against %.3g), so its spectra are likely wrong and this camera cannot read its phase "
                    "from it (--cfa-offset auto would take %d,%d, which may be wrong too); if it is a crop or a "
                    "region-of-interest readout, give the sensor row and column of its first pixel with --cfa-offset "
                    "Y,X; --cfa-offset 0,0 takes it as given", start, oy, ox, second, best, r2, origin, oy, ox)
        return
    log.warning("%sthe phase %d,%d explains it clearly better (relative residual %.3g against %.3g), so its spectra are "
                "likely wrong; if it is a crop or a region-of-interest readout, give the sensor row and column of its "
                "first pixel with --cfa-offset Y,X, or --cfa-offset auto (%d,%d here); --cfa-offset 0,0 takes it as "
                "given", start, oy, ox, best, origin, oy, ox)


def misorientation_check(model, sensor: torch.Tensor, source, est) -> dict | None:
    """The orientation check of a capture reconstructed without ``--orientation`` (after its CFA check ``est``):
    :func:`~hsicam.engine.orientation.check_orientation_at_origin`, and a warning naming another orientation when it
    explains the capture at least :data:`~hsicam.engine.orientation.MIN_ORIENTATION_RATIO` times better than the
    capture as read at its best phase. The record for the cube's metadata (``warned``), None when not scored."""
    from hsicam.engine.orientation import MIN_ORIENTATION_RATIO, check_orientation_at_origin

    if est.ambiguous or est.small:  # a featureless or small capture tells no orientation either
        return None
    found = check_orientation_at_origin(model, sensor, est, est.window[2])
    if found is None:
        return None
    warned = found["residual"] * MIN_ORIENTATION_RATIO <= found["as_read_best"]
    if warned:
        log.warning("%s: the capture does not look as if it were stored as the sensor reads it out: read as %s (a "
                    "mirrored or rotated readout, e.g. flipped by the camera's software or saved rotated) it is "
                    "explained clearly better (relative residual %.3g against %.3g at its best CFA phase as read), so "
                    "its spectra are likely wrong; give --orientation %s, or --orientation auto to score all "
                    "orientations and phases; --orientation as-read takes it as given", source, found["orientation"],
                    found["residual"], found["as_read_best"], found["orientation"])
    return {**found, "warned": warned}


def offset_reconstructor(fn, offset: tuple[int, int]):
    """``fn(sensor, origin)`` of a capture whose first pixel is the sensor pixel ``offset`` (row,
    column): every window's origin is shifted by it, so the CFA phase of each pixel is the sensor's."""
    if tuple(offset) == (0, 0):
        return fn
    oy, ox = int(offset[0]), int(offset[1])

    def shifted(sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        return fn(sensor, (origin[0] + oy, origin[1] + ox))

    shifted.context_px = fn.context_px
    shifted.tileable = getattr(fn, "tileable", True)
    if hasattr(fn, "steps"):  # the stages reconstruct_tiled takes apart, shifted alike
        shifted.before_steps = offset_reconstructor(fn.before_steps, offset)

        def steps(sensor: torch.Tensor, x: torch.Tensor, origin: tuple[int, int] = (0, 0), on_step=None):
            return fn.steps(sensor, x, (origin[0] + oy, origin[1] + ox), on_step)

        steps.count = fn.steps.count
        shifted.steps = steps
    return shifted


#: The suffixes of a cube file that reconstruct writes: our HDF5, an ENVI header or its data file.
CUBE_SUFFIXES = (".h5", ".hdf5", ".hdr", ".img", ".raw")


def output_files(path: Path) -> list[Path]:
    """The files a reconstruction writes: the cube (ENVI: header and data), then the preview."""
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        files = [path]
    else:  # as hsicam.data.formats.write_envi names the pair
        files = [path, path.with_suffix(".img")] if suffix == ".hdr" else [path.with_suffix(".hdr"), path]
    return [*files, path.with_name(f"{path.stem}_rgb.png")]


def check_one_cube_per_name(path: Path) -> None:
    """InputError when another cube of the same name lies beside ``path`` (``c.h5`` beside ``c.hdr``):
    both have the preview ``c_rgb.png`` (ENVI pairs also the header ``c.hdr``), so writing this one
    would replace the other's without a word. This cube's own files (:func:`output_files`) are
    judged by :func:`check_replaceable_outputs`: replaced only when they are its earlier output."""
    own = set(output_files(path))
    others = [q for q in (path.with_suffix(s) for s in CUBE_SUFFIXES) if q not in own and q.exists()]
    if others:
        preview = output_files(path)[-1].name
        raise InputError(f"{path}: {others[0].name} beside it is another cube named {path.stem}; both would have the "
                         f"preview {preview}, and this one would replace it: choose another --out name (a folder "
                         f"holds one cube per name) or remove {others[0].name}")


def check_outputs_are_not_inputs(path: Path, inputs: dict[str, str | None]) -> None:
    """InputError when a file that reconstructing to ``path`` writes (the cube, ENVI's pair, the
    preview ``STEM_rgb.png``) is one of the files it reads: ``inputs`` maps how each input is named
    ("the capture SENSOR", "the --dark frame" …) to its path (None: not given)."""
    from hsicam.io import same_path

    files = output_files(path)
    for f in files:
        role = "preview" if f == files[-1] else "cube"
        for what, given in inputs.items():
            if given is not None and f.exists() and same_path(f, given):
                shown = what if Path(given) == f else f"{what} {given} (the same file)"
                raise InputError(f"{f}: is {shown}, which reconstruct reads; the {role} of --out {path} would be "
                                 f"written over it: choose another --out name")


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _envi_data_size(h: dict[str, str]) -> int | None:
    """Bytes of the data file that the ENVI header ``h`` (float32, as reconstruct writes) describes."""
    try:
        return int(h["samples"]) * int(h["lines"]) * int(h["bands"]) * 4 if h.get("data type") == "4" else None
    except (KeyError, ValueError):
        return None


def check_replaceable_outputs(path: Path) -> None:
    """InputError unless every existing file that reconstructing to ``path`` writes is the earlier
    output of a reconstruction to ``path``: our HDF5 cube whose metadata names a capture and a run;
    an ENVI header that reconstruct wrote and the data file it describes (its size, or any data file
    when the header records the data's CRC-32: the pair is ours); the preview (an 8-bit RGB PNG) only
    beside such a cube. A user's file at any of these paths is never replaced."""
    from hsicam.data.formats import ENVI_CRC_KEY

    files = output_files(path)
    cube = files[0]
    suffix = path.suffix.lower()
    ours_cube = False
    if suffix in (".h5", ".hdf5"):
        if cube.exists():
            if not is_reconstruct_h5(cube):
                raise InputError(f"{cube}: exists and is not a cube that hsicam reconstruct wrote; reconstruct replaces "
                                 f"only its own earlier output: choose another --out name or move {cube.name} away")
            ours_cube = True
    else:
        hdr, data = files[0], files[1]
        header = None
        if hdr.exists():
            header = reconstruct_envi_header(hdr)
            if header is None:
                raise InputError(f"{hdr}: exists and is not an ENVI header that hsicam reconstruct wrote; reconstruct "
                                 f"replaces only its own earlier output: choose another --out name or move {hdr.name} away")
            ours_cube = True
        if data.exists() and not (header is not None and ENVI_CRC_KEY in header):
            # (a header that records its data's CRC-32 claims the pair: its data file is ours even when an
            # interrupted write left a new one of another size beside it, which read_envi refuses to read)
            size = _envi_data_size(header) if header is not None else None
            try:
                actual = data.stat().st_size
            except OSError:
                actual = -1
            if header is None or size != actual:
                why = (f"its header {hdr.name} is missing" if header is None else
                       f"{hdr.name} does not describe its size (samples, lines and bands of data type 4)"
                       if size is None else
                       f"its size ({actual} bytes) is not the {size} bytes that {hdr.name} describes")
                raise InputError(f"{data}: exists and is not the ENVI data of a cube that hsicam reconstruct wrote "
                                 f"({why}); reconstruct replaces only its own earlier output: choose another --out name "
                                 f"or move {data.name} away")
    preview = files[-1]
    if preview.exists():
        if not ours_cube:
            raise InputError(f"{preview}: exists, but no cube {cube.name} that hsicam reconstruct wrote lies beside it, "
                             f"so it is not the preview of an earlier reconstruction to {path.name}; choose another "
                             f"--out name or move {preview.name} away")
        png_head = head(preview, 26)
        if not (png_head.startswith(_PNG_MAGIC) and png_head[12:16] == b"IHDR" and png_head[24:26] == b"\x08\x02"):
            raise InputError(f"{preview}: exists and is not an sRGB preview (an 8-bit RGB PNG) that hsicam reconstruct "
                             f"wrote; choose another --out name or move {preview.name} away")


def check_outputs(path: Path, inputs: dict[str, str | None]) -> None:
    """Every check of reconstruct's output files (before the work, and again just before writing):
    none is an input, one cube per name, and existing ones are its own earlier output."""
    check_outputs_are_not_inputs(path, inputs)
    check_one_cube_per_name(path)
    check_replaceable_outputs(path)


#: Bytes a cube file holds besides its pixels (HDF5 headers, band centres, metadata; an ENVI header), at most.
CUBE_FILE_OVERHEAD_BYTES = 1 << 20


def cube_file_bytes(n_bands: int, height: int, width: int) -> int:
    """Bytes, at most, of what reconstructing a (n_bands, height, width) cube writes: the
    float32 cube and its file's overhead, and the preview (3 bytes a pixel: an upper bound of the PNG)."""
    return 4 * n_bands * height * width + CUBE_FILE_OVERHEAD_BYTES + 3 * height * width + (1 << 16)


def check_room_for_cube(path: Path, n_bands: int, height: int, width: int) -> None:
    """InputError when the file system of ``path`` has less free space than the output
    (:func:`cube_file_bytes`) and a margin (a tenth, at least 64 MiB): checked before the reconstruction
    (minutes for a large capture) rather than found by a full disk at its end. Files replaced are not
    counted as freed: each is written beside the old one before it takes its place."""
    from hsicam.io import free_space_short, free_space_text

    need = cube_file_bytes(n_bands, height, width)
    free = free_space_short(path, need)
    if free is not None:
        raise InputError(f"{path}: the cube of {n_bands} bands × {height}×{width} px and its preview need "
                         f"{free_space_text(need, free, path=path)}; free some space or choose an --out on a larger disk")


def write_cube_file(path: Path, cube: np.ndarray, bands, metadata: dict) -> float:
    """Our HDF5 (.h5) or ENVI (.hdr) by extension, plus an sRGB preview ``<stem>_rgb.png``; ``metadata``
    (with ``command``: reconstruct) goes into the HDF5's ``metadata_json`` or the ENVI header's
    ``hsicam metadata`` line (:data:`hsicam.data.formats.ENVI_METADATA_KEY`). The preview is exposed as every
    display preview is (its 99th-percentile luminance at :data:`hsicam.color.PREVIEW_LEVEL` of white,
    :func:`hsicam.color.preview_exposure`; before session 67 it was the absolute render, nearly black for a dim
    capture): the gain is recorded in its PNG text chunk :data:`hsicam.color.PREVIEW_EXPOSURE_KEY` and in
    the metadata (``preview_exposure``), and returned."""
    from hsicam.color import PREVIEW_EXPOSURE_KEY, preview_exposure, srgb_preview
    from hsicam.data.formats import write_cube_h5, write_envi
    from hsicam.io import atomic_path, write_png8

    suffix = path.suffix.lower()
    if suffix not in CUBE_SUFFIXES:
        raise InputError(f"{path}: output must end in .h5 (HDF5) or .hdr (ENVI)")
    exposure = preview_exposure(cube, bands)
    rgb = srgb_preview(cube, bands, exposure=exposure)  # before any file is written
    preview = path.with_name(f"{path.stem}_rgb.png")
    # ENVI's header keeps what the HDF5 keeps (write_envi)
    metadata = {"command": "reconstruct", **metadata, "preview_exposure": exposure}
    # The preview is written first, to a hidden temporary, and takes its place only after the cube has taken its own
    # (each written whole beside the file it replaces): a stop (Ctrl-C, SIGTERM, a full disk) before the cube's
    # rename leaves an earlier reconstruction's cube and preview as they were. (Before session 70 the earlier preview
    # was deleted first, and the new cube deleted when its preview's write stopped: a stop lost the earlier pair.)
    with atomic_path(preview) as preview_tmp:
        write_png8(preview_tmp, rgb, text={PREVIEW_EXPOSURE_KEY: f"{exposure:.6g}"})  # written and synced
        if suffix in (".h5", ".hdf5"):
            write_cube_h5(path, cube, bands, metadata)
        else:  # a stop between its two files removes the data file it put there (write_envi): none is left alone
            write_envi(path, cube, bands, description=ENVI_DESCRIPTIONS[0], metadata=metadata)
    return exposure


def check_reconstruction_memory(rec, bands: int, shape: tuple[int, int], tile: int | None, source) -> None:
    """One-line :class:`InputError` when reconstructing an image of ``shape`` would need more memory than the
    process may take (:func:`hsicam.engine.inference.memory_shortfall`, the limit named): the steps go over the
    whole image, so its peak grows with the image, whatever the tile (it was killed, or ended in torch's allocator
    traceback)."""
    from hsicam.engine.inference import memory_shortfall, reconstruction_memory_bytes
    from hsicam.memory import format_bytes

    short = memory_shortfall(lambda h, w: reconstruction_memory_bytes(rec, bands, h, w, tile), shape)
    if short is None:
        return
    h, w = shape
    lo = short.fits_px
    todo = (f"reconstruct it in parts of at most about {lo}×{lo} px (crop the capture; --cfa-offset gives each part's "
            "CFA phase)" if lo >= 64 else "even a small part would not fit: run it where more memory is free")
    raise InputError(f"{source}: reconstructing {h}×{w} px into {bands} bands takes about {format_bytes(short.need)} of "
                     f"memory (whole-image cubes for the consistency steps, and one tile's window), more than "
                     f"{short.limit} ({format_bytes(short.have)}); {todo}, or with fewer steps (--consistency-steps 0)")


def corrections_from_args(args: argparse.Namespace, cfa_period: int | None) -> "object":
    """A :class:`~hsicam.engine.inference.RawCorrection` from the command line."""
    from hsicam.data.images import RawCorrection, read_image_2d

    # the frames as read (RawImage): their stored type is checked against the capture's
    dark = read_image_2d(args.dark, "dark frame") if args.dark else None
    flat = read_image_2d(args.flat, "flat field") if args.flat else None
    period = None
    if args.flat_mode == "cfa":  # with a --flat: check_level_options
        period = cfa_period or 1
    return RawCorrection(black_level=args.black_level, white_level=args.white_level, dark=dark, flat=flat,
                         flat_period=period, cfa_period=cfa_period, exposure_s=args.exposure_s, reference_exposure_s=args.reference_exposure_s,
                         auto_level=args.auto_level, scale=1.0)


def check_level_options(args: argparse.Namespace) -> None:
    """Before any work (the run not loaded, no frame read): the library's rules
    (:class:`~hsicam.data.images.RawCorrection`) for the level options: black and white levels, the two
    exposures together or neither, ``--auto-level`` as the level's only source (neither exposures nor
    ``--scale`` beside it), ``--flat-mode cfa`` only with a ``--flat``."""
    from hsicam.data.images import RawCorrection

    if args.flat_mode == "cfa" and not args.flat:
        raise InputError("--flat-mode cfa needs --flat (the flat field it averages per CFA phase)")
    RawCorrection(black_level=args.black_level, white_level=args.white_level, exposure_s=args.exposure_s,
                  reference_exposure_s=args.reference_exposure_s, auto_level=args.auto_level,
                  scale=1.0 if args.scale is None else args.scale)


def check_noise_args(args: argparse.Namespace) -> None:
    """Before any work: --full-well-e a positive number in the range of ``camera.sensor.full_well_e``, --read-noise-e
    one >= 0, at most the full well (as ``camera.sensor.read_noise_e``) and only beside it: a full well of 1e-300 e-
    or a read noise of 1e308 e- overflowed the noise variance (r/E)² in an OverflowError traceback."""
    from hsicam.config import MAX_FULL_WELL_E, MAX_SENSOR_SIGMA, MIN_FULL_WELL_E

    if args.read_noise_e is not None and args.full_well_e is None:
        raise InputError("--read-noise-e needs --full-well-e (the electrons at the white level), which sets the "
                         "capture's noise model")
    if args.full_well_e is not None and not (np.isfinite(args.full_well_e) and args.full_well_e > 0):
        raise InputError(f"--full-well-e must be a positive number of electrons, got {args.full_well_e:g}")
    if args.full_well_e is not None and not MIN_FULL_WELL_E <= args.full_well_e <= MAX_FULL_WELL_E:
        raise InputError(f"--full-well-e must be a positive number of electrons in [{MIN_FULL_WELL_E:g}, "
                         f"{MAX_FULL_WELL_E:g}] (at the white level; sensors hold 10^3 to 10^6, as "
                         f"camera.sensor.full_well_e), got {args.full_well_e:g}")
    if args.read_noise_e is not None and not (np.isfinite(args.read_noise_e) and args.read_noise_e >= 0):
        raise InputError(f"--read-noise-e must be a number of electrons >= 0, got {args.read_noise_e:g}")
    if args.read_noise_e is not None and args.read_noise_e > MAX_SENSOR_SIGMA * args.full_well_e:
        raise InputError(f"--read-noise-e must be at most --full-well-e ({args.full_well_e:g} e-: read noise above the "
                         f"full scale buries any signal, as camera.sensor.read_noise_e), got {args.read_noise_e:g}")


def capture_noise(model, report: dict, full_well_e: float, read_noise_e: float, corr=None,
                  offset: tuple[int, int] = (0, 0), orientation: str = "as-read") -> dict:
    """Give ``model``'s camera the Poisson–Gaussian noise of a capture with ``full_well_e`` electrons at the
    white level and ``read_noise_e`` of read noise, on the image as :func:`~hsicam.data.images.read_capture`
    returned it (``report``): the gain it applied after normalising to [0, 1] (exposure ratio ×
    auto-level × --scale) divides the full well, since an image g = f·e/E has variance f·g/E + (f·r/E)².
    A flat field of ``corr`` (the :class:`~hsicam.data.images.RawCorrection` the image was read with)
    divided each pixel by its flat value F, so there f = 1/F per pixel: the camera's noise gets that gain
    map, placed at the capture's first sensor pixel ``offset`` (its CFA offset). The
    measurement-consistency steps weigh their residuals by that variance; the flat, stored as the capture is, is
    turned as the capture was (``orientation``, :func:`hsicam.engine.orientation.to_sensor`). Returns the cube
    metadata that records it."""
    import torch

    from hsicam.data.images import frame_data, normalised_flat
    from hsicam.sensor import SensorNoise

    factor = float(report["gain"]) * (float(report["white_level_dn"]) - float(report["black_level_dn"]))
    gain = None
    if corr is not None and corr.flat is not None:
        flat = normalised_flat(frame_data(corr.flat), float(report["black_level_dn"]), corr.flat_period)
        from hsicam.engine.orientation import to_sensor

        gain = torch.from_numpy(np.ascontiguousarray(to_sensor(1.0 / flat, orientation)))
    # quantisation is not modelled: a DN step's Δ²/12 is far below the read noise of a 12-bit or deeper capture
    model.camera.noise = SensorNoise("poisson_gaussian", full_well_e=full_well_e / factor, read_noise_e=read_noise_e,
                                     gain=gain, gain_origin=tuple(offset))
    if not model.consistency_on:
        log.warning("--full-well-e only weighs the measurement-consistency steps, which are off here: it changes "
                    "nothing")
    elif not model.consistency.noise_aware:
        log.warning("--full-well-e changes nothing: the run's model.consistency.noise_aware is off")
    return {"noise_full_well_e": full_well_e, "noise_read_noise_e": read_noise_e,
            "noise_full_well_e_at_image_scale": full_well_e / factor, "noise_flat_field_gain": gain is not None}


def capture_saturation(model, saturated: np.ndarray, offset: tuple[int, int] = (0, 0)) -> dict:
    """Give ``model``'s camera the capture's clipped pixels (``saturated``, (H, W) bool from
    :func:`~hsicam.data.images.read_capture`), placed at its first sensor pixel ``offset``: the
    measurement-consistency steps then take the capture there as a lower bound of the light
    (:func:`hsicam.models.consistency.clipped_residual`), not as its value. Returns the cube metadata that records
    it ({} when no pixel is clipped)."""
    import torch

    count = int(np.count_nonzero(saturated))
    # (none clipped: a map set before, e.g. of another capture through the same model, is cleared)
    model.camera.noise.mark_saturated(torch.from_numpy(np.ascontiguousarray(saturated)) if count else None,
                                      tuple(offset))
    if not count:
        return {}
    if not model.consistency_on:
        log.info("%d clipped pixel(s) reach the network as they are: the measurement-consistency steps, which would "
                 "take them as lower bounds, are off", count)
    return {"clipped_px_as_lower_bounds": count if model.consistency_on else 0}


def psf_mismatch_message(args: argparse.Namespace, measured, fine_tuned: bool) -> str:
    """The warning for ``--psf-dir`` PSFs other than those the network of ``--run`` was fine-tuned on:
    when the run was fine-tuned on the same folder, what differs (the pixel pitch, naming both, …)."""
    from hsicam.runs.folder import finetune_source
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE, load_measured_psf, psf_difference

    diff = None
    source = None
    if fine_tuned:
        try:
            diff = psf_difference(load_measured_psf(Path(args.run) / MEASURED_PSF_FILE), measured, args.psf_dir)
        except InputError:  # only a better message: an unreadable file keeps the plain one
            diff = None
        source = finetune_source(Path(args.run))[0]
    from hsicam.runs.pretrained import run_label

    run = run_label(args.run)  # a shipped camera by its pretrained:NAME, not its folder inside the package
    base = (source or "ORIGINAL_RUN") if fine_tuned else run  # fine-tuning starts from the design run
    if diff is None:
        return (f"the network of {run} was not fine-tuned on the PSFs of {args.psf_dir}; run `hsicam finetune "
                f"--run {base} --psf-dir {args.psf_dir} --out RUN2` and reconstruct with RUN2")
    what, why = diff
    if what == "pixel_pitch_um":
        tuned_pitch = load_measured_psf(Path(args.run) / MEASURED_PSF_FILE).report["pixel_pitch_um"]
        now = "--psf-pitch-um" if args.psf_pitch_um is not None else f"pixel_pitch_um in {Path(args.psf_dir) / 'psf.json'}"
        pitch = measured.report["pixel_pitch_um"]
        return (f"the PSFs of {args.psf_dir} differ from the ones the network of {run} was fine-tuned on: the same "
                f"folder, but read at pixel pitch {pitch:g} µm ({now}) instead of the {tuned_pitch:g} µm it was "
                f"fine-tuned with; reconstruct with --psf-pitch-um {tuned_pitch:g} if that is the images' pitch, or "
                f"fine-tune for this one: `hsicam finetune --run {base} --psf-dir {args.psf_dir} --psf-pitch-um "
                f"{pitch:g} --out RUN2` and reconstruct with RUN2")
    return (f"the PSFs of {args.psf_dir} differ from the ones the network of {run} was fine-tuned on (the same "
            f"folder): {why}; fine-tune again: `hsicam finetune --run {base} --psf-dir {args.psf_dir} --out RUN2` and "
            "reconstruct with RUN2")


def check_tv_args(args: argparse.Namespace, max_steps: int) -> None:
    """One-line InputError for --tv-steps out of [1, max_steps], --tv-weight without --tv-steps, or --tv-steps with
    --consistency-steps 0."""
    if args.tv_weight is not None and args.tv_steps is None:
        raise InputError("--tv-weight is the weight of the --tv-steps' prior: give --tv-steps N too")
    if args.tv_steps is None:
        return
    if not 1 <= args.tv_steps <= max_steps:
        raise InputError(f"--tv-steps must be >= 1 and <= {max_steps}, got {args.tv_steps}")
    if args.consistency_steps == 0:
        raise InputError("--tv-steps adds measurement-consistency steps and --consistency-steps 0 removes them: give one")


def tv_consistency(model, args: argparse.Namespace):
    """``model.consistency`` with ``args.tv_steps`` Landweber steps carrying the TV prior of ``args.tv_weight``
    (default :data:`hsicam.config.RECOMMENDED_TV_WEIGHT`): a run of kind linear takes them after its linear step
    (``landweber_after``; the linear step on, ``--consistency-steps`` times), a run of kind landweber takes them as
    its steps (``iterations``; with ``--consistency-steps`` too, the two options would name its steps twice).
    InputError where they cannot apply: the linear step off in the run, or a camera the steps skip."""
    from hsicam.config import RECOMMENDED_TV_WEIGHT

    if not model.camera_takes_consistency:  # (before consistency_on, which would warn of the skip first)
        raise InputError(f"--tv-steps: the measurement-consistency steps do not apply to this run's camera "
                         f"(camera.kind={model.camera.kind}); drop --tv-steps")
    c = model.consistency
    weight = RECOMMENDED_TV_WEIGHT if args.tv_weight is None else args.tv_weight
    if c.kind == "linear":
        if c.iterations == 0:
            raise InputError("--tv-steps follow the run's linear consistency step, which is off "
                             "(model.consistency.iterations=0): give --consistency-steps 1 too")
        tuned = dataclasses.replace(c, tv_weight=weight, landweber_after=args.tv_steps)
    else:
        if args.consistency_steps is not None:
            raise InputError(f"--tv-steps and --consistency-steps both give the steps of this run (model.consistency."
                             f"kind={c.kind}): give --tv-steps alone")
        tuned = dataclasses.replace(c, tv_weight=weight, iterations=args.tv_steps)
    model.consistency = tuned
    return tuned


def cmd_reconstruct(args: argparse.Namespace) -> int:
    """``hsicam reconstruct``: every check of the options and output files, the run and capture read, the cube
    reconstructed tile by tile, then the cube file and its preview written."""
    import torch  # here, not with the module: the parser is built without torch (hsicam.cli.camera)

    from hsicam.data.images import read_capture
    from hsicam.engine.inference import reconstruct_tiled

    _check_options(args)
    out, inputs = _checked_output(args)
    _check_step_options(args)
    cfg, model = _loaded_model(args)
    meta = _consistency_metadata(args, model)
    if args.psf_dir:
        _use_measured_psfs(args, model, meta)
    # a CFA only on a DOE camera: a CASSI config keeps the (unused) cfa section of the defaults, enabled
    cfa_period = cfg.camera.cfa.period if cfg.camera.kind == "doe" and cfg.camera.cfa.enabled else None
    corr = corrections_from_args(args, cfa_period)
    # a CASSI camera of convention 'sum' adds its bands on the sensor: trained on images up to its band count
    peak = float(getattr(model.camera, "white_peak", 1.0))
    img, report, saturated = read_capture(args.sensor, corr, args.scale, return_saturated=True, trained_peak=peak)
    # which frames corrected it (their statistics alone did not say which files they were)
    report.update({k: str(Path(v).resolve()) for k, v in (("dark_frame", args.dark), ("flat_frame", args.flat)) if v})
    meta["preprocessing"] = report
    period = int(getattr(model.camera, "code_period", 1))
    _check_capture_size(args, img.shape, period)
    check_room_for_cube(out, len(model.bands), *img.shape)  # before the work, which takes minutes at full size
    sensor = torch.from_numpy(img)[None, None].to(args.device)
    # the sensor's readout first (the capture, its clipped pixels and its flat's gain turned alike), then the offset
    # (a check or an estimate on a central window: about a second), then the noise model at it
    orientation, sensor, saturated, estimate = _capture_orientation(args, model, sensor, saturated, period, meta)
    offset = _capture_offset(args, cfg, model, sensor, period, meta, estimate)
    if args.full_well_e is not None:  # after the offset: a flat field's gain map sits at the capture's first pixel
        meta.update(capture_noise(model, report, args.full_well_e, args.read_noise_e or 0.0, corr, offset,
                                  orientation))
    meta.update(capture_saturation(model, saturated, offset))  # after the noise model, which it joins
    del saturated
    # after the noise model, which widens the steps' context (a noise-aware step's halo): the memory is checked here
    fn = offset_reconstructor(_checked_reconstructor(args, model, img.shape), offset)
    cube = reconstruct_tiled(fn, sensor, args.tile, progress=None)[0]  # the halo fn declares
    del sensor
    # Radiance is non-negative: the network's small negative excursions are clipped at 0.
    cube = cube.float().clamp_min_(0).cpu().numpy()
    if orientation != "as-read":  # back into the capture's frame: the cube lies over the file as stored
        from hsicam.engine.orientation import to_capture

        cube = np.ascontiguousarray(to_capture(cube, orientation))
    exposure = _write_outputs(out, inputs, cube, model.bands, meta)
    print(f"reconstructed {cube.shape[0]} bands × {cube.shape[1]}×{cube.shape[2]} -> {out} "
          f"(sRGB preview {output_files(out)[-1].name}, exposed ×{exposure:.3g} for display)")
    return 0


def _check_options(args: argparse.Namespace) -> None:
    """Before any file is touched: one-line InputError for a bad --tile, --scale, level, noise or --psf-pitch-um."""
    from hsicam.cli.args import check_tile

    check_tile(args.tile)
    if args.scale is not None and not (np.isfinite(args.scale) and args.scale > 0):
        raise InputError("--scale must be a positive number")
    check_level_options(args)
    check_noise_args(args)
    if args.psf_pitch_um is not None and not args.psf_dir:
        raise InputError("--psf-pitch-um is the pixel pitch of the measured PSFs of --psf-dir: give --psf-dir DIR "
                         "too, or drop --psf-pitch-um")


def _checked_output(args: argparse.Namespace) -> tuple[Path, dict[str, str | None]]:
    """(``--out``, the inputs by how they are named) once every file the output writes may be written."""
    from hsicam.cli import prepare_output

    out = Path(args.out)
    if out.suffix.lower() not in CUBE_SUFFIXES:
        if not out.suffix and out.name.lower() in CUBE_SUFFIXES:  # '.h5': a hidden name, no suffix (Path's reading)
            raise InputError(f"{out}: names no file before its suffix: give the cube a name, e.g. cube{out.name}")
        raise InputError(f"{out}: output must end in .h5 or .hdf5 (HDF5), or .hdr, .img or .raw (ENVI)")
    for f in output_files(out):  # before any work: an existing folder, a path inside a file, no permission
        prepare_output(f, "file")
    inputs = {"the capture SENSOR": args.sensor, "the --dark frame": args.dark, "the --flat frame": args.flat}
    check_outputs(out, inputs)
    return out, inputs


def _check_step_options(args: argparse.Namespace) -> None:
    """One-line InputError for --consistency-steps, --tv-steps or --tv-weight out of range or at odds."""
    from hsicam.config import MAX_CONSISTENCY_ITERATIONS

    if args.consistency_steps is not None and not 0 <= args.consistency_steps <= MAX_CONSISTENCY_ITERATIONS:
        raise InputError(f"--consistency-steps must be >= 0 and <= {MAX_CONSISTENCY_ITERATIONS} (each step widens "
                         "the tiles' halo; more than one rarely changes the estimate)")
    check_tv_args(args, MAX_CONSISTENCY_ITERATIONS)


def _loaded_model(args: argparse.Namespace):
    """(the run's config, its model) with the consistency steps that --consistency-steps and --tv-steps give."""
    from hsicam.runs.folder import load_run

    cfg, model = load_run(args.run, args.device)
    if args.consistency_steps is not None:
        model.consistency = dataclasses.replace(cfg.model.consistency, iterations=args.consistency_steps)
    if args.tv_steps is not None:
        model.consistency = tv_consistency(model, args)
    return cfg, model


def _consistency_metadata(args: argparse.Namespace, model) -> dict:
    """The cube's first metadata: the capture, the run and the consistency steps taken after its network."""
    from hsicam.runs.pretrained import run_label

    meta: dict = {"source": str(args.sensor), "run": run_label(args.run),
                  "consistency_steps": model.consistency.iterations if model.consistency_on else 0}
    if model.consistency_on and model.consistency.landweber_after:
        meta["consistency_landweber_after"] = model.consistency.landweber_after
        meta["consistency_spectral_prior"] = model.consistency.spectral_prior
    if model.consistency_on and model.consistency.tv_weight > 0:
        meta["consistency_tv_weight"] = model.consistency.tv_weight
    return meta


def _use_measured_psfs(args: argparse.Namespace, model, meta: dict) -> None:
    """``--psf-dir``: the consistency steps of ``model`` explain the capture with the measured PSFs; ``meta``
    records them, and a warning says when the network was not fine-tuned on them."""
    import torch

    from hsicam.cameras.measured import FixedPSFCamera
    from hsicam.data.measured_psf import import_for_camera
    from hsicam.engine.calibration import run_psf_fingerprint

    measured = import_for_camera(args.psf_dir, model.camera, pitch_um=args.psf_pitch_um)
    tuned = run_psf_fingerprint(args.run)
    meta["psf_dir"] = str(args.psf_dir)
    meta["psf_fingerprint"] = measured.fingerprint
    meta["network_tuned_to_psfs"] = tuned == measured.fingerprint
    # the consistency step explains the capture with the measured PSFs (what this camera does); the network
    # still sees the camera it was trained with (load_run: a fine-tuned run's PSFs, else the design's).
    # runs.folder.with_measured_psf would put the measured PSFs under an unrolled network's own data steps too:
    # measured no better, and 2-4.5 dB worse for PSFs it was not tuned to (docs/hardware_log.md, session 63)
    model.step_camera = FixedPSFCamera.from_camera(model.camera, torch.from_numpy(measured.psf))
    if tuned != measured.fingerprint:
        log.warning("%s", psf_mismatch_message(args, measured, tuned is not None))


def _check_capture_size(args: argparse.Namespace, shape: tuple[int, int], period: int) -> None:
    """InputError for a capture smaller than one CFA period (or than 2×2 px)."""
    if min(shape) < max(period, 2):
        raise InputError(f"{args.sensor}: the capture is {shape[0]}×{shape[1]} px, smaller than "
                         f"{'one CFA period' if period > 1 else 'a 2×2 image'} ({max(period, 2)}×{max(period, 2)} px): "
                         "too small to reconstruct")


def _capture_orientation(args: argparse.Namespace, model, sensor: torch.Tensor, saturated: np.ndarray, period: int,
                         meta: dict):
    """(orientation, the capture and its clipped pixels brought back to the sensor's readout, the CFA estimate of
    that orientation when ``--orientation auto`` made one) from ``--orientation``, recorded in ``meta``."""
    from hsicam.engine.cfa_offset import NarrowBandCapture
    from hsicam.engine.orientation import estimate_orientation, to_sensor

    name, estimate = args.orientation, None
    if name is None:
        meta["orientation"] = "as-read"
        return "as-read", sensor, saturated, None  # checked with the CFA phase (checked_sensor_origin)
    if name == "auto":
        if period <= 1:
            raise InputError("--orientation auto reads the orientation from the colour filter array, which this "
                             "camera has not: give --orientation NAME (as-read where the capture is the sensor's "
                             "readout)")
        phases = [args.cfa_offset] if isinstance(args.cfa_offset, tuple) else None  # the phase given: that one only
        try:
            est = estimate_orientation(model, sensor, phases=phases, progress=None)
        except NarrowBandCapture as e:
            raise InputError(f"--orientation auto: {e}; give the orientation with --orientation NAME") from None
        name, estimate = est.orientation, est.estimates[est.orientation]
        second, r2 = est.runner_up
        log.info("--orientation auto: %s (relative residual %.3g at CFA phase %d,%d; next best %s: %.3g)", name,
                 est.residuals[name], *estimate.offset, second, r2)
        if est.close_runner_up:
            log.warning("--orientation auto: %s explains the capture barely better than %s (residual %.4g against "
                        "%.4g): the CFA does not tell them apart here; check the reconstruction's spectra, or give "
                        "the orientation the camera stores its captures in with --orientation NAME", name, second,
                        est.residuals[name], r2)
        meta["orientation_estimate"] = est.as_dict()
    meta["orientation"] = name
    if name != "as-read":
        sensor = to_sensor(sensor, name).contiguous()
        saturated = np.ascontiguousarray(to_sensor(saturated, name))
    return name, sensor, saturated, estimate


def _capture_offset(args: argparse.Namespace, cfg, model, sensor: torch.Tensor, period: int, meta: dict,
                    estimate=None):
    """The sensor row and column of the capture's first pixel (``--cfa-offset``, estimated for auto), recorded in
    ``meta``; (0, 0) for a camera without a CFA. ``estimate``: the CFA phases already scored (``--orientation
    auto``), else scored here."""
    offset = args.cfa_offset
    if period > 1:
        if offset is None and estimate is not None:  # the phases of the orientation chosen, checked at 0,0
            offset = (0, 0)
            if estimate.rules_out_origin:
                warn_phase_off_origin(args.sensor, estimate, meta["orientation"])
            meta["cfa_offset_check"] = {**estimate.as_dict(), "warned": estimate.rules_out_origin}
        elif offset is None:
            offset, check = (0, 0), checked_sensor_origin(model, sensor, args.sensor, args.orientation is None)
            if check is not None:
                meta["cfa_offset_check"] = check
        elif offset == "auto":
            offset, meta["cfa_offset_estimate"] = estimated_cfa_offset(model, sensor, estimate)
        meta["cfa_offset"] = list(offset)
        if tuple(offset) != (0, 0):
            from hsicam.engine.cfa_offset import phase_blind

            if phase_blind(model, tuple(sensor.shape[-2:]), tuple(offset)):
                meta["cfa_offset_used"] = False
                log.info("%s: CFA offset %d,%d changes nothing: this run's reconstruction takes no CFA phase (a "
                         "network that reads the sensor image alone, e.g. the paper's RDN, and no consistency "
                         "steps), so a crop reconstructs as the whole capture does away from its borders",
                         args.sensor, offset[0], offset[1])
    elif cfg.camera.kind != "doe":  # a CASSI camera's coded aperture is taken at the capture's place, as a CFA is
        if offset == "auto":
            raise InputError("--cfa-offset auto estimates the phase of a periodic CFA; this CASSI camera's coded "
                             "aperture has no period: give the sensor row and column of the capture's first pixel, "
                             "--cfa-offset Y,X (0,0: where the sensor starts)")
        offset = (0, 0) if offset is None else offset
        meta["cfa_offset"] = list(offset)
    else:
        if offset not in (None, (0, 0)):
            log.warning("--cfa-offset is ignored: the camera has no colour filter array")
        offset = (0, 0)
    return offset


def _checked_reconstructor(args: argparse.Namespace, model, shape: tuple[int, int]):
    """The model's reconstructor, once the memory it takes for an image of ``shape`` is checked (and a tile
    smaller than its halo warned of); :func:`offset_reconstructor` shifts it to the capture's place."""
    from hsicam.engine.inference import tiled_pixels

    rec = model.reconstructor()
    # the halo of the tiles: what comes before the consistency steps, which then go over the whole image
    halo = rec.before_steps.context_px if hasattr(rec, "steps") else rec.context_px
    tile = args.tile  # None: reconstruct_tiled's default (default_tile_px), never below the halo
    check_reconstruction_memory(rec, len(model.bands), shape, tile, args.sensor)  # before minutes of work
    if tile is not None and tile < halo and max(shape) > tile and getattr(rec, "tileable", True):
        log.warning("--tile %d is smaller than the reconstruction's context (%d px per side): the tiles compute about "
                    "%.0f× the image's pixels; a tile of %d px or more is faster", tile, halo,
                    tiled_pixels(shape, tile, halo) / math.prod(shape), min(2 * halo, max(shape)))
    return rec


def _write_outputs(out: Path, inputs: dict[str, str | None], cube: np.ndarray, bands, meta: dict) -> float:
    """The cube file and its preview, once the output files are checked again (the work may have taken a while);
    returns the preview's exposure."""
    from hsicam.memory import format_bytes

    check_outputs(out, inputs)  # again: the reconstruction may have taken a while
    check_room_for_cube(out, cube.shape[0], *cube.shape[1:])
    log.info("writing %s (%s) and its sRGB preview", out, format_bytes(cube.nbytes))  # a minute at 4096² px
    return write_cube_file(out, cube, bands, meta)
