"""Torch devices by name: which ones this machine has (``--device``, ``train.device``,
:func:`hsicam.runs.folder.load_run`'s ``device``)."""

from __future__ import annotations

import torch


def device_problem(spec: str) -> str | None:
    """Why ``spec`` is not a torch device this machine has (cpu, cuda, cuda:N, mps), or None."""
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
