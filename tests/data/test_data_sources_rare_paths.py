"""Lines of the data modules that the default suite never ran (coverage audit, session 58, cov12a; those of the
report, export and measured-camera modules went to their floors): each test drives one such path and checks it
against a reference computed here (the exact message a user sees, a file read back in its real format,
colour-science's own data, a closed form).
"""

from __future__ import annotations

import json
import pickle
import re

import h5py
import numpy as np
import pytest

from cli_helpers import entries
from hsicam.data.formats import write_cube_h5
from hsicam.errors import InputError
from hsicam.io import mark_complete
from hsicam.spectral import Bands

B3 = [500.0, 550.0, 600.0]


# ------------------------------------------------------------------------------------------------
# data/datasets.py
# ------------------------------------------------------------------------------------------------
def _cave_pngs(folder, prefix):
    from PIL import Image

    folder.mkdir(parents=True)
    for i in range(1, 32):
        Image.fromarray(np.full((4, 4), 100 * i, np.uint16)).save(folder / f"{prefix}_ms_{i:02d}.png")
    return folder


def test_cave_folders_are_listed_as_the_folder_that_holds_the_band_images(tmp_path):
    """A CAVE folder given as the dataset is its one scene; inside a dataset, a folder of band images is listed as
    itself unless it sits in a folder of the same name (the archive's name_ms/name_ms layout: the outer one)."""
    from hsicam.data.datasets import list_scenes

    root = tmp_path / "data"
    flat = _cave_pngs(root / "flat_ms", "flat")  # band images right under the dataset root
    other = _cave_pngs(root / "day1" / "b_ms", "b")  # inside a folder of another name
    nested = _cave_pngs(root / "n_ms" / "n_ms", "n")  # the archive's layout
    assert list_scenes(flat) == [flat]
    assert list_scenes(nested) == [nested]
    assert list_scenes(root) == sorted([flat, other, nested.parent])


def test_a_file_inside_another_commands_output_is_data_but_the_folder_itself_is_not(tmp_path):
    """Only the marked folder itself is refused for a command other than evaluate; a cube file or a sub-folder
    inside it is taken as named."""
    from hsicam.data.datasets import check_not_an_output, list_scenes

    d = tmp_path / "sim"
    (d / "cubes").mkdir(parents=True)
    cube = write_cube_h5(d / "cubes" / "s.h5", np.ones((3, 4, 4), np.float32), Bands.from_centers(B3))
    mark_complete(d, {"command": "simulate"})
    assert check_not_an_output(cube) is None
    assert check_not_an_output(d / "cubes") is None
    assert list_scenes(cube) == [cube]
    assert list_scenes(d / "cubes") == [cube]
    with pytest.raises(InputError) as info:
        check_not_an_output(d)
    assert str(info.value) == f"{d}: is the output of hsicam simulate, not a folder of scenes; use a folder of cube files as the data"


def test_an_hsicam_file_without_its_band_list_is_refused_by_the_full_reader_naming_the_key(tmp_path):
    """The window probe gives up on a header it cannot read (a KeyError on bands_nm): the whole-file reader then
    says what is missing and under which names it looks for a band list, in one line."""
    from hsicam.data.datasets import SceneDataset, probe_hsicam

    bands = Bands.from_centers(B3)
    path = write_cube_h5(tmp_path / "s.h5", np.ones((3, 8, 8), np.float32), bands)
    with h5py.File(path, "r+") as f:
        del f["bands_nm"]
    assert probe_hsicam(path, bands) is None
    with pytest.raises(InputError) as info:
        SceneDataset([path], bands).info(0)
    assert str(info.value) == (f"{path}: HDF5 file with 'cube' but missing key 'bands_nm' (our format) or a band list "
                               "'bands' (ARAD; also read under the names bands_nm, wavelength, wavelengths, "
                               "wavelength_nm, wavelengths_nm, lambda, lambdas, wl, wls, wave, waves, wvl, wvls)")


def test_a_header_that_claims_all_zeros_over_real_pixels_is_read_whole_and_normalised_by_its_pixels(tmp_path):
    """max_value = 0 in the header (hand-edited): not windowable (the probe returns None), so the scene is read
    whole and normalised by the maximum of its pixels, not by the header; its patches keep the scene's bands."""
    from hsicam.data.datasets import PatchDataset, SceneDataset, probe_hsicam

    bands = Bands.from_centers(B3)
    data = np.arange(3 * 8 * 8, dtype=np.float32).reshape(3, 8, 8) / 50.0  # maximum 191/50
    path = write_cube_h5(tmp_path / "s.h5", data, bands)
    with h5py.File(path, "r+") as f:
        f.attrs["max_value"] = 0.0
    assert probe_hsicam(path, bands) is None
    ds = SceneDataset([path], bands)
    info = ds.info(0)
    assert (info.height, info.width) == (8, 8) and info.peak == pytest.approx(191 / 50, rel=1e-6)
    np.testing.assert_allclose(ds.window(0, 2, 3, 4, 5), data[:, 2:6, 3:8] / data.max(), rtol=1e-6)
    patches = PatchDataset(ds, 4, patches_per_epoch=2)
    np.testing.assert_array_equal(patches.bands.centers_nm, B3)


# (cov11a, moved from report/test_report_rare_paths.py)
def test_list_scenes_skips_hidden_folders(tmp_path):
    from hsicam.data.datasets import list_scenes

    np.save(tmp_path / "a.npy", np.ones((3, 4, 4), np.float32))
    (tmp_path / ".trash").mkdir()
    np.save(tmp_path / ".trash" / "b.npy", np.ones((3, 4, 4), np.float32))
    assert list_scenes(tmp_path) == [tmp_path / "a.npy"]


def test_scene_path_of_a_scene_outside_its_root_is_its_name(tmp_path):
    from hsicam.data.datasets import scene_path

    assert scene_path(tmp_path / "x" / "day1" / "s.h5", tmp_path / "y") == "s.h5"
    assert scene_path(tmp_path / "y" / "day1" / "s.h5", tmp_path / "y") == "day1/s.h5"


@pytest.mark.parametrize("results", [None, "{not json", json.dumps(["list"]), json.dumps({"data": ""})])
def test_evaluate_folder_as_data_without_a_usable_results_json(tmp_path, results):
    """The refusal stays one line; only the '(which scored …)' part is left out."""
    from hsicam.data.datasets import check_not_an_output

    d = tmp_path / "ev"
    d.mkdir()
    if results is not None:
        (d / "results.json").write_text(results)
    mark_complete(d, {"command": "evaluate"})
    with pytest.raises(InputError) as info:
        check_not_an_output(d)
    assert str(info.value) == (f"{d}: is the output of hsicam evaluate; its cubes/*_estimate.h5 are a method's "
                               "reconstructions, not scenes: use the scenes it scored as the data, or copy its "
                               "*_truth.h5 files into a folder of their own")


def test_a_windowed_scene_whose_header_claims_light_but_whose_pixels_are_zero(tmp_path):
    from hsicam.data.datasets import SceneDataset

    bands = Bands.from_centers(B3)
    path = write_cube_h5(tmp_path / "z.h5", np.zeros((3, 8, 8), np.float32), bands)
    with h5py.File(path, "r+") as f:
        f.attrs["max_value"] = 1.0  # a hand-edited header: the probe takes the file as windowable
    with pytest.raises(InputError) as info:
        SceneDataset([path], bands).info(0)
    assert str(info.value) == f"{path}: the cube is all zeros; cannot normalise by its maximum"


def test_probe_declines_a_file_on_other_bands(tmp_path):
    """Not windowable on another grid: the full reader resamples it instead (None), on its own grid it is."""
    from hsicam.data.datasets import probe_hsicam

    path = write_cube_h5(tmp_path / "s.h5", np.full((3, 5, 6), 2.0, np.float32), Bands.from_centers(B3))
    assert probe_hsicam(path, Bands.from_centers([500.0, 560.0, 600.0])) is None
    info = probe_hsicam(path, Bands.from_centers(B3))
    assert (info.height, info.width, info.peak) == (5, 6, 2.0)


def test_near_black_percentile_of_a_black_cube_is_none():
    from hsicam.data.datasets import near_black_percentile

    assert near_black_percentile(np.zeros((2, 4, 4), np.float32)) is None


def test_a_pickled_scene_dataset_reopens_its_files(tmp_path):
    """What a spawned DataLoader worker receives: no cached cubes, no open handles; its windows are the file's."""
    from hsicam.data.datasets import SceneDataset

    bands = Bands.from_centers(B3)
    cube = np.random.default_rng(2).random((3, 10, 12), dtype=np.float32) * 5
    path = write_cube_h5(tmp_path / "s.h5", cube, bands)
    ds = SceneDataset([path], bands)
    first = ds.window(0, 1, 2, 4, 5)  # opens the file
    assert ds._handles
    copy = pickle.loads(pickle.dumps(ds))
    assert copy._handles == {} and len(copy._cache) == 0
    with h5py.File(path, "r") as f:
        expected = f["cube"][:, 1:5, 2:7] / f["cube"][()].max()
    np.testing.assert_array_equal(copy.window(0, 1, 2, 4, 5), expected.astype(np.float32))
    np.testing.assert_array_equal(first, copy.window(0, 1, 2, 4, 5))


# ------------------------------------------------------------------------------------------------
# data/synthetic.py
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("via", ["XDG_CACHE_HOME", "HOME"])
def test_an_unusable_cache_root_names_the_setting_it_came_from(tmp_path, monkeypatch, via):
    """The cache root from $XDG_CACHE_HOME, or the default ~/.cache/hsicam, under a file: the refusal names that
    setting with its value, and what to set instead."""
    from hsicam.data import synthetic as syn

    afile = tmp_path / "afile"
    afile.write_text("x")
    monkeypatch.delenv("HSICAM_CACHE", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv(via, str(afile))
    with pytest.raises(InputError) as info:
        syn.synthetic_dataset(2, 32, 0, Bands.paper(), progress=False)
    if via == "XDG_CACHE_HOME":
        setting, root = f"XDG_CACHE_HOME={afile}", afile / "hsicam"
    else:
        setting, root = f"the default cache {afile / '.cache' / 'hsicam'}", afile / ".cache" / "hsicam"
    assert re.fullmatch(re.escape(f"{setting} (the dataset cache): {root / 'synthetic'}/") + r"[^/]+"
                        + re.escape(f": cannot be created inside {afile}, which is a file; set HSICAM_CACHE to a "
                                    "writable folder"), str(info.value)), str(info.value)
    assert not (tmp_path / "afile").is_dir()


def test_version_differences_of_a_folder_that_records_no_versions_is_empty(tmp_path):
    from hsicam.data.synthetic import version_differences

    assert version_differences(tmp_path) == []  # no manifest at all
    (tmp_path / "manifest.json").write_text(json.dumps({"scenes": [], "software": "colour-science 0.4"}))
    assert version_differences(tmp_path) == []  # versions not recorded as a mapping


def test_a_power_law_procedural_texture_is_the_power_law_field_of_its_drawn_exponent():
    """The first of the three procedural kinds (never drawn by the default suite): replayed from the same seed,
    the texture is power_law_noise of an exponent drawn uniform in [0.5, 2.2], in [0, 1]."""
    from hsicam.data.synthetic import _procedural_texture, power_law_noise

    seed = next(s for s in range(100) if int(np.random.default_rng(s).integers(3)) == 0)
    tex, kind = _procedural_texture(np.random.default_rng(seed), 32)
    rng = np.random.default_rng(seed)
    rng.integers(3)
    beta = float(rng.uniform(0.5, 2.2))
    assert kind == "power_law" and 0.5 <= beta <= 2.2
    np.testing.assert_array_equal(tex, power_law_noise(rng, 32, beta))
    assert tex.shape == (32, 32) and tex.min() >= 0 and tex.max() <= 1


# library callers; the CLI's config checks these first (cov11a, moved from report/test_report_rare_paths.py)
@pytest.mark.parametrize("kwargs, message", [
    ({"n": 0, "size": 32}, "synthetic: need at least one scene, got n=0"),
    ({"n": 2, "size": 15}, "synthetic: scenes must be at least 16 px, got size=15"),
    ({"n": 2, "size": 32, "split": "test"}, "split must be one of {splits}, got 'test'"),
])
def test_generate_dataset_refuses_before_writing(tmp_path, kwargs, message):
    from hsicam.data.synthetic import SPLITS, generate_dataset

    with pytest.raises(InputError) as info:
        generate_dataset(tmp_path / "syn", progress=False, **kwargs)
    assert str(info.value) == message.format(splits=", ".join(SPLITS))
    assert entries(tmp_path) == []


def test_dataset_folder_that_is_a_file(tmp_path):
    from hsicam.data.synthetic import check_dataset_folder

    (tmp_path / "syn").write_text("mine")
    with pytest.raises(InputError) as info:
        check_dataset_folder(tmp_path / "syn")
    assert str(info.value) == f"{tmp_path / 'syn'}: exists and is not a folder"
    assert (tmp_path / "syn").read_text() == "mine"


# ------------------------------------------------------------------------------------------------
# data/spectral_sources.py
# ------------------------------------------------------------------------------------------------
colour_filters = pytest.mark.filterwarnings("ignore:Aligning", "ignore:.*shape could not be honoured",
                                            "ignore:.*Interpolating")


@colour_filters
def test_a_lamp_dark_on_every_band_is_left_out_of_the_library():
    """400-440 nm: the low-pressure sodium lamp (its light at 589 nm) gives nothing on these bands (colour-science's
    own spectrum is 0 from 370 to 470 nm), so it is not used as an emitter, and the library says so."""
    pytest.importorskip("colour")
    from colour.colorimetry import SDS_LIGHT_SOURCES

    from hsicam.data.spectral_sources import spectral_library

    sd = SDS_LIGHT_SOURCES["LPS"]
    wl = np.asarray(sd.wavelengths)
    assert np.all(np.asarray(sd.values)[(wl >= 370) & (wl <= 470)] == 0)
    lib = spectral_library(Bands.uniform(400, 440, 10))
    assert "LPS" not in lib.emitter_names and "LPS" not in lib.illuminant_names
    assert lib.sources["not_used_out_of_range"]["nist-traditional"] == ["LPS"]
    assert lib.emitter_names  # the other emitters are kept


@pytest.fixture(scope="module")
def full():
    pytest.importorskip("colour")
    from hsicam.data.spectral_sources import spectral_library

    return spectral_library(Bands.paper())


REFLECTANCE_SOURCES = ["colorchecker", "cie-ces", "cie-tcs", "nist-cqs", "pmc", "rawtoaces", "rgb-basis"]


@colour_filters
def test_split_library_refuses_a_split_that_is_not_train_or_heldout(full):
    from hsicam.data.spectral_sources import split_library

    with pytest.raises(InputError) as info:
        split_library(full, "rawtoaces", "all")
    assert str(info.value) == "split must be 'train' or 'heldout', got 'all'"


@colour_filters
def test_holding_out_every_reflectance_and_the_photo_basis_leaves_no_training_surface(full):
    from hsicam.data.spectral_sources import SOURCES, split_library

    assert sorted(s.id for s in SOURCES.values() if s.role == "reflectance") == sorted(REFLECTANCE_SOURCES)
    held = sorted(REFLECTANCE_SOURCES + ["otsu2018"])
    with pytest.raises(InputError) as info:
        split_library(full, held, "train")
    assert str(info.value) == f"holding out {', '.join(held)} leaves no reflectance for the train scenes"


@colour_filters
def test_holding_out_every_reflectance_trains_on_the_otsu_cluster_means(full):
    """No measured reflectance left for training, the photo basis kept: the surfaces are the means of Otsu's 8
    clusters, which on 10 nm bands follow colour-science's tabulated means at the band centres."""
    from colour.recovery.otsu2018 import DATASET_REFERENCE_OTSU2018 as ref

    from hsicam.data.spectral_sources import split_library

    train = split_library(full, REFLECTANCE_SOURCES, "train")
    means = np.asarray(ref.means)
    assert train.reflectance_names == [f"otsu2018:cluster {k}" for k in range(means.shape[0])] and means.shape[0] == 8
    assert train.reflectance_sources == ["otsu2018"] * 8 and train.otsu is not None
    wl = np.asarray(ref.basis_functions.wavelengths if hasattr(ref.basis_functions, "wavelengths")
                    else ref.shape.wavelengths)
    expect = np.stack([np.interp(Bands.paper().centers_nm, wl, m) for m in means])
    np.testing.assert_allclose(train.reflectances, np.clip(expect, 0, 1), atol=0.01)
    np.testing.assert_allclose(train.basis.mean, train.reflectances.mean(axis=0), atol=1e-6)
