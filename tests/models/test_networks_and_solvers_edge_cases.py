"""Guards found by mutation testing of the solvers (GAP-TV, TV, DeSCI, Choi's ADMM and its prior) and of the
networks' building blocks (RDN, receptive-field bounds, MosaicNet, UnrolledNet, the demosaics): each test kills a
hand-made mutant (a swapped axis, a dropped normalisation, an ignored origin, a wrong bound, a skipped branch)
that the rest of the suite let through, and checks the behaviour against a reference computed here (loop sums
over the aperture, the published recursions in numpy, a numpy SVD, dependency radii measured by autograd, closed
forms), not against the code under test. The CASSI operators' guards are in tests/cameras/test_cassi.py, the
export's in tests/export/.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cassi_reference import cassi, loop_gram_diagonal
from demosaic_reference import box_demosaic_reference
from hsicam.cameras import build_camera
from hsicam.config import load_config


# --------------------------------------------------------------------------------------------
# solvers/gaptv.py, solvers/common.py
# --------------------------------------------------------------------------------------------
def published_gap_tv(cam, y, iterations, weights, accelerate):
    """GAP-TV as published (Yuan 2016's code): θ = 0, ȳ = 0; per iteration yb = Φθ, (acc.) ȳ += y − yb,
    θ += Φᵀ((ȳ − yb) ⊘ diag ΦΦᵀ) (plain: (y − yb)), then TV denoising with that iteration's weight
    (diag ΦΦᵀ = Φ(Φᵀ𝟙), 1 where it is 0)."""
    from hsicam.solvers.common import tv_denoise

    phi = cam.A(cam.A_adjoint(torch.ones_like(y)))
    phi = torch.where(phi > 0, phi, torch.ones_like(phi))  # a pixel no band reaches: its y and Φᵀ are 0 anyway
    x = torch.zeros_like(cam.A_adjoint(y))
    y1 = torch.zeros_like(y)
    for k in range(iterations):
        yb = cam.A(x)
        if accelerate:
            y1 = y1 + (y - yb)
            x = x + cam.A_adjoint((y1 - yb) / phi)
        else:
            x = x + cam.A_adjoint((y - yb) / phi)
        x = tv_denoise(x, weights[min(k, len(weights) - 1)], 5)
    return x


@pytest.mark.parametrize("accelerate", (True, False))
def test_gap_tv_is_the_published_recursion_with_its_per_iteration_weights(accelerate):
    """gap_tv from its minimum-norm start equals the published recursion started from θ = 0 (the docstring's
    claim), with the accelerated residual accumulation and the per-iteration TV weights (the last repeating).
    Accelerated GAP run as plain GAP, or the first weight used throughout, moved the result by ~1e-2."""
    from hsicam.solvers.gaptv import gap_tv

    cam = cassi("dd_cassi", "camera.cassi.convention=sum")
    g = torch.Generator().manual_seed(1)
    x = torch.nn.functional.avg_pool2d(torch.rand(1, 5, 20, 20, generator=g, dtype=torch.float64), 3, 1, 1)
    y = cam.A(x)
    weights = [0.08, 0.03, 0.01]
    got = gap_tv(cam, y, iterations=6, tv_weight=weights, tv_iterations=5, accelerate=accelerate)
    ref = published_gap_tv(cam, y, 6, weights, accelerate)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-10)


def np_grad(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward differences along rows and columns, 0 on the last row / column (Chambolle 2004, eq. 2.1)."""
    gy, gx = np.zeros_like(u), np.zeros_like(u)
    gy[..., :-1, :] = u[..., 1:, :] - u[..., :-1, :]
    gx[..., :, :-1] = u[..., :, 1:] - u[..., :, :-1]
    return gy, gx


def np_div(py: np.ndarray, px: np.ndarray) -> np.ndarray:
    """The discrete divergence, −(adjoint of np_grad), written out by Chambolle's cases (first, inner, last)."""
    d = np.zeros_like(py)
    d[..., 0, :] += py[..., 0, :]
    d[..., 1:-1, :] += py[..., 1:-1, :] - py[..., :-2, :]
    d[..., -1, :] -= py[..., -2, :]
    d[..., :, 0] += px[..., :, 0]
    d[..., :, 1:-1] += px[..., :, 1:-1] - px[..., :, :-2]
    d[..., :, -1] -= px[..., :, -2]
    return d


def test_total_variation_is_the_isotropic_sum_of_forward_difference_magnitudes():
    """TV(u) = Σ_pixels √(∂y u² + ∂x u²) per cube (forward differences, Chambolle's discretisation), by numpy.
    The anisotropic |∂y u| + |∂x u| or a dropped column difference gave another number on a random cube."""
    from hsicam.solvers.common import total_variation

    u = np.random.default_rng(0).random((2, 3, 7, 9))
    gy, gx = np_grad(u)
    ref = np.sqrt(gy**2 + gx**2).reshape(2, -1).sum(1)
    np.testing.assert_allclose(total_variation(torch.from_numpy(u)).numpy(), ref, rtol=1e-12)


@pytest.mark.parametrize("iterations", (1, 5))
def test_tv_denoise_runs_chambolles_projection_iteration_with_step_one_eighth(iterations):
    """A few iterations of Chambolle's algorithm (2004, eq. 3.3) from p = 0, by numpy: g = f/λ,
    p ← (p + τ∇(div p − g)) / (1 + τ|∇(div p − g)|), τ = 1/8 (his bound), u = f − λ div p. The solvers (GAP-TV,
    DeSCI) call it with 5 iterations, far from convergence, so the step matters: τ = 1/16 changed u by ~1e-2
    where the existing test, at convergence, did not see it."""
    from hsicam.solvers.common import tv_denoise

    f = np.random.default_rng(1).random((1, 2, 8, 10))
    lam, tau = 0.1, 0.125
    g = f / lam
    py, px = np.zeros_like(f), np.zeros_like(f)
    for _ in range(iterations):
        ay, ax = np_grad(np_div(py, px) - g)
        norm = 1.0 + tau * np.sqrt(ay**2 + ax**2)
        py, px = (py + tau * ay) / norm, (px + tau * ax) / norm
    ref = f - lam * np_div(py, px)
    got = tv_denoise(torch.from_numpy(f), lam, iterations).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-12)


# --------------------------------------------------------------------------------------------
# models/mosaic.py, models/unrolled.py, models/demosaic.py
# --------------------------------------------------------------------------------------------
def tiny_camera_of(kind: str, *overrides: str):
    torch.manual_seed(0)
    return build_camera(load_config("tiny", overrides=[f"camera.kind={kind}", *overrides]))


def randomised(net: torch.nn.Module, scale: float = 0.3, seed: int = 1) -> torch.nn.Module:
    """Every parameter drawn at random (the zero-initialised output convs would hide paths), float64, eval."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(scale * torch.randn(p.shape, generator=g))
    return net.double().eval()


def dependency_radius(run, h: int, w: int, at: tuple[int, int]) -> int:
    """The farthest sensor pixel (Chebyshev distance) whose value reaches the output at pixel ``at``: the support of
    the gradient of Σ_c out[c, at] with respect to the sensor (measured, float64; an FFT convolution leaves
    round-off of ~1e-16 relative everywhere, so entries below 1e-9 of the largest do not count)."""
    g = torch.Generator().manual_seed(2)
    y = (0.2 + torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)).requires_grad_(True)
    out = run(y)
    out[0, :, at[0], at[1]].sum().backward()
    grad = y.grad[0, 0].abs()
    nz = torch.nonzero(grad > 1e-9 * grad.max())
    return int(torch.maximum((nz[:, 0] - at[0]).abs(), (nz[:, 1] - at[1]).abs()).max())


def test_mosaic_context_covers_a_brightness_window_wider_than_the_demosaic():
    """b = box_w(g) + ε multiplies every output pixel, so a pixel depends on g up to w // 2 away: with a 21 px
    brightness window and a 3 px demosaic that is 10 px, and the declared tiling halo must reach that far (the
    demosaic window alone gave 6 px: tiles differed from the whole image)."""
    from hsicam.models.mosaic import MosaicNet

    cam = tiny_camera_of("doe")
    op = cam.snapshot(nominal=True)
    net = randomised(MosaicNet(len(cam.bands), 3, features=4, blocks=0, head_layers=0, demosaic_window=3,
                               brightness_window=21))
    radius = dependency_radius(lambda y: net(y, op), 41, 41, (20, 20))
    assert radius >= 10
    assert net.context_px >= radius


def test_mosaic_net_inputs_are_the_phase_cells_the_cell_mean_skip_and_the_filtered_residual():
    """What the trunk and the head of a MosaicNet read, by loops over the definitions (module docstring): the stem
    sees each m×m cell of the sensor grid (a window at ``origin`` padded by origin mod m) as m² phase channels and
    the cell means of the box demosaic x̃; the head sees g − Σ_c κ_c x̃_c and the detail features u = ReLU(·) ≥ 0.
    A zeroed skip channel, g − mean_c x̃_c (the filters ignored) or u without its ReLU passed every other test."""
    from hsicam.models.mosaic import MosaicNet

    cam = tiny_camera_of("doe")
    op = cam.snapshot(nominal=True)
    m, c = 3, len(cam.bands)
    net = randomised(MosaicNet(c, m, features=6, blocks=1, head_features=4, head_layers=2, demosaic_window=3,
                               detail_features=2))
    seen = {}
    net.stem.register_forward_pre_hook(lambda mod, args: seen.__setitem__("stem", args[0].detach().clone()))
    net.head.register_forward_pre_hook(lambda mod, args: seen.__setitem__("head", [a.detach().clone() for a in args]))
    net.detail.register_forward_hook(lambda mod, args, out: seen.__setitem__("detail", out.detach().clone()))
    h, w, origin = 8, 10, (1, 2)
    y = torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    with torch.no_grad():
        net(y, op, origin)
    g = y[0, 0].numpy()
    code = op.sensor_code(h, w, origin).detach().double().numpy()
    skip = box_demosaic_reference(g, code, 3)
    top, left = origin[0] % m, origin[1] % m
    hp, wp = -(-(h + top) // m), -(-(w + left) // m)
    cells = np.zeros((m * m + c, hp, wp))
    for ci in range(hp):
        for cj in range(wp):
            for a in range(m):
                for b in range(m):
                    i, j = ci * m + a - top, cj * m + b - left
                    if 0 <= i < h and 0 <= j < w:
                        cells[a * m + b, ci, cj] = g[i, j]
                        cells[m * m:, ci, cj] += skip[:, i, j] / (m * m)
    np.testing.assert_allclose(seen["stem"][0].numpy(), cells, atol=1e-12)
    _, sensor, residual, u = seen["head"]
    np.testing.assert_allclose(residual[0, 0].numpy(), g - (code * skip).sum(0), atol=1e-12)
    assert float(seen["detail"].min()) < 0  # the detail conv has negative outputs: the ReLU is visible
    assert float(u.min()) >= 0 and float(u.max()) > 0


def test_a_mosaic_net_on_a_camera_without_a_cfa_groups_3x3_cells():
    """``model.mosaic.factor: 0`` takes the CFA's period, and 3 without a CFA (config docs): κ = 1 has period 1,
    and a factor of 1 ran the trunk at full resolution (9× the work, another network)."""
    from hsicam.config import MosaicConfig
    from hsicam.models.mosaic import build_mosaic

    cam = tiny_camera_of("doe", "camera.cfa.enabled=false")
    assert cam.code_period == 1
    net = build_mosaic(MosaicConfig(features=4, blocks=1, head_layers=0), cam)
    assert net.factor == 3
    assert net.stem.in_channels == 9 + len(cam.bands)


@pytest.mark.parametrize("init, stages", (("demosaic", 1), ("backprojection", 2)))
def test_unrolled_context_covers_the_measured_dependency_of_its_stages(init, stages):
    """Tiles equal the whole image when the halo reaches as far as an output pixel depends on the sensor. Measured
    here by autograd on a DOE camera (K = 21 px kernel, AᵀA reaches K − 1 = 20 px) with priors on 2×2 cells (1 px
    within a cell): one stage after the 3 px demosaic reaches 1 + 20 + 1 = 22 px exactly; a back-projection
    (Aᵀy: K // 2 = 10 px) and two stages reach about 50 px, beyond 2 × 20 + 2 (the PSF's faint corners, squared,
    fall below the threshold).
    Declaring the init's reach 0, one stage's reach for all, or a prior without its cell left tiles short of that
    (the existing tiling test, on a DD-CASSI camera of reach 0 and one stage, did not see it)."""
    from hsicam.models.unrolled import UnrolledNet

    cam = tiny_camera_of("doe").double()
    with torch.no_grad():
        op = cam.snapshot(nominal=True)
    k = cam.optics.kernel_px
    assert tuple(op.reach_px) == (k - 1, k - 1)
    net = randomised(UnrolledNet(len(cam.bands), tuple(op.reach_px), stages=stages, init=init, prior_features=4,
                                 prior_blocks=0, prior_scale=2, demosaic_window=3), scale=0.5)
    size = 111
    radius = dependency_radius(lambda y: net(y, op), size, size, (size // 2, size // 2))
    if stages == 1:
        assert radius == 1 + (k - 1) + 1
    else:
        assert radius > 2 * (k - 1) + 2
    assert net.context_px >= radius


def test_a_one_pixel_demosaic_is_the_sensor_value_where_the_filter_passes_light():
    """The box demosaic Σ κ_c g / Σ κ_c over a 1 px window is g itself (loops): κ_c·g, the filtered value, is the
    light of the band through the filter, not an estimate of the band on the cube's scale."""
    from hsicam.models.demosaic import demosaic

    g = torch.rand(1, 1, 5, 6, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    code = 0.05 + torch.rand(3, 5, 6, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    ref = box_demosaic_reference(g[0, 0].numpy(), code.numpy(), 1)
    np.testing.assert_allclose(demosaic(g, code, 1)[0].numpy(), ref, rtol=1e-12)


def test_linear_demosaic_ridge_is_relative_to_the_mean_diagonal_of_the_gram_matrix():
    """``ridge`` × the mean diagonal of each phase's Gram matrix (class docstring): with one phase, ridge regression
    on K×K patches built here by loops (replicated border), solved by numpy. A ridge of ``ridge`` × the trace
    (K² = 9 times stronger) shrank the filters ~2× more at ridge 0.5."""
    from hsicam.models.demosaic import LinearDemosaicFit

    rng = np.random.default_rng(6)
    g = rng.random((1, 1, 7, 8))
    truth = rng.random((1, 2, 7, 8))
    k, ridge = 3, 0.5
    padded = np.pad(g[0, 0], 1, mode="edge")
    x = np.array([padded[i:i + k, j:j + k].reshape(-1) for i in range(7) for j in range(8)])
    t = truth[0].reshape(2, -1).T
    gram = x.T @ x
    ref = np.linalg.solve(gram + ridge * np.trace(gram) / (k * k) * np.eye(k * k), x.T @ t)  # (K², C)
    fit = LinearDemosaicFit(1, 2, k, ridge=ridge)
    fit.add(torch.from_numpy(g), torch.from_numpy(truth))
    got = fit.solve()[0].double().numpy().reshape(2, k * k).T
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("origin", ((0, 0), (3, 5)))
def test_unrolled_gap_step_of_a_tile_divides_by_its_own_windows_gram_diagonal(origin):
    """The unrolled network's GAP step x + α Aᵀ((y − A x) ⊘ diag ΦΦᵀ) on the window at ``origin``, with the
    diagonal from loops over the aperture there (DD-CASSI, a random half-open code: the diagonal varies). A tile
    divided by the top-left window's diagonal, or by its square root, moved the step."""
    from hsicam.models.unrolled import UnrolledNet

    cam = cassi("dd_cassi", "camera.cassi.convention=sum")
    snap = cam.snapshot(nominal=True)
    net = UnrolledNet(5, tuple(snap.reach_px), stages=1, init="backprojection", step="gap").double()
    h, w = 6, 9
    gen = torch.Generator().manual_seed(7)
    x = torch.rand(1, 5, h, w, generator=gen, dtype=torch.float64)
    y = torch.rand(1, 1, h, w, generator=gen, dtype=torch.float64)
    diag = torch.from_numpy(loop_gram_diagonal(cam, "dd_cassi", h, w, origin))
    assert float(diag.min()) > 0 and float(diag.max()) > float(diag.min())
    alpha = torch.tensor(0.7, dtype=torch.float64)
    ref = x + alpha * snap.A_adjoint((y - snap.A(x, origin)) / diag, origin)
    got = net.data_step(x, y, snap, alpha, origin)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# models/rdn.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("window", [3, 5])
def test_rdn_context_adds_half_the_demosaic_window_to_the_conv_reach(window):
    """Receptive radius by counting 3×3 convolutions (sfe1, sfe2, every dense layer, global fusion 3×3, output:
    4 + D·C px) plus the demosaic's own reach, half its (odd) box width."""
    from hsicam.models.rdn import RDNReconstructor

    d, c = 2, 3
    net = RDNReconstructor(4, demosaic_input=True, window=window, blocks=d, features=8, growth=4, layers_per_block=c)
    assert net.context_px == 4 + d * c + window // 2


def test_rdn_on_the_back_projection_starts_as_its_band_mean_in_every_band():
    """backprojection_input: the untrained network (output conv at zero) returns, in every band, the mean of the
    C input bands at that pixel."""
    from hsicam.models.rdn import RDN, RDNReconstructor

    torch.manual_seed(0)
    net = RDNReconstructor(5, backprojection_input=True, blocks=1, features=8, growth=4)
    x = torch.rand(2, 5, 6, 7)
    out = RDN.forward(net, x)  # the network on its input (the back-projection needs a camera, not tested here)
    np.testing.assert_allclose(out.detach().numpy(), x.mean(1, keepdim=True).expand(-1, 5, -1, -1).numpy(),
                               rtol=1e-6, atol=1e-7)


# --------------------------------------------------------------------------------------------
# models/context.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("padding", ["valid", "same", 0, 1, 2])
def test_conv_reach_is_the_farthest_input_pixel_an_output_pixel_depends_on(padding):
    """Brute force by autograd: the output pixel at (i, j) of a 3×5 conv depends on input pixels up to conv_reach px
    away from (i, j), on some side of some axis (valid padding: all of them after the pixel)."""
    from torch import nn

    from hsicam.models.context import conv_reach

    torch.manual_seed(0)
    conv = nn.Conv2d(1, 1, (3, 5), padding=padding)
    with torch.no_grad():
        conv.weight.fill_(1.0)
    x = torch.rand(1, 1, 21, 21, requires_grad=True)
    i = j = 8
    conv(x)[0, 0, i, j].backward()
    ys, xs = torch.nonzero(x.grad[0, 0], as_tuple=True)
    measured = int(max((ys - i).abs().max(), (xs - j).abs().max()))
    assert conv_reach(conv) == measured


# --------------------------------------------------------------------------------------------
# models/priors.py
# --------------------------------------------------------------------------------------------
def test_the_prior_encoder_pads_by_reflection():
    """The encoder is 3×3 convolutions with reflect padding and ReLU between them: recomputed layer by layer with
    F.pad(mode='reflect') + F.conv2d, borders included (zero padding darkens the border pixels)."""
    import torch.nn.functional as F

    from hsicam.models.priors import SpectralAutoencoder

    torch.manual_seed(1)
    prior = SpectralAutoencoder(3, features=4, latent=5, layers=3)
    x = torch.rand(2, 3, 6, 7) + 0.5
    convs = [mod for mod in prior.encoder if isinstance(mod, torch.nn.Conv2d)]
    ref = x
    for k, conv in enumerate(convs):
        ref = F.conv2d(F.pad(ref, (1, 1, 1, 1), mode="reflect"), conv.weight, conv.bias)
        if k < len(convs) - 1:
            ref = ref.relu()
    torch.testing.assert_close(prior.encode(x), ref, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------------------------
# solvers/desci.py
# --------------------------------------------------------------------------------------------
def test_wnnm_groups_equal_a_numpy_svd_with_the_closed_form_shrinkage():
    """Each group Y (d × K): mean column removed, SVD (numpy), singular values s shrunk to
    (s − ε + √((s + ε)² − 4w)) / 2 where the discriminant is positive (else 0), w = c·σ²(√d + √K)²/4, mean put back."""
    from hsicam.solvers.desci import wnnm_groups

    rng = np.random.default_rng(7)
    g, d, k, sigma, c, eps = 3, 12, 6, 0.1, 1.3, 1e-8
    low = rng.random((g, d, 2)) @ rng.random((g, 2, k))  # rank 2 + noise: some values kept, some removed
    groups = low + sigma * rng.standard_normal((g, d, k))
    got = wnnm_groups(torch.from_numpy(groups), sigma, c).numpy()
    w = c * sigma**2 * (np.sqrt(d) + np.sqrt(k)) ** 2 / 4
    for i in range(g):
        mean = groups[i].mean(axis=1, keepdims=True)
        u, s, vt = np.linalg.svd(groups[i] - mean, full_matrices=False)
        disc = (s + eps) ** 2 - 4 * w
        shrunk = np.where(disc > 0, (s - eps + np.sqrt(np.maximum(disc, 0))) / 2, 0.0)
        assert 0 < np.count_nonzero(shrunk) < k  # the test exercises both branches
        np.testing.assert_allclose(got[i], u @ np.diag(shrunk) @ vt + mean, rtol=1e-7, atol=1e-9)


# --------------------------------------------------------------------------------------------
# solvers/choi.py
# --------------------------------------------------------------------------------------------
def _small_cassi(bands: int = 4):
    from hsicam.cameras import build_camera
    from hsicam.config import load_config

    cfg = load_config(overrides=["bands.start_nm=500", f"bands.stop_nm={500 + 20 * (bands - 1)}", "bands.step_nm=20",
                                 "camera.kind=dd_cassi"])
    return build_camera(cfg).to(torch.float64)


def test_prior_residual_is_half_the_squared_distance_to_the_prior():
    """½‖z − R(z)‖² per cube, for a prior R(z) = z/2 + 0.1: ½·Σ(z/2 − 0.1)²."""
    from hsicam.solvers.choi import prior_residual

    z = torch.rand(3, 2, 4, 5, dtype=torch.float64)
    got = prior_residual(lambda t: 0.5 * t + 0.1, z)
    torch.testing.assert_close(got, 0.5 * ((0.5 * z - 0.1) ** 2).sum(dim=(1, 2, 3)))


@pytest.mark.parametrize("tv_weight", [0.0, 0.02])
def test_choi_admm_with_an_identity_prior_is_the_closed_form_x_update_then_the_tv_prox(tv_weight):
    """With R = identity (an untrained autoencoder) and τ1 = 0, one proximal-gradient step of size 1/ρ lands on
    w = x + u, so each iteration is scaled-form ADMM: the exact x-update x = v + Φᵀ((y − Φv)/m / (diag(ΦΦᵀ)/m + ρ))
    at v = z − u (m the mean of diag ΦΦᵀ), the TV prox of w at weight τ2/ρ, u += x − z; ρ grows by rho_growth, and
    the scaled dual u shrinks by it (the multiplier ρu carries over: Boyd et al. 2011, §3.4.1; since session 74)."""
    from hsicam.config import ChoiConfig
    from hsicam.models.priors import SpectralAutoencoder
    from hsicam.solvers.choi import admm_prior
    from hsicam.solvers.common import tv_denoise

    torch.manual_seed(0)
    cam = _small_cassi(4)
    truth = torch.rand(1, 4, 12, 12, dtype=torch.float64)
    y = cam.A(truth)
    prior = SpectralAutoencoder(4, features=2, latent=2, layers=2).double()
    s = ChoiConfig(iterations=3, rho=0.7, rho_growth=1.5, prior_weight=0.0, tv_weight=tv_weight, inner_steps=1,
                   init_iterations=0)
    got = admm_prior(cam, y, prior, s, x0=torch.zeros_like(truth))
    phi = cam.gram_diagonal(y)
    m = phi.mean()
    z, u, rho = torch.zeros_like(truth), torch.zeros_like(truth), 0.7
    for _ in range(3):  # scaled-form ADMM (u stays 0 without TV)
        v = z - u
        x = v + cam.A_adjoint((y - cam.A(v)) / m / (phi / m + rho))
        z = tv_denoise(x + u, tv_weight / rho, 5)
        u = (u + x - z) / 1.5
        rho *= 1.5
    torch.testing.assert_close(got, z, rtol=1e-9, atol=1e-12)


def test_choi_minimum_norm_start_fits_the_measurement():
    """No GAP-TV start and no iteration: the start Φᵀ(y ⊘ diag ΦΦᵀ) reproduces y exactly (ΦΦᵀ is diagonal)."""
    from hsicam.config import ChoiConfig
    from hsicam.models.priors import SpectralAutoencoder
    from hsicam.solvers.choi import admm_prior

    torch.manual_seed(0)
    cam = _small_cassi(4)
    y = cam.A(torch.rand(1, 4, 12, 12, dtype=torch.float64))
    prior = SpectralAutoencoder(4, features=2, latent=2, layers=2).double()
    x = admm_prior(cam, y, prior, ChoiConfig(iterations=0, init_iterations=0))
    torch.testing.assert_close(cam.A(x), y, rtol=1e-9, atol=1e-12)
