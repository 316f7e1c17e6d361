"""Colour filter array for filter suppliers: transmission table, colour picture, parametric fits.

The model's filters κ are relative: Σ_λ κ = 1 per filter (paper eq. 9). A physical filter can
only match a curve up to a gain, so the table also lists each filter's peak-normalised curve
(maximum 1), and the fits describe that shape.

κ weighs band values, each the spectrum averaged over its band's Gaussian response
(:func:`hsicam.spectral.band_matrix` G), so the filter the camera was trained with is continuous:
T(λ) = Σ_c κ_c G_c(λ) per nm, its response to monochromatic light, exact for every spectrum however
fine its lines (:func:`model_filter_curves`; written on the 1 nm grid the spectra are averaged on). A
filter that holds all of its κ in one band is a Gaussian of that band's FWHM there. The band table holds κ, the
weights of the band values, which T spreads over each band's response.

Fit model per filter (:func:`fit_tile`: the filter the model applies, T of :func:`model_filter_curves`, scaled to a
peak of 1, t(λ) on its 1 nm grid; :func:`fit_filter` fits any sampled curve the same way):

    t(λ) ≈ b + Σ_g a_g · exp(−(λ − μ_g)² / (2 σ_g²)),   g = 1 (or 2)

b, a_g ≥ 0 (a_g ≤ 1.5), centres μ within the curve's range ± half its span, FWHM = 2√(2 ln 2) σ
between one sample step (narrower is not resolved) and twice the span. One Gaussian always; two when the samples
are enough (≥ 9) and the small-sample Akaike criterion (AICc) prefers it. Fit error: RMS and maximum absolute
difference on the samples, in units of the peak (1). Until session 66 the fits were of κ's band values, taken as
samples of the filter: between band centres they overshot (peaks up to 1.5 on the shipped camera) and they differed
from the filter the model applies by up to 0.87 of the peak, with an RMS error of 0.000 at the centres.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.io import atomic_open, save_figure, write_npy
from hsicam.spectral import FWHM_PER_SIGMA, Bands, band_matrix, fine_grid


def filter_names(m_rows: int, m_cols: int) -> list[str]:
    """``r{row}c{col}`` for the filters of an m×m tile, row-major."""
    return [f"r{i}c{j}" for i in range(m_rows) for j in range(m_cols)]


def _fmt(v: float) -> str:
    return repr(float(np.float32(v)))


def write_transmission_csv(path: str | Path, tile: np.ndarray, bands: Bands, peak_normalised: bool = False) -> None:
    """Band × filter table: ``wavelength_nm, fwhm_nm, r0c0, r0c1, …`` (float32 values, exact)."""
    t = np.asarray(tile, dtype=np.float32)
    c, mr, mc = t.shape
    curves = t.reshape(c, mr * mc)
    if peak_normalised:
        curves = (curves / np.maximum(curves.max(axis=0, keepdims=True), np.float32(1e-30))).astype(np.float32)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["wavelength_nm", "fwhm_nm", *filter_names(mr, mc)])
    for b in range(c):
        w.writerow([f"{bands.centers_nm[b]:.12g}", f"{bands.fwhm_nm[b]:.12g}", *[_fmt(v) for v in curves[b]]])
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())


def read_transmission_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(wavelengths nm (C,), transmissions float32 (C, F), filter names) of a transmission CSV."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    names = rows[0][2:]
    lam = np.array([float(r[0]) for r in rows[1:]])
    vals = np.array([[np.float32(float(v)) for v in r[2:]] for r in rows[1:]], dtype=np.float32)
    return lam, vals, names


def model_filter_curves(tile: np.ndarray, bands: Bands) -> tuple[np.ndarray, np.ndarray]:
    """(wavelengths nm (F,), T (F, m_rows·m_cols)): each filter of a (C, m_rows, m_cols) tile as the camera model
    applies it, a transmission per nm on the 1 nm grid of :func:`hsicam.spectral.fine_grid`, filters row-major.

    The model images band values x_c = Σ_λ G_cλ s(λ) (:func:`hsicam.spectral.band_matrix`: the Gaussian response of
    band c, rows summing to 1), so a filter of weights κ gives Σ_c κ_c x_c = Σ_λ T(λ) s(λ) Δλ with
    T(λ) = Σ_c κ_c G_cλ / Δλ: its response to monochromatic light at λ, and ∫ T dλ = Σ_c κ_c (1 in the model's
    convention)."""
    t = np.asarray(tile, dtype=np.float64)
    c = t.shape[0]
    fine = fine_grid(bands)
    g = band_matrix(bands, fine)  # (C, F)
    dl = np.gradient(fine) if fine.size > 1 else np.ones(1)
    return fine, (g.T @ t.reshape(c, -1)) / dl[:, None]


def _peak_one(curves: np.ndarray) -> np.ndarray:
    """``curves`` (F, filters) each scaled to a maximum of 1 (an all-zero curve kept zero)."""
    peaks = curves.max(axis=0, keepdims=True)
    return curves / np.where(peaks > 0, peaks, 1.0)


def write_model_filter_csv(path: str | Path, tile: np.ndarray, bands: Bands) -> None:
    """``wavelength_nm, r0c0, r0c1, …``: :func:`model_filter_curves` on its 1 nm grid, each filter scaled to a peak
    of 1 (float32 values)."""
    fine, curves = model_filter_curves(tile, bands)
    curves = _peak_one(curves)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    _, mr, mc = np.shape(tile)
    w.writerow(["wavelength_nm", *filter_names(mr, mc)])
    for lam, row in zip(fine, curves):
        w.writerow([f"{lam:.12g}", *[_fmt(v) for v in row]])
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())


def _model(lam: np.ndarray, p: np.ndarray, n_g: int) -> np.ndarray:
    out = np.full_like(lam, p[0])
    for g in range(n_g):
        a, mu, s = p[1 + 3 * g : 4 + 3 * g]
        out = out + a * np.exp(-0.5 * ((lam - mu) / s) ** 2)
    return out


def fit_gaussians(lam_nm: np.ndarray, t: np.ndarray, n_gaussians: int) -> dict[str, Any]:
    """Least-squares fit of ``n_gaussians`` Gaussians plus a non-negative offset to ``t`` (C,)."""
    from scipy.optimize import least_squares

    lam = np.asarray(lam_nm, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    span = max(float(lam[-1] - lam[0]), 1.0)
    step = float(np.min(np.diff(lam))) if lam.size > 1 else span  # (one band: no step; the span is 1 nm)
    s_lo, s_hi = step / FWHM_PER_SIGMA, 2.0 * span / FWHM_PER_SIGMA  # FWHM ≥ one band step (resolvable)
    mu_lo, mu_hi = lam[0] - span / 2, lam[-1] + span / 2
    base = max(float(t.min()), 0.0)
    p0 = [base]
    lo, hi = [0.0], [max(1.0, 2 * float(t.max()))]
    resid = t - base
    for _ in range(n_gaussians):
        i = int(np.argmax(resid))
        above = np.count_nonzero(resid >= resid[i] / 2)
        s0 = float(np.clip(above * step / FWHM_PER_SIGMA, s_lo * 1.01, s_hi * 0.99))
        a0 = max(float(resid[i]), 1e-6)
        p0 += [a0, float(lam[i]), s0]
        lo += [0.0, mu_lo, s_lo]
        hi += [1.5 * max(1.0, float(t.max())), mu_hi, s_hi]
        resid = resid - a0 * np.exp(-0.5 * ((lam - lam[i]) / s0) ** 2)
    p0 = np.clip(p0, np.array(lo) + 1e-12, np.array(hi) - 1e-12)
    res = least_squares(lambda p: _model(lam, p, n_gaussians) - t, p0, bounds=(lo, hi), method="trf",
                        x_scale="jac", max_nfev=2000)
    p = res.x.copy()
    # an offset or amplitude at its bound 0 came back as a denormal (4.9e-324 in cfa_fit.csv): 0, as it is
    amp = np.r_[0, 1 + 3 * np.arange(n_gaussians)]
    p[amp] = np.where(p[amp] < 1e-12, 0.0, p[amp])
    err = _model(lam, p, n_gaussians) - t
    comps = sorted(({"amplitude": float(p[1 + 3 * g]), "centre_nm": float(p[2 + 3 * g]),
                     "fwhm_nm": float(p[3 + 3 * g] * FWHM_PER_SIGMA)} for g in range(n_gaussians)),
                   key=lambda c: c["centre_nm"])
    return {"n_gaussians": n_gaussians, "offset": float(p[0]), "components": comps,
            "rms_error": float(np.sqrt(np.mean(err**2))), "max_abs_error": float(np.max(np.abs(err))),
            "n_params": 1 + 3 * n_gaussians, "_params": p}


def _aicc(rss: float, n: int, k: int) -> float:
    if n - k - 1 <= 0:
        return math.inf
    return n * math.log(max(rss, 1e-300) / n) + 2 * k + 2 * k * (k + 1) / (n - k - 1)


def fit_filter(lam_nm: np.ndarray, curve: np.ndarray) -> dict[str, Any]:
    """Best parametric fit (1 or 2 Gaussians + offset) of one filter's peak-normalised curve."""
    t = np.asarray(curve, dtype=np.float64)
    peak = float(t.max())
    t = t / peak if peak > 0 else t
    n = t.size
    fits = [fit_gaussians(lam_nm, t, 1)]
    if n >= 9:
        fits.append(fit_gaussians(lam_nm, t, 2))
    scores = [_aicc(f["rms_error"] ** 2 * n, n, f["n_params"]) for f in fits]
    best = fits[int(np.argmin(scores))] if all(math.isfinite(s) for s in scores) else fits[0]
    return {**best, "peak_kappa": peak}


def fit_tile(tile: np.ndarray, bands: Bands) -> list[dict[str, Any]]:
    """Fits of every filter of a (C, m, m) tile, row-major: of the filter the model applies
    (:func:`model_filter_curves`) on its 1 nm grid (see module docstring); ``peak_kappa``: the largest of the
    filter's κ."""
    t = np.asarray(tile, dtype=np.float64)
    c, mr, mc = t.shape
    grid, curves = model_filter_curves(t, bands)
    out = []
    for name, curve, kappa in zip(filter_names(mr, mc), curves.T, t.reshape(c, -1).T):
        f = fit_filter(grid, curve)
        out.append({"filter": name, **f, "peak_kappa": float(kappa.max())})
    return out


def write_fit_csv(path: str | Path, fits: list[dict[str, Any]]) -> None:
    """One row per filter: model, offset, up to two Gaussians (amplitude, centre, FWHM), errors."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["filter", "n_gaussians", "peak_kappa", "offset", "amplitude_1", "centre_1_nm", "fwhm_1_nm",
                "amplitude_2", "centre_2_nm", "fwhm_2_nm", "rms_error", "max_abs_error"])
    for f in fits:
        comps = f["components"] + [{"amplitude": "", "centre_nm": "", "fwhm_nm": ""}] * (2 - len(f["components"]))
        row = [f["filter"], f["n_gaussians"], f"{f['peak_kappa']:.6g}", f"{f['offset']:.6g}"]
        for c in comps[:2]:
            row += [c["amplitude"] if c["amplitude"] == "" else f"{c['amplitude']:.6g}",
                    c["centre_nm"] if c["centre_nm"] == "" else f"{c['centre_nm']:.6g}",
                    c["fwhm_nm"] if c["fwhm_nm"] == "" else f"{c['fwhm_nm']:.6g}"]
        row += [f"{f['rms_error']:.6g}", f"{f['max_abs_error']:.6g}"]
        w.writerow(row)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())


def plot_fits(tile: np.ndarray, bands: Bands, fits: list[dict[str, Any]], path: str | Path) -> None:
    """Small multiples laid out like the tile: each filter's peak-normalised κ (dots), the filter as the camera model
    applies it (:func:`model_filter_curves`, peak 1, grey) and its fit (``fits``, black) against wavelength, one panel
    per filter, all on the same axes (wavelength in nm, transmission relative to the filter's peak), the x range
    covering the model filters' 1 nm grid and the y range every curve and fit: a fit overshooting the peak (an
    offset plus Gaussians between sparse bands) is drawn whole, not cut flat."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from hsicam.report.camera import cfa_tile_rgb

    t = np.asarray(tile, dtype=np.float64)
    c, mr, mc = t.shape
    rgb = cfa_tile_rgb(t, bands).reshape(-1, 3)
    lam = bands.centers_nm
    grid, applied = model_filter_curves(t, bands)
    applied = _peak_one(applied)
    fine = np.linspace(grid[0], grid[-1], 400)
    curves = t.reshape(c, -1).T
    peaks = np.where(curves.max(axis=1) > 0, curves.max(axis=1), 1.0)
    models = [_model(fine, f["_params"], f["n_gaussians"]) for f in fits]
    lo = min(0.0, *(float(m.min()) for m in models), *(float((cv / p).min()) for cv, p in zip(curves, peaks)))
    hi = max(1.0, *(float(m.max()) for m in models))
    pad = 0.05 * (hi - lo)
    # the same limits set on every panel, not shared axes: 225 shared panels (a 15 × 15 tile) took 20 s to draw
    fig = Figure(figsize=(1.9 * mc + 0.8, 1.5 * mr + 0.8))
    axes = fig.subplots(mr, mc, squeeze=False)
    margin = 0.03 * (float(grid[-1] - grid[0]) or 1.0)
    for idx, (ax, f) in enumerate(zip(axes.flat, fits)):
        ax.plot(lam, curves[idx] / peaks[idx], "o", ms=3, color=np.clip(rgb[idx], 0, 0.85))
        ax.plot(fine, models[idx], "-", lw=1, color="k")
        ax.plot(grid, applied[:, idx], "-", lw=2.5, color="0.8", zorder=1)  # under the dots and the fit
        ax.set_title(f"{f['filter']}  rms {f['rms_error']:.3f}", fontsize=8)
        ax.set_xlim(grid[0] - margin, grid[-1] + margin)
        ax.set_ylim(lo - pad, hi + pad)
        ax.xaxis.set_major_locator(MaxNLocator(3))
        ax.yaxis.set_major_locator(MaxNLocator(4))
        i, j = divmod(idx, mc)
        ax.tick_params(labelsize=7, labelbottom=i == mr - 1, labelleft=j == 0)
    fig.subplots_adjust(wspace=0.12, hspace=0.35)
    fig.supxlabel("wavelength (nm)", fontsize=9)
    fig.supylabel("transmission (each filter's peak = 1)", fontsize=9)
    fig.suptitle("CFA filters, each at a peak of 1\nκ (dots), model filter on 1 nm (grey), its Gaussian fit (black)",
                 fontsize=10)
    save_figure(fig, path)


def export_cfa(camera, out: Path) -> dict[str, Any]:
    """Write the CFA files into ``out``; returns the facts for ``spec.json``."""
    import torch

    from hsicam.report.camera import plot_cfa

    with torch.no_grad():
        tile = camera.cfa.tile().detach().float().cpu().numpy()
    bands = camera.bands
    write_npy(out / "cfa_tile.npy", tile.astype(np.float32))
    write_transmission_csv(out / "cfa_transmission.csv", tile, bands)
    write_transmission_csv(out / "cfa_transmission_peak1.csv", tile, bands, peak_normalised=True)
    write_model_filter_csv(out / "cfa_transmission_1nm_peak1.csv", tile, bands)
    plot_cfa(tile, bands, out / "cfa.png")
    fits = fit_tile(tile, bands)
    grid = fine_grid(bands)
    write_fit_csv(out / "cfa_fit.csv", fits)
    plot_fits(tile, bands, fits, out / "cfa_fit.png")
    rms = [f["rms_error"] for f in fits]
    return {
        "enabled": bool(camera.cfa.enabled),
        "period": int(tile.shape[-1]),
        "filters": len(fits),
        "convention": "kappa sums to 1 over bands per filter (model); *_peak1.csv: each filter scaled to a peak of 1",
        "model_filter": ("cfa_transmission_1nm_peak1.csv: each filter's transmission as the camera model applies it, on "
                         "a 1 nm grid: sum over bands of kappa times the band's Gaussian response (the response to "
                         "monochromatic light; exact for any spectrum, line spectra included); cfa_transmission.csv "
                         f"holds kappa, the weights of the band values. Outside {grid[0]:g}-{grid[-1]:g} nm the model "
                         "sees no light at all: a camera built to it blocks what its sensor would see there, with a "
                         f"long-pass filter at {grid[0]:g} nm and a short-pass at {grid[-1]:g} nm (a visible camera's "
                         "UV and IR-cut filters)"),
        "placement": (f"filter r{{i}}c{{j}} covers the sensor pixels (row, column) with row mod {tile.shape[-2]} = i and "
                      f"column mod {tile.shape[-1]} = j, counted from the sensor image's pixel (0, 0) as read out; one "
                      "filter per pixel, at the sensor's pixel pitch; a tile mounted mirrored or rotated is another "
                      "CFA (reconstruct --cfa-offset finds shifts, and reconstruct --orientation undoes a capture stored "
                      "flipped or turned, not a tile mounted so)"),
        "fit_model": ("offset + 1 or 2 Gaussians (AICc choice) fitted to each filter as the model applies it "
                      "(cfa_transmission_1nm_peak1.csv), errors on its 1 nm grid in units of its peak"),
        "fit_rms_error": {"mean": float(np.mean(rms)), "max": float(np.max(rms))},
        "fits": [{k: v for k, v in f.items() if not k.startswith("_")} for f in fits],
    }
