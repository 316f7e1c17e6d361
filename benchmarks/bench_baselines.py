"""Baselines benchmark (issue 6): prints one JSON object.

Seconds to reconstruct one 256 × 256 × 31 scene (the quick preset's band grid) from its DD-CASSI
measurement with each baseline at its default settings, next to the DOE camera's network
inference (the untrained quick preset, ``CameraSystem.from_config(load_config("quick"))``: the runtime does not
depend on the weights):

- ``dd-cassi-gaptv``: GAP-TV (``baselines.gaptv`` defaults)
- ``dd-cassi-desci``: DeSCI ``fast`` preset (``--full`` adds the ``full`` preset: many minutes)
- ``dd-cassi-choi``: ADMM with the spectral prior (an untrained autoencoder of the default size)
- ``dd-cassi-rdn``: the quick-size RDN on the DD-CASSI measurement
- ``doe-rdn`` (the name kept from when the quick network was an RDN): the quick preset's whole inference on the DOE
  camera's sensor image, its network and its consistency steps (the linear step with zero filters of the fitted
  shape; through the untrained camera's wide lens PSF, so the steps cost more than a trained camera's)

Iterative solvers run once (they take seconds to minutes); networks take the median of
``--repeats`` runs after a warm-up. Run: `.venv/bin/python benchmarks/bench_baselines.py [--out FILE]`.
"""

from __future__ import annotations

import argparse
import json
import platform

import torch
import torch.nn.functional as F

from hsicam.config import load_config
from hsicam.engine.experiments import CASSI_RDN_OVERRIDES
from hsicam.models import CameraSystem
from hsicam.engine.methods import dd_cassi_camera
from hsicam.models.priors import SpectralAutoencoder
from hsicam.solvers.choi import admm_prior
from hsicam.config import BaselinesConfig
from hsicam.devices import device_problem
from hsicam.solvers.desci import desci, desci_settings
from hsicam.solvers.gaptv import gap_tv
from timing import median_time, positive_int, untrained_system_for_inference


def smooth_scene(c: int, size: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(1, c, size // 16, size // 16, generator=g)
    return F.interpolate(low, size=(size, size), mode="bilinear", align_corners=False).clamp(0, 1)


@torch.no_grad()
def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=positive_int, default=256)
    ap.add_argument("--repeats", type=positive_int, default=3)
    ap.add_argument("--full", action="store_true", help="also time DeSCI's full preset (slow)")
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or mps")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if args.size < 16:  # the smooth scene is drawn on a size/16 grid
        ap.error(f"--size must be >= 16, got {args.size}")
    problem = device_problem(args.device)  # a device this machine lacks: one line, not torch's traceback
    if problem is not None:
        ap.error(f"--device {args.device}: {problem}")
    dev = torch.device(args.device)
    torch.manual_seed(0)
    cfg = load_config("quick")
    bands = cfg.bands.to_bands()
    b = BaselinesConfig()
    cam = dd_cassi_camera(cfg, dev)
    scene = smooth_scene(len(bands), args.size).to(dev)
    y = cam.A(scene)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    def run(fn):
        def f():
            fn()
            sync()
        return f

    result: dict = {"torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.machine(),
                    "device": str(dev), "scene": [len(bands), args.size, args.size], "seconds_per_scene": {}, "settings": {}}
    sec = result["seconds_per_scene"]
    g = b.gaptv
    sec["dd-cassi-gaptv"] = median_time(run(lambda: gap_tv(cam, y, g.iterations, g.tv_weight, g.tv_iterations, g.accelerate)))
    result["settings"]["dd-cassi-gaptv"] = {"iterations": g.iterations}
    fast = desci_settings("fast")
    sec["dd-cassi-desci"] = median_time(run(lambda: desci(cam, y, fast)))
    result["settings"]["dd-cassi-desci"] = {"preset": "fast", "iterations": sum(fast.iterations), "step": fast.step,
                                            "group": fast.group}
    if args.full:
        full = desci_settings("full")
        sec["dd-cassi-desci-full"] = median_time(run(lambda: desci(cam, y, full)))
    c = b.choi_or_default
    prior = SpectralAutoencoder(len(bands), c.features, c.latent).to(dev).requires_grad_(False).eval()
    sec["dd-cassi-choi"] = median_time(run(lambda: admm_prior(cam, y, prior, c)))
    result["settings"]["dd-cassi-choi"] = {"iterations": c.iterations, "inner_steps": c.inner_steps}
    cassi_net = CameraSystem.from_config(load_config("quick", list(CASSI_RDN_OVERRIDES))).to(dev).eval()
    sec["dd-cassi-rdn"] = median_time(run(lambda: cassi_net.reconstruct(y)), args.repeats, 1)
    doe = untrained_system_for_inference(CameraSystem.from_config(cfg).to(dev).eval(), cfg)
    sensor = torch.rand(1, 1, args.size, args.size, device=dev)
    doe_fn = doe.reconstructor()  # the operator computed once, as `hsicam reconstruct` and `evaluate` do
    sec["doe-rdn"] = median_time(run(lambda: doe_fn(sensor)), args.repeats, 1)
    result["doe_rdn_speedup"] = {k: v / sec["doe-rdn"] for k, v in sec.items() if k != "doe-rdn"}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        from hsicam.io import atomic_open

        with atomic_open(args.out, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
