"""Draw trained PSFs of several cameras side by side (docs: the DOE/CFA ablation).

    python scripts/psf_compare_figure.py OUT.png LABEL=DIR/psf.npy [LABEL=DIR/psf.npy ...] [--bands 420,570,720]

Each `psf.npy` is a (bands, K, K) stack as `hsicam psf` and `hsicam demo` write it; its band centres are read
from the `psf.json` beside it (`bands_nm`), else, for a stack without one, taken as 420 nm on in 10 nm steps
(said). One row per camera, one column per chosen band (a wavelength that is not a band of a stack is refused):
the central 9×9 px on a linear scale (each panel normalised to its own peak), titled with the share of the
kernel's light on the central pixel and within 3×3 px, and the RMS radius (hsicam.report.camera.rms_radius_px).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hsicam.report.camera import rms_radius_px  # noqa: E402

START_NM, STEP_NM, CROP = 420.0, 10.0, 9


def _waves(text: str) -> list[float]:
    try:
        return [float(w) for w in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers (nm), got {text!r}") from None


def _stack(path: str) -> np.ndarray:
    """The (bands, K, K) PSF stack in ``path``; a file that is not one is a ValueError naming it."""
    try:
        stack = np.load(path, allow_pickle=False)
    except (ValueError, EOFError):  # not a .npy file (numpy takes it for a pickle), truncated, or pickled objects
        raise ValueError(f"{path}: not a .npy array") from None
    if not isinstance(stack, np.ndarray) or stack.ndim != 3 or stack.shape[1] != stack.shape[2]:
        raise ValueError(f"{path}: expected a (bands, K, K) PSF stack, got shape {getattr(stack, 'shape', None)}")
    return stack


def _band_centres(path: str, n: int) -> tuple[np.ndarray, str]:
    """The ``n`` band centres (nm) of the stack ``path``: its psf.json's ``bands_nm``, else 420 nm on in 10 nm steps;
    and where they come from, for a message."""
    meta = Path(path).with_name("psf.json")
    if not meta.is_file():
        print(f"{path}: no psf.json beside it: its {n} bands taken as {START_NM:g} nm on in {STEP_NM:g} nm steps",
              file=sys.stderr)
        return START_NM + STEP_NM * np.arange(n), f"{START_NM:g} nm on in {STEP_NM:g} nm steps (assumed)"
    try:
        centres = np.asarray(json.loads(meta.read_text(encoding="utf-8"))["bands_nm"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{meta}: no band list 'bands_nm' ({exc})") from None
    if centres.shape != (n,):
        raise ValueError(f"{meta}: lists {centres.size} band centres, but {path} holds {n} bands")
    return centres, f"{', '.join(f'{c:g}' for c in centres)} nm ({meta.name})"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out")
    p.add_argument("psfs", nargs="+", help="LABEL=path/to/psf.npy")
    p.add_argument("--bands", type=_waves, default="420,570,720", help="band centres in nm")
    args = p.parse_args(argv)
    waves = args.bands
    rows = []
    for item in args.psfs:
        label, sep, path = item.partition("=")
        if not sep:
            p.error(f"expected LABEL=path/to/psf.npy, got {item!r}")
        try:  # a missing or unreadable file, or no PSF stack: one line, before anything is drawn
            stack = _stack(path)
            rows.append((label, stack, *_band_centres(path, stack.shape[0])))
        except (OSError, ValueError) as exc:
            p.error(str(exc))
    fig, axes = plt.subplots(len(rows), len(waves), figsize=(2.4 * len(waves), 2.5 * len(rows)), squeeze=False)
    for r, (label, stack, centres, grid) in enumerate(rows):
        k = stack.shape[1]
        c, h = k // 2, CROP // 2
        radii = rms_radius_px(stack)
        for j, w in enumerate(waves):
            b = int(np.argmin(np.abs(centres - w)))
            if abs(centres[b] - w) > 0.5:
                p.error(f"{w:g} nm is not a band of {label} (its bands: {grid})")
            psf = stack[b] / stack[b].sum()
            ax = axes[r, j]
            ax.imshow(psf[c - h:c + h + 1, c - h:c + h + 1], cmap="inferno", vmin=0)
            ax.set_title(f"{w:g} nm: centre {psf[c, c]:.0%}\n3×3 {psf[c - 1:c + 2, c - 1:c + 2].sum():.0%}, "
                         f"r {radii[b]:.1f} px", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
            if j == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle(f"PSF, central {CROP}×{CROP} px, linear, each panel to its peak; shares of the kernel's light",
                 fontsize=9)
    fig.tight_layout()
    try:
        fig.savefig(args.out, dpi=110)
    except OSError as exc:  # a folder that is not there, a full disk
        p.error(str(exc))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
