"""Guards found by mutation testing of the capture and cube file readers and writers (data/images, cube,
estimates, formats, pipeline): each test kills a hand-made mutant (a swapped axis, a wrong interleave or byte
order, a dropped normalisation, an off-by-one window, a skipped branch) that the rest of the suite let through.
References are independent of the code under test: files written here byte by byte (numpy raw bytes and a
hand-written ENVI header), with h5py or Pillow; corrections computed in numpy; brute-force loops.
"""

from __future__ import annotations

import numpy as np
import pytest


# --------------------------------------------------------------------------------------------
# data/images.py
# --------------------------------------------------------------------------------------------
def test_cfa_flat_is_the_period_window_centred_on_each_pixel():
    """flat_period m (odd): each pixel's flat is the mean of the m×m window centred on it (every CFA phase once),
    so a vignetting ramp is kept at the pixel where it is; checked on interior pixels against a brute-force window
    mean (up to the common normalisation). A window one pixel off misplaces the vignetting by a pixel."""
    from hsicam.data.images import normalised_flat

    m, h, w = 3, 13, 17
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    vignette = 1.0 + 0.05 * xx + 0.03 * yy + 0.002 * xx * yy  # smooth, but not symmetric about any pixel
    cfa = np.tile(np.array([[0.5, 1.0, 1.5], [1.0, 1.5, 0.5], [1.5, 0.5, 1.0]]), (5, 6))[:h, :w]
    black = 64.0
    flat_dn = black + 1000.0 * vignette * cfa
    got = normalised_flat(flat_dn, black, m)
    r = m // 2
    ref = np.full((h, w), np.nan)
    for i in range(r, h - r):
        for j in range(r, w - r):
            ref[i, j] = (flat_dn[i - r:i + r + 1, j - r:j + r + 1] - black).mean()
    inner = np.isfinite(ref)
    ratio = got[inner] / ref[inner]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)


@pytest.mark.parametrize("shape", [(5, 7, 1), (1, 5, 7)])
def test_a_single_channel_npy_capture_with_a_unit_axis_is_read_as_its_pixels(tmp_path, shape):
    """(H, W, 1) and (1, H, W) arrays are the (H, W) image they hold, value for value."""
    from hsicam.data.images import read_image_2d

    pixels = np.arange(35, dtype=np.uint16).reshape(5, 7) * 100
    path = tmp_path / "capture.npy"
    np.save(path, pixels.reshape(shape))
    image = read_image_2d(path, "sensor image")
    assert image.data.shape == (5, 7) and image.full_scale == 65535.0
    np.testing.assert_array_equal(image.data, pixels.astype(np.float32))


# --------------------------------------------------------------------------------------------
# data/cube.py
# --------------------------------------------------------------------------------------------
def test_per_cube_max_normalisation_divides_by_the_maximum_over_all_bands():
    """The brightest sample anywhere in the cube (here in the last band) becomes 1."""
    from hsicam.data.cube import normalize_per_cube_max

    rng = np.random.default_rng(3)
    cube = rng.random((4, 6, 5)).astype(np.float32)
    cube[3, 2, 1] = 7.5
    out, peak = normalize_per_cube_max(cube)
    assert peak == 7.5 and out.dtype == np.float32
    np.testing.assert_allclose(out, cube.astype(np.float64) / 7.5, rtol=1e-6)
    assert out.max() == 1.0


# --------------------------------------------------------------------------------------------
# data/estimates.py
# --------------------------------------------------------------------------------------------
def test_an_older_reconstruct_output_is_recognised_only_with_its_preview_beside_it(tmp_path):
    """Before reconstruct named itself, its HDF5 held the capture and run ('source', 'run') and its ENVI header the
    description 'hsicam cube'; a user's own file can hold the same, so only the preview that reconstruct wrote
    beside it (<stem>_rgb.png) makes either one reconstruct's (which it may then replace)."""
    import h5py

    from hsicam.data.estimates import is_reconstruct_h5, reconstruct_envi_header

    h5 = tmp_path / "old.h5"
    with h5py.File(h5, "w") as f:  # our format's layout, written here with h5py
        f.create_dataset("cube", data=np.ones((3, 4, 4), np.float32))
        f.create_dataset("bands_nm", data=np.array([500.0, 550.0, 600.0]))
        f.attrs["format"] = "hsicam-cube"
        f.attrs["metadata_json"] = '{"run": "runs/a", "source": "capture.png"}'
    hdr = tmp_path / "old.hdr"
    hdr.write_text("ENVI\ndescription = {hsicam cube}\nsamples = 4\nlines = 4\nbands = 3\ndata type = 4\n"
                   "interleave = bsq\nbyte order = 0\nwavelength = {500, 550, 600}\n")
    (tmp_path / "old.img").write_bytes(np.ones((3, 4, 4), "<f4").tobytes())
    assert not is_reconstruct_h5(h5) and reconstruct_envi_header(hdr) is None
    (tmp_path / "old_rgb.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    assert is_reconstruct_h5(h5) and reconstruct_envi_header(hdr)["description"] == "{hsicam cube}"


# --------------------------------------------------------------------------------------------
# data/formats.py
# --------------------------------------------------------------------------------------------
def _envi(folder, chw: np.ndarray, header_lines: str, dtype: str = "<f4", code: int = 4, interleave: str = "bsq",
          order: int = 0, offset: int = 0):
    """An ENVI pair written here: a hand-written header and the raw bytes of ``chw`` (C, H, W) in ``interleave``."""
    c, h, w = chw.shape
    hdr = folder / "scene.hdr"
    hdr.write_text(f"ENVI\nsamples = {w}\nlines = {h}\nbands = {c}\nheader offset = {offset}\ndata type = {code}\n"
                   f"interleave = {interleave}\nbyte order = {order}\n{header_lines}")
    disk = {"bsq": chw, "bil": chw.transpose(1, 0, 2), "bip": chw.transpose(1, 2, 0)}[interleave]
    (folder / "scene.img").write_bytes(b"\0" * offset + np.ascontiguousarray(disk).astype(dtype).tobytes())
    return hdr


def test_envi_fwhm_in_micrometres_is_converted_with_the_wavelengths(tmp_path):
    """'wavelength units = Micrometers' applies to 'fwhm' too: 0.01 µm is a 10 nm band."""
    from hsicam.data.formats import read_envi

    cube = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)
    hdr = _envi(tmp_path, cube, "wavelength units = Micrometers\nwavelength = {0.5, 0.55, 0.6}\n"
                               "fwhm = {0.01, 0.012, 0.015}\n")
    got, bands, _ = read_envi(hdr)
    np.testing.assert_allclose(bands.centers_nm, [500.0, 550.0, 600.0], atol=1e-9)
    np.testing.assert_allclose(bands.fwhm_nm, [10.0, 12.0, 15.0], atol=1e-9)
    np.testing.assert_array_equal(got, cube)


def test_cave_8bit_bands_are_divided_by_255_and_a_colour_band_gives_its_first_channel(tmp_path):
    """CAVE PNGs (written here with Pillow) are divided by their own type's full scale (255 for 8 bit), and a band
    stored as RGB contributes its red (first) channel."""
    from PIL import Image

    from hsicam.data.formats import read_cave

    rng = np.random.default_rng(5)
    planes = rng.integers(0, 256, size=(31, 6, 8), dtype=np.uint8)
    scene = tmp_path / "balloons_ms"
    scene.mkdir()
    for i in range(31):
        name = scene / f"balloons_ms_{i + 1:02d}.png"
        if i == 7:  # one colour band: R holds the band, G and B something else
            rgb = np.stack([planes[i], 255 - planes[i], np.zeros_like(planes[i])], axis=-1)
            Image.fromarray(rgb).save(name)
        else:
            Image.fromarray(planes[i]).save(name)
    cube, bands, _ = read_cave(scene)
    np.testing.assert_allclose(cube, planes.astype(np.float64) / 255.0, rtol=1e-6, atol=0)
    np.testing.assert_allclose(bands.centers_nm, np.arange(400.0, 701.0, 10.0))


def test_envi_fractional_ignore_value_flags_nothing_in_an_integer_file(tmp_path):
    """'data ignore value = 0.5' in a uint16 file: no stored integer holds it, so no value is no-data; the stored
    zeros are data and get the band's offset like every other value (value = gain · stored + offset)."""
    from hsicam.data.formats import read_envi

    stored = np.array([[[0, 3], [5, 0]], [[2, 0], [0, 7]]], dtype=np.uint16)
    hdr = _envi(tmp_path, stored, "wavelength = {500, 600}\ndata ignore value = 0.5\n"
                                  "data gain values = {2, 3}\ndata offset values = {1, 4}\n", dtype="<u2", code=12)
    got, _, meta = read_envi(hdr)
    ref = stored * np.array([2.0, 3.0])[:, None, None] + np.array([1.0, 4.0])[:, None, None]
    np.testing.assert_array_equal(got, ref.astype(np.float32))
    assert meta["ignored_pixels"] == 0


def test_envi_float_ignore_value_matches_the_stored_float32_value(tmp_path):
    """'data ignore value = 0.1' in a float32 file flags the stored float32 0.1 (which is not the float64 0.1)."""
    from hsicam.data.formats import read_envi

    stored = np.array([[[0.1, 0.5], [0.25, 0.1]], [[0.75, 0.1], [0.3, 0.2]]], dtype=np.float32)
    hdr = _envi(tmp_path, stored, "wavelength = {500, 600}\ndata ignore value = 0.1\n")
    got, _, meta = read_envi(hdr)
    np.testing.assert_array_equal(got, np.where(stored == np.float32(0.1), 0.0, stored).astype(np.float32))
    assert meta["ignored_pixels"] == 3


def test_a_float32_band_list_in_our_hdf5_is_read_at_its_decimal(tmp_path):
    """bands_nm stored as float32 (by h5py here) is read at the decimal its writer meant: 453.3, not
    453.29998779…, so it matches MST's grid exactly."""
    import h5py

    from hsicam.data.formats import MST_28_NM, read_hsicam_h5

    path = tmp_path / "f32.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("cube", data=np.ones((28, 3, 3), np.float32))
        f.create_dataset("bands_nm", data=np.asarray(MST_28_NM, dtype=np.float32))
        f.attrs["format"] = "hsicam-cube"
    _, bands, _ = read_hsicam_h5(path)
    assert bands.centers_nm.tolist() == list(MST_28_NM)


def test_write_envi_keeps_the_band_centres_and_widths_to_the_readers_decimals_beyond_1000_nm(tmp_path):
    """write_envi → read_envi gives back centres and FWHM to NM_DECIMALS (3) decimals of a nm above 1000 nm too
    (printed with 6 significant digits, 1234.567 nm came back as 1234.57)."""
    from hsicam.data.formats import read_envi, write_envi
    from hsicam.spectral import Bands

    centres, widths = [912.125, 1234.567, 1500.25], [5.125, 12.375, 20.5]
    hdr, _ = write_envi(tmp_path / "swir.hdr", np.ones((3, 2, 2), np.float32), Bands(centres, widths))
    line = next(l for l in hdr.read_text().splitlines() if l.startswith("wavelength ="))
    assert [float(v) for v in line.split("{")[1].rstrip("}").split(",")] == centres
    _, bands, _ = read_envi(hdr)
    assert bands.centers_nm.tolist() == centres and bands.fwhm_nm.tolist() == widths


# --------------------------------------------------------------------------------------------
# data/pipeline.py
# --------------------------------------------------------------------------------------------
def test_patch_source_names_the_scene_of_every_item_and_none_past_the_end(tmp_path):
    """Items 0 … len − 1 of a PatchDataset come from its (only) scene; index len is outside it: None, no IndexError."""
    from hsicam.data.datasets import PatchDataset, SceneDataset
    from hsicam.data.pipeline import patch_source
    from hsicam.spectral import Bands

    path = tmp_path / "scene.npy"
    np.save(path, np.full((3, 12, 12), 0.5, np.float32))
    bands = Bands.from_centers([500.0, 550.0, 600.0])
    ds = PatchDataset(SceneDataset([path], bands, source_bands=bands), 8, patches_per_epoch=5)
    assert [patch_source(ds, k) for k in range(5)] == [path] * 5
    assert patch_source(ds, 5) is None and patch_source(ds, -1) is None


def test_preload_limit_is_in_mebibytes(tmp_path):
    """data.preload_max_mb counts MiB (2^20 bytes): 1.04 MB of scenes (under 1 MiB) are preloaded at a 1 MiB limit."""
    import dataclasses

    from hsicam.config import DataConfig
    from hsicam.data.pipeline import _should_preload

    path = tmp_path / "scene.bin"
    path.write_bytes(b"\0" * 1_040_000)  # > 10^6 bytes, < 2^20
    cfg = dataclasses.replace(DataConfig(), preload=None, preload_max_mb=1.0)
    assert _should_preload(cfg, [path])
    path.write_bytes(b"\0" * (2**20 + 1))
    assert not _should_preload(cfg, [path])
