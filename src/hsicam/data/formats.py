"""Readers and writers for hyperspectral cube files.

:func:`read_cube` detects the format **by content** (magic bytes, MAT header, HDF5/MAT variable
names), never by file extension alone, and returns ``(cube, bands, metadata)`` with ``cube`` a
float32 array (C, H, W), bands ascending. Explicit readers exist for each format; every problem
(truncated or corrupt file, missing key, NaN/Inf, negative values, wrong dimensions, unknown format)
raises one :class:`~hsicam.errors.InputError` that names the file and the problem.

Formats and their band grids (when the file does not carry wavelengths):

================  ===================================================  ==========================
format            layout on disk                                       bands
================  ===================================================  ==========================
``hsicam``        our HDF5: ``cube`` (C, H, W) float32, ``bands_nm``,   from the file
                  ``fwhm_nm``, attributes (``format="hsicam-cube"``,
                  ``version``: a newer one than this code writes, or
                  one below 1, is refused, :func:`check_format_version`)
``icvl``          MAT v7.3 (HDF5), ``rad`` H×W×C in MATLAB order —      band list (else 400-700/10)
                  h5py returns it reversed, (C, W, H)
``arad``          ARAD / NTIRE MAT v7.3, ``cube`` (as ICVL), ``bands``;  band list (else 400-700/10)
                  also a plain HDF5 ``cube`` with a band list
``kaist-mat``     MST-style MAT (v5 or v7.3), ``img`` or               band list (else 28 bands: MST's
                  ``img_expand`` H×W×C                                  453.3-648.1; 31: 400-700/10)
``harvard``       MAT v5, ``ref`` H×W×31                                band list (else 420-720/10)
``kaist-exr``     OpenEXR, one channel per band, wavelength in the      from channel names
                  channel name (``550nm``, ``w550nm``, ``S0.550,0nm``)
``cave``          folder of 31 16-bit PNGs ``<name>_ms_01.png`` …       400-700/10
                  ``_31.png`` (may be one level down)
``envi``          ``.hdr`` + raw data, bsq/bil/bip, ENVI data types,    ``wavelength``/``fwhm``
                  byte order, header offset; ``bbl`` bands dropped,
                  ``data ignore value`` pixels set to 0, ``data gain
                  values`` / ``data offset values`` applied
                  (:func:`read_envi`)
``npy``           ``.npy`` (C, H, W)                                    caller's ``bands`` (config:
                                                                        ``data.npy_bands``), else C
                                                                        bands evenly over 400-700
================  ===================================================  ==========================

MAT and HDF5 files: the file's own band list is used whenever it has one, whatever the cube's key:
a variable named ``bands`` or another of :data:`BAND_LIST_NAMES` (``wavelength``, ``wavelengths``,
``lambda``, ``wl`` …, in any case; two that differ are refused), its length checked against the
cube's band axis. The grid in the last column is assumed only for a file without one, said in one
log line and recorded as the metadata's ``assumed_grid``. A MAT file (v5, or v7.3: HDF5 with the
512-byte "MATLAB 7.3 MAT-file" user block or ``MATLAB_class`` attributes) holds H×W×C; an HDF5 file
without either (h5py's) is read in C order, as (C, H, W) or (H, W, C) by which of its first and last
axes has the band count (both: refused as ambiguous). A MAT cube whose *first* axis has the band
count is refused with a note on the (C, H, W) order, not guessed.

A band list stored without a unit (MAT ``bands``, ENVI ``wavelength`` without ``wavelength units``)
whose values all lie below :data:`MICROMETRE_BELOW` (30) is read as micrometres, with a logged note;
one that is not numbers (text, a struct or cell array) is an :class:`~hsicam.errors.InputError`.
Band centres (in nm, or converted from micrometres) are rounded to :data:`NM_DECIMALS` (3) decimals of a nm, and a
float32 list is read at its shortest decimal (float32 0.7 µm is 700 nm, not 699.99998). A strictly
descending list (MAT, HDF5, ours) is reversed together with the cube's band axis (ENVI sorts any
order, each band carrying its own wavelength); a list in neither order is refused.

ICVL, CAVE, KAIST and ARAD cover 400-700 nm; the paper's camera uses 420-720 nm. We
**resample, never relabel** (:func:`hsicam.spectral.resample_spectra`: interpolation by band centre,
or integration over a band's FWHM where the data are finer): bringing a 400-700 nm cube onto 420-720 nm is
refused (720 nm lies outside the data) — use a camera grid inside the data's range (e.g.
``bands.start_nm=420, bands.stop_nm=700``) or data that reaches 720 nm (Harvard, or the embedded
synthetic set). See ``docs/data.md``.

**Memory budget**: every reader compares the size that the file *declares* (HDF5 dataset shape,
MAT v5 variable header, NPY header, ENVI header, EXR data window, PNG headers) with the memory
budget (:func:`hsicam.data.cube.memory_budget_bytes`: the ``memory_budget_mb`` argument, else
``$HSICAM_MEMORY_BUDGET_MB``, else a quarter of the machine's memory) *before* allocating the cube,
and refuses a larger one with one :class:`~hsicam.errors.InputError`.

Writers: :func:`write_cube_h5` (our HDF5) and :func:`write_envi`; both write atomically.
"""

from __future__ import annotations

import contextlib
import glob
import json
import logging
import math
import numbers
import os
import re
import zlib
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple, Sequence

import numpy as np

from hsicam.data.cube import NEGATIVE_READ_ADVICE, check_cube, check_memory_budget
from hsicam.errors import InputError
from hsicam.io import NPY_MAGIC, atomic_path, check_output_path, json_text, nan_for_null
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

HSICAM_FORMAT = "hsicam-cube"
HSICAM_FORMAT_VERSION = 1

#: MST (Meng et al. / Cai et al.) 28-band KAIST/CAVE grid, nm.
MST_28_NM = (453.3, 457.6, 462.1, 466.8, 471.6, 476.5, 481.6, 486.9, 492.4, 498.0, 503.9, 509.9, 516.2, 522.7,
             529.5, 536.5, 543.8, 551.4, 558.6, 567.5, 575.3, 584.3, 594.4, 604.2, 614.4, 625.1, 636.3, 648.1)

FORMATS = ("hsicam", "icvl", "arad", "kaist-mat", "harvard", "kaist-exr", "cave", "envi", "npy")

#: File suffixes considered when a folder is listed as a dataset (format is still judged by content).
SCENE_SUFFIXES = (".h5", ".hdf5", ".mat", ".npy", ".exr", ".hdr")

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_EXR_MAGIC = b"v/1\x01"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_CAVE_RE = re.compile(r"^(?P<prefix>.+)_ms_(?P<index>\d{2})\.png$", re.IGNORECASE)
_ENVI_DATA_SUFFIXES = ("", ".img", ".dat", ".raw", ".bsq", ".bil", ".bip", ".bin", ".IMG", ".DAT", ".RAW")
#: Key of the CRC-32 (hex) of the data file in the ENVI headers hsicam writes (:func:`write_envi`);
#: other ENVI software ignores unknown keys.
ENVI_CRC_KEY = "hsicam data crc32"
#: The ENVI header key under which :func:`write_envi` keeps a cube's metadata (the JSON that our HDF5 keeps as its
#: ``metadata_json`` attribute; :func:`envi_metadata_value`), which :func:`read_envi` returns in the cube's meta.
ENVI_METADATA_KEY = "hsicam metadata"
_ENVI_DTYPES = {1: "u1", 2: "i2", 3: "i4", 4: "f4", 5: "f8", 12: "u2", 13: "u4", 14: "i8", 15: "u8"}
_ENVI_INTERLEAVES = ("bsq", "bil", "bip")

Cube = tuple[np.ndarray, Bands, dict[str, Any]]


def bands_400_700(n: int = 31) -> Bands:
    """``n`` bands evenly spaced over 400-700 nm (the 10 nm grid for n = 31; one band: 550 nm)."""
    if n == 1:
        return Bands.from_centers([550.0])
    return Bands.from_centers(np.linspace(400.0, 700.0, n))


def describe_400_700(n: int) -> str:
    """What :func:`bands_400_700` assumed, for a log line or a file's metadata."""
    return "one band at 550 nm" if n == 1 else f"{n} bands evenly spaced over 400-700 nm"


# ------------------------------------------------------------------------------------------------
# Error handling
# ------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _reading(path: Path, what: str) -> Iterator[None]:
    """Turn any failure of a third-party parser into one InputError naming the file."""
    try:
        yield
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{path}: the {what} data is too large to load into memory") from None
    except FileNotFoundError:
        raise InputError(f"{path}: no such file or folder") from None
    except Exception as exc:  # noqa: BLE001 - h5py/scipy/imageio/OpenEXR raise many types
        if path.is_dir():  # h5py's words for it: "[Errno 21] Unable to synchronously open file", read as corrupt
            raise InputError(f"{path}: a folder, not a file ({what} expected)") from None
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{path}: cannot read {what} file (corrupt or truncated?): {detail}") from None


def _checked_read(p: Path, ds: Any, budget_mb: float | None) -> np.ndarray:
    """Read a whole h5py dataset after checking its declared size against the memory budget (a
    corrupt or hostile header can declare terabytes in a few bytes)."""
    check_memory_budget(p, ds.shape, ds.dtype, what=f"dataset '{ds.name.lstrip('/')}'", budget_mb=budget_mb)
    return ds[()]


def _as_path(path: str | os.PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    return p


# ------------------------------------------------------------------------------------------------
# Detection
# ------------------------------------------------------------------------------------------------
def detect_format(path: str | os.PathLike) -> str:
    """Return the format name (one of :data:`FORMATS`) of ``path``, judged by its content."""
    p = _as_path(path)
    if p.is_dir():
        if _find_cave_pngs(p) is not None:
            return "cave"
        raise InputError(f"{p}: unknown format: a folder that is not a CAVE scene (no '*_ms_01.png' files)")
    head = _head(p, 128)
    if not head:
        raise InputError(f"{p}: empty file")
    if head.startswith(_HDF5_MAGIC) or head.startswith(b"MATLAB 7.3"):
        return _detect_hdf5(p, head)
    if head.startswith(b"MATLAB 5.0"):
        return _detect_mat5(p)
    if head.startswith(NPY_MAGIC):
        return "npy"
    if head.startswith(_EXR_MAGIC):
        return "kaist-exr"
    if head.lstrip().startswith(b"ENVI"):
        return "envi"
    if _envi_header_for(p) is not None:
        return "envi"
    if head.startswith(_PNG_MAGIC) and _CAVE_RE.match(p.name):
        raise InputError(f"{p}: a single CAVE band image; pass the scene folder that holds all 31 PNGs")
    hint = ""
    if p.suffix.lower() in _ENVI_DATA_SUFFIXES:  # e.g. an ENVI pair whose header was lost or not copied along
        hint = f"; if it is an ENVI data file, its header is missing: no ENVI {p.with_suffix('.hdr').name} next to it"
    raise InputError(f"{p}: unknown format (not our HDF5, MAT v5/v7.3, NPY, OpenEXR, ENVI or a CAVE folder){hint}")


def _head(p: Path, n: int) -> bytes:
    if p.is_dir():
        raise InputError(f"{p}: a folder, not a file")
    try:
        with open(p, "rb") as fh:
            return fh.read(n)
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror})") from None


_HDF5_KEYS = (("rad", "icvl"), ("img", "kaist-mat"), ("img_expand", "kaist-mat"), ("HSI", "kaist-mat"),
              ("ref", "harvard"))


def _detect_hdf5(p: Path, head: bytes) -> str:
    import h5py

    with _reading(p, "HDF5/MAT v7.3"):
        with h5py.File(p, "r") as f:
            keys = set(f.keys())
            if "cube" in keys and "bands_nm" in keys:
                return "hsicam"
            if "cube" in keys and (_band_list_names(sorted(keys)) or _is_matlab_h5(head, f)):
                return "arad"  # MATLAB v7.3, or a plain HDF5 cube with its band list (read in C order)
            for key, fmt in _HDF5_KEYS:
                if key in keys:
                    return fmt
            if "cube" in keys:
                raise InputError(f"{p}: HDF5 file with 'cube' but missing key 'bands_nm' (our format) or a band list "
                                 f"'bands' (ARAD; also read under the names {', '.join(BAND_LIST_NAMES[1:])})")
    raise _no_known_variable(p, "HDF5/MAT", ("cube", *(k for k, _ in _HDF5_KEYS)), sorted(keys), _cube_like_arrays(p))


_MAT5_KEYS = (("rad", "icvl"), ("cube", "arad"), ("img", "kaist-mat"), ("img_expand", "kaist-mat"), ("HSI", "kaist-mat"),
              ("ref", "harvard"))


def _detect_mat5(p: Path) -> str:
    import scipy.io

    with _reading(p, "MAT v5"):
        names = [w[0] for w in scipy.io.whosmat(p)]
    for key, fmt in _MAT5_KEYS:
        if key in names:
            return fmt
    raise _no_known_variable(p, "MAT", tuple(k for k, _ in _MAT5_KEYS), names, _cube_like_arrays(p))


def _no_known_variable(p: Path, kind: str, known: Sequence[str], found: Sequence[str],
                       arrays: Sequence[tuple[str, tuple[int, ...]]] | None = None) -> InputError:
    """The refusal of a MAT/HDF5 file whose variables hold no cube under a name we know, saying what to do; ``arrays``:
    its arrays that may be the cube (:func:`_cube_like_arrays`), named in it."""
    shapes = ", ".join(f"'{name}' {'×'.join(map(str, shape))}" for name, shape in (arrays or ())[:SHOWN_ARRAYS])
    more = f" and {len(arrays) - SHOWN_ARRAYS} more" if arrays and len(arrays) > SHOWN_ARRAYS else ""
    may = "" if not arrays else (f"; {shapes} may be the cube" if len(arrays) == 1 else
                                 f"; {len(arrays)} arrays may be the cube, which is ambiguous: {shapes}{more}")
    return InputError(f"{p}: {kind} file with no known hyperspectral variable (expected one of {', '.join(known)}; "
                      f"found {', '.join(found) or 'none'}{may}): rename the cube's variable to one of these (with its "
                      "band list as 'bands', in nm), or rewrite it with hsicam.data.formats.write_cube_h5")


#: How many of a file's arrays that may be its cube a refusal names (:func:`_no_known_variable`).
SHOWN_ARRAYS = 3


# ------------------------------------------------------------------------------------------------
# MAT and HDF5 files that hold no cube (a dataset's meta.mat, a calibration .h5 of 2-D frames)
# ------------------------------------------------------------------------------------------------
#: MATLAB classes (scipy.io.whosmat) of arrays of numbers (not text, true/false values, sparse matrices).
_MAT5_NUMERIC = frozenset(("double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
                           "uint64"))
#: MATLAB classes whose contents a MAT v5 header does not show: loaded to be looked into.
_MAT5_CONTAINERS = ("struct", "cell", "object")
#: A MAT v5 file larger than this (bytes) whose structs or cell arrays would have to be loaded to be looked into is
#: taken to hold a cube: listing a dataset folder never loads a large file (its reader says what it holds).
PEEK_MAX_BYTES = 64 * 2**20


def cube_like(shape: Sequence[int] | None, dtype: Any) -> bool:
    """True for an array that may be a hyperspectral cube: real numbers (integers or floats; not text, true/false
    values or complex numbers) of 3 or more axes, at least 3 of them longer than 1 (two image axes and a band axis of
    2 or more bands: an image stored with a trailing axis of 1 is none)."""
    if shape is None or np.dtype(dtype).kind not in "iuf":
        return False
    return len(shape) >= 3 and sum(int(s) > 1 for s in shape) >= 3


def _cube_like_arrays(p: Path) -> list[tuple[str, tuple[int, ...]]] | None:
    """The arrays of the MAT (v5, v7.3) or HDF5 file ``p`` that may be a cube (:func:`cube_like`), as (name, shape as
    stored), told from its headers (inside MATLAB structs and cell arrays, HDF5 groups too: ``a/b``); None when that
    cannot be told: another format, a file that cannot be read (its reader says why), a MAT v5 file over
    :data:`PEEK_MAX_BYTES` whose structs would have to be loaded."""
    found = _variables(p)
    return None if found is None else found[1]


def _variables(p: Path) -> tuple[list[str], list[tuple[str, tuple[int, ...]]]] | None:
    """(the top-level variable names, the arrays that may be a cube) of the MAT or HDF5 file ``p``, or None
    (:func:`_cube_like_arrays`)."""
    try:
        head = _head(p, 128)
        if head.startswith(_HDF5_MAGIC) or head.startswith(b"MATLAB 7.3"):
            return _h5_variables(p)
        if head.startswith(b"MATLAB 5.0"):
            return _mat5_variables(p)
    except Exception:  # noqa: BLE001 - h5py and scipy raise many types; a file not told is its reader's to refuse
        return None
    return None


def _h5_variables(p: Path) -> tuple[list[str], list[tuple[str, tuple[int, ...]]]]:
    import h5py

    found: list[tuple[str, tuple[int, ...]]] = []

    def visit(name: str, obj: Any) -> None:
        matlab_class = obj.attrs.get("MATLAB_class") if isinstance(obj, h5py.Dataset) else None
        if isinstance(matlab_class, bytes):
            matlab_class = matlab_class.decode("ascii", "replace")
        if isinstance(obj, h5py.Dataset) and matlab_class not in ("char", "logical") and cube_like(obj.shape, obj.dtype):
            found.append((name, tuple(int(s) for s in obj.shape)))

    with h5py.File(p, "r") as f:
        names = sorted(f.keys())
        f.visititems(visit)  # every dataset, in groups (MATLAB structs) and #refs# (cell arrays) too
    return names, found


def _mat5_variables(p: Path) -> tuple[list[str], list[tuple[str, tuple[int, ...]]]] | None:
    import scipy.io

    info = scipy.io.whosmat(p)
    found = [(n, tuple(int(s) for s in shape)) for n, shape, cls in info
             if cls in _MAT5_NUMERIC and cube_like(shape, np.float64)]
    containers = [n for n, _, cls in info if cls in _MAT5_CONTAINERS]
    if containers and not found:
        if p.stat().st_size > PEEK_MAX_BYTES:
            return None
        loaded = scipy.io.loadmat(p, variable_names=containers)
        for n in containers:
            found += _arrays_inside(n, loaded[n])
    return [n for n, _, _ in info], found


def _arrays_inside(name: str, value: Any) -> list[tuple[str, tuple[int, ...]]]:
    """The arrays that may be a cube inside a MATLAB struct or cell array as scipy.io.loadmat returns it (``name``:
    ``s.field``, ``c{i}``)."""
    arr = np.asarray(value)
    if arr.dtype.names:  # a struct (array): its fields
        return [x for f in arr.dtype.names for item in arr[f].reshape(-1) for x in _arrays_inside(f"{name}.{f}", item)]
    if arr.dtype.kind == "O":  # a cell array (or an object's contents)
        return [x for i, item in enumerate(arr.reshape(-1)) for x in _arrays_inside(f"{name}{{{i + 1}}}", item)]
    return [(name, tuple(arr.shape))] if cube_like(arr.shape, arr.dtype) else []


#: Variable names under which the readers find a cube (MAT and HDF5; :func:`detect_format`).
CUBE_NAMES = tuple(dict.fromkeys(("cube", *(k for k, _ in (*_HDF5_KEYS, *_MAT5_KEYS)))))
#: (real path, size, mtime) -> :func:`holds_no_cube` of the files it has looked into in this process.
_NO_CUBE: dict[tuple[str, int, int], bool] = {}


def holds_no_cube(path: str | os.PathLike) -> bool:
    """True for a MAT (v5, v7.3) or HDF5 file that is not a cube file: no variable under a name the readers take a
    cube from (:data:`CUBE_NAMES`) and no array that may be a cube (:func:`cube_like`, looked for in its headers,
    structs and groups): a dataset's ``meta.mat`` of text and numbers, a calibration ``.h5`` of 2-D frames, a ``.mat``
    of labels. False for every other file, and for one that cannot be read or told (its reader then says why), so a
    dataset folder skips the first and refuses the others (:func:`hsicam.data.datasets.list_scenes`)."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return False
    key = (os.path.realpath(p), st.st_size, st.st_mtime_ns)
    if key not in _NO_CUBE:
        found = _variables(p) if p.is_file() else None
        _NO_CUBE[key] = found is not None and not found[1] and not set(CUBE_NAMES) & set(found[0])
    return _NO_CUBE[key]


# ------------------------------------------------------------------------------------------------
# Entry point
# ------------------------------------------------------------------------------------------------
def read_cube(path: str | os.PathLike, *, bands: Bands | None = None, allow_negative: bool = False,
              memory_budget_mb: float | None = None) -> Cube:
    """Read any supported cube: returns (cube float32 (C, H, W), Bands, metadata dict).

    ``bands`` is the band grid of a ``.npy`` file (it carries no wavelengths; the config's ``data.npy_bands``), and
    is not applied to any other format: those are read on their own band list, or, a MAT/HDF5 file without one, on
    the grid assumed for its format and band count (metadata ``assumed_grid``, said in a log line). With
    ``allow_negative=True`` negative values are clipped to 0 instead of being an error.
    ``memory_budget_mb`` overrides the memory budget (see the module docstring).
    """
    fmt = detect_format(path)
    reader = READERS[fmt]
    if fmt == "npy":
        return read_npy(path, bands=bands, allow_negative=allow_negative, memory_budget_mb=memory_budget_mb)
    return reader(path, allow_negative=allow_negative, memory_budget_mb=memory_budget_mb)


def _finish(p: Path, cube: np.ndarray, bands: Bands, meta: dict[str, Any], allow_negative: bool) -> Cube:
    if np.ndim(cube) == 3 and np.shape(cube)[0] != len(bands):
        hint = (f" (its last axis has {np.shape(cube)[-1]}: the band axis must come first, (bands, height, width); "
                "transpose the array)") if np.shape(cube)[-1] == len(bands) else ""
        raise InputError(f"{p}: the cube has {np.shape(cube)[0]} bands but the file lists {len(bands)} wavelengths{hint}")
    cube = check_cube(cube, p, bands=bands, allow_negative=allow_negative, negative_advice=NEGATIVE_READ_ADVICE)
    meta.setdefault("source", str(p))
    return cube, bands, meta


#: Band centres stored without a unit that all lie below this are micrometres, else nanometres
#: (30 µm is far infrared, 30 nm extreme ultraviolet: no hyperspectral camera's band is either).
MICROMETRE_BELOW = 30.0
#: ENVI ``wavelength units`` read as micrometres / nanometres (lower case; American and British spellings, the
#: micro sign U+00B5 and the Greek mu U+03BC); none or "unknown" means "look at the values", another unit is refused.
MICROMETRE_UNITS = ("micrometers", "micrometer", "micrometres", "micrometre", "microns", "micron", "um", "\u00b5m",
                    "\u03bcm")
NANOMETRE_UNITS = ("nanometers", "nanometer", "nanometres", "nanometre", "nm")


def _unitless_scale(p: Path, centres: np.ndarray, key: str) -> tuple[float, str | None]:
    """(factor to nm, note to log or None) for band centres ``centres`` that the file stores without
    a unit: 1000 when all lie below :data:`MICROMETRE_BELOW` (micrometres), else 1."""
    if centres.size and float(np.max(centres)) < MICROMETRE_BELOW:
        return 1000.0, f"{p}: {key} units not given and values < {MICROMETRE_BELOW:g}; reading them as micrometres"
    return 1.0, None


def _band_numbers(p: Path, values: Any, key: str) -> np.ndarray:
    """The values of the file's band list ``key`` as float64 (flattened); InputError unless numbers.

    A list stored in float32 (or float16) is taken at the decimal its writer meant, the shortest one
    that the stored number rounds to: float32 453.3 is 453.29998779… as float64, and 453.3 here."""
    arr = np.asarray(values)
    if arr.dtype.kind not in "iuf":
        raise InputError(f"{p}: '{key}' must be a list of numbers (nm), got {_describe_values(arr)}")
    if arr.dtype.kind == "f" and arr.dtype.itemsize < 8:
        return arr.reshape(-1).astype(str).astype(np.float64)  # numpy prints each at its own precision
    return arr.astype(np.float64).reshape(-1)


#: Decimals (of a nanometre) kept of the band centres (and widths) that a file lists: float32 0.7 µm is
#: 699.99998 nm after the conversion, and an ENVI header that prints float32 centres lists 719.99997 nm;
#: neither would cover a camera band at 700 or 720 nm. (Grids are compared to half of this,
#: :data:`hsicam.spectral.bands.BAND_TOL_NM`, so a grid of more decimals read back is the grid written.)
NM_DECIMALS = 3


def _um_to_nm(values: np.ndarray | float, scale: float = 1000.0) -> Any:
    """``values`` × ``scale`` (1000 for micrometres, 1 for nanometres) in nm, rounded to
    :data:`NM_DECIMALS` decimals (a float for a float, else an array)."""
    nm = np.round(np.asarray(values, dtype=np.float64) * scale, NM_DECIMALS)
    return float(nm) if np.ndim(values) == 0 else nm


def _ascending(p: Path, cube: np.ndarray, centres: np.ndarray, fwhm: np.ndarray | None, key: str,
               axis: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(cube, centres, fwhm) with the bands ascending: a strictly descending list is reversed, and the
    cube's band ``axis`` with it; a list in neither order is an InputError saying so."""
    if centres.size < 2 or not np.all(np.isfinite(centres)):
        return cube, centres, fwhm  # one band, or non-finite values (the Bands check names them)
    step = np.diff(centres)
    if np.all(step > 0):
        return cube, centres, fwhm
    if np.all(step < 0):
        flipped = np.flip(cube, axis) if cube.shape[axis] == centres.size else cube
        if any(flipped.strides):  # (a shape-only cube, :func:`_shape_only`, stays a view of no data)
            flipped = np.ascontiguousarray(flipped)
        return flipped, centres[::-1].copy(), None if fwhm is None else np.asarray(fwhm)[::-1].copy()
    if np.any(step == 0):
        same = centres[1:][step == 0][0]
        raise InputError(f"{p}: the band list '{key}' names {same:g} nm twice; each band needs its own wavelength")
    i = int(np.argmax(np.sign(step) != np.sign(step[0]))) + 1  # first centre that turns back
    raise InputError(f"{p}: the band list '{key}' is neither ascending nor descending (it turns at band {i + 1} of "
                     f"{centres.size}: {centres[i - 1]:g}, {centres[i]:g}{', …' if i + 1 < centres.size else ''} nm); "
                     "bands are read in either order, not shuffled")


def _describe_values(arr: np.ndarray) -> str:
    """A few words on a band list that holds no numbers (text, a cell array or struct, booleans …)."""
    items = arr.reshape(-1).tolist() if arr.dtype.kind in "SUO" else []
    if items and all(isinstance(x, (str, bytes)) for x in items):
        text = " ".join(x.decode("utf-8", "replace") if isinstance(x, bytes) else x for x in items)
        return f"the text {text[:40] + ('…' if len(text) > 40 else '')!r}"
    kinds = {"O": "a cell array or struct", "V": "a struct", "b": "true/false values", "c": "complex numbers"}
    return kinds.get(arr.dtype.kind, f"values of type {arr.dtype}")


def _bands_from(p: Path, values: Any, fwhm: Any = None, key: str = "bands") -> Bands:
    """Bands from the file's band centres ``values`` (and FWHM) in nm, already ascending (:func:`_ascending`);
    InputError naming ``p``."""
    c = _band_numbers(p, values, key)
    widths = None if fwhm is None else _band_numbers(p, fwhm, key.replace("bands", "fwhm"))
    try:
        return Bands.from_centers(c) if widths is None else Bands(c, widths)
    except InputError as exc:
        raise InputError(f"{p}: invalid band list: {exc}") from None


# ------------------------------------------------------------------------------------------------
# Our HDF5
# ------------------------------------------------------------------------------------------------
def read_hsicam_h5(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """Our HDF5: ``cube`` (C, H, W) float32, ``bands_nm`` (C,), optional ``fwhm_nm``, attributes."""
    import h5py

    p = _as_path(path)
    with _reading(p, "HDF5"):
        with h5py.File(p, "r") as f:
            for key in ("cube", "bands_nm"):
                if key not in f:
                    raise InputError(f"{p}: missing key '{key}' (not an hsicam cube file)")
                if not isinstance(f[key], h5py.Dataset):  # e.g. a group of that name
                    raise InputError(f"{p}: '{key}' is a {type(f[key]).__name__.lower()}, not an array "
                                     "(not an hsicam cube file)")
            check_format_version(p, f.attrs)
            cube = _checked_read(p, f["cube"], memory_budget_mb)
            cube, bands = _h5_bands(p, f, cube)
            meta = _read_attrs(f.attrs)
    meta["format"] = "hsicam"
    return _finish(p, cube, bands, meta, allow_negative)


def _h5_bands(p: Path, f: Any, cube: np.ndarray) -> tuple[np.ndarray, Bands]:
    """(cube, Bands) of our HDF5 file ``f``: ``bands_nm`` (and ``fwhm_nm``), a descending list reversed
    together with the cube's band axis (axis 0)."""
    centres = _band_numbers(p, f["bands_nm"][()], "bands_nm")
    fwhm = _band_numbers(p, f["fwhm_nm"][()], "fwhm_nm") if "fwhm_nm" in f else None
    cube, centres, fwhm = _ascending(p, cube, centres, fwhm, "bands_nm")
    return cube, _bands_from(p, centres, fwhm, "bands_nm")


def check_format_version(p: Path, attrs: Any) -> None:
    """InputError unless our HDF5 file's ``version`` attribute is one this code reads (1 to
    :data:`HSICAM_FORMAT_VERSION`: a newer one, or one below 1, which no hsicam wrote; a file without
    it predates the attribute and is read). Files of another tool's ``format`` attribute are not
    judged by their ``version``."""
    if "version" not in attrs or attrs.get("format", HSICAM_FORMAT) != HSICAM_FORMAT:
        return
    value = attrs["version"]
    value = value.item() if isinstance(value, np.generic) else value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
        raise InputError(f"{p}: unreadable hsicam cube format version {value!r} (expected an integer)")
    if int(value) > HSICAM_FORMAT_VERSION:
        raise InputError(f"{p}: hsicam cube format version {int(value)}, newer than this hsicam reads (version "
                         f"{HSICAM_FORMAT_VERSION} and older): upgrade hsicam to read it")
    if int(value) < 1:
        known = "1" if HSICAM_FORMAT_VERSION == 1 else f"1 to {HSICAM_FORMAT_VERSION}"
        raise InputError(f"{p}: unknown hsicam cube format version {int(value)} (versions start at 1; this hsicam "
                         f"reads version {known}): not a file that hsicam wrote, or a damaged one")


def _read_attrs(attrs: Any) -> dict[str, Any]:
    meta: dict[str, Any] = {}
    if "metadata_json" in attrs:
        raw = attrs["metadata_json"]
        raw = raw.decode() if isinstance(raw, bytes) else str(raw)
        try:
            loaded = json.loads(raw)
            if isinstance(loaded, dict):  # a score written as null (not finite) is NaN again, as older files' NaN
                meta.update(nan_for_null(loaded))
        except json.JSONDecodeError:
            log.warning("ignoring unreadable metadata_json attribute")
    for key in ("max_value", "version"):
        if key in attrs:
            meta.setdefault(f"file_{key}", attrs[key].item() if hasattr(attrs[key], "item") else attrs[key])
    return meta


def _cube_of_bands(p: Path, cube: Any, bands: Bands) -> np.ndarray:
    """``cube`` (C, H, W) checked (:func:`~hsicam.data.cube.check_cube`) for writing to ``p``, as float32; InputError
    unless it has one band per centre of ``bands``."""
    arr = check_cube(cube, p)
    if arr.shape[0] != len(bands):
        raise InputError(f"{p}: the cube has {arr.shape[0]} bands but {len(bands)} band centres were given")
    return arr


def write_cube_h5(path: str | os.PathLike, cube: np.ndarray, bands: Bands, metadata: dict[str, Any] | None = None) -> Path:
    """Write our HDF5 cube file atomically (byte-identical for identical inputs: no timestamps).

    ``cube`` (C, H, W) is stored contiguous float32 (so windows can be read cheaply); ``metadata``
    must be JSON-serialisable and is stored as the ``metadata_json`` attribute, strict JSON
    (:func:`hsicam.io.json_text`: a float that is not finite, NaN or ±inf, written as null). HDF5 writes through
    a Python file object, so a failed write (a full disk …) is a plain OSError: with HDF5's own file
    driver, a file it could not flush stayed open in the library and crashed the interpreter at exit.
    """
    import h5py

    p = Path(path)
    arr = _cube_of_bands(p, cube, bands)
    meta_json = json_text(metadata or {}, sort_keys=True)  # strict JSON: h5py + any JSON parser read it
    with atomic_path(p) as tmp, open(tmp, "w+b") as fh, h5py.File(fh, "w", libver=("earliest", "v110")) as f:
        f.create_dataset("cube", data=arr, track_times=False)
        f.create_dataset("bands_nm", data=np.asarray(bands.centers_nm, dtype=np.float64), track_times=False)
        f.create_dataset("fwhm_nm", data=np.asarray(bands.fwhm_nm, dtype=np.float64), track_times=False)
        f.attrs["format"] = HSICAM_FORMAT
        f.attrs["version"] = HSICAM_FORMAT_VERSION
        f.attrs["layout"] = "cube (bands, height, width), bands ascending, wavelengths in nm"
        f.attrs["max_value"] = float(arr.max())
        f.attrs["metadata_json"] = meta_json
    return p


# ------------------------------------------------------------------------------------------------
# MATLAB files (v5 via scipy, v7.3 via h5py)
# ------------------------------------------------------------------------------------------------
#: Variable names under which MAT and HDF5 files keep their band centres, in order of preference
#: (matched regardless of case). A file that holds one is read on it, whatever the cube's key.
BAND_LIST_NAMES = ("bands", "bands_nm", "wavelength", "wavelengths", "wavelength_nm", "wavelengths_nm",
                   "lambda", "lambdas", "wl", "wls", "wave", "waves", "wvl", "wvls")

# format -> cube keys, in order of preference
_MAT_KEYS: dict[str, tuple[str, ...]] = {
    "icvl": ("rad",),
    "arad": ("cube",),
    "kaist-mat": ("img", "img_expand", "HSI"),  # HSI: MST's KAIST_CVPR2021 release
    "harvard": ("ref",),
}

# format -> band counts of the grids assumed for a file without a band list (:func:`_assumed_grid`)
_ASSUMED_COUNTS: dict[str, tuple[int, ...]] = {"icvl": (31,), "arad": (31,), "kaist-mat": (28, 31), "harvard": (31,)}


def _assumed_grid(fmt: str, n: int) -> tuple[Bands, str]:
    """The grid that a ``fmt`` file of ``n`` bands (one of ``_ASSUMED_COUNTS[fmt]``) without a band
    list is read on, and its description."""
    if fmt == "harvard":
        return Bands.uniform(420.0, 720.0, 10.0), "Harvard's 31 bands, 420-720 nm in 10 nm steps"
    if fmt == "kaist-mat" and n == 28:
        return Bands.from_centers(MST_28_NM), "MST's 28 KAIST bands, 453.3-648.1 nm"
    if fmt == "kaist-mat":  # (31) MST-style files hold CAVE scenes too: they say nothing of which
        return Bands.uniform(400.0, 700.0, 10.0), ("31 bands, 400-700 nm in 10 nm steps (CAVE's grid; KAIST's own 31 "
                                                   "bands span 420-720 nm: a KAIST file needs its band list)")
    return Bands.uniform(400.0, 700.0, 10.0), "31 bands, 400-700 nm in 10 nm steps"


# MATLAB class (as scipy.io.whosmat reports it) -> numpy dtype; other classes count as 8 bytes per element
_MAT5_DTYPES = {"double": "f8", "single": "f4", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
                "int32": "i4", "uint32": "u4", "int64": "i8", "uint64": "u8", "logical": "u1"}


class _MatFile(NamedTuple):
    """What :func:`_load_mat` found in a MAT or HDF5 file."""

    key: str  # the cube's variable
    data: np.ndarray  # MATLAB's order (H, W, C) for a MAT file; as stored, C order, for a plain HDF5 file
    band_lists: dict[str, Any]  # band-list variables (:data:`BAND_LIST_NAMES`) as stored, in order of preference
    vectors: dict[str, int]  # the other variables that are vectors: name -> length
    version: str | None  # MAT version "5" or "7.3"; None for an HDF5 file that is not MATLAB's


def _band_list_names(names: Sequence[str]) -> list[str]:
    """The variables among ``names`` that are band lists, in the order of :data:`BAND_LIST_NAMES`."""
    return [n for want in BAND_LIST_NAMES for n in names if n.lower() == want]


def _vector_length(shape: Sequence[int]) -> int:
    """Length of a vector (one axis longer than 1, as MATLAB's 1×N), else 0."""
    long = [int(s) for s in shape if int(s) > 1]
    return long[0] if len(long) == 1 else 0


def _is_matlab_h5(head: bytes, f: Any) -> bool:
    """True for a MATLAB v7.3 MAT-file: its 512-byte user block starts with "MATLAB 7.3 MAT-file", or (a
    copy that lost it) a top-level variable carries MATLAB's ``MATLAB_class`` attribute. Other HDF5
    files (h5py's, NumPy order) are not MATLAB's column-major arrays."""
    return head.startswith(b"MATLAB 7.3") or any("MATLAB_class" in f[k].attrs for k in f.keys())


def _shape_only(shape: Sequence[int]) -> np.ndarray:
    """A read-only array of ``shape`` that holds no data (zero strides): what the band-axis and band-order logic
    reads of a cube whose values are not needed (:func:`read_bands`)."""
    return np.lib.stride_tricks.as_strided(np.zeros(1, np.float32), shape=tuple(int(s) for s in shape),
                                           strides=(0,) * len(shape), writeable=False)


def _load_mat(p: Path, keys: Sequence[str], budget_mb: float | None, read_data: bool = True) -> _MatFile:
    """The cube variable (the first of ``keys`` present), the band lists and the vector lengths of a
    MAT v5, MAT v7.3 or plain HDF5 file. ``read_data=False``: the cube's shape alone (:func:`_shape_only`)."""
    head = _head(p, 128)
    if head.startswith(_HDF5_MAGIC) or head.startswith(b"MATLAB 7.3"):
        import h5py

        with _reading(p, "MAT v7.3/HDF5"):
            with h5py.File(p, "r") as f:
                names = list(f.keys())
                key = next((k for k in keys if k in f), None)
                if key is None:
                    raise InputError(f"{p}: missing key {' or '.join(repr(k) for k in keys)} "
                                     f"(found: {', '.join(sorted(names)) or 'none'})")
                if not isinstance(f[key], h5py.Dataset):
                    raise InputError(f"{p}: '{key}' is not a numeric array")
                matlab = _is_matlab_h5(head, f)
                data = np.asarray(_checked_read(p, f[key], budget_mb)) if read_data else _shape_only(f[key].shape)
                if matlab:
                    data = data.T  # h5py returns MATLAB arrays with axes reversed
                band_lists = {}
                for name in _band_list_names(names):
                    if isinstance(f[name], h5py.Dataset):
                        check_memory_budget(p, f[name].shape, f[name].dtype, what=f"dataset '{name}'",
                                            budget_mb=budget_mb)
                    band_lists[name] = _h5_band_values(f[name])
                vectors = {n: _vector_length(f[n].shape) for n in names
                           if n != key and n not in band_lists and isinstance(f[n], h5py.Dataset)}
        return _MatFile(key, data, band_lists, {n: v for n, v in vectors.items() if v}, "7.3" if matlab else None)
    if head.startswith(b"MATLAB 5.0"):
        import scipy.io

        with _reading(p, "MAT v5"):
            info = {name: (shape, cls) for name, shape, cls in scipy.io.whosmat(p)}
            names = list(info)
            key = next((k for k in keys if k in names), None)
            if key is None:
                raise InputError(f"{p}: missing key {' or '.join(repr(k) for k in keys)} (found: {', '.join(names) or 'none'})")
            lists = _band_list_names(names)
            read = [key] * read_data + lists
            for name in read:
                shape, cls = info[name]
                check_memory_budget(p, shape, _MAT5_DTYPES.get(cls, "f8"), what=f"variable '{name}' ({cls})",
                                    budget_mb=budget_mb)
            loaded = scipy.io.loadmat(p, variable_names=read) if read else {}
            data = np.asarray(loaded[key]) if read_data else _shape_only(info[key][0])
            band_lists = {n: np.asarray(loaded[n]) for n in lists if n in loaded}
            vectors = {n: _vector_length(info[n][0]) for n in names if n != key and n not in lists}
        return _MatFile(key, data, band_lists, {n: v for n, v in vectors.items() if v}, "5")
    raise InputError(f"{p}: not a MAT file (no MATLAB 5.0 header and not HDF5/MAT v7.3)")


def _h5_band_values(obj: Any) -> np.ndarray:
    """The stored band list of a MAT v7.3 variable, as is (MATLAB text, uint16 character codes
    marked ``MATLAB_class = char``, comes back as that text; a struct or cell array as objects)."""
    import h5py

    if not isinstance(obj, h5py.Dataset):
        return np.array([None], dtype=object)
    values = np.asarray(obj[()])
    if obj.attrs.get("MATLAB_class") in (b"char", "char") and values.dtype.kind in "iu":
        return np.array("".join(map(chr, values.reshape(-1).tolist())))
    return values


def _grid_text(centres: np.ndarray) -> str:
    return f"{centres.size} values, {centres.min():g}-{centres.max():g} nm" if centres.size else "no values"


def _file_band_list(p: Path, band_lists: dict[str, Any]) -> tuple[np.ndarray | None, str | None, str | None]:
    """(band centres in nm as stored, their variable, a note on micrometres or None) from the file's
    band lists, or (None, None, None) without one. Several lists must agree."""
    parsed = []
    for name, values in band_lists.items():
        centres = _band_numbers(p, values, name)
        scale, note = _unitless_scale(p, centres, f"'{name}'")
        parsed.append((name, _um_to_nm(centres, scale), note))
    if not parsed:
        return None, None, None
    name, centres, note = parsed[0]
    for other, values, _ in parsed[1:]:
        if values.shape != centres.shape or not np.allclose(values, centres, rtol=0.0, atol=10.0 ** -NM_DECIMALS):
            raise InputError(f"{p}: the file holds two different band lists, '{name}' ({_grid_text(centres)}) and "
                             f"'{other}' ({_grid_text(values)}); keep the one that belongs to the cube")
    return centres, name, note


def _band_axis_first(p: Path, m: _MatFile, counts: Sequence[int], matched: str,
                     unmatched: str) -> tuple[np.ndarray, str | None]:
    """``m.data`` as (C, H, W), C one of ``counts`` (the band list's length, or the assumed grids'),
    and a note on the axis order of a plain HDF5 file. A MAT file holds H×W×C; a plain HDF5 file
    (C order) holds (C, H, W) or (H, W, C), told by which of its first and last axes has C.
    ``matched`` names what the count comes from, ``unmatched`` ends the refusal of a cube without it."""
    data, key = m.data, m.key
    if data.ndim != 3:
        axes = "height, width, bands" if m.version else "bands, height, width"
        raise InputError(f"{p}: '{key}' must be a 3-D array ({axes}), got {data.ndim} dimensions {data.shape}")
    dims = "×".join(str(s) for s in data.shape)
    first, last = data.shape[0] in counts, data.shape[2] in counts
    if m.version is not None:  # MATLAB: H×W×C
        if last:
            return np.transpose(data, (2, 0, 1)), None
        if first:
            raise InputError(f"{p}: '{key}' is {dims}, its first axis matching {matched}: its axes look like (C, H, W), "
                             "as NumPy's (bands, height, width) array saved by scipy.io.savemat, but a MATLAB file holds "
                             "H×W×C (bands last): save np.transpose(cube, (1, 2, 0)), or write the cube with "
                             "hsicam.data.formats.write_cube_h5")
        raise InputError(f"{p}: the cube has {data.shape[2]} bands (the last axis of '{key}', {dims}, MATLAB's H×W×C) "
                         f"{unmatched}")
    if first and last:
        raise InputError(f"{p}: HDF5 file without a MATLAB 7.3 header, read in C order, but '{key}' ({dims}) has "
                         f"{data.shape[0]} on both its first and last axes, matching {matched}: cannot tell whether "
                         "it is stored (C, H, W) or (H, W, C); write it with hsicam.data.formats.write_cube_h5 "
                         "(bands, height, width) or as a MATLAB v7.3 file (H×W×C)")
    if first or last:
        order = "(C, H, W)" if first else "(H, W, C)"
        note = (f"{p}: HDF5 file without a MATLAB 7.3 header: '{key}' ({dims}) read in C order (as h5py and NumPy "
                f"write it) as {order}, its {'first' if first else 'last'} axis matching {matched}")
        return (data if first else np.transpose(data, (2, 0, 1))), note
    raise InputError(f"{p}: '{key}' is {dims} (an HDF5 file without a MATLAB 7.3 header: (C, H, W) or (H, W, C) in "
                     f"C order), and neither its first nor its last axis has the bands {unmatched}")


def _read_mat_format(path: str | os.PathLike, fmt: str, allow_negative: bool, budget_mb: float | None) -> Cube:
    p = _as_path(path)
    m = _load_mat(p, _MAT_KEYS[fmt], budget_mb)
    cube, bands, list_key, assumed, notes = _mat_cube_bands(p, fmt, m)
    meta: dict[str, Any] = {"format": fmt, "key": m.key, "bands_key": list_key, "assumed_grid": assumed}
    if m.version is None:
        meta["container"] = "HDF5"
    else:
        meta["mat_version"] = m.version
    return _finished_noting(notes, _finish(p, cube, bands, meta, allow_negative))


def _mat_cube_bands(p: Path, fmt: str, m: _MatFile
                    ) -> tuple[np.ndarray, Bands, str | None, str | None, list[tuple[int, str]]]:
    """(cube (C, H, W) ascending, its Bands, the band list's variable or None, the assumed grid's description or
    None, notes to log) of the MAT or HDF5 file ``p`` of format ``fmt`` that :func:`_load_mat` read as ``m``."""
    centres, list_key, um_note = _file_band_list(p, m.band_lists)
    notes: list[tuple[int, str]] = [(logging.WARNING, um_note)] if um_note else []
    assumed = None
    if centres is not None:  # the file's own band list, whatever the cube's key
        n = centres.size
        cube, order = _band_axis_first(p, m, (n,), f"the {n} wavelengths of '{list_key}'",
                                       f"but the file lists {n} wavelengths ('{list_key}')")
        cube, centres, _ = _ascending(p, cube, centres, None, list_key)
        bands = _bands_from(p, centres, key=list_key)
    else:
        names = ", ".join(BAND_LIST_NAMES[:3]) + " …"
        counts = _ASSUMED_COUNTS[fmt]
        grids = "; ".join(_assumed_grid(fmt, c)[1] for c in counts)
        matched = f"the grid assumed without a band list ({grids})"
        unmatched = (f"and the file lists no wavelengths (no variable {names}), so it is read only on {grids}: "
                     "add its wavelengths as a variable 'bands' (nm)")
        cube, order = _band_axis_first(p, m, counts, matched, unmatched)
        bands, assumed = _assumed_grid(fmt, cube.shape[0])
        text = f"{p}: the file lists no wavelengths (no variable {names}); assuming {assumed}"
        hints = [n for n, length in m.vectors.items() if length == cube.shape[0] and "fwhm" not in n.lower()]
        level = logging.WARNING if (fmt, cube.shape[0]) == ("kaist-mat", 31) else logging.INFO  # a 20 nm guess
        if hints:  # a vector of the band count under another name may be the wavelengths
            level, text = logging.WARNING, f"{text}; if '{hints[0]}' holds the wavelengths, name it 'bands'"
        notes.append((level, text))
    if order:
        notes.append((logging.INFO, order))
    return cube, bands, list_key, assumed, notes


def assumed_bands_note(meta: dict[str, Any]) -> str | None:
    """Words for a refusal of a cube's band range saying that its grid was assumed (the file lists no
    wavelengths: metadata ``assumed_grid``), or None when the file gave its bands."""
    grid = meta.get("assumed_grid")
    if not grid:
        return None
    if meta.get("format") == "npy":
        return f"the file carries no wavelengths, so its bands were taken as {grid}"
    return (f"the file lists no wavelengths, so its bands were assumed to be {grid}; add its band list as a "
            "variable 'bands' (nm)")


#: INFO notes already logged by this process (one line per file, not one per re-read of a cached scene).
_NOTED: set[str] = set()


def _finished_noting(notes: str | None | Sequence[tuple[int, str]], result: Cube) -> Cube:
    """``result``, after logging ``notes`` (a warning, or (level, text) pairs; each text, which names its file, once
    per process: a dataset reads its scenes again and again, and a tolerance study printed one file's warning 38
    times) once the file was read without error: an error stays the one line the user sees."""
    for level, text in ([(logging.WARNING, notes)] if isinstance(notes, str) else notes or ()):
        if text in _NOTED:
            continue
        _NOTED.add(text)
        log.log(level, "%s", text)
    return result


def read_icvl(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """ICVL ``.mat`` v7.3: ``rad`` (H×W×C in MATLAB, reversed by h5py) and ``bands`` (nm)."""
    return _read_mat_format(path, "icvl", allow_negative, memory_budget_mb)


def read_arad(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """ARAD / NTIRE ``.mat`` v7.3: ``cube`` (H×W×C in MATLAB, reversed by h5py) and ``bands`` (nm); also
    a plain HDF5 file (h5py's) with ``cube`` (C, H, W) or (H, W, C) and a band list."""
    return _read_mat_format(path, "arad", allow_negative, memory_budget_mb)


def read_kaist_mat(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """MST-style KAIST/CAVE ``.mat``: ``img`` or ``img_expand`` H×W×C (28 bands: MST's grid)."""
    return _read_mat_format(path, "kaist-mat", allow_negative, memory_budget_mb)


def read_harvard(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """Harvard ``.mat``: ``ref`` H×W×31, 420-720 nm in 10 nm steps (the file's band list if it has one)."""
    return _read_mat_format(path, "harvard", allow_negative, memory_budget_mb)


# ------------------------------------------------------------------------------------------------
# OpenEXR (KAIST)
# ------------------------------------------------------------------------------------------------
_EXR_NUM = re.compile(r"(\d+(?:[.,]\d+)?)\s*(nm|um|µm)?\s*$", re.IGNORECASE)
#: A channel named by its band's edges, ``415-425nm`` (spectral EXR writers such as RenderToolbox3's):
#: the band's centre is their mean (read as the upper edge, every band would be off by half its width).
_EXR_RANGE = re.compile(r"(\d+(?:[.,]\d+)?)\s*(?:nm|um|µm)?\s*-\s*(\d+(?:[.,]\d+)?)\s*(nm|um|µm)?\s*$", re.IGNORECASE)


def exr_channel_wavelength(name: str, bare_micrometres: bool = False) -> float | None:
    """Wavelength in nm encoded in an EXR channel name, or None for a non-spectral channel.

    Accepts ``550``, ``550nm``, ``w550nm``, ``550.5nm``, ``0.55um``, the spectral-EXR names
    ``S0.550,000nm`` (emissive) / ``T.550nm`` (reflective), and a band's edges ``545-555nm`` (its
    centre, 550); polarisation components S1-S3 are not spectral bands. A number without a unit is
    in nm, or in µm with ``bare_micrometres`` (:func:`exr_bare_micrometres` decides it for a whole file).
    """
    if re.match(r"^S[123]\.", name):
        return None
    stem = re.sub(r"^(S0|T)\.", "", name)
    r = _EXR_RANGE.search(stem)
    if r is not None and float(r.group(2).replace(",", ".")) > float(r.group(1).replace(",", ".")):
        value = (float(r.group(1).replace(",", ".")) + float(r.group(2).replace(",", "."))) / 2
        unit = (r.group(3) or "").lower()
    else:
        m = _EXR_NUM.search(stem)
        if m is None:
            return None
        value = float(m.group(1).replace(",", "."))
        unit = (m.group(2) or "").lower()
    if unit in ("um", "µm") or (not unit and bare_micrometres):
        value = float(_um_to_nm(value))
    return value if 200.0 <= value <= 2600.0 else None


def exr_bare_micrometres(names) -> bool:
    """True when the channels named by a number alone (no unit, e.g. ``0.55``) are all wavelengths
    in µm (0.2-2.6): as nm they would all be dropped as below 200 nm. Band numbers (``0`` … ``30``)
    are not all in that range, so they stay non-spectral."""
    bare = [float(m.group(1).replace(",", ".")) for n in names
            if not re.match(r"^S[123]\.", n) and (m := re.fullmatch(r"\s*(\d+(?:[.,]\d+)?)\s*", re.sub(r"^(S0|T)\.", "", n)))]
    return bool(bare) and all(0.2 <= v <= 2.6 for v in bare)


def _openexr(p: Path) -> Any:
    """The ``OpenEXR`` module (openexr >= 3.3, the optional ``exr`` extra); InputError naming ``p`` without it."""
    try:
        import OpenEXR
    except ImportError:
        raise InputError(f"{p}: reading OpenEXR needs the 'openexr' package (pip install 'hsicam[exr]')") from None
    if not hasattr(OpenEXR, "File"):
        raise InputError(f"{p}: reading OpenEXR needs openexr >= 3.3 (the OpenEXR.File API)")
    return OpenEXR


def read_kaist_exr(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """KAIST OpenEXR: one channel per band, the wavelength in each channel's name."""
    p = _as_path(path)
    OpenEXR = _openexr(p)
    with _reading(p, "OpenEXR"):
        with OpenEXR.File(str(p), header_only=True) as f:  # the header dict is only valid while open
            header = f.header()
            (x0, y0), (x1, y1) = (np.asarray(v, dtype=np.int64).tolist() for v in header["dataWindow"])
            n_channels = len(header.get("channels", ())) or 1
        # every channel is read (4 bytes a sample at most) before the spectral ones are picked
        check_memory_budget(p, (n_channels, int(y1) - int(y0) + 1, int(x1) - int(x0) + 1), "f4",
                            what="OpenEXR image", budget_mb=memory_budget_mb)
        with OpenEXR.File(str(p), separate_channels=True) as f:
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    spectral = _exr_spectral_channels(p, list(channels), note=True)
    waves = [w for w, _ in spectral]
    shapes = {channels[n].shape for _, n in spectral}
    if len(shapes) != 1:
        raise InputError(f"{p}: EXR spectral channels have different sizes {sorted(shapes)}")
    cube = np.stack([channels[n].astype(np.float32) for _, n in spectral])
    meta = {"format": "kaist-exr", "channels": [n for _, n in spectral]}
    return _finish(p, cube, Bands.from_centers(waves), meta, allow_negative)


def _exr_spectral_channels(p: Path, names: Sequence[str], note: bool = False) -> list[tuple[float, str]]:
    """(wavelength nm, channel name) of the EXR channels ``names`` that carry a wavelength, ascending; InputError
    when none does or two name the same one. ``note``: log that bare numbers were read as micrometres."""
    micrometres = exr_bare_micrometres(names)
    if micrometres and note:
        log.info("%s: EXR channel names carry no unit and lie within 0.2-2.6; reading them as micrometres", p)
    spectral = [(exr_channel_wavelength(n, micrometres), n) for n in names]
    spectral = sorted((w, n) for w, n in spectral if w is not None)
    if not spectral:
        raise InputError(f"{p}: no EXR channel name carries a wavelength (channels: {', '.join(sorted(names))})")
    waves = [w for w, _ in spectral]
    if len(set(waves)) != len(waves):
        raise InputError(f"{p}: two EXR channels name the same wavelength")
    return spectral


# ------------------------------------------------------------------------------------------------
# CAVE
# ------------------------------------------------------------------------------------------------
def _find_cave_pngs(folder: Path) -> list[Path] | None:
    """The 31 band PNGs of the CAVE scene in ``folder`` (or one/two levels down), or None."""
    groups: dict[tuple[Path, str], dict[int, Path]] = {}
    candidates = list(folder.glob("*")) + list(folder.glob("*/*")) + list(folder.glob("*/*/*"))
    for f in candidates:
        m = _CAVE_RE.match(f.name)
        if m and f.is_file() and not f.name.startswith("."):
            groups.setdefault((f.parent, m.group("prefix")), {})[int(m.group("index"))] = f
    if not groups:
        return None
    if len(groups) > 1:
        names = ", ".join(sorted(f"{d.name}/{prefix}" for d, prefix in groups))
        raise InputError(f"{folder}: holds several CAVE scenes ({names}); pass one scene folder")
    (_, files), = groups.items()
    missing = [i for i in range(1, 32) if i not in files]
    if missing:
        raise InputError(f"{folder}: CAVE scene is missing band image(s) {', '.join(f'{i:02d}' for i in missing)}")
    extra = sorted(i for i in files if not 1 <= i <= 31)
    if extra:
        raise InputError(f"{folder}: CAVE scene has unexpected band index(es) {extra} (expected 01..31)")
    return [files[i] for i in range(1, 32)]


def _png_header(f: Path) -> tuple[int, int, int]:
    """(height, width, samples per pixel) from a PNG's IHDR chunk, without decoding the image."""
    head = _head(f, 33)
    if not head.startswith(_PNG_MAGIC) or head[12:16] != b"IHDR" or len(head) < 26:
        raise InputError(f"{f}: not a PNG file (no PNG signature and IHDR header)")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    samples = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(head[25], 4)
    return height, width, samples


def read_cave(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """CAVE: a folder of 31 PNGs ``<name>_ms_01.png`` … ``_31.png`` (400-700 nm, 10 nm), 16-bit.

    Values are divided by the integer full scale (65535 for 16-bit, 255 for 8-bit images); a PNG
    stored with colour channels (one CAVE scene has them) contributes its first channel.
    """
    import imageio.v3 as iio

    p = _as_path(path)
    if not p.is_dir():
        raise InputError(f"{p}: a CAVE scene is a folder of 31 PNGs")
    files = _find_cave_pngs(p)
    if files is None:
        raise InputError(f"{p}: no CAVE band images '*_ms_01.png' … '*_ms_31.png' found")
    sizes = [_png_header(f) for f in files]
    h_max, w_max = max(s[0] for s in sizes), max(s[1] for s in sizes)
    check_memory_budget(p, (len(files), h_max, w_max), "f4", what="CAVE scene (31 PNG band images)",
                        budget_mb=memory_budget_mb)
    planes = []
    for f in files:
        with _reading(f, "PNG"):
            img = np.asarray(iio.imread(f))
        if img.ndim == 3:
            log.warning("%s: colour PNG in a CAVE scene; using its first channel", f)
            img = img[..., 0]
        if img.ndim != 2:
            raise InputError(f"{f}: expected a 2-D band image, got shape {img.shape}")
        if img.dtype.kind not in "ui":
            raise InputError(f"{f}: expected an integer PNG, got {img.dtype}")
        full = float(np.iinfo(img.dtype).max)
        planes.append(img.astype(np.float32) / np.float32(full))
    if len({pl.shape for pl in planes}) != 1:
        raise InputError(f"{p}: CAVE band images have different sizes")
    cube = np.stack(planes)
    meta = {"format": "cave", "scene": files[0].name.rsplit("_ms_", 1)[0], "files": [f.name for f in files]}
    return _finish(p, cube, Bands.uniform(400.0, 700.0, 10.0), meta, allow_negative)


# ------------------------------------------------------------------------------------------------
# ENVI
# ------------------------------------------------------------------------------------------------
def parse_envi_header(path: str | os.PathLike) -> dict[str, str]:
    """Parse an ENVI ``.hdr`` into {lower-case key: raw value string} (braced values joined)."""
    p = _as_path(path)
    with _reading(p, "ENVI header"):
        raw = p.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:  # a header saved in Latin-1 (e.g. 'wavelength units = µm' by older Windows tools)
        text = raw.decode("latin-1")
    lines = text.splitlines()
    if not lines or not lines[0].strip().startswith("ENVI"):
        raise InputError(f"{p}: not an ENVI header (first line must be 'ENVI')")
    out: dict[str, str] = {}
    i = 1
    while i < len(lines):
        line = lines[i]
        i += 1
        if not line.strip() or line.lstrip().startswith(";"):
            continue
        if "=" not in line:
            raise InputError(f"{p}: malformed ENVI header line {i}: {line.strip()!r}")
        key, _, value = line.partition("=")
        value = value.strip()
        if value.startswith("{"):
            while "}" not in value:
                if i >= len(lines):
                    raise InputError(f"{p}: ENVI header value of '{key.strip()}' has no closing brace")
                value += " " + lines[i].strip()
                i += 1
        out[key.strip().lower()] = value
    return out


def _envi_list(value: str) -> list[str]:
    value = value.strip()
    if value.startswith("{") and value.endswith("}"):
        value = value[1:-1]
    return [v.strip() for v in value.split(",") if v.strip()]


def _envi_floats(hdr: Path, h: dict[str, str], key: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in _envi_list(h[key])], dtype=np.float64)
    except ValueError:
        raise InputError(f"{hdr}: ENVI header key '{key}' must be a list of numbers") from None


def _envi_scale_factor(hdr: Path, h: dict[str, str]) -> float:
    """The header's ``reflectance scale factor``: InputError unless one positive number (ENVI defines
    one for the whole file; a list of equal values is taken as that value, unequal ones are refused
    rather than applying the first to every band)."""
    values = _envi_floats(hdr, h, "reflectance scale factor")
    if not values.size:
        raise InputError(f"{hdr}: ENVI header key 'reflectance scale factor' is empty (give the number the data "
                         "were multiplied by, or remove the key)")
    if values.size > 1 and not np.all(values == values[0]):
        raise InputError(f"{hdr}: ENVI header key 'reflectance scale factor' holds {values.size} different values "
                         f"({values.min():g} to {values.max():g}); ENVI defines one factor for the whole file: give "
                         "one, or divide each band by its own factor before reading")
    if not (math.isfinite(values[0]) and values[0] > 0):
        raise InputError(f"{hdr}: ENVI header key 'reflectance scale factor' must be a positive number, got "
                         f"{values[0]:g} (the data are divided by it)")
    return float(values[0])


def _envi_header_for(p: Path) -> Path | None:
    for cand in (p.with_name(p.name + ".hdr"), p.with_suffix(".hdr"), p.with_suffix(".HDR")):
        if cand != p and cand.is_file() and _is_envi_header(cand):
            return cand
    return None


def envi_data_file(hdr: str | os.PathLike) -> Path | None:
    """The raw data file next to the ENVI header ``hdr`` (same name without ``.hdr``, or with one of
    the usual data suffixes: ``.img``, ``.dat``, ``.raw``, …), or None when there is none."""
    hdr = Path(hdr)
    base = hdr.with_suffix("")
    for suffix in _ENVI_DATA_SUFFIXES:
        cand = base.with_name(base.name + suffix)
        if cand != hdr and cand.is_file():
            return cand
    # the usual suffixes in any case (.Img, .Raw: what another tool, or a --out of that case, named the file)
    wanted = {s.lower() for s in _ENVI_DATA_SUFFIXES if s}
    for cand in sorted(hdr.parent.glob(glob.escape(base.name) + ".*")):
        if cand != hdr and cand.stem == base.name and cand.suffix.lower() in wanted and cand.is_file():
            return cand
    return None


def read_envi(path: str | os.PathLike, *, allow_negative: bool = False, memory_budget_mb: float | None = None) -> Cube:
    """ENVI: ``path`` is the ``.hdr`` or the raw data file next to it.

    Supports interleave bsq/bil/bip, data types 1-5 and 12-15, byte order, header offset,
    ``wavelength`` (nm or µm via ``wavelength units``), ``fwhm``, ``data gain values`` and
    ``data offset values`` (one per band: value = gain · stored value + offset, applied after the
    no-data mask, said in one log line and recorded in the metadata: ``data_gain_offset_applied``,
    ``data_gain_values``, ``data_offset_values`` per band returned; a list of another length is
    refused) and ``reflectance scale factor`` (divides the values, after gains and offsets).
    ``bbl`` (bad band list): bands marked 0 are dropped with their wavelengths, so resampling
    bridges them with the linear interpolant (fewer than 2 good bands left: refused). ``data ignore value``
    (no-data, in the file's units): every value that holds it is set to 0 (a value, not its whole
    pixel: with an ignore value of 0, common, a dark band of a real pixel must not blank the others;
    every value no-data: refused). Both are said in one log line and recorded in the metadata
    (``bad_bands_nm``; ``data_ignore_value``, ``ignored_pixels``).
    """
    hdr, data = _envi_pair(_as_path(path))
    h = parse_envi_header(hdr)
    layout = _envi_layout(hdr, h)
    gains = _envi_per_band(hdr, h, "data gain values", layout.nbands)
    offsets = _envi_per_band(hdr, h, "data offset values", layout.nbands)
    raw = _envi_raw(hdr, data, h, layout, memory_budget_mb)
    good = _envi_good_bands(hdr, h, layout.nbands)
    stored = _envi_chw(raw, layout.interleave, good)  # the bad bands' values are never looked at
    ignore = _envi_ignore_value(hdr, h)
    nodata = _envi_nodata(stored, ignore) if ignore is not None else None
    cube = stored.astype(np.float32)
    notes: list[tuple[int, str]] = []
    n_nodata = _envi_blank_nodata(hdr, data, cube, nodata, ignore, notes)
    _envi_check_byte_order(hdr, data, raw, cube, layout, good, nodata)
    scaling = _envi_apply_gain_offset(hdr, data, cube, gains, offsets, good, nodata, notes)
    if "reflectance scale factor" in h:
        cube /= np.float32(_envi_scale_factor(hdr, h))
    waves, fwhm, note = _envi_wavelengths(hdr, h, layout.nbands)
    waves, fwhm, dropped = _envi_drop_bad_bands(hdr, data, waves, fwhm, good, notes)
    cube, waves, fwhm, scaling = _envi_ascending(cube, waves, fwhm, scaling)
    bands = _bands_from(hdr, waves, fwhm)
    meta = _envi_meta(hdr, data, h, layout, dropped, ignore, n_nodata, scaling)
    if note:
        notes.insert(0, (logging.WARNING, note))
    return _finished_noting(notes, _finish(data, cube, bands, meta, allow_negative))


def _is_envi_header(p: Path) -> bool:
    """Whether the file ``p`` starts as an ENVI header does (``ENVI``, after any white space)."""
    return _head(p, 64).lstrip().startswith(b"ENVI")


def _envi_pair(p: Path) -> tuple[Path, Path]:
    """(header, data file) of the ENVI pair that ``p`` (either of them) belongs to; InputError when the other
    one is not there."""
    if _is_envi_header(p):
        hdr, data = p, envi_data_file(p)
        if data is None:
            raise InputError(f"{p}: ENVI data file not found next to the header (tried {hdr.with_suffix('').name}"
                             f"{{{','.join(s for s in _ENVI_DATA_SUFFIXES if s)}}})")
    else:
        hdr, data = _envi_header_for(p), p
        if hdr is None:
            raise InputError(f"{p}: no ENVI header (.hdr) next to this file")
    return hdr, data


class _EnviLayout(NamedTuple):
    """How an ENVI header says its data file is laid out (:func:`_envi_layout`)."""

    samples: int  # width W, pixels
    lines: int  # height H, pixels
    nbands: int  # bands C
    dtype_code: int  # ENVI data type (a key of _ENVI_DTYPES)
    order: int  # byte order: 0 little-endian, 1 big-endian
    dtype: np.dtype  # the stored values' type, in that byte order
    offset: int  # header offset: bytes before the data
    interleave: str  # bsq (C, H, W), bil (H, C, W) or bip (H, W, C) on disk

    @property
    def disk_shape(self) -> tuple[int, int, int]:
        """The shape of the stored array, in the file's interleave order."""
        c, h, w = self.nbands, self.lines, self.samples
        return {"bsq": (c, h, w), "bil": (h, c, w), "bip": (h, w, c)}[self.interleave]


def _envi_int(hdr: Path, h: dict[str, str], key: str) -> int:
    """The header's integer ``key``; InputError when it is missing or not an integer."""
    if key not in h:
        raise InputError(f"{hdr}: ENVI header is missing key '{key}'")
    try:
        return int(h[key].strip())
    except ValueError:
        raise InputError(f"{hdr}: ENVI header key '{key}' is not an integer: {h[key]!r}") from None


def _envi_layout(hdr: Path, h: dict[str, str]) -> _EnviLayout:
    """The data layout the header ``h`` declares: its required keys, header offset, data type, byte order and
    interleave checked, in that order (one InputError for the first that is wrong)."""
    samples, lines = _envi_int(hdr, h, "samples"), _envi_int(hdr, h, "lines")
    nbands, dtype_code = _envi_int(hdr, h, "bands"), _envi_int(hdr, h, "data type")
    offset = _envi_int(hdr, h, "header offset") if "header offset" in h else 0
    if offset < 0:
        raise InputError(f"{hdr}: ENVI header offset must be >= 0 bytes, got {offset}")
    if dtype_code not in _ENVI_DTYPES:
        raise InputError(f"{hdr}: unsupported ENVI data type {dtype_code} (supported: {sorted(_ENVI_DTYPES)})")
    order = _envi_int(hdr, h, "byte order") if "byte order" in h else 0
    if order not in (0, 1):
        raise InputError(f"{hdr}: ENVI byte order must be 0 or 1, got {order}")
    dtype = np.dtype(_ENVI_DTYPES[dtype_code]).newbyteorder(">" if order == 1 else "<")
    interleave = h.get("interleave", "bsq").strip().lower()
    if "interleave" not in h and nbands > 1 and samples * lines > 1:  # (one band or one pixel: every order is one)
        text = (f"{hdr}: the header has no 'interleave'; reading the data as bsq (band after band, ENVI's and GDAL's "
                "default): if the images look scrambled, add 'interleave = bil' or 'interleave = bip'")
        if text not in _NOTED:  # once per file: a dataset reads its scenes again and again
            _NOTED.add(text)
            log.warning("%s", text)
    if interleave not in _ENVI_INTERLEAVES:
        raise InputError(f"{hdr}: unknown ENVI interleave {interleave!r} (expected bsq, bil or bip)")
    if min(samples, lines, nbands) <= 0:
        raise InputError(f"{hdr}: ENVI dimensions must be positive (samples={samples}, lines={lines}, bands={nbands})")
    return _EnviLayout(samples, lines, nbands, dtype_code, order, dtype, offset, interleave)


def _envi_raw(hdr: Path, data: Path, h: dict[str, str], layout: _EnviLayout, budget_mb: float | None) -> np.ndarray:
    """The stored values of ``data`` (``layout.disk_shape``, the file's dtype and byte order), read after the
    declared size was checked against the memory budget and the file's size, and checked against the CRC-32 that
    the header of a pair hsicam wrote records."""
    c, h_px, w = layout.nbands, layout.lines, layout.samples
    check_memory_budget(hdr, (c, h_px, w), layout.dtype, what="ENVI cube", budget_mb=budget_mb)
    count = w * h_px * c
    expected = layout.offset + count * layout.dtype.itemsize
    size = data.stat().st_size
    if size < expected:
        raise InputError(f"{data}: truncated ENVI data: {size} bytes, the header needs {expected}")
    if size > expected:  # e.g. the data of another (larger) cube beside this header
        text = (f"{data}: {size} bytes of ENVI data, but {hdr.name} describes {expected} ({h_px}×{w}×"
                f"{c} {layout.dtype.name})")
        if ENVI_CRC_KEY in h:  # a pair hsicam wrote: its data file is exactly what the header describes
            raise InputError(f"{text}: the header and the data do not belong together")
        log.warning("%s; reading the first %d (other software may pad its files)", text, expected)
    with _reading(data, "ENVI data"):
        raw = np.fromfile(data, dtype=layout.dtype, count=count, offset=layout.offset).reshape(layout.disk_shape)
    if ENVI_CRC_KEY in h:  # written by hsicam: the data must be the one the header was written for
        want, got = h[ENVI_CRC_KEY].strip().lower(), f"{zlib.crc32(memoryview(raw).cast('B')):08x}"
        if want != got:
            raise InputError(f"{data}: not the data {hdr.name} was written for (CRC-32 {got}, the header records {want}): "
                             "an interrupted write left a new data file beside an old header (write the cube again), "
                             f"or the data were edited since (to keep them, remove the '{ENVI_CRC_KEY}' line from "
                             f"{hdr.name})")
    return raw


def _envi_chw(raw: np.ndarray, interleave: str, good: np.ndarray | None) -> np.ndarray:
    """The stored array ``raw`` (in ``interleave`` order) as (C, H, W): a view, or a copy of the ``good`` bands
    only (a mask of the file's C bands) when given."""
    cube = {"bsq": raw, "bil": raw.transpose(1, 0, 2), "bip": raw.transpose(2, 0, 1)}[interleave]
    return cube[good] if good is not None else cube


def _envi_blank_nodata(hdr: Path, data: Path, cube: np.ndarray, nodata: np.ndarray | None, ignore: float | None,
                       notes: list[tuple[int, str]]) -> int | None:
    """Set the no-data values of ``cube`` (float32 (C, H, W); ``nodata`` its mask of the values that hold the data
    ignore value ``ignore``) to 0 in place, with a note; returns how many pixels hold at least one (None without
    a data ignore value). InputError when every value is no-data."""
    if nodata is None:
        return None
    n_values = int(np.count_nonzero(nodata))
    n_nodata = int(np.count_nonzero(nodata.any(axis=0)))  # pixels with at least one no-data value
    if n_values == nodata.size:
        raise InputError(f"{data}: every value ({n_values}) is the data ignore value {ignore:g} of {hdr.name}: "
                         "no data to read")
    if n_values:
        cube[nodata] = 0.0
        notes.append((logging.INFO, f"{data}: {n_nodata} of {nodata[0].size} pixels hold the data ignore value "
                                    f"{ignore:g} of {hdr.name} (no data; {n_values} values): those values set "
                                    "to 0"))
    return n_nodata


def _envi_check_byte_order(hdr: Path, data: Path, raw: np.ndarray, cube: np.ndarray, layout: _EnviLayout,
                           good: np.ndarray | None, nodata: np.ndarray | None) -> None:
    """InputError when the float ``cube`` (C, H, W) holds NaN/Inf values (other than no-data) and the same
    bytes ``raw`` read in the other byte order hold none: the header's byte order is wrong."""
    if not (layout.dtype.kind == "f" and layout.dtype.itemsize > 1 and not np.isfinite(cube).all()):
        return
    other = raw.view(raw.dtype.newbyteorder())  # the same bytes read the other way round
    other = _envi_chw(other, layout.interleave, good)
    if nodata is not None:
        other = other[~nodata]
    if np.isfinite(other).all():  # the other byte order reads clean: the header's is wrong
        raise InputError(f"{data}: {int((~np.isfinite(cube)).sum())} NaN/Inf value(s) with byte order {layout.order}, "
                         f"none with byte order {1 - layout.order}: fix 'byte order' in {hdr.name}")


def _envi_apply_gain_offset(hdr: Path, data: Path, cube: np.ndarray, gains: np.ndarray | None,
                            offsets: np.ndarray | None, good: np.ndarray | None, nodata: np.ndarray | None,
                            notes: list[tuple[int, str]]) -> tuple[np.ndarray, np.ndarray] | None:
    """Apply the header's per-band ``data gain values`` and ``data offset values`` (either may be None; (C0,) for
    the file's C0 bands) to ``cube`` (float32 (C, H, W), the ``good`` bands) in place, with a note; returns the
    (gains, offsets) of the cube's bands, or None when the header has neither."""
    if gains is None and offsets is None:
        return None
    # physical = gain · stored + offset, per band
    gain = np.ones(offsets.size) if gains is None else gains  # (either list has one value per band of the file)
    off = np.zeros(gain.size) if offsets is None else offsets
    if good is not None:
        gain, off = gain[good], off[good]
    cube *= gain.astype(np.float32)[:, None, None]
    cube += off.astype(np.float32)[:, None, None]
    if nodata is not None and nodata.any():  # flagged by their stored value: they stay 0 (no data)
        cube[nodata] = 0.0
    keys = " and ".join(k for k, v in (("data gain values", gains), ("data offset values", offsets)) if v is not None)
    notes.append((logging.INFO, f"{data}: applied the {keys} of {hdr.name} (value = gain × stored value + offset, "
                                "per band)"))
    return gain, off


def _envi_wavelengths(hdr: Path, h: dict[str, str], nbands: int) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """(centres (C,) nm, FWHM (C,) nm or None, a note to log when the unit was judged from the values) of the
    file's ``nbands`` bands, in the file's order; InputError without a ``wavelength`` list or for a list of
    another length."""
    if "wavelength" not in h:
        raise InputError(f"{hdr}: ENVI header has no 'wavelength' list; cannot tell the bands")
    waves = _envi_floats(hdr, h, "wavelength")
    scale, note = _envi_wavelength_scale(hdr, h, waves)
    waves = _um_to_nm(waves, scale)
    if waves.size != nbands:
        raise InputError(f"{hdr}: {waves.size} wavelengths listed for {nbands} bands")
    fwhm = None
    if "fwhm" in h:
        fwhm = _envi_floats(hdr, h, "fwhm")
        if fwhm.size != nbands:
            raise InputError(f"{hdr}: {fwhm.size} FWHM values listed for {nbands} bands")
        fwhm = _um_to_nm(fwhm, scale)
    return waves, fwhm, note


def _envi_wavelength_scale(hdr: Path, h: dict[str, str], waves: np.ndarray) -> tuple[float, str | None]:
    """(factor to nm, note to log or None) of the header's ``wavelength`` values ``waves``, by its ``wavelength
    units`` (none or "unknown": judged from the values, :func:`_unitless_scale`); InputError for another unit, or
    micrometres whose values are nanometres."""
    units = h.get("wavelength units", "").strip().lower()
    if units in MICROMETRE_UNITS:
        if waves.size and waves.min() > MICROMETRE_BELOW:  # 420 "µm" is far infrared: the values are nanometres
            raise InputError(f"{hdr}: wavelength units say {h['wavelength units'].strip()} but the values "
                             f"({waves.min():g}–{waves.max():g}) are nanometres; fix 'wavelength units'")
        return 1000.0, None
    if units in ("", "unknown"):
        return _unitless_scale(hdr, waves, "wavelength")
    if units not in NANOMETRE_UNITS:
        raise InputError(f"{hdr}: unsupported wavelength units {h['wavelength units']!r} (nm or µm)")
    return 1.0, None


def _envi_drop_bad_bands(hdr: Path, data: Path, waves: np.ndarray, fwhm: np.ndarray | None,
                         good: np.ndarray | None, notes: list[tuple[int, str]]
                         ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(centres, FWHM, dropped centres) without the bands that the bbl marks bad (``good``: mask of the good
    ones, or None: all kept, nothing dropped), with a note."""
    if good is None:
        return waves, fwhm, None
    dropped = waves[~good]
    notes.append((logging.INFO, f"{data}: dropped {dropped.size} band(s) that the bbl of {hdr.name} marks bad "
                                f"({', '.join(f'{w:g}' for w in np.sort(dropped))} nm); resampling "
                                "bridges them with the linear interpolant"))
    return waves[good], fwhm[good] if fwhm is not None else None, dropped


def _envi_ascending(cube: np.ndarray, waves: np.ndarray, fwhm: np.ndarray | None,
                    scaling: tuple[np.ndarray, np.ndarray] | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """(cube (C, H, W), centres, FWHM, (gains, offsets)) with the bands sorted by wavelength: an ENVI file may
    list them in any order, each band carrying its own wavelength."""
    order_idx = np.argsort(waves)
    if np.any(order_idx != np.arange(waves.size)):  # store bands ascending
        cube = cube[order_idx]
        waves = waves[order_idx]
        fwhm = fwhm[order_idx] if fwhm is not None else None
        scaling = None if scaling is None else (scaling[0][order_idx], scaling[1][order_idx])
    return cube, waves, fwhm, scaling


def _envi_meta(hdr: Path, data: Path, h: dict[str, str], layout: _EnviLayout, dropped: np.ndarray | None,
               ignore: float | None, n_nodata: int | None, scaling: tuple[np.ndarray, np.ndarray] | None
               ) -> dict[str, Any]:
    """The metadata :func:`read_envi` returns: the file's facts, what :func:`write_envi` kept, and what was done to
    the values (bad bands dropped, nm; no-data; gains and offsets per band of the cube returned)."""
    meta = {"format": "envi", "interleave": layout.interleave, "data_type": layout.dtype_code,
            "byte_order": layout.order, "header": str(hdr), "data_file": str(data),
            "description": h.get("description", "").strip("{} ")}
    # what write_envi kept (e.g. reconstruct's source, run and cfa_offset), as read_hsicam_h5 returns its metadata;
    # the file's own facts above win over a key of the same name
    meta = {**_envi_metadata(hdr, h), **meta}
    if dropped is not None:
        meta["bad_bands_nm"] = [float(w) for w in np.sort(dropped)]
    if ignore is not None:
        meta["data_ignore_value"] = ignore
        meta["ignored_pixels"] = n_nodata
    if scaling is not None:  # per band of the cube returned (ascending, bad bands dropped)
        meta["data_gain_offset_applied"] = True
        meta["data_gain_values"] = [float(v) for v in scaling[0]]
        meta["data_offset_values"] = [float(v) for v in scaling[1]]
    return meta


def _envi_good_bands(hdr: Path, h: dict[str, str], nbands: int) -> np.ndarray | None:
    """The header's ``bbl`` (bad band list: 1 good, 0 bad) as a boolean mask of the good bands, or
    None when it has none or marks every band good. InputError for a list of the wrong length or
    other values, or when fewer than 2 good bands would remain."""
    if "bbl" not in h:
        return None
    bbl = _envi_floats(hdr, h, "bbl")
    if bbl.size != nbands:
        raise InputError(f"{hdr}: ENVI header key 'bbl' lists {bbl.size} values for {nbands} bands")
    if not np.all((bbl == 0) | (bbl == 1)):
        raise InputError(f"{hdr}: ENVI header key 'bbl' must hold 1 (good band) or 0 (bad band) per band")
    good = bbl == 1
    if good.all():
        return None
    if np.count_nonzero(good) < 2:
        raise InputError(f"{hdr}: the bad band list (bbl) leaves {np.count_nonzero(good)} of {nbands} bands good; "
                         "at least 2 are needed")
    return good


def _envi_per_band(hdr: Path, h: dict[str, str], key: str, nbands: int) -> np.ndarray | None:
    """The header's per-band list ``key`` (``data gain values``, ``data offset values``: one finite
    number per band of the file, in the file's band order), or None when it has none."""
    if key not in h:
        return None
    values = _envi_floats(hdr, h, key)
    if values.size != nbands:
        raise InputError(f"{hdr}: ENVI header key '{key}' lists {values.size} values for {nbands} bands "
                         "(one per band)")
    if not np.all(np.isfinite(values)):
        raise InputError(f"{hdr}: ENVI header key '{key}' holds {int((~np.isfinite(values)).sum())} value(s) that "
                         "are not finite numbers")
    return values


def _envi_ignore_value(hdr: Path, h: dict[str, str]) -> float | None:
    """The header's ``data ignore value`` (one number, in the file's units; may be NaN), or None."""
    if "data ignore value" not in h:
        return None
    values = _envi_floats(hdr, h, "data ignore value")
    if values.size != 1:
        raise InputError(f"{hdr}: ENVI header key 'data ignore value' must be one number, got {values.size}")
    return float(values[0])


def _envi_nodata(cube: np.ndarray, value: float) -> np.ndarray:
    """(C, H, W) mask of the values of ``cube`` (C, H, W, as stored) that are ``value``."""
    dt = cube.dtype
    if math.isnan(value):
        return np.isnan(cube) if dt.kind == "f" else np.zeros(cube.shape, dtype=bool)
    if dt.kind in "iu":  # an integer file holds only integers of its type's range
        info = np.iinfo(dt)
        if not value.is_integer() or not info.min <= value <= info.max:
            return np.zeros(cube.shape, dtype=bool)
    return cube == dt.type(value)


def write_envi(path: str | os.PathLike, cube: np.ndarray, bands: Bands, *, interleave: str = "bsq",
               dtype: str | np.dtype = "float32", byte_order: str = "little", description: str = "hsicam write_envi",
               reflectance_scale: float | None = None, metadata: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """Write an ENVI pair ``<name>.hdr`` + ``<name>.img`` atomically; returns (header, data) paths.

    ``metadata`` (JSON-serialisable): kept in the header as one line, ``hsicam metadata = {JSON}``
    (:func:`envi_metadata_value`), and returned by :func:`read_envi` in the cube's meta, as our HDF5's
    ``metadata_json`` is by :func:`read_hsicam_h5`.

    ``reflectance_scale``: the data are written as ``cube × reflectance_scale`` and the header's ``reflectance scale
    factor`` says so (:func:`read_envi` divides it out): e.g. 10000 for an integer ``dtype`` of a [0, 1] cube. An
    integer ``dtype`` without it rounds the values themselves, so a cube of fractions (peak ≤ 1) is refused (it
    would be written as 0s and 1s), and so is a cube whose values (× ``reflectance_scale``) exceed the type's maximum
    (they would be clipped to it).

    ``path`` may name either file. The data file is written first, the header last, so a reader
    never finds a header without its data; the header records the data's CRC-32
    (:data:`ENVI_CRC_KEY`), so a pair left half-replaced by an interruption between the two renames
    (new data, old header) is refused by :func:`read_envi` instead of read as another shape. A failure
    or interruption (Ctrl-C, SIGTERM) between the two removes the files of the pair that this call
    put where none was, so no data file is left without its header.
    """
    p = Path(path)
    hdr, data = (p, p.with_suffix(".img")) if p.suffix.lower() == ".hdr" else (p.with_suffix(".hdr"), p)
    arr = _cube_of_bands(p, cube, bands)
    dt, code = _envi_write_options(dtype, interleave, byte_order, description)
    arr = _envi_stored_values(p, arr, dt, reflectance_scale)
    raw = _envi_disk_bytes(arr, dt, interleave, byte_order)
    header = _envi_header_text(arr.shape, bands, code, interleave, byte_order, description, reflectance_scale,
                               metadata, raw)
    _write_envi_pair(hdr, data, raw, header)
    return hdr, data


def _envi_write_options(dtype: str | np.dtype, interleave: str, byte_order: str, description: str
                        ) -> tuple[np.dtype, int]:
    """(numpy dtype, ENVI data type code) of :func:`write_envi`'s ``dtype``, after its options are checked:
    InputError for a type ENVI has no code for, another interleave or byte order, or a description that is not
    one line without braces."""
    codes = {np.dtype(v): k for k, v in _ENVI_DTYPES.items()}
    try:
        dt = np.dtype(dtype)
    except TypeError:  # numpy's "data type 'int99' not understood"
        raise InputError(f"write_envi: unknown data type {dtype!r} (e.g. float32, int16, uint16)") from None
    if dt not in codes:
        raise InputError(f"write_envi: unsupported data type {dt}")
    if interleave not in _ENVI_INTERLEAVES:
        raise InputError(f"write_envi: interleave must be bsq, bil or bip, got {interleave!r}")
    if byte_order not in ("little", "big"):
        raise InputError(f"write_envi: byte_order must be 'little' or 'big', got {byte_order!r}")
    if not isinstance(description, str) or any(ch in description for ch in "{}\r\n"):
        # a brace ends the header's braced value: what followed it was read as more header keys
        raise InputError(f"write_envi: description must be one line of text without braces, got {description!r}")
    return dt, codes[dt]


def _envi_stored_values(p: Path, arr: np.ndarray, dt: np.dtype, reflectance_scale: float | None) -> np.ndarray:
    """The values to store of the cube ``arr`` (C, H, W): × ``reflectance_scale`` when given. InputError when an
    integer type ``dt`` would store them as 0s and 1s (fractions, no scale) or clip them (above its maximum)."""
    if reflectance_scale is not None:
        if (isinstance(reflectance_scale, (bool, np.bool_)) or not isinstance(reflectance_scale, numbers.Real)
                or not (math.isfinite(reflectance_scale) and reflectance_scale > 0)):  # numpy's scalars are Real
            raise InputError(f"write_envi: reflectance_scale must be a positive number, got {reflectance_scale!r}")
        reflectance_scale = float(reflectance_scale)
        arr = arr * np.float64(reflectance_scale)
    elif dt.kind in "iu" and arr.size and float(np.nanmax(arr)) <= 1.0 and not np.array_equal(arr, np.round(arr)):
        raise InputError(f"{p}: a cube of values up to {float(np.nanmax(arr)):.3g} written as {dt} would be rounded to "
                         f"0s and 1s; pass reflectance_scale (e.g. 10000: the header's reflectance scale factor, which "
                         "read_envi divides out) or write float32")
    if dt.kind in "iu" and arr.size and float(np.round(np.max(arr))) > np.iinfo(dt).max:  # (no negatives: check_cube)
        peak = float(np.max(arr))
        scaled = "" if reflectance_scale is None else \
            f"{peak / reflectance_scale:.6g} × reflectance_scale {reflectance_scale:g} = "
        raise InputError(f"{p}: a cube of values up to {scaled}{peak:.6g} written as {dt} (at most {np.iinfo(dt).max}) "
                         f"would be clipped to {np.iinfo(dt).max}; pass a smaller reflectance_scale, or write a wider "
                         "integer type or float32")
    return arr


def _envi_disk_bytes(arr: np.ndarray, dt: np.dtype, interleave: str, byte_order: str) -> np.ndarray:
    """The data file's bytes (uint8) of the values ``arr`` (C, H, W): in ``interleave`` order, as ``dt`` (integers
    rounded) in ``byte_order``."""
    out = {"bsq": arr, "bil": arr.transpose(1, 0, 2), "bip": arr.transpose(1, 2, 0)}[interleave]
    if dt.kind in "iu":
        info = np.iinfo(dt)
        out = np.clip(np.round(out), info.min, info.max)
    out = np.ascontiguousarray(out, dtype=dt.newbyteorder("<" if byte_order == "little" else ">"))
    return out.reshape(-1).view(np.uint8)  # the bytes, without a copy (tobytes() doubled a cube in memory)


def _envi_header_text(shape: tuple[int, ...], bands: Bands, code: int, interleave: str, byte_order: str,
                      description: str, reflectance_scale: float | None, metadata: dict[str, Any] | None,
                      raw: np.ndarray) -> str:
    """The ENVI header of a cube of ``shape`` (C, H, W) stored as the bytes ``raw`` (their CRC-32 recorded)."""
    c, h, w = shape
    # to the NM_DECIMALS the readers keep (6 significant digits dropped the third decimal above 1000 nm)
    fmt = lambda v: ", ".join(f"{round(float(x), NM_DECIMALS):.12g}" for x in v)  # noqa: E731
    return (
        "ENVI\n"
        f"description = {{{description}}}\n"
        f"samples = {w}\nlines = {h}\nbands = {c}\nheader offset = 0\nfile type = ENVI Standard\n"
        f"data type = {code}\ninterleave = {interleave}\nbyte order = {0 if byte_order == 'little' else 1}\n"
        "wavelength units = Nanometers\n"
        f"wavelength = {{{fmt(bands.centers_nm)}}}\n"
        f"fwhm = {{{fmt(bands.fwhm_nm)}}}\n"
        + (f"reflectance scale factor = {reflectance_scale:.10g}\n" if reflectance_scale is not None else "")
        + (f"{ENVI_METADATA_KEY} = {envi_metadata_value(metadata)}\n" if metadata is not None else "")
        + f"{ENVI_CRC_KEY} = {zlib.crc32(raw):08x}\n"
    )


def _write_envi_pair(hdr: Path, data: Path, raw: np.ndarray, header: str) -> None:
    """Write ``data`` (the bytes ``raw``) and ``hdr`` (the text ``header``), each to a hidden temporary first: the
    header's is written, then the data's, which takes its place, then the header's takes its own (a stop while the
    data is written leaves an earlier pair as it was); on a failure or interruption, remove those of the two that
    were not there before."""
    for f in (data, hdr):  # both before either is written
        check_output_path(f, "file")
    new = [f for f in (data, hdr) if not os.path.lexists(f)]
    try:
        with atomic_path(hdr) as hdr_tmp:
            hdr_tmp.write_text(header, encoding="utf-8")
            with atomic_path(data) as tmp, open(tmp, "wb") as fh:
                fh.write(raw)
    except BaseException:
        # stopped between the two renames, a new data file stood alone: no reader takes it without its header, and
        # `hsicam reconstruct` run again refused it as a user's file. A file that was there before is kept (an old
        # header beside new data is refused by its CRC-32, and the same command replaces the pair).
        for f in new:
            f.unlink(missing_ok=True)
        raise


def envi_metadata_value(metadata: dict[str, Any]) -> str:
    """The ENVI header value of :data:`ENVI_METADATA_KEY`: ``metadata`` as one line of JSON in ENVI's braces,
    ``{{...}}``, that every ENVI reader takes whole. Strict JSON (:func:`hsicam.io.json_text`: a float that is not
    finite written as null, which strict parsers take and ``NaN``/``Infinity`` they refuse). ASCII only (``ensure_ascii``: no character that a reader's
    line splitting, e.g. Python's ``str.splitlines`` on U+2028, would break the line at); no spaces after the
    separators; and inside strings ``{``, ``}`` and ``,`` written as JSON's ``\\u007b``, ``\\u007d`` and
    ``\\u002c``: readers that count braces to find the value's end see them balanced, and those that split a
    braced value at its commas (the ``spectral`` package) split only between JSON items, with nothing stripped, so
    that joining the pieces with ``,`` gives the JSON back. :func:`read_envi` reads it (:func:`_envi_metadata`)."""
    text = json_text(metadata, sort_keys=True, ensure_ascii=True, separators=(",", ":"))
    text = _JSON_STRING.sub(lambda m: m.group(0).replace("{", "\\u007b").replace("}", "\\u007d")
                            .replace(",", "\\u002c"), text)
    return "{" + text + "}"


#: A JSON string literal (its escapes, ``\\"`` included, kept inside it).
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def _envi_metadata(hdr: Path, h: dict[str, str]) -> dict[str, Any]:
    """The metadata that :func:`write_envi` kept in the header ``h`` ({} when none; a value that is not a JSON
    object in braces: a warning, and {}, as an unreadable ``metadata_json`` of our HDF5 is ignored)."""
    value = h.get(ENVI_METADATA_KEY)
    if value is None:
        return {}
    value = value.strip()
    try:
        if not (value.startswith("{") and value.endswith("}")):
            raise ValueError("not in braces")
        loaded = json.loads(value[1:-1])
    except ValueError:  # json.JSONDecodeError too
        loaded = None
    if not isinstance(loaded, dict):
        log.warning("%s: ignoring its unreadable '%s' (not a JSON object in braces)", hdr, ENVI_METADATA_KEY)
        return {}
    return nan_for_null(loaded)  # a score written as null (not finite) is NaN again, as older files' NaN


# ------------------------------------------------------------------------------------------------
# NumPy
# ------------------------------------------------------------------------------------------------
def npy_header(path: str | os.PathLike) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) declared by a ``.npy`` file's header, without reading its data."""
    p = Path(path)
    with _reading(p, "NPY"):
        with open(p, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version in ((2, 0), (3, 0)):
                # 3.0 is 2.0's layout with a UTF-8 header instead of Latin-1, which np.load reads: numpy writes it
                # only for a structured dtype with field names beyond Latin-1 (no cube: refused by its dtype, those
                # names garbled here); a plain array saved as 3.0 has an ASCII header, read alike
                shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise InputError(f"{p}: unsupported NPY format version {version[0]}.{version[1]}")
    return tuple(int(s) for s in shape), np.dtype(dtype)


def _checked_npy_header(p: Path, bands: Bands | None) -> tuple[tuple[int, ...], np.dtype, str]:
    """(shape, dtype, the hint for a cube stored bands last) of the ``.npy`` file ``p``, from its header; InputError
    unless a 3-D array of numbers whose axis 0 has the bands of ``bands`` (when given)."""
    shape, dtype = npy_header(p)
    if len(shape) != 3:
        raise InputError(f"{p}: expected a 3-D array (bands, height, width), got {len(shape)} dimensions {shape}")
    if dtype.hasobject:
        raise InputError(f"{p}: the array holds Python objects ({dtype}); a cube holds numbers (pickles are never loaded)")
    last = (f"; its last axis has {shape[-1]}: a cube stored bands last (height, width, bands) is "
            "np.save(path, np.moveaxis(cube, -1, 0))")
    if bands is not None and len(bands) != shape[0]:
        raise InputError(f"{p}: the cube has {shape[0]} bands (axis 0 of a (bands, height, width) array) but "
                         f"the band grid given for it has {len(bands)}" + (last if shape[-1] == len(bands) else ""))
    return shape, dtype, last


def read_npy(path: str | os.PathLike, *, bands: Bands | None = None, allow_negative: bool = False,
             memory_budget_mb: float | None = None) -> Cube:
    """``.npy`` array (C, H, W). Bands: ``bands`` if given, else C bands evenly over 400-700 nm, said in a warning
    once per file and process (the file carries no wavelengths: a cube of 420-720 nm read so is resampled from the
    wrong wavelengths)."""
    p = _as_path(path)
    shape, dtype, last = _checked_npy_header(p, bands)
    check_memory_budget(p, shape, dtype, what="NPY array", budget_mb=memory_budget_mb)
    with _reading(p, "NPY"):
        arr = np.load(p, mmap_mode="r", allow_pickle=False)
        arr = np.array(arr)
    if bands is None:
        bands = bands_400_700(arr.shape[0])
        assumed = True
    else:
        assumed = False
    meta = {"format": "npy", "bands_assumed": assumed,
            "assumed_grid": describe_400_700(arr.shape[0]) if assumed else None}
    cube = _finish(p, arr, bands, meta, allow_negative)
    text = f"{p}: the file carries no wavelengths and none were given for it; assuming {meta['assumed_grid']}"
    if shape[-1] < min(shape[0], shape[1]):  # the shortest axis last: more likely (height, width, bands)
        text += last.replace("its last axis has", "its last axis, the shortest, has")
    if assumed and text not in _NOTED:  # once per file: a dataset reads its scenes again and again
        _NOTED.add(text)
        log.warning("%s", text)
    return cube


READERS: dict[str, Callable[..., Cube]] = {
    "hsicam": read_hsicam_h5,
    "icvl": read_icvl,
    "arad": read_arad,
    "kaist-mat": read_kaist_mat,
    "harvard": read_harvard,
    "kaist-exr": read_kaist_exr,
    "cave": read_cave,
    "envi": read_envi,
    "npy": read_npy,
}


# ------------------------------------------------------------------------------------------------
# Cheap access for datasets: shapes and windows without reading the whole cube
# ------------------------------------------------------------------------------------------------
def read_window(path: str | os.PathLike, y: int, x: int, h: int, w: int) -> tuple[np.ndarray, Bands] | None:
    """Read the window [y:y+h, x:x+w] of an hsicam HDF5 file without loading the rest.

    Returns (cube (C, h, w) float32, bands), or None when the file is not in our format (callers
    then load the whole cube). Values are not checked here (the whole file was checked on write).
    """
    import h5py

    p = Path(path)
    if not p.is_file() or not _head(p, 8).startswith(_HDF5_MAGIC):
        return None
    with _reading(p, "HDF5"):
        with h5py.File(p, "r") as f:
            if f.attrs.get("format") != HSICAM_FORMAT or "cube" not in f or "bands_nm" not in f:
                return None
            check_format_version(p, f.attrs)
            ds = f["cube"]
            if y < 0 or x < 0 or y + h > ds.shape[1] or x + w > ds.shape[2]:
                raise InputError(f"{p}: window {h}x{w} at ({y}, {x}) is outside the cube {ds.shape[1]}x{ds.shape[2]}")
            cube, bands = _h5_bands(p, f, np.asarray(ds[:, y:y + h, x:x + w], dtype=np.float32))
    return cube, bands


def read_bands(path: str | os.PathLike, *, bands: Bands | None = None) -> Bands:
    """The band grid :func:`read_cube` returns for ``path``, read without loading the cube's values: from the
    header, band list or channel names (an ENVI header's good bands, a MAT/HDF5 file's band list or, without one,
    the grid assumed for its band count, an EXR file's channel names, CAVE's 400-700 nm, a ``.npy`` file's
    ``bands`` or C bands over 400-700 nm). InputError as the reader would raise it for what this reads."""
    p = _as_path(path)
    fmt = detect_format(p)
    if fmt == "cave":
        return Bands.uniform(400.0, 700.0, 10.0)
    if fmt == "npy":
        shape = _checked_npy_header(p, bands)[0]
        return bands if bands is not None else bands_400_700(shape[0])
    if fmt == "envi":
        hdr, data = _envi_pair(p)
        h = parse_envi_header(hdr)
        n = _envi_layout(hdr, h).nbands
        waves, fwhm, _ = _envi_wavelengths(hdr, h, n)
        waves, fwhm, _ = _envi_drop_bad_bands(hdr, data, waves, fwhm, _envi_good_bands(hdr, h, n), [])
        _, waves, fwhm, _ = _envi_ascending(_shape_only((waves.size, 1, 1)), waves, fwhm, None)
        return _bands_from(hdr, waves, fwhm)
    if fmt == "kaist-exr":
        OpenEXR = _openexr(p)
        with _reading(p, "OpenEXR"):
            with OpenEXR.File(str(p), header_only=True) as f:
                names = [c.name for c in f.header().get("channels", ())]
        return Bands.from_centers([w for w, _ in _exr_spectral_channels(p, names)])
    if fmt == "hsicam":
        import h5py

        with _reading(p, "HDF5"), h5py.File(p, "r") as f:
            check_format_version(p, f.attrs)
            for key in ("cube", "bands_nm"):  # as read_hsicam_h5 refuses a group of that name
                if not isinstance(f[key], h5py.Dataset):
                    raise InputError(f"{p}: '{key}' is a {type(f[key]).__name__.lower()}, not an array "
                                     "(not an hsicam cube file)")
            return _h5_bands(p, f, _shape_only(f["cube"].shape))[1]
    return _mat_cube_bands(p, fmt, _load_mat(p, _MAT_KEYS[fmt], None, read_data=False))[1]


__all__ = [
    "BAND_LIST_NAMES",
    "FORMATS",
    "MST_28_NM",
    "READERS",
    "SCENE_SUFFIXES",
    "assumed_bands_note",
    "bands_400_700",
    "detect_format",
    "envi_data_file",
    "exr_channel_wavelength",
    "npy_header",
    "parse_envi_header",
    "read_arad",
    "read_bands",
    "read_cave",
    "read_cube",
    "read_envi",
    "read_harvard",
    "read_hsicam_h5",
    "read_icvl",
    "read_kaist_exr",
    "read_kaist_mat",
    "read_npy",
    "read_window",
    "write_cube_h5",
    "write_envi",
]
