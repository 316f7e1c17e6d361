"""Shared timing helpers for the benchmark scripts (imported as a sibling module)."""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from hsicam.memory import keep_freed_memory


def positive_int(text: str) -> int:
    """argparse ``type`` of a count that needs at least one (``--repeats``, ``--steps``, ``--threads``, ``--size``):
    0 ended in a StatisticsError traceback of the median of no times, after the set-up, and ``--threads -1`` in
    torch's RuntimeError. The CLI's ``count_arg`` is not imported: ``bench_cli`` must run, and report, when the
    ``hsicam.cli`` package itself is broken."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def allocator_option(parser: argparse.ArgumentParser) -> None:
    """``--glibc-default``: time under glibc's own allocator settings instead of the ``hsicam`` command's."""
    parser.add_argument("--glibc-default", action="store_true",
                        help="leave glibc's allocator as it is; by default the benchmark keeps freed memory for the "
                             "next tensor as the hsicam command does (hsicam.memory.keep_freed_memory)")


def apply_allocator(args: argparse.Namespace) -> bool:
    """Keep freed memory as the ``hsicam`` command does, unless ``--glibc-default``; whether it was applied (for
    the JSON: ``keep_freed_memory``)."""
    return False if args.glibc_default else keep_freed_memory()


def synchronize(device=None) -> None:
    """Wait for the work queued on ``device`` (a torch device or its name; CUDA runs asynchronously, so a wall
    time read without this measures the queueing); nothing on CPU."""
    import torch

    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def clock_times(fn, repeats: int = 1, warmup: int = 0, device=None) -> tuple[list[float], list[float]]:
    """(wall times, CPU times) in s of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls, one of each per
    call: the wall clock and this process's CPU time (all its threads: up to the thread count times the wall time).
    On a shared machine the wall time swells with the load, the CPU time much less. On a CUDA ``device`` each call's
    queued work is waited for before its times are read."""
    for _ in range(warmup):
        fn()
    synchronize(device)
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        synchronize(device)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def median_time(fn, repeats: int = 1, warmup: int = 0, device=None) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls (:func:`clock_times`)."""
    return statistics.median(clock_times(fn, repeats, warmup, device)[0])


def hsicam_command(python: str | None = None) -> list[str]:
    """The command that runs ``hsicam`` with ``python`` (default: this one): the console script beside it where it is
    installed, else ``python -m hsicam`` (a Python without the script, e.g. a source tree on ``PYTHONPATH``: the
    script's path alone was a FileNotFoundError traceback after the work was built)."""
    python = python or sys.executable
    script = Path(python).with_name("hsicam")
    return [str(script)] if script.is_file() else [python, "-m", "hsicam"]


def untrained_system_for_inference(system, cfg):
    """``system`` (an untrained :class:`~hsicam.models.CameraSystem` of ``cfg``) able to reconstruct as a trained run
    does: a preset with the linear consistency step gets zero filters of the fitted shape (a trained run's come from
    its ``linear_step.safetensors``; zero ones cost the same). Returns ``system``."""
    import torch

    if cfg.model.consistency.iterations > 0 and cfg.model.consistency.kind == "linear" and system.linear_step is None:
        m, w = system.camera.code_period, cfg.model.consistency.window_px
        device = next(system.parameters()).device
        system.linear_step = torch.zeros(m * m, len(system.bands), w, w, device=device)
    return system


def as_trained(system, cfg, device):
    """``system`` (a :class:`~hsicam.models.CameraSystem` on ``device``) set up for ``cfg``'s training step as training
    sets it up (:meth:`hsicam.engine.tasks.SystemTask.on_device`): ``train.bf16``'s bfloat16 autocast of the network
    (which :class:`~hsicam.models.CameraSystem` takes off the CPU only), ``train.channels_last``, ``train.compile``.
    Returns ``system``."""
    from hsicam.engine.tasks import SystemTask

    SystemTask(cfg, system).on_device(device)
    return system
