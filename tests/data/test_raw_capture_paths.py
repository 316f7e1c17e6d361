"""Bad paths of raw captures and measured PSFs that used to pass silently or with a misleading line:
``--auto-level`` together with another gain, a white level the file cannot hold or far above the
data, a (nearly) all-saturated capture, an empty ``--psf-dir`` or a file given as one, and the PSFs
of a fine-tuned run's own folder read at another pitch.

The run is real (``hsicam.engine.train``, one epoch on four small scenes with the tiny optics of
conftest); the "fine-tuned" run is a copy of it with the measured PSFs stored the way ``hsicam
finetune`` stores them (no training: only what ``reconstruct`` reads is needed). Captures are
written in their real formats (8/16-bit PNG, ``.npy``)."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from PIL import Image

from cli_helpers import assert_ok, error_line, run_cli_in_process
from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import write_homogeneous_scenes, write_psf_dir
from hsicam.config import load_config
from hsicam.data.images import RawCorrection, read_capture
from hsicam.data.measured_psf import import_for_camera, import_psf_dir
from hsicam.errors import InputError
from hsicam.io import write_json
from hsicam.spectral import Bands


_error, _ok = error_line, assert_ok


@pytest.fixture(scope="module")
def run(tmp_path_factory, cache_env) -> Path:
    """A finished 1-epoch run of the tiny optics (3 bands, 10 µm pixels)."""
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("run")
    data = write_homogeneous_scenes(base / "data", n=4, size=32)
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}", "train.epochs=1"])
    train(cfg, base / "run", progress=False)
    return base / "run"


def _reconstruct(capture: Path, run: Path, out: Path, *extra: str):
    return run_cli_in_process("reconstruct", str(capture), "--run", str(run), "--out", str(out), "--tile", "16",
                   "--consistency-steps", "0", *extra)


def _preprocessing(out: Path) -> dict:
    with h5py.File(out, "r") as f:
        return json.loads(f.attrs["metadata_json"])["preprocessing"]


@pytest.fixture
def png16(tmp_path) -> Path:
    """A 16-bit PNG capture, black level 1000 DN, values up to about 49000 DN."""
    dn = 1000 + np.round(np.random.default_rng(0).random((48, 48)) * 48000)
    path = tmp_path / "cap16.png"
    Image.fromarray(dn.astype(np.uint16)).save(path)
    assert read_capture(path)[1]["stored_dtype"] == "uint16"
    return path


# ------------------------------------------------------------------------------------------------
# 1. --auto-level with another way of setting the level
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("extra, named", [
    (("--exposure-s", "0.01", "--reference-exposure-s", "0.02"), "--exposure-s 0.01 and --reference-exposure-s 0.02"),
    (("--scale", "2"), "--scale 2"),
    (("--exposure-s", "0.01", "--reference-exposure-s", "0.02", "--scale", "2"),
     "--exposure-s 0.01 and --reference-exposure-s 0.02 and --scale 2"),
])
def test_auto_level_with_another_gain_is_refused(run, png16, tmp_path, extra, named):
    line = _error(_reconstruct(png16, run, tmp_path / "c.h5", "--black-level", "1000", "--auto-level", "0.5", *extra))
    assert line == (f"hsicam: error: --auto-level 0.5 sets the level from the image itself and cannot be combined with "
                    f"{named}: choose one way of setting the level: --auto-level alone, or "
                    "--exposure-s/--reference-exposure-s and/or --scale")
    assert not list(tmp_path.glob("c.*")) and not (tmp_path / "c_rgb.png").exists(), "nothing is written"
    with pytest.raises(InputError, match="--auto-level 0.5 sets the level from the image itself"):  # the library too
        RawCorrection(auto_level=0.5, exposure_s=0.01, reference_exposure_s=0.02)
    with pytest.raises(InputError, match="cannot be combined with --scale 2"):
        read_capture(png16, RawCorrection(auto_level=0.5), scale=2.0)


@pytest.mark.parametrize("given, missing", [("exposure_s", "reference_exposure_s"),
                                            ("reference_exposure_s", "exposure_s")])
def test_one_exposure_without_the_other_is_refused_before_the_run_is_read(png16, tmp_path, given, missing):
    """`reconstruct --exposure-s T` without --reference-exposure-s (as docs/hardware.md's synopsis showed it) was
    refused only after the run had been loaded and the frames read, in a line naming neither option; now before
    any work (here the --run folder does not exist), naming both."""
    option = f"--{given.replace('_', '-')}"
    line = _error(_reconstruct(png16, tmp_path / "no-such-run", tmp_path / "c.h5", option, "0.01"))
    assert line == (f"hsicam: error: {given} ({option}) needs {missing} (--{missing.replace('_', '-')}): the exposure "
                    "normalisation multiplies the image by reference/exposure; give both or neither")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap16.png"], "nothing is written"


def test_flat_mode_cfa_without_a_flat_is_refused_before_the_run_is_read(png16, tmp_path):
    """`reconstruct --flat-mode cfa` without --flat was refused only after the run had been loaded; now
    before any work (here the --run folder does not exist)."""
    line = _error(_reconstruct(png16, tmp_path / "no-such-run", tmp_path / "c.h5", "--flat-mode", "cfa"))
    assert line == "hsicam: error: --flat-mode cfa needs --flat (the flat field it averages per CFA phase)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap16.png"], "nothing is written"


def test_the_success_line_names_the_cube_and_its_preview(run, png16, tmp_path):
    res = _reconstruct(png16, run, tmp_path / "a.h5", "--black-level", "1000")
    _ok(res)
    out = res.stdout
    assert f"-> {tmp_path / 'a.h5'} (sRGB preview a_rgb.png, exposed ×" in out and (tmp_path / "a_rgb.png").is_file()


def test_the_metadata_records_only_the_gains_applied(run, png16, tmp_path):
    _ok(_reconstruct(png16, run, tmp_path / "a.h5", "--black-level", "1000", "--auto-level", "0.5"))
    rep = _preprocessing(tmp_path / "a.h5")
    assert rep["auto_level"] == 0.5 and not {"exposure_s", "reference_exposure_s", "scale"} & rep.keys(), rep
    _ok(_reconstruct(png16, run, tmp_path / "e.h5", "--black-level", "1000", "--exposure-s", "0.02",
                     "--reference-exposure-s", "0.01", "--scale", "1.5"))
    rep = _preprocessing(tmp_path / "e.h5")
    assert "auto_level" not in rep and (rep["exposure_s"], rep["reference_exposure_s"], rep["scale"]) == (0.02, 0.01, 1.5)
    assert rep["gain"] == pytest.approx(0.5 * 1.5 / (65535 - 1000))  # what was applied, exactly


# ------------------------------------------------------------------------------------------------
# 2. A white level the file cannot hold, far above the data, or below (nearly) every pixel
# ------------------------------------------------------------------------------------------------
def test_a_white_level_above_the_integer_type_is_refused(run, tmp_path):
    path = tmp_path / "cap8.png"
    Image.fromarray(np.round(np.random.default_rng(1).random((48, 48)) * 200).astype(np.uint8)).save(path)
    brightest = int(np.asarray(Image.open(path)).max())
    line = _error(_reconstruct(path, run, tmp_path / "c.h5", "--white-level", "4095"))
    assert line == (f"hsicam: error: {path}: --white-level 4095 DN is above the largest value its uint8 pixels can "
                    f"hold (255): no pixel can reach it, and the image would stay below 0.0623 of full scale: pass the "
                    f"sensor's white level, at most 255 (the brightest pixel here is {brightest} DN), or leave "
                    "--white-level out for the type's maximum")
    assert not (tmp_path / "c.h5").exists()
    img, rep = read_capture(path, RawCorrection(white_level=255.0))  # the type's maximum itself is fine
    assert rep["white_level_dn"] == 255.0 and float(img.max()) == pytest.approx(brightest / 255)


def test_a_dn_white_level_on_a_float_capture(run, tmp_path, caplog):
    """On the [0, 1] scale already (values within [0, 1]): refused. In DN (a float image of 12-bit data)
    with a white level 16× too high: a warning; with its own white level: nothing."""
    rng = np.random.default_rng(2)
    unit = tmp_path / "unit.npy"
    np.save(unit, (rng.random((48, 48)) * 0.2).astype(np.float32))
    level = float(np.percentile(np.load(unit) / np.float32(255), 99.9))
    line = _error(_reconstruct(unit, run, tmp_path / "c.h5", "--white-level", "255"))
    assert line.startswith(f"hsicam: error: {unit}: --white-level 255 is far above this float capture's values, which "
                           "lie within [0, 1] (brightest "), line
    assert line.endswith(f"divides it down to a 99.9th percentile of {level:.3g} of full scale (refused below 1/16): "
                         "leave --white-level out"), line
    assert not (tmp_path / "c.h5").exists()
    dark = tmp_path / "dark.npy"  # a dark float capture with its own level, 1: read as without the option
    np.save(dark, (rng.random((48, 48)) * 0.03).astype(np.float32))
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        img, _ = read_capture(dark, RawCorrection(white_level=1.0))
    assert not caplog.records and float(img.max()) < 0.03
    dn = tmp_path / "dn.npy"
    np.save(dn, np.round(rng.random((48, 48)) * 4000).astype(np.float32))
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        read_capture(dn, RawCorrection(white_level=65535.0))
    [msg] = [r.getMessage() for r in caplog.records]
    assert msg.startswith(f"{dn}: very dark: with --white-level 65535 the image's 99.9th percentile is ") and \
        "is 65535 this sensor's full scale (4095 for 12 bit" in msg, msg
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        read_capture(dn, RawCorrection(white_level=4095.0))
        read_capture(unit)  # the default white level (1) of a float capture
    assert not caplog.records, caplog.text


def test_a_mostly_saturated_capture_is_refused_and_a_few_saturated_pixels_warn(run, png16, tmp_path, caplog):
    line = _error(_reconstruct(png16, run, tmp_path / "c.h5", "--white-level", "255"))
    raw = np.asarray(Image.open(png16)).astype(np.float64)
    assert line == (f"hsicam: error: {png16}: 2304 of 2304 pixels (100 %) are at or above the white level 255 DN "
                    "(saturated; refused above 50 %): there is nothing but a flat white image to reconstruct: is "
                    f"--white-level 255 the sensor's full scale? (the capture's median is {np.median(raw):g} DN, its "
                    f"brightest pixel {raw.max():g} DN); or the capture is over-exposed: take it again with a shorter "
                    "exposure")
    assert not (tmp_path / "c.h5").exists()
    white = float(np.percentile(raw, 90))  # 10 % of the pixels at or above it: a warning, reconstructed
    n = int(np.count_nonzero(raw >= white))
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(png16, run, tmp_path / "d.h5", "--white-level", f"{white:g}", "--black-level", "1000"))
    [msg] = [r.getMessage() for r in caplog.records if "saturated" in r.getMessage()]
    assert msg == (f"{png16}: {n} pixel(s) at or above the white level {white:g} DN (saturated; "
                   f"{100 * n / raw.size:.2g} % of the pixels, refused above 50 %)")
    assert _preprocessing(tmp_path / "d.h5")["saturated_px"] == n
    white = float(np.percentile(raw, 40))  # 60 %: refused
    assert "pixels (60 %) are at or above" in _error(_reconstruct(png16, run, tmp_path / "e.h5", "--white-level",
                                                                  f"{white:g}"))


# ------------------------------------------------------------------------------------------------
# 3. finetune --psf-dir: an empty folder, a file
# ------------------------------------------------------------------------------------------------
def test_an_empty_psf_folder_and_a_file_are_named_for_what_they_are(run, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    bands = Bands.uniform(500, 600, 50)
    with pytest.raises(InputError, match=r"empty: no PSF images \(\*\.npy"):  # no psf.json: the pitch is not the issue
        import_psf_dir(empty, bands, 10e-6, 9)
    line = _error(run_cli_in_process("finetune", "--run", str(run), "--psf-dir", str(empty), "--out", str(tmp_path / "o")))
    assert line == (f"hsicam: error: {empty}: no PSF images (*.npy, *.png, *.tif named with their wavelength, or "
                    "psf.npy + psf.json)")
    config = run / "config.yaml"
    line = _error(run_cli_in_process("finetune", "--run", str(run), "--psf-dir", str(config), "--out", str(tmp_path / "o")))
    assert line == (f"hsicam: error: {config}: is a file, not a folder: --psf-dir takes the folder that holds the "
                    "measured PSF images (one per band, named with their wavelength, e.g. psf_450nm.tif, or psf.npy + "
                    "psf.json)")
    assert "no such PSF folder" in _error(run_cli_in_process("finetune", "--run", str(run), "--psf-dir", str(tmp_path / "nope"),
                                                  "--out", str(tmp_path / "o")))
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------------------
# 4. reconstruct --psf-dir: the fine-tuned run's own folder, read at another pitch
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tuned(run, tmp_path_factory) -> tuple[Path, Path]:
    """(a run that stores measured PSFs the way ``hsicam finetune`` does, their folder at 10 µm)."""
    import torch

    from hsicam.runs.folder import load_run
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE, save_measured_psf

    base = tmp_path_factory.mktemp("tuned")
    _, model = load_run(run)
    with torch.no_grad():
        psf = model.camera.psf().double().numpy()
    k = psf.shape[-1]
    d = write_psf_dir(base / "psfs", psf, model.bands, 10.0, centre="axis", axis_px=[k // 2, k // 2])
    out = base / "ft"
    shutil.copytree(run, out)
    save_measured_psf(out / MEASURED_PSF_FILE, import_for_camera(d, model.camera))
    write_json(out / "finetune.json", {"source_run": str(run), "psf_dir": str(d)})
    return out, d


def test_the_same_psf_folder_at_another_pitch_names_both_pitches(run, tuned, tmp_path, caplog):
    ft, d = tuned
    cap = tmp_path / "cap.npy"
    np.save(cap, (np.random.default_rng(3).random((48, 48)) * 0.5).astype(np.float32))
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(cap, ft, tmp_path / "a.h5", "--psf-dir", str(d), "--psf-pitch-um", "5"))
    [msg] = [r.getMessage() for r in caplog.records if "fine-tuned" in r.getMessage()]
    assert msg == (f"the PSFs of {d} differ from the ones the network of {ft} was fine-tuned on: the same folder, but "
                   "read at pixel pitch 5 µm (--psf-pitch-um) instead of the 10 µm it was fine-tuned with; reconstruct "
                   f"with --psf-pitch-um 10 if that is the images' pitch, or fine-tune for this one: `hsicam finetune "
                   f"--run {run} --psf-dir {d} --psf-pitch-um 5 --out RUN2` and reconstruct with RUN2")
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # the folder and pitch it was tuned on: no warning
        _ok(_reconstruct(cap, ft, tmp_path / "b.h5", "--psf-dir", str(d), "--psf-pitch-um", "10"))
    assert not [r for r in caplog.records if "fine-tuned" in r.getMessage()], caplog.text
    other = tmp_path / "other"  # another folder, other PSFs: the plain message
    shutil.copytree(d, other)
    np.save(other / "psf.npy", np.load(d / "psf.npy")[:, ::-1].copy())
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(cap, ft, tmp_path / "c.h5", "--psf-dir", str(other)))
    [msg] = [r.getMessage() for r in caplog.records if "fine-tuned" in r.getMessage()]
    assert msg.startswith(f"the network of {ft} was not fine-tuned on the PSFs of {other}; run `hsicam finetune"), msg


# ------------------------------------------------------------------------------------------------
# A capture cropped off the CFA grid: --cfa-offset gives its first pixel's place on the sensor
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mosaic_run(tmp_path_factory, cache_env) -> Path:
    """The run of ``run`` with the mosaic-aware network, which sees each pixel's CFA phase."""
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("mosaic")
    data = write_homogeneous_scenes(base / "data", n=4, size=32)
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}", "train.epochs=1", "model.kind=mosaic",
                               "model.mosaic.features=8", "model.mosaic.blocks=1"])
    train(cfg, base / "run", progress=False)
    return base / "run"


def test_a_crop_off_the_cfa_grid_reconstructs_as_the_whole_capture_given_its_offset(mosaic_run, tmp_path):
    from hsicam.runs.folder import load_run

    run = mosaic_run
    _, model = load_run(run)
    c = int(model.context_px)
    period = int(model.camera.code_period)
    assert period > 1
    whole = (np.random.default_rng(5).random((64 + 2 * c, 64 + 2 * c)) * 0.5).astype(np.float32)
    np.save(tmp_path / "whole.npy", whole)
    dy, dx = 1, period + 2  # off the period in both directions
    np.save(tmp_path / "crop.npy", whole[dy:, dx:])
    _ok(_reconstruct(tmp_path / "whole.npy", run, tmp_path / "whole.h5", "--tile", "512"))
    _ok(_reconstruct(tmp_path / "crop.npy", run, tmp_path / "crop.h5", "--tile", "512", "--cfa-offset", f"{dy},{dx}"))
    _ok(_reconstruct(tmp_path / "crop.npy", run, tmp_path / "crop0.h5", "--tile", "512"))
    read = lambda p: h5py.File(p, "r")["cube"][()]  # noqa: E731
    ref = read(tmp_path / "whole.h5")[:, c + dy : -c, c + dx : -c]  # pixels whose whole context lies in both
    np.testing.assert_allclose(read(tmp_path / "crop.h5")[:, c:-c, c:-c], ref, atol=1e-5)
    assert np.abs(read(tmp_path / "crop0.h5")[:, c:-c, c:-c] - ref).max() > 1e-2  # the phase matters
    with h5py.File(tmp_path / "crop.h5", "r") as f:
        assert json.loads(f.attrs["metadata_json"])["cfa_offset"] == [dy, dx]
    res = _reconstruct(tmp_path / "crop.npy", run, tmp_path / "bad.h5", "--cfa-offset", "1")
    assert res.returncode == 2 and "--cfa-offset" in _error(res), _error(res)


def test_the_psf_warning_names_a_shipped_camera_by_its_pretrained_name():
    """`reconstruct --run pretrained:standard --psf-dir D` resolves the run to its folder inside the package; the
    warning named that folder (meaningless on another machine, and not what the user typed) in the finetune command
    it gives, where every other message says pretrained:standard."""
    import argparse

    from hsicam.cli.reconstruct import psf_mismatch_message
    from hsicam.runs.pretrained import pretrained_dir

    folder = pretrained_dir("standard")
    msg = psf_mismatch_message(argparse.Namespace(run=str(folder), psf_dir="psfs", psf_pitch_um=None), None, False)
    assert "the network of pretrained:standard was not fine-tuned" in msg
    assert "`hsicam finetune --run pretrained:standard --psf-dir psfs --out RUN2`" in msg
    assert str(folder) not in msg


@pytest.mark.parametrize("peak", [1e-6, 1e-30])
def test_a_float_capture_far_below_full_scale_is_warned_about(tmp_path, caplog, peak):
    """A float capture read on the simulator's scale whose 99.9th percentile is below one 8-bit step of full scale was
    reconstructed silently (session 70's hunt: through the shipped camera a constant 1e-30 came back at about 4e-6, the
    network's output being no longer proportional that far below its training levels); it is warned about, naming the level and the options
    that bring it up. Given a gain, only the gain's own message speaks; a capture at 0.01 is not warned about."""
    rng = np.random.default_rng(4)
    values = rng.random((48, 48)).astype(np.float32)
    path = tmp_path / "dim.npy"
    np.save(path, values * np.float32(peak))
    level = float(np.percentile(np.load(path), 99.9))
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        read_capture(path)
    [msg] = [r.getMessage() for r in caplog.records]
    assert msg.startswith(f"{path}: very dark: the float capture's 99.9th percentile is {level:.3g} of the sensor's full "
                          "scale (1; warned below 1/256)"), msg
    assert "--auto-level 0.5" in msg, msg
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        read_capture(path, RawCorrection(auto_level=0.5))  # brought up: no warning
        np.save(tmp_path / "ok.npy", values * np.float32(0.01))
        read_capture(tmp_path / "ok.npy")
    assert not caplog.records, caplog.text
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
        read_capture(path, RawCorrection(scale=2.0))  # a gain that leaves it dark: the gain's message alone
    [msg] = [r.getMessage() for r in caplog.records]
    assert "--scale 2 leaves the image very dark" in msg, msg


def test_a_pixel_wise_flat_taken_through_the_cfa_is_warned_about(caplog):
    """A fabricated camera's CFA is bonded to the sensor, so its flat is taken through it: with a lamp that is not
    white, divided pixel by pixel (the default --flat-mode pixel), it divides each filter's own transmission out of
    the capture (through the demo camera: 27.85 → 20.57 dB, SAM 6.4 → 29°) without a word (session 73's hunt). The
    flat's means over the CFA phases (vignetting and pixel noise average out over the frame) say it; a flat without
    the CFA (vignetting and 1 % pixel noise) and the same flat with flat_period (--flat-mode cfa) are not warned about."""
    import logging

    from hsicam.data.images import RawCorrection, cfa_phase_means, preprocess_raw

    m, h, w, black = 4, 64, 72, 64.0
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    vignette = 1.0 - 0.3 * ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / (h ** 2 + w ** 2)
    tile = rng.uniform(0.4, 2.3, (m, m))
    through = black + 2000.0 * vignette * np.tile(tile, (h // m, w // m))
    bare = black + 2000.0 * vignette * rng.normal(1.0, 0.01, (h, w))
    rel = cfa_phase_means(through, black, m)
    np.testing.assert_allclose(rel / rel.mean(), tile / tile.mean(), rtol=0.02)  # the CFA's pattern, vignetting out
    capture = black + rng.uniform(500, 3000, (h, w))

    def warned(flat, **kw) -> list[str]:
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):
            preprocess_raw(capture, 4095.0, RawCorrection(black_level=black, flat=flat, cfa_period=m, **kw))
        return [r.getMessage() for r in caplog.records if "CFA's" in r.getMessage()]

    said = warned(through)
    assert len(said) == 1 and f"{m}×{m} phases span" in said[0] and "--flat-mode cfa" in said[0], said
    assert warned(bare) == [] and warned(through, flat_period=m) == []
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hsicam.data.images"):  # the CFA period unknown: nothing to check
        preprocess_raw(capture, 4095.0, RawCorrection(black_level=black, flat=through))
    assert "CFA's" not in caplog.text
