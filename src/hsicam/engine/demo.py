"""The README's main job (``hsicam demo``): train the CPU preset on the embedded data (or resume or
reuse the run), reconstruct the validation scenes, score them against network-free references (and
the network alone where a consistency step follows it), and write tables and figures."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

from hsicam.config import Config, check_list_keys, load_config
from hsicam.data.datasets import scene_names
from hsicam.data.pipeline import scene_dataset, split_dataset
from hsicam.engine.evaluate import (HELDOUT_NOISE_SET, TestNoise, config_hash_of, demosaic_reference, evaluate_method, evaluate_scenes,
                                    format_table, grey_reference, heldout_sources_label, scored_region,
                                    summarize, validation_data_label)
from hsicam.engine.experiments import check_same_training, ensure_trained, heldout_scenes
from hsicam.engine.methods import (LINEAR_REFERENCE_WINDOW, linear_demosaic_reference, network_alone_reference,
                                   network_skip)
from hsicam.engine.provenance import commit_label, software_record
from hsicam.errors import InputError
from hsicam.io import (OutputLock, atomic_open, clear_complete, clear_derived, cleanup_stale_temporaries, is_complete,
                       is_temporary, mark_complete, output_description, read_marker, write_json)
from hsicam.report.camera import write_optics_figures, write_psf_outputs
from hsicam.report.reconstruction import plot_reconstructions, plot_training_curves
from hsicam.runs.checkpoint import weights_identity, weights_text
from hsicam.runs.folder import load_run

log = logging.getLogger(__name__)

FIGURES = ("reconstructions.png", "psf.png", "cfa.png", "doe.png", "training.png")


def means_line(m: dict) -> str:
    """"PSNR … dB, SSIM …, SAM …°" of a mean-metrics dict."""
    return f"PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, SAM {m['sam']:.2f}°"


def check_demo_folder(out: str | Path) -> None:
    """InputError unless ``out`` may receive a demo: absent, empty, a finished demo (its completion
    marker) or an interrupted one (its ``run/``). Creates nothing; call it before any work."""
    out = Path(out)
    if not out.is_dir() or not any(not is_temporary(p.name) for p in out.iterdir()):
        return
    if is_complete(out):
        if read_marker(out).get("command") in (None, "demo"):  # an older demo's marker names no command
            return
        raise InputError(f"{out}: holds {output_description(out)}, not a demo; choose another --out")
    if not (out / "run").is_dir():
        raise InputError(f"{out}: folder exists and is not empty, and is not a demo folder (no run/ in it); "
                         "choose another --out")


def _made_by(cfg: Config, run: Path, summary: dict) -> str:
    """results.md's line on how its table was made and is made again: the run, its config and weights, the scenes and
    the test noise's seed, the software (session 74's records hunt: the demo's results.md said none of it)."""
    d = cfg.data
    data = (f"the synthetic set (data.synthetic_seed {d.synthetic_seed}, {d.synthetic_n} scenes of {d.synthetic_size} px, "
            f"split seed {d.split_seed})" if d.root is None else f"the scenes of {d.root}")
    sw = summary.get("software") or {}
    return (f"Made by `hsicam demo`: the run {run} (its config.yaml, config hash {summary.get('config_hash')}; weights "
            f"sha256 {str(summary.get('weights_sha256'))[:12]}…, train.seed {cfg.train.seed}), scored on the validation "
            f"split of {data}, test-noise seed {TestNoise().seeds[0]}; hsicam {sw.get('hsicam') or 'source'} "
            f"({commit_label(sw)}), torch {sw.get('torch')}, {sw.get('threads')} thread(s). The same table: "
            f"`hsicam evaluate --run {run} --out DIR`.")


def run_demo(cfg: Config, out: str | Path) -> dict[str, Any]:
    """Train (or resume, or reuse) ``out/run`` with ``cfg``, evaluate and write ``out``'s results.

    Returns the summary written to ``out/results.json`` plus ``status`` (trained / resumed /
    reused) and ``table`` (Markdown). An existing ``out/run`` started with another config is an
    :class:`InputError` (``ensure_trained``), never silently reused.
    """
    out = Path(out)
    # one demo at a time per folder, from its checks to its marker: a second one reusing the run while the first
    # scored it switched the kept weights under it (results naming one checkpoint and scoring another)
    out.parent.mkdir(parents=True, exist_ok=True)  # the lock file lies beside the folder: without a parent, no lock
    with OutputLock(out, "demo") as lock:
        lock.acquire()
        return _run_demo(cfg, out)


def _run_demo(cfg: Config, out: Path) -> dict[str, Any]:
    check_demo_folder(out)
    run = out / "run"
    check_same_training(run, cfg)  # refused before any change
    if out.is_dir():
        clear_derived(out)  # a report/ of its old results would stand beside the new ones
        # before the run is touched: a reuse that switches its kept weights or refits its step, interrupted, left a
        # finished folder whose results no longer matched its run
        clear_complete(out)
        cleanup_stale_temporaries(out)  # a figure or table of a killed demo, half-written
    status = ensure_trained(run, cfg)
    asked = cfg
    cfg, model = load_run(run)  # its model.consistency is the demo's (ensure_trained)
    scored = weights_identity(run)  # what is scored below, recorded
    bands = cfg.bands.to_bands()
    train_list, val = split_dataset(cfg.data, bands)
    scenes, names = scene_dataset(cfg.data, val, bands), scene_names(val)  # as evaluate names them (unique)
    # the test noise of `hsicam evaluate`'s first seed (0), whatever train.seed: runs of other seeds are scored on the
    # same draws, and the demo's figures are `hsicam evaluate --run RUN`'s (train.seed chose them before session 60)
    seed = TestNoise().seeds[0]
    results = evaluate_scenes(model, scenes, names, seed=seed)
    train_scenes = scene_dataset(cfg.data, train_list, bands)
    references = [grey_reference(model, train_scenes)]
    if model.consistency_on:
        references.append(network_alone_reference(model))
    try:
        references.append(demosaic_reference(model))
        skip = network_skip(model.net)
        if skip is not None and skip.demosaic_kernel == "tent":  # the network's own start, network-free
            references.append(demosaic_reference(model, "tent", skip.demosaic_window))
        # the best linear map: the linear step's own W when the run has one (fitted on these scenes), else fitted now
        own = model.linear_step
        own = own if own is not None and own.shape[-1] == LINEAR_REFERENCE_WINDOW else None
        references.append(linear_demosaic_reference(model, train_scenes, weight=own))
    except ValueError:  # a camera without a per-band sensor code (CASSI)
        pass
    summary = summarize(results)
    summary["references"] = [
        {"method": ref.name,
         "mean": summarize(evaluate_method(ref, scenes, names, TestNoise(seeds=(seed,)), keep_arrays=False))["mean"]}
        for ref in references
    ]
    # as many held-out scenes as the demo asks (data.heldout_n, a runtime key: a reused run's own count was scored)
    held_cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, heldout_n=asked.data.heldout_n))
    held = heldout_scenes(held_cfg)
    if held is not None:  # the same camera on scenes of spectral sources the training never saw
        h_results = evaluate_scenes(model, held[0], held[1], seed=seed, keep_arrays=False,
                                    scene_set=HELDOUT_NOISE_SET)
        summary["heldout"] = {
            "data": heldout_sources_label(held_cfg),
            **summarize(h_results),
            "references": [{"method": ref.name, "mean": summarize(evaluate_method(
                ref, held[0], held[1], TestNoise(seeds=(seed,)), keep_arrays=False,
                scene_set=HELDOUT_NOISE_SET))["mean"]}
                for ref in references],
        }
    summary["run"] = str(run)
    # as `hsicam evaluate` records them: the folder read (`hsicam report` finds the camera from anywhere), the
    # method and the scenes
    summary.update(run_path=str(run.resolve()), method="doe-learned",
                   data=validation_data_label(cfg))
    # which weights and config were scored, as `hsicam evaluate` records them (`hsicam pretrained pack --results`
    # checks them: a run trained on since, or another demo's run of the same relative path, is not these)
    summary.update(scored)  # weights_sha256, and the last step's or the best validation's checkpoint (a selection)
    summary["config_hash"] = config_hash_of(cfg)
    kept = scored.get("weights")
    summary["region"] = scored_region(model.camera)  # as `hsicam evaluate` says it (a `--set camera.boundary=same` demo: the whole scene)
    summary["software"] = software_record("cpu")  # what scored (session 74's records hunt: the demo's said none)
    write_json(out / "results.json", summary)
    table = format_table(summary)
    with atomic_open(out / "results.md", "w", encoding="utf-8") as fh:
        fh.write(f"Validation scenes, {summary['conventions']['psnr']}; SSIM {summary['conventions']['ssim']}; "
                 f"SAM in degrees.{' ' + weights_text(kept) if kept else ''}\n\n{_made_by(cfg, run, summary)}\n\n"
                 f"{table}\n\nReferences:\n\n"
                 + "".join(f"- {r['method']}: {means_line(r['mean'])}\n" for r in summary["references"])
                 + (f"\nOn {summary['heldout']['data']}:\n\n{format_table(summary['heldout'])}\n\n"
                    "References on these scenes:\n\n"
                    + "".join(f"- {r['method']}: {means_line(r['mean'])}\n" for r in summary["heldout"]["references"])
                    if "heldout" in summary else ""))
    if model.camera.kind == "doe":
        write_psf_outputs(model.camera, out, design=True)  # the element doe.png draws (σ_p left out, said)
        write_optics_figures(model.camera, out)
    plot_reconstructions(results, bands, out / "reconstructions.png")
    plot_training_curves(run / "metrics.jsonl", out / "training.png", cfg.train.loss_formula())
    mark_complete(out, {"command": "demo"})
    return {**summary, "status": status, "table": table, "n_scenes": len(results)}


def demo_config(config: str | Path | None, overrides: tuple[str, ...]) -> Config:
    """The demo's config: ``config`` (default the ``quick`` preset) with ``overrides`` (an empty item in a list of
    the file refused: :func:`hsicam.config.check_list_keys`)."""
    cfg = load_config(config or "quick", list(overrides))
    check_list_keys(cfg, config or "quick")
    return cfg
