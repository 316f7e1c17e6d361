"""How many epochs of a preset fill a time box, from a short calibration run (scripts/gpu_session.sh).

    python scripts/calibrate_epochs.py CALIB/metrics.jsonl MINUTES PRESET [--set KEY=VALUE ...]

prints the epoch count on stdout (at least 2) and how it was reached on stderr. A training step is the median gap
between consecutive logged steps of the calibration's second epoch (its first also pays for start-up; calibrate with
``train.log_every_steps=1``); when steps were logged sparsely, the time over the steps between the first and last
logged ones of that epoch. A validation is what the run's end took after its last logged step. The epochs are the
demo's own (PRESET with the same overrides: its ``patches_per_epoch`` and ``batch_size``), not the calibration's.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys

from hsicam.config import load_config
from hsicam.errors import HsicamError, InputError


def seconds_per_step_and_validation(records: list[dict]) -> tuple[float, float]:
    """(s per training step, s per validation) of a calibration run's metrics.jsonl records."""
    finals = [r for r in records if r.get("final")]
    if not finals:  # a calibration that was stopped or is still running: its time per step is unknown
        raise InputError("no final record")
    final = finals[-1]
    steps = [r for r in records if "train_loss" in r]
    second = [r for r in steps if r["epoch"] >= 1] or steps
    gaps = [b["elapsed_s"] - a["elapsed_s"] for a, b in zip(second, second[1:]) if b["step"] == a["step"] + 1]
    if gaps:
        per_step = statistics.median(gaps)
    elif len(second) >= 2:  # logged sparsely: time over the steps between the logged ones, not over the lines
        per_step = (second[-1]["elapsed_s"] - second[0]["elapsed_s"]) / (second[-1]["step"] - second[0]["step"])
    else:
        per_step = final["elapsed_s"] / max(final["step"], 1)
    val_s = max(final["elapsed_s"] - steps[-1]["elapsed_s"], 0.0) if steps else 0.0
    return per_step, val_s


def _minutes(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of minutes, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("metrics", help="the calibration run's metrics.jsonl")
    ap.add_argument("minutes", type=_minutes, help="the time box of the demo's training")
    ap.add_argument("preset", help="the demo's preset (or YAML)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="the demo's config overrides (repeatable)")
    args = ap.parse_args(argv)
    try:
        with open(args.metrics, encoding="utf-8-sig") as fh:
            try:
                records = [json.loads(line) for line in fh if line.strip()]
                per_step, val_s = seconds_per_step_and_validation(records)
            except (ValueError, KeyError, TypeError, AttributeError) as exc:  # JSON, UTF-8, not a run's records
                raise InputError(f"{args.metrics}: not a finished run's metrics.jsonl ({exc})") from None
        cfg = load_config(args.preset, args.overrides)  # the demo's own config
    except (HsicamError, OSError) as exc:
        ap.error(str(exc))
    steps_per_epoch = cfg.data.patches_per_epoch // cfg.train.batch_size
    epochs = max(2, int(args.minutes * 60 / (per_step * steps_per_epoch + val_s)))
    print(epochs)
    print(f"calibration: {per_step:.4f} s per step, {val_s:.1f} s per validation, {steps_per_epoch} steps per epoch "
          f"-> {epochs} epochs in {args.minutes:g} min", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
