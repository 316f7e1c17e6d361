"""Clipped pixels in the measurement-consistency steps: where the sensor saturated, the capture is a lower bound of
the light (hsicam.models.consistency.clipped_residual), carried from the capture's raw values
(hsicam.data.images.read_capture(return_saturated=True)) through the camera's sensor model
(hsicam.sensor.SensorNoise.mark_saturated) to the steps of every kind, and through `hsicam reconstruct`.

References: the rule written out pixel by pixel in numpy; the truth of a clipped capture, which explains it exactly
and must therefore be a fixed point of correct steps; the unclipped steps, which the map must not change where the
estimate is darker than the clip; and the whole image, which tiles and bands of rows must reproduce."""

from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from hsicam.engine.inference import reconstruct_tiled
from hsicam.models.consistency import clipped_residual, consistency_step, linear_consistency_step
from hsicam.sensor import SensorNoise
from cli_helpers import assert_ok, run_cli_in_process
from test_consistency import C, _high_contrast_problem, _linear_system, _system


def _clipped_problem(seed: int, share: float = 0.2):
    """(operator, truth (1, C, 24, 24), its capture clipped at the level that ``share`` of the pixels reach, the
    clipped pixels (bool, like the capture), the clip level)."""
    snap, truth, clean, _ = _high_contrast_problem(seed, seed + 100, (1, C, 24, 24))
    level = float(torch.quantile(clean.flatten(), 1 - share))
    return snap, truth, clean.clamp(max=level), clean >= level, level


def test_the_residual_is_one_sided_exactly_where_the_sensor_clipped():
    g = torch.Generator().manual_seed(0)
    r = torch.randn(2, 1, 9, 7, generator=g, dtype=torch.float64)
    clipped = torch.rand(1, 1, 9, 7, generator=g) < 0.4
    got = clipped_residual(r, clipped).numpy()
    rn, cn = r.numpy(), np.broadcast_to(clipped.numpy(), r.shape)
    want = np.array([max(v, 0.0) if c else v for v, c in zip(rn.ravel(), cn.ravel())]).reshape(r.shape)
    np.testing.assert_array_equal(got, want)
    assert clipped_residual(r, None) is r
    assert bool((torch.from_numpy(got) != r).any())  # some negative residual at a clipped pixel was dropped


@pytest.mark.parametrize("seed", [2, 7])
@pytest.mark.parametrize("settings", [{}, {"spectral_prior": 4.0}, {"noise": True}])
def test_the_truth_of_a_clipped_capture_is_a_fixed_point_of_the_steps(seed, settings):
    """The truth explains a clipped capture (A x* ≥ the clip where it clipped, = y elsewhere): Landweber steps
    (plain, spectrally preconditioned, noise-aware) that know the clipped pixels leave it where it is; steps that
    take the clip as the value darken it. (With the TV prior the truth is no fixed point either way: its prox moves
    it.)"""
    snap, truth, y, clipped, _ = _clipped_problem(seed)
    kw = dict(damping=1e-3, iterations=3, psf_energy=1.0, extend=False, spectral_prior=settings.get("spectral_prior", 0))
    if settings.get("noise"):
        kw["noise_variance"] = torch.full_like(y, 1e-4)
    kept = consistency_step(snap, y, truth, clipped=clipped, **kw)
    torch.testing.assert_close(kept, truth, rtol=0, atol=1e-12)
    darkened = consistency_step(snap, y, truth, **kw)
    assert float((darkened - truth).norm()) > 1e-2 * float(truth.norm())
    assert float(snap.A(darkened)[clipped].mean()) < float(snap.A(truth)[clipped].mean())


def test_the_linear_step_keeps_the_truth_of_a_clipped_capture_too():
    snap, truth, y, clipped, _ = _clipped_problem(4)
    weight = 0.1 * torch.rand(snap.code_period**2, C, 3, 3, generator=torch.Generator().manual_seed(1),
                              dtype=torch.float64)
    kw = dict(gain=0.7, psf_energy=1.0, extend=False, iterations=2)
    torch.testing.assert_close(linear_consistency_step(snap, y, truth, weight, clipped=clipped, **kw), truth,
                               rtol=0, atol=1e-12)
    assert (linear_consistency_step(snap, y, truth, weight, **kw) - truth).abs().max() > 1e-3


def test_a_map_of_no_clipped_pixel_changes_no_bit():
    """An all-False map (a capture without clipped pixels) gives the plain steps bit for bit, Landweber with the TV
    prior and the linear step."""
    snap, truth, y, _, _ = _clipped_problem(5)
    rough = truth + 0.1 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    none = torch.zeros_like(y, dtype=torch.bool)
    kw = dict(damping=1e-3, iterations=3, psf_energy=1.0, tv_weight=0.05)
    assert torch.equal(consistency_step(snap, y, rough, clipped=none, **kw), consistency_step(snap, y, rough, **kw))
    weight = 0.1 * torch.rand(snap.code_period**2, C, 3, 3, generator=torch.Generator().manual_seed(1),
                              dtype=torch.float64)
    assert torch.equal(linear_consistency_step(snap, y, rough, weight, clipped=none, psf_energy=1.0),
                       linear_consistency_step(snap, y, rough, weight, psf_energy=1.0))


@pytest.mark.parametrize("seed", [3, 8])
def test_an_estimate_darker_than_every_clipped_pixel_is_stepped_as_without_the_map(seed):
    """Where A x < y at every clipped pixel, each residual there is positive already: the first step is the plain
    one, bit for bit."""
    snap, truth, y, clipped, level = _clipped_problem(seed)
    dark = 0.3 * truth
    assert bool((snap.A(dark)[clipped] < level).all())
    kw = dict(damping=1e-3, iterations=1, psf_energy=1.0, extend=False)
    assert torch.equal(consistency_step(snap, y, dark, clipped=clipped, **kw), consistency_step(snap, y, dark, **kw))


@pytest.mark.parametrize("seed", [2, 7, 11])
def test_the_map_brings_a_close_estimate_nearer_the_truth_than_the_plain_steps(seed):
    """An estimate off by noise of 0.03 per value (values ~0.5: near the truth, as a network's is): four steps that
    know the clipped pixels end nearer the truth than the same steps taking the clip as the value, which pull the
    highlights, and the pixels sharing their light, towards the clip (error ratio 0.28-0.86 over seeds 2-13 when
    written). An estimate off by 0.3 gains nothing (0.96-1.01): its clipped pixels are as often too bright as too
    dark, and the plain steps' pull then helps as often as it hurts."""
    snap, truth, y, clipped, _ = _clipped_problem(seed)
    close = truth + 0.03 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    kw = dict(damping=1e-3, iterations=4, psf_energy=1.0, extend=False)
    aware = float((consistency_step(snap, y, close, clipped=clipped, **kw) - truth).norm())
    plain = float((consistency_step(snap, y, close, **kw) - truth).norm())
    assert aware < 0.9 * plain, (aware, plain)


def test_a_bad_map_is_one_clear_error():
    snap, truth, y, clipped, _ = _clipped_problem(2)
    for bad, match in ((clipped.double(), "bool tensor"), (clipped[..., :5], "does not broadcast"),
                       (clipped.expand(2, -1, -1, -1), "does not broadcast"), (clipped.numpy(), "bool tensor")):
        with pytest.raises(ValueError, match=match):
            consistency_step(snap, y, truth, clipped=bad, psf_energy=1.0)
    with pytest.raises(ValueError, match=r"\(H, W\) bool"):
        SensorNoise().mark_saturated(torch.zeros(3, 4))
    noise = SensorNoise(gain=torch.ones(6, 5), gain_origin=(1, 2))
    with pytest.raises(ValueError, match="of one capture"):
        noise.mark_saturated(torch.zeros(6, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="of one capture"):
        noise.mark_saturated(torch.zeros(6, 5, dtype=torch.bool), (0, 0))
    noise.mark_saturated(np.zeros((6, 5), dtype=bool))  # numpy is taken, at the gain map's place
    assert noise.saturated.dtype == torch.bool and noise.gain_origin == (1, 2)
    with pytest.raises(ValueError, match="not within the saturated-pixel map"):
        noise.saturated_window(torch.zeros(1, 1, 3, 3), origin=(0, 0))
    assert "saturated=0 px" in repr(noise)
    noise.mark_saturated(None, (0, 0))  # cleared: the gain map stays where it is
    assert noise.saturated is None and noise.gain_origin == (1, 2)
    assert noise.saturated_window(torch.zeros(1, 1, 3, 3)) is None
    with pytest.raises(ValueError, match="bool tensor"):  # checked before the steps' early return too
        consistency_step(snap, y, truth, clipped=clipped.double(), iterations=0)


def _offset_cube(system, sensor, saturated_map, tile_px):
    """The cube of the capture ``sensor`` (1, 1, H, W) taken at CFA offset (1, 2), whose clipped pixels are
    ``saturated_map`` (H, W; None: none), reconstructed by ``system`` in ``tile_px`` tiles as `hsicam reconstruct`
    does."""
    from hsicam.cli.reconstruct import offset_reconstructor

    system.camera.noise = SensorNoise("none")
    system.camera.noise.mark_saturated(saturated_map, (1, 2))
    fn = offset_reconstructor(system.reconstructor(), (1, 2))
    with torch.no_grad():
        return reconstruct_tiled(fn, sensor, tile_px, None)


@pytest.mark.parametrize("kind", ["landweber", "linear"])
def test_tiles_see_their_part_of_the_saturated_map_and_equal_the_whole_image(tiny_config, kind):
    """A capture at CFA offset (1, 2) with clipped pixels: the reconstructor tiles its network (and linear step)
    and takes its Landweber/TV steps on the whole image (bands of rows: tests/models/test_consistency_bands.py); each
    part reads the map's window under it, so 40 px tiles give the whole image's cube, and the map changes that cube
    (it reaches both kinds of step)."""
    if kind == "landweber":
        system = _system(tiny_config, "model.consistency.psf_energy=0.9", "camera.boundary=same")
        system.consistency = dataclasses.replace(system.consistency, iterations=2, tv_weight=0.05)
    else:
        system = _linear_system(tiny_config)
        system.consistency = dataclasses.replace(system.consistency, landweber_after=0)
        # a network whose estimate images brighter than the capture at some clipped pixels (the untrained one's is
        # darker everywhere, where the map changes nothing)
        torch.nn.init.normal_(system.net.output.weight, std=0.3, generator=torch.Generator().manual_seed(5))
    h, w, tile = 150, 130, 40
    sensor = 0.2 + 0.9 * torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(3))
    saturated = sensor[0, 0] >= 0.4  # (the estimates image to about the clip: some of them above it there)
    sensor = sensor.clamp(max=0.4)

    def cube(saturated_map, tile_px):
        return _offset_cube(system, sensor, saturated_map, tile_px)

    whole = cube(saturated, max(h, w))
    rec = system.reconstructor()
    assert tile + 2 * (rec.before_steps if hasattr(rec, "steps") else rec).context_px < min(h, w)  # real tiles
    torch.testing.assert_close(cube(saturated, tile), whole, rtol=0, atol=2e-5)
    assert (cube(None, max(h, w)) - whole).abs().max() > 1e-3


def test_read_capture_maps_the_pixels_at_the_white_level(tmp_path):
    """A 12-bit capture in a 16-bit file: the pixels at or above --white-level 4095 are the map, whatever the flat
    field and the gain do to their values afterwards; the 2-tuple stays the default. Without a white level the
    file type's maximum is the clip; a float file is mapped only when one is given; a dark frame's hot pixel
    (subtracted afterwards) is not a clipped pixel of the capture."""
    from hsicam.data.images import RawCorrection, read_capture

    g = np.random.default_rng(0)
    raw = g.integers(64, 4096, size=(40, 30)).astype(np.uint16)
    raw[3, 4] = raw[10, 11] = 4095
    raw[20, 7] = 5000  # above the white level (a hot pixel, or a white level set low): clipped too
    np.save(tmp_path / "raw.npy", raw)
    flat = 1000.0 + 300 * g.random((40, 30))
    corr = RawCorrection(black_level=64, white_level=4095, flat=flat.astype(np.float32), scale=0.5)
    img, report, saturated = read_capture(tmp_path / "raw.npy", corr, return_saturated=True)
    np.testing.assert_array_equal(saturated, raw >= 4095)
    assert report["saturated_px"] == int(saturated.sum()) >= 3
    assert len(set(np.round(img[saturated], 4))) > 1  # their values differ after the flat: a value would not tell
    assert len(read_capture(tmp_path / "raw.npy", corr)) == 2
    _, report, none = read_capture(tmp_path / "raw.npy", RawCorrection(black_level=64, white_level=6000),
                                   return_saturated=True)
    assert not none.any() and report["saturated_px"] == 0
    full = raw.copy()
    full[5, 6] = 65535
    np.save(tmp_path / "full.npy", full)
    dark = np.full((40, 30), 64, dtype=np.uint16)
    dark[3, 4] = 4000  # a hot pixel of the dark frame, under a clipped pixel of the capture
    dark[8, 9] = 4000  # and under an ordinary one
    _, _, saturated = read_capture(tmp_path / "full.npy", RawCorrection(dark=dark), return_saturated=True)
    assert np.argwhere(saturated).tolist() == [[5, 6]]  # the type's maximum only, the dark frame's pixels not
    floats = (raw / 4095.0).astype(np.float32)
    np.save(tmp_path / "float.npy", floats)
    assert not read_capture(tmp_path / "float.npy", return_saturated=True)[2].any()
    _, _, given = read_capture(tmp_path / "float.npy", RawCorrection(white_level=1.0), return_saturated=True)
    np.testing.assert_array_equal(given, floats >= 1.0)
    assert given.sum() == 3


@pytest.fixture(scope="module")
def clipped_capture(tmp_path_factory):
    """(folder, truth aligned with the sensor, the clipped pixels) of a procedural scene through the shipped standard
    camera, exposed so that 3 % of the pixels pass full scale, stored as a 12-bit raw in a 16-bit file."""
    from hsicam.runs.folder import load_run
    from procedural_scenes import procedural_scene

    _, system = load_run("pretrained:standard")
    scene = torch.from_numpy(procedural_scene(system.camera.bands.centers_nm, size=360))[None]
    with torch.no_grad():
        clean = system.camera.A(scene)[0, 0]
    k = 1.0 / float(torch.quantile(clean.flatten(), 0.97))
    raw = np.minimum(np.round(k * clean.numpy() * 4095), 4095).astype(np.uint16)
    folder = tmp_path_factory.mktemp("clipped")
    np.save(folder / "raw.npy", raw)
    return folder, k * system.target(scene)[0].numpy(), raw >= 4095


def test_reconstruct_takes_the_clipped_pixels_as_lower_bounds(clipped_capture):
    """`hsicam reconstruct` of a capture with clipped highlights: the cube's metadata counts them, and the cube is
    the shipped camera's reconstruction with the map: nearer the truth within 8 px of the clipped pixels than the
    same reconstruction without it (squared error 0.94× when written), and within 1e-3 of it further away (1.1e-4
    when written: the steps carry the change a little beyond 8 px)."""
    from hsicam.data.images import RawCorrection, read_capture
    from hsicam.runs.folder import load_run

    folder, truth, clipped = clipped_capture
    out = folder / "cube.h5"
    assert_ok(run_cli_in_process("reconstruct", str(folder / "raw.npy"), "--run", "pretrained:standard", "--out",
                                 str(out), "--white-level", "4095"))
    with h5py.File(out, "r") as f:
        meta = json.loads(f.attrs["metadata_json"])
        cube = f["cube"][()]
    assert meta["clipped_px_as_lower_bounds"] == int(clipped.sum()) == meta["preprocessing"]["saturated_px"] > 0
    img, _ = read_capture(folder / "raw.npy", RawCorrection(white_level=4095))
    _, system = load_run("pretrained:standard")
    with torch.no_grad():
        plain = reconstruct_tiled(system.reconstructor(), torch.from_numpy(img)[None, None])[0].clamp_min(0).numpy()
    near = F.max_pool2d(torch.from_numpy(clipped)[None, None].float(), 17, 1, 8)[0, 0].numpy() > 0
    assert 0.05 < near.mean() < 0.8
    err = (cube - truth) ** 2
    err_plain = (plain - truth) ** 2
    assert err[:, near].mean() < 0.97 * err_plain[:, near].mean(), (err[:, near].mean(), err_plain[:, near].mean())
    assert np.abs(cube - plain)[:, ~near].max() < 1e-3
    assert np.abs(cube - plain)[:, near].max() > 1e-2
    # a capture without clipped pixels through the same model clears the map the last one set
    from hsicam.cli.reconstruct import capture_saturation

    assert capture_saturation(system, clipped, (0, 0)) == {"clipped_px_as_lower_bounds": int(clipped.sum())}
    assert system.camera.noise.saturated is not None
    assert capture_saturation(system, np.zeros_like(clipped), (0, 0)) == {}
    assert system.camera.noise.saturated is None


# ------------------------------------------------------------------------------------------------
# The unrolled network's data steps read the measurement too
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [2, 7])
def test_an_unrolled_data_step_keeps_the_truth_of_a_clipped_capture_and_follows_the_rule(seed):
    """A gradient data step x − α Aᵀ r of the unrolled network, r = A x − y with, at a clipped pixel, only its
    negative part (the rule written out in numpy): the truth of a clipped capture is its fixed point with the map and
    is darkened without it; a map of no clipped pixel changes no bit."""
    from hsicam.models.unrolled import UnrolledNet

    snap, truth, y, clipped, _ = _clipped_problem(seed)
    net = UnrolledNet(C, (4, 4), stages=1, init="backprojection", prior_features=4, prior_blocks=1,
                      prior_scale=1).double()
    alpha = torch.tensor(0.5 / float(snap.lipschitz), dtype=torch.float64)
    rough = truth + 0.2 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(net.data_step(truth, y, snap, alpha, clipped=clipped), truth, rtol=0, atol=1e-12)
        assert float((net.data_step(truth, y, snap, alpha) - truth).norm()) > 1e-2 * float(truth.norm())
        got = net.data_step(rough, y, snap, alpha, clipped=clipped)
        r = (snap.A(rough) - y).numpy()
        r = np.where(clipped.numpy(), np.minimum(r, 0.0), r)
        want = rough - alpha * snap.A_adjoint(torch.from_numpy(r))
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
        plain = net.data_step(rough, y, snap, alpha)
        assert (got - plain).abs().max() > 1e-4  # the rough estimate is brighter than some clipped pixels
        assert torch.equal(net.data_step(rough, y, snap, alpha, clipped=torch.zeros_like(clipped)), plain)
        assert torch.equal(net(y, snap, clipped=torch.zeros_like(clipped)), net(y, snap))
    with pytest.raises(ValueError, match="clipped must be a bool tensor"):
        net(y, snap, clipped=clipped.double())


def _unrolled_system(tiny_config):
    """A tiny `model.kind=unrolled` system whose priors brighten the estimate above the clip at some clipped pixels
    (the demosaic start images darker than the capture there, where the map changes nothing)."""
    from hsicam.models.system import CameraSystem
    from test_networks import randomise

    torch.manual_seed(0)
    system = CameraSystem.from_config(tiny_config(
        "model.kind=unrolled", "model.unrolled.stages=2", "model.unrolled.prior_features=8",
        "model.unrolled.prior_blocks=1", "model.unrolled.prior_scale=3", "model.unrolled.step_init=1.5",
        "model.consistency.iterations=0", "camera.boundary=same")).eval()
    randomise(system.net, 0.2)
    return system


def _clipped_capture(h: int, w: int, level: float = 0.5):
    sensor = 0.2 + 0.9 * torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(3))
    return sensor.clamp(max=level), sensor[0, 0] >= level


def test_the_unrolled_network_tiles_with_the_saturated_map_as_the_whole_image(tiny_config):
    """A `model.kind=unrolled` system reads its camera's saturated-pixel map in its stages: 40 px tiles of a capture
    at CFA offset (1, 2) give the whole image's cube, which the map changes (the network alone, no steps after it)."""
    system = _unrolled_system(tiny_config)
    assert system.net.takes_clipped
    h, w, tile = 130, 120, 40
    sensor, saturated = _clipped_capture(h, w)

    def cube(saturated_map, tile_px):
        return _offset_cube(system, sensor, saturated_map, tile_px)

    whole = cube(saturated, max(h, w))
    assert tile + 2 * system.reconstructor().context_px < min(h, w)  # real tiles
    torch.testing.assert_close(cube(saturated, tile), whole, rtol=0, atol=2e-5)
    assert (cube(None, max(h, w)) - whole).abs().max() > 1e-3


def test_the_cfa_phase_estimate_of_an_unrolled_camera_does_not_read_the_map_at_its_candidates(tiny_config):
    """The candidates of the CFA-phase estimate are windows at phases the map was not placed by: the unrolled network
    reconstructs them without the map (its window at a wrong phase would be the wrong pixels, or off the map), so a
    capture's marked map leaves the estimate as it is without one."""
    from hsicam.engine.cfa_offset import estimate_cfa_offset

    system = _unrolled_system(tiny_config)
    sensor, saturated = _clipped_capture(60, 60)
    system.camera.noise = SensorNoise("none")
    plain = estimate_cfa_offset(system, sensor)
    system.camera.noise.mark_saturated(saturated, (1, 2))
    marked = estimate_cfa_offset(system, sensor)
    assert marked.offset == plain.offset and marked.residuals == plain.residuals
    with torch.no_grad():  # (the network does read the map where it is asked to)
        assert (system.network(sensor, (1, 2)) - system.network(sensor, (1, 2), read_clipped=False)).abs().max() > 1e-3
