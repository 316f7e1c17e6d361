"""Camera forward models. Every camera is an ``nn.Module`` with ``A`` (noiseless, linear in the
scene), its exact adjoint ``A_adjoint``, and ``forward(x) = noise(A(x))``."""

from hsicam.cameras.base import Camera
from hsicam.cameras.cassi import CodedAperture, DDCASSICamera, SDCASSICamera
from hsicam.cameras.doe_camera import DOECamera
from hsicam.errors import ConfigError

__all__ = ["Camera", "CodedAperture", "DDCASSICamera", "DOECamera", "SDCASSICamera", "build_camera"]


def build_camera(cfg) -> Camera:  # cfg: hsicam.config.Config
    """The camera ``cfg.camera.kind`` describes (the one factory every caller uses)."""
    kind = cfg.camera.kind
    if kind == "doe":
        return DOECamera.from_config(cfg)
    if kind == "dd_cassi":
        return DDCASSICamera.from_config(cfg)
    if kind == "sd_cassi":
        return SDCASSICamera.from_config(cfg)
    raise ConfigError(f"camera.kind={kind!r} is not available yet")
