"""The network registry: ``model.kind`` → a builder ``(cfg, camera) -> network``.

A network module registers its builder with one decorator line::

    @register_network("rdn", parameters=rdn_parameter_count, sizes=("blocks", "features", ...))
    def build_rdn(cfg, camera): ...

The builder gets the whole config (its settings are the section ``cfg.model.<kind>``) and the
camera, so physics-aware networks can use the camera's operator and sensor code. ``parameters``
(same arguments; required, so that no kind is built unchecked) is the closed-form count of the
network's parameters, declared next to the builder (tests hold it equal to the built network's);
``sizes`` (required) are the keys of the section that set it. :func:`build_network` refuses a network whose
weights do not fit the memory budget before the builder allocates anything
(``model.rdn.features=1000000000`` asked for 250 GB), and training
(:class:`hsicam.engine.tasks.SystemTask`) one whose training does not (:func:`check_network_memory`).
The Choi prior, not a ``model.kind``, is held to the same check (:func:`check_parameter_memory`).

Every network is an ``nn.Module`` with

- ``forward(sensor, camera, origin=(0, 0)) -> cube``: sensor (B, 1, H, W), ``origin`` the sensor
  pixel of this window's top-left corner (tiles of a larger image: the CFA phase depends on it),
  cube (B, C, H, W) on ``camera.bands``;
- ``context_px``: the per-side halo (sensor px) tiled inference needs so that tiles equal the
  whole image.
"""

from __future__ import annotations

import logging

from dataclasses import dataclass
from typing import Any, Callable, Sequence, Union

from torch import nn

from hsicam.config import config_value
from hsicam.errors import ConfigError
from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes

Builder = Callable[..., nn.Module]
#: ``parameters(cfg, camera) -> int``: how many parameters the builder's network has.
ParameterCount = Callable[..., int]
#: The keys of ``model.<kind>`` that set the size, or ``(settings) -> keys`` when they depend on them.
SizeKeys = Union[Sequence[str], Callable[[Any], Sequence[str]]]

#: Bytes per float32 parameter while it trains: the weight, its gradient and Adam's two moments.
TRAINING_BYTES_PER_PARAMETER = 4 * 4
#: Bytes per float32 parameter of a network that only reconstructs (evaluate, reconstruct, export).
WEIGHT_BYTES_PER_PARAMETER = 4


@dataclass(frozen=True)
class NetworkKind:
    """A registered ``model.kind``: its builder, its parameter count and the keys that size it."""

    build: Builder
    parameters: ParameterCount
    sizes: SizeKeys


log = logging.getLogger(__name__)

NETWORKS: dict[str, NetworkKind] = {}


def register_network(kind: str, *, parameters: ParameterCount, sizes: SizeKeys) -> Callable[[Builder], Builder]:
    """Decorator: register ``builder(cfg, camera) -> nn.Module`` under ``model.kind = kind``, with
    ``parameters(cfg, camera) -> int``, its exact parameter count (required: without it a network
    would be built unchecked), and ``sizes``, the keys of ``model.<kind>`` that set it (required and not
    empty: the refusal of a network too large names them); see the module docstring."""
    if not callable(parameters):
        raise TypeError(f"register_network({kind!r}): parameters must be the network's parameter count "
                        f"(cfg, camera) -> int, got {parameters!r}")
    if not callable(sizes) and (isinstance(sizes, str) or not sizes):
        raise TypeError(f"register_network({kind!r}): sizes must name the keys of model.{kind} that set the "
                        f"network's size (a sequence of them, or (settings) -> keys), got {sizes!r}")

    def deco(builder: Builder) -> Builder:
        if kind in NETWORKS:
            raise ValueError(f"network kind {kind!r} is registered twice")
        NETWORKS[kind] = NetworkKind(builder, parameters, sizes)
        return builder

    return deco


def network_kinds() -> tuple[str, ...]:
    """The registered ``model.kind`` values, sorted."""
    return tuple(sorted(NETWORKS))


def check_network_kind(kind: str) -> None:
    """Raise :class:`ConfigError` naming the valid kinds unless ``kind`` is registered."""
    if kind not in NETWORKS:
        raise ConfigError(f"model.kind={kind!r} is unknown; choose one of {', '.join(network_kinds())}")


def network_parameters(cfg, camera) -> int:
    """The parameter count of the network ``cfg.model.kind`` describes for ``camera`` (computed, not
    built)."""
    check_network_kind(cfg.model.kind)
    return int(NETWORKS[cfg.model.kind].parameters(cfg, camera))


def check_network_memory(cfg, camera, training: bool = True) -> int:
    """ConfigError, before anything is allocated, for a network whose training or, with ``training``
    false, whose weights alone (a trained run read for inference) need more than the memory budget
    (:func:`check_parameter_memory`), naming the keys of ``model.<kind>`` that size it. Returns the declared
    parameter count it checked."""
    n = network_parameters(cfg, camera)
    kind = cfg.model.kind
    # a kind registered outside hsicam has no section in ModelConfig (its settings are its builder's): None
    check_parameter_memory(n, f"model.kind={kind}: model.{kind}", getattr(cfg.model, kind, None), NETWORKS[kind].sizes,
                           len(camera.bands), training)
    return n


def check_parameter_memory(n: int, section: str, settings: Any, sizes: SizeKeys, bands: int,
                           training: bool = True) -> None:
    """ConfigError for a network of ``n`` parameters (``bands`` bands) whose training (weights, gradients
    and Adam's two moments: :data:`TRAINING_BYTES_PER_PARAMETER` bytes a parameter) or, with ``training``
    false, whose weights alone (:data:`WEIGHT_BYTES_PER_PARAMETER`) need more than the memory budget
    (:func:`hsicam.memory.memory_budget_bytes`): one line headed ``section`` that names the values of
    the keys ``sizes`` of ``settings`` (or ``sizes(settings)``) that set ``n`` (the keys alone where ``settings`` is None: a
    kind registered outside hsicam, whose settings are not in the config), the estimate and the
    budget. The one message of a network too large: registered networks
    (:func:`check_network_memory`) and the Choi prior (:func:`hsicam.models.priors.build_prior`)."""
    per = TRAINING_BYTES_PER_PARAMETER if training else WEIGHT_BYTES_PER_PARAMETER
    use = ("training needs", ": weight, gradient, Adam's two moments") if training else ("weights need", "")
    need, budget = per * n, memory_budget_bytes()
    if need <= budget:
        return
    keys = list(sizes(settings) if callable(sizes) else sizes)
    values = ", ".join(k if settings is None else f"{k}={_setting(settings, k)}" for k in keys)
    count = f"{n:,}" if n < 10**12 else f"{n:.3g}"
    raise ConfigError(f"{section} ({values}) is a network of {count} parameters for "
                      f"{bands} bands, whose {use[0]} {format_bytes(need)} ({per} bytes a parameter"
                      f"{use[1]}), more "
                      f"than the memory budget of {format_bytes(budget)}; make these sizes smaller, or raise "
                      f"{MEMORY_BUDGET_ENV} (MiB)")


def _setting(settings: Any, key: str) -> str:
    """The value of ``key`` (dotted, below ``settings``) as the config writes it."""
    settings = config_value(settings, key)
    return str(settings).lower() if isinstance(settings, bool) else str(settings)


def build_network(cfg, camera) -> nn.Module:
    """The network ``cfg.model.kind`` describes, for ``camera``; one whose weights do not fit the
    memory budget is refused before it is built (:func:`check_network_memory`; training checks its
    own larger need)."""
    declared = check_network_memory(cfg, camera, training=False)
    net = NETWORKS[cfg.model.kind].build(cfg, camera)
    built = sum(p.numel() for p in net.parameters())
    if declared != built:  # the memory checks before building trust the declared count
        log.warning("model.kind=%s declares %d parameters (its registered parameters function) but builds %d: the "
                    "memory checks made before building used %d; correct its parameters function",
                    cfg.model.kind, declared, built, declared)
    return net
