"""Lines of the configuration and the command line (config, cli) that the default suite never ran: each test runs
one and checks what it does against an independent reference (the exact line a user sees, a cube read back)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import yaml

from cli_helpers import assert_ok, error_line, run_cli_in_process
from hsicam.config import BandsConfig, ChoiConfig, ConfigError, TrainConfig, load_config
from hsicam.errors import InputError


# --- config.py -----------------------------------------------------------------------------------------------------

def test_config_not_utf8_is_one_config_error(tmp_path):
    p = tmp_path / "a.yaml"
    p.write_bytes(b"seed: 1\n# \xff\xfe\n")
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    assert str(exc.value) == (f"{p}: cannot read config ('utf-8' codec can't decode byte 0xff in position 10: "
                              "invalid start byte)")


def test_an_old_model_section_is_read_as_kind_and_rdn(tmp_path):
    """``model: {name: rdn, blocks: …}`` (configs written before network kinds) reads as the current layout."""
    old, new = tmp_path / "old.yaml", tmp_path / "new.yaml"
    old.write_text("model:\n  name: rdn\n  blocks: 3\n  features: 8\n")
    new.write_text("model:\n  kind: rdn\n  rdn: {blocks: 3, features: 8}\n")
    assert load_config(old).model == load_config(new).model
    assert load_config(old).model.rdn.blocks == 3
    # both spellings agreeing are one setting; disagreeing, neither is silently dropped (session 57)
    old.write_text("model:\n  name: rdn\n  kind: rdn\n  blocks: 3\n  rdn: {blocks: 3, features: 8}\n")
    assert load_config(old).model == load_config(new).model
    for text, error in (("model:\n  kind: rdn\n  name: unrolled\n",
                         "model.name (the older spelling of model.kind) is 'unrolled' but model.kind is 'rdn'; keep one"),
                        ("model:\n  blocks: 5\n  rdn: {blocks: 3}\n",
                         "model.blocks (the older spelling of model.rdn.blocks) is 5 but model.rdn.blocks is 3; keep one")):
        old.write_text(text)
        with pytest.raises(ConfigError) as exc:
            load_config(old)
        assert str(exc.value) == f"{old}: {error}"  # the file is named, as for every other error in it
        with pytest.raises(ConfigError) as exc:  # with an override that is not at fault: still the file's
            load_config(old, ["train.epochs=2"])
        assert str(exc.value) == f"{old}: {error}"
    # model.rdn not a mapping: that is the error, not the older keys beside it (they were named unknown)
    old.write_text("model:\n  name: rdn\n  rdn: 5\n  blocks: 3\n")
    with pytest.raises(ConfigError) as exc:
        load_config(old)
    assert str(exc.value) == f"{old}: model.rdn must be a mapping, got int"
    old.write_text("model:\n  name: rdn\n")
    with pytest.raises(ConfigError) as exc:  # an override breaking the section: the override's error, no file
        load_config(old, ["model.rdn=5"])
    assert str(exc.value) == "model.rdn must be a mapping, got int"


@pytest.mark.parametrize("override, text", [
    ("a..b=1", "override 'a..b=1': empty key"),
    ("model.rdn.blocks=0", "model.rdn.blocks must be >= 1, got 0"),
    ("train.epochs=0", "train.epochs must be >= 1, got 0"),
    ("train.warmup_steps=-1", "train.warmup_steps must be >= 0, got -1"),
    ("data.heldout_n=0", "data.heldout_n must be >= 1, got 0"),
    ('data.root=" "', "data.root must be a path or null"),
    ("camera.sensor.read_noise_e=-1", "camera.sensor.read_noise_e must be >= 0, got -1.0"),
    ("baselines.gaptv.tv_weight=-1", "baselines.gaptv.tv_weight must be >= 0, got -1.0"),
])
def test_config_refusals(override, text):
    with pytest.raises(ConfigError) as exc:
        load_config(None, [override])
    assert str(exc.value) == text


def test_a_seed_set_in_python_that_is_no_integer_is_refused_with_its_key():
    """The YAML path refuses it in _coerce; a section built in Python reaches seed_problem's type check."""
    from hsicam.engine.tolerance import ToleranceSpec

    with pytest.raises(ConfigError) as exc:
        ChoiConfig(seed=1.5)
    assert str(exc.value) == "baselines.choi.seed must be an integer, got 1.5"
    with pytest.raises(ConfigError) as exc:
        TrainConfig(seed=True)  # a bool is no seed although Python counts it as an int
    assert str(exc.value) == "train.seed must be an integer, got True"
    with pytest.raises(InputError) as exc:
        ToleranceSpec(seed=2.0).check()
    assert str(exc.value) == "ToleranceSpec.seed must be an integer, got 2.0"


@pytest.mark.parametrize("overrides, text", [
    (["baselines.desci.sigmas=[1, 2]", "baselines.desci.iterations=[3]"], "baselines.desci: 2 sigmas but 1 iteration counts"),
    (["baselines.choi.train_noise=-1"], "baselines.choi.train_noise must be >= 0, got -1.0"),
    (["baselines.choi.prior_weight=-0.5"], "baselines.choi.prior_weight must be >= 0, got -0.5"),
    (["baselines.choi.tv_weight=-0.001"], "baselines.choi.tv_weight must be >= 0, got -0.001"),
])
def test_baseline_settings_refused_with_their_key(overrides, text):
    with pytest.raises(ConfigError) as exc:
        load_config(overrides=overrides)
    assert str(exc.value) == text


def test_a_config_file_with_a_control_character_is_one_line_naming_the_file(tmp_path):
    """PyYAML's reader error has no problem mark (yaml_error_text's branch without line:column)."""
    path = tmp_path / "bad.yaml"
    path.write_bytes(b"train:\n  lr: 1\x07\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value) == f"{path}: invalid YAML (unacceptable character #x0007: special characters are not allowed)"


def test_a_section_left_empty_in_a_file_takes_its_defaults(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("train:\nbands:\ndata: {synthetic_n: 7}\n", encoding="utf-8")
    cfg = load_config(path)
    assert cfg.train == TrainConfig() and cfg.bands == BandsConfig() and cfg.data.synthetic_n == 7


# (from models/test_models_rare_paths.py)
@pytest.mark.parametrize("overrides, message", [
    (["baselines.desci.iterations=[]"], "baselines.desci.iterations must be a non-empty list of counts >= 0, got []"),
    (["baselines.desci.iterations=[3, -1]"],
     "baselines.desci.iterations must be a non-empty list of counts >= 0, got [3, -1]"),
    # a value that is not valid YAML is kept as the string typed, then refused as that string
    (["model.consistency.kind=[linear"],
     "config key 'model.consistency.kind' must be one of 'landweber', 'linear', got '[linear'"),
])
def test_config_refusals_name_the_key_and_the_value_typed(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_config(overrides=overrides)
    assert str(err.value) == message


# --- cli: the one line a user sees ---------------------------------------------------------------------------------

def test_error_line_of_unreadable_inputs():
    from hsicam.cli import error_line as line

    try:
        json.loads('{"a": }')
    except json.JSONDecodeError as exc:
        assert line(exc) == "unreadable JSON input (Expecting value at line 1)"
    try:
        b"\xff".decode("utf-8")
    except UnicodeDecodeError as exc:
        assert line(exc) == "unreadable input: not UTF-8 text (invalid start byte)"
    assert line(MemoryError()).startswith("out of memory (lower the memory budget HSICAM_MEMORY_BUDGET_MB")
    try:
        yaml.safe_load("a: [1")
    except yaml.YAMLError as exc:
        assert line(exc) == f"unreadable YAML input ({str(exc).splitlines()[0]})"
    assert line(ValueError("a bug")) is None


def test_cli_refusals_without_a_run(tmp_path):
    res = run_cli_in_process("data", "show", str(tmp_path / "nothing"), "--out", str(tmp_path / "o"))
    assert error_line(res) == f"hsicam: error: {tmp_path / 'nothing'}: no such dataset folder or cube file"
    res = run_cli_in_process("data", "synth", "--n", "1", "--size", "16", "--split", "heldout", "--holdout-sources",
                             "none", "--out", str(tmp_path / "s"))
    assert error_line(res) == ("hsicam: error: --split heldout needs at least one held-out source "
                               "(--holdout-sources)")
    assert not (tmp_path / "s").exists()
    res = run_cli_in_process("psf", "--config", "dd_cassi_rdn", "--out", str(tmp_path / "p"))
    assert error_line(res) == "hsicam: error: hsicam psf needs a DOE camera (camera.kind=doe), not camera.kind=dd_cassi"


@pytest.fixture(scope="module")
def no_cfa_run(tmp_path_factory, cache_env):
    """A DOE run without a CFA, one consistency step that is not noise-aware (trains in seconds)."""
    run = tmp_path_factory.mktemp("nocfa") / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--set", "camera.cfa.enabled=false", "--set",
                             "model.consistency.iterations=1", "--set", "model.consistency.noise_aware=false",
                             "--set", "train.epochs=1", "--out", str(run))
    assert_ok(res)
    return run


def test_reconstruct_options_that_change_nothing_say_so_and_change_nothing(no_cfa_run, tmp_path):
    cap = tmp_path / "cap.npy"
    np.save(cap, np.random.default_rng(0).uniform(0.1, 0.6, (40, 40)).astype(np.float32))
    assert_ok(run_cli_in_process("reconstruct", str(cap), "--run", str(no_cfa_run), "--out", str(tmp_path / "a.h5")))
    res = run_cli_in_process("reconstruct", str(cap), "--run", str(no_cfa_run), "--out", str(tmp_path / "b.h5"),
                             "--cfa-offset", "1,2", "--full-well-e", "1000")
    assert_ok(res)
    assert "--cfa-offset is ignored: the camera has no colour filter array" in res.stderr
    assert "--full-well-e changes nothing: the run's model.consistency.noise_aware is off" in res.stderr
    with h5py.File(tmp_path / "a.h5", "r") as a, h5py.File(tmp_path / "b.h5", "r") as b:
        np.testing.assert_array_equal(a["cube"][()], b["cube"][()])
        assert "cfa_offset" not in json.loads(b.attrs["metadata_json"])
    res = run_cli_in_process("reconstruct", str(cap), "--run", str(no_cfa_run), "--out", str(tmp_path / "c.tif"))
    assert error_line(res) == (f"hsicam: error: {tmp_path / 'c.tif'}: output must end in .h5 or .hdf5 (HDF5), or .hdr, "
                               ".img or .raw (ENVI)")
    assert not list(tmp_path.glob("c.*")) and not list(tmp_path.glob("c_*"))


def test_experiment_refuses_a_folder_that_holds_something_else(tmp_path):
    out = tmp_path / "ex"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = run_cli_in_process("experiment", "ablation", "--scale", "tiny", "--out", str(out))
    assert error_line(res) == f"hsicam: error: {out}: folder exists and is not an experiment folder; choose another --out"
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"] and (out / "notes.txt").read_text() == "mine"


def test_data_show_of_an_all_zero_cube_is_one_clear_error(tmp_path):
    cube = tmp_path / "zero.npy"
    np.save(cube, np.zeros((7, 32, 32), np.float32))
    res = run_cli_in_process("data", "show", str(cube), "--out", str(tmp_path / "show"))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1] == (f"hsicam: error: {cube}: the cube is all zeros; cannot normalise by "
                                                  "its maximum")


def test_reconstruct_output_names_a_dot_file_and_a_data_suffix_of_any_case_reads_back(no_cfa_run, tmp_path):
    """(A reconstruct hunt, session 72.) `--out .h5` was refused as "must end in .h5"; `--out D.Raw` wrote D.hdr and
    D.Raw, which read_cube could not pair (it tried .raw and .RAW only)."""
    from hsicam.data.formats import read_cube

    cap = tmp_path / "cap.npy"
    np.save(cap, np.random.default_rng(0).uniform(0.1, 0.6, (40, 40)).astype(np.float32))
    res = run_cli_in_process("reconstruct", str(cap), "--run", str(no_cfa_run), "--out", str(tmp_path / ".h5"))
    assert error_line(res) == (f"hsicam: error: {tmp_path / '.h5'}: names no file before its suffix: give the cube a "
                               "name, e.g. cube.h5")
    assert_ok(run_cli_in_process("reconstruct", str(cap), "--run", str(no_cfa_run), "--out", str(tmp_path / "D.Raw")))
    assert sorted(p.name for p in tmp_path.glob("D*")) == ["D.Raw", "D.hdr", "D_rgb.png"]
    cube, _, meta = read_cube(tmp_path / "D.hdr")
    assert meta["data_file"] == str(tmp_path / "D.Raw") and cube.shape[1:] == (40, 40)
    np.testing.assert_array_equal(read_cube(tmp_path / "D.Raw")[0], cube)
