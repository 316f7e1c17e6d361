"""Reconstruction methods, so evaluation treats the learned DOE camera and the baselines alike.

A method owns a camera (the forward model that makes its measurement) and a reconstruction:

    y = method.camera(scene)            # simulated measurement (noise included)
    x̂ = method.reconstruct(y)           # cube aligned with method.camera's sensor area

Names: ``doe-rdn`` (our learned camera, from a run folder) and the CASSI baselines
``dd-cassi-gaptv``, ``dd-cassi-desci``, ``dd-cassi-choi``, ``dd-cassi-rdn`` (built by
:func:`hsicam.solvers.methods.build_baseline`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from hsicam.cameras import Camera
from hsicam.errors import InputError

DOE_METHOD = "doe-rdn"
BASELINE_METHODS = ("dd-cassi-gaptv", "dd-cassi-desci", "dd-cassi-choi", "dd-cassi-rdn")
METHOD_NAMES = (DOE_METHOD, *BASELINE_METHODS)


@dataclass
class Method:
    """A named camera + reconstruction pair.

    Attributes:
        name: method name (one of METHOD_NAMES).
        camera: forward model; ``camera.boundary`` decides the scene/sensor geometry.
        reconstruct: measurement (B, 1, H', W') → cube (B, C, H, W) on ``camera.bands``,
            aligned with ``target(scene)``.
        target: scene (B, C, H0, W0) → the ground truth the reconstruction is compared with.
        info: facts for result files (run folder, iterations, ...).
    """

    name: str
    camera: Camera
    reconstruct: Callable[[torch.Tensor], torch.Tensor]
    target: Callable[[torch.Tensor], torch.Tensor]
    info: dict[str, Any] = field(default_factory=dict)


def build_method(name: str, cfg, run: str | Path | None = None, device: str | torch.device = "cpu") -> Method:
    """Method ``name``. ``cfg`` is the evaluation config (band grid, camera noise, data);
    ``run`` is a trained run folder for learned methods."""
    if name == DOE_METHOD:
        from hsicam.engine.checkpoint import load_run

        if run is None:
            raise InputError("method doe-rdn needs --run RUN (a trained camera)")
        run_cfg, model = load_run(run, device)
        return Method(name, model.camera, model.reconstruct, model.target, {"run": str(run)})
    if name in BASELINE_METHODS:
        from hsicam.solvers.methods import build_baseline

        return build_baseline(name, cfg, run, device)
    raise InputError(f"unknown method {name!r}; choose one of {', '.join(METHOD_NAMES)}")
