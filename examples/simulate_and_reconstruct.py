"""The shipped camera on a scene of spectra it never saw: simulate a noisy capture, reconstruct, score.

    python examples/simulate_and_reconstruct.py [--out DIR] [--size 256] [--full-well-e 10000] [--seed 3]

What the README's three commands do (`hsicam data synth --split heldout`, `hsicam simulate`,
`hsicam reconstruct`), from Python: one synthetic scene painted with the held-out spectral sources
(needs colour-science, `pip install 'hsicam[synth]'`), the camera `pretrained:standard` with
Poisson–Gaussian noise at FULL_WELL_E electrons at full scale (2 e- read noise), its reconstruction,
and the project's scores (PSNR per band with peak 1, SSIM, SAM in degrees) on the camera's sensor area.
Writes DIR/scenes_SIZEpx_seedSEED/scene_0000.h5, DIR/sensor.npy, DIR/cube.h5, DIR/truth_rgb.png and DIR/cube_rgb.png.
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from hsicam.color import srgb_preview
from hsicam.data import normalize_per_cube_max, read_cube, write_cube_h5
from hsicam.data.synthetic import generate_dataset
from hsicam.io import write_png8
from hsicam.metrics import all_metrics, psnr_per_band
from hsicam.runs.folder import load_run

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="output folder (default: a new temporary folder)")
parser.add_argument("--size", type=int, default=256, help="scene side, px (the sensor is 140 px smaller)")
parser.add_argument("--full-well-e", type=float, default=10000.0, help="electrons at full scale (photon level)")
parser.add_argument("--seed", type=int, default=3, help="the scene's seed")
args = parser.parse_args()
out = args.out or Path(tempfile.mkdtemp(prefix="hsicam_sim_"))
out.mkdir(parents=True, exist_ok=True)

# 1. The camera shipped with the package, its sensor given Poisson–Gaussian noise (keys of camera.sensor).
cfg, system = load_run("pretrained:standard", overrides=(
    "camera.sensor.noise=poisson_gaussian", f"camera.sensor.full_well_e={args.full_well_e}",
    "camera.sensor.read_noise_e=2"))
cam = system.camera
print(f"camera {cam.kind}, {len(cam.bands)} bands {cam.bands.min_nm:.0f}-{cam.bands.max_nm:.0f} nm, "
      f"CFA {cam.code_period}x{cam.code_period}, kernel {cam.kernel_px} px, noise {cam.noise.model}")

# 2. One held-out-sources scene (as `hsicam data synth --n 1 --split heldout`), read back with its Bands
#    and normalised by its maximum, the training data's policy.
scenes = out / f"scenes_{args.size}px_seed{args.seed}"  # one folder per set: a set is never overwritten
generate_dataset(scenes, n=1, size=args.size, seed=args.seed, bands=cam.bands, split="heldout",
                 progress=False)
cube, bands, _ = read_cube(scenes / "scene_0000.h5")
cube, _ = normalize_per_cube_max(cube)
scene = torch.from_numpy(cube)[None]  # (1, 31, S, S)

# 3. The capture: A(scene) plus the sensor's noise, drawn from a seeded generator.
with torch.no_grad():
    sensor = cam.capture(scene, torch.Generator().manual_seed(0))  # (1, 1, S-140, S-140): boundary "valid"
    estimate = system.reconstruct(sensor).clamp(0, 1)  # network, linear step, 12 Landweber steps with TV
truth = system.target(scene)  # the scene's centre crop under the sensor
print(f"scene {tuple(scene.shape)} -> sensor {tuple(sensor.shape)} -> cube {tuple(estimate.shape)}")

# 4. Scores, the project's conventions (hsicam.metrics.CONVENTIONS).
m = {k: v[0] for k, v in all_metrics(estimate, truth).items()}
per_band = psnr_per_band(estimate[0].unsqueeze(1), truth[0].unsqueeze(1))  # each band as its own 1-band cube
print(f"PSNR {m['psnr']:.2f} dB (per band {per_band.min():.1f}-{per_band.max():.1f} dB), SSIM {m['ssim']:.4f}, "
      f"SAM {m['sam']:.2f} deg")

# 5. Files: the sensor image, the cube (HDF5 with its wavelengths), sRGB previews of truth and estimate.
np.save(out / "sensor.npy", sensor[0, 0].numpy())
est = estimate[0].numpy()
write_cube_h5(out / "cube.h5", est, cam.bands, metadata={"source": "examples/simulate_and_reconstruct.py", **m})
write_png8(out / "cube_rgb.png", srgb_preview(est, cam.bands))
write_png8(out / "truth_rgb.png", srgb_preview(truth[0].numpy(), cam.bands))
print(f"wrote {out}")
