"""Paths of the command line that the default suite did not execute (coverage audit): each asserts
what a user meets there (the exact warning or one-line error, the cube read back), not only that the
line runs. The runs are real (``hsicam.engine.train``, one epoch of the tiny optics of conftest)."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from cli_helpers import assert_ok, error_line, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import write_homogeneous_scenes, write_psf_dir
from test_cli_bad_paths import capture  # noqa: F401 - shared fixture: a 48×48 float capture
from hsicam.config import load_config
from hsicam.data.formats import read_cube


@pytest.fixture(scope="module")
def runs(tmp_path_factory, cache_env) -> dict[str, Path]:
    """{"plain": the tiny run, "deep": its RDN with 7 blocks (a context of more than 16 px, the smallest
    --tile), "sd": an SD-CASSI run, "sd_linear": one whose config asks for the linear consistency step}, each
    finished after one epoch."""
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("runs")
    data = write_homogeneous_scenes(base / "data", n=2, size=32)
    kinds = {"plain": [], "deep": ["model.rdn.blocks=7"],
             "sd": ["camera.kind=sd_cassi", "model.rdn.backprojection_input=true"],
             "sd_linear": ["camera.kind=sd_cassi", "model.rdn.backprojection_input=true", "model.consistency.iterations=1",
                           "model.consistency.kind=linear"]}
    for name, extra in kinds.items():
        cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}", "train.epochs=1", *extra])
        assert train(cfg, base / name, progress=False)["final"]
    return {name: base / name for name in kinds}


def _reconstruct(capture: Path, run: Path, out: Path, *extra: str):
    return run_cli_in_process("reconstruct", str(capture), "--run", str(run), "--out", str(out), *extra)


# ------------------------------------------------------------------------------------------------
# cli/reconstruct.py
# ------------------------------------------------------------------------------------------------
def _reach_px(run: Path) -> int:
    """How far (px, per side) one sensor pixel reaches into the reconstruction, measured: the farthest
    output pixel that changes when the centre pixel of a 64² image does."""
    from hsicam.runs.folder import load_run

    _, model = load_run(run)
    rec = model.reconstructor()
    x = torch.rand(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
    y = x.clone()
    y[..., 32, 32] += 1.0
    with torch.no_grad():
        changed = (rec(y) - rec(x)).abs().amax(dim=(0, 1)) > 0
    rows, cols = torch.nonzero(changed, as_tuple=True)
    return int(max((rows - 32).abs().max(), (cols - 32).abs().max()))


def test_a_tile_smaller_than_the_context_warns_and_changes_nothing_but_the_time(runs, capture, tmp_path, caplog):
    """--tile 16 on a network whose context is wider than 16 px: the warning (never run before) names
    the context the network declares, which bounds how far a pixel is measured to reach, and the cube is
    the one of a tile past it (the warning is about time only)."""
    from hsicam.runs.folder import load_run

    halo = load_run(runs["deep"])[1].reconstructor().context_px
    assert halo > 16  # else the run would not test the warning
    assert 0 < _reach_px(runs["deep"]) <= halo
    with caplog.at_level(logging.WARNING):
        assert_ok(_reconstruct(capture, runs["deep"], tmp_path / "small.h5", "--tile", "16"))
    [msg] = [r.getMessage() for r in caplog.records if "--tile" in r.getMessage()]
    # the pixels the windows really add up to: counted by a reconstruction that records each window it is given
    # (the warning said (16 + 2·halo)²/16², whatever the image's size)
    import torch

    from hsicam.engine.inference import reconstruct_tiled

    seen = []

    def recording(window, origin=(0, 0)):
        seen.append(window.shape[-2] * window.shape[-1])
        return window.expand(1, 2, *window.shape[-2:])

    reconstruct_tiled(recording, torch.zeros(1, 1, 48, 48), 16, halo)
    assert len(seen) == 9
    assert msg == (f"--tile 16 is smaller than the reconstruction's context ({halo} px per side): the tiles compute "
                   f"about {sum(seen) / 48 ** 2:.0f}× the image's pixels; a tile of {min(2 * halo, 48)} px or more is "
                   "faster")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert_ok(_reconstruct(capture, runs["deep"], tmp_path / "whole.h5", "--tile", "64"))
    assert not [r for r in caplog.records if "--tile" in r.getMessage()], caplog.text
    small, whole = read_cube(tmp_path / "small.h5")[0], read_cube(tmp_path / "whole.h5")[0]
    np.testing.assert_allclose(small, whole, rtol=0, atol=1e-5)


def test_tv_steps_on_an_sd_cassi_run_are_refused_naming_the_camera(runs, capture, tmp_path):
    out = tmp_path / "c.h5"
    res = _reconstruct(capture, runs["sd"], out, "--tile", "16", "--tv-steps", "2")
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        "hsicam: error: --tv-steps: the measurement-consistency steps do not apply to this run's camera "
        "(camera.kind=sd_cassi); drop --tv-steps")
    assert "is skipped" not in res.stderr  # the refusal alone, not a warning that the steps are skipped before it
    assert not list(tmp_path.glob("c.*")) and not list(tmp_path.glob("c_*"))  # nothing written


def test_an_envi_header_without_a_size_is_named_as_such(runs, capture, tmp_path):
    """An earlier reconstruction's header (its description) that no longer gives samples × lines × bands:
    its data file was refused as 'its size (100 bytes) is not the None bytes that o.hdr describes'."""
    from hsicam.data.estimates import ENVI_DESCRIPTIONS

    hdr, img = tmp_path / "o.hdr", tmp_path / "o.img"
    hdr.write_text(f"ENVI\ndescription = {{{ENVI_DESCRIPTIONS[0]}}}\ndata type = 4\nsamples = 48\nbands = 3\n")
    img.write_bytes(b"\0" * 100)
    line = error_line(_reconstruct(capture, runs["plain"], hdr, "--tile", "16"))
    assert line == (f"hsicam: error: {img}: exists and is not the ENVI data of a cube that hsicam reconstruct wrote "
                    "(o.hdr does not describe its size (samples, lines and bands of data type 4)); reconstruct "
                    "replaces only its own earlier output: choose another --out name or move o.img away")
    assert img.read_bytes() == b"\0" * 100


def test_psfs_of_the_same_folder_changed_since_the_fine_tuning_say_so(runs, capture, tmp_path, caplog):
    """The folder a run was fine-tuned on, its images changed since (same pitch, kernel, options): the
    warning says what changed and how to fine-tune again (the 'images' case of psf_difference)."""
    from hsicam.data.measured_psf import import_for_camera
    from hsicam.io import write_json
    from hsicam.runs.folder import load_run
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE, save_measured_psf

    run = runs["plain"]
    _, model = load_run(run)
    with torch.no_grad():
        psf = model.camera.psf().double().numpy()
    k = psf.shape[-1]
    d = write_psf_dir(tmp_path / "psfs", psf, model.bands, 10.0, centre="axis", axis_px=[k // 2, k // 2])
    ft = tmp_path / "ft"
    shutil.copytree(run, ft)
    save_measured_psf(ft / MEASURED_PSF_FILE, import_for_camera(d, model.camera))
    write_json(ft / "finetune.json", {"source_run": str(run), "psf_dir": str(d)})
    stack = np.load(d / "psf.npy")
    np.save(d / "psf.npy", stack[:, ::-1].copy())  # new images, the same folder and psf.json
    with caplog.at_level(logging.WARNING):
        assert_ok(_reconstruct(capture, ft, tmp_path / "c.h5", "--tile", "16", "--consistency-steps", "0",
                               "--psf-dir", str(d)))
    [msg] = [r.getMessage() for r in caplog.records if "fine-tuned" in r.getMessage()]
    assert msg == (f"the PSFs of {d} differ from the ones the network of {ft} was fine-tuned on (the same folder): the "
                   f"PSF images (or psf.json) of the folder changed since it was fine-tuned; fine-tune again: `hsicam "
                   f"finetune --run {run} --psf-dir {d} --out RUN2` and reconstruct with RUN2")


# ------------------------------------------------------------------------------------------------
# cli/__init__.py, cli/args.py, cli/pretrained.py
# ------------------------------------------------------------------------------------------------
def test_an_unfinished_spectral_prior_as_out_is_never_replaced(runs, tmp_path):
    """A `baseline train-prior` folder stopped before its end (config.yaml and prior.yaml, no completion
    marker) given as another command's --out: named as a spectral prior, left as it was."""
    prior = tmp_path / "prior"
    prior.mkdir()
    shutil.copy(runs["plain"] / "config.yaml", prior / "config.yaml")
    (prior / "prior.yaml").write_text("kind: pca\n")
    before = sorted((p.name, p.read_bytes()) for p in prior.iterdir())
    line = error_line(run_cli_in_process("psf", "--config", "tiny", "--out", str(prior)))
    assert line == f"hsicam: error: {prior}: holds a spectral prior, which hsicam psf never replaces; choose another --out"
    assert sorted((p.name, p.read_bytes()) for p in prior.iterdir()) == before


def test_reconstruct_on_a_cuda_index_this_machine_lacks_gives_device_problems_reason(tmp_path):
    from hsicam.devices import device_problem

    problem = device_problem("cuda:99")  # no machine has 100 GPUs: the reason this one gives
    assert problem
    res = run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(tmp_path / "run"),
                             "--out", str(tmp_path / "p.h5"), "--device", "cuda:99")
    assert res.returncode == 2
    assert f"argument --device: device 'cuda:99': {problem}" in res.stderr
    assert "Traceback" not in res.stderr and not list(tmp_path.iterdir())


@pytest.mark.parametrize("metrics", [None, {"validation": {"mean": {"psnr": 30.0}}, "training_log": {"psnr": 1}},
                                     {"training_log": {"psnr": "30", "ssim": 0.9, "sam": 2.0}}])
def test_a_card_without_all_three_scores_lists_none(metrics):
    """`hsicam pretrained` lists a card whose metrics lack one of PSNR, SSIM, SAM (or hold a string) as
    'val –', not a half-filled line or a format error."""
    from hsicam.cli.pretrained import _metrics

    assert _metrics({} if metrics is None else {"metrics": metrics}) == "val –"
    full = {"metrics": {"training_log": {"psnr": 30.0, "ssim": 0.9, "sam": 2.0}}}
    assert _metrics(full) == "its validation patches: PSNR 30.00 dB, SSIM 0.9000, SAM 2.00°"


# ------------------------------------------------------------------------------------------------
# spectral/bands.py, spectral/materials.py
# ------------------------------------------------------------------------------------------------
def test_a_one_sample_grid_gives_each_band_that_sample_whole():
    """band_matrix on a grid of one wavelength: every band (narrower than the grid) reads that sample
    with weight 1; interpolating from one band gives that band to every target inside its range."""
    from hsicam.spectral import Bands
    from hsicam.spectral.bands import band_matrix, interpolation_matrix

    bands = Bands.from_centers([500.0, 550.0], fwhm_nm=1e-3)  # both off the grid: clipped to it
    np.testing.assert_array_equal(band_matrix(bands, np.array([550.0])), np.ones((2, 1)))
    one = Bands.from_centers([550.0], fwhm_nm=10.0)
    np.testing.assert_array_equal(interpolation_matrix(one, one), np.ones((1, 1)))


@pytest.mark.parametrize("wl, n, why", [([500.0], [1.5], "need at least two (wavelength, n) rows of equal length"),
                                        ([500.0, 600.0], [1.5], "need at least two (wavelength, n) rows of equal length"),
                                        ([500.0, 600.0], [1.5, np.nan], "table contains NaN or Inf"),
                                        ([500.0, np.inf], [1.5, 1.4], "table contains NaN or Inf")])
def test_a_refractive_index_table_that_cannot_be_interpolated_is_refused(wl, n, why):
    from hsicam.errors import InputError
    from hsicam.spectral import TabulatedMaterial

    with pytest.raises(InputError) as err:
        TabulatedMaterial(np.array(wl), np.array(n), name="glass")
    assert str(err.value) == f"material 'glass': {why}"


def test_sd_cassi_is_reconstructed_whole_and_its_linear_step_is_skipped_as_reconstruct_skips_it(runs, tmp_path):
    """(A config hunt, session 72.) An SD-CASSI cube is narrower than its sensor image, so it cannot be tiled: a 600 px
    wide capture failed by default (512 px tiles) after its first window, and an explicit small --tile only then;
    the image is now reconstructed whole by default and a small --tile refused before any work. A run whose config
    asks for the linear step (accepted: SD-CASSI skips every step) trained without one and then could not be
    evaluated, advising a refit that fitted nothing."""
    import torch

    from hsicam.engine.inference import reconstruct_tiled
    from hsicam.errors import InputError
    from hsicam.runs.folder import load_run

    _, model = load_run(runs["sd"])
    rec = model.reconstructor()
    assert rec.tileable is False and model.tileable is False and load_run(runs["plain"])[1].tileable is True
    sensor = torch.rand(1, 1, 8, 600, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        whole = reconstruct_tiled(rec, sensor)
        assert torch.equal(whole, rec(sensor)) and whole.shape == (1, len(model.bands), 8, 600 - model.camera.span)
        with pytest.raises(InputError) as exc:
            reconstruct_tiled(rec, sensor, tile_px=64)
    assert str(exc.value) == ("a tile of 64 px: this reconstruction cannot be tiled (its camera's scene grid is not the "
                              "sensor's, e.g. SD-CASSI), so the 8×600 px image is reconstructed whole: drop the tile size "
                              "or give one of at least 600 px")
    np.save(tmp_path / "wide.npy", sensor[0, 0].numpy())  # the command too: whole by default, refused in tiles
    assert_ok(_reconstruct(tmp_path / "wide.npy", runs["sd"], tmp_path / "w.h5"))
    np.testing.assert_allclose(read_cube(tmp_path / "w.h5")[0], whole[0].clamp_min(0).numpy(), rtol=0, atol=1e-6)
    res = _reconstruct(tmp_path / "wide.npy", runs["sd"], tmp_path / "t.h5", "--tile", "64")
    assert error_line(res).endswith("drop the tile size or give one of at least 600 px")
    # and the memory check prices the whole image, which it takes in one window (it priced one 512 px tile's)
    from hsicam.engine.inference import reconstruction_working_bytes

    plain_rec = load_run(runs["plain"])[1].reconstructor()
    assert reconstruction_working_bytes(rec, 7, 2048, 2048) == reconstruction_working_bytes(rec, 7, 2048, 2048, 2048)
    assert reconstruction_working_bytes(plain_rec, 7, 2048, 2048) < reconstruction_working_bytes(rec, 7, 2048, 2048)
    assert not (runs["sd_linear"] / "linear_step.safetensors").exists()
    res = run_cli_in_process("evaluate", "--run", str(runs["sd_linear"]), "--method", "sd-cassi-rdn",
                             "--out", str(tmp_path / "ev"))
    assert_ok(res)
    assert "model.consistency is skipped: SD-CASSI's scene grid is not the sensor's" in res.stderr


def test_a_data_folder_whose_name_is_not_utf8_is_evaluated_and_shown(tmp_path, cache_env):
    """(A real-format dataset hunt, session 72.) A folder named in Latin-1 (Python holds its byte as a lone
    surrogate): evaluate scored every scene, then failed writing results.md (UnicodeEncodeError, exit 1, nothing
    kept), and `data show` failed in matplotlib; both write it with a \\xe9 escape, as scene names already were."""
    import json
    import os

    from hsicam.engine.train import train

    folder = tmp_path / os.fsdecode(b"d\xe9ta")
    write_homogeneous_scenes(folder, n=3, size=32)
    run = tmp_path / "run"
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={folder}", "train.epochs=1"])
    assert train(cfg, run, progress=False)["final"]
    for extra, label in (([], f"validation split of {tmp_path}/d\\xe9ta"), (["--data", str(folder)],
                                                                          f"{tmp_path}/d\\xe9ta")):
        out = tmp_path / f"ev{len(extra)}"
        assert_ok(run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), *extra))
        assert json.loads((out / "results.json").read_text(encoding="utf-8"))["data"] == label
        assert label in (out / "results.md").read_text(encoding="utf-8")
    assert_ok(run_cli_in_process("data", "show", str(folder), "--out", str(tmp_path / "show")))
    assert sorted(p.suffix for p in (tmp_path / "show").iterdir() if not p.name.startswith(".")) == [".png"] * 3
