"""The filters of a run's linear consistency step (``RUN/linear_step.safetensors``): the least-
squares linear map from the sensor image to the cube (:class:`hsicam.models.demosaic.LinearDemosaicFit`),
fitted on the run's training scenes through its trained optics (:func:`hsicam.engine.linear_step.refresh_linear_step`)
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
    """``linear_step.safetensors`` (atomic): ``weight`` (m², C, K, K) and ``info`` as metadata
    (``weights_sha256``: the run's weights it was fitted through, see :func:`stale_reason`)."""
    from hsicam.runs.checkpoint import save_safetensors

    meta = {"format": "hsicam-linear-step-1", "info": json.dumps(info, default=float)}
    save_safetensors(path, {"weight": weight.detach().float().cpu().contiguous()}, meta)


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
    if not bool(w.isfinite().all()):
        raise InputError(f"{path}: {int((~w.isfinite()).sum())} NaN/Inf value(s) in the linear step's filters; delete "
                         "the file and resume the run (hsicam train --out RUN --resume) to fit it again")
    return w


def linear_step_info(path: str | Path) -> dict[str, Any]:
    """The metadata :func:`save_linear_step` recorded (``weights_sha256`` …), with ``filter_px`` the
    filters' width as stored; {} when the file cannot be read as a linear-step file."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), "pt") as fh:
            meta = fh.metadata() or {}
            shape = fh.get_slice("weight").get_shape() if "weight" in fh.keys() else None
        info = json.loads(meta.get("info") or "{}")
    except (OSError, ValueError, RuntimeError, SafetensorError):
        return {}
    info = info if isinstance(info, dict) else {}
    return {**info, "filter_px": int(shape[-1])} if shape else info


def stale_reason(path: str | Path, weights: str | Path, window_px: int | None = None) -> str | None:
    """Why the filters in ``path`` no longer fit the run: fitted through other weights than
    ``weights`` (the run trained on after the fit; files written before the sha256 was recorded are
    not checked), or (``window_px`` given) of another filter width than the config asks for. None
    when they fit."""
    from hsicam.io import file_sha256

    info = linear_step_info(path)
    if not info and Path(path).is_file():  # a file cut short or overwritten: refitted like a stale one
        return f"{path} cannot be read as a linear-step file (damaged)"
    fitted_through = info.get("weights_sha256")
    if isinstance(fitted_through, str) and fitted_through != file_sha256(weights):
        return (f"{path} was fitted through other weights (sha256 {fitted_through[:12]}…) than {Path(weights).name} "
                f"(sha256 {file_sha256(weights)[:12]}…): the run trained on after it was fitted, or now keeps another of its "
                f"checkpoints (train.keep_weights), or {Path(weights).name} was changed or damaged since (an edit, a copy "
                f"cut short, a disk error)")
    if window_px is not None and info.get("filter_px") is not None and info["filter_px"] != int(window_px):
        return f"{path} holds {info['filter_px']} px filters; model.consistency.window_px asks for {int(window_px)}"
    return None
