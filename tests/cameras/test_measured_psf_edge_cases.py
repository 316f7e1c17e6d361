"""Mutation guards for measured cameras and measured PSFs: the fixed-PSF camera (cameras/measured.py), the PSF
import (data/measured_psf.py) and the measured-PSF file (runs/measured_psf.py) (probe mut4b).

Each test kills a hand-made mutant that the other tests let through, asserting against a reference computed
here: brute-force sums and area overlaps, the Airy pattern's encircled energy from Bessel functions, a file read
back in its real format (safetensors, hashlib).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hsicam.errors import InputError


# ------------------------------------------------------------------------------------------------
# cameras/measured.py
# ------------------------------------------------------------------------------------------------
def test_a_fixed_psf_cameras_energy_is_each_bands_sum_and_its_noise_is_the_sensors_only(tiny_camera):
    """energy in the kernel = Σ over the K×K kernel of each band (brute force); noise levels: the sensor's σ only
    (a fixed PSF has no DOE height noise to set: asking for it is the camera's ConfigError)."""
    import torch

    from hsicam.cameras.measured import FixedPSFCamera
    from hsicam.errors import ConfigError

    cam = tiny_camera("camera.doe.sigma_height_nm=20", "camera.sensor.sigma=0.01")
    k = cam.kernel_px
    psf = torch.rand(len(cam.bands), k, k, generator=torch.Generator().manual_seed(3)) / (k * k)
    fixed = FixedPSFCamera.from_camera(cam, psf)
    brute = [float(sum(psf[c, i, j] for i in range(k) for j in range(k))) for c in range(len(cam.bands))]
    np.testing.assert_allclose(fixed.psf_result().energy.numpy(), brute, rtol=1e-5)
    assert fixed.noise_levels() == {"sensor_sigma": pytest.approx(0.01)}
    with pytest.raises(ConfigError, match="no noise level sigma_height_nm"):
        fixed.set_noise(sigma_height_nm=10.0)


def test_a_fixed_psf_stack_of_another_kernel_is_refused_and_the_given_one_is_a_copy(tiny_camera):
    import torch

    from hsicam.cameras.measured import FixedPSFCamera

    cam = tiny_camera()
    c, k = len(cam.bands), cam.kernel_px
    for shape in ((c, k - 2, k - 2), (c, k, k + 2), (c + 1, k, k)):
        with pytest.raises(InputError, match=rf"must be \({c}, {k}, {k}\)"):
            FixedPSFCamera.from_camera(cam, torch.zeros(shape))
    new = torch.full((c, k, k), 1.0 / (k * k))
    fixed = FixedPSFCamera.from_camera(cam, new)
    new.mul_(2.0)  # the caller's tensor changes afterwards: the camera keeps what it was given
    assert torch.equal(fixed.psf(), torch.full((c, k, k), 1.0 / (k * k)))


# ------------------------------------------------------------------------------------------------
# data/measured_psf.py: the pitch-in-the-wrong-unit test against the Airy pattern
# ------------------------------------------------------------------------------------------------
def _airy_image(lam_m: float, f_number: float, pitch_m: float, n: int = 201) -> np.ndarray:
    """(2 J1(v)/v)², v = π r/(λN), sampled at the centres of an n×n image of pitch ``pitch_m``."""
    from scipy.special import j1

    x = (np.arange(n) - n // 2) * pitch_m
    v = math.pi * np.hypot(x[:, None], x[None, :]) / (lam_m * f_number)
    with np.errstate(invalid="ignore", divide="ignore"):
        img = np.where(v > 0, (2 * j1(v) / v) ** 2, 1.0)
    return img


def test_airy_half_light_radius_constant_is_the_bessel_root():
    """1 − J0(v)² − J1(v)² = 1/2 (encircled energy of the Airy pattern) at v = π·r50/(λN)."""
    from scipy.optimize import brentq
    from scipy.special import j0, j1

    from hsicam.data.measured_psf import AIRY_EE50

    v = brentq(lambda v: 1 - j0(v) ** 2 - j1(v) ** 2 - 0.5, 0.5, 3.0)
    assert AIRY_EE50 == pytest.approx(v / math.pi, abs=1e-4)


@pytest.mark.parametrize("k", [1, 2, 7, 10, 33])
def test_half_light_radius_of_k_equal_pixels_is_that_of_ceil_k_over_2_pixels(k):
    from hsicam.data.measured_psf import half_light_radius_px

    img = np.zeros((9, 9))
    img.flat[np.random.default_rng(k).permutation(81)[:k]] = 1.0
    assert half_light_radius_px(img) == pytest.approx(math.sqrt(math.ceil(k / 2) / math.pi))


@pytest.mark.parametrize("sharpness, accepted", [(1.0, True), (0.7, True), (0.4, False)])
def test_an_airy_psf_of_the_cameras_f_number_is_accepted_and_a_much_sharper_one_refused(tiny_camera, tmp_path,
                                                                                        sharpness, accepted):
    """The camera's f-number is sensor distance / aperture diameter (N = 5 mm / 0.5 mm = 10 for the tiny camera):
    its own Airy PSF passes, as does one of 0.7·N (within the margin MIN_DIFFRACTION_FRACTION = 0.5 for a larger
    aperture); one of 0.4·N cannot come from this aperture and is refused naming the diffraction limit."""
    from hsicam.data.measured_psf import import_for_camera
    from hsicam.io import write_json

    cam = tiny_camera()
    n_cam = cam.optics.sensor_distance_m / (2 * cam.optics.aperture_radius_m)
    assert n_cam == pytest.approx(10.0)
    d = tmp_path / "psf"
    d.mkdir()
    for lam in cam.bands.centers_nm:
        np.save(d / f"psf_{lam:g}nm.npy", _airy_image(lam * 1e-9, sharpness * n_cam, 0.25e-6))
    write_json(d / "psf.json", {"pixel_pitch_um": 0.25})
    if accepted:
        m = import_for_camera(d, cam)
        assert m.psf.shape == (len(cam.bands), cam.kernel_px, cam.kernel_px)
    else:
        with pytest.raises(InputError, match="diffraction limit"):
            import_for_camera(d, cam)


@pytest.mark.parametrize("shape", [(20, 20), (24, 31), (41, 41), (64, 48), (100, 120)])
def test_border_background_is_the_median_of_a_frame_of_max_2_px_or_5_percent(shape):
    """``background: border``: the median of the pixels within t = max(2, 5 % of the smaller side) of an edge,
    selected here by each pixel's distance to the nearest edge."""
    from hsicam.data.measured_psf import border_level, subtract_background

    img = np.random.default_rng(sum(shape)).random(shape) * 10
    h, w = shape
    t = max(2, int(0.05 * min(h, w)))
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    edge = np.minimum(np.minimum(rows, h - 1 - rows), np.minimum(cols, w - 1 - cols))
    ref = float(np.median(img[edge < t]))
    assert border_level(img) == pytest.approx(ref, rel=1e-12)
    out, b = subtract_background(img, "border")
    assert b == pytest.approx(ref, rel=1e-12)
    np.testing.assert_allclose(out, img - ref, rtol=1e-12)  # signed: the kernel alone is clipped, at the end


def test_axis_px_anywhere_on_the_image_is_accepted_up_to_its_outer_pixel_edges():
    """Pixel centres at integers: an h×w image spans −0.5 … h − 0.5 (rows) and −0.5 … w − 0.5 (cols)."""
    from hsicam.data.measured_psf import find_centre

    img = np.ones((5, 8))
    for axis in ((-0.5, -0.5), (-0.4, 7.3), (4.5, 7.5), (2.0, 3.0)):
        assert find_centre(img, "axis", axis) == axis
    for axis in ((-0.6, 3.0), (2.0, 7.6), (4.51, 0.0)):
        with pytest.raises(InputError, match="lies outside the 5×8 px PSF image"):
            find_centre(img, "axis", axis)


def test_the_import_report_gives_the_centre_relative_to_the_images_middle_pixel():
    """centre_offset_px: the centre used minus the image's middle ((h − 1)/2, (w − 1)/2 with pixel centres at
    integers: pixel (10, 15) of a 21×31 image)."""
    from hsicam.data.measured_psf import PSFImportOptions, import_psf_image

    img = np.zeros((21, 31))
    img[3, 20] = 1.0
    img[10, 15] = 0.5
    opts = PSFImportOptions(pitch_um=2.0, centre="peak")
    _, rep = import_psf_image(img, 2e-6, 2e-6, 5, opts)
    assert rep["centre_px"] == [3.0, 20.0] and rep["centre_offset_px"] == [3 - 10, 20 - 15]
    _, rep = import_psf_image(img, 2e-6, 2e-6, 5, PSFImportOptions(pitch_um=2.0, centre="axis", axis_px=(10.0, 15.0)))
    assert rep["centre_offset_px"] == [0.0, 0.0]


@pytest.mark.parametrize("clipped, warned", [(2, False), (3, True)])
def test_three_pixels_at_an_8bit_images_maximum_are_warned_about_once_per_file(tiny_camera, tmp_path, caplog,
                                                                              clipped, warned):
    """SATURATED_MIN_PX = 3: two pixels at 255 are what an image scaled to its own maximum has; three are a clip."""
    import logging

    from hsicam.data.measured_psf import SATURATED_MIN_PX, import_for_camera
    from hsicam.io import write_json

    assert SATURATED_MIN_PX == 3
    cam = tiny_camera()
    x = np.arange(64) - 32
    blob = np.round(200 * np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * 6.0**2))).astype(np.uint8)
    blob.flat[[32 * 64 + 32 + i for i in range(clipped)]] = 255
    d = tmp_path / "psf"
    d.mkdir()
    for lam in cam.bands.centers_nm:
        np.save(d / f"psf_{lam:g}nm.npy", blob)
    write_json(d / "psf.json", {"pixel_pitch_um": 1.0})
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        import_for_camera(d, cam)
    said = [r for r in caplog.records if "clipped (over-exposed)" in r.getMessage()]
    assert len(said) == (len(cam.bands) if warned else 0)


def test_a_band_without_a_psf_within_the_wavelength_tolerance_is_named(tiny_camera, tmp_path):
    """wavelength_tolerance_nm (default 1 nm): a PSF at 501.5 nm is no PSF of the 500 nm band."""
    from hsicam.data.measured_psf import import_for_camera
    from hsicam.io import write_json

    cam = tiny_camera()
    x = np.arange(64) - 32
    blob = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * 6.0**2))
    d = tmp_path / "psf"
    d.mkdir()
    for lam in (501.5, 550.0, 600.0):
        np.save(d / f"psf_{lam:g}nm.npy", blob)
    write_json(d / "psf.json", {"pixel_pitch_um": 1.0})
    with pytest.raises(InputError, match=r"no measured PSF for band\(s\) 500 nm .*tolerance 1 nm"):
        import_for_camera(d, cam)
    write_json(d / "psf.json", {"pixel_pitch_um": 1.0, "wavelength_tolerance_nm": 1.6})
    assert import_for_camera(d, cam).psf.shape[0] == 3


# ------------------------------------------------------------------------------------------------
# runs/measured_psf.py
# ------------------------------------------------------------------------------------------------
def test_measured_psf_file_read_back_with_safetensors_carries_the_sha256_of_its_float32_stack(tmp_path):
    import hashlib

    from safetensors import safe_open

    from hsicam.runs.measured_psf import MeasuredPSF, load_measured_psf, save_measured_psf
    from hsicam.spectral import Bands

    psf = np.random.default_rng(1).random((3, 5, 5)).astype(np.float32)
    bands = Bands.uniform(500, 600, 50)
    save_measured_psf(tmp_path / "m.safetensors", MeasuredPSF(psf, bands, {"kernel_px": 5}))
    with safe_open(str(tmp_path / "m.safetensors"), framework="numpy") as fh:
        stored, meta = fh.get_tensor("psf"), fh.metadata()
    np.testing.assert_array_equal(stored, psf)
    ref = hashlib.sha256(np.ascontiguousarray(stored, dtype="<f4").tobytes()).hexdigest()[:16]
    assert meta["fingerprint"] == ref == load_measured_psf(tmp_path / "m.safetensors").fingerprint


def test_a_measured_psf_file_with_an_even_kernel_is_damaged(tmp_path):
    import json

    import torch

    from hsicam.runs.checkpoint import save_safetensors
    from hsicam.runs.measured_psf import load_measured_psf
    from hsicam.spectral import Bands

    bands = Bands.uniform(500, 600, 50)
    save_safetensors(tmp_path / "m.safetensors", {"psf": torch.zeros(3, 4, 4)},
                     {"format": "hsicam-measured-psf-1", "bands": json.dumps(bands.to_dict())})
    with pytest.raises(InputError, match=r"not \(3 bands, K, K\) with K odd"):
        load_measured_psf(tmp_path / "m.safetensors")


def test_psf_difference_names_the_pitch_then_the_kernel_then_the_options(tmp_path):
    from hsicam.runs.measured_psf import MeasuredPSF, psf_difference
    from hsicam.spectral import Bands

    bands = Bands.uniform(500, 600, 50)
    base = {"psf_dir": str(tmp_path), "pixel_pitch_um": 2.0, "kernel_px": 5, "centre": "centroid", "axis_px": None,
            "background": "none", "normalize": "sum"}
    tuned = MeasuredPSF(np.zeros((3, 5, 5), np.float32), bands, base)

    def now(**changes):
        return MeasuredPSF(np.ones((3, 5, 5), np.float32), bands, {**base, **changes})

    assert psf_difference(tuned, now(pixel_pitch_um=2.5, kernel_px=7), tmp_path)[0] == "pixel_pitch_um"
    assert psf_difference(tuned, now(kernel_px=7, centre="peak"), tmp_path)[0] == "kernel_px"
    assert psf_difference(tuned, now(centre="peak"), tmp_path)[0] == "options"
    assert psf_difference(tuned, now(), tmp_path)[0] == "images"
    # the images' bandwidth (fwhm_nm, session 75) is an option when both reports have it; one made before has none
    assert psf_difference(tuned, now(fwhm_nm=[10.0, 10.0, 10.0]), tmp_path)[0] == "images"
    banded = MeasuredPSF(tuned.psf, bands, {**base, "fwhm_nm": 2.0})
    what, why = psf_difference(banded, now(fwhm_nm=1.0), tmp_path)
    assert what == "options" and why.endswith("fwhm_nm 1.0 now, 2.0 then")
    # a fine-tuning imported before session 73 (no import_version: 1) against today's import of the same folder: the
    # import changed, not the files (it read "the PSF images … changed since")
    what, why = psf_difference(tuned, now(import_version=2), tmp_path)
    assert what == "import" and "version 1 then, 2 now" in why and "the files may have changed too" in why
    assert psf_difference(MeasuredPSF(tuned.psf, bands, {**base, "import_version": 2}), now(import_version=2),
                          tmp_path)[0] == "images"


def test_zero_mean_noise_in_a_large_frame_is_neither_light_nor_a_pull_on_the_centre(tmp_path, caplog):
    """A measured PSF off-centre in a 301² px frame, a 100 DN pedestal and 2 DN of read noise under a 30 000 DN
    peak, `background: border`, `centre: centroid`: the background was clipped at 0 before the normalisation and
    the centroid, so the noise's positive half became a floor over the whole frame, counted as light and pulling the
    centroid toward the frame's centre (here: kernels of 0.92 and 0.95 of the band's light, the centre 4 px off;
    the hunt's 401² frame with a sharper PSF: 0.55–0.68 and ~40 px; session 73). Now the centre is the PSF's (within
    0.2 px), the kernel holds its light up to the noise the clip at its end adds (reported as noise_clipped and
    warned about above 2 %), and a noise-free frame is exact."""
    import json
    import logging

    from hsicam.data.measured_psf import import_psf_dir
    from hsicam.spectral import Bands

    bands = Bands.from_centers([500.0, 600.0])
    k, size, at = 41, 301, (90, 200)
    yy, xx = np.mgrid[0:size, 0:size]
    clean = {}
    for i, (w, sigma) in enumerate(((500, 2.0), (600, 2.6))):
        g = np.exp(-((yy - at[0]) ** 2 + (xx - at[1]) ** 2) / (2 * sigma ** 2))
        clean[w] = 30000 * g / g.max()

    def folder(name: str, noise: float):
        d = tmp_path / name
        d.mkdir()
        rng = np.random.default_rng(3)
        for w, img in clean.items():
            np.save(d / f"psf_{w}nm.npy", (img + 100 + rng.normal(0, noise, img.shape)).astype(np.float32))
        (d / "psf.json").write_text(json.dumps({"pixel_pitch_um": 6.0, "background": "border"}))
        return d

    exact = import_psf_dir(folder("clean", 0.0), bands, 6e-6, k)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.measured_psf"):
        noisy = import_psf_dir(folder("noisy", 2.0), bands, 6e-6, k)
    assert exact.report["import_version"] == 3
    for m in (exact, noisy):
        rep = m.report["bands"]
        for b in rep:
            assert b["centre_px"] == pytest.approx(list(at), abs=0.2)
    np.testing.assert_allclose(exact.psf.sum(axis=(1, 2)), 1.0, atol=1e-5)
    sums = noisy.psf.sum(axis=(1, 2))
    clipped = np.array([b["noise_clipped"] for b in noisy.report["bands"]])
    assert np.all(sums > 0.98) and np.all(sums < 1.1)  # the clip's floor in 41² px: a few per cent (it was ~0.6)
    np.testing.assert_allclose(sums, 1.0 + clipped, atol=0.01)  # the floor is what the report says
    assert np.abs(noisy.psf - exact.psf).sum(axis=(1, 2)).max() < 0.1
    assert "measured PSFs are noisy" not in caplog.text  # a floor of 0.1 %
    with caplog.at_level(logging.WARNING, logger="hsicam.data.measured_psf"):
        loud = import_psf_dir(folder("loud", 40.0), bands, 6e-6, k)  # 40 DN: a floor of a few per cent
    clipped = np.array([b["noise_clipped"] for b in loud.report["bands"]])
    assert clipped.max() > 0.02
    for b in loud.report["bands"]:  # the light measured in the kernel, and the floor the clip adds on top
        assert b["kernel_sum"] == pytest.approx(b["energy_in_kernel"] + b["noise_clipped"], rel=1e-9)
        assert b["energy_in_kernel"] < 1.0 + b["noise_clipped"]
    # (the frame's noise and the border median's own error, over 301² px, move the light by a few per cent more)
    np.testing.assert_allclose(loud.psf.sum(axis=(1, 2)), 1.0 + clipped, atol=0.05)
    said = [r.getMessage() for r in caplog.records if "measured PSFs are noisy" in r.getMessage()]
    assert len(said) == 1 and "average more frames" in said[0], said
