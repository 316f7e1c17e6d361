"""The run folder: its layout, loading a trained run, the metrics log, starting or resuming.

Layout (written by :func:`hsicam.engine.loop.fit` and its tasks)::

    RUN/config.yaml            resolved config
    RUN/metrics.jsonl          one JSON object per log/eval event
    RUN/model.safetensors      weights (network + optics) of the best (else last) checkpoint
    RUN/checkpoints/step-N/    model.safetensors, optimizer.safetensors, state.json
    RUN/checkpoints.json       the manifest naming last and best (see :mod:`hsicam.runs.checkpoint`)
    RUN/measured_psf.safetensors  (fine-tuned runs) the measured PSFs the run images with
    RUN/data.json              (runs on a data.root folder) the scenes, their sizes and times, the split
    RUN/camera_files.json      (cameras built from files: material tables, a coded aperture) their SHA-256

A run is rebuilt from its config through the registries (camera kind, network kind), so
:func:`load_run` works for every camera and network. ``load_run("pretrained:NAME")`` loads a
camera shipped with the package (:mod:`hsicam.runs.pretrained`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsicam.config import CAMERA_FILES_RECORD
from hsicam.errors import HsicamError, InputError
from hsicam.io import (OS_ERROR_HINTS, atomic_open, cleanup_stale_temporaries, held_elsewhere, held_here, is_temporary,
                       json_text, lock_holder_text, nan_for_null, output_lock_path, remove_if_stale, restore_set_aside)
from hsicam.runs.checkpoint import LEGACY_POINTERS, MANIFEST, CheckpointManager, load_weights, root_weights_path
from hsicam.runs.linear_step import LINEAR_STEP_FILE, load_linear_step, stale_reason
from hsicam.runs.lock import LOCK_FILE
from hsicam.runs.measured_psf import MEASURED_PSF_FILE, MeasuredPSF, load_measured_psf
from hsicam.runs.pretrained import resolve_run

log = logging.getLogger(__name__)


def with_measured_psf(model, measured: MeasuredPSF):
    """A :class:`~hsicam.models.CameraSystem` imaging with ``measured`` PSFs (same network, same CFA)."""
    from hsicam.cameras.measured import FixedPSFCamera

    cam = model.camera
    if not measured.bands.matches(cam.bands):
        raise InputError(f"measured PSFs are on {measured.bands!r}, the camera on {cam.bands!r}")
    if measured.psf.shape != (len(cam.bands), cam.kernel_px, cam.kernel_px):
        raise InputError(f"measured PSFs are {'×'.join(map(str, measured.psf.shape))} (bands × px × px), the camera's "
                         f"kernels {len(cam.bands)}×{cam.kernel_px}×{cam.kernel_px}")
    return model.with_camera(FixedPSFCamera.from_camera(cam, torch.from_numpy(measured.psf)))


#: What to do about a run whose config.yaml holds no settings (training always writes it in full).
EMPTY_RUN_CONFIG = ("the run's config.yaml is damaged (training writes it in full, and the weights need the camera "
                    "and network it describes): restore it from a copy of the run")


_BAND_RULES_WARNED: set[str] = set()


def _warn_of_older_band_samples(run_dir: Path, cfg) -> None:
    """Warn (once per run and process) when a run trained (``cfg``: its config.yaml's) with ``camera.psf.band_samples``
    > 1 began before the band rules of
    session 74 (its first session record names no ``band_rules``): it trained with PSFs averaged over ±FWHM/2 slices,
    and this hsicam images it with Gauss–Hermite wavelengths of each band's Gaussian, 2-3 % other PSFs (the tiny
    preset at M = 3: its kernel 21 → 23 px; session 74's second review). A shipped camera or a run without
    metrics.jsonl says nothing (none used M > 1)."""
    psf = getattr(getattr(cfg.camera, "psf", None), "band_samples", 1)
    if psf <= 1 or str(run_dir) in _BAND_RULES_WARNED:
        return
    first = starting_session(run_records(run_dir))
    if first is not None and "band_rules" not in first:
        _BAND_RULES_WARNED.add(str(run_dir))
        log.warning("%s: trained with camera.psf.band_samples %d over slices of ±FWHM/2 (an hsicam before session 74); "
                    "this one averages each band over its whole Gaussian (Gauss–Hermite wavelengths), so the camera it "
                    "images with differs from the trained one by a few %% of each PSF (docs/optics.md); train it again "
                    "to score it as it is imaged now", run_dir, psf)


def _check_same_band_widths(run_dir: Path, own, cfg, overrides: tuple[str, ...]) -> None:
    """InputError when the ``--set`` keys ``overrides`` give the run's bands (same centres) other widths than its
    config.yaml's: the FWHM sets how scenes are resampled onto the bands (and with ``camera.psf.band_samples`` the
    PSFs), which the run was trained with; ``simulate --set bands.fwhm_nm=40`` was taken, its sensor image 2.9 % off
    the run's own (session 74's spectral audit), where ``evaluate`` refused it."""
    a, b = own.bands.to_bands(), cfg.bands.to_bands()
    if len(a) == len(b) and a.matches(b) and not np.allclose(a.fwhm_nm, b.fwhm_nm, rtol=0, atol=1e-6):
        keys = [o for o in overrides if str(o).split("=", 1)[0].strip().startswith("bands.")] or list(overrides)
        raise InputError(f"--set {' '.join(map(str, keys))}: changes the FWHM of the bands {run_dir} was trained with "
                         f"({a.fwhm_nm.min():g}-{a.fwhm_nm.max():g} nm to {b.fwhm_nm.min():g}-{b.fwhm_nm.max():g} nm); a "
                         "trained run's camera, bands and network are fixed by its training (another design: hsicam "
                         "train)")


def load_run(run_dir: str | Path, device: torch.device | str = "cpu", overrides: tuple[str, ...] = (),
             linear_step: bool = True):
    """(config, CameraSystem) of a trained run, weights from ``RUN/model.safetensors``; a run
    fine-tuned on measured PSFs (``RUN/measured_psf.safetensors``) images with those PSFs.
    ``run_dir`` may be ``pretrained:NAME``, a camera shipped with the package.

    ``device``: cpu, cuda, cuda:N or mps, one this machine has (:func:`hsicam.devices.device_problem`,
    as ``--device``). ``linear_step=False``: without the linear step's filters (fine-tuning and the
    refit itself, which make their own: no stale-filter check). Raises :class:`InputError` for another device, a missing folder,
    missing/corrupt weights, another band grid, or a file its camera is built from gone or changed since training
    (:func:`hsicam.runs.camera_files.check_camera_files`).
    """
    from hsicam.config import load_config, override_keys
    from hsicam.devices import device_problem
    from hsicam.models import CameraSystem
    from hsicam.runs.camera_files import check_camera_files

    problem = device_problem(str(device))
    if problem is not None:
        raise InputError(f"load_run: device {str(device)!r}: {problem}")
    run_dir = resolve_run(run_dir)
    check_is_run(run_dir)
    cfg_path = run_dir / "config.yaml"
    cfg = load_config(cfg_path, overrides, empty=EMPTY_RUN_CONFIG)
    own = load_config(cfg_path, (), empty=EMPTY_RUN_CONFIG) if overrides else cfg  # what it trained with
    if overrides:  # the weights file records the band centres only: a --set of the bands' widths loaded silently
        _check_same_band_widths(run_dir, own, cfg, overrides)
    # the files its camera is built from, as it was trained: one edited since changed the camera silently
    check_camera_files(run_dir, cfg, override_keys(overrides))
    weights = run_dir / "model.safetensors"
    if not weights.is_file():
        damaged = damaged_weights_message(run_dir)  # a kept checkpoint to read them from, but damaged
        raise InputError(f"{run_dir}: the run has no readable weights: {damaged}" if damaged else
                         no_weights_message(run_dir))
    model = CameraSystem.from_config(cfg)
    try:
        load_weights(kept := root_weights_path(run_dir), model, cfg.bands.to_bands())
    except InputError as exc:
        if not overrides or not _weights_load_with(run_dir, cfg_path):
            raise  # a damaged file (weights, manifest) fails whatever the --set keys are: say that, not them
        # the weights fitted the run's own config: the --set keys changed what it trained; named are those that do
        # alone (a command adds its own keys, e.g. simulate's camera.boundary, which leave the weights as they are)
        culprits = [o for o in overrides if not _weights_load_with(run_dir, cfg_path, (o,))] or list(overrides)
        raise InputError(f"--set {' '.join(map(str, culprits))}: changes what {run_dir} was trained with, so its "
                         f"weights do not load ({exc}); a trained run's camera, bands and network are fixed by its "
                         "training (another design: hsicam train)") from None
    check_finite_weights(model, kept)
    _warn_of_older_band_samples(run_dir, own)
    if linear_step and (run_dir / LINEAR_STEP_FILE).is_file():  # the linear step's filters (fitted after training)
        uses = cfg.model.consistency.kind == "linear" and cfg.model.consistency.iterations > 0
        try:
            model.linear_step = load_linear_step(run_dir / LINEAR_STEP_FILE, len(model.bands),
                                                 int(getattr(model.camera, "code_period", 1)))
        except InputError as exc:
            if uses:  # a resume refits a damaged file (runs.linear_step.stale_reason), where there is one to resume
                raise InputError(f"{exc}; {_refit_damaged_step_advice(run_dir)}") from None
            # a run reconstructed without the step (e.g. --set model.consistency.kind=landweber) does not need it
            log.warning("%s; not used (model.consistency.kind %s)", exc, cfg.model.consistency.kind)
        if model.linear_step is not None:
            problem = linear_step_problem(run_dir, cfg.model.consistency)
            if problem:
                raise InputError(problem)
            if stale_reason(run_dir / LINEAR_STEP_FILE, kept):
                model.linear_step = None  # not used (e.g. kind landweber): never the step of other weights
    if (run_dir / MEASURED_PSF_FILE).is_file():  # a run fine-tuned on measured PSFs images with them
        measured = load_measured_psf(run_dir / MEASURED_PSF_FILE)
        try:
            model = with_measured_psf(model, measured)
        except InputError as exc:  # another camera's PSFs (a file copied in): name the file, not only the grids
            raise InputError(f"{run_dir / MEASURED_PSF_FILE}: {exc}: the file is not this run's; copy the run folder "
                             "again from its source, or fine-tune it again (hsicam finetune)") from None
    unfinished = unfinished_training(run_dir, cfg)
    if unfinished:
        log.warning("%s", unfinished)
    if linear_step and not (run_dir / LINEAR_STEP_FILE).is_file():  # said, naming the run, if the step is used
        from hsicam.runs.pretrained import is_pretrained_path

        how = ("a shipped camera's files are fixed: install it again" if is_pretrained_path(run_dir) else
               f"its training did not finish, and the step is fitted when it ends: "
               f"{refit_command(run_dir)}" if unfinished else
               f"fit it: {refit_command(run_dir, ('model.consistency.kind=linear', 'model.consistency.iterations=1'))}")
        model.linear_step_missing = (f"{run_dir}: model.consistency.kind=linear needs the run's {LINEAR_STEP_FILE}, "
                                     f"which it does not have: {how}; or go without it: reconstruct "
                                     "--consistency-steps 0 (the network alone), evaluate --set "
                                     "model.consistency.kind=landweber")
    return cfg, model.to(device).eval()


def _weights_load_with(run_dir: Path, cfg_path: Path, overrides: tuple[str, ...] = ()) -> bool:
    """Whether the run's weights load into the model of its own config.yaml (with ``overrides`` only: by default no
    ``--set``)."""
    from hsicam.config import load_config
    from hsicam.models import CameraSystem

    try:
        cfg = load_config(cfg_path, overrides, empty=EMPTY_RUN_CONFIG)
        load_weights(root_weights_path(run_dir), CameraSystem.from_config(cfg), cfg.bands.to_bands())
    except HsicamError:
        return False
    return True


def check_finite_weights(model: torch.nn.Module, weights: str | Path) -> None:
    """One-line :class:`InputError` naming ``weights`` (the file they came from) and the first tensor
    of ``model`` that holds NaN or Inf: no reader (reconstruct, psf, evaluate, export) works through
    weights of a diverged training (a reconstruction would only blame its output)."""
    for name, t in model.state_dict().items():
        if t.is_floating_point() and not bool(t.isfinite().all()):
            bad = int((~t.isfinite()).sum())
            raise InputError(f"{weights}: {bad} NaN/Inf value(s) in {name}: the run's weights are not finite "
                             "(training diverged?); nothing was done with them")


def not_a_run_message(path: str | Path) -> str | None:
    """The one line for ``path`` given as a run folder when it is none (no ``config.yaml``), else None.
    A demo's folder (its run in ``run/``) or an experiment's (``runs/NAME``) is named with the run(s)
    it holds, so the fix is in the message."""
    path = Path(path)
    if (path / "config.yaml").is_file():
        return None
    if path.is_file():
        return f"{path}: a file, not a run folder (give the folder that holds config.yaml and model.safetensors)"
    if not path.is_dir():
        return f"{path}: no such run folder"
    inner = [p for p in (path / "run", *sorted((path / "runs").glob("*"))) if (p / "config.yaml").is_file()]
    if inner:
        names = ", ".join(str(p) for p in inner[:4]) + (", …" if len(inner) > 4 else "")
        return (f"{path}: not a run folder (config.yaml is missing); it holds the run folder{'s' if len(inner) > 1 else ''} "
                f"{names}: give {'that' if len(inner) == 1 else 'one'} as the run")
    return f"{path}: not a run folder (config.yaml is missing)"


def check_is_run(path: str | Path) -> None:
    """:class:`InputError` (:func:`not_a_run_message`) unless ``path`` holds a run's ``config.yaml``."""
    message = not_a_run_message(path)
    if message is not None:
        raise InputError(message)


#: What a run without checkpoints (a copied camera) is told when its linear step's filters must be refitted.
NO_CHECKPOINT_TO_REFIT = ("the run has no checkpoint to refit the filters from: copy the run folder again from its "
                          "source, or train it again")


def linear_step_problem(run_dir: Path, consistency) -> str | None:
    """Why ``consistency`` (a :class:`~hsicam.config.ConsistencyConfig`: the run's own, or an
    evaluation's) cannot use the run's ``linear_step.safetensors``: fitted through other weights,
    or of another width than ``window_px`` (the step would use the file's). The message names the
    command that refits it with those settings. None when the step is not asked for, the file is
    missing (the step says so when it runs), or it fits."""
    path = run_dir / LINEAR_STEP_FILE
    if consistency.kind != "linear" or consistency.iterations <= 0 or not path.is_file():
        return None
    why = stale_reason(path, root_weights_path(run_dir), consistency.window_px)
    if why is None:
        return None
    try:
        from hsicam.config import load_config

        own = load_config(run_dir / "config.yaml").model.consistency
    except HsicamError:
        own = None
    from hsicam.runs.pretrained import is_pretrained_path

    if is_pretrained_path(run_dir):  # read-only, and a copy has no checkpoint to resume
        return f"{why}; a shipped camera's filters are fixed: evaluate it with its own model.consistency settings"
    from hsicam.runs.checkpoint import CheckpointManager

    if CheckpointManager(run_dir).manifest() is None and stale_reason(path, root_weights_path(run_dir)):
        return f"{why}; {NO_CHECKPOINT_TO_REFIT}"
    sets = [f"model.consistency.{k}={getattr(consistency, k)}" for k in ("kind", "iterations", "window_px")
            if own is None or getattr(own, k) != getattr(consistency, k)]
    return f"{why}; refit it: {refit_command(run_dir, sets)}"


def _refit_damaged_step_advice(run_dir: Path) -> str:
    """How to replace a run's damaged linear-step file: refit it by resuming the run (or its fine-tuning); a copied
    camera (no checkpoint) or a shipped one has nothing to resume ("hsicam train --out RUN --resume" then failed with
    "no checkpoint to resume")."""
    from hsicam.runs.checkpoint import CheckpointManager
    from hsicam.runs.pretrained import is_pretrained_path

    if is_pretrained_path(run_dir):
        return "a shipped camera's files are fixed: install hsicam again"
    if CheckpointManager(run_dir).manifest() is None:
        return NO_CHECKPOINT_TO_REFIT
    return f"refit it: {refit_command(run_dir)}"


def refit_command(run_dir: Path, sets: list[str] | tuple[str, ...] = ()) -> str:
    """The command that brings a finished run's derived files (its linear step) up to date, with
    ``sets`` (``key=value``): resuming its training, or its fine-tuning (with the source run and
    PSFs its finetune.json names)."""
    extra = "".join(f" --set {s}" for s in sets)
    if not (run_dir / MEASURED_PSF_FILE).is_file():
        return f"hsicam train --out {run_dir} --resume{extra}"
    try:
        info = json.loads((run_dir / "finetune.json").read_text(encoding="utf-8"))
        source, psfs = info["source_run"], info["psf_dir"]
    except (OSError, ValueError, KeyError, TypeError):
        source, psfs = "SOURCE_RUN", "PSF_DIR"
    return f"hsicam finetune --run {source} --psf-dir {psfs} --out {run_dir} --resume{extra}"


def holds_prior(run_dir: Path) -> bool:
    """True for a spectral-prior folder (``hsicam baseline train-prior``: prior.yaml or its weights),
    finished or not."""
    return any((Path(run_dir) / name).is_file() for name in ("prior.yaml", "prior.safetensors"))


def no_weights_message(run_dir: Path) -> str:
    """Why :func:`load_run` cannot load ``run_dir`` (no model.safetensors): a spectral prior (``hsicam
    baseline train-prior``: prior.yaml / prior.safetensors) is told apart from a run with no weights."""
    if holds_prior(run_dir):
        return (f"{run_dir}: a spectral prior (hsicam baseline train-prior), not a camera run: use it with `hsicam "
                f"evaluate --method dd-cassi-choi --run {run_dir} --out DIR`; this command needs a camera run "
                "(hsicam train, or --run pretrained:NAME)")
    text = f"{run_dir}: the run has no trained weights (model.safetensors is missing)"
    src = CheckpointManager(run_dir).root_source()
    if src is not None and src[0].is_file() and not (run_dir / MEASURED_PSF_FILE).is_file():
        # the kept checkpoint is there (intact: damaged_weights_message is asked first): a resume copies it back
        # (engine.linear_step's refresh; a stopped run trains on first). A fine-tuned run's resume does not.
        text += f"; its kept checkpoint {src[0]} holds them: {refit_command(run_dir)} restores them"
    return text


def damaged_weights_message(run_dir: Path) -> str | None:
    """Why the weights a run keeps cannot be read (:func:`~hsicam.runs.checkpoint.root_weights_path`'s refusal: its
    kept checkpoint, ``train.keep_weights``, damaged and the root weights not those the manifest records), with the
    way out: the run's last checkpoint when it is another one and intact (:func:`refit_command` with
    ``train.keep_weights=last``), else copying the run again; None when they can be read."""
    from hsicam.runs.checkpoint import RECOPY_HINT, kept_entry
    from hsicam.io import file_sha256

    src = CheckpointManager(run_dir).root_source()
    if src is None or (src[0].is_file() and src[1] in (None, file_sha256(src[0]))):
        # no checkpoint, or the kept one intact: nothing damaged to name (load_run, which asks only when the root
        # is missing, then says so and how a resume restores it: no_weights_message)
        return None
    try:
        root_weights_path(run_dir)
        return None
    except InputError as exc:
        text = str(exc)
    man = CheckpointManager(run_dir).manifest()
    tag, entry = kept_entry(man)
    last = man["last"]
    weights = run_dir / last["dir"] / "model.safetensors"
    if tag != "last" and last["dir"] != entry["dir"] and weights.is_file() and \
            last.get("weights_sha256") in (None, file_sha256(weights)):
        way = (f"keep the last checkpoint's weights (step {last.get('step')}, intact) instead: "
               f"{refit_command(run_dir, ('train.keep_weights=last',))}; or {RECOPY_HINT}")
        text = text[: -len(RECOPY_HINT)] + way if text.endswith(RECOPY_HINT) else f"{text}; {way}"
    return text


def unfinished_training(run_dir: Path, cfg) -> str | None:
    """A one-line note when the training of ``run_dir`` did not finish (crashed or killed), else None.

    Finished: ``metrics.jsonl`` ends with the ``final`` record of the last checkpoint's step, which
    the training loop writes last. A folder without checkpoints (a shipped camera, weights written
    by hand) records no training: None; nor does one killed after its last checkpoint, which holds
    all its epochs (only the summary record is missing). The note names the last checkpoint's step
    and epoch out of the run's totals: the epochs of its config and the steps the loop planned (saved
    with each checkpoint; older checkpoints name the epochs only)."""
    state = CheckpointManager(run_dir).state()
    if state is None:
        return None
    step, epoch = int(state.get("global_step", 0)), int(state.get("epoch", 0))
    records = MetricsLog(run_dir / "metrics.jsonl", enabled=False).read()
    if records and records[-1].get("final") and records[-1].get("step") == step:
        return None
    epochs, total = cfg.train.epochs, int(state.get("total_steps") or 0)
    if epoch >= epochs or (total and step >= total):
        return None
    of_total = f" of {total}" if total else ""
    if held_elsewhere(run_dir / LOCK_FILE):  # not stopped: "continue it with --resume" would be refused
        return (f"{run_dir}: {lock_holder_text(run_dir / LOCK_FILE, 'train')}: the last checkpoint is at step "
                f"{step}{of_total} ({epoch} of {epochs} epochs done); the weights read are of a partly trained network, "
                "as of that checkpoint")
    again = f"continue it with `hsicam train --resume --out {run_dir}`"
    if (run_dir / MEASURED_PSF_FILE).is_file():
        source, psf_dir = finetune_source(run_dir)
        again = (f"continue it with `hsicam finetune --resume --run {source or 'RUN'} --psf-dir {psf_dir or 'DIR'} "
                 f"--out {run_dir}`")
    return (f"{run_dir}: its training did not finish: the last checkpoint is at step {step}{of_total} ({epoch} of "
            f"{epochs} epochs done) and metrics.jsonl has no final record; the weights are of a partly trained "
            f"network: {again}")


RESTART_HINT = "start it again with `hsicam train --restart --config CONFIG --out {run}`"
#: What to do with a new run's folder that is not empty, in `hsicam train` (the default of
#: :func:`check_run_dir`); a command without --resume/--restart passes its own.
TRAIN_NOT_EMPTY_HINT = "use --resume, --restart (a run without a checkpoint) or another --out"


#: Root weights files of the run folders the training loop writes (camera runs, spectral priors).
WEIGHTS_FILES = ("model.safetensors", "prior.safetensors")


def weights_without_checkpoint(run_dir: Path) -> str | None:
    """The name of the weights file of a folder that holds trained weights but no checkpoint (a
    camera copied by ``hsicam pretrained copy`` or shipped, weights put there by hand), else None.
    A resume has nothing to continue there: it would train from a random start over the weights."""
    run_dir = Path(run_dir)
    if CheckpointManager(run_dir).state() is not None:
        return None
    return next((name for name in WEIGHTS_FILES if (run_dir / name).is_file()), None)


def check_run_dir(run_dir: Path, resume: bool, not_empty_hint: str = TRAIN_NOT_EMPTY_HINT,
                  restart_hint: str = RESTART_HINT) -> None:
    """A run folder must hold a run to resume, or (a new run) be absent or empty; the error for a
    new run's folder that is not empty ends in ``not_empty_hint`` (what the command can do instead),
    the error for a folder with nothing to resume in ``restart_hint`` (``{run}``: the folder).

    A folder with trained weights but no checkpoint (a copied camera) is never resumed: the resume
    would start from random weights and write over them. Hidden temporaries a killed process left
    (in the folder, or the folder's own temporary sibling) do not count: they are removed. Creates
    nothing."""
    run_dir = Path(run_dir)
    remove_run_temporaries(run_dir)
    if resume:
        if not (run_dir / "config.yaml").is_file():
            foreign = foreign_entries(run_dir) if run_dir.is_dir() else []
            if foreign:  # a user's own folder: --restart would refuse it too
                shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
                raise InputError(f"{run_dir}: nothing to resume: not a run folder (no config.yaml, and it holds "
                                 f"{shown}, which no training writes); resume the folder the run was started "
                                 "in (--out RUN --resume), or start a new run with another --out")
            if run_dir.is_dir() and not any(p for p in run_dir.iterdir() if not p.name.startswith(".")):
                why = "an empty folder: no training was started in it"
            else:
                why = "no such folder" if not run_dir.exists() else "no config.yaml: it was interrupted before it started"
            raise InputError(f"{run_dir}: nothing to resume ({why}); " + restart_hint.format(run=run_dir))
        weights = weights_without_checkpoint(run_dir)
        if weights == "model.safetensors":
            raise InputError(f"{run_dir}: holds trained weights ({weights}) but no checkpoint to resume (a copied or "
                             "shipped camera, e.g. from `hsicam pretrained copy`); training cannot go on from weights "
                             f"alone and nothing was changed: {_copied_camera_hint(run_dir)}")
        if weights is not None:
            raise InputError(f"{run_dir}: holds trained weights ({weights}) but no checkpoint to resume; training "
                             "cannot go on from weights alone and nothing was changed: train a new one with another "
                             "--out")
        return
    if run_dir.exists() and not run_dir.is_dir():
        raise InputError(f"{run_dir}: exists and is not a folder; choose another --out")
    if run_dir.exists() and any(run_dir.iterdir()):
        foreign = foreign_entries(run_dir)
        if foreign and not (run_dir / "config.yaml").is_file():  # no run to resume, nothing --restart may wipe
            remedy = ("nothing there is resumed or wiped: choose another --out" if not_empty_hint == TRAIN_NOT_EMPTY_HINT
                      else not_empty_hint)
            raise InputError(f"{run_dir}: run folder exists and is not empty: it holds other files than a run's "
                             f"({', '.join(foreign[:3])}{', …' if len(foreign) > 3 else ''}); {remedy}")
        raise InputError(f"{run_dir}: run folder exists and is not empty; {not_empty_hint}")


def _copied_camera_hint(run_dir: Path) -> str:
    """What to do instead of resuming the copied camera ``run_dir`` (weights, no checkpoint), by its
    camera kind: a DOE camera can also be adapted to measured PSFs (``hsicam finetune``); a CASSI camera
    cannot (finetune needs a DOE camera), so it is offered a new run of its own settings instead; a
    camera whose config.yaml does not load, a new run alone."""
    from hsicam.config import load_config

    try:
        kind = load_config(run_dir / "config.yaml").camera.kind
    except (HsicamError, OSError, ValueError):  # a config.yaml that no longer loads: no command built on it
        return "train a new run with another --out"
    if kind == "doe":
        return ("train a new run with another --out, or adapt this camera to measured PSFs with "
                f"`hsicam finetune --run {run_dir} --psf-dir DIR --out NEW`")
    return (f"train a new run with another --out (`hsicam train --config {run_dir / 'config.yaml'} --out NEW`: the same "
            f"settings from a random start), or use this camera as it is with --run {run_dir}")


def check_train_can_resume(run_dir: Path) -> None:
    """InputError for a folder that ``hsicam train --resume`` must not continue although it holds
    checkpoints: a run made by ``hsicam finetune`` (its optics are frozen to measured PSFs, its
    optimizer has other parameter groups) and a spectral prior (``hsicam baseline train-prior``).
    Reads only; the message names the command that can continue or redo it."""
    run_dir = Path(run_dir)
    if any((run_dir / name).is_file() for name in (MEASURED_PSF_FILE, "measured_psf.json", "finetune.json")):
        source, psf_dir = finetune_source(run_dir)
        raise InputError(f"{run_dir}: a fine-tuned run (made by `hsicam finetune`{f' from {source}' if source else ''}"
                         "): `hsicam train` cannot continue it (its optics are frozen to the measured PSFs); nothing "
                         f"was changed: continue it with hsicam finetune --resume --run {source or 'ORIGINAL'} "
                         f"--psf-dir {psf_dir or 'DIR'} --out {run_dir} (--epochs N for more epochs)")
    if holds_prior(run_dir):
        raise InputError(f"{run_dir}: holds a spectral prior (hsicam baseline train-prior), not a camera run; continue "
                         f"it with `hsicam baseline train-prior --resume --out {run_dir}`")


def finetune_source(run_dir: Path) -> tuple[str | None, str | None]:
    """(the run, the measured-PSF folder) a fine-tuned run was made from: from its finetune.json
    (written when the fine-tuning ends), else the run from its weights' metadata; None when unknown."""
    try:
        info = json.loads((Path(run_dir) / "finetune.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        info = {}
    info = info if isinstance(info, dict) else {}
    source, psf_dir = info.get("source_run"), info.get("psf_dir")
    if not isinstance(source, str) or not isinstance(psf_dir, str):  # unfinished: the weights' metadata
        from safetensors import SafetensorError, safe_open

        try:
            last = CheckpointManager(run_dir).path("last")
            weights = last / "model.safetensors" if last is not None else Path(run_dir) / "model.safetensors"
            with safe_open(str(weights), framework="pt") as fh:
                meta = fh.metadata() or {}
        except (InputError, SafetensorError, OSError, ValueError, RuntimeError):  # only a hint for the message
            meta = {}
        source = source if isinstance(source, str) else meta.get("finetuned_from")
        psf_dir = psf_dir if isinstance(psf_dir, str) else meta.get("psf_dir") or None  # older runs: none
    return source, psf_dir if isinstance(psf_dir, str) else None


def remove_run_temporaries(run_dir: Path) -> list[Path]:
    """Remove the hidden temporaries of a killed run: inside ``run_dir`` (recursively) and the
    temporary siblings ``.NAME.XXXXXXXX.tmpdir`` of the folder itself. Never one that another process
    is writing now (it holds the folder's :class:`~hsicam.io.OutputLock`:
    :func:`~hsicam.io.remove_if_stale` leaves it). Where this process holds that lock (a new run:
    the training takes it before it checks the folder, and makes its own temporary only later), the
    siblings are a killed run's, and go, except a finished output that a killed replacement set aside
    (``.NAME.XXXXXXXX.old`` with ``NAME`` missing): it is renamed back (:func:`~hsicam.io.restore_set_aside`),
    so the check that follows finds the folder as it was. Returns the removed paths (a restored folder
    is not among them; :func:`~hsicam.io.remove_if_stale`, where another process held the lock, restores
    the same way and lists it)."""
    run_dir = Path(run_dir)
    removed = []
    parent = run_dir.parent
    if parent.is_dir():  # first: a folder restored here is cleaned inside as well, below
        ours = held_here(output_lock_path(run_dir))
        for p in sorted(parent.glob(f".{run_dir.name}.*")):
            if not (is_temporary(p.name) and p.name[len(run_dir.name) + 2:].count(".") == 1):
                continue
            if ours:
                if restore_set_aside(p):  # a replacement killed between its renames: the previous output comes back
                    continue
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            elif not remove_if_stale(p):
                continue
            removed.append(p)
    if run_dir.is_dir():
        removed += cleanup_stale_temporaries(run_dir, recursive=True)
    return removed


#: The record of the scenes a run on a ``data.root`` folder trained and validated on
#: (:mod:`hsicam.engine.provenance`).
DATA_RECORD = "data.json"

#: What a run folder may hold (anything else means it is not only a run folder: never wiped).
RUN_ENTRIES = frozenset({"config.yaml", "metrics.jsonl", "checkpoints", "tensorboard", MANIFEST, *LEGACY_POINTERS,
                         "model.safetensors", "prior.safetensors", "summary.json", "prior.yaml", MEASURED_PSF_FILE, LINEAR_STEP_FILE,
                         "measured_psf.json", DATA_RECORD, CAMERA_FILES_RECORD, LOCK_FILE})


def foreign_entries(run_dir: Path) -> list[str]:
    """Names (sorted) of what ``run_dir`` holds that a run never writes (:data:`RUN_ENTRIES`;
    hidden temporaries aside): a folder with any is not only a run folder."""
    return sorted(p.name for p in run_dir.iterdir() if p.name not in RUN_ENTRIES and not p.name.startswith("."))


def finished_checkpoint_step(run_dir: Path) -> int | None:
    """Global step of the run's last committed checkpoint, or None when it has none."""
    try:
        state = CheckpointManager(run_dir).state()
    except InputError:
        return None
    return None if state is None else int(state.get("global_step", 0))


def restart_run_dir(run_dir: Path) -> bool:
    """Wipe a run folder that has no finished checkpoint, so that a new run can start in it.

    Refuses (one-line :class:`InputError`) a folder that holds a committed checkpoint (resume it,
    or remove it yourself) and a folder holding files a run never writes. Returns True when
    something was removed."""
    run_dir = Path(run_dir)
    remove_run_temporaries(run_dir)
    if not run_dir.exists():
        return False
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: exists and is not a folder; choose another --out")
    entries = sorted(run_dir.iterdir())
    if not entries:
        return False
    foreign = foreign_entries(run_dir)
    if foreign:
        raise InputError(f"{run_dir}: not only a run folder (it holds {', '.join(foreign[:3])}); --restart wipes "
                         "run folders only: choose another --out")
    step = finished_checkpoint_step(run_dir)
    if step is not None:
        raise InputError(f"{run_dir}: holds a finished checkpoint (step {step}); continue it with --resume, or delete "
                         "the folder yourself to start over")
    weights = next((name for name in WEIGHTS_FILES if (run_dir / name).is_file()), None)
    if weights is not None:  # no checkpoint, yet trained weights: a copied camera, not a killed run
        raise InputError(f"{run_dir}: holds trained weights ({weights}) but no checkpoint (a copied or shipped camera); "
                         "--restart would delete them: choose another --out, or delete the folder yourself to start over")

    def refused(path: str | os.PathLike, exc: OSError) -> InputError:
        hint = OS_ERROR_HINTS.get(exc.errno, "")
        return InputError(f"{path}: cannot be removed for --restart ({exc.strerror or exc}"
                          f"{'; ' + hint if hint else ''}); the rest of the unfinished run may be gone already: "
                          "fix that, then run the same command again")

    def on_exc(_func, path, exc) -> None:  # rmtree's: names the entry it could not remove
        raise refused(path, exc) if isinstance(exc, OSError) else exc

    for p in entries:
        if p.is_dir() and not p.is_symlink():
            if sys.version_info >= (3, 12):
                shutil.rmtree(p, onexc=on_exc)
            else:
                shutil.rmtree(p, onerror=lambda f, path, info: on_exc(f, path, info[1]))
        else:
            try:
                p.unlink()
            except OSError as exc:
                raise refused(p, exc) from None
    log.info("%s: removed the unfinished run (no checkpoint) to start again", run_dir)
    return True


def _record(line: str) -> dict[str, Any] | None:
    """The record a metrics.jsonl line holds; None for a line that is not one (torn by a kill, blank, not an object)."""
    try:
        rec = json.loads(line)
    except json.JSONDecodeError:
        return None
    return rec if isinstance(rec, dict) else None


class MetricsLog:
    """Append-only metrics.jsonl; each record is written with one write() call."""

    def __init__(self, path: Path, enabled: bool = True) -> None:
        self.path, self.enabled = path, enabled

    def write(self, record: dict[str, Any]) -> None:
        if not self.enabled:
            return
        data = (json_text(record) + "\n").encode()  # strict JSON: a non-finite score as null
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, data)
        finally:
            os.close(fd)

    def read(self) -> list[dict[str, Any]]:
        """The complete records, in order (a line torn by a kill, or not an object, is skipped);
        [] when the file does not exist. A score written as null (not finite) reads as NaN again. A file saved
        on Windows reads the same: CRLF line ends, and the UTF-8 byte-order mark Notepad may put first (which made
        the first record, the run's starting session, unreadable)."""
        return [nan_for_null(rec) for rec in map(_record, self._lines()) if rec is not None]

    def first_line_whole(self) -> bool:
        """Whether the file's first line is a whole record: False when it is torn (a kill or a crash mid-write) or
        blank, which loses the run's starting session record (:func:`starting_session`);
        True when the file does not exist or is empty."""
        lines = self._lines()
        return not lines or _record(lines[0]) is not None

    def _lines(self) -> list[str]:
        if not self.path.exists():
            return []
        return self.path.read_text(encoding="utf-8-sig", errors="replace").splitlines()

    def truncate_after(self, step: int, epoch: int) -> None:
        """Keep only the complete records a checkpoint at (``step``, ``epoch`` epochs done) had seen.

        A validation record at the checkpoint's step belongs to a later epoch when the process
        died between writing it and saving the epoch-end checkpoint: it is dropped and redone. A
        ``final`` record summarises a training that the resume now continues: it is dropped too
        (the continued training writes its own at its end).
        """
        if not self.path.exists():
            return
        kept = [r for r in self.read() if not r.get("final") and
                (r.get("step", 0) < step or (r.get("step", 0) == step and r.get("epoch", 0) <= epoch))]
        # a torn first line stays: the run's starting session record was there, and without it the run's start is
        # unknown, which a later resume must still see (not a run whose first record is a step's, an older hsicam's)
        torn = [] if self.first_line_whole() else [self._lines()[0]]
        with atomic_open(self.path, "w", encoding="utf-8") as fh:
            fh.write("".join(line + "\n" for line in torn) + "".join(json_text(r) + "\n" for r in kept))


def run_records(run_dir: str | Path) -> list[dict[str, Any]]:
    """The run's metrics.jsonl records; [] when it has none or they cannot be read."""
    try:
        return MetricsLog(Path(run_dir) / "metrics.jsonl", enabled=False).read()
    except (InputError, OSError):
        return []


def starting_session(records: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The session record a run began with: the first of its metrics.jsonl ``records`` (the software record written
    before any other since db9c133); None for a run of an hsicam before session records, whose first record is
    another (the session records of the resumes that came later are not its start), or no record."""
    first = records[0].get("session") if records else None
    return first if isinstance(first, dict) else None
