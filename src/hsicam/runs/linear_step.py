"""The filters of a run's linear consistency step (``RUN/linear_step.safetensors``): the least-
squares linear map from the sensor image to the cube (:class:`hsicam.models.demosaic.LinearDemosaicFit`),
fitted on the run's training scenes through its trained optics (:func:`hsicam.engine.linear_step.ensure_linear_step`)
and used by ``model.consistency.kind: linear`` (:func:`hsicam.models.consistency.linear_consistency_step`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from hsicam.errors import InputError
from hsicam.runs.checkpoint import read_weights

LINEAR_STEP_FILE = "linear_step.safetensors"


def save_linear_step(path: str | Path, weight: torch.Tensor, info: dict[str, Any]) -> None:
    """``linear_step.safetensors`` (atomic): ``weight`` (m², C, K, K) and ``info`` as metadata."""
    from safetensors.torch import save_file

    from hsicam.io import atomic_path

    meta = {"format": "hsicam-linear-step-1", "info": json.dumps(info, default=float)}
    with atomic_path(path) as tmp:
        save_file({"weight": weight.detach().float().cpu().contiguous()}, str(tmp), metadata=meta)


def load_linear_step(path: str | Path, bands: int, period: int) -> torch.Tensor:
    """The filters (m², C, K, K) of :func:`save_linear_step`'s file, checked against the camera's
    band count C and CFA period m; :class:`InputError` if missing, corrupt or for another camera."""
    tensors, meta = read_weights(path)
    w = tensors.get("weight")
    if w is None or meta.get("format") != "hsicam-linear-step-1" or w.dim() != 4:
        raise InputError(f"{path}: not a linear-step file")
    if tuple(w.shape[:2]) != (period * period, bands) or w.shape[-1] != w.shape[-2] or w.shape[-1] % 2 == 0:
        raise InputError(f"{path}: filters of shape {tuple(w.shape)} do not fit a camera of {bands} bands and CFA "
                         f"period {period} (expected ({period * period}, {bands}, K, K), K odd)")
    return w
