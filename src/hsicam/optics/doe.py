"""Diffractive optical element: a learnable height map h (m) on square cells.

Phase (paper eq. 7): φ_λ = 2π (n(λ) − 1) h / λ, with the real dispersion of the DOE material.
Optional, in this order: phase wrapping (h mod h_2π), height clamp to [0, max], L-level
quantization (straight-through gradient), fabrication noise σ_p (m of height, i.i.d. Gaussian
per cell, drawn on every forward pass while σ_p > 0).
"""

from __future__ import annotations

import math
import numpy as np
import torch
from torch import nn

from hsicam.config import design_seed
from hsicam.errors import ConfigError
from hsicam.spectral.materials import Material


def height_2pi_m(material: Material, wavelength_nm: float) -> float:
    """Height (m) that delays the phase by exactly 2π at ``wavelength_nm``: λ / (n(λ) − 1)."""
    return float(wavelength_nm * 1e-9 / (material.n(wavelength_nm) - 1.0))


def phase_per_height(material: Material, wavelength_nm: np.ndarray) -> np.ndarray:
    """2π (n(λ) − 1) / λ in rad/m, shape (C,): multiply by h (m) for the DOE phase."""
    lam = np.asarray(wavelength_nm, dtype=np.float64)
    return 2.0 * np.pi * (material.n(lam) - 1.0) / (lam * 1e-9)


def straight_through(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Value of ``y`` with the gradient of ``x`` (straight-through estimator): ``y + (x − x)`` with the second ``x``
    detached, whose value is ``y`` exactly (``x + (y − x)`` lost ``y`` to rounding where ``x`` is large: a sensor
    image of 1e9 clipped to 1 came out 0 in float32)."""
    return y + (x - x.detach())


def quantize_heights(h: torch.Tensor, levels: int, top_m: float, wrap: bool = True) -> torch.Tensor:
    """Round h to ``levels`` heights k·top/levels, k = 0..levels−1 (straight-through gradient).

    With ``top = h_2π`` these are the phase levels of an L-level (e.g. binary-weighted lithography)
    DOE, and ``wrap`` sends heights that round up to ``top`` (or lie above it) back modulo L (the
    same phase at the design wavelength), so the phase error there is at most π/L; at other
    wavelengths a wrapped height above h_2π is another element (dispersion). Without ``wrap`` (a
    height range that is not a phase period) heights are clamped to the top level (L−1)·top/L, so
    the error reaches a whole step just below ``top``.
    """
    step = top_m / levels
    k = torch.round(h / step)
    k = torch.remainder(k, levels) if wrap else torch.clamp(k, 0, levels - 1)
    q = k * step
    return straight_through(h, q)


def gaussian_lowpass_periodic(x: torch.Tensor, sigma_cells: float) -> torch.Tensor:
    """``x`` (H, W) convolved with a unit-sum Gaussian of std ``sigma_cells`` (cells), periodically
    (by FFT: the Gaussian's transfer function exp(−2π²σ²f²), f in cycles per cell)."""
    fy = torch.fft.fftfreq(x.shape[-2], dtype=x.dtype)[:, None]
    fx = torch.fft.rfftfreq(x.shape[-1], dtype=x.dtype)[None, :]
    # (σ f)², not σ² f²: σ ≳ 1e154 cells overflowed σ² (a Python OverflowError, the key unnamed), where (σ f)² is inf
    # away from f = 0 (transfer 0) and 0 at it (the mean kept): a constant field, which DOE refuses naming the key
    transfer = torch.exp(-2.0 * (math.pi * sigma_cells * torch.sqrt(fy**2 + fx**2)) ** 2)
    return torch.fft.irfft2(torch.fft.rfft2(x) * transfer, s=x.shape[-2:])


# Per-axis phase depth m (rad) at which a sinusoidal phase grating puts equal light into its 0th and
# each ±1st order: J0(m) = J1(m) (Jacobi–Anger: exp(i m sin θ) = Σₙ Jₙ(m) e^{inθ}), 30.0 % each.
EQUAL_ORDERS_DEPTH_RAD = 1.4346956508195650


def crossed_grating_heights_m(n_cells: int, period_cells: float, range_m: float) -> torch.Tensor:
    """Heights (m), (n_cells, n_cells) float64, of a crossed sinusoidal phase grating within [0, range_m]:
    h = range/4 · (2 + sin(2π x/Λ) + sin(2π y/Λ)), x, y the cell centres (cells) from the grid centre.

    At a wavelength whose full phase period is h_2π the per-axis phase depth is m = π·range/(2 h_2π), and the
    far field is a 3×3 (and fainter) array of orders (p, q) carrying J_p(m)² J_q(m)² of the light, the first
    orders shifted on the sensor by z·λ/(Λ·cell) (z the sensor distance): a spread whose size grows with λ,
    i.e. a dispersive spectral code, not only a blur."""
    if not (period_cells > 2 and math.isfinite(period_cells)):
        raise ValueError(f"a grating period must be a finite number of cells above 2 (2 or fewer per period "
                         f"sample a flat element), got {period_cells}")
    x = torch.arange(n_cells, dtype=torch.float64) - (n_cells - 1) / 2
    s = torch.sin(2.0 * math.pi * x / float(period_cells))
    return float(range_m) / 4.0 * (2.0 + s[:, None] + s[None, :])


class DOE(nn.Module):
    """Height map over ``n_cells``×``n_cells`` cells (m). ``enabled=False`` means h = 0, no parameters.

    Args:
        n_cells: cells across the pupil grid (odd).
        material: DOE material (refractive index).
        design_wavelength_nm: λ0 for h_2π.
        init: "random" (i.i.d. uniform in [0, init_range_m], default [0, h_2π]), "smooth" (a random
            field low-passed by a periodic Gaussian of σ = ``init_correlation_cells`` cells, rescaled
            to span [0, init_range_m] exactly: a structured, band-dependent diffuser), "grating" (a crossed
            sinusoidal phase grating of period ``init_grating_period_cells`` spanning [0, init_range_m],
            :func:`crossed_grating_heights_m`; default range: the depth of equal 0th and ±1st orders at λ0,
            2·m·h_2π/π with m = :data:`EQUAL_ORDERS_DEPTH_RAD`) or "zeros".
        max_height_m, wrap, quantization_levels, sigma_height_m: see module docstring.
    """

    def __init__(
        self,
        n_cells: int,
        material: Material,
        design_wavelength_nm: float = 587.6,
        enabled: bool = True,
        init: str = "random",
        seed: int = 0,
        max_height_m: float | None = None,
        wrap: bool = False,
        quantization_levels: int | None = None,
        sigma_height_m: float = 0.0,
        init_range_m: float | None = None,
        init_correlation_cells: float = 12.0,
        init_grating_period_cells: float = 55.0,
    ) -> None:
        super().__init__()
        seed = design_seed(seed, "DOE seed")
        self.n_cells = int(n_cells)
        self.material = material
        self.design_wavelength_nm = float(design_wavelength_nm)
        self.enabled = bool(enabled)
        self.max_height_m = max_height_m
        self.wrap = bool(wrap)
        self.quantization_levels = quantization_levels
        self.sigma_height_m = float(sigma_height_m)
        self.h2pi_m = height_2pi_m(material, design_wavelength_nm)
        if self.enabled:
            g = torch.Generator().manual_seed(int(seed))
            top = self.h2pi_m if init_range_m is None else float(init_range_m)
            if init == "random":
                h0 = torch.rand(self.n_cells, self.n_cells, generator=g, dtype=torch.float64) * top
            elif init == "smooth":
                white = torch.rand(self.n_cells, self.n_cells, generator=g, dtype=torch.float64)
                field = gaussian_lowpass_periodic(white, float(init_correlation_cells))
                span = float(field.max() - field.min())
                if not span > 1e-9 * float(field.abs().mean()):  # the low-pass left a constant: 0/0 below
                    raise ConfigError(f"camera.doe.init_correlation_cells={init_correlation_cells:g} is too wide for a "
                                      f"DOE of {self.n_cells} cells across: the smoothed field is constant (no "
                                      f"structure survives a Gaussian of σ ≳ 1.35 × the grid); use at most "
                                      f"{max(self.n_cells // 2, 1)} cells")
                h0 = (field - field.min()) / span * top
            elif init == "grating":
                if init_range_m is None:
                    top = 2.0 * EQUAL_ORDERS_DEPTH_RAD * self.h2pi_m / math.pi
                h0 = crossed_grating_heights_m(self.n_cells, init_grating_period_cells, top)
            elif init == "zeros":
                h0 = torch.zeros(self.n_cells, self.n_cells, dtype=torch.float64)
            else:
                raise ValueError(f"unknown DOE init {init!r}")
            self.height_m = nn.Parameter(h0.float())
        else:
            self.register_buffer("height_m", torch.zeros(self.n_cells, self.n_cells), persistent=False)

    def heights(self, generator: torch.Generator | None = None, *, noise: bool = True) -> torch.Tensor:
        """Effective heights (m), (n_cells, n_cells): constraints, quantization and (``noise``) the fabrication
        noise σ_p applied, drawn from ``generator``; ``noise=False``: the design, as exported and drawn."""
        h = self.height_m
        if not self.enabled:
            return h
        if self.wrap:
            h = torch.remainder(h, self.h2pi_m)
        if self.max_height_m is not None:
            h = straight_through(h, h.clamp(0.0, self.max_height_m))
        if self.quantization_levels is not None:
            top, wrap = self.level_grid()
            h = quantize_heights(h, self.quantization_levels, top, wrap=wrap)
        if noise and self.sigma_height_m > 0:
            h = h + self.sigma_height_m * torch.randn(h.shape, generator=generator, device=h.device, dtype=h.dtype)
        return h

    def level_grid(self) -> tuple[float, bool]:
        """(top m, wrap) of the L-level quantisation (:func:`quantize_heights`): L phase levels over
        h_2π, wrapping (a height above h_2π becomes its phase modulo 2π: exact at the design
        wavelength only), unless a clamp range that is not wrapped is set (``max_height_m`` with
        ``wrap`` false): L levels k·max/L, k = 0..L−1, clamped. Export (``hsicam export-optics``)
        quantises by the same rule, so an L-level trained element is exported unchanged."""
        clamp_range = self.max_height_m is not None and not self.wrap
        return (float(self.max_height_m), False) if clamp_range else (float(self.h2pi_m), True)

    def extra_repr(self) -> str:
        return (f"n_cells={self.n_cells}, enabled={self.enabled}, material={self.material!r}, "
                f"h_2pi={self.h2pi_m * 1e9:.1f} nm, sigma={self.sigma_height_m * 1e9:g} nm")
