"""A reconstruction stopped by SIGTERM (``kill``, a job scheduler) or Ctrl-C leaves nothing half-written: no
temporary file, and no cube without its preview (session 37: SIGTERM used to end the process at once, leaving
the cube's hidden temporary behind, and a stop between the cube and its preview left the cube alone)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from cli_helpers import cli_env

# A subprocess that reconstructs a small capture through the shipped camera and is stopped at one point
# (the patched function sends the signal to its own process, as `kill` would, then waits for it to act).
SCRIPT = textwrap.dedent("""
    import os, signal, sys, time
    import hsicam.io
    where, how, sensor, out = sys.argv[1:5]
    sig = {"term": signal.SIGTERM, "int": signal.SIGINT}[how]
    # as in a terminal: a test runner's worker (pytest-xdist, make) may hand its children SIGINT ignored
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

    def stop(*args, **kwargs):
        os.kill(os.getpid(), sig)
        time.sleep(10)  # the handler acts at once; this line is never finished
        raise AssertionError("the signal did not stop the command")

    if where == "reconstruction":  # cmd_reconstruct imports it from hsicam.engine.inference when it runs
        import hsicam.engine.inference
        hsicam.engine.inference.reconstruct_tiled = stop
    else:  # the preview, after the cube was written
        hsicam.io.write_png8 = stop
    from hsicam.cli import main
    sys.exit(main(["reconstruct", sensor, "--run", "pretrained:standard", "--out", out]))
""")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("capture")
    sensor = folder / "sensor.npy"
    np.save(sensor, np.random.default_rng(0).uniform(0.2, 0.8, (48, 48)).astype(np.float32))
    return sensor


def stopped(capture, tmp_path, where: str, how: str, name: str = "cube.h5") -> tuple[subprocess.CompletedProcess, list[str]]:
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    res = subprocess.run([sys.executable, "-c", SCRIPT, where, how, str(capture), str(out_dir / name)],
                         capture_output=True, text=True, timeout=300, env=cli_env())
    return res, sorted(p.name for p in out_dir.iterdir())


@pytest.mark.parametrize("where", ["reconstruction", "preview"])
def test_sigterm_stops_a_reconstruction_cleanly(capture, tmp_path, where):
    res, left = stopped(capture, tmp_path, where, "term")
    assert res.returncode == 128 + signal.SIGTERM, (res.returncode, res.stderr)
    assert res.stderr.strip().splitlines()[-1] == "hsicam: terminated (SIGTERM); nothing half-written was left"
    assert "Traceback" not in res.stderr
    assert left == [], left  # neither the cube nor a temporary (".cube.XXXXXXXX.tmp.h5")


@pytest.mark.parametrize("name", ["cube.h5", "cube.hdr"])
def test_ctrl_c_before_the_preview_leaves_no_cube_without_it(capture, tmp_path, name):
    res, left = stopped(capture, tmp_path, "preview", "int", name)
    assert res.returncode == 130, (res.returncode, res.stderr)
    assert res.stderr.strip().splitlines()[-1] == "hsicam: interrupted"
    assert left == [], left  # the cube (ENVI: header and data) went with the preview it lacked


def test_sigterm_keeps_its_default_where_a_command_trains_or_a_handler_is_set():
    """The training commands stop on SIGTERM by themselves (hsicam.engine.stopping), and an embedding program's
    own handler is left alone: the context changes nothing there, and restores the default on exit."""
    from hsicam.cli import sigterm_as_interrupt
    from hsicam.errors import Terminated

    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    with sigterm_as_interrupt(enabled=False):
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    with sigterm_as_interrupt():
        handler = signal.getsignal(signal.SIGTERM)
        with pytest.raises(Terminated):
            handler(signal.SIGTERM, None)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    mine = lambda signum, frame: None  # noqa: E731
    previous = signal.signal(signal.SIGTERM, mine)
    try:
        with sigterm_as_interrupt():
            assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_the_training_commands_are_marked_as_such():
    from hsicam.cli import build_parser

    parser = build_parser()
    trains = {cmd: bool(getattr(parser.parse_args(argv), "trains", False)) for cmd, argv in {
        "train": ["train", "--out", "x"], "demo": ["demo"], "finetune": ["finetune", "--run", "r", "--psf-dir", "p", "--out", "x"],
        "experiment": ["experiment", "ablation", "--out", "x"], "train-prior": ["baseline", "train-prior", "--out", "x"],
        "reconstruct": ["reconstruct", "s.npy", "--run", "r", "--out", "x.h5"], "evaluate": ["evaluate", "--out", "x"],
        "psf": ["psf", "--out", "x"]}.items()}
    assert trains == {"train": True, "demo": True, "finetune": True, "experiment": True, "train-prior": True,
                      "reconstruct": False, "evaluate": False, "psf": False}


@pytest.mark.parametrize("how", ["int", "term"])
def test_a_stop_between_the_envi_data_and_its_header_leaves_no_data_file_and_the_command_runs_again(
        capture, tmp_path, monkeypatch, capsys, how):
    """An ENVI cube is two files: stopped after its .img took its place and before its .hdr, the .img was left alone,
    and the same command then refused it as a user's file ("its header c.hdr is missing"), while SIGTERM's line said
    nothing half-written was left (session 54 review). The data file this write put there goes with the stop now."""
    import contextlib

    import hsicam.data.formats as formats
    from hsicam.cli import main
    from hsicam.errors import Terminated

    out = tmp_path / "out"
    out.mkdir()
    argv = ["reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(out / "c.hdr")]
    real = formats.atomic_path

    @contextlib.contextmanager
    def stopped_before_the_header(path):
        with real(path) as tmp:
            yield tmp
            if str(path).endswith(".hdr"):  # before the header's temporary takes its place
                assert (out / "c.img").is_file()  # the data file is in place: the stop falls between the two
                raise Terminated() if how == "term" else KeyboardInterrupt()

    monkeypatch.setattr(formats, "atomic_path", stopped_before_the_header)
    assert main(argv) == (143 if how == "term" else 130)
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "hsicam: terminated (SIGTERM); nothing half-written was left" if how == "term" else "hsicam: interrupted")
    assert sorted(p.name for p in out.iterdir()) == []  # no .img without its header, no temporary
    monkeypatch.undo()
    assert main(argv) == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["c.hdr", "c.img", "c_rgb.png"]


@pytest.mark.parametrize("name", ["c.h5", "c.hdr"])
@pytest.mark.parametrize("stop_in", ["preview", "cube"])
def test_a_stopped_overwrite_leaves_the_earlier_cube_and_preview_as_they_were(capture, tmp_path, monkeypatch, capsys,
                                                                              name, stop_in):
    """Reconstructing over an earlier cube deleted its preview first and, stopped while writing the new preview,
    deleted the new cube too: both of the earlier result's files were lost (session 70's hunt). Stopped while the new
    preview or the new cube is written, the earlier files are there, byte for byte, and no temporary is left."""
    import hsicam.data.formats as formats
    import hsicam.io
    from hsicam.cli import main

    out = tmp_path / "out"
    out.mkdir()
    earlier = np.random.default_rng(1).uniform(0.2, 0.8, (48, 48)).astype(np.float32)
    np.save(tmp_path / "earlier.npy", earlier)
    assert main(["reconstruct", str(tmp_path / "earlier.npy"), "--run", "pretrained:standard", "--out",
                 str(out / name)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert len(before) == (2 if name.endswith(".h5") else 3)

    def stop(*args, **kwargs):
        raise KeyboardInterrupt()

    if stop_in == "preview":
        monkeypatch.setattr(hsicam.io, "write_png8", stop)
    else:
        monkeypatch.setattr(formats, "write_cube_h5" if name.endswith(".h5") else "_write_envi_pair", stop)
    assert main(["reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(out / name)]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "hsicam: interrupted"
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the same files, the same bytes, nothing else
    monkeypatch.undo()
    assert main(["reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(out / name)]) == 0
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after.keys() == before.keys() and all(after[k] != before[k] for k in after)  # the new pair replaced it
