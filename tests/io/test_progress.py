"""Progress on long work: off a terminal (CI, nohup, a log file) every long loop logs k/N lines
with an ETA on stderr (hsicam.progress), never on stdout."""

from __future__ import annotations

import logging
import re

import pytest

from cli_helpers import assert_ok, module_cache, run_cli
from hsicam.progress import Progress


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


def counts(text: str, desc: str) -> list[tuple[int, int]]:
    """The (k, N) of every ``desc: k/N`` line of ``text``, in order."""
    return [(int(k), int(n)) for k, n in re.findall(rf"^{re.escape(desc)}: (\d+)/(\d+) ", text, re.M)]


def test_lines_off_a_terminal_first_last_and_throttled(caplog, monkeypatch):
    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    with caplog.at_level(logging.INFO, logger="hsicam.progress"):
        with Progress(5, "job", "scene", every_s=3600) as p:
            for _ in range(5):
                p.update()
        with Progress(3, "each", "scene", every_s=0) as p:
            for i in range(3):
                p.update(note=f"s{i}")
        with Progress(3, "quiet", show=False) as p:
            p.update()
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert counts(text, "job") == [(1, 5), (5, 5)]  # throttled: the first and the last
    assert counts(text, "each") == [(1, 3), (2, 3), (3, 3)]
    assert "eta" in text and "s1" in text and "quiet" not in text


def test_a_resumed_count_starts_at_the_items_done_and_its_eta_is_the_rate_of_this_counts_items(caplog, monkeypatch):
    """A resumed job (``initial``: 3 of 5 done before): its lines count 4/5, 5/5, and the ETA is the time of the items
    done in this count: 10 s for its one item so far, 1 left -> 10 s (over the 4 items counted, 2.5 s: too soon)."""
    import hsicam.progress as progress

    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    now = [100.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    with caplog.at_level(logging.INFO, logger="hsicam.progress"):
        with Progress(5, "again", "point", every_s=0, initial=3) as p:
            now[0] = 110.0
            p.update()
            now[0] = 120.0
            p.update()
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert counts(text, "again") == [(4, 5), (5, 5)], text
    assert "again: 4/5 points (10 s elapsed, eta 10 s)" in text, text
    with pytest.raises(ValueError, match="initial must be in"):
        Progress(2, "x", initial=3)


def test_data_synth_logs_scene_counts_off_a_terminal(env, tmp_path):
    res = run_cli("data", "synth", "--n", "3", "--size", "64", "--out", str(tmp_path / "d"), env=env)
    assert_ok(res)
    assert counts(res.stderr, "synthetic train set")[-1] == (3, 3), res.stderr
    assert counts(res.stderr, "synthetic train set")[0] == (1, 3), res.stderr
    assert "eta" in res.stderr and "/3" not in res.stdout
    quiet = run_cli("data", "synth", "--n", "2", "--size", "64", "--no-progress", "--out", str(tmp_path / "q"), env=env)
    assert_ok(quiet)
    assert not counts(quiet.stderr, "synthetic train set"), quiet.stderr


def assert_first_and_last(seen, total, text):
    """k/N lines off a terminal: the first (1/N) and the last (N/N), and between them only the ones the log's
    interval let through (wall-clock: a loaded machine shows more), counting up."""
    assert seen[0] == (1, total) and seen[-1] == (total, total), text
    assert all(a[0] < b[0] and b[1] == total for a, b in zip(seen, seen[1:])), text


def test_tiled_reconstruction_counts_its_tiles_off_a_terminal(caplog, monkeypatch):
    """``hsicam reconstruct`` of a large image (progress=None): a bar on a terminal used to be all, so a
    log showed nothing for minutes; now k/N tile lines, the first and the last at least."""
    import torch

    from hsicam.engine.inference import reconstruct_tiled

    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    with caplog.at_level(logging.INFO, logger="hsicam.progress"):
        out = reconstruct_tiled(lambda x: x.repeat(1, 2, 1, 1), torch.rand(1, 1, 40, 50), 16, 2, progress=None)
        reconstruct_tiled(lambda x: x.repeat(1, 2, 1, 1), torch.rand(1, 1, 40, 50), 16, 2)  # default: silent
    assert out.shape == (1, 2, 40, 50)
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert_first_and_last(counts(text, "reconstruct"), 12, text)


def test_tiled_reconstruction_counts_its_consistency_steps_off_a_terminal(caplog, monkeypatch, tiny_config):
    """The consistency steps that go over the whole image after the tiles (minutes on a large capture) count
    themselves too: k/N step lines after the tile lines."""
    import torch

    from hsicam.engine.inference import reconstruct_tiled
    from hsicam.models import CameraSystem

    model = CameraSystem.from_config(tiny_config("model.consistency.iterations=3",
                                                 "model.consistency.tv_weight=0.05")).eval()
    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    with caplog.at_level(logging.INFO, logger="hsicam.progress"):
        reconstruct_tiled(model.reconstructor(), torch.rand(1, 1, 40, 50), 16, progress=None)
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert_first_and_last(counts(text, "reconstruct"), 12, text)
    assert counts(text, "consistency steps")[0] == (1, 3) and counts(text, "consistency steps")[-1] == (3, 3), text
    assert text.index("reconstruct: 12/12") < text.index("consistency steps: 1/3")


@pytest.mark.parametrize("seconds, text", [(4.24, "4.2 s"), (37.4, "37 s"), (185, "3m05s"), (3720, "1h02m"), (-3, "0.0 s"),
                                           (float("inf"), "?"), (float("nan"), "?")])
def test_format_seconds(seconds, text):
    """Durations as a person reads them; an ETA that cannot be estimated reads ``?`` instead of raising
    (``int(round(inf))`` was an OverflowError, NaN a ValueError)."""
    from hsicam.progress import format_seconds

    assert format_seconds(seconds) == text
