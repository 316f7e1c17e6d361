"""Cube files that ``hsicam reconstruct`` wrote: estimates, not scenes.

Reconstruct writes our HDF5 (metadata ``"command": "reconstruct"``) or an ENVI pair (description
:data:`ENVI_DESCRIPTIONS`), with an sRGB preview ``<stem>_rgb.png`` beside it. Reconstruct
recognises its own earlier output here (it replaces only that), and the dataset scan
(:func:`hsicam.data.datasets.list_scenes`) skips such files: an estimate saved into a data folder
must not become a training, validation or test scene.
"""

from __future__ import annotations

import json
from pathlib import Path

from hsicam.errors import InputError

#: Descriptions of the ENVI headers that reconstruct writes (``hsicam cube``: before it named itself,
#: also write_envi's default until session 23, so reconstruct's only with its preview beside it).
ENVI_DESCRIPTIONS = ("hsicam reconstruct", "hsicam cube")

def head(path: Path, n: int) -> bytes:
    """The first ``n`` bytes of ``path`` (b"" when it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError:
        return b""


def preview_beside(cube: Path) -> bool:
    """True when the preview reconstruct writes beside ``cube`` (``<stem>_rgb.png``) exists."""
    return cube.with_name(f"{cube.stem}_rgb.png").is_file()


def _h5_metadata(path: Path) -> dict | None:
    """The metadata of our HDF5 cube file ``path``, else None (another file, or unreadable)."""
    import h5py

    from hsicam.data.formats import _HDF5_MAGIC, HSICAM_FORMAT

    if not head(path, 8).startswith(_HDF5_MAGIC):
        return None
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != HSICAM_FORMAT or "cube" not in f:
                return None
            meta = json.loads(f.attrs.get("metadata_json", "{}"))
    except (OSError, ValueError, TypeError, KeyError):
        return None
    return meta if isinstance(meta, dict) else None


def is_reconstruct_h5(path: Path, legacy: bool = True) -> bool:
    """True for our HDF5 cube file written by reconstruct (its metadata names the command; with
    ``legacy``, also one from before it named itself: the capture and run, its preview beside it)."""
    meta = _h5_metadata(path)
    if meta is None:
        return False
    return meta.get("command") == "reconstruct" or (legacy and {"source", "run"} <= meta.keys() and preview_beside(path))


#: The metadata keys that only ``hsicam evaluate --save``'s estimate cubes hold (those written before they named the
#: command and their role too).
EVALUATE_ESTIMATE_KEYS = {"method", "run", "seed", "seeds_scored"}


def is_evaluate_estimate_h5(path: Path) -> bool:
    """True for an estimate cube that ``hsicam evaluate --save`` wrote (``cubes/NAME_estimate.h5``; its truth cube
    beside it is a scene): its metadata names the command and role, or holds :data:`EVALUATE_ESTIMATE_KEYS`."""
    meta = _h5_metadata(path)
    if meta is None:
        return False
    return (meta.get("command") == "evaluate" and meta.get("role") == "estimate") or EVALUATE_ESTIMATE_KEYS <= meta.keys()


def reconstruct_envi_header(path: Path) -> dict[str, str] | None:
    """The fields of an ENVI header that reconstruct wrote, else None."""
    from hsicam.data.formats import parse_envi_header

    if not head(path, 64).lstrip().startswith(b"ENVI") or path.stat().st_size > 1 << 20:
        return None
    try:
        h = parse_envi_header(path)
    except InputError:
        return None
    description = h.get("description", "").strip("{} ")
    if description == ENVI_DESCRIPTIONS[0]:
        return h
    return h if description in ENVI_DESCRIPTIONS[1:] and preview_beside(path) else None


def is_estimate(path: Path) -> bool:
    """True when the cube file ``path`` (an .h5, or an ENVI pair listed by its .hdr) is a
    reconstruction that hsicam reconstruct wrote, by what only reconstruct writes (its metadata's
    command, its header's description ``hsicam reconstruct``): the older forms, which a user's own
    ``write_cube_h5``/``write_envi`` file with a quick-look beside it also has, count as scenes. An estimate that
    ``hsicam evaluate --save`` wrote is one too (:func:`is_evaluate_estimate_h5`; its truth cube is a scene)."""
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return is_reconstruct_h5(path, legacy=False) or is_evaluate_estimate_h5(path)
    if suffix == ".hdr":
        h = reconstruct_envi_header(path)
        return h is not None and h.get("description", "").strip("{} ") == ENVI_DESCRIPTIONS[0]
    return False
