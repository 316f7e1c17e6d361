"""A command that fails before it wrote anything leaves no new folder behind, and a folder the user named
stays as it was (hsicam.cli.prepare_output records what existed; hsicam.cli.main removes the empty folders
the failed command made)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
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


# ---- an evaluation generates only the synthetic scenes it scores ------------------------------------------

#: The tiny preset with a set of 12 scenes, 3 of them validation scenes.
SMALL_SET = ("data.synthetic_n=12", "data.val_fraction=0.25")


def _scene_files(cache: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(cache.rglob("scene_*.h5")) if "heldout-" not in str(p.parent)}


@pytest.mark.slow  # ~13 s: two evaluations (GAP-TV) of 3 scenes, 12 + 3 scenes generated
def test_evaluation_generates_only_the_validation_scenes_the_same_files_and_scores_as_the_whole_set(tmp_path):
    """`hsicam evaluate` without --data generated the run's whole synthetic set (pretrained:standard: 320 scenes
    of 256 px, 2.6 GB) to score its 16 validation scenes. Now only those, the same files byte for byte, the same
    scores, and a training of the config later completes the same cached set (the same manifest)."""
    import h5py

    from hsicam.config import load_config
    from hsicam.data.pipeline import dataset_root, split_dataset

    part, whole = tmp_path / "part", tmp_path / "whole"
    cfg = load_config("tiny", [*SMALL_SET, f"data.cache_dir={whole}"])
    bands = cfg.bands.to_bands()
    _, val = split_dataset(cfg.data, bands)  # the whole set, generated as a training does
    assert len(val) == 3
    args = ("evaluate", "--config", "tiny", "--method", "dd-cassi-gaptv", *[x for s in SMALL_SET for x in ("--set", s)])
    res = {}
    for name, cache in (("part", part), ("whole", whole)):
        r = run_cli_in_process(*args, "--set", f"data.cache_dir={cache}", "--out", str(tmp_path / f"eval-{name}"))
        assert r.returncode == 0, r.stderr
        res[name] = json.loads((tmp_path / f"eval-{name}" / "results.json").read_text())
    got = _scene_files(part)
    assert sorted(got) == sorted(p.name for p in val)  # the 3 scored, not the 12
    full = _scene_files(whole)
    assert all(got[k] == full[k] for k in got)
    for p in val:
        with h5py.File(p, "r") as a, h5py.File(part / p.relative_to(whole), "r") as b:
            assert np.array_equal(a["cube"][()], b["cube"][()])
    rows = lambda r: [(s["name"], s["psnr"], s["ssim"], s["sam"]) for s in r["scenes"]]  # noqa: E731
    assert rows(res["part"]) == rows(res["whole"])
    # a training of the same config finds the partial set and completes it: the same files, the same manifest
    root = dataset_root(dataclasses.replace(cfg.data, cache_dir=str(part)), bands)
    assert _scene_files(part) == full
    manifest = lambda d: json.loads(next(d.rglob("manifest.json")).read_text())["scenes"]  # noqa: E731
    assert [s["sha256"] for s in manifest(root.parent.parent)] == [s["sha256"] for s in manifest(whole)]
