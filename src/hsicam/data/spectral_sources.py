"""Spectral sources of the synthetic generator: a registry of short stable ids, the measured
spectra behind them on a band grid, and the split of that library for the held-out protocol.

Every spectrum the generator paints comes from one *source* (a measured set shipped with
colour-science, or a documented physical model), named by a short stable id (:data:`SOURCES`).
``holdout_sources`` removes whole sources from the training scenes: :func:`split_library` gives the
training library (held-out sources removed, plus any training spectrum equal by value to a
held-out one) and the held-out library (only held-out spectra). Derived spectra (mixtures,
layers, basis draws) are made per scene from the library they are given, so a training scene can
never contain a mixture of a held-out spectrum.

colour-science is imported only while the library is built (generation), never to read data.
"""

from __future__ import annotations

import functools
import logging
import re
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from hsicam.errors import InputError
from hsicam.spectral import Bands
from hsicam.spectral.bands import BAND_REACH_SIGMA, FWHM_PER_SIGMA, band_matrix, fine_grid  # the band model (band_matrix re-exported)

log = logging.getLogger(__name__)

#: Band centres the generator can serve (Otsu 2018 covers 380-730 nm; tails are held constant).
SUPPORTED_RANGE_NM = (380.0, 730.0)

#: The oldest colour-science whose datasets the library reads: 0.4.7 (the PMC chart, and SDS_TCS as CIE 1995 and CIE
#: 2024 sets; 0.4.4-0.4.6 stop with a KeyError or AttributeError). pyproject.toml's ``synth`` extra asks for the same.
COLOUR_MIN_VERSION = (0, 4, 7)


@dataclass(frozen=True)
class Source:
    """One spectral source: ``role`` is reflectance, illuminant, emitter or rgb-upsampling."""

    id: str
    role: str
    origin: str


_SOURCE_LIST = (
    # reflectances
    Source("rawtoaces", "reflectance", "AMPAS rawtoaces training data v1: 190 measured patches "
           "(colour.characterisation.read_training_data_rawtoaces_v1)"),
    Source("colorchecker", "reflectance", "X-Rite ColorChecker Classic, three measurements: N Ohta (1997), "
           "BabelColor average (2012), ISO 17321-1 (colour.SDS_COLOURCHECKERS)"),
    Source("pmc", "reflectance", "PMC chart, Luo (2024), 400-700 nm (colour.SDS_COLOURCHECKERS['PMC']); used only "
           "when the bands lie inside its range"),
    Source("cie-tcs", "reflectance", "CIE 13.3 test colour samples: TCS01-14 (CIE 1995) and TCS01-15 (CIE 2024) "
           "(colour.quality.datasets.SDS_TCS)"),
    Source("nist-cqs", "reflectance", "NIST Colour Quality Scale samples VS1-15, versions 7.4 and 9.0, Ohno & Davis "
           "(colour.quality.datasets.SDS_VS)"),
    Source("cie-ces", "reflectance", "CIE 224:2017 colour fidelity index: 99 colour evaluation samples "
           "(colour.quality.cfi2017.load_TCS_CIE2017)"),
    Source("rgb-basis", "reflectance", "RGB-to-spectrum basis reflectances: Mallett & Yuksel (2019) sRGB basis (3); "
           "Smits (1999) basis (7) when the bands lie inside its 380-720 nm"),
    # light sources
    Source("cie-daylight", "illuminant", "CIE daylight: D-series computed for 4000-20000 K in 1000 K steps, D50, D55, "
           "D60, D65, D75, ID50, ID65 (indoor), B, C (colour.SDS_ILLUMINANTS, colour.sd_CIE_illuminant_D_series)"),
    Source("cie-a", "illuminant", "CIE illuminant A, tungsten 2856 K (colour.SDS_ILLUMINANTS)"),
    Source("blackbody", "illuminant", "Planckian radiators 2000-5000 K in 250 K steps (colour.sd_blackbody): "
           "incandescent and flame-like light"),
    Source("cie-fl", "illuminant", "CIE fluorescent FL1-FL12 and FL3.1-FL3.15 (colour.SDS_ILLUMINANTS)"),
    Source("cie-hp", "illuminant", "CIE high-pressure discharge HP1-HP5 (colour.SDS_ILLUMINANTS)"),
    Source("cie-led", "illuminant", "CIE LED illuminants LED-B1..B5, BH1, RGB1, V1, V2 (colour.SDS_ILLUMINANTS)"),
    Source("rit", "illuminant", "RIT measured light sources: Natural, Philips TL-84, SA, SC, T8 Luxline Plus White, "
           "T8 Polylux 3000/4000, Thorn Kolor-rite (colour SDS_LIGHT_SOURCES_RIT)"),
    Source("nist-traditional", "illuminant", "NIST CQS traditional lamps: fluorescent, incandescent, HPS, mercury, "
           "metal halide; its low-pressure sodium lamp (LPS, 589 nm) is used as an emitter "
           "(colour SDS_LIGHT_SOURCES_NIST_TRADITIONAL)"),
    Source("nist-led", "illuminant", "NIST CQS LED lamps: 3- and 4-LED mixtures, phosphor LEDs "
           "(colour SDS_LIGHT_SOURCES_NIST_LED)"),
    Source("nist-philips", "illuminant", "NIST CQS Philips lamps: triphosphor and broadband fluorescent, HPS, "
           "mercury, metal halide, soft-white incandescent (colour SDS_LIGHT_SOURCES_NIST_PHILIPS)"),
    Source("kinoton", "illuminant", "Kinoton 75P cinema projector lamp (colour SDS_LIGHT_SOURCES_COMMON)"),
    # emitters (seen directly, not as illumination)
    Source("led-model", "emitter", "near-monochromatic LEDs, Ohno (2005) model (colour.sd_single_led): peaks "
           "430-710 nm in 10 nm steps, half-widths 15, 25 and 35 nm"),
    Source("displays", "emitter", "display primaries R, G, B: typical CRT (Brainard 1997) and Apple Studio "
           "Display LCD (colour.MSDS_DISPLAY_PRIMARIES)"),
    # RGB upsampling of photos
    Source("otsu2018", "rgb-upsampling", "Otsu, Yamamoto & Hachisuka (2018) RGB-to-spectrum basis (8 clusters, "
           "380-730 nm; colour.recovery) for scikit-image's photos; holding it out removes the photo-upsampled "
           "spectra (photo scenes are then painted with library spectra)"),
)
SOURCES: dict[str, Source] = {s.id: s for s in _SOURCE_LIST}
#: The default held-out sources of the embedded dataset: one reflectance set and one lamp collection.
DEFAULT_HOLDOUT: tuple[str, ...] = ("nist-philips", "rawtoaces")
#: Value tolerance (max |difference| over bands; illuminants at mean 1, reflectances in [0, 1]) under
#: which a training spectrum counts as the same spectrum as a held-out one and is dropped.
SAME_SPECTRUM_ATOL = 0.005


def parse_holdout(value: str | Iterable[str] | None) -> tuple[str, ...]:
    """Held-out source ids, sorted and unique, from ``"a,b"`` or a sequence.

    ``None``, ``""``, ``"none"`` and an empty sequence mean no held-out source. An unknown id is one
    :class:`InputError` listing the valid ids.
    """
    if value is None:
        return ()
    if isinstance(value, str):
        items = [] if value.strip().lower() in ("", "none") else value.split(",")
    else:
        items = list(value)
    ids = sorted({str(v).strip() for v in items if str(v).strip()})
    unknown = [i for i in ids if i not in SOURCES]
    if unknown:
        raise InputError(f"unknown spectral source(s) {', '.join(unknown)}; valid ids: {', '.join(SOURCES)}")
    return tuple(ids)


#: Where every source is used (nm): each band's centre ± 3σ (± 1.27 FWHM) must stay inside it, since a measured
#: spectrum (most span 380-730 nm or more) is used only where it reaches that far to within 10 nm.
ALL_SOURCES_RANGE_NM = (370.0, 740.0)


def check_bands(bands: Bands) -> None:
    """Refuse band centres outside :data:`SUPPORTED_RANGE_NM` (380-730 nm). Inside it, every source is used
    only while each band's centre ± 3σ (± 1.27 FWHM) stays within :data:`ALL_SOURCES_RANGE_NM` (370-740 nm:
    e.g. 390-720 nm for 10 nm bands, all of 380-730 nm for bands up to 7.8 nm wide); beyond that most spectra
    are dropped, with a WARNING."""
    lo, hi = SUPPORTED_RANGE_NM
    if bands.min_nm < lo or bands.max_nm > hi:
        a, b = ALL_SOURCES_RANGE_NM
        raise InputError(f"synthetic: bands {bands.min_nm:g}-{bands.max_nm:g} nm are outside the generator's "
                         f"{lo:g}-{hi:g} nm (the range of its measured spectra); all of them are used only for bands "
                         f"whose centre ± 1.27 FWHM stays inside {a:g}-{b:g} nm (e.g. 390-720 nm for 10 nm bands)")


# ------------------------------------------------------------------------------------------------
# The library
# ------------------------------------------------------------------------------------------------
@dataclass
class ReflectanceBasis:
    """Principal components of a reflectance set, for smooth draws inside its gamut."""

    mean: np.ndarray  # (C,)
    components: np.ndarray  # (q, C), orthonormal rows
    coeffs: np.ndarray  # (K, q): coefficients of the measured spectra
    sigma: np.ndarray  # (q,): their standard deviations

    @classmethod
    def fit(cls, refl: np.ndarray, q: int = 8) -> "ReflectanceBasis":
        x = np.asarray(refl, dtype=np.float64)
        mean = x.mean(axis=0)
        _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
        comps = vt[: min(q, vt.shape[0])]
        coeffs = (x - mean) @ comps.T
        return cls(mean, comps, coeffs, coeffs.std(axis=0) + 1e-12)


@dataclass
class SpectralLibrary:
    """Spectra integrated onto a band grid, each tagged with its source id (:data:`SOURCES`).

    ``split`` is ``"all"`` (every source), ``"train"`` or ``"heldout"`` (see :func:`split_library`).
    """

    bands: Bands
    reflectances: np.ndarray  # (K, C) float32 in [0, 1]
    reflectance_names: list[str]
    illuminants: np.ndarray  # (L, C) float32, mean 1 over the bands
    illuminant_names: list[str]
    illuminant_groups: dict[str, list[int]]
    otsu: "OtsuModel | None"
    srgb_to_xyz: Callable[[np.ndarray], np.ndarray] | None
    sources: dict[str, Any] = field(default_factory=dict)
    reflectance_sources: list[str] = field(default_factory=list)
    illuminant_sources: list[str] = field(default_factory=list)
    emitters: np.ndarray | None = None  # (M, C) float32, maximum 1 each
    emitter_names: list[str] = field(default_factory=list)
    emitter_sources: list[str] = field(default_factory=list)
    split: str = "all"
    holdout: tuple[str, ...] = ()
    basis: ReflectanceBasis | None = None  # for basis draws; None: no basis draws
    removed: list[str] = field(default_factory=list)  # training spectra dropped as equal to held-out ones
    # per source, the lights left out for being 0 on every band though they span the grid (listed with the others
    # under the manifest's not_used_out_of_range; kept apart here to say so when a held-out set is refused)
    zero_on_bands: dict[str, list[str]] = field(default_factory=dict)

    def counts(self) -> dict[str, dict[str, int]]:
        """Number of spectra per role and source id."""
        out: dict[str, dict[str, int]] = {}
        for role, srcs in (("reflectances", self.reflectance_sources), ("illuminants", self.illuminant_sources),
                           ("emitters", self.emitter_sources)):
            d: dict[str, int] = {}
            for s in srcs:
                d[s] = d.get(s, 0) + 1
            out[role] = d
        if self.otsu is not None:
            out["rgb_upsampling"] = {"otsu2018": int(self.otsu.basis.shape[0])}
        return out


#: colour-science's CIE daylight illuminants (source cie-daylight): D series, indoor daylight ID, B and C.
_CIE_DAYLIGHT = ("D50", "D55", "D60", "D65", "D75", "ID50", "ID65", "B", "C")


def _illuminant_group(name: str) -> str:
    """Lighting family used to weight the draw (daylight, fluorescent, incandescent, led, discharge, other)."""
    if name.startswith("CIE D ") or name in _CIE_DAYLIGHT or name == "SC":
        return "daylight"
    if name in ("A", "SA", "Incandescent", "60 A/W (Soft White)", "Neodimium Incandescent") or name.startswith("Planck"):
        return "incandescent"
    if "LED" in name or name.startswith("PHOS") or name.startswith("Luxeon"):
        return "led"
    if name.startswith(("FL", "F32", "F34", "F40", "T8", "Philips", "Thorn")) or name.endswith(" FL") or name == "Natural":
        return "fluorescent"
    if name.startswith(("HP", "MHC", "H38", "SDW", "C100")) or name in ("Super HPS", "Mercury", "Metal Halide"):
        return "discharge"
    return "other"


def _illuminant_groups(names: Sequence[str]) -> dict[str, list[int]]:
    """The indices of ``names`` by lighting family (:func:`_illuminant_group`), in order of first appearance."""
    groups: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        groups.setdefault(_illuminant_group(name), []).append(i)
    return groups


def _cie_illuminant_source(name: str) -> str | None:
    """The source id of colour-science's CIE illuminant ``name`` (daylight, A, fluorescent, high-pressure, LED), or
    None for one the library does not take."""
    if name in _CIE_DAYLIGHT:
        return "cie-daylight"
    if name == "A":
        return "cie-a"
    if name.startswith("FL"):
        return "cie-fl"
    if name.startswith("HP"):
        return "cie-hp"
    if name.startswith("LED"):
        return "cie-led"
    return None  # E (not a light source), ISO 7589 (stops at 690 nm)


def _check_colour_version(version: str) -> None:
    """InputError naming the upgrade when colour-science ``version`` is older than :data:`COLOUR_MIN_VERSION`
    (a version that does not parse is let through)."""
    m = re.match(r"(\d+)\.(\d+)(?:\.(\d+))?", version)
    if m and tuple(int(p or 0) for p in m.groups()) < COLOUR_MIN_VERSION:
        need = ".".join(map(str, COLOUR_MIN_VERSION))
        raise InputError(f"generating the synthetic dataset needs colour-science >= {need}, found {version} "
                         f"(pip install -U 'hsicam[synth]')")


@dataclass
class _Unused:
    """The spectra of a library being built that are left out, and the counts behind the out-of-range WARNING."""

    skipped: dict[str, list[str]] = field(default_factory=dict)  # per source: the manifest's not_used_out_of_range
    # of those, the lights that span the grid but are 0 on every band
    zero: dict[str, list[str]] = field(default_factory=dict)
    # for the out-of-range warning: per role, spectra seen and spectra dropped by source
    seen: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)
    # where the fine grid may lie for every spectrum outside the partial sets to be used; how many of those were not
    reach_lo: float = -np.inf
    reach_hi: float = np.inf
    unexpected: int = 0


#: Spectra of one role on the bands: their values, names and source ids, in the same order.
_OnBands = tuple[list[np.ndarray], list[str], list[str]]


@functools.lru_cache(maxsize=4)
def _library_cached(centers: tuple[float, ...], fwhm: tuple[float, ...]) -> SpectralLibrary:
    """The full library (split "all") on the bands of ``centers`` and ``fwhm`` (nm), built from colour-science's
    datasets: once per band grid."""
    import colour

    _check_colour_version(getattr(colour, "__version__", ""))
    bands = Bands(np.array(centers), np.array(fwhm))
    fine = fine_grid(bands)
    G = band_matrix(bands, fine)
    unused = _Unused()
    refl = _reflectances_on_bands(_measured_reflectances(), fine, G, unused)
    illum, emit = _lights_on_bands(_measured_lights(unused.skipped), fine, G, unused)
    _check_something_to_draw(bands, fine, refl, illum)
    if unused.unexpected:
        _warn_out_of_range(bands, fine, unused.seen, unused.dropped, (unused.reach_lo, unused.reach_hi))
    return _full_library(bands, fine, G, refl, illum, emit, unused)


def _measured_reflectances() -> Iterator[tuple[str, str, Any, Any]]:
    """Every reflectance of the reflectance sources (:data:`SOURCES`) as (source id, name, wavelengths in nm,
    values), in the library's order."""
    import colour
    from colour.characterisation import read_training_data_rawtoaces_v1
    from colour.quality.cfi2017 import load_TCS_CIE2017
    from colour.quality.datasets import SDS_TCS, SDS_VS
    from colour.recovery import MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019, SDS_SMITS1999

    td = read_training_data_rawtoaces_v1()
    for j, label in enumerate(td.labels):
        yield "rawtoaces", f"rawtoaces:{label}", td.wavelengths, td.values[:, j]
    for set_name in ("ColorChecker N Ohta", "BabelColor Average", "ISO 17321-1", "PMC"):
        for patch, sd in colour.SDS_COLOURCHECKERS[set_name].items():
            yield "pmc" if set_name == "PMC" else "colorchecker", f"{set_name}:{patch}", sd.wavelengths, sd.values
    for set_name, sds in SDS_TCS.items():
        for patch, sd in sds.items():
            yield "cie-tcs", f"TCS {set_name}:{patch}", sd.wavelengths, sd.values
    for set_name, sds in SDS_VS.items():
        for patch, sd in sds.items():
            yield "nist-cqs", f"CQS {set_name}:{patch}", sd.wavelengths, sd.values
    ces = load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))
    for j in range(len(ces.labels)):
        yield "cie-ces", f"CES {j + 1:02d}", ces.wavelengths, ces.values[:, j]
    mal = MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    for j, label in enumerate(mal.labels):
        yield "rgb-basis", f"Mallett 2019:{label}", mal.wavelengths, mal.values[:, j]
    for label, sd in SDS_SMITS1999.items():
        yield "rgb-basis", f"Smits 1999:{label}", sd.wavelengths, sd.values


def _measured_lights(skipped: dict[str, list[str]]) -> Iterator[tuple[str, str, Any, Any, bool]]:
    """Every spectrum of the illuminant and emitter sources as (source id, name, wavelengths in nm, values, emitter),
    in the library's order; colour-science's CIE illuminants that are no light source go to ``skipped``."""
    import colour
    from colour.colorimetry.datasets.light_sources import sds as light_sources

    for cct in range(4000, 20001, 1000):
        sd = colour.sd_CIE_illuminant_D_series(colour.temperature.CCT_to_xy_CIE_D(float(cct)))
        yield "cie-daylight", f"CIE D {cct}K", sd.wavelengths, sd.values, False
    for name, sd in colour.SDS_ILLUMINANTS.items():
        source = _cie_illuminant_source(name)
        if source is None:
            skipped.setdefault("cie (not used)", []).append(name)
            continue
        yield source, name, sd.wavelengths, sd.values, False
    shape = colour.SpectralShape(360, 780, 1)
    for t in range(2000, 5001, 250):
        sd = colour.sd_blackbody(float(t), shape)
        yield "blackbody", f"Planck {t}K", sd.wavelengths, sd.values, False
    for source, mapping in (("rit", light_sources.SDS_LIGHT_SOURCES_RIT),
                            ("nist-traditional", light_sources.SDS_LIGHT_SOURCES_NIST_TRADITIONAL),
                            ("nist-led", light_sources.SDS_LIGHT_SOURCES_NIST_LED),
                            ("nist-philips", light_sources.SDS_LIGHT_SOURCES_NIST_PHILIPS),
                            ("kinoton", light_sources.SDS_LIGHT_SOURCES_COMMON)):
        for name, sd in mapping.items():
            yield source, name, sd.wavelengths, sd.values, name == "LPS"
    for peak in range(430, 711, 10):
        for width in (15, 25, 35):
            sd = colour.sd_single_led(float(peak), shape, half_spectral_width=float(width))
            yield "led-model", f"LED {peak} nm / {width} nm", sd.wavelengths, sd.values, True
    for display, msd in colour.MSDS_DISPLAY_PRIMARIES.items():
        for j, label in enumerate(msd.labels):
            yield "displays", f"{display}:{label}", msd.wavelengths, msd.values[:, j], True


def _integrate(fine: np.ndarray, G: np.ndarray, wl: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Band averages (C,) of a spectrum sampled at ``wl`` (nm), through the fine grid and its band matrix ``G``."""
    # linear interpolation onto the fine grid (ends held constant), then band averaging
    return G @ np.interp(fine, np.asarray(wl, dtype=np.float64), np.asarray(values, dtype=np.float64))


def _out_of_range(unused: _Unused, fine: np.ndarray, role: str, source: str, name: str, wl: np.ndarray) -> bool:
    """Whether a spectrum sampled at ``wl`` (nm) does not reach the fine grid's ends to within 10 nm (then noted in
    ``unused``); counted in ``unused`` for the out-of-range WARNING either way."""
    unused.seen[role] = unused.seen.get(role, 0) + 1
    partial = name.startswith(_PARTIAL_SETS)
    if not partial:
        unused.reach_lo = max(unused.reach_lo, float(wl[0]) - 10.0)
        unused.reach_hi = min(unused.reach_hi, float(wl[-1]) + 10.0)
    if wl[0] <= fine[0] + 10.0 and wl[-1] >= fine[-1] - 10.0:
        return False
    by_source = unused.dropped.setdefault(role, {})
    by_source[source] = by_source.get(source, 0) + 1
    unused.unexpected += 0 if partial else 1
    unused.skipped.setdefault(source, []).append(name)
    return True


def _reflectances_on_bands(spectra: Iterable[tuple[str, str, Any, Any]], fine: np.ndarray, G: np.ndarray,
                           unused: _Unused) -> _OnBands:
    """The reflectances of ``spectra`` that span the fine grid, clipped to [0, 1] and band-averaged."""
    values: list[np.ndarray] = []
    names: list[str] = []
    sources: list[str] = []
    for source, name, wl, v in spectra:
        if _out_of_range(unused, fine, "reflectance", source, name, np.asarray(wl)):
            continue
        values.append(np.clip(_integrate(fine, G, wl, np.clip(v, 0.0, 1.0)), 0.0, 1.0))
        names.append(name)
        sources.append(source)
    return values, names, sources


def _lights_on_bands(spectra: Iterable[tuple[str, str, Any, Any, bool]], fine: np.ndarray, G: np.ndarray,
                     unused: _Unused) -> tuple[_OnBands, _OnBands]:
    """The illuminants (mean 1 over the bands) and emitters (maximum 1) of ``spectra`` that span the fine grid;
    one that is 0 on every band is noted in ``unused`` (``skipped`` and ``zero``)."""
    illum: _OnBands = ([], [], [])
    emit: _OnBands = ([], [], [])
    for source, name, wl, v, emitter in spectra:
        if _out_of_range(unused, fine, "emitter" if emitter else "illuminant", source, name, np.asarray(wl)):
            continue
        e = _integrate(fine, G, wl, np.clip(v, 0.0, None))
        if not e.max() > 0:
            unused.skipped.setdefault(source, []).append(name)
            unused.zero.setdefault(source, []).append(name)
            continue
        values, names, sources = emit if emitter else illum
        values.append(e / e.max() if emitter else e / e.mean())
        names.append(name)
        sources.append(source)
    return illum, emit


def _check_something_to_draw(bands: Bands, fine: np.ndarray, refl: _OnBands, illum: _OnBands) -> None:
    """InputError when no reflectance or no illuminant spans the fine grid ``fine`` of ``bands``."""
    if not refl[0] or not illum[0]:
        # each band weighs wavelengths up to 3σ of its FWHM beyond its centre; a spectrum must reach that far
        raise InputError(f"synthetic: bands {bands.min_nm:g}-{bands.max_nm:g} nm of FWHM up to "
                         f"{float(bands.fwhm_nm.max()):g} nm weigh light from {fine[0]:g} to {fine[-1]:g} nm, and no "
                         f"measured {'reflectance' if not refl[0] else 'illuminant'} spectrum spans that range: the "
                         "generator has nothing to draw scenes from; narrow the bands (bands.fwhm_nm, or a smaller "
                         "bands.step_nm), keep them further inside 380-730 nm, or train on your own data (data.root)")


def _full_library(bands: Bands, fine: np.ndarray, G: np.ndarray, refl: _OnBands, illum: _OnBands, emit: _OnBands,
                  unused: _Unused) -> SpectralLibrary:
    """The library of split "all" from the spectra on the bands, with the Otsu upsampling, the illuminant groups,
    the basis draws and its manifest description (:func:`_describe`)."""
    import colour

    otsu = OtsuModel.build(fine, G)
    rvals, rnames, rsrc = refl
    ivals, inames, isrc = illum
    evals, enames, esrc = emit
    groups = _illuminant_groups(inames)
    refl_arr = np.asarray(rvals, dtype=np.float32)
    lib = SpectralLibrary(
        bands, refl_arr, rnames, np.asarray(ivals, dtype=np.float32), inames, groups, otsu,
        functools.partial(colour.sRGB_to_XYZ), {}, rsrc, isrc, np.asarray(evals, dtype=np.float32), enames, esrc,
        split="all", holdout=(), basis=ReflectanceBasis.fit(refl_arr), zero_on_bands=unused.zero)
    lib.sources = _describe(lib, unused.skipped, colour.__version__)
    return lib


#: Sets documented as used only on bands inside their shorter range (PMC 400-700 nm, Smits 380-720 nm): dropping
#: them alone is expected (the default 420-720 nm grid does), not worth a warning.
_PARTIAL_SETS = ("PMC:", "Smits 1999:")


def _warn_out_of_range(bands: Bands, fine: np.ndarray, seen: dict[str, int], dropped: dict[str, dict[str, int]],
                       reach: tuple[float, float]) -> None:
    """The WARNING, once per library build, that spectra beyond the partial sets were dropped for not reaching
    the bands' ±3σ (fine grid ``fine``, nm; ``reach``: where it may lie to use them all, nm): the manifest's
    not_used_out_of_range alone went unnoticed (380-730 nm bands kept 43 of 423 reflectances). One short line: the
    count and the three sources that lose most; the count per role and source at DEBUG (``hsicam -v``)."""
    by_source: dict[str, int] = {}
    for d in dropped.values():
        for s, k in d.items():
            by_source[s] = by_source.get(s, 0) + k
    top = sorted(by_source.items(), key=lambda kv: -kv[1])
    names = ", ".join(f"{s} {k}" for s, k in top[:3]) + (", …" if len(top) > 3 else "")
    band_reach = BAND_REACH_SIGMA * float(bands.fwhm_nm.max()) / FWHM_PER_SIGMA
    lo, hi = round(reach[0] + band_reach, 1), round(reach[1] - band_reach, 1)
    log.warning("synthetic: %d of %d spectra (%s) do not span %g-%g nm, which bands of FWHM up to %g nm weigh: not "
                "used (by source: hsicam -v); band centres within %g-%g nm would use all but PMC and Smits",
                sum(by_source.values()), sum(seen.values()), names, fine[0], fine[-1], float(bands.fwhm_nm.max()),
                lo, hi)
    parts = [f"{sum(d.values())} of {seen[role]} {role} spectra ("
             + ", ".join(f"{s} {k}" for s, k in sorted(d.items(), key=lambda kv: -kv[1])) + ")"
             for role, d in dropped.items()]
    log.debug("synthetic: not used for bands %g-%g nm: %s (names: the manifest's not_used_out_of_range)",
              bands.min_nm, bands.max_nm, " and ".join(parts))


def _describe(lib: SpectralLibrary, skipped: dict[str, list[str]] | None = None,
              colour_version: str | None = None) -> dict[str, Any]:
    """The manifest's description of ``lib`` (its ``sources``): split, held-out sources, counts, illuminant groups by
    name, emitters, basis draws, and where there are any the training spectra removed as equal to held-out ones, the
    spectra not used (``skipped``: names per source) and the colour-science version."""
    out: dict[str, Any] = {
        "split": lib.split,
        "holdout_sources": list(lib.holdout),
        "counts": lib.counts(),
        "illuminant_groups": {g: [lib.illuminant_names[i] for i in idx] for g, idx in lib.illuminant_groups.items()},
        "emitters": list(lib.emitter_names),
        "basis_draws": lib.basis is not None,
    }
    if lib.removed:
        out["removed_as_equal_to_held_out"] = list(lib.removed)
    if skipped:
        out["not_used_out_of_range"] = skipped
    if colour_version is not None:
        out["colour_science_version"] = colour_version
    return out


def spectral_library(bands: Bands, holdout_sources: str | Iterable[str] | None = None,
                     split: str = "all") -> SpectralLibrary:
    """The spectral library on ``bands`` (built once per grid, cached).

    ``split="all"`` (default): every source. ``"train"`` / ``"heldout"``: :func:`split_library` with
    ``holdout_sources``.
    """
    import warnings

    check_bands(bands)
    try:
        with warnings.catch_warnings():  # colour-science reports its (expected) re-samplings as warnings
            warnings.filterwarnings("ignore", message=r".*(shape could not be honoured|Interpolating|Aligning).*")
            full = _library_cached(tuple(bands.centers_nm.tolist()), tuple(bands.fwhm_nm.tolist()))
    except ImportError as exc:
        raise InputError(f"generating the synthetic dataset needs colour-science (pip install 'hsicam[synth]'): {exc}") from None
    if split == "all":
        if parse_holdout(holdout_sources):
            raise InputError("spectral_library: holdout_sources needs split='train' or 'heldout'")
        return full
    return split_library(full, holdout_sources, split)


def _same_as_any(x: np.ndarray, ref: np.ndarray, atol: float) -> np.ndarray:
    """Boolean (len(x),): rows of x within ``atol`` (max abs difference) of some row of ref."""
    if x.shape[0] == 0 or ref.shape[0] == 0:
        return np.zeros(x.shape[0], dtype=bool)
    d = np.abs(x[:, None, :].astype(np.float64) - ref[None, :, :]).max(axis=2)
    return d.min(axis=1) <= atol


class NoHeldOutSpectra(InputError):
    """The held-out sources give no spectrum on this band grid (each is used only where it covers the grid's
    range, ±10 nm, and is not 0 on every band): a held-out set of them would be made of the training spectra alone."""


def _why_unused(names: list[str], zero: list[str]) -> str:
    """Why a source's spectra ``names`` are not in the library: they do not span the grid, or (``zero``) they do
    but are 0 on every band (a lamp dark at these wavelengths)."""
    out = len(names) - len(zero)
    parts = ([f"{out} spectra do not span the grid"] if out else []) + \
        ([f"{len(zero)} spectra are 0 on every band"] if zero else [])
    return " and ".join(parts)


def split_library(lib: SpectralLibrary, holdout_sources: str | Iterable[str] | None, split: str) -> SpectralLibrary:
    """The training or held-out part of a full library.

    ``"train"``: spectra of sources not held out, minus any spectrum equal (within
    :data:`SAME_SPECTRUM_ATOL`) to a held-out one of the same role; basis draws fitted on these
    reflectances only; Otsu upsampling unless ``otsu2018`` is held out.

    ``"heldout"``: only held-out spectra. Where no source of a role is held out, that role keeps the
    training spectra (e.g. holding out only lamps tests new light on known surfaces); emitters
    appear only when an emitter source is held out; no basis draws (they would be derived from a
    fit); Otsu upsampling only when ``otsu2018`` is held out.
    """
    holdout = _checked_holdout(lib, holdout_sources, split)
    held = set(holdout)
    parts, removed = _role_parts(lib, held, split)
    # which roles hold held-out spectra (a held-out set's other roles fall back to the training spectra)
    held_roles = {role: any(s in held for s in parts[role][2]) for role in parts}
    otsu_ok = ("otsu2018" in held) == (split == "heldout")  # Otsu upsampling: where its photos belong
    if split == "heldout" and "otsu2018" not in held and not any(held_roles.values()):
        # every role would fall back to the training spectra: scenes scored as "held-out sources" that are not
        raise _no_held_out_spectra(lib, holdout)
    _check_parts(parts, holdout, split, otsu_ok)
    rr, rn, rs = _reflectances_or_otsu_means(parts["reflectances"], lib.otsu)
    ir, in_, is_ = parts["illuminants"]
    er, en, es = parts["emitters"]
    sub = replace(lib, reflectances=rr, reflectance_names=rn, reflectance_sources=rs, illuminants=ir,
                  illuminant_names=in_, illuminant_sources=is_, illuminant_groups=_illuminant_groups(in_), emitters=er,
                  emitter_names=en, emitter_sources=es, otsu=lib.otsu if otsu_ok else None,
                  srgb_to_xyz=lib.srgb_to_xyz if otsu_ok else None, split=split, holdout=holdout,
                  basis=ReflectanceBasis.fit(rr) if split == "train" and rr.shape[0] >= 3 else None,
                  removed=removed if split == "train" else [])
    sub.sources = _describe(sub, lib.sources.get("not_used_out_of_range"), lib.sources.get("colour_science_version"))
    if split == "heldout":
        sub.sources["held_out_roles"] = held_roles
    return sub


#: Spectra of one role of a library: (values (K, C), names, source ids), in the same order.
_Part = tuple[np.ndarray, list[str], list[str]]


def _checked_holdout(lib: SpectralLibrary, holdout_sources: str | Iterable[str] | None, split: str) -> tuple[str, ...]:
    """The held-out source ids (:func:`parse_holdout`) for :func:`split_library`; InputError for a split other than
    "train" or "heldout", a library that is split already, or a held-out set without held-out sources."""
    holdout = parse_holdout(holdout_sources)
    if split not in ("train", "heldout"):
        raise InputError(f"split must be 'train' or 'heldout', got {split!r}")
    if lib.split != "all":
        raise InputError("split_library needs the full library (split='all')")
    if split == "heldout" and not holdout:
        raise InputError("a held-out set needs at least one held-out source (holdout_sources)")
    return holdout


def _role_parts(lib: SpectralLibrary, held: set[str], split: str) -> tuple[dict[str, _Part], list[str]]:
    """(per role, the spectra of ``split``: the training ones, or the held-out ones where the role has any (always
    for emitters); the names of the training spectra dropped as equal to a held-out one of their role, within
    :data:`SAME_SPECTRUM_ATOL`)."""
    roles = {
        "reflectances": (lib.reflectances, lib.reflectance_names, lib.reflectance_sources),
        "illuminants": (lib.illuminants, lib.illuminant_names, lib.illuminant_sources),
        "emitters": (lib.emitters, lib.emitter_names, lib.emitter_sources),
    }
    parts: dict[str, _Part] = {}
    removed: list[str] = []
    for role, (arr, names, srcs) in roles.items():
        is_held = np.array([s in held for s in srcs], dtype=bool)
        train_idx = np.flatnonzero(~is_held)
        held_idx = np.flatnonzero(is_held)
        same = _same_as_any(arr[train_idx], arr[held_idx], SAME_SPECTRUM_ATOL)
        removed += [names[i] for i in train_idx[same]]
        train_idx = train_idx[~same]
        if split == "train":
            idx = train_idx
        elif held_idx.size or role == "emitters":
            idx = held_idx
        else:
            idx = train_idx
        parts[role] = (arr[idx], [names[i] for i in idx], [srcs[i] for i in idx])
    return parts, removed


def _no_held_out_spectra(lib: SpectralLibrary, holdout: tuple[str, ...]) -> NoHeldOutSpectra:
    """The refusal of held-out sources ``holdout`` that give no spectrum on ``lib``'s bands, saying why for each
    source the library left out (:func:`_why_unused`) and which range the bands' widths need."""
    skipped = lib.sources.get("not_used_out_of_range") or {}
    why = "; ".join(f"{src}: {_why_unused(skipped[src], lib.zero_on_bands.get(src, []))}" for src in holdout
                    if src in skipped)
    fine = fine_grid(lib.bands)
    return NoHeldOutSpectra(
        f"the held-out sources {', '.join(holdout)} give no spectrum on bands {lib.bands.min_nm:g}-"
        f"{lib.bands.max_nm:g} nm, whose widths need spectra spanning {fine[0]:g}-{fine[-1]:g} nm ({why or 'none of their spectra is in the library'}): a held-out set would be "
        "the training spectra; hold out sources that cover these bands (`hsicam data sources`)")


def _check_parts(parts: dict[str, _Part], holdout: tuple[str, ...], split: str, otsu_ok: bool) -> None:
    """InputError when holding out ``holdout`` leaves the ``split`` scenes no reflectance (and no Otsu upsampling,
    ``otsu_ok``) or no light source."""
    if parts["reflectances"][0].shape[0] == 0 and not otsu_ok:
        raise InputError(f"holding out {', '.join(holdout)} leaves no reflectance for the {split} scenes")
    if parts["illuminants"][0].shape[0] == 0:
        raise InputError(f"holding out {', '.join(holdout)} leaves no light source for the {split} scenes")


def _reflectances_or_otsu_means(part: _Part, otsu: "OtsuModel | None") -> _Part:
    """The reflectances of a split, (K, C) float32 with names and source ids; where it has none, the Otsu clusters'
    mean spectra on the bands (clipped to [0, 1])."""
    rr, rn, rs = part
    if rr.shape[0] == 0:  # only photos (otsu2018) held out: paint with the Otsu clusters' mean spectra
        rr = np.clip(otsu.means @ otsu.to_bands.T, 0, 1).astype(np.float32)
        rn = [f"otsu2018:cluster {k}" for k in range(rr.shape[0])]
        rs = ["otsu2018"] * rr.shape[0]
    return rr, rn, rs


# ------------------------------------------------------------------------------------------------
# RGB -> spectrum (Otsu et al. 2018), vectorised
# ------------------------------------------------------------------------------------------------
@dataclass
class OtsuModel:
    """Otsu et al. (2018) RGB→spectrum recovery, vectorised over pixels.

    Per cluster k (chosen by a kd-tree on CIE xy): reflectance = mean_k + w·basis_k with the three
    weights solving XYZ(reflectance) = XYZ under D65 and the CIE 1931 2° observer; clipped to
    [0, 1] on the 380-730 nm, 10 nm grid (as colour-science's ``XYZ_to_sd_Otsu2018``, to 1e-9), except
    for XYZ = 0 (black), which has no chromaticity: here it takes the D65 white point's xy (the limit of
    dimmer and dimmer D65 greys), where colour-science takes xy (0, 0) and so another cluster; the two
    spectra of a black pixel differ by up to 0.03. Kept, since the synthetic scenes (and the datasets
    cached from them) are made with it.
    """

    selector: np.ndarray  # (R, 4): origin, axis, lesser, greater
    basis: np.ndarray  # (K, 3, S)
    means: np.ndarray  # (K, S)
    m_inv: np.ndarray  # (K, 3, 3)
    xyz_mu: np.ndarray  # (K, 3)
    wavelengths: np.ndarray  # (S,)
    to_bands: np.ndarray  # (C, S): Otsu grid → band averages

    @classmethod
    def build(cls, fine: np.ndarray, G: np.ndarray) -> "OtsuModel":
        """colour-science's Otsu et al. (2018) model, its spectra taken from its 10 nm grid to the bands by ``G``
        (C, F) on the fine grid ``fine`` (F,) nm."""
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



__all__ = [
    "ALL_SOURCES_RANGE_NM",
    "DEFAULT_HOLDOUT",
    "NoHeldOutSpectra",
    "OtsuModel",
    "ReflectanceBasis",
    "SAME_SPECTRUM_ATOL",
    "SOURCES",
    "SUPPORTED_RANGE_NM",
    "Source",
    "SpectralLibrary",
    "band_matrix",
    "check_bands",
    "parse_holdout",
    "spectral_library",
    "split_library",
]
