"""The project's set-up and its maintainer tools fail loudly and cleanly: the Makefile repairs a ``.venv`` whose python
no longer runs and installs a changed ``TORCH_SPEC``; ``benchmarks/bench_cli.py`` refuses to time a CLI that fails;
the scripts and benchmarks answer bad arguments with one usage line (exit 2) before any work, never a traceback;
``hsicam --version``."""

from __future__ import annotations

import importlib.util
import inspect
import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS, BENCHMARKS = ROOT / "scripts", ROOT / "benchmarks"


# --- Makefile --------------------------------------------------------------------------------------------------------

#: A stand-in for ``python3``: ``-m venv DIR`` makes DIR/bin/python, a script that logs its arguments (pip's installs
#: among them) and succeeds; so the Makefile's set-up runs for real in a second, offline, without pip.
FAKE_PYTHON = """#!/bin/sh
echo "base $*" >> "$LOG"
if [ "$1 $2" = "-m venv" ]; then
    mkdir -p "$3/bin"
    printf '#!/bin/sh\\necho "venv $*" >> "$LOG"\\n' > "$3/bin/python"
    chmod +x "$3/bin/python"
fi
"""


@pytest.fixture
def make_dir(tmp_path):
    if shutil.which("make") is None:
        pytest.skip("no make")
    shutil.copy(ROOT / "Makefile", tmp_path / "Makefile")
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    fake = tmp_path / "fake-python3"
    fake.write_text(FAKE_PYTHON)
    fake.chmod(0o755)
    return tmp_path


def _make(where: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "LOG": str(where / "log")}
    env.pop("MAKEFLAGS", None)
    return subprocess.run(["make", "-C", str(where), f"PYTHON={where / 'fake-python3'}", *args], capture_output=True,
                          text=True, timeout=60, env=env)


def _log(where: Path) -> list[str]:
    """The python calls logged since the last look."""
    log = where / "log"
    lines = log.read_text().splitlines() if log.exists() else []
    log.unlink(missing_ok=True)
    return lines


def test_make_rebuilds_a_venv_whose_python_no_longer_runs(make_dir):
    """A base python upgraded or removed leaves .venv/bin/python3 a dangling link: the stamp looked current (`make
    test` then failed with 'not found'), and `test -x` never rebuilt it. Now the stamp is stale, the venv is made
    anew and installed again, and then it is up to date."""
    assert _make(make_dir, "setup").returncode == 0
    assert "base -m venv .venv" in _log(make_dir)
    assert _make(make_dir, "-q", "setup").returncode == 0  # set up: nothing to do
    python = make_dir / ".venv" / "bin" / "python"
    python.unlink()
    python.symlink_to("/nonexistent/python3")
    assert _make(make_dir, "-q", "setup").returncode == 1  # stale
    proc = _make(make_dir, "setup")
    assert proc.returncode == 0, proc.stderr
    calls = _log(make_dir)
    assert "base -m venv .venv" in calls and "venv -m pip install -q -e .[dev]" in calls
    assert python.is_file() and not python.is_symlink()
    assert _make(make_dir, "-q", "setup").returncode == 0


def test_make_installs_a_changed_torch_spec_into_an_existing_venv(make_dir):
    """`make test TORCH_SPEC=torch` (README) on a set-up .venv did nothing: the stamp depended on pyproject.toml and
    the Makefile only. The spec installed is recorded; another one reruns the install, the same one does not."""
    assert _make(make_dir, "setup").returncode == 0
    assert "venv -m pip install -q torch==2.13.0" in _log(make_dir)
    assert _make(make_dir, "-q", "setup", "TORCH_SPEC=torch==2.13.0").returncode == 0
    assert _make(make_dir, "-q", "setup", "TORCH_SPEC=torch").returncode == 1
    assert (make_dir / ".venv" / ".torch-spec").read_text() == "torch==2.13.0\n"
    assert _make(make_dir, "setup", "TORCH_SPEC=torch").returncode == 0
    calls = _log(make_dir)
    assert "venv -m pip install -q torch" in calls and "base -m venv .venv" not in calls  # the venv is kept
    assert _make(make_dir, "-q", "setup", "TORCH_SPEC=torch").returncode == 0
    assert _make(make_dir, "-q", "setup").returncode == 1  # back to the pinned one: installed again


def test_make_lint_installs_its_pinned_ruff_once_and_checks_src(make_dir):
    """`make lint` puts the Makefile's RUFF_VERSION into the venv when the venv's ruff is missing or another version,
    not when it is that one, and runs it on src/ (the rules are pyproject.toml's)."""
    assert _make(make_dir, "setup").returncode == 0
    _log(make_dir)
    ruff = make_dir / ".venv" / "bin" / "ruff"

    def fake_ruff(version: str, findings: bool = False) -> None:
        check = 'echo "ruff $*" >> "$LOG"' + ("; echo 'src/x.py:1:1: F401 unused'; exit 1" if findings else "")
        ruff.write_text(f'#!/bin/sh\nif [ "$1" = --version ]; then echo "ruff {version}"; else {check}; fi\n')
        ruff.chmod(0o755)

    def calls() -> list[str]:  # (less the python start that tells whether the venv still runs)
        return [c for c in _log(make_dir) if c != "venv -c "]

    pinned = re.search(r"^RUFF_VERSION \?= (\S+)$", (make_dir / "Makefile").read_text(), re.M).group(1)
    fake_ruff("0.0.1")
    proc = _make(make_dir, "lint")
    assert proc.returncode == 0, proc.stderr
    tests = "ruff check --select F --ignore F811 tests benchmarks scripts"
    assert calls() == [f"venv -m pip install -q ruff=={pinned}", "ruff check src", tests]
    fake_ruff(pinned)
    assert _make(make_dir, "lint").returncode == 0
    assert calls() == ["ruff check src", tests]
    fake_ruff(pinned, findings=True)  # a finding fails the target, with ruff's line shown
    proc = _make(make_dir, "lint")
    assert proc.returncode != 0 and "src/x.py:1:1: F401 unused" in proc.stdout, proc.stdout + proc.stderr

# --- bench_cli.py ----------------------------------------------------------------------------------------------------


def test_bench_cli_refuses_to_time_a_cli_that_fails(tmp_path):
    """A CLI that crashes at start-up exits fast: its 'start-up times' were printed as a passing benchmark (exit 0).
    Each command's exit code is checked before it is timed; a wrong one is an ``error`` in the JSON and exit 1."""
    broken = tmp_path / "src" / "hsicam"
    (broken / "cli").mkdir(parents=True)
    (broken / "__init__.py").write_text("")
    (broken / "memory.py").write_text("def keep_freed_memory():\n    return False\n")  # what timing.py imports
    for module in (broken / "cli" / "__init__.py", broken / "__main__.py"):
        module.write_text("raise ImportError('a broken hsicam for the test')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "src")}
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "bench_cli.py"), "--repeats", "1"], capture_output=True,
                          text=True, timeout=60, env=env)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    out = json.loads(proc.stdout)
    assert "--help exited 1, expected 0" in out["error"] and "a broken hsicam for the test" in out["error"]
    assert "help_s" not in out and "Traceback" not in proc.stderr


# --- bad arguments: one usage line, exit 2, before any work ----------------------------------------------------------


def _load(path: Path):
    """The script or benchmark at ``path`` as a module (benchmarks import their sibling ``timing``)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(f"_under_test_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _usage_error(capsys, monkeypatch, path: Path, *argv: str) -> str:
    """``path``'s main() run on ``argv``: it must end in a usage error (exit 2: raised, or returned for sys.exit),
    whose one error line is returned."""
    monkeypatch.setattr(sys, "argv", [path.name, *argv])  # the benchmarks read sys.argv
    main = _load(path).main
    try:
        code = main(list(argv)) if inspect.signature(main).parameters else main()
    except SystemExit as stop:
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize("argv, said", [
    ((), "the following arguments are required: metrics, minutes, preset"),  # was an IndexError
    (("/nonexistent.jsonl", "1", "quick"), "No such file or directory: '/nonexistent.jsonl'"),  # FileNotFoundError
    (("{metrics}", "0", "quick"), "argument minutes: must be a finite number > 0"),
    (("{unfinished}", "1", "quick"), "not a finished run's metrics.jsonl (no final record)"),  # an IndexError
    (("{metrics}", "1", "quick", "--set", "camera.nosuch=1"), "unknown config key 'camera.nosuch'"),  # ConfigError
])
def test_calibrate_epochs_bad_arguments(capsys, monkeypatch, tmp_path, argv, said):
    (tmp_path / "m.jsonl").write_text('{"step": 1, "epoch": 0, "train_loss": 0.1, "elapsed_s": 1.0}\n'
                                      '{"step": 1, "epoch": 1, "final": true, "elapsed_s": 2.0}\n')
    (tmp_path / "u.jsonl").write_text('{"step": 1, "epoch": 0, "train_loss": 0.1, "elapsed_s": 1.0}\n')
    argv = [a.format(metrics=tmp_path / "m.jsonl", unfinished=tmp_path / "u.jsonl") for a in argv]
    assert said in _usage_error(capsys, monkeypatch, SCRIPTS / "calibrate_epochs.py", *argv)


def test_calibrate_epochs_as_a_command_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, str(SCRIPTS / "calibrate_epochs.py"), str(tmp_path / "none.jsonl"), "1",
                           "tiny"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.splitlines()[-1].endswith(f"No such file or directory: '{tmp_path / 'none.jsonl'}'")


def test_pretrained_figure_unknown_camera(capsys, monkeypatch, tmp_path):
    line = _usage_error(capsys, monkeypatch, SCRIPTS / "pretrained_figure.py", "nosuch", str(tmp_path / "f.png"))
    assert "no pre-trained camera 'nosuch'" in line  # was an InputError traceback
    assert not (tmp_path / "f.png").exists()


def test_psf_compare_figure_unreadable_stacks(capsys, monkeypatch, tmp_path):
    script = SCRIPTS / "psf_compare_figure.py"
    out = str(tmp_path / "f.png")
    assert "No such file or directory" in _usage_error(capsys, monkeypatch, script, out, f"a={tmp_path / 'no.npy'}")
    (tmp_path / "text.npy").write_text("not an array\n")
    assert "text.npy: not a .npy array" in _usage_error(capsys, monkeypatch, script, out, f"a={tmp_path / 'text.npy'}")
    assert "argument --bands" in _usage_error(capsys, monkeypatch, script, out, "a=x.npy", "--bands", "420,green")
    assert not (tmp_path / "f.png").exists()


@pytest.mark.parametrize("argv, said", [
    (("--iterations", "a,b"), "argument --iterations: expected comma-separated integers"),  # after loading the data
    (("--iterations", "0"), "argument --iterations: every value must be >= 1"),
    (("--weights", "0.1>x"), "argument --weights: expected numbers or schedules a>b, got '0.1>x'"),
])
def test_tune_gaptv_bad_arguments(capsys, monkeypatch, argv, said):
    assert said in _usage_error(capsys, monkeypatch, SCRIPTS / "tune_gaptv.py", *argv)


@pytest.mark.parametrize("script, argv, said", [
    ("bench_networks.py", ("--kinds", "quick,bogus", "--run", "none"), "--kinds: unknown kind 'bogus'"),  # a KeyError
    ("bench_networks.py", ("--kinds", "none", "--run", "none", "--config", "nosuch"), "nosuch: no such config file"),
    ("bench_networks.py", ("--steps", "0"), "argument --steps: must be >= 1, got 0"),
    ("bench_networks.py", ("--repeats", "0"), "argument --repeats: must be >= 1, got 0"),
    ("psf_accuracy.py", ("--set", "camera.nosuch=1"), "unknown config key 'camera.nosuch'"),  # a ConfigError
    ("bench_camera.py", ("--repeats", "0", "--size", "32", "--batch", "1"), "argument --repeats: must be >= 1"),
    ("bench_cli.py", ("--repeats", "0"), "argument --repeats: must be >= 1, got 0"),  # a StatisticsError
    ("bench_train.py", ("--steps", "0"), "argument --steps: must be >= 1, got 0"),
    ("bench_baselines.py", ("--repeats", "0"), "argument --repeats: must be >= 1, got 0"),
    ("bench_data.py", ("--scenes", "0"), "argument --scenes: must be >= 1, got 0"),  # a ZeroDivisionError
    # torch's RuntimeError traceback for a negative thread count (bench_capture's child ran with OMP_NUM_THREADS=-1)
    ("bench_networks.py", ("--threads", "-1", "--kinds", "none", "--run", "none"), "argument --threads: must be >= 1"),
    ("bench_camera.py", ("--threads", "-1"), "argument --threads: must be >= 1, got -1"),
    ("bench_train.py", ("--threads", "-1"), "argument --threads: must be >= 1, got -1"),
    ("bench_capture.py", ("--threads", "-1", "--size", "64"), "argument --threads: must be >= 1, got -1"),
    # a device torch cannot make, or one this machine lacks: torch's traceback, after the set-up
    ("bench_baselines.py", ("--device", "foo", "--size", "16"), "--device foo: unknown device"),
    ("bench_baselines.py", ("--device", "cuda:99", "--size", "16"), "--device cuda:99: "),
    # a ConfigError traceback once the model was built; a run built, then the dark frame's error, not --size's
    ("bench_capture.py", ("--size", "64", "--set", "model.kind=nosuch"), "model.kind='nosuch' is unknown"),
    ("bench_capture.py", ("--size", "0"), "argument --size: must be >= 1, got 0"),
    # the nearest band (720 nm) was compared, silently
    ("psf_accuracy.py", ("--bands-nm", "550", "5000"), "--bands-nm 5000: outside the camera's bands (415–725 nm)"),
])
def test_benchmarks_bad_arguments(capsys, monkeypatch, script, argv, said):
    assert said in _usage_error(capsys, monkeypatch, BENCHMARKS / script, *argv)


# --- hsicam --version ------------------------------------------------------------------------------------------------


def test_version_is_printed_without_torch():
    from hsicam import __version__

    code = textwrap.dedent("""
        import contextlib, sys
        from hsicam.cli import main
        with contextlib.suppress(SystemExit):
            main(["--version"])
        print(sorted({"torch", "scipy"} & set(sys.modules)))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [f"hsicam {__version__}", "[]"]
    module = subprocess.run([sys.executable, "-m", "hsicam", "--version"], capture_output=True, text=True, timeout=60)
    assert (module.returncode, module.stdout) == (0, f"hsicam {__version__}\n")
