"""`hsicam pretrained`: the cameras shipped with the package (list, show, copy; pack for maintainers).

    hsicam pretrained                          one line per shipped camera
    hsicam pretrained show NAME                its model card (card.md)
    hsicam pretrained copy NAME DIR            a writable run folder holding it
    hsicam pretrained pack RUN --name NAME [--dest DIR] [--results results.json] [--heldout results.json] [--force]

Every ``--run`` accepts ``pretrained:NAME``. ``HSICAM_PRETRAINED_DIR`` replaces the package's folder.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("pretrained", help="cameras shipped with the package: list, show, copy (use: --run pretrained:NAME)")
    p.set_defaults(func=cmd_list)
    psub = p.add_subparsers(dest="pretrained_command", metavar="SUBCOMMAND")
    q = psub.add_parser("list", help="one line per shipped camera (the default)")
    q.set_defaults(func=cmd_list)
    q = psub.add_parser("show", help="print a shipped camera's model card")
    q.add_argument("name", metavar="NAME", help="a shipped camera's name (`hsicam pretrained` lists them)")
    q.set_defaults(func=cmd_show)
    q = psub.add_parser("copy", help="copy a shipped camera into a normal, writable run folder")
    q.add_argument("name", metavar="NAME", help="a shipped camera's name (`hsicam pretrained` lists them)")
    q.add_argument("dir", metavar="DIR", help="new run folder (absent or empty)")
    q.set_defaults(func=cmd_copy)
    q = psub.add_parser("pack", help="(maintainers) pack a finished run as a shipped camera, with its card")
    q.add_argument("run", metavar="RUN", help="finished run folder")
    q.add_argument("--name", required=True, help="camera name (e.g. standard)")
    q.add_argument("--results", metavar="FILE", help="results.json of `hsicam demo` or `hsicam evaluate` on this run "
                                                     "(an evaluation of another run is refused)")
    q.add_argument("--heldout", metavar="FILE", help="results.json of an evaluation of this run on held-out data "
                                                     "(instead of --results' own held-out section)")
    from hsicam.cli.args import text_arg

    q.add_argument("--summary", type=text_arg, help="one-line summary (default: made from the run)")
    q.add_argument("--preset", type=text_arg, help="shipped preset the run was trained from (default: the preset its config equals, "
                                    "if any; a camera that differs from it is warned about)")
    q.add_argument("--dest", metavar="DIR", help="folder of cameras to pack into (default: $HSICAM_PRETRAINED_DIR, "
                                                 "else, from a source checkout only, the package's "
                                                 "resources/pretrained; from an installed package, give it)")
    q.add_argument("--force", action="store_true", help="replace an existing camera of that name")
    q.set_defaults(func=cmd_pack)


def _bare(name: str) -> str:
    """A camera's name as `show` and `copy` take it: ``pretrained:NAME`` (what ``--run`` takes) is ``NAME``."""
    return name.removeprefix("pretrained:")


def _dict(value) -> dict:
    return value if isinstance(value, dict) else {}


def _metrics(card: dict) -> str:
    """The camera's scores on its own validation (its scenes whole, else its training log's patches),
    said as such: another camera's or the demo's scenes score differently."""
    m = _dict(card.get("metrics"))
    scenes = _dict(m.get("validation"))
    val = _dict(scenes.get("mean"))
    n = scenes.get("n_scenes")
    what = f"its {n} validation scenes" if val and isinstance(n, int) else "its validation scenes"
    if not val:
        val, what = _dict(m.get("training_log")), "its validation patches"
    if not all(isinstance(val.get(k), (int, float)) for k in ("psnr", "ssim", "sam")):
        return "val –"
    return f"{what}: PSNR {val['psnr']:.2f} dB, SSIM {val['ssim']:.4f}, SAM {val['sam']:.2f}°"


def _no_cameras() -> str:
    """The line of `hsicam pretrained` when the root holds no camera."""
    import os

    from hsicam.runs.pretrained import ENV_VAR, available, env_root_problem, package_root, root

    problem = env_root_problem()
    if problem:
        return f"no pre-trained cameras: {problem}"
    if os.environ.get(ENV_VAR):
        shipped = available(package_root())
        return (f"no pre-trained cameras in {root()} ({ENV_VAR}); unset {ENV_VAR} for the cameras shipped with "
                f"hsicam ({', '.join(shipped) if shipped else 'none'})")
    return f"no pre-trained cameras are shipped in {root()} (set {ENV_VAR} to use another folder)"


def _list_line(name: str) -> tuple[str, bool]:
    """(the line of camera ``name`` in `hsicam pretrained`, whether it is usable): its summary, bands
    and numbers, or what is wrong with its folder."""
    from hsicam.runs.pretrained import parse_card, root, weights_problem

    card, why = parse_card(root() / name)
    if card is None:
        return f"{name}: {why}: not usable", False
    why = weights_problem(root() / name)  # what --run and copy refuse it for
    if why is not None:
        return f"{name}: {why}: not usable", False
    count = _dict(card.get("bands")).get("count", "?")
    return f"{name}: {card.get('summary', '')} | {count} bands | {_metrics(card)}", True


def cmd_list(args: argparse.Namespace) -> int:
    """One line per camera folder; a broken one (files missing, card unreadable) is reported on its
    own line and the others are still listed (exit status 0: the listing itself succeeded)."""
    from hsicam.runs.pretrained import camera_folders

    names = camera_folders()
    if not names:
        print(_no_cameras())
        return 0
    lines = [_list_line(name) for name in names]
    for line, _ in lines:
        print(line)
    if any(ok for _, ok in lines):
        print("use one with --run pretrained:NAME; `hsicam pretrained show NAME` prints its card")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    """The camera's card.md; weights that are not the card's are said after it (the card is shown)."""
    from hsicam.runs.pretrained import pretrained_dir, weights_problem

    name = _bare(args.name)
    folder = pretrained_dir(name)
    print(_card_text(folder), end="")
    problem = weights_problem(folder)
    if problem:
        print(f"\nWARNING: {problem}; until then `--run pretrained:{name}` and `hsicam pretrained copy "
              f"{name}` refuse this camera")
    return 0


def _card_text(folder) -> str:
    """The camera's card.md; when it is missing or unreadable, the card made again from its card.json (whence
    card.md is made, :func:`hsicam.engine.pretrained.card_markdown`) under a line that says so, or one InputError
    naming the file."""
    from hsicam.errors import InputError
    from hsicam.runs.pretrained import CARD_MD, parse_card

    path = folder / CARD_MD
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        why = "not UTF-8 text" if isinstance(exc, UnicodeDecodeError) else (exc.strerror or str(exc)).lower()
    card, _ = parse_card(folder)
    if card is not None:
        from hsicam.engine.pretrained import card_markdown

        try:
            return f"({path}: {why}; the card below is made from card.json)\n\n" + card_markdown(card)
        except (KeyError, TypeError, ValueError, AttributeError):
            pass  # a card.json of other fields than a packed camera's
    raise InputError(f"{path}: {why}")


def cmd_copy(args: argparse.Namespace) -> int:
    from hsicam.cli import prepare_output
    from hsicam.runs.pretrained import copy_pretrained

    prepare_output(args.dir, "dir")
    name = _bare(args.name)
    dest = copy_pretrained(name, args.dir)
    print(f"copied pre-trained camera {name} -> {dest} (a normal run folder: --run {dest})")
    return 0


def cmd_pack(args: argparse.Namespace) -> int:
    from hsicam.engine.pretrained import pack_pretrained

    target = pack_pretrained(args.run, args.name, args.dest, args.results, args.heldout, summary=args.summary,
                             preset=args.preset, overwrite=args.force)
    print(f"packed {args.run} as pre-trained camera {args.name} -> {target}")
    return 0
