"""A run keeps the files its camera is built from (a material table, a coded aperture: session 75's hunt): its
config.yaml names them absolute, RUN/camera_files.json records their SHA-256, and loading the run refuses one that
is gone or holds other bytes, naming the key, the run and the path; an older run without the record loads as before,
and a packed camera carries copies of its tables."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_helpers import assert_clean_error, assert_ok, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from hsicam.config import CAMERA_FILES_RECORD, absolute_paths, camera_files, dump_yaml, load_config, preset_names
from hsicam.engine.evaluate import config_hash
from hsicam.runs.camera_files import camera_files_record
from hsicam.runs.folder import load_run
from hsicam.spectral import Bands

SETS = [x for o in (*TINY_CAMERA_OVERRIDES, "train.epochs=1") for x in ("--set", o)]
CASSI_SETS = [x for o in ("bands.start_nm=500", "bands.stop_nm=600", "bands.step_nm=50", "train.epochs=1",
                          "camera.kind=dd_cassi", "model.consistency.kind=landweber") for x in ("--set", o)]
BANDS = Bands.uniform(500, 600, 50)


def _table(path: Path, n400: float, n700: float) -> Path:
    """A two-row ``wavelength_nm,n`` table: n linear from ``n400`` at 400 nm to ``n700`` at 700 nm."""
    path.write_text(f"wavelength_nm,n\n400,{n400}\n700,{n700}\n")
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def proj(tmp_path_factory, cache_env):
    """projA/pmma.csv (n 1.50 → 1.48) and projA/mask.npy; ../run (DOE camera) and ../cassi (DD-CASSI) trained from
    projA with the relative camera.doe.material=pmma.csv and camera.cassi.mask_file=mask.npy; projB holds another
    pmma.csv (n 1.60 → 1.58)."""
    base = tmp_path_factory.mktemp("camfiles")
    (base / "projA").mkdir()
    (base / "projB").mkdir()
    _table(base / "projA" / "pmma.csv", 1.50, 1.48)
    _table(base / "projB" / "pmma.csv", 1.60, 1.58)
    np.save(base / "projA" / "mask.npy", (np.random.default_rng(0).uniform(size=(128, 128)) > 0.5).astype(np.float32))
    with contextlib.chdir(base / "projA"):
        assert_ok(run_cli_in_process("train", "--config", "tiny", *SETS, "--set", "camera.doe.material=pmma.csv",
                                     "--out", "../run"))
        assert_ok(run_cli_in_process("train", "--config", "tiny", *CASSI_SETS, "--set", "camera.cassi.mask_file=mask.npy",
                                     "--out", "../cassi"))
    return base


def _own_copy(proj: Path, tmp_path: Path, run: str = "run", key: str = "camera.doe.material",
              name: str = "pmma.csv") -> tuple[Path, Path]:
    """A copy of the run and of its file (``key``), the copy's config.yaml pointed at the copied file."""
    src = proj / "projA" / name
    own, file = tmp_path / run, tmp_path / "files" / name
    shutil.copytree(proj / run, own)
    file.parent.mkdir()
    shutil.copy2(src, file)
    text = (own / "config.yaml").read_text()
    assert text.count(str(src)) == 1
    (own / "config.yaml").write_text(text.replace(str(src), str(file)))
    return own, file


def _n(model, nm: float = 550.0) -> float:
    """The refractive index the run's DOE is imaged with at ``nm``."""
    return float(model.camera.optics.doe.material.n(nm))


def test_config_names_the_files_absolute_and_the_run_records_their_bytes(proj):
    cfg = yaml.safe_load((proj / "run" / "config.yaml").read_text())
    table = proj / "projA" / "pmma.csv"
    assert cfg["camera"]["doe"]["material"] == str(table)
    assert json.loads((proj / "run" / CAMERA_FILES_RECORD).read_text()) == {
        "files": {"camera.doe.material": {"path": str(table), "sha256": _sha(table)}}}
    mask = proj / "projA" / "mask.npy"
    assert yaml.safe_load((proj / "cassi" / "config.yaml").read_text())["camera"]["cassi"]["mask_file"] == str(mask)
    assert json.loads((proj / "cassi" / CAMERA_FILES_RECORD).read_text()) == {
        "files": {"camera.cassi.mask_file": {"path": str(mask), "sha256": _sha(mask)}}}


def test_a_run_read_from_another_folder_uses_its_own_table(proj, monkeypatch):
    """From projB (its own pmma.csv, n + 0.1), the run is imaged with projA's table: n(550) = 1.49, not 1.59."""
    monkeypatch.chdir(proj / "projB")
    _, model = load_run(proj / "run")
    assert _n(model) == pytest.approx(1.49, abs=1e-12)
    assert_ok(run_cli_in_process("evaluate", "--run", str(proj / "run"), "--out", "ev"))


def test_an_edited_table_is_refused_naming_it(proj, tmp_path):
    """The hunt's edit (n + 0.1 after training) changed export-optics' etch depths under the same hashes."""
    run, table = _own_copy(proj, tmp_path)
    assert_ok(run_cli_in_process("export-optics", "--run", str(run), "--out", str(tmp_path / "ex")))
    _table(table, 1.60, 1.58)
    for args in (("evaluate", "--run", str(run), "--out", str(tmp_path / "ev")),
                 ("export-optics", "--run", str(run), "--out", str(tmp_path / "ex2")),
                 ("train", "--resume", "--out", str(run), "--set", "train.epochs=2")):
        assert_clean_error(run_cli_in_process(*args), f"{run}: camera.doe.material: {table} has changed",
                           "restore it, or train again")
    assert not (tmp_path / "ev").exists() and not (tmp_path / "ex2").exists()


def test_a_deleted_table_is_refused_naming_key_and_run(proj, tmp_path):
    run, table = _own_copy(proj, tmp_path)
    table.unlink()
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--out", str(tmp_path / "ev")),
                       f"{run}: camera.doe.material: {table}: no such file",
                       f"give camera.doe.material its new place in {run / 'config.yaml'} (its SHA-256 is checked)")


def test_an_older_run_without_the_record_loads_as_before(proj, tmp_path):
    """No camera_files.json (a run of an hsicam before it): the table is read as it is now, without a word."""
    run, table = _own_copy(proj, tmp_path)
    (run / CAMERA_FILES_RECORD).unlink()
    _table(table, 1.60, 1.58)
    _, model = load_run(run)
    assert _n(model) == pytest.approx(1.59, abs=1e-12)


def test_an_older_run_naming_a_table_relative_says_which_file_it_reads(proj, tmp_path, caplog, monkeypatch):
    """An older run whose config.yaml names `pmma.csv` relative reads the table of the folder a command runs in (as
    before): said once, with the path it was read from (a resume writes that path into config.yaml; the review)."""
    run, table = _own_copy(proj, tmp_path)
    (run / CAMERA_FILES_RECORD).unlink()
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace(f"material: {table}", "material: pmma.csv"))
    here = tmp_path / "elsewhere"
    here.mkdir()
    _table(here / "pmma.csv", 1.60, 1.58)
    monkeypatch.chdir(here)
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        _, model = load_run(run)
        load_run(run)
    assert _n(model) == pytest.approx(1.59, abs=1e-12)  # this folder's table
    said = [r.getMessage() for r in caplog.records if "relative to where a command runs" in r.getMessage()]
    assert len(said) == 1 and "camera.doe.material=pmma.csv" in said[0] and str(here / "pmma.csv") in said[0], said


def test_a_set_of_another_table_is_a_warning_not_a_refusal(proj, caplog):
    """``--set camera.doe.material=…`` asks for another table by name (a what-if): said, then done."""
    other = proj / "projB" / "pmma.csv"
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        _, model = load_run(proj / "run", overrides=(f"camera.doe.material={other}",))
    assert _n(model) == pytest.approx(1.59, abs=1e-12)
    assert any(f"--set camera.doe.material={other}: not the file" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam"):  # a built-in material asked for: no file, said too
        load_run(proj / "run", overrides=("camera.doe.material=fused_silica",))
    assert any("--set camera.doe.material=fused_silica: not the file" in r.getMessage() for r in caplog.records)


def test_a_cassi_mask_file_is_kept_the_same_way(proj, tmp_path):
    run, mask = _own_copy(proj, tmp_path, "cassi", "camera.cassi.mask_file", "mask.npy")
    _, model = load_run(run)
    np.save(mask, 1.0 - np.load(mask))
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--method", "dd-cassi-rdn", "--out",
                                          str(tmp_path / "ev")), f"{run}: camera.cassi.mask_file: {mask} has changed")
    mask.unlink()
    assert_clean_error(run_cli_in_process("evaluate", "--run", str(run), "--method", "dd-cassi-rdn", "--out",
                                          str(tmp_path / "ev")), f"{run}: camera.cassi.mask_file: {mask}: no such file")


def test_a_packed_camera_carries_its_table(proj, tmp_path, monkeypatch):
    """pack copies the table beside config.yaml, which names it relative to the camera: the camera loads (and its
    copy is a run folder that loads) after the original is gone, read from any folder."""
    from hsicam.engine.pretrained import pack_pretrained
    from hsicam.runs.pretrained import copy_pretrained

    run, table = _own_copy(proj, tmp_path)
    cam = pack_pretrained(run, "mat", tmp_path / "cams")
    copied = yaml.safe_load((cam / "config.yaml").read_text())["camera"]["doe"]["material"]
    assert copied == "camera.doe.material.csv" and (cam / copied).read_bytes() == table.read_bytes()
    assert json.loads((cam / CAMERA_FILES_RECORD).read_text())["files"]["camera.doe.material"]["sha256"] == _sha(table)
    table.unlink()
    monkeypatch.chdir(proj / "projB")
    monkeypatch.setenv("HSICAM_PRETRAINED_DIR", str(tmp_path / "cams"))
    _, model = load_run("pretrained:mat")
    assert _n(model) == pytest.approx(1.49, abs=1e-12)
    _, model = load_run(copy_pretrained("mat", tmp_path / "mine"))
    assert _n(model) == pytest.approx(1.49, abs=1e-12)
    (tmp_path / "mine" / copied).write_text("wavelength_nm,n\n400,1.6\n700,1.58\n")
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(tmp_path / "mine"), "--out", "ex"),
                       f"camera.doe.material: {tmp_path / 'mine' / copied} has changed")


def test_a_packed_camera_whose_table_is_missing_or_changed_is_listed_as_not_usable(proj, tmp_path, monkeypatch):
    """A wheel that shipped a camera without its copied table (package-data without *.csv: session 76's packaging
    hunt): `hsicam pretrained list` showed it healthy, and `--run pretrained:NAME` then told the user to edit a
    config.yaml in site-packages. Now list, show and --run name the missing or changed copy in one line (and say
    to re-pack it, the camera being outside the package)."""
    from hsicam.engine.pretrained import pack_pretrained

    run, _ = _own_copy(proj, tmp_path)
    cams = tmp_path / "cams"
    cam = pack_pretrained(run, "mat", cams)
    monkeypatch.setenv("HSICAM_PRETRAINED_DIR", str(cams))
    copy = cam / "camera.doe.material.csv"
    good = copy.read_bytes()
    remedy = (f"re-pack it (`hsicam pretrained pack RUN --name mat --dest {cams} --force`) or re-install it from "
              "where it came")
    assert run_cli_in_process("pretrained", "list").stdout.startswith("mat: DOE camera with a 3×3 CFA")
    for damage, why in ((copy.unlink, f"{copy}: missing (the camera's camera.doe.material: its camera_files.json "
                                      "records it)"),
                        (lambda: copy.write_text("wavelength_nm,n\n400,1.6\n700,1.58\n"),
                         f"{copy}: does not match its camera_files.json (sha256 ")):
        damage()
        listed = run_cli_in_process("pretrained", "list")
        assert_ok(listed)
        line, *rest = listed.stdout.splitlines()
        assert not rest, rest  # no "use one with --run pretrained:NAME": no usable camera
        assert line.startswith(f"mat: {why}") and line.endswith(f"{remedy}: not usable"), line
        shown = run_cli_in_process("pretrained", "show", "mat")
        assert_ok(shown)
        assert shown.stdout.splitlines()[-1].startswith(f"WARNING: {why}"), shown.stdout
        assert_clean_error(run_cli_in_process("export-optics", "--run", "pretrained:mat", "--out",
                                              str(tmp_path / "ex")), why, remedy)
        assert_clean_error(run_cli_in_process("pretrained", "copy", "mat", str(tmp_path / "mine")), why)
    copy.write_bytes(good)
    assert run_cli_in_process("pretrained", "list").stdout.startswith("mat: DOE camera with a 3×3 CFA")


def test_a_finetuned_run_records_its_source_runs_table(proj, tmp_path):
    from fab_runs import design_psf_dir

    run, table = _own_copy(proj, tmp_path)
    d = design_psf_dir(run, tmp_path / "psf", BANDS)
    ft = tmp_path / "ft"
    assert_ok(run_cli_in_process("finetune", "--run", str(run), "--psf-dir", str(d), "--out", str(ft), "--epochs", "1"))
    assert json.loads((ft / CAMERA_FILES_RECORD).read_text()) == {
        "files": {"camera.doe.material": {"path": str(table), "sha256": _sha(table)}}}
    assert _sha(table) == json.loads((run / CAMERA_FILES_RECORD).read_text())["files"]["camera.doe.material"]["sha256"]
    table.write_text("wavelength_nm,n\n400,1.6\n700,1.58\n")
    assert_clean_error(run_cli_in_process("export-optics", "--run", str(ft), "--out", str(tmp_path / "ex")),
                       f"{ft}: camera.doe.material: {table} has changed")


@pytest.mark.parametrize("preset", preset_names())
def test_presets_name_no_files_and_keep_their_config_hash(preset):
    """Built-in materials and a random mask name no file: nothing is recorded, and the config (the demo's quick
    preset's fused_silica included) and its hash are those it had."""
    cfg = load_config(preset)
    assert absolute_paths(cfg) is cfg
    assert config_hash(dump_yaml(absolute_paths(cfg))) == config_hash(dump_yaml(cfg))
    assert camera_files(cfg) == {} and camera_files_record(cfg) is None


def test_absolute_paths_covers_data_and_camera_files(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    cfg = absolute_paths(load_config("tiny", ["data.root=~/scenes", "data.cache_dir=c", "camera.doe.material=t.csv",
                                              "camera.lens.material=~/l.csv", "camera.cassi.mask_file=m.npy",
                                              "camera.cassi.prism_material=fused_silica"]))
    assert (cfg.data.root, cfg.data.cache_dir) == (str(tmp_path / "scenes"), str(tmp_path / "c"))
    assert (cfg.camera.doe.material, cfg.camera.lens.material, cfg.camera.cassi.mask_file) == (
        str(tmp_path / "t.csv"), str(tmp_path / "l.csv"), str(tmp_path / "m.npy"))
    assert cfg.camera.cassi.prism_material == "fused_silica"
    # the DOE camera reads its DOE's table; the achromatic lens and the CASSI keys are not read
    assert camera_files(cfg) == {"camera.doe.material": str(tmp_path / "t.csv")}


def test_a_windows_path_read_elsewhere_is_named_as_recorded_with_the_way_to_its_new_place(tmp_path):
    """A run trained on Windows names `C:\\...` in its config.yaml: read on Linux it is not joined to the run folder
    (a path nobody wrote: the review), and the refusal says how to give the table its new place."""
    from hsicam.config import _run_relative_files

    data = {"camera": {"doe": {"material": "C:\\Users\\me\\proj\\pmma.csv"}, "lens": {"material": "/abs/pmma.csv"},
                       "cassi": {"prism_material": "fused_silica", "mask_file": "camera.cassi.mask_file.npy"}}}
    _run_relative_files(data, tmp_path)
    assert data["camera"]["doe"]["material"] == "C:\\Users\\me\\proj\\pmma.csv"
    assert data["camera"]["lens"]["material"] == "/abs/pmma.csv"
    assert data["camera"]["cassi"]["mask_file"] == str(tmp_path.absolute() / "camera.cassi.mask_file.npy")


def test_the_config_hash_names_camera_files_by_their_bytes_not_their_place(tmp_path):
    """One camera hashes alike wherever its table sits (a packed camera's copy in another install folder: three
    hashes for one camera before, the review), and apart when the table's bytes differ; a config naming no file
    hashes as its YAML."""
    from hsicam.engine.evaluate import config_hash_of

    for d in "abc":
        (tmp_path / d).mkdir()
    a = _table(tmp_path / "a" / "pmma.csv", 1.50, 1.48)
    b = tmp_path / "b" / "copy.csv"
    shutil.copyfile(a, b)
    c = _table(tmp_path / "c" / "pmma.csv", 1.60, 1.58)
    of = lambda t: config_hash_of(load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"camera.doe.material={t}"]))  # noqa: E731
    assert of(a) == of(b) != of(c)
    plain = load_config("tiny", list(TINY_CAMERA_OVERRIDES))
    assert config_hash_of(plain) == config_hash(dump_yaml(plain))
    # the hash of the bytes, written out: the YAML with the path replaced by "sha256:<hex>"
    data = yaml.safe_load(dump_yaml(load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"camera.doe.material={a}"])))
    data["camera"]["doe"]["material"] = f"sha256:{_sha(a)}"
    assert of(a) == hashlib.sha256(yaml.safe_dump(data, sort_keys=False).encode()).hexdigest()[:12]
