"""Camera + reconstruction network as one trainable module (the optics are part of the model)."""

from __future__ import annotations

import logging

import torch
from torch import nn

from hsicam.cameras import Camera, build_camera
from hsicam.cameras.base import check_device, check_finite, check_origin, check_sensor_image
from hsicam.errors import InputError
from hsicam.models.consistency import (WIENER_WINDOW_PX, _half_reach, consistency_step, cut_psf, default_band_px,
                                       linear_consistency_step, linear_reach_px, reach_px)
from hsicam.models.registry import build_network

log = logging.getLogger(__name__)


class CameraSystem(nn.Module):
    """Scene → simulated sensor image → reconstructed cube.

    ``forward(scene)`` returns ``(reconstruction, sensor)``; in ``valid`` mode both are smaller than
    the scene by ``camera.margin`` and aligned with :meth:`target` (the scene's centre crop).
    The network is any registered kind (:mod:`hsicam.models.registry`); it is called as
    ``net(sensor, camera, origin)``. ``forward`` (training and its validation) is the network
    alone; :meth:`reconstruct` in eval mode adds ``consistency`` (``model.consistency``:
    iterations, damping, psf_energy), the measurement-consistency step of
    :mod:`hsicam.models.consistency`, through ``step_camera`` (default: ``camera``).
    """

    def __init__(self, camera: Camera, net: nn.Module, consistency=None) -> None:
        super().__init__()
        self.camera, self.net = camera, net
        self.consistency = consistency  # hsicam.config.ConsistencyConfig or None (off)
        # the camera whose operator the step uses (None: ``camera``), e.g. the nominal design while
        # ``camera`` images with fabrication errors the deployed system does not know
        # A reference, not a submodule (see __setattr__): not in the state dict, not moved by .to().
        self.step_camera: Camera | None = None
        # model.consistency.kind linear: the filters (m², C, K, K) of RUN/linear_step.safetensors (not
        # in the state dict: fitted after training, hsicam.engine.linear_step)
        self.linear_step: torch.Tensor | None = None
        # why a run has no linear step and what to do, naming the run (set by hsicam.runs.folder.load_run)
        self.linear_step_missing: str | None = None
        self.autocast_dtype: torch.dtype | None = None  # e.g. torch.bfloat16 for the network on CUDA

    def __setattr__(self, name: str, value) -> None:
        if name in ("step_camera", "linear_step"):  # nn.Module would register a camera as a submodule (its
            # weights saved twice) and a tensor would not be a plain attribute
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)

    def missing_linear_step(self, consistency=None) -> str | None:
        """Why ``consistency`` (default: the model's own) asks for a linear step that the run has not got, naming
        the run and what to do (:func:`hsicam.runs.folder.load_run` sets it), else None. None too for a camera that
        takes no step (:attr:`camera_takes_consistency`: SD-CASSI, whose training fits no linear step and whose
        reconstructions skip it)."""
        c = self.consistency if consistency is None else consistency
        if c is None or c.kind != "linear" or c.iterations <= 0 or self.linear_step is not None:
            return None
        if not self.camera_takes_consistency:
            return None
        return self.linear_step_missing

    @classmethod
    def from_config(cls, cfg) -> "CameraSystem":  # cfg: hsicam.config.Config
        """The untrained system a config describes: its camera (``cfg.camera``, on ``cfg.bands``), its network
        (``cfg.model.kind``) and its consistency settings (``cfg.model.consistency``). A trained run's system:
        :func:`hsicam.runs.folder.load_run`."""
        if not hasattr(cfg, "camera") or not hasattr(cfg, "model"):  # e.g. a preset's name: AttributeError 'camera'
            raise InputError(f"CameraSystem.from_config takes a Config (hsicam.config.load_config('quick')), got "
                             f"{type(cfg).__name__} {cfg!r}"[:300])
        camera = build_camera(cfg)
        return cls(camera, build_network(cfg, camera), cfg.model.consistency)

    def with_camera(self, camera: Camera) -> "CameraSystem":
        """The same network imaging through ``camera`` (e.g. a measured-PSF camera), same autocast
        and consistency step (through ``camera``: ``step_camera`` is not carried over)."""
        out = type(self)(camera, self.net, self.consistency)
        out.autocast_dtype = self.autocast_dtype
        out.linear_step, out.linear_step_missing = self.linear_step, self.linear_step_missing
        return out

    @property
    def camera_takes_consistency(self) -> bool:
        """Whether the camera's scene grid is the sensor's, so that measurement-consistency steps apply to it
        (SD-CASSI's is not)."""
        return getattr(self.camera, "kind", None) != "sd_cassi"

    @property
    def consistency_on(self) -> bool:
        """Whether :meth:`reconstruct` takes the step: configured, and a camera whose scene grid is
        the sensor's (SD-CASSI's is not: its reconstructions skip the step, with a warning once)."""
        if self.consistency is None or self.consistency.iterations <= 0:
            return False
        if not self.camera_takes_consistency:
            if not getattr(self, "_warned_grid", False):
                log.warning("model.consistency is skipped: SD-CASSI's scene grid is not the sensor's")
                self._warned_grid = True
            return False
        return True

    @property
    def tileable(self) -> bool:
        """Whether a reconstruction can be cut into tiles: a camera whose scene grid is the sensor's (each window's
        cube is the window's size); SD-CASSI's cube is narrower than its sensor image, so it is reconstructed whole
        (:func:`~hsicam.engine.inference.reconstruct_tiled`)."""
        return self.camera_takes_consistency

    @property
    def context_px(self) -> int:
        """Pixels of sensor context each output pixel depends on, per side (halo for tiling): the
        network's, plus (consistency on) the step's reach through the camera's current PSFs."""
        if not self.consistency_on:
            return int(self.net.context_px)
        return self._context_px(self._step_operator(), self.consistency.psf_energy)

    def _context_px(self, step_op, psf_energy: float) -> int:
        """:attr:`context_px` with the step through ``step_op``, its PSFs cut to ``psf_energy``."""
        c = self.consistency
        iterations = self._landweber_iterations
        return (self._context_before_steps_px(step_op, psf_energy)
                + reach_px(step_op, iterations, psf_energy, tv=c.tv_weight > 0) + self._wiener_reach_px * iterations)

    def _context_before_steps_px(self, step_op, psf_energy: float) -> int:
        """The context (px per side) of :meth:`reconstruct_before_steps` with the step through ``step_op``."""
        c = self.consistency
        if c.kind != "linear":
            return int(self.net.context_px)
        # the filters' own width when loaded (a file fitted with another window_px)
        window = int(self.linear_step.shape[-1]) if self.linear_step is not None else c.window_px
        return (int(self.net.context_px) + linear_reach_px(step_op, window, c.iterations, psf_energy)
                + self._wiener_reach_px * c.iterations)

    @property
    def _landweber_iterations(self) -> int:
        """The Landweber steps of ``consistency``: kind linear's ``landweber_after`` (after its linear step), else
        its ``iterations``."""
        c = self.consistency
        return c.landweber_after if c.kind == "linear" else c.iterations

    @property
    def _wiener_reach_px(self) -> int:
        """How much further each step reaches on a noisy capture: its Wiener gain looks WIENER_WINDOW_PX // 2
        further (0 unless :attr:`_weighs_noise`)."""
        return WIENER_WINDOW_PX // 2 if self._weighs_noise else 0

    @property
    def _weighs_noise(self) -> bool:
        """Whether the consistency steps weigh residuals against noise: ``model.consistency.noise_aware`` and a
        camera noise model (``camera.sensor``) that declares some."""
        return self.consistency.noise_aware and getattr(getattr(self.camera, "noise", None), "declares_noise", False)

    def _noise_variance(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor | None:
        """The capture's per-pixel noise variance by the camera's noise model
        (:meth:`hsicam.sensor.SensorNoise.variance`; ``origin``: the window's top-left sensor pixel, which
        picks its part of a flat field's gain map), which the consistency steps weigh residuals by; None
        unless :attr:`_weighs_noise`."""
        return self.camera.noise.variance(sensor, origin) if self._weighs_noise else None

    def _clipped(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor | None:
        """The pixels of the window ``sensor`` (B, 1, H, W) at ``origin`` that the capture clipped (the camera's noise
        model's :meth:`~hsicam.sensor.SensorNoise.saturated_window`, (1, 1, H, W) bool), which the consistency steps
        take as lower bounds; None without a saturated-pixel map."""
        window = getattr(getattr(self.camera, "noise", None), "saturated_window", None)
        m = window(sensor, origin) if window is not None else None
        return None if m is None else m[None, None]

    @property
    def bands(self):
        return self.camera.bands

    def target(self, scene: torch.Tensor) -> torch.Tensor:
        """Ground truth aligned with the sensor: the centre crop in ``valid`` mode, else the scene.
        ``scene``: (B, C, H, W) on the camera's bands; anything else is an :class:`InputError`
        (:meth:`~hsicam.cameras.Camera.check_scene_layout`: a bands-last cube was cropped along its bands, silently)."""
        self.camera.check_scene_layout(scene)
        if self.camera.boundary != "valid":
            return scene
        self.camera.check_sensor_area(tuple(scene.shape[-2:]))  # as capture (an empty crop was scored as 0×0 px)
        r = self.camera.margin // 2
        h, w = scene.shape[-2] - 2 * r, scene.shape[-1] - 2 * r
        return scene[..., r : r + h, r : r + w]

    def network(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0), operator=None, *,
                read_clipped: bool = True) -> torch.Tensor:
        """The network alone: sensor image (B, 1, H, W) → cube (B, C, H, W) (float32).

        ``origin``: the sensor pixel of the window's top-left corner (the CFA phase of a tile).
        ``operator``: what the network sees of the camera (default the camera; a snapshot from
        :meth:`Camera.measure` saves rebuilding it). A network with ``takes_clipped`` (the unrolled one) also gets
        the window's clipped pixels (:meth:`_clipped`), lower bounds in its data steps, unless ``read_clipped`` is
        False (a window whose place on the map is not known, e.g. a candidate CFA phase of
        :func:`~hsicam.engine.cfa_offset.estimate_cfa_offset`).
        """
        check_origin(origin)
        op = self.camera if operator is None else operator
        # a network whose data steps read the measurement (the unrolled one) takes the capture's clipped pixels too
        takes = read_clipped and getattr(self.net, "takes_clipped", False)
        kw = {"clipped": self._clipped(sensor, origin)} if takes else {}
        if self.autocast_dtype is not None and sensor.device.type != "cpu":
            with torch.autocast(sensor.device.type, dtype=self.autocast_dtype):
                return self._checked_output(self.net(sensor, op, origin, **kw), sensor).float()
        return self._checked_output(self.net(sensor, op, origin, **kw), sensor)

    def cube_size(self, sensor_hw: tuple[int, int]) -> tuple[int, int]:
        """The cube (H', W') a network returns for a sensor window of ``sensor_hw``: the scene behind it
        (:meth:`~hsicam.cameras.Camera.scene_size`) without the PSF kernel's margin of a ``valid`` sensor, i.e. the
        sensor's own size, and SD-CASSI's scene (W − D) behind its dispersed measurement."""
        m = self.camera.margin if self.camera.boundary == "valid" else 0
        h, w = self.camera.scene_size(tuple(sensor_hw))
        return h - m, w - m

    def _checked_output(self, x, sensor: torch.Tensor) -> torch.Tensor:
        """``x``, the network's output for ``sensor`` (B, 1, H, W), once it is a floating (B, C, H', W') tensor of the
        camera's C bands and of :meth:`cube_size`; else one :class:`InputError` naming the network (a network of
        one's own that returned the wrong bands or size was scored, or failed deep in a loss, a step or a tile)."""
        b, c = sensor.shape[0], len(self.bands)
        hw = self.cube_size(tuple(sensor.shape[-2:]))
        if not (isinstance(x, torch.Tensor) and x.is_floating_point() and x.dim() == 4 and x.shape[:2] == (b, c)
                and tuple(x.shape[-2:]) == hw):
            got = f"shape {tuple(x.shape)} of {x.dtype}" if isinstance(x, torch.Tensor) else type(x).__name__
            raise InputError(f"the network ({type(self.net).__name__}) returned {got} for a sensor image of shape "
                             f"{tuple(sensor.shape)}; a network returns a floating (B, C, H, W) cube of the camera's "
                             f"C = {c} bands and {hw[0]}×{hw[1]} px")
        return x

    def reconstruct(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0), operator=None,
                    step_operator=None) -> torch.Tensor:
        """Sensor image (B, 1, H, W) → cube (B, C, H, W) (float32): :meth:`network`, then, in eval
        mode with ``consistency`` on, the measurement-consistency step through the nominal snapshot
        of ``step_camera`` (default ``camera``), its PSFs cut to ``consistency.psf_energy``, or
        through ``step_operator`` as given (already cut: :meth:`reconstructor` passes one). Without
        gradients the Landweber steps go in bands of rows (:func:`~hsicam.models.consistency.consistency_step`'s
        ``band_px``: the same cube, a band's working memory).

        ``sensor``: floating (any precision), finite, on the model's device, else an :class:`InputError` naming what
        is wrong (:meth:`check_input`); its values on the scale the camera gives, 1 = full scale (not checked: a raw
        capture's counts are divided by their full scale first, :func:`hsicam.data.images.read_capture`; values a
        little below 0 after a black level are taken as they are)."""
        x = self.reconstruct_before_steps(sensor, origin, operator, step_operator)
        if self.training or not self.consistency_on:
            return x
        return self.landweber_steps(sensor, x, origin, step_operator)

    def reconstruct_before_steps(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0), operator=None,
                                 step_operator=None) -> torch.Tensor:
        """:meth:`reconstruct` without its Landweber steps: the network, then (eval mode, consistency on, kind
        linear) the linear step. Arguments as there."""
        self.check_input(sensor)
        x = self.network(sensor, origin, operator)
        if self.training or not self.consistency_on or self.consistency.kind != "linear":
            return x
        c = self.consistency
        op, energy = (self._step_operator(), c.psf_energy) if step_operator is None else (step_operator, 1.0)
        if self.linear_step is None:
            why = self.missing_linear_step()
            if why:
                raise InputError(why)
            raise InputError("model.consistency.kind=linear needs the run's linear_step.safetensors, fitted when "
                             "training ends; for a run without it: `hsicam train --out RUN --resume --set "
                             "model.consistency.kind=linear --set model.consistency.iterations=1` (a fine-tuned run: "
                             "`hsicam finetune … --resume`); or go without it: reconstruct --consistency-steps 0 (the "
                             "network alone), evaluate --set model.consistency.kind=landweber")
        return linear_consistency_step(op, sensor, x, self.linear_step, origin, gain=c.gain, iterations=c.iterations,
                                       psf_energy=energy, extend=self._extension(),
                                       noise_variance=self._noise_variance(sensor, origin),
                                       clipped=self._clipped(sensor, origin))

    def landweber_steps(self, sensor: torch.Tensor, x: torch.Tensor, origin: tuple[int, int] = (0, 0),
                        step_operator=None, on_step=None) -> torch.Tensor:
        """The Landweber steps of ``consistency`` (kind landweber: its ``iterations``; linear: ``landweber_after``)
        from the estimate x (B, C, H, W) of ``sensor`` (B, 1, H, W) at ``origin``; x itself when there are none.
        ``step_operator`` as in :meth:`reconstruct`; ``on_step``: called after each step (progress)."""
        check_origin(origin)
        c = self.consistency
        iterations = self._landweber_iterations
        if self.training or not self.consistency_on or iterations <= 0:  # as reconstruct: the steps are inference's
            return x
        op, energy = (self._step_operator(), c.psf_energy) if step_operator is None else (step_operator, 1.0)
        band = None if torch.is_grad_enabled() else default_band_px(sensor.shape[-1])
        return consistency_step(op, sensor, x, origin, damping=c.damping, iterations=iterations,
                                psf_energy=energy, extend=self._extension(), spectral_prior=c.spectral_prior,
                                noise_variance=self._noise_variance(sensor, origin), tv_weight=c.tv_weight,
                                band_px=band, on_step=on_step, clipped=self._clipped(sensor, origin))

    def check_input(self, sensor: torch.Tensor) -> None:
        """:class:`InputError` unless ``sensor`` is a finite floating (B, 1, H, W) image, B, H, W >= 1, on
        the model's device (shape and dtype: :func:`~hsicam.cameras.base.check_sensor_image`)."""
        check_sensor_image(sensor, "sensor")
        check_device(sensor, self, "sensor")
        check_finite(sensor, "sensor")

    def reconstructor(self):
        """``reconstruct`` with the camera's nominal operator computed once, for inference on many
        tiles or scenes of one camera: ``fn(sensor, origin=(0, 0)) → cube``; ``fn.context_px`` is
        :attr:`context_px` (the halo :func:`~hsicam.engine.inference.reconstruct_tiled` takes by
        default). (A network given the camera itself would rebuild its PSF stack on every call.)
        Take a new one after the optics change. With Landweber steps, ``fn.before_steps(sensor, origin)`` (what
        comes before them; its ``context_px``) and ``fn.steps(sensor, x, origin, on_step)`` (the ``fn.steps.count``
        steps from x) too:
        :func:`~hsicam.engine.inference.reconstruct_tiled` tiles the first and takes the steps on the whole
        image, in bands, whose halo would otherwise grow with every step."""
        snap = getattr(self.camera, "snapshot", None)
        with torch.no_grad():
            op = snap(nominal=True) if callable(snap) else self.camera
            step_op = None
            if self.consistency_on:
                step_op = op if self.step_camera is None else self._step_operator()
                step_op = cut_psf(step_op, self.consistency.psf_energy)

        def fn(sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
            return self.reconstruct(sensor, origin, operator=op, step_operator=step_op)

        fn.context_px = int(self.net.context_px) if step_op is None else self._context_px(step_op, 1.0)
        fn.tileable = self.tileable
        if step_op is not None and self._landweber_iterations > 0:
            def before_steps(sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
                return self.reconstruct_before_steps(sensor, origin, operator=op, step_operator=step_op)

            def steps(sensor: torch.Tensor, x: torch.Tensor, origin: tuple[int, int] = (0, 0),
                      on_step=None) -> torch.Tensor:
                return self.landweber_steps(sensor, x, origin, step_operator=step_op, on_step=on_step)

            before_steps.context_px = self._context_before_steps_px(step_op, 1.0)
            steps.count = self._landweber_iterations
            steps.tv = self.consistency.tv_weight > 0  # (its memory: hsicam.engine.inference.reconstruction_memory_bytes)
            steps.frame_px = max(_half_reach(step_op))  # the margin its frame extends the image by (ditto)
            fn.before_steps, fn.steps = before_steps, steps
        return fn

    def forward(self, scene: torch.Tensor, generator: torch.Generator | None = None,
                measure=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``measure``: how the scene is imaged, ``fn(scene, generator) → (sensor, operator)``;
        default ``camera.measure`` (gradients reach the optics), e.g. ``camera.fixed_measure()``
        while the optics are fixed. The network alone: the consistency step is for inference, so
        training and its validation (which picks the best weights) never depend on it."""
        sensor, operator = (self.camera.measure if measure is None else measure)(scene, generator)
        return self.network(sensor, operator=operator), sensor

    def _step_operator(self):
        cam = self.camera if self.step_camera is None else self.step_camera
        snap = getattr(cam, "snapshot", None)
        with torch.no_grad():
            return snap(nominal=True) if callable(snap) else cam

    def _extension(self) -> str | None:
        """How the step extends the estimate across the window's border: as the camera makes the
        light the border pixels see from beyond the reconstructed area. ``valid``: real scene light,
        guessed by replication; ``same``: the camera's own padding (zeros: none; circular wraps
        around the whole image, which a tile cannot see: replication)."""
        cam = self.camera
        if getattr(cam, "boundary", "valid") == "valid":
            return "replicate"
        padding = getattr(cam, "padding", "zeros")
        return None if padding == "zeros" else ("reflect" if padding == "reflect" else "replicate")
