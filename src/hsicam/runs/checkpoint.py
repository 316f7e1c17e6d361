"""Checkpoints in safetensors, written atomically (loading a run for inference: :mod:`hsicam.runs.folder`).

Run folder layout::

    RUN/config.yaml            resolved config
    RUN/metrics.jsonl          one JSON object per log/eval event
    RUN/model.safetensors      weights (network + optics) of the best (else last) checkpoint
    RUN/checkpoints/step-N/    model.safetensors, optimizer.safetensors, state.json
    RUN/last.json, best.json   pointers {"dir": "checkpoints/step-N", ...}

A checkpoint directory is written under a temporary name and renamed into place; the pointer
files are replaced atomically afterwards, so a process killed at any moment leaves the previous
checkpoint intact and referenced.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from hsicam.errors import InputError
from hsicam.io import atomic_path, write_json
from hsicam.spectral import Bands

FORMAT = "hsicam-checkpoint-1"


def save_weights(path: str | Path, model: nn.Module, bands: Bands, extra: dict[str, str] | None = None) -> None:
    """Model state dict → safetensors (atomic), with the band grid in the metadata."""
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    meta = {"format": FORMAT, "bands": json.dumps(bands.to_dict()), **(extra or {})}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def read_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of a safetensors file; :class:`InputError` if missing or corrupt."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such weights file")
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise InputError(f"{path}: corrupt or unreadable safetensors file ({str(exc).splitlines()[0]})") from None
    return tensors, meta


def load_weights(path: str | Path, model: nn.Module, bands: Bands) -> None:
    """Load weights into ``model`` after checking the band grid and the tensor names and shapes."""
    tensors, meta = read_weights(path)
    if "bands" in meta:
        saved = Bands.from_dict(json.loads(meta["bands"]))
        if not saved.matches(bands):
            raise InputError(f"{path}: checkpoint was trained on {saved!r}, but the model has {bands!r}")
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise InputError(f"{path}: weights do not fit this model (missing {missing[:3]}, unexpected {unexpected[:3]})")
    for k, v in tensors.items():
        if v.shape != expected[k].shape:
            raise InputError(f"{path}: tensor {k} has shape {tuple(v.shape)}, the model expects {tuple(expected[k].shape)}")
    model.load_state_dict(tensors)


def save_optimizer(path: str | Path, optimizer: torch.optim.Optimizer) -> None:
    """Optimizer state → safetensors (tensors) + JSON metadata (param groups, scalars)."""
    sd = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, Any] = {}
    for idx, st in sd["state"].items():
        for name, val in st.items():
            if isinstance(val, torch.Tensor):
                tensors[f"{idx}.{name}"] = val.detach().cpu().contiguous()
            else:
                scalars[f"{idx}.{name}"] = val
    meta = {"format": FORMAT, "param_groups": json.dumps(sd["param_groups"]), "scalars": json.dumps(scalars)}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def load_optimizer(path: str | Path, optimizer: torch.optim.Optimizer) -> None:
    tensors, meta = read_weights(path)
    try:
        groups = json.loads(meta["param_groups"])
        scalars = json.loads(meta["scalars"])
    except (KeyError, json.JSONDecodeError):
        raise InputError(f"{path}: not an hsicam optimizer state") from None
    state: dict[int, dict[str, Any]] = {}
    for key, val in [*tensors.items(), *scalars.items()]:
        idx, name = key.split(".", 1)
        state.setdefault(int(idx), {})[name] = val
    try:
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except (ValueError, KeyError) as exc:
        raise InputError(f"{path}: optimizer state does not fit ({exc})") from None


class CheckpointManager:
    """Writes and finds the checkpoints of one run folder (see module docstring)."""

    def __init__(self, run_dir: str | Path) -> None:
        self.run_dir = Path(run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"

    def save(self, model: nn.Module, optimizer: torch.optim.Optimizer, state: dict[str, Any], bands: Bands,
             tags: tuple[str, ...] = ("last",)) -> Path:
        """Write checkpoint ``step-<global_step>`` and point ``tags`` (last / best) at it."""
        self.ckpt_dir.mkdir(parents=True, exist_ok=True)
        name = f"step-{int(state['global_step']):08d}"
        final = self.ckpt_dir / name
        if final.exists():
            # Same step (e.g. the epoch-end save after a periodic one): the weights are the
            # same; only the training state moves on (epoch counter, best).
            write_json(final / "state.json", state)
        else:
            tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=self.ckpt_dir))
            try:
                save_weights(tmp / "model.safetensors", model, bands)
                save_optimizer(tmp / "optimizer.safetensors", optimizer)
                write_json(tmp / "state.json", state)
                os.rename(tmp, final)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        for tag in tags:
            write_json(self.run_dir / f"{tag}.json", {"dir": f"checkpoints/{name}", **state})
        self._prune()
        return final

    def path(self, tag: str) -> Path | None:
        """Checkpoint directory that ``tag`` points to, or None."""
        ptr = self.run_dir / f"{tag}.json"
        if not ptr.is_file():
            return None
        try:
            d = self.run_dir / json.loads(ptr.read_text())["dir"]
        except (json.JSONDecodeError, KeyError):
            raise InputError(f"{ptr}: corrupt checkpoint pointer") from None
        return d if d.is_dir() else None

    def _prune(self) -> None:
        keep = {p.name for p in (self.path("last"), self.path("best")) if p is not None}
        for d in self.ckpt_dir.iterdir():
            if d.name not in keep and (d.name.startswith("step-") or d.name.startswith(".step-")):
                shutil.rmtree(d, ignore_errors=True)

    def load(self, tag: str, model: nn.Module, optimizer: torch.optim.Optimizer | None, bands: Bands) -> dict[str, Any]:
        """Restore model (and optimizer) from ``tag``; returns the saved training state."""
        d = self.path(tag)
        if d is None:
            raise InputError(f"{self.run_dir}: no '{tag}' checkpoint to resume from")
        load_weights(d / "model.safetensors", model, bands)
        if optimizer is not None:
            load_optimizer(d / "optimizer.safetensors", optimizer)
        return json.loads((d / "state.json").read_text())
