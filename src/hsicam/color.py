"""Colour rendering of spectra: CIE 1931 2° observer × D65 → XYZ → linear sRGB → sRGB gamma.

Spectra are treated as **reflectances under D65** (HSI2RGB style): a spectrum ``s`` on the band
grid ``bands`` is reconstructed piecewise-linearly between band centres (the interpolant that
:func:`hsicam.spectral.resample_spectra` also integrates for bands wider than the data's), multiplied by D65 and the colour-matching functions and
integrated on a 1 nm grid over the bands' range. The CMF/D65 table (``resources/
cie1931_2deg_d65.csv``, 5 nm, 380-780 nm, from colour-science) ships with the package, so rendering
needs neither colour-science nor a network.

Normalisation: ``spectra_to_xyz`` scales so that a perfect white reflector (all ones) has Y = 1;
``spectra_to_srgb`` additionally scales each linear sRGB channel so that the perfect white reflector
maps exactly to (1, 1, 1) (a camera's white balance: it absorbs the white-point error of a truncated or
coarse grid, e.g. 420-720 nm) when each channel's white is within :data:`WHITE_BALANCE_RANGE`, i.e.
the grid covers part of every primary's spectrum. A grid that misses a primary's (550-700 nm, say,
where blue's white is negative) is rendered without that balance, so its hues stay right and its white
is tinted: balancing there divided by near-zero or negative sums and turned a 620 nm line white. Its
channels are scaled together so that the white's brightest is 1, and previews expose it by that channel
(with Y = 1 a 650-950 nm grid's white had R = 7.2, and every preview was one flat red).
Values outside [0, 1] are clipped before gamma encoding.

Band grids beyond the table (a VIS-NIR camera, 500-900 nm) are rendered from the part of their
range inside 380-780 nm: the other bands carry no colour. A grid with nothing inside (800-1000 nm)
renders grey, the mean over its bands, so a preview never stops a simulation or a reconstruction.

The conversions accept numpy arrays or torch tensors (differentiable; computed in the input's dtype
and device) and return the same kind; the display previews (:func:`srgb_preview`, :func:`preview_exposure`)
take NumPy cubes only.
"""

from __future__ import annotations

import functools
import math
from importlib import resources
from typing import Union

import numpy as np
import torch

from hsicam.errors import InputError
from hsicam.spectral import Bands, interpolation_matrix

Array = Union[np.ndarray, torch.Tensor]

#: Wavelength range of the shipped CMF/D65 table, nm.
TABLE_RANGE_NM = (380.0, 780.0)

#: sRGB primaries and white point (IEC 61966-2-1), CIE xy.
_SRGB_PRIMARIES_XY = np.array([[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]])
_D65_WHITE_XY = np.array([0.3127, 0.3290])


@functools.lru_cache(maxsize=1)
def cmf_d65_table() -> np.ndarray:
    """The shipped table as an array (N, 5): wavelength nm, x̄, ȳ, z̄, D65 (relative)."""
    text = resources.files("hsicam").joinpath("resources/cie1931_2deg_d65.csv").read_text(encoding="utf-8")
    rows = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    table = np.array([[float(v) for v in ln.split(",")] for ln in rows[1:]], dtype=np.float64)
    table.setflags(write=False)
    return table


def _d65_white_xyz() -> np.ndarray:
    """XYZ (3,) of the D65 white point with Y = 1 (linear sRGB (1, 1, 1))."""
    wx, wy = _D65_WHITE_XY
    return np.array([wx / wy, 1.0, (1 - wx - wy) / wy])


def xyz_to_linear_srgb_matrix() -> np.ndarray:
    """The 3×3 matrix M with linear sRGB = M @ XYZ, derived from the sRGB primaries and D65 white."""
    xy = _SRGB_PRIMARIES_XY
    prim = np.stack([xy[:, 0] / xy[:, 1], np.ones(3), (1 - xy[:, 0] - xy[:, 1]) / xy[:, 1]])  # columns: XYZ of R, G, B (Y=1)
    scale = np.linalg.solve(prim, _d65_white_xyz())
    return np.linalg.inv(prim * scale[None, :])


#: Range of every linear sRGB channel's white-reflector value within which :func:`srgb_weights` balances
#: the channels to 1 (a factor 3 either way; 420-720 nm: 0.99, 1.01, 0.95; 550-700 nm: 2.5, 0.65, −0.13).
WHITE_BALANCE_RANGE = (1.0 / 3.0, 3.0)


@functools.lru_cache(maxsize=32)
def _xyz_weights_cached(centers: tuple[float, ...]) -> np.ndarray:
    c = np.asarray(centers, dtype=np.float64)
    lo, hi = TABLE_RANGE_NM
    a, b = max(c[0], lo), min(c[-1], hi)  # the part of the grid's range that has colour
    if a > b + 1e-9 or (c.size == 1 and not lo - 1e-9 <= c[0] <= hi + 1e-9):
        # nothing inside the table (e.g. 800-1000 nm): grey, the mean over the bands, white point Y = 1
        w = np.outer(_d65_white_xyz(), np.full(c.size, 1.0 / c.size))
        w.setflags(write=False)
        return w
    table = cmf_d65_table()
    if c.size == 1:
        fine = c.copy()
        weights_fine = np.ones(1)
    elif b - a < 1e-9:  # the grid touches the table at one end only (…-380 or 780-…): that wavelength alone
        fine = np.array([a])
        weights_fine = np.ones(1)
    else:
        inner = np.arange(np.ceil(a), np.floor(b) + 1.0, 1.0)
        fine = np.unique(np.concatenate([[a], inner, [b]]))
        weights_fine = np.zeros_like(fine)  # trapezoid weights on the fine grid, nm
        d = np.diff(fine)
        weights_fine[:-1] += d / 2
        weights_fine[1:] += d / 2
    cmf = np.stack([np.interp(fine, table[:, 0], table[:, k]) for k in (1, 2, 3)])  # (3, F)
    d65 = np.interp(fine, table[:, 0], table[:, 4])
    kernel = cmf * d65[None, :] * weights_fine[None, :]  # (3, F)
    if c.size == 1:
        w = kernel
    else:  # the piecewise-linear spectrum between band centres, evaluated on the fine grid
        interp = interpolation_matrix(Bands.from_centers(c), Bands.from_centers(fine))  # (F, C)
        w = kernel @ interp  # (3, C)
    w = w / w[1].sum()  # perfect white reflector: Y = 1
    w.setflags(write=False)
    return w


def xyz_weights(bands: Bands) -> np.ndarray:
    """Weights W (3, C), float64, with XYZ = W @ reflectance (white reflector: Y = 1). Bands outside
    380-780 nm get no weight beyond their share of the interpolant inside it; a grid entirely outside
    gives grey (module docstring)."""
    return _xyz_weights_cached(tuple(float(v) for v in bands.centers_nm))


def white_balanced(bands: Bands) -> bool:
    """Whether :func:`srgb_weights` balances ``bands``' white to (1, 1, 1): each channel's white (Y = 1) within
    :data:`WHITE_BALANCE_RANGE`, a grid covering every primary's spectrum."""
    white = (xyz_to_linear_srgb_matrix() @ xyz_weights(bands)).sum(axis=1)
    lo, hi = WHITE_BALANCE_RANGE
    return bool(np.all((white >= lo) & (white <= hi)))


def srgb_weights(bands: Bands) -> np.ndarray:
    """Weights W (3, C) with linear sRGB = W @ reflectance. All-ones maps exactly to (1, 1, 1) when the grid is
    :func:`white_balanced`; otherwise the channels are left unbalanced, so hues stay right, and scaled together so
    that the white's brightest channel is 1 (with Y = 1, a red or near-infrared grid's white had R = 5.6 at 600-900 nm
    and 7.2 at 650-950 nm: every pixel brighter than a fifth of white rendered as one flat red; session 75's hunt)."""
    w = xyz_to_linear_srgb_matrix() @ xyz_weights(bands)
    white = w.sum(axis=1, keepdims=True)
    if white_balanced(bands):
        return w / white
    top = float(white.max())
    return w / top if top > 0 else w


def srgb_encode(linear: Array) -> Array:
    """sRGB transfer function (IEC 61966-2-1) of linear values, clipped to [0, 1] first."""
    if isinstance(linear, torch.Tensor):
        x = linear.clamp(0.0, 1.0)
        hi = 1.055 * x.clamp(min=0.0031308).pow(1.0 / 2.4) - 0.055  # clamp keeps the gradient finite
        return torch.where(x <= 0.0031308, 12.92 * x, hi)
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1.0 / 2.4) - 0.055)


def _apply(spectra: Array, w: np.ndarray, what: str, n: int) -> Array:
    if not isinstance(spectra, torch.Tensor):
        spectra = np.asarray(spectra)
    if spectra.ndim == 0 or spectra.shape[-1] != n:
        raise InputError(f"{what}: the last axis must hold the {n} bands, got shape {tuple(spectra.shape)}")
    if isinstance(spectra, torch.Tensor):
        dtype = spectra.dtype if spectra.is_floating_point() else torch.float32
        wt = torch.as_tensor(w, dtype=dtype, device=spectra.device)
        return spectra.to(dtype) @ wt.T
    return np.asarray(spectra, dtype=np.float64) @ w.T


def spectra_to_xyz(spectra: Array, bands: Bands) -> Array:
    """CIE XYZ (..., 3) of reflectance spectra (..., C) under D65; white reflector has Y = 1."""
    return _apply(spectra, xyz_weights(bands), "spectra_to_xyz", len(bands))


def spectra_to_linear_srgb(spectra: Array, bands: Bands) -> Array:
    """Linear sRGB (..., 3), unclipped, of reflectance spectra (..., C) under D65; white → (1, 1, 1) on a grid
    covering every primary's spectrum, tinted on one that misses part of it (:func:`srgb_weights`)."""
    return _apply(spectra, srgb_weights(bands), "spectra_to_linear_srgb", len(bands))


def spectra_to_srgb(spectra: Array, bands: Bands) -> Array:
    """Gamma-encoded sRGB in [0, 1], shape (..., 3), of reflectance spectra (..., C) under D65."""
    return srgb_encode(spectra_to_linear_srgb(spectra, bands))


def _check_band_axis(cube: Array, axis: int, bands: Bands, what: str) -> None:
    """:class:`InputError` in the user's own shape when ``cube``'s band axis ``axis`` does not hold ``bands``
    (naming the transpose when its last axis does: a cube stored bands last)."""
    n = len(bands)
    if cube.shape[axis] == n:
        return
    layout = "(C, H, W)" if axis == 0 else "(B, C, H, W)"
    move = f"cube.movedim(-1, {axis})" if isinstance(cube, torch.Tensor) else f"np.moveaxis(cube, -1, {axis})"
    hint = f"; its last axis has the bands: a cube stored bands last is {move}" if cube.shape[-1] == n else ""
    raise InputError(f"{what}: the cube must be {layout} with the {n} bands of {bands!r} on axis {axis}, "
                     f"got shape {tuple(cube.shape)}{hint}")


def cube_to_srgb(cube: Array, bands: Bands) -> Array:
    """sRGB render of a cube (B, C, H, W) → (B, 3, H, W), or (C, H, W) → (3, H, W); values in [0, 1]."""
    if cube.ndim not in (3, 4):
        raise InputError(f"cube_to_srgb expects (C, H, W) or (B, C, H, W), got shape {tuple(cube.shape)}")
    axis = cube.ndim - 3
    _check_band_axis(cube, axis, bands, "cube_to_srgb")
    if isinstance(cube, torch.Tensor):
        rgb = spectra_to_srgb(cube.movedim(axis, -1), bands)
        return rgb.movedim(-1, axis)
    rgb = spectra_to_srgb(np.moveaxis(np.asarray(cube), axis, -1), bands)
    return np.moveaxis(rgb, -1, axis)


#: Pixels of the cube that :func:`srgb_preview` renders at a time (256 Ki: 32 MB of a 31-band cube).
PREVIEW_CHUNK_PX = 1 << 18


#: Where every exposed display preview puts the 99th percentile of its image (simulate's sensor preview,
#: :func:`hsicam.data.images.sensor_preview`) or of its luminance (reconstruct's ``*_rgb.png``,
#: :func:`preview_exposure`; ``data show``'s thumbnails).
PREVIEW_LEVEL = 0.8
#: The PNG text chunk in which an exposed preview records its exposure (the gain its values were multiplied by).
PREVIEW_EXPOSURE_KEY = "hsicam-display-preview-exposure"


def display_gain(p99: float) -> float:
    """The exposure of a display preview whose image (or luminance) has the 99th percentile ``p99``: the gain that
    puts it at :data:`PREVIEW_LEVEL`; 1 when ``p99`` is not a positive finite number or the gain would not be a
    finite float32 (a denormal-dim image)."""
    gain = PREVIEW_LEVEL / p99 if math.isfinite(p99) and p99 > 0 else 1.0
    return gain if gain < float(np.finfo(np.float32).max) else 1.0


def _checked_preview_cube(cube: np.ndarray, bands: Bands, what: str) -> None:
    if not isinstance(cube, np.ndarray):
        hint = ": cube.detach().cpu().numpy()" if isinstance(cube, torch.Tensor) else ""
        raise InputError(f"{what}: the cube must be a NumPy array (C, H, W), got {type(cube).__name__}{hint}")
    if cube.ndim != 3:
        raise InputError(f"{what}: the cube must be (C, H, W), got shape {tuple(cube.shape)}")
    _check_band_axis(cube, 0, bands, what)


def _row_chunks(cube: np.ndarray, chunk_px: int | None):
    """Row slices of about ``chunk_px`` pixels (default :data:`PREVIEW_CHUNK_PX`) covering the (C, H, W) cube."""
    _, h, w = cube.shape
    rows = max(1, int(PREVIEW_CHUNK_PX if chunk_px is None else chunk_px) // w)
    return [slice(r0, r0 + rows) for r0 in range(0, h, rows)]


def preview_exposure(cube: np.ndarray, bands: Bands, chunk_px: int | None = None) -> float:
    """The gain that puts the 99th percentile of the luminance of a (C, H, W) cube (CIE 1931 Y, a white
    reflector's Y = 1) at :data:`PREVIEW_LEVEL`: the exposure of a display preview, so that a dim cube is seen and a
    tiny highlight does not set the scale; NaN pixels are left out; 1 when that percentile is not above 0 or the
    gain would not be a finite float32. A grid that is not :func:`white_balanced` (it misses a primary: a red or
    near-infrared camera) takes the brightest linear sRGB channel instead of Y: its white is far from grey, and Y at
    0.8 put every pixel's red past full scale. Computed a band of rows at a time (float32: with the percentile's
    copy, 2/C of the cube)."""
    _checked_preview_cube(cube, bands, "preview_exposure")
    balanced = white_balanced(bands)
    w = (xyz_weights(bands)[1:2] if balanced else srgb_weights(bands)).astype(np.float32)
    y = np.empty(cube.shape[1:], dtype=np.float32)
    for rows in _row_chunks(cube, chunk_px):
        y[rows] = np.tensordot(w, cube[:, rows].astype(np.float32, copy=False), axes=1).max(axis=0)
    return display_gain(float(np.nanpercentile(y, 99)) if not np.isnan(y).all() else math.nan)


def srgb_preview(cube: np.ndarray, bands: Bands, chunk_px: int | None = None, exposure: float = 1.0) -> np.ndarray:
    """The 8-bit sRGB preview (H, W, 3) uint8 of a (C, H, W) float32 cube: :func:`cube_to_srgb` of the cube times
    ``exposure`` (default 1: the absolute render, as the experiments' comparison figures draw every method;
    ``reconstruct``'s ``*_rgb.png`` takes :func:`preview_exposure`), quantised as :func:`hsicam.io.write_png8`
    does, rendered a band of rows (about ``chunk_px`` pixels, default :data:`PREVIEW_CHUNK_PX`) at a time, so its
    temporaries stay that size whatever the cube's (whole, they were half a cube; the same values: each pixel's
    colour is its own). A pixel with a NaN band is black."""
    from hsicam.io import png8_values

    _checked_preview_cube(cube, bands, "srgb_preview")
    if not (isinstance(exposure, (int, float, np.floating, np.integer)) and not isinstance(exposure, bool)
            and math.isfinite(exposure) and exposure > 0):
        raise InputError(f"srgb_preview: exposure must be a positive number, got {exposure!r}")
    out = np.empty((*cube.shape[1:], 3), dtype=np.uint8)
    for rows in _row_chunks(cube, chunk_px):
        rgb = cube_to_srgb(torch.from_numpy(cube[:, rows]) * float(exposure), bands).numpy()  # × 1: exact
        out[rows] = png8_values(np.moveaxis(rgb, 0, -1))
    return out


__all__ = [
    "PREVIEW_CHUNK_PX",
    "PREVIEW_EXPOSURE_KEY",
    "PREVIEW_LEVEL",
    "TABLE_RANGE_NM",
    "WHITE_BALANCE_RANGE",
    "white_balanced",
    "cmf_d65_table",
    "cube_to_srgb",
    "display_gain",
    "preview_exposure",
    "spectra_to_linear_srgb",
    "spectra_to_srgb",
    "spectra_to_xyz",
    "srgb_encode",
    "srgb_preview",
    "srgb_weights",
    "xyz_to_linear_srgb_matrix",
    "xyz_weights",
]
