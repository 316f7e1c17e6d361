"""Guards found by mutation testing of the data side of the numerical core (spectral grids and materials, the
training datasets, the synthetic generator, scoring, the linear step, stopping): each test kills a hand-made mutant
(a wrong constant, an off-by-one, a dropped normalisation, a skipped branch) that the rest of the suite let through,
and checks the behaviour against a reference computed here (closed forms, numerical integrals, brute force), not
against the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from hsicam.errors import InputError
from hsicam.spectral import Bands, interpolation_matrix, resample_spectra, resolved_bands
from hsicam.spectral.bands import band_sample_wavelengths, kernel_fwhm

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


# --------------------------------------------------------------------------------------------
# spectral/bands.py
# --------------------------------------------------------------------------------------------
def test_band_sub_wavelengths_are_the_slice_midpoints_weighted_by_the_gaussian_of_the_fwhm():
    """M sub-wavelengths at the midpoints of M equal slices of [c − f/2, c + f/2], weighted by the band's Gaussian
    of FWHM f: the weight at an offset x is 2^(−(2x/f)²) of the centre's (half at ±f/2)."""
    c, f, m = np.array([450.0, 600.0]), np.array([10.0, 24.0]), 4
    lam, w = band_sample_wavelengths(c, f, m)
    for i in range(len(c)):
        edges = np.linspace(c[i] - f[i] / 2, c[i] + f[i] / 2, m + 1)
        np.testing.assert_allclose(lam[i], 0.5 * (edges[:-1] + edges[1:]), rtol=0, atol=1e-9)
        ref = 2.0 ** (-((2.0 * (lam[i] - c[i]) / f[i]) ** 2))
        np.testing.assert_allclose(w[i], ref / ref.sum(), rtol=1e-12)


def test_a_target_band_beyond_the_source_by_a_fraction_of_a_nm_is_refused():
    """No extrapolation: a grid ending 0.01 nm past the data's last centre is refused (only 1e-6 nm of rounding
    is forgiven); a tolerance of a nm would clip it onto the last band silently."""
    src = Bands.uniform(420, 720, 10)
    for end in (720.01, 720.5):
        dst = Bands.from_centers([500.0, end], 10.0)
        assert not src.covers(dst)
        with pytest.raises(InputError, match="not covered"):
            interpolation_matrix(src, dst)
    assert src.covers(Bands.from_centers([420.0 - 5e-7, 720.0 + 5e-7], 10.0))


def test_default_fwhm_of_given_centres_is_the_local_spacing():
    """from_centers without FWHM: each band is as wide as its local spacing, (c[i+1] − c[i−1]) / 2 inside and the
    one-sided step at the ends (10 nm for a single band)."""
    c = np.array([400.0, 410.0, 430.0, 460.0, 465.0])
    got = Bands.from_centers(c).fwhm_nm
    ref = np.concatenate([[c[1] - c[0]], (c[2:] - c[:-2]) / 2, [c[-1] - c[-2]]])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert Bands.from_centers([550.0]).fwhm_nm.tolist() == [10.0]


def test_bands_a_fraction_of_a_nm_wider_than_the_data_integrate_it():
    """Same centres, camera bands √(10² + 0.5²) nm wide over 10 nm data: 0.5 nm of averaging is left, so the bands
    are resolved (kernel FWHM > 0) and a line at one band loses a little of its height to the neighbours: the
    linear interpolant integrated over the truncated (±3σ) Gaussian of FWHM 0.5 nm, by scipy quad."""
    src = Bands.uniform(420, 720, 10)
    k = 0.5
    dst = Bands(src.centers_nm, np.full(len(src), math.hypot(10.0, k)))
    np.testing.assert_allclose(kernel_fwhm(src, dst), k, rtol=1e-9)
    assert resolved_bands(src, dst).all()
    x = np.zeros(len(src))
    x[13] = 1.0
    s = k * FWHM_TO_SIGMA
    num = integrate.quad(lambda t: math.exp(-0.5 * (t / s) ** 2) * (1 - abs(t) / 10.0), -3 * s, 3 * s, points=[0])[0]
    den = integrate.quad(lambda t: math.exp(-0.5 * (t / s) ** 2), -3 * s, 3 * s)[0]
    got = resample_spectra(x, src, dst)
    assert got is not x
    np.testing.assert_allclose(got[13], num / den, rtol=0, atol=1e-4)  # the quadrature of 0.02 nm steps
    np.testing.assert_allclose(got[12] + got[13] + got[14], 1.0, atol=1e-9)  # the line's area is kept


def test_the_remaining_width_uses_the_source_fwhm_at_each_band():
    """Source bands whose FWHM changes along the grid (4 nm at the blue end to 9 nm at the red): the kernel left
    for a 10 nm band is √(10² − f_src(c)²) with f_src read at that band's centre (Gaussians compose in quadrature),
    not one width for all."""
    c = np.arange(420.0, 721.0, 5.0)
    f_src = np.linspace(4.0, 9.0, len(c))
    src = Bands(c, f_src)
    dst = Bands.uniform(430, 710, 10)
    ref = np.sqrt(10.0 ** 2 - np.interp(dst.centers_nm, c, f_src) ** 2)
    np.testing.assert_allclose(kernel_fwhm(src, dst), ref, rtol=1e-12)


# --------------------------------------------------------------------------------------------
# spectral/materials.py
# --------------------------------------------------------------------------------------------
def test_fused_silica_is_refused_beyond_both_ends_of_malitsons_fit():
    """The Sellmeier fit holds for 0.21–3.71 µm: a wavelength past either end is one clear error (past 3.71 µm
    the third term's pole at 9.9 µm is near, and the formula is no longer the glass)."""
    from hsicam.spectral import FusedSilica

    fs = FusedSilica()
    for lam in (200.0, 3800.0, [500.0, 5000.0]):
        with pytest.raises(InputError, match="valid for 210-3710 nm only"):
            fs.n(lam)
    assert np.isfinite(fs.n([210.0, 3710.0])).all()


def test_a_material_table_is_refused_a_fraction_of_a_nm_past_its_ends():
    """A table from 400 to 700 nm answers inside (linear interpolation) and refuses 700.5 nm and 399.5 nm: no
    extrapolation, not even by a few nm."""
    from hsicam.spectral import TabulatedMaterial

    mat = TabulatedMaterial(np.array([400.0, 550.0, 700.0]), np.array([1.47, 1.46, 1.455]), name="glass")
    np.testing.assert_allclose(mat.n([400.0, 475.0, 700.0]), [1.47, 1.465, 1.455], rtol=0, atol=1e-12)
    for lam in (700.5, 399.5, 705.0):
        with pytest.raises(InputError, match="tabulated for 400-700 nm only"):
            mat.n(lam)


# --------------------------------------------------------------------------------------------
# data/datasets.py
# --------------------------------------------------------------------------------------------
def _scene_files(tmp_path, sizes, seed=0):
    from hsicam.data import write_cube_h5

    bands = Bands.uniform(420, 720, 30)
    rng = np.random.default_rng(seed)
    paths, cubes = [], []
    for i, (h, w) in enumerate(sizes):
        cube = (rng.random((len(bands), h, w)) + 0.1).astype(np.float32)
        write_cube_h5(tmp_path / f"s{i}.h5", cube, bands)
        paths.append(tmp_path / f"s{i}.h5")
        cubes.append(cube / cube.max())
    return paths, cubes, bands


@pytest.mark.parametrize("n, fraction", [(1, 0.9), (2, 0.9), (3, 0.95), (10, 0.99)])
def test_a_split_always_keeps_a_training_scene(tmp_path, n, fraction):
    """round(fraction · n) may be all n scenes (0.9 of 2 is 2): the split still leaves one to train on, and the two
    sets are a partition of the scenes."""
    from hsicam.data import split_scenes

    scenes = [tmp_path / f"s{i}.h5" for i in range(n)]
    train, val = split_scenes(scenes, fraction, seed=3)
    assert len(train) >= 1 and sorted(train + val) == sorted(scenes) and not set(train) & set(val)
    assert len(val) >= (1 if n >= 2 else 0)


def test_patches_reach_every_position_and_every_scene(tmp_path):
    """Patch positions are uniform over all placements, the last row and column included, and scenes uniform over
    all scenes: with scenes one pixel larger than a patch each patch is found by brute force in its scene, and all
    (scene, y, x) of the 3 × 2 × 2 come up among 96 patches."""
    from hsicam.data import PatchDataset, SceneDataset

    paths, cubes, bands = _scene_files(tmp_path, [(9, 9)] * 3)
    ds = PatchDataset(SceneDataset(paths, bands), 8, 0, patches_per_epoch=96, flips=False, rot90=False, seed=5)
    seen = set()
    for k in range(len(ds)):
        p = ds[k].numpy()
        hits = [(i, y, x) for i, c in enumerate(cubes) for y in range(2) for x in range(2)
                if np.allclose(c[:, y:y + 8, x:x + 8], p, rtol=0, atol=1e-6)]
        assert len(hits) == 1
        assert ds.scene_of(k) == paths[hits[0][0]]
        seen.add(hits[0])
    assert seen == {(i, y, x) for i in range(3) for y in range(2) for x in range(2)}


def test_a_window_one_pixel_past_the_edge_of_a_windowed_scene_is_refused(tmp_path):
    """A window read straight from an hsicam HDF5 file (no full load) that reaches one pixel past the right or
    bottom edge is one clear error; h5py would return it a pixel narrower without a word. Windows that end on the
    edge are the normalised crop of the cube."""
    from hsicam.data import SceneDataset

    paths, cubes, bands = _scene_files(tmp_path, [(12, 10)])
    ds = SceneDataset(paths, bands)
    np.testing.assert_allclose(ds.window(0, 4, 2, 8, 8), cubes[0][:, 4:12, 2:10], rtol=1e-6)
    for y, x in ((4, 3), (5, 2)):
        with pytest.raises(InputError, match=r"window 8x8 at \(%d, %d\) is outside the cube" % (y, x)):
            ds.window(0, y, x, 8, 8)


# --------------------------------------------------------------------------------------------
# engine/evaluate.py
# --------------------------------------------------------------------------------------------
class _ToyCamera(torch.nn.Module):
    """A camera for scoring tests: the sensor image is the band sum; it remembers the scene it imaged, the seeds
    of its two generators and its noise levels at each capture."""

    boundary, margin, kind = "same", 0, "toy"

    def __init__(self, n_bands: int, levels: dict[str, float] | None = None) -> None:
        super().__init__()
        self.bands = Bands.uniform(420, 420 + 10 * (n_bands - 1), 10)
        self.levels = dict(levels or {"sensor_sigma": 0.0})
        self.captures: list[dict] = []

    def noise_levels(self) -> dict[str, float]:
        return dict(self.levels)

    def set_noise(self, **levels: float) -> None:
        self.levels.update(levels)

    def forward(self, scene, generator=None, sensor_generator=None):
        self.captures.append({"scene": scene, "seed": generator.initial_seed(),
                              "sensor_seed": sensor_generator.initial_seed(), "levels": dict(self.levels)})
        return scene.sum(dim=1, keepdim=True)


def _toy_method(cam, offset, border_px=0):
    from hsicam.engine.methods import Method

    def reconstruct(sensor):  # the scene imaged last, plus an offset that may depend on the capture's seed
        last = cam.captures[-1]
        return last["scene"] + offset(last["seed"], last["scene"])

    return Method("toy", cam, reconstruct, lambda s: s, border_px=border_px)


def _toy_scenes(n, hw=(20, 24), c=3, seed=0):
    rng = np.random.default_rng(seed)
    return [torch.from_numpy((0.5 + 0.3 * rng.random((c, *hw))).astype(np.float32)) for _ in range(n)]


def test_scores_cover_the_scene_less_the_border_and_the_estimate_is_clipped_to_one():
    """border_px = 3: truth and estimate are the scene less 3 px a side, and the RMSE is that of the estimate clipped
    to [0, 1] on those pixels (numpy); the border, 0.4 off, is not scored; an estimate above 1 counts as 1."""
    from hsicam.engine.evaluate import evaluate_method

    b = 3
    scenes = _toy_scenes(2)

    def offset(seed, scene):
        d = torch.full_like(scene, 0.4)
        d[..., b:-b, b:-b] = 0.05
        d[..., b:-b, b:b + 4] = 0.5  # above 1 (scene values 0.5-0.8): clipped
        return d

    cam = _ToyCamera(3)
    res = evaluate_method(_toy_method(cam, offset, border_px=b), scenes, ["a", "b"])
    for r, scene in zip(res, scenes):
        s = scene.numpy()
        est = np.clip(s + offset(0, scene).numpy(), 0.0, 1.0)[:, b:-b, b:-b]
        assert r.truth.shape == r.estimate.shape == (3, s.shape[1] - 2 * b, s.shape[2] - 2 * b)
        np.testing.assert_allclose(r.truth, s[:, b:-b, b:-b], rtol=0, atol=0)
        np.testing.assert_allclose(r.estimate, est, rtol=0, atol=1e-6)
        np.testing.assert_allclose(r.metrics["rmse"], np.sqrt(np.mean((est - s[:, b:-b, b:-b]) ** 2)), rtol=1e-5)


def test_several_seeds_give_the_mean_and_spread_over_seeds_and_keep_the_first_seeds_estimate():
    """Seeds (3, 7) with an estimate off by 0.01 · (seed + 1): RMSE 0.04 and 0.08 per seed, mean 0.06, spread
    (np.std over the seeds) 0.02; the estimate kept is seed 3's, and the result says so."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method

    scenes = _toy_scenes(1)
    cam = _ToyCamera(3)
    method = _toy_method(cam, lambda seed, scene: torch.full_like(scene, 0.01 * (seed + 1)))
    (r,) = evaluate_method(method, scenes, ["a"], TestNoise(seeds=(3, 7)))
    per = [0.01 * (s + 1) for s in (3, 7)]
    np.testing.assert_allclose([m["rmse"] for m in r.metrics_per_seed], per, rtol=1e-5)
    assert [m["seed"] for m in r.metrics_per_seed] == [3, 7]
    np.testing.assert_allclose(r.metrics["rmse"], np.mean(per), rtol=1e-5)
    np.testing.assert_allclose(r.metrics_std["rmse"], np.std(per), rtol=1e-4)
    assert r.seed == 3
    np.testing.assert_allclose(r.estimate, scenes[0].numpy() + per[0], rtol=0, atol=1e-6)


def test_test_noise_levels_reach_the_camera_while_scoring_and_are_restored_after():
    """TestNoise σ_p = 20 nm and σ_s = 0: every capture is made under them and the result records them; the camera's
    own levels (5 nm, 0.01) are back afterwards."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method

    own = {"sensor_sigma": 0.01, "sigma_height_nm": 5.0}
    cam = _ToyCamera(3, own)
    method = _toy_method(cam, lambda seed, scene: torch.zeros_like(scene))
    (r,) = evaluate_method(method, _toy_scenes(1), ["a"], TestNoise(sigma_height_nm=20.0, sensor_sigma=0.0, seeds=(0, 1)))
    want = {"sensor_sigma": 0.0, "sigma_height_nm": 20.0}
    assert [c["levels"] for c in cam.captures] == [want, want]
    assert r.noise == want
    assert cam.noise_levels() == own


def test_each_scenes_capture_seed_is_its_own_and_the_same_for_every_method():
    """Under one noise seed, scenes of the same size get different sensor-noise seeds (their own fields), the same
    scene gets the same one for another method, and the DOE draw's seed is the noise seed itself."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method

    seeds = {}
    for run in range(2):
        cam = _ToyCamera(3)
        evaluate_method(_toy_method(cam, lambda seed, scene: torch.zeros_like(scene) + 0.01 * run), _toy_scenes(3),
                        ["a", "b", "c"], TestNoise(seeds=(4,)))
        assert [c["seed"] for c in cam.captures] == [4, 4, 4]
        seeds[run] = [c["sensor_seed"] for c in cam.captures]
    assert len(set(seeds[0])) == 3 and seeds[0] == seeds[1]


def test_the_grey_reference_is_the_sensor_times_the_pixel_mean_training_spectrum():
    """Training scenes of different sizes: the mean spectrum is over all their pixels (numpy on the pixels laid
    side by side), and the estimate is the sensor image times that spectrum over its mean."""
    from types import SimpleNamespace

    from hsicam.engine.evaluate import grey_reference

    rng = np.random.default_rng(1)
    scenes = [torch.from_numpy(rng.random((4, h, w)).astype(np.float32) * (i + 1))
              for i, (h, w) in enumerate([(5, 6), (12, 10), (3, 3)])]
    pixels = np.concatenate([s.numpy().reshape(4, -1) for s in scenes], axis=1).astype(np.float64)
    spectrum = pixels.mean(axis=1)
    cam = _ToyCamera(4)
    method = grey_reference(SimpleNamespace(camera=cam, target=lambda s: s), scenes)
    np.testing.assert_allclose(method.info["mean_spectrum"], spectrum, rtol=1e-6)
    sensor = torch.from_numpy(rng.random((1, 1, 7, 8)).astype(np.float32))
    want = sensor.numpy() * (spectrum / spectrum.mean())[None, :, None, None]
    np.testing.assert_allclose(method.reconstruct(sensor).numpy(), want, rtol=1e-6)


def test_the_mean_sam_leaves_out_scenes_without_a_spectral_angle_and_names_them():
    """A scene whose SAM is NaN (its truth all zero) is listed under sam_undefined and the mean SAM is that of the
    other scenes (numpy nanmean); the other means are over every scene."""
    from hsicam.engine.evaluate import SceneResult, summarize

    rows = [SceneResult(n, {"psnr": p, "ssim": 0.9, "sam": s}, None, None, 1.0)
            for n, p, s in [("a", 30.0, 4.0), ("dark", 40.0, float("nan")), ("c", 20.0, 6.0)]]
    out = summarize(rows)
    assert out["sam_undefined"] == ["dark"]
    np.testing.assert_allclose(out["mean"]["sam"], np.nanmean([4.0, np.nan, 6.0]))
    np.testing.assert_allclose(out["mean"]["psnr"], np.mean([30.0, 40.0, 20.0]))


def test_a_scored_area_of_exactly_the_ssim_window_is_scored_and_one_pixel_less_is_refused_before_any_work():
    """SSIM needs 11×11 px: a scene whose area less the border is exactly that is scored; one whose area is a pixel
    short is refused with its one-line message before any scene is reconstructed (the first, good, scene
    included)."""
    from hsicam.engine.evaluate import evaluate_method
    from hsicam.metrics import SSIM_WINDOW_PX

    b, w = 2, SSIM_WINDOW_PX
    cam = _ToyCamera(3)
    calls = []
    method = _toy_method(cam, lambda seed, scene: calls.append(1) or torch.zeros_like(scene), border_px=b)
    (r,) = evaluate_method(method, _toy_scenes(1, (w + 2 * b, w + 2 * b + 3)), ["ok"])
    assert r.truth.shape[-2:] == (w, w + 3)
    calls.clear()
    scenes = _toy_scenes(1, (w + 2 * b, w + 2 * b)) + _toy_scenes(1, (w + 2 * b - 1, 40))
    with pytest.raises(InputError, match=rf"small: scene of {w + 2 * b - 1}×40 px leaves {w - 1}×{40 - 2 * b} px"):
        evaluate_method(method, scenes, ["ok", "small"])
    assert calls == []


def test_pixels_whose_truth_is_all_zero_are_counted_as_left_out_of_sam():
    """A scene with 7 scored pixels whose spectrum is zero in every band (and one pixel zero in one band only, which
    keeps its angle): sam_excluded_px is 7, counted by numpy on the scored truth."""
    from hsicam.engine.evaluate import evaluate_method

    scene = _toy_scenes(1, (16, 16))[0]
    rng = np.random.default_rng(4)
    for y, x in rng.choice(16, size=(7, 2), replace=False):
        scene[:, y, x] = 0.0
    scene[1, 15, 15] = 0.0
    cam = _ToyCamera(3)
    (r,) = evaluate_method(_toy_method(cam, lambda seed, s: torch.zeros_like(s)), [scene], ["dark spots"])
    assert r.sam_excluded_px == int(np.count_nonzero(np.all(r.truth == 0, axis=0))) == 7


# --------------------------------------------------------------------------------------------
# data/synthetic.py
# --------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------
# engine/linear_step.py
# --------------------------------------------------------------------------------------------
def _linear_fit_setup(tiny_camera):
    from types import SimpleNamespace

    cam = tiny_camera().double()
    r = cam.margin // 2

    def target(scene):
        return scene[..., r: scene.shape[-2] - r, r: scene.shape[-1] - r]

    rng = np.random.default_rng(0)
    size = cam.margin + 18
    scenes = [torch.from_numpy(rng.random((len(cam.bands), size, size)).astype(np.float32)).double() for _ in range(3)]
    return cam, SimpleNamespace(camera=cam, target=target), scenes, target


def _residual(cam, target, scenes, weight):
    from hsicam.models.demosaic import phase_linear

    psf = cam.snapshot(nominal=True).psf
    total = 0.0
    for s in scenes:
        with torch.no_grad():
            sensor = cam.A(s[None], psf)
            total += float((phase_linear(sensor, weight.double()) - target(s[None])).square().sum())
    return total


def test_the_linear_map_is_fitted_through_the_nominal_psfs_whatever_the_height_noise(tiny_camera):
    """The filters are fitted on noise-free images through the nominal DOE: a camera with σ_p = 80 nm of height
    noise gives the filters of the same camera at σ_p = 0, every time (no PSF draw enters the fit)."""
    from hsicam.engine.linear_step import fit_linear_map

    cam, model, scenes, _ = _linear_fit_setup(tiny_camera)
    ref = fit_linear_map(model, scenes, window=5)
    cam.set_noise(sigma_height_nm=80.0)
    torch.manual_seed(0)
    a = fit_linear_map(model, scenes, window=5)
    b = fit_linear_map(model, scenes, window=5)
    torch.testing.assert_close(a, ref, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(b, ref, rtol=1e-6, atol=1e-9)


def test_without_the_flat_field_constraint_the_fit_is_the_unconstrained_least_squares_optimum(tiny_camera):
    """flat_field=False is the plain least-squares fit: its error on the training pairs is below that of the
    constrained fit (which gives up some of it to keep flat areas flat), and a small move of any of its taps
    does not lower it (the optimum, up to the 1e-6 ridge); the constrained fit maps a uniform scene to a uniform
    estimate."""
    from hsicam.engine.linear_step import fit_linear_map
    from hsicam.models.demosaic import phase_linear

    cam, model, scenes, target = _linear_fit_setup(tiny_camera)
    free = fit_linear_map(model, scenes, window=5, flat_field=False)
    flat = fit_linear_map(model, scenes, window=5, flat_field=True)
    e_free, e_flat = _residual(cam, target, scenes, free), _residual(cam, target, scenes, flat)
    assert e_free < e_flat * (1 - 1e-3)
    rng = np.random.default_rng(1)
    for _ in range(3):
        step = torch.from_numpy(rng.standard_normal(free.shape)) * 1e-3
        assert _residual(cam, target, scenes, free.double() + step) > e_free
    uniform = torch.full((1, len(cam.bands), cam.margin + 18, cam.margin + 18), 0.5, dtype=torch.float64)
    with torch.no_grad():
        est = phase_linear(cam.A(uniform, cam.snapshot(nominal=True).psf), flat.double())
    inner = est[..., 4:-4, 4:-4]  # away from the replicated border
    assert float((inner - inner.mean(dim=(-2, -1), keepdim=True)).abs().max()) < 1e-6 * float(inner.abs().max())


@pytest.mark.slow
def test_a_linear_consistency_step_of_zero_iterations_is_not_fitted(tmp_path, cache_env):
    """model.consistency kind linear with 0 iterations applies no step, so the run gets no filter file (its fit
    images the whole training split); with 1 iteration the same training fits it."""
    from hsicam.cli import main
    from hsicam.runs.linear_step import LINEAR_STEP_FILE

    for it in (0, 1):
        out = tmp_path / f"run{it}"
        assert main(["train", "--config", "tiny", "--out", str(out), "--set", "train.epochs=1", "--set",
                     "model.consistency.kind=linear", "--set", f"model.consistency.iterations={it}"]) == 0
        assert (out / LINEAR_STEP_FILE).is_file() == (it == 1)
