"""Independent reference for the CFA box demosaic (no code of the package used): loops over pixels."""

from __future__ import annotations

import numpy as np


def box_demosaic_reference(g: np.ndarray, kappa: np.ndarray, window: int) -> np.ndarray:
    """x̃_c(p) = Σ_q κ_c(q) g(q) / Σ_q κ_c(q) over the window × window box around p, inside the image only.

    g: (H, W) sensor image; kappa: (C, H, W) per-band sensor code; returns (C, H, W)."""
    c, h, w = kappa.shape
    r = window // 2
    out = np.zeros((c, h, w))
    for i in range(h):
        for j in range(w):
            sl = (slice(max(i - r, 0), i + r + 1), slice(max(j - r, 0), j + r + 1))
            out[:, i, j] = (kappa[:, sl[0], sl[1]] * g[sl]).sum((1, 2)) / kappa[:, sl[0], sl[1]].sum((1, 2))
    return out
