"""Camera + reconstruction network as one trainable module (the optics are part of the model)."""

from __future__ import annotations

import torch
from torch import nn

from hsicam.cameras import Camera, build_camera
from hsicam.errors import ConfigError
from hsicam.models.rdn import RDN


class CameraSystem(nn.Module):
    """Scene → simulated sensor image → reconstructed cube.

    ``forward(scene)`` returns ``(reconstruction, sensor)``; in ``valid`` mode both are smaller than
    the scene by ``camera.margin`` and aligned with :meth:`target` (the scene's centre crop).

    With ``code_input`` the network sees ``[g, κ_1 ⊙ g, …, κ_C ⊙ g]`` (1 + C channels) where κ is
    the camera's per-band sensor code (:meth:`Camera.sensor_code`, the CFA), instead of g alone.
    """

    def __init__(self, camera: Camera, net: nn.Module, code_input: bool = False) -> None:
        super().__init__()
        self.camera, self.net, self.code_input = camera, net, bool(code_input)
        self.autocast_dtype: torch.dtype | None = None  # e.g. torch.bfloat16 for the network on CUDA
        if self.code_input:
            try:
                camera.sensor_code(1, 1)
            except NotImplementedError as exc:
                raise ConfigError(f"model.code_input needs a camera with a per-band sensor code (the DOE camera's CFA): {exc}") from None

    @classmethod
    def from_config(cls, cfg) -> "CameraSystem":  # cfg: hsicam.config.Config
        camera = build_camera(cfg)
        m = cfg.model
        c = len(camera.bands)
        net = RDN(c, 1 + c if m.code_input else 1, m.blocks, m.features, m.growth, m.layers_per_block)
        return cls(camera, net, m.code_input)

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
        """(B, 1, H, W) sensor → what the network reads: itself, or [g, κ ⊙ g] (B, 1 + C, H, W).

        ``origin``: the sensor pixel of the window's top-left corner (for tiles of a larger image).
        """
        if not self.code_input:
            return sensor
        code = self.camera.sensor_code(sensor.shape[-2], sensor.shape[-1], origin).to(sensor.dtype)
        return torch.cat([sensor, sensor * code.unsqueeze(0)], dim=1)

    def reconstruct(self, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """Network only: sensor image (B, 1, H, W) → cube (B, C, H, W) (float32).

        ``origin``: the sensor pixel of the window's top-left corner (matters with ``code_input``).
        """
        inp = self.network_input(sensor, origin)
        if self.autocast_dtype is not None and sensor.device.type != "cpu":
            with torch.autocast(sensor.device.type, dtype=self.autocast_dtype):
                return self.net(inp).float()
        return self.net(inp)

    def forward(self, scene: torch.Tensor, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        sensor = self.camera(scene, generator)
        return self.reconstruct(sensor), sensor
