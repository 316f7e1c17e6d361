"""The measurement-consistency step after the network (hsicam.models.consistency): a dense-matrix
reference, the residual and error guarantees, GAP on DD-CASSI, exact tiling, configs."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hsicam.cameras import build_camera
from hsicam.cameras.doe_camera import DOESnapshot
from hsicam.cameras.measured import FixedPSFCamera
from hsicam.config import load_config
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import ConfigError, InputError
from hsicam.models import CameraSystem
from hsicam.models.consistency import consistency_step, cut_psf, reach_px, spectral_preconditioner
from hsicam.solvers.common import gap_projection
from hsicam.spectral import Bands

C, K, M = 3, 5, 3  # bands, kernel (px), CFA period


def _snapshot(seed: int = 0) -> DOESnapshot:
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(C, K, K, generator=g, dtype=torch.float64)
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True)
    tile = torch.rand(C, M, M, generator=g, dtype=torch.float64)
    return DOESnapshot(Bands.uniform(500, 700, 100), psf, tile, M)


def _lipschitz_bound(psf: np.ndarray, tile: np.ndarray) -> float:
    """L = max_c (Σ_kl p_c[k, l])² · max_pixel Σ_c κ_c² (Young's inequality per band, Cauchy–Schwarz
    over the bands), by loops over the test's own PSF stack (C, K, K) and CFA tile (C, M, M)."""
    psf_sum = max(float(sum(psf[c, k, l] for k in range(psf.shape[1]) for l in range(psf.shape[2])))
                  for c in range(psf.shape[0]))
    code = max(float(sum(tile[c, i, j] ** 2 for c in range(tile.shape[0])))
               for i in range(tile.shape[1]) for j in range(tile.shape[2]))
    return psf_sum**2 * code


def _snapshot_lipschitz(snap: DOESnapshot) -> float:
    return _lipschitz_bound(snap.psf.numpy(), snap.tile.numpy())


def test_snapshot_lipschitz_is_the_bound_from_its_psf_and_cfa():
    """DOESnapshot.lipschitz = max_c ‖p_c‖₁² · max_pixel Σ_c κ_c², computed here from the PSF and tile
    handed to it (PSFs of different energies, so the band maximum matters), and it bounds ‖A‖² of
    the dense matrix (largest singular value squared)."""
    g = torch.Generator().manual_seed(21)
    psf = torch.rand(C, K, K, generator=g, dtype=torch.float64)
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True) * torch.tensor([0.5, 1.3, 0.8], dtype=torch.float64)[:, None, None]
    tile = torch.rand(C, M, M, generator=g, dtype=torch.float64)
    snap = DOESnapshot(Bands.uniform(500, 700, 100), psf, tile, M)
    want = _lipschitz_bound(psf.numpy(), tile.numpy())
    assert snap.lipschitz == pytest.approx(want, rel=1e-12)
    norm2 = np.linalg.norm(_dense_valid(snap, 7, 8, (0, 0)), 2) ** 2
    assert 0 < norm2 <= want * (1 + 1e-12)


def _dense_valid(snap: DOESnapshot, h: int, w: int, origin: tuple[int, int]) -> np.ndarray:
    """Matrix of the physical (valid) operator from the definitions: the sensor window (h, w) at
    ``origin`` sees the cube on (h + K − 1, w + K − 1) through y[i, j] = Σ_c κ_c(i, j) Σ_kl
    p_c[k, l] x_c[i + K − 1 − k, j + K − 1 − l], κ_c(i, j) = tile_c[(origin + (i, j)) mod M]."""
    psf, tile = snap.psf.numpy(), snap.tile.numpy()
    H, W = h + K - 1, w + K - 1
    a = np.zeros((h * w, C * H * W))
    for i in range(h):
        for j in range(w):
            for c in range(C):
                kap = tile[c, (origin[0] + i) % M, (origin[1] + j) % M]
                for k in range(K):
                    for l in range(K):
                        a[i * w + j, c * H * W + (i + K - 1 - k) * W + (j + K - 1 - l)] += kap * psf[c, k, l]
    return a


def test_step_matches_a_dense_matrix_reference():
    """One step = x_e + Aᵀ((y − A x_e) ⊘ (A Aᵀ 𝟙 + λ)) with x_e the estimate extended by K//2
    replicated pixels, written with an explicit matrix of the valid-geometry operator."""
    snap, h, w, origin = _snapshot(), 6, 7, (1, 2)
    g = torch.Generator().manual_seed(1)
    x0 = torch.rand(1, C, h, w, generator=g, dtype=torch.float64)
    y = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    damping = 0.05
    got = consistency_step(snap, y, x0, origin, damping=damping, iterations=1, psf_energy=1.0)

    a = _dense_valid(snap, h, w, origin)
    r = K // 2
    xe = np.pad(x0[0].numpy(), ((0, 0), (r, r), (r, r)), mode="edge").reshape(-1)
    lam = damping * _snapshot_lipschitz(snap)
    d = a @ (a.T @ np.ones(h * w)) + lam
    x1 = xe + a.T @ ((y.numpy().reshape(-1) - a @ xe) / d)
    want = x1.reshape(C, h + 2 * r, w + 2 * r)[:, r:-r, r:-r]
    np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-10, atol=1e-12)


def _high_contrast_problem(seed: int, data_seed: int, shape: tuple[int, ...]):
    """(operator with a high-contrast CFA (one band nearly dark per pixel), truth of ``shape``, its
    noiseless measurement, an estimate off by 0.3 per value): where a plain gradient step overshoots."""
    snap = _snapshot(seed)
    snap = DOESnapshot(snap.bands, snap.psf, torch.where(snap.tile > 0.5, 1.0, 0.01).double(), M)
    g = torch.Generator().manual_seed(data_seed)
    truth = torch.rand(*shape, generator=g, dtype=torch.float64)
    return snap, truth, snap.A(truth), truth + 0.3 * torch.randn(truth.shape, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("seed", [2, 7, 11])
def test_steps_never_grow_the_error_nor_the_weighted_residual(seed):
    """For noiseless data and the exact operator (``same`` geometry, zero light beyond the
    window, so nothing is extended): x − x* is multiplied by I − Aᵀ D⁻¹ A (eigenvalues in
    [0, 1]), so the error never grows, and the D⁻¹-weighted residual never grows. A
    high-contrast CFA (one band nearly dark per pixel) is where a plain gradient step overshoots."""
    snap, truth, y, x0 = _high_contrast_problem(seed, seed + 100, (2, C, 14, 11))
    d = snap.A(snap.A_adjoint(torch.ones_like(y[:1]))) + 1e-6 * _snapshot_lipschitz(snap)
    errors, weighted = [], []
    for n in range(5):
        x = consistency_step(snap, y, x0, damping=1e-6, iterations=n, psf_energy=1.0, extend=False)
        errors.append(float((x - truth).norm()))
        r = y - snap.A(x)
        weighted.append(float((r * r / d).sum()))
    assert all(b <= a + 1e-12 for a, b in zip(errors, errors[1:])), errors
    assert all(b <= a + 1e-12 for a, b in zip(weighted, weighted[1:])), weighted
    assert errors[-1] < 0.97 * errors[0] and weighted[-1] < 0.5 * weighted[0]


class _Oracle(torch.nn.Module):
    """A "network" that returns a fixed cube (context 0)."""

    context_px = 0

    def __init__(self, cube: torch.Tensor) -> None:
        super().__init__()
        self.cube = cube

    def forward(self, sensor, camera, origin=(0, 0)):
        return self.cube


@pytest.mark.parametrize("padding", ["zeros", "replicate", "reflect"])
def test_a_perfect_estimate_is_a_fixed_point_for_same_cameras(tiny_camera, padding):
    """A ``same`` camera pads the scene itself: with zeros the system does not extend the
    estimate (no light from beyond), with replication or reflection it extends it the same way,
    so in each the true cube explains y exactly and stays put. Extending under zero padding, or
    replicating under reflection, would move it."""
    cam = tiny_camera("camera.boundary=same", f"camera.padding={padding}", dtype=torch.float64)
    truth = 0.2 + 0.6 * torch.rand(1, len(cam.bands), 40, 40, generator=torch.Generator().manual_seed(8),
                                   dtype=torch.float64)
    consistency = load_config(overrides=["model.consistency.iterations=2", "model.consistency.psf_energy=1"])
    model = CameraSystem(cam, _Oracle(truth), consistency.model.consistency).eval()
    y = cam.A(truth)
    with torch.no_grad():
        got = model.reconstructor()(y)
    torch.testing.assert_close(got, truth, rtol=0, atol=1e-10)
    wrong = {"zeros": True, "reflect": "replicate"}.get(padding)
    if wrong is not None:
        moved = consistency_step(cam.snapshot(nominal=True), y, truth, iterations=2, psf_energy=1.0, extend=wrong)
        assert (moved - truth).abs().max() > 1e-3


def test_step_camera_is_the_operator_the_step_uses(tiny_camera):
    """``step_camera``: the step uses that camera's nominal operator (the tolerance study's
    design PSF), not the camera the scene was imaged with."""
    from hsicam.cameras.measured import FixedPSFCamera

    cam = tiny_camera()
    psf = cam.psf().detach()
    perturbed = FixedPSFCamera.from_camera(cam, torch.roll(psf, 1, dims=-1))
    x0 = torch.rand(1, len(cam.bands), 24, 24, generator=torch.Generator().manual_seed(9))
    c = load_config(overrides=["model.consistency.iterations=1"]).model.consistency
    model = CameraSystem(perturbed, _Oracle(x0), c).eval()
    y = torch.rand(1, 1, 24, 24, generator=torch.Generator().manual_seed(10))
    with torch.no_grad():
        own = model.reconstructor()(y)
        model.step_camera = cam
        nominal = model.reconstructor()(y)
        want = consistency_step(cam.snapshot(nominal=True), y, x0, damping=c.damping, iterations=1,
                                psf_energy=c.psf_energy)
    torch.testing.assert_close(nominal, want)
    assert (own - nominal).abs().max() > 1e-4


def test_sd_cassi_skips_the_step():
    """SD-CASSI's scene grid is not the sensor's: its system trains and reconstructs without the
    step (the quick preset switched to SD-CASSI, as a user would)."""
    cfg = load_config("quick", ["camera.kind=sd_cassi", "model.kind=unrolled", "model.unrolled.init=backprojection",
                                "model.unrolled.step=gap", "model.unrolled.stages=1"])
    assert cfg.model.consistency.iterations == 1
    model = CameraSystem.from_config(cfg).eval()
    assert not model.consistency_on and model.context_px == model.net.context_px
    y = torch.rand(1, 1, 24, 160)
    with torch.no_grad():
        torch.testing.assert_close(model.reconstructor()(y), model.network(y, operator=model.camera.snapshot()))


def test_reconstructor_equals_reconstruct_with_a_cut_psf(tiny_config):
    """reconstructor() cuts the step's PSFs once, as reconstruct does (not twice). A flat 7×7 PSF
    cut to 30 % of its light keeps 5×5 px, and cutting that again would keep 3×3: so a second cut
    would change the result here."""
    model = _system(tiny_config, "model.consistency.psf_energy=0.3")
    k, c = model.camera.kernel_px, len(model.bands)
    assert k == 7
    model.step_camera = FixedPSFCamera.from_camera(model.camera, torch.full((c, k, k), 1.0 / k**2))
    once = cut_psf(model.step_camera.snapshot(nominal=True), 0.3)
    assert once.kernel_px == 5 and cut_psf(once, 0.3).kernel_px == 3
    sensor = torch.rand(1, 1, 30, 26, generator=torch.Generator().manual_seed(12))
    with torch.no_grad():
        torch.testing.assert_close(model.reconstructor()(sensor), model.reconstruct(sensor), rtol=1e-5, atol=1e-6)


def test_step_camera_is_not_part_of_the_state():
    """step_camera is a reference, not a submodule: the system's state dict and parameters stay
    those of camera + network (weights saved from it load into a plain system)."""
    model = CameraSystem.from_config(load_config("tiny"))
    keys, n_params = set(model.state_dict()), len(list(model.parameters()))
    model.step_camera = FixedPSFCamera.from_camera(model.camera, model.camera.psf().detach() * 0.5)
    assert set(model.state_dict()) == keys and len(list(model.parameters())) == n_params
    assert model.step_camera is not None and "step_camera" not in dict(model.named_modules())


def test_one_undamped_step_on_dd_cassi_is_the_gap_projection():
    """DD-CASSI's A Aᵀ is diagonal, so the row sums are its diagonal: one step is GAP's projection
    onto {x : A x = y} (hsicam.solvers.common.gap_projection), and the result explains y."""
    cam = build_camera(load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50",
                                              "camera.kind=dd_cassi", "camera.boundary=same"])).double()
    g = torch.Generator().manual_seed(4)
    x0 = torch.rand(1, len(cam.bands), 20, 24, generator=g, dtype=torch.float64)
    y = cam.A(torch.rand(x0.shape, generator=g, dtype=torch.float64))
    got = consistency_step(cam.snapshot(), y, x0, damping=1e-12, iterations=1)
    want = gap_projection(cam, x0, y, cam.gram_diagonal(y))
    torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-9)
    seen = cam.gram_diagonal(y) != 1  # pixels that some band reaches
    torch.testing.assert_close(cam.A(got)[seen], y[seen], rtol=1e-8, atol=1e-9)


def test_cut_psf_keeps_the_requested_light():
    snap = _snapshot()
    big = torch.zeros(C, 31, 31, dtype=torch.float64)
    big[:, 15, 15] = 0.9
    big[:, 14:17, 14:17] += 0.01  # 9 % of the light in the 3×3 ring (minus the centre's share)
    big[:, 0, 0] = 0.001  # a far tail
    snap = DOESnapshot(snap.bands, big, snap.tile, M)
    total = big.sum(dim=(-2, -1))
    assert cut_psf(snap, 0.9).kernel_px == 1
    assert cut_psf(snap, 0.99).kernel_px == 3
    cut = cut_psf(snap, 0.9995)
    assert cut.kernel_px == 31 and (cut.psf.sum(dim=(-2, -1)) >= 0.9995 * total).all()
    assert cut_psf(snap, 1.0) is snap


def _system(tiny_config, *overrides):
    torch.manual_seed(0)
    model = CameraSystem.from_config(tiny_config("model.consistency.iterations=1", *overrides)).eval()
    g = torch.Generator().manual_seed(5)  # a network whose output depends on its neighbourhood
    torch.nn.init.normal_(model.net.output.weight, std=0.1, generator=g)
    return model


def _assert_step_tiles_equal_whole(model, snap) -> None:
    """The step changes the network's output, and tiles with ``model.context_px`` of halo equal the
    whole image."""
    sensor = torch.rand(1, 1, 53, 47)
    f = model.reconstructor()
    with torch.no_grad():
        whole = f(sensor)
        plain = model.net(sensor, snap, (0, 0))
    assert (whole - plain).abs().max() > 1e-3  # the step does something
    tiled = reconstruct_tiled(f, sensor, tile_px=16, halo_px=model.context_px)
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)


def test_tiles_with_the_declared_context_equal_the_whole_image(tiny_config):
    model = _system(tiny_config)
    snap = model.camera.snapshot(nominal=True)
    step = reach_px(snap, 1, model.consistency.psf_energy)
    assert step > 0 and model.context_px == model.net.context_px + step
    _assert_step_tiles_equal_whole(model, snap)


@pytest.mark.parametrize("iterations", [1, 2])
def test_step_reach_is_the_halo_it_needs(iterations):
    """The step alone after a pixel-wise estimate: tiles with ``reach_px`` of halo equal the whole
    image; with less they do not."""
    snap = _snapshot(6)
    reach = reach_px(snap, iterations, psf_energy=1.0)
    assert reach == (2 * iterations + 1) * (K // 2)

    def f(window, origin=(0, 0)):
        x0 = window.expand(-1, C, -1, -1) * 0.7
        return consistency_step(snap, window, x0, origin, iterations=iterations, psf_energy=1.0)

    sensor = torch.rand(1, 1, 41, 38, dtype=torch.float64)
    whole = f(sensor)
    torch.testing.assert_close(reconstruct_tiled(f, sensor, tile_px=12, halo_px=reach), whole, rtol=1e-12, atol=1e-12)
    assert (reconstruct_tiled(f, sensor, tile_px=12, halo_px=reach - 2) - whole).abs().max() > 1e-6


def test_step_runs_in_eval_mode_only(tiny_config):
    model = _system(tiny_config)
    sensor = torch.rand(1, 1, 20, 20)
    with torch.no_grad():
        evaluated = model.reconstruct(sensor)
        model.train()
        trained = model.reconstruct(sensor)
        plain = model.net(sensor, model.camera, (0, 0))
    torch.testing.assert_close(trained, plain)
    assert (evaluated - plain).abs().max() > 1e-3
    off = CameraSystem.from_config(tiny_config()).eval()
    assert not off.consistency_on and off.context_px == off.net.context_px


@pytest.mark.parametrize("override, match", [
    ("model.consistency.iterations=-1", "iterations"),
    ("model.consistency.damping=0", "damping"),
    ("model.consistency.psf_energy=1.5", "psf_energy"),
])
def test_bad_settings_are_one_clear_error(tiny_config, override, match):
    with pytest.raises(ConfigError, match=match):
        tiny_config(override)


def test_a_camera_whose_scene_grid_differs_is_refused():
    cam = build_camera(load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50",
                                              "camera.kind=sd_cassi"])).double()
    y = torch.rand(1, 1, 12, 20, dtype=torch.float64)
    x0 = torch.rand(1, len(cam.bands), 12, 20, dtype=torch.float64)
    with pytest.raises(InputError, match="scene grid"):
        consistency_step(cam.snapshot(), y, x0)


def test_consistency_is_not_a_training_difference(tiny_config):
    from hsicam.config import training_differences

    assert training_differences(tiny_config(), tiny_config("model.consistency.iterations=2")) == []
    assert training_differences(tiny_config(), tiny_config("train.lr=0.5"))


def test_learned_cassi_rows_are_scored_without_the_step():
    """Table 1's learned CASSI controls: the DOE presets' step lowers the blind RDN's per-band PSNR
    (docs/networks.md), so the experiments' CASSI overrides switch it off; the DOE camera keeps it."""
    from hsicam.engine.experiments import LEARNED_CASSI

    assert load_config("quick").model.consistency.iterations == 1
    for name, overrides in LEARNED_CASSI.items():
        model = CameraSystem.from_config(load_config("quick", list(overrides))).eval()
        assert model.camera.kind == "dd_cassi" and not model.consistency_on, name


def test_experiment_builds_learned_cassi_methods_from_their_own_overrides(monkeypatch, tmp_path):
    """_baseline_rows hands build_method the learned CASSI rows' own config (step off), and the
    evaluation config to the others (GAP-TV)."""
    from hsicam.engine import experiments
    from hsicam.engine.experiments import LEARNED_CASSI

    seen = {}

    class Built(Exception):
        pass

    def fake_build(name, cfg, run=None, device="cpu"):
        seen[name] = cfg
        raise Built

    monkeypatch.setattr(experiments, "ensure_trained", lambda *a, **k: None)
    monkeypatch.setattr(experiments, "build_method", fake_build)
    cfg = load_config("quick")
    for name in (*LEARNED_CASSI, "dd-cassi-gaptv"):
        with pytest.raises(Built):
            experiments._baseline_rows(cfg, "quick", tmp_path, [], [], 1, [name])
    for name in LEARNED_CASSI:
        assert seen[name].camera.kind == "dd_cassi" and seen[name].model.consistency.iterations == 0, name
    assert seen["dd-cassi-gaptv"] is cfg


def test_experiment_evaluates_each_camera_with_the_config_it_trained_with(monkeypatch, tmp_path):
    """The cfa-period sweep trains its cameras with the linear step widened to its largest period (15 px at
    quick scale, whose preset has 11): each camera is built for scoring with its own config, or the 15 px
    linear step its training fitted would be refused against the preset's 11 after all five trainings."""
    from hsicam.engine import experiments

    seen = []

    class Built(Exception):
        pass

    def fake_build(name, cfg, run=None, device="cpu"):
        seen.append((Path(run).name, cfg))
        raise Built

    monkeypatch.setattr(experiments, "ensure_trained", lambda *a, **k: None)
    monkeypatch.setattr(experiments, "validation_scenes", lambda cfg: ([], []))
    monkeypatch.setattr(experiments, "build_method", fake_build)
    assert load_config("quick").model.consistency.window_px == 11
    with pytest.raises(Built):
        experiments.run_experiment("cfa-period", "quick", tmp_path / "sweep")
    (run, cfg), = seen
    assert run == "period-3" and cfg.camera.cfa.period == 3 and cfg.model.consistency.window_px == 15


# ------------------------------------------------------------------------------------------------
# The linear step: x + gain · W(y − A x), W per-phase filters (RUN/linear_step.safetensors)
# ------------------------------------------------------------------------------------------------
def test_linear_step_matches_a_dense_matrix_reference():
    """x0 + gain · W r, r = y − A x_e (x_e: x0 extended by K//2 replicated pixels), with A the
    explicit matrix of the valid operator and W applied by the loop reference of phase_linear."""
    from hsicam.models.consistency import linear_consistency_step
    from test_linear_demosaic import _loop_reference

    snap, h, w, origin = _snapshot(3), 6, 7, (2, 1)
    g = torch.Generator().manual_seed(4)
    x0 = torch.rand(1, C, h, w, generator=g, dtype=torch.float64)
    y = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    weight = torch.randn(M * M, C, 3, 3, generator=g, dtype=torch.float64)
    got = linear_consistency_step(snap, y, x0, weight, origin, gain=0.4, psf_energy=1.0)
    a = _dense_valid(snap, h, w, origin)
    r = K // 2
    xe = np.pad(x0[0].numpy(), ((0, 0), (r, r), (r, r)), mode="edge").reshape(-1)
    res = (y.numpy().reshape(-1) - a @ xe).reshape(h, w)
    want = x0[0].numpy() + 0.4 * _loop_reference(res, weight.numpy(), origin)
    np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-10, atol=1e-12)
    # an estimate that explains its measurement is a fixed point, whatever W
    x_true = torch.rand(1, C, h + 2 * r, w + 2 * r, generator=g, dtype=torch.float64)
    x_true[..., :r, :] = x_true[..., r : r + 1, :]  # constant beyond the window: what replication extends
    x_true[..., -r:, :] = x_true[..., -r - 1 : -r, :]
    x_true[..., :, :r] = x_true[..., :, r : r + 1]
    x_true[..., :, -r:] = x_true[..., :, -r - 1 : -r]
    y_true = torch.from_numpy(a @ x_true[0].numpy().reshape(-1)).reshape(1, 1, h, w)
    inner = x_true[..., r:-r, r:-r]
    torch.testing.assert_close(linear_consistency_step(snap, y_true, inner, weight, origin, psf_energy=1.0), inner)


def _linear_system(tiny_config):
    model = CameraSystem.from_config(tiny_config("model.consistency.iterations=1", "model.consistency.kind=linear",
                                                 "model.consistency.window_px=5")).eval()
    m, c = model.camera.code_period, len(model.bands)
    model.linear_step = torch.randn(m * m, c, 5, 5, generator=torch.Generator().manual_seed(9)) * 0.05
    return model


def test_linear_step_tiles_with_the_declared_context_equal_the_whole_image(tiny_config):
    from hsicam.models.consistency import linear_reach_px

    model = _linear_system(tiny_config)
    snap = model.camera.snapshot(nominal=True)
    assert model.context_px == model.net.context_px + linear_reach_px(snap, 5, 1, model.consistency.psf_energy)
    _assert_step_tiles_equal_whole(model, snap)
    model.linear_step = torch.nn.functional.pad(model.linear_step, (2, 2, 2, 2))  # 9×9 filters under window_px 5:
    assert model.context_px == model.net.context_px + linear_reach_px(snap, 9, 1, model.consistency.psf_energy)
    _assert_step_tiles_equal_whole(model, snap)  # the halo follows the filters loaded


def test_linear_step_needs_its_filters_and_checks_its_settings(tiny_config):
    model = _linear_system(tiny_config)
    model.linear_step = None
    with pytest.raises(InputError, match="linear_step.safetensors"):
        model.reconstruct(torch.rand(1, 1, 20, 20))
    for override, match in (("model.consistency.kind=gap", "kind"), ("model.consistency.gain=0", "gain"),
                            ("model.consistency.window_px=4", "window_px")):
        with pytest.raises(ConfigError, match=match):
            tiny_config(override)
    # the flat-field fit needs every CFA phase in the window: refused when the config is read, not
    # after training; without the linear step, or with a window as wide as the period, it is fine
    wide = ("model.consistency.kind=linear", "model.consistency.iterations=1", "camera.cfa.period=13")
    with pytest.raises(ConfigError, match="narrower than the CFA period 13.*at least 13"):
        tiny_config(*wide)
    tiny_config(*wide, "model.consistency.window_px=13")
    tiny_config(*wide[1:], "model.consistency.kind=landweber")


def test_training_with_the_linear_step_fits_and_ships_its_filters(tiny_config, tmp_path, cache_env):
    """A run trained with kind=linear gets RUN/linear_step.safetensors: the least-squares map fitted
    on its training scenes through its optics; load_run reads it and the step uses it."""
    from hsicam.engine.linear_step import fit_linear_map
    from hsicam.engine.train import train
    from hsicam.data.pipeline import scene_dataset, split_dataset
    from hsicam.runs.folder import load_run
    from hsicam.runs.linear_step import LINEAR_STEP_FILE

    cfg = load_config("tiny", ["model.consistency.iterations=1", "model.consistency.kind=linear", "train.epochs=1"])
    train(cfg, tmp_path / "run")
    assert (tmp_path / "run" / LINEAR_STEP_FILE).is_file()
    run_cfg, model = load_run(tmp_path / "run")
    bands = run_cfg.bands.to_bands()
    train_list, _ = split_dataset(run_cfg.data, bands)
    want = fit_linear_map(model, scene_dataset(run_cfg.data, train_list, bands), 11)
    torch.testing.assert_close(model.linear_step, want)
    sensor = torch.rand(1, 1, 30, 30)
    with torch.no_grad():
        lin = model.reconstructor()(sensor)
        model.consistency = tiny_config("model.consistency.iterations=1").model.consistency  # Landweber's
        landweber = model.reconstructor()(sensor)
    assert (lin - landweber).abs().max() > 1e-4


def _dense_spectral_prior(xe: np.ndarray, alpha: float) -> np.ndarray:
    """S = α ŝŝᵀ + I for every pixel of the extended estimate xe (C, H, W), as one matrix on the
    (band-major) flattened cube: ŝ = xe⁺ / |xe⁺| per pixel."""
    c, hh, ww = xe.shape
    s = np.clip(xe, 0, None).reshape(c, -1)
    s = s / np.maximum(np.linalg.norm(s, axis=0, keepdims=True), 1e-300)
    n = hh * ww
    big = np.eye(c * n)
    for p in range(n):
        idx = np.arange(c) * n + p
        big[np.ix_(idx, idx)] += alpha * np.outer(s[:, p], s[:, p])
    return big


@pytest.mark.parametrize("alpha", [0.0, 3.0])
def test_spectral_prior_step_matches_a_dense_matrix_reference(alpha):
    """x_e + S Aᵀ((y − A x_e) ⊘ (A S Aᵀ 𝟙 + λ)), S = α ŝŝᵀ + I per pixel from x_e itself, written with
    explicit matrices; α = 0 is the plain step."""
    snap, h, w, origin = _snapshot(4), 5, 6, (2, 0)
    g = torch.Generator().manual_seed(8)
    x0 = torch.rand(1, C, h, w, generator=g, dtype=torch.float64) - 0.1  # a few negative values: clipped in ŝ
    y = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    got = consistency_step(snap, y, x0, origin, damping=0.05, iterations=1, psf_energy=1.0, spectral_prior=alpha)
    a = _dense_valid(snap, h, w, origin)
    r = K // 2
    xe3 = np.pad(x0[0].numpy(), ((0, 0), (r, r), (r, r)), mode="edge")
    xe = xe3.reshape(-1)
    s = _dense_spectral_prior(xe3, alpha)
    d = a @ (s @ (a.T @ np.ones(h * w))) + 0.05 * _snapshot_lipschitz(snap)
    x1 = xe + s @ (a.T @ ((y.numpy().reshape(-1) - a @ xe) / d))
    want = x1.reshape(C, h + 2 * r, w + 2 * r)[:, r:-r, r:-r]
    np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-10, atol=1e-12)
    if alpha == 0:
        torch.testing.assert_close(got, consistency_step(snap, y, x0, origin, damping=0.05, psf_energy=1.0))


@pytest.mark.parametrize("seed", [3, 9])
def test_spectral_prior_steps_never_grow_the_error_in_the_priors_metric(seed):
    """Noiseless data, the exact operator (``same`` geometry, nothing extended): x − x* is multiplied
    by I − S Aᵀ D⁻¹ A with D = A S Aᵀ 𝟙 + λ ≥ A S Aᵀ, so ‖x − x*‖ in the S⁻¹-norm never grows, for a
    strong prior and a high-contrast CFA. And the prior moves bands that a pixel's filter hardly
    passes: a grey stroke missing from the estimate is restored on every band."""
    snap, truth, y, x0 = _high_contrast_problem(seed, seed + 50, (1, C, 13, 12))
    alpha = 20.0
    xe = x0[0].numpy()
    s_inv = np.linalg.inv(_dense_spectral_prior(xe, alpha))
    prior = spectral_preconditioner(x0, alpha)
    d = snap.A(prior(snap.A_adjoint(torch.ones_like(y)))) + 1e-6 * _snapshot_lipschitz(snap)
    errors, weighted = [], []
    for n in range(5):
        x = consistency_step(snap, y, x0, damping=1e-6, iterations=n, psf_energy=1.0, extend=False, spectral_prior=alpha)
        e = (x - truth)[0].numpy().reshape(-1)
        errors.append(float(e @ s_inv @ e))
        r = y - snap.A(x)
        weighted.append(float((r * r / d).sum()))
    assert all(b <= a * (1 + 1e-12) for a, b in zip(errors, errors[1:])), errors
    assert all(b <= a * (1 + 1e-12) for a, b in zip(weighted, weighted[1:])), weighted
    # one measurement per pixel for C bands: most of the error lies where A cannot see it
    assert errors[-1] < 0.99 * errors[0] and weighted[-1] < 0.6 * weighted[0]
    # a grey cube whose estimate lacks a one-pixel stroke: the prior's step restores more of it on the
    # bands the stroke's pixels barely see than the plain step does
    delta = torch.zeros(C, K, K, dtype=torch.float64)
    delta[:, K // 2, K // 2] = 1.0  # a sharp lens: each pixel sees its own point through its filter
    snap = DOESnapshot(snap.bands, delta, snap.tile, M)
    spectrum = torch.tensor([0.5, 0.6, 0.7], dtype=torch.float64).view(1, C, 1, 1)
    grey = spectrum * torch.ones(1, 1, 13, 12, dtype=torch.float64)
    stroke = grey.clone()
    stroke[..., 6, :] *= 3.0
    y = snap.A(stroke)

    def stroke_error(alpha_):
        x = consistency_step(snap, y, grey, damping=1e-6, iterations=2, psf_energy=1.0, extend=False,
                             spectral_prior=alpha_)
        return float((x - stroke)[..., 4:9, 2:10].norm())

    assert stroke_error(alpha) < 0.3 * stroke_error(0.0)


def test_linear_step_then_landweber_tiles_with_the_declared_context_equal_the_whole_image(tiny_config):
    """kind linear + landweber_after: the linear map's step, then Landweber steps with the spectral
    prior; the halo is the sum of both steps' reaches, and tiles with it equal the whole image."""
    from hsicam.models.consistency import linear_reach_px

    model = _linear_system(tiny_config)
    snap = model.camera.snapshot(nominal=True)
    sensor = torch.rand(1, 1, 30, 30)
    with torch.no_grad():
        linear_only = model.reconstructor()(sensor)
    model.consistency = dataclasses.replace(model.consistency, landweber_after=2, spectral_prior=4.0)
    e = model.consistency.psf_energy
    assert model.context_px == (model.net.context_px + linear_reach_px(snap, 5, 1, e) + reach_px(snap, 2, e))
    _assert_step_tiles_equal_whole(model, snap)
    with torch.no_grad():
        both = model.reconstructor()(sensor)
        net = model.net(sensor, snap, (0, 0))
        want = consistency_step(cut_psf(snap, e), sensor, linear_only, damping=model.consistency.damping,
                                iterations=2, psf_energy=1.0, spectral_prior=4.0)
    assert (both - linear_only).abs().max() > 1e-4 and (linear_only - net).abs().max() > 1e-4
    torch.testing.assert_close(both, want)


@pytest.mark.parametrize("overrides, match", [
    (("model.consistency.kind=linear", "model.consistency.landweber_after=-1"), "landweber_after"),
    (("model.consistency.spectral_prior=-1",), "spectral_prior"),
    (("model.consistency.spectral_prior=inf",), "spectral_prior"),
])
def test_bad_refinement_settings_are_one_clear_error(tiny_config, overrides, match):
    with pytest.raises(ConfigError, match=match):
        tiny_config("model.consistency.iterations=1", *overrides)


def test_kind_landweber_takes_its_own_steps_and_ignores_landweber_after(tiny_config):
    """`--set model.consistency.kind=landweber` on a preset with landweber_after (quick) is the plain
    (or spectral-prior) Landweber step, `iterations` times: landweber_after belongs to kind linear."""
    a = _system(tiny_config, "model.consistency.kind=landweber", "model.consistency.landweber_after=3")
    b = _system(tiny_config, "model.consistency.kind=landweber")
    sensor = torch.rand(1, 1, 20, 20)
    assert a.context_px == b.context_px
    with torch.no_grad():
        torch.testing.assert_close(a.reconstruct(sensor), b.reconstruct(sensor))


# --------------------------------------------------------------------------------------------
# models/consistency.py
# --------------------------------------------------------------------------------------------
def test_steps_with_the_prior_carry_fistas_momentum_schedule(tiny_camera):
    """With a vanishing TV weight the prox is the identity, and the steps with the prior are plain Landweber steps L
    taken from z_k = x_k + β_k (x_k − x_{k−1}), β_k = min(cap, (t_k − 1) / t_{k+1}), t_1 = 1,
    t_{k+1} = (1 + √(1 + 4 t_k²)) / 2 (Beck & Teboulle): rebuilt here from single plain steps."""
    from hsicam.models.consistency import TV_MOMENTUM_MAX, consistency_step

    cam = tiny_camera("camera.doe.init=random", dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        snap = cam.snapshot()
        truth = torch.rand(1, len(cam.bands), 12, 12, generator=g, dtype=torch.float64)
        y = snap.A(truth)
        x0 = torch.rand(1, len(cam.bands), 12, 12, generator=g, dtype=torch.float64)

        def plain(z):
            return consistency_step(snap, y, z, extend=False, psf_energy=1.0)

        got = consistency_step(snap, y, x0, iterations=4, extend=False, psf_energy=1.0, tv_weight=1e-12)
        x, prev, t = x0, x0, 1.0
        for _ in range(4):
            t_next = (1 + math.sqrt(1 + 4 * t * t)) / 2
            beta = min(TV_MOMENTUM_MAX, (t - 1) / t_next)
            x, prev, t = plain(x + beta * (x - prev)), x, t_next
    assert (x - plain(plain(plain(plain(x0))))).abs().max() > 1e-4  # the momentum matters here
    torch.testing.assert_close(got, x, rtol=0, atol=1e-9)
