"""Iterative reconstruction for CASSI cameras (the paper's baselines, DESIGN.md §3).

- :func:`gap_tv` (GAP-TV, accelerated or plain), :mod:`hsicam.solvers.gaptv`
- :func:`desci` (GAP + WNNM on block-matched groups), :mod:`hsicam.solvers.desci`
- :func:`admm_prior` with a learned prior such as :class:`~hsicam.models.priors.SpectralAutoencoder`
  (Choi et al. 2017), :mod:`hsicam.solvers.choi`

Solvers are pure algorithms over a camera: they see it only through ``camera.A`` /
``camera.A_adjoint`` and ``camera.gram_diagonal`` (ΦΦᵀ diagonal: every CASSI camera). The
evaluation methods built on them (``dd-cassi-*``) live in :mod:`hsicam.engine.methods`.
"""

from hsicam.solvers.choi import admm_prior
from hsicam.solvers.common import tv_denoise
from hsicam.solvers.desci import DeSCISettings, desci, desci_settings, wnnm_denoise
from hsicam.solvers.gaptv import SolverInfo, gap_tv

__all__ = ["DeSCISettings", "SolverInfo", "admm_prior", "desci", "desci_settings", "gap_tv", "tv_denoise",
           "wnnm_denoise"]
