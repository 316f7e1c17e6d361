"""Metrics against scikit-image and closed-form cases."""

from __future__ import annotations

import numpy as np
import math

import pytest
import torch
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity

from hsicam import metrics


@pytest.fixture
def pair():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 1, (5, 40, 36))
    est = np.clip(truth + rng.normal(0, 0.05, truth.shape), 0, 1)
    return torch.from_numpy(est), torch.from_numpy(truth)


def test_psnr_per_band_matches_skimage(pair):
    est, truth = pair
    ref = np.mean([peak_signal_noise_ratio(truth[c].numpy(), est[c].numpy(), data_range=1.0) for c in range(5)])
    assert metrics.psnr_per_band(est, truth).item() == pytest.approx(ref, rel=1e-10)
    cube = peak_signal_noise_ratio(truth.numpy(), est.numpy(), data_range=1.0)
    assert metrics.psnr_cube(est, truth).item() == pytest.approx(cube, rel=1e-10)


def test_ssim_matches_skimage_gaussian(pair):
    est, truth = pair
    ref = np.mean([
        structural_similarity(truth[c].numpy(), est[c].numpy(), gaussian_weights=True, sigma=1.5,
                              use_sample_covariance=False, data_range=1.0)
        for c in range(5)
    ])
    assert metrics.ssim(est, truth).item() == pytest.approx(ref, abs=1e-8)


@pytest.mark.parametrize("data_range, k1, k2", [(2.0, 0.01, 0.03), (0.25, 0.05, 0.1)])
def test_ssim_constants_and_data_range_match_skimage(pair, data_range, k1, k2):
    """The stabilising constants C1 = (k1·L)², C2 = (k2·L)² follow ``data_range`` L and k1, k2 as in
    scikit-image (dark, low-contrast images, where the constants matter)."""
    est, truth = (0.1 * t for t in pair)
    ref = np.mean([
        structural_similarity(truth[c].numpy(), est[c].numpy(), gaussian_weights=True, sigma=1.5,
                              use_sample_covariance=False, data_range=data_range, K1=k1, K2=k2)
        for c in range(5)
    ])
    got = metrics.ssim(est, truth, data_range=data_range, k1=k1, k2=k2).item()
    assert got == pytest.approx(ref, abs=1e-8)
    assert abs(got - metrics.ssim(est, truth).item()) > 1e-3  # the constants change the value here


def test_identical_inputs():
    x = torch.rand(2, 4, 20, 20, dtype=torch.float64)
    assert torch.all(metrics.ssim(x, x) > 1 - 1e-12)
    assert torch.all(metrics.sam_degrees(x, x) < 1e-5)
    assert torch.all(torch.isinf(metrics.psnr_per_band(x, x)) | (metrics.psnr_per_band(x, x) > 250))


def test_sam_closed_form():
    x = torch.rand(1, 6, 8, 8, dtype=torch.float64) + 0.1
    assert metrics.sam_degrees(3.0 * x, x).max().item() < 1e-5  # scaling a spectrum keeps its angle
    a = torch.zeros(1, 2, 1, 1, dtype=torch.float64)
    b = torch.zeros(1, 2, 1, 1, dtype=torch.float64)
    a[0, 0], b[0, 1] = 1.0, 1.0
    assert metrics.sam_degrees(a, b).item() == pytest.approx(90.0)


def test_sam_breakdown_by_brightness_and_edges_against_closed_form_angles():
    """A 2-band truth whose left half is dark (band mean 0.004) and right half bright with a
    vertical step in brightness; the estimate is off by known angles per region."""
    h, w = 8, 12
    truth = torch.zeros(1, 2, h, w, dtype=torch.float64)
    truth[0, 0, :, :6] = 0.008                       # dark: spectrum (1, 0), band mean 0.004
    truth[0, 0, :, 6:9], truth[0, 1, :, 6:9] = 0.2, 0.2  # bright, 45° from band 0
    truth[0, 0, :, 9:], truth[0, 1, :, 9:] = 0.6, 0.6    # brighter: an edge between columns 8 and 9
    est = truth.clone()
    est[0, 1, :, :6] = 0.008                         # dark pixels 45° off
    est[0, :, :, 6:] = truth[0, :, :, 6:] * torch.tensor([1.0, 0.0], dtype=torch.float64)[:, None, None]  # bright: 45° off
    est[0, :, :, 8:10] = truth[0, :, :, 8:10]        # the edge columns exact
    got = metrics.sam_breakdown(est, truth, dark_level=0.01, edge_quantile=0.7)
    assert got["dark_fraction"][0] == pytest.approx(0.5)
    assert got["dark"][0] == pytest.approx(45.0)
    assert got["edges"][0] == pytest.approx(0.0, abs=1e-6)  # central differences: columns 8 and 9 only
    assert got["flat"][0] == pytest.approx(45.0)
    assert got["bright"][0] == pytest.approx(45.0 * 4 / 6)
    assert got["all"][0] == pytest.approx(metrics.sam_degrees(est, truth).item())
    uniform = metrics.sam_breakdown(est[..., 6:8], truth[..., 6:8])
    assert math.isnan(uniform["dark"][0]) and uniform["dark_fraction"][0] == 0.0


def test_mst_psnr_is_msts_torch_psnr():
    """Against MST's torch_psnr written out as in its code (×256, round, per band, peak 255, mean)."""
    truth = torch.full((1, 2, 4, 4), 0.5, dtype=torch.float64)
    est = truth + 0.001  # below half a step of 1/256: identical after rounding
    assert torch.isinf(metrics.psnr_mst(est, truth)) or metrics.psnr_mst(est, truth).item() > 250
    est2 = truth.clone()
    est2[0, 0] += 10 / 256  # band 0 off by 10 steps, band 1 by 5
    est2[0, 1] += 5 / 256
    want = (20 * np.log10(255 / 10) + 20 * np.log10(255 / 5)) / 2  # per band, then the mean
    assert metrics.psnr_mst(est2, truth).item() == pytest.approx(want, rel=1e-9)

    def mst_torch_psnr(img, ref):  # MST simulation/train_code/utils.py, input [C, H, W]
        img, ref = (img * 256).round(), (ref * 256).round()
        return sum(10 * torch.log10((255 * 255) / torch.mean((img[i] - ref[i]) ** 2)) for i in range(img.shape[0])) / img.shape[0]

    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 5, 16, 16, generator=g, dtype=torch.float64)
    b = (a + 0.05 * torch.randn(3, 5, 16, 16, generator=g, dtype=torch.float64)).clamp(0, 1)
    got = metrics.psnr_mst(b, a)
    for i in range(3):
        assert got[i].item() == pytest.approx(mst_torch_psnr(b[i], a[i]).item(), rel=1e-12)


def test_ergas_closed_form():
    truth = torch.full((1, 2, 4, 4), 0.5, dtype=torch.float64)
    est = truth + 0.05  # RMSE 0.05 per band, mean 0.5 → 100 · 0.1
    assert metrics.ergas(est, truth).item() == pytest.approx(10.0)


def test_ergas_of_a_band_with_a_tiny_positive_mean_divides_by_that_mean():
    """A band whose truth mean lies in (0, 1e-12) (dark but for one pixel of 1e-10, as a float32 cube normalised by
    its maximum can hold) divides by its own mean, as the formula and a float64 numpy reference do: the floor at
    1e-12 gave a finite ERGAS 2.56× too small here (divided by 1e-12 instead of 3.9e-13), neither the formula's
    value nor undefined. all_metrics (evaluate's scores) gives the same; a mean so small that the squared ratio
    exceeds float64 gives +inf, as numpy does."""
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.2, 1.0, (4, 16, 16)).astype(np.float32)
    truth[2] = 0.0
    truth[2, 5, 7] = 1e-10  # mean 1e-10 / 256 = 3.9e-13
    est = (0.9 * truth).astype(np.float32)
    est[2] = 0.01
    t64, e64 = truth.astype(np.float64), est.astype(np.float64)
    mu = t64.mean(axis=(1, 2))
    assert 0 < mu[2] < 1e-12
    want = 100 * np.sqrt(np.mean((np.sqrt(((e64 - t64) ** 2).mean(axis=(1, 2))) / mu) ** 2))
    assert metrics.ergas(torch.from_numpy(est), torch.from_numpy(truth)).item() == pytest.approx(want, rel=1e-12)
    assert metrics.all_metrics(torch.from_numpy(est)[None], torch.from_numpy(truth)[None])["ergas"][0] == \
        pytest.approx(want, rel=1e-12)
    sub = t64.copy()
    sub[2] = 1e-300  # mean_b 1e-300: (RMSE_b / mean_b)² overflows float64
    with np.errstate(over="ignore"):
        want_sub = 100 * np.sqrt(np.mean((np.sqrt(((e64 - sub) ** 2).mean(axis=(1, 2))) / sub.mean(axis=(1, 2))) ** 2))
    assert want_sub == math.inf and metrics.ergas(torch.from_numpy(e64), torch.from_numpy(sub)).item() == math.inf


def test_rmse_matches_skimage_per_cube_and_closed_form():
    """RMSE of each cube of a batch is √(scikit-image's mean squared error over the whole cube);
    a constant offset of 0.05 gives 0.05 (3-D input is one cube)."""
    rng = np.random.default_rng(7)
    truth = rng.uniform(0, 1, (3, 4, 17, 13))
    est = np.clip(truth + rng.normal(0, 0.1, truth.shape), 0, 1)
    got = metrics.rmse(torch.from_numpy(est), torch.from_numpy(truth))
    assert got.shape == (3,)
    for b in range(3):
        ref = np.sqrt(mean_squared_error(truth[b], est[b]))
        assert got[b].item() == pytest.approx(ref, rel=1e-12)
    cube = torch.full((2, 5, 6), 0.5, dtype=torch.float64)
    assert metrics.rmse(cube + 0.05, cube).tolist() == pytest.approx([0.05], rel=1e-12)


# band matrices (patch sizes); shifted multiply-adds (large images), all bands at once or one at a time
@pytest.mark.parametrize("matrix_max_px, chunk_bytes", [(512, 2**28), (8, 2**28), (8, 1)])
def test_ssim_both_filter_paths_match_skimage(monkeypatch, matrix_max_px, chunk_bytes):
    monkeypatch.setattr(metrics, "_SSIM_MATRIX_MAX_PX", matrix_max_px)
    monkeypatch.setattr(metrics, "_SSIM_CHUNK_BYTES", chunk_bytes)
    g = torch.Generator().manual_seed(5)
    truth = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64)
    est = (truth + 0.1 * torch.randn(truth.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    for b in range(2):
        ref = np.mean([structural_similarity(truth[b, c].numpy(), est[b, c].numpy(), gaussian_weights=True, sigma=1.5,
                                             use_sample_covariance=False, data_range=1.0) for c in range(3)])
        assert metrics.ssim(est, truth)[b].item() == pytest.approx(ref, abs=1e-10)


def test_ssim_as_a_loss_differentiates_only_the_estimates_filtered_images():
    """As the training loss (the truth without gradient) the truth's mean and variance are filtered outside
    autograd: the backward's matrix products run over the estimate's 3 filtered images (x, x², x·y), 3/5 of
    those of a backward through all 5 (counted by torch's FLOP counter); the value and the gradient stay
    those of the full graph, and the gradient that of finite differences (gradcheck)."""
    from torch.utils.flop_counter import FlopCounterMode

    g = torch.Generator().manual_seed(3)
    truth = torch.rand(2, 3, 16, 18, generator=g, dtype=torch.float64)
    est0 = (truth + 0.1 * torch.randn(truth.shape, generator=g, dtype=torch.float64)).clamp(0, 1)

    def backward(truth_grad: bool) -> tuple[int, torch.Tensor, torch.Tensor]:
        est, y = est0.clone().requires_grad_(), truth.clone().requires_grad_(truth_grad)
        value = metrics.ssim(est, y, dtype=torch.float64)
        with FlopCounterMode(display=False) as counter:
            value.sum().backward()
        return counter.get_total_flops(), value.detach(), est.grad

    loss_flops, loss_value, loss_grad = backward(False)
    full_flops, full_value, full_grad = backward(True)
    assert full_flops > 0 and 5 * loss_flops == 3 * full_flops
    assert torch.equal(loss_value, full_value)
    torch.testing.assert_close(loss_grad, full_grad, rtol=1e-12, atol=1e-15)
    small = est0[:1, :1, :12, :12].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda e: metrics.ssim(e, truth[:1, :1, :12, :12]), (small,))


def _sam_reference(est: np.ndarray, truth: np.ndarray) -> tuple[float, np.ndarray]:
    """Independent SAM of (C, H, W) arrays: arccos of the normalised dot product at the pixels whose
    truth is not all zero (an all-zero estimate there: 90°), mean in degrees; and the angle map (NaN
    where the truth is all zero)."""
    e, t = est.reshape(est.shape[0], -1).T, truth.reshape(truth.shape[0], -1).T  # (pixels, bands)
    ne, nt = np.linalg.norm(e, axis=1), np.linalg.norm(t, axis=1)
    defined = nt > 0
    angle = np.full(len(t), np.nan)
    cos = np.zeros(len(t))
    both = defined & (ne > 0)
    cos[both] = np.einsum("pc,pc->p", e[both], t[both]) / (ne[both] * nt[both])
    angle[defined] = np.degrees(np.arccos(np.clip(cos[defined], -1, 1)))
    return float(angle[defined].mean()) if defined.any() else float("nan"), angle.reshape(truth.shape[1:])


def test_sam_leaves_out_pixels_whose_truth_is_zero_and_counts_zero_estimates_as_90_degrees():
    """Probe 28 #3: a zero spectrum was clamped to an angle of 90° (a perfect estimate of an image
    with 1 black pixel in 16 scored 5.6°, a scene with a black rectangle 46° for a true 5°). Now the
    pixels whose truth is all zero have no angle and are left out; an all-zero estimate where the
    truth is not stays 90°; checked against an independent numpy computation."""
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.05, 1, (2, 6, 9, 11))
    est = np.clip(truth + rng.normal(0, 0.05, truth.shape), 0, 1)
    truth[0, :, 2:5, 3:7] = 0.0          # a black rectangle in the truth (12 px) ...
    est[0, :, 2:4, 3:7] = 0.0            # ... estimated zero on 8 of them, non-zero on the others
    est[0, :, 7, 1:4] = 0.0              # an estimate without spectrum where the truth has one: 90°
    truth[1, :, 0, 0] = 0.0              # one black truth pixel in the second cube
    e_t, t_t = torch.from_numpy(est), torch.from_numpy(truth)
    got, amap = metrics.sam_degrees(e_t, t_t), metrics.sam_map(e_t, t_t)
    for b in range(2):
        want, want_map = _sam_reference(est[b], truth[b])
        assert got[b].item() == pytest.approx(want, abs=1e-9)
        np.testing.assert_allclose(amap[b].numpy(), want_map, atol=1e-9)  # NaN exactly where the truth is zero
    assert torch.all(amap[0, 7, 1:4] == 90.0)
    assert metrics.sam_undefined_pixels(t_t).tolist() == [12, 1]
    # the probe's cases: a perfect estimate with one black pixel in 16 scores 0°, not 5.6°; zero vs zero has no angle
    y = torch.rand(1, 31, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    y[..., 0, 0] = 0
    assert metrics.sam_degrees(y.clone(), y).item() < 1e-5
    zero = torch.zeros(1, 31, 12, 12, dtype=torch.float64)
    assert math.isnan(metrics.sam_degrees(zero, zero).item())
    assert metrics.all_metrics(zero + 0.5, zero + 0.5)["sam"][0] < 1e-5
    assert math.isnan(metrics.all_metrics(zero, zero)["sam"][0])  # undefined: NaN (other non-finite values stay inf)
    # the angle is scale-invariant down to tiny spectra (no clamp of the norms)
    tiny = torch.from_numpy(truth[1:] * 1e-200)
    assert metrics.sam_degrees(torch.from_numpy(est[1:]) * 1e-200, tiny).item() == pytest.approx(got[1].item(), abs=1e-9)
    # the other metrics did not change: PSNR against scikit-image, ERGAS closed form, on the cube with zeros
    ref_psnr = np.mean([peak_signal_noise_ratio(truth[0, c], est[0, c], data_range=1.0) for c in range(6)])
    assert metrics.psnr_per_band(e_t, t_t)[0].item() == pytest.approx(ref_psnr, rel=1e-12)
    rmse_b = np.sqrt(((est[0] - truth[0]) ** 2).mean(axis=(1, 2)))
    want_ergas = 100 * np.sqrt(np.mean((rmse_b / truth[0].mean(axis=(1, 2))) ** 2))
    assert metrics.ergas(e_t, t_t)[0].item() == pytest.approx(want_ergas, rel=1e-12)


def test_sam_breakdown_leaves_out_pixels_without_an_angle():
    """The breakdown's regions average the defined angles only; ``all`` equals sam_degrees."""
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.1, 1, (1, 4, 10, 10))
    truth[0, :, :, :3] = 0.0  # 30 black pixels: dark, no angle
    est = np.clip(truth + rng.normal(0, 0.05, truth.shape), 0, 1)
    got = metrics.sam_breakdown(torch.from_numpy(est), torch.from_numpy(truth), dark_level=0.01)
    want, amap = _sam_reference(est[0], truth[0])
    assert got["all"][0] == pytest.approx(want, abs=1e-9)
    assert got["dark_fraction"][0] == pytest.approx(0.3)
    assert math.isnan(got["dark"][0])  # the dark pixels are exactly those without an angle
    assert got["bright"][0] == pytest.approx(np.nanmean(amap[:, 3:]), abs=1e-9)


def test_all_metrics_sam_is_undefined_only_for_a_black_truth_and_the_worst_for_a_broken_estimate():
    """NaN SAM means "no angle anywhere" (a truth zero at every pixel: the scene is left out of the mean
    SAM); an estimate with NaN pixels is a broken reconstruction and scores the worst value of every
    metric (−inf PSNR and SSIM, +inf errors), never a NaN that a mean would skip nor a +inf PSNR that
    reads as a perfect score."""
    import math

    from hsicam.metrics import all_metrics

    truth = torch.rand(2, 5, 16, 16, generator=torch.Generator().manual_seed(0))
    truth[1] = 0
    est = truth.clone()
    est[0, :, 3, 3] = float("nan")
    m = all_metrics(est, truth)
    assert m["sam"][0] == math.inf and math.isnan(m["sam"][1])
    for name in ("psnr", "psnr_cube", "psnr_mst", "ssim"):
        assert m[name][0] == -math.inf, name
        assert math.isfinite(m[name][1]), name  # the black truth estimated exactly: a finite (floored) score
    for name in ("ergas", "rmse"):
        assert m[name][0] == math.inf, name


# --------------------------------------------------------------------------------------------
# metrics.py
# --------------------------------------------------------------------------------------------
def test_sam_breakdown_edges_count_bright_pixels_only():
    """``sam_breakdown``'s ``edges`` and ``flat`` are parts of the bright pixels: closed-form angles θ per pixel (two
    bands rotated by θ), regions rebuilt with numpy from the documented definitions (band mean below ``dark_level``;
    central-difference gradient of the band mean above its 0.8 quantile)."""
    from hsicam.metrics import sam_breakdown

    rng = np.random.default_rng(4)
    h = w = 24
    level = rng.uniform(0.0, 0.03, size=(h, w))
    a = rng.uniform(0.1, 1.4, size=(h, w))
    theta = rng.uniform(0.0, 0.5, size=(h, w))
    truth = np.stack([level * np.cos(a), level * np.sin(a)])
    est = np.stack([level * np.cos(a + theta), level * np.sin(a + theta)])
    out = sam_breakdown(torch.from_numpy(est)[None], torch.from_numpy(truth)[None])
    b = truth.mean(axis=0)
    gy, gx = np.gradient(b)
    grad = np.hypot(gx, gy)
    edge = grad > np.quantile(grad, 0.8)
    dark = b < 0.01
    assert (edge & dark).any() and (edge & ~dark).any()  # the test has teeth
    deg = np.degrees(theta)
    assert out["edges"][0] == pytest.approx(deg[edge & ~dark].mean(), abs=1e-6)
    assert out["flat"][0] == pytest.approx(deg[~edge & ~dark].mean(), abs=1e-6)
    assert out["dark"][0] == pytest.approx(deg[dark].mean(), abs=1e-6)


def test_sam_of_tiny_negative_spectra_is_their_true_angle():
    """The spectral angle is scale-invariant: an estimate −1e-200 · s is at 180° from s, and 1e-200 · s at 0°
    (float64; each spectrum is scaled by its largest magnitude before the dot product, so nothing underflows)."""
    from hsicam.metrics import sam_map

    s = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)[None, :, None, None]
    assert float(sam_map(-1e-200 * s, s)) == pytest.approx(180.0, abs=1e-6)
    assert float(sam_map(1e-200 * s, s)) == pytest.approx(0.0, abs=1e-5)


@pytest.mark.parametrize("n", [1, 2, 7, 100, 577])
def test_quantile_is_numpys_linear_quantile(n):
    """``sam_breakdown``'s edge threshold: the linear-interpolation quantile (numpy's default method), at ranks that
    fall on an element (q·(n − 1) whole) and between two, and at both ends."""
    t = torch.from_numpy(np.random.default_rng(n).permutation(np.linspace(-1.0, 3.0, n) ** 3))
    for q in (0.0, 0.1, 0.25, 0.5, 0.8, 0.95, 1.0):
        assert metrics._quantile(t, q).item() == pytest.approx(np.quantile(t.numpy(), q), rel=1e-12, abs=1e-15), q


def test_sam_breakdown_dark_is_strictly_below_dark_level():
    """"Dark": a band mean *below* ``dark_level``; a pixel whose band mean equals it (0.25, exact in binary) is
    bright."""
    truth = torch.full((1, 2, 4, 4), 0.25, dtype=torch.float64)
    truth[0, :, :, :1] = 0.125  # one column dark
    got = metrics.sam_breakdown(truth.clone(), truth, dark_level=0.25)
    assert got["dark_fraction"][0] == 0.25
    assert got["bright"][0] == pytest.approx(0.0, abs=1e-6)


def test_spectra_scaled_divides_each_spectrum_by_its_largest_magnitude():
    """Each pixel's spectrum over its largest |value| (numpy): the scaled spectrum's peak magnitude is exactly 1;
    an all-zero spectrum stays zero."""
    rng = np.random.default_rng(2)
    t = rng.normal(0.0, 1e-3, (2, 5, 3, 4))
    t[0, :, 1, 2] = 0.0
    peak = np.abs(t).max(axis=1, keepdims=True)
    want = np.divide(t, peak, out=np.zeros_like(t), where=peak > 0)
    got = metrics.spectra_scaled(torch.from_numpy(t)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-15, atol=0)
    got_peak, nonzero = np.abs(got).max(axis=1), peak[:, 0] > 0
    assert np.all(got_peak[nonzero] == 1.0) and np.all(got_peak[~nonzero] == 0.0) and (~nonzero).sum() == 1


def test_all_metrics_of_a_single_non_square_black_cube_has_sam_undefined():
    """A (C, H, W) truth (one cube, no batch axis) that is zero at every one of its H·W pixels has no spectral angle:
    SAM NaN (undefined), as for a (1, C, H, W) batch, on a non-square image (H ≠ W), not +inf (a broken
    estimate's)."""
    zero = torch.zeros(3, 12, 17, dtype=torch.float64)
    for est, truth in ((zero, zero), (zero[None], zero[None]), (zero.transpose(1, 2), zero.transpose(1, 2))):
        got = metrics.all_metrics(est, truth)
        assert len(got["sam"]) == 1 and math.isnan(got["sam"][0]), tuple(truth.shape)
