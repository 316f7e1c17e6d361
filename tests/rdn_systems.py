"""A small camera system whose RDN reads the CFA demosaic as its input (tiny optics, one block of 8 features):
used by tests/models (the demosaic input against its loop reference) and tests/engine (its tiles)."""

from __future__ import annotations

import torch


def demosaic_input_system(tiny_config, *overrides: str):
    """The tiny preset's CameraSystem with ``model.rdn.demosaic_input=true`` (seeded, in eval mode); ``tiny_config``
    is conftest's fixture of that name."""
    from hsicam.models import CameraSystem

    torch.manual_seed(0)
    return CameraSystem.from_config(tiny_config("model.rdn.demosaic_input=true", "model.rdn.blocks=1", "model.rdn.features=8",
                                                "model.rdn.growth=4", *overrides)).eval()
