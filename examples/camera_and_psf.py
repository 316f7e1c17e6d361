"""The paper's DOE camera from a preset: its PSF stack, and the exact adjoint of its operator.

    python examples/camera_and_psf.py [--out DIR] [--lens achromatic|singlet] [--no-doe]

Builds the camera of the ``paper`` preset (a 35 mm lens, a learned DOE of 30 µm cells over a 5 mm
aperture radius, a 9×9 CFA on a 6 µm-pixel sensor), prints its PSF stack's shape, the fraction of
each band's light that falls inside the kernel and the PSF's RMS radius, draws the PSFs at three
wavelengths into DIR/psf_3_bands.png (the stack: DIR/psf.npy), and checks <A x, y> = <x, Aᵀ y> on random float64 tensors.
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure  # a figure for a file: no pyplot, your matplotlib backend left as it is

from hsicam.cameras import DOECamera
from hsicam.config import load_config
from hsicam.report.camera import rms_radius_px

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="folder for the figure (default: a new temporary folder)")
parser.add_argument("--lens", choices=("achromatic", "singlet"), default="achromatic")
parser.add_argument("--no-doe", action="store_true", help="the lens alone (camera.doe.enabled=false): the initial "
                    "random DOE diffuses the light so much that the singlet's chromatic focus shift hardly shows")
args = parser.parse_args()
out = args.out or Path(tempfile.mkdtemp(prefix="hsicam_psf_"))
out.mkdir(parents=True, exist_ok=True)

# 1. The camera: the preset `paper` (configs/paper.yaml), one key changed the way `--set` changes it.
cfg = load_config("paper", [f"camera.lens.model={args.lens}", f"camera.doe.enabled={not args.no_doe}"])
cam = DOECamera.from_config(cfg)
bands = cam.bands  # Bands: 31 centres, 420-720 nm in 10 nm steps

# 2. Its PSF stack: (C, K, K), each pixel the fraction of the band's light it receives.
res = cam.psf_result()
psf = res.psf.detach().numpy()
energy = res.energy.detach().numpy()  # light inside the K×K kernel, per band (the rest is lost, not renormalised)
rms = rms_radius_px(psf)  # RMS radius about the optical axis, px
print(f"PSF stack {psf.shape} (bands × K × K), kernel {cam.kernel_px} px, margin {cam.margin} px")
for i in (0, len(bands) // 2, len(bands) - 1):
    print(f"  {bands.centers_nm[i]:.0f} nm: energy in kernel {energy[i]:.4f}, RMS radius {rms[i]:.2f} px")
print(f"energy in kernel: min {energy.min():.4f}, max {energy.max():.4f}")
np.save(out / "psf.npy", psf)

# 3. A figure of the PSFs at three wavelengths (log scale: the DOE spreads light far from the centre).
fig = Figure(figsize=(10, 3.6))
axes = fig.subplots(1, 3)
for ax, i in zip(axes, (0, len(bands) // 2, len(bands) - 1)):
    im = ax.imshow(np.log10(psf[i] + 1e-8), cmap="magma", vmin=-8, vmax=float(np.log10(psf.max())))
    ax.set_title(f"{bands.centers_nm[i]:.0f} nm, RMS {rms[i]:.1f} px")
    ax.axis("off")
fig.colorbar(im, ax=axes, label="log10 energy per pixel")
fig.savefig(out / "psf_3_bands.png", dpi=100)

# 4. The adjoint identity <A x, y> = <x, Aᵀ y> on random tensors, in float64.
#    A: scene (1, C, H+K-1, W+K-1) -> sensor (1, 1, H, W) (boundary "valid"); Aᵀ back to the scene's shape.
g = torch.Generator().manual_seed(0)
with torch.no_grad():
    cam64 = cam.double()
    x = torch.rand(1, len(bands), 32 + cam.margin, 40 + cam.margin, generator=g, dtype=torch.float64)
    ax_ = cam64.A(x)
    y = torch.rand(ax_.shape, generator=g, dtype=torch.float64)
    lhs, rhs = float((ax_ * y).sum()), float((x * cam64.A_adjoint(y)).sum())
print(f"sensor {tuple(ax_.shape)} from scene {tuple(x.shape)}")
print(f"adjoint check: <Ax,y> = {lhs:.10g}, <x,A^T y> = {rhs:.10g}, relative error {abs(lhs - rhs) / abs(lhs):.2e}")
print(f"wrote {out}")
