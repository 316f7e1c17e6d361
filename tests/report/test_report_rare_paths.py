"""Lines of the report, DOE export and dataset modules that the default suite never ran (coverage round 11, cov11a)."""

from __future__ import annotations

import html
import json
import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest

from hsicam.data.formats import write_cube_h5
from hsicam.errors import InputError
from hsicam.io import mark_complete
from hsicam.report.html import build_report
from hsicam.spectral import Bands
from test_report_fields import folder_with

MEAN = {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}
B3 = [500.0, 550.0, 600.0]


def evaluation(**changes) -> dict:
    """A results.json of the shape `hsicam evaluate` writes, with ``changes``."""
    return {"method": "doe-learned", "scenes": [{"name": "a", **MEAN}], "mean": MEAN,
            "conventions": {"psnr": "per band, peak 1"}, "bands_nm": B3, **changes}


def entries(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


# ------------------------------------------------------------------------------------------------
# report/html.py
# ------------------------------------------------------------------------------------------------
def test_report_of_a_folder_that_does_not_exist(tmp_path):
    with pytest.raises(InputError) as info:
        build_report(tmp_path / "nowhere")
    assert str(info.value) == f"{tmp_path / 'nowhere'}: no such folder"
    assert entries(tmp_path) == []


@pytest.mark.parametrize("name, data, field", [
    ("results.json", evaluation(scenes=[{"name": "a", **MEAN}, 3]), "scenes"),
    ("experiment.json", {"experiment": "compare", "scale": "tiny", "seeds": [0], "scenes": ["a"],
                         "rows": ["doe-learned"], "conventions": {}}, "rows"),
])
def test_report_names_a_row_that_is_not_an_object(tmp_path, name, data, field):
    d = folder_with(tmp_path, name, data)
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == f"{d / name}: corrupt {name} (an entry of '{field}' is not an object)"
    assert entries(d) == [".complete", name]


def test_report_of_an_evaluation_whose_run_is_gone_says_so_on_the_page(tmp_path):
    gone = tmp_path / "run-moved-away"
    d = folder_with(tmp_path, "results.json", evaluation(run=str(gone)))
    page = build_report(d).read_text(encoding="utf-8")
    assert f"<p class='note'>camera figures unavailable: {html.escape(str(gone))}: no such run folder</p>" in page
    assert "<h2>Camera" not in page and entries(d / "report") == [".complete", "index.html"]


@pytest.mark.parametrize("weights, sentence", [
    ({"checkpoint": "best"}, None),  # no step: a results.json from elsewhere, left unsaid
    (["last"], None),
    ({"checkpoint": "last", "step": 7}, "Weights: the last step&#x27;s (7), no checkpoint selection."),
])
def test_report_weights_sentence_only_from_a_well_formed_entry(tmp_path, weights, sentence):
    page = build_report(folder_with(tmp_path, "results.json", evaluation(weights=weights))).read_text(encoding="utf-8")
    if sentence is None:
        assert "Weights:" not in page and "<table>" in page
    else:
        assert f"<p class='note'>{sentence}</p>" in page


def test_report_refuses_unordered_bands_naming_the_field(tmp_path):
    d = folder_with(tmp_path, "results.json", evaluation(bands_nm=[600.0, 500.0, 550.0]))
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == f"{d / 'results.json'}: corrupt results.json ('bands_nm' is not in strictly ascending order)"
    assert entries(d) == [".complete", "results.json"]


def _with_cubes(tmp_path: Path, truth: np.ndarray, truth_bands: list[float], est: np.ndarray | None) -> Path:
    d = tmp_path / "ev"
    d.mkdir()
    (d / "results.json").write_text(json.dumps(evaluation()))
    (d / "cubes").mkdir()
    write_cube_h5(d / "cubes" / "a_truth.h5", truth, Bands.from_centers(truth_bands))
    if est is None:
        (d / "cubes" / "a_estimate.h5").write_bytes(b"not a cube")
    else:
        write_cube_h5(d / "cubes" / "a_estimate.h5", est, Bands.from_centers(B3))
    mark_complete(d, {"command": "evaluate"})
    return d


@pytest.mark.parametrize("shape, bands, text", [
    ((3, 12, 12), B3, "a 3-band (500-600 nm) 12×12 cube, but a_estimate.h5 holds a 3-band (500-600 nm) 16×16 one"),
    ((4, 16, 16), B3 + [650.0], "a 4-band (500-650 nm) 16×16 cube, but a_estimate.h5 holds a 3-band (500-600 nm) "
                                "16×16 one"),
    ((3, 16, 16), [510.0, 550.0, 600.0], "a 3-band (510-600 nm) 16×16 cube, but a_estimate.h5 holds a 3-band "
                                         "(500-600 nm) 16×16 one"),
])
def test_report_names_a_truth_cube_that_is_not_its_estimates_pair(tmp_path, shape, bands, text):
    """It said 'corrupt results.json (a field holds a value of the wrong kind: operands could not be broadcast …)'
    (or nothing at all for another band grid of the same size, plotting the truth on the estimate's wavelengths)."""
    rng = np.random.default_rng(0)
    d = _with_cubes(tmp_path, rng.random(shape, dtype=np.float32), bands, rng.random((3, 16, 16), dtype=np.float32))
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == (f"{d / 'cubes' / 'a_truth.h5'}: {text}: not the same scene's pair (cubes/ of two "
                               "evaluations?)")
    assert entries(d) == [".complete", "cubes", "results.json"]


def test_report_names_an_unreadable_cube_not_results_json(tmp_path):
    d = _with_cubes(tmp_path, np.ones((3, 8, 8), np.float32), B3, None)
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value).startswith(f"{d / 'cubes' / 'a_estimate.h5'}: unknown format")
    assert "results.json" not in str(info.value)
    assert entries(d) == [".complete", "cubes", "results.json"]


def test_report_of_a_matching_pair_draws_it(tmp_path):
    """The reference pair for the refusals above: same grid and size, both figures written."""
    rng = np.random.default_rng(1)
    d = _with_cubes(tmp_path, rng.random((3, 16, 16), dtype=np.float32), B3, rng.random((3, 16, 16), dtype=np.float32))
    build_report(d)
    assert entries(d / "report") == [".complete", "errors_a.png", "index.html", "recon_a.png"]


# ------------------------------------------------------------------------------------------------
# export/doe.py
# ------------------------------------------------------------------------------------------------
def test_height_tiff_refuses_negative_heights_and_writes_nothing(tmp_path):
    from hsicam.export.doe import write_height_tiff

    with pytest.raises(InputError) as info:
        write_height_tiff(tmp_path / "h.tif", np.array([[0.0, 10.0], [-0.5, 3.0]]), 30.0, {})
    assert str(info.value) == "heights must be >= 0 for the 16-bit TIFF"
    assert entries(tmp_path) == []


# ------------------------------------------------------------------------------------------------
# data/datasets.py
# ------------------------------------------------------------------------------------------------
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
# data/synthetic.py (library callers; the CLI's config checks these first)
# ------------------------------------------------------------------------------------------------
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
