"""hsicam leaves the user's matplotlib backend alone: no module switches it at import or when it draws (session 76's
packaging hunt: importing hsicam.report.camera, .html or .reconstruction, or drawing a tolerance, CFA-fit or DOE
export figure, called ``matplotlib.use("Agg")``, so a notebook user following examples/camera_and_psf.py lost
inline figures). hsicam draws on ``matplotlib.figure.Figure`` objects, which need no pyplot and no backend: the
figures are written headless (no DISPLAY, no MPLBACKEND) all the same. Each check runs in a fresh interpreter,
whose backend no other test has chosen."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio

import hsicam

SRC = Path(hsicam.__file__).resolve().parents[1]

IMPORT_EVERY_MODULE = """
import importlib, pkgutil, sys
import matplotlib
matplotlib.use("svg")  # the user's choice (a notebook's inline backend, a GUI one): any but Agg
import hsicam
switched = []
for name in sorted(m.name for m in pkgutil.walk_packages(hsicam.__path__, "hsicam.")):
    if name.endswith("__main__"):
        continue
    importlib.import_module(name)
    if matplotlib.get_backend() != "svg":
        switched.append(name)
        matplotlib.use("svg")
print("switched", switched)
print("pyplot", "matplotlib.pyplot" in sys.modules)
"""

DRAW = """
import sys
from pathlib import Path
import numpy as np
import matplotlib
if sys.argv[2] == "svg":
    matplotlib.use("svg")
from hsicam.export import cfa as export_cfa, doe as export_doe
from hsicam.report.camera import plot_cfa
from hsicam.report.tolerance import plot_tolerance
from hsicam.spectral import Bands
out = Path(sys.argv[1])
bands = Bands.from_centers(np.arange(420.0, 721.0, 50.0))
tile = np.random.default_rng(1).uniform(0, 1, (7, 2, 2))
tile /= tile.sum(axis=0)
plot_cfa(tile, bands, out / "cfa.png")
export_cfa.plot_fits(tile, bands, export_cfa.fit_tile(tile, bands), out / "cfa_fit.png")
n = 21
yy, xx = np.mgrid[:n, :n] - n // 2
height = 100.0 * (xx + n // 2)
export_doe.plot_doe_export(height, np.round(height / 250) * 250, (np.hypot(yy, xx) <= 10).astype(float), 30.0, 8,
                           1282.0, out / "doe.png")
sweep = {"values": [0, 20], "psnr": [30.0, 29.0], "psnr_std": [0.0, 0.1]}
plot_tolerance({"metric": "psnr", "nominal": {"psnr": 30.0}, "sweeps": {"sigma_height_nm": sweep}}, out / "tol.png")
print("pyplot", "matplotlib.pyplot" in sys.modules)  # (before get_backend(), which imports it to resolve a default)
print("backend", matplotlib.get_backend())
"""


def _python(code: str, *args: str) -> list[str]:
    """stdout lines of ``code`` run by a fresh interpreter on this src/, headless: no DISPLAY, no MPLBACKEND."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")}
    env.update(PYTHONPATH=str(SRC), OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_importing_every_hsicam_module_leaves_the_users_backend():
    assert _python(IMPORT_EVERY_MODULE) == ["switched []", "pyplot False"]


def test_figures_are_drawn_without_pyplot_under_the_users_backend_and_headless(tmp_path):
    for backend in ("svg", "default"):
        out = tmp_path / backend
        out.mkdir()
        lines = _python(DRAW, str(out), backend)
        assert lines[0] == "pyplot False"
        if backend == "svg":
            assert lines[1] == "backend svg"
        # (headless with no backend named, matplotlib resolves its own default: hsicam names none)
        for name in ("cfa.png", "cfa_fit.png", "doe.png", "tol.png"):
            img = iio.imread(out / name)
            assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100 and img.std() > 0, name
