"""Output paths through links, ``~``, a full disk, a bad cache and ``-v`` (probe 24, findings 3, 4, 7,
10, 11, 13 and 14).

3. A leading ``~`` in a path argument is expanded once, by the CLI: the output lands in ``$HOME``
   whole (no ``./~`` folder, no empty preview), and the PNG writers never let imageio expand it.
4. An ``--out`` that is a symbolic link to a folder is written in (or replaced inside) its target;
   the link is kept.
10. A dangling link or a link loop as an output is named as such, with its target.
7. An ``OSError`` while a file is written (disk full …) is one line naming the file it was to
   become (never the hidden temporary), exit code 2, no traceback, nothing left behind.
11. A ``HSICAM_CACHE`` that cannot hold the dataset is named with its value and what to do.
13. ``-v`` shows hsicam's debug lines, not matplotlib's font search.
14. ``--out`` equal to the input run is said to be the input run.
"""

from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import assert_clean_error, assert_ok, module_cache, run_cli, run_cli_in_process, unprivileged_prefix
from hsicam.cli import error_line
from hsicam.errors import InputError
from hsicam.io import COMPLETE_MARKER, atomic_output, atomic_path, is_temporary, read_marker, write_png8


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


@pytest.fixture(scope="module")
def run(tmp_path_factory, env) -> Path:
    """A trained tiny run (one epoch)."""
    d = tmp_path_factory.mktemp("trained") / "run1"
    assert_ok(run_cli_in_process("train", "--config", "tiny", "--out", str(d), "--set", "train.epochs=1", env=env))
    return d


def simulate(scene: Path, out: str | Path, *extra: str) -> subprocess.CompletedProcess:
    return run_cli_in_process("simulate", "--config", "tiny", "--scene", str(scene), "--out", str(out), *extra)


def entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def visible(folder: Path) -> list[str]:
    """The entries of ``folder`` but hidden ones (a library's caches and settings in ``$HOME``)."""
    return [n for n in entries(folder) if not n.startswith(".")]


# ------------------------------------------------------------------------------------------------
# 3. "~"
# ------------------------------------------------------------------------------------------------
def test_a_tilde_in_an_output_and_an_input_means_home(tmp_path, monkeypatch, scene):
    home = tmp_path / "home"
    home.mkdir()
    (home / "scene.npy").write_bytes(scene.read_bytes())
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(tmp_path)
    res = simulate(Path("~/scene.npy"), "~/sim")
    assert_ok(res)
    assert res.stdout.splitlines()[0].endswith(f"-> {home / 'sim'}")  # (the next line: the display preview)
    assert entries(tmp_path) == ["home"]  # no "./~" folder
    assert visible(home) == ["scene.npy", "sim"] and not any(is_temporary(n) for n in entries(home))
    assert read_marker(home / "sim")["command"] == "simulate" and (home / "sim" / "sensor.png").stat().st_size > 0


def test_the_png_writers_write_where_hsicam_says(tmp_path, monkeypatch):
    """A folder really named "~" (made by a script): the preview goes there, whole, not to $HOME."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(tmp_path)
    write_png8(Path("~") / "c_rgb.png", np.full((4, 5, 3), 0.5))
    assert (tmp_path / "~" / "c_rgb.png").stat().st_size > 0
    assert visible(home) == [] and not any(is_temporary(n) for n in entries(home))


# ------------------------------------------------------------------------------------------------
# 4. An --out that is a link to a folder
# ------------------------------------------------------------------------------------------------
def test_a_link_to_a_folder_is_written_through_and_kept(tmp_path, scene):
    (tmp_path / "bigdisk" / "sim").mkdir(parents=True)
    link = tmp_path / "sim_link"
    link.symlink_to("bigdisk/sim")
    assert_ok(simulate(scene, link))
    assert link.is_symlink() and os.readlink(link) == "bigdisk/sim"
    assert read_marker(tmp_path / "bigdisk" / "sim")["command"] == "simulate"
    # a link to an earlier output ("latest"): that output is replaced, the link kept
    latest = tmp_path / "latest"
    latest.symlink_to("sim_link")
    assert_ok(simulate(scene, latest, "--seed", "7"))
    assert latest.is_symlink() and link.is_symlink()
    assert '"seed": 7' in (tmp_path / "bigdisk" / "sim" / "simulate.json").read_text()
    assert entries(tmp_path) == ["bigdisk", "latest", "sim_link"] and entries(tmp_path / "bigdisk") == ["sim"]
    # a link to a user's folder: refused as the folder would be, link and files kept
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    (tmp_path / "mine_link").symlink_to("mine")
    assert_clean_error(simulate(scene, tmp_path / "mine_link"), "is not a completed hsicam output")
    assert entries(tmp_path / "mine") == ["notes.txt"] and (tmp_path / "mine_link").is_symlink()


def test_training_through_a_link_keeps_the_link(tmp_path, env):
    (tmp_path / "bigdisk" / "run").mkdir(parents=True)
    link = tmp_path / "run_link"
    link.symlink_to(tmp_path / "bigdisk" / "run")
    assert_ok(run_cli_in_process("train", "--config", "tiny", "--out", str(link), "--set", "train.epochs=1", env=env))
    assert link.is_symlink()
    assert (tmp_path / "bigdisk" / "run" / "model.safetensors").is_file()
    assert entries(tmp_path / "bigdisk") == ["run"]


def test_the_atomic_writers_follow_links(tmp_path):
    (tmp_path / "target").mkdir()
    (tmp_path / "dir_link").symlink_to("target")
    with atomic_output(tmp_path / "dir_link", overwrite=True) as d:
        (d / "a.txt").write_text("a")
    (tmp_path / "file.txt").write_text("old")
    (tmp_path / "file_link.txt").symlink_to("file.txt")
    with atomic_path(tmp_path / "file_link.txt") as tmp:
        tmp.write_text("new")
    assert (tmp_path / "dir_link").is_symlink() and (tmp_path / "file_link.txt").is_symlink()
    assert entries(tmp_path / "target") == [COMPLETE_MARKER, "a.txt"]
    assert (tmp_path / "file.txt").read_text() == "new"


# ------------------------------------------------------------------------------------------------
# 10. Dangling links and loops
# ------------------------------------------------------------------------------------------------
def test_a_dangling_link_or_a_loop_is_named_with_its_target(tmp_path, scene):
    dang = tmp_path / "dang"
    dang.symlink_to(tmp_path / "not_there")
    loop = tmp_path / "loop"
    loop.symlink_to("loop")
    assert_clean_error(simulate(scene, dang), f"{dang}: is a symbolic link to {tmp_path / 'not_there'}, which does not exist")
    assert_clean_error(simulate(scene, loop), f"{loop}: is a symbolic link to loop, which leads back to itself")
    assert_clean_error(simulate(scene, loop / "sub"), f"{loop / 'sub'}: cannot be created inside {loop}: it is a "
                                                      "symbolic link to loop, which leads back to itself")
    file_link = tmp_path / "c.h5"
    file_link.symlink_to("nowhere.h5")
    with pytest.raises(InputError, match="is a symbolic link to nowhere.h5, which does not exist"):
        with atomic_path(file_link):
            raise AssertionError("must not run")
    assert entries(tmp_path) == ["c.h5", "dang", "loop"] and all(p.is_symlink() for p in tmp_path.iterdir())


# ------------------------------------------------------------------------------------------------
# 7. Disk full
# ------------------------------------------------------------------------------------------------
def _failing_writes(monkeypatch, exc: OSError) -> None:
    """Every file hsicam.io opens for writing refuses its first write with ``exc``."""
    import builtins

    class Full:
        def __init__(self, fh):
            self._fh = fh

        def write(self, data):
            raise exc

        def __getattr__(self, name):
            return getattr(self._fh, name)

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self._fh.close()

    def fake_open(file, mode="r", *args, **kwargs):
        fh = builtins.open(file, mode, *args, **kwargs)
        return Full(fh) if any(c in mode for c in "wax") else fh

    monkeypatch.setattr("hsicam.io.open", fake_open, raising=False)


def test_a_full_disk_is_one_line_naming_the_file(tmp_path, monkeypatch, scene):
    _failing_writes(monkeypatch, OSError(errno.ENOSPC, "No space left on device"))
    out = tmp_path / "sim"
    assert_clean_error(simulate(scene, out), f"hsicam: error: {out}/sensor.npy: No space left on device (the disk is "
                                             "full: free some space, or write to another disk)")
    assert entries(tmp_path) == []  # no temporary, no half-written folder


def test_a_short_write_names_the_file(tmp_path, monkeypatch, scene):
    _failing_writes(monkeypatch, OSError("4096 requested and 3040 written"))  # numpy's words, no errno
    out = tmp_path / "sim"
    assert_clean_error(simulate(scene, out), f"{out}/sensor.npy: the write stopped after 3040 of 4096 bytes "
                                             "(is the disk full?")
    assert entries(tmp_path) == []


def test_a_libraries_write_error_names_the_file_it_was_to_become(tmp_path):
    """h5py's multi-line text with errno 28 and no file name; an error naming a file in a temporary folder."""
    cube = tmp_path / "c.h5"
    with pytest.raises(OSError) as exc:
        with atomic_path(cube) as tmp:
            raise OSError(errno.ENOSPC, f"Can't synchronously write data (file write failed: time = …\n, filename = "
                                        f"'{tmp.name}', errno = 28, error message = 'No space left on device')")
    assert error_line(exc.value) == (f"{cube}: No space left on device (the disk is full: free some space, or write "
                                     "to another disk)")
    with pytest.raises(OSError) as exc:
        with atomic_output(tmp_path / "ev") as d:
            raise OSError(errno.EDQUOT, "Disk quota exceeded", str(d / "cubes" / "s_estimate.h5"))
    assert exc.value.filename == str(tmp_path / "ev" / "cubes" / "s_estimate.h5")
    assert entries(tmp_path) == []


# ------------------------------------------------------------------------------------------------
# 11. A bad HSICAM_CACHE
# ------------------------------------------------------------------------------------------------
def test_a_cache_that_is_a_file_is_named(tmp_path, monkeypatch):
    cache = tmp_path / "cachefile"
    cache.write_text("x")
    monkeypatch.setenv("HSICAM_CACHE", str(cache))
    res = run_cli_in_process("data", "synth", "--n", "1", "--size", "16", "--no-progress")
    assert_clean_error(res, f"HSICAM_CACHE={cache} (the dataset cache):", "which is a file; set HSICAM_CACHE to a "
                                                                          "writable folder")
    res = run_cli_in_process("data", "synth", "--n", "1", "--size", "16", "--no-progress", "--set",
                             f"data.cache_dir={cache}/sub")
    assert_clean_error(res, f"data.cache_dir={cache}/sub (the dataset cache):", "point data.cache_dir to a writable folder "
                      "(--set data.cache_dir=DIR, or cache_dir under data: in the config file; a run's is its config.yaml)")
    assert cache.read_text() == "x"


def test_a_read_only_cache_is_named(tmp_path):
    prefix = unprivileged_prefix()
    if prefix is None:
        pytest.skip("cannot drop root's permission override here")
    cache = tmp_path / "rocache"
    cache.mkdir()
    cache.chmod(0o555)
    try:
        from cli_helpers import HSICAM, cli_env

        res = subprocess.run([*prefix, str(HSICAM), "data", "synth", "--n", "1", "--size", "16", "--no-progress"],
                             capture_output=True, text=True, timeout=120, env=cli_env({"HSICAM_CACHE": str(cache)}))
    finally:
        cache.chmod(0o755)
    assert_clean_error(res, f"HSICAM_CACHE={cache} (the dataset cache):", "is not writable", "set HSICAM_CACHE")


# ------------------------------------------------------------------------------------------------
# 13. -v
# ------------------------------------------------------------------------------------------------
def test_verbose_shows_hsicams_debug_lines_not_matplotlibs(tmp_path, env):
    res = run_cli("-v", "psf", "--config", "tiny", "--out", str(tmp_path / "psf"), env=env)
    assert_ok(res)
    assert "findfont" not in res.stderr and len(res.stderr.splitlines()) < 20, res.stderr[:2000]
    synth = ("-v", "data", "synth", "--n", "1", "--size", "16", "--no-progress")
    assert_ok(run_cli(*synth, env=env))
    res = run_cli(*synth, env=env)  # the cached dataset: said by a debug line of hsicam's
    assert_ok(res)
    assert "synthetic dataset cached at" in res.stderr


# ------------------------------------------------------------------------------------------------
# 14. --out equal to the input run
# ------------------------------------------------------------------------------------------------
def test_the_input_run_as_out_is_named(run, scene):
    before = entries(run)
    for args in (("psf",), ("simulate", "--scene", str(scene)), ("export-optics",)):
        res = run_cli_in_process(*args, "--run", str(run), "--out", str(run))
        assert_clean_error(res, f"{run}: is the input run (--run, a training run)", "choose another --out")
    res = run_cli_in_process("psf", "--config", "tiny", "--out", str(run))  # another command's input: still a run
    assert_clean_error(res, f"{run}: holds a training run, which hsicam psf never replaces; choose another --out")
    assert entries(run) == before


def test_a_replaced_folder_holding_a_link_names_where_it_leads(tmp_path):
    """`hsicam report EV` written through a link EV/report, then `evaluate --out EV`: the refusal named
    `report` as a user's file without saying it is a link, nor that removing it keeps the report
    (probe 25, F8)."""
    from hsicam.io import check_replaceable

    ev = tmp_path / "ev"
    with atomic_output(ev, marker={"command": "evaluate"}) as tmp:
        (tmp / "results.json").write_text("{}")
    (tmp_path / "site").mkdir()
    (ev / "report").symlink_to("../site")
    with pytest.raises(InputError, match=r"holds report \(a symbolic link to \.\./site: remove the link, its target is "
                                         r"kept\), which hsicam evaluate did not write"):
        check_replaceable(ev, overwrite=True, command="evaluate")
