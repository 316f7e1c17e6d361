"""A command that fails before it wrote anything leaves no new folder behind, and a folder the user named
stays as it was (hsicam.cli.prepare_output records what existed; hsicam.cli.main removes the empty folders
the failed command made)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from cli_helpers import run_cli_in_process

NO_COLOUR = "hsicam: error: generating the synthetic dataset needs colour-science (pip install 'hsicam[synth]')"


@pytest.fixture
def no_colour(monkeypatch):
    """colour-science missing (`import colour`: ImportError), the spectral library's cache bypassed."""
    from hsicam.data import spectral_sources

    monkeypatch.setitem(sys.modules, "colour", None)
    monkeypatch.setattr(spectral_sources, "_library_cached", spectral_sources._library_cached.__wrapped__)


def _tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


#: Commands that fail at the synthetic data (no colour-science), by the arguments before ``--out``.
FAILING = {
    "demo": ["demo", "--config", "tiny"],
    "experiment": ["experiment", "ablation", "--scale", "tiny"],
    "train": ["train", "--config", "tiny"],
    "evaluate": ["evaluate", "--run", "pretrained:standard"],
    "data synth": ["data", "synth", "--config", "tiny"],
    "baseline train-prior": ["baseline", "train-prior", "--config", "tiny"],
}


@pytest.mark.parametrize("command", list(FAILING))
def test_a_failed_command_leaves_no_new_folder(command, tmp_path, no_colour):
    """`hsicam demo --out runs/demo` without colour-science left the runs/ it made for its lock file (empty), and
    `hsicam experiment` left OUT/ and OUT/runs/ (empty), after the one-line error."""
    work = tmp_path / "work"
    work.mkdir()
    res = run_cli_in_process(*FAILING[command], "--out", str(work / "runs" / "new" / "out"),
                             env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1].startswith(NO_COLOUR), res.stderr
    assert _tree(work) == []


@pytest.mark.parametrize("command", list(FAILING))
def test_a_failed_command_leaves_the_empty_folder_it_was_given_as_it_was(command, tmp_path, no_colour):
    """An existing empty --out stays, empty (experiment left runs/ in it), and so does its parent."""
    out = tmp_path / "work" / "out"
    out.mkdir(parents=True)
    res = run_cli_in_process(*FAILING[command], "--out", str(out), env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1].startswith(NO_COLOUR), res.stderr
    assert _tree(tmp_path / "work") == ["out"]


def test_a_failed_command_keeps_a_new_folder_that_holds_a_file(tmp_path, no_colour, monkeypatch):
    """Only folders that hold nothing are removed: a file written in the new folder tree keeps it all (a guard of
    the fix: passes on the old code too)."""
    from hsicam.engine import demo

    made = tmp_path / "runs" / "notes.txt"  # beside the demo folder, in the runs/ the command made
    real = demo._run_demo

    def writes_then_fails(cfg, out):
        made.parent.mkdir(parents=True, exist_ok=True)
        made.write_text("kept")
        return real(cfg, out)

    monkeypatch.setattr(demo, "_run_demo", writes_then_fails)
    res = run_cli_in_process("demo", "--config", "tiny", "--out", str(tmp_path / "runs" / "demo"),
                             env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1].startswith(NO_COLOUR), res.stderr
    assert made.read_text() == "kept"
