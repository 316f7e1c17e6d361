"""Guards found by mutation testing of the synthetic generator's building blocks (data/synthetic.py: power-law
noise, anti-aliased lines, dead leaves, smooth fields, Kubelka-Munk mixing): each test kills a hand-made mutant
(a wrong exponent, a width applied twice, a uniform draw, a skipped normalisation) that the rest of the suite let
through, and checks the behaviour against a reference computed here (a fitted power spectrum, supersampling,
a Kolmogorov-Smirnov test, brute force, closed forms). None of them needs colour-science (test_data_synthetic.py
is skipped without it).
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("beta", [1.0, 2.0, 3.0])
def test_power_law_noise_has_a_power_spectrum_of_slope_minus_beta(beta):
    """|FFT|² of the field falls as 1/f^β: the log-log slope fitted over 0.02-0.25 cycles/px is −β (± 0.25; the 1 %
    clip at both ends barely bends it), not −2β (an amplitude of f^−β)."""
    from hsicam.data.synthetic import power_law_noise

    n = 256
    t = power_law_noise(np.random.default_rng(0), n, beta).astype(np.float64)
    assert t.shape == (n, n) and t.min() == 0.0 and t.max() == 1.0
    p = np.abs(np.fft.fft2(t - t.mean())) ** 2
    f = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :])
    m = (f > 0.02) & (f < 0.25)
    slope = np.polyfit(np.log(f[m]), np.log(p[m]), 1)[0]
    assert abs(slope + beta) < 0.25


@pytest.mark.parametrize("y0", [12.3, 12.5, 12.0, 12.9])
@pytest.mark.parametrize("width", [0.4, 0.5, 0.8, 1.0, 2.0, 2.5, 4.0])
def test_a_line_covers_its_width_per_unit_length(width, y0):
    """A horizontal segment of width w at a sub-pixel height: along its length each column's coverage sums
    to w (the area of the line per px of length; below 1 px too, where generator version 2 scaled by w twice:
    0.28 px for a 0.5 px line), and a 16×16 supersampling of the band |y − y0| ≤ w/2 agrees pixel by pixel
    within the anti-aliasing ramp's error (a half-pixel narrower ramp loses a pixel of width)."""
    from hsicam.data.synthetic import line_coverage

    ys, xs, cov = line_coverage(32, y0, 4.0, y0, 28.0, width)
    full = np.zeros((32, 32))
    full[ys, xs] = cov
    inner = full[:, 8:24]
    np.testing.assert_allclose(inner.sum(axis=0), width, rtol=0, atol=1e-5)
    sub = (np.arange(32 * 16) + 0.5) / 16
    area = (np.abs(sub - y0) <= width / 2).reshape(32, 16).mean(axis=1)
    np.testing.assert_allclose(inner, np.broadcast_to(area[:, None], inner.shape), rtol=0, atol=0.3)


def test_dead_leaves_radii_follow_the_power_law():
    """Radii ∝ r^−α between r_min and r_max: a Kolmogorov-Smirnov test against the CDF of that density,
    (r^(1−α) − r_min^(1−α)) / (r_max^(1−α) − r_min^(1−α)), passes; a uniform draw of the radii fails it."""
    from scipy import stats

    from hsicam.data.synthetic import dead_leaves_labels

    r0, r1, alpha = 1.0, 40.0, 3.0
    _, params = dead_leaves_labels(np.random.default_rng(0), 64, 2000, r0, r1, alpha)
    k = 1.0 - alpha
    radii = params["r"][1:]
    assert radii.min() >= r0 and radii.max() <= r1
    assert stats.kstest(radii, lambda r: (r ** k - r0 ** k) / (r1 ** k - r0 ** k)).pvalue > 1e-3


class _ConstantNormal:
    """A generator whose normal draws are all 1: a blend of equal cells must be that value everywhere."""

    def standard_normal(self, shape):
        return np.ones(shape)


def test_a_smooth_field_is_a_blend_that_keeps_a_constant_and_spans_zero_to_one():
    """The field is a normalised Gaussian blend of the cells: equal cells blend to one value everywhere (rows of
    weights summing to 1, no darker border), which the stretch maps to 0; random cells span exactly [0, 1]."""
    from hsicam.data.synthetic import smooth_field

    flat = smooth_field(_ConstantNormal(), 48, 4)
    np.testing.assert_allclose(flat, 0.0, atol=1e-2)  # float rounding, stretched by 1/1e-12
    f = smooth_field(np.random.default_rng(2), 48, 4)
    assert f.dtype == np.float32 and f.min() == 0.0 and f.max() == 1.0


def test_kubelka_munk_ks_and_reflectance_are_inverse():
    """K/S = (1 − R)² / 2R and R = 1 + K/S − √((K/S)² + 2 K/S) (Kubelka-Munk, infinite layer) invert each other over
    R in [0.001, 1]: a pigment mixture of one pigment is that pigment."""
    from hsicam.data.synthetic import _km_ks, _km_r

    r = np.linspace(1e-3, 1.0, 500)
    np.testing.assert_allclose(_km_r(_km_ks(r)), r, rtol=1e-9, atol=1e-12)


class _AllDiscs:
    """numpy's generator, except that every leaf drawn is a disc (shape kind 0)."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)

    def __getattr__(self, name):
        return getattr(self.rng, name)

    def choice(self, n, size=None, p=None):
        self.rng.choice(n, size, p=p)
        return np.zeros(size, dtype=np.int64)


def test_dead_leaves_discs_cover_the_pixels_whose_centres_lie_within_their_radius():
    """Leaves that are discs: a pixel belongs to the topmost disc (the last drawn) whose circle holds its centre,
    else the background, by brute force over all pixels and discs."""
    from hsicam.data.synthetic import dead_leaves_labels

    size = 48
    labels, p = dead_leaves_labels(_AllDiscs(3), size, 12, 2.0, 12.0)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    ref = np.zeros((size, size), dtype=np.int32)
    for j in range(1, 13):
        ref[(yy - p["cy"][j]) ** 2 + (xx - p["cx"][j]) ** 2 <= p["r"][j] ** 2] = j
    assert len(np.unique(ref)) > 5  # several discs visible
    np.testing.assert_array_equal(labels, ref)
