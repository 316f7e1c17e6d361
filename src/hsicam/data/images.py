"""Single-channel images from disk: sensor captures, dark/flat frames, measured PSF images.

Raw captures (:func:`read_image_2d`, :func:`preprocess_raw`): a 16-bit (or 8-bit, or float) TIFF
or PNG, or a ``.npy``, in sensor digital numbers (DN), is brought onto the simulator's scale
(0 = black, 1 = full scale) by

    g = (raw − dark) / (white − black) / flat_norm · (t_ref / t_exp) · scale

``dark`` is a dark frame (DN, same exposure) or else the constant black level; ``flat_norm`` a
flat-field frame (DN) minus the black level, normalised to mean 1 — pixel-wise, or averaged over
the CFA period so the CFA's own pattern (which the forward model contains) is not divided out;
``t_ref / t_exp`` the exposure normalisation. Files are judged by their content (magic bytes),
their declared size is checked against :data:`MAX_IMAGE_PIXELS` before any pixel is decoded, and
every problem is one :class:`~hsicam.errors.InputError`.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.errors import InputError

log = logging.getLogger(__name__)

#: Largest image accepted (pixels): 2^27 ≈ 134 M px (e.g. 11585²), 512 MiB as float32.
MAX_IMAGE_PIXELS = 1 << 27

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_NPY_MAGIC = b"\x93NUMPY"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
IMAGE_SUFFIXES = (".npy", ".png", ".tif", ".tiff")


# ------------------------------------------------------------------------------------------------
# Reading single-channel images (captures, dark/flat frames, measured PSFs)
# ------------------------------------------------------------------------------------------------
@dataclass
class RawImage:
    """A single-channel image as read from disk.

    Attributes:
        data: (H, W) float32 (float64 for float64 files), values as stored (DN for integer files).
        full_scale: the file type's full scale: the integer maximum (65535 for 16 bit), 1 for floats.
        dtype: the stored data type.
        format: "npy", "png" or "tiff".
    """

    data: np.ndarray
    full_scale: float
    dtype: str
    format: str


def _sniff(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    if not head:
        raise InputError(f"{path}: empty file")
    if head.startswith(_PNG_MAGIC):
        return "png"
    if head.startswith(_NPY_MAGIC):
        return "npy"
    if head[:4] in _TIFF_MAGICS:
        return "tiff"
    raise InputError(f"{path}: not a PNG, TIFF or NPY file (unknown content; corrupt?)")


def _check_pixels(path: Path, shape: tuple[int, ...], what: str) -> None:
    n = 1
    for s in shape:
        n *= int(s)
    if any(int(s) <= 0 for s in shape) or n == 0:
        raise InputError(f"{path}: empty {what} (shape {tuple(shape)})")
    if n > MAX_IMAGE_PIXELS:
        raise InputError(f"{path}: {what} of shape {tuple(shape)} is larger than the limit of {MAX_IMAGE_PIXELS} pixels")


def _squeeze_2d(path: Path, arr_shape: tuple[int, ...], what: str) -> tuple[int, int]:
    """(H, W) of a stored shape (H, W), (1, H, W) or (H, W, 1); InputError otherwise."""
    shape = tuple(int(s) for s in arr_shape)
    if len(shape) == 3 and shape[0] == 1:
        shape = shape[1:]
    elif len(shape) == 3 and shape[-1] == 1:
        shape = shape[:2]
    if len(shape) == 3 and shape[-1] in (3, 4):
        raise InputError(f"{path}: {what} must be 2-D (single-channel, monochrome), got shape {tuple(arr_shape)} "
                         f"({shape[-1]} channels?)")
    if len(shape) != 2:
        raise InputError(f"{path}: {what} must be 2-D, got shape {tuple(arr_shape)}")
    return shape  # type: ignore[return-value]


def _read_npy(path: Path, what: str) -> tuple[np.ndarray, np.dtype]:
    try:
        mm = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError, OSError, EOFError...
        raise InputError(f"{path}: not a readable .npy file ({_first_line(exc)})") from None
    if not isinstance(mm, np.ndarray):
        raise InputError(f"{path}: not a plain .npy array")
    _check_pixels(path, mm.shape, what)
    _squeeze_2d(path, mm.shape, what)
    if mm.dtype.kind not in "uifb":
        raise InputError(f"{path}: unsupported data type {mm.dtype} (expected integers or floats)")
    try:
        arr = np.array(mm)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path}: cannot read the array data ({_first_line(exc)})") from None
    return arr, mm.dtype


def _read_png(path: Path, what: str) -> tuple[np.ndarray, np.dtype]:
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                w, h = im.size
                _check_pixels(path, (h, w), what)
                if im.mode not in ("L", "I;16", "I;16B", "I;16L", "I", "F", "1"):
                    raise InputError(f"{path}: expected a single-channel (monochrome) {what}, got PNG mode {im.mode}")
                if getattr(im, "n_frames", 1) > 1:
                    raise InputError(f"{path}: animated PNG; expected one {what}")
                arr = np.array(im)
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{path}: {what} too large to decode") from None
    except Exception as exc:  # noqa: BLE001 - PIL raises OSError, SyntaxError, ValueError, zlib.error...
        raise InputError(f"{path}: cannot read PNG (corrupt or truncated?): {_first_line(exc)}") from None
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    return arr, arr.dtype


def _read_tiff(path: Path, what: str) -> tuple[np.ndarray, np.dtype]:
    import tifffile

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with tifffile.TiffFile(path) as tf:
                if len(tf.pages) < 1:
                    raise InputError(f"{path}: TIFF without images")
                page = tf.pages[0]
                if not hasattr(page, "shape"):
                    raise InputError(f"{path}: unreadable first TIFF page")
                _check_pixels(path, page.shape, what)
                _squeeze_2d(path, page.shape, what)
                dtype = np.dtype(page.dtype)
                if dtype.kind not in "uifb":
                    raise InputError(f"{path}: unsupported TIFF data type {dtype}")
                arr = page.asarray()
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{path}: {what} too large to decode") from None
    except Exception as exc:  # noqa: BLE001 - tifffile raises many types on corrupt files
        raise InputError(f"{path}: cannot read TIFF (corrupt or truncated?): {_first_line(exc)}") from None
    return np.asarray(arr), dtype


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_image_2d(path: str | Path, what: str = "image") -> RawImage:
    """A single-channel image from ``.npy`` (H, W) / (1, H, W), PNG (8/16-bit grey) or TIFF
    (integer or float, first page), judged by content. Values are returned as stored.

    Raises :class:`InputError` for a missing, empty, truncated, corrupt, colour, non-2-D, oversized
    (> :data:`MAX_IMAGE_PIXELS`) or non-finite image.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such {what}")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    fmt = _sniff(path)
    reader = {"npy": _read_npy, "png": _read_png, "tiff": _read_tiff}[fmt]
    arr, dtype = reader(path, what)
    h, w = _squeeze_2d(path, arr.shape, what)
    arr = arr.reshape(h, w)
    if dtype.kind in "ui":
        full = float(np.iinfo(dtype).max)
    elif dtype.kind == "b":
        full = 1.0
    else:
        full = 1.0
    data = arr.astype(np.float64 if arr.dtype == np.float64 else np.float32)
    if not np.all(np.isfinite(data)):
        bad = int(data.size - np.count_nonzero(np.isfinite(data)))
        raise InputError(f"{path}: {what} contains {bad} NaN or Inf value(s)")
    return RawImage(data, full, str(dtype), fmt)


# ------------------------------------------------------------------------------------------------
# Raw capture preprocessing
# ------------------------------------------------------------------------------------------------
@dataclass
class RawCorrection:
    """Raw-capture corrections (see module docstring). DN = the file's stored values.

    Attributes:
        black_level: constant offset (DN). None: the median of ``dark`` if given, else 0.
        white_level: full-scale value (DN). None: the file type's full scale (65535 for 16 bit,
            1 for float files).
        dark: dark frame (H, W) in DN (same exposure as the capture); subtracted instead of the
            black level.
        flat: flat-field frame (H, W) in DN; normalised to mean 1 after subtracting the black level.
        flat_period: average the flat over this period (the CFA period) before normalising, so a
            flat taken through the CFA corrects vignetting and not the CFA pattern; None: pixel-wise.
        exposure_s, reference_exposure_s: multiply by reference/exposure (both or neither).
        auto_level: if set, scale so the 99.9th percentile of the image equals this value
            (replaces absolute scaling; for captures of unknown radiometric scale).
        scale: final multiplier.
    """

    black_level: float | None = None
    white_level: float | None = None
    dark: np.ndarray | None = None
    flat: np.ndarray | None = None
    flat_period: int | None = None
    exposure_s: float | None = None
    reference_exposure_s: float | None = None
    auto_level: float | None = None
    scale: float = 1.0
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("black_level", "white_level", "exposure_s", "reference_exposure_s", "auto_level", "scale"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise InputError(f"{name} must be a finite number, got {v}")
        for name in ("exposure_s", "reference_exposure_s", "auto_level", "scale"):
            v = getattr(self, name)
            if v is not None and v <= 0:
                raise InputError(f"{name} must be positive, got {v}")
        if (self.exposure_s is None) != (self.reference_exposure_s is None):
            raise InputError("exposure normalisation needs both the capture's exposure and the reference exposure")
        if self.flat_period is not None and self.flat_period < 1:
            raise InputError(f"flat period must be >= 1, got {self.flat_period}")
        if self.black_level is not None and self.black_level < 0:
            raise InputError(f"black level must be >= 0, got {self.black_level}")

    @property
    def is_identity(self) -> bool:
        return (self.black_level in (None, 0.0) and self.white_level is None and self.dark is None and self.flat is None
                and self.exposure_s is None and self.auto_level is None and self.scale == 1.0)


def preprocess_raw(raw: np.ndarray, full_scale: float, corr: RawCorrection, source: str = "capture") -> tuple[np.ndarray, dict]:
    """Raw capture (H, W) in DN → float32 (H, W) on the simulator's scale, plus a report dict.

    Args:
        raw: the stored values (DN).
        full_scale: the file type's full scale (used when ``corr.white_level`` is None).
        corr: the corrections.
    """
    raw = np.asarray(raw, dtype=np.float32)
    h, w = raw.shape
    for name, frame in (("dark frame", corr.dark), ("flat field", corr.flat)):
        if frame is not None and frame.shape != raw.shape:
            raise InputError(f"{name} is {frame.shape[0]}×{frame.shape[1]} px but the capture is {h}×{w}")
    black = corr.black_level
    if black is None:
        black = float(np.median(corr.dark)) if corr.dark is not None else 0.0
    white = float(full_scale if corr.white_level is None else corr.white_level)
    if not white > black:
        raise InputError(f"white level ({white:g} DN) must be above the black level ({black:g} DN)")
    report: dict[str, Any] = {"black_level_dn": black, "white_level_dn": white}
    saturated = int(np.count_nonzero(raw >= white)) if corr.white_level is not None or full_scale > 1 else 0
    if saturated:
        log.warning("%s: %d pixel(s) at or above the white level %g DN (saturated)", source, saturated, white)
    report["saturated_px"] = saturated
    img = raw - (corr.dark.astype(np.float32) if corr.dark is not None else np.float32(black))
    img *= np.float32(1.0 / (white - black))
    if corr.flat is not None:
        flat = corr.flat.astype(np.float64) - black
        if corr.flat_period and corr.flat_period > 1:
            from scipy.ndimage import uniform_filter

            flat = uniform_filter(flat, size=corr.flat_period, mode="nearest")
        mean = float(flat.mean())
        if not mean > 0:
            raise InputError(f"flat field has no signal above the black level ({black:g} DN)")
        flat /= mean
        low = int(np.count_nonzero(flat < 0.05))
        if low:
            raise InputError(f"flat field has {low} pixel(s) below 5 % of its mean (dead pixels or a wrong black level)")
        img /= flat.astype(np.float32)
        report["flat_min_rel"] = float(flat.min())
        report["flat_period_px"] = corr.flat_period
    factor = 1.0
    if corr.exposure_s is not None:
        factor = corr.reference_exposure_s / corr.exposure_s
        report["exposure_s"], report["reference_exposure_s"] = corr.exposure_s, corr.reference_exposure_s
    if corr.auto_level is not None:
        p = float(np.percentile(img, 99.9))
        if not p > 0:
            raise InputError(f"{source}: no signal above the black level; cannot auto-level")
        factor = corr.auto_level / p
        report["auto_level"] = corr.auto_level
    factor *= corr.scale
    img *= np.float32(factor)
    report["gain"] = factor / (white - black)
    if not np.all(np.isfinite(img)):
        raise InputError(f"{source}: the corrections produced NaN or Inf values")
    return img.astype(np.float32, copy=False), report


def read_capture(path: str | Path, corr: RawCorrection | None = None, scale: float | None = None) -> tuple[np.ndarray, dict]:
    """Read a capture and apply ``corr`` → (float32 (H, W) on the simulator scale, report).

    ``scale`` (if given) overrides ``corr.scale``; by default PNG/TIFF captures with a
    ``simulate.json`` beside them (written by ``hsicam simulate``) use its ``sensor_png_scale``.
    """
    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(f"{path}: unsupported sensor image format (use .npy, .png, .tif)")
    image = read_image_2d(path, "sensor image")
    corr = corr or RawCorrection()
    if scale is None and image.format in ("png", "tiff"):
        meta = path.parent / "simulate.json"
        if meta.is_file() and corr.scale == 1.0 and corr.auto_level is None:
            try:
                scale = float(json.loads(meta.read_text()).get("sensor_png_scale", 1.0))
            except (ValueError, TypeError, AttributeError):
                raise InputError(f"{meta}: unreadable simulate.json") from None
    if scale is not None:
        corr = RawCorrection(**{**corr.__dict__, "scale": float(scale)})
    img, report = preprocess_raw(image.data, image.full_scale, corr, str(path))
    report.update({"source": str(path), "stored_dtype": image.dtype, "format": image.format,
                   "shape": [int(s) for s in img.shape]})
    return img, report


def read_sensor_image(path: str | Path, scale: float | None = None) -> np.ndarray:
    """A sensor image as float32 (H, W) on the simulator's [0, 1] scale.

    ``.npy`` float arrays are used as is; integer images (PNG, TIFF, integer ``.npy``) are divided
    by the type's maximum; then multiplied by ``scale`` — by default ``sensor_png_scale`` from a
    ``simulate.json`` beside a PNG/TIFF (written by ``hsicam simulate``), else 1.
    """
    img, _ = read_capture(path, None, scale)
    return img
