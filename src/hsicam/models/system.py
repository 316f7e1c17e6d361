"""Camera + reconstruction network as one trainable module (the optics are part of the model)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from hsicam.cameras import Camera, build_camera
from hsicam.errors import ConfigError
from hsicam.models.rdn import RDN


def demosaic(sensor: torch.Tensor, code: torch.Tensor, window: int) -> torch.Tensor:
    """Per-band normalised local average of the coded sensor image (no learning).

    x̃_c = box(κ_c ⊙ g) / box(κ_c), a ``window``×``window`` box (odd; zero outside the image),
    i.e. the average of g over the neighbourhood weighted by how much each pixel's filter
    transmits band c. With selective filters this is a crude spectral estimate.

    Args:
        sensor: g, (B, 1, H, W).
        code: κ, (C, H, W) (the CFA over the same pixels).
    Returns:
        (B, C, H, W).
    """
    if window <= 1:
        return sensor * code.unsqueeze(0) / code.clamp_min(1e-6).unsqueeze(0)
    num = _box(sensor * code.unsqueeze(0), window)
    den = _box(code.unsqueeze(0), window)
    return num / den.clamp_min(1e-6)


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window``×``window`` box (zeros outside), as two 1-D passes: (B, C, H, W)."""
    r = window // 2
    x = F.avg_pool2d(x, (1, window), stride=1, padding=(0, r))
    return F.avg_pool2d(x, (window, 1), stride=1, padding=(r, 0))


class CameraSystem(nn.Module):
    """Scene → simulated sensor image → reconstructed cube.

    ``forward(scene)`` returns ``(reconstruction, sensor)``; in ``valid`` mode both are smaller than
    the scene by ``camera.margin`` and aligned with :meth:`target` (the scene's centre crop).

    With ``demosaic_input`` (beyond the paper) the network reads ``[g, x̃_1, …, x̃_C]`` (1 + C
    channels), where x̃ is :func:`demosaic` of g with the camera's per-band sensor code
    (:meth:`Camera.sensor_code`, the CFA) over one CFA period, instead of g alone; its tentative
    reconstruction then starts as x̃.
    """

    def __init__(self, camera: Camera, net: nn.Module, demosaic_input: bool = False) -> None:
        super().__init__()
        self.camera, self.net, self.demosaic_input = camera, net, bool(demosaic_input)
        self.autocast_dtype: torch.dtype | None = None  # e.g. torch.bfloat16 for the network on CUDA
        if self.demosaic_input:
            try:
                camera.sensor_code(1, 1)
            except NotImplementedError as exc:
                raise ConfigError(f"model.demosaic_input needs a camera with a per-band sensor code (the DOE camera's CFA): "
                                  f"{exc}; set model.demosaic_input=false") from None

    @classmethod
    def from_config(cls, cfg) -> "CameraSystem":  # cfg: hsicam.config.Config
        camera = build_camera(cfg)
        m = cfg.model
        c = len(camera.bands)
        net = RDN(c, 1 + c if m.demosaic_input else 1, m.blocks, m.features, m.growth, m.layers_per_block)
        if m.demosaic_input:
            net.start_from_input(list(range(1, 1 + c)))
        return cls(camera, net, m.demosaic_input)

    @property
    def demosaic_window(self) -> int:
        """Odd box width of the demosaic input: the CFA period (rounded up to odd)."""
        p = int(getattr(self.camera, "code_period", 1))
        return p if p % 2 else p + 1

    @property
    def context_px(self) -> int:
        """Pixels of sensor context each output pixel depends on, per side (halo for tiling)."""
        from hsicam.engine.inference import receptive_radius

        return receptive_radius(self.net) + (self.demosaic_window // 2 if self.demosaic_input else 0)

    @property
    def bands(self):
        return self.camera.bands

    def target(self, scene: torch.Tensor) -> torch.Tensor:
        """Ground truth aligned with the sensor: the centre crop in ``valid`` mode, else the scene."""
        if self.camera.boundary != "valid":
            return scene
        r = self.camera.margin // 2
        h, w = scene.shape[-2] - 2 * r, scene.shape[-1] - 2 * r
        return scene[..., r : r + h, r : r + w]

    def network_input(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """(B, 1, H, W) sensor → what the network reads: itself, or [g, x̃] (B, 1 + C, H, W).

        ``origin``: the sensor pixel of the window's top-left corner (for tiles of a larger image).
        """
        if not self.demosaic_input:
            return sensor
        code = self.camera.sensor_code(sensor.shape[-2], sensor.shape[-1], origin).to(sensor.dtype)
        return torch.cat([sensor, demosaic(sensor, code, self.demosaic_window)], dim=1)

    def reconstruct(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """Network only: sensor image (B, 1, H, W) → cube (B, C, H, W) (float32).

        ``origin``: the sensor pixel of the window's top-left corner (matters with ``demosaic_input``).
        """
        inp = self.network_input(sensor, origin)
        if self.autocast_dtype is not None and sensor.device.type != "cpu":
            with torch.autocast(sensor.device.type, dtype=self.autocast_dtype):
                return self.net(inp).float()
        return self.net(inp)

    def forward(self, scene: torch.Tensor, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        sensor = self.camera(scene, generator)
        return self.reconstruct(sensor), sensor
