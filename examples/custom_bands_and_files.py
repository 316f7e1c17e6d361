"""Cubes on another band grid and in files: resample to a camera's Bands, write and read HDF5 and ENVI.

    python examples/custom_bands_and_files.py [--out DIR]

A cube on ICVL's grid (31 bands, 400-700 nm in 10 nm steps) is brought onto a camera's bands. hsicam
resamples and never relabels bands, and never extrapolates: the paper's 420-720 nm camera is refused
(710 and 720 nm are not in the data), a 420-700 nm camera (29 bands) is accepted. The resampled cube is
written as hsicam's HDF5 and as ENVI (float32, and int16 with a reflectance scale factor) and read back
with its wavelengths. Writes DIR/cube.h5, DIR/cube_f32.hdr/.img and DIR/cube_i16.hdr/.img.
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np

from hsicam import InputError
from hsicam.config import load_config
from hsicam.data import read_cube, resample_cube, write_cube_h5, write_envi
from hsicam.spectral import Bands

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="output folder (default: a new temporary folder)")
args = parser.parse_args()
out = args.out or Path(tempfile.mkdtemp(prefix="hsicam_bands_"))
out.mkdir(parents=True, exist_ok=True)

# 1. A cube (C, H, W) on ICVL's grid whose spectra are linear in wavelength (a slope and an offset per
#    pixel), so the exact value at any wavelength is known and the resampling can be checked against it.
icvl = Bands.uniform(400, 700, 10)  # 31 bands, FWHM = the step
rng = np.random.default_rng(0)
offset, slope = rng.uniform(0.2, 0.6, (2, 24, 32))
slope = (slope - 0.4) / 1000  # per nm
cube = (offset + slope * (icvl.centers_nm[:, None, None] - 550)).astype(np.float32)
print(f"data: {cube.shape} on {icvl.min_nm:.0f}-{icvl.max_nm:.0f} nm ({len(icvl)} bands)")

# 2. The paper's 420-720 nm bands are refused (no extrapolation); one clear InputError, no traceback.
paper = load_config("paper").bands.to_bands()
try:
    resample_cube(cube, icvl, paper)
except InputError as exc:
    print(f"refused: {exc}")

# 3. A camera grid inside the data: the paper preset with bands.stop_nm=700 (29 bands, 420-700 nm).
bands = load_config("paper", ["bands.stop_nm=700"]).bands.to_bands()
on_camera = resample_cube(cube, icvl, bands)  # linear interpolation in band centre (same 10 nm FWHM)
exact = offset + slope * (bands.centers_nm[:, None, None] - 550)
print(f"camera: {on_camera.shape} on {bands.min_nm:.0f}-{bands.max_nm:.0f} nm; "
      f"max error against the exact spectra {np.abs(on_camera - exact).max():.2e}")

# 4. Files: hsicam HDF5 and ENVI; each keeps the wavelengths (and FWHM) with the cube.
h5 = write_cube_h5(out / "cube.h5", on_camera, bands, metadata={"source": "ICVL-style example"})
hdr32, _ = write_envi(out / "cube_f32.hdr", on_camera, bands)
hdr16, _ = write_envi(out / "cube_i16.hdr", on_camera, bands, dtype="int16", reflectance_scale=10000)
for path, tol in ((h5, 0.0), (hdr32, 0.0), (hdr16, 0.5e-4)):
    back, back_bands, meta = read_cube(path)  # the format is told by the content
    assert back_bands.matches(bands) and np.allclose(back_bands.fwhm_nm, bands.fwhm_nm)
    err = float(np.abs(back - on_camera).max())
    assert err <= tol + 1e-7, (path, err)
    print(f"{path.name}: read back as {meta['format']}, {back.shape}, "
          f"bands {back_bands.min_nm:.0f}-{back_bands.max_nm:.0f} nm, max difference {err:.1e}")
print(f"wrote {out}")
