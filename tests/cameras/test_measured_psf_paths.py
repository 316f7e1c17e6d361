"""Measured-PSF and `hsicam psf` bad paths (probe 21, F3–F5).

* F3: a measured PSF folder whose ``pixel_pitch_um`` is in mm (0.006 for 6 µm) used to collapse to
  a single-pixel PSF, and `finetune` / `reconstruct --psf-dir` went on with it.
* F4: clipped (over-exposed) PSF images were accepted without a word.
* F5: `hsicam psf --config RUN/config.yaml` gave the untrained DOE's PSFs; `psf` had no `--run`.

The "measured" PSFs are the trained tiny camera's own simulated kernels (21×21 px at its 6 µm
pitch), written as images the way a lab would (npy, 8- and 16-bit PNG).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from cli_helpers import assert_clean_error, final_error_line, run_cli_in_process
from hsicam.data.measured_psf import import_for_camera, import_psf_dir
from hsicam.errors import InputError
from hsicam.io import write_json
from hsicam.spectral import Bands

LOGGER = "hsicam.data.measured_psf"




@pytest.fixture(scope="module")
def trained(tmp_path_factory, cache_env):
    """(run folder, its camera, the camera's PSFs (C, K, K) float64) of the tiny preset trained one epoch."""
    from hsicam.config import load_config
    from hsicam.engine.train import train
    from hsicam.runs.folder import load_run

    run = tmp_path_factory.mktemp("psf_paths") / "run"
    train(load_config("tiny", ["train.epochs=1"]), run, progress=False)
    _, model = load_run(run)
    with torch.no_grad():
        psf = model.camera.psf().double().numpy()
    return run, model.camera, psf


def band_images(d: Path, images, bands, pitch_um: float, suffix: str = ".npy") -> Path:
    """One image per band (``psf_<nm>nm<suffix>``: .npy as given, .png with the array's integer type)."""
    d.mkdir(parents=True)
    for img, lam in zip(images, bands.centers_nm):
        f = d / f"psf_{lam:g}nm{suffix}"
        np.save(f, img) if suffix == ".npy" else iio.imwrite(f, img)
    write_json(d / "psf.json", {"pixel_pitch_um": pitch_um})
    return d


def exposed(psf: np.ndarray, level: float, factor: float, dtype) -> np.ndarray:
    """The PSFs as integer images exposed so each band's peak would reach ``factor`` × ``level``,
    clipped at ``level`` (a sensor's maximum)."""
    img = np.round(psf / psf.max(axis=(1, 2), keepdims=True) * level * factor)
    return np.clip(img, 0, level).astype(dtype)


# ------------------------------------------------------------------------------------------------
# F3: a pitch in the wrong unit
# ------------------------------------------------------------------------------------------------
def test_a_pitch_written_in_mm_is_refused(trained, tmp_path):
    run, cam, psf = trained
    d = band_images(tmp_path / "mm", psf, cam.bands, 0.006)
    with pytest.raises(InputError) as exc:
        import_for_camera(d, cam)
    msg = str(exc.value)
    assert msg.startswith(f"{d}/psf_420nm.npy (420 nm): at pixel_pitch_um 0.006 the 21×21 px image spans 0.126 µm, "
                          "0.021 of one 6 µm camera pixel, so the camera's PSF would be a single pixel"), msg
    assert "wrong unit (0.006 mm would be 6 µm)" in msg and f"(pixel_pitch_um in {d}/psf.json)" in msg, msg
    with pytest.raises(InputError, match=r"0\.006 mm would be 6 µm\): give the images' pixel pitch in µm \(--psf-pitch-um\)"):
        import_for_camera(d, cam, pitch_um=0.006)
    # the same images with the pitch in µm are the camera's PSFs again
    m = import_for_camera(d, cam, pitch_um=6.0)
    np.testing.assert_allclose(m.psf, psf / psf.sum(axis=(1, 2), keepdims=True), atol=1e-6)


def test_a_large_frame_with_a_pitch_in_mm_is_refused_by_the_diffraction_limit(trained, tmp_path):
    """A 1100 px frame at 0.006 spans 1.1 camera pixels (more than one): the light of the PSF then
    lies within far less than the aperture's diffraction limit, which no PSF of it can do."""
    run, cam, psf = trained
    d = tmp_path / "big"
    d.mkdir()
    k, n = psf.shape[-1], 1100
    stack = np.zeros((len(cam.bands), n, n), np.float32)
    stack[:, n // 2 - k // 2: n // 2 + k // 2 + 1, n // 2 - k // 2: n // 2 + k // 2 + 1] = psf
    np.save(d / "psf.npy", stack)
    write_json(d / "psf.json", {"pixel_pitch_um": 0.006, "bands_nm": cam.bands.centers_nm.tolist()})
    f_number = cam.optics.sensor_distance_m / (2 * cam.optics.aperture_radius_m)
    with pytest.raises(InputError, match=rf"psf\.npy \(420 nm\): at pixel_pitch_um 0\.006 half of the image's light lies "
                                         rf"within .* µm of its centre, .*× less than the smallest spot the camera's "
                                         rf"f/{f_number:.3g} aperture can form at 420 nm .*the diffraction limit\); the "
                                         r"1100×1100 px image spans 1\.1 camera pixels and its PSF would put 100% of its "
                                         r"light in one pixel; the pitch looks like it is in the wrong unit"):
        import_for_camera(d, cam)
    write_json(d / "psf.json", {"pixel_pitch_um": 6.0, "bands_nm": cam.bands.centers_nm.tolist()})
    assert import_for_camera(d, cam).psf.shape == psf.shape  # in µm: accepted


def test_finetune_and_reconstruct_refuse_a_pitch_in_mm(trained, tmp_path):
    run, cam, psf = trained
    d = band_images(tmp_path / "mm", psf, cam.bands, 0.006)
    out = tmp_path / "ft"
    res = run_cli_in_process("finetune", "--run", str(run), "--psf-dir", str(d), "--out", str(out), "--epochs", "1")
    assert_clean_error(res, "psf_420nm.npy (420 nm): at pixel_pitch_um 0.006", "0.021 of one 6 µm camera pixel",
                       "0.006 mm would be 6 µm")
    assert not out.exists()
    cap = tmp_path / "cap.npy"
    np.save(cap, np.random.default_rng(3).random((64, 64)).astype(np.float32))
    res = run_cli_in_process("reconstruct", str(cap), "--run", str(run), "--psf-dir", str(d), "--out", str(tmp_path / "c.h5"))
    assert_clean_error(res, "psf_420nm.npy (420 nm): at pixel_pitch_um 0.006", "0.006 mm would be 6 µm")
    assert not (tmp_path / "c.h5").exists()


# ------------------------------------------------------------------------------------------------
# F4: clipped PSF images
# ------------------------------------------------------------------------------------------------
def test_clipped_psf_images_are_warned_about_once_per_file(trained, tmp_path, caplog):
    from hsicam.data.measured_psf import SATURATED_MIN_PX

    run, cam, psf = trained
    img = exposed(psf, 255, 2.0, np.uint8)  # each peak exposed to twice the 8-bit maximum
    counts = (img == 255).sum(axis=(1, 2))
    clipped = [f"psf_{lam:g}nm.png" for lam, n in zip(cam.bands.centers_nm, counts) if n >= SATURATED_MIN_PX]
    assert 0 < len(clipped) < len(counts), counts  # some bands clipped, others only touch full scale
    d = band_images(tmp_path / "sat8", img, cam.bands, 6.0, ".png")
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        m = import_for_camera(d, cam)
    msgs = [r.getMessage() for r in caplog.records if "clipped" in r.getMessage()]
    assert len(msgs) == len(clipped), msgs
    for name, msg in zip(clipped, msgs):
        n = int(counts[[f"psf_{lam:g}nm.png" for lam in cam.bands.centers_nm].index(name)])
        assert msg.startswith(f"{d / name} ("), msg
        assert f"a clipped (over-exposed) PSF image: {n} of its 441 pixels are at 255 (the file type's maximum)" in msg
        assert "measure it again with a shorter exposure" in msg
    assert [b["saturated_px"] for b in m.report["bands"]] == counts.tolist()

    # a 12-bit sensor in a 16-bit file clips at 4095
    d12 = band_images(tmp_path / "sat12", exposed(psf, 4095, 2.0, np.uint16), cam.bands, 6.0, ".png")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        import_for_camera(d12, cam)
    msgs = [r.getMessage() for r in caplog.records if "clipped" in r.getMessage()]
    assert len(msgs) == len(clipped) and all("are at 4095 (a 12-bit sensor's maximum)" in x for x in msgs), msgs

    # an image scaled to its own maximum has one pixel at full scale: not a clipped PSF
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        import_for_camera(band_images(tmp_path / "scaled", exposed(psf, 255, 1.0, np.uint8), cam.bands, 6.0, ".png"), cam)
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def test_heavily_clipped_psf_images_are_refused(trained, tmp_path):
    from hsicam.data.measured_psf import MAX_CLIPPED_LIGHT_SHARE

    run, cam, psf = trained
    img = exposed(psf, 255, 8.0, np.uint8)  # the probe's over-exposure: peaks at 8× the 8-bit maximum
    share = np.array([float(im[im == 255].sum()) / im.sum() for im in img.astype(np.float64)])
    first = int(np.argmax(share > MAX_CLIPPED_LIGHT_SHARE))
    assert share[first] > MAX_CLIPPED_LIGHT_SHARE, share
    lam, n = cam.bands.centers_nm[first], int((img[first] == 255).sum())
    d = band_images(tmp_path / "sat", img, cam.bands, 6.0, ".png")
    with pytest.raises(InputError, match=rf"psf_{lam:g}nm\.png \({lam:g} nm\): a clipped \(over-exposed\) PSF image: {n} of "
                                         rf"its 441 pixels are at 255 \(the file type's maximum\), holding "
                                         rf"{share[first]:.0%} of its light, more than the 50% allowed; .*measure it "
                                         r"again with a shorter exposure \(brightest pixel below 255\)"):
        import_for_camera(d, cam)
    out = tmp_path / "ft"
    res = run_cli_in_process("finetune", "--run", str(run), "--psf-dir", str(d), "--out", str(out), "--epochs", "1")
    # after the warnings about the bands clipped within the allowance, as the user sees them
    assert f"psf_{lam:g}nm.png ({lam:g} nm): a clipped (over-exposed) PSF image: {n} of its 441 pixels" in final_error_line(res)
    assert not out.exists()


# ------------------------------------------------------------------------------------------------
# F5: `hsicam psf --run`
# ------------------------------------------------------------------------------------------------
def test_psf_of_a_trained_run_and_of_a_pretrained_camera(trained, tmp_path, monkeypatch):
    from hsicam.engine.pretrained import pack_pretrained
    from hsicam.runs import pretrained as shipped

    run, cam, psf = trained
    res = run_cli_in_process("psf", "--run", str(run), "--out", str(tmp_path / "trained"))
    assert res.returncode == 0, res.stderr
    assert f"PSF stack ({run}'s trained camera): 7 bands, 21×21 px" in res.stdout
    got = np.load(tmp_path / "trained" / "psf.npy")
    np.testing.assert_allclose(got, psf, rtol=0, atol=1e-7)
    meta = json.loads((tmp_path / "trained" / "psf.json").read_text())
    assert meta["source"] == {"run": str(run.resolve()), "optics": "the run's trained DOE (model.safetensors)"}
    res = run_cli_in_process("psf", "--config", "tiny", "--out", str(tmp_path / "design"))
    assert res.returncode == 0 and "(the config's camera, DOE as initialised)" in res.stdout, res.stderr
    assert np.abs(np.load(tmp_path / "design" / "psf.npy") - got).max() > 1e-3  # training moved the DOE
    assert json.loads((tmp_path / "design" / "psf.json").read_text())["source"]["config"] == "tiny"

    root = tmp_path / "root"
    pack_pretrained(run, "cam", root)
    monkeypatch.setenv(shipped.ENV_VAR, str(root))
    res = run_cli_in_process("psf", "--run", "pretrained:cam", "--out", str(tmp_path / "pre"))
    assert res.returncode == 0, res.stderr
    np.testing.assert_array_equal(np.load(tmp_path / "pre" / "psf.npy"), got)
    # a shipped camera is named as the user gave it, not by its package folder (export-optics' spec.json does the same)
    assert json.loads((tmp_path / "pre" / "psf.json").read_text())["source"]["run"] == "pretrained:cam"


def test_psf_and_simulate_refuse_a_runs_config_yaml(trained, tmp_path):
    run, cam, psf = trained
    out = tmp_path / "p"
    res = run_cli_in_process("psf", "--config", str(run / "config.yaml"), "--out", str(out))
    assert_clean_error(res, f"--config {run}/config.yaml: the config.yaml of the trained run {run}, whose DOE heights are in "
                            f"{run}/model.safetensors", f"use `hsicam psf --run {run} --out DIR` for the trained camera")
    scene = tmp_path / "scene.npy"
    np.save(scene, np.random.default_rng(0).random((len(cam.bands), 48, 48)).astype(np.float32))
    res = run_cli_in_process("simulate", "--config", str(run / "config.yaml"), "--scene", str(scene), "--out", str(out))
    assert_clean_error(res, f"use `hsicam simulate --run {run} --scene FILE --out DIR`")
    assert_clean_error(run_cli_in_process("psf", "--run", str(run), "--config", "tiny", "--out", str(out)), "drop --config")
    assert not out.exists()


def test_psf_of_a_finetuned_run_is_its_measured_psfs(trained, tmp_path):
    from hsicam.engine.calibration import finetune
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE, load_measured_psf

    run, cam, psf = trained
    measured = np.roll(psf, 1, axis=-1)  # a built camera whose PSFs sit one pixel off the design
    d = band_images(tmp_path / "m", measured, cam.bands, 6.0)
    ft = tmp_path / "ft"
    finetune(run, d, ft, overrides=("train.epochs=1",), progress=False)
    res = run_cli_in_process("psf", "--run", str(ft), "--out", str(tmp_path / "p"))
    assert res.returncode == 0, res.stderr
    assert f"PSF stack ({ft}'s measured PSFs)" in res.stdout
    np.testing.assert_array_equal(np.load(tmp_path / "p" / "psf.npy"), load_measured_psf(ft / MEASURED_PSF_FILE).psf)
    assert json.loads((tmp_path / "p" / "psf.json").read_text())["source"]["optics"] == \
        "the run's measured PSFs (fine-tuned run)"


# ------------------------------------------------------------------------------------------------
# Probe 26 #3: a stack's bands_nm that are not wavelengths
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad, said", [
    (float("nan"), "bands_nm must hold wavelengths in nm (finite, > 0), got nan"),
    (-470.0, "bands_nm must hold wavelengths in nm (finite, > 0), got -470.0"),
    (10**400, f"bands_nm must hold wavelengths in nm (finite, > 0), got {10**400!r}"),  # no float holds it
    ("twice", "bands_nm names 420 nm more than once (one PSF per wavelength)"),
])
def test_a_stack_whose_bands_are_not_wavelengths_is_named_as_such(trained, tmp_path, bad, said):
    """A NaN wavelength used to be reported as a pixel pitch in the wrong unit, a repeated one as a
    missing band."""
    run, cam, psf = trained
    d = tmp_path / "stack"
    d.mkdir()
    np.save(d / "psf.npy", psf.astype(np.float32))
    bands = [float(v) for v in cam.bands.centers_nm]
    bands[1] = bands[0] if bad == "twice" else bad
    (d / "psf.json").write_text(json.dumps({"bands_nm": bands, "pixel_pitch_um": 6.0}))  # NaN as JSON's NaN
    with pytest.raises(InputError) as exc:
        import_for_camera(d, cam)
    assert str(exc.value) == f"{d / 'psf.json'}: {said}"
    bands[1] = float(cam.bands.centers_nm[1])  # the same stack with its wavelengths is the camera's PSFs
    (d / "psf.json").write_text(json.dumps({"bands_nm": bands, "pixel_pitch_um": 6.0}))
    m = import_for_camera(d, cam)
    np.testing.assert_allclose(m.psf, psf / psf.sum(axis=(1, 2), keepdims=True), atol=1e-6)


def test_a_doe_of_more_cells_than_the_memory_holds_is_refused_before_its_heights_are_drawn(monkeypatch):
    """A cell size in the wrong unit (0.05 µm across the tiny 1.2 mm aperture: 24 001 cells a side)
    drew a 4.6 GB height map before any memory check, and ended in an allocator traceback; now the
    cell count is checked first (24 bytes a cell against the budget), naming both keys."""
    import hsicam.cameras.doe_camera as doe_camera
    from hsicam.cameras import build_camera
    from hsicam.config import load_config
    from hsicam.errors import ConfigError

    def no_draw(*a, **k):
        raise AssertionError("the DOE's heights were allocated before the memory check")

    monkeypatch.setattr(doe_camera, "DOE", no_draw)
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "1024")
    cfg = load_config("tiny", ["camera.doe.cell_size_um=0.05"])
    with pytest.raises(ConfigError, match=r"^camera.doe.cell_size_um=0.05 across the 1.2 mm aperture \(2 × "
                                          r"camera.aperture_radius_mm\) is a DOE of 24,001×24,001 cells, whose heights "
                                          r"alone need 12.9 GiB, more than the memory budget of 1 GiB"):
        build_camera(cfg)
    # 24 bytes a cell: 6 700 cells a side (1.0035 GiB) is over a 1 GiB budget, 6 600 (0.97 GiB) within it
    for n, over in ((6700, True), (6600, False)):
        if over:
            with pytest.raises(ConfigError, match=f"{n:,}×{n:,} cells"):
                doe_camera.check_doe_memory(n, 1.0, 3.3)
        else:
            doe_camera.check_doe_memory(n, 1.0, 3.3)
    # a DOE switched off keeps a float32 grid of zeros: 4 bytes a cell (24 001² is 2.1 GiB)
    with pytest.raises(ConfigError, match="24,001×24,001 cells, whose heights alone need 2.15 GiB"):
        doe_camera.check_doe_memory(24001, 0.05, 0.6, enabled=False)
    doe_camera.check_doe_memory(16000, 0.05, 0.4, enabled=False)  # 0.95 GiB


@pytest.mark.parametrize("period, said", [
    ("100000", "camera.cfa.period=100000 is a CFA tile of 100,000×100,000 px whose 7 filter weights per pixel need "
               "1.02 TiB, more than the memory budget of 1 GiB"),
    ("99999999999999999999999", "camera.cfa.period=99999999999999999999999 is a CFA tile of"),
])
def test_a_cfa_period_whose_weights_exceed_the_memory_is_refused_in_one_line(tmp_path, monkeypatch, period, said):
    """`hsicam psf --set camera.cfa.period=100000` asked torch for the 280 GB of its random weights (a
    RuntimeError traceback of the allocator); a period beyond int64 failed in torch's argument parsing
    (a TypeError traceback). Now the CFA's weights are checked against the memory budget first."""
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "1024")
    res = run_cli_in_process("psf", "--config", "tiny", "--set", f"camera.cfa.period={period}", "--out", str(tmp_path / "psf"))
    assert_clean_error(res, said, "HSICAM_MEMORY_BUDGET_MB")
    assert not (tmp_path / "psf").exists()


def test_a_cfa_period_within_the_memory_is_built():
    import hsicam.cameras.doe_camera as doe_camera

    doe_camera.check_cfa_memory(15, 31)
    doe_camera.check_cfa_memory(10**12, 31, enabled=False)  # no CFA: κ = 1, no weights


ONE_BAND = Bands(np.array([500.0]), np.array([10.0]))


def _spot(size: int = 31) -> np.ndarray:
    img = np.zeros((size, size))
    img[size // 2, size // 2] = 1.0
    img[size // 2 - 1:size // 2 + 2, size // 2 - 1:size // 2 + 2] += 0.1
    return img


def _psf_dir(d: Path, meta, files: dict[str, np.ndarray | bytes]) -> Path:
    d.mkdir()
    if meta is not None:
        (d / "psf.json").write_text(meta if isinstance(meta, str) else json.dumps(meta))
    for name, arr in files.items():
        if isinstance(arr, bytes):  # a file of these bytes (not an array)
            (d / name).write_bytes(arr)
        else:
            np.save(d / name, arr)
    return d


# --- data/measured_psf.py: every refusal of a PSF folder is one clear line naming what is wrong -----------------

STACK = np.stack([_spot()] * 2)


@pytest.mark.parametrize("meta, files, text", [
    ("[1, 2]", {"psf_500nm.npy": _spot()}, "{d}/psf.json: must be a JSON object"),
    ({"axis_px": [1]}, {"psf_500nm.npy": _spot()}, "{d}/psf.json: axis_px must be [row, col], got [1]"),
    ({"wavelength_tolerance_nm": "x"}, {"psf_500nm.npy": _spot()}, "{d}/psf.json: wavelength_tolerance_nm must be a number"),
    # JSON booleans are no numbers (Python counts them as ints: [true, false] was read as the axis (1, 0))
    ({"axis_px": [True, False]}, {"psf_500nm.npy": _spot()}, "{d}/psf.json: axis_px must be [row, col], got [True, False]"),
    ({"wavelength_tolerance_nm": True}, {"psf_500nm.npy": _spot()}, "{d}/psf.json: wavelength_tolerance_nm must be a number"),
    ({"bands_nm": "abc"}, {"psf.npy": STACK}, "{d}/psf.json: bands_nm must be a list of numbers"),
    ({"bands_nm": [500, 510, 520]}, {"psf.npy": STACK},
     "{d}/psf.npy: expected a (C, H, W) stack with C = 3 (bands_nm), got shape (2, 31, 31)"),
    ({"bands_nm": [500, 510]}, {"psf.npy": STACK > 0}, "{d}/psf.npy: unsupported data type bool"),
    ({"bands_nm": [500, 510]}, {"psf.npy": np.zeros((2, 0, 5))}, "{d}/psf.npy: unusable PSF stack shape (2, 0, 5)"),
    (None, {"psf.npy": STACK}, "{d}/psf.npy: a PSF stack needs its wavelengths: bands_nm in {d}/psf.json, which is missing"),
    # what `hsicam psf` writes beside the stack (files named with no wavelength) is not blamed for a missing psf.json
    (None, {"psf.npy": STACK, "aperture.npy": _spot()},
     "{d}/psf.npy: a PSF stack needs its wavelengths: bands_nm in {d}/psf.json, which is missing"),
    ({}, {"psf.npy": STACK, "aperture.npy": _spot()},
     "{d}/psf.npy: a PSF stack needs its wavelengths: bands_nm in {d}/psf.json"),
    # a stack that is no .npy: said so, not numpy's "pickled data … allow_pickle" advice
    ({"bands_nm": [500, 510]}, {"psf.npy": b"x\n"},
     "{d}/psf.npy: not a .npy file (no NumPy header); save the PSF stack (C, H, W) with numpy.save"),
    ({"bands_nm": [500, 510]}, {"psf.npy": b""},
     "{d}/psf.npy: not a .npy file (an empty file); save the PSF stack (C, H, W) with numpy.save"),
    (None, {"psf_500nm.npy": _spot(), "b_500nm.npy": _spot()}, "{d}: two PSF images name the same wavelength"),
    ({"centre": "middle"}, {"psf_500nm.npy": _spot()},
     "{d}: PSF centre must be one of centroid, peak, axis, centroid_per_band, peak_per_band, got 'middle'"),
    ({"centre": "axis"}, {"psf_500nm.npy": _spot()}, "{d}: PSF centre 'axis' needs axis_px [row, col] in psf.json"),
    ({"normalize": "max"}, {"psf_500nm.npy": _spot()}, "{d}: PSF normalize must be 'sum' or 'none', got 'max'"),
    ({"wavelength_tolerance_nm": 0}, {"psf_500nm.npy": _spot()}, "{d}: wavelength_tolerance_nm must be positive"),
    ({"background": "nan"}, {"psf_500nm.npy": _spot()},
     "{d}/psf_500nm.npy (500 nm): PSF background must be finite, got 'nan'"),
    ({"background": "median"}, {"psf_500nm.npy": _spot()},
     "{d}/psf_500nm.npy (500 nm): PSF background must be 'none', 'border' or a number, got 'median'"),
    ({"background": "border"}, {"psf_500nm.npy": _spot()[:3, :3]},
     "{d}/psf_500nm.npy (500 nm): PSF image of 3×3 px is too small for border background estimation"),
    # a JSON boolean is no level either (float(True) subtracted 1)
    ({"background": True}, {"psf_500nm.npy": _spot()},
     "{d}/psf_500nm.npy (500 nm): PSF background must be 'none', 'border' or a number, got True"),
    ({"background": 5}, {"psf_500nm.npy": _spot()},
     "{d}/psf_500nm.npy (500 nm): PSF image has no positive signal (after background subtraction)"),
])
def test_psf_folder_refusals_name_the_problem(tmp_path, meta, files, text):
    d = _psf_dir(tmp_path / "psfs", meta, files)
    with pytest.raises(InputError) as exc:
        import_psf_dir(d, ONE_BAND, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == text.format(d=d)


def test_a_json_boolean_pixel_pitch_is_refused_not_read_as_1_um(tmp_path):
    """psf.json's `"pixel_pitch_um": true` was a pitch of 1 µm (Python counts a bool as an int), recorded as `true`
    in the import report; the other numbers of psf.json already refused booleans."""
    d = _psf_dir(tmp_path / "a", {"pixel_pitch_um": True}, {"psf_500nm.npy": _spot()})
    with pytest.raises(InputError) as exc:
        import_psf_dir(d, ONE_BAND, 5e-6, 15)
    assert str(exc.value) == f"{d}: PSF pixel pitch must be a positive number of µm, got True"


def test_psf_pitch_unknown_and_mixed_sizes_under_a_common_centre(tmp_path):
    d = _psf_dir(tmp_path / "a", {}, {"psf_500nm.npy": _spot()})
    with pytest.raises(InputError) as exc:
        import_psf_dir(d, ONE_BAND, 5e-6, 15)
    assert str(exc.value) == (f"{d}: the measured PSFs' pixel pitch is unknown: put pixel_pitch_um in psf.json or pass "
                              "--psf-pitch-um")
    two = Bands(np.array([500.0, 510.0]), np.array([10.0, 10.0]))
    d = _psf_dir(tmp_path / "b", {"centre": "centroid"}, {"psf_500nm.npy": _spot(31), "psf_510nm.npy": _spot(21)})
    with pytest.raises(InputError) as exc:
        import_psf_dir(d, two, 5e-6, 15, pitch_um=5.0)
    assert str(exc.value) == (f"{d}: PSF images have different sizes [(21, 21), (31, 31)]; a common centre needs one "
                              "frame (use centre: centroid_per_band or axis in psf.json)")


def test_a_coarser_psf_pitch_spreads_each_sample_over_its_pixel(tmp_path, caplog):
    """Sampled at twice the camera's pitch, a one-sample PSF centred on the axis is a 10 µm square of light over 5 µm
    pixels: per axis half on the centre pixel and a quarter on each neighbour (area resampling), with the warning
    that says so."""
    img = np.zeros((31, 31))
    img[15, 15] = 1.0
    d = _psf_dir(tmp_path / "p", {"centre": "axis", "axis_px": [15.0, 15.0]}, {"psf_500nm.npy": img})
    caplog.set_level("WARNING")
    psf = import_psf_dir(d, ONE_BAND, 5e-6, 15, pitch_um=10.0).psf
    assert "coarser than the camera's 5 µm pixels" in caplog.text
    k = np.asarray(psf[0])
    assert k.sum() == pytest.approx(1.0, abs=1e-9)
    one_axis = np.array([0.25, 0.5, 0.25])
    expected = np.zeros((15, 15))
    expected[6:9, 6:9] = np.outer(one_axis, one_axis)
    np.testing.assert_allclose(k, expected, atol=1e-6)
