"""The network registry: ``model.kind`` → a builder ``(cfg, camera) -> network``.

A network module registers its builder with one decorator line::

    @register_network("rdn")
    def build_rdn(cfg, camera): ...

The builder gets the whole config (its settings are the section ``cfg.model.<kind>``) and the
camera, so physics-aware networks can use the camera's operator and sensor code.

Every network is an ``nn.Module`` with

- ``forward(sensor, camera, origin=(0, 0)) -> cube``: sensor (B, 1, H, W), ``origin`` the sensor
  pixel of this window's top-left corner (tiles of a larger image: the CFA phase depends on it),
  cube (B, C, H, W) on ``camera.bands``;
- ``context_px``: the per-side halo (sensor px) tiled inference needs so that tiles equal the
  whole image.
"""

from __future__ import annotations

from typing import Callable

from torch import nn

from hsicam.errors import ConfigError

Builder = Callable[..., nn.Module]
NETWORKS: dict[str, Builder] = {}


def register_network(kind: str) -> Callable[[Builder], Builder]:
    """Decorator: register ``builder(cfg, camera) -> nn.Module`` under ``model.kind = kind``."""

    def deco(builder: Builder) -> Builder:
        if kind in NETWORKS:
            raise ValueError(f"network kind {kind!r} is registered twice")
        NETWORKS[kind] = builder
        return builder

    return deco


def network_kinds() -> tuple[str, ...]:
    """The registered ``model.kind`` values, sorted."""
    return tuple(sorted(NETWORKS))


def check_network_kind(kind: str) -> None:
    """Raise :class:`ConfigError` naming the valid kinds unless ``kind`` is registered."""
    if kind not in NETWORKS:
        raise ConfigError(f"model.kind={kind!r} is unknown; choose one of {', '.join(network_kinds())}")


def build_network(cfg, camera) -> nn.Module:
    """The network ``cfg.model.kind`` describes, for ``camera``."""
    check_network_kind(cfg.model.kind)
    return NETWORKS[cfg.model.kind](cfg, camera)
