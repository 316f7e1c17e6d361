"""Items earlier reviews noticed and left alone: a TIFF page that holds no image, NPY format 3.0, a held-out
source whose spectra are zero on the bands, a material table short of the camera's wavelengths."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from hsicam.errors import InputError


# --- data/images.py: a TIFF whose first page holds no image ---------------------------------------------------------

def _tiff(entries: list[tuple[int, int, int, int]]) -> bytes:
    """A little-endian TIFF of one IFD with ``entries`` (tag, type, count, value), written after the TIFF 6.0
    specification: header, IFD at offset 8, no next IFD."""
    ifd = struct.pack("<H", len(entries))
    for tag, typ, count, value in entries:
        ifd += struct.pack("<HHII", tag, typ, count, value)
    return b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0)


@pytest.mark.parametrize("entries, says", [
    ([], "the first TIFF page has no tags (no width, height or pixel data): corrupt, or not an image"),
    ([(305, 2, 4, int.from_bytes(b"abc\x00", "little"))],  # Software "abc" only
     "the first TIFF page has no image: its ImageWidth and ImageLength tags are missing (corrupt, or not an image)"),
    ([(256, 4, 1, 4), (257, 4, 1, 4), (258, 3, 1, 16)],  # 4×4, 16 bits, no strips
     "the first TIFF page has no pixel data: its StripOffsets (or TileOffsets) tag is missing (corrupt, or not an "
     "image)"),
])
def test_a_tiff_whose_first_page_holds_no_image_says_what_the_file_lacks(tmp_path, entries, says):
    """A page with no tags was refused as "image must be 2-D, got shape ()", one without width and height as an
    "empty image (shape (0, 0))", one without strips with tifffile's "missing data offset"."""
    import tifffile

    from hsicam.data.images import read_image_2d

    path = tmp_path / "odd.tif"
    path.write_bytes(_tiff(entries))
    with tifffile.TiffFile(path) as tf:  # a TIFF with one page, as tifffile reads it
        assert len(tf.pages) == 1 and len(tf.pages[0].tags) == len(entries)
    with pytest.raises(InputError) as exc:
        read_image_2d(path, "sensor image")
    assert str(exc.value) == f"{path}: {says}"


def test_a_tiff_with_its_tags_and_strip_still_reads(tmp_path):
    """The same hand-written TIFF with its strip (4×4 uint16) reads back as written."""
    from hsicam.data.images import read_image_2d

    image = np.arange(16, dtype="<u2").reshape(4, 4) * 1000
    entries = [(256, 4, 1, 4), (257, 4, 1, 4), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8 + 2 + 12 * 9 + 4), (277, 3, 1, 1), (278, 4, 1, 4), (279, 4, 1, image.nbytes)]
    (tmp_path / "ok.tif").write_bytes(_tiff(entries) + image.tobytes())
    got = read_image_2d(tmp_path / "ok.tif", "sensor image")
    np.testing.assert_array_equal(got.data, image.astype(np.float32))


# --- data/formats.py: NPY format version 3.0 -------------------------------------------------------------------------

def test_an_npy_of_format_version_3_reads_as_np_load_reads_it(tmp_path):
    """numpy's format 3.0 is 2.0 with a UTF-8 header; np.load reads a plain float cube saved as 3.0, which
    npy_header and read_cube refused: "unsupported NPY format version 3.0"."""
    from hsicam.data.formats import npy_header, read_cube

    cube = np.random.default_rng(3).random((4, 5, 6)).astype(np.float32)
    path = tmp_path / "v3.npy"
    with open(path, "wb") as fh:
        np.lib.format.write_array(fh, cube, version=(3, 0))
    assert path.read_bytes()[:8] == b"\x93NUMPY\x03\x00"
    ref = np.load(path, allow_pickle=False)
    assert npy_header(path) == (ref.shape, ref.dtype)
    data, _, meta = read_cube(path)
    assert meta["format"] == "npy"
    np.testing.assert_array_equal(data, ref)


def test_an_npy_of_an_unknown_format_version_is_still_refused_by_its_version(tmp_path):
    from hsicam.data.formats import npy_header

    path = tmp_path / "v4.npy"
    with open(path, "wb") as fh:
        np.lib.format.write_array(fh, np.zeros((2, 3, 4), np.float32), version=(2, 0))
    data = bytearray(path.read_bytes())
    data[6] = 4  # major version 4: np.load refuses it too
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError):
        np.load(path)
    with pytest.raises(InputError) as exc:
        npy_header(path)
    assert str(exc.value) == f"{path}: unsupported NPY format version 4.0"


# --- data/spectral_sources.py: the Otsu model's black pixel (documented, not changed) ---------------------------------

def test_the_otsu_model_departs_from_colour_science_only_at_black_as_its_docstring_says():
    """XYZ = 0 takes the D65 white point's chromaticity (colour-science: xy (0, 0), another cluster): the spectra
    differ by up to 0.03 there and nowhere else. Behaviour kept (the synthetic scenes are made with it)."""
    colour = pytest.importorskip("colour")
    from hsicam.data.spectral_sources import OtsuModel, spectral_library
    from hsicam.spectral import Bands

    o = spectral_library(Bands.paper()).otsu
    ref = colour.XYZ_to_sd(np.zeros(3), method="Otsu 2018").values
    d65 = np.array([0.3127, 0.3290, 1 - 0.3127 - 0.3290]) / 0.3290
    dim = colour.XYZ_to_sd(1e-12 * d65, method="Otsu 2018").values
    black = o.reflectance(np.zeros((1, 3)))[0]
    np.testing.assert_allclose(black, dim, atol=1e-9)  # the limit of dim D65 greys, computed by colour-science
    assert 0.02 < np.abs(black - ref).max() <= 0.03
    assert "XYZ = 0" in OtsuModel.__doc__ and "differ by up to 0.03" in OtsuModel.__doc__


# --- data/spectral_sources.py: a held-out source whose lamps are dark on the bands ------------------------------------

@pytest.mark.filterwarnings("ignore:Aligning", "ignore:.*shape could not be honoured", "ignore:.*Interpolating")
def test_a_held_out_source_dark_on_every_band_is_refused_as_dark_not_as_out_of_range(monkeypatch):
    """A lamp measured over 380-780 nm with no output below 560 nm spans the 400-440 nm grid but is 0 on it; a
    held-out source made only of it was refused as "kinoton: 1 spectra do not span the grid". The manifest's
    not_used_out_of_range still lists it (cache keys depend on it)."""
    colour = pytest.importorskip("colour")
    from colour.colorimetry.datasets.light_sources import sds as light_sources

    from hsicam.data import spectral_sources as ss
    from hsicam.spectral import Bands, fine_grid

    wl = np.arange(380.0, 781.0, 5.0)
    dark = colour.SpectralDistribution(np.where(wl >= 560.0, 1.0, 0.0), wl)
    bands = Bands.uniform(400, 440, 10)
    monkeypatch.setattr(light_sources, "SDS_LIGHT_SOURCES_COMMON", {"Dark lamp": dark})
    ss._library_cached.cache_clear()
    try:
        lib = ss.spectral_library(bands)
        fine = fine_grid(bands)
        assert wl[0] <= fine[0] and wl[-1] >= fine[-1]  # the lamp spans the grid ...
        assert not (ss.band_matrix(bands, fine) @ np.interp(fine, wl, dark.values)).any()  # ... and is 0 on it
        assert lib.sources["not_used_out_of_range"]["kinoton"] == ["Dark lamp"]  # manifest field unchanged
        with pytest.raises(ss.NoHeldOutSpectra) as exc:
            ss.split_library(lib, "kinoton,pmc", "heldout")
        n_pmc = len(lib.sources["not_used_out_of_range"]["pmc"])  # PMC's 400-700 nm do not reach 387 nm
        assert f"(kinoton: 1 spectra are 0 on every band; pmc: {n_pmc} spectra do not span the grid)" in str(exc.value)
    finally:
        ss._library_cached.cache_clear()  # the next library is built of colour-science's own lamps


# --- spectral/materials.py + cameras: a material table short of the camera's wavelengths names its config key -------

@pytest.mark.parametrize("key, overrides", [
    ("camera.doe.material", []),
    ("camera.lens.material", ["camera.lens.model=singlet"]),
    ("camera.cassi.prism_material", ["camera.kind=dd_cassi", "camera.cassi.dispersion=prism"]),
])
def test_a_material_table_short_of_the_bands_names_the_config_key_that_chose_it(tmp_path, key, overrides):
    """A table covering 450-700 nm (the design wavelength 587.6 nm inside it) and tiny's bands beyond it: the camera
    named the file and the wavelengths but not the key (`--set camera.doe.material=glass.csv`)."""
    from hsicam.cameras import build_camera
    from hsicam.config import load_config

    table = tmp_path / "glass.csv"
    table.write_text("wavelength_nm,n\n450,1.47\n700,1.45\n", encoding="utf-8")
    cfg = load_config("tiny", overrides=overrides + [f"{key}={table}"])  # accepted: the file is not opened here
    centres = cfg.bands.to_bands().centers_nm
    assert cfg.camera.psf.band_samples == 1 and centres.min() < 450  # the PSF is computed at the band centres
    with pytest.raises(InputError) as exc:
        build_camera(cfg)
    assert str(exc.value) == (f"{key}: {table}: material 'glass' is tabulated for 450-700 nm only, but its "
                              f"refractive index is needed at {centres.min():g}-{centres.max():g} nm")


def test_a_table_built_in_memory_still_names_only_itself():
    from hsicam.spectral import TabulatedMaterial, get_material

    assert get_material("fused_silica", "camera.doe.material").n(550.0) == pytest.approx(1.45991, abs=1e-5)
    with pytest.raises(InputError) as exc:
        TabulatedMaterial(np.array([400.0, 700.0]), np.array([1.5, 1.4]), name="mine").n(380.0)
    assert str(exc.value) == "material 'mine' is tabulated for 400-700 nm only, but its refractive index is needed at 380 nm"


def test_an_envi_data_file_without_its_header_says_the_header_is_missing(tmp_path):
    """`hsicam data show out.img` of a data file whose .hdr was lost (or not copied) said only "unknown format";
    a file of another name keeps the plain refusal."""
    from hsicam.data.formats import detect_format

    (tmp_path / "out.img").write_bytes(bytes(range(200)))
    (tmp_path / "notes.xyz").write_bytes(bytes(range(200)))
    with pytest.raises(InputError) as exc:
        detect_format(tmp_path / "out.img")
    assert str(exc.value) == (f"{tmp_path / 'out.img'}: unknown format (not our HDF5, MAT v5/v7.3, NPY, OpenEXR, ENVI "
                              "or a CAVE folder); if it is an ENVI data file, its header is missing: no ENVI out.hdr "
                              "next to it")
    with pytest.raises(InputError) as exc:
        detect_format(tmp_path / "notes.xyz")
    assert str(exc.value).endswith("unknown format (not our HDF5, MAT v5/v7.3, NPY, OpenEXR, ENVI or a CAVE folder)")
