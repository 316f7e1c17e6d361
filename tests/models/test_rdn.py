"""The RDN reconstructor: its receptive radius (counted from its layers), its documented initialisation (an
untrained RDN returns the grey sensor image in every band) and its demosaic input (the sensor image and the
normalised local average per band, against a loop reference). Moved from engine/test_inference.py, whose tiling
tests stay there."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from demosaic_reference import box_demosaic_reference
from hsicam.models import RDN
from hsicam.models.context import conv_receptive_radius as receptive_radius
from rdn_systems import demosaic_input_system


def test_receptive_radius_of_rdn():
    net = RDN(bands=3, blocks=2, features=8, growth=4, layers_per_block=3)
    # sfe1, sfe2, 2×3 block convs, global 3×3, output: all 3×3 → radius 1 each
    assert receptive_radius(net) == 2 + 6 + 2


@pytest.mark.parametrize("period", [3, 4])
def test_demosaic_input_is_the_normalised_local_average_per_band(tiny_config, period):
    model = demosaic_input_system(tiny_config, f"camera.cfa.period={period}")
    c = len(model.bands)
    assert model.net.tentative.in_channels == 1 + c
    assert model.net.window == (3 if period == 3 else 5)
    g = torch.rand(2, 1, 13, 17, dtype=torch.float64)
    with torch.no_grad():
        inp = model.double().net.network_input(g, model.camera, origin=(3, 4))
        kappa = model.camera.cfa.pattern(20, 25)[:, 3:16, 4:21].numpy()
    assert inp.shape == (2, 1 + c, 13, 17)
    torch.testing.assert_close(inp[:, :1], g)
    for b in range(2):
        np.testing.assert_allclose(inp[b, 1:].numpy(), box_demosaic_reference(g[b, 0].numpy(), kappa, model.net.window),
                                   rtol=1e-10)
    # a flat grey sensor image demosaics to the same grey in every band
    flat = model.net.network_input(torch.full((1, 1, 13, 17), 0.3, dtype=torch.float64), model.camera)
    torch.testing.assert_close(flat[:, 1:], torch.full((1, c, 13, 17), 0.3, dtype=torch.float64))
    # untrained, the system returns the demosaic (tentative = x̃, zero output conv)
    with torch.no_grad():
        torch.testing.assert_close(model.reconstruct(g, origin=(3, 4)), inp[:, 1:])


def test_untrained_rdn_returns_the_grey_image():
    """Documented initialisation: tentative t_c = g, zero output conv, so f̂ = g in every band."""
    net = RDN(bands=5, in_channels=3, blocks=1, features=8, growth=4, layers_per_block=2)
    x = torch.rand(2, 3, 9, 7)
    with torch.no_grad():
        out = net(x)
    torch.testing.assert_close(out, x[:, :1].expand(2, 5, 9, 7))
