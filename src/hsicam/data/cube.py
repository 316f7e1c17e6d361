"""Cube checks, the band-grid policy, the memory budget and the normalisation policy.

A cube is a float32 array (C, H, W) with C bands ascending, paired with a :class:`Bands`.

**Cube check** (one for every entry point): :func:`check_cube` — a real, finite, non-negative,
non-empty (C, H, W) array whose band count matches its band grid.

**Band-grid policy** (the one place it is defined): :func:`conform_bands` brings a cube onto the
camera's bands (:func:`hsicam.spectral.resample_spectra`: a camera band wider than the data's own
bands integrates the data over a Gaussian of the width they lack; otherwise linear interpolation in
band centre), logs a note when it resamples, and refuses only extrapolation (a camera band outside the
data's range). It never relabels bands. Within :func:`trained_bands` (a command on a trained run)
the refusal says the run's bands are fixed.

**Memory budget**: :func:`check_memory_budget` compares the size a file *declares* (its header)
with :func:`hsicam.memory.memory_budget_bytes` (re-exported here) before any reader allocates the
cube; :mod:`hsicam.memory` says how the budget is set.

**Normalisation policy**: :func:`normalize_per_cube_max` divides a cube — after it has been
resampled onto the camera's bands — by its own maximum over all bands and pixels, so values lie in
[0, 1] (the readers refuse or clip negative values first) and the brightest sample of each scene is 1. Training patches are cut from the normalised
cube (they are *not* re-normalised per patch), so dark regions stay dark. PSNR "peak 1" metrics
assume this policy.
"""

from __future__ import annotations

import logging
import math
import os
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Iterator, Sequence, Union

import numpy as np

from hsicam.errors import InputError, negative_radiance_error
from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes
from hsicam.spectral import Bands, nm_text, resample_spectra, resolved_bands

PathLike = Union[str, os.PathLike]

log = logging.getLogger(__name__)

def check_memory_budget(source: PathLike | str, shape: Sequence[int], dtype: Any, *, what: str = "cube",
                        budget_mb: float | None = None) -> int:
    """Refuse, before anything is allocated, a ``what`` whose declared ``shape`` and ``dtype``
    would take more memory than the budget (:func:`memory_budget_bytes`).

    The estimate is the array as stored plus its float32 copy (what every reader returns). Returns
    the estimate in bytes; raises one-line :class:`InputError` naming ``source``, the declared
    shape and size, and the budget.
    """
    dims = tuple(int(s) for s in shape)
    n = math.prod(max(d, 0) for d in dims)  # python ints: no overflow for hostile headers
    dt = np.dtype(dtype)
    stored = n * dt.itemsize
    need = stored + n * 4
    budget = memory_budget_bytes(budget_mb)
    if need > budget:
        raise InputError(
            f"{source}: the {what} declares shape {dims} of {dt.name} ({format_bytes(stored)}); reading it needs about "
            f"{format_bytes(need)}, over the memory budget of {format_bytes(budget)} "
            f"(raise it with {MEMORY_BUDGET_ENV}=<MiB> or memory_budget_mb)"
        )
    return need


# ------------------------------------------------------------------------------------------------
# The cube check
# ------------------------------------------------------------------------------------------------
#: How a reader's refusal of negative values (:func:`check_cube`, the dataset's windowed check) says to clip them:
#: the config key that every command reading scenes takes, and the argument of the Python readers.
NEGATIVE_READ_ADVICE = ("dark noise after a background subtraction? --set data.allow_negative=true clips them to 0 "
                        "(hsicam tolerance: --allow-negative); in Python, read_cube(..., allow_negative=True)")


def check_cube(cube: Any, source: PathLike | str = "cube", *, bands: Bands | None = None,
               allow_negative: bool = False, negative_advice: str = "") -> np.ndarray:
    """Validate a (C, H, W) cube and return it as float32 (C-contiguous): the one cube check.

    Raises one-line :class:`InputError` naming ``source`` for: a wrong number of dimensions, an
    empty cube, complex or non-numeric values, NaN/Inf, negative values, or (when ``bands`` is
    given) a band count that differs from the band grid. Entry points pass the cube's ``bands``;
    a cube whose grid is unknown must be given one (or refused) before it is checked. With
    ``allow_negative=True`` negative values (e.g. dark noise after background subtraction) are
    clipped to 0 instead; ``negative_advice`` ends their refusal (a reader's: :data:`NEGATIVE_READ_ADVICE`). A torch
    tensor is accepted and returned as a numpy array.
    """
    if hasattr(cube, "detach") and hasattr(cube, "cpu"):  # torch.Tensor, without importing torch
        cube = cube.detach().cpu()
        if cube.is_floating_point() and cube.element_size() < 4:  # bfloat16 has no numpy type (a TypeError)
            cube = cube.float()
        cube = cube.numpy()
    arr = np.asarray(cube)
    if arr.ndim != 3:
        raise InputError(f"{source}: expected a 3-D cube (bands, height, width), got {arr.ndim} dimensions {arr.shape}")
    if min(arr.shape) == 0:
        raise InputError(f"{source}: empty cube of shape {arr.shape}")
    if arr.dtype.kind == "c":
        raise InputError(f"{source}: complex values ({arr.dtype}); a cube holds real radiance or reflectance "
                         "(take the magnitude or the real part first)")
    if arr.dtype.kind not in "fiub":
        raise InputError(f"{source}: unsupported data type {arr.dtype} (expected real numbers)")
    if bands is not None:
        if not isinstance(bands, Bands):
            raise InputError(f"{source}: the band grid must be a Bands object, got {type(bands).__name__}")
        if arr.shape[0] != len(bands):
            raise InputError(f"{source}: the cube has {arr.shape[0]} bands but its band grid has {len(bands)} ({bands!r})")
    with np.errstate(over="ignore"):  # values beyond float32 become Inf, reported just below
        out = np.ascontiguousarray(arr, dtype=np.float32)
    # band by band: a mask of the whole cube would cost a quarter of its size (1 GB for a 4096² capture's)
    bad = sum(int(band.size - np.count_nonzero(np.isfinite(band))) for band in out)
    if bad:
        raise InputError(f"{source}: {bad} NaN/Inf value(s) in the cube (after conversion to float32)")
    lo = float(out.min())
    if lo < 0:
        if not allow_negative:
            neg = int(np.count_nonzero(out < 0))
            raise negative_radiance_error(source, neg, lo, negative_advice)
        if out is arr:  # never clip the caller's array in place
            out = out.copy()
        np.maximum(out, 0.0, out=out)
    return out


# ------------------------------------------------------------------------------------------------
# The band-grid policy
# ------------------------------------------------------------------------------------------------
#: True while the camera bands come from a trained run: its band grid cannot change.
_TRAINED_BANDS: ContextVar[bool] = ContextVar("hsicam_trained_bands", default=False)


@contextmanager
def trained_bands(active: bool = True) -> Iterator[None]:
    """Within: the camera's bands are a trained run's (fixed), so a range refusal says to bring
    data that covers them (or train a new camera), not to change the camera's grid."""
    token = _TRAINED_BANDS.set(active)
    try:
        yield
    finally:
        _TRAINED_BANDS.reset(token)


def _range_text(bands: Bands) -> str:
    return f"{nm_text(bands.min_nm)}-{nm_text(bands.max_nm)} nm"


def mixed_ranges_refusal(source: PathLike | str, cube_bands: Bands, camera_bands: Bands,
                         grids: Sequence[Bands]) -> InputError | None:
    """The refusal of a file whose ``cube_bands`` do not cover ``camera_bands`` when the files of its dataset
    (``grids``: each one's band grid) are on different band ranges: it names the ranges, how many files cover the
    camera's bands and the range every file covers, since the range of one file (:func:`conform_bands`'s advice)
    is refused by another's. None when they lie on one range (the file's own refusal says it all)."""
    counts: dict[tuple[float, float], int] = {}
    for g in grids:  # to the 1e-3 nm a file lists (ranges that Bands.covers takes as one are one)
        key = (round(g.min_nm, 3), round(g.max_nm, 3))
        counts[key] = counts.get(key, 0) + 1
    if len(counts) < 2:
        return None
    listed = ", ".join(f"{nm_text(a)}-{nm_text(b)} nm: {n}" for (a, b), n in sorted(counts.items()))
    covering = sum(g.covers(camera_bands) for g in grids)
    cam = _range_text(camera_bands)
    trained = _TRAINED_BANDS.get()
    text = (f"{source}: the {'run' if trained else 'camera'}'s bands {cam} are not covered by the data's "
            f"{_range_text(cube_bands)} (no extrapolation), and the {len(grids)} files of its set lie on {len(counts)} "
            f"band ranges ({listed}), of which {covering} cover{'s' if covering == 1 else ''} {cam}")
    if trained:
        return InputError(f"{text}: a trained run's bands are fixed by its training, so use only files that cover {cam}")
    lo, hi = max(g.min_nm for g in grids), min(g.max_nm for g in grids)
    if lo <= hi:
        return InputError(f"{text}: every file covers {nm_text(lo)}-{nm_text(hi)} nm, so use a camera band grid inside "
                          "it (bands.start_nm, bands.stop_nm) or only files that cover the camera's range")
    return InputError(f"{text}: no range is common to every file, so use only files that cover the camera's range "
                      "(or a camera band grid inside the range of the files kept)")


def conform_bands(cube: Any, cube_bands: Bands, camera_bands: Bands, source: PathLike | str = "cube", *,
                  axis: int = -3, note: bool = True) -> Any:
    """Bring ``cube`` (bands on ``axis``: -3 fits (C, H, W) and (B, C, H, W)) from ``cube_bands``
    onto ``camera_bands``: the one band-grid policy of every command.

    Same band centres and no camera band wider than the data's own: the cube is returned unchanged.
    Otherwise :func:`hsicam.spectral.resample_spectra`
    (a camera band wider than the data's own bands: the data's interpolant integrated over a Gaussian
    of the width they lack; any other: linear interpolation in band centre), with an INFO log note
    naming ``source`` and the rule unless ``note=False``; numpy input gives float32, a torch tensor keeps its dtype (and gradient).
    Raises one-line :class:`InputError` when the band count does not match ``cube_bands``, or when
    a camera band lies outside the data's range (no extrapolation, no relabelling; worded for a
    trained run's fixed bands within :func:`trained_bands`).
    """
    n = cube.shape[axis]
    if n != len(cube_bands):
        raise InputError(f"{source}: the cube has {n} bands but its band grid has {len(cube_bands)} ({cube_bands!r})")
    # same centres but wider camera bands: still resampled (integrated), as a 2e-6 nm shift would be
    if cube_bands.matches(camera_bands) and not resolved_bands(cube_bands, camera_bands).any():
        return cube
    if not cube_bands.covers(camera_bands):
        cam, data = _range_text(camera_bands), _range_text(cube_bands)
        if _TRAINED_BANDS.get():
            raise InputError(f"{source}: the run's bands {cam} are not covered by the data's {data} (no extrapolation): "
                             f"a trained run's bands are fixed by its training, so use data that covers {cam} "
                             f"or train a new camera on a band grid inside {data}")
        raise InputError(f"{source}: the camera's bands {cam} are not covered by the data's {data} (no extrapolation): "
                         f"use a camera band grid inside {data} or data that covers the camera's range")
    if note:
        n_fine = int(resolved_bands(cube_bands, camera_bands).sum())
        how = ("by band centre" if n_fine == 0 else "over each band's FWHM (the camera's bands are wider than the data's)"
               if n_fine == len(camera_bands) else
               f"over the FWHM of the {n_fine} bands wider than the data's, by band centre for the others")
        log.info("%s: resampling %d bands (%g-%g nm) onto the camera's %d bands (%g-%g nm) %s",
                 source, len(cube_bands), cube_bands.min_nm, cube_bands.max_nm,
                 len(camera_bands), camera_bands.min_nm, camera_bands.max_nm, how)
    if hasattr(cube, "detach"):  # torch: differentiable, same dtype and device
        return resample_spectra(cube, cube_bands, camera_bands, axis=axis)
    out = resample_spectra(np.asarray(cube, dtype=np.float64), cube_bands, camera_bands, axis=axis)
    return np.ascontiguousarray(out, dtype=np.float32)


def resample_cube(cube: np.ndarray, bands: Bands, target: Bands, source: PathLike | str = "cube") -> np.ndarray:
    """:func:`conform_bands` for a numpy (C, H, W) cube without the log note; always float32."""
    return np.ascontiguousarray(conform_bands(np.asarray(cube), bands, target, source, axis=0, note=False),
                                dtype=np.float32)


def normalize_per_cube_max(cube: np.ndarray, source: PathLike | str = "cube") -> tuple[np.ndarray, float]:
    """The normalisation policy: divide by the cube's maximum → values at most 1, in [0, 1] for a non-negative cube
    (what the readers hand on: :func:`check_cube`; negative values are divided as they are). Returns (cube, max).

    ``cube``: a NumPy array (C, H, W), any scale (raw counts, radiance). Raises :class:`InputError` for an
    all-zero cube (nothing to learn from, and no scale), one without a positive value, one holding NaN/Inf
    values (its maximum is no scale: the result would be NaN), and for a torch tensor (divide it by its maximum).
    """
    if not isinstance(cube, np.ndarray):
        hint = ": cube.numpy(), or divide the tensor by cube.max()" if type(cube).__module__.startswith("torch") else ""
        raise InputError(f"{source}: normalize_per_cube_max takes a NumPy array (C, H, W), got {type(cube).__name__}{hint}")
    if cube.size == 0:  # (numpy's "zero-size array to reduction operation maximum" otherwise)
        raise InputError(f"{source}: the cube of shape {cube.shape} is empty; cannot normalise by its maximum")
    peak = float(np.max(cube))
    if not math.isfinite(peak):
        bad = int(np.count_nonzero(~np.isfinite(cube)))
        raise InputError(f"{source}: the cube contains {bad} NaN or Inf value(s) of {cube.size}; cannot normalise by its "
                         "maximum")
    if peak < 0:
        raise InputError(f"{source}: the cube has no positive value (its maximum is {peak:.4g}); cannot normalise by "
                         "its maximum")
    if not peak > 0:
        raise InputError(f"{source}: the cube is all zeros; cannot normalise by its maximum")
    return (np.asarray(cube, dtype=np.float32) / np.float32(peak)).astype(np.float32, copy=False), peak


__all__ = [
    "MEMORY_BUDGET_ENV",
    "check_cube",
    "check_memory_budget",
    "conform_bands",
    "memory_budget_bytes",
    "normalize_per_cube_max",
    "resample_cube",
    "trained_bands",
]
