"""Fabrication and assembly tolerances of a trained camera (the network is fixed).

The trained camera is re-imaged with perturbed optics and the *unchanged* network reconstructs;
PSNR (per band, peak 1; also SSIM and SAM) over validation scenes versus each perturbation:

* **height noise** σ_p (nm): i.i.d. Gaussian height error per cell. A fabricated element carries
  one fixed error realisation, so each draw is one DOE; results are mean ± std over draws.
* **quantisation levels** L: the heights of the fabrication export (piston removed, L levels over
  h_2π, wrapped, or over a clamp range that does not wrap; :mod:`hsicam.export.doe`), so the study
  and the exported files agree.
* **lateral misalignment** of the DOE against the lens and aperture stop by a fraction of a cell,
  along x and along the diagonal. Method: pupil oversampling — the pupil is resampled with Q
  samples per cell (``shift_subsamples``, rounded up to a multiple of the camera's own q; the
  same lens, aperture, sensor distance and kernel), the relief is shifted by whole samples (shift
  resolution 1/Q cell; relief entering from outside the design reads height 0) and the PSFs are
  computed exactly on that grid. Reference: the same Q model without shift
  (``shift_reference``), because the Q model's PSFs differ from the trained q-model's even
  unshifted — the higher diffraction orders of the cell grid leave the kernel instead of folding
  back in — so comparing with the nominal PSNR would mix that modelling change into the shift
  effect. (A Fourier sub-cell shift would ring on the stepped relief; area-averaging the shifted
  transmission at q = 1 would report the aliased light as lost.)
* **sensor distance error** Δz (µm): the optics are rebuilt with the sensor Δz farther
  (:func:`~hsicam.optics.perturb.psf_sensor_moved`), so every simulated wavelength gets its residual
  defocus (π/λ)(1/z_o + 1/(z_λ + Δz) − 1/f_λ) and its PSF grows by Δz/z_λ (the far field's scale
  λ(z_λ + Δz)/d; at +1 mm on the quick camera the scale alone moves 14 % of the PSF's light against
  the defocus alone), in the camera's K×K kernel (light that leaves it lowers ``energy``). The
  scene's own magnification change Δz/z_i is not applied to the images (reported as
  ``magnification_change``; e.g. 0.3 % for 100 µm at 35 mm): the network sees the same field a
  hair wider or narrower. ``defocus_waves`` is the peak residual defocus (R²/2)·Δ(1/z)/λ at
  the design wavelength. The PSFs are computed on the run's own pupil grid, so a Δz whose defocus
  aliases there (:func:`~hsicam.optics.sampling.defocus_aliasing` > 1, the criterion with which
  :class:`~hsicam.optics.psf.PSFModel` refuses a sensor distance) is refused up front, naming the
  representable range (``sensor_distance_um_representable``): an aliased PSF looks nearly in focus
  at any Δz and would report no tolerance at all.

A camera without a DOE (``camera.doe.enabled: false``, the no-DOE ablation) has no heights,
levels or position to be in error: the DOE sweeps are skipped (logged, and recorded under
``skipped`` in tolerance.json) and only the sensor distance is swept; the CLI refuses the DOE sweep
options for it. A run fine-tuned on measured PSFs is refused (:func:`refuse_finetuned_run`): it
images with the measured PSFs of a camera already built, while every perturbation here is of the
simulated design optics; its design run is the one to study. tolerance.json records
``optics_studied``: the design.

Outputs (:func:`write_tolerance`): ``tolerance.json`` (the studied run: folder, weights file and
its SHA-256; every value, the nominal result, the 1-dB tolerances), ``tolerance.csv`` (one row
per evaluated case) and ``tolerance.png``.

Resume (:class:`StudyProgress`): a study run into a folder keeps each finished case, as it finishes, in
``PARTIAL_FILE`` there (JSON lines: first what is studied, then one line per case, each appended whole);
the same study started again in that folder skips them, and one whose run weights, run config, scenes or
settings differ is refused naming them (``--restart`` discards the finished cases). The final files are
written only when every case is done (:func:`finish_study`).
"""

from __future__ import annotations

import csv
import io
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np
import torch

from hsicam.config import MAX_SIGMA_HEIGHT_NM, TOLERANCE_DRAW_STRIDE, TOLERANCE_SEED_MAX, seed_problem
from hsicam.errors import InputError
from hsicam.io import json_text
from hsicam.optics.perturb import (
    nominal_heights, oversampled_optics, psf_for_heights, psf_sensor_moved, psf_shifted, sensor_distance_aliasing,
    sensor_distance_limits_m, shift_subsamples_for,
)
from hsicam.report.tolerance import plot_tolerance

log = logging.getLogger(__name__)


@dataclass
class ToleranceSpec:
    """What to sweep. Lengths in the unit of the field name."""

    sigma_height_nm: tuple[float, ...] = (0.0, 10.0, 20.0, 40.0, 60.0)
    height_draws: int = 3
    levels: tuple[int, ...] = (2, 4, 8, 16, 32)
    shift_cells: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 2.0)
    shift_subsamples: int = 4  # Q: pupil samples per cell for the misalignment study (resolution 1/Q cell)
    sensor_distance_um: tuple[float, ...] = (-100.0, -50.0, -20.0, 0.0, 20.0, 50.0, 100.0)
    max_scenes: int = 8
    seed: int = 0

    def check(self) -> None:
        """InputError naming the first field (and its value) that cannot be swept. The command line
        refuses the same values as usage errors of their options before the run is loaded."""
        for name in ("height_draws", "max_scenes", "shift_subsamples"):
            if getattr(self, name) < 1:
                raise InputError(f"ToleranceSpec.{name} must be >= 1, got {getattr(self, name)}")
        if self.height_draws > TOLERANCE_DRAW_STRIDE:  # draw d seeds seed·stride + d: more would repeat the next seed's
            raise InputError(f"ToleranceSpec.height_draws must be at most {TOLERANCE_DRAW_STRIDE}, got {self.height_draws}")
        problem = seed_problem(self.seed, 0, TOLERANCE_SEED_MAX)
        if problem is not None:
            raise InputError(f"ToleranceSpec.seed {problem}")
        bad = [s for s in self.sigma_height_nm if not (math.isfinite(s) and s >= 0)]
        if bad:
            raise InputError(f"ToleranceSpec.sigma_height_nm values must be finite and >= 0, got {bad[0]:g}")
        bad = [s for s in self.sigma_height_nm if s > MAX_SIGMA_HEIGHT_NM]
        if bad:
            raise InputError(f"ToleranceSpec.sigma_height_nm values must be at most {MAX_SIGMA_HEIGHT_NM:.0f} nm, got {bad[0]:g}")
        bad = [lv for lv in self.levels if lv < 2]
        if bad:
            raise InputError(f"ToleranceSpec.levels (height levels) must be >= 2, got {bad[0]}")
        for name in ("shift_cells", "sensor_distance_um"):
            bad = [v for v in getattr(self, name) if not math.isfinite(v)]
            if bad:
                raise InputError(f"ToleranceSpec.{name} values must be finite, got {bad[0]:g}")


# ------------------------------------------------------------------------------------------------
# Evaluation
# ------------------------------------------------------------------------------------------------
#: ``tolerance`` has no ``--set``: a ``.npy`` cube's grid can only come from a file that records it.
NPY_BANDS_ADVICE = ("tolerance reads the wavelengths from the file only, so save it as .h5 with its band list "
                    "(hsicam.data.formats.write_cube_h5) and pass that to --data")


def evaluation_scenes(cfg, bands, max_scenes: int, data: str | Path | None = None, run: str | Path | None = None):
    """(SceneDataset, names): the run's validation scenes (those of ``run``'s data.json when it has one:
    :func:`~hsicam.engine.provenance.recorded_validation`; all scenes when it has none), or ``data``."""
    from hsicam.data import dataset_root, list_scenes
    from hsicam.data.datasets import scene_names
    from hsicam.data.pipeline import scene_dataset, validation_split
    from hsicam.engine.provenance import recorded_validation

    if data is not None:
        scenes = list_scenes(data)
    elif run is not None and (recorded := recorded_validation(run, cfg.data, bands)):
        scenes = recorded
    else:
        val, _ = validation_split(cfg.data, bands)  # of the synthetic data, only these scenes are generated
        scenes = val or list_scenes(dataset_root(cfg.data, bands))
        if not val:  # said: the study's figures are then of scenes the network trained on
            log.warning("tolerance: the run holds out no validation scenes (data.val_fraction 0), so the study scores "
                        "its training scenes; give other scenes with --data DIR")
    scenes = scenes[:max_scenes]
    advice = {} if data is None else {"npy_bands_advice": NPY_BANDS_ADVICE}  # its own data: no --set to give a grid
    return scene_dataset(cfg.data, scenes, bands, **advice), scene_names(scenes, data)


def evaluate_psf(model, psf: torch.Tensor, scenes, names: Sequence[str], seed: int = 0) -> dict[str, float]:
    """Mean PSNR / SSIM / SAM of ``model``'s network on ``scenes`` imaged with the PSF stack ``psf``, as ``hsicam
    evaluate`` takes it (:func:`~hsicam.engine.evaluate.summarize`: the mean SAM over the scenes where it is defined,
    NaN when none).

    Which PSFs go where (``psf``: the perturbed camera, e.g. a fabricated DOE; ``model.camera``: the camera the run
    knows, the design's PSFs or, for a fine-tuned run, its measured ones):

    - the scenes are imaged with ``psf`` (a :class:`~hsicam.cameras.measured.FixedPSFCamera` with the model's CFA and
      sensor noise): the fabricated camera's measurement;
    - the whole reconstruction (the network, and the measurement-consistency steps when on) is ``model``'s own, on
      ``model.camera``: the deployed system knows the design, not the fabrication error (an unrolled network's
      stages and the RDN's ``backprojection_input`` use the camera's PSFs: handed ``psf``, they would know it).

    This is the reverse of ``hsicam reconstruct --psf-dir``, whose consistency steps take the measured PSFs: there the
    measured PSFs are the best knowledge of the real camera; here ``psf`` is an error to be suffered, not known."""
    from hsicam.cameras.measured import FixedPSFCamera
    from hsicam.engine.evaluate import TestNoise, evaluate_method, summarize
    from hsicam.engine.methods import Method

    fabricated = FixedPSFCamera.from_camera(model.camera, psf)  # images the scenes; the reconstruction never sees it
    model.eval()
    method = Method("doe-learned", fabricated, model.reconstructor(), model.target, model=model)
    device = next(model.net.parameters()).device
    results = evaluate_method(method, scenes, list(names), TestNoise(seeds=(seed,)), device, keep_arrays=False)
    mean = summarize(results)["mean"]  # a scene of all-zero truth has no SAM: one NaN made every point's NaN
    return {k: mean[k] for k in ("psnr", "ssim", "sam")}


#: The key of tolerance.json's ``summary`` that lists the 1-dB tolerances left null because their sweep (or, for
#: the sensor distance, its side: ``sensor_distance_um_at_1db_loss.minus``, ``.plus``) held no value but 0: never
#: swept, not "not reached up to X" (absent when every sweep run reached out from 0).
NOT_SWEPT_KEY = "not_swept"


def _tolerance_at(values: Sequence[float], psnr: Sequence[float], nominal: float, drop_db: float = 1.0) -> float | None:
    """Largest |value| (interpolated) before the PSNR falls ``drop_db`` below nominal, scanning
    outward from 0; None if it never does within the range."""
    pairs = sorted((abs(v), p) for v, p in zip(values, psnr))
    prev_v, prev_p = 0.0, nominal
    for v, p in pairs:
        if nominal - p > drop_db:
            if p == prev_p:
                return v
            t = (nominal - drop_db - prev_p) / (p - prev_p)
            return float(prev_v + t * (v - prev_v))
        prev_v, prev_p = v, p
    return None


def check_sweeps(spec: ToleranceSpec, optics) -> None:
    """The sweep values that no camera geometry allows, refused before any evaluation: a sensor
    distance error that puts the sensor onto or past the lens, a lateral shift of the DOE by
    more than the aperture's diameter (the element would leave the aperture: the camera would be
    the bare lens, not a misaligned DOE camera), and a level count export-optics refuses
    (:func:`check_levels`)."""
    z_um = optics.sensor_distance_m * 1e6
    # in µm with a rounding tolerance: -35000 µm of a 0.035 m distance left 7e-18 m in metres, "in front of the
    # lens" by rounding, and was refused as a defocus needing a pupil oversampling of 1e17
    on_lens_um = 1e-6 * max(1.0, z_um)
    for dz_um in spec.sensor_distance_um:
        if z_um + dz_um <= on_lens_um:
            where = ("onto the lens" if abs(z_um + dz_um) <= on_lens_um else
                     f"past the lens, {-(z_um + dz_um):.6g} µm in front of it")
            raise InputError(f"--sensor-distance-um: Δz = {dz_um:g} µm moves the sensor {where} (the sensor sits "
                             f"{z_um:.6g} µm behind the lens); Δz toward the lens must stay above -{z_um:.6g} µm")
    for lv in spec.levels if optics.doe.enabled else ():
        check_levels(lv)
    check_defocus_sweep(spec.sensor_distance_um, optics)
    limit = 2 * optics.aperture_radius_m / optics.cell_m
    q = shift_subsamples_for(optics, spec.shift_subsamples)
    for s in spec.shift_cells:
        if abs(s) > limit:
            raise InputError(f"--shift-cells {s:g}: a DOE shift of {s:g} cells exceeds the aperture's diameter ({limit:.0f} cells of "
                             f"{optics.cell_m * 1e6:g} µm): the element would leave the aperture")
        if optics.doe.enabled and not math.isclose(s * q, round(s * q), abs_tol=1e-6):
            # the relief moves by whole pupil sub-samples: the CSV, plot and summary would show a shift not applied
            raise InputError(f"--shift-cells {s:g}: the misalignment study moves the relief by whole sub-samples of "
                             f"1/{q} cell, so {s:g} would be applied as {round(s * q) / q:g}; give multiples of "
                             f"{1 / q:g} (or raise --shift-subsamples)")
    if optics.doe.enabled and spec.shift_cells:
        check_shift_sampling(spec, optics, q)


def check_shift_sampling(spec: ToleranceSpec, optics, q: int) -> None:
    """The misalignment study's Q-oversampled pupil (:func:`oversampled_optics`) planned before any
    evaluation: a ``--shift-subsamples`` whose PSF plan exceeds the memory budget was refused only after
    the other sweeps ran, by a message that named camera.psf.pupil_oversample and not the option."""
    from hsicam.errors import ConfigError
    from hsicam.optics.sampling import plan_psf_sampling

    try:
        plan_psf_sampling(optics.line_wavelengths_nm * 1e-9, float(np.max(optics.line_sensor_distances_m)),
                          optics.pixel_m, optics.cell_m, optics.doe.n_cells, q, optics.sampling.supersample,
                          optics.kernel_px, optics.aperture_radius_m)
    except ConfigError as exc:
        reason = str(exc).split("; check ")[0]
        raise InputError(f"--shift-subsamples {spec.shift_subsamples}: the misalignment study's pupil of {q} samples per "
                         f"DOE cell cannot be simulated here ({reason}); give a smaller --shift-subsamples (default "
                         f"{ToleranceSpec().shift_subsamples}), or no --shift-cells") from None


def check_levels(levels: int) -> None:
    """InputError for a level count ``hsicam export-optics`` refuses (not a power of 2 in
    :data:`hsicam.config.LEVELS_RANGE`): a tolerance for it would be of a DOE that cannot be exported."""
    from hsicam.config import LEVELS_RANGE, levels_problem

    lo, hi = LEVELS_RANGE
    if levels_problem(levels) is not None:
        raise InputError(f"--levels {levels}: hsicam export-optics exports only a power of 2 in {lo}..{hi} levels "
                         f"(binary-weighted lithography), so a DOE of {levels} levels cannot be made from this run; "
                         "sweep powers of 2, e.g. --levels 2,4,8,16,32")


def levels_requirement(values: Sequence[int], psnr: Sequence[float], nominal: float,
                       drop_db: float = 1.0) -> dict[str, Any]:
    """The level count the camera needs (``min_levels_within_1db``: the fewest swept levels within
    ``drop_db`` of nominal) and whether the sweep brackets it (``bracketed``: a swept count below it
    loses more than ``drop_db``). Unbracketed, it is no requirement: fewer levels were not tried
    (``reason``)."""
    ok = sorted(lv for lv, p in zip(values, psnr) if nominal - p <= drop_db)
    if not ok:
        swept = ", ".join(str(v) for v in sorted(set(values)))
        return {"min_levels_within_1db": None, "bracketed": False,
                "reason": f"no swept level count ({swept}) within {drop_db:g} dB"}
    lower = [lv for lv in values if lv < ok[0]]
    if lower:
        return {"min_levels_within_1db": ok[0], "bracketed": True, "reason": None}
    why = ("only one value tried" if len(set(values)) == 1 else f"no fewer levels than {ok[0]} tried")
    return {"min_levels_within_1db": ok[0], "bracketed": False, "reason": f"not bracketed: {why}"}


def _um_toward_zero(v_m: float) -> float:
    """``v_m`` in µm, cut toward zero to 0.1 µm (a printed limit that is itself representable)."""
    return math.copysign(math.floor(abs(v_m) * 1e7) / 10.0, v_m)


def check_defocus_sweep(values_um: Sequence[float], optics) -> None:
    """Refuse the sensor distance errors whose defocus the optics' pupil grid cannot represent:
    the criterion :class:`~hsicam.optics.psf.PSFModel` refuses a config with
    (:func:`~hsicam.optics.perturb.sensor_distance_aliasing` > 1), so the sweep never evaluates an
    aliased PSF (one that looks nearly in focus at any Δz). The message names the refused values,
    the range this camera represents (:func:`~hsicam.optics.perturb.sensor_distance_limits_m`) and
    the pupil oversampling the largest refused value would need."""
    ratios = {v: float(sensor_distance_aliasing(optics, v * 1e-6).max()) for v in values_um}
    bad = [v for v, r in ratios.items() if r > 1.0]
    if not bad:
        return
    q, d_um = optics.pupil_oversample, optics.cell_m / optics.pupil_oversample * 1e6
    lo, hi = sensor_distance_limits_m(optics)
    away = "any distance away from it" if math.isinf(hi) else f"+{_um_toward_zero(hi):g} µm away from it"
    worst = max(ratios[v] for v in bad)
    q_need = int(math.ceil(q * worst - 1e-9))
    raise InputError(
        f"--sensor-distance-um: Δz = {', '.join(f'{v:g}' for v in bad)} µm defocus the lens more than the pupil "
        f"sampling can represent (the residual defocus would alias on the {d_um:.4g} µm pupil samples, up to "
        f"{worst:.3g}× the limit; `hsicam psf` refuses such a sensor distance too), so the PSFs would be those of "
        f"another lens; this camera's PSFs represent Δz from {_um_toward_zero(lo):g} µm toward the lens to {away}: "
        f"sweep within that range (these values would need camera.psf.pupil_oversample >= {q_need}; the run's is {q})"
    )


def refuse_finetuned_run(run_dir: str | Path) -> None:
    """A run fine-tuned on measured PSFs is refused: it images with the measured PSFs of a camera
    already fabricated, while the study perturbs the simulated design optics (heights, shift,
    defocus of the design PSF), so its numbers would be of a camera the run does not image with."""
    from hsicam.export.tolerance import finetuned_from

    source = finetuned_from(run_dir)
    if source is None:
        return
    design = f"the design run it was fine-tuned from ({source}, finetune.json)" if source else \
        "the design run it was fine-tuned from"
    raise InputError(
        f"{run_dir}: a run fine-tuned on measured PSFs (measured_psf.safetensors): its camera is already fabricated "
        f"and measured, and a tolerance study perturbs the simulated design optics, not the measured PSFs this run "
        f"images with; study {design}: hsicam tolerance --run {source or 'DESIGN_RUN'} --out DIR"
    )


def run_tolerance(model, cfg, spec: ToleranceSpec | None = None, data: str | Path | None = None,
                  progress: bool | None = None, run: str | Path | None = None, partial: str | Path | None = None,
                  restart: bool = False) -> dict[str, Any]:
    """Evaluate the camera of ``model`` (a :class:`~hsicam.models.CameraSystem` with a DOE camera)
    under every perturbation of ``spec`` (None: the default :class:`ToleranceSpec`); returns the JSON-ready result. ``run``: the run folder
    ``model`` was loaded from; its identity (:func:`hsicam.export.tolerance.run_identity`: folder,
    weights file and its SHA-256) is recorded as ``"run"`` so that ``hsicam export-optics`` cites
    the study only for that run (None: not recorded). ``progress``: one line per sweep point, k/N
    with an ETA (:class:`hsicam.progress.Progress`; None: a bar on a terminal, lines otherwise; False: none).
    ``partial``: the progress file (:class:`StudyProgress`; None: nothing kept) that every finished case is appended
    to, and whose cases, from an interrupted run of the same study, are not evaluated again (``restart``: they are
    discarded); InputError naming what differs when it is of another study, before any evaluation."""
    from hsicam.engine.evaluate import check_scenes
    from hsicam.engine.methods import Method
    from hsicam.optics.perturb import design_heights
    from hsicam.export.tolerance import TOLERANCE_FORMAT, run_identity
    from hsicam.progress import Progress

    spec = ToleranceSpec() if spec is None else spec
    spec.check()
    cam = _studied_camera(model, cfg, run)
    optics = cam.optics
    check_sweeps(spec, optics)
    has_doe = bool(optics.doe.enabled)
    skipped = _skipped_doe_sweeps(has_doe)
    studied_run = None if run is None else run_identity(run)
    t0 = time.perf_counter()
    scenes, names = evaluation_scenes(cfg, cam.bands, spec.max_scenes, data, run)
    check_scenes(Method("doe-learned", model.camera, model.reconstructor(), model.target, model=model), scenes, names,
                 boundary_advice=False)  # every scene before the first point; no --set to change the boundary
    points = _point_count(spec, has_doe)
    device = str(next(model.parameters()).device) if any(True for _ in model.parameters()) else "cpu"
    kept = StudyProgress(partial, study_identity(cfg, spec, names, data, studied_run, device), points, restart)

    def evaluate(psf: torch.Tensor) -> dict[str, float]:
        """The fixed network's metrics on the study's scenes imaged with ``psf`` (:func:`evaluate_psf`)."""
        return evaluate_psf(model, psf, scenes, names, spec.seed)

    h0 = nominal_heights(cam)
    nominal = kept.part("nominal")
    if nominal is None:
        nominal_psf = psf_for_heights(optics, h0)
        nominal = {**evaluate(nominal_psf.psf), "energy_in_kernel_min": float(nominal_psf.energy.min())}
        kept.save_part("nominal", nominal)
    log.info("tolerance: nominal PSNR %.2f dB on %d scene(s)", nominal["psnr"], len(names))
    big_q = shift_subsamples_for(optics, spec.shift_subsamples)
    shift_ref = None
    with Progress(points, "tolerance", "point", show=progress, every_s=0, initial=kept.done_count) as bar:
        study = _Study(kept, evaluate, bar)  # the bar is closed on an error too
        try:
            if has_doe:
                _sweep_height_noise(spec, optics, h0, study)
                _sweep_levels(spec, cam, study)
                # the exported relief (piston removed, 0 outside the aperture), not the DOE parameters, whose
                # untrained values outside the aperture a shift brought into it (1.8 % L1 of the demo camera's PSF at
                # 2 cells)
                exported = torch.from_numpy(design_heights(cam)[0]).to(h0)
                shift_ref = _sweep_shift(spec, optics, exported, big_q, study)
            _sweep_sensor_distance(spec, optics, h0, study)
        except BaseException:
            kept.said_kept()
            raise
    rows = study.rows
    sweeps = _sweeps_by_name(rows, None if shift_ref is None else shift_ref.metrics["psnr"])
    summary = _summary(sweeps, nominal["psnr"])
    return {
        "format": TOLERANCE_FORMAT,
        **({} if studied_run is None else {"run": studied_run}),
        "scenes": list(names),
        "metric": "PSNR per band then averaged, peak 1 (per-cube max normalisation), mean over scenes; network fixed",
        "sensor_noise": {"model": cam.noise.model, "sigma": cam.noise.sigma, "seed": spec.seed},
        "spec": asdict(spec),
        "optics_studied": "design (the simulated optics of the run's config and weights)",
        "doe_enabled": has_doe,
        "methods": _methods(optics, big_q, skipped),
        "sensor_distance_um_representable": [_um_toward_zero(v) if math.isfinite(v) else None
                                             for v in sensor_distance_limits_m(optics)],
        "skipped": skipped,
        # the design heights without fabrication noise: a camera.doe.sigma_height_nm, which evaluate applies (its
        # figure is then the sigma_height_nm sweep's point at that σ_p), is left out of the nominal, said here
        "nominal": {**{k: nominal[k] for k in ("psnr", "ssim", "sam", "energy_in_kernel_min")},
                    "heights": "design, without fabrication noise",
                    "camera_sigma_height_nm_left_out": float(optics.doe.sigma_height_m * 1e9)},
        "shift_reference": None if shift_ref is None else {
            **shift_ref.metrics, "pupil_oversample": big_q, "energy_in_kernel_min": float(shift_ref.energy.min())},
        "sweeps": sweeps,
        "summary": summary,
        "rows": rows,
        "rows_resumed": kept.done_count,  # read from an interrupted run's progress file, not evaluated again
        "elapsed_s": time.perf_counter() - t0,  # of this run (a resumed study's earlier runs not counted)
    }


def _studied_camera(model, cfg, run: str | Path | None):
    """``model``'s camera, or the InputError of a model the study cannot perturb: not a DOE camera, or a
    run fine-tuned on measured PSFs (:func:`refuse_finetuned_run`)."""
    from hsicam.cameras import DOECamera
    from hsicam.cameras.measured import FixedPSFCamera

    cam = model.camera
    if not isinstance(cam, DOECamera) or not hasattr(cam, "optics"):
        raise InputError(f"{'' if run is None else f'{run}: '}tolerance analysis needs a DOE camera (camera.kind: doe), "
                         f"got camera.kind: {cfg.camera.kind}")
    if run is not None:
        refuse_finetuned_run(run)
    if isinstance(cam, FixedPSFCamera):  # a model imaging with measured PSFs (fine-tuned run)
        raise InputError("the model images with measured PSFs (a run fine-tuned on them): a tolerance study perturbs "
                         "the simulated design optics; study the design run it was fine-tuned from")
    return cam


def _skipped_doe_sweeps(has_doe: bool) -> dict[str, str]:
    """tolerance.json's ``skipped``: for a camera without a DOE, the DOE sweeps and why (logged); else empty."""
    if has_doe:
        return {}
    why = ("the camera has no DOE (camera.doe.enabled: false): there is no element whose heights, "
           "quantisation or position could be in error")
    log.info("tolerance: the camera has no DOE (camera.doe.enabled: false): the DOE sweeps (height noise, "
             "quantisation levels, lateral shift) are skipped; the sensor distance sweep is run")
    return {"sigma_height_nm": why, "levels": why, "shift": why}


def _point_count(spec: ToleranceSpec, has_doe: bool) -> int:
    """How many cases the study evaluates after the nominal one (the progress bar's total)."""
    return (len(spec.sigma_height_nm) + len(spec.levels) + 2 * len(spec.shift_cells) if has_doe else 0) + \
        len(spec.sensor_distance_um)


# ------------------------------------------------------------------------------------------------
# Resume: the progress file of a study run into a folder
# ------------------------------------------------------------------------------------------------
#: The progress file in a study's folder while it runs (:class:`StudyProgress`): removed when the study completes.
PARTIAL_FILE = "tolerance.partial.jsonl"
#: ``format`` of its first line.
PARTIAL_FORMAT = "hsicam-tolerance-partial-1"
#: The files of a completed study (:func:`write_tolerance`), written only when every case is done.
TOLERANCE_FILES = ("tolerance.csv", "tolerance.json", "tolerance.png")
#: The ``hsicam tolerance`` option of each :class:`ToleranceSpec` field, named when a resume's settings differ.
SPEC_OPTIONS = {"sigma_height_nm": "--sigma-height-nm", "height_draws": "--draws", "levels": "--levels",
                "shift_cells": "--shift-cells", "shift_subsamples": "--shift-subsamples",
                "sensor_distance_um": "--sensor-distance-um", "max_scenes": "--max-scenes", "seed": "--seed"}


#: The parts of :func:`~hsicam.engine.provenance.software_record` a study's cases depend on: rows computed by another
#: hsicam, torch or numpy (or local changes) are not mixed into one study (session 75's review).
STUDY_SOFTWARE_KEYS = ("hsicam", "git_commit", "source_diff_sha256", "torch", "numpy")


def study_identity(cfg, spec: ToleranceSpec, names: Sequence[str], data: str | Path | None,
                   studied_run: dict[str, str] | None, device: str = "cpu") -> dict[str, Any]:
    """What a study's cases depend on, the first line of its progress file: the run (its weights' SHA-256,
    :func:`~hsicam.export.tolerance.run_identity`; None: not a run folder), its config's hash (with ``tolerance
    --allow-negative``'s data.allow_negative), the scenes (``data`` resolved, or None: the run's validation scenes,
    and their names), the settings (``spec``), the torch ``device`` and the software (:data:`STUDY_SOFTWARE_KEYS`),
    as JSON reads them back."""
    import json

    from hsicam.engine.evaluate import config_hash_of
    from hsicam.engine.provenance import software_record

    sw = software_record(device)
    return json.loads(json_text({
        "format": PARTIAL_FORMAT, "run": studied_run, "config_hash": config_hash_of(cfg),
        "data": None if data is None else str(Path(data).resolve()), "scenes": list(names), "spec": asdict(spec),
        "device": device, "software": {k: sw.get(k) for k in STUDY_SOFTWARE_KEYS}}))


def _listed(value: Any, most: int = 4) -> str:
    """A recorded setting as its option takes it (a list comma-separated, at most ``most`` items shown)."""
    if isinstance(value, list):
        shown = ",".join(_listed(v) for v in value[:most])
        return shown + (f",… ({len(value)} in all)" if len(value) > most else "")
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def identity_differences(then: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """What differs between two :func:`study_identity` records, each as "WHAT (X then, Y now)"; [] when none."""
    out = []
    sha = [r.get("weights_sha256") if isinstance(r, dict) else None for r in (then.get("run"), now.get("run"))]
    if sha[0] != sha[1]:
        a, b = (f"{x[:12]}…" if isinstance(x, str) else "not recorded" for x in sha)
        out.append(f"the run's weights (sha256 {a} then, {b} now)")
    if then.get("config_hash") != now.get("config_hash"):
        out.append(f"the run's config.yaml (config hash {then.get('config_hash')} then, {now.get('config_hash')} now)")
    if then.get("data") != now.get("data"):
        a, b = (x if x is not None else "the run's validation scenes" for x in (then.get("data"), now.get("data")))
        out.append(f"--data ({a} then, {b} now)")
    elif then.get("scenes") != now.get("scenes"):
        out.append(f"the scenes ({_listed(then.get('scenes'))} then, {_listed(now.get('scenes'))} now)")
    was = then.get("spec") if isinstance(then.get("spec"), dict) else {}
    for field, option in SPEC_OPTIONS.items():
        if was.get(field) != now["spec"].get(field):
            out.append(f"{option} ({_listed(was.get(field))} then, {_listed(now['spec'].get(field))} now)")
    if then.get("device") != now.get("device"):
        out.append(f"--device ({then.get('device') or 'not recorded'} then, {now.get('device')} now)")
    sw = [r if isinstance(r, dict) else {} for r in (then.get("software"), now.get("software"))]
    changed = [k for k in STUDY_SOFTWARE_KEYS if sw[0].get(k) != sw[1].get(k)]
    if changed:
        out.append("the software (" + ", ".join(f"{k} {sw[0].get(k)} then, {sw[1].get(k)} now" for k in changed) + ")")
    return out


class StudyProgress:
    """The finished cases of a study, kept in its progress file ``path`` (:data:`PARTIAL_FILE`; None: nothing kept).

    The file is JSON lines: first the study's identity (:func:`study_identity`), written atomically; then one line
    per finished case, appended whole (one ``write``) as it finishes: ``{"point": k, "row": ROW}`` for the k-th
    case of the study's fixed order (its ``sweep`` and ``value`` checked against that order when read back), and
    ``{"part": NAME, "data": ...}`` for the evaluations that are no row (the nominal, the shift reference).
    Opened on an existing file (and not ``restart``): the file must be of the same study (else one InputError
    naming what differs, with the ways on: the same command as then, or ``--restart``), its cases are taken, and a
    line cut short by a kill is dropped (its case evaluated again); the file is then rewritten atomically with the
    whole lines alone, so that the next line appended starts a line of its own."""

    def __init__(self, path: str | Path | None, identity: dict[str, Any], points: int, restart: bool = False):
        from hsicam.runs.folder import MetricsLog

        self.path = None if path is None else Path(path)
        self.rows: dict[int, dict[str, Any]] = {}
        self.parts: dict[str, dict[str, Any]] = {}
        self.points, self._next, self.done_count = points, 0, 0
        self._log = MetricsLog(self.path if self.path is not None else Path(PARTIAL_FILE), enabled=path is not None)
        if self.path is None:
            return
        records: list[dict[str, Any]] = []
        torn = 0
        if self.path.is_file():
            if restart:
                log.info("tolerance: --restart: the interrupted study's progress in %s is discarded", self.path)
            else:
                records, torn = self._read(identity)
        for rec in records:
            if isinstance(rec.get("part"), str) and isinstance(rec.get("data"), dict):
                self.parts[rec["part"]] = rec["data"]
            elif isinstance(rec.get("point"), int) and 0 <= rec["point"] < points and _is_row(rec.get("row")):
                self.rows[rec["point"]] = rec["row"]
            else:
                torn += 1
        from hsicam.io import atomic_open

        with atomic_open(self.path, "w", encoding="utf-8") as fh:  # the whole lines alone: the next one starts anew
            fh.write("".join(json_text(r) + "\n" for r in [identity, *records]))
        if self.rows or self.parts:
            log.info("tolerance: resuming: %d of %d rows done%s (kept in %s)", len(self.rows), points,
                     f"; {torn} line(s) cut short by the interruption dropped, evaluated again" if torn else "",
                     self.path)
        self.done_count = len(self.rows)

    def _read(self, identity: dict[str, Any]) -> tuple[list[dict[str, Any]], int]:
        """The records after the first line, and the count of lines that are none (cut short), of the same study."""
        start_over = "add --restart to discard it and start over, or choose another --out"
        if not self._log.first_line_whole():
            raise InputError(f"{self.path}: its first line, which names the study, is damaged: the study cannot be "
                             f"resumed; {start_over}")
        lines = [x for x in self.path.read_text(encoding="utf-8-sig", errors="replace").splitlines() if x.strip()]
        records = self._log.read()
        head = records[0] if records else {}
        if head.get("format") != PARTIAL_FORMAT:
            raise InputError(f"{self.path}: not the progress file of an hsicam tolerance study (no format "
                             f"{PARTIAL_FORMAT!r}); {start_over}")
        changed = identity_differences(head, identity)
        if changed:
            raise InputError(f"{self.path.parent}: holds an interrupted tolerance study that differs from this one "
                             f"({'; '.join(changed)}): run the command it was started with to resume it, or add "
                             "--restart to discard its finished rows and start over (or choose another --out)")
        return records[1:], len(lines) - len(records)

    def part(self, name: str) -> dict[str, Any] | None:
        """The kept evaluation ``name`` (e.g. "nominal"), or None."""
        return self.parts.get(name)

    def save_part(self, name: str, data: dict[str, Any]) -> None:
        self.parts[name] = data
        self._log.write({"part": name, "data": data})

    def take(self, sweep: str, value: float) -> dict[str, Any] | None:
        """The kept row of the study's next case (``sweep`` at ``value``), or None: that case is to be evaluated."""
        row = self.rows.get(self._next)
        if row is not None and (row.get("sweep"), row.get("value")) != (sweep, value):
            log.warning("tolerance: %s: case %d is %s %s there, not %s %g: evaluated again", self.path, self._next + 1,
                        row.get("sweep"), row.get("value"), sweep, value)
            self.done_count -= 1
            row = None
        if row is not None:
            self._next += 1
        return row

    def add(self, row: dict[str, Any]) -> None:
        """Keep the next case's ``row`` (appended whole to the file)."""
        self.rows[self._next] = row
        self._log.write({"point": self._next, "row": row})
        self._next += 1

    def said_kept(self) -> None:
        """Log where the finished cases are kept, for a study that stopped (interrupted, failed)."""
        if self.path is not None and self.path.is_file():
            log.info("tolerance: stopped with %d of %d rows done, kept in %s: the same command resumes the study",
                     len(self.rows), self.points, self.path)


#: The keys of a row of tolerance.json (:func:`_row`) that the study's tables and summary read.
ROW_KEYS = ("sweep", "value", "unit", "psnr", "psnr_std", "ssim", "sam", "n", "energy_in_kernel_min")


def _is_row(row: Any) -> bool:
    """Whether ``row`` (read from a progress file) holds every :data:`ROW_KEYS`."""
    return isinstance(row, dict) and all(k in row for k in ROW_KEYS)


class _Study:
    """The cases of one run of a study, in order: ``done`` takes a kept case's row, ``record`` adds an evaluated
    one (its progress line, its row, kept in the progress file)."""

    def __init__(self, kept: StudyProgress, evaluate, bar):
        self.kept, self.evaluate, self.bar = kept, evaluate, bar
        self.rows: list[dict[str, Any]] = []

    def done(self, sweep: str, value: float) -> bool:
        """Whether the next case (``sweep`` at ``value``) was finished by an earlier run (then its row is taken)."""
        row = self.kept.take(sweep, value)
        if row is not None:
            self.rows.append(row)
        return row is not None

    def record(self, sweep: str, value: float, unit: str, metrics: list[dict[str, float]], energy: torch.Tensor,
               **extra) -> None:
        """One evaluated case: its row (:func:`_row`), kept, and its progress line."""
        row = _row(sweep, value, unit, metrics, energy, **extra)
        self.kept.add(row)
        self.rows.append(row)
        self.bar.update(note=f"{sweep} {value:g} {unit}: PSNR {row['psnr']:.2f} dB")


def study_folder_state(out: str | Path) -> str:
    """What the folder ``out`` holds for ``hsicam tolerance``: "interrupted" (a study's progress file, with nothing
    but a completed study's files beside it; InputError naming anything else), else "other" (absent, empty, a
    completed study or anything else: for :func:`hsicam.cli.prepare_output` to judge)."""
    from hsicam.io import COMPLETE_MARKER, OS_METADATA, is_temporary

    out = Path(out)
    if not (out / PARTIAL_FILE).is_file():
        return "other"
    extra = sorted(p.name for p in out.iterdir() if p.name not in (PARTIAL_FILE, COMPLETE_MARKER, *TOLERANCE_FILES)
                   and not is_temporary(p.name) and p.name not in OS_METADATA and not p.name.startswith("._"))
    if extra:
        raise InputError(f"{out}: holds an interrupted tolerance study ({PARTIAL_FILE}) and {', '.join(extra[:5])}, "
                         "which hsicam tolerance did not write; move them, or choose another --out")
    return "interrupted"


def finish_study(out: str | Path, result: dict[str, Any]) -> None:
    """Write the completed study into its folder ``out``: the marker taken off, ``tolerance.json``, ``.csv`` and
    ``.png`` (:func:`write_tolerance`, each atomically), the marker put on naming them, the progress file removed.
    A kill at any step leaves the progress file, from which the same command finishes the study."""
    from hsicam.io import clear_complete, clear_derived, mark_complete

    out = Path(out)
    clear_derived(out)
    clear_complete(out)
    write_tolerance(out, result)
    mark_complete(out, {"command": "tolerance", "files": list(TOLERANCE_FILES)})
    (out / PARTIAL_FILE).unlink(missing_ok=True)


def _row(sweep: str, value: float, unit: str, metrics: list[dict[str, float]], energy: torch.Tensor,
         **extra) -> dict[str, Any]:
    """One row of tolerance.json's ``rows`` and tolerance.csv: the mean (and, over several draws, the std) of
    ``metrics``, and the least energy left in the kernel over the bands (and draws)."""
    ps = [m["psnr"] for m in metrics]
    return {"sweep": sweep, "value": value, "unit": unit, "psnr": float(np.mean(ps)),
            "psnr_std": float(np.std(ps)) if len(ps) > 1 else 0.0,
            "ssim": float(np.mean([m["ssim"] for m in metrics])),
            "sam": float(np.mean([m["sam"] for m in metrics])), "n": len(metrics),
            "energy_in_kernel_min": float(energy.min()), **extra}


def _sweep_height_noise(spec: ToleranceSpec, optics, h0: torch.Tensor, study: _Study) -> None:
    """Records each σ_p of ``spec.sigma_height_nm`` over ``spec.height_draws`` draws (one draw for σ_p = 0)."""
    # height noise: one fixed error realisation per draw (a fabricated element)
    for sigma in spec.sigma_height_nm:
        if study.done("sigma_height_nm", sigma):
            continue
        ms, en = [], []
        for d in range(spec.height_draws if sigma > 0 else 1):
            g = torch.Generator().manual_seed(spec.seed * TOLERANCE_DRAW_STRIDE + d)
            noise = torch.randn(h0.shape, generator=g, dtype=torch.float64) * sigma * 1e-9
            res = psf_for_heights(optics, h0 + noise)
            ms.append(study.evaluate(res.psf))
            en.append(res.energy.min())
        study.record("sigma_height_nm", sigma, "nm", ms, torch.stack(en))


def _sweep_levels(spec: ToleranceSpec, cam, study: _Study) -> None:
    """Records each level count of ``spec.levels``."""
    from hsicam.export.doe import quantize_levels
    from hsicam.optics.perturb import design_heights

    optics = cam.optics
    # quantisation: the exported L-level heights
    h_design, _, _ = design_heights(cam)
    for lv in spec.levels:
        if study.done("levels", lv):
            continue
        _, hq = quantize_levels(h_design, lv, *optics.doe.level_grid())
        res = psf_for_heights(optics, torch.from_numpy(hq))
        study.record("levels", lv, "levels", [study.evaluate(res.psf)], res.energy)


class _ShiftReference(NamedTuple):
    """The unshifted case of the shift sweeps on the oversampled pupil."""

    energy: torch.Tensor  # (C,) energy in the kernel (or its least value alone, as a progress file keeps it)
    applied_cells: tuple[float, float]  # the shift applied (rows, columns), cells
    metrics: dict[str, float]


def _sweep_shift(spec: ToleranceSpec, optics, h0: torch.Tensor, big_q: int, study: _Study) -> _ShiftReference:
    """Records each shift of ``spec.shift_cells`` along x, then along the diagonal, on the pupil oversampled to
    ``big_q`` samples per cell; returns the reference (energy, applied shift, metrics): the unshifted case, evaluated
    once (kept in the progress file as the part ``shift_reference``)."""
    # lateral misalignment along x and along the diagonal, on the Q-oversampled pupil; the
    # reference is the same model without shift (its PSFs differ from the trained q-model's:
    # higher orders of the cell grid leave the kernel instead of folding back in)
    kept = study.kept.part("shift_reference")
    shift_ref = None if kept is None else _ShiftReference(
        torch.tensor([kept["energy_in_kernel_min"]], dtype=torch.float64), tuple(kept["applied_cells"]),
        {k: kept[k] for k in ("psnr", "ssim", "sam")})
    fine = oversampled_optics(optics, big_q)

    def reference(psf: torch.Tensor, energy: torch.Tensor, applied) -> _ShiftReference:
        ref = _ShiftReference(energy, tuple(applied), study.evaluate(psf))
        study.kept.save_part("shift_reference", {**ref.metrics, "energy_in_kernel_min": float(energy.min()),
                                                 "applied_cells": list(ref.applied_cells)})
        return ref

    for sweep, direction in (("shift_x_cells", (0.0, 1.0)), ("shift_diag_cells", (1.0, 1.0))):
        for s in spec.shift_cells:
            if study.done(sweep, s):
                continue
            if s == 0 and shift_ref is not None:
                energy, applied, m0 = shift_ref
            else:
                psf, energy, applied = psf_shifted(fine, h0, s * direction[0], s * direction[1])
                if s == 0:
                    shift_ref = reference(psf, energy, applied)
                    m0 = shift_ref.metrics
                else:
                    m0 = study.evaluate(psf)
            study.record(sweep, s, "cells", [m0], energy, applied_cells=list(applied),
                         shift_um=[a * optics.cell_m * 1e6 for a in applied], pupil_oversample=big_q)
    if shift_ref is None:
        psf, energy, applied = psf_shifted(fine, h0, 0.0, 0.0)
        shift_ref = reference(psf, energy, applied)
    return shift_ref


def _sweep_sensor_distance(spec: ToleranceSpec, optics, h0: torch.Tensor, study: _Study) -> None:
    """Records each Δz of ``spec.sensor_distance_um``, with its peak residual defocus in waves at the design
    wavelength and the (unapplied) magnification change."""
    from hsicam.optics.perturb import defocus_step_pi
    from hsicam.optics.psf import DEFOCUS_L1_PER_STEP2, DEFOCUS_STEP_WARN

    lam0 = optics.doe.design_wavelength_nm * 1e-9
    z = optics.sensor_distance_m
    coarse = []
    for dz_um in spec.sensor_distance_um:
        dz = dz_um * 1e-6
        step = defocus_step_pi(optics, dz)
        if step > DEFOCUS_STEP_WARN:  # (said for a resumed row too: the study's rows are flagged as a whole)
            coarse.append((dz_um, step))
        if study.done("sensor_distance_um", dz_um):
            continue
        res = psf_sensor_moved(optics, h0, dz)
        waves = optics.aperture_radius_m**2 / 2 * (1 / (z + dz) - 1 / z) / lam0
        # coarse_defocus: the PSF's defocus sampled coarsely on the pupil grid, the row's PSF ≳ 11 % off
        study.record("sensor_distance_um", dz_um, "um", [study.evaluate(res.psf)], res.energy,
               defocus_waves=float(waves), magnification_change=float(dz / z), defocus_step_pi=step,
               coarse_defocus=step > DEFOCUS_STEP_WARN)
    if coarse:
        worst = max(coarse, key=lambda t: t[1])
        log.warning("tolerance: at %d sensor distance error(s) (%s µm) the moved sensor's residual defocus is sampled "
                    "coarsely on the pupil grid (a phase step up to %.2fπ between samples at the aperture edge): those "
                    "rows' PSFs are up to about %.0f %% off (coarse_defocus in tolerance.json); the run's "
                    "camera.psf.pupil_oversample (%d) sets the grid", len(coarse),
                    ", ".join(f"{v:+g}" for v, _ in coarse), worst[1], 100 * DEFOCUS_L1_PER_STEP2 * worst[1] ** 2,
                    optics.pupil_oversample)


def _sweeps_by_name(rows: list[dict[str, Any]], shift_psnr0: float | None) -> dict[str, Any]:
    """tolerance.json's ``sweeps``: the rows' columns per sweep; a shift sweep also holds its ``reference_psnr``
    (``shift_psnr0``, the unshifted Q model's)."""
    sweeps: dict[str, Any] = {}
    for r in rows:
        s = sweeps.setdefault(r["sweep"], {"unit": r["unit"], "values": [], "psnr": [], "psnr_std": [], "ssim": [], "sam": [],
                                           "energy_in_kernel_min": []})
        for k in ("psnr", "psnr_std", "ssim", "sam", "energy_in_kernel_min"):
            s[k].append(r[k])
        s["values"].append(r["value"])
    for name in ("shift_x_cells", "shift_diag_cells"):
        if name in sweeps and shift_psnr0 is not None:
            sweeps[name]["reference_psnr"] = shift_psnr0
    return sweeps


def _summary(sweeps: dict[str, Any], nominal_psnr: float) -> dict[str, Any]:
    """tolerance.json's ``summary``: each sweep's 1-dB tolerance (a shift's against its ``reference_psnr``, the
    sensor distance's per side), those never swept (:data:`NOT_SWEPT_KEY`), and the level count required."""
    summary = {}
    # a null tolerance is either a sweep that never lost 1 dB or a side that holds no value but 0 (never swept):
    # the second is named in "not_swept", so that neither reads as the other (:data:`NOT_SWEPT_KEY`)
    not_swept: list[str] = []
    if "sigma_height_nm" in sweeps:
        sw = sweeps["sigma_height_nm"]
        summary["sigma_height_nm_at_1db_loss"] = _tolerance_at(sw["values"], sw["psnr"], nominal_psnr)
        if not any(v != 0 for v in sw["values"]):
            not_swept.append("sigma_height_nm_at_1db_loss")
    for name in ("shift_x_cells", "shift_diag_cells"):
        if name in sweeps and "reference_psnr" in sweeps[name]:
            summary[f"{name}_at_1db_loss"] = _tolerance_at(sweeps[name]["values"], sweeps[name]["psnr"],
                                                           sweeps[name]["reference_psnr"])
            if not any(v != 0 for v in sweeps[name]["values"]):
                not_swept.append(f"{name}_at_1db_loss")
    if "sensor_distance_um" in sweeps:
        sw = sweeps["sensor_distance_um"]
        neg = [(v, p) for v, p in zip(sw["values"], sw["psnr"]) if v <= 0]
        pos = [(v, p) for v, p in zip(sw["values"], sw["psnr"]) if v >= 0]
        summary["sensor_distance_um_at_1db_loss"] = {
            "minus": _tolerance_at([v for v, _ in neg], [p for _, p in neg], nominal_psnr),
            "plus": _tolerance_at([v for v, _ in pos], [p for _, p in pos], nominal_psnr),
        }
        not_swept += [f"sensor_distance_um_at_1db_loss.{side}" for side, pts in (("minus", neg), ("plus", pos))
                      if not any(v != 0 for v, _ in pts)]
    if not_swept:
        summary[NOT_SWEPT_KEY] = not_swept
    if "levels" in sweeps:
        req = levels_requirement(sweeps["levels"]["values"], sweeps["levels"]["psnr"], nominal_psnr)
        summary["min_levels_within_1db"] = req["min_levels_within_1db"]
        summary["levels_bracketed"] = req["bracketed"]
        if req["reason"]:
            summary["levels_note"] = req["reason"]
    return summary


def _methods(optics, big_q: int, skipped: dict[str, str]) -> dict[str, str]:
    """tolerance.json's ``methods``: how each sweep perturbs the camera, but those ``skipped``."""
    from hsicam.export.doe import level_grid_text
    from hsicam.export.gds import SURROUND_FRAME_CELLS

    return {k: v for k, v in {
        "sigma_height_nm": "i.i.d. Gaussian height error per cell; each draw = one fabricated DOE; mean ± std over draws",
        "levels": f"exported L-level heights (piston removed; {level_grid_text(optics.doe)})",
        "shift": (f"pupil oversampled to Q = {big_q} samples per cell, the exported relief (doe_height_nm: piston "
                  "removed, 0 outside the aperture) shifted by whole samples against the fixed aperture and lens, "
                  f"height 0 entering (the GDS etches the surround to level 0 out to {SURROUND_FRAME_CELLS} cells beyond "
                  "the grid, unetched substrate beyond); "
                  "PSNR and its 1-dB tolerance relative to the same Q model without shift (reference_psnr)"),
        "sensor_distance_um": ("optics rebuilt with the sensor dz farther: residual defocus and PSF scale "
                               "lambda*(z_lambda + dz)/d at every simulated wavelength, in the camera's kernel (the "
                               "scene's own magnification dz/z is not applied); values whose defocus would alias "
                               "on the pupil grid are refused"),
    }.items() if k not in skipped}


# ------------------------------------------------------------------------------------------------
# Files
# ------------------------------------------------------------------------------------------------
def write_tolerance(out: str | Path, result: dict[str, Any]) -> None:
    """``tolerance.json``, ``tolerance.csv`` and ``tolerance.png`` in ``out`` (atomic writes)."""
    from hsicam.io import atomic_open, write_json

    out = Path(out)
    write_json(out / "tolerance.json", result)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["sweep", "value", "unit", "psnr_db", "psnr_std_db", "ssim", "sam_deg", "n", "energy_in_kernel_min"])
    nom = result["nominal"]
    w.writerow(["nominal", 0, "", f"{nom['psnr']:.6g}", 0, f"{nom['ssim']:.6g}", f"{nom['sam']:.6g}", 1,
                f"{nom['energy_in_kernel_min']:.6g}"])
    for r in result["rows"]:
        w.writerow([r["sweep"], r["value"], r["unit"], f"{r['psnr']:.6g}", f"{r['psnr_std']:.6g}", f"{r['ssim']:.6g}",
                    f"{r['sam']:.6g}", r["n"], f"{r['energy_in_kernel_min']:.6g}"])
    with atomic_open(out / "tolerance.csv", "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())
    plot_tolerance(result, out / "tolerance.png")
