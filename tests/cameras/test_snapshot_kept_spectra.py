"""``DOESnapshot`` applied without gradients keeps the PSFs' spectra and the CFA tiling of a few window geometries
(session 48), and the coded convolutions take kept spectra: the operator stays the one computed afresh, the adjoint
identity holds through the kept tensors, with gradients nothing is kept, and what is kept stays bounded.
"""

from __future__ import annotations

import pytest
import torch

from hsicam.cameras.doe_camera import DOESnapshot
from hsicam.config import BandsConfig
from hsicam.models.consistency import consistency_step
from hsicam.optics.convolution import (
    coded_conv_valid,
    coded_conv_valid_adjoint,
    linear_fft_shape,
    conv_valid,
    psf_spectrum,
)


def _rand(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _snapshot(k: int = 7, bands: int = 5, period: int = 3, seed: int = 0) -> DOESnapshot:
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(bands, k, k, generator=g, dtype=torch.float64)
    psf /= psf.sum(dim=(-2, -1), keepdim=True)
    tile = torch.rand(bands, period, period, generator=g, dtype=torch.float64)
    grid = BandsConfig(start_nm=500.0, stop_nm=500.0 + 20 * (bands - 1), step_nm=20.0).to_bands()
    return DOESnapshot(grid, psf, tile, period)


def test_coded_convolutions_take_kept_spectra():
    k, c = 5, 3
    x, y = _rand(2, c, 12 + k - 1, 10 + k - 1, seed=9), _rand(2, 1, 12, 10, seed=10)
    psf, kappa = _rand(c, k, k, seed=11), _rand(c, 12, 10, seed=12)
    spectra = psf_spectrum(psf, linear_fft_shape(tuple(x.shape[-2:])))
    with torch.no_grad():
        torch.testing.assert_close(coded_conv_valid(x, psf, kappa, spectra), coded_conv_valid(x, psf, kappa),
                                   rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(coded_conv_valid_adjoint(y, psf, kappa, spectra),
                                   coded_conv_valid_adjoint(y, psf, kappa), rtol=1e-12, atol=1e-14)
        # against the plain per-band convolution, summed through the CFA
        torch.testing.assert_close(coded_conv_valid(x, psf, kappa, spectra),
                                   (conv_valid(x, psf) * kappa).sum(1, keepdim=True), rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="psf_f must be the PSFs' spectra"):
        coded_conv_valid(x, psf, kappa, spectra[:, :-1])
    with pytest.raises(ValueError, match="psf_f must be the PSFs' spectra"):
        coded_conv_valid_adjoint(y, psf, kappa, spectra[1:])


def test_a_snapshot_keeps_what_it_reuses_and_stays_the_same_operator():
    snap = _snapshot()
    fresh = _snapshot()  # the same operator; its kept spectra are emptied before every call
    windows = [((9, 8), (0, 0)), ((9, 8), (4, 2)), ((13, 8), (1, 1)), ((9, 8), (0, 0)), ((6, 11), (2, 5)),
               ((7, 7), (3, 3)), ((9, 8), (3, 0))]
    with torch.no_grad():
        for i, ((h, w), origin) in enumerate(windows):
            x, y = _rand(1, 5, h, w, seed=20 + i), _rand(1, 1, h, w, seed=40 + i)
            for op in ("A", "A_adjoint"):
                fresh._kept.clear()
                arg = x if op == "A" else y
                torch.testing.assert_close(getattr(snap, op)(arg, origin), getattr(fresh, op)(arg, origin),
                                           rtol=1e-12, atol=1e-14)
            # the adjoint identity through the kept tensors
            lhs = float((snap.A(x, origin) * y).sum())
            assert lhs == pytest.approx(float((x * snap.A_adjoint(y, origin)).sum()), rel=1e-12)
            kinds = [key[0] for key in snap._kept]
            assert kinds.count("spectra") <= DOESnapshot.KEPT_WINDOWS
            assert kinds.count("code") <= DOESnapshot.KEPT_WINDOWS
    # an origin one CFA period further is the same phase: the kept tiling serves it
    n = len(snap._kept)
    with torch.no_grad():
        snap.A(_rand(1, 5, 9, 8), (3, 0 + 3))
    assert len(snap._kept) == n


def test_a_snapshot_whose_psfs_need_gradients_keeps_nothing_and_passes_them():
    base = _snapshot()
    psf, tile = base.psf.clone().requires_grad_(True), base.tile.clone().requires_grad_(True)
    snap = DOESnapshot(base.bands, psf, tile, base.code_period)
    x, y = _rand(1, 5, 9, 8, seed=60), _rand(1, 1, 9, 8, seed=61)
    loss = (snap.A(x) * y).sum() + (snap.A_adjoint(y) * x).sum()
    loss.backward()
    assert snap._kept == {}
    assert psf.grad is not None and float(psf.grad.abs().sum()) > 0
    assert tile.grad is not None and float(tile.grad.abs().sum()) > 0
    # without autograd the same snapshot keeps them
    with torch.no_grad():
        snap.A(x)
    assert {key[0] for key in snap._kept} == {"spectra", "code"}


def test_the_steps_on_a_camera_snapshot_are_those_of_a_snapshot_that_keeps_nothing(monkeypatch, tiny_camera):
    """Twelve TV steps with the spectral prior through the tiny camera's snapshot (21 px PSFs, a 3×3 CFA): the
    same cube whether the snapshot keeps its spectra and CFA tiling or computes them afresh at every call."""
    with torch.no_grad():
        snap = tiny_camera().snapshot(nominal=True)
    g = torch.Generator().manual_seed(3)
    x0 = torch.rand(1, len(snap.bands), 24, 20, generator=g)
    y = snap.A(x0 + 0.05 * torch.rand(x0.shape, generator=g), (0, 0)).detach()
    kwargs = dict(iterations=12, spectral_prior=4.0, tv_weight=0.03)
    with torch.no_grad():
        kept = consistency_step(snap, y, x0, (2, 1), **kwargs)
        assert snap._kept
        monkeypatch.setattr(DOESnapshot, "_keep", lambda self, key, make, source: make())
        afresh = consistency_step(snap, y, x0, (2, 1), **kwargs)
    torch.testing.assert_close(kept, afresh, rtol=0, atol=1e-6)
    assert float((kept - x0).abs().max()) > 1e-3  # the steps did move the estimate
