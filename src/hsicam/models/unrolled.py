"""Deep-unfolding reconstruction for any camera with ``A`` / ``A_adjoint`` (DOE camera, CASSI).

    x⁰ = init(y)                                   demosaic (CFA cameras), normalised back-projection,
                                                   or a MosaicNet front end
    for k = 1..K:
        z = x − α_k Aᵀ(A x − y)                      gradient step on ½‖A x − y‖², α_k = softplus(θ_k) / L
          or x + α_k Aᵀ((y − A x) ⊘ diag(AAᵀ))       GAP step (CASSI: ΦΦᵀ diagonal), α_k = softplus(θ_k)
        x = z + P_k(z)                              learned prior: residual CNN at 1/s resolution

At a pixel the sensor clipped (``clipped``, a capture's saturated-pixel map; never in training) y is a lower
bound of A x*: there the residual is one-sided (:func:`hsicam.models.consistency.clipped_residual`), as in the
consistency steps after the network, so no stage pulls a highlight down to the clip.

With ``brightness_window`` w > 0 each prior works on z/b and returns b·P(z/b), b = box_w(mean_c |z|) + ε,
so a stage treats a scene and a darker copy alike (the gradient step is linear already).

A is the camera's operator frozen for the batch (:meth:`Camera.snapshot`: the DOE camera's PSF
stack and CFA, computed once, with gradients to the optics); L is the snapshot's bound of ‖A‖², so
α_k·L = softplus(θ_k) is a step in units of the largest safe one (< 2 decreases the data term).
Every stage sees the exact operator that made the measurement, so the same network serves the
DOE camera and both CASSI cameras. The prior starts at zero (P_k = 0): the untrained network runs
K plain gradient steps from x⁰.

Tiling: the prior regroups pixels in s×s cells aligned with the sensor grid (``origin``), and each
gradient step spreads a pixel by the operator's reach (K_psf − 1 px for the DOE camera, the
dispersion span for SD-CASSI, 0 for DD-CASSI); :attr:`UnrolledNet.context_px` sums these over the
stages, so tiles with that halo equal the whole image (the ``same``-geometry operator treats
light from outside the window as zero).
"""

from __future__ import annotations

import logging
import math

import torch
import torch.nn.functional as F
from torch import nn

from hsicam.config import UnrolledConfig
from hsicam.errors import ConfigError
from hsicam.models.registry import register_network
from hsicam.models.mosaic import (MOSAIC_SIZES, MosaicNet, ResBlock, _odd_window, build_mosaic,
                                  mosaic_parameter_count, phase_pad)
from hsicam.models.consistency import checked_clipped, clipped_residual
from hsicam.models.demosaic import backprojection, brightness, camera_operator, demosaic

INITS = UnrolledConfig.INITS
STEPS = UnrolledConfig.STEPS

log = logging.getLogger(__name__)


class Prior(nn.Module):
    """z + P(z) − z: residual CNN at 1/s resolution, (B, C, H, W) → Δ (B, C, H, W); output conv zero."""

    def __init__(self, bands: int, features: int, blocks: int, scale: int, brightness_window: int = 0,
                 brightness_eps: float = 1e-3) -> None:
        super().__init__()
        self.scale, self.blocks = int(scale), int(blocks)
        self.brightness_window, self.brightness_eps = int(brightness_window), float(brightness_eps)
        ch = bands * scale * scale
        self.stem = nn.Conv2d(ch, features, 1)
        self.body = nn.Sequential(*(ResBlock(features) for _ in range(blocks)))
        self.tail = nn.Conv2d(features, ch, 1)
        nn.init.zeros_(self.tail.weight)
        nn.init.zeros_(self.tail.bias)

    @property
    def reach_px(self) -> int:
        return 2 * self.blocks * self.scale + self.scale - 1 + self.brightness_window // 2

    def forward(self, z: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        h, w = z.shape[-2:]
        s = self.scale
        b = None
        if self.brightness_window:
            b = brightness(z.abs().mean(dim=1, keepdim=True), self.brightness_window, self.brightness_eps)
            z = z / b
        zp, (top, left) = phase_pad(z, s, origin)
        f = self.body(self.stem(F.pixel_unshuffle(zp, s)))
        out = F.pixel_shuffle(self.tail(f), s)[..., top : top + h, left : left + w]
        return out if b is None else out * b


class UnrolledNet(nn.Module):
    """Sensor (B, 1, H, W) + camera → cube (B, C, H', W') (H', W' = ``scene_size``); module docstring.

    Args:
        bands: C.
        op_reach: (rows, columns) a gradient step spreads a pixel (the operator's AᵀA reach, px).
        init: "demosaic", "backprojection" or "mosaic".
        front: the MosaicNet of init="mosaic".

    Its data steps read the measurement, so ``forward`` takes a capture's clipped pixels (:attr:`takes_clipped`:
    :class:`~hsicam.models.system.CameraSystem` passes the map of its camera's noise model).
    """

    takes_clipped = True

    def __init__(self, bands: int, op_reach: tuple[int, int], stages: int = 2, init: str = "demosaic",
                 share_weights: bool = False, prior_features: int = 64, prior_blocks: int = 2, prior_scale: int = 4,
                 step_init: float = 1.0, stage_kernel_px: int = 0, demosaic_window: int = 9,
                 front: MosaicNet | None = None, step: str = "gradient", brightness_window: int = 0,
                 brightness_eps: float = 1e-3) -> None:
        super().__init__()
        # the config's checks (UnrolledConfig), again for a network built directly
        if int(stages) < 1:
            raise ValueError(f"stages must be >= 1, got {stages}")
        if not (step_init > 0 and math.isfinite(step_init)):
            raise ValueError(f"step_init must be a finite number > 0, got {step_init}")
        if init not in ("demosaic", "backprojection", "mosaic") or (init == "mosaic") != (front is not None):
            raise ValueError(f"init must be demosaic, backprojection or mosaic (with front=a MosaicNet), got {init!r}")
        if step not in ("gradient", "gap"):
            raise ValueError(f"step must be gradient or gap, got {step!r}")
        self.bands, self.stages, self.init, self.step = int(bands), int(stages), init, step
        self.op_reach, self.stage_kernel_px, self.demosaic_window = tuple(op_reach), int(stage_kernel_px), int(demosaic_window)
        self.front = front
        n_priors = 1 if share_weights else stages
        self.priors = nn.ModuleList(Prior(bands, prior_features, prior_blocks, prior_scale, brightness_window, brightness_eps)
                                    for _ in range(n_priors))
        theta = math.log(math.expm1(step_init))  # softplus⁻¹
        self.step_logits = nn.Parameter(torch.full((stages,), theta))

    @property
    def context_px(self) -> int:
        """Per-side halo (sensor px) for exact tiling: the init's reach + K × (AᵀA reach + prior reach)."""
        reach = max(self.op_reach)
        if self.init == "demosaic":
            first = self.demosaic_window // 2
        elif self.init == "mosaic":
            first = self.front.context_px
        else:
            first = reach
        return first + self.stages * reach + sum(self._prior(k).reach_px for k in range(self.stages))

    def _prior(self, k: int) -> Prior:
        return self.priors[k % len(self.priors)]

    def step_sizes(self, lipschitz: float | torch.Tensor | None) -> torch.Tensor:
        """α_k (K,) = softplus(θ_k) / L (gradient steps) or softplus(θ_k) (GAP steps). ``lipschitz``: the
        operator's bound L of ‖A‖², a 0-dim tensor where it carries gradients to the optics."""
        if self.step == "gap":
            return F.softplus(self.step_logits)
        return F.softplus(self.step_logits) / (lipschitz or 1.0)

    def operator(self, camera):
        op = camera_operator(camera)
        if self.stage_kernel_px and hasattr(op, "cropped"):
            op = op.cropped(self.stage_kernel_px)
        return op

    def initial(self, sensor: torch.Tensor, op, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """x⁰ (B, C, H', W')."""
        if self.init == "mosaic":
            return self.front(sensor, op, origin)
        if self.init == "demosaic":
            code = op.sensor_code(sensor.shape[-2], sensor.shape[-1], origin).to(sensor)
            return demosaic(sensor, code, self.demosaic_window)
        return backprojection(op, sensor, origin)

    def data_step(self, x: torch.Tensor, sensor: torch.Tensor, op, alpha: torch.Tensor,
                  origin: tuple[int, int] = (0, 0), clipped: torch.Tensor | None = None) -> torch.Tensor:
        """x − α Aᵀ(A x − y), or the GAP step x + α Aᵀ((y − A x) ⊘ diag(AAᵀ)); at the ``clipped`` pixels (bool,
        broadcastable to y; None: none) only an estimate darker than y is corrected (:func:`clipped_residual`)."""
        r = -clipped_residual(sensor - op.A(x, origin), clipped)
        if self.step == "gap":
            d = op.gram_diagonal(sensor, origin)
            r = r / d.clamp_min(1e-6 * (getattr(op, "lipschitz", None) or 1.0))  # position-independent ε
        return x - alpha * op.A_adjoint(r, origin)

    def forward(self, sensor: torch.Tensor, camera, origin: tuple[int, int] = (0, 0),
                clipped: torch.Tensor | None = None) -> torch.Tensor:
        """``sensor`` (B, 1, H, W) of the window at ``origin``; ``camera``: a Camera or its snapshot; ``clipped``:
        the window's clipped pixels (bool, broadcastable to ``sensor``; None: none), lower bounds in every data
        step. Returns (B, C, H', W') in the network's dtype (float32)."""
        if sensor.dim() != 4 or sensor.shape[1] != 1:
            raise ValueError(f"sensor image must be (B, 1, H, W), got shape {tuple(sensor.shape)}")
        sensor = sensor.to(self.step_logits.dtype)  # float32 unless the network was converted
        clipped = checked_clipped(clipped, sensor)
        op = self.operator(camera)
        if len(op.bands) != self.bands:
            raise ValueError(f"the camera has {len(op.bands)} bands, the network {self.bands}")
        x = self.initial(sensor, op, origin)
        bound = getattr(op, "lipschitz_in_graph", None)  # L with its gradient to the optics, where they have one
        alphas = self.step_sizes(bound if bound is not None else getattr(op, "lipschitz", None))
        for k in range(self.stages):
            x = self.data_step(x, sensor, op, alphas[k], origin, clipped)
            x = x + self._prior(k)(x, origin)
        return x


def build_unrolled(mcfg: UnrolledConfig, camera) -> UnrolledNet:
    """An :class:`UnrolledNet` for ``camera`` (any camera with ``snapshot``)."""
    try:
        camera.sensor_code(1, 1)
        has_code = True
    except NotImplementedError:
        has_code = False
    init = mcfg.init if mcfg.init != "auto" else ("demosaic" if has_code else "backprojection")
    if init in ("demosaic", "mosaic") and not has_code:
        raise ConfigError(f"model.unrolled.init={init} needs a camera with a colour filter array (the DOE camera), "
                          f"not {type(camera).__name__}; use init=backprojection (or auto)")
    with torch.no_grad():
        op = camera.snapshot(nominal=True)
        if mcfg.stage_kernel_px and hasattr(op, "cropped"):
            op = op.cropped(mcfg.stage_kernel_px)
    if mcfg.stage_kernel_px and not hasattr(op, "cropped"):
        # a note, not a warning nor a refusal: the quick preset's 31 (the DOE camera's) reaches its own
        # dd-cassi-unrolled baseline (hsicam.engine.experiments), whose trained runs must still load
        log.info("model.unrolled.stage_kernel_px=%d is not applied: it cuts the DOE camera's PSF in the stages, and "
                 "%s has no PSF kernel to cut (its stages use its exact operator)",
                 mcfg.stage_kernel_px, type(camera).__name__)
    if mcfg.step == "gap" and not hasattr(op, "gram_diagonal"):
        raise ConfigError(f"model.unrolled.step=gap needs a camera whose ΦΦᵀ is diagonal (CASSI), not "
                          f"{type(camera).__name__}; use step=gradient")
    period = int(getattr(camera, "code_period", 1))
    window = mcfg.demosaic_window or _odd_window(period)
    front = build_mosaic(mcfg.mosaic, camera, "model.unrolled.mosaic") if init == "mosaic" else None
    return UnrolledNet(len(camera.bands), tuple(op.reach_px), mcfg.stages, init, mcfg.share_weights, mcfg.prior_features,
                       mcfg.prior_blocks, mcfg.prior_scale, mcfg.step_init, mcfg.stage_kernel_px, window, front,
                       mcfg.step, mcfg.brightness_window, mcfg.brightness_eps)


def unrolled_parameters(bands: int, stages: int = 2, share_weights: bool = False, prior_features: int = 64,
                        prior_blocks: int = 2, prior_scale: int = 4) -> int:
    """The parameters of an :class:`UnrolledNet` of these sizes without its front end, in closed form:
    one step logit per stage and one :class:`Prior` per stage (or one shared)."""
    ch, f = bands * prior_scale * prior_scale, prior_features
    prior = (ch * f + f) + prior_blocks * 2 * (9 * f * f + f) + (f * ch + ch)  # stem 1×1, residual blocks, tail 1×1
    return stages + (1 if share_weights else stages) * prior


def unrolled_parameter_count(mcfg: UnrolledConfig, camera) -> int:
    """The parameters :func:`build_unrolled` makes for ``mcfg`` and ``camera`` (with init=mosaic, its front end's)."""
    n = unrolled_parameters(len(camera.bands), mcfg.stages, mcfg.share_weights, mcfg.prior_features, mcfg.prior_blocks,
                            mcfg.prior_scale)
    return n + (mosaic_parameter_count(mcfg.mosaic, camera) if mcfg.init == "mosaic" else 0)  # auto is never mosaic


def unrolled_sizes(mcfg: UnrolledConfig) -> tuple[str, ...]:
    """The keys of ``model.unrolled`` that set its parameter count (the front end's with init=mosaic)."""
    own = ("stages", "share_weights", "prior_features", "prior_blocks", "prior_scale")
    return own + tuple(f"mosaic.{k}" for k in MOSAIC_SIZES) if mcfg.init == "mosaic" else own


__all__ = ["Prior", "UnrolledNet", "UnrolledConfig", "backprojection", "build_unrolled", "camera_operator",
           "unrolled_parameter_count", "unrolled_parameters"]


@register_network("unrolled", parameters=lambda cfg, camera: unrolled_parameter_count(cfg.model.unrolled, camera),
                  sizes=unrolled_sizes)
def _build_registered(cfg, camera):
    """``model.kind: unrolled`` with the settings ``cfg.model.unrolled``."""
    return build_unrolled(cfg.model.unrolled, camera)
