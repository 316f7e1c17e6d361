"""Portability beyond Linux/glibc: macOS (Apple silicon, the ``mps`` device) and Windows, simulated here.

MPS has no float64: a float64 tensor there is a TypeError ("Cannot convert a MPS Tensor to float64 dtype as the
MPS framework doesn't support float64"). No MPS device can be had here, so the tests check the rule where it is
decided (a pure function of the device) and that the code follows it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

SRC = Path(__file__).resolve().parents[2] / "src" / "hsicam"


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


class _NoFloat64(torch.overrides.TorchFunctionMode):
    """Stands for a device without float64 (MPS): any operation that makes a float64 tensor raises MPS's TypeError."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in out if isinstance(out, (tuple, list)) else (out,):
            if isinstance(t, torch.Tensor) and t.dtype == torch.float64:
                raise TypeError(f"{getattr(func, '__name__', func)}: Cannot convert a MPS Tensor to float64 dtype "
                                "as the MPS framework doesn't support float64. Please use float32 instead.")
        return out


@pytest.mark.parametrize("density", [0.5, 0.1, 0.9, 1.0, 2.0**-32 * 3, 0.5 + 2.0**-33])
def test_the_random_coded_aperture_is_made_on_its_device_without_float64(density):
    """A CASSI camera on ``mps`` hashes its aperture there: the old float64 draw (hashed_uniform) was a TypeError.
    The cells are those of the float64 rule ``hashed_uniform < density``, computed here outside the device."""
    from hsicam.cameras.cassi import hashed_uniform, random_aperture

    want = (hashed_uniform(40, 50, 7, origin=(3, 11)) < density).to(torch.float32)
    with _NoFloat64():
        got = random_aperture(40, 50, seed=7, density=density, origin=(3, 11))
    assert got.dtype == torch.float32
    assert torch.equal(got, want)


def test_a_coded_aperture_file_does_not_stop_the_camera_from_moving_to_a_device_without_float64(tmp_path):
    """``camera.to("mps")`` converts every buffer and parameter to the device: a float64 one is a TypeError there.
    The file's values stay exact (float64 on the CPU) for a float64 window."""
    import numpy as np

    from hsicam.cameras import build_camera
    from hsicam.config import load_config

    mask = np.random.default_rng(0).random((12, 30))
    np.save(tmp_path / "mask.npy", mask)
    cfg = load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50",
                                 "camera.kind=dd_cassi", f"camera.cassi.mask_file={tmp_path / 'mask.npy'}"])
    cam = build_camera(cfg)
    moved = [name for name, t in [*cam.named_buffers(), *cam.named_parameters()] if t.dtype == torch.float64]
    assert moved == []
    np.testing.assert_array_equal(cam.aperture.pattern(12, 18, dtype=torch.float64).numpy(), mask[:, :18])
    np.testing.assert_array_equal(cam.aperture.pattern(12, 18).numpy(), mask[:, :18].astype(np.float32))


def test_desci_does_its_float64_eigen_work_where_float64_device_says(monkeypatch):
    """DeSCI's spectral PCA and WNNM groups made float64 tensors on the data's device (`evaluate --method
    dd-cassi-desci --device mps`: a TypeError on MPS). They go through float64_device now (the CPU for mps; here a
    spy on the CPU), with the same results as before and back on the data's device in its dtype."""
    import importlib

    d = importlib.import_module("hsicam.solvers.desci")  # the package exports a function of that name

    seen = []

    def spy(device):
        seen.append(torch.device(device))
        return torch.device("cpu")

    g = torch.Generator().manual_seed(0)
    x = torch.rand(6, 12, 10, generator=g)
    groups = torch.rand(4, 9, 5, generator=g)
    before = d.spectral_features(x, 3), d.wnnm_groups(groups, 0.1)
    monkeypatch.setattr(d, "float64_device", spy)
    after = d.spectral_features(x, 3), d.wnnm_groups(groups, 0.1)
    assert seen == [torch.device("cpu")] * 2
    for a, b in zip(before, after):
        assert b.dtype == torch.float32 and b.device.type == "cpu"
        torch.testing.assert_close(a, b, rtol=0, atol=0)
