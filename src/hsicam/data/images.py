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

Checks on the result (:func:`preprocess_raw`, :func:`read_capture`):

* 32/64-bit integer captures (numpy's default int) need an explicit white level: the type's
  maximum (2^31 − 1, 2^63 − 1) is never a sensor's full scale (:class:`InputError`). A white level
  above the integer type's maximum (4095 for an 8-bit file) is an :class:`InputError` too.
* ``auto_level`` sets the level from the image itself: with an exposure normalisation or a
  ``scale`` it is an :class:`InputError` (one source for the level); the report records only the
  gains applied.
* More than :data:`MAX_SATURATED_SHARE` of the pixels at or above the white level is an
  :class:`InputError` (a wrong white level or an over-exposed capture); any fewer, a warning.
* With an explicit white level, a 99.9th percentile below :data:`DARK_WHITE_FRACTION` of full scale
  (after every correction) is a warning, and an :class:`InputError` for a float capture whose values
  lie within [0, 1] (on the simulator's scale already: a DN white level divides it down).
* A dark frame stored in other units than the capture — another full scale: a float frame (0-1)
  for an integer capture, 8 bit for 16 bit — is an :class:`InputError` (it is subtracted from the
  capture's DN as it is; no conversion is guessed: a float dark may hold DN, an 8-bit one may hold
  small DN values), and so is such a flat field when a black level is subtracted from it (without
  one, the flat's normalisation to mean 1 makes its units irrelevant). Only frames given as the
  :class:`RawImage` that :func:`read_image_2d` returns know their stored type; a bare array is taken
  to be in the capture's DN.
* (Nearly) no pixel above 0 after subtracting the dark frame / black level — fewer than
  :data:`MIN_SIGNAL_SHARE` of them — is an :class:`InputError` (nothing to reconstruct); more than
  :data:`MAX_NEGATIVE_SHARE` of the pixels below 0 is a warning (dark frame or black level too high?).
* A gain the user asked for (``scale``, ``auto_level``, the exposure ratio) that puts the image's
  99.9th percentile above :data:`MAX_LEVEL` × full scale is an :class:`InputError` naming the
  option(s) and the resulting level; one that puts more than :data:`CLIP_SHARE` of the pixels above
  full scale is a warning (the scale restoring ``hsicam simulate``'s stretched image is no gain: a gain on top of it
  is checked on the image at its simulated level).
* An integer capture read with the container's full scale whose brightest pixel ends below
  :data:`DIM_FRACTION` of full scale gets a warning naming the likely cause: a sensor with fewer
  bits than the container (a 12-bit sensor in a 16-bit file reaches at most 1/16). Not for the
  sensor image that ``hsicam simulate`` wrote (its ``sensor.png``, :func:`is_simulated_image`): it holds the simulated values at the file's full 16 bits, so a dark
  one is a dark scene, never a sensor of fewer bits.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.errors import InputError
from hsicam.io import NPY_MAGIC

log = logging.getLogger(__name__)

#: Largest image accepted (pixels): 2^27 ≈ 134 M px (e.g. 11585²), 512 MiB as float32.
MAX_IMAGE_PIXELS = 1 << 27

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
IMAGE_SUFFIXES = (".npy", ".png", ".tif", ".tiff")

#: Fewer pixels than this share above 0 after the dark/black subtraction: nothing to reconstruct.
#: (A dark scene still has about half its pixels above 0 from noise; exact zeros and negatives
#: everywhere mean the subtracted dark frame or black level is at least as bright as the capture.)
MIN_SIGNAL_SHARE = 1e-3
#: More pixels than this share below 0 after the dark/black subtraction: warn (offset too high?).
MAX_NEGATIVE_SHARE = 0.10
#: ... counting only pixels below −this × the image's largest magnitude: a float capture simulated through FFT
#: convolutions holds round-off negatives of ~1e-7 of its peak on its dark pixels (`hsicam simulate` of a point or a
#: narrow-band ramp: "35 % below 0 ... a signed or mean-subtracted image?", session 74's hunt), which are no offset.
NEGATIVE_ROUNDOFF = 1e-6
#: An integer capture read with its container's full scale whose brightest pixel (after all the
#: corrections) stays below this fraction of the simulator's full scale is warned about. An n-bit
#: sensor in a 16-bit container reaches at most 2^(n−16): 1/16 for 12 bit (the commonest raw depth),
#: 1/64 for 10 bit, 1/256 for 8 bit — 1/8 catches all of them (not 14 bit, 1/4, which looks like an
#: ordinary exposure: its pixels clipped at 16383 DN are, :data:`SENSOR_CLIP_MIN_PX`). A correct 16-bit
#: capture trips it only when its brightest pixel is three stops
#: below full scale, far darker than the simulated training images (scenes normalised to max 1 give
#: sensor maxima of about 0.3–0.75), so the warning is worth reading then too.
DIM_FRACTION = 1.0 / 8.0
#: A float capture (read on the simulator's scale, full scale 1) brighter than this is warned about:
#: it probably holds DN (a float image of 12-bit data reaches 4095).
FLOAT_OVER_SCALE = 4.0
#: A gain the user asked for (``scale``, ``auto_level``, the exposure ratio) that puts the image's
#: 99.9th percentile above this multiple of full scale (1) is refused: two stops over, beyond any
#: highlight a real sensor records (it clips at 1); the network was trained on images within [0, 1].
#: The percentile, as ``auto_level`` uses, so that a few hot pixels do not decide.
MAX_LEVEL = 4.0
#: More than this share of the pixels above full scale after such a gain: a warning (clipped highlights
#: a real sensor would not have recorded). ``auto_level`` 1 leaves 0.1 % above: no warning.
CLIP_SHARE = 0.01
#: A gain the user asked for that leaves the image's 99.9th percentile below this share of full scale (one step of
#: an 8-bit sensor) is warned about: likely a typo (``--auto-level 0.0001``, ``--scale 1e-6``).
DIM_AFTER_GAIN = 1.0 / 256.0
#: More than this share of the capture's pixels at or above the white level: refused (the image is
#: a flat white plateau, or the white level is wrong); a smaller share (but any pixel) is a warning.
MAX_SATURATED_SHARE = 0.5
#: A capture read with an explicit white level whose 99.9th percentile (after all the corrections)
#: stays below this fraction of full scale: the white level is far above the data (a DN white level for
#: a float image already on the [0, 1] scale, 65535 for a 12-bit sensor): a warning, refused for a
#: float capture whose values all lie within [0, 1] (it is on the simulator's scale already).
DARK_WHITE_FRACTION = 1.0 / 16.0


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
        path: the file it was read from.
    """

    data: np.ndarray
    full_scale: float
    dtype: str
    format: str
    path: str = ""


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
    if head.startswith(NPY_MAGIC):
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
    if mm.dtype.kind == "b":
        raise InputError(_binary_image(path, what, "a bool array"))
    if mm.dtype.kind not in "uif":
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
                if im.mode == "1":
                    raise InputError(_binary_image(path, what, "a 1-bit (black and white) PNG"))
                if im.mode not in ("L", "I;16", "I;16B", "I;16L", "I", "F"):
                    raise InputError(f"{path}: expected a single-channel (monochrome) {what}, got PNG mode {im.mode}")
                if getattr(im, "n_frames", 1) > 1:
                    raise InputError(f"{path}: animated PNG; expected one {what}")
                arr = np.array(im)
                if im.mode == "I" and arr.dtype.kind in "iu":
                    # Pillow < 10 opens a 16-bit grey PNG as 32-bit mode "I"; a PNG holds at most 16 bits, so
                    # its full scale is 65535 (as int32 it read 2^31 - 1, and the capture was refused)
                    if arr.size and (int(arr.min()) < 0 or int(arr.max()) > 65535):
                        raise InputError(f"{path}: PNG values outside 0..65535 (corrupt?)")
                    arr = arr.astype(np.uint16)
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{path}: {what} too large to decode") from None
    except Exception as exc:  # noqa: BLE001 - PIL raises OSError, SyntaxError, ValueError, zlib.error...
        raise InputError(f"{path}: cannot read PNG (corrupt or truncated?): {_first_line(exc)}") from None
    return arr, arr.dtype


def _binary_image(path: Path, what: str, kind: str) -> str:
    """The refusal of a two-level image: a mask, not sensor values (it was read as 0 and 1 of 255 DN)."""
    return (f"{path}: {kind} holds two levels, not the values of a {what}; save the capture at its sensor's bit depth "
            "(8- or 16-bit integers, or floats with 1 = full scale)")


@contextlib.contextmanager
def _quiet_logger(name: str):
    """Inside the block the library logger ``name`` prints nothing: its complaints about a damaged file (tifffile
    logs an ERROR line per bad tag before it raises) are said once, in hsicam's own refusal."""
    logger = logging.getLogger(name)
    disabled = logger.disabled
    logger.disabled = True
    try:
        yield
    finally:
        logger.disabled = disabled


def _read_tiff(path: Path, what: str) -> tuple[np.ndarray, np.dtype]:
    import tifffile

    try:
        with warnings.catch_warnings(), _quiet_logger("tifffile"):
            warnings.simplefilter("ignore")
            with tifffile.TiffFile(path) as tf:
                if len(tf.pages) < 1:
                    raise InputError(f"{path}: TIFF without images")
                _check_single_page(path, tf, what)
                page = tf.pages[0]
                if not hasattr(page, "shape"):
                    raise InputError(f"{path}: unreadable first TIFF page")
                _check_tiff_page(path, page)
                _check_pixels(path, page.shape, what)
                _squeeze_2d(path, page.shape, what)
                dtype = np.dtype(page.dtype)
                if dtype.kind == "b":
                    raise InputError(_binary_image(path, what, "a 1-bit TIFF"))
                if dtype.kind not in "uif":
                    raise InputError(f"{path}: unsupported TIFF data type {dtype}")
                if 262 in page.tags and page.tags[262].value == 0:  # PhotometricInterpretation: WhiteIsZero
                    # tifffile returns the stored values, Pillow (a compressed page) inverts them: refused, not read
                    # one way or the other by the compression
                    raise InputError(f"{path}: a WhiteIsZero (MINISWHITE) TIFF stores light inverted (0 = white), as no "
                                     "sensor records it: save the capture as BlackIsZero (MINISBLACK, 0 = black)")
                try:
                    arr = page.asarray()
                except ValueError as exc:  # LZW, JPEG …: tifffile decodes them only with the optional imagecodecs
                    if "imagecodecs" not in str(exc):
                        raise
                    arr = _tiff_by_pillow(path, page.shape, dtype, getattr(page.compression, "name", page.compression))
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{path}: {what} too large to decode") from None
    except Exception as exc:  # noqa: BLE001 - tifffile raises many types on corrupt files
        raise InputError(f"{path}: cannot read TIFF (corrupt or truncated?): {_first_line(exc)}") from None
    return np.asarray(arr), dtype


def _tiff_by_pillow(path: Path, shape: tuple[int, ...], dtype: np.dtype, compression) -> np.ndarray:
    """The pixels of a single-page TIFF whose compression (LZW, the commonest for captures; JPEG …) tifffile
    decodes only with the optional ``imagecodecs`` package, decoded by Pillow (a dependency already); they
    must come back with the page's shape and data type. A lossy (JPEG) page is read with a warning."""
    from PIL import Image

    why = f"{path}: TIFF compressed with {compression}, which neither tifffile without the imagecodecs package nor Pillow " \
          "decodes here: `pip install imagecodecs`, or save the capture uncompressed"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                arr = np.array(im)
    except Exception as exc:  # noqa: BLE001 - PIL raises OSError, ValueError … on what it cannot decode
        raise InputError(f"{why} ({_first_line(exc)})") from None
    if arr.dtype.byteorder not in "=|":  # a big-endian ("MM") file's 16-bit page: Pillow keeps its byte order (I;16B)
        arr = arr.astype(arr.dtype.newbyteorder("="))
    if arr.dtype != dtype or arr.shape != _squeeze_2d(path, shape, "image"):
        raise InputError(f"{why} (Pillow decodes it as {arr.dtype} {arr.shape}, not {dtype} {tuple(shape)})")
    if str(compression).upper().startswith("JPEG"):
        log.warning("%s: JPEG-compressed TIFF: lossy, its values are not the sensor's as captured", path)
    return arr


def _check_tiff_page(path: Path, page) -> None:
    """InputError for a first TIFF page that holds no image: no tags at all, no ImageWidth/ImageLength, or no
    StripOffsets/TileOffsets (a page without tags was refused as "image must be 2-D, got shape ()")."""
    tags = getattr(page, "tags", None)
    if tags is None or len(tags) == 0:
        raise InputError(f"{path}: the first TIFF page has no tags (no width, height or pixel data): corrupt, or not "
                         "an image")
    missing = [name for code, name in ((256, "ImageWidth"), (257, "ImageLength")) if code not in tags]
    if missing:
        raise InputError(f"{path}: the first TIFF page has no image: its {' and '.join(missing)} tag"
                         f"{'s are' if len(missing) > 1 else ' is'} missing (corrupt, or not an image)")
    if not (273 in tags or 324 in tags):  # StripOffsets, TileOffsets (TIFF 6.0 tag codes, as 256/257 above)
        raise InputError(f"{path}: the first TIFF page has no pixel data: its StripOffsets (or TileOffsets) tag is "
                         "missing (corrupt, or not an image)")


def _check_single_page(path: Path, tf, what: str) -> None:
    """InputError for a multi-page TIFF (a stack or burst): which page is the image is not ours to
    guess. Reduced-resolution pages (thumbnails, pyramid levels) do not count."""
    pages = sum(1 for page in tf.pages if not getattr(page, "is_reduced", False))
    if pages > 1:
        raise InputError(f"{path}: multi-page TIFF ({pages} pages); expected one {what} on a single page: save the "
                         "page to use as its own TIFF or .npy (e.g. tifffile.imwrite(OUT, tifffile.imread(FILE, key=N)))")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def read_image_2d(path: str | Path, what: str = "image") -> RawImage:
    """A single-channel image from ``.npy`` (H, W) / (1, H, W), PNG (8/16-bit grey) or TIFF
    (integer or float, a single page), judged by content. Values are returned as stored.

    Raises :class:`InputError` for a missing, empty, truncated, corrupt, colour, non-2-D, multi-page
    (TIFF), oversized (> :data:`MAX_IMAGE_PIXELS`) or non-finite image.
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
    return RawImage(data, full, str(dtype), fmt, str(path))


# ------------------------------------------------------------------------------------------------
# Raw capture preprocessing
# ------------------------------------------------------------------------------------------------
@dataclass
class RawCorrection:
    """Raw-capture corrections (see module docstring). DN = the file's stored values.

    Attributes:
        black_level: constant offset (DN). None: the median of ``dark`` if given, else 0.
        white_level: full-scale value (DN). None: the file type's full scale (65535 for 16 bit,
            1 for float files); :func:`read_capture` refuses None for 32/64-bit integer files.
        dark: dark frame (H, W) in DN (same exposure as the capture); subtracted instead of the
            black level. A :class:`RawImage` (as read by :func:`read_image_2d`) must have the
            capture's full scale; a bare array is taken to be in the capture's DN.
        flat: flat-field frame (H, W) in DN; normalised to mean 1 after subtracting the black level
            (with a black level, a :class:`RawImage` must have the capture's full scale).
        flat_period: average the flat over this period (the CFA period) before normalising, so a
            flat taken through the CFA corrects vignetting and not the CFA pattern; None: pixel-wise.
        cfa_period: the camera's CFA period (None: unknown): a pixel-wise flat whose means over the CFA's
            phases differ by more than :data:`FLAT_PHASE_SPREAD` is warned about (taken through the CFA, it divides
            the filters' own transmissions out of the capture).
        exposure_s, reference_exposure_s: multiply by reference/exposure (both or neither).
        auto_level: if set, scale so the 99.9th percentile of the image equals this value
            (replaces absolute scaling; for captures of unknown radiometric scale).
        scale: final multiplier.
    """

    black_level: float | None = None
    white_level: float | None = None
    dark: "np.ndarray | RawImage | None" = None
    flat: "np.ndarray | RawImage | None" = None
    flat_period: int | None = None
    cfa_period: int | None = None
    exposure_s: float | None = None
    reference_exposure_s: float | None = None
    auto_level: float | None = None
    scale: float = 1.0
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("black_level", "white_level", "exposure_s", "reference_exposure_s", "auto_level", "scale"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise InputError(f"{name} (--{name.replace('_', '-')}) must be a finite number, got {v}")
        for name in ("exposure_s", "reference_exposure_s", "auto_level", "scale"):
            v = getattr(self, name)
            if v is not None and v <= 0:
                raise InputError(f"{name} (--{name.replace('_', '-')}) must be positive, got {v}")
        if (self.exposure_s is None) != (self.reference_exposure_s is None):
            given, missing = (("exposure_s", "reference_exposure_s") if self.reference_exposure_s is None
                              else ("reference_exposure_s", "exposure_s"))
            raise InputError(f"{given} (--{given.replace('_', '-')}) needs {missing} (--{missing.replace('_', '-')}): "
                             "the exposure normalisation multiplies the image by reference/exposure; give both or "
                             "neither")
        if self.auto_level is not None and (self.exposure_s is not None or self.scale != 1.0):
            given = [f"--exposure-s {self.exposure_s:g} and --reference-exposure-s {self.reference_exposure_s:g}"
                     ] if self.exposure_s is not None else []
            given = " and ".join(given + ([f"--scale {self.scale:g}"] if self.scale != 1.0 else []))
            raise InputError(f"--auto-level {self.auto_level:g} sets the level from the image itself and cannot be "
                             f"combined with {given}: choose one way of setting the level: --auto-level alone, or "
                             "--exposure-s/--reference-exposure-s and/or --scale")
        if self.flat_period is not None and self.flat_period < 1:
            raise InputError(f"flat period must be >= 1, got {self.flat_period}")
        if self.black_level is not None and self.black_level < 0:
            raise InputError(f"black_level (--black-level) must be >= 0, got {self.black_level}")


def preprocess_raw(raw: np.ndarray, full_scale: float, corr: RawCorrection, source: str = "capture",
                   check_saturation: bool = True, check_bit_depth: bool = True,
                   check_level: bool = True, stored_dtype: str | None = None,
                   return_saturated: bool = False, restored_scale: float = 1.0, trained_peak: float = 1.0
                   ) -> tuple[np.ndarray, dict] | tuple[np.ndarray, dict, np.ndarray]:
    """Raw capture (H, W) in DN → float32 (H, W) on the simulator's scale, plus a report dict (and, with
    ``return_saturated``, the (H, W) bool map of the pixels at or above the white level: clipped by the sensor; all
    False where ``check_saturation`` is off or the capture has no white level, as ``saturated_px`` counts).

    Args:
        raw: the stored values (DN).
        full_scale: the file type's full scale (used when ``corr.white_level`` is None).
        corr: the corrections.
        check_saturation: warn about pixels at the white level (off for an image that ``hsicam
            simulate`` stretched so that its brightest pixel is full scale).
        check_bit_depth: warn about a very dark integer capture, whose likely cause is a sensor of
            fewer bits than the file (off for ``hsicam simulate``'s own sensor image).
        check_level: refuse / warn about a gain (``scale``, ``auto_level``, exposure ratio) that
            pushes the image past full scale (:func:`_check_level`).
        stored_dtype: the capture file's data type (for the messages about frames of other units).
        restored_scale: a factor that is no gain of the user's: the scale that brings ``hsicam simulate``'s
            stretched PNG back to its simulated level (above full scale by design); applied with the gains, never
            checked as one (a gain on top of it is: the image at its simulated level times the gain).
        trained_peak: the most a white scene gives the run's camera on the sensor (1, but for a CASSI camera of
            ``convention: sum``, whose images reach up to its band count: ``reconstruct`` passes it): a float capture is
            taken to hold DN only far above it.
    """
    raw = _float32_capture(raw, source)
    dark, flat_dn = _dark_and_flat(raw, corr, full_scale, stored_dtype, source)
    black, white = _black_and_white(corr, dark, full_scale, stored_dtype, source)
    report: dict[str, Any] = {"black_level_dn": black, "white_level_dn": white}
    saturated_map = _saturated(raw, white, corr, full_scale, check_saturation)
    saturated = int(np.count_nonzero(saturated_map))
    report["saturated_px"] = saturated
    notes = _check_saturated(raw, saturated, white, corr.white_level is not None, source)
    if check_saturation and full_scale == 1 and corr.white_level is None:
        notes += _check_float_clip(raw, source)
    img, signal_notes = _minus_dark_or_black(raw, dark, black, corr, source)
    notes += signal_notes
    img = _to_full_scale(img, white, black, source)
    if flat_dn is not None:
        img = _divide_by_flat(img, flat_dn, black, corr.flat_period, report)
        notes += _flat_through_cfa(flat_dn, black, corr)
    factor = _gain_factor(img, corr, source, report) * restored_scale
    if restored_scale != 1.0:
        report["simulated_scale"] = restored_scale
    img = _apply_gain(img, factor, corr, source)
    report["gain"] = factor / (white - black)
    notes += _level_notes(img, raw, full_scale, white, corr, source, check_level, check_bit_depth, trained_peak)
    for note in notes:  # only once every check passed: an error stays the one line the user sees
        log.warning("%s", note)
    if return_saturated:
        return img.astype(np.float32, copy=False), report, saturated_map
    return img.astype(np.float32, copy=False), report


def _float32_capture(raw: np.ndarray, source: str) -> np.ndarray:
    """The capture (H, W, DN) as float32 (itself if it is float32 already); InputError for anything but a non-empty
    (H, W) array of numbers, and for a float64 capture whose values lie beyond float32's range."""
    stored = np.asarray(raw)
    if stored.ndim != 2 or stored.size == 0 or stored.dtype.kind not in "buif":
        # (the readers refuse these first; from Python they reached numpy's "zero-size array to reduction" or an unpack)
        raise InputError(f"{source}: a capture is a non-empty (H, W) array of numbers, got shape {stored.shape} "
                         f"of {stored.dtype}")
    with np.errstate(over="ignore"):  # a float64 capture beyond float32's range: said below, not as numpy's warning
        raw = stored.astype(np.float32, copy=False)
    if stored.dtype.kind == "f" and stored.dtype.itemsize > 4 and np.isinf(raw).any() and not np.isinf(stored).any():
        raise InputError(f"{source}: {int(np.count_nonzero(np.isinf(raw)))} value(s) beyond float32's range (largest "
                         f"{float(np.abs(stored).max()):.3g}); a capture is processed in float32: scale it, or check "
                         "the file")
    return raw


def _dark_and_flat(raw: np.ndarray, corr: RawCorrection, full_scale: float, stored_dtype: str | None,
                   source: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The values (H, W, DN) of ``corr``'s dark frame and flat field, None where not given; InputError for a dark
    frame stored in other units than the capture (:func:`_check_frame_type`) or a frame of another size."""
    h, w = raw.shape
    _check_frame_type("dark frame", corr.dark, stored_dtype, full_scale, source,
                      "it would be subtracted from the capture's DN as it is")
    dark, flat_dn = frame_data(corr.dark), frame_data(corr.flat)
    for name, frame in (("dark frame", dark), ("flat field", flat_dn)):
        if frame is not None and frame.shape != raw.shape:
            raise InputError(f"{name} is {frame.shape[0]}×{frame.shape[1]} px but the capture is {h}×{w}")
    return dark, flat_dn


def _black_and_white(corr: RawCorrection, dark: np.ndarray | None, full_scale: float, stored_dtype: str | None,
                     source: str) -> tuple[float, float]:
    """(black level, white level) in DN: ``corr``'s, else the dark frame's median (0 without one) and the file
    type's full scale. InputError for a flat field stored in other units when a black level is subtracted from it,
    or a white level not above the black level."""
    black = corr.black_level
    if black is None:
        black = float(np.median(dark)) if dark is not None else 0.0
    if black:
        _check_frame_type("flat field", corr.flat, stored_dtype, full_scale, source,
                          f"the black level {black:g} DN would be subtracted from it as it is")
    white = float(full_scale if corr.white_level is None else corr.white_level)
    if not white > black:
        raise InputError(f"white level ({white:g} DN) must be above the black level ({black:g} DN)")
    return black, white


def _saturated(raw: np.ndarray, white: float, corr: RawCorrection, full_scale: float, check: bool) -> np.ndarray:
    """The capture's pixels at or above the white level ``white`` (DN), (H, W) bool; none without the ``check``, and
    for a float capture read at its own full scale (1)."""
    if not (check and (corr.white_level is not None or full_scale > 1)):
        return np.zeros(raw.shape, dtype=bool)
    with np.errstate(over="ignore"):  # a white level beyond float32 (e.g. 1e39) compares as +inf: nothing saturates
        return raw >= white


def _minus_dark_or_black(raw: np.ndarray, dark: np.ndarray | None, black: float, corr: RawCorrection,
                source: str) -> tuple[np.ndarray, list[str]]:
    """(the capture minus its dark frame, or minus the black level: float32 (H, W, DN), the warnings of
    :func:`_check_signal`); InputError from it for an image without signal."""
    img = raw - (dark.astype(np.float32) if dark is not None else np.float32(black))
    dark_median = (black if corr.black_level is None else float(np.median(dark))) if dark is not None else None
    return img, _check_signal(img, raw, black, dark_median, source)


def _to_full_scale(img: np.ndarray, white: float, black: float, source: str) -> np.ndarray:
    """``img`` (H, W, DN above black) divided by white − black in place (1 = full scale); InputError when that takes
    the image below float32's smallest numbers."""
    img *= np.float32(1.0 / (white - black))
    if _underflowed(img):
        raise InputError(f"{source}: the white level {white:g} DN (--white-level) takes the image below float32's "
                         f"smallest numbers (its brightest pixel becomes {float(img.max()):g}): nothing would be left "
                         "to reconstruct; give the sensor's full scale as --white-level (4095 for 12 bit, 65535 for "
                         "16 bit)")
    return img


def _underflowed(img: np.ndarray) -> bool:
    """Whether no more than :data:`MIN_SIGNAL_SHARE` of the pixels of ``img`` (H, W) are above 0 after a factor
    applied to an image that had signal (:func:`_check_signal`): float32 underflow."""
    return np.count_nonzero(img > 0) <= MIN_SIGNAL_SHARE * img.size


def _divide_by_flat(img: np.ndarray, flat_dn: np.ndarray, black: float, period: int | None,
                    report: dict[str, Any]) -> np.ndarray:
    """``img`` (H, W) divided in place by the flat field (H, W, DN) normalised by :func:`normalised_flat`; its
    smallest relative value and ``period`` go into ``report``."""
    flat = normalised_flat(flat_dn, black, period)
    img /= flat.astype(np.float32)
    report["flat_min_rel"] = float(flat.min())
    report["flat_period_px"] = period
    return img


#: A pixel-wise flat whose means over the CFA's m×m phases span more than this ratio (largest / smallest) is warned
#: about: averaged over the whole frame each phase's mean is free of vignetting and pixel noise (a flat without a CFA:
#: within a per cent), so a spread is the CFA's filters seen through the flat's lamp (session 73: a flat of one
#: non-white spectrum through the demo camera spans 0.36-2.37, and divided pixel-wise it took the capture from 27.85 to
#: 20.57 dB, SAM 6.4 to 29°).
FLAT_PHASE_SPREAD = 1.1


def cfa_phase_means(flat_dn: np.ndarray, black: float, period: int) -> np.ndarray:
    """The flat's (H, W, DN) mean over each of the ``period``² CFA phases, minus ``black``, relative to its mean
    (period, period) float64; phase (i, j) holds the pixels (i + k·period, j + l·period)."""
    flat = np.asarray(flat_dn, dtype=np.float64) - black
    m = int(period)
    means = np.array([[flat[i::m, j::m].mean() for j in range(m)] for i in range(m)])
    return means / max(float(flat.mean()), 1e-300)


def _flat_through_cfa(flat_dn: np.ndarray, black: float, corr: RawCorrection) -> list[str]:
    """The warning (returned) for a pixel-wise flat that carries the CFA's pattern (:data:`FLAT_PHASE_SPREAD`)."""
    m = corr.cfa_period
    if corr.flat_period not in (None, 1) or not m or m < 2 or min(np.shape(flat_dn)) < m:
        return []
    rel = cfa_phase_means(flat_dn, black, m)
    lo, hi = float(rel.min()), float(rel.max())
    if not (lo > 0 and hi / lo > FLAT_PHASE_SPREAD):
        return []
    return [f"flat field: its means over the CFA's {m}×{m} phases span {lo:.3g}–{hi:.3g} of its mean: a flat taken "
            "through the CFA (its lamp not white) divides each filter's own transmission out of the capture, pixel by "
            "pixel, and the spectra with it: use --flat-mode cfa (the flat averaged over each CFA period), or a flat "
            "taken without the CFA"]


def _gain_factor(img: np.ndarray, corr: RawCorrection, source: str, report: dict[str, Any]) -> float:
    """The factor the corrected image ``img`` (H, W, full scale 1) is multiplied by: the exposure ratio, or the one
    that puts its 99.9th percentile at ``auto_level``, times ``scale``; the options applied go into ``report``.
    InputError for ``auto_level`` on an image without signal."""
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
    if corr.scale != 1.0:
        report["scale"] = corr.scale
    factor *= corr.scale
    return factor


def _apply_gain(img: np.ndarray, factor: float, corr: RawCorrection, source: str) -> np.ndarray:
    """``img`` (H, W) multiplied by ``factor`` in place; InputError when that leaves float32's range (naming the
    options of ``corr`` to lower) or takes the image below its smallest numbers (the options to raise)."""
    peak = max(abs(float(img.max())), abs(float(img.min()))) if img.size else 0.0  # not finite: from before the gain
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is the one-line error below, no warning
        img *= np.float32(factor)
    if not np.all(np.isfinite(img)):
        if factor > float(np.finfo(np.float32).max):
            raise InputError(f"{source}: the exposure × auto-level × --scale factor {factor:g} exceeds float32; "
                             f"lower {_gain_option_names(corr)}")
        if math.isfinite(peak):  # the factor alone fits, its product with the brightest pixel does not
            raise InputError(f"{source}: the exposure × auto-level × --scale factor {factor:g} times the brightest "
                             f"corrected pixel {peak:g} exceeds float32; lower {_gain_option_names(corr)}")
        raise InputError(f"{source}: the corrections produced NaN or Inf values")
    if _underflowed(img):
        raise InputError(f"{source}: the exposure × auto-level × --scale factor {factor:g} takes the image below "
                         f"float32's smallest numbers (its brightest pixel becomes {float(img.max()):g}): nothing would "
                         f"be left to reconstruct; raise {_gain_option_names(corr)}")
    return img


def _level_notes(img: np.ndarray, raw: np.ndarray, full_scale: float, white: float, corr: RawCorrection, source: str,
                 check_level: bool, check_bit_depth: bool, trained_peak: float = 1.0) -> list[str]:
    """The warnings about the level of the corrected image ``img`` (H, W, full scale 1) of the capture ``raw`` (DN),
    InputError for those refused: a gain past full scale or far below it (:func:`_check_level`), a dim integer
    capture (:func:`_check_dim`) or float capture (:func:`_check_dim_float`), a white level far above the data
    (:func:`_check_white_level`), a float capture that holds DN."""
    notes: list[str] = []
    if check_level:
        notes += _check_level(img, corr, source)
    if check_bit_depth and full_scale > 1 and corr.white_level is None and corr.auto_level is None:
        notes += _check_dim(img, raw, full_scale, source)
    if corr.white_level is not None and corr.auto_level is None:
        notes += _check_white_level(img, raw, full_scale, white, source)
    if check_bit_depth and full_scale == 1 and corr.white_level is None and not _gain_options(corr):
        notes += _check_dim_float(img, source)
    if full_scale == 1 and corr.white_level is None and corr.auto_level is None and raw.size \
            and raw.max() > FLOAT_OVER_SCALE * trained_peak:
        notes.append(f"{source}: a float capture is read on the simulator's scale (0 = black, 1 = full scale), and this "
                     f"one reaches {float(raw.max()):g}: if it holds DN, pass the sensor's white level (--white-level DN) "
                     f"or --auto-level; the network was trained on images within [0, {trained_peak:g}]")
    return notes


def _same_phase_index(n: int, m: int) -> np.ndarray:
    """Indices into an axis of ``n`` pixels for the positions −m … n + m − 1: inside, themselves; outside,
    the nearest pixel of the same phase modulo ``m`` (clipped to the axis when it is shorter than ``m``)."""
    k = np.arange(-m, n + m)
    k = np.where(k < 0, k % m, k)
    k = np.where(k >= n, k - m * ((k - n) // m + 1), k)
    return np.clip(k, 0, n - 1)


def normalised_flat(flat_dn: np.ndarray, black: float, period: int | None = None) -> np.ndarray:
    """The flat-field frame (H, W, DN) as the capture is divided by it: minus the black level, averaged
    over ``period`` (the CFA period; None or 1: pixel-wise), normalised to mean 1 (float64). InputError
    for a flat without signal, or with pixels below 5 % of its mean."""
    flat = np.asarray(flat_dn, dtype=np.float64) - black
    if period and period > 1:
        from scipy.ndimage import uniform_filter

        # padded by whole periods, so every window of the border sees each CFA phase once (edge
        # replication counted the border's phases twice and left the CFA's pattern in the flat there)
        m = period
        rows, cols = (_same_phase_index(n, m) for n in flat.shape)
        flat = uniform_filter(flat[np.ix_(rows, cols)], size=m, mode="nearest")[m:-m, m:-m]
    mean = float(flat.mean())
    if not mean > 0:
        raise InputError(f"flat field has no signal above the black level ({black:g} DN)")
    flat /= mean
    low = int(np.count_nonzero(flat < 0.05))
    if low:
        hint = "" if period and period > 1 else "; a flat taken through the CFA: --flat-mode cfa"
        raise InputError(f"flat field has {low} pixel(s) below 5 % of its mean (dead pixels or a wrong black level"
                         f"{hint})")
    return flat


def frame_data(frame: "np.ndarray | RawImage | None") -> np.ndarray | None:
    """The values (DN) of a dark or flat frame given as an array or as the :class:`RawImage` read."""
    return frame.data if isinstance(frame, RawImage) else frame


def _check_frame_type(name: str, frame: "np.ndarray | RawImage | None", capture_dtype: str | None,
                      full_scale: float, source: str, why: str) -> None:
    """InputError when ``frame``, a :class:`RawImage`, was stored with another full scale than the
    capture's ``full_scale`` (float 0-1 against integer DN, 8 against 16 bit): other units."""
    if not isinstance(frame, RawImage) or frame.full_scale == full_scale:
        return
    dtype, frame_scale, path = frame.dtype, frame.full_scale, frame.path
    capture = (f"is stored as {capture_dtype} (full scale {full_scale:g})" if capture_dtype
               else f"has full scale {full_scale:g}")
    target = capture_dtype or "the capture's type"
    who = "the capture" if source == "capture" else f"the capture {source}"
    raise InputError(f"{path}: the {name} is stored as {dtype} (full scale {frame_scale:g}) but {who} "
                     f"{capture}: its values are in other units, and {why}: save the {name} as {target}, in the "
                     "capture's DN")


def _given_gains(corr: RawCorrection) -> list[tuple[str, str]]:
    """The options of ``corr`` that multiply the image, each as (its name, its name with the values given): the
    one list of them (a new gain option is added here)."""
    gains = []
    if corr.exposure_s is not None:
        ratio = corr.reference_exposure_s / corr.exposure_s
        gains.append(("--reference-exposure-s / --exposure-s",
                      f"--reference-exposure-s {corr.reference_exposure_s:g} / --exposure-s {corr.exposure_s:g} "
                      f"(×{ratio:.3g})"))
    if corr.auto_level is not None:
        gains.append(("--auto-level", f"--auto-level {corr.auto_level:g}"))
    if corr.scale != 1.0:
        gains.append(("--scale", f"--scale {corr.scale:g}"))
    return gains


def _gain_options(corr: RawCorrection) -> list[str]:
    """The options of ``corr`` that multiply the image (CLI spelling, with their values)."""
    return [given for _, given in _given_gains(corr)]


def _gain_option_names(corr: RawCorrection) -> str:
    """The options of ``corr`` that multiply the image, by name (what a gain's refusal tells to change)."""
    return " or ".join(name for name, _ in _given_gains(corr)) or "--scale"


def _check_level(img: np.ndarray, corr: RawCorrection, source: str) -> list[str]:
    """After a gain the user asked for (``scale``, ``auto_level``, the exposure ratio): InputError
    when the image's 99.9th percentile exceeds :data:`MAX_LEVEL` × full scale (1); a warning
    (returned) when more than :data:`CLIP_SHARE` of the pixels are above full scale."""
    opts = _gain_options(corr)
    if not opts or not img.size:
        return []
    used = " and ".join(opts)
    level, peak = float(np.percentile(img, 99.9)), float(img.max())
    if level > MAX_LEVEL:
        fix = (f"--scale {corr.scale / level:.3g} puts it at 1" if corr.scale != 1.0 and corr.auto_level is None
               else "--auto-level 1 or lower puts it there" if corr.auto_level is not None
               else "check --exposure-s and --reference-exposure-s")
        raise InputError(f"{source}: {used} puts the image far past the sensor's full scale (1): its 99.9th percentile "
                         f"is {level:.3g} and its brightest pixel {peak:.3g} (refused above {MAX_LEVEL:g}); the network "
                         f"was trained on images within [0, 1]: {fix}")
    if level < DIM_AFTER_GAIN:
        fix = ("--auto-level 0.5 to 1 is usual" if corr.auto_level is not None
               else f"--scale {corr.scale * 0.5 / max(level, 1e-30):.3g} puts it at 0.5" if corr.scale != 1.0
               else "check --exposure-s and --reference-exposure-s")
        return [f"{source}: {used} leaves the image very dark: its 99.9th percentile is {level:.3g} of the sensor's full "
                f"scale (1; warned below 1/{round(1 / DIM_AFTER_GAIN)}), far below the levels the network was trained on: {fix}"]
    share = float(np.count_nonzero(img > 1.0)) / img.size
    if share > CLIP_SHARE:
        return [f"{source}: {used} puts {100 * share:.1f} % of the pixels above the sensor's full scale (1; brightest "
                f"pixel {peak:.3g}): a real sensor clips there, and the network was trained on images within [0, 1]"]
    return []


def _subtracted(black: float, dark_median: float | None) -> str:
    if dark_median is not None:
        return f"after subtracting the dark frame (median {dark_median:g} DN)"
    return f"after subtracting the black level {black:g} DN" if black else "(no dark frame or black level subtracted)"


def _check_signal(img: np.ndarray, raw: np.ndarray, black: float, dark_median: float | None, source: str) -> list[str]:
    """InputError if (nearly) no pixel of ``img`` = raw − dark/black is above 0 (fewer than
    :data:`MIN_SIGNAL_SHARE`); a warning (returned) if more than :data:`MAX_NEGATIVE_SHARE` are below 0."""
    n = img.size
    positive = int(np.count_nonzero(img > 0))
    negative = int(np.count_nonzero(img < -NEGATIVE_ROUNDOFF * float(np.max(np.abs(img)))))
    brightest = float(raw.max())
    if positive <= MIN_SIGNAL_SHARE * n:
        if dark_median is not None:
            cause = (f"after subtracting the dark frame (median {dark_median:g} DN; the capture's brightest pixel is "
                     f"{brightest:g} DN): the dark frame is as bright as the capture or brighter (another exposure, "
                     "gain or file? pass the dark frame taken with this capture's settings)")
        elif black:
            cause = (f"after subtracting the black level {black:g} DN (the capture's brightest pixel is {brightest:g} DN): "
                     "lower the black level (--black-level)")
        else:
            cause = f"(brightest pixel {brightest:g}): the capture has no signal"
        raise InputError(f"{source}: {positive} of {n} pixels are above 0 {cause}; nothing to reconstruct")
    if negative > MAX_NEGATIVE_SHARE * n:
        advice = ("is the dark frame / black level too high? (pass the dark frame taken with this capture's settings)"
                  if dark_median is not None or black else "is it a signed or mean-subtracted image?")
        share = 100.0 * negative / n
        return [f"{source}: {share:.0f} % of the pixels are below 0 {_subtracted(black, dark_median)}; the capture should "
                f"be in sensor units with 0 = black: {advice} (negative values go to the network as they are)"]
    return []


def _check_saturated(raw: np.ndarray, saturated: int, white: float, explicit: bool, source: str) -> list[str]:
    """InputError when more than :data:`MAX_SATURATED_SHARE` of the pixels are at or above the white
    level ``white`` (``explicit``: given by the user); a warning (returned) for any fewer."""
    if not saturated:
        return []
    n = raw.size
    share = saturated / n
    if share > MAX_SATURATED_SHARE:
        brightest, median = float(raw.max()), float(np.median(raw))
        fix = (f"is --white-level {white:g} the sensor's full scale? (the capture's median is {median:g} DN, its "
               f"brightest pixel {brightest:g} DN); or the capture is over-exposed: take it again with a shorter exposure"
               if explicit else "the capture is over-exposed: take it again with a shorter exposure")
        raise InputError(f"{source}: {saturated} of {n} pixels ({100 * share:.0f} %) are at or above the white level "
                         f"{white:g} DN (saturated; refused above {100 * MAX_SATURATED_SHARE:.0f} %): there is nothing "
                         f"but a flat white image to reconstruct: {fix}")
    return [f"{source}: {saturated} pixel(s) at or above the white level {white:g} DN (saturated; {100 * share:.2g} % of "
            f"the pixels, refused above {100 * MAX_SATURATED_SHARE:.0f} %)"]


def _check_float_clip(raw: np.ndarray, source: str) -> list[str]:
    """A warning (returned) for a float capture read at its own scale (no ``--white-level``) with at least
    :data:`SENSOR_CLIP_MIN_PX` pixels at exactly 1.0, its brightest value: clipped at full scale (a conversion or the
    sensor), but read as measured light, where a white level reads them as lower bounds (session 74's hunt: 28 % of a
    capture at 1.0 reconstructed without a word, its clipped pixels' error 7× the rest's)."""
    if not raw.size or float(raw.max()) != 1.0:
        return []
    clipped = int(np.count_nonzero(raw == 1.0))
    if clipped < SENSOR_CLIP_MIN_PX:
        return []
    return [f"{source}: {clipped} pixel(s) ({100 * clipped / raw.size:.2g} %) sit at exactly 1.0, the capture's brightest "
            "value: clipped at full scale? They are read as measured light; give --white-level 1 to read them as "
            "clipped (lower bounds of their light; refused above "
            f"{100 * MAX_SATURATED_SHARE:.0f} % of the pixels)"]


def _check_white_level(img: np.ndarray, raw: np.ndarray, full_scale: float, white: float, source: str) -> list[str]:
    """With an explicit white level: InputError for a float capture whose values all lie within [0, 1]
    (the simulator's scale already) and whose 99.9th percentile (after every correction) ends below
    :data:`DARK_WHITE_FRACTION` of full scale; a warning (returned) for any other such capture."""
    if not img.size:
        return []
    level = float(np.percentile(img, 99.9))
    if not level < DARK_WHITE_FRACTION:
        return []
    brightest = float(raw.max())
    if full_scale == 1 and brightest <= 1.0:
        if white <= 1.0:  # a float capture's own level (or below): a dark scene, judged as without the option
            return []
        raise InputError(f"{source}: --white-level {white:g} is far above this float capture's values, which lie "
                         f"within [0, 1] (brightest {brightest:g}): it is on the simulator's scale (1 = full scale) "
                         f"already, and the white level divides it down to a 99.9th percentile of {level:.3g} of full "
                         f"scale (refused below 1/{round(1 / DARK_WHITE_FRACTION)}): leave --white-level out")
    return [f"{source}: very dark: with --white-level {white:g} the image's 99.9th percentile is {level:.3g} of full "
            f"scale (brightest pixel {brightest:g}; warned below 1/{round(1 / DARK_WHITE_FRACTION)}): is {white:g} this "
            "sensor's full scale (4095 for 12 bit, 65535 for 16 bit)? if the capture is just dark, scale it "
            "(--exposure-s/--reference-exposure-s, --scale or --auto-level)"]


def _check_dim_float(img: np.ndarray, source: str) -> list[str]:
    """A warning (returned) when a float capture, read on the simulator's scale with no gain asked for, has its
    99.9th percentile below :data:`DIM_AFTER_GAIN` of full scale (1): far darker than any training image (the
    network's output is then no longer proportional to the capture: through the shipped camera a constant capture of
    1e-4 comes back at 1.01× its level, one of 1e-6 at 4.4×, one of 1e-30 at about 4e-6, 4e24×; session 70)."""
    level = float(np.percentile(img, 99.9)) if img.size else 0.0
    if not 0 < level < DIM_AFTER_GAIN:  # (no signal at all is refused before)
        return []
    return [f"{source}: very dark: the float capture's 99.9th percentile is {level:.3g} of the sensor's full scale (1; "
            f"warned below 1/{round(1 / DIM_AFTER_GAIN)}), far below the levels the network was trained on (about 0.1 "
            "to 0.75): if its values are on another scale, pass --white-level, or bring it up with --auto-level 0.5 "
            "(or --scale)"]


#: This many pixels (or more) at exactly 2^b − 1 DN (b = 10, 12, 14) in a 16-bit capture read without a white level
#: are the clipped pixels of a b-bit sensor: warned about (:func:`_check_dim`), whatever the level.
SENSOR_CLIP_MIN_PX = 3


def _check_dim(img: np.ndarray, raw: np.ndarray, full_scale: float, source: str) -> list[str]:
    """A warning (returned) when an integer capture normalised with its container's full scale stays below
    :data:`DIM_FRACTION` of full scale at its brightest pixel (see the module docstring), or when
    :data:`SENSOR_CLIP_MIN_PX` or more of its pixels sit at a 10-, 12- or 14-bit sensor's white level in a 16-bit file:
    a 14-bit capture (at most 1/4 of full scale, which :data:`DIM_FRACTION` leaves alone) was read at a quarter of
    its level without a word, its clipped pixels not counted as saturated (session 73)."""
    peak = float(img.max())
    raw_max = float(raw.max())
    container = max(1, math.ceil(math.log2(full_scale + 1)))
    depth = next((b for b in (10, 12, 14) if raw_max == 2 ** b - 1 and b < container), None)
    at_white = int(np.count_nonzero(raw == raw_max)) if depth is not None else 0
    if at_white >= SENSOR_CLIP_MIN_PX and not peak < DIM_FRACTION:
        return [f"{source}: {at_white} pixels sit at {raw_max:g} DN, a {depth}-bit sensor's white level, in a "
                f"{container}-bit file: if the sensor has {depth} bits, the capture is read at {raw_max / full_scale:.3g} "
                f"of its level and those pixels are not counted as clipped: pass --white-level {raw_max:g}"]
    if not peak < DIM_FRACTION:
        return []
    used = math.ceil(math.log2(raw_max + 1)) if raw_max > 0 else 1  # bits the brightest pixel needs
    bits = next((b for b in (8, 10, 12, 14) if used <= b < container), None)  # the common raw depths
    hint = (f"if the sensor has {bits} bits (stored in a {container}-bit file), pass --white-level {2 ** bits - 1}"
            if bits is not None else "pass the sensor's white level (--white-level DN)")
    return [f"{source}: very dark: the brightest pixel is {peak:.3g} of full scale ({raw_max:g} of {full_scale:g} DN; "
            f"warned below {DIM_FRACTION:.3g}); likely cause: a sensor bit depth below the file's: {hint}; if the "
            "capture is just dark, scale it (--exposure-s/--reference-exposure-s, --scale or --auto-level)"]


#: What ``hsicam simulate`` writes beside its sensor image (``sensor_png_scale``: sensor = PNG · scale).
SIMULATE_JSON = "simulate.json"

#: The PNG text chunk of ``hsicam simulate``'s ``sensor.png`` holding the same scale (sensor = PNG · scale),
#: so that a copy taken away from its simulate.json reconstructs at the right level.
SENSOR_SCALE_KEY = "hsicam-sensor-scale"


#: ``hsicam simulate``'s display image of its sensor image, beside the data file sensor.png: 8-bit, linear, exposed
#: so that its 99th percentile is :data:`hsicam.color.PREVIEW_LEVEL` of white (the data file of a dim scene, e.g. the tiny
#: camera's at 0.12 of full scale, looks black). Not sensor data: reconstruct refuses it (its text chunk
#: :data:`hsicam.color.PREVIEW_EXPOSURE_KEY` holds the exposure).
SENSOR_PREVIEW = "sensor_preview.png"


def sensor_preview(sensor: np.ndarray) -> tuple[np.ndarray, float]:
    """(image in [0, 1], exposure) of :data:`SENSOR_PREVIEW`: ``sensor`` times the exposure that puts its 99th
    percentile at :data:`hsicam.color.PREVIEW_LEVEL` (:func:`hsicam.color.display_gain`), clipped."""
    from hsicam.color import display_gain

    exposure = display_gain(float(np.percentile(sensor, 99)) if sensor.size else 0.0)
    return np.clip(np.asarray(sensor, dtype=np.float64) * exposure, 0.0, 1.0), exposure


def _png_text(path: str | Path, key: str) -> str | None:
    """The PNG text chunk ``key`` of ``path``, else None (none, another format, or unreadable)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return getattr(im, "text", {}).get(key) if im.format == "PNG" else None
    except Exception:  # noqa: BLE001 - unreadable: the reader says so
        return None


def png_sensor_scale(path: str | Path) -> float | None:
    """The scale that ``hsicam simulate`` wrote into a ``sensor.png`` (:data:`SENSOR_SCALE_KEY`), else
    None (another PNG, or not a PNG). :class:`InputError` for a chunk that is no positive finite number."""
    value = _png_text(path, SENSOR_SCALE_KEY)
    if value is None:
        return None
    try:
        scale = float(value)
    except ValueError:
        scale = float("nan")
    if not (math.isfinite(scale) and scale > 0):
        raise InputError(f"{path}: its {SENSOR_SCALE_KEY} text chunk is {value!r}, not a positive scale")
    return scale


#: The file name of the sensor image that ``hsicam simulate`` writes as a 16-bit PNG.
SIMULATED_SENSOR_PNG = "sensor.png"


def is_simulated_image(path: str | Path, fmt: str, png_scale: float | None = None) -> bool:
    """Whether ``path`` (read as format ``fmt``) is the sensor image that ``hsicam simulate`` wrote:
    a PNG carrying its scale (``png_scale``, its :func:`png_sensor_scale`), or (an older simulation's) a
    :data:`SIMULATED_SENSOR_PNG` with ``simulate.json`` beside it (whose ``sensor_png_scale`` then applies). Another
    image in that folder, a capture copied there (a float TIFF holds its level already), is not."""
    if png_scale is not None:
        return True
    path = Path(path)
    return fmt == "png" and path.name == SIMULATED_SENSOR_PNG and (path.parent / SIMULATE_JSON).is_file()


def read_capture(path: str | Path, corr: RawCorrection | None = None, scale: float | None = None,
                 return_saturated: bool = False, trained_peak: float = 1.0
                 ) -> tuple[np.ndarray, dict] | tuple[np.ndarray, dict, np.ndarray]:
    """Read a capture and apply ``corr`` → (float32 (H, W) on the simulator scale, report); with
    ``return_saturated`` also the (H, W) bool map of the pixels the sensor clipped (at or above the white level,
    :func:`preprocess_raw`).

    ``scale`` (if given) overrides ``corr.scale``. The ``sensor.png`` of ``hsicam simulate`` is first brought
    back to its simulated level by the scale written inside it (:data:`SENSOR_SCALE_KEY`), an older simulation's
    ``sensor.png`` by the ``sensor_png_scale`` of the ``simulate.json`` beside it (:func:`is_simulated_image`);
    ``scale`` multiplies that level, as it would simulate's ``sensor.npy`` (``corr.auto_level`` sets the level instead).
    ``trained_peak``: as :func:`preprocess_raw` takes it.

    Raises :class:`InputError` for a 32/64-bit integer capture without ``corr.white_level`` (or
    ``auto_level``, which makes the white level irrelevant): the type's maximum is no full scale.
    """
    from hsicam.color import PREVIEW_EXPOSURE_KEY

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: a folder, not a sensor image (give one .npy, .png or .tif file)")
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(f"{path}: unsupported sensor image format (use .npy, .png, .tif)")
    image = read_image_2d(path, "sensor image")
    preview_exposure = _png_text(path, PREVIEW_EXPOSURE_KEY) if image.format == "png" else None
    if preview_exposure is not None:
        raise InputError(f"{path}: hsicam simulate's display preview (exposed x{preview_exposure}, 8 bit), not sensor "
                         "data: give its sensor.png or sensor.npy")
    corr = corr or RawCorrection()
    if np.dtype(image.dtype).kind in "ui" and np.dtype(image.dtype).itemsize >= 4 and corr.white_level is None \
            and corr.auto_level is None:
        raise InputError(f"{path}: {image.dtype} capture without a white level: the type's maximum "
                         f"({image.full_scale:.3g}) is no sensor's full scale; pass the sensor's white level, "
                         f"--white-level DN (4095 for 12 bit, 65535 for 16 bit; the brightest pixel here is "
                         f"{float(image.data.max()):g} DN)")
    if np.dtype(image.dtype).kind in "ui" and corr.white_level is not None and corr.white_level > image.full_scale:
        raise InputError(f"{path}: --white-level {corr.white_level:g} DN is above the largest value its "
                         f"{image.dtype} pixels can hold ({image.full_scale:g}): no pixel can reach it, and the image "
                         f"would stay below {image.full_scale / corr.white_level:.3g} of full scale: pass the sensor's "
                         f"white level, at most {image.full_scale:g} (the brightest pixel here is "
                         f"{float(image.data.max()):g} DN), or leave --white-level out for the type's maximum")
    png_scale = png_sensor_scale(path) if image.format == "png" else None  # the PNG's own, wherever it was copied
    simulated = is_simulated_image(path, image.format, png_scale)
    simulated_scale = 1.0
    if simulated:
        simulated_scale = png_scale
        if simulated_scale is None:
            meta = path.parent / SIMULATE_JSON
            try:
                simulated_scale = float(json.loads(meta.read_text(encoding="utf-8")).get("sensor_png_scale", 1.0))
            except (ValueError, TypeError, AttributeError):
                raise InputError(f"{meta}: unreadable simulate.json") from None
            if not (math.isfinite(simulated_scale) and simulated_scale > 0):  # not a --scale the user gave
                raise InputError(f"{meta}: its sensor_png_scale is {simulated_scale:g}, not a positive scale")
    # simulate's PNG of an image brighter than full scale: its peak is full scale by design, no sensor's clipping
    # (whatever sets the level: with --auto-level too)
    stretched = simulated_scale > 1.0
    if scale is not None:
        corr = RawCorrection(**{**corr.__dict__, "scale": float(scale)})
    # simulate's own image is written at the file's full bit depth: a dark one is a dark scene. Its scale brings it
    # back to its simulated level (--auto-level sets the level itself); a --scale multiplies that level, as it
    # multiplies simulate's sensor.npy, and is checked as there
    restored = simulated_scale if corr.auto_level is None else 1.0
    img, report, saturated = preprocess_raw(image.data, image.full_scale, corr, str(path),
                                            check_saturation=not stretched, check_bit_depth=not simulated,
                                            restored_scale=restored, stored_dtype=image.dtype, return_saturated=True,
                                            trained_peak=trained_peak)
    if stretched and restored > FLOAT_OVER_SCALE * trained_peak:  # its brightest pixel: simulated_scale
        # the float capture's warning (preprocess_raw), for simulate's image of a scene far above full scale
        log.warning("%s: hsicam simulate's image of a scene far brighter than full scale: it is read back at its "
                    "simulated level (%s %g, its brightest pixel); a real sensor saturates at 1 and the network was "
                    "trained on images within [0, %g]: simulate the scene normalised to [0, 1]", path,
                    SENSOR_SCALE_KEY if png_scale is not None else SIMULATE_JSON, simulated_scale, trained_peak)
    report.update({"source": str(path), "stored_dtype": image.dtype, "format": image.format,
                   "shape": [int(s) for s in img.shape]})
    return (img, report, saturated) if return_saturated else (img, report)


def read_sensor_image(path: str | Path, scale: float | None = None) -> np.ndarray:
    """A sensor image as float32 (H, W) on the simulator's [0, 1] scale.

    ``.npy`` float arrays are used as is; integer images (PNG, TIFF, integer ``.npy``) are divided
    by the type's maximum (32/64-bit integers are refused: see :func:`read_capture`); ``hsicam simulate``'s
    image is then brought back to its simulated level (the scale written into its PNG, or an older simulation's
    ``sensor_png_scale`` from the ``simulate.json`` beside its ``sensor.png``); then multiplied by ``scale`` (default 1).
    """
    img, _ = read_capture(path, None, scale)
    return img
