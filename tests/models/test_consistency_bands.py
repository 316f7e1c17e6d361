"""The consistency steps in bands of rows (``consistency_step(band_px=…)``) and the tiling that takes the steps
apart from what comes before them (``reconstruct_tiled`` with ``fn.before_steps`` / ``fn.steps``).

References: the whole-window steps (one call, no bands), which the older tests check against closed forms and
adjoint identities; and the whole image through :meth:`CameraSystem.reconstruct`."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from hsicam.engine.inference import reconstruct_tiled
from hsicam.models import CameraSystem
from hsicam.models.consistency import consistency_step, default_band_px


def _camera(tiny_config, *overrides):
    torch.manual_seed(0)
    return CameraSystem.from_config(tiny_config(*overrides)).camera.snapshot(nominal=True)


SETTINGS = {
    "plain": {},
    "spectral prior": {"spectral_prior": 4.0},
    "TV prior with momentum": {"tv_weight": 0.05},
    "TV prior, spectral prior, noise": {"tv_weight": 0.05, "spectral_prior": 4.0, "noise": True},
    "TV prior without momentum, zero light beyond": {"tv_weight": 0.05, "tv_momentum": 0.0, "extend": False},
    "TV prior, spectral prior, mirrored border": {"tv_weight": 0.05, "spectral_prior": 4.0, "extend": "reflect"},
    "TV prior, clipped pixels, noise": {"tv_weight": 0.05, "clipped": True, "noise": True},
    "plain, clipped pixels": {"clipped": True},
}


@pytest.mark.parametrize("name", list(SETTINGS))
@pytest.mark.parametrize("band_px", [1, 9, 30])
def test_steps_in_bands_equal_the_whole_window(tiny_config, name, band_px):
    """Bands of 1 row (so each band is the halo's height), 9 rows and 30 rows of a 61-row window give the
    whole window's steps to float rounding, for every kind of step: the bands read the old rows above them
    that the band before overwrote, and every row that reaches their output."""
    kw = dict(SETTINGS[name])
    snap = _camera(tiny_config)
    g = torch.Generator().manual_seed(1)
    y = 0.1 + 0.8 * torch.rand(2, 1, 61, 47, generator=g)
    x0 = torch.rand(2, snap.psf.shape[0], 61, 47, generator=g)
    if kw.pop("noise", False):
        kw["noise_variance"] = 1e-3 * torch.rand(2, 1, 61, 47, generator=g)
    if kw.pop("clipped", False):  # the brightest fifth of the capture clipped (the map bands' rows, as the variance)
        kw["clipped"] = y >= 0.74
        y = y.clamp(max=0.74)
    with torch.no_grad():
        whole = consistency_step(snap, y, x0, (2, 3), iterations=6, psf_energy=1.0, **kw)
        bands = consistency_step(snap, y, x0, (2, 3), iterations=6, psf_energy=1.0, band_px=band_px, **kw)
    assert (whole - x0).abs().max() > 1e-2  # the steps do something
    torch.testing.assert_close(bands, whole, rtol=1e-5, atol=1e-5)


def test_steps_in_bands_leave_the_callers_estimate_alone(tiny_config):
    """With no extension (the estimate is not padded into a new tensor) the bands still write into a copy."""
    snap = _camera(tiny_config)
    y = torch.rand(1, 1, 40, 30)
    x0 = torch.rand(1, snap.psf.shape[0], 40, 30)
    before = x0.clone()
    with torch.no_grad():
        consistency_step(snap, y, x0, iterations=3, extend=False, tv_weight=0.05, spectral_prior=2.0, band_px=8)
    torch.testing.assert_close(x0, before, rtol=0, atol=0)


def test_steps_in_bands_refuse_gradients_and_bad_band_heights(tiny_config):
    snap = _camera(tiny_config)
    y = torch.rand(1, 1, 20, 20)
    x0 = torch.rand(1, snap.psf.shape[0], 20, 20, requires_grad=True)
    with pytest.raises(ValueError, match="without gradients"):
        consistency_step(snap, y, x0, band_px=8)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="band_px"), torch.no_grad():
            consistency_step(snap, y, x0, band_px=bad)
    assert default_band_px(512) == 512 and default_band_px(2048) == 128 and default_band_px(10**7) == 1


def test_steps_are_called_back_once_each(tiny_config):
    snap = _camera(tiny_config)
    calls = []
    with torch.no_grad():
        consistency_step(snap, torch.rand(1, 1, 20, 20), torch.rand(1, snap.psf.shape[0], 20, 20), iterations=5,
                         tv_weight=0.05, band_px=4, on_step=lambda: calls.append(1))
    assert len(calls) == 5


def _system(tiny_config, *overrides):
    torch.manual_seed(0)
    model = CameraSystem.from_config(tiny_config("model.consistency.iterations=2", *overrides)).eval()
    torch.nn.init.normal_(model.net.output.weight, std=0.1, generator=torch.Generator().manual_seed(5))
    return model


@pytest.mark.parametrize("overrides", [
    ("model.consistency.tv_weight=0.05", "model.consistency.spectral_prior=4"),
    ("model.consistency.kind=linear", "model.consistency.window_px=5", "model.consistency.iterations=1",
     "model.consistency.landweber_after=5", "model.consistency.tv_weight=0.05"),
])
def test_tiles_up_to_the_steps_then_steps_on_the_whole_image_equal_the_whole_image(tiny_config, overrides):
    """reconstruct_tiled cuts tiles with the halo of what comes before the steps (the network, and the linear
    step of kind linear), far less than the steps' own, and takes the steps on the whole image: the cube is
    the whole image's. Every window the network sees is a tile plus that smaller halo."""
    model = _system(tiny_config, *overrides)
    if model.consistency.kind == "linear":
        m, c = model.camera.code_period, len(model.bands)
        model.linear_step = torch.randn(m * m, c, 5, 5, generator=torch.Generator().manual_seed(9)) * 0.05
    fn = model.reconstructor()
    assert fn.before_steps.context_px < fn.context_px == model.context_px
    assert fn.steps.count == 5 if model.consistency.kind == "linear" else 2
    sensor = torch.rand(1, 1, 83, 71, generator=torch.Generator().manual_seed(1))
    windows = []
    before = fn.before_steps

    def counted(s, origin=(0, 0)):
        windows.append(tuple(s.shape[-2:]))
        return before(s, origin)

    counted.context_px = before.context_px
    fn.before_steps = counted
    with torch.no_grad():
        whole = fn(sensor)
        tiled = reconstruct_tiled(fn, sensor, tile_px=20)
        without_steps = fn.before_steps(sensor)
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)
    assert (whole - without_steps).abs().max() > 1e-3
    tiles = windows[:-1]  # the last: without_steps
    assert len(tiles) == 5 * 4 and max(max(w) for w in tiles) <= 20 + 2 * before.context_px


def test_a_capture_at_a_cfa_offset_tiles_up_to_the_steps_too(tiny_config):
    """offset_reconstructor shifts both stages: the tiled cube at CFA offset (1, 2) equals the whole image's."""
    from hsicam.cli.reconstruct import offset_reconstructor

    model = _system(tiny_config, "model.consistency.tv_weight=0.05")
    fn = offset_reconstructor(model.reconstructor(), (1, 2))
    assert hasattr(fn, "before_steps") and fn.steps.count == 2
    sensor = torch.rand(1, 1, 70, 64, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        whole = fn(sensor)
        tiled = reconstruct_tiled(fn, sensor, tile_px=24)
        unshifted = model.reconstructor()(sensor)
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)
    assert (whole - unshifted).abs().max() > 1e-3


def test_a_halo_given_keeps_the_steps_in_the_tiles(tiny_config):
    """An explicit halo_px (the whole reconstruction's context) tiles the whole reconstruction as before."""
    model = _system(tiny_config, "model.consistency.tv_weight=0.05")
    fn = model.reconstructor()
    sensor = torch.rand(1, 1, 60, 50, generator=torch.Generator().manual_seed(3))
    calls = []
    steps = fn.steps
    fn.steps = lambda *a, **k: calls.append(1) or steps(*a, **k)
    with torch.no_grad():
        torch.testing.assert_close(reconstruct_tiled(fn, sensor, 24, fn.context_px), fn(sensor), rtol=1e-5,
                                   atol=1e-5)
    assert not calls


def test_without_steps_the_reconstructor_has_no_stages(tiny_config):
    model = _system(tiny_config)
    assert hasattr(model.reconstructor(), "steps")
    model.consistency = dataclasses.replace(model.consistency, iterations=0)
    assert not hasattr(model.reconstructor(), "steps")
