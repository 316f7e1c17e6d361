"""Training data: scene lists, scene-level splits, scene and patch datasets.

Any folder of supported files is a dataset (:func:`list_scenes`); the embedded synthetic set is
the default (:func:`hsicam.data.synthetic.synthetic_dataset`). Every cube is resampled onto the
camera's :class:`Bands` and normalised by :func:`hsicam.data.cube.normalize_per_cube_max` (the
single normalisation policy). Tensors are (C, H, W) float32, bands ascending.

:class:`PatchDataset` serves square patches of ``patch_px + margin_px`` pixels: the margin is what
the camera's ``valid`` convolution consumes (kernel_px − 1 pixels in total per axis), so the
sensor crop is ``patch_px`` wide. Patch positions and augmentations (flips, 90° rotations) are
drawn from a generator seeded by ``(seed, epoch, index[, stream])``, so a patch does not depend on which
DataLoader worker serves it and runs are reproducible.
"""

from __future__ import annotations

import logging
import math
import os
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from hsicam.data.cube import NEGATIVE_READ_ADVICE, normalize_per_cube_max, resample_cube
from hsicam.data.formats import _CAVE_RE, CUBE_NAMES, SCENE_SUFFIXES, _reading, holds_no_cube, read_cube
from hsicam.errors import InputError, negative_radiance_error
from hsicam.spectral import Bands

log = logging.getLogger(__name__)


def list_scenes(root: str | os.PathLike) -> list[Path]:
    """The scenes of a dataset folder, sorted: supported files and CAVE scene folders.

    ``root`` may also be a single file or a single CAVE folder. ENVI pairs are listed by their
    ``.hdr``. Linked sub-folders are followed (after the real ones; each folder is walked once, so a
    link loop ends), and a scene reached by several paths (a linked file or folder) is listed once,
    by its path without links when it has one; the aliases dropped are said in one log line. A scene file that
    is a link pointing nowhere (or round a loop) is refused, naming its target.
    Hidden and temporary files are skipped, and so are sub-folders that hold another
    hsicam command's completed output (a completion marker, :func:`hsicam.io.is_complete`: an
    evaluation saved next to the data, a simulated sensor image …) and cube files that ``hsicam
    reconstruct`` wrote (estimates, :func:`hsicam.data.estimates.is_estimate`), said once in the log; so are MAT and
    HDF5 files that hold no cube (:func:`hsicam.data.formats.holds_no_cube`: a download's ``meta.mat``, a calibration
    ``.h5`` of 2-D frames), counted in one warning, while one that may hold a cube under another name, two, or that
    cannot be read is listed and refused when read. A dataset hsicam generated (its ``manifest.json``) lists exactly the scenes of its manifest. A
    root that is (or lies inside) an ``evaluate`` output, or is any other command's output, is
    refused (:func:`check_not_an_output`). Raises :class:`InputError` when no scene is found.
    """
    root = Path(root)
    alone = _scene_alone(root)
    if alone is not None:
        return alone
    listed = _manifest_scenes(root)
    if listed is not None:
        return listed
    _check_not_partial_synthetic(root)
    found = _walk_dataset(root)
    scenes = _one_path_per_scene(root, sorted(set(found.scenes)), found.aliases)
    found.no_cube = [p for p in scenes if holds_no_cube(p)]
    scenes = [p for p in scenes if p not in found.no_cube]
    if found.skipped:
        _log_skipped(root, found.skipped)
    if found.estimates:
        log.warning("%s: skipped %s", root, _estimates_text(root, found.estimates))
    if found.unread and scenes:  # (none: the refusal below says them)
        _log_unread(root, found.unread)
    if found.no_cube and scenes:
        _log_once(_NO_CUBE_LOGGED, root, found.no_cube, logging.WARNING, _no_cube_text)
    if not scenes:
        raise _no_scenes_error(root, found)
    return scenes


def _scene_alone(root: Path) -> list[Path] | None:
    """``[root]`` when the dataset ``root`` is one scene (a file or a CAVE folder), None for a folder of scenes;
    InputError when it does not exist or is an hsicam output (:func:`check_not_an_output`)."""
    if not root.exists():
        raise InputError(f"{root}: no such dataset file or folder")
    check_not_an_output(root)
    if root.is_file() or _is_cave_dir(root):
        return [root]
    return None


@dataclass
class _Found:
    """What :func:`_walk_dataset` found below a dataset folder."""

    scenes: list[Path] = field(default_factory=list)  # scene files and CAVE folders, in walk order
    skipped: list[Path] = field(default_factory=list)  # sub-folders that hold an hsicam output
    estimates: list[Path] = field(default_factory=list)  # cube files that hsicam reconstruct wrote
    aliases: list[tuple[Path, Path]] = field(default_factory=list)  # (a link to what was listed already, that)
    unread: list[Path] = field(default_factory=list)  # files of a cube format hsicam does not read (UNREAD_CUBE_SUFFIXES)
    no_cube: list[Path] = field(default_factory=list)  # MAT/HDF5 files that hold no cube (formats.holds_no_cube)


def _walk_dataset(root: Path) -> _Found:
    """The scenes below the folder ``root`` (and what is not a scene): its real sub-folders first, then the linked
    ones (each folder walked once, by its (st_dev, st_ino), so a link loop ends)."""
    found = _Found()
    visited: dict[tuple[int, int], Path] = {}  # (st_dev, st_ino) of every folder walked
    links: list[Path] = []  # linked sub-folders, walked after the folders themselves
    starts = [root]
    while starts:
        start = starts.pop(0)
        key = _dir_key(start)
        if key is None:
            continue
        if key in visited:  # a link to a folder listed already (or a link loop)
            found.aliases.append((start, visited[key]))
            continue
        visited[key] = start
        for dirpath, dirnames, filenames in os.walk(start):  # links are not followed here: queued below
            d = Path(dirpath)
            dirnames[:] = _subfolders_to_walk(d, dirnames, visited, links, found)
            if d != root and _is_cave_dir(d):
                found.scenes.append(_cave_scene_root(d, root))
                dirnames[:] = []
                continue
            _add_scene_files(d, filenames, found)
        if not starts:
            starts, links = links, []
    return found


def _subfolders_to_walk(d: Path, dirnames: list[str], visited: dict[tuple[int, int], Path], links: list[Path],
                        found: _Found) -> list[str]:
    """The names of the sub-folders of ``d`` (``dirnames``) to walk into, sorted: not hidden, not an hsicam
    output (added to ``found.skipped``), not a link (queued on ``links``), not a folder walked already (each one
    kept is added to ``visited``)."""
    from hsicam.io import is_complete

    kept = []
    for n in sorted(dirnames):
        if n.startswith("."):
            continue
        if is_complete(d / n):  # an hsicam output, not scenes
            found.skipped.append(d / n)
            continue
        if (d / n).is_symlink():
            links.append(d / n)
            continue
        sub = _dir_key(d / n)
        if sub is None or sub in visited:  # unreadable, or a folder mounted twice
            continue
        visited[sub] = d / n
        kept.append(n)
    return kept


def _add_scene_files(d: Path, filenames: list[str], found: _Found) -> None:
    """Add the files of folder ``d`` (``filenames``) with a scene suffix to ``found.scenes``, or to
    ``found.estimates`` when hsicam reconstruct wrote them. InputError for one that is a symbolic link that cannot
    be followed (a scene file whose disk is not mounted, say)."""
    from hsicam.data.estimates import is_estimate
    from hsicam.io import broken_link_problem

    for name in filenames:
        if name.startswith("."):  # hidden files, including atomic-write temporaries
            continue
        if Path(name).suffix.lower() in SCENE_SUFFIXES:
            broken = broken_link_problem(d / name)
            if broken is not None:  # else listed, then refused as "no such file" without its target
                raise InputError(f"{d / name}: {broken} (remove the link, or restore what it points to)")
            (found.estimates if is_estimate(d / name) else found.scenes).append(d / name)
        elif Path(name).suffix.lower() in UNREAD_CUBE_SUFFIXES:
            found.unread.append(d / name)
        elif (d / name).is_symlink() and not (d / name).exists():
            # a link to a folder of scenes on a disk not mounted (os.walk lists it among the files): the folder's
            # scenes would be left out without a word
            log.warning("%s: %s: skipped (if it led to scenes, restore what it points to)", d / name,
                        broken_link_problem(d / name) or "a symbolic link that leads nowhere")


#: Suffixes of files that may hold a cube but that a dataset folder does not read as scenes (a multi-page TIFF, a
#: NumPy archive): the scan says it skipped them, as a folder of only such files is refused saying so.
UNREAD_CUBE_SUFFIXES = (".tif", ".tiff", ".npz")
#: (root, files) already logged by :func:`_log_unread` in this process.
_UNREAD_LOGGED: set[tuple[str, tuple[str, ...]]] = set()


def _unread_text(root: Path, unread: list[Path]) -> str:
    names = sorted(displayable_name(scene_path(p, root)) for p in unread)
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return (f"{len(names)} file(s) of a format not read as scenes ({shown}; a cube in one: save it as .h5 with its band "
            "list, hsicam.data.formats.write_cube_h5)")


def _log_unread(root: Path, unread: list[Path]) -> None:
    _log_once(_UNREAD_LOGGED, root, unread, logging.WARNING, _unread_text)


#: (root, files) already logged as holding no cube by :func:`list_scenes` in this process.
_NO_CUBE_LOGGED: set[tuple[str, tuple[str, ...]]] = set()


def _no_cube_text(root: Path, files: list[Path]) -> str:
    """What :func:`list_scenes` says of the MAT/HDF5 files of ``root`` that hold no cube (a dataset's ``meta.mat``,
    a calibration ``.h5``): how many, and the first few by name."""
    names = sorted(displayable_name(scene_path(p, root)) for p in files)
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    return (f"{len(names)} MAT/HDF5 file(s) that hold no hyperspectral cube ({shown}: no variable of a cube's name "
            f"({', '.join(CUBE_NAMES)}) and no numeric array with 3 or more axes longer than 1)")


def _no_scenes_error(root: Path, found: _Found) -> InputError:
    """The refusal of a dataset folder without scenes, saying what was skipped."""
    also = "; ".join(t for t in (_skipped_text(root, found.skipped) if found.skipped else "",
                                  _estimates_text(root, found.estimates) if found.estimates else "",
                                  _unread_text(root, found.unread) if found.unread else "",
                                  _no_cube_text(root, found.no_cube) if found.no_cube else "") if t)
    also = f" (skipped {also})" if also else ""
    return InputError(f"{root}: no hyperspectral scenes found (supported: {', '.join(SCENE_SUFFIXES)}, CAVE "
                      f"folders){also}")


def _dir_key(d: Path) -> tuple[int, int] | None:
    """(st_dev, st_ino) of folder ``d`` (links followed), or None when it cannot be read."""
    try:
        st = os.stat(d)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _one_path_per_scene(root: Path, scenes: list[Path], aliases: list[tuple[Path, Path]]) -> list[Path]:
    """``scenes`` (sorted) with one path per real file or folder: of the paths that lead to the same
    one, the one without links below ``root`` is kept, else the first. The dropped ones, and the
    linked folders in ``aliases`` (already listed), are said in one log line."""
    real_root = os.path.realpath(root)
    by_real: dict[str, list[Path]] = {}
    for p in scenes:
        by_real.setdefault(os.path.realpath(p), []).append(p)
    if all(len(group) == 1 for group in by_real.values()) and not aliases:
        return scenes

    def linked(p: Path) -> bool:  # reached through a link below root
        return os.path.realpath(p) != os.path.join(real_root, os.path.relpath(p, root))

    dropped = list(aliases)
    kept: set[Path] = set()
    for group in by_real.values():
        keep = min(group, key=lambda p: (linked(p), p))
        kept.add(keep)
        dropped += [(p, keep) for p in group if p != keep]
    if dropped:
        _log_aliases(root, dropped)
    return [p for p in scenes if p in kept]


#: (root, aliases) already logged by :func:`list_scenes` in this process.
_ALIASES_LOGGED: set[tuple[str, tuple[str, ...]]] = set()


def _log_aliases(root: Path, dropped: list[tuple[Path, Path]]) -> None:
    def rel(p: Path) -> str:
        return scene_path(p, root) if p != root else "."

    texts = sorted(f"{rel(a)} (= {rel(b)})" for a, b in dropped)
    key = (os.path.abspath(root), tuple(texts))
    if key in _ALIASES_LOGGED:
        return
    _ALIASES_LOGGED.add(key)
    shown = ", ".join(texts[:5]) + (f" and {len(texts) - 5} more" if len(texts) > 5 else "")
    log.warning("data: %s: %d link(s) lead to scenes listed already, each scene counted once: %s", root, len(texts),
                shown)


def scene_path(scene: str | os.PathLike, root: str | os.PathLike) -> str:
    """``scene`` relative to the dataset ``root`` it was listed from (:func:`list_scenes`), with ``/``
    separators (``day1/scene.h5``); its name when ``root`` is the scene itself (a file or a CAVE
    folder given alone) or does not hold it."""
    scene, root = Path(scene), Path(root)
    try:
        rel = Path(os.path.abspath(scene)).relative_to(os.path.abspath(root))
    except ValueError:
        return scene.name
    return rel.as_posix() if rel.parts else scene.name


def displayable_name(text: str) -> str:
    """``text`` (a file name from the file system) as text any writer takes: the bytes of a name that is not
    UTF-8 (an old Latin-1 ``sc\\xe8ne.h5``, which Python holds as lone surrogates) as ``\\xe8`` escapes; valid text
    unchanged. Such a name stopped an evaluation with "UnicodeEncodeError: surrogates not allowed"."""
    try:
        raw = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a lone surrogate that no byte maps to
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return raw.decode("utf-8", "backslashreplace")


#: What joins the folders of a scene's relative path in its name (``day1/scene.h5`` → ``day1__scene``).
SCENE_NAME_SEPARATOR = "__"


def scene_names(scenes: Sequence[str | os.PathLike], root: str | os.PathLike | None = None) -> list[str]:
    """One name per scene, all different, for results rows and saved cube files (``NAME_estimate.h5``).

    A scene is named by its stem (``scene_0010``; a CAVE folder ``balloons_ms``) unless another
    scene of the list has the same one (compared ignoring case, as a case-insensitive file system
    would when the cubes are saved): those scenes are named by their path relative to ``root``
    (default: their common folder; :func:`scene_path`), the suffix dropped and the folders joined by
    :data:`SCENE_NAME_SEPARATOR` (``day1/scene.h5`` → ``day1__scene``). Scenes that still share a name
    (``scene.h5`` beside ``scene.mat``) keep their suffix (``scene.h5``), and any left then get
    ``-2``, ``-3`` … in list order. A name that is not UTF-8 is given as :func:`displayable_name`."""
    paths = [Path(p) for p in scenes]
    if root is None:
        root = os.path.commonpath([os.path.abspath(p.parent) for p in paths]) if paths else "."

    def relative(p: Path, suffix: bool) -> str:
        rel = scene_path(p, root)
        if not suffix and not p.is_dir():
            rel = rel[: len(rel) - len(p.suffix)] if p.suffix else rel
        return displayable_name(rel.replace("/", SCENE_NAME_SEPARATOR))

    names = [displayable_name(p.stem) for p in paths]
    for rename in (lambda p: relative(p, False), lambda p: relative(p, True)):
        clash = _clashing(names)
        if not clash:
            return names
        names = [rename(p) if i in clash else n for i, (p, n) in enumerate(zip(paths, names))]
    taken: set[str] = set()
    for i, n in enumerate(names):  # last resort: number the ones left in list order
        name, k = n, 1
        while name.casefold() in taken:
            k += 1
            name = f"{n}-{k}"
        taken.add(name.casefold())
        names[i] = name
    return names


def _clashing(names: list[str]) -> set[int]:
    """Indices of the names that another name equals, ignoring case."""
    seen: dict[str, list[int]] = {}
    for i, n in enumerate(names):
        seen.setdefault(n.casefold(), []).append(i)
    return {i for group in seen.values() if len(group) > 1 for i in group}


def _estimates_text(root: Path, estimates: list[Path]) -> str:
    shown = ", ".join(str(p.relative_to(root)) for p in sorted(estimates)[:5])
    more = f" and {len(estimates) - 5} more" if len(estimates) > 5 else ""
    return f"{len(estimates)} cube file(s) that hsicam reconstruct wrote (estimates, not scenes): {shown}{more}"


def _manifest_scenes(root: Path) -> list[Path] | None:
    """The scenes a dataset that hsicam generated lists in its ``manifest.json`` (sorted), or None
    for another folder. Files beside them that it does not list are not its scenes (said in the
    log); a listed scene that is missing is an :class:`InputError`."""
    import json

    path = root / "manifest.json"
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
        ours = isinstance(manifest, dict) and manifest.get("format") == "hsicam-synthetic"
        files = [str(s["file"]) for s in manifest["scenes"]] if ours else None
    except (OSError, ValueError, KeyError, TypeError):
        return None  # not ours (or unreadable): the folder is scanned as any other
    if not files:
        return None
    scenes = sorted(root / f for f in files)
    missing = [p.name for p in scenes if not p.is_file()]
    if missing:
        raise InputError(f"{root}: {len(missing)} scene(s) its manifest.json lists are missing ({', '.join(missing[:5])}"
                         f"{' …' if len(missing) > 5 else ''}); generate the dataset again (delete the folder, or "
                         "`hsicam data synth` with its parameters)")
    listed = {os.path.realpath(p) for p in scenes}
    # every scene file or CAVE folder below it, sub-folders too (a folder of one's own scenes put inside a generated
    # set was left out without a word)
    extra = sorted(scene_path(p, root) for p in _walk_dataset(root).scenes
                   if os.path.realpath(p) not in listed and not holds_no_cube(p))
    if extra:
        log.warning("%s: a generated dataset: its %d scenes are those its manifest.json lists; not %s",
                    root, len(scenes), ", ".join(extra[:5]) + (" …" if len(extra) > 5 else ""))
    return scenes


def _check_not_partial_synthetic(root: Path) -> None:
    """InputError for a folder that holds fewer scene files than the synthetic set they belong to (no manifest: the
    validation scenes alone that ``hsicam evaluate`` generates, or a generation cut short;
    :func:`hsicam.data.synthetic.partial_set_size`); scenes copied into a folder of one's own are listed as any files.
    Listed as any folder, a partial set was a dataset of its few scenes, without a word (3 of 12 scenes scored, or
    trained on, as if they were the set)."""
    from hsicam.data.synthetic import partial_set_size

    size = partial_set_size(root)
    if size is not None:
        held, n = size
        raise InputError(f"{root}: holds {held} of the {n} scenes of a synthetic set (a partial set: the "
                         "validation scenes that hsicam evaluate generates, or a generation cut short), not a whole "
                         "dataset; `hsicam data synth` with the config that made it completes the set, or give a "
                         "folder of the scenes you mean")


def _skipped_text(root: Path, skipped: list[Path]) -> str:
    from hsicam.io import read_marker

    def one(p: Path) -> str:
        command = read_marker(p).get("command")
        return f"{p.relative_to(root)} ({command})" if isinstance(command, str) and command else str(p.relative_to(root))

    shown = ", ".join(one(p) for p in skipped[:5]) + (f" and {len(skipped) - 5} more" if len(skipped) > 5 else "")
    return f"{len(skipped)} sub-folder(s) holding hsicam outputs, not scenes: {shown}"


#: (root, skipped sub-folders) already logged by :func:`list_scenes` in this process.
_SKIPPED_LOGGED: set[tuple[str, tuple[str, ...]]] = set()


def _log_skipped(root: Path, skipped: list[Path]) -> None:
    _log_once(_SKIPPED_LOGGED, root, skipped, logging.INFO, _skipped_text)


def _log_once(logged: set[tuple[str, tuple[str, ...]]], root: Path, files: list[Path], level: int, text) -> None:
    """Log "data: ROOT: skipped TEXT" (``text(root, files)``) at ``level`` once per process for these ``files`` of
    ``root`` (``logged``: the registry of one kind of skipped file)."""
    key = (os.path.abspath(root), tuple(str(p) for p in files))
    if key in logged:
        return
    logged.add(key)
    log.log(level, "data: %s: skipped %s", root, text(root, files))


def check_not_an_output(root: str | os.PathLike) -> None:
    """InputError when the dataset ``root`` is not data but an hsicam output: the folder (or a file
    or folder inside it) of an ``evaluate``, whose ``cubes/`` hold a method's reconstructions
    (``*_estimate.h5``) beside the ground truths (``*_truth.h5``), not scenes to score — one
    ``*_truth.h5`` file named alone is accepted —, or a folder that carries the completion marker
    of any other command (a simulated sensor image, PSFs, a report …)."""
    from hsicam.io import is_complete, output_description, read_marker

    root = Path(root)
    full = Path(os.path.abspath(root))
    for a in (full, *full.parents):
        if not is_complete(a):
            continue
        if read_marker(a).get("command") == "evaluate":
            if root.is_file() and root.name.endswith("_truth.h5"):
                return  # one saved ground truth, named on purpose
            where = "is" if a == full else f"lies inside {_as_given(root, full, a)}, which is"
            raise InputError(f"{root}: {where} the output of hsicam evaluate{_evaluated_data(a)}; its "
                             "cubes/*_estimate.h5 are a method's reconstructions, not scenes: use the scenes it scored "
                             "as the data, or copy its *_truth.h5 files into a folder of their own")
        if a == full and root.is_dir():
            raise InputError(f"{root}: is {output_description(a)}, not a folder of scenes; use a folder of cube files "
                             "as the data")
        # (no return: that output may itself lie inside an evaluate's, e.g. its report/, which the folders above show)


def _as_given(root: Path, full: Path, ancestor: Path) -> Path:
    """``ancestor`` of ``full`` (= abspath(root)) written as the user wrote ``root`` when it can be."""
    p = root
    for _ in range(len(full.parts) - len(ancestor.parts)):
        p = p.parent
    return p if Path(os.path.abspath(p)) == ancestor else ancestor


def _evaluated_data(folder: Path) -> str:
    """`` (which scored DATA)``: the data an evaluation folder's results.json names, or ""."""
    import json

    try:
        data = json.loads((folder / "results.json").read_text(encoding="utf-8")).get("data")
    except (OSError, ValueError, AttributeError):
        return ""
    if not isinstance(data, str) or not data:
        return ""
    return f" (which scored {'the ' if data.startswith('synthetic') else ''}{data})"


def _is_cave_dir(d: Path) -> bool:
    return any(_CAVE_RE.match(f.name) for f in d.glob("*_ms_01.*"))


def _cave_scene_root(d: Path, root: Path) -> Path:
    # CAVE archives unpack as name_ms/name_ms/name_ms_01.png: list the outer folder once
    parent = d.parent
    if parent != root and parent.name == d.name:
        return parent
    return d


def split_scenes(scenes: Sequence[Path], val_fraction: float, seed: int = 0, pool: int | None = None
                 ) -> tuple[list[Path], list[Path]]:
    """Scene-level train/validation split, deterministic for a seed and the *set* of scenes.

    ``round(val_fraction * n)`` scenes (at least one when ``val_fraction > 0`` and n ≥ 2) go to
    validation; patches of one scene never appear in both sets. ``pool`` k: the split is drawn
    among the first k scenes (sorted by path, n = k) and every later scene trains, so a dataset
    grown beyond k scenes keeps its validation set.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise InputError(f"val_fraction must be in [0, 1), got {val_fraction}")
    ordered = sorted(Path(s) for s in scenes)
    if pool is not None and pool < len(ordered):
        train, val = split_scenes(ordered[:pool], val_fraction, seed)
        return train + ordered[pool:], val
    n = len(ordered)
    n_val = int(round(val_fraction * n))
    if val_fraction > 0 and n >= 2:
        n_val = max(n_val, 1)
    n_val = min(n_val, n - 1) if n > 0 else 0
    perm = np.random.default_rng([int(seed), 0x5E11]).permutation(n)
    val_idx = set(perm[:n_val].tolist())
    train = [s for i, s in enumerate(ordered) if i not in val_idx]
    val = [s for i, s in enumerate(ordered) if i in val_idx]
    return train, val


@dataclass(frozen=True)
class SceneInfo:
    """What a dataset needs to know about a scene before serving patches."""

    path: Path
    height: int
    width: int
    peak: float  # maximum after resampling onto the target bands (the normalisation divisor)


def probe_hsicam(path: Path, bands: Bands, *, allow_negative: bool = False) -> SceneInfo | None:
    """SceneInfo of an hsicam HDF5 file on ``bands`` that can be read window by window, else None.

    The header decides (no pixel read) whether the file qualifies; one that does has every pixel
    checked once per process (:func:`check_windowed_pixels`), and its ``peak`` is the checked maximum."""
    import h5py

    from hsicam.data.formats import HSICAM_FORMAT, _HDF5_MAGIC, _head, check_format_version

    if not path.is_file() or not _head(path, 8).startswith(_HDF5_MAGIC):
        return None
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != HSICAM_FORMAT or "cube" not in f or "max_value" not in f.attrs:
                return None
            check_format_version(path, f.attrs)  # a newer file: no windowed reads; the full reader refuses it
            shape, kind = f["cube"].shape, f["cube"].dtype.kind
            peak = float(f.attrs["max_value"])
    except (OSError, KeyError, TypeError, ValueError, InputError):
        return None  # the full reader reports the problem properly
    if len(shape) != 3 or min(shape) == 0 or kind not in "fiub" or not peak > 0:
        return None  # likewise (a wrong shape or type, a header that says all zeros)
    # only a file on the camera's bands as read_cube would leave it: the same centres and no camera band wider than
    # the file's own (those a whole read integrates: a window read as stored was other ground truth, session 72)
    from hsicam.data.formats import read_bands
    from hsicam.spectral import resolved_bands

    try:
        file_bands = read_bands(path)
    except InputError:
        return None
    if not file_bands.matches(bands) or resolved_bands(file_bands, bands).any():
        return None
    peak = check_windowed_pixels(path, allow_negative=allow_negative)
    return SceneInfo(path, int(shape[1]), int(shape[2]), peak)


#: Bytes of pixels read at a time by :func:`check_windowed_pixels` (whole bands, or rows of one band).
CHECK_CHUNK_BYTES = 64 * 2**20

#: (real path, size, mtime, allow_negative) → maximum of the files :func:`check_windowed_pixels` passed.
_PIXELS_CHECKED: dict[tuple[str, int, int, bool], float] = {}


def check_windowed_pixels(path: str | os.PathLike, *, allow_negative: bool = False,
                          chunk_bytes: int = CHECK_CHUNK_BYTES) -> float:
    """Check every pixel of an hsicam HDF5 file that is read window by window; returns its maximum
    (negative values clipped to 0 with ``allow_negative``), the normalisation divisor.

    The checks and one-line :class:`InputError` messages are a preloaded read's
    (:func:`hsicam.data.cube.check_cube`, :func:`hsicam.data.cube.normalize_per_cube_max`): NaN/Inf,
    negative values (refused, or clipped with ``allow_negative``), an all-zero cube. A ``max_value``
    attribute other than the maximum (beyond float32 rounding) is a warning and the maximum is used,
    as a preloaded read does. A scene whose 99.9th percentile is below 1 % of its maximum is warned
    about (:func:`warn_if_near_black`). Reads ``chunk_bytes`` at a time; a file passes once per
    process (until it changes)."""
    import h5py

    path = Path(path)
    st = path.stat()
    key = (os.path.realpath(path), st.st_size, st.st_mtime_ns, bool(allow_negative))
    if key in _PIXELS_CHECKED:
        return _PIXELS_CHECKED[key]
    bad = neg = 0
    lo, hi = math.inf, -math.inf
    with _reading(path, "HDF5"), h5py.File(path, "r") as f:
        ds = f["cube"]
        header = float(f.attrs["max_value"])
        top = _TopValues(math.prod(ds.shape))
        for chunk in _chunks(ds, chunk_bytes):
            with np.errstate(over="ignore"):  # values beyond float32 become Inf, as in a preloaded read
                chunk = np.asarray(chunk, dtype=np.float32)
            finite = np.isfinite(chunk)
            if not finite.all():
                bad += int(chunk.size - np.count_nonzero(finite))
            if bad:
                continue  # the count is all that is reported now
            lo = min(lo, float(chunk.min()))
            if lo < 0:
                neg += int(np.count_nonzero(chunk < 0))
                np.maximum(chunk, 0.0, out=chunk)
            hi = max(hi, float(chunk.max()))
            top.add(chunk)
    if bad:
        raise InputError(f"{path}: {bad} NaN/Inf value(s) in the cube (after conversion to float32)")
    if neg and not allow_negative:
        raise negative_radiance_error(path, neg, lo, NEGATIVE_READ_ADVICE)
    if not hi > 0:
        raise InputError(f"{path}: the cube is all zeros; cannot normalise by its maximum")
    if not math.isclose(header, hi, rel_tol=2.0 ** -22):  # float32 rounding of a maximum written as float64
        log.warning("%s: its max_value attribute %.6g is not the cube's maximum %.6g; normalising by the maximum",
                    path, header, hi)
    warn_if_near_black(path, top.percentile(), hi)
    _PIXELS_CHECKED[key] = hi
    return hi


def _chunks(ds: Any, chunk_bytes: int) -> Iterator[np.ndarray]:
    """The (C, H, W) dataset ``ds`` in pieces of about ``chunk_bytes``: whole bands, else rows of a band."""
    c, h, w = ds.shape
    band = h * w * max(ds.dtype.itemsize, 4)
    if band <= chunk_bytes:
        step = max(chunk_bytes // band, 1)
        for c0 in range(0, c, step):
            yield ds[c0:c0 + step]
        return
    rows = max(chunk_bytes // (w * max(ds.dtype.itemsize, 4)), 1)
    for ci in range(c):
        for r0 in range(0, h, rows):
            yield ds[ci, r0:r0 + rows]


#: A scene is near-black after normalisation when this percentile of its values …
NEAR_BLACK_PERCENTILE = 99.9
#: … is below this fraction of its maximum (one hot or saturated pixel sets the maximum).
NEAR_BLACK_FRACTION = 0.01


class _TopValues:
    """The largest values of ``n`` seen chunk by chunk, enough for :data:`NEAR_BLACK_PERCENTILE`
    exactly as ``numpy.percentile`` (linear) computes it."""

    def __init__(self, n: int) -> None:
        self.index = NEAR_BLACK_PERCENTILE / 100.0 * max(n - 1, 0)
        self.keep = max(n - int(math.floor(self.index)), 1)  # the values at and above the lower rank
        self.values = np.empty(0, np.float32)

    def add(self, chunk: np.ndarray) -> None:
        v = chunk.ravel()
        if self.values.size >= self.keep:
            v = v[v > self.values[0]]  # values[0]: the smallest kept (kept partitioned)
        if v.size > self.keep:
            v = np.partition(v, v.size - self.keep)[v.size - self.keep:]
        v = np.concatenate([self.values, v])
        if v.size > self.keep:
            v = np.partition(v, v.size - self.keep)[v.size - self.keep:]
        else:
            v = np.partition(v, 0) if v.size else v
        self.values = v

    def percentile(self) -> float:
        v = np.sort(self.values)
        if not v.size:
            return 0.0
        frac = self.index - math.floor(self.index)
        return float(v[0]) + frac * (float(v[min(1, v.size - 1)]) - float(v[0]))


#: Real paths of the scenes :func:`warn_if_near_black` warned about in this process.
_NEAR_BLACK_WARNED: set[str] = set()


def near_black_percentile(cube: np.ndarray) -> float | None:
    """The :data:`NEAR_BLACK_PERCENTILE` of ``cube``'s values when it is below
    :data:`NEAR_BLACK_FRACTION` of its maximum (after normalisation: of 1), else None."""
    peak = float(cube.max())
    if not peak > 0:
        return None
    top = _TopValues(cube.size)
    if np.count_nonzero(cube >= NEAR_BLACK_FRACTION * peak) >= top.keep:
        return None  # the percentile's lower rank is at or above the threshold already
    top.add(cube)
    p = top.percentile()
    return p if p < NEAR_BLACK_FRACTION * peak else None


def warn_if_near_black(path: str | os.PathLike, percentile: float | None, peak: float) -> None:
    """Warn once per scene when its :data:`NEAR_BLACK_PERCENTILE` (``percentile``, in the units of
    ``peak``, its maximum) is below :data:`NEAR_BLACK_FRACTION` of the maximum."""
    if percentile is None or not peak > 0 or percentile >= NEAR_BLACK_FRACTION * peak:
        return
    key = os.path.realpath(path)
    if key in _NEAR_BLACK_WARNED:
        return
    _NEAR_BLACK_WARNED.add(key)
    log.warning("%s: its %gth percentile %.4g is %.2g%% of its maximum %.4g: normalised by that maximum (a hot or "
                "saturated pixel?) the scene is nearly black; clip or remove such pixels", path,
                NEAR_BLACK_PERCENTILE, percentile, 100.0 * percentile / peak, peak)


#: How to give a ``.npy`` cube's band grid (the file carries none), ending the refusal of a grid
#: that does not fit the camera's; a command without ``--set`` passes its own (``npy_bands_advice``).
NPY_BANDS_ADVICE = "give its grid with data.npy_bands, e.g. data.npy_bands={start_nm: ..., stop_nm: ..., step_nm: ...}"


class SceneDataset(Dataset):
    """Whole scenes on ``bands``, normalised: item i is a float32 tensor (C, H, W) in [0, 1].

    ``preload=True`` reads every scene once (at construction) and keeps it in memory — DataLoader
    workers started by fork share it. Otherwise an LRU cache of ``cache_size`` scenes per process
    is used, and hsicam HDF5 files on the same band grid are read window by window.
    ``source_bands`` gives the grid for files that carry none (``.npy``). ``dataset_paths``: every file of the
    dataset ``scenes`` were drawn from (e.g. both splits; default ``scenes``), whose band ranges a refusal names.
    """

    def __init__(self, scenes: Sequence[str | os.PathLike], bands: Bands, *, preload: bool = False,
                 cache_size: int = 4, source_bands: Bands | None = None, allow_negative: bool = False,
                 npy_bands_advice: str = NPY_BANDS_ADVICE, dataset_paths: Sequence[str | os.PathLike] | None = None) -> None:
        if len(scenes) == 0:
            raise InputError("SceneDataset: no scenes")
        self.paths = [Path(s) for s in scenes]
        self.dataset_paths = self.paths if dataset_paths is None else [Path(s) for s in dataset_paths]
        self.bands = bands
        self.source_bands = source_bands
        self.npy_bands_advice = npy_bands_advice  # how the caller's user gives a .npy cube's grid
        self.allow_negative = allow_negative
        self.cache_size = max(int(cache_size), 1)
        self._infos: list[SceneInfo | None] = [None] * len(self.paths)
        self._source_grids: list[Bands | None] = [None] * len(self.paths)  # each file's own bands, once read
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._preloaded: list[np.ndarray] | None = None
        self._windowable = [False] * len(self.paths)  # hsicam HDF5 on our bands: read windows directly
        self._handles: dict[int, Any] = {}  # open HDF5 files of this process
        self._handles_pid = os.getpid()
        self._orphans: list[Any] = []
        if preload:
            self._preloaded = [self._load(i) for i in range(len(self.paths))]

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> torch.Tensor:
        return torch.from_numpy(self.cube(i))

    # -- numpy access --------------------------------------------------------------------------
    def cube(self, i: int) -> np.ndarray:
        """Scene ``i`` as a normalised float32 array (C, H, W) on :attr:`bands`."""
        if self._preloaded is not None:
            return self._preloaded[i]
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        arr = self._load(i)
        self._cache[i] = arr
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return arr

    def info(self, i: int) -> SceneInfo:
        """Size and peak of scene ``i`` (reads the file once)."""
        info = self._infos[i]
        if info is None:
            info = probe_hsicam(self.paths[i], self.bands, allow_negative=self.allow_negative)
            self._windowable[i] = info is not None
            if info is not None:  # an hsicam HDF5 file on these bands: nothing resampled
                self._source_grids[i] = self.bands
            if info is None:
                self.cube(i)  # loads the scene and records its info
                info = self._infos[i]
            self._infos[i] = info
        assert info is not None
        return info

    def source_grid(self, i: int) -> Bands:
        """The band grid scene ``i``'s file holds (before it was resampled onto :attr:`bands`; reads it once)."""
        if self._source_grids[i] is None:
            self.info(i)
        grid = self._source_grids[i]
        assert grid is not None
        return grid

    def window(self, i: int, y: int, x: int, h: int, w: int) -> np.ndarray:
        """Normalised window [y:y+h, x:x+w] (C, h, w) of scene ``i``, read without loading it all when possible."""
        if self._preloaded is None and i not in self._cache:
            info = self.info(i)
            if self._windowable[i]:
                ds = self._h5(i)["cube"]
                if y < 0 or x < 0 or y + h > ds.shape[1] or x + w > ds.shape[2]:
                    raise InputError(f"{info.path}: window {h}x{w} at ({y}, {x}) is outside the cube")
                with _reading(info.path, "HDF5"):  # corrupt pixel data shows here (or in the probe's check)
                    win = np.asarray(ds[:, y:y + h, x:x + w], dtype=np.float32)
                if self.allow_negative:  # as a preloaded read clips them (the probe checked the rest)
                    np.maximum(win, 0.0, out=win)
                return win / np.float32(info.peak)
        return self.cube(i)[:, y:y + h, x:x + w]

    def _h5(self, i: int) -> Any:
        """This process's open handle on scene ``i`` (reopened after a fork, never shared)."""
        import h5py

        if self._handles_pid != os.getpid():
            # handles inherited through fork belong to the parent: keep them referenced, never use them
            self._orphans.append(self._handles)
            self._handles, self._handles_pid = {}, os.getpid()
        f = self._handles.get(i)
        if f is None:
            try:
                f = h5py.File(self.paths[i], "r")
            except OSError as exc:
                raise InputError(f"{self.paths[i]}: cannot open HDF5 file: {exc}") from None
            self._handles[i] = f
        return f

    def _load(self, i: int) -> np.ndarray:
        path = self.paths[i]
        cube, src_bands, meta = read_cube(path, bands=self.source_bands, allow_negative=self.allow_negative)
        self._source_grids[i] = src_bands
        try:
            cube = resample_cube(cube, src_bands, self.bands, source=path)
        except InputError as exc:
            mixed = self._mixed_ranges_refusal(path, src_bands)
            if meta.get("bands_assumed"):  # a file without wavelengths (.npy): say how to give them
                raise InputError(f"{mixed or exc} (the file carries no wavelengths, so its {cube.shape[0]} bands were "
                                 f"taken as 400-700 nm: {self.npy_bands_advice})") from None
            from hsicam.data.formats import assumed_bands_note

            note = assumed_bands_note(meta)
            if note:  # a MAT/HDF5 file without a band list: its grid was assumed
                raise InputError(f"{mixed or exc} ({note})") from None
            if mixed is not None:
                raise mixed from None
            raise
        cube, peak = normalize_per_cube_max(cube, source=path)
        p = near_black_percentile(cube)
        warn_if_near_black(path, None if p is None else p * peak, peak)
        self._infos[i] = SceneInfo(path, cube.shape[1], cube.shape[2], peak)
        return np.ascontiguousarray(cube)

    def _mixed_ranges_refusal(self, path: Path, src_bands: Bands) -> InputError | None:
        """When ``path`` (on ``src_bands``) does not cover :attr:`bands` and the files of :attr:`dataset_paths` lie
        on different band ranges, the refusal that names them (:func:`hsicam.data.cube.mixed_ranges_refusal`), else
        None. Each file's grid is read from its header (:func:`hsicam.data.formats.read_bands`); a file that cannot be
        told is left out, its own read says why."""
        if src_bands.covers(self.bands) or len(self.dataset_paths) < 2:
            return None
        from hsicam.data.cube import mixed_ranges_refusal
        from hsicam.data.formats import read_bands

        grids = []
        for p in self.dataset_paths:
            try:
                grids.append(read_bands(p, bands=self.source_bands))
            except InputError:
                continue
        return mixed_ranges_refusal(path, src_bands, self.bands, grids)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_cache"] = OrderedDict()  # do not ship cached cubes to spawned workers
        state["_handles"], state["_orphans"], state["_handles_pid"] = {}, [], -1  # file handles cannot travel
        return state


class PatchDataset(Dataset):
    """Random square patches (C, S, S), S = ``patch_px + margin_px``, from a :class:`SceneDataset`.

    ``len`` is ``patches_per_epoch``. Item ``k`` of epoch ``e`` picks a scene (uniformly), a
    position and, with ``flips``/``rot90``, one of the 8 dihedral transforms, all from
    ``numpy.random.default_rng((seed, e, k))``, or ``(seed, e, k, stream)`` for a ``stream`` other than 0
    (the run's ``train.seed``: another seed, other patches; 0 keeps the stream of ``seed`` alone, the one
    before ``stream`` existed). ``fixed=True`` (validation) ignores the epoch, so
    the same patches are served every time. ``relight_sigma`` > 0: with probability
    ``relight_prob`` the patch is also relit (:func:`relight`, Legendre coefficients drawn N(0, σ²)
    from the same generator, after the rest).
    """

    def __init__(self, scenes: SceneDataset, patch_px: int, margin_px: int = 0, *, patches_per_epoch: int = 1024,
                 flips: bool = True, rot90: bool = True, seed: int = 0, fixed: bool = False,
                 relight_sigma: float = 0.0, relight_prob: float = 0.5, stream: int = 0) -> None:
        if patch_px < 1 or margin_px < 0:
            raise InputError(f"PatchDataset: need patch_px >= 1 and margin_px >= 0, got {patch_px}, {margin_px}")
        if patches_per_epoch < 1:
            raise InputError(f"PatchDataset: patches_per_epoch must be >= 1, got {patches_per_epoch}")
        self.scenes = scenes
        self.patch_px = int(patch_px)
        self.margin_px = int(margin_px)
        self.size_px = self.patch_px + self.margin_px
        self.patches_per_epoch = int(patches_per_epoch)
        self.flips = flips
        self.rot90 = rot90
        if not (math.isfinite(relight_sigma) and relight_sigma >= 0 and 0 <= relight_prob <= 1):
            raise InputError(f"PatchDataset: need relight_sigma >= 0 and relight_prob in [0, 1], got {relight_sigma}, "
                             f"{relight_prob}")
        self.relight_sigma = float(relight_sigma)
        self.relight_prob = float(relight_prob)
        self.seed = int(seed)
        self.stream = int(stream)
        self.fixed = fixed
        self.epoch = 0
        for i in range(len(scenes)):
            info = scenes.info(i)
            if min(info.height, info.width) < self.size_px:
                raise InputError(
                    f"{info.path}: scene is {info.height}x{info.width} px, smaller than a patch of {self.patch_px} px "
                    f"plus the camera margin of {self.margin_px} px ({self.size_px} px)"
                )

    @property
    def bands(self) -> Bands:
        return self.scenes.bands

    def set_epoch(self, epoch: int) -> None:
        """Draw a new set of patches (call once per epoch, before iterating)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.patches_per_epoch

    def _draw(self, k: int) -> tuple[np.random.Generator, int]:
        """(the generator of patch ``k`` this epoch, the scene index it drew first)."""
        if not 0 <= k < self.patches_per_epoch:
            raise IndexError(k)
        key = [self.seed, 0 if self.fixed else self.epoch, int(k)]
        rng = np.random.default_rng(key + [self.stream] if self.stream else key)
        return rng, int(rng.integers(len(self.scenes)))

    def scene_of(self, k: int) -> Path:
        """The scene file patch ``k`` of this epoch is cut from (no pixel read)."""
        return self.scenes.paths[self._draw(k)[1]]

    def __getitem__(self, k: int) -> torch.Tensor:
        rng, i = self._draw(k)
        info = self.scenes.info(i)
        s = self.size_px
        y = int(rng.integers(info.height - s + 1))
        x = int(rng.integers(info.width - s + 1))
        patch = self.scenes.window(i, y, x, s, s)
        turns = int(rng.integers(4)) if self.rot90 else 0
        flip = bool(rng.integers(2)) if self.flips else False
        patch = augment(patch, turns, flip)
        if self.relight_sigma > 0:  # drawn after the rest: the same scenes, places and turns as without it
            apply, coeffs = rng.random() < self.relight_prob, rng.normal(0.0, self.relight_sigma, RELIGHT_ORDER)
            if apply:
                patch = relight(patch, coeffs)
        return torch.from_numpy(np.ascontiguousarray(patch, dtype=np.float32))


#: Legendre orders 1..RELIGHT_ORDER of the band axis in a relighting factor (:func:`relight`).
RELIGHT_ORDER = 3


def relighting_exponent(n_bands: int, coeffs: np.ndarray) -> np.ndarray:
    """Σ_k a_k P_k(x_c) (N,), x_c the band index mapped onto [-1, 1], P_k the Legendre polynomial of
    order k = 1, 2, …, len(coeffs): the log of the smooth spectral factor :func:`relight` applies (a
    tilt, a bow and an S-curve across the bands); coeffs all 0: zeros."""
    x = np.linspace(-1.0, 1.0, n_bands) if n_bands > 1 else np.zeros(1)
    return np.polynomial.legendre.legval(x, np.concatenate([[0.0], np.asarray(coeffs, dtype=np.float64)]))


def relight(patch: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    """A scene patch (C, H, W) under another light: every spectrum multiplied by
    exp(:func:`relighting_exponent`) (the same at every pixel, as a change of illuminant or of a global
    reflectance tint would be), then the patch rescaled to keep its peak value (an exposure), so it
    stays in the data's range. Spectra the data never held, with the same geometry."""
    e = relighting_exponent(patch.shape[0], coeffs)
    s = np.exp(e - e.max())[:, None, None]  # the factor over its maximum: no σ overflows, the peak is kept below
    out = patch * s
    peak, new = float(np.max(patch)), float(np.max(out))
    return (out * (peak / new)).astype(patch.dtype, copy=False) if new > 0 else patch


def augment(patch: np.ndarray, turns: int, flip: bool) -> np.ndarray:
    """Dihedral transform of (C, H, W): ``turns`` × 90° counter-clockwise, then a left-right flip."""
    out = np.rot90(patch, k=turns, axes=(1, 2)) if turns % 4 else patch
    return out[:, :, ::-1] if flip else out


__all__ = ["PatchDataset", "RELIGHT_ORDER", "SCENE_SUFFIXES", "SceneDataset", "SceneInfo", "augment", "check_not_an_output",
           "check_windowed_pixels", "list_scenes", "probe_hsicam", "relight", "relighting_exponent", "scene_names",
           "scene_path", "split_scenes", "warn_if_near_black"]
