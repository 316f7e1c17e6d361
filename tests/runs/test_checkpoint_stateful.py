"""Stateful property test (hypothesis RuleBasedStateMachine) of a run folder's checkpoints.

Rules are what a training's life does to a run folder: a checkpoint at the next step (random small
weights and optimizer state, a validation score that is sometimes the best), the same step saved
again (the epoch-end save after a periodic one), a save interrupted inside its writes (an OSError,
a KeyboardInterrupt or another exception after k low-level writes), damage to one file of a
checkpoint or to the root weights (deleted, truncated, one byte flipped: a user or a disk), a resume
(a new process: a new CheckpointManager under the run lock, its cleanup and root sync) and the
loads of the last and best checkpoints. A small model of what should be there is checked after
every rule (see the invariants)."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
import torch
from hypothesis import Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from hsicam import io as hio
from hsicam.errors import InputError
from hsicam.runs import checkpoint as ck
from hsicam.runs.checkpoint import MANIFEST, CheckpointManager, read_weights, root_weights_path
from hsicam.runs.lock import LOCK_FILE, RunLock
from hsicam.spectral import Bands
from hsicam.io import _HASHES as hashes_read  # the file hashes read in this process

BANDS = Bands.uniform(500, 600, 50)
FILES = ("model.safetensors", "optimizer.safetensors", "state.json")


def _net(seed: int) -> tuple[torch.nn.Module, torch.optim.Optimizer]:
    """A tiny network and its Adam state, both drawn from ``seed`` (one optimizer step on random gradients)."""
    g = torch.Generator().manual_seed(seed)
    net = torch.nn.Linear(2, 3)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for p in net.parameters():
        p.grad = torch.randn(p.shape, generator=g)
    opt.step()
    with torch.no_grad():  # the weights saved are these (the step moved them)
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g))
    return net, opt


def _opt_tensors(opt: torch.optim.Optimizer) -> dict[str, torch.Tensor]:
    return {f"{i}.{k}": v.clone() for i, s in opt.state_dict()["state"].items() for k, v in s.items()}


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def _step(d: str) -> int:
    return int(Path(d).name.removeprefix("step-"))


class Interrupt:
    """Patches the low-level writers so that the ``k``-th call (0-based) raises ``exc``; records whether the
    manifest's temporary was synced (so renamed into place: the checkpoint committed) before the fault."""

    def __init__(self, mp: pytest.MonkeyPatch, k: int, exc: BaseException) -> None:
        self.k, self.exc, self.calls, self.committed, self.fired = k, exc, 0, False, False
        for mod, name in ((ck, "_write_safetensors"), (ck, "_sort_metadata"), (hio, "_fsync_file"), (hio, "_fsync_dir")):
            mp.setattr(mod, name, self._wrap(getattr(mod, name), name))

    def _wrap(self, fn, name):
        def wrapped(*args, **kwargs):
            # _fsync_dir swallows its OSErrors: only another exception (a KeyboardInterrupt) can come from there
            if not (name == "_fsync_dir" and isinstance(self.exc, OSError)) and not self.fired:
                if self.calls == self.k:
                    self.fired = True
                    raise self.exc
                self.calls += 1
            out = fn(*args, **kwargs)
            if name == "_fsync_file" and Path(args[0]).name.startswith("." + Path(MANIFEST).stem + "."):
                self.committed = True  # os.replace follows at once, and nothing is patched there
            return out
        return wrapped


class RunFolderMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.run = Path(tempfile.mkdtemp(prefix="hsicam-stateful-")) / "run"
        self.run.mkdir()
        self.keep = "best"
        self.mgr = CheckpointManager(self.run, keep=self.keep)
        self.saved: dict[int, dict] = {}  # step -> {"w", "opt", "seed"}: what each committed save wrote
        self.states: dict[int, dict] = {}  # step -> the training state committed with it
        self.last: int | None = None
        self.best: int | None = None
        self.best_psnr: float | None = None
        self.damaged: set[tuple[str, str]] = set()  # (folder name relative to the run, file name)
        self.dirty = False  # an interrupted save may leave an unnamed step folder until the next save / cleanup
        self.hashes_cleared = 0

    def teardown(self) -> None:
        shutil.rmtree(self.run.parent, ignore_errors=True)

    @initialize(keep=st.sampled_from(["best", "last"]))
    def choose_keep(self, keep):
        self.keep = keep
        self.mgr = CheckpointManager(self.run, keep=keep)

    # -- helpers ----------------------------------------------------------------------------------
    def _tags_state(self, step: int, score: float | None) -> tuple[tuple[str, ...], dict, float | None]:
        tags, best_psnr = ("last",), self.best_psnr
        if score is not None and (best_psnr is None or score > best_psnr):  # the loop's rule (engine/loop.py)
            tags, best_psnr = ("last", "best"), score
        return tags, {"global_step": step, "epoch": step, "best_psnr": best_psnr, "score": score}, best_psnr

    def _commit(self, step: int, seed: int, net, opt, state: dict, tags, best_psnr) -> None:
        if step not in self.saved or self.last != step:  # a new folder (a same-step save keeps the old weights)
            self.saved[step] = {"w": {k: v.clone() for k, v in net.state_dict().items()}, "opt": _opt_tensors(opt),
                                "state": dict(state)}  # its state.json: a same-step save does not rewrite it
            self.damaged = {d for d in self.damaged if d[0] != f"checkpoints/step-{step:08d}"}
        self.states[step] = dict(state)
        self.last = step
        if "best" in tags:
            self.best, self.best_psnr = step, best_psnr

    def _kept(self) -> int:
        return self.best if self.keep == "best" and self.best is not None else self.last

    def _dir(self, step: int) -> str:
        return f"checkpoints/step-{step:08d}"

    # -- rules --------------------------------------------------------------------------------------
    @rule(seed=st.integers(0, 2**16), score=st.none() | st.sampled_from([20.0, 21.5, 23.0, 23.0, 25.0]))
    def save(self, seed, score):
        step = (self.last or 0) + 1
        net, opt = _net(seed)
        tags, state, best_psnr = self._tags_state(step, score)
        self._save_expecting_damage(step, seed, net, opt, state, tags, best_psnr)

    def _save_expecting_damage(self, step, seed, net, opt, state, tags, best_psnr) -> None:
        """A save commits; the root weights then follow the kept checkpoint, which a damage may have removed:
        one line naming its missing weights file (committed, the unnamed folders not yet pruned)."""
        try:
            self.mgr.save(net, opt, state, BANDS, tags)
            raised = None
        except InputError as exc:
            raised = exc
        self._saved_or_refused(raised, step, seed, net, opt, state, tags, best_psnr)

    def _saved_or_refused(self, exc, step, seed, net, opt, state, tags, best_psnr) -> None:
        if exc is not None:
            assert isinstance(exc, InputError), repr(exc)
            self._commit(step, seed, net, opt, state, tags, best_psnr)
            kept = self.run / self._dir(self._kept()) / "model.safetensors"
            assert (self._dir(self._kept()), "model.safetensors") in self.damaged and not kept.exists(), str(exc)
            assert str(exc).startswith(f"{kept}: the checkpoint named by"), str(exc)
            self.dirty = True
            return
        self._commit(step, seed, net, opt, state, tags, best_psnr)
        self.dirty = False

    # (right after the periodic save, in the same process: its folder as that save left it)
    @precondition(lambda self: self.last is not None and not any(d == self._dir(self.last) for d, _ in self.damaged))
    @rule(score=st.none() | st.sampled_from([20.0, 24.0, 26.0]))
    def save_same_step(self, score):
        """The epoch-end save after a periodic one at the same step: same weights, the state moves on."""
        step = self.last
        net, opt = torch.nn.Linear(2, 3), None
        net.load_state_dict(self.saved[step]["w"])
        opt = torch.optim.Adam(net.parameters())
        tags, state, best_psnr = self._tags_state(step, score)
        self._save_expecting_damage(step, -1, net, opt, state, tags, best_psnr)

    @rule(seed=st.integers(0, 2**16), score=st.none() | st.sampled_from([20.0, 23.0, 25.0]), k=st.integers(0, 15),
          kind=st.sampled_from(["oserror", "interrupt", "runtime"]))
    def interrupted_save(self, seed, score, k, kind):
        step = (self.last or 0) + 1
        net, opt = _net(seed)
        tags, state, best_psnr = self._tags_state(step, score)
        exc = {"oserror": OSError(errno.ENOSPC, "No space left on device"), "interrupt": KeyboardInterrupt(),
               "runtime": RuntimeError("injected")}[kind]
        with pytest.MonkeyPatch.context() as mp:
            fault = Interrupt(mp, k, exc)
            try:
                self.mgr.save(net, opt, state, BANDS, tags)
                raised = None
            except BaseException as e:  # noqa: BLE001 — what reaches the user is checked below
                raised = e
        if not fault.fired:
            self._saved_or_refused(raised, step, seed, net, opt, state, tags, best_psnr)
            return
        if kind == "oserror":  # one line naming the file and what the run keeps
            assert isinstance(raised, InputError), repr(raised)
            msg = str(raised)
            assert "\n" not in msg and msg.startswith(str(self.run)), msg
            said = "was committed, but" in msg
            assert said == fault.committed and ("nothing was committed" in msg) != said, (msg, fault.committed)
        else:
            assert raised is exc, repr(raised)
        if fault.committed:
            self._commit(step, seed, net, opt, state, tags, best_psnr)
        self.dirty = True

    @rule(data=st.data(), how=st.sampled_from(["delete", "truncate", "flip"]))
    def damage(self, data, how):
        """One file of a named checkpoint, or the root weights, damaged as a user or a disk would."""
        man = self.mgr.manifest()
        if man is None:
            return
        dirs = sorted({e["dir"] for e in (man["last"], man.get("best")) if e})
        choices = [(d, f) for d in dirs for f in FILES if (self.run / d / f).is_file() and (self.run / d / f).stat().st_size]
        if (self.run / "model.safetensors").is_file() and (self.run / "model.safetensors").stat().st_size:
            choices.append((".", "model.safetensors"))
        if not choices:
            return
        d, f = data.draw(st.sampled_from(choices))
        path = self.run / d / f
        raw = path.read_bytes()
        if how == "delete":
            path.unlink()
        elif how == "truncate":
            path.write_bytes(raw[: data.draw(st.integers(0, len(raw) - 1))])
        else:
            lo = 0
            if f.endswith(".safetensors") and data.draw(st.booleans()):  # in the tensors' bytes, past the header
                lo = min(8 + int.from_bytes(raw[:8], "little"), len(raw) - 1)
            i = data.draw(st.integers(lo, len(raw) - 1))
            path.write_bytes(raw[:i] + bytes([raw[i] ^ 0x01]) + raw[i + 1:])
            st_ = path.stat()
            os.utime(path, ns=(st_.st_atime_ns, st_.st_mtime_ns + 1_000_000_000))  # later than its write
        self.damaged.add((d, f))

    @rule()
    def resume(self):
        """A new process: the cached hashes are gone; the loop's resume (lock, cleanup, root sync)."""
        hashes_read.clear()
        self.mgr = CheckpointManager(self.run, keep=self.keep)
        with RunLock(self.run) as lock:
            lock.acquire()
            self.mgr.cleanup()
            try:
                self.mgr.sync_root()
            except InputError as exc:
                kept = self._dir(self._kept())
                assert (kept, "model.safetensors") in self.damaged, str(exc)
                assert str(exc).startswith(str(self.run / kept / "model.safetensors")), str(exc)
        assert not (self.run / LOCK_FILE).exists()
        self.dirty = False

    @precondition(lambda self: self.last is not None)
    @rule(tag=st.sampled_from(["last", "best"]))
    def load(self, tag):
        step = self.last if tag == "last" else self.best
        net = torch.nn.Linear(2, 3)
        opt = torch.optim.Adam(net.parameters(), lr=1e-3)
        try:
            state = self.mgr.load(tag, net, opt, BANDS)
        except InputError as exc:
            msg = str(exc)
            assert "\n" not in msg, msg
            if step is None:
                assert msg == f"{self.run}: no '{tag}' checkpoint to resume from"
                return
            named = [f for (d, f) in self.damaged if d == self._dir(step)]
            assert named, f"refused an undamaged checkpoint: {msg}"
            assert any(msg.startswith(str(self.run / self._dir(step) / f)) for f in named), (msg, named)
            return
        assert step is not None, "loaded a best checkpoint that was never saved"
        assert _same(net.state_dict(), self.saved[step]["w"]), f"wrong weights loaded for step {step}"
        if self.saved[step]["opt"] and any(True for _ in opt.state_dict()["state"]):
            assert _same(_opt_tensors(opt), self.saved[step]["opt"]), f"wrong optimizer state loaded for step {step}"
        want = self.states[self.last] if tag == "last" else self.saved[step]["state"]
        # state.json is informational (nothing reads load("best")'s state) and carries no hash: a flipped byte there
        # comes back as it is (noted in the report, not fixed)
        assert state == want or (tag == "best" and (self._dir(step), "state.json") in self.damaged), (state, want)

    # -- invariants ---------------------------------------------------------------------------------
    @invariant()
    def manifest_matches_the_model(self):
        man = self.mgr.manifest()
        if self.last is None:
            assert man is None
            return
        assert man["last"]["step"] == self.last and man["last"]["dir"] == self._dir(self.last)
        assert man["state"] == self.states[self.last]
        if self.best is None:
            assert man["best"] is None
        else:
            assert man["best"]["step"] == self.best and man["best"]["psnr"] == self.best_psnr
        kept = self._kept()
        assert man["weights"]["dir"] == self._dir(kept), (man["weights"], kept)

    @invariant()
    def named_folders_exist_and_are_complete(self):
        man = self.mgr.manifest()
        if man is None:
            return
        for e in (man["last"], man.get("best")):
            if not e:
                continue
            d = self.run / e["dir"]
            assert d.is_dir(), f"the manifest names a missing folder {e['dir']}"
            for f in FILES:
                if (e["dir"], f) not in self.damaged:
                    assert (d / f).is_file(), f"{e['dir']}/{f} missing"
            if (e["dir"], "model.safetensors") not in self.damaged:
                assert ck.file_sha256(d / "model.safetensors") == e["weights_sha256"]

    @invariant()
    def kept_folders_and_no_temporaries(self):
        ckdir = self.run / "checkpoints"
        on_disk = {p.name for p in ckdir.iterdir()} if ckdir.is_dir() else set()
        temps = [str(p) for p in self.run.rglob("*") if hio.is_temporary(p.name)]
        assert not temps, temps
        named = set() if self.last is None else {Path(self._dir(s)).name for s in (self.last, self.best) if s}
        assert named <= on_disk
        if not self.dirty:
            assert on_disk == named, (on_disk, named)  # the keep settings: the last and the best, no more
        assert not (self.run / LOCK_FILE).exists()

    @invariant()
    def root_weights_are_the_kept_ones(self):
        if self.last is None:
            return
        kept = self._kept()
        try:
            path = root_weights_path(self.run)
            tensors, _ = read_weights(path)
        except InputError as exc:
            assert any(d in (self._dir(kept), ".") and f == "model.safetensors" for d, f in self.damaged), str(exc)
            return
        if not _same(tensors, self.saved[kept]["w"]):
            assert ((self._dir(kept), "model.safetensors") in self.damaged
                    and (".", "model.safetensors") in self.damaged), f"{path} holds other weights than step {kept}'s"


# ~40 sequences of 20 rules in about 20 s; STATEFUL_EXAMPLES=400 explores further, NO_SHRINK=1 reports unshrunk
RunFolderMachine.TestCase.settings = settings(
    max_examples=int(os.environ.get("STATEFUL_EXAMPLES", 40)), stateful_step_count=20, deadline=None, derandomize=True,
    database=None, **({"phases": [Phase.explicit, Phase.generate]} if os.environ.get("NO_SHRINK") else {}))
test_run_folder_checkpoints = RunFolderMachine.TestCase


# ------------------------------------------------------------------------------------------------
# The minimal sequences the machine found, as plain regression tests
# ------------------------------------------------------------------------------------------------
def _saved_run(tmp_path: Path) -> tuple[Path, CheckpointManager, torch.nn.Module, torch.optim.Optimizer]:
    run = tmp_path / "run"
    net, opt = _net(7)
    mgr = CheckpointManager(run)
    mgr.save(net, opt, {"global_step": 1, "best_psnr": None}, BANDS)
    return run, mgr, net, opt


def test_loading_a_checkpoint_whose_weights_file_was_deleted_is_one_line(tmp_path):
    """save; delete the checkpoint's model.safetensors; load last: was a raw FileNotFoundError from the hash check."""
    run, mgr, _, _ = _saved_run(tmp_path)
    weights = run / "checkpoints" / "step-00000001" / "model.safetensors"
    weights.unlink()
    with pytest.raises(InputError) as err:
        mgr.load("last", torch.nn.Linear(2, 3), None, BANDS)
    assert str(err.value) == (f"{weights}: missing from the 'last' checkpoint that {run / MANIFEST} names (the run "
                              f"folder is incomplete); {ck.RECOPY_HINT}")


def test_loading_a_checkpoint_whose_optimizer_state_has_a_flipped_byte_is_refused(tmp_path):
    """save; flip one byte of the tensor data of optimizer.safetensors (a disk error); load last with the optimizer:
    its Adam moments came back silently wrong (exp_avg_sq 0.0019 -> 6.4e35), as the weights never do."""
    run, mgr, _, opt = _saved_run(tmp_path)
    path = run / "checkpoints" / "step-00000001" / "optimizer.safetensors"
    raw = bytearray(path.read_bytes())
    sha = hashlib.sha256(raw).hexdigest()  # what the save wrote
    header = json.loads(raw[8:8 + int.from_bytes(raw[:8], "little")])
    raw[8 + int.from_bytes(raw[:8], "little") + header["1.exp_avg_sq"]["data_offsets"][0] + 3] ^= 0x40
    path.write_bytes(bytes(raw))
    net2 = torch.nn.Linear(2, 3)
    opt2 = torch.optim.Adam(net2.parameters(), lr=1e-3)
    with pytest.raises(InputError) as err:
        mgr.load("last", net2, opt2, BANDS)
    assert str(err.value) == (f"{path} differs from the optimizer state {run / MANIFEST} records (sha256 {sha[:12]}…): "
                              f"the checkpoint is damaged (a copy cut short, a disk error, an edit); {ck.RECOPY_HINT}")
    assert not opt2.state  # nothing loaded from it


def test_a_stale_root_is_not_handed_out_when_the_kept_checkpoint_is_missing(tmp_path, monkeypatch):
    """keep last; save step 1; save step 2 interrupted (KeyboardInterrupt) right after its manifest's rename, before
    the root weights' rewrite; the step-2 weights file deleted (a copy without checkpoints/): root_weights_path handed
    out the root file, which holds step 1's weights, for the run's kept step 2."""
    run = tmp_path / "run"
    mgr = CheckpointManager(run, keep="last")
    net1, opt1 = _net(1)
    mgr.save(net1, opt1, {"global_step": 1}, BANDS)
    net2, opt2 = _net(2)
    with pytest.MonkeyPatch.context() as mp:
        fault = Interrupt(mp, 11, KeyboardInterrupt())  # 11: the manifest's folder sync, after its rename
        with pytest.raises(KeyboardInterrupt):
            mgr.save(net2, opt2, {"global_step": 2}, BANDS)
    assert fault.committed and json.loads((run / MANIFEST).read_text())["weights"]["dir"] == "checkpoints/step-00000002"
    assert _same(read_weights(run / "model.safetensors")[0], net1.state_dict())  # the root: still step 1's
    kept = run / "checkpoints" / "step-00000002" / "model.safetensors"
    sha = hashlib.sha256(kept.read_bytes()).hexdigest()
    kept.unlink()
    with pytest.raises(InputError) as err:
        root_weights_path(run)
    assert str(err.value) == (f"{run / 'model.safetensors'} differs from the weights {run / MANIFEST} records (sha256 "
                              f"{sha[:12]}…), and {kept}, which holds them, is missing: the run's weights are out of "
                              f"date or damaged (a process killed while it wrote them, a copy cut short); {ck.RECOPY_HINT}")
