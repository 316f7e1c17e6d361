"""Exception types. The CLI turns every :class:`HsicamError` into one line and exit code 2."""

import re
from pathlib import Path


class HsicamError(Exception):
    """Base class for errors caused by the user's input (config, files, arguments)."""


class ConfigError(HsicamError, ValueError):
    """An invalid configuration: unknown key, wrong type, or a physically meaningless value."""


class InputError(HsicamError, ValueError):
    """An input file or array that cannot be used (format, shape, band grid, values)."""


class TrainingDiverged(InputError):
    """A training whose loss or gradient stopped being finite (the learning rates, or the loss weights).
    :func:`hsicam.engine.loop.fit` adds what its run folder keeps: ``run_dir`` and ``checkpoint_step`` (the step of
    its last checkpoint, all of whose weights are finite; None when it has none yet), so the CLI can say how to go
    on with a lower rate."""

    run_dir: Path | None = None
    checkpoint_step: int | None = None
    step: int | None = None  # the step that diverged (0: before any update, which no lower rate changes)


class PeerFailed(HsicamError):
    """What the other processes of a ``torchrun`` group raise when rank 0 failed in work they wait for (its work alone
    between two collectives: :class:`hsicam.engine.loop.SoloWork`): one line each, rank 0's own error saying why."""


class _Stop:
    """What a training that stopped on request says: the run, the step, why, the exit code, and
    whether the training had already ended (its last files written; then there is nothing to resume)."""

    def __init__(self, run_dir, step: int, total_steps: int, reason: str, exit_code: int, finished: bool = False) -> None:
        self.run_dir, self.step, self.total_steps, self.reason = run_dir, step, total_steps, reason
        self.exit_code, self.finished = exit_code, finished
        if finished:
            text = f"{run_dir}: training finished (step {step} of {total_steps}) before stopping on {reason}"
        else:
            text = (f"{run_dir}: training stopped at step {step} of {total_steps} ({reason}); the checkpoint of "
                    f"step {step} is saved")
        super().__init__(text)


class TrainingStopped(_Stop, Exception):
    """A training stopped at its time budget ``train.max_minutes``, after saving the checkpoint of
    the step it stopped at: the run resumes from there. The CLI prints it as one line and exits with
    :attr:`exit_code` 75 (EX_TEMPFAIL of sysexits.h, "try again")."""


class TrainingInterrupted(_Stop, KeyboardInterrupt):
    """A training stopped by a signal (SIGTERM, Ctrl-C) at the end of a step, after saving that
    step's checkpoint. A ``KeyboardInterrupt``, so that ``except Exception`` (a sweep in a notebook)
    does not swallow it; the CLI prints it as one line and exits with 128 + the signal's number."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a job scheduler) received by a command that does not train
    (:func:`hsicam.cli.sigterm_as_interrupt`): raised where Ctrl-C's ``KeyboardInterrupt`` would be, so the same
    clean-up runs (temporaries removed, no output left half-written); the CLI exits with 143 (128 + 15)."""


def negative_radiance_error(source: object, count: int, minimum: float, advice: str = "") -> InputError:
    """The one refusal of a cube or scene holding ``count`` negative values (the most negative ``minimum``), naming
    ``source``: file readers (:func:`hsicam.data.cube.check_cube`, the dataset's windowed check) and
    :meth:`hsicam.cameras.Camera.capture` say it alike; ``advice`` (e.g. how to clip) is appended."""
    return InputError(f"{source}: {count} negative radiance value(s) (minimum {minimum:.4g}); radiance and reflectance "
                      f"must be >= 0{f' ({advice})' if advice else ''}")


#: How torch's DataLoader re-raises in the main process an exception of a worker process: the same
#: type, its message replaced by this line and the worker's whole traceback (``ExceptionWrapper``).
_WORKER_WRAPPED = re.compile(r"Caught \w+ in DataLoader worker process \d+\.\nOriginal Traceback")


def original_message(exc: BaseException) -> str:
    """``str(exc)``, or for an exception that torch's DataLoader re-raised from a worker process, the
    message that the worker's exception had (the text after ``<Type>: `` that ends the traceback
    torch puts in its place); the wrapped text when that cannot be found."""
    text = str(exc)
    if not _WORKER_WRAPPED.match(text):
        return text
    t = type(exc)
    name = t.__qualname__ if t.__module__ in ("builtins", "__main__") else f"{t.__module__}.{t.__qualname__}"
    at = text.rfind(f"\n{name}: ")  # the last exception of the traceback is the one raised
    if at >= 0:
        return text[at + len(name) + 3:].strip()
    return "" if text.rstrip().endswith(f"\n{name}") else text  # "" : raised without a message
