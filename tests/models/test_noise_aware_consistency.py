"""Noise-aware measurement consistency: the local Wiener gain on the steps' residual
(hsicam.models.consistency.wiener_residual), and the steps on noisy captures: they fit less noise, a
noise-free model leaves them exactly as they were, and tiles still equal the whole image. The sensor noise
model's variance they weigh by (hsicam.sensor.SensorNoise.variance, against the empirical variance of the noise it
adds) is tested in optics/test_sensor.py. The `hsicam reconstruct --full-well-e` tests below drive the whole
command on one photon-limited capture of the shipped camera (a module fixture), to show the steps' effect end to
end."""

from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest
import torch

from hsicam.config import load_config
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import ConfigError
from hsicam.models.consistency import (WIENER_WINDOW_PX, consistency_step, linear_consistency_step, reach_px,
                                       wiener_residual)
from hsicam.sensor import SensorNoise
from cli_helpers import assert_ok, error_line, run_cli_in_process
from test_consistency import _assert_step_tiles_equal_whole, _high_contrast_problem, _linear_system, _snapshot, _system

C = 3


def _piecewise_residual(seed: int) -> torch.Tensor:
    """A residual with the structure a network leaves: a few constant blocks (edges), zero elsewhere."""
    g = torch.Generator().manual_seed(seed)
    r = torch.zeros(1, 1, 64, 64, dtype=torch.float64)
    for _ in range(6):
        i, j = torch.randint(0, 48, (2,), generator=g).tolist()
        r[..., i : i + 12, j : j + 12] += 0.05 * (2 * torch.rand(1, generator=g, dtype=torch.float64) - 1)
    return r


def test_a_noise_free_capture_keeps_its_residual_exactly():
    r = torch.randn(2, 1, 20, 17)
    assert wiener_residual(r, None) is r
    assert torch.equal(wiener_residual(r, torch.zeros_like(r)), r)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wiener_gain_removes_most_of_the_noise_and_keeps_the_structure(seed):
    truth = _piecewise_residual(seed)
    sigma = 0.01
    noisy = truth + sigma * torch.randn(truth.shape, generator=torch.Generator().manual_seed(seed + 10),
                                        dtype=torch.float64)
    out = wiener_residual(noisy, torch.full_like(noisy, sigma**2))
    assert float(((out - truth) ** 2).mean()) < 0.3 * float(((noisy - truth) ** 2).mean())
    assert bool((out.abs() <= noisy.abs() + 1e-15).all())  # a gain in [0, 1], never an amplification
    assert bool((torch.sign(out) * torch.sign(noisy) >= 0).all())
    # pure noise: most of it goes
    pure = sigma * torch.randn(truth.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    assert float(wiener_residual(pure, torch.full_like(pure, sigma**2)).square().mean()) < 0.2 * sigma**2


def test_wiener_gain_is_local():
    """A crop of the residual gives the whole image's result WIENER_WINDOW_PX // 2 px inside its edge."""
    g = torch.Generator().manual_seed(3)
    r = torch.randn(1, 1, 40, 40, generator=g, dtype=torch.float64)
    v = 0.5 + torch.rand(1, 1, 40, 40, generator=g, dtype=torch.float64)
    whole = wiener_residual(r, v)
    h = WIENER_WINDOW_PX // 2
    crop = wiener_residual(r[..., 10:30, 5:35], v[..., 10:30, 5:35])
    torch.testing.assert_close(crop[..., h:-h, h:-h], whole[..., 10 + h : 30 - h, 5 + h : 35 - h])
    assert not torch.allclose(crop[..., 0, :], whole[..., 10, 5:35])  # the edge does differ


def _wiener_reference(r: np.ndarray, v: np.ndarray, window: int) -> np.ndarray:
    """The documented rule by loops: at each pixel the means of r² and v over the ``window`` px square
    around it, cut at the image's edge (only the pixels inside count), P = max(mean r² − mean v, 0),
    out = r · P / (P + v), or r where v is 0."""
    h, w = r.shape
    half = window // 2
    out = np.empty_like(r)
    for i in range(h):
        for j in range(w):
            rows, cols = slice(max(i - half, 0), min(i + half + 1, h)), slice(max(j - half, 0), min(j + half + 1, w))
            power = max(float(np.mean(r[rows, cols] ** 2)) - float(np.mean(v[rows, cols])), 0.0)
            out[i, j] = r[i, j] if v[i, j] == 0 else r[i, j] * power / (power + v[i, j])
    return out


def test_wiener_gain_matches_the_documented_rule_at_every_pixel():
    """wiener_residual against a loop reference of its docstring's rule, border pixels included, with
    a noise variance that varies (a Poisson–Gaussian capture's) and a few noise-free pixels."""
    rng = np.random.default_rng(11)
    g = rng.uniform(0.0, 1.0, (12, 11))
    r = rng.normal(0.0, 0.02, (12, 11)) + 0.05 * np.sin(np.arange(11) / 2.0)[None, :]
    v = SensorNoise("poisson_gaussian", full_well_e=500.0, read_noise_e=3.0).variance(
        torch.from_numpy(g)[None, None])[0, 0].double().numpy()
    v[0, 0] = v[5, 7] = 0.0  # trusted whole there
    got = wiener_residual(torch.from_numpy(r)[None, None], torch.from_numpy(v)[None, None])[0, 0].numpy()
    want = _wiener_reference(r, v, WIENER_WINDOW_PX)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert got[0, 0] == r[0, 0] and got[5, 7] == r[5, 7]
    assert 0.05 < float(np.mean(np.abs(got) / np.abs(r))) < 0.95  # the noise is shrunk, not kept or zeroed


@pytest.mark.parametrize("seed", [2, 7])
def test_steps_on_a_noisy_capture_fit_less_noise(seed):
    """A good estimate (off by 0.01) of a capture with much more noise (σ = 0.05): plain steps pull it
    towards the noise and the error grows; with the noise's variance they keep nearly all of the
    estimate. A poor estimate (off by 0.3) of a mildly noisy capture: the noise-aware steps still
    correct it as far as the plain ones."""
    snap, truth, clean, rough = _high_contrast_problem(seed, seed + 100, (1, C, 24, 24))
    gen = torch.Generator().manual_seed(seed + 7)

    def errors(x0, sigma):
        y = clean + sigma * torch.randn(clean.shape, generator=gen, dtype=torch.float64)
        var = torch.full_like(y, sigma**2)
        kw = dict(damping=1e-3, iterations=3, psf_energy=1.0, extend=False)
        plain = consistency_step(snap, y, x0, **kw)
        aware = consistency_step(snap, y, x0, noise_variance=var, **kw)
        return [float((x - truth).norm()) for x in (x0, plain, aware)]

    good = truth + 0.01 * torch.randn(truth.shape, generator=gen, dtype=torch.float64)
    start, plain, aware = errors(good, 0.05)
    assert plain > 2 * start and aware < 0.5 * plain, (start, plain, aware)
    start, plain, aware = errors(rough, 0.002)
    assert plain < 0.97 * start and aware < 1.01 * plain, (start, plain, aware)


@pytest.mark.parametrize("kind", ["landweber", "linear"])
def test_a_noise_free_camera_reconstructs_as_without_the_option(tiny_config, kind):
    """The presets' noise-free camera: noise_aware on (the default) and off give the same bits, with the
    Landweber step and with the linear step followed by spectral-prior Landweber steps."""
    models = []
    for aware in ("true", "false"):
        if kind == "landweber":
            m = _system(tiny_config, f"model.consistency.noise_aware={aware}")
        else:
            m = _linear_system(tiny_config)
            m.consistency = dataclasses.replace(m.consistency, landweber_after=2, spectral_prior=4.0,
                                                noise_aware=aware == "true")
        models.append(m)
    on, off = models
    assert on.consistency.noise_aware and not off.consistency.noise_aware
    assert not on.camera.noise.declares_noise
    sensor = torch.rand(1, 1, 30, 30)
    assert on.context_px == off.context_px
    with torch.no_grad():
        assert torch.equal(on.reconstructor()(sensor), off.reconstructor()(sensor))


def test_noise_aware_steps_reach_further_than_plain_ones():
    """Two Landweber steps alone after a pixel-wise estimate of a noisy capture: tiles with reach_px + 2 px per
    step of halo (what CameraSystem declares) equal the whole image; with the plain steps' reach_px they do not
    (the least that works here is reach_px + 2: the declared halo is a bound, 2 px to spare)."""
    snap = _snapshot(6)
    iterations = 2
    plain = reach_px(snap, iterations, psf_energy=1.0)
    reach = plain + WIENER_WINDOW_PX // 2 * iterations
    noise = SensorNoise("poisson_gaussian", full_well_e=50.0, read_noise_e=1.0)

    def f(window, origin=(0, 0)):
        x0 = window.expand(-1, C, -1, -1) * 0.7
        return consistency_step(snap, window, x0, origin, iterations=iterations, psf_energy=1.0,
                                noise_variance=noise.variance(window))

    sensor = torch.rand(1, 1, 61, 58, dtype=torch.float64)
    whole = f(sensor)
    torch.testing.assert_close(reconstruct_tiled(f, sensor, tile_px=12, halo_px=reach), whole, rtol=1e-12, atol=1e-12)
    assert (reconstruct_tiled(f, sensor, tile_px=12, halo_px=plain) - whole).abs().max() > 1e-6


def test_the_linear_step_and_its_landweber_steps_on_a_noisy_camera_tile_with_their_halo(tiny_config):
    """kind linear + landweber_after on a camera that declares noise: the halo adds 2 px for each of the
    1 + landweber_after steps, and tiles with it equal the whole image."""
    def system(aware: bool):
        m = _linear_system(tiny_config)
        m.consistency = dataclasses.replace(m.consistency, landweber_after=2, spectral_prior=4.0, noise_aware=aware)
        m.camera.noise = SensorNoise("poisson_gaussian", full_well_e=200.0, read_noise_e=2.0)
        return m

    on, off = system(True), system(False)
    assert on.context_px == off.context_px + WIENER_WINDOW_PX // 2 * 3
    snap = on.camera.snapshot(nominal=True)
    _assert_step_tiles_equal_whole(on, snap)
    sensor = torch.rand(1, 1, 40, 40)
    with torch.no_grad():
        assert (on.reconstructor()(sensor) - off.reconstructor()(sensor)).abs().max() > 1e-4


def test_wiener_gain_gradient_is_its_derivative():
    g = torch.Generator().manual_seed(2)
    r = torch.randn(1, 1, 9, 8, generator=g, dtype=torch.float64, requires_grad=True)
    v = (0.5 + torch.rand(1, 1, 9, 8, generator=g, dtype=torch.float64)).requires_grad_(False)
    assert torch.autograd.gradcheck(lambda t: wiener_residual(t, v), (r,))


def test_a_noisy_camera_weighs_the_residual_and_tiles_still_equal_the_whole_image(tiny_config):
    noisy = ("camera.sensor.noise=poisson_gaussian", "camera.sensor.full_well_e=300")
    on = _system(tiny_config, *noisy)
    off = _system(tiny_config, *noisy, "model.consistency.noise_aware=false")
    assert on.context_px == off.context_px + WIENER_WINDOW_PX // 2 * on.consistency.iterations
    sensor = torch.rand(1, 1, 53, 47)
    f = on.reconstructor()
    with torch.no_grad():
        whole = f(sensor)
        assert (whole - off.reconstructor()(sensor)).abs().max() > 1e-4
        tiled = reconstruct_tiled(f, sensor, tile_px=16, halo_px=on.context_px)
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)


def test_the_linear_step_weighs_its_residual_too():
    """No variance: the step as before; a variance far above the residual's power: the estimate stays."""
    snap, truth, y, x0 = _high_contrast_problem(4, 104, (1, C, 20, 20))
    weight = 0.1 * torch.rand(snap.code_period**2, C, 3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    kw = dict(gain=0.7, psf_energy=1.0, extend=False)
    plain = linear_consistency_step(snap, y, x0, weight, **kw)
    assert (plain - x0).abs().max() > 1e-2
    torch.testing.assert_close(linear_consistency_step(snap, y, x0, weight, noise_variance=torch.zeros_like(y), **kw),
                               plain, rtol=0, atol=0)
    drowned = linear_consistency_step(snap, y, x0, weight, noise_variance=torch.full_like(y, 1e4), **kw)
    assert (drowned - x0).abs().max() < 1e-3 * (plain - x0).abs().max()


def test_noise_aware_must_be_a_boolean(tiny_config):
    with pytest.raises(ConfigError, match="noise_aware"):
        tiny_config("model.consistency.noise_aware=sometimes")
    assert load_config("quick").model.consistency.noise_aware is True


# ------------------------------------------------------------------------------------------------
# `hsicam reconstruct --full-well-e E [--read-noise-e R]`: a real capture's photon level
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def noisy_capture(tmp_path_factory):
    """(folder, truth (C, h, w) aligned with the sensor, full well) of a photon-limited capture (300 e⁻ at full
    scale, 2 e⁻ read noise) of the procedural scene through the shipped standard camera."""
    from hsicam.runs.folder import load_run
    from hsicam.sensor import poisson_gaussian_noise
    from procedural_scenes import procedural_scene

    _, system = load_run("pretrained:standard")
    scene = torch.from_numpy(procedural_scene(system.camera.bands.centers_nm, size=220))[None]
    with torch.no_grad():
        clean = system.camera.A(scene)
    full_well = 300.0
    sensor = poisson_gaussian_noise(clean, full_well, 2.0, torch.Generator().manual_seed(0)).clamp(0, 1)
    folder = tmp_path_factory.mktemp("noisy")
    np.save(folder / "capture.npy", sensor[0, 0].numpy())
    np.save(folder / "half.npy", sensor[0, 0].numpy() / 2)  # the same electrons, stored at half the scale
    return folder, system.target(scene)[0].numpy(), full_well


def test_reconstruct_weighs_a_noisy_capture_by_its_photon_level(noisy_capture):
    folder, truth, full_well = noisy_capture
    cap, run = str(folder / "capture.npy"), "pretrained:standard"
    assert_ok(run_cli_in_process("reconstruct", cap, "--run", run, "--out", str(folder / "plain.h5")))
    assert_ok(run_cli_in_process("reconstruct", cap, "--run", run, "--out", str(folder / "aware.h5"),
                      "--full-well-e", f"{full_well:g}", "--read-noise-e", "2"))
    # the same electrons stored at half the scale: twice the electrons at its white level, --scale 2
    assert_ok(run_cli_in_process("reconstruct", str(folder / "half.npy"), "--run", run, "--out", str(folder / "half.h5"),
                      "--scale", "2", "--full-well-e", f"{2 * full_well:g}", "--read-noise-e", "2"))

    def read(name):
        with h5py.File(folder / name, "r") as f:
            return f["cube"][()], json.loads(f.attrs["metadata_json"])

    (plain, meta_plain), (aware, meta), (half, meta_half) = read("plain.h5"), read("aware.h5"), read("half.h5")
    mse = lambda x: float(np.mean((x - truth) ** 2))  # noqa: E731
    assert mse(aware) < 0.9 * mse(plain), (mse(aware), mse(plain))  # 0.85 when written
    np.testing.assert_allclose(half, aware, rtol=0, atol=1e-5)
    assert meta["noise_full_well_e"] == full_well and meta["noise_read_noise_e"] == 2.0
    assert meta_half["noise_full_well_e_at_image_scale"] == pytest.approx(full_well)
    assert "noise_full_well_e" not in meta_plain


@pytest.mark.parametrize("args, match", [
    (("--read-noise-e", "2"), "--read-noise-e needs --full-well-e"),
    (("--full-well-e", "0"), "--full-well-e must be a positive number"),
    (("--full-well-e", "nan"), "--full-well-e must be a positive number"),
    (("--full-well-e", "100", "--read-noise-e", "-1"), "--read-noise-e must be a number of electrons >= 0"),
])
def test_bad_noise_settings_are_one_clear_error(noisy_capture, args, match):
    folder, _, _ = noisy_capture
    line = error_line(run_cli_in_process("reconstruct", str(folder / "capture.npy"), "--run", "pretrained:standard",
                              "--out", str(folder / "bad.h5"), *args))
    assert match in line
    assert not (folder / "bad.h5").exists()


def test_the_full_well_is_counted_from_the_black_to_the_white_level(noisy_capture, caplog):
    """A 12-bit integer capture with a black level: E electrons at the white level are E on the image's [0, 1]
    scale, whatever black and white are; with the steps off the option says it changes nothing."""
    import logging

    folder, _, _ = noisy_capture
    g = np.load(folder / "capture.npy")
    black, white = 64, 4095
    np.save(folder / "raw12.npy", np.round(black + g * (white - black)).astype(np.uint16))
    out = folder / "raw12.h5"
    assert_ok(run_cli_in_process("reconstruct", str(folder / "raw12.npy"), "--run", "pretrained:standard", "--out", str(out),
                      "--black-level", str(black), "--white-level", str(white), "--full-well-e", "300"))
    with h5py.File(out, "r") as f:
        meta = json.loads(f.attrs["metadata_json"])
    assert meta["noise_full_well_e_at_image_scale"] == pytest.approx(300.0)
    with caplog.at_level(logging.WARNING):
        assert_ok(run_cli_in_process("reconstruct", str(folder / "capture.npy"), "--run", "pretrained:standard",
                          "--out", str(folder / "off.h5"), "--consistency-steps", "0", "--full-well-e", "300"))
    assert any("--full-well-e only weighs the measurement-consistency steps" in r.getMessage() for r in caplog.records)


def test_reconstruct_counts_the_flat_fields_gain_in_the_capture_noise(noisy_capture, tmp_path):
    """``--flat F --full-well-e E``: the capture was divided by the normalised flat, so each pixel's noise is
    scaled by 1/F; the camera's noise model gets that gain map, placed at the capture's CFA offset (before, the
    flat's gain was not counted). Checked in-process against the variance written out with 1/F, and end to end."""
    from hsicam.cli.reconstruct import capture_noise
    from hsicam.config import load_config
    from hsicam.data.images import RawCorrection, read_capture
    from hsicam.models import CameraSystem

    folder, _, _ = noisy_capture
    g = np.load(folder / "capture.npy")
    h, w = g.shape
    yy, xx = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    flat_dn = 1000.0 * (1 - 0.35 * (yy**2 + xx**2)) + 64.0  # vignetting, in DN above a black level of 64
    np.save(tmp_path / "flat.npy", np.round(flat_dn).astype(np.uint16))  # in the capture's DN, as the CLI asks
    raw = np.round(64 + g * (4095 - 64)).astype(np.uint16)
    np.save(tmp_path / "raw.npy", raw)
    flat_dn = np.round(flat_dn)
    corr = RawCorrection(black_level=64, white_level=4095, flat=flat_dn.astype(np.float32))
    img, report = read_capture(tmp_path / "raw.npy", corr)
    model = CameraSystem.from_config(load_config("tiny"))
    meta = capture_noise(model, report, 300.0, 2.0, corr, offset=(1, 2))
    a = (flat_dn - 64.0).mean() / (flat_dn - 64.0)  # 1 / the flat normalised to mean 1
    window = torch.from_numpy(img[10:40, 20:70])[None, None]
    expected = a[10:40, 20:70] * img[10:40, 20:70] / 300.0 + (a[10:40, 20:70] * 2.0 / 300.0) ** 2
    got = model.camera.noise.variance(window, origin=(11, 22))[0, 0].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert meta["noise_flat_field_gain"] is True
    out = tmp_path / "cube.h5"
    assert_ok(run_cli_in_process("reconstruct", str(tmp_path / "raw.npy"), "--run", "pretrained:standard", "--out", str(out),
                      "--black-level", "64", "--white-level", "4095", "--flat", str(tmp_path / "flat.npy"),
                      "--full-well-e", "300", "--read-noise-e", "2", "--cfa-offset", "1,2"))
    with h5py.File(out, "r") as f:
        written = json.loads(f.attrs["metadata_json"])
    assert written["noise_flat_field_gain"] is True and written["cfa_offset"] == [1, 2]


def test_tiles_see_their_part_of_the_flat_field_gain_map():
    """reconstruct_tiled through offset_reconstructor (a capture at CFA offset (1, 2)): each tile's consistency
    step weighs residuals by the gain map's window under it, so the tiled cube equals the whole image's, and the
    gain map changes that cube (it reaches the step)."""
    from hsicam.cli.reconstruct import offset_reconstructor
    from hsicam.config import load_config
    from hsicam.engine.inference import reconstruct_tiled
    from hsicam.models import CameraSystem

    torch.manual_seed(0)
    cfg = load_config("tiny", ["model.consistency.iterations=1", "model.consistency.kind=landweber",
                               "model.consistency.psf_energy=0.9", "camera.boundary=same"])
    system = CameraSystem.from_config(cfg).eval()
    h, w, tile = 170, 150, 40
    assert tile + 2 * system.reconstructor().context_px < min(h, w)  # real tiles, not the whole image each time
    g = torch.Generator().manual_seed(3)
    sensor = 0.2 + 0.6 * torch.rand(1, 1, h, w, generator=g)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    gain = 1.0 / (1.0 - 0.45 * (yy**2 + xx**2))

    def cube(gain_map, tile_px):
        system.camera.noise = SensorNoise("poisson_gaussian", full_well_e=50.0, read_noise_e=2.0, gain=gain_map,
                                          gain_origin=(1, 2))
        fn = offset_reconstructor(system.reconstructor(), (1, 2))
        with torch.no_grad():
            return reconstruct_tiled(fn, sensor, tile_px, fn.context_px)

    whole = cube(gain, max(h, w))
    torch.testing.assert_close(cube(gain, tile), whole, rtol=0, atol=2e-5)
    assert (cube(None, max(h, w)) - whole).abs().max() > 1e-3
