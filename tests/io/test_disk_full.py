"""A full disk: one line naming the file that could not be written, nothing half-written trusted,
the last checkpoint kept and resumed from; ``evaluate --save`` refuses at once when the cubes cannot
fit, and a cube that cannot be written ends the command cleanly (it used to crash in h5py)."""

from __future__ import annotations

import errno
import json
import re
import resource
import shutil
import signal
import subprocess
from pathlib import Path

import pytest
import torch
from cli_helpers import HSICAM, cli_env, error_line, final_error_line, module_cache, run_cli_in_process

import hsicam.runs.checkpoint as checkpoint
from hsicam.config import load_config
from hsicam.engine.train import train
from hsicam.errors import InputError
from hsicam.runs.checkpoint import read_weights



@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


def _cfg():
    return load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3"])


@pytest.fixture(scope="module")
def reference(env, tmp_path_factory):
    """An uninterrupted run (8 steps; checkpoints at steps 3, 4, 6 and 8), its held-out scenes cached."""
    from hsicam.engine.experiments import heldout_scenes

    run = tmp_path_factory.mktemp("ref") / "run"
    train(_cfg(), run, progress=False)
    heldout_scenes(_cfg())  # generated now: evaluate scores them too
    return run


def _weights(run: Path) -> dict[str, torch.Tensor]:
    return read_weights(run / "model.safetensors")[0]


def _fail_at_step_6(monkeypatch, which: str) -> None:
    """The write of ``which`` (a checkpoint file, or the manifest) of step 6 meets a full disk."""
    if which == "manifest":
        real_json = checkpoint.write_json

        def write_json(path, obj):
            if Path(path).name == "checkpoints.json" and obj["last"]["step"] == 6:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real_json(path, obj)

        monkeypatch.setattr(checkpoint, "write_json", write_json)
        return
    real = checkpoint._write_safetensors

    def write(tensors, path, meta):
        if ".step-00000006." in str(path) and f"{which}." in Path(path).name:
            Path(path).write_bytes(b"half")  # what the failed write left
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(tensors, path, meta)

    monkeypatch.setattr(checkpoint, "_write_safetensors", write)


@pytest.mark.parametrize("which", ["model", "optimizer", "manifest"])
def test_a_checkpoint_that_cannot_be_written_commits_nothing_and_the_run_resumes(which, reference, tmp_path,
                                                                                  monkeypatch):
    run = tmp_path / "run"
    _fail_at_step_6(monkeypatch, which)
    with pytest.raises(InputError) as err:
        train(_cfg(), run, progress=False)
    failed = run / ("checkpoints.json" if which == "manifest" else f"checkpoints/step-00000006/{which}.safetensors")
    assert str(err.value) == (f"{failed}: No space left on device; nothing was committed: the last checkpoint (step 4) "
                              "is unchanged; free some space, then resume the run")
    man = json.loads((run / "checkpoints.json").read_text())
    assert man["last"]["step"] == 4 and man["state"]["global_step"] == 4
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step-00000004"]  # no temporary, no step 6
    monkeypatch.undo()
    summary = train(_cfg(), run, resume=True, progress=False)
    assert summary["step"] == 8
    ref, got = _weights(reference), _weights(run)
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)


def test_train_on_a_full_disk_is_one_line(env, tmp_path, monkeypatch):
    _fail_at_step_6(monkeypatch, "model")
    res = run_cli_in_process("train", "--config", "tiny", "--set", "train.epochs=2", "--set",
                             "train.checkpoint_every_steps=3", "--out", str(tmp_path / "run"))
    assert final_error_line(res) == (f"hsicam: error: {tmp_path / 'run'}/checkpoints/step-00000006/model.safetensors: No "
                               "space left on device; nothing was committed: the last checkpoint (step 4) is "
                               "unchanged; free some space, then resume the run")


def test_evaluate_save_checks_the_free_space_first(reference, tmp_path, monkeypatch):
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr("shutil.disk_usage", lambda p: usage._replace(free=300_000))
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(reference), "--out", str(out), "--save")
    line = error_line(res)
    assert re.fullmatch(rf"hsicam: error: {re.escape(str(out))}: --save writes cubes \(2 scenes\) of about [\d.]+ [KM]iB, "
                        r"and 1 MiB more is kept free beyond it \([\d.]+ [KM]iB in all\), but that disk has 293 KiB "
                        r"free; free some space, choose another --out, or drop --save", line), line
    assert "[1/2]" not in res.stderr  # refused before the evaluation
    assert not out.exists() and not list(tmp_path.glob(".ev.*"))


def _file_size_limit(limit: int):
    """preexec_fn: writes past ``limit`` bytes fail with EFBIG (as on a full disk: the write is refused)."""
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_a_cube_that_cannot_be_written_ends_evaluate_cleanly(reference, tmp_path, env):
    """Each cube is about 60 kB, the results files less than 32 kB: the first cube's write fails."""
    out = tmp_path / "ev"
    res = subprocess.run([str(HSICAM), "evaluate", "--run", str(reference), "--out", str(out), "--save"],
                         capture_output=True, text=True, timeout=120, env=cli_env(env),
                         preexec_fn=_file_size_limit(32_000))
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])  # it used to be 139 (segfault)
    line = res.stderr.strip().splitlines()[-1]  # after the evaluation's progress lines
    assert re.fullmatch(rf"hsicam: error: {re.escape(str(out))}/cubes/scene_\d+_(estimate|truth)\.h5: File too large.*",
                        line), line
    assert "Traceback" not in res.stderr and "Exception ignored" not in res.stderr
    assert not out.exists() and not list(tmp_path.glob(".ev.*"))


def test_pretrained_copy_on_a_full_disk_names_the_destination(tmp_path, env):
    res = subprocess.run([str(HSICAM), "pretrained", "copy", "standard", str(tmp_path / "cam")], capture_output=True,
                         text=True, timeout=120, env=cli_env(env), preexec_fn=_file_size_limit(64_000))
    line = error_line(res)
    assert line.startswith(f"hsicam: error: {tmp_path / 'cam'}/model.safetensors: File too large"), line
    assert not (tmp_path / "cam").exists() and not list(tmp_path.glob(".cam.*"))
