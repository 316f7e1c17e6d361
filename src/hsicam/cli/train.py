"""`hsicam train`."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


from hsicam.cli import add_config_args
from hsicam.errors import InputError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train optics + reconstruction network jointly")
    add_config_args(p)
    p.add_argument("--out", required=True, metavar="RUN", help="run folder")
    p.add_argument("--resume", action="store_true", help="continue the run from its last checkpoint")
    p.set_defaults(func=cmd_train)


def cmd_train(args: argparse.Namespace) -> int:
    from hsicam.config import load_config
    from hsicam.engine.train import train

    run = Path(args.out)
    if args.resume:
        if args.config:
            raise InputError("--resume continues with the run's own config.yaml; drop --config (use --set to change keys)")
        if not (run / "config.yaml").is_file():
            raise InputError(f"{run}: nothing to resume (no config.yaml)")
        cfg = load_config(run / "config.yaml", args.overrides)
    else:
        cfg = load_config(args.config, args.overrides)
    summary = train(cfg, run, resume=args.resume)
    if summary.get("best_psnr") is not None:
        print(f"trained {summary['epoch']} epochs ({summary['step']} steps, {summary['patches_per_s']:.1f} patches/s): "
              f"val PSNR {summary['val_psnr']:.2f} dB, SSIM {summary['val_ssim']:.4f}, SAM {summary['val_sam']:.2f}° -> {run}")
    else:
        print(f"trained {summary['epoch']} epochs ({summary['step']} steps) -> {run}")
    return 0
