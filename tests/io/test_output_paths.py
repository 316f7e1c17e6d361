"""Output paths that replaced a user's files (probe 22, findings 1, 2, 6 and 12).

1. A command replacing its own completed folder checks every entry at any depth against its marker's
   ``files`` (and a derived ``report/`` against its own marker): a user's file in ``DIR/cubes/`` or
   ``DIR/report/`` is refused, named by its path relative to DIR, before any work.
2. ``data show`` needs ``--out``: it never writes into its data folder (it wrote its PNGs there by default
   until session 62; before that, over a user's files of the previews' names).
6. The spectral-gamut plot samples every scene of a folder with mixed band grids (resampled onto one
   grid), and says which scenes it leaves out and why.
12. A held-out set on another grid is resampled, or refused naming the folder, the grids and the reason.
"""

from __future__ import annotations

import json
import logging
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import (HSICAM, assert_clean_error, assert_ok, cli_env, error_line, run_cli_in_process,
                         unprivileged_prefix)
from hsicam.data.formats import write_cube_h5
from hsicam.errors import InputError
from hsicam.io import COMPLETE_MARKER, atomic_output, mark_complete
from hsicam.spectral import Bands

PNGS = ["contact_sheet.png", "mean_spectra.png", "spectral_gamut.png"]


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder`` with its bytes (None for a folder)."""
    return {p.relative_to(folder).as_posix(): (None if p.is_dir() else p.read_bytes())
            for p in sorted(folder.rglob("*"))}


def _refused(out: Path, command: str, *fragments: str) -> str:
    """The one-line InputError of ``atomic_output(out, overwrite=True)`` for ``command`` (its block never runs)."""
    with pytest.raises(InputError) as exc:
        with atomic_output(out, overwrite=True, marker={"command": command}):
            raise AssertionError("must not run")
    text = str(exc.value)
    assert "\n" not in text and all(f in text for f in fragments), text
    return text


def _evaluation(out: Path) -> Path:
    """A folder written like ``hsicam evaluate --save``: results.json and cubes/ with one cube."""
    with atomic_output(out, overwrite=True, marker={"command": "evaluate"}) as d:
        (d / "results.json").write_text("{}")
        (d / "cubes").mkdir()
        (d / "cubes" / "s_estimate.h5").write_bytes(b"cube")
    return out


# ------------------------------------------------------------------------------------------------
# 1. check_replaceable at any depth
# ------------------------------------------------------------------------------------------------
def test_the_marker_lists_every_entry_at_any_depth(tmp_path):
    ev = _evaluation(tmp_path / "ev")
    marker = json.loads((ev / COMPLETE_MARKER).read_text())
    assert marker["files"] == ["cubes/", "cubes/s_estimate.h5", "results.json"]


def test_a_users_entry_inside_a_commands_subfolder_is_refused(tmp_path):
    ev = _evaluation(tmp_path / "ev")
    (ev / "cubes" / "my_analysis.txt").write_text("mine")
    (ev / "cubes" / "plots").mkdir()
    (ev / "cubes" / ".DS_Store").write_bytes(b"\0")  # a file browser's, not the user's work
    before = snapshot(tmp_path)
    _refused(ev, "evaluate", f"{ev}: holds cubes/my_analysis.txt, cubes/plots, which hsicam evaluate did not write",
             "choose another folder or move them")
    assert snapshot(tmp_path) == before  # nothing deleted, no temporary left
    (ev / "cubes" / "my_analysis.txt").unlink()
    (ev / "cubes" / "plots").rmdir()
    _evaluation(ev)  # its own files (and the file browser's) are replaced as before
    assert snapshot(ev)["cubes/s_estimate.h5"] == b"cube" and not (ev / "cubes" / ".DS_Store").exists()


def test_a_derived_report_holding_a_users_file_is_refused(tmp_path):
    ev = _evaluation(tmp_path / "ev")
    with atomic_output(ev / "report", marker={"command": "report"}) as d:
        (d / "index.html").write_text("r")
    (ev / "report" / "notes.txt").write_text("my notes")
    before = snapshot(tmp_path)
    _refused(ev, "evaluate", f"{ev}: holds report/notes.txt, which hsicam evaluate did not write")
    assert snapshot(tmp_path) == before
    _refused(ev / "report", "report", f"{ev / 'report'}: holds notes.txt, which hsicam report did not write")
    (ev / "report" / "notes.txt").unlink()
    _evaluation(ev)  # report/ with its own files only: it goes with the results it was made from
    assert not (ev / "report").exists()


def test_a_folder_filled_in_place_again_loses_its_out_of_date_report_but_never_a_users_file(tmp_path):
    """An experiment (or demo) run again kept the report/ of its old results beside the new table
    (probe 23: seeds [0] in the report, [0, 1, 2] in table.md)."""
    from hsicam.io import clear_derived

    folder = tmp_path / "xp"
    folder.mkdir()
    (folder / "table.md").write_text("old")
    mark_complete(folder, {"command": "experiment"})
    with atomic_output(folder / "report", marker={"command": "report"}) as d:
        (d / "index.html").write_text("r")
    (folder / "report" / "notes.txt").write_text("my notes")
    before = snapshot(tmp_path)
    with pytest.raises(InputError, match=r"report: holds notes.txt, which hsicam report did not write; it is made "
                                         r"from .* results and would be removed as out of date: move them"):
        clear_derived(folder)
    assert snapshot(tmp_path) == before
    (folder / "report" / "notes.txt").unlink()
    assert clear_derived(folder) == [folder / "report"]
    assert not (folder / "report").exists() and (folder / "table.md").read_text() == "old"


def test_an_older_marker_listing_a_subfolder_only_is_refused_unless_it_is_empty(tmp_path):
    ev = tmp_path / "ev"
    (ev / "cubes").mkdir(parents=True)
    (ev / "cubes" / "s_estimate.h5").write_bytes(b"cube")
    mark_complete(ev, {"command": "evaluate", "files": ["cubes", "results.json"]})  # before per-file records
    before = snapshot(tmp_path)
    _refused(ev, "evaluate", f"{ev}: cannot tell which files in cubes/ hsicam evaluate wrote",
             f"move your files out of {ev / 'cubes'} and delete it")
    assert snapshot(tmp_path) == before
    (ev / "cubes" / "s_estimate.h5").unlink()
    _evaluation(ev)
    assert snapshot(ev)["cubes/s_estimate.h5"] == b"cube"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, cache_env) -> Path:
    """A tiny trained run (``hsicam train --config tiny``)."""
    run = tmp_path_factory.mktemp("runs") / "run"
    assert_ok(run_cli_in_process("train", "--config", "tiny", "--set", "train.epochs=1", "--out", str(run)))
    return run


def test_rerunning_evaluate_keeps_user_files_in_cubes_and_report(run_dir, tmp_path):
    ev = tmp_path / "ev"
    again = ("evaluate", "--run", str(run_dir), "--out", str(ev), "--save")
    assert_ok(run_cli_in_process(*again))
    assert_ok(run_cli_in_process("report", str(ev)))
    (ev / "cubes" / "my_analysis.txt").write_text("my analysis")
    (ev / "report" / "notes.txt").write_text("my notes")
    before = snapshot(tmp_path)
    # one line, before any work (no progress line), nothing deleted
    assert_clean_error(run_cli_in_process(*again), f"{ev}: holds cubes/my_analysis.txt, report/notes.txt, "
                                                   "which hsicam evaluate did not write; choose another folder or move them")
    assert_clean_error(run_cli_in_process("report", str(ev)),
                       f"{ev / 'report'}: holds notes.txt, which hsicam report did not write")
    assert snapshot(tmp_path) == before
    (ev / "cubes" / "my_analysis.txt").unlink()
    (ev / "report" / "notes.txt").unlink()
    assert_ok(run_cli_in_process(*again))  # its own files (and the report made from them): replaced
    cubes = sorted(p.name for p in (ev / "cubes").iterdir())
    assert cubes == sorted(p[len("ev/cubes/"):] for p in before if p.startswith("ev/cubes/") and "my_" not in p)
    assert not (ev / "report").exists()


# ------------------------------------------------------------------------------------------------
# 2. data show without --out: only its own previews are replaced
# ------------------------------------------------------------------------------------------------
def _scenes(folder: Path, *grids: Bands, size: int = 24) -> Path:
    """One random scene per grid in ``folder`` (s0.h5, s1.h5, ...)."""
    rng = np.random.default_rng(0)
    for k, b in enumerate(grids):
        write_cube_h5(folder / f"s{k}.h5", rng.uniform(0.05, 1, (len(b), size, size)).astype(np.float32), b)
    return folder


def _show(*args: str):
    return run_cli_in_process("data", "show", *args)


def test_data_show_never_writes_into_its_data_folder(tmp_path):
    """`hsicam data show DIR` wrote its three PNGs into the data folder DIR itself (a user's input; docs/usage.md did
    not say so): it needs --out now, a folder of its own; the data folder is left byte for byte as it was, a refusal
    is one line, and an --out holding a file of the user's is refused, not mixed into."""
    from PIL import Image

    data = _scenes(tmp_path / "data", Bands.paper(), Bands.paper())
    before = snapshot(tmp_path)
    res = _show(str(data))
    assert error_line(res) == "hsicam: error: the following arguments are required: --out"
    assert_clean_error(_show(str(data / "s0.h5")), "required: --out")  # a cube file: not its folder either
    assert_clean_error(_show(str(data), "--out", str(data)), f"{data}: folder exists and is not empty")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my notes")
    before = snapshot(tmp_path)
    assert_clean_error(_show(str(data), "--out", str(mine)), f"{mine}: folder exists and is not empty")
    assert snapshot(tmp_path) == before
    out = tmp_path / "preview"
    for _ in range(2):  # the second run refreshes the first's output
        assert_ok(_show(str(data), "--out", str(out)))
    assert snapshot(data) == {k[len("data/"):]: v for k, v in before.items() if k.startswith("data/")}
    assert sorted(p.name for p in out.iterdir()) == sorted([COMPLETE_MARKER, *PNGS])
    for name in PNGS:
        with Image.open(out / name) as im:
            assert im.format == "PNG" and min(im.size) > 16


def test_data_show_of_a_read_only_data_folder(tmp_path):
    """Data on a read-only mount (a shared dataset) is previewed into --out; an unwritable --out is one line."""
    prefix = unprivileged_prefix()
    if prefix is None:
        pytest.skip("running as root without setpriv: chmod cannot make a folder unwritable here")
    data = _scenes(tmp_path / "data", Bands.paper())
    data.chmod(0o500)
    try:
        def show(out: Path) -> subprocess.CompletedProcess:
            return subprocess.run([*prefix, str(HSICAM), "data", "show", str(data), "--out", str(out)],
                                  capture_output=True, text=True, timeout=300, env=cli_env())

        assert_ok(show(tmp_path / "preview"))
        assert_clean_error(show(data / "preview"), f"{data / 'preview'}: cannot be created", "not writable")
    finally:
        data.chmod(0o700)
    assert sorted(p.name for p in data.iterdir()) == ["s0.h5"]
    assert sorted(p.name for p in (tmp_path / "preview").iterdir()) == sorted([COMPLETE_MARKER, *PNGS])


# ------------------------------------------------------------------------------------------------
# 6 and 12. The spectral gamut of mixed band grids
# ------------------------------------------------------------------------------------------------
def test_gamut_samples_every_scene_of_a_folder_with_mixed_grids(tmp_path):
    from hsicam.data.datasets import list_scenes
    from hsicam.data.preview import pixel_spectra

    data = _scenes(tmp_path / "mixed", Bands.uniform(400, 700, 10), Bands.uniform(420, 720, 50),
                   Bands.uniform(420, 720, 50))
    spectra, grid = pixel_spectra(list_scenes(data), per_scene=100)
    assert spectra.shape == (300, 29) and np.isfinite(spectra).all()
    assert grid.matches(Bands.uniform(420, 700, 10))  # the first scene's bands that every scene covers


def test_gamut_says_which_scenes_it_leaves_out_and_why(tmp_path, caplog):
    from hsicam.data.datasets import list_scenes
    from hsicam.data.preview import pixel_spectra

    data = _scenes(tmp_path / "mixed", Bands.uniform(400, 700, 10), Bands.uniform(420, 720, 50),
                   Bands.uniform(380, 430, 10))
    with caplog.at_level(logging.WARNING):
        spectra, grid = pixel_spectra(list_scenes(data), per_scene=100, source=data)
    assert spectra.shape == (200, 29) and grid.matches(Bands.uniform(420, 700, 10))
    [line] = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert line == (f"{data}: spectral gamut: left out 1 of 3 scenes, whose bands do not cover the plot's grid "
                    "(29 bands, 420-700 nm; no extrapolation): s2.h5: 6 bands, 380-430 nm")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert_ok(_show(str(data), "--out", str(tmp_path / "o")))
    assert any("s2.h5: 6 bands, 380-430 nm" in r.getMessage() for r in caplog.records)


def test_a_heldout_set_on_another_grid_is_resampled(tmp_path):
    data = _scenes(tmp_path / "data", Bands.uniform(420, 720, 50))
    held = _scenes(tmp_path / "held", Bands.uniform(420, 720, 10))
    assert_ok(_show(str(data), "--out", str(tmp_path / "o"), "--heldout", str(held)))
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == sorted([COMPLETE_MARKER, *PNGS])


def test_a_heldout_set_that_does_not_cover_names_its_folder_the_grids_and_the_reason(tmp_path):
    data = _scenes(tmp_path / "data", Bands.uniform(420, 720, 50))
    held = _scenes(tmp_path / "held", Bands.uniform(500, 600, 50))
    before = snapshot(tmp_path)
    assert_clean_error(_show(str(data), "--out", str(tmp_path / "o"), "--heldout", str(held)),
                       f"{held}: no scenes to sample spectra from: their bands (s0.h5: 3 bands, 500-600 nm) do not "
                       "cover the plot's grid (7 bands, 420-720 nm) and are not extrapolated")
    assert snapshot(tmp_path) == before
