"""`hsicam report` on a results.json / experiment.json whose fields are damaged: one line that names the
field, and no report left behind (the fields each section reads are checked before any is drawn)."""

from __future__ import annotations

import pytest

from hsicam.errors import InputError
from hsicam.report.html import build_report
from report_files import MEAN, evaluation, experiment, folder_with


@pytest.mark.parametrize("data, fragment", [
    (evaluation(bands_nm="500-600"), "'bands_nm' is not a list of wavelengths in nm"),
    (evaluation(bands_nm=[500, -1]), "'bands_nm' is not a list of wavelengths in nm"),
    (evaluation(heldout={"scenes": [1], "mean": MEAN}), "'heldout.scenes' is not a list of objects"),
    (evaluation(heldout={"scenes": [{"name": "b"}]}), "'heldout.mean' is missing or not a dict"),
])
def test_a_damaged_evaluation_field_is_named(tmp_path, data, fragment):
    d = folder_with(tmp_path, "results.json", data)
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == f"{d / 'results.json'}: corrupt results.json ({fragment})"
    assert sorted(p.name for p in d.iterdir()) == [".complete", "results.json"]


@pytest.mark.parametrize("change, fragment", [
    ({"drop": "seeds"}, "'seeds' is missing"),
    ({"rows": [{"psnr": 30.0, "missing": True}]}, "an entry of 'rows' names no 'method'"),
    ({"noise_grid": {"sigma_height_nm": "0", "sensor_sigma": [0.0], "results": {}}},
     "'noise_grid.sigma_height_nm' is not a list of numbers"),
    ({"noise_grid": {"sigma_height_nm": [0.0], "sensor_sigma": [0.0], "results": {"doe-learned": [{"psnr": 1}]}}},
     "'noise_grid.results' is not, per camera, a list of points with numeric sigma_height_nm, sensor_sigma, psnr, ssim"),
])
def test_a_damaged_experiment_field_is_named(tmp_path, change, fragment):
    data = experiment(**change)
    d = folder_with(tmp_path, "experiment.json", data)
    with pytest.raises(InputError) as info:
        build_report(d)
    assert str(info.value) == f"{d / 'experiment.json'}: corrupt experiment.json ({fragment})"
    assert not (d / "report").exists()


def test_the_sound_files_of_these_tests_are_reported(tmp_path):
    """The reference files the damaged ones are made from pass (so each refusal above is its field's)."""
    ev = folder_with(tmp_path / "1", "results.json", evaluation())
    assert build_report(ev).is_file()
    ex = folder_with(tmp_path / "2", "experiment.json", experiment())
    page = build_report(ex).read_text()
    assert "noise_grid.png" in page and (ex / "report" / "noise_grid.png").is_file()
