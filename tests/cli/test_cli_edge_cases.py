"""Mutation guards of the command-line floor (``hsicam.cli.*``): each test pins a behaviour that a small
change of the code (a bound, a forwarded option, a default) broke without any other test noticing. The
engine is replaced by a recorder where the test is about what the command line hands it."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process


class Received(Exception):
    """Raised by a recording stand-in of an engine function: the command stops there."""


def record(store: dict):
    def fake(*args, **kwargs):
        store["args"], store["kwargs"] = args, kwargs
        raise Received
    return fake


# -- args.py ----------------------------------------------------------------------------------------------

def test_counts_take_their_maximum_and_refuse_one_more():
    from hsicam.cli.args import MAX_DRAWS, MAX_SEEDS, draws_arg, seeds_arg

    assert seeds_arg(str(MAX_SEEDS)) == MAX_SEEDS
    assert draws_arg(str(MAX_DRAWS)) == MAX_DRAWS
    for parse, most in ((seeds_arg, MAX_SEEDS), (draws_arg, MAX_DRAWS)):
        with pytest.raises(argparse.ArgumentTypeError, match=f"must be at most {most} "):
            parse(str(most + 1))


def test_a_seed_above_the_commands_own_bound_is_a_usage_error(tmp_path):
    from hsicam.config import TOLERANCE_SEED_MAX

    res = run_cli_in_process("tolerance", "--run", "pretrained:standard", "--out", tmp_path / "t",
                             "--seed", str(TOLERANCE_SEED_MAX + 1))
    line = error_line(res)
    assert line.startswith("hsicam: error: argument --seed: ")
    assert not (tmp_path / "t").exists()


def test_the_bounds_of_noise_and_weight_options_are_inclusive():
    from hsicam.cli.args import sensor_sigma_arg, sigma_height_arg, tv_weight_arg
    from hsicam.config import MAX_SENSOR_SIGMA, MAX_SIGMA_HEIGHT_NM, MAX_TV_WEIGHT, MIN_TV_WEIGHT

    assert sensor_sigma_arg("0") == 0.0 and sensor_sigma_arg(repr(MAX_SENSOR_SIGMA)) == MAX_SENSOR_SIGMA
    assert sigma_height_arg("0") == 0.0 and sigma_height_arg(repr(MAX_SIGMA_HEIGHT_NM)) == MAX_SIGMA_HEIGHT_NM
    assert tv_weight_arg(repr(MIN_TV_WEIGHT)) == MIN_TV_WEIGHT and tv_weight_arg(repr(MAX_TV_WEIGHT)) == MAX_TV_WEIGHT


# -- train.py ---------------------------------------------------------------------------------------------

def test_train_summary_line_says_throughput_and_every_metric():
    from hsicam.cli.train import summary_line

    s = {"epoch": 2, "step": 1, "patches_per_s": 12.345, "val_psnr": 30.123, "val_ssim": 0.98765, "val_sam": 3.456}
    assert summary_line(s, "RUN") == ("trained 2 epochs (1 step, 12.3 patches/s): val PSNR 30.12 dB, SSIM 0.9877, "
                                      "SAM 3.46° -> RUN")


def test_train_resume_refuses_a_config_it_would_ignore(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    line = error_line(run_cli_in_process("train", "--out", run, "--resume", "--config", "tiny"))
    assert line == ("hsicam: error: --resume continues with the run's own config.yaml; drop --config (use --set to "
                    "change keys)")
    assert list(run.iterdir()) == []


# -- reconstruct.py ---------------------------------------------------------------------------------------

def test_a_cfa_offset_shifts_rows_by_y_and_columns_by_x():
    from hsicam.cli.reconstruct import offset_reconstructor

    seen = []

    def fn(sensor, origin=(0, 0)):
        seen.append(origin)
        return sensor

    fn.context_px = 3
    shifted = offset_reconstructor(fn, (1, 2))
    shifted(None, (10, 20))
    shifted(None)
    assert seen == [(11, 22), (1, 2)] and shifted.context_px == 3


def test_a_cfa_flat_is_averaged_over_the_runs_cfa_period(tmp_path):
    from hsicam.cli.reconstruct import corrections_from_args

    np.save(tmp_path / "flat.npy", np.ones((8, 8), np.float32))
    args = argparse.Namespace(dark=None, flat=str(tmp_path / "flat.npy"), flat_mode="cfa", black_level=None,
                              white_level=None, exposure_s=None, reference_exposure_s=None, auto_level=None)
    assert corrections_from_args(args, 4).flat_period == 4
    assert corrections_from_args(args, None).flat_period == 1  # no CFA: the flat as it is
    assert corrections_from_args(argparse.Namespace(**{**vars(args), "flat_mode": "pixel"}), 4).flat_period is None


def test_a_cfa_offset_below_zero_in_either_coordinate_is_a_usage_error():
    from hsicam.cli.reconstruct import cfa_offset_arg

    assert cfa_offset_arg("0,0") == (0, 0) and cfa_offset_arg("2, 3") == (2, 3)
    for text in ("-1,0", "0,-1"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"Y and X must be >= 0, got '{text}'"):
            cfa_offset_arg(text)


def test_reconstruct_takes_a_read_noise_of_zero_and_refuses_a_gain_of_zero(tmp_path):
    from hsicam.cli.reconstruct import check_noise_args

    check_noise_args(argparse.Namespace(full_well_e=100.0, read_noise_e=0.0))  # shot noise alone: accepted
    np.save(tmp_path / "s.npy", np.full((16, 16), 0.5, np.float32))
    line = error_line(run_cli_in_process("reconstruct", tmp_path / "s.npy", "--run", "pretrained:standard",
                                         "--out", tmp_path / "c.h5", "--scale", "0"))
    assert line == "hsicam: error: --scale must be a positive number"
    assert not (tmp_path / "c.h5").exists()


def _read_cube(path):
    import h5py

    with h5py.File(path, "r") as f:
        return f["cube"][()], json.loads(f.attrs["metadata_json"])


def test_reconstruct_clips_negative_radiance_at_zero(tmp_path):
    import torch

    from hsicam.runs.folder import load_run

    sensor = np.random.default_rng(0).random((48, 48)).astype(np.float32)  # a noisy capture: negative excursions
    np.save(tmp_path / "s.npy", sensor)
    res = run_cli_in_process("reconstruct", tmp_path / "s.npy", "--run", "pretrained:standard", "--out", tmp_path / "c.h5")
    assert res.returncode == 0, res.stderr
    cube, _ = _read_cube(tmp_path / "c.h5")
    _, model = load_run("pretrained:standard")
    with torch.no_grad():
        raw = model.eval().reconstructor()(torch.from_numpy(sensor)[None, None])[0].numpy()
    assert raw.min() < -0.01  # the network's own estimate goes below 0 here
    np.testing.assert_allclose(cube, np.maximum(raw, 0), rtol=1e-5, atol=1e-6)


def test_a_cube_records_no_consistency_steps_when_the_camera_skips_them(tmp_path, monkeypatch):
    from hsicam.models import CameraSystem

    np.save(tmp_path / "s.npy", np.full((24, 24), 0.3, np.float32))
    res = run_cli_in_process("reconstruct", tmp_path / "s.npy", "--run", "pretrained:standard", "--out", tmp_path / "on.h5")
    assert res.returncode == 0, res.stderr
    assert _read_cube(tmp_path / "on.h5")[1]["consistency_steps"] >= 1  # the run's steps, taken
    # a camera whose steps are skipped (as SD-CASSI's): the run's config keeps its steps, the cube took none
    monkeypatch.setattr(CameraSystem, "consistency_on", property(lambda self: False))
    res = run_cli_in_process("reconstruct", tmp_path / "s.npy", "--run", "pretrained:standard", "--out", tmp_path / "off.h5")
    assert res.returncode == 0, res.stderr
    meta = _read_cube(tmp_path / "off.h5")[1]
    assert meta["consistency_steps"] == 0 and "consistency_landweber_after" not in meta


def _bare_run(folder, *overrides):
    """An untrained camera of the tiny config with ``overrides``, saved as a run folder (config and weights)."""
    from hsicam.config import dump_yaml, load_config
    from hsicam.models import CameraSystem
    from hsicam.runs.checkpoint import save_weights

    from conftest import TINY_CAMERA_OVERRIDES

    folder.mkdir()
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, *overrides])
    (folder / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    model = CameraSystem.from_config(cfg)
    save_weights(folder / "model.safetensors", model, model.bands)
    return folder


def test_a_capture_thinner_than_two_pixels_is_refused_without_a_cfa(tmp_path):
    run = _bare_run(tmp_path / "nocfa", "camera.cfa.enabled=false")
    np.save(tmp_path / "thin.npy", np.full((1, 40), 0.5, np.float32))
    line = error_line(run_cli_in_process("reconstruct", tmp_path / "thin.npy", "--run", run, "--out", tmp_path / "t.h5"))
    assert line == (f"hsicam: error: {tmp_path / 'thin.npy'}: the capture is 1×40 px, smaller than a 2×2 image "
                    "(2×2 px): too small to reconstruct")
    assert not (tmp_path / "t.h5").exists()


# -- evaluate.py ------------------------------------------------------------------------------------------

def test_evaluate_hands_the_engine_its_noise_seeds_and_tile(tmp_path, monkeypatch):
    import hsicam.engine.evaluate as ev
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    data = tmp_path / "data"
    data.mkdir()
    bands = Bands.paper()
    write_cube_h5(data / "a.h5", np.full((len(bands), 160, 160), 0.5, np.float32), bands)
    got: dict = {}
    monkeypatch.setattr(ev, "evaluate_method", record(got))
    with pytest.raises(Received):
        run_cli_in_process("evaluate", "--run", "pretrained:standard", "--data", data,
                           "--out", tmp_path / "ev", "--sensor-sigma", "0.01", "--sigma-height-nm", "5",
                           "--seeds", "3", "--tile", "40")
    noise = got["args"][3]
    assert (noise.sigma_height_nm, noise.sensor_sigma, tuple(noise.seeds)) == (5.0, 0.01, (0, 1, 2))
    assert got["kwargs"]["tile_px"] == 40


def test_evaluate_of_a_run_refuses_a_config_it_would_ignore(tmp_path, monkeypatch):
    import hsicam.engine.evaluate as ev
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    data = tmp_path / "data"
    data.mkdir()
    write_cube_h5(data / "a.h5", np.full((len(Bands.paper()), 32, 32), 0.5, np.float32), Bands.paper())
    monkeypatch.setattr(ev, "evaluate_method", record({}))  # never reached: the refusal comes first
    line = error_line(run_cli_in_process("evaluate", "--run", "pretrained:standard", "--config", "tiny",
                                         "--data", data, "--out", tmp_path / "ev"))
    assert line == "hsicam: error: --run uses the run's config.yaml; drop --config"


def test_experiment_writes_to_runs_experiments_name_scale_by_default(tmp_path, monkeypatch):
    import hsicam.engine.experiments as experiments

    got: dict = {}
    monkeypatch.setattr(experiments, "run_experiment", record(got))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(Received):
        run_cli_in_process("experiment", "ablation", "--scale", "tiny")
    name, scale, out = got["args"][:3]
    assert (name, scale) == ("ablation", "tiny")
    assert (tmp_path / out).resolve() == (tmp_path / "runs" / "experiments" / "ablation-tiny").resolve()


# -- camera.py --------------------------------------------------------------------------------------------

def _simulate(tmp_path, name, *extra):
    scene = tmp_path / "scene.npy"
    if not scene.exists():
        from hsicam.config import load_config

        n = len(load_config("tiny").bands.to_bands())
        np.save(scene, np.random.default_rng(0).uniform(0.1, 0.2, (n, 24, 24)).astype(np.float32))
    out = tmp_path / name
    res = run_cli_in_process("simulate", "--config", "tiny", "--scene", scene, "--out", out,
                             "--set", "camera.sensor.sigma=0.05", *extra)
    assert res.returncode == 0, res.stderr
    return out


def test_simulate_draws_its_noise_from_seed_and_records_it(tmp_path):
    a, b, a2 = (_simulate(tmp_path, n, "--seed", s) for n, s in (("a", "1"), ("b", "2"), ("a2", "1")))
    sa, sb, sa2 = (np.load(p / "sensor.npy") for p in (a, b, a2))
    assert np.array_equal(sa, sa2) and not np.array_equal(sa, sb)
    from hsicam.data.images import SIMULATE_JSON

    assert json.loads((b / SIMULATE_JSON).read_text())["seed"] == 2


def test_simulate_png_of_a_dim_sensor_image_is_not_stretched(tmp_path):
    from PIL import Image

    out = _simulate(tmp_path, "s", "--set", "camera.sensor.sigma=0")
    sensor = np.load(out / "sensor.npy")
    assert 0 < sensor.max() < 1.0
    png = np.asarray(Image.open(out / "sensor.png")).astype(np.float64) / 65535
    np.testing.assert_allclose(png, np.clip(sensor, 0, 1), atol=1 / 65535)


# -- fabrication.py ---------------------------------------------------------------------------------------

def test_tolerance_hands_the_engine_every_option(tmp_path, monkeypatch):
    import hsicam.engine.tolerance as tol

    got: dict = {}
    monkeypatch.setattr(tol, "run_tolerance", record(got))
    with pytest.raises(Received):
        run_cli_in_process("tolerance", "--run", "pretrained:standard", "--out", tmp_path / "t", "--draws", "7",
                           "--max-scenes", "2", "--seed", "5", "--shift-subsamples", "3", "--levels", "2,4",
                           "--sigma-height-nm", "0,15", "--shift-cells", "0,1", "--sensor-distance-um=-5,5")
    spec = got["args"][2]
    assert (spec.height_draws, spec.max_scenes, spec.seed, spec.shift_subsamples) == (7, 2, 5, 3)
    assert (tuple(spec.levels), tuple(spec.sigma_height_nm), tuple(spec.shift_cells),
            tuple(spec.sensor_distance_um)) == ((2, 4), (0.0, 15.0), (0.0, 1.0), (-5.0, 5.0))


@pytest.mark.parametrize("resume", [False, True])
def test_finetune_rate_is_a_tenth_of_the_runs_unless_resumed(tmp_path, monkeypatch, resume):
    import hsicam.engine.calibration as cal
    from hsicam.cli import run_folder
    from hsicam.config import load_config

    run_lr = load_config(run_folder("pretrained:standard") / "config.yaml").train.lr
    got: dict = {}
    monkeypatch.setattr(cal, "finetune", record(got))
    with pytest.raises(Received):
        run_cli_in_process("finetune", "--run", "pretrained:standard", "--psf-dir", tmp_path, "--out", tmp_path / "f",
                           *(["--resume"] if resume else []))
    rates = [o for o in got["kwargs"]["overrides"] if o.startswith("train.lr=")]
    if resume:
        assert rates == []  # a resume goes on with the rate it started with
    else:
        assert len(rates) == 1 and float(rates[0].split("=")[1]) == pytest.approx(0.1 * run_lr, rel=1e-6)


def test_a_tolerance_never_swept_is_said_so():
    from hsicam.cli.fabrication import _fmt

    # a null the sweep never reached is said with the range measured: a lower bound, not "beyond the swept range"
    assert (_fmt(None, "nm", not_swept=True), _fmt(None, "nm"), _fmt(12.34, "nm"), _fmt(None, "nm", swept_to=60.0)) == (
        "not swept", "not reached within the swept range", "12.3 nm", "not reached up to 60 nm")


def test_the_tolerance_line_names_the_range_swept_and_the_rows_that_scored_above_their_reference():
    """Every perturbation of a study on 2 scenes raised PSNR a little (levels 8: +0.14 dB) and the line said each
    tolerance was "beyond the swept range": it says what was measured now (not reached up to the largest value
    swept, per side of the sensor distance) and notes the rows above their reference (a shift's: the unshifted
    reference), whose size is the scatter of the scores."""
    from hsicam.cli.fabrication import _swept_to
    from hsicam.report.tolerance import above_reference_text

    result = {"scenes": ["a", "b"], "nominal": {"psnr": 30.0}, "shift_reference": {"psnr": 29.0},
              "sweeps": {"sensor_distance_um": {"values": [-50.0, -20.0, 0.0, 100.0]},
                         "sigma_height_nm": {"values": [0.0, 10.0, 40.0]}},
              "rows": [{"sweep": "sigma_height_nm", "value": 0.0, "psnr": 30.5},  # unperturbed: no gain counted
                       {"sweep": "sigma_height_nm", "value": 40.0, "psnr": 30.1},
                       {"sweep": "levels", "value": 8, "psnr": 30.14},
                       {"sweep": "levels", "value": 2, "psnr": 28.0},
                       {"sweep": "shift_x_cells", "value": 0.5, "psnr": 29.2},  # +0.2 over the shift reference
                       {"sweep": "sensor_distance_um", "value": 100.0, "psnr": 29.9}]}
    assert (_swept_to(result, "sensor_distance_um", "minus"), _swept_to(result, "sensor_distance_um", "plus"),
            _swept_to(result, "sigma_height_nm"), _swept_to(result, "levels")) == (50.0, 100.0, 40.0, None)
    assert above_reference_text(result) == (
        "3 of 5 perturbed rows scored above their reference (up to +0.20 dB, shift_x_cells 0.5): the scores of 2 "
        "scene(s) move by that much, so the 1-dB tolerances are uncertain by as much (--max-scenes scores more)")
    for r in result["rows"]:
        r["psnr"] = 20.0
    assert above_reference_text(result) == ""


def test_tolerance_refuses_an_empty_list_of_values(tmp_path, monkeypatch):
    import hsicam.engine.tolerance as tol

    monkeypatch.setattr(tol, "run_tolerance", record({}))  # never reached: the refusal comes first
    for opt in ("--levels", "--sigma-height-nm", "--shift-cells", "--sensor-distance-um"):
        line = error_line(run_cli_in_process("tolerance", "--run", "pretrained:standard", "--out", tmp_path / "t",
                                             f"{opt}="))
        assert line == f"hsicam: error: {opt} needs at least one value"
    assert not (tmp_path / "t").exists()


def test_tolerance_without_a_doe_refuses_draws_alone(tmp_path, monkeypatch):
    import hsicam.engine.tolerance as tol

    monkeypatch.setattr(tol, "run_tolerance", record({}))
    run = _bare_run(tmp_path / "nodoe", "camera.doe.enabled=false")
    line = error_line(run_cli_in_process("tolerance", "--run", run, "--out", tmp_path / "t", "--draws", "2"))
    assert line.startswith("hsicam: error: ") and "--draws" in line and "has no DOE (camera.doe.enabled: false)" in line


def test_finetune_refuses_zero_epochs_naming_its_option(tmp_path):
    line = error_line(run_cli_in_process("finetune", "--run", "pretrained:standard", "--psf-dir", tmp_path,
                                         "--out", tmp_path / "f", "--epochs", "0"))
    assert line == "hsicam: error: --epochs must be >= 1"
    assert not (tmp_path / "f").exists()


# -- data.py ----------------------------------------------------------------------------------------------

def test_data_synth_hands_the_generator_its_options(tmp_path, monkeypatch):
    import hsicam.data.synthetic as syn

    got: dict = {}
    monkeypatch.setattr(syn, "generate_dataset", record(got))
    with pytest.raises(Received):
        run_cli_in_process("data", "synth", "--config", "tiny", "--split", "heldout", "--seed", "17", "--size", "16",
                           "--holdout-sources", "cie-a", "--out", tmp_path / "d", "--no-progress")
    kw = got["kwargs"]
    assert (kw["n"], kw["size"], kw["seed"], kw["split"], tuple(kw["holdout_sources"])) == (
        syn.HELDOUT_N, 16, 17, "heldout", ("cie-a",))


def test_data_synth_refuses_scenes_below_16_px(tmp_path):
    line = error_line(run_cli_in_process("data", "synth", "--config", "tiny", "--n", "1", "--size", "15",
                                         "--out", tmp_path / "d", "--no-progress"))
    assert line == "hsicam: error: --n must be >= 1 and --size >= 16, got 1 and 15"
    assert not (tmp_path / "d").exists()


# -- pretrained.py ----------------------------------------------------------------------------------------

def test_pretrained_pack_forwards_force(tmp_path, monkeypatch):
    import hsicam.engine.pretrained as pre

    for force in (False, True):
        got: dict = {}
        monkeypatch.setattr(pre, "pack_pretrained", record(got))
        with pytest.raises(Received):
            run_cli_in_process("pretrained", "pack", tmp_path, "--name", "x", *(["--force"] if force else []))
        assert got["kwargs"]["overwrite"] is force


def test_pretrained_show_takes_the_run_spelling(tmp_path):
    bare, prefixed = (run_cli_in_process("pretrained", "show", n) for n in ("standard", "pretrained:standard"))
    assert bare.returncode == prefixed.returncode == 0 and prefixed.stdout == bare.stdout


# -- demo.py ----------------------------------------------------------------------------------------------

def test_demo_says_whether_it_trains_or_resumes_its_run(tmp_path, monkeypatch, capsys):
    import hsicam.engine.demo as demo
    from hsicam.cli import main
    from hsicam.config import dump_yaml

    monkeypatch.setattr(demo, "run_demo", record({}))
    out = tmp_path / "demo"
    with pytest.raises(Received):
        main(["demo", "--config", "tiny", "--out", str(out)])
    assert capsys.readouterr().out.startswith(f"[demo] training the camera in {out / 'run'} (")
    (out / "run").mkdir(parents=True, exist_ok=True)  # a run started with this config, not finished
    (out / "run" / "config.yaml").write_text(dump_yaml(demo.demo_config("tiny", ())), encoding="utf-8")
    with pytest.raises(Received):
        main(["demo", "--config", "tiny", "--out", str(out)])
    assert capsys.readouterr().out.startswith(f"[demo] resuming the camera in {out / 'run'} (")


@pytest.mark.slow  # two PSF stacks of the 31-band camera: ~10 s on a 2-core CPU
def test_psf_refuses_the_config_a_psf_of_a_trained_run_wrote(tmp_path):
    trained = tmp_path / "trained"
    assert run_cli_in_process("psf", "--run", "pretrained:standard", "--out", trained).returncode == 0
    assert json.loads((trained / "psf.json").read_text())["source"]["run"] == "pretrained:standard"
    line = error_line(run_cli_in_process("psf", "--config", trained / "config.yaml", "--out", tmp_path / "again"))
    assert line == (f"hsicam: error: --config {trained / 'config.yaml'}: the config.yaml that hsicam psf wrote for the "
                    "trained camera pretrained:standard, whose DOE heights are in that run's weights; --config gives the "
                    "untrained design's camera: use `hsicam psf --run pretrained:standard --out DIR` for the trained camera "
                    "(the design before training: copy the config.yaml out of that folder first)")
    assert not (tmp_path / "again").exists()
    # a psf of a config (no run behind it) is that config's camera: its config.yaml gives it again
    design = tmp_path / "design"
    assert run_cli_in_process("psf", "--config", "tiny", "--out", design).returncode == 0
    assert run_cli_in_process("psf", "--config", design / "config.yaml", "--out", tmp_path / "design2").returncode == 0


@pytest.mark.slow  # one PSF stack of the 31-band camera: ~5 s on a 2-core CPU
def test_simulate_records_its_source_and_refuses_the_config_a_simulation_of_a_trained_run_wrote(tmp_path):
    """simulate.json records the run or config simulated; the config.yaml beside it, when a run's, is refused as
    --config (it would be the untrained design), and a config's own is taken again."""
    scene = tmp_path / "scene.npy"
    np.save(scene, np.full((31, 24, 24), 0.5, np.float32))
    trained = tmp_path / "trained"
    assert run_cli_in_process("simulate", "--run", "pretrained:standard", "--scene", scene, "--out", trained).returncode == 0
    assert json.loads((trained / "simulate.json").read_text())["source"] == {"run": "pretrained:standard"}
    line = error_line(run_cli_in_process("simulate", "--config", trained / "config.yaml", "--scene", scene,
                                         "--out", tmp_path / "again"))
    assert line == (f"hsicam: error: --config {trained / 'config.yaml'}: the config.yaml that hsicam simulate wrote for "
                    "the trained camera pretrained:standard, whose DOE heights are in that run's weights; --config gives "
                    "the untrained design's camera: use `hsicam simulate --run pretrained:standard --scene FILE --out DIR` "
                    "for the trained camera (the design before training: copy the config.yaml out of that folder first)")
    assert not (tmp_path / "again").exists()
    small = tmp_path / "small.npy"
    np.save(small, np.full((7, 24, 24), 0.5, np.float32))  # the tiny camera's 7 bands
    design = tmp_path / "design"
    assert run_cli_in_process("simulate", "--config", "tiny", "--scene", small, "--out", design).returncode == 0
    assert json.loads((design / "simulate.json").read_text())["source"] == {"config": "tiny"}
    assert run_cli_in_process("simulate", "--config", design / "config.yaml", "--scene", small,
                              "--out", tmp_path / "design2").returncode == 0
