"""Reconstruction networks beyond the RDN (mosaic-aware, unrolled) and the camera snapshots they use.

Contract per network and camera kind: any band count and size, float32 output on the camera's
scene grid, overfits a batch, tiled = whole with the declared ``context_px``, the unrolled data
step lowers ‖A x − y‖, gradients reach the optics through the stages, bad settings are one
ConfigError line. Tiny cameras (``tiny`` preset: 7 bands, 21 px kernel, CFA period 3).
"""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch

from hsicam.cameras import build_camera
from hsicam.config import load_config
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import ConfigError
from hsicam.config import MosaicConfig, UnrolledConfig
from hsicam.models.mosaic import MosaicNet, build_mosaic, phase_pad
from hsicam.models.rdn import RDNReconstructor
from hsicam.models.unrolled import UnrolledNet, build_unrolled

CAMERA_KINDS = ("doe", "dd_cassi", "sd_cassi")
MOSAIC = MosaicConfig(features=8, blocks=1, head_features=4, head_layers=2)
MOSAIC_DETAIL = dataclasses.replace(MOSAIC, detail_features=3)  # the trunk's features at full resolution in the head
# + the half-resolution stage (needs an even factor: 6 = two periods of the tiny camera's 3×3 CFA)
MOSAIC_MID = dataclasses.replace(MOSAIC_DETAIL, factor=6, mid_features=4, mid_blocks=1)
UNROLLED = UnrolledConfig(stages=2, prior_features=8, prior_blocks=1, prior_scale=2)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def camera(kind: str = "doe", *overrides: str):
    torch.manual_seed(0)
    return build_camera(load_config("tiny", overrides=[f"camera.kind={kind}", *overrides]))


def networks(cam) -> dict:
    """The small networks that fit ``cam`` (the mosaic net needs a CFA)."""
    nets = {"unrolled": build_unrolled(UNROLLED, cam), "rdn-backprojection": rdn_backprojection(cam)}
    try:
        cam.sensor_code(1, 1)
    except NotImplementedError:
        return nets
    nets["mosaic"] = build_mosaic(MOSAIC, cam)
    nets["mosaic-detail"] = build_mosaic(MOSAIC_DETAIL, cam)
    nets["mosaic-mid"] = build_mosaic(MOSAIC_MID, cam)
    nets["unrolled-mosaic"] = build_unrolled(UnrolledConfig(stages=1, init="mosaic", prior_features=8, prior_blocks=1,
                                                              prior_scale=2, mosaic=MOSAIC), cam)
    return nets


def rdn_backprojection(cam) -> RDNReconstructor:
    """A small RDN reading Aᵀy ⊘ AᵀA𝟙 (the CASSI RDN), with the operator's reach as its first context."""
    return RDNReconstructor(len(cam.bands), blocks=1, features=8, growth=4, layers_per_block=2,
                            backprojection_input=True, op_reach_px=max(cam.snapshot(nominal=True).reach_px))


def randomise(net: torch.nn.Module, scale: float = 0.05) -> torch.nn.Module:
    """Perturb every parameter (the zero-initialised output convs would hide paths)."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g))
    return net


# ------------------------------------------------------------------------------------------------
# Snapshots: the frozen operators
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", CAMERA_KINDS)
@pytest.mark.parametrize("origin", [(0, 0), (4, 7)])
def test_snapshot_adjointness_float64(kind, origin):
    cam = camera(kind).double()
    op = cam.snapshot()
    g = torch.Generator().manual_seed(0)
    h, w = 19, 26
    x = torch.randn(2, len(cam.bands), *op.scene_size((h, w)), generator=g, dtype=torch.float64)
    y = torch.randn(2, 1, h, w, generator=g, dtype=torch.float64)
    ax, aty = op.A(x, origin), op.A_adjoint(y, origin)
    assert ax.shape == y.shape and aty.shape == x.shape
    lhs, rhs = (ax * y).sum().detach(), (x * aty).sum().detach()
    assert abs(float(lhs - rhs)) <= 1e-10 * float(lhs.abs() + rhs.abs())


@pytest.mark.parametrize("kind", CAMERA_KINDS)
def test_snapshot_window_at_origin_is_a_crop(kind):
    """Pixel-wise structure (CFA phase, aperture) follows the window's origin."""
    cam = camera(kind, "camera.boundary=same")
    op = cam.snapshot()
    h, w = 24, 30
    x = torch.rand(1, len(cam.bands), *op.scene_size((h, w)))
    whole = op.A(x)
    if kind == "doe":  # same geometry, zero padding: the camera's own A in same mode
        assert torch.allclose(whole, cam.A(x), atol=1e-6)
        x = torch.zeros_like(x)
        x[..., 10, 12] = 1.0  # a point far from both windows' borders
        whole = op.A(x)
    else:
        assert torch.allclose(whole, cam.A(x), atol=1e-6)
    r0, c0 = 4, 5
    part = op.A(x[..., r0:, c0:], (r0, c0))
    d = cam.span if kind == "sd_cassi" else 0  # SD-CASSI: sensor columns < c0 + D also see scene columns < c0
    assert torch.allclose(part[..., d:], whole[..., r0:, c0 + d :], atol=1e-6)


def test_snapshot_lipschitz_bounds_the_operator_norm():
    """L ≥ ‖A‖² (power iteration on AᵀA) for every snapshot. DOE: L is max_c ‖p_c‖₁² · max_pixel
    Σ_c κ_c², recomputed here from the snapshot's PSF stack and CFA tile. DD-CASSI: ΦΦᵀ is diagonal
    with entries s² Σ_c P(shifted)², and a 20×24 window of the random binary aperture has pixels
    whose C shifted code entries are all open, so L = s²·C is reached (power iteration ≥ 0.99 L)."""
    for kind in CAMERA_KINDS:
        cam = camera(kind).double()
        op = cam.snapshot()
        x = torch.rand(1, len(cam.bands), *op.scene_size((20, 24)), dtype=torch.float64)
        for _ in range(30):  # power iteration on AᵀA
            x = op.A_adjoint(op.A(x))
            x = x / x.norm()
        sq = float(op.A(x).square().sum().detach())
        assert 0 < sq <= op.lipschitz * (1 + 1e-9), kind
        if kind == "doe":
            psf, tile = op.psf.detach().double(), op.tile.detach().double()
            psf_sum = max(float(psf[c].sum()) for c in range(psf.shape[0]))
            code = max(float(sum(tile[c, i, j] ** 2 for c in range(tile.shape[0])))
                       for i in range(tile.shape[1]) for j in range(tile.shape[2]))
            assert op.lipschitz == pytest.approx(psf_sum**2 * code, rel=1e-9)
        if kind == "dd_cassi":
            assert op.lipschitz == pytest.approx(cam.scale**2 * len(cam.bands), rel=1e-12)
            assert sq >= 0.99 * op.lipschitz


def test_doe_snapshot_draws_height_noise_once_and_nominal_has_none():
    cam = camera("doe", "camera.doe.sigma_height_nm=20")
    a = cam.snapshot(torch.Generator().manual_seed(3)).psf
    b = cam.snapshot(torch.Generator().manual_seed(3)).psf
    assert torch.equal(a, b)
    nominal = cam.snapshot(nominal=True).psf
    cam.optics.doe.sigma_height_m = 0.0
    assert torch.allclose(nominal, cam.psf())
    assert not torch.allclose(a, nominal)
    assert cam.optics.doe.sigma_height_m == 0.0


def test_phase_pad_aligns_cells_with_the_sensor_grid():
    x = torch.arange(1 * 1 * 7 * 8, dtype=torch.float32).reshape(1, 1, 7, 8)
    p, (top, left) = phase_pad(x, 3, (4, 5))
    assert (top, left) == (1, 2) and p.shape[-2] % 3 == 0 and p.shape[-1] % 3 == 0
    assert torch.equal(p[..., top : top + 7, left : left + 8], x)


# ------------------------------------------------------------------------------------------------
# Network contract
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", CAMERA_KINDS)
@pytest.mark.parametrize("bands_step", [50.0, 100.0])  # 7 and 4 bands
@pytest.mark.parametrize("hw", [(12, 18), (17, 23)])  # 17, 23: not multiples of the CFA period (SD-CASSI: wider than D = 12)
def test_shape_contract(kind, bands_step, hw):
    cam = camera(kind, f"bands.step_nm={bands_step}")
    for name, net in networks(cam).items():
        y = torch.rand(2, 1, *hw, dtype=torch.float64)  # any input dtype: float32 out
        out = net(y, cam)
        assert out.dtype == torch.float32, name
        assert out.shape == (2, len(cam.bands), *cam.snapshot().scene_size(hw)), name
        assert torch.isfinite(out).all(), name


@pytest.mark.parametrize("settings", [MOSAIC, MOSAIC_DETAIL, MOSAIC_MID,
                                      dataclasses.replace(MOSAIC, factor=6, mid_features=4)])
def test_untrained_mosaic_net_returns_the_demosaic(settings):
    from hsicam.models.demosaic import demosaic

    cam = camera("doe")
    net = build_mosaic(settings, cam)
    y = torch.rand(1, 1, 15, 20)
    with torch.no_grad():
        assert torch.allclose(net(y, cam), demosaic(y, cam.sensor_code(15, 20), 3), atol=1e-6)


@pytest.mark.parametrize("name", ["mosaic", "mosaic-detail", "mosaic-mid", "unrolled", "unrolled-mosaic"])
def test_overfits_one_batch(name):
    cam = camera("doe", "camera.boundary=same", "camera.cfa.init=bandpass")
    wide = MosaicConfig(features=32, blocks=1, head_features=8, head_layers=2)
    net = {"mosaic": lambda: build_mosaic(wide, cam),
           "mosaic-detail": lambda: build_mosaic(dataclasses.replace(wide, detail_features=4), cam),
           "mosaic-mid": lambda: build_mosaic(dataclasses.replace(wide, detail_features=4, factor=6, mid_features=8,
                                                                  mid_blocks=1), cam),
           "unrolled": lambda: build_unrolled(UnrolledConfig(stages=2, prior_features=32, prior_blocks=1, prior_scale=2), cam),
           "unrolled-mosaic": lambda: build_unrolled(UnrolledConfig(stages=1, init="mosaic", prior_features=32, prior_blocks=1,
                                                                      prior_scale=2, mosaic=wide), cam)}[name]()
    g = torch.Generator().manual_seed(0)
    abundance = torch.nn.functional.interpolate(torch.rand(2, 2, 4, 4, generator=g), size=(18, 18), mode="bilinear",
                                                align_corners=False)
    truth = torch.einsum("bkhw,kc->bchw", abundance, torch.rand(2, len(cam.bands), generator=g))  # two endmembers
    with torch.no_grad():
        op = cam.snapshot(nominal=True)  # frozen optics: compute the PSF once
        sensor = op.A(truth)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = torch.nn.functional.l1_loss(net(sensor, op), truth)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], (name, losses[0], losses[-1])


@pytest.mark.parametrize("kind", ["doe", "dd_cassi"])
@pytest.mark.parametrize("bright", [0, 5])
def test_tiled_equals_whole_with_the_declared_context(kind, bright):
    cam = camera(kind)
    small = UnrolledConfig(stages=1, prior_features=8, prior_blocks=1, prior_scale=2, brightness_window=bright)
    nets = {"unrolled": build_unrolled(small, cam)}
    if kind == "dd_cassi":
        nets["rdn-backprojection"] = rdn_backprojection(cam)
    if kind == "doe":
        nets["mosaic"] = build_mosaic(dataclasses.replace(MOSAIC, brightness_window=bright), cam)
        nets["mosaic-detail"] = build_mosaic(dataclasses.replace(MOSAIC_DETAIL, brightness_window=bright), cam)
        nets["mosaic-mid"] = build_mosaic(dataclasses.replace(MOSAIC_MID, brightness_window=bright), cam)
    y = torch.rand(1, 1, 80, 74)
    op = cam.snapshot(nominal=True)
    for name, net in nets.items():
        randomise(net).eval()
        ctx = net.context_px
        assert 0 < ctx < 40, (name, ctx)  # the test must cut real tiles
        with torch.no_grad():
            whole = net(y, op)
        run = lambda s, origin=(0, 0): net(s, op, origin)  # noqa: E731
        tiled = reconstruct_tiled(run, y, tile_px=24, halo_px=ctx)
        assert torch.allclose(tiled, whole, atol=1e-5), (name, float((tiled - whole).abs().max()))
        short = reconstruct_tiled(run, y, tile_px=24, halo_px=2)
        assert not torch.allclose(short, whole, atol=1e-5), name  # the halo matters: the test can fail


@pytest.mark.parametrize("detail", [0, 3])
def test_an_untrained_half_resolution_stage_adds_nothing_to_a_trained_net(detail):
    """The stage starts at zero (its tail and its detail output): added to a trained net (every
    other parameter random), the output is that net's, bit for bit in float64."""
    cam = camera("doe")
    plain = dataclasses.replace(MOSAIC, factor=6, detail_features=detail)
    base = randomise(build_mosaic(plain, cam), 0.3).double().eval()
    staged = build_mosaic(dataclasses.replace(plain, mid_features=4, mid_blocks=1), cam).double().eval()
    missing, unexpected = staged.load_state_dict(base.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("mid_") for k in missing)
    y, op = torch.rand(1, 1, 25, 31, dtype=torch.float64), cam.snapshot(nominal=True)
    with torch.no_grad():
        torch.testing.assert_close(staged(y, op), base(y, op), rtol=0, atol=0)
        for name, p in staged.named_parameters():  # a stage that starts non-zero changes it: the test can fail
            if name.startswith(("mid_tail", "mid_detail")):
                p.add_(0.1)
        assert not torch.allclose(staged(y, op), base(y, op))


@pytest.mark.parametrize("mid", [dict(mid_features=-4), dict(mid_features=4, mid_blocks=-1)])
def test_mosaic_net_built_directly_refuses_negative_stage_sizes(mid):
    with pytest.raises(ValueError, match="mid_features and mid_blocks must be >= 0"):
        MosaicNet(3, 6, features=8, blocks=1, **mid)


@pytest.mark.parametrize("mid_blocks", [0, 1, 2])
def test_the_half_resolution_stage_reach_is_in_the_declared_context(mid_blocks):
    """The gradient of the output over one cell reaches exactly as far into the sensor image as
    ``context_px`` says, and further than the same net's context without the stage's term, so
    tiles cut with a halo that left the stage out would differ from the whole image."""
    cam = camera("doe")
    net = randomise(build_mosaic(dataclasses.replace(MOSAIC_MID, mid_blocks=mid_blocks), cam), 0.3).double().eval()
    ctx, size = net.context_px, 2 * net.context_px + 18
    y = torch.rand(1, 1, size, size, dtype=torch.float64, requires_grad=True)
    op = cam.snapshot(nominal=True)
    reach = 0
    rows = cols = torch.arange(size)
    for i in range(ctx + 6, ctx + 12):  # six consecutive rows and columns: every phase of the factor 6
        for j in range(ctx + 6, ctx + 12):
            (grad,) = torch.autograd.grad(net(y, op)[0, :, i, j].sum(), y)
            hit = grad[0, 0].abs() > 0
            dist = torch.maximum((rows[:, None] - i).abs(), (cols[None, :] - j).abs())
            reach = max(reach, int(dist[hit].max()))
    stage = 2 * (1 + 2 * mid_blocks)
    assert ctx - stage < reach <= ctx, (reach, ctx, stage)


@pytest.mark.parametrize("kind", ["doe", "dd_cassi"])
def test_brightness_normalised_networks_are_scale_equivariant(kind):
    """With b = box(g) + ε, ε → 0: net(c·y) = c·net(y) for any c > 0; without it the trained
    (randomised) network is not (the test can fail)."""
    cam = camera(kind)
    op = cam.snapshot(nominal=True)
    y = torch.rand(1, 1, 30, 28) + 0.1
    for bright in (5, 0):
        mos = dataclasses.replace(MOSAIC, brightness_window=bright, brightness_eps=1e-12)
        nets = {"unrolled": build_unrolled(dataclasses.replace(UNROLLED, brightness_window=bright,
                                                               brightness_eps=1e-12), cam)}
        if kind == "doe":
            nets["mosaic"] = build_mosaic(mos, cam)
            nets["mosaic-detail"] = build_mosaic(dataclasses.replace(mos, detail_features=3), cam)
            nets["mosaic-mid"] = build_mosaic(dataclasses.replace(mos, detail_features=3, factor=6, mid_features=4), cam)
            nets["unrolled-mosaic"] = build_unrolled(UnrolledConfig(stages=1, init="mosaic", prior_features=8,
                                                                    prior_blocks=1, prior_scale=2, mosaic=mos,
                                                                    brightness_window=bright, brightness_eps=1e-12), cam)
        for name, net in nets.items():
            randomise(net, 0.3).eval()
            with torch.no_grad():
                a, b = net(0.01 * y, op), 0.01 * net(y, op)
            same = torch.allclose(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))
            assert same == bool(bright), (name, bright, float((a - b).abs().max()))


@pytest.mark.parametrize("kind", CAMERA_KINDS)
def test_data_step_decreases_the_residual(kind):
    """Identity prior (the untrained priors are exactly zero): each stage lowers ‖A x − y‖."""
    cam = camera(kind).double()
    net = build_unrolled(UnrolledConfig(stages=4, init="backprojection"), cam).double()
    op = cam.snapshot()
    g = torch.Generator().manual_seed(0)
    hw = (20, 24)
    truth = torch.rand(1, len(cam.bands), *op.scene_size(hw), generator=g, dtype=torch.float64)
    y = op.A(truth)
    with torch.no_grad():
        x = torch.zeros_like(truth)  # (the CASSI back-projection already fits y exactly)
        alphas = net.step_sizes(op.lipschitz)
        res = [float((op.A(x) - y).norm())]
        for k in range(net.stages):
            x = net.data_step(x, y, op, alphas[k])
            assert float(net._prior(k)(x).abs().max()) == 0.0
            res.append(float((op.A(x) - y).norm()))
    assert all(b < a for a, b in zip(res, res[1:])), res


def _dense_operator(op, hw: tuple[int, int]) -> torch.Tensor:
    """Matrix (h·w, C·H'·W') of the snapshot's A on sensor windows of ``hw`` at origin (0, 0), one
    column per unit-vector cube (float64)."""
    c = len(op.bands)
    sh, sw = op.scene_size(hw)
    n = c * sh * sw
    eye = torch.eye(n, dtype=torch.float64).reshape(n, c, sh, sw)
    with torch.no_grad():
        return op.A(eye).reshape(n, -1).T.contiguous()


def _softplus(t: float) -> float:
    return math.log1p(math.exp(t))


@pytest.mark.parametrize("kind", CAMERA_KINDS)
def test_gradient_step_size_is_softplus_theta_over_l_and_one_step_is_the_dense_gradient_step(kind):
    """α_k = softplus(θ_k) / L (α_k = model.unrolled.step_init / L before training), and a data step
    is x − α Aᵀ(A x − y) with A a dense matrix built from unit vectors (Aᵀ its transpose); the
    untrained one-stage network (zero prior, back-projection init Aᵀy ⊘ AᵀA𝟙) is exactly that step."""
    cam = camera(kind).double()
    step_init = 0.7
    net = build_unrolled(UnrolledConfig(stages=2, init="backprojection", step_init=step_init, prior_features=4,
                                        prior_blocks=1, prior_scale=1), cam).double()
    lip = 3.25
    torch.testing.assert_close(net.step_sizes(lip).detach(), torch.full((2,), step_init / lip, dtype=torch.float64),
                               rtol=1e-6, atol=0)  # θ was set in float32
    with torch.no_grad():
        net.step_logits.copy_(torch.tensor([-0.4, 1.3], dtype=torch.float64))
    want = torch.tensor([_softplus(-0.4) / lip, _softplus(1.3) / lip], dtype=torch.float64)
    torch.testing.assert_close(net.step_sizes(lip).detach(), want, rtol=1e-12, atol=0)

    op = cam.snapshot(nominal=True)
    hw = (6, 18) if kind == "sd_cassi" else (6, 7)  # SD-CASSI: the scene is D = 12 px narrower
    a = _dense_operator(op, hw)
    g = torch.Generator().manual_seed(2)
    scene_hw = op.scene_size(hw)
    x = torch.rand(1, len(cam.bands), *scene_hw, generator=g, dtype=torch.float64)
    y = torch.rand(1, 1, *hw, generator=g, dtype=torch.float64)
    alpha = 0.3 / op.lipschitz
    with torch.no_grad():
        got = net.data_step(x, y, op, torch.tensor(alpha, dtype=torch.float64))
    xv, yv = x.reshape(-1), y.reshape(-1)
    torch.testing.assert_close(got.reshape(-1), xv - alpha * (a.T @ (a @ xv - yv)), rtol=1e-10, atol=1e-12)

    one = build_unrolled(UnrolledConfig(stages=1, init="backprojection", step_init=step_init, prior_features=4,
                                        prior_blocks=1, prior_scale=1), cam).double()
    lip = op.lipschitz
    x0 = (a.T @ yv) / (a.T @ (a @ torch.ones(a.shape[1], dtype=torch.float64))).clamp_min(1e-6 * lip)
    x1 = x0 - (step_init / lip) * (a.T @ (a @ x0 - yv))
    with torch.no_grad():
        out = one(y, op)
    torch.testing.assert_close(out.reshape(-1), x1, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("kind", ["dd_cassi", "sd_cassi"])
def test_gap_step_makes_cassi_data_consistent(kind):
    """With α = 1 a GAP step solves A x = y exactly (ΦΦᵀ is diagonal), and tiles still match."""
    cam = camera(kind).double()
    net = build_unrolled(UnrolledConfig(stages=1, step="gap", prior_features=8, prior_blocks=1, prior_scale=2), cam).double()
    op = cam.snapshot()
    truth = torch.rand(1, len(cam.bands), *op.scene_size((20, 30)), dtype=torch.float64)
    y = op.A(truth)
    with torch.no_grad():
        x = net.data_step(torch.zeros_like(truth), y, op, net.step_sizes(op.lipschitz)[0])
    covered = op.gram_diagonal(y) > 0
    assert torch.allclose(op.A(x)[covered], y[covered], atol=1e-10)
    if kind == "dd_cassi":
        randomise(net).eval()
        y = torch.rand(1, 1, 60, 52, dtype=torch.float64)
        run = lambda s, origin=(0, 0): net(s, op, origin)  # noqa: E731
        with torch.no_grad():
            assert torch.allclose(reconstruct_tiled(run, y, tile_px=16, halo_px=net.context_px), net(y, op), atol=1e-5)


def test_gradients_reach_the_doe_and_cfa_through_the_stages():
    cam = camera("doe", "camera.boundary=same")
    net = randomise(build_unrolled(UnrolledConfig(stages=2, init="demosaic", prior_features=8, prior_blocks=1,
                                                    prior_scale=2), cam))
    truth = torch.rand(1, len(cam.bands), 16, 16)
    with torch.no_grad():
        sensor = cam.A(truth)  # the measurement carries no gradient: only the stages do
    loss = torch.nn.functional.l1_loss(net(sensor, cam), truth)
    loss.backward()
    h, w = cam.optics.doe.height_m.grad, cam.cfa.weights.grad
    assert h is not None and torch.isfinite(h).all() and h.abs().sum() > 0
    assert w is not None and torch.isfinite(w).all() and w.abs().sum() > 0
    assert net.step_logits.grad is not None and net.step_logits.grad.abs().sum() > 0


def test_the_optics_gradient_through_the_stages_is_the_losss_derivative():
    """Finite differences (float64) of a loss through the unrolled stages along a random direction of the CFA weights
    and of the DOE heights equal autograd's. The steps' α = softplus(θ)/L depend on the optics through the bound L;
    a snapshot kept L as a float, so the optics got the gradient of another function (CFA: the sign was wrong here)."""
    cam = camera("doe", "camera.boundary=same").double()
    net = randomise(build_unrolled(UnrolledConfig(stages=2, init="demosaic", prior_features=8, prior_blocks=1,
                                                  prior_scale=2), cam)).double()
    truth = torch.rand(1, len(cam.bands), 16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        sensor = cam.A(truth)

    def loss() -> torch.Tensor:
        return (net(sensor, cam.snapshot()) - truth).square().sum()

    for param in (cam.cfa.weights, cam.optics.doe.height_m):
        direction = torch.randn(param.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
        param.grad = None
        loss().backward()
        along = float((param.grad * direction).sum())
        eps = 1e-6 * float(param.detach().abs().max())
        with torch.no_grad():
            param.add_(eps * direction)
            up = float(loss())
            param.sub_(2 * eps * direction)
            down = float(loss())
            param.add_(eps * direction)
        assert along == pytest.approx((up - down) / (2 * eps), rel=1e-4, abs=1e-9)


@pytest.mark.parametrize("kwargs,match", [({"stages": 0}, "stages must be >= 1"), ({"step_init": -1.0}, "step_init"),
                                          ({"step_init": float("nan")}, "step_init"), ({"init": "mosaic"}, "front="),
                                          ({"init": "zeros"}, "init must be"), ({"step": "admm"}, "step must be")])
def test_an_unrolled_net_built_directly_refuses_what_its_config_refuses(kwargs, match):
    """Built from Python, stages=0 returned x⁰ unchanged and step_init=-1 failed as 'math domain error'."""
    with pytest.raises(ValueError, match=match):
        UnrolledNet(7, (4, 4), **kwargs)


def test_a_snapshot_passed_in_is_used_as_is():
    cam = camera("doe", "camera.doe.sigma_height_nm=30")
    net = randomise(build_unrolled(UNROLLED, cam)).eval()
    op = cam.snapshot(torch.Generator().manual_seed(0))
    y = torch.rand(1, 1, 14, 14)
    with torch.no_grad():
        assert torch.equal(net(y, op), net(y, op))
        assert not torch.allclose(net(y, op), net(y, cam))  # the camera: the nominal (noise-free) PSF


# ------------------------------------------------------------------------------------------------
# Settings
# ------------------------------------------------------------------------------------------------
BAD = [
    ("mosaic", MosaicConfig(blocks=0), "model.mosaic.blocks"),
    ("mosaic", MosaicConfig(factor=4), "multiple of the CFA period"),
    ("mosaic", MosaicConfig(demosaic_window=4), "odd"),
    ("mosaic", MosaicConfig(brightness_window=6), "model.mosaic.brightness_window"),
    ("mosaic", MosaicConfig(head_layers=0, detail_features=8), "needs a head"),
    ("mosaic", MosaicConfig(detail_features=-1), "model.mosaic.detail_features"),
    ("mosaic", MosaicConfig(mid_features=8), "needs an even model.mosaic.factor"),  # the tiny CFA's period 3
    ("mosaic", MosaicConfig(factor=6, mid_features=-2), "model.mosaic.mid_features"),
    ("mosaic", MosaicConfig(factor=6, mid_features=8, mid_blocks=-1), "model.mosaic.mid_blocks"),
    ("mosaic", MosaicConfig(brightness_window=5, brightness_eps=0.0), "model.mosaic.brightness_eps"),
    ("unrolled", UnrolledConfig(step="gap"), "diagonal"),
]


@pytest.mark.parametrize("kind,settings,needle", BAD)
def test_bad_settings_are_one_config_error(kind, settings, needle):
    cam = camera("doe")
    build = build_mosaic if kind == "mosaic" else build_unrolled
    with pytest.raises(ConfigError, match=needle) as info:
        build(settings, cam)
    assert "\n" not in str(info.value)


#: Settings meaningless on any camera: refused as the section is made (at load), whichever model.kind is selected.
UNROLLED_BAD = [
    ({"brightness_window": -3}, r"^model.unrolled.brightness_window must be odd \(or 0 for off\), got -3$"),
    ({"stages": 0}, r"^model.unrolled.stages must be >= 1, got 0$"),
    ({"init": "zeros"}, r"^model.unrolled.init='zeros' is not one of auto, demosaic, backprojection, mosaic$"),
    ({"step_init": 0.0}, r"^model.unrolled.step_init must be > 0, got 0.0$"),
    ({"stage_kernel_px": 8}, r"^model.unrolled.stage_kernel_px must be odd \(or 0 for the full kernel\), got 8$"),
    ({"demosaic_window": 4}, r"^model.unrolled.demosaic_window must be odd \(or 0 for the CFA period\), got 4$"),
    ({"prior_scale": 0}, r"^model.unrolled.prior_scale must be >= 1, got 0$"),
    ({"step": "admm"}, r"^model.unrolled.step='admm' is not one of gradient, gap$"),
]


@pytest.mark.parametrize("settings,message", UNROLLED_BAD)
def test_bad_unrolled_settings_are_refused_as_the_section_is_made(settings, message):
    with pytest.raises(ConfigError, match=message):
        UnrolledConfig(**settings)
    (key, value), = settings.items()
    for kind in ("rdn", "mosaic"):  # not the selected network: still refused at load (was accepted silently)
        with pytest.raises(ConfigError, match=message):
            load_config("tiny", [f"model.kind={kind}", f"model.unrolled.{key}={value}"])


@pytest.mark.parametrize("section", ["model.mosaic", "model.unrolled.mosaic"])
@pytest.mark.parametrize("setting,message", [
    ("blocks=0", r"blocks must be >= 1, got 0"),
    ("features=-3", r"features must be >= 1, got -3"),
    ("demosaic_window=4", r"demosaic_window must be odd \(or 0 for the CFA period\), got 4"),
    ("brightness_window=6", r"brightness_window must be odd \(or 0 for off\), got 6"),
    ("brightness_eps=0", r"brightness_eps must be > 0, got 0.0"),
    ("mid_blocks=-1", r"mid_blocks must be >= 0, got -1"),
    ("detail_features=-1", r"detail_features must be >= 0, got -1"),
])
def test_bad_mosaic_settings_in_an_unselected_section_name_that_section(section, setting, message):
    """Both mosaic sections are checked at load whatever model.kind is, each error naming its own section
    (model.unrolled.mosaic is a MosaicConfig too: a message naming model.mosaic there would be wrong)."""
    for kind in ("rdn", "unrolled", "mosaic"):
        with pytest.raises(ConfigError, match="^" + section.replace(".", r"\.") + r"\." + message + "$"):
            load_config("tiny", [f"model.kind={kind}", f"{section}.{setting}"])


def test_mosaic_checks_that_need_no_camera_come_at_load():
    with pytest.raises(ConfigError, match=r"^model.unrolled.mosaic.mid_features=4 \(a half-resolution stage\) needs an "
                                          r"even model.unrolled.mosaic.factor, got 3;"):
        load_config("tiny", ["model.unrolled.mosaic.mid_features=4", "model.unrolled.mosaic.factor=3"])
    with pytest.raises(ConfigError, match=r"^model.mosaic.detail_features=2 needs a head: set model.mosaic.head_layers >= 1"):
        load_config("tiny", ["model.mosaic.detail_features=2", "model.mosaic.head_layers=0"])
    with pytest.raises(ConfigError, match=r"^model.mosaic.head_features must be >= 1"):
        load_config("tiny", ["model.mosaic.head_features=0"])
    cfg = load_config("tiny", ["model.mosaic.mid_features=4"])  # factor 0: the CFA period, known only with the camera
    with pytest.raises(ConfigError, match=r"^model.mosaic.mid_features=4 .*model.mosaic.factor=0 gives 3 on this camera"):
        build_mosaic(cfg.model.mosaic, camera("doe"))


@pytest.mark.parametrize("settings", [MosaicConfig(), UnrolledConfig(init="demosaic")])
def test_cfa_networks_on_cassi_are_one_config_error(settings):
    cam = camera("dd_cassi")
    build = build_mosaic if isinstance(settings, MosaicConfig) else build_unrolled
    with pytest.raises(ConfigError, match="colour filter array") as info:
        build(settings, cam)
    assert "\n" not in str(info.value)


def test_settings_are_plain_dataclasses_with_defaults():
    m, u = MosaicConfig(), UnrolledConfig()
    assert copy.deepcopy(u) == u and u.mosaic == m


# --------------------------------------------------------------------------------------------
# Through the registry: every model.kind builds from a config and keeps the system contract
# --------------------------------------------------------------------------------------------
from hsicam.models import CameraSystem, network_kinds  # noqa: E402


@pytest.mark.parametrize("kind", network_kinds())
def test_every_registered_network_through_the_system(kind):
    torch.manual_seed(0)
    model = CameraSystem.from_config(load_config("tiny", [f"model.kind={kind}"]))
    scene = torch.rand(2, len(model.bands), 40, 44)
    recon, sensor = model(scene, torch.Generator().manual_seed(0))
    assert recon.shape == model.target(scene).shape == (2, len(model.bands), *sensor.shape[-2:])
    assert torch.isfinite(recon).all() and model.context_px >= 0
    # the snapshot the camera passes on (one PSF per step) gives the same result as the camera
    with torch.no_grad():
        torch.testing.assert_close(model.reconstruct(sensor), recon.detach(), rtol=1e-5, atol=1e-6)


def test_unknown_network_kind_is_one_clear_error():
    """The error lists every registered kind (a network added as docs/architecture.md says joins the list)."""
    from hsicam.models.registry import network_kinds

    assert {"mosaic", "rdn", "unrolled"} <= set(network_kinds())
    with pytest.raises(ConfigError, match=f"model.kind='transformer' is unknown; choose one of {', '.join(network_kinds())}$"):
        CameraSystem.from_config(load_config("tiny", ["model.kind=transformer"]))


def test_relative_l1_loss_weighs_errors_by_the_local_brightness_of_the_truth():
    """train.relative_l1: L1 + w · mean(|x̂ − x| / (box₉(mean_c x) + ε)), box zero-padded (scipy reference)."""
    import numpy as np
    from scipy.ndimage import uniform_filter

    from hsicam.config import TrainConfig
    from hsicam.engine.tasks import system_loss

    g = torch.Generator().manual_seed(0)
    truth = torch.rand(2, 5, 14, 17, generator=g, dtype=torch.float64) * torch.linspace(0.001, 1, 17, dtype=torch.float64)
    recon = truth + 0.01 * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    plain = system_loss(recon, truth, TrainConfig())
    assert float(plain) == pytest.approx(float((recon - truth).abs().mean()), rel=1e-12)
    local = uniform_filter(truth.mean(dim=1).numpy(), size=(1, 9, 9), mode="constant")[:, None] + 0.02
    expect = float((recon - truth).abs().mean()) + 0.3 * float(np.mean(np.abs((recon - truth).numpy()) / local))
    got = system_loss(recon, truth, TrainConfig(relative_l1=0.3, relative_eps=0.02))
    assert float(got) == pytest.approx(expect, rel=1e-9)
    with pytest.raises(ConfigError, match="relative_l1"):
        TrainConfig(relative_l1=-1.0)


def test_ssim_and_spectral_angle_loss_terms_against_independent_references():
    """train.ssim_loss: + w · (1 − SSIM) with scikit-image's Gaussian SSIM (mean over bands and cubes);
    train.sam_loss: + w · mean angle (rad) over pixels whose truth is brighter than relative_eps
    (a per-pixel numpy loop); both differentiable, finite gradients at a perfect estimate."""
    import numpy as np
    from skimage.metrics import structural_similarity

    from hsicam.config import TrainConfig
    from hsicam.engine.tasks import system_loss

    g = torch.Generator().manual_seed(3)
    truth = torch.rand(2, 4, 16, 18, generator=g, dtype=torch.float64) * torch.linspace(0.0, 1, 18, dtype=torch.float64)
    recon = (truth + 0.05 * torch.randn(truth.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    l1 = float((recon.detach() - truth).abs().mean())
    ref_ssim = np.mean([structural_similarity(truth[b, c].numpy(), recon[b, c].detach().numpy(), gaussian_weights=True,
                                              sigma=1.5, use_sample_covariance=False, data_range=1.0)
                        for b in range(2) for c in range(4)])
    got = system_loss(recon, truth, TrainConfig(ssim_loss=0.5))
    assert float(got.detach()) == pytest.approx(l1 + 0.5 * (1 - ref_ssim), rel=1e-9)

    r, t = recon.detach().numpy(), truth.numpy()
    angles = [np.arccos(np.clip(np.dot(r[b, :, i, j], t[b, :, i, j]) /
                                (np.linalg.norm(r[b, :, i, j]) * np.linalg.norm(t[b, :, i, j])), -1, 1))
              for b in range(2) for i in range(16) for j in range(18) if t[b, :, i, j].mean() > 0.2]
    assert 0 < len(angles) < 2 * 16 * 18  # the threshold drops dark pixels
    got = system_loss(recon, truth, TrainConfig(sam_loss=2.0, relative_eps=0.2))
    assert float(got.detach()) == pytest.approx(l1 + 2.0 * np.mean(angles), rel=1e-6)
    got.backward()
    assert torch.isfinite(recon.grad).all()

    perfect = truth.clone().requires_grad_(True)
    loss = system_loss(perfect, truth, TrainConfig(ssim_loss=1.0, sam_loss=1.0))
    assert float(loss.detach()) == pytest.approx(0.0, abs=2e-3)  # acos is clamped at 1 − 1e-6
    loss.backward()
    assert torch.isfinite(perfect.grad).all()
    black = truth.clone()
    black[0, :, 3, 4] = 0.0  # a bright pixel reconstructed as a zero spectrum: an angle of 90°, a finite gradient
    black.requires_grad_(True)
    loss = system_loss(black, truth, TrainConfig(sam_loss=1.0, relative_eps=0.2))
    loss.backward()
    assert torch.isfinite(black.grad).all()
    with pytest.raises(ConfigError, match="sam_loss"):
        TrainConfig(sam_loss=-1.0)
    with pytest.raises(ConfigError, match="ssim_loss"):
        TrainConfig(ssim_loss=float("nan"))


def test_spectral_gradient_loss_term_against_a_numpy_reference():
    """train.spectral_grad_loss: + w · mean |(x̂[c+1] − x̂[c]) − (x[c+1] − x[c])| (a numpy loop over
    band steps); blind to an offset common to all bands, not to a ripple of the same L1 size."""
    import numpy as np

    from hsicam.config import TrainConfig
    from hsicam.engine.tasks import spectral_gradient_loss, system_loss

    g = torch.Generator().manual_seed(5)
    truth = torch.rand(2, 6, 8, 9, generator=g, dtype=torch.float64)
    recon = truth + 0.05 * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    r, t = recon.numpy(), truth.numpy()
    ref = np.mean([np.abs((r[:, c + 1] - r[:, c]) - (t[:, c + 1] - t[:, c])).mean() for c in range(5)])
    l1 = float((recon - truth).abs().mean())
    got = system_loss(recon, truth, TrainConfig(spectral_grad_loss=0.7))
    assert float(got) == pytest.approx(l1 + 0.7 * ref, rel=1e-9)

    offset = truth + 0.1  # the same spectral shape everywhere
    ripple = truth + 0.1 * torch.tensor([1.0, -1.0] * 3, dtype=torch.float64)[None, :, None, None]
    assert float(spectral_gradient_loss(offset, truth)) == pytest.approx(0.0, abs=1e-12)
    assert float(spectral_gradient_loss(ripple, truth)) == pytest.approx(0.2, rel=1e-9)
    assert float(spectral_gradient_loss(truth[:, :1], truth[:, :1] + 0.1)) == 0.0  # no band step, no term (not NaN)
    with pytest.raises(ConfigError, match="spectral_grad_loss"):
        TrainConfig(spectral_grad_loss=-0.5)


def test_tent_demosaic_is_the_weighted_bilinear_msfa_demosaic():
    """demosaic(kernel="tent") = Σ w(p−q) κ_c(q) g(q) / Σ w(p−q) κ_c(q) with w the outer product of
    (1, 2, …, m, …, 2, 1) (a numpy loop, zeros outside); with one-hot filters of period m and
    w = 2m − 1 it interpolates each filter's samples bilinearly, so a cube whose bands are linear
    in x and y comes back exactly away from the border, where the odd box over an even period
    does not (the test can fail)."""
    import numpy as np

    from hsicam.models.demosaic import demosaic

    m, h, w = 4, 17, 19
    c = m * m
    code = torch.zeros(c, h, w, dtype=torch.float64)
    for i in range(h):
        for j in range(w):
            code[(i % m) * m + j % m, i, j] = 1.0  # one filter per pixel, period m
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    g = torch.Generator().manual_seed(0)
    a, b, d = (torch.rand(c, 1, 1, generator=g, dtype=torch.float64) for _ in range(3))
    cube = a + 0.05 * b * yy + 0.03 * d * xx  # (C, H, W), each band linear in position
    sensor = (code * cube).sum(0)[None, None]

    got = demosaic(sensor, code, 2 * m - 1, "tent")
    tri = np.array([1, 2, 3, 4, 3, 2, 1], dtype=np.float64)
    wts, r = np.outer(tri, tri), m - 1
    k = np.pad(code.numpy(), ((0, 0), (r, r), (r, r)))  # zeros outside the image
    s = np.pad(sensor[0, 0].numpy(), r)
    ref = np.zeros((c, h, w))
    for i in range(h):  # every pixel, by the definition
        for j in range(w):
            kk, ss = k[:, i : i + 2 * r + 1, j : j + 2 * r + 1], s[i : i + 2 * r + 1, j : j + 2 * r + 1]
            ref[:, i, j] = (wts * kk * ss).sum(axis=(1, 2)) / (wts * kk).sum(axis=(1, 2))
    np.testing.assert_allclose(got[0].numpy(), ref, rtol=1e-12)

    inner = (slice(None), slice(None), slice(r, h - r), slice(r, w - r))
    torch.testing.assert_close(got[inner], cube[None][inner], rtol=0, atol=1e-12)
    box = demosaic(sensor, code, m + 1, "box")
    assert float((box[inner] - cube[None][inner]).abs().max()) > 1e-3
    with pytest.raises(ValueError, match="tent"):
        demosaic(sensor, code, 7, "gauss")


@pytest.mark.parametrize("origin", [(0, 0), (1, 2)])
def test_box_demosaic_of_an_even_cfa_period_is_the_5px_box_average(origin):
    """demosaic(kernel="box") = Σ_box κ_c g / Σ_box κ_c over a w×w box (zeros outside the image), by
    a numpy loop with κ_c = ReLU(weights) normalised over bands, tiled from the sensor's pixel (0, 0).
    The default box of a CFA of even period m is m + 1 px (odd: centred), of odd period m itself:
    the period-4 tiny camera's box demosaic and the unrolled network's demosaic start use 5×5."""
    import numpy as np

    from hsicam.models.demosaic import demosaic, demosaic_window, skip_window

    assert (skip_window(4), skip_window(9), skip_window(3), skip_window(2), skip_window(1)) == (5, 9, 3, 3, 1)
    cam = camera("doe", "camera.cfa.period=4").double()
    assert cam.code_period == 4 and demosaic_window(cam) == 5
    net = build_unrolled(UnrolledConfig(stages=1, init="demosaic", prior_features=4, prior_blocks=1, prior_scale=2),
                         cam).double()
    assert net.demosaic_window == 5

    h, w, win = 13, 15, 5
    t = np.maximum(cam.cfa.weights.detach().double().numpy(), 0.0)
    t = t / t.sum(axis=0, keepdims=True)
    kappa = np.stack([[[t[c, (origin[0] + i) % 4, (origin[1] + j) % 4] for j in range(w)] for i in range(h)]
                      for c in range(t.shape[0])])
    g = torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    r = win // 2
    k = np.pad(kappa, ((0, 0), (r, r), (r, r)))  # zeros outside the image
    s = np.pad(g[0, 0].numpy(), r)
    ref = np.zeros(kappa.shape)
    for i in range(h):
        for j in range(w):
            kk, ss = k[:, i : i + win, j : j + win], s[i : i + win, j : j + win]
            ref[:, i, j] = (kk * ss).sum(axis=(1, 2)) / kk.sum(axis=(1, 2))

    got = demosaic(g, torch.from_numpy(kappa), demosaic_window(cam), "box")
    np.testing.assert_allclose(got[0].numpy(), ref, rtol=1e-12, atol=1e-14)
    with torch.no_grad():
        start = net.initial(g, net.operator(cam), origin)
    np.testing.assert_allclose(start[0].numpy(), ref, rtol=1e-10, atol=1e-12)


def test_mosaic_net_with_the_tent_demosaic():
    """model.mosaic.demosaic_kernel=tent: the window defaults to 2·period − 1, the untrained
    network returns the tent demosaic, tiles equal the whole image; a bad kernel is one ConfigError."""
    from hsicam.models.demosaic import demosaic

    cam = camera("doe")
    settings = dataclasses.replace(MOSAIC_DETAIL, demosaic_kernel="tent")
    net = build_mosaic(settings, cam)
    assert net.demosaic_window == 2 * cam.code_period - 1
    y = torch.rand(1, 1, 80, 74)
    with torch.no_grad():
        torch.testing.assert_close(net(y, cam), demosaic(y, cam.sensor_code(80, 74), 5, "tent"), atol=1e-6, rtol=0)
    op = cam.snapshot(nominal=True)
    randomise(net).eval()
    with torch.no_grad():
        whole = net(y, op)
    tiled = reconstruct_tiled(lambda s, origin=(0, 0): net(s, op, origin), y, tile_px=24, halo_px=net.context_px)
    assert torch.allclose(tiled, whole, atol=1e-5)
    # untrained, the output is the skip: tiles need exactly its reach, window // 2 (the test can fail)
    fresh = build_mosaic(dataclasses.replace(settings, brightness_window=0), cam).eval()
    run = lambda s, origin=(0, 0): fresh(s, op, origin)  # noqa: E731
    with torch.no_grad():
        whole = fresh(y, op)
        reach = fresh.demosaic_window // 2
        assert torch.allclose(reconstruct_tiled(run, y, tile_px=24, halo_px=reach), whole, atol=1e-6)
        assert not torch.allclose(reconstruct_tiled(run, y, tile_px=24, halo_px=reach - 1), whole, atol=1e-6)
    with pytest.raises(ConfigError, match="demosaic_kernel"):
        build_mosaic(dataclasses.replace(MOSAIC, demosaic_kernel="gauss"), cam)


def test_phase_trace_loss_term_against_a_loop_reference():
    """train.phase_loss: + w · mean over (b, c, p) of |ē_p − ē|, ē_p the error's mean over the pixels
    of phase p = (i mod m, j mod m) in the top-left m-multiple window (numpy loops); 0 for an error
    without an m-periodic part, and only the CFA camera's period makes it count."""
    import numpy as np

    from hsicam.config import TrainConfig
    from hsicam.engine.tasks import phase_trace_loss, system_loss

    g = torch.Generator().manual_seed(5)
    truth = torch.rand(2, 3, 13, 10, generator=g, dtype=torch.float64)
    recon = truth + 0.02 * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    e, m = (recon - truth).numpy(), 4
    ref = []
    for b in range(2):
        for c in range(3):
            win = e[b, c, :12, :8]
            means = np.array([[win[a::m, d::m].mean() for d in range(m)] for a in range(m)])
            ref.extend(np.abs(means - means.mean()).ravel())
    l1 = float((recon - truth).abs().mean())
    got = system_loss(recon, truth, TrainConfig(phase_loss=3.0), period=m)
    assert float(got) == pytest.approx(l1 + 3.0 * np.mean(ref), rel=1e-9)
    assert float(system_loss(recon, truth, TrainConfig(phase_loss=3.0))) == pytest.approx(l1, rel=1e-12)  # no CFA
    assert float(phase_trace_loss(torch.full((1, 2, 12, 8), 0.07, dtype=torch.float64), m)) == pytest.approx(0, abs=1e-15)
    column = 0.05 * (torch.arange(8) % m == 1).to(torch.float64).expand(1, 2, 12, 8)  # one phase column 0.05 too bright
    assert float(phase_trace_loss(column, m)) == pytest.approx((4 * 0.0375 + 12 * 0.0125) / 16, rel=1e-12)


def test_the_unrolled_front_ends_bad_setting_names_its_own_section(tiny_config):
    """``model.unrolled.mosaic.features=-3`` was refused as ``model.mosaic.features must be >= 1``, a key
    the user had not set; the front end's checks now name the section they read."""
    from hsicam.errors import ConfigError
    from hsicam.models import CameraSystem

    with pytest.raises(ConfigError, match=r"^model.unrolled.mosaic.features must be >= 1, got -3$"):
        CameraSystem.from_config(tiny_config("model.kind=unrolled", "model.unrolled.init=mosaic",
                                             "model.unrolled.mosaic.features=-3"))
    with pytest.raises(ConfigError, match=r"^model.mosaic.features must be >= 1, got -3$"):
        CameraSystem.from_config(tiny_config("model.kind=mosaic", "model.mosaic.features=-3"))


# --------------------------------------------------------------------------------------------
# Parameter counts: each kind's closed form (registered with its builder) is the built network's,
# and a network whose training does not fit the memory budget is refused before it is built
# --------------------------------------------------------------------------------------------
from hsicam.models import build_network  # noqa: E402
from hsicam.models import registry  # noqa: E402
from hsicam.models.registry import TRAINING_BYTES_PER_PARAMETER, network_parameters  # noqa: E402

#: The CFA of each preset's camera (its mosaic factors are multiples of the period), on the tiny optics.
PRESET_CFA = {"tiny": ("camera.cfa.period=3",), "paper": ("camera.cfa.period=9",),
              "paper-unrolled": ("camera.cfa.period=9",), "dd_cassi_rdn": ("camera.cfa.period=3",),
              "quick": ("camera.cfa.period=4", "camera.cfa.init=bandpass", "camera.cfa.layout=dispersed"),
              "standard": ("camera.cfa.period=4", "camera.cfa.init=bandpass", "camera.cfa.layout=dispersed")}


def _with_model(cfg, model):
    return dataclasses.replace(cfg, model=model)


def _count(net) -> int:
    return sum(p.numel() for p in net.parameters())


@pytest.mark.parametrize("kind", network_kinds())
@pytest.mark.parametrize("preset", sorted(PRESET_CFA))
def test_parameter_count_of_every_presets_model_section_is_the_built_networks(preset, kind):
    """The model sections of the shipped presets (each kind of each preset), on the tiny optics with the
    preset's CFA period: the registered closed form equals the built network's parameter count."""
    torch.manual_seed(0)
    cfg = load_config("tiny", list(PRESET_CFA[preset]))
    cfg = _with_model(cfg, dataclasses.replace(load_config(preset).model, kind=kind))
    cam = build_camera(cfg)
    net = build_network(cfg, cam)
    assert network_parameters(cfg, cam) == _count(net) > 0


VARIANTS = [
    ("doe", ["model.kind=rdn", "model.rdn.blocks=2", "model.rdn.layers_per_block=3", "model.rdn.growth=5"]),
    ("doe", ["model.kind=rdn", "model.rdn.demosaic_input=true", "model.rdn.features=6"]),
    ("sd_cassi", ["model.kind=rdn", "model.rdn.backprojection_input=true"]),
    ("dd_cassi", ["model.kind=rdn", "model.rdn.backprojection_input=true", "model.rdn.layers_per_block=1"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.features=8", "model.mosaic.blocks=2",
             "model.mosaic.head_layers=1"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.features=8", "model.mosaic.blocks=1", "model.mosaic.head_layers=0"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.features=8", "model.mosaic.blocks=1", "model.mosaic.head_layers=4",
             "model.mosaic.head_features=5", "model.mosaic.detail_features=3", "model.mosaic.factor=6",
             "model.mosaic.mid_features=4", "model.mosaic.mid_blocks=3"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.features=8", "model.mosaic.blocks=1", "model.mosaic.factor=6",
             "model.mosaic.mid_features=4", "model.mosaic.mid_blocks=0"]),
    ("doe", ["model.kind=unrolled", "model.unrolled.stages=3", "model.unrolled.prior_features=8",
             "model.unrolled.prior_blocks=1", "model.unrolled.prior_scale=2"]),
    ("doe", ["model.kind=unrolled", "model.unrolled.stages=3", "model.unrolled.share_weights=true",
             "model.unrolled.prior_features=8", "model.unrolled.prior_blocks=2"]),
    ("doe", ["model.kind=unrolled", "model.unrolled.init=mosaic", "model.unrolled.stages=1",
             "model.unrolled.mosaic.features=8", "model.unrolled.mosaic.blocks=1", "model.unrolled.mosaic.detail_features=2"]),
    ("sd_cassi", ["model.kind=unrolled", "model.unrolled.init=backprojection", "model.unrolled.step=gap",
                  "model.unrolled.prior_scale=3"]),
]


@pytest.mark.parametrize("camera_kind,overrides", VARIANTS)
def test_parameter_count_of_variants_is_the_built_networks(camera_kind, overrides):
    """Every branch of the closed forms (inputs, head sizes, detail and half-resolution stages, shared
    priors, the unrolled front end), on the DOE camera and the CASSI cameras."""
    torch.manual_seed(0)
    cfg = load_config("tiny", [f"camera.kind={camera_kind}", *overrides])
    cam = build_camera(cfg)
    assert network_parameters(cfg, cam) == _count(build_network(cfg, cam))


def _budget_mb(nbytes: int) -> str:
    return repr(nbytes / 2**20)  # exact: a whole number of bytes over 2^20 is a float with 20 fraction bits


def test_a_network_is_refused_exactly_when_its_weights_or_its_training_exceed_the_budget(monkeypatch, tiny_config):
    """Building (what evaluate, reconstruct and export do) needs the weights, 4 bytes a parameter; training needs 16
    (weight, gradient, Adam's two moments), checked when the training task is made: a trained run stays readable on
    a machine that could not train it."""
    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    cfg = tiny_config("model.kind=rdn", "model.rdn.blocks=1", "model.rdn.features=8", "model.rdn.growth=4")
    cam = build_camera(cfg)
    n = network_parameters(cfg, cam)
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(4 * n))
    assert _count(build_network(cfg, cam)) == n  # the weights fit exactly
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(4 * n - 1))
    with pytest.raises(ConfigError, match=r"whose weights need .* \(4 bytes a parameter\), more than the memory budget "
                                          r".*HSICAM_MEMORY_BUDGET_MB"):
        build_network(cfg, cam)
    monkeypatch.delenv("HSICAM_MEMORY_BUDGET_MB")
    system = CameraSystem.from_config(cfg)
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(TRAINING_BYTES_PER_PARAMETER * n))
    SystemTask(cfg, system)  # training fits exactly
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(TRAINING_BYTES_PER_PARAMETER * n - 1))
    with pytest.raises(ConfigError, match=r"whose training needs .* \(16 bytes a parameter: weight, gradient, Adam's two "
                                          r"moments\)"):
        SystemTask(cfg, system)
    frozen = tiny_config("model.kind=rdn", "model.rdn.blocks=1", "model.rdn.features=8", "model.rdn.growth=4",
                         "train.freeze=[net]")
    SystemTask(frozen, system)  # a frozen network does not train


ABSURD = [
    ("doe", ["model.kind=rdn", "model.rdn.features=1000000000"], "model.rdn (",
     ["blocks=1", "features=1000000000", "growth=4", "layers_per_block=2"]),
    ("doe", ["model.kind=rdn", "model.rdn.blocks=1000000000"], "model.rdn (", ["blocks=1000000000", "features=8"]),
    ("doe", ["model.kind=rdn", "model.rdn.layers_per_block=1000000000"], "model.rdn (", ["layers_per_block=1000000000"]),
    ("doe", ["model.kind=rdn", "model.rdn.growth=1000000000"], "model.rdn (", ["growth=1000000000"]),
    ("doe", ["model.kind=unrolled", "model.unrolled.stages=1000000000"], "model.unrolled (",
     ["stages=1000000000", "share_weights=false", "prior_features=64", "prior_blocks=2", "prior_scale=4"]),
    ("doe", ["model.kind=unrolled", "model.unrolled.stages=1000000000", "model.unrolled.share_weights=true"],
     "model.unrolled (", ["stages=1000000000", "share_weights=true"]),  # one prior, but a billion step sizes
    ("sd_cassi", ["model.kind=unrolled", "model.unrolled.prior_scale=1000000"], "model.unrolled (", ["prior_scale=1000000"]),
    ("doe", ["model.kind=unrolled", "model.unrolled.init=mosaic", "model.unrolled.mosaic.blocks=1000000000"],
     "model.unrolled (", ["mosaic.blocks=1000000000", "mosaic.features=128"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.features=1000000000"], "model.mosaic (",
     ["features=1000000000", "blocks=10", "head_features=32"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.blocks=1000000000"], "model.mosaic (", ["blocks=1000000000"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.head_layers=1000000000"], "model.mosaic (", ["head_layers=1000000000"]),
    ("doe", ["model.kind=mosaic", "model.mosaic.factor=300000"], "model.mosaic (", ["factor=300000"]),
]


@pytest.mark.parametrize("camera_kind,overrides,section,settings", ABSURD)
def test_absurd_network_sizes_are_one_config_error_before_anything_is_built(monkeypatch, camera_kind, overrides,
                                                                            section, settings):
    """The fuzz's sizes allocated gigabytes (or looped for minutes) before failing: now the closed form
    refuses them and the builder never runs. The message names the section and the values of the keys
    that size the network, the estimate against the budget, and the override."""
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "1024")
    cfg = load_config("tiny", [f"camera.kind={camera_kind}", *overrides])
    cam = build_camera(cfg)

    def never(cfg, camera):
        raise AssertionError("the builder ran")

    entry = registry.NETWORKS[cfg.model.kind]
    monkeypatch.setitem(registry.NETWORKS, cfg.model.kind, dataclasses.replace(entry, build=never))
    with pytest.raises(ConfigError) as info:
        build_network(cfg, cam)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"model.kind={cfg.model.kind}: {section}")
    assert all(f"{k}, " in msg or f"{k})" in msg for k in settings), msg
    assert "more than the memory budget of 1 GiB; " in msg and "raise HSICAM_MEMORY_BUDGET_MB" in msg
    assert network_parameters(cfg, cam) * 4 > 2**30  # the weights alone: what building needs


def test_every_network_kind_registers_its_parameter_count():
    assert all(callable(registry.NETWORKS[k].parameters) and registry.NETWORKS[k].sizes for k in network_kinds())


def test_a_network_kind_cannot_be_registered_without_its_parameter_count():
    """``parameters`` is required (keyword-only, no default): a kind without it would be built unchecked
    by the memory budget. Refused when the decorator is made, before it registers anything."""
    kinds = dict(registry.NETWORKS)
    with pytest.raises(TypeError, match="parameters"):
        registry.register_network("unchecked")
    with pytest.raises(TypeError, match=r"register_network\('unchecked'\): parameters must be"):
        registry.register_network("unchecked", parameters=None, sizes=("features",))
    with pytest.raises(TypeError):
        registry.register_network("unchecked", lambda cfg, camera: 1)  # keyword-only
    # the keys that size it: the refusal of a network too large names them
    count = lambda cfg, camera: 1  # noqa: E731
    with pytest.raises(TypeError):
        registry.register_network("unchecked", parameters=count)
    for sizes in ((), [], "features"):
        with pytest.raises(TypeError, match=r"register_network\('unchecked'\): sizes must name"):
            registry.register_network("unchecked", parameters=count, sizes=sizes)
    assert registry.NETWORKS == kinds


def test_a_network_registered_outside_hsicam_is_built_and_checked(monkeypatch):
    """A user's own ``model.kind`` (registered in their script, examples/custom_network.py) has no section in
    ``ModelConfig``: building it through ``CameraSystem.from_config`` raised AttributeError ('ModelConfig' object
    has no attribute '<kind>') in the memory check. Now it is built, and a too-large one is refused in one line
    naming its ``sizes`` keys (they have no config values to give)."""
    from hsicam.models import CameraSystem

    class Plain(torch.nn.Module):
        def __init__(self, bands: int) -> None:
            super().__init__()
            self.conv = torch.nn.Conv2d(1, bands, 3, padding=1)

        def forward(self, sensor, camera, origin=(0, 0)):
            return self.conv(sensor)

        context_px = 1

    monkeypatch.setitem(registry.NETWORKS, "outside", registry.NetworkKind(
        lambda cfg, camera: Plain(len(camera.bands)), lambda cfg, camera: 10 * len(camera.bands), ("width",)))
    cfg = load_config("tiny", ["model.kind=outside"])
    system = CameraSystem.from_config(cfg)
    assert isinstance(system.net, Plain)
    assert sum(p.numel() for p in system.net.parameters()) == 10 * len(system.camera.bands)  # the declared count
    monkeypatch.setitem(registry.NETWORKS, "outside", registry.NetworkKind(
        lambda cfg, camera: Plain(1), lambda cfg, camera: 10**12, ("width",)))
    with pytest.raises(ConfigError) as info:
        build_network(cfg, system.camera)
    msg = str(info.value)
    assert msg.startswith("model.kind=outside: model.outside (width) is a network of 1e+12 parameters for 7 bands")
    assert "\n" not in msg and "more than the memory budget" in msg


def test_the_unrolled_refusal_names_its_front_end_only_with_init_mosaic(monkeypatch):
    cam = build_camera(load_config("tiny"))
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "1")  # after the camera (its PSF plan needs more)
    for init, named in (("mosaic", True), ("demosaic", False)):
        cfg = load_config("tiny", ["model.kind=unrolled", f"model.unrolled.init={init}"])
        with pytest.raises(ConfigError, match=r"^model.kind=unrolled: model.unrolled \(stages=2, ") as info:
            build_network(cfg, cam)
        assert ("mosaic.features=128" in str(info.value)) is named


# ------------------------------------------------------------------------------------------------
# Forward passes against hand-written references (float64, seeded random weights): the residual
# connections of the RDN's blocks and of the whole RDN (DESIGN §2), of the ResBlock that the mosaic
# net and the unrolled priors are made of, and which prior each unrolled stage applies.
# ------------------------------------------------------------------------------------------------
def _seeded_weights(net: torch.nn.Module, seed: int, std: float = 0.2) -> torch.nn.Module:
    """Every parameter drawn N(0, std²) (the zero-initialised output convs must not hide a path)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(std * torch.randn(p.shape, generator=g, dtype=torch.float64))
    return net


def _conv(x: torch.Tensor, conv: torch.nn.Conv2d) -> torch.Tensor:
    """A k×k convolution with the layer's own weights, zero padding k // 2 (same size), by F.conv2d."""
    k = conv.weight.shape[-1]
    return torch.nn.functional.conv2d(x, conv.weight, conv.bias, padding=k // 2)


def _rdb_reference(x: torch.Tensor, block) -> torch.Tensor:
    """RDB: F_c = ReLU(Conv3×3([x, F_1, …, F_{c−1}])), c = 1..C; out = x + Conv1×1([x, F_1, …, F_C])."""
    feats = [x]
    for layer in block.convs:
        conv = next(m for m in layer.modules() if isinstance(m, torch.nn.Conv2d))
        feats.append(torch.relu(_conv(torch.cat(feats, dim=1), conv)))
    return x + _conv(torch.cat(feats, dim=1), block.fusion)


def _rdn_reference(g: torch.Tensor, net) -> torch.Tensor:
    """t = Conv1×1(g); F₋₁ = Conv3×3(t); F₀ = Conv3×3(F₋₁); F_d = RDB_d(F_{d−1});
    F_GF = Conv3×3(Conv1×1([F_1, …, F_D])) + F₋₁; out = Conv3×3(F_GF) + t."""
    t = _conv(g, net.tentative)
    f_1 = _conv(t, net.sfe1)
    f = _conv(f_1, net.sfe2)
    outs = []
    for block in net.blocks:
        f = _rdb_reference(f, block)
        outs.append(f)
    fuse1, fuse3 = [m for m in net.global_fusion.modules() if isinstance(m, torch.nn.Conv2d)]
    assert fuse1.kernel_size == (1, 1) and fuse3.kernel_size == (3, 3)
    f_gf = _conv(_conv(torch.cat(outs, dim=1), fuse1), fuse3) + f_1
    return _conv(f_gf, net.output) + t


def test_residual_dense_block_and_rdn_forward_equal_a_hand_written_reference():
    """One RDB (local dense connections, 1×1 fusion, local residual) and a small RDN (shallow features,
    D blocks, global fusion, global residual, output + tentative) in float64 with random weights: the
    modules give the reference's numbers to rounding; without a residual they differ by O(1)."""
    from hsicam.models.rdn import RDN, ResidualDenseBlock

    x = torch.randn(2, 6, 9, 11, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    block = _seeded_weights(ResidualDenseBlock(6, 3, layers=3).double(), 11)
    with torch.no_grad():
        got, ref = block(x.clone()), _rdb_reference(x, block)
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
        assert (got - (ref - x)).abs().max() > 0.1  # the local residual is a visible part of the output
    net = _seeded_weights(RDN(bands=3, in_channels=2, blocks=2, features=6, growth=3, layers_per_block=2).double(), 12)
    g = torch.rand(2, 2, 10, 8, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    with torch.no_grad():
        got, ref = net(g.clone()), _rdn_reference(g, net)
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
        # the global residual F₋₁ moves the output (through the linear output conv) by far more than the
        # tolerance: the check above can fail
        f_1 = _conv(_conv(g, net.tentative), net.sfe1)
        assert torch.nn.functional.conv2d(f_1, net.output.weight, padding=1).abs().max() > 0.1


def test_resblock_forward_equals_a_hand_written_reference():
    """ResBlock (mosaic trunk, half-resolution stage, unrolled priors): x + Conv3×3(ReLU(Conv3×3(x))),
    float64, random weights; the residual x is a visible part of the output."""
    from hsicam.models.mosaic import ResBlock

    block = _seeded_weights(ResBlock(5).double(), 21)
    x = torch.randn(2, 5, 8, 13, generator=torch.Generator().manual_seed(22), dtype=torch.float64)
    ref = x + _conv(torch.relu(_conv(x, block.conv1)), block.conv2)
    with torch.no_grad():
        got = block(x.clone())
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    assert (got - (ref - x)).abs().max() > 0.5


def test_unrolled_stages_each_apply_their_own_prior_without_shared_weights():
    """share_weights=false: stage k applies priors[k]. The 2-stage net equals a hand-unrolled loop
    x⁰ = demosaic(y), x ← z + P_k(z), z = x − α_k Aᵀ(A x − y), α_k = softplus(θ_k) / L, and perturbing
    the second stage's prior changes the output (a net reusing priors[0] would not move)."""
    from hsicam.models.demosaic import demosaic

    cam = camera("doe").double()
    op = cam.snapshot(nominal=True)
    net = build_unrolled(dataclasses.replace(UNROLLED, stages=2, share_weights=False), cam).double().eval()
    assert len(net.priors) == 2
    randomise(net, 0.3)
    y = torch.rand(1, 1, 14, 17, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    with torch.no_grad():
        x = demosaic(y, op.sensor_code(14, 17).to(y), net.demosaic_window)
        for k in range(2):
            alpha = torch.nn.functional.softplus(net.step_logits[k]) / float(op.lipschitz)
            z = x - alpha * op.A_adjoint(op.A(x) - y)
            x = z + net.priors[k](z)
        got = net(y, op)
        torch.testing.assert_close(got, x, rtol=1e-10, atol=1e-12)
        # the loop with priors[0] twice is another cube: the comparison above can tell them apart
        x0 = demosaic(y, op.sensor_code(14, 17).to(y), net.demosaic_window)
        for k in range(2):
            alpha = torch.nn.functional.softplus(net.step_logits[k]) / float(op.lipschitz)
            z = x0 - alpha * op.A_adjoint(op.A(x0) - y)
            x0 = z + net.priors[0](z)
        assert (x0 - x).abs().max() > 1e-6
        net.priors[1].tail.weight.add_(0.1)
        assert (net(y, op) - got).abs().max() > 1e-6
