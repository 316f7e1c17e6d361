"""A leading ``~`` in a path argument means the home folder, through argparse's public API (the
parser gives every path argument, :data:`hsicam.cli.PATH_METAVARS`, the ``type``
:func:`hsicam.cli.args.path_arg`): options, positionals, argument groups, sub-sub-commands, an
argument's own type (``--run``) after it. ``--set KEY=VALUE`` is no path: the config keeps the value
as written and a path key (``data.root``) is expanded where it is read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli_helpers import assert_ok, error_line, run_cli_in_process
from hsicam.cli import _Parser, build_parser
from hsicam.cli.args import path_arg
from hsicam.config import PRESETS_DIR, load_config
from hsicam.io import read_marker


@pytest.fixture
def home(tmp_path, monkeypatch) -> Path:
    h = tmp_path / "home"
    h.mkdir()
    monkeypatch.setenv("HOME", str(h))
    monkeypatch.chdir(tmp_path)
    return h


def parsed(*argv: str) -> dict:
    return vars(build_parser().parse_args(list(argv)))


def test_the_path_options_expand_a_tilde(home):
    a = parsed("train", "--config", "~/c.yaml", "--out", "~/run", "--set", "data.root=~/scenes")
    assert (a["config"], a["out"]) == (f"{home}/c.yaml", f"{home}/run")
    assert a["overrides"] == ["data.root=~/scenes"]  # not a path argument: as written
    a = parsed("evaluate", "--run", "~/run", "--data", "~/scenes", "--out", "~/ev")
    assert a["run"] == home / "run" and isinstance(a["run"], Path)  # --run's own type, after the expansion
    assert (a["data"], a["out"]) == (f"{home}/scenes", f"{home}/ev")
    a = parsed("tolerance", "--run", "~/run", "--data", "~/s.h5", "--out", "~/tol")
    assert (a["run"], a["data"], a["out"]) == (home / "run", f"{home}/s.h5", f"{home}/tol")


def test_positionals_groups_and_sub_sub_commands_expand_a_tilde_too(home):
    a = parsed("reconstruct", "~/sensor.png", "--run", "~/run", "--out", "~/x.npy", "--dark", "~/dark.npy",
               "--psf-dir", "~/psf")
    assert (a["sensor"], a["out"], a["dark"], a["psf_dir"]) == tuple(f"{home}/{n}" for n in ("sensor.png", "x.npy", "dark.npy", "psf"))
    assert parsed("data", "show", "~/scenes", "--out", "~/show")["path"] == f"{home}/scenes"
    assert parsed("pretrained", "copy", "standard", "~/copy")["dir"] == f"{home}/copy"
    assert parsed("baseline", "train-prior", "--out", "~/prior")["out"] == f"{home}/prior"


def test_only_a_leading_tilde_of_a_path_is_expanded(home):
    a = parsed("train", "--config", "tiny", "--out", "a~/b", "--set", "x=~/y")
    assert (a["config"], a["out"], a["overrides"]) == ("tiny", "a~/b", ["x=~/y"])
    assert parsed("psf", "--out", "~nobody_of_this_name/p")["out"] == "~nobody_of_this_name/p"  # as a shell leaves it
    a = parsed("psf", "--run", "pretrained:standard", "--out", "p")
    assert a["run"].name == "standard" and a["run"].is_dir()
    res = run_cli_in_process("evaluate", "--run", "pretrained:nope", "--out", "x")  # --run's own error, named
    assert error_line(res).startswith("hsicam: error: argument --run: no pre-trained camera 'nope' (available: ")


def test_set_keeps_a_path_value_as_written_and_it_is_expanded_where_read(home):
    from hsicam.data.pipeline import dataset_root

    cfg = load_config("tiny", parsed("train", "--config", "tiny", "--out", "r", "--set", "data.root=~/scenes")["overrides"])
    assert cfg.data.root == "~/scenes"  # saved in the run's config.yaml as written
    assert dataset_root(cfg.data, cfg.bands.to_bands()) == home / "scenes"


def test_a_command_reads_and_writes_in_home(home, tmp_path):
    """`--config ~/c.yaml --scene ~/scene.npy --out ~/sim`: the real command."""
    (home / "c.yaml").write_text((PRESETS_DIR / "tiny.yaml").read_text())
    np.save(home / "scene.npy", np.random.default_rng(0).uniform(0.1, 1, (7, 40, 40)).astype(np.float32))
    res = run_cli_in_process("simulate", "--config", "~/c.yaml", "--scene", "~/scene.npy", "--out", "~/sim")
    assert_ok(res)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["home"]  # no "./~" folder
    assert read_marker(home / "sim")["command"] == "simulate" and (home / "sim" / "sensor.png").is_file()


def test_the_expansion_uses_argparse_s_public_api():
    assert "_get_value" not in vars(_Parser)  # argparse's private conversion hook is left alone
    assert path_arg()("~/x") != "~/x" and path_arg(Path)("a~/x") == Path("a~/x")
    assert path_arg(int).__name__ == "int"  # argparse names the type in its "invalid int value" errors
