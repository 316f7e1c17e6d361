"""The run folder: its layout, loading a trained run, the metrics log, starting or resuming.

Layout (written by :func:`hsicam.engine.loop.fit` and its tasks)::

    RUN/config.yaml            resolved config
    RUN/metrics.jsonl          one JSON object per log/eval event
    RUN/model.safetensors      weights (network + optics) of the best (else last) checkpoint
    RUN/checkpoints/step-N/    model.safetensors, optimizer.safetensors, state.json
    RUN/last.json, best.json   pointers {"dir": "checkpoints/step-N", ...}
    RUN/measured_psf.safetensors  (fine-tuned runs) the measured PSFs the run images with

A run is rebuilt from its config through the registries (camera kind, network kind), so
:func:`load_run` works for every camera and network.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from hsicam.errors import InputError
from hsicam.io import atomic_open
from hsicam.runs.checkpoint import load_weights
from hsicam.runs.measured_psf import MEASURED_PSF_FILE, MeasuredPSF, load_measured_psf


def with_measured_psf(model, measured: MeasuredPSF):
    """A :class:`~hsicam.models.CameraSystem` imaging with ``measured`` PSFs (same network, same CFA)."""
    from hsicam.cameras.measured import FixedPSFCamera

    cam = model.camera
    if not measured.bands.matches(cam.bands):
        raise InputError(f"measured PSFs are on {measured.bands!r}, the camera on {cam.bands!r}")
    if measured.psf.shape[-1] != cam.kernel_px:
        raise InputError(f"measured PSFs are {measured.psf.shape[-1]} px wide, the camera's kernel {cam.kernel_px} px")
    return model.with_camera(FixedPSFCamera.from_camera(cam, torch.from_numpy(measured.psf)))


def load_run(run_dir: str | Path, device: torch.device | str = "cpu", overrides: tuple[str, ...] = ()):
    """(config, CameraSystem) of a trained run, weights from ``RUN/model.safetensors``; a run
    fine-tuned on measured PSFs (``RUN/measured_psf.safetensors``) images with those PSFs.

    Raises :class:`InputError` for a missing folder, missing/corrupt weights or another band grid.
    """
    from hsicam.config import load_config
    from hsicam.models import CameraSystem

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder")
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise InputError(f"{run_dir}: not a run folder (config.yaml is missing)")
    cfg = load_config(cfg_path, overrides)
    weights = run_dir / "model.safetensors"
    if not weights.is_file():
        raise InputError(f"{run_dir}: the run has no trained weights (model.safetensors is missing)")
    model = CameraSystem.from_config(cfg)
    load_weights(weights, model, cfg.bands.to_bands())
    if (run_dir / MEASURED_PSF_FILE).is_file():  # a run fine-tuned on measured PSFs images with them
        model = with_measured_psf(model, load_measured_psf(run_dir / MEASURED_PSF_FILE))
    return cfg, model.to(device).eval()


def check_run_dir(run_dir: Path, resume: bool) -> None:
    """A run folder must hold a run to resume, or (a new run) be absent or empty. Creates nothing."""
    if resume:
        if not (run_dir / "config.yaml").is_file():
            raise InputError(f"{run_dir}: nothing to resume (no config.yaml)")
        return
    if run_dir.exists() and not run_dir.is_dir():
        raise InputError(f"{run_dir}: exists and is not a folder; choose another --out")
    if run_dir.exists() and any(run_dir.iterdir()):
        raise InputError(f"{run_dir}: run folder exists and is not empty; use --resume or another --out")


def prepare_run_dir(run_dir: Path, resume: bool) -> None:
    """:func:`check_run_dir`, then create the folder of a new run."""
    check_run_dir(run_dir, resume)
    if not resume:
        run_dir.mkdir(parents=True, exist_ok=True)


class MetricsLog:
    """Append-only metrics.jsonl; each record is written with one write() call."""

    def __init__(self, path: Path, enabled: bool = True) -> None:
        self.path, self.enabled = path, enabled

    def write(self, record: dict[str, Any]) -> None:
        if not self.enabled:
            return
        data = (json.dumps(record) + "\n").encode()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, data)
        finally:
            os.close(fd)

    def truncate_after(self, step: int, epoch: int) -> None:
        """Keep only the complete records a checkpoint at (``step``, ``epoch`` epochs done) had seen.

        A validation record at the checkpoint's step belongs to a later epoch when the process
        died between writing it and saving the epoch-end checkpoint: it is dropped and redone.
        """
        if not self.path.exists():
            return
        kept = []
        for line in self.path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            r_step = rec.get("step", 0)
            if r_step < step or (r_step == step and rec.get("epoch", 0) <= epoch):
                kept.append(line)
        with atomic_open(self.path, "w", encoding="utf-8") as fh:
            fh.write("".join(f"{x}\n" for x in kept))
