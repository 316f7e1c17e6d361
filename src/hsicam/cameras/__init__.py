"""Camera forward models. Every camera is an ``nn.Module`` with ``A`` (noiseless, linear in the
scene), its exact adjoint ``A_adjoint``, and ``forward(x) = noise(A(x))``; it declares its noise
levels (:meth:`Camera.noise_levels`) and trainable parameter groups (:meth:`Camera.param_groups`).

Kinds are registered in :mod:`hsicam.cameras.registry`; importing this package registers the
shipped ones (one import line per camera module below).
"""

from hsicam.cameras.base import Camera
from hsicam.cameras.cassi import CodedAperture, DDCASSICamera, SDCASSICamera
from hsicam.cameras.doe_camera import DOECamera
from hsicam.cameras.measured import FixedPSFCamera
from hsicam.cameras.registry import build_camera, camera_kinds, check_camera_kind, register_camera

__all__ = ["Camera", "CodedAperture", "DDCASSICamera", "DOECamera", "FixedPSFCamera", "SDCASSICamera", "build_camera",
           "camera_kinds", "check_camera_kind", "register_camera"]
