"""Settings of the baseline solvers, as strict config sections (``baselines.gaptv``, ``.desci``, ``.choi``).

Plain dataclasses that import nothing but :mod:`hsicam.errors`, so that :mod:`hsicam.config` can
make them a section of the top-level config. Until it does, :class:`ConfigWithBaselines` (in
:mod:`hsicam.solvers.methods`) is the top-level config plus this section, and the solvers use
the defaults below for configs without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Optional

from hsicam.errors import ConfigError


def _check_positive(section: str, **values) -> None:
    for k, v in values.items():
        if v is not None and not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"{section}.{k} must be positive, got {v}")


def _check_at_least(section: str, low: int, **values) -> None:
    for k, v in values.items():
        if v is not None and v < low:
            raise ConfigError(f"{section}.{k} must be >= {low}, got {v}")


@dataclass
class GAPTVConfig:
    """GAP-TV (hsicam.solvers.gaptv): accelerated GAP + spatial TV denoising."""

    iterations: int = 80
    tv_weight: float = 0.01  # λ of ½‖u − x‖² + λ·TV(u), cube values in [0, 1]
    tv_iterations: int = 5  # Chambolle iterations per denoising
    accelerate: bool = True

    def __post_init__(self) -> None:
        _check_at_least("baselines.gaptv", 0, iterations=self.iterations, tv_iterations=self.tv_iterations)
        if not (self.tv_weight >= 0 and math.isfinite(self.tv_weight)):
            raise ConfigError(f"baselines.gaptv.tv_weight must be >= 0, got {self.tv_weight}")


@dataclass
class DeSCIConfig:
    """DeSCI (hsicam.solvers.desci). ``preset`` fast (minutes per 256×256×31 scene on a CPU) or
    full (closer to the published setting); any other key set here overrides the preset."""

    preset: Literal["fast", "full"] = "fast"
    patch: Optional[int] = None
    step: Optional[int] = None
    search: Optional[int] = None
    group: Optional[int] = None
    sigmas: Optional[list[float]] = None
    iterations: Optional[list[int]] = None
    c: Optional[float] = None
    match_every: Optional[int] = None
    match_components: Optional[int] = None
    init_iterations: Optional[int] = None
    init_tv_weight: Optional[float] = None

    def __post_init__(self) -> None:
        sec = "baselines.desci"
        _check_at_least(sec, 1, patch=self.patch, step=self.step, group=self.group, match_every=self.match_every,
                        match_components=self.match_components)
        _check_at_least(sec, 0, search=self.search, init_iterations=self.init_iterations)
        _check_positive(sec, c=self.c)
        if self.sigmas is not None and (not self.sigmas or not all(s > 0 and math.isfinite(s) for s in self.sigmas)):
            raise ConfigError(f"{sec}.sigmas must be a non-empty list of positive numbers, got {self.sigmas}")
        if self.iterations is not None and (not self.iterations or min(self.iterations) < 0):
            raise ConfigError(f"{sec}.iterations must be a non-empty list of counts >= 0, got {self.iterations}")
        if self.sigmas is not None and self.iterations is not None and len(self.sigmas) != len(self.iterations):
            raise ConfigError(f"{sec}: {len(self.sigmas)} sigmas but {len(self.iterations)} iteration counts")

    def overrides(self) -> dict:
        """The keys set here (not None), without ``preset``."""
        return {k: v for k, v in self.__dict__.items() if k != "preset" and v is not None}


@dataclass
class ChoiConfig:
    """Choi et al. 2017 (hsicam.solvers.choi): autoencoder spectral prior + ADMM.

    Prior architecture and training (``hsicam baseline train-prior``) and the ADMM solve.
    """

    # autoencoder
    features: int = 48
    latent: int = 12  # latent channels (the learned spectral representation), < bands
    # training (a denoising autoencoder on training-split patches)
    train_steps: int = 1500
    batch_size: int = 8
    lr: float = 1e-3
    train_noise: float = 0.05  # Gaussian σ of the input corruption, drawn in [0, train_noise] per patch
    seed: int = 0
    # ADMM
    iterations: int = 60
    rho: float = 0.5  # ADMM penalty (data term normalised so that mean diag ΦΦᵀ = 1)
    rho_growth: float = 1.03  # ρ ← ρ·growth per iteration (1: constant)
    prior_weight: float = 0.1  # τ1 of (τ1/2)‖z − D(E(z))‖²
    tv_weight: float = 0.003  # τ2 of τ2·TV(z)
    inner_steps: int = 2  # proximal-gradient steps of each z-update
    init_iterations: int = 20  # GAP-TV iterations of the start (0: the minimum-norm solution)

    def __post_init__(self) -> None:
        sec = "baselines.choi"
        _check_at_least(sec, 1, features=self.features, latent=self.latent, train_steps=self.train_steps,
                        batch_size=self.batch_size, inner_steps=self.inner_steps)
        _check_at_least(sec, 0, iterations=self.iterations, init_iterations=self.init_iterations)
        _check_positive(sec, lr=self.lr, rho=self.rho, rho_growth=self.rho_growth)
        for k in ("train_noise", "prior_weight", "tv_weight"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{sec}.{k} must be >= 0, got {v}")


@dataclass
class BaselinesConfig:
    """Settings of the CASSI baseline solvers."""

    gaptv: GAPTVConfig = field(default_factory=GAPTVConfig)
    desci: DeSCIConfig = field(default_factory=DeSCIConfig)
    choi: ChoiConfig = field(default_factory=ChoiConfig)


def baseline_settings(cfg) -> BaselinesConfig:
    """``cfg.baselines`` when the config has that section, else the defaults."""
    b = getattr(cfg, "baselines", None)
    return b if isinstance(b, BaselinesConfig) else BaselinesConfig()
