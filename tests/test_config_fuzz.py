"""Every config key against hostile values (fuzz10a): a user's mistake is one ConfigError naming the key, never a
traceback, and the bounds the checks keep are ones the code behind them computes correctly at."""

from __future__ import annotations

import re

import pytest
import torch

from hsicam.config import MAX_FULL_WELL_E, MIN_FULL_WELL_E, load_config
from hsicam.errors import ConfigError
from hsicam.sensor import poisson_gaussian_noise


def _refused(override: str, key: str) -> str:
    with pytest.raises(ConfigError) as info:
        load_config("tiny", [override])
    assert key in str(info.value), str(info.value)
    return str(info.value)


# -- camera.sensor: the Poisson-Gaussian photon level ----------------------------------------------------------
@pytest.mark.parametrize("value", ["1e20", "1e300", "1e-300", "0.001"])
def test_full_well_outside_its_range_is_refused_naming_the_key(value):
    # 1e20 e-: torch.poisson's int64 count overflowed to -2^63, a constant negative image; 1e-300: an infinite one
    text = _refused(f"camera.sensor.full_well_e={value}", "camera.sensor.full_well_e")
    assert f"got {float(value):g}" in text


@pytest.mark.parametrize("read_noise", ["1e300", "20001"])
def test_read_noise_above_the_full_scale_is_refused(read_noise):
    text = _refused(f"camera.sensor.read_noise_e={read_noise}", "camera.sensor.read_noise_e")
    assert "full_well_e" in text


@pytest.mark.parametrize("full_well", [MIN_FULL_WELL_E, MAX_FULL_WELL_E])
def test_full_well_bounds_give_poisson_statistics(full_well):
    # at both ends of the range the noisy image keeps the clean one's mean: E[Poisson(gN)/N] = g, var g/N (closed form)
    cfg = load_config("tiny", [f"camera.sensor.full_well_e={full_well}", f"camera.sensor.read_noise_e={full_well}",
                               "camera.sensor.noise=poisson_gaussian"])
    g = torch.full((1, 1, 256, 256), 0.5)
    out = poisson_gaussian_noise(g, cfg.camera.sensor.full_well_e, 0.0, torch.Generator().manual_seed(0))
    assert torch.isfinite(out).all()
    sd = (0.5 / full_well) ** 0.5
    assert abs(out.mean().item() - 0.5) < 5 * sd / 256 + 1e-6
    assert out.min().item() >= 0.0
