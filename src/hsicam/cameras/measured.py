"""A DOE camera whose PSFs are fixed: measured (calibration) or perturbed (tolerance studies).

:class:`FixedPSFCamera` is a :class:`~hsicam.cameras.DOECamera` that shares the optics, CFA and
noise modules of a trained camera but returns a fixed PSF stack (C, K, K) from ``psf()`` instead
of simulating it. The stack is a *non-persistent* buffer, so the state dict is exactly that of the
DOE camera: weights saved from a system built on it load into a plain
:class:`~hsicam.models.CameraSystem` (``hsicam reconstruct`` and ``load_run`` keep working), and the
PSFs travel separately (``measured_psf.safetensors``, see :mod:`hsicam.engine.calibration`).

DOE height noise (σ_p) does not apply to a fixed PSF; sensor noise does.
"""

from __future__ import annotations

import torch

from hsicam.cameras.base import Camera
from hsicam.cameras.doe_camera import DOECamera
from hsicam.errors import InputError
from hsicam.optics.psf import PSFResult


class FixedPSFCamera(DOECamera):
    """DOE camera with a fixed PSF stack ``psf`` (C, K, K), K = the camera's kernel.

    Build it with :meth:`from_camera`; the optics are kept (geometry, DOE parameters for the
    state dict) but never evaluated by ``psf()`` / ``A`` / ``forward``.
    """

    kind = "measured_psf"  # not in the registry: built from a trained camera and a PSF stack
    fixed_psf: torch.Tensor

    @classmethod
    def from_camera(cls, camera: DOECamera, psf: torch.Tensor) -> "FixedPSFCamera":
        """A camera sharing ``camera``'s modules, imaging with ``psf`` (C, K, K): finite and non-negative (a PSF is
        an intensity); kept in float64 when given so (the camera's ``.double()`` then images with it exactly), else
        float32. InputError for another shape or such values."""
        psf = torch.as_tensor(psf).detach()
        k = camera.kernel_px
        if psf.shape != (len(camera.bands), k, k):
            raise InputError(f"PSF stack must be ({len(camera.bands)}, {k}, {k}) for this camera, got {tuple(psf.shape)}")
        if not torch.is_floating_point(psf) or not bool(torch.isfinite(psf).all()) or bool((psf < 0).any()):
            raise InputError("PSF stack must hold finite, non-negative numbers (an intensity per pixel): clip a "
                             "background-subtracted measurement at 0 first" + ("" if torch.is_floating_point(psf) else
                                                                               f"; got {psf.dtype}"))
        device = camera.optics.amplitude.device
        # float64 where given and the device has it (MPS has none)
        dtype = torch.float64 if psf.dtype == torch.float64 and device.type != "mps" else torch.float32
        obj = cls(camera.bands, camera.optics, camera.cfa, camera.noise, camera.boundary, camera.padding)
        obj.register_buffer("fixed_psf", psf.to(device, dtype).clone(), persistent=False)
        return obj

    def noise_levels(self) -> dict[str, float]:
        """Sensor noise only: DOE height noise does not apply to a fixed PSF."""
        return Camera.noise_levels(self)

    def param_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """The CFA only (when enabled): the PSFs are fixed, the DOE heights unused."""
        return {k: v for k, v in super().param_groups().items() if k != "doe"}

    def psf_result(self, generator: torch.Generator | None = None) -> PSFResult:
        return PSFResult(self.fixed_psf, self.fixed_psf.sum(dim=(-2, -1)))

    def psf(self, generator: torch.Generator | None = None) -> torch.Tensor:
        return self.fixed_psf
