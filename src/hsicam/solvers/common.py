"""Pieces shared by the iterative solvers: the GAP projection and total-variation denoising.

Every solver sees the camera only through ``camera.A`` and ``camera.A_adjoint`` and, for GAP-type
steps, ``camera.gram_diagonal(y)`` (diag ΦΦᵀ, declared by cameras whose ΦΦᵀ is diagonal: CASSI).
"""

from __future__ import annotations

import numbers

import torch

from hsicam.errors import InputError
from hsicam.models.tv import chambolle_step, dual_divergence


def checked_gram_diagonal(camera, y: torch.Tensor, x0: torch.Tensor | None, solver: str) -> torch.Tensor:
    """diag ΦΦᵀ of ``camera`` for the measurement ``y`` (B, 1, H, W'), a solver's inputs checked first: ``y`` (the
    camera's :meth:`check_measurement`), that ΦΦᵀ is diagonal (a CASSI camera; another is one :class:`InputError`
    naming ``solver``) and that a start ``x0`` is a cube this camera takes, of the size ``y``'s scene has."""
    camera.check_measurement(y)
    try:
        phi = camera.gram_diagonal(y)
    except NotImplementedError as exc:
        raise InputError(f"{solver} needs a camera whose ΦΦᵀ is diagonal (a CASSI camera): {exc}") from None
    if x0 is not None:
        camera.check_scene_layout(x0)
        want = (y.shape[0], len(camera.bands), *camera.scene_size(tuple(y.shape[-2:])))
        if tuple(x0.shape) != want:
            raise InputError(f"{solver}: the start x0 is {tuple(x0.shape)} but the measurement's cube is {want}")
        camera.check_scene(x0)
    return phi


def check_count(name: str, value, least: int = 0) -> None:
    """:class:`InputError` unless ``value`` is an integer >= ``least`` (a solver's number of iterations)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
        raise InputError(f"{name} must be an integer >= {least}, got {value!r}")


def gap_projection(camera, x: torch.Tensor, y: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Euclidean projection of ``x`` onto {x : Φx = y} for diagonal ΦΦᵀ: x + Φᵀ((y − Φx) / diag ΦΦᵀ)."""
    return x + camera.A_adjoint((y - camera.A(x)) / phi)


def _grad(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences along H and W (zero on the last row/column): (B, C, H, W) each."""
    gy = torch.zeros_like(u)
    gx = torch.zeros_like(u)
    gy[..., :-1, :] = u[..., 1:, :] - u[..., :-1, :]
    gx[..., :, :-1] = u[..., :, 1:] - u[..., :, :-1]
    return gy, gx


def total_variation(u: torch.Tensor) -> torch.Tensor:
    """Isotropic spatial TV of each cube, summed over bands and pixels, (B,)."""
    gy, gx = _grad(u)
    return torch.sqrt(gy * gy + gx * gx).flatten(1).sum(1)


def tv_denoise(f: torch.Tensor, weight: float | torch.Tensor, iterations: int = 5, tau: float = 0.125) -> torch.Tensor:
    """argmin_u ½‖u − f‖² + weight·TV(u), isotropic spatial TV per band (Chambolle 2004).

    Args:
        f: (B, C, H, W) cube.
        weight: λ ≥ 0 (a float or a tensor broadcastable to (B, C, 1, 1)).
        iterations: dual projection iterations (started from zero).
        tau: dual step (≤ 1/8 for convergence).
    """
    if iterations <= 0 or (not torch.is_tensor(weight) and weight <= 0):
        return f
    w = torch.as_tensor(weight, dtype=f.dtype, device=f.device)
    g = f / w.clamp_min(1e-12)
    py = torch.zeros_like(f)
    px = torch.zeros_like(f)
    for _ in range(iterations):
        py, px = chambolle_step(py, px, g, tau, inplace=True)
    return f - w * dual_divergence(py, px)
