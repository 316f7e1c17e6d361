"""Contracts of the reconstruction networks measured across kinds (session 55 review): input precision."""

from __future__ import annotations

import pytest
import torch

from hsicam.config import load_config
from hsicam.models import CameraSystem


pytestmark = pytest.mark.usefixtures("one_torch_thread")


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


def _measured_reach(net: torch.nn.Module, size: int = 41) -> int:
    """Farthest distance (px, along either axis) between a perturbed input pixel and an output pixel it
    changes, output index i aligned with input index i."""
    c = size // 2
    x = torch.rand(1, net[0].in_channels if isinstance(net, torch.nn.Sequential) else net.in_channels,
                   size, size, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    bumped = x.clone()
    bumped[..., c, c] += 1.0
    with torch.no_grad():
        changed = (net(bumped) - net(x)).abs().sum(dim=(0, 1)) > 0
    rows, cols = torch.nonzero(changed, as_tuple=True)
    return int(max((rows - c).abs().max(), (cols - c).abs().max()))


@pytest.mark.filterwarnings("ignore:Using padding=.same. with even kernel")
@pytest.mark.parametrize("make", [
    lambda: torch.nn.Conv2d(2, 2, (1, 5), padding=(0, 2)),               # a 1×k kernel: its reach is along x
    lambda: torch.nn.Conv2d(2, 2, (5, 1), padding=(2, 0)),
    lambda: torch.nn.Conv2d(2, 2, 4, padding="same"),                     # an even kernel: 2 px on one side
    lambda: torch.nn.Conv2d(2, 2, 3, padding=0),                          # unpadded: the window lies on one side
    lambda: torch.nn.Conv2d(2, 2, (3, 5), padding=(1, 2), dilation=(1, 3)),
    lambda: torch.nn.Sequential(torch.nn.Conv2d(2, 2, 3, padding=1), torch.nn.ReLU(),
                                torch.nn.Conv2d(2, 2, (1, 7), padding=(0, 3))),
])
def test_conv_receptive_radius_bounds_the_measured_reach(make):
    """The tiling halo of a conv network bounds how far a pixel's change travels, for kernels that are not
    square and odd too (it read the first axis's dilation·(k−1)//2 only: 0 for a 1×5 kernel that reaches 2 px)."""
    from hsicam.models.context import conv_receptive_radius

    torch.manual_seed(0)
    net = make().double()
    measured = _measured_reach(net)
    assert conv_receptive_radius(net) >= measured
    if not isinstance(net, torch.nn.Sequential):
        assert conv_receptive_radius(net) == measured  # one conv: the bound is its reach
