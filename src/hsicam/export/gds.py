"""GDSII layout of an L-level DOE for binary-weighted multi-level lithography (needs ``gdstk``).

L = 2^k levels are made with k masks and k etches: mask j (GDS layer j + 1, datatype 0) opens the
cells etched by d_j = 2^j · step (step = h_2π / L for a wrapped element; top / L for one of a clamped height range,
top its maximum height: the ``step_nm`` :mod:`hsicam.export.doe` passes). A cell at level q (height q·step) is etched by
(L − 1 − q)·step in total, so mask j opens exactly the cells whose etch count L − 1 − q has bit j
set; the unetched top surface is level L − 1. Cells are squares of the design's cell size,
centred as in :mod:`hsicam.export.doe` (row 0 at the top, y up), merged along rows into
rectangles. Layer 100 holds the aperture circle (reference; outside it the light is blocked,
e.g. by a chrome stop) and layer 101 a text label. Units: 1 µm, precision 1 nm. The file is
written with a fixed timestamp, so identical designs give identical files.

The surround is level 0, as in the height files (``doe_height_nm.*`` hold 0 outside the aperture) and the
tolerance study's lateral shift (relief entering the aperture reads height 0): the cells of the n × n
grid outside the aperture and a frame :data:`SURROUND_FRAME_CELLS` cells wide around the grid are opened
by every mask. (Before session 75 only the aperture's cells were drawn, so a fabricated surround stood at
the top level: another element than the one whose misalignment tolerance was reported.)
"""

from __future__ import annotations

import datetime
import logging
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.errors import InputError
from hsicam.io import atomic_path

log = logging.getLogger(__name__)

APERTURE_LAYER = 100
LABEL_LAYER = 101
CELL_NAME = "DOE"
#: Width (cells) of the frame around the n × n grid that the GDS etches to level 0, with the grid's cells outside
#: the aperture: a DOE shifted by up to this many cells against its stop still shows level 0 where the tolerance
#: study assumes it (twice the study's largest default shift, 2 cells).
SURROUND_FRAME_CELLS = 4
_TIMESTAMP = datetime.datetime(2000, 1, 1)


def _gdstk():
    try:
        import gdstk
    except ImportError:
        raise ImportError("GDSII export needs the optional package gdstk: pip install 'hsicam[fab]'") from None
    return gdstk


def gds_layers(levels: int, step_nm: float) -> list[dict[str, Any]]:
    """The masks: GDS layer, datatype and etch depth (nm) of each etch step."""
    k = int(round(np.log2(levels)))
    return [{"layer": j + 1, "datatype": 0, "etch_depth_nm": (2**j) * step_nm,
             "opens": f"cells whose etch count (L-1-level) has bit {j} set"} for j in range(k)]


def etch_masks(level: np.ndarray, levels: int, inside: np.ndarray) -> list[np.ndarray]:
    """Boolean mask (n, n) per etch step j (cells etched by 2^j·step): the cells ``inside`` the aperture by their
    level, every other cell at level 0 (etched by every mask)."""
    k = int(round(np.log2(levels)))
    if 2**k != levels:
        raise InputError(f"binary-weighted lithography needs L = 2^k levels, got {levels}")
    etch = (levels - 1) - np.where(inside, np.asarray(level, dtype=np.int64), 0)
    return [((etch >> j) & 1).astype(bool) for j in range(k)]


def frame_rectangles_um(edges: np.ndarray, frame_edge_um: float) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """(corner, opposite corner) in µm of the four rectangles that tile the square ring between the grid's outer
    edges (``edges[0]``, ``edges[-1]`` along x; y the same, negated) and ± ``frame_edge_um``."""
    lo, hi, f = float(edges[0]), float(edges[-1]), float(frame_edge_um)
    # x runs lo..hi across the grid, y runs -hi..-lo (row 0 at the top): top and bottom bands span the frame's
    # whole width, left and right bands the grid's height only
    return [((-f, -lo), (f, f)), ((-f, -f), (f, -hi)), ((-f, -hi), (lo, -lo)), ((hi, -hi), (f, -lo))]


def _row_runs(mask: np.ndarray) -> list[tuple[int, int, int]]:
    """(row, first col, last col + 1) of every run of True along each row."""
    runs = []
    padded = np.zeros((mask.shape[0], mask.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = mask
    d = np.diff(padded, axis=1)
    for i in range(mask.shape[0]):
        starts = np.nonzero(d[i] == 1)[0]
        ends = np.nonzero(d[i] == -1)[0]
        runs.extend((i, int(s), int(e)) for s, e in zip(starts, ends))
    return runs


def cell_centres_um(n: int, cell_um: float) -> tuple[np.ndarray, np.ndarray]:
    """(x of column j, y of row i) in µm: x = (j − (n−1)/2)·Δ, y = −(i − (n−1)/2)·Δ."""
    c = (n - 1) / 2.0
    idx = np.arange(n, dtype=np.float64)
    return (idx - c) * cell_um, -(idx - c) * cell_um


def cell_edges_um(n: int, cell_um: float) -> np.ndarray:
    """The n + 1 cell edges (µm) along x, (j − n/2)·Δ, each on the 1 nm database grid: neighbouring
    rectangles share an edge exactly (rounding each rectangle's own edges left 1 nm slivers and
    overlaps for a cell of an odd number of nm, whose edges fall on half nanometres). Rows use the
    same edges negated (row 0 at the top, y up)."""
    return np.round((np.arange(n + 1, dtype=np.float64) - n / 2.0) * cell_um * 1000.0) / 1000.0


def write_gds(path: str | Path, level: np.ndarray, levels: int, cell_um: float, aperture: np.ndarray,
              step_nm: float, aperture_radius_um: float) -> dict[str, Any]:
    """Write the etch masks of an L-level height map (level indices (n, n)) as GDSII, atomically."""
    gdstk = _gdstk()
    n = level.shape[0]
    inside = np.asarray(aperture) > 0
    masks = etch_masks(level, levels, inside)
    lib = gdstk.Library(name="HSICAM_DOE", unit=1e-6, precision=1e-9)
    cell = lib.new_cell(CELL_NAME)
    edges = cell_edges_um(n, cell_um)
    if abs(cell_um * 1000.0 - round(cell_um * 1000.0)) > 1e-6:
        log.warning("the DOE cell of %g µm is not a whole number of nm: on the GDSII's 1 nm grid its edges round, so "
                    "cells are %g or %g nm wide (each edge within 0.5 nm of the design)", cell_um,
                    np.floor(cell_um * 1000.0), np.ceil(cell_um * 1000.0))
    frame_edge = float(np.round((n / 2.0 + SURROUND_FRAME_CELLS) * cell_um * 1000.0) / 1000.0)
    counts = []
    for j, m in enumerate(masks):
        runs = _row_runs(m)
        for i, a, b in runs:  # row i spans y from -edges[i + 1] (bottom) to -edges[i] (top)
            cell.add(gdstk.rectangle((edges[a], -edges[i + 1]), (edges[b], -edges[i]), layer=j + 1, datatype=0))
        for c0, c1 in frame_rectangles_um(edges, frame_edge):
            cell.add(gdstk.rectangle(c0, c1, layer=j + 1, datatype=0))
        counts.append(len(runs) + 4)
    cell.add(gdstk.ellipse((0, 0), aperture_radius_um, tolerance=min(0.01 * cell_um, 0.1), layer=APERTURE_LAYER))
    cell.add(gdstk.Label(f"hsicam DOE L={levels} step={step_nm:.3f}nm cell={cell_um:g}um", (0, -aperture_radius_um - 2 * cell_um),
                         layer=LABEL_LAYER))
    with atomic_path(path) as tmp:
        lib.write_gds(str(tmp), timestamp=_TIMESTAMP)
    return {"rectangles_per_layer": counts, "surround": {"level": 0, "frame_cells": SURROUND_FRAME_CELLS,
                                                         "frame_edge_um": frame_edge}}


def read_gds_levels(path: str | Path, n: int, cell_um: float, levels: int) -> np.ndarray:
    """Level indices (n, n) recovered from a GDS written by :func:`write_gds`: each cell centre is
    tested against every etch layer's polygons, level = L − 1 − Σ_j 2^j·[etched by mask j], for
    every cell of the grid (the surround outside the aperture included: level 0 as written)."""
    gdstk = _gdstk()
    lib = gdstk.read_gds(str(path))
    cells = {c.name: c for c in lib.cells}
    if CELL_NAME not in cells:
        raise InputError(f"{path}: no '{CELL_NAME}' cell")
    cell = cells[CELL_NAME]
    xc, yc = cell_centres_um(n, cell_um)
    rows, cols = np.indices((n, n)).reshape(2, -1)
    points = np.stack([xc[cols], yc[rows]], axis=1)
    k = int(round(np.log2(levels)))
    etch = np.zeros(len(points), dtype=np.int64)
    for j in range(k):
        polys = [p for p in cell.polygons if p.layer == j + 1]
        if polys:
            hit = np.asarray(gdstk.inside(points, polys), dtype=bool)
            etch += hit.astype(np.int64) << j
    out = np.zeros((n, n), dtype=np.int64)
    out[rows, cols] = (levels - 1) - etch
    return out
