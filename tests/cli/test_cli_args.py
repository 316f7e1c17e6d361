"""Command-line options and config names with a bad value: one line naming the option (or name) and
what it takes, exit code 2, before any work and before an output folder exists. In-process through
:func:`hsicam.cli.main`, the boundary the console script runs."""

from __future__ import annotations

import argparse
import re

import pytest

from hsicam.cli import main
from hsicam.cli.args import count_arg, non_negative_number_arg
from hsicam.config import PRESETS_DIR


def one_line_error(capsys, args: list[str]) -> str:
    """The one ``hsicam: error:`` line of a call that exits with code 2 (usage or input error)."""
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hsicam: error: "), err
    return lines[0]


@pytest.mark.parametrize("text,message", [("1", None), ("3", None), ("0", "must be >= 1, got 0"),
                                          ("-2", "must be >= 1, got -2"),
                                          ("two", "must be an integer >= 1, got 'two'"),
                                          ("1.5", "must be an integer >= 1, got '1.5'")])
def test_count_arg(text, message):
    if message is None:
        assert count_arg(text) == int(text)
    else:
        with pytest.raises(argparse.ArgumentTypeError, match=rf"^{message}$"):
            count_arg(text)


@pytest.mark.parametrize("text,message", [("0", None), ("0.002", None), ("1e-3", None),
                                          ("-1", "must be a finite number >= 0, got '-1'"),
                                          ("-0.001", "must be a finite number >= 0, got '-0.001'"),
                                          ("nan", "must be a finite number >= 0, got 'nan'"),
                                          ("inf", "must be a finite number >= 0, got 'inf'"),
                                          ("high", "must be a finite number >= 0, got 'high'")])
def test_non_negative_number_arg(text, message):
    if message is None:
        assert non_negative_number_arg(text) == float(text)
    else:
        with pytest.raises(argparse.ArgumentTypeError, match=rf"^{message}$"):
            non_negative_number_arg(text)


@pytest.mark.parametrize("option", ["--sensor-sigma", "--sigma-height-nm"])
def test_a_negative_test_noise_level_is_a_usage_error_before_the_data_is_read(tmp_path, capsys, monkeypatch, option):
    """``evaluate --sensor-sigma -1`` was refused only after the --data folder had been scanned and
    the method built (a negative σ once scored NaN as "inf dB"); now it is a usage error of the
    option, before any scene is listed and before --out exists."""
    import hsicam.data.datasets as datasets

    def no_scan(*a, **k):
        raise AssertionError("the data folder was scanned before the noise level was checked")

    monkeypatch.setattr(datasets, "list_scenes", no_scan)
    data, out = tmp_path / "data", tmp_path / "ev"
    data.mkdir()
    line = one_line_error(capsys, ["evaluate", "--config", "tiny", "--data", str(data), "--out", str(out),
                                   option, "-1"])
    assert line == f"hsicam: error: argument {option}: must be a finite number >= 0, got '-1'"
    assert not out.exists()


@pytest.mark.parametrize("value", ["0", "-1"])
def test_experiment_seeds_below_one_is_a_usage_error_before_any_work(tmp_path, capsys, monkeypatch, value):
    """``experiment --seeds 0`` ran as if 1; now it is the same error as ``evaluate --seeds 0``."""
    import hsicam.engine.experiments as experiments

    def no_work(*a, **k):
        raise AssertionError("the experiment started with a seed count below one")

    monkeypatch.setattr(experiments, "run_experiment", no_work)
    out = tmp_path / "exp"
    line = one_line_error(capsys, ["experiment", "ablation", "--scale", "tiny", "--seeds", value, "--out", str(out)])
    assert line == f"hsicam: error: argument --seeds: must be >= 1, got {value}"
    line = one_line_error(capsys, ["evaluate", "--config", "tiny", "--seeds", value, "--out", str(tmp_path / "ev")])
    assert line == f"hsicam: error: argument --seeds: must be >= 1, got {value}"
    assert not any(tmp_path.iterdir())


def test_experiment_seeds_reach_the_experiment(tmp_path, monkeypatch):
    import hsicam.engine.experiments as experiments

    seen = {}

    def record(name, scale, out, seeds):
        seen["seeds"] = seeds
        raise KeyboardInterrupt  # stop here: nothing to run

    monkeypatch.setattr(experiments, "run_experiment", record)
    assert main(["experiment", "ablation", "--scale", "tiny", "--seeds", "2", "--out", str(tmp_path / "e")]) == 130
    assert seen["seeds"] == (0, 1)


def test_an_unknown_config_name_lists_the_presets(tmp_path, capsys):
    names = ", ".join(sorted(p.stem for p in PRESETS_DIR.glob("*.yaml")))
    line = one_line_error(capsys, ["psf", "--config", "nonpreset", "--out", str(tmp_path / "psf")])
    assert line == f"hsicam: error: nonpreset: no such config file, nor a shipped preset (presets: {names})"
    assert not any(tmp_path.iterdir())


def test_a_config_file_with_a_key_given_twice_is_refused(tmp_path, capsys):
    path = tmp_path / "dup.yaml"
    path.write_text("train:\n  lr: 0.001\ntrain:\n  epochs: 3\n", encoding="utf-8")
    line = one_line_error(capsys, ["psf", "--config", str(path), "--out", str(tmp_path / "psf")])
    assert line == (f"hsicam: error: {path}: key 'train' is given twice (lines 1 and 3); YAML keeps only the last, "
                    "so remove one")
    line = one_line_error(capsys, ["psf", "--config", "tiny", "--set", "camera.doe={seed: 1, seed: 2}",
                                   "--out", str(tmp_path / "psf")])
    assert "key 'camera.doe.seed' is given twice; give it once" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dup.yaml"]


@pytest.mark.parametrize("option,value,message", [
    ("--max-scenes", "0", "must be >= 1, got 0"),
    ("--draws", "-1", "must be >= 1, got -1"),
    ("--draws", "1000000000000", "must be at most 1000 (each draw is a whole evaluation), got '1000000000000'"),
    ("--shift-subsamples", "0", "must be >= 1, got 0"),
    ("--sigma-height-nm", "0,10,-5", "every value must be a finite number in [0, 1000000] nm, got -5"),
    ("--sigma-height-nm", "nan", "every value must be a finite number in [0, 1000000] nm, got nan"),
    ("--sigma-height-nm", "0,1e300", "every value must be a finite number in [0, 1000000] nm, got 1e+300"),
    ("--levels", "2,1", "every value must be a power of 2 in 2..65536 (height levels that export-optics exports), got 1"),
    ("--levels", "2.5", "expected comma-separated integers, got '2.5'"),
    ("--shift-cells", "0,inf", "every value must be finite, got inf"),
    ("--sensor-distance-um", "nan", "every value must be finite, got nan"),
])
def test_tolerance_options_out_of_range_are_usage_errors_naming_the_option(tmp_path, capsys, monkeypatch, option,
                                                                            value, message):
    """``tolerance --max-scenes 0`` (or ``--draws``, ``--shift-subsamples``, a negative σ_p, a level
    below 2) used to load the run and then say "height_draws, max_scenes and shift_subsamples must be
    >= 1", naming none of the options; now each is a usage error of its option before any work."""
    import hsicam.runs.folder as folder

    def no_load(*a, **k):
        raise AssertionError("the run was loaded before the options were checked")

    monkeypatch.setattr(folder, "load_run", no_load)
    out = tmp_path / "tol"
    line = one_line_error(capsys, ["tolerance", "--run", "pretrained:standard", "--out", str(out), f"{option}={value}"])
    assert line == f"hsicam: error: argument {option}: {message}"
    assert not out.exists()


def test_list_types_live_with_the_other_argument_types():
    """The comma-separated list types are cli.args' (they were private to cli/fabrication.py), and the
    tolerance options take them from there."""
    import math

    from hsicam.cli import build_parser
    from hsicam.cli.args import finite_numbers_arg, levels_list_arg, list_arg, sigma_heights_arg

    odd = list_arg(int, "integers", lambda v: v % 2 == 1, "odd")
    assert odd("1, 3 ,5") == (1, 3, 5) and odd("") == ()
    with pytest.raises(argparse.ArgumentTypeError, match=r"^every value must be odd, got 4$"):
        odd("1,4")
    with pytest.raises(argparse.ArgumentTypeError, match=r"^expected comma-separated integers, got 'x'$"):
        odd("x")
    assert finite_numbers_arg("-1,0.5") == (-1.0, 0.5) and sigma_heights_arg("0,2") == (0.0, 2.0)
    assert levels_list_arg("2,512") == (2, 512) and math.isinf(list_arg(float, "numbers")("inf")[0])
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    types = {a.dest: a.type for a in sub.choices["tolerance"]._actions}
    assert types["sigma_height_nm"] is sigma_heights_arg and types["levels"] is levels_list_arg
    assert types["shift_cells"] is finite_numbers_arg and types["sensor_distance_um"] is finite_numbers_arg


@pytest.mark.parametrize("argv,value,item", [
    (["tolerance", "--run", "pretrained:standard", "--sigma-height-nm"], "0,,20", 2),
    (["tolerance", "--run", "pretrained:standard", "--levels"], "2,4,", 3),
    (["tolerance", "--run", "pretrained:standard", "--shift-cells"], ",0.5", 1),
    (["tolerance", "--run", "pretrained:standard", "--sensor-distance-um"], "-50, ,50", 2),
    (["tolerance", "--run", "pretrained:standard", "--levels"], ",", 1),
    (["data", "synth", "--config", "tiny", "--holdout-sources"], "nist-philips,,rawtoaces", 2),
])
def test_an_empty_item_of_a_list_option_is_refused_naming_it(tmp_path, capsys, monkeypatch, argv, value, item):
    """``--sigma-height-nm 0,,20`` (or a trailing comma) ran the study on 0 and 20 alone, and
    ``--holdout-sources a,,b`` held out a and b, without a word: every list option dropped its empty items. Now
    an empty item is a usage error of its option naming the item, before any work."""
    import hsicam.runs.folder as folder

    def no_load(*a, **k):
        raise AssertionError("the run was loaded before the options were checked")

    monkeypatch.setattr(folder, "load_run", no_load)
    out = tmp_path / "out"
    line = one_line_error(capsys, [*argv[:-1], f"{argv[-1]}={value}", "--out", str(out)])
    assert line == (f"hsicam: error: argument {argv[-1]}: item {item} of {value!r} is empty (two commas in a row, "
                    "or one at an end); give its value or remove the comma")
    assert [v.strip() for v in value.split(",")][item - 1] == ""  # the item named is the empty one
    assert not out.exists()


@pytest.mark.parametrize("field,value,message", [
    ("max_scenes", 0, "ToleranceSpec.max_scenes must be >= 1, got 0"),
    ("height_draws", -2, "ToleranceSpec.height_draws must be >= 1, got -2"),
    ("shift_subsamples", 0, "ToleranceSpec.shift_subsamples must be >= 1, got 0"),
    ("sigma_height_nm", (0.0, -1.0), "ToleranceSpec.sigma_height_nm values must be finite and >= 0, got -1"),
    ("sigma_height_nm", (0.0, 1e300), "ToleranceSpec.sigma_height_nm values must be at most 1000000 nm, got 1e\\+300"),
    ("levels", (4, 1), r"ToleranceSpec.levels \(height levels\) must be >= 2, got 1"),
    ("shift_cells", (0.0, float("nan")), "ToleranceSpec.shift_cells values must be finite, got nan"),
    ("sensor_distance_um", (float("-inf"),), "ToleranceSpec.sensor_distance_um values must be finite, got -inf"),
])
def test_tolerance_spec_names_the_field_it_refuses(field, value, message):
    from dataclasses import replace

    from hsicam.engine.tolerance import ToleranceSpec
    from hsicam.errors import InputError

    ToleranceSpec().check()  # the defaults pass
    with pytest.raises(InputError, match=rf"^{message}$"):
        replace(ToleranceSpec(), **{field: value}).check()


def test_simulates_seed_help_says_its_range_as_every_seed_key():
    """simulate --seed takes the range of every seed key and of data synth --seed, [0, 2^32 - 1], and says so."""
    from hsicam.cli import build_parser
    from hsicam.config import load_config

    parser = build_parser()
    assert parser.parse_args(["simulate", "--scene", "s.npy", "--out", "o", "--seed", str(2**32 - 1)]).seed == 2**32 - 1
    assert load_config("tiny", ["camera.doe.seed=0", f"train.seed={2**32 - 1}"]).train.seed == 2**32 - 1
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    (seed,) = [a for a in sub.choices["simulate"]._actions if a.dest == "seed"]
    assert "[0, 2^32 - 1]" in seed.help and "camera.doe.seed" in seed.help and "data synth" in seed.help


def test_a_test_sensor_noise_above_the_full_scale_is_a_usage_error(tmp_path, capsys):
    """``evaluate --sensor-sigma`` takes camera.sensor.sigma's range [0, 1]: the config refuses σ above the full
    scale (it buries any signal), and the option took any σ."""
    data, out = tmp_path / "data", tmp_path / "ev"
    data.mkdir()
    line = one_line_error(capsys, ["evaluate", "--config", "tiny", "--data", str(data), "--out", str(out),
                                   "--sensor-sigma", "1e30"])
    assert line == ("hsicam: error: argument --sensor-sigma: must be at most 1 (σ as a fraction of full scale, as "
                    "camera.sensor.sigma), got '1e30'")
    assert not out.exists()
    from hsicam.cli.args import sensor_sigma_arg

    assert sensor_sigma_arg("1") == 1.0 and sensor_sigma_arg("0.01") == 0.01


def test_a_height_noise_beyond_any_relief_is_refused_naming_its_option_or_key(tmp_path, capsys):
    """``evaluate --sigma-height-nm 1e300`` (or the config's camera.doe.sigma_height_nm / train.sigma_height_nm)
    overflowed the float32 heights and ended in 'sensor contains 1936 NaN or Inf value(s)', naming no option;
    σ_p now takes at most 1e6 nm (1 mm) wherever it is given."""
    from hsicam.cli.args import sigma_height_arg
    from hsicam.config import load_config
    from hsicam.errors import ConfigError

    data, out = tmp_path / "data", tmp_path / "ev"
    data.mkdir()
    line = one_line_error(capsys, ["evaluate", "--config", "tiny", "--data", str(data), "--out", str(out),
                                   "--sigma-height-nm", "1e300"])
    assert line.startswith("hsicam: error: argument --sigma-height-nm: must be at most 1000000 nm") and "'1e300'" in line
    assert not out.exists()
    assert sigma_height_arg("1000000") == 1e6 and sigma_height_arg("20") == 20.0
    with pytest.raises(ConfigError, match=r"camera.doe.sigma_height_nm must be at most 1000000 nm"):
        load_config("tiny", ["camera.doe.sigma_height_nm=1e300"])
    with pytest.raises(ConfigError, match=r"train.sigma_height_nm=\[0.0, 1e\+300\]"):
        load_config("tiny", ["train.sigma_height_nm=[0, 1e300]"])


@pytest.mark.parametrize("argv, option", [
    (["evaluate", "--config", "tiny", "--out", "E", "--sensor-sig", "0.1"], "--sensor-sig"),
    (["train", "--config", "tiny", "--out", "RUN", "--resum"], "--resum"),
    (["data", "synth", "--n", "1", "--siz", "16", "--out", "S"], "--siz"),
])
def test_an_abbreviated_option_is_a_usage_error_not_the_option_it_begins(tmp_path, capsys, monkeypatch, argv, option):
    """argparse's default takes a unique prefix for the whole option (``--sensor-sig`` for
    ``--sensor-sigma``), in subcommands of subcommands too; hsicam takes options only in full."""
    monkeypatch.chdir(tmp_path)
    line = one_line_error(capsys, argv)
    assert line.startswith("hsicam: error: unrecognized arguments:") and option in line
    assert list(tmp_path.iterdir()) == []


def test_counts_of_one_are_singular_in_the_summary_lines(tmp_path, capsys):
    """'trained 1 epochs', 'wrote 1 held-out scenes': the one-line summaries agree with their counts."""
    from hsicam.cli.train import summary_line

    assert summary_line({"epoch": 1, "step": 1}, "R").startswith("trained 1 epoch (1 step)")
    assert summary_line({"epoch": 2, "step": 8}, "R").startswith("trained 2 epochs (8 steps)")
    for n, split, what in (("1", "heldout", "1 held-out scene of"), ("2", "train", "2 scenes of")):
        assert main(["data", "synth", "--n", n, "--size", "16", "--split", split, "--out", str(tmp_path / split)]) == 0
        assert f"wrote {what} 16x16x31 to" in capsys.readouterr().out


def test_every_argument_of_every_command_says_what_it_is():
    """`hsicam COMMAND --help` explains each option and positional argument: none is listed bare
    (evaluate's --out, experiment's name and --scale, report's DIR, demo's --out and pretrained's NAME were)."""
    from hsicam.cli import build_parser

    def bare(parser, name):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, child in action.choices.items():
                    yield from bare(child, f"{name} {sub}")
            elif not (action.help or "").strip():
                yield f"{name} {'/'.join(action.option_strings) or action.dest}"

    assert list(bare(build_parser(), "hsicam")) == []


@pytest.mark.parametrize("argv", [
    ("evaluate", "--seeds", "99999999999999999999999", "--out", "OUT"),
    ("experiment", "compare", "--scale", "tiny", "--seeds", "99999999999999999999999", "--out", "OUT"),
    ("experiment", "noise", "--scale", "tiny", "--seeds", "1001", "--out", "OUT"),
])
def test_a_seed_count_beyond_the_bound_is_a_usage_error(tmp_path, argv):
    """`hsicam evaluate --seeds 99999999999999999999999` (and `experiment --seeds`) passed the parser and
    ended in an OverflowError traceback of range(); --seeds now takes at most MAX_SEEDS (1000)."""
    from cli_helpers import assert_clean_error, run_cli_in_process

    argv = tuple(str(tmp_path / "out") if a == "OUT" else a for a in argv)
    assert_clean_error(run_cli_in_process(*argv), "argument --seeds: must be at most 1000")
    assert not (tmp_path / "out").exists()


def test_the_parser_is_built_without_torch():
    """`hsicam --help`, `hsicam COMMAND --help` and a usage error waited ~2.5 s for torch and scipy, which the
    parser's modules imported (cli/camera.py, cli/reconstruct.py, the method and experiment registries behind
    evaluate's choices, Bands inside the configs). Built in a fresh process, the whole parser, its help and a
    usage error of every command load neither (the help of evaluate and experiment lists the registries' names,
    which loads them); a command that works still gets them."""
    import subprocess
    import sys

    script = (
        "import contextlib, io, sys\n"
        "from hsicam.cli import build_parser, main\n"
        "parser = build_parser()\n"
        "assert 'evaluate' in parser.format_help() and 'reconstruct' in parser.format_help()\n"
        "for command in ('psf', 'simulate', 'data', 'train', 'reconstruct', 'evaluate', 'experiment', 'report',\n"
        "                'demo', 'baseline', 'export-optics', 'tolerance', 'finetune', 'pretrained'):\n"
        "    if command not in ('evaluate', 'experiment'):  # their help lists the registries' names\n"
        "        with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "            main([command, '--help'])\n"
        "    with contextlib.redirect_stderr(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "        main([command, '--no-such-option'])\n"
        "print(sorted({'torch', 'scipy'} & set(sys.modules)))\n"
        "main(['psf', '--config', 'tiny', '--out', sys.argv[1]])\n"
        "print(sorted({'torch', 'scipy'} & set(sys.modules)))\n"
    )
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        res = subprocess.run([sys.executable, "-c", script, f"{tmp}/psf"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert lines[0] == "[]" and lines[-1] == "['scipy', 'torch']", res.stdout


def test_evaluate_and_experiment_choices_are_the_registries_names(capsys, monkeypatch):
    """The registry choices (read when a value is checked or the help written, not while the parser is built)
    are exactly the method and experiment registries' names: every one is taken, another is refused with the
    list, and each command's help lists them."""
    from hsicam.cli import build_parser
    from hsicam.engine.experiments import EXPERIMENTS, SCALES
    from hsicam.engine.methods import METHOD_ALIASES, method_names

    parser = build_parser()
    methods = (*method_names(), *METHOD_ALIASES)
    assert len(methods) >= 9 and "doe-learned" in methods and "dd-cassi-unrolled" in methods
    for method in methods:
        assert parser.parse_args(["evaluate", "--method", method, "--out", "o"]).method == method
    assert parser.parse_args(["evaluate", "--out", "o"]).method == "doe-learned"
    for name in EXPERIMENTS:
        for scale in SCALES:
            args = parser.parse_args(["experiment", name, "--scale", scale])
            assert (args.name, args.scale) == (name, scale)
    line = one_line_error(capsys, ["evaluate", "--method", "gap-tv", "--out", "o"])
    assert line == ("hsicam: error: argument --method: invalid choice: 'gap-tv' (choose from "
                    + ", ".join(repr(m) for m in methods) + ")")
    line = one_line_error(capsys, ["experiment", "table1"])
    assert line == ("hsicam: error: argument NAME: invalid choice: 'table1' (choose from "
                    + ", ".join(repr(e) for e in EXPERIMENTS) + ")")
    monkeypatch.setenv("COLUMNS", "2000")  # argparse wraps help to the terminal, at hyphens too
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    evaluate_help = sub.choices["evaluate"].format_help()
    assert f"reconstruction method: {', '.join(methods)} (default: " in evaluate_help
    experiment_help = sub.choices["experiment"].format_help()
    assert f"the experiment ({', '.join(EXPERIMENTS)})" in experiment_help
    assert f"the preset of that name ({', '.join(SCALES)})" in experiment_help


@pytest.mark.parametrize("value,bad", [("2,3", "3"), ("1", "1"), (str(2 * 2**16), str(2 * 2**16)), ("2,12,16", "12")])
def test_tolerance_levels_that_export_optics_refuses_are_a_usage_error_before_the_run_is_loaded(
        tmp_path, capsys, monkeypatch, value, bad):
    """``tolerance --levels 2,3``: its help said "each >= 2", and 3 passed the option only to be refused after the
    run was loaded (hsicam.engine.tolerance.check_levels: export-optics exports a power of 2 in 2..2^16 levels). The
    option now takes what its help says, the counts export-optics exports, and refuses the others at once."""
    import hsicam.runs.folder as folder
    from hsicam.config import MAX_HEIGHT_LEVELS
    from hsicam.engine.tolerance import check_levels
    from hsicam.errors import InputError

    def no_load(*a, **k):
        raise AssertionError("the run was loaded before the options were checked")

    monkeypatch.setattr(folder, "load_run", no_load)
    with pytest.raises(InputError, match=rf"--levels {bad}: hsicam export-optics exports only a power of 2"):
        check_levels(int(bad))  # the refusal the study would give later: the option refuses the same counts
    out = tmp_path / "out"
    line = one_line_error(capsys, ["tolerance", "--run", "pretrained:standard", "--out", str(out), "--levels", value])
    assert line == (f"hsicam: error: argument --levels: every value must be a power of 2 in 2..{MAX_HEIGHT_LEVELS} "
                    f"(height levels that export-optics exports), got {bad}")
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# What `hsicam COMMAND --help` claims, held to what the commands do (the claims read from the parser)
# ------------------------------------------------------------------------------------------------
def _help_claims() -> list[tuple[tuple[str, ...], argparse.Action, str]]:
    """(command words, action, its help as `--help` shows it, on one line) of every option and positional of every
    command and sub-command (``-h``, ``--version`` and the sub-command lists aside)."""
    from hsicam.cli import build_parser

    def walk(parser, words):
        formatter = parser._get_formatter()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    yield from walk(child, (*words, name))
            elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)) and action.help:
                yield words, action, " ".join(formatter._expand_help(action).split())

    return list(walk(build_parser(), ()))


def _name(words, action) -> str:
    return f"hsicam {' '.join(words)} {'/'.join(action.option_strings) or action.metavar or action.dest}"


#: "(default 16)", "(default: 0,10,20)", "; default 0)", "default runs/demo": the word or number list after "default";
#: a number followed by " ×" ("0.1 × the run's train.lr") is a description, not a value.
_DEFAULT_CLAIM = re.compile(r"\bdefault:? (-?[\w.][\w.-]*(?:[,/]-?[\w.][\w.-]*)*)(?=[;:),]|\s(?!×)|$)")
#: "same (default): …", "quick (minutes on a 2-core CPU, the default)".
_NAMED_DEFAULT = re.compile(r"([\w.-]+) \((?:[^()]*, )?(?:the )?default\)")
_NUMBERS = re.compile(r"-?\d+(?:\.\d+)?(?:,-?\d+(?:\.\d+)?)*")


def _fallbacks(tmp_path, monkeypatch) -> dict[tuple[tuple[str, ...], str], object]:
    """The value a command takes for an option whose argparse default is None (the command fills it in), by
    (command words, dest): tolerance's sweeps from the ToleranceSpec it starts from; reconstruct's --tv-weight,
    --read-noise-e and --cfa-offset as one reconstruct without them uses them (:func:`_reconstruct_fallbacks`)."""
    from hsicam.engine.tolerance import ToleranceSpec

    spec = ToleranceSpec()
    tolerance = {"draws": spec.height_draws, "shift_subsamples": spec.shift_subsamples,
                 **{k: getattr(spec, k) for k in ("sigma_height_nm", "levels", "shift_cells", "sensor_distance_um")}}
    return {**{(("tolerance",), k): v for k, v in tolerance.items()},
            **{(("reconstruct",), k): v for k, v in _reconstruct_fallbacks(tmp_path, monkeypatch).items()}}


def _reconstruct_fallbacks(tmp_path, monkeypatch) -> dict[str, float]:
    """``reconstruct --tv-steps 2 --full-well-e 1000`` without --tv-weight, --read-noise-e and --cfa-offset, stopped
    where its work starts: the TV weight of the consistency steps it builds (``tv_consistency``), the read noise it
    gives the capture's noise model (``capture_noise``) and the capture's place on the sensor it passes there."""
    import numpy as np

    import hsicam.cli.reconstruct as reconstruct

    seen: dict[str, float] = {}
    build = reconstruct.tv_consistency

    def tv_consistency(model, args):
        steps = build(model, args)
        seen["tv_weight"] = steps.tv_weight
        return steps

    def capture_noise(model, report, full_well_e, read_noise_e, corr=None, offset=None, orientation="as-read"):
        seen["read_noise_e"] = read_noise_e
        seen["cfa_offset"] = offset  # the capture's place, found before its noise (a flat field's gain map sits there)
        raise _Reached()

    monkeypatch.setattr(reconstruct, "tv_consistency", tv_consistency)
    monkeypatch.setattr(reconstruct, "capture_noise", capture_noise)
    capture = tmp_path / "capture.npy"
    np.save(capture, np.full((64, 64), 0.25, np.float32))
    with pytest.raises(_Reached):
        main(["reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(tmp_path / "cube.h5"),
              "--tv-steps", "2", "--full-well-e", "1000"])
    assert set(seen) == {"tv_weight", "read_noise_e", "cfa_offset"}, seen
    return seen


def _same_value(claim: str, value) -> bool:
    values = value if isinstance(value, (tuple, list)) else (value,)
    if _NUMBERS.fullmatch(claim):
        try:
            return [float(v) for v in claim.split(",")] == [float(v) for v in values]
        except (TypeError, ValueError):
            return False
    return claim == ",".join(str(v) for v in values)


def test_every_default_a_help_states_is_the_value_the_command_takes(tmp_path, monkeypatch):
    """A help's "(default X)" (or "X (default)") is the option's argparse default, and an option with a default of
    its own says it; where the argparse default is None and the command fills in the value (tolerance's sweeps,
    reconstruct's --tv-weight, --read-noise-e and --cfa-offset, captured where one reconstruct uses them), a value
    the help states is the one the command takes. A help's default written in words ("the run's train.epochs") is not
    checked here."""
    fallbacks = _fallbacks(tmp_path, monkeypatch)
    wrong, unsaid, unknown = [], [], []
    for words, action, text in _help_claims():
        claims = _DEFAULT_CLAIM.findall(text) + _NAMED_DEFAULT.findall(text)
        default = action.default
        if not (default is None or isinstance(default, bool) or default == [] or default == argparse.SUPPRESS):
            if not any(_same_value(c, default) for c in claims):
                unsaid.append(f"{_name(words, action)}: default {default!r}, help {text!r}")
            wrong += [f"{_name(words, action)}: help says default {c}, argparse's is {default!r}"
                      for c in claims if _NUMBERS.fullmatch(c) and not _same_value(c, default)]
            continue
        for claim in claims:
            if not _NUMBERS.fullmatch(claim):
                continue  # in words
            key = (words, action.dest)
            if key not in fallbacks:
                unknown.append(f"{_name(words, action)}: help says default {claim}; add where the command takes it")
            elif not _same_value(claim, fallbacks[key]):
                wrong.append(f"{_name(words, action)}: help says default {claim}, the command takes {fallbacks[key]!r}")
    assert (wrong, unsaid, unknown) == ([], [], [])


def test_the_default_claims_are_read_as_the_help_writes_them():
    """The readers of the test above on the forms the helps use (so that it checks what it should)."""
    assert _DEFAULT_CLAIM.findall("at most this many scenes, >= 1 (default 16)") == ["16"]
    assert _DEFAULT_CLAIM.findall("σ_p (nm) (default: 0,10,20,40,60)") == ["0,10,20,40,60"]
    assert _DEFAULT_CLAIM.findall("Δz (µm) (default: -100,-50,0); a list") == ["-100,-50,0"]
    assert _DEFAULT_CLAIM.findall("(default 0,0: the capture starts)") == ["0,0"]
    assert _DEFAULT_CLAIM.findall("read noise (needs --full-well-e; default 0)") == ["0"]
    assert _DEFAULT_CLAIM.findall("demo folder (default runs/demo): the run") == ["runs/demo"]
    assert _DEFAULT_CLAIM.findall("(default: 0.1 × the run's train.lr)") == []
    assert _DEFAULT_CLAIM.findall("%(choices)s (default: doe-learned, the run's camera)") == ["doe-learned"]
    assert _DEFAULT_CLAIM.findall("(default: 4× its context)") == []
    assert _NAMED_DEFAULT.findall("same (default): sensor as large") == ["same"]
    assert _NAMED_DEFAULT.findall("tiny (seconds), quick (minutes on a 2-core CPU, the default), paper") == ["quick"]
    assert _same_value("0,10", (0.0, 10.0)) and _same_value("cpu", "cpu") and not _same_value("3", 4)


def test_every_choice_of_an_option_is_named_in_its_help():
    """An option with choices explains each (or lists them with %(choices)s): a choice added to the code and not
    to the help, or one named in the help that the option no longer takes, fails."""
    missing = []
    for words, action, text in _help_claims():
        if action.choices is None:
            continue
        missing += [f"{_name(words, action)}: {choice}" for choice in action.choices
                    if not re.search(rf"(?<![\w-]){re.escape(choice)}(?![\w-])", text)]
        named = set(re.findall(r"(?:^|; )([\w-]+)(?: \([^()]*\))?: ", text))  # "same (default): …; valid: …"
        missing += [f"{_name(words, action)}: the help explains {n!r}, no choice" for n in named - set(action.choices)]
    assert missing == []


def _bound(text: str):
    """A range's bound as a help writes it: an integer, a decimal number, or 2^N - K."""
    m = re.fullmatch(r"(\d+)\^(\d+)(?: - (\d+))?", text.strip())
    if m:
        return int(m[1]) ** int(m[2]) - int(m[3] or 0)
    return int(text) if re.fullmatch(r"-?\d+", text.strip()) else float(text)


#: "in [0, 1]", "in (0, 1]", "1 to 1000", "in 2..65536", ">= 16", "> 0": (low, low included, high, high included).
_RANGES = (
    (re.compile(r"\bin ([\[(])([^,\]]+), ([^\]]+)\]"), lambda m: (_bound(m[2]), m[1] == "[", _bound(m[3]), True)),
    (re.compile(r"(?<![\d.+])(\d+) to (\d+)\b"), lambda m: (int(m[1]), True, int(m[2]), True)),
    (re.compile(r"\bin (\d+)\.\.(\d+)\b"), lambda m: (int(m[1]), True, int(m[2]), True)),
    (re.compile(r"(?<![-\w])>= (-?\d+(?:\.\d+)?)\b"), lambda m: (_bound(m[1]), True, None, True)),
    (re.compile(r"(?<![-\w=])> (-?\d+(?:\.\d+)?)\b"), lambda m: (_bound(m[1]), False, None, True)),
)


class _Reached(Exception):
    """Raised where a command starts its work: every check of its options passed."""


#: Runs loaded by the tolerance harness, by (run, device): its checks of the sweeps need the run's optics, and a
#: probe stops before any work, so one load serves every probe.
_LOADED_RUNS: dict = {}


def _command_harness(words, tmp_path, monkeypatch):
    """The arguments that take ``words``' command to its checks of the options, with its first step of work
    replaced by :class:`_Reached` (None: the command's options are checked by their argparse types alone).
    ``tolerance`` loads its run (once, :data:`_LOADED_RUNS`) and checks its sweeps against the optics before it
    reads its scenes."""
    import hsicam.data.preview
    import hsicam.data.synthetic
    import hsicam.engine.calibration
    import hsicam.engine.methods
    import hsicam.engine.tolerance
    import hsicam.export
    import hsicam.runs.folder

    def reached(*a, **k):
        raise _Reached()

    out = tmp_path / "out"
    data = tmp_path / "data"
    data.mkdir(exist_ok=True)
    harness = {
        ("data", "synth"): (hsicam.data.synthetic, "is_complete", ["--config", "tiny", "--out", str(out)]),
        ("data", "show"): (hsicam.data.preview, "write_preview", [str(data), "--out", str(out)]),
        ("reconstruct",): (hsicam.runs.folder, "load_run",
                           [str(tmp_path / "capture.npy"), "--run", "pretrained:standard", "--out", str(out / "c.h5")]),
        ("evaluate",): (hsicam.engine.methods, "build_method", ["--config", "tiny", "--out", str(out)]),
        ("export-optics",): (hsicam.export, "export_optics", ["--run", "pretrained:standard", "--out", str(out)]),
        ("finetune",): (hsicam.engine.calibration, "finetune",
                        ["--run", "pretrained:standard", "--psf-dir", str(data), "--out", str(out)]),
        # one shift of 0 cells: the default shifts (0.25 cell) take only a --shift-subsamples that is a multiple of 4
        ("tolerance",): (hsicam.engine.tolerance, "evaluation_scenes",
                         ["--run", "pretrained:standard", "--out", str(out), "--shift-cells=0"]),
    }
    if words not in harness:
        return None
    if words == ("tolerance",):
        load_run = hsicam.runs.folder.load_run

        def load_once(run, device="cpu"):
            key = (str(run), str(device))
            if key not in _LOADED_RUNS:
                _LOADED_RUNS[key] = load_run(run, device)
            return _LOADED_RUNS[key]

        monkeypatch.setattr(hsicam.runs.folder, "load_run", load_once)
    module, name, argv = harness[words]
    monkeypatch.setattr(module, name, reached)
    return [*words, *argv]


def _needs(text: str) -> list[str]:
    return re.findall(r"\bneeds (--[\w-]+)", text)


def _outcome(capsys, argv) -> str:
    """"reached" when the command passed every check, else its one error line."""
    from hsicam.cli import main

    try:
        code = main(argv)
    except _Reached:
        return "reached"
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, (argv, err)
    return err.strip()


#: Options whose help states a lower bound only, while the command also refuses values far above it for a reason no
#: help can state as a number: the memory the machine has (data synth --size: the scene cube; tolerance
#: --shift-subsamples: the misalignment study's pupil, hsicam.engine.tolerance.check_shift_sampling). Their values
#: well above the bound are taken or refused by that memory budget (a refusal naming HSICAM_MEMORY_BUDGET_MB).
_CAPPED_BY_MEMORY = {(("data", "synth"), "--size"), (("tolerance",), "--shift-subsamples")}


def _clauses(text: str) -> list[str]:
    """A help's clauses: its text split at ';', each parenthesised group a clause of its own (an interval's
    "(0, 1]" is no group)."""
    groups: list[str] = []

    def pull(m) -> str:
        groups.append(m[1])
        return ";"

    outer = None
    while outer != text:  # innermost groups first
        outer, text = text, re.sub(r"(?<!\bin )\(([^()]*)\)", pull, text)
    return [clause for part in (text, *groups) for clause in part.split(";")]


def _range_cases():
    """The ranges each valued option's help states, read in its clauses that name no other option (a clause about
    another option, "with --seeds N > 1", states that option's range)."""
    cases = []
    for words, action, text in _help_claims():
        if action.nargs == 0 or not action.option_strings:
            continue
        own = [c for c in _clauses(text) if set(re.findall(r"--[\w-]+", c)) <= set(action.option_strings)]
        for pattern, bounds in _RANGES:
            cases += [pytest.param(words, action.option_strings[0], bounds(m),
                                   clause[:m.start()].endswith("power of 2 "),
                                   id=f"{' '.join(words)} {action.option_strings[0]} {m[0]}")
                      for clause in own for m in pattern.finditer(clause)]
    return cases


def test_a_range_in_a_clause_about_another_option_is_not_read_as_this_ones(monkeypatch):
    """A valued option's help that states another option's range ("with --seeds N > 1", "12 to 24 steps of
    --tv-steps") made a false case of this option's range; only the clauses of a help (split at ';' and out of its
    parentheses, an interval's "(0, 1]" aside) that name no other option are read for ranges."""
    import hsicam.cli

    parser = argparse.ArgumentParser(prog="x")
    parser.add_argument("--every", type=int, help="save every N steps, >= 1 (with --seeds N > 1: one file per seed); "
                                                  "12 to 24 steps of --tv-steps are usual; --every in [1, 50] saves")
    parser.add_argument("--weight", type=float, help="weight, in (0, 1] as train.lr (default: 0.1 × the run's "
                                                     "train.lr; with --resume, the rate it started with)")
    monkeypatch.setattr(hsicam.cli, "build_parser", lambda: parser)
    assert [p.values[1:3] for p in _range_cases()] == [("--every", (1, True, 50, True)),
                                                       ("--every", (1, True, None, True)),
                                                       ("--weight", (0, False, 1, True))]


def _probes(low, low_in, high, integer: bool, powers_of_two: bool) -> tuple[list, list]:
    """(values the range takes, values it refuses), the ends and just beyond them aside: inside a closed range a few
    interior values; above a one-sided bound values well above it (low + 1, low + 2, low + 10 and
    max(1000, 1000·|low|)), so that a cap the help does not state fails. A range of powers of 2 ("a power of 2 in
    2..65536") takes its interior powers and refuses the integers between them."""
    if powers_of_two:
        inside = [2 * low, 2 ** ((low.bit_length() + high.bit_length()) // 2 - 1), high // 2]
        return [v for v in inside if low < v < high], [v for v in (low + 1, 3 * low, high - 1) if v & (v - 1)]
    if high is None:
        return [low + 1, low + 2, low + 10, max(1000, 1000 * abs(low))], []
    if integer:
        return [v for v in (low + 1, (low + high) // 2, high - 1) if low < v < high], []
    return [low + (high - low) * f for f in (1e-3, 0.5, 0.999)], []


@pytest.mark.parametrize("words,option,bounds,powers_of_two", _range_cases())
def test_every_range_a_help_states_is_the_one_the_command_enforces(tmp_path, capsys, monkeypatch, words, option,
                                                                   bounds, powers_of_two):
    """Each range a help states ("in [0, 1]", "1 to 1000", "a power of 2 in 2..65536", ">= 16", "> 0") is the one
    enforced: taken (by the option's type, and by the command's own checks up to its first step of work) are its
    included ends, a few values inside a closed range, and values well above a one-sided bound (up to
    max(1000, 1000·|low|); not for the options in :data:`_CAPPED_BY_MEMORY`); refused, in one line naming the
    option, are the values just beyond its ends (and the integers between the powers of a range of powers of 2).
    ``tolerance --levels`` said ">= 2" and its study refused 3 once the run was loaded; ``finetune --lr`` said
    "> 0" and refused 2."""
    action, text = next((a, t) for w, a, t in _help_claims() if w == words and option in a.option_strings)
    argv = _command_harness(words, tmp_path, monkeypatch)
    companions = [f"{need}=2" for need in _needs(text)]

    def typed(value) -> bool:
        try:
            action.type(str(value))
        except (argparse.ArgumentTypeError, ValueError):
            return False
        return True

    def takes(value) -> bool:  # by the option's type, then by the command's checks
        return typed(value) and (argv is None or _outcome(capsys, [*argv, *companions, f"{option}={value}"]) == "reached")

    def refuses(value, why: str = "") -> bool:  # by the option's type, else by the command's checks, naming the option
        if not typed(value):
            return not why
        line = "reached" if argv is None else _outcome(capsys, [*argv, *companions, f"{option}={value}"])
        return line != "reached" and option in line and why in line

    integer = not typed("1.5")
    low, low_in, high, high_in = bounds
    step = (lambda v: 1) if integer else (lambda v: max(abs(v) * 1e-6, 1e-12))
    taken = [low if low_in else low + step(low)]
    refused = [low - step(low) if low_in else low]
    if high is not None:
        taken.append(high)
        refused.append(high + step(high))
    inside, between = _probes(low, low_in, high, integer, powers_of_two)
    memory = high is None and (words, option) in _CAPPED_BY_MEMORY
    taken += [] if memory else inside
    refused += between
    capped = [v for v in inside if memory and not (takes(v) or refuses(v, "HSICAM_MEMORY_BUDGET_MB"))]
    assert ([v for v in taken if not takes(v)], [v for v in refused if not refuses(v)], capped) == ([], [], []), bounds


def test_the_options_capped_by_memory_state_a_lower_bound_only():
    """Every exemption of :data:`_CAPPED_BY_MEMORY` names an option whose help states a one-sided range (an
    option renamed, or given an upper bound, leaves no stale exemption behind)."""
    one_sided = {(words, option) for words, option, (_, _, high, _), _ in (p.values for p in _range_cases())
                 if high is None}
    assert _CAPPED_BY_MEMORY <= one_sided


def _companion_cases():
    cases = []
    for words, action, text in _help_claims():
        for need in _needs(text):
            cases.append(pytest.param(words, action.option_strings[0], need, "needs", id=f"{action.option_strings[0]} "
                                      f"needs {need}"))
        for clause in re.findall(r"\bnot with ((?:--[\w-]+(?:, | or )?)+)", text):
            cases += [pytest.param(words, action.option_strings[0], other, "not with",
                                   id=f"{action.option_strings[0]} not with {other}")
                      for other in re.findall(r"--[\w-]+", clause)]
    return cases


@pytest.mark.parametrize("words,option,other,how", _companion_cases())
def test_what_a_help_says_an_option_needs_or_excludes_is_refused_without_or_with_it(tmp_path, capsys, monkeypatch,
                                                                                     words, option, other, how):
    """"needs --Y": the option without --Y is refused in one line naming both; "not with --Y": the two together
    are. (A choice-valued option: one of its choices is.)"""
    claims = {a.option_strings[0]: (a, t) for w, a, t in _help_claims() if w == words and a.option_strings}
    action, text = claims[option]
    argv = _command_harness(words, tmp_path, monkeypatch)
    assert argv is not None, f"{' '.join(words)}: add its command to _command_harness"
    values = [c for c in action.choices if c != action.default] if action.choices else ["2"]
    extra = []
    if how == "not with":
        extra = [f"{other}=2", *(f"{n}=2" for n in _needs(claims[other][1]))]
    lines = [_outcome(capsys, [*argv, *extra, f"{option}={v}"]) for v in values]
    assert any(line != "reached" and option in line and other in line for line in lines), lines
