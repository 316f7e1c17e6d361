"""The PSF stack of the DOE camera (paper eq. 6), exact for square DOE cells.

p_λ(x, y) ∝ | F{ A · exp(i φ_λ^d) · exp(i (π/λ)(1/z_o + 1/z_i − 1/f_λ) r²) } |² at (x, y)/(λ z_i)

The Fourier transform *is* the lens; only the residual defocus is sampled on the pupil grid.
The pupil is piecewise constant on square cells (the DOE's own cells, or q×q sub-cells of them
with pupil oversampling). Its far field is exactly the periodic cell-grid sum times the cells'
sinc² envelope; one N-point FFT (N ≥ 2P − 1, the same for every band) holds the periodic factor
exactly, and a per-wavelength matrix W (K, N) integrates envelope × periodic intensity over
each sensor pixel (see :mod:`hsicam.optics.sampling`): every diffraction order that falls in the
kernel is kept, at the exact per-band pitch.
Normalisation (Parseval): the energy over the whole sensor plane is 1; what the K×K kernel holds
is returned as ``energy`` (light outside is reported, never hidden by renormalising).
Band integration (optional): each band's PSF is the weighted mean over M sub-wavelengths.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from hsicam.errors import ConfigError
from hsicam.optics.doe import DOE, phase_per_height
from hsicam.optics.lens import Lens
from hsicam.optics.pupil import aperture_amplitude, cells_across, sample_coordinates_m
from hsicam.memory import format_bytes, memory_budget_bytes
from hsicam.optics.sampling import (
    WAVELENGTHS_PER_BATCH,
    PSFSampling,
    defocus_aliasing,
    far_field_period_px,
    pixel_weights,
    plan_psf_sampling,
    psf_memory_estimate,
)
from hsicam.spectral import Bands
from hsicam.spectral.bands import band_sample_wavelengths

log = logging.getLogger(__name__)

#: A residual defocus whose phase steps more than this (in π) between pupil samples at the aperture edge, below
#: the aliasing limit of 1, is warned about (:meth:`PSFModel._warn_coarse_defocus`): its PSF is ≳ 11 % off.
DEFOCUS_STEP_WARN = 0.5
#: The step the warning's advice aims at (the paper singlet's, 0.43π at 420 nm: 8.9 % L1, documented).
DEFOCUS_STEP_GOOD = 0.45
#: The PSF's relative L1 error per squared step (in π), measured against a 6× finer pupil grid (docs/optics.md).
DEFOCUS_L1_PER_STEP2 = 0.45
_COARSE_DEFOCUS_WARNED: set[tuple[str, int, float]] = set()
#: :class:`PSFModel`'s constant buffers (derived from the config, not saved): float32, or float64 exactly in a float64
#: module (:meth:`PSFModel._apply`).
OPTICS_CONSTANTS = ("amplitude", "r2_m2", "doe_phase_per_m", "defocus_per_m2", "pixel_weights", "line_weights")

@dataclass
class PSFResult:
    psf: torch.Tensor  # (C, K, K), energy fraction per pixel
    energy: torch.Tensor  # (C,), fraction of each band's light inside the kernel


class _PSFBatch(torch.autograd.Function):
    """A few wavelengths: pupil phases (L, P, P) → W·|FFT_N(A·e^{iφ})|²·Wᵀ, the (L, K, K) kernels.

    The FFT is pruned over the zero-padded rows. W (L, K, N) holds envelope, tiling of the periodic
    far field over the kernel and pixel integration. The backward is the exact adjoint written
    out, down to the pupil: for u = A·e^{iφ}, ∂L/∂φ = Im(conj(u)·∂L/∂u) and
    ∂L/∂A = Re(e^{−iφ}·∂L/∂u) (summed over the wavelengths, A being shared). A backward with
    ``create_graph=True`` (second-order gradients) takes autograd's through :func:`psf_batch_reference` instead.
    """

    @staticmethod
    def forward(ctx, phase: torch.Tensor, amplitude: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        n, p = weights.shape[-1], phase.shape[-1]
        field = torch.polar(amplitude.expand_as(phase), phase)
        rows = torch.fft.fft(field, n=n, dim=-1)  # (L, P, N)
        # the column transforms run along the contiguous last dimension of a transposed zero canvas (what
        # fft(dim=-2) copies its input into anyway): one copy of the P non-zero rows, not a padded copy and a
        # transposing copy of all N; spec is the same tensor, bit for bit, in the same memory layout
        canvas = rows.new_empty(rows.shape[0], n, n)
        canvas[..., p:].zero_()
        canvas[..., :p].copy_(rows.transpose(-1, -2))
        spec = torch.fft.fft(canvas, dim=-1).transpose(-1, -2)
        inten = spec.real.square() + spec.imag.square()
        pooled = weights @ inten @ weights.transpose(-1, -2)
        ctx.save_for_backward(phase, amplitude, field, spec, weights)
        return pooled

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        phase, amplitude, field, spec, weights = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph=True: the gradient is differentiated again
            return _psf_batch_gradients_differentiable(ctx, grad, phase, amplitude, weights)
        n, p = weights.shape[-1], phase.shape[-1]
        g = weights.transpose(-1, -2) @ grad @ weights  # (L, N, N): adjoint of W·I·Wᵀ
        # ∂L/∂u = 2·(adjoint of the zero-padded FFT)(g·U) = 2n²·ifft(g·U), first p rows/columns
        # spec (complex) times g (real) as real pairs: no complex copy of g, the same products
        sg = torch.view_as_complex(torch.view_as_real(spec) * g[..., None])
        gf = torch.fft.ifft(sg, dim=-2)[..., :p, :]
        gf = torch.fft.ifft(gf, dim=-1)[..., :p]
        gf = gf * (2.0 * n * n)
        grad_phase = (field.conj() * gf).imag if ctx.needs_input_grad[0] else None
        grad_amplitude = None
        if ctx.needs_input_grad[1]:
            grad_amplitude = (torch.polar(torch.ones_like(phase), -phase) * gf).real.sum(0)
        return grad_phase, grad_amplitude, None


def psf_batch_reference(phase: torch.Tensor, amplitude: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """What :class:`_PSFBatch` computes, composed of differentiable torch operations (no pruning, no written-out
    backward): W·|FFT_N×N(A·e^{iφ} zero-padded)|²·Wᵀ, (L, K, K) for phases (L, P, P), amplitude (P, P) and W
    (L, K, N). Equal to the batch's forward (its test compares them bit for bit)."""
    n = weights.shape[-1]
    field = torch.polar(amplitude.expand_as(phase), phase)
    spec = torch.fft.fft(torch.fft.fft(field, n=n, dim=-1), n=n, dim=-2)
    return weights @ (spec.real.square() + spec.imag.square()) @ weights.transpose(-1, -2)


def _psf_batch_gradients_differentiable(ctx, grad: torch.Tensor, phase: torch.Tensor, amplitude: torch.Tensor,
                                        weights: torch.Tensor) -> tuple:
    """:class:`_PSFBatch`'s gradients (phase, amplitude) as a differentiable function of its inputs and of ``grad``
    (backward with ``create_graph=True``): autograd's through :func:`psf_batch_reference`, re-run here. The written-out
    backward runs without autograd; marked once-differentiable, it returned constants whenever ``grad`` needed no
    gradient, so a penalty on the DOE's gradient had a silent zero gradient."""
    needs = ctx.needs_input_grad[:2]
    inputs = [t for t, need in zip((phase, amplitude), needs) if need]
    with torch.enable_grad():
        grads = iter(torch.autograd.grad(psf_batch_reference(phase, amplitude, weights), inputs, grad,
                                         create_graph=True))
    return tuple(next(grads) if need else None for need in needs) + (None,)


def psf_stack(
    height_m: torch.Tensor,
    amplitude: torch.Tensor,
    r2_m2: torch.Tensor,
    doe_phase_per_m: torch.Tensor,
    defocus_per_m2: torch.Tensor,
    weights: torch.Tensor,
    line_weights: torch.Tensor | None = None,
) -> PSFResult:
    """Pixel-integrated PSFs, exact for a pupil of square cells.

    Args:
        height_m: DOE heights on the pupil cells (m), (P, P).
        amplitude: pupil transmission per cell, (P, P).
        r2_m2: squared radius of each cell centre (m²), (P, P).
        doe_phase_per_m: 2π(n(λ)−1)/λ per wavelength (rad/m), (L,).
        defocus_per_m2: (π/λ)(1/z_o + 1/z_i − 1/f_λ) per wavelength (rad/m²), (L,).
        weights: pixel-integration matrices W per wavelength (:func:`~hsicam.optics.sampling.pixel_weights`), (L, K, N), N ≥ 2P − 1.
        line_weights: (C, M) with L = C·M: each band is the weighted sum of its M wavelengths;
            None: one wavelength per band.
    Returns:
        :class:`PSFResult` with ``psf`` (C, K, K) and ``energy`` (C,).
    """
    power = (amplitude * amplitude).sum()
    phase = doe_phase_per_m[:, None, None] * height_m + defocus_per_m2[:, None, None] * r2_m2  # (L, P, P)
    k = WAVELENGTHS_PER_BATCH
    lines = torch.cat([_PSFBatch.apply(ph, amplitude, w) for ph, w in zip(phase.split(k), weights.split(k))])
    psf = lines / power  # Parseval: the whole sensor plane of each wavelength sums to 1
    if line_weights is not None:
        c, m = line_weights.shape
        psf = (psf.reshape(c, m, *psf.shape[-2:]) * line_weights[:, :, None, None]).sum(dim=1)
    return PSFResult(psf, psf.sum(dim=(-2, -1)))


class PSFModel(nn.Module):
    """Lens + DOE optics of the camera; ``forward()`` returns the :class:`PSFResult` stack.

    All geometry is in metres. ``sensor_distance_m`` is measured from the lens's rear principal
    plane H' at its design wavelength and defaults to the focal length there; the sensor plane is
    fixed, so a singlet whose H' moves with λ sees a slightly different distance per band.
    ``object_distance_m=None`` puts the object at infinity. ``supersample=None`` integrates each
    pixel exactly; ``band_samples`` M > 1 averages each band over M Gauss–Hermite wavelengths of its Gaussian.
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
        band_samples: int = 1,
        warn_coarse_defocus: bool = True,
    ) -> None:
        super().__init__()
        self.warn_coarse_defocus = bool(warn_coarse_defocus)  # False: a study that records the step itself
        n_cells = cells_across(aperture_radius_m, cell_m)
        if doe.n_cells != n_cells:
            raise ValueError(f"DOE has {doe.n_cells} cells across but the aperture needs {n_cells}")
        self.bands, self.lens, self.doe = bands, lens, doe
        self.aperture_radius_m, self.cell_m, self.pixel_m = aperture_radius_m, cell_m, pixel_m
        self.pupil_oversample = int(pupil_oversample)
        self.band_samples = int(band_samples)
        self.lens_design_wavelength_nm = float(lens_design_wavelength_nm)
        lam_nm, line_w = band_sample_wavelengths(bands.centers_nm, bands.fwhm_nm, self.band_samples)  # (C, M)
        self.line_wavelengths_nm = lam_nm.reshape(-1)
        lam0 = np.array([self.lens_design_wavelength_nm])
        self.focal_lengths_m = lens.focal_lengths_m(bands.centers_nm)
        z_i = float(lens.focal_lengths_m(lam0)[0]) if sensor_distance_m is None else float(sensor_distance_m)
        self.sensor_distance_m = z_i
        # the sensor plane is fixed: its distance from H'(λ) changes as H' moves with λ
        h0 = float(lens.rear_principal_plane_m(lam0)[0])
        z_line = z_i + h0 - lens.rear_principal_plane_m(self.line_wavelengths_nm)
        self.line_sensor_distances_m = z_line
        self.object_distance_m = object_distance_m
        inv_zo = 0.0 if object_distance_m is None else 1.0 / object_distance_m
        lam_m = self.line_wavelengths_nm * 1e-9
        f_line = lens.focal_lengths_m(self.line_wavelengths_nm)
        with np.errstate(divide="ignore", over="ignore"):  # a zero distance: plan_psf_sampling; inf: _check_defocus
            defocus = np.pi / lam_m * (inv_zo + 1.0 / z_line - 1.0 / f_line)
        self._check_defocus(defocus, z_line, sensor_distance_m is not None, n_cells)
        self.sampling: PSFSampling = plan_psf_sampling(
            self.line_wavelengths_nm * 1e-9, float(z_line.max()), pixel_m, cell_m, n_cells, pupil_oversample,
            supersample, kernel_px, aperture_radius_m,
        )
        self._period_px = far_field_period_px(lam_m, z_line, self.sampling.pupil_pitch_m, pixel_m)  # (L,)
        self._defocus_per_m2, self._line_weights = defocus, line_w
        # Derived from the config, so not saved in checkpoints (persistent=False); float32 until the module's dtype
        # changes (_apply)
        for name, value in self._constants().items():
            self.register_buffer(name, torch.from_numpy(value).float(), persistent=False)

    def _constants(self) -> dict[str, np.ndarray]:
        """The optics' constant arrays in float64, by buffer name (:data:`OPTICS_CONSTANTS`): the pupil's amplitude
        and squared radius (P, P) (m²), the DOE phase per metre of height (L,) (rad/m), the residual defocus (L,)
        (rad/m²), the pixel-integration matrices W (L, K, N) and the band weights (C, M)."""
        smp, n_cells, q = self.sampling, self.doe.n_cells, self.pupil_oversample
        x = sample_coordinates_m(n_cells, self.cell_m, q)
        return {
            "amplitude": aperture_amplitude(n_cells, self.cell_m, self.aperture_radius_m, q),
            "r2_m2": x[:, None] ** 2 + x[None, :] ** 2,
            "doe_phase_per_m": phase_per_height(self.doe.material, self.line_wavelengths_nm),
            "defocus_per_m2": self._defocus_per_m2,
            "pixel_weights": np.stack([pixel_weights(per, smp.kernel_px, smp.fft_size, smp.supersample)
                                       for per in self._period_px]),
            "line_weights": self._line_weights,
        }

    def _apply(self, fn, recurse: bool = True):
        """``nn.Module``'s (``.double()``, ``.to(dtype, device)``, …), then each optics constant whose dtype changed
        rebuilt from its float64 value: a float64 module holds the float64 constants, not float32 ones cast up (a
        float64 camera's PSFs were float32-accurate, ~5e-8 relative); another dtype is rounded from float32 as the
        float32 buffers always were; back to float32 too (a ``.half().float()`` camera kept the half constants cast up:
        inf phases, NaN PSFs; session 76's review), the float64 constants rounding to the fresh float32 bits."""
        before = {name: getattr(self, name).dtype for name in OPTICS_CONSTANTS}
        super()._apply(fn, recurse)
        stale = [name for name in OPTICS_CONSTANTS if getattr(self, name).dtype != before[name]
                 and getattr(self, name).dtype.is_floating_point]
        if stale:
            exact = self._constants()
            for name in stale:
                t = getattr(self, name)
                value = torch.from_numpy(exact[name])
                self._buffers[name] = (value if t.dtype == torch.float64 else value.float()).to(t.device, t.dtype)
        return self

    def _check_defocus(self, defocus_per_m2: np.ndarray, z_line: np.ndarray, sensor_distance_set: bool,
                       n_cells: int) -> None:
        """Refuse, before anything is allocated, a residual defocus that aliases on the pupil grid
        (:func:`~hsicam.optics.sampling.defocus_aliasing` > 1): its geometric blur is wider than the
        field λz/d the pupil samples can represent, so the PSF would be that of another lens. The
        paper singlet's 17.7 waves at 420 nm are 0.43 of that limit; a sensor distance far from the
        focal length (e.g. a value in the wrong unit) is far above it."""
        if not np.all(np.isfinite(z_line)) or np.any(z_line <= 0):
            return  # plan_psf_sampling refuses a non-positive distance with its own message
        q, cell = self.pupil_oversample, self.cell_m
        ratio = defocus_aliasing(defocus_per_m2, self.aperture_radius_m, cell / q)
        i = int(np.argmax(ratio))
        if not ratio[i] > 1.0:
            if ratio[i] > DEFOCUS_STEP_WARN and self.warn_coarse_defocus:
                self._warn_coarse_defocus(float(ratio[i]), float(self.line_wavelengths_nm[i]), sensor_distance_set)
            return
        lam_m, z = float(self.line_wavelengths_nm[i]) * 1e-9, float(z_line[i])
        blur_mm = 2.0 * self.aperture_radius_m * z * abs(float(defocus_per_m2[i])) * lam_m / np.pi * 1e3
        field_mm = lam_m * z / (cell / q) * 1e3
        lam0 = np.array([self.lens_design_wavelength_nm])
        f0 = float(self.lens.focal_lengths_m(lam0)[0])
        zo = self.object_distance_m
        z_focus = f0 if zo is None or zo <= f0 else 1.0 / (1.0 / f0 - 1.0 / zo)
        if sensor_distance_set:
            what = f"camera.sensor_distance_mm={self.sensor_distance_m * 1e3:g}"
        elif zo is not None:
            what = f"camera.object_distance_m={zo:g}"
        else:
            what = f"the {self.lens.model} lens's focus shift"
        obj = "object at infinity" if zo is None else f"object at {zo:g} m"
        q_need_f = q * float(ratio[i])
        if not q_need_f < 1e9:  # e.g. a sensor at 1e-300 mm: infinite defocus (int(inf) was a traceback)
            deliberate = "no pupil oversampling can represent a defocus this large"
        else:
            q_need = int(np.ceil(q_need_f - 1e-9))
            n_need = 2 * n_cells * q_need - 1  # about the FFT length that oversampling needs
            k_est = int(np.ceil(self.line_wavelengths_nm.max() * 1e-9 * float(z_line.max()) / (cell * self.pixel_m)))
            mem = psf_memory_estimate(PSFSampling(n_cells * q_need, cell / q_need, n_need, k_est, k_est, None, 1),
                                      self.line_wavelengths_nm * 1e-9, float(z_line.max()), self.pixel_m)
            if mem.total <= memory_budget_bytes():
                deliberate = f"for a deliberate defocus raise camera.psf.pupil_oversample to at least {q_need}"
            else:
                deliberate = (f"a deliberate defocus this large would need camera.psf.pupil_oversample >= {q_need}: "
                              f"an FFT of about {n_need} points per axis, {format_bytes(mem.total)} of memory")
        lens_facts = (f"focal length {f0 * 1e3:.4g} mm at {self.lens_design_wavelength_nm:g} nm, {obj}: "
                      f"the sensor belongs near {z_focus * 1e3:.4g} mm")
        blur = (f"the residual defocus blurs a point over {blur_mm:.3g} mm at {lam_m * 1e9:.4g} nm, wider than the "
                f"{field_mm:.3g} mm field λz/d that {cell / q * 1e6:.4g} µm pupil samples can represent, so the PSF "
                "would alias")
        if sensor_distance_set and not 0.5 * z_focus <= self.sensor_distance_m <= 2.0 * z_focus:
            # not a focus error but a wrong number (e.g. in another unit)
            raise ConfigError(f"{what} is implausible for this lens ({lens_facts}): {blur}; check the value "
                              f"(in mm), or {deliberate}")
        focus = (f"focus on the object (camera.sensor_distance_mm={z_focus * 1e3:.4g}), or "
                 if zo is not None and not sensor_distance_set else "")
        raise ConfigError(f"{what} defocuses the lens more than the pupil sampling can represent ({lens_facts}): "
                          f"{blur}; {focus}{deliberate}")

    def _warn_coarse_defocus(self, step_pi: float, lam_nm: float, sensor_distance_set: bool) -> None:
        """Warn (once per setting and process) that a residual defocus below the aliasing limit is still too coarse
        on the pupil grid for an accurate PSF: the defocus is constant over each pupil sample, and the PSF's error
        grows as the square of the phase step between samples at the aperture edge (``step_pi``, in π), about
        0.45·step² of relative L1 against a fine grid (tiny optics, no DOE, object at 0.1–0.4 m: steps 0.86 / 0.43
        / 0.21 → 33 / 9 / 2.5 %; the paper singlet's 17.7 waves at 420 nm are a step of 0.43: 8.9 %, documented)."""
        q = self.pupil_oversample
        q_need = int(np.ceil(q * step_pi / DEFOCUS_STEP_GOOD - 1e-9))
        if sensor_distance_set:
            what = f"camera.sensor_distance_mm={self.sensor_distance_m * 1e3:g}"
        elif self.object_distance_m is not None:
            what = f"camera.object_distance_m={self.object_distance_m:g}"
        else:
            what = f"the {self.lens.model} lens's focus shift"
        key = (what, q, round(step_pi, 2))
        if key in _COARSE_DEFOCUS_WARNED:
            return
        _COARSE_DEFOCUS_WARNED.add(key)
        log.warning("optics: %s leaves a residual defocus the pupil grid samples coarsely (a phase step of %.2fπ "
                    "between samples at the aperture edge at %.0f nm): its PSF is about %.0f %% off (relative L1, "
                    "light lost from the kernel), against 9 %% at 0.43π; raise camera.psf.pupil_oversample to %d "
                    "(memory and time grow as its square)", what, step_pi, lam_nm, 100 * DEFOCUS_L1_PER_STEP2 * step_pi ** 2,
                    q_need)

    @property
    def kernel_px(self) -> int:
        return self.sampling.kernel_px

    def pupil_heights(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """DOE heights on the pupil samples (m), (P, P): each cell repeated q×q."""
        return self.expand_cells(self.doe.heights(generator))

    def expand_cells(self, h_cells: torch.Tensor) -> torch.Tensor:
        """Cell heights (n, n) → pupil samples (n·q, n·q), in the optics' dtype and device."""
        q = self.pupil_oversample
        h = h_cells.to(self.amplitude)
        if q > 1:
            h = h.repeat_interleave(q, dim=0).repeat_interleave(q, dim=1)
        return h

    def psf_from_pupil(self, pupil_heights: torch.Tensor, defocus_delta_per_m2: torch.Tensor | None = None,
                       bands: slice | None = None) -> PSFResult:
        """PSF stack for given pupil heights (P, P) (m), optionally with an extra defocus per simulated
        wavelength (rad/m², (C·M,) for M = ``band_samples``, in ``line_wavelengths_nm`` order) and
        only for ``bands`` (a contiguous slice of band indices: a step is refused, since each band's
        ``band_samples`` wavelengths are selected as one run)."""
        if bands is not None and bands.step not in (None, 1):
            raise ValueError(f"psf_from_pupil: bands must be a contiguous slice (step 1), got {bands}: compute the "
                             "contiguous range and index its bands")
        m = self.band_samples
        sel = slice(None) if bands is None else slice(
            None if bands.start is None else bands.start * m, None if bands.stop is None else bands.stop * m)
        defocus = self.defocus_per_m2[sel]
        if defocus_delta_per_m2 is not None:
            delta = defocus_delta_per_m2.to(defocus)
            if delta.shape != self.defocus_per_m2.shape:
                raise ValueError(f"extra defocus must have one value per simulated wavelength "
                                 f"{tuple(self.defocus_per_m2.shape)}, got {tuple(delta.shape)}")
            defocus = defocus + delta[sel]
        line_w = None if m == 1 else self.line_weights[bands if bands is not None else slice(None)]
        return psf_stack(pupil_heights, self.amplitude, self.r2_m2, self.doe_phase_per_m[sel], defocus,
                         self.pixel_weights[sel], line_w)

    def forward(self, generator: torch.Generator | None = None) -> PSFResult:
        return self.psf_from_pupil(self.pupil_heights(generator))

    def aperture_per_cell(self) -> np.ndarray:
        """Aperture transmission (area fraction) per DOE cell, (n, n) float64."""
        n, q = self.doe.n_cells, self.pupil_oversample
        amp = self.amplitude.detach().cpu().double().numpy()
        return amp.reshape(n, q, n, q).mean(axis=(1, 3)) if q > 1 else amp

    def describe(self) -> dict:
        """Geometry, sampling and model facts (for psf.json and reports)."""
        smp = self.sampling
        lam0 = np.array([self.lens_design_wavelength_nm])
        lens = {
            "model": self.lens.model,
            "focal_length_mm": (self.focal_lengths_m * 1e3).tolist(),
            "sensor_distance_mm": self.sensor_distance_m * 1e3,
            "sensor_distance_from": f"rear principal plane H' at {self.lens_design_wavelength_nm:g} nm",
            "rear_principal_plane_mm": float(self.lens.rear_principal_plane_m(lam0)[0]) * 1e3,
            "rear_principal_plane_from": "rear vertex (negative: towards the object)",
            "sensor_distance_per_band_mm": (self.line_sensor_distances_m.reshape(len(self.bands), -1).mean(axis=1) * 1e3).tolist(),
            "object_distance_m": self.object_distance_m,
        }
        exact = smp.supersample is None
        return {
            "lens": lens,
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
            "model": {
                "pupil": "square cells, exact far field (cell-grid sum at the exact per-band pitch, "
                         "all orders inside the kernel, sinc^2 cell envelope)",
                "cells_exact": True,
                "pupil_oversample": self.pupil_oversample,
                "pupil_cell_um": round(smp.pupil_pitch_m * 1e6, 9),
                "pixel_integration": "exact" if exact else f"midpoint {smp.supersample}x{smp.supersample}",
                "band_samples": self.band_samples,
                "band_integration": "band centre only" if self.band_samples == 1 else
                    f"{self.band_samples} Gauss–Hermite wavelengths of each band's Gaussian (its FWHM), their weights",
                "approximations": [
                    "aperture: each pupil cell transmits uniformly the fraction of its area inside the circle",
                    "residual defocus phase sampled at each pupil cell's centre (constant over the cell)",
                    "scalar Fraunhofer diffraction, thin DOE",
                ],
                "normalization": "Parseval: each band's energy over the whole sensor plane is 1",
            },
            "sampling": {
                "supersample": smp.supersample,
                "nyquist_supersample": smp.nyquist_supersample,
                "pupil_oversample": self.pupil_oversample,
                "pupil_samples": smp.pupil_samples,
                "fft_size": smp.fft_size,
                "kernel_px": smp.kernel_px,
                "min_kernel_px": smp.min_kernel_px,
            },
        }
