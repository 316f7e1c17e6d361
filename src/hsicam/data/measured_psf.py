"""Measured PSFs from a folder of images, onto a camera's band grid, pixel pitch and kernel.

Measured PSFs (``--psf-dir DIR``)
---------------------------------
``DIR`` holds one image per wavelength (``.npy``, 8/16-bit PNG, integer or float TIFF), its
wavelength in the file name (``psf_450nm.tif``, ``450.png``, ``band-450.5nm.npy``), or one stack
``psf.npy`` (C, H, W) with ``bands_nm`` in ``psf.json`` (what ``hsicam psf`` writes): one per camera band, or a
monochromator sweep finer than the bands. The pixel
pitch of the images is ``pixel_pitch_um`` in ``DIR/psf.json`` (or the ``pitch_um`` argument).
Optional ``psf.json`` keys: ``centre`` (below), ``axis_px`` ([row, col] of the optical axis in
the images, pixel centres at integers; for ``axis``),
``background`` (``none`` | ``border`` | a number in the file's units), ``normalize`` (``sum`` |
``none``), ``wavelength_tolerance_nm`` (1 nm), ``fwhm_nm`` (the images' own bandwidth, a monochromator's: one number
or one per image; default the sweep's step). A folder written by ``hsicam psf`` (its
``psf.json`` has ``kernel_px``) is read with ``centre: axis`` at the kernel centre and
``normalize: none`` (its values are already energy fractions) by default.

Each band image is (1) background-subtracted, (2) normalised so it sums to 1
(``normalize: sum``: the image holds all the light of that band; the simulator's PSFs are also
normalised to 1 over the whole FFT plane), (3) centred: the centre point becomes the centre of
the kernel's centre pixel, and (4) resampled onto
the camera's K×K pixel grid by **exact area integration**: each source pixel spreads its energy
uniformly over its square and every camera pixel collects the overlap; (5) the kernel's negative pixels
(the measurement noise left by the background subtraction, where the PSF is dark) are set to 0. Steps 1–4 keep
the noise's sign: clipped at 0 before them, zero-mean noise became a positive floor over the whole frame, which
the normalisation counted as PSF light and the centroid as light at the frame's centre (a 401² px frame with 2 DN
of noise under a 30 000 DN peak: kernels summing to 0.55–0.68 of their light and centred ~40 px off; session 73). Centring and resampling
are one linear map (two 1-D overlap matrices, any pitch ratio, sub-pixel shifts included), so
energy is preserved; light falling outside the K×K kernel is reported (``energy_in_kernel``),
never renormalised away. A band keeping less than :data:`MIN_ENERGY_IN_KERNEL` of its image's
light in the kernel is an :class:`~hsicam.errors.InputError` (its PSF would be (nearly) black: a
wrong ``axis_px``, centre or pitch), less than :data:`LOW_ENERGY_IN_KERNEL` a warning.

Checks on each band image (one line naming the file and what to do):

* **Pixel pitch in the wrong unit** (:func:`implausible_pitch`, an :class:`InputError`): at
  ``pixel_pitch_um`` the image spans less than one camera pixel (``0.006`` for 6 µm, a pitch
  written in mm), or half of its light lies within a radius smaller than half the diffraction limit
  of the camera's aperture (:data:`AIRY_EE50` λ·N, N = sensor distance / aperture diameter; no
  PSF of that camera can be that small). Either way the camera's PSF would collapse to (nearly) a
  single pixel, and fine-tuning on it would remove the DOE's blur from the model.
* **Saturation** (:func:`saturated_pixels`): pixels of an integer image at the type's maximum (255,
  65535; in a 16-bit file also 1023, 4095 or 16383, the maximum of a 10-, 12- or 14-bit sensor, when
  that is the image's maximum) are clipped. :data:`SATURATED_MIN_PX` or more are a warning (once per
  image, a stack's band being one; one or two pixels at full scale are what an image scaled to its own maximum has);
  clipped pixels holding more than :data:`MAX_CLIPPED_LIGHT_SHARE` of the image's light (after the
  background) are an :class:`InputError`: the PSF's core is then mostly a flat plateau and, once
  normalised, its tails are over-weighted. Float images carry no clip level and are not checked.

Centring (``centre``): ``centroid`` (default) — the intensity centroid of the band-summed images,
**one shift for all bands**, so the bands keep their relative positions (a DOE's PSF centroid is
not its optical axis, and its band-to-band shifts are physics the network relies on); ``peak`` —
the brightest pixel of the band sum; ``axis`` — the known axis position ``axis_px`` (exact);
``centroid_per_band`` / ``peak_per_band`` — each band on its own centre (images of different
sizes or frames). When the camera pitch is an integer multiple n of the measurement pitch
(n = 1: PSFs measured with the camera's own sensor), the centre snaps to the nearest position
whose output pixels cover whole measured pixels, since a fractional shift would only blur.

A band's PSF (:func:`band_sources`, session 75). A band is a Gaussian of its FWHM, not a line (DESIGN §1): where the
sweep is finer than the band (the images' FWHM, by default the step, narrower than the band's by more than twice
``wavelength_tolerance_nm``) the band's PSF is the weighted average of the images within its reach, with the weights
:func:`~hsicam.spectral.bands.resampling_matrix` gives that band from the sweep's grid, the weights a scene's band
integrates its spectrum with; each image is imported as above (background, normalisation, centre, area resampling),
their kernels averaged, and only then the negative pixels set to 0. With ``normalize: none`` the average is of energy
fractions (the band's throughput is the weighted mean of the images'); a common centre (``centroid``, ``peak``) is found
on the sum over the bands of each band's weighted average, so every image a band uses counts; ``*_per_band`` centres a
band on its weighted average (its images in one frame, keeping their shifts within the band). A sweep as coarse as the
bands (one image per band centre, within the tolerance) gives each band its nearest image, bit for bit the import before
session 75. Every band still needs an image within ``wavelength_tolerance_nm`` of its centre (else refused); a band
whose ±3σ passes the sweep's end is averaged symmetrically over what the sweep covers (the resampling rule at the
edge of data) and warned about. The report lists each band's ``sources`` (wavelength, file, weight).

The stack is a :class:`~hsicam.runs.measured_psf.MeasuredPSF`; a fine-tuned run stores it
(:mod:`hsicam.runs.measured_psf`).
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from hsicam.data.images import MAX_IMAGE_PIXELS, read_image_2d
from hsicam.errors import InputError
from hsicam.io import npy_content_problem
from hsicam.runs.measured_psf import MeasuredPSF, psf_fingerprint
from hsicam.spectral import Bands
from hsicam.spectral.bands import BAND_REACH_SIGMA, BAND_TOL_NM, FWHM_PER_SIGMA, resampling_matrix, resolved_bands

log = logging.getLogger(__name__)

CENTRE_MODES = ("centroid", "peak", "axis", "centroid_per_band", "peak_per_band")
_WAVE_NM = re.compile(r"(\d+(?:\.\d+)?)\s*nm", re.IGNORECASE)
_NUMBER = re.compile(r"(?<![\d.])(\d{3,4}(?:\.\d+)?)(?![\d.])")
_IMAGE_SUFFIXES = (".npy", ".png", ".tif", ".tiff")
#: A band whose kernel keeps less than this share of its image's light is refused: its PSF would be
#: (nearly) black and the camera would image (nearly) nothing in that band.
MIN_ENERGY_IN_KERNEL = 0.01
#: Less than this share (most of the light lost outside the kernel) is warned about: the kernel is
#: too small for these PSFs, or the centre / axis_px / pitch is off.
LOW_ENERGY_IN_KERNEL = 0.5
#: Radius holding half the light of an aberration-free (Airy) PSF, in units of λ·N (N: f-number):
#: 1 − J0(v)² − J1(v)² = 1/2 at v = 1.680 = π r / (λ N). No PSF of a circular aperture of that
#: f-number concentrates half its light in a much smaller disc; a DOE or aberrations only widen it.
AIRY_EE50 = 0.5348
#: A measured image whose half-light radius is below this fraction of the Airy one is refused (its
#: pitch is in the wrong unit): a margin for an aperture a little larger than the config's.
MIN_DIFFRACTION_FRACTION = 0.5
#: This many pixels (or more) at an integer image's clip level are warned about (a clipped PSF).
SATURATED_MIN_PX = 3
#: Clipped pixels holding more than this share of an image's light (after the background) are refused.
MAX_CLIPPED_LIGHT_SHARE = 0.5
#: Maxima of 10-, 12- and 14-bit sensors: where a 16-bit file of such a sensor clips.
_SENSOR_MAXIMA = (1023.0, 4095.0, 16383.0)


# ------------------------------------------------------------------------------------------------
# Pure functions: area resampling, centring
# ------------------------------------------------------------------------------------------------
def overlap_matrix(n_out: int, pitch_out: float, first_edge_out: float, n_in: int, pitch_in: float) -> np.ndarray:
    """Fractions of each input pixel's energy that land in each output pixel, (n_out, n_in).

    Input pixel j covers [j·p_in, (j+1)·p_in); output pixel i covers
    [e + i·p_out, e + (i+1)·p_out) with e = ``first_edge_out`` (same length unit). Each column
    sums to the fraction of that input pixel inside the output window (1 when fully inside).
    """
    t_lo = first_edge_out + pitch_out * np.arange(n_out, dtype=np.float64)
    s_lo = pitch_in * np.arange(n_in, dtype=np.float64)
    lo = np.maximum(t_lo[:, None], s_lo[None, :])
    hi = np.minimum(t_lo[:, None] + pitch_out, s_lo[None, :] + pitch_in)
    return np.clip(hi - lo, 0.0, None) / pitch_in


def resample_area(image: np.ndarray, pitch_in: float, pitch_out: float, centre_in: tuple[float, float],
                  size_out: int) -> np.ndarray:
    """Energy-preserving resampling of ``image`` (H, W) onto a ``size_out``² grid of pitch ``pitch_out``.

    ``centre_in`` (row, col) is the point of the input (in input pixel units, pixel centres at
    integers) that becomes the centre of the output's centre pixel (size_out odd). Returns
    float64 (size_out, size_out); its sum equals the input's sum minus what falls outside.
    """
    if size_out < 1 or size_out % 2 == 0:
        raise ValueError(f"size_out must be odd, got {size_out}")
    h, w = image.shape
    half = (size_out // 2 + 0.5) * pitch_out
    # centre in length units: pixel j's centre is at (j + 0.5)·pitch_in
    cy, cx = (centre_in[0] + 0.5) * pitch_in, (centre_in[1] + 0.5) * pitch_in
    wy = overlap_matrix(size_out, pitch_out, cy - half, h, pitch_in)
    wx = overlap_matrix(size_out, pitch_out, cx - half, w, pitch_in)
    return wy @ np.asarray(image, dtype=np.float64) @ wx.T


def centroid(image: np.ndarray) -> tuple[float, float]:
    """Intensity centroid (row, col) in pixel units (pixel centres at integers)."""
    img = np.asarray(image, dtype=np.float64)
    total = img.sum()
    if not total > 0:
        raise InputError("PSF image has no positive signal (after background subtraction)")
    rows = np.arange(img.shape[0], dtype=np.float64)
    cols = np.arange(img.shape[1], dtype=np.float64)
    return float(img.sum(axis=1) @ rows / total), float(img.sum(axis=0) @ cols / total)


def _frame(image: np.ndarray) -> np.ndarray | None:
    """The outer frame's pixels of ``image`` (max(2, 5 %) of the smaller side), or None for an image too small."""
    img = np.asarray(image, dtype=np.float64)
    t = max(2, int(0.05 * min(img.shape)))
    if 2 * t >= min(img.shape):
        return None
    return np.concatenate([img[:t].ravel(), img[-t:].ravel(), img[t:-t, :t].ravel(), img[t:-t, -t:].ravel()])


def border_level(image: np.ndarray) -> float | None:
    """Median of the outer frame of ``image`` (``background: border``'s estimate), or None for an image too
    small to have a frame."""
    frame = _frame(image)
    return None if frame is None else float(np.median(frame))


def pedestal_level(image: np.ndarray) -> float | None:
    """The frame's median when the frame looks like a black level: flat (its 10th–90th percentile spread within
    half its median, noise on a pedestal) rather than the PSF's own tail, which varies across the frame; else None."""
    frame = _frame(image)
    if frame is None:
        return None
    level = float(np.median(frame))
    lo, hi = np.percentile(frame, [10, 90])
    return level if level > 0 and hi - lo <= 0.5 * level else None


#: A border median above this fraction of the image's peak, with ``background: none``, is warned about as a black
#: level counted as PSF light (a PSF's far tail is orders of magnitude below its peak; a 64 DN pedestal under a
#: 40 000 DN peak is 0.16 %, and already distorts the PSF by 0.67 of its peak on a 128 px frame).
PEDESTAL_FRACTION = 1e-3

#: How the images become PSFs, by version: 3 (session 75) gives a band of a sweep finer than the bands the weighted
#: average of its images (:func:`band_sources`; 2 took the nearest image); 2 (session 73) keeps the
#: background-subtracted noise's sign until the kernel (1, unrecorded: clipped at 0 first). The same folder imported by
#: another version may give other PSFs (a sweep as coarse as the bands gives the same ones): a fine-tuning made from it
#: says so (:func:`hsicam.runs.measured_psf.psf_difference`), not that its files changed.
PSF_IMPORT_VERSION = 3

#: A kernel whose clipped noise (its negative pixels set to 0) adds more than this share of the band's light is
#: warned about (:func:`_warn_folder`): the measured PSFs need more frames averaged.
NOISE_FLOOR_WARN = 0.02

#: With ``normalize: none`` an image is energy fractions of the band's light: a sum above this is refused.
MAX_UNNORMALISED_SUM = 1.05


def subtract_background(image: np.ndarray, background: str | float) -> tuple[np.ndarray, float]:
    """``image − b`` (float64, its noise keeping its sign: not clipped), with b = 0 (``none``), the median of the
    outer frame (``border``: a frame of max(2, 5 %) of the smaller side, :func:`border_level`), or the given
    number. Returns (image, b)."""
    img = np.asarray(image, dtype=np.float64)
    if background == "none":
        b = 0.0
    elif background == "border":
        level = border_level(img)
        if level is None:
            raise InputError(f"PSF image of {img.shape[0]}×{img.shape[1]} px is too small for border background estimation")
        b = level
    else:
        try:
            if isinstance(background, bool):  # psf.json's `true` is no level (float(True) read as 1)
                raise TypeError
            b = float(background)
        except (TypeError, ValueError):
            raise InputError(f"PSF background must be 'none', 'border' or a number, got {background!r}") from None
        if not math.isfinite(b):
            raise InputError(f"PSF background must be finite, got {background!r}")
    return img - b, b


@dataclass
class PSFImportOptions:
    """How measured PSF images become camera PSFs (see module docstring)."""

    pitch_um: float | None = None
    centre: str = "centroid"
    axis_px: tuple[float, float] | None = None
    background: str | float = "none"
    normalize: str = "sum"
    wavelength_tolerance_nm: float = 1.0
    #: FWHM (nm) of each image's light (a monochromator's bandwidth): one number or one per image; None: the sweep's
    #: local step (:func:`sweep_bands`)
    fwhm_nm: float | list[float] | None = None

    def check(self) -> None:
        if self.pitch_um is None:
            raise InputError("the measured PSFs' pixel pitch is unknown: put pixel_pitch_um in psf.json or pass --psf-pitch-um")
        if not (_is_number(self.pitch_um) and math.isfinite(self.pitch_um) and self.pitch_um > 0):  # true is no pitch
            raise InputError(f"PSF pixel pitch must be a positive number of µm, got {self.pitch_um!r}")
        if self.centre not in CENTRE_MODES:
            raise InputError(f"PSF centre must be one of {', '.join(CENTRE_MODES)}, got {self.centre!r}")
        if self.centre == "axis" and self.axis_px is None:
            raise InputError("PSF centre 'axis' needs axis_px [row, col] in psf.json")
        if self.normalize not in ("sum", "none"):
            raise InputError(f"PSF normalize must be 'sum' or 'none', got {self.normalize!r}")
        if not self.wavelength_tolerance_nm > 0:
            raise InputError("wavelength_tolerance_nm must be positive")
        f = self.fwhm_nm
        if f is not None and not all(_is_number(v) and math.isfinite(v) and v > 0 for v in (f if isinstance(f, list) else [f])):
            raise InputError(f"fwhm_nm (the images' bandwidth) must be a positive number of nm or a list of them, got {f!r}")


def snap_centre(c: float, pitch_in: float, pitch_out: float) -> float:
    """Move centre ``c`` (input pixel units) so the output pixels' edges fall on input pixel edges,
    when the camera pitch is an integer multiple n of the input pitch (n = 1: the camera's own
    pitch). A fractional shift would only blur such images; for other ratios ``c`` is returned."""
    ratio = pitch_out / pitch_in
    n = round(ratio)
    if n < 1 or abs(ratio - n) > 1e-6 * ratio:
        return c
    off = (n - 1) / 2.0
    return float(np.floor(c - off + 0.5) + off)


def prepare_psf_image(image: np.ndarray, opts: PSFImportOptions) -> tuple[np.ndarray, float, float]:
    """Background-subtracted (not clipped: its noise is zero-mean) and, with ``normalize: sum``, unit-sum image;
    returns (image float64, background, total signal before normalising)."""
    img, b = subtract_background(image, opts.background)
    total = float(img.sum())
    if not total > 0:
        raise InputError("PSF image has no positive signal (after background subtraction)")
    if opts.normalize == "sum":
        img = img / total
    return img, b, total


def saturated_pixels(image: np.ndarray, type_max: float | None) -> tuple[int, float, str]:
    """(count, level, what) of the pixels at which an integer image is clipped: those at the type's
    maximum ``type_max`` (255, 65535); for a 16-bit image without any, those at its own maximum when
    that is a 10/12/14-bit sensor's (1023, 4095, 16383). ``type_max`` None (a float image): (0, nan, "")."""
    if type_max is None:
        return 0, float("nan"), ""
    img = np.asarray(image)
    n = int(np.count_nonzero(img == type_max))
    if n:
        return n, float(type_max), "the file type's maximum"
    top = float(img.max()) if img.size else 0.0
    if type_max == 65535.0 and top in _SENSOR_MAXIMA:
        bits = {1023.0: 10, 4095.0: 12, 16383.0: 14}[top]
        return int(np.count_nonzero(img == top)), top, f"a {bits}-bit sensor's maximum"
    return 0, float(type_max), "the file type's maximum"


def half_light_radius_px(img: np.ndarray) -> float:
    """Radius (pixels) of the disc whose area is that of the fewest pixels holding half of the
    (non-negative) image's light: √(n/π). At least √(1/π) ≈ 0.56 (one pixel)."""
    v = np.sort(np.asarray(img, dtype=np.float64).ravel())[::-1]
    cum = np.cumsum(v)
    n = int(np.searchsorted(cum, 0.5 * cum[-1])) + 1
    return math.sqrt(n / math.pi)


def implausible_pitch(img: np.ndarray, pitch_um: float, camera_pixel_m: float, wavelength_nm: float,
                      f_number: float | None, psf: np.ndarray, pitch_from: str) -> str | None:
    """Why ``pitch_um`` cannot be the pixel pitch of the measured image ``img`` (background-subtracted,
    non-negative) — it spans less than one camera pixel, or its light is more concentrated than the
    camera's aperture (f-number ``f_number``; None: not checked) can focus it at ``wavelength_nm`` —
    else None. ``psf``: the image resampled onto the camera's kernel (its largest pixel is quoted);
    ``pitch_from``: where the pitch came from (named in the message)."""
    pitch_m = pitch_um * 1e-6
    span_um = max(img.shape) * pitch_um
    span_px = span_um * 1e-6 / camera_pixel_m
    total = float(psf.sum())
    one = f"{float(psf.max()) / total:.0%}" if total > 0 else "all"
    unit = (f"the pitch looks like it is in the wrong unit ({pitch_um:g} mm would be {pitch_um * 1e3:g} µm): give "
            f"the images' pixel pitch in µm ({pitch_from})")
    if span_px < 1.0:
        return (f"at pixel_pitch_um {pitch_um:g} the {img.shape[0]}×{img.shape[1]} px image spans {span_um:.3g} µm, "
                f"{span_px:.3g} of one {camera_pixel_m * 1e6:g} µm camera pixel, so the camera's PSF would be a single "
                f"pixel ({one} of its light in one pixel); {unit}")
    if f_number is None or not f_number > 0:
        return None
    r50 = half_light_radius_px(img) * pitch_m
    airy = AIRY_EE50 * wavelength_nm * 1e-9 * f_number
    if r50 >= MIN_DIFFRACTION_FRACTION * airy:
        return None
    return (f"at pixel_pitch_um {pitch_um:g} half of the image's light lies within {r50 * 1e6:.3g} µm of its centre, "
            f"{airy / r50:.3g}× less than the smallest spot the camera's f/{f_number:.3g} aperture can form at "
            f"{wavelength_nm:g} nm ({airy * 1e6:.3g} µm, the diffraction limit); the {img.shape[0]}×{img.shape[1]} px "
            f"image spans {span_px:.3g} camera pixels and its PSF would put {one} of its light in one pixel; {unit}")


def find_centre(img: np.ndarray, mode: str, axis_px: tuple[float, float] | None = None) -> tuple[float, float]:
    """Centre (row, col), pixel centres at integers: intensity centroid, brightest pixel or the given axis."""
    if mode in ("centroid", "centroid_per_band"):
        return centroid(img)
    if mode in ("peak", "peak_per_band"):
        r, q = np.unravel_index(int(np.argmax(img)), img.shape)
        return float(r), float(q)
    if axis_px is None:
        raise InputError("PSF centre 'axis' needs axis_px [row, col]")
    r, c = float(axis_px[0]), float(axis_px[1])
    h, w = img.shape
    if not (-0.5 <= r <= h - 0.5 and -0.5 <= c <= w - 0.5):  # the image spans -0.5 … n − 0.5 (pixel centres at integers)
        raise InputError(f"axis_px [{r:g}, {c:g}] (psf.json) lies outside the {h}×{w} px PSF image "
                         f"(row -0.5…{h - 0.5:g}, col -0.5…{w - 0.5:g}; [row, col] of the optical axis in image pixels)")
    return r, c


def import_psf_image(image: np.ndarray, pitch_m: float, camera_pixel_m: float, kernel_px: int,
                     opts: PSFImportOptions, centre: tuple[float, float] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """One measured PSF image (H, W) → camera PSF (K, K) float64 and a report (see module docstring).

    ``centre`` (row, col; e.g. a centre shared by all bands) overrides ``opts.centre``.
    """
    psf, report, _, _ = _image_kernel(image, pitch_m, camera_pixel_m, kernel_px, opts, centre)
    return psf, report


def _image_kernel(image: np.ndarray, pitch_m: float, camera_pixel_m: float, kernel_px: int, opts: PSFImportOptions,
                  centre: tuple[float, float] | None) -> tuple[np.ndarray, dict[str, Any], np.ndarray, float]:
    """:func:`import_psf_image`'s (PSF, report) and also the kernel before its negative pixels are set to 0 (K, K)
    and the image's light (its sum after the background and normalisation: 1 with ``normalize: sum``)."""
    img, b, _ = prepare_psf_image(image, opts)
    c = centre if centre is not None else find_centre(img, opts.centre, opts.axis_px)
    c = (snap_centre(c[0], pitch_m, camera_pixel_m), snap_centre(c[1], pitch_m, camera_pixel_m))
    signed = resample_area(img, pitch_m, camera_pixel_m, c, kernel_px)
    psf = np.clip(signed, 0.0, None)  # a PSF has no negative light: the kernel's dark pixels' noise
    clipped = float(psf.sum() - signed.sum())
    energy_in = float(img.sum())
    report = {
        "source_shape": [int(s) for s in image.shape],
        "background": b,
        "centre_px": [c[0], c[1]],
        "centre_offset_px": [c[0] - (image.shape[0] - 1) / 2, c[1] - (image.shape[1] - 1) / 2],
        # of the image's light, as measured (its noise zero-mean): without the floor the clip below adds
        "energy_in_kernel": float(signed.sum() / energy_in) if energy_in > 0 else 0.0,
        "kernel_sum": float(psf.sum()),  # the PSF's total (1 for all the light with normalize: sum)
        # the light the kernel's negative pixels set to 0 added (of the image's light): a noise floor (kernel_sum
        # is that much above the light measured in the kernel)
        "noise_clipped": clipped / energy_in if energy_in > 0 else 0.0,
    }
    return psf, report, signed, energy_in


# ------------------------------------------------------------------------------------------------
# A PSF folder → the camera's (C, K, K) stack
# ------------------------------------------------------------------------------------------------
def wavelength_from_name(name: str) -> float | None:
    """Wavelength (nm) in a file stem: ``…450nm…`` / ``…450.5 nm…``, else a lone 3–4 digit number."""
    m = _WAVE_NM.findall(name)
    if len(m) == 1:
        return float(m[0])
    if len(m) > 1:
        return None
    nums = _NUMBER.findall(name)
    return float(nums[0]) if len(nums) == 1 else None


def _read_manifest(d: Path) -> dict[str, Any]:
    p = d / "psf.json"
    if not p.is_file():
        return {}
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: not valid JSON ({str(exc).splitlines()[0]})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{p}: must be a JSON object")
    return meta


def _is_number(v: Any) -> bool:
    """A JSON number (``true`` / ``false`` are bools, which Python counts as ints: an axis at [true, false] is no
    position)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def options_from_manifest(meta: dict[str, Any], pitch_um: float | None = None, centre: str | None = None,
                          background: str | float | None = None, folder: Path | None = None) -> PSFImportOptions:
    """Import options: arguments first, then ``psf.json`` keys, then defaults. ``folder``: the PSF folder, named in
    every refusal."""
    where = folder / "psf.json" if folder is not None else "psf.json"
    axis = meta.get("axis_px")
    if axis is None and centre is None and "centre" not in meta and isinstance(meta.get("kernel_px"), int):
        # written by `hsicam psf`: simulated kernels with the optical axis on the centre pixel
        k = meta["kernel_px"]
        axis, centre = [(k - 1) / 2, (k - 1) / 2], "axis"
        meta = {"normalize": "none", **meta}  # already energy fractions of the whole FFT plane
    if axis is not None:
        if not (isinstance(axis, list) and len(axis) == 2 and all(_is_number(v) for v in axis)):
            raise InputError(f"{where}: axis_px must be [row, col], got {axis!r}")
        axis = (float(axis[0]), float(axis[1]))
    tol = meta.get("wavelength_tolerance_nm", 1.0)
    if not _is_number(tol):
        raise InputError(f"{where}: wavelength_tolerance_nm must be a number")
    opts = PSFImportOptions(
        pitch_um=pitch_um if pitch_um is not None else meta.get("pixel_pitch_um"),
        centre=centre or meta.get("centre", "centroid"),
        axis_px=axis,
        background=background if background is not None else meta.get("background", "none"),
        normalize=meta.get("normalize", "sum"),
        wavelength_tolerance_nm=float(tol),
        fwhm_nm=meta.get("fwhm_nm"),
    )
    try:
        opts.check()
    except InputError as exc:
        if folder is None:
            raise
        raise InputError(f"{folder}: {exc}") from None
    return opts


def _list_band_images(d: Path, meta: dict[str, Any]) -> list[tuple[float, Path, np.ndarray, float | None]]:
    """(wavelength nm, file, image as stored (float64), the integer type's maximum or None for a
    float image) for every PSF in the folder."""
    stack = d / "psf.npy"
    if stack.is_file():  # a stack (what `hsicam psf` writes, beside files of no wavelength), never band files
        if "bands_nm" not in meta:
            raise InputError(f"{stack}: a PSF stack needs its wavelengths: bands_nm in {d / 'psf.json'}"
                             + ("" if (d / "psf.json").is_file() else ", which is missing"))
        return _read_psf_stack(d, stack, meta["bands_nm"])
    return _read_band_files(d)


def _check_bands_nm(d: Path, bands: Any) -> None:
    """Refuse a ``bands_nm`` in ``psf.json`` that is not a list of distinct wavelengths in nm."""
    if not (isinstance(bands, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in bands)):
        raise InputError(f"{d / 'psf.json'}: bands_nm must be a list of numbers")
    bad = [v for v in bands if not (math.isfinite(v if isinstance(v, float) else 1.0) and 0 < v < 1e6)]
    if bad:
        raise InputError(f"{d / 'psf.json'}: bands_nm must hold wavelengths in nm (finite, > 0), got {bad[0]!r}")
    twice = sorted({float(v) for v in bands if bands.count(v) > 1})
    if twice:
        raise InputError(f"{d / 'psf.json'}: bands_nm names {twice[0]:g} nm more than once (one PSF per wavelength)")


def _read_psf_stack(d: Path, stack: Path, bands: Any) -> list[tuple[float, Path, np.ndarray, float | None]]:
    """:func:`_list_band_images` of a ``psf.npy`` (C, H, W) stack whose wavelengths are ``bands_nm`` in
    ``psf.json``: every band's entry names the stack's file."""
    _check_bands_nm(d, bands)
    try:
        problem = npy_content_problem(stack)  # np.load calls any other content "pickled data", advising allow_pickle
        if problem is not None:
            raise InputError(f"{stack}: not a .npy file ({problem}); save the PSF stack (C, H, W) with numpy.save")
        arr = np.load(stack, mmap_mode="r", allow_pickle=False)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{stack}: not a readable .npy file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if arr.ndim != 3 or arr.shape[0] != len(bands):
        raise InputError(f"{stack}: expected a (C, H, W) stack with C = {len(bands)} (bands_nm), got shape {arr.shape}")
    if arr.dtype.kind not in "uif":
        raise InputError(f"{stack}: unsupported data type {arr.dtype}")
    if arr.shape[1] * arr.shape[2] > MAX_IMAGE_PIXELS or min(arr.shape) == 0:
        raise InputError(f"{stack}: unusable PSF stack shape {arr.shape}")
    data = np.array(arr, dtype=np.float64)
    if not np.all(np.isfinite(data)):
        raise InputError(f"{stack}: PSF stack contains NaN or Inf values")
    type_max = float(np.iinfo(arr.dtype).max) if arr.dtype.kind in "ui" else None
    return [(float(w), stack, data[i], type_max) for i, w in enumerate(bands)]


def _read_band_files(d: Path) -> list[tuple[float, Path, np.ndarray, float | None]]:
    """:func:`_list_band_images` of a folder of one image per band, each named with its wavelength (all
    names are checked before any image is read)."""
    items = []
    for f in sorted(d.iterdir()):
        if f.name.startswith(".") or f.suffix.lower() not in _IMAGE_SUFFIXES or not f.is_file():
            continue
        w = wavelength_from_name(f.stem)
        if w is None:
            raise InputError(f"{f}: cannot tell the wavelength from the file name (use e.g. psf_450nm{f.suffix})")
        items.append((w, f))
    if not items:
        raise InputError(f"{d}: no PSF images (*.npy, *.png, *.tif named with their wavelength, or psf.npy + psf.json)")
    waves = [w for w, _ in items]
    if len(set(waves)) != len(waves):
        raise InputError(f"{d}: two PSF images name the same wavelength")
    out = []
    for w, f in items:
        raw = read_image_2d(f, "PSF image")
        type_max = raw.full_scale if np.dtype(raw.dtype).kind in "ui" else None
        out.append((w, f, raw.data.astype(np.float64), type_max))
    return out


def _check_saturation(items: list[tuple[float, Path, np.ndarray, float | None]], chosen: list[int],
                      opts: PSFImportOptions) -> dict[int, int]:
    """{item index: clipped pixels} of the images the bands use (:func:`saturated_pixels`): a warning
    per image (file, or band of a stack) with :data:`SATURATED_MIN_PX` or more, an :class:`InputError` when they hold more than
    :data:`MAX_CLIPPED_LIGHT_SHARE` of its light (after the background)."""
    out: dict[int, int] = {}
    for j in dict.fromkeys(chosen):  # once per image (a stack's band is one), in band order
        w, f, img, type_max = items[j]
        n, level, what = saturated_pixels(img, type_max)
        out[j] = n
        if n < SATURATED_MIN_PX:
            continue
        try:
            bs, _, total = prepare_psf_image(img, PSFImportOptions(pitch_um=opts.pitch_um, background=opts.background,
                                                                  normalize="none"))
        except InputError:  # nothing above the background: clipped up to its border (the frame's median, which
            # `background: border` subtracts, is the clipping level), else refused without signal, with its name, below
            if n == img.size or border_level(img) == level:
                raise InputError(f"{f} ({w:g} nm): a clipped (over-exposed) PSF image: {n} of its {img.size} pixels "
                                 f"are at {level:g} ({what}), the median of its border too, so nothing is left above the background: "
                                 f"measure it again with a shorter exposure (brightest pixel below {level:g})") from None
            continue
        share = float(bs[img == level].sum()) / total
        where = f"{n} of its {img.size} pixels are at {level:g} ({what}), holding {share:.0%} of its light"
        if share > MAX_CLIPPED_LIGHT_SHARE:
            raise InputError(f"{f} ({w:g} nm): a clipped (over-exposed) PSF image: {where}, more than the "
                             f"{MAX_CLIPPED_LIGHT_SHARE:.0%} allowed; its core would be a flat plateau and its tails "
                             "over-weighted: measure it again with a shorter exposure (brightest pixel below "
                             f"{level:g})")
        log.warning("%s (%g nm): a clipped (over-exposed) PSF image: %s; its core is flattened and, normalised, its "
                    "tails over-weighted: measure it again with a shorter exposure (brightest pixel below %g)",
                    f, w, where, level)
    return out


def import_psf_dir(psf_dir: str | Path, bands: Bands, camera_pixel_m: float, kernel_px: int,
                   pitch_um: float | None = None, centre: str | None = None,
                   background: str | float | None = None, f_number: float | None = None) -> MeasuredPSF:
    """Measured PSFs of ``psf_dir`` on the camera's bands, pixel pitch and K×K kernel.

    Every camera band needs a PSF whose wavelength is within ``wavelength_tolerance_nm``; extra
    wavelengths are ignored, except in a sweep finer than the bands, whose images within a band's reach are averaged
    with the band's weights (:func:`band_sources`). Raises :class:`InputError` for anything unusable, including a
    pitch in the wrong unit (:func:`implausible_pitch`; the diffraction test needs the camera's ``f_number``)
    and images clipped over more than :data:`MAX_CLIPPED_LIGHT_SHARE` of their light; warns (once per
    image: each band of a ``psf.npy`` stack is one, named by its wavelength) about :data:`SATURATED_MIN_PX` or more clipped pixels.
    """
    d = _psf_folder(psf_dir)
    meta = _read_manifest(d)
    items = _list_band_images(d, meta)  # first: a folder without images needs no pitch to be refused
    opts = options_from_manifest(meta, pitch_um, centre, background, folder=d)
    sources = band_sources(d, [w for w, _, _, _ in items], bands, opts)
    used = list(dict.fromkeys(j for src in sources for j, _ in src))  # every image a band uses, in band order
    saturated = _check_saturation(items, used, opts)
    pitch_from = "--psf-pitch-um" if pitch_um is not None else f"pixel_pitch_um in {d / 'psf.json'}"
    common = _common_centre(d, items, sources, opts)
    floors = []
    for j in used:
        w, f, img, _ = items[j]
        _check_unnormalised_sum(w, f, img, opts)
        floor = _pedestal_note(w, f, img, opts)
        if floor is not None:
            floors.append(floor)
    stack, per_band, low, noisy = [], [], [], []
    for lam, src in zip(bands.centers_nm, sources):
        if len(src) == 1:  # one image (a sweep as coarse as the bands): that image's PSF
            w, f, img, _ = items[src[0][0]]
            psf, rep, _, _ = _band_psf(w, f, img, opts, camera_pixel_m, kernel_px, f_number, pitch_from, common)
            entry = {"band_nm": float(lam), "wavelength_nm": w, "file": f.name, **rep,
                     "saturated_px": saturated[src[0][0]], "sources": [{"wavelength_nm": w, "file": f.name, "weight": 1.0}]}
            name = f"{f.name} ({w:g} nm)"
        else:
            psf, entry = _averaged_band_psf(d, float(lam), src, items, opts, camera_pixel_m, kernel_px, f_number,
                                            pitch_from, common, saturated)
            name = entry["name"]
        e = entry["energy_in_kernel"]
        if e < LOW_ENERGY_IN_KERNEL:
            low.append(f"{name}: {100 * e:.0f} %")
        if entry["noise_clipped"] > NOISE_FLOOR_WARN:
            noisy.append((name, entry["noise_clipped"]))
        stack.append(psf)
        per_band.append(entry)
    _warn_folder(d, kernel_px, floors, low, noisy, len(sources))
    _warn_coarse_pitch(opts, camera_pixel_m)
    _warn_cut_bands(d, [w for w, _, _, _ in items], bands, sources, opts)
    return _measured_psf(d, bands, opts, camera_pixel_m, kernel_px, stack, per_band)


def _psf_folder(psf_dir: str | Path) -> Path:
    """``psf_dir`` as a Path, refused when it is a file or does not exist."""
    d = Path(psf_dir)
    if d.exists() and not d.is_dir():
        raise InputError(f"{d}: is a file, not a folder: --psf-dir takes the folder that holds the measured PSF images "
                         "(one per band, named with their wavelength, e.g. psf_450nm.tif, or psf.npy + psf.json)")
    if not d.is_dir():
        raise InputError(f"{d}: no such PSF folder")
    return d


def _match_bands(d: Path, waves: Sequence[float], bands: Bands, opts: PSFImportOptions) -> list[int]:
    """Index into ``waves`` (the images' wavelengths, nm) of the nearest wavelength for each camera band; refuses the
    bands without one within ``wavelength_tolerance_nm``."""
    waves = np.asarray(waves, dtype=np.float64)
    chosen, missing = [], []
    for lam in bands.centers_nm:
        j = int(np.argmin(np.abs(waves - lam)))
        if abs(waves[j] - lam) > opts.wavelength_tolerance_nm:
            missing.append(f"{lam:g}")
        chosen.append(j)
    if missing:
        raise InputError(f"{d}: no measured PSF for band(s) {', '.join(missing)} nm "
                         f"(found {', '.join(f'{w:g}' for w in sorted(waves))} nm; tolerance {opts.wavelength_tolerance_nm:g} nm)")
    return chosen


def sweep_bands(d: Path, waves: Sequence[float], opts: PSFImportOptions) -> tuple[Bands, np.ndarray]:
    """The images' wavelengths as a band grid, and the order (indices into ``waves``) that sorts them: each image
    stands for a band of ``opts.fwhm_nm`` (the monochromator's bandwidth: one number, or one per image in the order
    of ``bands_nm`` / of ascending wavelength for files) or, not given, of the sweep's local step
    (:meth:`Bands.from_centers`, the rule of a cube whose file lists no FWHM)."""
    order = np.argsort(np.asarray(waves, dtype=np.float64), kind="stable")
    centres = np.asarray(waves, dtype=np.float64)[order]
    fwhm = opts.fwhm_nm
    if isinstance(fwhm, list):
        if len(fwhm) != len(centres):
            raise InputError(f"{d / 'psf.json'}: fwhm_nm lists {len(fwhm)} values for {len(centres)} PSF images "
                             "(one number for all, or one per image)")
        fwhm = [fwhm[int(k)] for k in order] if (d / "psf.npy").is_file() else fwhm  # a stack's in bands_nm order
    return Bands.from_centers(centres, fwhm), order


def finer_than_bands(sweep: Bands, bands: Bands, opts: PSFImportOptions) -> np.ndarray:
    """Boolean (len(bands),): True where the sweep (:func:`sweep_bands`) is finer than the band, so its images are
    averaged: its images' FWHM (``fwhm_nm``, else the local step) narrower than the band's
    (:func:`~hsicam.spectral.bands.resolved_bands`) and its local step narrower than the band's FWHM by more than
    twice ``wavelength_tolerance_nm``: images within the tolerance of a grid as coarse as the bands (10 nm bands
    measured at 440.4, 449.6, 460.3 nm) are each band's nearest image, not 0.7 % of a neighbour mixed in by a step
    0.4 nm short; and a coarse sweep of a narrow monochromator (``fwhm_nm`` 2 nm every 10 nm under 10 nm bands) is
    not averaged into ghost copies of the PSF 10 nm away (session 75's review: it was, with ``fwhm_nm`` given)."""
    finer = resolved_bands(sweep, bands)
    step = np.interp(bands.centers_nm, sweep.centers_nm, Bands.from_centers(sweep.centers_nm).fwhm_nm)
    return finer & (step < bands.fwhm_nm - 2.0 * opts.wavelength_tolerance_nm)


def band_sources(d: Path, waves: Sequence[float], bands: Bands, opts: PSFImportOptions) -> list[list[tuple[int, float]]]:
    """For each camera band, the images (indices into ``waves``, the images' wavelengths in nm) whose PSFs it averages
    and their weights (summing to 1).

    Every band needs an image within ``wavelength_tolerance_nm`` of its centre (:func:`_match_bands`, else refused).
    Where the sweep is finer than the band (:func:`finer_than_bands`) the band's PSF is its band average: the weights are the
    band's row of :func:`~hsicam.spectral.bands.resampling_matrix` from the sweep onto the camera's bands, the weights
    a scene's band integrates its spectrum with. Elsewhere, and for a band whose centre lies outside the sweep's
    range (by less than the tolerance), the nearest image with weight 1: a sweep as coarse as the bands gives each
    band its nearest image, as before session 75."""
    chosen = _match_bands(d, waves, bands, opts)
    out = [[(j, 1.0)] for j in chosen]
    if len(waves) < 2:
        return out
    sweep, order = sweep_bands(d, waves, opts)
    inside = (bands.centers_nm >= sweep.min_nm - BAND_TOL_NM) & (bands.centers_nm <= sweep.max_nm + BAND_TOL_NM)
    k = np.flatnonzero(inside)
    if not len(k):
        return out
    dst = Bands(bands.centers_nm[k], bands.fwhm_nm[k])
    finer = finer_than_bands(sweep, dst, opts)
    rows = resampling_matrix(sweep, dst)
    for i, row in zip(k[finer], rows[finer]):
        nz = np.flatnonzero(row > 0.0)
        if len(nz) > 1:
            out[i] = [(int(order[m]), float(row[m])) for m in nz]
    return out


def _one_frame(d: Path, items: list[tuple[float, Path, np.ndarray, float | None]], used: Sequence[int]) -> None:
    """Refuse images (indices into ``items``) of different sizes: one centre for them needs one frame."""
    shapes = {items[j][2].shape for j in used}  # type: ignore[union-attr]
    if len(shapes) != 1:
        raise InputError(f"{d}: PSF images have different sizes {sorted(shapes)}; a common centre needs one frame "
                         "(use centre: centroid_per_band or axis in psf.json)")


def _unit_sum_average(d: Path, items: list[tuple[float, Path, np.ndarray, float | None]],
                      src: list[tuple[int, float]], opts: PSFImportOptions) -> np.ndarray:
    """Σ weight · image / Σ image over a band's images (``src``: (index into ``items``, weight)), each prepared
    (:func:`prepare_psf_image`); refuses images of different sizes (one centre needs one frame)."""
    _one_frame(d, items, [j for j, _ in src])
    total = None
    for j, wt in src:
        try:
            img, _, _ = prepare_psf_image(items[j][2], opts)  # type: ignore[arg-type]
        except InputError as exc:
            raise InputError(f"{items[j][1]} ({items[j][0]:g} nm): {exc}") from None
        img = img / img.sum()
        if wt != 1.0:
            img = wt * img
        total = img if total is None else total + img
    return total  # type: ignore[return-value]


def _common_centre(d: Path, items: list[tuple[float, Path, np.ndarray, float | None]],
                   sources: list[list[tuple[int, float]]], opts: PSFImportOptions) -> tuple[float, float] | None:
    """With ``centre: centroid`` or ``peak``, that centre of the sum over the bands of each band's unit-sum image
    (a band averaging several images: their weighted average, :func:`_unit_sum_average`, so every image a band uses
    counts); else None (each band finds its own)."""
    if opts.centre not in ("centroid", "peak"):
        return None
    # one centre for all bands: keeps their relative positions
    _one_frame(d, items, [j for src in sources for j, _ in src])
    total = None
    for src in sources:
        img = _unit_sum_average(d, items, src, opts)
        total = img if total is None else total + img
    return find_centre(total, opts.centre)


def _check_unnormalised_sum(w: float, f: Path, img: np.ndarray, opts: PSFImportOptions) -> None:
    """With ``normalize: none``, refuse an image summing to more than :data:`MAX_UNNORMALISED_SUM`."""
    if opts.normalize != "none":
        return
    # counts read as energy fractions: a camera ×10⁵ too bright
    try:
        total = prepare_psf_image(img, opts)[2]
    except InputError as exc:
        raise InputError(f"{f} ({w:g} nm): {exc}") from None
    if total > MAX_UNNORMALISED_SUM:
        raise InputError(f"{f} ({w:g} nm): with normalize: none a PSF image holds fractions of the band's "
                         f"light, but this one sums to {total:.4g} (counts?): set normalize: sum in psf.json")


def _pedestal_note(w: float, f: Path, img: np.ndarray, opts: PSFImportOptions) -> str | None:
    """With ``background: none``, "file (λ nm): level %" for an image whose border looks like a black level above
    :data:`PEDESTAL_FRACTION` of its peak; else None."""
    level = pedestal_level(img) if opts.background == "none" else None
    if level is not None and level > PEDESTAL_FRACTION * float(np.max(img)):
        return f"{f.name} ({w:g} nm): {100 * level / float(np.max(img)):.2g} %"
    return None


def _band_psf(w: float, f: Path, img: np.ndarray, opts: PSFImportOptions, camera_pixel_m: float, kernel_px: int,
              f_number: float | None, pitch_from: str,
              common: tuple[float, float] | None) -> tuple[np.ndarray, dict[str, Any], np.ndarray, float]:
    """One image's camera PSF and report (:func:`import_psf_image`), with its kernel before the clip and its light
    (:func:`_image_kernel`), refused for an implausible pitch or less than :data:`MIN_ENERGY_IN_KERNEL` of its light
    in the kernel; every refusal names the file."""
    try:
        psf, rep, signed, light = _image_kernel(img, opts.pitch_um * 1e-6, camera_pixel_m, kernel_px, opts, common)  # type: ignore[operator]
    except InputError as exc:
        raise InputError(f"{f} ({w:g} nm): {exc}") from None
    bs = prepare_psf_image(img, opts)[0]
    why = implausible_pitch(bs, opts.pitch_um, camera_pixel_m, w, f_number, psf, pitch_from)  # type: ignore[arg-type]
    if why:
        raise InputError(f"{f} ({w:g} nm): {why}")
    e = rep["energy_in_kernel"]
    if not e >= MIN_ENERGY_IN_KERNEL:
        raise InputError(f"{f} ({w:g} nm): only {100 * e:.3g} % of the PSF's light falls in the camera's "
                         f"{kernel_px}×{kernel_px} px kernel (centred on row {rep['centre_px'][0]:g}, col "
                         f"{rep['centre_px'][1]:g} of the {img.shape[0]}×{img.shape[1]} px image, centre: "
                         f"{opts.centre}); check axis_px / centre and pixel_pitch_um in psf.json (or --psf-pitch-um)")
    return psf, rep, signed, light


def _averaged_band_psf(d: Path, lam: float, src: list[tuple[int, float]],
                       items: list[tuple[float, Path, np.ndarray, float | None]], opts: PSFImportOptions,
                       camera_pixel_m: float, kernel_px: int, f_number: float | None, pitch_from: str,
                       common: tuple[float, float] | None, saturated: dict[int, int]) -> tuple[np.ndarray, dict[str, Any]]:
    """The PSF (K, K) of a band that averages several images (``src``: (index into ``items``, weight)) and its report
    entry. Each image is imported as one band's (:func:`_band_psf`, same checks) on the common centre, or with a
    ``*_per_band`` centre on the centre of the band's weighted average (:func:`_unit_sum_average`: the images keep
    their shifts within the band), or ``axis``; their kernels are averaged before the negative pixels are set to 0
    (the noise averages down first). ``energy_in_kernel`` and ``noise_clipped`` are of the band's light, the weighted
    sum of the images' (1 with ``normalize: sum``)."""
    centre = common
    if centre is None and opts.centre in ("centroid_per_band", "peak_per_band"):
        centre = find_centre(_unit_sum_average(d, items, src, opts), opts.centre)
    signed = np.zeros((kernel_px, kernel_px))
    light = 0.0
    parts = []
    for j, wt in src:
        w, f, img, _ = items[j]
        _, rep, s_j, light_j = _band_psf(w, f, img, opts, camera_pixel_m, kernel_px, f_number, pitch_from, centre)
        signed += wt * s_j
        light += wt * light_j
        parts.append({"wavelength_nm": w, "file": f.name, "weight": wt, "saturated_px": saturated[j],
                      **{k: rep[k] for k in ("source_shape", "background", "centre_px", "energy_in_kernel")}})
    psf = np.clip(signed, 0.0, None)
    lo, hi = min(p["wavelength_nm"] for p in parts), max(p["wavelength_nm"] for p in parts)
    entry = {"band_nm": lam, "name": f"band {lam:g} nm ({len(parts)} images, {lo:g}–{hi:g} nm)",
             "centre_px": parts[0]["centre_px"] if all(p["centre_px"] == parts[0]["centre_px"] for p in parts) else None,
             "energy_in_kernel": float(signed.sum() / light),
             "kernel_sum": float(psf.sum()),
             "noise_clipped": float((psf.sum() - signed.sum()) / light),
             "saturated_px": sum(p["saturated_px"] for p in parts),
             "sources": parts}
    return psf, entry


def _warn_cut_bands(d: Path, waves: Sequence[float], bands: Bands, sources: list[list[tuple[int, float]]],
                    opts: PSFImportOptions) -> None:
    """Warn about the bands that average a sweep (more than one image) or would (the sweep finer than the band) but
    whose reach, ±3σ of their Gaussian (:func:`~hsicam.spectral.bands.band_matrix`'s cut), passes the sweep's end: the
    average is cut symmetrically there (the band at the very end is its nearest image), naming the range to measure."""
    if len(waves) < 2:
        return
    sweep, _ = sweep_bands(d, waves, opts)
    reach = BAND_REACH_SIGMA * bands.fwhm_nm / FWHM_PER_SIGMA
    lo, hi = bands.centers_nm - reach, bands.centers_nm + reach
    finer = finer_than_bands(sweep, bands, opts)
    cut = [i for i in range(len(bands)) if (len(sources[i]) > 1 or finer[i]) and (lo[i] < sweep.min_nm or hi[i] > sweep.max_nm)]
    if cut:
        log.warning("%s: the PSF sweep (%g–%g nm) ends within the reach (±3σ) of band(s) %s nm: their PSF averages "
                    "only the images up to the sweep's end, symmetrically about the centre (a band on the end is its "
                    "nearest image); to average the whole bands measure %g–%g nm", d, sweep.min_nm, sweep.max_nm,
                    ", ".join(f"{bands.centers_nm[i]:g}" for i in cut), math.floor(min(lo[cut])), math.ceil(max(hi[cut])))


def _warn_folder(d: Path, kernel_px: int, floors: list[str], low: list[str],
                 noisy: Sequence[tuple[str, float]] = (), n_bands: int = 0) -> None:
    """One warning for the bands whose border looks like a black level (``floors``), one for those keeping less
    than :data:`LOW_ENERGY_IN_KERNEL` of their light in the kernel (``low``), one for those whose kernel's noise
    floor holds more than :data:`NOISE_FLOOR_WARN` of their light (``noisy``: (band, share), of ``n_bands``)."""
    if floors:  # a black level read as light: each band loses another share of its PSF to it
        log.warning("%s: the images' borders sit above zero (border median, of the peak: %s) and background is none: "
                    "if that is a black level (pedestal, dark current), it is counted as PSF light, spread over the whole "
                    "frame; set background: border (or the black level in the files' units) in psf.json", d,
                    ", ".join(floors))
    if noisy:
        shares = [v for _, v in noisy]
        worst = max(noisy, key=lambda t: t[1])
        span = (f"{100 * min(shares):.2g}–{100 * max(shares):.2g} %" if len(shares) > 1
                else f"{100 * shares[0]:.2g} %")
        log.warning("%s: the measured PSFs are noisy: in the camera's %d×%d px kernel their negative noise set to 0 "
                    "adds a floor of %s of the band's light in %d of the %d bands (most: %s); the PSF's own light is "
                    "kept, its dark pixels read as a faint glow: average more frames of each PSF (and of the dark frame "
                    "subtracted)", d, kernel_px, kernel_px, span, len(noisy), n_bands, worst[0])
    if low:
        log.warning("%s: most of the measured PSF light falls outside the camera's %d×%d px kernel (energy in kernel: "
                    "%s); the camera model loses it: %scheck axis_px / centre and pixel_pitch_um in psf.json "
                    "(or --psf-pitch-um), or use a larger camera.psf.kernel_px", d, kernel_px, kernel_px, ", ".join(low),
                    "subtract the black level first (above), " if floors else "")


def _warn_coarse_pitch(opts: PSFImportOptions, camera_pixel_m: float) -> None:
    """Warn when the measured pixels are coarser than the camera's."""
    ratio = opts.pitch_um * 1e-6 / camera_pixel_m  # type: ignore[operator]
    if ratio > 1.0 + 1e-9:
        log.warning("measured PSFs are sampled at %.3g µm, coarser than the camera's %.3g µm pixels: "
                    "they are spread uniformly over each measured pixel", opts.pitch_um, camera_pixel_m * 1e6)


def _measured_psf(d: Path, bands: Bands, opts: PSFImportOptions, camera_pixel_m: float, kernel_px: int,
                  stack: list[np.ndarray], per_band: list[dict[str, Any]]) -> MeasuredPSF:
    """The bands' PSFs as one float32 (C, K, K) stack with the import report."""
    psf = np.stack(stack).astype(np.float32)
    report = {
        "import_version": PSF_IMPORT_VERSION,
        "psf_dir": str(Path(d).resolve()),  # absolute: compared with --psf-dir from any working folder
        "pixel_pitch_um": opts.pitch_um,
        "camera_pixel_pitch_um": camera_pixel_m * 1e6,
        "kernel_px": int(kernel_px),
        "centre": opts.centre,
        "axis_px": list(opts.axis_px) if opts.axis_px else None,
        "background": opts.background,
        "normalize": opts.normalize,
        "fwhm_nm": opts.fwhm_nm,
        "band_average": ("a band is the weighted average of the images within its reach when the sweep is finer than "
                         "the band (the weights resampling gives a scene's band: hsicam.spectral.resampling_matrix), "
                         "else its nearest image; each band's sources and weights are in bands[].sources"),
        "resampling": "exact area integration (piecewise-constant source pixels), energy preserving",
        "bands": per_band,
        "energy_in_kernel": [b["energy_in_kernel"] for b in per_band],
        "fingerprint": psf_fingerprint(psf),
    }
    return MeasuredPSF(psf, bands, report)


def import_for_camera(psf_dir: str | Path, camera, **kwargs: Any) -> MeasuredPSF:
    """:func:`import_psf_dir` on a :class:`~hsicam.cameras.DOECamera`'s bands, pixel pitch and kernel
    (and its f-number, sensor distance / aperture diameter, for the diffraction test of the pitch)."""
    if not hasattr(camera, "optics"):
        raise InputError("measured PSFs need a DOE camera (camera.kind: doe)")
    optics = camera.optics
    kwargs.setdefault("f_number", optics.sensor_distance_m / (2.0 * optics.aperture_radius_m))
    return import_psf_dir(psf_dir, camera.bands, optics.pixel_m, camera.kernel_px, **kwargs)
