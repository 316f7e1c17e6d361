"""`hsicam tolerance` resumes: a study stopped after k rows (Ctrl-C, a kill) goes on from its progress file in the
output folder and ends with the tolerance.json of an uninterrupted study; another study's progress is refused."""

from __future__ import annotations

import json
import re

import pytest

from cli_helpers import assert_clean_error, final_error_line, run_cli_in_process
from fab_runs import fab_run  # noqa: F401 - shared fixture

#: The progress file a study keeps in its folder while it runs (hsicam.engine.tolerance.PARTIAL_FILE, as documented).
PARTIAL_FILE = "tolerance.partial.jsonl"

#: A small study of the shared run: 2 + 2 + 2×2 + 3 = 11 rows; 12 evaluations (the nominal, σ_p 40 nm twice, the
#: unshifted reference once for both shift sweeps).
STUDY = ("--max-scenes", "1", "--draws", "2", "--sigma-height-nm", "0,40", "--levels", "2,16", "--shift-cells", "0,0.5",
         "--sensor-distance-um=-50,0,50")
ROWS = 11
#: What a completed study's tolerance.json must hold as an uninterrupted one does.
SAME = ("scenes", "spec", "nominal", "shift_reference", "sweeps", "summary", "rows")


def _study(run, out, *extra):
    return run_cli_in_process("tolerance", "--run", str(run), "--out", str(out), *STUDY, *extra)


def _counting(monkeypatch, stop_at: int | None = None) -> list[int]:
    """Count the study's evaluations (``evaluate_psf`` calls); ``stop_at``: the one that raises KeyboardInterrupt
    (a Ctrl-C while that case is evaluated)."""
    import hsicam.engine.tolerance as tol

    real, calls = tol.evaluate_psf, []

    def counted(*a, **k):
        calls.append(1)
        if stop_at is not None and len(calls) == stop_at:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(tol, "evaluate_psf", counted)
    return calls


def _lines(path):
    return path.read_text(encoding="utf-8").splitlines()


@pytest.fixture(scope="module")
def whole(fab_run, tmp_path_factory):  # noqa: F811 - the fixture
    """The uninterrupted study's tolerance.json (and its folder)."""
    out = tmp_path_factory.mktemp("tol_whole") / "tol"
    res = _study(fab_run, out)
    assert res.returncode == 0, res.stderr
    assert not (out / PARTIAL_FILE).exists()  # removed when the study completes
    assert json.loads((out / ".complete").read_text())["files"] == ["tolerance.csv", "tolerance.json", "tolerance.png"]
    return json.loads((out / "tolerance.json").read_text()), out


def test_a_study_stopped_after_four_rows_resumes_to_the_uninterrupted_result(fab_run, whole, tmp_path, monkeypatch):  # noqa: F811
    want, whole_out = whole
    out = tmp_path / "tol"
    with monkeypatch.context() as m:
        calls = _counting(m, stop_at=7)  # the 7th evaluation: the shift reference, after the nominal and 4 rows
        res = _study(fab_run, out)
    assert res.returncode == 130 and len(calls) == 7, res.stderr
    assert f"stopped with 4 of {ROWS} rows done, kept in {out / PARTIAL_FILE}" in res.stderr, res.stderr
    # no final file, no marker: only the progress file, its first line the study, then the nominal and 4 rows
    assert sorted(p.name for p in out.iterdir()) == [PARTIAL_FILE]
    lines = [json.loads(x) for x in _lines(out / PARTIAL_FILE)]
    assert lines[0]["run"]["weights_sha256"] == want["run"]["weights_sha256"] and lines[0]["spec"] == want["spec"]
    assert lines[1] == {"part": "nominal", "data": {k: want["nominal"][k] for k in ("psnr", "ssim", "sam",
                                                                                   "energy_in_kernel_min")}}
    assert [x["point"] for x in lines[2:]] == [0, 1, 2, 3] and [x["row"] for x in lines[2:]] == want["rows"][:4]

    # the same command again: the nominal and the 4 rows (5 evaluations) are not evaluated again: 12 - 6 = 6 left
    calls = _counting(monkeypatch)
    res = _study(fab_run, out)
    assert res.returncode == 0, res.stderr
    assert len(calls) == 6
    assert f"resuming: 4 of {ROWS} rows done" in res.stderr, res.stderr
    done = [int(k) for k in re.findall(rf"^tolerance: (\d+)/{ROWS} points ", res.stderr, re.M)]
    assert done == list(range(5, ROWS + 1)), res.stderr
    got = json.loads((out / "tolerance.json").read_text())
    assert {k: got[k] for k in SAME} == {k: want[k] for k in SAME}
    assert (got["rows_resumed"], want["rows_resumed"]) == (4, 0)
    assert (out / "tolerance.csv").read_text() == (whole_out / "tolerance.csv").read_text()
    assert sorted(p.name for p in out.iterdir()) == [".complete", "tolerance.csv", "tolerance.json", "tolerance.png"]


def test_a_row_cut_short_by_a_kill_is_evaluated_again(fab_run, whole, tmp_path, monkeypatch):  # noqa: F811
    """A kill in the middle of a row's write leaves its line cut short: the line is dropped, its case evaluated again,
    and the next row appended starts a line of its own (appended onto the cut line, it was lost too)."""
    want, _ = whole
    out = tmp_path / "tol"
    with monkeypatch.context() as m:
        _counting(m, stop_at=11)  # stopped at row 9 (sensor distance 0), rows 0..8 done
        assert _study(fab_run, out).returncode == 130
    path = out / PARTIAL_FILE
    text = path.read_text(encoding="utf-8")
    assert [json.loads(x).get("point") for x in text.splitlines()[-2:]] == [7, 8]
    path.write_text(text[: len(text) - 40], encoding="utf-8")  # the last row (point 8) cut, no newline after it
    calls = _counting(monkeypatch, stop_at=2)  # point 8 again, then stopped at point 9
    res = _study(fab_run, out)
    assert res.returncode == 130 and len(calls) == 2
    assert f"resuming: 8 of {ROWS} rows done; 1 line(s) cut short by the interruption dropped" in res.stderr, res.stderr
    assert [json.loads(x)["point"] for x in _lines(path)[-2:]] == [7, 8]  # every line whole
    calls = _counting(monkeypatch)
    res = _study(fab_run, out)
    assert res.returncode == 0 and len(calls) == 2, res.stderr  # points 9 and 10
    got = json.loads((out / "tolerance.json").read_text())
    assert {k: got[k] for k in SAME} == {k: want[k] for k in SAME}


def test_a_resume_of_another_study_is_refused_naming_what_differs_and_restart_starts_over(fab_run, whole, tmp_path,  # noqa: F811
                                                                                         monkeypatch):
    want, _ = whole
    out = tmp_path / "tol"
    with monkeypatch.context() as m:
        _counting(m, stop_at=4)  # the nominal and 2 rows done
        assert _study(fab_run, out).returncode == 130
    path = out / PARTIAL_FILE
    kept = path.read_text(encoding="utf-8")
    calls = _counting(monkeypatch)
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), *STUDY, "--levels", "2,8",
                             "--seed", "3")
    assert_clean_error(res, f"{out}: holds an interrupted tolerance study that differs from this one (--levels (2,16 then, 2,8 "
                            "now); --seed (0 then, 3 now))", "add --restart to discard its finished rows")
    assert not calls and path.read_text(encoding="utf-8") == kept  # refused before any evaluation, nothing changed
    # another run's weights, other scenes (the first line as a study of them would have written it)
    head = json.loads(kept.splitlines()[0])
    sha = head["run"]["weights_sha256"]
    head["run"]["weights_sha256"], head["scenes"] = "0" * 64, ["elsewhere"]
    path.write_text("\n".join([json.dumps(head), *kept.splitlines()[1:]]) + "\n", encoding="utf-8")
    line = final_error_line(_study(fab_run, out))
    assert f"the run's weights (sha256 000000000000… then, {sha[:12]}… now); the scenes (elsewhere then, " \
           f"{want['scenes'][0]} now)" in line, line
    assert not calls
    # begun on another device, or by other software (another torch): rows of two computations are not mixed
    head["run"]["weights_sha256"], head["scenes"] = sha, want["scenes"]
    torch_now = head["software"]["torch"]
    head["device"], head["software"]["torch"] = "cuda:0", "1.0.0"
    path.write_text("\n".join([json.dumps(head), *kept.splitlines()[1:]]) + "\n", encoding="utf-8")
    line = final_error_line(_study(fab_run, out))
    assert f"--device (cuda:0 then, cpu now); the software (torch 1.0.0 then, {torch_now} now)" in line, line
    assert not calls
    # --restart discards them: every case evaluated, the result the uninterrupted study's
    res = _study(fab_run, out, "--restart")
    assert res.returncode == 0, res.stderr
    assert len(calls) == 12 and "resuming" not in res.stderr
    got = json.loads((out / "tolerance.json").read_text())
    assert {k: got[k] for k in SAME} == {k: want[k] for k in SAME} and got["rows_resumed"] == 0


def test_a_damaged_progress_file_is_refused_with_the_way_to_start_over(fab_run, tmp_path):  # noqa: F811
    out = tmp_path / "tol"
    out.mkdir()
    (out / PARTIAL_FILE).write_text('{"format": "hsicam-tolerance-partial-1", "ru\n', encoding="utf-8")
    assert_clean_error(_study(fab_run, out), "its first line, which names the study, is damaged",
                       "add --restart to discard it and start over")
    (out / PARTIAL_FILE).write_text('{"format": "something else"}\n', encoding="utf-8")
    assert_clean_error(_study(fab_run, out), "not the progress file of an hsicam tolerance study")
    (out / "mine.txt").write_text("notes")  # a file of the user's beside it: never resumed into, never removed
    assert_clean_error(_study(fab_run, out, "--restart"), f"{out}: holds an interrupted tolerance study "
                       f"({PARTIAL_FILE}) and mine.txt, which hsicam tolerance did not write")
    assert (out / "mine.txt").is_file()


def test_a_completed_study_rerun_and_stopped_keeps_the_old_results_until_the_new_ones_are_whole(fab_run, whole,  # noqa: F811
                                                                                               tmp_path, monkeypatch):
    """A completed folder is studied again as a whole (as before resume); stopped half-way, its completed files and
    marker stay as they were beside the new progress file, and the same command completes the new study."""
    import shutil

    want, whole_out = whole
    out = tmp_path / "tol"
    shutil.copytree(whole_out, out)
    before = {n: (out / n).read_bytes() for n in ("tolerance.json", "tolerance.csv", "tolerance.png", ".complete")}
    with monkeypatch.context() as m:
        _counting(m, stop_at=3)
        assert _study(fab_run, out, "--sensor-distance-um=0,50").returncode == 130
    assert {n: (out / n).read_bytes() for n in before} == before and (out / PARTIAL_FILE).is_file()
    res = _study(fab_run, out, "--sensor-distance-um=0,50")
    assert res.returncode == 0, res.stderr
    assert f"resuming: 1 of {ROWS - 1} rows done" in res.stderr
    got = json.loads((out / "tolerance.json").read_text())
    assert got["sweeps"]["sensor_distance_um"]["values"] == [0.0, 50.0]
    assert got["rows"][:-2] == want["rows"][:-3]  # the other sweeps as the whole study's
    assert not (out / PARTIAL_FILE).exists()
