"""Fitting the least-squares linear map from sensor image to cube through a trained camera: the
``doe-linear-demosaic`` reference (:func:`hsicam.engine.methods.linear_demosaic_reference`) and the
filters of the linear consistency step (``model.consistency.kind: linear``), which a run gets when
its training ends (:func:`refresh_linear_step`, ``RUN/linear_step.safetensors``)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import torch

from hsicam.models.demosaic import LinearDemosaicFit
from hsicam.runs.linear_step import LINEAR_STEP_FILE, save_linear_step

log = logging.getLogger(__name__)

#: Ridge of the least-squares fit, relative to the mean diagonal of each phase's Gram matrix.
LINEAR_MAP_RIDGE = 1e-6


def fit_linear_map(model, scenes, window: int = 11, ridge: float = LINEAR_MAP_RIDGE,
                   flat_field: bool = True) -> torch.Tensor:
    """Least-squares filters (m², C, K, K) of :func:`hsicam.models.demosaic.phase_linear` from the
    noise-free sensor images of ``scenes`` (items (C, H, W), at least the camera's kernel) through
    ``model.camera`` (nominal PSFs) to their targets, by default under the flat-field constraint (a
    uniform scene gives a uniform estimate: no CFA trace; :class:`LinearDemosaicFit`). ValueError for
    a camera without a per-band sensor code (the CFA), no scenes, or a window narrower than the CFA
    period under the constraint."""
    cam = model.camera
    try:
        cam.sensor_code(1, 1)
    except NotImplementedError:
        raise ValueError(f"the linear map needs a camera with a per-band sensor code, not {type(cam).__name__}") from None
    if len(scenes) == 0:
        raise ValueError("the linear map needs at least one training scene")
    fit = LinearDemosaicFit(cam.code_period, len(cam.bands), window, ridge, flat_field)
    device = next(iter(cam.parameters()), torch.empty(0)).device
    with torch.no_grad():
        psf = cam.snapshot(nominal=True).psf if hasattr(cam, "psf") else None
        for i in range(len(scenes)):
            scene = scenes[i][None].to(device, torch.float32)
            sensor = cam.A(scene, psf) if psf is not None else cam.A(scene)
            fit.add(sensor, model.target(scene))
    return fit.solve()


def refresh_linear_step(run_dir: str | Path, consistency, keep_weights: str | None = None) -> list[str]:
    """Make a finished run's linear consistency step the one ``consistency`` (a
    :class:`~hsicam.config.ConsistencyConfig`) asks for, when training (or fine-tuning) ends or a
    finished run is resumed with other ``model.consistency`` keys:

    - ``keep_weights`` (``train.keep_weights``; None: as the run has it): the checkpoint the run
      keeps, its root weights switched to it when it differs (a finished run reused by a demo or an
      experiment whose config asks for the other: :meth:`~hsicam.runs.checkpoint.CheckpointManager.apply_keep`);
    - the run's config.yaml gets ``consistency`` as its ``model.consistency`` (an inference setting:
      the training never sees it, so nothing else is touched), and ``keep_weights``;
    - with ``kind: linear``, ``RUN/linear_step.safetensors`` is fitted on the run's training scenes
      through the run's kept weights (train.keep_weights), when it is missing or no longer fits them
      (:func:`~hsicam.runs.linear_step.stale_reason`: the run trained on, or another filter width).

    It holds the run folder's lock (:mod:`hsicam.runs.lock`) while it writes (after training, the
    loop's own: the lock is re-entrant). Returns what changed, in words (empty: nothing)."""
    from hsicam.runs.lock import RunLock

    with RunLock(run_dir) as lock:
        lock.acquire()
        return _refresh_linear_step(Path(run_dir), consistency, keep_weights)


def _refresh_linear_step(run_dir: Path, consistency, keep_weights: str | None = None) -> list[str]:
    """:func:`refresh_linear_step` under the lock. The filters are fitted first and replace the old
    file atomically; config.yaml is rewritten last, so an interruption leaves a working run."""
    from hsicam.config import dump_yaml, load_config
    from hsicam.io import atomic_open
    from hsicam.runs.checkpoint import CheckpointManager, kept_checkpoint, root_weights_path
    from hsicam.runs.folder import EMPTY_RUN_CONFIG, load_run
    from hsicam.runs.linear_step import stale_reason

    changed = []
    run_cfg = load_config(run_dir / "config.yaml", empty=EMPTY_RUN_CONFIG)
    was = kept_checkpoint(run_dir)  # (None: no checkpoint, and then nothing to switch)
    if keep_weights is not None and CheckpointManager(run_dir, keep=keep_weights).apply_keep():
        now = kept_checkpoint(run_dir)
        changed.append(f"its kept weights: the {now['checkpoint']} checkpoint's (step {now['step']}; were the "
                       f"{was['checkpoint']} checkpoint's, step {was['step']}; train.keep_weights {keep_weights})")
    elif was is not None and CheckpointManager(run_dir, keep=keep_weights or run_cfg.train.keep_weights).sync_root():
        # a finished run resumed after its root weights were lost (deleted, a copy without them): readers refuse a
        # run without them, so they come back from the intact checkpoint the manifest keeps (a damaged one is not
        # copied: sync_root warns, and the training's end refuses the run, engine.train.check_kept_weights)
        changed.append(f"its root weights {run_dir / 'model.safetensors'} restored from the {was['checkpoint']} "
                       f"checkpoint (step {was['step']})")
    if consistency.kind == "linear" and consistency.iterations > 0 and run_cfg.camera.kind == "doe":
        # (SD-CASSI skips the step; the config refuses it for DD-CASSI)
        path = run_dir / LINEAR_STEP_FILE
        why = stale_reason(path, root_weights_path(run_dir), consistency.window_px) if path.is_file() else "missing"
        if why is not None:
            if why != "missing":
                log.info("refitting the linear consistency step: %s", why)
            _, model = load_run(run_dir, linear_step=False)
            _fit_linear_step(run_dir, run_cfg, model, consistency.window_px)
            changed.append(f"its linear consistency step {'fitted' if why == 'missing' else 'refitted'} "
                           f"({LINEAR_STEP_FILE})")
    rewrite = False
    if run_cfg.model.consistency != consistency:
        before = run_cfg.model.consistency
        diff = ", ".join(f"{k} {getattr(before, k)} → {getattr(consistency, k)}" for k in vars(consistency)
                         if getattr(before, k) != getattr(consistency, k))
        run_cfg.model.consistency = consistency
        rewrite = True
        changed.insert(0, f"model.consistency in config.yaml ({diff})")
    if keep_weights is not None and run_cfg.train.keep_weights != keep_weights:
        run_cfg.train.keep_weights = keep_weights
        rewrite = True
    if rewrite:
        with atomic_open(run_dir / "config.yaml", encoding="utf-8") as fh:
            fh.write(dump_yaml(run_cfg))
    return changed


def _fit_linear_step(run_dir: Path, cfg, model, window_px: int) -> None:
    """Fit the linear step's filters on the run's training scenes through ``model`` (the run's
    weights, loaded), write them with the weights' sha256 and set ``model.linear_step``."""
    from hsicam.data.pipeline import scene_dataset, split_dataset
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256

    bands = cfg.bands.to_bands()
    train, _ = split_dataset(cfg.data, bands)
    t0 = time.perf_counter()
    weight = fit_linear_map(model, scene_dataset(cfg.data, train, bands), window_px)
    path = Path(run_dir) / LINEAR_STEP_FILE
    save_linear_step(path, weight, {"window_px": window_px, "training_scenes": len(train), "ridge": LINEAR_MAP_RIDGE,
                                    "flat_field": True, "weights_sha256": file_sha256(root_weights_path(run_dir))})
    log.info("linear consistency step: %d×%d filters per CFA phase and band fitted on %d training scenes (%.0f s) -> %s",
             window_px, window_px, len(train), time.perf_counter() - t0, path)
    model.linear_step = weight
