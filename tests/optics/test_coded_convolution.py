"""The coded convolutions of hsicam.optics.convolution, g = Σ_c κ_c ⊙ (f_c ⊛ p_c) and its adjoint, in the valid and
the same geometry: against the direct shift-and-add convolution (optics_reference), the dense transpose of their
matrices, torch's gradcheck and the plain correlation of κ ⊙ g; the (batch, band) chunk plans of the CPU and of an
accelerator (whole batches, run on CPU and on torch's meta device). Moved from cameras/test_camera.py, which tests
the DOE camera built on them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsicam.optics.convolution import (coded_conv_same, coded_conv_same_adjoint, coded_conv_valid, coded_conv_valid_adjoint,
                                      conv_valid_adjoint, pad_same, pad_same_adjoint)
from optics_reference import direct_valid_conv


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().double().cpu().numpy()


def test_coded_conv_valid_gradcheck():
    g = torch.Generator().manual_seed(7)
    x = torch.rand(2, 3, 8, 9, generator=g, dtype=torch.float64, requires_grad=True)
    psf = torch.rand(3, 5, 5, generator=g, dtype=torch.float64, requires_grad=True)
    kappa = torch.rand(3, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(coded_conv_valid, (x, psf, kappa), eps=1e-6, atol=1e-8, rtol=1e-5)
    # and it is the band sum of κ-weighted valid convolutions (direct reference)
    direct = (direct_valid_conv(_np(x), _np(psf)) * _np(kappa)[None]).sum(axis=1, keepdims=True)
    np.testing.assert_allclose(_np(coded_conv_valid(x, psf, kappa)), direct, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("needs", ["psf", "kappa", "x", "psf,kappa", "x,psf"])
@pytest.mark.parametrize("geometry", ["valid", "same"])
def test_coded_convolutions_differentiate_any_subset_of_their_inputs(geometry, needs):
    """Only some inputs with a gradient (a learned DOE behind a fixed CFA, a learned CFA behind a fixed DOE, a fixed
    scene): the gradients of those are the finite-difference ones (torch's gradcheck), in both geometries."""
    g = torch.Generator().manual_seed(8)
    x = torch.rand(2, 3, 8, 9, generator=g, dtype=torch.float64)
    psf = torch.rand(3, 5, 5, generator=g, dtype=torch.float64)
    kappa = torch.rand(3, *((4, 5) if geometry == "valid" else (8, 9)), generator=g, dtype=torch.float64)
    args = tuple(t.requires_grad_(name in needs.split(",")) for name, t in zip(("x", "psf", "kappa"), (x, psf, kappa)))
    op = coded_conv_valid if geometry == "valid" else coded_conv_same
    assert torch.autograd.gradcheck(op, args, eps=1e-6, atol=1e-8, rtol=1e-5)


def test_coded_adjoint_is_the_transpose_of_the_coded_convolution(monkeypatch):
    """coded_conv_valid_adjoint against the dense transpose of coded_conv_valid's matrix, and against the
    plain correlation of κ ⊙ g, with the work split into many chunks (CHUNK_BYTES shrunk) and whole."""
    import hsicam.optics.convolution as conv

    g = torch.Generator().manual_seed(8)
    c, k, h, w = 3, 5, 4, 6
    psf = torch.rand(c, k, k, generator=g, dtype=torch.float64)
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64)
    n, m = c * (h + k - 1) * (w + k - 1), h * w
    a = coded_conv_valid(torch.eye(n, dtype=torch.float64).reshape(n, c, h + k - 1, w + k - 1), psf, kappa).reshape(n, m).T
    for chunk_bytes in (conv.CHUNK_BYTES, 1):
        monkeypatch.setattr(conv, "CHUNK_BYTES", chunk_bytes)
        at = coded_conv_valid_adjoint(torch.eye(m, dtype=torch.float64).reshape(m, 1, h, w), psf, kappa).reshape(m, n).T
        torch.testing.assert_close(at, a.T, rtol=0, atol=1e-12)
        y = torch.rand(2, 1, 9, 11, generator=g, dtype=torch.float64)
        kap = torch.rand(c, 9, 11, generator=g, dtype=torch.float64)
        torch.testing.assert_close(coded_conv_valid_adjoint(y, psf, kap), conv_valid_adjoint(y * kap, psf), rtol=1e-12,
                                   atol=1e-13)
    with pytest.raises(ValueError, match="sensor image"):
        coded_conv_valid_adjoint(torch.rand(1, 3, 4, 6), psf, kappa)


@pytest.mark.parametrize("device", ["cpu", "cuda"])
@pytest.mark.parametrize("batch, bands, spectrum_bytes", [(8, 31, 400 * 201 * 8), (16, 31, 208 * 105 * 8), (1, 3, 5),
                                                          (3, 7, 2**31)])
def test_convolution_chunks_cover_every_image_once(device, batch, bands, spectrum_bytes):
    """The coded convolutions' (batch, band) chunks: every image of the batch in every band exactly once, each
    chunk's spectra within the device's limit (or a single image); on CPU the small chunks of ``CHUNK_BYTES``, on an
    accelerator (planned here without one: a plan is arithmetic) whole batches, so that the paper camera's
    training step (8 patches of 256 px behind 141 px PSFs: 400² FFTs) is one chunk, not 62."""
    import hsicam.optics.convolution as conv

    dev = torch.device(device)
    limit = conv.chunk_bytes(dev)
    assert limit == (conv.CHUNK_BYTES if device == "cpu" else conv.ACCELERATOR_CHUNK_BYTES)
    chunks = conv._chunks(batch, bands, spectrum_bytes, dev)
    seen = torch.zeros(batch, bands, dtype=torch.int64)
    for bs, cs in chunks:
        seen[bs, cs] += 1
        images = len(range(*bs.indices(batch))) * len(range(*cs.indices(bands)))
        assert images == 1 or images * spectrum_bytes <= limit
    assert bool((seen == 1).all())
    if (batch, bands, spectrum_bytes) == (8, 31, 400 * 201 * 8):
        assert len(chunks) == (1 if device == "cuda" else 62)


def test_coded_convolution_in_whole_batches_equals_small_chunks(monkeypatch):
    """The accelerator's chunk plan (whole batches) run here on CPU: the same measurement, adjoint and gradients as
    the CPU's small chunks, to float64 rounding (the band sum stays the CPU's: it follows the device, not the plan;
    the meta-device test below runs the accelerator's)."""
    import hsicam.optics.convolution as conv

    g = torch.Generator().manual_seed(21)
    x = torch.rand(3, 4, 14, 15, generator=g, dtype=torch.float64, requires_grad=True)
    psf = torch.rand(4, 5, 5, generator=g, dtype=torch.float64, requires_grad=True)
    kappa = torch.rand(4, 10, 11, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(3, 1, 10, 11, generator=g, dtype=torch.float64)
    results = []
    for limit in (1, conv.ACCELERATOR_CHUNK_BYTES):  # one image a chunk; everything at once
        monkeypatch.setattr(conv, "chunk_bytes", lambda device, limit=limit: limit)
        out = coded_conv_valid(x, psf, kappa)
        grads = torch.autograd.grad((out * y).sum(), (x, psf, kappa))
        with torch.no_grad():
            results.append((out.detach(), coded_conv_valid(x, psf, kappa), coded_conv_valid_adjoint(y, psf.detach(),
                                                                                                      kappa.detach()), *grads))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("limit", [1, None])  # one image a chunk; the CPU's own chunks (here: everything at once)
@pytest.mark.parametrize("spectra", [False, True])
@pytest.mark.parametrize("k, h, w", [(7, 9, 13), (9, 3, 2), (11, 4, 17), (1, 5, 6)])
@pytest.mark.parametrize("einsum", [False, True])  # the CPU's band-by-band CFA sum, or an accelerator's einsum
def test_coded_convolution_in_same_geometry_equals_the_padded_valid_one(monkeypatch, limit, spectra, k, h, w, einsum):
    """coded_conv_same / coded_conv_same_adjoint (the snapshot's A and Aᵀ without gradients: no padded copy, pruned
    transforms on transposed spectra, the adjoint's columns read wrapped) against their definitions, the valid
    convolution of the zero-padded cube and its adjoint folded back, on rectangular windows (narrower than half the
    kernel too, and a 1 px kernel), with and without kept spectra, the CFA sum either way; and the pair is adjoint."""
    import hsicam.optics.convolution as conv

    if limit is not None:
        monkeypatch.setattr(conv, "chunk_bytes", lambda device: limit)
    if einsum:
        add_coded = conv._add_coded
        monkeypatch.setattr(conv, "_add_coded", lambda g, y, kappa, cs, band_by_band: add_coded(g, y, kappa, cs, False))
    g = torch.Generator().manual_seed(31)
    b, c = 2, 5
    x = torch.rand(b, c, h, w, generator=g, dtype=torch.float64)
    y = torch.rand(b, 1, h, w, generator=g, dtype=torch.float64)
    psf = torch.rand(c, k, k, generator=g, dtype=torch.float64)
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64)
    psf_f = conv.same_spectra(psf, conv.linear_fft_shape((h + k - 1, w + k - 1))) if spectra else None
    with torch.no_grad():
        forward = conv.coded_conv_same(x, psf, kappa, psf_f)
        back = conv.coded_conv_same_adjoint(y, psf, kappa, psf_f)
    torch.testing.assert_close(forward, coded_conv_valid(pad_same(x, k), psf, kappa), rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(back, pad_same_adjoint(conv_valid_adjoint(y * kappa, psf), k), rtol=1e-12, atol=1e-13)
    direct = (direct_valid_conv(_np(pad_same(x, k)), _np(psf)) * _np(kappa)[None]).sum(axis=1, keepdims=True)
    np.testing.assert_allclose(_np(forward), direct, rtol=1e-10, atol=1e-12)
    assert float((forward * y).sum()) == pytest.approx(float((x * back).sum()), rel=1e-12)


def test_coded_convolution_in_same_geometry_keeps_gradients_and_refuses_bad_shapes():
    """With gradients required the same-geometry pair is the differentiable composition (gradients reach the PSFs
    and the CFA, as the unrolled stages need); a wrong CFA shape or wrong spectra are one clear ValueError."""
    import hsicam.optics.convolution as conv

    g = torch.Generator().manual_seed(32)
    x = torch.rand(1, 3, 8, 10, generator=g, dtype=torch.float64, requires_grad=True)
    psf = torch.rand(3, 5, 5, generator=g, dtype=torch.float64, requires_grad=True)
    kappa = torch.rand(3, 8, 10, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 1, 8, 10, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(conv.coded_conv_same, (x, psf, kappa), eps=1e-6, atol=1e-8, rtol=1e-5)
    (gp, gk) = torch.autograd.grad((conv.coded_conv_same_adjoint(y, psf, kappa) * x.detach()).sum(), (psf, kappa))
    (rp, rk) = torch.autograd.grad((pad_same_adjoint(conv_valid_adjoint(y * kappa, psf), 5) * x.detach()).sum(),
                                   (psf, kappa))
    torch.testing.assert_close((gp, gk), (rp, rk), rtol=1e-12, atol=1e-13)
    # the cube needing gradients and the PSFs not (frozen optics): kept spectra, transposed, serve the composition
    spectra = conv.same_spectra(psf.detach(), conv.linear_fft_shape((8 + 4, 10 + 4)))
    forward = conv.coded_conv_same(x, psf.detach(), kappa.detach(), spectra)
    (gx,) = torch.autograd.grad((forward * y).sum(), x)
    torch.testing.assert_close(forward, coded_conv_valid(pad_same(x, 5), psf, kappa), rtol=1e-12, atol=1e-13)
    with torch.no_grad():
        torch.testing.assert_close(gx, conv.coded_conv_same_adjoint(y, psf, kappa), rtol=1e-12, atol=1e-13)
    back = conv.coded_conv_same_adjoint(y.requires_grad_(True), psf.detach(), kappa.detach(), spectra)
    (gy,) = torch.autograd.grad((back * x.detach()).sum(), y)
    with torch.no_grad():
        torch.testing.assert_close(gy, conv.coded_conv_same(x, psf, kappa), rtol=1e-12, atol=1e-13)
    y.requires_grad_(False)
    with torch.no_grad(), pytest.raises(ValueError, match="kappa must have shape"):
        conv.coded_conv_same(x, psf, kappa[:, :7])
    with torch.no_grad(), pytest.raises(ValueError, match="kappa must have shape"):
        conv.coded_conv_same_adjoint(y, psf, kappa[:, :, :9])
    with torch.no_grad(), pytest.raises(ValueError, match="psf_f must be"):
        conv.coded_conv_same(x, psf, kappa, conv.psf_spectrum(psf, (8, 10)))


def test_coded_convolution_runs_the_accelerator_path_on_the_meta_device():
    """The path a GPU takes (whole batches, the einsum's band sum without gradients too), run on torch's ``meta``
    device (shapes only, no data): the measurement, the adjoint and the three gradients come out in their shapes,
    and on the meta device, not silently on CPU."""
    x = torch.empty(2, 4, 14, 15, device="meta")
    psf, kappa = torch.empty(4, 5, 5, device="meta"), torch.empty(4, 10, 11, device="meta")
    with torch.no_grad():
        g = coded_conv_valid(x, psf, kappa)
        back = coded_conv_valid_adjoint(torch.empty(2, 1, 10, 11, device="meta"), psf, kappa)
        kappa_same = torch.empty(4, 14, 15, device="meta")
        g_same = coded_conv_same(x, psf, kappa_same)
        back_same = coded_conv_same_adjoint(torch.empty(2, 1, 14, 15, device="meta"), psf, kappa_same)
    assert (g.shape, g.device.type) == ((2, 1, 10, 11), "meta")
    assert (back.shape, back.device.type) == ((2, 4, 14, 15), "meta")
    assert (g_same.shape, g_same.device.type) == ((2, 1, 14, 15), "meta")
    assert (back_same.shape, back_same.device.type) == ((2, 4, 14, 15), "meta")
    for t in (x, psf, kappa):
        t.requires_grad_(True)
    coded_conv_valid(x, psf, kappa).sum().backward()
    assert [t.grad.shape for t in (x, psf, kappa)] == [x.shape, psf.shape, kappa.shape]


def test_coded_adjoint_keeps_gradients_to_the_psf():
    """With gradients required (an unrolled network's stages train the optics through Aᵀ) the coded
    adjoint gives the plain correlation's value and gradients."""
    g = torch.Generator().manual_seed(9)
    y = torch.rand(1, 1, 7, 8, generator=g, dtype=torch.float64)
    kappa = torch.rand(3, 7, 8, generator=g, dtype=torch.float64)
    psf = torch.rand(3, 5, 5, generator=g, dtype=torch.float64, requires_grad=True)
    weights = torch.rand(1, 3, 11, 12, generator=g, dtype=torch.float64)
    (grad_coded,) = torch.autograd.grad((coded_conv_valid_adjoint(y, psf, kappa) * weights).sum(), psf)
    (grad_plain,) = torch.autograd.grad((conv_valid_adjoint(y * kappa, psf) * weights).sum(), psf)
    torch.testing.assert_close(grad_coded, grad_plain, rtol=1e-12, atol=1e-13)
    assert grad_coded.abs().max() > 0


def test_coded_convolution_for_training_fills_one_canvas_and_copies_no_spectrum_transposed(monkeypatch):
    """The training op (PSFs and κ with gradients, the scene without), one band a chunk as on a CPU: its forward
    zero-fills one FFT canvas for all the chunks (the scene chunk only ever overwrites the same corner; it was one
    canvas a chunk: 31 fills of 3 MB in a quick training step) and its backward's column transforms run on a
    transposed canvas (fft(dim=-2) of a plain canvas copied each chunk's spectrum transposed first; review 64). The
    measurement and both gradients against the direct shift-and-add convolution, differentiated by autograd."""
    from torch.profiler import ProfilerActivity, profile

    import hsicam.optics.convolution as conv

    g = torch.Generator().manual_seed(64)
    b, c, k, h, w = 2, 3, 5, 6, 7
    x = torch.rand(b, c, h + k - 1, w + k - 1, generator=g, dtype=torch.float64)
    psf = torch.rand(c, k, k, generator=g, dtype=torch.float64, requires_grad=True)
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    weight = torch.rand(b, 1, h, w, generator=g, dtype=torch.float64)
    lh, lw = conv.linear_fft_shape((h + k - 1, w + k - 1))
    monkeypatch.setattr(conv, "chunk_bytes", lambda device: b * lh * (lw // 2 + 1) * 16)  # the batch, one band
    assert len(conv._spectrum_chunks(b, c, (lh, lw), x)) == c

    def top_level(run):  # (op, shape of its first input) of the ops ``run`` calls, and its result
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            result = run()
        return [(e.name, list(e.input_shapes[0])) for e in prof.events() if e.input_shapes], result

    forward, out = top_level(lambda: coded_conv_valid(x, psf, kappa))
    backward, grads = top_level(lambda: torch.autograd.grad((out * weight).sum(), (psf, kappa)))
    assert forward.count(("aten::zero_", [b, 1, lh, lw])) == 1
    assert ("aten::copy_", [b, 1, lw // 2 + 1, lh]) not in backward

    r = k // 2
    direct = sum(psf[None, :, r + dy, r + dx, None, None] * x[:, :, r - dy : r - dy + h, r - dx : r - dx + w]
                 for dy in range(-r, r + 1) for dx in range(-r, r + 1))
    ref = (direct * kappa).sum(1, keepdim=True)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    for got, want in zip(grads, torch.autograd.grad((ref * weight).sum(), (psf, kappa))):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def _direct_coded(x: torch.Tensor, psf: torch.Tensor, kappa: torch.Tensor) -> torch.Tensor:
    """Σ_c κ_c ⊙ (x_c ⊛ psf_c), valid, as a sum of shifted copies (differentiable to any order by torch alone)."""
    k = psf.shape[-1]
    r, h, w = k // 2, x.shape[-2] - k + 1, x.shape[-1] - k + 1
    direct = sum(psf[None, :, r + dy, r + dx, None, None] * x[:, :, r - dy : r - dy + h, r - dx : r - dx + w]
                 for dy in range(-r, r + 1) for dx in range(-r, r + 1))
    return (direct * kappa).sum(1, keepdim=True)


@pytest.mark.parametrize("op", ["valid", "same", "valid_adjoint", "same_adjoint"])
def test_coded_convolutions_differentiate_twice(op):
    """Second-order gradients (backward with create_graph=True: a gradient penalty, a Hessian-vector product) of the
    coded convolutions and their adjoints in both geometries are the finite differences of their first-order ones
    (torch's gradgradcheck, float64). The fused op's backward was once-differentiable: gradgradcheck raised."""
    g = torch.Generator().manual_seed(76)
    c, k, h, w = 2, 3, 4, 5
    same = op.startswith("same")
    kappa = torch.rand(c, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    psf = torch.rand(c, k, k, generator=g, dtype=torch.float64, requires_grad=True)
    if op.endswith("adjoint"):
        first = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64, requires_grad=True)
        fn = coded_conv_same_adjoint if same else coded_conv_valid_adjoint
    else:
        first = torch.rand(1, c, *((h, w) if same else (h + k - 1, w + k - 1)), generator=g, dtype=torch.float64,
                           requires_grad=True)
        fn = coded_conv_same if same else coded_conv_valid
    assert torch.autograd.gradgradcheck(fn, (first, psf, kappa), eps=1e-6, atol=1e-8, rtol=1e-5)


@pytest.mark.parametrize("needs", ["psf", "psf,kappa", "kappa"])
def test_a_gradient_penalty_through_the_coded_convolution_reaches_the_optics(needs):
    """A penalty on the scene gradient, ‖∂⟨A x, w⟩/∂x‖², differentiated with respect to the PSFs and the CFA: the
    gradients of the same penalty through the direct shift-and-add convolution (session 76's hunt: the fused op's
    once-differentiable backward gave a constant ∂/∂x, so the penalty's gradient was silently 0 against 454.3)."""
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(2, 3, 10, 11, generator=g, dtype=torch.float64)
    psf0 = torch.rand(3, 5, 5, generator=g, dtype=torch.float64)
    kappa0 = torch.rand(3, 6, 7, generator=g, dtype=torch.float64)
    weight = torch.rand(2, 1, 6, 7, generator=g, dtype=torch.float64)
    grads = []
    for op in (coded_conv_valid, _direct_coded):
        x = x0.clone().requires_grad_(True)
        psf = psf0.clone().requires_grad_("psf" in needs)
        kappa = kappa0.clone().requires_grad_("kappa" in needs)
        (gx,) = torch.autograd.grad((op(x, psf, kappa) * weight).sum(), x, create_graph=True)
        wrt = [t for t in (psf, kappa) if t.requires_grad]
        grads.append(torch.autograd.grad(gx.square().sum() + 0.0 * sum(t.sum() for t in wrt), wrt))
    for got, want in zip(*grads):
        assert want.abs().max() > 1.0
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
