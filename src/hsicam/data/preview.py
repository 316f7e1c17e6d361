"""Previews of a dataset: a contact sheet of sRGB renders and a plot of mean spectra.

Display rule (previews only, not the data): each cube is normalised by its maximum (the data
policy), rendered with :func:`hsicam.color.cube_to_srgb` (CIE 1931 2°, D65), after an exposure
that puts the 99th percentile of linear luminance at 0.8 so that scenes with a tiny highlight
are still visible.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np

from hsicam.color import TABLE_RANGE_NM, cube_to_srgb, spectra_to_xyz
from hsicam.data.cube import normalize_per_cube_max
from hsicam.data.datasets import list_scenes
from hsicam.data.formats import read_cube
from hsicam.errors import InputError
from hsicam.io import save_figure
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

CONTACT_SHEET = "contact_sheet.png"
MEAN_SPECTRA = "mean_spectra.png"


def preview_rgb(cube: np.ndarray, bands: Bands, max_side: int = 192) -> np.ndarray:
    """Display sRGB (h, w, 3) in [0, 1] of a cube (C, H, W), downsampled to at most ``max_side``."""
    lo, hi = TABLE_RANGE_NM
    keep = (bands.centers_nm >= lo) & (bands.centers_nm <= hi)
    if keep.sum() < 2:
        raise InputError(f"cannot render bands {bands.min_nm:g}-{bands.max_nm:g} nm: fewer than 2 bands in {lo:g}-{hi:g} nm")
    sub = Bands(bands.centers_nm[keep], bands.fwhm_nm[keep])
    c = cube[keep]
    step = max(1, int(math.ceil(max(c.shape[1:]) / max_side)))
    if step > 1:  # area average over step×step blocks
        h, w = (c.shape[1] // step) * step, (c.shape[2] // step) * step
        c = c[:, :h, :w].reshape(c.shape[0], h // step, step, w // step, step).mean(axis=(2, 4))
    c, _ = normalize_per_cube_max(c)
    y = spectra_to_xyz(np.moveaxis(c, 0, -1), sub)[..., 1]
    p99 = float(np.percentile(y, 99))
    exposure = 0.8 / p99 if p99 > 0 else 1.0
    return np.moveaxis(cube_to_srgb(c * exposure, sub), 0, -1)


def write_preview(path: str | os.PathLike, out_dir: str | os.PathLike | None = None, max_scenes: int = 16) -> list[Path]:
    """Write ``contact_sheet.png`` and ``mean_spectra.png`` for a dataset folder or one cube file.

    ``out_dir`` defaults to the dataset folder (the file's folder for a single file). Both PNGs
    are written atomically. Returns their paths.
    """
    from matplotlib.figure import Figure

    path = Path(path)
    scenes = list_scenes(path)[: max(1, int(max_scenes))]
    out = Path(out_dir) if out_dir is not None else (path if path.is_dir() else path.parent)
    thumbs, spectra = [], []
    for s in scenes:
        cube, bands, _ = read_cube(s)
        thumbs.append((s.name, preview_rgb(cube, bands)))
        norm, _ = normalize_per_cube_max(cube, s)
        spectra.append((s.name, bands, norm.mean(axis=(1, 2))))
    cols = min(len(thumbs), 4)
    rows = int(math.ceil(len(thumbs) / cols))
    fig = Figure(figsize=(2.6 * cols, 2.8 * rows))
    for k, (name, rgb) in enumerate(thumbs):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.imshow(np.clip(rgb, 0, 1), interpolation="nearest")
        ax.set_title(name, fontsize=8)
        ax.axis("off")
    fig.suptitle(f"{path.name}: sRGB renders (CIE 1931 2°, D65)", fontsize=10)
    sheet = out / CONTACT_SHEET
    save_figure(fig, sheet)

    fig = Figure(figsize=(7, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    for name, bands, mean in spectra:
        ax.plot(bands.centers_nm, mean, lw=1.2, label=name)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("mean value (per-cube max = 1)")
    ax.set_title(f"{path.name}: mean spectra")
    ax.grid(alpha=0.3)
    if len(spectra) <= 16:
        ax.legend(fontsize=6, ncol=2)
    plot = out / MEAN_SPECTRA
    save_figure(fig, plot)
    log.info("wrote %s and %s", sheet, plot)
    return [sheet, plot]


__all__ = ["CONTACT_SHEET", "MEAN_SPECTRA", "preview_rgb", "write_preview"]
