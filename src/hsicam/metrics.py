"""Image-quality metrics for hyperspectral cubes, with named conventions (DESIGN.md §5).

All functions take (B, C, H, W) tensors (or (C, H, W), treated as B = 1) with values on a
[0, 1] scale (peak 1 after per-cube max normalisation) and return one value per cube, shape (B,), except where
their own docstring says otherwise (``sam_map``: (B, H, W); ``sam_breakdown``, ``all_metrics``: dicts).

- ``psnr_per_band``: PSNR of each band with peak 1, then averaged over bands ("psnr_band_mean").
- ``psnr_cube``: PSNR over the whole cube with peak 1 ("psnr_cube").
- ``psnr_mst``: MST's ``torch_psnr`` recipe: both cubes times 256 and rounded, PSNR of each band with
  peak 255, averaged over bands.
- ``ssim``: per band, Gaussian window 11×11 with σ = 1.5, K = (0.01, 0.03), data range 1,
  averaged over bands and pixels of the 'valid' window positions (scikit-image's
  ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1)`` crops the same border).
- ``sam_degrees``: mean spectral angle in degrees over the pixels where it is defined: a pixel whose
  truth spectrum is all zero has no angle and is left out (:func:`sam_undefined_pixels` counts them);
  an estimate spectrum that is all zero where the truth is not counts as 90° (leaving it out would
  reward returning zeros); NaN for a cube whose truth is zero at every pixel.
- ``ergas``: NaN for a cube in which a band's truth mean is 0 (a band dark in the truth has no relative
  error; :func:`ergas_undefined`). ``rmse``.
- ``exact_zero_bands``: per cube, the bands zero in the truth that the estimate reproduces exactly (300 dB each in
  ``psnr_per_band``, which then outweighs the other bands).
"""

from __future__ import annotations

import math

import torch

from hsicam.devices import float64_device
from hsicam.errors import InputError

CONVENTIONS = {
    "psnr": ("per band, peak 1, mean over bands; a band reproduced exactly (MSE 0, e.g. a band dark in truth and "
             "estimate) counts 300 dB (MSE floored at 1e-30), where scikit-image would give inf"),
    "psnr_cube": "whole cube, peak 1 (MSE floored at 1e-30: an exact cube counts 300 dB)",
    "psnr_mst": ("MST's torch_psnr: x*256 rounded, per band, peak 255, mean over bands; a band equal after the "
                 "rounding counts 348 dB (MSE floored at 1e-30), where MST's code gives inf"),
    "ssim": "per band, Gaussian 11x11 sigma 1.5, K=(0.01,0.03), population covariance, data range 1, mean",
    "sam": ("mean spectral angle over pixels, degrees; pixels whose truth spectrum is all zero have no angle "
            "and are left out (sam_excluded_px counts them); an all-zero estimate spectrum where the truth is "
            "not counts as 90 degrees; undefined when the truth is zero at every pixel: NaN (null in the JSON "
            "files, nan in results.csv and results.md; results.json lists such scenes in sam_undefined, and a mean "
            "is over the other scenes)"),
    "ergas": ("100 * sqrt(mean_b (RMSE_b / mean_b)^2), resolution ratio 1, mean_b the truth's mean of band b "
              "(in float64, however small: no floor); undefined when a band's mean_b is 0 (a band zero at every "
              "pixel of the truth): NaN (null in the JSON "
              "files, nan in results.csv and results.md; results.json lists such scenes in ergas_undefined, and a "
              "mean is over the other scenes)"),
    "rmse": "whole cube",
}


def _check_pair(x: torch.Tensor, y: torch.Tensor) -> None:
    """:class:`InputError` unless ``x`` and ``y`` are floating torch tensors of one shape, (B, C, H, W) or (C, H, W)."""
    for t, what in ((x, "estimate"), (y, "truth")):
        if not isinstance(t, torch.Tensor):
            hint = ": torch.from_numpy(a)" if type(t).__module__ == "numpy" else ""
            raise InputError(f"{what} must be a torch.Tensor (B, C, H, W) or (C, H, W), got {type(t).__name__}{hint}")
        if not t.is_floating_point():  # 8- or 16-bit counts were scored on the peak-1 scale: PSNR −40 dB
            raise InputError(f"{what} must be floating-point with values on the peak-1 scale (the metrics' peak is 1), "
                             f"got {t.dtype}: divide counts by their full scale first (e.g. x.float() / 255)")
    if x.shape != y.shape:
        raise InputError(f"shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
    if x.dim() not in (3, 4):
        raise InputError(f"expected (B, C, H, W) or (C, H, W), got {tuple(x.shape)}")
    if min(x.shape[-3:]) < 1:  # an empty band axis or image: nothing to score (NaN or a reduction's IndexError)
        raise InputError(f"nothing to score: shape {tuple(x.shape)} has no bands or no pixels (C, H, W >= 1)")
    if x.device != y.device:
        raise InputError(f"the estimate is on {x.device}, the truth on {y.device}: move one of them")


def _batched(x: torch.Tensor, y: torch.Tensor, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    _check_pair(x, y)
    if x.dim() == 3:
        x, y = x[None], y[None]
    return _as(x, dtype), _as(y, dtype)


def _as(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``t`` in ``dtype``; float64 on the CPU for a device that has none (MPS: :func:`~hsicam.devices.float64_device`),
    so a score is the same whatever the device."""
    if dtype == torch.float64:
        t = t.to(float64_device(t.device))
    return t.to(dtype)


def _psnr_from_mse(mse: torch.Tensor, peak: float) -> torch.Tensor:
    """PSNR (dB) of a mean squared error; MSE 0 (an exact band) gives 300 dB instead of inf (CONVENTIONS)."""
    return 10.0 * torch.log10(peak**2 / mse.clamp_min(1e-30))


def psnr_per_band(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean over bands of each band's PSNR (peak 1), dB, (B,)."""
    x, y = _batched(x, y)
    return _psnr_from_mse((x - y).square().mean(dim=(-2, -1)), 1.0).mean(dim=1)


def psnr_cube(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """PSNR of the whole cube (peak 1), dB, (B,)."""
    x, y = _batched(x, y)
    return _psnr_from_mse((x - y).square().mean(dim=(1, 2, 3)), 1.0)


def psnr_mst(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """MST's ``torch_psnr`` (caiyuanhao1998/MST, simulation/train_code/utils.py), the convention of the
    CASSI papers that report MST-style numbers: both cubes multiplied by 256 (not 255) and rounded,
    each band's PSNR with peak 255, averaged over bands; no clipping. dB, (B,)."""
    x, y = _batched(x, y)
    xq, yq = torch.round(x * 256.0), torch.round(y * 256.0)
    return _psnr_from_mse((xq - yq).square().mean(dim=(-2, -1)), 255.0).mean(dim=1)


def rmse(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Root-mean-square error over the whole cube, (B,)."""
    x, y = _batched(x, y)
    return (x - y).square().mean(dim=(1, 2, 3)).sqrt()


def _gaussian_1d(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    r = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(r**2) / (2 * sigma**2))
    return g / g.sum()


def _valid_filter_matrix(n: int, g: torch.Tensor) -> torch.Tensor:
    """(n, n − k + 1) matrix M with (v @ M)[j] = Σ_i g[i] v[j + i]: a 'valid' 1-D correlation."""
    k = g.numel()
    idx = torch.arange(n, device=g.device)[:, None] - torch.arange(n - k + 1, device=g.device)[None, :]
    inside = (idx >= 0) & (idx < k)
    return torch.where(inside, g[idx.clamp(0, k - 1)], g.new_zeros(()))


# Above this side (px) the Gaussian window runs as shifted multiply-adds instead of band matrices
# (whose cost grows with the side): matrices are ~20× faster at patch sizes, the training loss's case.
_SSIM_MATRIX_MAX_PX = 512


#: Large images: SSIM's five filtered images are made for as many bands at a time as fit in this many bytes.
_SSIM_CHUNK_BYTES = 2**28


def _gaussian_filter_valid(t: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (..., H, W), 'valid' area (..., H − k + 1, W − k + 1).

    Large images: k shifted multiply-adds per axis, in place (a convolution's im2col would unfold
    k copies of the image: 10 GB for 31 bands at 884² in float64)."""
    h, w = t.shape[-2:]
    if max(h, w) <= _SSIM_MATRIX_MAX_PX:
        return _valid_filter_matrix(h, g).T @ (t @ _valid_filter_matrix(w, g))
    weights = g.tolist()  # once (each float() of a CUDA tensor would wait for the device)
    k = len(weights)
    hh, ww = h - k + 1, w - k + 1
    rows = t[..., 0:hh, :] * weights[0]
    for i in range(1, k):
        rows.add_(t[..., i : i + hh, :], alpha=weights[i])
    out = rows[..., :, 0:ww] * weights[0]
    for i in range(1, k):
        out.add_(rows[..., :, i : i + ww], alpha=weights[i])
    return out


#: Side of SSIM's Gaussian window (px): images smaller than this have no SSIM.
SSIM_WINDOW_PX = 11


def ssim(x: torch.Tensor, y: torch.Tensor, window: int = SSIM_WINDOW_PX, sigma: float = 1.5, k1: float = 0.01,
         k2: float = 0.03, data_range: float = 1.0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Mean SSIM over bands (each band a grey image), Gaussian window, (B,). ``x`` is the estimate; ``window`` and
    the Gaussian's ``sigma`` in pixels, ``data_range`` on the cubes' scale.

    The window is separable: two 1-D passes (as band matrices at patch sizes: fast enough to train
    with, ``train.ssim_loss``, which computes in ``dtype`` float32); the 'valid' area, i.e.
    scikit-image's value with its default crop."""
    x, y = _batched(x, y, dtype)
    b, c, h, w = x.shape
    if min(h, w) < window:
        raise InputError(f"SSIM needs images of at least {window}×{window} px, got {h}×{w}")
    g = _gaussian_1d(window, sigma, x.dtype, x.device)
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    if max(h, w) <= _SSIM_MATRIX_MAX_PX:
        return _ssim_map(x, y, g, c1, c2).mean(dim=(1, 2, 3))
    # large images: a few bands at a time, so that memory stays near a few copies of the image
    step = max(1, _SSIM_CHUNK_BYTES // (5 * b * h * w * x.element_size()))
    total = sum(_ssim_map(x[:, i : i + step], y[:, i : i + step], g, c1, c2).sum(dim=(1, 2, 3))
                for i in range(0, c, step))
    return total / (c * (h - window + 1) * (w - window + 1))


def _ssim_map(x: torch.Tensor, y: torch.Tensor, g: torch.Tensor, c1: float, c2: float) -> torch.Tensor:
    """SSIM at every pixel of the 'valid' area of (B, C, H, W) ``x`` and ``y``, Gaussian window ``g``.

    As a loss (autograd recording, the truth ``y`` without gradient) the truth's statistics are filtered
    apart, without autograd: the filter's backward then runs over the estimate's three images, not all five."""
    if torch.is_grad_enabled() and not y.requires_grad:
        mx, xx, xy = _gaussian_filter_valid(torch.stack([x, x * x, x * y]), g)
        with torch.no_grad():
            my, yy = _gaussian_filter_valid(torch.stack([y, y * y]), g)
    else:
        mx, my, xx, yy, xy = _gaussian_filter_valid(torch.stack([x, y, x * x, y * y, x * y]), g)
    vx = xx - mx * mx
    vy = yy - my * my
    cxy = xy - mx * my
    return ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def spectra_scaled(t: torch.Tensor) -> torch.Tensor:
    """Each pixel's spectrum (dim 1) divided by its largest magnitude (all-zero spectra kept zero):
    the angle is scale-invariant, and the squared norms of the scaled spectra lie in [1, C], so they
    can neither underflow nor overflow."""
    peak = t.abs().amax(dim=1, keepdim=True)
    return t / torch.where(peak > 0, peak, torch.ones_like(peak))


def sam_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Spectral angle (degrees) between the spectra of corresponding pixels, (B, H, W); ``x`` is the
    estimate, ``y`` the truth.

    NaN where the truth spectrum is all zero (the angle is undefined); 90° where the estimate is
    all zero and the truth is not (no spectrum at all is as far as any from the truth's)."""
    x, y = _batched(x, y)
    xs, ys = spectra_scaled(x), spectra_scaled(y)
    norm = ((xs * xs).sum(dim=1) * (ys * ys).sum(dim=1)).sqrt()  # one root: exactly the dot product for x = y
    cos = ((xs * ys).sum(dim=1) / torch.where(norm > 0, norm, torch.ones_like(norm))).clamp(-1.0, 1.0)
    angle = torch.rad2deg(torch.acos(cos))  # a zero estimate: cos 0, 90°
    return torch.where(_sam_defined(y), angle, torch.full_like(angle, math.nan))


def _sam_defined(y: torch.Tensor) -> torch.Tensor:
    """(B, H, W) True where the truth spectrum is not all zero (the spectral angle is defined)."""
    return (y[None] if y.dim() == 3 else y).ne(0).any(dim=1)


def sam_undefined_pixels(y: torch.Tensor) -> torch.Tensor:
    """Pixels whose truth spectrum is all zero (no spectral angle: :func:`sam_degrees` leaves them
    out), per cube, (B,) int64."""
    return (~_sam_defined(y)).sum(dim=(-2, -1))


def sam_degrees(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean spectral angle (degrees) over the pixels where it is defined (:func:`sam_map`: not those
    whose truth spectrum is all zero), (B,); NaN for a cube whose truth is zero everywhere (and, as
    before, where the estimate holds a NaN at a scored pixel)."""
    angle = sam_map(x, y)
    defined = _sam_defined(y).to(angle.device)  # where the angle was computed (the CPU for MPS)
    total = torch.where(defined, angle, torch.zeros_like(angle)).sum(dim=(1, 2))
    return total / defined.sum(dim=(1, 2))  # 0/0: NaN where no pixel has an angle


def sam_breakdown(x: torch.Tensor, y: torch.Tensor, dark_level: float = 0.01, edge_quantile: float = 0.8
                  ) -> dict[str, list[float]]:
    """Where the spectral angle comes from, one entry per cube (``y`` the truth, peak 1):

    ``all`` (= :func:`sam_degrees`), ``dark_fraction`` (pixels whose truth has a band mean below
    ``dark_level``), mean SAM over the ``dark`` and the ``bright`` pixels, and over the bright
    pixels on ``edges`` (gradient magnitude of the truth's band mean, central differences, above
    its ``edge_quantile`` over the image) and off them (``flat``). As in :func:`sam_degrees`,
    pixels whose truth is all zero have no angle and count in no region's mean (they do count in
    ``dark_fraction``). NaN for a region without an angle.
    """
    angle = sam_map(x, y)
    _, y = _batched(x, y)
    level = y.mean(dim=1)  # (B, H, W)
    out: dict[str, list[float]] = {k: [] for k in ("all", "dark_fraction", "dark", "bright", "edges", "flat")}
    nan = float("nan")
    for a, b, t in zip(angle, level, y):
        gy, gx = torch.gradient(b)
        grad = (gx * gx + gy * gy).sqrt()
        edge = grad > _quantile(grad.flatten(), edge_quantile)
        dark = b < dark_level
        regions = {"dark": dark, "bright": ~dark, "edges": edge & ~dark, "flat": ~edge & ~dark}
        out["dark_fraction"].append(float(dark.double().mean()))
        defined = (t != 0).any(dim=0)  # the angle is undefined where the truth is all zero
        out["all"].append(float(a[defined].mean()) if bool(defined.any()) else nan)
        for k, mask in regions.items():
            mask = mask & defined
            out[k].append(float(a[mask].mean()) if bool(mask.any()) else nan)
    return out


def _quantile(t: torch.Tensor, q: float) -> torch.Tensor:
    """``torch.quantile(t, q)`` (linear interpolation) of a 1-D tensor of any length: torch's refuses more than
    2²⁴ elements ("input tensor is too large", a 4097×4096 image)."""
    pos = q * (t.numel() - 1)
    lo = math.floor(pos)
    values = torch.kthvalue(t, lo + 1).values
    if pos > lo:
        values = torch.lerp(values, torch.kthvalue(t, lo + 2).values, pos - lo)
    return values


def ergas(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """ERGAS (resolution ratio 1): 100·sqrt(mean over bands of (RMSE_b / mean_b(y))²), (B,); NaN for a cube
    in which a band's truth mean is 0 (:func:`ergas_undefined`: the ratio is undefined there, as SAM is for a
    truth zero at every pixel; a floor of 1e-12 on |mean_b| made it RMSE_b·10¹²: 5·10¹¹ for an error of 0.01 in
    one band of four). Any other mean_b, however small, divides as it is, in float64 (a floor at 1e-12 made a
    band of mean 5·10⁻¹⁴ count as one of 10⁻¹²: an ERGAS neither the formula's nor undefined); a ratio beyond
    float64 is +inf."""
    x, y = _batched(x, y)
    rmse_b = (x - y).square().mean(dim=(-2, -1)).sqrt()
    mean_b = y.mean(dim=(-2, -1)).abs()
    dark = (mean_b == 0).any(dim=1)
    value = 100.0 * (rmse_b / torch.where(mean_b == 0, 1.0, mean_b)).square().mean(dim=1).sqrt()
    return torch.where(dark, torch.full_like(value, math.nan), value)


def ergas_undefined(y: torch.Tensor) -> torch.Tensor:
    """(B,) True for a truth cube in which a band's mean is 0 (a band dark at every pixel): its ERGAS is
    undefined (:func:`ergas` gives NaN)."""
    y = y[None] if y.dim() == 3 else y
    return (_as(y, torch.float64).mean(dim=(-2, -1)) == 0).any(dim=1)


def exact_zero_bands(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(B,) the number of bands of each cube whose truth ``y`` is zero at every pixel and whose estimate ``x`` is
    exactly zero there too: each scores 300 dB in :func:`psnr_per_band` (MSE 0, CONVENTIONS["psnr"])."""
    x, y = _batched(x, y)
    return ((y == 0).all(dim=-1).all(dim=-1) & (x == 0).all(dim=-1).all(dim=-1)).sum(dim=1)


def all_metrics(estimate: torch.Tensor, truth: torch.Tensor) -> dict[str, list[float]]:
    """Every metric above, one list entry per cube (SAM NaN where :func:`sam_degrees` is, ERGAS NaN where
    :func:`ergas` is: undefined): ``{"psnr": [dB, ...], "psnr_cube": [dB], "psnr_mst": [dB], "ssim": [...],
    "sam": [degrees], "ergas": [...], "rmse": [...]}``. ``estimate`` and ``truth``: torch tensors of one shape,
    (B, C, H, W) or (C, H, W), values on a [0, 1] scale (peak 1); anything else is an :class:`InputError`."""
    _check_pair(estimate, truth)  # before the undefined-scene masks read the truth's shape
    fns = {"psnr": psnr_per_band, "psnr_cube": psnr_cube, "psnr_mst": psnr_mst, "ssim": ssim,
           "sam": sam_degrees, "ergas": ergas, "rmse": rmse}
    out = {}
    undefined = {"sam": (sam_undefined_pixels(truth) == truth.shape[-2] * truth.shape[-1]).tolist(),  # per cube
                 "ergas": ergas_undefined(truth).tolist()}
    for name, fn in fns.items():
        vals = fn(estimate, truth).tolist()
        # SAM is NaN, undefined, only for a truth that is zero everywhere (no angle anywhere), ERGAS only for a
        # truth with a band whose mean is 0; a NaN that a broken estimate (NaN pixels) gives is the worst score,
        # for every metric: −inf for those where higher is better (PSNR, SSIM), +inf for the errors (a NaN would
        # be skipped by a mean, and +inf PSNR read as a perfect band)
        worst = -math.inf if name in HIGHER_IS_BETTER else math.inf
        none = undefined.get(name, [False] * len(vals))
        out[name] = [v if math.isfinite(v) or (math.isnan(v) and u) else worst for v, u in zip(vals, none)]
    return out


#: The metrics of :func:`all_metrics` where a higher value is better (the others are errors).
HIGHER_IS_BETTER = frozenset({"psnr", "psnr_cube", "psnr_mst", "ssim"})
