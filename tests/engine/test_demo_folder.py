"""The demo folder as a user meets it again: one demo at a time, nothing stale left marked complete, a killed
demo's temporaries removed, and refusals that name the same keys every time (session 53 audit)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from hsicam.cli import main
from hsicam.config import load_config, training_differences
from hsicam.io import COMPLETE_MARKER


@pytest.fixture(scope="module")
def finished(tmp_path_factory, cache_env):
    """A finished tiny demo folder (one epoch)."""
    from hsicam.engine.demo import run_demo

    out = tmp_path_factory.mktemp("demo") / "demo"
    run_demo(load_config("tiny", ["train.epochs=1"]), out)
    assert (out / COMPLETE_MARKER).is_file()
    return out


def test_a_demo_holds_its_folder_while_it_scores(finished, tmp_path, monkeypatch):
    """Two demos into one finished folder both ran: one reused the run (switching its kept weights) while the other
    scored it, and the folder was marked complete with results naming one checkpoint and scoring another. A demo
    now holds its folder's lock from its checks to its marker: another writer is refused while it scores."""
    from hsicam.engine import demo

    out = shutil.copytree(finished, tmp_path / "demo")
    probe = ("import sys\nfrom hsicam.io import OutputLock\ntry:\n    OutputLock(sys.argv[1], 'demo').acquire()\n"
             "    print('free')\nexcept Exception as exc:\n    print(exc)")
    seen = []
    scores = demo.evaluate_scenes

    def scoring(*a, **k):  # while the demo scores: can another process take its folder?
        if not seen:
            seen.append(subprocess.run([sys.executable, "-c", probe, str(out)], capture_output=True, text=True,
                                       env={**os.environ}).stdout.strip())
        return scores(*a, **k)

    monkeypatch.setattr(demo, "evaluate_scenes", scoring)
    demo.run_demo(load_config("tiny", ["train.epochs=1"]), out)
    assert seen and seen[0].startswith(f"{out}: being written by another process (hsicam demo, pid {os.getpid()}"), seen
    assert (out / COMPLETE_MARKER).is_file()


def test_an_interrupted_reuse_leaves_no_complete_marker_and_a_rerun_restores_it(finished, tmp_path, monkeypatch):
    """The marker came off only after the run was reused (its kept weights switched, its step refitted): a Ctrl-C in
    between left a folder marked complete over results that no longer matched its run."""
    from hsicam.engine import demo

    out = shutil.copytree(finished, tmp_path / "demo")
    (out / ".psf.0a1b2c3d.tmp.png").write_bytes(b"half a figure")  # a killed demo's temporary

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "ensure_trained", interrupted)
    with pytest.raises(KeyboardInterrupt):
        demo.run_demo(load_config("tiny", ["train.epochs=1"]), out)
    assert not (out / COMPLETE_MARKER).exists()
    assert not (out / ".psf.0a1b2c3d.tmp.png").exists()
    monkeypatch.undo()
    assert main(["demo", "--config", "tiny", "--set", "train.epochs=1", "--out", str(out)]) == 0
    assert (out / COMPLETE_MARKER).is_file()
    res, was = (json.loads((d / "results.json").read_text())["mean"] for d in (out, finished))
    assert {k: res[k] for k in ("psnr", "ssim", "sam")} == pytest.approx({k: was[k] for k in ("psnr", "ssim", "sam")})


def test_the_keys_a_refusal_names_do_not_depend_on_the_hash_seed(tmp_path):
    """training_differences stopped at `limit` while walking sets of keys in hash order, so a tiny demo folder
    reused with the quick preset named other keys in every process."""
    every = training_differences(load_config("tiny"), load_config("quick"), limit=10**6)
    assert len(every) > 3 and every == sorted(every)
    assert training_differences(load_config("tiny"), load_config("quick")) == every[:3]
    code = ("from hsicam.config import load_config, training_differences; "
            "print(training_differences(load_config('tiny'), load_config('quick')))")
    seen = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env={**os.environ, "PYTHONHASHSEED": seed}).stdout for seed in ("1", "2", "3")}
    assert seen == {f"{every[:3]}\n"}


def test_the_demo_scores_on_the_test_noise_of_evaluate_whatever_the_training_seed(tmp_path, cache_env):
    """The demo drew its test noise from train.seed, so a demo of seed 3 under sensor noise printed figures that
    `hsicam evaluate --run` of its own run (test-noise seed 0) did not give, and runs of different seeds were scored
    on different draws. Now the demo's means are evaluate's, to the last bit, on both sets."""
    from hsicam.engine.demo import run_demo

    out = tmp_path / "demo"
    run_demo(load_config("tiny", ["train.epochs=1", "train.seed=3", "camera.sensor.sigma=0.02"]), out)
    assert main(["evaluate", "--run", str(out / "run"), "--out", str(tmp_path / "eval")]) == 0
    demo, ev = (json.loads((d / "results.json").read_text()) for d in (out, tmp_path / "eval"))
    keys = ("psnr", "ssim", "sam")
    assert {k: demo["mean"][k] for k in keys} == {k: ev["mean"][k] for k in keys}
    if "heldout" in demo:
        assert {k: demo["heldout"]["mean"][k] for k in keys} == {k: ev["heldout"]["mean"][k] for k in keys}


def test_a_reused_run_is_scored_on_as_many_held_out_scenes_as_the_demo_asks(finished, tmp_path):
    """`demo --set data.heldout_n=3` on a finished demo reused its run (heldout_n is a runtime key) but scored the
    run's own 8 held-out scenes, and a plain demo on a folder made with 3 scored 3 (a helper's hunt, session 71).
    Now the count asked is scored, and said in results.json's held-out label."""
    from hsicam.engine.demo import run_demo

    out = shutil.copytree(finished, tmp_path / "demo")
    for n in (3, 8):
        summary = run_demo(load_config("tiny", ["train.epochs=1", f"data.heldout_n={n}"]), out)
        assert len(summary["heldout"]["scenes"]) == n, n
        assert len(json.loads((out / "results.json").read_text())["heldout"]["scenes"]) == n


def test_the_demos_results_say_how_they_were_made(finished):
    """The demo's results.md could not reproduce its own table (no run, config or weights, scenes, seed or software)
    and its results.json named no software (session 74's records hunt)."""
    import hashlib

    res = json.loads((finished / "results.json").read_text())
    assert {"hsicam", "git_commit", "torch", "numpy", "threads"} <= res["software"].keys()
    md = (finished / "results.md").read_text()
    sha = hashlib.sha256((finished / "run" / "model.safetensors").read_bytes()).hexdigest()
    cfg = load_config(finished / "run" / "config.yaml")
    assert res["weights_sha256"] == sha
    line = next(x for x in md.splitlines() if x.startswith("Made by `hsicam demo`: the run "))
    assert f"config hash {res['config_hash']}; weights sha256 {sha[:12]}…, train.seed 0" in line
    assert (f"data.synthetic_seed {cfg.data.synthetic_seed}, {cfg.data.synthetic_n} scenes of "
            f"{cfg.data.synthetic_size} px, split seed {cfg.data.split_seed}") in line
    assert "test-noise seed 0; hsicam " in line and f"`hsicam evaluate --run {finished / 'run'} --out DIR`" in line
