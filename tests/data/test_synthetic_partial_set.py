"""A partial synthetic set: the scenes an evaluation scores (``hsicam evaluate`` without --data:
:func:`hsicam.data.pipeline.validation_split` → :func:`hsicam.data.synthetic.synthetic_scenes`), written into the set's
cache folder without its manifest. It recorded nothing of the package versions its scenes were made with, so after a
colour-science or scikit-image upgrade they were reused without the warning a complete set gives. It now records what
the complete set's manifest does of its parameters and versions (``partial.json``) and warns the same way; a complete
generation over it leaves the very files of a fresh one. References: the manifest of a complete set of the same
parameters, the warning a complete set gives, and the files of a fresh generation read back byte for byte."""

from __future__ import annotations

import json
import logging

import pytest

import hsicam.data.synthetic as syn
from hsicam.errors import InputError
from hsicam.spectral import Bands

BANDS = Bands.uniform(420, 720, 50)
N, SIZE = 4, 32


def _files(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _upgraded(monkeypatch):
    """This installation's versions, colour-science's another (an upgrade since the scenes were written)."""
    real = syn._versions()
    monkeypatch.setattr(syn, "_versions", lambda: {**real, "colour-science": "99.0"})
    return f"colour-science {real['colour-science']} → 99.0"


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if "other versions" in r.getMessage()]


def test_a_partial_set_records_the_versions_and_parameters_of_a_complete_one(tmp_path):
    paths = syn.synthetic_scenes([1, 3], N, SIZE, 0, BANDS, cache_dir=tmp_path / "part", progress=False)
    part = paths[0].parent
    assert sorted(_files(part)) == [syn.PARTIAL, "scene_0001.h5", "scene_0003.h5"]
    whole = syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "whole", progress=False)
    record = json.loads((part / syn.PARTIAL).read_text())
    manifest = json.loads((whole / syn.MANIFEST).read_text())
    assert {k: record[k] for k in ("parameters", "key", "software")} == \
        {k: manifest[k] for k in ("parameters", "key", "software")}
    assert not syn.is_complete(part, N, SIZE, 0, BANDS)  # still a partial set


def test_a_partial_set_of_other_package_versions_is_reused_with_the_complete_sets_warning(tmp_path, monkeypatch,
                                                                                           caplog):
    part = syn.synthetic_scenes([1, 3], N, SIZE, 0, BANDS, cache_dir=tmp_path / "part", progress=False)[0].parent
    whole = syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "whole", progress=False)
    before = _files(part)
    diff = _upgraded(monkeypatch)
    assert syn.version_differences(part) == syn.version_differences(whole) == [diff]
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        for _ in range(2):  # reused as they are (said once)
            syn.synthetic_scenes([1, 3], N, SIZE, 0, BANDS, cache_dir=tmp_path / "part", progress=False)
        assert _files(part) == before
        syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "whole")
    said = _warnings(caplog)
    assert len(said) == 2 and said[0] == said[1].replace(str(whole), str(part)) and diff in said[0]


def test_scenes_added_to_a_partial_set_after_an_upgrade_keep_the_first_scenes_versions(tmp_path, monkeypatch, caplog):
    part = syn.synthetic_scenes([1], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)[0].parent
    diff = _upgraded(monkeypatch)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        syn.synthetic_scenes([1, 2], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)
    assert syn.version_differences(part) == [diff] and len(_warnings(caplog)) == 1


def test_a_complete_set_written_over_a_partial_one_is_a_fresh_generation_byte_for_byte(tmp_path):
    part = syn.synthetic_scenes([0, 2], N, SIZE, 0, BANDS, cache_dir=tmp_path / "part", progress=False)[0].parent
    assert syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "part", progress=False) == part
    fresh = syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "fresh", progress=False)
    assert _files(part) == _files(fresh)  # manifest.json included, partial.json gone


def test_a_partial_set_of_other_parameters_is_not_written_into(tmp_path):
    part = syn.synthetic_scenes([1], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)[0].parent
    syn.check_dataset_folder(part, syn.parameters(N, SIZE, 0, BANDS))  # its own
    with pytest.raises(InputError, match="holds scenes of a synthetic dataset with other parameters"):
        syn.generate_dataset(part, N, SIZE, 1, BANDS, progress=False)  # another seed: other scenes under its names
    assert sorted(_files(part)) == [syn.PARTIAL, "scene_0001.h5"]


def test_scenes_of_an_hsicam_before_the_record_get_none_claiming_todays_versions(tmp_path, monkeypatch):
    """A partial folder written before partial.json existed (its scenes, no record), joined by a new scene: a record
    written then would give this installation's versions to scenes made with unknown ones; none is written."""
    syn.synthetic_scenes([1], N, SIZE, 0, BANDS, cache_dir=tmp_path / "old", progress=False)
    folder = next((tmp_path / "old").rglob(syn.PARTIAL)).parent
    (folder / syn.PARTIAL).unlink()  # as an hsicam before the record left it
    _upgraded(monkeypatch)  # today's installation differs from the one that wrote scene 1
    syn.synthetic_scenes([1, 3], N, SIZE, 0, BANDS, cache_dir=tmp_path / "old", progress=False)
    assert sorted(p.name for p in folder.iterdir()) == [syn.SCENE_PATTERN.format(1), syn.SCENE_PATTERN.format(3)]
