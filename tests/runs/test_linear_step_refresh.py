"""The linear consistency step's filters (``RUN/linear_step.safetensors``) stay those of the run's
weights and config (session 23).

Before: extending a finished run (``train --resume --set train.epochs=N``) kept the filters fitted
through the old optics, and every later reconstruction used them without a word; a fine-tuned run
of a linear-step run had no filters at all (``evaluate`` refused it, naming a command that refuses
fine-tuned runs); ``train --resume --set model.consistency.window_px=w`` on a finished run refitted
nothing (or, with the file removed, left config.yaml at the old width); a packed camera's filters
were not on its card.

The references are independent of the code under test's bookkeeping: the filters a run holds are
compared with :func:`fit_linear_map` through the weights as loaded, and sha256 with hashlib.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
import torch

from hsicam.cli import main
from hsicam.config import load_config
from hsicam.errors import InputError
from hsicam.runs import pretrained as shipped
from hsicam.runs.linear_step import LINEAR_STEP_FILE, linear_step_info

WINDOW = 11  # the default filter width
LINEAR = ("model.consistency.iterations=1", "model.consistency.kind=linear")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def refit_reference(run: Path, window: int) -> torch.Tensor:
    """The least-squares filters through the run's weights as load_run gives them (measured PSFs
    for a fine-tuned run), fitted here on the run's training scenes."""
    from hsicam.data.pipeline import scene_dataset, split_dataset
    from hsicam.engine.linear_step import fit_linear_map
    from hsicam.runs.folder import load_run

    (run / LINEAR_STEP_FILE).rename(run / "aside.safetensors")  # load_run must not check the file under test
    try:
        cfg, model = load_run(run)
    finally:
        (run / "aside.safetensors").rename(run / LINEAR_STEP_FILE)
    bands = cfg.bands.to_bands()
    train_list, _ = split_dataset(cfg.data, bands)
    return fit_linear_map(model, scene_dataset(cfg.data, train_list, bands), window)


def stored_filters(run: Path) -> torch.Tensor:
    from safetensors.torch import load_file

    return load_file(str(run / LINEAR_STEP_FILE))["weight"].clone()  # not a view of the file (copied over below)


@pytest.fixture(scope="module")
def linear_run(tmp_path_factory, cache_env):
    """A finished tiny run (1 epoch) with the linear consistency step."""
    d = tmp_path_factory.mktemp("linear") / "run"
    sets = [x for s in LINEAR for x in ("--set", s)]
    assert main(["train", "--config", "tiny", "--out", str(d), "--set", "train.epochs=1", *sets]) == 0
    return d


def test_a_new_run_records_the_weights_its_filters_were_fitted_through(linear_run):
    info = linear_step_info(linear_run / LINEAR_STEP_FILE)
    assert info["weights_sha256"] == sha256(linear_run / "model.safetensors")
    assert info["filter_px"] == WINDOW == stored_filters(linear_run).shape[-1]
    torch.testing.assert_close(stored_filters(linear_run), refit_reference(linear_run, WINDOW))


def test_extending_a_finished_run_refits_its_filters_through_the_new_weights(linear_run, tmp_path, capsys):
    run = shutil.copytree(linear_run, tmp_path / "run")
    old = stored_filters(run)
    assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=4"]) == 0
    info = linear_step_info(run / LINEAR_STEP_FILE)
    assert info["weights_sha256"] == sha256(run / "model.safetensors") != sha256(linear_run / "model.safetensors")
    new = stored_filters(run)
    torch.testing.assert_close(new, refit_reference(run, WINDOW))
    assert (new - old).abs().max() > 1e-6  # the optics trained on: the old filters no longer fit


def test_load_run_refuses_filters_fitted_through_other_weights(linear_run, tmp_path, capsys):
    from hsicam.runs.folder import load_run

    run = shutil.copytree(linear_run, tmp_path / "run")
    assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=4"]) == 0
    shutil.copyfile(linear_run / LINEAR_STEP_FILE, run / LINEAR_STEP_FILE)  # the filters of epoch 1, as before the fix
    with pytest.raises(InputError, match=rf"{run / LINEAR_STEP_FILE} was fitted through other weights .*; refit it: "
                                         rf"hsicam train --out {run} --resume$"):
        load_run(run)
    capsys.readouterr()
    assert main(["evaluate", "--run", str(run), "--out", str(tmp_path / "ev")]) == 2
    err = capsys.readouterr().err
    assert "was fitted through other weights" in err and "Traceback" not in err and not (tmp_path / "ev").exists()
    # the command it names brings the run back: the filters through its weights, load_run accepts them
    assert main(["train", "--out", str(run), "--resume"]) == 0
    assert "its linear consistency step refitted" in capsys.readouterr().out
    torch.testing.assert_close(stored_filters(run), refit_reference(run, WINDOW))
    load_run(run)


def test_a_damaged_filter_file_is_refitted_by_the_resume_it_names(linear_run, tmp_path, capsys):
    """A linear_step.safetensors cut short made the run unloadable, even reconstructed without the step, and the
    `train --resume` that refits stale filters called it up to date ("nothing changed")."""
    from hsicam.runs.folder import load_run

    run = shutil.copytree(linear_run, tmp_path / "run")
    path = run / LINEAR_STEP_FILE
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(InputError, match=rf"corrupt or unreadable .*; refit it: hsicam train --out {run} --resume$"):
        load_run(run)
    _, model = load_run(run, overrides=("model.consistency.kind=landweber",))  # without the step: loads
    assert model.linear_step is None
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume"]) == 0
    assert "its linear consistency step refitted" in capsys.readouterr().out
    torch.testing.assert_close(stored_filters(run), refit_reference(run, WINDOW))
    assert load_run(run)[1].linear_step is not None


def test_a_finished_run_resumed_with_another_filter_width_records_and_refits_it(linear_run, tmp_path, capsys):
    run = shutil.copytree(linear_run, tmp_path / "run")
    weights = sha256(run / "model.safetensors")
    assert main(["train", "--out", str(run), "--resume", "--set", "model.consistency.window_px=5"]) == 0
    out = capsys.readouterr().out
    assert ("already finished at step 4 (1 epochs); model.consistency in config.yaml (window_px 11 → 5); its linear "
            "consistency step refitted (linear_step.safetensors), nothing else changed") in out
    assert load_config(run / "config.yaml").model.consistency.window_px == 5
    assert stored_filters(run).shape[-1] == 5 and sha256(run / "model.safetensors") == weights
    torch.testing.assert_close(stored_filters(run), refit_reference(run, 5))
    # the same again: nothing to do, nothing written
    before = (run / LINEAR_STEP_FILE).stat().st_mtime_ns, (run / "config.yaml").read_bytes()
    assert main(["train", "--out", str(run), "--resume", "--set", "model.consistency.window_px=5"]) == 0
    assert "nothing changed" in capsys.readouterr().out
    assert ((run / LINEAR_STEP_FILE).stat().st_mtime_ns, (run / "config.yaml").read_bytes()) == before


def test_a_finetuned_run_gets_filters_through_its_measured_psfs(linear_run, tmp_path, capsys):
    from cli_helpers import write_measured_psfs
    from hsicam.runs.folder import load_run

    # "measured": shifted by a pixel, so the fit must differ
    psf_dir = write_measured_psfs(linear_run, tmp_path / "measured", shift_px=1)
    ft = tmp_path / "ft"
    assert main(["finetune", "--run", str(linear_run), "--psf-dir", str(psf_dir), "--out", str(ft), "--epochs", "1"]) == 0
    assert linear_step_info(ft / LINEAR_STEP_FILE)["weights_sha256"] == sha256(ft / "model.safetensors")
    mine = stored_filters(ft)
    torch.testing.assert_close(mine, refit_reference(ft, WINDOW))
    assert (mine - stored_filters(linear_run)).abs().max() > 1e-4
    capsys.readouterr()
    assert main(["evaluate", "--run", str(ft), "--out", str(tmp_path / "ev")]) == 0  # refused before: no filters
    # a stale copy names the fine-tuning's own command, which refits it
    shutil.copyfile(linear_run / LINEAR_STEP_FILE, ft / LINEAR_STEP_FILE)
    with pytest.raises(InputError, match=rf"refit it: hsicam finetune --run {linear_run} --psf-dir {psf_dir} --out "
                                         rf"{ft} --resume$"):
        load_run(ft)
    assert main(["finetune", "--run", str(linear_run), "--psf-dir", str(psf_dir), "--out", str(ft), "--resume"]) == 0
    torch.testing.assert_close(stored_filters(ft), mine)


def test_a_packed_camera_records_its_filters_and_refuses_others(linear_run, tmp_path, monkeypatch):
    from hsicam.engine.pretrained import pack_pretrained

    root = tmp_path / "root"
    pack_pretrained(linear_run, "camL", root)
    card = json.loads((root / "camL" / "card.json").read_text())
    step = root / "camL" / LINEAR_STEP_FILE
    assert card["linear_step"] == {"file": LINEAR_STEP_FILE, "bytes": step.stat().st_size, "sha256": sha256(step)}
    monkeypatch.setenv(shipped.ENV_VAR, str(root))
    assert shipped.resolve_run("pretrained:camL") == root / "camL"
    from safetensors.torch import save_file

    save_file({"weight": stored_filters(linear_run) * 1.01}, str(step), metadata={"format": "hsicam-linear-step-1"})
    with pytest.raises(InputError, match=rf"{step}: does not match its card \(sha256 {sha256(step)[:12]}…, card.json "
                                         rf"records {card['linear_step']['sha256'][:12]}…\)"):
        shipped.resolve_run("pretrained:camL")
    step.unlink()
    with pytest.raises(InputError, match=rf"{step}: missing \(its card records it\)"):
        shipped.resolve_run("pretrained:camL")


@pytest.mark.parametrize("name", shipped.available(shipped.package_root()))
def test_a_shipped_cameras_card_records_its_filters(name, monkeypatch):
    monkeypatch.delenv(shipped.ENV_VAR, raising=False)
    folder = shipped.pretrained_dir(name)
    step = folder / LINEAR_STEP_FILE
    if step.is_file():
        assert shipped.read_card(name)["linear_step"]["sha256"] == sha256(step)
    assert shipped.weights_problem(folder) is None


def test_stale_filters_do_not_block_a_run_evaluated_without_them(linear_run, tmp_path):
    from hsicam.runs.folder import load_run

    run = shutil.copytree(linear_run, tmp_path / "run")
    assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=4"]) == 0
    shutil.copyfile(linear_run / LINEAR_STEP_FILE, run / LINEAR_STEP_FILE)
    _, model = load_run(run, overrides=("model.consistency.kind=landweber",))
    assert model.linear_step is None


def test_evaluate_with_another_filter_width_or_stale_filters_names_the_refit(linear_run, tmp_path, capsys):
    """evaluate --set model.consistency.window_px=5 used the run's 11 px filters and recorded a config
    of its own (probe 25, F4); stale filters asked for by --set kind=linear were called missing (F6)."""
    from cli_helpers import assert_clean_error, run_cli_in_process

    out = tmp_path / "ev"
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(linear_run), "--out", str(out), "--set",
                                          "model.consistency.window_px=5"),
                       f"{linear_run / LINEAR_STEP_FILE} holds 11 px filters; model.consistency.window_px asks for 5; "
                       f"refit it: hsicam train --out {linear_run} --resume --set model.consistency.window_px=5")
    run = shutil.copytree(linear_run, tmp_path / "run")
    assert main(["train", "--out", str(run), "--resume", "--set", "train.epochs=4", "--set",
                 "model.consistency.kind=landweber"]) == 0  # trained on: the filters (not refitted) are stale
    assert "landweber" in (run / "config.yaml").read_text()
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), "--set",
                                          "model.consistency.kind=linear"),
                       f"{run / LINEAR_STEP_FILE} was fitted through other weights",
                       f"refit it: hsicam train --out {run} --resume --set model.consistency.kind=linear")
    assert not out.exists()
    assert main(["train", "--out", str(run), "--resume", "--set", "model.consistency.kind=linear"]) == 0
    assert run_cli_in_process("evaluate", "--run", str(run), "--out", str(out)).returncode == 0


@pytest.mark.parametrize("name", shipped.available(shipped.package_root()))
def test_a_shipped_camera_with_another_width_is_told_its_filters_are_fixed(name, monkeypatch):
    """A shipped camera is read-only and a copy has no checkpoint to resume: no refit command."""
    import dataclasses

    from hsicam.runs.folder import linear_step_problem

    monkeypatch.delenv(shipped.ENV_VAR, raising=False)
    folder = shipped.pretrained_dir(name)
    if not (folder / LINEAR_STEP_FILE).is_file():
        pytest.skip("no linear step")
    own = load_config(folder / "config.yaml").model.consistency
    width = linear_step_info(folder / LINEAR_STEP_FILE)["filter_px"]
    assert linear_step_problem(folder, own) is None
    other = dataclasses.replace(own, window_px=width + 2)
    assert linear_step_problem(folder, other) == (
        f"{folder / LINEAR_STEP_FILE} holds {width} px filters; model.consistency.window_px asks for {width + 2}; "
        "a shipped camera's filters are fixed: evaluate it with its own model.consistency settings")


def test_a_run_without_its_filters_is_named_with_what_to_do(cache_env, linear_run, tmp_path):
    """A run stopped before its training ended has no filters yet: evaluate said only "for a run without it:
    `hsicam train --out RUN …`" (a placeholder, and a refit for a run that needs its training finished)."""
    from cli_helpers import assert_clean_error, final_error_line, run_cli_in_process

    from hsicam.engine.train import train

    stopped = tmp_path / "stopped"
    keys = ["train.epochs=2", *LINEAR]
    assert train(load_config("tiny", keys), stopped, progress=False, stop_after_steps=3) == {"stopped_at_step": 3}
    assert not (stopped / LINEAR_STEP_FILE).exists()
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(stopped), "--out", str(out))
    line = final_error_line(res)  # after the warning that the training did not finish, before any scene is read
    for fragment in (f"{stopped}: model.consistency.kind=linear needs the run's {LINEAR_STEP_FILE}",
                     f"its training did not finish, and the step is fitted when it ends: hsicam train --out {stopped} "
                     "--resume", "--set model.consistency.kind=landweber"):
        assert fragment in line, line
    assert "generating" not in res.stderr and "[1/" not in res.stderr
    finished = shutil.copytree(linear_run, tmp_path / "finished")
    (finished / LINEAR_STEP_FILE).unlink()
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(finished), "--out", str(out)),
                       f"fit it: hsicam train --out {finished} --resume --set model.consistency.kind=linear")
    assert not out.exists()


def test_a_damaged_filter_file_of_a_copied_camera_names_no_resume_it_cannot_do(tmp_path, capsys):
    """A copied camera (`hsicam pretrained copy`: weights, no checkpoint) whose linear_step.safetensors was cut short
    advised "hsicam train --out COPY --resume", which then failed with "no checkpoint to resume" (a helper's hunt,
    session 71); it says to copy the camera again."""
    from hsicam.runs.folder import load_run

    copy = tmp_path / "copy"
    assert main(["pretrained", "copy", "standard", str(copy)]) == 0
    path = copy / LINEAR_STEP_FILE
    path.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(InputError) as exc:
        load_run(copy)
    assert str(exc.value).startswith(f"{path}: corrupt or unreadable safetensors file")
    assert str(exc.value).endswith("; the run has no checkpoint to refit the filters from: copy the run folder again "
                                   "from its source, or train it again")
