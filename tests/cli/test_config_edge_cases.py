"""Guards found by mutation testing of the configuration (hsicam.config): each test kills a hand-made mutant (a bound
moved by one, a dropped check, a wrong key name, a skipped branch) that the rest of the suite let through. References
are independent of the code under test: the exact one-line error a user sees, values written out by hand, PyYAML's
own reading of a document. (The same probe's guards of the output helpers, the memory budget and the device checks
are in io/test_io.py, io/test_memory_edge_cases.py and engine/test_device_choice.py.)
"""

from __future__ import annotations

import pytest

from hsicam.config import Config, identity_differences, load_config, training_differences
from hsicam.errors import ConfigError


def refused(overrides: list[str], message: str) -> None:
    """load_config with ``overrides`` over the defaults is a ConfigError whose text is exactly ``message``."""
    with pytest.raises(ConfigError) as exc:
        load_config(None, overrides)
    assert str(exc.value) == message


# --------------------------------------------------------------------------------------------
# config.py: ranges, each at its edge (the value just inside loads, the one just outside is refused)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides, message", [
    (["camera.doe.quantization_levels=1"],
     "camera.doe.quantization_levels must be in [2, 65536] (height levels of the lithography), got 1"),
    (["camera.doe.max_height_nm=2e6"],
     "camera.doe.max_height_nm must be at most 1000000 nm (1 mm, far beyond any DOE's relief), got 2e+06"),
    (["camera.cfa.period=0"], "camera.cfa.period must be >= 1, got 0"),
    (["camera.sensor.bit_depth=33"], "camera.sensor.bit_depth must be in 1..32, got 33"),
    (["camera.sensor.sigma=-0.01"], "camera.sensor.sigma must be in [0, 1] (σ of the image scaled to full scale 1; "
                                    "more buries any signal), got -0.01"),
    (["camera.cassi.mask_density=0"], "camera.cassi.mask_density must be in (0, 1], got 0.0"),
    (["camera.cassi.prism_apex_deg=90"], "camera.cassi.prism_apex_deg must be below 90, got 90.0"),
    (["train.sigma_height_nm=[20, 10]"], "train.sigma_height_nm must be [lo, hi] with 0 <= lo <= hi, got [20.0, 10.0]"),
    (["data.val_fraction=1"], "data.val_fraction must be in [0, 1), got 1.0"),
    (["data.val_pool=1"], "data.val_pool must be >= 2 scenes or null, got 1"),
    (["model.consistency.iterations=1", "model.consistency.kind=linear", "model.consistency.tv_weight=0.03"],
     "model.consistency.tv_weight=0.03 acts in the Landweber steps, and kind=linear takes none (landweber_after=0): "
     "set model.consistency.landweber_after, e.g. 24, or model.consistency.tv_weight=0 for the linear step alone"),
    (["camera.cfa.period=10", "model.consistency.iterations=1", "model.consistency.kind=linear",
      "model.consistency.window_px=9"],
     "model.consistency.window_px=9 is narrower than the CFA period 10: the linear step's filters must see every CFA "
     "phase (flat-field constraint); set it to at least 11"),
    (["train.freeze=doe"], "config key 'train.freeze' must be a list, got 'doe'"),
])
def test_a_value_just_outside_its_range_is_refused_with_its_one_line(overrides, message):
    refused(overrides, message)


def test_the_values_at_the_edges_of_those_ranges_still_load():
    cfg = load_config(None, ["camera.doe.quantization_levels=2", "camera.doe.max_height_nm=1e6", "camera.cfa.period=1",
                             "camera.sensor.bit_depth=32", "camera.sensor.sigma=0", "camera.cassi.mask_density=1",
                             "camera.cassi.prism_apex_deg=89.9", "train.sigma_height_nm=[10, 10]",
                             "data.val_fraction=0", "data.val_pool=2"])
    assert (cfg.camera.doe.quantization_levels, cfg.camera.cfa.period, cfg.camera.sensor.bit_depth) == (2, 1, 32)
    cfg = load_config(None, ["camera.cfa.period=10", "model.consistency.iterations=1", "model.consistency.kind=linear",
                             "model.consistency.window_px=11", "model.consistency.tv_weight=0.03",
                             "model.consistency.landweber_after=4"])
    assert cfg.model.consistency.window_px == 11


def test_a_group_frozen_twice_is_frozen_once():
    """train.freeze is a set of group names: a repeat counts once, in the order first given."""
    assert load_config(None, ["train.freeze=[doe, cfa, doe]"]).train.freeze == ["doe", "cfa"]


@pytest.mark.parametrize("override, item", [
    ("data.holdout_sources=nist-cqs,,rawtoaces", 2), ("data.holdout_sources=nist-cqs,", 2),
    ("data.holdout_sources=,nist-cqs", 1), ("data={holdout_sources: 'nist-cqs,,rawtoaces'}", 2),
])
def test_an_empty_item_of_the_held_out_sources_in_an_override_is_refused(override, item):
    """`--set data.holdout_sources=nist-cqs,,rawtoaces` held out two sources without a word (the empty item
    dropped), while `data synth --holdout-sources nist-cqs,,rawtoaces` refuses it: one error naming the key."""
    value = override.split("=", 1)[1].strip("{}").split(": ")[-1].strip("'")
    refused([override], f"data.holdout_sources: item {item} of {value!r} is empty (two commas in a row, or one at an "
                        "end); give its value or remove the comma")


def test_a_run_config_written_with_an_empty_held_out_item_still_loads(tmp_path):
    """A run's config.yaml keeps data.holdout_sources as it was given (checked here: the file training writes
    holds the string, empty item and all), so a run trained with one before the check still loads, resumes
    with other overrides, and holds out the sources it held out."""
    import yaml

    from hsicam.config import DataConfig, dump_yaml
    from hsicam.data.spectral_sources import parse_holdout

    path = tmp_path / "config.yaml"
    path.write_text(dump_yaml(Config(data=DataConfig(holdout_sources="nist-cqs,,rawtoaces"))))
    assert yaml.safe_load(path.read_text())["data"]["holdout_sources"] == "nist-cqs,,rawtoaces"
    for overrides in ([], ["train.epochs=3"]):
        cfg = load_config(path, overrides)
        assert parse_holdout(cfg.data.holdout_sources) == ("nist-cqs", "rawtoaces")


@pytest.mark.parametrize("value, item", [("nist-cqs,,rawtoaces", 2), ("nist-cqs,", 2), (",nist-cqs", 1)])
def test_an_empty_held_out_item_in_a_config_file_given_with_config_is_refused(tmp_path, value, item):
    """A YAML file of the user's own (`--config my.yaml`) with `data: {holdout_sources: "nist-cqs,,rawtoaces"}`
    loaded without a word and held out one source fewer than typed, while the same value in `--set` is refused:
    now the same one line, naming the file; an override that replaces the value loads, and so does the run's own
    config.yaml written with it (the test above)."""
    from hsicam.cli import config_from_args
    from hsicam.engine.demo import demo_config

    path = tmp_path / "my.yaml"
    path.write_text(f"data:\n  holdout_sources: '{value}'\n")
    message = (f"{path}: data.holdout_sources: item {item} of {value!r} is empty (two commas in a row, or one at an "
               "end); give its value or remove the comma")
    for load in (config_from_args, demo_config):
        for overrides in ((), ("train.epochs=3",)):
            with pytest.raises(ConfigError) as exc:
                load(path, overrides)
            assert str(exc.value) == message
        assert load(path, ("data.holdout_sources=nist-cqs",)).data.holdout_sources == "nist-cqs"


# --------------------------------------------------------------------------------------------
# config.py: YAML
# --------------------------------------------------------------------------------------------
def test_yaml_12_octal_integers_are_read_in_base_8():
    assert load_config(None, ["train.seed=0o17", "data.synthetic_n=0o1_0"]).train.seed == 15
    assert load_config(None, ["data.synthetic_n=0o1_0"]).data.synthetic_n == 8


@pytest.mark.parametrize("text", ["0x_", "0o_", "0x__", "0o__"])
def test_a_hex_or_octal_prefix_without_digits_is_a_config_error_not_a_traceback(text, tmp_path):
    """`seed: 0x_` matched the YAML 1.2 integer pattern (digits optional after the prefix) and PyYAML's int()
    raised a ValueError: a traceback from `hsicam train`, in a file or in --set alike."""
    refused([f"train.seed={text}"], f"config key 'train.seed' must be an integer, got '{text}'")
    path = tmp_path / "c.yaml"
    path.write_text(f"train:\n  seed: {text}\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value) == f"{path}: config key 'train.seed' must be an integer, got '{text}'"


def test_two_merge_keys_in_one_mapping_are_not_a_key_given_twice():
    """`<<:` twice merges both anchors (PyYAML's merge); only real keys given twice are refused."""
    import yaml

    from hsicam.config import strict_yaml

    text = "a: &a {epochs: 3}\nb: &b {batch_size: 2}\ntrain:\n  <<: *a\n  <<: *b\n  lr: 0.001\n"
    assert strict_yaml(text)["train"] == yaml.safe_load(text)["train"] == {"epochs": 3, "batch_size": 2, "lr": 0.001}


def test_an_empty_run_config_is_refused_with_the_callers_words(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("# nothing here\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path, empty="the run's config.yaml is damaged")
    assert str(exc.value) == f"{path}: empty config (no settings); the run's config.yaml is damaged"
    assert load_config(path) == Config()  # without `empty`: the defaults


@pytest.mark.parametrize("text", ["{}\n", "camera:\n", "camera:\ntrain: {}\n"])
def test_a_config_of_empty_braces_or_empty_sections_is_an_empty_config(tmp_path, text):
    """`--config FILE` holding `{}` or `camera:` alone (a section whose settings were not indented under it) was the
    built-in paper camera, silently, where an empty or comment-only file is refused (a helper's hunt, session 71).
    A section with settings beside an empty one is still read."""
    from hsicam.cli import config_from_args

    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        config_from_args(path)
    assert str(exc.value).startswith(f"{path}: empty config (no settings); give a preset")
    path.write_text(("" if text.startswith("{}") else text) + "data: {synthetic_n: 7}\n")
    assert config_from_args(path).data.synthetic_n == 7


# --------------------------------------------------------------------------------------------
# config.py: what a resumed run may change (RUN_IDENTITY_KEYS) and what a training is (RUNTIME_ONLY_KEYS)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("override, difference", [
    ("data.split_seed=1", "data.split_seed: 0 → 1"),
    ("data.synthetic_n=16", "data.synthetic_n: 32 → 16"),
    ("data.patch_px=32", "data.patch_px: 64 → 32"),
    ("data.holdout_sources=none", "data.holdout_sources: 'nist-philips,rawtoaces' → 'none'"),
    ("data.val_pool=8", "data.val_pool: None → 8"),
    ("data.root=/somewhere", "data.root: None → '/somewhere'"),
    ("camera.cfa.period=4", "camera.cfa.period: 9 → 4"),
])
def test_a_resume_may_not_change_the_runs_scenes_split_or_camera(override, difference):
    assert identity_differences(Config(), load_config(None, [override])) == [difference]


@pytest.mark.parametrize("override", ["train.epochs=3", "train.keep_weights=last", "data.num_workers=0",
                                      "model.consistency.iterations=2", "train.lr=0.001"])
def test_a_resume_may_change_how_the_run_goes_on(override):
    assert identity_differences(Config(), load_config(None, [override])) == []


@pytest.mark.parametrize("override", ["train.keep_weights=last", "train.device=cpu", "data.num_workers=0",
                                      "model.consistency.iterations=2"])
def test_runtime_only_keys_train_the_same_camera(override):
    assert training_differences(Config(), load_config(None, [override])) == []


def test_dotted_keys_are_walked_the_same_way_in_a_config_and_in_its_mapping():
    """config_value reads a dotted key of the dataclasses (a default where a part is missing) and mapping_section finds
    its place in the same settings as a nested mapping (None where a section is missing or not a mapping)."""
    from hsicam.config import Config, config_value, mapping_section, to_dict

    cfg = Config()
    assert config_value(cfg, "camera.doe.material") == cfg.camera.doe.material
    assert config_value(cfg, "camera.doe.no_such_key", None) is None
    with pytest.raises(AttributeError):
        config_value(cfg, "camera.no_such_section.material")
    data = to_dict(cfg)
    section, name = mapping_section(data, "camera.doe.material")
    assert section is data["camera"]["doe"] and name == "material"
    section[name] = "table.csv"
    assert data["camera"]["doe"]["material"] == "table.csv"
    assert mapping_section(data, "camera.no_such_section.material") == (None, "material")
    assert mapping_section({"camera": None}, "camera.doe.material") == (None, "material")
    assert mapping_section({"camera": {"doe": "text"}}, "camera.doe.material") == (None, "material")
