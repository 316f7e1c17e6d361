"""`hsicam data ...`: generate the synthetic dataset (`synth`) and preview a dataset (`show`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from hsicam.cli import add_config_args

    p = sub.add_parser("data", help="hyperspectral datasets: generate, show")
    actions = p.add_subparsers(dest="data_command", metavar="ACTION", parser_class=type(p))
    actions.required = True

    s = actions.add_parser("synth", help="generate the embedded synthetic dataset (our HDF5 + manifest.json)")
    s.add_argument("--n", type=int, default=None, help="number of scenes (default: data.synthetic_n)")
    s.add_argument("--size", type=int, default=None, help="scene side in px (default: data.synthetic_size)")
    s.add_argument("--seed", type=int, default=None, help="random seed (default: data.synthetic_seed)")
    s.add_argument("--out", metavar="DIR", default=None,
                   help="output folder (default: the cache, $HSICAM_CACHE or ~/.cache/hsicam)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_args(s)
    s.set_defaults(func=_synth)

    v = actions.add_parser("show", help="contact sheet of sRGB renders and mean spectra of a dataset or cube")
    v.add_argument("path", metavar="DIR", help="dataset folder, or one cube file / CAVE folder")
    v.add_argument("--out", metavar="DIR", default=None, help="where to write the PNGs (default: DIR)")
    v.add_argument("--max-scenes", type=int, default=16, help="at most this many scenes (default 16)")
    v.set_defaults(func=_show)


def _synth(args: argparse.Namespace) -> int:
    from hsicam.config import load_config
    from hsicam.data.synthetic import generate_dataset, is_complete, synthetic_dataset
    from hsicam.errors import InputError

    cfg = load_config(args.config, args.overrides)
    n = cfg.data.synthetic_n if args.n is None else args.n
    size = cfg.data.synthetic_size if args.size is None else args.size
    seed = cfg.data.synthetic_seed if args.seed is None else args.seed
    if n < 1 or size < 16:
        raise InputError(f"--n must be >= 1 and --size >= 16, got {n} and {size}")
    bands = cfg.bands.to_bands()
    progress = False if args.no_progress else None
    if args.out is None:
        out = synthetic_dataset(n, size, seed, bands, cache_dir=cfg.data.cache_dir, progress=progress)
    else:
        out = Path(args.out)
        if is_complete(out, n, size, seed, bands):
            print(f"{out}: already holds this dataset (n={n}, size={size}, seed={seed})")
            return 0
        generate_dataset(out, n=n, size=size, seed=seed, bands=bands, progress=progress)
    print(f"wrote {n} scenes of {size}x{size}x{len(bands)} to {out}")
    return 0


def _show(args: argparse.Namespace) -> int:
    from hsicam.data.preview import write_preview

    for path in write_preview(args.path, args.out, max_scenes=args.max_scenes):
        print(path)
    return 0
