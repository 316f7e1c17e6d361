"""Bad paths whose messages or recorded facts were wrong (probe 21: 13, 15 test noise, 20 a b c h i k m).

* evaluate --sigma-height-nm on a camera without a DOE is refused (it applied nothing but was recorded);
* pretrained pack refuses results measured under test noise, and a --dest/--name that is not a camera;
* tolerance says plainly where a sensor moved onto/past the lens goes, refuses level counts
  export-optics refuses, and does not call an unbracketed level count a requirement;
* data synth refuses a scene size over the memory budget before making any folder, and leaves no
  empty folder on a failure;
* demo --help names its real default; pretrained list says when HSICAM_PRETRAINED_DIR is no folder;
* tolerance --data of a .npy without wavelengths gives advice tolerance can follow.

Runs: one tiny run and a tiny run without a DOE, trained one epoch on the module's own cache.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cli_helpers import assert_clean_error, run_cli, run_cli_in_process
from hsicam.errors import InputError


@pytest.fixture(scope="module")
def runs(tmp_path_factory, cache_env):
    """Folder holding run (tiny, 1 epoch) and nodoe (the same without a DOE)."""
    from hsicam.config import load_config
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("msg_paths")
    train(load_config("tiny", ["train.epochs=1"]), base / "run", progress=False)
    train(load_config("tiny", ["train.epochs=1", "camera.doe.enabled=false"]), base / "nodoe", progress=False)
    return base


def _tree(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ------------------------------------------------------------------------------------------------
# 13: test DOE height noise on a camera without a DOE
# ------------------------------------------------------------------------------------------------
def test_evaluate_refuses_height_noise_without_a_doe(runs, tmp_path):
    out, cache = tmp_path / "ev", tmp_path / "empty-cache"
    res = run_cli_in_process("evaluate", "--method", "dd-cassi-gaptv", "--config", "tiny", "--sigma-height-nm", "50",
                             "--out", str(out), env={"HSICAM_CACHE": str(cache)})
    assert_clean_error(res, "--sigma-height-nm 50: dd-cassi-gaptv (--config tiny): its camera (camera.kind dd_cassi) has "
                       "no DOE", "no height noise would be applied", "drop --sigma-height-nm")
    # refused before the validation and held-out scenes are generated (it once made both first)
    assert "generating" not in res.stderr and not cache.exists()
    nodoe = runs / "nodoe"
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(nodoe), "--sigma-height-nm", "50", "--out", str(out)),
                       f"--sigma-height-nm 50: doe-learned (run {nodoe}): its camera has no DOE "
                       "(camera.doe.enabled: false)", "drop --sigma-height-nm")
    assert not out.exists()


def test_evaluate_method_refuses_height_noise_without_a_doe(runs):
    from hsicam.engine.evaluate import TestNoise, evaluate_method
    from hsicam.engine.methods import build_method
    from hsicam.runs.folder import load_run

    cfg, _ = load_run(runs / "nodoe")
    method = build_method("doe-learned", cfg, runs / "nodoe")
    with pytest.raises(InputError, match="camera.doe.enabled: false"):
        evaluate_method(method, [], [], TestNoise(sigma_height_nm=20.0))
    assert evaluate_method(method, [], [], TestNoise(sigma_height_nm=0.0)) == []  # 0: nothing claimed


# ------------------------------------------------------------------------------------------------
# 15: pack refuses results measured under test noise
# ------------------------------------------------------------------------------------------------
def test_pack_refuses_results_measured_under_test_noise(runs, tmp_path):
    from hsicam.cli import main

    run = runs / "run"
    ev = tmp_path / "ev"
    assert main(["evaluate", "--run", str(run), "--sensor-sigma", "0.5", "--out", str(ev)]) == 0
    dest = tmp_path / "root"
    res = run_cli_in_process("pretrained", "pack", str(run), "--name", "x", "--dest", str(dest), "--results",
                             str(ev / "results.json"))
    assert_clean_error(res, f"{ev / 'results.json'}: measured under test noise --sensor-sigma 0.5 (the camera's own: 0)",
                       f"`hsicam evaluate --run {run} --out DIR`, no --sensor-sigma", "as --results")
    assert not dest.exists()
    data = json.loads((ev / "results.json").read_text())
    data["noise"] = {"sigma_height_nm": 40.0, "sensor_sigma": None, "seeds": 1}
    held = tmp_path / "held.json"
    held.write_text(json.dumps(data))
    from hsicam.engine.pretrained import check_results_noise

    with pytest.raises(InputError, match=r"--sigma-height-nm 40 nm \(the camera's own: 0\).*as --heldout"):
        check_results_noise(data, held, run, "--heldout")
    data["noise"] = {"sigma_height_nm": 0.0, "sensor_sigma": 0.0, "seeds": 3}  # the camera's own noise: accepted
    check_results_noise(data, held, run)


# ------------------------------------------------------------------------------------------------
# 20 a: pack onto a folder that is not a packed camera
# ------------------------------------------------------------------------------------------------
def test_pack_onto_a_run_folder_is_refused_without_offering_force(runs, tmp_path):
    run = tmp_path / "runP"
    shutil.copytree(runs / "run", run)
    before = _tree(run)
    for force in ((), ("--force",)):
        assert_clean_error(run_cli_in_process("pretrained", "pack", str(run), "--name", "runP", "--dest", str(tmp_path), *force),
                           f"{run}: not a packed camera (a run folder, not a completed hsicam output)",
                           "even with --force",
                           "choose another --name or --dest")
        assert _tree(run) == before
    # a packed camera of that name still asks for --force, and is replaced with it
    res = run_cli_in_process("pretrained", "pack", str(run), "--name", "cam", "--dest", str(tmp_path / "root"))
    assert res.returncode == 0, res.stderr
    assert_clean_error(run_cli_in_process("pretrained", "pack", str(run), "--name", "cam", "--dest", str(tmp_path / "root")),
                       "a pre-trained camera 'cam' exists; pass --force")
    res = run_cli_in_process("pretrained", "pack", str(run), "--name", "cam", "--dest", str(tmp_path / "root"), "--force")
    assert res.returncode == 0, res.stderr


def test_pack_into_its_own_run_folder_or_over_it_is_refused(runs, tmp_path):
    """--dest RUN (or a folder inside it) wrote the camera into the run being packed, and was accepted;
    a camera folder holding the run was refused only as "not a packed camera". Each is one line now,
    and nothing is written."""
    from cli_helpers import tree_snapshot

    run = tmp_path / "runQ"
    shutil.copytree(runs / "run", run)
    before = tree_snapshot(tmp_path)
    for dest in (run, run / "cameras", run / "checkpoints"):
        assert_clean_error(run_cli_in_process("pretrained", "pack", str(run), "--name", "cam", "--dest", str(dest)),
                           f"{dest / 'cam'}: inside the run folder {run} that is being packed",
                           f"give a --dest outside {run}")
        assert tree_snapshot(tmp_path) == before
    # the same run reached through a link: still its own folder
    (tmp_path / "link").symlink_to(run)
    assert_clean_error(run_cli_in_process("pretrained", "pack", str(tmp_path / "link"), "--name", "cam",
                                          "--dest", str(run)), "inside the run folder")
    (tmp_path / "link").unlink()
    # the camera folder would hold (and replace) the run
    inner = tmp_path / "root" / "cam" / "runQ"
    inner.parent.mkdir(parents=True)
    run.rename(inner)
    before = tree_snapshot(tmp_path)
    for force in ((), ("--force",)):
        assert_clean_error(run_cli_in_process("pretrained", "pack", str(inner), "--name", "cam",
                                              "--dest", str(tmp_path / "root"), *force),
                           f"{tmp_path / 'root' / 'cam'}: holds the run folder {inner} that is being packed",
                           "choose another --name or --dest")
        assert tree_snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------
# 20 b, c: tolerance wording
# ------------------------------------------------------------------------------------------------
def test_tolerance_says_where_the_sensor_goes_and_refuses_unexportable_levels(runs):
    from hsicam.engine.tolerance import ToleranceSpec, check_sweeps
    from hsicam.runs.folder import load_run

    _, model = load_run(runs / "run")
    optics = model.camera.optics
    z = optics.sensor_distance_m * 1e6
    with pytest.raises(InputError, match=rf"Δz = -{z:g} µm moves the sensor onto the lens \(the sensor sits {z:g} µm "
                                         rf"behind the lens\); Δz toward the lens must stay above -{z:g} µm"):
        check_sweeps(ToleranceSpec(sensor_distance_um=(-z,)), optics)
    with pytest.raises(InputError, match=r"moves the sensor past the lens, 1000 µm in front of it"):
        check_sweeps(ToleranceSpec(sensor_distance_um=(-z - 1000,)), optics)
    for lv in (3, 131072):  # the export's range is the config's: 2..2^16 (camera.doe.quantization_levels)
        with pytest.raises(InputError, match=rf"--levels {lv}: hsicam export-optics exports only a power of 2 in "
                                             r"2..65536 levels.*e.g. --levels 2,4,8"):
            check_sweeps(ToleranceSpec(levels=(2, lv), sensor_distance_um=(0.0,)), optics)
    check_sweeps(ToleranceSpec(levels=(2, 1024), sensor_distance_um=(0.0,)), optics)


def test_levels_requirement_only_when_bracketed():
    from hsicam.engine.tolerance import levels_requirement
    from hsicam.report.tolerance import levels_text

    def text(values, psnr):
        req = levels_requirement(values, psnr, 30.0)
        summary = {"min_levels_within_1db": req["min_levels_within_1db"], "levels_bracketed": req["bracketed"],
                   **({"levels_note": req["reason"]} if req["reason"] else {})}
        return levels_text({"sweeps": {"levels": {}}, "summary": summary})

    assert text([16], [29.9]) == "levels: 16 within 1 dB, not bracketed: only one value tried"
    assert text([8, 16], [29.5, 29.9]) == "levels: 8 within 1 dB, not bracketed: no fewer levels than 8 tried"
    assert text([2, 4, 8], [20.0, 28.0, 29.5]) == "levels ≥ 8"
    assert text([2, 4], [20.0, 25.0]) == "levels: no swept level count (2, 4) within 1 dB"
    assert levels_text({"sweeps": {}, "summary": {}}) == ""


def test_tolerance_one_value_level_sweep_is_recorded_as_not_bracketed(runs, tmp_path):
    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(runs / "run"), "--out", str(out), "--max-scenes", "1", "--draws", "1",
                             "--levels", "16", "--sigma-height-nm", "0", "--shift-cells", "0", "--sensor-distance-um", "0")
    assert res.returncode == 0, res.stderr
    s = json.loads((out / "tolerance.json").read_text())["summary"]
    assert s["levels_bracketed"] is False and s["levels_note"] == "not bracketed: only one value tried"
    assert "levels: 16 within 1 dB, not bracketed: only one value tried" in res.stdout, res.stdout
    assert "levels ≥" not in res.stdout


# ------------------------------------------------------------------------------------------------
# 20 h: data synth memory
# ------------------------------------------------------------------------------------------------
def test_synth_refuses_a_scene_over_the_memory_budget_before_any_folder(tmp_path):
    """In a process of its own: were the check broken, the scene's 40 GB label map would be allocated, which a
    large machine grants and then kills the process for (the test's, not the suite's)."""
    out = tmp_path / "big"
    res = run_cli("data", "synth", "--n", "2", "--size", "100000", "--out", str(out), timeout=120,
                  env={"HSICAM_MEMORY_BUDGET_MB": "1024", "HSICAM_CACHE": str(tmp_path / "cache")})
    assert_clean_error(res, "--size 100000: one 100000×100000-px scene of 31 bands is a cube of 1.13 TiB",
                       "more than the memory budget of 1 GiB for one cube (HSICAM_MEMORY_BUDGET_MB", "give --size ",
                       "or raise HSICAM_MEMORY_BUDGET_MB")
    assert "tile size" not in res.stderr and "batch size" not in res.stderr
    assert not out.exists()
    res = run_cli("data", "synth", "--n", "2", "--size", "100000", timeout=120,  # into the cache: no folder there either
                  env={"HSICAM_MEMORY_BUDGET_MB": "1024", "HSICAM_CACHE": str(tmp_path / "cache")})
    assert res.returncode == 2 and "--size 100000" in res.stderr
    assert not any((tmp_path / "cache").rglob("n2-s100000*"))


def test_synth_largest_size_named_is_accepted(monkeypatch):
    from hsicam.data.synthetic import check_scene_memory

    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "64")
    with pytest.raises(InputError, match="--size 1000: .* give --size (\\d+) or less") as err:
        check_scene_memory(1000, 31, "--size")
    largest = int(str(err.value).split("give --size ")[1].split()[0])
    check_scene_memory(largest, 31, "--size")
    with pytest.raises(InputError):
        check_scene_memory(largest + 1, 31, "--size")


def test_synth_failure_leaves_no_empty_folder(tmp_path, monkeypatch):
    import hsicam.data.synthetic as syn
    from hsicam.spectral import Bands

    def fail(*a, **k):
        raise MemoryError

    monkeypatch.setattr(syn, "generate_scene", fail)
    out = tmp_path / "a" / "b" / "ds"
    with pytest.raises(MemoryError):
        syn.generate_dataset(out, n=1, size=16, bands=Bands.paper(), progress=False)
    assert not (tmp_path / "a").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    with pytest.raises(MemoryError):
        syn.generate_dataset(kept, n=1, size=16, bands=Bands.paper(), progress=False)
    assert kept.is_dir()  # the user's own (empty) folder stays


# ------------------------------------------------------------------------------------------------
# 20 i, k, m
# ------------------------------------------------------------------------------------------------
def test_demo_help_names_the_quick_preset():
    res = run_cli_in_process("demo", "--help")
    assert res.returncode == 0
    assert "(default: the quick preset)" in res.stdout and "paper camera" not in res.stdout


def test_pretrained_dir_that_is_no_folder(tmp_path):
    missing = tmp_path / "nonexistent"
    res = run_cli_in_process("pretrained", "list", env={"HSICAM_PRETRAINED_DIR": str(missing)})
    assert res.returncode == 0, res.stderr
    assert (f"no pre-trained cameras: HSICAM_PRETRAINED_DIR={missing}, a folder that does not exist; unset "
            "HSICAM_PRETRAINED_DIR for the cameras shipped with hsicam (") in res.stdout, res.stdout
    assert "shipped in" not in res.stdout
    assert_clean_error(run_cli_in_process("pretrained", "show", "standard", env={"HSICAM_PRETRAINED_DIR": str(missing)}),
                       f"none is shipped in HSICAM_PRETRAINED_DIR={missing}, a folder that does not exist; unset "
                       "HSICAM_PRETRAINED_DIR for the cameras shipped with hsicam")
    empty = tmp_path / "empty"
    empty.mkdir()
    res = run_cli_in_process("pretrained", "list", env={"HSICAM_PRETRAINED_DIR": str(empty)})
    assert res.returncode == 0, res.stderr
    assert f"no pre-trained cameras in {empty} (HSICAM_PRETRAINED_DIR); unset HSICAM_PRETRAINED_DIR" in res.stdout
    assert "shipped in" not in res.stdout


def test_tolerance_npy_without_wavelengths_gives_advice_tolerance_can_follow(runs, tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    np.save(d / "cube.npy", np.random.default_rng(0).random((7, 64, 64), dtype=np.float32))
    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(runs / "run"), "--out", str(out), "--data", str(d / "cube.npy"),
                             "--max-scenes", "1", "--draws", "1")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    last = res.stderr.strip().splitlines()[-1]  # after the reader's "carries no wavelengths" warning
    assert last.startswith("hsicam: error:") and "its 7 bands were taken as 400-700 nm" in last, last
    assert last.endswith("tolerance reads the wavelengths from the file only, so save it as .h5 with its band list "
                         "(hsicam.data.formats.write_cube_h5) and pass that to --data)"), last
    assert "data.npy_bands" not in res.stderr
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# 20 d: the DOE camera's method on a learned CASSI run
# ------------------------------------------------------------------------------------------------
def test_doe_learned_on_a_cassi_run_names_the_runs_own_method(tmp_path, cache_env):
    """It was accepted and its results labelled doe-learned; the reverse was already refused."""
    from hsicam.config import load_config
    from hsicam.engine.experiments import CASSI_RDN_OVERRIDES
    from hsicam.engine.train import train

    run = tmp_path / "cassi"
    train(load_config("tiny", ["train.epochs=1", *CASSI_RDN_OVERRIDES]), run, progress=False)
    res = run_cli_in_process("evaluate", "--method", "doe-learned", "--run", str(run), "--out", str(tmp_path / "ev"))
    assert_clean_error(res, f"{run}: method doe-learned evaluates a DOE camera; this run was trained with "
                            "camera.kind=dd_cassi (model.kind=rdn): use --method dd-cassi-rdn")
    assert not (tmp_path / "ev").exists()
    # the old name doe-rdn: the refusal names doe-learned, and says that it is the method asked for
    res = run_cli_in_process("evaluate", "--method", "doe-rdn", "--run", str(run), "--out", str(tmp_path / "ev"))
    assert_clean_error(res, "method doe-learned evaluates a DOE camera",
                       "use --method dd-cassi-rdn (--method doe-rdn is the old name of doe-learned)")
    assert not (tmp_path / "ev").exists()
    res = run_cli_in_process("evaluate", "--method", "dd-cassi-rdn", "--run", str(run), "--out", str(tmp_path / "ev"))
    assert res.returncode == 0, res.stderr


def test_doe_demosaic_references_on_a_cassi_run_name_the_runs_own_method(tmp_path, cache_env):
    """`evaluate --method doe-box-demosaic` (tent, linear) with a learned CASSI run was a ValueError
    traceback ("needs a camera with a per-band sensor code, not DDCASSICamera") after loading it."""
    from hsicam.config import load_config
    from hsicam.engine.experiments import CASSI_UNROLLED_OVERRIDES
    from hsicam.engine.train import train

    run = tmp_path / "cassi"
    train(load_config("tiny", ["train.epochs=1", *CASSI_UNROLLED_OVERRIDES]), run, progress=False)
    for method in ("doe-box-demosaic", "doe-tent-demosaic", "doe-linear-demosaic"):
        out = tmp_path / method
        res = run_cli_in_process("evaluate", "--method", method, "--run", str(run), "--out", str(out))
        assert_clean_error(res, f"{run}: method {method} evaluates a DOE camera; this run was trained with "
                                "camera.kind=dd_cassi (model.kind=unrolled): use --method dd-cassi-unrolled")
        assert not out.exists()


@pytest.mark.parametrize("override, cause", [
    ("camera.doe.enabled=false", "weights do not fit this model"),
    ("bands.step_nm=10", "checkpoint was trained on Bands(7 bands"),
])
def test_a_set_that_a_trained_run_cannot_take_is_named(runs, tmp_path, override, cause):
    """`psf --run R --set camera.doe.enabled=false` said only "weights do not fit" (probe 24, finding 12)."""
    out = tmp_path / "p"
    assert_clean_error(run_cli_in_process("psf", "--run", str(runs / "run"), "--set", override, "--out", str(out)),
                       f"--set {override}: changes what {runs / 'run'} was trained with, so its weights do not load",
                       cause, "fixed by its training")
    assert not out.exists()


def test_simulate_names_only_the_users_set_that_a_trained_run_cannot_take(runs, tmp_path):
    """simulate adds its own camera.boundary to the --set keys; the refusal named it beside the user's key (session
    70's hunt: "--set camera.cfa.period=4 camera.boundary=same: changes what RUN was trained with")."""
    scene = tmp_path / "scene.npy"
    np.save(scene, np.random.default_rng(0).random((3, 32, 32)).astype(np.float32))
    out = tmp_path / "s"
    res = run_cli_in_process("simulate", "--run", str(runs / "run"), "--scene", str(scene), "--out", str(out),
                             "--set", "camera.doe.enabled=false")
    assert_clean_error(res, f"--set camera.doe.enabled=false: changes what {runs / 'run'} was trained with, so its "
                            "weights do not load")
    assert "camera.boundary" not in res.stderr, res.stderr
    assert not out.exists()


@pytest.mark.parametrize("command", ["psf", "simulate"])
def test_an_unknown_network_kind_is_refused_by_the_commands_that_write_the_config(tmp_path, command):
    """`psf --config tiny --set model.kind=foo` wrote `kind: foo` into its config.yaml, which only train refused
    (session 70's hunt); every command that writes the config refuses it, naming the kinds, before any output."""
    from hsicam.models import network_kinds

    out = tmp_path / "o"
    args = ["--config", "tiny", "--set", "model.kind=foo", "--out", str(out)]
    if command == "simulate":
        scene = tmp_path / "scene.npy"
        np.save(scene, np.random.default_rng(0).random((3, 32, 32)).astype(np.float32))
        args += ["--scene", str(scene)]
    assert_clean_error(run_cli_in_process(command, *args),
                       f"model.kind='foo' is unknown; choose one of {', '.join(network_kinds())}")
    assert not out.exists()
