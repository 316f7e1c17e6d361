"""Measured PSFs stored with a run (``RUN/measured_psf.safetensors``): a run fine-tuned on them
images with them when it is loaded (:func:`hsicam.runs.folder.load_run`)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hsicam.errors import InputError
from hsicam.io import same_path
from hsicam.runs.checkpoint import read_weights
from hsicam.spectral import Bands

MEASURED_PSF_FILE = "measured_psf.safetensors"


@dataclass
class MeasuredPSF:
    """A measured PSF stack on a camera's grid: ``psf`` (C, K, K) float32 and the import report."""

    psf: np.ndarray
    bands: Bands
    report: dict[str, Any]

    @property
    def fingerprint(self) -> str:
        return psf_fingerprint(self.psf)


def psf_fingerprint(psf: np.ndarray) -> str:
    """Short SHA-256 of a float32 PSF stack (identifies the PSFs a network was tuned to)."""
    return hashlib.sha256(np.ascontiguousarray(psf, dtype=np.float32).tobytes()).hexdigest()[:16]


def save_measured_psf(path: str | Path, m: MeasuredPSF) -> None:
    """``measured_psf.safetensors`` (atomic) with the band grid and the import report as metadata."""
    from hsicam.runs.checkpoint import save_safetensors

    meta = {"format": "hsicam-measured-psf-1", "bands": json.dumps(m.bands.to_dict()),
            "report": json.dumps(m.report, default=float), "fingerprint": m.fingerprint}
    save_safetensors(path, {"psf": torch.from_numpy(np.ascontiguousarray(m.psf, dtype=np.float32))}, meta)


def load_measured_psf(path: str | Path) -> MeasuredPSF:
    """Read :func:`save_measured_psf`'s file; :class:`InputError` if missing or corrupt."""
    tensors, meta = read_weights(path)
    if "psf" not in tensors or "bands" not in meta:
        raise InputError(f"{path}: not a measured-PSF file")
    try:
        bands = Bands.from_dict(json.loads(meta["bands"]))
        report = json.loads(meta.get("report", "{}"))
    except (ValueError, KeyError, TypeError, AttributeError):  # JSONDecodeError is a ValueError
        raise InputError(f"{path}: corrupt measured-PSF metadata") from None
    psf = tensors["psf"]
    problem = _psf_problem(psf, len(bands))
    if problem is not None:
        raise InputError(f"{path}: {problem}: the file is damaged; copy the run folder again from its source, or "
                         "fine-tune it again (hsicam finetune)")
    return MeasuredPSF(psf.float().numpy(), bands, report)


def _psf_problem(psf: torch.Tensor, n_bands: int) -> str | None:
    """What makes ``psf`` no PSF stack of ``n_bands`` bands as the import writes one ((C, K, K) floats,
    K odd, finite), or None."""
    shape = tuple(psf.shape)
    if psf.dim() != 3 or shape[1] != shape[2] or shape[1] % 2 == 0 or shape[0] != n_bands:
        return f"the PSF stack is {shape}, not ({n_bands} bands, K, K) with K odd"
    if not psf.is_floating_point():
        return f"the PSF stack holds {str(psf.dtype).removeprefix('torch.')} values, not floats"
    bad = int((~psf.isfinite()).sum())
    if bad:
        return f"{bad} NaN/Inf value(s) in the PSF stack"
    return None


def psf_difference(tuned: MeasuredPSF, measured: MeasuredPSF, psf_dir: str | Path) -> tuple[str, str] | None:
    """Why the PSFs ``measured`` (imported from ``psf_dir``) differ from ``tuned`` (those a run was
    fine-tuned on, with their import report) when both come from the same folder: the pixel pitch
    they were imported at, the kernel, the other import options, else the images (or ``psf.json``)
    changed since: (what differs: "pixel_pitch_um", "kernel_px", "options", "import" (another version of the
    import: :data:`~hsicam.data.measured_psf.PSF_IMPORT_VERSION`) or "images", the reason in
    words). None when ``tuned`` came from another folder (or does not say which) or they are the same
    PSFs."""
    if tuned.fingerprint == measured.fingerprint:
        return None
    before, now = tuned.report, measured.report
    src = before.get("psf_dir")
    if not isinstance(src, str) or not same_path(src, psf_dir):
        return None
    p0, p1 = before.get("pixel_pitch_um"), now.get("pixel_pitch_um")
    if isinstance(p0, (int, float)) and isinstance(p1, (int, float)) and abs(p0 - p1) > 1e-9 * max(abs(p0), abs(p1)):
        return "pixel_pitch_um", f"the pixel pitch differs: {p1:g} µm now, {p0:g} µm when it was fine-tuned"
    if before.get("kernel_px") != now.get("kernel_px"):
        return "kernel_px", f"the kernel differs: {now.get('kernel_px')} px now, {before.get('kernel_px')} px when it was fine-tuned"
    keys = ("centre", "axis_px", "background", "normalize", *(("fwhm_nm",) if "fwhm_nm" in before else ()))  # since v3
    changed = [k for k in keys if before.get(k) != now.get(k)]
    if changed:
        return "options", "the import options differ: " + ", ".join(f"{k} {now.get(k)!r} now, {before.get(k)!r} then" for k in changed)
    v0, v1 = before.get("import_version", 1), now.get("import_version", 1)
    if v0 != v1:
        return "import", (f"it was imported by an hsicam whose import differs (version {v0} then, {v1} now: since "
                          "session 73 the images' noise keeps its sign until the kernel, not clipped at 0 first; since "
                          "session 75 a band of a sweep finer than the bands averages its images, not the nearest one; "
                          "the files may have changed too)")
    return "images", "the PSF images (or psf.json) of the folder changed since it was fine-tuned"
