"""Network-free per-band estimates of a sensor image (the start of the learned networks).

The demosaic of a CFA camera's image:

    x̃_c = box_w(κ_c ⊙ g) / box_w(κ_c)

a ``w``×``w`` box (odd; zero outside the image): the average of g over the neighbourhood, weighted
by how much each pixel's filter transmits band c. With selective filters it is a crude spectral
estimate; the demo reports it as the reference a network must beat.

The back-projection Aᵀy ⊘ AᵀA𝟙 of any camera (the CASSI networks' start: which bands each
pixel's code lets through, on the scale of the cube).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def demosaic(sensor: torch.Tensor, code: torch.Tensor, window: int) -> torch.Tensor:
    """Per-band normalised local average of the coded sensor image (no learning).

    Args:
        sensor: g, (B, 1, H, W).
        code: κ, (C, H, W) (the CFA over the same pixels).
        window: odd box width in pixels.
    Returns:
        (B, C, H, W).
    """
    if window <= 1:
        return sensor * code.unsqueeze(0) / code.clamp_min(1e-6).unsqueeze(0)
    num = box_mean(sensor * code.unsqueeze(0), window)
    den = box_mean(code.unsqueeze(0), window)
    return num / den.clamp_min(1e-6)


def box_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window``×``window`` box (zeros outside), as two 1-D passes: (B, C, H, W)."""
    r = window // 2
    x = F.avg_pool2d(x, (1, window), stride=1, padding=(0, r))
    return F.avg_pool2d(x, (window, 1), stride=1, padding=(r, 0))


def brightness(sensor: torch.Tensor, window: int, eps: float) -> torch.Tensor:
    """Local brightness b = box_w(g) + ε, (B, 1, H, W) → (B, 1, H, W), in sensor units.

    The networks see g / b and return b × their output, so a scene and the same scene ×c get
    the same reconstruction ×c (for b ≫ ε): what is learned on bright patches serves dark ones.
    Since Σ_c κ_c = 1 per pixel, g is a weighted mean over bands and b is on the scale of the cube.
    """
    return box_mean(sensor, window) + eps


def demosaic_window(camera) -> int:
    """Odd box width for ``camera``: its code period (the CFA's m), rounded up to odd."""
    p = int(getattr(camera, "code_period", 1))
    return p if p % 2 else p + 1


def camera_demosaic(camera, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """:func:`demosaic` of ``sensor`` (B, 1, H, W) with ``camera``'s sensor code at ``origin``.

    Raises ``NotImplementedError`` for cameras without a per-band sensor code (CASSI).
    """
    code = camera.sensor_code(sensor.shape[-2], sensor.shape[-1], origin).to(sensor.dtype)
    return demosaic(sensor, code, demosaic_window(camera))


def camera_operator(camera):
    """The frozen operator a network uses: ``camera.snapshot(nominal=True)``, or ``camera`` itself
    when it already is one (e.g. the snapshot that made the measurement)."""
    snap = getattr(camera, "snapshot", None)
    return snap(nominal=True) if callable(snap) else camera


def backprojection(op, y: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Aᵀy ⊘ AᵀA𝟙: for a pixel-wise (CASSI) operator each coded voxel's share of its measurement."""
    b, _, h, w = y.shape
    ones = y.new_ones(1, len(op.bands), *op.scene_size((h, w)))
    norm = op.A_adjoint(op.A(ones, origin), origin)
    eps = 1e-6 * (getattr(op, "lipschitz", None) or 1.0)  # position-independent, so tiles = whole
    return op.A_adjoint(y, origin) / norm.clamp_min(eps)
