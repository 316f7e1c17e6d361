"""Guards found by mutation testing of the methods registry, the experiments and the demo (session 56, mut5c):
each test kills a small change of the code that the rest of the suite let through, and checks against an
independent reference (a brute-force search, the camera's own image sizes, a file read back, the exact line a
user sees). Those of the reports are in report/test_report_edge_cases.py."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch

from hsicam.config import load_config
from hsicam.errors import InputError


# ------------------------------------------------------------------------------------------------
# methods
# ------------------------------------------------------------------------------------------------
def test_an_old_method_name_is_built_as_the_registered_method():
    """``doe-rdn`` (METHOD_ALIASES) reaches doe-learned's builder: its refusal without --run, not an unknown name."""
    from hsicam.engine.methods import build_method

    with pytest.raises(InputError) as err:
        build_method("doe-rdn", load_config("tiny"), None)
    assert str(err.value) == "method doe-learned needs --run RUN (a trained camera)"


def test_the_linear_reference_window_grows_to_the_smallest_odd_width_covering_the_cfa_period():
    from hsicam.engine.methods import LINEAR_REFERENCE_WINDOW, linear_reference_window

    for period in (1, 3, 4, 9, 11, 12, 14, 15, 20):
        # the smallest odd width >= the period, found by search, and at least the default window
        odd_cover = next(w for w in range(1, 100, 2) if w >= period)
        assert linear_reference_window(SimpleNamespace(code_period=period)) == max(LINEAR_REFERENCE_WINDOW, odd_cover)
    assert linear_reference_window(SimpleNamespace()) == LINEAR_REFERENCE_WINDOW  # no CFA: the default


def test_the_compared_border_is_half_the_difference_between_scene_and_sensor(tiny_config):
    """A CASSI row of a DOE ``valid`` config is scored without the px a side that the DOE camera's sensor
    does not see: measured by imaging a scene through that camera."""
    from hsicam.cameras import build_camera
    from hsicam.engine.methods import compared_border_px, sensor_border_px

    cfg = tiny_config("camera.boundary=valid")
    cam = build_camera(cfg)
    size = 40
    with torch.no_grad():
        sensor = cam.A(torch.rand(1, len(cam.bands), size, size))
    lost = size - sensor.shape[-1]
    assert lost > 0 and lost % 2 == 0
    assert compared_border_px(cfg) == sensor_border_px(cam) == lost // 2
    assert compared_border_px(tiny_config("camera.boundary=same")) == 0
    assert compared_border_px(load_config("tiny", ["camera.kind=dd_cassi", "model.consistency.iterations=0"])) == 0


def test_the_own_method_of_a_cassi_run_is_its_registered_name():
    from hsicam.engine.experiments import CASSI_RDN_OVERRIDES, CASSI_UNROLLED_OVERRIDES
    from hsicam.engine.methods import METHODS, own_learned_method

    assert own_learned_method(load_config("tiny")) == "doe-learned"
    assert own_learned_method(load_config("tiny", list(CASSI_RDN_OVERRIDES))) == "dd-cassi-rdn"
    assert own_learned_method(load_config("tiny", list(CASSI_UNROLLED_OVERRIDES))) == "dd-cassi-unrolled"
    assert {"dd-cassi-rdn", "dd-cassi-unrolled"} <= set(METHODS)


# ------------------------------------------------------------------------------------------------
# experiments: the sweeps' overrides
# ------------------------------------------------------------------------------------------------
def _overrides(spec) -> dict[str, str]:
    return dict(o.split("=", 1) for o in spec.overrides)


def test_the_cfa_sweep_keeps_a_dispersed_layout_exactly_when_every_period_is_a_power_of_two():
    from hsicam.engine.experiments import cfa_period_specs

    quick = load_config("quick")
    assert quick.camera.cfa.layout == "dispersed"
    powers = {2**i for i in range(10)}
    for periods in ((2, 4, 8), (4, 16), (1, 2), (3, 4), (4, 6), (2, 4, 7)):
        specs = cfa_period_specs(quick, periods)
        random = [_overrides(s).get("camera.cfa.layout") == "random" for s in specs]
        assert random == [not set(periods) <= powers] * len(periods), periods


def test_the_cfa_sweep_widens_the_linear_step_to_the_smallest_odd_width_over_every_period():
    from hsicam.engine.experiments import cfa_period_specs

    cfg = load_config("quick", ["model.consistency.window_px=5"])
    assert cfg.model.consistency.kind == "linear" and cfg.model.consistency.iterations > 0
    for periods in ((3, 6, 12), (4, 8), (3, 5), (2, 4)):
        want = next(w for w in range(cfg.model.consistency.window_px, 100, 2) if w >= max(periods))
        got = {_overrides(s).get("model.consistency.window_px") for s in cfa_period_specs(cfg, periods)}
        assert got == ({None} if want == 5 else {str(want)}), periods
    # without the step (iterations 0) its filters are not used: nothing is widened
    off = load_config("quick", ["model.consistency.window_px=5", "model.consistency.iterations=0"])
    assert all("model.consistency.window_px" not in _overrides(s) for s in cfa_period_specs(off, (3, 6, 12)))


def test_the_cfa_sweep_sets_the_mosaic_factor_to_the_nearest_multiple_of_each_period():
    from hsicam.engine.experiments import cfa_period_specs

    cfg = load_config("quick", ["model.mosaic.factor=4"])
    for m, spec in zip((3, 4, 6, 9, 15), cfa_period_specs(cfg, (3, 4, 6, 9, 15))):
        got = _overrides(spec).get("model.mosaic.factor")
        if 4 % m == 0:
            assert got is None, m  # already a multiple of the period: the preset's
            continue
        nearest = min((k * m for k in range(1, 20)), key=lambda f: abs(f - 4))  # brute force, at least m
        assert got == str(nearest), m
        assert f"model.mosaic.factor={nearest} (a multiple of the period near the preset's 4)" in spec.note


def test_the_ablation_pins_the_mosaic_factor_only_when_the_preset_lets_the_cfa_period_choose_it():
    from hsicam.engine.experiments import same_network_without_cfa

    assert same_network_without_cfa(load_config("quick")) == ()  # factor 8 given: kept without the CFA
    assert same_network_without_cfa(load_config("quick", ["model.mosaic.factor=0"])) == ("model.mosaic.factor=4",)
    assert same_network_without_cfa(load_config("quick", ["model.mosaic.factor=0", "camera.cfa.enabled=false"])) == ()
    assert same_network_without_cfa(None) == ()
    # a period-1 CFA regroups nothing: the no-CFA run keeps the network's own fallback, as the CFA run does
    assert same_network_without_cfa(load_config("quick", ["model.mosaic.factor=0", "camera.cfa.period=1"])) == ()
    assert same_network_without_cfa(load_config("quick", ["model.kind=unrolled", "model.unrolled.init=mosaic",
                                                          "model.unrolled.mosaic.factor=0"])) == (
        "model.unrolled.mosaic.factor=4",)


# ------------------------------------------------------------------------------------------------
# experiments: finished runs, test noise, folders, tables
# ------------------------------------------------------------------------------------------------
MEAN = {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}


def _run_folder(path, records, weights=True):
    path.mkdir(parents=True)
    (path / "config.yaml").write_text("{}\n")
    if weights:
        (path / "model.safetensors").write_bytes(b"")
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records) + "\n")
    return path


def test_a_run_is_finished_when_its_log_ends_with_its_final_record_and_it_has_its_weights(tmp_path):
    from hsicam.engine.experiments import is_finished

    assert is_finished(_run_folder(tmp_path / "a", [{"step": 1}, {"step": 2, "final": True}]))
    assert not is_finished(_run_folder(tmp_path / "b", [{"step": 2, "final": True}, {"step": 3}]))  # trained on since
    assert not is_finished(_run_folder(tmp_path / "c", [{"step": 1}, {"step": 2}]))
    assert not is_finished(_run_folder(tmp_path / "d", [{"step": 2, "final": True}], weights=False))


def test_test_noise_is_what_the_sensor_model_and_the_doe_add():
    from hsicam.engine.experiments import has_test_noise

    assert not has_test_noise(load_config("tiny", ["camera.sensor.noise=none", "camera.sensor.sigma=0.01"]))
    assert has_test_noise(load_config("tiny", ["camera.sensor.noise=gaussian", "camera.sensor.sigma=0.01"]))
    assert not has_test_noise(load_config("tiny", ["camera.sensor.noise=gaussian", "camera.sensor.sigma=0"]))
    assert has_test_noise(load_config("tiny", ["camera.sensor.sigma=0", "camera.doe.sigma_height_nm=10"]))


def test_the_noise_experiment_scores_every_seed_without_test_noise():
    from hsicam.engine.experiments import scored_seeds

    cfg = load_config("tiny", ["camera.sensor.sigma=0"])
    assert scored_seeds("noise", "tiny", cfg, (0, 1, 2)) == (0, 1, 2)  # its grid adds the noise
    assert scored_seeds("ablation", "tiny", cfg, (5, 1, 2)) == (5,)


def test_a_folder_of_other_runs_is_refused_naming_three_and_hidden_entries_are_ignored(tmp_path):
    from hsicam.engine.experiments import check_experiment_folder, run_configs

    cfgs = run_configs("ablation", "tiny")
    out = tmp_path / "abl"
    (out / "runs" / ".cache").mkdir(parents=True)
    check_experiment_folder(out, "ablation", "tiny", cfgs)  # a hidden entry is nobody's run
    for name in ("e", "d", "c", "b", "a"):
        (out / "runs" / name).mkdir()
    with pytest.raises(InputError) as err:
        check_experiment_folder(out, "ablation", "tiny", cfgs)
    assert str(err.value) == (f"{out / 'runs'}: holds a, b, c and 2 more, which experiment ablation does not train "
                              "(another experiment's runs); choose another --out (e.g. runs/experiments/ablation-tiny)")


def test_a_compare_folder_may_hold_its_choi_prior(tmp_path):
    from hsicam.engine.experiments import check_experiment_folder, run_configs

    out = tmp_path / "cmp"
    (out / "runs" / "dd-cassi-choi").mkdir(parents=True)
    check_experiment_folder(out, "compare", "tiny", run_configs("compare", "tiny"))  # no refusal


def test_an_interrupted_experiment_is_recognised_by_its_experiment_json(tmp_path):
    from hsicam.engine.experiments import recorded_experiment

    assert recorded_experiment(tmp_path) is None
    (tmp_path / "experiment.json").write_text(json.dumps({"experiment": "noise", "scale": "tiny"}))
    assert recorded_experiment(tmp_path) == ("noise", "tiny")


def _noise_result():
    from hsicam.engine.evaluate import summarize

    hs, ss = (0.0, 30.0), (0.0, 0.005, 0.01)
    grid = [{"sigma_height_nm": h, "sensor_sigma": s, "psnr": 40.0 - h / 10 - 100 * s, "ssim": 0.9}
            for h in hs for s in ss]
    return {"experiment": "noise", "scale": "tiny", "seeds": [0], "scenes": ["a"],
            "conventions": summarize([])["conventions"], "region": None,
            "rows": [{"method": "trained-clean", "psnr": 40.0, "ssim": 0.9, "psnr_worst": 36.0, "ssim_worst": 0.9}],
            "noise_grid": {"sigma_height_nm": list(hs), "sensor_sigma": list(ss), "results": {"trained-clean": grid}}}


def test_the_noise_table_has_a_row_per_height_noise_and_a_column_per_sensor_noise():
    from hsicam.engine.experiments import format_experiment_table

    lines = format_experiment_table(_noise_result()).splitlines()
    assert "| σ_p \\ σ_s | 0 | 0.005 | 0.01 |" in lines
    assert "| 0 | 40.00 | 39.50 | 39.00 |" in lines
    assert "| 30 | 37.00 | 36.50 | 36.00 |" in lines


def test_a_missing_row_is_shown_as_not_available():
    from hsicam.engine.evaluate import summarize
    from hsicam.engine.experiments import format_experiment_table

    result = {"experiment": "compare", "scale": "tiny", "seeds": [0], "scenes": ["a"],
              "conventions": summarize([])["conventions"],
              "rows": [{"method": "dd-cassi-desci", "missing": True}]}
    assert format_experiment_table(result).splitlines()[-1] == "| dd-cassi-desci | – | – | – | not available |"


# ------------------------------------------------------------------------------------------------
# demo folder
# ------------------------------------------------------------------------------------------------
def test_a_demo_folder_check_takes_an_older_demo_and_a_folder_of_temporaries(tmp_path):
    from hsicam.engine.demo import check_demo_folder
    from hsicam.io import mark_complete

    old = tmp_path / "old"
    old.mkdir()
    (old / "results.json").write_text("{}")
    mark_complete(old)  # an older demo's marker names no command
    check_demo_folder(old)
    temp = tmp_path / "temp"
    temp.mkdir()
    (temp / ".results.json.abcd1234.tmp").write_text("")  # a killed demo's temporary only
    check_demo_folder(temp)
    other = tmp_path / "other"
    other.mkdir()
    mark_complete(other, {"command": "evaluate"})
    with pytest.raises(InputError) as err:
        check_demo_folder(other)
    assert str(err.value) == f"{other}: holds the output of hsicam evaluate, not a demo; choose another --out"


# ------------------------------------------------------------------------------------------------
# demo: its references (a tiny run, one epoch)
# ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_demo_with_a_consistency_step_scores_the_network_alone_and_each_reference_on_its_own_scenes(
        tmp_path, cache_env, monkeypatch):
    from hsicam.engine.demo import run_demo
    from hsicam.engine.evaluate import TestNoise, evaluate_method, summarize
    from hsicam.engine.experiments import heldout_scenes
    from hsicam.engine.methods import demosaic_reference
    from hsicam.runs.folder import load_run

    monkeypatch.chdir(tmp_path)
    run_demo(load_config("tiny", ["train.epochs=1", "model.consistency.iterations=1",
                                  "model.consistency.kind=landweber"]), "demo")  # a relative --out
    res = json.loads((tmp_path / "demo" / "results.json").read_text())
    assert res["run_path"] == str(tmp_path.resolve() / "demo" / "run")  # absolute: `hsicam report` from anywhere
    assert "network alone (no consistency step)" in [r["method"] for r in res["references"]]
    # the held-out references are scored on the held-out scenes: the box demosaic scored here on them
    cfg, model = load_run(tmp_path / "demo" / "run")
    held, names = heldout_scenes(cfg)
    box = summarize(evaluate_method(demosaic_reference(model), held, names, TestNoise(seeds=(cfg.train.seed,)),
                                    keep_arrays=False))["mean"]
    got = {r["method"]: r["mean"] for r in res["heldout"]["references"]}["CFA box demosaic (no network)"]
    val = {r["method"]: r["mean"] for r in res["references"]}["CFA box demosaic (no network)"]
    assert got["psnr"] == pytest.approx(box["psnr"], abs=1e-6) and got["psnr"] != pytest.approx(val["psnr"], abs=1e-3)


# ------------------------------------------------------------------------------------------------
# methods: the demosaic references of a run (an in-memory run stands in for load_run)
# ------------------------------------------------------------------------------------------------
def _in_memory_run(monkeypatch, tmp_path, overrides):
    """A tiny DOE system built from ``overrides``, which methods.load_run hands back for ``tmp_path``."""
    from hsicam.engine import methods
    from hsicam.models import CameraSystem

    cfg = load_config("tiny", overrides)
    torch.manual_seed(0)
    model = CameraSystem.from_config(cfg).eval()
    monkeypatch.setattr(methods, "load_run", lambda run, device=None: (cfg, model))
    return model


def test_the_tent_reference_of_a_run_whose_network_starts_with_a_tent_demosaic_uses_its_window(tmp_path, monkeypatch):
    """doe-tent-demosaic through a run whose mosaic network's skip is a 3-px tent (not the default 2·3 − 1 = 5 px)
    is that network's own start: the tent demosaic of width 3; the box reference keeps its own window."""
    from hsicam.engine.methods import build_method
    from hsicam.models.demosaic import camera_demosaic

    _in_memory_run(monkeypatch, tmp_path, ["model.kind=mosaic", "model.mosaic.demosaic_kernel=tent",
                                          "model.mosaic.demosaic_window=3"])
    tent = build_method("doe-tent-demosaic", load_config("tiny"), tmp_path)
    y = torch.rand(1, 1, 24, 24, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        got = tent.reconstruct(y)
        torch.testing.assert_close(got, camera_demosaic(tent.camera, y, kernel="tent", window=3))
        assert not torch.allclose(got, camera_demosaic(tent.camera, y, kernel="tent"))


def test_a_demosaic_reference_captures_with_the_evaluation_configs_padding(tmp_path, monkeypatch):
    """The evaluation config's camera.padding (with boundary same) is the capture's, not the run's own."""
    from hsicam.engine.methods import build_method

    model = _in_memory_run(monkeypatch, tmp_path, [])
    assert model.camera.padding == "zeros"
    box = build_method("doe-box-demosaic", load_config("tiny", ["camera.boundary=same", "camera.padding=reflect"]),
                       tmp_path)
    assert (box.camera.boundary, box.camera.padding) == ("same", "reflect")


def test_a_demosaic_reference_captures_with_the_evaluation_configs_doe_height_noise(tmp_path, monkeypatch):
    """--set camera.doe.sigma_height_nm=15 on the evaluation draws 15 nm (1.5e-8 m) of height noise per DOE cell in
    the reference's captures, whatever the run trained with (0 here)."""
    from hsicam.engine.methods import build_method

    model = _in_memory_run(monkeypatch, tmp_path, ["camera.doe.sigma_height_nm=0"])
    assert model.camera.optics.doe.sigma_height_m == 0
    box = build_method("doe-box-demosaic", load_config("tiny", ["camera.doe.sigma_height_nm=15"]), tmp_path)
    assert box.camera.optics.doe.sigma_height_m == pytest.approx(1.5e-8, rel=1e-12)


def test_a_demosaic_reference_of_an_unknown_kernel_is_refused_by_name():
    from hsicam.engine.methods import demosaic_reference
    from hsicam.models import CameraSystem

    model = CameraSystem.from_config(load_config("tiny"))
    with pytest.raises(ValueError) as err:
        demosaic_reference(model, "gauss")
    assert str(err.value) == "demosaic kernel must be one of box, tent, got 'gauss'"


def test_an_evaluation_asking_for_a_linear_step_the_run_has_not_got_is_refused_when_the_method_is_built(
        tmp_path, monkeypatch):
    """--set model.consistency.kind=linear on a run without linear_step.safetensors: the refusal load_run prepared
    (model.linear_step_missing) is raised by build_method, before any scene is read."""
    from hsicam.engine.methods import build_method

    model = _in_memory_run(monkeypatch, tmp_path, [])
    assert model.linear_step is None
    model.linear_step_missing = f"{tmp_path}: no linear step here"
    cfg = load_config("tiny", ["model.consistency.kind=linear", "model.consistency.iterations=1"])
    with pytest.raises(InputError) as err:
        build_method("doe-learned", cfg, tmp_path)
    assert str(err.value) == f"{tmp_path}: no linear step here"


def test_an_unfinished_run_of_an_experiment_is_resumed_not_reused(tmp_path, monkeypatch):
    """A run folder of the same config whose log has no final record is trained on (resume=True), not scored as
    it is; a finished one is reused without training, its linear step and kept weights brought to the config's."""
    from hsicam.config import dump_yaml
    from hsicam.engine import experiments

    calls = []
    monkeypatch.setattr(experiments, "train", lambda cfg, run, resume=False: calls.append((run, resume)))
    refreshed = []
    monkeypatch.setattr(experiments, "refresh_linear_step", lambda *a: refreshed.append(a) or [])
    cfg = load_config("tiny")
    run = _run_folder(tmp_path / "run", [{"step": 1}, {"step": 2}])
    (run / "config.yaml").write_text(dump_yaml(cfg))
    assert experiments.ensure_trained(run, cfg) == "resumed" and calls == [(run, True)]
    (run / "metrics.jsonl").write_text(json.dumps({"step": 2, "final": True}) + "\n")
    assert experiments.ensure_trained(run, cfg) == "reused" and calls == [(run, True)]
    assert refreshed == [(run, cfg.model.consistency, cfg.train.keep_weights)]


def test_each_row_of_a_run_with_a_note_records_its_overrides_and_note(tmp_path, monkeypatch):
    """A row of experiment.json (read back as JSON) whose run the experiment set beyond the swept key says so:
    the run's overrides and note (training and scoring stubbed: only the rows' fields are checked)."""
    from hsicam.engine import experiments

    specs = [experiments.RunSpec("plain"), experiments.RunSpec("wide", ("model.consistency.window_px=9",), "why")]
    monkeypatch.setattr(experiments, "ensure_trained", lambda run, cfg: "reused")
    monkeypatch.setattr(experiments, "validation_scenes", lambda cfg: ([], ["a"]))
    monkeypatch.setattr(experiments, "build_method", lambda *a: SimpleNamespace(camera=None))
    monkeypatch.setattr(experiments, "scored_region", lambda camera: None)
    monkeypatch.setattr(experiments, "evaluate_method", lambda *a, **k: [])
    conventions = experiments.summarize([])["conventions"]
    monkeypatch.setattr(experiments, "summarize",
                        lambda res: {"mean": {**MEAN, "runtime_s": 0.5}, "scenes": [], "conventions": conventions})
    cfg = load_config("tiny")
    experiments._run_experiment("ablation", "tiny", tmp_path / "ex", cfg, (0,), specs,
                                {"plain": cfg, "wide": cfg}, ())
    rows = json.loads((tmp_path / "ex" / "experiment.json").read_text())["rows"]
    assert [(r["method"], r.get("overrides"), r.get("note")) for r in rows] == [
        ("plain", None, None), ("wide", ["model.consistency.window_px=9"], "why")]


def test_the_demo_trains_the_quick_preset_unless_told_otherwise():
    from hsicam.config import dump_yaml
    from hsicam.engine.demo import demo_config

    assert dump_yaml(demo_config(None, ())) == dump_yaml(load_config("quick"))
    assert dump_yaml(demo_config("tiny", ("train.epochs=1",))) == dump_yaml(load_config("tiny", ["train.epochs=1"]))


def test_a_demo_over_a_run_of_another_config_is_refused_before_its_folder_changes(tmp_path):
    """A finished demo folder whose run was trained with another CFA period: refused naming the difference, its
    completion marker and its report/ left as they were."""
    from hsicam.config import dump_yaml
    from hsicam.engine.demo import _run_demo
    from hsicam.io import mark_complete

    out = tmp_path / "demo"
    (out / "run").mkdir(parents=True)
    (out / "run" / "config.yaml").write_text(dump_yaml(load_config("tiny", ["camera.cfa.period=4"])))
    (out / "report").mkdir()
    (out / "report" / "index.html").write_text("x")
    mark_complete(out / "report", {"command": "report", "files": ["index.html"]})
    mark_complete(out, {"command": "demo"})
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    with pytest.raises(InputError, match=r"demo/run was trained with another config \(.*camera\.cfa\.period"):
        _run_demo(load_config("tiny"), out)
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before


def test_every_experiment_scale_is_a_shipped_preset_and_the_cli_takes_each(capsys):
    """The experiments run at the scales of the presets tiny, quick and paper (docs/training.md): `hsicam experiment
    NAME --scale S` parses for each, and each names a preset that loads; another name is refused by argparse."""
    from hsicam.cli import build_parser

    parser = build_parser()
    for scale in ("tiny", "quick", "paper"):
        assert parser.parse_args(["experiment", "ablation", "--scale", scale, "--out", "x"]).scale == scale
        load_config(scale)
    with pytest.raises(SystemExit):
        parser.parse_args(["experiment", "ablation", "--scale", "huge", "--out", "x"])
    assert "invalid choice: 'huge'" in capsys.readouterr().err


def test_the_noise_grids_worst_score_does_not_depend_on_where_an_undefined_point_sits():
    """psnr_worst / ssim_worst of the noise experiment were min() over the grid: NaN when the undefined (NaN) point
    came first, the least of the others when it came later. Now the least defined point in every order (the
    reference: the sorted defined values' first), NaN only when no point is defined."""
    import itertools
    import math

    from hsicam.engine.experiments import grid_worst

    grid = [31.5, math.nan, 24.25, 40.0]
    for order in itertools.permutations(grid):
        assert grid_worst(order) == sorted(v for v in grid if not math.isnan(v))[0] == 24.25
    assert grid_worst([-math.inf, math.nan, 30.0]) == -math.inf  # a broken estimate's worst score stays the worst
    assert math.isnan(grid_worst([math.nan, math.nan]))
