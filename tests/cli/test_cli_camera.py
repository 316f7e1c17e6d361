"""`hsicam psf` and `hsicam simulate` through the console script's ``main`` (in-process; the console script
itself where a test needs a process of its own), including bad input."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from cli_helpers import assert_clean_error, run_cli, run_cli_in_process
from optics_reference import doe_field, reference_measurement, relative_l1, square_cell_psf

TINY = ["--set", "camera.aperture_radius_mm=0.6", "--set", "camera.lens.focal_length_mm=5",
        "--set", "bands.step_nm=50", "--set", "camera.cfa.period=3"]


def test_psf_command_writes_contract_files(tmp_path):
    proc = run_cli_in_process("psf", "--out", str(tmp_path), *TINY)
    assert proc.returncode == 0, proc.stderr
    psf = np.load(tmp_path / "psf.npy")
    info = json.loads((tmp_path / "psf.json").read_text())
    assert psf.dtype == np.float32 and psf.ndim == 3
    assert psf.shape == (len(info["bands_nm"]), info["kernel_px"], info["kernel_px"])
    assert info["bands_nm"] == [420.0, 470.0, 520.0, 570.0, 620.0, 670.0, 720.0]
    assert info["pixel_pitch_um"] == pytest.approx(6.0)
    # kernel ≥ λ_max·z/(Δ·pixel) = 0.72 µm · 5 mm / (30 µm · 6 µm) = 20 → 21 (odd)
    assert info["kernel_px"] == 21
    np.testing.assert_allclose(psf.sum(axis=(1, 2)), info["energy_in_kernel"], rtol=1e-5)
    assert {"model", "focal_length_mm"} <= set(info["lens"]) and "enabled" in info["doe"]
    img = iio.imread(tmp_path / "psf.png")
    assert img.ndim == 3 and img.shape[0] > 50
    # the model is stated, and the DOE heights and aperture it used are written: anyone can
    # recompute the PSFs from them (here with the independent square-cell integral)
    assert info["model"]["cells_exact"] and info["model"]["pixel_integration"] == "exact"
    assert info["model"]["band_samples"] == 1 and "rear principal plane" in info["lens"]["sensor_distance_from"]
    h = np.load(tmp_path / "doe_height_m.npy")
    amp = np.load(tmp_path / "aperture.npy")
    assert h.shape == amp.shape == (41, 41) and h.dtype == amp.dtype == np.float64
    assert 0 < h.max() < 2e-6 and amp[20, 20] == 1.0 and amp[0, 0] == 0.0
    k = info["kernel_px"]
    for band in (0, 6):
        lam = info["bands_nm"][band]
        ref = square_cell_psf(doe_field(h, amp, lam), 30e-6, lam * 1e-9, info["lens"]["sensor_distance_mm"] * 1e-3,
                              6e-6, np.arange(k) - k // 2, sub=15)
        assert relative_l1(psf[band], ref) < 0.02


def test_psf_paper_defaults_kernel_141(tmp_path):
    proc = run_cli_in_process("psf", "--out", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    info = json.loads((tmp_path / "psf.json").read_text())
    assert info["kernel_px"] == 141 and len(info["bands_nm"]) == 31
    # the random diffuser sends light beyond the kernel under the cells' sinc² envelope (issue 13)
    e = info["energy_in_kernel"]
    assert e[0] == pytest.approx(0.82, abs=0.01) and e[-1] == pytest.approx(0.62, abs=0.01)


def test_simulate_command_outputs(tmp_path):
    """sensor.npy is the camera model's image of the scene: the direct shift-and-add reference
    g = Σ_c κ_c ⊙ (f_c ⊛ p_c) ('same' boundary, the config's padding) with the PSFs and CFA weights
    of the camera built from the same settings, noise off, within float32 rounding."""
    rng = np.random.default_rng(0)
    scene = rng.uniform(0, 1, size=(7, 40, 48)).astype(np.float32)
    np.save(tmp_path / "scene.npy", scene)
    out = tmp_path / "out"
    noise_off = ["--set", "camera.sensor.sigma=0", "--set", "camera.doe.sigma_height_nm=0"]
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(out), *TINY, *noise_off)
    assert proc.returncode == 0, proc.stderr
    # the grid it assumed is said (evaluate --data takes a .npy as 400-700 nm, and would refuse this one)
    assert "its 7 bands were taken as the camera's (420-720 nm): give data.npy_bands if they are not" in proc.stderr
    sensor = np.load(out / "sensor.npy")
    assert sensor.dtype == np.float32 and sensor.shape == (40, 48)  # 'same' boundary by default
    png = iio.imread(out / "sensor.png")
    assert png.dtype == np.uint16 and png.shape == (40, 48)
    meta = json.loads((out / "simulate.json").read_text())
    np.testing.assert_allclose(png / 65535.0 * meta["sensor_png_scale"], sensor, atol=1.0 / 65535 * meta["sensor_png_scale"])
    for name in ("cfa.png", "doe.png"):
        assert iio.imread(out / name).ndim == 3

    import torch

    from hsicam.cameras import DOECamera
    from hsicam.config import load_config

    cfg = load_config(overrides=[*TINY[1::2], *noise_off[1::2], "camera.boundary=same"])
    cam = DOECamera.from_config(cfg)
    with torch.no_grad():
        psf = cam.psf().double().numpy()
        weights = cam.cfa.weights.detach().double().numpy()
    assert weights.shape == (7, 3, 3) and weights.max() > 0
    want = reference_measurement(scene[None], psf, weights, "same", cfg.camera.padding)[0, 0]
    assert float(np.abs(want).max()) > 0.1
    np.testing.assert_allclose(sensor, want, rtol=0, atol=2e-6 * float(np.abs(want).max()))


def test_simulate_writes_a_display_preview_beside_the_dim_data_file(tmp_path):
    """A dim scene's sensor.png (the linear 16-bit data reconstruct reads) looks black: the tiny camera's image of a
    scene at 0.1 peaks near 0.1 of full scale. sensor_preview.png beside it is the same image times the exposure
    that puts its 99th percentile at 0.8 (computed here from sensor.npy), said in the printed line and
    simulate.json; reconstruct refuses it as sensor data, in one line."""
    from hsicam.data.images import read_capture
    from hsicam.errors import InputError

    scene = np.random.default_rng(1).uniform(0, 0.1, size=(7, 40, 48)).astype(np.float32)
    np.save(tmp_path / "scene.npy", scene)
    out = tmp_path / "out"
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(out), *TINY)
    assert proc.returncode == 0, proc.stderr
    sensor = np.load(out / "sensor.npy")
    data = iio.imread(out / "sensor.png")  # the data file: unchanged, linear, dim
    assert data.dtype == np.uint16 and data.max() / 65535 < 0.15
    np.testing.assert_allclose(data / 65535.0, sensor, atol=1 / 65535)
    exposure = 0.8 / float(np.percentile(sensor, 99))
    preview = iio.imread(out / "sensor_preview.png")
    assert preview.dtype == np.uint8 and preview.shape == sensor.shape
    want = np.round(np.clip(sensor.astype(np.float64) * exposure, 0, 1) * 255)
    assert np.abs(preview.astype(np.float64) - want).max() <= 1
    assert abs(np.percentile(preview, 99) / 255 - 0.8) < 0.01
    assert json.loads((out / "simulate.json").read_text())["sensor_preview_exposure"] == pytest.approx(exposure)
    assert (f"sensor_preview.png: a display preview (linear, ×{exposure:.3g}: its 99th percentile at 0.8 of white), "
            "not data") in proc.stdout
    with pytest.raises(InputError, match=r"sensor_preview.png: hsicam simulate's display preview \(exposed x[0-9.]+, "
                                         r"8 bit\), not sensor data: give its sensor.png or sensor.npy$"):
        read_capture(out / "sensor_preview.png")


def test_simulate_png_keeps_its_scale_when_copied_elsewhere(tmp_path):
    """A sensor brighter than full scale is stored stretched (PNG = sensor / peak): the scale travels
    inside the PNG, so a copy away from simulate.json reads back at the simulated level."""
    from PIL import Image

    from hsicam.data.images import SENSOR_SCALE_KEY, read_sensor_image

    np.save(tmp_path / "scene.npy", np.full((7, 40, 48), 3.0, np.float32))  # a scene 3× full scale
    out = tmp_path / "out"
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(out), *TINY)
    assert proc.returncode == 0, proc.stderr
    sensor = np.load(out / "sensor.npy")
    scale = json.loads((out / "simulate.json").read_text())["sensor_png_scale"]
    assert scale == pytest.approx(float(sensor.max())) and scale > 1.5
    with Image.open(out / "sensor.png") as im:
        assert float(im.text[SENSOR_SCALE_KEY]) == scale
    (tmp_path / "elsewhere").mkdir()
    copy = tmp_path / "elsewhere" / "capture.png"
    copy.write_bytes((out / "sensor.png").read_bytes())
    tol = scale / 65535
    np.testing.assert_allclose(read_sensor_image(copy), sensor, atol=tol)  # was sensor / scale
    np.testing.assert_allclose(read_sensor_image(out / "sensor.png"), sensor, atol=tol)
    # a scale multiplies the simulated level, as it multiplies sensor.npy (it replaced the PNG's own scale)
    np.testing.assert_allclose(read_sensor_image(copy, 0.5), 0.5 * sensor, atol=tol)
    plain = np.arange(16, dtype=np.uint16).reshape(4, 4) * 4000
    Image.fromarray(plain).save(tmp_path / "plain.png")  # any other PNG: as stored
    np.testing.assert_allclose(read_sensor_image(tmp_path / "plain.png"), plain / 65535.0, atol=1e-7)


def test_reading_simulates_image_of_a_scene_far_above_full_scale_warns(tmp_path, caplog):
    """simulate's PNG of a scene far brighter than full scale reads back at its level, with the warning a
    float capture that far above 1 gets (the network never saw such images); a scene at full scale: none."""
    import logging

    from hsicam.data.images import FLOAT_OVER_SCALE, read_sensor_image

    levels = {}
    for name, level in (("hot", 20.0), ("normal", 1.0)):
        np.save(tmp_path / f"{name}.npy", np.full((7, 40, 48), level, np.float32))
        out = tmp_path / name
        proc = run_cli_in_process("simulate", "--scene", str(tmp_path / f"{name}.npy"), "--out", str(out), *TINY)
        assert proc.returncode == 0, proc.stderr
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
            levels[name] = float(read_sensor_image(out / "sensor.png").max())
        levels[name + "_warned"] = any("far brighter than full scale" in r.getMessage() for r in caplog.records)
    assert levels["hot"] > FLOAT_OVER_SCALE and levels["hot_warned"]
    assert levels["normal"] < FLOAT_OVER_SCALE and not levels["normal_warned"]


def test_simulate_valid_boundary_shrinks_sensor(tmp_path):
    np.save(tmp_path / "scene.npy", np.ones((7, 40, 40), np.float32))
    out = tmp_path / "out"
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(out), "--boundary", "valid", *TINY)
    assert proc.returncode == 0, proc.stderr
    sensor = np.load(out / "sensor.npy")
    assert sensor.shape == (20, 20)  # 40 - (21 - 1)
    # a uniform unit scene through the normalised CFA gives Σ_λ κ_λ·(light of band λ inside the
    # kernel): between the smallest and largest band energy, repeating with the CFA period
    import torch

    from hsicam.cameras import DOECamera
    from hsicam.config import load_config

    cam = DOECamera.from_config(load_config(overrides=TINY[1::2]))
    with torch.no_grad():
        energy = cam.psf_result().energy.numpy()
    assert energy.min() - 1e-4 <= sensor.min() and sensor.max() <= energy.max() + 1e-4
    np.testing.assert_allclose(sensor[3:], sensor[:-3], atol=1e-5)
    np.testing.assert_allclose(sensor[:, 3:], sensor[:, :-3], atol=1e-5)


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("camera.not_a_key=1", "unknown config key 'camera.not_a_key'"),
        ("camera.aperture_radius_mm=-2", "aperture_radius_mm"),
        ("camera.sensor.pixel_pitch_um=0", "pixel_pitch_um"),
        ("camera.doe.cell_size_um=20000", "larger than the aperture"),
        ("camera.psf.kernel_px=101", "at least 141 px"),
        ("camera.lens.model=zoom", "camera.lens.model"),
    ],
)
def test_psf_bad_config_is_one_clean_line(tmp_path, override, fragment):
    assert_clean_error(run_cli_in_process("psf", "--out", str(tmp_path), "--set", override), fragment)


@pytest.mark.parametrize(
    "distance_mm, fragments",
    [
        # 5 mm lens: 1 µm would need ~54 000 quadrature nodes per pixel (a 22 GiB matrix: OOM-killed before)
        ("0.001", ("camera.sensor_distance_mm=0.001 is implausible", "the sensor belongs near 5 mm",
                   "so the PSF would alias", "pupil_oversample >= 85698", "PiB of memory")),
        # 100× the focal length: a 2001 px kernel whose report ran out of memory before
        ("500", ("camera.sensor_distance_mm=500 is implausible", "the sensor belongs near 5 mm",
                 "blurs a point over 119 mm at 420 nm", "check the value (in mm)")),
    ],
)
def test_psf_refuses_implausible_sensor_distances_before_allocating(tmp_path, distance_mm, fragments):
    out = tmp_path / "p"
    # a process of its own, with a timeout: were the check to regress, the allocation (22 GiB and more,
    # OOM-killed before) must not take the test process with it
    proc = run_cli("psf", "--config", "tiny", "--set", f"camera.sensor_distance_mm={distance_mm}", "--out", str(out),
                      timeout=120, env={"HSICAM_MEMORY_BUDGET_MB": "2000"})
    assert_clean_error(proc, *fragments)
    assert not out.exists()


def test_psf_deliberate_defocus_needs_the_pupil_sampling_it_implies(tmp_path):
    """10 % behind the focus of the tiny 5 mm lens the residual defocus aliases on 30 µm cells
    (blur 0.12 mm > field λz/Δ = 0.077 mm at 420 nm): refused with the oversampling that fixes it,
    which then runs; a 4 % defocus (blur 0.05 mm) runs as it is."""
    proc = run_cli_in_process("psf", "--config", "tiny", "--set", "camera.sensor_distance_mm=5.5", "--out", str(tmp_path / "a"))
    assert_clean_error(proc, "camera.sensor_distance_mm=5.5 defocuses the lens more than the pupil sampling can "
                             "represent", "raise camera.psf.pupil_oversample to at least 2")
    for overrides in (["camera.sensor_distance_mm=5.5", "camera.psf.pupil_oversample=2"],
                      ["camera.sensor_distance_mm=5.2"]):
        out = tmp_path / overrides[-1]
        proc = run_cli_in_process("psf", "--config", "tiny", *[a for o in overrides for a in ("--set", o)], "--out", str(out))
        assert proc.returncode == 0, proc.stderr
        assert json.loads((out / "psf.json").read_text())["lens"]["sensor_distance_mm"] == pytest.approx(
            float(overrides[0].split("=")[1]))


@pytest.mark.parametrize(
    "override, fragments",
    [
        # 300 µm pixels span 4.3 far-field periods: 562 Gauss–Legendre nodes per pixel (a 562² matrix)
        ("camera.sensor.pixel_pitch_um=300", ("562 quadrature nodes", "camera.sensor.pixel_pitch_um",
                                              "camera.psf.supersample=1")),
        # 3 mm aperture: 201 cells of 30 µm, 405-point FFTs (18 MiB per batch of 4 wavelengths)
        ("camera.aperture_radius_mm=3", ("the 201-sample pupil", "FFTs of 405 points per axis",
                                         "camera.aperture_radius_mm")),
        ("camera.psf.kernel_px=401", ("the 401×401 px kernel (camera.psf.kernel_px)",)),
    ],
)
def test_psf_sampling_plan_over_the_memory_budget_is_refused(tmp_path, override, fragments):
    out = tmp_path / "p"
    proc = run_cli_in_process("psf", "--config", "tiny", "--set", override, "--out", str(out), env={"HSICAM_MEMORY_BUDGET_MB": "4"})
    assert_clean_error(proc, "the PSF sampling plan needs at least", "over the memory budget of 4 MiB", *fragments)
    assert not out.exists()
    # the tiny camera itself (81-point FFTs, 21 px kernel) fits that budget
    proc = run_cli_in_process("psf", "--config", "tiny", "--out", str(out), env={"HSICAM_MEMORY_BUDGET_MB": "4"})
    assert proc.returncode == 0, proc.stderr


def test_bad_config_file(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("camera:\n  doe:\n    sigma_heigth_nm: 3\n")
    assert_clean_error(run_cli_in_process("psf", "--config", str(cfg), "--out", str(tmp_path / "o")), "sigma_heigth_nm")


def test_simulate_band_count_mismatch(tmp_path):
    np.save(tmp_path / "scene.npy", np.ones((5, 30, 30), np.float32))
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(tmp_path / "o"), *TINY)
    assert_clean_error(proc, "5 bands", "7")
    assert not (tmp_path / "o" / "sensor.npy").exists()


def test_simulate_reads_npy_scenes_on_the_grid_data_npy_bands_gives(tmp_path):
    """With ``data.npy_bands`` a .npy scene of another band count is resampled from that grid, so
    its sensor image equals the one of the same cube written as our HDF5 with that grid."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    fine = Bands.uniform(410, 730, 20)  # 17 bands around the camera's 7 (420-720 nm / 50)
    cube = np.random.default_rng(2).random((len(fine), 30, 30)).astype(np.float32)
    np.save(tmp_path / "scene.npy", cube)
    write_cube_h5(tmp_path / "scene.h5", cube, fine)
    grid = ["--set", "data.npy_bands={start_nm: 410, stop_nm: 730, step_nm: 20}"]
    for name, extra in (("scene.npy", grid), ("scene.h5", [])):
        proc = run_cli_in_process("simulate", "--scene", str(tmp_path / name), "--out", str(tmp_path / name[-3:]), *TINY, *extra)
        assert proc.returncode == 0, proc.stderr
    np.testing.assert_allclose(np.load(tmp_path / "npy" / "sensor.npy"), np.load(tmp_path / ".h5" / "sensor.npy"), rtol=1e-6)


def test_simulate_band_grid_mismatch(tmp_path):
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    write_cube_h5(tmp_path / "scene.h5", np.ones((7, 30, 30), np.float32), Bands.uniform(400, 700, 50))
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.h5"), "--out", str(tmp_path / "o"), *TINY)
    assert_clean_error(proc, "scene.h5")


@pytest.mark.parametrize("kind", ["dd_cassi", "sd_cassi"])
def test_simulate_refuses_valid_boundary_on_a_cassi_camera(tmp_path, kind):
    """A CASSI camera has no PSF kernel (margin 0): --boundary valid gave the default's sensor image and
    recorded "valid" in simulate.json. It is one line now, nothing written; the default still works."""
    np.save(tmp_path / "scene.npy", np.ones((31, 24, 24), np.float32))
    out = tmp_path / "o"
    cassi = ["--config", "dd_cassi_rdn", "--set", f"camera.kind={kind}"]
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(out),
                              "--boundary", "valid", *cassi)
    assert_clean_error(proc, f"--boundary valid: the {kind} camera images without a PSF", "no kernel margin to crop",
                       "drop --boundary")
    assert not out.exists()
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(out), *cassi)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "simulate.json").read_text())["boundary"] == "same"


def test_simulate_missing_scene(tmp_path):
    assert_clean_error(run_cli_in_process("simulate", "--scene", str(tmp_path / "nope.npy"), "--out", str(tmp_path)), "nope.npy")


def test_simulate_scene_too_small_for_valid(tmp_path):
    np.save(tmp_path / "scene.npy", np.ones((7, 10, 10), np.float32))
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "scene.npy"), "--out", str(tmp_path / "o"), "--boundary", "valid", *TINY)
    assert_clean_error(proc, "too small")


def test_simulate_refusal_says_a_mat_files_grid_was_assumed(tmp_path):
    """A MAT cube without a band list is read on its format's assumed grid (ICVL: 400-700 nm); when that
    does not cover the camera, the one line says the grid was assumed and how to give the real one."""
    import scipy.io

    scipy.io.savemat(tmp_path / "icvl.mat", {"rad": np.ones((40, 40, 31), np.float32)})
    proc = run_cli_in_process("simulate", "--scene", str(tmp_path / "icvl.mat"), "--out", str(tmp_path / "o"), *TINY)
    assert proc.returncode == 2
    assert ("not covered by the data's 400-700 nm" in proc.stderr and "the file lists no wavelengths, so its bands "
            "were assumed to be 31 bands, 400-700 nm in 10 nm steps; add its band list as a variable 'bands'"
            in proc.stderr), proc.stderr
