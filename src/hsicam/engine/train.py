"""Joint training of the optics (DOE heights, CFA) and the reconstruction network.

Each step simulates sensor images of ground-truth patches through the *current* optics, then
reconstructs them; loss L1 (paper eq. 10). Adam with separate learning rates for the network,
the DOE heights (``doe_lr_nm``: nm per step) and the CFA.

Determinism and resume: patches depend only on (seed, epoch, index), the noise of step n only
on (seed, n, rank), and the learning rate only on the global step, so a run resumed from its
last checkpoint continues exactly the same schedule.

Noise: ``train.sigma_height_nm`` and ``train.sensor_sigma`` ([lo, hi], drawn per step) are used
while training; validation uses the camera's configured noise with a fixed seed.

Distributed: launched by ``torchrun``, each process takes its share of every global batch
(``train.batch_size`` must divide by the number of processes); DDP averages the gradients;
validation, logging and checkpoints happen on rank 0 only.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import torch
import torch.distributed as dist
from torch.utils.data import Sampler

from hsicam.config import Config, dump_yaml
from hsicam.engine.checkpoint import CheckpointManager, save_weights
from hsicam.errors import InputError
from hsicam.io import atomic_open
from hsicam.metrics import psnr_per_band, sam_degrees, ssim
from hsicam.models import CameraSystem

log = logging.getLogger(__name__)


class ShardedBatches(Sampler[int]):
    """Indices of this rank's share of global batches ``start_batch..n_batches-1``.

    Global batch b holds items b·B … b·B + B − 1; rank r takes the r-th contiguous slice.
    """

    def __init__(self, n_batches: int, global_batch: int, rank: int = 0, world: int = 1, start_batch: int = 0) -> None:
        self.n_batches, self.global_batch, self.rank, self.world = n_batches, global_batch, rank, world
        self.per_rank = global_batch // world
        self.start_batch = start_batch

    def __iter__(self) -> Iterator[int]:
        for b in range(self.start_batch, self.n_batches):
            base = b * self.global_batch + self.rank * self.per_rank
            yield from range(base, base + self.per_rank)

    def __len__(self) -> int:
        return (self.n_batches - self.start_batch) * self.per_rank


def lr_factor(cfg: Config, step: int, total_steps: int, steps_per_epoch: int) -> float:
    """Learning-rate multiplier at global ``step`` (warm-up, then the schedule)."""
    t = cfg.train
    if t.warmup_steps and step < t.warmup_steps:
        return (step + 1) / t.warmup_steps
    if t.lr_schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * min(step / max(total_steps, 1), 1.0)))
    if t.lr_schedule == "step":
        return t.lr_gamma ** ((step // steps_per_epoch) // t.lr_step_epochs)
    return 1.0


def build_optimizer(cfg: Config, model: CameraSystem) -> torch.optim.Optimizer:
    """Adam with three parameter groups: network, DOE heights, CFA weights."""
    groups = [{"params": list(model.net.parameters()), "lr": cfg.train.lr, "name": "net"}]
    cam = model.camera
    doe, cfa = _doe(cam), getattr(cam, "cfa", None)
    if doe is not None and doe.enabled:
        groups.append({"params": [doe.height_m], "lr": cfg.train.doe_lr_nm * 1e-9, "name": "doe"})
    if cfa is not None and cfa.enabled:
        groups.append({"params": [cfa.weights], "lr": cfg.train.cfa_lr, "name": "cfa"})
    for g in groups:
        g["base_lr"] = g["lr"]
    return torch.optim.Adam(groups)


def _doe(camera):
    """The camera's DOE module, or None for cameras without one (CASSI)."""
    optics = getattr(camera, "optics", None)
    return getattr(optics, "doe", None)


def set_noise(camera, sigma_height_m: float | None, sensor_sigma: float) -> None:
    """Set the DOE height noise (m; ignored without a DOE) and the sensor's Gaussian σ."""
    doe = _doe(camera)
    if doe is not None and sigma_height_m is not None:
        doe.sigma_height_m = sigma_height_m
    camera.noise.sigma = sensor_sigma


def get_noise(camera) -> tuple[float | None, float]:
    doe = _doe(camera)
    return (None if doe is None else doe.sigma_height_m), camera.noise.sigma


def _device(spec: str, local_rank: int) -> torch.device:
    if spec == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    dev = torch.device(spec)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("train.device=cuda but no CUDA device is available")
    return dev


def _dist_env() -> tuple[int, int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0"))


def _step_generator(seed: int, step: int, rank: int, device: torch.device) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed((seed * 1_000_003 + step * 7919 + rank * 104_729) % (2**63 - 1))
    return g


def _draw(lo_hi: list[float], g: torch.Generator) -> float:
    lo, hi = lo_hi
    if hi <= lo:
        return lo
    return lo + (hi - lo) * float(torch.rand((), generator=g, device=g.device))


class MetricsLog:
    """Append-only metrics.jsonl; each record is written with one write() call."""

    def __init__(self, path: Path, enabled: bool) -> None:
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


@torch.no_grad()
def validate(model: CameraSystem, loader, device: torch.device, seed: int) -> dict[str, float]:
    """Mean PSNR (per band, peak 1), SSIM and SAM (°) over the validation patches.

    Reconstructions are clipped to [0, 1] before scoring. Noise is the camera's configured noise,
    drawn from a fixed seed.
    """
    model.eval()
    g = _step_generator(seed, 0, 0, device)
    sums = {"psnr": 0.0, "ssim": 0.0, "sam": 0.0}
    n = 0
    for scene in loader:
        scene = scene.to(device)
        recon, _ = model(scene, g)
        recon, truth = recon.float().clamp(0, 1), model.target(scene)
        sums["psnr"] += psnr_per_band(recon, truth).sum().item()
        sums["ssim"] += ssim(recon, truth).sum().item()
        sums["sam"] += sam_degrees(recon, truth).sum().item()
        n += scene.shape[0]
    model.train()
    return {k: v / max(n, 1) for k, v in sums.items()}


def prepare_run_dir(run_dir: Path, resume: bool) -> None:
    if resume:
        if not (run_dir / "config.yaml").is_file():
            raise InputError(f"{run_dir}: nothing to resume (no config.yaml)")
        return
    if run_dir.exists() and any(run_dir.iterdir()):
        raise InputError(f"{run_dir}: run folder exists and is not empty; use --resume or another --out")
    run_dir.mkdir(parents=True, exist_ok=True)


def train(cfg: Config, run_dir: str | Path, resume: bool = False, progress: bool | None = None,
          stop_after_steps: int | None = None) -> dict[str, Any]:
    """Train (or resume) a run; returns the final summary (also the last line of metrics.jsonl).

    Args:
        cfg: the full config.
        run_dir: run folder (created; must be empty unless ``resume``).
        resume: continue from the run's ``last`` checkpoint.
        progress: tqdm bar (None: only on a terminal).
        stop_after_steps: stop after this global step (simulates an interruption; for tests).
    """
    from hsicam.data.pipeline import build_datasets, dataset_root, make_loader

    run_dir = Path(run_dir)
    rank, world, local_rank = _dist_env()
    distributed = world > 1
    device = _device(cfg.train.device, local_rank)
    if distributed and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    is_main = rank == 0
    if cfg.train.batch_size % world:
        raise InputError(f"train.batch_size={cfg.train.batch_size} must be divisible by the {world} processes")
    if cfg.train.deterministic:
        torch.use_deterministic_algorithms(True, warn_only=True)
    if is_main:
        prepare_run_dir(run_dir, resume)
    if distributed:
        dist.barrier()

    torch.manual_seed(cfg.train.seed)
    model = CameraSystem.from_config(cfg).to(device)
    if cfg.train.bf16:
        model.autocast_dtype = torch.bfloat16
    if cfg.train.channels_last:
        model.net.to(memory_format=torch.channels_last)
    bands = model.bands
    optimizer = build_optimizer(cfg, model)
    ckpt = CheckpointManager(run_dir)
    metrics = MetricsLog(run_dir / "metrics.jsonl", is_main)

    state = {"epoch": 0, "step_in_epoch": 0, "global_step": 0, "best_psnr": None, "best_step": None}
    if resume:
        state = ckpt.load("last", model, optimizer, bands) if ckpt.path("last") else state
        if is_main:
            metrics.truncate_after(state["global_step"], state["epoch"])
            log.info("resuming %s at epoch %d, step %d", run_dir, state["epoch"], state["global_step"])
    elif is_main:
        with atomic_open(run_dir / "config.yaml") as fh:
            fh.write(dump_yaml(cfg))

    if distributed:  # generate/cache the dataset once, on rank 0, before the others read it
        if is_main:
            dataset_root(cfg.data, bands)
        dist.barrier()
    train_ds, val_ds = build_datasets(cfg.data, bands, model.camera.margin)
    steps_per_epoch = len(train_ds) // cfg.train.batch_size
    if steps_per_epoch < 1:
        raise InputError(f"data.patches_per_epoch={len(train_ds)} is smaller than train.batch_size={cfg.train.batch_size}")
    total_steps = steps_per_epoch * cfg.train.epochs
    workers = cfg.data.num_workers
    val_loader = make_loader(val_ds, cfg.train.batch_size, workers, shuffle=False) if (val_ds is not None and is_main) else None

    if cfg.train.compile:
        model.net.compile()  # in place: state-dict keys stay those of the plain module
    trainable: torch.nn.Module = model
    if distributed:
        trainable = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    writer = _tensorboard(run_dir) if (cfg.train.tensorboard and is_main) else None

    cam = model.camera
    eval_noise = get_noise(cam)
    use_bar = (sys.stderr.isatty() if progress is None else progress) and is_main
    from tqdm.auto import tqdm

    bar = tqdm(total=total_steps, initial=state["global_step"], disable=not use_bar, unit="step", dynamic_ncols=True)
    summary: dict[str, Any] = {}
    t_start, steps_done, last_val = time.perf_counter(), 0, None
    model.train()
    epoch = state["epoch"]
    while epoch < cfg.train.epochs:
        train_ds.set_epoch(epoch)
        sampler = ShardedBatches(steps_per_epoch, cfg.train.batch_size, rank, world, state["step_in_epoch"])
        loader = make_loader(train_ds, cfg.train.batch_size // world, workers, shuffle=False, sampler=sampler)
        loss_sum, loss_n = 0.0, 0
        for scene in loader:
            step = state["global_step"]
            g = _step_generator(cfg.train.seed, step, rank, device)
            set_noise(cam, _draw(cfg.train.sigma_height_nm, g) * 1e-9, _draw(cfg.train.sensor_sigma, g))
            factor = lr_factor(cfg, step, total_steps, steps_per_epoch)
            for group in optimizer.param_groups:
                group["lr"] = group["base_lr"] * factor
            scene = scene.to(device, non_blocking=True)
            recon, _ = trainable(scene, g)
            loss = torch.nn.functional.l1_loss(recon.float(), model.target(scene))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.train.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.train.grad_clip)
            optimizer.step()
            loss_v = loss.item()
            if not math.isfinite(loss_v):
                raise InputError(f"training diverged at step {step} (loss {loss_v}); lower the learning rates")
            loss_sum, loss_n = loss_sum + loss_v, loss_n + 1
            state["global_step"], state["step_in_epoch"] = step + 1, state["step_in_epoch"] + 1
            steps_done += 1
            bar.update(1)
            bar.set_postfix(loss=f"{loss_v:.4f}", psnr="-" if last_val is None else f"{last_val:.2f}", epoch=epoch)
            if is_main and state["global_step"] % cfg.train.log_every_steps == 0:
                rec = {"step": state["global_step"], "epoch": epoch, "train_loss": loss_sum / loss_n,
                       "lr": cfg.train.lr * factor, "elapsed_s": time.perf_counter() - t_start}
                metrics.write(rec)
                if writer:
                    writer.add_scalar("train/loss", rec["train_loss"], rec["step"])
                if not use_bar:
                    eta = (time.perf_counter() - t_start) / steps_done * (total_steps - state["global_step"])
                    log.info("step %d/%d epoch %d loss %.4f eta %.0fs", rec["step"], total_steps, epoch, rec["train_loss"], eta)
            if is_main and state["global_step"] % cfg.train.checkpoint_every_steps == 0:
                ckpt.save(model, optimizer, state, bands)
            if stop_after_steps is not None and state["global_step"] >= stop_after_steps:
                if is_main:
                    ckpt.save(model, optimizer, state, bands)
                bar.close()
                return {"stopped_at_step": state["global_step"]}
        # end of epoch
        epoch += 1
        state["epoch"], state["step_in_epoch"] = epoch, 0
        tags = ["last"]
        if is_main and val_loader is not None and (epoch % cfg.train.eval_every_epochs == 0 or epoch == cfg.train.epochs):
            set_noise(cam, *eval_noise)
            val = validate(model, val_loader, device, cfg.train.seed)
            last_val = val["psnr"]
            rec = {"step": state["global_step"], "epoch": epoch, **{f"val_{k}": v for k, v in val.items()}}
            metrics.write(rec)
            if writer:
                for k, v in val.items():
                    writer.add_scalar(f"val/{k}", v, state["global_step"])
            log.info("epoch %d: val PSNR %.2f dB, SSIM %.4f, SAM %.2f°", epoch, val["psnr"], val["ssim"], val["sam"])
            if state["best_psnr"] is None or val["psnr"] > state["best_psnr"]:
                state["best_psnr"], state["best_step"] = val["psnr"], state["global_step"]
                tags.append("best")
            summary = {**val}
        if is_main:
            ckpt.save(model, optimizer, state, bands, tuple(tags))
            if "best" in tags or val_loader is None:
                save_weights(run_dir / "model.safetensors", model, bands)
        if distributed:
            dist.barrier()
    bar.close()
    set_noise(cam, *eval_noise)
    if is_main and not (run_dir / "model.safetensors").exists():
        save_weights(run_dir / "model.safetensors", model, bands)
    elapsed = time.perf_counter() - t_start
    summary = {"step": state["global_step"], "epoch": state["epoch"], "final": True, "best_psnr": state["best_psnr"],
               **{f"val_{k}": v for k, v in summary.items()}, "elapsed_s": elapsed,
               "patches_per_s": steps_done * cfg.train.batch_size / max(elapsed, 1e-9)}
    metrics.write(summary)
    if writer:
        writer.close()
    return summary


def _tensorboard(run_dir: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        log.warning("train.tensorboard=true but tensorboard is not installed; continuing without it")
        return None
    return SummaryWriter(str(run_dir / "tensorboard"))
