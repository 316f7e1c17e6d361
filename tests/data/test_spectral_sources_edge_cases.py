"""Guards found by mutation testing of the spectral sources (the measured library, its split into training and
held-out sources, the held-out set) and of the data preview (``data show``): each test kills a hand-made mutant (a
wrong bound, a dropped check, a skipped branch, a wrong key) that the rest of the suite let through, and checks the
behaviour against a reference computed here (brute force, colour-science's own code, the exact message a user
sees, a PNG read back), not against the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest

from hsicam.errors import InputError
from hsicam.spectral import Bands

colour = pytest.importorskip("colour")
pytestmark = pytest.mark.filterwarnings("ignore:Aligning", "ignore:.*shape could not be honoured",
                                        "ignore:.*Interpolating")

PAPER = Bands.paper()


@pytest.fixture(scope="module")
def ss():
    from hsicam.data import spectral_sources

    return spectral_sources


@pytest.fixture(scope="module")
def full(ss):
    return ss.spectral_library(PAPER)


# --------------------------------------------------------------------------------------------
# data/spectral_sources.py
# --------------------------------------------------------------------------------------------
def test_blank_items_of_a_holdout_list_are_ignored_not_unknown_ids(ss):
    """A trailing comma (``rawtoaces,``) or a blank list item names no source: it is skipped, not refused as the
    unknown id ''."""
    assert ss.parse_holdout("rawtoaces,") == ("rawtoaces",)
    assert ss.parse_holdout(["cie-tcs", " ", ""]) == ("cie-tcs",)
    assert ss.parse_holdout(" , ") == ()


def test_bands_past_730_nm_are_refused_with_the_generators_range(ss):
    """Band centres up to 740 nm were accepted (the upper bound checked 10 nm late)."""
    with pytest.raises(InputError) as err:
        ss.check_bands(Bands.uniform(420.0, 740.0, 10.0))
    assert str(err.value) == ("synthetic: bands 420-740 nm are outside the generator's 380-730 nm (the range of its "
                              "measured spectra); all of them are used only for bands whose centre ± 1.27 FWHM stays "
                              "inside 370-740 nm (e.g. 390-720 nm for 10 nm bands)")
    ss.check_bands(Bands.uniform(420.0, 730.0, 10.0))  # the edge itself is served


def test_daylight_series_spans_4000_to_20000_k_and_the_illuminant_c_simulator_is_daylight(full):
    """The D series is computed for 4000-20000 K in 1000 K steps (both ends, as SOURCES documents), and RIT's SC (a
    simulator of CIE illuminant C, like C itself) is drawn with the daylight group."""
    dseries = {n for n in full.illuminant_names if n.startswith("CIE D ")}
    assert dseries == {f"CIE D {t}K" for t in range(4000, 20001, 1000)}
    daylight = {full.illuminant_names[i] for i in full.illuminant_groups["daylight"]}
    assert "SC" in full.illuminant_names and {"SC", "C", "D65"} <= daylight


def test_the_library_counts_the_eight_otsu_clusters(full):
    from colour.recovery import CLUSTER_MEANS_OTSU2018

    assert full.counts()["rgb_upsampling"] == {"otsu2018": len(CLUSTER_MEANS_OTSU2018)} == {"otsu2018": 8}


def test_spectra_removed_from_training_are_reported_for_the_training_set_only(ss, full):
    """The training library lists (and its manifest records as removed_as_equal_to_held_out) the spectra dropped for
    equalling a held-out one, found here by brute force; the held-out library removed nothing."""
    hold = ("nist-philips", "rawtoaces")
    train = ss.split_library(full, hold, "train")
    held = ss.split_library(full, hold, "heldout")
    expect = []
    for arr, names, srcs in ((full.reflectances, full.reflectance_names, full.reflectance_sources),
                             (full.illuminants, full.illuminant_names, full.illuminant_sources),
                             (full.emitters, full.emitter_names, full.emitter_sources)):
        h = [arr[i].astype(np.float64) for i, s in enumerate(srcs) if s in hold]
        for i, s in enumerate(srcs):
            if s not in hold and any(np.abs(arr[i] - x).max() <= ss.SAME_SPECTRUM_ATOL for x in h):
                expect.append(names[i])
    assert expect and sorted(train.removed) == sorted(expect)
    assert sorted(train.sources["removed_as_equal_to_held_out"]) == sorted(expect)
    assert held.removed == [] and "removed_as_equal_to_held_out" not in held.sources


def test_holding_out_only_the_photo_upsampling_is_a_held_out_set(ss, full):
    """otsu2018 alone held out: the held-out scenes are photos upsampled by Otsu on the training surfaces and lights,
    not a NoHeldOutSpectra refusal."""
    held = ss.split_library(full, "otsu2018", "heldout")
    train = ss.split_library(full, "otsu2018", "train")
    assert held.otsu is not None and train.otsu is None
    assert held.reflectances.shape == train.reflectances.shape
    assert held.sources["held_out_roles"] == {"reflectances": False, "illuminants": False, "emitters": False}


def test_refusals_of_a_holdout_without_a_split_and_of_a_split_of_a_split(ss, full):
    with pytest.raises(InputError) as err:
        ss.spectral_library(PAPER, "rawtoaces")
    assert str(err.value) == "spectral_library: holdout_sources needs split='train' or 'heldout'"
    train = ss.split_library(full, "rawtoaces", "train")
    with pytest.raises(InputError) as err:
        ss.split_library(train, "cie-tcs", "train")
    assert str(err.value) == "split_library needs the full library (split='all')"


def test_reflectance_basis_is_the_pca_of_the_set(ss):
    """Against a brute-force PCA (eigenvectors of the covariance): mean, leading directions, coefficients, their
    per-component standard deviations, and an exact reconstruction when q equals the rank."""
    rng = np.random.default_rng(3)
    x = rng.random((40, 3)) @ rng.random((3, 12)) * 0.3 + np.linspace(0.1, 0.3, 12)  # rank 3 around a mean
    x += 0.01 * rng.standard_normal(x.shape) * np.array([3.0, 1.0] * 6)
    b = ss.ReflectanceBasis.fit(x, q=4)
    mean = x.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((x - mean).T))
    v = v[:, ::-1][:, :4].T  # leading 4 directions
    np.testing.assert_allclose(b.mean, mean, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(b.components * v, axis=1)), 1.0, atol=1e-9)
    proj = (x - mean) @ b.components.T
    np.testing.assert_allclose(b.coeffs, proj, atol=1e-12)
    np.testing.assert_allclose(b.sigma, np.sqrt(((proj - proj.mean(0)) ** 2).mean(0)), rtol=1e-9)
    exact = ss.ReflectanceBasis.fit(x, q=12)
    np.testing.assert_allclose(exact.mean + exact.coeffs @ exact.components, x, atol=1e-12)


def test_otsu_clusters_on_the_split_lines_follow_colour_science(full):
    """A chromaticity exactly on a split of the selector tree goes where colour-science sends it (x <= origin:
    lesser branch); off the lines too."""
    from colour.recovery.otsu2018 import DATASET_REFERENCE_OTSU2018 as ref

    o = full.otsu
    xy = [np.array([0.31, 0.33]) for _ in o.selector]
    for p, row in zip(xy, o.selector):
        p[int(row[1])] = row[0]
    xy = np.array(xy + list(np.random.default_rng(0).uniform(0.15, 0.55, (40, 2))))
    np.testing.assert_array_equal(o.clusters(xy), [ref.select(p) for p in xy])


def test_a_black_pixel_is_upsampled_as_the_limit_of_a_dim_neutral_one(full):
    """XYZ = 0 has no chromaticity: it takes the D65 white point's (x 0.3127, y 0.3290), so that its spectrum is
    the limit of dimmer and dimmer D65-grey pixels (the recovery is affine in XYZ within a cluster)."""
    d65 = np.array([0.3127, 0.3290, 1 - 0.3127 - 0.3290]) / 0.3290
    o = full.otsu
    np.testing.assert_allclose(o.reflectance(np.zeros((1, 3))), o.reflectance(1e-12 * d65[None]), atol=1e-9)


# --------------------------------------------------------------------------------------------
# data/preview.py
# --------------------------------------------------------------------------------------------
def _cubes(folder, n, bands=Bands.uniform(420.0, 720.0, 30.0), size=12, seed=0):
    from hsicam.data.formats import write_cube_h5

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for k in range(n):
        write_cube_h5(folder / f"scene_{k}.h5", rng.random((len(bands), size, size)).astype(np.float32) + 0.05, bands)
    return folder


def test_common_grid_is_the_best_range_by_brute_force():
    """Against a brute force over every (first band, last band) range of the first grid: most grids covering it,
    then most bands, the earliest such range winning ties; at least min_bands bands."""
    from hsicam.data.preview import common_grid

    grids = [Bands.uniform(400.0, 700.0, 10.0), Bands.uniform(420.0, 680.0, 20.0), Bands.uniform(380.0, 650.0, 10.0),
             Bands.uniform(500.0, 720.0, 10.0)]
    first = grids[0]
    best, score = None, (-1, -1)
    for lo in sorted({b.min_nm for b in grids}):
        for hi in sorted({b.max_nm for b in grids}):
            c = first.centers_nm[(first.centers_nm >= lo - 1e-6) & (first.centers_nm <= hi + 1e-6)]
            if len(c) < 3:
                continue
            cand = Bands(c, first.fwhm_nm[: len(c)])
            s = (sum(b.covers(cand) for b in grids), len(c))
            if s > score:
                best, score = c, s
    got = common_grid(grids)
    np.testing.assert_array_equal(got.centers_nm, best)
    # a tie: 400-500 and 600-700 are each covered by two grids with 11 bands; the earlier range wins
    tie = [Bands.uniform(400.0, 700.0, 10.0), Bands.uniform(400.0, 500.0, 10.0), Bands.uniform(600.0, 700.0, 10.0)]
    np.testing.assert_array_equal(common_grid(tie).centers_nm, np.arange(400.0, 501.0, 10.0))
    tiny = [Bands.from_centers([500.0, 510.0]), Bands.from_centers([505.0])]
    np.testing.assert_array_equal(common_grid([Bands.from_centers([500.0, 510.0, 520.0]), *tiny]).centers_nm,
                                  [500.0, 510.0, 520.0])


def test_write_preview_has_no_default_folder_and_leaves_the_data_as_it_was(tmp_path):
    """write_preview without out_dir wrote its three PNGs into the dataset folder, which `hsicam data show` (--out
    required) never writes: the call is refused as Python refuses a missing argument, the folder's listing unchanged;
    given a folder, the three PNGs go there and only there."""
    from hsicam.data import preview as pv

    data = _cubes(tmp_path / "d", 2)
    before = sorted(p.name for p in data.iterdir())
    with pytest.raises(TypeError, match="out_dir"):
        pv.write_preview(data)
    assert sorted(p.name for p in data.iterdir()) == before == ["scene_0.h5", "scene_1.h5"]
    written = pv.write_preview(data, tmp_path / "o", max_scenes=1)
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == sorted(
        [pv.CONTACT_SHEET, pv.MEAN_SPECTRA, pv.SPECTRAL_GAMUT]) == sorted(p.name for p in written)
    assert sorted(p.name for p in data.iterdir()) == before


def test_max_scenes_caps_the_dataset_and_the_held_out_set(tmp_path, monkeypatch):
    """``max_scenes`` 2 of 3 scenes: the contact sheet shows 2 renders, and 2 scenes of each set are sampled for the
    gamut plot (write_preview and write_spectral_gamut)."""
    from hsicam.data import preview as pv

    data, held = _cubes(tmp_path / "d", 3), _cubes(tmp_path / "h", 3, seed=1)
    seen, figs = [], {}
    real = pv.pixel_spectra

    def spy(scenes, *a, **k):
        seen.append(len(scenes))
        return real(scenes, *a, **k)

    monkeypatch.setattr(pv, "pixel_spectra", spy)
    monkeypatch.setattr(pv, "save_figures", lambda f, out: figs.update(f) or [])
    pv.write_preview(data, tmp_path / "o", max_scenes=2, heldout=held)
    assert seen == [2, 2] and len(figs[pv.CONTACT_SHEET].axes) == 2
    seen.clear()
    monkeypatch.setattr(pv, "save_figure", lambda fig, out: None)
    pv.write_spectral_gamut(data, tmp_path / "g.png", heldout=held, max_scenes=2)
    assert seen == [2, 2]


def test_preview_exposure_puts_the_99th_percentile_at_0_8_despite_a_highlight():
    """A grey (flat) cube of 400 pixels at 0.25 with two highlights at 1: the 99th percentile of luminance is the
    background's, exposed to linear 0.8, i.e. sRGB 1.055·0.8^(1/2.4) − 0.055 = 0.906; the highlights clip at 1."""
    from hsicam.data.preview import preview_rgb

    bands = Bands.uniform(400.0, 700.0, 10.0)
    cube = np.full((len(bands), 20, 20), 0.25, np.float32)
    cube[:, 0, 0] = cube[:, 5, 7] = 1.0
    rgb = preview_rgb(cube, bands)
    np.testing.assert_allclose(rgb[1, 1], 1.055 * 0.8 ** (1 / 2.4) - 0.055, atol=2e-3)
    np.testing.assert_allclose(rgb[0, 0], 1.0, atol=1e-6)
