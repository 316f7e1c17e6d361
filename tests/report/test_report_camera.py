"""PSF figure helpers: encircled energy, RMS radius and the automatic crop against closed forms."""

import imageio.v3 as iio
import numpy as np
import pytest

from hsicam.report.camera import (
    encircled_energy,
    encircled_fraction_in_square,
    plot_psf_montage,
    psf_crop_px,
    rms_radius_px,
)
from hsicam.spectral import Bands


def gaussian_stack(sigmas, k=81):
    yy, xx = np.mgrid[:k, :k] - k // 2
    out = np.stack([np.exp(-(yy**2 + xx**2) / (2 * s * s)) for s in sigmas])
    return out / out.sum(axis=(-2, -1), keepdims=True)


def test_encircled_energy_of_a_gaussian_follows_the_rayleigh_law():
    # 2-D Gaussian: EE(r) = 1 − exp(−r²/2σ²); pixel centres inside r approximate the disc
    sigma = 4.0
    psf = gaussian_stack([sigma])
    radii = np.array([4.0, 8.0, 12.0, 20.0])
    ee = encircled_energy(psf, radii)[0]
    np.testing.assert_allclose(ee, 1 - np.exp(-radii**2 / (2 * sigma**2)), atol=0.03)
    assert np.all(np.diff(encircled_energy(psf, np.arange(0, 40.0))[0]) >= 0)


def test_rms_radius_of_a_gaussian_and_of_a_point():
    psf = gaussian_stack([2.0, 5.0])
    np.testing.assert_allclose(rms_radius_px(psf), np.sqrt(2) * np.array([2.0, 5.0]), rtol=0.01)
    point = np.zeros((1, 21, 21))
    point[0, 10, 10] = 1.0
    assert rms_radius_px(point)[0] == 0.0
    assert encircled_energy(point, np.array([0.0]))[0, 0] == 1.0


def test_crop_holds_every_band_and_the_light_lost_outside_the_kernel_is_not_counted():
    k = 81
    psf = np.zeros((2, k, k))
    psf[0, 40, 40] = 0.5  # physical normalisation: half of this band's light is outside the kernel
    psf[1, 40, 40] = 0.7
    psf[1, 40, 40 + 20] = 0.3  # an order 20 px off axis
    assert psf_crop_px(psf[:1]) == 15  # the minimum
    assert psf_crop_px(psf) == 41  # must hold the order at +20 px: 2·20 + 1
    assert psf_crop_px(psf, fraction=0.6) == 15


def test_psf_figure_is_written(tmp_path):
    bands = Bands.uniform(420, 720, 50, 10)
    psf = gaussian_stack(np.linspace(1, 6, len(bands)), k=41)
    plot_psf_montage(psf, bands, tmp_path / "psf.png")
    img = iio.imread(tmp_path / "psf.png")
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 300
    with pytest.raises(ValueError, match="radii"):
        encircled_energy(np.zeros((1, 5, 5)), np.array([[1.0]]))
    with pytest.raises(ValueError, match="stack"):
        encircled_energy(np.zeros((5, 5)), np.array([1.0]))


def test_montage_crops_a_sharp_core_with_a_faint_wide_halo_to_the_core(tmp_path):
    # a trained quick DOE: ~88 % of the light in a 3x3 core, ~10 % spread thinly to the kernel's edge; a crop
    # holding 99 % of it would show a dot in a 103 px square
    k = 141
    yy, xx = np.mgrid[:k, :k] - k // 2
    halo = np.exp(-np.hypot(yy, xx) / 40.0)
    halo *= 0.10 / halo.sum()
    psf = np.repeat(halo[None], 3, axis=0)
    psf[:, k // 2 - 1 : k // 2 + 2, k // 2 - 1 : k // 2 + 2] += 0.88 / 9
    assert psf_crop_px(psf, fraction=0.99) > 100
    crop = plot_psf_montage(psf, Bands.uniform(420, 720, 150, 10), tmp_path / "psf.png")
    assert crop == psf_crop_px(psf, fraction=0.9) and crop < 41
    assert np.all(encircled_fraction_in_square(psf, crop) >= 0.9)
    assert np.all(encircled_fraction_in_square(psf, crop - 2) < 0.9) or crop == 15
    # a diffuser keeps a crop wide enough for 90 % of its light, and an explicit crop is honoured
    wide = gaussian_stack([15.0, 20.0], k=141)
    assert plot_psf_montage(wide, Bands.uniform(420, 720, 300, 10), tmp_path / "wide.png") == psf_crop_px(wide, 0.9)
    assert psf_crop_px(wide, 0.9) > 60
    assert plot_psf_montage(wide, Bands.uniform(420, 720, 300, 10), tmp_path / "w2.png", crop_px=21) == 21


def test_encircled_fraction_in_square_against_direct_sums():
    rng = np.random.default_rng(1)
    psf = rng.random((2, 21, 21))
    np.testing.assert_allclose(encircled_fraction_in_square(psf, 21), 1.0)
    np.testing.assert_allclose(encircled_fraction_in_square(psf, 5), psf[:, 8:13, 8:13].sum((1, 2)) / psf.sum((1, 2)))
    np.testing.assert_allclose(encircled_fraction_in_square(psf, 1), psf[:, 10, 10] / psf.sum((1, 2)))


def reference_encircled_energy(psf, radii):
    """The former implementation: a (R, K, K) mask of the pixels inside each radius."""
    k = psf.shape[-1]
    yy, xx = np.mgrid[:k, :k] - k // 2
    inside = np.hypot(yy, xx)[None] <= np.asarray(radii, dtype=np.float64)[:, None, None] + 1e-9
    return np.einsum("ckl,rkl->cr", np.asarray(psf, dtype=np.float64), inside.astype(np.float64))


def test_encircled_energy_matches_the_mask_method_on_a_small_psf():
    rng = np.random.default_rng(3)
    psf = rng.random((3, 15, 15))
    psf /= psf.sum(axis=(-2, -1), keepdims=True) * 1.25  # a fifth of the light outside the kernel
    # pixel-centre radii exactly (0, 1, √2, 5 = |(3, 4)|), just below them, between, negative, beyond the corners
    radii = np.array([-1.0, 0.0, 0.5, 1.0 - 1e-6, 1.0, np.sqrt(2), 2.5, 5.0 - 1e-6, 5.0, 7.0, 7 * np.sqrt(2), 30.0])
    np.testing.assert_allclose(encircled_energy(psf, radii), reference_encircled_energy(psf, radii), rtol=0, atol=1e-14)
    np.testing.assert_allclose(encircled_energy(psf, radii)[:, -1], 0.8, rtol=1e-12)


def test_encircled_energy_of_a_point_and_of_a_uniform_disc():
    k = 41
    point = np.zeros((1, k, k))
    point[0, k // 2, k // 2] = 1.0
    np.testing.assert_array_equal(encircled_energy(point, np.array([-0.5, 0.0, 0.3, 20.0]))[0], [0, 1, 1, 1])
    # a disc of the pixels with centre within 10 px, uniform: EE(r) = (pixels within r) / (pixels within 10)
    yy, xx = np.mgrid[:k, :k] - k // 2
    disc = (np.hypot(yy, xx) <= 10.0).astype(np.float64)
    n = disc.sum()
    radii = np.array([0.0, 1.0, np.sqrt(2), 2.0, 5.0, 10.0, 15.0])
    counts = np.array([1, 5, 9, 13, 81, n, n])  # lattice points with x² + y² <= r² (Gauss circle problem)
    np.testing.assert_allclose(encircled_energy(disc[None] / n, radii)[0], counts / n, rtol=1e-12)


def test_encircled_energy_of_a_large_kernel_needs_no_radius_by_kernel_array():
    """The montage asks for one radius per pixel out to the corner: for a 401 px kernel the former
    (R, K, K) mask took 284 × 401² × 9 bytes ≈ 0.4 GB; now the memory is that of the PSF stack."""
    import tracemalloc

    k = 401
    psf = np.full((2, k, k), 1.0 / k**2)
    radii = np.arange(0, k // 2 * np.sqrt(2) + 1.0)
    tracemalloc.start()
    try:
        ee = encircled_energy(psf, radii)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * psf.nbytes  # 20 MB, against ≈ 0.4 GB for the mask
    np.testing.assert_allclose(ee[:, -1], 1.0, rtol=1e-9)  # a running sum of 160 801 pixels
    assert np.all(np.diff(ee, axis=1) >= 0)


def test_a_camera_without_a_cfa_gets_no_cfa_figure(tmp_path, tiny_camera):
    """`camera.cfa.enabled: false` (κ = 1) drew a "CFA tile 1×1" whose curves summed to C over the bands under an
    axis saying Σ = 1, listed as the colour filter array; export-optics wrote no CFA files for the same camera."""
    from hsicam.report.camera import write_optics_figures

    written = write_optics_figures(tiny_camera("camera.cfa.enabled=false"), tmp_path)
    assert "cfa.png" not in written and not (tmp_path / "cfa.png").exists() and "doe.png" in written
    assert "cfa.png" in write_optics_figures(tiny_camera(), tmp_path / "with")


def test_psf_figure_of_a_one_pixel_kernel_draws_its_encircled_energy_as_points(tmp_path, monkeypatch):
    """`hsicam psf` of a camera whose PSF kernel is 1×1 px (a 200 µm pixel pitch) ended in "ValueError: zero-size array
    to reduction operation minimum" (the encircled energy's radii were [0] alone). Now the curve is one point per
    band at radius 1 px (the whole pixel: its energy), drawn as a marker."""
    import matplotlib.figure

    bands = Bands.uniform(420, 720, 150, 10)
    psf = np.array([0.9, 0.8, 0.7])[:, None, None]  # (3, 1, 1): each band's light kept in the pixel
    axes = []
    real = matplotlib.figure.Figure.add_subplot

    def keep(self, *args, **kwargs):
        axes.append(real(self, *args, **kwargs))
        return axes[-1]

    monkeypatch.setattr(matplotlib.figure.Figure, "add_subplot", keep)
    assert plot_psf_montage(psf, bands, tmp_path / "psf.png") == 1
    assert iio.imread(tmp_path / "psf.png").ndim == 3
    curves = axes[-1].lines
    assert [list(line.get_xdata()) for line in curves] == [[1.0]] * 3
    np.testing.assert_allclose([line.get_ydata()[0] for line in curves], [0.9, 0.8, 0.7])
    assert all(line.get_marker() == "o" for line in curves)
