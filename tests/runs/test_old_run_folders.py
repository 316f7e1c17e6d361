"""Run folders written by older hsicam versions, which users keep for months: a run trained by an older
version must still resume, evaluate and report today, or be refused in one line that says what to do.

No run folder of an older version is stored in git: each test trains a tiny run with today's code and turns
it into the layout an older version wrote (the keys and records that version did not write are taken out).
The layouts (see `git log -- src/hsicam/runs/ src/hsicam/engine/loop.py`):

- before ab50949: the checkpoint's training state (checkpoints.json "state", the step's state.json) had no
  ``steps_per_epoch`` or ``batch_size``;
- before db9c133: metrics.jsonl had no "session" records;
- before 0e7b4fa: checkpoints.json's entries had no ``optimizer_sha256``.
- before c1ab911 (session 60): the session records had no ``synthetic_generator``.
- c5559eb … 215c9e2 (an hour of session 60): the same, but the session record's ``git_commit`` is one of those.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from safetensors.torch import load_file

from cli_helpers import tree_snapshot
from hsicam.config import load_config


def _as_before_loop_state_kept_its_epoch_length(run: Path) -> None:
    """The checkpoint state an hsicam before ab50949 wrote: no steps_per_epoch, no batch_size."""
    man = json.loads((run / "checkpoints.json").read_text())
    state_file = run / man["last"]["dir"] / "state.json"
    state = json.loads(state_file.read_text())
    for entry in (man["state"], state):
        del entry["steps_per_epoch"], entry["batch_size"]
    state_file.write_text(json.dumps(state, indent=2))
    (run / "checkpoints.json").write_text(json.dumps(man, indent=2))


def _as_before_sessions_and_optimizer_hashes(run: Path) -> None:
    """metrics.jsonl without session records (before db9c133), checkpoints.json without optimizer_sha256
    (before 0e7b4fa)."""
    lines = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text("".join(x + "\n" for x in lines if '"session"' not in x))
    man = json.loads((run / "checkpoints.json").read_text())
    for tag in ("last", "best"):
        if isinstance(man.get(tag), dict):
            man[tag].pop("optimizer_sha256", None)
    (run / "checkpoints.json").write_text(json.dumps(man, indent=2))


@pytest.mark.parametrize("change", ["train.batch_size=2", "train.batch_size=8", "data.patches_per_epoch=128"])
def test_an_older_checkpoint_resumed_with_another_epoch_length_is_refused(cache_env, tmp_path, change):
    """A run stopped in its second epoch by an hsicam that did not keep its batch size in the checkpoint was
    resumed with another one: batch size 2 trained on from a misplaced position (20 steps where a new run of
    that config has 24), 128 patches per epoch stopped at step 68 of 96, and batch size 8 was refused as
    asking for fewer steps ("ask for at least as many"). A newer run is refused naming the batch size; the
    older one now too, by the length its completed epochs had, and nothing changes."""
    from hsicam.engine.train import train
    from hsicam.errors import InputError

    keys = ["train.epochs=3"]
    cfg = load_config("tiny", keys)
    run = tmp_path / "r"
    assert train(cfg, run, progress=False, stop_after_steps=7) == {"stopped_at_step": 7}
    _as_before_loop_state_kept_its_epoch_length(run)
    before = tree_snapshot(run)
    old_steps = cfg.data.patches_per_epoch // cfg.train.batch_size  # the epochs it trained in
    new = load_config("tiny", [*keys, change])
    new_steps = new.data.patches_per_epoch // new.train.batch_size
    with pytest.raises(InputError) as e:
        train(new, run, resume=True, progress=False)
    assert str(e.value) == (
        f"{run}: was trained in epochs of {old_steps} steps (a checkpoint of an older hsicam, which did not "
        f"record its batch size), and its config now asks for {new_steps} steps of {new.train.batch_size} "
        f"({new.data.patches_per_epoch} patches per epoch, train.batch_size={new.train.batch_size}): a resume would "
        "misplace where it stopped; keep the batch size and the patches per epoch as they were; nothing was changed")
    assert tree_snapshot(run) == before
    # the config it trained with goes on, to the length of an uninterrupted run
    assert train(cfg, run, resume=True, progress=False)["step"] == cfg.train.epochs * old_steps


def test_an_older_run_without_sessions_or_optimizer_hashes_resumes_bit_identically(cache_env, tmp_path):
    """A run stopped by an hsicam before session records and optimizer hashes resumes today to the weights
    of an uninterrupted run, and the resume adds its own session record."""
    from hsicam.engine.train import train

    cfg = load_config("tiny", ["train.epochs=2", "train.keep_weights=last"])
    full = tmp_path / "full"
    train(cfg, full, progress=False)
    run = tmp_path / "r"
    assert train(cfg, run, progress=False, stop_after_steps=5) == {"stopped_at_step": 5}
    _as_before_sessions_and_optimizer_hashes(run)
    train(cfg, run, resume=True, progress=False)
    a, b = load_file(full / "model.safetensors"), load_file(run / "model.safetensors")
    assert a.keys() == b.keys() and all((a[k] == b[k]).all() for k in a)
    sessions = [r for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines()) if "session" in r]
    assert [r["step"] for r in sessions] == [5]


def test_the_report_of_an_older_demo_folder_leaves_out_the_facts_it_does_not_record(tmp_path):
    """A demo folder of an older hsicam (before c36e057) records no method, data, noise or config hash in its
    results.json: its report read "Results: " and "data: ; noise: null; config ". Now only the facts it has; a
    folder of today's shows every one as before."""
    import html as html_lib

    from hsicam.io import mark_complete
    from hsicam.report.html import build_report

    def page(res):
        d = tmp_path / str(len(list(tmp_path.iterdir())))
        d.mkdir()
        (d / "results.json").write_text(json.dumps(res), encoding="utf-8")
        mark_complete(d)
        return build_report(d).read_text(encoding="utf-8")

    from hsicam.metrics import CONVENTIONS

    scenes = [{"name": "scene_0000", "psnr": 30.0, "ssim": 0.9, "sam": 5.0}]
    old = page({"scenes": scenes, "mean": {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}, "conventions": dict(CONVENTIONS)})
    assert "<h2>Results</h2>" in old
    assert "data: ;" not in old and "noise: null" not in old and "config <" not in old
    new = page({"method": "doe-learned", "data": "synthetic validation split", "noise": {"sensor_sigma": None},
                "config_hash": "abc123", "region": "valid area", "scenes": scenes,
                "mean": {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}, "conventions": dict(CONVENTIONS)})
    assert "<h2>Results: doe-learned</h2>" in new
    assert ("<p class='note'>data: synthetic validation split; noise: "
            + html_lib.escape(json.dumps({"sensor_sigma": None})) + "; config abc123; scored area: valid area</p>") in new


def _as_before_session_60(run: Path) -> None:
    """The session records an hsicam of session 59 wrote (db9c133 … c1ab911): no ``synthetic_generator``."""
    path = run / "metrics.jsonl"
    records = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
    for r in records:
        if "session" in r:
            r["session"].pop("synthetic_generator")
    path.write_text("".join(json.dumps(r) + "\n" for r in records), encoding="utf-8")


def test_a_run_started_before_session_60_resumed_today_says_what_changes(cache_env, tmp_path, caplog):
    """Session 60 changed the cosine after a warm-up (c5559eb) and the patch stream of a seed other than 0: a run
    an older hsicam started (tiny, warm-up 2 of 8 steps, seed 3, stopped at step 3) resumed today went on at
    0.933 x the rate where its own schedule gives 0.6913, on another patch stream, without a word. The resume
    now says so in one warning, naming both (again at a later resume: the run's start decides); a run of today,
    and an older one that none of the changes touch (no warm-up, seed 0), resume without it."""
    import logging
    import math
    import shutil

    from hsicam.engine.train import train

    keys = ["train.lr_schedule=cosine", "train.warmup_steps=2", "train.seed=3", "train.epochs=2"]
    cfg = load_config("tiny", keys)
    today = tmp_path / "today"
    assert train(cfg, today, progress=False, stop_after_steps=3) == {"stopped_at_step": 3}
    total = 2 * cfg.data.patches_per_epoch // cfg.train.batch_size
    older = 0.5 * (1 + math.cos(math.pi * 3 / total))  # the schedule before c5559eb, at step 3
    now = 0.5 * (1 + math.cos(math.pi * (3 - 2) / (total - 2)))
    assert (total, round(older, 4), round(now, 4)) == (8, 0.6913, 0.933)

    def warnings(run, keys_now=keys):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            train(load_config("tiny", keys_now), run, resume=True, progress=False)
        return [r.getMessage() for r in caplog.records if "session 60" in r.getMessage()]

    for fabricate in (_as_before_sessions_and_optimizer_hashes, _as_before_session_60):
        run = shutil.copytree(today, tmp_path / fabricate.__name__)
        fabricate(run)
        assert warnings(run) == [
            f"{run}: started by an hsicam before session 60, whose training this one changed; it goes on with this "
            f"one's: the cosine after the 2-step warm-up runs over the remaining {total - 2} steps (step 3: {now:.4g} x "
            f"the base rate, where that hsicam gives {older:.4g}); the training patches come from train.seed=3's own "
            "stream (that hsicam drew seed 0's) (docs/training.md): not the run that hsicam would have finished; to "
            "finish it as it began, resume it with that hsicam, or train a new run with another --out"], fabricate
    assert len(warnings(run, [*keys, "train.epochs=3"])) == 1  # its own session records since: still its start
    assert warnings(today) == []
    plain = shutil.copytree(today, tmp_path / "plain")  # the same run resumed without a warm-up, at seed 0
    _as_before_sessions_and_optimizer_hashes(plain)
    assert warnings(plain, ["train.lr_schedule=cosine", "train.warmup_steps=0", "train.seed=0", "train.epochs=2"]) == []


@pytest.mark.parametrize("damage", ["torn", "blank"])
def test_a_run_of_today_whose_first_metrics_line_is_torn_is_not_taken_for_an_older_hsicams(cache_env, tmp_path,
                                                                                            caplog, damage):
    """The run's start is judged from metrics.jsonl's first record (its starting session record). With that line
    torn (a kill mid-write: its first 40 characters) or blanked, the first whole record was the step-1 record, as
    in a run of an hsicam before db9c133, so a run of today (seed 3, warm-up 2) resumed with the warning that an
    hsicam before session 60 started it, and again at every later resume (the resume rewrote the file without the
    torn line). The start is now unknown: no warning, the torn line kept, and a fabricated older run still warns."""
    import logging
    import shutil

    from hsicam.engine.train import train

    keys = ["train.lr_schedule=cosine", "train.warmup_steps=2", "train.seed=3", "train.epochs=2"]
    today = tmp_path / "today"
    assert train(load_config("tiny", keys), today, progress=False, stop_after_steps=3) == {"stopped_at_step": 3}
    run = shutil.copytree(today, tmp_path / damage)
    path = run / "metrics.jsonl"
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    assert '"session"' in lines[0] and '"session"' not in lines[1]
    first = lines[0][:40] + "\n" if damage == "torn" else "\n"
    path.write_text(first + "".join(lines[1:]), encoding="utf-8")

    def warnings(run, epochs):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            train(load_config("tiny", [*keys, f"train.epochs={epochs}"]), run, resume=True, progress=False)
        return [r.getMessage() for r in caplog.records if "session 60" in r.getMessage()]

    assert warnings(run, 2) == []
    assert path.read_text(encoding="utf-8").splitlines(keepends=True)[0] == first  # the evidence kept
    assert warnings(run, 3) == []  # a later resume: still unknown, not older
    older = shutil.copytree(today, tmp_path / "older")
    _as_before_sessions_and_optimizer_hashes(older)
    assert len(warnings(older, 2)) == 1


def _as_started_by(commit: str):
    """The session records a run of ``commit`` (session 60, c5559eb … 215c9e2, from a git checkout) wrote: its
    git_commit, no ``synthetic_generator`` (recorded since c1ab911)."""
    def fabricate(run: Path) -> None:
        _as_before_session_60(run)
        path = run / "metrics.jsonl"
        records = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
        for r in records:
            if "session" in r:
                r["session"]["git_commit"] = commit
        path.write_text("".join(json.dumps(r) + "\n" for r in records), encoding="utf-8")
    return fabricate


@pytest.mark.parametrize("commit, named", [
    ("215c9e2c6a5b8cfb4155e94a547c7cb96ff3dbbd", None),  # the last before c1ab911: every change already
    ("487c91d1c989396c1c7d8405a8e6d100198dfd25+dirty", None),  # the validation noise's commit, src edited
    ("c5559eb5f5d609ab584e8aa0697d03cb6f465f42", "stream"),  # the cosine's commit: the seed's patches not yet
    ("c5559eb^", "cosine"),  # (the commit before: see below) an hsicam before session 60
])
def test_a_run_started_in_session_60_before_it_recorded_the_generator_is_told_by_its_commit(
        cache_env, tmp_path, caplog, commit, named):
    """A run started by a commit of session 60 between c5559eb (the cosine after a warm-up) and c1ab911 (the
    first to record ``synthetic_generator``) was taken for an older hsicam's: a run of 215c9e2 (tiny, warm-up 2,
    seed 3) resumed with the warning that 'that hsicam' gave 0.5 x the rate at step 4, where 215c9e2 gave 0.75 as
    today's does, and drew seed 0's patches. Its session record's git_commit tells which of the changes it had
    (the records fabricated here are those that commit's hsicam writes, measured by training with it)."""
    import logging
    import subprocess

    from hsicam.engine.train import train

    if commit == "c5559eb^":  # the commit before the window, from this checkout's history when it has it
        root = Path(__file__).parents[2]
        got = subprocess.run(["git", "-C", str(root), "rev-parse", "c5559eb^"], capture_output=True, text=True)
        if got.returncode:
            pytest.skip("no git history of session 60 here")
        commit = got.stdout.strip()
    keys = ["train.lr_schedule=cosine", "train.warmup_steps=2", "train.seed=3", "train.epochs=2"]
    run = tmp_path / "run"
    assert train(load_config("tiny", keys), run, progress=False, stop_after_steps=3) == {"stopped_at_step": 3}
    _as_started_by(commit)(run)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        train(load_config("tiny", keys), run, resume=True, progress=False)
    got = [r.getMessage() for r in caplog.records if "session 60" in r.getMessage()]
    if named is None:
        assert got == []
    elif named == "stream":
        assert got == [
            f"{run}: started by hsicam c5559eb (session 60, before c1ab911), whose training this one changed; it goes "
            "on with this one's: the training patches come from train.seed=3's own stream (that hsicam drew seed 0's) "
            "(docs/training.md): not the run that hsicam would have finished; to finish it as it began, resume it "
            "with that hsicam, or train a new run with another --out"]
    else:
        assert len(got) == 1 and "started by an hsicam before session 60" in got[0] and "cosine" in got[0]


def test_the_session_60_commits_are_those_between_c5559eb_and_c1ab911():
    """SESSION_60_COMMITS against this checkout's git history (skipped without it): every commit from c5559eb to
    c1ab911's parent, each with the changes its ancestors made (c5559eb cosine, 4625829 seed, 7cf40af choi_seed,
    487c91d validation_noise)."""
    import subprocess

    from hsicam.engine.provenance import SESSION_60_COMMITS

    root = Path(__file__).parents[2]
    git = lambda *a: subprocess.run(["git", "-C", str(root), *a], capture_output=True, text=True)  # noqa: E731
    listed = git("rev-list", "c5559eb^..c1ab911^")
    if listed.returncode:
        pytest.skip("no git history of session 60 here")
    firsts = {"cosine": "c5559eb", "seed": "4625829", "choi_seed": "7cf40af", "validation_noise": "487c91d"}
    want = {c: frozenset(k for k, first in firsts.items() if git("merge-base", "--is-ancestor", first, c).returncode == 0)
            for c in listed.stdout.split()}
    assert len(want) == 39 and SESSION_60_COMMITS == want


def test_an_older_run_with_noisy_validation_is_told_its_validation_noise_changed(cache_env, tmp_path, caplog):
    """Session 60 drew the validation noise from seed 0, not train.seed (487c91d): an older run of seed 3 that
    validates under sensor noise (camera.sensor.sigma 0.01, no warm-up: the patch stream the only other change)
    resumed today is told so, and a run without validation noise is not (the branch of older_run_changes for it
    had no test). The reference: the message's words, and its absence under sigma 0 or seed 0."""
    import logging

    from hsicam.config import TrainConfig
    from hsicam.engine.loop import older_run_changes
    from hsicam.engine.train import train

    noise = "the validation noise is drawn from seed 0 (that hsicam drew it from train.seed=3)"
    stream = "the training patches come from train.seed=3's own stream (that hsicam drew seed 0's)"
    t = TrainConfig(seed=3)
    assert older_run_changes(t, 3, 8, noisy_validation=True) == [stream, noise]
    assert older_run_changes(t, 3, 8, noisy_validation=False) == [stream]
    assert older_run_changes(TrainConfig(seed=0), 3, 8, noisy_validation=True) == []
    assert older_run_changes(t, 3, 8, noisy_validation=True, had=frozenset({"seed"})) == [noise]

    keys = ["train.seed=3", "train.epochs=2", "camera.sensor.sigma=0.01"]  # the task's noisy_validation() reaches it
    run = tmp_path / "run"
    assert train(load_config("tiny", keys), run, progress=False, stop_after_steps=3) == {"stopped_at_step": 3}
    _as_before_session_60(run)
    with caplog.at_level(logging.WARNING):
        train(load_config("tiny", keys), run, resume=True, progress=False)
    (got,) = [r.getMessage() for r in caplog.records if "session 60" in r.getMessage()]
    assert f"it goes on with this one's: {stream}; {noise} (docs/training.md)" in got
