"""`hsicam pretrained pack` bad paths (probe 21, F2): the numbers and the preset on a card must be
the packed run's.

The module fixture trains two tiny runs that differ only in their seed (A and B) and evaluates each
with `hsicam evaluate` (the real producer of results.json: it records the run folder and the hash
of the config it evaluated). Packing A with B's evaluation used to publish B's numbers on A's card.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest

from cli_helpers import assert_clean_error, run_cli
from hsicam.errors import InputError

LOGGER = "hsicam.engine.pretrained"


@pytest.fixture(scope="module")
def runs(tmp_path_factory, cache_env):
    """Folder holding runA, runB (tiny, one epoch, seeds 0 and 3) and evA, evB (their evaluations)."""
    from hsicam.cli import main
    from hsicam.config import load_config
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("pack_paths")
    train(load_config("tiny", ["train.epochs=1"]), base / "runA", progress=False)
    train(load_config("tiny", ["train.epochs=1", "train.seed=3"]), base / "runB", progress=False)
    for run, ev in (("runA", "evA"), ("runB", "evB")):
        assert main(["evaluate", "--run", str(base / run), "--out", str(base / ev)]) == 0
    return base


def _results(folder: Path) -> dict:
    return json.loads((folder / "results.json").read_text())


def _pack(*args: str):
    return run_cli("pretrained", "pack", *args)


def test_pack_refuses_an_evaluation_of_another_run(runs, tmp_path):
    a, b = runs / "runA", runs / "runB"
    ev_b = runs / "evB" / "results.json"
    dest = tmp_path / "root"
    res = _pack(str(a), "--name", "x", "--dest", str(dest), "--results", str(ev_b))
    sha_a, sha_b = _results(runs / "evA")["weights_sha256"], _results(runs / "evB")["weights_sha256"]
    assert_clean_error(res, f"{ev_b}: results of another run ({b.resolve()}, weights sha256 {sha_b[:12]}…)",
                       f"not of {a} (weights sha256 {sha_a[:12]}…)",
                       f"`hsicam evaluate --run {a} --out DIR`", "as --results")
    older = tmp_path / "older.json"  # an evaluation written before evaluate recorded the weights' sha256
    older.write_text(json.dumps({k: v for k, v in _results(runs / "evB").items() if k != "weights_sha256"}))
    hash_a, hash_b = _results(runs / "evA")["config_hash"], _results(runs / "evB")["config_hash"]
    assert_clean_error(_pack(str(a), "--name", "x", "--dest", str(dest), "--results", str(older)),
                       f"{older}: results of another run ({b.resolve()}, config hash {hash_b})",
                       f"not of {a} (config hash {hash_a})")
    res = _pack(str(a), "--name", "x", "--dest", str(dest), "--results", str(runs / "evA" / "results.json"),
                "--heldout", str(ev_b))
    assert_clean_error(res, f"{ev_b}: results of another run", "as --heldout")
    assert not dest.exists()


def test_pack_takes_its_own_evaluation_and_that_of_a_copy(runs, tmp_path, caplog):
    from hsicam.engine.pretrained import pack_pretrained

    ev_a = runs / "evA" / "results.json"
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        own = pack_pretrained(runs / "runA", "own", tmp_path / "root", ev_a)
        copy = tmp_path / "copyA"  # another folder, the same weights: evA names runA, which holds them too
        shutil.copytree(runs / "runA", copy)
        pack_pretrained(copy, "copy", tmp_path / "root", ev_a, heldout=ev_a)
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    card = json.loads((own / "card.json").read_text())
    assert card["metrics"]["validation"]["mean"] == {k: _results(runs / "evA")["mean"][k] for k in ("psnr", "ssim", "sam")}


def test_pack_refuses_an_evaluation_with_another_config_or_method(runs, tmp_path):
    from hsicam.cli import main
    from hsicam.engine.pretrained import pack_pretrained

    a = runs / "runA"
    noisy, box = tmp_path / "ev_noisy", tmp_path / "ev_box"
    assert main(["evaluate", "--run", str(a), "--set", "camera.sensor.sigma=0.05", "--out", str(noisy)]) == 0
    with pytest.raises(InputError, match=rf"ev_noisy/results.json: an evaluation of {a} with another config .*"
                                         r"evaluated with --set overrides, the run trained on since, or an older hsicam evaluated it .*; "
                                         rf"evaluate this run \(`hsicam evaluate --run {a} --out DIR`\)"):
        pack_pretrained(a, "x", tmp_path / "root", noisy / "results.json")
    assert main(["evaluate", "--method", "doe-box-demosaic", "--run", str(a), "--out", str(box)]) == 0
    with pytest.raises(InputError, match=r"ev_box/results.json: results of method 'doe-box-demosaic', not of the "
                                         r"run's own network \(doe-learned\)"):
        pack_pretrained(a, "x", tmp_path / "root", box / "results.json")
    assert not (tmp_path / "root").exists()


def test_pack_warns_when_the_evaluated_run_cannot_be_compared(runs, tmp_path, caplog):
    """Results whose run is gone (same config hash) or that name no run (older files) are cited
    with a warning naming the file: nothing is left to compare."""
    from hsicam.cli import main
    from hsicam.engine.pretrained import pack_pretrained

    gone = tmp_path / "gone"
    shutil.copytree(runs / "runA", gone)
    assert main(["evaluate", "--run", str(gone), "--out", str(tmp_path / "ev_gone")]) == 0
    shutil.rmtree(gone)
    ev_gone = tmp_path / "ev_gone" / "results.json"  # as written before evaluate recorded the weights' sha256
    ev_gone.write_text(json.dumps({k: v for k, v in json.loads(ev_gone.read_text()).items() if k != "weights_sha256"}))
    older = tmp_path / "older.json"
    older.write_text(json.dumps({k: v for k, v in _results(runs / "evA").items() if k not in ("run", "config_hash", "weights_sha256")}))
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        pack_pretrained(runs / "runA", "g", tmp_path / "root", tmp_path / "ev_gone" / "results.json", heldout=older)
    msgs = [r.getMessage() for r in caplog.records]
    assert any(f"ev_gone/results.json: the run it evaluated ({gone.resolve()}) is no longer there" in m
               and "(the config hashes match); cited as given" in m for m in msgs), msgs
    assert any(f"{older}: the results do not record which run they evaluated" in m for m in msgs), msgs


def test_pack_preset_must_be_a_shipped_one_and_is_checked_against_the_camera(runs, tmp_path, caplog):
    from hsicam.config import preset_names
    from hsicam.engine.pretrained import pack_pretrained

    a = runs / "runA"
    res = _pack(str(a), "--name", "x", "--dest", str(tmp_path / "r"), "--preset", "nonexistent")
    assert_clean_error(res, "--preset 'nonexistent': not a shipped preset (presets: " + ", ".join(preset_names()) + ")",
                       "leave --preset out")
    assert not (tmp_path / "r").exists()
    res = _pack(str(a), "--name", "p", "--dest", str(tmp_path / "r"), "--preset", "paper")
    assert res.returncode == 0, res.stderr
    warning = [x for x in res.stderr.splitlines() if "differs from preset" in x]
    assert len(warning) == 1 and f"{a}: its camera differs from preset 'paper'" in warning[0], res.stderr
    assert "camera.aperture_radius_mm: 0.6 → 5.0" in warning[0] and "leave --preset out" in warning[0], warning
    assert json.loads((tmp_path / "r" / "p" / "card.json").read_text())["preset"] == "paper"
    with caplog.at_level(logging.WARNING, logger=LOGGER):  # the preset it was trained from: no warning
        t = pack_pretrained(a, "t", tmp_path / "r", preset="tiny")
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    assert json.loads((t / "card.json").read_text())["preset"] == "tiny"
