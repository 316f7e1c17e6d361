"""`hsicam baseline ...`: what the CASSI baselines need before `hsicam evaluate --method dd-cassi-*`.

    hsicam baseline train-prior --config quick --out runs/choi-prior [--set baselines.choi.train_steps=500]

The learned CASSI baseline is trained by the ordinary trainer:
`hsicam train --config configs/dd_cassi_rdn.yaml --out RUN` (or any preset with
`--set camera.kind=dd_cassi`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hsicam.cli import add_config_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("baseline", help="CASSI baselines: train the spectral prior of Choi et al.")
    bsub = p.add_subparsers(dest="baseline_command", metavar="SUBCOMMAND")
    bsub.required = True
    q = bsub.add_parser("train-prior", help="train the autoencoder spectral prior (Choi et al. 2017) on the training split")
    add_config_args(q)
    q.add_argument("--out", required=True, metavar="DIR", help="prior folder (used as --run of dd-cassi-choi)")
    q.set_defaults(func=cmd_train_prior)


def cmd_train_prior(args: argparse.Namespace) -> int:
    from hsicam.cli import config_from_args
    from hsicam.engine.prior import train_prior
    from hsicam.cli import prepare_output

    prepare_output(args.out, "dir")
    cfg = config_from_args(args.config, args.overrides)
    summary = train_prior(cfg, cfg.baselines.choi, Path(args.out))
    extra = f", validation autoencoder PSNR {summary['val_psnr_autoencoder']:.2f} dB" if "val_psnr_autoencoder" in summary else ""
    print(f"spectral prior trained: {summary['step']} steps in {summary['elapsed_s']:.0f} s{extra} -> {args.out}")
    return 0
