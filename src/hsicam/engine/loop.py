"""The one training loop: :func:`fit` trains any :class:`Task` (joint camera + network training,
fine-tuning to measured PSFs, the Choi spectral prior).

The loop owns everything that is not the task's business: device and DDP, the sampler, the
learning-rate schedule, gradient clipping, the metrics log and progress, the validation cadence,
checkpoints and resume. A task supplies its modules, parameter groups, data, the per-step noise,
the loss of a batch and the validation metrics; it never writes a checkpoint.

Determinism and resume: patches depend only on (seeds, epoch, index), the random numbers of step n
only on (seed, n, rank), and the learning rate only on the global step, so a run resumed from its
last checkpoint continues exactly the same schedule (the :class:`LoopState`, including the
running train loss of the current epoch, is part of every checkpoint).

Distributed: launched by ``torchrun``, each process takes its share of every global batch
(``batch_size`` must divide by the number of processes); DDP averages the gradients; validation,
logging and checkpoints happen on rank 0 only; an error there ends every rank at the next collective, rank 0's
with its own error, the others' in one line (:class:`SoloWork`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn

import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import Sampler

from hsicam.config import TrainConfig
from hsicam.data.pipeline import make_loader, patch_source
from hsicam.devices import autocast_problem, device_problem, dist_env
from hsicam.engine.provenance import (check_same_data, read_data_record, resumed_config_changes,
                                      session_60_changes_had, software_record, started_before_session_60,
                                      write_data_record)
from hsicam.engine.stopping import BUDGET_EXIT_CODE, StopRequests
from hsicam.errors import ConfigError, InputError, PeerFailed, TrainingDiverged, TrainingInterrupted, TrainingStopped
from hsicam.io import OutputLock, atomic_output, is_complete, output_description
from hsicam.runs.camera_files import write_camera_files
from hsicam.runs.checkpoint import CheckpointManager, save_weights
from hsicam.runs.folder import MetricsLog, check_run_dir
from hsicam.runs.lock import RunLock, check_not_locked
from hsicam.spectral import Bands

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------
# Loop state, schedule, random numbers
# ------------------------------------------------------------------------------------------------
@dataclass
class LoopState:
    """Where the loop stands; saved with every checkpoint (``state.json``) and restored on resume."""

    epoch: int = 0  # epochs completed
    step_in_epoch: int = 0  # steps completed in the current epoch
    global_step: int = 0
    best_psnr: float | None = None  # best validation score so far (the task's ``score``)
    best_step: int | None = None
    loss_sum: float = 0.0  # running train loss of the current epoch (so a mid-epoch resume continues it)
    loss_n: int = 0
    total_steps: int = 0  # the run's planned steps (epochs × steps per epoch, capped by max_steps); 0 = unknown
    steps_per_epoch: int = 0  # the unit of step_in_epoch and global_step (0: a checkpoint from before it was kept)
    batch_size: int = 0

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LoopState":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


def older_epoch_length(state: LoopState) -> int | None:
    """The steps per epoch of a checkpoint saved before :class:`LoopState` kept them (None: a newer one, or
    one whose length cannot be told: no completed epoch, or epochs of unequal lengths)."""
    done = state.global_step - state.step_in_epoch  # the steps of its completed epochs
    if state.steps_per_epoch or state.epoch < 1 or done <= 0 or done % state.epoch:
        return None
    return done // state.epoch


class ShardedBatches(Sampler[int]):
    """Indices of this rank's share of global batches ``start_batch..n_batches-1``.

    Global batch b holds items b·B … b·B + B − 1; rank r takes the r-th contiguous slice.
    """

    def __init__(self, n_batches: int, global_batch: int, rank: int = 0, world: int = 1, start_batch: int = 0) -> None:
        self.n_batches, self.global_batch, self.rank, self.world = n_batches, global_batch, rank, world
        self.per_rank = global_batch // world
        self.start_batch = start_batch

    def __iter__(self) -> Iterator[int]:
        for b in range(self.start_batch, self.n_batches):
            base = b * self.global_batch + self.rank * self.per_rank
            yield from range(base, base + self.per_rank)

    def __len__(self) -> int:
        return (self.n_batches - self.start_batch) * self.per_rank


def lr_factor(t: TrainConfig, step: int, total_steps: int, steps_per_epoch: int) -> float:
    """Learning-rate multiplier at global ``step`` (warm-up, then the schedule of ``t``).

    The warm-up climbs (s + 1)/W to 1 at its last step W − 1; the cosine then runs over the remaining
    T − W steps, ½(1 + cos(π (s − W)/(T − W))): 1 at step W, so the rate does not drop where the warm-up
    ends (without a warm-up, ½(1 + cos(π s/T)))."""
    w = t.warmup_steps
    if w and step < w:
        return (step + 1) / w
    if t.lr_schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * min((step - w) / max(total_steps - w, 1), 1.0)))
    if t.lr_schedule == "step":
        return t.lr_gamma ** ((step // steps_per_epoch) // t.lr_step_epochs)
    return 1.0


def older_run_changes(t: TrainConfig, step: int, total_steps: int, seed_key: str = "train.seed",
                      noisy_validation: bool = False, had: frozenset[str] = frozenset()) -> list[str]:
    """What this hsicam trains otherwise, from ``step`` on, than an hsicam before session 60 that started the run
    (:func:`hsicam.engine.provenance.started_before_session_60`): the cosine after a warm-up (c5559eb: over the
    remaining steps, not ½(1 + cos(π s/T))), the patch stream of a seed other than 0 (``seed_key``; that hsicam
    drew seed 0's) and, where the validation draws noise, its seed (0, not ``train.seed``). [] when the run's
    settings meet none of them (no warm-up or another schedule, seed 0). ``had``: those the hsicam that started the
    run trained with already (a commit of session 60 before c1ab911,
    :data:`hsicam.engine.provenance.SESSION_60_COMMITS`), left out."""
    changes = []
    w = t.warmup_steps
    s = max(step, w)  # the first step after the warm-up that the resume trains
    if t.lr_schedule == "cosine" and w and s < total_steps and "cosine" not in had:
        old = 0.5 * (1.0 + math.cos(math.pi * min(s / max(total_steps, 1), 1.0)))
        changes.append(f"the cosine after the {w}-step warm-up runs over the remaining {total_steps - w} steps "
                       f"(step {s}: {lr_factor(t, s, total_steps, 1):.4g} x the base rate, where that hsicam "
                       f"gives {old:.4g})")
    if t.seed != 0 and ("seed" if seed_key == "train.seed" else "choi_seed") not in had:
        changes.append(f"the training patches come from {seed_key}={t.seed}'s own stream (that hsicam drew seed 0's)")
    if t.seed != 0 and noisy_validation and "validation_noise" not in had:
        changes.append(f"the validation noise is drawn from seed 0 (that hsicam drew it from train.seed={t.seed})")
    return changes


def step_generator(seed: int, step: int, rank: int, device: torch.device | str) -> torch.Generator:
    """The random numbers of one training step: a generator seeded from (seed, step, rank)."""
    g = torch.Generator(device=device)
    g.manual_seed((seed * 1_000_003 + step * 7919 + rank * 104_729) % (2**63 - 1))
    return g


def draw_uniform(lo_hi: list[float] | tuple[float, float], g: torch.Generator) -> float:
    """A value uniform in [lo, hi] from ``g`` (``lo`` when the range is empty)."""
    lo, hi = lo_hi
    if hi <= lo:
        return lo
    return lo + (hi - lo) * float(torch.rand((), generator=g, device=g.device))


def resolve_device(spec: str, local_rank: int = 0) -> torch.device:
    """``auto`` → this rank's CUDA device when there is one, else the CPU; else ``spec``
    (:class:`InputError` for a device this machine lacks, :func:`device_problem`)."""
    if spec == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    problem = device_problem(spec)
    if problem is not None:
        raise InputError(f"train.device={spec}: {problem}")
    device = torch.device(spec)
    if device.type == "cuda" and device.index is None:  # under torchrun each rank its own GPU, as `auto` does
        return torch.device(f"cuda:{local_rank}")
    return device


# ------------------------------------------------------------------------------------------------
# The task interface
# ------------------------------------------------------------------------------------------------
class Task:
    """What :func:`fit` trains. Subclasses override the hooks they need.

    Attributes:
        bands: band grid stored with the weights.
        weights_file: name of the root weights file in the run folder.
        what: a word for log and error messages ("training", "fine-tuning", ...).
    """

    bands: Bands
    weights_file: str = "model.safetensors"
    what: str = "training"
    batch_size_key: str = "train.batch_size"  # the config key of the batch size, for error messages
    seed_key: str = "train.seed"  # the config key of the loop's seed (its patch stream), for messages
    # True when some steps leave trainable parameters without a gradient (DDP must then look for them)
    find_unused_parameters: bool = False

    def module(self) -> nn.Module:
        """Everything the checkpoints hold (network and optics)."""
        raise NotImplementedError

    def param_groups(self) -> list[dict[str, Any]]:
        """Optimizer groups ``{"name", "params", "lr"}`` (base learning rates)."""
        raise NotImplementedError

    def write_run_files(self, run_dir: Path) -> None:
        """Files written into a new run folder (e.g. ``config.yaml``) before training, and again on
        resume (the config it goes on with)."""

    def data_record(self) -> dict[str, Any] | None:
        """What ``RUN/data.json`` records of the task's scenes (:mod:`hsicam.engine.provenance`);
        None: nothing (e.g. the synthetic data)."""
        return None

    def camera_record(self) -> dict[str, Any] | None:
        """What ``RUN/camera_files.json`` records of the files the task's camera is built from
        (:mod:`hsicam.runs.camera_files`); None: nothing (none, or no camera)."""
        return None

    def synthetic_set(self) -> dict[str, Any] | None:
        """Which cached synthetic set the task reads, for each session record
        (:func:`hsicam.engine.provenance.synthetic_set_record`); None: none (e.g. a ``data.root`` folder)."""
        return None

    def resume_warning(self, run_dir: Path) -> str | None:
        """What a resume of ``run_dir`` should be warned of about the task's data (e.g. synthetic scenes of another
        generator version than the run started on: :func:`hsicam.engine.provenance.generator_change_warning`)."""
        return None

    def noisy_validation(self) -> bool:
        """Whether the validation draws noise (whose seed session 60 changed: :func:`older_run_changes`)."""
        return False

    def on_device(self, device: torch.device) -> None:
        """Called once the module is on ``device`` (memory format, ``torch.compile``, autocast)."""

    def prepare_data(self) -> None:
        """Generate or cache data (rank 0 runs it before the other ranks read it)."""

    def datasets(self):
        """(training dataset, validation dataset or None); items are batches' elements."""
        raise NotImplementedError

    def on_step_start(self, step: int, generator: torch.Generator) -> None:
        """Per-step settings drawn from the step's generator (e.g. noise levels)."""

    def training_step(self, trainable: nn.Module, batch: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """The loss of one batch (``trainable`` is the module, DDP-wrapped when distributed)."""
        raise NotImplementedError

    def validate(self, loader, device: torch.device) -> dict[str, float]:
        """Validation metrics (higher ``psnr`` is better: it selects the best weights)."""
        raise NotImplementedError

    def weights_metadata(self) -> dict[str, str]:
        """Extra safetensors metadata for the weights files."""
        return {}

    def on_fit_end(self, run_dir: Path, summary: dict[str, Any]) -> dict[str, Any]:
        """Files written last (they mark the run finished); returns the summary to report."""
        return summary


@dataclass
class FitOptions:
    """What :func:`fit` needs beyond the task.

    ``loop`` supplies epochs, batch size, learning-rate schedule, clipping, the logging, validation
    and checkpoint cadence, seed and device. ``max_steps`` ends training early (the spectral prior
    counts steps, not epochs); ``validate_at_start`` scores the starting weights (fine-tuning)."""

    loop: TrainConfig
    num_workers: int = 2
    max_steps: int | None = None
    validate_at_start: bool = False
    progress: bool | None = None
    stop_after_steps: int | None = None  # simulate an interruption (tests)


# ------------------------------------------------------------------------------------------------
# The loop
# ------------------------------------------------------------------------------------------------
def _clear_traceback_frames(exc: BaseException | None) -> None:
    """Clear the locals of the frames of ``exc``'s traceback and of the errors it was raised from or
    during (``__cause__``, ``__context__``: a frame such as the training step's, holding the DDP wrapper,
    may be reachable only through them); executing frames are left alone (:func:`traceback.clear_frames`)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        traceback.clear_frames(exc.__traceback__)
        exc = exc.__cause__ or exc.__context__


def fit(task: Task, opts: FitOptions, run_dir: str | Path, resume: bool = False,
        then: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Train (or resume) ``task`` into ``run_dir``; returns the final summary (also the last line of
    ``metrics.jsonl``), or ``{"stopped_at_step": n}`` when ``opts.stop_after_steps`` cut it short.
    Resuming a finished run (nothing left of ``epochs`` / ``max_steps``) writes nothing and returns
    its final record with ``"already_finished": True``.

    Under torchrun (WORLD_SIZE > 1) it joins the process group, or creates it and then destroys it
    when training ends: a gloo group left to the interpreter's exit can abort the process
    ("terminate called without an active exception", pytorch/pytorch#190489). After an error it is
    destroyed too, without a barrier (a peer may still wait in a collective), the locals of the traceback's
    frames below ``fit`` are cleared (they hold the DDP wrapper, and through it the group), and the error
    propagates.

    Rank 0 holds the run folder's lock (:mod:`hsicam.runs.lock`) for as long as it writes into it,
    and lets go however it ends: another process training there is refused before anything is touched.
    A new run's folder is this process's from before its data are prepared until it is in place (its
    :class:`~hsicam.io.OutputLock`): another training into it is refused the same way meanwhile.
    ``then(summary) -> summary`` runs on rank 0 under that lock after a training that was not cut
    short (files derived from the final weights, e.g. the linear step's filters); an error of rank 0 there, as in
    all its work alone, ends the other ranks with :class:`~hsicam.errors.PeerFailed` (:class:`SoloWork`).

    SIGTERM, Ctrl-C and the budget ``train.max_minutes`` stop the loop at the end of a step: that
    step's checkpoint is saved and :class:`~hsicam.errors.TrainingStopped` (the budget) or
    :class:`~hsicam.errors.TrainingInterrupted` (a signal) raised, every rank at the same step, so a
    resume goes on exactly (:mod:`hsicam.engine.stopping`). A signal during the last step or the
    files written after it lets them finish, then raises ``TrainingInterrupted(finished=True)``, on every rank when it
    reached one alone (the training's last agreement carries it). An error of one rank in a training step (e.g. a
    scene file only it reads) ends the others, whose collective of that step then fails, with
    :class:`~hsicam.errors.PeerFailed` naming it (:func:`_tell_failure`), not gloo's traceback."""
    global _fit_calls
    _fit_calls += 1  # (this call's failed-rank key: _failed_rank_key)
    rank, world, local_rank = dist_env()
    if opts.loop.batch_size % world:  # before the group: one rank's error tore its half down while the other connected
        raise InputError(f"train.batch_size={opts.loop.batch_size} must be divisible by the {world} processes")
    own_group = world > 1 and not dist.is_initialized()
    if own_group:
        # before the group exists: torch._dynamo, which torch imports lazily later on (the optimizer's
        # add_param_group, use_deterministic_algorithms, torch.compile), takes references to a live process group as it is imported (10 with torch 2.13) that
        # destroy_process_group does not drop; the group then lived on to the interpreter's exit, where its gloo
        # threads aborted a finished rank now and then ("terminate called without an active exception", exit -6;
        # a torchrun resume in CI)
        import torch._dynamo  # noqa: F401
        device = resolve_device(opts.loop.device, local_rank)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    try:
        with RunLock(run_dir, enabled=rank == 0) as lock, OutputLock(run_dir, "train", enabled=rank == 0) as new_run, \
                StopRequests(opts.loop.max_minutes) as stop, deterministic_algorithms(opts.loop.deterministic):
            result = _fit(task, opts, Path(run_dir), resume, lock, new_run, stop)
            if "stopped_at_step" not in result:
                result = _finish_together(task, opts, run_dir, result, then, stop)
    except (TrainingStopped, TrainingInterrupted):  # every rank stopped at the same step (_agreed_stop): the group ends cleanly
        if own_group:
            _end_group(barrier=True)
        raise
    except BaseException as exc:
        _after_error(exc, run_dir, rank, world, own_group)
        raise
    if own_group:
        _end_group(barrier=True)
    return result


def _finish_together(task: Task, opts: FitOptions, run_dir: str | Path, result: dict[str, Any],
                     then: Callable[[dict[str, Any]], dict[str, Any]] | None, stop: StopRequests) -> dict[str, Any]:
    """After a training that was not cut short: rank 0's ``then(result)`` (its error ends the other ranks with
    :class:`~hsicam.errors.PeerFailed`, :class:`SoloWork`), then one agreement on whether a stop signal arrived
    since the last step began; the summary, or :class:`~hsicam.errors.TrainingInterrupted` ``(finished=True)``
    raised on every rank alike."""
    rank, world, local_rank = dist_env()
    solo = SoloWork(rank, world, resolve_device(opts.loop.device, local_rank))
    if then is not None:
        with solo.work():
            if rank == 0:
                result = then(result)
    # a signal during the last step or the files after it, which may have reached one rank alone: every
    # rank learns of it here (the signalled one exited 143 and the others 0), and all stop alike
    code = solo.reduce([stop.exit_code() if stop.received is not None else 0], f"at the end of the {task.what}")[0]
    if code and "step" in result:
        raise TrainingInterrupted(run_dir, result["step"], result["step"], stop.describe(code), code, finished=True)
    return result


def _after_error(exc: BaseException, run_dir: str | Path, rank: int, world: int, own_group: bool) -> None:
    """What :func:`fit` does for an error that ends the training, before it propagates: a divergence is told what
    the run folder keeps, the other ranks which rank failed (:func:`_tell_failure`), and the group :func:`fit`
    created is destroyed without a barrier."""
    if isinstance(exc, TrainingDiverged):  # what the run folder keeps: the CLI says how to go on from it
        exc.run_dir = Path(run_dir)
        try:
            exc.checkpoint_step = (CheckpointManager(run_dir).state() or {}).get("global_step")
        except Exception:  # noqa: BLE001 - a damaged manifest: the divergence is still the error to report
            exc.run_dir = None
    if world > 1 and not isinstance(exc, PeerFailed):  # this rank's own error: the others' step learns who failed
        _tell_failure(rank)
    # any other error: no barrier (the other ranks may be anywhere, or gone), but the group is destroyed all the
    # same, which only lets go of this process's side of it. Left alive, it lived on to the interpreter's exit
    # with its gloo threads, the one condition under which a finished rank was seen to abort ("terminate called
    # without an active exception", exit -6, instead of the error's own exit status; pytorch#190489). Caught
    # under gdb (docs/training_log.md): a pt_gloo_runloop thread drops the last reference to a finished work after
    # wait() has returned; ~AsyncAllreduceWork frees a Python-made tensor, take_gil during Py_FinalizeEx calls
    # pthread_exit, whose unwinding through that noexcept destructor is std::terminate. After a waited
    # all_reduce, 9 of 20 runs that left the group alive to the exit aborted, 0 of 20 that destroyed it.
    if own_group:
        # the traceback's frames below fit's hold the DDP wrapper, whose reducer holds the group: cleared (their
        # locals only; the traceback still prints), else the group and its threads lived as long as the error,
        # to the interpreter's exit when it is not caught (hsicam's CLI re-raises an unexpected one)
        _clear_traceback_frames(exc)
        try:
            _end_group(barrier=False)
        except Exception:  # noqa: BLE001 - never in place of the error that ended the training
            log.debug("destroy_process_group failed after an error", exc_info=True)


class SoloWork:
    """Work that one rank does alone between two collectives of a DDP group (rank 0's: the run folder's checks, the
    data, the metrics log, checkpoints, validation, the files that end a training, ``fit``'s ``then``; any rank's:
    reading its data and a resume's checkpoint), and the agreement after it, where every rank learns whether one of
    them failed.

    An error in such work used to end that rank's side of the group alone: the others, waiting in their next
    collective, died with gloo's 26-line traceback ("Connection closed by peer"), and NCCL's collectives wait for the
    group's timeout instead. In a group, :meth:`work` holds the error until the next agreement (:meth:`agree`, one
    collective where the loop had a barrier; :meth:`reduce`, one value more in a reduction made anyway, so that no
    step pays for another collective): the rank that failed raises its own error there, the others
    :class:`~hsicam.errors.PeerFailed` (one line each). A rank that holds an error does no more work alone before it
    (``held``). In one process an error is raised at once."""

    def __init__(self, rank: int, world: int, device: torch.device) -> None:
        self.rank, self.world, self.device = rank, world, device
        self.error: BaseException | None = None

    @property
    def held(self) -> bool:
        """Whether this rank failed in its work since the last agreement."""
        return self.error is not None

    @contextlib.contextmanager
    def work(self):
        """A block of this rank's own work: in a group, an error in it is held until the next agreement."""
        try:
            yield
        except BaseException as exc:
            if self.world == 1 or self.error is not None:
                raise
            self.error = exc

    def reduce(self, values: list[int], where: str) -> list[int]:
        """``values`` reduced to their maximum over the group, in one collective with whether a rank failed in its
        work: this rank's error raised when it holds one, else :class:`PeerFailed` when another rank failed
        (``where``: when, for its message, e.g. "at step 12 of the training")."""
        if self.world == 1:
            return values
        flags = torch.tensor([*values, self.rank + 1 if self.error is not None else 0], device=self.device)
        try:
            dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        except Exception:  # noqa: BLE001 - a peer gone: never in place of this rank's own error
            if self.error is None:
                raise
            log.debug("telling the other ranks that rank %d failed: they are gone", self.rank, exc_info=True)
        if self.error is not None:
            error, self.error = self.error, None
            raise error
        failed = int(flags[-1].item())
        if failed:
            raise PeerFailed(f"rank {failed - 1} failed {where} (its own error says why); rank {self.rank} stops "
                             "with it")
        return [int(v) for v in flags[:-1].tolist()]

    def agree(self, where: str) -> None:
        """Every rank learns whether one failed in its work (:meth:`reduce`, nothing else reduced)."""
        self.reduce([], where)


def _end_group(barrier: bool) -> None:
    """Destroy the process group :func:`fit` created, after a barrier when every rank ends here together: also
    when that barrier fails (a peer gone), so that the group never outlives the script (:func:`fit`)."""
    try:
        if barrier:
            dist.barrier()
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


#: The key of the group's store under which a rank that fails on its own leaves its number (:func:`_tell_failure`),
#: followed by the number of the :func:`fit` call (:func:`_failed_rank_key`).
_FAILED_RANK_KEY = "hsicam/failed_rank"
_fit_calls = 0  # fit calls in this process so far: every rank of a group calls fit alike, so the numbers match


def _failed_rank_key() -> str:
    """The store key of this :func:`fit` call's failed rank. One per call: a key left by an earlier fit in the same
    group (a script that made its own group and trains twice) named that fit's failed rank for a later fit's own
    error; a delete when fit starts would race a peer still telling the earlier failure."""
    return f"{_FAILED_RANK_KEY}/{_fit_calls}"


def _tell_failure(rank: int) -> None:
    """Leave this rank's number in the process group's store before its error ends its side of the group: the other
    ranks' training step, whose collective then fails, learns who failed (:func:`_failed_peer`) at no cost to a step
    that goes well."""
    try:
        store = dist.distributed_c10d._get_default_store()
        key = _failed_rank_key()
        store.set(key, str(rank))
        store.get(key)  # a round trip (a set is not answered): the store holds it before the group ends
    except Exception:  # noqa: BLE001 - never in place of the error that ended the training
        log.debug("could not tell the other ranks that rank %d failed", rank, exc_info=True)


def _failed_peer(rank: int) -> int | None:
    """The rank other than ``rank`` that failed on its own (:func:`_tell_failure`) before this rank's error surfaced,
    else None (this rank's error is its own, or a peer was killed outright)."""
    try:
        store = dist.distributed_c10d._get_default_store()
        key = _failed_rank_key()
        failed = int(store.get(key)) if store.check([key]) else None
    except Exception:  # noqa: BLE001 - no word from another rank: the collective's own error is the one to report
        return None
    return failed if failed != rank else None


def finished_record(run_dir: Path, epochs: int, total_steps: int, steps_per_epoch: int | None = None,
                    batch_size: int | None = None) -> dict[str, Any] | None:
    """The final ``metrics.jsonl`` record of a run with nothing left to train, else None.

    Finished: the last checkpoint has done ``epochs`` epochs (or ``total_steps`` steps) and the
    metrics log ends with the final record of that step. A config of other epochs (``steps_per_epoch``
    batches of ``batch_size``) than the run trained in is not judged here: its steps count other
    batches, and the resume refuses it naming both. Reads only."""
    state = CheckpointManager(run_dir).state()
    if state is None:
        return None
    last = LoopState.from_dict(state)
    if steps_per_epoch is not None:
        trained = ((last.steps_per_epoch, last.batch_size) if last.steps_per_epoch else
                   (older_epoch_length(last), batch_size))
        if trained[0] is not None and trained != (steps_per_epoch, batch_size):
            return None  # e.g. more epochs of a larger batch: "already finished, raise train.epochs" misled
    if last.epoch < epochs and last.global_step < total_steps:
        return None  # e.g. resumed with more epochs
    records = MetricsLog(run_dir / "metrics.jsonl", enabled=False).read()
    if not records or not records[-1].get("final") or records[-1].get("step") != last.global_step:
        return None  # killed before its final record: the resume writes it
    return records[-1]


def last_validation(records: list[dict[str, Any]]) -> dict[str, float]:
    """The metrics (``val_`` prefix removed) of the last validation record before any final one; {} when none."""
    for rec in reversed(records):
        if not rec.get("final") and any(k.startswith("val_") for k in rec):
            return {k[4:]: v for k, v in rec.items() if k.startswith("val_")}
    return {}


def check_not_an_output(run_dir: Path, action: str = "resume") -> None:
    """InputError when ``run_dir`` carries a completion marker: a run folder never does, so it is
    another command's output (``simulate``, ``evaluate`` …), which ``action`` ("resume", "restart"
    or "train") must not train in; and when another process is training in it (its lock: the
    commands call this first, before their checks remove a killed run's temporaries)."""
    check_not_locked(run_dir)
    if is_complete(run_dir):
        what = f"nothing to {action}" if action in ("resume", "restart") else "a run needs its own folder"
        raise InputError(f"{run_dir}: holds {output_description(run_dir)}, not a training run; {what} "
                         "(choose another --out)")


def not_finite_error(what: str, step: int, loss: float, batch: torch.Tensor,
                     source: Callable[[int], Any] = lambda j: None) -> InputError:
    """The error for a loss that is not finite at ``step``: the batch's data when it holds NaN/Inf
    values (naming up to 3 scene files, ``source(row)``), else a divergence (the learning rates)."""
    bad = ~torch.isfinite(batch.detach())
    if not bool(bad.any()):
        exc = TrainingDiverged(f"{what} diverged at step {step} (loss {loss}); lower the learning rates")
        exc.step = step
        return exc
    rows = bad.reshape(bad.shape[0], -1).any(dim=1).nonzero().flatten().tolist() if bad.ndim > 1 else []
    files = sorted({str(f) for f in (source(j) for j in rows) if f is not None})
    more = f" and {len(files) - 3} more" if len(files) > 3 else ""
    where = f" (patches of {', '.join(files[:3])}{more})" if files else ""
    return InputError(f"{what} stopped at step {step}: the loss is {loss} because the training batch holds "
                      f"{int(bad.sum())} NaN/Inf value(s){where}; the data, not the learning rate: fix or remove "
                      "those scene files, then train again")


def _agreed_stop(stop: StopRequests, next_step_s: float, solo: SoloWork, where: str) -> tuple[str, int] | None:
    """(reason, exit code) when the training is to stop now (:class:`StopRequests`), else None; in a
    DDP group every rank gets the same answer (the strongest code any rank has: a signal over the budget),
    in the collective that also tells every rank whether one failed in its work since the last (``solo``)."""
    why = stop.reason(next_step_s)
    code = solo.reduce([0 if why is None else stop.exit_code()], where)[0]
    return None if code == 0 else (stop.describe(code), code)


@contextlib.contextmanager
def deterministic_algorithms(enabled: bool):
    """``train.deterministic``: torch's deterministic algorithms (warn-only) inside the block, and the caller's
    setting back afterwards (a training called from a notebook or a test process leaves torch as it found it)."""
    before = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    if enabled:
        torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        if (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()) != before:
            torch.use_deterministic_algorithms(before[0], warn_only=before[1])


def _fit(task: Task, opts: FitOptions, run_dir: Path, resume: bool, lock: RunLock, new_run: OutputLock,
         stop: StopRequests) -> dict[str, Any]:
    """The training of :func:`fit`, inside its locks and signal handlers: the parts of :class:`_Training` in order.

    Under DDP every rank runs these same parts, so every rank reaches the same agreements (:class:`SoloWork`) and
    collectives in the same order; rank 0's work alone between them is held in ``solo.work()``."""
    run = _Training(task, opts, run_dir, stop)
    record = run.check_run_and_data(resume, lock, new_run)
    run.read_datasets()
    if resume:
        done = finished_record(run_dir, run.t.epochs, run.total_steps, run.steps_per_epoch, run.t.batch_size)
        if done is not None:  # nothing left to train: the run stays as it is (no file is written)
            log.debug("%s: already finished at step %d (%d epochs); nothing to train", run_dir, done["step"],
                     done["epoch"])
            return {**done, "already_finished": True}
    run.build_model()
    if resume:
        run.load_checkpoint()
    run.open_session(resume, lock, new_run, record)
    run.start()
    stop.armed = True  # from here a signal stops the loop at the next step's end (hsicam.engine.stopping)
    if opts.validate_at_start and not resume:
        run.validate_at_start()
    run.model.train()
    while run.state.epoch < run.t.epochs and run.state.global_step < run.total_steps:
        if not run.train_epoch():
            return {"stopped_at_step": run.state.global_step}
        run.end_epoch()
    return run.finish()


class _Training:
    """One training of :func:`fit` on this rank: its settings, data, model, checkpoints and where it stands
    (``state``, a :class:`LoopState`). :func:`_fit` calls its parts in order.

    Invariants kept by every method: each rank calls the same collectives (``solo.agree``/``solo.reduce``, DDP's,
    the loss's ``all_reduce``) in the same order; rank 0's work alone (the run folder, metrics, checkpoints,
    validation) runs inside ``solo.work()``, so that its error reaches the other ranks at the next agreement instead
    of leaving them in a collective; a checkpoint is one commit (:class:`CheckpointManager`), so a kill at any moment
    leaves the last one whole; a stop signal or the budget stops every rank at the same step (:meth:`stop_here`)."""

    # What the parts set, in the order :func:`_fit` calls them (each part reads only what an earlier one set):
    # read_datasets
    train_ds: Any
    val_ds: Any
    steps_per_epoch: int
    total_steps: int
    # build_model
    model: nn.Module
    optimizer: torch.optim.Optimizer
    bands: Bands
    meta: dict[str, str]
    ckpt: CheckpointManager
    metrics: MetricsLog
    state: LoopState
    # start
    val_loader: Any
    trainable: nn.Module  # the model, DDP-wrapped in a group
    writer: Any
    use_bar: bool
    bar: Any
    t_start: float
    steps_done: int
    last_val: float | None

    def __init__(self, task: Task, opts: FitOptions, run_dir: Path, stop: StopRequests) -> None:
        self.task, self.opts, self.t, self.run_dir, self.stop = task, opts, opts.loop, run_dir, stop
        self.rank, self.world, local_rank = dist_env()
        self.distributed = self.world > 1
        self.device = resolve_device(self.t.device, local_rank)
        if self.t.bf16:  # before any work: a torch that cannot failed at the first step, or trained in float32 unsaid
            problem = autocast_problem(self.device, torch.bfloat16)
            if problem is not None:
                raise ConfigError(f"train.bf16 on {self.device}: torch {torch.__version__} cannot autocast the network "
                                  f"there in bfloat16 ({problem}); set train.bf16=false to train in float32")
        self.is_main = self.rank == 0  # (train.batch_size divides by the world size: checked by fit, before the group)
        # rank 0's own work between the collectives of a DDP group: its error, held until the next agreement, ends every
        # rank there in one line (SoloWork; the others waited in a barrier and died with gloo's traceback)
        self.solo = SoloWork(self.rank, self.world, self.device)
        self.summary: dict[str, Any] = {}  # the last validation's metrics, reported by the final record

    def where(self) -> str:
        """When, for the messages of an agreement: "at step n of the training"."""
        return f"at step {self.state.global_step} of the {self.task.what}"

    # -- set-up: every rank agrees after each part, before anything is created -----------------------------------
    def check_run_and_data(self, resume: bool, lock: RunLock, new_run: OutputLock) -> dict[str, Any] | None:
        """Rank 0 takes the run folder's lock and checks the folder, records the task's scenes (checked against the
        run's own on resume) and, under DDP, prepares the data before the others read it; returns the record.
        Nothing is created until the data are known good."""
        task, run_dir, is_main = self.task, self.run_dir, self.is_main
        with self.solo.work():
            if is_main:
                if resume:
                    lock.acquire()  # before anything in the run is read or removed
                    check_not_an_output(run_dir)
                else:
                    check_not_locked(run_dir)  # a new run's folder: locked in its temporary folder below
                    new_run.acquire()  # until then its output lock: taken before check_run_dir removes a killed run's temporaries
                check_run_dir(run_dir, resume)  # before any work; nothing is created until the data are known good
            record = task.data_record() if is_main else None  # the scenes, before any is read
            if is_main and resume:  # a run goes on with the scenes and the split it started with
                check_same_data(run_dir, read_data_record(run_dir), record)
            if self.distributed and is_main:  # generate/cache the dataset once, on rank 0, before the others read it
                task.prepare_data()
        self.solo.agree(f"before the {task.what} started")
        return record

    def read_datasets(self) -> None:
        """Every rank reads its data, and agrees; then the run's length: ``steps_per_epoch`` and ``total_steps``."""
        t, task = self.t, self.task
        with self.solo.work():  # every rank reads its data: one rank's error (a file only it reads) is told before any file is made
            self.train_ds, self.val_ds = task.datasets()
        self.solo.agree(f"before the {task.what} started")
        self.steps_per_epoch = len(self.train_ds) // t.batch_size
        if self.steps_per_epoch < 1:
            raise InputError(f"data.patches_per_epoch={len(self.train_ds)} is smaller than {task.batch_size_key}="
                             f"{t.batch_size}")
        total_steps = self.steps_per_epoch * t.epochs
        if self.opts.max_steps is not None:
            total_steps = min(total_steps, self.opts.max_steps)
        if t.warmup_steps > total_steps and self.is_main:  # a warm-up meant for a longer run, or a typo (equal: its last step)
            log.warning("train.warmup_steps=%d is more than the run's %d steps: the learning rate never reaches train.lr "
                        "(it climbs to %.3g of it)", t.warmup_steps, total_steps, total_steps / t.warmup_steps)
        self.total_steps = total_steps

    def build_model(self) -> None:
        """The task's module on the device, its Adam optimizer (each group's ``base_lr``, the rate the schedule
        scales), the checkpoints, the metrics log and a fresh :class:`LoopState`."""
        task, t = self.task, self.t
        self.model = task.module().to(self.device)
        self.optimizer = torch.optim.Adam(task.param_groups())
        for g in self.optimizer.param_groups:
            g["base_lr"] = g["lr"]
        self.bands, self.meta = task.bands, task.weights_metadata()
        self.ckpt = CheckpointManager(self.run_dir, task.weights_file, keep=t.keep_weights)
        self.metrics = MetricsLog(self.run_dir / "metrics.jsonl", self.is_main)
        self.state = LoopState()

    def load_checkpoint(self) -> None:
        """Resume: every rank loads the last checkpoint (rank 0 first removes what a killed process left) and checks
        that the config's epochs count the same batches and no fewer steps; then every rank agrees, so that one
        rank's failure is told before anything changes."""
        t, run_dir, ckpt, optimizer = self.t, self.run_dir, self.ckpt, self.optimizer
        steps_per_epoch, total_steps = self.steps_per_epoch, self.total_steps
        with self.solo.work():
            if self.is_main:
                ckpt.cleanup()  # temporaries and step folders the manifest does not name (a killed process)
            if ckpt.path("last"):
                base_lrs = [g["base_lr"] for g in optimizer.param_groups]
                state = self.state = LoopState.from_dict(ckpt.load("last", self.model, optimizer, self.bands))
                # the learning rates of the config it goes on with (e.g. `--set train.lr=…`), not the
                # checkpoint's: the optimizer's moments continue, its schedule starts from these
                for g, lr in zip(optimizer.param_groups, base_lrs):
                    g["base_lr"] = lr
                batches = (f"{steps_per_epoch} steps of {t.batch_size} ({len(self.train_ds)} patches per epoch, "
                           f"{self.task.batch_size_key}={t.batch_size}): a resume would misplace where it stopped; keep "
                           "the batch size and the patches per epoch as they were; nothing was changed")
                if state.steps_per_epoch and (state.steps_per_epoch, state.batch_size) != (steps_per_epoch, t.batch_size):
                    # its position (step in epoch, steps done) counts batches of the size it was trained with
                    raise InputError(f"{run_dir}: was trained in epochs of {state.steps_per_epoch} steps of "
                                     f"{state.batch_size} patches, and its config now asks for {batches}")
                old_epoch = older_epoch_length(state)
                if old_epoch is not None and old_epoch != steps_per_epoch:
                    # a checkpoint of an older hsicam (no batch size kept): its completed epochs give their length
                    raise InputError(f"{run_dir}: was trained in epochs of {old_epoch} steps (a checkpoint of an older "
                                     f"hsicam, which did not record its batch size), and its config now asks for {batches}")
                if state.global_step > total_steps:  # before the config is rewritten: nothing changes
                    raise InputError(f"{run_dir}: has trained {state.global_step} steps ({state.epoch} epochs), more than the "
                                     f"{total_steps} its config now asks for; a resume cannot take training back: ask for at "
                                     "least as many, or leave the length as it was; nothing was changed")
        # every rank read the checkpoint: one rank's failure (e.g. a file only it reads) is told before any change
        self.solo.agree(f"before the {self.task.what} started")

    def open_session(self, resume: bool, lock: RunLock, new_run: OutputLock, record: dict[str, Any] | None) -> None:
        """Rank 0 makes the run folder in place, whole and locked (a new run), or brings a resumed run's files to its
        checkpoint (:meth:`note_resume`); then records this session's software in the metrics log. Every rank
        agrees afterwards."""
        changed: list[str] = []
        with self.solo.work():
            if resume:
                if self.is_main:
                    changed = self.note_resume()
            elif self.is_main:
                # The run folder appears at once with all its files (config.yaml, ...) or not at all.
                camera = self.task.camera_record()  # the files its camera is built from, hashed before any is made
                with atomic_output(self.run_dir, marker=False) as tmp:
                    lock.acquire(tmp)  # held across the rename: the run is never in place unlocked
                    self.task.write_run_files(tmp)
                    if record is not None:
                        write_data_record(tmp, record)
                    if camera is not None:  # its material tables, coded aperture
                        write_camera_files(tmp, camera)
                lock.moved()
                new_run.release()  # in place: the run's own lock keeps it
            if self.is_main:  # which software this session trains with (a resume adds its own record)
                # and what a resume's --set changed: config.yaml is rewritten to the config it goes on with, so it
                # alone no longer says how the steps before trained (session 74's records hunt)
                self.metrics.write({"step": self.state.global_step, "epoch": self.state.epoch,
                                    "session": {**software_record(str(self.device), self.world),
                                                **({"config_changed": changed} if changed else {}),
                                                **({"synthetic_set": s} if (s := self.task.synthetic_set()) else {})}})
        state = self.state
        state.total_steps = self.total_steps  # saved with each checkpoint: what a half-trained run is measured against
        state.steps_per_epoch, state.batch_size = self.steps_per_epoch, self.t.batch_size
        self.solo.agree(f"before the {self.task.what} started")

    def note_resume(self) -> list[str]:
        """Rank 0, on resume: the root weights and the metrics log brought back to the last checkpoint, the last
        validation kept for the final record, the config it goes on with written, and what the resume changes
        said (the task's data, an older hsicam's training). Returns the settings the config it goes on with changes
        (``"key: before → now"``, :func:`~hsicam.config.config_changes`), for the session record."""
        task, run_dir, state = self.task, self.run_dir, self.state
        self.ckpt.sync_root()  # a kill between the manifest's commit and the root weights' rewrite
        self.metrics.truncate_after(state.global_step, state.epoch)
        self.summary = last_validation(self.metrics.read())  # kept when no epoch is left to validate
        cfg = getattr(task, "cfg", None)  # (a task's config.yaml is its Config)
        changed = resumed_config_changes(run_dir, cfg) if cfg is not None else []
        task.write_run_files(run_dir)  # the config it goes on with (e.g. `--set train.epochs=…`)
        log.info("resuming %s at epoch %d, step %d", run_dir, state.epoch, state.global_step)
        warning = task.resume_warning(run_dir)
        if warning:
            log.warning(warning)
        commit, had = session_60_changes_had(run_dir)  # a commit of session 60 before it recorded this
        changes = older_run_changes(self.t, state.global_step, self.total_steps, task.seed_key,
                                    task.noisy_validation(), had) if started_before_session_60(run_dir) else []
        if changes:  # the resume cannot be the run that hsicam would have finished: said, not hidden
            log.warning("%s: started by %s, whose training this one changed; it goes "
                        "on with this one's: %s (docs/training.md): not the run that hsicam would have "
                        "finished; to finish it as it began, resume it with that hsicam, or train a new "
                        "run with another --out", run_dir,
                        f"hsicam {commit[:7]} (session 60, before c1ab911)" if commit
                        else "an hsicam before session 60", "; ".join(changes))
        return changed

    def start(self) -> None:
        """What the steps need: rank 0's validation loader, the module ready on its device (DDP-wrapped as
        ``trainable`` in a group), tensorboard, the progress bar and the clock."""
        t, task, device, is_main = self.t, self.task, self.device, self.is_main
        self.val_loader = (make_loader(self.val_ds, t.batch_size, self.opts.num_workers, shuffle=False)
                           if (self.val_ds is not None and is_main) else None)
        task.on_device(device)
        self.trainable = self.model
        if self.distributed:
            self.trainable = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[device.index] if device.type == "cuda" else None,
                find_unused_parameters=task.find_unused_parameters)
        self.writer = _tensorboard(self.run_dir) if (t.tensorboard and is_main) else None
        self.use_bar = (sys.stderr.isatty() if self.opts.progress is None else self.opts.progress) and is_main
        from tqdm.auto import tqdm

        self.bar = tqdm(total=self.total_steps, initial=self.state.global_step, disable=not self.use_bar, unit="step",
                        dynamic_ncols=True)
        self.t_start, self.steps_done, self.last_val = time.perf_counter(), 0, None

    # -- validation -----------------------------------------------------------------------------------------------
    def stoppable(self, loader):
        """``loader``'s batches until a stop signal arrives: a long validation (many or large
        patches) ends at its next batch, so that a scheduler's notice is honoured in time."""
        for batch in loader:
            if self.stop.received is not None:
                raise _ValidationCut
            yield batch

    def validate(self, cut: bool = True) -> dict[str, float] | None:
        """The validation metrics (rank 0); None when a stop signal arrived meanwhile (with ``cut``, the
        validation ends at its next batch) or ended the loader's workers (a SIGTERM to the whole
        process group reaches them too): that validation is not recorded. The last epoch's is not
        ``cut``: a signal then lets the training finish, its final validation included."""
        stop = self.stop
        self.model.eval()
        try:
            with torch.no_grad():
                return self.task.validate(self.stoppable(self.val_loader) if cut else self.val_loader, self.device)
        except (RuntimeError, _ValidationCut) as exc:
            if stop.received is None:
                raise
            why = "its data workers ended" if isinstance(exc, RuntimeError) else "it stopped at its next batch"
            log.warning("%s: the validation at step %d was cut short by %s (%s); not recorded",
                        self.run_dir, self.state.global_step, stop.received, why)
            return None
        finally:
            self.model.train()

    def log_validation(self, val: dict[str, float]) -> None:
        """A validation's record in the metrics log, tensorboard and the log."""
        state = self.state
        self.metrics.write({"step": state.global_step, "epoch": state.epoch, **{f"val_{k}": v for k, v in val.items()}})
        if self.writer:
            for k, v in val.items():
                self.writer.add_scalar(f"val/{k}", v, state.global_step)
        log.info("epoch %d: val %s", state.epoch, ", ".join(f"{k} {v:.4g}" for k, v in val.items()))

    def validate_at_start(self) -> None:
        """``validate_at_start`` (fine-tuning): rank 0 scores the starting weights and saves them as step 0's
        checkpoint (also the best when scored); then every rank agrees whether to stop."""
        state = self.state
        with self.solo.work():
            if self.is_main:
                val = self.validate() if self.val_loader is not None else None
                if val is not None:
                    self.summary = val
                    self.log_validation(val)
                    state.best_psnr, state.best_step = val.get("psnr"), 0
                self.ckpt.save(self.model, self.optimizer, state.to_dict(), self.bands,
                               ("last", "best") if val is not None else ("last",), self.meta)
        # (a full validation can take minutes)
        asked = _agreed_stop(self.stop, 0.0, self.solo, f"at step 0 of the {self.task.what}")
        if asked is not None:
            self.stop_here(*asked, saved=True)  # the step-0 checkpoint just written: a resume starts from it

    # -- the steps of an epoch ------------------------------------------------------------------------------------
    def train_epoch(self) -> bool:
        """This rank's batches of the current epoch (from ``step_in_epoch`` on, so a resume continues the epoch),
        one :meth:`train_step` each, until the epoch or the run's steps end; False when ``opts.stop_after_steps``
        ended the training (its checkpoint saved). A stop signal or the budget, agreed by every rank after a step
        that is not the epoch's last, stops here (:meth:`stop_here`)."""
        t, state = self.t, self.state
        self.train_ds.set_epoch(state.epoch)
        sampler = ShardedBatches(self.steps_per_epoch, t.batch_size, self.rank, self.world, state.step_in_epoch)
        loader = make_loader(self.train_ds, t.batch_size // self.world, self.opts.num_workers, shuffle=False,
                             sampler=sampler)
        batches = iter(loader)
        while True:
            try:
                batch = next(batches)
            except StopIteration:
                break
            except RuntimeError:  # a stop signal to the whole process group ended the loader's workers too
                if self.stop.received is None:
                    raise
                self.stop_here(self.stop.describe(self.stop.exit_code()), self.stop.exit_code(), saved=False)
            factor = self.train_step(batch)
            self.record_step(factor)
            if self.opts.stop_after_steps is not None and state.global_step >= self.opts.stop_after_steps:
                with self.solo.work():
                    if self.is_main and not self.solo.held:
                        self.ckpt.save(self.model, self.optimizer, state.to_dict(), self.bands, ("last",), self.meta)
                self.solo.agree(self.where())
                self.bar.close()
                return False
            if state.global_step >= self.total_steps:
                break
            if state.step_in_epoch < self.steps_per_epoch:  # (at an epoch's end: after its checkpoint, end_epoch)
                self.stop_if_asked(saved=False)
        return True

    def train_step(self, batch: torch.Tensor) -> float:
        """One optimizer step on this rank's share of a global batch; returns the step's learning-rate factor.
        Its random numbers depend only on (seed, step, rank) and its rate only on the step (an exact resume).
        Every rank reaches the same collectives (DDP's buffers and gradients, the loss's ``all_reduce``); the
        weights change only when the loss and its gradient are finite on every rank (:meth:`check_finite`)."""
        t, task, state, world = self.t, self.task, self.state, self.world
        step = state.global_step
        g = step_generator(t.seed, step, self.rank, self.device)
        task.on_step_start(step, g)
        factor = lr_factor(t, step, self.total_steps, self.steps_per_epoch)
        for group in self.optimizer.param_groups:
            group["lr"] = group["base_lr"] * factor
        try:  # (in a group, its collectives: DDP's buffers and gradients, the loss)
            loss = task.training_step(self.trainable, batch.to(self.device, non_blocking=True), g)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = None
            if t.grad_clip is not None:
                grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), t.grad_clip)
            loss_v = own_v = loss.item()
            if self.distributed:  # the global batch's loss (each rank holds a share), logged and checked by every rank
                total = loss.detach().reshape(1).clone()
                dist.all_reduce(total)
                loss_v = total.item() / world
        except RuntimeError as exc:
            # another rank failed alone in this step (e.g. a scene file only it reads): its error ended its side
            # of the group, and this rank's collective failed with gloo's traceback ("Connection reset by
            # peer"); now one line, as SoloWork's. Before the optimizer's step: the run keeps its last checkpoint
            failed = _failed_peer(self.rank) if self.distributed else None
            if failed is None:
                raise
            raise PeerFailed(f"rank {failed} failed at step {step} of the {task.what} (its own error says why); "
                             f"rank {self.rank} stops with it") from exc
        self.check_finite(step, batch, own_v, loss_v, grad_norm)
        self.optimizer.step()
        state.loss_sum, state.loss_n = state.loss_sum + loss_v, state.loss_n + 1
        state.global_step, state.step_in_epoch = step + 1, state.step_in_epoch + 1
        self.steps_done += 1
        self.bar.update(1)
        self.bar.set_postfix(loss=f"{loss_v:.4f}", psnr="-" if self.last_val is None else f"{self.last_val:.2f}",
                             epoch=state.epoch)
        return factor

    def check_finite(self, step: int, batch: torch.Tensor, own_v: float, loss_v: float,
                     grad_norm: torch.Tensor | None) -> None:
        """The error for a step whose loss (this rank's ``own_v``, the global batch's ``loss_v``) or gradient norm
        is not finite, raised before the optimizer's step: the weights stay those of the last good step."""
        t, what = self.t, self.task.what
        if not math.isfinite(own_v):  # before the step: the weights stay those of the last good step
            first = self.state.step_in_epoch * t.batch_size + self.rank * (t.batch_size // self.world)  # this rank's first item
            raise not_finite_error(what, step, own_v, batch, lambda j: patch_source(self.train_ds, first + j))
        if not math.isfinite(loss_v):  # another rank's share: it names its patches; this one stops with it
            exc = TrainingDiverged(f"{what} diverged at step {step}: the loss of another process's share of "
                                   f"the batch is {loss_v:.4g}; that process's error names its patches")
            exc.step = step
            raise exc
        if grad_norm is not None and not math.isfinite(norm_v := grad_norm.item()):
            # a finite loss whose gradient is not: clipping by an infinite norm zeroed every gradient, and the run
            # trained on, flat, without an error (e.g. train.ssim_loss=1e30)
            why = ("it overflows float32" if math.isinf(norm_v) else
                   "a NaN in the backward pass of a finite loss, e.g. a square root or division at 0")
            exc = TrainingDiverged(f"{what} diverged at step {step}: the loss is {loss_v:.4g} but its "
                                   f"gradient's norm is {norm_v} ({why}), so clipping would zero every gradient; "
                                   "lower the loss weights (train.ssim_loss, sam_loss, relative_l1, "
                                   "spectral_grad_loss, phase_loss) or the learning rates")
            exc.step = step
            raise exc

    def record_step(self, factor: float) -> None:
        """Rank 0's metrics record (every ``log_every_steps``) and checkpoint (every ``checkpoint_every_steps``)
        after a step. An error is held to the stop check that follows (its collective says it to the other ranks),
        or to the end of the epoch's (nothing more is done alone before it: ``solo.held``)."""
        t, state = self.t, self.state
        with self.solo.work():
            if self.is_main and state.global_step % t.log_every_steps == 0:
                rec = {"step": state.global_step, "epoch": state.epoch, "train_loss": state.loss_sum / state.loss_n,
                       "lr": self.optimizer.param_groups[0]["base_lr"] * factor,
                       "elapsed_s": time.perf_counter() - self.t_start}
                self.metrics.write(rec)
                if self.writer:
                    self.writer.add_scalar("train/loss", rec["train_loss"], rec["step"])
                if not self.use_bar:
                    eta = (time.perf_counter() - self.t_start) / self.steps_done * (self.total_steps - state.global_step)
                    log.info("step %d/%d epoch %d loss %.4f eta %.0fs", rec["step"], self.total_steps, state.epoch,
                             rec["train_loss"], eta)
            if self.is_main and state.global_step % t.checkpoint_every_steps == 0:
                self.ckpt.save(self.model, self.optimizer, state.to_dict(), self.bands, ("last",), self.meta)

    # -- the end of an epoch, stops, the end of the run -------------------------------------------------------------
    def end_epoch(self) -> None:
        """The epoch counted; rank 0's validation (every ``eval_every_epochs`` and at the last epoch) and the
        epoch's checkpoint, one commit (tagged best when it scores best); then every rank learns whether a signal
        cut that validation, and all stop together, or go on unless asked to stop (:meth:`stop_if_asked`)."""
        t, total_steps = self.t, self.total_steps
        ended = dataclasses.replace(self.state)  # its last step done, the epoch not yet counted
        state = self.state
        state.epoch, state.step_in_epoch, state.loss_sum, state.loss_n = state.epoch + 1, 0, 0.0, 0
        last_epoch = state.epoch == t.epochs or state.global_step >= total_steps
        tags = ["last"]
        cut = False  # a stop signal cut this epoch's validation short
        with self.solo.work():  # rank 0's validation and checkpoint; not after its last step's files failed (held)
            if self.is_main and not self.solo.held and self.val_loader is not None and (
                    state.epoch % t.eval_every_epochs == 0 or last_epoch):
                val = self.validate(cut=not last_epoch)
                cut = val is None
                if val is not None:
                    self.last_val = val.get("psnr")
                    self.log_validation(val)
                    if state.best_psnr is None or (self.last_val is not None and self.last_val > state.best_psnr):
                        state.best_psnr, state.best_step = self.last_val, state.global_step
                        tags.append("best")
                    self.summary = {**val}
            if cut:
                # the checkpoint keeps the epoch uncounted, so that a resume takes its (empty) rest and then the
                # validation again: counted, the validation was lost for good (its record, and the best
                # weights when it would have been the best)
                self.state = ended
            if self.is_main and not self.solo.held:  # one commit: the manifest names it last (and best); the root weights follow
                self.ckpt.save(self.model, self.optimizer, self.state.to_dict(), self.bands, tuple(tags), self.meta)
        # every rank learns whether rank 0's validation was cut (by a signal that may have reached rank 0 alone), and
        # by which signal: they stop together below (a rank 0 that stopped alone left the others in a collective)
        cut_code = self.solo.reduce([self.stop.exit_code() if cut else 0], self.where())[0]
        if cut_code and not cut:
            self.state, cut = ended, True
        if cut and not (self.state.epoch + 1 < t.epochs and self.state.global_step < total_steps):
            # the last epoch's validation, cut only by the loader's workers ending: unfinished, not finished
            self.stop_here(self.stop.describe(cut_code), cut_code, saved=True)
        if self.state.epoch + cut < t.epochs and self.state.global_step < total_steps:
            self.stop_if_asked(saved=True)  # rank 0 saved it just above

    def stop_if_asked(self, saved: bool) -> None:
        """Stop here (:meth:`stop_here`) when a signal or the budget asks to, as agreed by every rank
        (:func:`_agreed_stop`: one collective, which also tells whether a rank failed in its work)."""
        asked = _agreed_stop(self.stop, (time.perf_counter() - self.t_start) / max(self.steps_done, 1), self.solo,
                             self.where())
        if asked is not None:
            self.stop_here(*asked, saved=saved)

    def stop_here(self, why: str, code: int, saved: bool) -> NoReturn:
        """Save the checkpoint of this step (unless ``saved``) and raise :class:`TrainingStopped`
        (the budget) or :class:`TrainingInterrupted` (a signal)."""
        if not saved:
            with self.solo.work():
                if self.is_main:
                    self.ckpt.save(self.model, self.optimizer, self.state.to_dict(), self.bands, ("last",), self.meta)
            self.solo.agree(self.where())
        self.bar.close()
        kind = TrainingStopped if code == BUDGET_EXIT_CODE else TrainingInterrupted
        raise kind(self.run_dir, self.state.global_step, self.total_steps, why, code)

    def finish(self) -> dict[str, Any]:
        """The run's last files (rank 0): the root weights when no checkpoint gave them, then the final record
        (the task's files first: they mark the run finished); every rank agrees; returns the final record."""
        t, task, run_dir, state = self.t, self.task, self.run_dir, self.state
        self.bar.close()  # (a signal from here on is honoured once the training's last files are written: fit)
        # no checkpoint at all: the final weights are the run's. A kept checkpoint that is damaged leaves a missing root
        # missing (sync_root's warning names it): the final model's weights there were not those the manifest records
        with self.solo.work():  # rank 0's last files
            ckpt = self.ckpt
            if self.is_main and not ckpt.sync_root() and not (run_dir / task.weights_file).exists() and \
                    ckpt.root_source() is None:
                save_weights(run_dir / task.weights_file, self.model, self.bands, self.meta)
            elapsed = time.perf_counter() - self.t_start
            final = {"step": state.global_step, "epoch": state.epoch, "final": True, "best_psnr": state.best_psnr,
                     **{f"val_{k}": v for k, v in self.summary.items()}, "elapsed_s": elapsed}
            if self.steps_done:  # (a resume that only writes the final record trained nothing to time)
                final["patches_per_s"] = self.steps_done * t.batch_size / max(elapsed, 1e-9)
            if self.is_main:
                final = task.on_fit_end(run_dir, final)
                self.metrics.write(final)
        self.solo.agree(f"at the end of the {task.what}")
        if self.writer:
            self.writer.close()
        return final


class _ValidationCut(Exception):
    """A stop signal arrived during a validation: it ends at its next batch, unrecorded."""


def _tensorboard(run_dir: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        log.warning("train.tensorboard=true but tensorboard is not installed (pip install tensorboard); continuing without it")
        return None
    return SummaryWriter(str(run_dir / "tensorboard"))
