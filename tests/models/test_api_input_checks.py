"""The Python API refuses bad input in one line (probe 24, findings 6 and 9): sensor images given to
``CameraSystem.reconstruct`` / ``reconstructor()`` / ``reconstruct_tiled`` and scenes given to a
camera, named with what was received and what is expected; good input of any floating dtype or
layout gives the float32 result; ``reconstruct_tiled`` takes the model's context as its halo."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from hsicam.config import load_config
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import InputError
from hsicam.models import CameraSystem


@pytest.fixture(scope="module")
def system() -> CameraSystem:
    """The tiny DOE system (7 bands, 21-px kernel, 3×3 CFA) with one consistency step, its network
    given random output weights so that every pixel depends on its neighbourhood (tiles show seams
    without enough halo), in eval mode."""
    torch.manual_seed(0)
    model = CameraSystem.from_config(load_config("tiny", ["model.consistency.iterations=1"])).eval()
    g = torch.Generator().manual_seed(5)
    torch.nn.init.normal_(model.net.output.weight, std=0.1, generator=g)
    torch.nn.init.normal_(model.net.tentative.weight, std=0.5, generator=g)
    return model


def _sensor(h: int = 24, w: int = 24) -> torch.Tensor:
    return torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(1))


def test_non_finite_sensor_is_refused_with_its_count(system):
    s = _sensor()
    s[0, 0, 3, 4], s[0, 0, 10, 11] = float("nan"), float("inf")
    msg = re.escape("sensor contains 2 NaN or Inf value(s) of 576")
    with torch.no_grad():
        for fn in (system.reconstruct, system.reconstructor()):
            with pytest.raises(InputError, match=msg):
                fn(s)
        with pytest.raises(InputError, match=msg):
            reconstruct_tiled(system.reconstructor(), s, tile_px=8)


def test_sensor_of_any_floating_dtype_or_layout_gives_the_float32_cube_and_integers_are_refused(system):
    s = _sensor(20, 22)
    with torch.no_grad():
        want = system.reconstruct(s)
        torch.testing.assert_close(system.reconstruct(s.double()), want, rtol=1e-5, atol=1e-6)
        wide = torch.rand(1, 1, 20, 44)
        wide[..., ::2] = s
        assert not wide[..., ::2].is_contiguous()
        torch.testing.assert_close(system.reconstruct(wide[..., ::2]), want, rtol=0, atol=0)
        for bad in (s > 0.5, (s * 65535).long(), (s * 255).to(torch.uint8)):
            with pytest.raises(InputError, match=re.escape(f"sensor must be a floating-point tensor with values "
                                                           f"in [0, 1] (1 = full scale), got {bad.dtype}")):
                system.reconstruct(bad)


@pytest.mark.parametrize("shape, expected", [
    ((1, 24, 24), "sensor must be (B, 1, H, W), got shape (1, 24, 24)"),
    ((24, 24), "sensor must be (B, 1, H, W), got shape (24, 24)"),
    ((1, 2, 24, 24), "sensor must be (B, 1, H, W), got shape (1, 2, 24, 24)"),
    ((0, 1, 24, 24), "sensor of shape (0, 1, 24, 24) is empty: it needs B, H, W >= 1"),
    ((1, 1, 0, 5), "sensor of shape (1, 1, 0, 5) is empty: it needs B, H, W >= 1"),
])
def test_wrong_sensor_shapes_are_one_line_errors(system, shape, expected):
    with torch.no_grad(), pytest.raises(InputError, match="^" + re.escape(expected) + "$"):
        system.reconstruct(torch.rand(shape))


def test_sensor_on_another_device_is_refused(system):
    with torch.no_grad(), pytest.raises(InputError, match=re.escape(
            "sensor is on meta, the CameraSystem on cpu: move one of them (.to('cpu'))")):
        system.reconstruct(_sensor().to("meta"))


def test_scene_checks_of_the_camera(system):
    cam = system.camera  # eval mode: a user's call
    scene = torch.rand(1, 7, 44, 44, generator=torch.Generator().manual_seed(2))
    bad = scene.clone()
    bad[0, 2, 5, 5] = float("inf")
    n = bad.numel()
    with torch.no_grad():
        with pytest.raises(InputError, match=re.escape(f"scene contains 1 NaN or Inf value(s) of {n}")):
            cam.capture(bad)  # the user's entry point (A itself is not scanned: solvers call it every iteration)
        with pytest.raises(InputError, match=re.escape(f"my.h5 contains 1 NaN or Inf value(s) of {n}")):
            cam.capture(bad, source="my.h5")
        cases = [
            ((scene * 100).long(), "scene must be a floating-point tensor with values in [0, 1] (reflectance-like), "
                                   "got torch.int64"),
            (scene.half(), "scene is torch.float16 on the CPU: the DOECamera's FFT convolution needs float32 or "
                           "float64 there (x.float())"),
            (scene.bfloat16(), "scene is torch.bfloat16 on the CPU: the DOECamera's FFT convolution needs float32 or "
                               "float64 there (x.float())"),
            (scene[:0], "scene of shape (0, 7, 44, 44) is an empty batch: it needs B >= 1"),
            (scene.to("meta"), "scene is on meta, the DOECamera on cpu: move one of them (.to('cpu'))"),
        ]
        for x, expected in cases:
            with pytest.raises(InputError, match="^" + re.escape(expected) + "$"):
                cam(x)
        with pytest.raises(InputError, match=re.escape("sensor image of shape (0, 1, 24, 24) is empty")):
            cam.A_adjoint(torch.rand(0, 1, 24, 24))
        # float64 images as float32 does; A itself does not scan the values (a solver's inner loop)
        torch.testing.assert_close(cam.A(scene.double()).float(), cam.A(scene), rtol=1e-5, atol=1e-6)
        assert cam.A(bad).isnan().any()


def test_target_refuses_a_scene_not_on_the_band_axis(system):
    """The truth crop of a bands-last cube was a (1, 28, 0, ...) slice of the wrong axis, silently; now an
    InputError naming the permute, while a (B, C, H, W) scene gives the centre crop the sensor sees."""
    scene = torch.rand(1, 7, 44, 44, generator=torch.Generator().manual_seed(2))
    r = system.camera.margin // 2
    torch.testing.assert_close(system.target(scene), scene[..., r:44 - r, r:44 - r], rtol=0, atol=0)
    with torch.no_grad():
        assert system.target(scene).shape[-2:] == system.camera(scene).shape[-2:]
    expected = (f"scene has 44 bands but the camera has 7 ({system.camera.bands!r}); its last axis has the camera's "
                "bands: a (B, H, W, C) cube is x.permute(0, 3, 1, 2)")
    with pytest.raises(InputError, match="^" + re.escape(expected) + "$"):
        system.target(scene.permute(0, 2, 3, 1))
    with pytest.raises(InputError, match=re.escape("got shape (7, 44, 44)")):
        system.target(scene[0])


def test_target_refuses_a_numpy_scene_in_one_line(system):
    """A NumPy scene reached ``scene.dim()``: AttributeError "'numpy.ndarray' object has no attribute 'dim'" (before
    the layout check, the crop of the array, silently); now the InputError its docstring promises, as
    Camera.check_scene says it."""
    expected = "scene must be a torch.Tensor (B, C, H, W), got ndarray: torch.from_numpy(x)"
    with pytest.raises(InputError, match="^" + re.escape(expected) + "$"):
        system.target(np.zeros((1, 7, 44, 44), dtype=np.float32))


def test_tiled_reconstruction_takes_the_models_context_as_its_default_halo(system):
    sensor = _sensor(53, 47)
    fn = system.reconstructor()
    assert fn.context_px == system.context_px > system.net.context_px  # the step's reach included
    with torch.no_grad():
        whole = system.reconstruct(sensor)
    for rec in (fn, system.reconstruct):
        torch.testing.assert_close(reconstruct_tiled(rec, sensor, tile_px=16), whole, rtol=1e-5, atol=1e-5)
    # a function that declares no context: the halo is needed once the image is tiled
    plain = lambda s, origin=(0, 0): fn(s, origin)  # noqa: E731
    with pytest.raises(InputError, match=r"^halo_px is needed: function declares no context_px, and the 53×47 px "
                                         r"image is cut into 16 px tiles"):
        reconstruct_tiled(plain, sensor, tile_px=16)
    torch.testing.assert_close(reconstruct_tiled(plain, sensor, tile_px=64), whole, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kwargs, expected", [
    ({"tile_px": 0}, "tile_px must be an int >= 1, got 0"),
    ({"tile_px": -5}, "tile_px must be an int >= 1, got -5"),
    ({"tile_px": 2.5}, "tile_px must be an int >= 1, got 2.5"),
    ({"tile_px": True}, "tile_px must be an int >= 1, got True"),
    ({"tile_px": 16, "halo_px": -3}, "halo_px must be an int >= 0, got -3"),
    ({"tile_px": 16, "halo_px": 1.5}, "halo_px must be an int >= 0, got 1.5"),
])
def test_tiled_reconstruction_refuses_bad_tile_and_halo(system, kwargs, expected):
    with pytest.raises(InputError, match="^" + re.escape(expected) + "$"):
        reconstruct_tiled(system.reconstructor(), _sensor(40, 40), **kwargs)


def test_tiled_reconstruction_refuses_bad_sensors(system):
    fn = system.reconstructor()
    with pytest.raises(InputError, match=re.escape("sensor image must be (1, 1, H, W), got (1, 40, 40)")):
        reconstruct_tiled(fn, _sensor(40, 40)[0], tile_px=16)
    with pytest.raises(InputError, match=re.escape("sensor must be a floating-point tensor with values in [0, 1] "
                                                   "(1 = full scale), got torch.bool")):
        reconstruct_tiled(fn, _sensor(40, 40) > 0.5, tile_px=16)


@pytest.mark.parametrize("device, problem", [
    ("meta", "hsicam runs on cpu, cuda or mps"),
    ("gpu", "unknown device; use cpu, cuda, cuda:N or mps"),
    ("", "unknown device; use cpu, cuda, cuda:N or mps"),
])
def test_load_run_refuses_a_device_as_the_cli_does(device, problem, tmp_path):
    """load_run(device="meta") returned a model whose reconstructions were uninitialised memory (probe
    24, finding 5); the device is checked first (no run is needed here), in the words of ``--device``."""
    from hsicam.runs.folder import load_run

    with pytest.raises(InputError, match="^" + re.escape(f"load_run: device {device!r}: {problem}") + "$"):
        load_run(tmp_path / "no-run", device=device)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a machine with CUDA")
def test_load_run_names_a_missing_cuda_device(tmp_path):
    from hsicam.runs.folder import load_run

    with pytest.raises(InputError, match=re.escape("load_run: device 'cuda': no CUDA device is available here")):
        load_run(tmp_path / "no-run", device="cuda")


def test_a_cassi_camera_images_half_precision_scenes_on_the_cpu():
    """No FFT in CASSI's forward model: float16/bfloat16 scenes image as before (probe 25, F5: the
    DOE camera's rule had been applied to every camera)."""
    for kind in ("dd_cassi", "sd_cassi"):
        from hsicam.cameras import build_camera

        cam = build_camera(load_config("tiny", [f"camera.kind={kind}"])).eval()  # the camera alone (no network)
        scene = torch.rand(1, 7, 32, 32, generator=torch.Generator().manual_seed(3))
        with torch.no_grad():
            want = cam.A(scene)
            for dtype, tol in ((torch.float16, 2e-3), (torch.bfloat16, 2e-2)):
                torch.testing.assert_close(cam.A(scene.to(dtype)).float(), want, rtol=tol, atol=tol)


def test_a_dark_area_below_zero_gives_a_finite_cube_in_proportion():
    """A capture whose black level was set a little high has areas whose local mean is below 0. The mosaic network
    divides by the local brightness box(g) + eps, which reached 0 there: g / b was infinite and the whole cube NaN.
    The brightness is now taken at 0 below 0: the cube stays finite and the dark area stays dark."""
    cfg = load_config("tiny", ["model.kind=mosaic", "model.mosaic.features=8", "model.mosaic.blocks=1",
                               "model.mosaic.brightness_window=5"])
    torch.manual_seed(0)
    s = CameraSystem.from_config(cfg).eval()
    y = torch.rand(1, 1, 40, 40, generator=torch.Generator().manual_seed(1)) * 0.5
    y[..., 10:20, 10:20] = -cfg.model.mosaic.brightness_eps
    with torch.no_grad():
        out = s.reconstruct(y)
    assert out.isfinite().all()
    assert out[..., 13:17, 13:17].abs().max() < 0.05 * out[..., 25:, 25:].abs().max()


def test_train_mode_reconstructs_tiled_as_whole():
    """In train mode reconstruct is the network alone (the steps are inference's): tiled reconstruction of the same
    reconstructor is too, where it ran the Landweber steps (a module fresh from from_config is in train mode)."""
    cfg = load_config("tiny", ["model.consistency.iterations=2", "model.consistency.kind=landweber"])
    torch.manual_seed(0)
    s = CameraSystem.from_config(cfg)
    assert s.training
    y = torch.rand(1, 1, 40, 40, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        f = s.reconstructor()
        whole = f(y)
        assert torch.equal(whole, s.network(y))
        torch.testing.assert_close(reconstruct_tiled(f, y), whole)
        torch.testing.assert_close(reconstruct_tiled(f, y, tile_px=16), whole, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("padding", ["reflect", "circular"])
def test_min_scene_size_of_a_padded_camera_is_a_scene_it_captures(padding):
    """A `same` camera's reflect or circular padding needs a scene of about half the kernel: min_scene_size said 3×3
    and capture's own refusal named 3×3 px, then the camera refused that scene."""
    cam = CameraSystem.from_config(load_config("tiny", ["camera.boundary=same", f"camera.padding={padding}"])).camera
    h, w = cam.min_scene_size()
    assert min(h, w) >= cam.margin // 2
    with torch.no_grad():
        cam.capture(torch.rand(1, len(cam.bands), h, w))
        with pytest.raises(InputError, match=rf"needs {h}×{w} px"):
            cam.capture(torch.rand(1, len(cam.bands), h - 1, w))


# ------------------------------------------------------------------------------------------------
# Session 70's hunt of the Python API (helper report): each of these was a deep error or a silent wrong result
# ------------------------------------------------------------------------------------------------
def test_target_refuses_a_scene_smaller_than_the_kernel_as_capture_does(system):
    """`target` of a scene smaller than the valid kernel returned an empty (…, 0, 0) crop, scored later as "SSIM
    needs images of at least 11×11 px, got 0×0"; it is the camera's own refusal now, word for word."""
    cam = system.camera
    small = torch.rand(1, len(system.bands), cam.margin, cam.margin + 5)
    with pytest.raises(InputError) as captured:
        cam(small)
    with pytest.raises(InputError) as targeted:
        system.target(small)
    assert str(targeted.value) == str(captured.value)
    ok = torch.rand(1, len(system.bands), cam.margin + 1, cam.margin + 1)
    assert system.target(ok).shape[-2:] == (1, 1)


@pytest.mark.parametrize("origin", [(1, 2, 3), None, 0, "00", (0.5, 0), (True, 0), [1]])
def test_a_bad_origin_is_one_clear_error(system, origin):
    """`reconstruct(y, origin=…)` took (1, 2, 3) as (1, 2) and failed deep in torch (roll, subscripts) for the rest."""
    msg = re.escape(f"origin must be a pair of ints (row, column): the sensor pixel of the window's top-left "
                    f"corner, got {origin!r}")
    with torch.no_grad():
        for call in (lambda: system.reconstruct(_sensor(), origin), lambda: system.network(_sensor(), origin),
                     lambda: system.landweber_steps(_sensor(), torch.zeros(1, len(system.bands), 24, 24), origin),
                     lambda: system.camera.sensor_code(6, 6, origin)):
            with pytest.raises(InputError, match=f"^{msg}$"):
                call()
        a = system.reconstruct(_sensor(), (np.int64(1), 2))  # numpy integers are integers
    torch.testing.assert_close(a, system.reconstruct(_sensor(), (1, 2)))
    with pytest.raises(InputError, match=r"^sensor window must be at least 1×1 px \(two ints\), got -1×8$"):
        system.camera.sensor_code(-1, 8)


def test_metrics_refuse_integer_tensors():
    """8-bit counts were scored on the peak-1 scale (PSNR −40 dB) without a word."""
    from hsicam.metrics import all_metrics, psnr_per_band

    counts = torch.full((1, 3, 16, 16), 200, dtype=torch.uint8)
    with pytest.raises(InputError, match=r"^estimate must be floating-point with values on the peak-1 scale .* got "
                                         r"torch.uint8: divide counts by their full scale first"):
        all_metrics(counts, counts.float() / 255)
    with pytest.raises(InputError, match=r"^truth must be floating-point .* got torch.bool"):
        psnr_per_band(torch.rand(3, 8, 8), torch.rand(3, 8, 8) > 0.5)


def test_a_string_of_overrides_is_refused_naming_it_not_its_first_character(tmp_path):
    from hsicam.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^overrides must be a sequence of 'key=value' strings \(a list or tuple\), "
                                          r"got the string 'train.epochs=2': pass \['train.epochs=2'\]$"):
        load_config("tiny", "train.epochs=2")
    assert load_config("tiny", ["train.epochs=2"]).train.epochs == 2


def test_a_network_of_ones_own_that_returns_the_wrong_bands_is_named(caplog):
    """A registered network returning the 1-band sensor was a "cube" of 1 band for a 7-band camera (scored, or
    failing deep in the loss); a declared parameter count other than the built one went unnoticed (the memory
    checks trust it)."""
    import logging

    from torch import nn

    from hsicam.models.registry import NETWORKS, register_network

    class Echo(nn.Module):
        context_px = 0

        def __init__(self):
            super().__init__()
            self.w = nn.Parameter(torch.ones(3))

        def forward(self, sensor, camera, origin=(0, 0)):
            return sensor * self.w[0]

    try:
        register_network("echo_s70", parameters=lambda cfg, camera: 5, sizes=("features",))(lambda cfg, camera: Echo())
        with caplog.at_level(logging.WARNING, logger="hsicam.models.registry"):
            model = CameraSystem.from_config(load_config("tiny", ["model.kind=echo_s70"])).eval()
        [msg] = [r.getMessage() for r in caplog.records]
        assert msg.startswith("model.kind=echo_s70 declares 5 parameters (its registered parameters function) but "
                              "builds 3"), msg
        with pytest.raises(InputError, match=re.escape(
                "the network (Echo) returned shape (1, 1, 24, 24) of torch.float32 for a sensor image of shape "
                f"(1, 1, 24, 24); a network returns a floating (B, C, H, W) cube of the camera's C = "
                f"{len(model.bands)} bands and 24×24 px")):
            with torch.no_grad():
                model.reconstruct(_sensor())
    finally:
        NETWORKS.pop("echo_s70", None)


@pytest.mark.parametrize("bad", ["nan_y", "nan_weight", "negative_weight", "empty_weights"])
def test_gap_tv_refuses_what_would_give_a_nan_cube_or_a_negative_weight(bad):
    from hsicam.cameras import build_camera
    from hsicam.solvers.gaptv import gap_tv

    torch.manual_seed(0)
    cam = build_camera(load_config("tiny", ["camera.kind=dd_cassi"])).double()
    y = cam.A(torch.rand(1, len(cam.bands), 20, 20, dtype=torch.float64))
    kw = {"iterations": 2}
    if bad == "nan_y":
        y[0, 0, 3, 3] = float("nan")
        match = r"^sensor image contains 1 NaN or Inf value\(s\) of 400$"
    else:
        kw["tv_weight"] = {"nan_weight": float("nan"), "negative_weight": -1.0, "empty_weights": []}[bad]
        match = r"^tv_weight must be a finite number >= 0 \(or a non-empty list of them\), got "
    with pytest.raises(InputError, match=match):
        gap_tv(cam, y, **kw)
    assert torch.isfinite(gap_tv(cam, y if bad != "nan_y" else y.nan_to_num(), iterations=2)).all()


def test_from_config_of_a_name_and_an_empty_cube_are_one_clear_error():
    from hsicam.data.cube import normalize_per_cube_max

    with pytest.raises(InputError, match=r"^CameraSystem.from_config takes a Config \(hsicam.config.load_config\('quick'\)\), "
                                         r"got str 'tiny'$"):
        CameraSystem.from_config("tiny")
    with pytest.raises(InputError, match=r"^cube: the cube of shape \(31, 0, 16\) is empty; cannot normalise by its maximum$"):
        normalize_per_cube_max(np.zeros((31, 0, 16)))


def test_dataset_generation_envi_types_and_residual_sizes_are_one_clear_error(tmp_path, system):
    """Wrong types given to generate_dataset failed in Python's or numpy's words (a float size: "'float' object
    cannot be interpreted as an integer"; bands as a string: "no attribute 'min_nm'"); an unknown ENVI data type was
    numpy's "not understood"; a residual of mismatched windows was torch's size error."""
    from hsicam.data.formats import write_envi
    from hsicam.data.synthetic import generate_dataset
    from hsicam.spectral import Bands

    for kwargs, text in (({"size": 32.5}, "size must be an int, got 32.5"),
                         ({"seed": -1}, "seed must be >= 0, got -1"),
                         ({"n": "2"}, "n must be an int, got '2'"),
                         ({"bands": "420-720"}, "bands must be a Bands")):
        args = {"n": 1, "size": 32, "seed": 0, **kwargs}
        with pytest.raises(InputError, match=f"^synthetic: {re.escape(text)}"):
            generate_dataset(tmp_path / "d", progress=False, **args)
    assert not (tmp_path / "d").exists()
    bands = Bands.paper()
    with pytest.raises(InputError, match=r"^write_envi: unknown data type 'int99' \(e.g. float32, int16, uint16\)$"):
        write_envi(tmp_path / "c.hdr", np.zeros((len(bands), 4, 4), np.float32), bands, dtype="int99")
    cam = system.camera
    x = torch.rand(1, len(system.bands), 40, 40)
    with pytest.raises(InputError, match=r"^the estimate images to \(1, 1, 20, 20\) px but the measurement is "
                                         r"\(1, 1, 19, 20\): not the same window$"):
        cam.relative_residual(x, torch.rand(1, 1, 19, 20))


@pytest.mark.parametrize("kind", ["doe", "sd_cassi"])
def test_a_network_of_ones_own_that_returns_the_wrong_size_is_named(kind):
    """A registered network returning a cube of the camera's bands at another size (here every other pixel) was scored
    on a misaligned crop or failed deep in a loss or a tile; now one error naming the network and the size the
    camera's window needs: the sensor's own (the DOE camera) or the scene behind SD-CASSI's dispersed measurement
    (W − D, what its built-in networks return)."""
    from torch import nn

    from hsicam.models.registry import NETWORKS, register_network

    class EveryOther(nn.Module):
        context_px = 0

        def __init__(self, bands):
            super().__init__()
            self.n = len(bands)
            self.w = nn.Parameter(torch.ones(1))

        def forward(self, sensor, camera, origin=(0, 0)):
            return (sensor * self.w).expand(-1, self.n, -1, -1)[..., ::2, ::2].contiguous()

    try:
        register_network("every_other_s71", parameters=lambda cfg, camera: 1, sizes=("features",))(
            lambda cfg, camera: EveryOther(camera.bands))
        model = CameraSystem.from_config(load_config("tiny", ["model.kind=every_other_s71", f"camera.kind={kind}"])).eval()
        y = torch.rand(1, 1, 24, 40)
        hw = (24, 40) if kind == "doe" else (24, 40 - model.camera.span)
        assert model.cube_size((24, 40)) == hw
        with pytest.raises(InputError, match=re.escape(
                f"the network (EveryOther) returned shape (1, {len(model.bands)}, 12, 20) of torch.float32 for a sensor "
                f"image of shape (1, 1, 24, 40); a network returns a floating (B, C, H, W) cube of the camera's C = "
                f"{len(model.bands)} bands and {hw[0]}×{hw[1]} px")):
            with torch.no_grad():
                model.network(y)
    finally:
        NETWORKS.pop("every_other_s71", None)


def test_the_adjoint_and_the_snapshot_refuse_what_A_refuses():
    """A Python API hunt (session 72): the DOE camera's Aᵀ took a half-precision, other-device or (reflect/circular
    padding) too small image to a deep torch error, its snapshot a NumPy array or an int tensor; each is now the
    refusal ``A`` gives a scene, worded for a sensor image. Good input is unchanged (the adjoint identity holds)."""
    from hsicam.cameras import DOECamera

    cam = DOECamera.from_config(load_config("tiny", ["camera.boundary=same", "camera.padding=reflect"]))
    g = torch.rand(1, 1, 30, 30, generator=torch.Generator().manual_seed(2))
    cases = [
        (g.half(), "sensor image is torch.float16 on the CPU: the DOECamera's FFT convolution needs float32 or float64 "
                   "there (y.float())"),
        (g.bfloat16(), "sensor image is torch.bfloat16 on the CPU: the DOECamera's FFT convolution needs float32 or "
                       "float64 there (y.float())"),
        (g.to("meta"), "sensor image is on meta, the DOECamera on cpu: move one of them (.to('cpu'))"),
        (g[..., :9, :9], "sensor image of 9×9 px is too small for reflect padding by 10 px: it needs at least 11 px per "
                         "side"),
    ]
    for y, said in cases:
        with pytest.raises(InputError) as exc:
            cam.A_adjoint(y)
        assert str(exc.value) == said
    with pytest.raises(InputError, match="too small for reflect padding by 10 px"):
        cam.A(torch.rand(1, 7, 9, 9))  # what A says of the scene of that size
    circular = DOECamera.from_config(load_config("tiny", ["camera.boundary=same", "camera.padding=circular"]))
    with pytest.raises(InputError, match="too small for circular padding by 10 px: it needs at least 10 px"):
        circular.A_adjoint(g[..., :9, :20])
    assert circular.A_adjoint(g[..., :10, :10]).shape == (1, 7, 10, 10)
    x = torch.rand(1, 7, 30, 30, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    c64 = cam.double()
    with torch.no_grad():  # (the camera's parameters need no graph here)
        lhs, rhs = (c64.A(x) * g.double()).sum(), (x * c64.A_adjoint(g.double())).sum()
    assert abs(float(lhs - rhs)) <= 1e-12 * abs(float(lhs))
    snap = DOECamera.from_config(load_config("tiny")).snapshot()
    for bad, what in ((np.zeros((1, 7, 16, 16)), "cube must be a torch.Tensor (B, 7, H, W), got ndarray"),
                      (torch.zeros(1, 7, 16, 16, dtype=torch.int64), "cube is torch.int64"),
                      (torch.zeros(1, 7, 16, 16).half(), "cube is torch.float16"),
                      (torch.zeros(1, 6, 16, 16), "cube must be (B, 7, H, W), got shape (1, 6, 16, 16)"),
                      (torch.zeros(1, 7, 16, 16, device="meta"), "cube is on meta, the camera's PSFs on cpu")):
        with pytest.raises(InputError, match="^" + re.escape(what)):
            snap.A(bad)
    with pytest.raises(InputError, match=re.escape("sensor image is torch.float16")):
        snap.A_adjoint(torch.zeros(1, 1, 16, 16).half())
    with pytest.raises(InputError, match=re.escape("sensor image must be (B, 1, H, W), got shape (1, 2, 16, 16)")):
        snap.A_adjoint(torch.zeros(1, 2, 16, 16))


def test_a_fixed_psf_stack_is_an_intensity_kept_in_its_precision():
    """``FixedPSFCamera.from_camera`` refused a wrong shape with a bare ValueError, took negative or NaN PSFs (a
    negative sensor image followed) and cut float64 PSFs to float32 (a float64 camera then imaged 5e-8 off them)."""
    import torch.nn.functional as F

    from hsicam.cameras import DOECamera
    from hsicam.cameras.measured import FixedPSFCamera

    cam = DOECamera.from_config(load_config("tiny"))
    c, k = len(cam.bands), cam.kernel_px
    psf = torch.rand(c, k, k, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) / (k * k)
    fixed = FixedPSFCamera.from_camera(cam, psf).double()
    assert torch.equal(fixed.psf(), psf)
    x = torch.rand(1, c, 28, 28, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    # the image of band b is the scene's band b correlated with the PSF flipped (a convolution), times the CFA
    want = sum(F.conv2d(x[:, b:b + 1], psf[b].flip(-2, -1)[None, None]) * fixed.cfa.pattern(8, 8)[b].double()
               for b in range(c))
    torch.testing.assert_close(fixed.A(x), want, rtol=1e-12, atol=1e-15)
    assert FixedPSFCamera.from_camera(cam, psf.float()).fixed_psf.dtype == torch.float32
    for bad, said in ((psf - psf.mean(), "PSF stack must hold finite, non-negative numbers"),
                      (psf.clone().fill_(float("nan")), "PSF stack must hold finite, non-negative numbers"),
                      (torch.ones(c, k, k, dtype=torch.int64), "got torch.int64"),
                      (psf[:-1], f"PSF stack must be ({c}, {k}, {k}) for this camera, got ({c - 1}, {k}, {k})")):
        with pytest.raises(InputError, match=re.escape(said)):
            FixedPSFCamera.from_camera(cam, bad)


def test_metrics_refuse_an_empty_image_and_two_devices():
    from hsicam.metrics import all_metrics, psnr_per_band, sam_degrees, ssim

    x = torch.rand(1, 4, 16, 16)
    for a in (x[..., :0, :], x[:, :0], x[..., :, :0]):
        for metric in (psnr_per_band, sam_degrees, ssim, all_metrics):
            with pytest.raises(InputError, match="nothing to score: shape .* has no bands or no pixels"):
                metric(a, a.clone())
    with pytest.raises(InputError, match=re.escape("the estimate is on cpu, the truth on meta: move one of them")):
        psnr_per_band(x, x.to("meta"))
    assert psnr_per_band(x[:0], x[:0]).shape == (0,)  # an empty batch: no scores, as before
