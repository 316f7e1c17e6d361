"""Refractive lens models: focal length versus wavelength.

Inside the PSF only the *residual* defocus of each band is simulated (DESIGN.md §1): the Fourier
transform plays the lens, so a lens model only has to say f(λ) and where its rear principal plane
H' sits (distances to the sensor are measured from H').
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hsicam.spectral.materials import Material, get_material


@dataclass(frozen=True)
class AchromaticLens:
    """Ideal achromat: the same focal length ``focal_length_m`` at every wavelength (paper, eq. 6)."""

    focal_length_m: float
    model: str = "achromatic"

    def focal_lengths_m(self, wavelength_nm: np.ndarray) -> np.ndarray:
        """f(λ) in metres, float64 array shaped like ``wavelength_nm``."""
        return np.full(np.shape(wavelength_nm), self.focal_length_m, dtype=np.float64)

    def rear_principal_plane_m(self, wavelength_nm: np.ndarray) -> np.ndarray:
        """H' relative to the lens's rear vertex (m): a thin lens, 0 at every wavelength."""
        return np.zeros(np.shape(wavelength_nm), dtype=np.float64)


@dataclass(frozen=True)
class SingletLens:
    """Plano-convex singlet, convex face towards the object: f(λ) = R / (n(λ) − 1) (exact for a
    thick plano-convex lens: the flat face has no power). The thickness t moves the principal
    planes: H sits on the convex vertex, H' at t/n(λ) in front of the flat rear vertex."""

    radius_of_curvature_m: float
    center_thickness_m: float
    material: Material
    model: str = "singlet"

    def focal_lengths_m(self, wavelength_nm: np.ndarray) -> np.ndarray:
        return self.radius_of_curvature_m / (self.material.n(wavelength_nm) - 1.0)

    def rear_principal_plane_m(self, wavelength_nm: np.ndarray) -> np.ndarray:
        """H' relative to the rear (flat) vertex (m, negative = towards the object): −t/n(λ).

        Thick lens, R1 = R, R2 = ∞: δ' = −f (n−1) t/(n R1) = −t/n.
        """
        return -self.center_thickness_m / self.material.n(wavelength_nm)


Lens = AchromaticLens | SingletLens


def lens_from_config(cfg) -> Lens:  # cfg: hsicam.config.LensConfig
    """Build the lens described by a :class:`~hsicam.config.LensConfig`. Its f at the design wavelength
    is repeated by :meth:`~hsicam.config.LensConfig.design_focal_length_mm` for the config's checks
    (config sits below optics); test_config holds the two equal."""
    if cfg.model == "achromatic":
        return AchromaticLens(cfg.focal_length_mm * 1e-3)
    return SingletLens(cfg.radius_of_curvature_mm * 1e-3, cfg.center_thickness_mm * 1e-3,
                       get_material(cfg.material, "camera.lens.material"))
