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

from timing import hsicam_command, median_time, positive_int

#: JSON key -> (the ``hsicam`` arguments timed, the exit code they must end with: 2 for the usage error).
CASES = {
    "help_s": (["--help"], 0),
    "psf_help_s": (["psf", "--help"], 0),
    "evaluate_help_s": (["evaluate", "--help"], 0),
    "experiment_help_s": (["experiment", "--help"], 0),
    "usage_error_s": (["train"], 2),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed runs of each command (>= 1)")
    args = parser.parse_args()
    command = hsicam_command()
    result: dict[str, object] = {"python": platform.python_version(), "repeats": args.repeats,
                                 "command": " ".join(command)}
    cases = {key: ([*command, *argv], code) for key, (argv, code) in CASES.items()}
    cases["torch_import_s"] = ([sys.executable, "-c", "import torch"], 0)
    for key, (argv, code) in cases.items():
        # One untimed run (the warm-up) must end as the command should: a CLI that crashes at start-up exits
        # quickly, and timing it would report a fast, passing start-up.
        proc = subprocess.run(argv, capture_output=True, text=True)
        if proc.returncode != code:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [""]
            result["error"] = f"{' '.join(argv)} exited {proc.returncode}, expected {code}: {tail[0]}"
            print(json.dumps(result, indent=2))
            print(f"bench_cli: {result['error']}", file=sys.stderr)
            return 1
        result[key] = round(median_time(lambda argv=argv: subprocess.run(argv, capture_output=True),
                                        repeats=args.repeats), 3)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
