"""`hsicam demo`: the README's main job (:mod:`hsicam.engine.demo`); this module only prints."""

from __future__ import annotations

import argparse
import time

from hsicam.cli import add_config_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="train the quick preset on the embedded data and report its numbers")
    add_config_args(p)
    for action in p._actions:  # the demo's default config is the quick preset (engine.demo.demo_config)
        if "--config" in action.option_strings:
            action.help = "YAML config or preset name (default: the quick preset)"
    p.add_argument("--out", default="runs/demo", metavar="DIR",
                   help="demo folder (default runs/demo): the trained run in DIR/run, results.json, results.md and "
                        "the figures")
    p.set_defaults(func=cmd_demo, trains=True, scores=True, resume_hint="run the same hsicam demo command again: it resumes the run")


def cmd_demo(args: argparse.Namespace) -> int:
    from hsicam.cli import prepare_output
    from hsicam.engine.demo import check_demo_folder, demo_config, means_line, run_demo
    from hsicam.engine.experiments import check_same_training, is_finished
    from hsicam.runs.checkpoint import weights_text

    t0 = time.perf_counter()
    out = prepare_output(args.out, "dir")  # before any work; never a shipped camera (the demo writes in place)
    check_demo_folder(out)
    cfg = demo_config(args.config, tuple(args.overrides))
    run = out / "run"
    check_same_training(run, cfg)  # before saying what it will do with the run
    if is_finished(run):
        print(f"[demo] reusing the trained run in {run}")
    else:
        resume = (run / "config.yaml").is_file()
        print(f"[demo] {'resuming' if resume else 'training'} the camera in {run} "
              f"({cfg.train.epochs} epochs × {cfg.data.patches_per_epoch} patches of {cfg.data.patch_px} px)")
    summary = run_demo(cfg, out)
    print(summary["table"])
    print(f"[demo] validation mean: {means_line(summary['mean'])} ({summary['n_scenes']} scenes; "
          f"{time.perf_counter() - t0:.0f} s)")
    if summary.get("weights"):
        print(f"[demo] {weights_text(summary['weights'])}")
    for r in summary["references"]:
        print(f"[demo] reference, {r['method']}: {means_line(r['mean'])}")
    if "heldout" in summary:
        h = summary["heldout"]
        print(f"[demo] {h['data']}, {len(h['scenes'])} scenes: {means_line(h['mean'])}")
        for r in h["references"]:
            print(f"[demo] held-out reference, {r['method']}: {means_line(r['mean'])}")
    from hsicam.engine.demo import FIGURES

    shown = ", ".join(name for name in (*FIGURES, "results.md") if (out / name).is_file())
    print(f"[demo] figures and tables in {out}: {shown}")
    return 0
