"""A procedural test scene with smooth spectra and sharp edges (moved here from test_cfa_offset.py so that tests of
any folder share it without importing another test file)."""

from __future__ import annotations

import numpy as np


def procedural_scene(centres_nm: np.ndarray, size: int = 200, seed: int = 0) -> np.ndarray:
    """(C, size, size) radiance in [0, 1]: a grey ramp, eight rectangles and discs of Gaussian
    spectra, and a sinusoidal texture; smooth spectra, sharp edges."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size] / size
    lam = centres_nm[:, None, None]
    cube = np.broadcast_to((0.15 + 0.25 * xx)[None], (len(lam), size, size)).copy()
    for k in range(8):
        mu, width, gain = rng.uniform(440, 700), rng.uniform(20, 90), rng.uniform(0.4, 0.9)
        spectrum = 0.05 + gain * np.exp(-0.5 * ((lam - mu) / width) ** 2)
        cy, cx, r = rng.uniform(0.15, 0.85, 2).tolist() + [rng.uniform(0.06, 0.16)]
        region = ((yy - cy) ** 2 + (xx - cx) ** 2 < r * r) if k % 2 else ((abs(yy - cy) < r) & (abs(xx - cx) < 1.5 * r))
        cube = np.where(region[None], spectrum, cube)
    texture = 0.5 + 0.5 * np.sin(2 * np.pi * (xx * 9 + yy * 4))
    band = (yy > 0.85)[None]
    cube = np.where(band, texture[None] * (0.2 + 0.6 * np.exp(-0.5 * ((lam - 600) / 40) ** 2)), cube)
    return np.clip(cube, 0, 1).astype(np.float32)
