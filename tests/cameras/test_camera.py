"""The DOE camera operator g = Σ_λ (f_λ ⊛ p_λ) ⊙ κ_λ: adjointness, an independent direct
(shift-and-add) reference, gradients, dtypes, batching, devices and input errors. (The coded convolutions it is
built on, hsicam.optics.convolution, are tested in optics/test_coded_convolution.py.)"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from torch.func import functional_call

from hsicam.errors import InputError
from optics_reference import reference_measurement

BOUNDARIES = [("valid", "zeros"), ("same", "zeros"), ("same", "reflect"), ("same", "replicate"), ("same", "circular")]
SWITCHES = list(itertools.product([True, False], [True, False]))  # (DOE enabled, CFA enabled)
SENSOR_HW = (8, 10)  # not a multiple of the 3×3 CFA period, not square


def _camera(tiny_camera, doe: bool, cfa: bool, boundary: str, padding: str, dtype=torch.float64, *extra: str):
    return tiny_camera(
        f"camera.doe.enabled={str(doe).lower()}", f"camera.cfa.enabled={str(cfa).lower()}",
        f"camera.boundary={boundary}", f"camera.padding={padding}", *extra, dtype=dtype,
    )


def _scene(cam, batch: int = 2, seed: int = 0, dtype=torch.float64, positive: bool = True) -> torch.Tensor:
    h, w = cam.scene_size(SENSOR_HW)
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, len(cam.bands), h, w, generator=g, dtype=dtype)
    return x if positive else x - 0.5


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().double().cpu().numpy()


# --------------------------------------------------------------------------------------------
# Linear operator: adjointness and the direct reference
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("boundary, padding", BOUNDARIES)
@pytest.mark.parametrize("doe, cfa", SWITCHES)
def test_adjointness(tiny_camera, doe, cfa, boundary, padding):
    cam = _camera(tiny_camera, doe, cfa, boundary, padding)
    with torch.no_grad():
        psf = cam.psf()
        x = _scene(cam, seed=1)
        y = torch.rand(2, 1, *SENSOR_HW, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        ax = cam.A(x, psf)
        aty = cam.A_adjoint(y, psf)
    assert ax.shape == y.shape and aty.shape == x.shape
    lhs, rhs = (ax * y).sum().item(), (x * aty).sum().item()
    assert abs(lhs - rhs) / abs(lhs) < 1e-6
    # also with zero-mean vectors, relative to the Cauchy-Schwarz bound
    x2, y2 = x - 0.5, y - 0.5
    with torch.no_grad():
        lhs2, rhs2 = (cam.A(x2, psf) * y2).sum().item(), (x2 * cam.A_adjoint(y2, psf)).sum().item()
    assert abs(lhs2 - rhs2) < 1e-10 * cam.A(x2, psf).norm().item() * y2.norm().item()


@pytest.mark.parametrize("boundary, padding", [("valid", "zeros"), ("same", "reflect")])
def test_adjoint_is_the_transpose_matrix(tiny_camera, boundary, padding):
    """Dense check on a small sensor: the matrix of A_adjoint is the transpose of the matrix of A."""
    cam = _camera(tiny_camera, True, True, boundary, padding)
    hw = (4, 5)
    sh, sw = cam.scene_size(hw)
    n, m = len(cam.bands) * sh * sw, hw[0] * hw[1]
    with torch.no_grad():
        psf = cam.psf()
        a = cam.A(torch.eye(n, dtype=torch.float64).reshape(n, len(cam.bands), sh, sw), psf).reshape(n, m).T
        at = cam.A_adjoint(torch.eye(m, dtype=torch.float64).reshape(m, 1, *hw), psf).reshape(m, n).T
    torch.testing.assert_close(at, a.T, rtol=0, atol=1e-12 * a.abs().max().item())
    assert torch.linalg.matrix_rank(a) == m  # a real, non-degenerate operator


@pytest.mark.parametrize("boundary, padding", BOUNDARIES)
@pytest.mark.parametrize("doe, cfa", SWITCHES)
def test_forward_matches_direct_convolution(tiny_camera, doe, cfa, boundary, padding):
    cam = _camera(tiny_camera, doe, cfa, boundary, padding)
    x = _scene(cam, seed=3)
    with torch.no_grad():
        psf = cam.psf()
        got = cam.A(x, psf)
    weights = _np(cam.cfa.weights) if cfa else None
    expected = reference_measurement(_np(x), _np(psf), weights, boundary, padding)
    assert got.shape == (2, 1, *SENSOR_HW)
    np.testing.assert_allclose(_np(got), expected, rtol=1e-10, atol=1e-12)


def test_point_source_images_the_psf_unflipped(tiny_camera):
    """A point at scene pixel (i0, j0) gives the PSF with its axis pixel at sensor (i0−K//2, j0−K//2)."""
    cam = _camera(tiny_camera, True, False, "valid", "zeros")
    k = cam.kernel_px
    x = torch.zeros(1, 3, *cam.scene_size(SENSOR_HW), dtype=torch.float64)
    i0, j0 = 7, 9
    x[0, 1, i0, j0] = 1.0  # one band only
    with torch.no_grad():
        psf = cam.psf()
        g = cam.A(x, psf)[0, 0]
    r = k // 2
    i, j = i0 - r, j0 - r  # sensor pixel on the optical axis of the point
    window = g[i - r : i + r + 1, j - r : j + r + 1]
    torch.testing.assert_close(window, psf[1], rtol=1e-10, atol=1e-14)
    assert torch.count_nonzero(g.abs() > 1e-14) <= k * k
    assert not torch.allclose(psf[1], torch.flip(psf[1], (0, 1)))  # the test can see a flip


def test_adjoint_agrees_with_autograd(tiny_camera):
    """A_adjoint and the custom backward of A (since session 34 both run the same chunked correlation,
    A_adjoint without autograd: the dense transpose test above and the coded adjoint's tests below
    check it against independent references)."""
    cam = _camera(tiny_camera, True, True, "same", "replicate")
    x = _scene(cam, seed=4).requires_grad_(True)
    y = torch.randn(2, 1, *SENSOR_HW, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    psf = cam.psf().detach()
    (vjp,) = torch.autograd.grad(cam.A(x, psf), x, y)
    torch.testing.assert_close(vjp, cam.A_adjoint(y, psf), rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------------
def test_gradients_reach_doe_heights_and_cfa_weights(tiny_camera):
    cam = _camera(tiny_camera, True, True, "valid", "zeros", torch.float32)
    x = _scene(cam, dtype=torch.float32)
    target = torch.rand(2, 1, *SENSOR_HW, generator=torch.Generator().manual_seed(6))
    loss = (cam(x) - target).square().mean()
    loss.backward()
    for p in (cam.optics.doe.height_m, cam.cfa.weights):
        assert p.grad is not None and p.grad.shape == p.shape
        assert torch.isfinite(p.grad).all() and p.grad.abs().max() > 0
    assert (cam.cfa.weights.grad != 0).float().mean() > 0.9  # every filter of the tile is used


@pytest.mark.parametrize("boundary, padding", [("valid", "zeros"), ("same", "circular")])
def test_camera_gradcheck_wrt_doe_heights_and_cfa_weights(tiny_camera, boundary, padding):
    cam = _camera(tiny_camera, True, True, boundary, padding)
    hw = (4, 5)
    x = torch.rand(1, 3, *cam.scene_size(hw), generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    h0 = (cam.optics.doe.height_m.detach() * 1e6).clone().requires_grad_(True)  # in µm: O(1) steps
    w0 = cam.cfa.weights.detach().clone().requires_grad_(True)

    def measure(h_um, weights):
        return functional_call(cam, {"optics.doe.height_m": h_um * 1e-6, "cfa.weights": weights}, (x,))

    assert torch.autograd.gradcheck(measure, (h0, w0), eps=1e-6, atol=1e-8, rtol=1e-4)


# --------------------------------------------------------------------------------------------
# dtypes, batching, devices, reproducibility
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("boundary, padding", [("valid", "zeros"), ("same", "reflect")])
def test_float32_and_float64_agree(tiny_camera, clone_camera, boundary, padding):
    cam32 = _camera(tiny_camera, True, True, boundary, padding, torch.float32)
    cam64 = clone_camera(cam32, torch.float64)
    x = _scene(cam64, seed=9)
    with torch.no_grad():
        g32, g64 = cam32.A(x.float()), cam64.A(x)
        p32, p64 = cam32.psf(), cam64.psf()
    assert g32.dtype == torch.float32 and g64.dtype == torch.float64 and p64.dtype == torch.float64
    torch.testing.assert_close(p32.double(), p64, rtol=0, atol=1e-5 * p64.max().item())
    torch.testing.assert_close(g32.double(), g64, rtol=0, atol=1e-5 * g64.abs().max().item())


@pytest.mark.parametrize("boundary, padding", [("valid", "zeros"), ("same", "replicate")])
def test_batched_equals_per_item(tiny_camera, boundary, padding):
    cam = _camera(tiny_camera, True, True, boundary, padding)
    x = _scene(cam, batch=3, seed=10)
    y = torch.rand(3, 1, *SENSOR_HW, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    with torch.no_grad():
        psf = cam.psf()
        batched, batched_adj = cam.A(x, psf), cam.A_adjoint(y, psf)
        for i in range(3):
            torch.testing.assert_close(batched[i : i + 1], cam.A(x[i : i + 1], psf), rtol=1e-12, atol=1e-14)
            torch.testing.assert_close(batched_adj[i : i + 1], cam.A_adjoint(y[i : i + 1], psf), rtol=1e-12, atol=1e-14)


def test_forward_is_reproducible_from_a_seed(tiny_camera):
    cam = tiny_camera("camera.sensor.sigma=0.01", "camera.doe.sigma_height_nm=20")
    x = _scene(cam, dtype=torch.float32)
    with torch.no_grad():
        a = cam(x, torch.Generator().manual_seed(3))
        b = cam(x, torch.Generator().manual_seed(3))
        c = cam(x, torch.Generator().manual_seed(4))
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.allclose(a, c)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_and_cuda_agree(tiny_camera, clone_camera, dtype):
    cpu = _camera(tiny_camera, True, True, "same", "reflect", dtype)
    gpu = clone_camera(cpu, dtype).to("cuda")
    x = _scene(cpu, seed=12, dtype=dtype)
    y = torch.rand(2, 1, *SENSOR_HW, generator=torch.Generator().manual_seed(13), dtype=dtype)
    with torch.no_grad():
        g_cpu, g_gpu = cpu.A(x), gpu.A(x.cuda())
        a_cpu, a_gpu = cpu.A_adjoint(y), gpu.A_adjoint(y.cuda())
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    assert g_gpu.device.type == "cuda" and g_gpu.dtype == dtype
    torch.testing.assert_close(g_gpu.cpu(), g_cpu, rtol=0, atol=tol * g_cpu.abs().max().item())
    torch.testing.assert_close(a_gpu.cpu(), a_cpu, rtol=0, atol=tol * a_cpu.abs().max().item())
    loss = gpu.A(x.cuda()).square().sum()
    loss.backward()
    assert torch.isfinite(gpu.optics.doe.height_m.grad).all() and gpu.cfa.weights.grad.device.type == "cuda"
    # the snapshot's A and Aᵀ without gradients (the consistency steps: the same-geometry convolutions, whole batches
    # and the einsum's band sum on the GPU) against the CPU's
    with torch.no_grad():
        s_cpu, s_gpu = cpu.snapshot(nominal=True), gpu.snapshot(nominal=True)
        xs = torch.rand(2, len(cpu.bands), *SENSOR_HW, generator=torch.Generator().manual_seed(14), dtype=dtype)
        for origin in ((0, 0), (1, 2)):
            sa_cpu, sa_gpu = s_cpu.A(xs, origin), s_gpu.A(xs.cuda(), origin)
            st_cpu, st_gpu = s_cpu.A_adjoint(y, origin), s_gpu.A_adjoint(y.cuda(), origin)
            torch.testing.assert_close(sa_gpu.cpu(), sa_cpu, rtol=0, atol=tol * sa_cpu.abs().max().item())
            torch.testing.assert_close(st_gpu.cpu(), st_cpu, rtol=0, atol=tol * st_cpu.abs().max().item())


# --------------------------------------------------------------------------------------------
# Input errors
# --------------------------------------------------------------------------------------------
def test_wrong_band_count_is_an_input_error(tiny_camera):
    cam = tiny_camera()
    x = torch.rand(1, 4, *cam.scene_size(SENSOR_HW))
    with pytest.raises(InputError, match="4 bands"):
        cam.A(x)


@pytest.mark.parametrize("shape", [(1, 3, 6, 20), (1, 3, 20, 6), (3, 20, 20)])
def test_too_small_or_malformed_scene_is_an_input_error(tiny_camera, shape):
    cam = tiny_camera()  # valid mode, 7-px kernel: the scene needs at least 7×7
    assert cam.kernel_px == 7
    with pytest.raises(InputError):
        cam.A(torch.rand(*shape))


def test_too_small_scene_for_reflect_padding_is_an_input_error(tiny_camera):
    cam = tiny_camera("camera.boundary=same", "camera.padding=reflect")
    with pytest.raises(InputError):
        cam.A(torch.rand(1, 3, 2, 2))


@pytest.mark.parametrize("padding, least", [("reflect", 4), ("circular", 3), ("replicate", 1), ("zeros", 1)])
def test_the_smallest_scene_each_padding_takes(tiny_camera, padding, least):
    """A 7-px kernel pads a ``same`` scene by 3 px a side: reflection needs 4 px (it mirrors about the edge
    pixel), wrapping around 3 (torch's circular padding may not wrap more than once); smaller scenes are one
    InputError naming the least size, not F.pad's RuntimeError. The least size images."""
    cam = tiny_camera("camera.boundary=same", f"camera.padding={padding}")
    assert cam.margin // 2 == 3
    assert cam.A(torch.rand(1, 3, least, least + 2)).shape[-2:] == (least, least + 2)
    if least > 1:
        with pytest.raises(InputError, match=rf"too small for {padding} padding by 3 px: it needs at least {least} px"):
            cam.A(torch.rand(1, 3, least - 1, 12))


def test_fixed_measure_computes_the_doe_psf_once_unless_height_noise_is_drawn(tiny_camera):
    """The DOE camera's ``fixed_measure`` reuses one nominal PSF stack (the optics do not change
    while it is used); with fabrication noise σ_p > 0 each call draws its own PSF."""
    cam = _camera(tiny_camera, True, True, "valid", "zeros")
    calls = []
    cam.optics.register_forward_hook(lambda *_: calls.append(1))
    x = _scene(cam)
    fn = cam.fixed_measure()
    y1, op1 = fn(x)
    y2, op2 = fn(0.5 * x)
    assert len(calls) == 1 and op1 is op2 and op1.psf.grad_fn is None
    torch.testing.assert_close(y2, 0.5 * y1, rtol=1e-12, atol=1e-15)  # linear, one operator
    torch.testing.assert_close(y1, cam.A(x).detach(), rtol=1e-12, atol=1e-15)
    cam.set_noise(sigma_height_nm=30.0)
    calls.clear()
    ya, _ = fn(x, torch.Generator().manual_seed(1))
    yb, _ = fn(x, torch.Generator().manual_seed(2))
    assert len(calls) == 2 and not torch.equal(ya, yb)
