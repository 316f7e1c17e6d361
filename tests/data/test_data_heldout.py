"""Spectral diversity and the held-out-sources protocol of the synthetic generator (issue #14).

The protocol is checked by the spectra themselves: the training library holds no spectrum equal to
a held-out one, and no pixel of a training scene has the spectral shape of a held-out reflectance
under that scene's light — while held-out scenes do (the check has the power to see a leak).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from hsicam.data import read_cube
from hsicam.data import synthetic as syn
from hsicam.data.spectral_sources import SAME_SPECTRUM_ATOL
from hsicam.errors import InputError
from hsicam.spectral import Bands

pytest.importorskip("colour")
pytestmark = pytest.mark.filterwarnings("ignore:Aligning")

PAPER = Bands.paper()
HOLDOUT = ("cie-tcs", "nist-philips", "rawtoaces")


@pytest.fixture(scope="module")
def full():
    return syn.spectral_library(PAPER)


@pytest.fixture(scope="module")
def train():
    return syn.spectral_library(PAPER, HOLDOUT, "train")


@pytest.fixture(scope="module")
def heldout():
    return syn.spectral_library(PAPER, HOLDOUT, "heldout")


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-30)


def _sam_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Spectral angle (degrees) between every row of a and every row of b."""
    return np.degrees(np.arccos(np.clip(_unit(a) @ _unit(b).T, -1.0, 1.0)))


def test_every_source_is_present_with_its_count(full):
    counts = full.counts()
    assert counts["reflectances"] == {"rawtoaces": 190, "colorchecker": 72, "cie-tcs": 29, "nist-cqs": 30,
                                      "cie-ces": 99, "rgb-basis": 3}
    ill = counts["illuminants"]
    assert ill["cie-fl"] == 27 and ill["cie-led"] == 9 and ill["nist-led"] == 15 and ill["nist-philips"] == 22
    assert ill["cie-daylight"] >= 20 and ill["blackbody"] == 13 and ill["rit"] == 8
    assert counts["emitters"]["led-model"] == 87 and counts["emitters"]["displays"] == 6
    assert counts["emitters"]["nist-traditional"] == 1  # low-pressure sodium: a line, used as an emitter
    used = set(full.reflectance_sources) | set(full.illuminant_sources) | set(full.emitter_sources) | {"otsu2018"}
    assert used == set(syn.SOURCES) - {"pmc"}  # PMC stops at 700 nm: outside the paper's bands
    assert "pmc" in full.sources["not_used_out_of_range"]


def test_physical_ranges(full, train):
    assert full.reflectances.min() >= 0.0 and full.reflectances.max() <= 1.0
    assert full.illuminants.min() >= 0.0 and np.allclose(full.illuminants.mean(axis=1), 1.0, atol=1e-5)
    assert full.emitters.min() >= 0.0 and np.allclose(full.emitters.max(axis=1), 1.0)
    rng = np.random.default_rng(0)
    spectra, kinds = syn.palette(rng, train, 4000)
    assert spectra.dtype == np.float32 and spectra.min() >= 0.0 and spectra.max() <= 1.0
    assert set(np.unique(kinds)) == set(range(len(syn.PALETTE_KINDS)))  # every kind is drawn
    # derived spectra stay smooth like the measured ones (no clipping kinks into flat white)
    assert np.median(np.abs(np.diff(spectra, 2, axis=1)).max(axis=1)) < 0.05
    # near-monochromatic emitters: most of their energy within a few bands
    led = full.emitters[[i for i, s in enumerate(full.emitter_sources) if s == "led-model"]]
    top3 = np.sort(led, axis=1)[:, -3:].sum(axis=1) / led.sum(axis=1)
    assert np.median(top3) > 0.6


def test_unknown_source_is_one_clear_error():
    with pytest.raises(InputError) as exc:
        syn.parse_holdout("rawtoaces,nope")
    msg = str(exc.value)
    assert "nope" in msg and "rawtoaces" in msg and "cie-tcs" in msg and "\n" not in msg
    assert syn.parse_holdout(" rawtoaces ,cie-tcs") == ("cie-tcs", "rawtoaces")
    assert syn.parse_holdout("none") == () == syn.parse_holdout(None) == syn.parse_holdout([])
    with pytest.raises(InputError, match="at least one held-out source"):
        syn.spectral_library(PAPER, (), "heldout")
    with pytest.raises(InputError, match="no light source"):
        syn.spectral_library(PAPER, [s for s, v in syn.SOURCES.items() if v.role == "illuminant"], "train")


def test_library_split_by_values(full, train, heldout):
    for role in ("reflectances", "illuminants", "emitters"):
        tr = getattr(train, role)
        arr = getattr(full, role)
        srcs = {"reflectances": full.reflectance_sources, "illuminants": full.illuminant_sources,
                "emitters": full.emitter_sources}[role]
        held = arr[[i for i, s in enumerate(srcs) if s in HOLDOUT]]
        if held.shape[0] == 0 or tr.shape[0] == 0:
            continue
        dist = np.abs(tr[:, None, :].astype(np.float64) - held[None]).max(axis=2)
        assert dist.min() > SAME_SPECTRUM_ATOL, role  # no training spectrum equals a held-out one
    assert not set(train.reflectance_sources) & set(HOLDOUT)
    assert not set(train.illuminant_sources) & set(HOLDOUT)
    assert set(heldout.reflectance_sources) == {"rawtoaces", "cie-tcs"}
    assert set(heldout.illuminant_sources) == {"nist-philips"}
    assert heldout.emitters.shape[0] == 0 and heldout.basis is None and heldout.otsu is None
    assert "Incandescent" in train.removed  # NIST's incandescent lamp is the same measurement as 60 A/W


def _pixel_min_sam(cube: np.ndarray, lib, light_names: list[str], held: np.ndarray) -> float:
    """Smallest angle between a pixel spectrum and (held-out reflectance × one of the scene's lights)."""
    pix = cube.reshape(cube.shape[0], -1).T
    pix = pix[pix.max(axis=1) > 1e-4]
    best = 180.0
    for name in light_names:
        e = lib.illuminants[lib.illuminant_names.index(name)]
        best = min(best, float(_sam_deg(pix, held * e).min()))
    return best


def test_training_pixels_are_not_held_out_spectra(full, train, heldout):
    refl = heldout.reflectances.astype(np.float64)
    flat = _sam_deg(refl, np.ones((1, refl.shape[1])))[:, 0] < 0.1
    held = refl[~flat]  # a spectrally flat grey (rawtoaces patch4) is every grey: excluded
    tiny = 0.02  # degrees; distinct measured spectra are >= 0.07 deg apart
    for i in range(len(syn.SCHEDULE)):
        cube, info = syn.generate_scene(i, 5, 40, train)
        assert _pixel_min_sam(cube, train, info["illuminants"], held) > tiny, info
    # the same check sees held-out spectra in held-out scenes (flat leaves and edges are pure)
    seen = 0
    for i in range(len(syn.SCHEDULE)):
        cube, info = syn.generate_scene(i, 5, 40, heldout)
        assert set(info["illuminants"]) <= set(heldout.illuminant_names)
        seen += _pixel_min_sam(cube, heldout, info["illuminants"], held) < tiny
    assert seen >= 3


def test_deterministic_per_seed_and_split(train, heldout):
    for lib in (train, heldout):
        a, ia = syn.generate_scene(6, 2, 32, lib)
        b, ib = syn.generate_scene(6, 2, 32, lib)
        np.testing.assert_array_equal(a, b)
        assert ia == ib
        c, _ = syn.generate_scene(6, 3, 32, lib)
        assert not np.array_equal(a, c)
    assert not np.array_equal(syn.generate_scene(0, 2, 32, train)[0], syn.generate_scene(0, 2, 32, heldout)[0])


def test_values_and_dynamic_range(train):
    means = []
    for i in range(2 * len(syn.SCHEDULE)):
        cube, info = syn.generate_scene(i, 7, 32, train)
        assert np.isfinite(cube).all() and cube.min() >= 0.0 and cube.max() == 1.0
        means.append(float(cube.mean()))
    assert min(means) < 0.03 and max(means) > 0.1  # dark scenes next to bright ones


def test_no_scene_kind_survives_a_9x9_box(train):
    """Every kind has detail that a 9×9 box (the CFA period) destroys: >= 10 % relative loss."""
    for i in range(len(syn.SCHEDULE)):
        cube, info = syn.generate_scene(i, 11, 64, train)
        smooth = uniform_filter(cube, size=(1, 9, 9), mode="reflect")
        loss = np.linalg.norm(cube - smooth) / np.linalg.norm(cube)
        assert loss > 0.1, (info["kind"], loss)


def test_heldout_dataset_is_cached_apart(tmp_path, monkeypatch):
    tr = syn.synthetic_dataset(2, 24, 1, PAPER, cache_dir=tmp_path, progress=False, holdout_sources=HOLDOUT)
    ho = syn.heldout_dataset(2, 24, 1, PAPER, cache_dir=tmp_path, progress=False, holdout_sources=HOLDOUT)
    assert ho.parent == tr.parent == tmp_path / "synthetic" and ho.name.startswith("heldout-n2-s24-seed1-")
    assert ho == syn.dataset_dir(2, 24, 1, PAPER, cache_dir=tmp_path, holdout_sources=HOLDOUT, split="heldout")
    man = json.loads((ho / "manifest.json").read_text())
    assert man["parameters"]["split"] == "heldout" and man["parameters"]["holdout_sources"] == list(HOLDOUT)
    assert man["sources"]["held_out_roles"] == {"reflectances": True, "illuminants": True, "emitters": False}
    assert set(man["sources"]["counts"]["reflectances"]) == {"rawtoaces", "cie-tcs"}
    _, _, meta = read_cube(ho / "scene_0000.h5")
    assert meta["split"] == "heldout"

    def boom(*a, **k):
        raise AssertionError("regenerated")

    monkeypatch.setattr(syn, "generate_dataset", boom)
    assert syn.heldout_dataset(2, 24, 1, PAPER, cache_dir=tmp_path, holdout_sources="rawtoaces,nist-philips,cie-tcs") == ho
    # the default dataset (presets) holds out DEFAULT_HOLDOUT; holding out nothing is another set
    assert syn.cache_key(2, 24, 1, PAPER) != syn.cache_key(2, 24, 1, PAPER, holdout_sources=())
    assert syn.parameters(2, 24, 1, PAPER)["holdout_sources"] == sorted(syn.DEFAULT_HOLDOUT)


TINY = Bands.uniform(420.0, 720.0, 50.0)  # the tiny preset's grid: 50 nm bands need spectra over 356-784 nm


def test_held_out_sources_without_a_spectrum_on_the_grid_are_refused_not_replaced_by_training_spectra():
    """On the tiny grid nist-philips and rawtoaces give no spectrum (their data start at 380 nm), and every role of the
    held-out library fell back to the training spectra: scenes of training spectra scored as "held-out sources"."""
    from hsicam.data.spectral_sources import NoHeldOutSpectra

    with pytest.raises(NoHeldOutSpectra, match=r"nist-philips, rawtoaces give no spectrum on bands 420-720 nm, whose "
                                                r"widths need spectra spanning 356-784 nm \(nist-philips: 22 spectra"):
        syn.spectral_library(TINY, syn.DEFAULT_HOLDOUT, "heldout")
    held = syn.spectral_library(TINY, "nist-cqs", "heldout")  # a source that covers the grid: a true held-out set
    train = syn.spectral_library(TINY, "nist-cqs", "train")
    assert set(held.reflectance_sources) == {"nist-cqs"} and "nist-cqs" not in set(train.reflectance_sources)
    assert held.sources["held_out_roles"]["reflectances"]


def test_no_held_out_scenes_rather_than_false_ones(tmp_path, caplog):
    """`evaluate`/`demo` score a held-out-sources set beside the validation scenes when the config has one: on a grid
    its sources do not cover there is none (a warning says why), also when an older hsicam cached a false one."""
    import logging

    from hsicam.config import load_config
    from hsicam.data.pipeline import heldout_root

    cfg = load_config("tiny", [f"data.cache_dir={tmp_path}", "data.holdout_sources=nist-philips,rawtoaces"]).data
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert heldout_root(cfg, TINY, n=1, progress=False) is None
    assert "no held-out-sources scenes: the held-out sources nist-philips, rawtoaces give no spectrum" in caplog.text
    fake = syn.dataset_dir(1, cfg.synthetic_size, cfg.synthetic_seed, TINY, cache_dir=tmp_path,
                           holdout_sources=syn.DEFAULT_HOLDOUT, split="heldout")
    good = load_config("tiny", [f"data.cache_dir={tmp_path}"]).data  # nist-cqs: a true held-out set
    root = heldout_root(good, TINY, n=1, progress=False)
    fake.parent.mkdir(parents=True, exist_ok=True)
    import shutil

    shutil.copytree(root, fake)  # as an older hsicam left it: its manifest says no role was held out
    man = json.loads((fake / "manifest.json").read_text())
    man["parameters"] = syn.parameters(1, cfg.synthetic_size, cfg.synthetic_seed, TINY,
                                       holdout_sources=syn.DEFAULT_HOLDOUT, split="heldout")
    man["sources"]["held_out_roles"] = {"reflectances": False, "illuminants": False, "emitters": False}
    (fake / "manifest.json").write_text(json.dumps(man))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert heldout_root(cfg, TINY, n=1, progress=False) is None
    assert "was made of the training spectra" in caplog.text


def test_data_synth_holds_out_the_configs_sources(tmp_path):
    """`data synth --config C` took --n, --size and --seed from the config but held out the default sources."""
    from cli_helpers import run_cli_in_process

    res = run_cli_in_process("data", "synth", "--config", "tiny", "--set", "data.holdout_sources=cie-tcs", "--n", "1",
                             "--out", str(tmp_path / "d"), "--no-progress")
    assert res.returncode == 0, res.stderr
    man = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert man["parameters"]["holdout_sources"] == ["cie-tcs"]
