"""Guards found by mutation testing of the capture and cube file readers/writers (data/images, cube, estimates,
formats, pipeline) and of the remaining models and solvers (RDN, the Choi prior, receptive-field bounds, DeSCI,
Choi's ADMM): each test kills a hand-made mutant (a swapped axis, a wrong interleave or byte order, a dropped
normalisation, an off-by-one window, a skipped branch) that the rest of the suite let through. References are
independent of the code under test: files written here byte by byte (numpy raw bytes and a hand-written ENVI
header), with h5py or scipy.io.savemat; corrections computed in numpy; brute-force loops.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch



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


# --------------------------------------------------------------------------------------------
# models/rdn.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("window", [3, 5])
def test_rdn_context_adds_half_the_demosaic_window_to_the_conv_reach(window):
    """Receptive radius by counting 3×3 convolutions (sfe1, sfe2, every dense layer, global fusion 3×3, output:
    4 + D·C px) plus the demosaic's own reach, half its (odd) box width."""
    from hsicam.models.rdn import RDNReconstructor

    d, c = 2, 3
    net = RDNReconstructor(4, demosaic_input=True, window=window, blocks=d, features=8, growth=4, layers_per_block=c)
    assert net.context_px == 4 + d * c + window // 2


def test_rdn_on_the_back_projection_starts_as_its_band_mean_in_every_band():
    """backprojection_input: the untrained network (output conv at zero) returns, in every band, the mean of the
    C input bands at that pixel."""
    from hsicam.models.rdn import RDN, RDNReconstructor

    torch.manual_seed(0)
    net = RDNReconstructor(5, backprojection_input=True, blocks=1, features=8, growth=4)
    x = torch.rand(2, 5, 6, 7)
    out = RDN.forward(net, x)  # the network on its input (the back-projection needs a camera, not tested here)
    np.testing.assert_allclose(out.detach().numpy(), x.mean(1, keepdim=True).expand(-1, 5, -1, -1).numpy(),
                               rtol=1e-6, atol=1e-7)


# --------------------------------------------------------------------------------------------
# models/context.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("padding", ["valid", "same", 0, 1, 2])
def test_conv_reach_is_the_farthest_input_pixel_an_output_pixel_depends_on(padding):
    """Brute force by autograd: the output pixel at (i, j) of a 3×5 conv depends on input pixels up to conv_reach px
    away from (i, j), on some side of some axis (valid padding: all of them after the pixel)."""
    from torch import nn

    from hsicam.models.context import conv_reach

    torch.manual_seed(0)
    conv = nn.Conv2d(1, 1, (3, 5), padding=padding)
    with torch.no_grad():
        conv.weight.fill_(1.0)
    x = torch.rand(1, 1, 21, 21, requires_grad=True)
    i = j = 8
    conv(x)[0, 0, i, j].backward()
    ys, xs = torch.nonzero(x.grad[0, 0], as_tuple=True)
    measured = int(max((ys - i).abs().max(), (xs - j).abs().max()))
    assert conv_reach(conv) == measured


# --------------------------------------------------------------------------------------------
# models/priors.py
# --------------------------------------------------------------------------------------------
def test_the_prior_encoder_pads_by_reflection():
    """The encoder is 3×3 convolutions with reflect padding and ReLU between them: recomputed layer by layer with
    F.pad(mode='reflect') + F.conv2d, borders included (zero padding darkens the border pixels)."""
    import torch.nn.functional as F

    from hsicam.models.priors import SpectralAutoencoder

    torch.manual_seed(1)
    prior = SpectralAutoencoder(3, features=4, latent=5, layers=3)
    x = torch.rand(2, 3, 6, 7) + 0.5
    convs = [mod for mod in prior.encoder if isinstance(mod, torch.nn.Conv2d)]
    ref = x
    for k, conv in enumerate(convs):
        ref = F.conv2d(F.pad(ref, (1, 1, 1, 1), mode="reflect"), conv.weight, conv.bias)
        if k < len(convs) - 1:
            ref = ref.relu()
    torch.testing.assert_close(prior.encode(x), ref, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------------------------
# solvers/desci.py
# --------------------------------------------------------------------------------------------
def test_wnnm_groups_equal_a_numpy_svd_with_the_closed_form_shrinkage():
    """Each group Y (d × K): mean column removed, SVD (numpy), singular values s shrunk to
    (s − ε + √((s + ε)² − 4w)) / 2 where the discriminant is positive (else 0), w = c·σ²(√d + √K)²/4, mean put back."""
    from hsicam.solvers.desci import wnnm_groups

    rng = np.random.default_rng(7)
    g, d, k, sigma, c, eps = 3, 12, 6, 0.1, 1.3, 1e-8
    low = rng.random((g, d, 2)) @ rng.random((g, 2, k))  # rank 2 + noise: some values kept, some removed
    groups = low + sigma * rng.standard_normal((g, d, k))
    got = wnnm_groups(torch.from_numpy(groups), sigma, c).numpy()
    w = c * sigma**2 * (np.sqrt(d) + np.sqrt(k)) ** 2 / 4
    for i in range(g):
        mean = groups[i].mean(axis=1, keepdims=True)
        u, s, vt = np.linalg.svd(groups[i] - mean, full_matrices=False)
        disc = (s + eps) ** 2 - 4 * w
        shrunk = np.where(disc > 0, (s - eps + np.sqrt(np.maximum(disc, 0))) / 2, 0.0)
        assert 0 < np.count_nonzero(shrunk) < k  # the test exercises both branches
        np.testing.assert_allclose(got[i], u @ np.diag(shrunk) @ vt + mean, rtol=1e-7, atol=1e-9)


# --------------------------------------------------------------------------------------------
# solvers/choi.py
# --------------------------------------------------------------------------------------------
def _small_cassi(bands: int = 4):
    from hsicam.cameras import build_camera
    from hsicam.config import load_config

    cfg = load_config(overrides=["bands.start_nm=500", f"bands.stop_nm={500 + 20 * (bands - 1)}", "bands.step_nm=20",
                                 "camera.kind=dd_cassi"])
    return build_camera(cfg).to(torch.float64)


def test_prior_residual_is_half_the_squared_distance_to_the_prior():
    """½‖z − R(z)‖² per cube, for a prior R(z) = z/2 + 0.1: ½·Σ(z/2 − 0.1)²."""
    from hsicam.solvers.choi import prior_residual

    z = torch.rand(3, 2, 4, 5, dtype=torch.float64)
    got = prior_residual(lambda t: 0.5 * t + 0.1, z)
    torch.testing.assert_close(got, 0.5 * ((0.5 * z - 0.1) ** 2).sum(dim=(1, 2, 3)))


@pytest.mark.parametrize("tv_weight", [0.0, 0.02])
def test_choi_admm_with_an_identity_prior_is_the_closed_form_x_update_then_the_tv_prox(tv_weight):
    """With R = identity (an untrained autoencoder) and τ1 = 0, one proximal-gradient step of size 1/ρ lands on
    w = x + u, so each iteration is scaled-form ADMM: the exact x-update x = v + Φᵀ((y − Φv)/m / (diag(ΦΦᵀ)/m + ρ))
    at v = z − u (m the mean of diag ΦΦᵀ), the TV prox of w at weight τ2/ρ, u += x − z; ρ grows by rho_growth."""
    from hsicam.config import ChoiConfig
    from hsicam.models.priors import SpectralAutoencoder
    from hsicam.solvers.choi import admm_prior
    from hsicam.solvers.common import tv_denoise

    torch.manual_seed(0)
    cam = _small_cassi(4)
    truth = torch.rand(1, 4, 12, 12, dtype=torch.float64)
    y = cam.A(truth)
    prior = SpectralAutoencoder(4, features=2, latent=2, layers=2).double()
    s = ChoiConfig(iterations=3, rho=0.7, rho_growth=1.5, prior_weight=0.0, tv_weight=tv_weight, inner_steps=1,
                   init_iterations=0)
    got = admm_prior(cam, y, prior, s, x0=torch.zeros_like(truth))
    phi = cam.gram_diagonal(y)
    m = phi.mean()
    z, u, rho = torch.zeros_like(truth), torch.zeros_like(truth), 0.7
    for _ in range(3):  # scaled-form ADMM (u stays 0 without TV)
        v = z - u
        x = v + cam.A_adjoint((y - cam.A(v)) / m / (phi / m + rho))
        z = tv_denoise(x + u, tv_weight / rho, 5)
        u = u + x - z
        rho *= 1.5
    torch.testing.assert_close(got, z, rtol=1e-9, atol=1e-12)


def test_choi_minimum_norm_start_fits_the_measurement():
    """No GAP-TV start and no iteration: the start Φᵀ(y ⊘ diag ΦΦᵀ) reproduces y exactly (ΦΦᵀ is diagonal)."""
    from hsicam.config import ChoiConfig
    from hsicam.models.priors import SpectralAutoencoder
    from hsicam.solvers.choi import admm_prior

    torch.manual_seed(0)
    cam = _small_cassi(4)
    y = cam.A(torch.rand(1, 4, 12, 12, dtype=torch.float64))
    prior = SpectralAutoencoder(4, features=2, latent=2, layers=2).double()
    x = admm_prior(cam, y, prior, ChoiConfig(iterations=0, init_iterations=0))
    torch.testing.assert_close(cam.A(x), y, rtol=1e-9, atol=1e-12)


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
