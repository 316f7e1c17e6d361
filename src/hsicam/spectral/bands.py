"""`Bands`: the wavelength grid (band centres and FWHM, in nm) that travels with every cube,
operator, dataset and checkpoint, plus resampling of spectra between grids."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from hsicam.errors import InputError

_TOL_NM = 1e-6
#: Most bands a uniform grid may have (a hyperspectral camera has tens to hundreds; a mistyped step
#: would otherwise build arrays of billions before any memory check could refuse it).
MAX_UNIFORM_BANDS = 10_000


def nm_text(nm: float) -> str:
    """A wavelength in nm as text, to 6 decimals without trailing zeros (a coverage refusal never
    prints two different ends alike: 699.99998 is not "700")."""
    return f"{float(nm):.6f}".rstrip("0").rstrip(".")


@dataclass(frozen=True, eq=False)
class Bands:
    """Spectral bands: strictly ascending centres and positive FWHM, both in nanometres."""

    centers_nm: np.ndarray
    fwhm_nm: np.ndarray

    def __post_init__(self) -> None:
        c = np.asarray(self.centers_nm, dtype=np.float64).reshape(-1).copy()
        if c.size == 0:
            raise InputError("Bands: at least one band is required")
        if not np.all(np.isfinite(c)) or np.any(c <= 0):
            bad = c[~(np.isfinite(c) & (c > 0))]
            raise InputError(f"Bands: band centres must be finite and positive, got {bad.size} that are not "
                             f"(e.g. {bad[:3].tolist()}) among {c.size}")
        if c.size > 1 and np.any(np.diff(c) <= 0):
            raise InputError("Bands: band centres must be strictly ascending")
        f = np.asarray(self.fwhm_nm, dtype=np.float64).reshape(-1).copy()
        if f.size == 1 and c.size > 1:
            f = np.full_like(c, f[0])
        if f.shape != c.shape:
            raise InputError(f"Bands: {c.size} centres but {f.size} FWHM values")
        if not np.all(np.isfinite(f)) or np.any(f <= 0):
            raise InputError("Bands: FWHM must be finite and positive")
        c.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "centers_nm", c)
        object.__setattr__(self, "fwhm_nm", f)

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def uniform(cls, start_nm: float, stop_nm: float, step_nm: float, fwhm_nm: float | None = None) -> "Bands":
        """Evenly spaced bands from ``start_nm`` to ``stop_nm`` inclusive (FWHM defaults to the step)."""
        if step_nm <= 0 or stop_nm < start_nm:
            raise InputError(f"Bands.uniform: need step > 0 and stop >= start, got {start_nm}..{stop_nm} step {step_nm}")
        n = round((stop_nm - start_nm) / step_nm) + 1
        if n > MAX_UNIFORM_BANDS:  # checked before any array is made (a step of 1e-6 nm is 3e8 bands)
            raise InputError(f"Bands.uniform: {start_nm:g}..{stop_nm:g} nm in steps of {step_nm:g} nm gives {n:,} bands, "
                             f"more than {MAX_UNIFORM_BANDS}; check the step (in nm)")
        centers = start_nm + step_nm * np.arange(n, dtype=np.float64)
        if abs(centers[-1] - stop_nm) > 1e-6 * max(1.0, step_nm):
            raise InputError(f"Bands.uniform: ({stop_nm} - {start_nm}) is not a multiple of the step {step_nm}")
        return cls(centers, np.full(n, step_nm if fwhm_nm is None else fwhm_nm))

    @classmethod
    def from_centers(cls, centers_nm: Sequence[float], fwhm_nm: Sequence[float] | float | None = None) -> "Bands":
        """Bands from centres; FWHM defaults to the local spacing (10 nm for a single band)."""
        c = np.asarray(centers_nm, dtype=np.float64).reshape(-1)
        if fwhm_nm is None:
            fwhm = np.gradient(c) if c.size > 1 else np.array([10.0])
            fwhm = np.abs(fwhm) if c.size > 1 else fwhm
            # the Bands validator reports non-ascending centres with a clear message
            fwhm = np.where(fwhm > 0, fwhm, 1.0)
        else:
            fwhm = np.asarray(fwhm_nm, dtype=np.float64).reshape(-1)
        return cls(c, fwhm)

    @classmethod
    def paper(cls) -> "Bands":
        """The paper's grid: 31 bands, 420 to 720 nm in 10 nm steps."""
        return cls.uniform(420.0, 720.0, 10.0)

    # -- queries -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.centers_nm.size)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Bands):
            return NotImplemented
        return self.matches(other)

    def __hash__(self) -> int:
        return hash(tuple(np.round(self.centers_nm, 6)))

    def __repr__(self) -> str:
        c = self.centers_nm
        if len(self) <= 4:
            return f"Bands({c.tolist()} nm)"
        return f"Bands({len(self)} bands, {c[0]:g}..{c[-1]:g} nm)"

    def matches(self, other: "Bands", tol_nm: float = _TOL_NM) -> bool:
        """True when both grids have the same band centres (within ``tol_nm``)."""
        return len(self) == len(other) and bool(np.all(np.abs(self.centers_nm - other.centers_nm) <= tol_nm))

    def covers(self, other: "Bands", tol_nm: float = _TOL_NM) -> bool:
        """True when ``other``'s centres lie inside this grid's range (so interpolation suffices)."""
        return bool(other.centers_nm[0] >= self.centers_nm[0] - tol_nm and other.centers_nm[-1] <= self.centers_nm[-1] + tol_nm)

    @property
    def min_nm(self) -> float:
        return float(self.centers_nm[0])

    @property
    def max_nm(self) -> float:
        return float(self.centers_nm[-1])

    def wavelengths_m(self, device: torch.device | str | None = None, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Band centres in metres as a tensor of shape (C,)."""
        return torch.as_tensor(self.centers_nm * 1e-9, dtype=dtype, device=device)

    def to_dict(self) -> dict[str, Any]:
        return {"centers_nm": self.centers_nm.tolist(), "fwhm_nm": self.fwhm_nm.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Bands":
        try:
            return cls(np.asarray(d["centers_nm"], dtype=np.float64), np.asarray(d["fwhm_nm"], dtype=np.float64))
        except KeyError as exc:
            raise InputError(f"Bands: missing key {exc}") from None

    def require_match(self, other: "Bands", what: str = "data") -> None:
        """Raise :class:`InputError` unless ``other`` has this band grid."""
        if not self.matches(other):
            raise InputError(f"{what} has {other!r} but the camera expects {self!r}; resample it first")


def interpolation_matrix(src: Bands, dst: Bands) -> np.ndarray:
    """Linear-interpolation matrix W (len(dst), len(src)) such that ``dst_values = W @ src_values``.

    Interpolates by band centre. Raises :class:`InputError` when ``dst`` reaches outside ``src``:
    no silent extrapolation.
    """
    if not src.covers(dst):
        raise InputError(
            f"cannot resample {src!r} onto {dst!r}: the target range "
            f"{nm_text(dst.min_nm)}-{nm_text(dst.max_nm)} nm is not covered by {nm_text(src.min_nm)}-{nm_text(src.max_nm)} nm"
        )
    s = src.centers_nm
    w = np.zeros((len(dst), len(src)), dtype=np.float64)
    for i, lam in enumerate(dst.centers_nm):
        if len(src) == 1:
            w[i, 0] = 1.0
            continue
        lam = float(np.clip(lam, s[0], s[-1]))
        j = int(np.searchsorted(s, lam, side="right")) - 1
        j = min(max(j, 0), len(s) - 2)
        t = (lam - s[j]) / (s[j + 1] - s[j])
        w[i, j] = 1.0 - t
        w[i, j + 1] = t
    return w


def resample_spectra(values: np.ndarray | torch.Tensor, src: Bands, dst: Bands, axis: int = 0) -> np.ndarray | torch.Tensor:
    """Resample ``values`` along ``axis`` (the band axis, length len(src)) onto the grid ``dst``.

    Works on numpy arrays and torch tensors (differentiable); linear in band centre.
    """
    n = values.shape[axis]
    if n != len(src):
        raise InputError(f"resample_spectra: axis {axis} has {n} entries but the source grid has {len(src)} bands")
    if src.matches(dst):
        return values
    w = interpolation_matrix(src, dst)
    if isinstance(values, torch.Tensor):
        wt = torch.as_tensor(w, dtype=values.dtype, device=values.device)
        moved = values.movedim(axis, -1)
        return (moved @ wt.T).movedim(-1, axis)
    moved = np.moveaxis(np.asarray(values), axis, -1)
    return np.moveaxis(moved @ w.T, -1, axis)
