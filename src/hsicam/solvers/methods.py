"""The CASSI baselines as evaluation methods (:class:`hsicam.engine.methods.Method`).

    dd-cassi-gaptv   DD-CASSI + GAP-TV                 settings: baselines.gaptv
    dd-cassi-desci   DD-CASSI + DeSCI                  settings: baselines.desci (preset fast|full)
    dd-cassi-choi    DD-CASSI + Choi et al. ADMM       run: a spectral-prior folder (hsicam baseline train-prior);
                                                       ADMM settings: baselines.choi of the evaluation config when
                                                       it has that section, else the folder's prior.yaml
    dd-cassi-rdn     DD-CASSI + the paper's RDN        run: `hsicam train --set camera.kind=dd_cassi`

The DD-CASSI camera of the iterative methods is built from the evaluation config's band grid,
``camera.cassi`` and ``camera.sensor`` (whatever ``camera.kind`` says); ``dd-cassi-rdn`` uses its
run's own camera. CASSI has no blur, so the ground truth is the whole scene and every
reconstruction has the scene's size.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import torch

from hsicam.cameras.cassi import DDCASSICamera
from hsicam.config import Config, load_config
from hsicam.engine.methods import Method
from hsicam.errors import InputError
from hsicam.solvers.config import BaselinesConfig, baseline_settings

log = logging.getLogger(__name__)

BASELINES = ("dd-cassi-gaptv", "dd-cassi-desci", "dd-cassi-choi", "dd-cassi-rdn")

# spectral-prior settings per experiment scale (on top of the scale's preset)
PRIOR_SCALE_OVERRIDES: dict[str, tuple[str, ...]] = {
    "tiny": ("baselines.choi.train_steps=400", "baselines.choi.lr=0.003", "baselines.choi.features=16",
             "baselines.choi.latent=4", "baselines.choi.batch_size=4", "baselines.choi.iterations=10"),
    "quick": (),
    "paper": ("baselines.choi.train_steps=20000", "baselines.choi.features=64", "baselines.choi.latent=16",
              "baselines.choi.batch_size=16"),
}


@dataclass
class ConfigWithBaselines(Config):
    """The top-level config plus the ``baselines`` section (solver settings)."""

    baselines: BaselinesConfig = field(default_factory=BaselinesConfig)


def load_baseline_config(path=None, overrides=()) -> ConfigWithBaselines:
    """:func:`hsicam.config.load_config` that also accepts a ``baselines`` section."""
    return load_config(path, list(overrides), cls=ConfigWithBaselines)


def plain_config(cfg) -> Config:
    """The :class:`Config` part of a config (drops the ``baselines`` section, if Config lacks it)."""
    if type(cfg) is Config:
        return cfg
    return Config(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(Config)})


def dd_cassi_camera(cfg, device: torch.device | str = "cpu") -> DDCASSICamera:
    """The DD-CASSI camera of a config's bands, ``camera.cassi`` and ``camera.sensor``."""
    cam_cfg = dataclasses.replace(cfg.camera, kind="dd_cassi")
    return DDCASSICamera.from_config(dataclasses.replace(plain_config(cfg), camera=cam_cfg)).to(device)


def _identity(scene: torch.Tensor) -> torch.Tensor:
    return scene


def _camera_info(cam: DDCASSICamera) -> dict:
    return {"camera": cam.kind, "convention": cam.convention, "shifts_px": list(cam.shifts),
            "aperture": cam.aperture.source or f"random seed {cam.aperture.seed}, density {cam.aperture.density}"}


def build_baseline(name: str, cfg, run: str | Path | None = None, device: str | torch.device = "cpu") -> Method:
    """The baseline method ``name`` (see the module docstring)."""
    if name not in BASELINES:
        raise InputError(f"unknown baseline {name!r}; choose one of {', '.join(BASELINES)}")
    if name == "dd-cassi-rdn":
        return _learned_cassi(run, device)
    settings = baseline_settings(cfg)
    cam = dd_cassi_camera(cfg, device)
    if name == "dd-cassi-gaptv":
        from hsicam.solvers.gaptv import gap_tv

        s = settings.gaptv
        rec = functools.partial(gap_tv, cam, iterations=s.iterations, tv_weight=s.tv_weight,
                                tv_iterations=s.tv_iterations, accelerate=s.accelerate)
        return Method(name, cam, rec, _identity, {"solver": "gap-tv", **dataclasses.asdict(s), **_camera_info(cam)})
    if name == "dd-cassi-desci":
        from hsicam.solvers.desci import desci, desci_settings

        ds = desci_settings(settings.desci.preset, **settings.desci.overrides())
        rec = functools.partial(desci, cam, settings=ds)
        return Method(name, cam, rec, _identity,
                      {"solver": "desci", "preset": settings.desci.preset, **dataclasses.asdict(ds), **_camera_info(cam)})
    # dd-cassi-choi
    from hsicam.solvers.choi import admm_prior, load_prior

    if run is None:
        raise InputError("method dd-cassi-choi needs --run PRIOR (a spectral prior from `hsicam baseline train-prior`)")
    prior, trained = load_prior(run, cam.bands, device)
    admm = settings.choi if hasattr(cfg, "baselines") else trained
    admm = dataclasses.replace(admm, features=trained.features, latent=trained.latent)
    rec = functools.partial(admm_prior, cam, prior=prior, settings=admm)
    return Method(name, cam, rec, _identity, {"solver": "choi-admm", "run": str(run), **dataclasses.asdict(admm),
                                              **_camera_info(cam)})


def _learned_cassi(run, device) -> Method:
    from hsicam.engine.checkpoint import load_run

    if run is None:
        raise InputError("method dd-cassi-rdn needs --run RUN (trained with `hsicam train --set camera.kind=dd_cassi`)")
    cfg_path = Path(run) / "config.yaml"
    if cfg_path.is_file():
        kind = load_config(cfg_path).camera.kind
        if kind != "dd_cassi":
            raise InputError(f"{run}: method dd-cassi-rdn needs a run trained with camera.kind=dd_cassi, "
                             f"this one has camera.kind={kind}")
    run_cfg, model = load_run(run, device)
    return Method("dd-cassi-rdn", model.camera, model.reconstruct, model.target,
                  {"run": str(run), **_camera_info(model.camera)})


def ensure_choi_prior(run: str | Path, scale: str = "quick") -> Path:
    """A trained spectral prior in ``run`` for an experiment ``scale`` (trained when missing).

    An unfinished folder (interrupted training) is trained again from scratch.
    """
    from hsicam.solvers.choi import is_prior_run, train_prior

    run = Path(run)
    if is_prior_run(run):
        log.info("%s: spectral prior finished, reused", run)
        return run
    if scale not in PRIOR_SCALE_OVERRIDES:
        raise InputError(f"unknown scale {scale!r}; choose one of {', '.join(PRIOR_SCALE_OVERRIDES)}")
    if run.exists():
        log.warning("%s: unfinished spectral prior, training it again", run)
        shutil.rmtree(run)
    cfg = load_baseline_config(scale, PRIOR_SCALE_OVERRIDES[scale])
    log.info("%s: training the spectral prior (%s scale)", run, scale)
    train_prior(plain_config(cfg), cfg.baselines.choi, run)
    return run
