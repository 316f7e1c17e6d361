"""Tiled reconstruction equals the whole-image pass. (The RDN's own receptive radius, initialisation and demosaic
input are in models/test_rdn.py, the sensor image reader in data/test_data_formats.py, the CFA window in
optics/test_sensor.py.)"""

from __future__ import annotations

import pytest
import torch

from hsicam.config import load_config
from hsicam.models.context import conv_receptive_radius as receptive_radius
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import InputError
from hsicam.models import RDN, CameraSystem
from rdn_systems import demosaic_input_system


def _untrained_but_spatial(net: RDN) -> None:
    """An untrained RDN returns its 1×1 tentative image (zero output conv, only the sensor channel
    weighted): give both convs random weights so the result depends on the neighbourhood and on
    every input channel, as a trained network's does."""
    g = torch.Generator().manual_seed(5)
    torch.nn.init.normal_(net.output.weight, std=0.1, generator=g)
    torch.nn.init.normal_(net.tentative.weight, std=0.5, generator=g)


def test_tiles_are_seamless():
    """In float64 the tiled pass with the declared halo is the whole-image pass to rounding, and one
    pixel less of halo shows (a float32 tolerance of 1e-5 let a halo one or two pixels short pass)."""
    torch.manual_seed(0)
    net = RDN(bands=4, blocks=2, features=8, growth=4, layers_per_block=2).eval().double()
    _untrained_but_spatial(net)
    img = torch.rand(1, 1, 97, 83, dtype=torch.float64)
    with torch.no_grad():
        whole = net(img)
    halo = receptive_radius(net)
    tiled = reconstruct_tiled(net, img, tile_px=32, halo_px=halo)
    assert tiled.dtype == torch.float64
    torch.testing.assert_close(tiled, whole, rtol=0, atol=1e-12)
    # without enough context the seams show, by a pixel of halo: the test above can fail
    short = reconstruct_tiled(net, img, tile_px=32, halo_px=halo - 1)
    assert (short - whole).abs().max() > 1e-9
    bad = reconstruct_tiled(net, img, tile_px=32, halo_px=0)
    assert (bad - whole).abs().max() > 1e-3


def test_demosaic_input_tiles_are_seamless(tiny_config):
    """Each tile must see the CFA phase of its own position and enough context, or seams show."""
    model = demosaic_input_system(tiny_config).double()
    _untrained_but_spatial(model.net)
    img = torch.rand(1, 1, 61, 47, dtype=torch.float64)
    with torch.no_grad():
        whole = model.reconstruct(img)
    assert model.context_px == receptive_radius(model.net) + model.net.window // 2
    tiled = reconstruct_tiled(model.reconstruct, img, tile_px=16, halo_px=model.context_px)
    torch.testing.assert_close(tiled, whole, rtol=0, atol=1e-12)  # float64: equal to rounding
    # one pixel less of context shows: the declared halo is the least that works
    short = reconstruct_tiled(model.reconstruct, img, tile_px=16, halo_px=model.context_px - 1)
    assert (short - whole).abs().max() > 1e-9
    # fed the CFA at the wrong phase per tile, it differs: the check above can fail
    wrong = reconstruct_tiled(lambda w: model.reconstruct(w), img, tile_px=16, halo_px=model.context_px)
    assert (wrong - whole).abs().max() > 1e-4


def test_demosaic_input_needs_a_camera_with_a_code():
    from hsicam.errors import ConfigError
    from hsicam.models import CameraSystem

    with pytest.raises(ConfigError, match="demosaic_input"):
        CameraSystem.from_config(load_config("dd_cassi_rdn", ["model.rdn.demosaic_input=true",
                                                              "model.rdn.backprojection_input=false"]))
    # the quick preset (demosaic input on) switched to CASSI the way experiments and benchmarks do it
    from hsicam.engine.experiments import CASSI_RDN_OVERRIDES

    with pytest.raises(ConfigError, match="demosaic_input=false"):
        CameraSystem.from_config(load_config("quick", ["camera.kind=dd_cassi", "model.kind=rdn",
                                                       "model.consistency.iterations=0"]))
    cassi = CameraSystem.from_config(load_config("quick", list(CASSI_RDN_OVERRIDES)))
    assert cassi.camera.kind == "dd_cassi" and cassi.net.tentative.in_channels == 1


def test_reconstructor_builds_the_operator_once_for_all_tiles(tiny_config):
    """Tiled inference with ``CameraSystem.reconstructor()`` computes the camera's PSF stack once
    (the network given the camera would snapshot it per tile) and gives the same cube."""
    torch.manual_seed(0)
    model = CameraSystem.from_config(tiny_config("model.kind=unrolled", "model.unrolled.stages=1",
                                                 "model.unrolled.prior_features=8", "model.unrolled.prior_blocks=1",
                                                 "model.unrolled.prior_scale=2")).eval()
    calls = []
    real = model.camera.snapshot

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    model.camera.snapshot = counting
    sensor = torch.rand(1, 1, 40, 36)
    halo = model.context_px
    per_call = reconstruct_tiled(model.reconstruct, sensor, tile_px=16, halo_px=halo)
    n_tiles = len(calls)
    assert n_tiles == 9
    calls.clear()
    once = reconstruct_tiled(model.reconstructor(), sensor, tile_px=16, halo_px=halo)
    assert len(calls) == 1
    torch.testing.assert_close(once, per_call)


def test_tiling_refuses_a_camera_whose_scene_grid_is_not_the_sensors():
    """SD-CASSI maps an (h, w + span) cube onto an (h, w) sensor: its tiles cannot be stitched on the
    sensor grid, so tiling is one clear error, and one whole tile still works."""
    torch.manual_seed(0)
    cfg = load_config("tiny", ["camera.kind=sd_cassi", "model.kind=unrolled", "model.unrolled.stages=1",
                               "model.unrolled.prior_features=8", "model.unrolled.prior_blocks=1",
                               "model.unrolled.prior_scale=2"])
    model = CameraSystem.from_config(cfg).eval()
    sensor = torch.rand(1, 1, 30, 40)
    whole = reconstruct_tiled(model.reconstructor(), sensor, tile_px=64)
    assert whole.shape[-2:] == model.camera.scene_size((30, 40)) != (30, 40)
    with pytest.raises(InputError, match="cannot be tiled"):
        reconstruct_tiled(model.reconstructor(), sensor, tile_px=16, halo_px=4)


def test_default_tile_is_four_halos_within_512_and_1024():
    """The tiles' halos cost at most (1 + 2·¼)² of their own pixels by default, where the window stays small."""
    from hsicam.engine.inference import default_tile_px

    assert default_tile_px(0) == 512 and default_tile_px(128) == 512
    assert default_tile_px(230) == 920  # the quick demo camera's context with its steps
    assert default_tile_px(566) == 1024  # an untrained quick camera's: windows stay near 2000 px


def test_tiles_are_default_tile_px_of_the_declared_context_unless_told():
    """reconstruct_tiled (under `reconstruct` and `evaluate`) cuts 4-halo tiles by default: a 1700 px wide
    image with a 200 px context is 3 tiles of 800 px across, 4 of 512 when told."""
    from hsicam.engine.inference import default_tile_px

    calls = []

    def fn(window, origin=(0, 0)):
        calls.append(origin)
        return window.expand(-1, 2, -1, -1)

    fn.context_px = 200
    sensor = torch.rand(1, 1, 10, 1700)
    out = reconstruct_tiled(fn, sensor)
    assert default_tile_px(200) == 800 and len(calls) == 3
    torch.testing.assert_close(out, sensor.expand(-1, 2, -1, -1))
    calls.clear()
    reconstruct_tiled(fn, sensor, tile_px=512)
    assert len(calls) == 4


def test_evaluate_passes_its_tile_on(tiny_config, monkeypatch):
    """`evaluate_method` hands its tile_px (None: reconstruct_tiled's default) to the tiling; `hsicam evaluate
    --tile` below 16 px is one clear error."""
    import hsicam.engine.evaluate as ev
    from cli_helpers import error_line, run_cli_in_process
    from hsicam.engine.evaluate import Method, evaluate_method

    seen = []
    real = ev.reconstruct_tiled

    def spy(fn, sensor, tile_px=None, halo_px=None, progress=False):
        seen.append(tile_px)
        return real(fn, sensor, tile_px, halo_px, progress)

    monkeypatch.setattr(ev, "reconstruct_tiled", spy)
    model = CameraSystem.from_config(tiny_config()).eval()
    method = Method("net", model.camera, model.reconstructor(), model.target, model=model)
    scene = torch.rand(1, len(model.bands), 60, 60)
    evaluate_method(method, scene, ["a"], keep_arrays=False)
    evaluate_method(method, scene, ["a"], keep_arrays=False, tile_px=16)
    assert seen == [None, 16]
    line = error_line(run_cli_in_process("evaluate", "--config", "tiny", "--out", "never", "--tile", "8"))
    assert "--tile must be at least 16 px" in line


def _float64_camera_and_nets(kind: str):
    """The tiny camera of ``kind`` in float64, its frozen operator, and small random-weight (every path
    on) unrolled and mosaic networks in float64 (prior scale 2: a cell reaches 1 px past its pixel)."""
    import dataclasses

    from hsicam.cameras import build_camera
    from hsicam.config import MosaicConfig, UnrolledConfig
    from hsicam.models.mosaic import build_mosaic
    from hsicam.models.unrolled import build_unrolled

    torch.manual_seed(0)
    cam = build_camera(load_config("tiny", [f"camera.kind={kind}"])).double()
    op = cam.snapshot(nominal=True)
    small = UnrolledConfig(stages=1, prior_features=6, prior_blocks=1, prior_scale=2)
    nets = {"unrolled": build_unrolled(small, cam)}
    if kind == "dd_cassi":  # (the DOE camera's AᵀA reach, 20 px a stage, would need a larger image)
        nets["unrolled-2"] = build_unrolled(dataclasses.replace(small, stages=2), cam)
    if kind == "doe":
        nets["unrolled-brightness"] = build_unrolled(dataclasses.replace(small, brightness_window=5), cam)
        mosaic = MosaicConfig(features=6, blocks=1, head_features=4, head_layers=2)
        nets["mosaic"] = build_mosaic(mosaic, cam)
        nets["mosaic-mid"] = build_mosaic(dataclasses.replace(mosaic, detail_features=2, factor=6, mid_features=4,
                                                              mid_blocks=1), cam)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for net in nets.values():
            for p in net.parameters():
                p.add_(0.3 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return op, {name: net.double().eval() for name, net in nets.items()}


@pytest.mark.parametrize("kind", ["doe", "dd_cassi"])
def test_unrolled_and_mosaic_tiles_are_seamless_in_float64_with_exactly_the_declared_context(kind):
    """As for the RDN above: in float64 the tiled pass with halo = context_px is the whole-image pass to
    rounding, and one pixel less of halo shows. The tiles are 23 px, odd, so that tiles start at either
    phase of the priors' 2×2 cells (a cell reaches scale − 1 px past the pixel at its far corner, a term
    of the prior's reach that a float32 tolerance of 1e-5 and cell-aligned tiles let drop unnoticed).
    Two stages: context_px adds each stage's worst case, but a second prior starts from a cell-aligned
    pixel, so its scale − 1 px are spare there; only the first part of the check applies."""
    op, nets = _float64_camera_and_nets(kind)
    y = torch.rand(1, 1, 75, 71, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for name, net in nets.items():
        run = lambda s, origin=(0, 0): net(s, op, origin)  # noqa: E731
        ctx = net.context_px
        with torch.no_grad():
            whole = net(y, op)
        assert whole.dtype == torch.float64 and 0 < ctx < 35, (name, ctx)  # real tiles: kept centres beside halos
        tiled = reconstruct_tiled(run, y, tile_px=23, halo_px=ctx)
        assert tiled.dtype == torch.float64
        torch.testing.assert_close(tiled, whole, rtol=0, atol=1e-12, msg=lambda m: f"{name}: {m}")
        if name != "unrolled-2":
            short = reconstruct_tiled(run, y, tile_px=23, halo_px=ctx - 1)
            assert (short - whole).abs().max() > 1e-9, name  # the declared halo is the least that works


def test_tiled_pixels_is_what_the_windows_add_up_to():
    """:func:`tiled_pixels` (the tile warning's count) against the windows reconstruct_tiled hands a reconstruction."""
    from hsicam.engine.inference import reconstruct_tiled, tiled_pixels

    for shape, tile, halo in (((48, 48), 16, 18), ((1000, 700), 300, 400), ((37, 91), 10, 3), ((20, 20), 32, 5),
                              ((64, 65), 64, 0)):
        seen = []

        def recording(window, origin=(0, 0)):
            seen.append(window.shape[-2] * window.shape[-1])
            return window.expand(1, 1, *window.shape[-2:])

        reconstruct_tiled(recording, torch.zeros(1, 1, *shape), tile, halo)
        assert tiled_pixels(shape, tile, halo) == sum(seen), (shape, tile, halo)
