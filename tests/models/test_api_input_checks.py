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
