"""Mutation guards of the camera operators (cameras/base.py, cameras/doe_camera.py), moved here from the optics and
models floors' edge-case files (probes mut8b and the numerical core's): each test kills a hand-made mutant that the
rest of the suite let through, asserting against a reference computed here (the noise drawn from a seeded generator
by hand, an adjoint identity with a deliberately wrong adjoint, a camera built without height noise, a point source
through the cropped operator).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from conftest import TINY_CAMERA_OVERRIDES
from hsicam.cameras import build_camera
from hsicam.cameras.base import Camera
from hsicam.config import load_config
from hsicam.errors import InputError
from hsicam.sensor import SensorNoise
from hsicam.spectral import Bands


def _cassi(*overrides: str, dtype=torch.float64):
    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "camera.kind=dd_cassi", *overrides])
    return build_camera(cfg).to(dtype)


# ------------------------------------------------------------------------------------------------
# cameras/base.py
# ------------------------------------------------------------------------------------------------
def test_forward_draws_the_sensor_noise_from_sensor_generator_when_given():
    """Camera.forward(x, generator, sensor_generator=g): the noise is σ·randn drawn from g (by hand here), whatever
    ``generator`` is; without it the noise comes from ``generator``."""
    cam = _cassi("camera.sensor.noise=gaussian", "camera.sensor.sigma=0.05")
    x = torch.rand(1, len(cam.bands), 12, 13, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    clean = cam.A(x)

    def by_hand(seed):
        return clean + 0.05 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(seed), dtype=clean.dtype)

    got = cam(x, torch.Generator().manual_seed(1), sensor_generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(got, by_hand(2), rtol=0, atol=1e-12)
    torch.testing.assert_close(cam(x, torch.Generator().manual_seed(1)), by_hand(1), rtol=0, atol=1e-12)


class _SumCamera(Camera):
    """y = Σ_c w_c x_c (a band-weighted sum), cropped by ``crop`` px per side (boundary valid when crop > 0), with an
    adjoint scaled by ``adjoint_scale`` (1: the exact adjoint)."""

    kind = "sum_test"

    def __init__(self, adjoint_scale: float = 1.0, crop: int = 0) -> None:
        super().__init__()
        self.bands = Bands.uniform(500, 600, 50)
        self.weights = torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64)
        self.scale, self.crop = adjoint_scale, crop
        self.boundary = "valid" if crop else "same"
        self.noise = SensorNoise("none")

    @property
    def margin(self) -> int:
        return 2 * self.crop

    def A(self, x):  # noqa: N802
        c = self.crop
        y = (x * self.weights[:, None, None]).sum(dim=1, keepdim=True)
        return y[..., c : y.shape[-2] - c, c : y.shape[-1] - c]

    def A_adjoint(self, y):  # noqa: N802
        c = self.crop
        return self.scale * torch.nn.functional.pad(y, (c, c, c, c)) * self.weights[:, None, None]


def test_adjointness_error_is_the_size_of_the_mismatch_whichever_its_sign():
    """⟨Ax, y⟩ − ⟨x, Aᵀy⟩ = (1 − s)·⟨Ax, y⟩ for an adjoint scaled by s: the error is |1 − s|·⟨Ax, y⟩/(‖Ax‖‖y‖),
    recomputed here from the same draws; an adjoint too large (s > 1, a negative difference) is no adjoint either."""
    for s in (1.0, 2.0, 0.5):
        cam = _SumCamera(s)
        g = torch.Generator().manual_seed(4)
        x = torch.rand((1, 3, 6, 7), generator=g, dtype=torch.float64)
        ax = cam.A(x)
        y = torch.rand(ax.shape, generator=g, dtype=torch.float64)
        want = abs(1 - s) * float((ax * y).sum() / (ax.norm() * y.norm()))
        got = cam.adjointness_error((6, 7), generator=torch.Generator().manual_seed(4))
        assert got == pytest.approx(want, rel=1e-9, abs=1e-15)
        assert (got > 0.1) == (s != 1.0)


@pytest.mark.parametrize("period", [1, 3, 5])
def test_capture_needs_a_sensor_image_of_one_cfa_period(tiny_camera, period):
    """The smallest sensor image capture makes is max(2, CFA period) px per side: the scene needs that plus the
    kernel margin (valid); one pixel less is refused with the user's message naming the CFA period."""
    cam = tiny_camera(f"camera.cfa.period={period}")
    n = max(2, period)
    assert cam.min_sensor_px() == n
    assert cam.min_scene_size() == (n + cam.margin, n + cam.margin)
    cam.check_capture_size((n + cam.margin, n + cam.margin))
    with pytest.raises(InputError) as err:
        cam.check_capture_size((n + cam.margin - 1, n + cam.margin + 4), "s.npy")
    msg = str(err.value)
    assert msg.startswith(f"s.npy: the scene is {n + cam.margin - 1}×{n + cam.margin + 4} px, too small: this camera "
                          f"needs {n + cam.margin}×{n + cam.margin} px, a sensor image of at least {n}×{n} px")
    assert ("(one CFA period)" in msg) == (period > 2)


def test_default_snapshot_maps_the_cube_its_scene_size_names_onto_the_sensor_window():
    """OperatorSnapshot.scene_size(h, w) is the cube that A maps onto an (h, w) sensor window: for a valid camera
    cropping 2 px per side, (h + 4, w + 4) (A applied to it gives (h, w)), and Aᵀ of the window has that size."""
    snap = _SumCamera(crop=2).snapshot()
    hw = (5, 9)
    assert snap.scene_size(hw) == (9, 13)
    x = torch.rand(1, 3, *snap.scene_size(hw), dtype=torch.float64)
    assert tuple(snap.A(x).shape[-2:]) == hw
    assert tuple(snap.A_adjoint(torch.ones(1, 1, *hw, dtype=torch.float64)).shape[-2:]) == snap.scene_size(hw)


@pytest.mark.parametrize("peak, warns", [(3.9, False), (4.5, True)])
def test_capture_warns_for_a_scene_peak_just_above_two_stops_over_full_scale(peak, warns, caplog):
    """A scene whose peak is above 4 (two stops over full scale, SCENE_PEAK_WARN) is warned about, naming the source
    and the peak; 3.9 is a highlight, not warned about."""
    cam = _SumCamera()
    x = torch.full((1, 3, 4, 4), 0.5, dtype=torch.float64)
    x[0, 1, 2, 2] = peak
    with caplog.at_level(logging.WARNING, logger="hsicam.cameras.base"):
        cam.capture(x, source="s.npy")
    msgs = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert bool(msgs) == warns
    if warns:
        assert msgs[0].startswith(f"s.npy: the scene's peak value is {peak:.4g}, far above 1")


def test_capture_size_refusal_offers_boundary_same_only_when_it_would_help(tiny_camera):
    """A scene of at least n px per side (n = the smallest sensor image) fits boundary=same, so the refusal offers
    it; a scene below n px fits neither, and the refusal says only "use a larger scene"."""
    cam = tiny_camera("camera.cfa.period=3")
    n, m = cam.min_sensor_px(), cam.margin
    assert m > 0
    with pytest.raises(InputError) as err:
        cam.check_capture_size((n, n + m))
    assert str(err.value).endswith(f"to the {m + 1}-px PSF kernel; use a larger scene or boundary=same")
    with pytest.raises(InputError) as err:
        cam.check_capture_size((n - 1, n + m))
    assert str(err.value).endswith(f"to the {m + 1}-px PSF kernel; use a larger scene")


# --------------------------------------------------------------------------------------------
# cameras/doe_camera.py
# --------------------------------------------------------------------------------------------
def test_a_nominal_snapshot_has_the_psf_of_the_element_without_height_noise(tiny_camera):
    """``snapshot(nominal=True)`` of a camera with fabrication noise σ_p is the operator of the design: its PSFs are
    those of the same camera built with σ_p = 0, whatever the generator (the noisy snapshot differs)."""
    noisy = tiny_camera("camera.doe.sigma_height_nm=80", dtype=torch.float64)
    clean = tiny_camera("camera.doe.sigma_height_nm=0", dtype=torch.float64)
    with torch.no_grad():
        ref = clean.psf()
        nominal = noisy.snapshot(torch.Generator().manual_seed(5), nominal=True).psf
        drawn = noisy.snapshot(torch.Generator().manual_seed(5)).psf
    torch.testing.assert_close(nominal, ref, rtol=1e-12, atol=1e-15)
    assert (drawn - ref).abs().max() > 1e-3 * ref.abs().max()  # the test has teeth: σ_p moves the PSF
    assert noisy.optics.doe.sigma_height_m == pytest.approx(80e-9)  # and the camera keeps its σ_p


def test_a_cropped_snapshot_keeps_the_kernel_centred_on_the_optical_axis(tiny_camera):
    """``cropped(k)`` cuts each PSF to its central k×k about the axis pixel (K//2, K//2): a point source imaged
    through the cropped operator (no CFA) is that central part of the full PSF, centred on the source."""
    cam = tiny_camera("camera.cfa.enabled=false", "camera.doe.init=random", dtype=torch.float64)
    with torch.no_grad():
        snap = cam.snapshot()
        full = snap.psf.numpy()
        kk, c = full.shape[-1], full.shape[-1] // 2
        assert kk >= 5
        small = snap.cropped(3)
        x = torch.zeros(1, len(cam.bands), 15, 15, dtype=torch.float64)
        x[0, 1, 7, 7] = 1.0
        img = small.A(x)[0, 0].numpy()
    np.testing.assert_allclose(small.psf.numpy(), full[:, c - 1 : c + 2, c - 1 : c + 2], rtol=0, atol=0)
    ref = np.zeros((15, 15))
    ref[6:9, 6:9] = full[1, c - 1 : c + 2, c - 1 : c + 2]
    np.testing.assert_allclose(img, ref, atol=1e-12)


def test_sensor_noise_comes_from_the_sensor_generator_when_one_is_given(tiny_camera):
    """``forward(x, generator, sensor_generator=g)``: the sensor noise is σ_s · N(0, 1) drawn from g (the same draw
    as ``torch.randn`` from a generator of g's seed), not from ``generator``."""
    cam = tiny_camera("camera.sensor.noise=gaussian", "camera.sensor.sigma=0.01", dtype=torch.float64)
    x = torch.rand(1, len(cam.bands), 20, 20, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    with torch.no_grad():
        clean = cam.A(x)
        noisy = cam(x, torch.Generator().manual_seed(1), sensor_generator=torch.Generator().manual_seed(2))
    draw = torch.randn(clean.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    torch.testing.assert_close(noisy - clean, 0.01 * draw, rtol=1e-9, atol=1e-12)


def test_a_camera_without_a_cfa_has_code_period_one(tiny_camera):
    """No CFA: κ = 1 at every pixel, so the sensor code repeats every pixel (period 1), whatever ``cfa.period``."""
    cam = tiny_camera("camera.cfa.enabled=false", "camera.cfa.period=3")
    code = cam.sensor_code(6, 6)
    assert torch.equal(code, torch.ones_like(code))
    assert cam.code_period == 1
    assert tiny_camera("camera.cfa.period=3").code_period == 3
