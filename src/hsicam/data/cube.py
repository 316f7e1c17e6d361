"""Cube checks, resampling onto a camera's bands, and the normalisation policy.

A cube is a float32 array (C, H, W) with C bands ascending, paired with a :class:`Bands`.

**Normalisation policy** (the one place it is defined): :func:`normalize_per_cube_max` divides a
cube — after it has been resampled onto the camera's bands — by its own maximum over all bands and
pixels, so values lie in [0, 1] and the brightest sample of each scene is 1. Training patches are
cut from the normalised cube (they are *not* re-normalised per patch), so dark regions stay dark.
PSNR "peak 1" metrics assume this policy.
"""

from __future__ import annotations

import os
from typing import Union

import numpy as np

from hsicam.errors import InputError
from hsicam.spectral import Bands, resample_spectra

PathLike = Union[str, os.PathLike]


def check_cube(cube: np.ndarray, source: PathLike | str = "cube", *, allow_negative: bool = False) -> np.ndarray:
    """Validate a (C, H, W) cube and return it as float32 (C-contiguous).

    Raises :class:`InputError` naming ``source`` for a wrong number of dimensions, an empty cube,
    NaN/Inf values or negative values. With ``allow_negative=True`` negative values (e.g. dark
    noise after background subtraction) are clipped to 0 instead.
    """
    arr = np.asarray(cube)
    if arr.ndim != 3:
        raise InputError(f"{source}: expected a 3-D cube (bands, height, width), got {arr.ndim} dimensions {arr.shape}")
    if min(arr.shape) == 0:
        raise InputError(f"{source}: empty cube of shape {arr.shape}")
    if arr.dtype.kind not in "fiub":
        raise InputError(f"{source}: unsupported data type {arr.dtype} (expected real numbers)")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    finite = np.isfinite(out)
    if not finite.all():
        bad = int(out.size - np.count_nonzero(finite))
        raise InputError(f"{source}: {bad} NaN/Inf value(s) in the cube (after conversion to float32)")
    lo = float(out.min())
    if lo < 0:
        if not allow_negative:
            neg = int(np.count_nonzero(out < 0))
            raise InputError(f"{source}: {neg} negative radiance value(s) (minimum {lo:.4g}); "
                             "radiance and reflectance must be >= 0")
        np.maximum(out, 0.0, out=out)
    return out


def resample_cube(cube: np.ndarray, bands: Bands, target: Bands, source: PathLike | str = "cube") -> np.ndarray:
    """Bring ``cube`` (C, H, W) on ``bands`` onto ``target`` by linear interpolation in band centre.

    No extrapolation: raises :class:`InputError` (naming ``source``) when the target range reaches
    outside the cube's range. Returns float32.
    """
    if cube.shape[0] != len(bands):
        raise InputError(f"{source}: the cube has {cube.shape[0]} bands but its band list has {len(bands)}")
    if bands.matches(target):
        return np.asarray(cube, dtype=np.float32)
    if not bands.covers(target):
        raise InputError(
            f"{source}: the camera's bands {target.min_nm:g}-{target.max_nm:g} nm are not covered by the data's "
            f"{bands.min_nm:g}-{bands.max_nm:g} nm (no extrapolation)"
        )
    return np.asarray(resample_spectra(np.asarray(cube, dtype=np.float64), bands, target, axis=0), dtype=np.float32)


def normalize_per_cube_max(cube: np.ndarray, source: PathLike | str = "cube") -> tuple[np.ndarray, float]:
    """The normalisation policy: divide by the cube's maximum → values in [0, 1]. Returns (cube, max).

    Raises :class:`InputError` for an all-zero cube (nothing to learn from, and no scale).
    """
    peak = float(np.max(cube))
    if not peak > 0:
        raise InputError(f"{source}: the cube is all zeros; cannot normalise by its maximum")
    return (np.asarray(cube, dtype=np.float32) / np.float32(peak)).astype(np.float32, copy=False), peak


__all__ = ["check_cube", "normalize_per_cube_max", "resample_cube"]
