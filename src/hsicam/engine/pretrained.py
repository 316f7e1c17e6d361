"""Packing a finished run as a shipped pre-trained camera, with its model card.

``pack_pretrained(RUN, NAME)`` copies the run's ``config.yaml`` and kept weights into
``ROOT/NAME/`` (ROOT: :func:`hsicam.runs.pretrained.root`) and writes the card: ``card.json``
(:func:`card_fields`) and ``card.md`` (:func:`card_markdown`, the one place the card's text is
made). Everything in the card is read from the run (config, ``metrics.jsonl``, weights) and from
an optional ``results.json`` of ``hsicam demo`` / ``hsicam evaluate``; nothing is typed in.

A results.json must be an evaluation of the run being packed (:func:`check_results_of_run`: the
weights' sha256 when it records one, else its config hash and the run folder it names) with no test
noise beyond the run's own (:func:`check_results_noise`), and a
``preset`` given by hand must be a shipped preset's name (:func:`check_preset`, which warns when the
run's camera differs from that preset's).
"""

from __future__ import annotations

import datetime
import json
import logging
from pathlib import Path
from typing import Any

from hsicam.config import camera_files, dump_yaml, load_config, with_values
from hsicam.engine.provenance import commit_label, running_version, source_state
from hsicam.errors import InputError
from hsicam.io import (COMPLETE_MARKER, atomic_open, atomic_output, copy_file, is_complete, json_number, mark_complete,
                       nan_for_null, same_path, write_json)
from hsicam.runs import pretrained as shipped
from hsicam.runs.camera_files import check_camera_files, copy_name, write_camera_files
from hsicam.runs.checkpoint import root_weights_path
from hsicam.io import file_sha256
from hsicam.runs.folder import EMPTY_RUN_CONFIG, MetricsLog, check_is_run, load_run
from hsicam.runs.linear_step import LINEAR_STEP_FILE
from hsicam.runs.measured_psf import MEASURED_PSF_FILE

log = logging.getLogger(__name__)

CARD_FORMAT = "hsicam-pretrained-card-1"
METRICS = ("psnr", "ssim", "sam")
#: The evaluation method of a run's own network (``hsicam evaluate --method``); results of another
#: method (a network-free reference through the run's optics, a baseline) are not the camera's numbers.
LEARNED_METHOD = "doe-learned"


# ------------------------------------------------------------------------------------------------
# Reading the run and its results
# ------------------------------------------------------------------------------------------------
def _records(run_dir: Path) -> list[dict[str, Any]]:
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        raise InputError(f"{run_dir}: no metrics.jsonl: not a finished run (train it first)")
    return MetricsLog(path).read()


def training_seconds(run_dir: Path) -> float | None:
    """Wall time the kept steps of a run took, over all its sessions (s): each session's
    ``elapsed_s`` counts from its own start, so its ``session`` record (or, in logs from before
    those, a drop) marks a resume and the sessions' last values add up. None when the log has no times."""
    total, last = 0.0, None
    for r in _records(run_dir):
        if "session" in r and last is not None:  # a resume: its times count from 0 again, however slow its start
            total, last = total + last, None
        e = r.get("elapsed_s")
        if not isinstance(e, (int, float)):
            continue
        if last is not None and e < last:
            total += last
        last = float(e)
    return None if last is None else total + last


def final_record(run_dir: Path) -> dict[str, Any]:
    """The run's final ``metrics.jsonl`` record (written when training finished); InputError otherwise."""
    final = [r for r in _records(run_dir) if r.get("final")]
    if not final:
        raise InputError(f"{run_dir}: the run has not finished (no final record in metrics.jsonl); "
                         f"finish it with `hsicam train --resume --out {run_dir}` before packing")
    return final[-1]


def _means(block: Any, source: Path, what: str, sam_undefined: Any = None) -> dict[str, float]:
    """``{psnr, ssim, sam}`` of a results.json ``mean`` block; one-line InputError unless each is a finite
    number (JSON ``NaN``/``Infinity`` included: a card does not cite a score that is no number).
    ``sam_undefined``: the file's list of scenes without a spectral angle (truth zero at every scored pixel)."""
    if not isinstance(block, dict) or not all(json_number(block.get(k), finite=False) for k in METRICS):
        raise InputError(f"{source}: {what} has no mean PSNR/SSIM/SAM as numbers (not a results.json of "
                         "`hsicam demo` or `hsicam evaluate`)")
    bad = [k for k in METRICS if not json_number(block[k])]
    if bad == ["sam"] and sam_undefined:
        raise InputError(f"{source}: {what} has no mean SAM: the spectral angle is undefined on every scene (the "
                         f"truth is zero at every scored pixel: {', '.join(map(str, sam_undefined))}); a card cites "
                         "scores of scenes with light: evaluate the run on other scenes")
    if bad:
        raise InputError(f"{source}: {what} has a mean {'/'.join(k.upper() for k in bad)} that is not a finite "
                         f"number ({', '.join(f'{k}: {block[k]}' for k in bad)}); a card cites finite scores only: "
                         "evaluate the run again")
    return {k: float(block[k]) for k in METRICS}


def _references(entries: Any, source: Path) -> list[dict[str, Any]]:
    if entries is None:
        return []
    if not isinstance(entries, list):
        raise InputError(f"{source}: 'references' is not a list")
    return [{"method": str(r.get("method")), "mean": _means(r.get("mean"), source, f"reference {r.get('method')!r}")}
            for r in entries if isinstance(r, dict)]


def _read_results(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such results file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable results.json ({getattr(exc, 'msg', None) or exc})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: unreadable results.json (not a JSON object)")
    return nan_for_null(data)  # a mean written as null (not finite: an undefined SAM) is NaN again


def _scene_block(data: dict[str, Any], source: Path, data_label: str) -> dict[str, Any]:
    scenes = data.get("scenes")
    if scenes is not None and not isinstance(scenes, list):
        raise InputError(f"{source}: 'scenes' is not a list (got {type(scenes).__name__}; not a results.json of "
                         "`hsicam demo` or `hsicam evaluate`)")
    trained_on = [r.get("name", "?") for r in scenes or () if isinstance(r, dict) and r.get("split") == "train"]
    if trained_on:  # evaluate marks the scenes the run trained on (its data.json)
        raise InputError(f"{source}: {len(trained_on)} of its {len(scenes)} scenes were training scenes of the run "
                         f"({', '.join(map(str, trained_on[:3]))}{', …' if len(trained_on) > 3 else ''}): their scores "
                         "are not a validation, and a card cites none of them")
    return {"source": str(source), "data": str(data.get("data") or data_label),
            "n_scenes": len(scenes or []),
            "mean": _means(data.get("mean"), source, "'mean'", data.get("sam_undefined")),
            "references": _references(data.get("references"), source)}


def results_metrics(results: str | Path | None, heldout: str | Path | None = None,
                    run_dir: str | Path | None = None) -> dict[str, Any]:
    """Validation and held-out-sources means (and the network-free references) of a results.json.

    ``results``: a results.json of ``hsicam demo`` or ``hsicam evaluate`` (keys ``mean``,
    ``references``, ``heldout``). ``heldout``: a results.json of an evaluation on held-out data,
    used instead of ``results``' own ``heldout`` section. With ``run_dir``, each file must be an
    evaluation of that run (:func:`check_results_of_run`)."""
    from hsicam.engine.evaluate import is_validation_data_label

    out: dict[str, Any] = {"validation": None, "heldout": None}
    if results is not None:
        data = _read_results(results)
        scored = data.get("data")
        if not is_validation_data_label(scored):
            # `evaluate --data DIR`: any scenes, the training ones included (a synthetic folder records no split)
            raise InputError(f"{results}: an evaluation of the scenes in {scored} (--data), not of the run's validation "
                             "split: the card's validation figures are those of the scenes its training held out; "
                             "evaluate it without --data (`hsicam evaluate --run RUN --out DIR`) and pass DIR/results.json")
        # the file's own fields first: a file refused for them is refused before any "cited as given" warning
        out["validation"] = _scene_block(data, Path(results), "validation scenes")
        if isinstance(data.get("heldout"), dict):
            out["heldout"] = _scene_block(data["heldout"], Path(results), "held-out spectral sources")
        if run_dir is not None:
            check_results_of_run(data, Path(results), Path(run_dir), "--results")
    if heldout is not None:
        data = _read_results(heldout)
        out["heldout"] = _scene_block(data.get("heldout") if isinstance(data.get("heldout"), dict) else data,
                                      Path(heldout), "held-out data")
        if run_dir is not None:
            check_results_of_run(data, Path(heldout), Path(run_dir), "--heldout")
    return out


def run_config_hash(run_dir: Path) -> str:
    """The config hash ``hsicam evaluate --run RUN`` records for ``run_dir`` (its config.yaml, no --set)."""
    from hsicam.config import load_config
    from hsicam.engine.evaluate import config_hash_of

    return config_hash_of(load_config(Path(run_dir) / "config.yaml"))


def _evaluated_folder(recorded: str, source: Path) -> Path | None:
    """The run folder a results.json names, if it is still there. ``hsicam evaluate`` records it
    resolved; ``hsicam demo`` as given (``OUT/run``, relative to where the demo ran, beside its
    results.json)."""
    p = Path(recorded).expanduser()
    for c in ([p] if p.is_absolute() else [source.parent / p.name, Path.cwd() / p]):  # beside it first
        if (c / "config.yaml").is_file():
            return c
    return None


#: results.json ``noise`` keys (as ``hsicam evaluate`` writes them) → the evaluate option and the
#: run config's own level of that noise.
_TEST_NOISE = {"sigma_height_nm": ("--sigma-height-nm", lambda cfg: cfg.camera.doe.sigma_height_nm, "nm"),
               "sensor_sigma": ("--sensor-sigma", lambda cfg: cfg.camera.sensor.sigma, "")}


def check_results_noise(data: dict[str, Any], source: Path, run_dir: Path, option: str = "--results") -> None:
    """One-line :class:`InputError` when the results.json ``data`` was measured under test noise
    (``hsicam evaluate --sigma-height-nm/--sensor-sigma``, recorded in its ``noise``) other than the
    noise ``run_dir``'s config gives its camera: a card's numbers are those of the camera as
    configured, and it does not say that they were measured under extra noise."""
    from hsicam.config import load_config

    noise = data.get("noise")
    if not isinstance(noise, dict):
        return
    cfg = load_config(Path(run_dir) / "config.yaml")
    extra = []
    for key, (opt, own, unit) in _TEST_NOISE.items():
        value = noise.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and float(value) != float(own(cfg)):
            extra.append(f"{opt} {value:g}{' ' + unit if unit else ''} (the camera's own: {own(cfg):g})")
    if extra:
        raise InputError(f"{source}: measured under test noise {', '.join(extra)}; a card's numbers are those of "
                         f"the camera with its own noise: evaluate without it (`hsicam evaluate --run {run_dir} --out "
                         f"DIR`, no {' / '.join(e.split(' ', 1)[0] for e in extra)}) and pass DIR/results.json as {option}")


def check_results_of_run(data: dict[str, Any], source: Path, run_dir: Path, option: str = "--results") -> None:
    """One-line :class:`InputError` unless the results.json ``data`` (read from ``source``) is an
    evaluation of the run ``run_dir`` by its own network.

    Compared: the weights' sha256 when the file records one (``weights_sha256``, as ``hsicam
    evaluate`` writes it, or ``run: {weights_sha256}``) must be ``run_dir``'s; the config hash
    (``hsicam evaluate`` records the hash of the config it evaluated: another run, a run trained on
    since, or ``--set`` overrides give another one) must equal that of ``run_dir``'s config.yaml;
    without a recorded sha256, the run folder it names must be ``run_dir`` or hold the same weights
    (a copy). A file that names no run, or a run
    that is no longer on disk, is used with a logged warning (nothing left to compare). Results
    measured under test noise other than the run's own are refused (:func:`check_results_noise`)."""
    from hsicam.engine.methods import METHOD_ALIASES

    from hsicam.config import load_config
    from hsicam.engine.methods import own_learned_method

    own = own_learned_method(load_config(Path(run_dir) / "config.yaml")) or LEARNED_METHOD  # dd-cassi-rdn for a CASSI run
    how = "" if own == LEARNED_METHOD else f" --method {own}"
    again = (f"evaluate this run (`hsicam evaluate --run {run_dir}{how} --out DIR`) and pass DIR/results.json as "
             f"{option}")
    method = data.get("method")
    if isinstance(method, str) and METHOD_ALIASES.get(method, method) != own:
        raise InputError(f"{source}: results of method {method!r}, not of the run's own network ({own}); {again}")
    check_results_noise(data, source, run_dir, option)
    recorded = data.get("run")
    rec_path = recorded.get("path") if isinstance(recorded, dict) else recorded
    rec_path = rec_path if isinstance(rec_path, str) and rec_path else None
    sha = data.get("weights_sha256") or (recorded.get("weights_sha256") if isinstance(recorded, dict) else None)
    this_sha = file_sha256(root_weights_path(run_dir))
    same_weights = isinstance(sha, str) and bool(sha)
    if same_weights and sha != this_sha:
        raise InputError(f"{source}: results of another run ({rec_path or '?'}, weights sha256 {sha[:12]}…), not of "
                         f"{run_dir} (weights sha256 {this_sha[:12]}…); {again}")
    folder = _evaluated_folder(rec_path, source) if rec_path and not same_weights else None
    same = same_weights or (folder is not None and same_path(folder, run_dir))
    recorded_hash, this_hash = data.get("config_hash"), run_config_hash(run_dir)
    if isinstance(recorded_hash, str) and recorded_hash != this_hash:
        if same:
            raise InputError(f"{source}: an evaluation of {run_dir} with another config (config hash {recorded_hash}; its "
                             f"config.yaml hashes to {this_hash}): evaluated with --set overrides, the run trained on "
                             f"since, or an older hsicam evaluated it (the hash covers every config key, defaults "
                             f"included, and keys were added since); {again} (no --set)")
        raise InputError(f"{source}: results of another run ({rec_path or '?'}, config hash {recorded_hash}), not of "
                         f"{run_dir} (config hash {this_hash}); {again}")
    if same_weights:
        return
    if rec_path is None:
        log.warning("%s: the results do not record which run they evaluated: cannot check that they are of %s; "
                    "cited as given", source, run_dir)
        return
    if folder is None:
        log.warning("%s: the run it evaluated (%s) is no longer there, so its weights cannot be compared with %s's%s; "
                    "cited as given", source, rec_path, run_dir,
                    " (the config hashes match)" if isinstance(recorded_hash, str) else "")
        return
    if same:
        return
    other = root_weights_path(folder)
    other_sha = file_sha256(other) if other.is_file() else None
    if other_sha != this_sha:
        raise InputError(f"{source}: results of another run ({folder}, weights sha256 "
                         f"{other_sha[:12] + '…' if other_sha else 'missing'}), not of {run_dir} (weights sha256 "
                         f"{this_sha[:12]}…); {again}")


def check_preset(preset: str, cfg, run_dir: Path) -> str:
    """``preset`` when it names a shipped preset (:func:`hsicam.config.preset_names`), else a
    one-line :class:`InputError` listing them. Logs a warning when the run's camera (``camera.*``,
    ``bands.*``) differs from that preset's: the card would name a preset the camera was not made from."""
    from hsicam.config import load_config, preset_names, training_differences

    names = preset_names()
    if preset not in names:
        raise InputError(f"--preset {preset!r}: not a shipped preset (presets: {', '.join(names)}); give the preset "
                         f"{run_dir} was trained from, or leave --preset out (the card then names the preset its "
                         "config equals, if any)")
    diffs = [d for d in training_differences(cfg, load_config(preset), limit=10**6) if d.startswith(("camera.", "bands."))]
    if diffs:
        log.warning("%s: its camera differs from preset %r in %d setting(s) (run → preset: %s%s); the card names %r "
                    "as the preset it was trained from: leave --preset out unless it was", run_dir, preset, len(diffs),
                    "; ".join(diffs[:4]), "; …" if len(diffs) > 4 else "", preset)
    return preset


def matching_preset(cfg) -> str | None:
    """The shipped preset whose resolved config equals ``cfg`` (None: a config of its own)."""
    from hsicam.config import PRESETS_DIR, dump_yaml, load_config

    text = dump_yaml(cfg)
    for p in sorted(PRESETS_DIR.glob("*.yaml")):
        try:
            if dump_yaml(load_config(p)) == text:
                return p.stem
        except InputError:  # pragma: no cover - a preset that does not load is another test's failure
            continue
    return None


def _training_data(cfg, run_dir: Path) -> dict[str, Any]:
    d = cfg.data
    if d.root is not None:
        return {"kind": "folder", "root": str(d.root), "note": "the maintainer's own scene folder (data.root)"}
    from hsicam.data.spectral_sources import SOURCES, parse_holdout
    from hsicam.data.synthetic import GENERATOR_VERSION
    from hsicam.engine.provenance import started_before_session_60, trained_generator_version
    from hsicam.runs.folder import MetricsLog

    version = trained_generator_version(run_dir)  # the run's own (recorded since session 60)
    if version is None:
        if started_before_session_60(run_dir):
            why = "a run of an hsicam before session 60"
        elif not MetricsLog(Path(run_dir) / "metrics.jsonl", enabled=False).first_line_whole():
            why = "its metrics.jsonl's first line, the record of the session that started it, is torn or blank"
        else:
            why = "the record of the session that started it does not say"
        log.warning("%s does not record the synthetic-data generator version it trained on (%s): the card names this "
                    "hsicam's, version %d", run_dir, why, GENERATOR_VERSION)
        version = GENERATOR_VERSION
    held = list(parse_holdout(d.holdout_sources))
    return {"kind": "embedded synthetic generator", "generator_version": version,
            "scenes": d.synthetic_n, "scene_px": d.synthetic_size, "seed": d.synthetic_seed,
            "validation_fraction": d.val_fraction, **({"validation_pool": d.val_pool} if d.val_pool is not None else {}),
            "holdout_sources": held,
            "sources": [{"id": s.id, "role": s.role, "origin": s.origin}
                        for s in SOURCES.values() if s.id not in held]}


# ------------------------------------------------------------------------------------------------
# The card
# ------------------------------------------------------------------------------------------------
def consistency_summary(c) -> str:
    """What the measurement-consistency steps of ``c`` (:class:`hsicam.config.ConsistencyConfig`, on) do,
    in words for the model card."""
    def landweber(n: int) -> str:
        priors = ([f"a spectral prior (α = {c.spectral_prior:g})"] if c.spectral_prior else []) + \
                 ([f"a TV prior (w = {c.tv_weight:g})"] if c.tv_weight else [])
        return f"{n} Landweber step{'s' if n != 1 else ''}" + (" with " + " and ".join(priors) if priors else "")

    if c.kind == "linear":
        text = (f"{c.iterations} linear measurement-consistency step{'s' if c.iterations != 1 else ''} "
                f"(gain {c.gain:g}, {c.window_px} px filters)")
        return text + (f", then {landweber(c.landweber_after)}" if c.landweber_after else "")
    return f"{landweber(c.iterations)} of measurement consistency"


def card_fields(run_dir: str | Path, name: str, results: str | Path | None = None, heldout: str | Path | None = None,
                *, summary: str | None = None, preset: str | None = None) -> dict[str, Any]:
    """The machine-readable model card (``card.json``) of the finished run ``run_dir`` packed as ``name``."""
    import torch

    run_dir = Path(run_dir)
    final = final_record(run_dir)
    cfg, model = load_run(run_dir)
    for key, t in model.state_dict().items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise InputError(f"{run_dir}: NaN/Inf in the weights ({key}); nothing packed")
    missing = model.missing_linear_step()
    if missing:
        raise InputError(f"{missing}; nothing packed (a shipped camera could not reconstruct)")
    bands = model.camera.bands
    weights = root_weights_path(run_dir)
    preset = check_preset(preset, cfg, run_dir) if preset else matching_preset(cfg)
    scene_metrics = results_metrics(results, heldout, run_dir)
    cam, t = cfg.camera, cfg.train
    n_net = sum(p.numel() for p in model.net.parameters())
    n_cam = sum(p.numel() for p in model.camera.parameters())
    data = _training_data(cfg, run_dir)
    cfa = cam.cfa.period if cam.kind == "doe" and cam.cfa.enabled else None
    if summary is None:
        on = ("the embedded synthetic data" if cfg.data.root is None else "its own scene folder")
        summary = (f"{cam.kind.upper()} camera{f' with a {cfa}×{cfa} CFA' if cfa else ''} + {cfg.model.kind} network "
                   f"({n_net:,} parameters), {len(bands)} bands {bands.centers_nm[0]:g}–{bands.centers_nm[-1]:g} nm, "
                   f"{final.get('step')} steps on {on}")
    val_log = {k: final.get(f"val_{k}") for k in METRICS}
    return {
        "format": CARD_FORMAT,
        "name": name,
        "summary": " ".join(str(summary).split()),
        "preset": preset,
        "packed_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "hsicam_version": running_version(),  # the running code's (a source checkout has no installed metadata)
        **source_state(),  # git_commit (+dirty) and source_diff_sha256, as a training session records them
        "source_run": str(run_dir.resolve()),
        "camera": {"kind": cam.kind, "cfa_period": cfa, "pixel_pitch_um": cam.sensor.pixel_pitch_um,
                   "aperture_radius_mm": cam.aperture_radius_mm, "lens_model": cam.lens.model,
                   # the focal length at the design wavelength (a singlet ignores focal_length_mm: R / (n(λ0) − 1))
                   "focal_length_mm": cam.lens.design_focal_length_mm(),
                   "kernel_px": getattr(model.camera, "kernel_px", None), "trainable_parameters": n_cam},
        "network": {"kind": cfg.model.kind, "parameters": n_net, "context_px": model.context_px,
                    "consistency_steps": cfg.model.consistency.iterations if model.consistency_on else 0,
                    "consistency": consistency_summary(cfg.model.consistency) if model.consistency_on else None},
        "bands": {"start_nm": cfg.bands.start_nm, "stop_nm": cfg.bands.stop_nm, "step_nm": cfg.bands.step_nm,
                  "count": len(bands), "centers_nm": [float(x) for x in bands.centers_nm]},
        "noise": {"train_sensor_sigma": list(t.sensor_sigma), "train_sigma_height_nm": list(t.sigma_height_nm),
                  "sensor_noise_model": cam.sensor.noise, "sensor_sigma": cam.sensor.sigma,
                  "full_well_e": cam.sensor.full_well_e, "read_noise_e": cam.sensor.read_noise_e,
                  "doe_sigma_height_nm": cam.doe.sigma_height_nm if cam.kind == "doe" else None},
        "training": {"data": data, "steps": final.get("step"), "epochs": cfg.train.epochs,
                     "elapsed_s": training_seconds(run_dir), "patches_per_s": final.get("patches_per_s"),
                     "batch_size": t.batch_size, "patch_px": cfg.data.patch_px,
                     "patches_per_epoch": cfg.data.patches_per_epoch},
        "metrics": {"training_log": {"what": "validation patches at the end of training (metrics.jsonl)",
                                     **val_log, "best_psnr": final.get("best_psnr")},
                    **scene_metrics},
        "weights": {"file": "model.safetensors", "bytes": weights.stat().st_size, "sha256": file_sha256(weights)},
        **({"linear_step": {"file": LINEAR_STEP_FILE, "bytes": step.stat().st_size, "sha256": file_sha256(step)}}
           if (step := Path(run_dir) / LINEAR_STEP_FILE).is_file() else {}),
        "limits": _limits(cfg, name, bands, cfa, data),
    }


def _limits(cfg, name: str, bands, cfa: int | None, data: dict[str, Any]) -> list[str]:
    t = cfg.train
    out = []
    if data["kind"] == "folder":
        out.append("trained on the maintainer's own scene folder, not on real captures of this camera")
    else:
        out.append(f"trained only on synthetic scenes (embedded generator version {data['generator_version']}, "
                   f"{data['scenes']} scenes of {data['scene_px']} px); real scenes may differ in content and spectra")
    out.append(f"band grid {bands.centers_nm[0]:g}–{bands.centers_nm[-1]:g} nm in {cfg.bands.step_nm:g} nm steps "
               f"({len(bands)} bands); cubes on other grids are resampled, outside the range refused")
    sensor = f"pixel pitch {cfg.camera.sensor.pixel_pitch_um:g} µm"
    out.append(f"the sensor must match the simulated one: {sensor}" + (f", {cfa}×{cfa} CFA period" if cfa else ""))
    doe = cfg.camera.kind == "doe"
    out.append(f"trained with sensor noise σ_s in [{t.sensor_sigma[0]:g}, {t.sensor_sigma[1]:g}] "
               f"({cfg.camera.sensor.noise} model)"
               + (f" and DOE height noise σ_p in [{t.sigma_height_nm[0]:g}, {t.sigma_height_nm[1]:g}] nm" if doe else "")
               + "; noisier captures reconstruct worse"
               + ("; give a capture's photon level (`hsicam reconstruct --full-well-e E --read-noise-e R`) so that "
                  "the consistency steps do not fit its noise"
                  if cfg.model.consistency.iterations > 0 and cfg.model.consistency.noise_aware else ""))
    if doe:
        out.append("a built camera differs from the simulation: measure its PSFs and adapt the network with "
                   f"`hsicam finetune --run pretrained:{name} --psf-dir PSFS --out RUN2` before reconstructing real "
                   "captures")
    else:  # measured-PSF fine-tuning needs a DOE camera (hsicam finetune refuses others)
        from hsicam.runs.camera_files import copy_name

        c = cfg.camera.cassi
        # files by the name of the copy the camera ships (the packer's own paths mean nothing to its users)
        mask = (f"the mask {copy_name('camera.cassi.mask_file', c.mask_file)}" if c.mask_file
                else f"the random mask of seed {c.mask_seed}")
        prism = (c.prism_material if c.prism_material == "fused_silica"
                 else copy_name("camera.cassi.prism_material", c.prism_material))
        shear = (f"{c.shift_px:g} px per band" if c.dispersion == "linear" else
                 f"a {prism} prism of {c.prism_apex_deg:g}° before a {c.prism_focal_length_mm:g} mm lens")
        out.append(f"a built camera must match the simulated {cfg.camera.kind} one, its coded aperture ({mask}) and "
                   f"its dispersion ({shear}); measured-PSF fine-tuning (`hsicam finetune`) needs a DOE camera")
    return out


def _duration(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _fmt_means(m: dict[str, Any] | None) -> tuple[str, str, str]:
    if not m or any(m.get(k) is None for k in METRICS):
        return ("–", "–", "–")
    return (f"{m['psnr']:.2f}", f"{m['ssim']:.4f}", f"{m['sam']:.2f}")


def card_markdown(card: dict[str, Any]) -> str:
    """``card.md``: the model card for people, made only from ``card`` (:func:`card_fields`)."""
    name, b, tr, m, nz = card["name"], card["bands"], card["training"], card["metrics"], card["noise"]
    data = tr["data"]
    lines = [f"# Pre-trained camera `{name}`", "", card["summary"], "",
             f"Use it with `--run pretrained:{name}` (e.g. `hsicam reconstruct SENSOR --run pretrained:{name} "
             f"--out cube.h5`); copy it with `hsicam pretrained copy {name} DIR`.", "",
             "## Camera and network", "",
             f"- camera: {card['camera']['kind']}" + (f", {card['camera']['cfa_period']}×{card['camera']['cfa_period']} "
                                                      "CFA" if card['camera']['cfa_period'] else "")
             + f", pixel pitch {card['camera']['pixel_pitch_um']:g} µm"
             + (f", PSF kernel {card['camera']['kernel_px']} px" if card['camera'].get('kernel_px') else ""),
             f"- network: {card['network']['kind']}, {card['network']['parameters']:,} parameters"
             + (f", then {card['network']['consistency']} at inference (`model.consistency`)"
                if card['network'].get('consistency') else
                f", then {card['network']['consistency_steps']} measurement-consistency step(s) at inference "
                "(`model.consistency`)" if card['network'].get('consistency_steps') else ""),
             f"- bands: {b['count']} bands, {b['centers_nm'][0]:g}–{b['centers_nm'][-1]:g} nm in {b['step_nm']:g} nm steps",
             f"- preset: {card['preset'] or 'a config of its own (see config.yaml)'}", "",
             "## Training", ""]
    if data["kind"] == "folder":
        lines.append(f"- data: {data['note']} ({data['root']})")
    else:
        lines.append(f"- data: the {data['kind']} (version {data['generator_version']}): {data['scenes']} scenes of "
                     f"{data['scene_px']} px, seed {data['seed']}; spectral sources "
                     f"{', '.join(s['id'] for s in data['sources'])}; held out of training: "
                     f"{', '.join(data['holdout_sources']) or 'none'}")
    elapsed = tr.get("elapsed_s")
    lines += [f"- {tr['steps']} steps ({tr['epochs']} epochs, batch {tr['batch_size']}, {tr['patch_px']} px patches)"
              + (f" in {_duration(elapsed)}" if isinstance(elapsed, (int, float)) else ""),
              f"- noise: sensor σ_s in {nz['train_sensor_sigma']} ({nz['sensor_noise_model']} model)"
              + (f", DOE height σ_p in {nz['train_sigma_height_nm']} nm" if card["camera"]["kind"] == "doe" else ""),
              "",
              "## Numbers", ""]
    log = m["training_log"]
    p, s, a = _fmt_means(log)
    lines.append(f"Validation patches at the end of training: PSNR {p} dB, SSIM {s}, SAM {a}°.")
    lines.append("")
    val, held = m.get("validation"), m.get("heldout")
    if val or held:
        from hsicam.engine.evaluate import is_heldout_sources_label

        # `--heldout` may be an evaluation of any folder (`evaluate --data DIR`): its column says "held-out data"
        held_what = "held-out sources" if held is None or is_heldout_sources_label(held["data"]) else "held-out data"
        lines += [f"| method | validation PSNR (dB) | SSIM | SAM (°) | {held_what} PSNR (dB) | SSIM | SAM (°) |",
                  "|---|---|---|---|---|---|---|"]
        lines.append(f"| {name} | " + " | ".join((*_fmt_means(val and val["mean"]), *_fmt_means(held and held["mean"])))
                     + " |")
        refs = [r["method"] for r in (val or {}).get("references", [])]
        refs += [r["method"] for r in (held or {}).get("references", []) if r["method"] not in refs]
        for ref in refs:
            v = next((r["mean"] for r in (val or {}).get("references", []) if r["method"] == ref), None)
            h = next((r["mean"] for r in (held or {}).get("references", []) if r["method"] == ref), None)
            lines.append(f"| {ref} | " + " | ".join((*_fmt_means(v), *_fmt_means(h))) + " |")
        lines.append("")
        for what, blk in (("validation", val), (held_what, held)):
            if blk:
                lines.append(f"- {what}: {blk['n_scenes']} scenes, {blk['data']} (from {Path(blk['source']).name})")
        lines.append("")
    else:
        lines += ["No results.json was given when packing: no scene-level numbers.", ""]
    lines += ["## Limits", "", *(f"- {x}" for x in card["limits"]), "",
              f"Weights: {card['weights']['bytes'] / 1e6:.2f} MB, sha256 {card['weights']['sha256']}; "
              f"packed {card['packed_utc']} with hsicam {card['hsicam_version']}"
              + (f" ({commit_label(card)})" if card.get("git_commit") else "") + ".", ""]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
# Packing
# ------------------------------------------------------------------------------------------------
def _only_camera_files(folder: Path) -> bool:
    """True when ``folder`` is a camera (:func:`hsicam.runs.pretrained.is_camera`) with nothing else in it."""
    return shipped.is_camera(folder) and {p.name for p in folder.iterdir()} <= {*shipped.FILES, COMPLETE_MARKER}


def check_pack_target(target: Path, name: str, overwrite: bool) -> None:
    """One-line :class:`InputError` unless ``target`` (DEST/NAME) may receive the packed camera:
    absent, an empty folder, or a packed camera (replaced only with ``overwrite``). Anything else
    (a training run, another command's output, a user's folder or file) is never replaced, so
    --force is not offered for it."""
    from hsicam.io import output_description, read_marker

    if not target.exists() or (target.is_dir() and not any(target.iterdir())):
        return
    command = read_marker(target).get("command")
    if shipped.is_camera(target) and (command == "pretrained pack" or _only_camera_files(target)):
        if not overwrite:
            raise InputError(f"{target}: a pre-trained camera {name!r} exists; pass --force to replace it")
        return
    if not target.is_dir():
        what = "a file"
    elif command:
        what = output_description(target)
    else:
        kind = ("a camera's files with others besides" if shipped.is_camera(target) else
                "a run folder" if (target / "config.yaml").is_file() else "a folder of other files")
        what = f"{kind}, not a completed hsicam output"
    raise InputError(f"{target}: not a packed camera ({what}), and pack never replaces it, even with --force; "
                     "choose another --name or --dest")


def check_pack_apart(run_dir: Path, target: Path) -> None:
    """One-line :class:`InputError` when the camera folder ``target`` (DEST/NAME) lies inside the run
    ``run_dir`` being packed (``--dest RUN`` or a folder in it: the camera would be written into the
    run, files its training never wrote), or holds it (the camera would replace the folder of its
    own run). Both compared resolved (links followed); ``target`` equal to the run is
    :func:`check_pack_target`'s (a run folder, never replaced)."""
    run, cam = run_dir.resolve(), target.resolve()
    if cam != run and cam.is_relative_to(run):
        raise InputError(f"{target}: inside the run folder {run_dir} that is being packed; pack writes the camera "
                         f"outside its run: give a --dest outside {run_dir}")
    if cam != run and run.is_relative_to(cam):
        raise InputError(f"{target}: holds the run folder {run_dir} that is being packed, which the camera would "
                         "replace; choose another --name or --dest")


def default_pack_root() -> Path:
    """Where ``pack`` writes without ``--dest``: ``$HSICAM_PRETRAINED_DIR`` when set, else the package's own
    folder of cameras when hsicam runs from a source checkout (:func:`hsicam.engine.provenance.source_checkout`:
    a maintainer adding a camera to the repository). An installed package's folder (site-packages) is never
    written: one-line :class:`InputError` asking for ``--dest`` (pip would not remove a camera it did not install)."""
    import os

    from hsicam.engine.provenance import source_checkout

    if os.environ.get(shipped.ENV_VAR):
        return shipped.root()
    if source_checkout() is not None:
        return shipped.package_root()
    raise InputError(f"no --dest: hsicam runs from an installed package, whose cameras ({shipped.package_root()}) "
                     f"are read-only; give --dest DIR (a folder of cameras: use them with {shipped.ENV_VAR}=DIR), or "
                     f"set {shipped.ENV_VAR}")


def pack_pretrained(run_dir: str | Path, name: str, dest_root: str | Path | None = None,
                    results: str | Path | None = None, heldout: str | Path | None = None, *,
                    summary: str | None = None, preset: str | None = None, overwrite: bool = False) -> Path:
    """Pack the finished run ``run_dir`` as the pre-trained camera ``name`` under ``dest_root``
    (default: :func:`default_pack_root`, refused from an installed package); returns its folder.

    Refuses (one-line :class:`InputError`, nothing written) a run that has not finished, a
    fine-tuned run (its measured PSFs are not shipped), results of another run
    (:func:`check_results_of_run`), a ``preset`` that is not a shipped preset, weights over
    :data:`hsicam.runs.pretrained.MAX_WEIGHTS_BYTES`, an existing camera unless ``overwrite``, a
    ``dest_root/name`` inside the run or holding it (:func:`check_pack_apart`), and a
    ``dest_root/name`` that is not a packed camera (:func:`check_pack_target`), and a run whose camera files are gone
    or changed since training (:func:`hsicam.runs.camera_files.check_camera_files`). A camera built from files
    carries a copy of each (:func:`hsicam.runs.camera_files.copy_name`), which its config.yaml names relative to its
    folder, and their record. The folder is written under a temporary name and renamed into place."""
    run_dir = Path(run_dir)
    shipped.check_name(name)
    dest = Path(dest_root) if dest_root is not None else default_pack_root()
    if shipped.is_spec(str(run_dir)):
        raise InputError(f"{run_dir}: already a pre-trained camera; pack a run folder")
    check_is_run(run_dir)
    if (run_dir / MEASURED_PSF_FILE).is_file():  # first: finishing it (`hsicam finetune --resume`) would not help
        raise InputError(f"{run_dir}: a fine-tuned run (measured PSFs) cannot be shipped; pack the run trained on "
                         "simulated optics")
    final_record(run_dir)
    if not (run_dir / "model.safetensors").is_file():
        raise InputError(f"{run_dir}: the run has no final weights (model.safetensors is missing)")
    weights = root_weights_path(run_dir)
    size, limit = weights.stat().st_size, shipped.MAX_WEIGHTS_BYTES
    if size > limit:
        raise InputError(f"{weights}: {size / 1e6:.1f} MB of weights, more than the {limit / 1e6:g} MB a shipped "
                         "camera may have; train a smaller network")
    target = dest / name
    check_pack_apart(run_dir, target)
    check_pack_target(target, name, overwrite)
    card = card_fields(run_dir, name, results, heldout, summary=summary, preset=preset)
    text = card_markdown(card)
    if overwrite and not is_complete(target) and _only_camera_files(target):
        # A camera from a git checkout has no completion marker (.gitignore'd): it is still ours to
        # replace. A folder holding anything else keeps the marker rule (a user's folder is never deleted).
        mark_complete(target, {"command": "pretrained pack"})
    cfg = load_config(run_dir / "config.yaml", empty=EMPTY_RUN_CONFIG)
    check_camera_files(run_dir, cfg)  # the tables it was trained with (card_fields loaded it: said again, cheaply)
    files = camera_files(cfg)
    with atomic_output(target, "dir", overwrite=True, marker={"command": "pretrained pack"}) as tmp:
        if files:  # a shipped camera is self-contained: a copy of each file, named relative to its folder
            names = {k: copy_name(k, p) for k, p in files.items()}
            for key, path in files.items():
                copy_file(path, tmp / names[key])
            with atomic_open(tmp / "config.yaml", "w", encoding="utf-8") as fh:
                fh.write(dump_yaml(with_values(cfg, names)))
            write_camera_files(tmp, {"files": {k: {"path": n, "sha256": file_sha256(tmp / n)} for k, n in names.items()}})
        else:
            copy_file(run_dir / "config.yaml", tmp / "config.yaml")
        copy_file(weights, tmp / "model.safetensors")
        if (run_dir / LINEAR_STEP_FILE).is_file():  # the linear consistency step's filters travel with the camera
            copy_file(run_dir / LINEAR_STEP_FILE, tmp / LINEAR_STEP_FILE)
        write_json(tmp / shipped.CARD_JSON, card)
        with atomic_open(tmp / shipped.CARD_MD, "w", encoding="utf-8") as fh:
            fh.write(text)
    return target
