"""Shipped pre-trained cameras: run folders that live inside the package.

Each shipped camera is a folder ``hsicam/resources/pretrained/NAME/`` holding what
:func:`hsicam.runs.folder.load_run` reads from a run folder, plus its model card::

    NAME/config.yaml          the run's resolved config
    NAME/model.safetensors    its weights (network + optics), at most MAX_WEIGHTS_BYTES
    NAME/card.json            machine-readable card (summary, bands, training, metrics, noise, limits)
    NAME/card.md              the same card for people
    NAME/camera_files.json    (a camera built from files) their SHA-256, and NAME/camera.doe.material.csv … their
                              copies, which its config.yaml names relative to NAME/ (:mod:`hsicam.runs.camera_files`)

Everywhere a run folder is accepted (``load_run``, every ``--run`` of the CLI), ``pretrained:NAME``
names a shipped camera (:func:`resolve_run`). The folders may sit in site-packages: they are
read-only, and :func:`check_not_pretrained` refuses them as outputs. Maintainers add a camera with
``hsicam pretrained pack`` (:mod:`hsicam.engine.pretrained`), which writes into the package's folder only from a
source checkout (an installed package needs its ``--dest``).

``HSICAM_PRETRAINED_DIR`` replaces the package's folder as the root of the shipped cameras (tests,
or a site's own collection).

A camera is used (:func:`resolve_run`) or copied (:func:`copy_pretrained`) only when its weights'
sha256 is the one its card records and the copies of its material tables or coded aperture hold the bytes its
camera_files.json records (:func:`check_weights`): the card's numbers are those of these files. A folder missing a
camera's files, or whose card.json does not parse, is not available (:func:`folder_problem`); ``hsicam pretrained
list`` reports it on its own line.
"""

from __future__ import annotations

import json
import os
import re
from importlib import resources
from pathlib import Path
from typing import Any

from hsicam.errors import InputError
from hsicam.io import nan_for_null
from hsicam.config import CAMERA_FILES_RECORD
from hsicam.runs.camera_files import COPY_NAMES, read_camera_files

#: Environment variable: another root folder of pre-trained cameras (instead of the package's).
ENV_VAR = "HSICAM_PRETRAINED_DIR"
#: The prefix of a run specification naming a shipped camera.
PREFIX = "pretrained:"
CARD_JSON = "card.json"
CARD_MD = "card.md"
#: The files of a shipped camera (what pack writes and copy copies; the linear consistency step's
#: filters, ``linear_step.safetensors``, when the camera has them; its material tables or coded aperture, with their
#: record, when its camera is built from files: :mod:`hsicam.runs.camera_files`).
FILES = ("config.yaml", "model.safetensors", "linear_step.safetensors", CARD_JSON, CARD_MD, CAMERA_FILES_RECORD, *COPY_NAMES)
#: The files a folder must hold to be a camera.
REQUIRED = ("config.yaml", "model.safetensors", CARD_JSON)
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


def missing_files(folder: Path) -> list[str]:
    """The camera files (:data:`REQUIRED`) that ``folder`` lacks."""
    return [f for f in REQUIRED if not (folder / f).is_file()]


def is_camera(folder: Path) -> bool:
    """True when ``folder`` holds a camera's files (config.yaml, model.safetensors and card.json)."""
    return folder.is_dir() and not folder.name.startswith(".") and not missing_files(folder)


def camera_folders(root_dir: str | Path | None = None) -> list[str]:
    """Sorted names of the folders in ``root_dir`` (default: :func:`root`) holding any of a camera's
    files (:data:`REQUIRED`): the cameras, usable or broken."""
    r = Path(root_dir) if root_dir is not None else root()
    if not r.is_dir():
        return []
    return sorted(p.name for p in r.iterdir()
                  if p.is_dir() and not p.name.startswith(".") and len(missing_files(p)) < len(REQUIRED))


def parse_card(folder: Path) -> tuple[dict[str, Any] | None, str | None]:
    """(card, None) for the camera ``folder`` whose card.json parses to an object, else (None, why)
    with why "not a packed camera (… missing)" or "unreadable model card (…)"."""
    missing = missing_files(folder)
    if missing:
        return None, f"not a packed camera ({', '.join(missing)} missing)"
    try:
        card = json.loads((folder / CARD_JSON).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        return None, f"unreadable model card ({getattr(exc, 'msg', None) or getattr(exc, 'strerror', None) or exc})"
    return (_scores(card), None) if isinstance(card, dict) else (None, "unreadable model card (not a JSON object)")


def _scores(card: dict[str, Any]) -> dict[str, Any]:
    """``card`` with its scores written as null (not finite: e.g. the SAM of validation patches with no light)
    read as NaN again (:func:`hsicam.io.nan_for_null`); a training log whose PSNR, SSIM and SAM are all null is
    that of a run without validation: they stay None, as the card wrote them."""
    metrics = card.get("metrics")
    log = metrics.get("training_log") if isinstance(metrics, dict) else None
    out = nan_for_null(card)
    if isinstance(log, dict) and all(log.get(k) is None for k in ("psnr", "ssim", "sam")):
        out["metrics"]["training_log"] = log
    return out


def folder_problem(folder: Path) -> str | None:
    """Why ``folder`` is not a usable camera (:func:`parse_card`), None when it is."""
    return parse_card(folder)[1]


def available(root_dir: str | Path | None = None) -> list[str]:
    """Sorted names of the usable cameras in ``root_dir`` (default: :func:`root`): their files are
    there and their card.json parses (:func:`folder_problem`)."""
    r = Path(root_dir) if root_dir is not None else root()
    return [n for n in camera_folders(r) if folder_problem(r / n) is None]


def broken(root_dir: str | Path | None = None) -> dict[str, str]:
    """{name: why} of the cameras in ``root_dir`` (default: :func:`root`) that are not usable."""
    r = Path(root_dir) if root_dir is not None else root()
    return {n: why for n in camera_folders(r) if (why := folder_problem(r / n)) is not None}


def check_name(name: str) -> str:
    """``name`` when it can name a camera folder (letters, digits, ``_ . -``), else :class:`InputError`."""
    if not _NAME_RE.match(name or ""):
        raise InputError(f"{name!r}: a pre-trained camera name is letters, digits, '_', '.' and '-' "
                         "(starting with a letter or digit)")
    return name


def pretrained_dir(name: str) -> Path:
    """The folder of the camera ``name`` when it holds a camera's files (its card and weights are
    not checked: :func:`check_weights`). One-line :class:`InputError` otherwise: a folder of that
    name that is not a packed camera says what it lacks; no folder lists the usable cameras (and
    names the broken ones apart: `hsicam pretrained list` says what is wrong with each)."""
    folder = root() / name
    if _NAME_RE.match(name or "") and folder.is_dir():
        missing = missing_files(folder)
        if not missing:
            return folder
        raise InputError(f"{folder}: not a packed camera ({', '.join(missing)} missing)")
    names, bad = available(), broken()
    problem = env_root_problem()
    have = ", ".join(names) if names else ("none is shipped" + (f" in {problem}" if problem else ""))
    if bad:
        have += f"; broken: {', '.join(bad)}"
    raise InputError(f"no pre-trained camera {name!r} (available: {have}; list them with `hsicam pretrained`)")


def is_spec(spec: str | Path) -> bool:
    """True for a run specification ``pretrained:NAME`` (a string, or a Path made from one)."""
    return str(spec).startswith(PREFIX)


def resolve_run(spec: str | Path) -> Path:
    """``pretrained:NAME`` → that camera's folder, its weights checked against its card
    (:func:`check_weights`); anything else → ``Path(spec)`` unchanged."""
    if is_spec(spec):
        return check_weights(pretrained_dir(str(spec)[len(PREFIX):]))
    return Path(spec)


def load_card(folder: Path) -> dict[str, Any]:
    """The parsed ``card.json`` of the camera ``folder``; one-line :class:`InputError` when it does not parse."""
    card, why = parse_card(folder)
    if card is None:
        raise InputError(f"{folder if missing_files(folder) else folder / CARD_JSON}: {why}")
    return card


def read_card(name: str) -> dict[str, Any]:
    """The parsed ``card.json`` of the shipped camera ``name``."""
    return load_card(pretrained_dir(name))


def _remedy(folder: Path) -> str:
    """What to do about a damaged camera ``folder``: re-install it (hsicam, for the package's own
    cameras, which only a source checkout re-packs in place) or re-pack it in place."""
    if folder.parent.resolve() == package_root().resolve():
        return (f"re-install hsicam, or in a source checkout re-pack it (`hsicam pretrained pack RUN --name "
                f"{folder.name} --force`)")
    return (f"re-pack it (`hsicam pretrained pack RUN --name {folder.name} --dest {folder.parent} --force`) or "
            "re-install it from where it came")


def weights_problem(folder: Path) -> str | None:
    """Why the weights of the camera ``folder`` cannot be used with its card: the card does not
    parse or records no sha256 of model.safetensors, or a file the card records (model.safetensors,
    and linear_step.safetensors when the card names it) is missing or has another sha256, or a file its
    camera was built from is (:func:`camera_files_problem`); None when they match."""
    try:
        card = load_card(folder)
    except InputError as exc:
        return f"{exc}; {_remedy(folder)}"
    from hsicam.io import file_sha256

    for key, name, required in (("weights", "model.safetensors", True), ("linear_step", "linear_step.safetensors", False)):
        recorded = card.get(key)
        want = recorded.get("sha256") if isinstance(recorded, dict) else None
        path = folder / name
        if not isinstance(want, str) or not want:
            if required or recorded is not None:
                return f"{folder / CARD_JSON}: records no sha256 of {name}, so {path} cannot be checked; {_remedy(folder)}"
            continue
        if not path.is_file():
            return f"{path}: missing (its card records it); {_remedy(folder)}"
        got = file_sha256(path)  # read once per process
        if got != want:
            return (f"{path}: does not match its card (sha256 {got[:12]}…, {CARD_JSON} records {want[:12]}…): the "
                    f"card describes other weights; {_remedy(folder)}")
    return camera_files_problem(folder)


def camera_files_problem(folder: Path) -> str | None:
    """Why the copies of the files the camera ``folder`` is built from (material tables, a coded aperture: its
    camera_files.json, :mod:`hsicam.runs.camera_files`) are not those it was packed with: the record does not
    parse, or a file it names (relative to ``folder``) is missing or has another sha256; None when they match or the
    camera names no file."""
    from hsicam.io import file_sha256

    try:
        record = read_camera_files(folder, _remedy(folder))
    except InputError as exc:
        return str(exc)
    for key, entry in sorted((record or {}).get("files", {}).items()):
        path = folder / str(entry.get("path") or "")
        if not path.is_file():
            return f"{path}: missing (the camera's {key}: its {CAMERA_FILES_RECORD} records it); {_remedy(folder)}"
        got, want = file_sha256(path), entry["sha256"]
        if got != want:
            return (f"{path}: does not match its {CAMERA_FILES_RECORD} (sha256 {got[:12]}…, recorded "
                    f"{want[:12]}…): not the {key} the camera was trained with; {_remedy(folder)}")
    return None


def check_weights(folder: Path) -> Path:
    """``folder`` when its weights are the ones its card records and its camera's files the ones its
    camera_files.json records (:func:`weights_problem`), else a one-line :class:`InputError`."""
    problem = weights_problem(folder)
    if problem:
        raise InputError(problem)
    return folder


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


def run_label(path: str | Path) -> str:
    """How output files name the run they came from, the one label of a run (``run`` in evaluate's
    results.json and saved cubes, reconstruct's cubes, psf.json, export-optics' spec.json, the
    report's camera heading): ``pretrained:NAME`` for a shipped camera, given as the spec or as its
    folder (which may lie in site-packages and means nothing on another machine), else the run
    folder's absolute path."""
    if is_spec(path):
        return str(path)
    if is_pretrained_path(path):
        return f"{PREFIX}{Path(path).resolve().name}"
    return str(Path(path).resolve())


def check_not_pretrained(path: str | Path, what: str = "output folder") -> None:
    """Refuse (one-line :class:`InputError`) an output that is a shipped camera: ``pretrained:NAME``,
    or a path inside a root of shipped cameras. They are read-only (they may sit in site-packages)."""
    if is_spec(path) or is_pretrained_path(path):
        raise InputError(f"{path}: pretrained cameras are read-only; use another {what}, or {READ_ONLY_HINT}")


def copy_pretrained(name: str, dest: str | Path) -> Path:
    """Copy the shipped camera ``name`` into the new run folder ``dest`` (absent or empty); weights
    that are not its card's are refused (:func:`check_weights`), nothing written.

    The copy is an ordinary, writable run folder (mode bits of the package files are not kept);
    it is written under a temporary name and renamed into place."""
    from hsicam.io import atomic_output, copy_file

    src = pretrained_dir(name)
    dest = Path(dest)
    check_not_pretrained(dest)
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise InputError(f"{dest}: exists and is not an empty folder; choose another DIR")
    check_weights(src)
    with atomic_output(dest, "dir", marker=False) as tmp:
        for f in FILES:
            if (src / f).is_file():
                copy_file(src / f, tmp / f)
    return dest
