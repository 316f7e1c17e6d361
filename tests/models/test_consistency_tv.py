"""The TV prior in the measurement-consistency steps (``model.consistency.tv_weight``,
hsicam.models.consistency.BrightnessTV): its proximal step against scikit-image's Chambolle solver, the
vectorial coupling of the bands, the reach that tiles need, what it does to a blotchy estimate, configs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from skimage.restoration import denoise_tv_chambolle

from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import ConfigError
from hsicam.models import CameraSystem
from hsicam.models.consistency import BRIGHTNESS_EPS, TV_MOMENTUM_MAX, BrightnessTV, consistency_step, reach_px
from test_consistency import C, K, _snapshot  # bands, kernel (px); a DOE snapshot of random PSFs and CFA


def _prox(v: torch.Tensor, x0: torch.Tensor, weight: float, calls: int = 5000, level: float | None = None) -> torch.Tensor:
    """The prox as the steps approach it: the same input given ``calls`` times (one dual iteration each); ``level``:
    the brightness b set to that one number (else x0's local brightness)."""
    tv = BrightnessTV(x0, weight)
    if level is not None:
        tv.brightness = torch.full_like(tv.brightness, level)
    for _ in range(calls):
        out = tv(v)
    return out


def test_one_band_prox_is_scikit_images_tv_denoising():
    """One band, the brightness b one number: the prox converges to b · argmin_u ½‖u − v/b‖² + w·TV(u), as
    scikit-image's Chambolle solver computes it (isotropic TV, Neumann border)."""
    g = torch.Generator().manual_seed(0)
    v = torch.rand(1, 1, 14, 17, generator=g, dtype=torch.float64) * 0.2
    b = 0.2 + BRIGHTNESS_EPS
    weight = 0.05
    got = _prox(v, v, weight, level=b)
    want = b * denoise_tv_chambolle((v / b)[0, 0].numpy(), weight=weight, eps=1e-15, max_num_iter=100000)
    np.testing.assert_allclose(got[0, 0].numpy(), want, atol=1e-9)
    assert float((got - v).abs().max()) > 0.01  # the weight does something


def test_the_bands_share_their_edges():
    """Vectorial TV: bands u_c = s_c·φ cost ‖s‖·TV(φ), so the prox of the cube is s_c · prox_{w/‖s‖}(φ) in every
    band (one image, scaled), where a TV of each band alone would smooth each by w/s_c; scikit-image computes
    prox_{w/‖s‖}(φ) on the image alone."""
    g = torch.Generator().manual_seed(1)
    phi = torch.rand(1, 1, 12, 13, generator=g, dtype=torch.float64)
    s = torch.tensor([0.2, 0.5, 1.0], dtype=torch.float64)[None, :, None, None]
    v = s * phi
    weight = 0.05
    got = _prox(v, v, weight, level=1.0)
    psi = denoise_tv_chambolle(phi[0, 0].numpy(), weight=weight / float(s.norm()), eps=1e-15, max_num_iter=100000)
    np.testing.assert_allclose(got[0].numpy(), (s[0] * torch.from_numpy(psi)).numpy(), atol=1e-6)
    per_band = denoise_tv_chambolle(v[0, 0].numpy(), weight=weight, eps=1e-15, max_num_iter=100000)
    assert np.abs(per_band - got[0, 0].numpy()).max() > 0.01  # not the band's own TV


def test_the_prior_follows_the_local_brightness():
    """The estimate divided by its local brightness is regularised: a dark copy of a scene (× 0.1) comes out as
    the bright one's output × 0.1, where a TV of the values themselves would smooth the dark one ten times as much."""
    g = torch.Generator().manual_seed(2)
    bright = 0.5 + 0.3 * torch.rand(1, 2, 24, 24, generator=g, dtype=torch.float64)
    out_bright = _prox(bright, bright, 0.05, calls=200)
    out_dark = _prox(bright * 0.1, bright * 0.1, 0.05, calls=200)
    # the same up to BRIGHTNESS_EPS, which is not scaled
    rel = float((out_dark / 0.1 - out_bright).abs().max() / (out_bright - bright).abs().max())
    assert rel < 0.05
    assert float((out_bright - bright).abs().max()) > 0.01


def test_a_flat_true_cube_is_a_fixed_point_of_the_steps_with_the_prior_up_to_the_border(tiny_camera):
    """The true cube explains y exactly and a flat one has no variation for the TV to remove, so the steps must leave it
    as it is everywhere. The brightness the prior divides by was averaged with zeros beyond the image (half at an edge,
    a quarter at a corner): x/b had a false ramp within 9 px of the border, which the prox flattened (5 % of the
    value at the border of a zero-padded `same` camera)."""
    cam = tiny_camera("camera.boundary=same", "camera.padding=zeros", dtype=torch.float64)
    truth = torch.full((1, len(cam.bands), 40, 40), 0.4, dtype=torch.float64)
    y = cam.A(truth)
    with torch.no_grad():
        got = consistency_step(cam.snapshot(nominal=True), y, truth, iterations=12, psf_energy=1.0, extend=False,
                               spectral_prior=4.0, tv_weight=0.03)
    torch.testing.assert_close(got, truth, rtol=0, atol=1e-9)


@pytest.mark.parametrize("iterations", [1, 3])
def test_steps_with_the_prior_reach_what_reach_px_says(iterations):
    """The steps with the TV prior after a pixel-wise estimate: tiles with ``reach_px(..., tv=True)`` of halo (an
    upper bound) equal the whole image; with the plain steps' reach they do not (the prior reaches further)."""
    snap = _snapshot(6)
    reach = reach_px(snap, iterations, psf_energy=1.0, tv=True)
    assert reach > reach_px(snap, iterations, psf_energy=1.0)

    def f(window, origin=(0, 0)):
        x0 = window.expand(-1, C, -1, -1) * torch.tensor([0.7, 0.4, 1.1], dtype=window.dtype)[:, None, None]
        return consistency_step(snap, window, x0, origin, iterations=iterations, psf_energy=1.0, tv_weight=0.1)

    sensor = torch.rand(1, 1, 70, 66, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    whole = f(sensor)
    torch.testing.assert_close(reconstruct_tiled(f, sensor, tile_px=16, halo_px=reach), whole, rtol=1e-12, atol=1e-12)
    plain = reach_px(snap, iterations, psf_energy=1.0)
    assert (reconstruct_tiled(f, sensor, tile_px=16, halo_px=plain) - whole).abs().max() > 1e-6


def test_the_prior_removes_blotches_the_plain_steps_keep():
    """A piecewise-constant scene (blocks of three spectra), its noiseless measurement, and an estimate with
    blotches (smooth random errors of 5 %, as a network leaves on flat regions): 10 steps with a small TV prior (and
    its momentum) end closer to the truth than 20 plain steps, which can only remove what the camera sees, and than
    the start; the measurement stays explained. (A large weight, or many more steps towards the regularised solution,
    would flatten these small blocks: here 40 steps with the prior end behind the plain ones. The weight and the
    steps are a trade, chosen on a camera's training scenes.)"""
    snap = _snapshot(4)
    g = torch.Generator().manual_seed(8)
    spectra = torch.tensor([[0.8, 0.3, 0.2], [0.2, 0.6, 0.4], [0.5, 0.5, 0.9]], dtype=torch.float64)
    labels = torch.zeros(36, 36, dtype=torch.long)
    labels[:, 12:] = 1
    labels[14:30, 6:26] = 2
    truth = spectra[labels].permute(2, 0, 1)[None]  # (1, C, 36, 36)
    y = snap.A(truth)[..., K // 2 : -(K // 2), K // 2 : -(K // 2)]
    t = truth[..., K // 2 : -(K // 2), K // 2 : -(K // 2)]
    blotches = torch.nn.functional.avg_pool2d(torch.randn(1, C, 32, 32, generator=g, dtype=torch.float64), 5, 1, 2)
    x0 = t * (1 + 0.05 * blotches / blotches.std())

    def error(x):
        return float((x - t).norm() / t.norm())

    origin = (K // 2, K // 2)  # the window's first pixel: the CFA phase of y
    plain = consistency_step(snap, y, x0, origin, iterations=20, psf_energy=1.0)
    tv = consistency_step(snap, y, x0, origin, iterations=10, psf_energy=1.0, tv_weight=0.003)
    assert error(tv) < 0.85 * error(plain) and error(tv) < 0.6 * error(x0)

    def residual(x):  # the border extended by replication, as the steps start it; the padded cube starts at pixel 0
        image = snap.A(torch.nn.functional.pad(x, (2, 2, 2, 2), mode="replicate"), (0, 0))[..., 2:-2, 2:-2]
        return float((image - y).norm() / y.norm())

    assert residual(tv) < 0.5 * residual(x0)


def test_the_system_takes_the_prior_from_its_config_and_tiles_exactly(tiny_config):
    """model.consistency.tv_weight reaches the steps (kind landweber and linear + landweber_after): the output
    differs from the steps without it, the declared context grows by the prior's reach, and tiles with it equal
    the whole image."""
    torch.manual_seed(0)
    model = CameraSystem.from_config(tiny_config("model.consistency.iterations=2", "model.consistency.tv_weight=0.05",
                                                 "model.consistency.spectral_prior=4")).eval()
    torch.nn.init.normal_(model.net.output.weight, std=0.1, generator=torch.Generator().manual_seed(5))
    snap = model.camera.snapshot(nominal=True)
    e = model.consistency.psf_energy
    assert model.context_px == model.net.context_px + reach_px(snap, 2, e, tv=True)
    sensor = torch.rand(1, 1, 61, 57, generator=torch.Generator().manual_seed(1))
    f = model.reconstructor()
    with torch.no_grad():
        whole = f(sensor)
        tiled = reconstruct_tiled(f, sensor, tile_px=24, halo_px=model.context_px)
        model.consistency = dataclasses.replace(model.consistency, tv_weight=0.0)
        without = model.reconstructor()(sensor)
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)
    assert (whole - without).abs().max() > 1e-4


@pytest.mark.parametrize("overrides, match", [
    (("model.consistency.tv_weight=-0.1",), r"tv_weight must be 0 \(no TV prior\) or in \[1e-06, 10\], got -0.1"),
    (("model.consistency.tv_weight=1e308",), r"tv_weight must be 0 \(no TV prior\) or in \[1e-06, 10\], got 1e\+308"),
    (("model.consistency.tv_weight=1e-320",), r"tv_weight must be 0 \(no TV prior\) or in \[1e-06, 10\]"),
    (("model.consistency.tv_weight=nan",), "'model.consistency.tv_weight' must be a finite number, got 'nan'"),
    (("model.consistency.tv_weight=inf",), "'model.consistency.tv_weight' must be a finite number, got 'inf'"),
    (("model.consistency.kind=linear", "model.consistency.tv_weight=0.03"),
     "acts in the Landweber steps, and kind=linear takes none .* or model.consistency.tv_weight=0 for the linear step "
     "alone"),
])
def test_bad_tv_settings_are_one_clear_error(tiny_config, overrides, match):
    with pytest.raises(ConfigError, match=match):
        tiny_config("model.consistency.iterations=1", *overrides)


def test_steps_with_the_prior_are_differentiable():
    """Gradients flow through the steps with the prior to the estimate (as through the plain steps), and match
    finite differences."""
    snap = _snapshot(2)
    g = torch.Generator().manual_seed(4)
    y = torch.rand(1, 1, 9, 10, generator=g, dtype=torch.float64)
    x0 = torch.rand(1, C, 9, 10, generator=g, dtype=torch.float64).requires_grad_(True)
    w = torch.rand(1, C, 9, 10, generator=g, dtype=torch.float64)

    def f(x):
        return (consistency_step(snap, y, x, iterations=3, psf_energy=1.0, tv_weight=0.05) * w).sum()

    assert torch.autograd.gradcheck(f, (x0,), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("prior", [dict(), dict(spectral_prior=4.0), dict(tv_weight=0.05),
                                   dict(tv_weight=0.05, spectral_prior=4.0)])
def test_whole_window_steps_leave_the_callers_estimate_alone(prior):
    """Without the estimate's extension (``extend=False``) and without bands the steps start from the caller's own
    tensor, and without gradients they write their sums in place (session 50): never into x0, nor into y."""
    snap = _snapshot(2)
    g = torch.Generator().manual_seed(6)
    y = torch.rand(1, 1, 9, 10, generator=g, dtype=torch.float64)
    x0 = torch.rand(1, C, 9, 10, generator=g, dtype=torch.float64)
    x_kept, y_kept = x0.clone(), y.clone()
    with torch.no_grad():
        out = consistency_step(snap, y, x0, iterations=3, psf_energy=1.0, extend=False, **prior)
    assert float((out - x0).abs().max()) > 1e-6  # the steps moved the estimate
    torch.testing.assert_close(x0, x_kept, rtol=0, atol=0)
    torch.testing.assert_close(y, y_kept, rtol=0, atol=0)


def test_reconstruct_takes_tv_steps_and_records_them(tmp_path):
    """`hsicam reconstruct --tv-steps N [--tv-weight W]` reconstructs with N Landweber steps carrying the prior after
    the run's linear step (the run's own config with those two keys), and the cube's metadata says so; bad uses are
    one line each."""
    import json

    import h5py

    from hsicam.runs.folder import load_run
    from cli_helpers import assert_ok, error_line, run_cli_in_process

    g = torch.Generator().manual_seed(0)
    sensor = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 72, 72, generator=g), 5, 1, 2)[0, 0].numpy()
    np.save(tmp_path / "s.npy", sensor.astype(np.float32))
    out = tmp_path / "tv.h5"
    assert_ok(run_cli_in_process("reconstruct", str(tmp_path / "s.npy"), "--run", "pretrained:standard", "--out", str(out),
                                 "--tv-steps", "3", "--tv-weight", "0.05"))
    with h5py.File(out, "r") as f:
        cube, meta = f["cube"][()], json.loads(f.attrs["metadata_json"])
    assert meta["consistency_landweber_after"] == 3 and meta["consistency_tv_weight"] == 0.05
    _, model = load_run("pretrained:standard", overrides=("model.consistency.landweber_after=3",
                                                          "model.consistency.tv_weight=0.05"))
    with torch.no_grad():
        want = model.eval().reconstructor()(torch.from_numpy(sensor)[None, None])[0].numpy()
    np.testing.assert_allclose(cube, want, rtol=1e-5, atol=1e-6)
    assert_ok(run_cli_in_process("reconstruct", str(tmp_path / "s.npy"), "--run", "pretrained:standard",
                                 "--out", str(tmp_path / "plain.h5")))
    with h5py.File(tmp_path / "plain.h5", "r") as f:  # the shipped camera's own: 12 steps with the prior at 0.03
        meta = json.loads(f.attrs["metadata_json"])
        assert meta["consistency_tv_weight"] == 0.03 and meta["consistency_landweber_after"] == 12
        assert np.abs(f["cube"][()] - cube).max() > 1e-4
    for extra, message in [(("--tv-weight", "0.1"), "--tv-weight is the weight of the --tv-steps' prior"),
                           (("--tv-steps", "0"), "--tv-steps must be >= 1 and <= 100, got 0"),
                           (("--tv-steps", "2", "--consistency-steps", "0"),
                            "--tv-steps adds measurement-consistency steps and --consistency-steps 0 removes them"),
                           (("--tv-steps", "2", "--tv-weight", "-1"), "argument --tv-weight: must be a number in [1e-06, 10]"),
                           (("--tv-steps", "2", "--tv-weight", "1e308"), "argument --tv-weight: must be a number in"),
                           (("--tv-steps", "2", "--tv-weight", "nan"), "argument --tv-weight: must be a number in")]:
        res = run_cli_in_process("reconstruct", str(tmp_path / "s.npy"), "--run", "pretrained:standard",
                                 "--out", str(tmp_path / "bad.h5"), *extra)
        assert res.returncode == 2 and message in error_line(res), res.stderr
    assert not (tmp_path / "bad.h5").exists()


@pytest.mark.parametrize("weight", [0.03, 0.3])
def test_the_steps_with_the_prior_settle(weight):
    """The steps with the prior converge, with their capped momentum and without it: the 400th moves the estimate by
    less than 1e-4 of its norm and by a tenth of what the 50th moved it, at the recommended weight and at ten times it
    (FISTA's uncapped momentum with a prox solved one dual iteration at a time cycled here, moving it by 3 % to 25 %
    per step)."""
    snap = _snapshot(4)
    g = torch.Generator().manual_seed(8)
    truth = torch.rand(1, C, 36, 36, generator=g, dtype=torch.float64)
    truth = torch.nn.functional.avg_pool2d(truth, 7, 1, 3)
    y = snap.A(truth)[..., 2:-2, 2:-2]
    x0 = truth[..., 2:-2, 2:-2] * (1 + 0.1 * torch.randn(1, C, 32, 32, generator=g, dtype=torch.float64))

    for momentum in (TV_MOMENTUM_MAX, 0.0):
        def change(n):  # how much the n-th step moves the estimate
            before, after = (consistency_step(snap, y, x0, (2, 2), iterations=k, psf_energy=1.0, tv_weight=weight,
                                              tv_momentum=momentum) for k in (n - 1, n))
            return float((after - before).norm() / after.norm())

        late = change(400)
        assert late < 1e-4 and late < 0.1 * change(50), momentum


def test_the_momentum_reaches_the_steps_limit_sooner():
    """The steps with the prior lead to one estimate with their capped momentum or without it (1500 steps each), and
    the momentum gets there sooner: after 24 and 48 steps it is about two thirds as far from it as the plain steps
    (0.63, 0.68; half and a third while the prior's brightness was zero-padded at the border, whose false ramp also
    slowed both: the plain steps are now 1.9× and 3.4× closer there); a momentum of 1 or more, or below 0, is refused."""
    snap = _snapshot(4)
    g = torch.Generator().manual_seed(5)
    truth = torch.nn.functional.avg_pool2d(torch.rand(1, C, 36, 36, generator=g, dtype=torch.float64), 5, 1, 2)
    y = snap.A(truth)[..., 2:-2, 2:-2]
    x0 = truth[..., 2:-2, 2:-2] * (1 + 0.1 * torch.randn(1, C, 32, 32, generator=g, dtype=torch.float64))

    def steps(n, momentum):
        return consistency_step(snap, y, x0, (2, 2), iterations=n, psf_energy=1.0, tv_weight=0.03, tv_momentum=momentum)

    limit = steps(1500, TV_MOMENTUM_MAX)
    torch.testing.assert_close(steps(1500, 0.0), limit, rtol=0, atol=1e-5)

    def distance(x):
        return float((x - limit).norm() / (x0 - limit).norm())

    for n, ratio in ((24, 0.7), (48, 0.75)):
        assert distance(steps(n, TV_MOMENTUM_MAX)) < ratio * distance(steps(n, 0.0)), n
    for bad in (1.0, 1.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match="tv_momentum"):
            steps(1, bad)


def test_tv_steps_name_the_steps_of_either_kind_of_run(tiny_config):
    """--tv-steps on a run of kind landweber are its steps (also where they were off), with --consistency-steps
    they would name them twice; on a run of kind linear they follow the linear step, which must be on."""
    import argparse

    from hsicam.cli.reconstruct import tv_consistency
    from hsicam.config import RECOMMENDED_TV_WEIGHT
    from hsicam.errors import InputError

    def args(**kw):
        return argparse.Namespace(**{"tv_steps": 3, "tv_weight": None, "consistency_steps": None, **kw})

    landweber = CameraSystem.from_config(tiny_config("model.consistency.iterations=0"))
    c = tv_consistency(landweber, args())
    assert (c.iterations, c.tv_weight, landweber.consistency_on) == (3, RECOMMENDED_TV_WEIGHT, True)
    assert tv_consistency(landweber, args(tv_weight=0.2)).tv_weight == 0.2
    with pytest.raises(InputError, match="--tv-steps and --consistency-steps both give the steps of this run"):
        tv_consistency(landweber, args(consistency_steps=2))
    linear = CameraSystem.from_config(tiny_config("model.consistency.iterations=1", "model.consistency.kind=linear"))
    c = tv_consistency(linear, args(tv_steps=5))
    assert (c.iterations, c.landweber_after, c.tv_weight) == (1, 5, RECOMMENDED_TV_WEIGHT)
    linear.consistency = dataclasses.replace(linear.consistency, iterations=0)
    with pytest.raises(InputError, match="follow the run's linear consistency step, which is off"):
        tv_consistency(linear, args())
