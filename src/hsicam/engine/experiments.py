"""The paper's experiments, one call each, resumable, written into one folder.

    compare     Table 1: our camera versus the CASSI baselines that are available
    ablation    Table 2: DOE × CFA on/off (three trained cameras)
    noise       Fig. 7: cameras trained without and with noise, tested on σ_p × σ_s grids
    cfa-period  CFA periods 3, 6, 9, 12, 15

Scales: ``tiny`` (tests), ``quick`` (this CPU) and ``paper`` (GPU): the preset of that name plus
each experiment's overrides. Every trained camera lives in ``OUT/runs/<name>``; a finished run
is reused, an interrupted one resumed. All cameras are evaluated on the same validation scenes
(the preset's scene-level split), with the same seeds. One folder holds one experiment at one
scale: a folder of another is refused before any change (:func:`check_experiment_folder`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hsicam.config import Config, absolute_paths, load_config, training_differences
from hsicam.engine.evaluate import TestNoise, evaluate_method, scored_region, summarize
from hsicam.engine.linear_step import refresh_linear_step
from hsicam.engine.methods import baseline_names, build_method, sensor_border_px
from hsicam.engine.names import EXPERIMENTS, SCALES  # their one home (the CLI reads them torch-free)
from hsicam.engine.prior import check_choi_prior, ensure_choi_prior
from hsicam.engine.train import train
from hsicam.errors import InputError
from hsicam.io import OutputLock, atomic_open, clear_complete, clear_derived, write_json
from hsicam.runs.checkpoint import read_with_weights_identity

log = logging.getLogger(__name__)

NOISE_SIGMA_HEIGHT_NM = (0.0, 15.0, 30.0, 45.0, 60.0)
NOISE_SIGMA_SENSOR = (0.0, 0.0025, 0.005, 0.0075, 0.01)
CFA_PERIODS = (3, 6, 9, 12, 15)


@dataclass(frozen=True)
class RunSpec:
    """One trained camera of an experiment: its name under ``OUT/runs``, the overrides of the scale
    preset it is trained with, and ``note``: why the experiment sets keys beyond the swept one
    (recorded in experiment.json and table.md)."""

    name: str
    overrides: tuple[str, ...] = ()
    note: str = ""


def run_specs(experiment: str, cfg: Config | None = None) -> list[RunSpec]:
    """The trained cameras an experiment needs (``cfg``: the scale preset, for the ablation)."""
    if experiment == "compare":
        return [RunSpec("doe-learned")]
    if experiment == "ablation":
        return [RunSpec("doe+cfa"), RunSpec("no-doe", ("camera.doe.enabled=false",)),
                RunSpec("no-cfa", ("camera.cfa.enabled=false", *same_network_without_cfa(cfg)))]
    if experiment == "noise":
        return [RunSpec("trained-clean"),
                RunSpec("trained-noisy", ("train.sigma_height_nm=[0, 60]", "train.sensor_sigma=[0, 0.01]"))]
    if experiment == "cfa-period":
        return cfa_period_specs(cfg)
    raise InputError(f"unknown experiment {experiment!r}; choose one of {', '.join(EXPERIMENTS)}")


def same_network_without_cfa(cfg: Config | None) -> tuple[str, ...]:
    """Overrides that keep the preset's network unchanged when its CFA is switched off.

    A mosaic front end regroups the sensor by the CFA period; without a CFA it would fall back to
    3 × 3 (a trunk at 1/3 instead of 1/9 resolution: 9× the cost and another network). The no-CFA
    run of the ablation pins the factor to the preset's period, so that only the optics differ.
    """
    if cfg is None or not cfg.camera.cfa.enabled or cfg.camera.cfa.period <= 1:
        return ()
    m, out = cfg.camera.cfa.period, []
    if cfg.model.kind == "mosaic" and cfg.model.mosaic.factor == 0:
        out.append(f"model.mosaic.factor={m}")
    if cfg.model.kind == "unrolled" and cfg.model.unrolled.init == "mosaic" and cfg.model.unrolled.mosaic.factor == 0:
        out.append(f"model.unrolled.mosaic.factor={m}")
    return tuple(out)


def _power_of_two(m: int) -> bool:
    return m >= 1 and not m & (m - 1)


def cfa_period_specs(cfg: Config | None, periods: tuple[int, ...] = CFA_PERIODS) -> list[RunSpec]:
    """The cameras of the CFA-period sweep on the scale preset ``cfg``: ``camera.cfa.period=m``,
    plus what the preset needs to build a camera at every period of the sweep.

    - The dispersed filter layout (quick, paper presets may set it) is an ordered-dither matrix
      that exists for power-of-two periods only: when a period of the sweep is not one, every run
      of the sweep uses the random layout (one layout across the sweep, so the periods are
      compared, not the layouts).
    - The linear consistency step's filters (``model.consistency.window_px``) must be at least as
      wide as the CFA period: when the sweep's largest period is wider, every run uses the
      smallest odd width that covers it.
    - A mosaic front end regroups the sensor by a multiple of the CFA period: a preset factor that
      is not a multiple of ``m`` becomes the multiple of ``m`` nearest to it (at least ``m``), so the
      trunk works at about the preset's resolution.
    """
    if cfg is None:
        return [RunSpec(f"period-{m}", (f"camera.cfa.period={m}",)) for m in periods]
    random_layout = cfg.camera.cfa.layout == "dispersed" and not all(_power_of_two(m) for m in periods)
    factors = []  # (config key, preset factor) of the network's mosaic front end, if any
    if cfg.model.kind == "mosaic" and cfg.model.mosaic.factor:
        factors.append(("model.mosaic.factor", cfg.model.mosaic.factor))
    if cfg.model.kind == "unrolled" and cfg.model.unrolled.init == "mosaic" and cfg.model.unrolled.mosaic.factor:
        factors.append(("model.unrolled.mosaic.factor", cfg.model.unrolled.mosaic.factor))
    c = cfg.model.consistency  # the linear consistency step's filters must see every CFA phase
    window = (max(c.window_px, *(m | 1 for m in periods))
              if c.kind == "linear" and c.iterations > 0 and cfg.camera.kind == "doe" else c.window_px)
    specs = []
    for m in periods:
        overrides, notes = [f"camera.cfa.period={m}"], []
        if random_layout:
            overrides.append("camera.cfa.layout=random")
            notes.append("camera.cfa.layout=random (the preset's dispersed layout needs a power-of-two period)")
        if window != c.window_px:
            overrides.append(f"model.consistency.window_px={window}")
            notes.append(f"model.consistency.window_px={window} (the linear consistency step's filters must be as "
                         "wide as the largest period of the sweep)")
        for key, f in factors:
            if f % m:
                new = m * max(1, round(f / m))
                overrides.append(f"{key}={new}")
                notes.append(f"{key}={new} (a multiple of the period near the preset's {f})")
        specs.append(RunSpec(f"period-{m}", tuple(overrides), "; ".join(notes)))
    return specs


def is_finished(run: Path) -> bool:
    """A run whose metrics.jsonl ends with its final record and that has its weights."""
    m = run / "metrics.jsonl"
    if not (m.is_file() and (run / "model.safetensors").is_file() and (run / "config.yaml").is_file()):
        return False  # (without its config.yaml a run is damaged: load_run says so)
    lines = [x for x in m.read_text(encoding="utf-8-sig").splitlines() if x.strip()]
    try:
        return bool(lines) and bool(json.loads(lines[-1]).get("final", False))
    except json.JSONDecodeError:
        return False


#: A scale preset's RDN on the DD-CASSI camera, reading the measurement alone (the paper's input; the
#: DOE-camera presets may switch on the CFA demosaic input, which CASSI has no CFA for). The
#: code-aware input (model.rdn.backprojection_input) ties it at quick scale (31.89 against 31.88 dB,
#: docs/training_log.md): 640 CPU steps do not teach either to decode the code, and the experiments
#: keep the paper's input.
#: The learned CASSI rows are scored without the DOE presets' consistency step: on the blind RDN one
#: GAP projection lowers the total squared error but moves it between bands (quick, 8 validation
#: scenes: 31.90 → 31.44 dB per-band PSNR, SSIM 0.744 → 0.724; docs/networks.md), and the unrolled
#: network's stages are GAP steps already.
CASSI_RDN_OVERRIDES = ("camera.kind=dd_cassi", "model.kind=rdn", "model.rdn.demosaic_input=false",
                       "model.rdn.backprojection_input=false", "model.consistency.iterations=0")
#: The scale preset's unrolled network on the DD-CASSI camera: it starts from the back-projection
#: Aᵀy ⊘ AᵀA1 (no CFA to demosaic) and its data steps are GAP projections (ΦΦᵀ is diagonal).
CASSI_UNROLLED_OVERRIDES = ("camera.kind=dd_cassi", "model.kind=unrolled", "model.unrolled.init=backprojection",
                            "model.unrolled.step=gap", "model.consistency.iterations=0")


LEARNED_CASSI = {"dd-cassi-rdn": CASSI_RDN_OVERRIDES, "dd-cassi-unrolled": CASSI_UNROLLED_OVERRIDES}


def check_same_training(run: Path, cfg: Config) -> None:
    """InputError naming the first differences when the run folder ``run`` exists and was started
    with another config than ``cfg``, up to how it runs (:func:`~hsicam.config.training_differences`)."""
    if (run / "config.yaml").is_file():
        # a data.root or camera file as given here against the run's, recorded absolute (a relative one as read from here)
        from hsicam.runs.folder import EMPTY_RUN_CONFIG

        have = load_config(run / "config.yaml", empty=EMPTY_RUN_CONFIG)
        changed = training_differences(absolute_paths(have), absolute_paths(cfg))
        if changed:
            raise InputError(f"{run} was trained with another config ({'; '.join(changed)}): "
                             "delete it to train it again, or choose another output folder")


def ensure_trained(run: Path, preset, overrides: tuple[str, ...] = ()) -> str:
    """Train ``run`` (or resume it, or reuse it when finished); returns "reused", "resumed" or "trained".

    ``preset``: a preset name or config path (``overrides`` applied), or an already loaded
    :class:`~hsicam.config.Config`. A run folder that exists must have been started with the same
    config, up to how it runs (:func:`~hsicam.config.training_differences`), so that a table never
    reports a camera trained with other settings: otherwise :class:`InputError` names the first
    differences. The run's ``model.consistency`` and ``train.keep_weights`` (inference settings)
    become ``cfg``'s, its kept weights and linear step's filters made to match
    (:func:`~hsicam.engine.linear_step.refresh_linear_step`).
    """
    cfg = preset if isinstance(preset, Config) else load_config(preset, list(overrides))
    check_same_training(run, cfg)
    if (run / "config.yaml").is_file():
        if is_finished(run):
            log.info("%s: finished, reused", run)
            changed = refresh_linear_step(run, cfg.model.consistency, cfg.train.keep_weights)  # (training: when it ends)
            if changed:
                log.info("%s: %s", run, "; ".join(changed))
            return "reused"
        log.info("%s: resuming", run)
        train(cfg, run, resume=True)
        return "resumed"
    what = (f"camera {cfg.camera.kind}, network {cfg.model.kind}, {cfg.train.epochs} epochs"
            + ("" if isinstance(preset, Config) else f", from {preset}"))  # ("given config" said nothing)
    log.info("%s: training (%s)", run, what)
    train(cfg, run)
    return "trained"


def validation_scenes(cfg, no_scenes_hint: str = ""):
    """The preset's validation scenes (SceneDataset) and their names; ``no_scenes_hint`` ends the refusal of a
    config that has none (what the caller's user can do instead)."""
    from hsicam.data.pipeline import no_validation_reason, scene_dataset, validation_split

    bands = cfg.bands.to_bands()
    val, n_scenes = validation_split(cfg.data, bands)  # of the synthetic data, only these scenes are generated
    if not val:
        raise InputError(f"the config has no validation scenes ({no_validation_reason(cfg.data, n_scenes)})"
                         f"{no_scenes_hint}")
    from hsicam.data.datasets import scene_names

    # unique names (day1/a.h5 and day2/a.h5 were both "a": evaluate --save then failed writing a_estimate.h5 twice)
    return scene_dataset(cfg.data, val, bands), scene_names(val)


def scored_scenes(cfg, heldout: bool = False):
    """(SceneDataset, names) of the run config's validation split, or (``heldout``) of its
    held-out-sources set; :class:`InputError` when the config holds nothing out."""
    if not heldout:
        return validation_scenes(cfg)
    held = heldout_scenes(cfg)
    if held is None:
        raise InputError("the run holds out no spectral sources (data.holdout_sources)")
    return held


def heldout_scenes(cfg):
    """The held-out-sources validation scenes (SceneDataset) and their names, or None (real data,
    or nothing held out): scenes built only from spectral sources the training scenes never use."""
    from hsicam.data.datasets import list_scenes
    from hsicam.data.pipeline import heldout_root, scene_dataset

    bands = cfg.bands.to_bands()
    root = heldout_root(cfg.data, bands)
    if root is None:
        return None
    paths = list_scenes(root)
    return scene_dataset(cfg.data, paths, bands), [p.stem for p in paths]


def _scene_lines(what: str):
    """evaluate_method's per-scene line (``[k/N] scene: PSNR …, SSIM …, SAM … (t s)``) logged at INFO as
    ``experiment: WHAT [k/N] …``: an experiment scoring slow baselines (DeSCI: a minute a scene) is not silent."""
    return lambda line: log.info("experiment: %s %s", what, line)


def _row(name: str, summary: dict, **extra: Any) -> dict:
    m = summary["mean"]
    return {"method": name, "psnr": m["psnr"], "ssim": m["ssim"], "sam": m["sam"], "runtime_s": m["runtime_s"], **extra}


def run_experiment(experiment: str, scale: str, out: str | Path, seeds: tuple[int, ...] = (0,),
                   baselines: tuple[str, ...] | None = None) -> dict:
    """Run (or resume) one experiment; writes ``experiment.json`` and ``table.md`` into ``out``.

    Holds ``out``'s :class:`~hsicam.io.OutputLock` from its checks to its last file (``hsicam experiment`` from
    before its checks to its marker: re-entrant): another process writing the folder is refused in one line,
    naming its pid."""
    if scale not in SCALES:
        raise InputError(f"unknown scale {scale!r}; choose one of {', '.join(SCALES)}")
    out = Path(out)
    cfg = load_config(scale)  # every check before any change (the configs of all its cameras too)
    seeds = scored_seeds(experiment, scale, cfg, seeds)
    specs = run_specs(experiment, cfg)
    run_cfgs = run_configs(experiment, scale)
    # one experiment at a time per folder: two at once both trained and scored into it, and its experiment.json and
    # table.md could come from different runs (two --seeds), marked complete all the same
    with experiment_lock(out):
        return _run_experiment(experiment, scale, out, cfg, seeds, specs, run_cfgs, baselines)


def experiment_lock(out: Path) -> OutputLock:
    """The experiment folder ``out``'s :class:`~hsicam.io.OutputLock`, taken (one-line InputError naming the
    process that holds it; re-entrant), to be let go by ``with``. The folder's parent is made first: the lock file
    lies beside the folder, and without a parent nothing would be locked (a first experiment under a new
    runs/experiments/, which a second one could then run into)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = OutputLock(out, "experiment")
    lock.acquire()
    return lock


def grid_worst(values) -> float:
    """The least of a noise grid's scores that are defined (not NaN, as the means of
    :func:`~hsicam.engine.evaluate.summarize` leave an undefined scene out), NaN when none is: min() returned a NaN
    point or skipped it by its place in the grid."""
    kept = [v for v in values if not math.isnan(v)]
    return min(kept) if kept else math.nan


def _run_experiment(experiment: str, scale: str, out: Path, cfg: Config, seeds: tuple[int, ...], specs: list[RunSpec],
                    run_cfgs: dict[str, Config], baselines: tuple[str, ...] | None) -> dict:
    """:func:`run_experiment` under the folder's lock."""
    check_experiment_folder(out, experiment, scale, run_cfgs)
    # filled in place (its trained runs resume): a finished folder's marker comes off until
    # experiment.json and table.md are written again (``hsicam experiment`` marks it then)
    if out.is_dir():
        clear_derived(out)  # its report/ would describe the old results
        clear_complete(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    for spec in specs:
        ensure_trained(out / "runs" / spec.name, run_cfgs[spec.name])
    scenes, names = validation_scenes(cfg)
    rows: list[dict] = []
    grids: dict[str, Any] = {}
    region = None  # the pixels the DOE cameras score (the CASSI rows of compare are scored on the same)
    figures = ComparisonFigures(experiment in FIGURE_EXPERIMENTS, cfg.bands.to_bands(), len(names))
    for spec in specs:
        run = out / "runs" / spec.name
        # evaluated as it was trained (the preset plus the spec's overrides, e.g. the sweep's wider linear step)
        method, weights = read_with_weights_identity(run, build_method, "doe-learned", run_cfgs[spec.name], run)
        if region is None:
            region, doe_camera = scored_region(method.camera), method.camera
        if experiment == "noise":
            grid = []
            for sp in NOISE_SIGMA_HEIGHT_NM:
                for ss in NOISE_SIGMA_SENSOR:
                    res = evaluate_method(method, scenes, names, TestNoise(sp, ss, seeds), keep_arrays=False,
                                          progress=_scene_lines(f"{spec.name}, σ_h {sp:g} nm, σ {ss:g}"))
                    s = summarize(res)
                    grid.append({"sigma_height_nm": sp, "sensor_sigma": ss, "psnr": s["mean"]["psnr"], "ssim": s["mean"]["ssim"]})
            grids[spec.name] = grid
            clean = grid[0]
            rows.append({"method": spec.name, "psnr": clean["psnr"], "ssim": clean["ssim"],
                         "psnr_worst": grid_worst(g["psnr"] for g in grid), "ssim_worst": grid_worst(g["ssim"] for g in grid)})
        else:
            res = evaluate_method(method, scenes, names, TestNoise(seeds=seeds), keep_arrays=figures.chosen_names(),
                                  progress=_scene_lines(spec.name))
            if figures.wanted and spec is specs[0]:  # our camera (the first): its worst and median scenes
                figures.choose(res)  # (its arrays of the first seed, its scores of every seed: the table's)
                figures.keep(spec.name, _rescore(method, scenes, names, figures.chosen_names(), seeds[0]),
                             scores={r.name: r.metrics for r in res})
            else:
                figures.keep(spec.name, res)
            s = summarize(res)
            rows.append(_row(spec.name, s, run=str(run), scenes=s["scenes"]))
        # which weights were scored (the best validation's is a selection on these scenes), and their hash: the
        # report draws a run's camera only while its weights are still these
        rows[-1].update(weights)
        if spec.note:
            rows[-1]["overrides"], rows[-1]["note"] = list(spec.overrides), spec.note
    if experiment == "compare":
        rows += _baseline_rows(cfg, scale, out, scenes, names, seeds, baseline_names() if baselines is None else baselines,
                               border_px=sensor_border_px(doe_camera), figures=figures)
    result = {"experiment": experiment, "scale": scale, "seeds": list(seeds), "scenes": names,
              "conventions": summarize([])["conventions"], "region": region, "rows": rows}
    if figures.wanted:
        several = f"renders and error maps of noise seed {seeds[0]}; PSNR / SSIM: means over noise seeds " \
                  f"{', '.join(map(str, seeds))}, as experiment.json records them"
        result["figures"] = figures.write(out, f"{experiment}, {scale} scale, noise seed {seeds[0]}",
                                          several if len(seeds) > 1 else "")
    notes = [f"{spec.name}: {spec.note}" for spec in specs if spec.note]
    if notes:
        result["notes"] = notes
    if grids:
        result["noise_grid"] = {"sigma_height_nm": list(NOISE_SIGMA_HEIGHT_NM), "sensor_sigma": list(NOISE_SIGMA_SENSOR),
                                "results": grids}
    write_json(out / "experiment.json", result)
    with atomic_open(out / "table.md", "w", encoding="utf-8") as fh:
        fh.write(format_experiment_table(result) + "\n")
    return result


#: The experiments whose folder gets comparison figures (:class:`ComparisonFigures`), by the scene's role.
#: Not the CFA-period sweep: a figure chooses its scenes by our camera (the first row) and sets every other row
#: beside it, and the sweep has no such camera. Its rows are candidate periods of one design; its first, period 3,
#: is the scale's own camera at tiny scale only (quick's 4 x 4 CFA is not among CFA_PERIODS, paper's 9 x 9 is the
#: third row), so its figures would show period 3's worst and median scenes with period 3 in the place of ours.
#: The sweep's answer is its table (PSNR / SSIM / SAM against the period).
FIGURE_EXPERIMENTS = ("compare", "ablation")
COMPARISON_FILES = {"worst": "comparison_worst.png", "median": "comparison_median.png"}


class ComparisonFigures:
    """The comparison figures of an experiment (``wanted``): for our camera's worst and median validation scene
    by PSNR (the first method scored; the upper median, so two scenes give two figures), the truth and every
    method's reconstruction, rendered and with its error map (:func:`~hsicam.report.reconstruction.
    plot_method_comparison`). Only the chosen scenes' arrays are kept, and of them only what the figure draws
    (:class:`~hsicam.report.reconstruction.ComparisonPanel`: 4 values a pixel, not two cubes)."""

    def __init__(self, wanted: bool, bands, n_scenes: int):
        self.wanted, self.bands, self.n_scenes = wanted, bands, n_scenes
        self.chosen: dict[str, str] = {}  # role -> scene
        self.truth_rgb: dict[str, Any] = {}  # scene -> (H, W, 3)
        self.panels: dict[str, list] = {}  # scene -> ComparisonPanel per method, in the rows' order

    def chosen_names(self) -> set[str] | bool:
        """What :func:`~hsicam.engine.evaluate.evaluate_method` keeps arrays of: the chosen scenes (False: none)."""
        return set(self.chosen.values()) if self.wanted else False

    def choose(self, results) -> None:
        order = sorted(results, key=lambda r: r.metrics["psnr"])
        picks = {"worst": order[0].name, "median": order[len(order) // 2].name} if order else {}
        self.chosen = {role: scene for role, scene in picks.items() if role == "worst" or scene != picks["worst"]}

    def keep(self, label: str, results, scores: dict[str, dict] | None = None) -> None:
        """The panels of ``label``'s results on the chosen scenes: their first seed's estimate, titled with their
        scores (``scores``, by scene, else the results' own): the means over every seed scored, as the experiment's
        table and experiment.json's per-scene rows give them, not the first seed's alone."""
        from hsicam.report.reconstruction import comparison_panel, cube_rgb

        if not self.wanted:
            return
        for r in results:
            if r.name not in self.chosen.values() or r.estimate is None:
                continue
            if r.name not in self.truth_rgb:
                self.truth_rgb[r.name] = cube_rgb(r.truth, self.bands)
            mean = r.metrics if scores is None else scores[r.name]
            scored = self.truth_rgb[r.name].shape[:2]
            try:
                if tuple(r.truth.shape[-2:]) != tuple(scored):  # scored on other pixels than the figure's truth
                    raise ValueError(f"scored on {r.truth.shape[-2]}x{r.truth.shape[-1]} px, the figure's truth on "
                                     f"{scored[0]}x{scored[1]}")
                panel = comparison_panel(label, r.truth, r.estimate, self.bands, mean["psnr"], mean["ssim"])
            except ValueError as exc:  # not on the pixels the others are scored on: left out of the figure, said
                log.warning("experiment: %s left out of the comparison figure of %s (%s)", label, r.name, exc)
                continue
            self.panels.setdefault(r.name, []).append(panel)

    def write(self, out: Path, what: str, note: str = "") -> list[dict]:
        """Draw the figures into ``out`` (COMPARISON_FILES; an earlier run's of a role not drawn now removed),
        titled with ``what`` (and ``note`` on a second line); their records for experiment.json."""
        from hsicam.report.reconstruction import plot_method_comparison

        records = []
        for role, file in COMPARISON_FILES.items():
            (out / file).unlink(missing_ok=True)
            scene = self.chosen.get(role)
            if scene is None or scene not in self.panels:
                continue
            first = self.panels[scene][0].label
            plot_method_comparison(self.truth_rgb[scene], self.panels[scene], out / file,
                                   title=f"{scene}: the {role} of {self.n_scenes} validation scenes for {first} by "
                                         f"PSNR ({what})" + (f"\n{note}" if note else ""))
            records.append({"file": file, "scene": scene, "role": role,
                            "methods": [p.label for p in self.panels[scene]]})
        return records


def _rescore(method, scenes, names, keep: set[str], seed: int):
    """``method``'s results, with arrays, on the scenes ``keep`` names alone under noise seed ``seed``: the same
    captures and estimates as in the experiment's scoring (every scene's noise is drawn from its own seed,
    :func:`~hsicam.engine.evaluate.capture_noise_seed`), for the figures of the method that chooses their scenes."""
    idx = [i for i, n in enumerate(names) if n in keep]
    return evaluate_method(method, [scenes[i] for i in idx], [names[i] for i in idx], TestNoise(seeds=(seed,)))


def has_test_noise(cfg: Config) -> bool:
    """Whether the config's camera adds random noise at test time (its own, as ``evaluate`` scores it without
    --sigma options): Poisson–Gaussian sensor noise, a Gaussian σ_s or a DOE height σ_p above 0."""
    sensor = cfg.camera.sensor  # (noise "none" leaves a σ_s unapplied: hsicam.sensor.SensorNoise.from_config)
    return (sensor.noise == "poisson_gaussian" or (sensor.noise != "none" and sensor.sigma > 0)
            or cfg.camera.doe.sigma_height_nm > 0)


def scored_seeds(experiment: str, scale: str, cfg: Config, seeds: tuple[int, ...]) -> tuple[int, ...]:
    """The noise seeds an experiment scores: ``seeds``, or its first alone (with a warning) when nothing it scores is
    noisy (not the noise experiment, and no test noise in ``cfg``, :func:`has_test_noise`): every seed would score
    the same captures, N identical tables that read as replication."""
    if len(seeds) > 1 and experiment != "noise" and not has_test_noise(cfg):
        log.warning("experiment %s at %s scale has no test noise (the camera's sensor and DOE noise are 0): its %d "
                    "seeds would score the same; scoring seed %d only (the runs are trained once, whatever the seeds)",
                    experiment, scale, len(seeds), seeds[0])
        return tuple(seeds[:1])
    return tuple(seeds)


def run_configs(experiment: str, scale: str) -> dict[str, Config]:
    """The config of every camera ``experiment`` trains at ``scale``, by run name (compare: its
    learned CASSI baselines too); building them checks them all before any training."""
    specs = run_specs(experiment, load_config(scale))
    cfgs = {spec.name: load_config(scale, list(spec.overrides)) for spec in specs}
    if experiment == "compare":
        cfgs.update({name: load_config(scale, list(o)) for name, o in LEARNED_CASSI.items()})
    return cfgs


def recorded_experiment(out: Path) -> tuple[str, str] | None:
    """(experiment, scale) that the folder ``out`` holds the results of: from its completion marker,
    else from its experiment.json (the marker comes off while an experiment is re-run); None when
    it records none."""
    from hsicam.io import read_marker

    for info in (read_marker(out), _read_json(out / "experiment.json")):
        name, scale = info.get("experiment"), info.get("scale")
        if isinstance(name, str) and isinstance(scale, str):
            return name, scale
    return None


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def check_experiment_folder(out: Path, experiment: str, scale: str, run_cfgs: dict[str, Config]) -> None:
    """InputError, before any change, when the folder ``out`` holds another experiment than
    ``experiment`` at ``scale``: the experiment (or scale) its marker or experiment.json records,
    run folders this experiment does not write (another experiment's, interrupted), or a run that
    was trained with another config than ``run_cfgs`` (:func:`run_configs`) gives it. Reads only."""
    default = f"runs/experiments/{experiment}-{scale}"
    recorded = recorded_experiment(out)
    if recorded is not None and recorded != (experiment, scale):
        raise InputError(f"{out}: holds the results of experiment {recorded[0]} at {recorded[1]} scale; experiment "
                         f"{experiment} --scale {scale} would replace them and mix its runs with theirs: choose "
                         f"another --out (e.g. {default})")
    runs = out / "runs"
    if not runs.is_dir():
        return
    names = {*run_cfgs, *(("dd-cassi-choi",) if experiment == "compare" else ())}  # compare: its prior too
    other = sorted(p.name for p in runs.iterdir() if p.name not in names and not p.name.startswith("."))
    if other:
        shown = ", ".join(other[:3]) + (f" and {len(other) - 3} more" if len(other) > 3 else "")
        raise InputError(f"{runs}: holds {shown}, which experiment {experiment} does not train (another experiment's "
                         f"runs); choose another --out (e.g. {default})")
    for name, cfg in run_cfgs.items():
        run = runs / name
        if not (run / "config.yaml").is_file():
            continue
        have = load_config(run / "config.yaml")
        if not training_differences(have, cfg):
            continue
        for other_scale in SCALES:
            if other_scale != scale and not training_differences(have, run_configs(experiment, other_scale)[name]):
                raise InputError(f"{run} was trained at {other_scale} scale: {out} holds experiment {experiment} at "
                                 f"{other_scale} scale, not {scale}; choose another --out (e.g. {default})")
        check_same_training(run, cfg)
    if experiment == "compare":  # its Choi prior, trained by an earlier compare: checked now, not after the other rows
        check_choi_prior(runs / "dd-cassi-choi", scale)


def _baseline_rows(cfg, scale, out, scenes, names, seeds, baselines, border_px: int = 0,
                   figures: ComparisonFigures | None = None) -> list[dict]:
    """Rows for the CASSI baselines (learned ones are trained, or resumed, first), each scored without a
    border of ``border_px`` px a side: on the pixels the DOE camera's rows are scored on (its sensor area);
    ``figures`` keeps their panels of its chosen scenes."""
    rows = []
    for name in baselines:
        run = None
        if name in LEARNED_CASSI:
            run = out / "runs" / name
            ensure_trained(run, scale, LEARNED_CASSI[name])
        elif name == "dd-cassi-choi":
            run = ensure_choi_prior(out / "runs" / name, scale)
        # a learned CASSI method is evaluated with its own overrides (e.g. without the consistency step)
        method_cfg = load_config(scale, list(LEARNED_CASSI[name])) if name in LEARNED_CASSI else cfg
        if name in LEARNED_CASSI:  # a trained run: its weights recorded as read
            built, weights = read_with_weights_identity(run, build_method, name, method_cfg, run)
        else:
            built, weights = build_method(name, method_cfg, run), {}
        method = dataclasses.replace(built, border_px=border_px)
        res = evaluate_method(method, scenes, names, TestNoise(seeds=seeds),
                              keep_arrays=figures.chosen_names() if figures is not None else False,
                              progress=_scene_lines(name))
        if figures is not None:
            figures.keep(name, res)
        s = summarize(res)
        rows.append(_row(name, s, scenes=s["scenes"], **weights))
    return rows


def format_experiment_table(result: dict) -> str:
    """Markdown table of an experiment's rows (conventions stated above the table)."""
    c = result["conventions"]
    lines = [f"## {result['experiment']} ({result['scale']} scale; {len(result['scenes'])} validation scenes, "
             f"seeds {result['seeds']})", "", f"PSNR: {c['psnr']}. SSIM: {c['ssim']}. SAM: {c['sam']}."
             + (f" Scored area: the DOE cameras' {result['region']}"
                + (" (the CASSI rows too: their whole-scene reconstructions scored on the same pixels)."
                   if result["experiment"] == "compare" else ".") if result.get("region") else ""),
             ""]
    if result["experiment"] == "noise":
        lines += ["| camera | PSNR clean | SSIM clean | worst PSNR on grid | worst SSIM on grid |", "|---|---|---|---|---|"]
        for r in result["rows"]:
            lines.append(f"| {r['method']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['psnr_worst']:.2f} | {r['ssim_worst']:.4f} |")
        grid = result["noise_grid"]
        for name, g in grid["results"].items():
            lines += ["", f"{name}: PSNR (dB), rows σ_p (nm), columns σ_s", "",
                      "| σ_p \\ σ_s | " + " | ".join(f"{s:g}" for s in grid["sensor_sigma"]) + " |",
                      "|---" * (len(grid["sensor_sigma"]) + 1) + "|"]
            for sp in grid["sigma_height_nm"]:
                vals = [x["psnr"] for x in g if x["sigma_height_nm"] == sp]
                lines.append(f"| {sp:g} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")
        return "\n".join(lines)
    lines += ["| method | PSNR | SSIM | SAM | runtime (s/scene) |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        if "missing" in r:
            lines.append(f"| {r['method']} | – | – | – | not available |")
        else:
            lines.append(f"| {r['method']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['sam']:.2f} | {r['runtime_s']:.3f} |")
    if result.get("notes"):
        lines += ["", "Set by the experiment beyond the swept key:", "", *(f"- {n}" for n in result["notes"])]
    return "\n".join(lines)
