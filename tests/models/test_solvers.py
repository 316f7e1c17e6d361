"""Baseline solvers: GAP projection, TV, GAP-TV, DeSCI (block matching, WNNM), Choi ADMM, the baselines config
section, the Choi prior's settings on the command line. (The methods built from them, the Choi prior's folder and
the experiments' CASSI rows are in engine/test_baseline_methods.py; diag(ΦΦᵀ) of the CASSI cameras in
cameras/test_cassi.py.)"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml

from cassi_reference import cassi_bands as cassi
from cli_helpers import assert_clean_error, run_cli_in_process
from hsicam.config import load_config
from hsicam.engine.methods import build_method
from hsicam.engine.prior import load_prior
from hsicam.errors import ConfigError, InputError
from hsicam.metrics import psnr_per_band
from hsicam.models.priors import SpectralAutoencoder
from hsicam.solvers.choi import admm_prior
from hsicam.solvers.common import gap_projection, total_variation, tv_denoise
from hsicam.config import BaselinesConfig, ChoiConfig
from hsicam.solvers.desci import (block_matching, desci, desci_settings, reference_positions, spectral_features,
                                  wnnm_denoise, wnnm_shrink)
from hsicam.solvers.gaptv import gap_tv


def piecewise_constant_cube(c: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    """Rectangles and discs, each with its own smooth spectrum, on a background: (1, C, H, W)."""
    g = np.random.default_rng(seed)
    lam = np.linspace(0, 1, c)

    def spectrum():
        a, b, m = g.uniform(0.1, 0.9), g.uniform(-0.5, 0.5), g.uniform(0, 1)
        return np.clip(a + b * (lam - m) + 0.2 * np.sin(3 * lam + g.uniform(0, 6)), 0.02, 1)

    cube = np.tile(spectrum()[:, None, None], (1, h, w))
    yy, xx = np.mgrid[:h, :w]
    for _ in range(6):
        s = spectrum()[:, None, None]
        if g.random() < 0.5:
            y0, x0 = g.integers(0, h - 6), g.integers(0, w - 6)
            mask = (yy >= y0) & (yy < y0 + g.integers(5, h // 2)) & (xx >= x0) & (xx < x0 + g.integers(5, w // 2))
        else:
            cy, cx, r = g.uniform(0, h), g.uniform(0, w), g.uniform(3, h / 3)
            mask = (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
        cube = np.where(mask[None], s, cube)
    return torch.from_numpy(cube)[None]


def textured_cube(c: int, h: int, w: int) -> torch.Tensor:
    """Repeating texture (gratings and a checkerboard) with smooth spectra: non-local self-similarity."""
    lam = np.linspace(0, 1, c)[:, None, None]
    yy, xx = np.mgrid[:h, :w].astype(float)
    a = 0.5 + 0.5 * np.sin(2 * np.pi * (xx * 0.15 + yy * 0.05))
    b = ((xx // 4 + yy // 4) % 2).astype(float)
    s1 = 0.3 + 0.6 * lam
    s2 = 0.8 - 0.5 * lam
    s3 = 0.5 + 0.3 * np.cos(4 * lam)
    cube = 0.45 * a[None] * s1 + 0.35 * b[None] * s2 + 0.2 * s3 * (yy[None] < h / 2)
    return torch.from_numpy(cube)[None]


# --------------------------------------------------------------------------------------------
# GAP pieces
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
def test_gap_projection_is_feasible_and_a_projection(kind):
    cam = cassi(kind, 6)
    g = torch.Generator().manual_seed(0)
    truth = torch.rand(1, 6, 10, 12, generator=g, dtype=torch.float64)
    y = cam.A(truth)
    phi = cam.gram_diagonal(y)
    x = torch.rand(1, 6, 10, 12, generator=g, dtype=torch.float64)
    p = gap_projection(cam, x, y, phi)
    torch.testing.assert_close(cam.A(p), y)
    torch.testing.assert_close(gap_projection(cam, p, y, phi), p)  # idempotent
    # the projection is the closest feasible point: x − p ⟂ (truth − p) (both feasible)
    assert abs(float(((x - p) * (truth - p)).sum())) < 1e-9


def test_tv_denoise_matches_scikit_image_at_convergence():
    skimage = pytest.importorskip("skimage.restoration")
    g = np.random.default_rng(0)
    img = np.kron(g.random((4, 4)), np.ones((8, 8))) + 0.1 * g.standard_normal((32, 32))
    ref = skimage.denoise_tv_chambolle(img, weight=0.1, eps=1e-10, max_num_iter=5000)
    ours = tv_denoise(torch.from_numpy(img)[None, None], 0.1, iterations=5000)[0, 0].numpy()
    np.testing.assert_allclose(ours, ref, atol=2e-3)


def test_tv_denoise_lowers_the_tv_objective():
    f = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    u = tv_denoise(f, 0.05, 20)

    def obj(v):
        return 0.5 * (v - f).square().flatten(1).sum(1) + 0.05 * total_variation(v)

    assert torch.all(obj(u) < obj(f))
    assert torch.equal(tv_denoise(f, 0.0, 5), f)


# --------------------------------------------------------------------------------------------
# GAP-TV
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("accelerate", (True, False))
@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
def test_gap_tv_lowers_the_error_on_a_piecewise_constant_cube(accelerate, kind):
    cam = cassi(kind, 8)
    truth = piecewise_constant_cube(8, 40, 40, seed=2)
    y = cam.A(truth)
    start = cam.A_adjoint(y / cam.gram_diagonal(y))
    x, info = gap_tv(cam, y, iterations=60, tv_weight=0.01, accelerate=accelerate, return_info=True)
    assert x.shape == truth.shape
    p0, p1 = float(psnr_per_band(start, truth)), float(psnr_per_band(x, truth))
    assert p1 > p0 + 8, (p0, p1)
    assert info.residual[-1] < 0.05 and info.iterations == 60


def test_gap_tv_float32_and_batch():
    cam = cassi("dd_cassi", 8, dtype=torch.float32)
    truth = torch.cat([piecewise_constant_cube(8, 24, 24, 0), piecewise_constant_cube(8, 24, 24, 1)]).float()
    x = gap_tv(cam, cam.A(truth), iterations=20)
    assert x.dtype == torch.float32 and x.shape == truth.shape
    single = gap_tv(cam, cam.A(truth[1:]), iterations=20)
    torch.testing.assert_close(x[1:], single, rtol=1e-4, atol=1e-5)


def test_solver_input_errors():
    cam = cassi("dd_cassi", 8)
    with pytest.raises(InputError, match="B, 1, H, W"):
        gap_tv(cam, torch.rand(1, 2, 8, 8, dtype=torch.float64))
    with pytest.raises(InputError, match="smaller than the patch"):
        desci(cam, torch.rand(1, 1, 4, 4, dtype=torch.float64), desci_settings("fast", init_iterations=1))
    with pytest.raises(InputError, match="preset"):
        desci_settings("slow")
    # reference patches every 20 px of 4 px left 68 % of the cube at exactly 0 (probe 23)
    with pytest.raises(InputError, match=r"step 20 is larger than patch 4: the pixels between reference patches"):
        desci_settings("fast", patch=4, step=20)
    assert desci_settings("fast", patch=4, step=4).step == 4


# --------------------------------------------------------------------------------------------
# DeSCI
# --------------------------------------------------------------------------------------------
def _brute_force_distances(img: torch.Tensor, p: int, i: int, j: int, search: int) -> dict[int, float]:
    """Squared distance of every in-image patch within ±search of the reference at (i, j), by flat
    top-left index a·W + b."""
    _, h, w = img.shape
    ref = img[:, i : i + p, j : j + p]
    return {a * w + b: float((img[:, a : a + p, b : b + p] - ref).square().sum())
            for a in range(max(0, i - search), min(h - p + 1, i + search + 1))
            for b in range(max(0, j - search), min(w - p + 1, j + search + 1))}


def _check_matches(img: torch.Tensor, p: int, rows, cols, search: int, got: torch.Tensor) -> None:
    """Each row of ``got`` holds K in-image patches of its reference with the K smallest distances,
    the reference first."""
    w = img.shape[2]
    refs = [(i, j) for i in rows.tolist() for j in cols.tolist()]
    assert got.shape[0] == len(refs)
    for r, (i, j) in enumerate(refs):
        d = _brute_force_distances(img, p, i, j, search)
        assert set(got[r].tolist()) <= set(d), (i, j, got[r].tolist())  # in the image, no wrapped rows
        assert len(set(got[r].tolist())) == got.shape[1]  # K different patches
        np.testing.assert_allclose(sorted(d[int(q)] for q in got[r]), sorted(d.values())[: got.shape[1]],
                                   rtol=1e-9, atol=1e-12)
        assert int(got[r, 0]) == i * w + j  # the reference itself comes first


def test_block_matching_agrees_with_brute_force():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(3, 20, 22, generator=g, dtype=torch.float64)
    p, search, k = 4, 3, 6
    rows, cols = reference_positions(20, p, 5), reference_positions(22, p, 5)
    got = block_matching(img, p, rows, cols, search, k)
    assert got.shape[1] == k
    _check_matches(img, p, rows, cols, search, got)
    assert reference_positions(20, 4, 5).tolist() == [0, 5, 10, 15, 16]


@pytest.mark.parametrize("hw", [(8, 8), (7, 12), (40, 7)])
def test_block_matching_on_images_with_fewer_patch_positions_than_k(hw):
    """A 6 px patch fits 3 × 3 times in 8 × 8 px, fewer than K = 24: K shrinks to what every
    reference has in the image (before: indices past the image, IndexError, or patches wrapping
    into the next row at 40 × 7), and DeSCI runs."""
    h, w = hw
    g = torch.Generator().manual_seed(0)
    img = torch.rand(4, h, w, generator=g, dtype=torch.float64)
    s = desci_settings("fast")  # patch 6, step 4, search 10, K 24
    rows, cols = reference_positions(h, s.patch, s.step), reference_positions(w, s.patch, s.step)
    got = block_matching(img, s.patch, rows, cols, s.search, s.group)
    fewest = min(len(_brute_force_distances(img, s.patch, i, j, s.search)) for i in rows.tolist() for j in cols.tolist())
    _check_matches(img, s.patch, rows, cols, s.search, got)
    assert got.shape[1] == min(s.group, fewest) < s.group
    den, _ = wnnm_denoise(img, 0.05, s)
    assert den.shape == img.shape and torch.isfinite(den).all()
    cam = cassi("dd_cassi", 8)
    truth = torch.rand(1, 8, h, w, generator=g, dtype=torch.float64)
    x = desci(cam, cam.A(truth), desci_settings("fast", sigmas=[0.05], iterations=[2], init_iterations=3))
    assert x.shape == truth.shape and torch.isfinite(x).all()


def test_wnnm_keeps_a_constant_cube_and_every_reference_leads_its_group():
    """In flat regions every candidate ties with the reference at distance 0; the reference must
    still lead its group, or pixels no chosen patch covers come out as 0 (before: 86 such pixels on
    a constant 0.5 cube)."""
    s = desci_settings("fast")
    for cube in (torch.full((8, 32, 32), 0.5, dtype=torch.float64), piecewise_constant_cube(8, 48, 48, seed=2)[0]):
        _, h, w = cube.shape
        den, matches = wnnm_denoise(cube, 0.05, s)
        rows, cols = reference_positions(h, s.patch, s.step), reference_positions(w, s.patch, s.step)
        torch.testing.assert_close(matches[:, 0], (rows[:, None] * w + cols[None, :]).reshape(-1))
        assert not (den == 0).all(0).any()
    torch.testing.assert_close(wnnm_denoise(torch.full((8, 32, 32), 0.5, dtype=torch.float64), 0.05, s)[0],
                               torch.full((8, 32, 32), 0.5, dtype=torch.float64))


def test_spectral_features_keep_the_leading_principal_components():
    """On a cube of spectral rank 2 (6 bands) the 2 leading components keep all of it: the features
    have the cube's pixel Gram matrix (so block-matching distances are exact), and the leading one
    alone is ± the projection on the dominant spectrum."""
    g = torch.Generator().manual_seed(0)
    basis, _ = torch.linalg.qr(torch.randn(6, 2, generator=g, dtype=torch.float64))  # orthonormal spectra
    maps = torch.randn(2, 10 * 12, generator=g, dtype=torch.float64) * torch.tensor([[3.0], [1.0]])
    cube = (basis @ maps).reshape(6, 10, 12)
    f = spectral_features(cube, 2).reshape(2, -1)
    flat = cube.reshape(6, -1)
    torch.testing.assert_close(f.T @ f, flat.T @ flat)
    lead = spectral_features(cube, 1).reshape(-1)
    dominant = torch.linalg.svd(flat, full_matrices=False).U[:, 0] @ flat  # the dominant spectrum's map
    torch.testing.assert_close(lead.abs(), dominant.abs())
    assert spectral_features(cube, None) is cube and spectral_features(cube, 6) is cube


def test_accelerated_desci_fits_the_measurement_better_than_plain_gap():
    """Accelerated GAP adds the accumulated residual back after each WNNM step, so from the same
    start it ends far closer to Φx = y than plain GAP (measured: 0.002 against 0.03 on this scene)."""
    cam = cassi("dd_cassi", 8)
    truth = textured_cube(8, 24, 24)
    y = cam.A(truth)
    x0 = cam.A_adjoint(y / cam.gram_diagonal(y))
    res = {}
    for acc in (True, False):
        s = desci_settings("fast", patch=4, step=2, search=4, group=8, sigmas=[0.05], iterations=[6], accelerate=acc)
        _, info = desci(cam, y, s, x0=x0, return_info=True)
        res[acc] = info.residual
    assert all(a < 0.5 * b for a, b in zip(res[True][1:], res[False][1:])), res


def test_wnnm_shrink_is_the_reweighting_fixed_point():
    s = torch.linspace(0, 5, 101, dtype=torch.float64)
    w, eps = 1.5, 1e-8
    x = wnnm_shrink(s, w, eps)
    big = (s + eps) ** 2 > 4 * w
    torch.testing.assert_close(x[big], s[big] - w / (x[big] + eps))  # x = s − w / (x + ε)
    assert torch.all(x[~big] == 0) and torch.all(x <= s)


def test_wnnm_denoiser_removes_noise_on_a_texture():
    clean = textured_cube(6, 32, 32)[0]
    g = torch.Generator().manual_seed(0)
    noisy = clean + 0.05 * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    s = desci_settings("fast", patch=4, step=2, search=8, group=24)
    den, matches = wnnm_denoise(noisy, 0.05, s)
    assert matches.shape[1] == 24
    assert float(psnr_per_band(den[None], clean[None])) > float(psnr_per_band(noisy[None], clean[None])) + 3


def test_desci_beats_gap_tv_on_a_textured_scene():
    cam = cassi("dd_cassi", 8)
    truth = textured_cube(8, 32, 32)
    y = cam.A(truth)
    base = gap_tv(cam, y, iterations=40, tv_weight=0.01)
    s = desci_settings("fast", patch=4, step=2, search=6, group=16, sigmas=[0.05, 0.03, 0.02], iterations=[5, 5, 5],
                       match_every=2, init_iterations=40)
    x, info = desci(cam, y, s, return_info=True)
    p_tv, p_de = float(psnr_per_band(base, truth)), float(psnr_per_band(x, truth))
    assert p_de > p_tv + 1.0, (p_tv, p_de)
    assert info.iterations == 15 and info.runtime_s > 0


# --------------------------------------------------------------------------------------------
# Choi et al.: autoencoder prior + ADMM
# --------------------------------------------------------------------------------------------
def _tiny_prior(c: int, steps: int = 60, size: int = 12) -> SpectralAutoencoder:
    """A small autoencoder (8 features, 2 + 2 layers) trained ``steps`` steps as a denoiser of
    piecewise-constant cubes."""
    torch.manual_seed(0)
    ae = SpectralAutoencoder(c, 8, 2 * c, layers=2).double()
    opt = torch.optim.Adam(ae.parameters(), lr=3e-3)
    data = torch.cat([piecewise_constant_cube(c, size, size, s) for s in range(8)])
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        noisy = data + 0.05 * torch.randn(data.shape, generator=g, dtype=data.dtype)
        loss = F.mse_loss(ae(noisy), data)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return ae.requires_grad_(False).eval()


@pytest.mark.parametrize("bands,layers", [(1, 2), (7, 3), (31, 6)])
def test_spectral_autoencoder_shapes(bands, layers):
    """Any band count, odd sizes: the code is (B, latent, H, W) at full resolution, R(x) has x's shape,
    and the untrained prior is the identity (clean cubes are its fixed points from the start)."""
    ae = SpectralAutoencoder(bands, 8, 16, layers=layers)
    x = torch.rand(2, bands, 9, 13)
    code = ae.encode(x)
    assert code.shape == (2, 16, 9, 13)
    assert ae.decode(code).shape == x.shape and ae(x).shape == x.shape
    assert torch.equal(ae(x), x)
    assert sum(isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3) for m in ae.modules()) == 2 * layers
    with pytest.raises(ValueError):
        SpectralAutoencoder(bands, 8, 16, layers=1)


@pytest.mark.parametrize("bands,features,latent,layers", [(1, 1, 1, 2), (7, 8, 16, 3), (5, 3, 9, 4), (31, 64, 64, 6)])
def test_the_prior_parameter_count_is_the_built_autoencoders(bands, features, latent, layers):
    """The closed form the memory check uses equals the built autoencoder's parameter count, and
    build_prior builds the ``baselines.choi`` sizes it counts."""
    from hsicam.models.priors import autoencoder_parameter_count, build_prior

    ae = SpectralAutoencoder(bands, features, latent, layers=layers)
    assert autoencoder_parameter_count(bands, features, latent, layers) == sum(p.numel() for p in ae.parameters())
    built = build_prior(ChoiConfig(features=features, latent=latent), bands)
    assert autoencoder_parameter_count(bands, features, latent) == sum(p.numel() for p in built.parameters())


def _budget_mb(nbytes: int) -> str:
    return repr(nbytes / 2**20)  # exact: a whole number of bytes over 2^20 is a float with 20 fraction bits


def test_a_prior_is_refused_exactly_when_its_weights_or_its_training_exceed_the_budget(monkeypatch):
    """Loading a prior needs its weights (4 bytes a parameter), training it 16 (weight, gradient, Adam's
    two moments): the same check and message as a reconstruction network's."""
    from hsicam.engine.tasks import PriorTask
    from hsicam.models.priors import autoencoder_parameter_count, build_prior

    cfg = load_config("tiny", ["baselines.choi.features=4", "baselines.choi.latent=2"])
    settings, bands = cfg.baselines.choi, len(cfg.bands.to_bands())
    n = autoencoder_parameter_count(bands, 4, 2)
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(4 * n))
    build_prior(settings, bands)  # the weights fit exactly
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(4 * n - 1))
    with pytest.raises(ConfigError, match=r"^baselines.choi \(features=4, latent=2\) is a network of .* whose weights "
                                          r"need .* \(4 bytes a parameter\), more than the memory budget"):
        build_prior(settings, bands)
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(16 * n))
    PriorTask(cfg, settings)  # training fits exactly
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", _budget_mb(16 * n - 1))
    with pytest.raises(ConfigError, match=r"whose training needs .* \(16 bytes a parameter: weight, gradient, Adam's "
                                          r"two moments\)"):
        PriorTask(cfg, settings)


def test_an_absurd_prior_is_one_config_error_before_anything_is_built(monkeypatch, tmp_path, capsys):
    """``baselines.choi.features=1000000000`` built a 6 + 6 layer autoencoder of ~10^20 parameters (torch's
    allocation error, or the machine's memory); now train-prior and loading a prior folder refuse it in one
    line naming the ``baselines.choi`` sizes, the estimate and the budget, and the autoencoder is never built."""
    from cli_helpers import in_process_error_line
    from hsicam.engine.tasks import PriorTask
    from hsicam.models import priors

    def never(*args, **kwargs):
        raise AssertionError("the autoencoder was built")

    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "1024")
    monkeypatch.setattr(priors, "SpectralAutoencoder", never)
    cfg = load_config("tiny", ["baselines.choi.features=1000000000"])
    bands = len(cfg.bands.to_bands())
    with pytest.raises(ConfigError) as info:
        PriorTask(cfg, cfg.baselines.choi)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"baselines.choi (features=1000000000, latent=64) is a network of 7.2e+19 parameters for "
                          f"{bands} bands, whose training needs ")
    assert msg.endswith("more than the memory budget of 1 GiB; make these sizes smaller, or raise "
                        "HSICAM_MEMORY_BUDGET_MB (MiB)")
    out = tmp_path / "prior"
    line = in_process_error_line(capsys, ["baseline", "train-prior", "--config", "tiny", "--out", out,
                                          "--set", "baselines.choi.features=1000000000"])
    assert line == f"hsicam: error: {msg}"
    assert not out.exists()
    # a prior folder whose prior.yaml asks for such sizes (evaluate --method dd-cassi-choi --run it)
    folder = tmp_path / "absurd"
    folder.mkdir()
    (folder / "prior.yaml").write_text(yaml.safe_dump(dataclasses.asdict(ChoiConfig(features=10**9))))
    (folder / "prior.safetensors").write_bytes(b"")
    with pytest.raises(ConfigError, match=r"^baselines.choi \(features=1000000000, latent=64\) .* whose weights need "):
        load_prior(folder, cfg.bands.to_bands())


def test_trained_prior_denoises_better_than_the_untrained_one():
    """A few training steps make R a denoiser: on a held-out noisy cube R(x + n) is closer to x than
    the untrained R (the identity) leaves it, and a clean cube stays close to a fixed point."""
    c = 6
    truth = piecewise_constant_cube(c, 16, 16, seed=21)
    noisy = truth + 0.05 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(5), dtype=truth.dtype)
    untrained = SpectralAutoencoder(c, 8, 2 * c, layers=2).double()
    trained = _tiny_prior(c, steps=200, size=16)
    with torch.no_grad():
        err_untrained = float((untrained(noisy) - truth).square().mean())
        err_trained = float((trained(noisy) - truth).square().mean())
        err_clean = float((trained(truth) - truth).square().mean())
    # (slow: the decoder's last layer starts at zero, R = identity; measured 0.91)
    assert err_trained < 0.95 * err_untrained, (err_trained, err_untrained)
    assert err_clean < err_untrained


def _admm_problem(size: int, seed: int):
    """(a 6-band DD-CASSI camera, a tiny trained prior, a piecewise-constant truth of ``size``² px, its capture)."""
    cam = cassi("dd_cassi", 6)
    truth = piecewise_constant_cube(6, size, size, seed=seed)
    return cam, _tiny_prior(6), truth, cam.A(truth)


def test_admm_decreases_the_residual_and_the_objective():
    """On a small fixed DD-CASSI camera: from x = 0 the ADMM lowers ‖Φx − y‖ and the objective, the
    objective decreases from the first iterations on (up to 1 %), the splitting closes; from the
    minimum-norm start (which fits y exactly) the objective decreases and the cube improves."""
    cam, prior, truth, y = _admm_problem(24, 11)
    s = ChoiConfig(iterations=40, rho=1.0, rho_growth=1.05, prior_weight=0.5, tv_weight=0.002, inner_steps=2,
                   init_iterations=0)
    _, info = admm_prior(cam, y, prior, s, x0=torch.zeros_like(truth), return_info=True)
    obj, res = info.objective, info.residual
    assert len(obj) == 41 and len(res) == 40
    assert cam.relative_residual(torch.zeros_like(truth), y) == pytest.approx(1.0)
    assert res[-1] < 0.02 and obj[-1] < 0.05 * obj[0], (res, obj)
    assert all(b <= a * 1.01 for a, b in zip(obj[5:], obj[6:])), obj
    primal = info.extra["primal_residual"]
    assert primal[-1] < 0.01 * primal[0] and primal[-1] < 1e-3
    x, info = admm_prior(cam, y, prior, s, return_info=True)
    obj = info.objective
    assert obj[-1] < 0.95 * obj[0] and all(b <= a * 1.01 for a, b in zip(obj, obj[1:])), obj
    start = cam.A_adjoint(y / cam.gram_diagonal(y))
    assert float(psnr_per_band(x, truth)) > float(psnr_per_band(start, truth)) + 0.5


def test_admm_runs_under_no_grad_and_in_float32():
    cam = cassi("dd_cassi", 6, dtype=torch.float32)
    prior = _tiny_prior(6)  # float64 prior on float32 data
    truth = piecewise_constant_cube(6, 16, 16, seed=3).float()
    with torch.no_grad():
        x = admm_prior(cam, cam.A(truth), prior, ChoiConfig(iterations=3, init_iterations=2))
    assert x.dtype == torch.float32 and x.shape == truth.shape


def test_admm_starts_from_gap_tv_with_the_given_tv_weight():
    """With no ADMM iterations the result is the start: GAP-TV at ``init_tv_weight`` (before: always
    the class default 0.01, whatever the GAP-TV baseline was set to)."""
    cam = cassi("dd_cassi", 6)
    prior = torch.nn.Conv2d(6, 6, 1).double()  # not run: no ADMM iterations
    y = cam.A(piecewise_constant_cube(6, 16, 16, seed=5))
    s = ChoiConfig(iterations=0, init_iterations=5)
    x, info = admm_prior(cam, y, prior, s, return_info=True, init_tv_weight=0.05)
    torch.testing.assert_close(x, gap_tv(cam, y, 5, 0.05))
    assert not torch.allclose(x, gap_tv(cam, y, 5, 0.01))  # the weight matters on this scene
    assert info.extra["init_tv_weight"] == 0.05
    with pytest.raises(InputError, match="init_tv_weight must be a finite number >= 0, got -1"):
        admm_prior(cam, y, prior, s, init_tv_weight=-1.0)


def test_the_choi_method_starts_from_the_configured_gap_tv_baseline(monkeypatch, tmp_path):
    """dd-cassi-choi passes ``baselines.gaptv.tv_weight`` to its GAP-TV start and records it."""
    import hsicam.engine.methods as methods

    monkeypatch.setattr(methods, "load_prior",  # a stand-in prior: never run with no ADMM iterations
                        lambda run, b, device="cpu": (torch.nn.Conv2d(len(b), len(b), 1).double(), ChoiConfig()))
    cfg = load_config("tiny", ["baselines.gaptv.tv_weight=0.05", "baselines.choi.iterations=0",
                               "baselines.choi.init_iterations=5"])
    method = build_method("dd-cassi-choi", cfg, tmp_path)
    g = torch.Generator().manual_seed(0)
    cam = method.camera.to(torch.float64)
    truth = torch.rand(1, len(cam.bands), 24, 24, generator=g, dtype=torch.float64)
    y = cam.A(truth)
    torch.testing.assert_close(method.reconstruct(y), gap_tv(cam, y, 5, 0.05))
    assert method.info["init_tv_weight"] == 0.05


@pytest.mark.parametrize("own", [None, 0.2])
def test_the_desci_method_starts_from_the_configured_gap_tv_baseline(own):
    """dd-cassi-desci's GAP-TV start takes ``baselines.gaptv.tv_weight`` (as Choi's does) unless
    ``baselines.desci.init_tv_weight`` is set; no DeSCI iteration runs, so the result is the start."""
    sets = ["baselines.gaptv.tv_weight=0.05", "baselines.desci.iterations=[0]", "baselines.desci.sigmas=[10]",
            "baselines.desci.init_iterations=5"]
    if own is not None:
        sets.append(f"baselines.desci.init_tv_weight={own}")
    method = build_method("dd-cassi-desci", load_config("tiny", sets))
    weight = 0.05 if own is None else own
    assert method.info["init_tv_weight"] == weight
    g = torch.Generator().manual_seed(0)
    cam = method.camera.to(torch.float64)
    truth = torch.rand(1, len(cam.bands), 24, 24, generator=g, dtype=torch.float64)
    y = cam.A(truth)
    expected = gap_tv(cam, y, 5, weight, accelerate=method.info["accelerate"])
    torch.testing.assert_close(method.reconstruct(y), expected)


# --------------------------------------------------------------------------------------------
# Config section
# --------------------------------------------------------------------------------------------
def test_baselines_config_section():
    cfg = load_config("tiny", ["baselines.desci.preset=full", "baselines.gaptv.iterations=7",
                                        "baselines.desci.sigmas=[0.1, 0.05]", "baselines.desci.iterations=[3, 2]"])
    assert isinstance(cfg.baselines, BaselinesConfig) and cfg.baselines.choi is None  # choi: from the prior folder
    assert cfg.baselines.gaptv.iterations == 7
    assert cfg.baselines.desci.overrides() == {"sigmas": [0.1, 0.05], "iterations": [3, 2]}
    s = desci_settings(cfg.baselines.desci.preset, **cfg.baselines.desci.overrides())
    assert s.step == 2 and s.sigmas == [0.1, 0.05]
    for bad, match in (("baselines.gaptv.iterations=-1", "iterations"), ("baselines.desci.sigmas=[-0.1]", "sigmas"),
                       ("baselines.choi.latent=0", "latent"), ("baselines.choi.nope=1", "unknown config key"),
                       ("baselines.desci.preset=slow", "preset")):
        with pytest.raises(ConfigError, match=match):
            load_config("tiny", [bad])


# --------------------------------------------------------------------------------------------
# The Choi prior's settings on the command line, the solvers' setting refusals
# --------------------------------------------------------------------------------------------
def test_cli_train_prior_config_error_is_one_line():
    r = run_cli_in_process("baseline", "train-prior", "--config", "tiny", "--out", "unused",
                           "--set", "baselines.choi.lr=-1")
    assert_clean_error(r, "baselines.choi.lr")


@pytest.mark.parametrize("key, value, bound", [("lr", "2", "1"), ("train_steps", "2000000", "1000000")])
def test_train_prior_beyond_the_training_bounds_names_the_prior_key(key, value, bound):
    """The prior trains through a TrainConfig of its settings, whose bounds (train.lr <= 1, train.epochs <= 10^6) then
    refused baselines.choi.lr=2 as 'train.lr must be at most 1', a key the user did not set; now the prior's own key,
    at the config's load, and the bound itself is taken."""
    r = run_cli_in_process("baseline", "train-prior", "--config", "tiny", "--out", "unused",
                           "--set", f"baselines.choi.{key}={value}")
    assert_clean_error(r, f"baselines.choi.{key} must be at most {bound}", f"got {value}")
    assert "train." not in r.stderr.split("(")[0]
    assert getattr(load_config("tiny", [f"baselines.choi.{key}={bound}"]).baselines.choi, key) == float(bound)


def test_solver_setting_refusals(tiny_camera):
    import torch

    from hsicam.solvers.desci import desci_settings
    from hsicam.solvers.gaptv import gap_tv

    with pytest.raises(InputError) as exc:
        desci_settings(sigmas=[1.0, 2.0], iterations=[3])
    assert str(exc.value) == "DeSCI: 2 sigmas but 1 iteration counts"
    with pytest.raises(InputError) as exc:
        desci_settings(patch=0)
    assert str(exc.value) == "DeSCI: patch, step, group, match_every and chunk must be >= 1, search >= 0"
    cam = cassi("dd_cassi", 8, dtype=torch.float32)
    y = torch.rand(1, 1, 8, 8)  # a DD-CASSI image is the scene's size
    assert cam.scene_size((8, 8)) == (8, 8)
    for kw, said in (({"iterations": -1}, "iterations must be an integer >= 0, got -1"),
                     ({"iterations": 2.0}, "iterations must be an integer >= 0, got 2.0"),
                     ({"tv_iterations": -1}, "tv_iterations must be an integer >= 0, got -1")):
        with pytest.raises(InputError) as exc:
            gap_tv(cam, y, **kw)
        assert str(exc.value) == said
    # a start of another size, or not a tensor, is named; a camera whose ΦΦᵀ is not diagonal too (was
    # NotImplementedError, AttributeError)
    with pytest.raises(InputError, match=r"GAP-TV: the start x0 is \(1, 8, 8, 9\) but the measurement's cube is "
                                         r"\(1, 8, 8, 8\)"):
        gap_tv(cam, y, x0=torch.zeros(1, 8, 8, 9))
    with pytest.raises(InputError, match="scene must be a torch.Tensor"):
        gap_tv(cam, y, x0=np.zeros((1, 8, 8, 8)))
    doe = tiny_camera()
    h, w = doe.sensor_size((32, 32))
    with pytest.raises(InputError) as exc:
        gap_tv(doe, torch.zeros(1, 1, h, w))
    assert str(exc.value) == "GAP-TV needs a camera whose ΦΦᵀ is diagonal (a CASSI camera): DOECamera: A·Aᵀ is not diagonal"


def test_admm_carries_its_multiplier_over_when_rho_grows():
    """The scaled dual u = λ/ρ must be divided by ρ's growth when ρ grows, so the multiplier λ carries over (Boyd et
    al. 2011, §3.4.1); it was left as it was (session 74's audit of the baselines: ~0.01 dB). Checked against a
    textbook ADMM with varying ρ written here in the unscaled dual λ (the same x- and z-updates)."""
    from hsicam.solvers.choi import _prior_grad

    cam, prior, truth, y = _admm_problem(16, 4)
    s = ChoiConfig(iterations=6, rho=0.5, rho_growth=1.3, prior_weight=0.5, tv_weight=0.002, inner_steps=2,
                   init_iterations=0)
    x0 = cam.A_adjoint(y / cam.gram_diagonal(y))
    got = admm_prior(cam, y, prior, s, x0=x0)
    phi = cam.gram_diagonal(y)
    m = float(phi.mean())
    z, lam, rho = x0.clone(), torch.zeros_like(x0), s.rho
    with torch.no_grad():
        for _ in range(s.iterations):
            v = z - lam / rho  # argmin ½‖ỹ − Φ̃x‖² + λᵀ(x − z) + ρ/2‖x − z‖²
            x = v + cam.A_adjoint((y - cam.A(v)) / m / (phi / m + rho))
            w = x + lam / rho
            step = 1.0 / (rho + 4.0 * s.prior_weight)
            for _ in range(s.inner_steps):
                z = tv_denoise(z - step * (s.prior_weight * _prior_grad(prior, z) + rho * (z - w)), step * s.tv_weight, 5)
            lam = lam + rho * (x - z)
            rho *= s.rho_growth
    torch.testing.assert_close(got, z, rtol=1e-10, atol=1e-12)
