"""Evaluation of a camera + reconstruction method on whole scenes.

Each scene is imaged by the method's camera (the learned DOE camera in ``valid`` mode: the scene
border is context the sensor does not see, so metrics cover the sensor area, the scene minus the
kernel margin), optionally with test noise (DOE height σ_p, sensor σ_s) over several seeds, and
reconstructed (the DOE network tile by tile with an exact halo). Reconstructions are clipped to
[0, 1] (scenes are per-cube max normalised, see ``hsicam.data.cube``). Every result file states
the metric conventions (``hsicam.metrics.CONVENTIONS``).
"""

from __future__ import annotations

import csv
import hashlib
import io
import re
import time
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Collection, Sequence

import numpy as np
import torch

from hsicam.engine.inference import memory_shortfall, reconstruct_tiled, reconstruction_memory_bytes
from hsicam.engine.methods import Method, demosaic_reference  # noqa: F401  (re-exported)
from hsicam.engine.provenance import commit_label
from hsicam.errors import InputError
from hsicam.io import atomic_open, free_space_short, free_space_text, write_json
from hsicam.metrics import CONVENTIONS, SSIM_WINDOW_PX, all_metrics, exact_zero_bands, sam_undefined_pixels
from hsicam.progress import format_seconds

METRIC_KEYS = ("psnr", "ssim", "sam", "ergas", "psnr_cube", "psnr_mst", "rmse")


@dataclass
class SceneResult:
    name: str
    metrics: dict[str, float]  # mean over seeds
    truth: np.ndarray | None  # (C, H, W), the sensor-aligned ground truth (first seed)
    estimate: np.ndarray | None  # (C, H, W) (first seed)
    runtime_s: float  # reconstruction time (mean over seeds)
    metrics_std: dict[str, float] = field(default_factory=dict)  # over seeds
    path: str | None = None  # the scene's file, as the results name it (relative to the data folder)
    seed: int = 0  # the noise seed of ``estimate`` (the first of the seeds scored)
    metrics_per_seed: list[dict[str, float]] = field(default_factory=list)  # one dict per seed, with its "seed"
    noise: dict[str, float] = field(default_factory=dict)  # the camera's noise levels while it was scored
    sam_excluded_px: int = 0  # scored pixels whose truth spectrum is all zero (no spectral angle)
    scored_px: tuple[int, int] | None = None  # (H, W) of the scored area (the region results.json names)
    exact_zero_bands: int = 0  # bands zero in the truth and exactly 0 in an estimate (300 dB each), most of any seed


@dataclass(frozen=True)
class TestNoise:
    """Test-time noise: DOE height σ_p (nm; None keeps the camera's) and sensor Gaussian σ_s."""

    sigma_height_nm: float | None = None
    sensor_sigma: float | None = None
    seeds: tuple[int, ...] = (0,)


#: How the test noise is drawn (results.json's ``noise.draws``): see :func:`capture_noise_seed`.
NOISE_DRAWS = ("under noise seed s, one DOE height draw (sigma_p) from s images every scene (one fabricated element); "
               "each scene's sensor noise is drawn from seed capture_noise_seed(s, scene name, scene set): its own "
               "field, the same for every method scored on that scene (the held-out-sources scenes' seeds mix in "
               "their set's name: independent of the validation scenes' of the same name)")


def capture_noise_seed(seed: int, scene_name: str, scene_set: str | None = None) -> int:
    """The seed of scene ``scene_name``'s sensor noise under noise seed ``seed``: each scene's capture gets
    its own noise field (one seed for all would give same-size scenes the same field, correlating their
    errors), and every method scored on that scene with that seed gets the same one (paired comparisons).
    The DOE height draw (σ_p) comes from ``seed`` alone: one fabricated element images every scene.

    ``scene_set``: the name of the set the scene belongs to, mixed into the seed, so that two sets scored
    together (the validation split and the held-out-sources scenes, both named ``scene_0000``…) get independent
    noise; None (the validation split, a ``--data`` folder) keeps the seed of the scene name alone."""
    key = f"{int(seed)}:{scene_name}" if scene_set is None else f"{int(seed)}:{scene_set}:{scene_name}"
    return zlib.crc32(key.encode())


#: results.json ``data`` of a run's own validation split: the embedded synthetic data, or ``VALIDATION_OF`` its folder.
SYNTHETIC_VALIDATION = "synthetic validation split"
VALIDATION_OF = "validation split of "


def validation_data_label(cfg) -> str:
    """What results.json's ``data`` says of the config ``cfg``'s own validation split (``hsicam evaluate`` without
    ``--data``, ``hsicam demo``)."""
    from hsicam.data.datasets import displayable_name
    from hsicam.config import absolute_paths

    if cfg.data.root is None:
        return SYNTHETIC_VALIDATION
    return f"{VALIDATION_OF}{displayable_name(str(absolute_paths(cfg).data.root))}"  # (a folder not UTF-8)


HELDOUT_SOURCES = "held-out spectral sources"
#: The ``scene_set`` of the held-out-sources scenes' capture noise (:func:`capture_noise_seed`).
HELDOUT_NOISE_SET = "heldout-sources"


def heldout_sources_label(cfg, detail: str = "") -> str:
    """What results.json's ``heldout.data`` says of the config ``cfg``'s held-out-sources scenes (its synthetic
    companion set, :func:`hsicam.data.pipeline.heldout_dataset`); ``detail`` is appended after a colon."""
    return f"{HELDOUT_SOURCES} ({cfg.data.holdout_sources})" + (f": {detail}" if detail else "")


def is_heldout_sources_label(label) -> bool:
    """Whether a results.json ``data`` names held-out spectral sources (not any other folder given as held out)."""
    return str(label).startswith(HELDOUT_SOURCES)


def is_validation_data_label(label) -> bool:
    """Whether a results.json ``data`` is a run's own validation split (None: an older file that did not say)."""
    return label is None or label == SYNTHETIC_VALIDATION or str(label).startswith(VALIDATION_OF)


def config_hash(yaml_text: str) -> str:
    """Short SHA-256 of a resolved config (identifies the run a result came from)."""
    return hashlib.sha256(yaml_text.encode()).hexdigest()[:12]


def config_hash_of(cfg) -> str:
    """:func:`config_hash` of the config ``cfg`` with each file its camera is built from
    (:func:`hsicam.config.camera_files`) named by its SHA-256 instead of its path, so that one camera hashes alike
    wherever its tables sit (a packed camera's copies moved with the package: three hashes for one camera before,
    session 75's review) and an edited table hashes apart; a file that cannot be read keeps its path. A config that
    names no file hashes as its YAML does (the presets' hashes unchanged)."""
    import yaml

    from hsicam.config import camera_files, dump_yaml, mapping_section, to_dict
    from hsicam.io import file_sha256

    files = camera_files(cfg)
    if not files:
        return config_hash(dump_yaml(cfg))
    data = to_dict(cfg)
    for key, path in files.items():
        node, name = mapping_section(data, key)
        try:
            node[name] = f"sha256:{file_sha256(path)}"
        except OSError:
            pass
    return config_hash(yaml.safe_dump(data, sort_keys=False))


def scored_region(camera, border_px: int = 0) -> str:
    """What a result's scores cover, for ``results.json``: the sensor area of a ``valid`` camera, or
    the whole scene (``same``, its border imaged with the camera's padding); with ``border_px``
    (:attr:`~hsicam.engine.methods.Method.border_px`) a CASSI method's whole-scene reconstruction
    scored on a DOE camera's sensor area."""
    if border_px:
        return (f"the sensor area of the DOE camera it is compared with: the scene less {border_px} px a side "
                "(the reconstruction covers the whole scene)")
    margin = getattr(camera, "margin", 0)
    if camera.boundary == "valid" and margin > 0:
        a, b = margin // 2, margin - margin // 2
        side = f"{a} px a side" if a == b else f"{margin} px per axis"
        return (f"sensor area (scene minus the camera's kernel margin: {side}, an H×W scene scores "
                f"(H − {margin})×(W − {margin}) px; each scene's scored_px)")
    if camera.boundary == "valid":  # a CASSI camera: no PSF kernel, so 'valid' crops nothing
        return "whole scene (no kernel margin to crop: the camera images without a PSF)"
    return f"whole scene (boundary 'same', {getattr(camera, 'padding', 'zeros')} padding: border pixels included)"


def _check_scored_area(name: str, scene_hw: tuple[int, int], truth_hw: tuple[int, int], camera,
                       border_px: int = 0, boundary_advice: bool = True) -> None:
    """InputError unless the scored area ``truth_hw`` (empty when a ``valid`` camera's margin, or the
    ``border_px`` a method leaves out, exceeds the scene) holds SSIM's window; the message names the
    scene by ``name`` (its path when it has one) and gives the minimum scene size, and (``boundary_advice``,
    for a command that takes ``--set``) the ``camera.boundary=same`` that scores whole scenes."""
    if min(truth_hw) >= SSIM_WINDOW_PX:
        return
    if border_px:
        raise InputError(
            f"{name}: scene of {scene_hw[0]}×{scene_hw[1]} px leaves {max(truth_hw[0], 0)}×{max(truth_hw[1], 0)} px "
            f"to score on the sensor area of the DOE camera it is compared with ({border_px} px a side left out); "
            f"SSIM needs at least {SSIM_WINDOW_PX}×{SSIM_WINDOW_PX}: scenes of at least "
            f"{2 * border_px + SSIM_WINDOW_PX} px on each side"
            + (", or camera.boundary=same (whole scenes scored)" if boundary_advice else ""))
    crop = camera.boundary == "valid"
    margin = camera.margin if crop else 0
    raise InputError(
        f"{name}: scene of {scene_hw[0]}×{scene_hw[1]} px leaves {max(truth_hw[0], 0)}×{max(truth_hw[1], 0)} px to score"
        + (f" (camera boundary 'valid' crops its {margin}-px kernel margin)" if crop else "")
        + f"; SSIM needs at least {SSIM_WINDOW_PX}×{SSIM_WINDOW_PX}: scenes of at least {margin + SSIM_WINDOW_PX} px "
        "on each side" + (", or camera.boundary=same (the whole scene, border pixels included, is then scored)"
                          if crop and boundary_advice else ""))


def _scored_hw(method: Method, n_bands: int, scene_hw: tuple[int, int]) -> tuple[int, int]:
    """(H, W) of ``method.target`` for a scene of ``scene_hw``, computed on a tensor without data
    (the ``meta`` device: no memory, no pixels read)."""
    b = 2 * method.border_px
    try:
        t = method.target(torch.empty((1, n_bands, *scene_hw), device="meta"))
        return int(t.shape[-2]) - b, int(t.shape[-1]) - b
    except InputError:  # a scene smaller than the camera's valid kernel: nothing to score (said by the caller)
        return 0, 0
    except (RuntimeError, NotImplementedError, TypeError):  # a target that needs data: the scene's own size
        return scene_hw[0] - b, scene_hw[1] - b


def _without_border(x: torch.Tensor, border_px: int) -> torch.Tensor:
    """x (…, H, W) less ``border_px`` px on every side."""
    b = border_px
    return x[..., b : x.shape[-2] - b, b : x.shape[-1] - b] if b else x


def scene_label(scenes, i: int, name: str) -> str:
    """How messages name scene ``i``: its file as the dataset lists it (the path the user gave,
    e.g. ``data/day1/scene.h5``), else ``name``."""
    paths = getattr(scenes, "paths", None)
    return str(paths[i]) if paths is not None and i < len(paths) else name


#: What scoring a scene adds to its reconstruction's peak (:func:`evaluation_memory_bytes`): a fixed part (the
#: data readers, the metrics' code) and float32 cubes of the scene's size (the scene, its truth, the clipped estimate,
#: the metrics' float64 copies of both and of their difference). Fitted to ``hsicam evaluate``'s peak resident memory
#: (session 76, the quick demo camera, one 512² or 1024² scene, with and without its 12 consistency steps: 1.03–2.99
#: GiB measured, the estimate 1.09–1.26× of it).
EVALUATE_EXTRA_BYTES = 256 * 2**20
EVALUATE_SCENE_CUBES = 8


def evaluation_memory_bytes(method: Method, n_bands: int, scene_hw: tuple[int, int], tile_px: int | None = None,
                            held_bytes: int = 0) -> int | None:
    """About the peak memory (bytes) of scoring one scene of ``scene_hw`` (H, W) into ``n_bands`` bands with a
    learned ``method`` (its network tiled in ``tile_px``): the reconstruction of its target's size
    (:func:`~hsicam.engine.inference.reconstruction_memory_bytes`: its consistency steps go over the whole image,
    whatever the tile), :data:`EVALUATE_EXTRA_BYTES`, :data:`EVALUATE_SCENE_CUBES` of the scene, and ``held_bytes``
    (other scenes' cubes a dataset keeps). None for a method without a network (a baseline's memory is its own)."""
    if method.model is None:
        return None
    b = method.border_px
    h, w = _scored_hw(method, n_bands, scene_hw)
    rec = reconstruction_memory_bytes(method.reconstruct, n_bands, max(h + 2 * b, 1), max(w + 2 * b, 1), tile_px)
    return int(rec + EVALUATE_EXTRA_BYTES + EVALUATE_SCENE_CUBES * 4 * n_bands * scene_hw[0] * scene_hw[1]
               + held_bytes)


def check_scenes(method: Method, scenes, names: Sequence[str], boundary_advice: bool = True,
                 tile_px: int | None = None) -> None:
    """Before any scoring: InputError for the first scene of ``scenes`` that cannot be scored, with
    the one-line message its scoring would end with: a file that cannot be read, whose bands do not
    cover the camera's, or whose scored area is too small for SSIM's window (named by its path; without
    ``boundary_advice`` the message does not offer ``camera.boundary=same``: a command without ``--set``);
    then for the first scene whose scoring would need more memory than the process may take
    (:func:`check_scene_memory`).

    A :class:`~hsicam.data.datasets.SceneDataset` is asked for each scene's size
    (:meth:`~hsicam.data.datasets.SceneDataset.info`): an hsicam HDF5 file on the camera's bands by
    its header alone; any other file is read, resampled and normalised once (what its scoring
    does), and only the dataset's few cached cubes stay in memory. Other sequences are checked by
    their tensors' shapes."""
    info = getattr(scenes, "info", None)
    n_bands = len(method.camera.bands)
    sizes = []
    for i, name in enumerate(names):
        if info is not None:
            got = info(i)
            hw = (got.height, got.width)
        else:
            hw = tuple(int(v) for v in scenes[i].shape[-2:])
        _check_scored_area(scene_label(scenes, i, name), hw, _scored_hw(method, n_bands, hw), method.camera,
                           method.border_px, boundary_advice)
        sizes.append(hw)
    check_scene_memory(method, sizes, [scene_label(scenes, i, name) for i, name in enumerate(names)], tile_px,
                       int(getattr(scenes, "cache_size", 1) or 1))


def check_scene_memory(method: Method, sizes: Sequence[tuple[int, int]], labels: Sequence[str],
                       tile_px: int | None = None, cached: int = 1) -> None:
    """InputError, before any scoring, for the first scene (of ``sizes``, (H, W) each, named by ``labels``) whose
    scoring (:func:`evaluation_memory_bytes`, beside the ``cached`` − 1 largest other scenes a dataset keeps) would
    need more memory than the process may take (:func:`~hsicam.engine.inference.memory_shortfall`). A 2048² scene
    under ``ulimit -v 4000000`` was scored for 38 s, then ended in an out-of-memory error that advised a smaller tile,
    which failed again after 2 min: the consistency steps go over the whole image, whatever the tile."""
    from hsicam.memory import format_bytes

    if method.model is None:  # no estimate (evaluation_memory_bytes)
        return
    n_bands = len(method.camera.bands)
    cubes = [4 * n_bands * h * w for h, w in sizes]
    for i, (hw, label) in enumerate(zip(sizes, labels)):
        held = sum(sorted(cubes[:i] + cubes[i + 1 :], reverse=True)[: max(cached - 1, 0)])
        short = memory_shortfall(lambda h, w, b=held: evaluation_memory_bytes(method, n_bands, (h, w), tile_px, b), hw)
        if short is None:
            continue
        lo = short.fits_px
        todo = [f"crop the scenes to at most about {lo}×{lo} px" if lo >= 64 else
                "even a small scene would not fit: score where more memory is free"]
        before = getattr(method.reconstruct, "before_steps", None)  # the tiled part, the linear step included
        alone = None if before is None else replace(method, reconstruct=before)
        if alone is not None and evaluation_memory_bytes(alone, n_bands, hw, tile_px, held) <= short.have:
            todo.append("score without the consistency steps (--set model.consistency.iterations=0)")
        steps = ", whose consistency steps go over the whole image whatever the tile" if before is not None else ""
        raise InputError(f"{label}: scoring this {hw[0]}×{hw[1]} px scene ({n_bands} bands) with {method.name} takes "
                         f"about {format_bytes(short.need)} of memory (the scene, its scores and its reconstruction"
                         f"{steps}), more than {short.limit} ({format_bytes(short.have)}); {', or '.join(todo)}")


def interpolated_truth_warning(scenes, names: Sequence[str], bands) -> str | None:
    """The warning for scenes of ``scenes`` whose files hold a coarser band grid than the camera's ``bands``
    (:func:`hsicam.spectral.interpolated_bands`: a camera band between two data bands more than 1.5 of its FWHM
    apart), else None: their ground truth there is a linear interpolation of the data, and a smooth reconstruction
    scores well against it. Asks a :class:`~hsicam.data.datasets.SceneDataset` for each file's own grid (read once,
    as :func:`check_scenes` does); other sequences hold cubes already on ``bands``: None."""
    from hsicam.spectral import interpolated_bands

    grid_of = getattr(scenes, "source_grid", None)
    if grid_of is None:
        return None
    coarse = []
    for i, name in enumerate(names):
        grid = grid_of(i)
        n = int(interpolated_bands(grid, bands).sum())
        if n:
            coarse.append((scene_label(scenes, i, name), grid, n))
    if not coarse:
        return None
    label, grid, n = coarse[0]
    others = f" and {len(coarse) - 1} other scene(s)" if len(coarse) > 1 else ""
    return (f"{label}{others}: the data's {len(grid)} bands ({grid.min_nm:g}-{grid.max_nm:g} nm) are coarser than the "
            f"camera's {len(bands)} ({bands.min_nm:g}-{bands.max_nm:g} nm): {n} of the camera's bands lie between data "
            "bands more than 1.5 of their FWHM apart, so their ground truth is a linear interpolation of the data and "
            "the scores there are against it, not against a measurement; score on data at least as fine as the camera's "
            "bands")


def no_doe_reason(camera) -> str | None:
    """Why test DOE height noise cannot reach ``camera`` (None when it can): a camera kind without a
    DOE (CASSI), a camera imaging with fixed (measured) PSFs, or a DOE camera whose DOE is disabled
    (``camera.doe.enabled: false``, the no-DOE ablation)."""
    if getattr(camera, "kind", None) == "measured_psf":
        return "its camera images with fixed (measured) PSFs, which DOE height noise does not change"
    if "sigma_height_nm" not in camera.noise_levels():
        return f"its camera (camera.kind {getattr(camera, 'kind', type(camera).__name__)}) has no DOE"
    optics = getattr(camera, "optics", None)
    if optics is not None and not optics.doe.enabled:
        return "its camera has no DOE (camera.doe.enabled: false)"
    return None


def check_test_noise(method: Method, noise: TestNoise, source: str | None = None) -> None:
    """InputError for test DOE height noise (``sigma_height_nm`` > 0) on a camera without a DOE: no
    noise would reach it, yet the results would record the σ as applied. ``source`` names where the
    method's camera comes from (e.g. ``run xab/runs/no-doe``) in the message."""
    if not noise.sigma_height_nm:
        return
    why = no_doe_reason(method.camera)
    if why is not None:
        of = f"{method.name} ({source})" if source else method.name
        raise InputError(f"--sigma-height-nm {noise.sigma_height_nm:g}: {of}: {why}, so no height noise would be "
                         "applied; drop --sigma-height-nm (it applies only to a camera with a DOE)")


#: A scene whose sensor image has at least this many pixels shows its reconstruction's progress (tiles, consistency
#: steps: :class:`hsicam.progress.Progress`, as ``reconstruct`` does) when :func:`evaluate_method` is given
#: ``progress``: with the demo camera on this project's 2-core CPU such a scene takes 15 s or more (a 2048² scene,
#: 2 min in silence before session 76); smaller ones would add lines for seconds of work.
SCENE_PROGRESS_PX = 512 * 512


@torch.no_grad()
def evaluate_method(method: Method, scenes, names: Sequence[str], noise: TestNoise = TestNoise(),
                    device: str | torch.device = "cpu", keep_arrays: bool | Collection[str] = True,
                    tile_px: int | None = None, progress: Callable[[str], None] | None = None, paths: Sequence[str] | None = None,
                    scene_set: str | None = None, on_scene: Callable[[int, SceneResult], None] | None = None
                    ) -> list[SceneResult]:
    """Simulate, reconstruct and score every scene of ``scenes`` (items: (C, H, W) tensors).

    Every scene is checked first (:func:`check_scenes`): a scene that cannot be scored fails before
    any work. ``progress``: called with one line per finished scene (e.g. ``print`` to stderr); given, a scene of
    :data:`SCENE_PROGRESS_PX` or more also counts its reconstruction's tiles and steps on the way (a bar on a
    terminal, else ``hsicam.progress`` log lines).
    ``paths``: each scene's file as the results name it (:attr:`SceneResult.path`). The arrays kept
    (``keep_arrays``: every scene's, none, or those of the scenes it names) are those of the first seed,
    :attr:`SceneResult.seed`. ``tile_px``: the tile side
    for a network's large images (default :func:`~hsicam.engine.inference.default_tile_px` of its context).
    ``scene_set``: the scenes' set, mixed into their capture noise seeds (:func:`capture_noise_seed`; e.g.
    :data:`HELDOUT_NOISE_SET`); None for the validation split or a folder of scenes.
    ``on_scene``: called with each scene's index and result as soon as it is scored, before the next scene: e.g.
    ``evaluate --save`` writes its arrays there and drops them (:attr:`SceneResult.truth` and ``estimate`` set to
    None), so that one scene's cubes at a time are held, not every scene's until the end (a 1001×777 scene's two
    cubes are 136 MB).
    """
    if len(names) != len(scenes) or (paths is not None and len(paths) != len(names)):
        raise ValueError(f"{len(scenes)} scenes, {len(names)} names" + (f", {len(paths)} paths" if paths is not None else ""))
    cam = method.camera
    check_test_noise(method, noise)
    check_scenes(method, scenes, names, tile_px=tile_px)
    if method.prepare is not None:  # e.g. a fit: not part of the first scene's reconstruction time
        method.prepare()
    saved = cam.noise_levels()
    levels = dict(saved)
    if noise.sigma_height_nm is not None and "sigma_height_nm" in levels:
        levels["sigma_height_nm"] = noise.sigma_height_nm
    if noise.sensor_sigma is not None:
        levels["sensor_sigma"] = noise.sensor_sigma
    cam.set_noise(**levels)
    applied = cam.noise_levels()
    # a network: tile large images with the context it declares (tiles of default_tile_px unless given)
    halo = method.model.context_px if method.model is not None else None
    out = []
    t_start = time.perf_counter()
    try:
        cam.eval()
        for i, name in enumerate(names):
            scene = scenes[i][None].to(device)
            truth = _without_border(method.target(scene), method.border_px)
            _check_scored_area(scene_label(scenes, i, name), scene.shape[-2:], truth.shape[-2:], cam, method.border_px)
            per_seed, times, est0, exact = [], [], None, 0
            for seed in noise.seeds:
                g = torch.Generator(device=device).manual_seed(int(seed))
                sensor = cam(scene, g, sensor_generator=torch.Generator(device=device).manual_seed(
                    capture_noise_seed(int(seed), name, scene_set)))
                t0 = time.perf_counter()
                if halo is not None:  # the halo the reconstructor declares (tiles up to its steps, if it has any)
                    declared = getattr(method.reconstruct, "context_px", None) is not None
                    large = sensor.shape[-2] * sensor.shape[-1] >= SCENE_PROGRESS_PX
                    est = reconstruct_tiled(method.reconstruct, sensor, tile_px, None if declared else halo,
                                            progress=None if progress is not None and large else False)
                else:
                    est = method.reconstruct(sensor)
                times.append(time.perf_counter() - t0)
                bad = int((~torch.isfinite(est)).sum())
                if bad:  # clipping would hide inf and metrics would score NaN as infinitely good: refuse
                    raise InputError(f"{scene_label(scenes, i, name)}: the {method.name} reconstruction holds {bad} "
                                     "non-finite values (NaN or inf): a broken reconstruction is not scored")
                est = _without_border(est, method.border_px).float().clamp(0, 1)
                per_seed.append({k: v[0] for k, v in all_metrics(est, truth).items()})
                exact = max(exact, int(exact_zero_bands(est, truth)[0]))
                if est0 is None:
                    est0 = est
            mean = {k: float(np.mean([m[k] for m in per_seed])) for k in per_seed[0]}
            std = {k: float(np.std([m[k] for m in per_seed])) for k in per_seed[0]} if len(per_seed) > 1 else {}
            kept = keep_arrays if isinstance(keep_arrays, bool) else name in keep_arrays
            out.append(SceneResult(name, mean, truth[0].cpu().numpy() if kept else None,
                                   est0[0].cpu().numpy() if kept else None, float(np.mean(times)), std,
                                   path=None if paths is None else str(paths[i]), seed=int(noise.seeds[0]),
                                   metrics_per_seed=[{"seed": int(s), **m} for s, m in zip(noise.seeds, per_seed)],
                                   noise=dict(applied), sam_excluded_px=int(sam_undefined_pixels(truth)[0]),
                                   scored_px=(int(est0.shape[-2]), int(est0.shape[-1])), exact_zero_bands=exact))
            del scene, truth, sensor, est, est0  # not alive through the next scene's capture
            if on_scene is not None:
                on_scene(i, out[-1])
            if progress is not None:
                left = len(names) - i - 1  # the scenes still to do, at the mean time per scene so far (all seeds)
                eta = f", eta {format_seconds((time.perf_counter() - t_start) / (i + 1) * left)}" if left else ""
                progress(f"[{i + 1}/{len(names)}] {name}: PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.4f}, "
                         f"SAM {_sam_text(mean['sam'])} ({np.mean(times):.1f} s{eta})")
    finally:
        cam.set_noise(**saved)
    return out


def _sam_text(sam: float) -> str:
    return f"{sam:.2f}°" if np.isfinite(sam) else "undefined (the truth is zero at every scored pixel)"


def evaluate_scenes(model, scenes, names: Sequence[str], seed: int = 0, device: str | torch.device = "cpu",
                    keep_arrays: bool = True, scene_set: str | None = None) -> list[SceneResult]:
    """The learned camera (a :class:`~hsicam.models.CameraSystem`) with its configured noise (``scene_set``: see
    :func:`evaluate_method`)."""
    method = Method("doe-learned", model.camera, model.reconstructor(), model.target, model=model)
    return evaluate_method(method, scenes, names, TestNoise(seeds=(seed,)), device, keep_arrays, scene_set=scene_set)


def grey_reference(model, train_scenes) -> Method:
    """A network-free reference: the sensor image times the mean training spectrum.

    x̂_c = g · s̄_c / mean(s̄), where s̄ is the mean spectrum over all pixels of ``train_scenes``
    (items (C, H, W)). What a reconstruction scores above this is what it recovers beyond the
    brightness and the average colour of the training data.
    """
    total, n = None, 0
    for i in range(len(train_scenes)):
        cube = train_scenes[i]
        s = cube.double().sum(dim=(-2, -1))
        total, n = (s if total is None else total + s), n + cube.shape[-2] * cube.shape[-1]
    if total is None:
        raise ValueError("the grey reference needs at least one training scene")
    spectrum = (total / n).float()
    weights = (spectrum / spectrum.mean()).view(1, -1, 1, 1)

    def reconstruct(sensor: torch.Tensor) -> torch.Tensor:
        return sensor * weights.to(sensor.device, sensor.dtype)

    return Method("sensor image x mean training spectrum", model.camera, reconstruct, model.target,
                  {"mean_spectrum": spectrum.tolist()})


def summarize(results: list[SceneResult], **facts) -> dict:
    """Per-scene rows, means and the metric conventions, as a JSON-ready dict.

    A row has the scene's ``path`` (when known), its metrics (means over the seeds), ``std`` and
    ``per_seed`` (several seeds), ``sam_excluded_px`` and ``scored_px`` ([H, W] of the scored area, when known).
    A scene whose SAM is undefined (NaN:
    its truth is zero at every scored pixel) is listed in ``sam_undefined``, and the mean SAM is
    over the other scenes; likewise a scene whose ERGAS is undefined (NaN: a band's truth mean over the
    scored area is 0) in ``ergas_undefined``. A scene with a band zero in the truth that an estimate reproduces
    exactly (:attr:`SceneResult.exact_zero_bands`: 300 dB each) is listed in ``exact_zero_bands``."""
    rows = [{"name": r.name, **({"path": r.path} if r.path is not None else {}), **r.metrics,
             "runtime_s": r.runtime_s, "sam_excluded_px": r.sam_excluded_px,
             **({"scored_px": list(r.scored_px)} if r.scored_px is not None else {}),
             **({"std": r.metrics_std} if r.metrics_std else {}),
             **({"per_seed": r.metrics_per_seed} if len(r.metrics_per_seed) > 1 else {})} for r in results]
    keys = [k for k in METRIC_KEYS if results and k in results[0].metrics] + ["runtime_s"]
    means = {k: _mean([row[k] for row in rows]) for k in keys} if rows else {}
    undefined = {f"{k}_undefined": names for k in ("sam", "ergas")
                 if (names := [row["name"] for row in rows if k in row and np.isnan(row[k])])}
    exact = [r.name for r in results if r.exact_zero_bands]
    return {**facts, "scenes": rows, "mean": means, **undefined, **({"exact_zero_bands": exact} if exact else {}),
            "conventions": CONVENTIONS}


def exact_band_note(names: list[str]) -> str:
    """Why the PSNR of scenes ``names`` (a summary's ``exact_zero_bands``: a band zero in the truth, estimated exactly
    0) compares methods badly: such a band scores 300 dB, which dominates a mean over bands (session 74's hunt: a box
    demosaic 173.99 dB against the network's 42.29 on one narrow-band scene, with the worse SAM). Only for those
    scenes: said of every scene without an ERGAS, it told of 300 dB bands where none was (a mean PSNR of 9.14 dB)."""
    return (f"PSNR of {', '.join(names)}: a band whose truth is zero at every scored pixel scores 300 dB where the "
            "estimate is exactly 0 there too (the convention for an exact band), which outweighs the other bands in "
            "the mean over bands and the mean over scenes: compare methods there by SAM, SSIM or psnr_cube")


def _mean(values: list[float]) -> float:
    """Mean over the values that are not NaN (an undefined SAM or ERGAS), NaN when none is; an infinite value (the
    worst score of a broken estimate) is kept: the mean is that infinity."""
    kept = [v for v in values if not np.isnan(v)]
    return float(np.mean(kept)) if kept else float("nan")


def format_table(summary: dict, keys: tuple[str, ...] = ("psnr", "ssim", "sam")) -> str:
    """A Markdown table of the per-scene metrics and their mean (and each row's ``split`` when the
    rows have one)."""
    split = any("split" in row for row in summary["scenes"])
    head = "| scene | " + " | ".join(keys) + " |" + (" split |" if split else "")
    sep = "|---" * (len(keys) + 1 + split) + "|"
    lines = [head, sep]
    for row in summary["scenes"] + [{"name": "**mean**", **summary["mean"]}]:
        lines.append(f"| {_md_cell(row['name'])} | " + " | ".join(_fmt(k, row[k]) for k in keys) + " |"
                     + (f" {row.get('split', '')} |" if split else ""))
    return "\n".join(lines)


def _md_cell(text) -> str:
    """``text`` as one Markdown table cell: backslashes and ``|`` escaped (a scene file may be named ``a|b``),
    line breaks as spaces (a line break would end the row)."""
    return re.sub(r"\r\n?|\n", " ", str(text).replace("\\", "\\\\").replace("|", "\\|"))


def _fmt(key: str, v: float) -> str:
    if key in ("ssim", "rmse", "runtime_s"):
        return f"{v:.4f}"
    return f"{v:.2f}"


#: Bytes an HDF5 cube file holds besides its pixels (headers, band centres, attributes), at most.
H5_OVERHEAD_BYTES = 16 * 1024


def check_room_for_cubes(out: Path, scenes, n_bands: int) -> None:
    """Before ``evaluate --save`` starts: InputError when the file system of ``out`` has less free
    space than the cubes it will write (an estimate and a ground truth per scene of ``scenes``, a
    :class:`~hsicam.data.datasets.SceneDataset`, float32 at most the scene's size) and a margin."""
    infos = [scenes.info(i) for i in range(len(scenes))]
    need = sum(2 * (n_bands * info.height * info.width * 4 + H5_OVERHEAD_BYTES) for info in infos)
    free = free_space_short(out, need, min_margin_bytes=1 << 20)
    if free is not None:
        raise InputError(f"{out}: --save writes cubes ({len(scenes)} scenes) of {free_space_text(need, free, 1 << 20, path=out)}; "
                         "free some space, choose another --out, or drop --save")


def write_results(out: Path, summary: dict) -> None:
    """results.json, results.csv and results.md (conventions stated in each). Rows with a ``split``
    (train / validation / unseen by the run's data record) get a ``split`` column."""
    write_json(out / "results.json", summary)
    keys = [k for k in METRIC_KEYS if k in summary["mean"]] + ["runtime_s"]
    split = ["split"] if any("split" in row for row in summary["scenes"]) else []
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["name", "path", *keys, "sam_excluded_px", *split])
    for row in summary["scenes"]:
        w.writerow([row["name"], row.get("path", ""), *[f"{row[k]:.6g}" for k in keys], row.get("sam_excluded_px", ""),
                    *([row.get("split", "")] if split else [])])
    w.writerow(["mean", "", *[f"{summary['mean'][k]:.6g}" for k in keys], "", *([""] if split else [])])
    with atomic_open(out / "results.csv", "w", encoding="utf-8", newline="") as fh:
        fh.write(buf.getvalue())
    conv = summary["conventions"]
    head = [f"# Results: {summary.get('method', '')}", ""]
    for k in ("run", "run_path", "data", "warning", "truth_interpolated", "noise", "overrides", "config_hash",
              "weights_sha256", "saved_cubes"):
        # run_path (the folder read) only where it differs from run: a shipped camera's package folder
        if k in summary and not (k == "run_path" and summary[k] == summary.get("run")):
            head.append(f"- {k}: {summary[k]}")
    sw = summary.get("software")
    if isinstance(sw, dict):
        head.append(f"- software: hsicam {sw.get('hsicam') or 'source'} ({commit_label(sw)}), torch "
                    f"{sw.get('torch')}, numpy {sw.get('numpy')}, {sw.get('device')}, {sw.get('threads')} thread(s), "
                    f"{sw.get('started_utc')}")
    head.append(f"- PSNR: {conv['psnr']}; SSIM: {conv['ssim']}; SAM: {conv['sam']}")
    if summary.get("sam_undefined"):
        head.append(f"- SAM undefined (the truth is zero at every scored pixel) for {', '.join(summary['sam_undefined'])}; "
                    "the mean SAM is over the other scenes")
    if summary.get("ergas_undefined"):
        head.append(f"- ERGAS undefined (a band of the truth is zero at every scored pixel) for "
                    f"{', '.join(summary['ergas_undefined'])}; the mean ERGAS is over the other scenes")
    if summary.get("exact_zero_bands"):
        head.append("- " + exact_band_note(summary["exact_zero_bands"]))
    excluded = [f"{row['name']} ({row['sam_excluded_px']} px)" for row in summary["scenes"] if row.get("sam_excluded_px")]
    if excluded:
        head.append(f"- pixels without a spectral angle (truth all zero), left out of SAM: {', '.join(excluded)}")
    head.append("")
    with atomic_open(out / "results.md", "w", encoding="utf-8") as fh:
        fh.write("\n".join(head) + "\n" + format_table(summary, ("psnr", "ssim", "sam", "ergas", "runtime_s")) + "\n")
        if "heldout" in summary:
            fh.write(f"\n## Held-out spectral sources\n\n{summary['heldout']['data']}\n\n"
                     + format_table(summary["heldout"], ("psnr", "ssim", "sam", "ergas", "runtime_s")) + "\n")
