"""DOE height map for fabrication: continuous and L-level heights, phase error, files.

Conventions (also written into ``spec.json``):

* Heights are the relief of the DOE material in nm on the design's square cells (Δ = cell size),
  cell (row i, col j) centred at x = (j − (n−1)/2)·Δ, y = −(i − (n−1)/2)·Δ: row 0 at the top, as
  in the PNG and in the sensor image. The array axes coincide with the sensor's (row, column)
  axes when both are viewed from the same side along the optical axis; mounting the DOE
  mirrored mirrors every PSF.
* Only cells with light through them in the optics model carry the design (``aperture`` = the
  fraction of the cell inside the circle, sampled on 8×8 sub-points as the PSFs are: a cell that
  the circle only grazes, missing every sub-point, counts as outside); the other cells are written
  as 0 (no relief; light does not pass).
* The piston (the minimum height over the aperture) is removed: a constant height adds the same
  phase everywhere and leaves every PSF unchanged, so the relief starts at 0.
* L-level quantisation (binary-weighted lithography, L = 2^k) by the DOE's own rule
  (:meth:`hsicam.optics.doe.DOE.level_grid`), so an element trained with L levels is exported as
  trained: heights k·h_2π/L, k = 0..L−1, rounded and wrapped modulo h_2π (phase-equivalent at the
  design wavelength λ0: the phase error there is at most π/L; at other wavelengths the 2π step is
  not exactly 2π, which the per-band phase error reports; heights above h_2π are warned about); or,
  for a clamp range (``camera.doe.max_height_nm`` with ``wrap`` false), heights k·max/L clamped to
  k ≤ L−1, which keeps a multi-order design's heights.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.config import is_power_of_two
from hsicam.optics.perturb import design_heights
from hsicam.errors import InputError
from hsicam.io import atomic_open, atomic_path, save_figure, write_npy

log = logging.getLogger(__name__)


def quantize_levels(height_m: np.ndarray, levels: int, top_m: float, wrap: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(level index k (n, n) int, quantised heights k·top/L m) with k = round(h/step) mod L (``wrap``,
    phase levels over top = h_2π) or clamped to [0, L−1] (a clamp range): the rule of
    :func:`hsicam.optics.doe.quantize_heights`, in float64."""
    if levels < 2:
        raise InputError(f"quantisation needs at least 2 levels, got {levels}")
    step = top_m / levels
    k = np.round(np.asarray(height_m, dtype=np.float64) / step)
    k = (np.mod(k, levels) if wrap else np.clip(k, 0, levels - 1)).astype(np.int64)
    return k, k * step


def phase_error(height_m: np.ndarray, quantized_m: np.ndarray, phase_per_m: np.ndarray, weight: np.ndarray) -> dict[str, list[float]]:
    """Per band, the DOE phase error φ_λ(h_q) − φ_λ(h) wrapped to (−π, π], weighted by ``weight``
    (the aperture fraction): RMS and max in rad (``phase_per_m``: 2π(n(λ)−1)/λ per band, rad/m)."""
    dh = (np.asarray(quantized_m) - np.asarray(height_m))
    w = np.asarray(weight, dtype=np.float64)
    inside = w > 0
    rms, mx = [], []
    for k in np.asarray(phase_per_m, dtype=np.float64):
        e = np.angle(np.exp(1j * k * dh[inside]))
        rms.append(float(np.sqrt(np.sum(w[inside] * e**2) / np.sum(w[inside]))))
        mx.append(float(np.max(np.abs(e))) if e.size else 0.0)
    return {"rms_rad": rms, "max_rad": mx}


def nice_scale(max_value: float, counts: int = 65535) -> float:
    """Smallest of 1, 2, 5 × 10^k with ``max_value / scale <= counts`` (the TIFF's nm per count)."""
    if not max_value > 0:
        return 1.0
    raw = max_value / counts
    e = math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        s = m * 10.0**e
        if s >= raw * (1 - 1e-12):
            return float(f"{s:.12g}")
    return float(10.0 ** (e + 1))


def tiff_scale(max_nm: float, step_nm: float | None = None) -> float:
    """nm per count of a 16-bit height TIFF: :func:`nice_scale` of the largest height; for an L-level
    map (``step_nm`` = its level step) at most half a step, so every level reads back as itself, else
    (more levels than a nice scale resolves within 65535 counts: L up to 2^16) the step itself (count
    = level index)."""
    scale = nice_scale(max_nm)
    if step_nm is not None and scale > step_nm / 2:
        return float(step_nm)
    return scale


def write_height_tiff(path: str | Path, height_nm: np.ndarray, cell_um: float, info: dict[str, Any],
                      step_nm: float | None = None) -> float:
    """16-bit TIFF of a height map: value × ``scale_nm_per_count`` = height (nm). The scale, units,
    cell size and ``info`` are in the ImageDescription (JSON); the resolution tags give the cell
    size (pixels per cm). ``step_nm``: the level step of an L-level map (:func:`tiff_scale`).
    Returns the scale."""
    import tifffile

    h = np.asarray(height_nm, dtype=np.float64)
    if h.size and float(h.min()) < 0:
        raise InputError("heights must be >= 0 for the 16-bit TIFF")
    scale = tiff_scale(float(h.max()) if h.size else 0.0, step_nm)
    data = np.round(h / scale).astype(np.uint16)
    desc = {"hsicam": "doe-height-map", "scale_nm_per_count": scale, "offset_nm": 0.0, "unit": "nm",
            "cell_size_um": cell_um, "rows": "row 0 = top (+y)", **info}
    px_per_cm = 1e4 / cell_um
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, data, description=json.dumps(desc), metadata=None, software="hsicam",
                         resolution=(px_per_cm, px_per_cm), resolutionunit="CENTIMETER")
    return scale


def read_height_tiff(path: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """Height map (nm, float64) and description of :func:`write_height_tiff`'s file."""
    import tifffile

    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        desc = json.loads(page.description)
        data = page.asarray()
    return data.astype(np.float64) * float(desc["scale_nm_per_count"]), desc


def _fmt(v: float) -> str:
    """Shortest text that reads back as the same float32 (exact round trip)."""
    return repr(float(np.float32(v)))


def write_height_csv(path: str | Path, height_nm: np.ndarray, aperture: np.ndarray, cell_um: float,
                     level: np.ndarray | None = None) -> None:
    """Long-format CSV, one row per cell touching the aperture:
    ``row, col, x_um, y_um, aperture_fraction, height_nm[, level]`` (float32 values, exact)."""
    h = np.asarray(height_nm, dtype=np.float32)
    n = h.shape[0]
    c = (n - 1) / 2.0
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["row", "col", "x_um", "y_um", "aperture_fraction", "height_nm"] + (["level"] if level is not None else []))
    rows, cols = np.nonzero(np.asarray(aperture) > 0)
    for i, j in zip(rows.tolist(), cols.tolist()):
        rec = [i, j, _fmt((j - c) * cell_um), _fmt(-(i - c) * cell_um), _fmt(aperture[i, j]), _fmt(h[i, j])]
        if level is not None:
            rec.append(int(level[i, j]))
        w.writerow(rec)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())


def read_height_csv(path: str | Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(heights nm float32 (n, n), aperture fraction float32 (n, n)) of :func:`write_height_csv`'s file."""
    h = np.zeros((n, n), np.float32)
    a = np.zeros((n, n), np.float32)
    with open(path, newline="", encoding="utf-8") as fh:
        for rec in csv.DictReader(fh):
            i, j = int(rec["row"]), int(rec["col"])
            h[i, j] = np.float32(float(rec["height_nm"]))
            a[i, j] = np.float32(float(rec["aperture_fraction"]))
    return h, a


def write_phase_error_csv(path: str | Path, bands_nm: np.ndarray, err: dict[str, list[float]]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["wavelength_nm", "rms_rad", "max_rad", "rms_waves", "max_waves"])
    for lam, r, m in zip(bands_nm, err["rms_rad"], err["max_rad"]):
        w.writerow([f"{lam:g}", f"{r:.6g}", f"{m:.6g}", f"{r / (2 * np.pi):.6g}", f"{m / (2 * np.pi):.6g}"])
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())


def plot_doe_export(height_nm: np.ndarray, quantized_nm: np.ndarray, aperture: np.ndarray, cell_um: float,
                    levels: int, top_nm: float, path: str | Path) -> None:
    """Continuous heights, L-level heights and their difference over the aperture (nm), the
    difference wrapped to ±h_2π/2 (a wrap by h_2π is no error at the design wavelength). The two
    height maps share one colour scale (a colour is the same height in both)."""
    from matplotlib.figure import Figure

    inside = np.asarray(aperture) > 0
    n = height_nm.shape[0]
    half = n * cell_um * 1e-3 / 2
    ext = (-half, half, -half, half)
    fig = Figure(figsize=(13, 3.8), layout="constrained")  # constrained: colour bars clear of the next panel
    axes = fig.subplots(1, 3)
    heights = np.concatenate([height_nm[inside], quantized_nm[inside]])
    height_range = {"vmin": float(heights.min()), "vmax": float(heights.max())} if heights.size else {}
    panels = [(height_nm, "continuous height (nm)", "viridis"), (quantized_nm, f"{levels}-level height (nm)", "viridis"),
              (np.mod(quantized_nm - height_nm + top_nm / 2, top_nm) - top_nm / 2,
               "quantised − continuous, mod h$_{2π}$ (nm)", "coolwarm")]
    for ax, (img, title, cmap) in zip(axes, panels):
        shown = np.where(inside, img, np.nan)
        kw = dict(height_range)
        if cmap == "coolwarm":
            lim = float(np.nanmax(np.abs(shown))) if inside.any() else 1.0
            kw = {"vmin": -lim, "vmax": lim}
        im = ax.imshow(shown, cmap=cmap, extent=ext, interpolation="nearest", **kw)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (mm)")
        fig.colorbar(im, ax=ax, fraction=0.046)
    axes[0].set_ylabel("y (mm)")
    fig.suptitle(f"DOE: {n}×{n} cells of {cell_um:g} µm", fontsize=10)
    save_figure(fig, path)


def level_grid_text(doe) -> str:
    """How an L-level element's heights are quantised (:meth:`hsicam.optics.doe.DOE.level_grid`), in words
    (for ``spec.json`` and the tolerance study's methods)."""
    top, wrap = doe.level_grid()
    return ("phase levels k·h_2π/L, wrapped modulo h_2π" if wrap else
            f"clamp range k·{top * 1e9:g} nm/L, k = 0..L−1 (camera.doe.max_height_nm, wrap false)")


def export_doe(camera, out: Path, levels: int, bands_nm: np.ndarray) -> dict[str, Any]:
    """Write the DOE files into ``out``; returns the facts for ``spec.json``."""
    from hsicam.export.gds import gds_layers, write_gds

    optics = camera.optics
    doe = optics.doe
    cell_um = round(optics.cell_m * 1e6, 9)
    h_m, aperture, piston = design_heights(camera)
    # the rule the DOE quantises by in training: with the run's own L the trained element comes out
    # unchanged (a clamp range keeps its k·max/L grid instead of moving onto h_2π's)
    top, wrap = doe.level_grid()
    level, hq_m = quantize_levels(h_m, levels, top, wrap)
    if wrap and float(h_m.max(initial=0.0)) > doe.h2pi_m * (1 + 0.5 / levels):  # beyond what rounds to h_2π
        log.warning("the DOE's heights reach %.0f nm, above h_2π = %.0f nm: its %d-level version wraps them modulo "
                    "h_2π, the same element at the design wavelength only (phase error per band in "
                    "doe_phase_error_L%d.csv); for a multi-order design train with camera.doe.max_height_nm and "
                    "wrap false, which the export keeps", h_m.max() * 1e9, doe.h2pi_m * 1e9, levels, levels)
    inside = aperture > 0
    hq_m = np.where(inside, hq_m, 0.0)
    level = np.where(inside, level, 0)
    h_nm = (h_m * 1e9).astype(np.float32)
    hq_nm = (hq_m * 1e9).astype(np.float32)
    write_npy(out / "doe_height_nm.npy", h_nm)
    write_npy(out / "doe_aperture.npy", aperture.astype(np.float32))
    write_npy(out / f"doe_height_L{levels}_nm.npy", hq_nm)
    write_npy(out / f"doe_level_L{levels}.npy", level.astype(np.uint8 if levels <= 256 else np.uint16))
    info = {"cells_across": int(doe.n_cells), "piston_removed_nm": piston * 1e9}
    scale = write_height_tiff(out / "doe_height_nm.tif", h_nm, cell_um, {**info, "quantized": False})
    scale_q = write_height_tiff(out / f"doe_height_L{levels}_nm.tif", hq_nm, cell_um,
                                {**info, "quantized": True, "levels": levels, "step_nm": top * 1e9 / levels},
                                step_nm=top * 1e9 / levels)
    write_height_csv(out / "doe_height_nm.csv", h_nm, aperture, cell_um)
    write_height_csv(out / f"doe_height_L{levels}_nm.csv", hq_nm, aperture, cell_um, level)
    from hsicam.optics.doe import phase_per_height

    k = phase_per_height(doe.material, np.asarray(bands_nm, dtype=np.float64))
    err = phase_error(h_m, hq_m, k, aperture)
    write_phase_error_csv(out / f"doe_phase_error_L{levels}.csv", bands_nm, err)
    k0 = phase_per_height(doe.material, np.array([doe.design_wavelength_nm]))
    err0 = phase_error(h_m, hq_m, k0, aperture)
    plot_doe_export(h_nm.astype(np.float64), hq_nm.astype(np.float64), aperture, cell_um, levels, top * 1e9, out / "doe.png")
    gds_info: dict[str, Any]
    if is_power_of_two(levels):
        try:
            written = write_gds(out / f"doe_L{levels}.gds", level, levels, cell_um, aperture, top * 1e9 / levels,
                                optics.aperture_radius_m * 1e6)
            gds_info = {"file": f"doe_L{levels}.gds", "layers": gds_layers(levels, top * 1e9 / levels),
                        "surround": written["surround"]}
        except ImportError as exc:
            log.warning("no GDSII written: %s", exc)
            gds_info = {"file": None, "skipped": str(exc)}
    else:
        gds_info = {"file": None, "skipped": f"{levels} levels are not a power of 2 (binary-weighted lithography needs L = 2^k)"}
    return {
        "cell_size_um": cell_um,
        "cells_across": int(doe.n_cells),
        "cells_in_aperture": int(inside.sum()),
        "material": getattr(doe.material, "name", str(doe.material)),
        "refractive_index_design": float(doe.material.n(doe.design_wavelength_nm)),
        "design_wavelength_nm": doe.design_wavelength_nm,
        "height_2pi_nm": doe.h2pi_m * 1e9,
        "height_range_nm": [float(h_nm[inside].min()), float(h_nm[inside].max())] if inside.any() else [0.0, 0.0],
        "piston_removed_nm": piston * 1e9,
        "tiff_scale_nm_per_count": scale,
        "orientation": "row 0 at the top (+y), column 0 at the left (−x); array axes = sensor (row, column) axes "
                       "seen from the same side along the optical axis: the files (GDS, TIFF, CSV) show the element as "
                       "seen from the side from which the sensor's rows and columns are counted; a relief made as "
                       "drawn and seen from its other side is mirrored (x → −x), and a mirrored element mirrors every "
                       "PSF",
        "quantized": {
            "levels": levels,
            "step_nm": top * 1e9 / levels,
            "grid": level_grid_text(doe),
            "tiff_scale_nm_per_count": scale_q,
            "phase_error_design_wavelength_rad": {"rms": err0["rms_rad"][0], "max": err0["max_rad"][0],
                                                  "bound_pi_over_L": math.pi / levels if wrap else None},
            "phase_error_per_band_rad": err,
            "first_order_efficiency_sinc2": float(np.sinc(1.0 / levels) ** 2),
            "gds": gds_info,
        },
    }
