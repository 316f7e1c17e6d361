"""Previews of a dataset: a contact sheet of sRGB renders, a plot of mean spectra and a
spectral-gamut plot (first two principal components of spectral shapes: training against held-out).

Display rule (previews only, not the data): each cube is normalised by its maximum (the data
policy), rendered with :func:`hsicam.color.cube_to_srgb` (CIE 1931 2°, D65), after an exposure
that puts the 99th percentile of linear luminance at 0.8 so that scenes with a tiny highlight
are still visible.
"""

from __future__ import annotations

import contextlib
import logging
import math
import numbers
import os
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.color import PREVIEW_LEVEL, TABLE_RANGE_NM, cube_to_srgb, display_gain, preview_exposure
from hsicam.data.cube import conform_bands, normalize_per_cube_max
from hsicam.data.datasets import displayable_name, list_scenes
from hsicam.data.formats import read_cube
from hsicam.errors import InputError
from hsicam.io import atomic_path, save_figure
from hsicam.spectral import Bands
from hsicam.spectral.bands import BAND_TOL_NM

log = logging.getLogger(__name__)

CONTACT_SHEET = "contact_sheet.png"
MEAN_SPECTRA = "mean_spectra.png"
SPECTRAL_GAMUT = "spectral_gamut.png"


def renderable(bands: Bands) -> bool:
    """True when ``bands`` has at least 2 bands inside the colour-matching table (380-780 nm)."""
    lo, hi = TABLE_RANGE_NM
    return int(((bands.centers_nm >= lo) & (bands.centers_nm <= hi)).sum()) >= 2


def _downsample(c: np.ndarray, max_side: int) -> np.ndarray:
    """(C, H, W) area-averaged over step×step blocks so that its longer side is at most ``max_side`` (a side
    shorter than a step, e.g. a 4×1000 strip's, is one block: a strip keeps at least one row)."""
    step = max(1, int(math.ceil(max(c.shape[1:]) / max_side)))
    if step > 1:
        sy, sx = min(step, c.shape[1]), min(step, c.shape[2])
        h, w = (c.shape[1] // sy) * sy, (c.shape[2] // sx) * sx
        # summed in float64: a float32 sum of large values (a cube near float32's 3.4e38) overflows to inf
        c = c[:, :h, :w].reshape(c.shape[0], h // sy, sy, w // sx, sx).mean(axis=(2, 4), dtype=np.float64)
    return c


def preview_grey(cube: np.ndarray, max_side: int = 192) -> np.ndarray:
    """Grey display image (h, w, 3) in [0, 1] of a cube (C, H, W): its mean over bands, exposed like
    :func:`preview_rgb` (99th percentile at 0.8), for cubes with no visible bands to render."""
    m = _downsample(np.asarray(cube, dtype=np.float64), max_side).mean(axis=0)
    m = np.clip(m * display_gain(float(np.percentile(m, 99))), 0.0, 1.0)
    return np.repeat(m[..., None], 3, axis=-1)


def preview_rgb(cube: np.ndarray, bands: Bands, max_side: int = 192) -> np.ndarray:
    """Display sRGB (h, w, 3) in [0, 1] of a cube (C, H, W), downsampled to at most ``max_side``;
    InputError when fewer than 2 bands lie in 380-780 nm (:func:`renderable`)."""
    lo, hi = TABLE_RANGE_NM
    keep = (bands.centers_nm >= lo) & (bands.centers_nm <= hi)
    if not renderable(bands):
        raise InputError(f"cannot render bands {bands.min_nm:g}-{bands.max_nm:g} nm: fewer than 2 bands in {lo:g}-{hi:g} nm")
    sub = Bands(bands.centers_nm[keep], bands.fwhm_nm[keep])
    c = _downsample(cube[keep], max_side)
    c, _ = normalize_per_cube_max(c)
    return np.moveaxis(cube_to_srgb(c * preview_exposure(c, sub), sub), 0, -1)


def check_max_scenes(max_scenes: int) -> int:
    """``max_scenes`` as an int ≥ 1, else :class:`InputError`."""
    if isinstance(max_scenes, bool) or not isinstance(max_scenes, numbers.Integral) or max_scenes < 1:
        raise InputError(f"max_scenes must be an integer >= 1, got {max_scenes!r}")
    return int(max_scenes)


def save_figures(figures: dict[str, Any], out_dir: Path, dpi: int = 120) -> list[Path]:
    """Save matplotlib figures as ``out_dir/NAME``, all or none: each is drawn into a temporary file
    and the files are renamed into place only when every one was drawn. Returns their paths."""
    with contextlib.ExitStack() as stack:
        finals = [out_dir / name for name in figures]
        for final, fig in zip(finals, figures.values()):
            tmp = stack.enter_context(atomic_path(final))
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    return finals


def write_preview(path: str | os.PathLike, out_dir: str | os.PathLike, max_scenes: int = 16,
                  heldout: str | os.PathLike | None = None, npy_bands: Bands | None = None,
                  allow_negative: bool = False) -> list[Path]:
    """Write ``contact_sheet.png``, ``mean_spectra.png`` and ``spectral_gamut.png`` for a dataset.

    ``path`` is a dataset folder or one cube file; ``out_dir``, the folder written into, has no
    default: as with ``hsicam data show --out``, a preview is not written into its data unasked.
    ``heldout``: a held-out dataset folder to compare in the gamut plot (default: for a cached
    synthetic set, its held-out companion when one exists).
    ``max_scenes`` (≥ 1) caps the scenes of each set. Every input is read and every figure drawn
    before the first PNG is written: on an error none is written. ``npy_bands``: the band grid of
    ``.npy`` cubes, which carry none (the config's ``data.npy_bands``,
    :func:`hsicam.data.pipeline.npy_bands`; None: C bands evenly over 400-700 nm). ``allow_negative`` (the config's
    ``data.allow_negative``): negative values are clipped to 0 instead of refused. Returns their paths.
    """
    path = Path(path)
    n = check_max_scenes(max_scenes)
    every = list_scenes(path)
    scenes = every[:n]
    held_dir = Path(heldout) if heldout is not None else _find_heldout(path)
    held_scenes = list_scenes(held_dir)[:n] if held_dir is not None else []  # a bad held-out set fails before any work
    out = Path(out_dir)
    sheet, plot = _scene_figures(path, scenes, npy_bands, of=len(every), allow_negative=allow_negative)
    gamut = _gamut_figure(path, scenes, held_dir, held_scenes, npy_bands, allow_negative)
    written = save_figures({CONTACT_SHEET: sheet, MEAN_SPECTRA: plot, SPECTRAL_GAMUT: gamut}, out)
    # the cap said in the log and on the figures: a sheet of 16 scenes reads as the whole set otherwise
    log.info("wrote %s%s", ", ".join(str(p) for p in written),
             f" (the first {n} of the {len(every)} scenes of {path})" if len(every) > n else "")
    return written


def _scene_figures(path: Path, scenes: list[Path], npy_bands: Bands | None = None, of: int | None = None,
                   allow_negative: bool = False):
    """(contact sheet, mean spectra) figures of ``scenes`` (``.npy`` cubes on ``npy_bands``), the first of the ``of``
    scenes of ``path`` (their titles say so when there are more). Each scene is labelled by its path below ``path``
    (``day1/a.h5``): two files of one name in two sub-folders had the same label."""
    from matplotlib.figure import Figure

    from hsicam.data.datasets import scene_path

    thumbs, spectra, grey = [], [], 0
    for s in scenes:
        cube, bands, _ = read_cube(s, bands=npy_bands, allow_negative=allow_negative)
        norm, _ = normalize_per_cube_max(cube, s)  # first: an all-zero cube is refused naming its file
        label = displayable_name(scene_path(s, path))
        if renderable(bands):
            thumbs.append((label, preview_rgb(cube, bands)))
        else:  # e.g. a near-infrared cube: nothing to render in colour
            thumbs.append((f"{label} (grey)", preview_grey(cube)))
            grey += 1
        spectra.append((label, bands, norm.mean(axis=(1, 2))))
    first = f" (the first {len(scenes)} of {of} scenes)" if of is not None and of > len(scenes) else ""
    cols = min(len(thumbs), 4)
    rows = int(math.ceil(len(thumbs) / cols))
    sheet = Figure(figsize=(2.6 * cols, 2.8 * rows), layout="constrained")  # the two-line title clear of the thumbnails
    for k, (name, rgb) in enumerate(thumbs):
        ax = sheet.add_subplot(rows, cols, k + 1)
        ax.imshow(np.clip(rgb, 0, 1), interpolation="nearest")
        ax.set_title(name, fontsize=8)
        ax.axis("off")
    lo, hi = TABLE_RANGE_NM
    # each thumbnail is exposed to its own brightness (preview_rgb): say so, or a dim scene looks as bright as
    # any other, and 3x brighter than its absolute render (hsicam.color.srgb_preview at exposure 1)
    title = [f"{displayable_name(path.name)}: sRGB renders (CIE 1931 2°, D65){first}", "each scene exposed to its own brightness "
             f"(99th-percentile luminance at {PREVIEW_LEVEL:g})" + (
                 f"; (grey): mean over bands, fewer than 2 bands in {lo:g}-{hi:g} nm" if grey else "")]
    width = 30 * cols + 4  # characters of 10 pt text across the sheet: a narrow sheet's title wraps, not widens it
    sheet.suptitle("\n".join(textwrap.fill(line, width) for line in title), fontsize=10)

    plot = Figure(figsize=(7, 4.2))
    ax = plot.add_subplot(1, 1, 1)
    for i, (name, bands, mean) in enumerate(spectra):
        # a spectrum of one band is a point: a line through it draws nothing; the 11th spectrum on takes the first ten's
        # colours again, so it gets another line style (16 legend entries named two curves each by colour alone)
        ax.plot(bands.centers_nm, mean, lw=1.2, label=name, marker="o" if len(bands) == 1 else None,
                color=f"C{i % 10}", ls=("-", "--", ":", "-.")[(i // 10) % 4])
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("mean value (per-cube max = 1)")
    ax.set_title(f"{displayable_name(path.name)}: mean spectra{first}")
    ax.grid(alpha=0.3)
    if len(spectra) <= 16:
        ax.legend(fontsize=6, ncol=2)
    return sheet, plot


# ------------------------------------------------------------------------------------------------
# Spectral gamut: PCA of spectral shapes
# ------------------------------------------------------------------------------------------------
def _shapes(spectra: np.ndarray) -> np.ndarray:
    """Spectra (N, C) → unit-norm shapes, dropping (near-)black ones."""
    x = np.asarray(spectra, dtype=np.float64)
    norm = np.linalg.norm(x, axis=1)
    keep = norm > 1e-3 * max(float(norm.max(initial=0.0)), 1e-30)
    return x[keep] / norm[keep, None]


def pixel_spectra(scenes: list[Path], bands: Bands | None = None, per_scene: int = 400, seed: int = 0,
                  source: str | os.PathLike | None = None, npy_bands: Bands | None = None,
                  allow_negative: bool = False) -> tuple[np.ndarray, Bands]:
    """Up to ``per_scene`` random pixel spectra (N, C) from each scene, all on one band grid: ``bands``,
    or :func:`common_grid` of the scenes'. A scene on another grid is resampled onto it as training
    data are (:func:`hsicam.data.cube.conform_bands`); one whose bands do not cover it is left out,
    said in one log line. ``source`` (the folder) names the set in messages; InputError when no
    scene is left. ``npy_bands``, ``allow_negative``: as :func:`write_preview` reads the files."""
    rng = np.random.default_rng(seed)
    samples = []
    for s in scenes:
        cube, b, _ = read_cube(s, bands=npy_bands, allow_negative=allow_negative)
        pix = cube.reshape(cube.shape[0], -1).T
        idx = rng.choice(pix.shape[0], size=min(per_scene, pix.shape[0]), replace=False)
        samples.append((s, b, pix[np.sort(idx)]))
    where = f"{source}: " if source is not None else ""
    if not samples:
        raise InputError(f"{where}no scenes to sample spectra from")
    grid = bands if bands is not None else common_grid([b for _, b, _ in samples])
    kept = [(s, b, pix) for s, b, pix in samples if b.covers(grid)]
    left = [(s, b) for s, b, _ in samples if not b.covers(grid)]
    if not kept:
        raise InputError(f"{where}no scenes to sample spectra from: their bands ({_left_text(left)}) do not cover "
                         f"the plot's grid ({_grid_text(grid)}) and are not extrapolated")
    if left:
        log.warning("%sspectral gamut: left out %d of %d scenes, whose bands do not cover the plot's grid (%s; no "
                    "extrapolation): %s", where, len(left), len(samples), _grid_text(grid), _left_text(left))
    out = [conform_bands(pix, b, grid, s, axis=-1, note=False) for s, b, pix in kept]
    return np.concatenate(out), grid


def common_grid(grids: list[Bands], min_bands: int = 3) -> Bands:
    """The first grid's bands within the range that the most grids cover (each can be resampled onto
    it), keeping at least ``min_bands`` of them; among equals, the most bands. Ranges tried: from
    one grid's first band to one grid's last. The whole first grid when none keeps enough."""
    first, best, score = grids[0], grids[0], (-1, -1)
    for lo in sorted({b.min_nm for b in grids}):
        for hi in sorted({b.max_nm for b in grids}):
            keep = (first.centers_nm >= lo - BAND_TOL_NM) & (first.centers_nm <= hi + BAND_TOL_NM)  # as covers()
            if keep.sum() < min_bands:
                continue
            cand = Bands(first.centers_nm[keep], first.fwhm_nm[keep])
            cand_score = (sum(b.covers(cand) for b in grids), len(cand))
            if cand_score > score:
                best, score = cand, cand_score
    return best


def _grid_text(b: Bands) -> str:
    return f"{len(b)} bands, {b.min_nm:g}-{b.max_nm:g} nm"


def _left_text(left: list[tuple[Path, Bands]]) -> str:
    shown = ", ".join(f"{displayable_name(s.name)}: {_grid_text(b)}" for s, b in left[:5])
    return shown + (f" and {len(left) - 5} more" if len(left) > 5 else "")


def _find_heldout(path: Path) -> Path | None:
    """The held-out companion of a cached synthetic training set (same size, seed, bands, held-out sources)."""
    import json

    def params(d: Path) -> dict | None:
        try:
            return json.loads((d / "manifest.json").read_text(encoding="utf-8")).get("parameters")
        except (OSError, ValueError):
            return None

    mine = params(path) if path.is_dir() else None
    if not mine or mine.get("split", "train") != "train" or not mine.get("holdout_sources"):
        return None
    for d in sorted(path.parent.glob("heldout-*")):
        p = params(d)
        if p and all(p.get(k) == mine.get(k) for k in ("generator_version", "size", "seed", "bands", "holdout_sources")):
            return d
    return None


def _library_shapes(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, str] | None:
    """(training measured, training derived, held-out) reflectance shapes for a synthetic set, or None.

    Needs colour-science (the generator's library); returns None without it or for other datasets.
    """
    import json

    try:
        params = json.loads((path / "manifest.json").read_text(encoding="utf-8"))["parameters"]
        holdout = params["holdout_sources"]
        bands = Bands.from_dict(params["bands"])
    except (OSError, ValueError, KeyError, TypeError, InputError):
        return None
    if not holdout:
        return None
    try:
        from hsicam.data.synthetic import palette, spectral_library

        train = spectral_library(bands, holdout, "train")
        held = spectral_library(bands, holdout, "heldout")
    except (InputError, ImportError):
        return None
    derived, _ = palette(np.random.default_rng(0), train, 3000)
    label = ", ".join(holdout)
    return _shapes(train.reflectances), _shapes(derived), _shapes(held.reflectances), label


def write_spectral_gamut(path: str | os.PathLike, out_png: str | os.PathLike, heldout: str | os.PathLike | None = None,
                         max_scenes: int = 16, npy_bands: Bands | None = None, allow_negative: bool = False) -> Path:
    """Scatter of the first two principal components of spectral shapes (unit-norm spectra).

    Left (synthetic sets with held-out sources, colour-science installed): the reflectance library
    — measured training spectra, spectra derived from them (mixtures, layers, basis draws), held-out
    spectra. Right: pixel spectra of the dataset's scenes against those of the held-out set.
    """
    path, out_png = Path(path), Path(out_png)
    n = check_max_scenes(max_scenes)
    held_dir = Path(heldout) if heldout is not None else _find_heldout(path)
    held_scenes = list_scenes(held_dir)[:n] if held_dir is not None else []
    save_figure(_gamut_figure(path, list_scenes(path)[:n], held_dir, held_scenes, npy_bands, allow_negative), out_png)
    return out_png


def _gamut_figure(path: Path, scenes: list[Path], held_dir: Path | None, held_scenes: list[Path],
                  npy_bands: Bands | None = None, allow_negative: bool = False):
    """The figure of :func:`write_spectral_gamut` for the dataset's ``scenes`` (and the held-out set's)."""
    from matplotlib.figure import Figure

    pix, bands = pixel_spectra(scenes, source=path, npy_bands=npy_bands, allow_negative=allow_negative)
    groups = [("dataset pixels", _shapes(pix), "tab:blue", "o")]
    if held_dir is not None:
        hpix, _ = pixel_spectra(held_scenes, bands, seed=1, source=held_dir, npy_bands=npy_bands,
                                allow_negative=allow_negative)
        groups.append((f"held-out pixels ({displayable_name(held_dir.name)})", _shapes(hpix), "tab:red", "x"))
    lib = _library_shapes(path) if path.is_dir() else None
    panels = [("scene pixel spectra", groups)]
    if lib is not None:
        measured, derived, held, label = lib
        panels.insert(0, ("reflectance library", [
            ("training: derived (mixtures, layers, basis draws)", derived, "tab:cyan", "."),
            ("training: measured", measured, "tab:blue", "o"),
            (f"held out ({label})", held, "tab:red", "x")]))
    if len(bands) < 2:  # every unit-norm spectrum of one band is 1: no shape to tell apart (the library's panel is
        panels = []      # drawn on the same grid)
    fig = Figure(figsize=(6.2 * max(len(panels), 1), 5.0))
    if not panels:
        ax = fig.add_subplot(1, 1, 1)
        ax.text(0.5, 0.5, f"no spectral gamut: the data have one band ({bands.min_nm:g} nm),\n"
                "and a spectral shape needs two or more", ha="center", va="center", fontsize=10)
        ax.set_axis_off()
    for k, (title, data) in enumerate(panels):
        allx = np.concatenate([d for _, d, _, _ in data])
        mean = allx.mean(axis=0)
        _, sv, vt = np.linalg.svd(allx - mean, full_matrices=False)
        var = sv ** 2 / max(float((sv ** 2).sum()), 1e-30)
        ax = fig.add_subplot(1, len(panels), k + 1)
        for name, d, color, marker in data:
            pc = (d - mean) @ vt[:2].T
            ax.scatter(pc[:, 0], pc[:, 1], s=6 if marker != "x" else 14, c=color, marker=marker, alpha=0.5,
                       linewidths=0.8, label=f"{name} ({len(d)})")
        ax.set_xlabel(f"PC1 ({100 * var[0]:.0f} % of variance)")
        ax.set_ylabel(f"PC2 ({100 * var[1]:.0f} % of variance)")
        ax.set_title(f"{title}: spectral shapes", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best", markerscale=2)
    fig.suptitle(f"{displayable_name(path.name)}: spectral gamut (PCA of unit-norm spectra, {bands.min_nm:g}-{bands.max_nm:g} nm)",
                 fontsize=10)
    return fig


__all__ = ["CONTACT_SHEET", "MEAN_SPECTRA", "SPECTRAL_GAMUT", "check_max_scenes", "common_grid", "pixel_spectra",
           "preview_rgb", "save_figures", "write_preview", "write_spectral_gamut"]
