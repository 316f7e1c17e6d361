"""Camera forward models. Every camera is an ``nn.Module`` with ``A`` (noiseless, linear in the
scene), its exact adjoint ``A_adjoint``, and ``forward(x) = noise(A(x))``."""

from hsicam.cameras.base import Camera
from hsicam.cameras.doe_camera import DOECamera

__all__ = ["Camera", "DOECamera"]
