"""Linear (not circular) 2-D convolution of band images with band PSFs, by FFT, and its adjoint.

``valid``: the input is larger than the output by K − 1 pixels per axis (the physically right
mode for training patches). ``same``: the input is first padded by K//2 on each side with an
explicit mode. Every operator here has an exact adjoint, written out (not left to autograd),
so solvers can use them and tests can check ⟨Ax, y⟩ = ⟨x, Aᵀy⟩.

Convention: out[i, j] = Σ_kl psf[k, l] · x[i + K−1−k, j + K−1−l] (true convolution). The PSF's
centre pixel (K//2, K//2) is the optical axis, so output pixel (i, j) sees input pixel
(i + K//2, j + K//2) through the axis.
"""

from __future__ import annotations

import functools

import scipy.fft
import torch
import torch.nn.functional as F

PAD_MODES = ("zeros", "reflect", "replicate", "circular")


@functools.lru_cache(maxsize=256)
def fast_fft_size(n: int) -> int:
    """Smallest 5-smooth length ≥ n (fast for every FFT backend)."""
    return int(scipy.fft.next_fast_len(int(n), real=True))


def _check(x: torch.Tensor, psf: torch.Tensor) -> None:
    if x.dim() != 4:
        raise ValueError(f"expected a (B, C, H, W) tensor, got shape {tuple(x.shape)}")
    if psf.dim() != 3 or psf.shape[-1] != psf.shape[-2] or psf.shape[-1] % 2 == 0:
        raise ValueError(f"expected an odd square PSF stack (C, K, K), got shape {tuple(psf.shape)}")
    if x.shape[1] != psf.shape[0]:
        raise ValueError(f"input has {x.shape[1]} bands but the PSF stack has {psf.shape[0]}")


def psf_spectrum(psf: torch.Tensor, fft_shape: tuple[int, int]) -> torch.Tensor:
    """rFFT of the PSF stack (C, K, K) zero-padded to ``fft_shape``: (C, Lh, Lw//2 + 1)."""
    return torch.fft.rfft2(psf, s=fft_shape)


def linear_fft_shape(scene_hw: tuple[int, int]) -> tuple[int, int]:
    """The FFT shape of every valid convolution here (and its adjoint) for a scene (H+K−1, W+K−1): the fast sizes
    ≥ the scene's, enough for a linear convolution's valid part; the spectra :func:`coded_conv_valid` and
    :func:`coded_conv_valid_adjoint` take as ``psf_f`` are ``psf_spectrum(psf, linear_fft_shape(scene_hw))``."""
    return fast_fft_size(scene_hw[0]), fast_fft_size(scene_hw[1])


def conv_valid(x: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Per-band valid convolution: (B, C, H+K−1, W+K−1) × (C, K, K) → (B, C, H, W).

    FFT length ≥ H+K−1 suffices for the valid part (the circular wrap only touches the first K−1
    outputs, which are discarded), rounded up to a fast size.
    """
    _check(x, psf)
    k = psf.shape[-1]
    hx, wx = x.shape[-2:]
    h, w = hx - k + 1, wx - k + 1
    if h < 1 or w < 1:
        raise ValueError(f"valid convolution needs inputs of at least {k}×{k} pixels, got {hx}×{wx}")
    shape = linear_fft_shape((hx, wx))
    y = torch.fft.irfft2(torch.fft.rfft2(x, s=shape) * psf_spectrum(psf, shape), s=shape)
    return y[..., k - 1 : k - 1 + h, k - 1 : k - 1 + w]


def conv_valid_adjoint(y: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Exact adjoint of :func:`conv_valid`: (B, C, H, W) → (B, C, H+K−1, W+K−1) (a correlation)."""
    _check(y, psf)
    k = psf.shape[-1]
    h, w = y.shape[-2:]
    hx, wx = h + k - 1, w + k - 1
    shape = linear_fft_shape((hx, wx))
    placed = F.pad(y, (k - 1, shape[1] - (k - 1) - w, k - 1, shape[0] - (k - 1) - h))
    x = torch.fft.irfft2(torch.fft.rfft2(placed) * psf_spectrum(psf, shape).conj(), s=shape)
    return x[..., :hx, :wx]


def pad_same(x: torch.Tensor, k: int, mode: str = "zeros") -> torch.Tensor:
    """Pad (B, C, H, W) by k//2 on every side so that a valid convolution returns H×W."""
    r = k // 2
    if mode not in PAD_MODES:
        raise ValueError(f"unknown padding {mode!r}; use one of {PAD_MODES}")
    if mode == "reflect" and (x.shape[-1] <= r or x.shape[-2] <= r):
        raise ValueError(f"reflect padding by {r} px needs images larger than {r} px")
    if mode == "zeros":
        return F.pad(x, (r, r, r, r))
    return F.pad(x, (r, r, r, r), mode=mode)


def pad_same_adjoint(y: torch.Tensor, k: int, mode: str = "zeros") -> torch.Tensor:
    """Exact adjoint of :func:`pad_same`: fold the border back onto the pixels it copied."""
    r = k // 2
    if r == 0:
        return y
    for dim in (-2, -1):
        y = _unpad_1d(y, r, mode, dim)
    return y


def _unpad_1d(y: torch.Tensor, r: int, mode: str, dim: int) -> torch.Tensor:
    n = y.shape[dim] - 2 * r
    left, core, right = y.narrow(dim, 0, r), y.narrow(dim, r, n).clone(), y.narrow(dim, r + n, r)
    if mode == "zeros":
        return core
    idx = torch.arange(r, device=y.device)
    if mode == "replicate":
        core.narrow(dim, 0, 1).add_(left.sum(dim=dim, keepdim=True))
        core.narrow(dim, n - 1, 1).add_(right.sum(dim=dim, keepdim=True))
    elif mode == "reflect":  # left[j] copies core[r - j]; right[j] copies core[n - 2 - j]
        core.index_add_(dim, r - idx, left)
        core.index_add_(dim, n - 2 - idx, right)
    elif mode == "circular":  # left[j] copies core[n - r + j]; right[j] copies core[j]
        core.index_add_(dim, n - r + idx, left)
        core.index_add_(dim, idx, right)
    else:
        raise ValueError(f"unknown padding {mode!r}")
    return core


# On CPU, spectra of at most this many bytes are computed at a time. Small temporaries are recycled
# by the C allocator; whole-batch spectra (tens of MB each) are fresh mmaps that the kernel has to
# page-fault and zero on every call, which cost more than the FFTs themselves on CPU.
CHUNK_BYTES = 4 * 2**20
# On an accelerator the opposite holds: a chunk costs a few kernel launches and a Python pass whatever its
# size, and the caching allocator reuses whole-batch buffers. At CHUNK_BYTES the paper camera's training step
# (8 patches of 256 px, 31 bands, 141 px PSFs) ran each coded convolution in 62 chunks of 6 images: on an H200
# (session 49) ~1 000 FFT calls a step, the GPU mostly waiting for Python. Up to this many bytes go at once there.
ACCELERATOR_CHUNK_BYTES = 2**30


def chunk_bytes(device: torch.device) -> int:
    """The most bytes of spectra the coded convolutions compute at a time on ``device``."""
    return CHUNK_BYTES if device.type == "cpu" else ACCELERATOR_CHUNK_BYTES


def _chunks(batch: int, bands: int, spectrum_bytes: int, device: torch.device) -> list[tuple[slice, slice]]:
    """(batch slice, band slice) pairs whose spectra hold at most :func:`chunk_bytes` of ``device``
    (at least one image)."""
    per_band = max(1, chunk_bytes(device) // max(1, spectrum_bytes))
    if per_band >= batch:  # whole batch, several bands at a time
        step = per_band // batch
        return [(slice(0, batch), slice(c, min(bands, c + step))) for c in range(0, bands, step)]
    return [(slice(b, min(batch, b + per_band)), slice(c, c + 1)) for c in range(bands) for b in range(0, batch, per_band)]


def _spectrum_chunks(batch: int, bands: int, shape: tuple[int, int], like: torch.Tensor) -> list[tuple[slice, slice]]:
    """:func:`_chunks` for rFFT spectra of ``shape`` (complex, of ``like``'s precision) on ``like``'s device."""
    return _chunks(batch, bands, shape[0] * (shape[1] // 2 + 1) * 2 * like.element_size(), like.device)


def _placed(img: torch.Tensor, shape: tuple[int, int], row0: int = 0, col0: int = 0) -> torch.Tensor:
    """``img`` (…, h, w) copied at (row0, col0) into a zero canvas (…, *shape)."""
    out = img.new_zeros(img.shape[:-2] + tuple(shape))
    out[..., row0 : row0 + img.shape[-2], col0 : col0 + img.shape[-1]] = img
    return out


def _irfft2_rows(spec: torch.Tensor, shape: tuple[int, int], row0: int, rows: int) -> torch.Tensor:
    """irfft2 of ``spec`` (…, Lh, Lw//2+1) keeping only output rows row0..row0+rows−1 (pruned)."""
    tmp = torch.fft.ifft(spec, dim=-2).narrow(-2, row0, rows)
    return torch.fft.irfft(tmp, n=shape[1], dim=-1)


def _rfft2_rows(img: torch.Tensor, shape: tuple[int, int], row0: int, col0: int) -> torch.Tensor:
    """rfft2 of ``img`` (…, h, w) placed at (row0, col0) in a zero ``shape`` canvas (pruned:
    the row transforms run over the h non-zero rows only)."""
    # the column transforms on a transposed canvas (:func:`_rfft2_transposed`; what fft(dim=-2) would copy a plain
    # canvas into): the same spectrum, bit for bit, as the transposed view that fft(dim=-2) returns
    return _rfft2_transposed(_placed(img, (img.shape[-2], shape[1]), 0, col0), shape, row0).transpose(-1, -2)


def same_spectra(psf: torch.Tensor, fft_shape: tuple[int, int]) -> torch.Tensor:
    """The PSFs' spectra as :func:`coded_conv_same` and :func:`coded_conv_same_adjoint` take them (``psf_f``):
    :func:`psf_spectrum` transposed, (C, Lw//2 + 1, Lh), contiguous."""
    return psf_spectrum(psf, fft_shape).transpose(-1, -2).contiguous()


def _rfft2_transposed(img: torch.Tensor, shape: tuple[int, int], row0: int) -> torch.Tensor:
    """rfft2 of ``img`` (…, h, w) placed at (row0, 0) in a zero ``shape`` canvas, transposed: (…, Lw//2+1, Lh). The
    row transforms run over the h rows of ``img`` only; their output is copied transposed into the canvas of the
    column transforms, which then run along its contiguous last dimension (along a strided one torch copies each
    chunk twice more). ``img`` may already be Lw wide, zero beyond its columns (:func:`_coded_rows`)."""
    rows = torch.fft.rfft(img, n=shape[1], dim=-1)
    canvas = rows.new_zeros(rows.shape[:-2] + (rows.shape[-1], shape[0]))
    canvas[..., row0 : row0 + img.shape[-2]].copy_(rows.transpose(-1, -2))
    return torch.fft.fft(canvas, dim=-1)


def _coded_rows(g: torch.Tensor, kappa: torch.Tensor, width: int) -> torch.Tensor:
    """κ ⊙ g for a chunk's bands, g (b, 1, h, w) and κ (c, h, w), written into rows ``width`` wide whose columns
    beyond w are zero: (b, c, h, width), what the row transforms take without padding it again."""
    b, _, h, w = g.shape
    out = g.new_empty(b, kappa.shape[0], h, width)
    out[..., w:].zero_()
    torch.mul(g, kappa, out=out[..., :w])
    return out


def _irfft2_transposed(spec: torch.Tensor, shape: tuple[int, int], row0: int, rows: int) -> torch.Tensor:
    """Rows row0..row0+rows−1 of the irfft2 of a transposed spectrum ``spec`` (…, Lw//2+1, Lh): (…, rows, Lw)."""
    tmp = torch.fft.ifft(spec, dim=-1)[..., row0 : row0 + rows]
    return torch.fft.irfft(tmp.transpose(-1, -2), n=shape[1], dim=-1)


class _CodedConvolution(torch.autograd.Function):
    """g = Σ_c κ_c ⊙ valid_conv(x_c, psf_c): the DOE camera's measurement in one fused op.

    The work runs over (batch, band) chunks (small on CPU, whole batches on an accelerator: see
    :func:`chunk_bytes`) and the backward is
    written out (gradients for x, psf and κ, each only when needed), with the FFTs pruned over
    the rows that are known to be zero or discarded. When the PSFs need a gradient and the scene
    does not (a training batch), the chunks' scene spectra are kept for the backward (the quick
    camera's batch: 31 × 3 MB) instead of transformed again there: the op's forward and backward
    481 → 376 ms on 1 thread, bit for bit the same result. With a scene that needs a gradient too,
    the scene's spectrum is recomputed chunk by chunk (one FFT). About 2× faster than the unchunked
    op on CPU. A backward with ``create_graph=True`` (second-order gradients) takes autograd's through the equal
    composition instead (:func:`_coded_gradients_differentiable`).
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, psf: torch.Tensor, kappa: torch.Tensor,  # type: ignore[override]
                psf_f: torch.Tensor | None = None, recording: bool = True) -> torch.Tensor:
        # recording: whether autograd records this call (grad mode on outside the Function; inside forward it is
        # off, and ctx.needs_input_grad follows requires_grad alone): under no_grad nothing is kept for a backward
        k = psf.shape[-1]
        batch, bands, hx, wx = x.shape
        h, w = hx - k + 1, wx - k + 1
        shape = linear_fft_shape((hx, wx))
        chunks = _spectrum_chunks(batch, bands, shape, x)
        keep_y = recording and ctx.needs_input_grad[2]
        differentiated = any(ctx.needs_input_grad[:3])
        on_cpu = x.device.type == "cpu"
        y_all = x.new_empty(batch, bands, h, w) if keep_y else None
        # the PSFs' gradient correlates the scene's spectra with the coded gradient's: kept (when the scene needs no
        # gradient, e.g. a training batch) instead of transformed again in the backward
        keep_xf = recording and ctx.needs_input_grad[1] and not ctx.needs_input_grad[0]
        kept_xf = []
        g = x.new_zeros(batch, h, w)
        canvas = None  # one zero canvas for the chunks of a shape: only its top-left corner is ever written
        for bs, cs in chunks:
            size = x[bs, cs].shape[:2]
            if canvas is None or canvas.shape[:2] != size:
                canvas = x.new_zeros(size + shape)
            canvas[..., :hx, :wx] = x[bs, cs]
            xf = torch.fft.rfft2(canvas)
            spectrum = torch.fft.rfft2(psf[cs], s=shape) if psf_f is None else psf_f[cs]
            if keep_xf:
                kept_xf.append(xf)
                xf = xf * spectrum
            else:
                xf.mul_(spectrum)
            y = _irfft2_rows(xf, shape, k - 1, h)[..., k - 1 : k - 1 + w]
            _add_coded(g[bs], y, kappa, cs, band_by_band=not differentiated and on_cpu)
            if keep_y:
                y_all[bs, cs] = y
        ctx.save_for_backward(x, psf, kappa, y_all)
        ctx.geometry = (k, shape, chunks)
        ctx.kept_xf = kept_xf
        return g.unsqueeze(1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        if torch.is_grad_enabled():  # create_graph=True: the gradient is differentiated again
            return _coded_gradients_differentiable(ctx, grad)
        x, psf, kappa, y_all = ctx.saved_tensors
        k, shape, chunks = ctx.geometry
        hx, wx = x.shape[-2:]
        grad_x = grad_psf = grad_kappa = None
        if ctx.needs_input_grad[2]:
            # a broadcast product and a sum over the batch: einsum lowers this to H·W tiny matmuls
            # (bmm of (HW, 1, B) by (HW, B, C) after a transposing copy), ~40× slower on CPU
            grad_kappa = (grad[:, 0, None] * y_all).sum(0)
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            if ctx.needs_input_grad[0]:
                grad_x = torch.empty_like(x)
            if ctx.needs_input_grad[1]:
                cross = torch.zeros(psf.shape[0], shape[0], shape[1] // 2 + 1, dtype=grad.dtype.to_complex(), device=grad.device)
            kept_xf, ctx.kept_xf = ctx.kept_xf, None
            for i, (bs, cs) in enumerate(chunks):
                gf = _rfft2_rows(grad[bs] * kappa[cs], shape, k - 1, k - 1)
                if ctx.needs_input_grad[1]:  # correlation of the scene with the coded gradient
                    xf = kept_xf[i] if kept_xf else torch.fft.rfft2(_placed(x[bs, cs], shape))
                    cross[cs] += (gf * xf.conj_physical()).sum(0)
                if ctx.needs_input_grad[0]:
                    grad_x[bs, cs] = _correlate_chunk(gf, psf[cs], shape, hx, wx)
            if ctx.needs_input_grad[1]:
                grad_psf = torch.fft.irfft2(cross, s=shape)[..., :k, :k]
        return grad_x, grad_psf, grad_kappa, None, None


def _coded_gradients_differentiable(ctx, grad: torch.Tensor) -> tuple:
    """:class:`_CodedConvolution`'s gradients as a differentiable function of its inputs and of ``grad`` (backward
    with ``create_graph=True``: a gradient penalty, a Hessian-vector product): autograd's through the composition
    the op equals, ``(conv_valid(x, psf) * kappa).sum(1, keepdim=True)``, re-run here. The written-out backward
    above runs without autograd (in-place chunks): marked once-differentiable, it returned the gradients as
    constants whenever ``grad`` itself needed none, so a penalty on them had a silent zero gradient (session 76's
    hunt: 0 against 454.3 for the PSF)."""
    x, psf, kappa, _ = ctx.saved_tensors
    ctx.kept_xf = None
    needs = ctx.needs_input_grad[:3]
    inputs = [t for t, need in zip((x, psf, kappa), needs) if need]
    with torch.enable_grad():
        out = (conv_valid(x, psf) * kappa).sum(1, keepdim=True)
        grads = iter(torch.autograd.grad(out, inputs, grad, create_graph=True))
    return tuple(next(grads) if need else None for need in needs) + (None, None)


def _add_coded(g: torch.Tensor, y: torch.Tensor, kappa: torch.Tensor, cs: slice, band_by_band: bool) -> None:
    """g (b, h, w) += Σ_c κ_c ⊙ y_c over a chunk's bands ``cs`` (y (b, c, h, w), κ (C, h, w)), in place.
    ``band_by_band`` (inference on CPU): one addcmul a band, where the einsum is a bmm after a transposing copy (A of
    a 512² × 31 window 46 → 35 ms). Training keeps the einsum's order of summation, so that runs train bit for bit
    as before (the demo's figures are compared across sessions); an accelerator keeps it too (one launch, not one per
    band)."""
    if not band_by_band:
        g += torch.einsum("bchw,chw->bhw", y, kappa[cs])
        return
    for j, c in enumerate(range(*cs.indices(kappa.shape[0]))):
        g.addcmul_(y[:, j], kappa[c])


def _correlate_chunk(gf: torch.Tensor, psf: torch.Tensor, shape: tuple[int, int], hx: int, wx: int,
                     psf_f: torch.Tensor | None = None) -> torch.Tensor:
    """Correlation of a chunk's coded sensor spectrum ``gf`` (b, c, Lh, Lw//2+1) with its PSFs (c, K, K) (or their
    spectra ``psf_f``, (c, Lh, Lw//2+1)), cropped to the scene (b, c, hx, wx): the x-part of
    :class:`_CodedConvolution`'s adjoint."""
    spectrum = torch.fft.rfft2(psf, s=shape) if psf_f is None else psf_f
    return torch.fft.irfft2(gf * spectrum.conj_physical(), s=shape)[..., :hx, :wx]


def coded_conv_valid_adjoint(g: torch.Tensor, psf: torch.Tensor, kappa: torch.Tensor,
                             psf_f: torch.Tensor | None = None) -> torch.Tensor:
    """Exact adjoint of :func:`coded_conv_valid` in the scene: (B, 1, H, W) → (B, C, H+K−1, W+K−1),
    x_c = psf_c ⋆ (κ_c ⊙ g), equal to ``conv_valid_adjoint(g * kappa, psf)``.

    Run chunk by chunk with the row transforms pruned, as the fused op's backward: about 3× faster
    on CPU for 31 bands at 512² with a 21 px kernel (0.33 → 0.10 s, session 34), which the consistency steps take at
    inference. Without autograd only (its chunks are written in place); with gradients required
    it falls back to :func:`conv_valid_adjoint`. ``psf_f``: the PSFs' spectra at :func:`linear_fft_shape` of the
    scene, when the caller keeps them (an operator applied many times: 31 FFTs fewer a call; ignored with
    gradients)."""
    _check_sensor(g, psf)
    if torch.is_grad_enabled() and (g.requires_grad or psf.requires_grad or kappa.requires_grad):
        return conv_valid_adjoint(g * kappa, psf)
    k = psf.shape[-1]
    batch, _, h, w = g.shape
    _check_kappa(kappa, (psf.shape[0], h, w))
    hx, wx = h + k - 1, w + k - 1
    shape = linear_fft_shape((hx, wx))
    _check_spectra(psf_f, psf, shape)
    out = g.new_empty(batch, psf.shape[0], hx, wx)
    for bs, cs in _spectrum_chunks(batch, psf.shape[0], shape, g):
        out[bs, cs] = _correlate_chunk(_rfft2_rows(g[bs] * kappa[cs], shape, k - 1, k - 1), psf[cs], shape, hx, wx,
                                       None if psf_f is None else psf_f[cs])
    return out


def coded_conv_valid(x: torch.Tensor, psf: torch.Tensor, kappa: torch.Tensor,
                     psf_f: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over bands of κ ⊙ (valid convolution of each band with its PSF).

    Args:
        x: scene (B, C, H+K−1, W+K−1).
        psf: PSF stack (C, K, K).
        kappa: per-band weights on the sensor (C, H, W).
        psf_f: optional, the PSFs' spectra ``psf_spectrum(psf, linear_fft_shape(x.shape[-2:]))`` (C, Lh, Lw//2+1)
            when the caller keeps them (an operator applied many times without gradients: 31 of the call's 62
            FFTs saved); the PSF's gradient is still taken from ``psf``.
    Returns:
        Sensor image (B, 1, H, W). Equal to ``(conv_valid(x, psf) * kappa).sum(1, keepdim=True)``.
    """
    _check(x, psf)
    k = psf.shape[-1]
    h, w = x.shape[-2] - k + 1, x.shape[-1] - k + 1
    if h < 1 or w < 1:
        raise ValueError(f"valid convolution needs inputs of at least {k}×{k} pixels, got {tuple(x.shape[-2:])}")
    _check_kappa(kappa, (psf.shape[0], h, w))
    _check_spectra(psf_f, psf, linear_fft_shape(tuple(x.shape[-2:])))
    return _CodedConvolution.apply(x, psf, kappa, psf_f, torch.is_grad_enabled())


def _same_plan(psf: torch.Tensor, h: int, w: int, psf_f: torch.Tensor | None):
    """The same-geometry pair's FFT shape for an h × w window, with ``psf_f`` (:func:`same_spectra`'s layout) checked,
    and those spectra as the padded valid composition takes them (a transposed view; None without them)."""
    k = psf.shape[-1]
    shape = linear_fft_shape((h + k - 1, w + k - 1))
    _check_spectra(psf_f, psf, shape, transposed=True)
    return shape, None if psf_f is None else psf_f.transpose(-1, -2)


def _chunk_spectra(psf: torch.Tensor, psf_f: torch.Tensor | None, cs: slice, shape: tuple[int, int]) -> torch.Tensor:
    """A chunk's bands ``cs`` of the transposed spectra: the kept ones, or computed from the PSFs."""
    return same_spectra(psf[cs], shape) if psf_f is None else psf_f[cs]


def coded_conv_same(x: torch.Tensor, psf: torch.Tensor, kappa: torch.Tensor,
                    psf_f: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over bands of κ ⊙ (each band convolved with its PSF), in ``same`` geometry with zero padding: x (B, C, H, W),
    psf (C, K, K), kappa (C, H, W) → (B, 1, H, W), equal to ``coded_conv_valid(pad_same(x, K), psf, kappa)``.
    ``psf_f``: the PSFs' spectra when the caller keeps them, ``same_spectra(psf, linear_fft_shape((H + K − 1,
    W + K − 1)))`` (transposed, (C, Lw//2+1, Lh)).

    Without gradients each chunk of x goes straight into its FFT canvas (no padded copy of the cube; x at the
    canvas's corner, the output read K//2 px further), its row transforms over the H rows of x only, its column
    transforms along a contiguous dimension (the spectra transposed): a DOE camera's snapshot A of a 532² × 31
    window 44–56 → 35–39 ms (session 49) → 33–34 ms against 37–40 ms the same hour (session 50). With gradients
    required it is that composition (differentiable)."""
    _check(x, psf)
    k = psf.shape[-1]
    batch, bands, h, w = x.shape
    shape, valid_f = _same_plan(psf, h, w, psf_f)
    if torch.is_grad_enabled() and (x.requires_grad or psf.requires_grad or kappa.requires_grad):
        return coded_conv_valid(pad_same(x, k), psf, kappa, valid_f)
    _check_kappa(kappa, (bands, h, w))
    r = k // 2
    g = x.new_zeros(batch, h, w)
    for bs, cs in _spectrum_chunks(batch, bands, shape, x):
        xf = _rfft2_transposed(x[bs, cs], shape, 0)
        xf.mul_(_chunk_spectra(psf, psf_f, cs, shape))
        _add_coded(g[bs], _irfft2_transposed(xf, shape, r, h)[..., r : r + w], kappa, cs,
                   band_by_band=x.device.type == "cpu")
    return g.unsqueeze(1)


def coded_conv_same_adjoint(g: torch.Tensor, psf: torch.Tensor, kappa: torch.Tensor,
                            psf_f: torch.Tensor | None = None) -> torch.Tensor:
    """Exact adjoint of :func:`coded_conv_same`: (B, 1, H, W) → (B, C, H, W), equal to
    ``pad_same_adjoint(coded_conv_valid_adjoint(g, psf, kappa), K)``; ``psf_f`` as there. Without gradients each
    chunk's correlation is inverse-transformed over the H rows kept only (the transposed spectra, as the forward)
    and written into the output cropped (κ ⊙ g at the canvas's left edge, so the H·W kept are the columns from
    −K//2, wrapped: no (H + K − 1)² cube, no crop copy); with gradients required it is that composition."""
    _check_sensor(g, psf)
    k = psf.shape[-1]
    batch, _, h, w = g.shape
    shape, valid_f = _same_plan(psf, h, w, psf_f)
    if torch.is_grad_enabled() and (g.requires_grad or psf.requires_grad or kappa.requires_grad):
        return pad_same_adjoint(coded_conv_valid_adjoint(g, psf, kappa, valid_f), k)
    _check_kappa(kappa, (psf.shape[0], h, w))
    r = k // 2
    out = g.new_empty(batch, psf.shape[0], h, w)
    for bs, cs in _spectrum_chunks(batch, psf.shape[0], shape, g):
        gf = _rfft2_transposed(_coded_rows(g[bs], kappa[cs], shape[1]), shape, k - 1)
        gf.mul_(_chunk_spectra(psf, psf_f, cs, shape).conj())
        full = _irfft2_transposed(gf, shape, r, h)
        # output column j is the correlation's column j − K//2, which the canvas wraps to its end for j < K//2
        left = min(r, w)
        out[bs, cs, :, :left] = full[..., shape[1] - r : shape[1] - r + left]
        if w > r:
            out[bs, cs, :, r:] = full[..., : w - r]
    return out


def _check_sensor(g: torch.Tensor, psf: torch.Tensor) -> None:
    """The adjoints' arguments: a (B, 1, H, W) sensor image and an odd square PSF stack (C, K, K)."""
    if g.dim() != 4 or g.shape[1] != 1:
        raise ValueError(f"expected a (B, 1, H, W) sensor image, got shape {tuple(g.shape)}")
    if psf.dim() != 3 or psf.shape[-1] != psf.shape[-2] or psf.shape[-1] % 2 == 0:
        raise ValueError(f"expected an odd square PSF stack (C, K, K), got shape {tuple(psf.shape)}")


def _check_kappa(kappa: torch.Tensor, expected: tuple[int, int, int]) -> None:
    """The coded convolutions' CFA transmission: (C, H, W) of the sensor window."""
    if tuple(kappa.shape) != expected:
        raise ValueError(f"kappa must have shape {expected}, got {tuple(kappa.shape)}")


def _check_spectra(psf_f: torch.Tensor | None, psf: torch.Tensor, shape: tuple[int, int],
                   transposed: bool = False) -> None:
    """A ValueError unless ``psf_f`` is None or shaped as the PSFs' spectra at FFT ``shape``: :func:`psf_spectrum`'s
    (C, Lh, Lw//2+1), or ``transposed`` :func:`same_spectra`'s (C, Lw//2+1, Lh). Where Lh = Lw//2+1 the two layouts
    have one shape and the check cannot tell them apart (the snapshot, the one caller that keeps spectra, makes
    them with the function that goes with its convolutions)."""
    c, lh, lw = psf.shape[0], shape[0], shape[1] // 2 + 1
    expected = (c, lw, lh) if transposed else (c, lh, lw)
    if psf_f is not None and tuple(psf_f.shape) != expected:
        raise ValueError(f"psf_f must be the PSFs' spectra of {'same_spectra()' if transposed else 'psf_spectrum()'}, "
                         f"shape {expected}, got {tuple(psf_f.shape)}")
