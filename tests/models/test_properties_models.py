"""Property-based tests (hypothesis) of the reconstruction networks' and solvers' pure functions on unusual
inputs: odd and prime sizes, 1-px images, one band or many, any CFA period and phase, tiles that do not divide
the image, batches whose items differ. Each invariant is checked against an independent reference: a brute-force
loop in numpy, the call on one batch item alone, the whole image, or a closed form. The least-squares linear
map (:class:`LinearDemosaicFit`, free and flat-field) against the ridge normal equations and the constrained optimum
by the null-space method, and the linear consistency step against its definition by loops.

Operators are random :class:`~hsicam.cameras.doe_camera.DOESnapshot` stacks (any band count, kernel and CFA
period, built in microseconds) and the tiny preset's CASSI cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from hsicam.cameras.doe_camera import DOESnapshot
from hsicam.engine.inference import reconstruct_tiled
from hsicam.models.consistency import (consistency_step, cut_psf, linear_consistency_step, reach_px,
                                       spectral_preconditioner, wiener_residual)
from hsicam.models.demosaic import LinearDemosaicFit, demosaic, phase_linear
from hsicam.models.mosaic import MosaicNet, phase_pad
from hsicam.models.rdn import RDNReconstructor
from hsicam.models.tv import chambolle_step, dual_divergence, forward_differences
from hsicam.models.unrolled import UnrolledNet
from hsicam.sensor import cfa_tile, tile_pattern
from hsicam.spectral import Bands
from property_settings import CORE_FEW, CORE_PROP, PIPELINE_PROPS, seeds

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PROPS = settings(max_examples=30, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
FEW = settings(PROPS, max_examples=15)

sizes = st.integers(1, 13)
origins = st.tuples(st.integers(-7, 11), st.integers(-7, 11))


def _bands(n: int) -> Bands:
    return Bands.uniform(400.0, 400.0 + 10.0 * (n - 1), 10.0)


def snapshot(bands: int, kernel: int, period: int, seed: int, dtype=torch.float64) -> DOESnapshot:
    """A random DOE operator: ``bands`` PSFs of ``kernel`` px (each summing to 1), a CFA tile of ``period`` with
    transmissions in [0.05, 1] (not normalised: any non-negative CFA)."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(bands, kernel, kernel, generator=g, dtype=torch.float64)
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True)
    tile = 0.05 + 0.95 * torch.rand(bands, period, period, generator=g, dtype=torch.float64)
    return DOESnapshot(_bands(bands),
                       psf.to(dtype), tile.to(dtype), period)


def randomise(net: torch.nn.Module, seed: int = 1, scale: float = 0.1) -> torch.nn.Module:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return net.eval()


# ------------------------------------------------------------------------------------------------
# phase_pad, demosaic, phase_linear: brute force
# ------------------------------------------------------------------------------------------------
@PROPS
@given(h=sizes, w=sizes, factor=st.integers(1, 6), origin=origins)
def test_phase_pad_aligns_cells_with_the_sensor_grid_for_any_size_and_origin(h, w, factor, origin):
    """The padded tensor's (0, 0) is a sensor pixel ≡ 0 (mod factor), its sides are multiples of factor, shorter
    than a cell more than needed, zeros outside x and x inside."""
    x = torch.rand(2, 3, h, w, dtype=torch.float64)
    p, (top, left) = phase_pad(x, factor, origin)
    assert (top, left) == (origin[0] % factor, origin[1] % factor)
    assert (origin[0] - top) % factor == 0 and (origin[1] - left) % factor == 0
    H, W = p.shape[-2:]
    assert H % factor == 0 and W % factor == 0 and top + h <= H < top + h + factor and left + w <= W < left + w + factor
    assert torch.equal(p[..., top : top + h, left : left + w], x)
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[top : top + h, left : left + w] = False
    assert (p[..., mask] == 0).all()


def _demosaic_reference(g: np.ndarray, code: np.ndarray, window: int, kernel: str) -> np.ndarray:
    """x̃_c(i, j) = Σ ω κ_c g / Σ ω κ_c over the window inside the image (ω: 1 or the tent's weights)."""
    c, h, w = code.shape
    r = window // 2
    out = np.zeros((c, h, w))
    for i in range(h):
        for j in range(w):
            for b in range(c):
                num = den = 0.0
                for u in range(-r, r + 1):
                    for v in range(-r, r + 1):
                        if 0 <= i + u < h and 0 <= j + v < w:
                            wt = 1.0 if kernel == "box" else (r + 1 - abs(u)) * (r + 1 - abs(v))
                            num += wt * code[b, i + u, j + v] * g[i + u, j + v]
                            den += wt * code[b, i + u, j + v]
                out[b, i, j] = num / den
    return out


@PROPS
@given(h=st.integers(1, 7), w=st.integers(1, 7), bands=st.integers(1, 5), window=st.sampled_from([1, 3, 5, 7, 9]),
       kernel=st.sampled_from(["box", "tent"]), seed=st.integers(0, 99))
def test_demosaic_is_the_weighted_local_average_for_any_size_and_window(h, w, bands, window, kernel, seed):
    """Windows wider than the image included (the box's zeros outside cancel in the ratio)."""
    g = torch.Generator().manual_seed(seed)
    sensor = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    code = 0.1 + torch.rand(bands, h, w, generator=g, dtype=torch.float64)
    got = demosaic(sensor, code, window, kernel)
    want = _demosaic_reference(sensor[0, 0].numpy(), code.numpy(), window, kernel)
    np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-10)


@PROPS
@given(h=st.integers(1, 9), w=st.integers(1, 9), m=st.integers(1, 4), bands=st.integers(1, 3),
       k=st.sampled_from([1, 3, 5]), origin=origins, seed=st.integers(0, 99))
def test_phase_linear_is_the_per_phase_filter_with_replicated_border(h, w, m, bands, k, origin, seed):
    g = torch.Generator().manual_seed(seed)
    sensor = torch.rand(2, 1, h, w, generator=g, dtype=torch.float64)
    weight = torch.randn(m * m, bands, k, k, generator=g, dtype=torch.float64)
    got = phase_linear(sensor, weight, origin).numpy()
    s, wt, r = sensor.numpy(), weight.numpy(), k // 2
    want = np.zeros((2, bands, h, w))
    for i in range(h):
        for j in range(w):
            p = ((origin[0] + i) % m) * m + (origin[1] + j) % m
            for u in range(-r, r + 1):
                for v in range(-r, r + 1):
                    ii, jj = min(max(i + u, 0), h - 1), min(max(j + v, 0), w - 1)
                    want[:, :, i, j] += wt[p, :, u + r, v + r] * s[:, 0, ii, jj][:, None]
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Networks: shapes, batch items, tiled = whole at any CFA origin
# ------------------------------------------------------------------------------------------------
def _check_network(net, op, bands: int, h: int, w: int, origin, tile: int, seed: int) -> None:
    """Shape (B, C, h, w) float32 and finite; item i of a batch of different items = the call on item i alone;
    tiles (any size, the declared halo) at the window's origin = the whole window."""
    g = torch.Generator().manual_seed(seed)
    y = torch.rand(3, 1, h, w, generator=g, dtype=torch.float64)
    y[1] *= 0.1  # items of different brightness and content
    with torch.no_grad():
        out = net(y, op, origin)
        assert out.shape == (3, bands, h, w) and out.dtype == torch.float32
        assert torch.isfinite(out).all()
        for i in range(3):
            alone = net(y[i : i + 1], op, origin)
            torch.testing.assert_close(out[i : i + 1], alone, rtol=1e-5, atol=1e-6)
        run = lambda s, origin_=(0, 0): net(s, op, (origin[0] + origin_[0], origin[1] + origin_[1]))  # noqa: E731

        def run_o(s, origin=(0, 0)):
            return run(s, origin)

        tiled = reconstruct_tiled(run_o, y[:1].float(), tile_px=tile, halo_px=net.context_px)
        torch.testing.assert_close(tiled, out[:1], rtol=1e-5, atol=1e-5)


@FEW
@given(bands=st.integers(1, 9), period=st.integers(1, 4), cells=st.integers(1, 2), h=st.integers(1, 23),
       w=st.integers(1, 23), origin=origins, tile=st.integers(1, 23), bright=st.sampled_from([0, 3]),
       detail=st.sampled_from([0, 2]), kernel=st.sampled_from(["box", "tent"]), seed=st.integers(0, 99))
def test_mosaic_net_shapes_batch_items_and_tiles(bands, period, cells, h, w, origin, tile, bright, detail, kernel, seed):
    op = snapshot(bands, 3, period, seed, torch.float32)
    factor = period * cells
    window = 2 * period - 1 if kernel == "tent" else period | 1
    net = randomise(MosaicNet(bands, factor, features=4, blocks=1, head_features=4, head_layers=2,
                              demosaic_window=window, brightness_window=bright, detail_features=detail,
                              demosaic_kernel=kernel), seed)
    _check_network(net, op, bands, h, w, origin, tile, seed)


@FEW
@given(bands=st.integers(1, 9), period=st.integers(1, 4), h=st.integers(2, 20), w=st.integers(2, 20),
       origin=origins, tile=st.integers(1, 20), mid_blocks=st.integers(0, 1), seed=st.integers(0, 99))
def test_mosaic_net_with_a_half_resolution_stage_shapes_batch_items_and_tiles(bands, period, h, w, origin, tile,
                                                                              mid_blocks, seed):
    op = snapshot(bands, 3, period, seed, torch.float32)
    factor = 2 * period
    net = randomise(MosaicNet(bands, factor, features=4, blocks=1, head_features=4, head_layers=1,
                              demosaic_window=period | 1, detail_features=2, mid_features=3, mid_blocks=mid_blocks),
                    seed)
    _check_network(net, op, bands, h, w, origin, tile, seed)


@FEW
@given(bands=st.integers(1, 9), period=st.integers(1, 4), kernel=st.sampled_from([1, 3, 5]), h=st.integers(1, 17),
       w=st.integers(1, 17), origin=origins, tile=st.integers(1, 17), scale=st.integers(1, 3),
       stages=st.integers(1, 2), init=st.sampled_from(["demosaic", "backprojection"]),
       bright=st.sampled_from([0, 3]), seed=st.integers(0, 99))
def test_unrolled_net_shapes_batch_items_and_tiles(bands, period, kernel, h, w, origin, tile, scale, stages, init,
                                                   bright, seed):
    op = snapshot(bands, kernel, period, seed, torch.float32)
    net = randomise(UnrolledNet(bands, op.reach_px, stages, init, prior_features=4, prior_blocks=1,
                                prior_scale=scale, demosaic_window=period | 1, brightness_window=bright), seed)
    _check_network(net, op, bands, h, w, origin, tile, seed)


@FEW
@given(bands=st.integers(1, 9), h=st.integers(1, 17), w=st.integers(1, 17), tile=st.integers(1, 17),
       demosaic_input=st.booleans(), seed=st.integers(0, 99))
def test_rdn_shapes_batch_items_and_tiles(bands, h, w, tile, demosaic_input, seed):
    op = snapshot(bands, 3, 3, seed, torch.float32)
    net = randomise(RDNReconstructor(bands, demosaic_input, 3, blocks=1, features=4, growth=2, layers_per_block=2),
                    seed)
    _check_network(net, op, bands, h, w, (0, 0), tile, seed)


# ------------------------------------------------------------------------------------------------
# Consistency steps
# ------------------------------------------------------------------------------------------------
@PROPS
@given(bands=st.integers(1, 6), kernel=st.sampled_from([1, 3, 5]), period=st.integers(1, 4), h=st.integers(1, 11),
       w=st.integers(1, 11), origin=origins, iterations=st.integers(1, 4), damping=st.sampled_from([1e-6, 0.02, 0.5]),
       prior=st.sampled_from([0.0, 2.0]), seed=st.integers(0, 99))
def test_steps_never_grow_the_weighted_residual_nor_the_error(bands, kernel, period, h, w, origin, iterations,
                                                               damping, prior, seed):
    """Noiseless data, the exact ``same`` operator, nothing extended: ‖y − A x‖_{D⁻¹} and ‖x − x*‖ (the S⁻¹-norm
    with the spectral prior S) never grow, D = A S Aᵀ 𝟙 + λ computed here from the definition."""
    op = snapshot(bands, kernel, period, seed)
    g = torch.Generator().manual_seed(seed + 1)
    truth = torch.rand(2, bands, h, w, generator=g, dtype=torch.float64)
    y = op.A(truth, origin)
    x = truth + 0.3 * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    lam = damping * op.lipschitz
    s = spectral_preconditioner(x, prior) if prior else (lambda v: v)
    d = op.A(s(op.A_adjoint(torch.ones_like(y), origin)), origin) + lam

    def s_inv_norm(e):
        if not prior:
            return float(e.square().sum())
        # S = α ŝŝᵀ + I: S⁻¹ = I − α/(1 + α‖ŝ‖²) ŝŝᵀ
        sh = x.clamp_min(0)
        sh = sh / sh.square().sum(1, keepdim=True).sqrt().clamp_min(torch.finfo(sh.dtype).tiny)
        n2 = sh.square().sum(1, keepdim=True)
        se = (sh * e).sum(1, keepdim=True)
        return float((e * e).sum() - (prior / (1 + prior * n2) * se * se).sum())

    res = [float(((y - op.A(x, origin)).square() / d).sum())]
    err = [s_inv_norm(x - truth)]
    for n in range(1, iterations + 1):  # n steps from x (the spectral prior follows the start's spectra)
        out = consistency_step(op, y, x, origin, damping=damping, iterations=n, psf_energy=1.0, extend=False,
                               spectral_prior=prior)
        res.append(float(((y - op.A(out, origin)).square() / d).sum()))
        err.append(s_inv_norm(out - truth))
    tol = 1e-9 * (res[0] + err[0] + 1e-30)
    assert all(b <= a + tol for a, b in zip(res, res[1:])), res
    assert all(b <= a + tol for a, b in zip(err, err[1:])), err


@PROPS
@given(bands=st.integers(1, 5), kernel=st.sampled_from([1, 3, 5, 7]), period=st.integers(1, 4),
       h=st.integers(1, 30), w=st.integers(1, 12), origin=origins, iterations=st.integers(1, 3),
       band_px=st.integers(1, 30), extend=st.sampled_from([True, False, "reflect"]),
       tv=st.sampled_from([0.0, 0.05]), prior=st.sampled_from([0.0, 1.0]), noisy=st.booleans(), seed=st.integers(0, 99))
def test_steps_in_bands_of_rows_equal_the_whole_window(bands, kernel, period, h, w, origin, iterations, band_px,
                                                       extend, tv, prior, noisy, seed):
    op = snapshot(bands, kernel, period, seed)
    g = torch.Generator().manual_seed(seed + 2)
    x0 = torch.rand(2, bands, h, w, generator=g, dtype=torch.float64)
    y = torch.rand(2, 1, h, w, generator=g, dtype=torch.float64)
    var = torch.full((1, 1, 1, 1), 0.01, dtype=torch.float64) if noisy else None
    kw = dict(damping=0.02, iterations=iterations, psf_energy=1.0, extend=extend, spectral_prior=prior,
              noise_variance=var, tv_weight=tv)
    with torch.no_grad():
        whole = consistency_step(op, y, x0, origin, **kw)
        banded = consistency_step(op, y, x0, origin, band_px=band_px, **kw)
        for i in range(2):  # batch item i = the call on item i alone
            alone = consistency_step(op, y[i : i + 1], x0[i : i + 1], origin, **kw)
            torch.testing.assert_close(whole[i : i + 1], alone, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(banded, whole, rtol=1e-10, atol=1e-12)


@FEW
@given(bands=st.integers(1, 4), kernel=st.sampled_from([3, 5]), period=st.integers(1, 4), h=st.integers(1, 40),
       w=st.integers(1, 40), origin=origins, iterations=st.integers(1, 2), tile=st.integers(1, 40),
       extend=st.sampled_from([True, False]), tv=st.sampled_from([0.0, 0.05]), seed=st.integers(0, 99))
def test_step_tiles_with_the_declared_reach_equal_the_whole_image(bands, kernel, period, h, w, origin, iterations, tile,
                                                                  extend, tv, seed):
    op = snapshot(bands, kernel, period, seed, torch.float32)
    g = torch.Generator().manual_seed(seed + 3)
    x0 = torch.rand(1, bands, h, w, generator=g)
    y = op.A(torch.rand(1, bands, h, w, generator=g), origin)
    kw = dict(damping=0.02, iterations=iterations, psf_energy=1.0, extend=extend, tv_weight=tv)
    with torch.no_grad():
        whole = consistency_step(op, y, x0, origin, **kw)

        def run(s, origin_=(0, 0)):
            ys, xs = origin_
            part = x0[..., ys : ys + s.shape[-2], xs : xs + s.shape[-1]]
            return consistency_step(op, s, part, (origin[0] + ys, origin[1] + xs), **kw)

        def run_o(s, origin=(0, 0)):
            return run(s, origin)

        tiled = reconstruct_tiled(run_o, y, tile_px=tile, halo_px=reach_px(op, iterations, 1.0, tv=tv > 0))
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)


@PROPS
@given(bands=st.integers(1, 5), kernel=st.sampled_from([1, 3, 5, 7, 9]), energy=st.floats(0.05, 1.0),
       seed=st.integers(0, 99))
def test_cut_psf_is_the_smallest_odd_kernel_keeping_the_light(bands, kernel, energy, seed):
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(bands, kernel, kernel, generator=g, dtype=torch.float64) ** 4  # spiky, off-centre light
    op = DOESnapshot(_bands(bands), psf, torch.ones(bands, 1, 1, dtype=torch.float64), 1)
    got = cut_psf(op, energy).kernel_px
    p = psf.numpy()
    c = kernel // 2

    def keeps(k):
        a = c - k // 2
        return all(p[b, a : a + k, a : a + k].sum() >= energy * p[b].sum() for b in range(bands))

    want = kernel if energy >= 1 else next(k for k in range(1, kernel + 1, 2) if k == kernel or keeps(k))
    assert got == want


@PROPS
@given(h=st.integers(1, 9), w=st.integers(1, 9), window=st.sampled_from([1, 3, 5]), scalar=st.booleans(),
       seed=st.integers(0, 99))
def test_wiener_residual_is_the_local_gain_by_brute_force(h, w, window, scalar, seed):
    g = torch.Generator().manual_seed(seed)
    r = torch.randn(2, 1, h, w, generator=g, dtype=torch.float64)
    var = (torch.full((1, 1, 1, 1), 0.5, dtype=torch.float64) if scalar
           else torch.rand(2, 1, h, w, generator=g, dtype=torch.float64) * (torch.rand(2, 1, h, w, generator=g) > 0.2))
    got = wiener_residual(r, var, window).numpy()
    rr, vv = r.numpy(), np.broadcast_to(var.numpy(), r.shape)
    q = window // 2
    want = np.zeros_like(rr)
    for b in range(2):
        for i in range(h):
            for j in range(w):
                sl = (b, 0, slice(max(i - q, 0), i + q + 1), slice(max(j - q, 0), j + q + 1))
                p = max((rr[sl] ** 2).mean() - vv[sl].mean(), 0.0)
                v = vv[b, 0, i, j]
                want[b, 0, i, j] = rr[b, 0, i, j] * (p / (p + v) if v > 0 else 1.0)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Solvers on tiny random CASSI problems
# ------------------------------------------------------------------------------------------------
_CASSI: dict = {}


def cassi(kind: str, bands_step: float):
    """The tiny preset's CASSI camera (float64), ``bands_step`` nm apart (7, 4 or 2 bands), built once."""
    key = (kind, bands_step)
    if key not in _CASSI:
        from hsicam.cameras import build_camera
        from hsicam.config import load_config

        _CASSI[key] = build_camera(load_config("tiny", overrides=[f"camera.kind={kind}",
                                                                  f"bands.step_nm={bands_step}"])).double()
    return _CASSI[key]


cassi_kinds = st.sampled_from(["dd_cassi", "sd_cassi"])
band_steps = st.sampled_from([50.0, 100.0, 300.0])


def _problem(cam, h: int, w: int, seed: int, batch: int = 2):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, len(cam.bands), h, w, generator=g, dtype=torch.float64)
    return x, cam.A(x)


@PROPS
@given(kind=cassi_kinds, step=band_steps, h=sizes, w=sizes, accelerate=st.booleans(), seed=st.integers(0, 99))
def test_gap_without_tv_is_the_projection_onto_the_measurement(kind, step, h, w, accelerate, seed):
    """One GAP iteration with λ = 0 from the minimum-norm start: A x = y exactly, batch item i = item i alone."""
    from hsicam.solvers import gap_tv

    cam = cassi(kind, step)
    _, y = _problem(cam, h, w, seed)
    x = gap_tv(cam, y, 1, 0.0, accelerate=accelerate)
    assert x.shape == (2, len(cam.bands), h, w)
    assert float((cam.A(x) - y).norm()) <= 1e-12 * max(float(y.norm()), 1.0)
    alone = torch.cat([gap_tv(cam, y[i : i + 1], 1, 0.0, accelerate=accelerate) for i in range(2)])
    torch.testing.assert_close(x, alone, rtol=0, atol=1e-14)


@FEW
@given(kind=cassi_kinds, step=band_steps, h=st.integers(6, 13), w=st.integers(6, 13), seed=st.integers(0, 99))
def test_gap_tv_lowers_the_residual_and_recovers_a_flat_cube(kind, step, h, w, seed):
    """The residual after 20 iterations is below the first one's; batch items are independent. A cube with one
    spectrum everywhere (TV 0: in the prior's model) is a fixed point from itself, and from the minimum-norm start
    its noiseless capture comes back closer than that start (not exactly: a 6 px, 7-band problem leaves a smooth
    ramp in the operator's null space that TV barely sees, 10 % off after 100 iterations)."""
    from hsicam.solvers import gap_tv

    cam = cassi(kind, step)
    x, y = _problem(cam, h, w, seed)
    out, info = gap_tv(cam, y, 20, 0.05, return_info=True)
    assert info.residual[-1] < info.residual[0]
    alone = torch.cat([gap_tv(cam, y[i : i + 1], 20, 0.05) for i in range(2)])
    torch.testing.assert_close(out, alone, rtol=0, atol=1e-12)
    flat = x[:1, :, :1, :1].expand(1, len(cam.bands), h, w).contiguous()
    yf = cam.A(flat)
    torch.testing.assert_close(gap_tv(cam, yf, 5, 0.01, x0=flat), flat, rtol=0, atol=1e-12)
    start = cam.A_adjoint(yf / cam.gram_diagonal(yf))
    rec = gap_tv(cam, yf, 30, 0.01)
    assert float((rec - flat).norm()) < float((start - flat).norm())


@FEW
@given(kind=cassi_kinds, step=band_steps, h=st.integers(3, 11), w=st.integers(3, 11), patch=st.integers(1, 3),
       data=st.data())
def test_desci_shapes_batch_items_and_residual(kind, step, h, w, patch, data):
    from hsicam.solvers import desci, desci_settings

    cam = cassi(kind, step)
    p = min(patch, h, w)
    s = desci_settings("fast", patch=p, step=data.draw(st.integers(1, p)), group=data.draw(st.integers(1, 30)),
                       search=data.draw(st.integers(0, 12)), sigmas=[0.1, 0.05], iterations=[2, 2], init_iterations=3,
                       match_components=data.draw(st.sampled_from([None, 1, 3])))
    _, y = _problem(cam, h, w, data.draw(st.integers(0, 99)))
    out, info = desci(cam, y, s, return_info=True)
    assert out.shape == (2, len(cam.bands), h, w) and torch.isfinite(out).all()
    assert info.residual[-1] < info.residual[0]
    alone = torch.cat([desci(cam, y[i : i + 1], s) for i in range(2)])
    torch.testing.assert_close(out, alone, rtol=0, atol=1e-12)


@FEW
@given(kind=cassi_kinds, step=band_steps, h=st.integers(2, 9), w=st.integers(2, 9), seed=st.integers(0, 99))
def test_choi_admm_shapes_and_batch_items(kind, step, h, w, seed):
    from hsicam.config import ChoiConfig
    from hsicam.models.priors import SpectralAutoencoder
    from hsicam.solvers import admm_prior

    cam = cassi(kind, step)
    torch.manual_seed(seed)
    prior = randomise(SpectralAutoencoder(len(cam.bands), 4, 4).double(), seed, 0.01)
    _, y = _problem(cam, h, w, seed)
    cfg = ChoiConfig(iterations=3, inner_steps=2, init_iterations=3)
    out = admm_prior(cam, y, prior, cfg)
    assert out.shape == (2, len(cam.bands), h, w) and torch.isfinite(out).all()
    alone = torch.cat([admm_prior(cam, y[i : i + 1], prior, cfg) for i in range(2)])
    torch.testing.assert_close(out, alone, rtol=0, atol=1e-12)


@PROPS
@given(h=sizes, w=sizes, bands=st.integers(1, 5), iterations=st.integers(0, 8), seed=st.integers(0, 99))
def test_tv_denoise_keeps_each_bands_mean_and_a_flat_image(h, w, bands, iterations, seed):
    """div p sums to 0 (it is −∇ᵀp): every band keeps its mean; a flat image is a fixed point; a weight per
    (item, band) equals the scalar call on that item and band."""
    from hsicam.solvers import tv_denoise

    g = torch.Generator().manual_seed(seed)
    f = torch.rand(2, bands, h, w, generator=g, dtype=torch.float64)
    weight = 0.01 + torch.rand(2, bands, 1, 1, generator=g, dtype=torch.float64)
    u = tv_denoise(f, weight, iterations)
    torch.testing.assert_close(u.mean(dim=(-2, -1)), f.mean(dim=(-2, -1)), rtol=0, atol=1e-12)
    flat = f[..., :1, :1].expand_as(f).contiguous()
    torch.testing.assert_close(tv_denoise(flat, weight, iterations), flat, rtol=0, atol=1e-14)
    for i in range(2):
        for c in range(bands):
            one = tv_denoise(f[i : i + 1, c : c + 1], float(weight[i, c]), iterations)
            torch.testing.assert_close(u[i : i + 1, c : c + 1], one, rtol=0, atol=1e-13)


@pytest.mark.parametrize("kind", ["dd_cassi", "sd_cassi"])
@pytest.mark.parametrize("hw", [(1, 9), (9, 1), (1, 1)])
def test_choi_admm_on_a_one_px_cube_is_one_input_error(kind, hw):
    """A cube 1 px high or wide: the prior's reflect padding cannot mirror it (torch raised a RuntimeError from
    deep inside the autoencoder); one InputError naming the size instead, as DeSCI's for an image below its patch."""
    from hsicam.config import ChoiConfig
    from hsicam.errors import InputError
    from hsicam.models.priors import SpectralAutoencoder
    from hsicam.solvers import admm_prior

    cam = cassi(kind, 100.0)
    y = torch.rand(1, 1, hw[0], hw[1] + (cam.span if kind == "sd_cassi" else 0), dtype=torch.float64)
    prior = SpectralAutoencoder(len(cam.bands), 4, 4).double()
    with pytest.raises(InputError, match=rf"^Choi: the cube \({hw[0]}×{hw[1]} px\) is smaller than 2×2 px"):
        admm_prior(cam, y, prior, ChoiConfig(iterations=1, init_iterations=1))


# ------------------------------------------------------------------------------------------------
# LinearDemosaicFit and the linear consistency step (moved from engine/test_properties_pipeline.py; their
# settings are those of PIPELINE_PROPS)
# ------------------------------------------------------------------------------------------------
def _patches(g: np.ndarray, k: int) -> np.ndarray:
    """(B, H, W, K²): the K×K window around every pixel of g (B, 1, H, W), the image extended by replication."""
    r = k // 2
    gp = np.pad(g[:, 0], ((0, 0), (r, r), (r, r)), mode="edge")
    b, h, w = g.shape[0], g.shape[2], g.shape[3]
    out = np.empty((b, h, w, k * k))
    for i in range(h):
        for j in range(w):
            out[:, i, j] = gp[:, i : i + k, j : j + k].reshape(b, -1)
    return out


def _phase(h: int, w: int, m: int, origin: tuple[int, int]) -> np.ndarray:
    return ((np.arange(h)[:, None] + origin[0]) % m) * m + (np.arange(w)[None, :] + origin[1]) % m


def _normal_equations(g, t, m, k, origin, ridge):
    """Per phase: X_qᵀX_q + reg I and X_qᵀT_q from the definition (reg = ridge × mean diagonal)."""
    x = _patches(g, k)
    ph = np.broadcast_to(_phase(g.shape[2], g.shape[3], m, origin), x.shape[:3])
    vals = t.transpose(0, 2, 3, 1)
    grams, cross = [], []
    for q in range(m * m):
        xs, ts = x[ph == q], vals[ph == q]
        gram = xs.T @ xs
        grams.append(gram + ridge * np.trace(gram) / (k * k) * np.eye(k * k))
        cross.append(xs.T @ ts)
    return grams, cross


# ------------------------------------------------------------------------------------------------
# LinearDemosaicFit: the least-squares filters
# ------------------------------------------------------------------------------------------------
@PIPELINE_PROPS
@given(m=st.integers(1, 3), k=st.sampled_from([1, 3, 5]), c=st.integers(1, 4), h=st.integers(1, 9),
       w=st.integers(1, 9), b=st.integers(1, 2), oy=st.integers(0, 5), ox=st.integers(0, 5), seed=st.integers(0, 999),
       scale=st.sampled_from([1e-6, 1.0, 1e4]))
def test_free_fit_is_the_ridge_least_squares_by_brute_force(m, k, c, h, w, b, oy, ox, seed, scale):
    """Per phase (w_q = (X_qᵀX_q + reg I)⁻¹ X_qᵀT_q, a phase without samples 0), for any image size (smaller
    than the window or the period too), origin, batch and brightness (the ridge is relative: scale-free)."""
    rng = np.random.default_rng(seed)
    g, t = rng.random((b, 1, h, w)) * scale, rng.random((b, c, h, w))
    fit = LinearDemosaicFit(m, c, k, ridge=1e-3)
    fit.add(torch.from_numpy(g), torch.from_numpy(t), (oy, ox))
    got = fit.solve().double().numpy()
    grams, cross = _normal_equations(g, t, m, k, (oy, ox), 1e-3)
    ref = np.stack([np.linalg.solve(gr, cr).T.reshape(c, k, k) if np.trace(gr) > 0 else np.zeros((c, k, k))
                    for gr, cr in zip(grams, cross)])
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-5 * np.abs(ref).max())


@PIPELINE_PROPS
@given(m=st.integers(1, 3), k=st.sampled_from([1, 3, 5]), c=st.integers(1, 3), h=st.integers(1, 9),
       w=st.integers(1, 9), b=st.integers(1, 2), oy=st.integers(0, 5), ox=st.integers(0, 5), seed=st.integers(0, 999),
       scale=st.sampled_from([1e-6, 1.0, 1e4]), ridge=st.sampled_from([1e-6, 1e-2]))
def test_flat_field_fit_is_the_constrained_optimum_by_the_null_space_method(m, k, c, h, w, b, oy, ox, seed, scale,
                                                                            ridge):
    """Under S_q w_q = S_0 w_0 for all phases q (S_q[p, tap] = 1 where phase q's tap reads a pixel of phase p,
    written here from the definition) the fit minimises Σ_q ‖X_q w_q − T_q‖² + reg_q ‖w_q‖²: w = Z z with Z a
    basis of the constraints' null space (SVD) and (ZᵀGZ) z = Zᵀc.

    Every phase has samples (h, w >= m, as on any training scene): a phase without any is a degenerate problem
    (its Gram matrix 0, an absolute ridge of 1 against a relative one elsewhere) that only a sub-period image makes."""
    assume(k >= m and h >= m and w >= m)
    rng = np.random.default_rng(seed)
    g, t = rng.random((b, 1, h, w)) * scale, rng.random((b, c, h, w))
    fit = LinearDemosaicFit(m, c, k, ridge=ridge, flat_field=True)
    fit.add(torch.from_numpy(g), torch.from_numpy(t), (oy, ox))
    got = fit.solve().double().numpy()
    q_n, n, r = m * m, k * k, k // 2
    select = np.zeros((q_n, q_n, n))
    for q in range(q_n):
        for u in range(k):
            for v in range(k):
                select[q, ((q // m + u - r) % m) * m + (q % m + v - r) % m, u * k + v] = 1.0
    cons = np.zeros(((q_n - 1) * q_n, q_n * n))
    for q in range(1, q_n):
        cons[(q - 1) * q_n : q * q_n, q * n : (q + 1) * n] = select[q]
        cons[(q - 1) * q_n : q * q_n, :n] = -select[0]
    if cons.size:
        _, sv, vt = np.linalg.svd(cons)
        null = vt[int((sv > 1e-9).sum()) :].T
    else:
        null = np.eye(q_n * n)
    grams, cross = _normal_equations(g, t, m, k, (oy, ox), ridge)
    big = np.zeros((q_n * n, q_n * n))
    for q in range(q_n):
        big[q * n : (q + 1) * n, q * n : (q + 1) * n] = grams[q]
    sol = null @ np.linalg.solve(null.T @ big @ null, null.T @ np.concatenate(cross))
    ref = sol.reshape(q_n, n, c).transpose(0, 2, 1).reshape(q_n, c, k, k)
    np.testing.assert_allclose(got, ref, rtol=1e-3, atol=1e-4 * np.abs(ref).max())


# ------------------------------------------------------------------------------------------------
# linear_consistency_step: the definition, batch items
# ------------------------------------------------------------------------------------------------
def _a_replicated(x, psf, tile, origin):
    """y_ij = Σ_c κ_c(i + oy, j + ox) Σ_uv p_c[u, v] x_c[i − u + r, j − v + r], x extended by replication."""
    b, c, h, w = x.shape
    k, m, r = psf.shape[-1], tile.shape[-1], psf.shape[-1] // 2
    rows, cols = np.clip(np.arange(-r, h + r), 0, h - 1), np.clip(np.arange(-r, w + r), 0, w - 1)
    xe = x[:, :, rows][:, :, :, cols]
    y = np.zeros((b, 1, h, w))
    for i in range(h):
        for j in range(w):
            win = xe[:, :, i : i + k, j : j + k][:, :, ::-1, ::-1]  # x[i − u + r]: the window flipped
            kappa = tile[:, (i + origin[0]) % m, (j + origin[1]) % m]
            y[:, 0, i, j] = np.einsum("bcuv,cuv,c->b", win, psf, kappa)
    return y


def _phase_linear(g, weight, origin):
    m, k = math.isqrt(weight.shape[0]), weight.shape[-1]
    x = _patches(g, k)
    ph = _phase(g.shape[2], g.shape[3], m, origin)
    return np.einsum("bhwn,hwcn->bchw", x, weight.reshape(m * m, weight.shape[1], k * k)[ph])


@PIPELINE_PROPS
@given(bands=st.integers(1, 5), kernel=st.sampled_from([1, 3, 5]), m=st.integers(1, 4),
       window=st.sampled_from([1, 3, 5]), h=st.integers(1, 11), w=st.integers(1, 11),
       origin=st.tuples(st.integers(0, 9), st.integers(0, 9)), gain=st.sampled_from([0.1, 0.5, 1.0]),
       iterations=st.integers(0, 3), seed=st.integers(0, 99))
def test_linear_step_is_x_plus_gain_w_residual_by_brute_force(bands, kernel, m, window, h, w, origin, gain, iterations,
                                                              seed):
    """x ← x + gain · W(y − A x), the estimate extended by replication for A, each batch item as alone."""
    op = snapshot(bands, kernel, m, seed)
    rng = np.random.default_rng(seed)
    x0 = rng.random((2, bands, h, w))
    y = rng.random((2, 1, h, w))
    weight = rng.normal(size=(m * m, bands, window, window)) * 0.1
    got = linear_consistency_step(op, torch.from_numpy(y), torch.from_numpy(x0), torch.from_numpy(weight), origin,
                                  gain=gain, iterations=iterations, psf_energy=1.0).numpy()
    x = x0
    for _ in range(iterations):
        x = x + gain * _phase_linear(y - _a_replicated(x, op.psf.numpy(), op.tile.numpy(), origin), weight, origin)
    np.testing.assert_allclose(got, x, rtol=1e-9, atol=1e-10)


# ------------------------------------------------------------------------------------------------
# Demosaic and TV
# ------------------------------------------------------------------------------------------------
def _zero_padded_mean(x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Brute force: Σ_{u,v} w_u w_v x[i+u, j+v] (zeros outside), w normalised to sum 1, per (B, C)."""
    k = len(weights)
    r = k // 2
    b, c, h, w = x.shape
    p = np.zeros((b, c, h + 2 * r, w + 2 * r))
    p[..., r : r + h, r : r + w] = x
    out = np.zeros_like(x)
    for u in range(k):
        for v in range(k):
            out += weights[u] * weights[v] * p[..., u : u + h, v : v + w]
    return out


@CORE_PROP
@given(seed=seeds, b=st.integers(1, 2), c=st.integers(1, 6), h=st.integers(1, 13), w=st.integers(1, 13),
       m=st.integers(1, 5), window=st.sampled_from([1, 3, 5, 7, 9, 15]), kernel=st.sampled_from(["box", "tent"]),
       grey=st.floats(0.01, 10.0), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_demosaic_grey_scene_comes_back_and_is_the_brute_force(seed, b, c, h, w, m, window, kernel, grey, dtype):
    """A grey scene (every band v) gives g = v through any CFA (Σκ = 1) and the demosaic returns v at every pixel,
    border included, any window and size; in general it is the brute-force ratio of zero-padded weighted sums.
    (Grey comes back only where the band is seen: a filter that blocks band c at every pixel of the window gives 0,
    the clamped 0/0; so the grey part uses filters that pass every band, the brute-force part zero filters too.)"""
    gen = torch.Generator().manual_seed(seed)
    code = tile_pattern(cfa_tile(torch.rand(c, m, m, generator=gen) + 0.05), h, w).to(dtype)
    g = torch.full((b, 1, h, w), grey, dtype=dtype)
    out = demosaic(g, code, window, kernel)
    torch.testing.assert_close(out, torch.full((b, c, h, w), grey, dtype=dtype),
                               rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
    code = tile_pattern(cfa_tile(torch.rand(c, m, m, generator=gen) - 0.3), h, w).to(dtype)
    scene = torch.rand(b, c, h, w, generator=gen, dtype=torch.float64)
    g = (scene * code.double()).sum(1, keepdim=True).to(dtype)
    out = demosaic(g, code, window, kernel).double().numpy()
    r = window // 2
    wts = np.ones(window) if kernel == "box" else (r + 1 - np.abs(np.arange(-r, r + 1))).astype(float)
    wts = wts / wts.sum()
    num = _zero_padded_mean(g.double().numpy() * code.double().numpy()[None], wts)
    den = _zero_padded_mean(code.double().numpy()[None], wts)
    np.testing.assert_allclose(out, num / np.maximum(den, 1e-6), rtol=1e-5 if dtype == torch.float32 else 1e-10)


@CORE_PROP
@given(seed=seeds, b=st.integers(1, 2), c=st.integers(1, 4), h=st.integers(1, 12), w=st.integers(1, 12),
       channels_last=st.booleans())
def test_tv_divergence_is_minus_the_adjoint_of_the_gradient(seed, b, c, h, w, channels_last):
    """<∇d, p> = −<d, div p> for p with zero last row (py) / column (px); fast and differentiable paths agree."""
    gen = torch.Generator().manual_seed(seed)
    d = torch.randn(b, c, h, w, generator=gen, dtype=torch.float64)
    py = torch.randn(b, c, h, w, generator=gen, dtype=torch.float64)
    px = torch.randn(b, c, h, w, generator=gen, dtype=torch.float64)
    py[..., -1, :] = 0
    px[..., :, -1] = 0
    if channels_last:
        d, py, px = (t.to(memory_format=torch.channels_last) for t in (d, py, px))
    gy, gx = forward_differences(d)
    div = dual_divergence(py, px)
    lhs = float((gy * py).sum() + (gx * px).sum())
    rhs = -float((d * div).sum())
    assert lhs == pytest.approx(rhs, rel=1e-10, abs=1e-10)
    # numpy reference of the forward differences
    dn = d.numpy()
    ref_y = np.zeros_like(dn)
    ref_y[..., :-1, :] = dn[..., 1:, :] - dn[..., :-1, :]
    ref_x = np.zeros_like(dn)
    ref_x[..., :, :-1] = dn[..., :, 1:] - dn[..., :, :-1]
    np.testing.assert_allclose(gy.numpy(), ref_y, atol=1e-14)
    np.testing.assert_allclose(gx.numpy(), ref_x, atol=1e-14)
    dr = d.clone().requires_grad_(True)
    gy2, gx2 = forward_differences(dr)
    torch.testing.assert_close(gy2.detach(), gy)
    torch.testing.assert_close(gx2.detach(), gx)
    torch.testing.assert_close(dual_divergence(py.clone().requires_grad_(True), px).detach(), div)


@CORE_FEW
@given(seed=seeds, c=st.integers(1, 3), h=st.integers(1, 10), w=st.integers(1, 10), weight=st.floats(0.01, 2.0),
       vectorial=st.booleans())
def test_tv_prox_keeps_the_mean_and_lowers_tv(seed, c, h, w, weight, vectorial):
    """u = f − w div p after Chambolle's iterations: mean of u = mean of f (div sums to 0), TV(u) ≤ TV(f), and the
    prox objective ½|u − f|² + w TV(u) ≤ its value at u = f."""
    gen = torch.Generator().manual_seed(seed)
    f = torch.rand(1, c, h, w, generator=gen, dtype=torch.float64)
    py, px = torch.zeros_like(f), torch.zeros_like(f)
    for _ in range(200):
        py, px = chambolle_step(py, px, f / weight, vectorial=vectorial)
    u = f - weight * dual_divergence(py, px)

    def tv(z):
        gy, gx = forward_differences(z)
        if vectorial:
            return float((gy.square().sum(1) + gx.square().sum(1)).sqrt().sum())
        return float(torch.hypot(gy, gx).sum())

    torch.testing.assert_close(u.mean(dim=(-2, -1)), f.mean(dim=(-2, -1)), rtol=0, atol=1e-12)
    assert tv(u) <= tv(f) + 1e-9
    assert 0.5 * float((u - f).square().sum()) + weight * tv(u) <= weight * tv(f) + 1e-9


@CORE_PROP
@given(seed=seeds, m=st.integers(1, 4), k=st.sampled_from([1, 3, 5]), h=st.integers(1, 11), w=st.integers(1, 11),
       oy=st.integers(0, 7), ox=st.integers(0, 7), b=st.integers(1, 2))
def test_phase_linear_is_the_brute_force(seed, m, k, h, w, oy, ox, b):
    """Each output pixel = the K×K replicate-padded neighbourhood · W[phase of the pixel on the whole sensor]."""
    gen = torch.Generator().manual_seed(seed)
    c = 2
    g = torch.rand(b, 1, h, w, generator=gen, dtype=torch.float64)
    wt = torch.randn(m * m, c, k, k, generator=gen, dtype=torch.float64)
    out = phase_linear(g, wt, (oy, ox)).numpy()
    r = k // 2
    p = np.pad(g.numpy()[:, 0], ((0, 0), (r, r), (r, r)), mode="edge")
    ref = np.zeros((b, c, h, w))
    for i in range(h):
        for j in range(w):
            q = ((i + oy) % m) * m + (j + ox) % m
            patch = p[:, i : i + k, j : j + k]
            ref[:, :, i, j] = np.einsum("buv,cuv->bc", patch, wt[q].numpy())
    np.testing.assert_allclose(out, ref, atol=1e-12)
