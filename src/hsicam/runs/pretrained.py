"""Shipped pre-trained cameras: run folders that live inside the package.

Each shipped camera is a folder ``hsicam/resources/pretrained/NAME/`` holding what
:func:`hsicam.runs.folder.load_run` reads from a run folder, plus its model card::

    NAME/config.yaml          the run's resolved config
    NAME/model.safetensors    its weights (network + optics), at most MAX_WEIGHTS_BYTES
    NAME/card.json            machine-readable card (summary, bands, training, metrics, noise, limits)
    NAME/card.md              the same card for people

Everywhere a run folder is accepted (``load_run``, every ``--run`` of the CLI), ``pretrained:NAME``
names a shipped camera (:func:`resolve_run`). The folders may sit in site-packages: they are
read-only, and :func:`check_not_pretrained` refuses them as outputs. Maintainers add a camera with
``hsicam pretrained pack`` (:mod:`hsicam.engine.pretrained`).

``HSICAM_PRETRAINED_DIR`` replaces the package's folder as the root of the shipped cameras (tests,
or a site's own collection).
"""

from __future__ import annotations

import json
import os
import re
import shutil
from importlib import resources
from pathlib import Path
from typing import Any

from hsicam.errors import InputError

#: Environment variable: another root folder of pre-trained cameras (instead of the package's).
ENV_VAR = "HSICAM_PRETRAINED_DIR"
#: The prefix of a run specification naming a shipped camera.
PREFIX = "pretrained:"
CARD_JSON = "card.json"
CARD_MD = "card.md"
#: The files of a shipped camera (what pack writes and copy copies; the linear consistency step's
#: filters, ``linear_step.safetensors``, when the camera has them).
FILES = ("config.yaml", "model.safetensors", "linear_step.safetensors", CARD_JSON, CARD_MD)
#: Largest weights file a shipped camera may have (bytes; 20 MB).
MAX_WEIGHTS_BYTES = 20_000_000
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
READ_ONLY_HINT = "copy it with `hsicam pretrained copy NAME DIR` to get a writable run folder"


def package_root() -> Path:
    """The package's own folder of shipped cameras (it may not exist when none is shipped)."""
    return Path(str(resources.files("hsicam").joinpath("resources", "pretrained")))


def root() -> Path:
    """The folder of shipped cameras: ``$HSICAM_PRETRAINED_DIR`` if set, else the package's."""
    env = os.environ.get(ENV_VAR)
    return Path(env).expanduser() if env else package_root()


def env_root_problem() -> str | None:
    """What is wrong with ``$HSICAM_PRETRAINED_DIR`` when it is set to something that is not a
    folder (it would otherwise read as "no camera is shipped", hiding the package's own cameras):
    the variable, what it names, and that unsetting it gives the shipped cameras; None when unset
    or a folder."""
    env = os.environ.get(ENV_VAR)
    if not env or Path(env).expanduser().is_dir():
        return None
    shipped = available(package_root())
    what = "a folder that does not exist" if not Path(env).expanduser().exists() else "not a folder"
    return (f"{ENV_VAR}={env}, {what}; unset {ENV_VAR} for the cameras shipped with hsicam "
            f"({', '.join(shipped) if shipped else 'none'}), or set it to a folder of packed cameras")


def is_camera(folder: Path) -> bool:
    """True when ``folder`` holds a camera (config.yaml, model.safetensors and card.json)."""
    return (folder.is_dir() and not folder.name.startswith(".")
            and all((folder / f).is_file() for f in ("config.yaml", "model.safetensors", CARD_JSON)))


def available(root_dir: str | Path | None = None) -> list[str]:
    """Sorted names of the shipped cameras (folders holding config.yaml, model.safetensors and
    card.json) in ``root_dir`` (default: :func:`root`)."""
    r = Path(root_dir) if root_dir is not None else root()
    if not r.is_dir():
        return []
    return sorted(p.name for p in r.iterdir() if is_camera(p))


def check_name(name: str) -> str:
    """``name`` when it can name a camera folder (letters, digits, ``_ . -``), else :class:`InputError`."""
    if not _NAME_RE.match(name or ""):
        raise InputError(f"{name!r}: a pre-trained camera name is letters, digits, '_', '.' and '-' "
                         "(starting with a letter or digit)")
    return name


def pretrained_dir(name: str) -> Path:
    """The folder of the shipped camera ``name``; one-line :class:`InputError` listing the names otherwise."""
    names = available()
    if name not in names:
        problem = env_root_problem()
        have = ", ".join(names) if names else ("none is shipped" + (f" in {problem}" if problem else ""))
        raise InputError(f"no pre-trained camera {name!r} (available: {have}; list them with `hsicam pretrained`)")
    return root() / name


def is_spec(spec: str | Path) -> bool:
    """True for a run specification ``pretrained:NAME`` (a string, or a Path made from one)."""
    return str(spec).startswith(PREFIX)


def resolve_run(spec: str | Path) -> Path:
    """``pretrained:NAME`` → that camera's folder; anything else → ``Path(spec)`` unchanged."""
    if is_spec(spec):
        return pretrained_dir(str(spec)[len(PREFIX):])
    return Path(spec)


def read_card(name: str) -> dict[str, Any]:
    """The parsed ``card.json`` of the shipped camera ``name``."""
    path = pretrained_dir(name) / CARD_JSON
    try:
        card = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable model card ({getattr(exc, 'msg', None) or exc})") from None
    if not isinstance(card, dict):
        raise InputError(f"{path}: unreadable model card (not a JSON object)")
    return card


def summary(name: str) -> str:
    """The one-line summary of the shipped camera ``name`` (from its card)."""
    lines = str(read_card(name).get("summary") or "").splitlines()
    return lines[0] if lines else ""


def is_pretrained_path(path: str | Path) -> bool:
    """True when ``path`` lies inside a root of shipped cameras (the package's or ``$HSICAM_PRETRAINED_DIR``)."""
    try:
        p = Path(path).expanduser().resolve()
    except (OSError, RuntimeError):
        return False
    for r in {package_root(), root()}:
        try:
            r = r.resolve()
        except (OSError, RuntimeError):
            continue
        if p == r or r in p.parents:
            return True
    return False


def check_not_pretrained(path: str | Path, what: str = "output folder") -> None:
    """Refuse (one-line :class:`InputError`) an output that is a shipped camera: ``pretrained:NAME``,
    or a path inside a root of shipped cameras. They are read-only (they may sit in site-packages)."""
    if is_spec(path) or is_pretrained_path(path):
        raise InputError(f"{path}: pretrained cameras are read-only; use another {what}, or {READ_ONLY_HINT}")


def copy_pretrained(name: str, dest: str | Path) -> Path:
    """Copy the shipped camera ``name`` into the new run folder ``dest`` (absent or empty).

    The copy is an ordinary, writable run folder (mode bits of the package files are not kept);
    it is written under a temporary name and renamed into place."""
    from hsicam.io import atomic_output

    src = pretrained_dir(name)
    dest = Path(dest)
    check_not_pretrained(dest)
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise InputError(f"{dest}: exists and is not an empty folder; choose another DIR")
    with atomic_output(dest, "dir", marker=False) as tmp:
        for f in FILES:
            if (src / f).is_file():
                shutil.copyfile(src / f, tmp / f)
    return dest
