"""Every script in examples/ runs as a user runs it (a subprocess, ``--out`` a fresh folder) and produces what its
docstring and docs/python.md say, so the examples cannot rot.

What each writes is read back in its real format by another library than the one that wrote it (h5py for hsicam's
HDF5, numpy for .npy and ENVI's raw data, the header's text, imageio for PNG, safetensors, json/yaml), and the numbers
it prints are recomputed from those files where that is cheap: the PSF's energy and RMS radius from the stack, PSNR
per band with numpy from the scene file and the written cube. The adjoint identity must hold to < 1e-5.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import imageio.v3 as iio
import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
#: Each example and the options the test runs it with (its defaults, or a smaller size where they take long).
RUNS = {
    "camera_and_psf.py": [],
    "simulate_and_reconstruct.py": [],
    "cassi_baseline.py": ["--size", "160", "--iterations", "60"],
    "custom_bands_and_files.py": [],
    "train_tiny.py": [],
    "custom_network.py": [],
}
#: The DOE camera's kernel margin (px, the 141-px kernel less one) of the paper's optics: the sensor area is the
#: scene less half of it a side.
PAPER_MARGIN = 140


def run_example(name: str, out: Path, *extra: str) -> str:
    """Run examples/``name`` with ``--out out`` and this checkout's package; its stdout (it must exit 0)."""
    return run_example_process(name, out, *extra).stdout


def run_example_process(name: str, out: Path, *extra: str) -> subprocess.CompletedProcess:
    """:func:`run_example`'s finished process (stdout and stderr)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "HSICAM_CACHE": str(out / "hsicam_cache")}
    env.pop("HSICAM_PRETRAINED_DIR", None)  # pretrained:standard is the shipped camera
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), "--out", str(out), *extra], env=env, cwd=out.parent,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{name} failed:\n{proc.stdout}\n{proc.stderr}"
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc


def number(text: str, pattern: str) -> float:
    """The number the regular expression ``pattern`` captures in ``text`` (one group)."""
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in:\n{text}"
    return float(m.group(1))


def psnr_per_band(estimate: np.ndarray, truth: np.ndarray) -> float:
    """PSNR with peak 1 of each band, averaged over bands (the project's "psnr"), in numpy float64."""
    mse = ((estimate.astype(np.float64) - truth.astype(np.float64)) ** 2).mean(axis=(-2, -1))
    return float(np.mean(10 * np.log10(1.0 / np.maximum(mse, 1e-30))))


def h5_cube(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(cube (C, H, W), band centres nm) of an hsicam HDF5 cube, read with h5py."""
    with h5py.File(path, "r") as f:
        return f["cube"][()], f["bands_nm"][()]


def normalised_scene(out: Path) -> np.ndarray:
    """The one synthetic scene the example wrote, divided by its maximum (the normalisation policy)."""
    (scene,) = sorted(out.glob("scenes_*/scene_0000.h5"))
    cube, _ = h5_cube(scene)
    return cube / cube.max()


def test_every_example_is_tested():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(RUNS)


def test_every_example_is_in_the_guide():
    guide = (ROOT / "docs" / "python.md").read_text(encoding="utf-8")
    missing = [name for name in RUNS if f"examples/{name}" not in guide]
    assert not missing, f"docs/python.md does not walk through {missing}"


def test_camera_and_psf(tmp_path):
    out = tmp_path / "out"
    text = run_example("camera_and_psf.py", out)
    psf = np.load(out / "psf.npy")
    assert psf.shape == (31, 141, 141) and psf.dtype == np.float32
    energy = psf.astype(np.float64).sum(axis=(1, 2))  # Parseval-normalised: what the kernel keeps of each band
    assert np.all((energy > 0.3) & (energy <= 1 + 1e-6))
    # each printed band's energy and RMS radius, recomputed from the stack
    k = np.arange(141) - 70
    r2 = k[:, None] ** 2 + k[None, :] ** 2
    for nm, band in ((420, 0), (570, 15), (720, 30)):
        assert number(text, rf"{nm} nm: energy in kernel ([\d.]+)") == pytest.approx(energy[band], abs=1e-4)
        rms = np.sqrt((psf[band] * r2).sum() / psf[band].sum())
        assert number(text, rf"{nm} nm: energy in kernel [\d.]+, RMS radius ([\d.]+) px") == pytest.approx(rms, abs=0.01)
    assert number(text, r"relative error ([\d.e+-]+)") < 1e-5
    assert number(text, r"<Ax,y> = ([\d.e+-]+)") > 0
    img = iio.imread(out / "psf_3_bands.png")
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 300



@pytest.mark.slow
def test_camera_and_psf_shows_the_singlets_focus_shift_without_the_doe(tmp_path):
    """docs/python.md: ``--lens singlet --no-doe`` shows the singlet's chromatic focus shift (``--lens singlet`` alone
    did not: behind the initial random DOE its RMS radius was 37.41 px at 420 nm against 37.23 for the achromat).
    Reference: the geometric blur disk of a fused-silica plano-convex lens (R 16 mm, f(λ) = R/(n(λ) − 1), n from
    Malitson's Sellmeier coefficients) focused at 587.6 nm, aperture radius 5 mm, 6 µm pixels: radius
    a·|z_i − f(λ)|/f(λ), RMS radius that over √2."""
    out = tmp_path / "out"
    text = run_example("camera_and_psf.py", out, "--lens", "singlet", "--no-doe")

    def n_fused_silica(um):
        l2 = um ** 2
        return np.sqrt(1 + 0.6961663 * l2 / (l2 - 0.0684043 ** 2) + 0.4079426 * l2 / (l2 - 0.1162414 ** 2)
                       + 0.8974794 * l2 / (l2 - 9.896161 ** 2))

    z_i = 16e-3 / (n_fused_silica(0.5876) - 1)
    rms = {}
    for nm in (420, 570, 720):
        rms[nm] = number(text, rf"{nm} nm: energy in kernel [\d.]+, RMS radius ([\d.]+) px")
        f = 16e-3 / (n_fused_silica(nm / 1000) - 1)
        disk_rms_px = 5e-3 * abs(z_i - f) / f / 6e-6 / np.sqrt(2)
        if nm != 570:  # away from the design wavelength the defocus dominates diffraction
            assert 0.9 * disk_rms_px <= rms[nm] <= 1.5 * disk_rms_px, (nm, rms[nm], disk_rms_px)
    assert rms[570] < rms[720] < rms[420]

def test_simulate_and_reconstruct_with_the_shipped_camera(tmp_path):
    out = tmp_path / "out"
    text = run_example("simulate_and_reconstruct.py", out)
    assert "noise poisson_gaussian" in text
    scene = normalised_scene(out)
    assert scene.shape == (31, 256, 256)
    b = PAPER_MARGIN // 2
    truth = scene[:, b:-b, b:-b]  # the sensor area of a "valid" camera
    cube, nm = h5_cube(out / "cube.h5")
    assert cube.shape == truth.shape and np.allclose(nm, np.arange(420, 721, 10))
    assert cube.min() >= 0 and cube.max() <= 1
    psnr = psnr_per_band(cube, truth)
    assert number(text, r"PSNR ([\d.]+) dB") == pytest.approx(psnr, abs=0.01)
    assert psnr > 30  # the shipped camera on a held-out-sources scene at 10 000 e-
    assert 0 < number(text, r"SSIM ([\d.]+)") <= 1 and 0 < number(text, r"SAM ([\d.]+) deg") < 90
    sensor = np.load(out / "sensor.npy")
    assert sensor.shape == truth.shape[1:] and np.isfinite(sensor).all()
    for png in ("cube_rgb.png", "truth_rgb.png"):
        assert iio.imread(out / png).shape == (*truth.shape[1:], 3)


def test_cassi_baseline(tmp_path):
    out = tmp_path / "out"
    text = run_example("cassi_baseline.py", out, *RUNS["cassi_baseline.py"])
    scene = normalised_scene(out)
    cube, nm = h5_cube(out / "gaptv.h5")
    assert cube.shape == scene.shape == (31, 160, 160) and len(nm) == 31
    b = PAPER_MARGIN // 2  # scored on the DOE camera's sensor area
    psnr = psnr_per_band(cube[:, b:-b, b:-b], scene[:, b:-b, b:-b])
    assert number(text, r"PSNR ([\d.]+) dB") == pytest.approx(psnr, abs=0.01)
    assert psnr > 25
    assert np.load(out / "cassi_sensor.npy").shape == (160, 160)  # DD-CASSI: the scene's size
    assert iio.imread(out / "gaptv_rgb.png").shape == (160, 160, 3)


def _envi(hdr: Path) -> tuple[dict[str, str], np.ndarray]:
    """An ENVI header's keys and its bsq little-endian data, read without hsicam."""
    keys = dict(line.split(" = ", 1) for line in hdr.read_text().splitlines()[1:] if " = " in line)
    dtype = {"2": "<i2", "4": "<f4"}[keys["data type"]]
    assert keys["interleave"] == "bsq" and keys["byte order"] == "0"
    data = np.fromfile(hdr.with_suffix(".img"), dtype=dtype)
    return keys, data.reshape(int(keys["bands"]), int(keys["lines"]), int(keys["samples"]))


def test_custom_bands_and_files(tmp_path):
    out = tmp_path / "out"
    text = run_example("custom_bands_and_files.py", out)
    assert "refused: cube: the camera's bands 420-720 nm are not covered by the data's 400-700 nm" in text
    assert number(text, r"max error against the exact spectra ([\d.e+-]+)") < 1e-6
    cube, nm = h5_cube(out / "cube.h5")
    assert cube.shape == (29, 24, 32) and np.allclose(nm, np.arange(420, 701, 10))
    keys, f32 = _envi(out / "cube_f32.hdr")
    assert [float(v) for v in keys["wavelength"].strip("{}").split(",")] == list(nm)
    np.testing.assert_array_equal(f32, cube)
    keys, i16 = _envi(out / "cube_i16.hdr")
    assert float(keys["reflectance scale factor"]) == 10000
    assert np.abs(i16 - cube.astype(np.float64) * 10000).max() <= 0.5 + 1e-3  # rounded, not truncated
    assert text.count("max difference") == 3


def test_train_tiny(tmp_path):
    out = tmp_path / "out"
    proc = run_example_process("train_tiny.py", out)
    text = proc.stdout
    # the tiny preset's 50 nm bands leave most spectra unused: one short warning (561 characters before session 62)
    # whose count and largest source are those of the manifest's not_used_out_of_range
    said = [line for line in proc.stderr.splitlines() if line.startswith("synthetic:")]
    assert len(said) == 1 and len(said[0]) <= 250, proc.stderr
    (manifest,) = (out / "cache").rglob("n6-*/manifest.json")
    unused = {k: len(v) for k, v in json.loads(manifest.read_text())["sources"]["not_used_out_of_range"].items()
              if k != "cie (not used)"}  # listed there, but not for their range
    top = max(unused, key=unused.get)
    assert said[0].startswith(f"synthetic: {sum(unused.values())} of ") and f"({top} {unused[top]}, " in said[0], said
    run = out / "run"
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["model"]["kind"] == "rdn" and cfg["data"]["cache_dir"] == str(out / "cache")
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1].get("final") is True and records[-1]["step"] == number(text, r"trained (\d+) steps")
    from safetensors.numpy import load_file

    weights = load_file(run / "model.safetensors")
    n_net = sum(v.size for k, v in weights.items() if k.startswith("net."))
    assert n_net == number(text, r"\((\d+) parameters\)")
    results = json.loads((out / "eval" / "results.json").read_text())
    rows = results["scenes"]
    assert len(rows) == number(text, r"(\d+) validation scenes") >= 1
    assert results["mean"]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in rows]))
    assert number(text, r"PSNR ([\d.]+) dB") == pytest.approx(results["mean"]["psnr"], abs=0.01)
    assert (out / "eval" / "results.csv").read_text().splitlines()[-1].startswith("mean,")
    assert any((out / "cache").rglob("scene_0000.h5"))  # its data went to out/cache (data.cache_dir) ...
    assert not (out / "hsicam_cache").exists()  # ... not to the default cache ($HSICAM_CACHE here)


def test_custom_network(tmp_path):
    out = tmp_path / "out"
    text = run_example("custom_network.py", out)
    from safetensors.numpy import load_file

    weights = load_file(out / "code_cnn.safetensors")
    c, f = 7, 16  # the tiny preset's bands, the example's FEATURES
    net = {k: v for k, v in weights.items() if k.startswith("net.")}
    assert sum(v.size for v in net.values()) == 9 * c * f + f + 9 * f * f + f + 9 * f * c + c
    assert number(text, r"CodeCNN: (\d+) parameters") == sum(v.size for v in net.values())
    assert any(k.startswith("camera.") for k in weights)  # the optics are part of the system's weights
    first, last = number(text, r"step 1 ([\d.]+)"), number(text, r"-> step \d+ ([\d.]+)")
    assert last < first
    assert number(text, r"DOE heights moved up to ([\d.]+) nm") > 0
    assert "sensor (2, 1, 32, 32) -> cube (2, 7, 32, 32)" in text
