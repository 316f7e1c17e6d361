"""Tiled reconstruction equals the whole-image pass; sensor image reading."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsicam.engine.inference import read_sensor_image, receptive_radius, reconstruct_tiled
from hsicam.errors import InputError
from hsicam.models import RDN


def test_tiles_are_seamless():
    torch.manual_seed(0)
    net = RDN(bands=4, blocks=2, features=8, growth=4, layers_per_block=2).eval()
    img = torch.rand(1, 1, 97, 83)
    with torch.no_grad():
        whole = net(img)
    tiled = reconstruct_tiled(net, img, tile_px=32, halo_px=receptive_radius(net))
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)
    # without enough context the seams show: the test above can fail
    bad = reconstruct_tiled(net, img, tile_px=32, halo_px=0)
    assert (bad - whole).abs().max() > 1e-3


def test_receptive_radius_of_rdn():
    net = RDN(bands=3, blocks=2, features=8, growth=4, layers_per_block=3)
    # sfe1, sfe2, 2×3 block convs, global 3×3, output: all 3×3 → radius 1 each
    assert receptive_radius(net) == 2 + 6 + 2


def test_read_sensor_png16_and_scale(tmp_path):
    import imageio.v3 as iio

    data = np.array([[0, 65535], [32768, 1000]], dtype=np.uint16)
    iio.imwrite(tmp_path / "s.png", data)
    img = read_sensor_image(tmp_path / "s.png", scale=2.0)
    np.testing.assert_allclose(img, data / 65535.0 * 2.0, rtol=1e-6)


def test_read_sensor_errors(tmp_path):
    np.save(tmp_path / "s.npy", np.ones((2, 3, 4)))
    with pytest.raises(InputError, match="2-D"):
        read_sensor_image(tmp_path / "s.npy")
    (tmp_path / "x.jpg").write_bytes(b"123")
    with pytest.raises(InputError, match="unsupported"):
        read_sensor_image(tmp_path / "x.jpg")
    with pytest.raises(InputError, match="no such"):
        read_sensor_image(tmp_path / "missing.npy")
