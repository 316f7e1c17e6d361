"""Refractive indices n(λ) of optical materials (DOE substrate, singlet lens).

``FusedSilica`` uses the three-term Sellmeier equation of Malitson (1965), valid 0.21–3.71 µm.
Any other material comes from a CSV table (``wavelength_nm,n``) and is interpolated linearly.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Protocol

import numpy as np

from hsicam.errors import InputError


class Material(Protocol):
    name: str

    def n(self, wavelength_nm: np.ndarray | float) -> np.ndarray:
        """Refractive index at the given vacuum wavelengths (nm); float64 array."""
        ...


class FusedSilica:
    """Fused silica, Sellmeier coefficients of I. H. Malitson, JOSA 55, 1205 (1965)."""

    name = "fused_silica"
    RANGE_NM = (210.0, 3710.0)  # where Malitson's fit holds
    B = (0.6961663, 0.4079426, 0.8974794)
    C_um = (0.0684043, 0.1162414, 9.896161)

    def n(self, wavelength_nm: np.ndarray | float) -> np.ndarray:
        lam_um = np.asarray(wavelength_nm, dtype=np.float64) * 1e-3
        lo, hi = self.RANGE_NM
        if np.any(lam_um < lo * 1e-3) or np.any(lam_um > hi * 1e-3):
            raise InputError(f"fused silica Sellmeier formula is valid for {lo:g}-{hi:g} nm only")
        l2 = lam_um**2
        n2 = 1.0 + sum(b * l2 / (l2 - c**2) for b, c in zip(self.B, self.C_um))
        return np.sqrt(n2)

    def __repr__(self) -> str:
        return "FusedSilica()"


class TabulatedMaterial:
    """A material given by a table of (wavelength in nm, refractive index), linearly interpolated."""

    def __init__(self, wavelength_nm: np.ndarray, n: np.ndarray, name: str = "tabulated",
                 path: Path | None = None, key: str | None = None) -> None:
        wl = np.asarray(wavelength_nm, dtype=np.float64).reshape(-1)
        nn = np.asarray(n, dtype=np.float64).reshape(-1)
        if wl.size < 2 or wl.shape != nn.shape:
            raise InputError(f"material {name!r}: need at least two (wavelength, n) rows of equal length")
        if not (np.all(np.isfinite(wl)) and np.all(np.isfinite(nn))):
            raise InputError(f"material {name!r}: table contains NaN or Inf")
        if np.any(np.diff(wl) <= 0):
            raise InputError(f"material {name!r}: wavelengths must be strictly ascending")
        if np.any(nn < 1.0):
            raise InputError(f"material {name!r}: refractive index below 1")
        self.wavelength_nm, self.n_table, self.name = wl, nn, name
        self.path = path  # the CSV file it was read from (from_csv), named in its refusals
        self.key = key  # the config key that chose it (e.g. camera.doe.material), named in its refusals

    @classmethod
    def from_csv(cls, path: str | Path, key: str | None = None) -> "TabulatedMaterial":
        """Read a CSV with a header row naming ``wavelength_nm`` and ``n`` columns (``key``: the config key that
        names the file, said when the table falls short of a wavelength)."""
        path = Path(path)
        try:
            # utf-8-sig: Excel's "CSV UTF-8" starts with a byte-order mark that would glue onto the first column name
            with open(path, newline="", encoding="utf-8-sig") as fh:
                reader = csv.DictReader(fh)
                rows = list(reader)
                header = reader.fieldnames or []
        except OSError as exc:
            raise InputError(f"{path}: cannot read material table ({exc.strerror})") from None
        if "wavelength_nm" not in header or "n" not in header:
            raise InputError(f"{path}: material CSV needs columns 'wavelength_nm' and 'n'")
        if len(rows) < 2:
            raise InputError(f"{path}: the material table has {len(rows)} row(s) under its header; it needs two or more "
                             "(wavelength_nm, n) rows to interpolate between")
        try:
            wl = [float(r["wavelength_nm"]) for r in rows]
            n = [float(r["n"]) for r in rows]
        except (TypeError, ValueError):
            raise InputError(f"{path}: non-numeric value in material table") from None
        return cls(np.array(wl), np.array(n), name=path.stem, path=path, key=key)

    def n(self, wavelength_nm: np.ndarray | float) -> np.ndarray:
        lam = np.asarray(wavelength_nm, dtype=np.float64)
        if np.any(lam < self.wavelength_nm[0] - 1e-9) or np.any(lam > self.wavelength_nm[-1] + 1e-9):
            # the wavelengths asked for, and the file: a camera built on this table said only "material 'glass' is
            # tabulated for 400-700 nm only", naming neither the table's path nor the bands that fall outside it
            where = "".join(f"{part}: " for part in (self.key, self.path) if part is not None)
            lo, hi = float(lam.min()), float(lam.max())
            asked = f"{lo:g} nm" if lo == hi else f"{lo:g}-{hi:g} nm"
            raise InputError(
                f"{where}material {self.name!r} is tabulated for {self.wavelength_nm[0]:g}-{self.wavelength_nm[-1]:g} nm "
                f"only, but its refractive index is needed at {asked}"
            )
        return np.interp(lam, self.wavelength_nm, self.n_table)

    def __repr__(self) -> str:
        return f"TabulatedMaterial({self.name!r}, {self.wavelength_nm[0]:g}-{self.wavelength_nm[-1]:g} nm)"


def get_material(spec: str, key: str | None = None) -> Material:
    """``"fused_silica"`` or a path to a ``wavelength_nm,n`` CSV file (``key``: the config key that names it, said
    in a table's refusal of a wavelength outside it)."""
    if spec == "fused_silica":
        return FusedSilica()
    if spec.lower().endswith(".csv"):
        return TabulatedMaterial.from_csv(spec, key)
    raise InputError(f"unknown material {spec!r}: use 'fused_silica' or a path to a CSV file (wavelength_nm,n)")
