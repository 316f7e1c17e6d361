"""The tolerance figure (:mod:`hsicam.engine.tolerance` computes the sweeps)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

def levels_text(result: dict[str, Any]) -> str:
    """The level-count part of the one-line tolerance summary: "levels ≥ L" only when the sweep
    brackets L (a swept count below it loses more than 1 dB); else what was found and why it is no
    requirement (e.g. "not bracketed: only one value tried"). "" when the levels were not swept."""
    s = result.get("summary") or {}
    if "levels" not in (result.get("sweeps") or {}):
        return ""
    lv = s.get("min_levels_within_1db")
    if lv is None:
        return f"levels: {s.get('levels_note') or 'no swept level count within 1 dB'}"
    if s.get("levels_bracketed", True):
        return f"levels ≥ {lv}"
    return f"levels: {lv} within 1 dB, {s.get('levels_note') or 'not bracketed'}"


def above_reference_text(result: dict[str, Any]) -> str:
    """The one-line summary's note on the perturbed rows (value ≠ 0) that scored above their reference (the
    nominal; a shift's: the unshifted reference): how many and the largest gain, which is the size of the scatter of
    the study's scores on its scenes, so its 1-dB tolerances are uncertain by as much. "" when none did."""
    nominal = result["nominal"]["psnr"]
    shift_ref = (result.get("shift_reference") or {}).get("psnr")
    perturbed = [r for r in result.get("rows") or [] if r["value"] != 0]
    gains = []
    for r in perturbed:
        ref = shift_ref if r["sweep"].startswith("shift") and shift_ref is not None else nominal
        if r["psnr"] > ref:
            gains.append((r["psnr"] - ref, r))
    if not gains:
        return ""
    gain, row = max(gains, key=lambda t: t[0])
    return (f"{len(gains)} of {len(perturbed)} perturbed rows scored above their reference (up to +{gain:.2f} dB, "
            f"{row['sweep']} {row['value']:g}): the scores of {len(result['scenes'])} scene(s) move by that much, so "
            "the 1-dB tolerances are uncertain by as much (--max-scenes scores more)")


#: The distance a diagonal shift of 1 cell per axis moves the DOE (cells).
DIAGONAL_DISTANCE = 2 ** 0.5


def plot_tolerance(result: dict[str, Any], path: str | Path) -> None:
    """PSNR versus each perturbation (2×2 panels), nominal as a dashed line; a sweep recorded in
    ``result["skipped"]`` (e.g. the DOE sweeps of a camera without a DOE) gets its reason instead."""
    from matplotlib.figure import Figure

    from hsicam.io import save_figure

    sw = result["sweeps"]
    nom = result["nominal"]["psnr"]
    fig = Figure(figsize=(9, 6.5))
    axes = fig.subplots(2, 2)
    panels = [
        (axes[0, 0], ["sigma_height_nm"], "height noise σ$_p$ (nm)", False),
        (axes[0, 1], ["levels"], "quantisation levels L", True),
        (axes[1, 0], ["shift_x_cells", "shift_diag_cells"], "DOE lateral shift, its distance (cells)", False),
        (axes[1, 1], ["sensor_distance_um"], "sensor distance error Δz (µm)", False),
    ]
    skipped = result.get("skipped") or {}
    for ax, keys, label, logx in panels:
        why = next((skipped[k] for k in (keys[0], keys[0].split("_")[0]) if k in skipped), None)
        if why is not None:  # a sweep that does not apply to this camera (e.g. no DOE)
            ax.text(0.5, 0.5, "not studied:\n" + textwrap.fill(why, 42), ha="center", va="center", fontsize=8,
                    transform=ax.transAxes)
            ax.set_xlabel(label)
            ax.set_xticks([])
            ax.set_yticks([])
            continue
        for key in keys:
            if key not in sw:
                continue
            s = sw[key]
            # a diagonal shift of s cells per axis moves the element s·√2 cells: drawn at that distance (drawn at s,
            # beside the x shifts, it looked √2 times more tolerant than it is; tolerance.json keeps s per axis)
            scale = DIAGONAL_DISTANCE if key == "shift_diag_cells" else 1.0
            ax.errorbar([v * scale for v in s["values"]], s["psnr"], yerr=s["psnr_std"], marker="o", ms=3, capsize=2,
                        label={"shift_x_cells": "along x",
                               "shift_diag_cells": "along the diagonal (s per axis, at s·√2)"}.get(key, None))
        ref = nom
        if keys[0].startswith("shift") and result.get("shift_reference"):
            ref = result["shift_reference"]["psnr"]
            ax.axhline(nom, ls="-.", color="silver", lw=0.8, label="nominal (trained model)")
            ax.axhline(ref, ls="--", color="gray", lw=0.8,
                       label=f"no shift, {result['shift_reference']['pupil_oversample']} samples/cell")
        else:
            ax.axhline(nom, ls="--", color="gray", lw=0.8, label="nominal")
        ax.axhline(ref - 1.0, ls=":", color="gray", lw=0.8, label="−1 dB")
        if logx:
            ax.set_xscale("log", base=2)
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Tolerance of the trained camera (network fixed): " + result["metric"].split(",")[0], fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
