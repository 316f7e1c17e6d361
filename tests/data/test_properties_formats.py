"""Property-based tests (hypothesis) of the cube readers and writers, the capture readers and the
raw-capture corrections, and the atomic writers, on unusual but legal inputs: 1×1 and odd sizes,
one band and many, non-uniform band grids, float32/float64/integer data, zeros and big values, every
ENVI interleave and byte order, files written by independent writers (h5py, scipy.io.savemat,
numpy, a hand-written ENVI header, Pillow, tifffile), and paths with spaces and non-ASCII names.

Each invariant is checked against an independent reference: the array written, indexed by hand,
or a closed form computed in float64 with numpy.

Also the cube checks and band resampling (against a per-pixel loop of resample_spectra; moved from
optics/test_properties_spectral_sensor_metrics.py) and the previews of cubes of any band count and size (finite
images of the documented size; moved from report/test_properties_report.py).
"""

from __future__ import annotations

import json
import math
import uuid

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from hsicam.data import formats
from hsicam.data.cube import check_cube, normalize_per_cube_max, resample_cube
from hsicam.data.images import RawCorrection, normalised_flat, preprocess_raw, read_image_2d
from hsicam.errors import InputError
from hsicam.io import atomic_path, write_json, write_npy, write_png16
from hsicam.spectral import Bands
from hsicam.spectral.bands import resampling_matrix
from property_settings import CORE_PROP, OUTPUT_PROPS, random_grid, seeds

PROPS = settings(max_examples=50, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FEW = settings(PROPS, max_examples=15)

#: awkward names for the files: spaces, non-ASCII letters, an emoji, a leading dash
NAMES = st.sampled_from(["cube", "a b", "spéctre", "日本 語", "-x", "🌈 scene", "x.y.z"])


@pytest.fixture(scope="module")
def fresh_dir(tmp_path_factory):
    """A factory of new empty folders (hypothesis runs many examples in one test call)."""
    base = tmp_path_factory.mktemp("props")

    def make():
        d = base / uuid.uuid4().hex[:10]
        d.mkdir()
        return d

    return make


@st.composite
def band_grids(draw, min_bands=1, max_bands=40):
    """Strictly ascending band centres (nm) at 3 decimals, on a uniform or an irregular grid, from the
    UV to the SWIR (200-2500 nm), with FWHM of any positive size."""
    n = draw(st.integers(min_bands, max_bands))
    start = draw(st.floats(200.0, 1500.0))
    steps = draw(st.lists(st.floats(0.01, 40.0), min_size=n, max_size=n))
    if draw(st.booleans()):
        steps = [steps[0]] * n
    centres = np.round(start + np.concatenate([[0.0], np.cumsum(steps[1:])]), 3)
    assume(np.all(np.diff(centres) > 0))
    fwhm = np.round(np.asarray(draw(st.lists(st.floats(0.01, 100.0), min_size=n, max_size=n))), 3)
    assume(np.all(fwhm > 0))
    return centres, fwhm


@st.composite
def cubes(draw, bands=None, max_side=7, dtype=None, integers=False):
    """A (C, H, W) cube of C = len(bands) (or 1..40), sides 1..max_side, with zeros, tiny and big values."""
    c = len(bands) if bands is not None else draw(st.integers(1, 40))
    h, w = draw(st.integers(1, max_side)), draw(st.integers(1, max_side))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    if integers:
        cube = rng.integers(0, 65536, size=(c, h, w)).astype(np.float64)
    else:
        mag = draw(st.sampled_from([1.0, 1e-30, 1e-3, 1e4, 3e38]))
        cube = rng.random((c, h, w)) * mag
    cube[rng.random((c, h, w)) < 0.2] = 0.0
    return cube.astype(dtype or draw(st.sampled_from([np.float32, np.float64])))


# ------------------------------------------------------------------------------------------------
# Our HDF5
# ------------------------------------------------------------------------------------------------
@PROPS
@given(grid=band_grids(), data=st.data(), name=NAMES)
def test_hsicam_h5_round_trip(fresh_dir, grid, data, name):
    """write_cube_h5 -> read_cube: the float32 cube, the band centres and FWHM come back exactly; a
    window read with read_window is that slice of the cube."""
    centres, fwhm = grid
    bands = Bands(centres, fwhm)
    cube = data.draw(cubes(bands))
    path = fresh_dir() / f"{name}.h5"
    formats.write_cube_h5(path, cube, bands, metadata={"name": name})
    got, got_bands, meta = formats.read_cube(path)
    assert got.dtype == np.float32 and got.shape == cube.shape
    np.testing.assert_array_equal(got, cube.astype(np.float32))
    np.testing.assert_array_equal(got_bands.centers_nm, centres)
    np.testing.assert_array_equal(got_bands.fwhm_nm, fwhm)
    assert meta["name"] == name and meta["format"] == "hsicam"
    _, h, w = cube.shape
    y, x = data.draw(st.integers(0, h - 1)), data.draw(st.integers(0, w - 1))
    hh, ww = data.draw(st.integers(1, h - y)), data.draw(st.integers(1, w - x))
    win, win_bands = formats.read_window(path, y, x, hh, ww)
    np.testing.assert_array_equal(win, cube.astype(np.float32)[:, y:y + hh, x:x + ww])
    assert win_bands == bands


# ------------------------------------------------------------------------------------------------
# ENVI
# ------------------------------------------------------------------------------------------------
ENVI_CODES = {"u1": 1, "i2": 2, "i4": 3, "f4": 4, "f8": 5, "u2": 12, "u4": 13, "i8": 14, "u8": 15}


@PROPS
@given(grid=band_grids(), data=st.data(), interleave=st.sampled_from(["bsq", "bil", "bip"]),
       order=st.sampled_from(["little", "big"]), dtype=st.sampled_from(["float32", "float64", "uint16", "int32"]),
       name=NAMES)
def test_envi_round_trip(fresh_dir, grid, data, interleave, order, dtype, name):
    """write_envi -> read_envi for every interleave, byte order and a float or integer type: the cube
    as float32 (integers: the integer values), bands and FWHM at 3 decimals."""
    centres, fwhm = grid
    bands = Bands(centres, fwhm)
    integer = dtype in ("uint16", "int32")
    cube = data.draw(cubes(bands, integers=integer))
    if dtype == "float32" or integer:
        cube = cube.astype(np.float64)
    if dtype == "float32":  # a float32 file holds float32 values: keep them in range
        cube = np.minimum(cube, 1e38)
    hdr, raw = formats.write_envi(fresh_dir() / f"{name}.hdr", cube, bands, interleave=interleave, dtype=dtype,
                                  byte_order=order, metadata={"n": name, "s": "{a, b}"})
    for path in (hdr, raw):
        got, got_bands, meta = formats.read_cube(path)
        np.testing.assert_array_equal(got, cube.astype(np.float32))
        np.testing.assert_array_equal(got_bands.centers_nm, centres)
        np.testing.assert_array_equal(got_bands.fwhm_nm, fwhm)
        assert meta["interleave"] == interleave and meta["n"] == name and meta["s"] == "{a, b}"


@PROPS
@given(c=st.integers(1, 12), h=st.integers(1, 6), w=st.integers(1, 6), code=st.sampled_from(sorted(ENVI_CODES)),
       interleave=st.sampled_from(["bsq", "bil", "bip"]), big=st.booleans(), offset=st.integers(0, 40),
       shuffle=st.booleans(), micrometres=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_envi_independent_writer(fresh_dir, c, h, w, code, interleave, big, offset, shuffle, micrometres, seed):
    """A hand-written ENVI pair (numpy's tofile of the values in the file's own order, a header offset,
    the bands in any order, wavelengths in µm or nm) reads back as the brute-force indexing of the
    stored values, bands sorted ascending with their planes."""
    rng = np.random.default_rng(seed)
    dt = np.dtype(code).newbyteorder(">" if big else "<")
    hi = 255 if code == "u1" else 1000
    stored = rng.integers(0, hi + 1, size={"bsq": (c, h, w), "bil": (h, c, w), "bip": (h, w, c)}[interleave])
    waves_nm = np.round(rng.permutation(400.0 + 7.5 * np.arange(c)) if shuffle else 400.0 + 7.5 * np.arange(c), 3)
    listed = waves_nm / 1000.0 if micrometres else waves_nm
    d = fresh_dir()
    (d / "scene.hdr").write_text(
        "ENVI\ndescription = {hand written}\n"
        f"samples = {w}\nlines = {h}\nbands = {c}\nheader offset = {offset}\ndata type = {ENVI_CODES[code]}\n"
        f"interleave = {interleave}\nbyte order = {1 if big else 0}\n"
        f"wavelength units = {'Micrometers' if micrometres else 'Nanometers'}\n"
        f"wavelength = {{{', '.join(repr(float(v)) for v in listed)}}}\n", encoding="ascii")
    with open(d / "scene.img", "wb") as fh:
        fh.write(b"\x00" * offset)
        stored.astype(dt).tofile(fh)
    got, got_bands, _ = formats.read_envi(d / "scene.hdr")
    want = np.empty((c, h, w))
    for b in range(c):
        for y in range(h):
            for x in range(w):
                want[b, y, x] = (stored[b, y, x] if interleave == "bsq" else stored[y, b, x] if interleave == "bil"
                                 else stored[y, x, b])
    order = np.argsort(waves_nm)
    np.testing.assert_array_equal(got, want[order].astype(np.float32))
    np.testing.assert_allclose(got_bands.centers_nm, waves_nm[order], rtol=0, atol=5e-4)


def test_envi_integer_writer_refuses_values_beyond_the_type(fresh_dir):
    """A radiance cube peaking at 10, written as uint16 with the docstring's reflectance_scale 10000, came back
    capped at 6.5535 (uint8 counts of 300: 255), without a word: refused now, and no file is left."""
    d = fresh_dir()
    bands = Bands.from_centers([550.0])
    with pytest.raises(InputError, match=r"^.*r\.hdr: a cube of values up to 10 × reflectance_scale 10000 = "
                       r"100000 written as uint16 \(at most 65535\) would be clipped to 65535; pass a smaller "
                       r"reflectance_scale, or write a wider integer type or float32$"):
        formats.write_envi(d / "r.hdr", np.array([[[0.5, 2.0, 10.0]]]), bands, dtype="uint16", reflectance_scale=10000)
    with pytest.raises(InputError, match=r"values up to 300 written as uint8 \(at most 255\)"):
        formats.write_envi(d / "s.hdr", np.array([[[100.0, 300.0]]]), bands, dtype="uint8")
    assert not list(d.iterdir())


@PROPS
@given(data=st.data(), dtype=st.sampled_from(["uint8", "int16", "uint16", "int32"]),
       scale=st.sampled_from([None, 1.0, 255.0, 1000.0, 10000.0]), peak=st.floats(1.5, 1e5))
def test_envi_integer_round_trip(fresh_dir, data, dtype, scale, peak):
    """write_envi to an integer type reads back within half a step (0.5 / reflectance_scale) of the cube, or is
    refused with one InputError when the values (× the scale) do not fit the type: never clipped silently."""
    cube = data.draw(cubes(Bands.from_centers([500.0, 600.0]))).astype(np.float64)
    cube = cube / max(cube.max(), 1e-300) * peak
    k = 1.0 if scale is None else scale
    cube32 = cube.astype(np.float32).astype(np.float64)  # what the writer scales (its cube check gives float32)
    fits = np.round(cube32.max() * k) <= np.iinfo(dtype).max
    path = fresh_dir() / "i.hdr"
    if not fits:
        with pytest.raises(InputError, match="would be clipped to"):
            formats.write_envi(path, cube, Bands.from_centers([500.0, 600.0]), dtype=dtype, reflectance_scale=scale)
        return
    formats.write_envi(path, cube, Bands.from_centers([500.0, 600.0]), dtype=dtype, reflectance_scale=scale)
    got, _, _ = formats.read_envi(path)
    np.testing.assert_allclose(got, np.round(cube32 * k) / k, rtol=1e-6, atol=0)
    assert np.all(np.abs(got - cube) <= 0.5 / k * (1 + 1e-6) + 1e-6 * cube)


def test_envi_description_that_would_end_its_header_value_is_refused(fresh_dir):
    """write_envi wrote ``description = {TEXT}`` raw: a ``}`` and a newline in TEXT put header keys of the caller's
    choosing after it (here a bad-band list that drops band 1 on reading). Refused now, before any file."""
    d = fresh_dir()
    bands = Bands.from_centers([500.0, 600.0])
    bad = "mine}\nbbl = {0, 1"
    with pytest.raises(InputError, match=r"^write_envi: description must be one line of text without braces, got "):
        formats.write_envi(d / "x.hdr", np.ones((2, 2, 2)), bands, description=bad)
    assert not list(d.iterdir())
    hdr, _ = formats.write_envi(d / "y.hdr", np.ones((2, 2, 2)), bands, description="scene 3, (rev. 2): ok")
    cube, got_bands, meta = formats.read_envi(hdr)
    assert cube.shape == (2, 2, 2) and meta["description"] == "scene 3, (rev. 2): ok"


JSON_TEXT = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=12)
JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6) | JSON_TEXT
                           | st.floats(allow_nan=False, allow_infinity=False),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(JSON_TEXT, inner, max_size=3),
                           max_leaves=8)


@PROPS
@given(meta=st.dictionaries(JSON_TEXT, JSON_VALUES, max_size=4))
def test_envi_metadata_round_trip(fresh_dir, meta):
    """Any JSON object kept by write_envi (text with braces, commas, quotes, backslashes, line
    separators, any Unicode) comes back from read_envi as it was (keys not shadowed by the file's own
    facts)."""
    own = {"format", "interleave", "data_type", "byte_order", "header", "data_file", "description", "source"}
    meta = {k: v for k, v in meta.items() if k not in own}
    hdr, _ = formats.write_envi(fresh_dir() / "m.hdr", np.ones((2, 1, 1)), Bands.from_centers([500.0, 600.0]),
                                metadata=meta)
    _, _, got = formats.read_envi(hdr)
    assert {k: got[k] for k in meta} == json.loads(json.dumps(meta))


# ------------------------------------------------------------------------------------------------
# MAT v5 (scipy), MAT v7.3 and plain HDF5 (h5py), NPY (numpy): independent writers
# ------------------------------------------------------------------------------------------------
@PROPS
@given(grid=band_grids(min_bands=2, max_bands=33), data=st.data(), key=st.sampled_from(["rad", "cube", "img", "ref"]),
       descending=st.booleans(), list_name=st.sampled_from(["bands", "wavelength", "WL", "lambda"]))
def test_mat5_savemat(fresh_dir, grid, data, key, descending, list_name):
    """A MAT v5 file of scipy.io.savemat (H×W×C, a band list in nm, ascending or descending) reads as
    the (C, H, W) transpose, bands ascending with their planes."""
    import scipy.io

    centres, _ = grid
    cube = data.draw(cubes(Bands.from_centers(centres)))
    hwc = np.transpose(cube, (1, 2, 0))
    waves = centres[::-1] if descending else centres
    hwc_disk = hwc[..., ::-1] if descending else hwc
    path = fresh_dir() / "scene.mat"
    scipy.io.savemat(path, {key: np.ascontiguousarray(hwc_disk), list_name: waves[None, :]})
    got, got_bands, meta = formats.read_cube(path)
    np.testing.assert_array_equal(got, cube.astype(np.float32))
    np.testing.assert_array_equal(got_bands.centers_nm, centres)
    assert meta["mat_version"] == "5"


def _write_mat73(path, variables):
    """A MAT v7.3 file as MATLAB writes it: the 512-byte user block with its text header, every
    array stored with its axes reversed (column-major), MATLAB_class attributes."""
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            arr = np.asarray(value)
            ds = f.create_dataset(name, data=arr.T)
            ds.attrs["MATLAB_class"] = np.bytes_("double" if arr.dtype == np.float64 else "single")
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 .")


@PROPS
@given(grid=band_grids(min_bands=1, max_bands=33), data=st.data(), key=st.sampled_from(["rad", "cube", "img"]),
       descending=st.booleans(), micrometres=st.booleans())
def test_mat73_h5py(fresh_dir, grid, data, key, descending, micrometres):
    """A MAT v7.3 file (h5py with MATLAB's user block, axes reversed on disk) of an H×W×C cube reads as
    (C, H, W); a band list in µm (all below 30) is converted to nm; descending lists are reversed."""
    centres, _ = grid
    assume(not (descending and centres.size == 1))
    cube = data.draw(cubes(Bands.from_centers(centres)))
    waves = centres[::-1] if descending else centres
    hwc = np.transpose(cube[::-1] if descending else cube, (1, 2, 0))
    listed = waves / 1000.0 if micrometres else waves
    path = fresh_dir() / "scene.mat"
    _write_mat73(path, {key: hwc, "bands": listed[None, :]})
    got, got_bands, meta = formats.read_cube(path)
    np.testing.assert_array_equal(got, cube.astype(np.float32))
    np.testing.assert_allclose(got_bands.centers_nm, centres, rtol=0, atol=5e-4)
    assert meta["mat_version"] == "7.3"


@PROPS
@given(grid=band_grids(min_bands=1, max_bands=33), data=st.data(), hwc=st.booleans())
def test_plain_h5_c_order(fresh_dir, grid, data, hwc):
    """A plain HDF5 file (h5py, C order) with ``cube`` (C, H, W) or (H, W, C) and ``bands`` reads as
    (C, H, W) when only one of its first and last axes has the band count."""
    import h5py

    centres, _ = grid
    cube = data.draw(cubes(Bands.from_centers(centres)))
    c, h, w = cube.shape
    assume((h != c) if hwc else (w != c))  # both ends with the band count: refused as ambiguous (documented)
    path = fresh_dir() / "scene.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("cube", data=np.transpose(cube, (1, 2, 0)) if hwc else cube)
        f.create_dataset("bands", data=centres)
    got, got_bands, meta = formats.read_cube(path)
    np.testing.assert_array_equal(got, cube.astype(np.float32))
    np.testing.assert_array_equal(got_bands.centers_nm, centres)
    assert meta["container"] == "HDF5"


@PROPS
@given(c=st.integers(1, 40), h=st.integers(1, 7), w=st.integers(1, 7),
       dtype=st.sampled_from(["<f4", ">f4", "<f8", ">f8", "<u2", ">u2", "u1", "<i4"]), fortran=st.booleans(),
       given_bands=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_npy(fresh_dir, c, h, w, dtype, fortran, given_bands, seed):
    """np.save of a (C, H, W) array of any byte order and memory order reads back as its float32 copy;
    bands are the ones given, else C evenly over 400-700 nm (550 nm for one)."""
    rng = np.random.default_rng(seed)
    arr = (rng.random((c, h, w)) * 200).astype(dtype)
    arr = np.asfortranarray(arr) if fortran else arr
    path = fresh_dir() / "x.npy"
    np.save(path, arr)
    bands = Bands.from_centers(np.arange(c) * 3.0 + 900.0) if given_bands else None
    got, got_bands, meta = formats.read_cube(path, bands=bands)
    np.testing.assert_array_equal(got, arr.astype(np.float32))
    want = np.arange(c) * 3.0 + 900.0 if given_bands else (np.array([550.0]) if c == 1 else np.linspace(400, 700, c))
    np.testing.assert_array_equal(got_bands.centers_nm, want)
    assert meta["bands_assumed"] is (not given_bands)


@FEW
@given(h=st.integers(1, 5), w=st.integers(1, 5), bits=st.sampled_from([8, 16]), seed=st.integers(0, 2**31 - 1))
def test_cave_folder(fresh_dir, h, w, bits, seed):
    """A CAVE folder of 31 grey PNGs (Pillow) reads as the stack divided by the integer full scale."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    full = 2**bits - 1
    stack = rng.integers(0, full + 1, size=(31, h, w)).astype(np.uint16 if bits == 16 else np.uint8)
    d = fresh_dir() / "balloons_ms"
    d.mkdir()
    for i in range(31):
        Image.fromarray(stack[i]).save(d / f"balloons_ms_{i + 1:02d}.png")
    got, got_bands, _ = formats.read_cube(d)
    np.testing.assert_allclose(got, stack / full, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(got_bands.centers_nm, np.arange(400.0, 701.0, 10.0))


# ------------------------------------------------------------------------------------------------
# Captures: PNG, TIFF, NPY of 8/16-bit integers and floats
# ------------------------------------------------------------------------------------------------
@PROPS
@given(h=st.integers(1, 9), w=st.integers(1, 9), kind=st.sampled_from(["png8", "png16", "tif8", "tif16", "tif32f",
                                                                      "tif64f", "npy16", "npyf4", "npyf8"]),
       shape3=st.sampled_from([None, "first", "last"]), seed=st.integers(0, 2**31 - 1), name=NAMES)
def test_read_image_2d(fresh_dir, h, w, kind, shape3, seed, name):
    """A single-channel image written by Pillow, tifffile or numpy comes back with the stored values,
    (H, W), and the type's full scale (255, 65535; 1 for floats)."""
    import tifffile
    from PIL import Image

    # (1, N, 1) is both (1, H, W) with W = 1 and (H, W, 1) with H = 1: read as the first (the documented layout)
    assume(not (shape3 == "last" and h == 1))
    rng = np.random.default_rng(seed)
    dtype = {"png8": np.uint8, "png16": np.uint16, "tif8": np.uint8, "tif16": np.uint16, "tif32f": np.float32,
             "tif64f": np.float64, "npy16": np.uint16, "npyf4": np.float32, "npyf8": np.float64}[kind]
    if np.dtype(dtype).kind == "u":
        img = rng.integers(0, np.iinfo(dtype).max + 1, size=(h, w)).astype(dtype)
        full = float(np.iinfo(dtype).max)
    else:
        img = (rng.random((h, w)) * 3.0).astype(dtype)
        full = 1.0
    d = fresh_dir()
    if kind.startswith("png"):
        path = d / f"{name}.png"
        Image.fromarray(img).save(path)
    elif kind.startswith("tif"):
        path = d / f"{name}.tif"
        tifffile.imwrite(path, img, photometric="minisblack")  # (a 3-D array: tifffile decides which axes are H, W)
    else:
        path = d / f"{name}.npy"
        np.save(path, img[None] if shape3 == "first" else img[..., None] if shape3 == "last" else img)
    got = read_image_2d(path)
    assert got.data.shape == (h, w) and got.full_scale == full
    np.testing.assert_array_equal(got.data, img.astype(np.float64 if dtype == np.float64 else np.float32))


@PROPS
@given(h=st.integers(1, 9), w=st.integers(1, 9), black=st.floats(0, 500), span=st.floats(500, 60000),
       t_exp=st.floats(1e-6, 10.0), ratio=st.floats(0.25, 4.0), scale=st.floats(0.25, 2.0),
       period=st.sampled_from([None, 1, 2, 3, 5]), use_dark=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_preprocess_raw_closed_form(h, w, black, span, t_exp, ratio, scale, period, use_dark, seed):
    """g = (raw − dark) / (white − black) / flat_norm · (t_ref / t_exp) · scale, computed in float64 with
    numpy (flat_norm: flat − black, averaged over the period with the same-phase padding done by hand,
    over its mean)."""
    # an image smaller than the period has no window that sees every CFA phase: its flat is only "clipped to the
    # axis" (normalised_flat's docstring), with no closed form to hold it to
    assume(not period or min(h, w) >= period)
    rng = np.random.default_rng(seed)
    white = black + span
    raw = black + rng.uniform(0.05, 0.3, size=(h, w)) * span / (ratio * scale)
    dark = black + rng.uniform(-0.01, 0.01, size=(h, w)) * span if use_dark else None
    flat = black + rng.uniform(0.5, 1.0, size=(h, w)) * span
    corr = RawCorrection(black_level=black, white_level=white, dark=dark, flat=flat, flat_period=period,
                         exposure_s=t_exp, reference_exposure_s=t_exp * ratio, scale=scale)
    img, report = preprocess_raw(raw, 65535.0, corr, check_saturation=False, check_bit_depth=False, check_level=False)
    f = flat - black
    if period and period > 1:  # brute force: the mean over the m×m window of same-phase-padded pixels
        m = period

        def idx(k, n):
            return min(max(k if 0 <= k < n else (k % m if k < 0 else k - m * ((k - n) // m + 1)), 0), n - 1)

        lo, hi = -(m // 2), m - m // 2
        f = np.array([[np.mean([f[idx(y + a, h), idx(x + b, w)] for a in range(lo, hi) for b in range(lo, hi)])
                       for x in range(w)] for y in range(h)])
    f = f / f.mean()
    sub = raw - (dark if dark is not None else black)
    want = sub / (white - black) / f * ratio * scale
    np.testing.assert_allclose(img, want, rtol=2e-5, atol=1e-6 * np.abs(want).max())
    assert report["gain"] == pytest.approx(ratio * scale / (white - black), rel=1e-12)


@PROPS
@given(m=st.integers(2, 6), ny=st.integers(1, 4), nx=st.integers(1, 4), ry=st.integers(0, 5), rx=st.integers(0, 5),
       level=st.floats(10.0, 1e5), black=st.floats(0, 100), seed=st.integers(0, 2**31 - 1))
def test_flat_of_a_pure_cfa_pattern_is_one(m, ny, nx, ry, rx, level, black, seed):
    """A flat that is only the CFA's periodic pattern (no vignetting), averaged over that period, is 1
    everywhere, whatever the image's size (a multiple of the period or not, ≥ one period)."""
    rng = np.random.default_rng(seed)
    pattern = rng.uniform(0.2, 1.0, size=(m, m)) * level
    h, w = ny * m + min(ry, m - 1), nx * m + min(rx, m - 1)
    flat = black + np.tile(pattern, (ny + 1, nx + 1))[:h, :w]
    np.testing.assert_allclose(normalised_flat(flat, black, m), 1.0, rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# Atomic writers
# ------------------------------------------------------------------------------------------------
@PROPS
@given(name=NAMES, old=st.binary(max_size=64), h=st.integers(1, 6), w=st.integers(1, 6),
       seed=st.integers(0, 2**31 - 1))
def test_atomic_writers(fresh_dir, name, old, h, w, seed):
    """A write that fails midway leaves the old file byte for byte and no temporary; the writers'
    files (JSON, NPY, 16-bit PNG) read back in their real formats, at any name."""
    rng = np.random.default_rng(seed)
    d = fresh_dir()
    target = d / f"{name}.bin"
    target.write_bytes(old)
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"new" * 10)
            raise RuntimeError("interrupted")
    assert target.read_bytes() == old and sorted(p.name for p in d.iterdir()) == [target.name]
    obj = {"name": name, "values": rng.random(3).tolist()}
    write_json(d / f"{name}.json", obj)
    assert json.loads((d / f"{name}.json").read_text(encoding="utf-8")) == obj
    arr = rng.random((h, w))
    write_npy(d / f"{name}.npy", arr)
    np.testing.assert_array_equal(np.load(d / f"{name}.npy"), arr)
    img = rng.uniform(-0.2, 1.2, size=(h, w))
    write_png16(d / f"{name}.png", img)
    got = read_image_2d(d / f"{name}.png")
    np.testing.assert_array_equal(got.data, np.round(np.clip(img, 0, 1) * 65535))
    assert not [p for p in d.iterdir() if p.name.startswith(".")]


@PROPS
@given(c=st.integers(2, 10), h=st.integers(1, 5), w=st.integers(1, 5), code=st.sampled_from(["u2", "i2", "f4", "f8"]),
       interleave=st.sampled_from(["bsq", "bil", "bip"]), big=st.booleans(), use_bbl=st.booleans(),
       ignore=st.sampled_from([None, 0, 7, 1000]), use_gain=st.booleans(), use_offset=st.booleans(),
       rsf=st.sampled_from([None, 1.0, 10000.0, 0.5]), seed=st.integers(0, 2**31 - 1))
def test_envi_gain_offset_bbl_ignore_closed_form(fresh_dir, c, h, w, code, interleave, big, use_bbl, ignore, use_gain,
                                                 use_offset, rsf, seed):
    """value = (gain · stored + offset) / reflectance scale factor per band; values equal to the data ignore value
    are 0; bands marked 0 in bbl are dropped with their wavelengths; bands (listed shuffled) come back ascending
    with their planes. Reference: the same arithmetic in float64, value by value."""
    rng = np.random.default_rng(seed)
    chw = rng.integers(0, 12, size=(c, h, w)).astype(np.float64)  # small integers: the ignore value 7 occurs
    waves = np.round(rng.permutation(np.linspace(450.0, 850.0, c) + rng.uniform(-1, 1, c)), 3)
    good = np.ones(c, bool)
    if use_bbl:
        good[rng.choice(c, size=rng.integers(0, c - 1), replace=False)] = False
        assume(good.sum() >= 2 and not good.all())
    gain = np.round(rng.uniform(0.1, 3.0, c), 4) if use_gain else np.ones(c)
    offset = np.round(rng.uniform(0.0, 2.0, c), 4) if use_offset else np.zeros(c)
    ign = chw == ignore if ignore is not None else np.zeros(chw.shape, bool)
    assume(not ign[good].all())
    lines = [f"bbl = {{{', '.join(str(int(g)) for g in good)}}}" if use_bbl else "",
             f"data ignore value = {ignore}" if ignore is not None else "",
             f"data gain values = {{{', '.join(repr(float(g)) for g in gain)}}}" if use_gain else "",
             f"data offset values = {{{', '.join(repr(float(o)) for o in offset)}}}" if use_offset else "",
             f"reflectance scale factor = {rsf!r}" if rsf is not None else ""]
    d = fresh_dir()
    (d / "s.hdr").write_text(
        f"ENVI\nsamples = {w}\nlines = {h}\nbands = {c}\ndata type = {ENVI_CODES[code]}\ninterleave = {interleave}\n"
        f"byte order = {int(big)}\nwavelength = {{{', '.join(repr(float(v)) for v in waves)}}}\n"
        + "\n".join(x for x in lines if x) + "\n")
    disk = {"bsq": chw, "bil": chw.transpose(1, 0, 2), "bip": chw.transpose(1, 2, 0)}[interleave]
    np.ascontiguousarray(disk).astype(np.dtype(code).newbyteorder(">" if big else "<")).tofile(d / "s.img")
    got, bands, meta = formats.read_envi(d / "s.hdr")
    want = (gain[:, None, None] * chw + offset[:, None, None]) / (1.0 if rsf is None else rsf)
    want[ign] = 0.0
    order = [i for i in np.argsort(waves) if good[i]]
    np.testing.assert_allclose(got, want[order], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(bands.centers_nm, waves[order])
    if use_bbl:
        assert meta["bad_bands_nm"] == sorted(waves[~good].tolist())
    if use_gain or use_offset:
        np.testing.assert_array_equal(meta["data_gain_values"], gain[order])
        np.testing.assert_array_equal(meta["data_offset_values"], offset[order])


@PROPS
@given(grid=band_grids(min_bands=2, max_bands=33), data=st.data(), micrometres=st.booleans(),
       container=st.sampled_from(["mat5", "mat73", "h5"]))
def test_float32_band_lists_read_at_their_decimal(fresh_dir, grid, data, micrometres, container):
    """A band list stored as float32 (in nm, or µm below 30) reads as the decimals written (float32 453.3 is
    453.3 nm, not 453.29998779), in a MAT v5, MAT v7.3 or plain HDF5 file."""
    import h5py
    import scipy.io

    centres, _ = grid
    assume(centres.max() < 10000)
    centres = np.round(centres, 1)  # float32 holds 7 significant digits: 1 decimal of up to 4-digit nm, 4 of µm
    assume(np.all(np.diff(centres) > 0))
    cube = data.draw(cubes(Bands.from_centers(centres), dtype=np.float32))
    listed = (centres / 1000.0 if micrometres else centres).astype(np.float32)
    path = fresh_dir() / "s.mat"
    hwc = np.transpose(cube, (1, 2, 0))
    if container == "mat5":
        scipy.io.savemat(path, {"cube": hwc, "bands": listed[None, :]})
    elif container == "mat73":
        _write_mat73(path, {"cube": hwc, "bands": listed[None, :]})
    else:
        assume(cube.shape[2] != cube.shape[0])
        with h5py.File(path, "w") as f:
            f.create_dataset("cube", data=cube)
            f.create_dataset("wavelengths", data=listed)
    got, bands, _ = formats.read_cube(path)
    np.testing.assert_array_equal(bands.centers_nm, centres)
    np.testing.assert_array_equal(got, cube)


@PROPS
@given(grid=band_grids(min_bands=1, max_bands=24), data=st.data(),
       naming=st.sampled_from(["{}nm", "w{}nm", "S0.{}nm", "T.{}nm", "{}", "um", "range"]),
       extra=st.booleans())
def test_exr_round_trip(fresh_dir, grid, data, naming, extra):
    """An OpenEXR file (the OpenEXR package) with one float32 channel per band, named by its wavelength in any of
    the documented spellings (nm, µm, a band's edges), reads as the planes sorted by wavelength; non-spectral
    channels (R, S1 polarisation) are left out."""
    import OpenEXR

    centres, _ = grid
    assume(centres.max() <= 2600 and (naming != "um" or np.all(np.diff(np.round(centres, 1)) > 0)))
    if naming == "um":
        centres = np.round(centres, 1)  # 4 decimals of µm
    cube = data.draw(cubes(Bands.from_centers(centres), dtype=np.float32))
    cube = np.minimum(cube, 6e4)  # (float32 channels hold any float32; kept finite and moderate)

    def name(v):
        if naming == "um":
            return f"{v / 1000:.4f}um"
        if naming == "range":
            return f"{float(v) - 0.5}-{float(v) + 0.5}nm"
        return naming.format(float(v))  # the shortest decimal of the centre

    order = data.draw(st.permutations(range(centres.size)))
    channels = {name(centres[i]): OpenEXR.Channel(np.ascontiguousarray(cube[i])) for i in order}
    if extra:
        channels["R"] = OpenEXR.Channel(np.zeros(cube.shape[1:], np.float32))
        channels["S1.550nm"] = OpenEXR.Channel(np.ones(cube.shape[1:], np.float32))
    path = fresh_dir() / "s.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))
    got, bands, _ = formats.read_cube(path)
    np.testing.assert_array_equal(got, cube)
    np.testing.assert_allclose(bands.centers_nm, centres, rtol=0, atol=1e-9)


@PROPS
@given(h=st.integers(1, 9), w=st.integers(1, 9), level=st.floats(0.05, 1.0), black=st.floats(0, 1000),
       seed=st.integers(0, 2**31 - 1))
def test_auto_level_puts_the_percentile_at_the_level(h, w, level, black, seed):
    """auto_level: the corrected image's 99.9th percentile equals the level asked for, and the image is the
    black-subtracted capture times one gain (closed form: (raw − black) · level / P99.9(raw − black))."""
    rng = np.random.default_rng(seed)
    raw = black + rng.uniform(1.0, 4000.0, size=(h, w))
    img, report = preprocess_raw(raw, 65535.0, RawCorrection(black_level=black, auto_level=level),
                                 check_saturation=False, check_bit_depth=False, check_level=False)
    sub = raw.astype(np.float32).astype(np.float64) - black
    want = sub * level / np.percentile(sub, 99.9)
    np.testing.assert_allclose(img, want, rtol=1e-5)
    assert float(np.percentile(img, 99.9)) == pytest.approx(level, rel=1e-5)


# ------------------------------------------------------------------------------------------------
# Cubes
# ------------------------------------------------------------------------------------------------
@CORE_PROP
@given(seed=seeds, c=st.integers(1, 6), h=st.integers(1, 7), w=st.integers(1, 7),
       dtype=st.sampled_from([np.float64, np.float32, np.uint8, np.uint16, np.int32]), transpose=st.booleans())
def test_check_and_normalise_cube(seed, c, h, w, dtype, transpose):
    """check_cube: float32 C-contiguous, the same values (non-contiguous input too); normalised max is exactly 1."""
    rng = np.random.default_rng(seed)
    arr = (rng.random((c, w, h) if transpose else (c, h, w)) * 200 + 1).astype(dtype)
    if transpose:
        arr = arr.transpose(0, 2, 1)
    out = check_cube(arr)
    assert out.dtype == np.float32 and out.flags.c_contiguous and out.shape == (c, h, w)
    np.testing.assert_array_equal(out, arr.astype(np.float32))
    norm, peak = normalize_per_cube_max(out)
    assert peak == float(arr.astype(np.float32).max()) and norm.max() == 1.0 and norm.dtype == np.float32


@CORE_PROP
@given(seed=seeds, n=st.integers(2, 25), m=st.integers(1, 25))
def test_resample_cube_is_resample_spectra_per_pixel(seed, n, m):
    """resample_cube = resampling_matrix @ each pixel's spectrum (float64 reference), returned as float32."""
    rng = np.random.default_rng(seed)
    src = Bands.from_centers(random_grid(seed, n, 400.0, 10.0))
    dst = Bands(np.unique(rng.uniform(src.min_nm, src.max_nm, m)), rng.uniform(1, 40))
    cube = rng.random((n, 3, 4)).astype(np.float32)
    ref = np.einsum("dc,chw->dhw", resampling_matrix(src, dst), cube.astype(np.float64))
    out = resample_cube(cube, src, dst)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-7)


@CORE_PROP
@given(seed=seeds, dtype=st.sampled_from([torch.float16, torch.bfloat16, torch.float32, torch.float64]),
       c=st.integers(1, 4), h=st.integers(1, 5), w=st.integers(1, 5))
def test_check_cube_takes_a_tensor_of_any_float_dtype(seed, dtype, c, h, w):
    """check_cube of a torch tensor (bfloat16 included: it has no numpy type, a TypeError) = its float32 values."""
    t = torch.rand(c, h, w, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)
    out = check_cube(t)
    assert out.dtype == np.float32 and out.shape == (c, h, w)
    np.testing.assert_array_equal(out, t.float().numpy())


# -- previews ---------------------------------------------------------------------------------------------
def _preview_side(side: int, longest: int, max_side: int) -> int:
    """The documented preview size of one side: step×step blocks (step = ceil(longest / max_side)), at least
    one block (the whole side) when the side is shorter than a step."""
    step = max(1, math.ceil(longest / max_side))
    return max(1, side // step)


CUBES = st.tuples(st.integers(1, 8), st.integers(1, 70), st.integers(1, 70),
                  st.sampled_from(["random", "zero", "hot", "tiny", "huge"]))


@OUTPUT_PROPS
@given(spec=CUBES)
def test_previews_of_any_cube_are_finite_images_of_the_documented_size(spec):
    from hsicam.data.preview import preview_grey, preview_rgb, renderable

    c, h, w, kind = spec
    rng = np.random.default_rng(c * 1000 + h * 10 + w)
    cube = {"random": lambda: rng.random((c, h, w)), "zero": lambda: np.zeros((c, h, w)),
            "tiny": lambda: rng.random((c, h, w)) * 1e-37, "huge": lambda: rng.random((c, h, w)) * 3e38,
            "hot": lambda: np.zeros((c, h, w))}[kind]().astype(np.float32)
    if kind == "hot":
        cube[rng.integers(c), rng.integers(h), rng.integers(w)] = 1.0
    bands = Bands.from_centers(np.linspace(420.0, 720.0, c)) if c > 1 else Bands.from_centers([550.0])
    max_side = 16
    shape = (_preview_side(h, max(h, w), max_side), _preview_side(w, max(h, w), max_side), 3)
    grey = preview_grey(cube, max_side)
    assert grey.shape == shape and np.isfinite(grey).all() and grey.min() >= 0 and grey.max() <= 1
    if not renderable(bands):
        with pytest.raises(InputError, match="fewer than 2 bands"):
            preview_rgb(cube, bands, max_side)
        return
    if not cube.any():
        with pytest.raises(InputError, match="all zeros"):
            preview_rgb(cube, bands, max_side)
        return
    rgb = preview_rgb(cube, bands, max_side)
    assert rgb.shape == shape and np.isfinite(rgb).all()


def test_a_strip_cube_is_previewed(tmp_path):
    """A 4×1000 px cube (shorter than one 6-px block on its short side) crashed ``hsicam data show`` with
    numpy's "zero-size array to reduction operation maximum"; its contact sheet now holds a 1×166 render."""
    from PIL import Image

    from hsicam.data.preview import CONTACT_SHEET, preview_rgb, write_preview

    cube = np.random.default_rng(0).random((31, 4, 1000)).astype(np.float32)
    rgb = preview_rgb(cube, Bands.from_centers(np.linspace(400.0, 700.0, 31)))
    assert rgb.shape == (1, 166, 3) and np.isfinite(rgb).all()
    np.save(tmp_path / "strip.npy", cube)
    written = write_preview(tmp_path / "strip.npy", tmp_path / "out")
    assert (tmp_path / "out" / CONTACT_SHEET) in written
    for p in written:
        with Image.open(p) as im:
            im.load()
            assert min(im.size) > 0 and np.isfinite(np.asarray(im, dtype=np.float64)).all()
