"""Iterative reconstruction for CASSI cameras (the paper's baselines, DESIGN.md §3).

- :func:`gap_tv` (GAP-TV, accelerated or plain), :mod:`hsicam.solvers.gaptv`
- :func:`desci` (GAP + WNNM on block-matched groups), :mod:`hsicam.solvers.desci`
- :func:`admm_prior` with a :class:`SpectralAutoencoder` (Choi et al. 2017), :mod:`hsicam.solvers.choi`
- :func:`build_baseline`: the ``dd-cassi-*`` methods for evaluation, :mod:`hsicam.solvers.methods`

Solvers see a camera only through ``camera.A`` / ``camera.A_adjoint`` and need ΦΦᵀ diagonal
(true for every CASSI camera here). Names are imported lazily so that :mod:`hsicam.solvers.config`
stays importable from :mod:`hsicam.config`.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "gap_tv": "hsicam.solvers.gaptv",
    "SolverInfo": "hsicam.solvers.gaptv",
    "desci": "hsicam.solvers.desci",
    "desci_settings": "hsicam.solvers.desci",
    "DeSCISettings": "hsicam.solvers.desci",
    "wnnm_denoise": "hsicam.solvers.desci",
    "admm_prior": "hsicam.solvers.choi",
    "SpectralAutoencoder": "hsicam.solvers.choi",
    "train_prior": "hsicam.solvers.choi",
    "load_prior": "hsicam.solvers.choi",
    "tv_denoise": "hsicam.solvers.common",
    "build_baseline": "hsicam.solvers.methods",
    "BaselinesConfig": "hsicam.solvers.config",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'hsicam.solvers' has no attribute {name!r}")
