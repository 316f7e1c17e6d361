"""Pictures of a camera: PSF montage, CFA tile (colour + transmission curves), DOE height map."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import numpy as np
import torch
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from hsicam.errors import InputError
from hsicam.io import save_figure, write_json, write_npy
from hsicam.spectral import Bands


def encircled_energy(psf: np.ndarray, radii_px: np.ndarray) -> np.ndarray:
    """Light of each band inside a circle of radius r about the kernel centre (the optical axis).

    Args:
        psf: (C, K, K) PSF stack (energy fraction per pixel).
        radii_px: (R,) radii in pixels; a pixel counts when its centre lies within r.
    Returns:
        (C, R) energy fractions (of the band's whole light when the stack is physically normalised).

    Memory O(C·K²), whatever R: the pixels are sorted by radius once, each band's light summed
    cumulatively in that order, and each radius reads the sum over the pixels up to it.
    """
    psf = np.asarray(psf, dtype=np.float64)
    r = np.asarray(radii_px, dtype=np.float64)
    if psf.ndim != 3 or r.ndim != 1:
        raise ValueError(f"expected a (C, K, K) stack and (R,) radii, got {psf.shape} and {r.shape}")
    c, k = psf.shape[0], psf.shape[-1]
    yy, xx = np.mgrid[:k, :k] - k // 2
    rr = np.hypot(yy, xx).ravel()  # (K²,) pixel-centre radii, px
    order = np.argsort(rr, kind="stable")
    cumulative = np.zeros((c, rr.size + 1))
    np.cumsum(psf.reshape(c, -1)[:, order], axis=1, out=cumulative[:, 1:])  # light of the n nearest pixels
    n_inside = np.searchsorted(rr[order], r + 1e-9, side="right")  # (R,) pixels with centre within r
    return cumulative[:, n_inside]


def rms_radius_px(psf: np.ndarray) -> np.ndarray:
    """RMS radius (px) of each band's PSF about the optical axis, (C,): sqrt(Σ p·r² / Σ p)."""
    psf = np.asarray(psf, dtype=np.float64)
    k = psf.shape[-1]
    yy, xx = np.mgrid[:k, :k] - k // 2
    total = np.maximum(psf.sum(axis=(-2, -1)), 1e-300)
    return np.sqrt((psf * (yy**2 + xx**2)).sum(axis=(-2, -1)) / total)


def encircled_fraction_in_square(psf: np.ndarray, size: int) -> np.ndarray:
    """Fraction of each band's light in the kernel that lies in the central ``size``×``size`` px, (C,)."""
    psf = np.asarray(psf, dtype=np.float64)
    k = psf.shape[-1]
    a = (k - min(size, k)) // 2
    inside = psf[:, a : a + size, a : a + size].sum(axis=(-2, -1))
    return inside / np.maximum(psf.sum(axis=(-2, -1)), 1e-300)


def psf_crop_px(psf: np.ndarray, fraction: float = 0.99, minimum: int = 15) -> int:
    """Smallest odd centred crop that holds ``fraction`` of every band's light in the kernel
    (at least ``minimum`` px, at most the kernel)."""
    psf = np.asarray(psf, dtype=np.float64)  # once, not in every trial below
    k = psf.shape[-1]
    for size in range(min(minimum, k) | 1, k + 1, 2):
        if np.all(encircled_fraction_in_square(psf, size) >= fraction):
            return size
    return k


#: Light of every band that the montage's automatic crop holds (:func:`plot_psf_montage`).
MONTAGE_CROP_FRACTION = 0.9


def plot_psf_montage(psf: np.ndarray, bands: Bands, path: str | Path, decades: float = 4.0,
                     crop_px: int | None = None) -> int:
    """Band PSFs and how they differ: a montage (log scale) and the encircled-energy curves.

    Top: each band's PSF over the central ``crop_px`` pixels (None: the smallest crop holding
    :data:`MONTAGE_CROP_FRACTION` (90 %) of every band's light in the kernel, at least 15 px,
    :func:`psf_crop_px`), normalised to its own peak and shown over ``decades`` decades (log10), so
    that a diffuse halo is as visible as a sharp core; titles give the band and its RMS radius.
    Bottom: encircled energy against radius for every band, coloured by wavelength, over the whole
    kernel, which shows the light outside the crop. (A 99 % crop showed a trained ~2 px PSF, whose
    faint halo reaches 50 px, as a dot in a 103 px square.)

    Args:
        psf: (C, K, K) PSF stack.
    Returns:
        The crop shown, px.
    """
    psf = np.asarray(psf, dtype=np.float64)
    c, k, _ = psf.shape
    rms = rms_radius_px(psf)
    crop = psf_crop_px(psf, MONTAGE_CROP_FRACTION) if crop_px is None else min(int(crop_px), k)
    a = (k - crop) // 2
    shown = psf[:, a : a + crop, a : a + crop]
    cols = min(8, c)
    rows = math.ceil(c / cols)
    fig = Figure(figsize=(1.6 * cols, 1.75 * rows + 3.2), layout="constrained")
    grid = fig.add_gridspec(rows + 1, cols, height_ratios=[1.0] * rows + [1.8])
    tiles = []
    for i in range(c):
        ax = fig.add_subplot(grid[i // cols, i % cols])
        ax.axis("off")
        img = shown[i] / max(shown[i].max(), 1e-300)
        im = ax.imshow(np.log10(np.maximum(img, 10.0**-decades)), cmap="inferno", vmin=-decades, vmax=0,
                       interpolation="nearest")
        ax.set_title(f"{bands.centers_nm[i]:g} nm, r {rms[i]:.1f}", fontsize=7)
        tiles.append(ax)
    fig.colorbar(im, ax=tiles, shrink=0.6, label="log10(PSF / its band's peak)")  # one scale for every tile
    ax = fig.add_subplot(grid[rows, :])
    radii = np.arange(0, max(k // 2 * math.sqrt(2) + 1.0, 2.0))  # (a 1×1 kernel: radii 0 and 1, not 0 alone)
    ee = encircled_energy(psf, radii)
    cmap = matplotlib.colormaps["turbo"]
    lo, hi = float(np.min(bands.centers_nm)), float(np.max(bands.centers_nm))
    for i in range(c):
        ax.plot(radii[1:], ee[i, 1:], color=cmap((bands.centers_nm[i] - lo) / max(hi - lo, 1e-9)), lw=1,
                marker="o" if len(radii) == 2 else None)  # one radius: a point, which a line does not draw
    ax.set_xscale("log")
    ax.set_xlabel("radius (px)")
    ax.set_ylabel("encircled energy")
    # the lowest curve's start, rounded down to a tenth: a sharp camera's curves (0.85-1) are not squeezed flat
    ax.set_ylim(max(0.0, math.floor(float(ee[:, 1:].min()) * 10) / 10 - 0.1), 1.02)
    ax.grid(True, alpha=0.3)
    sm = ScalarMappable(cmap=cmap, norm=Normalize(lo, hi))
    fig.colorbar(sm, ax=ax, label="band (nm)", pad=0.01)
    held = math.floor(float(encircled_fraction_in_square(psf, crop).min()) * 100) / 100  # "≥": rounded down
    fig.suptitle(f"PSF per band: central {crop}×{crop} of {k}×{k} px (≥ {held:.0%} of each band's light in the "
                 f"kernel), log10 of each band's peak over {decades:g} decades, r = RMS radius (px)\n"
                 f"below: light within a radius, over the whole kernel", fontsize=9)
    save_figure(fig, path)
    return crop


def cfa_tile_rgb(tile: np.ndarray, bands: Bands) -> np.ndarray:
    """sRGB colour of each filter of a (C, m, m) tile, (m, m, 3) in [0, 1].

    Each filter's transmission is scaled to a peak of 1 before rendering (as a reflectance under
    D65), so the picture shows hue and saturation; absolute transmission is in the curves.
    """
    import torch

    from hsicam.color import spectra_to_srgb

    t = np.asarray(tile, dtype=np.float64)
    spectra = np.moveaxis(t, 0, -1)
    spectra = spectra / np.maximum(spectra.max(axis=-1, keepdims=True), 1e-12)
    return spectra_to_srgb(torch.from_numpy(spectra), bands).numpy()


def plot_cfa(tile: np.ndarray, bands: Bands, path: str | Path) -> None:
    """CFA tile rendered in colour next to the transmission curves of all its filters."""
    t = np.asarray(tile, dtype=np.float64)
    rgb = cfa_tile_rgb(t, bands)
    m = t.shape[-1]
    # constrained: the tile's title ran into the curves' y label (session 74's figure hunt)
    fig = Figure(figsize=(9, 3.6), layout="constrained")
    a0, a1 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.6]})
    a0.imshow(rgb, interpolation="nearest")
    a0.set_title(f"CFA tile {m}×{m}\n(sRGB, each filter peak-normalised)", fontsize=9)
    a0.set_xticks([])
    a0.set_yticks([])
    curves = t.reshape(t.shape[0], -1).T
    for i, curve in enumerate(curves):
        a1.plot(bands.centers_nm, curve, color=np.clip(rgb.reshape(-1, 3)[i], 0, 0.85), lw=0.8)
    a1.set_xlabel("wavelength (nm)")
    a1.set_ylabel("transmission κ (Σ over bands = 1)")
    a1.set_title("filter transmission curves", fontsize=9)
    a1.grid(alpha=0.3)
    save_figure(fig, path)


def plot_doe_heights(height_m: np.ndarray, aperture: np.ndarray, cell_um: float, path: str | Path) -> None:
    """DOE height map in nm over the aperture (outside shown blank): ``height_m`` (n, n) above the lowest cell (the
    piston removed, :func:`hsicam.optics.perturb.design_heights`), ``aperture`` (n, n) the open area fraction per cell."""
    h = np.asarray(height_m, dtype=np.float64) * 1e9
    shown = np.where(np.asarray(aperture) > 0, h, np.nan)
    n = h.shape[0]
    half = n * cell_um * 1e-3 / 2
    fig = Figure(figsize=(4.6, 3.8))
    ax = fig.subplots()
    im = ax.imshow(shown, cmap="viridis", extent=(-half, half, -half, half), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"DOE height map ({n}×{n} cells of {cell_um:g} µm)", fontsize=9)
    fig.colorbar(im, ax=ax, label="height above the lowest cell (nm)")
    save_figure(fig, path)


def write_psf_outputs(camera, out: Path, generator: torch.Generator | None = None, design: bool = False) -> dict:
    """psf.npy (C, K, K float32), psf.json (geometry, model, energy per band), psf.png (montage),
    and what is needed to recompute the PSFs independently: doe_height_m.npy (heights per DOE
    cell, m, (n, n) float64, exactly those used, fabrication noise included when enabled, drawn from
    ``generator``: the same element for the same seed; ``design``: the heights without it, as the camera figures
    draw them, psf.json's ``heights`` says which) and aperture.npy (transmission per pupil cell,
    (n·q, n·q) float64, area fraction in the circle). A measured-PSF camera writes the PSFs it images with."""
    optics = camera.optics
    sigma_nm = optics.doe.sigma_height_m * 1e9 if optics.doe.enabled else 0.0
    with torch.no_grad():
        heights = optics.doe.heights(generator, noise=not design)
        res = camera.psf_result() if camera.kind == "measured_psf" else optics.psf_from_pupil(optics.expand_cells(heights))
    psf = res.psf.float().cpu().numpy()
    desc = optics.describe()
    info = {
        "bands_nm": camera.bands.centers_nm.tolist(),
        "fwhm_nm": camera.bands.fwhm_nm.tolist(),
        "pixel_pitch_um": optics.pixel_m * 1e6,
        "kernel_px": camera.kernel_px,
        "energy_in_kernel": res.energy.cpu().double().numpy().tolist(),
        "lens": desc["lens"],
        "doe": desc["doe"],
        "aperture_radius_mm": desc["aperture_radius_mm"],
        "sampling": desc["sampling"],
        "model": desc["model"] if camera.kind != "measured_psf" else "measured PSFs (imported, fixed)",
        **({"heights": (f"the design, without the fabrication noise σ_p = {sigma_nm:g} nm" if design else
                        f"one draw of the fabrication noise σ_p = {sigma_nm:g} nm")}
           if sigma_nm > 0 and camera.kind != "measured_psf" else {}),
        "files": {
            "doe_height_m.npy": f"DOE heights (m) per {optics.cell_m * 1e6:g} µm cell, {optics.doe.n_cells}x{optics.doe.n_cells}, "
                                "row = y, column = x, centre cell on the optical axis",
            "aperture.npy": f"aperture transmission per {optics.sampling.pupil_pitch_m * 1e6:g} µm pupil cell "
                            "(area fraction inside the circle)",
        },
    }
    write_npy(out / "psf.npy", psf)
    write_npy(out / "doe_height_m.npy", heights.detach().cpu().double().numpy())
    write_npy(out / "aperture.npy", optics.amplitude.detach().cpu().double().numpy())
    write_json(out / "psf.json", info)
    plot_psf_montage(psf, camera.bands, out / "psf.png")
    return info


def write_optics_figures(camera, out: Path, prefix: str = "", psf: bool = False) -> dict[str, str]:
    """The camera's figures in ``out``: ``{prefix}psf.png`` (with ``psf``), ``{prefix}doe.png``
    (height map and aperture), ``{prefix}cfa.png`` (tile and transmission curves) — those the
    camera has. Returns {file name: caption}. The one place camera figures are drawn.

    A DOE is drawn as designed (:func:`hsicam.optics.perturb.design_heights`: piston removed, as exported) and its PSFs
    of those heights: a camera with fabrication noise σ_p draws another element at every capture, and a figure of
    one unseeded draw was neither the element simulated nor the one scored (session 74's figure hunt)."""
    from hsicam.optics.perturb import design_heights
    from hsicam.optics.perturb import nominal_heights, psf_for_heights

    out, written = Path(out), {}
    optics = getattr(camera, "optics", None)
    doe_on = optics is not None and optics.doe.enabled  # no DOE (h = 0): no height map to draw (export-optics: none)
    # (a measured-PSF camera images with its measured PSFs, no σ_p: nothing left out to say)
    sigma_nm = optics.doe.sigma_height_m * 1e9 if doe_on and getattr(camera, "kind", "") != "measured_psf" else 0.0
    design = (f"; the design, without the fabrication noise σ_p = {sigma_nm:g} nm each capture draws"
              if sigma_nm > 0 else "")
    with torch.no_grad():
        if psf and hasattr(camera, "psf_result"):
            res = (psf_for_heights(optics, nominal_heights(camera)) if sigma_nm > 0 and camera.kind != "measured_psf"
                   else camera.psf_result())
            if not bool(torch.isfinite(res.psf).all()):  # a damaged camera (e.g. DOE heights of 1e38 m), not a figure
                raise InputError(f"its PSF holds {int((~torch.isfinite(res.psf)).sum())} NaN/Inf value(s) (DOE heights "
                                 f"up to {float(camera.optics.doe.heights(noise=False).abs().max()):.3g} m)"
                                 if getattr(camera, "optics", None) is not None else "its PSF holds NaN/Inf values")
            crop = plot_psf_montage(res.psf.float().cpu().numpy(), camera.bands, out / f"{prefix}psf.png")
            written[f"{prefix}psf.png"] = (f"PSF per band (log scale, central {crop}×{crop} px) and encircled energy; "
                                           f"energy in kernel "
                                           f"{res.energy.min().item():.4f}–{res.energy.max().item():.4f}{design}")
        if doe_on:
            # the aperture per cell as its area fraction (a q-oversampled pupil's top-left sample per cell lost the
            # disc's top and left rim)
            heights, aperture, _ = design_heights(camera)
            plot_doe_heights(heights, aperture, optics.cell_m * 1e6, out / f"{prefix}doe.png")
            written[f"{prefix}doe.png"] = f"DOE height map (above its lowest cell, as exported{design})"
        cfa = getattr(camera, "cfa", None)
        if cfa is not None and cfa.enabled:  # no CFA (κ = 1): no tile to draw (a figure said "Σ over bands = 1" of κ = 1)
            plot_cfa(cfa.tile().detach().cpu().numpy(), camera.bands, out / f"{prefix}cfa.png")
            written[f"{prefix}cfa.png"] = "colour filter array tile and transmission curves"
    return written
