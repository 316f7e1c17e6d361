"""Joint training of the optics (DOE heights, CFA) and the reconstruction network: the
:class:`~hsicam.engine.tasks.SystemTask` run by the one training loop :func:`~hsicam.engine.loop.fit`
(schedule, determinism, resume and DDP are described there)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch

from hsicam.config import Config
from hsicam.engine.loop import FitOptions, fit
from hsicam.engine.tasks import SystemTask
from hsicam.models import CameraSystem

log = logging.getLogger(__name__)


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
        if (Path(run_dir) / "config.yaml").is_file():  # before its camera is built: trained on with the files it began with
            from hsicam.runs.camera_files import check_camera_files

            check_camera_files(run_dir, cfg)
    warn_camera_noise_not_trained(cfg)
    torch.manual_seed(cfg.train.seed)
    task = SystemTask(cfg, CameraSystem.from_config(cfg))
    opts = FitOptions(cfg.train, cfg.data.num_workers, progress=progress, stop_after_steps=stop_after_steps)
    # the run's weights are checked in the loop's end-of-training work (rank 0's, which a DDP group's other ranks
    # wait for and learn the outcome of: fit); a check after fit returned would fail rank 0 alone, the others exit 0
    return fit(task, opts, run_dir, resume, then=lambda summary: _refresh(run_dir, cfg, summary))


def check_kept_weights(run_dir: str | Path) -> None:
    """One-line :class:`InputError` when a run that finished training has no weights its readers take: the checkpoint
    it keeps (``train.keep_weights``) is damaged and its root weights are not those the manifest records
    (:func:`~hsicam.runs.checkpoint.root_weights_path`'s refusal; the loop's end then leaves the root as it is, with a
    warning). The training exited 0 and the next ``hsicam evaluate`` failed; now the training fails, naming the
    damaged file and the way out: the run's last checkpoint when it is another one and intact
    (``train.keep_weights=last``), else copying the run again."""
    from hsicam.errors import InputError
    from hsicam.runs.folder import damaged_weights_message

    text = damaged_weights_message(Path(run_dir))
    if text is not None:
        raise InputError(f"training ended, but the run has no readable weights: {text}")


def warn_camera_noise_not_trained(cfg: Config) -> list[str]:
    """Log (and return) a warning for each noise level of the camera (``camera.sensor.sigma``,
    ``camera.doe.sigma_height_nm``) that training does not draw: each step draws its levels from the ``train``
    ranges (:func:`hsicam.engine.tasks.draw_noise`), so a camera σ with a range of [0, 0] is seen only by
    the validation and the evaluation."""
    t, cam = cfg.train, cfg.camera
    lines = []
    sigma = cam.sensor.sigma if cam.sensor.noise != "none" else 0.0  # noise none: not applied (its own warning)
    for what, level, key, rng in (("sensor noise σ_s", sigma, "sensor_sigma", t.sensor_sigma),
                                  ("DOE height noise σ_p (nm)", cam.doe.sigma_height_nm, "sigma_height_nm",
                                   t.sigma_height_nm)):
        if level > 0 and max(rng) == 0:
            lines.append(f"the camera's {what} {level:g} is used by the validation and the evaluation only: training "
                         f"draws it from train.{key} = {list(rng)}; to train with it: --set train.{key}=[{level:g},{level:g}]")
    for line in lines:
        log.warning("%s", line)
    return lines


def _refresh(run_dir: str | Path, cfg: Config, summary: dict[str, Any]) -> dict[str, Any]:
    """After training (under the run's lock): the run's inference settings and its linear
    consistency step's filters, through the weights the run keeps (train.keep_weights): fitted when training
    ends, refitted when the run trained on or the filter width changed, config.yaml's
    model.consistency when a finished run got other keys; then :func:`check_kept_weights`."""
    from hsicam.engine.linear_step import refresh_linear_step

    changed = refresh_linear_step(run_dir, cfg.model.consistency, cfg.train.keep_weights)
    check_kept_weights(run_dir)
    return {**summary, "changed": changed} if changed else summary
