"""The embedded synthetic dataset: determinism, values, bands, spectra checked against colour-science; a partial
set (the scenes an evaluation scores) and the versions it records (see its section)."""

from __future__ import annotations

import hashlib
import json
import logging
import subprocess
import sys

import numpy as np
import pytest

from hsicam.color import spectra_to_srgb
from hsicam.data import read_cube
from hsicam.data import synthetic as syn
from hsicam.config import load_config
from hsicam.errors import ConfigError, InputError
from hsicam.spectral import Bands

colour = pytest.importorskip("colour")
pytestmark = pytest.mark.filterwarnings("ignore:Aligning")

PAPER = Bands.paper()


@pytest.fixture(scope="module")
def lib():
    return syn.spectral_library(PAPER)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("syn") / "a"
    manifest = syn.generate_dataset(out, n=8, size=48, seed=3, progress=False)
    return out, manifest


def test_same_seed_identical_bytes(dataset, tmp_path):
    out, _ = dataset
    again = tmp_path / "b"
    syn.generate_dataset(again, n=8, size=48, seed=3, progress=False)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(p.name for p in again.iterdir())
    assert names == ["manifest.json"] + [f"scene_{i:04d}.h5" for i in range(8)]
    for name in names:
        assert (out / name).read_bytes() == (again / name).read_bytes(), name


def test_every_kind_at_the_smallest_size(lib):
    for i in range(len(syn.SCHEDULE)):
        cube, info = syn.generate_scene(i, 0, 16, lib)
        assert cube.shape == (31, 16, 16) and cube.max() == 1.0 and cube.min() >= 0.0


def test_other_seed_differs_and_scenes_do_not_depend_on_n(lib):
    a, _ = syn.generate_scene(1, 3, 48, lib)
    b, _ = syn.generate_scene(1, 4, 48, lib)
    assert not np.array_equal(a, b)
    c, _ = syn.generate_scene(1, 3, 48, lib)
    np.testing.assert_array_equal(a, c)


def test_values_bands_and_shapes(dataset):
    out, manifest = dataset
    kinds = set()
    for s in manifest["scenes"]:
        cube, bands, meta = read_cube(out / s["file"])
        assert cube.shape == (31, 48, 48) and cube.dtype == np.float32
        assert bands.matches(PAPER) and len(bands) == 31
        assert np.isfinite(cube).all() and cube.min() >= 0.0 and cube.max() == 1.0
        assert cube.std() > 0.01  # not flat
        assert meta["kind"] == s["kind"] and meta["seed"] == 3
        kinds.add(s["kind"])
        assert hashlib.sha256((out / s["file"]).read_bytes()).hexdigest() == s["sha256"]
    assert kinds == {"photo", "dead_leaves", "smooth", "texture", "edges", "emitters"}


def test_manifest(dataset):
    out, manifest = dataset
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == json.loads(json.dumps(manifest))
    assert on_disk["parameters"] == syn.parameters(8, 48, 3, PAPER)
    assert on_disk["parameters"]["holdout_sources"] == sorted(syn.DEFAULT_HOLDOUT)
    assert on_disk["parameters"]["split"] == "train"
    counts = on_disk["sources"]["counts"]
    assert counts["reflectances"]["cie-ces"] == 99 and counts["reflectances"]["colorchecker"] >= 70
    assert not set(syn.DEFAULT_HOLDOUT) & (set(counts["reflectances"]) | set(counts["illuminants"]))
    assert {"daylight", "fluorescent", "led"} <= set(on_disk["sources"]["illuminant_groups"])
    assert set(on_disk["sources"]["descriptions"]) <= set(syn.SOURCES)
    assert len(on_disk["statistics"]["mean_spectrum"]) == 31
    assert on_disk["statistics"]["max"] == 1.0 and on_disk["statistics"]["min"] >= 0.0


def test_cache_generates_once(tmp_path, monkeypatch):
    first = syn.synthetic_dataset(2, 32, 0, PAPER, cache_dir=tmp_path, progress=False)
    assert (first / "manifest.json").is_file() and first.is_relative_to(tmp_path)

    def boom(*a, **k):
        raise AssertionError("regenerated")

    monkeypatch.setattr(syn, "generate_dataset", boom)
    assert syn.synthetic_dataset(2, 32, 0, PAPER, cache_dir=tmp_path) == first
    monkeypatch.setenv("HSICAM_CACHE", str(tmp_path))
    assert syn.synthetic_dataset(2, 32, 0, PAPER) == first
    assert syn.synthetic_dataset(2, 32, 0, PAPER, cache_dir=None) == first
    assert syn.cache_key(2, 32, 0, PAPER) != syn.cache_key(2, 32, 1, PAPER)


def test_an_empty_cache_dir_is_refused_at_load_not_taken_as_the_current_folder():
    """``data.cache_dir=''`` resolved to the current folder: the dataset was written wherever the command ran."""
    for value in ("''", "'  '"):
        with pytest.raises(ConfigError, match=r"data\.cache_dir must be a folder or null .*empty path"):
            load_config("tiny", [f"data.cache_dir={value}"])
    assert load_config("tiny", ["data.cache_dir=null"]).data.cache_dir is None


def test_refuses_foreign_or_other_output(dataset, tmp_path):
    out, _ = dataset
    with pytest.raises(InputError, match="other parameters"):
        syn.generate_dataset(out, n=2, size=48, seed=3, progress=False)
    (tmp_path / "mine.h5").write_bytes(b"x")
    with pytest.raises(InputError, match="other cube files"):
        syn.generate_dataset(tmp_path, n=1, size=32, progress=False)
    with pytest.raises(InputError, match="outside the generator"):
        syn.generate_dataset(tmp_path / "z", n=1, size=32, bands=Bands.uniform(400, 1000, 20), progress=False)


def test_otsu_vectorised_matches_colour_science(lib):
    rng = np.random.default_rng(0)
    xyz = colour.sRGB_to_XYZ(rng.random((60, 3)))
    ours = lib.otsu.reflectance(xyz)
    ref = np.stack([colour.XYZ_to_sd(x, method="Otsu 2018").values for x in xyz])
    np.testing.assert_allclose(ours, ref, atol=1e-9)


def test_rgb_to_spectrum_to_rgb_roundtrip(lib):
    rng = np.random.default_rng(1)
    rgb = rng.uniform(0.15, 0.85, (200, 3))
    spectra = lib.otsu.reflectance(colour.sRGB_to_XYZ(rgb)) @ lib.otsu.to_bands.T
    back = spectra_to_srgb(spectra, PAPER)
    assert np.abs(back - rgb).mean() < 0.02 and np.abs(back - rgb).max() < 0.08


def test_colorchecker_render_agrees_with_colour_science(lib):
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    checker = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    for patch, sd in checker.items():
        k = lib.reflectance_names.index(f"ColorChecker N Ohta:{patch}")
        ours = spectra_to_srgb(lib.reflectances[k].astype(np.float64), PAPER)
        ref = np.clip(colour.XYZ_to_sRGB(colour.sd_to_XYZ(sd, cmfs, d65) / 100.0), 0, 1)
        np.testing.assert_allclose(ours, ref, atol=0.02, err_msg=patch)


def test_band_responses_have_the_requested_fwhm():
    bands = Bands.from_centers([450.0, 550.0, 650.0], [10.0, 20.0, 6.0])
    fine = np.arange(380.0, 721.0, 0.25)
    g = syn.band_matrix(bands, fine)
    np.testing.assert_allclose(g.sum(axis=1), 1.0)
    for row, c, f in zip(g, bands.centers_nm, bands.fwhm_nm):
        above = fine[row >= row.max() / 2]
        assert above.max() - above.min() == pytest.approx(f, abs=0.5)
        assert fine[row.argmax()] == pytest.approx(c)


def test_light_sources_sharp_where_fluorescent(lib):
    def sharpness(name: str) -> float:
        """Largest ratio of a band to the mean of its neighbours 20 nm away."""
        e = lib.illuminants[lib.illuminant_names.index(name)].astype(np.float64)
        return float(np.max(e[2:-2] / (0.5 * (e[:-4] + e[4:]))))

    assert sharpness("FL11") > 5.0  # triphosphor lamp: narrow emission lines
    assert sharpness("FL2") > 1.8  # mercury line at 436 nm on a broad phosphor
    assert sharpness("D65") < 1.2 and sharpness("A") < 1.05  # daylight and tungsten are smooth
    assert lib.illuminants.min() >= 0 and np.allclose(lib.illuminants.mean(axis=1), 1.0, atol=1e-5)
    refl = lib.reflectances  # measured reflectances are smooth: small second differences
    assert np.median(np.abs(np.diff(refl, 2, axis=1)).max(axis=1)) < 0.05


def test_training_on_cached_data_does_not_import_colour(dataset):
    out, _ = dataset
    code = (
        "import sys\n"
        "from hsicam.data import PatchDataset, SceneDataset, list_scenes\n"
        "from hsicam.color import cube_to_srgb\n"
        "from hsicam.spectral import Bands\n"
        f"ds = PatchDataset(SceneDataset(list_scenes({str(out)!r}), Bands.paper()), 16, 8)\n"
        "cube_to_srgb(ds[0], Bands.paper())\n"
        "assert 'colour' not in sys.modules, 'colour-science was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_unseen_layout_scenes(lib):
    """Scenes of scikit-image images that no generated scene uses (UNSEEN_LAYOUTS, all bundled offline; not
    the photos, textures, or the text scans and patterns of the edges scenes):
    deterministic, (C, size, size) float32 in [0, 1] with maximum 1, their layout recorded, drawn
    from their own stream (not the generator's scene of the same index), lit as generated scenes."""
    pattern_kinds = ("siemens_star", "bars", "zone_plate", "slanted_edge", "checkerboard", "text", "thin_lines", "glyphs")
    assert not set(syn.UNSEEN_LAYOUTS) & set(syn.PHOTOS + syn.TEXTURES + syn.PATTERN_IMAGES + pattern_kinds)
    assert len(set(syn.UNSEEN_LAYOUTS)) == 7
    seen = set()
    for i in range(len(syn.UNSEEN_LAYOUTS)):
        cube, info = syn.unseen_layout_scene(i, 0, 40, lib)
        assert cube.dtype == np.float32 and cube.shape == (len(PAPER), 40, 40)
        assert cube.min() >= 0 and cube.max() == pytest.approx(1.0)
        assert info["kind"] == "unseen_layout" and info["layout"] == syn.UNSEEN_LAYOUTS[i]
        assert info["materials"] in (2, 3) and info["lighting"] in ("single", "blend", "sun_sky")
        seen.add(info["layout"])
        again, _ = syn.unseen_layout_scene(i, 0, 40, lib)
        np.testing.assert_array_equal(cube, again)
        other, _ = syn.generate_scene(i, 0, 40, lib)
        assert not np.array_equal(cube, other)
    assert seen == set(syn.UNSEEN_LAYOUTS)
    a, _ = syn.unseen_layout_scene(0, 0, 40, lib)
    b, _ = syn.unseen_layout_scene(0, 1, 40, lib)
    assert not np.array_equal(a, b)  # another seed, another crop and palette


def test_a_dataset_larger_than_the_free_disk_is_refused_before_any_scene(tmp_path, monkeypatch):
    """``data.synthetic_n=1000000000`` used to write scene after scene until the disk filled (115 TB
    asked); now the room the scenes still to write need (float32 pixels and a header each) is
    compared with the disk's free space first, nothing is made, and the message says what to change."""
    import shutil
    from collections import namedtuple

    from hsicam.data.synthetic import SCENE_FILE_OVERHEAD_BYTES, synthetic_dataset

    usage = namedtuple("usage", "total used free")
    bands = Bands.uniform(420, 720, 50)
    per_scene = 4 * 32 * 32 * len(bands) + SCENE_FILE_OVERHEAD_BYTES
    free = 1000 * per_scene  # room for 1000 scenes less the margin (64 MiB at least)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 * free, 9 * free, free))
    cache = tmp_path / "cache"
    with pytest.raises(InputError, match=r"the synthetic dataset of 2,000 scenes of 32×32 px and 7 bands needs, in .*, "
                                         r"about .*, and 64 MiB more is kept free beyond it \(.* in all\), but that "
                                         r"disk has .* free; lower data.synthetic_n"):
        synthetic_dataset(2000, 32, 0, bands, cache_dir=cache, progress=False)
    assert not cache.exists()
    # what fits is generated (the margin: a tenth of the need, at least 64 MiB)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**12, 0, 3 * per_scene + (1 << 26)))
    out = synthetic_dataset(3, 32, 0, bands, cache_dir=cache, progress=False)
    assert len(list(out.glob("scene_*.h5"))) == 3


def _damage(folder, name, how):
    """Truncate ``name`` (an interrupted copy) or zero a block of its pixels in place (still valid HDF5)."""
    import h5py

    path = folder / name
    if how == "truncated":
        with open(path, "r+b") as f:
            f.truncate(path.stat().st_size // 2)
        return
    with h5py.File(path, "r") as f:
        offset, shape = f["cube"].id.get_offset(), f["cube"].shape
    block = np.memmap(path, dtype="<f4", mode="r+", offset=offset, shape=shape)
    block[:, 4:12, 4:12] = 0.0
    block.flush()


@pytest.mark.parametrize("how", ["truncated", "altered"])
def test_data_synth_finds_a_damaged_cached_scene_and_generates_the_set_again(tmp_path, monkeypatch, capsys, how):
    """The cache trusted that its files exist: a truncated scene stopped training with no word of the cache, and one
    altered in place trained silently, while `data synth` said "wrote" and wrote nothing. It now checks every scene
    against the manifest's checksum and generates a damaged set again (the same bytes), and says an intact set is."""
    from hsicam.cli import main

    monkeypatch.setenv("HSICAM_CACHE", str(tmp_path))
    args = ["data", "synth", "--config", "tiny", "--n", "3", "--size", "32", "--no-progress"]
    assert main(args) == 0
    (folder,) = (tmp_path / "synthetic").iterdir()
    good = {p.name: p.read_bytes() for p in folder.glob("scene_*.h5")}
    assert syn.damaged_scenes(folder) == []
    capsys.readouterr()
    assert main(args) == 0
    assert "already holds this dataset" in capsys.readouterr().out
    _damage(folder, "scene_0001.h5", how)
    assert syn.damaged_scenes(folder) == ["scene_0001.h5"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "1 of its 3 scenes missing or not the bytes its manifest records (scene_0001.h5)" in out
    assert {p.name: p.read_bytes() for p in folder.glob("scene_*.h5")} == good
    assert syn.damaged_scenes(folder) == []


def test_training_on_a_truncated_cached_scene_says_how_to_repair_the_cache(tmp_path, monkeypatch):
    from hsicam.data.pipeline import build_datasets

    monkeypatch.setenv("HSICAM_CACHE", str(tmp_path))
    cfg = load_config("tiny", ["data.synthetic_n=3", "data.synthetic_size=32", "data.patch_px=16",
                               "data.preload=true"])
    bands = cfg.bands.to_bands()
    folder = syn.synthetic_dataset(3, 32, cfg.data.synthetic_seed, bands, progress=False,
                                   holdout_sources=cfg.data.holdout_sources)
    _damage(folder, "scene_0000.h5", "truncated")
    with pytest.raises(InputError, match=r"scene_0000\.h5: .*synthetic dataset cache .*`hsicam data synth`"):
        build_datasets(cfg.data, bands, margin_px=4)


def test_a_cached_set_of_other_package_versions_is_reused_with_a_warning(tmp_path, caplog):
    """The scenes depend on colour-science (spectra, Otsu basis) and scikit-image (photos, textures), which the
    cache key leaves out: a set made with other versions is reused, and now says so once."""
    import logging

    folder = syn.synthetic_dataset(2, 32, 0, PAPER, cache_dir=tmp_path, progress=False)
    assert syn.version_differences(folder) == []
    man = json.loads((folder / "manifest.json").read_text())
    man["software"]["colour-science"] = "0.3.16"
    (folder / "manifest.json").write_text(json.dumps(man))
    assert syn.version_differences(folder) == [f"colour-science 0.3.16 → {syn._versions()['colour-science']}"]
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        assert syn.synthetic_dataset(2, 32, 0, PAPER, cache_dir=tmp_path) == folder
        assert syn.synthetic_dataset(2, 32, 0, PAPER, cache_dir=tmp_path) == folder
    said = [r.getMessage() for r in caplog.records if "other versions" in r.getMessage()]
    assert len(said) == 1 and "colour-science 0.3.16" in said[0]


# --------------------------------------------------------------------------------------------
# A partial synthetic set
# --------------------------------------------------------------------------------------------
# A partial synthetic set: the scenes an evaluation scores (``hsicam evaluate`` without --data:
# :func:`hsicam.data.pipeline.validation_split` → :func:`hsicam.data.synthetic.synthetic_scenes`), written into the set's
# cache folder without its manifest. It recorded nothing of the package versions its scenes were made with, so after a
# colour-science or scikit-image upgrade they were reused without the warning a complete set gives. It now records what
# the complete set's manifest does of its parameters and versions (``partial.json``) and warns the same way; a complete
# generation over it leaves the very files of a fresh one. References: the manifest of a complete set of the same
# parameters, the warning a complete set gives, and the files of a fresh generation read back byte for byte.
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


def _interrupt_the_write_of_scene(index, monkeypatch):
    """A KeyboardInterrupt where scene ``index`` would be written (a Ctrl-C mid-generation); returns the real writer."""
    write = syn._write_scene

    def interrupted(out, i, *args, **kwargs):
        if i == index:
            raise KeyboardInterrupt
        return write(out, i, *args, **kwargs)

    monkeypatch.setattr(syn, "_write_scene", interrupted)
    return write


def test_a_partial_set_cut_short_after_its_first_scene_keeps_its_record(tmp_path, monkeypatch, caplog):
    """partial.json was written after the last scene: `hsicam evaluate` interrupted after scene 0 of [0, 2] left
    scene_0000.h5 alone, and the rerun (the folder no longer empty) wrote none, so after an upgrade the scene was
    reused without the warning. The record now comes with the first scene: the versions that wrote it."""
    real, write = syn._versions(), _interrupt_the_write_of_scene(2, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        syn.synthetic_scenes([0, 2], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)
    monkeypatch.setattr(syn, "_write_scene", write)
    part = next(tmp_path.rglob(syn.SCENE_PATTERN.format(0))).parent
    assert sorted(_files(part)) == [syn.PARTIAL, "scene_0000.h5"]
    assert json.loads((part / syn.PARTIAL).read_text())["software"] == real
    diff = _upgraded(monkeypatch)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        syn.synthetic_scenes([0, 2], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)
    said = _warnings(caplog)
    assert len(said) == 1 and diff in said[0] and str(part) in said[0]


def test_a_whole_set_generation_cut_short_after_its_first_scene_keeps_a_record(tmp_path, monkeypatch, caplog):
    """The generation of a whole set (`hsicam data synth`, the dataset cache of a training) killed after its first
    scene left scene_0000.h5 without any record of its versions (partial.json came from partial sets only): after an
    upgrade it was reused with "record no versions" only. Now the same record as a partial set's, with the first
    scene (reference: the manifest of the completed set); the completed set is a fresh one, byte for byte."""
    real, write = syn._versions(), _interrupt_the_write_of_scene(1, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "cut", progress=False)
    monkeypatch.setattr(syn, "_write_scene", write)
    cut = next((tmp_path / "cut").rglob(syn.SCENE_PATTERN.format(0))).parent
    assert sorted(_files(cut)) == [syn.PARTIAL, "scene_0000.h5"]
    record = json.loads((cut / syn.PARTIAL).read_text())
    assert record["software"] == real and syn.partial_set_size(cut) == (1, N)
    whole = syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "whole", progress=False)
    manifest = json.loads((whole / syn.MANIFEST).read_text())
    assert {k: record[k] for k in ("parameters", "key", "software")} == \
        {k: manifest[k] for k in ("parameters", "key", "software")}
    diff = _upgraded(monkeypatch)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        syn.synthetic_scenes([0], N, SIZE, 0, BANDS, cache_dir=tmp_path / "cut", progress=False)
    said = _warnings(caplog)
    assert len(said) == 1 and diff in said[0] and str(cut) in said[0]
    monkeypatch.setattr(syn, "_versions", lambda: real)
    syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "cut", progress=False)
    assert _files(cut) == _files(whole)  # manifest.json included, partial.json gone


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


def test_scenes_of_an_hsicam_before_the_record_are_reused_with_a_warning_that_their_versions_are_unknown(
        tmp_path, caplog):
    """Such a folder's scenes were reused by `hsicam evaluate` without a word (version_differences has nothing to
    compare): they may come from other package versions. One line says so (once a process) and how to make them
    anew; a partial set with its record, and a complete set, say nothing."""
    folder = syn.synthetic_scenes([1], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)[0].parent
    syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "whole", progress=False)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        syn.synthetic_scenes([1], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)
        syn.synthetic_scenes([1], N, SIZE, 0, BANDS, cache_dir=tmp_path / "whole", progress=False)
    assert not [r for r in caplog.records if "versions of the packages" in r.getMessage()]
    (folder / syn.PARTIAL).unlink()  # as an hsicam before the record left it
    with caplog.at_level(logging.WARNING, logger="hsicam.data.synthetic"):
        for _ in range(2):
            syn.synthetic_scenes([1, 3], N, SIZE, 0, BANDS, cache_dir=tmp_path, progress=False)
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and str(folder) in r.getMessage()]
    assert said == [f"synthetic scenes in {folder} record no versions of the packages they come from (written by an "
                    "hsicam before session 61, or by a generation cut short): they may differ from the scenes this "
                    "installation generates; delete the folder to generate them anew"]
    assert not (folder / syn.PARTIAL).exists()  # still none claiming today's versions


@pytest.mark.parametrize("record", [True, False], ids=["partial.json", "before-the-record"])
def test_a_partial_set_given_as_data_is_refused_not_taken_for_the_whole_set(tmp_path, record):
    """`hsicam evaluate --data FOLDER` (or data.root) of a partial set's cache folder scored its few scenes as if
    they were the set, without a word (2 of 4 here; 16 of the standard camera's 320), also for a folder an hsicam
    before partial.json left. Now one line says how many of how many scenes it holds; the same scenes copied into a
    folder of one's own, or the whole set, are listed as before."""
    from cli_helpers import error_line, run_cli_in_process

    from hsicam.data.datasets import list_scenes

    part = syn.synthetic_scenes([1, 3], N, SIZE, 0, BANDS, cache_dir=tmp_path / "c", progress=False)[0].parent
    if not record:
        (part / syn.PARTIAL).unlink()  # as an hsicam before the record left it
    held = sorted(p.name for p in part.glob("scene_*.h5"))
    line = error_line(run_cli_in_process("evaluate", "--config", "tiny", "--method", "dd-cassi-gaptv", "--data",
                                         str(part), "--out", str(tmp_path / "ev")))
    assert line == (f"hsicam: error: {part}: holds {len(held)} of the {N} scenes of a synthetic set (a partial set: "
                    "the validation scenes that hsicam evaluate generates, or a generation cut short), not a whole "
                    "dataset; `hsicam data synth` with the config that made it completes the set, or give a folder of "
                    "the scenes you mean")
    assert not (tmp_path / "ev").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    for name in held:
        (mine / name).write_bytes((part / name).read_bytes())
    assert [p.name for p in list_scenes(mine)] == held
    whole = syn.synthetic_dataset(N, SIZE, 0, BANDS, cache_dir=tmp_path / "c", progress=False)
    assert whole == part and [p.name for p in list_scenes(whole)] == [syn.SCENE_PATTERN.format(i) for i in range(N)]
