"""Lines of the camera and model modules that the default suite never ran: each test runs one and checks what it
does against an independent reference (the exact line a user sees, a closed form, a brute-force loop). The defocus
and coded-aperture refusals are in cameras/test_cameras_rare_paths.py, shift_fill in export/test_export_rare_paths.py,
the config refusals in cli/test_cli_and_config_rare_paths.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from conftest import TINY_CAMERA_OVERRIDES
from hsicam.cameras import DOECamera
from hsicam.cameras.base import Camera, OperatorSnapshot
from hsicam.config import load_config
from hsicam.errors import InputError
from hsicam.models.consistency import consistency_step, linear_consistency_step, linear_reach_px
from hsicam.models.demosaic import phase_linear
from hsicam.models.unrolled import build_unrolled
from hsicam.spectral import Bands


# --- cameras/base.py: a camera that brings only A and A_adjoint (a plug-in) gets the default operator ----------
class _Noiseless(nn.Module):
    def forward(self, g, generator=None):
        return g


class _WeightedSum(Camera):
    """y = 0.25 x₀ + 0.75 x₁ per pixel: the simplest camera a user could register."""

    boundary = "same"

    def __init__(self) -> None:
        super().__init__()
        self.bands = Bands(np.array([500.0, 600.0]), np.array([10.0, 10.0]))
        self.noise = _Noiseless()
        self.register_buffer("w", torch.tensor([0.25, 0.75], dtype=torch.float64))

    @property
    def margin(self) -> int:
        return 0

    def A(self, x):  # noqa: N802
        return (x * self.w[:, None, None]).sum(1, keepdim=True)

    def A_adjoint(self, y):  # noqa: N802
        return y * self.w[:, None, None]


def test_default_snapshot_of_a_plugin_camera_delegates_and_refuses_what_it_cannot_do():
    cam = _WeightedSum()
    x = torch.rand(2, 2, 4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    y, op = cam.measure(x)
    assert op is cam
    torch.testing.assert_close(y, 0.25 * x[:, :1] + 0.75 * x[:, 1:], rtol=0, atol=1e-15)
    snap = cam.snapshot()
    assert isinstance(snap, OperatorSnapshot) and snap.lipschitz is None
    assert snap.bands is cam.bands and snap.code_period == 1 and snap.scene_size((4, 5)) == (4, 5)
    torch.testing.assert_close(snap.A(x), y, rtol=0, atol=0)
    torch.testing.assert_close(snap.A_adjoint(y), torch.cat([0.25 * y, 0.75 * y], 1), rtol=0, atol=0)
    with pytest.raises(NotImplementedError, match=r"^_WeightedSum has no position-dependent operator for a window "
                                                  r"at origin \(1, 0\)$"):
        snap.A(x, (1, 0))
    with pytest.raises(NotImplementedError, match=r"at origin \(0, 2\)$"):
        snap.A_adjoint(y, (0, 2))
    # measurement consistency needs ‖A‖²: one clear error, not a TypeError from float(None)
    with pytest.raises(InputError, match=r"^measurement consistency needs an operator with a bound of ‖A‖² "
                                         r"\(lipschitz\), not OperatorSnapshot$"):
        consistency_step(snap, y, x, extend=False)


# --- models/consistency.py ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def reflect_camera():
    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "camera.boundary=same", "camera.padding=reflect"])
    return DOECamera.from_config(cfg).double()


def test_reflect_extension_falls_back_to_replicate_on_a_window_too_small_to_mirror(reflect_camera):
    op = reflect_camera.snapshot(nominal=True)  # 7-px kernel: the estimate is extended by 3 px per side
    g = torch.Generator().manual_seed(0)
    c = len(reflect_camera.bands)
    for n, same in ((3, True), (4, False)):  # 3 px cannot be mirrored by 3 px (F.pad would raise); 4 px can
        y = torch.rand(1, 1, n, n, dtype=torch.float64, generator=g)
        x0 = torch.rand(1, c, n, n, dtype=torch.float64, generator=g)
        a = consistency_step(op, y, x0, extend="reflect", iterations=2)
        b = consistency_step(op, y, x0, extend="replicate", iterations=2)
        assert torch.equal(a, b) is same


def test_zero_iterations_return_the_start_itself(reflect_camera):
    op = reflect_camera.snapshot(nominal=True)
    x0 = torch.rand(1, len(reflect_camera.bands), 6, 6, dtype=torch.float64)
    y = torch.rand(1, 1, 6, 6, dtype=torch.float64)
    weight = torch.zeros(9, len(reflect_camera.bands), 3, 3, dtype=torch.float64)
    assert linear_consistency_step(op, y, x0, weight, iterations=0) is x0
    assert linear_reach_px(op, window=3, iterations=0) == 0
    with pytest.raises(ValueError, match=r"^extend must be a bool, 'replicate' or 'reflect', got 'mirror'$"):
        linear_consistency_step(op, y, x0, weight, extend="mirror")


# --- models/demosaic.py: per-phase filters on a window smaller than one period -----------------------------------
def test_phase_linear_on_a_window_smaller_than_the_period_matches_a_loop():
    m, c, k = 3, 2, 3
    g = torch.Generator().manual_seed(3)
    weight = torch.randn(m * m, c, k, k, dtype=torch.float64, generator=g)
    sensor = torch.rand(1, 1, 2, 2, dtype=torch.float64, generator=g)  # 2 < m: some phases have no pixel here
    for origin in ((0, 0), (2, 1)):
        out = phase_linear(sensor, weight, origin)
        s = np.pad(sensor[0, 0].numpy(), 1, mode="edge")
        ref = np.zeros((c, 2, 2))
        for i in range(2):
            for j in range(2):
                phase = ((i + origin[0]) % m) * m + (j + origin[1]) % m
                ref[:, i, j] = np.einsum("ckl,kl->c", weight[phase].numpy(), s[i:i + k, j:j + k])
        np.testing.assert_allclose(out[0].numpy(), ref, rtol=1e-12, atol=1e-14)


# --- models/unrolled.py: the stages' PSFs cut to stage_kernel_px ------------------------------------------------
def test_unrolled_stages_use_the_psf_cut_to_stage_kernel_px():
    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "model.kind=unrolled", "model.unrolled.stage_kernel_px=3",
                                 "model.unrolled.stages=1"])
    cam = DOECamera.from_config(cfg).double()
    net = build_unrolled(cfg.model.unrolled, cam)
    full = cam.snapshot(nominal=True)
    op = net.operator(cam)
    assert full.kernel_px == 7 and op.kernel_px == 3
    torch.testing.assert_close(op.psf, full.psf[:, 2:5, 2:5], rtol=0, atol=0)
    assert tuple(op.reach_px) == net.op_reach
