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
    from safetensors.torch import save_file

    from hsicam.io import atomic_path

    meta = {"format": "hsicam-measured-psf-1", "bands": json.dumps(m.bands.to_dict()),
            "report": json.dumps(m.report, default=float), "fingerprint": m.fingerprint}
    with atomic_path(path) as tmp:
        save_file({"psf": torch.from_numpy(np.ascontiguousarray(m.psf, dtype=np.float32))}, str(tmp), metadata=meta)


def load_measured_psf(path: str | Path) -> MeasuredPSF:
    """Read :func:`save_measured_psf`'s file; :class:`InputError` if missing or corrupt."""
    tensors, meta = read_weights(path)
    if "psf" not in tensors or "bands" not in meta:
        raise InputError(f"{path}: not a measured-PSF file")
    try:
        bands = Bands.from_dict(json.loads(meta["bands"]))
        report = json.loads(meta.get("report", "{}"))
    except (json.JSONDecodeError, KeyError, TypeError):
        raise InputError(f"{path}: corrupt measured-PSF metadata") from None
    return MeasuredPSF(tensors["psf"].numpy(), bands, report)
