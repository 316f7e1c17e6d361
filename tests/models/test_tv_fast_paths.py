"""The TV prox's and the spectral preconditioner's inference paths (session 48) against the differentiable
expressions: without gradients ``hsicam.models.tv`` computes the divergence, the forward differences, Chambolle's step
and the bands' inner product with fewer passes over memory; they must give what the differentiable expressions give
(and the textbook ones), and the differences and divergence must stay each other's negative adjoints.
"""

from __future__ import annotations

import pytest
import torch

from hsicam.models.consistency import brightness_tv_prox, spectral_preconditioner
from hsicam.models.tv import band_inner, chambolle_step, dual_divergence, forward_differences


def _rand(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _as_differentiable(*tensors):
    """The tensors as leaves that require gradients (so the functions take their differentiable expressions)."""
    return [t.clone().requires_grad_(True) for t in tensors]


def _reference_divergence(py, px):
    """div p written out with explicit shifted copies (the textbook −∇ᵀ for forward differences)."""
    d = py.clone()
    d[..., 1:, :] -= py[..., :-1, :]
    d[..., -1, :] = -py[..., -2, :]
    e = px.clone()
    e[..., :, 1:] -= px[..., :, :-1]
    e[..., :, -1] = -px[..., :, -2]
    return d + e


def test_differences_and_divergence_match_the_textbook_and_are_adjoint():
    d, py, px = _rand(2, 5, 7, 9, seed=1), _rand(2, 5, 7, 9, seed=2), _rand(2, 5, 7, 9, seed=3)
    with torch.no_grad():
        gy, gx = forward_differences(d)
        # the dual field keeps a zero last row (py) and column (px), as chambolle_step does
        py[..., -1, :] = 0
        px[..., :, -1] = 0
        div = dual_divergence(py, px)
    expected_gy = torch.zeros_like(d)
    expected_gy[..., :-1, :] = d[..., 1:, :] - d[..., :-1, :]
    expected_gx = torch.zeros_like(d)
    expected_gx[..., :, :-1] = d[..., :, 1:] - d[..., :, :-1]
    torch.testing.assert_close(gy, expected_gy, rtol=0, atol=0)
    torch.testing.assert_close(gx, expected_gx, rtol=0, atol=0)
    torch.testing.assert_close(div, _reference_divergence(py, px), rtol=0, atol=1e-15)
    # ⟨∇d, p⟩ = −⟨d, div p⟩
    lhs = (gy * py).sum() + (gx * px).sum()
    assert float(lhs) == pytest.approx(-float((d * div).sum()), rel=1e-12)


@pytest.mark.parametrize("vectorial", [True, False])
def test_chambolle_steps_without_gradients_are_the_differentiable_ones(vectorial):
    py, px, g = _rand(1, 4, 8, 6, seed=4) - 0.5, _rand(1, 4, 8, 6, seed=5) - 0.5, _rand(1, 4, 8, 6, seed=6) * 5
    py[..., -1, :] = 0
    px[..., :, -1] = 0
    with torch.no_grad():
        fast = chambolle_step(py, px, g, vectorial=vectorial)
        in_place = chambolle_step(py.clone(), px.clone(), g, vectorial=vectorial, inplace=True)
    if vectorial:  # the differentiable expression (the non-vectorial step is never differentiated: solvers only)
        slow = chambolle_step(*_as_differentiable(py, px, g), vectorial=True)
    else:
        d = _reference_divergence(py, px) - g
        gy, gx = forward_differences(*_as_differentiable(d))
        norm = 1 + 0.125 * torch.hypot(gy, gx)
        slow = ((py + 0.125 * gy) / norm, (px + 0.125 * gx) / norm)
    for a, b, c in zip(fast, in_place, slow):
        torch.testing.assert_close(a, c.detach(), rtol=1e-13, atol=1e-15)
        torch.testing.assert_close(b, c.detach(), rtol=1e-13, atol=1e-15)
    assert float(fast[0][..., -1, :].abs().max()) == 0 and float(fast[1][..., :, -1].abs().max()) == 0


def test_the_prox_and_the_spectral_preconditioner_without_gradients_are_the_differentiable_ones():
    v, b = _rand(2, 6, 9, 11, seed=7), _rand(2, 1, 9, 11, seed=8) + 0.1
    dual = (torch.zeros_like(v), torch.zeros_like(v))
    dual_slow = tuple(_as_differentiable(*dual))
    v_slow, b_slow = _as_differentiable(v, b)
    divergence = None
    for _ in range(3):
        with torch.no_grad():
            out, dual, divergence = brightness_tv_prox(v, b, 0.05, dual, divergence)
        out_slow, dual_slow, _ = brightness_tv_prox(v_slow, b_slow, 0.05, dual_slow)
        torch.testing.assert_close(out, out_slow.detach(), rtol=1e-12, atol=1e-14)
        # the divergence handed on is the new field's
        torch.testing.assert_close(divergence, _reference_divergence(*dual), rtol=0, atol=1e-15)
    # the prox as first written: b · (u − w · div p), u = v ⊘ b
    torch.testing.assert_close(out, (v / b - 0.05 * _reference_divergence(*dual)) * b, rtol=1e-12, atol=1e-14)
    s = spectral_preconditioner(v, 3.0)
    with torch.no_grad():
        fast = s(b * v.flip(1))
    unit = v / v.square().sum(1, keepdim=True).sqrt()
    w = b * v.flip(1)
    torch.testing.assert_close(fast, w + 3.0 * unit * (unit * w).sum(1, keepdim=True), rtol=1e-12, atol=1e-14)
    with torch.no_grad():  # written over its argument (the steps' Aᵀ output): the same values, in that tensor
        over = w.clone()
        assert s(over, inplace=True) is over
    torch.testing.assert_close(over, fast, rtol=0, atol=0)
    with torch.no_grad():
        torch.testing.assert_close(band_inner(v, w), (v * w).sum(1, keepdim=True), rtol=1e-13, atol=0)


def test_the_prox_with_a_kept_divergence_is_the_prox_that_recomputes_it():
    """The consistency steps hand each prox the previous one's divergence (session 50): the same iterates as
    recomputing it each call, and the kept tensor is not written into."""
    v, b = _rand(1, 5, 12, 10, seed=9), _rand(1, 1, 12, 10, seed=10) + 0.1
    kept = recomputed = (torch.zeros_like(v), torch.zeros_like(v))
    divergence = None
    with torch.no_grad():
        for k in range(4):
            u = v * (1 + 0.1 * k)
            before = None if divergence is None else divergence.clone()
            out_kept, kept, new_divergence = brightness_tv_prox(u, b, 0.07, kept, divergence)
            if before is not None:
                torch.testing.assert_close(divergence, before, rtol=0, atol=0)
            divergence = new_divergence
            out, recomputed, _ = brightness_tv_prox(u, b, 0.07, recomputed)
            torch.testing.assert_close(out_kept, out, rtol=0, atol=0)
    assert float(out.sub(u).abs().max()) > 1e-3  # the prior moved the estimate: the comparison is not vacuous


def test_brightness_tv_restarts_its_dual_field_without_the_old_divergence():
    """``BrightnessTV`` keeps its dual field's divergence between calls: a field reset (``dual = None``) or set from
    outside starts from that field, as a fresh prior does, not from the divergence of the field it replaced."""
    from hsicam.models.consistency import BrightnessTV

    v = _rand(1, 4, 10, 9, seed=11)
    with torch.no_grad():
        tv = BrightnessTV(v, 0.05)
        for k in range(5):
            tv(v * (1 + 0.2 * k))
        tv.dual = None
        torch.testing.assert_close(tv(v), BrightnessTV(v, 0.05)(v), rtol=0, atol=0)
        other = BrightnessTV(v, 0.05)
        other(v * 0.5)
        tv.dual = tuple(t.clone() for t in other.dual)
        torch.testing.assert_close(tv(v), other(v), rtol=0, atol=0)
