"""hsicam: learned snapshot hyperspectral cameras (lens + DOE + colour filter array + RDN).

SI metres inside the code; wavelengths travel in nanometres inside a :class:`Bands` object.
Tensors are (B, C, H, W) with C = spectral bands in ascending wavelength order.
"""

from hsicam.errors import ConfigError, HsicamError, InputError
from hsicam.spectral import Bands

__version__ = "0.1.0"

__all__ = ["Bands", "ConfigError", "HsicamError", "InputError", "__version__"]
