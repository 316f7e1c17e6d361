"""PSF accuracy against the independent square-cell integral (tests/optics_reference.py).

Builds a camera from a config (default: the paper preset, random diffuser DOE), computes its PSF
stack and compares chosen bands with the reference (every order, 11×11 points per pixel):
relative L1 of the kernel and light inside the kernel. ``--bands-nm``: each is compared in the band nearest it
(``nm``, next to the ``asked_nm``); a wavelength outside the bands' span is refused. Prints JSON. Works with any version of
the package that has ``DOECamera.from_config`` (used for before/after tables).

Run: `PYTHONPATH=src .venv/bin/python benchmarks/psf_accuracy.py [--set key=value ...]`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from optics_reference import doe_field, relative_l1, square_cell_psf  # noqa: E402

from hsicam.cameras import DOECamera  # noqa: E402
from hsicam.config import load_config  # noqa: E402
from hsicam.errors import HsicamError  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--bands-nm", type=float, nargs="+", default=[420.0, 550.0, 720.0])
    ap.add_argument("--sub", type=int, default=11)
    args = ap.parse_args()
    if args.sub < 1:
        ap.error(f"--sub must be >= 1, got {args.sub}")
    try:  # a bad --set is one usage line, as the hsicam command says it, not a ConfigError traceback
        cfg = load_config(overrides=args.overrides)
        cam = DOECamera.from_config(cfg).double()
    except (HsicamError, OSError) as exc:
        ap.error(str(exc))
    # each wavelength is compared in the band nearest it: one outside the bands' span (their half widths included)
    # would silently be the edge band's, so it is refused
    lo = float(cam.bands.centers_nm[0] - cam.bands.fwhm_nm[0] / 2)
    hi = float(cam.bands.centers_nm[-1] + cam.bands.fwhm_nm[-1] / 2)
    outside = [lam for lam in args.bands_nm if not lo <= lam <= hi]
    if outside:
        ap.error(f"--bands-nm {outside[0]:g}: outside the camera's bands ({lo:g}–{hi:g} nm)")
    o = cam.optics
    with torch.no_grad():
        res = cam.psf_result()
        h = o.doe.heights().numpy()
    q = o.pupil_oversample
    amp = o.amplitude.numpy()
    k = cam.kernel_px
    pixels = np.arange(k) - k // 2
    out = {"config": args.overrides, "kernel_px": k, "bands": []}
    for lam in args.bands_nm:
        b = int(np.argmin(np.abs(cam.bands.centers_nm - lam)))
        lam_b = float(cam.bands.centers_nm[b])
        u = doe_field(h, amp, lam_b, q)
        ref = square_cell_psf(u, o.cell_m / q, lam_b * 1e-9, o.sensor_distance_m, o.pixel_m, pixels, args.sub)
        psf = res.psf[b].numpy()
        out["bands"].append({"asked_nm": lam, "nm": lam_b, "l1": relative_l1(psf, ref), "energy_model": float(res.energy[b]),
                             "energy_reference": float(ref.sum())})
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
