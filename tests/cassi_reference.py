"""Small CASSI cameras for tests, and diag(ΦΦᵀ) of a sensor window by loops over its aperture array (from the
definitions, not from the cameras' own ``gram_diagonal``): used by tests/cameras and tests/models."""

from __future__ import annotations

import numpy as np
import torch

from hsicam.cameras import build_camera
from hsicam.config import load_config


def cassi(kind: str, *overrides: str, dtype=torch.float64):
    """A CASSI camera of five bands (500..700 nm), 2 px per band."""
    cfg = load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50", f"camera.kind={kind}",
                                 *overrides])
    return build_camera(cfg).to(dtype)


def cassi_bands(kind: str = "dd_cassi", bands: int = 8, *overrides: str, dtype=torch.float64):
    """A CASSI camera of ``bands`` bands 20 nm apart from 500 nm (the baseline solvers' test camera)."""
    stop = 500 + 20 * (bands - 1)
    cfg = load_config(overrides=["bands.start_nm=500", f"bands.stop_nm={stop}", "bands.step_nm=20",
                                 f"camera.kind={kind}", *overrides])
    return build_camera(cfg).to(dtype)


def loop_gram_diagonal(cam, kind: str, h: int, w: int, origin: tuple[int, int]) -> np.ndarray:
    """diag(ΦΦᵀ) of the sensor window (h, w) at ``origin`` by loops over the aperture array (convention 'sum')."""
    r0, c0 = origin
    d = cam.shifts
    ap = cam.aperture.pattern(r0 + h + 1, c0 + w + max(d) + 1, dtype=torch.float64).numpy()
    ref = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            if kind == "dd_cassi":
                ref[i, j] = sum(ap[r0 + i, c0 + j + dc] ** 2 for dc in d)
            else:
                ref[i, j] = sum(ap[r0 + i, c0 + j - dc] ** 2 for dc in d if 0 <= j - dc < w - max(d))
    return ref
