"""The maintainer scripts of scripts/ that draw the docs' figures run on real inputs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPTS / args[0]), *args[1:]], capture_output=True, text=True, timeout=120)


def test_psf_compare_figure_draws_one_row_per_camera_and_rejects_bad_stacks(tmp_path):
    import imageio.v3 as iio

    k, bands = 21, 31
    sharp = np.zeros((bands, k, k), np.float32)
    sharp[:, k // 2, k // 2] = 1.0
    spread = np.zeros_like(sharp)
    spread[:, k // 2 - 1:k // 2 + 2, k // 2 - 1:k // 2 + 2] = 1.0 / 9
    np.save(tmp_path / "a.npy", sharp)
    np.save(tmp_path / "b.npy", spread)
    one, two = tmp_path / "one.png", tmp_path / "two.png"
    assert _run("psf_compare_figure.py", str(one), f"lens={tmp_path / 'a.npy'}").returncode == 0
    proc = _run("psf_compare_figure.py", str(two), f"lens={tmp_path / 'a.npy'}", f"doe={tmp_path / 'b.npy'}")
    assert proc.returncode == 0, proc.stderr
    h1, h2 = iio.imread(one).shape[0], iio.imread(two).shape[0]
    assert h2 > 1.7 * h1  # a second row of panels
    bad = _run("psf_compare_figure.py", str(tmp_path / "x.png"), f"flat={tmp_path / 'a.npy'}", "--bands", "800")
    assert bad.returncode != 0 and "800 nm is not a band" in bad.stderr and not (tmp_path / "x.png").exists()
    np.save(tmp_path / "c.npy", sharp[0])
    wrong = _run("psf_compare_figure.py", str(tmp_path / "y.png"), f"2d={tmp_path / 'c.npy'}")
    assert wrong.returncode != 0 and "expected a (bands, K, K)" in wrong.stderr
