"""Pictures of reconstructions: RGB renders with error maps, spectra at pixels, training curves."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from hsicam.io import nan_for_null, save_figure
from hsicam.spectral import Bands


def cube_rgb(cube: np.ndarray, bands: Bands) -> np.ndarray:
    """sRGB render (H, W, 3) of a (C, H, W) reflectance-like cube (CIE 1931 2°, D65)."""
    from hsicam.color import cube_to_srgb

    return np.moveaxis(cube_to_srgb(torch.from_numpy(np.clip(cube, 0, None)), bands).numpy(), 0, -1)


def spectra_exponent(spectra) -> int:
    """The power of ten by which spectra peaking below 0.01 are divided for plotting (their peak
    then in [1, 10)), so that tick labels stay short; 0 for brighter (or all-zero) spectra."""
    peak = max((float(np.max(np.abs(s))) for s in spectra), default=0.0)
    return int(np.floor(np.log10(peak))) if 0 < peak < 0.01 else 0


def plot_reconstructions(results, bands: Bands, path: str | Path, max_rows: int = 6) -> None:
    """Rows of [ground truth RGB | reconstruction RGB | mean abs error map | spectra at 3 pixels]; the first
    ``max_rows`` scenes (the figure's title says so when there are more)."""
    results = list(results)
    total, results = len(results), results[:max_rows]
    fig = Figure(figsize=(14, 3.2 * len(results)))
    axes = fig.subplots(len(results), 4, squeeze=False, gridspec_kw={"wspace": 0.55, "hspace": 0.45})
    for row, r in zip(axes, results):
        gt, est = r.truth, r.estimate
        row[0].imshow(np.clip(cube_rgb(gt, bands), 0, 1))
        row[0].set_title(f"{r.name}: ground truth", fontsize=9)
        row[1].imshow(np.clip(cube_rgb(est, bands), 0, 1))
        row[1].set_title(f"reconstruction  {r.metrics['psnr']:.2f} dB / SSIM {r.metrics['ssim']:.3f}", fontsize=9)
        err = np.abs(est - gt).mean(axis=0)
        im = row[2].imshow(err, cmap="magma", vmin=0, vmax=max(float(np.percentile(err, 99)), 1e-6))
        row[2].set_title("mean |error| over bands\n(this scene's scale; its top 1 % clipped)", fontsize=9)
        fig.colorbar(im, cax=row[2].inset_axes([1.03, 0.0, 0.05, 1.0]), extend="max")
        h, w = gt.shape[1:]
        pts = [(h // 4, w // 4), (h // 2, w // 2), (3 * h // 4, 3 * w // 4)]
        exp = spectra_exponent([a[:, y, x] for y, x in pts for a in (gt, est)])
        for (y, x), col in zip(pts, ("tab:red", "tab:green", "tab:blue")):
            row[0].plot(x, y, "o", mfc="none", mec=col, ms=8)
            row[3].plot(bands.centers_nm, gt[:, y, x] / 10.0**exp, color=col, lw=1.5)
            row[3].plot(bands.centers_nm, est[:, y, x] / 10.0**exp, color=col, lw=1.2, ls="--")
        row[3].set_title("spectra: truth (solid), reconstruction (dashed)", fontsize=9)
        row[3].yaxis.tick_right()  # clear of the error map's colour bar on the left
        row[3].yaxis.set_label_position("right")
        if exp:  # short tick labels (1.25 rather than 0.00125)
            row[3].set_ylabel(f"× 1e{exp}", fontsize=8)
        row[3].set_xlabel("wavelength (nm)")
        for ax in row[:3]:
            ax.set_xticks([])
            ax.set_yticks([])
    if total > len(results):
        height = fig.get_figheight()
        fig.subplots_adjust(top=1 - 0.6 / height)
        fig.suptitle(f"the first {len(results)} of {total} scenes (every scene's scores: results.md)", fontsize=10,
                     y=1 - 0.1 / height)
    save_figure(fig, path)


@dataclass(frozen=True)
class ComparisonPanel:
    """One method's column of :func:`plot_method_comparison`: its reconstruction's RGB render (H, W, 3), its mean
    absolute error over bands (H, W) and its scores on the scene. The render and the error map are what the figure
    needs of the two (C, H, W) cubes: an experiment keeps these, not the cubes (:func:`comparison_panel`)."""

    label: str
    rgb: np.ndarray
    error: np.ndarray
    psnr: float
    ssim: float


def comparison_panel(label: str, truth: np.ndarray, est: np.ndarray, bands: Bands, psnr: float,
                     ssim: float) -> ComparisonPanel:
    """The :class:`ComparisonPanel` of the estimate ``est`` of ``truth`` (both (C, H, W)): the absolute render
    :func:`cube_rgb` and mean |est − truth| over bands."""
    if est.shape != truth.shape:
        raise ValueError(f"{label}: estimate {est.shape} and truth {truth.shape} differ in shape")
    return ComparisonPanel(label, np.clip(cube_rgb(est, bands), 0, 1).astype(np.float32),
                           np.abs(est - truth).mean(axis=0).astype(np.float32), float(psnr), float(ssim))


def plot_method_comparison(truth_rgb: np.ndarray, panels, path: str | Path, title: str = "") -> None:
    """One scene, every method: top row the truth and each method's reconstruction as the absolute sRGB render
    (:func:`cube_rgb`, as the demo's reconstructions.png: not exposed per image, unlike reconstruct's ``*_rgb.png``, so
    a method that is too dark looks too dark), titled with the method and its PSNR / SSIM; bottom row each
    method's mean |error| over bands on one colour scale (0 to the largest error of any method: nothing clipped)
    with one colour bar."""
    panels = list(panels)
    n = len(panels) + 1
    vmax = max(max((float(p.error.max()) for p in panels), default=0.0), 1e-6)
    fig = Figure(figsize=(2.3 * n, 5.2), layout="constrained")
    axes = fig.subplots(2, n, squeeze=False)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0, 0].imshow(np.clip(truth_rgb, 0, 1))
    axes[0, 0].set_title("ground truth", fontsize=9)
    axes[1, 0].axis("off")
    axes[1, 0].text(0.5, 0.5, "mean |error|\nover bands,\none colour scale\nfor all methods", ha="center",
                    va="center", fontsize=8, transform=axes[1, 0].transAxes)
    im = None
    for col, p in enumerate(panels, start=1):
        axes[0, col].imshow(p.rgb)
        axes[0, col].set_title(f"{p.label}\n{p.psnr:.2f} dB / SSIM {p.ssim:.3f}", fontsize=9)
        im = axes[1, col].imshow(p.error, cmap="magma", vmin=0, vmax=vmax)
        axes[1, col].set_title(f"{p.label}: mean {float(p.error.mean()):.3g}", fontsize=8)
    if im is not None:
        fig.colorbar(im, ax=axes[1, 1:].tolist(), shrink=0.9, label="mean |error| over bands")
    if title:
        fig.suptitle(title, fontsize=10)
    save_figure(fig, path)


def plot_training_curves(metrics_jsonl: str | Path, path: str | Path, loss_formula: str | None = None) -> None:
    """Training loss and the validation PSNR/SSIM versus step, from a run's metrics.jsonl (the validation
    runs on the fixed patches of the validation scenes, ``data.val_patches``, not on whole scenes as the
    evaluation does, so its figures differ from the evaluation's). ``loss_formula``
    (the run's :meth:`hsicam.config.TrainConfig.loss_formula`) titles the loss panel; the logged loss is
    the whole training loss, whatever its terms."""
    recs = [nan_for_null(json.loads(x)) for x in Path(metrics_jsonl).read_text(encoding="utf-8-sig").splitlines() if x.strip()]
    tr = [(r["step"], r["train_loss"]) for r in recs if "train_loss" in r]
    va = [(r["step"], r["val_psnr"], r["val_ssim"]) for r in recs if "val_psnr" in r and not r.get("final")]
    # PSNR and SSIM each on its own panel, with markers: on two autoscaled axes of one panel, two validation points
    # drew the two lines exactly over each other (each axis spans its own two values), under the legend
    fig = Figure(figsize=(13, 3.5), layout="constrained")
    a0, a1, a2 = fig.subplots(1, 3)
    if tr:
        a0.plot(*zip(*tr), lw=1)
    a0.set_xlabel("step")
    a0.set_ylabel("training loss (epoch running mean)")
    if loss_formula:
        a0.set_title(loss_formula, fontsize=8)
    a0.set_yscale("log")
    a0.grid(alpha=0.3)
    if va:
        s, p, q = zip(*va)
        a1.plot(s, p, "o-", color="tab:blue")
        a2.plot(s, q, "s-", color="tab:orange")
    a1.set_ylabel("PSNR on validation patches (dB)")
    a2.set_ylabel("SSIM on validation patches")
    for ax in (a1, a2):
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    save_figure(fig, path)
