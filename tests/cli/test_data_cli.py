"""`hsicam data synth` / `hsicam data show` through the installed entry point."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from cli_helpers import cli_env
from hsicam.data import read_cube
from hsicam.data.synthetic import generate_dataset
from hsicam.spectral import Bands

HSICAM = Path(sys.executable).parent / "hsicam"

pytestmark = pytest.mark.skipif(not HSICAM.exists(), reason="hsicam entry point not installed")


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The installed ``hsicam`` in ``cwd`` (relative paths are the point), with the environment of
    :func:`cli_helpers.run_cli`: this checkout's ``src`` first, one thread."""
    return subprocess.run([str(HSICAM), *args], cwd=cwd, capture_output=True, text=True, timeout=300, env=cli_env())


def test_synth_then_show(tmp_path):
    r = run("data", "synth", "--n", "3", "--size", "40", "--seed", "11", "--out", "ds", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "ds"
    files = sorted(p.name for p in out.iterdir())
    assert files == ["manifest.json", "scene_0000.h5", "scene_0001.h5", "scene_0002.h5"]
    cube, bands, _ = read_cube(out / "scene_0001.h5")
    assert cube.shape == (31, 40, 40) and bands.matches(Bands.paper())

    # a second process draws the same bytes as this one (determinism across processes)
    generate_dataset(tmp_path / "here", n=3, size=40, seed=11, progress=False)
    for name in files:
        assert (out / name).read_bytes() == (tmp_path / "here" / name).read_bytes(), name

    again = run("data", "synth", "--n", "3", "--size", "40", "--seed", "11", "--out", "ds", cwd=tmp_path)
    assert again.returncode == 0 and "already" in again.stdout

    r = run("data", "synth", "--n", "2", "--size", "40", "--seed", "11", "--split", "heldout", "--out", "ho",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "held-out scenes" in r.stdout and "nist-philips, rawtoaces" in r.stdout
    _, _, meta = read_cube(tmp_path / "ho" / "scene_0000.h5")
    assert meta["split"] == "heldout" and meta["holdout_sources"] == ["nist-philips", "rawtoaces"]

    r = run("data", "show", "ds", "--out", "preview", "--heldout", "ho", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    sheet, plot = tmp_path / "preview" / "contact_sheet.png", tmp_path / "preview" / "mean_spectra.png"
    gamut = tmp_path / "preview" / "spectral_gamut.png"
    assert "preview/spectral_gamut.png" in r.stdout
    for png in (sheet, plot, gamut):
        img = iio.imread(png)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
        assert np.asarray(img[..., :3]).std() > 5  # not blank
    hidden = [p.name for p in (tmp_path / "preview").iterdir() if p.name.startswith(".")]
    assert hidden == [".complete"]  # atomic: no leftovers; the marker of data show's completed output


def test_synth_holdout_flag_and_sources(tmp_path):
    r = run("data", "synth", "--n", "1", "--size", "24", "--holdout-sources", "cie-tcs,rawtoaces", "--out", "a",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _, _, meta = read_cube(tmp_path / "a" / "scene_0000.h5")
    assert meta["holdout_sources"] == ["cie-tcs", "rawtoaces"] and meta["split"] == "train"
    r = run("data", "sources", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    ids = [ln.split()[0] for ln in r.stdout.splitlines()]
    assert {"rawtoaces", "cie-tcs", "nist-philips", "led-model", "otsu2018"} <= set(ids)


@pytest.mark.parametrize("args,words", [
    (("data", "show", "missing_dir", "--out", "o"), ["missing_dir", "no such"]),
    (("data", "synth", "--n", "0", "--out", "x"), ["--n"]),
    (("data", "synth", "--n", "1", "--holdout-sources", "rawtoaces,bogus", "--out", "x"),
     ["bogus", "valid ids", "cie-tcs"]),
    (("data", "synth", "--n", "1", "--holdout-sources", "none", "--split", "heldout", "--out", "x"),
     ["held-out source"]),
])
def test_bad_input_is_one_line_exit_2(tmp_path, args, words):
    r = run(*args, cwd=tmp_path)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("hsicam: error:"), r.stderr
    assert "Traceback" not in r.stderr
    for w in words:
        assert w in lines[0]


def test_show_corrupt_file_is_one_line(tmp_path):
    (tmp_path / "bad.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    r = run("data", "show", "bad.h5", "--out", "o", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "bad.h5" in r.stderr


# ------------------------------------------------------------------------------------------------
# `data show`: every input is checked before a PNG is written; a failure leaves nothing behind
# ------------------------------------------------------------------------------------------------
def _one_cube_set(folder: Path, bands: Bands, n: int = 1) -> Path:
    from hsicam.data.formats import write_cube_h5

    rng = np.random.default_rng(0)
    for k in range(n):
        write_cube_h5(folder / f"scene_{k}.h5", rng.random((len(bands), 32, 32), dtype=np.float32), bands)
    return folder


def _tree(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder``: a file's bytes, None for a folder."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() if p.is_file() else None
            for p in sorted(folder.rglob("*"))}


@pytest.mark.parametrize("heldout,words", [
    ("empty", ["empty", "no hyperspectral scenes"]),
    ("missing", ["missing", "no such"]),
    ("other_bands", ["no scenes to sample spectra from"]),  # read only when the gamut plot is drawn
])
def test_show_with_a_bad_heldout_writes_nothing(tmp_path, heldout, words):
    from cli_helpers import assert_clean_error, run_cli_in_process

    data = _one_cube_set(tmp_path / "data", Bands.paper())
    (tmp_path / "empty").mkdir()
    _one_cube_set(tmp_path / "other_bands", Bands.uniform(500, 600, 50))
    before = _tree(tmp_path)
    # a new output folder (and its parent) is not created
    r = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "show" / "o"),
                           "--heldout", str(tmp_path / heldout))
    assert_clean_error(r, *words)
    assert _tree(tmp_path) == before


def test_show_failure_keeps_the_previous_preview(tmp_path):
    """A rerun that fails (here: on its held-out set, read last) leaves the PNGs of the last
    successful run as they were, although it would have drawn other ones (one scene, not two)."""
    from cli_helpers import assert_clean_error, run_cli_in_process

    data = _one_cube_set(tmp_path / "data", Bands.paper(), n=2)
    (tmp_path / "empty").mkdir()
    out = tmp_path / "preview"
    r = run_cli_in_process("data", "show", str(data), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == [".complete", "contact_sheet.png", "mean_spectra.png",
                                                     "spectral_gamut.png"]
    before = _tree(tmp_path)
    assert_clean_error(run_cli_in_process("data", "show", str(data), "--out", str(out), "--max-scenes", "1",
                                          "--heldout", str(tmp_path / "empty")), "no hyperspectral scenes")
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("value", ["0", "-1"])
def test_show_max_scenes_below_one_is_an_error(tmp_path, value):
    from cli_helpers import assert_clean_error, run_cli_in_process

    data = _one_cube_set(tmp_path / "data", Bands.paper())
    before = _tree(tmp_path)
    assert_clean_error(run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / "o"),
                                          "--max-scenes", value), "--max-scenes", value)
    assert _tree(tmp_path) == before


def test_show_max_scenes_caps_the_scenes(tmp_path):
    from cli_helpers import run_cli_in_process

    data = _one_cube_set(tmp_path / "data", Bands.paper(), n=3)
    for n in ("1", "3"):
        r = run_cli_in_process("data", "show", str(data), "--out", str(tmp_path / n), "--max-scenes", n)
        assert r.returncode == 0, r.stderr
    one, three = (iio.imread(tmp_path / n / "contact_sheet.png") for n in ("1", "3"))
    assert one.shape[1] < three.shape[1] / 2  # one thumbnail per row, not three


def test_write_preview_rejects_max_scenes_below_one(tmp_path):
    from hsicam.data.preview import write_preview
    from hsicam.errors import InputError

    data = _one_cube_set(tmp_path / "data", Bands.paper())
    for bad in (0, -1, 1.5, True):
        with pytest.raises(InputError, match="max_scenes"):
            write_preview(data, tmp_path / "o", max_scenes=bad)
    assert not (tmp_path / "o").exists()


# `data show`: the output-folder rules of every command (hsicam.cli.prepare_output)
# ------------------------------------------------------------------------------------------------
def _show(capsys, *args: str) -> tuple[int, str]:
    """``hsicam data show ARGS`` in-process: (exit code, stderr)."""
    from hsicam.cli import main

    code = main(["data", "show", *args])
    return code, capsys.readouterr().err


def _evaluation_folder(folder: Path) -> Path:
    """A completed output of ``hsicam evaluate`` (its marker and files), with a saved cube."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.io import mark_complete

    (folder / "cubes").mkdir(parents=True)
    (folder / "results.json").write_text("{}")
    write_cube_h5(folder / "cubes" / "a_estimate.h5", np.full((len(Bands.paper()), 32, 32), 0.5, np.float32),
                  Bands.paper())
    mark_complete(folder, {"command": "evaluate", "files": ["cubes", "results.json"]})
    return folder


def test_show_never_writes_into_another_commands_output(tmp_path, capsys):
    """`data show --out` wrote its PNGs into any folder: another command's output (which that command
    then refused to refresh, holding files it did not write) or a user's own folder."""
    data = _one_cube_set(tmp_path / "data", Bands.paper())
    ev = _evaluation_folder(tmp_path / "ev")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("user data")
    before = _tree(tmp_path)
    code, err = _show(capsys, str(data), "--out", str(ev))
    assert code == 2 and err.strip() == (f"hsicam: error: {ev}: holds the output of hsicam evaluate, not of hsicam "
                                         "data show; choose another output folder"), err
    code, err = _show(capsys, str(data), "--out", str(mine))
    assert code == 2 and err.strip() == (f"hsicam: error: {mine}: folder exists and is not empty (and is not a "
                                         "completed hsicam output); choose another output folder"), err
    assert _tree(tmp_path) == before


def test_show_refreshes_its_own_output_and_other_commands_refuse_it(tmp_path, capsys):
    from hsicam.io import read_marker

    data = _one_cube_set(tmp_path / "data", Bands.paper())
    out = tmp_path / "preview"
    pngs = ["contact_sheet.png", "mean_spectra.png", "spectral_gamut.png"]
    for _ in range(2):  # the second run replaces the first's PNGs
        code, err = _show(capsys, str(data), "--out", str(out))
        assert code == 0, err
    assert read_marker(out) == {"complete": True, "command": "data show", "files": pngs}
    (out / "notes.txt").write_text("user data")
    code, err = _show(capsys, str(data), "--out", str(out))
    assert code == 2 and f"{out}: holds notes.txt, which hsicam data show did not write" in err, err
    (out / "notes.txt").unlink()
    from hsicam.cli import main

    assert main(["psf", "--config", "tiny", "--out", str(out)]) == 2
    assert "holds the output of hsicam data show, not of hsicam psf" in capsys.readouterr().err


def test_show_of_near_infrared_scenes_draws_them_grey(tmp_path):
    """Scenes with fewer than 2 bands in 380-780 nm have no colour to render: `data show` stopped at
    the first one ("cannot render bands"); it now draws them grey (the mean over bands), named so."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.data.preview import preview_grey

    rng = np.random.default_rng(4)
    nir = rng.random((11, 32, 32)).astype(np.float32)
    (tmp_path / "d").mkdir()
    write_cube_h5(tmp_path / "d" / "nir.h5", nir, Bands.uniform(800, 1000, 20))
    write_cube_h5(tmp_path / "d" / "vis.h5", rng.random((31, 32, 32)).astype(np.float32), Bands.paper())
    r = run("data", "show", "d", "--out", "p", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert iio.imread(tmp_path / "p" / "contact_sheet.png").shape[0] > 100
    grey = preview_grey(nir)
    mean = nir.astype(np.float64).mean(axis=0)
    np.testing.assert_allclose(grey[..., 0], np.clip(mean * 0.8 / np.percentile(mean, 99), 0, 1))
    assert (grey[..., 0] == grey[..., 1]).all() and (grey[..., 1] == grey[..., 2]).all()


@pytest.mark.parametrize("where", ["out", "cache"])
def test_data_synth_beyond_the_disk_names_its_own_options(tmp_path, monkeypatch, capsys, where):
    """`data synth --n HUGE` is refused before any scene, naming --n/--size and where to write instead
    (the training path names data.synthetic_n; the command line has options)."""
    import shutil
    from collections import namedtuple

    from hsicam.cli import main

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(2**40, 2**40 - 2**30, 2**30))
    monkeypatch.setenv("HSICAM_CACHE", str(tmp_path / "cache"))
    args = ["data", "synth", "--n", "100000", "--size", "64"] + (["--out", str(tmp_path / "d")] if where == "out" else [])
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hsicam: error: the synthetic dataset of 100,000 scenes of 64×64 px and "
                                                "31 bands needs, in "), err
    assert "more is kept free beyond it (" in err[0], err  # the margin the check keeps is said
    fix = ("give --out a folder on a larger disk" if where == "out" else
           "write to a larger disk (--out, or data.cache_dir / HSICAM_CACHE)")
    assert err[0].endswith(f"but that disk has 1 GiB free; lower --n or --size, or {fix}"), err
    assert not any(tmp_path.iterdir())


def test_an_interrupted_synth_leaves_no_dataset_that_evaluate_would_take(tmp_path, capsys, monkeypatch):
    """`data synth --out DIR` killed after some scenes used to leave DIR with those scenes and no manifest, which
    `evaluate --data DIR` scored as a dataset (a probe of session 51). Now the scenes go to a hidden temporary
    folder that takes DIR's name when the manifest is written: an interruption leaves no DIR, and the next run
    generates the whole set."""
    import hsicam.data.synthetic as synthetic
    from hsicam.cli import main
    from hsicam.data.datasets import list_scenes
    from hsicam.errors import InputError

    made = []
    real = synthetic.generate_scene

    def interrupted_at_the_third(i, *args, **kwargs):
        if len(made) == 2:
            raise KeyboardInterrupt
        made.append(i)
        return real(i, *args, **kwargs)

    monkeypatch.setattr(synthetic, "generate_scene", interrupted_at_the_third)
    out = tmp_path / "ds"
    assert main(["data", "synth", "--n", "4", "--size", "24", "--out", str(out), "--no-progress"]) == 130
    assert made == [0, 1] and capsys.readouterr().err.strip().endswith("hsicam: interrupted")
    assert list(tmp_path.iterdir()) == []  # neither the folder nor its temporary
    with pytest.raises(InputError, match="no such dataset"):
        list_scenes(out)
    monkeypatch.setattr(synthetic, "generate_scene", real)
    assert main(["data", "synth", "--n", "4", "--size", "24", "--out", str(out), "--no-progress"]) == 0
    assert [p.name for p in list_scenes(out)] == [f"scene_{i:04d}.h5" for i in range(4)]
    assert (out / "manifest.json").is_file() and [p.name for p in tmp_path.iterdir()] == ["ds"]


def test_synth_names_its_out_folder_and_counts_one_scene(tmp_path):
    """`data synth --n 1 --out scenes` (README's first command) said "generating ... (1 scenes of ...) in
    .scenes.1a2b3c4d.tmpdir": the hidden temporary instead of the folder asked for, and a plural for one scene."""
    from cli_helpers import assert_ok, run_cli_in_process

    out = tmp_path / "scenes"
    res = run_cli_in_process("data", "synth", "--n", "1", "--size", "16", "--seed", "3", "--split", "heldout",
                             "--out", str(out), "--no-progress")
    assert_ok(res)
    said = [line for line in res.stderr.splitlines() if line.startswith("generating the synthetic")]
    assert said == [f"generating the synthetic heldout set (1 scene of 16x16x31, held-out sources: nist-philips, "
                    f"rawtoaces) in {out}"], res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scenes"]
