"""`hsicam evaluate`, `hsicam experiment` and `hsicam report`."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from hsicam.cli import add_config_args, add_run_arg, config_from_args, run_config_from_args
from hsicam.cli.args import (MIN_TILE_PX, RegistryChoices, check_tile, device_arg, seeds_arg, sensor_sigma_arg,
                             sigma_height_arg)
from hsicam.errors import InputError

log = logging.getLogger(__name__)


def _method_names() -> tuple[str, ...]:
    from hsicam.engine.names import METHOD_NAMES  # torch-free; a test holds it equal to the methods' registry

    return METHOD_NAMES


def _experiment_names() -> tuple[str, ...]:
    from hsicam.engine.names import EXPERIMENTS

    return EXPERIMENTS


def _scale_names() -> tuple[str, ...]:
    from hsicam.engine.names import SCALES

    return SCALES


def register(sub: argparse._SubParsersAction) -> None:
    # the registries' names are read when a value is checked or a command's help written (RegistryChoices),
    # from hsicam.engine.names: torch-free, so neither this parser nor a command's help waits for torch
    p = sub.add_parser("evaluate", help="evaluate a camera + reconstruction method on a dataset")
    add_config_args(p)
    add_run_arg(p, "trained run folder (needed by learned methods)", required=False)
    p.add_argument("--method", default="doe-learned", choices=RegistryChoices(_method_names), metavar="METHOD",
                   help="reconstruction method: %(choices)s (default: doe-learned, the run's learned camera)")
    p.add_argument("--data", metavar="DIR",
                   help="folder of supported cube files (default: the validation split of the run's data: data.root, "
                        "else the synthetic data); its sub-folders holding hsicam outputs are skipped; --out must not "
                        "be it or hold it; with --run, each row says whether the run trained on the scene (split)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="result folder: results.json, results.csv, results.md (per scene and mean; with --save, cubes/)")
    p.add_argument("--sigma-height-nm", type=sigma_height_arg, default=None,
                   help="test DOE height noise σ_p (nm), in [0, 1000000]")
    p.add_argument("--sensor-sigma", type=sensor_sigma_arg, default=None,
                   help="test sensor noise σ_s (fraction of full scale), in [0, 1]")
    p.add_argument("--seeds", type=seeds_arg, default=1, help="number of noise seeds (0, 1, ...), 1 to 1000 (default 1)")
    p.add_argument("--save", action="store_true",
                   help="also write each scene's reconstruction and ground truth (cubes/NAME_estimate.h5, NAME_truth.h5; "
                        "with --seeds N > 1 the estimate of seed 0, its metadata says so)")
    p.add_argument("--device", default="cpu", type=device_arg, help="torch device (default cpu)")
    p.add_argument("--tile", type=int, default=None, metavar="PX",
                   help=f"tile side for a network's large scenes, >= {MIN_TILE_PX} (default: 4× its context, within "
                        "512-1024 px); smaller tiles take more time and less memory in the network only: its consistency "
                        "steps go over the whole scene whatever the tile (off: --set model.consistency.iterations=0)")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("experiment", help="run one of the paper's experiments (resumable)")
    p.add_argument("name", choices=RegistryChoices(_experiment_names), metavar="NAME",
                   help="the experiment (%(choices)s). compare: our camera against the CASSI baselines (the paper's Table 1); ablation: DOE and CFA "
                        "on/off, three trained cameras (Table 2); noise: cameras trained without and with noise, tested "
                        "on σ_p × σ_s grids (Fig. 7); cfa-period: CFA periods 3, 6, 9, 12, 15")
    p.add_argument("--scale", choices=RegistryChoices(_scale_names), default="quick", metavar="SCALE",
                   help="the preset of that name (%(choices)s) plus the experiment's overrides: tiny (seconds, for tests), quick "
                        "(minutes on a 2-core CPU, the default), paper (a GPU)")
    p.add_argument("--out", metavar="DIR", help="experiment folder (default: runs/experiments/NAME-SCALE)")
    p.add_argument("--seeds", type=seeds_arg, default=1,
                   help="number of test-noise seeds (0, 1, ...), 1 to 1000 (default 1): each scores the scenes again "
                        "under fresh test noise (the runs are trained once); the noise experiment's grid, or a "
                        "preset with camera noise, has some; without any, one seed is scored")
    p.set_defaults(func=cmd_experiment, trains=True, scores=True, resume_hint="run the same hsicam experiment command again: it resumes the run")

    p = sub.add_parser("report", help="HTML report (index.html + PNGs) of an evaluation or experiment folder")
    p.add_argument("dir", metavar="DIR", help="a folder `hsicam evaluate` or `hsicam experiment` wrote; the report "
                                              "goes to DIR/report/")
    p.set_defaults(func=cmd_report)


#: The sensor's capture-noise keys (``camera.sensor``; its pixel pitch is optics: the PSF sampling).
SENSOR_NOISE_KEYS = ("noise", "sigma", "full_well_e", "read_noise_e", "bit_depth")
#: What ``--set`` may change when ``evaluate`` scores a trained run (``--run``): the data, the
#: inference step after the network, how scenes are captured (boundary, padding, noise) and the
#: baselines' settings. A run's camera (the pixel pitch too), band grid and network are fixed by its
#: training.
RUN_EVALUATION_KEYS = ("data", "model.consistency", "camera.boundary", "camera.padding",
                       *(f"camera.sensor.{k}" for k in SENSOR_NOISE_KEYS), "camera.doe.sigma_height_nm", "baselines")


def check_run_overrides(overrides) -> None:
    """InputError for a ``--set`` that a trained run would silently ignore (it used to be recorded in
    the results' config hash all the same)."""
    from hsicam.config import load_config
    from hsicam.errors import ConfigError

    for item in overrides:
        key = str(item).split("=", 1)[0].strip()
        if not any(key == k or key.startswith(k + ".") for k in RUN_EVALUATION_KEYS):
            try:  # a key no config has is said as such, not as a key the run fixes
                load_config(None, [item])
            except ConfigError as exc:
                if "unknown config key" in str(exc):
                    raise
            raise InputError(f"--set {key}: a trained run's camera, bands and network are fixed by its training; with "
                             f"--run, evaluate changes only {', '.join(RUN_EVALUATION_KEYS)} (and their keys) "
                             "(other optics: hsicam tolerance; another design: hsicam train)")


def check_out_apart_from_data(out: str | Path, data: str | Path) -> None:
    """InputError when ``--out`` is the ``--data`` folder or holds it: evaluate replaces its ``--out``
    folder whole at the end, which would delete the scenes it has just read (the cubes of a ``--save``
    evaluation read back as data). An ``--out`` inside ``--data`` is allowed: the scene scan skips
    sub-folders holding hsicam outputs (:func:`hsicam.data.datasets.list_scenes`). Paths are compared
    resolved (links followed)."""
    from hsicam.io import broken_link_problem, same_path

    def resolved(path: str | Path) -> Path:
        try:
            return Path(path).resolve()
        except (OSError, RuntimeError):  # RuntimeError: Python < 3.13's symbolic link loop
            for part in reversed((Path(path), *Path(path).parents)):  # name the first link that cannot be followed
                problem = broken_link_problem(part) if part.is_symlink() else None
                if problem is not None:
                    raise InputError(f"{part}: {problem}") from None
            raise InputError(f"{path}: cannot be resolved (a symbolic link loop?)") from None

    o, d = resolved(out), resolved(data)
    same = same_path(o, d)
    if same or o in d.parents:
        what = "is the --data folder" if same else f"holds the --data {data}"
        raise InputError(f"{out}: {what}; evaluate replaces its --out folder whole, which would delete the scenes it "
                         f"reads: give --out a folder outside {data}")


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``hsicam evaluate``: every check before any scene is scored, then the scores, the result files and the means.
    Holds ``--out``'s :class:`~hsicam.io.OutputLock` from its start (where its parent exists) to its last file: a
    ``report`` of the folder running meanwhile is refused, and one running before refuses this command at its start
    (taken at the end only, a report running then made the evaluation fail after all its scoring)."""
    from hsicam.io import OutputLock

    with OutputLock(args.out, "evaluate") as lock:
        lock.acquire()
        return _evaluate(args)


def _evaluate(args: argparse.Namespace) -> int:
    """:func:`cmd_evaluate`, its lock held."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method, interpolated_truth_warning, write_results
    from hsicam.data.datasets import list_scenes
    from hsicam.cli import prepare_output
    from hsicam.io import atomic_output

    check_tile(args.tile)
    alias = _use_current_method_name(args)
    if args.data:
        check_out_apart_from_data(args.out, args.data)
    out = prepare_output(args.out, "dir", replace=True, command="evaluate", run=args.run)
    paths = list_scenes(args.data) if args.data else None  # before the method is built: a bad --data fails at once
    run_cfg, cfg = _evaluation_configs(args)
    from hsicam.runs.checkpoint import read_with_weights_identity

    # the weights read, what results.json records (taken when read, not after the scoring)
    if args.run:
        method, weights = read_with_weights_identity(args.run, _built_method, args, cfg, alias)
    else:
        method, weights = _built_method(args, cfg, alias), {}
    bands = method.camera.bands
    noise = TestNoise(args.sigma_height_nm, args.sensor_sigma, tuple(range(args.seeds)))
    _check_noise_and_sources(args, method, noise, run_cfg, cfg, paths)
    scenes, names, rel, data_label, heldout = _scenes_to_score(args, cfg, paths, bands)
    roles, warning = _training_roles(args, run_cfg, cfg, scenes, paths)
    _check_scenes_before_scoring(args, method, scenes, names, heldout, out, len(bands))
    interpolated = interpolated_truth_warning(scenes, names, bands)  # (each file was read by the check)
    if interpolated:
        log.warning(interpolated)
    show = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    camera_sensor = {k: getattr(cfg.camera.sensor, k) for k in SENSOR_NOISE_KEYS}
    # One result, several files: written into a temporary folder that gets the completion marker and is renamed
    # into place at the end (an interrupted evaluation leaves nothing `report` accepts); with --save each scene's
    # cubes go there as soon as it is scored, and leave memory (all of them were held until the end: 136 MB a
    # 1001×777 scene, about 22 GB for ten KAIST-size scenes)
    with atomic_output(out, overwrite=True, marker={"command": "evaluate", "method": args.method}) as tmp:
        save = None
        if args.save:
            def save(i: int, result) -> None:
                _save_scene_cubes(tmp, args, result, scenes, i, noise, camera_sensor, bands)

        results = evaluate_method(method, scenes, names, noise, args.device, keep_arrays=args.save, progress=show,
                                  paths=rel, tile_px=args.tile, on_scene=save)
        summary = _summary(args, cfg, method, results, noise, data_label, camera_sensor, roles, warning, weights)
        if interpolated:
            summary["truth_interpolated"] = interpolated
        if heldout is not None:
            summary["heldout"] = _heldout_summary(args, cfg, method, heldout, noise, show)
        write_results(tmp, summary)
    _print_means(args, summary, len(results), out)
    return 0


def _applied_sigma_height_nm(args: argparse.Namespace, method) -> float | None:
    """The DOE height noise σ_p (nm) the scoring draws: ``--sigma-height-nm``, else the camera's own; None for a
    camera without a DOE (:func:`~hsicam.engine.evaluate.no_doe_reason`)."""
    from hsicam.engine.evaluate import no_doe_reason

    if no_doe_reason(method.camera) is not None:
        return None
    if args.sigma_height_nm is not None:
        return float(args.sigma_height_nm)
    return method.camera.noise_levels().get("sigma_height_nm")


def _use_current_method_name(args: argparse.Namespace) -> str | None:
    """Rename an old ``--method`` name in ``args`` to its current one; return the old name given, else None."""
    from hsicam.engine.methods import METHOD_ALIASES

    alias = args.method if args.method in METHOD_ALIASES else None
    args.method = METHOD_ALIASES.get(args.method, args.method)  # results carry the method's current name
    return alias


def _evaluation_configs(args: argparse.Namespace):
    """(the config the run trained with, or None without ``--run``; the config of this evaluation)."""
    from hsicam.runs.folder import check_is_run

    if not args.run:
        return None, config_from_args(args.config, args.overrides)
    run = Path(args.run)
    if args.config:
        raise InputError("--run uses the run's config.yaml; drop --config")
    check_is_run(run)
    check_run_overrides(args.overrides)
    run_cfg = run_config_from_args(run)  # as the run trained (its data split and sources)
    cfg = run_config_from_args(run, args.overrides)
    if args.method == "dd-cassi-choi":  # a prior key given by --set, even at its default value
        from hsicam.engine.methods import check_prior_overrides

        check_prior_overrides(run, cfg, args.overrides)
    return run_cfg, cfg


def _built_method(args: argparse.Namespace, cfg, alias: str | None):
    """The reconstruction method ``--method`` names, built for ``cfg`` (and the run's weights)."""
    from hsicam.engine.methods import build_method

    try:
        return build_method(args.method, cfg, args.run, args.device)
    except InputError as exc:
        if alias is None:
            raise
        # the refusal names the method's current name: say it is the one the user asked for
        raise InputError(f"{exc} (--method {alias} is the old name of {args.method})") from None


def _check_noise_and_sources(args: argparse.Namespace, method, noise, run_cfg, cfg, paths) -> None:
    """InputError for test noise the method's camera cannot take, or for a run's held-out sources that the
    evaluation's config cannot regenerate."""
    from hsicam.engine.evaluate import check_test_noise
    from hsicam.engine.provenance import heldout_sources_problem

    # before the scenes are listed or generated: test noise the method's camera cannot take
    check_test_noise(method, noise, f"run {args.run}" if args.run else f"--config {args.config or 'default'}")
    problem = heldout_sources_problem(run_cfg.data, cfg.data) if run_cfg is not None and paths is None else None
    if problem:  # before any scene is generated
        raise InputError(f"{args.run}: {problem}")


def _scenes_to_score(args: argparse.Namespace, cfg, paths, bands):
    """(scenes, their names, their paths as rows show them, the data's label for results.json, the held-out
    scenes and names or None): the ``--data`` files, else the validation split of the config's data."""
    from hsicam.data.datasets import displayable_name, scene_names, scene_path
    from hsicam.data.pipeline import scene_dataset
    from hsicam.engine.evaluate import validation_data_label
    from hsicam.engine.experiments import heldout_scenes, validation_scenes
    from hsicam.engine.provenance import recorded_validation

    if paths is not None:
        scenes = scene_dataset(cfg.data, paths, bands)
        # unique names (stems; the scenes whose stems collide by their paths), each row with its path
        names, rel = scene_names(paths, args.data), [displayable_name(scene_path(p, args.data)) for p in paths]
        return scenes, names, rel, displayable_name(str(Path(args.data).resolve())), None  # (a folder not UTF-8)
    recorded = recorded_validation(args.run, cfg.data, bands) if args.run else None  # the run's own, exactly
    if recorded:
        scenes, names = scene_dataset(cfg.data, recorded, bands), scene_names(recorded)  # day1/a.h5, day2/a.h5 apart
    else:
        scenes, names = validation_scenes(cfg, no_scenes_hint=": score a folder of scenes instead, --data DIR")
    return scenes, names, _relative_to_common_folder(scenes.paths), validation_data_label(cfg), heldout_scenes(cfg)


def _training_roles(args: argparse.Namespace, run_cfg, cfg, scenes, paths):
    """(each scene's role in the run's training, or None; the warning when the run trained on some, or None),
    both warnings logged: that one, and a synthetic split regenerated by a changed generator."""
    from hsicam.engine.provenance import (changed_since_recorded, generator_change_warning, read_data_record,
                                          scene_roles, shown, synthetic_scene_roles, training_scenes_warning)

    # which scenes the run trained on (its data.json; none for the synthetic data or an older run)
    recorded = read_data_record(args.run) if args.run else None
    roles = scene_roles(recorded, scenes.paths) if recorded is not None else None
    if roles is None and args.run and paths is None:
        # the synthetic data: the scored split (the evaluation's data.* keys) against the run's own split
        synthetic = synthetic_scene_roles(run_cfg.data, cfg.data, scenes.paths)
        # recorded where the split is not the run's own validation split (training scenes, or scenes the run never
        # saw: another synthetic seed; session 74's records hunt found those rows with no split and no word)
        roles = synthetic if synthetic is not None and set(synthetic) != {"validation"} else None
    warnings = [training_scenes_warning(roles, args.run) if roles else None]
    changed = changed_since_recorded(recorded, scenes.paths) if recorded is not None else []
    if changed:  # edited or replaced since the run trained: scored as they are now, under the roles of their paths
        warnings.append(f"{len(changed)} scored scene(s) changed since {args.run} trained (size or modification time "
                        f"not its data.json's): {shown(changed)}; they are scored as they are now, not as trained on")
    if args.run and paths is None:  # the run's own synthetic split, regenerated by this hsicam's generator
        warnings.append(generator_change_warning(args.run, run_cfg.data, "is scored"))
    for line in filter(None, warnings):
        log.warning(line)
    # results.json's warning: both (the generator's change was said on stderr alone: session 74's records hunt)
    return roles, " ".join(filter(None, warnings)) or None


def _check_scenes_before_scoring(args: argparse.Namespace, method, scenes, names, heldout, out: Path,
                                 n_bands: int) -> None:
    """InputError for a scene the method cannot score, or (``--save``) too little room for the cubes."""
    from hsicam.engine.evaluate import check_room_for_cubes, check_scenes

    # every scene is read (or its header) before any is scored: a bad one fails now, not after hours of scoring
    check_scenes(method, scenes, names, tile_px=args.tile)
    if heldout is not None:
        check_scenes(method, *heldout, tile_px=args.tile)
    if args.save:
        check_room_for_cubes(out, scenes, n_bands)


def _summary(args: argparse.Namespace, cfg, method, results, noise, data_label: str, camera_sensor: dict, roles,
             warning: str | None, weights: dict) -> dict:
    """results.json's content for the scored scenes: the means and rows, each row's split, the run and its weights
    (``weights``: :func:`~hsicam.runs.checkpoint.weights_identity` when they were read), the ``--set`` overrides the
    scoring took (``config_hash`` covers them, but names none of them) and the software that scored."""
    from hsicam.engine.evaluate import NOISE_DRAWS, SYNTHETIC_VALIDATION, config_hash_of, scored_region, summarize
    from hsicam.engine.provenance import software_record, synthetic_set_record
    from hsicam.runs.pretrained import run_label

    saved = {"saved_cubes": _saved_cubes_text(noise.seeds)} if args.save else {}
    # the run by its label (pretrained:NAME for a shipped camera: its package folder means nothing elsewhere),
    # and the folder it was read from as run_path (where `hsicam report` finds the camera)
    where = {"run": run_label(args.run), "run_path": str(Path(args.run).resolve())} if args.run else {"run": None}
    if data_label == SYNTHETIC_VALIDATION and roles is not None and set(roles) == {"unseen"}:
        # another synthetic set than the run's (e.g. --set data.synthetic_seed=5): not its validation split
        keys = ", ".join(o for o in args.overrides if o.startswith("data.")) or "the evaluation's data keys"
        data_label = f"synthetic scenes of {keys}, none of them the run's"
    extra = {"overrides": list(args.overrides)} if args.overrides else {}
    if not args.data and cfg.data.root is None:  # which cached synthetic set was read (config.yaml does not say)
        extra["synthetic_set"] = synthetic_set_record(cfg.data, method.camera.bands)
    summary = summarize(results, method=args.method, **where, data=data_label, config_hash=config_hash_of(cfg),
                        noise={"sigma_height_nm": args.sigma_height_nm, "sensor_sigma": args.sensor_sigma, "seeds": args.seeds,
                               # the DOE height noise the scoring drew (--sigma-height-nm, else the camera's own
                               # camera.doe.sigma_height_nm: recorded as null, it read as none; session 73)
                               "sigma_height_nm_applied": _applied_sigma_height_nm(args, method),
                               # the capture noise of the evaluation's config (the camera's own, or --set)
                               "camera_sensor": camera_sensor, "draws": NOISE_DRAWS},
                        bands_nm=method.camera.bands.centers_nm.tolist(),
                        region=scored_region(method.camera, method.border_px), **extra, **saved,
                        software=software_record(args.device))
    if roles is not None:
        for row, role in zip(summary["scenes"], roles):
            row["split"] = role
    if warning:
        summary["warning"] = warning
    if args.run:  # which weights were scored (hsicam pretrained pack checks its --results by it)
        summary.update(weights)
    return summary


def _heldout_summary(args: argparse.Namespace, cfg, method, heldout, noise, show) -> dict:
    """results.json's ``heldout``: the scores of the scenes whose spectral sources training never saw."""
    from hsicam.engine.evaluate import HELDOUT_NOISE_SET, evaluate_method, heldout_sources_label, summarize

    held = evaluate_method(method, heldout[0], heldout[1], noise, args.device, keep_arrays=False, progress=show,
                           paths=_relative_to_common_folder(heldout[0].paths), tile_px=args.tile,
                           scene_set=HELDOUT_NOISE_SET)
    return {"data": heldout_sources_label(cfg, "scenes whose reflectances and lights the "
                                               "training scenes never contain"),
            **summarize(held)}


def _save_scene_cubes(tmp: Path, args: argparse.Namespace, result, scenes, i: int, noise, camera_sensor: dict,
                      bands) -> None:
    """``--save``: scene ``i``'s estimate and ground truth (``result``'s arrays) as ``tmp/cubes/NAME_estimate.h5``
    and ``NAME_truth.h5``, then the arrays dropped from ``result``: one scene's cubes in memory at a time."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.runs.pretrained import run_label

    scene = {"scene": result.name, "scene_path": result.path, "source": str(Path(scenes.paths[i]).resolve()),
             "normalization_peak": scenes.info(i).peak}
    # (command and role: a data folder that a copy of these cubes lands in lists the estimate as none
    # of its scenes, hsicam.data.estimates.is_estimate)
    estimate = {"command": "evaluate", "role": "estimate", "method": args.method, **scene,
                "run": run_label(args.run) if args.run else None, "seed": result.seed,
                "seeds_scored": len(noise.seeds), "noise": {**result.noise, "camera_sensor": camera_sensor}}
    if len(noise.seeds) > 1:
        estimate["note"] = (f"the estimate of seed {result.seed}, the first of the {len(noise.seeds)} seeds scored: "
                            "results.json holds means over the seeds, this scene's per_seed the metrics "
                            "of each (this cube's first)")
    for role, cube, meta in (("estimate", result.estimate, estimate),
                             ("truth", result.truth, {"role": "ground truth", **scene})):
        path = tmp / "cubes" / f"{result.name}_{role}.h5"
        if path.exists():  # scene names are unique (ignoring case): never overwrite a saved cube
            raise RuntimeError(f"{path.name}: written twice (scene names must be unique)")
        write_cube_h5(path, cube, bands, meta)
    result.truth = result.estimate = None


def _print_means(args: argparse.Namespace, summary: dict, n_scenes: int, out: Path) -> None:
    """The results' table and mean lines on stdout (the held-out scenes' too)."""
    from hsicam.engine.evaluate import format_table

    print(format_table(summary))
    m = summary["mean"]
    print(f"{args.method}: mean PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, SAM {m['sam']:.2f}° "
          f"over {n_scenes} scenes -> {out}")
    if summary.get("exact_zero_bands"):  # said where the mean is read, not only in results.md
        from hsicam.engine.evaluate import exact_band_note

        log.warning("evaluate: %s", exact_band_note(summary["exact_zero_bands"]))
    if "heldout" in summary:
        h = summary["heldout"]["mean"]
        print(f"{args.method}, held-out spectral sources: mean PSNR {h['psnr']:.2f} dB, SSIM {h['ssim']:.4f}, "
              f"SAM {h['sam']:.2f}° over {len(summary['heldout']['scenes'])} scenes")


def _relative_to_common_folder(paths) -> list[str]:
    """Scene paths relative to the folder that holds them all (the synthetic dataset's)."""
    from hsicam.data.datasets import displayable_name, scene_path

    root = os.path.commonpath([os.path.abspath(Path(p).parent) for p in paths]) if len(paths) else "."
    return [displayable_name(scene_path(p, root)) for p in paths]


def _saved_cubes_text(seeds) -> str:
    """What the cubes ``--save`` writes hold, for results.json/md and the estimates' metadata."""
    first = f"seed {seeds[0]}'s estimate"
    if len(seeds) > 1:
        first += (f" (the first of the {len(seeds)} seeds scored: the results are means over the seeds; each row's "
                  f"per_seed in results.json has seed {seeds[0]}'s metrics, those of the saved cube)")
    return f"cubes/NAME_estimate.h5: {first}; cubes/NAME_truth.h5: the ground truth (the scored area)"


def cmd_experiment(args: argparse.Namespace) -> int:
    from hsicam.engine.experiments import experiment_lock, format_experiment_table, run_experiment
    from hsicam.cli import prepare_output
    from hsicam.io import is_complete, mark_complete, output_description, read_marker

    out = prepare_output(args.out or f"runs/experiments/{args.name}-{args.scale}", "dir")
    # the folder is this process's from its checks to its marker (run_experiment takes the same lock, re-entrant):
    # a second experiment started meanwhile is refused naming this one, not run into the same files
    with experiment_lock(out):
        # accepted: absent or empty, an interrupted experiment (runs/, no marker) or a finished one
        if out.is_dir() and any(out.iterdir()):
            if is_complete(out):
                if read_marker(out).get("command") != "experiment":
                    raise InputError(f"{out}: holds {output_description(out)}, not an experiment; choose another --out")
            elif not (out / "runs").is_dir():
                raise InputError(f"{out}: folder exists and is not an experiment folder; choose another --out")
        # run_experiment checks the folder holds this experiment at this scale, then takes its marker off
        result = run_experiment(args.name, args.scale, out, tuple(range(args.seeds)))
        mark_complete(out, {"command": "experiment", "experiment": args.name, "scale": args.scale})
    print(format_experiment_table(result))
    print(f"-> {out}/experiment.json, {out}/table.md")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from hsicam.cli import prepare_output
    from hsicam.report.html import build_report

    if Path(args.dir).is_dir():
        prepare_output(Path(args.dir) / "report", "dir")
    index = build_report(args.dir)
    print(f"report -> {index}")
    return 0
