"""Total variation by Chambolle's dual projection (2004), shared by the TV prior of the consistency steps
(:class:`hsicam.models.consistency.BrightnessTV`) and the solvers' TV denoising
(:func:`hsicam.solvers.common.tv_denoise`).

argmin_u ½‖u − f‖² + w·TV(u) = f − w·div p*, p* the fixed point of

    d = div p − f / w;   p ← (p + τ ∇d) / (1 + τ |∇d|),

∇ the forward differences (zero on the last row / column), div = −∇ᵀ. |∇d| is the gradient's norm per band
(isotropic TV of each band) or over every band at once (vectorial TV: bands share their edges, Bresson & Chan
2008). Arrays are (B, C, H, W).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: Chambolle's dual step: ‖div‖² ≤ 8 for 2-D forward differences, and τ ≤ 1/8 makes the projection converge.
CHAMBOLLE_TAU = 0.125


def dual_divergence(py: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
    """div p = −∇ᵀp for a dual field whose last row (py) and last column (px) are zero, as
    :func:`chambolle_step` keeps them: p minus its shifted self."""
    return py - F.pad(py[..., :-1, :], (0, 0, 1, 0)) + px - F.pad(px[..., :, :-1], (1, 0))


def chambolle_step(py: torch.Tensor, px: torch.Tensor, g: torch.Tensor, tau: float = CHAMBOLLE_TAU,
                   vectorial: bool = False, inplace: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """One iteration of the dual projection for g = f / w: the new (py, px). ``vectorial``: the norm of the
    gradient over every band and both directions (else per band). ``inplace``: update py and px in place (the
    solvers' denoising; not differentiable through them)."""
    d = dual_divergence(py, px) - g
    gy = F.pad(d[..., 1:, :] - d[..., :-1, :], (0, 0, 0, 1))
    gx = F.pad(d[..., :, 1:] - d[..., :, :-1], (0, 1))
    if vectorial:
        # + tiny: the square root's gradient stays finite where the field is flat (its value does not move)
        norm = 1 + tau * ((gy * gy + gx * gx).sum(dim=1, keepdim=True) + torch.finfo(g.dtype).tiny).sqrt()
    else:
        norm = torch.hypot(gy, gx).mul_(tau).add_(1.0)
    if inplace:
        return py.add_(gy, alpha=tau).div_(norm), px.add_(gx, alpha=tau).div_(norm)
    return (py + tau * gy) / norm, (px + tau * gx) / norm
