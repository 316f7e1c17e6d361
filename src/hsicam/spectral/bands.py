"""`Bands`: the wavelength grid (band centres and FWHM, in nm) that travels with every cube,
operator, dataset and checkpoint, plus resampling of spectra between grids.

The band model: a band is a Gaussian response of its FWHM centred on its centre
(:func:`band_matrix`). Resampling (:func:`resampling_matrix`, the one rule behind
:func:`resample_spectra` and so behind every reader and command, via
:func:`hsicam.data.cube.conform_bands`) treats each target band by how much wider it is than the source's bands:

* **the band is wider than the source's own bands**: f = √(f_band² − f_source²) > 0 is the part of
  the band's width that the source's band averaging has not done yet (e.g. 1 nm or 5 nm data onto
  10 nm bands, or 10 nm data onto 20 nm bands). The band is the source's linear interpolant
  integrated over a Gaussian centred on the band, narrower than f by what the interpolant itself spreads (the
  band's response then has its declared width), cut at 3 σ or symmetrically at the nearer
  end of the data: it integrates what it sees (a narrow line between two band centres reaches
  both), keeps a spectrum linear in wavelength exactly, and tends to the point sample as f → 0;
* **otherwise** (f = 0: e.g. 10 nm data of 10 nm FWHM onto 10 nm bands, the common case, also
  when the 10 nm steps wobble by a fraction of a nm): linear interpolation in band centre
  (:func:`interpolation_matrix`), as before.

No rule extrapolates: a target centre outside the source's range is refused.
"""

from __future__ import annotations

import functools
import math
import numbers
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from hsicam.errors import InputError

if TYPE_CHECKING:
    import torch

_TOL_NM = 1e-6

#: A Gaussian band response's FWHM over its standard deviation σ: 2√(2 ln 2) ≈ 2.3548.
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
#: The band model's reach: :func:`band_matrix`, :func:`fine_grid` and resampling (:func:`resampling_matrix`) weigh
#: wavelengths up to this many σ from a band's centre (± 1.27 FWHM).
BAND_REACH_SIGMA = 3.0
#: Two band centres closer than this (nm) are the same band for :meth:`Bands.matches` and :meth:`Bands.covers`: half
#: the 1e-3 nm to which the file readers keep a listed centre (``hsicam.data.formats.NM_DECIMALS``), so a grid of more
#: decimals (720.0004 nm) written to a file and read back is still the grid it was, not one 0.0004 nm short of it.
BAND_TOL_NM = 5e-4
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
        bad = [f"{k} {v!r}" for k, v in (("start_nm", start_nm), ("stop_nm", stop_nm), ("step_nm", step_nm))
               if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v)]
        if bad:
            raise InputError(f"Bands.uniform: start, stop and step must be finite numbers (nm), got {', '.join(bad)}")
        if step_nm <= 0 or stop_nm < start_nm:
            raise InputError(f"Bands.uniform: need step > 0 and stop >= start, got {start_nm}..{stop_nm} step {step_nm}")
        ratio = (stop_nm - start_nm) / step_nm  # inf for a subnormal step (1e-320 nm): no integer to round to
        n = round(ratio) + 1 if math.isfinite(ratio) else None
        if n is None or n > MAX_UNIFORM_BANDS:  # checked before any array is made (a step of 1e-6 nm is 3e8 bands)
            raise InputError(f"Bands.uniform: {start_nm:g}..{stop_nm:g} nm in steps of {step_nm:g} nm gives "
                             f"{'infinitely many' if n is None else f'{n:,}' if n < 10**15 else f'{n:.3g}'} bands, more than "
                             f"{MAX_UNIFORM_BANDS}; "
                             "check the step (in nm)")
        centers = start_nm + step_nm * np.arange(n, dtype=np.float64)
        # relative to the smaller of step and stop: a step far beyond the range (1e30 nm) is one band at
        # start_nm, which is not stop_nm (a tolerance of the step's size let it drop stop_nm silently)
        if abs(centers[-1] - stop_nm) > 1e-6 * max(1.0, min(step_nm, abs(stop_nm))):
            raise InputError(f"Bands.uniform: ({stop_nm} - {start_nm}) is not a multiple of the step {step_nm}")
        return cls(centers, np.full(n, step_nm if fwhm_nm is None else fwhm_nm))

    @classmethod
    def from_centers(cls, centers_nm: ArrayLike, fwhm_nm: ArrayLike | None = None) -> "Bands":
        """Bands from centres (nm; a sequence or array); FWHM (nm: one value or one per band) defaults to the local
        spacing (10 nm for a single band)."""
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
        # the band count only: equality allows BAND_TOL_NM per centre, and any two grids of one length are
        # linked by a chain of such steps, so no hash of the centres (rounded or not) agrees with ==
        return hash(len(self))

    def __repr__(self) -> str:
        c = self.centers_nm
        if len(self) <= 4:
            return f"Bands({c.tolist()} nm)"
        return f"Bands({len(self)} bands, {c[0]:g}..{c[-1]:g} nm)"

    def matches(self, other: "Bands", tol_nm: float = BAND_TOL_NM) -> bool:
        """True when both grids have the same band centres (within ``tol_nm``)."""
        return len(self) == len(other) and bool(np.all(np.abs(self.centers_nm - other.centers_nm) <= tol_nm))

    def covers(self, other: "Bands", tol_nm: float = BAND_TOL_NM) -> bool:
        """True when ``other``'s centres lie inside this grid's range (so interpolation suffices)."""
        return bool(other.centers_nm[0] >= self.centers_nm[0] - tol_nm and other.centers_nm[-1] <= self.centers_nm[-1] + tol_nm)

    @property
    def min_nm(self) -> float:
        return float(self.centers_nm[0])

    @property
    def max_nm(self) -> float:
        return float(self.centers_nm[-1])

    def wavelengths_m(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Band centres in metres as a tensor of shape (C,), float64 unless ``dtype`` says otherwise. (torch is
        imported here, not with the module: the command line builds its parser from the configs, which hold
        Bands, without loading torch.)"""
        import torch

        return torch.as_tensor(self.centers_nm * 1e-9, dtype=torch.float64 if dtype is None else dtype, device=device)

    def to_dict(self) -> dict[str, Any]:
        return {"centers_nm": self.centers_nm.tolist(), "fwhm_nm": self.fwhm_nm.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Bands":
        try:
            return cls(np.asarray(d["centers_nm"], dtype=np.float64), np.asarray(d["fwhm_nm"], dtype=np.float64))
        except KeyError as exc:
            raise InputError(f"Bands: missing key {exc}") from None
        except InputError:
            raise
        except (TypeError, ValueError) as exc:  # text or nested lists where numbers belong
            raise InputError(f"Bands: centers_nm and fwhm_nm must be lists of numbers (nm): {exc}") from None


def fine_grid(bands: Bands) -> np.ndarray:
    """The 1 nm grid (nm) that spectra are band-averaged on for ``bands`` (:func:`band_matrix`): the lowest centre
    − 3σ to the highest + 3σ (σ of the widest band), rounded outwards to whole nm."""
    reach = BAND_REACH_SIGMA * float(bands.fwhm_nm.max()) / FWHM_PER_SIGMA
    lo = np.floor(bands.min_nm - reach)
    hi = np.ceil(bands.max_nm + reach)
    return np.arange(lo, hi + 0.5, 1.0)


def band_matrix(bands: Bands, fine_nm: np.ndarray) -> np.ndarray:
    """G (C, F): band-averaging weights of each band's Gaussian response (FWHM) on the ascending fine grid
    (nm), rows summing to 1. Each sample is weighed by the wavelength interval it stands for (half the
    distance between its neighbours, one spacing at the grid's ends), so a non-uniform grid averages per nm,
    not per sample; on a uniform grid every sample weighs the same. A band so narrow that no fine sample
    lies within its ±3σ (e.g. 0.3 nm wide at 420.5 nm on a 1 nm grid) samples the spectrum at its centre by
    linear interpolation (its rows were 0/0, NaN spectra)."""
    fine_nm = np.asarray(fine_nm, dtype=np.float64)
    sigma = bands.fwhm_nm / FWHM_PER_SIGMA
    g = np.exp(-0.5 * ((fine_nm[None, :] - bands.centers_nm[:, None]) / sigma[:, None]) ** 2)
    g[np.abs(fine_nm[None, :] - bands.centers_nm[:, None]) > BAND_REACH_SIGMA * sigma[:, None]] = 0.0
    if len(fine_nm) > 1:  # per-sample weights were biased towards the dense side of a non-uniform grid
        g *= np.gradient(fine_nm)[None, :]
    for c in np.flatnonzero(g.sum(axis=1) == 0.0):  # narrower than the grid: a point sample
        x = float(np.clip(bands.centers_nm[c], fine_nm[0], fine_nm[-1]))
        j = int(np.clip(np.searchsorted(fine_nm, x) - 1, 0, max(len(fine_nm) - 2, 0)))
        if len(fine_nm) == 1:
            g[c, 0] = 1.0
            continue
        t = (x - fine_nm[j]) / (fine_nm[j + 1] - fine_nm[j])
        g[c, j], g[c, j + 1] = 1.0 - t, t
    return g / g.sum(axis=1, keepdims=True)


def kernel_fwhm(src: Bands, dst: Bands) -> np.ndarray:
    """(len(dst),) FWHM (nm) of the Gaussian that takes ``src`` to each ``dst`` band:
    √max(f_dst² − f_src², 0), f_src interpolated at the band's centre. Gaussian responses compose in
    quadrature, so data already averaged over f_src need only the rest (0: nothing left to average)."""
    f_src = np.interp(dst.centers_nm, src.centers_nm, src.fwhm_nm)
    return np.sqrt(np.maximum(dst.fwhm_nm**2 - f_src**2, 0.0))


def resolved_bands(src: Bands, dst: Bands) -> np.ndarray:
    """Boolean (len(dst),): True where the band integrates ``src`` (:func:`kernel_fwhm` > 0: the
    band is wider than the source's own bands), False where it point-samples it by interpolation."""
    return kernel_fwhm(src, dst) > _TOL_NM


#: A band of the camera whose data neighbours lie farther apart than this many times its FWHM is
#: interpolated across a gap it resolves (:func:`interpolated_bands`): the 50 nm steps of a 7-band cube
#: under 10 nm bands, not the 10 nm steps of data shifted by half a band.
INTERPOLATION_GAP_FWHM = 1.5


def interpolated_bands(src: Bands, dst: Bands) -> np.ndarray:
    """Boolean (len(dst),): True where a band of ``dst`` lies strictly between two bands of ``src`` more than
    :data:`INTERPOLATION_GAP_FWHM` times its own FWHM apart: its value resampled from ``src`` is a linear
    interpolation across a gap the band would resolve, not a measurement (data on a coarser grid than the camera's:
    ground truth made up between the data's samples). A band outside ``src``'s range is not between two of its bands:
    False (resampling refuses it)."""
    c, d = src.centers_nm, dst.centers_nm
    if len(c) < 2:
        return np.zeros(len(d), dtype=bool)  # one data band: every camera band on it (the range check's)
    j = np.clip(np.searchsorted(c, d), 1, len(c) - 1)  # c[j - 1] <= d <= c[j]
    lo, hi = c[j - 1], c[j]
    on_sample = (np.abs(d - lo) <= _TOL_NM) | (np.abs(d - hi) <= _TOL_NM)
    inside = (d > c[0]) & (d < c[-1])
    return inside & ~on_sample & (hi - lo > INTERPOLATION_GAP_FWHM * dst.fwhm_nm)


#: Step (nm) of the quadrature over a band's response in :func:`resampling_matrix` (at most; finer for
#: narrow kernels): the linear interpolant is integrated, so this only sets the Gaussian's accuracy.
_QUADRATURE_STEP_NM = 0.05


def _band_quadrature(s: np.ndarray, c: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(nodes x, normalised weights) of the trapezoid that :func:`resampling_matrix` averages the data's linear
    interpolant over: a Gaussian of ``sigma`` centred on ``c``, cut at 3σ or symmetrically at the nearer end of the data
    ``s``; nodes uniform (at most :data:`_QUADRATURE_STEP_NM` apart, and σ/10) plus the interpolant's kinks (the data's
    samples) and their mirrors about c, so the set stays symmetric (a spectrum linear in wavelength is kept exactly) and
    every piece between nodes is linear (a kink between uniform nodes cost up to 3e-4 of the value: session 74).
    Empty arrays when the band sits on the data's end (nothing to average symmetrically)."""
    reach = max(min(BAND_REACH_SIGMA * sigma, c - s[0], s[-1] - c), 0.0)
    n = int(np.ceil(reach / min(_QUADRATURE_STEP_NM, sigma / 10.0))) if sigma > 0 else 0
    if n == 0:
        return np.zeros(0), np.zeros(0)
    kinks = s[(s > c - reach) & (s < c + reach)]
    x = np.unique(np.concatenate([c + reach * np.arange(-n, n + 1) / n, kinks, 2 * c - kinks]))
    dx = np.diff(x)
    g = np.exp(-0.5 * ((x - c) / sigma) ** 2) * (np.concatenate([dx, [0.0]]) + np.concatenate([[0.0], dx]))
    return x, g / g.sum()


def _interpolant_gaussian_sigma(s: np.ndarray, c: float, kernel_sigma: float) -> float:
    """σ' (nm) of the Gaussian that :func:`resampling_matrix` averages the data's linear interpolant over for a band
    centred on ``c``: the σ' ≥ 0 whose row spreads a line by ``kernel_sigma``², so that the band's response has the
    variance σ_src² + kernel_sigma² = σ_band², its declared width (session 74: the Gaussian had the kernel's width
    itself, and the interpolant's own spread came on top: 5 nm data under 10 nm bands 11.0 nm wide). The row's second
    moment about c is the average over :func:`_band_quadrature`'s nodes x of (x − c)² + t(1 − t)h², h the data's step
    around x and t the place of x within it (the interpolation weights' own), on the data's actual, possibly uneven,
    grid and with the same cut; found by bisection (the spread grows with σ'). 0 where the point sample at c already
    spreads a line more (t(1 − t)h² at c: data too coarse for the band); a band whose cut at the data's end keeps it
    narrower than asked takes the widest Gaussian there (it averages less near the edge, as before)."""
    target = kernel_sigma * kernel_sigma

    def spread_at(x: np.ndarray, w: np.ndarray) -> float:
        j = np.clip(np.searchsorted(s, x, side="right") - 1, 0, len(s) - 2)
        h = s[j + 1] - s[j]
        t = np.clip((x - s[j]) / h, 0.0, 1.0)
        return float(w @ ((x - c) ** 2 + t * (1.0 - t) * h * h))

    if spread_at(np.array([c]), np.ones(1)) >= target:
        return 0.0
    lo, hi = 0.0, math.sqrt(target)
    for _ in range(40):
        mid = (lo + hi) / 2
        x, w = _band_quadrature(s, c, mid)
        if (spread_at(x, w) if len(x) else 0.0) < target:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


def resampling_matrix(src: Bands, dst: Bands) -> np.ndarray:
    """The resampling matrix W (len(dst), len(src)) (:func:`_resampling_matrix`; computed once per pair of grids: each
    band's Gaussian is solved for, ~0.1 s for a 1 nm cube's 31 bands, and every scene of a folder shares it)."""
    key = (tuple(src.centers_nm), tuple(src.fwhm_nm), tuple(dst.centers_nm), tuple(dst.fwhm_nm))
    return _cached_resampling_matrix(key).copy()


@functools.lru_cache(maxsize=64)
def _cached_resampling_matrix(key: tuple) -> np.ndarray:
    src, dst = Bands(key[0], key[1]), Bands(key[2], key[3])
    return _resampling_matrix(src, dst)


def _resampling_matrix(src: Bands, dst: Bands) -> np.ndarray:
    """The resampling matrix W (len(dst), len(src)), ``dst_values = W @ src_values``: the one rule
    of the module docstring. A band wider than the source's (:func:`kernel_fwhm` f > 0) is the
    source's linear interpolant integrated over a Gaussian centred on the band, narrower than f by what the
    interpolant itself spreads (:func:`_interpolant_gaussian_sigma`: the band's response then has its declared
    width), cut at 3σ
    or symmetrically at the band's distance to the nearer end of the data, whichever is smaller (so
    a band at the data's edge is not pulled inwards and a spectrum linear in wavelength is kept
    exactly); f = 0 is the :func:`interpolation_matrix` row, unchanged. Raises :class:`InputError`
    when ``dst`` reaches outside ``src``.
    """
    w = interpolation_matrix(src, dst)  # refuses extrapolation
    f = kernel_fwhm(src, dst)
    s = src.centers_nm
    if len(s) < 2:
        return w
    for i in np.flatnonzero(f > _TOL_NM):
        c = float(dst.centers_nm[i])
        # the linear interpolant spreads a sample over its neighbours too: the Gaussian is narrowed so that the
        # band's response has the band's own width (session 74's audit)
        sigma = _interpolant_gaussian_sigma(s, c, float(f[i]) / FWHM_PER_SIGMA)
        x, g = _band_quadrature(s, c, sigma)
        if len(x):
            w[i] = g @ _interpolation_rows(s, x)
    return w


def _interpolation_rows(s: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(len(x), len(s)): linear-interpolation weights of the points ``x`` (inside [s₀, s₋₁]) on the
    ascending grid ``s`` (≥ 2 points); the arithmetic of :func:`interpolation_matrix`, without its checks."""
    x = np.clip(x, s[0], s[-1])
    j = np.clip(np.searchsorted(s, x, side="right") - 1, 0, len(s) - 2)
    t = (x - s[j]) / (s[j + 1] - s[j])
    rows = np.zeros((len(x), len(s)))
    rows[np.arange(len(x)), j] = 1.0 - t
    rows[np.arange(len(x)), j + 1] += t
    return rows


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
    if len(src) == 1:
        return np.ones((len(dst), 1), dtype=np.float64)
    return _interpolation_rows(src.centers_nm, dst.centers_nm)


def resample_spectra(values: np.ndarray | torch.Tensor, src: Bands, dst: Bands, axis: int = 0) -> np.ndarray | torch.Tensor:
    """Resample ``values`` along ``axis`` (the band axis, length len(src)) onto the grid ``dst``.

    Works on numpy arrays and torch tensors (differentiable); linear in the values. The rule
    (:func:`resampling_matrix`): bands that the source samples finer than their FWHM integrate the
    source over their Gaussian response; the others interpolate linearly in band centre. The
    same centres with nothing left to average (no ``dst`` band wider than the source's own) return
    ``values`` itself.
    """
    n = values.shape[axis]
    if n != len(src):
        raise InputError(f"resample_spectra: axis {axis} has {n} entries but the source grid has {len(src)} bands")
    # equal centres are not enough: wider dst bands still integrate the source (the rule, continuous in the centres)
    if src.matches(dst) and not resolved_bands(src, dst).any():
        return values
    w = resampling_matrix(src, dst)
    torch = sys.modules.get("torch")  # values that are a tensor mean torch is loaded: numpy input does not load it
    if torch is not None and isinstance(values, torch.Tensor):
        wt = torch.as_tensor(w, dtype=values.dtype, device=values.device)
        moved = values.movedim(axis, -1)
        return (moved @ wt.T).movedim(-1, axis)
    moved = np.moveaxis(np.asarray(values), axis, -1)
    return np.moveaxis(moved @ w.T, -1, axis)


#: The version of the band rules a run trains with, recorded in each training session (``band_rules``): 2 since
#: session 74 (:func:`band_sample_wavelengths` by Gauss–Hermite nodes of the band's Gaussian, :func:`resampling_matrix`
#: bands of their declared width); a run without it trained with ``camera.psf.band_samples`` over ±FWHM/2 slices.
BAND_RULES_VERSION = 2

#: :func:`band_sample_wavelengths` takes no wavelength farther than this many σ from a band's centre.
BAND_SAMPLE_REACH_SIGMA = 4.0


def band_sample_wavelengths(centers_nm: np.ndarray, fwhm_nm: np.ndarray, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-wavelengths (nm) and weights, both (C, M), that average each band over its Gaussian response.

    M = ``samples`` Gauss–Hermite nodes of the band's Gaussian of its FWHM (σ = FWHM / 2√(2 ln 2)) and their
    weights (summing to 1 per band): the average of a quantity polynomial in λ up to degree 2M − 1 over the band is
    exact, and M → ∞ averages over the whole Gaussian (cut at :data:`BAND_SAMPLE_REACH_SIGMA`), the band that
    resampling (:func:`resampling_matrix`) and the generator (:func:`band_matrix`) use. M = 1: the centre. (Before session 74: M equal slices of ±FWHM/2, a band
    of RMS width 2.6 nm for a declared 10 nm FWHM, which no M brought closer.)
    """
    c = np.asarray(centers_nm, dtype=np.float64).reshape(-1, 1)
    f = np.asarray(fwhm_nm, dtype=np.float64).reshape(-1, 1)
    m = int(samples)
    if m < 1:
        raise ValueError("band samples must be >= 1")
    x, w = np.polynomial.hermite_e.hermegauss(m)  # probabilists' Hermite: weight e^{-x²/2}
    # the nodes beyond 4σ (from M = 8; their weights sum to < 3e-4) are brought in to 4σ: 15 nodes reach 6.4σ, wider
    # than any band's light worth a PSF, and a material's formula range (the tiny preset's 50 nm bands, M = 50)
    x = np.clip(x, -BAND_SAMPLE_REACH_SIGMA, BAND_SAMPLE_REACH_SIGMA)
    lam = c + (f / FWHM_PER_SIGMA) * x[None, :]
    w = w[None, :] * np.ones_like(lam)
    return lam, w / w.sum(axis=1, keepdims=True)
