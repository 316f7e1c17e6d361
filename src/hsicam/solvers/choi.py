"""Choi et al. 2017, "High-quality hyperspectral reconstruction using a spectral prior" (ACM TOG 36(6)).

A convolutional autoencoder R = D∘E learns a low-dimensional spatial–spectral representation of
hyperspectral patches (trained as a denoising autoencoder on the training split of our data);
the reconstruction then solves, by ADMM with the splitting x = z,

    min_x ½‖ỹ − Φ̃x‖² + (τ1/2)‖x − R(x)‖² + τ2·TV(x)

where Φ̃ = Φ/√m and ỹ = y/√m with m the mean of diag ΦΦᵀ (so that ρ, τ1, τ2 do not depend on
the camera's band convention). The x-update is exact (ΦΦᵀ is diagonal for CASSI); the z-update
takes a few proximal-gradient steps on the prior term (gradient through the autoencoder by
autograd) with an exact TV proximal step; the dual update is standard. ρ grows geometrically,
which makes the iteration converge with an inexact prior step.

Differences from the paper, stated so results can be read correctly: the paper's prior term acts
on the latent code and is minimised with its own inner solver; here the "fidelity to the learned
representation" ‖x − D(E(x))‖² and TV act on the cube. The autoencoder's size (``features``,
``latent``) is ours, as the data are.

Prior run folder (``hsicam baseline train-prior``)::

    RUN/config.yaml        the data/band config it was trained with (a plain hsicam config)
    RUN/prior.yaml         the ``baselines.choi`` settings (architecture, training, ADMM)
    RUN/prior.safetensors  autoencoder weights (bands in the metadata)
    RUN/metrics.jsonl      training loss
    RUN/summary.json       written last: the run is finished
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path

import torch
import torch.nn.functional as F
import yaml
from torch import nn

from hsicam.errors import InputError
from hsicam.solvers.common import phi_diagonal, total_variation, tv_denoise
from hsicam.solvers.config import ChoiConfig
from hsicam.solvers.gaptv import SolverInfo, check_measurement, gap_tv, relative_residual
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

PRIOR_WEIGHTS = "prior.safetensors"
PRIOR_SETTINGS = "prior.yaml"


# --------------------------------------------------------------------------------------------
# The autoencoder
# --------------------------------------------------------------------------------------------
class SpectralAutoencoder(nn.Module):
    """Convolutional autoencoder: cube (B, C, H, W) → latent (B, L, H, W) → cube.

    Encoder 3×3 (C→F), 1×1 (F→F), 1×1 (F→L); decoder 1×1 (L→F), 3×3 (F→F), 1×1 (F→C); leaky ReLU
    between layers, reflect padding. Spatial context 5×5; the latent keeps full resolution (the
    spectral dimension is what is compressed, C → L).
    """

    def __init__(self, bands: int, features: int = 48, latent: int = 12) -> None:
        super().__init__()
        if min(bands, features, latent) < 1:
            raise ValueError("autoencoder sizes must be >= 1")
        act = lambda: nn.LeakyReLU(0.1)  # noqa: E731
        self.encoder = nn.Sequential(
            nn.Conv2d(bands, features, 3, padding=1, padding_mode="reflect"), act(),
            nn.Conv2d(features, features, 1), act(),
            nn.Conv2d(features, latent, 1),
        )
        self.decoder = nn.Sequential(
            nn.Conv2d(latent, features, 1), act(),
            nn.Conv2d(features, features, 3, padding=1, padding_mode="reflect"), act(),
            nn.Conv2d(features, bands, 1),
        )

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(z)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))


def build_prior(n_bands: int, settings: ChoiConfig) -> SpectralAutoencoder:
    return SpectralAutoencoder(n_bands, settings.features, settings.latent)


# --------------------------------------------------------------------------------------------
# Training and loading
# --------------------------------------------------------------------------------------------
def is_prior_run(run: str | Path) -> bool:
    """A finished prior run folder (summary.json and weights present)."""
    run = Path(run)
    return (run / "summary.json").is_file() and (run / PRIOR_WEIGHTS).is_file()


def train_prior(cfg, settings: ChoiConfig, out: str | Path, progress: bool | None = None,
                device: str | torch.device | None = None) -> dict:
    """Train the autoencoder on training-split patches of ``cfg.data`` (bands ``cfg.bands``).

    Writes the run folder ``out`` (see the module docstring); returns the summary. ``device``
    defaults to ``cfg.train.device`` (auto: CUDA when available).
    """
    import sys

    from hsicam.config import dump_yaml
    from hsicam.data.pipeline import build_datasets, make_loader
    from hsicam.engine.checkpoint import save_weights
    from hsicam.engine.train import MetricsLog
    from hsicam.io import atomic_open, write_json

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"{out}: prior folder exists and is not empty; choose another --out")
    bands = cfg.bands.to_bands()
    torch.manual_seed(settings.seed)
    if device is None:
        device = "cuda" if cfg.train.device == "auto" and torch.cuda.is_available() else cfg.train.device
        device = "cpu" if device == "auto" else device
    dev = torch.device(device)
    model = build_prior(len(bands), settings).to(dev)
    train_ds, val_ds = build_datasets(cfg.data, bands, 0)
    if len(train_ds) < settings.batch_size:
        raise InputError(f"data.patches_per_epoch={len(train_ds)} is smaller than baselines.choi.batch_size="
                         f"{settings.batch_size}")
    out.mkdir(parents=True, exist_ok=True)
    with atomic_open(out / "config.yaml") as fh:
        fh.write(dump_yaml(cfg))
    with atomic_open(out / PRIOR_SETTINGS) as fh:
        fh.write(yaml.safe_dump(dataclasses.asdict(settings), sort_keys=False))
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr)
    metrics = MetricsLog(out / "metrics.jsonl", True)
    g = torch.Generator().manual_seed(settings.seed)
    from tqdm.auto import tqdm

    use_bar = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=settings.train_steps, disable=not use_bar, unit="step", dynamic_ncols=True)
    t0, step, epoch, loss_sum, loss_n = time.perf_counter(), 0, 0, 0.0, 0
    model.train()
    while step < settings.train_steps:
        train_ds.set_epoch(epoch)
        loader = make_loader(train_ds, settings.batch_size, cfg.data.num_workers, shuffle=False, drop_last=True)
        for clean in loader:
            lr = settings.lr * 0.5 * (1 + math.cos(math.pi * step / settings.train_steps))
            for group in opt.param_groups:
                group["lr"] = lr
            sig = torch.rand(clean.shape[0], 1, 1, 1, generator=g) * settings.train_noise
            noisy = (clean + sig * torch.randn(clean.shape, generator=g)).to(dev)
            clean = clean.to(dev)
            loss = F.mse_loss(model(noisy), clean)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum, loss_n, step = loss_sum + loss.item(), loss_n + 1, step + 1
            bar.update(1)
            if step % 50 == 0 or step == settings.train_steps:
                elapsed = time.perf_counter() - t0
                metrics.write({"step": step, "train_mse": loss_sum / loss_n, "elapsed_s": elapsed})
                if not use_bar:
                    log.info("prior step %d/%d mse %.5f eta %.0fs", step, settings.train_steps, loss_sum / loss_n,
                             elapsed / step * (settings.train_steps - step))
                loss_sum, loss_n = 0.0, 0
            if step >= settings.train_steps:
                break
        epoch += 1
    bar.close()
    model.eval()
    summary = {"step": step, "final": True, "elapsed_s": time.perf_counter() - t0}
    if val_ds is not None:
        with torch.no_grad():
            se, n = 0.0, 0
            for a in range(0, len(val_ds), settings.batch_size):
                val = torch.stack([val_ds[i] for i in range(a, min(a + settings.batch_size, len(val_ds)))]).to(dev)
                se += float((model(val) - val).square().sum())
                n += val.numel()
            summary["val_psnr_autoencoder"] = -10 * math.log10(max(se / n, 1e-30))
    save_weights(out / PRIOR_WEIGHTS, model, bands, {"kind": "choi-spectral-prior"})
    metrics.write(summary)
    write_json(out / "summary.json", summary)
    log.info("spectral prior: %d steps in %.0f s%s -> %s", step, summary["elapsed_s"],
             f", validation autoencoder PSNR {summary['val_psnr_autoencoder']:.2f} dB" if "val_psnr_autoencoder" in summary else "",
             out)
    return summary


def load_prior_settings(run: str | Path) -> ChoiConfig:
    from hsicam.config import from_dict

    path = Path(run) / PRIOR_SETTINGS
    if not path.is_file():
        raise InputError(f"{run}: not a spectral-prior folder ({PRIOR_SETTINGS} is missing); "
                         f"train one with `hsicam baseline train-prior`")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: invalid YAML ({str(exc).splitlines()[0]})") from None
    return from_dict(ChoiConfig, data, "baselines.choi")


def load_prior(run: str | Path, bands: Bands, device: torch.device | str = "cpu") -> tuple[SpectralAutoencoder, ChoiConfig]:
    """The trained autoencoder of a prior folder (checked against ``bands``) and its settings."""
    from hsicam.engine.checkpoint import load_weights

    run = Path(run)
    if not run.is_dir():
        raise InputError(f"{run}: no such spectral-prior folder")
    settings = load_prior_settings(run)
    if not (run / PRIOR_WEIGHTS).is_file():
        raise InputError(f"{run}: the spectral prior has no trained weights ({PRIOR_WEIGHTS} is missing)")
    model = build_prior(len(bands), settings)
    load_weights(run / PRIOR_WEIGHTS, model, bands)
    model.requires_grad_(False)
    return model.to(device).eval(), settings


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
               x0: torch.Tensor | None = None, return_info: bool = False):
    """Choi et al. reconstruction: measurement (B, 1, H, W') → cube (B, C, H, W) [, SolverInfo].

    ``info.objective`` holds the objective of the z-iterate after each iteration (when
    ``return_info``); ``info.extra["primal_residual"]`` the ‖x − z‖ / ‖z‖ sequence.
    """
    check_measurement(camera, y)
    s = settings or ChoiConfig()
    t0 = time.perf_counter()
    info = SolverInfo()
    phi = phi_diagonal(camera, y)
    scale = float(phi.mean())  # m: Φ̃ = Φ/√m has mean diag Φ̃Φ̃ᵀ = 1
    phi_n = phi / scale
    prior_dtype = next(prior.parameters()).dtype
    run_prior = prior if prior_dtype == y.dtype else _CastPrior(prior, prior_dtype)
    if x0 is not None:
        x = x0.clone()
    elif s.init_iterations > 0:
        x = gap_tv(camera, y, s.init_iterations, 0.01)
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
            info.residual.append(relative_residual(camera, z, y))
        rho *= s.rho_growth
    info.iterations = s.iterations
    info.runtime_s = time.perf_counter() - t0
    info.extra = {"primal_residual": primal}
    log.info("Choi ADMM: %d iterations in %.1f s", s.iterations, info.runtime_s)
    return (z, info) if return_info else z


class _CastPrior(nn.Module):
    """Runs a prior in its own dtype on inputs of another dtype."""

    def __init__(self, prior: nn.Module, dtype: torch.dtype) -> None:
        super().__init__()
        self.prior, self.dtype = prior, dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.prior(x.to(self.dtype)).to(x.dtype)

