"""Tolerance studies cited by the fabrication export: which run a study is of, and reading one back.

``hsicam tolerance`` records the studied run in its ``tolerance.json`` (:func:`run_identity`: the
run folder and the SHA-256 of the weights file that :func:`hsicam.runs.folder.load_run` reads —
the file and hash the pretrained model card reports). ``hsicam export-optics`` cites a study in
``spec.json`` only when it is one (:data:`TOLERANCE_FORMAT`, a nominal PSNR) and, when the study
records its run, only for the run being exported (:func:`read_tolerance_study`). A study written
before the identity was recorded is cited with a warning that it cannot be checked.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from hsicam.errors import InputError

log = logging.getLogger(__name__)

#: ``format`` of the tolerance.json that ``hsicam tolerance`` writes.
TOLERANCE_FORMAT = "hsicam-tolerance-1"


def run_identity(run_dir: str | Path) -> dict[str, str]:
    """``{"path", "weights", "weights_sha256"}`` of a run: its folder (``pretrained:NAME`` resolved),
    the weights file its kept weights are read from, relative to the folder, and that
    file's SHA-256 (hex)."""
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256
    from hsicam.runs.pretrained import resolve_run, run_label

    run = resolve_run(run_dir)
    weights = root_weights_path(run)
    try:
        rel = str(weights.relative_to(run))
    except ValueError:
        rel = str(weights)
    # run_label: a shipped camera is pretrained:NAME, not its folder inside the installed package
    return {"path": run_label(run), "weights": rel, "weights_sha256": file_sha256(weights)}


def finetuned_from(run_dir: str | Path) -> str | None:
    """The design run that ``run_dir`` was fine-tuned from, as ``finetune.json`` records it ("" when
    that file is missing or unreadable), or None when ``run_dir`` is not a run fine-tuned on measured
    PSFs (it has no ``measured_psf.safetensors``)."""
    from hsicam.runs.measured_psf import MEASURED_PSF_FILE
    from hsicam.runs.pretrained import resolve_run

    run = resolve_run(run_dir)
    if not (run / MEASURED_PSF_FILE).is_file():
        return None
    try:
        source = json.loads((run / "finetune.json").read_text(encoding="utf-8")).get("source_run")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        source = None
    return source if isinstance(source, str) else ""


def _swept_ranges(data: dict[str, Any]) -> dict[str, list[float]] | None:
    """{sweep: [smallest, largest value]} of a study's ``sweeps``: what a null 1-dB tolerance of its ``summary``
    (not reached within that range: a lower bound) means; None when the study has none readable."""
    sweeps = data.get("sweeps")
    if not isinstance(sweeps, dict):
        return None
    out = {}
    for name, sweep in sweeps.items():
        values = sweep.get("values") if isinstance(sweep, dict) else None
        nums = [v for v in values or [] if isinstance(v, (int, float)) and not isinstance(v, bool)]  # ints stay ints
        if nums:
            out[name] = [min(nums), max(nums)]
    return out or None


def read_tolerance_study(path: str | Path, run_dir: str | Path) -> dict[str, Any]:
    """The ``studied`` entry of ``spec.json`` for the tolerance.json at ``path``, cited for the run
    ``run_dir``.

    Raises one-line :class:`InputError` for a file that is not a tolerance study (unreadable JSON,
    another ``format``, no finite nominal PSNR) and for the study of another run (its recorded
    weights hash differs from ``run_dir``'s). A study without a recorded run is accepted with a
    logged warning and ``"run_checked": false``.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        what = "" if path.name == "tolerance.json" else " (a tolerance study is its tolerance.json)"
        raise InputError(f"{path}: unreadable as JSON ({getattr(exc, 'msg', None) or exc}){what}") from None
    hint = "pass the tolerance.json that `hsicam tolerance --run RUN --out DIR` writes"
    if not isinstance(data, dict):
        raise InputError(f"{path}: not an hsicam tolerance study (a JSON {type(data).__name__}, not an object); {hint}")
    fmt = data.get("format")
    if fmt != TOLERANCE_FORMAT:
        what = "no format" if fmt is None else f"format {fmt!r}"
        raise InputError(f"{path}: not an hsicam tolerance study ({what}, expected {TOLERANCE_FORMAT!r}); {hint}")
    nominal = data.get("nominal")
    psnr = nominal.get("psnr") if isinstance(nominal, dict) else None
    if isinstance(psnr, bool) or not isinstance(psnr, (int, float)) or not math.isfinite(psnr):
        raise InputError(f"{path}: not a complete hsicam tolerance study (no finite nominal PSNR); {hint}")
    # the study's file as an absolute path: spec.json is read elsewhere (a relative one meant nothing once moved)
    studied: dict[str, Any] = {"source": str(path.resolve()), "nominal_psnr_db": float(psnr),
                               "summary": data.get("summary"), "swept": _swept_ranges(data)}
    recorded = data.get("run")
    sha = recorded.get("weights_sha256") if isinstance(recorded, dict) else None
    if not isinstance(sha, str) or not sha:
        log.warning("%s: the tolerance study does not record which run it studied (written before hsicam "
                    "recorded it): cannot check that it is a study of %s; cited as given", path, run_dir)
        studied["run_checked"] = False
        return studied
    this = run_identity(run_dir)
    if sha != this["weights_sha256"] and recorded.get("path") == this["path"]:  # the same folder, trained on since
        raise InputError(
            f"{path}: a tolerance study of {run_dir}'s earlier weights (sha256 {sha[:12]}…; its weights changed "
            f"since, trained on or replaced: now {this['weights_sha256'][:12]}…); run `hsicam tolerance --run "
            f"{run_dir} --out DIR` again and pass that study")
    if sha != this["weights_sha256"]:
        raise InputError(
            f"{path}: a tolerance study of another run ({recorded.get('path', '?')}, weights sha256 {sha[:12]}…), "
            f"not of {run_dir} (weights sha256 {this['weights_sha256'][:12]}…); run `hsicam tolerance --run {run_dir} "
            f"--out DIR` and pass that study"
        )
    studied["run_checked"] = True
    studied["run"] = recorded
    return studied
