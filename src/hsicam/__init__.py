"""hsicam: learned snapshot hyperspectral cameras (lens + DOE + colour filter array + RDN).

SI metres inside the code; wavelengths travel in nanometres inside a :class:`Bands` object.
Tensors are (B, C, H, W) with C = spectral bands in ascending wavelength order.
"""

from typing import Any

from hsicam.errors import ConfigError, HsicamError, InputError
from hsicam.version import __version__

__all__ = ["Bands", "ConfigError", "HsicamError", "InputError", "__version__"]


def __getattr__(name: str) -> Any:
    """``hsicam.Bands`` on first use: importing the package does not import numpy and torch, so the
    command line can report an interruption during its start-up as one line."""
    if name == "Bands":
        from hsicam.spectral import Bands

        return Bands
    raise AttributeError(f"module 'hsicam' has no attribute {name!r}")
