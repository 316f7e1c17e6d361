"""Command-line interface: a thin shell over the library.

Each sub-command lives in a module of this package that defines ``register(subparsers)``; add a
module to ``COMMAND_MODULES`` to add commands. Every :class:`HsicamError` (bad config, bad file,
bad argument) is printed as one line and exits with code 2, without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import Sequence

from hsicam.errors import HsicamError

COMMAND_MODULES = (
    "hsicam.cli.camera",
    "hsicam.cli.data",
    "hsicam.cli.train",
    "hsicam.cli.reconstruct",
    "hsicam.cli.evaluate",
    "hsicam.cli.demo",
    "hsicam.cli.baselines",
    "hsicam.cli.fabrication",
)


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors reported as one line, exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"hsicam: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hsicam", description="Learned snapshot hyperspectral cameras: design, simulate, train, use.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def add_config_args(p: argparse.ArgumentParser) -> None:
    """The ``--config FILE`` and repeatable ``--set key=value`` options shared by commands."""
    p.add_argument("--config", metavar="FILE", help="YAML config (default: built-in paper camera)")
    p.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
                   help="dotted override, e.g. camera.doe.enabled=false (repeatable)")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s")
    try:
        return int(args.func(args) or 0)
    except HsicamError as exc:
        print(f"hsicam: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hsicam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
