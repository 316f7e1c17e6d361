"""A run on the user's own folder (``data.root``) can be traced to its data (probe 31, findings 01,
02, 05, 06): config.yaml names the folder absolutely, RUN/data.json records the scenes and the
split, a resume refuses a folder that changed, evaluate labels what it scored and flags training
scenes, and a loss made NaN by the data says so."""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from cli_helpers import assert_clean_error, assert_ok, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from hsicam.config import absolute_paths, dump_yaml, load_config
from hsicam.data.formats import write_cube_h5, write_envi
from hsicam.data.pipeline import split_dataset
from hsicam.engine.evaluate import config_hash
from hsicam.engine.provenance import data_record, scene_roles
from hsicam.errors import InputError
from hsicam.spectral import Bands

BANDS = Bands.uniform(500, 600, 50)  # the tiny camera's (TINY_CAMERA_OVERRIDES)
SETS = [x for o in (*TINY_CAMERA_OVERRIDES, "train.epochs=1") for x in ("--set", o)]


def _cube(seed: int, size: int = 40) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.1, 1.0, (3, size, size)).astype(np.float32)


def write_scenes(folder: Path, seed: int = 0) -> Path:
    """6 scenes in real formats: hsicam .h5 files, an ENVI pair, one in a sub-folder."""
    for i in range(4):
        write_cube_h5(folder / f"s{i}.h5", _cube(seed + i), BANDS)
    write_envi(folder / "e4.hdr", _cube(seed + 4), BANDS)
    write_cube_h5(folder / "day1" / "s5.h5", _cube(seed + 5), BANDS)
    return folder


def _config(run: Path):
    return yaml.safe_load((run / "config.yaml").read_text())


@pytest.fixture(scope="module")
def proj(tmp_path_factory, cache_env):
    """projA/data (6 scenes) and ../run trained from projA with the relative data.root=data."""
    base = tmp_path_factory.mktemp("prov")
    write_scenes(base / "projA" / "data")
    with contextlib.chdir(base / "projA"):
        assert_ok(run_cli_in_process("train", "--config", "tiny", *SETS, "--set", "data.root=data",
                          "--set", "data.cache_dir=cache", "--out", "../run"))
    return base


def _copy(proj: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A copy of the run and of its data folder (times kept), the run pointed at the copy."""
    data, run = tmp_path / "data", tmp_path / "run"
    shutil.copytree(proj / "projA" / "data", data)
    shutil.copytree(proj / "run", run)
    return run, data


def _resume(run: Path, data: Path, *extra: str):
    return run_cli_in_process("train", "--out", str(run), "--resume", "--set", f"data.root={data}", "--set", "train.epochs=2",
                   *extra)


def test_a_new_run_stores_absolute_paths_and_its_scenes(proj):
    data = proj / "projA" / "data"
    cfg = _config(proj / "run")["data"]
    assert cfg["root"] == str(data) and cfg["cache_dir"] == str(proj / "projA" / "cache")
    rec = json.loads((proj / "run" / "data.json").read_text())
    assert rec["root"] == str(data)
    assert [e["path"] for e in rec["scenes"]] == ["day1/s5.h5", "e4.hdr", "s0.h5", "s1.h5", "s2.h5", "s3.h5"]
    envi = next(e for e in rec["scenes"] if e["path"] == "e4.hdr")  # the header and its data file
    assert envi["size"] == (data / "e4.hdr").stat().st_size + (data / "e4.img").stat().st_size
    s0 = next(e for e in rec["scenes"] if e["path"] == "s0.h5")
    assert (s0["size"], s0["mtime_ns"]) == ((data / "s0.h5").stat().st_size, (data / "s0.h5").stat().st_mtime_ns)
    train, val = split_dataset(load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}"]).data, BANDS)
    assert rec["train"] == [p.relative_to(data).as_posix() for p in train]
    assert rec["validation"] == [p.relative_to(data).as_posix() for p in val] and len(val) == 2


def test_synthetic_default_keeps_its_config_and_hash(tmp_path, monkeypatch):
    """data.root and data.cache_dir null (the demo): nothing changes, nothing is recorded; `~` expands."""
    cfg = load_config("quick")
    assert absolute_paths(cfg) is cfg
    assert config_hash(dump_yaml(absolute_paths(cfg))) == config_hash(dump_yaml(cfg))
    assert data_record(cfg.data, BANDS) is None
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    got = absolute_paths(load_config("tiny", ["data.root=~/scenes", "data.cache_dir=c"])).data
    assert (got.root, got.cache_dir) == (str(tmp_path / "scenes"), str(tmp_path / "c"))


def test_evaluate_from_another_folder_scores_the_runs_own_validation_scenes(proj, tmp_path, monkeypatch):
    """02 + 06: from projB (its own data/), `evaluate --run` scores projA's validation split and says so."""
    write_scenes(tmp_path / "projB" / "data", seed=50)
    monkeypatch.chdir(tmp_path / "projB")
    assert_ok(run_cli_in_process("evaluate", "--run", str(proj / "run"), "--out", "ev"))
    res = json.loads(Path("ev/results.json").read_text())
    rec = json.loads((proj / "run" / "data.json").read_text())
    assert res["data"] == f"validation split of {proj / 'projA' / 'data'}"
    assert sorted(Path(r["path"]).name for r in res["scenes"]) == sorted(Path(p).name for p in rec["validation"])
    assert {r["split"] for r in res["scenes"]} == {"validation"} and "warning" not in res


def test_evaluate_on_the_training_folder_flags_training_scenes(proj, tmp_path, caplog):
    """06: --data at the run's folder: each row's split, one warning line, in results.csv/md too; a
    copy of the folder elsewhere (times kept) is recognised; another folder's scenes are unseen."""
    run, data = proj / "run", proj / "projA" / "data"
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "ev")))
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    rec = json.loads((run / "data.json").read_text())
    assert {r["path"]: r["split"] for r in res["scenes"]} == {
        **{p: "train" for p in rec["train"]}, **{p: "validation" for p in rec["validation"]}}
    line = f"4 of 6 scenes were training scenes of {run}: their scores are not a validation"
    assert res["warning"] == line and line in (tmp_path / "ev" / "results.md").read_text()
    assert [r.getMessage() for r in caplog.records if "training scenes" in r.getMessage()] == [line]
    rows = list(csv.DictReader((tmp_path / "ev" / "results.csv").open()))
    in_csv = {r["path"]: r["split"] for r in rows if r["name"] != "mean"}
    assert in_csv == {r["path"]: r["split"] for r in res["scenes"]}
    copy = tmp_path / "copy"
    shutil.copytree(data / "day1", copy / "day1")  # part of the folder, copied elsewhere
    shutil.copy2(data / "s0.h5", copy / "s0.h5")
    write_cube_h5(copy / "new.h5", _cube(99), BANDS)
    roles = scene_roles(rec, [copy / "day1" / "s5.h5", copy / "s0.h5", copy / "new.h5"])
    assert roles[2] == "unseen" and roles[:2] == [
        "train" if p in rec["train"] else "validation" for p in ("day1/s5.h5", "s0.h5")]
    other = write_scenes(tmp_path / "other", seed=70)
    assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--data", str(other), "--out", str(tmp_path / "ev2")))
    res2 = json.loads((tmp_path / "ev2" / "results.json").read_text())
    assert {r["split"] for r in res2["scenes"]} == {"unseen"} and "warning" not in res2


def test_evaluate_and_tolerance_score_the_recorded_validation_scenes_of_a_folder_that_changed(proj, tmp_path, caplog):
    """Scenes added to the run's folder after training split it otherwise (here two of the new split are training
    scenes of the run): `evaluate --run` and the tolerance study score the scenes the run validated on, by its
    data.json; a validation scene gone is refused by name; another split asked for (--set) is the config's own."""
    from hsicam.engine.tolerance import evaluation_scenes
    from hsicam.runs.folder import load_run

    run, data = _copy(proj, tmp_path)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace(f"root: {proj / 'projA' / 'data'}", f"root: {data}"))
    rec = json.loads((run / "data.json").read_text())
    for i in range(3):
        write_cube_h5(data / f"a{i}.h5", _cube(60 + i), BANDS)
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}"])
    _, now = split_dataset(cfg.data, BANDS)
    assert sorted(p.relative_to(data).as_posix() for p in now) != sorted(rec["validation"])  # the old code scored these
    with caplog.at_level(logging.INFO, logger="hsicam"):
        assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev")))
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert sorted(r["path"] for r in res["scenes"]) == sorted(rec["validation"])
    assert {r["split"] for r in res["scenes"]} == {"validation"} and "warning" not in res
    assert "would split otherwise" in caplog.text
    cfg_run, _ = load_run(run)
    scenes, names = evaluation_scenes(cfg_run, BANDS, 8, run=run)
    assert sorted(scene_roles(rec, scenes.paths)) == ["validation"] * len(rec["validation"])
    assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--set", "data.val_fraction=0.5",
                                 "--out", str(tmp_path / "ev_half")))  # another split: the config's own, 4 of 9
    assert len(json.loads((tmp_path / "ev_half" / "results.json").read_text())["scenes"]) == 4
    gone = rec["validation"][0]
    (data / gone).unlink()
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev2")),
                       f"1 of the 2 scenes the run validated on (its data.json) are not in {data}: {gone}",
                       "--data DIR")


@pytest.mark.parametrize("change, named", [
    ("add", "added: a_new.h5"), ("remove", "removed: s1.h5"),
    ("split", "not its bands, camera, network, scenes or split: data.val_fraction")])
def test_resume_refuses_a_changed_folder(proj, tmp_path, change, named):
    """01: scenes added or removed, or another split (refused from the config before the scenes are compared):
    one line, the run untouched."""
    run, data = _copy(proj, tmp_path)
    extra = ()
    if change == "add":
        write_cube_h5(data / "a_new.h5", _cube(40), BANDS)
    elif change == "remove":
        (data / "s1.h5").unlink()
    else:
        extra = ("--set", "data.val_fraction=0.5")
    def files():
        return {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and not p.name.startswith(".")}

    before = files()
    res = _resume(run, data, *extra)
    if change == "split":
        assert_clean_error(res, named, "nothing was changed")
    else:
        assert_clean_error(res, f"{run}: the scenes of {data} are not those the run started with", named,
                           "restore the folder as it was, or start a new run with another --out")
    assert files() == before


def test_resume_warns_about_an_edited_scene_and_keeps_the_split(proj, tmp_path, caplog):
    """The same scenes, one rewritten (or the folder copied without its file times): the split does
    not move, so the resume goes on, with a warning naming the scene."""
    import logging

    run, data = _copy(proj, tmp_path)
    write_envi(data / "e4.hdr", _cube(41, size=44), BANDS)
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.provenance"):
        assert_ok(_resume(run, data))
    said = [r.getMessage() for r in caplog.records if "changed size or time" in r.getMessage()]
    assert len(said) == 1 and "e4.hdr" in said[0] and "as they are now" in said[0], caplog.text


def test_resume_goes_on_with_the_same_scenes_and_older_runs_as_before(proj, tmp_path):
    """The folder moved whole (times kept) resumes; a run without data.json (older) resumes as before."""
    run, data = _copy(proj, tmp_path)
    assert_ok(_resume(run, data))
    assert _config(run)["data"]["root"] == str(data) and _config(run)["train"]["epochs"] == 2
    old, _ = _copy(proj, tmp_path / "old")
    (old / "data.json").unlink()
    write_cube_h5(data / "a_new.h5", _cube(40), BANDS)
    assert_ok(_resume(old, data))
    assert not (old / "data.json").exists()


def test_finetune_resume_refuses_a_changed_folder(proj, tmp_path):
    from fab_runs import design_psf_dir

    run, data = _copy(proj, tmp_path)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace(f"root: {proj / 'projA' / 'data'}", f"root: {data}"))
    d = design_psf_dir(run, tmp_path / "psf", BANDS)
    ft = tmp_path / "ft"
    args = ("--run", str(run), "--psf-dir", str(d), "--out", str(ft))
    assert_ok(run_cli_in_process("finetune", *args, "--epochs", "1"))
    assert json.loads((ft / "data.json").read_text())["root"] == str(data)
    (data / "s2.h5").unlink()
    assert_clean_error(run_cli_in_process("finetune", *args, "--resume", "--epochs", "2"), "removed: s2.h5")


def test_a_nan_batch_names_the_data_not_the_learning_rate(proj, tmp_path):
    """05: a loss made NaN by NaN values in the batch (a reader that let them through) names the
    scene files of those patches; a finite batch keeps the divergence message."""
    from hsicam.data.datasets import PatchDataset
    from hsicam.engine.loop import FitOptions, fit, not_finite_error
    from hsicam.engine.tasks import SystemTask
    from hsicam.models import CameraSystem

    class LeakyPatches(PatchDataset):  # as if s3.h5 had been read with its NaN pixels
        def __getitem__(self, k):
            patch = super().__getitem__(k)
            return patch.fill_(float("nan")) if "s3" in str(self.scenes.paths[self._scene(k)]) else patch

        def _scene(self, k):
            return int(np.random.default_rng([self.seed, self.epoch, int(k)]).integers(len(self.scenes)))

    class Task(SystemTask):
        def datasets(self):
            train, val = super().datasets()
            train.__class__ = LeakyPatches
            return train, val

    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={proj / 'projA' / 'data'}",
                               "data.val_fraction=0", "data.patches_per_epoch=32"])
    with pytest.raises(InputError) as err:
        fit(Task(cfg, CameraSystem.from_config(cfg)), FitOptions(cfg.train, 0, progress=False), tmp_path / "run")
    msg = str(err.value)
    assert "NaN/Inf value(s) (patches of " in msg and "s3.h5" in msg and "not the learning rate" in msg, msg
    assert "s0.h5" not in msg and "lower the learning rates" not in msg
    assert str(not_finite_error("training", 7, float("nan"), torch.ones(2, 3, 4, 4))) == \
        "training diverged at step 7 (loss nan); lower the learning rates"


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory, cache_env):
    """A tiny run trained on the synthetic data (no data.json)."""
    run = tmp_path_factory.mktemp("synthetic") / "run"
    # the sources most presets hold out (tiny's own, nist-cqs, is for its 420-720 nm grid of 50 nm bands)
    assert_ok(run_cli_in_process("train", "--config", "tiny", *SETS, "--set", "data.holdout_sources=nist-philips,rawtoaces",
                                 "--out", str(run)))
    return run


def test_evaluate_flags_training_scenes_of_a_synthetic_run_scored_on_another_split(synthetic_run, tmp_path, caplog):
    """A run on the synthetic data has no data.json, so ``evaluate --run RUN --set data.val_fraction=…``
    (or ``split_seed``, ``val_pool``, ``synthetic_n``: keys an evaluation may change) scored a
    "synthetic validation split" that held scenes the network trained on, without a word. The roles are
    now those of the run's own split: checked against the cubes themselves (a scored scene is a
    training scene when its pixels equal those of one of the run's training scenes)."""
    import h5py

    from hsicam.data.pipeline import split_dataset
    from hsicam.engine.provenance import synthetic_scene_roles

    run = synthetic_run
    run_cfg = load_config(run / "config.yaml")
    bands = run_cfg.bands.to_bands()
    wider = load_config(run / "config.yaml", ["data.val_fraction=0.5", "data.synthetic_n=8"])
    train, _ = split_dataset(run_cfg.data, bands)
    _, scored = split_dataset(wider.data, bands)

    def pixels(path):  # the file's cube, read with h5py
        with h5py.File(path, "r") as fh:
            return fh["cube"][()].tobytes()

    trained_on = {pixels(p) for p in train}
    want = ["train" if pixels(p) in trained_on else "not train" for p in scored]
    assert "train" in want and "not train" in want  # the case this test is about
    got = synthetic_scene_roles(run_cfg.data, wider.data, scored)
    assert [r if r == "train" else "not train" for r in got] == want
    held = ",".join(reversed(run_cfg.data.holdout_sources.split(",")))  # the same sources, written otherwise
    reordered = load_config(run / "config.yaml", ["data.val_fraction=0.5", "data.synthetic_n=8", f"data.holdout_sources={held}"])
    assert synthetic_scene_roles(run_cfg.data, reordered.data, scored) == got
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--set", "data.val_fraction=0.5", "--set", "data.synthetic_n=8",
                          "--out", str(tmp_path / "ev")))
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    n = want.count("train")
    assert res["warning"] == f"{n} of {len(want)} scenes were training scenes of {run}: their scores are not a validation"
    assert [r["split"] == "train" for r in res["scenes"]] == [w == "train" for w in want]
    # the run's own split: nothing to flag, the results as before (no split column)
    assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev0")))
    res0 = json.loads((tmp_path / "ev0" / "results.json").read_text())
    assert "warning" not in res0 and all("split" not in r for r in res0["scenes"])
    # what scored is recorded (session 74's records hunt): the --set overrides (config_hash named none of them) and
    # the software; results.md says both
    assert res["overrides"] == ["data.val_fraction=0.5", "data.synthetic_n=8"] and "overrides" not in res0
    assert res0["software"]["threads"] >= 1 and res0["software"]["device"] == "cpu"
    assert {"hsicam", "git_commit", "torch", "numpy", "started_utc"} <= res0["software"].keys()
    # which cached synthetic set was read: its folder and its manifest's hash (config.yaml names neither)
    import hashlib

    folder = Path(res0["synthetic_set"]["folder"])
    assert res0["synthetic_set"]["manifest_sha256"] == hashlib.sha256((folder / "manifest.json").read_bytes()).hexdigest()
    assert all(Path(r["path"]).name in {p.name for p in folder.glob("*.h5")} for r in res0["scenes"])
    md = (tmp_path / "ev" / "results.md").read_text()
    assert "- overrides: ['data.val_fraction=0.5', 'data.synthetic_n=8']" in md and "- software: hsicam " in md


def test_evaluate_says_when_a_data_override_scores_scenes_the_run_never_saw(synthetic_run, tmp_path):
    """``evaluate --run RUN --set data.synthetic_seed=5`` scores another synthetic set (none of it the run's) under the
    label "synthetic validation split" of that run, its rows without a split (session 74's records hunt): the label
    names the keys and says none of the scenes is the run's, each row is "unseen"."""
    from hsicam.engine.evaluate import is_validation_data_label

    assert_ok(run_cli_in_process("evaluate", "--run", str(synthetic_run), "--set", "data.synthetic_seed=5",
                                 "--out", str(tmp_path / "ev")))
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["data"] == "synthetic scenes of data.synthetic_seed=5, none of them the run's"
    assert not is_validation_data_label(res["data"])
    assert {r["split"] for r in res["scenes"]} == {"unseen"}


def test_evaluate_refuses_a_heldout_set_of_sources_the_run_trained_on(synthetic_run, tmp_path):
    """``--set data.holdout_sources=cie-tcs`` on a run that held out nist-philips and rawtoaces built a
    "held-out spectral sources" set (results: "scenes whose reflectances and lights the training scenes
    never contain") from the CIE test samples, which its training scenes were made of. Checked on the
    spectra: every reflectance of that set is one of the run's training library; now refused before
    anything is generated, while a subset of the run's held-out sources is still scored."""
    from hsicam.data.spectral_sources import spectral_library
    from hsicam.engine.provenance import heldout_sources_problem

    run_cfg = load_config(synthetic_run / "config.yaml")
    bands = run_cfg.bands.to_bands()
    trained = spectral_library(bands, run_cfg.data.holdout_sources, "train").reflectances
    asked = spectral_library(bands, "cie-tcs", "heldout").reflectances
    seen = np.abs(asked[:, None, :] - trained[None, :, :]).max(axis=2).min(axis=1) < 1e-9
    assert seen.all()  # not held out: the network trained on every one of these spectra
    wrong = load_config(synthetic_run / "config.yaml", ["data.holdout_sources=cie-tcs"]).data
    assert "cie-tcs" in heldout_sources_problem(run_cfg.data, wrong)
    res = run_cli_in_process("evaluate", "--run", str(synthetic_run), "--set", "data.holdout_sources=cie-tcs",
                  "--out", str(tmp_path / "ev"))
    assert_clean_error(res, "cie-tcs")
    assert not (tmp_path / "ev" / "results.json").exists()
    subset = load_config(synthetic_run / "config.yaml", ["data.holdout_sources=rawtoaces"]).data
    assert heldout_sources_problem(run_cfg.data, subset) is None
    assert heldout_sources_problem(run_cfg.data, run_cfg.data) is None


def test_the_source_checkout_is_told_from_an_installed_package(tmp_path):
    """``source_checkout`` (where `pretrained pack` may write into the package without --dest): the checkout when
    the module lies in its src/hsicam beside a .git (a source tree or an editable install), None for the same module
    in site-packages or in a src/ tree without git. The module is run from copies."""
    import importlib.util

    import hsicam.engine.provenance as real

    def copy_in(folder: Path):
        module = folder / "hsicam" / "engine" / "provenance.py"
        module.parent.mkdir(parents=True)
        shutil.copyfile(real.__file__, module)
        spec = importlib.util.spec_from_file_location(f"provenance_{folder.parent.name}", module)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    checkout = tmp_path / "checkout"
    (checkout / ".git").mkdir(parents=True)
    assert copy_in(checkout / "src").source_checkout() == checkout.resolve()
    assert copy_in(tmp_path / "tree" / "src").source_checkout() is None  # no .git
    wheel = tmp_path / "venv" / "lib" / "python3.11" / "site-packages"
    (tmp_path / "venv" / "lib" / "python3.11" / ".git").mkdir(parents=True)  # a .git where parents[3] would look
    assert copy_in(wheel).source_checkout() is None
    here = Path(__file__).resolve().parents[2]  # the suite runs from its tree's src/ (PYTHONPATH or editable)
    assert real.source_checkout() == (here if (here / ".git").exists() else None)


def test_the_session_records_commit_is_the_checkouts_with_a_hash_of_its_local_changes(tmp_path):
    """``source_state`` names the checkout hsicam runs from: its HEAD, with ``+dirty`` exactly when a file under src/
    differs from it (a tracked file edited, or an untracked file not ignored: a new module runs too; not a tracked
    file elsewhere nor an ignored one), and ``source_diff_sha256``, the hash of those changes: two "+dirty" states of
    one commit with other edits hash apart, the same edits alike; both None without git. The module is run from a
    copy inside a throwaway git checkout, whose state the test sets."""
    import importlib.util
    import subprocess

    import hsicam.engine.provenance as real

    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    root = tmp_path / "checkout"
    module = root / "src" / "hsicam" / "engine" / "provenance.py"
    module.parent.mkdir(parents=True)
    shutil.copyfile(real.__file__, module)
    (root / "README.md").write_text("readme\n")
    (root / ".gitignore").write_text("__pycache__/\n")
    spec = importlib.util.spec_from_file_location("provenance_copy", module)
    copy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(copy)
    assert copy.source_state() == {"git_commit": None, "source_diff_sha256": None}  # no .git: an installed package

    git = lambda *a: subprocess.run(["git", "-C", str(root), *a], capture_output=True, text=True,  # noqa: E731
                                    check=True).stdout.strip()
    git("init", "-q")
    git("add", "-A")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "start")
    head = git("rev-parse", "HEAD")
    assert len(head) == 40
    clean = {"git_commit": head, "source_diff_sha256": None}
    assert copy.source_state() == clean
    (root / "README.md").write_text("edited\n")  # tracked, outside src/
    (root / "src" / "hsicam" / "__pycache__").mkdir()
    (root / "src" / "hsicam" / "__pycache__" / "x.pyc").write_bytes(b"\0")  # ignored
    assert copy.source_state() == clean
    new = root / "src" / "hsicam" / "new.py"
    new.write_text("x = 1\n")  # untracked, not ignored: imported code
    untracked = copy.source_state()
    assert untracked["git_commit"] == head + "+dirty" and len(untracked["source_diff_sha256"]) == 64
    new.write_text("x = 2\n")
    other = copy.source_state()["source_diff_sha256"]
    assert other != untracked["source_diff_sha256"]
    new.unlink()
    original = module.read_text()
    module.write_text(original + "\n# edited\n")  # a tracked source edited
    edited = copy.source_state()
    assert edited["git_commit"] == head + "+dirty"
    module.write_text(original + "\n# edited otherwise\n")
    assert copy.source_state()["source_diff_sha256"] not in (edited["source_diff_sha256"], other, None)
    module.write_text(original + "\n# edited\n")
    assert copy.source_state() == edited  # the same edit, the same hash
    for key, value in (("diff.noprefix", "true"), ("color.ui", "always"), ("diff.context", "1"),
                       ("diff.external", "/bin/false"), ("diff.relative", "true")):  # the user's git settings: no change
        git("config", key, value)
        assert copy.source_state() == edited, key
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-am", "edit")
    assert copy.source_state() == {"git_commit": git("rev-parse", "HEAD"), "source_diff_sha256": None} != clean


def test_records_name_the_version_of_the_code_running_not_of_an_installed_distribution(tmp_path):
    """A checkout run over another installed hsicam (``PYTHONPATH=src`` in a venv holding a wheel) records its own
    ``hsicam.__version__`` in the session / results ``software`` (and the card's ``hsicam_version``, which reads the
    same helper) and in a synthetic set's manifest, not the installed distribution's (session 76's hunt: a 0.1.0
    checkout recorded 0.2.0). The other distribution is a bare .dist-info ahead of src/ on the path."""
    import os
    import subprocess
    import sys

    import hsicam

    other = tmp_path / "site" / "hsicam-9.9.9.dist-info"
    other.mkdir(parents=True)
    (other / "METADATA").write_text("Metadata-Version: 2.1\nName: hsicam\nVersion: 9.9.9\n")
    src = Path(hsicam.__file__).resolve().parents[1]
    code = ("import importlib.metadata as m, hsicam\n"
            "from hsicam.engine.provenance import running_version, software_record\n"
            "from hsicam.data.synthetic import _versions\n"
            "print(m.version('hsicam'), hsicam.__file__, hsicam.__version__, software_record('cpu')['hsicam'],"
            " running_version(), _versions()['hsicam'])")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(src)]), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    installed, where, running, session, card, manifest = out.stdout.split()
    assert installed == "9.9.9" and Path(where).resolve() == src / "hsicam" / "__init__.py"  # the set-up holds
    assert running == hsicam.__version__ != "9.9.9"
    assert session == card == manifest == running


def test_a_hidden_file_in_a_cave_folder_is_not_part_of_its_scene(tmp_path):
    """A file manager's .DS_Store (or ._ AppleDouble files) appearing in a CAVE folder changed the scene's recorded
    size: a resume warned the scene had changed, and a copy of the folder without it was not recognised as the
    run's training scene (scene_roles matched it by size and time). Its band images (and any visible file) count."""
    from PIL import Image

    from hsicam.data.pipeline import scene_files, scene_stat

    cave = tmp_path / "balloons_ms" / "balloons_ms"
    cave.mkdir(parents=True)
    for i in range(1, 4):
        Image.fromarray(np.full((8, 8), i, np.uint16)).save(cave / f"balloons_ms_{i:02d}.png")
    (cave / "balloons_RGB.bmp").write_bytes(b"BM" + bytes(30))
    scene = tmp_path / "balloons_ms"
    before = scene_stat(scene)
    (scene / ".DS_Store").write_bytes(bytes(6148))
    (cave / "._balloons_ms_01.png").write_bytes(bytes(4096))
    (scene / ".thumbs").mkdir()
    (scene / ".thumbs" / "a.png").write_bytes(bytes(100))
    assert scene_stat(scene)[0] == before[0]
    assert [f.name for f in scene_files(scene)] == ["balloons_RGB.bmp", *(f"balloons_ms_{i:02d}.png" for i in range(1, 4))]


def test_validation_scenes_of_one_name_in_two_folders_get_two_names(tmp_path):
    """A data.root folder whose validation scenes are day1/a.h5 and day2/a.h5 named both rows "a" (by stem), and
    evaluate --save then stopped after all its scoring ("a_estimate.h5: written twice"); they are named apart, by
    their folders (the review of session 73)."""
    from hsicam.engine.experiments import validation_scenes

    data = tmp_path / "data"
    for day in range(1, 5):
        write_cube_h5(data / f"day{day}" / "a.h5", _cube(day), BANDS)
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}", "data.val_fraction=0.5"])
    scenes, names = validation_scenes(cfg)
    assert len(names) == 2 and len(set(names)) == 2, names
    assert all(n.endswith("__a") and n.startswith("day") for n in names), names


def test_evaluate_records_the_weights_it_read_and_refuses_weights_changing_under_it(proj, tmp_path, monkeypatch):
    """results.json's weights_sha256 was taken after the scoring: a training writing the run meanwhile recorded a later
    step's hash beside an earlier step's scores (session 73's hunt). It is taken when the weights are read, and
    weights that change while they are read are refused in one line."""
    import hashlib

    import hsicam.cli.evaluate as ev

    run, _ = _copy(proj, tmp_path)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace(f"root: {proj / 'projA' / 'data'}", f"root: {tmp_path / 'data'}"))
    sha = hashlib.sha256((run / "model.safetensors").read_bytes()).hexdigest()
    real = ev._built_method
    calls = []

    def built_then_rewritten(args, cfg, alias):  # a training committing a new checkpoint once the weights are read
        method = real(args, cfg, alias)
        calls.append(1)
        if len(calls) == 2:  # other kept weights, in the root file and the checkpoint the manifest names (a commit)
            new = (run / "model.safetensors").read_bytes() + b" "
            manifest = json.loads((run / "checkpoints.json").read_text())
            entry = manifest[manifest["weights"]["from"]]
            for path in (run / "model.safetensors", run / entry["dir"] / "model.safetensors"):
                path.write_bytes(new)
            entry["weights_sha256"] = manifest["weights"]["sha256"] = hashlib.sha256(new).hexdigest()
            (run / "checkpoints.json").write_text(json.dumps(manifest))
        return method

    monkeypatch.setattr(ev, "_built_method", built_then_rewritten)
    assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev")))
    assert json.loads((tmp_path / "ev" / "results.json").read_text())["weights_sha256"] == sha
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev2")),
                       "its weights changed while they were read")


def test_evaluate_says_which_scored_scenes_changed_since_the_run_trained(proj, tmp_path):
    """A validation scene of a data.root run edited in place after training was scored (25.72 → 27.02 dB in the
    hunt) as the run's validation split, without a word, though data.json records each scene's size and time
    (session 74's records hunt): results.json's warning names it."""
    import os

    run, data = _copy(proj, tmp_path)
    record = json.loads((run / "data.json").read_text())
    record["root"] = str(data)
    (run / "data.json").write_text(json.dumps(record))
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace(f"root: {proj / 'projA' / 'data'}", f"root: {data}"))
    assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "same")))
    assert "warning" not in json.loads((tmp_path / "same" / "results.json").read_text())
    edited = record["validation"][0]
    st = (data / edited).stat()
    os.utime(data / edited, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # rewritten a second later
    assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev")))
    warning = json.loads((tmp_path / "ev" / "results.json").read_text())["warning"]
    assert f"1 scored scene(s) changed since {run} trained (size or modification time not its data.json's): " \
           f"{edited};" in warning
