"""`hsicam export-optics`, `hsicam tolerance`, `hsicam finetune`: from a trained run to hardware."""

from __future__ import annotations

import argparse
from pathlib import Path

from hsicam.config import MAX_EPOCHS, MAX_LR, TOLERANCE_SEED_MAX
from hsicam.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    from hsicam.cli import add_run_arg
    from hsicam.cli.args import (count_arg, device_arg, draws_arg, finite_numbers_arg, levels_arg, levels_list_arg,
                                 sigma_heights_arg, positive_number_arg, seed_arg)

    from hsicam.config import LEVELS_RULE  # the export's rule of the levels (from config: --help loads no torch)

    p = sub.add_parser("export-optics", help="fabrication files: DOE heights (npy/tiff/csv/gds), CFA spectra and fits, spec.json")
    add_run_arg(p, "trained run folder")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--levels", type=levels_arg, default=None, metavar="L",
                   help=f"DOE height levels for lithography, {LEVELS_RULE} "
                        "(default: the run's camera.doe.quantization_levels, else 8)")
    p.add_argument("--tolerance", metavar="PATH", help="tolerance.json (or its folder) to cite in spec.json "
                                                       "(default: RUN/tolerance/ if present)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("tolerance", help="PSNR of the trained camera under fabrication and assembly errors")
    add_run_arg(p, "trained run folder")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (tolerance.json, .csv, .png); a study interrupted there is resumed by the same "
                        "command (its finished rows are kept in DIR/tolerance.partial.jsonl)")
    p.add_argument("--restart", action="store_true",
                   help="discard the finished rows of a study interrupted in --out and start it over (a resume whose "
                        "run, scenes or settings differ is refused without it)")
    p.add_argument("--data", metavar="PATH", help="scenes to evaluate on (default: the run's validation scenes)")
    p.add_argument("--max-scenes", type=count_arg, default=8, help="scenes scored at most, >= 1 (default 8)")
    p.add_argument("--allow-negative", action="store_true",
                   help="clip negative values of the scenes (dark noise after a background subtraction) to 0 instead "
                        "of refusing them (data.allow_negative; default: the run's own setting)")
    # the lists' defaults are hsicam.engine.tolerance.ToleranceSpec's (that module imports torch: said here, and
    # tests/cli/test_cli_args.py holds them equal)
    p.add_argument("--sigma-height-nm", type=sigma_heights_arg, default=None, metavar="LIST",
                   help="DOE height noise levels σ_p (nm), each in [0, 1000000] (default: 0,10,20,40,60)")
    p.add_argument("--draws", type=draws_arg, default=None,
                   help="fabricated DOEs drawn per height-noise level, 1 to 1000 (default 3)")
    p.add_argument("--levels", type=levels_list_arg, default=None, metavar="LIST",
                   help=f"DOE height level counts, each {LEVELS_RULE} as export-optics exports "
                        "(default: 2,4,8,16,32)")
    p.add_argument("--shift-cells", type=finite_numbers_arg, default=None, metavar="LIST",
                   help="lateral DOE shifts (cells), each swept along x and along the diagonal, multiples of 1/Q cell "
                        "(--shift-subsamples) (default: 0,0.25,0.5,1,2)")
    p.add_argument("--shift-subsamples", type=count_arg, default=None,
                   help="pupil samples per cell Q for the misalignment study (shift resolution 1/Q cell; rounded up to a "
                        "multiple of the run's own pupil oversampling), >= 1 (default 4)")
    p.add_argument("--sensor-distance-um", type=finite_numbers_arg, default=None, metavar="LIST",
                   help="sensor distance errors Δz (µm; negative: toward the lens) (default: -100,-50,-20,0,20,50,100); "
                        "a list starting with '-' needs '=', e.g. --sensor-distance-um=-100,0,100")
    # height-noise draw d (< 1000) takes the torch seed seed·1000 + d, which must stay below 2^32 (torch keeps a seed's
    # low 32 bits, so larger or negative seeds would repeat another --seed's draws)
    p.add_argument("--seed", type=seed_arg(0, TOLERANCE_SEED_MAX), default=0,
                   help=f"seed for the height-noise draws and the sensor noise, in [0, {TOLERANCE_SEED_MAX}] (default 0)")
    p.add_argument("--device", default="cpu", type=device_arg, help="torch device (default cpu)")
    p.set_defaults(func=cmd_tolerance)

    p = sub.add_parser("finetune", help="adapt a run's network to measured PSFs (optics frozen)")
    add_run_arg(p, "trained run folder")
    p.add_argument("--psf-dir", required=True, metavar="DIR", help="measured PSFs: one image per band (see docs)")
    p.add_argument("--out", required=True, metavar="RUN2", help="new run folder")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted fine-tuning in --out (or extend a finished one with --epochs), "
                        "made from the same --run and --psf-dir")
    p.add_argument("--psf-pitch-um", type=float, default=None, help="pixel pitch of the PSF images (else psf.json)")
    p.add_argument("--epochs", type=int, default=None,
                   help=f"fine-tuning epochs, 1 to {MAX_EPOCHS} (default: the run's train.epochs)")
    p.add_argument("--lr", type=positive_number_arg, default=None,
                   help=f"network learning rate, in (0, {MAX_LR:g}] as train.lr (default: 0.1 × the run's train.lr; with "
                        "--resume, the rate the fine-tuning started with)")
    p.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
                   help="dotted override of the run's config, e.g. data.patches_per_epoch=256 (repeatable)")
    p.set_defaults(func=cmd_finetune, trains=True, resume_hint="go on with the same hsicam finetune command and --resume",
                   diverged_hint="continue with a lower rate: the same hsicam finetune command with --resume and a "
                                 "lower --lr (or remove {run} to start over)")


def cmd_export(args: argparse.Namespace) -> int:
    from hsicam.export import export_optics
    from hsicam.cli import prepare_output

    # (--levels: checked by its type, levels_arg)
    prepare_output(args.out, "dir", replace=True, command="export-optics", run=args.run)
    spec = export_optics(args.run, args.out, args.levels, args.tolerance)
    doe, cfa = spec["doe"], spec["cfa"]
    if doe["enabled"]:
        q = doe["quantized"]
        gds = q["gds"].get("file") or f"no GDS ({q['gds'].get('skipped')})"
        doe_text = (f"DOE ({doe['cells_across']}² cells of {doe['cell_size_um']:g} µm, {q['levels']} levels, "
                    f"phase error at λ0 rms {q['phase_error_design_wavelength_rad']['rms']:.3f} rad, {gds})")
    else:
        doe_text = "no DOE (camera.doe.enabled: false: no DOE files)"
    if cfa["enabled"]:
        cfa_text = f"CFA ({cfa['period']}×{cfa['period']}, fit rms ≤ {cfa['fit_rms_error']['max']:.3f})"
    else:
        cfa_text = "no CFA (camera.cfa.enabled: false: no CFA files)"
    print(f"exported {doe_text} and {cfa_text}, spec.json -> {args.out}")
    return 0


def cmd_tolerance(args: argparse.Namespace) -> int:
    from hsicam.engine.tolerance import study_folder_state
    from hsicam.cli import prepare_output
    from hsicam.io import OutputLock, cleanup_stale_temporaries

    # an interrupted study (its progress file) is resumed in place; anything else is replaced as a whole
    interrupted = study_folder_state(args.out) == "interrupted"
    out = prepare_output(args.out, "dir", replace=not interrupted, command="tolerance", run=args.run)
    out.parent.mkdir(parents=True, exist_ok=True)  # the lock file lies beside the folder
    # the folder is this process's from here to its marker: a second study started meanwhile is refused naming it
    with OutputLock(out, "tolerance") as lock:
        lock.acquire()
        if interrupted:  # a kill while its progress file was rewritten left a temporary in it
            cleanup_stale_temporaries(out)
        return _tolerance(args, out)


def _tolerance(args: argparse.Namespace, out: Path) -> int:
    """:func:`cmd_tolerance` under the output folder's lock."""
    from hsicam.runs.folder import load_run
    from hsicam.engine.tolerance import PARTIAL_FILE, ToleranceSpec, finish_study, refuse_finetuned_run, run_tolerance

    refuse_finetuned_run(args.run)  # before loading: its measured PSFs are not what the study perturbs
    defaults = ToleranceSpec()
    spec = ToleranceSpec(height_draws=defaults.height_draws if args.draws is None else args.draws,
                         max_scenes=args.max_scenes, seed=args.seed,
                         shift_subsamples=defaults.shift_subsamples if args.shift_subsamples is None else args.shift_subsamples)
    for name in ("sigma_height_nm", "levels", "shift_cells", "sensor_distance_um"):
        v = getattr(args, name)
        if v is not None:
            if not v:
                raise InputError(f"--{name.replace('_', '-')} needs at least one value")
            setattr(spec, name, v)
    cfg, model = load_run(args.run, args.device)
    if args.allow_negative:  # the study's identity hashes the config: a resume without it is refused, and said why
        cfg.data.allow_negative = True
    if not cfg.camera.doe.enabled:
        # without a DOE the DOE sweeps are skipped (noted in tolerance.json); asking for them is refused
        given = [opt for opt, v in (("--sigma-height-nm", args.sigma_height_nm), ("--draws", args.draws),
                                    ("--levels", args.levels), ("--shift-cells", args.shift_cells),
                                    ("--shift-subsamples", args.shift_subsamples)) if v is not None]
        if given:
            raise InputError(f"{' '.join(given)}: {args.run} has no DOE (camera.doe.enabled: false), so there is no "
                             "element whose heights, levels or position could be in error; leave out "
                             f"{', '.join(given)} (the study then sweeps the sensor distance only)")
    result = run_tolerance(model, cfg, spec, args.data, run=args.run, partial=out / PARTIAL_FILE, restart=args.restart)
    finish_study(out, result)
    from hsicam.engine.tolerance import NOT_SWEPT_KEY

    s = result["summary"]
    not_swept = set(s.get(NOT_SWEPT_KEY) or ())

    def tol(key: str, unit: str) -> str:
        """The summary's KEY (or KEY.SIDE of the sensor distance's) as the line says it."""
        name, _, side = key.partition(".")
        value = (s.get(name) or {}).get(side) if side else s.get(name)
        # null for a sweep (or side) that held no value but 0, or none at all (then absent), is not "not reached up
        # to …": it was never swept
        return _fmt(value, unit, not_swept=key in not_swept or name not in s,
                    swept_to=_swept_to(result, name.removesuffix("_at_1db_loss"), side))

    if result.get("skipped"):
        doe = "no DOE (camera.doe.enabled: false): DOE sweeps skipped; 1-dB tolerances: "
        doe_tol = ""
    else:
        doe = "1-dB tolerances: "
        doe_tol = f"σ_p {tol('sigma_height_nm_at_1db_loss', 'nm')}, shift {tol('shift_x_cells_at_1db_loss', 'cells')} (x), "
    from hsicam.report.tolerance import above_reference_text, levels_text

    lv = "" if result.get("skipped") else levels_text(result)  # "levels ≥ L" only when the sweep brackets L
    levels = f", {lv}" if lv else ""
    above = above_reference_text(result)
    if above:  # before the summary line, which stays the last
        print(f"note: {above}")
    print(f"nominal PSNR {result['nominal']['psnr']:.2f} dB on {len(result['scenes'])} scene(s); {doe}{doe_tol}"
          f"Δz toward the lens {tol('sensor_distance_um_at_1db_loss.minus', 'µm')}, "
          f"away {tol('sensor_distance_um_at_1db_loss.plus', 'µm')}{levels} -> {args.out}")
    return 0


def _swept_to(result: dict, sweep: str, side: str = "") -> float | None:
    """The largest |value| the study swept of ``sweep`` (``side`` "minus" / "plus": of the values ≤ 0 / ≥ 0), or
    None when it holds none."""
    values = ((result.get("sweeps") or {}).get(sweep) or {}).get("values") or []
    values = [v for v in values if (v <= 0 if side == "minus" else v >= 0 if side == "plus" else True)]
    return max((abs(v) for v in values), default=None)


def _fmt(v, unit: str, not_swept: bool = False, swept_to: float | None = None) -> str:
    """A 1-dB tolerance with its unit, or the words for one the sweep never reached (``swept_to``: its largest
    |value|, a lower bound on the tolerance and no more: nothing beyond it was measured), or (``not_swept``: its
    sweep, or side, held no value but 0) for one never swept."""
    if v is not None:
        return f"{v:.3g} {unit}"
    if not_swept:
        return "not swept"
    return "not reached within the swept range" if swept_to is None else f"not reached up to {swept_to:g} {unit}"


def cmd_finetune(args: argparse.Namespace) -> int:
    from hsicam.cli import run_config_from_args
    from hsicam.engine.calibration import finetune
    from hsicam.cli import prepare_output
    from hsicam.runs.folder import check_is_run

    prepare_output(args.out, "dir")
    run = Path(args.run)
    check_is_run(run)
    overrides = list(args.overrides)
    if args.epochs is not None:
        if args.epochs < 1:
            raise InputError("--epochs must be >= 1")
        if args.epochs > MAX_EPOCHS:
            raise InputError(f"--epochs must be at most {MAX_EPOCHS} (as train.epochs), got {args.epochs}")
        overrides.append(f"train.epochs={args.epochs}")
    lr = args.lr
    if lr is None and not args.resume:  # a resume goes on with the rate it was started with
        lr = 0.1 * run_config_from_args(run, args.overrides).train.lr
    if lr is not None:
        if not lr > 0:
            raise InputError("--lr must be positive")
        if lr > MAX_LR:
            raise InputError(f"--lr must be at most {MAX_LR:g} (as train.lr), got {lr:g}")
        overrides.append(f"train.lr={lr:.6e}")
    s = finetune(run, args.psf_dir, args.out, overrides=tuple(overrides), pitch_um=args.psf_pitch_um,
                 resume=args.resume)
    if s.get("already_finished"):  # as `hsicam train --resume` says it (finetune.json left as it was)
        changed = ("; ".join(s["changed"]) + ", nothing else changed" if s.get("changed") else "nothing changed")
        print(f"{args.out}: fine-tuning already finished at step {s['step']} ({s['epoch']} epochs); {changed}. To "
              f"fine-tune on, raise --epochs: hsicam finetune --run {args.run} --psf-dir {args.psf_dir} --out "
              f"{args.out} --resume --epochs N (N > {s['epoch']})")
        return 0
    before = s["before"].get("psnr")
    after = s["best_val_psnr"]
    e = s["energy_in_kernel"]
    # (the share of each measured image's light the kernel keeps: not `hsicam psf`'s "energy in kernel", the light
    # of the simulated PSF within the kernel of all that enters the aperture)
    print(f"fine-tuned {s['steps']} steps with the measured PSFs (kernel keeps {min(e):.3f}..{max(e):.3f} of each "
          f"measured image's light): "
          f"val PSNR {before if before is None else f'{before:.2f}'} -> {after if after is None else f'{after:.2f}'} dB "
          f"(best epoch {s['best_epoch']}) -> {args.out}")
    return 0
