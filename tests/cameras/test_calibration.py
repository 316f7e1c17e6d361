"""Measured PSFs, fine-tuning with frozen optics, raw-capture preprocessing, seamless tiling.

``fab_run`` (tests/fab_runs.py; shared with test_export / test_tolerance / test_reader_robustness) is a small trained run on
the 3-band tiny optics (conftest) with a homogeneous dataset (smooth abundance maps of three
fixed smooth spectra), trained with the optics frozen, so its network actually depends on the
PSFs (it drops > 2 dB when the band throughput changes) and fine-tuning effects are measurable.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_helpers import assert_clean_error, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import fab_run, write_psf_dir  # noqa: F401 - the shared fixture
from hsicam.cameras import DOECamera
from hsicam.cameras.measured import FixedPSFCamera
from hsicam.config import load_config
from hsicam.data.measured_psf import (
    centroid, import_for_camera, import_psf_dir, overlap_matrix, resample_area, wavelength_from_name,
)
from hsicam.runs.measured_psf import load_measured_psf
from hsicam.data.images import RawCorrection, normalised_flat, preprocess_raw, read_capture
from hsicam.errors import InputError
from hsicam.io import write_json
from hsicam.spectral import Bands


# ------------------------------------------------------------------------------------------------
# Area resampling against an independent reference
# ------------------------------------------------------------------------------------------------
def test_area_resampling_matches_fine_grid_reference():
    """Input pitch 3, output pitch 2 (units), output window starting at 5: upsample the input ×3 by
    replication (each unit sample carries 1/3 × 1/3 of its pixel), then sum 2×2 unit blocks."""
    rng = np.random.default_rng(0)
    img = rng.random((9, 11))
    unit = np.kron(img, np.ones((3, 3))) / 9.0  # 27 × 33 unit samples
    out = np.zeros((7, 7))
    big = np.zeros((40, 40))
    big[: unit.shape[0], : unit.shape[1]] = unit
    for i in range(7):
        for j in range(7):
            out[i, j] = big[5 + 2 * i : 7 + 2 * i, 5 + 2 * j : 7 + 2 * j].sum()
    wy = overlap_matrix(7, 2.0, 5.0, 9, 3.0)
    wx = overlap_matrix(7, 2.0, 5.0, 11, 3.0)
    np.testing.assert_allclose(wy @ img @ wx.T, out, rtol=1e-12, atol=1e-12)
    # centre convention: the output's centre pixel is centred on input point (3.5, 4.5), i.e. at
    # (3.5 + 0.5)·3 = 12 and 15 units; its window starts 7 units before: at 5 and 8
    got = resample_area(img, 3.0, 2.0, (3.5, 4.5), 7)
    ref = np.zeros((7, 7))
    for i in range(7):
        for j in range(7):
            ref[i, j] = big[5 + 2 * i : 7 + 2 * i, 8 + 2 * j : 10 + 2 * j].sum()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    # energy: a window covering the whole input keeps every bit of it
    assert abs(resample_area(img, 3.0, 2.0, (4.0, 5.0), 41).sum() - img.sum()) < 1e-10


def test_wavelength_from_file_names():
    assert wavelength_from_name("psf_450nm") == 450.0
    assert wavelength_from_name("band03_552.5 nm") == 552.5
    assert wavelength_from_name("600") == 600.0
    assert wavelength_from_name("psf") is None
    assert wavelength_from_name("450nm_500nm") is None


# ------------------------------------------------------------------------------------------------
# Measured-PSF import: another pitch, off-centre, mixed formats
# ------------------------------------------------------------------------------------------------
def _fine_camera_pair(tiny_config, *overrides):
    """The tiny camera with the s×s midpoint rule (supersample 3) and the same optics sampled s×
    finer with supersample 1 (point values): s×s sum-pooling of the fine PSF around the axis is
    exactly the coarse PSF."""
    cam = DOECamera.from_config(tiny_config(*overrides, "camera.psf.supersample=3"))
    s = cam.optics.sampling.supersample
    pitch = 10.0 / s
    fine = DOECamera.from_config(tiny_config(*overrides, f"camera.sensor.pixel_pitch_um={pitch}", "camera.psf.supersample=1",
                                                  f"camera.psf.kernel_px={s * cam.kernel_px}"))
    fine.load_state_dict(cam.state_dict())
    assert fine.optics.sampling.fft_size == cam.optics.sampling.fft_size
    with torch.no_grad():
        coarse, fine = cam.psf().double().numpy(), fine.psf().double().numpy()
    # the images hold only the light inside the fine kernel (square cells send the rest beyond it,
    # issue 13), and a "sum"-normalised import scales that to 1: compare with the coarse PSF scaled alike
    return coarse / fine.sum(axis=(1, 2))[:, None, None], fine, pitch, cam


def _save_band_images(d: Path, fine: np.ndarray, bands: Bands, offset: tuple[int, int], canvas: tuple[int, int]) -> tuple[int, int]:
    """One image per band, each in a different format, PSF axis at centre + offset; returns the axis."""
    import imageio.v3 as iio
    import tifffile

    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    k = fine.shape[-1]
    ay, ax = canvas[0] // 2 + offset[0], canvas[1] // 2 + offset[1]
    for i, lam in enumerate(bands.centers_nm):
        img = np.zeros(canvas)
        img[ay - k // 2 : ay + k // 2 + 1, ax - k // 2 : ax + k // 2 + 1] = fine[i]
        img *= 1234.5  # arbitrary exposure: normalize "sum" removes it
        if i == 0:
            tifffile.imwrite(d / f"psf_{lam:g}nm.tif", img.astype(np.float32))
        elif i == 1:
            iio.imwrite(d / f"{lam:g}.png", np.round(img / img.max() * 65535).astype(np.uint16))
        else:
            np.save(d / f"band_{lam:g}nm.npy", img.astype(np.float64))
    return ay, ax


def test_measured_psf_at_another_pitch_and_off_centre_comes_back(tiny_config, tmp_path):
    coarse, fine, pitch, cam = _fine_camera_pair(tiny_config)
    d = tmp_path / "psf"
    ay, ax = _save_band_images(d, fine, cam.bands, (7, -13), (61, 90))
    write_json(d / "psf.json", {"pixel_pitch_um": pitch, "centre": "axis", "axis_px": [ay, ax]})
    m = import_for_camera(d, cam)
    assert m.psf.shape == coarse.shape
    peak = coarse.max(axis=(1, 2))
    err = np.abs(m.psf - coarse).max(axis=(1, 2)) / peak
    assert err[0] < 1e-5 and err[2] < 1e-5, err  # float TIFF and float64 npy: exact up to float32
    assert err[1] < 2e-4, err  # 16-bit PNG quantisation
    np.testing.assert_allclose(m.report["energy_in_kernel"], coarse.sum(axis=(1, 2)), atol=2e-4)
    # the same images at the camera's own pitch, pre-pooled, come back identically
    d2 = write_psf_dir(tmp_path / "psf6", coarse, cam.bands, 10.0, centre="axis", axis_px=[coarse.shape[-1] // 2] * 2)
    np.testing.assert_allclose(import_for_camera(d2, cam).psf, coarse, rtol=0, atol=1e-7)


def test_centroid_and_peak_centring(tiny_config, tmp_path):
    """Centroid (common to all bands) and peak: independent of where the PSF sits in the frame,
    and the band-summed centroid lands on the kernel centre to within the measurement pixel."""
    coarse, fine, pitch, cam = _fine_camera_pair(tiny_config, "camera.doe.enabled=false")
    results = {}
    for centre in ("centroid", "peak", "centroid_per_band"):
        outs = []
        for off in ((0, 0), (9, -17)):
            d = tmp_path / f"{centre}{off[0]}"
            _save_band_images(d, fine, cam.bands, off, (70, 95))
            write_json(d / "psf.json", {"pixel_pitch_um": pitch, "centre": centre})
            outs.append(import_for_camera(d, cam).psf)
        np.testing.assert_allclose(outs[0], outs[1], atol=2e-6)
        results[centre] = outs[0]
    k = coarse.shape[-1]
    cy, cx = centroid(results["centroid"].sum(axis=0))
    s = cam.optics.sampling.supersample
    assert abs(cy - k // 2) <= 0.5 / s + 0.02 and abs(cx - k // 2) <= 0.5 / s + 0.02
    # without a DOE the PSF is an Airy pattern: its peak is the axis, so 'peak' is exact
    np.testing.assert_allclose(results["peak"], coarse, atol=2e-4 * coarse.max())


def test_measured_psf_energy_and_errors(tiny_camera, tmp_path):
    cam = tiny_camera()
    k = cam.kernel_px
    bands = cam.bands
    # a uniform square 3 camera pixels wider than the kernel: the kernel holds (k/(k+3))² of it
    big = np.ones((3, (k + 3) * 2, (k + 3) * 2))
    m = import_psf_dir(write_psf_dir(tmp_path / "big", big, bands, 5.0), bands, 10e-6, k)
    np.testing.assert_allclose(m.report["energy_in_kernel"], (k / (k + 3)) ** 2, rtol=1e-9)
    np.testing.assert_allclose(m.psf.sum(axis=(1, 2)), (k / (k + 3)) ** 2, rtol=1e-6)
    # errors, each one InputError naming the problem
    with pytest.raises(InputError, match="pitch"):
        import_psf_dir(write_psf_dir(tmp_path / "p", big, bands, 5.0), bands, 10e-6, k, pitch_um=-1.0)
    d = write_psf_dir(tmp_path / "miss", big[:2], Bands.uniform(500, 550, 50), 5.0)
    with pytest.raises(InputError, match="600"):
        import_psf_dir(d, bands, 10e-6, k)
    nan = big.copy()
    nan[1, 3, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        import_psf_dir(write_psf_dir(tmp_path / "nan", nan, bands, 5.0), bands, 10e-6, k)
    with pytest.raises(InputError, match="no positive signal"):
        import_psf_dir(write_psf_dir(tmp_path / "zero", np.zeros_like(big), bands, 5.0), bands, 10e-6, k)
    nameless = tmp_path / "nameless"
    nameless.mkdir()
    np.save(nameless / "psf_a.npy", np.ones((5, 5)))
    write_json(nameless / "psf.json", {"pixel_pitch_um": 5.0})
    with pytest.raises(InputError, match="wavelength"):
        import_psf_dir(nameless, bands, 10e-6, k)
    with pytest.raises(InputError, match="no such PSF folder"):
        import_psf_dir(tmp_path / "nope", bands, 10e-6, k)


def _gaussian_spots(bands: Bands, size: int = 64, width_px: float = 2.0) -> np.ndarray:
    """(C, size, size) unit-sum Gaussian spots, centred, one per band (a PSF in energy fractions)."""
    r = np.arange(size) - size // 2
    spot = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * width_px**2))
    return np.repeat((spot / spot.sum())[None], len(bands), axis=0)


def test_background_border_is_the_frame_median_and_a_number_is_subtracted(tiny_camera, tmp_path):
    """No test held `background` (a mutant that never subtracted it passed): a black level of 200 DN with a hot
    pixel in the frame comes off with `border` (the median ignores the hot pixel) or with the number 200."""
    cam = tiny_camera()
    bands, k = cam.bands, cam.kernel_px
    spots = _gaussian_spots(bands)
    counts = 40000 * spots / spots.max(axis=(1, 2), keepdims=True)
    counts[:, 0, 0] = 59800.0  # a hot pixel in the frame: it would lift the frame's mean by ~80 DN, not its median
    want = import_psf_dir(write_psf_dir(tmp_path / "clean", counts, bands, 10.0, normalize="sum"), bands, 10e-6, k).psf
    black = counts + 200.0
    for background in ("border", 200.0):
        got = import_psf_dir(write_psf_dir(tmp_path / f"b{background}", black, bands, 10.0, normalize="sum",
                                           background=background), bands, 10e-6, k)
        np.testing.assert_allclose(got.psf, want, atol=1e-9)


def test_a_black_level_left_in_is_warned_about_naming_background(tiny_camera, tmp_path, caplog):
    """A 200 DN pedestal with the default `background: none` was taken as PSF light (the imported PSF 0.96 off) and
    the warning sent the user to axis_px and the pitch."""
    import logging

    cam = tiny_camera()
    bands, k = cam.bands, cam.kernel_px
    spots = _gaussian_spots(bands)
    counts = 40000 * spots / spots.max(axis=(1, 2), keepdims=True) + 200.0
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        import_psf_dir(write_psf_dir(tmp_path / "ped", counts, bands, 10.0, normalize="sum"), bands, 10e-6, k)
    assert "if that is a black level (pedestal, dark current), it is counted as PSF light" in caplog.text
    assert "set background: border" in caplog.text and ": 0.5 %" in caplog.text  # 200 of 40200 at the peak
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        import_psf_dir(write_psf_dir(tmp_path / "ok", counts, bands, 10.0, normalize="sum", background="border"),
                       bands, 10e-6, k)
    assert "black level" not in caplog.text


def test_normalize_none_refuses_images_that_are_not_energy_fractions(tiny_camera, tmp_path):
    """`normalize: none` with 16-bit counts was accepted: a camera ~10⁵ times too bright, fine-tuned on silently."""
    cam = tiny_camera()
    bands, k = cam.bands, cam.kernel_px
    spots = _gaussian_spots(bands)
    with pytest.raises(InputError, match=r"with normalize: none .* sums to 1\.00\d+e\+06 \(counts\?\): set normalize: sum"):
        import_psf_dir(write_psf_dir(tmp_path / "dn", 40000 * spots / spots.max(), bands, 10.0, normalize="none"),
                       bands, 10e-6, k)
    m = import_psf_dir(write_psf_dir(tmp_path / "frac", 0.9 * spots, bands, 10.0, normalize="none"), bands, 10e-6, k)
    # fractions kept as given (10 % of the light lost before the image), less what falls outside the kernel
    np.testing.assert_allclose(m.psf.sum(axis=(1, 2)), 0.9 * np.asarray(m.report["energy_in_kernel"]), rtol=1e-5)
    assert m.report["psf_dir"] == str((tmp_path / "frac").resolve())


def test_fixed_psf_camera_keeps_the_state_dict(tiny_camera):
    cam = tiny_camera()
    with torch.no_grad():
        psf = cam.psf() * 0.5
    fixed = FixedPSFCamera.from_camera(cam, psf)
    assert set(fixed.state_dict()) == set(cam.state_dict())
    x = torch.rand(1, 3, 20, 20)
    with torch.no_grad():
        torch.testing.assert_close(fixed.A(x), cam.A(x, psf))
        torch.testing.assert_close(fixed(x), cam.A(x, psf))  # noise sigma 0


# ------------------------------------------------------------------------------------------------
# Fine-tuning with frozen optics
# ------------------------------------------------------------------------------------------------
def test_finetune_improves_psnr_on_perturbed_psfs(fab_run, tmp_path):
    """Measured PSFs with a band throughput of 0.5..1 (radiometric, normalize: none): the trained
    network loses > 1.5 dB on data made with them; fine-tuning recovers it, and the tuned network
    is now specific to them (worse on the nominal PSFs than the original network)."""
    from hsicam.runs.folder import load_run
    from hsicam.engine.tolerance import evaluate_psf, evaluation_scenes

    cfg, base = load_run(fab_run)
    with torch.no_grad():
        nominal = base.camera.psf().double().numpy()
    perturbed = nominal * np.linspace(0.5, 1.0, len(base.bands))[:, None, None]
    k = nominal.shape[-1]
    d = write_psf_dir(tmp_path / "measured", perturbed, base.bands, 10.0, centre="axis", axis_px=[k // 2, k // 2],
                      normalize="none")
    run2 = tmp_path / "run2"
    res = run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(d), "--out", str(run2), "--epochs", "10", "--lr", "0.001")
    assert res.returncode == 0, res.stderr
    assert "fine-tuned" in res.stdout
    summary = json.loads((run2 / "finetune.json").read_text())
    assert summary["best_val_psnr"] > summary["before"]["psnr"]
    # "before" is the validation of the starting weights (step 0), "after_last_epoch" the last one: read back
    vals = [r for r in map(json.loads, (run2 / "metrics.jsonl").read_text().splitlines())
            if "val_psnr" in r and not r.get("final")]
    assert vals[0]["step"] == 0 and len(vals) == 11
    assert summary["before"] == {k[4:]: v for k, v in vals[0].items() if k.startswith("val_")}
    assert summary["after_last_epoch"]["psnr"] == vals[-1]["val_psnr"] != vals[0]["val_psnr"]
    assert summary["best_val_psnr"] == max(r["val_psnr"] for r in vals)
    # independent check on whole scenes
    scenes, names = evaluation_scenes(cfg, base.bands, 8)
    _, tuned = load_run(run2)  # a fine-tuned run images with its measured PSFs
    measured = load_measured_psf(run2 / "measured_psf.safetensors")
    assert isinstance(tuned.camera, FixedPSFCamera)
    np.testing.assert_allclose(measured.psf, perturbed, atol=1e-7)
    p_meas = torch.from_numpy(measured.psf)
    p_nom = torch.from_numpy(nominal.astype(np.float32))
    base_nom = evaluate_psf(base, p_nom, scenes, names)["psnr"]
    base_meas = evaluate_psf(base, p_meas, scenes, names)["psnr"]
    tuned_meas = evaluate_psf(tuned, p_meas, scenes, names)["psnr"]
    tuned_nom = evaluate_psf(tuned, p_nom, scenes, names)["psnr"]
    assert base_nom - base_meas > 1.5, (base_nom, base_meas)
    assert tuned_meas - base_meas > 1.5, (base_meas, tuned_meas)
    assert tuned_nom < base_nom, (tuned_nom, base_nom)
    # the tuned run is a normal run: plain load_run loads it (weights have the standard layout), and fine-tuning
    # froze the optics: every camera tensor is the source run's, bit for bit (the CFA
    # weights drifted by 7e-5 here when the camera's groups were left to the optimizer)
    base_sd, plain_sd = base.state_dict(), tuned.state_dict()
    optics = [k for k in base_sd if not k.startswith("net.")]
    assert any("cfa" in k for k in optics) and set(optics) <= set(plain_sd)
    for key in optics:
        assert torch.equal(plain_sd[key], base_sd[key]), key
    # reconstruct with --psf-dir knows the network was tuned to these PSFs
    np.save(tmp_path / "cap.npy", np.random.default_rng(0).random((30, 34)).astype(np.float32))
    out = tmp_path / "rec.h5"
    rec = run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(run2), "--out", str(out), "--psf-dir", str(d))
    assert rec.returncode == 0, rec.stderr
    import h5py

    with h5py.File(out, "r") as f:
        meta = json.loads(f.attrs["metadata_json"])
    assert meta["network_tuned_to_psfs"] is True and meta["psf_fingerprint"] == measured.fingerprint
    assert load_measured_psf(run2 / "measured_psf.safetensors").fingerprint == measured.fingerprint
    # with a consistency step, --psf-dir makes the step explain the capture with the measured PSFs,
    # also for a run that was not tuned to them (it images with its design PSFs otherwise)
    out1 = tmp_path / "rec1.h5"
    rec = run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out1), "--psf-dir",
                  str(d), "--consistency-steps", "1")
    assert rec.returncode == 0, rec.stderr
    from hsicam.data.formats import read_hsicam_h5

    got = read_hsicam_h5(out1)[0]
    _, sys1 = load_run(fab_run)
    sys1.consistency = dataclasses.replace(cfg.model.consistency, iterations=1)
    cap = torch.from_numpy(np.load(tmp_path / "cap.npy"))[None, None]
    with torch.no_grad():
        through_design = sys1.reconstructor()(cap)[0].clamp_min(0).numpy()
        sys1.step_camera = FixedPSFCamera.from_camera(sys1.camera, p_meas)
        through_measured = sys1.reconstructor()(cap)[0].clamp_min(0).numpy()
    assert np.abs(through_measured - through_design).max() > 1e-3  # the two operators differ here
    np.testing.assert_allclose(got, through_measured, rtol=1e-4, atol=1e-5)


def test_finetune_cli_errors(fab_run, tmp_path):
    assert_clean_error(run_cli_in_process("finetune", "--run", str(tmp_path / "nope"), "--psf-dir", str(tmp_path), "--out", str(tmp_path / "o")),
                       "nope: no such run folder")
    d = tmp_path / "empty"
    d.mkdir()
    write_json(d / "psf.json", {"pixel_pitch_um": 10.0})
    assert_clean_error(run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(d), "--out", str(tmp_path / "o")),
                       "no PSF images")
    assert not (tmp_path / "o").exists()
    # the camera is what it is: a pixel pitch given here resampled the PSFs for a sensor it does not have
    for key in ("camera.sensor.pixel_pitch_um=4", "bands.step_nm=10", "camera.cfa.period=3"):
        assert_clean_error(run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(d), "--set", key,
                                              "--out", str(tmp_path / "o")),
                           f"--set {key.split('=')[0]}: fine-tuning keeps the camera it fine-tunes")
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------------------
# Raw captures
# ------------------------------------------------------------------------------------------------
def test_a_16bit_png_opened_as_32bit_mode_i_keeps_its_16bit_full_scale(tmp_path, monkeypatch):
    """Pillow < 10 (the dependency allows 9.1) opens a 16-bit grey PNG in mode "I" (int32): it is read as
    the uint16 it stores, full scale 65535, not refused as a 32-bit capture without a white level."""
    from PIL import Image

    values = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 1300 + 17)
    Image.fromarray(values).save(tmp_path / "c.png")
    expected, _ = read_capture(tmp_path / "c.png")
    opened = Image.open

    def open_as_mode_i(*args, **kwargs):  # what Pillow 9 returns for this file
        im = opened(*args, **kwargs)
        return im.convert("I") if im.format == "PNG" and im.mode.startswith("I;16") else im

    monkeypatch.setattr(Image, "open", open_as_mode_i)
    assert Image.open(tmp_path / "c.png").mode == "I"
    img, report = read_capture(tmp_path / "c.png")
    assert report["stored_dtype"] == "uint16"
    np.testing.assert_array_equal(img, expected)
    np.testing.assert_allclose(img, values / 65535.0, rtol=1e-6)


def test_raw_preprocessing_reference():
    """g = (raw − dark)/(white − black)/flat_norm · t_ref/t_exp, against a direct computation."""
    rng = np.random.default_rng(1)
    h, w = 12, 18
    signal = rng.random((h, w))
    vignette = 0.6 + 0.4 * rng.random((h, w))
    black, white = 64.0, 4095.0
    dark = black + rng.random((h, w)) * 5
    raw = np.round(dark + signal * vignette * (white - black) * 0.5)
    flat = black + vignette * 2000.0
    corr = RawCorrection(black_level=black, white_level=white, dark=dark, flat=flat, exposure_s=0.02, reference_exposure_s=0.01)
    img, rep = preprocess_raw(raw, 65535.0, corr)
    flat_norm = vignette / vignette.mean()
    ref = (raw - dark) / (white - black) / flat_norm * 0.5
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6)
    assert rep["black_level_dn"] == black and rep["saturated_px"] == 0
    # no black level given: the dark frame's median is used for the scale
    img2, rep2 = preprocess_raw(raw, 65535.0, RawCorrection(dark=dark, white_level=white))
    assert rep2["black_level_dn"] == pytest.approx(float(np.median(dark)))
    np.testing.assert_allclose(img2, (raw - dark) / (white - np.median(dark)), rtol=1e-5)
    # a flat through a period-3 CFA: averaging over the period removes the CFA pattern, keeps vignetting
    cfa = np.tile(np.array([[0.5, 1.0, 1.5], [1.0, 1.5, 0.5], [1.5, 0.5, 1.0]]), (4, 6))
    flat_cfa = black + 2000.0 * cfa
    img3, _ = preprocess_raw(raw, 65535.0, RawCorrection(black_level=black, white_level=white, flat=flat_cfa, flat_period=3))
    # ... on the border rows and columns too (edge replication left the pattern there: ±25 % at period 3)
    np.testing.assert_allclose(img3, (raw - black) / (white - black), rtol=1e-4)
    for hh, ww in ((11, 17), (2, 5)):  # sizes that are no multiple of the period, or below it
        flat_n = normalised_flat(flat_cfa[:hh, :ww], black, 3)
        assert flat_n.shape == (hh, ww) and np.all(np.isfinite(flat_n))
        if hh >= 3 and ww >= 3:
            np.testing.assert_allclose(flat_n, 1.0, rtol=1e-9)
    with pytest.raises(InputError, match="--flat-mode cfa"):  # a CFA flat used pixel-wise: the hint
        preprocess_raw(raw, 65535.0, RawCorrection(black_level=black, white_level=white,
                                                   flat=black + 2000.0 * np.where(cfa > 1.2, 1.0, 0.01)))
    # bad inputs
    with pytest.raises(InputError, match="both"):
        RawCorrection(exposure_s=0.1)
    with pytest.raises(InputError, match="white level"):
        preprocess_raw(raw, 65535.0, RawCorrection(black_level=5000.0, white_level=4095.0))
    with pytest.raises(InputError, match="flat field"):
        preprocess_raw(raw, 65535.0, RawCorrection(flat=np.zeros((h, w))))
    with pytest.raises(InputError, match="12×18"):
        preprocess_raw(raw, 65535.0, RawCorrection(dark=np.zeros((3, 3))))


def test_raw_capture_formats_agree(tmp_path):
    """The same 16-bit capture as PNG, TIFF and .npy reads identically (DN / 65535)."""
    import imageio.v3 as iio
    import tifffile

    raw = np.random.default_rng(2).integers(0, 65536, (17, 23)).astype(np.uint16)
    iio.imwrite(tmp_path / "c.png", raw)
    tifffile.imwrite(tmp_path / "c.tif", raw)
    np.save(tmp_path / "c.npy", raw)
    outs = [read_capture(tmp_path / f"c.{ext}")[0] for ext in ("png", "tif", "npy")]
    for o in outs:
        np.testing.assert_allclose(o, raw / 65535.0, rtol=2e-7, atol=0)
    img, rep = read_capture(tmp_path / "c.tif", RawCorrection(black_level=100.0, white_level=60000.0))
    np.testing.assert_allclose(img, (raw.astype(np.float64) - 100) / 59900, rtol=1e-5, atol=1e-6)
    assert rep["saturated_px"] == int(np.count_nonzero(raw >= 60000))


def test_reconstruct_raw_capture_cli_tiled_equals_whole(fab_run, tmp_path):
    """A 16-bit TIFF capture with dark and flat frames: tiled (16 px tiles) and whole-image
    reconstructions agree; the preprocessing is recorded in the output file."""
    import h5py
    import tifffile

    from hsicam.data import read_cube

    rng = np.random.default_rng(3)
    h, w = 45, 52
    dark = (100 + rng.integers(0, 8, (h, w))).astype(np.uint16)
    flat = (100 + 3000 * (0.8 + 0.2 * rng.random((h, w)))).astype(np.uint16)
    raw = (dark + rng.integers(0, 20000, (h, w))).astype(np.uint16)
    for name, a in (("raw", raw), ("dark", dark), ("flat", flat)):
        tifffile.imwrite(tmp_path / f"{name}.tif", a)
    common = ["--run", str(fab_run), "--dark", str(tmp_path / "dark.tif"), "--flat", str(tmp_path / "flat.tif"),
              "--black-level", "100", "--white-level", "40000", "--exposure-s", "0.5", "--reference-exposure-s", "0.25"]
    r1 = run_cli_in_process("reconstruct", str(tmp_path / "raw.tif"), "--out", str(tmp_path / "tiled.h5"), "--tile", "16", *common)
    assert r1.returncode == 0, r1.stderr
    r2 = run_cli_in_process("reconstruct", str(tmp_path / "raw.tif"), "--out", str(tmp_path / "whole.h5"), "--tile", "512", *common)
    assert r2.returncode == 0, r2.stderr
    tiled, _, _ = read_cube(tmp_path / "tiled.h5")
    whole, _, _ = read_cube(tmp_path / "whole.h5")
    assert tiled.shape == (3, h, w)
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5)
    with h5py.File(tmp_path / "whole.h5", "r") as f:
        meta = json.loads(f.attrs["metadata_json"])
    assert meta["preprocessing"]["black_level_dn"] == 100.0 and meta["preprocessing"]["exposure_s"] == 0.5
    # which frames corrected it, by absolute path (a reconstruct hunt, session 72: only their statistics were kept)
    assert meta["preprocessing"]["dark_frame"] == str((tmp_path / "dark.tif").resolve())
    assert meta["preprocessing"]["flat_frame"] == str((tmp_path / "flat.tif").resolve())
    # the CLI preprocessing equals the library's
    from hsicam.data.images import read_image_2d

    corr = RawCorrection(black_level=100.0, white_level=40000.0, dark=read_image_2d(tmp_path / "dark.tif").data,
                         flat=read_image_2d(tmp_path / "flat.tif").data, exposure_s=0.5, reference_exposure_s=0.25)
    img, _ = read_capture(tmp_path / "raw.tif", corr)
    from hsicam.runs.folder import load_run

    _, model = load_run(fab_run)
    with torch.no_grad():
        ref = model.reconstruct(torch.from_numpy(img)[None, None])[0].clamp_min(0).numpy()
    np.testing.assert_allclose(whole, ref, rtol=1e-5, atol=1e-5)
    # mismatched dark frame size: one-line error, no output file
    tifffile.imwrite(tmp_path / "small.tif", dark[:10, :10])
    bad = run_cli_in_process("reconstruct", str(tmp_path / "raw.tif"), "--out", str(tmp_path / "bad.h5"), "--run", str(fab_run),
                  "--dark", str(tmp_path / "small.tif"))
    assert_clean_error(bad, "dark frame")
    assert not (tmp_path / "bad.h5").exists() and not (tmp_path / "bad_rgb.png").exists()


def test_psf_folder_written_by_hsicam_psf_is_read_exactly(tiny_config, tmp_path):
    res = run_cli_in_process("psf", *[a for o in (*TINY_CAMERA_OVERRIDES, "camera.psf.pupil_oversample=3") for a in ("--set", o)], "--out", str(tmp_path / "psf"))
    assert res.returncode == 0, res.stderr
    cam = DOECamera.from_config(tiny_config("camera.psf.pupil_oversample=3"))
    m = import_for_camera(tmp_path / "psf", cam)
    assert m.report["centre"] == "axis" and m.report["normalize"] == "none"
    assert max(b["kernel_sum"] for b in m.report["bands"]) < 0.99  # q = 3: higher orders fell outside the kernel
    with torch.no_grad():
        np.testing.assert_allclose(m.psf, cam.psf().numpy(), rtol=0, atol=1e-7)


# ------------------------------------------------------------------------------------------------
# Silent wrong results refused or warned about: white level, dark frame, PSF energy
# ------------------------------------------------------------------------------------------------
def _outputs_absent(out: Path) -> None:
    assert not out.exists() and not out.with_name(f"{out.stem}_rgb.png").exists()


def test_integer_capture_white_level(tmp_path, caplog):
    """32/64-bit integer captures have no natural full scale (their maximum is 2^31 − 1 or 2^63 − 1):
    refused without a white level; a 12-bit capture in a 16-bit file is warned about (1/16 of full
    scale), naming the white level to pass; a full-range 16-bit capture is not."""
    sensor = np.random.default_rng(4).random((20, 24)) * 0.8
    dn = np.round(sensor * 4095)
    for dtype in (np.int64, np.int32, np.uint32):
        p = tmp_path / f"c_{np.dtype(dtype).name}.npy"
        np.save(p, dn.astype(dtype))
        with pytest.raises(InputError, match="--white-level") as err:
            read_capture(p)
        assert str(p) in str(err.value) and np.dtype(dtype).name in str(err.value)
        img, rep = read_capture(p, RawCorrection(white_level=4095.0))  # with the white level: exact
        np.testing.assert_allclose(img, dn / 4095.0, rtol=1e-6)
        assert rep["white_level_dn"] == 4095.0
        img, _ = read_capture(p, RawCorrection(auto_level=0.5))  # auto-level does not need it
        assert float(np.percentile(img, 99.9)) == pytest.approx(0.5, rel=1e-5)
    # 12 bit in uint16: 16× too dark with the container's 65535 -> a warning naming the cause and the fix
    np.save(tmp_path / "c12.npy", dn.astype(np.uint16))
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        img, _ = read_capture(tmp_path / "c12.npy")
    np.testing.assert_allclose(img, dn / 65535.0, rtol=1e-6)  # still read as asked
    msgs = [r.getMessage() for r in caplog.records if "c12.npy" in r.getMessage()]
    assert len(msgs) == 1 and "12 bits" in msgs[0] and "--white-level 4095" in msgs[0], msgs
    # no warning: a full-range 16-bit capture, or the 12-bit one with its white level
    np.save(tmp_path / "c16.npy", np.round(sensor * 65535).astype(np.uint16))
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        read_capture(tmp_path / "c16.npy")
        img, _ = read_capture(tmp_path / "c12.npy", RawCorrection(white_level=4095.0))
    assert not [r for r in caplog.records if "dark" in r.getMessage()], [r.getMessage() for r in caplog.records]
    np.testing.assert_allclose(img, dn / 4095.0, rtol=1e-6)
    # 14 bit in uint16 (at most 1/4 of full scale: not "very dark"): read at a quarter of its level without a word,
    # its clipped pixels uncounted; its pixels at 16383 DN, a 14-bit sensor's white level, say so (session 73)
    dn14 = np.minimum(np.round(sensor * 1.3 * 16383), 16383)
    assert np.count_nonzero(dn14 == 16383) >= 3
    np.save(tmp_path / "c14.npy", dn14.astype(np.uint16))
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        img, rep = read_capture(tmp_path / "c14.npy")
    np.testing.assert_allclose(img, dn14 / 65535.0, rtol=1e-6)
    msgs = [r.getMessage() for r in caplog.records if "c14.npy" in r.getMessage()]
    assert len(msgs) == 1 and f"{np.count_nonzero(dn14 == 16383)} pixels sit at 16383 DN, a 14-bit sensor's white " \
        "level" in msgs[0] and "--white-level 16383" in msgs[0], msgs
    img, rep = read_capture(tmp_path / "c14.npy", RawCorrection(white_level=16383.0))
    assert rep["saturated_px"] == np.count_nonzero(dn14 == 16383)
    caplog.clear()
    np.save(tmp_path / "c14_unclipped.npy", np.round(sensor * 16383).astype(np.uint16))  # no pixel at 16383
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        read_capture(tmp_path / "c14_unclipped.npy")
    assert not caplog.records


def test_reconstruct_int64_capture_needs_white_level(fab_run, tmp_path):
    sensor = np.random.default_rng(5).random((30, 34))
    np.save(tmp_path / "cap.npy", np.round(sensor * 4095).astype(np.int64))
    out = tmp_path / "x.h5"
    res = run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out))
    assert_clean_error(res, "cap.npy", "int64", "--white-level")
    _outputs_absent(out)
    ok = run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out), "--white-level", "4095")
    assert ok.returncode == 0, ok.stderr
    assert out.is_file()


def test_raw_capture_without_signal_after_dark_subtraction(tmp_path, caplog):
    rng = np.random.default_rng(6)
    raw = np.round(rng.random((64, 64)) * 50000).astype(np.uint16)
    # a dark frame brighter than the capture: nothing left -> one InputError naming the dark frame
    with pytest.raises(InputError, match="dark frame.*nothing to reconstruct"):
        preprocess_raw(raw, 65535.0, RawCorrection(dark=np.full((64, 64), 60000.0, np.float32)), "cap.tif")
    with pytest.raises(InputError, match=r"dark frame \(median 60000 DN.*nothing to reconstruct"):  # black level given too
        preprocess_raw(raw, 65535.0, RawCorrection(black_level=100.0, dark=np.full((64, 64), 60000.0, np.float32)))
    with pytest.raises(InputError, match="black level 60000 DN.*nothing to reconstruct"):
        preprocess_raw(raw, 65535.0, RawCorrection(black_level=60000.0), "cap.tif")
    np.save(tmp_path / "neg.npy", -rng.random((16, 16)).astype(np.float32))
    with pytest.raises(InputError, match="neg.npy.*nothing to reconstruct"):
        read_capture(tmp_path / "neg.npy")
    # half of a float capture below 0: accepted, with a warning
    half = (rng.random((32, 32)) - 0.5).astype(np.float32)
    np.save(tmp_path / "half.npy", half)
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        img, _ = read_capture(tmp_path / "half.npy")
    np.testing.assert_array_equal(img, half)
    msgs = [r.getMessage() for r in caplog.records if "below 0" in r.getMessage()]
    assert len(msgs) == 1 and "half.npy" in msgs[0] and f"{100 * np.mean(half < 0):.0f} %" in msgs[0], msgs
    # a later error is the only message: the warning is not printed before it
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"), pytest.raises(InputError, match="flat field"):
        preprocess_raw(half, 1.0, RawCorrection(flat=np.zeros_like(half)), "half.npy")
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    # a too-high black level leaving 30 % negative: warned about, naming the black level
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        preprocess_raw(raw, 65535.0, RawCorrection(black_level=15000.0), "cap.tif")
    msgs = [r.getMessage() for r in caplog.records if "below 0" in r.getMessage()]
    assert len(msgs) == 1 and "black level 15000 DN" in msgs[0], msgs
    # a normal dark-frame subtraction: no warning
    dark = 100.0 + rng.random((64, 64)) * 5
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        preprocess_raw(raw + 200, 65535.0, RawCorrection(dark=dark))
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def test_reconstruct_dark_frame_brighter_than_capture_is_an_error(fab_run, tmp_path):
    import tifffile

    raw = np.round(np.random.default_rng(7).random((64, 64)) * 50000).astype(np.uint16)
    tifffile.imwrite(tmp_path / "cap.tif", raw)
    np.save(tmp_path / "dark.npy", np.full((64, 64), 60000, np.uint16))
    out = tmp_path / "x.h5"
    res = run_cli_in_process("reconstruct", str(tmp_path / "cap.tif"), "--run", str(fab_run), "--out", str(out),
                  "--dark", str(tmp_path / "dark.npy"))
    assert_clean_error(res, "cap.tif", "dark frame", "nothing to reconstruct")
    _outputs_absent(out)


def _psf_tifs(d: Path, bands: Bands, size: int = 31, **meta) -> Path:
    """One float TIFF per band: a 3×3 px spot at the image centre; psf.json from ``meta``."""
    import tifffile

    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    c = size // 2
    for lam in bands.centers_nm:
        img = np.zeros((size, size), np.float32)
        img[c - 1 : c + 2, c - 1 : c + 2] = 1.0
        tifffile.imwrite(d / f"psf_{lam:g}nm.tif", img)
    write_json(d / "psf.json", meta)
    return d


def test_measured_psf_light_outside_the_kernel(tmp_path, caplog):
    """An axis outside the image, or one whose kernel holds (nearly) none of the light: one
    InputError naming the file and band (before: all-zero PSFs); some light lost: a warning."""
    bands = Bands.uniform(500, 600, 50)
    k, px = 9, 10e-6  # kernel 9 camera pixels of 10 µm = 15 measured pixels of 6 µm
    d = _psf_tifs(tmp_path / "far", bands, pixel_pitch_um=6, centre="axis", axis_px=[1e9, -5])
    with pytest.raises(InputError, match=r"psf_500nm\.tif \(500 nm\): axis_px \[1e\+09, -5\].*outside the 31×31 px"):
        import_psf_dir(d, bands, px, k)
    # inside the image, but the kernel (±7.5 measured px) misses the spot at 14..16
    d = _psf_tifs(tmp_path / "edge", bands, pixel_pitch_um=6, centre="axis", axis_px=[15, 29])
    with pytest.raises(InputError, match=r"psf_500nm\.tif \(500 nm\): only 0 % of the PSF's light.*9×9 px kernel"):
        import_psf_dir(d, bands, px, k)
    # axis at column 23: the kernel spans (23 + 0.5)·6 µm ± 45 µm = columns 16 … 31 of the image, so
    # it keeps one of the spot's three columns (14, 15, 16): 1/3 of the light -> a warning only
    d = _psf_tifs(tmp_path / "third", bands, pixel_pitch_um=6, centre="axis", axis_px=[15, 23])
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.measured_psf"):
        m = import_psf_dir(d, bands, px, k)
    np.testing.assert_allclose(m.report["energy_in_kernel"], 1 / 3, rtol=1e-9)
    msgs = [r.getMessage() for r in caplog.records if "outside the camera's" in r.getMessage()]
    assert len(msgs) == 1 and all(f"psf_{lam:g}nm.tif ({lam:g} nm): 33 %" in msgs[0] for lam in bands.centers_nm), msgs
    # centred: everything in the kernel, no warning
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.measured_psf"):
        m = import_psf_dir(_psf_tifs(tmp_path / "ok", bands, pixel_pitch_um=6, centre="axis", axis_px=[15, 15]), bands, px, k)
    np.testing.assert_allclose(m.report["energy_in_kernel"], 1.0, rtol=1e-9)
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    # an empty band image is named, also when the common centroid is computed first
    d = _psf_tifs(tmp_path / "dead", bands, pixel_pitch_um=6)
    import tifffile

    tifffile.imwrite(d / "psf_550nm.tif", np.zeros((31, 31), np.float32))
    with pytest.raises(InputError, match=r"psf_550nm\.tif \(550 nm\): PSF image has no positive signal"):
        import_psf_dir(d, bands, px, k)


def test_finetune_refuses_psfs_outside_the_kernel(fab_run, tmp_path):
    from hsicam.runs.folder import load_run

    _, base = load_run(fab_run)
    d = _psf_tifs(tmp_path / "psf", base.bands, pixel_pitch_um=6, centre="axis", axis_px=[1e9, -5])
    out = tmp_path / "run2"
    res = run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(d), "--out", str(out), "--epochs", "1")
    assert_clean_error(res, f"psf_{base.bands.centers_nm[0]:g}nm.tif", "axis_px", "outside")
    assert not out.exists()
    cap = tmp_path / "cap.npy"
    np.save(cap, np.random.default_rng(8).random((30, 34)).astype(np.float32))
    rec = run_cli_in_process("reconstruct", str(cap), "--run", str(fab_run), "--out", str(tmp_path / "x.h5"), "--psf-dir", str(d))
    assert_clean_error(rec, "axis_px", "outside")
    _outputs_absent(tmp_path / "x.h5")


def test_reconstructing_simulates_own_dark_png_gives_no_bit_depth_advice(fab_run, tmp_path):
    """`hsicam simulate` of a dark scene writes sensor.png at the full 16 bits (simulate.json beside
    it and its scale inside it): reconstructing it gives no "very dark ... sensor has N bits, pass
    --white-level" advice, which the same pixels as a real capture (no simulate.json, no text chunk) still get."""
    scene = tmp_path / "scene.npy"
    np.save(scene, (np.random.default_rng(3).random((3, 40, 40)) * 0.2).astype(np.float32))
    sim = tmp_path / "sim"
    res = run_cli_in_process("simulate", "--run", str(fab_run), "--scene", str(scene), "--out", str(sim))
    assert res.returncode == 0, res.stderr
    sensor = np.load(sim / "sensor.npy")
    assert sensor.max() < 1 / 8 and json.loads((sim / "simulate.json").read_text())["sensor_png_scale"] == 1.0
    res = run_cli_in_process("reconstruct", str(sim / "sensor.png"), "--run", str(fab_run), "--out", str(tmp_path / "a.h5"))
    assert res.returncode == 0, res.stderr
    assert "very dark" not in res.stderr and "--white-level" not in res.stderr, res.stderr
    from PIL import Image

    with Image.open(sim / "sensor.png") as im:  # the same pixels as a real capture: no hsicam text chunk
        Image.fromarray(np.array(im)).save(tmp_path / "capture.png")
    res = run_cli_in_process("reconstruct", str(tmp_path / "capture.png"), "--run", str(fab_run), "--out", str(tmp_path / "b.h5"))
    assert res.returncode == 0, res.stderr
    assert "capture.png: very dark" in res.stderr and "pass --white-level 16383" in res.stderr, res.stderr


def test_float_capture_in_dn_and_simulates_stretched_png(tmp_path, caplog):
    """A float capture far above full scale (DN stored as floats) is warned about, naming
    --white-level; a float capture within [0, 1] is not. A PNG that `hsicam simulate` stretched so
    that its brightest pixel is full scale (simulate.json's sensor_png_scale > 1) is not called
    saturated; the same PNG without simulate.json is."""
    import imageio.v3 as iio

    rng = np.random.default_rng(5)
    np.save(tmp_path / "dn.npy", (rng.random((16, 20)) * 4095).astype(np.float32))
    np.save(tmp_path / "unit.npy", rng.random((16, 20)).astype(np.float32))
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        read_capture(tmp_path / "dn.npy")
        read_capture(tmp_path / "unit.npy")
    msgs = [r.getMessage() for r in caplog.records]
    assert len([m for m in msgs if "dn.npy" in m and "--white-level" in m]) == 1, msgs
    assert not [m for m in msgs if "unit.npy" in m], msgs
    img16 = np.round(rng.random((16, 20)) * 65535).astype(np.uint16)
    img16[3, 4] = 65535
    sim = tmp_path / "sim"
    sim.mkdir()
    iio.imwrite(sim / "sensor.png", img16)
    (sim / "simulate.json").write_text(json.dumps({"sensor_png_scale": 3.0}))
    shutil.copy(sim / "sensor.png", tmp_path / "plain.png")
    caplog.clear()
    with caplog.at_level("WARNING", logger="hsicam.data.images"):
        img, rep = read_capture(sim / "sensor.png")
        _, rep_plain = read_capture(tmp_path / "plain.png")
    np.testing.assert_allclose(img, img16 / 65535.0 * 3.0, rtol=1e-6)
    assert rep["saturated_px"] == 0 and rep_plain["saturated_px"] >= 1
    assert [m for m in (r.getMessage() for r in caplog.records) if "saturated" in m] == \
        [m for m in (r.getMessage() for r in caplog.records) if "plain.png" in m and "saturated" in m] != []


def test_a_resumed_fine_tuning_goes_on_with_the_train_and_data_settings_it_was_started_with(tmp_path):
    """continued_settings: the train.* and data.* keys where the fine-tuning's config.yaml differs from the source
    run's, as --set overrides that rebuild exactly its train and data sections from the source's config; the
    camera and model sections are the source run's own (not listed)."""
    from hsicam.config import dump_yaml
    from hsicam.engine.calibration import continued_settings

    source_cfg = load_config("tiny")
    started_cfg = load_config("tiny", ["train.lr=0.0003", "train.epochs=7", "train.sensor_sigma=[0.001, 0.002]",
                                       "data.patch_px=40", "data.augment_relight=0.5"])
    (tmp_path / "src").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "src" / "config.yaml").write_text(dump_yaml(source_cfg))
    (tmp_path / "out" / "config.yaml").write_text(dump_yaml(started_cfg))
    sets = continued_settings(tmp_path / "out", tmp_path / "src")
    assert sorted(s.split("=")[0] for s in sets) == ["data.augment_relight", "data.patch_px", "train.epochs", "train.lr",
                                                     "train.sensor_sigma"]
    rebuilt = load_config(tmp_path / "src" / "config.yaml", sets)
    assert rebuilt.train == started_cfg.train and rebuilt.data == started_cfg.data
    assert rebuilt.camera == source_cfg.camera
