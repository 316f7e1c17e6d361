"""Choi et al. 2017, "High-quality hyperspectral reconstruction using a spectral prior" (ACM TOG 36(6)).

A convolutional autoencoder (encoder E, decoder D) learns a spatial–spectral representation of
hyperspectral patches (trained as a denoising autoencoder on the training split of our data; the
published layer stack, 6 + 6 3×3 convolutions and a full-resolution code with no spectral
bottleneck, plus a skip, so that R(x) = x + D(E(x)): :class:`hsicam.models.priors.SpectralAutoencoder`);
the reconstruction then solves, by ADMM with the splitting x = z,

    min_x ½‖ỹ − Φ̃x‖² + (τ1/2)‖x − R(x)‖² + τ2·TV(x)

where Φ̃ = Φ/√m and ỹ = y/√m with m the mean of diag ΦΦᵀ (so that ρ, τ1, τ2 do not depend on
the camera's band convention). It starts from GAP-TV (``init_iterations``, the GAP-TV baseline's
TV weight); the x-update is exact (ΦΦᵀ is diagonal for CASSI); the z-update takes a few
proximal-gradient steps on the prior term (gradient through the autoencoder by autograd) with an
exact TV proximal step; the dual update is standard. ρ grows geometrically, which makes the
iteration converge with an inexact prior step.

Differences from the paper, stated so results can be read correctly (tables call it
"Choi-style"): the paper's prior term acts on the code α (15 ADMM iterations × 100 Adam steps on
α through the decoder, TV split on the image gradients); here the prior term ‖x − D(E(x))‖² and
TV act on the cube, which costs one autoencoder gradient per inner step instead of a hundred
Adam steps. Measured (session 25, docs/training_log.md): the earlier 3 + 3 mostly-1×1 autoencoder
with a 12-channel code reconstructed *clean* cubes at SAM ≈ 23°, so the ADMM pulled spectra away
from the truth (SAM worse than GAP-TV); the published plain 6 + 6 stack did not train within the
CPU scales' step budgets (after 800 of 1500 steps its loss was still 3× the identity's), hence the skip. A "RED" z-update
(z pulled towards R(z) without the Jacobian) degraded SAM on training scenes and was not kept.

The prior is any module R (:class:`hsicam.models.priors.SpectralAutoencoder`, trained and loaded by
:mod:`hsicam.engine.prior`).
"""
from __future__ import annotations

import logging
import math
import time

import torch
from torch import nn

from hsicam.errors import InputError
from hsicam.solvers.common import checked_gram_diagonal, total_variation, tv_denoise
from hsicam.config import ChoiConfig, GAPTVConfig
from hsicam.solvers.gaptv import SolverInfo, gap_tv

log = logging.getLogger(__name__)



# --------------------------------------------------------------------------------------------
# ADMM
# --------------------------------------------------------------------------------------------
def prior_residual(prior: nn.Module, z: torch.Tensor) -> torch.Tensor:
    """½‖z − R(z)‖² per cube, (B,)."""
    return 0.5 * (z - prior(z)).square().flatten(1).sum(1)


def choi_objective(camera, prior: nn.Module, x: torch.Tensor, y: torch.Tensor, scale: float, prior_weight: float,
                   tv_weight: float) -> float:
    """½‖ỹ − Φ̃x‖² + τ1·½‖x − R(x)‖² + τ2·TV(x), summed over the batch (normalised data term)."""
    data = 0.5 * (camera.A(x) - y).square().sum() / scale
    return float(data + prior_weight * prior_residual(prior, x).sum() + tv_weight * total_variation(x).sum())


def _prior_grad(prior: nn.Module, z: torch.Tensor) -> torch.Tensor:
    """∇_z ½‖z − R(z)‖² by autograd (works inside torch.no_grad callers)."""
    with torch.enable_grad():
        zz = z.detach().requires_grad_(True)
        val = prior_residual(prior, zz).sum()
        (grad,) = torch.autograd.grad(val, zz)
    return grad


@torch.no_grad()
def admm_prior(camera, y: torch.Tensor, prior: nn.Module, settings: ChoiConfig | None = None,
               x0: torch.Tensor | None = None, return_info: bool = False,
               init_tv_weight: float = GAPTVConfig.tv_weight):
    """Choi et al. reconstruction: measurement (B, 1, H, W') → cube (B, C, H, W) [, SolverInfo].

    ``init_tv_weight`` is the TV weight λ of the GAP-TV start (the GAP-TV baseline's,
    ``baselines.gaptv.tv_weight``; cube values in [0, 1]). ``info.objective`` holds the objective of
    the z-iterate after each iteration (when ``return_info``); ``info.extra["primal_residual"]`` the
    ‖x − z‖ / ‖z‖ sequence.
    """
    phi = checked_gram_diagonal(camera, y, x0, "Choi")
    h, w = camera.scene_size(tuple(y.shape[-2:]))
    if min(h, w) < 2:  # a reflect-padded 3×3 convolution needs 2 px a side (torch refused 1 px with a RuntimeError)
        raise InputError(f"Choi: the cube ({h}×{w} px) is smaller than 2×2 px, which the prior's reflect-padded "
                         "convolutions need")
    if not (init_tv_weight >= 0 and math.isfinite(init_tv_weight)):
        raise InputError(f"Choi: init_tv_weight must be a finite number >= 0, got {init_tv_weight}")
    s = settings or ChoiConfig()
    t0 = time.perf_counter()
    info = SolverInfo()
    scale = float(phi.mean())  # m: Φ̃ = Φ/√m has mean diag Φ̃Φ̃ᵀ = 1
    phi_n = phi / scale
    prior_dtype = next(prior.parameters()).dtype
    run_prior = prior if prior_dtype == y.dtype else _CastPrior(prior, prior_dtype)
    if x0 is not None:
        x = x0.clone()
    elif s.init_iterations > 0:
        x = gap_tv(camera, y, s.init_iterations, init_tv_weight)
    else:
        x = camera.A_adjoint(y / phi)
    z, u = x.clone(), torch.zeros_like(x)
    rho = s.rho
    primal = []
    if return_info:
        info.objective.append(choi_objective(camera, run_prior, z, y, scale, s.prior_weight, s.tv_weight))
    for _ in range(s.iterations):
        # x-update: argmin ½‖ỹ − Φ̃x‖² + ρ/2‖x − v‖², exact for diagonal ΦΦᵀ
        v = z - u
        x = v + camera.A_adjoint((y - camera.A(v)) / scale / (phi_n + rho))
        # z-update: proximal-gradient steps on τ1·½‖z − R(z)‖² + ρ/2‖z − w‖², TV prox
        w = x + u
        step = 1.0 / (rho + 4.0 * s.prior_weight)
        for _ in range(s.inner_steps):
            grad = s.prior_weight * _prior_grad(run_prior, z) + rho * (z - w)
            z = tv_denoise(z - step * grad, step * s.tv_weight, 5)
        u = u + x - z
        primal.append(float((x - z).norm() / z.norm().clamp_min(1e-30)))
        if return_info:
            info.objective.append(choi_objective(camera, run_prior, z, y, scale, s.prior_weight, s.tv_weight))
            info.residual.append(camera.relative_residual(z, y))
        # u is the scaled dual (the multiplier over ρ): when ρ grows it shrinks by the same factor, so the multiplier
        # carries over (Boyd et al. 2011, §3.4.1; session 74's audit: ~0.01 dB, correct either way)
        u = u / s.rho_growth
        rho *= s.rho_growth
    info.iterations = s.iterations
    info.runtime_s = time.perf_counter() - t0
    info.extra = {"primal_residual": primal, "init_tv_weight": init_tv_weight}
    log.info("Choi ADMM: %d iterations in %.1f s", s.iterations, info.runtime_s)
    return (z, info) if return_info else z


class _CastPrior(nn.Module):
    """Runs a prior in its own dtype on inputs of another dtype."""

    def __init__(self, prior: nn.Module, dtype: torch.dtype) -> None:
        super().__init__()
        self.prior, self.dtype = prior, dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.prior(x.to(self.dtype)).to(x.dtype)
