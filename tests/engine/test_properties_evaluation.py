"""Property-based tests (hypothesis) of the evaluation's scoring, the reconstruction methods and the spectral
sources, on small random scenes of the tiny camera. Each invariant is checked against an independent reference:
the scene cropped by hand by the camera's kernel margin, numpy means of the per-scene rows, the sensor images a
method is handed (noise fields compared directly), the demosaic references' closed form on a constant scene (the
CFA-weighted mean of the sensor over one period, the sensor itself from the PSF energies and the CFA), the grey
reference's x̂ = g · s̄ / mean(s̄), an SVD of the library done again in numpy, colour-science's own
``XYZ_to_sd_Otsu2018``, the source ids of every spectrum of a split library, and data.json read back as JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cli_helpers import run_cli_in_process
from hsicam.config import dump_yaml, load_config
from hsicam.engine.evaluate import TestNoise as Noise, config_hash, evaluate_method, grey_reference, summarize
from hsicam.engine.methods import build_method, demosaic_reference, learned_method
from hsicam.errors import InputError
from hsicam.models import CameraSystem

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PROPS = settings(max_examples=12, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def system():
    return CameraSystem.from_config(load_config("tiny", ["baselines.gaptv.iterations=2"])).eval()


def _recording(method):
    """``method`` whose reconstruct records the sensor images it is handed."""
    seen = []
    f = method.reconstruct
    method.reconstruct = lambda y: (seen.append(y.clone()), f(y))[1]
    return method, seen


@PROPS
@given(sizes=st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)), min_size=1, max_size=3),
       seeds=st.lists(st.integers(0, 2**31), min_size=1, max_size=2, unique=True), data=st.data())
def test_scored_area_and_means(system, sizes, seeds, data):
    """Each scene's truth is the scene less margin // 2 px a side (cut by hand), the estimate covers it, each row is
    the mean over its seeds and the summary's mean the mean of the rows; one scene, or scenes of different sizes."""
    cam = system.camera
    n = len(cam.bands)
    m = cam.margin
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 1000)))
    scenes = [torch.rand(n, m + 11 + dh, m + 11 + dw, generator=g) for dh, dw in sizes]
    names = [f"s{i}" for i in range(len(scenes))]
    res = evaluate_method(demosaic_reference(system, "box"), scenes, names, Noise(sensor_sigma=0.02, seeds=tuple(seeds)))
    r = m // 2
    for scene, got in zip(scenes, res):
        cut = scene.numpy()[:, r : scene.shape[1] - r, r : scene.shape[2] - r]
        assert cut.shape[1:] == (scene.shape[1] - m, scene.shape[2] - m)
        np.testing.assert_array_equal(got.truth, cut)
        assert got.estimate.shape == cut.shape
        assert [p["seed"] for p in got.metrics_per_seed] == list(seeds)
        for k, v in got.metrics.items():
            assert v == pytest.approx(np.mean([p[k] for p in got.metrics_per_seed]), rel=1e-12)
    summary = summarize(res)
    for k, v in summary["mean"].items():
        assert v == pytest.approx(np.mean([row[k] for row in summary["scenes"]]), rel=1e-12)


def test_noise_fields_per_scene_and_shared_by_methods(system):
    """Two identical scenes get two noise fields, two seeds two more, and another method scored on the same scene
    and seed is handed the same sensor image; the camera's own noise levels come back after."""
    n = len(system.camera.bands)
    scene = torch.rand(n, system.camera.margin + 12, system.camera.margin + 12, generator=torch.Generator().manual_seed(3))
    before = system.camera.noise_levels()
    box, seen = _recording(demosaic_reference(system, "box"))
    evaluate_method(box, [scene, scene], ["a", "b"], Noise(sensor_sigma=0.05, seeds=(0, 1)))
    a0, a1, b0, b1 = seen
    assert (a0 - b0).abs().max() > 0.05 and (a0 - a1).abs().max() > 0.05 and (b0 - b1).abs().max() > 0.05
    other, seen2 = _recording(learned_method("doe-learned", system, "run"))
    evaluate_method(other, [scene], ["a"], Noise(sensor_sigma=0.05, seeds=(0,)))
    torch.testing.assert_close(seen2[0], a0, rtol=0, atol=0)
    assert system.camera.noise_levels() == before


@PROPS
@given(extra=st.tuples(st.integers(0, 5), st.integers(0, 9)))
def test_cassi_baseline_scored_on_the_doe_cameras_pixels(system, extra):
    """A DD-CASSI method of a 'valid' DOE config scores the same pixels as the DOE camera; a scene 1 px too small
    for either is one InputError naming the minimum size."""
    cfg = load_config("tiny", ["baselines.gaptv.iterations=2"])
    gap = build_method("dd-cassi-gaptv", cfg)
    doe = learned_method("doe-learned", system, "run")
    m = system.camera.margin
    assert gap.border_px == m // 2
    scene = torch.rand(len(system.camera.bands), m + 11 + extra[0], m + 11 + extra[1])
    a = evaluate_method(doe, [scene], ["s"])[0]
    b = evaluate_method(gap, [scene], ["s"])[0]
    np.testing.assert_array_equal(a.truth, b.truth)
    assert b.estimate.shape == a.truth.shape
    small = scene[:, : m + 10]
    for method in (doe, gap):
        with pytest.raises(InputError, match=f"scenes of at least {m + 11} px on each side"):
            evaluate_method(method, [small], ["s"])


@PROPS
@given(spectrum=st.lists(st.floats(0.05, 1.0), min_size=7, max_size=7), kernel=st.sampled_from(["box", "tent"]))
def test_demosaic_references_closed_form_on_a_constant_scene(system, spectrum, kernel):
    """A constant scene s_c images to g = Σ_c κ_c E_c s_c (E_c: band c's PSF energy on the kernel), and the box (and
    tent, 2m - 1 px: equal weight per CFA phase) demosaic away from the border is Σ κ_c g / Σ κ_c over one period."""
    cam = system.camera
    n, p = len(cam.bands), cam.code_period
    s = torch.tensor(spectrum, dtype=torch.float64)
    scene = s.view(1, n, 1, 1).expand(1, n, cam.margin + 4 * p, cam.margin + 4 * p + 1).float().contiguous()
    with torch.no_grad():
        energy = cam.psf().double().sum(dim=(-2, -1)).reshape(-1)
        y = cam(scene)
        h, w = y.shape[-2:]
        kappa = cam.sensor_code(h, w).double()
        sensor = (kappa * (s * energy).view(n, 1, 1)).sum(0)
        torch.testing.assert_close(y[0, 0].double(), sensor, rtol=0, atol=1e-6)
        k1 = kappa[:, :p, :p]
        expected = (k1 * sensor[:p, :p]).sum(dim=(1, 2)) / k1.sum(dim=(1, 2))
        est = demosaic_reference(system, kernel).reconstruct(y)[0].double()
    inner = est[:, p : h - p, p : w - p]
    torch.testing.assert_close(inner, expected.view(n, 1, 1).expand_as(inner), rtol=0, atol=1e-6)


def test_grey_reference_closed_form(system):
    """x̂_c = g · s̄_c / mean(s̄), s̄ the mean spectrum over all pixels of the training scenes (sizes differ)."""
    n = len(system.camera.bands)
    g = torch.Generator().manual_seed(5)
    train = [torch.rand(n, 9, 13, generator=g), torch.rand(n, 20, 4, generator=g) * 0.5]
    mean = np.concatenate([t.numpy().reshape(n, -1) for t in train], axis=1).astype(np.float64).mean(axis=1)
    y = torch.rand(2, 1, 6, 7, generator=g)
    est = grey_reference(system, train).reconstruct(y)
    ref = y.numpy() * (mean / mean.mean()).reshape(1, n, 1, 1)
    np.testing.assert_allclose(est.numpy(), ref, rtol=1e-5)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, cache_env):
    d = tmp_path_factory.mktemp("run") / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(d), "--set", "train.epochs=1",
                             "--set", "data.synthetic_n=3", "--set", "data.synthetic_size=40")
    assert res.returncode == 0, res.stderr
    return d


@pytest.mark.parametrize("name", ["doe-learned", "doe-box-demosaic", "doe-tent-demosaic", "doe-linear-demosaic",
                                  "dd-cassi-gaptv", "dd-cassi-desci"])
def test_registered_methods_give_cubes_on_the_cameras_bands(tiny_run, name):
    """Each method's reconstruct: (B, C, H, W) on its camera's bands, the size of target(scene), for a batch of
    small random scenes (down to a 1-px sensor image; DeSCI refuses images smaller than its patch in one line)."""
    cfg = load_config(tiny_run / "config.yaml", ["baselines.gaptv.iterations=2", "baselines.desci.preset=fast"])
    method = build_method(name, cfg, tiny_run)
    margin = getattr(method.camera, "margin", 0) if method.camera.boundary == "valid" else 0
    n = len(method.camera.bands)
    assert method.camera.bands.centers_nm.tolist() == cfg.bands.to_bands().centers_nm.tolist()
    smallest = 6 if name == "dd-cassi-desci" else 1
    for hw in ((margin + smallest, margin + smallest), (margin + 7, margin + 9)):
        scene = torch.rand(2, n, *hw, generator=torch.Generator().manual_seed(hw[1]))
        with torch.no_grad():
            est = method.reconstruct(method.camera(scene))
        assert est.shape == method.target(scene).shape == (2, n, hw[0] - margin, hw[1] - margin)
        assert torch.isfinite(est).all()


# ------------------------------------------------------------------------------------------------
# spectral sources
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def library():
    pytest.importorskip("colour")
    from hsicam.data.spectral_sources import spectral_library

    return spectral_library(load_config("tiny").bands.to_bands())


def test_library_basis_and_light_normalisation(library):
    """Basis rows orthonormal; mean + coeffs · components gives each spectrum back, to the energy of the singular
    values left out (numpy's SVD of the centred library); illuminants mean 1, emitters maximum 1, all ≥ 0."""
    from hsicam.data.spectral_sources import ReflectanceBasis

    for q in (3, 8):
        b = ReflectanceBasis.fit(library.reflectances, q)
        np.testing.assert_allclose(b.components @ b.components.T, np.eye(b.components.shape[0]), atol=1e-12)
        x = library.reflectances.astype(np.float64)
        sv = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
        left = float((sv[b.components.shape[0]:] ** 2).sum())
        assert ((b.mean + b.coeffs @ b.components - x) ** 2).sum() == pytest.approx(left, abs=1e-12, rel=1e-9)
    np.testing.assert_allclose(library.illuminants.mean(axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(library.emitters.max(axis=1), 1.0, rtol=1e-6)
    assert library.illuminants.min() >= 0 and library.emitters.min() >= 0
    assert 0 <= library.reflectances.min() and library.reflectances.max() <= 1


def test_otsu_equals_colour_science(library):
    """OtsuModel.reflectance equals colour's XYZ_to_sd_Otsu2018 for non-black XYZ, on the selector's thresholds too."""
    from colour.recovery import XYZ_to_sd_Otsu2018

    otsu = library.otsu
    rng = np.random.default_rng(0)
    xyz = [*rng.uniform(0, 1, (40, 3)), *rng.uniform(0, 1e-4, (5, 3)), np.array([0.9505, 1.0, 1.089])]
    for origin, axis, _, _ in otsu.selector[:10]:  # xy exactly on a split of the kd-tree
        xy = [0.3, 0.3]
        xy[int(axis)] = origin
        xyz.append(np.array([xy[0], xy[1], 1 - xy[0] - xy[1]]))
    xyz = np.array(xyz)
    ours = otsu.reflectance(xyz)
    for i, v in enumerate(xyz):
        np.testing.assert_allclose(ours[i], XYZ_to_sd_Otsu2018(v).values, atol=1e-9)


@settings(PROPS, max_examples=10)
@given(held=st.sets(st.sampled_from(["nist-cqs", "cie-tcs", "cie-a", "blackbody", "led-model", "otsu2018",
                                     "cie-daylight"]), min_size=1, max_size=3))
def test_split_library_holds_out_exactly_the_named_sources(library, held):
    """Training: no spectrum of a held-out source, and every other spectrum kept unless listed as removed (equal,
    to SAME_SPECTRUM_ATOL, to a held-out one of its role). Held out: a role with a held-out source has only those
    (all of them), another role the training spectra; emitters only when an emitter source is held out."""
    from hsicam.data.spectral_sources import SAME_SPECTRUM_ATOL, split_library

    try:
        train = split_library(library, ",".join(held), "train")
        heldout = split_library(library, ",".join(held), "heldout")
    except InputError:
        return  # e.g. nothing left to train on: refused in one line
    roles = (("reflectance", "reflectances"), ("illuminant", "illuminants"), ("emitter", "emitters"))
    for one, role in roles:
        names, srcs, arr = (getattr(library, f"{one}_names"), getattr(library, f"{one}_sources"),
                            getattr(library, role))
        held_rows = arr[[i for i, s in enumerate(srcs) if s in held]]
        expect_train = [nm for nm, s, row in zip(names, srcs, arr) if s not in held and not (
            len(held_rows) and np.abs(held_rows.astype(np.float64) - row).max(axis=1).min() <= SAME_SPECTRUM_ATOL)]
        if role == "reflectances" and not expect_train:
            continue  # painted with the Otsu clusters' means
        assert getattr(train, f"{one}_names") == expect_train
        held_names = [nm for nm, s in zip(names, srcs) if s in held]
        got = getattr(heldout, f"{one}_names")
        if held_names:
            assert got == held_names
        elif role == "emitters":
            assert got == []
        else:
            assert got == expect_train
    assert (train.otsu is None) == ("otsu2018" in held) and (heldout.otsu is None) == ("otsu2018" not in held)


# ------------------------------------------------------------------------------------------------
# provenance
# ------------------------------------------------------------------------------------------------
@PROPS
@given(perm=st.permutations(["data.val_fraction=0.5", "camera.sensor.sigma=0.01", "train.lr=0.002",
                             "model.rdn.features=6"]))
def test_config_hash_independent_of_override_order(perm):
    ref = config_hash(dump_yaml(load_config("tiny", ["data.val_fraction=0.5", "camera.sensor.sigma=0.01",
                                                     "train.lr=0.002", "model.rdn.features=6"])))
    assert config_hash(dump_yaml(load_config("tiny", list(perm)))) == ref


def test_data_record_round_trip_and_roles(tmp_path):
    """data.json read back (as JSON, and by read_data_record) is the record; no changes against the folder; each
    scene's role is the one its list gives it, also for a copy of the folder with its file times."""
    import shutil

    from hsicam.data.formats import write_cube_h5
    from hsicam.engine.provenance import data_changes, data_record, read_data_record, scene_roles, write_data_record

    root = tmp_path / "data"
    (root / "sub").mkdir(parents=True)
    cfg = load_config("tiny", [f"data.root={root}", "data.val_fraction=0.5"])
    bands = cfg.bands.to_bands()
    rel = ["a.h5", "sub/b.h5", "c.h5", "sub/d.h5"]
    for i, p in enumerate(rel):
        write_cube_h5(root / p, np.random.default_rng(i).random((len(bands), 12, 12)).astype(np.float32), bands, {})
    record = data_record(cfg.data, bands)
    write_data_record(tmp_path / "run", record)
    assert json.loads((tmp_path / "run" / "data.json").read_text()) == record == read_data_record(tmp_path / "run")
    assert sorted(record["train"] + record["validation"]) == sorted(rel) == [e["path"] for e in record["scenes"]]
    assert data_changes(record, data_record(cfg.data, bands)) == {"added": [], "removed": [], "changed": [], "moved": []}
    expect = ["train" if p in record["train"] else "validation" for p in rel]
    assert scene_roles(record, [root / p for p in rel]) == expect
    shutil.copytree(root, tmp_path / "copy")
    assert scene_roles(record, [tmp_path / "copy" / p for p in rel]) == expect
