"""A run whose kept weights are damaged or missing: the root weights (model.safetensors) gone and the checkpoint the
manifest keeps (``train.keep_weights``) damaged, at the end of a training, on a resume, on a change of
``train.keep_weights`` and in the commands that read the run.

- The end of a training: the loop leaves the root as it is with a warning, and ``hsicam train`` exited 0 while the
  next ``hsicam evaluate`` refused the run ("the run has no trained weights"). Now the training itself fails (exit 2),
  in one line naming the damaged file and the way out (the run's intact last checkpoint: ``--resume --set
  train.keep_weights=last``), the run folder finished and consistent (final record, manifest, no root written from
  the final model).
- The readers (``hsicam evaluate --run``, any reader through :func:`hsicam.runs.folder.load_run`) said "the run has no
  trained weights (model.safetensors is missing)", which hides the damaged checkpoint and the intact last one; they
  now name the damaged file and the way out, as ``hsicam train`` does (:func:`hsicam.engine.train.check_kept_weights`).
- A finished run whose root weights were lost (its kept checkpoint intact) gets them back on ``--resume``.

References: the exact line a user sees, written out here; the files' sha256 against the manifest's."""

from __future__ import annotations

import hashlib
import json

import pytest
import torch

from cli_helpers import error_line, run_cli_in_process
from damage import flip_byte_in_place
from hsicam.config import dump_yaml, load_config
from hsicam.errors import InputError
from hsicam.runs.checkpoint import MANIFEST, RECOPY_HINT, CheckpointManager, root_weights_path
from hsicam.runs.folder import load_run
from hsicam.spectral import Bands
from hsicam.io import _HASHES as hashes_read  # the file hashes read in this process

BANDS = Bands.uniform(500, 600, 50)


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _two_checkpoints(tmp_path):
    """A run keeping its best (step 1) whose last is step 2; its root weights deleted and its best damaged."""
    run = tmp_path / "run"
    mgr = CheckpointManager(run)
    for step, tags in ((1, ("last", "best")), (2, ("last",))):
        net = torch.nn.Linear(2, 3)
        mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": step, "best_psnr": 20.0}, BANDS, tags)
    man = json.loads((run / MANIFEST).read_text())
    root, best = run / "model.safetensors", run / man["best"]["dir"] / "model.safetensors"
    root.unlink()
    flip_byte_in_place(best, best.stat().st_size - 3)
    hashes_read.clear()
    return run, root, best, man


def _refusal(run, root, best, sha, way):
    return (f"training ended, but the run has no readable weights: {root} is missing, and {best}, which should hold "
            f"the weights {run / MANIFEST} records (sha256 {sha[:12]}…), differs from them: the run's weights are "
            f"damaged (a copy cut short, a disk error, an edit); {way}")


def test_a_damaged_kept_checkpoint_is_refused_with_the_intact_last_as_the_way_out(tmp_path):
    from hsicam.engine.train import check_kept_weights

    run, root, best, man = _two_checkpoints(tmp_path)
    with pytest.raises(InputError) as err:
        check_kept_weights(run)
    assert str(err.value) == _refusal(run, root, best, man["best"]["weights_sha256"],
                                      f"keep the last checkpoint's weights (step 2, intact) instead: hsicam train --out "
                                      f"{run} --resume --set train.keep_weights=last; or {RECOPY_HINT}")


def test_with_the_last_damaged_too_only_a_new_copy_is_offered(tmp_path):
    from hsicam.engine.train import check_kept_weights

    run, root, best, man = _two_checkpoints(tmp_path)
    last = run / man["last"]["dir"] / "model.safetensors"
    flip_byte_in_place(last, last.stat().st_size - 3)
    hashes_read.clear()
    with pytest.raises(InputError) as err:
        check_kept_weights(run)
    assert str(err.value) == _refusal(run, root, best, man["best"]["weights_sha256"], RECOPY_HINT)


def test_readable_runs_pass(tmp_path):
    from hsicam.engine.train import check_kept_weights

    run, root, best, man = _two_checkpoints(tmp_path)
    CheckpointManager(run, keep="last").apply_keep()  # the way out: the root now holds the last checkpoint's weights
    check_kept_weights(run)
    assert root_weights_path(run) == root and _sha(root) == man["last"]["weights_sha256"]


def _stopped_run_with_its_best_damaged(tmp_path):
    """Tiny run, 2 epochs, best after epoch 1 (step 4), stopped at step 5; its root weights deleted and the best
    checkpoint given a flipped byte. (config, run, root, damaged best, the best's recorded sha256)."""
    from hsicam.engine.train import train

    torch.set_num_threads(1)
    run = tmp_path / "run"
    cfg = load_config("tiny", ["train.epochs=2", "train.checkpoint_every_steps=3"])
    train(cfg, run, progress=False, stop_after_steps=5)
    man = json.loads((run / MANIFEST).read_text())
    assert man["weights"]["from"] == "best" and man["best"]["step"] < man["last"]["step"], man  # the case
    root, best, sha = run / "model.safetensors", run / man["best"]["dir"] / "model.safetensors", man["best"]["weights_sha256"]
    root.unlink()
    flip_byte_in_place(best, best.stat().st_size - 3)
    hashes_read.clear()
    return cfg, run, root, best, sha


def test_hsicam_train_fails_at_the_end_and_the_way_out_works(cache_env, tmp_path, capsys):
    """Tiny run, 2 epochs, best after epoch 1 (step 4), stopped at step 5; the root deleted and the best damaged;
    `hsicam train --resume` trains to step 8 and exits 2 (was 0), again when resumed as it is, and 0 with
    train.keep_weights=last, after which the run's weights are the last checkpoint's."""
    from hsicam.cli import main

    _, run, root, best, sha = _stopped_run_with_its_best_damaged(tmp_path)
    capsys.readouterr()
    for _ in range(2):  # the end of the training, then a resume of the finished run as it is
        assert main(["train", "--out", str(run), "--resume"]) == 2
        man = json.loads((run / MANIFEST).read_text())
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1] == "hsicam: error: " + _refusal(
            run, root, best, sha, f"keep the last checkpoint's weights (step {man['last']['step']}, intact) instead: "
                                  f"hsicam train --out {run} --resume --set train.keep_weights=last; or {RECOPY_HINT}")
        final = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
        assert final["final"] and final["step"] == man["last"]["step"] == 8 and not root.exists()
    assert main(["train", "--out", str(run), "--resume", "--set", "train.keep_weights=last"]) == 0
    assert root_weights_path(run) == root and _sha(root) == man["last"]["weights_sha256"]


def test_a_finished_run_resumed_without_its_root_weights_gets_them_back(cache_env, tmp_path, capsys):
    """A finished tiny run whose root weights were deleted (the kept checkpoint intact): every reader refused it ("the
    run has no trained weights") while `hsicam train --resume` said "already finished ... nothing changed" and exit 0,
    the root still missing. The resume now copies the kept checkpoint back (bytes equal to the manifest's sha256) and
    says so; `load_run` then reads the run."""
    from hsicam.cli import main
    from hsicam.config import load_config
    from hsicam.engine.train import train
    from hsicam.runs.folder import load_run

    torch.set_num_threads(1)
    run = tmp_path / "run"
    train(load_config("tiny", ["train.epochs=1"]), run, progress=False)
    man = json.loads((run / MANIFEST).read_text())
    root = run / "model.safetensors"
    root.unlink()
    hashes_read.clear()
    kept = man["weights"]["from"]
    with pytest.raises(InputError) as err:
        load_run(run)
    assert str(err.value) == (f"{run}: the run has no trained weights (model.safetensors is missing); its kept "
                              f"checkpoint {run / man[kept]['dir'] / 'model.safetensors'} holds them: hsicam train "
                              f"--out {run} --resume restores them")
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume"]) == 0
    said = capsys.readouterr().out.strip().splitlines()[-1]
    assert f"its root weights {root} restored from the {kept} checkpoint (step {man[kept]['step']})" in said, said
    assert _sha(root) == man[kept]["weights_sha256"] == man["weights"]["sha256"]
    load_run(run)


def _saved_run(tmp_path, keep: str = "best"):
    """A run folder with one committed checkpoint of a tiny network: (run, manager, network)."""
    run = tmp_path / "run"
    net = torch.nn.Linear(2, 3)
    mgr = CheckpointManager(run, keep=keep)
    mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": 1, "best_psnr": None}, BANDS)
    return run, mgr, net


def test_root_weights_path_says_the_root_is_missing_not_that_it_differs(tmp_path):
    """The root weights deleted and the kept checkpoint damaged: the refusal said the root "differs" from the manifest's
    weights, although there was no root file at all."""
    run, _, _ = _saved_run(tmp_path)
    root, kept = run / "model.safetensors", run / "checkpoints" / "step-00000001" / "model.safetensors"
    sha = json.loads((run / MANIFEST).read_text())["weights"]["sha256"]
    root.unlink()
    flip_byte_in_place(kept, kept.stat().st_size - 3)
    hashes_read.clear()
    with pytest.raises(InputError) as err:
        root_weights_path(run)
    assert str(err.value) == (f"{root} is missing, and {kept}, which should hold the weights {run / MANIFEST} records "
                              f"(sha256 {sha[:12]}…), differs from them: the run's weights are damaged (a copy cut "
                              f"short, a disk error, an edit); {RECOPY_HINT}")


def test_fit_does_not_write_its_final_weights_as_the_root_when_the_kept_checkpoint_is_damaged(cache_env, tmp_path,
                                                                                                caplog):
    """Tiny run, 2 epochs, best after epoch 1 (step 4), stopped at step 5; the root weights deleted and the best
    checkpoint given a flipped byte; then resumed to the end. The end of fit wrote the final model's weights (step 8's)
    as the root, which the manifest does not record (readers refused them as "differing"). The root now stays missing,
    the warning naming the damaged checkpoint, and the readers' refusal says the root is missing."""
    import hashlib
    import logging

    from hsicam.engine.train import train

    cfg, run, root, kept, sha = _stopped_run_with_its_best_damaged(tmp_path)
    with caplog.at_level(logging.WARNING, logger="hsicam.runs.checkpoint"):
        with pytest.raises(InputError, match="^training ended, but the run has no readable weights: "):  # (the refusal: test_hsicam_train_fails_at_the_end_...)
            train(cfg, run, resume=True, progress=False)
    final = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    man = json.loads((run / MANIFEST).read_text())
    assert final["final"] and final["step"] == man["last"]["step"] > 5 and man["weights"]["dir"] == man["best"]["dir"]  # best unchanged
    assert hashlib.sha256(kept.read_bytes()).hexdigest() != sha
    assert not root.exists()
    said = {r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "hsicam.runs.checkpoint"}
    assert said == {f"{kept} differs from the weights {run / MANIFEST} records (sha256 {sha[:12]}…): the checkpoint is "
                    f"damaged (a copy cut short, a disk error, an edit), so {root} was not rewritten from it; {RECOPY_HINT}"}
    with pytest.raises(InputError, match=r" is missing, and .* differs from them: the run's weights are damaged"):
        root_weights_path(run)


def test_apply_keep_refuses_a_damaged_checkpoint_before_committing_it(tmp_path):
    """A run keeping its best (step 1), its last checkpoint (step 2) given a flipped byte, then asked to keep its last
    (train.keep_weights: last): apply_keep committed the manifest to the damaged checkpoint, sync_root then left the
    root alone, and a run that readers took became one they refused. Now one refusal, the manifest and root unchanged."""
    import hashlib

    run = tmp_path / "run"
    mgr = CheckpointManager(run)
    for step, tags in ((1, ("last", "best")), (2, ("last",))):
        net = torch.nn.Linear(2, 3)
        mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": step, "best_psnr": 20.0}, BANDS, tags)
    root, last = run / "model.safetensors", run / "checkpoints" / "step-00000002" / "model.safetensors"
    sha = json.loads((run / MANIFEST).read_text())["last"]["weights_sha256"]
    flip_byte_in_place(last, last.stat().st_size - 3)
    hashes_read.clear()
    assert hashlib.sha256(last.read_bytes()).hexdigest() != sha
    before = {p: p.read_bytes() for p in (run / MANIFEST, root)}
    with pytest.raises(InputError) as err:
        CheckpointManager(run, keep="last").apply_keep()
    assert str(err.value) == (f"{last} differs from the weights {run / MANIFEST} records (sha256 {sha[:12]}…): the "
                              "last checkpoint is damaged (a copy cut short, a disk error, an edit), so the run cannot "
                              f"keep it (train.keep_weights: last); nothing was changed; {RECOPY_HINT}")
    assert {p: p.read_bytes() for p in before} == before
    assert root_weights_path(run) == root  # still the run's recorded (best) weights


def _reader_run(tmp_path, damage_last: bool = False):
    """A tiny run's config.yaml and a manifest keeping its best (step 1) whose last is step 2 (weights of a small
    stand-in module: the refusal comes before any is loaded); the root weights deleted and the best damaged."""
    run = tmp_path / "run"
    mgr = CheckpointManager(run)
    cfg = load_config("tiny")
    for step, tags in ((1, ("last", "best")), (2, ("last",))):
        net = torch.nn.Linear(2, 3)
        mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": step, "best_psnr": 20.0},
                 cfg.bands.to_bands(), tags)
    (run / "config.yaml").write_text(dump_yaml(cfg))
    man = json.loads((run / MANIFEST).read_text())
    root, best, last = (run / "model.safetensors", run / man["best"]["dir"] / "model.safetensors",
                        run / man["last"]["dir"] / "model.safetensors")
    root.unlink()
    for f in (best, last) if damage_last else (best,):
        flip_byte_in_place(f, f.stat().st_size - 3)
    hashes_read.clear()
    return run, (f"{run}: the run has no readable weights: {root} is missing, and {best}, which should hold the "
                 f"weights {run / MANIFEST} records (sha256 {man['best']['weights_sha256'][:12]}…), differs from them: "
                 f"the run's weights are damaged (a copy cut short, a disk error, an edit); ")


def test_load_run_names_the_damaged_checkpoint_and_the_intact_last(tmp_path):
    run, said = _reader_run(tmp_path)
    with pytest.raises(InputError) as err:
        load_run(run)
    assert str(err.value) == said + (f"keep the last checkpoint's weights (step 2, intact) instead: hsicam train --out "
                                     f"{run} --resume --set train.keep_weights=last; or {RECOPY_HINT}")


def test_load_run_with_the_last_damaged_too_offers_only_a_new_copy(tmp_path):
    run, said = _reader_run(tmp_path, damage_last=True)
    with pytest.raises(InputError) as err:
        load_run(run)
    assert str(err.value) == said + RECOPY_HINT


def test_hsicam_evaluate_says_it_in_one_line(tmp_path):
    run, said = _reader_run(tmp_path)
    res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev"))
    assert error_line(res) == "hsicam: error: " + said + (
        f"keep the last checkpoint's weights (step 2, intact) instead: hsicam train --out {run} --resume --set "
        f"train.keep_weights=last; or {RECOPY_HINT}")
    assert not (tmp_path / "ev").exists()
