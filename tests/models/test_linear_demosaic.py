"""The least-squares linear demosaic (one filter per CFA phase and band): against a loop reference,
exact recovery of known filters, the tent as a special case, tiles, optimality on its training
pairs, and the `doe-linear-demosaic` method through the command line."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cli_helpers import assert_clean_error, in_process_error_line, run_cli_in_process
from hsicam.models.demosaic import LinearDemosaicFit, demosaic, phase_linear
from hsicam.sensor import tile_pattern


def _loop_reference(g: np.ndarray, weight: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """x̂[c, i, j] = Σ_uv W[phase(i, j), c, u, v] · g_ext[i + u − r, j + v − r], g extended by
    replicating its border, phase(i, j) = ((i + o₀) mod m)·m + (j + o₁) mod m; written from the
    definition with explicit loops."""
    phases, bands, k, _ = weight.shape
    m, r = int(round(phases ** 0.5)), k // 2
    h, w = g.shape
    out = np.zeros((bands, h, w))
    for i in range(h):
        for j in range(w):
            p = ((i + origin[0]) % m) * m + (j + origin[1]) % m
            for u in range(k):
                for v in range(k):
                    y = min(max(i + u - r, 0), h - 1)
                    x = min(max(j + v - r, 0), w - 1)
                    out[:, i, j] += weight[p, :, u, v] * g[y, x]
    return out


@pytest.mark.parametrize("origin", [(0, 0), (1, 2), (7, 5)])
def test_phase_linear_matches_the_loop_reference(origin):
    gen = torch.Generator().manual_seed(1)
    g = torch.rand(1, 1, 11, 9, generator=gen, dtype=torch.float64)
    weight = torch.randn(9, 2, 5, 5, generator=gen, dtype=torch.float64)  # period 3, 2 bands, 5×5
    got = phase_linear(g, weight, origin)
    np.testing.assert_allclose(got[0].numpy(), _loop_reference(g[0, 0].numpy(), weight.numpy(), origin), atol=1e-12)


def test_fit_recovers_known_filters_exactly():
    """Truth made by known per-phase filters is fitted back exactly (ridge 0, enough samples)."""
    gen = torch.Generator().manual_seed(2)
    weight = torch.randn(16, 3, 5, 5, generator=gen, dtype=torch.float64)
    g = torch.rand(4, 1, 40, 36, generator=gen, dtype=torch.float64)
    fit = LinearDemosaicFit(4, 3, 5, ridge=0.0)
    fit.add(g[:2], phase_linear(g[:2], weight))
    fit.add(g[2:, :, 3:, 1:], phase_linear(g[2:, :, 3:, 1:], weight, (3, 1)), origin=(3, 1))  # windows elsewhere
    torch.testing.assert_close(fit.solve().double(), weight, atol=2e-5, rtol=0)


def test_the_tent_demosaic_is_one_such_linear_map():
    """The tent (weighted-bilinear) demosaic is linear per CFA phase: fitted on its own output it
    is reproduced, and the fitted filters match on a new image."""
    gen = torch.Generator().manual_seed(3)
    m, bands = 4, 5
    tile = torch.rand(bands, m, m, generator=gen, dtype=torch.float64) + 0.05
    tile = tile / tile.sum(0, keepdim=True)

    def tent(g):  # on the image extended by replication (so the border matches phase_linear's)
        r = 3
        ext = F.pad(g, (r, r, r, r), mode="replicate")
        code = tile_pattern(torch.roll(tile, (r, r), (-2, -1)), ext.shape[-2], ext.shape[-1])
        return demosaic(ext, code, 2 * m - 1, "tent")[..., r:-r, r:-r]

    g = torch.rand(2, 1, 32, 28, generator=gen, dtype=torch.float64)
    fit = LinearDemosaicFit(m, bands, 7, ridge=0.0)
    fit.add(g, tent(g))
    new = torch.rand(1, 1, 20, 24, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(phase_linear(new, fit.solve().double()), tent(new), atol=1e-5, rtol=0)


def test_tiles_with_a_halo_equal_the_whole_image():
    gen = torch.Generator().manual_seed(4)
    weight = torch.randn(16, 4, 7, 7, generator=gen)
    g = torch.rand(1, 1, 50, 45, generator=gen)
    whole = phase_linear(g, weight)
    r = 3
    for top, left in ((0, 0), (9, 13), (30, 21)):
        win = g[..., max(top - r, 0) : top + 20 + r, max(left - r, 0) : left + 24 + r]
        origin = (max(top - r, 0), max(left - r, 0))
        part = phase_linear(win, weight, origin)
        a, b = top - origin[0], left - origin[1]
        h, w = min(20, 50 - top), min(24, 45 - left)
        torch.testing.assert_close(part[..., a : a + h, b : b + w], whole[..., top : top + h, left : left + w])


def test_the_fit_is_the_least_squares_optimum_on_its_pairs():
    """No other filters (the fitted ones perturbed, or the tent's) do better on the training pairs."""
    gen = torch.Generator().manual_seed(5)
    g = torch.rand(3, 1, 24, 24, generator=gen, dtype=torch.float64)
    truth = torch.rand(3, 2, 24, 24, generator=gen, dtype=torch.float64) * g  # related to g, not a linear map of it
    fit = LinearDemosaicFit(2, 2, 3, ridge=0.0)
    fit.add(g, truth)
    best = fit.solve().double()
    err = ((phase_linear(g, best) - truth) ** 2).sum()
    for _ in range(5):
        other = best + 0.01 * torch.randn(best.shape, generator=gen, dtype=torch.float64)
        assert ((phase_linear(g, other) - truth) ** 2).sum() > err


def _kkt_reference(fit: LinearDemosaicFit) -> torch.Tensor:
    """The constrained least-squares filters from one dense KKT system: minimise Σ_q ‖X_q w_q − T_q‖²
    subject to S_q w_q = S_0 w_0 for every phase q (all phases' responses to an m-periodic image
    equal), with the tap-to-phase map written here from the definition."""
    m, k, r = fit.period, fit.window, fit.window // 2
    q_n, n, c = m * m, k * k, fit.bands
    select = torch.zeros(q_n, q_n, n, dtype=torch.float64)
    for q in range(q_n):
        for u in range(k):
            for v in range(k):
                p = ((q // m + u - r) % m) * m + (q % m + v - r) % m
                select[q, p, u * k + v] = 1.0
    gram = torch.block_diag(*fit.gram)
    cons = torch.zeros((q_n - 1) * q_n, q_n * n, dtype=torch.float64)
    for q in range(1, q_n):
        cons[(q - 1) * q_n : q * q_n, q * n : (q + 1) * n] = select[q]
        cons[(q - 1) * q_n : q * q_n, :n] = -select[0]
    zeros = torch.zeros(cons.shape[0], cons.shape[0], dtype=torch.float64)
    kkt = torch.cat([torch.cat([gram, cons.T], 1), torch.cat([cons, zeros], 1)])
    rhs = torch.cat([fit.cross.reshape(q_n * n, c), torch.zeros(cons.shape[0], c, dtype=torch.float64)])
    sol = torch.linalg.solve(kkt, rhs)[: q_n * n]
    return sol.reshape(q_n, n, c).transpose(1, 2).reshape(q_n, c, k, k)


@pytest.mark.parametrize("period,window", [(3, 5), (2, 3), (4, 5)])
def test_flat_field_fit_is_the_constrained_least_squares_optimum(period, window):
    """Under the flat-field constraint the fit equals a dense KKT solve of the same problem, and
    an m-periodic sensor image (what a uniform scene gives) comes out uniform in every band."""
    gen = torch.Generator().manual_seed(period * 10 + window)
    g = torch.rand(2, 1, 30, 27, generator=gen, dtype=torch.float64)
    truth = torch.rand(2, 3, 30, 27, generator=gen, dtype=torch.float64) * g
    fit = LinearDemosaicFit(period, 3, window, ridge=0.0, flat_field=True)
    fit.add(g, truth)
    got = fit.solve().double()
    ref = _kkt_reference(fit)
    torch.testing.assert_close(got, ref, atol=1e-5 * float(ref.abs().max()), rtol=0)
    free = LinearDemosaicFit(period, 3, window, ridge=0.0)
    free.gram, free.cross = fit.gram, fit.cross
    unconstrained = free.solve().double()
    err = lambda w: float(((phase_linear(g, w) - truth) ** 2).sum())  # noqa: E731
    assert err(unconstrained) <= err(got) * (1 + 1e-9)  # the constraint costs, never gains, on its own pairs
    periodic = torch.rand(1, 1, period, period, generator=gen, dtype=torch.float64).repeat(1, 1, 12, 12)
    for origin in ((0, 0), (1, 2)):
        flat = phase_linear(periodic, got, origin)[..., window:-window, window:-window]  # away from the border
        assert float((flat - flat.mean((-2, -1), keepdim=True)).abs().max()) < 1e-5 * float(flat.abs().max())
        spread = phase_linear(periodic, unconstrained, origin)[..., window:-window, window:-window]
        assert float((spread - spread.mean((-2, -1), keepdim=True)).abs().max()) > 1e-3 * float(spread.abs().max())


def test_flat_field_fit_recovers_filters_that_obey_it():
    """Truth made by filters that already answer a periodic image uniformly (the KKT projection of
    random filters) is fitted back exactly under the constraint."""
    gen = torch.Generator().manual_seed(7)
    g = torch.rand(3, 1, 36, 33, generator=gen, dtype=torch.float64)
    make = LinearDemosaicFit(3, 2, 5, ridge=0.0, flat_field=True)
    make.add(g, torch.rand(3, 2, 36, 33, generator=gen, dtype=torch.float64))
    weight = _kkt_reference(make)
    fit = LinearDemosaicFit(3, 2, 5, ridge=0.0, flat_field=True)
    fit.add(g, phase_linear(g, weight))
    torch.testing.assert_close(fit.solve().double(), weight, atol=2e-5 * float(weight.abs().max()), rtol=0)


def test_bad_shapes_are_clear_errors():
    with pytest.raises(ValueError, match="sensor image must be"):
        phase_linear(torch.rand(1, 2, 8, 8), torch.rand(4, 3, 3, 3))
    with pytest.raises(ValueError, match="weight must be"):
        phase_linear(torch.rand(1, 1, 8, 8), torch.rand(3, 3, 3, 3))  # 3 phases: not a square
    with pytest.raises(ValueError, match="window odd"):
        LinearDemosaicFit(4, 3, 4)
    with pytest.raises(ValueError, match="ridge"):
        LinearDemosaicFit(4, 3, 5, ridge=float("nan"))
    with pytest.raises(ValueError, match="at least one CFA period"):
        LinearDemosaicFit(9, 3, 7, flat_field=True)
    with pytest.raises(ValueError, match="same pixels"):
        LinearDemosaicFit(4, 3, 5).add(torch.rand(1, 1, 8, 8), torch.rand(1, 3, 8, 9))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    env = {"HSICAM_CACHE": str(tmp_path_factory.mktemp("cache"))}
    d = tmp_path_factory.mktemp("run") / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(d), "--set", "camera.cfa.init=bandpass", env=env)
    assert res.returncode == 0, res.stderr
    return d, env


def test_linear_reference_method_is_fitted_on_the_training_scenes_through_the_runs_optics(run, monkeypatch):
    """`doe-linear-demosaic` applies the filters that the least-squares fit of the run's own
    noise-free captures of the training split gives, and on those scenes it beats the tent."""
    from hsicam.config import load_config
    from hsicam.data.pipeline import scene_dataset, split_dataset
    from hsicam.engine.methods import build_method
    from hsicam.errors import InputError
    from hsicam.models.demosaic import camera_demosaic

    d, env = run
    monkeypatch.setenv("HSICAM_CACHE", env["HSICAM_CACHE"])
    cfg = load_config(d / "config.yaml")
    method = build_method("doe-linear-demosaic", cfg, d)
    bands = cfg.bands.to_bands()
    train, _ = split_dataset(cfg.data, bands)
    scenes = scene_dataset(cfg.data, train, bands)
    assert method.info["window_px"] == 11 and "training_scenes" not in method.info  # fitted at the first reconstruction
    cam = method.camera
    fit = LinearDemosaicFit(cam.code_period, len(cam.bands), 11, 1e-6, flat_field=True)
    se_lin = se_tent = 0.0
    with torch.no_grad():
        for i in range(len(train)):
            s = scenes[i][None]
            y, t = cam.A(s), method.target(s)
            fit.add(y, t)
            se_lin += float(((method.reconstruct(y) - t) ** 2).sum())
            se_tent += float(((camera_demosaic(cam, y, kernel="tent") - t) ** 2).sum())
        y = cam.A(scenes[0][None])
        torch.testing.assert_close(method.reconstruct(y), phase_linear(y, fit.solve()), atol=1e-5, rtol=1e-4)
        # flat-field constraint: a uniform scene's image through the run's optics comes out uniform
        uniform = scenes[0][None].mean((-2, -1), keepdim=True).expand_as(scenes[0][None]).contiguous()
        flat = method.reconstruct(cam.A(uniform))[..., 6:-6, 6:-6]
        assert float((flat - flat.mean((-2, -1), keepdim=True)).abs().max()) < 1e-4 * float(flat.abs().max())
    assert se_lin < se_tent
    assert method.info["training_scenes"] == len(train)
    with pytest.raises(InputError, match="needs --run"):
        build_method("doe-linear-demosaic", cfg)


def test_linear_reference_through_the_cli_and_its_errors(run, tmp_path):
    d, env = run
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(d), "--method", "doe-linear-demosaic", "--out", str(out), env=env)
    assert res.returncode == 0, res.stderr
    assert "doe-linear-demosaic: mean PSNR" in res.stdout
    summary = json.loads((out / "results.json").read_text())
    assert summary["method"] == "doe-linear-demosaic" and np.isfinite(summary["mean"]["psnr"])
    bad = run_cli_in_process("evaluate", "--method", "doe-linear-demosaic", "--out", str(tmp_path / "bad"), env=env)
    assert_clean_error(bad, "needs --run")


def test_linear_reference_fit_is_not_timed_as_the_first_scenes_reconstruction(run, monkeypatch):
    """The deferred fit ran inside the first scene's timed reconstruction, so its runtime_s (and the
    mean's) held the training split's generation and imaging: minutes for the standard camera. It is
    the method's ``prepare`` now, run after the scenes are checked and before any clock starts."""
    from hsicam.config import load_config
    from hsicam.data.pipeline import scene_dataset, split_dataset
    from hsicam.engine import evaluate, methods

    d, env = run
    monkeypatch.setenv("HSICAM_CACHE", env["HSICAM_CACHE"])
    events = []
    real_fit = methods.fit_linear_map
    monkeypatch.setattr(methods, "fit_linear_map", lambda *a, **k: events.append("fit") or real_fit(*a, **k))
    clock = types.SimpleNamespace(perf_counter=lambda: events.append("clock") or 0.0)
    monkeypatch.setattr(evaluate, "time", clock)
    cfg = load_config(d / "config.yaml")
    method = methods.build_method("doe-linear-demosaic", cfg, d)
    assert events == [] and method.prepare is not None
    bands = cfg.bands.to_bands()
    _, val = split_dataset(cfg.data, bands)
    names = [f"s{i}" for i in range(len(val))]
    results = evaluate.evaluate_method(method, scene_dataset(cfg.data, val, bands), names)
    assert events[0] == "fit" and events.count("fit") == 1, events
    assert [r.runtime_s for r in results] == [0.0] * len(val)
    assert method.info["training_scenes"] == len(split_dataset(cfg.data, bands)[0])


def test_linear_reference_refuses_small_scenes_before_making_its_training_split(run, tmp_path, monkeypatch, capsys):
    """Scenes too small to score (here 20 px, under the run's `valid` margin plus SSIM's window) are
    refused before the method's fit: the training split is neither made (generated, for the synthetic
    data: 2.5 GB for the standard camera) nor imaged, and no --out is written. The fit came first."""
    from hsicam.config import load_config
    from hsicam.data.formats import write_cube_h5
    from hsicam.engine import linear_step, methods

    d, env = run
    monkeypatch.setenv("HSICAM_CACHE", str(tmp_path / "empty-cache"))  # a split made would generate here

    def never(*args, **kwargs):
        raise AssertionError("the training split was made before the scenes were checked")

    monkeypatch.setattr(methods, "split_dataset", never)
    monkeypatch.setattr(methods, "fit_linear_map", never)
    monkeypatch.setattr(linear_step, "fit_linear_map", never)
    data = tmp_path / "small"
    bands = load_config(d / "config.yaml").bands.to_bands()
    write_cube_h5(data / "a.h5", np.random.default_rng(0).uniform(0.1, 0.9, (len(bands), 20, 20)).astype(np.float32), bands)
    out = tmp_path / "ev"
    line = in_process_error_line(capsys, ["evaluate", "--run", d, "--method", "doe-linear-demosaic", "--data", data,
                                          "--out", out])
    assert f"{data / 'a.h5'}: scene of 20×20 px leaves" in line and "to score" in line, line
    assert not out.exists() and not (tmp_path / "empty-cache").exists()


def test_linear_reference_needs_a_cfa_camera():
    from hsicam.config import load_config
    from hsicam.engine.methods import linear_demosaic_reference
    from hsicam.models import CameraSystem

    with pytest.raises(ValueError, match="per-band sensor code"):
        linear_demosaic_reference(CameraSystem.from_config(load_config("dd_cassi_rdn")), [torch.rand(31, 8, 8)])
    with pytest.raises(ValueError, match="at least one training scene"):
        linear_demosaic_reference(CameraSystem.from_config(load_config("tiny")), [])


def test_linear_reference_widens_its_window_to_a_wide_cfa_period(tiny_config):
    """A CFA period wider than the default 11 px window (13 here): the flat-field fit needs every
    phase in the window, so the reference fits 13×13 filters instead of failing."""
    from hsicam.engine.methods import linear_demosaic_reference
    from hsicam.models import CameraSystem

    model = CameraSystem.from_config(tiny_config("camera.cfa.period=13", "camera.cfa.init=bandpass"))
    k = model.camera.kernel_px
    scenes = [torch.rand(len(model.bands), k + 40, k + 40, generator=torch.Generator().manual_seed(i)) for i in range(2)]
    method = linear_demosaic_reference(model, scenes)
    assert method.info["window_px"] == 13 and method.info["flat_field"]
    with torch.no_grad():
        y = model.camera.A(scenes[0][None])
        assert method.reconstruct(y).shape == (1, len(model.bands), *y.shape[-2:])
