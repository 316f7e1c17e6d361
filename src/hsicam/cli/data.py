"""`hsicam data ...`: generate the synthetic dataset (`synth`), list its spectral sources
(`sources`) and preview a dataset (`show`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from hsicam.cli import add_config_args

    p = sub.add_parser("data", help="hyperspectral datasets: generate, list spectral sources, show")
    actions = p.add_subparsers(dest="data_command", metavar="ACTION", parser_class=type(p))
    actions.required = True

    s = actions.add_parser("synth", help="generate the embedded synthetic dataset (our HDF5 + manifest.json)")
    s.add_argument("--n", type=int, default=None,
                   help="number of scenes, >= 1 (default: data.synthetic_n; 8 for --split heldout)")
    s.add_argument("--size", type=int, default=None, help="scene side in px, >= 16 (default: data.synthetic_size)")
    from hsicam.cli.args import id_list_arg, seed_arg
    s.add_argument("--seed", type=seed_arg(0), default=None, help="random seed (default: data.synthetic_seed)")
    s.add_argument("--holdout-sources", metavar="IDS", default=None, type=id_list_arg,
                   help="comma-separated spectral source ids whose spectra never reach the training scenes "
                        "(default: the config's data.holdout_sources, nist-philips,rawtoaces in every preset but tiny, which holds out nist-cqs; "
                        "'none' for none; see `hsicam data sources`)")
    s.add_argument("--split", choices=("train", "heldout"), default="train",
                   help="train (default): scenes without the held-out sources; heldout: the held-out "
                        "validation set, made only of the held-out sources' spectra")
    s.add_argument("--out", metavar="DIR", default=None,
                   help="output folder (default: the cache: data.cache_dir, else $HSICAM_CACHE, else "
                        "$XDG_CACHE_HOME/hsicam, else ~/.cache/hsicam)")
    s.add_argument("--no-progress", action="store_true", help="no progress: neither the bar on a terminal nor the k/N log lines")
    add_config_args(s)
    s.set_defaults(func=_synth)

    c = actions.add_parser("sources", help="list the generator's spectral sources (ids for --holdout-sources)")
    c.set_defaults(func=_sources)

    v = actions.add_parser("show", help="contact sheet, mean spectra and spectral gamut of a dataset or cube",
                           epilog="A .npy cube carries no wavelengths: give its grid as the other commands take it, "
                                  "e.g. --set 'data.npy_bands={start_nm: 420, stop_nm: 720, step_nm: 10}' (default: "
                                  "its bands evenly over 400-700 nm); --set data.allow_negative=true clips negative "
                                  "values (dark noise after a background subtraction) to 0 instead of refusing them. "
                                  "Other config keys are not used here.")
    v.add_argument("path", metavar="DIR", help="dataset folder, or one cube file / CAVE folder")
    v.add_argument("--out", metavar="OUT", required=True,
                   help="a new or empty folder for the PNGs (or an earlier data show output, refreshed); never the "
                        "data folder itself: data show does not write into its input")
    v.add_argument("--max-scenes", type=int, default=16, help="at most this many scenes, >= 1 (default 16)")
    v.add_argument("--heldout", metavar="DIR", default=None,
                   help="held-out dataset to compare in the gamut plot (default: the cached companion of a "
                        "synthetic set, when present)")
    add_config_args(v)  # for data.npy_bands (the band grid of .npy cubes) and data.allow_negative, as train takes them
    v.set_defaults(func=_show)


def _synth(args: argparse.Namespace) -> int:
    from hsicam.cli import config_from_args
    from hsicam.data.synthetic import (
        HELDOUT_N,
        damaged_scenes,
        dataset_dir,
        generate_dataset,
        is_complete,
        parse_holdout,
        synthetic_dataset,
    )
    from hsicam.errors import InputError
    from hsicam.cli import prepare_output

    cfg = config_from_args(args.config, args.overrides)
    if args.size is not None:  # before any folder is made (synthetic_size of a config: checked by the generator)
        from hsicam.data.synthetic import check_scene_memory

        check_scene_memory(args.size, len(cfg.bands.to_bands()), "--size")
    if args.out is not None:
        from hsicam.data.synthetic import check_dataset_folder

        check_dataset_folder(prepare_output(args.out, "dir"))
    # the config's held-out sources, as training takes them (a set made here then is the one its cache key names)
    holdout = parse_holdout(cfg.data.holdout_sources if args.holdout_sources is None else args.holdout_sources)
    split = args.split
    if args.n is not None:
        n = args.n
    else:
        n = HELDOUT_N if split == "heldout" else cfg.data.synthetic_n
    size = cfg.data.synthetic_size if args.size is None else args.size
    seed = cfg.data.synthetic_seed if args.seed is None else args.seed
    if n < 1 or size < 16:
        raise InputError(f"--n must be >= 1 and --size >= 16, got {n} and {size}")
    if split == "heldout" and not holdout:
        raise InputError("--split heldout needs at least one held-out source (--holdout-sources)")
    bands = cfg.bands.to_bands()
    progress = False if args.no_progress else None
    kw = {"holdout_sources": holdout, "split": split}
    room_fix = "lower --n or --size, or " + (  # a refusal for want of disk space names the options
        "give --out a folder on a larger disk" if args.out is not None else
        "write to a larger disk (--out, or data.cache_dir / HSICAM_CACHE)")
    what = ("held-out scene" if split == "heldout" else "scene") + ("" if n == 1 else "s")
    target = Path(args.out) if args.out is not None else dataset_dir(n, size, seed, bands, cache_dir=cfg.data.cache_dir,
                                                                     **kw)
    if is_complete(target, n, size, seed, bands, **kw):
        # a finished set: its files checked against the manifest's checksums (training trusts them), a damaged one
        # generated again in place (the same bytes; each file replaced atomically, the manifest last)
        bad = damaged_scenes(target)
        if not bad:
            print(f"{target}: already holds this dataset (n={n}, size={size}, seed={seed}, split={split}); "
                  + (f"its {n} {what} match their checksums" if n > 1 else f"its {what} matches its checksum"))
            return 0
        print(f"{target}: {len(bad)} of its {n} {what} missing or not the bytes its manifest records "
              f"({', '.join(bad[:3])}{', …' if len(bad) > 3 else ''}): generating the set again")
        generate_dataset(target, n=n, size=size, seed=seed, bands=bands, progress=progress, room_fix=room_fix, **kw)
        print(f"wrote {n} {what} of {size}x{size}x{len(bands)} to {target} (held-out sources: "
              f"{', '.join(holdout) or 'none'})")
        return 0
    if args.out is None:
        out = synthetic_dataset(n, size, seed, bands, cache_dir=cfg.data.cache_dir, progress=progress,
                                room_fix=room_fix, **kw)
    else:
        out = Path(args.out)
        if out.is_dir() and any(not f.name.startswith(".") for f in out.iterdir()):
            # scene files of a generation killed before its manifest (written in place before session 51): finished there
            generate_dataset(out, n=n, size=size, seed=seed, bands=bands, progress=progress, room_fix=room_fix, **kw)
        else:
            # whole or not at all: written into a hidden temporary folder that takes the name at the end, so a killed
            # generation leaves no folder of scenes that `evaluate --data` or `data show` would take for a dataset
            from hsicam.data.synthetic import check_room_for_scenes
            from hsicam.io import atomic_output

            check_room_for_scenes(out, n, size, len(bands), room_fix)  # named by --out, before the temporary
            with atomic_output(out, "dir", marker=False) as tmp:
                generate_dataset(tmp, n=n, size=size, seed=seed, bands=bands, progress=progress, room_fix=room_fix, **kw)
    print(f"wrote {n} {what} of {size}x{size}x{len(bands)} to {out} (held-out sources: {', '.join(holdout) or 'none'})")
    return 0


def _sources(args: argparse.Namespace) -> int:
    from hsicam.data.spectral_sources import DEFAULT_HOLDOUT, SOURCES

    from hsicam.errors import InputError

    counts: dict[str, int] = {}
    why = None
    try:
        from hsicam.data.spectral_sources import spectral_library
        from hsicam.spectral import Bands

        for role in spectral_library(Bands.paper()).counts().values():
            for k, v in role.items():
                counts[k] = counts.get(k, 0) + v
    except InputError as exc:  # colour-science missing or too old: list the registry without counts, and say why
        counts, why = {}, str(exc)
    for s in SOURCES.values():
        n = str(counts.get(s.id, "-")) if counts else "?"
        mark = " (held out by default)" if s.id in DEFAULT_HOLDOUT else ""
        print(f"{s.id:18s} {s.role:15s} {n:>4s}  {s.origin}{mark}")
    if why:
        print(f"hsicam: counts '?': {why}", file=sys.stderr)
    return 0


def _show(args: argparse.Namespace) -> int:
    from hsicam.cli import config_from_args
    from hsicam.data.pipeline import npy_bands
    from hsicam.data.preview import write_preview
    from hsicam.errors import InputError

    data = config_from_args(args.config, args.overrides).data  # before any work: a bad --set fails first
    grid = npy_bands(data)
    if args.max_scenes < 1:
        raise InputError(f"--max-scenes must be at least 1, got {args.max_scenes}")
    src = Path(args.path)
    if not src.exists():
        raise InputError(f"{src}: no such dataset folder or cube file")
    preview = lambda out: write_preview(args.path, out, max_scenes=args.max_scenes,  # noqa: E731
                                        heldout=args.heldout, npy_bands=grid, allow_negative=data.allow_negative)
    written = _show_into(Path(args.out), preview)
    for path in written:
        print(path)
    return 0


def _show_into(out: Path, preview) -> list[Path]:
    """``preview(folder)`` written into ``--out`` under the rules of every command's output folder
    (:func:`hsicam.cli.prepare_output`): a new or empty folder, or the completed output of an earlier
    ``data show`` holding only its files. The PNGs are written all or none (``write_preview``), then
    the completion marker naming this command and them; returns their paths."""
    from hsicam.cli import prepare_output
    from hsicam.io import mark_complete

    out = prepare_output(out, "dir", replace=True, command="data show")
    written = preview(out)
    mark_complete(out, {"command": "data show", "files": sorted(p.name for p in written)})
    return written
