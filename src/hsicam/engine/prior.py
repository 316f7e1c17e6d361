"""The Choi et al. spectral prior: training (a :class:`~hsicam.engine.tasks.PriorTask` run by the
one training loop, resumable) and its run folder.

Prior run folder (``hsicam baseline train-prior``)::

    RUN/config.yaml        the data/band config it was trained with (a plain hsicam config)
    RUN/prior.yaml         the ``baselines.choi`` settings (architecture, training, ADMM)
    RUN/prior.safetensors  autoencoder weights (bands in the metadata)
    RUN/metrics.jsonl      training loss
    RUN/checkpoints/ ...   checkpoints (an interrupted training resumes from them)
    RUN/summary.json       written last: the run is finished
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
import yaml

from hsicam.config import ChoiConfig, Config, from_dict, load_config, training_differences
from hsicam.engine.loop import FitOptions, fit
from hsicam.engine.tasks import PriorTask
from hsicam.errors import InputError
from hsicam.models.priors import SpectralAutoencoder
from hsicam.runs.checkpoint import load_weights
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

PRIOR_WEIGHTS = "prior.safetensors"
PRIOR_SETTINGS = "prior.yaml"

# spectral-prior settings per experiment scale (on top of the scale's preset)
PRIOR_SCALE_OVERRIDES: dict[str, tuple[str, ...]] = {
    "tiny": ("baselines.choi.train_steps=400", "baselines.choi.lr=0.003", "baselines.choi.features=16",
             "baselines.choi.latent=4", "baselines.choi.batch_size=4", "baselines.choi.iterations=10"),
    "quick": (),
    "paper": ("baselines.choi.train_steps=20000", "baselines.choi.features=64", "baselines.choi.latent=16",
              "baselines.choi.batch_size=16"),
}


def is_prior_run(run: str | Path) -> bool:
    """A finished prior run folder (summary.json and weights present)."""
    run = Path(run)
    return (run / "summary.json").is_file() and (run / PRIOR_WEIGHTS).is_file()


def train_prior(cfg: Config, settings: ChoiConfig | None, out: str | Path, progress: bool | None = None,
                resume: bool = False) -> dict:
    """Train the autoencoder on training-split patches of ``cfg.data`` (bands ``cfg.bands``) into
    the folder ``out`` (see the module docstring); returns the summary. ``settings`` None: the
    defaults. The device is ``cfg.train.device`` (auto: CUDA when available)."""
    settings = settings if settings is not None else ChoiConfig()
    if not resume:  # before any work; this command has no --resume/--restart to offer
        from hsicam.runs.folder import check_run_dir

        check_run_dir(Path(out), False, "train-prior writes a new prior folder: choose another --out")
    torch.manual_seed(settings.seed)
    task = PriorTask(cfg, settings)
    summary = fit(task, FitOptions(task.loop_config(), cfg.data.num_workers, max_steps=settings.train_steps,
                                   progress=progress), out, resume)
    log.info("spectral prior: %d steps in %.0f s%s -> %s", summary["step"], summary["elapsed_s"],
             f", validation autoencoder PSNR {summary['val_psnr_autoencoder']:.2f} dB"
             if "val_psnr_autoencoder" in summary else "", out)
    return summary


#: ``baselines.choi`` settings that change the trained autoencoder (the ADMM ones apply at evaluation)
PRIOR_TRAINING_KEYS = ("features", "latent", "train_steps", "batch_size", "lr", "train_noise", "seed")


def prior_differences(run: str | Path, cfg: Config, settings: ChoiConfig, limit: int = 3) -> list[str]:
    """The first ``limit`` settings (``"key: have → want"``) in which the prior folder ``run`` was
    trained otherwise than ``settings`` on the bands and data of ``cfg``. Empty: the same prior."""
    run = Path(run)
    have_cfg, have = load_config(run / "config.yaml"), load_prior_settings(run)
    out = [d for d in training_differences(have_cfg, cfg, limit=10**6) if d.split(".")[0] in ("bands", "data")]
    out += [f"baselines.choi.{k}: {getattr(have, k)!r} → {getattr(settings, k)!r}"
            for k in PRIOR_TRAINING_KEYS if getattr(have, k) != getattr(settings, k)]
    return sorted(out)[:limit]


def ensure_choi_prior(run: str | Path, scale: str = "quick") -> Path:
    """A trained spectral prior in ``run`` for an experiment ``scale`` (trained when missing; an
    interrupted training resumes; a finished one is reused). A folder trained with other bands,
    data or prior training settings is an :class:`InputError` naming the first differences, so a
    table never reports a prior other than the scale's."""
    run = Path(run)
    if scale not in PRIOR_SCALE_OVERRIDES:
        raise InputError(f"unknown scale {scale!r}; choose one of {', '.join(PRIOR_SCALE_OVERRIDES)}")
    cfg = load_config(scale, PRIOR_SCALE_OVERRIDES[scale])
    settings = cfg.baselines.choi if cfg.baselines.choi is not None else ChoiConfig()
    resume = (run / "config.yaml").is_file()
    if resume:
        changed = prior_differences(run, cfg, settings)
        if changed:
            raise InputError(f"{run} was trained with other settings ({'; '.join(changed)}): "
                             "delete it to train it again, or choose another output folder")
    if is_prior_run(run):
        log.info("%s: spectral prior finished, reused", run)
        return run
    log.info("%s: %s the spectral prior (%s scale)", run, "resuming" if resume else "training", scale)
    train_prior(cfg, settings, run, resume=resume)
    return run


def load_prior_settings(run: str | Path) -> ChoiConfig:
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
    run = Path(run)
    if not run.is_dir():
        raise InputError(f"{run}: no such spectral-prior folder")
    settings = load_prior_settings(run)
    if not (run / PRIOR_WEIGHTS).is_file():
        raise InputError(f"{run}: the spectral prior has no trained weights ({PRIOR_WEIGHTS} is missing)")
    model = SpectralAutoencoder(len(bands), settings.features, settings.latent)
    load_weights(run / PRIOR_WEIGHTS, model, bands)
    model.requires_grad_(False)
    return model.to(device).eval(), settings
