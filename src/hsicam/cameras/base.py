"""The interface shared by all cameras, so solvers, training and evaluation treat them alike."""

from __future__ import annotations

import itertools
import logging
import math
import numbers

import torch
from torch import nn

from hsicam.errors import ConfigError, InputError, negative_radiance_error
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

#: A scene's peak above which :meth:`Camera.capture` warns. Scenes are normalised (reflectance-like,
#: 1 = a white reference), and a scene of 1 everywhere images to at most 1, the sensor's full scale
#: (DOE cameras: the PSF keeps at most the light it receives and the CFA transmits at most all of
#: it; CASSI with the ``mean`` convention likewise). Values somewhat above 1 are highlights that
#: the PSF's spread mostly keeps below full scale; a peak of 4 is two stops over full scale, while
#: unnormalised data (reflectance in percent, raw counts, radiance units) lie far beyond it.
SCENE_PEAK_WARN = 4.0
#: The smallest sensor image (px per side) that :meth:`Camera.capture` makes of a user's scene: 2×2, or
#: one period of the sensor code (the CFA) when that is larger — what ``hsicam reconstruct`` needs.
MIN_SENSOR_PX = 2


def check_finite(t: torch.Tensor, what: str) -> None:
    """:class:`InputError` naming ``what`` and the count when ``t`` holds NaN or Inf values. Screened by
    one sum (a tenth of an ``isfinite`` pass); only a sum that is not finite counts the values."""
    if t.numel() and t.device.type != "meta" and not bool(torch.isfinite(t.sum())):
        bad = int((~torch.isfinite(t)).sum())
        if bad:  # else a sum that overflowed: large values, but finite
            raise InputError(f"{what} contains {bad} NaN or Inf value(s) of {t.numel()}")


def check_non_negative(t: torch.Tensor, what: str) -> None:
    """:class:`InputError` naming ``what``, the count and the minimum when ``t`` holds negative values (radiance and
    reflectance are >= 0; as :func:`hsicam.data.cube.check_cube` says of a file)."""
    if t.numel() and t.device.type != "meta":
        lo = float(t.min())
        if lo < 0:
            neg = int((t < 0).sum())
            raise negative_radiance_error(what, neg, lo, "dark noise after a background subtraction: x.clamp_min(0)")


def check_device(t: torch.Tensor, module: nn.Module, what: str) -> None:
    """:class:`InputError` naming ``what`` when ``t`` is not on the device of ``module``'s first parameter
    or buffer (a module with neither takes any device)."""
    ref = next(itertools.chain(module.parameters(), module.buffers()), None)
    if ref is not None and t.device != ref.device:
        raise InputError(f"{what} is on {t.device}, the {type(module).__name__} on {ref.device}: move one of them "
                         f"(.to({str(ref.device)!r}))")


def check_sensor_image(y: torch.Tensor, what: str = "sensor image") -> None:
    """:class:`InputError` unless ``y`` is a floating (B, 1, H, W) tensor with B, H, W >= 1 (values: [0, 1],
    1 = full scale)."""
    if not isinstance(y, torch.Tensor):
        raise InputError(f"{what} must be a torch.Tensor (B, 1, H, W), got {type(y).__name__}")
    if y.dim() != 4 or y.shape[1] != 1:
        raise InputError(f"{what} must be (B, 1, H, W), got shape {tuple(y.shape)}")
    if not torch.is_floating_point(y):
        raise InputError(f"{what} must be a floating-point tensor with values in [0, 1] (1 = full scale), got {y.dtype}")
    if min(y.shape[0], y.shape[2], y.shape[3]) < 1:
        raise InputError(f"{what} of shape {tuple(y.shape)} is empty: it needs B, H, W >= 1")


def check_origin(origin, what: str = "origin") -> None:
    """:class:`InputError` unless ``origin`` is a pair of integers (row, column): the sensor pixel of a window's
    top-left corner (a CFA phase is taken from it modulo the period; a float, a None or a third item was read
    wrongly or failed deep inside)."""
    ok = isinstance(origin, (tuple, list)) and len(origin) == 2 and all(
        isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in origin)
    if not ok:
        raise InputError(f"{what} must be a pair of ints (row, column): the sensor pixel of the window's top-left "
                         f"corner, got {origin!r}")


def check_window_size(height, width, what: str = "sensor window") -> None:
    """:class:`InputError` unless ``height`` and ``width`` are integers >= 1."""
    for v in (height, width):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
            raise InputError(f"{what} must be at least 1×1 px (two ints), got {height!r}×{width!r}")


def _is_level(value) -> bool:
    """A noise level: a finite number >= 0 (a standard deviation)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return False
    return math.isfinite(v) and v >= 0


class Camera(nn.Module):
    """Scene cube (B, C, H, W) → sensor image. Subclasses implement ``A`` and ``A_adjoint``.

    Everything else a solver, a network or the training loop needs is derived here from ``A`` and
    ``A_adjoint`` (``A_adjoint_A``, :meth:`adjointness_error`, :meth:`sqnorm`), or declared by the
    camera (:meth:`noise_levels` / :meth:`set_noise`, :meth:`param_groups`, and the capability
    :attr:`has_diagonal_gram` with :meth:`gram_diagonal` for GAP-type solvers).

    Attributes:
        kind: the registry name (``camera.kind``), set by :func:`~hsicam.cameras.registry.register_camera`.
        bands: the band grid the camera expects (C = len(bands)).
        boundary: "valid" (scene larger than the sensor by ``margin`` pixels per axis) or "same".
        noise: module applied to A(x) in ``forward``.
    """

    kind: str = "camera"
    has_diagonal_gram: bool = False  # A·Aᵀ is diagonal (CASSI): gram_diagonal() is available
    half_precision_on_cpu: bool = True  # False where the forward model needs float32/64 on the CPU (FFTs)
    bands: Bands
    boundary: str
    noise: nn.Module

    @property
    def margin(self) -> int:
        """The PSF kernel's width − 1 (px; 0 for a camera without one), in both modes: the extra scene pixels per axis
        a ``valid`` sensor needs (:meth:`sensor_size`); a ``same`` sensor is as large as its scene."""
        raise NotImplementedError

    def A(self, x: torch.Tensor) -> torch.Tensor:  # noqa: N802 - operator notation
        raise NotImplementedError

    def A_adjoint(self, y: torch.Tensor) -> torch.Tensor:  # noqa: N802
        raise NotImplementedError

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None, *,
                sensor_generator: torch.Generator | None = None) -> torch.Tensor:
        """Noisy sensor image: the sensor noise drawn from ``sensor_generator`` if given, else ``generator``."""
        return self.noise(self.A(x), generator if sensor_generator is None else sensor_generator)

    @torch.no_grad()
    def capture(self, x: torch.Tensor, generator: torch.Generator | None = None, source: str = "scene") -> torch.Tensor:
        """The noisy sensor image of a user's scene ``x`` (``hsicam simulate``): ``self(x, generator)``
        without autograd, with the checks that a training step leaves out. A scene whose peak is above
        :data:`SCENE_PEAK_WARN` is logged (WARNING, naming ``source``): its image goes far past the
        sensor's full scale of 1. A scene holding NaN/Inf values is an :class:`InputError` naming ``source``
        and their count; so is a scene with negative values (light is never negative: ``hsicam simulate``'s cube
        check refuses them too), and a sensor image that is not finite (float overflow of a scene with huge
        values: naming the scene's peak; or a damaged camera, whose image of a uniform scene is not finite either), and a scene smaller than :meth:`min_scene_size`
        (:meth:`check_capture_size`). The layout is checked first (:meth:`check_scene`): a NumPy array, a cube
        without its batch axis or with its bands last is told as such, not as a scene of the wrong size."""
        self.check_scene_layout(x)
        self.check_capture_size(tuple(x.shape[-2:]), source)
        check_finite(x, source)
        check_non_negative(x, source)
        peak = float(x.max()) if x.numel() else 0.0
        advice = ("normalise the scene first: reflectance-like values in [0, 1] (a white reference at 1; "
                  "divide raw counts or percent by their full scale, or the cube by its maximum)")
        y = self(x, generator)
        if not bool(torch.isfinite(y).all()):
            if not bool(torch.isfinite(self.A(torch.ones_like(x))).all()):  # the camera, not the scene
                raise InputError(f"{source}: the simulated sensor image is not finite, and so is this camera's image of "
                                 "a uniform scene of 1: the camera's model (its weights or config.yaml: PSFs, DOE "
                                 "heights, CFA) holds NaN/Inf values or overflows; the scene is not the cause")
            raise InputError(f"{source}: the simulated sensor image is not finite (float overflow: the scene's peak "
                             f"value is {peak:.4g}); {advice}")
        if peak > SCENE_PEAK_WARN:
            log.warning("%s: the scene's peak value is %.4g, far above 1 (a scene of 1 fills the sensor's full scale): "
                        "the sensor image reaches %.4g and a real sensor saturates above 1; %s",
                        source, peak, float(y.max()), advice)
        return y

    def measure(self, x: torch.Tensor, generator: torch.Generator | None = None):
        """(noisy measurement, the operator a network should use for it): here ``(self(x), self)``;
        a camera whose operator is costly to build (the DOE camera's PSFs) returns the snapshot
        that made the measurement, so a training step builds it once."""
        return self(x, generator), self

    def fixed_measure(self):
        """:meth:`measure` for batches imaged while the camera's parameters stay fixed (the network
        trains alone): ``fn(x, generator) → (measurement, operator)``, without autograd through the
        camera. Here :meth:`measure` under ``no_grad``; a camera with a costly operator reuses it.
        Take a new one after the parameters change."""

        def fn(x: torch.Tensor, generator: torch.Generator | None = None):
            with torch.no_grad():
                return self.measure(x, generator)

        return fn

    # -- derived operator quantities (built only from A and A_adjoint) ---------------------------
    def A_adjoint_A(self, x: torch.Tensor) -> torch.Tensor:  # noqa: N802
        """Aᵀ A x, (B, C, H, W) → (B, C, H, W) (the normal operator)."""
        return self.A_adjoint(self.A(x))

    def check_measurement(self, y: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``y`` is a finite (B, 1, H, W) sensor image (:func:`check_sensor_image`;
        a solver given NaN returned a NaN cube without a word) in a precision this camera's operator takes on its
        device, on that device (as :meth:`check_scene` checks a scene)."""
        check_sensor_image(y)
        self._check_precision(y, "sensor image", "y")
        check_device(y, self, "sensor image")
        check_finite(y, "sensor image")

    def _check_precision(self, t: torch.Tensor, what: str, name: str) -> None:
        """:class:`InputError` for a half-precision ``t`` on the CPU when this camera's operator needs float32 or
        float64 there (:attr:`half_precision_on_cpu`)."""
        if t.device.type == "cpu" and t.dtype in (torch.float16, torch.bfloat16) and not self.half_precision_on_cpu:
            raise InputError(f"{what} is {t.dtype} on the CPU: the {type(self).__name__}'s FFT convolution needs "
                             f"float32 or float64 there ({name}.float())")

    @torch.no_grad()
    def relative_residual(self, x: torch.Tensor, y: torch.Tensor) -> float:
        """‖A x − y‖ / ‖y‖ (data consistency of an estimate ``x``); InputError when A x is not the shape of ``y``."""
        ax = self.A(x)
        if not isinstance(y, torch.Tensor) or ax.shape != y.shape:
            got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise InputError(f"the estimate images to {tuple(ax.shape)} px but the measurement is {got}: not the same "
                             "window")
        return float((ax - y).norm() / y.norm().clamp_min(1e-30))

    @torch.no_grad()
    def adjointness_error(self, scene_hw: tuple[int, int], generator: torch.Generator | None = None,
                          dtype: torch.dtype = torch.float64) -> float:
        """|⟨Ax, y⟩ − ⟨x, Aᵀy⟩| / (‖Ax‖‖y‖) for random x, y (0 for an exact adjoint, up to rounding)."""
        dev = next((p.device for p in self.parameters()), torch.device("cpu"))
        x = torch.rand((1, len(self.bands), *scene_hw), generator=generator, device=dev, dtype=dtype)
        ax = self.A(x)
        y = torch.rand(ax.shape, generator=generator, device=dev, dtype=dtype)
        lhs, rhs = (ax * y).sum(), (x * self.A_adjoint(y)).sum()
        return float((lhs - rhs).abs() / (ax.norm() * y.norm()).clamp_min(1e-300))

    @torch.no_grad()
    def sqnorm(self, scene_hw: tuple[int, int], iterations: int = 50, generator: torch.Generator | None = None,
               dtype: torch.dtype = torch.float64) -> float:
        """‖A‖² (largest eigenvalue of AᵀA) on scenes of ``scene_hw`` px, by the power method."""
        dev = next((p.device for p in self.parameters()), torch.device("cpu"))
        x = torch.rand((1, len(self.bands), *scene_hw), generator=generator, device=dev, dtype=dtype)
        x = x / x.norm()
        value = 0.0
        for _ in range(iterations):
            z = self.A_adjoint_A(x)
            value = float((x * z).sum())
            x = z / z.norm().clamp_min(1e-300)
        return value

    def gram_diagonal(self, y: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
        """diag(A·Aᵀ) shaped like ``y`` (B, 1, H, W), entries ≤ ``eps`` (unseen pixels) set to 1.

        Only for cameras with :attr:`has_diagonal_gram` (CASSI): there A·Aᵀ is diagonal and its
        diagonal is A(Aᵀ 1). Others raise ``NotImplementedError``.
        """
        if not self.has_diagonal_gram:
            raise NotImplementedError(f"{type(self).__name__}: A·Aᵀ is not diagonal")
        ones = torch.ones_like(y[:1])
        d = self.A(self.A_adjoint(ones))
        return torch.where(d > eps, d, torch.ones_like(d))

    # -- declared by the camera: noise and trainable parameters ----------------------------------
    def noise_levels(self) -> dict[str, float]:
        """The current noise levels by name (``sensor_sigma``: Gaussian σ on the [0, 1] image)."""
        return {"sensor_sigma": float(self.noise.sigma)}

    def set_noise(self, **levels: float) -> None:
        """Set noise levels by the names of :meth:`noise_levels`; unknown names are a ConfigError,
        and so is a level that is negative or not finite (a standard deviation)."""
        known = self.noise_levels()
        unknown = sorted(set(levels) - set(known))
        if unknown:
            raise ConfigError(f"{type(self).__name__} has no noise level {', '.join(unknown)}; "
                              f"it has {', '.join(sorted(known))}")
        bad = sorted(k for k, v in levels.items() if not _is_level(v))
        if bad:
            raise ConfigError("noise levels must be finite and >= 0, got "
                              + ", ".join(f"{k}={levels[k]}" for k in bad))
        self._apply_noise(levels)

    def _apply_noise(self, levels: dict[str, float]) -> None:
        if "sensor_sigma" in levels:
            self.noise.sigma = float(levels["sensor_sigma"])

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        """Trainable optics parameters by group name (e.g. ``doe``, ``cfa``); empty when none."""
        return {}

    def param_group_spans(self) -> dict[str, tuple[float, str]]:
        """For each group of :meth:`param_groups`, the span of values its parameters meaningfully take (in
        their own units) and what that span is, in words: an optimiser step as large moves them across it
        at once (training refuses such a learning rate). Empty: no bound declared."""
        return {}

    def sensor_code(self, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """How much each band counts at each sensor pixel, (C, height, width), for a window of the
        sensor whose top-left pixel is ``origin``. Cameras without such a code raise
        ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} has no per-band sensor code")

    def sensor_size(self, scene_hw: tuple[int, int]) -> tuple[int, int]:
        """Sensor (H, W) for a scene of ``scene_hw``."""
        m = self.margin if self.boundary == "valid" else 0
        return scene_hw[0] - m, scene_hw[1] - m

    def scene_size(self, sensor_hw: tuple[int, int]) -> tuple[int, int]:
        """Scene (H, W) a sensor of ``sensor_hw`` needs."""
        m = self.margin if self.boundary == "valid" else 0
        return sensor_hw[0] + m, sensor_hw[1] + m

    def min_sensor_px(self) -> int:
        """Side (px) of the smallest sensor image :meth:`capture` makes: :data:`MIN_SENSOR_PX`, or the
        period of the sensor code (the CFA's) when larger."""
        return max(MIN_SENSOR_PX, int(getattr(self, "code_period", 1)))

    def min_padded_px(self) -> int:
        """Smallest scene side (px) a ``same`` camera's padding takes (0: any): reflection mirrors the scene about its
        edge pixel, so it needs more pixels than it pads; wrapping around needs at least as many (the padding may not
        wrap around the scene more than once)."""
        if self.boundary != "same":
            return 0
        return {"reflect": self.margin // 2 + 1, "circular": self.margin // 2}.get(getattr(self, "padding", "zeros"), 0)

    def min_scene_size(self) -> tuple[int, int]:
        """Smallest scene (H, W) in px whose sensor image is at least ``n``×``n`` px, ``n`` =
        :meth:`min_sensor_px`: in ``valid`` mode the sensor is smaller than the scene by :attr:`margin`
        (the PSF kernel's width − 1), so the scene needs ``n + margin``; in ``same`` mode with reflect or
        circular padding at least :meth:`min_padded_px`."""
        n = max(self.min_sensor_px(), self.min_padded_px())
        h, w = self.scene_size((n, n))
        return max(h, n), max(w, n)

    def check_capture_size(self, scene_hw: tuple[int, int], source: str = "scene") -> None:
        """InputError naming ``source``, the scene's size and :meth:`min_scene_size` when the scene is smaller."""
        (h, w), (mh, mw) = scene_hw, self.min_scene_size()
        if h >= mh and w >= mw:
            return
        n = self.min_sensor_px()
        why = f"a sensor image of at least {n}×{n} px" + (" (one CFA period)" if n > MIN_SENSOR_PX else "")
        fix = "use a larger scene"
        if self.boundary == "valid" and self.margin:
            why += f", plus the {self.margin} px per axis that boundary=valid loses to the {self.margin + 1}-px PSF kernel"
            fix += " or boundary=same" if min(h, w) >= n else ""
        raise InputError(f"{source}: the scene is {h}×{w} px, too small: this camera needs {mh}×{mw} px, {why}; {fix}")

    def check_scene_layout(self, x: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``x`` is a torch tensor (B, C, H, W) with this camera's bands on axis 1,
        naming the fix of a NumPy array, a cube without its batch axis or one with its bands last. The layout alone
        (any device, dtype and size: the first of :meth:`check_scene`'s checks)."""
        c = len(self.bands)
        if not isinstance(x, torch.Tensor):
            hint = ": torch.from_numpy(x)" if type(x).__module__ == "numpy" else ""
            raise InputError(f"scene must be a torch.Tensor (B, C, H, W), got {type(x).__name__}{hint}")
        if x.dim() != 4:
            hint = ": a (C, H, W) cube is x[None]" if x.dim() == 3 and x.shape[0] == c else ""
            raise InputError(f"scene must be a (B, C, H, W) tensor, got shape {tuple(x.shape)}{hint}")
        if x.shape[1] != c:
            hint = ("; its last axis has the camera's bands: a (B, H, W, C) cube is x.permute(0, 3, 1, 2)"
                    if x.shape[-1] == c else "")
            raise InputError(f"scene has {x.shape[1]} bands but the camera has {c} ({self.bands!r}){hint}")

    def check_scene(self, x: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``x`` is a (B, C, H, W) cube on this camera's grid: floating
        (float32/float64 on the CPU for a camera whose FFTs have no half precision there:
        :attr:`half_precision_on_cpu`), B >= 1, on the camera's device. Values are not scanned here (a
        solver calls ``A`` every iteration): :meth:`capture` refuses NaN/Inf scenes, and
        :meth:`hsicam.models.CameraSystem.reconstruct` NaN/Inf sensor images."""
        self.check_scene_layout(x)
        if not torch.is_floating_point(x):
            raise InputError(f"scene must be a floating-point tensor with values in [0, 1] (reflectance-like), "
                             f"got {x.dtype}")
        self._check_precision(x, "scene", "x")
        if x.shape[0] < 1:
            raise InputError(f"scene of shape {tuple(x.shape)} is an empty batch: it needs B >= 1")
        check_device(x, self, "scene")
        self.check_padded_size(tuple(x.shape[-2:]), "scene")
        self.check_sensor_area(tuple(x.shape[-2:]))

    def check_padded_size(self, hw: tuple[int, int], what: str) -> None:
        """Raise :class:`InputError` unless an image of ``hw`` (H, W), a scene or (``same`` boundary: of the scene's
        size) a sensor image, is as large as the padding takes (:meth:`min_padded_px`)."""
        least = self.min_padded_px()
        if min(hw) < least:
            raise InputError(f"{what} of {hw[0]}×{hw[1]} px is too small for {self.padding} padding by "
                             f"{self.margin // 2} px: it needs at least {least} px per side")

    def check_sensor_area(self, scene_hw: tuple[int, int]) -> None:
        """Raise :class:`InputError` unless a scene of ``scene_hw`` (H, W) leaves a sensor image of at least 1×1 px
        (``valid`` boundary: the scene less the kernel's margin)."""
        h, w = self.sensor_size(tuple(scene_hw))
        if h < 1 or w < 1:
            raise InputError(
                f"scene of {scene_hw[0]}×{scene_hw[1]} px is too small for boundary='valid' with a "
                f"{self.margin + 1}-px kernel: it needs at least {self.margin + 1}×{self.margin + 1}"
            )

    def snapshot(self, generator: torch.Generator | None = None, *, nominal: bool = False) -> "OperatorSnapshot":
        """This camera's noiseless linear operator, frozen for one batch (see :class:`OperatorSnapshot`).

        ``generator`` draws whatever the operator itself randomises (the DOE height noise);
        ``nominal=True`` takes the design operator without such noise (what a reconstruction
        network knows). Gradients still flow to the camera's parameters.
        """
        return OperatorSnapshot(self)


def _zero_origin(origin: tuple[int, int], who: str) -> None:
    if tuple(origin) != (0, 0):
        raise NotImplementedError(f"{who} has no position-dependent operator for a window at origin {tuple(origin)}")


class OperatorSnapshot:
    """A camera's noiseless ``A`` / ``A_adjoint`` frozen as a linear operator on windows of the sensor.

    ``A(x, origin)`` maps a cube (B, C, h', w') to the sensor window (B, 1, h, w) whose top-left
    sensor pixel is ``origin``; ``A_adjoint`` is its exact adjoint. Cameras override
    :meth:`Camera.snapshot` with operators that compute their expensive parts (a PSF stack) once.
    This default calls the camera and supports ``origin=(0, 0)`` only.

    Attributes:
        lipschitz: an upper bound of ‖A‖² (position-independent), or None when unknown.
    """

    lipschitz: float | None = None
    reach_px: tuple[int, int] = (0, 0)  # how far (rows, columns) AᵀA spreads a pixel, in pixels

    def __init__(self, camera: Camera) -> None:
        self.camera = camera

    @property
    def bands(self) -> Bands:
        return self.camera.bands

    def scene_size(self, sensor_hw: tuple[int, int]) -> tuple[int, int]:
        """Cube (h', w') this operator maps onto a sensor window of ``sensor_hw``."""
        return self.camera.scene_size(sensor_hw)

    def sensor_code(self, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """Per-band sensor code (C, height, width) at ``origin``; NotImplementedError without one."""
        return self.camera.sensor_code(height, width, origin)

    @property
    def code_period(self) -> int:
        return int(getattr(self.camera, "code_period", 1))

    def A(self, x: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # noqa: N802
        _zero_origin(origin, type(self.camera).__name__)
        return self.camera.A(x)

    def A_adjoint(self, y: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # noqa: N802
        _zero_origin(origin, type(self.camera).__name__)
        return self.camera.A_adjoint(y)
