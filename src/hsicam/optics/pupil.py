"""The pupil grid: DOE cells inside the circular aperture.

Cell centres sit at j·Δ for j = −M..M with M = floor(R/Δ), so the grid has an odd number of cells
(333 for R = 5 mm, Δ = 30 µm) and the optical axis on the centre cell. With pupil oversampling q
each cell is split into q×q samples of pitch Δ/q (the height is constant over a cell).
"""

from __future__ import annotations

import math

import numpy as np

from hsicam.errors import InputError


#: Most DOE cells across the aperture: a 32769² pupil grid is 4 GiB per float32 map (the paper's is 333²).
MAX_CELLS_ACROSS = 32769


def cells_across(aperture_radius_m: float, cell_m: float) -> int:
    """Number of DOE cells across the aperture (odd): 2·floor(R/Δ) + 1."""
    if not (aperture_radius_m > 0 and cell_m > 0):
        raise InputError("aperture radius and DOE cell size must be positive")
    if cell_m > 2 * aperture_radius_m:
        raise InputError(f"DOE cell ({cell_m * 1e6:g} µm) is larger than the aperture diameter ({2e3 * aperture_radius_m:g} mm)")
    n = 2 * int(math.floor(min(aperture_radius_m / cell_m, 2.0**40) + 1e-9)) + 1
    if n > MAX_CELLS_ACROSS:
        raise InputError(f"DOE cells of {cell_m * 1e6:g} µm give {n} cells across the {2e3 * aperture_radius_m:g} mm "
                         f"aperture, more than the {MAX_CELLS_ACROSS} a pupil grid can hold in memory "
                         "(camera.doe.cell_size_um is in µm: the paper's is 30)")
    return n


def sample_coordinates_m(n_cells: int, cell_m: float, oversample: int = 1) -> np.ndarray:
    """Centres (m) of the n_cells·q pupil samples along one axis, symmetric about 0."""
    n = n_cells * oversample
    pitch = cell_m / oversample
    return (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * pitch


def aperture_amplitude(n_cells: int, cell_m: float, aperture_radius_m: float, oversample: int = 1, antialias: int = 8) -> np.ndarray:
    """Circular aperture transmission on the pupil samples, (n·q, n·q) float64 in [0, 1].

    Each sample's value is the fraction of its area inside the circle (``antialias``² sub-points),
    which smooths the staircase edge of a coarse grid.
    """
    x = sample_coordinates_m(n_cells, cell_m, oversample)
    pitch = cell_m / oversample
    sub = (np.arange(antialias) + 0.5) / antialias - 0.5
    xs = (x[:, None] + sub[None, :] * pitch).reshape(-1)
    inside = (xs[:, None] ** 2 + xs[None, :] ** 2) <= aperture_radius_m**2
    n = x.size
    return inside.reshape(n, antialias, n, antialias).mean(axis=(1, 3))
