"""Mutation guards for the camera system (models/system.py: CameraSystem, its reconstructor and linear step), from
probes mut8b and mut9a (the camera operators' guards are in cameras/test_camera_edge_cases.py, the reports' in
report/test_report_edge_cases.py, the optics export's in export/test_export_edge_cases.py).

Each test kills a hand-made mutant that the other tests let through, asserting against a reference computed here:
a state dict's keys, the step computed by hand through a PSF cut once, a tiled reconstruction against the whole
image, the step through a copy of the camera without fabrication noise.
"""

from __future__ import annotations

import copy
import logging

import pytest
import torch
from torch import nn

from conftest import TINY_CAMERA_OVERRIDES
from test_consistency import _Oracle  # a "network" returning a fixed cube
from hsicam.cameras import build_camera
from hsicam.config import load_config
from hsicam.models import CameraSystem
from hsicam.models.consistency import consistency_step, cut_psf, linear_consistency_step


# ------------------------------------------------------------------------------------------------
# models/system.py
# ------------------------------------------------------------------------------------------------
def _consistency(*overrides: str):
    return load_config(overrides=["model.consistency.iterations=1", *overrides]).model.consistency


def test_with_camera_keeps_the_network_and_its_settings_but_not_the_step_camera(tiny_camera):
    """with_camera: the same network object, consistency, autocast dtype, linear step and its missing-note, imaging
    through the new camera; the step camera (a nominal design for another camera) is not carried over."""
    cam, other = tiny_camera(), tiny_camera("camera.cfa.period=5")
    c = _consistency()
    model = CameraSystem(cam, _Oracle(torch.zeros(1)), c)
    model.autocast_dtype = torch.bfloat16
    model.linear_step = torch.ones(9, 3, 5, 5)
    model.linear_step_missing = "run r has no linear step"
    model.step_camera = tiny_camera()
    out = model.with_camera(other)
    assert out.camera is other and out.net is model.net and out.consistency is c
    assert out.autocast_dtype is torch.bfloat16
    assert out.linear_step is model.linear_step and out.linear_step_missing == "run r has no linear step"
    assert out.step_camera is None


def test_step_camera_is_a_reference_not_a_submodule(tiny_camera):
    """A step camera set on the model is neither a submodule nor in the state dict (the checkpoint holds the
    imaging camera and the network only), and .to() leaves it alone."""
    cam = tiny_camera()
    model = CameraSystem(cam, _Oracle(torch.zeros(1)), _consistency())
    keys = set(model.state_dict())
    step = tiny_camera()
    model.step_camera = step
    assert model.step_camera is step
    assert set(model.state_dict()) == keys and "step_camera" not in dict(model.named_children())
    model.to(torch.float64)
    assert next(step.parameters()).dtype == torch.float32


@pytest.mark.parametrize("kind, takes", [("dd_cassi", True), ("sd_cassi", False)])
def test_consistency_applies_to_cassi_cameras_whose_scene_grid_is_the_sensors(kind, takes, caplog):
    """DD-CASSI images a scene on the sensor's grid, so the step applies; SD-CASSI's scene grid is wider than the
    sensor (the dispersion), so its reconstructions skip the step, warning once."""
    cam = build_camera(load_config(overrides=[*TINY_CAMERA_OVERRIDES, f"camera.kind={kind}"]))
    model = CameraSystem(cam, _Oracle(torch.zeros(1)), _consistency())
    assert model.camera_takes_consistency is takes
    with caplog.at_level(logging.WARNING, logger="hsicam.models.system"):
        assert model.consistency_on is takes
        assert model.consistency_on is takes
    warned = [r.getMessage() for r in caplog.records if "scene grid is not the sensor's" in r.getMessage()]
    assert len(warned) == (0 if takes else 1)


def test_reconstruct_takes_the_landweber_steps_in_eval_mode_only(tiny_camera):
    """In training mode reconstruct is the network's output as it is; in eval mode the Landweber step moves it, to
    consistency_step's result from the same estimate (computed here through the camera's nominal snapshot)."""
    from hsicam.models.consistency import consistency_step

    cam = tiny_camera(dtype=torch.float64)
    x0 = torch.full((1, len(cam.bands), 24, 24), 0.3, dtype=torch.float64)
    c = _consistency("model.consistency.psf_energy=1")
    model = CameraSystem(cam, _Oracle(x0), c)
    y = torch.rand(1, 1, 24, 24, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    with torch.no_grad():
        assert torch.equal(model.train().reconstruct(y), x0)
        got = model.eval().reconstruct(y)
        want = consistency_step(cam.snapshot(nominal=True), y, x0, damping=c.damping, iterations=1, psf_energy=1.0,
                                extend="replicate", spectral_prior=c.spectral_prior, tv_weight=c.tv_weight)
    assert (got - x0).abs().max() > 1e-3
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


class _Pointwise(nn.Module):
    """cube_c = w_c · sensor, pixel by pixel (no context): a network that tiles exactly with no halo."""

    context_px = 0

    def __init__(self, weights: torch.Tensor) -> None:
        super().__init__()
        self.weights = weights

    def forward(self, sensor, camera, origin=(0, 0)):
        return sensor * self.weights[None, :, None, None].to(sensor.dtype)


def _linear_model(tiny_camera):
    """A tiny DOE camera with a 15-px kernel whose PSFs keep 95 % of their light in 13 px, but in 9 px once cut to
    13 px (so cutting them twice is a different operator), a pointwise network and a kind=linear step with random
    11-px filters."""
    cam = tiny_camera("camera.psf.kernel_px=15", dtype=torch.float64)
    c = _consistency("model.consistency.kind=linear", "model.consistency.psf_energy=0.95")
    model = CameraSystem(cam, _Pointwise(torch.tensor([0.8, 1.0, 1.2], dtype=torch.float64)), c).eval()
    g = torch.Generator().manual_seed(5)
    m = cam.code_period
    model.linear_step = 0.02 * torch.randn(m * m, len(cam.bands), c.window_px, c.window_px, generator=g,
                                           dtype=torch.float64)
    once = cut_psf(cam.snapshot(nominal=True), 0.95)
    assert once.psf.shape[-1] == 13 and cut_psf(once, 0.95).psf.shape[-1] == 9  # the premise
    y = torch.rand(1, 1, 40, 40, generator=g, dtype=torch.float64)
    return model, once, y


def test_reconstructor_takes_the_linear_step_through_the_psfs_cut_once(tiny_camera):
    """kind=linear: the reconstructor's step goes through the nominal PSFs cut to psf_energy once (13 px here), as
    reconstruct's own: the step computed by hand through that operator, not through one cut again (9 px)."""
    model, once, y = _linear_model(tiny_camera)
    c = model.consistency
    with torch.no_grad():
        x0 = model.network(y)
        want = linear_consistency_step(once, y, x0, model.linear_step, gain=c.gain, iterations=1, psf_energy=1.0,
                                       extend="replicate")
        got = model.reconstructor()(y)
        direct = model.reconstruct(y)
    assert (want - x0).abs().max() > 1e-3
    torch.testing.assert_close(direct, want, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


def test_reconstructor_declares_the_halo_its_tiles_need_to_equal_the_whole_image(tiny_camera):
    """The reconstructor's context_px (the halo reconstruct_tiled takes by default) is the model's, the reach of the
    linear step through the PSFs cut once, and with it the tiles give the whole image's cube."""
    from hsicam.engine.inference import reconstruct_tiled

    model, once, y = _linear_model(tiny_camera)
    fn = model.reconstructor()
    # the linear step's reach: its filters' half width plus twice A's (the 13-px kernel's half width)
    assert fn.context_px == model.context_px == model.consistency.window_px // 2 + 2 * (13 // 2)
    with torch.no_grad():
        whole = fn(y)
        tiled = reconstruct_tiled(fn, y, tile_px=8)
    torch.testing.assert_close(tiled, whole, rtol=1e-9, atol=1e-12)


def test_the_step_goes_through_the_nominal_design_not_a_draw_of_its_fabrication_noise(tiny_camera):
    """A camera imaging with fabrication noise (camera.doe.sigma_height_nm > 0): reconstruct's step and the
    reconstructor's go through the nominal design, i.e. the same camera without that noise (a copy with σ_p = 0
    here), on every call; so does the step through a step camera with fabrication noise of its own."""
    cam = tiny_camera("camera.doe.sigma_height_nm=200", dtype=torch.float64)
    model = CameraSystem(cam, _Pointwise(torch.tensor([0.8, 1.0, 1.2], dtype=torch.float64)),
                         _consistency("model.consistency.psf_energy=1")).eval()
    nominal = copy.deepcopy(cam)
    nominal.optics.doe.sigma_height_m = 0.0
    y = torch.rand(1, 1, 24, 24, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    c = model.consistency
    torch.manual_seed(0)
    with torch.no_grad():
        x0 = model.network(y)
        want = consistency_step(nominal.snapshot(), y, x0, damping=c.damping, iterations=1, psf_energy=1.0,
                                extend="replicate", spectral_prior=c.spectral_prior, tv_weight=c.tv_weight)
        noisy = consistency_step(cam.snapshot(), y, x0, damping=c.damping, iterations=1, psf_energy=1.0,
                                 extend="replicate", spectral_prior=c.spectral_prior, tv_weight=c.tv_weight)
        got = [model.reconstructor()(y), model.reconstruct(y), model.reconstruct(y)]
        model.step_camera = cam
        model.camera = nominal
        got += [model.reconstructor()(y), model.reconstruct(y)]
    assert (noisy - want).abs().max() > 1e-4  # the premise: a noise draw is another operator
    for g in got:
        torch.testing.assert_close(g, want, rtol=1e-9, atol=1e-12)


def test_a_linear_step_with_no_iterations_is_not_missing(tiny_camera):
    """model.consistency.iterations=0 scores the network alone: a kind=linear run without its linear_step file is
    then not refused (missing_linear_step is None); with one iteration it is, with the run's note as it is."""
    model = CameraSystem(tiny_camera(), _Pointwise(torch.ones(3)), _consistency("model.consistency.kind=linear"))
    model.linear_step_missing = "run r has no linear_step.safetensors"
    off = _consistency("model.consistency.kind=linear", "model.consistency.iterations=0")
    assert model.missing_linear_step(off) is None
    assert model.missing_linear_step() == "run r has no linear_step.safetensors"
    model.consistency = off
    assert model.missing_linear_step() is None
    y = torch.rand(1, 1, 12, 12, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(model.eval().reconstruct(y), y.expand(1, 3, 12, 12))
