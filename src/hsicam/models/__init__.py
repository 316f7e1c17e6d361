"""Reconstruction networks and the end-to-end camera + network system."""

from hsicam.models.rdn import RDN, ResidualDenseBlock
from hsicam.models.system import CameraSystem

__all__ = ["RDN", "CameraSystem", "ResidualDenseBlock"]
