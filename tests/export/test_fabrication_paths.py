"""Bad paths of `hsicam tolerance` and `hsicam export-optics` (probe 21: F1, F14, F15).

* F1: a sensor distance error whose defocus the pupil grid cannot represent is refused up front,
  by the same criterion as the PSF plan (`hsicam psf` / ``PSFModel`` refuse that sensor distance).
* F14: a camera without a DOE (or without a CFA) exports only what it has, and its tolerance study
  skips the DOE sweeps (recorded) and refuses the DOE sweep options.
* F15: a run fine-tuned on measured PSFs is refused by `tolerance` (it would study the design
  optics), and `export-optics` does not cite such a study.

Runs: the shared ``fab_run`` (tiny optics, trained) and two 1-epoch runs of the same config
without a DOE / without a CFA, trained on ``fab_run``'s scenes.
"""

from __future__ import annotations

import csv
import json
import math
import shutil

import numpy as np
import pytest
import torch
import yaml

from cli_helpers import assert_clean_error, run_cli_in_process
from fab_runs import FAB_OVERRIDES, fab_run, write_psf_dir  # noqa: F401 - shared fixture
from hsicam.cameras import DOECamera
from hsicam.config import load_config
from hsicam.errors import ConfigError, InputError


def _train_variant(fab_run, tmp_path_factory, name: str, *overrides: str):
    from hsicam.engine.train import train

    run = tmp_path_factory.mktemp(name) / "run"
    cfg = load_config("tiny", [*FAB_OVERRIDES, f"data.root={fab_run.parent / 'data'}", "train.epochs=1", *overrides])
    train(cfg, run, progress=False)
    return run


@pytest.fixture(scope="module")
def no_doe_run(fab_run, tmp_path_factory):
    return _train_variant(fab_run, tmp_path_factory, "nodoe", "camera.doe.enabled=false")


@pytest.fixture(scope="module")
def no_cfa_run(fab_run, tmp_path_factory):
    return _train_variant(fab_run, tmp_path_factory, "nocfa", "camera.cfa.enabled=false")


@pytest.fixture(scope="module")
def finetuned_run(fab_run, tmp_path_factory):
    """fab_run fine-tuned 1 epoch on 'measured' PSFs (its design PSFs with a band throughput 0.6..1)."""
    from hsicam.runs.folder import load_run

    _, model = load_run(fab_run)
    with torch.no_grad():
        psf = model.camera.psf().double().numpy() * np.linspace(0.6, 1.0, len(model.bands))[:, None, None]
    k = psf.shape[-1]
    base = tmp_path_factory.mktemp("ft")
    d = write_psf_dir(base / "measured", psf, model.bands, 10.0, centre="axis", axis_px=[k // 2, k // 2],
                      normalize="none")
    run = base / "ft"
    res = run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(d), "--out", str(run), "--epochs", "1")
    assert res.returncode == 0, res.stderr
    return run


# ------------------------------------------------------------------------------------------------
# F1: aliased sensor-distance sweeps
# ------------------------------------------------------------------------------------------------
def test_sensor_distance_limits_are_the_psf_plans_own(tiny_config):
    """The representable range of Δz is where the PSF plan's criterion reaches 1, and a camera
    built with the sensor just inside it is accepted by ``PSFModel``, just outside refused."""
    from hsicam.optics.perturb import sensor_distance_aliasing, sensor_distance_limits_m

    cfg = tiny_config()
    cam = DOECamera.from_config(cfg)
    o = cam.optics
    lo, hi = sensor_distance_limits_m(o)
    assert -o.sensor_distance_m < lo < 0 < hi < math.inf
    for dz in (lo, hi):
        assert float(sensor_distance_aliasing(o, dz).max()) == pytest.approx(1.0, abs=1e-9)
    assert float(sensor_distance_aliasing(o, 0.0).max()) < 1
    z_mm = o.sensor_distance_m * 1e3
    for dz in (lo, hi):
        inside, outside = dz * (1 - 1e-4), dz * (1 + 1e-4)
        assert float(sensor_distance_aliasing(o, outside).max()) > 1 > float(sensor_distance_aliasing(o, inside).max())
        DOECamera.from_config(tiny_config(f"camera.sensor_distance_mm={z_mm + inside * 1e3!r}"))
        with pytest.raises(ConfigError, match="pupil sampling can represent"):
            DOECamera.from_config(tiny_config(f"camera.sensor_distance_mm={z_mm + outside * 1e3!r}"))


def test_sensor_distance_limits_with_band_samples_and_a_singlet(tiny_config):
    """Every simulated wavelength counts (band_samples > 1, a singlet's per-band focus and its
    rear principal plane moving with λ): the limits are where the camera built with the sensor
    there is accepted by ``PSFModel``, just beyond refused."""
    from hsicam.optics.perturb import sensor_distance_aliasing, sensor_distance_limits_m

    singlet = ("camera.psf.band_samples=3", "camera.lens.model=singlet", "camera.lens.radius_of_curvature_mm=2.3",
               "camera.lens.center_thickness_mm=0.5")
    cam = DOECamera.from_config(tiny_config(*singlet))
    o = cam.optics
    assert np.ptp(o.line_sensor_distances_m) > 0  # the case this test is for
    lo, hi = sensor_distance_limits_m(o)
    for dz in (lo, hi):
        r = sensor_distance_aliasing(o, dz)
        assert r.shape == (3 * len(cam.bands),) and float(r.max()) == pytest.approx(1.0, abs=1e-9)
    grid = np.linspace(lo * 1.5, hi * 1.5, 301)
    ok = np.array([float(sensor_distance_aliasing(o, dz).max()) <= 1 for dz in grid])
    np.testing.assert_array_equal(ok, (grid >= lo * (1 + 1e-12)) & (grid <= hi * (1 + 1e-12)))
    z_mm = o.sensor_distance_m * 1e3
    for dz in (lo, hi):
        inside, outside = dz * (1 - 1e-4), dz * (1 + 1e-4)
        DOECamera.from_config(tiny_config(*singlet, f"camera.sensor_distance_mm={z_mm + inside * 1e3!r}"))
        with pytest.raises(ConfigError, match="pupil sampling can represent"):
            DOECamera.from_config(tiny_config(*singlet, f"camera.sensor_distance_mm={z_mm + outside * 1e3!r}"))


def test_tolerance_refuses_aliased_sensor_distances(fab_run, tmp_path, monkeypatch):
    import hsicam.engine.tolerance as tol

    out = tmp_path / "tol"
    with monkeypatch.context() as m:  # refused before any scene is loaded or scored
        m.setattr(tol, "evaluation_scenes", lambda *a, **k: (_ for _ in ()).throw(AssertionError("scored")))
        res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), "--max-scenes", "1", "--draws", "1",
                      "--sensor-distance-um=-4000,-1000,0,1000,1e6,1e9")
    assert_clean_error(res, "--sensor-distance-um: Δz = -4000, -1000, 1000, 1e+06, 1e+09 µm",
                       "pupil sampling can represent", "sweep within that range", "camera.psf.pupil_oversample >=")
    assert not out.exists()
    from hsicam.optics.perturb import sensor_distance_limits_m
    from hsicam.runs.folder import load_run

    _, model = load_run(fab_run)
    lo, hi = sensor_distance_limits_m(model.camera.optics)
    lo_um, hi_um = math.ceil(lo * 1e7) / 10, math.floor(hi * 1e7) / 10  # as printed: cut toward zero
    assert f"represent Δz from {lo_um:g} µm toward the lens to +{hi_um:g} µm away" in res.stderr, res.stderr
    # the printed limits themselves are accepted: the study runs and records the range
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), "--max-scenes", "1", "--draws", "1",
                  "--sigma-height-nm", "0", "--levels", "8", "--shift-cells", "0",
                  f"--sensor-distance-um={lo_um:g},0,{hi_um:g}")
    assert res.returncode == 0, res.stderr
    r = json.loads((out / "tolerance.json").read_text())
    assert r["sensor_distance_um_representable"] == [lo_um, hi_um]
    assert r["sweeps"]["sensor_distance_um"]["values"] == [lo_um, 0.0, hi_um]
    # one value just past the limit is refused on its own
    past = f"{hi_um + 1:g}"
    assert_clean_error(run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(tmp_path / "t2"),
                               f"--sensor-distance-um=0,{past}"), f"Δz = {past} µm")
    assert not (tmp_path / "t2").exists()


# ------------------------------------------------------------------------------------------------
# F14: cameras without a DOE / without a CFA
# ------------------------------------------------------------------------------------------------
def test_export_without_doe_writes_no_doe_files(no_doe_run, tmp_path):
    from hsicam.export.cfa import read_transmission_csv
    from hsicam.runs.folder import load_run

    out = tmp_path / "fab"
    res = run_cli_in_process("export-optics", "--run", str(no_doe_run), "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert "no DOE (camera.doe.enabled: false: no DOE files)" in res.stdout and "CFA (3×3" in res.stdout
    files = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert not [f for f in files if f.startswith("doe")], files
    assert {"cfa_tile.npy", "cfa_transmission.csv", "cfa_fit.csv", "spec.json"} <= set(files)
    spec = json.loads((out / "spec.json").read_text())
    assert spec["doe"]["enabled"] is False and set(spec["doe"]) == {"enabled", "note"}
    assert "no DOE files" in spec["doe"]["note"] and spec["cfa"]["enabled"] is True
    assert spec["files"] == files and "at the lens" in spec["aperture"]["stop"]
    _, model = load_run(no_doe_run)
    lam, t, names = read_transmission_csv(out / "cfa_transmission.csv")
    np.testing.assert_array_equal(t, model.camera.cfa.tile().detach().numpy().reshape(len(lam), -1))
    # nothing to quantise: --levels is refused, naming the way out
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(no_doe_run), "--out", str(tmp_path / "o"), "--levels", "8"),
                       "--levels 8", "has no DOE (camera.doe.enabled: false)", "leave out --levels")
    assert not (tmp_path / "o").exists()


def test_export_without_cfa_writes_no_cfa_files(no_cfa_run, tmp_path):
    out = tmp_path / "fab"
    res = run_cli_in_process("export-optics", "--run", str(no_cfa_run), "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert "no CFA (camera.cfa.enabled: false: no CFA files)" in res.stdout and "DOE (" in res.stdout
    files = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert not [f for f in files if f.startswith("cfa")], files
    assert {"doe_height_nm.npy", "doe_height_L8_nm.tif", "doe_L8.gds", "spec.json"} <= set(files)
    spec = json.loads((out / "spec.json").read_text())
    assert spec["cfa"]["enabled"] is False and set(spec["cfa"]) == {"enabled", "note"}
    assert spec["doe"]["enabled"] is True and spec["doe"]["quantized"]["levels"] == 8


def test_export_with_neither_doe_nor_cfa_is_the_spec_alone(fab_run, tmp_path):
    from hsicam.export import export_optics
    from hsicam.runs.checkpoint import save_weights
    from hsicam.runs.folder import load_run

    # an untrained camera of that config: the export reads weights and config only
    run = tmp_path / "bare"
    run.mkdir()
    cfg = load_config("tiny", [*FAB_OVERRIDES, "camera.doe.enabled=false", "camera.cfa.enabled=false"])
    from hsicam.config import dump_yaml
    from hsicam.models import CameraSystem

    (run / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    model = CameraSystem.from_config(cfg)
    save_weights(run / "model.safetensors", model, model.bands)
    load_run(run)
    spec = export_optics(run, tmp_path / "fab")
    assert spec["doe"]["enabled"] is False and spec["cfa"]["enabled"] is False
    assert sorted(p.name for p in (tmp_path / "fab").iterdir() if not p.name.startswith(".")) == ["spec.json"]
    res = run_cli_in_process("export-optics", "--run", str(run), "--out", str(tmp_path / "fab2"))
    assert res.returncode == 0, res.stderr
    assert "exported no DOE" in res.stdout and "no CFA" in res.stdout


def test_tolerance_without_doe_skips_the_doe_sweeps(no_doe_run, tmp_path):
    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(no_doe_run), "--out", str(out), "--max-scenes", "1",
                  "--sensor-distance-um=-50,0,50")
    assert res.returncode == 0, res.stderr
    assert "no DOE (camera.doe.enabled: false): DOE sweeps skipped" in res.stdout
    assert "σ_p" not in res.stdout and "levels ≥" not in res.stdout and "Δz toward the lens" in res.stdout
    r = json.loads((out / "tolerance.json").read_text())
    assert r["doe_enabled"] is False
    assert set(r["skipped"]) == {"sigma_height_nm", "levels", "shift"}
    assert all("camera.doe.enabled: false" in v for v in r["skipped"].values())
    assert set(r["sweeps"]) == {"sensor_distance_um"} and set(r["summary"]) == {"sensor_distance_um_at_1db_loss"}
    assert set(r["methods"]) == {"sensor_distance_um"} and r["shift_reference"] is None
    assert {row["sweep"] for row in r["rows"]} == {"sensor_distance_um"}
    rows = list(csv.DictReader(open(out / "tolerance.csv", encoding="utf-8")))
    assert [row["sweep"] for row in rows] == ["nominal"] + ["sensor_distance_um"] * 3
    i = r["sweeps"]["sensor_distance_um"]["values"].index(0.0)
    assert r["sweeps"]["sensor_distance_um"]["psnr"][i] == pytest.approx(r["nominal"]["psnr"], abs=1e-3)
    from PIL import Image

    assert Image.open(out / "tolerance.png").size[0] > 100
    # asking for a DOE sweep of a camera without a DOE is refused, naming the options and the way out
    for opts in (("--levels", "2,4"), ("--sigma-height-nm", "0,20", "--draws", "2"), ("--shift-cells", "0,1")):
        assert_clean_error(run_cli_in_process("tolerance", "--run", str(no_doe_run), "--out", str(tmp_path / "t2"), *opts),
                           f"{opts[0]}", "has no DOE (camera.doe.enabled: false)", "leave out", "sensor distance only")
    assert not (tmp_path / "t2").exists()


def test_tolerance_without_doe_logs_the_skip(no_doe_run, tmp_path, caplog):
    from hsicam.engine.tolerance import ToleranceSpec, run_tolerance
    from hsicam.runs.folder import load_run

    cfg, model = load_run(no_doe_run)
    with caplog.at_level("INFO", logger="hsicam.engine.tolerance"):
        r = run_tolerance(model, cfg, ToleranceSpec(max_scenes=1, sensor_distance_um=(0.0,)))
    assert any("DOE sweeps" in m and "skipped" in m for m in caplog.messages), caplog.messages
    assert set(r["sweeps"]) == {"sensor_distance_um"}


# ------------------------------------------------------------------------------------------------
# F15: runs fine-tuned on measured PSFs
# ------------------------------------------------------------------------------------------------
def test_tolerance_refuses_a_finetuned_run(fab_run, finetuned_run, tmp_path):
    from hsicam.engine.tolerance import ToleranceSpec, run_tolerance
    from hsicam.runs.folder import load_run

    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(finetuned_run), "--out", str(out), "--max-scenes", "1")
    assert_clean_error(res, f"{finetuned_run}: a run fine-tuned on measured PSFs", "already fabricated and measured",
                       "not the measured PSFs this run images with",
                       f"the design run it was fine-tuned from ({fab_run}, finetune.json)",
                       f"hsicam tolerance --run {fab_run} --out DIR")
    assert not out.exists()
    # the library refuses it too: with the run named, and for a model imaging with measured PSFs
    cfg, model = load_run(finetuned_run)
    with pytest.raises(InputError, match="fine-tuned on measured PSFs"):
        run_tolerance(model, cfg, ToleranceSpec(max_scenes=1), run=finetuned_run)
    with pytest.raises(InputError, match="images with measured PSFs"):
        run_tolerance(model, cfg, ToleranceSpec(max_scenes=1))
    # without finetune.json the advice still names the way out
    bare = tmp_path / "bare"
    shutil.copytree(finetuned_run, bare, ignore=shutil.ignore_patterns("checkpoints*"))
    (bare / "finetune.json").unlink()
    assert_clean_error(run_cli_in_process("tolerance", "--run", str(bare), "--out", str(out)),
                       "study the design run it was fine-tuned from: hsicam tolerance --run DESIGN_RUN")
    # a design run's study records that the design optics were studied
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), "--max-scenes", "1", "--draws", "1",
                  "--sigma-height-nm", "0", "--levels", "8", "--shift-cells", "0", "--sensor-distance-um", "0")
    assert res.returncode == 0, res.stderr
    assert json.loads((out / "tolerance.json").read_text())["optics_studied"].startswith("design")


def test_export_does_not_cite_a_study_of_a_finetuned_run(fab_run, finetuned_run, tmp_path):
    """A study of a fine-tuned run (written before `tolerance` refused them) studied the design
    optics: export-optics refuses it with --tolerance, and leaves it uncited (noted) in RUN/tolerance."""
    from hsicam.export.tolerance import TOLERANCE_FORMAT, run_identity

    ft = tmp_path / "ft"
    shutil.copytree(finetuned_run, ft)
    study = ft / "tolerance" / "tolerance.json"
    study.parent.mkdir()
    study.write_text(json.dumps({"format": TOLERANCE_FORMAT, "run": run_identity(ft), "nominal": {"psnr": 25.0},
                                 "summary": {}}))
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(ft), "--out", str(tmp_path / "o"), "--tolerance", str(study)),
                       f"{ft} is a run fine-tuned on measured PSFs", "perturbed the simulated design optics",
                       "export without --tolerance", f"export the design run it was fine-tuned from ({fab_run})")
    assert not (tmp_path / "o").exists()
    res = run_cli_in_process("export-optics", "--run", str(ft), "--out", str(tmp_path / "o"))
    assert res.returncode == 0, res.stderr
    tol = json.loads((tmp_path / "o" / "spec.json").read_text())["tolerances"]
    assert tol["studied"] is None and "not cited" in tol["note"] and "fine-tuned on measured PSFs" in tol["note"]


def test_export_of_a_finetuned_run_cites_a_study_of_its_design_run(fab_run, finetuned_run, tmp_path, monkeypatch):
    """`export-optics --run FT --tolerance STUDY` where STUDY is the design run's own study (what the refusal and the
    note recommend) was refused as "a tolerance study of it perturbed the simulated design optics … export the
    design run … and cite its study" (a helper's hunt, session 71). Now it is cited, checked against the design
    run's weights and said to be its; a study of the fine-tuned run itself is refused as before; the cited path is
    absolute."""
    import os

    from hsicam.export.tolerance import TOLERANCE_FORMAT, run_identity

    study = tmp_path / "design_study" / "tolerance.json"
    study.parent.mkdir()
    study.write_text(json.dumps({"format": TOLERANCE_FORMAT, "run": run_identity(fab_run), "nominal": {"psnr": 31.5},
                                 "summary": {}}))
    monkeypatch.chdir(tmp_path)
    rel = os.path.relpath(study, tmp_path)
    res = run_cli_in_process("export-optics", "--run", str(finetuned_run), "--out", str(tmp_path / "o"),
                             "--tolerance", rel)
    assert res.returncode == 0, res.stderr
    tol = json.loads((tmp_path / "o" / "spec.json").read_text())["tolerances"]
    assert tol["studied"]["run_checked"] is True and tol["studied"]["nominal_psnr_db"] == 31.5
    assert tol["studied"]["source"] == str(study) and tol["studied"]["of_design_run"] == str(fab_run)
    assert tol["note"].startswith(f"a study of the design run it was fine-tuned from ({fab_run}), whose optics")
    # a design run trained on since the fine-tuning (its DOE moved): its study is not of these optics (a review)
    from safetensors.torch import load_file, save_file

    # (the copy without its checkpoints: the root weights are then the kept ones, as after a finished training)
    design = shutil.copytree(fab_run, tmp_path / "design", ignore=shutil.ignore_patterns("checkpoints*"))
    ft = shutil.copytree(finetuned_run, tmp_path / "ft")
    weights = load_file(design / "model.safetensors")
    weights["camera.optics.doe.height_m"] = weights["camera.optics.doe.height_m"] + 1e-9
    save_file(weights, design / "model.safetensors")
    info = json.loads((ft / "finetune.json").read_text())
    (ft / "finetune.json").write_text(json.dumps({**info, "source_run": str(design)}))
    study.write_text(json.dumps({"format": TOLERANCE_FORMAT, "run": run_identity(design), "nominal": {"psnr": 31.5},
                                 "summary": {}}))
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(ft), "--out", str(tmp_path / "o2"),
                                          "--tolerance", str(study)),
                       f"{study}: a study of {design}, whose optics (DOE heights, CFA) are no longer those {ft} was "
                       "fine-tuned with (the design run trained on since); export without --tolerance")
    assert not (tmp_path / "o2").exists()


def test_export_of_a_finetuned_run_says_so_and_points_at_the_design_runs_study(fab_run, finetuned_run, tmp_path):
    """Probe 26 #2: the export of a fine-tuned run (no study) advised `hsicam tolerance --run RUN`,
    which tolerance refuses, and spec.json never said the run was fine-tuned."""
    from hsicam.export import export_optics

    spec = export_optics(finetuned_run, tmp_path / "o")
    assert spec["finetuned"]["on_measured_psfs"] is True and spec["finetuned"]["from_run"] == str(fab_run)
    assert spec["tolerances"]["studied"] is None
    assert spec["tolerances"]["note"].endswith(f"`hsicam tolerance --run {fab_run} --out DIR`")
    assert json.loads((tmp_path / "o" / "spec.json").read_text()) == spec
    # the note's command is one tolerance accepts (the design run), unlike the fine-tuned run itself
    assert_clean_error(run_cli_in_process("tolerance", "--run", str(finetuned_run), "--out", str(tmp_path / "t")),
                       "fine-tuned on measured PSFs")
    # the design run's own export: no "finetuned" entry, and its study's place named by the run's path
    design = export_optics(fab_run, tmp_path / "d")
    assert "finetuned" not in design and design["run"] == str(fab_run)
    assert design["tolerances"]["note"].endswith(f"`hsicam tolerance --run {fab_run} --out {fab_run / 'tolerance'}`")


def test_export_of_a_shipped_camera_names_it_not_its_package_folder(tmp_path):
    from hsicam.export import export_optics

    spec = export_optics("pretrained:standard", tmp_path / "o")
    assert spec["run"] == "pretrained:standard" and "finetuned" not in spec
    assert spec["tolerances"]["note"] == ("no tolerance study found: run `hsicam tolerance --run pretrained:standard "
                                          "--out DIR`")


def test_export_refusals_name_the_run_and_what_is_missing_of_a_tolerance_folder(tmp_path):
    """An untrained camera with 6 DOE levels (exported with them since session 73: no refusal to name the run for);
    --tolerance given a folder without tolerance.json, or a path that does not exist, says which (it said "DIR: no
    tolerance.json" for both)."""
    from hsicam.config import dump_yaml
    from hsicam.export import export_optics
    from hsicam.models import CameraSystem
    from hsicam.runs.checkpoint import save_weights

    run = tmp_path / "bare"
    run.mkdir()
    cfg = load_config("tiny", [*FAB_OVERRIDES, "camera.doe.quantization_levels=6"])
    (run / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    model = CameraSystem.from_config(cfg)
    save_weights(run / "model.safetensors", model, model.bands)
    assert export_optics(run, tmp_path / "six")["doe"]["quantized"]["levels"] == 6
    empty = tmp_path / "study"
    empty.mkdir()
    for given, why in ((empty, "no tolerance.json in this folder"), (tmp_path / "nowhere", "no such file or folder")):
        with pytest.raises(InputError) as exc:
            export_optics(run, tmp_path / "fab", levels=8, tolerance=given)
        assert str(exc.value) == (f"{given}: {why} (--tolerance takes the folder `hsicam tolerance --run "
                                  f"{run.resolve()} --out DIR` wrote, or its tolerance.json)")
    assert not (tmp_path / "fab").exists()  # nothing half-written


def test_tolerance_refuses_scenes_too_small_for_its_camera_up_front_without_advice_it_cannot_take(fab_run, tmp_path):
    """A scene whose scored area (the scene minus the kernel margin) is below SSIM's window is refused before the
    first point, naming it and the size needed; `tolerance` has no --set, so the `camera.boundary=same` that
    evaluate offers is not offered (it used to be)."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.runs.folder import load_run

    _, model = load_run(fab_run)
    bands, margin = model.camera.bands, model.camera.margin
    small = tmp_path / "small"
    write_cube_h5(small / "a.h5", np.full((len(bands), margin + 4, margin + 4), 0.5, np.float32), bands)
    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--data", str(small), "--out", str(out))
    assert_clean_error(res, "a.h5: scene of", "SSIM needs at least 11×11", f"scenes of at least {margin + 11} px")
    assert "boundary=same" not in res.stderr and not out.exists()
    ev = run_cli_in_process("evaluate", "--run", str(fab_run), "--data", str(small), "--out", str(tmp_path / "ev"))
    assert_clean_error(ev, "or camera.boundary=same")  # evaluate takes --set: its advice stays


def test_spec_says_where_the_sensor_distance_is_measured_from_and_the_lens_orientation(tiny_config, tmp_path):
    """A singlet run's spec.json gave sensor_distance_mm (from the rear principal plane H') without saying so: a fab
    measuring it from the flat back face puts the sensor t/n = 1.37 mm too far for the paper singlet (~23 waves of
    defocus at f/3.5; session 73's hunt). The lens block names the reference plane, H' from the rear vertex, the back
    focal distance (rear vertex to sensor) and which face points at the object; for the plano-convex singlet H' lies
    −t/n(λ0) from the flat rear vertex (the independent reference here, with fused silica's n at 587.6 nm)."""
    from hsicam.cameras import DOECamera
    from hsicam.export import _export_into
    from hsicam.spectral import FusedSilica

    cfg = tiny_config("camera.lens.model=singlet", "camera.doe.enabled=false", "camera.cfa.enabled=false")
    cam = DOECamera.from_config(cfg)
    out = tmp_path / "fab"
    out.mkdir()
    spec = _export_into(out, {"run": "test"}, cfg, cam, None, {})
    lens = spec["lens"]
    t_mm = cfg.camera.lens.center_thickness_mm
    n0 = float(FusedSilica().n(np.array([587.6]))[0])
    assert lens["model"] == "singlet" and lens["orientation"] == "plano-convex, the convex face towards the object"
    assert lens["sensor_distance_from"].startswith("rear principal plane H'")
    assert lens["rear_principal_plane_mm"] == pytest.approx(-t_mm / n0, rel=1e-6)
    assert lens["back_focal_distance_mm"] == pytest.approx(spec["sensor_distance_mm"] - t_mm / n0, rel=1e-9)
    assert json.loads((out / "spec.json").read_text())["lens"] == lens


def test_spec_records_the_weights_it_was_made_from_and_an_unfinished_training(fab_run, tmp_path):
    """spec.json named the run's folder only: a package made from a half-trained run looked like a final one, and a
    run resumed later could not be tied to the files sent to the fab (session 73's hunt). It records the weights
    file's SHA-256, the checkpoint they are (best or last, its step; the run's last step), and whether the training
    finished (the note when not)."""
    import hashlib

    from hsicam.export import export_optics

    spec = export_optics(fab_run, tmp_path / "fab")
    w = spec["weights"]
    assert w["file"] == "model.safetensors" and w["training_finished"] is True and "unfinished" not in w
    assert w["sha256"] == hashlib.sha256((fab_run / "model.safetensors").read_bytes()).hexdigest()
    manifest = json.loads((fab_run / "checkpoints.json").read_text())  # the checkpoint the weights are (best here)
    kept = manifest["weights"]["from"]
    assert w["checkpoint"]["checkpoint"] == kept and w["checkpoint"]["step"] == manifest[kept]["step"]
    assert w["checkpoint"]["last_step"] == manifest["last"]["step"]
    half = tmp_path / "half"
    shutil.copytree(fab_run, half)
    # as if killed halfway through a training twice as long: no final record, twice the epochs and steps planned
    lines = (half / "metrics.jsonl").read_text().splitlines()
    assert json.loads(lines[-1]).get("final")
    (half / "metrics.jsonl").write_text("\n".join(lines[:-1]) + "\n")
    cfg_text = (half / "config.yaml").read_text()
    epochs = yaml.safe_load(cfg_text)["train"]["epochs"]
    (half / "config.yaml").write_text(cfg_text.replace(f"  epochs: {epochs}\n", f"  epochs: {2 * epochs}\n", 1))
    manifest = json.loads((half / "checkpoints.json").read_text())
    manifest["state"]["total_steps"] *= 2
    (half / "checkpoints.json").write_text(json.dumps(manifest))
    spec = export_optics(half, tmp_path / "fab_half")
    assert spec["weights"]["training_finished"] is False
    assert "its training did not finish" in spec["weights"]["unfinished"]


def test_a_run_trained_with_three_levels_exports_its_element_and_other_levels_are_warned_about(fab_run, tmp_path,
                                                                                             caplog):
    """docs/hardware.md: a run trained with L levels not a power of 2 is exported with its own L, without GDS masks.
    A 3-level run was refused instead, with advice (--levels) that takes powers of 2 only, and --levels 4 exported
    another element without a word (session 73's hunt). Now the default exports the trained element cell for cell
    (no GDS), and a --levels other than the run's is warned about."""
    import logging

    from hsicam.optics.perturb import design_heights
    from hsicam.runs.folder import load_run

    run = tmp_path / "run3"
    shutil.copytree(fab_run, run, ignore=shutil.ignore_patterns("checkpoints*"))
    text = (run / "config.yaml").read_text()
    assert text.count("quantization_levels: null") == 1
    (run / "config.yaml").write_text(text.replace("quantization_levels: null", "quantization_levels: 3"))
    res = run_cli_in_process("export-optics", "--run", str(run), "--out", str(tmp_path / "fab"))
    assert res.returncode == 0, res.stderr
    spec = json.loads((tmp_path / "fab" / "spec.json").read_text())
    q = spec["doe"]["quantized"]
    assert q["levels"] == 3 and q["gds"]["file"] is None and "power of 2" in q["gds"]["skipped"]
    _, model = load_run(run)
    h_m, aperture, piston = design_heights(model.camera)
    with torch.no_grad():
        trained_nm = model.camera.optics.doe.heights().double().numpy() * 1e9
    inside = aperture > 0
    exported = np.load(tmp_path / "fab" / "doe_height_L3_nm.npy").astype(np.float64)
    np.testing.assert_allclose(exported[inside], (trained_nm - piston * 1e9)[inside], atol=1e-3)  # as trained
    assert q["phase_error_design_wavelength_rad"]["max"] < 1e-5
    with caplog.at_level(logging.WARNING, logger="hsicam.export"):
        res = run_cli_in_process("export-optics", "--run", str(run), "--out", str(tmp_path / "fab4"), "--levels", "4")
    assert res.returncode == 0, res.stderr
    said = [r.getMessage() for r in caplog.records if "trained with 3 DOE levels" in r.getMessage()]
    assert len(said) == 1 and "another element than the one trained" in said[0], caplog.text


def test_the_cameras_own_height_noise_is_recorded_where_it_is_applied_and_where_it_is_left_out(fab_run, tmp_path):
    """A run whose camera.doe.sigma_height_nm is 40: evaluate draws it (its results recorded sigma_height_nm: null,
    read as none), the tolerance study's nominal leaves it out (design heights: its nominal was evaluate's figure
    without the noise, unsaid). Each record says which (session 73's hunt)."""
    run = tmp_path / "run40"
    shutil.copytree(fab_run, run, ignore=shutil.ignore_patterns("checkpoints*"))
    text = (run / "config.yaml").read_text()
    assert text.count("sigma_height_nm: 0.0\n") == 1
    (run / "config.yaml").write_text(text.replace("sigma_height_nm: 0.0\n", "sigma_height_nm: 40.0\n"))
    for extra, applied in (((), 40.0), (("--sigma-height-nm", "0"), 0.0)):
        out = tmp_path / f"ev{applied:g}"
        res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), *extra)
        assert res.returncode == 0, res.stderr
        noise = json.loads((out / "results.json").read_text())["noise"]
        assert noise["sigma_height_nm_applied"] == applied, noise
    res = run_cli_in_process("tolerance", "--run", str(run), "--out", str(tmp_path / "tol"), "--max-scenes", "1",
                             "--sensor-distance-um=0", "--levels", "2", "--sigma-height-nm", "0", "--draws", "1",
                             "--shift-cells", "0")
    assert res.returncode == 0, res.stderr
    nominal = json.loads((tmp_path / "tol" / "tolerance.json").read_text())["nominal"]
    assert nominal["camera_sigma_height_nm_left_out"] == pytest.approx(40.0)
    assert nominal["heights"] == "design, without fabrication noise"


def test_an_unfinished_run_that_another_process_is_training_is_said_to_be_in_training(fab_run, tmp_path):
    """Reading a run that another process is training warned "its training did not finish … continue it with
    `hsicam train --resume`", advice that run's lock then refused (session 73's hunt): the note says it is being
    trained now, by whom, and where its last checkpoint stands."""
    import subprocess
    import sys

    from cli_helpers import cli_env
    from hsicam.config import load_config as load
    from hsicam.runs.folder import unfinished_training
    from hsicam.runs.lock import LOCK_FILE

    half = tmp_path / "half"
    shutil.copytree(fab_run, half)
    lines = (half / "metrics.jsonl").read_text().splitlines()
    (half / "metrics.jsonl").write_text("\n".join(lines[:-1]) + "\n")
    epochs = yaml.safe_load((half / "config.yaml").read_text())["train"]["epochs"]
    text = (half / "config.yaml").read_text()
    (half / "config.yaml").write_text(text.replace(f"  epochs: {epochs}\n", f"  epochs: {2 * epochs}\n", 1))
    manifest = json.loads((half / "checkpoints.json").read_text())
    manifest["state"]["total_steps"] *= 2
    (half / "checkpoints.json").write_text(json.dumps(manifest))
    cfg = load(str(half / "config.yaml"))
    assert "continue it with `hsicam train --resume" in unfinished_training(half, cfg)
    go = tmp_path / "go"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom pathlib import Path\nfrom hsicam.runs.lock import RunLock\n"
        "lock = RunLock(sys.argv[1]); lock.acquire(); print('held', flush=True)\n"
        "while not Path(sys.argv[2]).exists(): time.sleep(0.01)\n"), str(half), str(go)],
        env=cli_env(), stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert (half / LOCK_FILE).exists()
        note = unfinished_training(half, cfg)
        assert f"being trained by another process (pid {holder.pid}" in note and "--resume" not in note, note
        assert f"the last checkpoint is at step {manifest['state']['global_step']}" in note
    finally:
        go.write_text("")
        holder.communicate(timeout=60)
