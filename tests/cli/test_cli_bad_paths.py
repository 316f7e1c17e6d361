"""Bad paths of the command line that used to pass without a word: a gain far past full scale, a
multi-page TIFF capture, a half-trained run, two cubes sharing a preview, a cube file of a newer
format version, a scene too small for the camera, ``--psf-pitch-um`` without ``--psf-dir``.

The runs are real (``hsicam.engine.train`` on four small scenes, the tiny optics of conftest): one
stopped after 2 of its 12 steps like a killed training, one finished; captures and files are written
in their real formats (``.npy``, multi-page TIFF, our HDF5)."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from conftest import TINY_CAMERA_OVERRIDES
from cli_helpers import assert_clean_error, assert_ok, error_line, run_cli_in_process
from fab_runs import write_homogeneous_scenes
from hsicam.config import load_config
from hsicam.data.formats import HSICAM_FORMAT_VERSION, read_cube, read_window, write_cube_h5
from hsicam.data.images import read_image_2d
from hsicam.errors import InputError
from hsicam.spectral import Bands


_error, _ok = error_line, assert_ok


@pytest.fixture(scope="module")
def runs(tmp_path_factory, cache_env) -> dict[str, Path]:
    """{"half": a run stopped at step 2 of 12 (3 epochs of 4 steps), "done": a finished 1-epoch run}."""
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("runs")
    data = write_homogeneous_scenes(base / "data", n=4, size=32)
    cfg = lambda epochs: load_config("tiny", [*TINY_CAMERA_OVERRIDES, f"data.root={data}",  # noqa: E731
                                              f"train.epochs={epochs}"])
    assert train(cfg(3), base / "half", progress=False, stop_after_steps=2) == {"stopped_at_step": 2}
    assert train(cfg(1), base / "done", progress=False)["step"] == 4
    return {"half": base / "half", "done": base / "done"}


@pytest.fixture
def capture(tmp_path) -> Path:
    """A float capture on the simulator's scale, 48×48, values in [0, 0.5)."""
    path = tmp_path / "cap.npy"
    np.save(path, (np.random.default_rng(0).random((48, 48)) * 0.5).astype(np.float32))
    return path


def _reconstruct(capture: Path, run: Path, out: Path, *extra: str):
    return run_cli_in_process("reconstruct", str(capture), "--run", str(run), "--out", str(out), "--tile", "16", *extra)


# ------------------------------------------------------------------------------------------------
# 1. A gain that pushes the capture far past full scale
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("option, named, fix", [
    (("--scale", "1e6"), "--scale 1e+06", "--scale 2"),  # the capture's 99.9th percentile is ~0.5
    (("--auto-level", "1e10"), "--auto-level 1e+10", "--auto-level 1 or lower"),
    (("--exposure-s", "0.001", "--reference-exposure-s", "1"), "--exposure-s 0.001 (×1e+03)", "check --exposure-s"),
])
def test_a_gain_far_past_full_scale_is_refused(runs, capture, tmp_path, option, named, fix):
    line = _error(_reconstruct(capture, runs["done"], tmp_path / "rec.h5", *option))
    assert capture.name in line and named in line and "far past the sensor's full scale (1)" in line
    gain = {"--scale": 1e6, "--auto-level": None, "--exposure-s": 1e3}[option[0]]
    level = 1e10 if gain is None else float(np.percentile(np.load(capture) * np.float32(gain), 99.9))
    assert f"99.9th percentile is {level:.3g}" in line, line
    assert fix in line, line
    assert not list(tmp_path.glob("rec*")), "nothing is written"


def test_a_gain_that_clips_some_pixels_warns_and_one_within_full_scale_does_not(runs, capture, tmp_path, caplog):
    share = 100 * float(np.mean(np.load(capture) * np.float32(3) > 1))  # ~33 % above full scale
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(capture, runs["done"], tmp_path / "c.h5", "--scale", "3"))
    [msg] = [r.getMessage() for r in caplog.records if "full scale" in r.getMessage()]
    assert msg.startswith(f"{capture}: --scale 3 puts {share:.1f} % of the pixels above the sensor's full scale (1;")
    assert read_cube(tmp_path / "c.h5")[0].shape == (3, 48, 48)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(capture, runs["done"], tmp_path / "d.h5", "--scale", "1.9"))  # peak 0.95
        _ok(_reconstruct(capture, runs["done"], tmp_path / "e.h5", "--auto-level", "1"))  # 0.1 % above 1
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text


def test_a_gain_that_leaves_the_image_very_dark_warns(runs, capture, tmp_path, caplog):
    """A tiny --scale or --auto-level (a typo: 1e-4 for 1) was taken silently (session 37's hunt); it warns
    below one 8-bit step of full scale, with the value that would put the image at half scale."""
    level = float(np.percentile(np.load(capture) * np.float32(1e-4), 99.9))
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(capture, runs["done"], tmp_path / "a.h5", "--scale", "1e-4"))
        _ok(_reconstruct(capture, runs["done"], tmp_path / "b.h5", "--auto-level", "1e-6"))
    msgs = [r.getMessage() for r in caplog.records if "very dark" in r.getMessage()]
    assert len(msgs) == 2, caplog.text
    assert msgs[0].startswith(f"{capture}: --scale 0.0001 leaves the image very dark: its 99.9th percentile is "
                              f"{level:.3g} of the sensor's full scale (1; warned below 1/256)"), msgs[0]
    assert msgs[0].endswith(f"--scale {1e-4 * 0.5 / level:.3g} puts it at 0.5"), msgs[0]
    assert "--auto-level 1e-06 leaves the image very dark" in msgs[1] and msgs[1].endswith("--auto-level 0.5 to 1 is usual")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(capture, runs["done"], tmp_path / "c.h5", "--scale", "0.02"))  # 99.9th percentile ~0.01
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text


# ------------------------------------------------------------------------------------------------
# 2. A multi-page TIFF capture
# ------------------------------------------------------------------------------------------------
def _pages(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [(rng.random((20, 24)) * 60000).astype(np.uint16) for _ in range(n)]


def test_a_multi_page_tiff_capture_is_refused(runs, tmp_path):
    path = tmp_path / "burst.tif"
    with tifffile.TiffWriter(path) as tw:
        for page in _pages(3):
            tw.write(page, photometric="minisblack")
    with tifffile.TiffFile(path) as tf:
        assert len(tf.pages) == 3  # a real multi-page file
    with pytest.raises(InputError, match=r"burst\.tif: multi-page TIFF \(3 pages\); expected one sensor image"):
        read_image_2d(path, "sensor image")
    line = _error(_reconstruct(path, runs["done"], tmp_path / "c.h5"))
    assert "multi-page TIFF (3 pages)" in line and "tifffile.imread(FILE, key=N)" in line
    assert not (tmp_path / "c.h5").exists()


def test_a_single_page_tiff_and_one_with_a_thumbnail_are_read(tmp_path):
    image, thumb = _pages(1)[0], _pages(1, seed=1)[0][::4, ::4]
    tifffile.imwrite(tmp_path / "one.tif", image, photometric="minisblack")
    with tifffile.TiffWriter(tmp_path / "thumb.tif") as tw:
        tw.write(image, photometric="minisblack")
        tw.write(thumb, photometric="minisblack", subfiletype=1)  # a reduced-resolution page
    for name in ("one.tif", "thumb.tif"):
        got = read_image_2d(tmp_path / name, "sensor image")
        np.testing.assert_array_equal(got.data, image.astype(np.float32))
        assert got.full_scale == 65535.0


@pytest.mark.parametrize("dtype, full_scale", [(np.uint16, 65535.0), (np.uint8, 255.0), (np.float32, None)])
def test_an_lzw_tiff_is_read_without_imagecodecs(tmp_path, dtype, full_scale):
    """LZW, the commonest compression of captures, needs tifffile's optional imagecodecs package; without it
    the capture was refused as "corrupt or truncated?". Pillow (written by it here, read back the same) decodes
    it: the same pixels as the uncompressed file."""
    from PIL import Image

    rng = np.random.default_rng(3)
    image = (rng.random((37, 53)) * (1 if dtype == np.float32 else 4000 if dtype == np.uint16 else 250)).astype(dtype)
    Image.fromarray(image).save(tmp_path / "lzw.tif", compression="tiff_lzw")
    with tifffile.TiffFile(tmp_path / "lzw.tif") as tf:
        assert tf.pages[0].compression == 5  # LZW
    tifffile.imwrite(tmp_path / "plain.tif", image, photometric="minisblack")
    got, plain = read_image_2d(tmp_path / "lzw.tif", "sensor image"), read_image_2d(tmp_path / "plain.tif", "sensor image")
    np.testing.assert_array_equal(got.data, plain.data)
    assert got.full_scale == plain.full_scale and (full_scale is None or got.full_scale == full_scale)


def test_a_tiff_neither_reader_decodes_names_its_compression(tmp_path, monkeypatch):
    """When Pillow cannot decode the page either, the refusal says which compression and what to do, not
    "corrupt or truncated?"."""
    from PIL import Image

    Image.fromarray(np.arange(12, dtype=np.uint16).reshape(3, 4)).save(tmp_path / "lzw.tif", compression="tiff_lzw")

    def cannot(*a, **k):
        raise OSError("decoder tiff_lzw not available")

    def without_imagecodecs(*a, **k):  # as tifffile answers where imagecodecs is not installed
        raise ValueError("<COMPRESSION.LZW: 5> requires the 'imagecodecs' package")

    monkeypatch.setattr(tifffile.TiffPage, "asarray", without_imagecodecs)
    monkeypatch.setattr(Image, "open", cannot)
    with pytest.raises(InputError, match=r"lzw.tif: TIFF compressed with LZW.*pip install imagecodecs.*uncompressed") as err:
        read_image_2d(tmp_path / "lzw.tif", "sensor image")
    assert "corrupt" not in str(err.value)


# ------------------------------------------------------------------------------------------------
# 3. A half-trained run
# ------------------------------------------------------------------------------------------------
def _unfinished(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "did not finish" in r.getMessage()]


def test_a_half_trained_run_warns_once_on_reconstruct_and_evaluate(runs, capture, tmp_path, caplog):
    half = runs["half"]
    for args in (("reconstruct", str(capture), "--run", str(half), "--out", str(tmp_path / "c.h5")),
                 ("evaluate", "--run", str(half), "--out", str(tmp_path / "ev"))):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            _ok(run_cli_in_process(*args))
        [msg] = _unfinished(caplog)  # once
        assert msg.startswith(f"{half}: its training did not finish: the last checkpoint is at step 2 of 12 "
                              "(0 of 3 epochs done)"), msg
        assert f"hsicam train --resume --out {half}" in msg
    assert read_cube(tmp_path / "c.h5")[0].shape == (3, 48, 48)


def test_a_half_trained_run_of_an_older_checkpoint_names_its_epochs(runs, tmp_path):
    """Checkpoints written before the loop saved its planned steps: the note names the epochs only."""
    import json
    import shutil

    from hsicam.config import load_config
    from hsicam.runs.folder import unfinished_training

    half = shutil.copytree(runs["half"], tmp_path / "old")
    manifest = json.loads((half / "checkpoints.json").read_text())
    assert manifest["state"].pop("total_steps") == 12  # what the loop planned: 3 epochs of 4 steps
    (half / "checkpoints.json").write_text(json.dumps(manifest))
    msg = unfinished_training(half, load_config(half / "config.yaml"))
    assert msg.startswith(f"{half}: its training did not finish: the last checkpoint is at step 2 (0 of 3 epochs "
                          "done)"), msg


def test_a_finished_run_does_not_warn(runs, capture, tmp_path, caplog):
    """Nor does one killed after its last checkpoint, which holds all its epochs, before the final record."""
    import shutil

    late = shutil.copytree(runs["done"], tmp_path / "late")
    lines = (late / "metrics.jsonl").read_text().splitlines(keepends=True)
    assert '"final": true' in lines[-1]
    (late / "metrics.jsonl").write_text("".join(lines[:-1]))
    with caplog.at_level(logging.WARNING):
        _ok(_reconstruct(capture, runs["done"], tmp_path / "c.h5"))
        _ok(_reconstruct(capture, late, tmp_path / "d.h5"))
    assert not _unfinished(caplog)


# ------------------------------------------------------------------------------------------------
# 4. Two cubes of one name share the preview
# ------------------------------------------------------------------------------------------------
def test_a_second_cube_of_the_same_name_is_refused(runs, capture, tmp_path):
    from PIL import Image

    _ok(_reconstruct(capture, runs["done"], tmp_path / "c.h5"))
    preview = (tmp_path / "c_rgb.png").read_bytes()
    assert Image.open(tmp_path / "c_rgb.png").size == (48, 48)
    line = _error(_reconstruct(capture, runs["done"], tmp_path / "c.hdr", "--scale", "1.5"))
    assert "c.hdr: c.h5 beside it is another cube named c" in line and "preview c_rgb.png" in line
    assert "choose another --out name" in line
    assert (tmp_path / "c_rgb.png").read_bytes() == preview, "the first cube's preview is kept"
    assert not (tmp_path / "c.hdr").exists() and not (tmp_path / "c.img").exists()
    _ok(_reconstruct(capture, runs["done"], tmp_path / "c.h5"))  # the same cube again: its own files
    _ok(_reconstruct(capture, runs["done"], tmp_path / "e.hdr"))  # ENVI first, then HDF5 of that name
    assert read_cube(tmp_path / "e.hdr")[0].shape == (3, 48, 48)
    assert "e.h5: e.hdr beside it" in _error(_reconstruct(capture, runs["done"], tmp_path / "e.h5"))


# ------------------------------------------------------------------------------------------------
# 5. Our HDF5 cube of a newer (or impossible, below 1) format version
# ------------------------------------------------------------------------------------------------
def _cube_file(path: Path, version=None) -> Path:
    cube = np.random.default_rng(1).random((3, 12, 12)).astype(np.float32)
    write_cube_h5(path, cube, Bands.uniform(500, 600, 50))
    if version is not None:
        with h5py.File(path, "a") as f:
            f.attrs["version"] = version
    return path


def _both_readers_refuse(path: Path, expected: str) -> None:
    """read_cube and read_window raise InputError matching the regular expression ``expected``."""
    with pytest.raises(InputError, match=expected):
        read_cube(path)
    with pytest.raises(InputError, match=expected):
        read_window(path, 0, 0, 4, 4)


def test_a_cube_file_of_a_newer_format_version_is_refused(runs, tmp_path):
    newer = _cube_file(tmp_path / "v99.h5", 99)
    _both_readers_refuse(newer, rf"v99\.h5: hsicam cube format version 99, newer than this hsicam reads \(version "
                                rf"{HSICAM_FORMAT_VERSION} and older\): upgrade hsicam")
    line = _error(run_cli_in_process("simulate", "--run", str(runs["done"]), "--scene", str(newer), "--out", str(tmp_path / "sim")))
    assert "format version 99" in line and "upgrade hsicam" in line
    with pytest.raises(InputError, match=r"unreadable hsicam cube format version 'x'"):
        read_cube(_cube_file(tmp_path / "vx.h5", "x"))
    assert read_cube(_cube_file(tmp_path / "v1.h5"))[2]["file_version"] == HSICAM_FORMAT_VERSION
    with h5py.File(tmp_path / "v1.h5", "a") as f:
        del f.attrs["version"]  # files from before the attribute are read
    assert read_cube(tmp_path / "v1.h5")[0].shape == (3, 12, 12)


@pytest.mark.parametrize("version", [0, -3])
def test_a_cube_file_of_a_version_below_one_is_refused(tmp_path, version):
    """No hsicam ever wrote a version below 1 (files from before the attribute have none): refused
    naming the version, by the readers and the command line alike, as a newer version is."""
    path = _cube_file(tmp_path / "old.h5", version)
    _both_readers_refuse(path, rf"^{path}: unknown hsicam cube format version {version} \(versions start at 1; "
                               r"this hsicam reads version 1\): not a file that hsicam wrote, or a damaged one$")
    out = tmp_path / "show"
    res = run_cli_in_process("data", "show", str(path), "--out", str(out))
    assert_clean_error(res, f"{path}: unknown hsicam cube format version {version}")
    assert not out.exists()


def test_a_cube_file_of_version_one_is_still_read_whole_and_windowed(tmp_path):
    cube, bands, meta = read_cube(_cube_file(tmp_path / "v1.h5", 1))
    assert cube.shape == (3, 12, 12) and meta["file_version"] == 1
    assert bands.centers_nm.tolist() == [500.0, 550.0, 600.0]
    window, _ = read_window(tmp_path / "v1.h5", 0, 0, 4, 4)
    np.testing.assert_array_equal(window, cube[:, :4, :4])


# ------------------------------------------------------------------------------------------------
# 6. A scene smaller than the camera needs
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("boundary, side, minimum", [("same", 1, 3), ("same", 2, 3), ("valid", 1, 9), ("valid", 8, 9)])
def test_simulate_refuses_a_scene_smaller_than_the_camera_needs(runs, tmp_path, boundary, side, minimum):
    """The tiny optics: a 3×3 CFA period and a 7-px PSF kernel (valid: the sensor is 6 px smaller)."""
    scene = tmp_path / "scene.npy"
    np.save(scene, np.full((3, side, side), 0.5, np.float32))
    line = _error(run_cli_in_process("simulate", "--run", str(runs["done"]), "--scene", str(scene), "--boundary", boundary,
                          "--out", str(tmp_path / "sim")))
    assert f"scene.npy: the scene is {side}×{side} px, too small: this camera needs {minimum}×{minimum} px" in line
    assert "a sensor image of at least 3×3 px (one CFA period)" in line
    assert ("plus the 6 px per axis that boundary=valid loses to the 7-px PSF kernel" in line) == (boundary == "valid")
    assert not (tmp_path / "sim").exists()
    np.save(scene, np.full((3, minimum, minimum), 0.5, np.float32))  # the minimum itself is imaged
    _ok(run_cli_in_process("simulate", "--run", str(runs["done"]), "--scene", str(scene), "--boundary", boundary,
                "--out", str(tmp_path / "sim")))
    assert np.load(tmp_path / "sim" / "sensor.npy").shape == (3, 3)


# ------------------------------------------------------------------------------------------------
# 7. --psf-pitch-um without --psf-dir
# ------------------------------------------------------------------------------------------------
def test_psf_pitch_without_psf_dir_is_refused(runs, capture, tmp_path):
    line = _error(_reconstruct(capture, runs["done"], tmp_path / "rec.h5", "--psf-pitch-um", "3.45"))
    assert "--psf-pitch-um" in line and "--psf-dir" in line
    assert not list(tmp_path.glob("rec*"))
    # finetune: --psf-dir is required, so its --psf-pitch-um is never ignored
    line = _error(run_cli_in_process("finetune", "--run", str(runs["done"]), "--out", str(tmp_path / "ft"), "--psf-pitch-um", "3.45"))
    assert "--psf-dir" in line
