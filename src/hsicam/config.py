"""Strict configuration: nested dataclasses loaded from YAML (``yaml.safe_load``).

Unknown keys and wrong types are errors (:class:`ConfigError`); keys carry their units
(``focal_length_mm``, ``pixel_pitch_um``, ``sigma_height_nm``). Defaults are the paper's camera.
Dotted overrides (``camera.doe.enabled=false``) are applied before validation, so they are
checked exactly like the file.

Every section is a dataclass below; to add a setting, add a typed field with a default and,
where a value can be meaningless, a check in that section's ``__post_init__``.
"""

from __future__ import annotations

import copy

import dataclasses
import math
import operator
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, Optional, Sequence, Union

import yaml

from hsicam.errors import ConfigError
from hsicam.spectral import Bands

#: The smallest ``data.patch_px``: the side of SSIM's window, which validation scores on every patch
#: (and ``train.ssim_loss`` on every training patch). It is :data:`hsicam.metrics.SSIM_WINDOW_PX`,
#: repeated because config sits below metrics in the package layers; test_config holds them equal.
MIN_PATCH_PX = 11


def _positive(section: str, **values: float | None) -> None:
    for name, v in values.items():
        if v is not None and not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"{section}.{name} must be a finite number > 0, got {v}")


#: The seeds every key and ``--seed`` option takes: [0, 2^32 - 1], where distinct seeds give distinct draws. torch's
#: CPU generator (``torch.Generator.manual_seed``) takes [-2^63, 2^64 - 1] but keeps only a seed's low 32 bits, so 0,
#: 2^32 and -2^64 seeded the same DOE, CFA and network while config.yaml recorded the seed asked for; numpy's
#: ``SeedSequence`` drops a seed's high zero words, so [10·2^32, 0] and [0, 10] gave one scene.
SEED_MIN, SEED_MAX = 0, 2**32 - 1
#: ``hsicam tolerance`` seeds its height-noise draw d (fewer than this stride) with seed·stride + d, a seed above too.
TOLERANCE_DRAW_STRIDE = 1000
TOLERANCE_SEED_MAX = (SEED_MAX - TOLERANCE_DRAW_STRIDE + 1) // TOLERANCE_DRAW_STRIDE


#: The most wavelengths ``camera.psf.band_samples`` averages per band (a huge count ended in numpy's "Maximum allowed
#: size exceeded", the key unnamed; within the bound the PSF sampling plan's memory check applies). 100 since session
#: 74: the Gauss–Hermite nodes of 371 or more overflow numpy's hermegauss (NaN PSFs, said by no check), and 15 already
#: averages the paper diffuser's band within 0.3 % (docs/optics.md).
MAX_BAND_SAMPLES = 100


#: The most epochs ``train.epochs`` (and ``hsicam finetune --epochs``) takes: 10^4 times the paper's 100. A count far
#: beyond it (2^70) was accepted and trained for ever, its progress line promising an end in 10^18 s.
MAX_EPOCHS = 10**6


#: The largest network learning rate ``train.lr`` (and ``hsicam finetune --lr``) takes: Adam moves every weight by about
#: the rate each step, so 1 is 10^3 to 10^4 times the presets' 1e-4 to 1e-3. Beyond about 3e37 the first step's
#: size (rate / (1 − β1)) left float32 and the fine-tuning ended in torch's "cannot be converted to type float
#: without overflow" traceback.
MAX_LR = 1.0


#: The most patches an epoch (``data.patches_per_epoch``, ``data.val_patches``) can have: the length of a
#: dataset, which Python's ``len`` holds in a signed 64-bit integer.
MAX_PATCHES = 2**63 - 1


def _power_text(n: int) -> str:
    """``n`` as ``2^k``, ``-2^k`` or ``2^k - 1`` when it is one of those (seed bounds), else its digits."""
    for m, tail in ((abs(n), ""), (n + 1, " - 1")):
        if m > 1024 and m & (m - 1) == 0:
            return f"{'-' if n < 0 else ''}2^{m.bit_length() - 1}{tail}"
    return str(n)


def seed_problem(value: Any, low: int = SEED_MIN, high: int = SEED_MAX) -> Optional[str]:
    """Why ``value`` cannot be a seed in [``low``, ``high``] ("must be …, got …"), or None when it can:
    the one seed check of the config and of the command line's ``--seed`` options."""
    if isinstance(value, bool) or not isinstance(value, int):
        return f"must be an integer, got {value!r}"
    if not low <= value <= high:
        shown = str(value) if value.bit_length() <= 128 else f"an integer of {value.bit_length()} bits"
        return f"must be an integer in [{_power_text(low)}, {_power_text(high)}], got {shown}"
    return None


def design_seed(value: Any, name: str) -> int:
    """``value`` as the seed of a design drawn from it (``name``, e.g. ``"DOE seed"``: the DOE's heights, a CFA, a
    coded aperture), else a :class:`ConfigError` "``name`` must be an integer in [0, 2^32 - 1], got …": the draws keep
    only a seed's low 32 bits (``torch.Generator.manual_seed``, the aperture's 32-bit hash), so a seed outside gave the
    design of another seed (2^32 that of 0, -1 that of 2^32 - 1). The config's keys are checked at load
    (:func:`_check_seeds`); this checks the classes built without a config. Integers of any kind (numpy's too)."""
    if not isinstance(value, bool):
        try:
            value = operator.index(value)
        except TypeError:
            pass
    problem = seed_problem(value)
    if problem is not None:
        raise ConfigError(f"{name} {problem}")
    return value


def _check_seeds(section: str, **values: Any) -> None:
    """ConfigError naming the first of ``values`` (seed keys of ``section``) outside [SEED_MIN, SEED_MAX]."""
    for name, v in values.items():
        problem = seed_problem(v)
        if problem is not None:
            raise ConfigError(f"{section}.{name} {problem}")


# --------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------
@dataclass
class BandsConfig:
    """Camera band grid: ``start_nm`` to ``stop_nm`` inclusive in steps of ``step_nm``."""

    start_nm: float = 420.0
    stop_nm: float = 720.0
    step_nm: float = 10.0
    fwhm_nm: Optional[float] = None  # None: equal to the step

    #: Config section the errors name.
    section: ClassVar[str] = "bands"

    def __post_init__(self) -> None:
        s = self.section
        _positive(s, start_nm=self.start_nm, stop_nm=self.stop_nm, step_nm=self.step_nm, fwhm_nm=self.fwhm_nm)
        if self.stop_nm < self.start_nm:
            raise ConfigError(f"{s}.stop_nm ({self.stop_nm}) is below {s}.start_nm ({self.start_nm})")
        span = self.stop_nm - self.start_nm + self.step_nm
        if self.fwhm_nm is not None and self.stop_nm > self.start_nm and self.fwhm_nm > 10 * span:
            raise ConfigError(f"{s}.fwhm_nm ({self.fwhm_nm:g} nm) is more than 10 times the range its bands cover "
                              f"({span:g} nm): every band would see every wavelength alike; check the value (in nm)")
        try:
            self.to_bands()
        except Exception as exc:  # noqa: BLE001 - re-raised as a config error with the key named
            raise ConfigError(f"{s}.start_nm, {s}.stop_nm, {s}.step_nm ({self.start_nm:g}, {self.stop_nm:g}, "
                              f"{self.step_nm:g}): {str(exc).removeprefix('Bands.uniform: ')}") from None

    def to_bands(self) -> Bands:
        return Bands.uniform(self.start_nm, self.stop_nm, self.step_nm, self.fwhm_nm)


#: The most height levels ``camera.doe.quantization_levels`` takes (16 bits; binary-weighted lithography usually
#: makes 2-256; ``hsicam export-optics`` writes the same range: :data:`LEVELS_RANGE`).
MAX_HEIGHT_LEVELS = 2**16
#: The level counts ``hsicam export-optics`` exports (``--levels``) and ``hsicam tolerance --levels`` sweeps: those
#: training takes (``camera.doe.quantization_levels``; level indices in 16 bits, one GDS mask per bit), and of them
#: the command line takes the powers of 2 alone (:func:`levels_problem`). Here, not in :mod:`hsicam.export.doe`,
#: so that the parser's checks load no torch.
LEVELS_RANGE = (2, MAX_HEIGHT_LEVELS)
#: How :func:`levels_problem` says the level counts it takes (the helps and the list option's refusal say it so).
LEVELS_RULE = f"a power of 2 in {LEVELS_RANGE[0]}..{LEVELS_RANGE[1]}"


def is_power_of_two(n: int) -> bool:
    """``n`` is 2^k with k >= 1 (a level count binary-weighted lithography makes: one mask per bit)."""
    return n >= 2 and (n & (n - 1)) == 0


def levels_problem(levels: Any) -> str | None:
    """Why ``levels`` is not a height-level count ``hsicam export-optics`` exports ("must be a power of 2 in
    2..65536 (binary-weighted lithography), got …"), or None when it is: the one rule of ``export-optics
    --levels``, ``tolerance --levels`` (:mod:`hsicam.cli.args`) and the tolerance study
    (:func:`hsicam.engine.tolerance.check_levels`)."""
    if not isinstance(levels, bool) and isinstance(levels, int):
        if LEVELS_RANGE[0] <= levels <= LEVELS_RANGE[1] and is_power_of_two(levels):
            return None
    return f"must be {LEVELS_RULE} (binary-weighted lithography), got {levels!r}"
#: The largest DOE fabrication height noise σ_p (nm; ``camera.doe.sigma_height_nm``, ``train.sigma_height_nm``,
#: ``evaluate`` / ``tolerance --sigma-height-nm``): 1 mm, thousands of times any element's relief (a few µm), where
#: the phase is already uniformly random; far larger ones overflowed the float32 heights and ended in a
#: 'sensor contains NaN or Inf' refusal that named no option. The same bound holds camera.doe.max_height_nm and
#: init_range_nm.
MAX_SIGMA_HEIGHT_NM = 1e6


def _check_material_name(key: str, material: str) -> None:
    """ConfigError unless ``material`` names a material :func:`hsicam.spectral.materials.get_material`
    reads: ``fused_silica`` or a ``wavelength_nm,n`` CSV file."""
    if not (material == "fused_silica" or str(material).lower().endswith(".csv")):
        raise ConfigError(f"{key}: unknown material {material!r}: use 'fused_silica' or a path to a CSV file "
                          "(wavelength_nm,n)")


def _check_material_range(key: str, material: str, what: str, low_nm: float, high_nm: float) -> None:
    """ConfigError naming ``key`` when the built-in ``material`` has no refractive index over
    [``low_nm``, ``high_nm``] (``what`` says which wavelengths those are). A CSV table's range is
    checked when it is read (its file is not opened here)."""
    if material != "fused_silica":
        return
    from hsicam.spectral.materials import FusedSilica

    lo, hi = FusedSilica.RANGE_NM
    if low_nm < lo or high_nm > hi:
        shown = f"{low_nm:g} nm" if low_nm == high_nm else f"{low_nm:g}-{high_nm:g} nm"
        raise ConfigError(f"{key}: fused silica's Sellmeier formula holds for {lo:g}-{hi:g} nm, but {what} "
                          f"{'span' if low_nm != high_nm else 'is'} {shown}")


@dataclass
class LensConfig:
    """Refractive lens. ``achromatic``: f(λ) = focal_length_mm for every band (paper, under eq. 6).
    ``singlet``: plano-convex, f(λ) = R / (n(λ) - 1) (focal_length_mm is not used)."""

    model: Literal["achromatic", "singlet"] = "achromatic"
    focal_length_mm: float = 35.0
    radius_of_curvature_mm: float = 16.0
    center_thickness_mm: float = 2.0
    material: str = "fused_silica"
    design_wavelength_nm: float = 587.6  # the sensor sits at f(design wavelength)

    def __post_init__(self) -> None:
        _positive(
            "camera.lens",
            focal_length_mm=self.focal_length_mm,
            radius_of_curvature_mm=self.radius_of_curvature_mm,
            center_thickness_mm=self.center_thickness_mm,
            design_wavelength_nm=self.design_wavelength_nm,
        )
        # the name is checked whatever the model (a typo is caught before the day it matters); the singlet reads it
        _check_material_name("camera.lens.material", self.material)

    def design_focal_length_mm(self) -> float:
        """f at ``design_wavelength_nm`` (mm): ``focal_length_mm`` (achromatic) or R / (n(λ0) − 1)
        (singlet), what :func:`hsicam.optics.lens.lens_from_config` builds (test_config holds them equal)."""
        if self.model == "achromatic":
            return self.focal_length_mm
        from hsicam.spectral.materials import get_material

        try:
            n = float(get_material(self.material).n(self.design_wavelength_nm))
        except (ValueError, OSError) as exc:  # an unknown material or an unreadable table (InputError)
            raise ConfigError(f"camera.lens.material: {exc}") from None
        return self.radius_of_curvature_mm / (n - 1.0)


@dataclass
class DOEConfig:
    """Diffractive optical element: a height map on square cells inside the circular aperture."""

    enabled: bool = True  # false: h = 0 (the "no DOE" ablation)
    cell_size_um: float = 30.0
    material: str = "fused_silica"
    design_wavelength_nm: float = 587.6  # h_2π = λ0 / (n(λ0) - 1)
    init: Literal["random", "smooth", "grating", "zeros"] = "random"  # random: i.i.d. uniform in [0, init_range_nm]
    init_range_nm: Optional[float] = None  # None: h_2π(λ0) (a full-phase diffuser); grating: equal 0th/±1st orders
    init_correlation_cells: float = 12.0  # init smooth: σ (cells) of the Gaussian low-pass, then [0, range]
    # init grating: period Λ (cells) of a crossed sinusoidal phase grating; its ±1st orders land z·λ/(Λ·cell) from
    # the centre: 55 cells of 30 µm behind the paper's 35 mm lens: 2.0 px of 6 µm at 570 nm (1.5 px at 420, 2.5 at 720)
    init_grating_period_cells: float = 55.0
    seed: int = 0
    max_height_nm: Optional[float] = None  # clamp heights to [0, max] (straight-through gradient)
    wrap: bool = False  # wrap heights modulo h_2π (phase wrapping)
    quantization_levels: Optional[int] = None  # L levels over [0, h_2π] (straight-through gradient)
    sigma_height_nm: float = 0.0  # fabrication noise, i.i.d. Gaussian per cell, per forward pass (validation and
    # evaluation; training draws its level per step from train.sigma_height_nm)

    def __post_init__(self) -> None:
        _positive("camera.doe", cell_size_um=self.cell_size_um, design_wavelength_nm=self.design_wavelength_nm,
                  max_height_nm=self.max_height_nm, init_range_nm=self.init_range_nm,
                  init_correlation_cells=self.init_correlation_cells)
        _check_seeds("camera.doe", seed=self.seed)
        if not (self.init_grating_period_cells > 2 and math.isfinite(self.init_grating_period_cells)):
            raise ConfigError(f"camera.doe.init_grating_period_cells must be a finite number of cells above 2 (a "
                              f"sinusoid sampled at 2 cells or fewer per period leaves the DOE flat), got "
                              f"{self.init_grating_period_cells:g}")
        if self.quantization_levels is not None and not 2 <= self.quantization_levels <= MAX_HEIGHT_LEVELS:
            raise ConfigError(f"camera.doe.quantization_levels must be in [2, {MAX_HEIGHT_LEVELS}] (height levels of "
                              f"the lithography), got {self.quantization_levels}")
        _check_material_name("camera.doe.material", self.material)
        if not (self.sigma_height_nm >= 0 and math.isfinite(self.sigma_height_nm)):
            raise ConfigError(f"camera.doe.sigma_height_nm must be >= 0, got {self.sigma_height_nm}")
        if self.sigma_height_nm > MAX_SIGMA_HEIGHT_NM:
            raise ConfigError(f"camera.doe.sigma_height_nm must be at most {MAX_SIGMA_HEIGHT_NM:.0f} nm (1 mm, far beyond any "
                              f"DOE's relief), got {self.sigma_height_nm:g}")
        for key in ("max_height_nm", "init_range_nm"):  # 1e300 nm overflowed the float32 heights (a torch
            value = getattr(self, key)  # RuntimeError, or NaN PSFs and a traceback in their plot)
            if value is not None and value > MAX_SIGMA_HEIGHT_NM:
                raise ConfigError(f"camera.doe.{key} must be at most {MAX_SIGMA_HEIGHT_NM:.0f} nm (1 mm, far beyond "
                                  f"any DOE's relief), got {value:g}")


@dataclass
class PSFConfig:
    """PSF model (DESIGN.md §1, docs/optics.md): exact for square DOE cells."""

    kernel_px: Optional[int] = None  # odd; at least λ_max·z/Δ in pixels (141 for the paper optics); None: that minimum
    supersample: Optional[int] = None  # None: exact pixel integration; odd s: s×s midpoint rule (1: point values)
    pupil_oversample: int = 1  # q sub-cells per DOE cell: finer aperture edge and defocus (q² cost)
    band_samples: int = 1  # Gauss–Hermite wavelengths per band, over its Gaussian (1: band centre; 3: ~3× cost)

    def __post_init__(self) -> None:
        if self.kernel_px is not None and (self.kernel_px < 1 or self.kernel_px % 2 == 0):
            raise ConfigError(f"camera.psf.kernel_px must be a positive odd number, got {self.kernel_px}")
        if self.supersample is not None and (self.supersample < 1 or self.supersample % 2 == 0):
            raise ConfigError(f"camera.psf.supersample must be a positive odd number, got {self.supersample}")
        if self.pupil_oversample < 1:
            raise ConfigError(f"camera.psf.pupil_oversample must be >= 1, got {self.pupil_oversample}")
        if not 1 <= self.band_samples <= MAX_BAND_SAMPLES:  # each sample is a whole PSF stack of the bands
            raise ConfigError(f"camera.psf.band_samples must be 1 to {MAX_BAND_SAMPLES} (wavelengths averaged per band, "
                              f"each one a PSF per band; 3 is ~3× the cost), got {self.band_samples}")


@dataclass
class CFAConfig:
    """Periodic colour filter array, m×m×C parameters (paper eq. 9). ``enabled: false``: κ = 1."""

    enabled: bool = True
    period: int = 9
    seed: int = 0
    # uniform: weights uniform in [0, 1) (paper; nearly flat filters). bandpass (beyond the paper):
    # m² Gaussian band-pass filters whose centres spread evenly over the band range, in a
    # seeded random layout, so the sensor carries spectral contrast from the first step.
    init: Literal["uniform", "bandpass"] = "uniform"
    bandpass_fwhm_nm: float = 40.0
    # Placement of the band-pass filters over the tile: random (seeded) or dispersed (ordered
    # dither: spectral neighbours spread apart, every 2x2 window of a 4x4 tile sees each quarter of
    # the spectrum; power-of-two periods only; hsicam.sensor.dispersed_order).
    layout: Literal["random", "dispersed"] = "random"

    def __post_init__(self) -> None:
        if self.period < 1:
            raise ConfigError(f"camera.cfa.period must be >= 1, got {self.period}")
        _positive("camera.cfa", bandpass_fwhm_nm=self.bandpass_fwhm_nm)
        _check_seeds("camera.cfa", seed=self.seed)
        if self.layout == "dispersed":
            if self.init != "bandpass":
                raise ConfigError("camera.cfa.layout: dispersed places band-pass filters; it needs camera.cfa.init: bandpass")
            if self.period & (self.period - 1):
                raise ConfigError(f"camera.cfa.layout: dispersed needs a power-of-two camera.cfa.period (2, 4, 8, …), got {self.period}")


#: The largest Gaussian σ of the sensor noise, on the image scaled to full scale 1 (``camera.sensor.sigma``,
#: ``train.sensor_sigma``): noise above the full scale buries any signal (σ = 1e30 trained a flat network silently).
MAX_SENSOR_SIGMA = 1.0
#: The most electrons ``camera.sensor.full_well_e`` takes: 10⁶ times any sensor's full well, where the shot noise (σ 1e-6
#: of full scale) is below a float32 image's resolution; far more (1e20) overflowed torch.poisson's int64 count into a
#: negative, constant image, silently. The fewest is 1 (a full scale of less than one electron counts no photon; 1e-300
#: made the image infinite).
MIN_FULL_WELL_E, MAX_FULL_WELL_E = 1.0, 1e12


@dataclass
class SensorConfig:
    """Monochrome sensor: pixel pitch, noise model and optional bit depth."""

    pixel_pitch_um: float = 6.0
    noise: Literal["none", "gaussian", "poisson_gaussian"] = "gaussian"
    sigma: float = 0.0  # Gaussian σ_s on the [0, 1]-scaled image (gaussian; added to poisson_gaussian's noise too);
    # validation and evaluation: training draws its σ_s per step from train.sensor_sigma
    full_well_e: float = 10000.0  # poisson_gaussian: electrons at signal 1.0
    read_noise_e: float = 2.0  # poisson_gaussian: read noise σ in electrons
    bit_depth: Optional[int] = None  # quantise to 2^bits levels over [0, 1] (clipping)

    def __post_init__(self) -> None:
        _positive("camera.sensor", pixel_pitch_um=self.pixel_pitch_um, full_well_e=self.full_well_e)
        if not (0 <= self.sigma <= MAX_SENSOR_SIGMA):
            raise ConfigError(f"camera.sensor.sigma must be in [0, {MAX_SENSOR_SIGMA:g}] (σ of the image scaled to full "
                              f"scale 1; more buries any signal), got {self.sigma}")
        if not MIN_FULL_WELL_E <= self.full_well_e <= MAX_FULL_WELL_E:
            raise ConfigError(f"camera.sensor.full_well_e must be in [{MIN_FULL_WELL_E:g}, {MAX_FULL_WELL_E:g}] (electrons "
                              f"at full scale; sensors hold 10^3 to 10^6), got {self.full_well_e:g}")
        if self.read_noise_e < 0:
            raise ConfigError(f"camera.sensor.read_noise_e must be >= 0, got {self.read_noise_e}")
        if self.read_noise_e > MAX_SENSOR_SIGMA * self.full_well_e:  # σ above the full scale, as camera.sensor.sigma
            raise ConfigError(f"camera.sensor.read_noise_e must be at most camera.sensor.full_well_e ({self.full_well_e:g} "
                              f"e-: read noise above the full scale buries any signal), got {self.read_noise_e:g}")
        if self.bit_depth is not None and not (1 <= self.bit_depth <= 32):
            raise ConfigError(f"camera.sensor.bit_depth must be in 1..32, got {self.bit_depth}")


#: The smallest ``camera.cassi.mask_density``: a coded aperture opens 10-90 % of its cells (0.5 as the paper's
#: baselines); at 10^-3 a 64 px training patch still sees about 4 open cells. The random aperture's uniform values are
#: multiples of 2^-32, so a density below that (1e-300) closed every cell: CASSI trained on an all-zero sensor, silently.
MIN_MASK_DENSITY = 1e-3


@dataclass
class CASSIConfig:
    """Coded-aperture cameras (DD-CASSI, SD-CASSI) used as baselines (see hsicam.cameras.cassi)."""

    mask_seed: int = 0  # random binary coded aperture drawn from this seed
    mask_file: Optional[str] = None  # or a coded aperture from a .npy file (H, W), values in [0, 1]
    mask_density: float = 0.5  # random aperture: fraction of open (transmitting) pixels
    shift_px: float = 2.0  # dispersion per band in pixels (linear dispersion; rounded per band)
    dispersion: Literal["linear", "prism"] = "linear"  # prism: thin-prism shifts from n(λ) of the prism
    prism_material: str = "fused_silica"  # "fused_silica" or a wavelength_nm,n CSV file
    prism_apex_deg: float = 30.0  # thin-prism apex angle α: deviation (n(λ) - 1)·α
    prism_focal_length_mm: float = 50.0  # lens after the prism: shift = f·tan(Δdeviation) / pixel pitch
    convention: Literal["sum", "mean"] = "mean"  # sum over bands (MST) or mean over bands

    def __post_init__(self) -> None:
        _positive("camera.cassi", shift_px=self.shift_px, prism_apex_deg=self.prism_apex_deg,
                  prism_focal_length_mm=self.prism_focal_length_mm)
        _check_seeds("camera.cassi", mask_seed=self.mask_seed)
        if not (0.0 < self.mask_density <= 1.0):
            raise ConfigError(f"camera.cassi.mask_density must be in (0, 1], got {self.mask_density}")
        if self.mask_density < MIN_MASK_DENSITY:
            raise ConfigError(f"camera.cassi.mask_density={self.mask_density:g} leaves the coded aperture (almost) closed: "
                              f"it must be at least {MIN_MASK_DENSITY:g} (the fraction of open cells; 0.5 is usual)")
        if self.prism_apex_deg >= 90.0:
            raise ConfigError(f"camera.cassi.prism_apex_deg must be below 90, got {self.prism_apex_deg}")
        if self.mask_file is not None and not self.mask_file.lower().endswith(".npy"):
            raise ConfigError(f"camera.cassi.mask_file must be a .npy file, got {self.mask_file!r}")


@dataclass
class CameraConfig:
    """The camera: ``kind: doe`` is the paper's lens + DOE + CFA + sensor; the CASSI kinds are the
    baselines (they use ``cassi`` and ``sensor``; the optics sections are then ignored)."""

    kind: str = "doe"  # a registered camera kind (hsicam.cameras.registry): doe, dd_cassi, sd_cassi
    aperture_radius_mm: float = 5.0
    sensor_distance_mm: Optional[float] = None  # None: the lens focal length at its design wavelength
    object_distance_m: Optional[float] = None  # None: object at infinity
    boundary: Literal["valid", "same"] = "valid"  # valid: scene larger than sensor by the kernel margin
    padding: Literal["zeros", "reflect", "replicate", "circular"] = "zeros"  # for boundary=same
    lens: LensConfig = field(default_factory=LensConfig)
    doe: DOEConfig = field(default_factory=DOEConfig)
    psf: PSFConfig = field(default_factory=PSFConfig)
    cfa: CFAConfig = field(default_factory=CFAConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    cassi: CASSIConfig = field(default_factory=CASSIConfig)

    def __post_init__(self) -> None:
        _positive("camera", aperture_radius_mm=self.aperture_radius_mm, sensor_distance_mm=self.sensor_distance_mm,
                  object_distance_m=self.object_distance_m)
        self._check_object_distance()
        if self.doe.cell_size_um * 1e-3 > 2 * self.aperture_radius_mm:
            raise ConfigError(
                f"camera.doe.cell_size_um ({self.doe.cell_size_um} µm) is larger than the aperture diameter "
                f"({2 * self.aperture_radius_mm} mm, 2 × camera.aperture_radius_mm)"
            )

    def _check_object_distance(self) -> None:
        """ConfigError for an object at or inside the lens's focal length (at its design wavelength):
        1/z_i = 1/f − 1/z_o has no positive image distance z_i, so the object forms no real image."""
        zo_m = self.object_distance_m
        if zo_m is None:
            return
        f_mm = self.lens.design_focal_length_mm()
        if zo_m * 1e3 <= f_mm:
            raise ConfigError(
                f"camera.object_distance_m={zo_m:g} is not beyond the lens's focal length ({f_mm:.4g} mm at "
                f"{self.lens.design_wavelength_nm:g} nm): an object at or inside it forms no real image; set it above "
                f"{f_mm * 1e-3:.4g} m (in metres), or null for an object at infinity")


@dataclass
class RDNConfig:
    """The paper's network (``model.kind: rdn``): tentative 1×1 conv + RDN. See ``hsicam.models.rdn``."""

    blocks: int = 8  # D, residual dense blocks
    features: int = 64  # G0
    growth: int = 32  # G
    layers_per_block: int = 4  # C (paper: 4)
    # Beyond the paper: also feed the network a per-band demosaic of g (C extra channels: the
    # average of g over one CFA period weighted by each pixel's transmission of the band), and
    # start the tentative reconstruction from it. The paper's network gets g alone and has to
    # infer the CFA's phase from the image. DOE camera only. See hsicam.models.demosaic.
    demosaic_input: bool = False
    # Beyond the paper, for cameras without a CFA (CASSI): feed the back-projection Aᵀy ⊘ AᵀA𝟙 (C
    # channels: the measurement in the bands each pixel's code lets through) instead of g, and start
    # the tentative reconstruction from it. Without it a network reading g alone cannot know the code
    # at a pixel, and a CASSI measurement cannot be decoded.
    backprojection_input: bool = False

    def __post_init__(self) -> None:
        if self.demosaic_input and self.backprojection_input:
            raise ConfigError("model.rdn: demosaic_input and backprojection_input are alternatives; set one")
        for k in ("blocks", "features", "growth", "layers_per_block"):
            if getattr(self, k) < 1:
                raise ConfigError(f"model.rdn.{k} must be >= 1, got {getattr(self, k)}")


#: The widest window (px) of the networks' box / tent means and of a stage's PSF cut: wider than any sensor; a window of
#: 2^31 + 1 px ended in torch's "value cannot be converted to type int without overflow" (the key unnamed), and
#: 2^70 + 1 in avg_pool2d's "Overflow when unpacking long long".
MAX_WINDOW_PX = 32767


def _check_odd_window(section: str, key: str, value: int, zero: str) -> None:
    """ConfigError unless ``value`` (``section``.``key``, a window's width in px) is odd and at most
    :data:`MAX_WINDOW_PX`, or 0 (meaning ``zero``)."""
    if value < 0 or (value and value % 2 == 0):
        raise ConfigError(f"{section}.{key} must be odd (or {zero}), got {value}")
    if value > MAX_WINDOW_PX:
        raise ConfigError(f"{section}.{key} must be at most {MAX_WINDOW_PX} px (wider than any sensor), got {value}")


def _check_brightness(section: str, window: int, eps: float) -> None:
    """ConfigError unless ``section``.brightness_window is 0 (off) or odd and ``section``.brightness_eps > 0
    (the local-brightness normalisation of the mosaic and unrolled networks)."""
    _check_odd_window(section, "brightness_window", window, "0 for off")
    if not (eps > 0 and math.isfinite(eps)):
        raise ConfigError(f"{section}.brightness_eps must be > 0, got {eps}")


@dataclass
class MosaicConfig:
    """Settings of ``model.kind = mosaic`` (sizes in channels / layers; lengths in sensor pixels)."""

    features: int = 128  # channels of the residual blocks at 1/m resolution
    blocks: int = 10  # residual blocks (two 3×3 convs each) at 1/m resolution
    factor: int = 0  # space-to-depth factor (px); 0 = the camera's CFA period (3 without a CFA); a multiple of the period
    head_features: int = 32  # channels of the full-resolution refinement head
    head_layers: int = 3  # 3×3 convs of the head at full resolution (0: no head)
    detail_features: int = 0  # trunk features passed per pixel to the head (pixel-shuffled), with g − κ·x̃; 0 = off
    mid_features: int = 0  # channels of a half-resolution stage between the trunk and the head; 0 = off (factor must be even)
    mid_blocks: int = 2  # residual blocks (two 3×3 convs each) of the half-resolution stage; unused while mid_features is 0
    demosaic_window: int = 0  # width (px, odd) of the demosaic skip; 0 = the CFA period rounded up to odd (box), 2·period − 1 (tent)
    # weights of the demosaic skip: box (flat) or tent (separable triangle: the weighted-bilinear MSFA demosaic)
    demosaic_kernel: Literal["box", "tent"] = "box"
    brightness_window: int = 0  # local-brightness normalisation: box width (px, odd) of b = box(g) + ε; 0 = off
    brightness_eps: float = 1.0e-3  # ε of b (sensor units; full scale 1)

    # No __post_init__: this section sits at two places (model.mosaic, model.unrolled.mosaic), and an
    # error must name the one the user set. Its owner (ModelConfig, UnrolledConfig) runs check() with
    # the section's name as the config loads; build_mosaic runs it again for a hand-made MosaicConfig.
    def check(self, section: str) -> None:
        """ConfigError naming ``section``.KEY for a value meaningless on any camera; the checks that
        need the camera (factor a multiple of the CFA period, an even factor for mid_features=0's
        default) are build_mosaic's."""
        for key in ("features", "blocks"):
            if getattr(self, key) < 1:
                raise ConfigError(f"{section}.{key} must be >= 1, got {getattr(self, key)}")
        for key in ("factor", "head_layers", "detail_features", "mid_features", "mid_blocks"):
            if getattr(self, key) < 0:
                raise ConfigError(f"{section}.{key} must be >= 0, got {getattr(self, key)}")
        if self.head_layers > 1 and self.head_features < 1:
            raise ConfigError(f"{section}.head_features must be >= 1 with {section}.head_layers={self.head_layers}, "
                              f"got {self.head_features}")
        if self.detail_features and not self.head_layers:
            raise ConfigError(f"{section}.detail_features={self.detail_features} needs a head: set "
                              f"{section}.head_layers >= 1 (or detail_features=0)")
        if self.mid_features and self.factor % 2:
            raise ConfigError(f"{section}.mid_features={self.mid_features} (a half-resolution stage) needs an even "
                              f"{section}.factor, got {self.factor}; set {section}.factor to an even multiple of the "
                              f"CFA period or mid_features=0")
        _check_odd_window(section, "demosaic_window", self.demosaic_window, "0 for the CFA period")
        _check_brightness(section, self.brightness_window, self.brightness_eps)


#: The largest ``model.unrolled.step_init`` (α·L): 50 times the bound 2 below which a step decreases the data term;
#: the step's softplus⁻¹ overflowed above ~709 (a Python OverflowError as the network was built, the key unnamed).
MAX_STEP_INIT = 100.0


@dataclass
class UnrolledConfig:
    """Settings of ``model.kind = unrolled`` (sizes in channels / layers; lengths in sensor pixels)."""

    stages: int = 2  # K: gradient step + prior, repeated
    init: str = "auto"  # x⁰: auto (demosaic with a CFA, else backprojection), demosaic, backprojection, mosaic
    step: str = "gradient"  # data step: gradient (any camera) or gap (cameras with a diagonal ΦΦᵀ: CASSI)
    share_weights: bool = False  # one prior for all stages (else one per stage)
    prior_features: int = 64  # channels of each prior CNN
    prior_blocks: int = 2  # residual blocks (two 3×3 convs each) of each prior
    prior_scale: int = 4  # the prior runs at 1/prior_scale resolution (space-to-depth, px)
    step_init: float = 1.0  # initial α_k·L (L ≥ ‖A‖²; < 2 guarantees a decreasing data term)
    stage_kernel_px: int = 0  # DOE camera: PSF cut to this many px (odd) in the stages; 0 = the full kernel
    # (CASSI cameras have no kernel: not applied, a note says so)
    demosaic_window: int = 0  # box width (px, odd) of the demosaic init; 0 = the CFA period rounded up to odd
    brightness_window: int = 0  # priors see z / b, b = box(g) + ε of this width (px, odd); 0 = off
    brightness_eps: float = 1.0e-3  # ε of b (sensor units; full scale 1)
    mosaic: MosaicConfig = field(default_factory=MosaicConfig)  # the front end of init=mosaic

    INITS: ClassVar[tuple[str, ...]] = ("auto", "demosaic", "backprojection", "mosaic")
    STEPS: ClassVar[tuple[str, ...]] = ("gradient", "gap")

    def __post_init__(self) -> None:
        """The checks that need no camera (init=demosaic needing a CFA, step=gap a diagonal ΦΦᵀ: build_unrolled)."""
        for key in ("stages", "prior_features", "prior_blocks", "prior_scale"):
            if getattr(self, key) < 1:
                raise ConfigError(f"model.unrolled.{key} must be >= 1, got {getattr(self, key)}")
        if self.step not in self.STEPS:
            raise ConfigError(f"model.unrolled.step={self.step!r} is not one of {', '.join(self.STEPS)}")
        if self.init not in self.INITS:
            raise ConfigError(f"model.unrolled.init={self.init!r} is not one of {', '.join(self.INITS)}")
        if not (self.step_init > 0 and math.isfinite(self.step_init)):
            raise ConfigError(f"model.unrolled.step_init must be > 0, got {self.step_init}")
        if self.step_init > MAX_STEP_INIT:
            raise ConfigError(f"model.unrolled.step_init must be at most {MAX_STEP_INIT:g} (α·L; below 2 each stage "
                              f"decreases the data term), got {self.step_init:g}")
        _check_odd_window("model.unrolled", "stage_kernel_px", self.stage_kernel_px, "0 for the full kernel")
        _check_odd_window("model.unrolled", "demosaic_window", self.demosaic_window, "0 for the CFA period")
        _check_brightness("model.unrolled", self.brightness_window, self.brightness_eps)
        self.mosaic.check("model.unrolled.mosaic")


#: Most measurement-consistency steps: each widens the tiling halo by the PSF's reach, and on the demo
#: camera 2, 4 and 8 steps score within 0.01 dB of one (docs/networks.md).
MAX_CONSISTENCY_ITERATIONS = 100
#: The weight of the TV prior in the consistency steps (``model.consistency.tv_weight``) that `hsicam reconstruct
#: --tv-steps` takes by default: at 12 steps on 20 training scenes of the demo camera, the best SSIM of 0.01, 0.03
#: and 0.1, with PSNR within 0.01 dB of the best (docs/networks_log.md, "A TV prior in the steps").
RECOMMENDED_TV_WEIGHT = 0.03
#: The range of a non-zero ``tv_weight`` (dimensionless: the estimate over its local brightness): below, the prior
#: does nothing a float can tell (and f / w overflows); above, it flattens every scene to its brightness.
MIN_TV_WEIGHT, MAX_TV_WEIGHT = 1e-6, 10.0


@dataclass
class ConsistencyConfig:
    """Measurement consistency after the network, at inference (``hsicam.models.consistency``):
    x ← x + Aᵀ ((y − A x) ⊘ (A Aᵀ 𝟙 + λ)) with the camera's own operator, λ = damping · L (L ≥ ‖A‖²).
    Not applied while the network trains nor in its validation."""

    iterations: int = 0  # steps; 0 = off (the network's output as it is)
    # landweber: the step above; linear: x ← x + gain · W(y − A x), W the least-squares linear map from
    # sensor image to cube (one window_px filter per CFA phase and band) fitted on the run's training
    # scenes when training ends (RUN/linear_step.safetensors; docs/networks.md)
    kind: Literal["landweber", "linear"] = "landweber"
    damping: float = 0.02  # λ relative to L, the bound of ‖A‖² (larger: a smaller step, more robust to sensor noise)
    psf_energy: float = 0.995  # the step's PSFs are cut to the kernel keeping this share of each band's light (1: whole)
    gain: float = 0.5  # kind linear: the share of the linear map's correction taken
    window_px: int = 11  # kind linear: the filters' width (odd)
    # kind linear: Landweber steps (damping above) after the linear map's, which take what the map's fixed filters left
    # in the residual; 0 = none (kind landweber: unused, its steps are `iterations`)
    landweber_after: int = 0
    # Landweber steps: α of the preconditioner S = α ŝŝᵀ + I per pixel, ŝ the estimate's unit spectrum there, so a
    # pixel's residual moves every band along the local spectrum, not only its filter's (0: the plain step)
    spectral_prior: float = 0.0
    # weigh each step's residual by a local Wiener gain against the capture's noise variance from the camera's noise
    # model (camera.sensor: noise, sigma, full_well_e, read_noise_e, bit_depth): residuals at the noise's level move
    # the estimate little. A noise-free model (the default) leaves the steps exactly as without it.
    noise_aware: bool = True
    # Landweber steps: w of a total-variation prior, each step followed by one dual iteration towards b · prox_wTV(x / b),
    # the vectorial TV (every band's edges together) of the estimate divided by its local brightness b (in the spirit of
    # GAP-TV, started from the network's estimate); 0: none, else in [MIN_TV_WEIGHT, MAX_TV_WEIGHT]. Measured gains and
    # cost (0.11–0.15 s per step at 512² on a 2-core CPU since session 48; docs/results.md): docs/networks_log.md,
    # "A TV prior in the steps"
    tv_weight: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.iterations <= MAX_CONSISTENCY_ITERATIONS:
            raise ConfigError(f"model.consistency.iterations must be in [0, {MAX_CONSISTENCY_ITERATIONS}], got "
                              f"{self.iterations} (each step widens the tiles' halo; 2, 4 and 8 steps score as 1)")
        if not self.damping > 0:
            raise ConfigError(f"model.consistency.damping must be > 0, got {self.damping}")
        if not 0 < self.psf_energy <= 1:
            raise ConfigError(f"model.consistency.psf_energy must be in (0, 1], got {self.psf_energy}")
        if self.kind not in ("landweber", "linear"):
            raise ConfigError(f"model.consistency.kind must be landweber or linear, got {self.kind!r}")
        if not 0 < self.gain <= 1:
            raise ConfigError(f"model.consistency.gain must be in (0, 1], got {self.gain}")
        if self.window_px < 1 or self.window_px % 2 == 0:
            raise ConfigError(f"model.consistency.window_px must be odd and >= 1, got {self.window_px}")
        if not 0 <= self.landweber_after <= MAX_CONSISTENCY_ITERATIONS:
            raise ConfigError(f"model.consistency.landweber_after must be in [0, {MAX_CONSISTENCY_ITERATIONS}], got "
                              f"{self.landweber_after}")
        if not (math.isfinite(self.spectral_prior) and self.spectral_prior >= 0):
            raise ConfigError(f"model.consistency.spectral_prior must be a finite number >= 0 (0: the plain step), got "
                              f"{self.spectral_prior}")
        if not (self.tv_weight == 0 or MIN_TV_WEIGHT <= self.tv_weight <= MAX_TV_WEIGHT):
            raise ConfigError(f"model.consistency.tv_weight must be 0 (no TV prior) or in [{MIN_TV_WEIGHT:g}, "
                              f"{MAX_TV_WEIGHT:g}], got {self.tv_weight}")
        if self.tv_weight > 0 and self.kind == "linear" and self.iterations > 0 and self.landweber_after == 0:
            raise ConfigError(f"model.consistency.tv_weight={self.tv_weight} acts in the Landweber steps, and kind=linear "
                              "takes none (landweber_after=0): set model.consistency.landweber_after, e.g. 24, or "
                              "model.consistency.tv_weight=0 for the linear step alone")


@dataclass
class ModelConfig:
    """Reconstruction network: ``kind`` is a registered network (hsicam.models.registry): rdn, mosaic,
    unrolled; its settings are the section of the same name (docs/networks.md). ``consistency``: the
    measurement-consistency step after any of them."""

    kind: str = "rdn"
    rdn: RDNConfig = field(default_factory=RDNConfig)
    mosaic: MosaicConfig = field(default_factory=MosaicConfig)
    unrolled: UnrolledConfig = field(default_factory=UnrolledConfig)
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)

    def __post_init__(self) -> None:
        self.mosaic.check("model.mosaic")  # its own section's name (MosaicConfig has no __post_init__)


@dataclass
class TrainConfig:
    """Joint training of optics and network (paper: L1, Adam 1e-4, 100 epochs)."""

    epochs: int = 100
    batch_size: int = 8  # global batch (split over DDP processes)
    lr: float = 1e-4  # network learning rate (Adam)
    doe_lr_nm: float = 10.0  # Adam step size for the DOE heights, nm per step
    cfa_lr: float = 1e-3  # Adam learning rate for the CFA weights
    lr_schedule: Literal["constant", "cosine", "step"] = "constant"
    lr_step_epochs: int = 30  # "step": multiply by lr_gamma every lr_step_epochs
    lr_gamma: float = 0.5
    warmup_steps: int = 0
    grad_clip: Optional[float] = 1.0  # max global gradient norm; null: no clipping
    sigma_height_nm: list[float] = field(default_factory=lambda: [0.0, 0.0])  # [lo, hi]: drawn per step
    sensor_sigma: list[float] = field(default_factory=lambda: [0.0, 0.0])  # [lo, hi] Gaussian σ_s per step
    # loss = L1 + relative_l1 · mean(|x̂ − x| / (box₉(mean_c x) + relative_eps)): weighs errors of dark
    # regions by their local brightness (spectral angle, dark scenes); 0 = the paper's plain L1
    relative_l1: float = 0.0
    relative_eps: float = 0.01
    # + ssim_loss · (1 − SSIM) (per band, 11 px Gaussian window, peak 1: the metric itself) and
    # + sam_loss · mean spectral angle (radians, pixels whose truth is brighter than relative_eps)
    ssim_loss: float = 0.0
    sam_loss: float = 0.0
    # + spectral_grad_loss · L1 between the band-to-band differences x[c+1] − x[c] of estimate and truth
    # (penalises spectral ripple that the plain L1 lets through where texture aliases into the spectrum)
    spectral_grad_loss: float = 0.0
    # + phase_loss · mean |ē_p − ē| over the CFA phases p: the error averaged over each phase of the CFA
    # period against its mean over all (B, C): the m×m trace a per-phase network leaves on flat areas
    phase_loss: float = 0.0
    eval_every_epochs: int = 1
    checkpoint_every_steps: int = 200
    # the checkpoint whose weights the run keeps (RUN/model.safetensors: what evaluate, reconstruct and
    # export read): "best", the highest validation PSNR (the paper's practice; chosen on patches of the
    # validation scenes, so metrics reported on those scenes are of a selected model), or "last", the
    # last step (no selection; with a cosine schedule to zero the last is the best within the spread)
    keep_weights: Literal["best", "last"] = "best"
    log_every_steps: int = 20
    seed: int = 0
    device: str = "auto"  # auto: cuda when available, else cpu
    bf16: bool = False  # autocast the network in bfloat16 (CUDA; mps where torch can; nothing on the CPU)
    channels_last: bool = False
    compile: bool = False  # torch.compile the network
    deterministic: bool = False
    tensorboard: bool = False
    # parameter groups kept fixed: "net" (the network), or a group the camera declares
    # (DOE camera: "doe", "cfa"); e.g. [doe] trains the CFA and the network behind a fixed DOE
    freeze: list[str] = field(default_factory=list)
    # train the camera's groups during the first optics_steps steps only; afterwards the optics are
    # fixed and the network trains alone, each batch imaged without autograd through the optics (the
    # DOE camera's PSF stack computed once): ~2.8x faster steps on the quick preset. null: joint throughout
    optics_steps: Optional[int] = None
    # wall-clock budget of one invocation, minutes: the loop stops before a step would end past it,
    # saves that step's checkpoint and exits with code 75; `--resume` goes on (a job's time limit).
    # null: no budget. SIGTERM and Ctrl-C stop the same way (hsicam.engine.stopping)
    max_minutes: Optional[float] = None

    def __post_init__(self) -> None:
        for k in ("epochs", "batch_size", "eval_every_epochs", "checkpoint_every_steps", "log_every_steps", "lr_step_epochs"):
            if getattr(self, k) < 1:
                raise ConfigError(f"train.{k} must be >= 1, got {getattr(self, k)}")
        if self.epochs > MAX_EPOCHS:
            raise ConfigError(f"train.epochs must be at most {MAX_EPOCHS} (the paper trains 100), got {self.epochs}")
        _positive("train", lr=self.lr, doe_lr_nm=self.doe_lr_nm, cfa_lr=self.cfa_lr, lr_gamma=self.lr_gamma,
                  grad_clip=self.grad_clip, relative_eps=self.relative_eps, max_minutes=self.max_minutes)
        if self.lr > MAX_LR:
            raise ConfigError(f"train.lr must be at most {MAX_LR:g} (Adam's step per weight; the presets take 1e-4 to "
                              f"1e-3), got {self.lr:g}")
        _check_seeds("train", seed=self.seed)
        for k in ("relative_l1", "ssim_loss", "sam_loss", "spectral_grad_loss", "phase_loss"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"train.{k} must be >= 0, got {v}")
        if self.warmup_steps < 0:
            raise ConfigError(f"train.warmup_steps must be >= 0, got {self.warmup_steps}")
        if self.optics_steps is not None and self.optics_steps < 0:
            raise ConfigError(f"train.optics_steps must be >= 0 or null, got {self.optics_steps}")
        for k in ("sigma_height_nm", "sensor_sigma"):
            v = getattr(self, k)
            if len(v) != 2 or not (0 <= v[0] <= v[1]) or not all(math.isfinite(x) for x in v):
                raise ConfigError(f"train.{k} must be [lo, hi] with 0 <= lo <= hi, got {v}")
        if self.sigma_height_nm[1] > MAX_SIGMA_HEIGHT_NM:
            raise ConfigError(f"train.sigma_height_nm={self.sigma_height_nm}: σ_p above {MAX_SIGMA_HEIGHT_NM:.0f} nm (1 mm, far "
                              "beyond any DOE's relief) is no fabrication noise; use [lo, hi] with hi <= 1000000 (e.g. [0, 20])")
        if self.sensor_sigma[1] > MAX_SENSOR_SIGMA:
            raise ConfigError(f"train.sensor_sigma={self.sensor_sigma}: σ above {MAX_SENSOR_SIGMA:g} (the full scale of "
                              "the image) buries any signal; use [lo, hi] with hi <= 1 (e.g. [0, 0.02])")
        # a set of group names: a name given twice counts once (refusing it would make the config.yaml of a run
        # that trained with the repeat unreadable)
        self.freeze = list(dict.fromkeys(self.freeze))

    def loss_formula(self) -> str:
        """The training loss these settings make (:func:`hsicam.engine.tasks.system_loss`, the same terms
        in the same order), for a figure: ``L1`` alone (the paper), or e.g. ``L1 + 0.1·(1 − SSIM) +
        0.05·spectral angle + 1·spectral-gradient L1`` (the quick preset). The CFA-phase term counts only
        behind a CFA; it is named whenever its weight is set."""
        terms = [(self.relative_l1, "relative L1"), (self.ssim_loss, "(1 − SSIM)"), (self.sam_loss, "spectral angle"),
                 (self.spectral_grad_loss, "spectral-gradient L1"), (self.phase_loss, "CFA-phase trace")]
        return " + ".join(["L1", *(f"{w:g}·{name}" for w, name in terms if w > 0)])


@dataclass
class NpyBandsConfig(BandsConfig):
    """Band grid of ``.npy`` cubes (``data.npy_bands``): the same keys as ``bands``."""

    section: ClassVar[str] = "data.npy_bands"


@dataclass
class DataConfig:
    """Training/evaluation data (see ``hsicam.data`` and docs/data.md).

    Scenes come from ``root`` (any folder of supported cube files) or, by default, the embedded
    synthetic dataset generated once into the cache. Patches are ``patch_px`` plus the camera's
    kernel margin wide (the paper used 256 px patches, which need scenes of at least 396 px).
    """

    root: Optional[str] = None  # folder of supported files; None: the embedded synthetic dataset
    synthetic_n: int = 32  # scenes in the synthetic dataset
    synthetic_size: int = 256  # synthetic scene side, px
    synthetic_seed: int = 0
    cache_dir: Optional[str] = None  # None: $HSICAM_CACHE, else $XDG_CACHE_HOME/hsicam, else ~/.cache/hsicam
    patch_px: int = 64  # sensor-side patch; the scene patch is patch_px + kernel_px - 1 (boundary same: so is the sensor)
    patches_per_epoch: int = 1024  # random training patches drawn per epoch
    val_patches: int = 64  # fixed validation patches (drawn once from the validation scenes)
    val_fraction: float = 0.125  # fraction of scenes held out for validation (scene-level split)
    split_seed: int = 0
    # validation drawn among the first val_pool scenes (sorted), the rest all train; null: all scenes.
    # E.g. synthetic_n 192 with val_pool 64 trains on 128 more scenes and validates on those of n = 64
    val_pool: Optional[int] = None
    augment_flips: bool = True  # random left-right flips of training patches
    augment_rot90: bool = True  # random 90° rotations of training patches
    # Random relighting of training patches (hsicam.data.datasets.relight; docs/training.md): with probability
    # augment_relight_prob a patch's spectra are multiplied by exp(a1·P1 + a2·P2 + a3·P3) over the bands
    # (Legendre polynomials: a tilt, a bow, an S-curve; a_k ~ N(0, augment_relight²)), its peak kept: spectra
    # the scenes never held. 0: off. Validation patches are never relit.
    augment_relight: float = 0.0
    augment_relight_prob: float = 0.5
    preload: Optional[bool] = None  # keep all scenes in memory; None: when the files total <= preload_max_mb
    preload_max_mb: float = 2048.0
    num_workers: int = 2  # DataLoader worker processes
    # Spectral sources the synthetic training scenes never use (docs/data.md); a separate held-out
    # validation set of heldout_n scenes uses only them. "none": hold out nothing.
    holdout_sources: str = "nist-philips,rawtoaces"
    heldout_n: int = 8
    # Band grid of .npy cubes, which carry no wavelengths (e.g. {start_nm: 420, stop_nm: 720,
    # step_nm: 10}); null: C bands evenly over 400-700 nm (docs/data.md). Never a relabelling:
    # the cube is resampled from this grid onto the camera's.
    npy_bands: Optional[NpyBandsConfig] = None
    # Negative values in a cube file (dark noise after a background subtraction) are clipped to 0 instead of
    # refused: for every command that reads scenes (train, evaluate, simulate, data show ...; docs/data.md)
    allow_negative: bool = False

    def check_patches(self, margin_px: int = 0, code_period: int = 1) -> None:
        """ConfigError unless the patches can be scored and, for the synthetic data (``root`` null), fit
        its scenes with the camera's ``margin_px`` (kernel_px − 1): checked when patches are built
        (training), before the synthetic dataset is generated, not when a finished run's config is read,
        so a run trained with smaller patches still loads. (Scenes of ``root`` are checked as they are
        read: :class:`hsicam.data.datasets.PatchDataset`.) ``code_period``: the camera's CFA period,
        which a patch must hold whole."""
        if self.patch_px < MIN_PATCH_PX:
            raise ConfigError(f"data.patch_px must be >= {MIN_PATCH_PX} px (SSIM, scored on every validation patch and "
                              f"by train.ssim_loss, uses an {MIN_PATCH_PX}×{MIN_PATCH_PX} px window), got {self.patch_px}")
        if code_period > self.patch_px:
            raise ConfigError(f"camera.cfa.period ({code_period}) is larger than data.patch_px ({self.patch_px}): a "
                              "training patch must hold a whole CFA period; lower the period or raise the patch")
        if self.root is None and self.patch_px + margin_px > self.synthetic_size:
            raise ConfigError(f"data.patch_px {self.patch_px} plus the camera margin of {margin_px} px needs scenes of "
                              f"{self.patch_px + margin_px} px, but the synthetic scenes are data.synthetic_size="
                              f"{self.synthetic_size} px: " + (
                                  f"lower data.patch_px to <= {self.synthetic_size - margin_px} or raise "
                                  "data.synthetic_size" if self.synthetic_size - margin_px >= max(MIN_PATCH_PX, code_period)
                                  # (the size this patch needs: the smallest patch's size failed again at this patch)
                                  else f"raise data.synthetic_size to >= {self.patch_px + margin_px} (or to >= "
                                       f"{max(MIN_PATCH_PX, code_period) + margin_px} with data.patch_px="
                                       f"{max(MIN_PATCH_PX, code_period)}, the smallest patch)"))

    def __post_init__(self) -> None:
        for name in ("synthetic_n", "patch_px", "patches_per_epoch", "val_patches"):
            if getattr(self, name) < 1:
                raise ConfigError(f"data.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("patches_per_epoch", "val_patches"):  # a dataset's len(), which Python holds in 64 bits
            if getattr(self, name) > MAX_PATCHES:
                raise ConfigError(f"data.{name} must be at most {_power_text(MAX_PATCHES)} (patches an epoch), "
                                  f"got {getattr(self, name)}")
        _check_seeds("data", synthetic_seed=self.synthetic_seed, split_seed=self.split_seed)
        if self.synthetic_size < 16:
            raise ConfigError(f"data.synthetic_size must be >= 16 px, got {self.synthetic_size}")
        if not (0.0 <= self.val_fraction < 1.0):
            raise ConfigError(f"data.val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.val_pool is not None and self.val_pool < 2:
            raise ConfigError(f"data.val_pool must be >= 2 scenes or null, got {self.val_pool}")
        if self.num_workers < 0:
            raise ConfigError(f"data.num_workers must be >= 0, got {self.num_workers}")
        if self.heldout_n < 1:
            raise ConfigError(f"data.heldout_n must be >= 1, got {self.heldout_n}")
        _positive("data", preload_max_mb=self.preload_max_mb)
        if not (math.isfinite(self.augment_relight) and self.augment_relight >= 0):
            raise ConfigError(f"data.augment_relight must be a finite number >= 0 (0: off), got {self.augment_relight}")
        if not (0.0 <= self.augment_relight_prob <= 1.0):
            raise ConfigError(f"data.augment_relight_prob must be in [0, 1], got {self.augment_relight_prob}")
        if self.root is not None and not self.root.strip():
            raise ConfigError("data.root must be a path or null")
        if self.cache_dir is not None and not self.cache_dir.strip():
            # an empty path is the current folder: the dataset cache would be written wherever the command runs
            raise ConfigError("data.cache_dir must be a folder or null (null: $HSICAM_CACHE, else ~/.cache/hsicam), "
                              "got an empty path")


# --------------------------------------------------------------------------------------------
# Baseline solvers (baselines.gaptv, .desci, .choi)
# --------------------------------------------------------------------------------------------
def _check_positive(section: str, **values) -> None:
    for k, v in values.items():
        if v is not None and not (v > 0 and math.isfinite(v)):
            raise ConfigError(f"{section}.{k} must be positive, got {v}")


def _check_at_least(section: str, low: int, **values) -> None:
    for k, v in values.items():
        if v is not None and v < low:
            raise ConfigError(f"{section}.{k} must be >= {low}, got {v}")


@dataclass
class GAPTVConfig:
    """GAP-TV (hsicam.solvers.gaptv): accelerated GAP + spatial TV denoising. The defaults were tuned
    on training scenes, never the scored ones (``scripts/tune_gaptv.py``, docs/training_log.md): on the
    quick data's DD-CASSI camera 80 iterations score ~2 dB below 400 on the mean over those scenes, and more add
    ~0.2 dB. Per scene the accelerated GAP is not monotone: a textured scene can lose 2 dB from 40 to 400 iterations
    while a smooth one gains 14 (session 74's audit), so 400 is the mean's best, not every scene's."""

    iterations: int = 400
    tv_weight: float = 0.01  # λ of ½‖u − x‖² + λ·TV(u), cube values in [0, 1] (0.01–0.03 and 0.1→0.01: ties)
    tv_iterations: int = 5  # Chambolle iterations per denoising
    accelerate: bool = True

    def __post_init__(self) -> None:
        _check_at_least("baselines.gaptv", 0, iterations=self.iterations, tv_iterations=self.tv_iterations)
        if not (self.tv_weight >= 0 and math.isfinite(self.tv_weight)):
            raise ConfigError(f"baselines.gaptv.tv_weight must be >= 0, got {self.tv_weight}")


@dataclass
class DeSCIConfig:
    """DeSCI (hsicam.solvers.desci). ``preset`` fast (minutes per 256×256×31 scene on a CPU) or
    full (closer to the published setting); any other key set here overrides the preset."""

    preset: Literal["fast", "full"] = "fast"
    patch: Optional[int] = None
    step: Optional[int] = None
    search: Optional[int] = None
    group: Optional[int] = None
    sigmas: Optional[list[float]] = None
    iterations: Optional[list[int]] = None
    c: Optional[float] = None
    match_every: Optional[int] = None
    match_components: Optional[int] = None
    init_iterations: Optional[int] = None
    init_tv_weight: Optional[float] = None  # None: the GAP-TV baseline's baselines.gaptv.tv_weight

    def __post_init__(self) -> None:
        sec = "baselines.desci"
        _check_at_least(sec, 1, patch=self.patch, step=self.step, group=self.group, match_every=self.match_every,
                        match_components=self.match_components)
        _check_at_least(sec, 0, search=self.search, init_iterations=self.init_iterations)
        _check_positive(sec, c=self.c)
        if self.sigmas is not None and (not self.sigmas or not all(s > 0 and math.isfinite(s) for s in self.sigmas)):
            raise ConfigError(f"{sec}.sigmas must be a non-empty list of positive numbers, got {self.sigmas}")
        if self.iterations is not None and (not self.iterations or min(self.iterations) < 0):
            raise ConfigError(f"{sec}.iterations must be a non-empty list of counts >= 0, got {self.iterations}")
        if self.sigmas is not None and self.iterations is not None and len(self.sigmas) != len(self.iterations):
            raise ConfigError(f"{sec}: {len(self.sigmas)} sigmas but {len(self.iterations)} iteration counts")

    def overrides(self) -> dict:
        """The keys set here (not None), without ``preset``."""
        return {k: v for k, v in self.__dict__.items() if k != "preset" and v is not None}


@dataclass
class ChoiConfig:
    """Choi et al. 2017 (hsicam.solvers.choi): autoencoder spectral prior + ADMM.

    Prior architecture and training (``hsicam baseline train-prior``) and the ADMM solve. The ADMM
    defaults were tuned on training scenes of the quick data, never the scored ones (session 25,
    docs/training_log.md).
    """

    # autoencoder (hsicam.models.priors.SpectralAutoencoder: 6 + 6 3×3 convolutions, the published
    # sizes; the quick scale trains 32 features, hsicam.engine.prior.PRIOR_SCALE_OVERRIDES)
    features: int = 64
    latent: int = 64  # code channels at full resolution (>= bands: no spectral bottleneck)
    # training (a denoising autoencoder on training-split patches)
    train_steps: int = 1500
    batch_size: int = 8
    lr: float = 1e-3
    train_noise: float = 0.05  # Gaussian σ of the input corruption, drawn in [0, train_noise] per patch
    seed: int = 0
    # ADMM
    iterations: int = 30
    rho: float = 0.5  # ADMM penalty (data term normalised so that mean diag ΦΦᵀ = 1)
    rho_growth: float = 1.03  # ρ ← ρ·growth per iteration (1: constant)
    prior_weight: float = 0.5  # τ1 of (τ1/2)‖z − D(E(z))‖²
    tv_weight: float = 0.003  # τ2 of τ2·TV(z)
    inner_steps: int = 2  # proximal-gradient steps of each z-update
    init_iterations: int = 200  # GAP-TV iterations of the start (0: the minimum-norm solution)

    def __post_init__(self) -> None:
        sec = "baselines.choi"
        _check_at_least(sec, 1, features=self.features, latent=self.latent, train_steps=self.train_steps,
                        batch_size=self.batch_size, inner_steps=self.inner_steps)
        _check_at_least(sec, 0, iterations=self.iterations, init_iterations=self.init_iterations)
        _check_positive(sec, lr=self.lr, rho=self.rho, rho_growth=self.rho_growth)
        # the prior trains through a TrainConfig of these (PriorTask.loop_config): its bounds, named by their keys here
        if self.train_steps > MAX_EPOCHS:
            raise ConfigError(f"{sec}.train_steps must be at most {MAX_EPOCHS} (as train.epochs; the default is 1500), "
                              f"got {self.train_steps}")
        if self.lr > MAX_LR:
            raise ConfigError(f"{sec}.lr must be at most {MAX_LR:g} (as train.lr; the default is 1e-3), got {self.lr:g}")
        _check_seeds(sec, seed=self.seed)
        for k in ("train_noise", "prior_weight", "tv_weight"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{sec}.{k} must be >= 0, got {v}")


@dataclass
class BaselinesConfig:
    """Settings of the CASSI baseline solvers."""

    gaptv: GAPTVConfig = field(default_factory=GAPTVConfig)
    desci: DeSCIConfig = field(default_factory=DeSCIConfig)
    # None: ADMM runs with the settings the prior was trained with (its folder's prior.yaml), and
    # ``hsicam baseline train-prior`` uses the defaults; setting any baselines.choi key makes this a
    # full section (defaults for the keys not set) that both use.
    choi: Optional[ChoiConfig] = None

    @property
    def choi_or_default(self) -> ChoiConfig:
        """``choi`` when set, else the defaults."""
        return self.choi if self.choi is not None else ChoiConfig()


@dataclass
class Config:
    """Top-level configuration."""

    bands: BandsConfig = field(default_factory=BandsConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    baselines: BaselinesConfig = field(default_factory=BaselinesConfig)

    def __post_init__(self) -> None:
        c, cfa = self.model.consistency, self.camera.cfa
        self._check_material_ranges()
        if c.kind == "linear" and c.iterations > 0 and self.camera.kind not in ("doe", "sd_cassi"):
            # the step's filters are fitted per CFA phase: a CASSI camera has no such code (found
            # only after training, as a traceback, before session 23); SD-CASSI skips the step anyway
            # (its scene grid is not the sensor's: CameraSystem.consistency_on)
            # (the camera registry cannot be asked from here: hsicam.cameras imports this module)
            builtin = self.camera.kind == "dd_cassi"
            typo = "" if builtin else " (not a built-in camera kind: doe, dd_cassi, sd_cassi)"
            raise ConfigError(f"model.consistency.kind=linear needs the DOE camera's per-band sensor code "
                              f"(camera.kind=doe), not camera.kind={self.camera.kind}{typo}; use "
                              "model.consistency.kind=landweber, or model.consistency.iterations=0")
        if (c.kind == "linear" and c.iterations > 0 and self.camera.kind == "doe" and cfa.enabled
                and c.window_px < cfa.period):
            raise ConfigError(f"model.consistency.window_px={c.window_px} is narrower than the CFA period "
                              f"{cfa.period}: the linear step's filters must see every CFA phase (flat-field "
                              f"constraint); set it to at least {cfa.period | 1}")


    def _check_material_ranges(self) -> None:
        """Each material the camera uses has a refractive index at the wavelengths it is evaluated at
        (the PSF's: the band centres, or ``camera.psf.band_samples`` Gauss–Hermite points of each band's Gaussian; the
        prism's: the centres) and at its design wavelength; a wavelength outside the formula's range
        used to fail as the camera was built, naming no key."""
        from hsicam.spectral.bands import band_sample_wavelengths

        b, cam = self.bands.to_bands(), self.camera
        psf_nm, _ = band_sample_wavelengths(b.centers_nm, b.fwhm_nm, cam.psf.band_samples)
        what = ("the wavelengths the PSF is computed at (bands.start_nm .. bands.stop_nm"
                + (", camera.psf.band_samples over bands.fwhm_nm)" if cam.psf.band_samples > 1 else ")"))
        if cam.kind == "doe":
            if cam.doe.enabled:
                _check_material_range("camera.doe.material", cam.doe.material, what, psf_nm.min(), psf_nm.max())
                _check_material_range("camera.doe.material", cam.doe.material, "camera.doe.design_wavelength_nm",
                                      cam.doe.design_wavelength_nm, cam.doe.design_wavelength_nm)
            if cam.lens.model == "singlet":
                _check_material_range("camera.lens.material", cam.lens.material, what, psf_nm.min(), psf_nm.max())
                _check_material_range("camera.lens.material", cam.lens.material, "camera.lens.design_wavelength_nm",
                                      cam.lens.design_wavelength_nm, cam.lens.design_wavelength_nm)
        elif cam.cassi.dispersion == "prism":
            _check_material_range("camera.cassi.prism_material", cam.cassi.prism_material,
                                  "the band centres (bands.start_nm .. bands.stop_nm)", b.centers_nm.min(),
                                  b.centers_nm.max())


# --------------------------------------------------------------------------------------------
# The files a config names
# --------------------------------------------------------------------------------------------
#: The camera keys whose value names a file the camera is built from: a ``wavelength_nm,n`` material table (.csv; or
#: the built-in ``fused_silica``, no file) or a coded aperture (.npy; or null, a random one).
CAMERA_FILE_KEYS = ("camera.doe.material", "camera.lens.material", "camera.cassi.prism_material",
                    "camera.cassi.mask_file")
#: The record of the SHA-256 of each file a run's camera is built from (:mod:`hsicam.runs.camera_files`). A run
#: folder's config.yaml beside one names those files absolute (training writes them so) or relative to its own folder
#: (a packed camera carries copies of its tables): :func:`load_config` reads them so.
CAMERA_FILES_RECORD = "camera_files.json"


_REQUIRED = object()


def config_value(cfg: Any, key: str, default: Any = _REQUIRED) -> Any:
    """The value of the dotted ``key`` (e.g. ``camera.doe.material``) of a config dataclass; ``default`` where a part
    of it is missing (an AttributeError without one)."""
    for part in key.split("."):
        cfg = getattr(cfg, part) if default is _REQUIRED else getattr(cfg, part, default)
    return cfg


def mapping_section(data: Any, key: str) -> tuple[dict[str, Any] | None, str]:
    """``(section, name)`` of the dotted ``key`` in the nested mapping ``data`` (settings as read from YAML):
    ``section[name]`` is the key's place, ``section`` None where a part of the way is missing or not a mapping."""
    *parts, name = key.split(".")
    node: Any = data
    for part in parts:
        node = node.get(part) if isinstance(node, dict) else None
    return (node if isinstance(node, dict) else None), name


def _names_file(value: Any) -> bool:
    return isinstance(value, str) and value != "fused_silica"


def camera_files(cfg: Config) -> dict[str, str]:
    """``{key: path}`` of the files (:data:`CAMERA_FILE_KEYS`) the camera of ``cfg`` reads as it is built: the DOE
    camera its DOE's material table (read even with the DOE off) and a singlet's; a CASSI camera its mask file and a
    prism's table; a camera of another kind every file its config names. Built-in materials name none."""
    cam = cfg.camera
    if cam.kind == "doe":
        keys = ["camera.doe.material"] + (["camera.lens.material"] if cam.lens.model == "singlet" else [])
    elif cam.kind in ("dd_cassi", "sd_cassi"):
        keys = ["camera.cassi.mask_file"] + (["camera.cassi.prism_material"] if cam.cassi.dispersion == "prism" else [])
    else:
        keys = list(CAMERA_FILE_KEYS)
    return {k: v for k in keys if _names_file(v := config_value(cfg, k))}


def with_values(cfg: Any, values: dict[str, Any]) -> Any:
    """``cfg`` with the dotted keys of ``values`` replaced (new dataclasses; ``cfg`` is left as it is)."""
    for key, value in values.items():
        head, _, rest = key.partition(".")
        cfg = dataclasses.replace(cfg, **{head: with_values(getattr(cfg, head), {rest: value}) if rest else value})
    return cfg


def absolute_paths(cfg: Config) -> Config:
    """``cfg`` with every path it names made absolute (a leading ``~`` expanded first, then against the current
    folder): ``data.root``, ``data.cache_dir`` and the camera's files (:data:`CAMERA_FILE_KEYS`), so that a run's
    config.yaml names the same folders and files from wherever it is read; ``cfg`` itself when there is nothing to
    change (no path, or all absolute: a preset's built-in materials and synthetic data keep its config and hash)."""
    import os

    keys = ("data.root", "data.cache_dir", *CAMERA_FILE_KEYS)
    values = {k: config_value(cfg, k) for k in keys}
    new = {k: os.path.abspath(os.path.expanduser(v)) for k, v in values.items()
           if v is not None and (k.startswith("data.") or _names_file(v))}
    changed = {k: v for k, v in new.items() if v != values[k]}
    return with_values(cfg, changed) if changed else cfg


def _run_relative_files(data: dict[str, Any], folder: Path) -> None:
    """In the settings ``data`` of a run folder's config.yaml beside a :data:`CAMERA_FILES_RECORD`: each camera file
    named relative (a packed camera's copy of its table) made absolute against ``folder``, in place."""
    for key in CAMERA_FILE_KEYS:
        node, name = mapping_section(data, key)
        value = node.get(name) if node is not None else None
        if _names_file(value) and not is_absolute_anywhere(value):
            node[name] = str(folder.absolute() / value)


def is_absolute_anywhere(value: str) -> bool:
    """Whether ``value`` is an absolute path here or on another system (a run trained on Windows read on Linux names
    ``C:\\…``: joined to the run folder it was a path nobody wrote; session 75's review)."""
    from pathlib import PurePosixPath, PureWindowsPath

    return (Path(value).expanduser().is_absolute() or PurePosixPath(value).is_absolute()
            or bool(PureWindowsPath(value).drive))


# --------------------------------------------------------------------------------------------
# Loading, overrides, dumping
# --------------------------------------------------------------------------------------------
def load_config(path: str | Path | None = None, overrides: Sequence[str] = (), cls: type = Config,
                empty: str | None = None) -> Any:
    """Load ``path`` (YAML) over the defaults, apply dotted ``key=value`` overrides, validate.
    ``empty``: a file without settings (empty, only comments, ``{}``, or sections with nothing in them) is a
    :class:`ConfigError` saying
    ``"PATH: empty config (no settings); " + empty`` instead of the built-in defaults (e.g. a run's
    config.yaml, which training always writes in full)."""
    if isinstance(overrides, (str, bytes)):  # iterated, a string was its characters: "override 't' must look like …"
        raise ConfigError(f"overrides must be a sequence of 'key=value' strings (a list or tuple), got the string "
                          f"{overrides!r}: pass [{overrides!r}]")
    data: dict[str, Any] = {}
    if path is not None:
        path = resolve_preset(path)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read config ({getattr(exc, 'strerror', None) or exc})") from None
        try:
            loaded = strict_yaml(text)
        except DuplicateKeyError as exc:
            raise ConfigError(f"{path}: {exc}; YAML keeps only the last, so remove one") from None
        except yaml.YAMLError as exc:
            raise ConfigError(yaml_error_text(path, text, exc)) from None
        # no settings: an empty file, only comments, "{}", or sections with nothing in them ("camera:" alone)
        if loaded is None or (isinstance(loaded, dict) and all(v is None or v == {} for v in loaded.values())):
            if empty is not None:
                raise ConfigError(f"{path}: empty config (no settings); {empty}")
            loaded = {}
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: the top level must be a mapping of sections")
        data = loaded
        if path.name == "config.yaml" and (path.parent / CAMERA_FILES_RECORD).is_file():
            _run_relative_files(data, path.parent)  # a packed camera's tables, beside its config.yaml
    file_alone = copy.deepcopy(data) if path is not None and overrides else None
    for item in overrides:
        apply_override(data, item)
    if path is not None and not overrides:
        return _file_settings(path, cls, data)
    try:  # the file and the overrides together, as the module docstring says (an override may complete the file)
        _check_list_overrides(data, overrides)
        _migrate_model_section(data)
        return from_dict(cls, data)
    except ConfigError:
        if file_alone is not None:  # what is wrong in the file names the file; what an override breaks, the override
            _file_settings(path, cls, file_alone)
        raise


def _file_settings(path: Path, cls: type, data: dict[str, Any]) -> Any:
    """``cls`` from the settings ``data`` read from the file ``path``; a :class:`ConfigError` in them names the
    file (``PATH: unknown config key 'x'``), as the README's one error line promises."""
    try:
        _migrate_model_section(data)
        return from_dict(cls, data)
    except ConfigError as exc:
        text = str(exc)
        raise ConfigError(text if text.startswith(f"{path}: ") else f"{path}: {text}") from None


#: Keys whose value is a comma-separated list of names (``"a,b"``).
LIST_KEYS = ("data.holdout_sources",)


def empty_item_problem(text: str) -> str | None:
    """What is wrong with a comma-separated list ``text`` that has an empty item ("1,,2", "1,2,", ","), else None:
    one wording for the command line's list options (:func:`hsicam.cli.args.list_items`) and the overrides of
    :data:`LIST_KEYS`. Dropped, the empty item ran with one value fewer than typed, without a word."""
    items = [v.strip() for v in text.split(",")]
    if "" not in items:
        return None
    return (f"item {items.index('') + 1} of {text!r} is empty (two commas in a row, or one at an end); give its value "
            "or remove the comma")


def check_list_keys(cfg: Config, path: str | Path | None) -> None:
    """An empty item in a list key (:data:`LIST_KEYS`) of the config FILE ``path`` that a user gives (``--config``)
    is a :class:`ConfigError` naming the file, the key and the item, as the same value in an override is
    (:func:`_check_list_overrides`): loaded, ``data: {holdout_sources: "nist-cqs,,rawtoaces"}`` held out one source
    fewer than typed, without a word. Not in :func:`load_config`, which also reads a run's own config.yaml: that
    file keeps the value as it was given, and one written with an empty item still loads (ignored, as it was then).
    Call it on ``load_config(path, overrides)``'s result: an override that gives the key a bad value was refused
    there, so a bad value here is the file's."""
    if path is None:
        return
    for key in LIST_KEYS:
        node = config_value(cfg, key, None)
        if not isinstance(node, str) or node.strip().lower() in ("", "none"):
            continue
        problem = empty_item_problem(node)
        if problem:
            raise ConfigError(f"{resolve_preset(path)}: {key}: {problem}")


def _check_list_overrides(data: dict[str, Any], overrides: Sequence[str]) -> None:
    """An empty item in a list key an override sets (``--set data.holdout_sources=nist-cqs,,rawtoaces``) is a
    :class:`ConfigError` naming the key and the item, as ``data synth --holdout-sources`` refuses it: dropped, it
    held out one source fewer than typed, without a word. Checked on the overrides alone, not in
    :class:`DataConfig`: a run's config.yaml keeps the value as it was given, and one written before this check
    still loads (its empty item ignored, as it was then)."""
    given = {str(item).partition("=")[0].strip() for item in overrides}
    for key in LIST_KEYS:
        if not any(key == k or key.startswith(k + ".") for k in given):  # set itself, or in a section's mapping
            continue
        section, name = mapping_section(data, key)
        node = section.get(name) if section is not None else None
        if not isinstance(node, str) or node.strip().lower() in ("", "none"):
            continue  # a wrong type is from_dict's error; "none": no item
        problem = empty_item_problem(node)
        if problem:
            raise ConfigError(f"{key}: {problem}")


_RDN_KEYS = ("blocks", "features", "growth", "layers_per_block", "demosaic_input", "backprojection_input")


def _migrate_model_section(data: dict[str, Any]) -> None:
    """Configs written before network kinds existed (``model: {name: rdn, blocks: …}``, e.g. the
    config.yaml of an older run) are read as ``model: {kind: rdn, rdn: {blocks: …}}``."""
    model = data.get("model")
    if not isinstance(model, dict) or not any(k in model for k in (*_RDN_KEYS, "name")):
        return
    rdn = model.setdefault("rdn", {})
    if not isinstance(rdn, dict):  # said here: left as it is, the older keys would be the ones named unknown
        raise ConfigError(f"model.rdn must be a mapping, got {type(rdn).__name__}")
    for k in _RDN_KEYS:
        if k in model:
            old = model.pop(k)
            if rdn.setdefault(k, old) != old:  # both spellings, two values: neither is silently dropped
                raise ConfigError(f"model.{k} (the older spelling of model.rdn.{k}) is {old!r} but model.rdn.{k} is "
                                  f"{rdn[k]!r}; keep one")
    if "name" in model:
        old = model.pop("name")
        if model.setdefault("kind", old) != old:
            raise ConfigError(f"model.name (the older spelling of model.kind) is {old!r} but model.kind is "
                              f"{model['kind']!r}; keep one")


PRESETS_DIR = Path(__file__).resolve().parent / "configs"


def preset_names() -> list[str]:
    """The shipped presets (``--config NAME``), sorted: the ``*.yaml`` files of :data:`PRESETS_DIR`."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def resolve_preset(path: str | Path) -> Path:
    """A config path, or the name of a shipped preset (:func:`preset_names`); ConfigError listing the
    presets when ``path`` is neither an existing file nor a preset's name."""
    p = Path(path)
    # a bare name only: `--config myexp/quick` is that file or an error, never the shipped `quick`; a folder of the
    # preset's name in the working folder (e.g. a run trained with --out tiny) is no config: the preset (session 74)
    if (not p.exists() or p.is_dir()) and p.suffix == "" and len(p.parts) == 1 and \
            (PRESETS_DIR / f"{p.name}.yaml").is_file():
        return PRESETS_DIR / f"{p.name}.yaml"
    if p.is_dir():
        hint = f": a run's config is {p / 'config.yaml'}" if (p / "config.yaml").is_file() else ""
        raise ConfigError(f"{p}: a folder, not a config file{hint} (presets: {', '.join(preset_names())})")
    if not p.exists() and not p.is_symlink():
        raise ConfigError(f"{p}: no such config file, nor a shipped preset (presets: {', '.join(preset_names())})")
    return p


class DuplicateKeyError(yaml.YAMLError):
    """A key given twice in one YAML mapping: ``key`` (dotted from the document's top) and the
    1-based ``lines`` of its first and its repeated occurrence."""

    def __init__(self, key: str, lines: tuple[int, int]) -> None:
        super().__init__(f"key '{key}' is given twice (lines {lines[0]} and {lines[1]})")
        self.key, self.lines = key, lines


def yaml_error_text(path: str | Path, text: str, exc: yaml.YAMLError) -> str:
    """One line for a file that is not valid YAML: where (line:column, when the parser says) and what,
    and for a line indented with a tab, that YAML indents with spaces only."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    if mark is None:
        return f"{path}: invalid YAML ({problem})"
    lines = text.splitlines()
    line = lines[mark.line] if mark.line < len(lines) else ""
    tab = "; YAML indents with spaces, not tabs" if line[: len(line) - len(line.lstrip())].count("\t") else ""
    context, where = getattr(exc, "context", None), getattr(exc, "context_mark", None)
    opened = f" ({context} at line {where.line + 1}, column {where.column + 1})" if context and where else ""
    return f"{path}: invalid YAML at line {mark.line + 1}, column {mark.column + 1}: {problem}{opened}{tab}"


class ConfigLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader with YAML 1.2's integers: decimal (``42``, ``-3``, ``1_000``), ``0x…`` and ``0o…``.
    YAML 1.1's other forms read a zero-padded number as octal and ``h:mm`` in base 60 (``seed: 0042`` was 34,
    ``epochs: 1:30`` was 90, while ``008`` was refused); they stay text here, which an integer key refuses. So do
    YAML 1.1's base-60 floats (``lr: 1:30.0`` was 90.0), which a number key refuses."""


ConfigLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
# SafeLoader's float forms less the base-60 one ([-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*)
_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?
                    |\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X)
for _first in "-+0123456789.":
    ConfigLoader.yaml_implicit_resolvers.setdefault(_first, []).append(("tag:yaml.org,2002:float", _FLOAT))
for _first in "-+0123456789":  # before the float resolver, as in SafeLoader (so "7" is an int, not a float)
    ConfigLoader.yaml_implicit_resolvers.setdefault(_first, []).insert(
        0, ("tag:yaml.org,2002:int", re.compile(r"^(?:[-+]?(?:0|[1-9][0-9_]*)|0x_*[0-9a-fA-F][0-9a-fA-F_]*|0o_*[0-7][0-7_]*)$")))


def strict_yaml(text: str) -> Any:
    """``yaml.safe_load(text)`` with :class:`ConfigLoader`'s integers, and a key given twice in one mapping
    (``train:`` twice, or ``lr:`` twice in one section) is a :class:`DuplicateKeyError`, where ``safe_load``
    silently keeps the last."""
    loader = ConfigLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        found = _duplicate_key(node, "", set())
        if found is not None:
            raise DuplicateKeyError(found[0], found[1:])
        return loader.construct_document(node)
    finally:
        loader.dispose()


_MERGE_TAG = "tag:yaml.org,2002:merge"


def _duplicate_key(node: yaml.Node, where: str, seen: set[int]) -> Optional[tuple[str, int, int]]:
    """(dotted key, first line, repeated line) of the first key given twice in a mapping of the node
    tree under ``node``, or None. Keys merged in with ``<<:`` may be overridden (YAML's merge rule)."""
    if id(node) in seen:  # an alias to a node already walked (or a recursive one)
        return None
    seen.add(id(node))
    children: list[tuple[str, yaml.Node]] = []
    if isinstance(node, yaml.MappingNode):
        lines: dict[tuple[str, str], int] = {}
        for k, v in node.value:
            name = k.value if isinstance(k, yaml.ScalarNode) else "?"
            if isinstance(k, yaml.ScalarNode) and k.tag != _MERGE_TAG:
                line = k.start_mark.line + 1
                if (k.tag, k.value) in lines:
                    return _join(where, name), lines[k.tag, k.value], line
                lines[k.tag, k.value] = line
            children.append((where if k.tag == _MERGE_TAG else _join(where, name), v))
    elif isinstance(node, yaml.SequenceNode):
        children = [(f"{where}[{i}]", v) for i, v in enumerate(node.value)]
    for child_where, child in children:
        found = _duplicate_key(child, child_where, seen)
        if found is not None:
            return found
    return None


def override_keys(overrides: Sequence[str]) -> set[str]:
    """Every dotted key that ``overrides`` (``a.b=value`` items) set, with the keys inside a value
    given as a mapping (``a={b: 1, c: {d: 2}}`` sets a, a.b, a.c and a.c.d)."""
    out: set[str] = set()

    def walk(key: str, value: Any) -> None:
        out.add(key)
        if isinstance(value, dict):
            for k, v in value.items():
                walk(_join(key, str(k)), v)

    for item in overrides:
        key, _, raw = str(item).partition("=")
        try:
            value = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError:
            value = None
        walk(key.strip(), value)
    return out


#: Keys whose empty override (``--set data.root=``) is refused rather than read as null: the value of an unset shell
#: variable (``data.root=$DATA``) would otherwise switch a training to the embedded synthetic data without a word.
NO_EMPTY_OVERRIDE = {"data.root": "give the dataset's folder, or data.root=null for the embedded synthetic data"}


def apply_override(data: dict[str, Any], item: str) -> None:
    """Apply one ``a.b.c=value`` override to a nested dict (value parsed as YAML; an empty value is null, except for
    the keys of :data:`NO_EMPTY_OVERRIDE`)."""
    if "=" not in item:
        raise ConfigError(f"override {item!r} must look like key.sub=value")
    key, _, raw = item.partition("=")
    parts = [p for p in key.strip().split(".")]
    if not all(parts):
        raise ConfigError(f"override {item!r}: empty key")
    if not raw.strip() and key.strip() in NO_EMPTY_OVERRIDE:
        raise ConfigError(f"override {item!r}: the value is empty (an unset variable?): {NO_EMPTY_OVERRIDE[key.strip()]}")
    try:
        value = strict_yaml(raw) if raw.strip() else None
    except DuplicateKeyError as exc:
        raise ConfigError(f"override {item!r}: key '{_join(key.strip(), exc.key)}' is given twice; give it once") from None
    except yaml.YAMLError:
        value = raw
    node = data
    for p in parts[:-1]:
        nxt = node.setdefault(p, {})
        if nxt is None:  # an optional section left empty (e.g. a run's `npy_bands: null`): filled from here
            nxt = node[p] = {}
        if not isinstance(nxt, dict):
            raise ConfigError(f"override {item!r}: {p} is not a section")
        node = nxt
    node[parts[-1]] = value


def from_dict(cls: type, data: Any, where: str = "") -> Any:
    """Build dataclass ``cls`` from a mapping, rejecting unknown keys and wrong types."""
    label = where or "config"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{label} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for key in data:
        if key not in names:
            raise ConfigError(f"unknown config key '{_join(where, str(key))}' (known here: {', '.join(names)})")
    kwargs = {k: _coerce(hints[k], v, _join(where, k)) for k, v in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{label}: {exc}") from None


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of a config (for YAML/JSON)."""
    return dataclasses.asdict(cfg)


#: Keys that say how a run executes or is evaluated, not what it trains: two configs that differ only
#: here train the same camera (``training_differences``).
RUNTIME_ONLY_KEYS = (
    "baselines", "data.cache_dir", "data.preload", "data.preload_max_mb", "data.num_workers", "data.heldout_n",
    "train.device", "train.log_every_steps", "train.checkpoint_every_steps", "train.eval_every_epochs",
    "train.tensorboard", "train.compile", "train.channels_last", "train.deterministic", "train.max_minutes",
    "model.consistency",  # applied after the network at inference; the training never sees it
    "train.keep_weights",  # which of its checkpoints a run keeps: the same training either way
)


def training_differences(have: Config, want: Config, limit: int = 3, runtime: bool = False) -> list[str]:
    """The first ``limit`` settings (``"key: have → want"``) in which two configs train different
    cameras; keys in :data:`RUNTIME_ONLY_KEYS` (and below them) are ignored unless ``runtime``. Empty: the same."""
    out: list[str] = []

    def walk(a: Any, b: Any, where: str) -> None:
        if not runtime and any(where == k or where.startswith(k + ".") for k in RUNTIME_ONLY_KEYS):
            return
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(a.keys() | b.keys()):
                walk(a.get(key), b.get(key), _join(where, key))
        elif a != b:
            out.append(f"{where}: {a!r} → {b!r}")

    walk(to_dict(have), to_dict(want), "")
    # every difference, then the first `limit` in key order: the keys named no longer depend on the set's hash order
    return sorted(out)[:limit]


#: Keys (and sections) that say what a run *is*: its bands, camera, network, scenes and split. `hsicam train
#: --resume --set` may change how it goes on (epochs, learning rates, losses, augmentation, runtime keys), not these:
#: config.yaml would then describe a camera or a split the run never had (a resumed run whose split seed changed
#: scored one of its training scenes as "validation").
RUN_IDENTITY_KEYS = (
    "bands", "camera", "model", "data.synthetic_n", "data.synthetic_size", "data.synthetic_seed",
    "data.patch_px", "data.val_patches", "data.val_fraction", "data.split_seed", "data.val_pool",
    "data.holdout_sources", "data.npy_bands",
)


def identity_differences(have: Config, want: Config, limit: int = 3) -> list[str]:
    """The first ``limit`` differences (``"key: have → want"``) of :func:`training_differences` under
    :data:`RUN_IDENTITY_KEYS` (``model.consistency``, applied after the network, is not one), and ``data.root``
    turned on or off (synthetic ↔ a folder; a folder moved elsewhere is checked scene by scene by its data.json,
    :func:`hsicam.engine.provenance.check_same_data`). Empty: none."""
    every = training_differences(have, want, limit=10**6)
    out = [d for d in every if any(d.startswith(k + ".") or d.startswith(k + ":") for k in RUN_IDENTITY_KEYS)]
    if (have.data.root is None) != (want.data.root is None):
        out.append(f"data.root: {have.data.root!r} → {want.data.root!r}")
    return sorted(out)[:limit]


def dump_yaml(cfg: Any) -> str:
    """The resolved config as YAML text (round-trips through :func:`load_config`)."""
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


_DECIMAL = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_NON_FINITE = re.compile(r"^[+-]?\.?(inf|infinity|nan)$", re.IGNORECASE)  # what YAML leaves as text (not .inf/.nan)


def _coerce(tp: Any, value: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, value, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else f"config key '{key}': {value!r} has the wrong type")
    if origin is Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ConfigError(f"config key '{key}' must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        return value
    if origin in (list, tuple, Sequence):
        (inner, *_) = typing.get_args(tp) or (Any,)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key '{key}' must be a list, got {value!r}")
        items = [_coerce(inner, v, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, key)
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{key}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, str) and re.fullmatch(r"[-+]?0[0-9_]+", value.strip()):  # ConfigLoader: YAML 1.1's octal
            raise ConfigError(f"config key '{key}' must be an integer without leading zeros, got {value!r} (write "
                              f"{int(value.replace('_', ''))}; YAML 1.1 would read it as an octal number)")
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str) and _DECIMAL.match(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e-4 (no dot in the mantissa) as a string
        if isinstance(value, str) and _NON_FINITE.match(value.strip()) or isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"config key '{key}' must be a finite number, got {value!r}")  # inf, nan, .inf, .nan
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{key}' must be a number, got {value!r}")
        try:
            return float(value)
        except OverflowError:  # an integer beyond float range
            raise ConfigError(f"config key '{key}' must be a finite number, got an integer of {value.bit_length()} bits") from None
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{key}' must be a string, got {value!r}")
        return value
    raise ConfigError(f"config key '{key}': unsupported type {_type_name(tp)}")
