"""Spectral grids and optical materials."""

from hsicam.spectral.bands import Bands, interpolation_matrix, nm_text, resample_spectra
from hsicam.spectral.materials import (
    FusedSilica,
    Material,
    TabulatedMaterial,
    get_material,
)

__all__ = [
    "Bands",
    "FusedSilica",
    "Material",
    "TabulatedMaterial",
    "get_material",
    "interpolation_matrix",
    "nm_text",
    "resample_spectra",
]
