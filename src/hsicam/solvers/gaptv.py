"""GAP-TV: generalized alternating projection with total-variation denoising (Yuan, ICIP 2016).

Each iteration projects the estimate onto the measurement constraint {x : Φx = y} (exactly, since
ΦΦᵀ is diagonal for CASSI) and then denoises it with spatial TV::

    x ← x + Φᵀ((y − Φx) / diag ΦΦᵀ)                     (plain GAP)
    ȳ ← ȳ + (y − Φx);  x ← x + Φᵀ((ȳ − Φx) / diag ΦΦᵀ)   (accelerated GAP: ȳ accumulates the residual)
    x ← argmin_u ½‖u − x‖² + λ·TV(u)

The accelerated variant is GAP's "generalized" form that reaches noiseless-measurement
solutions faster; plain GAP is more robust to measurement noise.
"""

from __future__ import annotations

import logging
import math
import numbers
import time
from dataclasses import dataclass, field

import torch

from hsicam.config import GAPTVConfig
from hsicam.errors import InputError
from hsicam.solvers.common import check_count, checked_gram_diagonal, tv_denoise

log = logging.getLogger(__name__)


@dataclass
class SolverInfo:
    """What an iterative solver did: iterations, runtime, and per-iteration traces."""

    iterations: int = 0
    runtime_s: float = 0.0
    residual: list[float] = field(default_factory=list)  # ‖y − Φx‖ / ‖y‖ after each iteration
    objective: list[float] = field(default_factory=list)
    extra: dict = field(default_factory=dict)


@torch.no_grad()
def gap_tv(camera, y: torch.Tensor, iterations: int = GAPTVConfig.iterations,
           tv_weight: float | list[float] = GAPTVConfig.tv_weight,
           tv_iterations: int = 5, accelerate: bool = True, x0: torch.Tensor | None = None,
           return_info: bool = False):
    """GAP-TV reconstruction of a measurement.

    Args:
        camera: any camera with ``A``/``A_adjoint`` and diagonal ΦΦᵀ (CASSI).
        y: measurement (B, 1, H, W').
        iterations: GAP iterations (default: the config's, tuned on training scenes).
        tv_weight: TV weight λ (cube values in [0, 1]); a list gives one weight per iteration
            (the last one repeats).
        tv_iterations: Chambolle iterations of each TV denoising.
        accelerate: accelerated GAP (residual accumulation).
        x0: start (B, C, H, W); default Φᵀ(y / diag ΦΦᵀ), the minimum-norm solution (the published
            codes start from Φᵀy; with the accumulation below this start equals theirs from x = 0).
        return_info: also return a :class:`SolverInfo`.

    Returns:
        cube (B, C, H, W) [, SolverInfo].
    """
    phi = checked_gram_diagonal(camera, y, x0, "GAP-TV")
    check_count("iterations", iterations)
    check_count("tv_iterations", tv_iterations)
    weights = tv_weight if isinstance(tv_weight, (list, tuple)) else [tv_weight]
    bad = [w for w in weights if isinstance(w, bool) or not isinstance(w, numbers.Real) or not 0 <= w < math.inf]
    if bad or not weights:
        raise InputError(f"tv_weight must be a finite number >= 0 (or a non-empty list of them), got {tv_weight!r}")
    t0 = time.perf_counter()
    info = SolverInfo()
    x = camera.A_adjoint(y / phi) if x0 is None else x0.clone()
    y_acc = y.clone()
    for k in range(iterations):
        yb = camera.A(x)
        if accelerate:
            y_acc = y_acc + (y - yb) if k > 0 else y_acc
            x = x + camera.A_adjoint((y_acc - yb) / phi)
        else:
            x = x + camera.A_adjoint((y - yb) / phi)
        x = tv_denoise(x, weights[min(k, len(weights) - 1)], tv_iterations)
        if return_info:
            info.residual.append(camera.relative_residual(x, y))
    info.iterations = iterations
    info.runtime_s = time.perf_counter() - t0
    log.debug("GAP-TV: %d iterations in %.2f s", iterations, info.runtime_s)
    return (x, info) if return_info else x
