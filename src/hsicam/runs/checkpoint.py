"""Checkpoints in safetensors, written atomically (loading a run for inference: :mod:`hsicam.runs.folder`).

Run folder layout::

    RUN/config.yaml            resolved config
    RUN/metrics.jsonl          one JSON object per log/eval event
    RUN/checkpoints/step-N/    model.safetensors, optimizer.safetensors, state.json
    RUN/checkpoints.json       the manifest: the one commit point of every checkpoint
    RUN/model.safetensors      weights of the checkpoint the run keeps (``train.keep_weights``: its best,
                               else last; or its last), derived from the manifest
    RUN/.hsicam-lock           while a process trains in the run (:mod:`hsicam.runs.lock`)

**One commit point.** A checkpoint is written as a step folder under a hidden temporary name and
renamed into place; then ONE small manifest, ``checkpoints.json``, is replaced atomically::

    {"format": "hsicam-run-manifest-1",
     "last":  {"dir": "checkpoints/step-00000012", "step": 12, "weights_sha256": "…", "optimizer_sha256": "…"},
     "best":  {"dir": "checkpoints/step-00000008", "step": 8, "psnr": 23.4, "weights_sha256": "…",
               "optimizer_sha256": "…"} | null,
     "state": {LoopState of the last checkpoint: epoch, step_in_epoch, global_step, best_psnr, …},
     "weights": {"file": "model.safetensors", "from": "best" | "last", "sha256": "…"}}

Until the manifest is replaced, the previous one names checkpoints that still exist (only folders
the current manifest does not name are ever pruned, so the best checkpoint is never pruned). The
root weights file is a copy of the checkpoint the manifest's ``weights`` entry names; it is rewritten
after every commit, on resume when it is missing or out of date, and :func:`root_weights_path`
falls back to the checkpoint whenever the root file's hash differs from the manifest's: a reader
never takes other weights than the ones the manifest's ``weights`` entry names. Which checkpoint
that is, the training decides (``train.keep_weights``, :class:`CheckpointManager`'s ``keep``):
"best" (the highest validation PSNR so far, else the last) or "last" (the last step: no selection
on the validation scenes, whose metrics are then those of an unselected model). Runs written before the manifest
(``last.json`` / ``best.json`` pointers) are read as before and converted at their next checkpoint.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save
from torch import nn

from hsicam.errors import InputError
from hsicam.io import NO_SPACE_ERRNOS, atomic_path, cleanup_stale_temporaries, file_sha256, write_json
from hsicam.spectral import Bands

FORMAT = "hsicam-checkpoint-1"
MANIFEST = "checkpoints.json"
MANIFEST_FORMAT = "hsicam-run-manifest-1"
LEGACY_POINTERS = ("last.json", "best.json")
#: What a damaged or incomplete run folder's refusals tell the user to do.
RECOPY_HINT = "copy the run folder again from its source, or train it again"
#: Which checkpoint a run's root weights hold (``train.keep_weights``).
KEEP_WEIGHTS = ("best", "last")

log = logging.getLogger(__name__)


def _reason(exc: OSError) -> str:
    """What went wrong in ``exc``, without the file name."""
    if exc.errno is not None:
        return os.strerror(exc.errno)
    return exc.strerror or (str(exc).splitlines() or [type(exc).__name__])[0]


def _resume_hint(exc: OSError) -> str:
    full = exc.errno in NO_SPACE_ERRNOS
    return "free some space, then resume the run" if full else "resume the run once it can be written"


def save_safetensors(path: str | Path, tensors: dict[str, torch.Tensor], meta: dict[str, str]) -> None:
    """``tensors`` → safetensors file ``path`` (atomic). A failed write (a full disk …) is an
    OSError naming ``path``, ``path`` left as it was."""
    with atomic_path(path) as tmp:
        _write_safetensors(tensors, tmp, meta)
        _sort_metadata(tmp)


def _write_safetensors(tensors: dict[str, torch.Tensor], path: Path, meta: dict[str, str]) -> None:
    """The safetensors bytes of ``tensors`` into ``path`` (a temporary of :func:`save_safetensors`).

    Serialised in memory and written here, not by safetensors' ``save_file``: that writes a mkstemp file
    of its own (mode 0600 whatever the umask, so a group sharing the run could not read its checkpoints;
    named ``.tmpXXXXXX``, which a killed process left where no cleanup looks) and renames it onto
    ``path``; its errors named no file."""
    data = save(tensors, metadata=meta)
    with open(path, "wb") as fh:
        fh.write(data)


def _sort_metadata(path: Path) -> None:
    """Rewrite the safetensors header of ``path`` in place with its ``__metadata__`` keys sorted.

    The writer (Rust) keeps the metadata in a hash map whose order is random per call, so the same
    tensors and metadata gave files of different bytes, hence different SHA-256 (the runs' manifests,
    results.json's ``weights_sha256`` and the linear step's record of the weights it was fitted
    through). Only the order of keys changes: the header keeps its length, the tensors their bytes."""
    with open(path, "r+b") as fh:
        n = int.from_bytes(fh.read(8), "little")
        raw = fh.read(n)
        header = json.loads(raw)
        meta = header.get("__metadata__")
        if not isinstance(meta, dict) or len(meta) < 2:
            return
        ordered = {"__metadata__": dict(sorted(meta.items())), **{k: v for k, v in header.items() if k != "__metadata__"}}
        if list(header) != list(ordered):  # the metadata written first, as the writer does
            return
        text = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
        if len(text) > n or json.loads(text) != header:  # another serialisation than expected: leave it
            return
        fh.seek(8)
        fh.write(text + b" " * (n - len(text)))  # safetensors pads its header with spaces


def save_weights(path: str | Path, model: nn.Module, bands: Bands, extra: dict[str, str] | None = None) -> None:
    """Model state dict → safetensors (atomic), with the band grid in the metadata."""
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    meta = {"format": FORMAT, "bands": json.dumps(bands.to_dict()), **(extra or {})}
    save_safetensors(path, tensors, meta)


def read_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of a safetensors file; :class:`InputError` if missing or corrupt."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such weights file")
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise InputError(f"{path}: corrupt or unreadable safetensors file ({str(exc).splitlines()[0]})") from None
    return tensors, meta


def load_weights(path: str | Path, model: nn.Module, bands: Bands) -> None:
    """Load weights into ``model`` after checking the band grid and the tensor names and shapes."""
    tensors, meta = read_weights(path)
    if "bands" in meta:
        saved = _saved_bands(path, meta["bands"])
        if not saved.matches(bands):
            raise InputError(f"{path}: checkpoint was trained on {saved!r}, but the model has {bands!r}")
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise InputError(f"{path}: weights do not fit this model (missing {missing[:3]}, unexpected {unexpected[:3]})")
    for k, v in tensors.items():
        if v.shape != expected[k].shape:
            raise InputError(f"{path}: tensor {k} has shape {tuple(v.shape)}, the model expects {tuple(expected[k].shape)}")
        if expected[k].is_floating_point() and not v.is_floating_point():  # load_state_dict would cast it silently
            raise InputError(f"{path}: tensor {k} holds {str(v.dtype).removeprefix('torch.')} values, the model expects "
                             f"floating-point ({str(expected[k].dtype).removeprefix('torch.')}): not weights this "
                             "program wrote")
    model.load_state_dict(tensors)


def _saved_bands(path: str | Path, text: str) -> Bands:
    """The band grid a weights file's metadata records (``bands``: JSON of :meth:`Bands.to_dict`);
    :class:`InputError` naming the file when it is not one."""
    try:
        return Bands.from_dict(json.loads(text))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:  # JSONDecodeError is a ValueError
        reason = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise InputError(f"{path}: corrupt band grid in the file's metadata ({reason}); {RECOPY_HINT}") from None


def save_optimizer(path: str | Path, optimizer: torch.optim.Optimizer) -> None:
    """Optimizer state → safetensors (tensors) + JSON metadata (param groups, scalars)."""
    sd = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, Any] = {}
    for idx, st in sd["state"].items():
        for name, val in st.items():
            if isinstance(val, torch.Tensor):
                tensors[f"{idx}.{name}"] = val.detach().cpu().contiguous()
            else:
                scalars[f"{idx}.{name}"] = val
    meta = {"format": FORMAT, "param_groups": json.dumps(sd["param_groups"]), "scalars": json.dumps(scalars)}
    save_safetensors(path, tensors, meta)


def load_optimizer(path: str | Path, optimizer: torch.optim.Optimizer) -> None:
    tensors, meta = read_weights(path)
    try:
        groups = json.loads(meta["param_groups"])
        scalars = json.loads(meta["scalars"])
    except (KeyError, json.JSONDecodeError):
        raise InputError(f"{path}: not an hsicam optimizer state") from None
    if not isinstance(groups, list) or not isinstance(scalars, dict):
        raise InputError(f"{path}: not an hsicam optimizer state (its param_groups are no list, or its scalars "
                         "no mapping)")
    state: dict[int, dict[str, Any]] = {}
    for key, val in [*tensors.items(), *scalars.items()]:
        idx, _, name = key.partition(".")
        if not idx.isdigit() or not name:
            raise InputError(f"{path}: not an hsicam optimizer state (entry {key!r} is not PARAM_INDEX.NAME)")
        state.setdefault(int(idx), {})[name] = val
    saved = [g.get("name") for g in groups if isinstance(g, dict)]
    current = [g.get("name") for g in optimizer.param_groups]
    if None not in saved and saved != current:  # e.g. train.freeze changed: say which groups, not torch's words
        raise InputError(f"{path}: the run trained the parameter groups {', '.join(map(str, saved))}, this config trains "
                         f"{', '.join(map(str, current)) or 'none'} (train.freeze, or a camera part switched on or off, "
                         "differs from the run's config.yaml); resume with the run's own settings, or start a new run")
    try:
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except KeyError as exc:  # torch's own words would be just the key, e.g. ('params')
        raise InputError(f"{path}: not an hsicam optimizer state (a parameter group has no {exc.args[0]!r} entry); "
                         f"{RECOPY_HINT}") from None
    except (ValueError, TypeError, AttributeError) as exc:
        raise InputError(f"{path}: optimizer state does not fit ({exc})") from None
    for param, st in optimizer.state.items():  # torch checks none of this; the first step would fail on it
        for name, val in st.items():
            if isinstance(val, torch.Tensor) and val.dim() > 0 and val.shape != param.shape:
                optimizer.state.clear()
                raise InputError(f"{path}: optimizer state {name} has shape {tuple(val.shape)}, its parameter "
                                 f"{tuple(param.shape)}: the file belongs to another model; "
                                 f"{RECOPY_HINT}")


class CheckpointManager:
    """Writes and finds the checkpoints of one run folder (see the module docstring).

    ``weights_file`` is the name of the root weights file (``model.safetensors``; the spectral
    prior uses ``prior.safetensors``). ``keep`` is the checkpoint a commit makes the root weights
    hold: "best" (else last) or "last" (``train.keep_weights``); readers follow what the manifest
    records, whatever this manager's ``keep``."""

    def __init__(self, run_dir: str | Path, weights_file: str = "model.safetensors", keep: str = "best") -> None:
        if keep not in KEEP_WEIGHTS:
            raise ValueError(f"keep must be one of {KEEP_WEIGHTS}, got {keep!r}")
        self.run_dir = Path(run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.weights_file = weights_file
        self.keep = keep
        self._told_damaged: set[tuple[Path, str]] = set()  # sync_root's warnings given (one per file and hash)

    # -- the manifest -------------------------------------------------------------------------
    def manifest(self) -> dict[str, Any] | None:
        """The run's manifest (``checkpoints.json``; a run of the older layout: built from its
        ``last.json`` / ``best.json``), or None when the run has no checkpoint yet."""
        path = self.run_dir / MANIFEST
        if path.is_file():
            try:
                man = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, ValueError):
                raise InputError(f"{path}: corrupt checkpoint manifest (not readable JSON); {RECOPY_HINT}") from None
            if not isinstance(man, dict):
                raise InputError(f"{path}: corrupt checkpoint manifest (not a JSON object); {RECOPY_HINT}")
            if man.get("format") != MANIFEST_FORMAT:
                raise InputError(f"{path}: not a checkpoint manifest this hsicam reads (format {man.get('format')!r}, "
                                 f"expected {MANIFEST_FORMAT!r}: written by another hsicam version, or damaged); "
                                 f"use the hsicam that trained the run, or {RECOPY_HINT}")
            if not isinstance(man.get("last"), dict) or "dir" not in man["last"]:
                raise InputError(f"{path}: corrupt checkpoint manifest ('last' is not an entry {{dir, step, …}}); "
                                 f"{RECOPY_HINT}")
            problem = _manifest_problem(man)
            if problem is not None:
                raise InputError(f"{path}: corrupt checkpoint manifest ({problem}); {RECOPY_HINT}")
            return man
        return self._legacy_manifest()

    def _legacy_manifest(self) -> dict[str, Any] | None:
        entries: dict[str, Any] = {}
        for tag in ("last", "best"):
            ptr = self.run_dir / f"{tag}.json"
            if not ptr.is_file():
                continue
            try:
                data = json.loads(ptr.read_text(encoding="utf-8"))
                d = data.pop("dir")
            except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError):
                raise InputError(f"{ptr}: corrupt checkpoint pointer") from None
            entries[tag] = {"dir": d, "step": data.get("global_step"), "state": data}
            problem = _entry_problem(tag, entries[tag])  # checked as a manifest's entries are: readers index it
            if problem is not None:
                raise InputError(f"{ptr}: corrupt checkpoint pointer ({problem}); {RECOPY_HINT}")
        if "last" not in entries:
            return None
        best = entries.get("best")
        return {"format": MANIFEST_FORMAT, "last": {"dir": entries["last"]["dir"], "step": entries["last"]["step"]},
                "best": None if best is None else {"dir": best["dir"], "step": best["step"],
                                                   "psnr": best["state"].get("best_psnr")},
                "state": entries["last"]["state"], "legacy": True}

    def path(self, tag: str) -> Path | None:
        """Checkpoint directory that ``tag`` ("last" or "best") names, or None."""
        man = self.manifest()
        entry = None if man is None else man.get(tag)
        if not entry:
            return None
        d = self.run_dir / entry["dir"]
        return d if d.is_dir() else None

    def state(self) -> dict[str, Any] | None:
        """The training state (LoopState) committed with the last checkpoint, or None."""
        man = self.manifest()
        return None if man is None else dict(man["state"])

    # -- writing ------------------------------------------------------------------------------
    def save(self, model: nn.Module, optimizer: torch.optim.Optimizer, state: dict[str, Any], bands: Bands,
             tags: tuple[str, ...] = ("last",), meta: dict[str, str] | None = None) -> Path:
        """Write checkpoint ``step-<global_step>``, then commit it: the manifest names it as last
        (and as best when ``tags`` holds "best"). Then the root weights follow the manifest and
        the folders it no longer names are pruned.

        A failed write (a full disk …) is one :class:`InputError` naming the file and what the run
        keeps: before the manifest is replaced nothing is committed, and a resume continues from
        the previous checkpoint."""
        old = self.manifest()
        step = int(state["global_step"])
        name = f"step-{step:08d}"
        final = self.ckpt_dir / name
        rel = f"checkpoints/{name}"
        named = {} if old is None else {e["dir"]: e for e in (old.get("last"), old.get("best")) if e}
        if final.is_dir() and rel in named:
            # Same step (e.g. the epoch-end save after a periodic one): the weights are the same;
            # only the training state moves on, and it lives in the manifest.
            sha = named[rel].get("weights_sha256") or file_sha256(final / "model.safetensors")
            opt_sha = named[rel].get("optimizer_sha256")
        else:
            tmp = self.ckpt_dir / f".{name}.{os.urandom(4).hex()}.tmpdir"
            writing = final  # what a failed write is named by
            try:
                if final.is_dir() and not final.is_symlink():  # a folder no manifest names (left by a killed
                    shutil.rmtree(final)                          # process): redo it
                elif final.is_symlink() or final.exists():  # a file (or link) in the step folder's place
                    final.unlink()
                self.ckpt_dir.mkdir(parents=True, exist_ok=True)
                os.mkdir(tmp)
                for file, write in (("model.safetensors", lambda p: save_weights(p, model, bands, meta)),
                                    ("optimizer.safetensors", lambda p: save_optimizer(p, optimizer)),
                                    ("state.json", lambda p: write_json(p, state))):  # state.json: informational
                    writing = final / file
                    write(tmp / file)
                writing = final
                os.rename(tmp, final)
            except BaseException as exc:
                shutil.rmtree(tmp, ignore_errors=True)
                if isinstance(exc, OSError):
                    raise self._uncommitted(exc, writing, old) from None
                raise
            sha = file_sha256(final / "model.safetensors")
            opt_sha = file_sha256(final / "optimizer.safetensors")
        entry = {"dir": rel, "step": step, "weights_sha256": sha, "optimizer_sha256": opt_sha}
        best = None if old is None else old.get("best")
        if "best" in tags:
            best = {**entry, "psnr": state.get("best_psnr")}
        root_from = "best" if best and self.keep == "best" else "last"
        src = best if root_from == "best" else entry
        man = {"format": MANIFEST_FORMAT, "last": entry, "best": best, "state": dict(state),
               "weights": {"file": self.weights_file, "from": root_from, "dir": src["dir"],
                           "sha256": src.get("weights_sha256")}}
        try:
            write_json(self.run_dir / MANIFEST, man)  # the commit point
        except OSError as exc:
            if rel not in named:
                shutil.rmtree(final, ignore_errors=True)  # named by no manifest
            raise self._uncommitted(exc, self.run_dir / MANIFEST, old) from None
        for legacy in LEGACY_POINTERS:
            (self.run_dir / legacy).unlink(missing_ok=True)
        try:
            self.sync_root()
        except OSError as exc:
            raise InputError(f"{self.run_dir / self.weights_file}: {_reason(exc)}; checkpoint step {step} was committed, "
                             f"but {self.weights_file} still holds earlier weights (readers take the checkpoint's; "
                             f"a resume rewrites it): {_resume_hint(exc)}") from None
        self._prune(man)
        return final

    def apply_keep(self) -> bool:
        """Make the manifest's ``weights`` entry name the checkpoint this manager keeps (``keep``; "best"
        in a run without one: its last) and the root weights follow (:meth:`sync_root`): a finished
        run given another ``train.keep_weights``. A run of the older layout (``last.json`` /
        ``best.json``) gets its manifest now, as at its next checkpoint. Returns True when the
        manifest changed; a run without any checkpoint is left as it is. The checkpoint it would
        keep must exist and hold the weights the manifest records (one-line :class:`InputError` otherwise,
        nothing changed)."""
        man = self.manifest()
        if man is None:
            return False
        legacy = bool(man.pop("legacy", False))
        tag = "best" if self.keep == "best" and man.get("best") else "last"
        if not legacy and kept_entry(man)[0] == tag and isinstance(man.get("weights"), dict):
            return False
        src = man[tag]
        weights = self.run_dir / src["dir"] / "model.safetensors"
        if not weights.is_file():
            raise InputError(f"{weights}: the {tag} checkpoint named by {self.run_dir / MANIFEST if not legacy else tag + '.json'} "
                             f"is missing, so the run cannot keep it (train.keep_weights: {self.keep}); nothing was changed")
        sha = src.get("weights_sha256")
        if sha is not None and file_sha256(weights) != sha:  # committed, readers would then refuse the run's weights
            raise InputError(f"{weights} differs from the weights {self.run_dir / MANIFEST} records (sha256 {sha[:12]}…): "
                             f"the {tag} checkpoint is damaged (a copy cut short, a disk error, an edit), so the run "
                             f"cannot keep it (train.keep_weights: {self.keep}); nothing was changed; {RECOPY_HINT}")
        man["weights"] = {"file": self.weights_file, "from": tag, "dir": src["dir"], "sha256": sha}
        write_json(self.run_dir / MANIFEST, man)  # the commit point; the root weights follow
        for pointer in LEGACY_POINTERS:
            (self.run_dir / pointer).unlink(missing_ok=True)
        self.sync_root()
        return True

    def _uncommitted(self, exc: OSError, path: Path, old: dict[str, Any] | None) -> InputError:
        """The failed write of a checkpoint's ``path`` before its commit, saying what the run keeps."""
        kept = (f"the last checkpoint (step {old['last'].get('step')}) is unchanged" if old is not None
                else "the run has no checkpoint yet")
        return InputError(f"{path}: {_reason(exc)}; nothing was committed: {kept}; {_resume_hint(exc)}")

    def root_source(self) -> tuple[Path, str | None] | None:
        """(weights file of the checkpoint the root weights must hold, its SHA-256 when recorded): the
        one the manifest's ``weights`` entry names (manifests without one: the best, else the last)."""
        man = self.manifest()
        if man is None:
            return None
        _, entry = kept_entry(man)
        return self.run_dir / entry["dir"] / "model.safetensors", entry.get("weights_sha256")

    def sync_root(self) -> bool:
        """Rewrite the root weights file when it is missing or holds other weights than the
        checkpoint the manifest keeps (:meth:`root_source`); returns True when it was rewritten.
        A kept checkpoint that differs from the sha256 the manifest records (damaged) is not copied:
        a warning says so and the root file stays as it is (readers refuse both)."""
        src = self.root_source()
        if src is None:
            return False
        path, sha = src
        if not path.is_file():
            raise InputError(f"{path}: the checkpoint named by {self.run_dir / MANIFEST} is missing (the run folder "
                             f"is incomplete); {RECOPY_HINT}")
        recorded, sha = sha, sha or file_sha256(path)
        root = self.run_dir / self.weights_file
        if root.is_file() and file_sha256(root) == sha:
            return False
        if recorded is not None and file_sha256(path) != recorded:
            if (path, recorded) in self._told_damaged:  # a save after each epoch would repeat it word for word
                return False
            self._told_damaged.add((path, recorded))
            log.warning("%s differs from the weights %s records (sha256 %s…): the checkpoint is damaged (a copy cut "
                        "short, a disk error, an edit), so %s was not rewritten from it; %s", path,
                        self.run_dir / MANIFEST, recorded[:12], root, RECOPY_HINT)
            return False
        with atomic_path(root) as tmp:
            shutil.copyfile(path, tmp)
        return True

    def cleanup(self) -> list[Path]:
        """Remove what a killed process may have left: hidden temporaries (in the run folder and
        its checkpoints) and step folders the manifest does not name. Returns the removed paths."""
        removed = cleanup_stale_temporaries(self.run_dir, recursive=True)
        if self.ckpt_dir.is_dir():
            man = self.manifest()
            removed += self._prune(man)
        return removed

    def _prune(self, man: dict[str, Any] | None) -> list[Path]:
        keep = set() if man is None else {Path(e["dir"]).name for e in (man.get("last"), man.get("best")) if e}
        removed = []
        for d in sorted(self.ckpt_dir.iterdir()):
            if d.name in keep:
                continue
            if d.name.startswith(("step-", ".step-")):  # hidden: temporaries of killed writes
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
        return removed

    # -- reading ------------------------------------------------------------------------------
    def _check_recorded(self, path: Path, sha: str | None, what: str) -> None:
        """InputError when ``path`` differs from the sha256 the manifest records for it (``what``: "weights",
        "optimizer state"); nothing to check for an older manifest without it."""
        if sha is not None and file_sha256(path) != sha:
            raise InputError(f"{path} differs from the {what} {self.run_dir / MANIFEST} records (sha256 {sha[:12]}…): the "
                             f"checkpoint is damaged (a copy cut short, a disk error, an edit); {RECOPY_HINT}")

    def load(self, tag: str, model: nn.Module, optimizer: torch.optim.Optimizer | None, bands: Bands) -> dict[str, Any]:
        """Restore model (and optimizer) from ``tag``; returns the committed training state."""
        d = self.path(tag)
        if d is None:
            raise InputError(f"{self.run_dir}: no '{tag}' checkpoint to resume from")
        entry = (self.manifest() or {}).get(tag) or {}
        weights = d / "model.safetensors"
        if not weights.is_file():  # (file_sha256 would be a raw FileNotFoundError)
            raise InputError(f"{weights}: missing from the '{tag}' checkpoint that {self.run_dir / MANIFEST} "
                             f"names (the run folder is incomplete); {RECOPY_HINT}")
        self._check_recorded(weights, entry.get("weights_sha256"), "weights")  # never train on from damaged weights
        load_weights(weights, model, bands)
        if optimizer is not None:
            opt_file = d / "optimizer.safetensors"
            if opt_file.is_file():  # (a missing one: load_optimizer's refusal)
                self._check_recorded(opt_file, entry.get("optimizer_sha256"), "optimizer state")  # nor damaged moments
            load_optimizer(opt_file, optimizer)
        if tag == "last":
            return self.state() or {}
        try:
            return json.loads((d / "state.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            raise InputError(f"{d / 'state.json'}: corrupt checkpoint state") from None


def _entry_problem(key: str, entry: Any) -> str | None:
    """What is wrong with the manifest's checkpoint entry ``key`` ("last", "best"), or None."""
    if not isinstance(entry, dict):
        return f"'{key}' is not an entry {{dir, step, …}}"
    d = entry.get("dir")
    if not isinstance(d, str) or not d or Path(d).is_absolute() or ".." in Path(d).parts:
        return f"'{key}.dir' is not a checkpoint folder inside the run: {d!r}"
    step = entry.get("step")
    if step is not None and (not isinstance(step, int) or isinstance(step, bool) or step < 0):
        return f"'{key}.step' is not a step number: {step!r}"
    for field in ("weights_sha256", "optimizer_sha256"):
        sha = entry.get(field)
        if sha is not None and not isinstance(sha, str):
            return f"'{key}.{field}' is not a hash: {sha!r}"
    return None


def _manifest_problem(man: dict[str, Any]) -> str | None:
    """What is wrong with a manifest's structure beyond its format and 'last' entry (an edit, another
    program's file), or None: the readers index its entries without checking them again."""
    for key in ("last", "best"):
        if key == "best" and man.get(key) is None:
            continue
        problem = _entry_problem(key, man.get(key))
        if problem is not None:
            return problem
    if not isinstance(man.get("state"), dict):
        return f"'state' is not a mapping of the training state: {man.get('state')!r}"[:200]
    weights = man.get("weights")
    if weights is not None:
        if not isinstance(weights, dict):
            return f"'weights' is not an entry {{file, from, sha256}}: {weights!r}"[:200]
        sha = weights.get("sha256")
        if sha is not None and not isinstance(sha, str):
            return f"'weights.sha256' is not a hash: {sha!r}"
    return None


def kept_entry(man: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """("best" | "last", the manifest's entry ``{"dir", "step", …}``) of the checkpoint the run keeps:
    the one its ``weights`` entry names, else (older manifests) the best, else the last."""
    weights = man.get("weights")
    tag = weights.get("from") if isinstance(weights, dict) else None
    if tag in KEEP_WEIGHTS and man.get(tag):
        return tag, man[tag]
    return ("best", man["best"]) if man.get("best") else ("last", man["last"])


def kept_checkpoint(run_dir: str | Path, weights_file: str = "model.safetensors") -> dict[str, Any] | None:
    """Which checkpoint a run's root weights come from, for a results file: ``{"checkpoint": "best" |
    "last", "step": N, "last_step": M}`` (M: the step of the run's last checkpoint), with
    ``"selected_on"`` for the best (the validations chose it); None for a folder without any
    checkpoint (e.g. a shipped camera)."""
    man = CheckpointManager(run_dir, weights_file).manifest()
    if man is None:
        return None
    tag, entry = kept_entry(man)
    out: dict[str, Any] = {"checkpoint": tag, "step": entry.get("step"), "last_step": man["last"].get("step")}
    if tag == "best":
        out["selected_on"] = "validation PSNR (patches of the validation scenes): the highest of the run's validations"
    return out


def weights_identity(run_dir: str | Path, weights_file: str = "model.safetensors") -> dict[str, Any]:
    """What a results file records of the weights a run keeps, taken when they are read (``hsicam evaluate``,
    ``hsicam demo``): ``weights_sha256`` (of :func:`root_weights_path`) and ``weights`` (:func:`kept_checkpoint`),
    each when there is one; {} for a folder without its root weights file or with damaged weights (the run's loading
    refuses those in its own line)."""
    if not (Path(run_dir) / weights_file).is_file():
        return {}
    try:
        path = root_weights_path(run_dir, weights_file)
    except InputError:
        return {}
    kept = kept_checkpoint(run_dir, weights_file)
    return {**({"weights_sha256": file_sha256(path)} if path.is_file() else {}),
            **({"weights": kept} if kept is not None else {})}


def read_with_weights_identity(run_dir: str | Path, read, *args, weights_file: str = "model.safetensors"):
    """``read(*args)`` (what loads ``run_dir``'s weights: a method or model built from the run) and the
    :func:`weights_identity` of the weights it read: taken before and after the read, and one :class:`InputError` when
    they differ (a training writing the run meanwhile), so a results file never records another step's hash beside
    its scores (session 73's hunt). Returns ``(read(*args), identity)``."""
    before = weights_identity(run_dir, weights_file)
    value = read(*args)
    after = weights_identity(run_dir, weights_file)
    if after != before:
        raise InputError(f"{run_dir}: its weights changed while they were read (a training writing the run now?); "
                         "use it when that training has stopped, or a copy of the run")
    return value, after


def weights_text(kept: dict | None) -> str:
    """The sentence saying which checkpoint was scored (:func:`kept_checkpoint`), or "" when unknown."""
    if kept is None:
        return ""
    if kept["checkpoint"] == "last":
        return f"Weights: the last step's ({kept['step']}), no checkpoint selection."
    if kept["step"] == kept["last_step"]:
        return (f"Weights: the best validation's, which is the last step ({kept['step']}): the selection on these "
                "scenes changed nothing.")
    return (f"Weights: the best validation's (step {kept['step']} of {kept['last_step']}), selected on patches of "
            "these scenes (train.keep_weights: best), so these figures are mildly optimistic.")


def root_weights_path(run_dir: str | Path, weights_file: str = "model.safetensors") -> Path:
    """The weights file that holds the weights a run keeps (:func:`kept_entry`).

    The root file when it matches the manifest (or the run has no manifest); else — a process was
    killed between the manifest's commit and the root file's rewrite — the checkpoint the manifest
    names, so the kept weights are never taken from another checkpoint (that checkpoint missing too:
    one :class:`InputError`)."""
    run_dir = Path(run_dir)
    root = run_dir / weights_file
    mgr = CheckpointManager(run_dir, weights_file)
    src = mgr.root_source()
    if src is None:
        return root
    path, sha = src
    if not path.is_file():
        if sha is not None and root.is_file() and file_sha256(root) != sha:  # no checkpoint to fall back on
            raise InputError(f"{root} differs from the weights {run_dir / MANIFEST} records (sha256 {sha[:12]}…), and "
                             f"{path}, which holds them, is missing: the run's weights are out of date or damaged (a "
                             f"process killed while it wrote them, a copy cut short); {RECOPY_HINT}")
        return root
    if root.is_file() and file_sha256(root) == (sha or file_sha256(path)):
        return root
    if sha is not None and file_sha256(path) != sha:
        if not root.is_file():
            raise InputError(f"{root} is missing, and {path}, which should hold the weights {run_dir / MANIFEST} "
                             f"records (sha256 {sha[:12]}…), differs from them: the run's weights are damaged (a copy "
                             f"cut short, a disk error, an edit); {RECOPY_HINT}")
        raise InputError(f"{root} and {path} both differ from the weights {run_dir / MANIFEST} records (sha256 "
                         f"{sha[:12]}…): the run's weights are damaged (a copy cut short, a disk error, an edit); "
                         f"{RECOPY_HINT}")
    if (root, path) not in _FALLBACKS_SAID:  # readers ask more than once per command: one line
        _FALLBACKS_SAID.add((root, path))
        log.info("%s does not hold the weights %s records (out of date, or damaged); using %s, which does",
                 root, MANIFEST, path)
    return path


_FALLBACKS_SAID: set[tuple[Path, Path]] = set()  # the (root, checkpoint) pairs root_weights_path has said it falls back for
