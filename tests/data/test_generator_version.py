"""Which synthetic-data generator a run trained on (session 60; compat1's finding): a run of an older version
(generator 2) was evaluated, resumed and packed on regenerated version-3 scenes without a word, and its card named
version 3. A run records the version in its session records now; a run of another version is warned about."""

from __future__ import annotations

import json
import logging
import shutil

import pytest

from hsicam.cli import main
from hsicam.config import load_config
from hsicam.data.synthetic import GENERATOR_VERSION
from hsicam.engine.provenance import trained_generator_version

OLDER = GENERATOR_VERSION - 1


@pytest.fixture(scope="module")
def demo(tmp_path_factory, cache_env):
    """A finished tiny demo folder (one epoch, then resumable to two)."""
    from hsicam.engine.demo import run_demo

    out = tmp_path_factory.mktemp("genver") / "demo"
    run_demo(load_config("tiny", ["train.epochs=1"]), out)
    return out


def _as_of_version(run, version):
    """The run's session records as the software of ``version`` (None: an hsicam before session 60) wrote them."""
    path = run / "metrics.jsonl"
    records = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
    for r in records:
        if "session" in r:
            if version is None:
                r["session"].pop("synthetic_generator")
            else:
                r["session"]["synthetic_generator"] = version
    path.write_text("".join(json.dumps(r) + "\n" for r in records), encoding="utf-8")


def _warning(run, doing):
    return (f"{run} trained on scenes of synthetic-data generator version {OLDER}; this hsicam generates version "
            f"{GENERATOR_VERSION} (docs/data.md), so it {doing} on other scenes than its own version's: figures are "
            f"not comparable with those the run's version gave")


def test_a_run_records_the_generator_version_it_trains_on(demo):
    records = [json.loads(line) for line in (demo / "run" / "metrics.jsonl").read_text(encoding="utf-8").splitlines()]
    sessions = [r["session"] for r in records if "session" in r]
    assert sessions and all(s["synthetic_generator"] == GENERATOR_VERSION for s in sessions)
    assert trained_generator_version(demo / "run") == GENERATOR_VERSION


def test_evaluating_a_run_of_another_generator_version_says_so(demo, tmp_path, caplog):
    run = shutil.copytree(demo / "run", tmp_path / "run")
    with caplog.at_level(logging.WARNING):
        assert main(["evaluate", "--run", str(run), "--out", str(tmp_path / "same")]) == 0
    assert not [r for r in caplog.records if "generator version" in r.getMessage()]
    _as_of_version(run, OLDER)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert main(["evaluate", "--run", str(run), "--out", str(tmp_path / "other")]) == 0
    assert _warning(run, "is scored") in [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    # in the results too, not on stderr alone (session 74's records hunt)
    assert _warning(run, "is scored") in json.loads((tmp_path / "other" / "results.json").read_text())["warning"]
    assert "warning" not in json.loads((tmp_path / "same" / "results.json").read_text())
    _as_of_version(run, None)  # an hsicam before session 60 recorded none: nothing to tell
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert main(["evaluate", "--run", str(run), "--out", str(tmp_path / "unrecorded")]) == 0
    assert not [r for r in caplog.records if "generator version" in r.getMessage()]


def test_resuming_a_run_of_another_generator_version_says_so(demo, tmp_path, caplog):
    run = shutil.copytree(demo / "run", tmp_path / "run")
    _as_of_version(run, OLDER)
    with caplog.at_level(logging.WARNING):
        assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=2"]) == 0
    assert _warning(run, "goes on") in [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert trained_generator_version(run) == OLDER  # the run's start, not the resume's


def test_a_packed_card_names_the_generator_version_the_run_trained_on(demo, tmp_path, caplog):
    from hsicam.engine.pretrained import pack_pretrained

    run = shutil.copytree(demo / "run", tmp_path / "run")
    _as_of_version(run, OLDER)
    card = json.loads((pack_pretrained(run, "older", tmp_path / "root", demo / "results.json") / "card.json")
                      .read_text(encoding="utf-8"))
    assert card["training"]["data"]["generator_version"] == OLDER
    _as_of_version(run, None)
    with caplog.at_level(logging.WARNING):
        card = json.loads((pack_pretrained(run, "unrecorded", tmp_path / "root", demo / "results.json") / "card.json")
                          .read_text(encoding="utf-8"))
    assert card["training"]["data"]["generator_version"] == GENERATOR_VERSION
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"{run} does not record the synthetic-data generator version it trained on (a run of an hsicam before "
        f"session 60): the card names this hsicam's, version {GENERATOR_VERSION}"]


def test_a_packed_card_of_a_run_whose_start_is_unknown_or_of_session_60_says_which(demo, tmp_path, caplog, monkeypatch):
    """pack said "a run of an hsicam before session 60" of every run without a recorded generator version: also of one
    whose starting session record (metrics.jsonl's first line) is torn, whose start is not known, and of one that a
    commit of session 60 started before c1ab911 recorded the version, whose version is known: 3, the
    GENERATOR_VERSION of each of those commits (git show 215c9e2:src/hsicam/data/synthetic.py), which its card names
    with no warning, also under an hsicam of another version (4 here)."""
    from hsicam.engine.pretrained import pack_pretrained

    def packed(name, edit):
        run = shutil.copytree(demo / "run", tmp_path / name)
        path = run / "metrics.jsonl"
        lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
        first = json.loads(lines[0])
        first["session"].pop("synthetic_generator")
        lines[0] = edit(first)
        path.write_text("".join(lines), encoding="utf-8")
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            card = json.loads((pack_pretrained(run, name, tmp_path / "root", demo / "results.json") / "card.json")
                              .read_text(encoding="utf-8"))
        return run, card["training"]["data"]["generator_version"], [
            r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "generator version" in r.getMessage()]

    monkeypatch.setattr("hsicam.data.synthetic.GENERATOR_VERSION", 4)
    later = "the card names this hsicam's, version 4"
    run, version, said = packed("torn", lambda r: json.dumps(r)[:40] + "\n")
    assert version == 4 and said == [
        f"{run} does not record the synthetic-data generator version it trained on (its metrics.jsonl's first line, "
        f"the record of the session that started it, is torn or blank): {later}"]
    session_60 = lambda commit: lambda r: json.dumps({**r, "session": {**r["session"], "git_commit": commit}}) + "\n"  # noqa: E731
    for commit in ("215c9e2c6a5b8cfb4155e94a547c7cb96ff3dbbd", "c5559eb5f5d609ab584e8aa0697d03cb6f465f42+dirty"):
        assert packed(f"s60-{commit[:7]}", session_60(commit))[1:] == (3, [])
    run, version, said = packed("older", session_60("c5559eb5f5d609ab584e8aa0697d03cb6f465f42"[::-1]))
    assert version == 4 and said == [f"{run} does not record the synthetic-data generator version it trained on (a "
                                     f"run of an hsicam before session 60): {later}"]


def test_a_run_of_an_hsicam_before_session_records_resumed_today_records_no_version(tmp_path):
    """The generator version is that of the run's starting session record, the first record of metrics.jsonl: a run
    of an hsicam before session records (generator 2) resumed today begins with its training records, and the
    resume's record (this version) was taken for its start, so evaluate --run said nothing and a packed card named
    version 3 without its warning."""
    run = tmp_path / "run"
    run.mkdir()
    session = lambda v: {"step": 3, "epoch": 0, "session": {"hsicam": "0.1.0", "synthetic_generator": v}}  # noqa: E731
    lines = [{"step": 1, "epoch": 0, "train_loss": 0.1, "lr": 0.001}, session(GENERATOR_VERSION)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines), encoding="utf-8")
    assert trained_generator_version(run) is None
    lines = [{**session(OLDER), "step": 0}, lines[0], session(GENERATOR_VERSION)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines), encoding="utf-8")
    assert trained_generator_version(run) == OLDER
