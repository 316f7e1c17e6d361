"""Command-line start-up benchmark: prints one JSON object.

The seconds from starting ``hsicam`` to its exit, for what a user types before any work: ``hsicam --help``,
a command's ``--help`` (``psf``; ``evaluate`` and ``experiment``, whose help lists the method and experiment
registries' names, read torch-free from ``hsicam.engine.names``: about ``help_s`` now, ~1.8 s when they
loaded torch) and a usage error (``train`` without ``--out``). Each is the median of ``--repeats`` runs of the
installed console script (the ``hsicam`` beside this Python), so it includes the interpreter's own start.
``torch_import_s``: a bare ``import torch`` in the same way, what every command that works pays on top.

Usage: python benchmarks/bench_cli.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path

from timing import median_time

CASES = {
    "help_s": ["--help"],
    "psf_help_s": ["psf", "--help"],
    "evaluate_help_s": ["evaluate", "--help"],
    "experiment_help_s": ["experiment", "--help"],
    "usage_error_s": ["train"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    script = Path(sys.executable).with_name("hsicam")
    command = [str(script)] if script.is_file() else [sys.executable, "-m", "hsicam"]
    result: dict[str, object] = {"python": platform.python_version(), "repeats": args.repeats,
                                 "command": " ".join(command)}
    for key, argv in CASES.items():
        result[key] = round(median_time(lambda argv=argv: subprocess.run([*command, *argv], capture_output=True),
                                        repeats=args.repeats, warmup=1), 3)
    result["torch_import_s"] = round(median_time(lambda: subprocess.run([sys.executable, "-c", "import torch"]),
                                                 repeats=args.repeats, warmup=1), 3)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
