"""Measured PSFs from a monochromator sweep finer than the camera's bands (data/measured_psf.py, session 75).

A band is a Gaussian of its FWHM, not a line: each band's PSF is the weighted average of the sweep's images within its
reach. The references here are computed by hand: the band's Gaussian less what each image already spans (variances in
quadrature, FWHM = the sweep's step), sampled at the sweep's wavelengths; its second moment σ_band² − σ_image² in closed
form; the images written as 16-bit PNG / .npy files and their unit-sum averages summed with numpy.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from hsicam.data.measured_psf import import_psf_dir
from hsicam.errors import InputError
from hsicam.spectral import Bands

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def hand_weights(waves: np.ndarray, centre: float, band_fwhm: float, image_fwhm: float) -> np.ndarray:
    """Weights of the images at ``waves`` for a band: a Gaussian of variance σ_band² − σ_image² (what the band
    spreads beyond each image's own width), cut at 3σ, normalised."""
    var = (band_fwhm * FWHM_TO_SIGMA) ** 2 - (image_fwhm * FWHM_TO_SIGMA) ** 2
    w = np.exp(-((waves - centre) ** 2) / (2 * var))
    w[np.abs(waves - centre) > 3 * math.sqrt(var)] = 0.0
    return w / w.sum()


def four_spots(lam: float, size: int = 81) -> np.ndarray:
    """A diffractive-looking PSF whose scale goes as λ: a core and four spots at 34 px · λ/550 nm from the centre
    (symmetric: its centroid is the frame's centre pixel), 16-bit counts peaking near 60 000."""
    s = lam / 550.0
    y, x = np.mgrid[0:size, 0:size] - (size - 1) / 2
    img = 0.6 * np.exp(-(x**2 + y**2) / (2 * (1.2 * s) ** 2))
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        img += 0.4 * np.exp(-((x - 34 * s * dx) ** 2 + (y - 34 * s * dy) ** 2) / (2 * (0.8 * s) ** 2))
    return np.round(60000 * img / img.max()).astype(np.uint16)


def sweep_folder(d: Path, images: dict[float, np.ndarray], meta: dict | None = None) -> Path:
    d.mkdir()
    for lam, img in images.items():
        if img.dtype == np.uint16:
            iio.imwrite(d / f"psf_{lam:g}nm.png", img)
        else:
            np.save(d / f"psf_{lam:g}nm.npy", img)
    (d / "psf.json").write_text(json.dumps({"pixel_pitch_um": 6.0, **(meta or {})}))
    return d


def unit(img: np.ndarray) -> np.ndarray:
    a = img.astype(np.float64)
    return a / a.sum()


def test_a_2nm_sweep_under_10nm_bands_gives_each_band_the_weighted_average_of_its_images(tmp_path):
    """Images every 2 nm, 500–600 nm, of a PSF whose scale goes as λ, exposed differently at each wavelength (a
    lamp's spectrum: normalize: sum makes each image the band's light): each 10 nm band's PSF is the hand-weighted
    average of the unit-sum images (L1 ≤ 5e-4), not the image at its centre (L1 0.022–0.028 from it); the report lists
    each band's wavelengths and weights, whose mean is the centre and second moment σ_band² − σ_image² (closed form)."""
    waves = np.arange(500.0, 600.0 + 1e-9, 2.0)
    exposure = {lam: 0.4 + 0.6 * (lam - 500) / 100 for lam in waves}
    images = {lam: np.round(four_spots(lam) * exposure[lam]).astype(np.uint16) for lam in waves}
    d = sweep_folder(tmp_path / "sweep", images)
    bands = Bands.uniform(520.0, 580.0, 10.0)
    m = import_psf_dir(d, bands, 6e-6, 81)
    far, near = [], []
    for k, c in enumerate(bands.centers_nm):
        w = hand_weights(waves, c, 10.0, 2.0)
        ref = sum(wj * unit(images[lam]) for wj, lam in zip(w, waves) if wj > 0)
        far.append(np.abs(m.psf[k].astype(np.float64) - ref).sum())
        near.append(np.abs(unit(images[c]) - ref).sum())
    assert max(far) < 1e-3, far  # the hand weights' Gaussian is not quite the interpolant's
    assert min(near) > 0.02, near  # the nearest image is visibly another PSF
    for band, c in zip(m.report["bands"], bands.centers_nm):
        assert band["centre_px"] == [40.0, 40.0] and band["kernel_sum"] == pytest.approx(1.0, abs=1e-9)
        lam = np.array([s["wavelength_nm"] for s in band["sources"]])
        wt = np.array([s["weight"] for s in band["sources"]])
        assert wt.sum() == pytest.approx(1.0, abs=1e-12) and wt @ lam == pytest.approx(c, abs=1e-9)
        var = (10.0**2 - 2.0**2) * FWHM_TO_SIGMA**2  # the band's width beyond each image's own 2 nm
        assert wt @ (lam - c) ** 2 == pytest.approx(var, rel=1e-6)
        # within the band's ±3σ and the images next to it (the interpolant between them reaches the cut)
        assert lam.min() >= c - 3 * 10 * FWHM_TO_SIGMA - 2 and lam.max() <= c + 3 * 10 * FWHM_TO_SIGMA + 2
    assert m.report["import_version"] == 3


def test_a_sweep_as_coarse_as_the_bands_gives_each_band_its_image_bit_for_bit(tmp_path):
    """One image per band centre, 10 nm apart under 10 nm bands: each band is its own image imported alone
    (import_psf_image at the common centroid, the frame's centre pixel: the import before session 75) bit for bit,
    which is the unit-sum image cut to the kernel (to 1e-15), with a single source of weight 1. The same images named
    up to 0.4 nm off the band centres (within the 1 nm tolerance: steps of 9.2–10.8 nm) are still one image per band,
    not 0.5 % of a neighbour mixed in (their step short of the 10 nm FWHM by less than two tolerances)."""
    from hsicam.data.measured_psf import PSFImportOptions, import_psf_image

    waves = np.arange(520.0, 580.0 + 1e-9, 10.0)
    images = {lam: four_spots(lam) for lam in waves}
    d = sweep_folder(tmp_path / "coarse", images)
    m = import_psf_dir(d, Bands.uniform(520.0, 580.0, 10.0), 6e-6, 61)
    alone = [import_psf_image(images[lam], 6e-6, 6e-6, 61, PSFImportOptions(pitch_um=6.0), (40.0, 40.0))[0]
             for lam in waves]
    np.testing.assert_array_equal(m.psf, np.stack(alone).astype(np.float32))
    crop = np.stack([unit(images[lam])[10:71, 10:71] for lam in waves])
    np.testing.assert_allclose(m.psf, crop, rtol=1e-6, atol=1e-15)
    assert [b["sources"] for b in m.report["bands"]] == [
        [{"wavelength_nm": lam, "file": f"psf_{lam:g}nm.png", "weight": 1.0}] for lam in waves]
    jitter = [0.4, -0.4, 0.3, -0.2, 0.4, -0.4, 0.0]
    off = sweep_folder(tmp_path / "jittered", {lam + j: images[lam] for lam, j in zip(waves, jitter)})
    m2 = import_psf_dir(off, Bands.uniform(520.0, 580.0, 10.0), 6e-6, 61)
    np.testing.assert_array_equal(m2.psf, m.psf)
    assert [len(b["sources"]) for b in m2.report["bands"]] == [1] * 7
    # the monochromator's bandwidth recorded (2 nm, narrower than the bands): still one image per band, not the image
    # and ghosts of its neighbours 10 nm away (the review: 8.7 % of each neighbour with fwhm_nm given)
    narrow = sweep_folder(tmp_path / "narrow", images, {"fwhm_nm": 2.0})
    m3 = import_psf_dir(narrow, Bands.uniform(520.0, 580.0, 10.0), 6e-6, 61)
    np.testing.assert_array_equal(m3.psf, m.psf)
    assert [len(b["sources"]) for b in m3.report["bands"]] == [1] * 7


def spot_moving_quadratically(lam: float, size: int = 81) -> np.ndarray:
    """A spot whose column is 40 + 0.1 (λ − 550 nm)² px (float64 light, energy fractions 1)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    g = np.exp(-((y - 40) ** 2 + (x - 40 - 0.1 * (lam - 550.0) ** 2) ** 2) / (2 * 1.5**2))
    return g / g.sum()


@pytest.mark.parametrize("centre", ["centroid", "centroid_per_band"])
def test_the_centre_and_the_energy_fractions_of_a_band_count_every_image_it_averages(tmp_path, caplog, centre):
    """A spot moving as (λ − 550)² and a throughput 0.5 + 0.001 (λ − 550)² (``normalize: none``, energy fractions),
    2 nm sweep 536–564 nm, one 10 nm band at 550 nm: the band's centroid is that of its weighted average, 40 + 0.1
    Σw(λ−c)² = 41.73 px → column 42 (the image at 550 nm alone: 40), and its light Σw T = 0.5 + 0.001 · 17.31 (its
    centre image alone: 0.5). The sweep covers the band's ±3σ (537.3–562.7 nm), not the one of a band at 552 nm
    (539.3–564.7 nm): that is warned about; a band with no image within the tolerance is refused as before."""
    waves = np.arange(536.0, 564.0 + 1e-9, 2.0)
    throughput = {lam: 0.5 + 0.001 * (lam - 550.0) ** 2 for lam in waves}
    images = {lam: (throughput[lam] * spot_moving_quadratically(lam)).astype(np.float64) for lam in waves}
    d = sweep_folder(tmp_path / "fractions", images, {"normalize": "none", "centre": centre})
    band = Bands([550.0], [10.0])
    with caplog.at_level(logging.WARNING, logger="hsicam.data.measured_psf"):
        m = import_psf_dir(d, band, 6e-6, 61)
    var = (10.0**2 - 2.0**2) * FWHM_TO_SIGMA**2
    assert m.report["bands"][0]["centre_px"] == [40.0, 42.0]
    assert float(m.psf[0].sum(dtype=np.float64)) == pytest.approx(0.5 + 0.001 * var, rel=2e-3)
    w = hand_weights(waves, 550.0, 10.0, 2.0)
    ref = sum(wj * images[lam] for wj, lam in zip(w, waves))[10:71, 12:73]
    assert np.abs(m.psf[0] - ref).sum() < 0.02 * ref.sum()  # the hand weights' Gaussian is not the interpolant's
    assert np.abs(images[550.0][10:71, 12:73] - ref).sum() > 0.5 * ref.sum()  # the centre image alone: far off
    cut = "ends within the reach"
    assert not [r for r in caplog.records if cut in r.getMessage()]
    with caplog.at_level(logging.WARNING, logger="hsicam.data.measured_psf"):
        import_psf_dir(d, Bands([552.0], [10.0]), 6e-6, 61)
    said = [r.getMessage() for r in caplog.records if cut in r.getMessage()]
    assert len(said) == 1 and "band(s) 552 nm" in said[0] and "measure 539–565 nm" in said[0]
    with pytest.raises(InputError, match=r"no measured PSF for band\(s\) 570 nm"):
        import_psf_dir(d, Bands([550.0, 570.0], [10.0, 10.0]), 6e-6, 61)


def test_the_images_bandwidth_fwhm_nm_sets_what_the_band_still_averages_and_is_checked(tmp_path):
    """``fwhm_nm`` in psf.json (the monochromator's bandwidth, 1 nm here, under images 2 nm apart): the band's
    weights spread σ_band² − σ_1nm² (closed form); a bandwidth that is no positive number, or a list of the wrong
    length, is refused in one line."""
    waves = np.arange(530.0, 570.0 + 1e-9, 2.0)
    d = sweep_folder(tmp_path / "bw", {lam: four_spots(lam) for lam in waves}, {"fwhm_nm": 1.0})
    m = import_psf_dir(d, Bands([550.0], [10.0]), 6e-6, 81)
    src = m.report["bands"][0]["sources"]
    lam, wt = np.array([s["wavelength_nm"] for s in src]), np.array([s["weight"] for s in src])
    assert wt @ (lam - 550.0) ** 2 == pytest.approx((10.0**2 - 1.0**2) * FWHM_TO_SIGMA**2, rel=1e-6)
    assert m.report["fwhm_nm"] == 1.0
    for bad, said in ((-2, "fwhm_nm .* must be a positive number"), (True, "fwhm_nm .* must be a positive number"),
                      ([1.0, 1.0], "fwhm_nm lists 2 values for 21 PSF images")):
        (d / "psf.json").write_text(json.dumps({"pixel_pitch_um": 6.0, "fwhm_nm": bad}))
        with pytest.raises(InputError, match=said):
            import_psf_dir(d, Bands([550.0], [10.0]), 6e-6, 81)
