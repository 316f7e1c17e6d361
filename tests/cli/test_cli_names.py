"""The registries' names the command line reads torch-free (:mod:`hsicam.engine.names`).

`hsicam evaluate --help` and `hsicam experiment --help` took ~1.8 s: their choices imported the method
registry (torch) and the experiments to list the names. The names now come from hsicam.engine.names,
which imports nothing; these tests hold its copy of the method registry's names equal to the registry,
order included, so the two cannot drift, and check that the help and a refused name load no torch.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src"


def _run(*argv: str) -> subprocess.CompletedProcess:
    """``python -X importtime ARGV`` in a fresh process that imports this checkout's hsicam."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(SRC), env.get("PYTHONPATH")) if p)
    env["COLUMNS"] = "2000"  # argparse wraps help to the terminal, at hyphens too
    return subprocess.run([sys.executable, "-X", "importtime", *argv], capture_output=True, text=True, env=env,
                          timeout=120)


def _imported(stderr: str) -> set[str]:
    """The modules ``-X importtime`` reports (its lines: ``import time: SELF | CUMULATIVE | NAME``)."""
    return {line.rsplit("|", 1)[1].strip() for line in stderr.splitlines() if line.startswith("import time:")
            and "|" in line}


def _messages(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if not line.startswith("import time:")]


def test_the_method_names_are_the_registrys_names_and_aliases():
    """One home per list: the CLI's copy of the method names is exactly the registry's names (in registration
    order) and then the old names; the aliases, experiments and scales are the very objects the engine uses."""
    from hsicam.engine import experiments, methods, names

    assert names.METHOD_NAMES == (*methods.method_names(), *methods.METHOD_ALIASES)
    assert methods.METHOD_ALIASES is names.METHOD_ALIASES
    assert experiments.EXPERIMENTS is names.EXPERIMENTS and experiments.SCALES is names.SCALES
    assert all(methods.METHOD_ALIASES[old] in methods.method_names() for old in methods.METHOD_ALIASES)


def test_the_names_module_imports_nothing_heavy():
    res = _run("-c", "import hsicam.engine.names")
    assert res.returncode == 0, res.stderr
    assert not {"torch", "numpy", "hsicam.engine.methods", "hsicam.engine.experiments"} & _imported(res.stderr)


@pytest.mark.parametrize("command", ["evaluate", "experiment"])
def test_the_help_of_evaluate_and_experiment_loads_no_torch(command):
    """``python -m hsicam evaluate --help`` (and experiment's) lists the registries' names without importing
    torch or the method and experiment modules."""
    from hsicam.engine.names import EXPERIMENTS, METHOD_NAMES, SCALES

    res = _run("-m", "hsicam", command, "--help")
    assert res.returncode == 0, res.stderr
    loaded = _imported(res.stderr)
    assert "hsicam.cli" in loaded  # -X importtime did report the imports
    assert not {"torch", "hsicam.engine.methods", "hsicam.engine.experiments"} & loaded
    if command == "evaluate":
        assert f"reconstruction method: {', '.join(METHOD_NAMES)} (default: " in res.stdout
    else:
        assert f"the experiment ({', '.join(EXPERIMENTS)})" in res.stdout
        assert f"the preset of that name ({', '.join(SCALES)})" in res.stdout


@pytest.mark.parametrize("argv,listed", [
    (("evaluate", "--method", "gap-tv", "--out", "OUT"), "argument --method: invalid choice: 'gap-tv'"),
    (("experiment", "table1"), "argument NAME: invalid choice: 'table1'"),
    (("experiment", "compare", "--scale", "huge"), "argument --scale: invalid choice: 'huge'"),
])
def test_an_unknown_name_is_refused_listing_the_registrys_names(tmp_path, argv, listed):
    """An unknown method, experiment or scale is still a one-line usage error that lists every name (the
    method registry's names and old names, in the registry's order), before any output and without torch."""
    from hsicam.engine.experiments import EXPERIMENTS, SCALES
    from hsicam.engine.methods import METHOD_ALIASES, method_names

    names = {"--method": (*method_names(), *METHOD_ALIASES), "NAME": EXPERIMENTS, "--scale": SCALES}
    choices = next(v for k, v in names.items() if f"argument {k}:" in listed)
    out = tmp_path / "out"
    res = _run("-m", "hsicam", *(str(out) if a == "OUT" else a for a in argv))
    assert res.returncode == 2, res.stderr
    assert _messages(res.stderr)[-1] == (f"hsicam: error: {listed} (choose from "
                                         + ", ".join(repr(n) for n in choices) + ")")
    assert not {"torch", "hsicam.engine.methods"} & _imported(res.stderr)
    assert not out.exists()


def test_the_library_refuses_an_unknown_method_listing_the_registered_names():
    """:func:`build_method` (what a script calls) refuses an unknown name with the registered names (an old
    name is taken, not listed)."""
    from hsicam.engine.methods import build_method, method_names
    from hsicam.errors import InputError

    with pytest.raises(InputError) as err:
        build_method("gap-tv", None)
    assert str(err.value) == f"unknown method 'gap-tv'; choose one of {', '.join(method_names())}"
