"""Fitting the least-squares linear map from sensor image to cube through a trained camera: the
``doe-linear-demosaic`` reference (:func:`hsicam.engine.methods.linear_demosaic_reference`) and the
filters of the linear consistency step (``model.consistency.kind: linear``), which a run gets when
its training ends (:func:`ensure_linear_step`, ``RUN/linear_step.safetensors``)."""

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


def ensure_linear_step(run_dir: str | Path, cfg, model, consistency=None) -> bool:
    """Fit and write ``RUN/linear_step.safetensors`` on the run's training scenes (``cfg``: the run's
    config) when the linear consistency step is asked for (``consistency``, default the run's own
    ``model.consistency``) and the file is missing (training just ended, or an older run); sets
    ``model.linear_step``. Returns whether it wrote the file."""
    from hsicam.data.pipeline import scene_dataset, split_dataset
    from hsicam.runs.linear_step import load_linear_step

    c = cfg.model.consistency if consistency is None else consistency
    path = Path(run_dir) / LINEAR_STEP_FILE
    if c.kind != "linear" or c.iterations <= 0:
        return False
    cam = model.camera
    if model.linear_step is not None:  # loaded with the run (load_run)
        return False
    if path.is_file():
        model.linear_step = load_linear_step(path, len(cam.bands), cam.code_period)
        return False
    bands = cfg.bands.to_bands()
    train, _ = split_dataset(cfg.data, bands)
    t0 = time.perf_counter()
    weight = fit_linear_map(model, scene_dataset(cfg.data, train, bands), c.window_px)
    save_linear_step(path, weight, {"window_px": c.window_px, "training_scenes": len(train), "ridge": LINEAR_MAP_RIDGE,
                                       "flat_field": True})
    log.info("linear consistency step: %d×%d filters per CFA phase and band fitted on %d training scenes (%.0f s) -> %s",
             c.window_px, c.window_px, len(train), time.perf_counter() - t0, path)
    model.linear_step = weight
    return True
