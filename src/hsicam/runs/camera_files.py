"""The files a run's camera is built from: ``RUN/camera_files.json``.

A camera's config may name files (:data:`hsicam.config.CAMERA_FILE_KEYS`): a DOE, singlet or prism material table
(``wavelength_nm,n`` CSV) and a CASSI coded aperture (.npy). They are read again each time the run is loaded, so a
table edited after training changed the trained camera silently (its evaluation, its exported etch depths) under the
same config hash and weights. A new run records each one's SHA-256, written once, atomically, with its other first
files (:func:`hsicam.engine.loop.fit`; a fine-tuned run, whose camera is its source run's, records the same files)::

    {"files": {"camera.doe.material": {"path": "/abs/pmma.csv", "sha256": "9f86d0…"}}}

:func:`check_camera_files` (:func:`hsicam.runs.folder.load_run`, a resume) refuses a run whose file is gone or holds
other bytes, naming the key, the run and the path. A run without the record (older runs; built-in materials and
random masks, which name no file) is read as before. A packed camera (``hsicam pretrained pack``) carries a copy of
each file beside its config.yaml, which names it relative to the camera's folder (:func:`copy_name`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterable

from hsicam.config import CAMERA_FILE_KEYS, CAMERA_FILES_RECORD, camera_files, config_value
from hsicam.errors import InputError
from hsicam.io import file_sha256, read_record, write_json


log = logging.getLogger(__name__)

def copy_name(key: str, path: str) -> str:
    """The name a packed camera gives its copy of the file ``path`` of ``key``: the key, then the file's suffix
    (``camera.doe.material.csv``)."""
    return key + Path(path).suffix.lower()


#: The names a packed camera's copies of its files may have (:func:`copy_name`: a mask is a .npy, a table a .csv).
COPY_NAMES = tuple(copy_name(k, "file.npy" if k.endswith("mask_file") else "file.csv") for k in CAMERA_FILE_KEYS)


def _unreadable(exc: OSError) -> str:
    """Why a camera file could not be hashed, in words."""
    return "no such file" if isinstance(exc, FileNotFoundError) else f"cannot be read ({exc.strerror or exc})"


def _sha256(where: str, path: str) -> str:
    """SHA-256 of the file ``path``; one-line InputError beginning with ``where`` (the key) when it cannot be read."""
    try:
        return file_sha256(path)
    except OSError as exc:
        raise InputError(f"{where}: {_unreadable(exc)}") from None


def camera_files_record(cfg) -> dict[str, Any] | None:
    """The record of the files the camera of ``cfg`` (a :class:`~hsicam.config.Config`) is built from, as they are
    now; None when it names none."""
    files = camera_files(cfg)
    if not files:
        return None
    return {"files": {k: {"path": p, "sha256": _sha256(f"{k}: {p}", p)} for k, p in files.items()}}


def write_camera_files(run_dir: str | Path, record: dict[str, Any]) -> None:
    """``RUN/camera_files.json``, atomically."""
    write_json(Path(run_dir) / CAMERA_FILES_RECORD, record)


def read_camera_files(run_dir: str | Path, advice: str = "restore it from a copy of the run") -> dict[str, Any] | None:
    """The run's record; None when it has none (an older run, or a camera of built-in materials); one-line
    :class:`InputError` when it cannot be read, ending with ``advice``."""
    def valid(record: Any) -> bool:
        files = record.get("files") if isinstance(record, dict) else None
        return isinstance(files, dict) and all(isinstance(e, dict) and isinstance(e.get("sha256"), str)
                                               for e in files.values())

    return read_record(Path(run_dir) / CAMERA_FILES_RECORD, valid, advice)


def check_camera_files(run_dir: str | Path, cfg, overridden: Iterable[str] = ()) -> None:
    """One-line :class:`InputError` unless each file the run's record names holds the bytes its camera was trained
    with, at the path ``cfg`` (the config the run is loaded with) names for its key: gone (naming the key, the run and
    the path), or other bytes (edited or replaced since training). A key of ``overridden`` (``--set`` on the command
    line: a what-if asked for by name) may name another file: a warning says it is not the trained camera's. Without a
    record (a run from before session 75) nothing is checked; a file it names relative is read against the current
    folder, which is said (once per run and process: a resume then writes that folder's file into config.yaml)."""
    record = read_camera_files(run_dir)
    if record is None:
        _warn_of_relative_files(run_dir, cfg)
        return
    overridden = set(overridden)
    for key, entry in sorted(record["files"].items()):
        try:
            path = config_value(cfg, key)
        except AttributeError:  # a key this hsicam does not know: nothing reads it
            continue
        asked = key in overridden
        if not isinstance(path, str) or path == "fused_silica":  # no file there: a built-in material, a random mask
            if asked:
                log.warning("--set %s=%s: not the file %s's camera was trained with (%s in its %s); the camera is not "
                            "the trained one", key, path, run_dir, Path(entry.get("path", "?")).name,
                            CAMERA_FILES_RECORD)
            continue
        now = _sha256(f"--set {key}={path}", path) if asked else _recorded_file(run_dir, key, path, entry)
        if now == entry["sha256"]:
            continue
        if asked:
            log.warning("--set %s=%s: not the file %s's camera was trained with (its %s: sha256 %s…, this one %s…); "
                        "the camera is not the trained one", key, path, run_dir, CAMERA_FILES_RECORD, entry["sha256"][:12],
                        now[:12])
            continue
        raise InputError(f"{run_dir}: {key}: {path} has changed since the run's camera was trained with it (sha256 "
                         f"{now[:12]}… now, {entry['sha256'][:12]}… in its {CAMERA_FILES_RECORD}): the trained camera is the "
                         "one of the file as it was; restore it, or train again")


_RELATIVE_WARNED: set[str] = set()


def _warn_of_relative_files(run_dir: str | Path, cfg) -> None:
    """Warn (once per run and process) of the camera files an older run's config names relative: read against the
    current folder, they may not be the ones it was trained with (nothing recorded their bytes)."""
    from hsicam.config import camera_files, is_absolute_anywhere

    relative = {k: p for k, p in camera_files(cfg).items() if not is_absolute_anywhere(p)}
    if not relative or str(run_dir) in _RELATIVE_WARNED:
        return
    _RELATIVE_WARNED.add(str(run_dir))
    log.warning("%s: its config.yaml names %s relative to where a command runs, read here as %s; the run (from "
                "before session 75) records no checksum of them: if they are not the files it was trained with, give "
                "their absolute paths in its config.yaml", run_dir, ", ".join(f"{k}={p}" for k, p in relative.items()),
                ", ".join(str(Path(p).absolute()) for p in relative.values()))


def _recorded_file(run_dir: str | Path, key: str, path: str, entry: dict[str, Any]) -> str:
    """SHA-256 of the run's recorded file ``path``; InputError naming the key, the run and the path when it is gone."""
    try:
        return file_sha256(path)
    except OSError as exc:
        raise InputError(f"{run_dir}: {key}: {path}: {_unreadable(exc)}; the run's camera was built from it (sha256 "
                         f"{entry['sha256'][:12]}… in its {CAMERA_FILES_RECORD}): restore it there, or give {key} its new "
                         f"place in {Path(run_dir) / 'config.yaml'} (its SHA-256 is checked), or train again") from None


__all__ = ["COPY_NAMES", "camera_files_record", "check_camera_files", "copy_name",
           "read_camera_files", "write_camera_files"]
