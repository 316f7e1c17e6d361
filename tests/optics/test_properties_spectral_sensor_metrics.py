"""Property-based tests (hypothesis) of the core pure functions on unusual but legal inputs: odd and prime
sizes, 1-px images, one band, many bands, non-uniform band grids, extreme wavelengths, float64 input,
non-contiguous tensors, batches whose items differ. Each property is checked against an independent
reference: a closed form, a brute force in numpy, scikit-image, colour-science or the definition."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hsicam import metrics
from hsicam.color import srgb_encode, srgb_weights, xyz_to_linear_srgb_matrix, xyz_weights
from hsicam.data.cube import check_cube, normalize_per_cube_max, resample_cube
from hsicam.models.demosaic import demosaic, phase_linear
from hsicam.models.tv import chambolle_step, dual_divergence, forward_differences
from hsicam.sensor import SensorNoise, cfa_tile, poisson_gaussian_noise, quantize_bits, tile_pattern
from hsicam.spectral import Bands, resample_spectra
from hsicam.spectral.bands import band_matrix, band_sample_wavelengths, resampling_matrix
from hsicam.spectral.materials import FusedSilica, TabulatedMaterial

PROP = settings(max_examples=30, deadline=None, derandomize=True, database=None)
FEW = settings(max_examples=15, deadline=None, derandomize=True, database=None)

seeds = st.integers(0, 2**31 - 1)


def _grid(seed: int, n: int, start: float, mean_step: float) -> np.ndarray:
    """n strictly ascending centres from ``start`` with steps in [0.2, 1.8] × ``mean_step`` (non-uniform)."""
    rng = np.random.default_rng(seed)
    return start + np.concatenate([[0.0], np.cumsum(mean_step * rng.uniform(0.2, 1.8, n - 1))])


# ------------------------------------------------------------------------------------------------
# Bands and resampling
# ------------------------------------------------------------------------------------------------
@PROP
@given(start=st.floats(1e-3, 5e4), step=st.floats(1e-3, 1e3), n=st.integers(1, 400))
def test_uniform_bands_are_the_arithmetic_progression(start, step, n):
    """Bands.uniform(start, start + (n-1)·step, step) has n bands at start + k·step (reference: the formula)."""
    stop = start + (n - 1) * step
    b = Bands.uniform(start, stop, step)
    assert len(b) == n
    np.testing.assert_allclose(b.centers_nm, start + step * np.arange(n), rtol=1e-9, atol=1e-9 * step)
    assert np.all(b.fwhm_nm == step)


@PROP
@given(seed=seeds, n=st.integers(1, 40), start=st.floats(0.5, 3000.0), step=st.floats(0.01, 50.0),
       fwhm_scale=st.floats(0.05, 1.0))
def test_resampling_onto_own_grid_is_identity(seed, n, start, step, fwhm_scale):
    """A spectrum resampled onto its own (non-uniform) grid, no band wider than its own, comes back as is."""
    c = _grid(seed, n, start, step)
    src = Bands(c, np.full(n, step))
    dst = Bands(c, np.full(n, step * fwhm_scale))  # same or narrower bands: nothing left to average
    v = np.random.default_rng(seed + 1).random((n, 3))
    np.testing.assert_array_equal(resample_spectra(v, src, dst, axis=0), v)
    np.testing.assert_allclose(resampling_matrix(src, dst), np.eye(n), atol=1e-12)


@PROP
@given(seed=seeds, n=st.integers(2, 30), m=st.integers(1, 30), start=st.floats(1.0, 2000.0),
       step=st.floats(0.05, 30.0), fwhm_factor=st.floats(0.1, 6.0))
def test_resampling_keeps_constants_and_linear_spectra(seed, n, m, start, step, fwhm_factor):
    """Rows of the resampling matrix sum to 1 and a spectrum linear in wavelength is kept exactly at the
    target centres, for any (non-uniform) source, any target inside, narrower or wider (module docstring)."""
    c = _grid(seed, n, start, step)
    rng = np.random.default_rng(seed + 7)
    src = Bands(c, step * rng.uniform(0.5, 1.5, n))
    t = np.unique(rng.uniform(c[0], c[-1], m))
    dst = Bands(t, fwhm_factor * step * rng.uniform(0.5, 1.5, t.size))
    w = resampling_matrix(src, dst)
    assert np.all(w >= -1e-12)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    a, b = rng.normal(), rng.normal()
    lin = a + b * (c - c[0]) / (c[-1] - c[0])
    np.testing.assert_allclose(w @ lin, a + b * (t - c[0]) / (c[-1] - c[0]), atol=1e-9 * (abs(a) + abs(b) + 1))


@PROP
@given(seed=seeds, n=st.integers(1, 20), f=st.integers(1, 60), start=st.floats(1.0, 2000.0),
       step=st.floats(0.05, 30.0), fwhm=st.floats(0.01, 80.0))
def test_band_matrix_rows_are_averages(seed, n, f, start, step, fwhm):
    """band_matrix: non-negative rows summing to 1 (a band average), for any fine grid, narrow or wide bands."""
    c = _grid(seed, n, start, step)
    fine = _grid(seed + 3, f, start - step, 3 * step * max(n, 1) / max(f, 1))
    g = band_matrix(Bands(c, np.full(n, fwhm)), fine)
    assert g.shape == (n, f)
    assert np.all(np.isfinite(g)) and np.all(g >= 0)
    np.testing.assert_allclose(g.sum(axis=1), 1.0, rtol=1e-12)


@PROP
@given(seed=seeds, n=st.integers(1, 20), m=st.integers(1, 15), fwhm=st.floats(1e-3, 1e3))
def test_band_sample_wavelengths_are_centred_averages(seed, n, m, fwhm):
    """M sub-wavelengths inside the FWHM, weights summing to 1, symmetric about the centre (mean = centre)."""
    c = _grid(seed, n, 400.0, 10.0)
    lam, w = band_sample_wavelengths(c, np.full(n, fwhm), m)
    assert lam.shape == w.shape == (n, m)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose((lam * w).sum(axis=1), c, rtol=1e-12, atol=1e-9 * fwhm)
    assert np.all(np.abs(lam - c[:, None]) <= fwhm / 2)


# ------------------------------------------------------------------------------------------------
# Materials
# ------------------------------------------------------------------------------------------------
def _malitson(lam_um: np.ndarray) -> np.ndarray:
    """Malitson (1965), JOSA 55, 1205, eq. (as published): n² − 1 = Σ B_i λ² / (λ² − λ_i²)."""
    l2 = lam_um**2
    return np.sqrt(1 + 0.6961663 * l2 / (l2 - 0.0684043**2) + 0.4079426 * l2 / (l2 - 0.1162414**2)
                   + 0.8974794 * l2 / (l2 - 9.896161**2))


@PROP
@given(lam=st.lists(st.floats(210.0, 3710.0), min_size=1, max_size=20))
def test_fused_silica_is_malitson_and_normally_dispersive(lam):
    lam = np.array(lam)
    n = FusedSilica().n(lam)
    np.testing.assert_allclose(n, _malitson(lam * 1e-3), rtol=1e-12)
    order = np.argsort(lam)
    assert np.all(np.diff(n[order]) <= 1e-15)  # normal dispersion over the whole fit range (poles outside it)


def test_fused_silica_published_values():
    """Values tabulated by Malitson / refractiveindex.info: n_d (587.6 nm) = 1.4585, n (1014 nm) = 1.4502."""
    np.testing.assert_allclose(FusedSilica().n(np.array([587.56, 1013.98])), [1.45846, 1.45024], atol=5e-5)


@PROP
@given(seed=seeds, k=st.integers(2, 30), q=st.integers(1, 30))
def test_tabulated_material_interpolates_linearly(seed, k, q):
    """At the table's nodes its own values; between them the straight line through the two neighbours."""
    rng = np.random.default_rng(seed)
    wl = _grid(seed, k, rng.uniform(200, 1000), rng.uniform(0.1, 100))
    n = 1 + rng.random(k)
    mat = TabulatedMaterial(wl, n)
    np.testing.assert_array_equal(mat.n(wl), n)
    x = rng.uniform(wl[0], wl[-1], q)
    j = np.clip(np.searchsorted(wl, x) - 1, 0, k - 2)
    ref = n[j] + (n[j + 1] - n[j]) * (x - wl[j]) / (wl[j + 1] - wl[j])
    np.testing.assert_allclose(mat.n(x), ref, rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# Metrics
# ------------------------------------------------------------------------------------------------
def _pair(seed, b, c, h, w, dtype=torch.float32, noise=0.1):
    g = torch.Generator().manual_seed(seed)
    y = torch.rand(b, c, h, w, generator=g, dtype=torch.float64)
    x = (y + noise * torch.randn(b, c, h, w, generator=g, dtype=torch.float64)).clamp(0, 1)
    return x.to(dtype), y.to(dtype)


@PROP
@given(seed=seeds, b=st.integers(1, 3), c=st.integers(1, 7), h=st.integers(1, 13), w=st.integers(1, 13),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_psnr_rmse_ergas_are_the_formulas(seed, b, c, h, w, dtype):
    """PSNR per band / cube, RMSE and ERGAS against scikit-image and numpy, per batch item."""
    from skimage.metrics import peak_signal_noise_ratio as sk_psnr

    x, y = _pair(seed, b, c, h, w, dtype)
    xn, yn = x.double().numpy(), y.double().numpy()
    for i in range(b):
        bands = [sk_psnr(yn[i, k], xn[i, k], data_range=1.0) for k in range(c)]
        bands = [min(v, 300.0) for v in bands]
        assert float(metrics.psnr_per_band(x, y)[i]) == pytest.approx(np.mean(bands), rel=1e-9)
        assert float(metrics.psnr_cube(x, y)[i]) == pytest.approx(min(sk_psnr(yn[i], xn[i], data_range=1.0), 300.0), rel=1e-9)
        assert float(metrics.rmse(x, y)[i]) == pytest.approx(np.sqrt(np.mean((xn[i] - yn[i]) ** 2)), rel=1e-9, abs=1e-15)
        rb = np.sqrt(((xn[i] - yn[i]) ** 2).mean(axis=(1, 2)))
        mb = np.maximum(np.abs(yn[i].mean(axis=(1, 2))), 1e-12)
        assert float(metrics.ergas(x, y)[i]) == pytest.approx(100 * np.sqrt(np.mean((rb / mb) ** 2)), rel=1e-9)
        # batch item i of the batched call is the call on item i alone
        assert float(metrics.psnr_per_band(x[i], y[i])[0]) == float(metrics.psnr_per_band(x, y)[i])


@FEW
@given(seed=seeds, b=st.integers(1, 2), c=st.integers(1, 3), h=st.integers(11, 23), w=st.integers(11, 23),
       dtype=st.sampled_from([torch.float32, torch.float64]), noise=st.sampled_from([0.0, 0.02, 0.3]))
def test_ssim_is_scikit_image(seed, b, c, h, w, dtype, noise):
    """SSIM = skimage structural_similarity(gaussian_weights, σ 1.5, population covariance, range 1), mean over
    bands, for odd, prime and non-square sizes down to the 11-px window."""
    from skimage.metrics import structural_similarity

    x, y = _pair(seed, b, c, h, w, dtype, noise)
    got = metrics.ssim(x, y)
    for i in range(b):
        ref = np.mean([structural_similarity(y[i, k].double().numpy(), x[i, k].double().numpy(), gaussian_weights=True,
                                             sigma=1.5, use_sample_covariance=False, data_range=1.0)
                       for k in range(c)])
        assert float(got[i]) == pytest.approx(ref, abs=1e-6)


@FEW
@given(seed=seeds, h=st.integers(11, 20), w=st.integers(11, 20))
def test_ssim_chunked_path_equals_matrix_path(seed, h, w):
    """The large-image path (shifted multiply-adds, bands in chunks) gives the matrix path's value."""
    x, y = _pair(seed, 2, 5, h, w, torch.float64)
    ref = metrics.ssim(x, y)
    old = (metrics._SSIM_MATRIX_MAX_PX, metrics._SSIM_CHUNK_BYTES)
    try:
        metrics._SSIM_MATRIX_MAX_PX, metrics._SSIM_CHUNK_BYTES = 1, 5 * 2 * h * w * 8 * 2  # 2 bands per chunk
        got = metrics.ssim(x, y)
    finally:
        metrics._SSIM_MATRIX_MAX_PX, metrics._SSIM_CHUNK_BYTES = old
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


@PROP
@given(seed=seeds, b=st.integers(1, 3), c=st.integers(1, 8), h=st.integers(1, 6), w=st.integers(1, 6),
       zero_frac=st.sampled_from([0.0, 0.3, 1.0]), scale=st.sampled_from([1e-30, 1.0, 1e30]),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_sam_is_the_angle_brute_force(seed, b, c, h, w, zero_frac, scale, dtype):
    """SAM per pixel = arccos(<x, y> / |x||y|) in degrees (numpy, long double not needed at these scales after
    scaling), all-zero truth excluded, all-zero estimate 90°; mean per cube; NaN when nothing is defined."""
    rng = np.random.default_rng(seed)
    y = rng.random((b, c, h, w)) * (rng.random((b, 1, h, w)) >= zero_frac)
    x = np.abs(y + 0.2 * rng.normal(size=y.shape)) * (rng.random((b, 1, h, w)) > 0.2)
    x, y = x * scale, y * scale
    xt, yt = torch.tensor(x, dtype=dtype), torch.tensor(y, dtype=dtype)
    xs, ys = xt.double().numpy() / scale, yt.double().numpy() / scale  # what the metric sees, rescaled
    got = metrics.sam_degrees(xt, yt).numpy()
    for i in range(b):
        angles = []
        for r in range(h):
            for s in range(w):
                u, v = xs[i, :, r, s], ys[i, :, r, s]
                if not np.any(v != 0):
                    continue
                if not np.any(u != 0):
                    angles.append(90.0)
                    continue
                cos = np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))
                angles.append(math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
        if not angles:
            assert math.isnan(got[i])
        else:
            assert got[i] == pytest.approx(np.mean(angles), abs=1e-5)


# ------------------------------------------------------------------------------------------------
# Colour
# ------------------------------------------------------------------------------------------------
def test_srgb_matrix_is_colour_science():
    """The matrix derived from the sRGB primaries and D65 (colour-science's normalised primary matrix; its
    RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB is IEC 61966-2-1's 4-decimal rounding of it, 3.2406 for 3.24097)."""
    colour = pytest.importorskip("colour")
    npm = colour.normalised_primary_matrix(np.array([[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]]),
                                           np.array([0.3127, 0.3290]))
    np.testing.assert_allclose(xyz_to_linear_srgb_matrix(), np.linalg.inv(npm), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(xyz_to_linear_srgb_matrix(), colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB, atol=5e-4)


@PROP
@given(x=st.lists(st.floats(-1.0, 2.0), min_size=1, max_size=30))
def test_srgb_encode_is_colour_science(x):
    colour = pytest.importorskip("colour")
    x = np.array(x)
    ref = colour.cctf_encoding(np.clip(x, 0, 1), function="sRGB")
    np.testing.assert_allclose(srgb_encode(x), ref, atol=1e-12)
    np.testing.assert_allclose(srgb_encode(torch.tensor(x)).numpy(), ref, atol=1e-12)


@PROP
@given(seed=seeds, n=st.integers(1, 60), start=st.floats(300.0, 900.0), step=st.floats(0.5, 40.0))
def test_white_reflector_is_y_one_and_weights_finite(seed, n, start, step):
    """Any grid (inside, across or outside 380-780 nm, one band or many, non-uniform): XYZ weights finite, the
    white reflector's Y = 1; sRGB weights finite; balanced grids map white to exactly (1, 1, 1)."""
    bands = Bands.from_centers(_grid(seed, n, start, step))
    w = xyz_weights(bands)
    assert w.shape == (3, n) and np.all(np.isfinite(w))
    assert w[1].sum() == pytest.approx(1.0, rel=1e-12)
    s = srgb_weights(bands)
    assert np.all(np.isfinite(s))
    white = s.sum(axis=1)
    assert np.allclose(white, 1.0) or not np.all((white > 1 / 3) & (white < 3))


# ------------------------------------------------------------------------------------------------
# Sensor
# ------------------------------------------------------------------------------------------------
@PROP
@given(seed=seeds, c=st.integers(1, 12), m=st.integers(1, 7), h=st.integers(1, 20), w=st.integers(1, 20),
       oy=st.integers(-30, 30), ox=st.integers(-30, 30))
def test_cfa_pattern_is_modulo_indexing(seed, c, m, h, w, oy, ox):
    """κ over a window at any origin is tile[:, (i + oy) mod m, (j + ox) mod m]; Σ_c κ = 1 everywhere."""
    from hsicam.sensor import ColorFilterArray

    cfa = ColorFilterArray(c, m, seed=seed)
    with torch.no_grad():
        cfa.weights[:, 0, 0] = -1.0  # one neutral pixel (all weights ≤ 0)
    tile = cfa.tile().detach()
    pat = cfa.pattern(h, w, (oy, ox)).detach()
    i = (torch.arange(h)[:, None] + oy) % m
    j = (torch.arange(w)[None, :] + ox) % m
    torch.testing.assert_close(pat, tile[:, i, j], rtol=0, atol=0)
    torch.testing.assert_close(pat.sum(0), torch.ones(h, w), rtol=0, atol=1e-6)


@PROP
@given(seed=seeds, bits=st.integers(1, 16), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_quantize_is_clip_and_round(seed, bits, dtype):
    g = torch.tensor(np.random.default_rng(seed).uniform(-0.5, 1.5, 200), dtype=dtype)
    levels = 2**bits - 1
    ref = np.round(np.clip(g.double().numpy(), 0, 1) * levels) / levels
    np.testing.assert_allclose(quantize_bits(g, bits).double().numpy(), ref, atol=1e-7 if dtype == torch.float32 else 0)


@FEW
@given(seed=seeds, level=st.floats(0.0, 1.0), full_well=st.sampled_from([1.0, 37.0, 1e3, 1e5]),
       read=st.sampled_from([0.0, 1.5, 20.0]), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_poisson_gaussian_statistics(seed, level, full_well, read, dtype):
    """Mean g and variance g/N + (r/N)² at a stated photon level (closed form), as SensorNoise.variance says."""
    n = 40_000
    g = torch.full((1, 1, 200, n // 200), level, dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    out = poisson_gaussian_noise(g, full_well, read, gen).double()
    var = level / full_well + (read / full_well) ** 2
    sd = math.sqrt(var)
    assert abs(float(out.mean()) - level) < 5 * sd / math.sqrt(n) + 1e-12
    if var > 0:
        assert float(out.var()) == pytest.approx(var, rel=0.06)
    model = SensorNoise("poisson_gaussian", 0.0, full_well, read)
    torch.testing.assert_close(model.variance(g).double().mean(), torch.tensor(var, dtype=torch.float64),
                               rtol=1e-6, atol=1e-30)


# ------------------------------------------------------------------------------------------------
# Demosaic and TV
# ------------------------------------------------------------------------------------------------
def _zero_padded_mean(x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Brute force: Σ_{u,v} w_u w_v x[i+u, j+v] (zeros outside), w normalised to sum 1, per (B, C)."""
    k = len(weights)
    r = k // 2
    b, c, h, w = x.shape
    p = np.zeros((b, c, h + 2 * r, w + 2 * r))
    p[..., r : r + h, r : r + w] = x
    out = np.zeros_like(x)
    for u in range(k):
        for v in range(k):
            out += weights[u] * weights[v] * p[..., u : u + h, v : v + w]
    return out


@PROP
@given(seed=seeds, b=st.integers(1, 2), c=st.integers(1, 6), h=st.integers(1, 13), w=st.integers(1, 13),
       m=st.integers(1, 5), window=st.sampled_from([1, 3, 5, 7, 9, 15]), kernel=st.sampled_from(["box", "tent"]),
       grey=st.floats(0.01, 10.0), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_demosaic_grey_scene_comes_back_and_is_the_brute_force(seed, b, c, h, w, m, window, kernel, grey, dtype):
    """A grey scene (every band v) gives g = v through any CFA (Σκ = 1) and the demosaic returns v at every pixel,
    border included, any window and size; in general it is the brute-force ratio of zero-padded weighted sums.
    (Grey comes back only where the band is seen: a filter that blocks band c at every pixel of the window gives 0,
    the clamped 0/0; so the grey part uses filters that pass every band, the brute-force part zero filters too.)"""
    gen = torch.Generator().manual_seed(seed)
    code = tile_pattern(cfa_tile(torch.rand(c, m, m, generator=gen) + 0.05), h, w).to(dtype)
    g = torch.full((b, 1, h, w), grey, dtype=dtype)
    out = demosaic(g, code, window, kernel)
    torch.testing.assert_close(out, torch.full((b, c, h, w), grey, dtype=dtype),
                               rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
    code = tile_pattern(cfa_tile(torch.rand(c, m, m, generator=gen) - 0.3), h, w).to(dtype)
    scene = torch.rand(b, c, h, w, generator=gen, dtype=torch.float64)
    g = (scene * code.double()).sum(1, keepdim=True).to(dtype)
    out = demosaic(g, code, window, kernel).double().numpy()
    r = window // 2
    wts = np.ones(window) if kernel == "box" else (r + 1 - np.abs(np.arange(-r, r + 1))).astype(float)
    wts = wts / wts.sum()
    num = _zero_padded_mean(g.double().numpy() * code.double().numpy()[None], wts)
    den = _zero_padded_mean(code.double().numpy()[None], wts)
    np.testing.assert_allclose(out, num / np.maximum(den, 1e-6), rtol=1e-5 if dtype == torch.float32 else 1e-10)


@PROP
@given(seed=seeds, b=st.integers(1, 2), c=st.integers(1, 4), h=st.integers(1, 12), w=st.integers(1, 12),
       channels_last=st.booleans())
def test_tv_divergence_is_minus_the_adjoint_of_the_gradient(seed, b, c, h, w, channels_last):
    """<∇d, p> = −<d, div p> for p with zero last row (py) / column (px); fast and differentiable paths agree."""
    gen = torch.Generator().manual_seed(seed)
    d = torch.randn(b, c, h, w, generator=gen, dtype=torch.float64)
    py = torch.randn(b, c, h, w, generator=gen, dtype=torch.float64)
    px = torch.randn(b, c, h, w, generator=gen, dtype=torch.float64)
    py[..., -1, :] = 0
    px[..., :, -1] = 0
    if channels_last:
        d, py, px = (t.to(memory_format=torch.channels_last) for t in (d, py, px))
    gy, gx = forward_differences(d)
    div = dual_divergence(py, px)
    lhs = float((gy * py).sum() + (gx * px).sum())
    rhs = -float((d * div).sum())
    assert lhs == pytest.approx(rhs, rel=1e-10, abs=1e-10)
    # numpy reference of the forward differences
    dn = d.numpy()
    ref_y = np.zeros_like(dn)
    ref_y[..., :-1, :] = dn[..., 1:, :] - dn[..., :-1, :]
    ref_x = np.zeros_like(dn)
    ref_x[..., :, :-1] = dn[..., :, 1:] - dn[..., :, :-1]
    np.testing.assert_allclose(gy.numpy(), ref_y, atol=1e-14)
    np.testing.assert_allclose(gx.numpy(), ref_x, atol=1e-14)
    dr = d.clone().requires_grad_(True)
    gy2, gx2 = forward_differences(dr)
    torch.testing.assert_close(gy2.detach(), gy)
    torch.testing.assert_close(gx2.detach(), gx)
    torch.testing.assert_close(dual_divergence(py.clone().requires_grad_(True), px).detach(), div)


@FEW
@given(seed=seeds, c=st.integers(1, 3), h=st.integers(1, 10), w=st.integers(1, 10), weight=st.floats(0.01, 2.0),
       vectorial=st.booleans())
def test_tv_prox_keeps_the_mean_and_lowers_tv(seed, c, h, w, weight, vectorial):
    """u = f − w div p after Chambolle's iterations: mean of u = mean of f (div sums to 0), TV(u) ≤ TV(f), and the
    prox objective ½|u − f|² + w TV(u) ≤ its value at u = f."""
    gen = torch.Generator().manual_seed(seed)
    f = torch.rand(1, c, h, w, generator=gen, dtype=torch.float64)
    py, px = torch.zeros_like(f), torch.zeros_like(f)
    for _ in range(200):
        py, px = chambolle_step(py, px, f / weight, vectorial=vectorial)
    u = f - weight * dual_divergence(py, px)

    def tv(z):
        gy, gx = forward_differences(z)
        if vectorial:
            return float((gy.square().sum(1) + gx.square().sum(1)).sqrt().sum())
        return float(torch.hypot(gy, gx).sum())

    torch.testing.assert_close(u.mean(dim=(-2, -1)), f.mean(dim=(-2, -1)), rtol=0, atol=1e-12)
    assert tv(u) <= tv(f) + 1e-9
    assert 0.5 * float((u - f).square().sum()) + weight * tv(u) <= weight * tv(f) + 1e-9


@PROP
@given(seed=seeds, m=st.integers(1, 4), k=st.sampled_from([1, 3, 5]), h=st.integers(1, 11), w=st.integers(1, 11),
       oy=st.integers(0, 7), ox=st.integers(0, 7), b=st.integers(1, 2))
def test_phase_linear_is_the_brute_force(seed, m, k, h, w, oy, ox, b):
    """Each output pixel = the K×K replicate-padded neighbourhood · W[phase of the pixel on the whole sensor]."""
    gen = torch.Generator().manual_seed(seed)
    c = 2
    g = torch.rand(b, 1, h, w, generator=gen, dtype=torch.float64)
    wt = torch.randn(m * m, c, k, k, generator=gen, dtype=torch.float64)
    out = phase_linear(g, wt, (oy, ox)).numpy()
    r = k // 2
    p = np.pad(g.numpy()[:, 0], ((0, 0), (r, r), (r, r)), mode="edge")
    ref = np.zeros((b, c, h, w))
    for i in range(h):
        for j in range(w):
            q = ((i + oy) % m) * m + (j + ox) % m
            patch = p[:, i : i + k, j : j + k]
            ref[:, :, i, j] = np.einsum("buv,cuv->bc", patch, wt[q].numpy())
    np.testing.assert_allclose(out, ref, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Cubes
# ------------------------------------------------------------------------------------------------
@PROP
@given(seed=seeds, c=st.integers(1, 6), h=st.integers(1, 7), w=st.integers(1, 7),
       dtype=st.sampled_from([np.float64, np.float32, np.uint8, np.uint16, np.int32]), transpose=st.booleans())
def test_check_and_normalise_cube(seed, c, h, w, dtype, transpose):
    """check_cube: float32 C-contiguous, the same values (non-contiguous input too); normalised max is exactly 1."""
    rng = np.random.default_rng(seed)
    arr = (rng.random((c, w, h) if transpose else (c, h, w)) * 200 + 1).astype(dtype)
    if transpose:
        arr = arr.transpose(0, 2, 1)
    out = check_cube(arr)
    assert out.dtype == np.float32 and out.flags.c_contiguous and out.shape == (c, h, w)
    np.testing.assert_array_equal(out, arr.astype(np.float32))
    norm, peak = normalize_per_cube_max(out)
    assert peak == float(arr.astype(np.float32).max()) and norm.max() == 1.0 and norm.dtype == np.float32


@PROP
@given(seed=seeds, n=st.integers(2, 25), m=st.integers(1, 25))
def test_resample_cube_is_resample_spectra_per_pixel(seed, n, m):
    """resample_cube = resampling_matrix @ each pixel's spectrum (float64 reference), returned as float32."""
    rng = np.random.default_rng(seed)
    src = Bands.from_centers(_grid(seed, n, 400.0, 10.0))
    dst = Bands(np.unique(rng.uniform(src.min_nm, src.max_nm, m)), rng.uniform(1, 40))
    cube = rng.random((n, 3, 4)).astype(np.float32)
    ref = np.einsum("dc,chw->dhw", resampling_matrix(src, dst), cube.astype(np.float64))
    out = resample_cube(cube, src, dst)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------------------------------------
# More references: brute-force band integrals, colour-science's XYZ, gain maps, round trips
# ------------------------------------------------------------------------------------------------
@FEW
@given(seed=seeds, n=st.integers(2, 25), step=st.floats(0.2, 20.0), fwhm_factor=st.floats(1.2, 8.0),
       pos=st.floats(0.0, 1.0))
def test_wide_band_is_the_gaussian_integral_of_the_interpolant(seed, n, step, fwhm_factor, pos):
    """A band wider than the source's: ∫ interp(s, v)(x) G_f(x − c) dx / ∫ G_f over the symmetric reach
    min(3σ, distance to the nearer end), f = √(f_dst² − f_src²) (brute force: 200001 nodes, np.interp, trapz).
    Tolerance 1e-4 of the values' scale: the module's trapezoid on 0.05 nm nodes does not put a node on the
    interpolant's kinks (source centres), an error of up to ~2e-5 (measured: 0.353070 vs 0.353065 on 3 bands)."""
    rng = np.random.default_rng(seed)
    s = _grid(seed, n, 500.0, step)
    src = Bands(s, np.full(n, step))
    c = s[0] + pos * (s[-1] - s[0])
    dst = Bands([c], [fwhm_factor * step])
    v = rng.random(n)
    f = math.sqrt((fwhm_factor * step) ** 2 - step**2)
    sigma = f / (2 * math.sqrt(2 * math.log(2)))
    reach = max(min(3 * sigma, c - s[0], s[-1] - c), 0.0)
    got = float((resampling_matrix(src, dst) @ v)[0])
    if reach == 0.0:
        ref = float(np.interp(c, s, v))
    else:
        x = np.linspace(c - reach, c + reach, 200_001)
        gw = np.exp(-0.5 * ((x - c) / sigma) ** 2)
        ref = float(np.trapezoid(gw * np.interp(x, s, v), x) / np.trapezoid(gw, x))
    assert got == pytest.approx(ref, abs=1e-4)


@pytest.mark.filterwarnings("ignore:Aligning")  # colour-science aligns its D65 to the 1 nm CMFs, as we ask
@FEW
@given(seed=seeds, n=st.integers(1, 6))
def test_xyz_is_colour_science_on_a_1nm_grid(seed, n):
    """XYZ of a smooth reflectance on the 1 nm 380-780 grid = colour-science's sd_to_XYZ (integration, CIE 1931 2°,
    D65, k so that white has Y = 1), to the accuracy of the shipped 5 nm table (its linear interpolation)."""
    colour = pytest.importorskip("colour")
    lam = np.arange(380.0, 781.0)
    rng = np.random.default_rng(seed)
    refl = 0.5 + 0.4 * np.sin(np.outer(rng.uniform(0.005, 0.03, n), lam) + rng.uniform(0, 6, (n, 1)))
    got = xyz_weights(Bands.from_centers(lam)) @ refl.T  # (3, n)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    illum = colour.SDS_ILLUMINANTS["D65"]
    shape = colour.SpectralShape(380, 780, 1)
    for k in range(n):
        sd = colour.SpectralDistribution(dict(zip(lam, refl[k])))
        ref = colour.sd_to_XYZ(sd, cmfs, illum, method="Integration", shape=shape) / 100.0
        np.testing.assert_allclose(got[:, k], ref, rtol=0, atol=2e-3)


@FEW
@given(seed=seeds, level=st.floats(0.05, 1.0), sigma=st.sampled_from([0.0, 0.01]),
       bits=st.sampled_from([None, 8]))
def test_gain_map_noise_variance_is_declared(seed, level, sigma, bits):
    """With a per-pixel gain a the noisy image is a·n(g/a): mean g and variance a²·v(g/a), which variance() states."""
    gain = torch.tensor([[0.5, 1.0], [2.0, 3.0]]).repeat(50, 50)  # (100, 100)
    model = SensorNoise("poisson_gaussian", sigma, 500.0, 3.0, bits, gain=gain)
    g = torch.full((8, 1, 100, 100), level)
    out = model(g, torch.Generator().manual_seed(seed)).double()
    var = model.variance(g[:1]).double()[0, 0]
    for a in (0.5, 1.0, 2.0, 3.0):
        sel = gain == a
        emp = out[:, 0][:, sel]
        n = emp.numel()
        want = float(var[sel].mean())
        u = level / a
        sd = math.sqrt(want) / a
        # the ADC clips at 0 and full scale: within 4 σ of either the statistics are not Poisson-Gaussian (and
        # Δ²/12 is the quantiser's variance only for noise wider than a step)
        if bits is None or (u - 4 * sd > 0 and u + 4 * sd < 1 and sd > 1 / 255):
            assert float(emp.mean()) == pytest.approx(level, abs=6 * math.sqrt(want / n) + 2 * a / 255)
            assert float(emp.var()) == pytest.approx(want, rel=0.1)


@PROP
@given(seed=seeds, n=st.integers(1, 50), start=st.floats(0.1, 5000.0), step=st.floats(0.01, 100.0))
def test_bands_dict_round_trip_and_equality(seed, n, start, step):
    """to_dict → from_dict (and through JSON text) gives equal Bands with the same centres and FWHM bit for bit."""
    import json

    b = Bands(_grid(seed, n, start, step), np.random.default_rng(seed).uniform(0.1, 20, n))
    back = Bands.from_dict(json.loads(json.dumps(b.to_dict())))
    assert back == b and hash(back) == hash(b)
    np.testing.assert_array_equal(back.centers_nm, b.centers_nm)
    np.testing.assert_array_equal(back.fwhm_nm, b.fwhm_nm)
    np.testing.assert_array_equal(b.wavelengths_m().numpy(), b.centers_nm * 1e-9)


@PROP
@given(seed=seeds, n=st.integers(2, 12), m=st.integers(1, 12), b=st.integers(1, 3), channels_last=st.booleans())
def test_conform_bands_torch_equals_numpy_per_item(seed, n, m, b, channels_last):
    """conform_bands on a (B, C, H, W) float64 tensor (channels-last too) = the numpy float64 computation per item."""
    from hsicam.data.cube import conform_bands

    rng = np.random.default_rng(seed)
    src = Bands(_grid(seed, n, 450.0, 12.0), rng.uniform(1, 20, n))
    dst = Bands(np.unique(rng.uniform(src.min_nm, src.max_nm, m)), rng.uniform(1, 40))
    cube = torch.tensor(rng.random((b, n, 3, 5)))
    if channels_last:
        cube = cube.to(memory_format=torch.channels_last)
    out = conform_bands(cube, src, dst, note=False)
    assert out.dtype == torch.float64 and out.shape == (b, len(dst), 3, 5)
    w = resampling_matrix(src, dst)
    for i in range(b):
        np.testing.assert_allclose(out[i].numpy(), np.einsum("dc,chw->dhw", w, cube[i].numpy()), rtol=1e-12, atol=1e-14)


@FEW
@given(seed=seeds, b=st.integers(1, 3), h=st.integers(11, 15), w=st.integers(11, 15), c=st.integers(1, 4))
def test_all_metrics_per_item_equals_alone(seed, b, h, w, c):
    """all_metrics of a batch whose items differ (one item's truth all zero) = all_metrics of each item alone."""
    x, y = _pair(seed, b, c, h, w)
    y[0] = 0
    batch = metrics.all_metrics(x, y)
    for i in range(b):
        alone = metrics.all_metrics(x[i : i + 1], y[i : i + 1])
        for k, v in batch.items():
            assert v[i] == pytest.approx(alone[k][0], rel=1e-12, nan_ok=True), k


# ------------------------------------------------------------------------------------------------
# Regressions of the findings
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("full_well", [1e5, 1e6])
def test_poisson_gaussian_noise_of_a_half_precision_image_counts_beyond_65504_electrons(full_well):
    """A float16 image at 0.9 of a 10⁵ e⁻ full well: 90 000 electrons overflowed half precision and every pixel came
    back −inf; the noise is counted in float32 and the image keeps its dtype, with mean g and variance g/N + (r/N)²."""
    g = torch.full((1, 1, 64, 64), 0.9, dtype=torch.float16)
    out = poisson_gaussian_noise(g, full_well, 2.0, torch.Generator().manual_seed(0))
    assert out.dtype == torch.float16
    assert bool(torch.isfinite(out).all())
    var = 0.9 / full_well + (2.0 / full_well) ** 2
    step = 2.0**-11  # half precision's spacing just below 1
    assert float(out.float().mean()) == pytest.approx(0.9, abs=5 * math.sqrt(var / out.numel()) + step)
    if var > 10 * step**2:  # the shot noise spans several half-precision steps: its variance is measurable
        assert float(out.float().var()) == pytest.approx(var, rel=0.15)


@PROP
@given(seed=seeds, dtype=st.sampled_from([torch.float16, torch.bfloat16, torch.float32, torch.float64]),
       c=st.integers(1, 4), h=st.integers(1, 5), w=st.integers(1, 5))
def test_check_cube_takes_a_tensor_of_any_float_dtype(seed, dtype, c, h, w):
    """check_cube of a torch tensor (bfloat16 included: it has no numpy type, a TypeError) = its float32 values."""
    t = torch.rand(c, h, w, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)
    out = check_cube(t)
    assert out.dtype == np.float32 and out.shape == (c, h, w)
    np.testing.assert_array_equal(out, t.float().numpy())


@PROP
@given(seed=seeds, n=st.integers(1, 300), q=st.floats(0.0, 1.0), ties=st.booleans())
def test_sam_breakdown_quantile_is_torch_quantile(seed, n, q, ties):
    """The edge threshold of sam_breakdown = torch.quantile (linear interpolation) where torch's applies."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.rand(n, generator=gen, dtype=torch.float64)
    if ties:
        t = (t * 4).floor()
    torch.testing.assert_close(metrics._quantile(t, q), torch.quantile(t, q), rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_sam_breakdown_of_an_image_beyond_2_24_pixels():
    """A 4097×4096 image (2²⁴ + 4096 px): torch.quantile refused it ("quantile() input tensor is too large") and
    sam_breakdown stopped with a RuntimeError. A vertical step edge: the top 20 % of the gradient are its two
    columns' neighbours (numpy's quantile as the reference), SAM 0 for an estimate equal to the truth."""
    h, w = 4097, 4096
    y = torch.full((1, 1, h, w), 0.5)
    y[..., w // 2 :] = 1.0
    y[..., : h // 3, :] += torch.linspace(0, 0.1, w)  # a ramp over the top third: gradients of several sizes
    got = metrics.sam_breakdown(y, y)
    assert got["all"] == [0.0] and got["edges"] == [0.0] and got["dark_fraction"] == [0.0]
    gy, gx = np.gradient(y[0, 0].double().numpy())
    grad = np.sqrt(gx * gx + gy * gy)
    assert float(metrics._quantile(torch.from_numpy(grad).flatten(), 0.8)) == pytest.approx(np.quantile(grad, 0.8),
                                                                                             rel=1e-12)
