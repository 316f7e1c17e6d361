"""Training and inference benchmark (issue 4): prints one JSON object.

- Training throughput (patches/s) of full optimisation steps (PSF from the DOE, camera, network,
  the preset's loss: L1 and its optional terms, e.g. quick's SSIM term; backward, Adam) for the ``quick`` preset on this machine, with the time split between the
  optics (PSF + camera) and the network, forward and backward.
- The same preset's step once the optics are fixed (``train.optics_steps``): network only.
- With CUDA: the same for the ``paper`` preset (256 px patches, bf16 autocast, channels_last). Each step's model is
  set up as training sets it up (``timing.as_trained``: ``SystemTask.on_device``).
- Inference time of one 512×512 reconstruction (network only; all the preset's bands) for the quick and paper networks.
- The measurement-consistency steps after the network on 512×512, through the shipped ``standard`` camera's trained
  PSFs (the untrained quick camera's lens PSFs need a wider kernel than any trained camera measured here): its
  Landweber steps as it takes them (``landweber_steps_cpu``: the 12 steps with the spectral and TV priors, all and
  per step) and its linear step (``linear_step_cpu``).

Run: `.venv/bin/python benchmarks/bench_train.py [--steps N]`. Timings are medians.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import allocator_option, apply_allocator, as_trained, median_time, positive_int  # noqa: E402

from hsicam.config import load_config  # noqa: E402
from hsicam.engine.tasks import system_loss  # noqa: E402
from hsicam.engine.train import build_optimizer  # noqa: E402
from hsicam.models import CameraSystem  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def train_steps(preset: str, device: torch.device, steps: int, overrides: list[str]) -> dict:
    cfg = load_config(preset, overrides)
    torch.manual_seed(0)
    model = as_trained(CameraSystem.from_config(cfg).to(device), cfg, device)  # bf16 autocast (CUDA), channels_last
    opt = build_optimizer(cfg, model)
    b, p, m = cfg.train.batch_size, cfg.data.patch_px, model.camera.margin
    scene = torch.rand(b, len(model.bands), p + m, p + m, device=device)
    t_optics, t_net, t_step = [], [], []
    for i in range(steps + 1):
        _sync(device)
        t0 = time.perf_counter()
        sensor = model.camera(scene)
        _sync(device)
        t1 = time.perf_counter()
        sensor_in = sensor.detach().requires_grad_()
        recon = model.reconstruct(sensor_in)
        loss = system_loss(recon.float(), model.target(scene), cfg.train)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        _sync(device)
        t2 = time.perf_counter()
        sensor.backward(sensor_in.grad)  # optics backward, with the network's gradient
        opt.step()
        _sync(device)
        t3 = time.perf_counter()
        if i:  # first step is warm-up
            t_optics.append((t1 - t0) + (t3 - t2))
            t_net.append(t2 - t1)
            t_step.append(t3 - t0)
    step = statistics.median(t_step)
    return {"preset": preset, "device": str(device), "batch": b, "patch_px": p, "kernel_px": m + 1,
            "step_s": step, "patches_per_s": b / step,
            "optics_fraction": statistics.median(t_optics) / step, "network_fraction": statistics.median(t_net) / step}


def fixed_optics_steps(preset: str, device: torch.device, steps: int) -> dict:
    """Steps after ``train.optics_steps``: the batch imaged through ``camera.fixed_measure()`` (PSFs
    built once, no autograd through the optics), the network trained alone."""
    cfg = load_config(preset)
    torch.manual_seed(0)
    model = as_trained(CameraSystem.from_config(cfg).to(device), cfg, device)
    opt = torch.optim.Adam(model.net.parameters(), lr=cfg.train.lr)
    b, p, m = cfg.train.batch_size, cfg.data.patch_px, model.camera.margin
    scene = torch.rand(b, len(model.bands), p + m, p + m, device=device)
    measure = model.camera.fixed_measure()
    times = []
    for i in range(steps + 1):
        _sync(device)
        t0 = time.perf_counter()
        recon, _ = model(scene, measure=measure)
        loss = system_loss(recon.float(), model.target(scene), cfg.train)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        _sync(device)
        if i:  # the first step builds the PSFs and warms up
            times.append(time.perf_counter() - t0)
    step = statistics.median(times)
    return {"preset": preset, "device": str(device), "batch": b, "step_s": step, "patches_per_s": b / step}


@torch.no_grad()
def inference(preset: str, device: torch.device, repeats: int = 3) -> dict:
    cfg = load_config(preset)
    model = CameraSystem.from_config(cfg).to(device).eval()
    model.consistency = None  # the network alone (the steps: landweber_steps_time, linear_step_time)
    if device.type == "cuda" and cfg.train.bf16:
        model.autocast_dtype = torch.bfloat16
    g = torch.rand(1, 1, 512, 512, device=device)
    model.reconstruct(g)
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        model.reconstruct(g)
        _sync(device)
        times.append(time.perf_counter() - t0)
    return {"preset": preset, "device": str(device), "size": [len(model.bands), 512, 512],
            "seconds": statistics.median(times)}


@torch.no_grad()
def landweber_steps_time(run: str = "pretrained:standard", repeats: int = 3, size: int = 512) -> dict:
    """The Landweber steps of ``run`` as its reconstruction takes them (``reconstructor().steps``: kind linear's
    ``landweber_after`` after the linear step, else ``iterations``; with the run's spectral prior, TV prior and noise
    weighting, through its PSFs cut to ``psf_energy``) from a random estimate of a random ``size``² image: the
    median of ``repeats`` calls after one warm-up, all the steps (``seconds``) and per step. Until session 75 this
    entry (``consistency_step_cpu``) timed one plain Landweber step, no prior, labelled with the linear step's
    ``iterations``."""
    from hsicam.models.consistency import cut_psf
    from hsicam.runs.folder import load_run

    cfg, model = load_run(run)
    c = cfg.model.consistency
    fn = model.eval().reconstructor()
    steps = getattr(fn, "steps", None)
    out = {"camera": run, "steps": steps.count if steps else 0, "spectral_prior": c.spectral_prior,
           "tv_weight": c.tv_weight, "kernel_px": cut_psf(model.camera.snapshot(nominal=True), c.psf_energy).kernel_px,
           "size": [len(model.bands), size, size]}
    if steps is None:  # a run without Landweber steps: nothing to time
        return {**out, "seconds": None, "seconds_per_step": None}
    g = torch.rand(1, 1, size, size)
    x = torch.rand(1, len(model.bands), size, size)
    seconds = median_time(lambda: steps(g, x), repeats, warmup=1)
    return {**out, "seconds": seconds, "seconds_per_step": seconds / steps.count}


@torch.no_grad()
def linear_step_time(run: str = "pretrained:standard", window: int = 11, repeats: int = 3) -> dict:
    """The linear consistency step (``model.consistency.kind: linear``) on 512×512 through the same
    camera, with random filters of the quick preset's width (the time does not depend on them)."""
    from hsicam.models.consistency import linear_consistency_step
    from hsicam.runs.folder import load_run

    _, model = load_run(run)
    snap = model.camera.snapshot(nominal=True)
    m, c = model.camera.code_period, len(model.bands)
    weight = torch.randn(m * m, c, window, window) * 0.01
    g = torch.rand(1, 1, 512, 512)
    x = torch.rand(1, c, 512, 512)
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        linear_consistency_step(snap, g, x, weight, gain=0.5)
        times.append(time.perf_counter() - t0)
    return {"camera": run, "window_px": window, "size": [c, 512, 512], "seconds": statistics.median(times[1:])}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=positive_int, default=5)
    ap.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's choice)")
    allocator_option(ap)
    args = ap.parse_args()
    kept = apply_allocator(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    cpu = torch.device("cpu")
    out = {"torch": torch.__version__, "threads": torch.get_num_threads(), "keep_freed_memory": kept,
           "train_quick_cpu": train_steps("quick", cpu, args.steps, []),
           "train_quick_cpu_fixed_optics": fixed_optics_steps("quick", cpu, args.steps),
           "inference_cpu": [inference("quick", cpu), inference("paper", cpu, repeats=1)],
           "landweber_steps_cpu": landweber_steps_time(),
           "linear_step_cpu": linear_step_time()}
    if torch.cuda.is_available():
        gpu = torch.device("cuda")
        out["gpu"] = torch.cuda.get_device_name(0)
        out["train_paper_gpu"] = train_steps("paper", gpu, max(args.steps, 10), [])
        out["inference_gpu"] = [inference("quick", gpu), inference("paper", gpu)]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
