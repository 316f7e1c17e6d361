"""Colour filter array, sensor noise statistics and declared variance, ADC quantisation and DOE fabrication
effects."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from hsicam.optics.doe import DOE, quantize_heights
from hsicam.sensor import ColorFilterArray, SensorNoise, bandpass_weights, cfa_tile, tile_pattern
from hsicam.spectral import FusedSilica


def _h2pi_fused_silica(lam_nm: float) -> float:
    """λ/(n(λ) − 1) with Malitson's Sellmeier coefficients written out here."""
    l2 = (lam_nm * 1e-3) ** 2
    n = math.sqrt(1 + sum(b * l2 / (l2 - c * c) for b, c in
                          [(0.6961663, 0.0684043), (0.4079426, 0.1162414), (0.8974794, 9.896161)]))
    return lam_nm * 1e-9 / (n - 1)


# --------------------------------------------------------------------------------------------
# CFA
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("period", [1, 3, 9])
def test_cfa_is_periodic_normalised_and_non_negative(period):
    cfa = ColorFilterArray(n_bands=5, period=period, seed=3)
    with torch.no_grad():
        cfa.weights[0, 0, 0] = -0.7  # a negative raw weight: ReLU must block that band there
        kappa = cfa.pattern(2 * period + 5, 3 * period + 2)
    assert kappa.shape == (5, 2 * period + 5, 3 * period + 2)
    m = period
    torch.testing.assert_close(kappa[:, :-m, :-m], kappa[:, m:, m:], rtol=0, atol=0)  # κ[i, j] = κ[i+m, j+m]
    torch.testing.assert_close(kappa[:, :-m, :], kappa[:, m:, :], rtol=0, atol=0)
    torch.testing.assert_close(kappa[:, :, :-m], kappa[:, :, m:], rtol=0, atol=0)
    assert (kappa >= 0).all()
    torch.testing.assert_close(kappa.sum(0), torch.ones(kappa.shape[1:]), rtol=0, atol=1e-6)
    assert kappa[0, 0, 0] == 0 and kappa[0, m, m] == 0  # the ReLU'd band, at every period
    # the tile is the ReLU of the weights divided by its band sum (independent formula)
    w = cfa.weights.detach().clamp_min(0)
    torch.testing.assert_close(kappa[:, :m, :m], w / w.sum(0, keepdim=True))
    if period > 1:  # a learned CFA is not flat: different pixels filter differently
        assert not torch.allclose(kappa[:, 0, 0], kappa[:, 0, 1])


def test_no_cfa_is_all_ones():
    cfa = ColorFilterArray(n_bands=4, period=9, enabled=False)
    assert list(cfa.parameters()) == []
    torch.testing.assert_close(cfa.pattern(7, 11), torch.ones(4, 7, 11), rtol=0, atol=0)


def test_tile_pattern_origin_and_cfa_gradient():
    w = torch.rand(3, 2, 2, generator=torch.Generator().manual_seed(0), requires_grad=True)
    t = cfa_tile(w)
    p = tile_pattern(t, 5, 3)
    for i in range(5):
        for j in range(3):
            torch.testing.assert_close(p[:, i, j], t[:, i % 2, j % 2], rtol=0, atol=0)
    (p * torch.arange(45.0).reshape(3, 5, 3)).sum().backward()
    assert torch.isfinite(w.grad).all() and (w.grad != 0).all()


def test_cfa_pattern_window_matches_the_whole_sensor():
    from hsicam.sensor import ColorFilterArray

    cfa = ColorFilterArray(5, period=4, seed=3)
    whole = cfa.pattern(23, 19)
    for origin in [(0, 0), (1, 2), (5, 7), (12, 3)]:
        win = cfa.pattern(9, 11, origin)
        torch.testing.assert_close(win, whole[:, origin[0] : origin[0] + 9, origin[1] : origin[1] + 11], rtol=0, atol=0)


# --------------------------------------------------------------------------------------------
# Noise statistics (bounds: 5 standard deviations of the estimator)
# --------------------------------------------------------------------------------------------
N_SAMPLES = 200_000


def _assert_mean_var(out: torch.Tensor, mean: float, var: float, kurtosis_excess: float = 0.0):
    x = out.double().flatten()
    n = x.numel()
    assert abs(x.mean().item() - mean) < 5 * math.sqrt(var / n)
    var_std = var * math.sqrt((2.0 + kurtosis_excess) / (n - 1))  # std of the sample variance
    assert abs(x.var().item() - var) < 5 * var_std


def test_gaussian_noise_statistics():
    g = torch.full((2, 1, 400, 250), 0.3, dtype=torch.float64)
    noise = SensorNoise("gaussian", sigma=0.02)
    out = noise(g, torch.Generator().manual_seed(0))
    _assert_mean_var(out, 0.3, 0.02**2)
    # and the noise is white: neighbouring pixels are uncorrelated
    e = (out - 0.3).flatten(1)
    corr = (e[:, 1:] * e[:, :-1]).mean() / e.var()
    assert abs(corr.item()) < 5 / math.sqrt(e.numel())


@pytest.mark.parametrize("signal, full_well, read", [(0.3, 1000.0, 5.0), (0.8, 20000.0, 3.0), (0.05, 500.0, 0.0), (0.01, 1000.0, 10.0)])
def test_poisson_gaussian_noise_statistics(signal, full_well, read):
    g = torch.full((1, 1, 400, 500), signal, dtype=torch.float64)
    out = SensorNoise("poisson_gaussian", full_well_e=full_well, read_noise_e=read)(g, torch.Generator().manual_seed(1))
    var = signal / full_well + (read / full_well) ** 2
    photons = signal * full_well
    _assert_mean_var(out, signal, var, kurtosis_excess=2.0 / photons)


def test_poisson_noise_counts_whole_electrons():
    g = torch.full((1, 1, 300, 300), 0.3, dtype=torch.float64)
    out = SensorNoise("poisson_gaussian", full_well_e=10.0, read_noise_e=0.0)(g, torch.Generator().manual_seed(2))
    electrons = out * 10.0
    torch.testing.assert_close(electrons, electrons.round(), rtol=0, atol=1e-9)
    assert (electrons >= 0).all()
    # P(k electrons) of a Poisson law with mean 3
    counts = torch.bincount(electrons.round().long().flatten(), minlength=6)[:6].double() / electrons.numel()
    expected = torch.tensor([math.exp(-3) * 3**k / math.factorial(k) for k in range(6)], dtype=torch.float64)
    assert (counts - expected).abs().max() < 5 * math.sqrt(0.25 / electrons.numel())


def test_poisson_noise_has_a_straight_through_gradient():
    g = torch.full((1, 1, 4, 4), 0.5, requires_grad=True)
    SensorNoise("poisson_gaussian", full_well_e=100.0, read_noise_e=1.0)(g).sum().backward()
    torch.testing.assert_close(g.grad, torch.ones_like(g))


@pytest.mark.parametrize("peak", [1e7, 1e8, 1e9, 1e20, 3e38])
def test_a_far_too_bright_image_saturates_the_adc_at_full_scale(peak):
    """A sensor image far above full scale, through a 12-bit ADC, read 2 at 1e8 and 0 (black) from 1e9 on in float32:
    the straight-through estimator's x + (y − x) lost the clipped value to rounding (a helper's hunt, session 71).
    Now every pixel is the ADC's top code, 1, and the gradient still passes (1 per pixel)."""
    g = torch.full((1, 1, 3, 4), peak, dtype=torch.float32, requires_grad=True)
    out = SensorNoise("none", bit_depth=12)(g)
    assert torch.equal(out.detach(), torch.ones_like(out))
    out.sum().backward()
    torch.testing.assert_close(g.grad, torch.ones_like(g))


@pytest.mark.parametrize("peak", [1e16, 1e20, 3e34])
def test_shot_noise_of_a_count_beyond_the_poisson_draw_is_the_count_itself(peak):
    """torch.poisson overflows int64 above ~9e18 e⁻ (every count −9.2e18: a sensor image of −9e14 at 10 000 e⁻ full
    well). Above POISSON_MAX_E the mean count is taken (its shot noise is below float32's resolution); below it the
    draws are those of torch.poisson, unchanged."""
    from hsicam.sensor import POISSON_MAX_E, poisson_gaussian_noise

    g = torch.full((1, 1, 2, 3), peak / 1e4)
    out = poisson_gaussian_noise(g, 1e4, 0.0, torch.Generator().manual_seed(0))
    torch.testing.assert_close(out, g, rtol=1e-6, atol=0)
    low = torch.full((1, 1, 2, 3), 0.37)
    want = torch.poisson(low * 1e4, generator=torch.Generator().manual_seed(5)) / 1e4
    torch.testing.assert_close(poisson_gaussian_noise(low, 1e4, 0.0, torch.Generator().manual_seed(5)), want,
                               rtol=0, atol=0)
    assert POISSON_MAX_E < 9.2e18


@pytest.mark.parametrize("model", ["gaussian", "poisson_gaussian"])
def test_noise_is_reproducible_from_a_seeded_generator(model):
    g = torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    noise = SensorNoise(model, sigma=0.05, full_well_e=1000.0, read_noise_e=2.0)
    a = noise(g, torch.Generator().manual_seed(42))
    b = noise(g, torch.Generator().manual_seed(42))
    c = noise(g, torch.Generator().manual_seed(43))
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.allclose(a, c) and not torch.allclose(a, g)


@pytest.mark.parametrize("model", ["poisson_gaussian", "none"])
def test_sensor_sigma_set_on_any_noise_model_reaches_the_image(tiny_camera, model):
    """σ_s set by ``set_noise(sensor_sigma=…)`` (``hsicam evaluate --sensor-sigma``, ``train.sensor_sigma``)
    on a Poisson–Gaussian or noise-free camera was reported by ``noise_levels`` and written into the
    results as applied, but only the "gaussian" model added it (the image was left untouched). Now it
    is added in every model: the spread of y − A x is the closed-form √(g/N + (r/N)² + σ_s²), and the
    variance model (noise-aware consistency) counts σ_s² too."""
    sigma = 0.02
    extra = ("camera.sensor.full_well_e=5000", "camera.sensor.read_noise_e=3") if model == "poisson_gaussian" else ()
    cam = tiny_camera(f"camera.sensor.noise={model}", *extra, dtype=torch.float64)
    x = torch.full((1, len(cam.bands), *cam.scene_size((300, 300))), 0.4, dtype=torch.float64)
    cam.set_noise(sensor_sigma=sigma)
    assert cam.noise_levels()["sensor_sigma"] == sigma
    with torch.no_grad():
        g = cam.A(x)
        y = cam(x, torch.Generator().manual_seed(0))
    n, r = (5000.0, 3.0) if model == "poisson_gaussian" else (math.inf, 0.0)
    var = float(g.mean()) / n + (r / n) ** 2 + sigma**2
    _assert_mean_var(y - g + float(g.mean()), float(g.mean()), var)
    torch.testing.assert_close(cam.noise.variance(g), var + (g - g.mean()) / n, rtol=1e-6, atol=0)


def test_a_noise_free_sensor_config_with_a_gaussian_sigma_stays_noise_free(tiny_camera, caplog):
    """``noise: none`` with ``sigma`` > 0 loads (a run saved so keeps loading) and images as it always did,
    noise-free, with one warning naming the key; set_noise's σ_s (evaluate --sensor-sigma) still applies."""
    with caplog.at_level(logging.WARNING, logger="hsicam.sensor"):
        cam = tiny_camera("camera.sensor.noise=none", "camera.sensor.sigma=0.01")
    assert "camera.sensor.sigma=0.01 is not applied" in caplog.text
    x = torch.rand(1, len(cam.bands), *cam.scene_size((40, 40)))
    with torch.no_grad():
        g = cam.A(x)
        torch.testing.assert_close(cam(x, torch.Generator().manual_seed(0)), g, rtol=0, atol=0)
        cam.set_noise(sensor_sigma=0.01)
        assert float((cam(x, torch.Generator().manual_seed(0)) - g).std()) > 0.005
    caplog.clear()  # σ_s = 0 on a noise-free sensor is consistent: nothing to warn about
    with caplog.at_level(logging.WARNING, logger="hsicam.sensor"):
        tiny_camera("camera.sensor.noise=none", "camera.sensor.sigma=0")
    assert "not applied" not in caplog.text


def test_no_noise_is_identity():
    g = torch.rand(1, 1, 8, 8)
    torch.testing.assert_close(SensorNoise("none")(g), g, rtol=0, atol=0)
    torch.testing.assert_close(SensorNoise("gaussian", sigma=0.0)(g), g, rtol=0, atol=0)


@pytest.mark.parametrize("bits", [1, 3, 8])
def test_bit_depth_quantisation_levels(bits):
    g = torch.linspace(-0.2, 1.2, 5001, dtype=torch.float64).reshape(1, 1, 1, -1).requires_grad_(True)
    out = SensorNoise("none", bit_depth=bits)(g)
    levels = 2**bits
    vals = torch.unique(out.detach())
    assert vals.numel() == levels  # every ADC code appears, no other value
    torch.testing.assert_close(vals, torch.arange(levels, dtype=torch.float64) / (levels - 1))
    # nearest code of the clipped signal (ties aside)
    clipped = g.detach().clamp(0, 1)
    assert ((out.detach() - clipped).abs() <= 0.5 / (levels - 1) + 1e-12).all()
    out.sum().backward()  # straight-through gradient
    torch.testing.assert_close(g.grad, torch.ones_like(g))


# --------------------------------------------------------------------------------------------
# The variance each noise model declares (what the noise-aware consistency steps weigh by; moved from
# models/test_noise_aware_consistency.py)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("model, kw", [
    ("gaussian", {"sigma": 0.02}),
    ("poisson_gaussian", {"full_well_e": 1000.0, "read_noise_e": 3.0}),
    ("poisson_gaussian", {"full_well_e": 200.0, "read_noise_e": 0.0}),
    ("gaussian", {"sigma": 0.02, "bit_depth": 5}),  # Δ²/12 is 18 % of this variance
])
def test_variance_is_the_empirical_variance_of_the_noise(model, kw):
    """The variance the model declares at each signal level equals the sample variance of 100 000
    draws of the noise it adds there (Poisson: mean/N; read noise: (r/N)²; quantiser: Δ²/12, for a
    noise much wider than the step; levels 5σ inside [0, 1], where the quantiser clips nothing)."""
    noise = SensorNoise(model, **kw)
    levels = torch.tensor([0.1, 0.3, 0.6, 0.85], dtype=torch.float64).view(1, 1, 4, 1)
    g = levels.expand(1, 1, 4, 100_000).contiguous()
    gen = torch.Generator().manual_seed(0)
    sample = noise(g, gen)
    empirical = sample.var(dim=-1)
    declared = noise.variance(g)[..., 0]
    torch.testing.assert_close(declared, empirical, rtol=0.03, atol=0)


def test_noise_free_models_declare_no_variance():
    g = torch.rand(1, 1, 8, 8)
    assert SensorNoise("none").variance(g) is None
    assert SensorNoise("gaussian", sigma=0.0).variance(g) is None
    q = SensorNoise("none", bit_depth=10).variance(g)  # the quantiser alone: Δ²/12
    # relative tolerance only: the default atol (1e-5) is 100× this variance and passed any step
    torch.testing.assert_close(q, torch.full_like(g, (1 / 1023) ** 2 / 12), rtol=1e-6, atol=0)


@pytest.mark.parametrize("bits", [2, 3, 6])
def test_quantiser_variance_is_the_variance_of_its_rounding_error(bits):
    """Δ²/12 with Δ = 1/(2^bits − 1), the step between the ADC's codes, is the variance of the rounding
    error of a signal spread uniformly over [0, 1] (the error is then uniform on [−Δ/2, Δ/2]): checked
    against the sample variance of that error for 400 000 points of [0, 1]."""
    g = torch.linspace(0.0, 1.0, 400_001, dtype=torch.float64).reshape(1, 1, 1, -1)
    noise = SensorNoise("none", bit_depth=bits)
    err = noise(g) - g
    step = 1.0 / (2**bits - 1)
    empirical = float((err**2).mean())  # the error has mean 0 by symmetry
    assert abs(float(err.mean())) < 1e-4 * step
    assert empirical == pytest.approx(step**2 / 12.0, rel=1e-3)
    torch.testing.assert_close(noise.variance(g)[0, 0, 0, :3], torch.full((3,), empirical, dtype=torch.float64),
                               rtol=1e-3, atol=0)


def test_variance_is_computed_in_float32_for_half_precision_images():
    g = torch.full((1, 1, 4, 4), 0.25, dtype=torch.float16)
    var = SensorNoise("poisson_gaussian", full_well_e=1e4, read_noise_e=2.0).variance(g)
    assert var.dtype == torch.float32
    torch.testing.assert_close(var, torch.full((1, 1, 4, 4), 0.25 / 1e4 + (2 / 1e4) ** 2), rtol=1e-6, atol=0)
    assert SensorNoise("none", bit_depth=12).variance(g).min() > 0


def test_a_flat_field_gain_map_scales_the_variance_as_the_corrected_noise():
    """A capture divided by its flat field F (vignetting) is a·n(g/a) with a = 1/F: its variance is a²·v(g/a)
    (Poisson–Gaussian: a·g/N + (a·r/N)²), checked against the sample variance of 100 000 draws at each of four
    (gain, level) pairs; a window's variance at its origin is the whole image's there (what tiles see)."""
    gains = torch.tensor([0.8, 1.0, 1.6, 2.5], dtype=torch.float64)
    levels = torch.tensor([0.1, 0.3, 0.6, 0.85], dtype=torch.float64)
    n = 100_000
    noise = SensorNoise("poisson_gaussian", full_well_e=500.0, read_noise_e=3.0,
                        gain=gains.view(4, 1).expand(4, n).float())
    g = levels.view(1, 1, 4, 1).expand(1, 1, 4, n).contiguous()
    sample = noise(g, torch.Generator().manual_seed(0))
    expected = gains * levels / 500.0 + (gains * 3.0 / 500.0) ** 2  # written out, not the model's code
    torch.testing.assert_close(sample.var(dim=-1)[0, 0], expected, rtol=0.03, atol=0)
    torch.testing.assert_close(noise.variance(g)[0, 0, :, 0], expected, rtol=1e-6, atol=0)
    # a window of a larger map, the map placed at sensor pixel (2, 3) (a capture's CFA offset)
    rng = torch.Generator().manual_seed(1)
    gain = 0.5 + torch.rand(20, 30, generator=rng)
    image = torch.rand(1, 1, 20, 30, generator=rng)
    placed = SensorNoise("poisson_gaussian", full_well_e=200.0, read_noise_e=2.0, gain=gain, gain_origin=(2, 3))
    whole = placed.variance(image, origin=(2, 3))
    torch.testing.assert_close(whole, (gain * image / 200.0 + (gain * 2.0 / 200.0) ** 2).float(), rtol=1e-6, atol=0)
    window = image[..., 5:12, 7:19]
    torch.testing.assert_close(placed.variance(window, origin=(7, 10)), whole[..., 5:12, 7:19], rtol=0, atol=0)
    with pytest.raises(ValueError, match="not within the noise gain map"):
        placed.variance(window, origin=(0, 0))
    with pytest.raises(ValueError, match="finite and positive"):
        SensorNoise("poisson_gaussian", gain=torch.zeros(4, 4))


def test_the_variance_defaults_to_the_window_the_forward_noises():
    """``variance(g)`` without an origin took the map's window at sensor pixel (0, 0), while ``forward(g)`` noises
    the window at the map's own ``gain_origin``: with a flat field placed at a non-zero origin (a capture's CFA
    offset) the two disagreed (here a ValueError: (0, 0) is off the map). The default origin is now
    ``gain_origin``, and the declared variance is the sample variance of the forward's noise."""
    n = 100_000
    rows = torch.tensor([0.8, 1.0, 1.6, 2.5, 0.6, 1.9])
    gain = rows.view(6, 1).expand(6, n + 4).contiguous()
    noise = SensorNoise("poisson_gaussian", full_well_e=500.0, read_noise_e=3.0, gain=gain, gain_origin=(2, 3))
    levels = torch.tensor([0.1, 0.3, 0.6, 0.85], dtype=torch.float64)
    g = levels.view(1, 1, 4, 1).expand(1, 1, 4, n).contiguous()
    sample = noise(g, torch.Generator().manual_seed(0)).var(dim=-1)[0, 0]
    default = noise.variance(g)
    assert torch.equal(default, noise.variance(g, origin=(2, 3)))
    torch.testing.assert_close(default[0, 0, :, 0], sample, rtol=0.03, atol=0)
    a = rows[:4].double()
    torch.testing.assert_close(default[0, 0, :, 0], a * levels / 500.0 + (a * 3.0 / 500.0) ** 2, rtol=1e-6, atol=0)
    assert not torch.allclose(noise.variance(g, origin=(4, 3)), default)  # another window of the map
    assert torch.equal(noise.gain_window(g), gain[:4, :n])


@pytest.mark.parametrize("lead", [(), (1,), (2, 3, 1)])
def test_the_gain_window_takes_the_last_two_dimensions_as_the_image(lead):
    """gain_window's ``g`` is (..., H, W): the window is H×W whatever the leading dimensions (an (H, W) image,
    a (B, T, 1, H, W) stack), the rows and columns of the map under it."""
    gain = 0.5 + torch.arange(12 * 15, dtype=torch.float32).reshape(12, 15) / 100.0
    noise = SensorNoise("poisson_gaussian", gain=gain, gain_origin=(1, 2))
    g = torch.zeros(*lead, 5, 7)
    assert torch.equal(noise.gain_window(g, origin=(4, 6)), gain[3:8, 4:11])


# --------------------------------------------------------------------------------------------
# DOE fabrication: quantization and height noise
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("levels", [2, 4, 16])
def test_doe_quantization_gives_exactly_l_levels(levels):
    doe = DOE(41, FusedSilica(), 587.6, quantization_levels=levels, seed=1)
    h = doe.heights()
    vals = torch.unique(h.detach()).double()
    assert vals.numel() == levels
    step = _h2pi_fused_silica(587.6) / levels
    torch.testing.assert_close(vals, torch.arange(levels, dtype=torch.float64) * step, rtol=1e-6, atol=0)
    # every height goes to the nearest level in phase: modular distance (period h_2π) ≤ step/2
    top = _h2pi_fused_silica(587.6)
    d = torch.remainder((h.detach() - doe.height_m.detach()).double() + top / 2, top) - top / 2
    assert (d.abs() <= step / 2 * (1 + 1e-5)).all()
    # straight-through: d(heights)/d(parameter) = identity
    w = torch.rand(41, 41, generator=torch.Generator().manual_seed(0))
    (h * w).sum().backward()
    torch.testing.assert_close(doe.height_m.grad, w)


def test_quantize_heights_rounds_to_nearest_level():
    top = 1.0
    h = torch.tensor([0.0, 0.1, 0.13, 0.3, 0.62, 0.74, 0.99])
    q = quantize_heights(h, 4, top)  # levels 0, .25, .5, .75; 0.99 wraps to 0 (= the phase of 1.0)
    torch.testing.assert_close(q, torch.tensor([0.0, 0.0, 0.25, 0.25, 0.5, 0.75, 0.0]))


def test_doe_height_noise_sigma_in_nm_and_redrawn(tiny_camera):
    cam = tiny_camera("camera.doe.sigma_height_nm=20")
    doe = cam.optics.doe
    assert doe.sigma_height_m == pytest.approx(20e-9)
    big = DOE(201, FusedSilica(), 587.6, sigma_height_m=doe.sigma_height_m, seed=2)
    with torch.no_grad():
        d1 = (big.heights(torch.Generator().manual_seed(5)) - big.height_m).double()
        d2 = (big.heights(torch.Generator().manual_seed(6)) - big.height_m).double()
    n = d1.numel()
    sigma = 20e-9
    assert abs(d1.mean().item()) < 5 * sigma / math.sqrt(n)
    assert abs(d1.std().item() - sigma) < 5 * sigma / math.sqrt(2 * (n - 1)) + 1e-12  # float32 heights
    corr = (d1 * d2).mean().item() / sigma**2  # independent draws
    assert abs(corr) < 5 / math.sqrt(n)
    # every forward pass redraws: two PSFs of the same camera differ, and without noise they do not
    with torch.no_grad():
        assert not torch.allclose(cam.psf(), cam.psf())
        quiet = tiny_camera()
        torch.testing.assert_close(quiet.psf(), quiet.psf(), rtol=0, atol=0)


def test_quantization_wraps_top_level_to_zero_phase():
    """Heights that round up to h_2π are the same phase as 0: they go to level 0, not L−1."""
    from hsicam.optics.doe import quantize_heights

    top, levels = 1.0, 4
    h = torch.tensor([0.0, 0.2, 0.3, 0.9, 0.99], dtype=torch.float64)
    q = quantize_heights(h, levels, top, wrap=True)
    torch.testing.assert_close(q, torch.tensor([0.0, 0.25, 0.25, 0.0, 0.0], dtype=torch.float64))
    phase_err = torch.remainder(2 * torch.pi * (q - h) / top + torch.pi, 2 * torch.pi) - torch.pi
    assert phase_err.abs().max() <= torch.pi / levels + 1e-12
    clamped = quantize_heights(h, levels, top, wrap=False)
    assert clamped[-1].item() == pytest.approx(0.75)


def test_cfa_pixel_with_no_positive_weight_is_neutral():
    from hsicam.sensor import cfa_tile

    w = torch.rand(5, 3, 3)
    w[:, 1, 2] = -1.0
    k = cfa_tile(w)
    torch.testing.assert_close(k.sum(0), torch.ones(3, 3))
    torch.testing.assert_close(k[:, 1, 2], torch.full((5,), 0.2))


def test_bandpass_cfa_init_places_gaussian_filters_over_the_band_range():
    import numpy as np

    lam = np.arange(420.0, 721.0, 5.0)  # 61 bands, 5 nm apart
    cfa = ColorFilterArray(len(lam), period=3, seed=1, init="bandpass", centers_nm=lam, bandpass_fwhm_nm=60.0)
    w = cfa.weights.detach().double().reshape(len(lam), 9).numpy()
    # the 9 filters peak at 420, 457.5, ..., 720 nm (within half a band), each once
    peaks = np.sort(lam[w.argmax(axis=0)])
    np.testing.assert_allclose(peaks, np.linspace(420, 720, 9), atol=2.5 + 1e-9)
    # Gaussian with the requested FWHM above a floor of 1 % of the peak: half height ±30 nm
    k = int(np.argmin(np.abs(lam[w.argmax(axis=0)] - 570.0)))
    col = w[:, k] - 0.01
    peak = lam[col.argmax()]
    half = np.interp([peak - 30.0, peak + 30.0], lam, col)
    np.testing.assert_allclose(half, [0.5, 0.5], atol=0.02)
    # the layout is a seeded permutation; the filters are normalised like any CFA
    other = ColorFilterArray(len(lam), period=3, seed=2, init="bandpass", centers_nm=lam).weights
    assert not torch.equal(other, ColorFilterArray(len(lam), period=3, seed=1, init="bandpass", centers_nm=lam).weights)
    torch.testing.assert_close(cfa.tile().sum(0), torch.ones(3, 3))
    with pytest.raises(ValueError, match="centre wavelength"):
        ColorFilterArray(5, period=3, init="bandpass")


def test_one_bandpass_filter_sits_in_the_middle_of_the_range():
    """At period 1 the band-pass start's one filter peaked on the first band (a blue edge filter blocking 93 % of the
    rest): its centre is the middle of the bands' range, as 'spread evenly' means for one."""
    import numpy as np

    lam = np.arange(420.0, 721.0, 5.0)
    w = bandpass_weights(torch.from_numpy(lam), 1, 40.0).reshape(len(lam)).double().numpy()
    assert lam[w.argmax()] == 570.0


def test_bandpass_cfa_from_config(tiny_config):
    from hsicam.cameras import DOECamera
    from hsicam.errors import ConfigError

    def selectivity(init: str) -> float:  # mean over pixels of peak / mean transmission
        tile = DOECamera.from_config(tiny_config(f"camera.cfa.init={init}")).cfa.tile().detach()
        return float((tile.max(0).values * tile.shape[0]).mean())

    assert selectivity("bandpass") > selectivity("uniform") + 0.5
    with pytest.raises(ConfigError, match="bandpass_fwhm_nm"):
        tiny_config("camera.cfa.bandpass_fwhm_nm=0")


def test_dispersed_order_is_the_recursive_bayer_index_matrix():
    from hsicam.sensor import dispersed_order

    # the 4x4 ordered-dither matrix as printed in the literature (Bayer 1973)
    expected = torch.tensor([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]])
    assert torch.equal(dispersed_order(4), expected)
    assert torch.equal(dispersed_order(1), torch.zeros(1, 1, dtype=torch.long))
    for m in (2, 4, 8):  # a permutation of 0..m²-1, and each aligned 2x2 block holds 4 ranks m²/4 apart
        b = dispersed_order(m)
        assert torch.equal(b.reshape(-1).sort().values, torch.arange(m * m))
        q = b // (m * m // 4) if m > 1 else b
        for i in range(0, m, 2):
            for j in range(0, m, 2):
                assert sorted(q[i:i + 2, j:j + 2].reshape(-1).tolist()) == [0, 1, 2, 3]
    for m in (3, 6, 0):
        with pytest.raises(ValueError, match="power-of-two"):
            dispersed_order(m)


def test_dispersed_bandpass_layout_gives_every_2x2_window_each_quarter_of_the_spectrum():
    """The property the layout is for, checked on the filters themselves: over the periodic 4x4
    tile, every 2x2 window (aligned or not) holds one filter peaking in each quarter of
    420-720 nm; the seeded random layout does not (its seed-0 tile has four red filters together)."""
    import numpy as np

    lam = np.arange(420.0, 721.0, 10.0)

    def quarters_per_window(layout: str) -> list[int]:
        cfa = ColorFilterArray(len(lam), period=4, seed=0, init="bandpass", centers_nm=lam, bandpass_fwhm_nm=25.0,
                               layout=layout)
        peak = torch.from_numpy(lam)[cfa.tile().detach().argmax(0)]  # (4, 4) nm
        quarter = ((peak - 420.0) / 300.0 * 4).clamp(max=3.999).floor().long()
        wrapped = quarter.repeat(2, 2)
        return [len(set(wrapped[i:i + 2, j:j + 2].reshape(-1).tolist())) for i in range(4) for j in range(4)]

    assert quarters_per_window("dispersed") == [4] * 16
    assert min(quarters_per_window("random")) < 4
    # the filters themselves are those of the random layout, only placed differently
    w_d = bandpass_weights(torch.from_numpy(lam), 4, 25.0, layout="dispersed").reshape(len(lam), 16)
    w_r = bandpass_weights(torch.from_numpy(lam), 4, 25.0, seed=0).reshape(len(lam), 16)
    assert sorted(w_d.T.tolist()) == sorted(w_r.T.tolist())
    with pytest.raises(ValueError, match="unknown CFA layout"):
        bandpass_weights(torch.from_numpy(lam), 4, 25.0, layout="spiral")


def test_dispersed_layout_from_config(tiny_config):
    from hsicam.cameras import DOECamera
    from hsicam.errors import ConfigError
    from hsicam.sensor import dispersed_order

    cfg = tiny_config("camera.cfa.init=bandpass", "camera.cfa.period=4", "camera.cfa.layout=dispersed")
    cam = DOECamera.from_config(cfg)
    rank = cam.cfa.tile().detach().argmax(0)  # peak band per tile position grows with the Bayer index
    order = dispersed_order(4).reshape(-1).argsort()
    assert torch.all(rank.reshape(-1)[order].diff() >= 0)
    with pytest.raises(ConfigError, match="power-of-two"):
        tiny_config("camera.cfa.init=bandpass", "camera.cfa.period=3", "camera.cfa.layout=dispersed")
    with pytest.raises(ConfigError, match="init: bandpass"):
        tiny_config("camera.cfa.init=uniform", "camera.cfa.period=4", "camera.cfa.layout=dispersed")
    with pytest.raises(ConfigError):
        tiny_config("camera.cfa.layout=spiral")


def test_smooth_doe_init_is_a_periodic_gaussian_low_pass_spanning_the_range():
    """init=smooth: the seed's uniform field filtered by a wrapped Gaussian (scipy.ndimage as the
    reference), rescaled to [0, range] exactly; i.i.d. cells are uncorrelated, smooth ones are not."""
    from scipy.ndimage import gaussian_filter

    n, sigma, top = 101, 3.0, 2000e-9
    doe = DOE(n, FusedSilica(), 587.6, init="smooth", seed=4, init_range_m=top, init_correlation_cells=sigma)
    white = torch.rand(n, n, generator=torch.Generator().manual_seed(4), dtype=torch.float64).numpy()
    ref = gaussian_filter(white, sigma, mode="wrap", truncate=8.0)
    ref = (ref - ref.min()) / (ref.max() - ref.min()) * top
    h = doe.height_m.detach().double().numpy()
    assert h.min() == pytest.approx(0.0, abs=1e-15) and h.max() == pytest.approx(top, rel=1e-6)
    assert abs(h - ref).max() < 1e-6 * top

    def neighbour_correlation(x):
        x = x - x.mean()
        return float((x * np.roll(x, 1, axis=1)).mean() / x.var())

    iid = DOE(n, FusedSilica(), 587.6, init="random", seed=4, init_range_m=top).height_m.detach().double().numpy()
    assert abs(neighbour_correlation(iid)) < 0.05
    assert neighbour_correlation(h) > 0.9  # exp(−1/(4σ²)) = 0.97 for σ = 3 cells


def test_smooth_doe_init_from_config(tiny_config):
    from hsicam.cameras import DOECamera
    from hsicam.errors import ConfigError

    cam = DOECamera.from_config(tiny_config("camera.doe.init=smooth", "camera.doe.init_range_nm=500",
                                            "camera.doe.init_correlation_cells=2"))
    h = cam.optics.doe.height_m.detach()
    assert float(h.min()) == pytest.approx(0.0, abs=1e-15) and float(h.max()) == pytest.approx(500e-9, rel=1e-6)
    with pytest.raises(ConfigError, match="init_correlation_cells"):
        tiny_config("camera.doe.init=smooth", "camera.doe.init_correlation_cells=0")


def test_a_smooth_doe_init_wider_than_its_grid_is_a_config_error_not_nan_heights():
    """σ ≳ 1.35 × the grid leaves a constant field (exp(−2π²σ²/n²) below float64 precision): the
    rescale to [0, range] would divide 0 by 0 and give NaN heights and PSFs (probe 29 F2)."""
    from hsicam.errors import ConfigError
    from hsicam.optics.doe import DOE
    from hsicam.spectral.materials import FusedSilica

    with pytest.raises(ConfigError, match=r"init_correlation_cells=12 is too wide for a DOE of 9 cells across.*at most 4"):
        DOE(9, FusedSilica(), 587.6, init="smooth", init_correlation_cells=12.0)
    h = DOE(9, FusedSilica(), 587.6, init="smooth", init_correlation_cells=4.0, init_range_m=1e-6).height_m.detach()
    assert torch.isfinite(h).all() and float(h.max() - h.min()) == pytest.approx(1e-6, rel=1e-6)


def test_grating_doe_init_is_a_crossed_sinusoid_with_bessel_orders():
    """init=grating: a crossed sinusoidal phase grating whose default depth puts equal light in the 0th and
    each ±1st order at λ0. Reference: Jacobi–Anger, exp(i m sin θ) = Σ Jₙ(m) e^{inθ}, so the 2-D DFT of
    the element's transmission over whole periods holds J_p(m)·J_q(m) at order (p, q) (scipy's Bessel)."""
    from scipy.special import jv

    from hsicam.optics.doe import EQUAL_ORDERS_DEPTH_RAD

    assert jv(0, EQUAL_ORDERS_DEPTH_RAD) == pytest.approx(jv(1, EQUAL_ORDERS_DEPTH_RAD), abs=1e-12)
    period, n = 11, 110  # ten whole periods across
    doe = DOE(n, FusedSilica(), 587.6, init="grating", init_grating_period_cells=period)
    h = doe.height_m.detach().double()
    top = 2 * EQUAL_ORDERS_DEPTH_RAD * doe.h2pi_m / math.pi
    assert float(h.min()) >= 0 and float(h.max()) <= top * (1 + 1e-6)
    t = torch.exp(2j * math.pi * h / doe.h2pi_m)  # transmission at λ0: phase 2π h / h_2π
    amp = (torch.fft.fft2(t).abs() / n**2).numpy()
    k = n // period  # order p sits in DFT bin p·k
    for p, q in ((0, 0), (1, 0), (0, -1), (1, 1), (2, 0), (2, -1)):
        assert amp[p * k % n, q * k % n] == pytest.approx(abs(jv(p, EQUAL_ORDERS_DEPTH_RAD) * jv(q, EQUAL_ORDERS_DEPTH_RAD)),
                                                         abs=1e-6)
    shallow = DOE(n, FusedSilica(), 587.6, init="grating", init_grating_period_cells=period, init_range_m=top / 2)
    assert float(shallow.height_m.detach().max()) == pytest.approx(float(h.max()) / 2, rel=1e-6)


def test_grating_doe_psf_puts_its_orders_where_diffraction_sends_them(tiny_config):
    """The camera's PSF (exact square cells) behind a grating start: the first orders sit z·λ/(Λ·cell) from
    the centre, farther in red than in blue (a dispersive code), and the first-to-zeroth order energy
    ratio is (J1(m)/J0(m))²·sinc²(1/Λ) (the sinc: the cells' square aperture), m the band's phase depth."""
    from scipy.special import jv

    from hsicam.cameras import DOECamera
    from hsicam.errors import ConfigError
    from hsicam.optics.doe import EQUAL_ORDERS_DEPTH_RAD

    period, cell_m = 8, 15e-6
    cfg = tiny_config("bands.start_nm=480", "bands.stop_nm=720", "bands.step_nm=120", "camera.aperture_radius_mm=0.6",
                      "camera.lens.focal_length_mm=10", "camera.doe.cell_size_um=15", "camera.doe.init=grating",
                      f"camera.doe.init_grating_period_cells={period}")
    cam = DOECamera.from_config(cfg).double()
    optics = cam.optics
    with torch.no_grad():
        psf = optics().psf.numpy()
    c = psf.shape[-1] // 2
    top = 2 * EQUAL_ORDERS_DEPTH_RAD * optics.doe.h2pi_m / math.pi
    for b, lam in enumerate(cam.bands.centers_nm):
        shift = optics.sensor_distance_m * lam * 1e-9 / (period * cell_m) / optics.pixel_m
        s = int(round(shift))
        assert shift == pytest.approx(4 + b, abs=1e-6)  # 480, 600, 720 nm: 4, 5, 6 px
        first = psf[b, c - 1:c + 2, c + s - 1:c + s + 2]  # 3×3 px windows: disjoint for shifts ≥ 3 px
        centroid = float((first.sum(0) * np.arange(s - 1, s + 2)).sum() / first.sum())
        assert centroid == pytest.approx(shift, abs=0.05)
        m = 2 * math.pi * (optics.doe.material.n(lam) - 1) / (lam * 1e-9) * top / 4
        ratio = first.sum() / psf[b, c - 1:c + 2, c - 1:c + 2].sum()
        # measured −2.6 / −0.9 / −1.0 % (the orders' rings spill into each other's windows); without the cells'
        # sinc² it would be −8 / −6 / −6 %
        assert ratio == pytest.approx((jv(1, m) / jv(0, m)) ** 2 * np.sinc(1 / period) ** 2, rel=0.04)
    for bad in ("0", "2", "nan"):
        with pytest.raises(ConfigError, match="init_grating_period_cells"):
            tiny_config("camera.doe.init=grating", f"camera.doe.init_grating_period_cells={bad}")
