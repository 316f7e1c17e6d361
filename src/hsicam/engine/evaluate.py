"""Evaluation of a trained camera on whole scenes.

Each scene is imaged in the camera's ``valid`` mode (the physically right one: the scene border
is context the sensor does not see), so metrics cover the sensor area: the scene minus the
kernel margin. Reconstructions are clipped to [0, 1] (scenes are per-cube max normalised).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from hsicam.metrics import CONVENTIONS, all_metrics
from hsicam.models import CameraSystem


@dataclass
class SceneResult:
    name: str
    metrics: dict[str, float]
    truth: np.ndarray  # (C, H, W), the sensor-aligned ground truth
    estimate: np.ndarray  # (C, H, W)
    runtime_s: float  # reconstruction time (network only)


@torch.no_grad()
def evaluate_scenes(model: CameraSystem, scenes, names: list[str], seed: int = 0, device: str | torch.device = "cpu",
                    keep_arrays: bool = True) -> list[SceneResult]:
    """Simulate, reconstruct and score every scene of ``scenes`` (a SceneDataset-like sequence)."""
    model.eval()
    out = []
    g = torch.Generator(device=device).manual_seed(seed)
    psf = model.camera.psf(g)
    for i, name in enumerate(names):
        scene = scenes[i][None].to(device)
        sensor = model.camera.noise(model.camera.A(scene, psf), g)
        t0 = time.perf_counter()
        est = model.reconstruct(sensor).float().clamp(0, 1)
        runtime = time.perf_counter() - t0
        truth = model.target(scene)
        m = {k: v[0] for k, v in all_metrics(est, truth).items()}
        out.append(SceneResult(name, m, truth[0].cpu().numpy() if keep_arrays else None,
                               est[0].cpu().numpy() if keep_arrays else None, runtime))
    return out


def summarize(results: list[SceneResult]) -> dict:
    """Per-scene rows, means and the metric conventions, as a JSON-ready dict."""
    rows = [{"name": r.name, **r.metrics, "runtime_s": r.runtime_s} for r in results]
    keys = list(results[0].metrics) + ["runtime_s"] if results else []
    means = {k: float(np.mean([row[k] for row in rows])) for k in keys}
    return {"scenes": rows, "mean": means, "conventions": CONVENTIONS}


def format_table(summary: dict, keys: tuple[str, ...] = ("psnr", "ssim", "sam")) -> str:
    """A plain-text table (Markdown-compatible) of the per-scene metrics and their mean."""
    head = "| scene | " + " | ".join(keys) + " |"
    sep = "|---" * (len(keys) + 1) + "|"
    lines = [head, sep]
    for row in summary["scenes"] + [{"name": "**mean**", **summary["mean"]}]:
        lines.append(f"| {row['name']} | " + " | ".join(_fmt(k, row[k]) for k in keys) + " |")
    return "\n".join(lines)


def _fmt(key: str, v: float) -> str:
    return f"{v:.4f}" if key == "ssim" else f"{v:.2f}"
