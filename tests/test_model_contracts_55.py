"""Contracts of the reconstruction networks measured across kinds (session 55 review): input precision."""

from __future__ import annotations

import pytest
import torch

from hsicam.config import load_config
from hsicam.models import CameraSystem


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _random_weights(net: torch.nn.Module) -> None:
    """Every parameter perturbed (the zero-initialised output conv would hide the input estimate's paths)."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))


@pytest.mark.parametrize("setting", ["backprojection_input", "demosaic_input"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_rdn_input_estimate_of_a_low_precision_image_is_the_float32_one(setting, dtype):
    """`reconstruct` takes a sensor image of any floating precision. The RDN reading an input estimate (the
    back-projection, the demosaic) of a float16/bfloat16 image returns what its float32 copy gives: the estimate
    is computed in the network's float32, as the mosaic and unrolled networks do. Before, the back-projection
    through the DOE camera's FFTs raised torch's "Unsupported dtype Half" on the CPU, and the demosaic was computed
    in float16 (1e-3 off)."""
    torch.manual_seed(0)
    model = CameraSystem.from_config(load_config("tiny", overrides=[f"model.rdn.{setting}=true"])).eval()
    _random_weights(model.net)
    y = torch.rand(2, 1, 20, 23, generator=torch.Generator().manual_seed(2)).to(dtype)
    with torch.no_grad():
        low = model.reconstruct(y)
        reference = model.reconstruct(y.float())  # the same values, in float32
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, reference, rtol=0, atol=0)
