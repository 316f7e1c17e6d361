"""Which scenes a run on a ``data.root`` folder trained and validated on: ``RUN/data.json``.

Written once, atomically, into a new run (:func:`hsicam.engine.loop.fit`), before training::

    {"root": "/abs/data/root",
     "split": {"val_fraction": 0.125, "split_seed": 0, "val_pool": null},
     "scenes": [{"path": "day1/a.h5", "size": 123456, "mtime_ns": 1700000000000000000}, ...],
     "train": ["day1/a.h5", ...], "validation": ["day2/b.mat", ...]}

Scene paths are relative to ``root`` (``/`` separators); size and modification time cover every
file a scene is read from (:func:`hsicam.data.pipeline.scene_stat`). A resume compares the folder
with it and refuses another split (:func:`check_same_data`); ``evaluate --run`` tells training,
validation and unseen scenes apart by it (:func:`scene_roles`). Runs on the synthetic data (its
cache is deterministic) and runs from before this record have none: a synthetic run's scenes are told
apart by its config's split instead (:func:`synthetic_scene_roles`).

Which software trained it: each training session (a new run, or a resume) begins its ``metrics.jsonl`` records
with one ``{"step": S, "epoch": E, "session": {...}}`` (:func:`software_record`): the UTC time, the hsicam,
torch, numpy and Python versions, the platform, the device and the process count, and the hsicam git commit
when hsicam runs from a git checkout (``"+dirty"`` when its sources differ from it, with ``source_diff_sha256``,
the hash of the difference).
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any, Sequence

from hsicam.config import DataConfig
from hsicam.data.datasets import scene_path
from hsicam.data.pipeline import dataset_root, scene_stat, split_dataset
from hsicam.data.synthetic import GENERATOR_VERSION
from hsicam.errors import ConfigError, InputError
from hsicam.io import read_record, write_json
from hsicam.runs.folder import DATA_RECORD, MetricsLog, starting_session
from hsicam.runs.folder import run_records as _records
from hsicam.spectral import Bands
from hsicam.spectral.bands import BAND_RULES_VERSION

log = logging.getLogger(__name__)

#: How many scene names a message shows of each kind.
SHOWN = 3


def synthetic_set_record(cfg: DataConfig, bands: Bands) -> dict[str, Any] | None:
    """Which cached synthetic set ``cfg`` reads (None for a ``data.root`` run, which data.json records): its folder
    (chosen by ``data.cache_dir``, else ``$HSICAM_CACHE`` ..., which config.yaml does not record) and the SHA-256 of
    its manifest, which lists every scene's own SHA-256 and the software that made them: two scorings of one
    ``manifest_sha256`` read the same generated scenes, as long as the files were not edited since (``hsicam data
    synth`` checks them against the manifest; training and evaluate do not read every byte twice). Recorded in each
    training session and in evaluate's results.json (session 74's records hunt: a cache of other scenes left every
    record alike). Nothing is generated: a set an evaluation generated only the scored scenes of has no manifest
    yet (``manifest_sha256`` null, ``complete`` false)."""
    import hashlib

    from hsicam.data.synthetic import DEFAULT_HOLDOUT, MANIFEST, dataset_dir, parse_holdout

    if cfg.root is not None:
        return None
    root = dataset_dir(cfg.synthetic_n, cfg.synthetic_size, cfg.synthetic_seed, bands, cache_dir=cfg.cache_dir,
                       holdout_sources=parse_holdout(getattr(cfg, "holdout_sources", DEFAULT_HOLDOUT)))
    try:
        digest = hashlib.sha256((root / MANIFEST).read_bytes()).hexdigest()
    except OSError:
        digest = None
    return {"folder": os.path.abspath(root), "manifest_sha256": digest, "complete": digest is not None}


def data_record(cfg: DataConfig, bands: Bands) -> dict[str, Any] | None:
    """The record of the scenes ``cfg`` trains and validates on now; None for the synthetic data."""
    if cfg.root is None:
        return None
    root = Path(os.path.abspath(dataset_root(cfg, bands)))
    train, val = split_dataset(cfg, bands)
    rel = lambda p: scene_path(p, root)  # noqa: E731
    scenes = []
    for p in sorted([*train, *val]):
        size, mtime_ns = scene_stat(p)
        scenes.append({"path": rel(p), "size": size, "mtime_ns": mtime_ns})
    return {"root": str(root), "split": {"val_fraction": cfg.val_fraction, "split_seed": cfg.split_seed,
                                         "val_pool": cfg.val_pool},
            "scenes": scenes, "train": [rel(p) for p in train], "validation": [rel(p) for p in val]}


def write_data_record(run_dir: str | Path, record: dict[str, Any]) -> None:
    """``RUN/data.json``, atomically."""
    write_json(Path(run_dir) / DATA_RECORD, record)


def read_data_record(run_dir: str | Path) -> dict[str, Any] | None:
    """The run's data record; None when it has none (synthetic data, or a run from before it);
    :class:`InputError` when it cannot be read."""
    def valid(record: Any) -> bool:
        return (isinstance(record, dict) and isinstance(record.get("root"), str)
                and all(isinstance(record.get(k), list) for k in ("scenes", "train", "validation")))

    return read_record(Path(run_dir) / DATA_RECORD, valid,
                       "restore it from a copy of the run, or delete it to go on without checking the data")


def data_changes(recorded: dict[str, Any], current: dict[str, Any]) -> dict[str, list[str]]:
    """Scenes ``added``, ``removed``, ``changed`` (size or modification time) and ``moved`` (between
    training and validation) from ``recorded`` to ``current``; empty lists: the same data and split."""
    have = {e["path"]: e for e in recorded["scenes"]}
    now = {e["path"]: e for e in current["scenes"]}
    role = lambda r, p: "train" if p in r["train"] else "validation"  # noqa: E731
    common = sorted(have.keys() & now.keys())
    return {"added": sorted(now.keys() - have.keys()), "removed": sorted(have.keys() - now.keys()),
            "changed": [p for p in common if (have[p].get("size"), have[p].get("mtime_ns"))
                        != (now[p]["size"], now[p]["mtime_ns"])],
            "moved": [p for p in common if role(recorded, p) != role(current, p)]}


def shown(names: Sequence[str], n: int = SHOWN) -> str:
    """Up to ``n`` names, then how many more."""
    more = len(names) - n
    return ", ".join(names[:n]) + (f" and {more} more" if more > 0 else "")


def check_same_data(run_dir: str | Path, recorded: dict[str, Any] | None, current: dict[str, Any] | None) -> None:
    """Before a resume: :class:`InputError` in one line when the scenes are not those the run
    started with (``recorded``, its data.json; None: nothing to check): added, removed, or moved
    between training and validation, naming up to :data:`SHOWN` of each kind and the remedy. The
    same scenes with another size or time (edited, or a folder copied without its file times) keep
    the split: a warning. A folder moved whole goes on."""
    if recorded is None:
        return
    if current is None:
        raise InputError(f"{run_dir}: trained on the scenes of {recorded['root']} (its {DATA_RECORD}), but data.root "
                         "is now null (the synthetic data); resume with the run's own data.root, or start a new run "
                         "with another --out")
    changes = data_changes(recorded, current)
    words = {"added": "added", "removed": "removed", "moved": "moved between training and validation"}
    parts = [f"{words[k]}: {shown(v)}" for k, v in changes.items() if v and k in words]
    if changes["changed"] and not parts:  # the same scenes and split: a copy without its file times, or edits
        log.warning("data: %d scene(s) of %s changed size or time since the run started (%s): the resume trains "
                    "and validates on them as they are now", len(changes["changed"]), current["root"],
                    shown(changes["changed"]))
    if parts:
        raise InputError(f"{run_dir}: the scenes of {current['root']} are not those the run started with (its "
                         f"{DATA_RECORD}; {'; '.join(parts)}): a resume would train and validate on another split; "
                         "restore the folder as it was, or start a new run with another --out")
    if current["root"] != recorded["root"]:
        log.info("data: the run's scenes, now in %s (they were in %s)", current["root"], recorded["root"])


def recorded_validation(run_dir: str | Path, cfg: DataConfig, bands: Bands) -> list[Path] | None:
    """The scenes a run on a ``data.root`` folder validated on, by its data.json, in the folder ``cfg.root``
    names now (a folder moved whole is found there); None when the run has no record (the synthetic data, an
    older run) or ``cfg`` asks for another split than the run's (``val_fraction``, ``split_seed``, ``val_pool``):
    then ``cfg``'s own split is scored. A folder that gained or lost scenes since the training splits them
    otherwise: the run's own validation scenes are scored all the same (said in the log), and
    :class:`InputError` names those that are gone."""
    if cfg.root is None:
        return None
    recorded = read_data_record(run_dir)
    if recorded is None:
        return None
    split = recorded.get("split") or {}
    if (split.get("val_fraction"), split.get("split_seed"), split.get("val_pool")) != (
            cfg.val_fraction, cfg.split_seed, cfg.val_pool):
        return None
    root = dataset_root(cfg, bands)
    paths = [root / p for p in recorded["validation"]]
    gone = [p for p, full in zip(recorded["validation"], paths) if not full.exists()]
    if gone:
        raise InputError(f"{run_dir}: {len(gone)} of the {len(paths)} scenes the run validated on (its {DATA_RECORD}) "
                         f"are not in {root}: {shown(gone)}; restore them, or score other scenes with --data DIR")
    _, now = split_dataset(cfg, bands)
    if sorted(os.path.abspath(p) for p in now) != sorted(os.path.abspath(p) for p in paths):
        log.info("data: scoring the %d scenes %s validated on (its %s); the scenes of %s now would split otherwise",
                 len(paths), run_dir, DATA_RECORD, root)
    return paths


def scene_roles(recorded: dict[str, Any], paths: Sequence[str | os.PathLike]) -> list[str]:
    """``"train"``, ``"validation"`` or ``"unseen"`` for each scene of ``paths`` by the run's record:
    a scene under the recorded root by its relative path; one elsewhere (a copy of the folder) when
    its path ends with a recorded one and its size and modification time are the recorded ones."""
    role = {**{p: "validation" for p in recorded["validation"]}, **{p: "train" for p in recorded["train"]}}
    stats = {e["path"]: (e.get("size"), e.get("mtime_ns")) for e in recorded["scenes"]}
    roots = {Path(os.path.abspath(recorded["root"])), Path(os.path.realpath(recorded["root"]))}
    by_name: dict[str, list[str]] = {}
    for r in role:
        by_name.setdefault(r.rsplit("/", 1)[-1], []).append(r)
    out = []
    for p in paths:
        found = None
        for a in {Path(os.path.abspath(p)), Path(os.path.realpath(p))}:
            for root in roots:
                if a == root or root in a.parents:
                    found = found or role.get(scene_path(a, root))
        if found is None:
            posix = Path(os.path.abspath(p)).as_posix()
            matches = [r for r in by_name.get(Path(p).name, []) if posix.endswith("/" + r)]
            if matches:
                st = scene_stat(p)
                found = next((role[r] for r in matches if stats.get(r) == st), None)
        out.append(found or "unseen")
    return out


def changed_since_recorded(recorded: dict[str, Any], paths: Sequence[str | os.PathLike]) -> list[str]:
    """The scenes of ``paths`` under the recorded root (by their relative path) whose size or modification time is
    not the record's: files edited or replaced since the run trained (its data.json), scored as they are now."""
    stats = {e["path"]: (e.get("size"), e.get("mtime_ns")) for e in recorded["scenes"]}
    root = Path(os.path.abspath(recorded["root"]))
    out = []
    for p in paths:
        a = Path(os.path.abspath(p))
        rel = scene_path(a, root) if root in a.parents else None
        if rel in stats and tuple(scene_stat(p)) != stats[rel]:
            out.append(rel)
    return out


def synthetic_scene_roles(trained: DataConfig, scored: DataConfig, paths: Sequence[str | os.PathLike]) -> list[str] | None:
    """``"train"``, ``"validation"`` or ``"unseen"`` for each scene of ``paths``, scenes of the synthetic
    training-set cache of the config ``scored`` (e.g. the validation split of an evaluation's
    ``--set data.val_fraction=…``), by the split of the run's own synthetic data ``trained`` (its
    config.yaml): a synthetic run has no ``data.json``, and a scored split other than the run's (another
    ``val_fraction``, ``split_seed``, ``val_pool`` or ``synthetic_n``) holds scenes the network trained
    on. None unless both are the synthetic data; "unseen" for every scene when the two generate other
    scenes (another ``synthetic_seed``, ``synthetic_size`` or set of ``holdout_sources``: scene i of a seed is
    the same cube whatever ``synthetic_n``; the bands are the run's own)."""
    from hsicam.data.datasets import split_scenes
    from hsicam.data.synthetic import DEFAULT_HOLDOUT, SCENE_PATTERN, parse_holdout

    if trained.root is not None or scored.root is not None:
        return None

    def content(d: DataConfig) -> tuple:
        return d.synthetic_seed, d.synthetic_size, parse_holdout(getattr(d, "holdout_sources", DEFAULT_HOLDOUT))

    if content(trained) != content(scored):
        return ["unseen"] * len(paths)
    names = [Path(SCENE_PATTERN.format(i)) for i in range(trained.synthetic_n)]
    train, val = split_scenes(names, trained.val_fraction, trained.split_seed, trained.val_pool)
    role = {**{p.name: "validation" for p in val}, **{p.name: "train" for p in train}}
    return [role.get(Path(p).name, "unseen") for p in paths]


def heldout_sources_problem(trained: DataConfig, scored: DataConfig) -> str | None:
    """Why the held-out-sources set of the evaluation's data config ``scored`` would not be held out
    from a run trained on ``trained`` (its config.yaml), or None: ``--set data.holdout_sources=…``
    naming a source the run's synthetic training scenes contained built a "held-out" set of spectra the
    network trained on. None when ``scored`` builds no held-out set (real data, or nothing held out)."""
    from hsicam.data.synthetic import DEFAULT_HOLDOUT, parse_holdout

    asked = parse_holdout(getattr(scored, "holdout_sources", DEFAULT_HOLDOUT))
    if scored.root is not None or not asked:
        return None
    if trained.root is not None:
        return (f"data.holdout_sources={','.join(asked)}: the run trained on the scenes of {trained.root}, whose "
                "spectra are unknown, so no synthetic set is held out from it; add --set data.holdout_sources=none")
    held = set(parse_holdout(getattr(trained, "holdout_sources", DEFAULT_HOLDOUT)))
    seen = [s for s in asked if s not in held]
    if not seen:
        return None
    return (f"data.holdout_sources={','.join(asked)}: the run's training scenes contain the spectra of "
            f"{', '.join(seen)} (it held out {', '.join(sorted(held)) or 'none'}), so a set built from them is not held "
            "out; give data.holdout_sources a subset of the run's")


def training_scenes_warning(roles: Sequence[str], run: str | Path) -> str | None:
    """The one warning line when some scored scenes were training scenes of ``run``, else None."""
    n = sum(r == "train" for r in roles)
    if not n:
        return None
    return f"{n} of {len(roles)} scenes were training scenes of {run}: their scores are not a validation"


def running_version() -> str:
    """The version of the hsicam code running (``hsicam.__version__``, which the built wheel's metadata takes too):
    not ``importlib.metadata``'s, which names whatever hsicam distribution is installed, e.g. another one than a
    ``PYTHONPATH=src`` checkout's (session 76's packaging hunt: a 0.1.0 checkout recorded as an installed 0.2.0)."""
    from hsicam.version import __version__

    return __version__


def source_checkout() -> Path | None:
    """The git checkout hsicam runs from (``PYTHONPATH=src``, or an editable install: this module lies in its
    ``src/hsicam/``, beside its ``.git``), or None: an installed package (a wheel in site-packages)."""
    here = Path(__file__).resolve()
    root = here.parents[3]  # src/hsicam/engine/provenance.py → the checkout
    return root if here.parents[2].name == "src" and (root / ".git").exists() else None


def source_state() -> dict[str, str | None]:
    """The checkout hsicam runs from: ``git_commit`` (its HEAD, ``+dirty`` when a tracked file under src/ differs from
    it or an untracked, not ignored file sits there) and ``source_diff_sha256`` (SHA-256 over those files, in path
    order, of each one's path and bytes, or a mark for one deleted: a function of the files alone, whatever the
    user's git settings, so two "+dirty" runs of one commit ran the same code exactly when these agree); both None for
    an installed wheel, no git or a git that fails, the hash None for a clean checkout."""
    none: dict[str, str | None] = {"git_commit": None, "source_diff_sha256": None}
    root = source_checkout()
    if root is None:
        return none
    try:
        run = lambda *args: subprocess.run(["git", "-C", str(root), *args], capture_output=True,  # noqa: E731
                                           timeout=10, check=True).stdout
        commit = run("rev-parse", "HEAD").decode().strip()
        # names only (-z: unquoted): no patch text, which diff.* settings, colour or an external diff tool would change
        # (diff.relative off by -c, not --no-relative: a git before 2.28 has no such option)
        changed = run("-c", "diff.relative=false", "diff", "--name-only", "-z", "--no-renames", "--no-ext-diff", "HEAD",
                      "--", "src")
        untracked = run("ls-files", "-z", "--others", "--exclude-standard", "--", "src")
        names = sorted(set(filter(None, (changed + untracked).split(b"\0"))))
        h = hashlib.sha256()
        for name in names:
            path = root / os.fsdecode(name)
            h.update(b"\0file\0" + name + b"\0" + (path.read_bytes() if path.is_file() else b"\0deleted\0"))
    except (OSError, subprocess.SubprocessError, UnicodeDecodeError):
        return none
    if not commit:
        return none
    return {"git_commit": commit + ("+dirty" if names else ""), "source_diff_sha256": h.hexdigest() if names else None}


def commit_label(software: dict[str, Any]) -> str:
    """"commit C" of a :func:`software_record` (results.md's lines), with the first 12 hex digits of its local changes'
    hash when it is "+dirty" (two such records of one commit ran the same code when these agree)."""
    diff = software.get("source_diff_sha256")
    return f"commit {software.get('git_commit')}" + (f", local changes sha256 {str(diff)[:12]}…" if diff else "")


def software_record(device: str, world_size: int = 1) -> dict[str, Any]:
    """What a training session (its run's ``metrics.jsonl``) or a scoring (results.json's ``software``) runs on: UTC
    start time, versions (hsicam, torch, numpy, Python), platform, ``device`` (e.g. "cpu", "cuda:0"), ``threads``
    (torch's CPU threads: weights trained on other thread counts differ in their last bits), ``world_size``
    (processes), and the hsicam git commit when run from a checkout (None otherwise) with the hash of its local changes
    (:func:`source_state`)."""
    import numpy
    import torch

    return {"started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "hsicam": running_version(), **source_state(), "torch": torch.__version__,
            "numpy": numpy.__version__, "python": platform.python_version(), "platform": platform.platform(),
            "executable": sys.executable, "device": str(device), "threads": torch.get_num_threads(),
            "world_size": int(world_size),
            "synthetic_generator": GENERATOR_VERSION, "band_rules": BAND_RULES_VERSION}


def resumed_config_changes(run_dir: str | Path, cfg) -> list[str]:
    """The settings (``"key: before → now"``, runtime keys too: ``train.deterministic`` moves the weights' last bits;
    :func:`hsicam.config.training_differences`) in which ``cfg``, the config a resume goes on with, differs from the
    run's config.yaml before the resume rewrites it; [] when the same or unreadable (the resume's own checks refuse a
    damaged one)."""
    from hsicam.config import load_config, training_differences

    try:
        before = load_config(Path(run_dir) / "config.yaml")
    except (ConfigError, InputError, OSError):
        return []
    return training_differences(before, cfg, limit=1_000_000, runtime=True)


def trained_generator_version(run_dir: str | Path) -> int | None:
    """The synthetic-data generator version (:data:`hsicam.data.synthetic.GENERATOR_VERSION`) of the software that
    started the run ``run_dir``: its starting session record's; None when not recorded (a run of an hsicam before
    session 60, also when a later hsicam resumed it; a folder without metrics.jsonl such as a shipped camera's) or
    unreadable. A run one of :data:`SESSION_60_COMMITS` started records none but trained on
    :data:`SESSION_60_GENERATOR`."""
    start = starting_session(_records(run_dir)) or {}
    v = start.get("synthetic_generator")
    if v is None and "synthetic_generator" not in start and _session_60_commit(start):
        return SESSION_60_GENERATOR
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def started_before_session_60(run_dir: str | Path) -> bool:
    """Whether an hsicam before session 60 started the run at ``run_dir``: its metrics.jsonl holds records, but its
    starting session record (:func:`starting_session`) is missing (before db9c133) or lacks ``synthetic_generator``
    (recorded since session 60, after that session changed the training: :func:`hsicam.engine.loop.older_run_changes`).
    False when nothing is recorded (no metrics.jsonl, or no record in it), it cannot be read, or its first line is
    no whole record (torn by a kill, or blank: the starting session record is lost, the start unknown)."""
    records = _records(run_dir)
    if records and not MetricsLog(Path(run_dir) / "metrics.jsonl", enabled=False).first_line_whole():
        # a first line torn by a kill (or blanked) held the starting session record: the start is not known, and an
        # hsicam before session 60 is no likelier than this one (nothing else in the folder dates the run)
        log.debug("%s: metrics.jsonl's first line is no whole record: the software that started the run is not "
                  "known", run_dir)
        return False
    return bool(records) and "synthetic_generator" not in (starting_session(records) or {})


#: The commits of session 60 from c5559eb, its first change of the training that
#: :func:`hsicam.engine.loop.older_run_changes` names, to 215c9e2, the last before c1ab911 recorded
#: ``synthetic_generator`` (an hour): a run one of them started lacks it, as a run of an hsicam before session 60 does,
#: and it trained with some of those changes already: "cosine" (c5559eb: the cosine after a warm-up), "seed" (4625829:
#: train.seed's patch stream), "choi_seed" (7cf40af: baselines.choi.seed's), "validation_noise" (487c91d: drawn from
#: seed 0). Only its starting session record's ``git_commit`` tells which (a run from a git checkout; "+dirty" is read
#: as its commit): nothing else such a run writes differs from an older hsicam's (its hsicam version is the same, its
#: started_utc is the machine's clock, not the code's, its checkpoint and config are today's layout), so a run of that
#: hour from an installed package (git_commit null) cannot be told from an older one and its resume names every change.
SESSION_60_COMMITS: dict[str, frozenset[str]] = {
    **dict.fromkeys((
        "c5559eb5f5d609ab584e8aa0697d03cb6f465f42", "9a61ce975f2a83d998625ca23d012fd523182be2",
    ), frozenset({"cosine"})),
    **dict.fromkeys((
        "46258292dfa30e997d70c85c9806b1eb6dd61bb3", "cd86546166146b7ac1eec5383fadbf32e7e94a6f",
        "8709e122aec82bd34ab2aeab2307fdbe097ea457", "781e9eed8102b4fa31e99b951c91875bf5638091",
        "d3f87b6eae8bd3cbb46e045afce41b2280b3a6d0", "528b47533d06b87b3e7f50eede6a6ed96c72ba5e",
        "673e8051d612133bd92373137ad3cdc1306e6857", "d1e4deefa1163e2156638521d3974459eeaea00c",
        "f6ac91428b682dfb3b098fd2cb67dfb3c07d6847", "eede12b0e2558a9ae478b804f5320b1ad2e41a45",
        "c339cceffee4eb15968a8e1b8eb1c6951a13a06c", "01e709e8bc69fa69601f9e72f983f4a71b148227",
        "c30355916a3e112365611d0097994ce0bef5aad4", "d716039a77812b6c26a8d3f60b9276ef036951b3",
        "b1647cdf03d821a854c046a120025c02c5fe1997",
    ), frozenset({"cosine", "seed"})),
    **dict.fromkeys((
        "7cf40af10a5763a37f6198233efecef2dacda8b5",
    ), frozenset({"cosine", "seed", "choi_seed"})),
    **dict.fromkeys((
        "487c91d1c989396c1c7d8405a8e6d100198dfd25", "8d28eaa40e4714a705dd3333bc567d2caff8c0da",
        "c930343abc04e9c675db6f615fb07aa62165d64c", "fb48ab7309ec8f888b9fcc8bb384656b5e4eef0d",
        "68f907c15f82a32c81f9779f5ee08d10c35812eb", "f8ce426b730bfaf18c4bedf25d2c631310cff5d6",
        "d33dd4d30b49d1f217af100fa9d498d83f1f7edb", "e26a0ca242b0832e3c0607fbadf077424393f7c6",
        "cfa9e0019ebbdd31972ec8d5c941d1d801ab0815", "c79848ee4719ee471410c3a0e6713b159054db3e",
        "0e2ecde7acd7d01df487738359abe9696b7c0729", "135f19e260df158abf05239e1edba8e83e3c1c5a",
        "354395ea310c23e9b99cb1330080e141642b2f4b", "8d5fc3fba4e4db50035d9dadf12ef2a7891a30a8",
        "3779572269a78a85647c7068bb2efb8c4e66fb8d", "0b3ab4f4c32720cc7c9e724768815cb42b5a7cf8",
        "1688edeaf0f51be2f988f44680643a2064ff8915", "e2d121aea83247afa13f77c86ef1d63b5416ba82",
        "27a4dcaa378bd0aa98373323ce32b7b73d590881", "e9ca0fb98263ae444dc4e7e53d3518cc0f4593a2",
        "215c9e2c6a5b8cfb4155e94a547c7cb96ff3dbbd",
    ), frozenset({"cosine", "seed", "choi_seed", "validation_noise"})),
}


#: The synthetic-data generator version of every commit of :data:`SESSION_60_COMMITS` (each one's GENERATOR_VERSION).
SESSION_60_GENERATOR = 3


def session_60_changes_had(run_dir: str | Path) -> tuple[str | None, frozenset[str]]:
    """The commit that started the run at ``run_dir`` when it is one of :data:`SESSION_60_COMMITS`, and which of
    session 60's changes of the training it had already; (None, frozenset()) otherwise."""
    commit = _session_60_commit(starting_session(_records(run_dir)) or {})
    return (commit, SESSION_60_COMMITS[commit]) if commit else (None, frozenset())


def _session_60_commit(start: dict[str, Any]) -> str | None:
    """The commit of :data:`SESSION_60_COMMITS` that a starting session record names (its "+dirty" read as that
    commit), else None."""
    commit = start.get("git_commit")
    commit = commit.removesuffix("+dirty") if isinstance(commit, str) else None
    return commit if commit in SESSION_60_COMMITS else None


def generator_change_warning(run_dir: str | Path, data: DataConfig, doing: str) -> str | None:
    """A warning when the run at ``run_dir`` trained on the synthetic data of another generator version than this
    hsicam's, which ``doing`` (e.g. "is scored", "goes on") on this version's scenes; None otherwise (a data.root
    run, an unrecorded version, the same version)."""
    if data.root is not None:
        return None
    was = trained_generator_version(run_dir)
    if was is None or was == GENERATOR_VERSION:
        return None
    return (f"{run_dir} trained on scenes of synthetic-data generator version {was}; this hsicam generates version "
            f"{GENERATOR_VERSION} (docs/data.md), so it {doing} on other scenes than its own version's: figures are "
            f"not comparable with those the run's version gave")


__all__ = ["check_same_data", "data_changes", "data_record", "generator_change_warning",
           "read_data_record", "running_version", "scene_roles", "heldout_sources_problem", "SESSION_60_COMMITS",
           "SESSION_60_GENERATOR", "session_60_changes_had", "software_record", "started_before_session_60",
           "commit_label", "source_checkout", "source_state", "starting_session", "synthetic_scene_roles",
           "trained_generator_version", "training_scenes_warning", "write_data_record"]
