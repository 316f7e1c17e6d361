"""Every config key against hostile values (fuzz10a): a user's mistake is one ConfigError naming the key, never a
traceback, and the bounds the checks keep are ones the code behind them computes correctly at."""

from __future__ import annotations

import re

import pytest
import torch

from hsicam.config import MAX_FULL_WELL_E, MAX_STEP_INIT, MAX_WINDOW_PX, MIN_FULL_WELL_E, load_config
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


# -- camera.doe.init_correlation_cells (init smooth) --------------------------------------------------------------
@pytest.mark.parametrize("sigma", ["1e155", "1e300"])
def test_huge_smooth_correlation_is_refused_naming_the_key(sigma):
    # σ² overflowed in gaussian_lowpass_periodic: OverflowError (34, 'Numerical result out of range') at build
    from hsicam.cameras import build_camera

    cfg = load_config("tiny", ["camera.doe.init=smooth", f"camera.doe.init_correlation_cells={sigma}"])
    with pytest.raises(ConfigError, match=r"camera\.doe\.init_correlation_cells=1e\+(155|300) is too wide"):
        build_camera(cfg)


def test_lowpass_matches_a_direct_periodic_gaussian_convolution():
    # closed form: a cosine cos(2π k x / n) comes back scaled by the Gaussian's transfer exp(-2π² σ² (k/n)²)
    from hsicam.optics.doe import gaussian_lowpass_periodic

    n, k, sigma = 32, 3, 1.7
    x = torch.arange(n, dtype=torch.float64)
    wave = torch.cos(2 * torch.pi * k * x / n)[None, :].expand(n, n)
    out = gaussian_lowpass_periodic(wave, sigma)
    expected = wave * torch.exp(torch.tensor(-2.0 * torch.pi**2 * sigma**2 * (k / n) ** 2, dtype=torch.float64))
    assert torch.allclose(out, expected, atol=1e-12)
    flat = gaussian_lowpass_periodic(wave + 0.25, 1e300)  # the mean alone survives
    assert torch.allclose(flat, torch.full_like(flat, 0.25), atol=1e-12)


# -- model.unrolled.step_init --------------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["710", "1e300"])
def test_huge_unrolled_step_init_is_refused_naming_the_key(value):
    # was accepted, then math.log(math.expm1(step_init)) raised OverflowError: math range error as the network was built
    text = _refused(f"model.unrolled.step_init={value}", "model.unrolled.step_init")
    assert f"got {float(value):g}" in text


def test_largest_unrolled_step_init_starts_at_that_step():
    # closed form: the stages' step is softplus(θ) = log(1 + e^θ), which must give back step_init at the bound
    from hsicam.models.system import CameraSystem

    cfg = load_config("tiny", ["model.kind=unrolled", f"model.unrolled.step_init={MAX_STEP_INIT}"])
    net = CameraSystem.from_config(cfg).net
    steps = torch.nn.functional.softplus(net.step_logits.detach().double())
    assert torch.allclose(steps, torch.full_like(steps, MAX_STEP_INIT), rtol=1e-6)


# -- odd windows of the networks (brightness, demosaic, stage PSF cut) ------------------------------------------------
WINDOW_KEYS = ["model.mosaic.brightness_window", "model.mosaic.demosaic_window", "model.unrolled.brightness_window",
               "model.unrolled.demosaic_window", "model.unrolled.stage_kernel_px",
               "model.unrolled.mosaic.brightness_window", "model.unrolled.mosaic.demosaic_window"]


@pytest.mark.parametrize("key", WINDOW_KEYS)
@pytest.mark.parametrize("value", [2**31 + 1, 2**70 + 1])
def test_window_wider_than_any_sensor_is_refused_naming_the_key(key, value):
    # model.mosaic.brightness_window=2**70+1 was accepted; the forward then raised TypeError avg_pool2d(): argument
    # 'padding' failed to unpack ... Overflow when unpacking long long (2**31+1: RuntimeError ... without overflow)
    text = _refused(f"{key}={value}", key)
    assert f"got {value}" in text


def test_widest_window_box_mean_is_the_image_sum_over_its_area():
    # closed form: a box of W ≥ 2·side − 1 px covers the whole image at every pixel; zeros outside, so the mean is
    # the image's sum over W²
    from hsicam.models.demosaic import box_mean

    cfg = load_config("tiny", [f"model.mosaic.brightness_window={MAX_WINDOW_PX}"])
    w = cfg.model.mosaic.brightness_window
    x = torch.rand(1, 1, 12, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.allclose(box_mean(x, w), torch.full_like(x, float(x.sum()) / w**2), rtol=1e-9)


# -- the sweep: every leaf key against a small hostile battery ----------------------------------------------------
def _leaf_keys(cls, where: str = "") -> list[str]:
    """Every leaf key of the config tree, walking the dataclasses' fields (an optional section, e.g. baselines.choi,
    by its dataclass)."""
    import dataclasses
    import types
    import typing

    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp, key = hints[f.name], f"{where}.{f.name}" if where else f.name
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            tp = args[0] if len(args) == 1 else tp
        out += _leaf_keys(tp, key) if dataclasses.is_dataclass(tp) else [key]
    return out


def _config_class():
    from hsicam.config import Config

    return Config


LEAF_KEYS = _leaf_keys(_config_class())


def test_the_sweep_walks_every_section():
    assert len(LEAF_KEYS) > 150 and len(set(LEAF_KEYS)) == len(LEAF_KEYS)
    assert {"baselines.choi.rho", "data.npy_bands.step_nm", "model.unrolled.mosaic.factor", "train.freeze"} <= set(LEAF_KEYS)


@pytest.mark.parametrize("key", LEAF_KEYS)
def test_hostile_values_are_a_config_error_naming_the_key_or_accepted(key):
    from hsicam.errors import InputError

    for value in ("abc", ".nan", "-1", "[1, 2]"):
        try:
            load_config("tiny", [f"{key}={value}"])
        except (ConfigError, InputError) as exc:
            assert re.search(rf"(?<![\w.]){re.escape(key)}(?![\w])", str(exc)), (key, value, str(exc))
        # any other exception fails the test: a traceback for the user


def test_a_band_grid_refusal_names_the_keys_and_a_huge_count_in_a_few_digits():
    """`bands.start_nm=5` said "bands: (720.0 - 5.0) is not a multiple of the step 50.0" (the keys unnamed);
    `bands.stop_nm=1e300` printed a band count of ~300 digits."""
    with pytest.raises(ConfigError) as exc:
        load_config("tiny", ["bands.start_nm=5"])
    assert str(exc.value) == ("bands.start_nm, bands.stop_nm, bands.step_nm (5, 720, 50): (720.0 - 5.0) is not a "
                              "multiple of the step 50.0")
    with pytest.raises(ConfigError) as exc:
        load_config("tiny", ["bands.stop_nm=1e300"])
    assert str(exc.value) == ("bands.start_nm, bands.stop_nm, bands.step_nm (420, 1e+300, 50): 420..1e+300 nm in "
                              "steps of 50 nm gives 2e+298 bands, more than 10000; check the step (in nm)")
    with pytest.raises(ConfigError, match=r"^data\.npy_bands\.start_nm, data\.npy_bands\.stop_nm, "):
        load_config("tiny", ["data.npy_bands.start_nm=5"])
