"""Lines of the camera, model and optics modules that the default suite never ran: each test runs one and checks
what it does against an independent reference (the exact line a user sees, a closed form, a brute-force loop)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from conftest import TINY_CAMERA_OVERRIDES
from hsicam.cameras import DOECamera, build_camera
from hsicam.cameras.base import Camera, OperatorSnapshot
from hsicam.config import ConfigError, load_config
from hsicam.errors import InputError
from hsicam.models.consistency import consistency_step, linear_consistency_step, linear_reach_px
from hsicam.models.demosaic import phase_linear
from hsicam.models.unrolled import build_unrolled
from hsicam.optics.perturb import shift_fill
from hsicam.spectral import Bands


def _sellmeier_fused_silica(lam_nm: float) -> float:
    """Malitson (1965), written out here (not the library's table)."""
    x = (lam_nm / 1000.0) ** 2
    return math.sqrt(1 + 0.6961663 * x / (x - 0.0684043**2) + 0.4079426 * x / (x - 0.1162414**2)
                     + 0.8974794 * x / (x - 9.896161**2))


# --- optics/psf.py: the defocus refusal names the option that caused it -----------------------------------------
def test_object_distance_defocus_refusal_names_the_object_distance_and_where_the_sensor_belongs():
    # tiny optics: f = 5 mm, aperture radius 0.25 mm, 50 µm cells; an object at 5.1 mm images at
    # 1 / (1/5 − 1/5.1) = 255 mm, the sensor stays at f: geometric blur 2a · z_i / z_o = 0.5 · 5 / 5.1 mm
    blur_mm = 0.5 * 5.0 / 5.1
    field_mm = 500e-9 * 5e-3 / 50e-6 * 1e3  # λ z / d at 500 nm (the band that aliases most: the shortest)
    with pytest.raises(ConfigError) as err:
        DOECamera.from_config(load_config(overrides=[*TINY_CAMERA_OVERRIDES, "camera.object_distance_m=0.0051"]))
    msg = str(err.value)
    assert msg.startswith("camera.object_distance_m=0.0051 defocuses the lens more than the pupil sampling can "
                          "represent (focal length 5 mm at 587.6 nm, object at 0.0051 m: the sensor belongs near "
                          f"{1 / (1 / 5 - 1 / 5.1):.4g} mm)")
    assert f"blurs a point over {blur_mm:.3g} mm at 500 nm, wider than the {field_mm:.3g} mm field" in msg
    assert msg.endswith(f"focus on the object (camera.sensor_distance_mm={1 / (1 / 5 - 1 / 5.1):.4g}), or for a "
                        f"deliberate defocus raise camera.psf.pupil_oversample to at least "
                        f"{math.ceil(blur_mm / field_mm)}")


def test_singlet_focus_shift_refusal_blames_the_lens_not_an_option():
    # the paper's singlet (R = 16 mm, t = 2 mm, f = R/(n−1)) on 100 µm cells: at 420 nm the sensor, placed at f(587.6 nm)
    # from the rear principal plane H' (t/n behind the curved vertex, so it moves with n), sits off that band's focus
    n0, n1 = _sellmeier_fused_silica(587.6), _sellmeier_fused_silica(420.0)
    f0, f1 = 16.0 / (n0 - 1), 16.0 / (n1 - 1)
    z = f0 - 2.0 / n0 + 2.0 / n1  # the sensor's distance from H'(420 nm)
    blur_mm = 2 * 5.0 * abs(1 - z / f1)  # aperture diameter 10 mm
    field_mm = 420e-9 * z * 1e-3 / 100e-6 * 1e3
    with pytest.raises(ConfigError) as err:
        DOECamera.from_config(load_config(overrides=["camera.lens.model=singlet", "camera.doe.cell_size_um=100"]))
    msg = str(err.value)
    assert msg.startswith("the singlet lens's focus shift defocuses the lens more than the pupil sampling can represent "
                          f"(focal length {f0:.4g} mm at 587.6 nm, object at infinity: the sensor belongs near {f0:.4g} mm)")
    assert f"blurs a point over {blur_mm:.3g} mm at 420 nm, wider than the {field_mm:.3g} mm field" in msg
    assert msg.endswith(f"; for a deliberate defocus raise camera.psf.pupil_oversample to at least "
                        f"{math.ceil(blur_mm / field_mm)}")


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


# --- optics/perturb.py: a shift of the whole array or more leaves zeros ------------------------------------------
def test_shift_fill_by_the_size_or_more_is_all_zeros_and_smaller_shifts_match_a_loop():
    x = torch.arange(1.0, 13.0).reshape(3, 4)
    for dy, dx in ((3, 0), (0, -4), (-5, 1)):
        assert torch.equal(shift_fill(x, dy, dx), torch.zeros(3, 4))
    for dy, dx in ((1, -2), (-2, 3)):
        ref = torch.zeros(3, 4)
        for i in range(3):
            for j in range(4):
                if 0 <= i - dy < 3 and 0 <= j - dx < 4:
                    ref[i, j] = x[i - dy, j - dx]
        assert torch.equal(shift_fill(x, dy, dx), ref)


# --- cameras/cassi.py: coded-aperture files --------------------------------------------------------------------
def _cassi(tmp_path, mask_name: str):
    cfg = load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50",
                                 "camera.kind=dd_cassi", f"camera.cassi.mask_file={tmp_path / mask_name}"])
    return build_camera(cfg).double()


def test_a_boolean_mask_file_is_a_binary_coded_aperture(tmp_path):
    mask = np.random.default_rng(0).random((12, 30)) > 0.5  # np.save of a thresholded pattern: dtype bool
    np.save(tmp_path / "mask.npy", mask)
    cam = _cassi(tmp_path, "mask.npy")
    np.testing.assert_array_equal(cam.aperture.pattern(12, 18).numpy(), mask[:, :18].astype(np.float64))


@pytest.mark.parametrize("content, what", [(b"0 1 1 0\n1 0 0 1\n", "no NumPy header"), (None, "a .npz archive")])
def test_a_mask_file_that_is_not_npy_is_named_as_such_without_pickle_advice(tmp_path, content, what):
    path = tmp_path / "mask.npy"
    if content is None:  # np.savez to a file object keeps the .npy name
        with open(path, "wb") as fh:
            np.savez(fh, mask=np.ones((4, 4)))
    else:
        path.write_bytes(content)
    with pytest.raises(InputError) as err:
        _cassi(tmp_path, "mask.npy")
    assert str(err.value) == f"{path}: not a .npy file ({what}); save the coded aperture (H, W) with numpy.save"


# --- config.py ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides, message", [
    (["baselines.desci.iterations=[]"], "baselines.desci.iterations must be a non-empty list of counts >= 0, got []"),
    (["baselines.desci.iterations=[3, -1]"],
     "baselines.desci.iterations must be a non-empty list of counts >= 0, got [3, -1]"),
    # a value that is not valid YAML is kept as the string typed, then refused as that string
    (["model.consistency.kind=[linear"],
     "config key 'model.consistency.kind' must be one of 'landweber', 'linear', got '[linear'"),
])
def test_config_refusals_name_the_key_and_the_value_typed(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_config(overrides=overrides)
    assert str(err.value) == message
