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


class _BandPSF(torch.autograd.Function):
    """One band: pupil phase (P, P) → |FFT_N(A·e^{iφ})|² centred on the axis and sum-pooled s×s
    into a (K, K) kernel.

    The FFT is pruned over the zero-padded rows. Centring, cropping or padding to K·s samples and
    pooling are one index map (FFT sample → kernel pixel), applied with ``index_add_`` forward and
    gathered backward, so the n×n intensity is never shifted or copied. The backward is the exact
    adjoint written out, down to the pupil: for u = A·e^{iφ}, ∂L/∂φ = Im(conj(u)·∂L/∂u) and
    ∂L/∂A = Re(e^{−iφ}·∂L/∂u).
    """

    @staticmethod
    def forward(ctx, phase: torch.Tensor, amplitude: torch.Tensor, n: int, s: int, k: int) -> torch.Tensor:  # type: ignore[override]
        p = phase.shape[-1]
        keep, bins = _kernel_bins(n, s, k, phase.device)
        field = torch.polar(amplitude, phase)
        spec = torch.fft.fft(torch.fft.fft(field, n=n, dim=-1), n=n, dim=-2)
        inten = spec.real.square() + spec.imag.square()
        if keep is not None:  # kernel smaller than the FFT plane: drop what falls outside
            inten = inten.index_select(0, keep).index_select(1, keep)
        rows = inten.new_zeros(k, inten.shape[1]).index_add_(0, bins, inten)
        pooled = inten.new_zeros(k, k).index_add_(1, bins, rows)
        ctx.save_for_backward(phase, field, spec)
        ctx.geometry = (n, s, k, p)
        return pooled

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        phase, field, spec = ctx.saved_tensors
        n, s, k, p = ctx.geometry
        keep, bins = _kernel_bins(n, s, k, grad.device)
        g = grad.index_select(0, bins).index_select(1, bins)  # adjoint of the pooling
        if keep is not None:
            g = g.new_zeros(n, n).index_put_((keep[:, None], keep[None, :]), g)
        # ∂L/∂u = 2·(adjoint of the zero-padded FFT)(g·U) = 2n²·ifft(g·U), first p rows/columns
        gf = torch.fft.ifft(spec * g, dim=-2)[:p]
        gf = torch.fft.ifft(gf, dim=-1)[:, :p]
        gf = gf * (2.0 * n * n)
        grad_phase = (field.conj() * gf).imag if ctx.needs_input_grad[0] else None
        grad_amplitude = None
        if ctx.needs_input_grad[1]:
            grad_amplitude = (torch.polar(torch.ones_like(phase), -phase) * gf).real
        return grad_phase, grad_amplitude, None, None, None


def _centre_pads(n: int, ks: int) -> tuple[int, int]:
    """Pads (before, after; negative = crop) that put index n//2 of an n-array at index ks//2."""
    centre = ks // 2
    return centre - n // 2, (ks - 1 - centre) - (n - 1 - n // 2)


def _kernel_bins(n: int, s: int, k: int, device: torch.device) -> tuple[torch.Tensor | None, torch.Tensor]:
    """Map from FFT samples (unshifted order, length n) to kernel pixels (0..K−1).

    Returns (keep, bins): ``keep`` are the FFT sample indices inside the K·s window (None when
    all n are), ``bins`` the kernel pixel of each kept sample. Sample i has frequency index
    i − n·[i ≥ ⌈n/2⌉]; index 0 (the optical axis) lands on the centre of pixel K//2.
    """
    before, _ = _centre_pads(n, k * s)
    window = (torch.arange(n, device=device) + n // 2) % n + before  # position in the K·s window
    inside = (window >= 0) & (window < k * s)
    if bool(inside.all()):
        return None, window // s
    keep = torch.nonzero(inside).flatten()
    return keep, window[keep] // s


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
    phase = doe_phase_per_m[:, None, None] * height_m + defocus_per_m2[:, None, None] * r2_m2  # (C, P, P)
    # unbind (not phase[c]): its backward stacks the band gradients once instead of C times.
    pooled = [_BandPSF.apply(ph, amplitude, n, s, k) / (n * n) for ph, n in zip(phase.unbind(0), fft_sizes)]
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
