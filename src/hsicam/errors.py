"""Exception types. The CLI turns every :class:`HsicamError` into one line and exit code 2."""

import re


class HsicamError(Exception):
    """Base class for errors caused by the user's input (config, files, arguments)."""


class ConfigError(HsicamError, ValueError):
    """An invalid configuration: unknown key, wrong type, or a physically meaningless value."""


class InputError(HsicamError, ValueError):
    """An input file or array that cannot be used (format, shape, band grid, values)."""


class TrainingStopped(Exception):
    """A training stopped before its end when asked to (a signal such as SIGTERM or Ctrl-C, or the
    time budget ``train.max_minutes``), after saving the checkpoint of the step it stopped at: the
    run resumes from there. The CLI prints it as one line and exits with :attr:`exit_code`
    (128 + the signal's number, as a shell reports a process that a signal ended; 75, EX_TEMPFAIL
    of sysexits.h, "try again", for the budget)."""

    def __init__(self, run_dir, step: int, total_steps: int, reason: str, exit_code: int) -> None:
        self.run_dir, self.step, self.total_steps, self.reason, self.exit_code = run_dir, step, total_steps, reason, exit_code
        super().__init__(f"{run_dir}: training stopped at step {step} of {total_steps} ({reason}); "
                         f"the checkpoint of step {step} is saved")


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
