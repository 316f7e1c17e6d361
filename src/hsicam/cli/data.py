"""`hsicam data ...` commands (filled in by the data issue)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("data", help="hyperspectral datasets: generate, show")
    p.add_subparsers(dest="data_command", metavar="ACTION")
