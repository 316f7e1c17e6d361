"""`hsicam demo`: the README's main job (grows with the project)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on the embedded default data")
    p.add_argument("--out", default="runs/demo", metavar="DIR")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    raise NotImplementedError
