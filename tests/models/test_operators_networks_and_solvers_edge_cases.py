"""Guards found by mutation testing of the CASSI operators, the solvers, the networks' building blocks, the
tolerance perturbations and the fabrication export: each test kills a hand-made mutant (a swapped axis, a dropped
normalisation, an ignored origin, a wrong bound) that the rest of the suite let through, and checks the behaviour
against a reference computed here (power iteration for ‖A‖², impulse responses of AᵀA, loop sums over the aperture,
closed forms, files read back in their format), not against the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from demosaic_reference import box_demosaic_reference
from hsicam.cameras import build_camera
from hsicam.config import load_config


def cassi(kind: str, *overrides: str, dtype=torch.float64):
    """A CASSI camera of five bands (500..700 nm), 2 px per band."""
    cfg = load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50", f"camera.kind={kind}",
                                 *overrides])
    return build_camera(cfg).to(dtype)


def power_iteration(op, shape, iterations: int = 200) -> float:
    """‖A‖² = the largest eigenvalue of AᵀA, by power iteration from a fixed random start (float64)."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    lam = 0.0
    for _ in range(iterations):
        x = op.A_adjoint(op.A(x))
        lam = float(x.norm())
        x = x / lam
    return lam


# --------------------------------------------------------------------------------------------
# cameras/cassi.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
@pytest.mark.parametrize("convention", ("sum", "mean"))
def test_cassi_lipschitz_is_the_operator_norm_squared_of_an_open_aperture(kind, convention):
    """With every aperture pixel open, ΦΦᵀ = s²·C·I, so ‖A‖² = s²·C exactly (power iteration on AᵀA): the
    snapshot's ``lipschitz`` is a bound of ‖A‖² that the unrolled network divides its steps by, and s·C (a
    dropped square) made the 'mean' convention's steps C = 5 times too small. (SD-CASSI: a scene at least as wide as
    the span D = 8 px, so that some sensor column sees every band.)"""
    cam = cassi(kind, "camera.cassi.mask_density=1", f"camera.cassi.convention={convention}")
    snap = cam.snapshot(nominal=True)
    ref = power_iteration(snap, (1, 5, 4, 12))
    assert snap.lipschitz == pytest.approx(ref, rel=1e-6)


def test_sd_cassi_reach_is_the_support_of_a_gradient_steps_impulse_response():
    """One gradient step x − αAᵀ(Ax − y) spreads a voxel over the support of AᵀA δ: for SD-CASSI, the voxel of
    band c at column j reaches sensor column j + d_c, which every band c′ reads back from its column j + d_c − d_c′,
    so the reach is the dispersion span D along the columns and 0 along the rows (the tiling halo, ``reach_px``)."""
    cam = cassi("sd_cassi", "camera.cassi.mask_density=1")
    snap = cam.snapshot(nominal=True)
    h, w = 5, 21
    rows, cols = 0, 0
    for c in range(5):
        x = torch.zeros(1, 5, h, w, dtype=torch.float64)
        x[0, c, h // 2, w // 2] = 1.0
        nz = torch.nonzero(snap.A_adjoint(snap.A(x))[0].abs().sum(0) > 0)
        rows = max(rows, int((nz[:, 0] - h // 2).abs().max()))
        cols = max(cols, int((nz[:, 1] - w // 2).abs().max()))
    assert cam.span == 8
    assert tuple(snap.reach_px) == (rows, cols) == (0, 8)


def loop_gram_diagonal(cam, kind: str, h: int, w: int, origin: tuple[int, int]) -> np.ndarray:
    """diag(ΦΦᵀ) of the sensor window (h, w) at ``origin`` by loops over the aperture array (convention 'sum')."""
    r0, c0 = origin
    d = cam.shifts
    ap = cam.aperture.pattern(r0 + h + 1, c0 + w + max(d) + 1, dtype=torch.float64).numpy()
    ref = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            if kind == "dd_cassi":
                ref[i, j] = sum(ap[r0 + i, c0 + j + dc] ** 2 for dc in d)
            else:
                ref[i, j] = sum(ap[r0 + i, c0 + j - dc] ** 2 for dc in d if 0 <= j - dc < w - max(d))
    return ref


@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
@pytest.mark.parametrize("origin", ((0, 0), (3, 5)))
def test_cassi_gram_diagonal_of_a_window_is_the_loop_sum_over_its_aperture(kind, origin):
    """diag(ΦΦᵀ) of the sensor window at ``origin``, from the aperture array by the definitions: DD-CASSI
    s²·Σ_c P(r0 + i, c0 + j + d_c)², SD-CASSI s²·Σ_c P(r0 + i, c0 + j − d_c)² over the bands whose scene column
    j − d_c lies in the window. A diagonal taken at (0, 0) for every window fed the GAP steps of tiles the
    top-left code's normalisation."""
    cam = cassi(kind, "camera.cassi.convention=sum")
    snap = cam.snapshot(nominal=True)
    h, w = 6, 9
    ref = loop_gram_diagonal(cam, kind, h, w, origin)
    y = torch.zeros(1, 1, h, w, dtype=torch.float64)
    got = snap.gram_diagonal(y, origin)[0, 0].numpy()
    np.testing.assert_allclose(got, ref, atol=1e-12)


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


# --------------------------------------------------------------------------------------------
# optics/perturb.py
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("q", (1, 2, 3))
def test_misalignment_subsamples_round_up_to_the_pupil_oversampling(q):
    """The misalignment study needs at least the requested sub-samples per cell, on a grid that holds the camera's
    own pupil samples: the smallest multiple of q not below the request (rounding down gave 3 for a request of 5
    at q = 3, a coarser shift grid than asked)."""
    from types import SimpleNamespace

    from hsicam.optics.perturb import shift_subsamples_for

    optics = SimpleNamespace(pupil_oversample=q)
    for want in range(1, 12):
        ref = min(k for k in range(q, 100, q) if k >= want)
        assert shift_subsamples_for(optics, want) == ref, want


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


# --------------------------------------------------------------------------------------------
# export/doe.py, export/cfa.py
# --------------------------------------------------------------------------------------------
def test_exported_aperture_is_each_cells_area_fraction_on_the_psfs_sub_points(tiny_camera):
    """With pupil oversampling q = 2 each DOE cell holds q×q pupil samples, each an 8×8-point area fraction: the
    exported per-cell aperture (module docstring) is the fraction of the cell's 16×16 sub-points inside the
    circle, by brute force here. The largest sample per cell instead of their mean exported grazed cells as fully
    open."""
    from hsicam.export.doe import design_heights

    cam = tiny_camera("camera.psf.pupil_oversample=2")
    n, cell, radius = cam.optics.doe.n_cells, cam.optics.cell_m, cam.optics.aperture_radius_m
    sub = 16
    centres = (np.arange(n) - (n - 1) / 2) * cell
    xs = (centres[:, None] + ((np.arange(sub) + 0.5) / sub - 0.5)[None, :] * cell).reshape(-1)
    ref = ((xs[:, None] ** 2 + xs[None, :] ** 2) <= radius**2).reshape(n, sub, n, sub).mean(axis=(1, 3))
    _, aperture, _ = design_heights(cam)
    assert ((ref > 0) & (ref < 1)).any()  # partly covered cells: the test can tell
    np.testing.assert_allclose(aperture, ref, atol=1e-12)


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


def test_tiff_scale_is_the_smallest_1_2_5_step_that_fits_16_bits():
    """nm per count: the smallest of 1, 2, 5 × 10^k with max / scale ≤ 65535 (brute force over the 1-2-5 series).
    Without the 5s a 300 000 nm relief got 10 nm per count where 5 fit (half the height resolution)."""
    from hsicam.export.doe import nice_scale

    series = sorted(m * 10.0**e for e in range(-6, 6) for m in (1, 2, 5))
    for top in (1.0, 3.3, 65535.0, 65536.0, 1.2e5, 3e5, 7e5, 2.5e6):
        ref = min(s for s in series if top / s <= 65535 * (1 + 1e-12))
        assert nice_scale(top) == pytest.approx(ref, rel=1e-12), top


def test_phase_error_rms_is_weighted_by_the_aperture_fraction():
    """RMS over the aperture of the wrapped phase error, each cell weighted by its open fraction (loops): a cell
    half inside the circle carries half the light. The unweighted mean over the cells gave another RMS."""
    from hsicam.export.doe import phase_error

    rng = np.random.default_rng(8)
    h = rng.random((5, 5)) * 1e-6
    hq = h + rng.normal(0, 1e-7, (5, 5))
    wgt = np.clip(rng.random((5, 5)) * 1.5 - 0.25, 0, 1)
    k = np.array([1.2e7, 9.0e6])
    got = phase_error(h, hq, k, wgt)
    for b, kb in enumerate(k):
        num = den = 0.0
        worst = 0.0
        for i in range(5):
            for j in range(5):
                if wgt[i, j] > 0:
                    e = math.remainder(kb * (hq[i, j] - h[i, j]), 2 * math.pi)
                    num, den, worst = num + wgt[i, j] * e * e, den + wgt[i, j], max(worst, abs(e))
        assert got["rms_rad"][b] == pytest.approx(math.sqrt(num / den), rel=1e-9)
        assert got["max_rad"][b] == pytest.approx(worst, rel=1e-9)


def test_spec_first_order_efficiency_is_the_l_level_kinoforms_sinc_squared(tiny_camera, tmp_path):
    """The scalar first-order efficiency of an L-level kinoform is (sin(π/L) / (π/L))² (Swanson 1989): 0.405 for
    binary, 0.811 for 4 levels; sinc without its square (0.637 / 0.900) was written to spec.json."""
    from hsicam.export.doe import export_doe

    cam = tiny_camera()
    for levels in (2, 4):
        spec = export_doe(cam, tmp_path, levels, cam.bands.centers_nm)
        x = math.pi / levels
        assert spec["quantized"]["first_order_efficiency_sinc2"] == pytest.approx((math.sin(x) / x) ** 2, rel=1e-12)
