"""A folder of scenes whose spatial layouts no generated scene uses, for a generalisation test:
scikit-image's horse silhouette, microscopy cells, the Shepp-Logan phantom, a logo, a retina's
micro-aneurysms, binary blobs and a mosaic of faces (hsicam.data.synthetic.UNSEEN_LAYOUTS: none is a
photo, texture or pattern of the generator), each painted with 2 or 3 spectra and lit as the
generator lights its scenes (hsicam.data.synthetic.unseen_layout_scene).

    python scripts/unseen_layouts.py OUT [--n 7] [--seed 0] [--size 256] [--split heldout|train]

``--split heldout`` (default): the spectra come from the held-out sources only (data.holdout_sources'
default), so neither layout nor spectra occur in a training scene; ``train``: the training library
(layouts unseen, spectra seen). Bands: the paper's 31 (420-720 nm / 10 nm), those of the shipped
and the demo's cameras. Then, e.g.::

    hsicam evaluate --run RUN --data OUT --out DIR
    hsicam evaluate --run RUN --method doe-box-demosaic --data OUT --out DIR
    hsicam evaluate --config quick --method dd-cassi-gaptv --data OUT --out DIR

OUT is written whole or not at all (an existing OUT is refused).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hsicam.data.formats import write_cube_h5
from hsicam.data.spectral_sources import DEFAULT_HOLDOUT, spectral_library
from hsicam.data.synthetic import UNSEEN_LAYOUTS, unseen_layout_scene
from hsicam.errors import HsicamError
from hsicam.io import atomic_output
from hsicam.spectral import Bands


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", help="folder to write (must not exist)")
    p.add_argument("--n", type=int, default=len(UNSEEN_LAYOUTS), help=f"number of scenes (layouts repeat after {len(UNSEEN_LAYOUTS)})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=int, default=256, help="scene size in pixels")
    p.add_argument("--split", choices=("heldout", "train"), default="heldout", help="spectral library")
    args = p.parse_args(argv)
    out = Path(args.out)
    try:
        if args.n < 1 or args.size < 16:
            raise HsicamError(f"--n must be >= 1 and --size >= 16, got {args.n} and {args.size}")
        if out.exists():
            raise HsicamError(f"{out} exists; choose a new folder")
        bands = Bands.paper()
        lib = spectral_library(bands, DEFAULT_HOLDOUT, args.split)
        with atomic_output(out, marker=False) as tmp:  # a data folder: no completion marker (evaluate --data skips outputs)
            for i in range(args.n):
                cube, info = unseen_layout_scene(i, args.seed, args.size, lib)
                name = f"scene_{i:04d}_{info['layout']}.h5"
                meta = {"dataset": "hsicam-unseen-layouts", "index": i, "seed": args.seed, "split": args.split, **info}
                write_cube_h5(tmp / name, cube, bands, meta)
                print(f"[{i + 1}/{args.n}] {name}: mean {cube.mean():.4f}", file=sys.stderr, flush=True)
    except HsicamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
