"""From a :class:`~hsicam.config.DataConfig` to training and validation datasets and loaders."""

from __future__ import annotations

import logging
import os
import signal
import threading
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset

from hsicam.config import DataConfig
from hsicam.data.datasets import PatchDataset, SceneDataset, list_scenes, split_scenes
from hsicam.errors import InputError
from hsicam.spectral import Bands

log = logging.getLogger(__name__)


def dataset_root(cfg: DataConfig, bands: Bands, progress: bool | None = None) -> Path:
    """``cfg.root``, or the cached synthetic dataset on ``bands`` (generated on first use).

    The synthetic training set holds out ``cfg.holdout_sources`` when the config has that key, else
    :data:`hsicam.data.synthetic.DEFAULT_HOLDOUT` (see :func:`heldout_root` for the held-out set).
    """
    if cfg.root is not None:
        return Path(cfg.root).expanduser()
    from hsicam.data.synthetic import DEFAULT_HOLDOUT, synthetic_dataset

    return synthetic_dataset(cfg.synthetic_n, cfg.synthetic_size, cfg.synthetic_seed, bands,
                             cache_dir=cfg.cache_dir, progress=progress,
                             holdout_sources=getattr(cfg, "holdout_sources", DEFAULT_HOLDOUT))


def scene_files(scene: str | os.PathLike) -> list[Path]:
    """The files a scene of :func:`~hsicam.data.datasets.list_scenes` is read from: the file; an
    ENVI header and its data file; every file of a CAVE folder but hidden ones (a file manager's ``.DS_Store``
    appearing in it changed the scene's size: a resume warned it had changed, and a copy of the folder without it
    was no longer recognised as the run's training scene)."""
    p = Path(scene)
    if p.is_dir():
        return sorted(f for f in p.rglob("*")
                      if f.is_file() and not any(part.startswith(".") for part in f.relative_to(p).parts))
    if p.suffix.lower() == ".hdr":
        from hsicam.data.formats import envi_data_file

        data = envi_data_file(p)
        return [p] if data is None else [p, data]
    return [p]


def scene_stat(scene: str | os.PathLike) -> tuple[int, int]:
    """(bytes, newest modification time in ns) of the files of ``scene`` (:func:`scene_files`)."""
    stats = [f.stat() for f in scene_files(scene)]
    return sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0)


def patch_source(ds, k: int) -> Path | None:
    """The scene file item ``k`` of a :class:`PatchDataset` (current epoch) is cut from; None for
    another dataset or an index outside it."""
    if not isinstance(ds, PatchDataset) or not 0 <= k < len(ds):
        return None
    return ds.scene_of(int(k))


def heldout_root(cfg: DataConfig, bands: Bands, n: int | None = None, progress: bool | None = None) -> Path | None:
    """The held-out-sources validation set that goes with :func:`dataset_root`, or None for real data.

    Same size, seed, bands, cache and held-out sources as the synthetic training set
    (``cfg.holdout_sources`` when the config has that key, else
    :data:`hsicam.data.synthetic.DEFAULT_HOLDOUT`); ``n`` scenes (default
    :data:`hsicam.data.synthetic.HELDOUT_N`). Generated on first use and cached. None when
    ``cfg.root`` is set (a folder of real data has no held-out sources) or no source is held out.
    """
    if cfg.root is not None:
        return None
    from hsicam.data.synthetic import DEFAULT_HOLDOUT, HELDOUT_N, heldout_dataset, parse_holdout

    holdout = parse_holdout(getattr(cfg, "holdout_sources", DEFAULT_HOLDOUT))
    if not holdout:
        return None
    from hsicam.data.spectral_sources import NoHeldOutSpectra
    from hsicam.data.synthetic import heldout_roles

    n = (getattr(cfg, "heldout_n", HELDOUT_N) if n is None else n)
    try:
        root = heldout_dataset(n, cfg.synthetic_size, cfg.synthetic_seed, bands,
                               cache_dir=cfg.cache_dir, progress=progress, holdout_sources=holdout)
    except NoHeldOutSpectra as exc:  # e.g. the tiny preset's 50 nm bands: no held-out set rather than a false one
        log.warning("no held-out-sources scenes: %s", exc)
        return None
    roles = heldout_roles(root)
    if roles is not None and not any(roles.values()) and "otsu2018" not in holdout:  # cached by an older hsicam, which built it of training spectra
        log.warning("no held-out-sources scenes: %s was made of the training spectra (its held-out sources %s give no "
                    "spectrum on these bands)", root, ", ".join(holdout))
        return None
    return root


def _should_preload(cfg: DataConfig, scenes: list[Path]) -> bool:
    if cfg.preload is not None:
        return cfg.preload
    return sum(scene_stat(s)[0] for s in scenes) <= cfg.preload_max_mb * 2**20


def npy_bands(cfg: DataConfig) -> Bands | None:
    """The band grid the config gives ``.npy`` cubes (``data.npy_bands``), or None (400-700 nm)."""
    return None if cfg.npy_bands is None else cfg.npy_bands.to_bands()


def scene_dataset(cfg: DataConfig, paths, bands: Bands, **kwargs) -> SceneDataset:
    """:class:`SceneDataset` of ``paths`` on ``bands`` with the config's grid for ``.npy`` cubes and its
    ``allow_negative``; ``kwargs`` go to it (e.g. ``preload``). Every dataset built from a config goes through here."""
    return SceneDataset(paths, bands, source_bands=npy_bands(cfg), allow_negative=cfg.allow_negative, **kwargs)


def split_dataset(cfg: DataConfig, bands: Bands, *, progress: bool | None = None) -> tuple[list[Path], list[Path]]:
    """(training, validation) scene paths of the config's dataset: its scene-level split
    (``val_fraction``, ``split_seed``, ``val_pool``)."""
    return _split(cfg, list_scenes(dataset_root(cfg, bands, progress=progress)))


def validation_split(cfg: DataConfig, bands: Bands, *, progress: bool | None = None) -> tuple[list[Path], int]:
    """(validation scene paths, number of scenes) of the config's dataset: the validation scenes of
    :func:`split_dataset`. Of the synthetic data only these scenes are generated, in the set's own cache
    folder (:func:`hsicam.data.synthetic.synthetic_scenes`: scene i is the same file whatever else is
    there), not the whole set: an evaluation scores them alone (16 of the standard camera's 320 scenes),
    and a training of the same config completes the set."""
    if cfg.root is not None:
        train, val = split_dataset(cfg, bands, progress=progress)
        return val, len(train) + len(val)
    from hsicam.data.synthetic import DEFAULT_HOLDOUT, SCENE_PATTERN, dataset_dir, synthetic_scenes

    holdout = getattr(cfg, "holdout_sources", DEFAULT_HOLDOUT)
    folder = dataset_dir(cfg.synthetic_n, cfg.synthetic_size, cfg.synthetic_seed, bands, cache_dir=cfg.cache_dir,
                         holdout_sources=holdout)
    every = [folder / SCENE_PATTERN.format(i) for i in range(cfg.synthetic_n)]  # the set's files (list_scenes)
    _, val = _split(cfg, every)
    index = {p: i for i, p in enumerate(every)}
    return synthetic_scenes([index[p] for p in val], cfg.synthetic_n, cfg.synthetic_size, cfg.synthetic_seed, bands,
                            cache_dir=cfg.cache_dir, progress=progress, holdout_sources=holdout), len(every)


def _split(cfg: DataConfig, scenes: list[Path]) -> tuple[list[Path], list[Path]]:
    return split_scenes(scenes, cfg.val_fraction, cfg.split_seed, cfg.val_pool)


def no_validation_reason(cfg: DataConfig, n_scenes: int) -> str:
    """Why the config's split of ``n_scenes`` scenes holds none out for validation."""
    if cfg.val_fraction == 0:
        return "data.val_fraction is 0"
    return f"a split of {n_scenes} scene(s) keeps them all for training"


def build_datasets(cfg: DataConfig, bands: Bands, margin_px: int, *, progress: bool | None = None,
                   code_period: int = 1, stream: int = 0) -> tuple[PatchDataset, PatchDataset | None]:
    """Training and validation patch datasets (validation None when ``val_fraction`` is 0).

    ``margin_px`` is the camera's ``valid``-convolution margin (kernel_px − 1); ``code_period`` its CFA
    period (1: none), which a patch must hold whole (:meth:`DataConfig.check_patches`). Scenes are split at
    scene level with ``cfg.split_seed``; validation patches are fixed and not augmented. ``stream`` (the run's
    ``train.seed``) is mixed into the training patches' draws (:class:`PatchDataset`; 0: ``split_seed``'s
    stream alone, as before it existed); the split and the validation patches do not depend on it.
    """
    cfg.check_patches(margin_px, code_period)  # before the synthetic data is generated
    root = dataset_root(cfg, bands, progress=progress)
    scenes = list_scenes(root)
    train_scenes, val_scenes = _split(cfg, scenes)
    preload = _should_preload(cfg, scenes)
    log.info("data: %d training and %d validation scenes from %s (preload=%s)", len(train_scenes), len(val_scenes),
             root, preload)
    if not val_scenes:  # a warning unless asked for (val_fraction 0)
        more = ("raise data.synthetic_n to 2 or more" if cfg.root is None else  # (the synthetic data: not data.root)
                "point data.root to a folder of 2 or more scenes")
        fix = ("set data.val_fraction > 0 to hold scenes out" if cfg.val_fraction == 0 else
               f"{more} (data.val_fraction={cfg.val_fraction:g} sets the share held out)")
        log.log(logging.WARNING if cfg.val_fraction > 0 else logging.INFO,
                "data: no validation scenes (%s): training runs without validation and the run keeps its last "
                "checkpoint, not the best one; %s", no_validation_reason(cfg, len(scenes)), fix)
    try:
        train_set = scene_dataset(cfg, train_scenes, bands, preload=preload, dataset_paths=scenes)
        val_set = scene_dataset(cfg, val_scenes, bands, preload=preload, dataset_paths=scenes) if val_scenes else None
    except InputError as exc:
        if cfg.root is None:  # a scene of the synthetic cache that cannot be read: say how the cache is repaired
            raise InputError(f"{exc}; it is a scene of the synthetic dataset cache {root}: `hsicam data synth` with "
                             "the same --config and --set options checks every scene against its checksum and generates "
                             "a damaged set again") from None
        raise
    train = PatchDataset(train_set, cfg.patch_px, margin_px,
                         patches_per_epoch=cfg.patches_per_epoch, flips=cfg.augment_flips, rot90=cfg.augment_rot90,
                         seed=cfg.split_seed, relight_sigma=cfg.augment_relight, relight_prob=cfg.augment_relight_prob,
                         stream=stream)
    val = None
    if val_set is not None:
        val = PatchDataset(val_set, cfg.patch_px, margin_px,
                           patches_per_epoch=cfg.val_patches, flips=False, rot90=False, seed=cfg.split_seed + 1,
                           fixed=True)
    return train, val


#: Seconds a DataLoader worker goes on serving after SIGTERM: the batch the main process is waiting
#: for still arrives, and the main process stops at the end of its step (it fetches no more).
WORKER_GRACE_S = 3.0


def _end_worker(signum, frame) -> None:
    # exit status 0, so that the parent's DataLoader does not report it as a crash
    threading.Timer(WORKER_GRACE_S, os._exit, (0,)).start()


def leave_stop_signals_to_main(_worker_id: int = 0) -> None:
    """A DataLoader worker's ``worker_init_fn``: Ctrl-C (SIGINT, sent to the terminal's whole process
    group) is ignored, and SIGTERM ends the worker :data:`WORKER_GRACE_S` later with exit status 0.
    So a scheduler's SIGTERM to the whole group, or a Ctrl-C, reaches the main process, which gets the
    batch it is waiting for, stops the training cleanly at the end of that step
    (:mod:`hsicam.engine.stopping`) and fetches no more, instead of aborting on "worker exited
    unexpectedly"; and the parent's own shutdown, which ends workers with SIGTERM, still works."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _end_worker)
    # the worker was forked with the stop signals blocked (_StopSafeLoader): one sent while it started is
    # pending and reaches the handler above now, instead of killing the worker before it had one
    if _CAN_MASK:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)


_STOP_SIGNALS = {signal.SIGTERM, signal.SIGINT}
_CAN_MASK = hasattr(signal, "pthread_sigmask")  # POSIX; elsewhere the workers start as before


class _StopSafeLoader(DataLoader):
    """A DataLoader whose worker processes start with SIGTERM and SIGINT blocked (inherited across the
    fork) until :func:`leave_stop_signals_to_main` has installed their handlers: a scheduler's SIGTERM to
    the process group while an epoch's workers start no longer kills one with the default action (the
    main process would abort on "worker exited unexpectedly"). The main process's own signal arrives when
    the workers have started."""

    def __iter__(self):
        if self.num_workers == 0 or not _CAN_MASK:
            return super().__iter__()
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
        try:
            return super().__iter__()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)


_CAPPED_SAID: set[int] = set()


def max_workers() -> int:
    """The most DataLoader workers hsicam starts: twice the CPUs this process may use, at least 4 (a
    guard against a count no machine can run, not a tuning: PyTorch itself warns above the CPUs)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        cpus = os.cpu_count() or 1
    return max(2 * cpus, 4)


def make_loader(dataset: Dataset, batch_size: int, num_workers: int = 2, shuffle: bool = True,
                drop_last: bool = False, sampler: torch.utils.data.Sampler | None = None) -> DataLoader:
    """A DataLoader for patch datasets.

    Workers are not persistent, so each epoch's workers see the epoch set by
    :meth:`PatchDataset.set_epoch` (call it before iterating). ``num_workers`` is capped at
    :func:`max_workers` (with a warning): each worker is a process, and the batches are the same
    whatever their number.
    """
    cap = max_workers()
    if num_workers > cap:
        if num_workers not in _CAPPED_SAID:  # once, not at every epoch's loader
            _CAPPED_SAID.add(num_workers)
            log.warning("data.num_workers=%d is more processes than this machine's CPUs can keep busy; using %d",
                        num_workers, cap)
        num_workers = cap
    return _StopSafeLoader(dataset, batch_size=batch_size, shuffle=shuffle and sampler is None, sampler=sampler,
                           num_workers=num_workers, drop_last=drop_last, persistent_workers=False,
                           pin_memory=False, worker_init_fn=leave_stop_signals_to_main if num_workers > 0 else None)


__all__ = ["build_datasets", "dataset_root", "heldout_root", "make_loader",
           "no_validation_reason", "patch_source", "scene_files", "scene_stat", "split_dataset"]
