"""Damaged files inside a run folder: each is refused in one line that names the file, exit code 2,
and nothing in the run is changed (found by feeding commands edited and foreign run files).

- ``checkpoints.json`` whose entries are not what training writes (a ``state`` that is a list, a
  ``dir`` that is a number or leaves the run, a hash that is a number) ended in a TypeError.
- an ``optimizer.safetensors`` of other parameter shapes failed inside Adam's first step (after the
  resume had started); one whose entries are not ``INDEX.NAME`` in a ValueError.
- a weights file whose ``bands`` metadata is not JSON was "unreadable JSON input" without a file;
  integer tensors were cast into the float model silently.
- a ``measured_psf.safetensors`` of another shape ended in the camera's ValueError; one holding NaN
  made ``psf`` fail in matplotlib.
- ``simulate --run`` blamed its own ``--set camera.boundary=same`` for any damaged weights file.
- bands too wide for the synthetic generator's spectra (``--set bands.step_nm=100`` on tiny) ended
  in numpy's LinAlgError.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from cli_helpers import in_process_error_line, tree_snapshot
from hsicam.cli import main
from hsicam.errors import InputError
from hsicam.spectral import Bands


@pytest.fixture(scope="module")
def trained(tmp_path_factory, cache_env):
    """A finished tiny run (1 epoch) and a sensor image of its camera."""
    base = tmp_path_factory.mktemp("trained")
    run = base / "run"
    assert main(["train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=1"]) == 0
    sensor = base / "sensor.npy"
    np.save(sensor, np.random.default_rng(0).uniform(0.1, 0.5, (24, 24)).astype(np.float32))
    return run, sensor


@pytest.fixture
def run(trained, tmp_path):
    """A private copy of the trained run."""
    d = tmp_path / "run"
    shutil.copytree(trained[0], d)
    return d


def edit_manifest(run: Path, fn) -> None:
    man = json.loads((run / "checkpoints.json").read_text())
    fn(man)
    (run / "checkpoints.json").write_text(json.dumps(man))


def rewrite_safetensors(path: Path, fn) -> None:
    """Replace ``path``'s tensors and metadata by ``fn(tensors, meta)``'s."""
    with safe_open(str(path), "pt") as f:
        meta = dict(f.metadata() or {})
    tensors, meta = fn(load_file(str(path)), meta)
    save_file(tensors, str(path), metadata=meta)


def rewrite_all_weights(run: Path, fn) -> None:
    """Apply ``fn`` to the run's root and checkpoint weights and record their new hashes in the
    manifest (an edit the manifest's hash check does not catch: what a user's own tool writes). The
    rewritten files' metadata order is the writer's, so a reader may take either copy."""
    for p in [run / "model.safetensors", *sorted((run / "checkpoints").rglob("model.safetensors"))]:
        rewrite_safetensors(p, fn)

    def rehash(man):
        for key in ("last", "best"):
            if man.get(key):
                p = run / man[key]["dir"] / "model.safetensors"
                man[key]["weights_sha256"] = hashlib.sha256(p.read_bytes()).hexdigest()
        man["weights"]["sha256"] = hashlib.sha256((run / "model.safetensors").read_bytes()).hexdigest()

    edit_manifest(run, rehash)


# ------------------------------------------------------------------------------------------------
# checkpoints.json
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("edit, says", [
    (lambda m: m.__setitem__("state", [1]), "'state' is not a mapping"),
    (lambda m: m["last"].__setitem__("dir", 5), "'last.dir' is not a checkpoint folder inside the run"),
    (lambda m: m["last"].__setitem__("dir", "../../elsewhere"), "'last.dir' is not a checkpoint folder inside the run"),
    (lambda m: m["last"].__setitem__("weights_sha256", 5), "'last.weights_sha256' is not a hash"),
    (lambda m: m["last"].__setitem__("step", "eight"), "'last.step' is not a step number"),
])
@pytest.mark.parametrize("command", ["reconstruct", "resume"])
def test_a_manifest_of_other_entries_is_refused_naming_it(trained, run, tmp_path, capsys, edit, says, command):
    edit_manifest(run, edit)
    before = tree_snapshot(run)
    argv = (["reconstruct", trained[1], "--run", run, "--out", tmp_path / "o.h5"] if command == "reconstruct"
            else ["train", "--out", run, "--resume", "--set", "train.epochs=2"])
    line = in_process_error_line(capsys, argv)
    assert f"{run / 'checkpoints.json'}: corrupt checkpoint manifest" in line and says in line, line
    assert tree_snapshot(run) == before
    assert not (tmp_path / "o.h5").exists()


# ------------------------------------------------------------------------------------------------
# optimizer.safetensors
# ------------------------------------------------------------------------------------------------
def _other_shapes(tensors, meta):
    return {k: torch.zeros(2) for k in tensors}, meta


def _no_index(tensors, meta):
    return {f"x.{k}": v for k, v in tensors.items()}, meta


def _groups_not_dicts(tensors, meta):
    return tensors, {**meta, "param_groups": "[1, 2]", "scalars": "[]"}


@pytest.mark.parametrize("damage, says", [
    (_other_shapes, "has shape (2,), its parameter"),
    (_no_index, "is not PARAM_INDEX.NAME"),
    (_groups_not_dicts, "not an hsicam optimizer state"),
])
def test_resume_refuses_an_optimizer_state_of_another_layout(run, capsys, damage, says):
    opt = run / json.loads((run / "checkpoints.json").read_text())["last"]["dir"] / "optimizer.safetensors"
    rewrite_safetensors(opt, damage)

    def rehash(man):  # an edit the manifest's hash check does not catch: what a user's own tool writes
        for key in ("last", "best"):
            if man.get(key) and run / man[key]["dir"] / "optimizer.safetensors" == opt:
                man[key]["optimizer_sha256"] = hashlib.sha256(opt.read_bytes()).hexdigest()

    edit_manifest(run, rehash)
    before = tree_snapshot(run)
    line = in_process_error_line(capsys, ["train", "--out", run, "--resume", "--set", "train.epochs=2"])
    assert line.startswith(f"hsicam: error: {opt}: ") and says in line, line
    assert tree_snapshot(run) == before


# ------------------------------------------------------------------------------------------------
# model.safetensors
# ------------------------------------------------------------------------------------------------
def test_weights_with_an_unreadable_band_grid_are_refused_naming_the_file(trained, run, tmp_path, capsys):
    rewrite_all_weights(run, lambda t, m: (t, {**m, "bands": "{not json"}))
    line = in_process_error_line(capsys, ["reconstruct", trained[1], "--run", run, "--out", tmp_path / "o.h5"])
    assert line.startswith(f"hsicam: error: {run}/") and "model.safetensors: corrupt band grid" in line, line
    assert not (tmp_path / "o.h5").exists()


@pytest.mark.parametrize("command", ["evaluate", "resume"])
def test_an_emptied_run_config_is_called_damaged_not_a_missing_preset(run, tmp_path, capsys, command):
    """`evaluate --run` and `train --resume` of a run whose config.yaml was emptied advised `--config`'s fix ("give a
    preset (tiny, quick, paper) …"), which these commands do not take."""
    (run / "config.yaml").write_text("# emptied\n")
    args = (["evaluate", "--run", run, "--out", tmp_path / "ev"] if command == "evaluate"
            else ["train", "--out", run, "--resume", "--set", "train.epochs=2"])
    line = in_process_error_line(capsys, args)
    assert "config.yaml is damaged" in line and "restore it from a copy of the run" in line, line
    assert "give a preset" not in line


def test_integer_weights_are_refused_not_cast(trained, run, tmp_path, capsys):
    rewrite_all_weights(run, lambda t, m: ({k: v.to(torch.int16) for k, v in t.items()}, m))
    line = in_process_error_line(capsys, ["reconstruct", trained[1], "--run", run, "--out", tmp_path / "o.h5"])
    assert line.startswith(f"hsicam: error: {run}/") and "model.safetensors: tensor " in line, line
    assert "holds int16 values" in line, line
    assert not (tmp_path / "o.h5").exists()


def test_simulate_blames_the_damaged_weights_not_its_own_boundary_setting(run, tmp_path, capsys, scene):
    rewrite_all_weights(run, lambda t, m: (t, {**m, "bands": "{not json"}))
    line = in_process_error_line(capsys, ["simulate", "--run", run, "--scene", scene, "--out", tmp_path / "sim"])
    assert "camera.boundary" not in line and "corrupt band grid" in line, line
    assert not (tmp_path / "sim").exists()


def test_simulate_still_names_a_set_that_changes_the_trained_network(run, tmp_path, capsys, scene):
    line = in_process_error_line(capsys, ["simulate", "--run", run, "--scene", scene, "--out", tmp_path / "sim",
                               "--set", "model.rdn.features=16"])
    assert "--set" in line and "model.rdn.features=16" in line and "changes what" in line, line


# ------------------------------------------------------------------------------------------------
# measured_psf.safetensors
# ------------------------------------------------------------------------------------------------
def _measured(run: Path, psf: torch.Tensor) -> Path:
    with safe_open(str(run / "model.safetensors"), "pt") as f:
        bands = f.metadata()["bands"]  # the run's own grid: only the stack is wrong
    p = run / "measured_psf.safetensors"
    save_file({"psf": psf}, str(p), metadata={"format": "hsicam-measured-psf-1", "bands": bands, "report": "{}"})
    return p


@pytest.mark.parametrize("psf, says", [
    (torch.rand(21, 21), "the PSF stack is (21, 21), not (7 bands, K, K)"),
    (torch.rand(5, 21, 21), "the PSF stack is (5, 21, 21), not (7 bands, K, K)"),
    (torch.full((7, 21, 21), float("nan")), "NaN/Inf value(s) in the PSF stack"),
])
@pytest.mark.parametrize("command", ["reconstruct", "psf"])
def test_a_measured_psf_file_of_another_shape_or_with_nan_is_refused(trained, run, tmp_path, capsys, psf, says, command):
    p = _measured(run, psf)
    out = tmp_path / ("o.h5" if command == "reconstruct" else "psf")
    argv = (["reconstruct", trained[1], "--run", run, "--out", out] if command == "reconstruct"
            else ["psf", "--run", run, "--out", out])
    line = in_process_error_line(capsys, argv)
    assert line.startswith(f"hsicam: error: {p}: ") and says in line, line
    assert not out.exists()


def test_a_measured_psf_file_with_an_invalid_band_grid_is_named(trained, run, tmp_path, capsys):
    bad = json.dumps({"centers_nm": [-1.0] * 7, "fwhm_nm": [50.0] * 7})
    save_file({"psf": torch.rand(7, 21, 21)}, str(run / "measured_psf.safetensors"),
              metadata={"format": "hsicam-measured-psf-1", "bands": bad})
    line = in_process_error_line(capsys, ["reconstruct", trained[1], "--run", run, "--out", tmp_path / "o.h5"])
    assert line == f"hsicam: error: {run / 'measured_psf.safetensors'}: corrupt measured-PSF metadata", line


# ------------------------------------------------------------------------------------------------
# the synthetic generator and wide bands
# ------------------------------------------------------------------------------------------------
def test_bands_too_wide_for_the_generators_spectra_are_refused():
    pytest.importorskip("colour")
    from hsicam.data.spectral_sources import spectral_library

    with pytest.raises(InputError, match=r"no measured reflectance spectrum spans that range.*bands\.fwhm_nm"):
        spectral_library(Bands.uniform(420, 720, 50, fwhm_nm=100))
