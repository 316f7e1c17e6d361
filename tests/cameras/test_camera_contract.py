"""The operator contract every camera keeps, run over the camera registry (plus the measured-PSF
camera, which is built from a trained camera rather than a config).

A camera registered with ``@register_camera`` is covered here without editing this file; its
config overrides for a small instance go in ``SMALL`` (default: the tiny DOE optics of conftest).
Each camera's physics references (closed forms) stay in its own test file.
"""

from __future__ import annotations

import copy

import pytest
import torch

from conftest import TINY_CAMERA_OVERRIDES
from hsicam.cameras import FixedPSFCamera, build_camera, camera_kinds
from hsicam.config import load_config
from hsicam.errors import ConfigError, InputError

# Per-kind test overrides (small instances) and variants; kinds not named use the defaults.
SMALL: dict[str, list[tuple[str, ...]]] = {
    "doe": [(), ("camera.boundary=same",)],
    "dd_cassi": [("camera.cassi.convention=mean",), ("camera.cassi.convention=sum",)],
    "sd_cassi": [("camera.cassi.convention=mean",), ("camera.cassi.convention=sum",)],
}
SCENE_HW = (12, 13)


def _make_measured(overrides: tuple[str, ...]):
    cam = build_camera(load_config(overrides=[*TINY_CAMERA_OVERRIDES, "camera.kind=doe", *overrides]))
    g = torch.Generator().manual_seed(3)
    psf = cam.psf().detach() * (0.5 + torch.rand(cam.psf().shape, generator=g))
    return FixedPSFCamera.from_camera(cam, psf / psf.sum(dim=(-2, -1), keepdim=True))


CASES = [(kind, ov) for kind in camera_kinds() for ov in SMALL.get(kind, [()])] + [("measured_psf", ())]


def make_camera(kind: str, overrides: tuple[str, ...], dtype=torch.float64):
    if kind == "measured_psf":
        cam = _make_measured(overrides)
    else:
        cam = build_camera(load_config(overrides=[*TINY_CAMERA_OVERRIDES, f"camera.kind={kind}", *overrides]))
    return cam.to(dtype)


@pytest.fixture(params=CASES, ids=[f"{k}{'-' + '-'.join(o) if o else ''}" for k, o in CASES])
def case(request):
    kind, ov = request.param
    return kind, ov, make_camera(kind, ov)


def _rand(shape, seed, zero_mean=False):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    return x - x.mean() if zero_mean else x


def _scene(cam, b=1, seed=0, zero_mean=False):
    return _rand((b, len(cam.bands), *SCENE_HW), seed, zero_mean)


def test_kind_and_shapes(case):
    kind, _, cam = case
    assert cam.kind == kind
    x = _scene(cam, b=2)
    y = cam.A(x)
    assert y.shape == (2, 1, *cam.sensor_size(SCENE_HW))
    assert cam.A_adjoint(y).shape == x.shape
    assert cam.scene_size(tuple(y.shape[-2:])) == SCENE_HW


@pytest.mark.parametrize("zero_mean", [False, True])
def test_adjointness_float64(case, zero_mean):
    _, _, cam = case
    x = _scene(cam, seed=1, zero_mean=zero_mean)
    y = _rand(cam.A(x).shape, 2, zero_mean)
    with torch.no_grad():  # values only (the DOE camera's PSF carries the DOE's autograd graph)
        lhs, rhs = (cam.A(x) * y).sum(), (x * cam.A_adjoint(y)).sum()
        assert abs(float(lhs - rhs)) <= 1e-12 * float(cam.A(x).norm() * y.norm())
    assert cam.adjointness_error(SCENE_HW, torch.Generator().manual_seed(0)) < 1e-12


def _dense(cam) -> torch.Tensor:
    """The matrix of ``cam.A`` on scenes of SCENE_HW, (m, n): column j = A e_j (unit-vector scenes)."""
    c, (h, w) = len(cam.bands), SCENE_HW
    n = c * h * w
    basis = torch.eye(n, dtype=torch.float64).reshape(n, c, h, w)
    with torch.no_grad():
        return cam.A(basis).reshape(n, -1).T


def test_dense_transpose_and_gram_diagonal(case):
    _, _, cam = case
    c, (h, w) = len(cam.bands), SCENE_HW
    n = c * h * w
    a = _dense(cam)  # (m, n): column j = A e_j
    m = a.shape[0]
    ybasis = torch.eye(m, dtype=torch.float64).reshape(m, 1, *cam.sensor_size(SCENE_HW))
    at = cam.A_adjoint(ybasis).reshape(m, n)  # row i = Aᵀ e_i
    torch.testing.assert_close(at, a, rtol=0, atol=1e-12)
    if cam.has_diagonal_gram:
        gram = a @ a.T
        off = gram - torch.diag(torch.diag(gram))
        assert float(off.abs().max()) == 0.0
        d = torch.diag(gram)
        expect = torch.where(d > 1e-12, d, torch.ones_like(d))
        torch.testing.assert_close(cam.gram_diagonal(ybasis[:1]).reshape(-1), expect)
    else:
        with pytest.raises(NotImplementedError):
            cam.gram_diagonal(ybasis[:1])


def test_linearity_and_autograd_vjp(case):
    _, _, cam = case
    x1, x2 = _scene(cam, seed=4), _scene(cam, seed=5)
    torch.testing.assert_close(cam.A(2.0 * x1 - 0.5 * x2), 2.0 * cam.A(x1) - 0.5 * cam.A(x2))
    y = _rand(cam.A(x1).shape, 6)
    x = x1.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad((cam.A(x) * y).sum(), x)
    torch.testing.assert_close(grad, cam.A_adjoint(y))


def test_gradients_reach_each_parameter_group(case):
    """Autograd derivative along a random direction = central finite difference, per group."""
    _, _, cam = case
    x = _scene(cam, seed=7)
    y = _rand(cam.A(x).shape, 8)
    for name, params in cam.param_groups().items():
        p = params[0]
        with torch.no_grad():
            d = _rand(p.shape, 9) - 0.5
            d = d * (p.detach().abs().mean().clamp_min(1e-12) / d.abs().mean())
        loss = (cam.A(x) * y).sum()
        (grad,) = torch.autograd.grad(loss, p)
        eps = 1e-4
        with torch.no_grad():
            p.add_(eps * d)
            up = float((cam.A(x) * y).sum())
            p.sub_(2 * eps * d)
            down = float((cam.A(x) * y).sum())
            p.add_(eps * d)
        fd = (up - down) / (2 * eps)
        ad = float((grad * d).sum())
        assert abs(ad) > 0, f"group {name}: no gradient"
        assert abs(ad - fd) <= 1e-5 * abs(fd) + 1e-12, f"group {name}: autograd {ad} vs finite difference {fd}"


@torch.no_grad()  # values only: no autograd graph, no grad-to-scalar warnings
def test_float32_matches_float64_and_batch_matches_items(case):
    _, _, cam = case
    x = _scene(cam, b=3, seed=10)
    y64 = cam.A(x)
    y32 = copy.deepcopy(cam).float().A(x.float())
    torch.testing.assert_close(y32.double(), y64, rtol=1e-4, atol=1e-6 * float(y64.abs().max()))
    per_item = torch.cat([cam.A(x[i : i + 1]) for i in range(3)])
    torch.testing.assert_close(cam.A(x), per_item)


@torch.no_grad()  # values only: no autograd graph, no grad-to-scalar warnings
def test_noise_off_forward_is_A_and_seeded_noise_is_reproducible(case):
    _, _, cam = case
    x = _scene(cam, seed=11)
    off = {k: 0.0 for k in cam.noise_levels()}
    cam.set_noise(**off)
    if cam.noise.model != "none":
        torch.testing.assert_close(cam(x, torch.Generator().manual_seed(0)), cam.A(x))
        cam.set_noise(sensor_sigma=0.01)
        a = cam(x, torch.Generator().manual_seed(5))
        b = cam(x, torch.Generator().manual_seed(5))
        torch.testing.assert_close(a, b)
        assert float((a - cam.A(x)).std()) > 0.005


def test_set_noise_round_trip_and_unknown_names(case):
    _, _, cam = case
    levels = cam.noise_levels()
    assert "sensor_sigma" in levels
    new = {k: 0.5 * (i + 1) * 0.01 for i, k in enumerate(sorted(levels))}
    cam.set_noise(**new)
    got = cam.noise_levels()
    assert got.keys() == new.keys() and all(abs(got[k] - new[k]) < 1e-12 for k in new)
    with pytest.raises(ConfigError, match="sensor_sigma"):  # the message lists the valid names
        cam.set_noise(not_a_noise=1.0)
    for name in sorted(levels):  # a standard deviation: negative or NaN is an error, and nothing changes
        for bad in (-0.01, float("nan"), float("inf"), "abc"):
            with pytest.raises(ConfigError, match=f"{name}="):
                cam.set_noise(**{name: bad})
            assert cam.noise_levels() == got


def test_state_dict_round_trip(case):
    kind, ov, cam = case
    x = _scene(cam, seed=12)
    with torch.no_grad():
        for p in cam.parameters():
            p.mul_(1.1)
    other = make_camera(kind, ov)
    if kind == "measured_psf":  # the stack is no part of the state dict (a non-persistent buffer): given anew
        other = FixedPSFCamera.from_camera(other, cam.fixed_psf).to(cam.fixed_psf.dtype)
    other.load_state_dict(cam.state_dict())
    torch.testing.assert_close(other.A(x), cam.A(x))


def test_bad_shapes_are_input_errors(case):
    _, _, cam = case
    x = _scene(cam)
    with pytest.raises(InputError, match="bands"):
        cam.A(x[:, :-1])
    with pytest.raises(InputError):
        cam.A(x[0])
    with pytest.raises(InputError, match=r"\(B, 1, H, W\)"):
        cam.A_adjoint(torch.zeros(1, 2, 6, 6, dtype=torch.float64))
    with pytest.raises(InputError, match="floating"):
        cam.A_adjoint(torch.zeros(1, 1, 6, 6, dtype=torch.int64))


@torch.no_grad()  # values only: no autograd graph, no grad-to-scalar warnings
def test_sqnorm_is_the_largest_gain(case):
    """``sqnorm`` is ‖A‖² itself (its docstring: the largest eigenvalue of AᵀA, by the power method),
    not a bound: it equals the squared spectral norm of the dense matrix built from unit vectors,
    and no scene has a larger gain."""
    _, _, cam = case
    s = cam.sqnorm(SCENE_HW, iterations=60, generator=torch.Generator().manual_seed(0))
    assert s > 0 and torch.isfinite(torch.tensor(s))
    exact = float(torch.linalg.matrix_norm(_dense(cam), 2) ** 2)
    assert s == pytest.approx(exact, rel=1e-5)
    for seed in range(3):
        x = _scene(cam, seed=20 + seed)
        assert float(cam.A(x).square().sum() / x.square().sum()) <= s * (1 + 1e-6)


@pytest.mark.cuda  # selected by scripts/gpu_session.sh's `-m "cuda and not slow"`
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_equals_cuda(case):
    _, _, cam = case
    x = _scene(cam, seed=13)
    torch.testing.assert_close(copy.deepcopy(cam).cuda().A(x.cuda()).cpu(), cam.A(x))


def test_unknown_kind_is_one_clear_error():
    with pytest.raises(ConfigError, match="choose one of .*doe"):
        build_camera(load_config(overrides=["camera.kind=pinhole"]))


def test_fixed_measure_gives_the_measurement_without_autograd(case):
    """``fixed_measure()`` (training with the optics fixed) images a scene as ``measure`` does, but
    builds no graph through the camera, even when its parameters require gradients."""
    _, _, cam = case
    cam.eval()
    for p in cam.parameters():
        p.requires_grad_(True)
    x = _scene(cam, b=2, seed=4)
    fn = cam.fixed_measure()
    for seed in (0, 1):
        y_ref, _ = cam.measure(x, torch.Generator().manual_seed(seed))
        y, op = fn(x, torch.Generator().manual_seed(seed))
        assert not y.requires_grad and y.grad_fn is None
        torch.testing.assert_close(y, y_ref.detach(), rtol=1e-12, atol=1e-14)


@torch.no_grad()
def test_capture_warns_on_an_unnormalised_scene_and_refuses_an_overflowing_image(case, caplog):
    """Camera.capture (hsicam simulate's imaging): the forward pass itself for a normalised scene; a
    WARNING naming the source when the scene's peak exceeds SCENE_PEAK_WARN (a scene of 1 fills the
    sensor's full scale); one InputError naming the source and the peak when the image overflows."""
    import logging

    from hsicam.cameras.base import SCENE_PEAK_WARN

    _, ov, cam = case
    x = _scene(cam, seed=4)
    x[0, 0, 0, 0] = 1.0  # peak 1
    ones = torch.ones_like(x)
    if "camera.cassi.convention=sum" not in ov:  # (sum: the sensor adds the bands up)
        assert float(cam.A(ones).max()) <= 1 + 1e-6  # a scene of 1 fills the sensor's full scale at most
    with caplog.at_level(logging.WARNING, logger="hsicam.cameras.base"):
        torch.testing.assert_close(cam.capture(x, torch.Generator().manual_seed(2), source="s.npy"),
                                   cam(x, torch.Generator().manual_seed(2)))
        cam.capture(x * SCENE_PEAK_WARN, source="s.npy")  # up to the threshold: no warning
        assert not caplog.records
        y = cam.capture(x * 1e6, source="bright.npy")
    assert torch.isfinite(y).all() and not y.requires_grad
    [rec] = caplog.records
    assert rec.levelno == logging.WARNING and rec.getMessage().startswith("bright.npy: the scene's peak value is 1e+06")
    assert "saturates" in rec.getMessage() and "[0, 1]" in rec.getMessage()
    caplog.clear()
    if bool(torch.isfinite(cam.A(ones * 1e308)).all()):  # a camera whose image cannot overflow (a convex weighting
        return                                               # of the bands: docs/architecture.md's own new camera)
    with pytest.raises(InputError, match=r"^huge\.npy: the simulated sensor image is not finite .*peak value is 1e\+308.*\[0, 1\]"):
        cam.capture(ones * 1e308, source="huge.npy")  # float64: overflows in the sums of every shipped camera
    assert not caplog.records  # the error alone, no warning line before it


@torch.no_grad()
def test_capture_refuses_a_scene_with_negative_values(case):
    """Camera.capture refuses negative radiance as ``hsicam simulate``'s cube check does for a file (a scene with
    them imaged silently: the sensor image then dips below the light any real scene gives), naming the source, the
    count and the minimum; the same scene clamped at 0 is imaged."""
    _, _, cam = case
    x = _scene(cam, seed=5)
    x[0, 1, 2, 3] = -0.25
    x[0, 0, 0, 0] = -1e-9
    with pytest.raises(InputError, match=r"^neg\.npy: 2 negative radiance value\(s\) \(minimum -0\.25\)"):
        cam.capture(x, source="neg.npy")
    y = cam.capture(x.clamp_min(0), torch.Generator().manual_seed(1), source="neg.npy")
    torch.testing.assert_close(y, cam(x.clamp_min(0), torch.Generator().manual_seed(1)))
