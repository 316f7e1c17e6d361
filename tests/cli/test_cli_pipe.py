"""Output piped into a reader that stops early (``hsicam data sources | head -1``): found by following the docs
(session 60): the command printed ``hsicam: error: Broken pipe`` and exited 2, where a shell tool ends quietly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys


def test_a_reader_that_stops_early_ends_the_command_quietly_with_sigpipes_status():
    """stdout a pipe whose reader has gone: exit 128 + SIGPIPE (141, what `cat big | head` gives cat), nothing on
    stderr (no error line, no "Exception ignored" from the interpreter's final flush)."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader has gone before the first write
    try:
        done = subprocess.run([sys.executable, "-m", "hsicam", "pretrained", "list"], stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert done.returncode == 128 + signal.SIGPIPE, done.stderr
    assert done.stderr == ""


def test_a_broken_pipe_of_the_commands_own_output_is_still_an_error(monkeypatch, capsys):
    """Only standard output's reader may end a command quietly: a BrokenPipeError from elsewhere (an output the
    command opened, e.g. a FIFO whose reader died) is reported in one line and exits 2, as before."""
    from hsicam import cli

    def broken(args):
        raise BrokenPipeError(32, "Broken pipe")

    parser = cli.build_parser()
    args = parser.parse_args(["pretrained", "list"])
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    monkeypatch.setattr(args, "func", broken, raising=False)
    monkeypatch.setattr(parser, "parse_args", lambda argv=None: args)
    assert cli.main(["pretrained", "list"]) == 2
    assert capsys.readouterr().err.strip() == "hsicam: error: Broken pipe"
