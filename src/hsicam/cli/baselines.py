"""`hsicam baseline ...`: what the CASSI baselines need before `hsicam evaluate --method dd-cassi-*`.

    hsicam baseline train-prior --config quick --out runs/choi-prior [--set baselines.choi.train_steps=500]
    hsicam baseline train-prior --out runs/choi-prior --resume     (an interrupted training goes on)

The learned CASSI baseline is trained by the ordinary trainer:
`hsicam train --config configs/dd_cassi_rdn.yaml --out RUN` (or any preset with
`--set camera.kind=dd_cassi`).
"""

from __future__ import annotations

import argparse

from hsicam.cli import add_config_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("baseline", help="CASSI baselines: train the spectral prior of Choi et al.")
    bsub = p.add_subparsers(dest="baseline_command", metavar="SUBCOMMAND")
    bsub.required = True
    q = bsub.add_parser("train-prior", help="train the autoencoder spectral prior (Choi et al. 2017) on the training split")
    add_config_args(q)
    q.add_argument("--out", required=True, metavar="DIR", help="prior folder (used as --run of dd-cassi-choi)")
    q.add_argument("--resume", action="store_true",
                   help="continue the prior in --out from its last checkpoint (with its own config.yaml and prior.yaml; "
                        "--set baselines.choi.train_steps=N trains a finished one longer)")
    q.set_defaults(func=cmd_train_prior, trains=True, resume_hint="go on with: hsicam baseline train-prior --out {run} --resume")


def cmd_train_prior(args: argparse.Namespace) -> int:
    from hsicam.cli import config_from_args, prepare_output
    from hsicam.engine.loop import check_not_an_output
    from hsicam.engine.prior import PRIOR_RESTART_HINT, check_prior_out, resume_config, train_prior
    from hsicam.errors import InputError
    from hsicam.runs.folder import check_run_dir

    out = prepare_output(args.out, "dir")
    check_not_an_output(out, "resume" if args.resume else "train")
    if args.resume:
        if args.config:
            raise InputError("--resume continues with the prior folder's own config.yaml and prior.yaml; drop --config "
                             "(use --set baselines.choi.train_steps=N to train it longer)")
        check_run_dir(out, True, restart_hint=PRIOR_RESTART_HINT)  # before the config: nothing to resume, weights only
        cfg, settings = resume_config(out, args.overrides)
    else:
        check_prior_out(out)  # before the config and any data: a prior in --out is named with its state
        cfg = config_from_args(args.config, args.overrides)
        settings = cfg.baselines.choi
    summary = train_prior(cfg, settings, out, resume=args.resume)
    extra = f", validation autoencoder PSNR {summary['val_psnr_autoencoder']:.2f} dB" if "val_psnr_autoencoder" in summary else ""
    if summary.get("already_finished"):
        print(f"{out}: spectral prior already finished at step {summary['step']}{extra}; nothing changed. To train it "
              f"longer: hsicam baseline train-prior --out {out} --resume --set baselines.choi.train_steps=N "
              f"(N > {summary['step']})")
        return 0
    print(f"spectral prior trained: {summary['step']} steps in {summary['elapsed_s']:.0f} s{extra} -> {out}")
    return 0
