"""Guards found by mutation testing of the run folder (:mod:`hsicam.runs.folder`; its lock's guard is in
tests/runs/test_run_lock.py), the linear step's file (:mod:`hsicam.runs.linear_step`), shipped cameras
(:mod:`hsicam.runs.pretrained`, :mod:`hsicam.engine.pretrained`), the data record and provenance
(:mod:`hsicam.engine.provenance`) and checkpoints (:mod:`hsicam.runs.checkpoint`): each test kills a
mutant that the other tests let live, against an independent reference (the error a user sees, a file
read back in its real format, a sum done by hand)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from hsicam.errors import InputError
from hsicam.runs.linear_step import load_linear_step, save_linear_step


# ------------------------------------------------------------------------------------------------
# The linear step's file
# ------------------------------------------------------------------------------------------------
def test_linear_step_filters_of_even_width_are_refused_with_the_expected_shape(tmp_path):
    path = tmp_path / "linear_step.safetensors"
    save_linear_step(path, torch.zeros(4, 3, 4, 4), {"weights_sha256": "0" * 64})
    with pytest.raises(InputError) as exc:
        load_linear_step(path, bands=3, period=2)
    assert str(exc.value) == (f"{path}: filters of shape (4, 3, 4, 4) do not fit a camera of 3 bands and CFA period 2 "
                              "(expected (4, 3, K, K), K odd)")
    save_linear_step(path, torch.zeros(4, 3, 5, 5), {})
    assert tuple(load_linear_step(path, bands=3, period=2).shape) == (4, 3, 5, 5)


def test_linear_step_filters_holding_nan_or_inf_are_refused_with_their_count(tmp_path):
    path = tmp_path / "linear_step.safetensors"
    w = torch.zeros(1, 2, 3, 3)
    w[0, 1, 1, 1], w[0, 0, 2, 0] = float("nan"), float("inf")
    save_linear_step(path, w, {})
    with pytest.raises(InputError) as exc:
        load_linear_step(path, bands=2, period=1)
    assert str(exc.value) == (f"{path}: 2 NaN/Inf value(s) in the linear step's filters; delete the file and resume "
                              "the run (hsicam train --out RUN --resume) to fit it again")


def test_a_safetensors_file_of_another_format_is_not_a_linear_step_file(tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "linear_step.safetensors"
    save_file({"weight": torch.zeros(1, 2, 3, 3)}, str(path), metadata={"format": "hsicam-weights-1"})
    with pytest.raises(InputError) as exc:
        load_linear_step(path, bands=2, period=1)
    assert str(exc.value) == f"{path}: not a linear-step file"


# ------------------------------------------------------------------------------------------------
# The run folder
# ------------------------------------------------------------------------------------------------
def _manifest(run_dir: Path, state: dict) -> None:
    """A committed checkpoint as :class:`~hsicam.runs.checkpoint.CheckpointManager` writes its manifest."""
    d = f"checkpoints/step-{state['global_step']:08d}"
    (run_dir / d).mkdir(parents=True)
    entry = {"dir": d, "step": state["global_step"]}
    (run_dir / "checkpoints.json").write_text(json.dumps(
        {"format": "hsicam-run-manifest-1", "last": entry, "best": None, "state": state,
         "weights": {"file": "model.safetensors", "from": "last", "dir": d, "sha256": None}}))


def _metrics(run_dir: Path, records: list[dict]) -> None:
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_a_final_record_of_an_earlier_session_does_not_make_an_extended_run_finished(tmp_path):
    from hsicam.config import load_config
    from hsicam.runs.folder import unfinished_training

    cfg = load_config("tiny", ["train.epochs=4"])
    # trained 2 epochs (final at step 6), resumed with train.epochs=4, killed after its checkpoint at step 9 (no log
    # record since: train.log_every_steps above 3): the last record is the earlier training's final one
    _manifest(tmp_path, {"global_step": 9, "epoch": 3, "total_steps": 12})
    _metrics(tmp_path, [{"step": 3, "epoch": 1, "train_loss": 0.7}, {"step": 6, "epoch": 2, "final": True}])
    assert unfinished_training(tmp_path, cfg) == (
        f"{tmp_path}: its training did not finish: the last checkpoint is at step 9 of 12 (3 of 4 epochs done) and "
        "metrics.jsonl has no final record; the weights are of a partly trained network: continue it with "
        f"`hsicam train --resume --out {tmp_path}`")
    _metrics(tmp_path, [{"step": 9, "epoch": 3, "final": True}])  # its own final record: finished
    assert unfinished_training(tmp_path, cfg) is None


def test_a_folder_holding_four_runs_names_all_four_without_an_ellipsis(tmp_path):
    from hsicam.runs.folder import not_a_run_message

    runs = [tmp_path / "runs" / n for n in ("a", "b", "c", "d")]
    for r in runs:
        r.mkdir(parents=True)
        (r / "config.yaml").write_text("{}\n")
    assert not_a_run_message(tmp_path) == (f"{tmp_path}: not a run folder (config.yaml is missing); it holds the run "
                                           f"folders {', '.join(map(str, runs))}: give one as the run")
    (tmp_path / "runs" / "e").mkdir()
    (tmp_path / "runs" / "e" / "config.yaml").write_text("{}\n")
    assert not_a_run_message(tmp_path).endswith(f"folders {', '.join(map(str, runs))}, …: give one as the run")


def test_a_new_run_in_a_run_folder_with_other_files_is_told_to_resume_or_restart(tmp_path):
    from hsicam.runs.folder import check_run_dir

    (tmp_path / "config.yaml").write_text("{}\n")
    (tmp_path / "notes.txt").write_text("mine\n")
    with pytest.raises(InputError) as exc:
        check_run_dir(tmp_path, resume=False)
    assert str(exc.value) == (f"{tmp_path}: run folder exists and is not empty; use --resume, --restart (a run without "
                              "a checkpoint) or another --out")
    (tmp_path / "config.yaml").unlink()  # no run there: the user's files are named, nothing is offered to wipe them
    with pytest.raises(InputError) as exc:
        check_run_dir(tmp_path, resume=False)
    assert str(exc.value) == (f"{tmp_path}: run folder exists and is not empty: it holds other files than a run's "
                              "(notes.txt); nothing there is resumed or wiped: choose another --out")


def test_restart_wipes_an_unfinished_run_whatever_hidden_files_it_holds(tmp_path):
    from hsicam.runs.folder import restart_run_dir

    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.yaml", "metrics.jsonl", ".DS_Store"):  # a file manager's hidden file is no user's file
        (run / name).write_text("x\n")
    assert restart_run_dir(run) is True
    assert list(run.iterdir()) == []


def test_restart_refuses_a_run_with_a_finished_checkpoint_and_removes_nothing(tmp_path):
    from hsicam.runs.folder import restart_run_dir

    (tmp_path / "config.yaml").write_text("{}\n")
    _manifest(tmp_path, {"global_step": 9, "epoch": 3})
    before = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    with pytest.raises(InputError) as exc:
        restart_run_dir(tmp_path)
    assert str(exc.value) == (f"{tmp_path}: holds a finished checkpoint (step 9); continue it with --resume, or delete "
                              "the folder yourself to start over")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == before


def test_truncating_the_metrics_log_drops_the_final_record_of_the_training_a_resume_continues(tmp_path):
    from hsicam.runs.folder import MetricsLog

    records = [{"step": 3, "epoch": 0, "train_loss": 1.0}, {"step": 6, "epoch": 1, "val_psnr": 20.0},
               {"step": 6, "epoch": 1, "final": True, "elapsed_s": 2.0}, {"step": 6, "epoch": 2, "val_psnr": 21.0}]
    _metrics(tmp_path, records)
    MetricsLog(tmp_path / "metrics.jsonl").truncate_after(step=6, epoch=1)
    lines = (tmp_path / "metrics.jsonl").read_text(encoding="utf-8").splitlines()
    assert [json.loads(x) for x in lines] == records[:2]


def test_no_linear_step_problem_when_the_steps_are_off_even_for_stale_filters(tmp_path):
    from hsicam.config import ConsistencyConfig
    from hsicam.runs.folder import linear_step_problem

    (tmp_path / "model.safetensors").write_bytes(b"weights of the run")
    save_linear_step(tmp_path / "linear_step.safetensors", torch.zeros(1, 2, 3, 3), {"weights_sha256": "f" * 64})
    assert linear_step_problem(tmp_path, ConsistencyConfig(kind="linear", iterations=0, window_px=3)) is None
    why = linear_step_problem(tmp_path, ConsistencyConfig(kind="linear", iterations=1, window_px=3))
    assert why.startswith(f"{tmp_path / 'linear_step.safetensors'} was fitted through other weights (sha256 ffffffffffff…)")
    assert why.endswith("; the run has no checkpoint to refit the filters from: copy the run folder again from its "
                        "source, or train it again")


# ------------------------------------------------------------------------------------------------
# Packing a camera: its card
# ------------------------------------------------------------------------------------------------
def test_training_time_adds_each_sessions_last_time_even_when_a_resume_starts_slower(tmp_path):
    from hsicam.engine.pretrained import training_seconds

    # session 1 killed after its checkpoint at step 10 (5 s); the resume's first log (8 s) is later than that
    _metrics(tmp_path, [{"step": 0, "epoch": 0, "session": {"started_utc": "2025-01-01T00:00:00+00:00"}},
                        {"step": 10, "epoch": 0, "train_loss": 1.0, "elapsed_s": 5.0},
                        {"step": 10, "epoch": 1, "session": {"started_utc": "2025-01-01T01:00:00+00:00"}},
                        {"step": 20, "epoch": 1, "train_loss": 0.9, "elapsed_s": 8.0},
                        {"step": 30, "epoch": 2, "final": True, "elapsed_s": 16.0}])
    assert training_seconds(tmp_path) == 5.0 + 16.0
    # a log from before the session records: a drop in elapsed_s marks the resume
    _metrics(tmp_path, [{"step": 5, "elapsed_s": 3.0}, {"step": 10, "elapsed_s": 6.0}, {"step": 15, "elapsed_s": 2.0},
                        {"step": 20, "final": True, "elapsed_s": 9.0}])
    assert training_seconds(tmp_path) == 6.0 + 9.0
    _metrics(tmp_path, [{"step": 0, "epoch": 0, "session": {}}])
    assert training_seconds(tmp_path) is None


def test_a_run_folder_holding_its_data_record_is_only_a_run_folder(tmp_path):
    from hsicam.runs.folder import restart_run_dir

    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.yaml", "data.json", "metrics.jsonl"):  # a run on a data.root folder, killed before a checkpoint
        (run / name).write_text("{}\n")
    assert restart_run_dir(run) is True
    assert list(run.iterdir()) == []


def test_resuming_a_folder_with_only_hidden_files_says_no_training_was_started_in_it(tmp_path):
    from hsicam.runs.folder import check_run_dir

    (tmp_path / ".DS_Store").write_text("x")
    with pytest.raises(InputError) as exc:
        check_run_dir(tmp_path, resume=True)
    assert str(exc.value) == (f"{tmp_path}: nothing to resume (an empty folder: no training was started in it); start it "
                              f"again with `hsicam train --restart --config CONFIG --out {tmp_path}`")


# ------------------------------------------------------------------------------------------------
# The data record (provenance)
# ------------------------------------------------------------------------------------------------
def _record(scenes: dict[str, tuple[int, int]], train: list[str], root: str = "/data") -> dict:
    return {"root": root, "split": {}, "scenes": [{"path": p, "size": s, "mtime_ns": t} for p, (s, t) in scenes.items()],
            "train": train, "validation": [p for p in scenes if p not in train]}


def test_a_scene_with_only_another_modification_time_is_changed_and_only_warned_about(tmp_path, caplog):
    from hsicam.engine.provenance import check_same_data, data_changes

    was = _record({"a.h5": (10, 1), "b.h5": (20, 2)}, ["a.h5"])
    now = _record({"a.h5": (10, 5), "b.h5": (20, 2)}, ["a.h5"])
    assert data_changes(was, now) == {"added": [], "removed": [], "changed": ["a.h5"], "moved": []}
    with caplog.at_level("WARNING", logger="hsicam.engine.provenance"):
        check_same_data(tmp_path, was, now)  # goes on
    assert [r.getMessage() for r in caplog.records] == [
        "data: 1 scene(s) of /data changed size or time since the run started (a.h5): the resume trains and validates "
        "on them as they are now"]


def test_a_refused_resume_does_not_also_say_it_trains_on_the_changed_scenes(tmp_path, caplog):
    from hsicam.engine.provenance import check_same_data

    was = _record({"a.h5": (10, 1), "b.h5": (20, 2)}, ["a.h5"])
    now = _record({"a.h5": (11, 1), "b.h5": (20, 2), "c.h5": (5, 5)}, ["a.h5", "c.h5"])
    with caplog.at_level("WARNING", logger="hsicam.engine.provenance"), pytest.raises(InputError) as exc:
        check_same_data(tmp_path, was, now)
    assert str(exc.value) == (f"{tmp_path}: the scenes of /data are not those the run started with (its data.json; "
                              "added: c.h5): a resume would train and validate on another split; restore the folder as "
                              "it was, or start a new run with another --out")
    assert caplog.records == []


def test_shown_names_up_to_three_then_how_many_more():
    from hsicam.engine.provenance import shown

    assert shown(["a", "b", "c"]) == "a, b, c"
    assert shown(["a", "b", "c", "d", "e"]) == "a, b, c and 2 more"
    assert shown([]) == ""


def test_synthetic_scenes_of_another_held_out_source_set_are_all_unseen():
    import dataclasses

    from hsicam.config import load_config
    from hsicam.engine.provenance import synthetic_scene_roles

    trained = load_config("tiny").data
    paths = [f"scene_{i:04d}.h5" for i in range(trained.synthetic_n)]
    same = synthetic_scene_roles(trained, trained, paths)
    assert "train" in same  # the run's own cache: its training scenes are told apart
    other = dataclasses.replace(trained, holdout_sources="none")  # other spectra: other cubes under the same names
    assert synthetic_scene_roles(trained, other, paths) == ["unseen"] * len(paths)


def test_results_measured_under_less_noise_than_the_cameras_own_are_refused_for_a_card(tmp_path):
    from hsicam.config import dump_yaml, load_config
    from hsicam.engine.pretrained import check_results_noise

    (tmp_path / "config.yaml").write_text(dump_yaml(load_config("tiny", ["camera.sensor.sigma=0.01"])))
    check_results_noise({"noise": {"sensor_sigma": 0.01}}, Path("results.json"), tmp_path)  # its own noise: fine
    with pytest.raises(InputError) as exc:  # a noiseless evaluation flatters the camera
        check_results_noise({"noise": {"sensor_sigma": 0.0}}, Path("results.json"), tmp_path)
    assert str(exc.value) == ("results.json: measured under test noise --sensor-sigma 0 (the camera's own: 0.01); a "
                              "card's numbers are those of the camera with its own noise: evaluate without it (`hsicam "
                              f"evaluate --run {tmp_path} --out DIR`, no --sensor-sigma) and pass DIR/results.json as "
                              "--results")


@pytest.mark.slow
def test_a_packed_camera_carries_its_runs_linear_step_file_and_its_card_names_its_size_and_sha256(
        tmp_path, cache_env):
    """A run with the linear consistency step packs its filters beside the weights, byte for byte, and the card
    records that file's size and SHA-256 (hashlib over the run's own file here)."""
    import hashlib

    from hsicam.config import load_config
    from hsicam.engine.pretrained import pack_pretrained
    from hsicam.engine.train import train

    run = tmp_path / "linear"
    train(load_config("tiny", ["train.epochs=1", "model.consistency.kind=linear", "model.consistency.iterations=1"]),
          run, progress=False)
    step = (run / "linear_step.safetensors").read_bytes()
    target = pack_pretrained(run, "ls", tmp_path / "root")
    assert (target / "linear_step.safetensors").read_bytes() == step
    card = json.loads((target / "card.json").read_text(encoding="utf-8"))
    assert card["linear_step"] == {"file": "linear_step.safetensors", "bytes": len(step),
                                   "sha256": hashlib.sha256(step).hexdigest()}


def test_a_card_naming_a_linear_step_without_its_sha256_is_a_weights_problem(tmp_path):
    """A card whose "linear_step" entry records no sha256 cannot vouch for the filters: refused like the weights'
    (a card with no "linear_step" entry at all has none to check)."""
    import hashlib

    from hsicam.runs.pretrained import weights_problem

    cam = tmp_path / "cam"
    cam.mkdir()
    (cam / "config.yaml").write_text("{}\n")
    (cam / "model.safetensors").write_bytes(b"w")
    card = {"weights": {"file": "model.safetensors", "sha256": hashlib.sha256(b"w").hexdigest()}}
    (cam / "card.json").write_text(json.dumps(card))
    assert weights_problem(cam) is None
    (cam / "card.json").write_text(json.dumps({**card, "linear_step": {"file": "linear_step.safetensors"}}))
    assert weights_problem(cam) == (
        f"{cam / 'card.json'}: records no sha256 of linear_step.safetensors, so {cam / 'linear_step.safetensors'} "
        f"cannot be checked; re-pack it (`hsicam pretrained pack RUN --name cam --dest {tmp_path} --force`) or "
        "re-install it from where it came")


def _camera(folder: Path, files=("config.yaml", "model.safetensors", "card.json"), weights: bytes = b"w") -> Path:
    """A packed camera's files in ``folder`` (``files`` of them), its card recording the sha256 of ``weights``."""
    import hashlib

    folder.mkdir(parents=True)
    for f in files:
        (folder / f).write_text("{}\n")
    if "model.safetensors" in files:
        (folder / "model.safetensors").write_bytes(b"w")
    if "card.json" in files:
        (folder / "card.json").write_text(json.dumps({"weights": {"sha256": hashlib.sha256(weights).hexdigest()}}))
    return folder


def test_the_cameras_of_a_root_are_its_visible_folders_holding_any_camera_file(tmp_path, monkeypatch):
    """camera_folders lists broken cameras too (one file of three) and no hidden folder; is_camera is a visible
    folder with all three; a path inside the root is a shipped camera's, labelled pretrained:NAME."""
    from hsicam.runs import pretrained as shipped

    monkeypatch.setenv(shipped.ENV_VAR, str(tmp_path))
    _camera(tmp_path / "good")
    _camera(tmp_path / "broken", files=("config.yaml",))
    _camera(tmp_path / ".hidden")
    (tmp_path / "other").mkdir()
    assert shipped.camera_folders() == ["broken", "good"]
    assert [shipped.is_camera(tmp_path / n) for n in ("good", "broken", ".hidden")] == [True, False, False]
    assert shipped.is_pretrained_path(tmp_path / "good" / "model.safetensors")
    assert not shipped.is_pretrained_path(tmp_path.parent)
    assert shipped.run_label(tmp_path / "good") == "pretrained:good"


# ------------------------------------------------------------------------------------------------
# Checkpoints: the manifest's entries, pruning, damaged weights
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("entry, problem", [
    ({"dir": "checkpoints/step-1", "step": True}, "'last.step' is not a step number: True"),
    ({"dir": "checkpoints/../../elsewhere", "step": 1}, "'last.dir' is not a checkpoint folder inside the run: "
                                                       "'checkpoints/../../elsewhere'"),
    ({"dir": "checkpoints/step-1", "step": 0}, None),
])
def test_a_manifest_entry_with_a_boolean_step_or_a_dir_leaving_the_run_is_named(entry, problem):
    from hsicam.runs.checkpoint import _entry_problem

    assert _entry_problem("last", entry) == problem


def test_a_checkpoint_removes_hidden_temporaries_of_killed_writes_and_refuses_damaged_weights(tmp_path):
    from hsicam.runs.checkpoint import CheckpointManager
    from hsicam.spectral import Bands

    bands = Bands.uniform(500, 600, 50)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    mgr = CheckpointManager(tmp_path)
    mgr.save(model, opt, {"global_step": 1}, bands, ("last",))
    killed = mgr.ckpt_dir / ".step-7.tmp123"
    killed.mkdir()
    (killed / "model.safetensors").write_bytes(b"half")
    mgr.save(model, opt, {"global_step": 2}, bands, ("last",))
    assert not killed.exists()
    d = mgr.path("last")
    (d / "model.safetensors").write_bytes((d / "model.safetensors").read_bytes()[:-1] + b" ")
    with pytest.raises(InputError) as exc:
        CheckpointManager(tmp_path).load("last", model, opt, bands)
    assert str(exc.value).startswith(f"{d / 'model.safetensors'} differs from the weights {tmp_path / 'checkpoints.json'} "
                                     "records (sha256 ")


def test_a_metrics_log_saved_on_windows_reads_the_same(tmp_path):
    """metrics.jsonl as a Windows editor saves it: CRLF line ends and Notepad's UTF-8 byte-order mark. The mark made
    the first record unreadable, and it was skipped as torn: the run's starting session record, so the run's generator
    version read as unrecorded (and a resume took the run for one an hsicam before session 60 started)."""
    from hsicam.engine.provenance import trained_generator_version
    from hsicam.runs.folder import MetricsLog

    records = [{"step": 0, "epoch": 0, "session": {"hsicam": None, "synthetic_generator": 3}},
               {"step": 4, "epoch": 1, "train_loss": 0.25, "lr": 0.001}, {"step": 4, "epoch": 1, "final": True}]
    path = tmp_path / "metrics.jsonl"
    path.write_bytes(b"\xef\xbb\xbf" + "".join(json.dumps(r) + "\r\n" for r in records).encode("utf-8"))
    assert MetricsLog(path, enabled=False).read() == records
    assert trained_generator_version(tmp_path) == 3


def test_a_set_of_the_bands_widths_does_not_load_a_trained_run():
    """The weights record the band centres only: `simulate --run RUN --set bands.fwhm_nm=40` on a run trained with
    10 nm bands loaded, and resampled its scene over 40 nm bands (the sensor image 2.9 % off the run's own), where
    `evaluate` refused the key (session 74's spectral audit). The run's own widths, or a --set naming them, load."""
    from hsicam.errors import InputError
    from hsicam.runs.folder import load_run

    cfg, _ = load_run("pretrained:standard")
    own = float(cfg.bands.to_bands().fwhm_nm[0])
    with pytest.raises(InputError, match=r"^--set bands\.fwhm_nm=40: changes the FWHM of the bands .* was trained with "
                                         rf"\({own:g}-{own:g} nm to 40-40 nm\)"):
        load_run("pretrained:standard", overrides=("bands.fwhm_nm=40", "camera.boundary=same"))
    load_run("pretrained:standard", overrides=(f"bands.fwhm_nm={own}", "camera.boundary=same"))


def test_a_run_with_band_samples_from_before_the_gauss_hermite_rule_is_warned_about(tmp_path, caplog):
    """Session 74 changed camera.psf.band_samples from ±FWHM/2 slices to the Gauss–Hermite wavelengths of each band's
    Gaussian: a run trained before it with M > 1 was imaged with 2-3 % other PSFs, without a word (the second review).
    Its first session record names no band_rules: warned about, once; a run recording them, or with M = 1, is not."""
    import json
    import logging
    import shutil

    from hsicam.runs import folder
    from hsicam.runs.folder import load_run
    from hsicam.runs.pretrained import resolve_run
    from hsicam.spectral.bands import BAND_RULES_VERSION

    for name, session, m in (("old", {"torch": "x"}, 3), ("new", {"torch": "x", "band_rules": BAND_RULES_VERSION}, 3),
                             ("old1", {"torch": "x"}, 1)):
        run = shutil.copytree(resolve_run("pretrained:standard"), tmp_path / name)
        (run / "metrics.jsonl").write_text(json.dumps({"step": 0, "epoch": 0, "session": session}) + "\n")
        text = (run / "config.yaml").read_text()
        assert "band_samples: 1" in text
        (run / "config.yaml").write_text(text.replace("band_samples: 1", f"band_samples: {m}"))
    folder._BAND_RULES_WARNED.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.runs.folder"):
        for name in ("old", "old", "new"):
            load_run(tmp_path / name)
        load_run(tmp_path / "old1", overrides=("camera.psf.band_samples=3",))  # trained with M = 1: nothing to say
    said = [r.getMessage() for r in caplog.records if "band_samples" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith(f"{tmp_path / 'old'}: trained with camera.psf.band_samples 3 over slices")
