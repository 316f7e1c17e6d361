"""`hsicam evaluate`, `hsicam experiment` and `hsicam report` through the command line (the console
script's `main`, in-process)."""

from __future__ import annotations

import csv
import html
import hashlib
import json
import re
import os
import shutil
import subprocess

import numpy as np
import pytest
import torch

from cli_helpers import assert_clean_error, run_cli_in_process
from hsicam.data.formats import write_cube_h5
from hsicam.spectral import Bands


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return {"HSICAM_CACHE": str(tmp_path_factory.mktemp("cache"))}


@pytest.fixture(scope="module")
def run(tmp_path_factory, env):
    d = tmp_path_factory.mktemp("run") / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(d), env=env)
    assert res.returncode == 0, res.stderr
    return d


def test_evaluate_writes_results_in_all_formats(run, env, tmp_path):
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), "--save", "--seeds", "2",
                             "--sensor-sigma", "0.01", "--method", "doe-rdn", env=env)  # the old name of doe-learned
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("doe-learned:") or "\ndoe-learned:" in res.stdout, res.stdout
    summary = json.loads((out / "results.json").read_text())
    assert summary["method"] == "doe-learned" and summary["noise"]["seeds"] == 2
    assert "capture_noise_seed" in summary["noise"]["draws"]  # results say how the noise was drawn
    assert set(summary["conventions"]) >= {"psnr", "ssim", "sam", "ergas"}
    assert len(summary["config_hash"]) == 12
    names = [r["name"] for r in summary["scenes"]]
    assert len(names) == 2
    # one progress line per scene on stderr, with that scene's numbers
    for i, r in enumerate(summary["scenes"]):
        assert f"[{i + 1}/2] {r['name']}: PSNR {r['psnr']:.2f} dB" in res.stderr, res.stderr
    # with a time left while scenes remain (the last line has none)
    lines = re.findall(r"^\[(\d)/2\] .*\(\d+\.\d s(, eta [^)]+)?\)$", res.stderr, re.M)
    assert [(k, bool(eta)) for k, eta in lines] == [("1", True), ("2", False)], res.stderr
    for r in summary["scenes"]:
        assert {"psnr", "ssim", "sam", "ergas", "runtime_s"} <= set(r) and "std" in r
        # each row is the mean of its seeds, and its std their population standard deviation (numpy's)
        assert [s["seed"] for s in r["per_seed"]] == [0, 1]
        for k in ("psnr", "ssim", "sam"):
            values = [s[k] for s in r["per_seed"]]
            assert r[k] == pytest.approx(np.mean(values), abs=1e-12)
            assert r["std"][k] == pytest.approx(np.std(values), abs=1e-12)
        assert r["std"]["psnr"] > 0  # two noise seeds give two different scores
    for k in ("psnr", "ssim", "sam"):
        np.testing.assert_allclose(summary["mean"][k], np.mean([r[k] for r in summary["scenes"]]))
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["name"] for r in rows] == [*names, "mean"]
    for k in ("psnr", "ssim", "sam"):  # the scene rows and their mean row, as written (6 significant digits)
        for row, r in zip(rows, summary["scenes"]):
            assert float(row[k]) == pytest.approx(r[k], rel=1e-5)
        assert float(rows[-1][k]) == pytest.approx(np.mean([float(row[k]) for row in rows[:-1]]), rel=1e-5)
    md = (out / "results.md").read_text()
    mean_row = next(line for line in md.splitlines() if line.startswith("| **mean** |"))
    cells = [c.strip() for c in mean_row.strip("|").split("|")]
    assert cells[1:4] == [f"{summary['mean']['psnr']:.2f}", f"{summary['mean']['ssim']:.4f}",
                          f"{summary['mean']['sam']:.2f}"]
    from hsicam.data import read_cube

    est, bands, _ = read_cube(out / "cubes" / f"{names[0]}_estimate.h5")
    truth, _, _ = read_cube(out / "cubes" / f"{names[0]}_truth.h5")
    assert est.shape == truth.shape and len(bands) == 7
    # the PSNR in the table is the PSNR of the saved cubes (first seed is saved; 2 seeds are averaged)
    from hsicam.metrics import psnr_per_band
    import torch

    p = psnr_per_band(torch.from_numpy(est), torch.from_numpy(truth)).item()
    assert abs(p - summary["scenes"][0]["psnr"]) < 1.0


def test_evaluate_takes_capture_noise_and_the_step_from_its_config(run, env, tmp_path):
    """`--set camera.sensor.*` and `--set model.consistency.*` reach the loaded run's camera and
    system (they were once ignored: the run's own config decided)."""
    means = {}
    for name, sets in (("clean", []), ("noisy", ["camera.sensor.noise=poisson_gaussian", "camera.sensor.full_well_e=30"]),
                       ("step", ["model.consistency.iterations=1"])):
        args = [a for kv in sets for a in ("--set", kv)]
        res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / name), *args, env=env)
        assert res.returncode == 0, res.stderr
        means[name] = json.loads((tmp_path / name / "results.json").read_text())["mean"]
    assert means["noisy"]["psnr"] < means["clean"]["psnr"] - 1.0
    assert abs(means["step"]["psnr"] - means["clean"]["psnr"]) > 1e-3


def test_small_scenes_are_one_clear_error_and_score_whole_with_boundary_same(run, env, tmp_path):
    """A scene whose `valid` area (scene minus the kernel margin, 20 px at the tiny preset's 21 px
    kernel) is below SSIM's 11 px window was a traceback from the metrics; now it is one error
    that says how large scenes must be and offers `--set camera.boundary=same`, which reaches the
    loaded run's camera (it was ignored) and scores the whole scene."""
    bands = Bands.uniform(420, 720, 50)
    data = tmp_path / "small"
    data.mkdir()
    rng = np.random.default_rng(0)
    write_cube_h5(data / "small.h5", rng.random((len(bands), 26, 40)).astype(np.float32), bands)
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "valid"), env=env)
    assert_clean_error(res, "small", "6×20 px", "at least 31 px", "camera.boundary=same")
    assert not (tmp_path / "valid" / "results.json").exists()
    out = tmp_path / "same"
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(out), "--save",
                             "--set", "camera.boundary=same", env=env)
    assert res.returncode == 0, res.stderr
    from hsicam.data import read_cube

    assert json.loads((out / "results.json").read_text())["region"].startswith("whole scene")
    truth, _, _ = read_cube(out / "cubes" / "small_truth.h5")
    est, _, _ = read_cube(out / "cubes" / "small_estimate.h5")
    assert truth.shape == est.shape == (len(bands), 26, 40)  # the whole scene, not its valid centre


def test_evaluate_scores_npy_cubes_on_the_grid_data_npy_bands_gives(run, env, tmp_path):
    """`--data` of .npy cubes (no wavelengths in the file) with `--set data.npy_bands=...` scores
    exactly what the same cube written as our HDF5 with that grid scores; without the key the
    error names it (400-700 nm assumed cannot cover a 420-720 nm camera)."""
    bands = Bands.uniform(420, 720, 50)
    cube = np.random.default_rng(1).random((len(bands), 36, 40)).astype(np.float32)
    (tmp_path / "npy").mkdir()
    (tmp_path / "h5").mkdir()
    np.save(tmp_path / "npy" / "c.npy", cube)
    write_cube_h5(tmp_path / "h5" / "c.h5", cube, bands)
    same = ["--set", "camera.boundary=same"]
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(tmp_path / "npy"), "--out", str(tmp_path / "e0"), *same, env=env)
    last = res.stderr.strip().splitlines()[-1]  # after the reader's notice that 400-700 nm is assumed
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert last.startswith("hsicam: error:") and "c.npy" in last and "data.npy_bands" in last, res.stderr
    means = {}
    for kind, extra in (("npy", ["--set", "data.npy_bands={start_nm: 420, stop_nm: 720, step_nm: 50}"]), ("h5", [])):
        res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(tmp_path / kind), "--out", str(tmp_path / f"e_{kind}"),
                                 *same, *extra, env=env)
        assert res.returncode == 0, res.stderr
        means[kind] = json.loads((tmp_path / f"e_{kind}" / "results.json").read_text())["mean"]
    for k in ("psnr", "ssim", "sam"):
        assert means["npy"][k] == pytest.approx(means["h5"][k], rel=1e-6)


def test_box_reference_images_with_the_evaluation_noise(run):
    """The box-demosaic reference is scored on the same captures as the learned method: the
    evaluation config's sensor noise reaches its camera too (it once imaged noise-free)."""
    import torch

    from hsicam.config import load_config
    from hsicam.engine.methods import build_method

    cfg = load_config(run / "config.yaml", ["camera.sensor.noise=poisson_gaussian", "camera.sensor.full_well_e=30"])
    box, learned = (build_method(m, cfg, run) for m in ("doe-box-demosaic", "doe-learned"))
    scene = torch.rand(1, len(box.camera.bands), 48, 48, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        clean = box.camera.A(scene)
        shots = [m.camera(scene, generator=torch.Generator().manual_seed(5)) for m in (box, learned)]
    assert (shots[0] - clean).abs().mean() > 1e-3  # noisy, as the learned method's captures
    torch.testing.assert_close(shots[0], shots[1])


def test_tent_reference_is_the_tent_demosaic_through_the_runs_optics(run):
    """`--method doe-tent-demosaic` is the weighted-bilinear demosaic of the run's own captures
    (camera_demosaic with kernel tent), not the box one; like the box it needs a run."""
    import torch

    from hsicam.config import load_config
    from hsicam.engine.methods import build_method
    from hsicam.errors import InputError
    from hsicam.models.demosaic import camera_demosaic

    cfg = load_config(run / "config.yaml")
    tent, box = (build_method(m, cfg, run) for m in ("doe-tent-demosaic", "doe-box-demosaic"))
    assert tent.name.startswith("CFA tent demosaic") and tent.info == {"run": str(run)}
    scene = torch.rand(1, len(tent.camera.bands), 48, 48, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        y = tent.camera(scene)
        got = tent.reconstruct(y)
        torch.testing.assert_close(got, camera_demosaic(tent.camera, y, kernel="tent"))
        assert (got - box.reconstruct(y)).abs().max() > 1e-4
    with pytest.raises(InputError, match="needs --run"):
        build_method("doe-tent-demosaic", cfg)


def test_evaluate_on_a_folder_of_files(run, env, tmp_path):
    data = tmp_path / "data"
    rng = np.random.default_rng(0)
    for i in range(2):
        write_cube_h5(data / f"s{i}.h5", rng.uniform(0.1, 1, (7, 48, 52)).astype(np.float32), Bands.uniform(420, 720, 50))
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "ev"), env=env)
    assert res.returncode == 0, res.stderr
    summary = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert [r["name"] for r in summary["scenes"]] == ["s0", "s1"]


def test_evaluate_bad_input(run, env, tmp_path):
    nowt = tmp_path / "noweights"
    shutil.copytree(run, nowt)
    (nowt / "model.safetensors").unlink()
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(nowt), "--out", str(tmp_path / "o"), env=env), "no trained weights")
    data = tmp_path / "other_grid"
    write_cube_h5(data / "a.h5", np.ones((7, 48, 48), np.float32), Bands.uniform(400, 700, 50))  # does not reach 720 nm
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "o"), env=env), "720")
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(tmp_path / "missing"), "--out", str(tmp_path / "o"), env=env), "no such run")
    assert not (tmp_path / "o" / "results.json").exists()


def test_data_outside_a_trained_runs_bands_asks_for_other_data_not_another_grid(run, env, tmp_path):
    """400-700 nm cubes against a run trained on 420-720 nm: with --run the error says the run's
    bands are fixed (its grid cannot be changed with --set bands.*); training keeps the grid hint."""
    data = tmp_path / "d400"
    rng = np.random.default_rng(0)
    for i in range(2):  # two scenes: the run's split keeps one for validation
        write_cube_h5(data / f"s{i}.h5", rng.uniform(0.1, 1, (7, 48, 48)).astype(np.float32), Bands.uniform(400, 700, 50))
    for args in (("--set", f"data.root={data}"), ("--data", str(data))):
        res = run_cli_in_process("evaluate", "--run", str(run), *args, "--out", str(tmp_path / "o"), env=env)
        assert_clean_error(res, "the run's bands 420-720 nm", "data's 400-700 nm", "fixed by its training",
                           "data that covers 420-720 nm", "train a new camera on a band grid inside 400-700 nm")
        assert "use a camera band grid" not in res.stderr
    assert not (tmp_path / "o" / "results.json").exists()
    resumed = tmp_path / "resumed"
    shutil.copytree(run, resumed)
    res = run_cli_in_process("train", "--out", str(resumed), "--resume", "--set", f"data.root={data}", "--set", "train.epochs=9",
                             env=env)
    # a synthetic run resumed on a folder of scenes: refused as another run's data before its bands are looked at
    assert_clean_error(res, "not its bands, camera, network, scenes or split: data.root: None →")
    res = run_cli_in_process("train", "--config", "tiny", "--set", f"data.root={data}", "--out", str(tmp_path / "new"), env=env)
    assert_clean_error(res, "the camera's bands 420-720 nm", "use a camera band grid inside 400-700 nm")
    assert not (tmp_path / "new").exists()


def evaluate_mean(monkeypatch, env, run, out, *options) -> dict:
    """``hsicam evaluate --run RUN --out OUT OPTIONS`` (in this process, with the module's data cache):
    the mean row of its results.json."""
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), *options)
    assert res.returncode == 0, res.stderr
    return json.loads((out / "results.json").read_text())["mean"]


def test_experiment_ablation_tiny_is_resumable(env, tmp_path, monkeypatch):
    out = tmp_path / "abl"
    res = run_cli_in_process("experiment", "ablation", "--scale", "tiny", "--out", str(out), env=env)
    assert res.returncode == 0, res.stderr
    exp = json.loads((out / "experiment.json").read_text())
    # each scored scene of each camera is a k/N line on stderr (a slow method is not silent)
    n = len(exp["rows"][0]["scenes"])
    for m in ("doe+cfa", "no-doe", "no-cfa"):
        assert re.findall(rf"^experiment: {re.escape(m)} \[(\d+)/(\d+)\] ", res.stderr, re.M) == \
            [(str(k), str(n)) for k in range(1, n + 1)], res.stderr
    assert "experiment: " not in res.stdout
    assert [r["method"] for r in exp["rows"]] == ["doe+cfa", "no-doe", "no-cfa"]
    assert all(np.isfinite(r["psnr"]) for r in exp["rows"])
    # each row is its own camera: `hsicam evaluate` of that run (same validation scenes, the run's noise, seed 0)
    for r in exp["rows"]:
        run = out / "runs" / r["method"]
        mean = evaluate_mean(monkeypatch, env, run, tmp_path / f"ev-{r['method']}")
        for k in ("psnr", "ssim", "sam"):
            assert r[k] == pytest.approx(mean[k], rel=1e-6), (r["method"], k)
        assert r["run"] == str(run)
        # the weights scored, as evaluate records them (the report draws a run's camera only while they are these)
        assert r["weights_sha256"] == json.loads((tmp_path / f"ev-{r['method']}" / "results.json").read_text())[
            "weights_sha256"] == hashlib.sha256((run / "model.safetensors").read_bytes()).hexdigest()
        assert r["weights"]["checkpoint"] in ("best", "last")
    assert len({round(r["psnr"], 6) for r in exp["rows"]}) == 3  # three different cameras
    assert "| no-doe |" in (out / "table.md").read_text()
    from hsicam.config import load_config

    assert load_config(out / "runs" / "no-doe" / "config.yaml").camera.doe.enabled is False
    stamp = (out / "runs" / "no-cfa" / "model.safetensors").stat().st_mtime_ns
    again = run_cli_in_process("experiment", "ablation", "--scale", "tiny", "--out", str(out), env=env)
    assert again.returncode == 0, again.stderr
    assert (out / "runs" / "no-cfa" / "model.safetensors").stat().st_mtime_ns == stamp  # finished runs are skipped
    assert json.loads((out / "experiment.json").read_text())["rows"][0]["psnr"] == pytest.approx(exp["rows"][0]["psnr"])


def test_experiment_noise_grid_and_report(env, tmp_path, monkeypatch):
    out = tmp_path / "noise"
    res = run_cli_in_process("experiment", "noise", "--scale", "tiny", "--out", str(out), env=env)
    assert res.returncode == 0, res.stderr
    exp = json.loads((out / "experiment.json").read_text())
    grid = exp["noise_grid"]
    assert grid["sigma_height_nm"] == [0, 15, 30, 45, 60] and grid["sensor_sigma"] == [0, 0.0025, 0.005, 0.0075, 0.01]
    for name in ("trained-clean", "trained-noisy"):
        g = grid["results"][name]
        assert len(g) == 25
        clean = next(x for x in g if x["sigma_height_nm"] == 0 and x["sensor_sigma"] == 0)
        worst = next(x for x in g if x["sigma_height_nm"] == 60 and x["sensor_sigma"] == 0.01)
        assert worst["psnr"] < clean["psnr"]  # noise at test time costs quality
        # the table's row: the noise-free cell, and the worst over the grid (not its last cell, not its best)
        row = next(r for r in exp["rows"] if r["method"] == name)
        assert (row["psnr"], row["ssim"]) == (clean["psnr"], clean["ssim"])
        assert (row["psnr_worst"], row["ssim_worst"]) == (min(x["psnr"] for x in g), min(x["ssim"] for x in g))
        # an off-axis cell is `hsicam evaluate` of that camera with that test noise and seed count
        cell = next(x for x in g if x["sigma_height_nm"] == 60 and x["sensor_sigma"] == 0)
        mean = evaluate_mean(monkeypatch, env, out / "runs" / name, tmp_path / f"ev-{name}", "--sigma-height-nm", "60",
                             "--sensor-sigma", "0", "--seeds", str(len(exp["seeds"])))
        assert cell["psnr"] == pytest.approx(mean["psnr"], rel=1e-6), name
        assert cell["ssim"] == pytest.approx(mean["ssim"], rel=1e-6), name
        assert abs(cell["psnr"] - clean["psnr"]) > 1e-3, name
    rep = run_cli_in_process("report", str(out), env=env)
    assert rep.returncode == 0, rep.stderr
    page = (out / "report" / "index.html").read_text()
    assert "noise_grid.png" in page and (out / "report" / "noise_grid.png").is_file()
    assert f"scored area: the DOE cameras' {html.escape(exp['region'])}</p>" in page


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _browser_or_skip() -> str:
    """The headless browser; without one the test is skipped locally but fails under CI=true
    (.ci/run installs the Debian package chromium where it can, so CI never silently skips it)."""
    browser = _chromium()
    if browser is None:
        if os.environ.get("CI", "").strip().lower() in ("1", "true", "yes"):
            pytest.fail("CI=true but no Chromium was found (chromium, chromium-browser, google-chrome): the report's "
                        "browser test must run in CI; install the Debian package chromium (.ci/run does when it can)")
        pytest.skip("Chromium is not installed (apt-get install chromium) — browser rendering not checked")
    return browser


def test_browser_is_required_in_ci(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI=true"):
        _browser_or_skip()
    monkeypatch.setenv("CI", "")
    with pytest.raises(pytest.skip.Exception):
        _browser_or_skip()
    monkeypatch.setattr(shutil, "which", lambda name: "/usr/bin/chromium" if name == "chromium" else None)
    monkeypatch.setenv("CI", "true")
    assert _browser_or_skip() == "/usr/bin/chromium"


def test_report_renders_in_headless_chromium(run, env, tmp_path):
    out = tmp_path / "ev"
    assert run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), "--save", env=env).returncode == 0
    rep = run_cli_in_process("report", str(out), env=env)
    assert rep.returncode == 0, rep.stderr
    index = out / "report" / "index.html"
    page = index.read_text()
    srcs = [s.split("'")[0] for s in page.split("src='")[1:]]
    assert len(srcs) >= 5 and all((index.parent / s).is_file() for s in srcs)  # relative, present
    assert not any(s.startswith(("/", "http")) for s in srcs)
    browser = _browser_or_skip()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'ud'}", "--virtual-time-budget=10000", "--window-size=1200,2000"]
    dom = subprocess.run([browser, *flags, "--dump-dom", index.as_uri()], capture_output=True, text=True, timeout=120)
    assert f'data-images="report-ok {len(srcs)}"' in dom.stdout, dom.stdout[-2000:]
    shot = tmp_path / "shot.png"
    subprocess.run([browser, *flags, f"--screenshot={shot}", index.as_uri()], capture_output=True, timeout=120)
    import imageio.v3 as iio

    img = iio.imread(shot)
    assert img.shape[0] >= 1000 and img.std() > 5  # a rendered page, not a blank one


def test_report_of_a_run_whose_training_log_is_damaged_says_so_in_the_page(run, env, tmp_path):
    """The evaluated run's metrics.jsonl cut mid-line: the report is written, and where the training curves
    would be it says that the run's log is damaged (the results.json is sound and is not blamed)."""
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    out = tmp_path / "ev"
    assert run_cli_in_process("evaluate", "--run", str(copy), "--out", str(out), env=env).returncode == 0
    log = copy / "metrics.jsonl"
    log.write_text(log.read_text() + '{"step": 9, "train_lo')
    rep = run_cli_in_process("report", str(out), env=env)
    assert rep.returncode == 0, rep.stderr
    page = (out / "report" / "index.html").read_text()
    assert f"training curves unavailable: {log} is damaged (JSONDecodeError" in page
    assert not (out / "report" / "training.png").exists() and (out / "report" / "psf.png").is_file()


def test_report_bad_folder(tmp_path):
    assert_clean_error(run_cli_in_process("report", str(tmp_path)), "results.json")


@pytest.mark.parametrize("kind", ["mosaic", "unrolled", "rdn"])
def test_ablation_without_cfa_keeps_the_network(kind):
    """The no-CFA run differs from the full camera in its optics only: the same network (a mosaic
    front end keeps regrouping by the preset's CFA period instead of falling back to 3 × 3)."""
    from hsicam.config import load_config
    from hsicam.engine.experiments import run_specs
    from hsicam.models import CameraSystem

    # factor 0: the front end regroups by the CFA period (4 in quick), which the ablation must pin
    base = [f"model.kind={kind}", "model.unrolled.init=mosaic", "model.mosaic.factor=0", "model.unrolled.mosaic.factor=0"]
    cfg = load_config("quick", base)
    spec = {s.name: s for s in run_specs("ablation", cfg)}["no-cfa"]
    full = CameraSystem.from_config(cfg)
    ablated = CameraSystem.from_config(load_config("quick", [*base, *spec.overrides]))
    assert full.camera.code_period == 4 and ablated.camera.code_period == 1  # the CFA is off
    shapes = lambda m: [tuple(p.shape) for p in m.net.parameters()]  # noqa: E731
    assert shapes(ablated) == shapes(full)
    explicit = load_config("quick", [f"model.kind={kind}", "model.unrolled.init=mosaic"])  # quick's factor 8
    assert not {s.name: s for s in run_specs("ablation", explicit)}["no-cfa"].overrides[1:]  # nothing to pin
    if kind != "rdn":
        assert any("factor=4" in o for o in spec.overrides)
        # without the pinned factor the network would be another one (regrouped by 3)
        other = CameraSystem.from_config(load_config("quick", [*base, "camera.cfa.enabled=false"]))
        assert shapes(other) != shapes(full)


def test_sam_breakdown_script_on_a_trained_run(run, env, tmp_path):
    """scripts/sam_breakdown.py prints one row per validation scene and a mean whose SAM is the
    evaluation's; a missing run is one clear error."""
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "sam_breakdown.py"
    full_env = {**os.environ, **env}
    proc = subprocess.run([sys.executable, str(script), str(run)], capture_output=True, text=True, env=full_env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| ") and not line.startswith("| scene |")]
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), env=env)
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "results.json").read_text())
    assert len(rows) == len(summary["scenes"]) + 1
    mean_sam = float(rows[-1].split("|")[2].strip().rstrip("°"))
    assert mean_sam == pytest.approx(summary["mean"]["sam"], abs=0.006)
    bad = subprocess.run([sys.executable, str(script), str(tmp_path / "nope")], capture_output=True, text=True, env=full_env)
    assert bad.returncode == 2 and "no such run folder" in bad.stderr and "Traceback" not in bad.stderr


def test_report_shows_the_heldout_sources_results(run, env, tmp_path):
    """Probe 26 #1: results.json and results.md held the held-out-sources scores, the HTML report
    only the validation table."""
    out = tmp_path / "ev"
    assert run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), env=env).returncode == 0
    res = json.loads((out / "results.json").read_text())
    held = res["heldout"]
    assert held["scenes"]
    rep = run_cli_in_process("report", str(out), env=env)
    assert rep.returncode == 0, rep.stderr
    page = (out / "report" / "index.html").read_text()
    head, _, tail = page.partition("<h2>Held-out spectral sources</h2>")
    assert tail, "no held-out section"
    for scene in held["scenes"]:
        assert f"<td>{scene['name']}</td>" in tail and f"<td>{scene['psnr']:.2f}</td>" in tail
    assert f"<td>{held['mean']['psnr']:.2f}</td>" in tail
    assert f"<td>{res['mean']['psnr']:.2f}</td>" in head  # the validation mean stays in its own table
    assert f"scored area: {html.escape(res['region'])}" in head  # which pixels the scores cover, as results.json says
    # an evaluation without --save has no cubes to render: the page says so (its section was silently missing)
    assert ("<h2>Reconstructions</h2><p class='note'>None shown: the evaluation saved no cubes (run "
            "<code>hsicam evaluate … --save</code>") in page


def test_a_reconstruction_with_nan_is_refused_not_scored(run):
    """A method whose reconstruction holds NaN (a broken solver or network) is one clear error: scored,
    clipping kept the NaN and the metrics read it as an infinite PSNR, the best score there is."""
    import dataclasses

    import torch

    from hsicam.config import load_config
    from hsicam.engine.evaluate import evaluate_method
    from hsicam.engine.methods import build_method
    from hsicam.errors import InputError

    box = build_method("doe-box-demosaic", load_config(run / "config.yaml"), run)

    def broken(sensor):
        out = box.reconstruct(sensor)
        out[..., 0, 0] = float("nan")
        return out

    scene = torch.rand(len(box.camera.bands), 48, 48, generator=torch.Generator().manual_seed(3))
    with pytest.raises(InputError, match=r"s0: the CFA box demosaic \(no network\) reconstruction holds 7 non-finite"):
        evaluate_method(dataclasses.replace(box, reconstruct=broken), [scene], ["s0"])
    assert evaluate_method(box, [scene], ["s0"])[0].metrics["psnr"] < 100  # the method itself scores


def test_scored_region_names_a_crop_only_where_the_camera_has_a_kernel_margin():
    """results.json's ``region``: a DOE camera with boundary 'valid' scores its sensor area (the scene
    minus its kernel margin); a CASSI camera has no PSF, so 'valid' (the dd_cassi_rdn preset's) crops
    nothing and the whole scene is scored, as the sensor image's size shows."""
    from hsicam.cameras.registry import build_camera
    from hsicam.config import load_config
    from hsicam.engine.evaluate import scored_region

    doe = build_camera(load_config("tiny", ["camera.boundary=valid"]))
    assert doe.margin > 0 and scored_region(doe).startswith("sensor area")
    # in pixels: the sensor image of a 40×48 scene is (40 − K + 1)×(48 − K + 1), K the kernel (odd: K//2 a side)
    k = doe.kernel_px
    with torch.no_grad():
        g = doe(torch.rand(1, len(doe.bands), 40, 48))
    assert tuple(g.shape[-2:]) == (40 - k + 1, 48 - k + 1)
    assert f"{k // 2} px a side" in scored_region(doe) and f"(H − {k - 1})×(W − {k - 1}) px" in scored_region(doe)
    cassi = build_camera(load_config("dd_cassi_rdn", ["data.synthetic_size=32"]))
    assert cassi.boundary == "valid" and cassi.margin == 0
    with torch.no_grad():
        g = cassi(torch.rand(1, len(cassi.bands), 32, 32))
    assert tuple(g.shape[-2:]) == (32, 32)  # nothing cropped
    assert scored_region(cassi).startswith("whole scene")


def test_each_scene_gets_its_own_capture_noise_and_every_method_the_same(run):
    """Under one noise seed, two scenes of the same size are captured with different sensor noise (one
    field for all once correlated their errors), the same scene gets the same noise whichever method is
    scored, and the DOE height draw (σ_p) is one element's for every scene: checked by re-imaging with the
    generators evaluate documents (``capture_noise_seed``)."""
    import dataclasses

    import torch

    from hsicam.config import load_config
    from hsicam.engine.evaluate import TestNoise, capture_noise_seed, evaluate_method
    from hsicam.engine.methods import build_method

    cfg = load_config(run / "config.yaml", ["camera.sensor.noise=poisson_gaussian", "camera.sensor.full_well_e=30"])
    box, learned = (build_method(m, cfg, run) for m in ("doe-box-demosaic", "doe-learned"))
    scene = torch.rand(len(box.camera.bands), 48, 48, generator=torch.Generator().manual_seed(3))
    captures: dict[tuple[str, str], torch.Tensor] = {}

    def recording(method):
        def fn(sensor):
            captures[(method.name, f"s{sum(k[0] == method.name for k in captures)}")] = sensor.clone()
            return method.reconstruct(sensor)
        return dataclasses.replace(method, reconstruct=fn, model=None)

    noise = TestNoise(sigma_height_nm=5.0, seeds=(7,))
    for m in (box, learned):
        evaluate_method(recording(m), [scene, scene], ["s0", "s1"], noise, keep_arrays=False)
    b, l = box.name, learned.name
    assert (captures[(b, "s0")] - captures[(b, "s1")]).abs().mean() > 1e-3  # the same scene, two captures' noise
    for s in ("s0", "s1"):
        torch.testing.assert_close(captures[(b, s)], captures[(l, s)], rtol=0, atol=0)
    # what evaluate imaged: one σ_p draw from the seed, each scene's sensor noise from (seed, name)
    cam = box.camera
    levels = cam.noise_levels()
    cam.set_noise(**{**levels, "sigma_height_nm": 5.0})
    try:
        with torch.no_grad():
            for s in ("s0", "s1"):
                expect = cam(scene[None], torch.Generator().manual_seed(7),
                             sensor_generator=torch.Generator().manual_seed(capture_noise_seed(7, s)))
                torch.testing.assert_close(captures[(b, s)], expect, rtol=0, atol=0)
            other_element = cam(scene[None], torch.Generator().manual_seed(8),
                                sensor_generator=torch.Generator().manual_seed(capture_noise_seed(7, "s0")))
    finally:
        cam.set_noise(**levels)
    assert (other_element - captures[(b, "s0")]).abs().max() > 0  # σ_p was drawn (another seed, another element)


def test_each_scored_scene_records_the_size_of_its_scored_area():
    """results.json rows carry ``scored_px``, [H, W] of the area the metrics cover: a DOE camera's sensor area (the
    scene less K − 1 px per axis, the sensor image's own size) and, for a method leaving ``border_px`` out, less
    that a side."""
    import dataclasses

    from hsicam.cameras.registry import build_camera
    from hsicam.config import load_config
    from hsicam.engine.evaluate import evaluate_method, summarize
    from hsicam.engine.methods import Method

    cam = build_camera(load_config("tiny", ["camera.boundary=valid"]))
    k = cam.kernel_px
    scene = torch.rand(len(cam.bands), 40 + k - 1, 44 + k - 1)

    def flat(y):  # a sensor-sized estimate: the sensor image in every band
        return y.expand(-1, len(cam.bands), -1, -1).clamp(0, 1)

    r = (k - 1) // 2
    method = Method("flat", cam, flat, lambda x: x[..., r:-r, r:-r])  # the sensor-aligned crop, written out here
    rows = summarize(evaluate_method(method, [scene], ["s0"]))["scenes"]
    assert rows[0]["scored_px"] == [40, 44]
    bordered = dataclasses.replace(method, border_px=3)
    rows = summarize(evaluate_method(bordered, [scene], ["s0"]))["scenes"]
    assert rows[0]["scored_px"] == [34, 38]
