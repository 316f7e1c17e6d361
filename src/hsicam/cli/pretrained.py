"""`hsicam pretrained`: the cameras shipped with the package (list, show, copy; pack for maintainers).

    hsicam pretrained                          one line per shipped camera
    hsicam pretrained show NAME                its model card (card.md)
    hsicam pretrained copy NAME DIR            a writable run folder holding it
    hsicam pretrained pack RUN --name NAME [--results results.json] [--heldout results.json] [--force]

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
    q.add_argument("name", metavar="NAME")
    q.set_defaults(func=cmd_show)
    q = psub.add_parser("copy", help="copy a shipped camera into a normal, writable run folder")
    q.add_argument("name", metavar="NAME")
    q.add_argument("dir", metavar="DIR", help="new run folder (absent or empty)")
    q.set_defaults(func=cmd_copy)
    q = psub.add_parser("pack", help="(maintainers) pack a finished run as a shipped camera, with its card")
    q.add_argument("run", metavar="RUN", help="finished run folder")
    q.add_argument("--name", required=True, help="camera name (e.g. standard)")
    q.add_argument("--results", metavar="FILE", help="results.json of `hsicam demo` or `hsicam evaluate` on this run "
                                                     "(an evaluation of another run is refused)")
    q.add_argument("--heldout", metavar="FILE", help="results.json of an evaluation of this run on held-out data "
                                                     "(instead of --results' own held-out section)")
    q.add_argument("--summary", help="one-line summary (default: made from the run)")
    q.add_argument("--preset", help="shipped preset the run was trained from (default: the preset its config equals, "
                                    "if any; a camera that differs from it is warned about)")
    q.add_argument("--dest", metavar="DIR", help="root of the shipped cameras (default: $HSICAM_PRETRAINED_DIR, "
                                                 "else the package's resources/pretrained)")
    q.add_argument("--force", action="store_true", help="replace an existing camera of that name")
    q.set_defaults(func=cmd_pack)


def _metrics(card: dict) -> str:
    m = card.get("metrics", {})
    val = (m.get("validation") or {}).get("mean") or m.get("training_log") or {}
    if not all(isinstance(val.get(k), (int, float)) for k in ("psnr", "ssim", "sam")):
        return "val –"
    return f"val PSNR {val['psnr']:.2f} dB, SSIM {val['ssim']:.4f}, SAM {val['sam']:.2f}°"


def cmd_list(args: argparse.Namespace) -> int:
    import os

    from hsicam.runs.pretrained import ENV_VAR, available, env_root_problem, package_root, read_card, root

    names = available()
    if not names:
        problem = env_root_problem()
        if problem:
            print(f"no pre-trained cameras: {problem}")
        elif os.environ.get(ENV_VAR):
            shipped = available(package_root())
            print(f"no pre-trained cameras in {root()} ({ENV_VAR}); unset {ENV_VAR} for the cameras shipped with "
                  f"hsicam ({', '.join(shipped) if shipped else 'none'})")
        else:
            print(f"no pre-trained cameras are shipped in {root()} (set {ENV_VAR} to use another folder)")
        return 0
    for name in names:
        card = read_card(name)
        b = card.get("bands", {})
        print(f"{name}: {card.get('summary', '')} | {b.get('count', '?')} bands | {_metrics(card)}")
    print("use one with --run pretrained:NAME; `hsicam pretrained show NAME` prints its card")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from hsicam.runs.pretrained import CARD_MD, pretrained_dir

    print((pretrained_dir(args.name) / CARD_MD).read_text(encoding="utf-8"), end="")
    return 0


def cmd_copy(args: argparse.Namespace) -> int:
    from hsicam.cli import prepare_output
    from hsicam.runs.pretrained import copy_pretrained

    prepare_output(args.dir, "dir")
    dest = copy_pretrained(args.name, args.dir)
    print(f"copied pre-trained camera {args.name} -> {dest} (a normal run folder: --run {dest})")
    return 0


def cmd_pack(args: argparse.Namespace) -> int:
    from hsicam.engine.pretrained import pack_pretrained

    target = pack_pretrained(args.run, args.name, args.dest, args.results, args.heldout, summary=args.summary,
                             preset=args.preset, overwrite=args.force)
    print(f"packed {args.run} as pre-trained camera {args.name} -> {target}")
    return 0
