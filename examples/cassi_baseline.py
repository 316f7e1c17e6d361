"""The paper's CASSI baseline: a DD-CASSI camera and GAP-TV on a held-out-sources scene, scored as the DOE camera.

    python examples/cassi_baseline.py [--out DIR] [--size 256] [--iterations 400] [--seed 3]

(about a minute at the defaults on a 2-core CPU; `--size 192 --iterations 100`: 10 s)

A dual-disperser coded-aperture camera (random binary aperture, 2 px shift per band, mean over bands:
the preset `dd_cassi_rdn`'s camera) images the same kind of scene as simulate_and_reconstruct.py;
GAP-TV (hsicam.solvers.gap_tv) reconstructs the whole scene, and it is scored on the pixels the
DOE camera's sensor sees (the scene less 70 px a side), as `hsicam evaluate --method dd-cassi-gaptv`
does. Writes DIR/scenes_SIZEpx_seedSEED/scene_0000.h5, DIR/cassi_sensor.npy, DIR/gaptv.h5 and DIR/gaptv_rgb.png.
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from hsicam.cameras import DDCASSICamera
from hsicam.color import srgb_preview
from hsicam.config import load_config
from hsicam.data import normalize_per_cube_max, read_cube, write_cube_h5
from hsicam.data.synthetic import generate_dataset
from hsicam.io import write_png8
from hsicam.metrics import all_metrics
from hsicam.solvers import gap_tv

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="output folder (default: a new temporary folder)")
parser.add_argument("--size", type=int, default=256, help="scene side, px")
parser.add_argument("--iterations", type=int, default=None, help="GAP-TV iterations (default: the config's, 400)")
parser.add_argument("--seed", type=int, default=3, help="the scene's seed")
args = parser.parse_args()
out = args.out or Path(tempfile.mkdtemp(prefix="hsicam_cassi_"))
out.mkdir(parents=True, exist_ok=True)

# 1. The camera and the solver's settings, from a preset (baselines.gaptv holds the tuned GAP-TV settings).
cfg = load_config("dd_cassi_rdn")
cam = DDCASSICamera.from_config(cfg)
s = cfg.baselines.gaptv
iterations = s.iterations if args.iterations is None else args.iterations
print(f"camera {cam.kind}: shifts {cam.shifts[0]}..{cam.shifts[-1]} px over {len(cam.bands)} bands, "
      f"convention {cam.convention}; GAP-TV {iterations} iterations, TV weight {s.tv_weight}")

# 2. The scene (the same generator and seed as simulate_and_reconstruct.py), normalised by its maximum.
scenes = out / f"scenes_{args.size}px_seed{args.seed}"  # one folder per set: a set is never overwritten
generate_dataset(scenes, n=1, size=args.size, seed=args.seed, bands=cam.bands, split="heldout",
                 progress=False)
cube, _, _ = read_cube(scenes / "scene_0000.h5")
scene = torch.from_numpy(normalize_per_cube_max(cube)[0])[None]  # (1, 31, S, S)

# 3. Capture (noise-free: the preset's sensor) and GAP-TV. The two dispersers cancel: the sensor is the scene's size.
with torch.no_grad():
    y = cam.capture(scene)  # (1, 1, S, S)
    x, info = gap_tv(cam, y, iterations=iterations, tv_weight=s.tv_weight, tv_iterations=s.tv_iterations,
                     accelerate=s.accelerate, return_info=True)
x = x.clamp(0, 1)
print(f"scene {tuple(scene.shape)} -> sensor {tuple(y.shape)} -> cube {tuple(x.shape)} "
      f"in {info.runtime_s:.1f} s, relative residual {cam.relative_residual(x, y):.2e}")

# 4. Scores on the DOE camera's sensor area: the 141-px kernel's margin is 140 px, 70 px a side.
b = 70
m = {k: v[0] for k, v in all_metrics(x[..., b:-b, b:-b], scene[..., b:-b, b:-b]).items()}
print(f"PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, SAM {m['sam']:.2f} deg (the scene less {b} px a side)")

# 5. Files.
np.save(out / "cassi_sensor.npy", y[0, 0].numpy())
write_cube_h5(out / "gaptv.h5", x[0].numpy(), cam.bands, metadata={"method": "dd-cassi-gaptv", **m})
write_png8(out / "gaptv_rgb.png", srgb_preview(x[0].numpy(), cam.bands))
print(f"wrote {out}")
