"""`hsicam train`."""

from __future__ import annotations

import argparse
import logging

from hsicam.cli import add_config_args, config_from_args, run_config_from_args
from hsicam.errors import InputError

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train optics + reconstruction network jointly")
    add_config_args(p)
    p.add_argument("--out", required=True, metavar="RUN", help="run folder")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue the run from its last checkpoint")
    mode.add_argument("--restart", action="store_true",
                      help="start again in a run folder that holds no finished checkpoint (e.g. a run killed before "
                           "its first checkpoint): its files are removed first; a folder with a checkpoint is refused; "
                           "without --config it starts with the folder's own config.yaml (and --set)")
    p.set_defaults(func=cmd_train, trains=True, resume_hint="go on with: hsicam train --out {run} --resume",
                   diverged_hint="continue with a lower rate: hsicam train --out {run} --resume --set train.lr=LR "
                                 "(or start over with --restart)")


def cmd_train(args: argparse.Namespace) -> int:
    from hsicam.cli import prepare_output
    from hsicam.devices import dist_env
    from hsicam.engine.loop import check_not_an_output
    from hsicam.io import OutputLock
    from hsicam.runs.lock import RunLock

    run = prepare_output(args.out, "dir")  # refused while another training makes this new run
    check_not_an_output(run, "resume" if args.resume else "restart" if args.restart else "train")
    with RunLock(run) as lock, OutputLock(run, "train", enabled=dist_env()[0] == 0) as new_run:
        if not args.resume:
            new_run.acquire()  # a new run's folder: this process's until the loop takes it over
        if (args.resume or args.restart) and (run / "config.yaml").is_file():
            lock.acquire()  # held from the first change (a restart's removal) to the last (re-entrant in fit)
        summary = _train(args, run, new_run)
    from hsicam.devices import dist_env

    if dist_env()[0] != 0:  # under torchrun: rank 0 says it (the others hold no validation, their own throughput)
        return 0
    if summary.get("already_finished"):
        changed = ("; ".join(summary["changed"]) + ", nothing else changed" if summary.get("changed")
                   else "nothing changed")
        print(f"{run}: already finished at step {summary['step']} ({summary['epoch']} epochs); {changed}. "
              f"To train on, raise train.epochs: hsicam train --out {run} --resume --set train.epochs=N "
              f"(N > {summary['epoch']})")
    else:
        print(summary_line(summary, run))
    return 0


def _train(args: argparse.Namespace, run, new_run) -> dict:
    """The config of ``hsicam train`` (the run's own on --resume), a --restart's removal, the training
    (``new_run``, the new run's :class:`~hsicam.io.OutputLock`, is handed over to it: the loop holds
    its own until the run is in place, not for the whole training)."""
    from hsicam.engine.train import train
    from hsicam.runs.folder import check_run_dir, check_train_can_resume, restart_run_dir

    if args.resume:
        if args.config:
            raise InputError("--resume continues with the run's own config.yaml; drop --config (use --set to change keys)")
        check_run_dir(run, resume=True)  # says how to start again when there is nothing to resume
        check_train_can_resume(run)  # a fine-tuned run or a spectral prior: named, with the command that continues it
        cfg = run_config_from_args(run, args.overrides)
        if args.overrides:
            check_resume_keeps_the_run(run, cfg)
    elif args.restart and not args.config and (run / "config.yaml").is_file():
        # the run started again as it was started (it took the built-in paper config, silently), --set applied
        cfg = run_config_from_args(run, args.overrides)  # read before anything is removed: a bad one wipes nothing
        log.info("%s: starting again with its own config.yaml%s", run, " and --set" if args.overrides else "")
        restart_run_dir(run)
    else:
        cfg = config_from_args(args.config, args.overrides)  # a bad config wipes nothing
        if args.restart:
            restart_run_dir(run)
    new_run.release()
    return train(cfg, run, resume=args.resume)


def check_resume_keeps_the_run(run, cfg) -> None:
    """InputError when ``--resume --set`` would change what the run is (:data:`hsicam.config.RUN_IDENTITY_KEYS`)."""
    from hsicam.config import identity_differences

    changed = identity_differences(run_config_from_args(run), cfg)
    if changed:
        raise InputError(f"{run}: --resume may change how a run goes on (train.*, augmentation, model.consistency), not "
                         f"its bands, camera, network, scenes or split: {'; '.join(changed)}; nothing was changed. For "
                         f"another run: hsicam train --config {run / 'config.yaml'} --set … --out NEW")


def summary_line(summary: dict, run) -> str:
    """One line on a finished training; the validation part only for the metrics the summary holds."""
    epochs, steps = summary["epoch"], summary["step"]
    line = f"trained {epochs} epoch{'' if epochs == 1 else 's'} ({steps} step{'' if steps == 1 else 's'}"
    if "patches_per_s" in summary:
        line += f", {summary['patches_per_s']:.1f} patches/s"
    line += ")"
    val = [f"{name} {summary[key]:{fmt}}{unit}" for key, name, fmt, unit in
           (("val_psnr", "val PSNR", ".2f", " dB"), ("val_ssim", "SSIM", ".4f", ""), ("val_sam", "SAM", ".2f", "°"))
           if summary.get(key) is not None]
    if val:
        line += ": " + ", ".join(val)
    return f"{line} -> {run}"
