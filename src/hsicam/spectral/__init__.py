"""Spectral grids and optical materials."""

from hsicam.spectral.bands import (
    BAND_REACH_SIGMA,
    FWHM_PER_SIGMA,
    Bands,
    band_matrix,
    fine_grid,
    interpolated_bands,
    interpolation_matrix,
    nm_text,
    resample_spectra,
    resampling_matrix,
    resolved_bands,
)
from hsicam.spectral.materials import (
    FusedSilica,
    Material,
    TabulatedMaterial,
    get_material,
)

__all__ = [
    "BAND_REACH_SIGMA",
    "FWHM_PER_SIGMA",
    "Bands",
    "band_matrix",
    "fine_grid",
    "FusedSilica",
    "Material",
    "TabulatedMaterial",
    "get_material",
    "interpolated_bands",
    "interpolation_matrix",
    "nm_text",
    "resample_spectra",
    "resampling_matrix",
    "resolved_bands",
]
