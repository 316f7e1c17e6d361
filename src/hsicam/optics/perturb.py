"""Perturbed PSF stacks of a camera's optics: other cell heights, sensor-distance defocus, a DOE
shifted laterally on an oversampled pupil (pure functions; used by the tolerance sweeps)."""

from __future__ import annotations

import math

import numpy as np
import torch

from hsicam.optics.psf import PSFModel, PSFResult
from hsicam.optics.sampling import defocus_aliasing, smallest_kernel_px

# ------------------------------------------------------------------------------------------------
@torch.no_grad()
def psf_for_heights(optics, h_cells_m: torch.Tensor, defocus_delta: torch.Tensor | None = None):
    """:class:`~hsicam.optics.psf.PSFResult` of the camera's optics with cell heights ``h_cells_m``
    (n, n) (m) and optionally an extra defocus term per simulated wavelength (rad/m², (C·M,), M =
    ``optics.band_samples``; :func:`defocus_delta_per_m2`)."""
    return optics.psf_from_pupil(optics.expand_cells(h_cells_m), defocus_delta)


def nominal_heights(camera) -> torch.Tensor:
    """The trained design heights (m) per cell (n, n) float64, without fabrication noise."""
    with torch.no_grad():
        return camera.optics.doe.heights(noise=False).detach().cpu().double()


def design_heights(camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(heights m (n, n) float64 with the piston removed and 0 outside the aperture,
    aperture fraction (n, n) float64, removed piston m) of a :class:`~hsicam.cameras.DOECamera`.

    The heights are the DOE's effective design heights (its wrap/clamp/quantisation options
    applied) without fabrication noise.
    """
    aperture = camera.optics.aperture_per_cell()
    h = nominal_heights(camera).numpy()
    inside = aperture > 0
    piston = float(h[inside].min()) if inside.any() else 0.0
    h = np.where(inside, h - piston, 0.0)
    return h, aperture, piston


def defocus_delta_per_m2(optics, dz_m: float) -> torch.Tensor:
    """(π/λ)(1/(z_λ + Δz) − 1/z_λ) per simulated wavelength λ (rad/m²), float64 (C·M,): the band
    centres, or with ``band_samples`` M > 1 the M wavelengths over each band's FWHM at which the
    optics compute the PSF (``optics.line_wavelengths_nm``), so the added defocus matches the
    design defocus wavelength by wavelength. z_λ is the sensor's distance from the lens's rear
    principal plane at λ (``optics.line_sensor_distances_m``: a singlet's plane moves with λ), so
    the sum with ``optics.defocus_per_m2`` is the defocus of the optics built with the sensor Δz
    farther away (the PSF's scale, λ z_λ / pitch, is kept: a 1e-2 relative change at most)."""
    lam = np.asarray(optics.line_wavelengths_nm, dtype=np.float64) * 1e-9
    z = np.asarray(optics.line_sensor_distances_m, dtype=np.float64)
    return torch.as_tensor(math.pi / lam * (1.0 / (z + dz_m) - 1.0 / z), dtype=torch.float64)


def sensor_distance_aliasing(optics, dz_m: float) -> np.ndarray:
    """:func:`~hsicam.optics.sampling.defocus_aliasing` per simulated wavelength of the optics'
    residual defocus with the sensor moved by ``dz_m`` (the defocus that :func:`psf_for_heights`
    computes with :func:`defocus_delta_per_m2`), on the optics' own pupil grid (cell / q). Above 1
    the PSF aliases: the criterion :class:`~hsicam.optics.psf.PSFModel` refuses a config with."""
    total = optics.defocus_per_m2.detach().cpu().double().numpy() + defocus_delta_per_m2(optics, dz_m).numpy()
    return defocus_aliasing(total, optics.aperture_radius_m, optics.cell_m / optics.pupil_oversample)


def sensor_distance_limits_m(optics) -> tuple[float, float]:
    """(Δz_min ≤ 0, Δz_max ≥ 0) (m): the sensor distance errors whose residual defocus the optics'
    pupil grid represents (:func:`sensor_distance_aliasing` ≤ 1 at every wavelength); ``inf`` where
    no error on that side aliases (as far as the sensor can go). Closed form: with u_ℓ = 1/(z_ℓ + Δz)
    − 1/z_ℓ (z_ℓ: ``optics.line_sensor_distances_m``), simulated wavelength ℓ needs
    |c_ℓ + π u_ℓ/λ_ℓ| ≤ π/(2 a d) (``defocus_aliasing``); Δz falls as u_ℓ rises, so each wavelength
    bounds Δz on both sides and the range is the intersection."""
    c0 = optics.defocus_per_m2.detach().cpu().double().numpy()
    lam = np.asarray(optics.line_wavelengths_nm, dtype=np.float64) * 1e-9
    z = np.asarray(optics.line_sensor_distances_m, dtype=np.float64)
    limit = math.pi / (2.0 * optics.aperture_radius_m * optics.cell_m / optics.pupil_oversample)
    u_lo = (-limit - c0) * lam / math.pi  # (C·M,) the u_ℓ range each wavelength represents
    u_hi = (limit - c0) * lam / math.pi
    with np.errstate(divide="ignore"):
        # u > 0: the sensor nearer the lens; 1/z + u_lo <= 0: no distance on that side aliases
        dz_min = np.where(u_hi > 0, 1.0 / (1.0 / z + u_hi) - z, 0.0)
        dz_max = np.where(1.0 / z + u_lo <= 0, math.inf, np.where(u_lo < 0, 1.0 / (1.0 / z + u_lo) - z, 0.0))
    return float(dz_min.max()), float(dz_max.min())


def shift_fill(x: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """``x`` (H, W) moved by (dy, dx) samples (out[i, j] = x[i − dy, j − dx]), zeros entering."""
    out = torch.zeros_like(x)
    h, w = x.shape
    if abs(dy) >= h or abs(dx) >= w:
        return out
    ys, yd = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    xs, xd = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    out[yd, xd] = x[ys, xs]
    return out


def rebuilt_optics(optics, **changes) -> PSFModel:
    """A :class:`~hsicam.optics.psf.PSFModel` like ``optics`` (the same DOE module, lens and its design
    wavelength, aperture, cells, pixels, distances, kernel, sampling, band samples) with the keyword
    arguments in ``changes`` replaced, on the same device."""
    kwargs = dict(lens_design_wavelength_nm=optics.lens_design_wavelength_nm, sensor_distance_m=optics.sensor_distance_m,
                  object_distance_m=optics.object_distance_m, kernel_px=optics.kernel_px,
                  supersample=optics.sampling.supersample, pupil_oversample=optics.pupil_oversample,
                  band_samples=optics.band_samples)
    unknown = set(changes) - set(kwargs)
    if unknown:
        raise TypeError(f"rebuilt_optics: unknown changes {sorted(unknown)}")
    kwargs.update(changes)
    # a study of perturbed optics records how coarsely each samples its defocus (defocus_step_pi), in its own terms:
    # the camera's warning would name a config key the user never set
    return PSFModel(optics.bands, optics.lens, optics.doe, optics.aperture_radius_m, optics.cell_m, optics.pixel_m,
                    warn_coarse_defocus=False, **kwargs).to(device=optics.amplitude.device, dtype=optics.amplitude.dtype)


def defocus_step_pi(optics, dz_m: float = 0.0) -> float:
    """The largest residual-defocus phase step (in π) between neighbouring pupil samples at the aperture edge, over
    the simulated wavelengths, of ``optics`` with its sensor ``dz_m`` farther from the lens
    (:func:`~hsicam.optics.sampling.defocus_aliasing`): above :data:`~hsicam.optics.psf.DEFOCUS_STEP_WARN` the PSF
    is ≳ 11 % off (relative L1 ≈ 0.45·step²; docs/optics.md), above 1 it aliases."""
    lam_m = np.asarray(optics.line_wavelengths_nm, dtype=np.float64) * 1e-9
    z = np.asarray(optics.line_sensor_distances_m, dtype=np.float64) + float(dz_m)
    inv_zo = 0.0 if optics.object_distance_m is None else 1.0 / optics.object_distance_m
    c = np.pi / lam_m * (inv_zo + 1.0 / z - 1.0 / optics.lens.focal_lengths_m(optics.line_wavelengths_nm))
    return float(np.max(defocus_aliasing(c, optics.aperture_radius_m, optics.cell_m / optics.pupil_oversample)))


def oversampled_optics(optics, q: int) -> PSFModel:
    """The camera's optics (same DOE module, lens, aperture, sensor distance, kernel) with pupil
    oversampling ``q``: each DOE cell split into q×q samples."""
    return rebuilt_optics(optics, pupil_oversample=q)


@torch.no_grad()
def psf_sensor_moved(optics, h_cells_m: torch.Tensor, dz_m: float) -> PSFResult:
    """:class:`~hsicam.optics.psf.PSFResult` of the camera's optics with cell heights ``h_cells_m``
    (n, n) (m) and the sensor ``dz_m`` farther from the lens (negative: nearer), exactly: the optics
    rebuilt at sensor distance z + Δz, so every simulated wavelength gets its residual defocus
    (π/λ)(1/z_o + 1/(z_λ + Δz) − 1/f_λ) *and* its far-field scale λ(z_λ + Δz)/d (the PSF grows by
    Δz/z_λ; :func:`defocus_delta_per_m2` adds the defocus alone). The kernel stays the camera's K×K:
    where the moved sensor's far-field period needs a wider kernel, the PSF is computed on that one
    and its central K×K is kept, so ``energy`` reports the light that falls outside."""
    k = optics.kernel_px
    z = optics.sensor_distance_m + float(dz_m)
    lam_max = float(np.max(optics.line_wavelengths_nm)) * 1e-9
    z_far = float(np.max(optics.line_sensor_distances_m)) + float(dz_m)
    need = smallest_kernel_px(lam_max, z_far, optics.cell_m, optics.pixel_m)
    moved = rebuilt_optics(optics, sensor_distance_m=z, kernel_px=max(k, need))
    res = psf_for_heights(moved, h_cells_m)
    r = (moved.kernel_px - k) // 2
    psf = res.psf[..., r:r + k, r:r + k] if r else res.psf
    return PSFResult(psf, psf.sum(dim=(-2, -1)))


def shift_subsamples_for(optics, subsamples: int) -> int:
    """Sub-samples per cell Q used for the misalignment study: ``subsamples`` rounded up to a
    multiple of the camera's own pupil oversampling."""
    q = optics.pupil_oversample
    return q * max(1, math.ceil(subsamples / q))


@torch.no_grad()
def psf_shifted(fine_optics, h_cells_m: torch.Tensor, dy_cells: float, dx_cells: float) -> tuple[torch.Tensor, torch.Tensor, tuple[float, float]]:
    """PSF stack (C, K, K) of ``fine_optics`` (pupil oversampling Q, see :func:`oversampled_optics`)
    with the DOE relief moved by (dy, dx) cells — rounded to whole sub-samples, 1/Q cell — against
    the fixed aperture and lens; relief entering from outside the design reads height 0.
    Returns (psf float32, energy in the kernel (C,), the shift applied in cells). Bands are
    computed one at a time to bound memory."""
    big_q = fine_optics.pupil_oversample
    sy, sx = int(round(dy_cells * big_q)), int(round(dx_cells * big_q))
    h = shift_fill(fine_optics.expand_cells(h_cells_m), sy, sx)
    out, energy = [], []
    for c in range(len(fine_optics.bands)):
        res = fine_optics.psf_from_pupil(h, bands=slice(c, c + 1))
        out.append(res.psf[0])
        energy.append(res.energy[0])
    return torch.stack(out).float().cpu(), torch.stack(energy).cpu(), (sy / big_q, sx / big_q)
