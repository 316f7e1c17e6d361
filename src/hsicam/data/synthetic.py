"""The embedded synthetic hyperspectral dataset (DESIGN.md §4).

Real datasets cannot be shipped, so the default dataset is generated from material that is:
spatial structure from scikit-image's bundled photos and textures (those that load offline) and
procedural region maps; spectra from measurements shipped with colour-science.

Scene kinds (a fixed schedule over the scene index, so every kind appears in small sets):

- ``photo``: a random crop of a bundled colour photo; sRGB → XYZ → reflectance by Otsu et al.
  (2018) (colour-science's basis, 380-730 nm), vectorised here; then lit by an illuminant.
- ``dead_leaves``: occluding discs, ellipses and rotated rectangles with a power-law size
  distribution, each painted with a measured reflectance (rawtoaces' 190 training patches, the
  ColorChecker sets, CIE test colour samples), per-leaf shading gradients, some leaves textured,
  plus a few specular highlights (interface reflection = the illuminant's spectrum).
- ``smooth``: smooth spatial blends of 2-4 measured reflectances (gradients).
- ``texture``: a bundled grey-level texture (brick, grass, gravel, …) mixing two reflectances.
- ``edges``: fine periodic and sharp structure (Siemens stars, bars, zone plates, slanted edges,
  checkerboards, text) between reflectance pairs.

Every scene is lit by a CIE illuminant or measured light source (daylight of random CCT,
incandescent, fluorescent with its sharp mercury lines, LEDs, discharge lamps), sometimes by two
mixed across the scene, and shaded by a smooth field. Spectra are integrated over each band's
Gaussian response (FWHM from :class:`Bands`) on a 1 nm grid, so fluorescent lines land in the
right bands instead of being point-sampled. Each scene is divided by its maximum (values in
[0, 1]) and written as our HDF5 (:func:`hsicam.data.formats.write_cube_h5`).

Determinism: scene ``i`` of seed ``s`` is drawn from ``numpy.random.default_rng((s, i))`` and does
not depend on the number of scenes; the same seed and library versions give identical bytes.
colour-science is imported only here and only while generating; training on the cached files
does not need it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hsicam.data.formats import write_cube_h5
from hsicam.errors import InputError
from hsicam.io import write_json
from hsicam.spectral import Bands

log = logging.getLogger(__name__)

GENERATOR_VERSION = 1
MANIFEST = "manifest.json"
SCENE_PATTERN = "scene_{:04d}.h5"
SCHEDULE = ("photo", "dead_leaves", "photo", "texture", "dead_leaves", "smooth", "photo", "edges")
PHOTOS = ("astronaut", "chelsea", "coffee", "rocket", "motorcycle_left", "motorcycle_right",
          "immunohistochemistry", "colorwheel", "retina", "hubble_deep_field")
TEXTURES = ("brick", "grass", "gravel", "camera", "moon", "coins", "clock")
#: Band centres the generator can serve (Otsu 2018 covers 380-730 nm; tails are held constant).
SUPPORTED_RANGE_NM = (380.0, 730.0)
_ILLUMINANT_GROUP_WEIGHTS = {"daylight": 0.40, "fluorescent": 0.25, "incandescent": 0.13, "led": 0.15,
                             "discharge": 0.05, "other": 0.02}


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


def parameters(n: int, size: int, seed: int, bands: Bands) -> dict[str, Any]:
    """The generator parameters that determine the dataset's bytes (the cache key's content)."""
    return {"generator_version": GENERATOR_VERSION, "n": int(n), "size": int(size), "seed": int(seed),
            "bands": bands.to_dict()}


def cache_key(n: int, size: int, seed: int, bands: Bands) -> str:
    """A short hash of :func:`parameters`."""
    text = json.dumps(parameters(n, size, seed, bands), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def synthetic_dataset(n: int = 32, size: int = 256, seed: int = 0, bands: Bands | None = None,
                      cache_dir: str | os.PathLike | None = None, progress: bool | None = None) -> Path:
    """Folder of the synthetic dataset for these parameters, generated on first use and cached."""
    bands = bands or Bands.paper()
    root = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    out = root / "synthetic" / f"n{n}-s{size}-seed{seed}-{cache_key(n, size, seed, bands)}"
    if is_complete(out, n, size, seed, bands):
        log.debug("synthetic dataset cached at %s", out)
        return out
    log.info("generating the synthetic dataset (%d scenes of %dx%dx%d) in %s", n, size, size, len(bands), out)
    generate_dataset(out, n=n, size=size, seed=seed, bands=bands, progress=progress)
    return out


def is_complete(out: str | os.PathLike, n: int, size: int, seed: int, bands: Bands) -> bool:
    """True when ``out`` holds a finished dataset with exactly these parameters."""
    out = Path(out)
    man = _read_manifest(out)
    if man is None or man.get("parameters") != parameters(n, size, seed, bands):
        return False
    return all((out / s["file"]).is_file() for s in man.get("scenes", []))


def _read_manifest(out: Path) -> dict[str, Any] | None:
    try:
        return json.loads((out / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


def generate_dataset(out: str | os.PathLike, n: int, size: int, seed: int = 0, bands: Bands | None = None,
                     progress: bool | None = None) -> dict[str, Any]:
    """Write ``n`` scenes (``scene_0000.h5`` …) and ``manifest.json`` (last) into ``out``.

    Every file is written atomically; the manifest marks a finished dataset. Refuses a folder
    holding another dataset's manifest or foreign cube files. ``progress=None`` shows a tqdm bar
    only on a terminal. Returns the manifest.
    """
    from tqdm.auto import tqdm

    bands = bands or Bands.paper()
    if n < 1:
        raise InputError(f"synthetic: need at least one scene, got n={n}")
    if size < 16:
        raise InputError(f"synthetic: scenes must be at least 16 px, got size={size}")
    check_bands(bands)
    out = Path(out)
    _check_output_dir(out, n, size, seed, bands)
    out.mkdir(parents=True, exist_ok=True)
    params = parameters(n, size, seed, bands)
    lib = spectral_library(bands)
    show = sys.stderr.isatty() if progress is None else progress
    scenes = []
    sum_spectrum = np.zeros(len(bands))
    for i in tqdm(range(n), desc="synthetic scenes", unit="scene", disable=not show):
        cube, info = generate_scene(i, seed, size, lib)
        name = SCENE_PATTERN.format(i)
        meta = {"dataset": "hsicam-synthetic", "index": i, **params, **info}
        path = write_cube_h5(out / name, cube, bands, meta)
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
        "key": cache_key(n, size, seed, bands),
        "normalisation": "each scene is divided by its maximum over bands and pixels (values in [0, 1])",
        "software": _versions(),
        "sources": lib.sources,
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
    return manifest


def _check_output_dir(out: Path, n: int, size: int, seed: int, bands: Bands) -> None:
    if not out.exists():
        return
    if not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    man = _read_manifest(out)
    if man is not None and man.get("parameters") != parameters(n, size, seed, bands):
        raise InputError(f"{out}: holds a synthetic dataset with other parameters; choose another --out or remove it")
    from hsicam.data.datasets import SCENE_SUFFIXES

    foreign = [f.name for f in out.iterdir()
               if not f.name.startswith(".") and f.suffix.lower() in SCENE_SUFFIXES and not f.name.startswith("scene_")]
    if foreign:
        raise InputError(f"{out}: holds other cube files ({', '.join(sorted(foreign)[:3])}); choose an empty --out")


def _round(v: np.ndarray) -> list[float]:
    return [round(float(x), 6) for x in v]


def _versions() -> dict[str, str]:
    from importlib import metadata

    out = {}
    for dist in ("hsicam", "colour-science", "numpy", "scikit-image", "h5py"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "unknown"
    return out


def check_bands(bands: Bands) -> None:
    lo, hi = SUPPORTED_RANGE_NM
    if bands.min_nm < lo or bands.max_nm > hi:
        raise InputError(f"synthetic: bands {bands.min_nm:g}-{bands.max_nm:g} nm are outside the generator's "
                         f"{lo:g}-{hi:g} nm (the range of its measured spectra)")


# ------------------------------------------------------------------------------------------------
# Spectral library (built once per band grid; the only place colour-science is used)
# ------------------------------------------------------------------------------------------------
@dataclass
class SpectralLibrary:
    """Measured spectra integrated onto a band grid."""

    bands: Bands
    reflectances: np.ndarray  # (K, C) float32
    reflectance_names: list[str]
    illuminants: np.ndarray  # (L, C) float32, mean 1 over the bands
    illuminant_names: list[str]
    illuminant_groups: dict[str, list[int]]
    otsu: "OtsuModel"
    srgb_to_xyz: Callable[[np.ndarray], np.ndarray]
    sources: dict[str, Any] = field(default_factory=dict)


def band_matrix(bands: Bands, fine_nm: np.ndarray) -> np.ndarray:
    """G (C, F): band-averaging weights of each band's Gaussian response (FWHM) on the fine grid."""
    sigma = bands.fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    g = np.exp(-0.5 * ((fine_nm[None, :] - bands.centers_nm[:, None]) / sigma[:, None]) ** 2)
    g[np.abs(fine_nm[None, :] - bands.centers_nm[:, None]) > 3.0 * sigma[:, None]] = 0.0
    return g / g.sum(axis=1, keepdims=True)


def _fine_grid(bands: Bands) -> np.ndarray:
    sigma_max = float(bands.fwhm_nm.max()) / 2.3548
    lo = np.floor(bands.min_nm - 3 * sigma_max)
    hi = np.ceil(bands.max_nm + 3 * sigma_max)
    return np.arange(lo, hi + 0.5, 1.0)


def _illuminant_group(name: str) -> str | None:
    if name.startswith("ISO 7589") or name == "LPS":
        return None  # ISO 7589 stops at 690 nm; low-pressure sodium is monochromatic
    if name.startswith("CIE D ") or name in ("D50", "D55", "D60", "D65", "D75", "ID50", "ID65", "B", "C"):
        return "daylight"
    if name in ("A", "SA", "SC", "Incandescent", "60 A/W (Soft White)", "Neodimium Incandescent"):
        return "incandescent" if name != "SC" else "daylight"
    if "LED" in name or name.startswith("PHOS") or name.startswith("Luxeon"):
        return "led"
    if name.startswith(("FL", "F32", "F34", "F40", "T8", "Philips", "Thorn")) or name.endswith(" FL") or name == "Natural":
        return "fluorescent"
    if name.startswith(("HP", "MHC", "H38", "SDW", "C100")) or name in ("HPS", "Super HPS", "Mercury", "Metal Halide"):
        return "discharge"
    return "other"


@functools.lru_cache(maxsize=4)
def _library_cached(centers: tuple[float, ...], fwhm: tuple[float, ...]) -> SpectralLibrary:
    import colour
    from colour.characterisation import read_training_data_rawtoaces_v1
    from colour.quality.datasets import SDS_TCS

    bands = Bands(np.array(centers), np.array(fwhm))
    fine = _fine_grid(bands)
    G = band_matrix(bands, fine)

    def integrate(wl: np.ndarray, values: np.ndarray) -> np.ndarray:
        # linear interpolation onto the fine grid (ends held constant), then band averaging
        return G @ np.interp(fine, wl, values)

    def covers(wl: np.ndarray) -> bool:
        return wl[0] <= fine[0] + 10.0 and wl[-1] >= fine[-1] - 10.0

    refl, names, counts = [], [], {}
    td = read_training_data_rawtoaces_v1()
    for j, label in enumerate(td.labels):
        refl.append(integrate(td.wavelengths, np.clip(td.values[:, j], 0.0, None)))
        names.append(f"rawtoaces:{label}")
    counts["rawtoaces training data v1 (190 patches)"] = len(td.labels)
    for set_name in ("ColorChecker N Ohta", "BabelColor Average", "ISO 17321-1"):
        sds = colour.SDS_COLOURCHECKERS[set_name]
        used = 0
        for patch, sd in sds.items():
            if covers(sd.wavelengths):
                refl.append(integrate(sd.wavelengths, np.clip(sd.values, 0.0, None)))
                names.append(f"{set_name}:{patch}")
                used += 1
        counts[f"ColorChecker: {set_name}"] = used
    for set_name, sds in SDS_TCS.items():
        for patch, sd in sds.items():
            refl.append(integrate(sd.wavelengths, np.clip(sd.values, 0.0, None)))
            names.append(f"TCS {set_name}:{patch}")
        counts[f"CIE test colour samples ({set_name})"] = len(sds)

    illum, inames = [], []
    candidates: list[tuple[str, np.ndarray, np.ndarray]] = []
    for cct in range(4000, 20001, 1000):
        xy = colour.temperature.CCT_to_xy_CIE_D(float(cct))
        sd = colour.sd_CIE_illuminant_D_series(xy)
        candidates.append((f"CIE D {cct}K", sd.wavelengths, sd.values))
    for src in (colour.SDS_ILLUMINANTS, colour.SDS_LIGHT_SOURCES):
        for name, sd in src.items():
            candidates.append((name, sd.wavelengths, sd.values))
    groups: dict[str, list[int]] = {}
    skipped = []
    for name, wl, values in candidates:
        group = _illuminant_group(name)
        if group is None or not covers(wl) or name in inames:
            skipped.append(name)
            continue
        e = integrate(wl, np.clip(values, 0.0, None))
        if not e.mean() > 0 or e.min() < 0:
            skipped.append(name)
            continue
        groups.setdefault(group, []).append(len(illum))
        illum.append(e / e.mean())
        inames.append(name)
    if skipped:
        log.debug("synthetic: light sources not used (range/type): %s", ", ".join(skipped))

    otsu = OtsuModel.build(bands, fine, G)
    srgb_to_xyz = functools.partial(colour.sRGB_to_XYZ)
    sources = {
        "reflectances": counts,
        "illuminants": {g: [inames[i] for i in idx] for g, idx in groups.items()},
        "rgb_to_spectrum": "Otsu, Yamamoto & Hachisuka (2018), colour-science basis (8 clusters, 380-730 nm)",
        "photos": list(PHOTOS),
        "textures": list(TEXTURES),
        "colour_science_version": colour.__version__,
    }
    return SpectralLibrary(bands, np.asarray(refl, dtype=np.float32), names, np.asarray(illum, dtype=np.float32),
                           inames, groups, otsu, srgb_to_xyz, sources)


def spectral_library(bands: Bands) -> SpectralLibrary:
    """The measured reflectances, light sources and Otsu 2018 model on ``bands`` (cached)."""
    import warnings

    check_bands(bands)
    try:
        with warnings.catch_warnings():  # colour-science reports its (expected) re-samplings as warnings
            warnings.filterwarnings("ignore", message=r".*(shape could not be honoured|Interpolating|Aligning).*")
            return _library_cached(tuple(bands.centers_nm.tolist()), tuple(bands.fwhm_nm.tolist()))
    except ImportError as exc:
        raise InputError(f"generating the synthetic dataset needs colour-science (pip install 'hsicam[synth]'): {exc}") from None


@dataclass
class OtsuModel:
    """Otsu et al. (2018) RGB→spectrum recovery, vectorised over pixels.

    Per cluster k (chosen by a kd-tree on CIE xy): reflectance = mean_k + w·basis_k with the three
    weights solving XYZ(reflectance) = XYZ under D65 and the CIE 1931 2° observer; clipped to
    [0, 1] on the 380-730 nm, 10 nm grid (as colour-science's ``XYZ_to_sd_Otsu2018``).
    """

    selector: np.ndarray  # (R, 4): origin, axis, lesser, greater
    basis: np.ndarray  # (K, 3, S)
    means: np.ndarray  # (K, S)
    m_inv: np.ndarray  # (K, 3, 3)
    xyz_mu: np.ndarray  # (K, 3)
    wavelengths: np.ndarray  # (S,)
    to_bands: np.ndarray  # (C, S): Otsu grid → band averages

    @classmethod
    def build(cls, bands: Bands, fine: np.ndarray, G: np.ndarray) -> "OtsuModel":
        from colour import SpectralDistribution, sd_to_XYZ
        from colour.colorimetry import handle_spectral_arguments
        from colour.recovery import (
            BASIS_FUNCTIONS_OTSU2018,
            CLUSTER_MEANS_OTSU2018,
            SELECTOR_ARRAY_OTSU2018,
            SPECTRAL_SHAPE_OTSU2018,
        )
        from colour.utilities import domain_range_scale

        wl = SPECTRAL_SHAPE_OTSU2018.wavelengths
        cmfs, illuminant = handle_spectral_arguments(None, None, shape_default=SPECTRAL_SHAPE_OTSU2018)
        basis = np.asarray(BASIS_FUNCTIONS_OTSU2018, dtype=np.float64)
        means = np.asarray(CLUSTER_MEANS_OTSU2018, dtype=np.float64)

        def xyz(values: np.ndarray) -> np.ndarray:
            with domain_range_scale("ignore"):
                return np.asarray(sd_to_XYZ(SpectralDistribution(values, wl), cmfs, illuminant)) / 100.0

        k = basis.shape[0]
        m_inv = np.empty((k, 3, 3))
        xyz_mu = np.empty((k, 3))
        for c in range(k):
            m = np.stack([xyz(basis[c, i]) for i in range(3)], axis=1)
            m_inv[c] = np.linalg.inv(m)
            xyz_mu[c] = xyz(means[c])
        interp = np.stack([np.interp(fine, wl, np.eye(len(wl))[j]) for j in range(len(wl))], axis=1)  # (F, S)
        return cls(np.asarray(SELECTOR_ARRAY_OTSU2018, dtype=np.float64), basis, means, m_inv, xyz_mu,
                   np.asarray(wl, dtype=np.float64), G @ interp)

    def clusters(self, xy: np.ndarray) -> np.ndarray:
        """Cluster index (N,) for chromaticities xy (N, 2), walking the selector tree."""
        n = xy.shape[0]
        node = np.zeros(n, dtype=np.int64)
        result = np.full(n, -1, dtype=np.int64)
        active = np.arange(n)
        for _ in range(self.selector.shape[0] + 1):
            if active.size == 0:
                break
            row = self.selector[node[active]]
            coord = xy[active, row[:, 1].astype(np.int64)]
            nxt = np.where(coord <= row[:, 0], row[:, 2], row[:, 3]).astype(np.int64)
            leaf = nxt >= 0
            result[active[leaf]] = nxt[leaf]
            node[active[~leaf]] = -nxt[~leaf]
            active = active[~leaf]
        return result

    def reflectance(self, xyz: np.ndarray) -> np.ndarray:
        """Recovered reflectance (N, S) on :attr:`wavelengths` for XYZ (N, 3), clipped to [0, 1]."""
        xyz = np.asarray(xyz, dtype=np.float64)
        total = xyz.sum(axis=1, keepdims=True)
        safe = np.where(total > 0, total, 1.0)
        xy = np.where(total > 0, xyz[:, :2] / safe, np.array([0.3127, 0.3290]))
        idx = self.clusters(xy)
        out = np.empty((xyz.shape[0], self.basis.shape[2]))
        for c in np.unique(idx):
            sel = idx == c
            w = (xyz[sel] - self.xyz_mu[c]) @ self.m_inv[c].T
            out[sel] = w @ self.basis[c] + self.means[c]
        return np.clip(out, 0.0, 1.0)


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

    img = np.asarray(getattr(skd, name)(), dtype=np.float32)
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


def _pattern(rng: np.random.Generator, n: int) -> tuple[np.ndarray, str]:
    """A fine-structure pattern (n, n) in [0, 1] and its name."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32) + 0.5 - n / 2
    kind = ("siemens_star", "bars", "zone_plate", "slanted_edge", "checkerboard", "text")[int(rng.integers(6))]
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
        period = int(rng.integers(2, 17))
        t = (((xx + n) // period + (yy + n) // period) % 2).astype(np.float32)
    else:
        page = _texture(("text", "page")[int(rng.integers(2))])
        t = _random_crop(rng, page, n, max_zoom_out=1.0)
        t = (t > 0.5).astype(np.float32)
    return t.astype(np.float32), kind


# ------------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------------
def _pick_illuminant(rng: np.random.Generator, lib: SpectralLibrary) -> int:
    groups = [g for g in _ILLUMINANT_GROUP_WEIGHTS if g in lib.illuminant_groups]
    p = np.array([_ILLUMINANT_GROUP_WEIGHTS[g] for g in groups])
    g = groups[int(rng.choice(len(groups), p=p / p.sum()))]
    members = lib.illuminant_groups[g]
    return int(members[int(rng.integers(len(members)))])


def _refl(rng: np.random.Generator, lib: SpectralLibrary, k: int | None = None) -> np.ndarray:
    n = lib.reflectances.shape[0]
    return rng.integers(n) if k is None else rng.integers(n, size=k)


def _scene_photo(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    name = PHOTOS[int(rng.integers(len(PHOTOS)))]
    rgb = _random_crop(rng, _photo(name), size)
    xyz = np.asarray(lib.srgb_to_xyz(rgb.reshape(-1, 3).astype(np.float64)))
    refl = lib.otsu.reflectance(xyz) @ lib.otsu.to_bands.T  # (N, C)
    return refl.reshape(size, size, -1).astype(np.float32), {"photo": name}


def _scene_dead_leaves(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    # scale-free sizes: about 2 % of the scene is left to the background
    labels, prm = dead_leaves_labels(rng, size, n_leaves=int(rng.integers(1500, 2500)),
                                     r_min=max(1.0, size / 100.0), r_max=size / float(rng.uniform(3.0, 6.0)))
    n = prm["r"].size
    idx = _refl(rng, lib, n)
    albedo = lib.reflectances[idx][labels]  # (H, W, C)
    bright = rng.uniform(0.35, 1.0, n).astype(np.float32)
    gy, gx = rng.normal(0, 0.35, n), rng.normal(0, 0.35, n)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    rr = prm["r"][labels]
    shade = bright[labels] * np.clip(1.0 + ((yy - prm["cy"][labels]) * gy[labels] + (xx - prm["cx"][labels]) * gx[labels])
                                     / np.maximum(rr, 1.0), 0.3, 1.4)
    textured = rng.random(n) < 0.3
    tex_name = TEXTURES[int(rng.integers(3))]
    tex = _random_crop(rng, _texture(tex_name), size)
    depth = float(rng.uniform(0.2, 0.6))
    shade = np.where(textured[labels], shade * (1.0 - depth + depth * tex), shade)
    albedo *= shade[..., None].astype(np.float32)
    return albedo, {"leaves": int(n - 1), "texture": tex_name}


def _scene_smooth(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    k = int(rng.integers(2, 5))
    idx = _refl(rng, lib, k)
    fields = np.stack([smooth_field(rng, size, int(rng.integers(2, 6))) for _ in range(k)])
    sharp = float(rng.uniform(2.0, 10.0))
    w = np.exp(sharp * (fields - fields.max(axis=0, keepdims=True)))
    w /= w.sum(axis=0, keepdims=True)
    albedo = np.einsum("khw,kc->hwc", w, lib.reflectances[idx]).astype(np.float32)
    return albedo, {"blend": k}


def _scene_texture(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    name = TEXTURES[int(rng.integers(len(TEXTURES)))]
    t = _random_crop(rng, _texture(name), size)
    t = t ** float(rng.uniform(0.6, 1.6))
    r1, r2 = lib.reflectances[_refl(rng, lib, 2)]
    albedo = (1.0 - t)[..., None] * r1 + t[..., None] * r2
    return albedo.astype(np.float32), {"texture": name}


def _scene_edges(rng: np.random.Generator, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    tiles = 2 if size < 384 else 3
    bounds = np.linspace(0, size, tiles + 1).astype(int)
    albedo = np.empty((size, size, len(lib.bands)), dtype=np.float32)
    kinds = []
    for a in range(tiles):
        for b in range(tiles):
            y0, y1, x0, x1 = bounds[a], bounds[a + 1], bounds[b], bounds[b + 1]
            n = max(y1 - y0, x1 - x0)
            t, kind = _pattern(rng, n)
            t = t[: y1 - y0, : x1 - x0]
            r1, r2 = lib.reflectances[_refl(rng, lib, 2)]
            albedo[y0:y1, x0:x1] = (1.0 - t)[..., None] * r1 + t[..., None] * r2
            kinds.append(kind)
    return albedo, {"patterns": kinds}


_SCENES: dict[str, Callable[..., tuple[np.ndarray, dict[str, Any]]]] = {
    "photo": _scene_photo,
    "dead_leaves": _scene_dead_leaves,
    "smooth": _scene_smooth,
    "texture": _scene_texture,
    "edges": _scene_edges,
}


def generate_scene(index: int, seed: int, size: int, lib: SpectralLibrary) -> tuple[np.ndarray, dict[str, Any]]:
    """Scene ``index`` of ``seed``: (cube (C, size, size) float32 with maximum 1, info dict)."""
    rng = np.random.default_rng([int(seed), int(index)])
    kind = SCHEDULE[index % len(SCHEDULE)]
    albedo, info = _SCENES[kind](rng, size, lib)  # (H, W, C) reflectance (shaded)
    # illumination: one light source, or two mixed across the scene (e.g. sun and shade)
    e1 = _pick_illuminant(rng, lib)
    names = [lib.illuminant_names[e1]]
    light = lib.illuminants[e1][None, None, :]
    if rng.random() < 0.3:
        e2 = _pick_illuminant(rng, lib)
        names.append(lib.illuminant_names[e2])
        if rng.random() < 0.5:
            mix = smooth_field(rng, size, int(rng.integers(2, 5)))
        else:  # a soft shadow boundary
            theta = rng.uniform(0, 2 * np.pi)
            yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size - 0.5
            mix = 1.0 / (1.0 + np.exp(-(np.cos(theta) * xx + np.sin(theta) * yy) / rng.uniform(0.005, 0.05)))
        mix = mix.astype(np.float32)[..., None]
        light = mix * lib.illuminants[e1] + (1.0 - mix) * lib.illuminants[e2]
    shading = 0.35 + 0.65 * smooth_field(rng, size, int(rng.integers(2, 5)))
    radiance = albedo * shading[..., None] * light
    if kind in ("dead_leaves", "photo") and rng.random() < 0.3:  # specular highlights
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        spec = np.zeros((size, size), dtype=np.float32)
        for _ in range(int(rng.integers(1, 4))):
            cy, cx = rng.uniform(0, size, 2)
            s = rng.uniform(1.0, max(size / 40.0, 1.5))
            spec += float(rng.uniform(0.3, 1.0)) * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))
        radiance = radiance + spec[..., None] * light
        info["highlights"] = True
    cube = np.ascontiguousarray(np.transpose(radiance, (2, 0, 1)), dtype=np.float32)
    np.maximum(cube, 0.0, out=cube)
    peak = float(cube.max())
    if not peak > 0:
        raise InputError(f"synthetic: scene {index} of seed {seed} came out black")  # pragma: no cover
    cube /= np.float32(peak)
    return cube, {"kind": kind, "illuminants": names, **info}


__all__ = [
    "GENERATOR_VERSION",
    "MANIFEST",
    "OtsuModel",
    "SpectralLibrary",
    "band_matrix",
    "cache_key",
    "dead_leaves_labels",
    "default_cache_dir",
    "generate_dataset",
    "generate_scene",
    "is_complete",
    "parameters",
    "smooth_field",
    "spectral_library",
    "synthetic_dataset",
]
