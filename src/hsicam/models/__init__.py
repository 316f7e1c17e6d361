"""Reconstruction networks, their registry, and the end-to-end camera + network system.

Network kinds register themselves (:mod:`hsicam.models.registry`); importing this package loads
the shipped ones (one import line per network module below).
"""

from hsicam.models import mosaic, rdn, unrolled  # noqa: F401  (each registers its model.kind)
from hsicam.models.rdn import RDN, RDNReconstructor, ResidualDenseBlock
from hsicam.models.registry import build_network, check_network_kind, network_kinds, register_network
from hsicam.models.system import CameraSystem

__all__ = ["RDN", "CameraSystem", "RDNReconstructor", "ResidualDenseBlock", "build_network", "check_network_kind",
           "network_kinds", "register_network"]
