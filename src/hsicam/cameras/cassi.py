"""Coded-aperture snapshot spectral imagers (CASSI), the baselines of the paper's Table 1.

Band c (of C) is displaced by an integer dispersion ``d_c`` pixels along the sensor rows
(``d_0 = 0``, ``D = max_c d_c``); ``P`` is the coded aperture and ``s`` the band convention
(``sum``: s = 1, the MST convention; ``mean``: s = 1/C, so a white scene gives ≈ the aperture's
open fraction, comparable with the DOE camera whose CFA sums to 1 over bands). Under sensor noise
given relative to full scale 1 (``camera.sensor``, ``evaluate --sensor-sigma``) that level matters:
with the random aperture (density ½) a white scene's DD-CASSI measurement has mean ≈ 0.5 and peak
≈ 0.84 where the DOE camera's is ≈ 1 everywhere, so at equal σ CASSI's measurement SNR is lower (the
aperture blocks half the light; the DOE camera's filters are normalised as if each pixel saw all
of it). Noise-free scores do not depend on s (the solvers divide by ΦΦᵀ):

- **DD-CASSI** (dual disperser; Gehm et al. 2007). The first disperser shears the scene onto the
  aperture, the second undoes the shear, so the measurement has the scene's size and each band
  sees the aperture shifted by its dispersion::

      y(i, j) = s · Σ_c P(i, j + d_c) · x_c(i, j)           y: (B, 1, H, W), P: (H, W + D)

- **SD-CASSI** (single disperser; Wagadarikar et al. 2008, MST's simulation): the aperture codes
  the scene, the disperser shears the coded cube, the sensor sums it::

      y(i, j) = s · Σ_c P(i, j - d_c) · x_c(i, j - d_c)     y: (B, 1, H, W + D), P: (H, W)

Both are linear with exact adjoints, and ΦΦᵀ is diagonal (each scene voxel reaches one sensor
pixel), which GAP and ADMM use. Dispersion is linear (``d_c = ⌊shift_px · c + ½⌋``, halves up; MST: 2 px per
band) or from a thin prism (``d_c`` from the prism glass's n(λ), rounded to whole pixels so that
ΦΦᵀ stays diagonal; the thin-prism deviation (n − 1)·α underestimates a 30° apex's: fused silica, f = 50 mm, 6 µm
pixels, 420–720 nm: 57.8 px against the exact minimum-deviation 61.7 px, 6.8 % less dispersion, session 73's audit). CASSI has no blur kernel: ``margin`` is 0, so ``valid`` and ``same`` give the
same measurement (the scene is the reconstruction target in both).

The random aperture is a hash of (seed, row, column): the same seed gives the same aperture at
every size, on every device, and a crop of a larger aperture is the smaller one.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

from hsicam.cameras.base import Camera, check_origin
from hsicam.cameras.registry import register_camera
from hsicam.config import design_seed
from hsicam.errors import ConfigError, InputError
from hsicam.io import npy_content_problem
from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes
from hsicam.sensor import SensorNoise
from hsicam.spectral import Bands, get_material

log = logging.getLogger(__name__)

_M32 = 0xFFFFFFFF

#: Rows and columns of a hashed aperture over which training draws its patches' windows (px): the
#: code of a 512×512 sensor (see ``_CASSICamera.measure``).
TRAIN_APERTURE_PX = 512


# --------------------------------------------------------------------------------------------
# Coded aperture
# --------------------------------------------------------------------------------------------
def _mix32(h: torch.Tensor) -> torch.Tensor:
    """32-bit integer finaliser (values kept in int64 below 2^32, products below 2^63)."""
    h = (((h >> 16) ^ h) * 0x45D9F3B) & _M32
    h = (((h >> 16) ^ h) * 0x45D9F3B) & _M32
    return (h >> 16) ^ h


def hashed_bits(h: int, w: int, seed: int, device: torch.device | str | None = None,
                origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """32 random bits (int64 in [0, 2³²), (h, w)) that depend only on (seed, row, column): the window of rows
    ``origin[0]``… and columns ``origin[1]``… (only those are hashed: the memory is the window's, not its offset's)."""
    r0, c0 = int(origin[0]), int(origin[1])
    seed = design_seed(seed, "coded-aperture seed")  # the hash keeps its low 32 bits: 2^32 drew seed 0's aperture
    s = _mix32(torch.tensor((seed * 0x2545F491 + 0x9E3779B9) & _M32, dtype=torch.int64, device=device))
    rows = torch.arange(r0, r0 + h, dtype=torch.int64, device=device)[:, None]
    cols = torch.arange(c0, c0 + w, dtype=torch.int64, device=device)[None, :]
    return _mix32(_mix32(s ^ rows) ^ cols)


def hashed_uniform(h: int, w: int, seed: int, device: torch.device | str | None = None,
                   origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Uniform values in [0, 1) (float64, (h, w)): :func:`hashed_bits` / 2³²."""
    return hashed_bits(h, w, seed, device, origin).to(torch.float64) / 2.0**32


def random_aperture(h: int, w: int, seed: int = 0, density: float = 0.5,
                    device: torch.device | str | None = None, dtype: torch.dtype = torch.float32,
                    origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Random binary coded aperture (h, w) at ``origin`` (row, column): 1 (open) with probability ``density``,
    position-hashed: open where :func:`hashed_uniform` < ``density``, compared in integers (bits < ⌈density·2³²⌉,
    the same cells) so that no float64 tensor is made on ``device`` (MPS has none)."""
    d = float(density)
    limit = math.ceil(d * 2.0**32) if 0.0 < d <= 1.0 else (1 << 32 if d > 1.0 else 0)  # NaN or <= 0: all closed
    return (hashed_bits(h, w, seed, device, origin) < limit).to(dtype)


def load_aperture(path: str | Path) -> np.ndarray:
    """Coded aperture (H, W) from a ``.npy`` file; values must be finite and in [0, 1] (a boolean mask: 1 = open)."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a coded-aperture file (a .npy array (H, W))")
    if not path.is_file():
        raise InputError(f"{path}: no such coded-aperture file")
    try:
        problem = npy_content_problem(path)  # only a .npy is loaded
        arr = np.load(path, allow_pickle=False) if problem is None else None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npy array ({exc})") from None
    if arr is None:
        raise InputError(f"{path}: not a .npy file ({problem}); save the coded aperture (H, W) with numpy.save")
    stored = np.asarray(arr).shape
    arr = np.squeeze(np.asarray(arr))
    if arr.ndim != 2 or min(arr.shape) < 1:
        raise InputError(f"{path}: a coded aperture must be a 2-D (H, W) array of at least 1×1 after dropping axes of "
                         f"length 1, got shape {stored}")
    if arr.dtype != np.bool_ and (not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating)):
        raise InputError(f"{path}: a coded aperture must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{path}: coded-aperture values must be finite (the array has NaN or inf)")
    if arr.min() < 0 or arr.max() > 1:
        raise InputError(f"{path}: coded-aperture values must be in [0, 1] (got {arr.min():g}..{arr.max():g})")
    if not arr.max() > 0:
        raise InputError(f"{path}: the coded aperture is closed everywhere (all values 0): the camera would measure "
                         "nothing")
    return arr


class CodedAperture(nn.Module):
    """The coded aperture P: a position-hashed random binary pattern, or an array (from a file).

    ``pattern(h, w)`` is the top-left (h, w) window, ``pattern(h, w, origin=(r0, c0))`` the one at row r0, column c0;
    an array that does not hold the window is an :class:`InputError`. The array is no buffer: it stays on the CPU in
    float64 when the camera moves (a float64 buffer made ``camera.to("mps")`` a TypeError: MPS has no float64), its
    windows go to the device they are asked for; checkpoints do not store it.
    """

    def __init__(self, seed: int = 0, density: float = 0.5, array: np.ndarray | torch.Tensor | None = None,
                 source: str | None = None) -> None:
        super().__init__()
        if not (0.0 < density <= 1.0):
            raise ValueError(f"aperture density must be in (0, 1], got {density}")
        self.seed, self.density, self.source = design_seed(seed, "coded-aperture seed"), float(density), source
        arr = None if array is None else torch.as_tensor(np.asarray(array, dtype=np.float64))
        if arr is not None and arr.dim() != 2:
            raise InputError(f"a coded aperture must be 2-D, got shape {tuple(arr.shape)}")
        self.array = arr  # a plain attribute, on the CPU (see the class docstring)
        self._cache: dict[tuple, torch.Tensor] = {}

    @classmethod
    def from_file(cls, path: str | Path) -> "CodedAperture":
        return cls(array=load_aperture(path), source=str(path))

    def pattern(self, h: int, w: int, device: torch.device | str | None = None,
                dtype: torch.dtype = torch.float32, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """Aperture window (h, w) at ``origin`` (row, column) on ``device`` in ``dtype``: the (h, w) crop at ``origin``
        of the pattern ``pattern(r0 + h, c0 + w)``, of which only the window is hashed. A copy: editing it leaves the
        camera's code alone (the cameras read :meth:`cached_pattern`)."""
        return self.cached_pattern(h, w, device, dtype, origin).clone()

    def cached_pattern(self, h: int, w: int, device: torch.device | str | None = None,
                       dtype: torch.dtype = torch.float32, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """:meth:`pattern`'s window itself, cached for the last few windows and shared by every call that asks for
        it: never to be edited."""
        device = torch.device(device) if device is not None else torch.device("cpu")
        r0, c0 = int(origin[0]), int(origin[1])
        key = (h, w, r0, c0, str(device), dtype)
        p = self._cache.get(key)
        if p is not None:
            return p
        if self.array is None:
            p = random_aperture(h, w, self.seed, self.density, device, dtype, (r0, c0))
        else:
            ah, aw = self.array.shape
            if min(r0, c0) < 0:  # a slice from a negative start wraps round or comes back empty
                raise InputError(f"coded aperture {self.source or ''}: a window at row {r0}, column {c0} starts outside "
                                 f"its {ah}×{aw} px (rows and columns from 0)")
            if ah < r0 + h or aw < c0 + w:
                raise InputError(f"coded aperture {self.source or ''} is {ah}×{aw} px but {r0 + h}×{c0 + w} px are "
                                 f"needed (rows × columns, including the dispersion span)")
            p = self.array[r0:r0 + h, c0:c0 + w].to(device=device, dtype=dtype)
        if len(self._cache) >= 8:
            self._cache.clear()
        self._cache[key] = p
        return p

    def extra_repr(self) -> str:
        if self.array is not None:
            return f"array={tuple(self.array.shape)}, source={self.source!r}"
        return f"seed={self.seed}, density={self.density}"


# --------------------------------------------------------------------------------------------
# Dispersion
# --------------------------------------------------------------------------------------------
#: Pixels added before :func:`linear_dispersion` rounds a shift down: a product shift_px · c meant to be an exact
#: half is a few ulps below it in binary (0.7 · 45 = 31.499…, not 31.5), and the half must round up. 1e-9 px is
#: about 10^4 float64 ulps at a shift of 1000 px, and less than the 1e-8 px by which a product of a shift given to
#: 8 decimals misses a half when it is not one.
HALF_PX_ROUNDOFF = 1e-9


def linear_dispersion(n_bands: int, shift_px: float) -> list[int]:
    """d_c = ⌊shift_px · c + ½⌋, c = 0..C-1 (MST: shift_px = 2): halves round up, so the steps stay
    even (Python's round would send 1.5·3 = 4.5 to 4: [0, 2, 3, 4, 6]), with a tolerance of
    :data:`HALF_PX_ROUNDOFF` against round-off (0.7 px is 0.69999… in binary: 0.7·45 = 31.5 gave 31.499…, rounded
    down to 31)."""
    if not (shift_px > 0 and math.isfinite(shift_px)):
        raise ValueError(f"shift_px must be positive, got {shift_px}")
    return [int(math.floor(shift_px * c + 0.5 + HALF_PX_ROUNDOFF)) for c in range(n_bands)]


def prism_shifts_px(bands: Bands, material: str = "fused_silica", apex_deg: float = 30.0,
                    focal_length_m: float = 0.05, pixel_pitch_m: float = 6e-6,
                    material_key: str | None = None) -> np.ndarray:
    """Thin-prism dispersion (px, float64, not rounded), 0 for the least dispersed band.

    Deviation δ(λ) = (n(λ) − 1)·α; the lens after the prism maps the deviation difference to a
    sensor shift f·tan(δ(λ_0) − δ(λ)). Normal dispersion (n falls with λ) makes the shifts grow
    with the band index, faster in the blue than in the red. An absurd focal length gives huge (or, past
    float64, infinite) shifts, which :func:`check_dispersion_span` refuses. ``material_key``: the config key
    that named ``material``, said in a material table's refusal.
    """
    n = np.asarray(get_material(material, material_key).n(bands.centers_nm), dtype=np.float64)
    alpha = math.radians(apex_deg)
    delta = (n - 1.0) * alpha
    with np.errstate(over="ignore", invalid="ignore"):
        shift = focal_length_m * np.tan(delta[0] - delta) / pixel_pitch_m
        return shift - shift.min()


def prism_dispersion(bands: Bands, material: str = "fused_silica", apex_deg: float = 30.0,
                     focal_length_m: float = 0.05, pixel_pitch_m: float = 6e-6,
                     material_key: str | None = None) -> list[int]:
    """Thin-prism dispersion in whole pixels, d_0 = 0, for bands ascending in wavelength
    (:func:`prism_shifts_px` rounded)."""
    d = np.round(prism_shifts_px(bands, material, apex_deg, focal_length_m, pixel_pitch_m, material_key)).astype(int)
    return [int(v) for v in d]


#: The config key of the prism's material (a material table's refusal names it).
PRISM_MATERIAL_KEY = "camera.cassi.prism_material"


def dispersion_from_config(bands: Bands, cassi, pixel_pitch_um: float) -> list[int]:
    """Per-band shifts (px) of a ``camera.cassi`` config section."""
    if cassi.dispersion == "linear":
        return linear_dispersion(len(bands), cassi.shift_px)
    return prism_dispersion(bands, cassi.prism_material, cassi.prism_apex_deg, cassi.prism_focal_length_mm * 1e-3,
                            pixel_pitch_um * 1e-6, PRISM_MATERIAL_KEY)


#: Bytes per pixel of a CASSI sensor window while a scene is imaged: the float32 measurement, and the
#: int64 temporaries of hashing its coded-aperture window (:func:`hashed_uniform`: three live at once).
CASSI_BYTES_PER_SENSOR_PX = 4 + 3 * 8


def check_dispersion_span(cam, bands: Bands, scene_px: int,
                          scene_keys: str = "data.synthetic_size / data.patch_px") -> None:
    """ConfigError, before any shift is rounded or code is drawn, for a dispersion span D (the
    sensor's extra width across the bands, px) that is not finite or that widens the sensor beyond
    the memory budget (``camera.cassi.shift_px=1e30`` made the sensor 10^31 px wide).

    ``cam``: the camera section (:class:`hsicam.config.CameraConfig`). The bound: the sensor of one of
    the run's scenes, S × (S + D) px with S = ``scene_px`` (the side the run's scenes are generated and
    cut at, which the caller's ``scene_keys`` set), must fit the memory
    budget (:func:`hsicam.memory.memory_budget_bytes`) at :data:`CASSI_BYTES_PER_SENSOR_PX` bytes a
    pixel. Both cameras pay it: SD-CASSI's measurement is W + D wide, DD-CASSI hashes a code window
    W + D wide. Any real disperser (MST: 2 px per band over 28 bands, D = 54 px) is orders of
    magnitude below it; the span reaches it only when a key is orders of magnitude off.
    """
    cassi = cam.cassi
    if cassi.dispersion == "linear":
        span = cassi.shift_px * (len(bands) - 1)
        what = f"camera.cassi.shift_px={cassi.shift_px:g} px per band over {len(bands)} bands"
        fix = "set camera.cassi.shift_px to a few px (MST's CASSI: 2)"
    else:
        span = float(np.max(prism_shifts_px(bands, cassi.prism_material, cassi.prism_apex_deg,
                                            cassi.prism_focal_length_mm * 1e-3, cam.sensor.pixel_pitch_um * 1e-6,
                                            PRISM_MATERIAL_KEY)))
        what = (f"camera.cassi.dispersion=prism with camera.cassi.prism_focal_length_mm={cassi.prism_focal_length_mm:g}, "
                f"prism_apex_deg={cassi.prism_apex_deg:g} and prism_material={cassi.prism_material} over "
                f"{len(bands)} bands and {cam.sensor.pixel_pitch_um:g} µm pixels (camera.sensor.pixel_pitch_um)")
        fix = ("check camera.cassi.prism_focal_length_mm (in mm) and camera.cassi.prism_apex_deg (in degrees), "
               "or use camera.cassi.dispersion=linear")
    side = int(scene_px)
    budget = memory_budget_bytes()
    if not math.isfinite(span):
        raise ConfigError(f"{what} disperses the bands over an infinite span (the sensor's extra width); {fix}")
    need = CASSI_BYTES_PER_SENSOR_PX * side * (side + span)
    if need > budget:
        raise ConfigError(f"{what} disperses the bands over {span:.3g} px: the sensor of a {side} px scene "
                          f"({scene_keys}) would be {side + span:.3g} px wide and need "
                          f"{format_bytes(need)}, more than the memory budget of {format_bytes(budget)} "
                          f"({MEMORY_BUDGET_ENV}); {fix}")


# --------------------------------------------------------------------------------------------
# Pure forward models and adjoints
# --------------------------------------------------------------------------------------------
def _shift_index(shifts: Sequence[int], w: int, device: torch.device) -> torch.Tensor:
    """(C, w) column indices j + d_c."""
    d = torch.as_tensor(list(shifts), dtype=torch.int64, device=device)
    return torch.arange(w, dtype=torch.int64, device=device)[None, :] + d[:, None]


def dd_band_masks(aperture: torch.Tensor, shifts: Sequence[int], w: int) -> torch.Tensor:
    """Per-band DD-CASSI codes (C, H, w): M_c(i, j) = P(i, j + d_c); ``aperture`` is (H, w + D)."""
    idx = _shift_index(shifts, w, aperture.device)
    return aperture[:, idx].permute(1, 0, 2)


def dd_cassi_forward(x: torch.Tensor, masks: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """y = s · Σ_c M_c ⊙ x_c: (B, C, H, W), masks (C, H, W) → (B, 1, H, W)."""
    return (x * masks).sum(dim=1, keepdim=True) * scale


def dd_cassi_adjoint(y: torch.Tensor, masks: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """x_c = s · M_c ⊙ y: (B, 1, H, W) → (B, C, H, W)."""
    return y * masks * scale


def sd_cassi_forward(x: torch.Tensor, aperture: torch.Tensor, shifts: Sequence[int], scale: float = 1.0) -> torch.Tensor:
    """y(i, j) = s · Σ_c (P ⊙ x_c)(i, j − d_c): (B, C, H, W), P (H, W) → (B, 1, H, W + D)."""
    b, c, h, w = x.shape
    span = max(shifts)
    coded = (x * aperture).permute(0, 2, 1, 3).reshape(b, h, c * w)
    idx = _shift_index(shifts, w, x.device).reshape(-1)
    y = torch.zeros(b, h, w + span, dtype=coded.dtype, device=x.device).index_add(-1, idx, coded)
    return y.unsqueeze(1) * scale


def sd_cassi_adjoint(y: torch.Tensor, aperture: torch.Tensor, shifts: Sequence[int], scale: float = 1.0) -> torch.Tensor:
    """x_c(i, j) = s · P(i, j) · y(i, j + d_c): (B, 1, H, W + D) → (B, C, H, W)."""
    w = y.shape[-1] - max(shifts)
    idx = _shift_index(shifts, w, y.device)
    x = y[:, 0][:, :, idx]  # (B, H, C, W)
    return x.permute(0, 2, 1, 3) * aperture * scale


# --------------------------------------------------------------------------------------------
# Camera modules
# --------------------------------------------------------------------------------------------
class _CASSICamera(Camera):
    """Shared parts of the CASSI cameras (see the module docstring)."""

    has_diagonal_gram = True  # each sensor pixel sees each scene voxel at most once: A·Aᵀ is diagonal

    def __init__(self, bands: Bands, aperture: CodedAperture, shifts_px: Sequence[int], noise: SensorNoise | None = None,
                 convention: str = "mean", boundary: str = "valid") -> None:
        super().__init__()
        if boundary not in ("valid", "same"):
            raise ValueError(f"boundary must be 'valid' or 'same', got {boundary!r}")
        if convention not in ("sum", "mean"):
            raise ValueError(f"convention must be 'sum' or 'mean', got {convention!r}")
        shifts = [int(v) for v in shifts_px]
        if len(shifts) != len(bands):
            raise ValueError(f"{len(shifts)} dispersion shifts for {len(bands)} bands")
        if min(shifts) != 0:
            raise ValueError(f"dispersion shifts must be >= 0 with the smallest 0, got {shifts}")
        if len(set(shifts)) < len(shifts):
            log.warning("CASSI dispersion puts several bands on the same shift (%s): they see the same code", shifts)
        self.bands, self.aperture, self.shifts = bands, aperture, tuple(shifts)
        self.noise = noise if noise is not None else SensorNoise("none")
        self.convention, self.boundary = convention, boundary

    @classmethod
    def from_config(cls, cfg):  # cfg: hsicam.config.Config
        """Camera from a top-level config (``cfg.bands``, ``cfg.camera.cassi``, ``cfg.camera.sensor``)."""
        bands = cfg.bands.to_bands()
        cam = cfg.camera
        cassi = cam.cassi
        if cassi.mask_file is not None:
            aperture = CodedAperture.from_file(cassi.mask_file)
        else:
            aperture = CodedAperture(cassi.mask_seed, cassi.mask_density)
        check_dispersion_span(cam, bands, max(cfg.data.synthetic_size, cfg.data.patch_px))
        shifts = dispersion_from_config(bands, cassi, cam.sensor.pixel_pitch_um)
        s = cam.sensor
        noise = SensorNoise.from_config(s)
        return cls(bands, aperture, shifts, noise, cassi.convention, cam.boundary)

    @property
    def margin(self) -> int:
        return 0

    @property
    def span(self) -> int:
        """D: the dispersion of the last band relative to the first, in pixels."""
        return max(self.shifts)

    @property
    def scale(self) -> float:
        return 1.0 / len(self.bands) if self.convention == "mean" else 1.0

    @property
    def white_peak(self) -> float:
        """The most a white scene (all ones) can give a sensor pixel: C·scale, every band's code open there (1 with
        ``convention: mean``, the band count C with ``sum``): the range of the images a network of it trains on."""
        return self.scale * len(self.bands)

    def extra_repr(self) -> str:
        return f"bands={len(self.bands)}, shifts={self.shifts[0]}..{self.span} px, convention={self.convention}"

    def snapshot(self, generator: torch.Generator | None = None, *, nominal: bool = False) -> "CASSISnapshot":
        """The operator on sensor windows at any origin (nothing random to draw): :class:`CASSISnapshot`."""
        return CASSISnapshot(self)

    def measure(self, x: torch.Tensor, generator: torch.Generator | None = None):
        """(noisy measurement, the operator that made it). In training mode the patch is imaged
        through a random window of the aperture (offset drawn from ``generator``, uniform over
        :data:`TRAIN_APERTURE_PX` rows and columns, or over a file aperture), since a patch can lie
        anywhere on the sensor: a network trained on the top-left window alone learns that one
        code, not the camera's. In eval mode the window is the top-left one, as in :meth:`A`."""
        if not self.training:
            return self(x, generator), self
        h, w = x.shape[-2:]
        w_code = w + (self.span if isinstance(self, DDCASSICamera) else 0)
        arr = self.aperture.array
        rows, cols = (TRAIN_APERTURE_PX, TRAIN_APERTURE_PX) if arr is None else arr.shape
        dev = generator.device if generator is not None else torch.device("cpu")
        r0 = int(torch.randint(max(rows - h, 0) + 1, (1,), generator=generator, device=dev))
        c0 = int(torch.randint(max(cols - w_code, 0) + 1, (1,), generator=generator, device=dev))
        snap = CASSISnapshot(self, offset=(r0, c0))
        self.check_scene(x)
        return self.noise(snap.A(x), generator), snap


@register_camera("dd_cassi")
class DDCASSICamera(_CASSICamera):
    """Dual-disperser CASSI: scene (B, C, H, W) → measurement (B, 1, H, W)."""

    def band_masks(self, h: int, w: int, device: torch.device | str | None = None,
                   dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """The code each band sees, (C, h, w)."""
        return dd_band_masks(self.aperture.cached_pattern(h, w + self.span, device, dtype), self.shifts, w)

    def A(self, x: torch.Tensor) -> torch.Tensor:  # noqa: N802
        """Noiseless measurement (B, 1, H, W) of the scene ``x`` (B, C, H, W)."""
        self.check_scene(x)
        return dd_cassi_forward(x, self.band_masks(x.shape[-2], x.shape[-1], x.device, x.dtype), self.scale)

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:  # noqa: N802
        """Exact adjoint of :meth:`A`: (B, 1, H, W) → (B, C, H, W)."""
        self.check_measurement(y)
        return dd_cassi_adjoint(y, self.band_masks(y.shape[-2], y.shape[-1], y.device, y.dtype), self.scale)


@register_camera("sd_cassi")
class SDCASSICamera(_CASSICamera):
    """Single-disperser CASSI: scene (B, C, H, W) → measurement (B, 1, H, W + D)."""

    def sensor_size(self, scene_hw: tuple[int, int]) -> tuple[int, int]:
        return scene_hw[0], scene_hw[1] + self.span

    def scene_size(self, sensor_hw: tuple[int, int]) -> tuple[int, int]:
        """The scene (H, W − D) behind a sensor of ``sensor_hw`` (H, W) (W − D < 1 for a sensor no wider than the
        span: :meth:`check_measurement_width` refuses such a measurement)."""
        return sensor_hw[0], sensor_hw[1] - self.span

    def check_measurement_width(self, width: int) -> None:
        """InputError unless a measurement of ``width`` px is wider than the dispersion span (holds a scene)."""
        if width <= self.span:
            raise InputError(f"SD-CASSI measurement of width {width} is not wider than the dispersion span {self.span}")

    def A(self, x: torch.Tensor) -> torch.Tensor:  # noqa: N802
        """Noiseless measurement (B, 1, H, W + D) of the scene ``x`` (B, C, H, W)."""
        self.check_scene(x)
        p = self.aperture.cached_pattern(x.shape[-2], x.shape[-1], x.device, x.dtype)
        return sd_cassi_forward(x, p, self.shifts, self.scale)

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:  # noqa: N802
        """Exact adjoint of :meth:`A`: (B, 1, H, W + D) → (B, C, H, W)."""
        self.check_measurement(y)
        self.check_measurement_width(y.shape[-1])
        p = self.aperture.cached_pattern(y.shape[-2], y.shape[-1] - self.span, y.device, y.dtype)
        return sd_cassi_adjoint(y, p, self.shifts, self.scale)


class CASSISnapshot:
    """A CASSI camera's ``A`` / ``A_adjoint`` on a window of the sensor whose top-left pixel is ``origin``.

    The aperture window is taken at ``offset + origin`` (rows, columns of the scene grid; for
    SD-CASSI the window's scene columns are those of its first sensor column), so tiles see the
    code the whole image sees; ``offset`` (default (0, 0)) places the whole image on the aperture
    (a training patch at a random place). DD-CASSI: cube (B, C, h, w) ↔ (B, 1, h, w); SD-CASSI: (B, C, h, w − D) ↔
    (B, 1, h, w). ``lipschitz`` = s²·C ≥ ‖A‖² (ΦΦᵀ is diagonal with entries s² Σ_c P²).
    """

    def __init__(self, camera: "_CASSICamera", offset: tuple[int, int] = (0, 0)) -> None:
        self.camera, self.bands = camera, camera.bands
        self.offset = (int(offset[0]), int(offset[1]))
        if min(self.offset) < 0:
            raise ValueError(f"aperture offset must be >= 0, got {offset}")
        self.single = isinstance(camera, SDCASSICamera)
        self.lipschitz = camera.scale**2 * len(camera.bands)
        self.reach_px = (0, camera.span if self.single else 0)
        self.code_period = 1

    def scene_size(self, sensor_hw: tuple[int, int]) -> tuple[int, int]:
        """The cube (h, w′) behind a measured window of ``sensor_hw``; SD-CASSI: InputError unless it is wider than
        the dispersion span (the networks' start asked it of any capture: a narrower one reached torch as a
        negative size)."""
        if self.single:
            self.camera.check_measurement_width(sensor_hw[1])
        return self.camera.scene_size(sensor_hw)

    def sensor_code(self, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        raise NotImplementedError(f"{type(self.camera).__name__} has no per-band sensor code")

    def _aperture(self, h: int, w: int, origin: tuple[int, int], ref: torch.Tensor) -> torch.Tensor:
        check_origin(origin)  # a float, a None or a third item was taken as int(...) of the first two
        r0, c0 = self.offset[0] + int(origin[0]), self.offset[1] + int(origin[1])
        return self.camera.aperture.cached_pattern(h, w, ref.device, ref.dtype, (r0, c0))

    def A(self, x: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # noqa: N802
        self.camera.check_scene(x)
        h, w = x.shape[-2:]
        cam = self.camera
        if self.single:
            return sd_cassi_forward(x, self._aperture(h, w, origin, x), cam.shifts, cam.scale)
        return dd_cassi_forward(x, dd_band_masks(self._aperture(h, w + cam.span, origin, x), cam.shifts, w), cam.scale)

    def A_adjoint(self, y: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # noqa: N802
        cam = self.camera
        cam.check_measurement(y)
        h, w = y.shape[-2:]
        if self.single:
            w -= cam.span
            if w < 1:
                raise InputError(f"SD-CASSI measurement of width {y.shape[-1]} is not wider than the dispersion span {cam.span}")
            return sd_cassi_adjoint(y, self._aperture(h, w, origin, y), cam.shifts, cam.scale)
        return dd_cassi_adjoint(y, dd_band_masks(self._aperture(h, w + cam.span, origin, y), cam.shifts, w), cam.scale)

    def gram_diagonal(self, y: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """diag(ΦΦᵀ) on the sensor window of ``y`` (1, 1, h, w): ΦΦᵀ is diagonal, so it is A(Aᵀ𝟙)."""
        return self.A(self.A_adjoint(y.new_ones(1, 1, *y.shape[-2:]), origin), origin)


__all__ = [
    "CASSI_BYTES_PER_SENSOR_PX",
    "TRAIN_APERTURE_PX",
    "CASSISnapshot",
    "CodedAperture",
    "DDCASSICamera",
    "SDCASSICamera",
    "dd_band_masks",
    "dd_cassi_adjoint",
    "check_dispersion_span",
    "dd_cassi_forward",
    "dispersion_from_config",
    "hashed_bits",
    "hashed_uniform",
    "linear_dispersion",
    "load_aperture",
    "prism_dispersion",
    "prism_shifts_px",
    "random_aperture",
    "sd_cassi_adjoint",
    "sd_cassi_forward",
]
