"""The embedded synthetic hyperspectral dataset (DESIGN.md §4, issue #14).

Real datasets cannot be shipped, so the default dataset is generated. Spectra come from the
sources of :mod:`hsicam.data.spectral_sources` (every measured reflectance set and light-source
collection that colour-science ships, plus documented physical models), and from spectra derived
from them per scene: linear mixtures, Kubelka-Munk pigment mixtures, layered glazes (products),
wet surfaces (powers) and smooth draws in the principal-component space of the measured
reflectances (clipped to [0, 1]). Spatial structure comes from scikit-image's bundled photos and
textures and from procedural scenes.

Scene kinds (a fixed schedule over the scene index, so every kind appears in small sets):

- ``dead_leaves``: occluding discs, ellipses and rotated rectangles at every scale (radii from
  ~0.5 px to a quarter of the scene, power law), shaded, some textured.
- ``photo``: a crop of a bundled colour photo; sRGB → reflectance by Otsu et al. (2018), or, when
  ``otsu2018`` is held out, the photo's RGB as weights of three library spectra.
- ``texture``: a bundled texture or a procedural one (1/f noise, weaves, speckle) at full
  resolution, mixing two or three spectra.
- ``edges``: fine periodic and sharp structure (Siemens stars, bars, zone plates, slanted edges,
  checkerboards, text, thin lines, glyphs) between spectra.
- ``smooth``: smooth blends of 2-4 spectra, always overlaid with thin lines, glyphs and small
  occluders (no scene kind is smoothed away by a 9×9 box without loss).
- ``emitters``: a dark scene with near-monochromatic emitters (LED dots with glow, display
  subpixels, LED signs) when the library has emitters, else bright highlights.

Lighting: one light source, two blended across the scene, or sun and sky (cast shadows lit only
by a second, daylight source); a wide range of shading; specular highlights that carry the local
light's spectrum; dark scenes (the lit scene dimmed 3-100×, highlights and emitters left
bright). Spectra are integrated over each band's Gaussian response (FWHM from :class:`Bands`) on
a 1 nm grid, so lamp lines land in the right bands. Each scene is divided by its maximum (values
in [0, 1]) and written as our HDF5 (:func:`hsicam.data.formats.write_cube_h5`).

Held-out protocol: ``holdout_sources`` names sources (:data:`SOURCES`) whose spectra never reach
the training scenes; ``split="heldout"`` builds scenes from those sources only
(:func:`heldout_dataset`). The default dataset holds out :data:`DEFAULT_HOLDOUT`.

Determinism: scene ``i`` of seed ``s`` is drawn from ``numpy.random.default_rng((s, i))`` (held-out
scenes from ``(s, i, HELDOUT_STREAM)``) and does not depend on the number of scenes; the same seed
and library versions give identical bytes. colour-science is imported only while generating;
training on the cached files does not need it.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import numbers
import os
import re
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from hsicam.data.formats import SCENE_SUFFIXES, write_cube_h5
from hsicam.data.spectral_sources import (
    DEFAULT_HOLDOUT,
    SOURCES,
    SUPPORTED_RANGE_NM,
    OtsuModel,
    SpectralLibrary,
    band_matrix,
    check_bands,
    parse_holdout,
    spectral_library,
    split_library,
)
from hsicam.errors import InputError
from hsicam.io import output_path_problem, write_json
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

GENERATOR_VERSION = 3  # 3: sub-pixel lines at their full width (line_coverage); 2 under-inked them
MANIFEST = "manifest.json"
#: What a set of which only some scenes were written (:func:`generate_scenes`) records in place of the manifest, which
#: marks a finished set: the parameters and the package versions its scenes were made with (:func:`version_differences`).
PARTIAL = "partial.json"
SCENE_PATTERN = "scene_{:04d}.h5"
SPLITS = ("train", "heldout")
#: Third element of the random stream of held-out scenes (so they never repeat a training scene).
HELDOUT_STREAM = 0x4E1D
#: Default number of scenes in the held-out validation set.
HELDOUT_N = 8
SCHEDULE = ("dead_leaves", "photo", "texture", "edges", "dead_leaves", "smooth", "emitters", "texture", "photo",
            "dead_leaves")
PHOTOS = ("astronaut", "chelsea", "coffee", "rocket", "motorcycle_left", "motorcycle_right",
          "immunohistochemistry", "colorwheel", "retina", "hubble_deep_field")
TEXTURES = ("brick", "grass", "gravel", "camera", "moon", "coins", "clock")
#: scikit-image text scans the ``edges`` scenes tile (their ``text`` pattern).
PATTERN_IMAGES = ("text", "page")
#: scikit-image images that no generated scene uses (:func:`unseen_layout_scene`): not a photo, texture or
#: pattern image above, nor a pattern the ``edges`` scenes draw (checkerboards, text, bars …).
#: ``binary_blobs`` is drawn with a fixed seed; ``lfw_faces`` tiles the first 64 faces of ``lfw_subset``.
UNSEEN_LAYOUTS = ("horse", "cell", "shepp_logan_phantom", "logo", "microaneurysms", "binary_blobs", "lfw_faces")
#: Third element of the random stream of unseen-layout scenes.
UNSEEN_LAYOUT_STREAM = 0x1A70
_ILLUMINANT_GROUP_WEIGHTS = {"daylight": 0.36, "fluorescent": 0.22, "incandescent": 0.16, "led": 0.16,
                             "discharge": 0.07, "other": 0.03}
#: How the reflectance of a surface is made: a measured spectrum or one derived from measured ones.
PALETTE_KINDS = ("measured", "mix", "pigment", "layer", "wet", "basis")
_PALETTE_P = np.array([0.40, 0.10, 0.15, 0.10, 0.05, 0.20])


# ------------------------------------------------------------------------------------------------
# Cache and entry points
# ------------------------------------------------------------------------------------------------
def default_cache_dir() -> Path:
    """``$HSICAM_CACHE``, else ``$XDG_CACHE_HOME/hsicam``, else ``~/.cache/hsicam``."""
    env = os.environ.get("HSICAM_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "hsicam"


def _check_cache(out: Path, cache_dir: str | os.PathLike | None = None) -> None:
    """One-line InputError when the dataset folder ``out`` cannot be made in the cache root, naming
    what set that root (``data.cache_dir``, ``$HSICAM_CACHE``, ``$XDG_CACHE_HOME`` or the default)
    with its value and what to set instead."""
    problem = output_path_problem(out, "dir")
    if problem is None:
        return
    fix = "set HSICAM_CACHE to a writable folder"
    if cache_dir:
        setting, fix = f"data.cache_dir={cache_dir}", ("point data.cache_dir to a writable folder (--set data.cache_dir=DIR, or "
                                                    "cache_dir under data: in the config file; a run's is its config.yaml)")
    elif os.environ.get("HSICAM_CACHE"):
        setting, fix = f"HSICAM_CACHE={os.environ['HSICAM_CACHE']}", f"{fix}, or unset it"
    elif os.environ.get("XDG_CACHE_HOME"):
        setting = f"XDG_CACHE_HOME={os.environ['XDG_CACHE_HOME']}"
    else:
        setting = f"the default cache {default_cache_dir()}"
    raise InputError(f"{setting} (the dataset cache): {out}: {problem}; {fix}")


def _check_split(split: str) -> str:
    if split not in SPLITS:
        raise InputError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    return split


def parameters(n: int, size: int, seed: int, bands: Bands, *,
               holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train") -> dict[str, Any]:
    """The generator parameters that determine the dataset's bytes (the cache key's content)."""
    return {"generator_version": GENERATOR_VERSION, "n": int(n), "size": int(size), "seed": int(seed),
            "bands": bands.to_dict(), "holdout_sources": list(parse_holdout(holdout_sources)),
            "split": _check_split(split)}


def cache_key(n: int, size: int, seed: int, bands: Bands, *,
              holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train") -> str:
    """A short hash of :func:`parameters`."""
    text = json.dumps(parameters(n, size, seed, bands, holdout_sources=holdout_sources, split=split), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def dataset_dir(n: int, size: int, seed: int, bands: Bands, *, cache_dir: str | os.PathLike | None = None,
                holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train") -> Path:
    """Where the cached dataset with these parameters lives (whether or not it exists yet).

    ``<cache>/synthetic/n{n}-s{size}-seed{seed}-{key}`` for training sets,
    ``<cache>/synthetic/heldout-n{n}-s{size}-seed{seed}-{key}`` for held-out sets.
    """
    root = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    key = cache_key(n, size, seed, bands, holdout_sources=holdout_sources, split=split)
    prefix = "heldout-" if split == "heldout" else ""
    return root / "synthetic" / f"{prefix}n{n}-s{size}-seed{seed}-{key}"


#: The name of a cached set's folder (:func:`dataset_dir`); its group ``n``: the set's number of scenes.
_DATASET_DIR_RE = re.compile(r"(?:heldout-)?n(?P<n>\d+)-s\d+-seed\d+-[0-9a-f]{12}")
_SCENE_FILE_RE = re.compile(r"scene_\d{4,}\.h5")


def partial_set_size(folder: str | os.PathLike) -> tuple[int, int] | None:
    """(scene files held, scenes of the set) for a folder that holds fewer of a synthetic set's scene files than
    the set has: the set's size is its :data:`PARTIAL` record's ``n``, else (a partial set of an hsicam before that
    record, or a killed generation) the one its cache folder's name says (:func:`dataset_dir`). None for a finished
    set, a folder of other files, or one whose size is not known."""
    folder = Path(folder)
    held = sum(1 for p in folder.iterdir() if _SCENE_FILE_RE.fullmatch(p.name))
    if not held:
        return None
    record = _read_manifest(folder, PARTIAL)
    params = record.get("parameters") if isinstance(record, dict) else None
    n = params.get("n") if isinstance(params, dict) else None
    if not isinstance(n, int) or isinstance(n, bool):
        named = _DATASET_DIR_RE.fullmatch(folder.resolve().name)
        n = int(named.group("n")) if named else None
    return (held, n) if n is not None and held < n else None


def synthetic_dataset(n: int = 32, size: int = 256, seed: int = 0, bands: Bands | None = None,
                      cache_dir: str | os.PathLike | None = None, progress: bool | None = None, *,
                      holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train",
                      room_fix: str = "") -> Path:
    """Folder of the synthetic dataset for these parameters, generated on first use and cached.

    By default the training scenes hold out :data:`DEFAULT_HOLDOUT`; ``holdout_sources=()`` uses
    every source. ``split="heldout"`` gives the held-out set instead (see :func:`heldout_dataset`).
    ``room_fix``: see :func:`generate_dataset`.
    """
    bands = bands or Bands.paper()
    holdout = parse_holdout(holdout_sources)
    out = dataset_dir(n, size, seed, bands, cache_dir=cache_dir, holdout_sources=holdout, split=split)
    if is_complete(out, n, size, seed, bands, holdout_sources=holdout, split=split):
        log.debug("synthetic dataset cached at %s", out)
        _warn_versions(out)
        return out
    _check_cache(out, cache_dir)
    generate_dataset(out, n=n, size=size, seed=seed, bands=bands, progress=progress, holdout_sources=holdout,
                     split=split, room_fix=room_fix)
    return out


def heldout_dataset(n: int = HELDOUT_N, size: int = 256, seed: int = 0, bands: Bands | None = None,
                    cache_dir: str | os.PathLike | None = None, progress: bool | None = None, *,
                    holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT) -> Path:
    """Folder of the held-out validation set: scenes made only of the held-out sources' spectra.

    Cached like the training set (``<cache>/synthetic/heldout-…``). Use the same ``size``, ``seed``,
    ``bands`` and ``holdout_sources`` as the training set it validates: then none of its spectra
    (nor any mixture of them) occurs in those training scenes. Where no source of a role is held
    out (e.g. only lamps), that role uses the training spectra (see
    :func:`hsicam.data.spectral_sources.split_library`); the manifest's ``sources.held_out_roles``
    says which.
    """
    return synthetic_dataset(n, size, seed, bands, cache_dir, progress, holdout_sources=holdout_sources,
                             split="heldout")


def is_complete(out: str | os.PathLike, n: int, size: int, seed: int, bands: Bands, *,
                holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train") -> bool:
    """True when ``out`` holds a finished dataset with exactly these parameters."""
    out = Path(out)
    man = _read_manifest(out)
    if man is None or man.get("parameters") != parameters(n, size, seed, bands, holdout_sources=holdout_sources,
                                                          split=split):
        return False
    return all((out / s["file"]).is_file() for s in man.get("scenes", []))


def damaged_scenes(out: str | os.PathLike) -> list[str]:
    """The scene files of the finished dataset ``out`` that are missing or whose bytes are not the ones its manifest
    records (SHA-256; an interrupted copy, a disk error, an edit in place): [] when every one is intact. Reads every
    scene (~1 s per 500 MB): ``hsicam data synth`` checks a cached set with it, training does not."""
    out = Path(out)
    bad = []
    scenes = (_read_manifest(out) or {}).get("scenes", [])
    log.debug("synthetic dataset cached at %s: checking its %d scene files against their checksums", out, len(scenes))
    for s in scenes:
        path = out / s["file"]
        try:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        except OSError:
            digest = None
        if digest != s.get("sha256"):
            bad.append(s["file"])
    return bad


#: The packages whose output the generated scenes depend on (the spectral library and the Otsu basis; the photos and
#: textures): a cached set made with other versions may hold other scenes than this installation would generate.
SCENE_PACKAGES = ("colour-science", "scikit-image")


def version_differences(out: str | os.PathLike) -> list[str]:
    """``"package recorded → installed"`` for each of :data:`SCENE_PACKAGES` whose version differs between the
    manifest of ``out`` (of a partial set: its :data:`PARTIAL` record) and this installation ([] when none, or when
    they record no versions)."""
    recorded = (_read_manifest(Path(out)) or _read_manifest(Path(out), PARTIAL) or {}).get("software")
    if not isinstance(recorded, dict):
        return []
    installed = _versions()
    return [f"{k} {recorded[k]} → {installed[k]}" for k in SCENE_PACKAGES
            if k in recorded and recorded[k] != installed[k]]


_VERSIONS_SAID: set[Path] = set()


def _warn_versions(out: Path) -> None:
    """One warning per process and cached set made with other versions of :data:`SCENE_PACKAGES`, or (a partial set
    without a :data:`PARTIAL` record: written by an hsicam before that record, or by a generation of the whole set
    cut short before it wrote that record too) with versions that nobody recorded."""
    if out in _VERSIONS_SAID:
        return
    diff = version_differences(out)
    if diff:
        _VERSIONS_SAID.add(out)
        log.warning("synthetic dataset %s was generated with other versions of the packages its scenes come from (%s): "
                    "it may hold other scenes than this installation generates, so runs on it compare only with runs "
                    "on the same files; delete the folder to generate it anew", out, ", ".join(diff))
    elif _read_manifest(out) is None and not isinstance((_read_manifest(out, PARTIAL) or {}).get("software"), dict):
        _VERSIONS_SAID.add(out)
        log.warning("synthetic scenes in %s record no versions of the packages they come from (written by an hsicam "
                    "before session 61, or by a generation cut short): they may differ from the scenes this "
                    "installation generates; delete the folder to generate them anew", out)


def heldout_roles(out: str | os.PathLike) -> dict[str, bool] | None:
    """A held-out set's ``sources.held_out_roles`` from its manifest ({role: whether held-out spectra fill it}), or
    None when the manifest does not say."""
    sources = (_read_manifest(Path(out)) or {}).get("sources")
    roles = sources.get("held_out_roles") if isinstance(sources, dict) else None
    return roles if isinstance(roles, dict) else None


def _read_manifest(out: Path, name: str = MANIFEST) -> dict[str, Any] | None:
    try:
        return json.loads((out / name).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


#: Peak memory while one scene is generated and written, in multiples of its float32 cube
#: (measured: ~4.3× at 1024 px, 31 bands, over the interpreter's own; rounded up).
SCENE_MEMORY_FACTOR = 5


def scene_memory_bytes(size: int, n_bands: int) -> int:
    """Estimated peak memory (bytes) of generating one ``size``×``size`` scene of ``n_bands`` bands."""
    return SCENE_MEMORY_FACTOR * 4 * int(size) ** 2 * int(n_bands)


def check_scene_memory(size: int, n_bands: int, option: str = "data.synthetic_size",
                       budget_mb: float | None = None) -> None:
    """InputError when the float32 cube of one scene of ``size`` px and ``n_bands`` bands exceeds the
    memory budget of one cube (:func:`hsicam.memory.memory_budget_bytes`, the rule every reader of
    the scene applies), naming ``option`` (what set the size), the cube, the generation's peak
    (:func:`scene_memory_bytes`), the budget and the largest size that fits; checked before any
    folder is made or scene generated."""
    from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes

    cube, budget = 4 * int(size) ** 2 * int(n_bands), memory_budget_bytes(budget_mb)
    if cube <= budget:
        return
    largest = int((budget / (4 * n_bands)) ** 0.5)
    raise InputError(f"{option} {size}: one {size}×{size}-px scene of {n_bands} bands is a cube of {format_bytes(cube)} "
                     f"(about {format_bytes(scene_memory_bytes(size, n_bands))} of memory while it is generated), more "
                     f"than the memory budget of {format_bytes(budget)} for one cube ({MEMORY_BUDGET_ENV}, default a "
                     f"quarter of the machine's memory); give {option} {largest} or less, or raise {MEMORY_BUDGET_ENV} "
                     "if the machine has the memory")


#: Bytes a scene file holds besides its float32 pixels (HDF5 headers, bands, metadata), at most.
SCENE_FILE_OVERHEAD_BYTES = 64 * 1024


#: What a refusal of :func:`check_room_for_scenes` tells a training config to change.
ROOM_FIX = ("lower data.synthetic_n or data.synthetic_size, or point data.cache_dir (or HSICAM_CACHE) to a larger "
            "disk")


def check_room_for_scenes(out: Path, n: int, size: int, n_bands: int, fix: str = ROOM_FIX,
                          indices: Sequence[int] | None = None) -> None:
    """InputError, before any scene is generated, when the file system of ``out`` lacks the room for
    the scenes still to write (``n`` minus those already there, which a rerun rewrites in place) and a
    margin (a tenth, at least 64 MiB): a count of scenes far beyond the disk used to fill it scene by scene.
    ``fix``: what to change, in the caller's terms (the config's keys, or ``data synth``'s options).
    ``indices``: only these scenes are to be written (:func:`generate_scenes`)."""
    from hsicam.io import free_space_short, free_space_text

    todo = range(min(n, 100_000)) if indices is None else indices
    written = sum((out / SCENE_PATTERN.format(i)).is_file() for i in todo) if out.is_dir() else 0
    need = ((n if indices is None else len(indices)) - written) * (4 * int(size) ** 2 * int(n_bands)
                                                                  + SCENE_FILE_OVERHEAD_BYTES)
    free = free_space_short(out, need)
    if free is not None:
        raise InputError(f"the synthetic dataset of {n:,} scenes of {size}×{size} px and {n_bands} bands needs, in {out}, "
                         f"{free_space_text(need, free, path=out)}; {fix}")


def generate_dataset(out: str | os.PathLike, n: int, size: int, seed: int = 0, bands: Bands | None = None,
                     progress: bool | None = None, *, holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT,
                     split: str = "train", room_fix: str = "") -> dict[str, Any]:
    """Write ``n`` scenes (``scene_0000.h5`` …) and ``manifest.json`` (last) into ``out``.

    ``split="train"`` (default): scenes without the held-out sources' spectra; ``"heldout"``: scenes
    made of them only. Every file is written atomically; the manifest marks a finished dataset (until then, in a
    folder that held no scene, :data:`PARTIAL` records the versions from the first scene on: :func:`_record_partial`).
    Refuses a folder holding another dataset's manifest or foreign cube files. ``progress=None``
    shows a tqdm bar on a terminal and k/N log lines otherwise (:mod:`hsicam.progress`); False:
    neither. Returns the manifest. ``room_fix``: what a refusal for want of disk space tells the
    caller to change (default: the config's keys, :data:`ROOM_FIX`).
    """
    bands = bands or Bands.paper()
    holdout = parse_holdout(holdout_sources)
    out, params = _checked_output(out, n, size, seed, bands, holdout, split, room_fix)
    from hsicam.io import output_name

    log.info("generating the synthetic %s set (%d scene%s of %dx%dx%d, held-out sources: %s) in %s", split, n,
             "" if n == 1 else "s", size, size, len(bands), ", ".join(holdout) or "none", output_name(out))
    lib = spectral_library(bands, holdout, split)
    with _folder_removed_if_failed(out):  # scenes written stay; a rerun rewrites all, the same bytes
        return _generate_into(out, n, size, seed, bands, lib, params, holdout, split, progress)


def _checked_output(out: str | os.PathLike, n: int, size: int, seed: int, bands: Bands, holdout: tuple[str, ...],
                    split: str, room_fix: str, indices: Sequence[int] | None = None) -> tuple[Path, dict[str, Any]]:
    """(out, the set's parameters) after the checks before any scene of the ``n``-scene set is written into
    ``out`` (all, or ``indices``): the split, the sizes, the bands, the folder's own dataset, memory, disk room."""
    _check_split(split)
    for name, value in (("n", n), ("size", size), ("seed", seed)):  # ints, before their ranges are checked below
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise InputError(f"synthetic: {name} must be an int, got {value!r}")
    if seed < 0:  # (numpy's "expected non-negative integer" otherwise)
        raise InputError(f"synthetic: seed must be >= 0, got {seed}")
    if not isinstance(bands, Bands):
        raise InputError(f"synthetic: bands must be a Bands (e.g. Bands.paper(), or a config's band grid), got "
                         f"{type(bands).__name__} {bands!r}"[:200])
    if n < 1:
        raise InputError(f"synthetic: need at least one scene, got n={n}")
    if size < 16:
        raise InputError(f"synthetic: scenes must be at least 16 px, got size={size}")
    check_bands(bands)
    out = Path(out)
    params = parameters(n, size, seed, bands, holdout_sources=holdout, split=split)
    check_dataset_folder(out, params)
    check_scene_memory(size, len(bands))
    check_room_for_scenes(out, n, size, len(bands), room_fix or ROOM_FIX, indices=indices)
    return out, params


@contextlib.contextmanager
def _folder_removed_if_failed(out: Path):
    """Make ``out`` (and its missing parents); a failure inside removes those of them left empty again."""
    made = [p for p in (out, *out.parents) if not p.exists()]  # the folders this call creates
    out.mkdir(parents=True, exist_ok=True)
    try:
        yield
    except BaseException:
        for p in made:
            try:
                p.rmdir()
            except OSError:
                break
        raise


def _generate_into(out: Path, n: int, size: int, seed: int, bands: Bands, lib: SpectralLibrary,
                   params: dict[str, Any], holdout: Any, split: str, progress: bool | None) -> dict[str, Any]:
    """The scenes and the manifest of :func:`generate_dataset`, written into the existing ``out``."""
    from hsicam.progress import progress as counted

    scenes = []
    sum_spectrum = np.zeros(len(bands))
    first = _holds_no_scene(out)
    for i in counted(range(n), n, f"synthetic {split} set", "scene", show=progress):
        cube, info, path = _write_scene(out, i, seed, size, bands, lib, params)
        if first and i == 0:  # a generation cut short keeps its scenes with the record of their versions
            _record_partial(out, params, n, size, seed, bands, holdout, split)
        name = path.name
        mean_spec = cube.mean(axis=(1, 2), dtype=np.float64)
        sum_spectrum += mean_spec
        scenes.append({"file": name, **info, "min": float(cube.min()), "max": float(cube.max()),
                       "mean": float(cube.mean(dtype=np.float64)), "mean_spectrum": _round(mean_spec),
                       "sha256": hashlib.sha256(path.read_bytes()).hexdigest()})
    kinds: dict[str, int] = {}
    for s in scenes:
        kinds[s["kind"]] = kinds.get(s["kind"], 0) + 1
    manifest = {
        "format": "hsicam-synthetic",
        "parameters": params,
        "key": cache_key(n, size, seed, bands, holdout_sources=holdout, split=split),
        "normalisation": "each scene is divided by its maximum over bands and pixels (values in [0, 1])",
        "software": _versions(),
        "sources": {**lib.sources, "photos": list(PHOTOS), "textures": list(TEXTURES),
                    "descriptions": {k: SOURCES[k].origin for k in _used_sources(lib)}},
        "statistics": {
            "kinds": kinds,
            "min": min(s["min"] for s in scenes),
            "max": max(s["max"] for s in scenes),
            "mean": float(np.mean([s["mean"] for s in scenes])),
            "mean_spectrum": _round(sum_spectrum / n),
        },
        "scenes": scenes,
    }
    write_json(out / MANIFEST, manifest)
    (out / PARTIAL).unlink(missing_ok=True)  # every scene rewritten, with these versions: the manifest says it all
    return manifest


def _holds_no_scene(out: Path) -> bool:
    """Whether the folder ``out`` (or a missing one) holds no scene file yet: a generation into it writes the folder's
    first scenes, whose versions its :data:`PARTIAL` record may give (:func:`_record_partial`)."""
    return not any(out.glob(SCENE_PATTERN.replace("{:04d}", "*"))) if out.is_dir() else True


def _record_partial(out: Path, params: dict[str, Any], n: int, size: int, seed: int, bands: Bands, holdout: Any,
                    split: str) -> None:
    """Write ``out``'s :data:`PARTIAL` record (atomically) after the first scene of a generation into a folder that
    held none (:func:`_holds_no_scene`), unless it has a record or a manifest already: not after the last scene, so
    that the scenes of a generation cut short (an evaluation interrupted, a whole set's generation killed) say with
    which versions they were made (:func:`version_differences`). A finished set's manifest replaces it."""
    if _read_manifest(out) is None and _read_manifest(out, PARTIAL) is None:
        write_json(out / PARTIAL, {"format": "hsicam-synthetic-partial", "parameters": params,
                                   "key": cache_key(n, size, seed, bands, holdout_sources=holdout, split=split),
                                   "software": _versions()})


def _write_scene(out: Path, i: int, seed: int, size: int, bands: Bands, lib: SpectralLibrary,
                 params: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any], Path]:
    """Generate scene ``i`` and write it (atomically) as ``out/scene_IIII.h5``: (cube, info, path)."""
    cube, info = generate_scene(i, seed, size, lib)
    meta = {"dataset": "hsicam-synthetic", "index": i, **params, **info}
    return cube, info, write_cube_h5(out / SCENE_PATTERN.format(i), cube, bands, meta)


def synthetic_scenes(indices: Sequence[int], n: int, size: int = 256, seed: int = 0, bands: Bands | None = None,
                     cache_dir: str | os.PathLike | None = None, progress: bool | None = None, *,
                     holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train",
                     room_fix: str = "") -> list[Path]:
    """The files of scenes ``indices`` of the cached synthetic set of these parameters, in that set's
    folder (:func:`dataset_dir`), generating only those it lacks: the same files, byte for byte, as
    :func:`synthetic_dataset` writes, for a caller that reads a few scenes of a large set (an evaluation
    scores the validation split only). A folder of scene files without a manifest is what a generation
    cut short leaves: :func:`synthetic_dataset` completes it later (a training of the same config)."""
    bands = bands or Bands.paper()
    holdout = parse_holdout(holdout_sources)
    out = dataset_dir(n, size, seed, bands, cache_dir=cache_dir, holdout_sources=holdout, split=split)
    bad = [i for i in indices if not 0 <= int(i) < n]
    if bad:
        raise InputError(f"synthetic: scene index {bad[0]} is outside a set of {n} scenes")
    paths = [out / SCENE_PATTERN.format(i) for i in indices]
    if is_complete(out, n, size, seed, bands, holdout_sources=holdout, split=split):
        log.debug("synthetic dataset cached at %s", out)
        _warn_versions(out)
        return paths
    missing = [int(i) for i in dict.fromkeys(indices) if not (out / SCENE_PATTERN.format(i)).is_file()]
    if missing:
        _check_cache(out, cache_dir)
        generate_scenes(out, missing, n, size, seed, bands, progress, holdout_sources=holdout, split=split,
                        room_fix=room_fix)
    _warn_versions(out)  # a partial set's scenes, reused or joined by new ones: its record (PARTIAL) says with what
    return paths


def generate_scenes(out: str | os.PathLike, indices: Sequence[int], n: int, size: int, seed: int = 0,
                    bands: Bands | None = None, progress: bool | None = None, *,
                    holdout_sources: str | Iterable[str] | None = DEFAULT_HOLDOUT, split: str = "train",
                    room_fix: str = "") -> list[Path]:
    """Write the scenes ``indices`` of the ``n``-scene set into ``out`` (the files :func:`generate_dataset`
    writes for them), and no manifest: :func:`generate_dataset` completes the folder. What the manifest would record
    of the parameters and the package versions goes to :data:`PARTIAL` with the folder's first scene (kept when
    there: the versions the first scenes were made with; not written beside scenes of an hsicam before the record,
    whose versions are unknown), for :func:`version_differences`. Returns their paths."""
    from hsicam.progress import progress as counted

    bands = bands or Bands.paper()
    holdout = parse_holdout(holdout_sources)
    out, params = _checked_output(out, n, size, seed, bands, holdout, split, room_fix, indices)
    log.info("generating %d of the %d scenes of the synthetic %s set (%dx%dx%d, held-out sources: %s) in %s",
             len(indices), n, split, size, size, len(bands), ", ".join(holdout) or "none", out)
    lib = spectral_library(bands, holdout, split)
    # the record says with what the folder's scenes were made: written only with its first scenes (scenes already
    # there without one, from an hsicam before the record, were made with versions nobody knows)
    first = _holds_no_scene(out)
    paths = []
    with _folder_removed_if_failed(out):  # written scenes stay
        for i in counted(indices, len(indices), f"synthetic {split} scenes", "scene", show=progress):
            paths.append(_write_scene(out, i, seed, size, bands, lib, params)[2])
            # with the first scene, not after the last: a generation cut short (evaluate interrupted) kept its scenes
            # without it, and they were reused ever after as scenes of unknown versions
            if first and len(paths) == 1:
                _record_partial(out, params, n, size, seed, bands, holdout, split)
    return paths


def _used_sources(lib: SpectralLibrary) -> list[str]:
    used = set(lib.reflectance_sources) | set(lib.illuminant_sources) | set(lib.emitter_sources)
    if lib.otsu is not None:
        used.add("otsu2018")
    return [k for k in SOURCES if k in used]


def check_dataset_folder(out: str | os.PathLike, params: dict[str, Any] | None = None) -> None:
    """InputError unless ``out`` can take (or already holds) a dataset of :func:`generate_dataset`:
    absent, empty, a finished dataset (its manifest; with ``params``, of these parameters) without
    foreign cube files, or only scene files (a generation killed before its manifest, or a partial set of
    :func:`generate_scenes`, whose :data:`PARTIAL` record, with ``params``, has these parameters). Cheap: the
    CLI calls it before any work, :func:`generate_dataset` again before writing."""
    out = Path(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    names = [f.name for f in out.iterdir() if not f.name.startswith(".")]
    foreign = [n for n in names if Path(n).suffix.lower() in SCENE_SUFFIXES and not n.startswith("scene_")]
    if foreign:
        raise InputError(f"{out}: holds other cube files ({', '.join(sorted(foreign)[:3])}); choose an empty --out")
    man = _read_manifest(out)
    if isinstance(man, dict):
        if params is not None and man.get("parameters") != params:
            raise InputError(f"{out}: holds a synthetic dataset with other parameters; choose another --out or remove it")
        return
    partial = _read_manifest(out, PARTIAL)
    if isinstance(partial, dict) and params is not None and partial.get("parameters") != params:
        raise InputError(f"{out}: holds scenes of a synthetic dataset with other parameters; choose another --out or "
                         "remove it")
    other = sorted(n for n in names if not re.fullmatch(r"scene_\d{4,}\.h5", n) and n != PARTIAL)
    if other:
        shown = ", ".join(other[:3]) + (f" and {len(other) - 3} more" if len(other) > 3 else "")
        raise InputError(f"{out}: folder is not empty and holds no dataset of hsicam data synth ({shown}); "
                         "choose an empty or new --out")


def _round(v: np.ndarray) -> list[float]:
    return [round(float(x), 6) for x in v]


def _versions() -> dict[str, str]:
    """The manifest's ``software``: hsicam's version is the running code's (``hsicam.__version__``, not the metadata
    of whichever hsicam distribution is installed), the others' their installed distributions'."""
    from importlib import metadata

    from hsicam.version import __version__

    out = {"hsicam": __version__}
    for dist in ("colour-science", "numpy", "scikit-image", "h5py"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "unknown"
    return out

# ------------------------------------------------------------------------------------------------
# Images bundled with scikit-image
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    import skimage.data as skd

    if name == "motorcycle_left":
        img = skd.stereo_motorcycle()[0]
    elif name == "motorcycle_right":
        img = skd.stereo_motorcycle()[1]
    else:
        img = getattr(skd, name)()
    img = np.asarray(img)[..., :3]
    return img.astype(np.float32) / 255.0


@functools.lru_cache(maxsize=None)
def _texture(name: str) -> np.ndarray:
    import skimage.data as skd

    return _grey01(getattr(skd, name)())


@functools.lru_cache(maxsize=None)
def _unseen_layout(name: str) -> np.ndarray:
    """Grey image (H, W) in [0, 1] of :data:`UNSEEN_LAYOUTS` ``name``, the same on every call."""
    import skimage.data as skd

    if name == "binary_blobs":  # random per call unless seeded
        return _grey01(skd.binary_blobs(length=512, rng=0))
    if name == "lfw_faces":  # 64 faces of 25 px, 8 × 8
        return _grey01(np.asarray(skd.lfw_subset()[:64]).reshape(8, 8, 25, 25).transpose(0, 2, 1, 3).reshape(200, 200))
    return _texture(name)


def _grey01(img) -> np.ndarray:
    """An image (H, W) or (H, W, ≥3) as grey float32 stretched to [0, 1] between its 1st and 99th percentiles."""
    img = np.asarray(img, dtype=np.float32)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def _random_crop(rng: np.random.Generator, img: np.ndarray, size: int, max_zoom_out: float = 2.0) -> np.ndarray:
    """A square crop resized to size×size (downscaling by at most ``max_zoom_out``), random flip."""
    from skimage.transform import resize

    h, w = img.shape[:2]
    m = min(h, w)
    lo = min(size, m)
    hi = min(m, int(size * max_zoom_out))
    side = int(rng.integers(lo, hi + 1)) if hi > lo else lo
    y = int(rng.integers(0, h - side + 1))
    x = int(rng.integers(0, w - side + 1))
    crop = img[y:y + side, x:x + side]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    if side != size:
        crop = resize(crop, (size, size) + crop.shape[2:], order=1, anti_aliasing=side > size, preserve_range=True)
    return np.ascontiguousarray(crop, dtype=np.float32)


# ------------------------------------------------------------------------------------------------
# Spatial building blocks
# ------------------------------------------------------------------------------------------------
def smooth_field(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """A smooth random field (size, size) in [0, 1]: Gaussian-weighted blend of cells×cells noise."""
    g = rng.standard_normal((cells, cells))
    pos = (np.arange(size) + 0.5) / size * cells - 0.5
    a = np.exp(-0.5 * ((pos[:, None] - np.arange(cells)[None, :]) / 0.8) ** 2)
    a /= a.sum(axis=1, keepdims=True)
    f = a @ g @ a.T
    f -= f.min()
    return (f / max(float(f.max()), 1e-12)).astype(np.float32)


def dead_leaves_labels(rng: np.random.Generator, size: int, n_leaves: int, r_min: float, r_max: float,
                       alpha: float = 3.0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Label map (size, size) of occluding shapes with radii ∝ r^-alpha; 0 is the background.

    Returns the labels and per-leaf parameters (index 0 = background): centre, radius.
    """
    labels = np.zeros((size, size), dtype=np.int32)
    u = rng.random(n_leaves)
    k = 1.0 - alpha
    radii = (r_min ** k + u * (r_max ** k - r_min ** k)) ** (1.0 / k)
    cy = rng.uniform(-0.05, 1.05, n_leaves) * size
    cx = rng.uniform(-0.05, 1.05, n_leaves) * size
    kind = rng.choice(3, n_leaves, p=[0.55, 0.25, 0.20])  # disc, ellipse, rotated rectangle
    angle = rng.uniform(0, np.pi, n_leaves)
    aspect = rng.uniform(0.35, 1.0, n_leaves)
    for j in range(n_leaves):
        r = radii[j]
        y0, y1 = max(int(cy[j] - r), 0), min(int(cy[j] + r) + 2, size)
        x0, x1 = max(int(cx[j] - r), 0), min(int(cx[j] + r) + 2, size)
        if y0 >= y1 or x0 >= x1:
            continue
        yy = np.arange(y0, y1, dtype=np.float32)[:, None] + 0.5 - cy[j]
        xx = np.arange(x0, x1, dtype=np.float32)[None, :] + 0.5 - cx[j]
        if kind[j] == 0:
            mask = yy * yy + xx * xx <= r * r
        else:
            c, s = np.cos(angle[j]), np.sin(angle[j])
            u_ = xx * c + yy * s
            v_ = -xx * s + yy * c
            b = r * aspect[j]
            if kind[j] == 1:
                mask = (u_ / r) ** 2 + (v_ / b) ** 2 <= 1.0
            else:
                mask = (np.abs(u_) <= r * 0.8) & (np.abs(v_) <= b * 0.8)
        labels[y0:y1, x0:x1][mask] = j + 1
    params = {"cy": np.concatenate([[size / 2], cy]), "cx": np.concatenate([[size / 2], cx]),
              "r": np.concatenate([[size], radii])}
    return labels, params




def power_law_noise(rng: np.random.Generator, size: int, beta: float) -> np.ndarray:
    """A random field (size, size) in [0, 1] with power spectrum ∝ 1/f^beta (detail down to 1 px)."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape))
    t = np.fft.irfft2(spec, s=(size, size))
    lo, hi = np.percentile(t, [1, 99])
    return np.clip((t - lo) / max(hi - lo, 1e-12), 0.0, 1.0).astype(np.float32)


def line_coverage(size: int, y0: float, x0: float, y1: float, x1: float, width: float) -> tuple[slice, slice, np.ndarray]:
    """Anti-aliased coverage in [0, 1] of a line segment of ``width`` px: (rows, cols, window).

    The fraction of each pixel the line covers, as a ramp across the pixel edges: 1 px from the
    line's edge at most, capped at ``width`` for a line narrower than a pixel, so each column across a
    straight line sums to ``width`` (its area per px of length) at every width. Before generator
    version 3 a line narrower than a pixel was scaled by its width twice (a 0.5 px line carried 0.28 px
    of ink).
    """
    pad = width / 2.0 + 1.5
    ya, yb = max(int(min(y0, y1) - pad), 0), min(int(max(y0, y1) + pad) + 1, size)
    xa, xb = max(int(min(x0, x1) - pad), 0), min(int(max(x0, x1) + pad) + 1, size)
    if ya >= yb or xa >= xb:
        return slice(0, 0), slice(0, 0), np.zeros((0, 0), dtype=np.float32)
    yy = np.arange(ya, yb, dtype=np.float32)[:, None] + 0.5
    xx = np.arange(xa, xb, dtype=np.float32)[None, :] + 0.5
    dy, dx = y1 - y0, x1 - x0
    length2 = max(dy * dy + dx * dx, 1e-9)
    t = np.clip(((yy - y0) * dy + (xx - x0) * dx) / length2, 0.0, 1.0)
    dist = np.hypot(yy - (y0 + t * dy), xx - (x0 + t * dx))
    cov = np.clip(width / 2.0 + 0.5 - dist, 0.0, min(width, 1.0))
    return slice(ya, yb), slice(xa, xb), cov.astype(np.float32)


def glyph_text(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Text-like mask (h, w) in {0, 1}: rows of random 3×5 glyphs at 1-3 px per glyph cell."""
    s = int(rng.integers(1, 4))
    gh, gw = 5 * s, 3 * s
    rows = max(1, (h + 2 * s) // (gh + 2 * s))
    cols = max(1, (w + s) // (gw + s))
    bits = rng.random((rows, cols, 5, 3)) < 0.55
    bits[rng.random((rows, cols)) < 0.18] = False  # word gaps
    cell = np.zeros((rows, 5 + 2, cols, 3 + 1), dtype=np.float32)
    cell[:, :5, :, :3] = bits.transpose(0, 2, 1, 3)
    mask = np.kron(cell.reshape(rows * 7, cols * 4), np.ones((s, s), dtype=np.float32))
    out = np.zeros((h, w), dtype=np.float32)
    hh, ww = min(h, mask.shape[0]), min(w, mask.shape[1])
    out[:hh, :ww] = mask[:hh, :ww]
    return out


def _pattern(rng: np.random.Generator, n: int) -> tuple[np.ndarray, str]:
    """A fine-structure pattern (n, n) in [0, 1] and its name."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32) + 0.5 - n / 2
    kinds = ("siemens_star", "bars", "zone_plate", "slanted_edge", "checkerboard", "text", "thin_lines", "glyphs")
    kind = kinds[int(rng.integers(len(kinds)))]
    if kind == "siemens_star":
        spokes = int(rng.integers(8, 37))
        t = (np.sin(spokes * np.arctan2(yy, xx)) > 0).astype(np.float32)
    elif kind == "bars":
        period = float(rng.uniform(2.0, 16.0))
        theta = float(rng.uniform(0, np.pi))
        t = ((np.cos(theta) * xx + np.sin(theta) * yy) % period < period / 2).astype(np.float32)
    elif kind == "zone_plate":
        k = float(rng.uniform(0.5, 1.0)) * np.pi / n
        t = 0.5 + 0.5 * np.cos(k * (xx ** 2 + yy ** 2))
    elif kind == "slanted_edge":
        theta = np.deg2rad(float(rng.uniform(2.0, 12.0))) + float(rng.integers(4)) * np.pi / 2
        t = (np.cos(theta) * xx + np.sin(theta) * yy > 0).astype(np.float32)
    elif kind == "checkerboard":
        period = int(rng.integers(1, 17))
        t = (((xx + n) // period + (yy + n) // period) % 2).astype(np.float32)
    elif kind == "text":
        page = _texture(PATTERN_IMAGES[int(rng.integers(2))])
        t = _random_crop(rng, page, n, max_zoom_out=1.0)
        t = (t > 0.5).astype(np.float32)
    elif kind == "thin_lines":
        t = np.zeros((n, n), dtype=np.float32)
        for _ in range(int(rng.integers(5, 30))):
            y0, x0, y1, x1 = rng.uniform(-0.2, 1.2, 4) * n
            ys, xs, cov = line_coverage(n, y0, x0, y1, x1, float(rng.uniform(0.4, 2.5)))
            t[ys, xs] = np.maximum(t[ys, xs], cov)
    else:
        t = glyph_text(rng, n, n)
    return t.astype(np.float32), kind


# ------------------------------------------------------------------------------------------------
# Spectra of a scene (drawn from the library it is given: a training scene never sees held-out ones)
# ------------------------------------------------------------------------------------------------
def _km_ks(r: np.ndarray) -> np.ndarray:
    r = np.clip(r, 1e-3, 1.0)
    return (1.0 - r) ** 2 / (2.0 * r)


def _km_r(ks: np.ndarray) -> np.ndarray:
    return 1.0 + ks - np.sqrt(ks * ks + 2.0 * ks)


def palette(rng: np.random.Generator, lib: SpectralLibrary, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` reflectances (k, C) float32 in [0, 1] and their kind index into :data:`PALETTE_KINDS`.

    measured: a library spectrum; mix: linear mixture of two (side-by-side fibres, sub-pixel
    mixing); pigment: Kubelka-Munk mixture of three (K/S additive); layer: a glaze over a base,
    ``r1 · r2^d``; wet: ``r^γ``, γ ∈ [1.3, 2.5] (darker, more saturated); basis: a draw around a
    measured spectrum in the space of the library's first 8 principal components, negatives set to 0
    and scaled into [0, 1]
    (only when the library has a basis: never in held-out sets).
    """
    refl = lib.reflectances.astype(np.float64)
    n_refl = refl.shape[0]
    p = _PALETTE_P.copy()
    if lib.basis is None:
        p[0] += p[5]
        p[5] = 0.0
    kind = rng.choice(len(PALETTE_KINDS), size=k, p=p / p.sum())
    i1, i2, i3 = rng.integers(n_refl, size=(3, k))
    t = rng.uniform(0.15, 0.85, (k, 1))
    w = rng.dirichlet([1.0, 1.0, 1.0], size=k)
    depth = rng.uniform(0.4, 1.6, (k, 1))
    gamma = rng.uniform(1.3, 2.5, (k, 1))
    z = rng.standard_normal((k, 8))
    r1, r2, r3 = refl[i1], refl[i2], refl[i3]
    out = r1.copy()
    m = kind == 1
    out[m] = t[m] * r1[m] + (1.0 - t[m]) * r2[m]
    m = kind == 2
    if m.any():
        ks = w[m, 0:1] * _km_ks(r1[m]) + w[m, 1:2] * _km_ks(r2[m]) + w[m, 2:3] * _km_ks(r3[m])
        out[m] = _km_r(ks)
    m = kind == 3
    out[m] = r1[m] * r2[m] ** depth[m]
    m = kind == 4
    out[m] = r1[m] ** gamma[m]
    m = kind == 5
    if m.any() and lib.basis is not None:
        b = lib.basis
        q = b.components.shape[0]
        a = b.coeffs[i1[m]] + 0.5 * z[m, :q] * b.sigma
        draw = np.maximum(b.mean + a @ b.components, 0.0)
        # project into [0, 1] by scaling (clipping at 1 would flatten bright draws into a spectrally flat white)
        out[m] = draw / np.maximum(draw.max(axis=1, keepdims=True), 1.0)
    return np.clip(out, 0.0, 1.0).astype(np.float32), kind


def _pick_illuminant(rng: np.random.Generator, lib: SpectralLibrary, group: str | None = None) -> int:
    groups = [g for g in _ILLUMINANT_GROUP_WEIGHTS if g in lib.illuminant_groups]
    p = np.array([_ILLUMINANT_GROUP_WEIGHTS[g] for g in groups])
    g = groups[int(rng.choice(len(groups), p=p / p.sum()))]
    if group is not None and group in lib.illuminant_groups:
        g = group
    members = lib.illuminant_groups[g]
    return int(members[int(rng.integers(len(members)))])


def _details(rng: np.random.Generator, albedo: np.ndarray, lib: SpectralLibrary) -> dict[str, Any]:
    """Paint thin lines, a block of glyphs and small occluders onto ``albedo`` (H, W, C) in place."""
    size = albedo.shape[0]
    n_lines = int(rng.integers(3, 25))
    spectra, _ = palette(rng, lib, n_lines + 2)
    for j in range(n_lines):
        y0, x0 = rng.uniform(0, size, 2)
        length = float(rng.uniform(size / 10, size))
        ang = float(rng.uniform(0, np.pi))
        ys, xs, cov = line_coverage(size, y0, x0, y0 + length * np.sin(ang), x0 + length * np.cos(ang),
                                    float(rng.uniform(0.4, 2.5)))
        if cov.size:
            a = cov[..., None]
            albedo[ys, xs] = albedo[ys, xs] * (1.0 - a) + a * spectra[j]
    text = rng.random() < 0.5
    if text:
        h, w = (int(v) for v in rng.integers(size // 8, size // 2 + 1, 2))
        y, x = int(rng.integers(0, size - h + 1)), int(rng.integers(0, size - w + 1))
        mask = glyph_text(rng, h, w)[..., None]
        albedo[y:y + h, x:x + w] = albedo[y:y + h, x:x + w] * (1.0 - mask) + mask * spectra[n_lines]
    small = rng.random() < 0.5
    if small:
        labels, _ = dead_leaves_labels(rng, size, int(rng.integers(50, 300)), 0.5, max(2.0, size / 40.0))
        spots, _ = palette(rng, lib, int(labels.max()) + 1)
        hit = labels > 0
        albedo[hit] = spots[labels[hit]]
    return {"thin_lines": n_lines, "glyphs": bool(text), "small_occluders": bool(small)}


# ------------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------------
Scene = tuple[np.ndarray, dict[str, Any], np.ndarray | None]


def _count(kinds: np.ndarray) -> dict[str, int]:
    return {PALETTE_KINDS[k]: int(v) for k, v in zip(*np.unique(kinds, return_counts=True))}


def _scene_photo(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> Scene:
    name = PHOTOS[int(rng.integers(len(PHOTOS)))]
    rgb = _random_crop(rng, _photo(name), size)
    if lib.otsu is not None and lib.srgb_to_xyz is not None:
        xyz = np.asarray(lib.srgb_to_xyz(rgb.reshape(-1, 3).astype(np.float64)))
        refl = (lib.otsu.reflectance(xyz) @ lib.otsu.to_bands.T).reshape(size, size, -1).astype(np.float32)
        info: dict[str, Any] = {"photo": name, "spectra": "otsu2018"}
    else:  # the photo's RGB as weights of three library spectra
        spectra, kinds = palette(rng, lib, 3)
        wts = rgb / max(float(rgb.sum(axis=2).max()), 1.0)
        refl = np.einsum("hwk,kc->hwc", wts, spectra).astype(np.float32)
        info = {"photo": name, "spectra": "palette", "palette": _count(kinds)}
    if rng.random() < 0.3:
        info["details"] = _details(rng, refl, lib)
    return refl, info, None


def _leaves(rng: np.random.Generator, size: int, lib: SpectralLibrary, n_big: int, n_small: int
            ) -> tuple[np.ndarray, dict[str, Any]]:
    """Dead leaves at every scale: a covering layer (r ≥ ~1.5 px) and tiny occluders (0.5-3 px) on top."""
    labels, prm = dead_leaves_labels(rng, size, n_leaves=n_big, r_min=max(1.5, size / 128.0),
                                     r_max=size / float(rng.uniform(2.5, 6.0)))
    small, prm2 = dead_leaves_labels(rng, size, n_leaves=n_small, r_min=0.5, r_max=3.0)
    hit = small > 0
    labels[hit] = small[hit] + n_big
    prm = {k: np.concatenate([prm[k], prm2[k][1:]]) for k in prm}
    n = prm["r"].size
    spectra, kinds = palette(rng, lib, n)
    albedo = spectra[labels]  # (H, W, C)
    bright = rng.uniform(0.3, 1.0, n).astype(np.float32)
    gy, gx = rng.normal(0, 0.35, n), rng.normal(0, 0.35, n)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    rr = prm["r"][labels]
    shade = bright[labels] * np.clip(1.0 + ((yy - prm["cy"][labels]) * gy[labels] + (xx - prm["cx"][labels]) * gx[labels])
                                     / np.maximum(rr, 1.0), 0.3, 1.4)
    textured = rng.random(n) < 0.3
    if rng.random() < 0.5:
        tex_name = TEXTURES[int(rng.integers(3))]
        tex = _random_crop(rng, _texture(tex_name), size)
    else:
        beta = float(rng.uniform(0.6, 2.0))
        tex_name = f"power_law(beta={beta:.2f})"
        tex = power_law_noise(rng, size, beta)
    depth = float(rng.uniform(0.2, 0.7))
    shade = np.where(textured[labels], shade * (1.0 - depth + depth * tex), shade)
    albedo *= shade[..., None].astype(np.float32)
    return albedo, {"leaves": int(n - 1), "texture": tex_name, "palette": _count(kinds)}


def _scene_dead_leaves(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> Scene:
    albedo, info = _leaves(rng, size, lib, int(rng.integers(1500, 2500)), int(rng.integers(200, 1200)))
    if rng.random() < 0.5:
        info["details"] = _details(rng, albedo, lib)
    return albedo, info, None


def _scene_smooth(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> Scene:
    k = int(rng.integers(2, 5))
    spectra, kinds = palette(rng, lib, k)
    fields = np.stack([smooth_field(rng, size, int(rng.integers(2, 6))) for _ in range(k)])
    sharp = float(rng.uniform(2.0, 10.0))
    w = np.exp(sharp * (fields - fields.max(axis=0, keepdims=True)))
    w /= w.sum(axis=0, keepdims=True)
    albedo = np.einsum("khw,kc->hwc", w, spectra).astype(np.float32)
    grain = power_law_noise(rng, size, float(rng.uniform(0.5, 1.5)))
    depth = float(rng.uniform(0.1, 0.35))
    albedo *= (1.0 - depth + depth * grain)[..., None]
    info = {"blend": k, "palette": _count(kinds), "grain_depth": round(depth, 3)}
    info["details"] = _details(rng, albedo, lib)
    return albedo, info, None


def _procedural_texture(rng: np.random.Generator, size: int) -> tuple[np.ndarray, str]:
    kind = ("power_law", "weave", "speckle")[int(rng.integers(3))]
    if kind == "power_law":
        return power_law_noise(rng, size, float(rng.uniform(0.5, 2.2))), kind
    if kind == "weave":
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        py, px = rng.uniform(2.0, 8.0, 2)
        theta = float(rng.uniform(0, np.pi))
        u, v = np.cos(theta) * xx + np.sin(theta) * yy, -np.sin(theta) * xx + np.cos(theta) * yy
        warp = 0.5 * power_law_noise(rng, size, 2.5)
        t = 0.5 + 0.25 * np.sin(2 * np.pi * (u / px + warp)) + 0.25 * np.sign(np.sin(2 * np.pi * v / py))
        return np.clip(t, 0, 1).astype(np.float32), kind
    t = power_law_noise(rng, size, float(rng.uniform(0.0, 1.0)))
    return (t > float(rng.uniform(0.3, 0.7))).astype(np.float32), kind


def _scene_texture(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> Scene:
    if rng.random() < 0.5:
        name = TEXTURES[int(rng.integers(len(TEXTURES)))]
        t = _random_crop(rng, _texture(name), size, max_zoom_out=1.5)
    else:
        t, name = _procedural_texture(rng, size)
    t = t ** float(rng.uniform(0.6, 1.6))
    albedo, k, kinds = _materials(rng, t, lib)
    info: dict[str, Any] = {"texture": name, "materials": k, "palette": _count(kinds)}
    if rng.random() < 0.3:
        info["details"] = _details(rng, albedo, lib)
    return albedo, info, None


def _materials(rng: np.random.Generator, t: np.ndarray, lib: SpectralLibrary) -> tuple[np.ndarray, int, np.ndarray]:
    """A grey layout ``t`` (H, W) in [0, 1] painted with 2 or 3 palette spectra: (reflectance (H, W, C)
    float32, the number of materials, their palette kinds). Two blend linearly along ``t``; three
    softly quantise it."""
    k = int(rng.integers(2, 4))
    spectra, kinds = palette(rng, lib, k)
    if k == 2:
        albedo = (1.0 - t)[..., None] * spectra[0] + t[..., None] * spectra[1]
    else:  # soft quantisation of the texture into k materials
        levels = np.linspace(0.0, 1.0, k)
        w = np.exp(-((t[None] - levels[:, None, None]) ** 2) / (2 * 0.08 ** 2))
        w /= w.sum(axis=0, keepdims=True)
        albedo = np.einsum("khw,kc->hwc", w, spectra)
    return albedo.astype(np.float32), k, kinds


def _scene_edges(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> Scene:
    tiles = 2 if size < 384 else 3
    bounds = np.linspace(0, size, tiles + 1).astype(int)
    albedo = np.empty((size, size, len(lib.bands)), dtype=np.float32)
    kinds, pk = [], []
    for a in range(tiles):
        for b in range(tiles):
            y0, y1, x0, x1 = bounds[a], bounds[a + 1], bounds[b], bounds[b + 1]
            n = max(y1 - y0, x1 - x0)
            t, kind = _pattern(rng, n)
            t = t[: y1 - y0, : x1 - x0]
            (r1, r2), pkind = palette(rng, lib, 2)
            albedo[y0:y1, x0:x1] = (1.0 - t)[..., None] * r1 + t[..., None] * r2
            kinds.append(kind)
            pk.append(pkind)
    info: dict[str, Any] = {"patterns": kinds, "palette": _count(np.concatenate(pk))}
    if rng.random() < 0.3:
        info["details"] = _details(rng, albedo, lib)
    return albedo, info, None


def _scene_emitters(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> Scene:
    """A dim scene (leaves) with LED dots and their glow, a display showing glyphs, an LED sign."""
    albedo, info = _leaves(rng, size, lib, int(rng.integers(300, 900)), int(rng.integers(100, 500)))
    n_em = 0 if lib.emitters is None else lib.emitters.shape[0]
    if n_em == 0:
        info["emitters"] = []
        return albedo, info, None
    em = lib.emitters
    emission = np.zeros_like(albedo)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    names = []
    for _ in range(int(rng.integers(3, 25))):  # LED dots with a faint glow (scatter)
        j = int(rng.integers(n_em))
        cy, cx = rng.uniform(0, size, 2)
        r = float(rng.uniform(0.6, 4.0))
        level = float(rng.uniform(0.3, 1.0))
        d2 = (yy - cy) ** 2 + (xx - cx) ** 2
        dot = np.clip(r + 0.5 - np.sqrt(d2), 0.0, 1.0) * level
        glow = float(rng.uniform(0.0, 0.08)) * level * np.exp(-d2 / (2 * float(rng.uniform(2.0, 10.0)) ** 2))
        emission += (dot + glow)[..., None] * em[j]
        names.append(lib.emitter_names[j])
    if rng.random() < 0.7:  # a display: vertical subpixel stripes showing glyphs or a texture
        displays = [i for i, s in enumerate(lib.emitter_sources) if s == "displays"]
        if len(displays) >= 3 and rng.random() < 0.7:
            d0 = 3 * int(rng.integers(len(displays) // 3))
            prim = [displays[d0], displays[d0 + 1], displays[d0 + 2]]
        else:
            prim = [int(v) for v in rng.integers(n_em, size=3)]
        h, w = (int(v) for v in rng.integers(size // 6, size // 2 + 1, 2))
        y, x = int(rng.integers(0, size - h + 1)), int(rng.integers(0, size - w + 1))
        content = glyph_text(rng, h, w) if rng.random() < 0.5 else power_law_noise(rng, max(h, w), 1.5)[:h, :w]
        tint = rng.uniform(0.2, 1.0, 3)
        level = float(rng.uniform(0.3, 1.0))
        for c in range(3):
            stripe = ((np.arange(w) % 3) == c).astype(np.float32)[None, :]
            amount = level * tint[c] * (0.05 + 0.95 * content) * stripe
            emission[y:y + h, x:x + w] += amount[..., None] * em[prim[c]]
        names += [lib.emitter_names[p] for p in prim]
    if rng.random() < 0.5:  # an LED sign
        j = int(rng.integers(n_em))
        h, w = (int(v) for v in rng.integers(size // 10, size // 3 + 1, 2))
        y, x = int(rng.integers(0, size - h + 1)), int(rng.integers(0, size - w + 1))
        emission[y:y + h, x:x + w] += glyph_text(rng, h, w)[..., None] * float(rng.uniform(0.3, 1.0)) * em[j]
        names.append(lib.emitter_names[j])
    info["emitters"] = sorted(set(names))
    return albedo, info, emission


_SCENES: dict[str, Callable[..., Scene]] = {
    "photo": _scene_photo,
    "dead_leaves": _scene_dead_leaves,
    "smooth": _scene_smooth,
    "texture": _scene_texture,
    "edges": _scene_edges,
    "emitters": _scene_emitters,
}


def _soft_shadow(rng: np.random.Generator, size: int) -> np.ndarray:
    """Cast shadows (size, size) in [0, 1]: a few large occluders with a soft penumbra."""
    from scipy.ndimage import gaussian_filter

    labels, _ = dead_leaves_labels(rng, size, int(rng.integers(2, 7)), size / 8.0, size / 2.0)
    mask = (labels > 0).astype(np.float32)
    return np.clip(gaussian_filter(mask, float(rng.uniform(0.5, 6.0))), 0.0, 1.0)


def _highlights(rng: np.random.Generator, size: int) -> np.ndarray:
    """Specular highlight strength (size, size): soft lobes and 1-2 px glints."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    spec = np.zeros((size, size), dtype=np.float32)
    for _ in range(int(rng.integers(1, 5))):
        cy, cx = rng.uniform(0, size, 2)
        s = rng.uniform(0.7, max(size / 30.0, 1.5))
        spec += float(rng.uniform(0.3, 1.0)) * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))
    glints = rng.integers(0, 30)
    gy, gx = rng.integers(0, size, (2, glints))
    spec[gy, gx] += rng.uniform(0.5, 1.5, glints).astype(np.float32)
    return spec


def generate_scene(index: int, seed: int, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    """Scene ``index`` of ``seed``: (cube (C, size, size) float32 with maximum 1, info dict).

    Uses only the spectra of ``lib`` (a training or held-out library from :func:`spectral_library`).
    Held-out libraries draw from another random stream, so their scenes never repeat a training scene.
    """
    stream = [int(seed), int(index)] + ([HELDOUT_STREAM] if lib.split == "heldout" else [])
    rng = np.random.default_rng(stream)
    kind = SCHEDULE[index % len(SCHEDULE)]
    albedo, info, emission = _SCENES[kind](rng, size, lib)  # (H, W, C) reflectance (shaded)
    return _lit(rng, size, lib, kind, albedo, info, emission, f"scene {index} of seed {seed}")


def unseen_layout_scene(index: int, seed: int, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    """A scene whose spatial layout no generated scene uses: scikit-image image
    ``UNSEEN_LAYOUTS[index % 7]`` (a silhouette, microscopy cells, a phantom, a logo, a retina's
    micro-aneurysms, binary blobs, a mosaic of faces; a random crop, zoomed out by at most 1.5×, or enlarged
    bilinearly where the image is smaller than ``size``; flipped at random), painted with 2 or
    3 spectra of ``lib`` and lit as :func:`generate_scene` lights its scenes. (cube (C, size, size)
    float32 with maximum 1, info). With the held-out library (``split="heldout"``) neither its
    layout nor its spectra occur in the training scenes: a test of both kinds of generalisation
    (``scripts/unseen_layouts.py`` writes a folder of them). Drawn from its own random stream."""
    rng = np.random.default_rng([int(seed), int(index), UNSEEN_LAYOUT_STREAM])
    name = UNSEEN_LAYOUTS[index % len(UNSEEN_LAYOUTS)]
    t = _random_crop(rng, _unseen_layout(name), size, max_zoom_out=1.5)
    albedo, k, kinds = _materials(rng, t, lib)
    info = {"layout": name, "materials": k, "palette": _count(kinds)}
    return _lit(rng, size, lib, "unseen_layout", albedo, info, None, f"unseen-layout scene {index} of seed {seed}")


def _lit(rng: np.random.Generator, size: int, lib: SpectralLibrary, kind: str, albedo: np.ndarray,
         info: dict[str, Any], emission: np.ndarray | None, label: str) -> tuple[np.ndarray, dict[str, Any]]:
    """Light a scene's reflectance ``albedo`` (H, W, C) as every generated scene is lit (one source,
    two blended, or sun and sky; shading, dimming, highlights; ``emission`` added), divided by its
    maximum: (cube (C, H, W) float32, info). ``label`` names the scene in the error for a black one."""
    # illumination: one source; two blended across the scene; or sun + sky with cast shadows
    e1 = _pick_illuminant(rng, lib)
    names = [lib.illuminant_names[e1]]
    mode = ("single", "blend", "sun_sky")[int(rng.choice(3, p=[0.45, 0.2, 0.35]))]
    light = lib.illuminants[e1][None, None, :]
    if mode == "blend":
        e2 = _pick_illuminant(rng, lib)
        if rng.random() < 0.5:
            mix = smooth_field(rng, size, int(rng.integers(2, 5)))
        else:  # a soft boundary between two lit areas
            theta = rng.uniform(0, 2 * np.pi)
            yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size - 0.5
            mix = 1.0 / (1.0 + np.exp(-(np.cos(theta) * xx + np.sin(theta) * yy) / rng.uniform(0.005, 0.05)))
        mix = mix.astype(np.float32)[..., None]
        light = mix * lib.illuminants[e1] + (1.0 - mix) * lib.illuminants[e2]
        names.append(lib.illuminant_names[e2])
    elif mode == "sun_sky":  # shadows are lit only by the sky (daylight when the library has it)
        e2 = _pick_illuminant(rng, lib, group="daylight")
        sky = float(np.exp(rng.uniform(np.log(0.03), np.log(0.4))))
        shadow = _soft_shadow(rng, size)[..., None]
        light = (1.0 - shadow) * lib.illuminants[e1] + sky * lib.illuminants[e2]
        names.append(lib.illuminant_names[e2])
        info["sky_level"] = round(sky, 4)
    lo = float(rng.uniform(0.05, 0.6))
    shading = lo + (1.0 - lo) * smooth_field(rng, size, int(rng.integers(2, 5)))
    radiance = albedo * shading[..., None] * light
    dim = 1.0
    if kind == "emitters":
        dim = float(np.exp(rng.uniform(np.log(0.01), np.log(0.2))))
    elif rng.random() < 0.12:
        dim = float(np.exp(rng.uniform(np.log(0.03), np.log(0.3))))
    radiance = radiance * np.float32(dim)
    if rng.random() < 0.35 or (dim < 1.0 and emission is None):  # highlights carry the local light
        spec = _highlights(rng, size)
        radiance = radiance + (spec * float(rng.uniform(0.3, 2.0)))[..., None] * light
        info["highlights"] = True
    if emission is not None:
        radiance = radiance + emission
    cube = np.ascontiguousarray(np.transpose(radiance, (2, 0, 1)), dtype=np.float32)
    np.maximum(cube, 0.0, out=cube)
    peak = float(cube.max())
    if not peak > 0:
        raise InputError(f"synthetic: {label} came out black")  # pragma: no cover
    cube /= np.float32(peak)
    return cube, {"kind": kind, "illuminants": names, "lighting": mode, "dim": round(dim, 5), **info}


__all__ = [
    "DEFAULT_HOLDOUT",
    "GENERATOR_VERSION",
    "HELDOUT_N",
    "MANIFEST",
    "OtsuModel",
    "PALETTE_KINDS",
    "PATTERN_IMAGES",
    "SCENE_PACKAGES",
    "SOURCES",
    "SUPPORTED_RANGE_NM",
    "UNSEEN_LAYOUTS",
    "UNSEEN_LAYOUT_STREAM",
    "SpectralLibrary",
    "band_matrix",
    "cache_key",
    "check_bands",
    "damaged_scenes",
    "check_dataset_folder",
    "dataset_dir",
    "dead_leaves_labels",
    "default_cache_dir",
    "generate_dataset",
    "generate_scene",
    "glyph_text",
    "heldout_dataset",
    "heldout_roles",
    "is_complete",
    "palette",
    "parameters",
    "parse_holdout",
    "partial_set_size",
    "power_law_noise",
    "smooth_field",
    "spectral_library",
    "split_library",
    "synthetic_dataset",
    "unseen_layout_scene",
    "version_differences",
]
