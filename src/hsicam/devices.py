"""Torch devices by name: which ones this machine has (``--device``, ``train.device``,
:func:`hsicam.runs.folder.load_run`'s ``device``); and this process's place in a ``torchrun`` group.

Torch is imported by the functions that use it, not by the module: :func:`dist_env` is read by the command line's
clean-up after a failed or interrupted command, and a Ctrl-C that lands inside torch's first import leaves a
half-initialised torch, whose second import crashed the process (a double traceback, an abort or a segfault)."""

from __future__ import annotations

import os
import warnings
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch


def dist_env() -> tuple[int, int, int]:
    """(rank, world size, local rank) from the ``torchrun`` environment (0, 1, 0 without it)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0"))


def float64_device(device: torch.device | str) -> torch.device:
    """Where float64 work on the tensors of ``device`` runs (metrics, the PSF energy cut): on ``device`` itself, or
    on the CPU for a device without float64. Apple's MPS has none: a float64 tensor there is a TypeError ("Cannot
    convert a MPS Tensor to float64 dtype"), which stopped a training on ``mps`` at its first validation."""
    import torch

    device = torch.device(device)
    return torch.device("cpu") if device.type == "mps" else device


def autocast_problem(device: torch.device | str, dtype: torch.dtype) -> str | None:
    """Why this torch cannot autocast on ``device`` in ``dtype`` (torch's own words, one line), or None; None on the CPU,
    where the network is not autocast (:meth:`hsicam.models.CameraSystem.network` runs it in float32). ``train.bf16``
    on ``mps`` autocasts there, which torch 2.4 cannot (an error at the first step, after the data and the run folder
    were made), torch 2.5 only in float16 (a warning, and the training ran in float32 while its config said bf16), later
    ones in bfloat16 from macOS 14 on; a CUDA device without bfloat16 is an error too."""
    import torch

    device = torch.device(device)
    if device.type == "cpu":
        return None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with torch.autocast(device.type, dtype=dtype):
                on = torch.is_autocast_enabled(device.type) and torch.get_autocast_dtype(device.type) == dtype
        except (RuntimeError, TypeError, ValueError) as exc:
            return " ".join(str(exc).split())
    if on:
        return None
    said = " ".join(" ".join(str(w.message).split()) for w in caught)
    return said or f"torch does not autocast {device.type} in {dtype}"


def device_problem(spec: str) -> str | None:
    """Why ``spec`` is not a torch device this machine has (cpu, cuda, cuda:N, mps), or None."""
    import torch

    try:
        dev = torch.device(spec)
    except (RuntimeError, ValueError):
        return "unknown device; use cpu, cuda, cuda:N or mps"
    if dev.type == "cuda":
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if n == 0:
            return f"no CUDA device is available here (torch {torch.__version__}); use cpu"
        if dev.index is not None and dev.index >= n:
            return f"this machine has {n} CUDA device(s), cuda:0 to cuda:{n - 1}"
    elif dev.type == "mps" and not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
        return "no MPS device is available here; use cpu"
    elif dev.type not in ("cpu", "cuda", "mps"):
        return "hsicam runs on cpu, cuda or mps"
    return None
