"""Fabrication export of a trained camera: DOE height map (continuous and L-level, GDSII masks),
colour filter array (transmission table, picture, parametric fits) and ``spec.json``.

``export_optics(run, out, levels)`` writes into ``out``:

==============================  =========================================================================
``doe_height_nm.npy|.tif|.csv``   continuous heights (nm) over the aperture (float32; 16-bit TIFF whose
                                   ImageDescription JSON holds ``scale_nm_per_count``; long-format CSV)
``doe_aperture.npy``               fraction of each cell inside the circular aperture
``doe_height_L{L}_nm.*``           L-level heights (nm; L up to 2^16, as ``camera.doe.quantization_levels``);
                                   ``doe_level_L{L}.npy`` the level indices (uint8, uint16 above 256)
``doe_phase_error_L{L}.csv``       per band: RMS / max phase error of the quantisation (rad, waves)
``doe_L{L}.gds``                   GDSII etch masks (L = 2^k; needs the ``fab`` extra: gdstk)
``doe.png``                        continuous, quantised and difference maps
``cfa_tile.npy``, ``cfa_transmission.csv`` (band × filter), ``cfa_transmission_peak1.csv``,
``cfa_transmission_1nm_peak1.csv`` (each filter as the model applies it, continuous, on 1 nm),
``cfa.png``, ``cfa_fit.csv``, ``cfa_fit.png``
``spec.json``                      focal length, aperture, DOE cell/material/heights, design wavelength,
                                   pixel pitch, bands, CFA, tolerances studied, conventions, files
==============================  =========================================================================

Only what the camera has: without a DOE (``camera.doe.enabled: false``, the no-DOE ablation) no
``doe_*`` file is written and ``spec.json`` says ``"doe": {"enabled": false}``; without a CFA
(``camera.cfa.enabled: false``) no ``cfa_*`` file and ``"cfa": {"enabled": false}``. A tolerance
study of a run fine-tuned on measured PSFs is not cited (it perturbed the design optics).

Conventions: see :mod:`hsicam.export.doe`, :mod:`hsicam.export.gds`, :mod:`hsicam.export.cfa`.

The folder is one result: it is written under a temporary name, gets its completion marker
(``.complete``) and is renamed into place at the end. Everything that can be refused (the run, its
weights — NaN/Inf included —, the levels, the tolerance file) is checked before any file is written,
so a refused or interrupted export leaves nothing.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from hsicam.errors import InputError
from hsicam.config import LEVELS_RANGE
from hsicam.export.tolerance import finetuned_from, read_tolerance_study
from hsicam.runs.pretrained import is_pretrained_path, run_label

log = logging.getLogger(__name__)

SPEC_FORMAT = "hsicam-optics-spec-1"


def default_levels(cfg) -> int:
    """The run's ``camera.doe.quantization_levels`` (the element it trained; one of another value than a power of 2
    is exported without GDS masks, which binary-weighted lithography builds), else 8. (A run of 3 levels was refused
    with "pass --levels explicitly", which takes powers of 2 only: no command exported the element it trained.)"""
    lv = cfg.camera.doe.quantization_levels
    return 8 if lv is None else int(lv)


def _warn_other_levels(cfg, levels: int) -> None:
    """Warn when ``--levels`` is not the level count the run trained with: its heights are re-quantised onto another
    grid, an element other than the one trained (the tolerance study's ``levels`` sweep says what that costs)."""
    trained = cfg.camera.doe.quantization_levels
    if trained is not None and int(trained) != levels:
        log.warning("export-optics --levels %d: the run was trained with %d DOE levels, so its heights are quantised "
                    "again onto %d levels: another element than the one trained (leave out --levels to export that "
                    "one; `hsicam tolerance --levels %d` measures the cost)", levels, int(trained), levels, levels)


def _design_run_study(path: Path, source: str, run_dir: Path) -> tuple[dict[str, Any] | None, str | None]:
    """(the ``studied`` entry, None) for the tolerance study at ``path`` when it is a checked study of the design run
    ``source`` (finetune.json's ``source_run``: a folder or ``pretrained:NAME``) that the fine-tuned ``run_dir`` was
    made from, and that design run's optics (DOE heights, CFA) are still the ones ``run_dir`` froze; (None, why) for a
    study of a design run whose optics changed since (it was trained on: the study is not of these optics); (None,
    None) otherwise (a study of another run, of the fine-tuned run itself, one that records no run, or a design run
    that is no longer there)."""
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.runs.pretrained import resolve_run

    try:
        design = resolve_run(source)
        if not (design / "model.safetensors").is_file():
            return None, None
        studied = read_tolerance_study(path, design)
    except InputError:
        return None, None
    if not studied.get("run_checked"):
        return None, None
    if not _same_optics(root_weights_path(run_dir), root_weights_path(design)):
        return None, (f"a study of {source}, whose optics (DOE heights, CFA) are no longer those {run_dir} was "
                      "fine-tuned with (the design run trained on since)")
    return {**studied, "of_design_run": source}, None


def _same_optics(a: Path, b: Path) -> bool:
    """Whether the weights files ``a`` and ``b`` hold the same camera tensors (``camera.*``: DOE heights, CFA)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(a), "pt") as fa, safe_open(str(b), "pt") as fb:
            keys = sorted(k for k in fa.keys() if k.startswith("camera."))
            if keys != sorted(k for k in fb.keys() if k.startswith("camera.")):
                return False
            return all(fa.get_tensor(k).equal(fb.get_tensor(k)) for k in keys)
    except (OSError, SafetensorError):
        return False


def _tolerances(run_dir: Path, cfg, tolerance: str | Path | None) -> dict[str, Any]:
    t = cfg.train
    out: dict[str, Any] = {
        # the noise the network trained with (train.*, drawn per step); the camera's own σ_p (camera.doe.*) is
        # applied at validation and evaluation only, not in training (it was listed here as trained with)
        "trained_with": {"sigma_height_nm": list(t.sigma_height_nm), "sensor_sigma": list(t.sensor_sigma)},
        "validated_with": {"camera_sigma_height_nm": cfg.camera.doe.sigma_height_nm},
        "studied": None,
    }
    shipped = is_pretrained_path(run_dir)
    cand = Path(tolerance) if tolerance is not None else run_dir / "tolerance"
    if cand.is_dir():
        cand = cand / "tolerance.json"
    source = finetuned_from(run_dir)
    design = f"the design run it was fine-tuned from ({source})" if source else "the design run it was fine-tuned from"
    if source and cand.is_file():
        design_study, changed = _design_run_study(cand, source, run_dir)  # the study the note below recommends: cited
        if design_study is not None:
            out["studied"] = design_study
            out["note"] = (f"a study of {design}, whose optics these are (the network was fine-tuned on measured "
                           "PSFs; the study perturbed the design optics)")
            return out
        if changed is not None:
            if tolerance is not None:
                raise InputError(f"{cand}: {changed}; export without --tolerance")
            log.warning("%s: not cited: %s", cand, changed)
            out["note"] = f"{cand} not cited: {changed}"
            return out
    if source is not None and cand.is_file():
        # a study of a fine-tuned run perturbed the design optics, not the measured PSFs it images
        # with (`hsicam tolerance` refuses such a run now; an older study may exist)
        why = (f"{run_dir} is a run fine-tuned on measured PSFs: a tolerance study of it perturbed the simulated design "
               "optics, not the measured PSFs it images with")
        if tolerance is not None:
            raise InputError(f"{cand}: {why}; export without --tolerance, or export {design} and cite its study")
        log.warning("%s: not cited: %s", cand, why)
        out["note"] = f"{cand} not cited: {why}; the study of {design} applies to these optics"
        return out
    if cand.is_file():
        # a tolerance study (not any JSON), and of this run when it records its run
        try:
            out["studied"] = read_tolerance_study(cand, run_dir)
        except InputError as exc:
            if tolerance is not None:  # asked for: its refusal is the answer
                raise
            # found by itself in RUN/tolerance (e.g. a study of the run before it was resumed): the export
            # goes on without citing it, and says why
            log.warning("not cited: %s", exc)
            out["note"] = f"not cited: {exc}; run the study again (`hsicam tolerance --run {run_dir} --out DIR`)"
    elif tolerance is not None:
        where = "no tolerance.json in this folder" if Path(tolerance).is_dir() else "no such file or folder"
        raise InputError(f"{tolerance}: {where} (--tolerance takes the folder `hsicam tolerance --run {run_label(run_dir)} "
                         "--out DIR` wrote, or its tolerance.json)")
    elif source is not None:  # `hsicam tolerance` refuses a fine-tuned run: its optics are the design run's
        out["note"] = (f"no tolerance study: {run_dir} was fine-tuned on measured PSFs, so a study of {design} applies "
                       f"to these optics: `hsicam tolerance --run {source or 'DESIGN_RUN'} --out DIR`")
    elif shipped:  # its folder lies inside the installed package: a study goes elsewhere
        out["note"] = f"no tolerance study found: run `hsicam tolerance --run {run_label(run_dir)} --out DIR`"
    else:
        out["note"] = f"no tolerance study found: run `hsicam tolerance --run {run_dir} --out {run_dir / 'tolerance'}`"
    return out


def export_optics(run_dir: str | Path, out_dir: str | Path, levels: int | None = None,
                  tolerance: str | Path | None = None) -> dict[str, Any]:
    """Export the optics of a trained run into ``out_dir``; returns the ``spec.json`` content.

    Only what the camera has is exported: a camera without a DOE (``camera.doe.enabled: false``)
    gets ``spec.json`` ``doe: {"enabled": false, ...}`` and no DOE file (``levels`` is then refused);
    one without a CFA (``camera.cfa.enabled: false``) gets ``cfa: {"enabled": false, ...}`` and no
    CFA file."""
    from hsicam.cameras import DOECamera
    from hsicam.io import atomic_output, check_output_path
    from hsicam.runs.folder import load_run
    from hsicam.runs.pretrained import resolve_run

    run_dir, out = resolve_run(run_dir), Path(out_dir)  # run_dir may be pretrained:NAME
    check_output_path(out, "dir")
    cfg, model = load_run(run_dir, "cpu")  # (refuses weights with NaN/Inf: runs.folder.check_finite_weights)
    camera = model.camera
    if not isinstance(camera, DOECamera):
        raise InputError(f"{run_dir}: export-optics needs a DOE camera (camera.kind: doe), got {cfg.camera.kind}")
    if not camera.optics.doe.enabled:
        if levels is not None:
            raise InputError(f"--levels {levels}: {run_dir} has no DOE (camera.doe.enabled: false), so there are no "
                             "heights to quantise; leave out --levels (the export then holds "
                             f"{'the CFA files and ' if camera.cfa.enabled else ''}spec.json)")
    else:
        if levels is None:
            try:
                levels = default_levels(cfg)  # within the config's range (camera.doe.quantization_levels)
            except InputError as exc:
                raise InputError(f"{run_label(run_dir)}: {exc}") from None
        elif not LEVELS_RANGE[0] <= levels <= LEVELS_RANGE[1]:
            raise InputError(f"--levels must be in {LEVELS_RANGE[0]}..{LEVELS_RANGE[1]} (the range of "
                             f"camera.doe.quantization_levels), got {levels}")
        else:
            _warn_other_levels(cfg, levels)
    tolerances = _tolerances(run_dir, cfg, tolerance)  # a bad tolerance file: refused before any file is written
    source = finetuned_from(run_dir)
    facts: dict[str, Any] = {"run": run_label(run_dir),  # pretrained:NAME for a shipped camera, else the folder
                             "weights": _weights_facts(run_dir, cfg)}
    if source is not None:
        facts["finetuned"] = {"on_measured_psfs": True, "from_run": source or None,
                              "note": "fine-tuning on measured PSFs changed only the network: the DOE and CFA "
                                      "exported here are the design's"}
    with atomic_output(out, overwrite=True, marker={"command": "export-optics"}) as tmp:
        spec = _export_into(tmp, facts, cfg, camera, levels, tolerances)
    return spec


def _weights_facts(run_dir: Path, cfg) -> dict[str, Any]:
    """Which weights the files are made from: the weights file, its SHA-256, the checkpoint they are
    (:func:`~hsicam.runs.checkpoint.kept_checkpoint`: best or last, its step and the run's last step; None for a
    folder without checkpoints, a shipped camera) and whether the training finished (``unfinished``: the note
    :func:`~hsicam.runs.folder.unfinished_training` logs). A package made from a half-trained run looked like a final
    one, and a run resumed later could no longer be tied to the files sent to the fab."""
    from hsicam.export.tolerance import run_identity
    from hsicam.runs.checkpoint import kept_checkpoint
    from hsicam.runs.folder import unfinished_training

    ident = run_identity(run_dir)
    note = unfinished_training(run_dir, cfg)
    return {"file": ident["weights"], "sha256": ident["weights_sha256"], "checkpoint": kept_checkpoint(run_dir),
            "training_finished": note is None, **({"unfinished": note} if note else {})}


def _export_into(out: Path, facts: dict[str, Any], cfg, camera, levels: int | None, tolerances: dict[str, Any]) -> dict[str, Any]:
    """Write the optics' files into ``out`` and ``spec.json`` (``facts``: its ``run`` and, for a
    fine-tuned run, ``finetuned``); returns the spec."""
    from hsicam.export.cfa import export_cfa
    from hsicam.export.doe import export_doe
    from hsicam.io import write_json

    bands = camera.bands
    optics = camera.optics
    has_doe = bool(optics.doe.enabled)
    if has_doe:
        doe_info = {"enabled": True, **export_doe(camera, out, levels, bands.centers_nm)}
    else:
        doe_info = {"enabled": False,
                    "note": "the camera has no DOE (camera.doe.enabled: false): the lens and the aperture alone form "
                            "the PSF; no DOE files are written (nothing to fabricate)"}
    if camera.cfa.enabled:
        cfa_info = export_cfa(camera, out)
    else:
        cfa_info = {"enabled": False,
                    "note": "the camera has no colour filter array (camera.cfa.enabled: false): every pixel sees every "
                            "band (kappa = 1), a bare monochrome sensor; no CFA files are written"}
    lens = cfg.camera.lens
    desc = optics.describe()
    spec = {
        "format": SPEC_FORMAT,
        **facts,
        "units": "lengths in the key's unit suffix; heights in nm; wavelengths in nm (vacuum)",
        "lens": {
            "model": lens.model,
            "focal_length_mm": float(optics.lens.focal_lengths_m(np.array([lens.design_wavelength_nm]))[0] * 1e3),
            "design_wavelength_nm": lens.design_wavelength_nm,
            "focal_length_per_band_mm": desc["lens"]["focal_length_mm"],
            **({"radius_of_curvature_mm": lens.radius_of_curvature_mm, "center_thickness_mm": lens.center_thickness_mm,
                "material": lens.material, "orientation": "plano-convex, the convex face towards the object"}
               if lens.model == "singlet" else {}),
            # where sensor_distance_mm is measured from (a fab measuring it from the flat back face of the singlet
            # placed the sensor 1.37 mm too far, ~23 waves of defocus at f/3.5; session 73's hunt)
            "sensor_distance_from": desc["lens"]["sensor_distance_from"],
            "rear_principal_plane_mm": desc["lens"]["rear_principal_plane_mm"],
            "rear_principal_plane_from": desc["lens"]["rear_principal_plane_from"],
            "back_focal_distance_mm": optics.sensor_distance_m * 1e3 + desc["lens"]["rear_principal_plane_mm"],
            "back_focal_distance_from": "the lens's rear vertex to the sensor (sensor_distance_mm + "
                                        "rear_principal_plane_mm)",
        },
        "sensor_distance_mm": optics.sensor_distance_m * 1e3,
        "object_distance_m": optics.object_distance_m,
        "aperture": {"shape": "circle", "radius_mm": optics.aperture_radius_m * 1e3,
                     "diameter_mm": 2 * optics.aperture_radius_m * 1e3,
                     "stop": ("at the DOE, centred on the lens axis" if has_doe else
                              "at the lens (its pupil plane), centred on the lens axis")},
        "doe": doe_info,
        "cfa": cfa_info,
        "sensor": {"pixel_pitch_um": optics.pixel_m * 1e6, "noise": cfg.camera.sensor.noise,
                   "bit_depth": cfg.camera.sensor.bit_depth},
        "psf": {"kernel_px": camera.kernel_px, "supersample": optics.sampling.supersample,
                "pupil_oversample": optics.pupil_oversample},
        "bands": {"centers_nm": bands.centers_nm.tolist(), "fwhm_nm": bands.fwhm_nm.tolist()},
        "tolerances": tolerances,
    }
    spec["files"] = sorted(p.name for p in out.iterdir() if p.is_file() and not p.name.startswith(".")) + ["spec.json"]
    spec["files"] = sorted(set(spec["files"]))
    write_json(out / "spec.json", spec)
    return spec


__all__ = ["export_optics", "default_levels", "SPEC_FORMAT"]
