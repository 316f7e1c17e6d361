"""The Choi et al. spectral prior: training (a :class:`~hsicam.engine.tasks.PriorTask` run by the
one training loop, resumable) and its run folder.

Prior run folder (``hsicam baseline train-prior``)::

    RUN/config.yaml        the data/band config it was trained with (a plain hsicam config)
    RUN/prior.yaml         the ``baselines.choi`` settings (architecture, training, ADMM)
    RUN/prior.safetensors  autoencoder weights (bands in the metadata)
    RUN/metrics.jsonl      training loss
    RUN/checkpoints/ ...   checkpoints (an interrupted training resumes from them:
                           ``hsicam baseline train-prior --out RUN --resume``)
    RUN/summary.json       written last: the run is finished (a prior without it warns when loaded)
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import torch
import yaml

from hsicam.config import (ChoiConfig, Config, absolute_paths, from_dict, load_config, training_differences,
                           yaml_error_text)
from hsicam.engine.loop import FitOptions, fit
from hsicam.engine.tasks import PriorTask
from hsicam.errors import HsicamError, InputError
from hsicam.models.priors import SpectralAutoencoder, build_prior
from hsicam.runs.checkpoint import CheckpointManager, load_weights
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

PRIOR_WEIGHTS = "prior.safetensors"
PRIOR_SETTINGS = "prior.yaml"

# spectral-prior settings per experiment scale (on top of the scale's preset)
PRIOR_SCALE_OVERRIDES: dict[str, tuple[str, ...]] = {
    "tiny": ("baselines.choi.train_steps=400", "baselines.choi.lr=0.003", "baselines.choi.features=16",
             "baselines.choi.latent=16", "baselines.choi.batch_size=4", "baselines.choi.iterations=10",
             "baselines.choi.init_iterations=20"),
    # 32 features instead of the published 64: ~0.35 s a step on one CPU thread (64: ~1.4 s)
    "quick": ("baselines.choi.features=32",),
    "paper": ("baselines.choi.train_steps=20000", "baselines.choi.batch_size=16"),
}


#: Data settings a prior's training does not read (:meth:`hsicam.engine.tasks.PriorTask.datasets`):
#: a folder trained with other values is the same prior.
PRIOR_UNREAD_DATA_KEYS = ("data.augment_relight", "data.augment_relight_prob")


def is_prior_run(run: str | Path) -> bool:
    """A finished prior run folder (summary.json and weights present)."""
    run = Path(run)
    return (run / "summary.json").is_file() and (run / PRIOR_WEIGHTS).is_file()


#: What `hsicam baseline train-prior` says about a folder with nothing to resume.
PRIOR_RESTART_HINT = "train a new prior with `hsicam baseline train-prior --config CONFIG --out {run}` (without --resume)"


def prior_progress(run: str | Path, settings: ChoiConfig) -> tuple[int, int] | None:
    """(steps done, steps in all) of a prior folder whose training did not finish (no summary.json;
    its last checkpoint short of ``settings.train_steps``), else None: finished, or no checkpoint
    (weights from elsewhere record no training)."""
    run = Path(run)
    if (run / "summary.json").is_file():
        return None
    try:
        state = CheckpointManager(run, PRIOR_WEIGHTS).state()
    except InputError:
        return None
    if state is None:
        return None
    step = int(state.get("global_step", 0))
    return None if step >= settings.train_steps else (step, settings.train_steps)


def unfinished_prior(run: str | Path, settings: ChoiConfig) -> str | None:
    """A one-line note when the training of the prior folder ``run`` did not finish (crashed or
    killed: :func:`prior_progress`), naming the steps done and how to continue; else None."""
    progress = prior_progress(run, settings)
    if progress is None:
        return None
    return (f"{run}: its training did not finish: the last checkpoint is at step {progress[0]} of {progress[1]} and it "
            f"has no summary.json; the weights are of a partly trained spectral prior: continue it with "
            f"`hsicam baseline train-prior --resume --out {run}`")


def check_prior_out(out: Path) -> None:
    """Before any work, for a new prior (no --resume): ``out`` must be absent or empty; a folder
    that holds a prior is named with its state and what to do (resume an interrupted one)."""
    from hsicam.runs.folder import check_run_dir

    if (out / PRIOR_SETTINGS).is_file() and (out / "config.yaml").is_file():
        try:
            settings = load_prior_settings(out)
        except HsicamError:
            settings = None
        progress = None if settings is None else prior_progress(out, settings)
        if progress is not None:
            raise InputError(f"{out}: prior folder exists and is not empty: its training stopped at step {progress[0]} "
                             f"of {progress[1]}; continue it with `hsicam baseline train-prior --resume --out {out}`, "
                             "or choose another --out")
        if is_prior_run(out):
            raise InputError(f"{out}: prior folder exists and is not empty: it holds a trained spectral prior (use it: "
                             f"--run {out}); choose another --out")
        raise InputError(f"{out}: prior folder exists and is not empty: its training did not finish; continue it with "
                         f"`hsicam baseline train-prior --resume --out {out}`, or choose another --out")
    check_run_dir(out, False, "train-prior writes a new prior folder: choose another --out")


def resume_config(out: Path, overrides: tuple[str, ...] | list[str] = ()) -> tuple[Config, ChoiConfig]:
    """(config, prior settings) a resume of the prior folder ``out`` goes on with: its config.yaml
    and prior.yaml with the ``--set`` overrides (``baselines.choi.*`` apply to the folder's prior
    settings). Only ``baselines.choi.train_steps`` and the ADMM settings may differ from the
    folder's training: an :class:`InputError` names any other difference (another prior: train it
    into another --out)."""
    out = Path(out)
    have = load_prior_settings(out)
    pre = []
    sets_choi = any(str(o).strip().startswith("baselines.choi.") for o in overrides)
    if sets_choi and load_config(out / "config.yaml").baselines.choi is None:  # trained with the defaults
        pre.append(f"baselines.choi={json.dumps(dataclasses.asdict(have))}")  # the folder's settings, then the --set
    cfg = load_config(out / "config.yaml", [*pre, *overrides])
    settings = cfg.baselines.choi if cfg.baselines.choi is not None else have
    changed = [d for d in prior_differences(out, cfg, settings, limit=10**6)
               if not d.startswith("baselines.choi.train_steps:")]
    if changed:
        raise InputError(f"{out}: --resume continues the prior trained in it; {'; '.join(changed[:3])} would make "
                         "another prior: train it into another --out (only baselines.choi.train_steps may change)")
    return cfg, settings


def train_prior(cfg: Config, settings: ChoiConfig | None, out: str | Path, progress: bool | None = None,
                resume: bool = False) -> dict:
    """Train the autoencoder on training-split patches of ``cfg.data`` (bands ``cfg.bands``) into
    the folder ``out`` (see the module docstring); returns the summary (a resumed prior with nothing
    left to train: its summary with ``"already_finished": True``, nothing written). ``settings``
    None: the defaults. The device is ``cfg.train.device`` (auto: CUDA when available)."""
    from hsicam.runs.lock import RunLock

    out = Path(out)
    with RunLock(out) as lock:
        if resume and out.is_dir():
            lock.acquire()  # held from its first change (a summary.json removed) to the end (re-entrant in fit)
        return _train_prior(cfg, settings, out, progress, resume)


def _train_prior(cfg: Config, settings: ChoiConfig | None, out: Path, progress: bool | None, resume: bool) -> dict:
    from hsicam.runs.folder import check_run_dir

    settings = settings if settings is not None else ChoiConfig()
    if not resume:  # before any work
        check_prior_out(out)
    else:
        check_run_dir(out, True, restart_hint=PRIOR_RESTART_HINT)
    torch.manual_seed(settings.seed)
    task = PriorTask(cfg, settings)  # before the folder changes: a prior that cannot train here is refused
    if resume:
        state = CheckpointManager(out, PRIOR_WEIGHTS).state() if (out / "summary.json").is_file() else None
        if state is not None and int(state.get("global_step", 0)) < settings.train_steps:
            # a finished prior trained longer (more train_steps): its summary describes the shorter
            # training, and would mark it finished while it goes on; the new one is written at the end
            (out / "summary.json").unlink()
    summary = fit(task, FitOptions(task.loop_config(), cfg.data.num_workers, max_steps=settings.train_steps,
                                   progress=progress), out, resume)
    if summary.get("already_finished"):
        return summary
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
    out = [d for d in training_differences(absolute_paths(have_cfg), absolute_paths(cfg), limit=10**6)
           if d.split(".")[0] in ("bands", "data") and d.split(":")[0] not in PRIOR_UNREAD_DATA_KEYS]
    out += [f"baselines.choi.{k}: {getattr(have, k)!r} → {getattr(settings, k)!r}"
            for k in PRIOR_TRAINING_KEYS if getattr(have, k) != getattr(settings, k)]
    return sorted(out)[:limit]


def check_choi_prior(run: str | Path, scale: str = "quick") -> tuple[Config, ChoiConfig]:
    """The config and prior settings of an experiment ``scale``'s spectral prior; an :class:`InputError` naming the
    first differences when the folder ``run`` holds a prior trained otherwise (reads only: ``experiment compare``
    checks this before it changes its folder)."""
    run = Path(run)
    if scale not in PRIOR_SCALE_OVERRIDES:
        raise InputError(f"unknown scale {scale!r}; choose one of {', '.join(PRIOR_SCALE_OVERRIDES)}")
    cfg = load_config(scale, PRIOR_SCALE_OVERRIDES[scale])
    settings = cfg.baselines.choi if cfg.baselines.choi is not None else ChoiConfig()
    if (run / "config.yaml").is_file():
        changed = prior_differences(run, cfg, settings)
        if changed:
            raise InputError(f"{run} was trained with other settings ({'; '.join(changed)}): "
                             "delete it to train it again, or choose another output folder")
    return cfg, settings


def ensure_choi_prior(run: str | Path, scale: str = "quick") -> Path:
    """A trained spectral prior in ``run`` for an experiment ``scale`` (trained when missing; an
    interrupted training resumes; a finished one is reused). A folder trained with other bands,
    data or prior training settings is an :class:`InputError` naming the first differences, so a
    table never reports a prior other than the scale's."""
    run = Path(run)
    cfg, settings = check_choi_prior(run, scale)
    resume = (run / "config.yaml").is_file()
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
    text = path.read_text(encoding="utf-8")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(yaml_error_text(path, text, exc)) from None
    return from_dict(ChoiConfig, data, "baselines.choi")


def _misfit_hint(weights: Path, settings: ChoiConfig) -> str:
    """Why a prior's weights do not fit the autoencoder its ``prior.yaml`` describes, told from their shapes: the
    old 3 + 3 layer autoencoder of an earlier hsicam, or ``prior.yaml``'s sizes edited after its training."""
    from safetensors import safe_open

    from hsicam.models.priors import PRIOR_LAYERS

    try:
        with safe_open(str(weights), "pt") as f:
            convs = sorted(((int(k.split(".")[1]), f.get_slice(k).get_shape()) for k in f.keys()
                            if k.startswith("encoder.") and k.endswith(".weight")), key=lambda kv: kv[0])
    except Exception:  # noqa: BLE001 - shapes that cannot be read: the hint of the common case
        convs = []
    if len(convs) == PRIOR_LAYERS and all(len(shape) == 4 for _, shape in convs):
        trained = {"features": int(convs[0][1][0]), "latent": int(convs[-1][1][0])}
        edited = {k: v for k, v in trained.items() if getattr(settings, k) != v}
        if edited:
            said = ", ".join(f"{k}: {getattr(settings, k)}" for k in edited)
            were = ", ".join(f"{k}: {v}" for k, v in edited.items())
            return (f"its {PRIOR_SETTINGS} says {said}, but the weights were trained with {were} ({PRIOR_SETTINGS} "
                    f"edited after the training?); put back {were} in {PRIOR_SETTINGS}, or train it again with "
                    "`hsicam baseline train-prior`")
    return ("a prior trained by an earlier hsicam has the old 3 + 3 layer autoencoder; train it again with "
            "`hsicam baseline train-prior`")


def load_prior(run: str | Path, bands: Bands, device: torch.device | str = "cpu") -> tuple[SpectralAutoencoder, ChoiConfig]:
    """The trained autoencoder of a prior folder (checked against ``bands``) and its settings."""
    run = Path(run)
    if not run.is_dir():
        raise InputError(f"{run}: no such spectral-prior folder")
    settings = load_prior_settings(run)
    if not (run / PRIOR_WEIGHTS).is_file():
        raise InputError(f"{run}: the spectral prior has no trained weights ({PRIOR_WEIGHTS} is missing)")
    model = build_prior(settings, len(bands))  # refused when its weights do not fit the memory budget
    try:
        load_weights(run / PRIOR_WEIGHTS, model, bands)
    except InputError as exc:
        if "do not fit" not in str(exc) and "the model expects" not in str(exc):
            raise
        raise InputError(f"{exc}: {_misfit_hint(run / PRIOR_WEIGHTS, settings)}") from None
    model.requires_grad_(False)
    unfinished = unfinished_prior(run, settings)
    if unfinished:
        log.warning("%s", unfinished)
    return model.to(device).eval(), settings
