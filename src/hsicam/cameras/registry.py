"""The camera registry: ``camera.kind`` → the class that builds that camera from a config.

A camera module registers its class with one decorator line::

    @register_camera("dd_cassi")
    class DDCASSICamera(Camera): ...

and :func:`build_camera` (the one factory every caller uses: training, evaluation, CLI, tests)
looks the kind up. The contract tests (``tests/cameras/test_camera_contract.py``) run over
:func:`camera_kinds`, so a new camera is tested without editing a test.
"""

from __future__ import annotations

from typing import Callable, TypeVar

from hsicam.errors import ConfigError

T = TypeVar("T")

CAMERAS: dict[str, type] = {}


def register_camera(kind: str) -> Callable[[T], T]:
    """Class decorator: register a :class:`~hsicam.cameras.base.Camera` subclass under ``kind``.

    The class needs ``from_config(cfg) -> camera``; its ``kind`` attribute is set to ``kind``.
    """

    def deco(cls: T) -> T:
        if kind in CAMERAS:
            raise ValueError(f"camera kind {kind!r} is registered twice ({CAMERAS[kind].__name__}, {cls.__name__})")
        CAMERAS[kind] = cls
        cls.kind = kind  # type: ignore[attr-defined]
        return cls

    return deco


def camera_kinds() -> tuple[str, ...]:
    """The registered ``camera.kind`` values, sorted."""
    return tuple(sorted(CAMERAS))


def check_camera_kind(kind: str) -> None:
    """Raise :class:`ConfigError` naming the valid kinds unless ``kind`` is registered."""
    if kind not in CAMERAS:
        raise ConfigError(f"camera.kind={kind!r} is unknown; choose one of {', '.join(camera_kinds())}")


def build_camera(cfg):  # cfg: hsicam.config.Config -> Camera
    """The camera ``cfg.camera.kind`` describes."""
    check_camera_kind(cfg.camera.kind)
    return CAMERAS[cfg.camera.kind].from_config(cfg)
