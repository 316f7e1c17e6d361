"""PSF figure helpers: encircled energy, RMS radius and the automatic crop against closed forms."""

import imageio.v3 as iio
import numpy as np
import pytest

from hsicam.report.camera import encircled_energy, plot_psf_montage, psf_crop_px, rms_radius_px
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
