"""The PSF stack of the DOE camera (paper eq. 6) with exact per-band sampling.

p_λ(x, y) ∝ | F{ A · exp(i φ_λ^d) · exp(i (π/λ)(1/z_o + 1/z_i − 1/f_λ) r²) } |² at (x, y)/(λ z_i)

The Fourier transform *is* the lens; only the residual defocus is sampled on the pupil grid.
Each band's FFT is zero-padded to N_λ (see :mod:`hsicam.optics.sampling`), so its output pitch is
pixel/s; the intensity is centred on the optical axis, cut to K·s samples and sum-pooled s×s.
Normalisation (Parseval): the energy over the whole FFT plane is 1; what the K×K kernel holds is
returned as ``energy`` (light outside is reported, never hidden by renormalising).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from hsicam.optics.doe import DOE, phase_per_height
from hsicam.optics.lens import Lens
from hsicam.optics.pupil import aperture_amplitude, cells_across, sample_coordinates_m
from hsicam.optics.sampling import PSFSampling, plan_psf_sampling
from hsicam.spectral import Bands


@dataclass
class PSFResult:
    psf: torch.Tensor  # (C, K, K), energy fraction per pixel
    energy: torch.Tensor  # (C,), fraction of each band's light inside the kernel


class _PooledIntensity(torch.autograd.Function):
    """|FFT_N(field)|² centred on the axis, cut to K·s samples and sum-pooled s×s → (K, K).

    Forward and backward both prune the FFT over the zero-padded rows; the backward is the exact
    adjoint written out (one complex multiply and two pruned inverse FFTs), which is ~2× faster
    than letting autograd trace the same chain.
    """

    @staticmethod
    def forward(ctx, field: torch.Tensor, n: int, s: int, k: int) -> torch.Tensor:  # type: ignore[override]
        p = field.shape[-1]
        spec = torch.fft.fft(torch.fft.fft(field, n=n, dim=-1), n=n, dim=-2)
        inten = torch.fft.fftshift(torch.view_as_real(spec).square().sum(-1))
        before, after = _centre_pads(n, k * s)
        pooled = F.pad(inten, (before, after, before, after)).reshape(k, s, k, s).sum(dim=(1, 3))
        ctx.save_for_backward(spec)
        ctx.geometry = (n, s, k, p)
        return pooled

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (spec,) = ctx.saved_tensors
        n, s, k, p = ctx.geometry
        g = grad[:, None, :, None].expand(k, s, k, s).reshape(k * s, k * s)
        before, after = _centre_pads(n, k * s)
        g = torch.fft.ifftshift(F.pad(g, (-before, -after, -before, -after)))  # adjoint of pad + shift
        gspec = 2.0 * g * spec
        # adjoint of the zero-padded forward FFT: n·ifft, then keep the first p rows / columns
        gf = torch.fft.ifft(gspec, dim=-2)[:p] * n
        gf = torch.fft.ifft(gf, dim=-1)[:, :p] * n
        return gf, None, None, None


def _centre_pads(n: int, ks: int) -> tuple[int, int]:
    """Pads (before, after; negative = crop) that put index n//2 of an n-array at index ks//2."""
    centre = ks // 2
    return centre - n // 2, (ks - 1 - centre) - (n - 1 - n // 2)


def psf_stack(
    height_m: torch.Tensor,
    amplitude: torch.Tensor,
    r2_m2: torch.Tensor,
    doe_phase_per_m: torch.Tensor,
    defocus_per_m2: torch.Tensor,
    fft_sizes: Sequence[int],
    supersample: int,
    kernel_px: int,
) -> PSFResult:
    """Pixel-integrated PSFs for every band.

    Args:
        height_m: DOE heights on the pupil samples (m), (P, P).
        amplitude: pupil transmission, (P, P).
        r2_m2: squared radius of each pupil sample (m²), (P, P).
        doe_phase_per_m: 2π(n(λ)−1)/λ per band (rad/m), (C,).
        defocus_per_m2: (π/λ)(1/z_o + 1/z_i − 1/f_λ) per band (rad/m²), (C,).
        fft_sizes: N_λ per band (≥ P).
        supersample: odd s; the FFT pitch is pixel/s.
        kernel_px: odd K.
    Returns:
        :class:`PSFResult` with ``psf`` (C, K, K) and ``energy`` (C,).
    """
    s, k = int(supersample), int(kernel_px)
    power = (amplitude * amplitude).sum()
    phase = doe_phase_per_m[:, None, None] * height_m + defocus_per_m2[:, None, None] * r2_m2
    field = torch.complex(amplitude * torch.cos(phase), amplitude * torch.sin(phase))  # (C, P, P)
    # unbind (not field[c]): its backward stacks the band gradients once instead of C times.
    pooled = [_PooledIntensity.apply(f, n, s, k) / (n * n) for f, n in zip(field.unbind(0), fft_sizes)]
    psf = torch.stack(pooled) / power  # Parseval: the whole FFT plane of each band sums to 1
    return PSFResult(psf, psf.sum(dim=(-2, -1)))


class PSFModel(nn.Module):
    """Lens + DOE optics of the camera; ``forward()`` returns the :class:`PSFResult` stack.

    All geometry is in metres. ``sensor_distance_m`` defaults to the lens focal length at its
    design wavelength; ``object_distance_m=None`` puts the object at infinity.
    """

    def __init__(
        self,
        bands: Bands,
        lens: Lens,
        doe: DOE,
        aperture_radius_m: float,
        cell_m: float,
        pixel_m: float,
        lens_design_wavelength_nm: float = 587.6,
        sensor_distance_m: float | None = None,
        object_distance_m: float | None = None,
        kernel_px: int | None = None,
        supersample: int | None = None,
        pupil_oversample: int = 1,
    ) -> None:
        super().__init__()
        n_cells = cells_across(aperture_radius_m, cell_m)
        if doe.n_cells != n_cells:
            raise ValueError(f"DOE has {doe.n_cells} cells across but the aperture needs {n_cells}")
        self.bands, self.lens, self.doe = bands, lens, doe
        self.aperture_radius_m, self.cell_m, self.pixel_m = aperture_radius_m, cell_m, pixel_m
        self.pupil_oversample = int(pupil_oversample)
        lam_nm = bands.centers_nm
        self.focal_lengths_m = lens.focal_lengths_m(lam_nm)
        z_i = float(lens.focal_lengths_m(np.array([lens_design_wavelength_nm]))[0]) if sensor_distance_m is None else float(sensor_distance_m)
        self.sensor_distance_m = z_i
        self.object_distance_m = object_distance_m
        self.sampling: PSFSampling = plan_psf_sampling(
            lam_nm * 1e-9, z_i, pixel_m, cell_m, n_cells, pupil_oversample, supersample, kernel_px
        )
        inv_zo = 0.0 if object_distance_m is None else 1.0 / object_distance_m
        defocus = np.pi / (lam_nm * 1e-9) * (inv_zo + 1.0 / z_i - 1.0 / self.focal_lengths_m)
        x = sample_coordinates_m(n_cells, cell_m, self.pupil_oversample)
        amp = aperture_amplitude(n_cells, cell_m, aperture_radius_m, self.pupil_oversample)
        # Derived from the config, so not saved in checkpoints (persistent=False).
        self.register_buffer("amplitude", torch.from_numpy(amp).float(), persistent=False)
        self.register_buffer("r2_m2", torch.from_numpy(x[:, None] ** 2 + x[None, :] ** 2).float(), persistent=False)
        self.register_buffer("doe_phase_per_m", torch.from_numpy(phase_per_height(doe.material, lam_nm)).float(), persistent=False)
        self.register_buffer("defocus_per_m2", torch.from_numpy(defocus).float(), persistent=False)

    @property
    def kernel_px(self) -> int:
        return self.sampling.kernel_px

    def pupil_heights(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """DOE heights on the pupil samples (m), (P, P): each cell repeated q×q."""
        h = self.doe.heights(generator)
        q = self.pupil_oversample
        if q > 1:
            h = h.repeat_interleave(q, dim=0).repeat_interleave(q, dim=1)
        return h.to(self.amplitude.dtype)

    def forward(self, generator: torch.Generator | None = None) -> PSFResult:
        return psf_stack(
            self.pupil_heights(generator), self.amplitude, self.r2_m2, self.doe_phase_per_m,
            self.defocus_per_m2, self.sampling.fft_sizes, self.sampling.supersample, self.sampling.kernel_px,
        )

    def describe(self) -> dict:
        """Geometry and sampling facts (for psf.json and reports)."""
        smp = self.sampling
        return {
            "lens": {
                "model": self.lens.model,
                "focal_length_mm": (self.focal_lengths_m * 1e3).tolist(),
                "sensor_distance_mm": self.sensor_distance_m * 1e3,
                "object_distance_m": self.object_distance_m,
            },
            "doe": {
                "enabled": self.doe.enabled,
                "cells_across": self.doe.n_cells,
                "cell_size_um": round(self.cell_m * 1e6, 9),
                "material": getattr(self.doe.material, "name", str(self.doe.material)),
                "design_wavelength_nm": self.doe.design_wavelength_nm,
                "height_2pi_nm": self.doe.h2pi_m * 1e9,
                "sigma_height_nm": self.doe.sigma_height_m * 1e9,
                "quantization_levels": self.doe.quantization_levels,
            },
            "aperture_radius_mm": self.aperture_radius_m * 1e3,
            "sampling": {
                "supersample": smp.supersample,
                "pupil_oversample": self.pupil_oversample,
                "pupil_samples": smp.pupil_samples,
                "fft_sizes": list(smp.fft_sizes),
                "kernel_px": smp.kernel_px,
                "min_kernel_px": smp.min_kernel_px,
                "max_pitch_rel_error": float(np.max(np.abs(smp.pitch_rel_error))),
            },
        }
