"""Portability beyond Linux/glibc: macOS (Apple silicon, the ``mps`` device) and Windows, simulated here.

MPS has no float64: a float64 tensor there is a TypeError ("Cannot convert a MPS Tensor to float64 dtype as the
MPS framework doesn't support float64"). No MPS device can be had here, so the tests check the rule where it is
decided (a pure function of the device) and that the code follows it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

SRC = Path(__file__).resolve().parents[1] / "src" / "hsicam"


# ------------------------------------------------------------------------------------------------
# float64 work for a device without float64 (MPS)
# ------------------------------------------------------------------------------------------------
def test_float64_work_runs_on_the_cpu_for_mps_only():
    from hsicam.devices import float64_device

    assert float64_device("mps") == torch.device("cpu")
    assert float64_device(torch.device("mps")) == torch.device("cpu")
    assert float64_device("cpu") == torch.device("cpu")
    assert float64_device("cuda:1") == torch.device("cuda:1")  # CUDA has float64: scores stay on the GPU


def test_metrics_compute_in_float64_where_float64_device_says(monkeypatch):
    """The scores (training's validation, evaluate) go through float64_device: on MPS, the CPU. Simulated with
    the meta device standing for the place the work is sent to."""
    import hsicam.metrics as m

    sent = []

    def to_meta(device):
        sent.append(torch.device(device))
        return torch.device("meta")

    monkeypatch.setattr(m, "float64_device", to_meta)
    x, y = torch.rand(2, 3, 16, 16), torch.rand(2, 3, 16, 16)
    for fn in (m.psnr_per_band, m.psnr_cube, m.ssim, m.sam_degrees, m.rmse, m.ergas, m.ergas_undefined):
        out = fn(x, y) if fn is not m.ergas_undefined else fn(y)
        assert out.device.type == "meta", fn.__name__
        assert sent and sent[-1] == torch.device("cpu"), fn.__name__
    # float32 work (the training loss's SSIM, whose gradient flows to the network) stays where it is
    sent.clear()
    assert m.ssim(x, y, dtype=torch.float32).device.type == "cpu" and not sent


def test_the_psf_energy_cut_measures_in_float64_where_float64_device_says(monkeypatch):
    import hsicam.models.consistency as c

    seen = []

    def spy(device):
        seen.append(torch.device(device))
        return torch.device("cpu")

    class Op:
        psf = torch.zeros(2, 5, 5)

        def cropped(self, k):
            return k

    Op.psf[:, 2, 2] = 1.0
    monkeypatch.setattr(c, "float64_device", spy)
    assert c.cut_psf(Op(), 0.99) == 1 and seen == [torch.device("cpu")]


def _float64_then_cpu(node: ast.AST) -> bool:
    """``X.double().cpu()`` / ``X.to(torch.float64).cpu()``: the conversion runs on X's device before the copy."""
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "cpu"):
        return False
    inner = node.func.value
    if not (isinstance(inner, ast.Call) and isinstance(inner.func, ast.Attribute)):
        return False
    if inner.func.attr == "double":
        return True
    args = [*inner.args, *(k.value for k in inner.keywords)]
    return inner.func.attr == "to" and any(isinstance(a, ast.Attribute) and a.attr in ("float64", "double")
                                           for a in args)


def test_no_float64_conversion_on_the_device_before_a_copy_to_the_cpu():
    """``t.double().cpu()`` makes the float64 copy on ``t``'s device: on MPS a TypeError (a camera loaded with
    ``--device mps``: fabrication export, camera report, tolerance, the linear demosaic's fit); ``t.cpu().double()``
    gives the same values everywhere."""
    found = []
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if _float64_then_cpu(node):
                found.append(f"{path.relative_to(SRC)}:{node.lineno}")
    assert found == []
