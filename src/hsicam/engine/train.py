"""Joint training of the optics (DOE heights, CFA) and the reconstruction network: the
:class:`~hsicam.engine.tasks.SystemTask` run by the one training loop :func:`~hsicam.engine.loop.fit`
(schedule, determinism, resume and DDP are described there)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from hsicam.config import Config
from hsicam.engine.loop import FitOptions, fit
from hsicam.engine.tasks import SystemTask
from hsicam.models import CameraSystem


def build_optimizer(cfg: Config, model: CameraSystem) -> torch.optim.Optimizer:
    """Adam over the training groups of ``model`` (network, then the camera's declared groups)."""
    groups = SystemTask(cfg, model).param_groups()
    for g in groups:
        g["base_lr"] = g["lr"]
    return torch.optim.Adam(groups)


def train(cfg: Config, run_dir: str | Path, resume: bool = False, progress: bool | None = None,
          stop_after_steps: int | None = None) -> dict[str, Any]:
    """Train (or resume) a run; returns the final summary (also the last line of metrics.jsonl).
    Resuming a finished run changes nothing and returns its final record with ``"already_finished": True``.

    Args:
        cfg: the full config.
        run_dir: run folder (created; must be empty unless ``resume``).
        resume: continue from the run's ``last`` checkpoint.
        progress: tqdm bar (None: only on a terminal).
        stop_after_steps: stop after this global step (simulates an interruption; for tests).
    """
    if resume:  # a fine-tuned run or a spectral prior holds checkpoints that this task cannot continue
        from hsicam.runs.folder import check_train_can_resume

        check_train_can_resume(Path(run_dir))
    torch.manual_seed(cfg.train.seed)
    task = SystemTask(cfg, CameraSystem.from_config(cfg))
    opts = FitOptions(cfg.train, cfg.data.num_workers, progress=progress, stop_after_steps=stop_after_steps)
    return fit(task, opts, run_dir, resume, then=lambda summary: _refresh(run_dir, cfg, summary))


def _refresh(run_dir: str | Path, cfg: Config, summary: dict[str, Any]) -> dict[str, Any]:
    """After training (under the run's lock): the run's inference settings and its linear
    consistency step's filters, through the weights the run keeps (train.keep_weights): fitted when training
    ends, refitted when the run trained on or the filter width changed, config.yaml's
    model.consistency when a finished run got other keys."""
    from hsicam.engine.linear_step import refresh_linear_step

    changed = refresh_linear_step(run_dir, cfg.model.consistency, cfg.train.keep_weights)
    return {**summary, "changed": changed} if changed else summary
