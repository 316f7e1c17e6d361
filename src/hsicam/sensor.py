"""Sensor side of the camera: the periodic colour filter array and the noise models.

CFA (paper eq. 9): κ(x, y, λ) repeats with period m×m. Parameters (C, m, m), initialised uniform
random; every forward pass applies ReLU then normalises over λ so Σ_λ κ = 1 per pixel.
"No CFA" means κ = 1 for every band and pixel (the sensor then sums all bands).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch
from torch import nn

from hsicam.config import design_seed
from hsicam.optics.doe import straight_through
from hsicam.spectral import FWHM_PER_SIGMA

log = logging.getLogger(__name__)

_EPS = 1e-8


def cfa_tile(weights: torch.Tensor) -> torch.Tensor:
    """Filter transmissions from raw weights (C, m, m): ReLU, then Σ over bands = 1 per pixel.

    A pixel whose weights are all ≤ 0 (ReLU gives zeros) becomes a neutral filter, 1/C per band,
    so Σ κ = 1 holds everywhere.
    """
    t = torch.relu(weights)
    total = t.sum(dim=0, keepdim=True)
    return torch.where(total > _EPS, t / total.clamp_min(_EPS), torch.full_like(t, 1.0 / t.shape[0]))


def tile_pattern(tile: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Repeat a (C, m, m) tile periodically over a (C, height, width) sensor, origin at (0, 0)."""
    m_h, m_w = tile.shape[-2:]
    reps = (1, math.ceil(height / m_h), math.ceil(width / m_w))
    return tile.repeat(*reps)[:, :height, :width]


#: How the m² band-pass filters are placed over the tile: "random" (a seeded permutation) or
#: "dispersed" (:func:`dispersed_order`).
CFA_LAYOUTS = ("random", "dispersed")


def dispersed_order(period: int) -> torch.Tensor:
    """The ordered-dither (Bayer index) matrix of a power-of-two ``period``: (m, m) ints 0…m²−1.

    Placing the filter of spectral rank k where the matrix holds k spreads spectral neighbours
    as far apart as the tile allows: for m = 4 every 2×2 window of the periodic tile, aligned or
    not, holds one filter from each quarter of the spectrum, so each small neighbourhood samples
    the whole range (a random layout can put four red filters side by side).
    Recursion: B₁ = [[0]], B₂ₙ = [[4Bₙ, 4Bₙ + 2], [4Bₙ + 3, 4Bₙ + 1]].
    """
    m = int(period)
    if m < 1 or m & (m - 1):
        raise ValueError(f"a dispersed CFA layout needs a power-of-two period (1, 2, 4, 8, …), got {period}")
    b = torch.zeros(1, 1, dtype=torch.long)
    while b.shape[0] < m:
        b = torch.cat([torch.cat([4 * b, 4 * b + 2], dim=1), torch.cat([4 * b + 3, 4 * b + 1], dim=1)], dim=0)
    return b


def bandpass_weights(centers_nm: torch.Tensor, period: int, fwhm_nm: float, seed: int = 0,
                     layout: str = "random") -> torch.Tensor:
    """CFA weights (C, m, m) of m² Gaussian band-pass filters (FWHM ``fwhm_nm``) whose centre
    wavelengths spread evenly from the first to the last band centre, placed over the tile in a
    random (seeded) order, or with ``layout="dispersed"`` by :func:`dispersed_order` (tile
    position (i, j) gets the filter of spectral rank B[i, j]; ``seed`` is then unused).
    A small floor (1 % of the peak) keeps every band learnable."""
    lam = centers_nm.double()
    n = period * period
    # one filter (period 1): the middle of the range (linspace would put it on the first band, a blue edge filter)
    centres = (torch.linspace(float(lam[0]), float(lam[-1]), n, dtype=torch.float64) if n > 1 else
               torch.tensor([0.5 * (float(lam[0]) + float(lam[-1]))], dtype=torch.float64))
    if layout == "random":
        order = torch.randperm(n, generator=torch.Generator().manual_seed(design_seed(seed, "CFA seed")))
    elif layout == "dispersed":
        order = dispersed_order(period).reshape(-1)
    else:
        raise ValueError(f"unknown CFA layout {layout!r}; use one of {CFA_LAYOUTS}")
    sigma = fwhm_nm / FWHM_PER_SIGMA
    w = torch.exp(-0.5 * ((lam[:, None] - centres[order][None, :]) / sigma) ** 2)  # (C, m²)
    return (w + 0.01).float().reshape(len(lam), period, period)


class ColorFilterArray(nn.Module):
    """Learnable periodic CFA. ``enabled=False`` gives κ = 1 (no parameters).

    ``init``: "uniform" (paper: weights uniform in [0, 1)) or "bandpass" (:func:`bandpass_weights`,
    which needs ``centers_nm``, the band centres in nm, and places the filters by ``layout``).
    """

    def __init__(self, n_bands: int, period: int = 9, enabled: bool = True, seed: int = 0, init: str = "uniform",
                 centers_nm=None, bandpass_fwhm_nm: float = 40.0, layout: str = "random") -> None:
        super().__init__()
        seed = design_seed(seed, "CFA seed")
        self.n_bands, self.period, self.enabled = int(n_bands), int(period), bool(enabled)
        if self.enabled:
            if init == "uniform":
                g = torch.Generator().manual_seed(seed)
                w = torch.rand(self.n_bands, self.period, self.period, generator=g)
            elif init == "bandpass":
                if centers_nm is None or len(centers_nm) != self.n_bands:
                    raise ValueError("a band-pass CFA needs the centre wavelength of every band (centers_nm)")
                w = bandpass_weights(torch.tensor(np.asarray(centers_nm, dtype=np.float64)), self.period, bandpass_fwhm_nm, seed,
                                     layout)
            else:
                raise ValueError(f"unknown CFA init {init!r}; use 'uniform' or 'bandpass'")
            self.weights = nn.Parameter(w)
        else:
            self.register_buffer("weights", torch.ones(self.n_bands, 1, 1), persistent=False)

    def tile(self) -> torch.Tensor:
        """Transmission of one period, (C, m, m); ones (C, 1, 1) without a CFA."""
        return cfa_tile(self.weights) if self.enabled else self.weights

    def pattern(self, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """κ over a (C, height, width) window of the sensor whose top-left pixel is ``origin``."""
        tile = self.tile()
        shift = (-(origin[0] % tile.shape[-2]), -(origin[1] % tile.shape[-1]))
        if shift != (0, 0):
            tile = torch.roll(tile, shifts=shift, dims=(-2, -1))
        return tile_pattern(tile, height, width)

    def extra_repr(self) -> str:
        return f"n_bands={self.n_bands}, period={self.period}, enabled={self.enabled}"


def gaussian_noise(g: torch.Tensor, sigma: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """g + σ·N(0, 1), i.i.d. per pixel; σ on the sensor image's own scale (a fraction of full scale for the
    [0, 1] images the cameras give)."""
    if sigma <= 0:
        return g
    return g + sigma * torch.randn(g.shape, generator=generator, device=g.device, dtype=g.dtype)


#: The largest mean count (e⁻) drawn from a Poisson law; larger ones are taken as they are (√1e15 = 3e7 e⁻ of shot
#: noise is below float32's 6e7 e⁻ resolution of 1e15).
POISSON_MAX_E = 1e15


def poisson_gaussian_noise(
    g: torch.Tensor, full_well_e: float, read_noise_e: float, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Photon shot noise (signal 1.0 = ``full_well_e`` electrons) plus Gaussian read noise (e⁻),
    returned on the same [0, 1] scale. Straight-through gradient (identity) for training. The electrons are
    counted in float32 at least (a half-precision image tops out at 65504: a full well of 10⁵ e⁻ gave −inf)."""
    signal = g.detach()
    signal = signal.float() if signal.element_size() < 4 else signal
    rate = signal.clamp_min(0) * full_well_e
    # torch.poisson overflows int64 above ~9e18 e⁻ (a count of −9.2e18); above POISSON_MAX_E the shot noise
    # (√rate) is below the float's resolution of the rate, which is then the count
    electrons = torch.poisson(rate.clamp_max(POISSON_MAX_E), generator=generator)
    electrons = torch.where(rate > POISSON_MAX_E, rate, electrons)
    if read_noise_e > 0:
        electrons = electrons + read_noise_e * torch.randn(g.shape, generator=generator, device=g.device,
                                                           dtype=electrons.dtype)
    return straight_through(g, (electrons / full_well_e).to(g.dtype))


def quantize_bits(g: torch.Tensor, bits: int) -> torch.Tensor:
    """Clip to [0, 1] and round to 2^bits − 1 steps (an ADC); straight-through gradient."""
    levels = float(2**bits - 1)
    return straight_through(g, torch.round(g.clamp(0.0, 1.0) * levels) / levels)


class SensorNoise(nn.Module):
    """Noise and quantisation applied to the noiseless sensor image g = A(f).

    ``model``: "gaussian", "poisson_gaussian" (photon shot noise at ``full_well_e`` electrons for
    signal 1, read noise ``read_noise_e`` electrons) or "none". The Gaussian σ_s (``sigma``, on the
    [0, 1] image: the paper's sensor noise, :meth:`Camera.set_noise`'s ``sensor_sigma``) is added in
    every model when > 0, after the photon and read noise, before the quantisation (``bit_depth``).

    ``gain`` (H, W), optional: a per-pixel factor applied after the noise, as a flat-field correction
    multiplies a capture by 1/flat (vignetting); the image is then a·n(g/a), whose variance is
    a²·v(g/a) for the variance v of the uncorrected image (a Poisson–Gaussian capture: a·g/N + (a·r/N)²).
    ``gain_origin`` is the sensor pixel (row, column) of the map's top-left corner; a window's
    ``origin`` selects its part of the map (default: ``gain_origin``, the window :meth:`forward` takes
    an image to be). None: a = 1 everywhere.

    ``saturated`` (H, W) bool, optional: the pixels of one capture that the sensor clipped at its white level
    (:func:`hsicam.data.images.read_capture` with ``return_saturated``), placed at ``gain_origin`` as the gain map
    is (the same capture's); the measurement-consistency steps take the capture there as a lower bound only
    (:func:`hsicam.models.consistency.clipped_residual`). It describes a capture, not what :meth:`forward`
    simulates (which does not clip). None: no pixel clipped.
    """

    def __init__(self, model: str = "gaussian", sigma: float = 0.0, full_well_e: float = 1e4,
                 read_noise_e: float = 2.0, bit_depth: int | None = None, gain: torch.Tensor | None = None,
                 gain_origin: tuple[int, int] = (0, 0), saturated: torch.Tensor | None = None) -> None:
        super().__init__()
        if model not in ("none", "gaussian", "poisson_gaussian"):
            raise ValueError(f"unknown noise model {model!r}")
        self.model, self.sigma = model, float(sigma)
        self.full_well_e, self.read_noise_e, self.bit_depth = float(full_well_e), float(read_noise_e), bit_depth
        if gain is not None:
            gain = torch.as_tensor(gain, dtype=torch.float32)
            if gain.dim() != 2 or not bool(torch.isfinite(gain).all()) or not bool((gain > 0).all()):
                raise ValueError(f"the noise gain map must be (H, W), finite and positive, got {tuple(gain.shape)}")
        self.gain, self.gain_origin = gain, (int(gain_origin[0]), int(gain_origin[1]))
        self.saturated = None
        self.mark_saturated(saturated)

    def mark_saturated(self, saturated: torch.Tensor | None, origin: tuple[int, int] | None = None) -> None:
        """Set :attr:`saturated`, the clipped pixels of a capture ((H, W) bool, numpy or torch), at the sensor pixel
        ``origin`` of its top-left corner (None: :attr:`gain_origin`; a gain map, of the same capture, must be there
        already); None clears it (and leaves :attr:`gain_origin` where it is). ValueError for another shape or
        type, or a map that is not the gain map's size and place."""
        if saturated is None:
            self.saturated = None
            return
        saturated = torch.as_tensor(saturated)
        if saturated.dim() != 2 or saturated.dtype != torch.bool:
            raise ValueError(f"the saturated-pixel map must be (H, W) bool, got {tuple(saturated.shape)} of "
                             f"{saturated.dtype}")
        origin = self.gain_origin if origin is None else (int(origin[0]), int(origin[1]))
        if self.gain is not None and (saturated.shape != self.gain.shape or origin != self.gain_origin):
            raise ValueError(f"the saturated-pixel map ({tuple(saturated.shape)} px at {origin}) and the gain map "
                             f"({tuple(self.gain.shape)} px at {self.gain_origin}) are of one capture: give them its "
                             "size and place")
        self.saturated, self.gain_origin = saturated, origin

    def gain_window(self, g: torch.Tensor, origin: tuple[int, int] | None = None) -> torch.Tensor | None:
        """The part of :attr:`gain` under the window ``g`` (..., H, W) whose top-left sensor pixel is
        ``origin`` (None: :attr:`gain_origin`, as :meth:`forward`), as (H, W) on g's device; None without
        a gain map. ValueError for a window the map does not cover."""
        return self._window(self.gain, "noise gain map", g, origin)

    def saturated_window(self, g: torch.Tensor, origin: tuple[int, int] | None = None) -> torch.Tensor | None:
        """The part of :attr:`saturated` under the window ``g`` (..., H, W) at ``origin`` (as :meth:`gain_window`),
        (H, W) bool on g's device; None without the map. ValueError for a window the map does not cover."""
        return self._window(self.saturated, "saturated-pixel map", g, origin)

    def _window(self, m: torch.Tensor | None, name: str, g: torch.Tensor,
                origin: tuple[int, int] | None) -> torch.Tensor | None:
        """The part (H, W) of the capture's map ``m`` (placed at :attr:`gain_origin`) under the window ``g``
        (..., H, W) at the sensor pixel ``origin`` (None: :attr:`gain_origin`), on g's device; None for no map.
        ValueError, naming the map (``name``), for a window it does not cover."""
        if m is None:
            return None
        origin = self.gain_origin if origin is None else origin
        y, x = origin[0] - self.gain_origin[0], origin[1] - self.gain_origin[1]
        h, w = g.shape[-2:]
        if y < 0 or x < 0 or y + h > m.shape[0] or x + w > m.shape[1]:
            raise ValueError(f"the {h}×{w} px window at sensor pixel {tuple(origin)} is not within the {name} "
                             f"({m.shape[0]}×{m.shape[1]} px at {self.gain_origin})")
        return m[y : y + h, x : x + w].to(device=g.device)

    @classmethod
    def from_config(cls, s) -> "SensorNoise":  # s: hsicam.config.SensorConfig (camera.sensor)
        """The config's noise. ``noise: none`` with ``sigma`` > 0 stays noise-free, as it always imaged (a run saved
        so keeps its images and loads), with one warning: σ_s needs ``noise: gaussian`` or ``poisson_gaussian``."""
        sigma = s.sigma
        if s.noise == "none" and sigma > 0:
            log.warning("camera.sensor.sigma=%g is not applied: camera.sensor.noise=none is a noise-free sensor (set "
                        "camera.sensor.noise=gaussian for Gaussian noise σ_s, or sigma 0)", sigma)
            sigma = 0.0
        return cls(s.noise, sigma, s.full_well_e, s.read_noise_e, s.bit_depth)

    def forward(self, g: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The noisy image of ``g`` (B, 1, H, W), whose top-left pixel is the gain map's origin when
        there is one: a·n(g/a)."""
        a = self.gain_window(g)
        if a is not None:
            return a.to(g.dtype) * self._noisy(g / a.to(g.dtype), generator)
        return self._noisy(g, generator)

    def _noisy(self, g: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        if self.model == "poisson_gaussian":
            g = poisson_gaussian_noise(g, self.full_well_e, self.read_noise_e, generator)
        # σ_s in every model (it was applied by "gaussian" alone, so a σ_s set on a Poisson–Gaussian or
        # "none" camera, by ``evaluate --sensor-sigma`` or ``train.sensor_sigma``, was reported, never applied)
        g = gaussian_noise(g, self.sigma, generator)
        if self.bit_depth is not None:
            g = quantize_bits(g, self.bit_depth)
        return g

    @property
    def declares_noise(self) -> bool:
        """Whether :meth:`variance` gives a variance (False: a noise-free model, None)."""
        return self.sigma > 0 or self.model == "poisson_gaussian" or self.bit_depth is not None

    def variance(self, g: torch.Tensor, origin: tuple[int, int] | None = None) -> torch.Tensor | None:
        """Per-pixel variance of the noise this model adds to the noiseless image ``g`` (B, 1, H, W;
        1 = full scale), estimated from ``g`` itself (a noisy capture serves: its photon count is the
        mean's estimate): Poisson–Gaussian g / N + (r / N)² for N = ``full_well_e`` and
        r = ``read_noise_e``, plus σ_s², plus Δ²/12 of the quantiser's step Δ = 1 / (2^bits − 1); with a gain map
        a (the window at ``origin``; None: at :attr:`gain_origin`, the window :meth:`forward` noises),
        a²·v(g/a). None for a noise-free model (what the measurement-consistency steps take as "trust
        every residual"). Computed in float32 at least
        (half precision would round (2 / 10⁴)² and a 12-bit step's Δ²/12)."""
        if not self.declares_noise:
            return None
        g = g.detach()
        g = g.float() if g.element_size() < 4 else g
        a = self.gain_window(g, origin)
        if a is not None:
            a = a.to(g.dtype)
            return a * a * self._variance(g / a)
        return self._variance(g)

    def _variance(self, g: torch.Tensor) -> torch.Tensor:
        """:meth:`variance` of an image without a gain map (``declares_noise`` holds)."""
        var = None
        if self.model == "poisson_gaussian":
            var = g.clamp_min(0) / self.full_well_e + (self.read_noise_e / self.full_well_e) ** 2
        if self.sigma > 0:  # σ_s, independent of the photon and read noise
            var = torch.full_like(g, self.sigma**2) if var is None else var + self.sigma**2
        if self.bit_depth is not None:
            q = torch.full_like(g, (1.0 / (2**self.bit_depth - 1)) ** 2 / 12.0)
            var = q if var is None else var + q
        return var

    def extra_repr(self) -> str:
        gain = "" if self.gain is None else f", gain={tuple(self.gain.shape)} at {self.gain_origin}"
        if self.saturated is not None:
            gain += f", saturated={int(self.saturated.sum())} px at {self.gain_origin}"
        return f"model={self.model}, sigma={self.sigma}, bit_depth={self.bit_depth}{gain}"
