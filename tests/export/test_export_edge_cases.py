"""Guards found by mutation testing of the fabrication export (export/doe.py): each test kills a hand-made
mutant (a largest sample for a mean, a dropped step of the 1-2-5 series, an unweighted mean, a sinc without its
square) that the rest of the suite let through, and checks the behaviour against a reference computed here
(brute-force area fractions, the 1-2-5 series by brute force, loop sums of the wrapped phase error, the
kinoform's closed form), not against the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest


# --------------------------------------------------------------------------------------------
# export/doe.py, export/cfa.py
# --------------------------------------------------------------------------------------------
def test_exported_aperture_is_each_cells_area_fraction_on_the_psfs_sub_points(tiny_camera):
    """With pupil oversampling q = 2 each DOE cell holds q×q pupil samples, each an 8×8-point area fraction: the
    exported per-cell aperture (module docstring) is the fraction of the cell's 16×16 sub-points inside the
    circle, by brute force here. The largest sample per cell instead of their mean exported grazed cells as fully
    open."""
    from hsicam.export.doe import design_heights

    cam = tiny_camera("camera.psf.pupil_oversample=2")
    n, cell, radius = cam.optics.doe.n_cells, cam.optics.cell_m, cam.optics.aperture_radius_m
    sub = 16
    centres = (np.arange(n) - (n - 1) / 2) * cell
    xs = (centres[:, None] + ((np.arange(sub) + 0.5) / sub - 0.5)[None, :] * cell).reshape(-1)
    ref = ((xs[:, None] ** 2 + xs[None, :] ** 2) <= radius**2).reshape(n, sub, n, sub).mean(axis=(1, 3))
    _, aperture, _ = design_heights(cam)
    assert ((ref > 0) & (ref < 1)).any()  # partly covered cells: the test can tell
    np.testing.assert_allclose(aperture, ref, atol=1e-12)


def test_tiff_scale_is_the_smallest_1_2_5_step_that_fits_16_bits():
    """nm per count: the smallest of 1, 2, 5 × 10^k with max / scale ≤ 65535 (brute force over the 1-2-5 series).
    Without the 5s a 300 000 nm relief got 10 nm per count where 5 fit (half the height resolution)."""
    from hsicam.export.doe import nice_scale

    series = sorted(m * 10.0**e for e in range(-6, 6) for m in (1, 2, 5))
    for top in (1.0, 3.3, 65535.0, 65536.0, 1.2e5, 3e5, 7e5, 2.5e6):
        ref = min(s for s in series if top / s <= 65535 * (1 + 1e-12))
        assert nice_scale(top) == pytest.approx(ref, rel=1e-12), top


def test_phase_error_rms_is_weighted_by_the_aperture_fraction():
    """RMS over the aperture of the wrapped phase error, each cell weighted by its open fraction (loops): a cell
    half inside the circle carries half the light. The unweighted mean over the cells gave another RMS."""
    from hsicam.export.doe import phase_error

    rng = np.random.default_rng(8)
    h = rng.random((5, 5)) * 1e-6
    hq = h + rng.normal(0, 1e-7, (5, 5))
    wgt = np.clip(rng.random((5, 5)) * 1.5 - 0.25, 0, 1)
    k = np.array([1.2e7, 9.0e6])
    got = phase_error(h, hq, k, wgt)
    for b, kb in enumerate(k):
        num = den = 0.0
        worst = 0.0
        for i in range(5):
            for j in range(5):
                if wgt[i, j] > 0:
                    e = math.remainder(kb * (hq[i, j] - h[i, j]), 2 * math.pi)
                    num, den, worst = num + wgt[i, j] * e * e, den + wgt[i, j], max(worst, abs(e))
        assert got["rms_rad"][b] == pytest.approx(math.sqrt(num / den), rel=1e-9)
        assert got["max_rad"][b] == pytest.approx(worst, rel=1e-9)


def test_spec_first_order_efficiency_is_the_l_level_kinoforms_sinc_squared(tiny_camera, tmp_path):
    """The scalar first-order efficiency of an L-level kinoform is (sin(π/L) / (π/L))² (Swanson 1989): 0.405 for
    binary, 0.811 for 4 levels; sinc without its square (0.637 / 0.900) was written to spec.json."""
    from hsicam.export.doe import export_doe

    cam = tiny_camera()
    for levels in (2, 4):
        spec = export_doe(cam, tmp_path, levels, cam.bands.centers_nm)
        x = math.pi / levels
        assert spec["quantized"]["first_order_efficiency_sinc2"] == pytest.approx((math.sin(x) / x) ** 2, rel=1e-12)
