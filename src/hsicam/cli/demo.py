"""`hsicam demo`: the README's main job.

Generate (or reuse) the embedded synthetic dataset, train the CPU ``quick`` preset (resuming an
interrupted run, reusing a finished one), reconstruct the validation scenes, print PSNR / SSIM /
SAM and write figures and tables into ``--out``.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from hsicam.cli import add_config_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="train the quick preset on the embedded data and report its numbers")
    add_config_args(p)
    p.add_argument("--out", default="runs/demo", metavar="DIR")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    import torch

    from hsicam.cli.camera import write_psf_outputs
    from hsicam.config import load_config
    from hsicam.data.datasets import SceneDataset, list_scenes, split_scenes
    from hsicam.data.pipeline import dataset_root
    from hsicam.engine.checkpoint import load_run
    from hsicam.engine.evaluate import (TestNoise, demosaic_reference, evaluate_method, evaluate_scenes, format_table,
                                        grey_reference, summarize)
    from hsicam.engine.experiments import is_finished
    from hsicam.engine.train import train
    from hsicam.io import write_json
    from hsicam.report.camera import plot_cfa, plot_doe_heights
    from hsicam.report.reconstruction import plot_reconstructions, plot_training_curves

    t0 = time.perf_counter()
    out = Path(args.out)
    run = out / "run"
    cfg = load_config(args.config or "quick", args.overrides)
    if is_finished(run):
        print(f"[demo] reusing the trained run in {run}")
    else:
        resume = (run / "config.yaml").is_file()
        print(f"[demo] {'resuming' if resume else 'training'} the camera in {run} "
              f"({cfg.train.epochs} epochs × {cfg.data.patches_per_epoch} patches of {cfg.data.patch_px} px)")
        train(load_config(run / "config.yaml", args.overrides) if resume else cfg, run, resume=resume)

    cfg, model = load_run(run)
    bands = cfg.bands.to_bands()
    root = dataset_root(cfg.data, bands)
    train_list, val = split_scenes(list_scenes(root), cfg.data.val_fraction, cfg.data.split_seed)
    scenes = SceneDataset(val, bands)
    results = evaluate_scenes(model, scenes, [p.stem for p in val], seed=cfg.train.seed)
    references = [grey_reference(model, SceneDataset(train_list, bands))]
    if model.demosaic_input:
        references.append(demosaic_reference(model))
    summary = summarize(results)
    summary["references"] = [
        {"method": ref.name, "mean": summarize(evaluate_method(ref, scenes, [p.stem for p in val],
                                                               TestNoise(seeds=(cfg.train.seed,)), keep_arrays=False))["mean"]}
        for ref in references
    ]
    summary["run"] = str(run)
    summary["region"] = "sensor area of each scene (scene minus the kernel margin), valid mode"
    write_json(out / "results.json", summary)
    table = format_table(summary)
    (out / "results.md").write_text(f"Validation scenes, {summary['conventions']['psnr']}; SSIM {summary['conventions']['ssim']}; "
                                    f"SAM in degrees.\n\n{table}\n\nReferences without a network:\n\n"
                                    + "".join(f"- {r['method']}: {_means(r['mean'])}\n" for r in summary["references"]),
                                    encoding="utf-8")
    write_psf_outputs(model.camera, out)
    with torch.no_grad():
        plot_cfa(model.camera.cfa.tile().numpy(), bands, out / "cfa.png")
        optics = model.camera.optics
        q = optics.pupil_oversample
        plot_doe_heights(optics.doe.heights().numpy(), optics.amplitude[::q, ::q].numpy(), optics.cell_m * 1e6, out / "doe.png")
    plot_reconstructions(results, bands, out / "reconstructions.png")
    plot_training_curves(run / "metrics.jsonl", out / "training.png")
    m = summary["mean"]
    print(table)
    print(f"[demo] validation mean: {_means(m)} ({len(results)} scenes; {time.perf_counter() - t0:.0f} s)")
    for r in summary["references"]:
        print(f"[demo] reference without a network, {r['method']}: {_means(r['mean'])}")
    print(f"[demo] figures and tables in {out}: reconstructions.png, psf.png, cfa.png, doe.png, training.png, results.md")
    return 0


def _means(m: dict) -> str:
    return f"PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, SAM {m['sam']:.2f}°"
