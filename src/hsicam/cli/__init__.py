"""Command-line interface: a thin shell over the library.

Each sub-command lives in a module of this package that defines ``register(subparsers)``; add a
module to ``COMMAND_MODULES`` to add commands.

**One error boundary** (:func:`main`): every :class:`HsicamError` (bad config, bad file, bad
argument), every ``OSError`` (an output path that cannot be written, a full disk, an input that
cannot be read) and every unreadable JSON/YAML/text input is printed as ONE line ``hsicam: error:
<file>: <problem>`` and exits with code 2, without a traceback (``-v`` adds the traceback). Output piped into
a reader that stops early (``hsicam data sources | head -1``) ends quietly with 141 (128 + SIGPIPE), as a shell
tool's does (:func:`stdout_closed`). Commands
that write check their output paths with :func:`prepare_output` before any work starts and write
through :func:`hsicam.io.atomic_output`, so a failed or killed command leaves nothing that a later
command accepts. A command never removes what another process is writing now: a folder output that
another process is writing (a new training run included) is refused in one line naming it.

Paths: a leading ``~`` in a path argument is expanded (:data:`PATH_METAVARS`); an output that is a
symbolic link is written in what it leads to, the link kept (:func:`hsicam.io.follow_link`).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import logging
import os
import re
import select
import signal
import stat
import sys
import threading
import traceback
from pathlib import Path
from typing import Sequence

from hsicam.errors import (HsicamError, InputError, Terminated, TrainingDiverged, TrainingInterrupted, TrainingStopped,
                           original_message)

COMMAND_MODULES = (
    "hsicam.cli.camera",
    "hsicam.cli.data",
    "hsicam.cli.train",
    "hsicam.cli.reconstruct",
    "hsicam.cli.evaluate",
    "hsicam.cli.demo",
    "hsicam.cli.baselines",
    "hsicam.cli.fabrication",
    "hsicam.cli.pretrained",
)


#: Metavars of the options and positionals that take a path: a leading ``~`` in their values (and
#: string defaults) is expanded as a shell does, also when it reached hsicam quoted (a script, a
#: Makefile), so every reader and writer (hsicam's, imageio's) takes the same file. The parser gives
#: them the ``type`` :func:`hsicam.cli.args.path_arg` (around their own). ``--set KEY=VALUE`` is no
#: path: its value goes into the config as written (a path key, e.g. ``data.root``, is expanded
#: where it is read).
PATH_METAVARS = frozenset({"DIR", "FILE", "OUT", "PATH", "RUN", "RUN2", "SENSOR"})


def _path_kwargs(kwargs: dict) -> dict:
    """``add_argument``'s keyword arguments, with ``type`` expanding ``~`` for a path argument."""
    metavar = kwargs.get("metavar")
    if isinstance(metavar, str) and metavar in PATH_METAVARS:
        from hsicam.cli.args import path_arg

        kwargs = {**kwargs, "type": path_arg(kwargs.get("type"))}
    return kwargs


def _expanding(group):
    """An argument group of a :class:`_Parser` whose path arguments expand ``~`` too."""
    add_argument, add_group, add_exclusive = (group.add_argument, group.add_argument_group,
                                              group.add_mutually_exclusive_group)
    group.add_argument = lambda *args, **kwargs: add_argument(*args, **_path_kwargs(kwargs))
    group.add_argument_group = lambda *args, **kwargs: _expanding(add_group(*args, **kwargs))
    group.add_mutually_exclusive_group = lambda **kwargs: _expanding(add_exclusive(**kwargs))
    return group


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors reported as one line, exit code 2, and ``~`` expanded in paths
    (:data:`PATH_METAVARS`, in argument groups too). Options are taken only as spelled out in full
    (``allow_abbrev=False``): argparse's default would read ``--sensor-sig`` as ``--sensor-sigma``, and
    a prefix that names one option today may name another, or none, when an option is added."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"hsicam: error: {message}\n")

    def add_argument(self, *args, **kwargs):  # type: ignore[override]
        return super().add_argument(*args, **_path_kwargs(kwargs))

    def add_argument_group(self, *args, **kwargs):  # type: ignore[override]
        return _expanding(super().add_argument_group(*args, **kwargs))

    def add_mutually_exclusive_group(self, **kwargs):  # type: ignore[override]
        return _expanding(super().add_mutually_exclusive_group(**kwargs))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hsicam", description="Learned snapshot hyperspectral cameras: design, simulate, train, use.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    from hsicam import __version__  # hsicam/__init__ loads neither numpy nor torch: the help stays fast

    parser.add_argument("--version", action="version", version=f"hsicam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def add_config_args(p: argparse.ArgumentParser) -> None:
    """The ``--config FILE`` and repeatable ``--set key=value`` options shared by commands."""
    p.add_argument("--config", metavar="FILE",
                   help="YAML config or preset name (tiny, quick, paper, ...; default: the built-in config: the paper "
                        "preset's camera and network, not its data and training scale)")
    p.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
                   help="dotted override, e.g. camera.doe.enabled=false (repeatable)")


def run_folder(spec: str) -> Path:
    """argparse ``type`` of every ``--run``: a run folder, or ``pretrained:NAME`` (a camera shipped
    with the package, :func:`hsicam.runs.pretrained.resolve_run`); a bad name is a usage error
    listing the shipped names."""
    from hsicam.runs.pretrained import resolve_run

    try:
        return resolve_run(spec)
    except HsicamError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_run_arg(p: argparse.ArgumentParser, help: str, required: bool = True) -> None:
    """The ``--run RUN`` option: a run folder or ``pretrained:NAME`` (see :func:`run_folder`)."""
    p.add_argument("--run", required=required, type=run_folder, metavar="RUN",
                   help=f"{help}, or pretrained:NAME (a shipped camera, see `hsicam pretrained`)")


def config_from_args(path: str | Path | None, overrides: Sequence[str] = ()):
    """``load_config`` for the command line: a config FILE that is empty (or holds only comments)
    is an error, never silently the built-in defaults (the paper camera); so is an empty item in one of its
    comma-separated lists (:func:`hsicam.config.check_list_keys`), as in an override."""
    from hsicam.config import check_list_keys, load_config

    cfg = load_config(path, list(overrides), empty="give a preset (tiny, quick, paper) or a YAML file with at "
                                                    "least one section")
    check_list_keys(cfg, path)
    return cfg


def run_config_from_args(run: str | Path, overrides: Sequence[str] = ()):
    """``load_config`` of a run's own config.yaml (``--run``, ``--resume``), with ``overrides``: an emptied file
    is a damaged run (:data:`hsicam.runs.folder.EMPTY_RUN_CONFIG`), not a request for a preset."""
    from hsicam.config import load_config
    from hsicam.runs.folder import EMPTY_RUN_CONFIG

    return load_config(Path(run) / "config.yaml", list(overrides), empty=EMPTY_RUN_CONFIG)


def prepare_output(path: str | Path, kind: str = "dir", replace: bool = False, command: str | None = None,
                   run: str | Path | None = None) -> Path:
    """Before any work: :func:`hsicam.io.check_output_path` (one-line error for an output that cannot
    work, a symbolic link that points nowhere; a shipped pre-trained camera, which is read-only),
    then remove the hidden temporary siblings (``.NAME.XXXXXXXX.tmpdir`` …) that an earlier, killed
    run of a command left next to this output (next to a link's target: the writers follow links),
    never those another process is writing now (:func:`hsicam.io.remove_stale_siblings`): a folder
    that another process is writing (``atomic_output``, a new training run) is refused, naming it.
    In a ``torchrun`` group rank 0 does this for the group. ``replace``: the command writes the folder
    whole through ``atomic_output(..., overwrite=True)``, so a training run (named as the input
    ``run`` when it is), a non-empty folder that is not a completed hsicam output (a user's own),
    another ``command``'s output or a completed folder holding files the command did not write is
    refused now, before the work (:func:`hsicam.io.check_replaceable`, the check ``atomic_output``
    repeats with its marker's command)."""
    from hsicam.devices import dist_env
    from hsicam.io import check_output_path, check_replaceable, follow_link, remove_stale_siblings
    from hsicam.runs.pretrained import check_not_pretrained

    check_not_pretrained(path)
    out = check_output_path(path, kind)
    if replace and kind == "dir":
        _refuse_run_folder(out, command, run)
        check_replaceable(Path(out), overwrite=True, command=command)
    if dist_env()[0] == 0:  # another rank's temporaries are rank 0's own
        remove_stale_siblings(follow_link(out), kind)
    _note_output(out, kind)
    return out


#: The outputs :func:`prepare_output` checked for the command now running (:func:`main`), each with the outermost
#: folder of its path that did not exist then (None: none was missing) and whether it was an empty folder then.
_PREPARED: list[tuple[Path, Path | None, bool]] = []


def _note_output(out: Path, kind: str) -> None:
    """Record what of ``out``'s path exists before the command's work (:data:`_PREPARED`)."""
    path = Path(os.path.abspath(out))
    missing = []
    for a in (path, *path.parents):
        if os.path.lexists(a):
            break
        missing.append(a)
    if kind == "file":  # the output itself is a file: only the folders above it count
        missing = [a for a in missing if a != path]
    empty = kind == "dir" and path.is_dir() and not path.is_symlink() and not any(path.iterdir())
    _PREPARED.append((path, missing[-1] if missing else None, empty))


def _remove_unused_outputs() -> None:
    """After a failed command: the folders of its outputs' paths that were missing before its work
    (:func:`prepare_output`), and the sub-folders it made in an output folder that was empty then, are removed
    again while they hold no file at any depth: a command that failed before it wrote anything leaves no new
    folder, a folder the user named stays, and whatever it wrote stays (a run to resume). Never while another
    process holds the output's lock (it may be filling them); in a ``torchrun`` group, rank 0 only."""
    from hsicam.devices import dist_env
    from hsicam.io import output_lock_path

    prepared = list(_PREPARED)
    _PREPARED.clear()
    if dist_env()[0] != 0:
        return
    for out, top, empty in prepared:
        if os.path.lexists(output_lock_path(out)):  # another process's: this one's own were let go with the error
            continue
        if top is not None:
            _remove_empty_folders(top, keep_root=False)
        elif empty:
            _remove_empty_folders(out, keep_root=True)


def _remove_empty_folders(root: Path, keep_root: bool) -> None:
    """Remove the folder tree ``root`` (only its sub-folders with ``keep_root``) when it holds nothing but
    folders; a file or a link anywhere in it keeps it all."""
    if root.is_symlink() or not root.is_dir():
        return
    folders = []
    for folder, dirs, files in os.walk(root):
        if files or any(os.path.islink(os.path.join(folder, d)) for d in dirs):
            return
        folders.append(folder)
    for folder in reversed(folders[1:] if keep_root else folders):  # the innermost first
        with contextlib.suppress(OSError):  # not empty any more (another process): kept
            os.rmdir(folder)


def _refuse_run_folder(out: Path, command: str | None, run: str | Path | None) -> None:
    """InputError for a training run (or a spectral prior) as the folder that ``command`` would
    replace whole, named as what it is (the input ``run`` when it is that one)."""
    from hsicam.io import is_complete, same_path
    from hsicam.runs.folder import WEIGHTS_FILES, holds_prior

    if not out.is_dir() or is_complete(out) or not (out / "config.yaml").is_file():
        return
    what = None
    if holds_prior(out):
        what = "a spectral prior"
    elif (out / "checkpoints").is_dir() or any((out / w).is_file() for w in WEIGHTS_FILES):
        what = "a training run"
    writer = f"hsicam {command}" if command else "this command"
    if run is not None and same_path(out, run):
        raise InputError(f"{out}: is the input run (--run, {what or 'a run folder'}); {writer} writes its output "
                         "into a folder of its own: choose another --out")
    if what is not None:
        raise InputError(f"{out}: holds {what}, which {writer} never replaces; choose another --out")


def interrupt_behind(exc: BaseException) -> BaseException | None:
    """The stop among the causes and contexts of ``exc`` (a ``KeyboardInterrupt``: Ctrl-C, SIGTERM's
    :class:`~hsicam.errors.Terminated`, a training's :class:`~hsicam.errors.TrainingInterrupted`; or a
    :class:`~hsicam.errors.TrainingStopped`), else None: a Ctrl-C that arrives while a module is imported can surface
    as another error (Python 3.11: "RuntimeError: Error calling __set_name__ on 'Field' instance …" from torch's lazy
    imports), which is still the user's stop, not a failure."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, (KeyboardInterrupt, TrainingStopped)):
            return e
        seen.add(id(e))
        e = e.__cause__ if e.__cause__ is not None else e.__context__
    return None


def _stopped(stop: BaseException, args: argparse.Namespace | None = None) -> int:
    """The one line (stderr) and exit code of a command that ``stop`` ended: a training stopped by a signal or
    ``train.max_minutes`` (saved at that step: how to go on, the command's own ``resume_hint``; under ``torchrun``
    rank 0 alone says it), SIGTERM (143) or Ctrl-C (130)."""
    if isinstance(stop, (TrainingStopped, TrainingInterrupted)):
        from hsicam.devices import dist_env

        if dist_env()[0] == 0:
            hint = getattr(args, "resume_hint", None) or "run the same command with --resume to go on"
            print(f"hsicam: {stop}" + ("" if stop.finished else f"; {hint.format(run=stop.run_dir)}"), file=sys.stderr)
        return stop.exit_code
    if isinstance(stop, Terminated):
        print("hsicam: terminated (SIGTERM); nothing half-written was left", file=sys.stderr)
        return 128 + signal.SIGTERM
    print("hsicam: interrupted", file=sys.stderr)
    return 130


def error_line(exc: BaseException) -> str | None:
    """The one line a user sees for ``exc``, or None for an exception that is a bug (traceback). An
    error raised in a DataLoader worker process is told by its own message, not torch's wrapping."""
    if isinstance(exc, HsicamError):
        text = original_message(exc)
        return text.splitlines()[0] if text else type(exc).__name__
    if isinstance(exc, OSError):
        return _os_error_line(exc)
    if isinstance(exc, json.JSONDecodeError):
        return f"unreadable JSON input ({exc.msg} at line {exc.lineno})"
    if isinstance(exc, UnicodeDecodeError):
        return f"unreadable input: not UTF-8 text ({exc.reason})"
    if isinstance(exc, MemoryError):
        return "out of memory (lower the memory budget HSICAM_MEMORY_BUDGET_MB, the tile size or the batch size)"
    if isinstance(exc, RuntimeError) and (type(exc).__name__ == "OutOfMemoryError"
                                          or "can't allocate memory" in str(exc)):
        # torch's allocators (CPU: a RuntimeError; CUDA: torch.OutOfMemoryError), not Python's MemoryError
        what = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if _raised_in_consistency_steps(exc):  # whole-image work: a smaller tile cannot help (session 76)
            return (f"out of memory ({what}) in the consistency steps, which go over the whole image whatever the "
                    "tile size: work on a smaller image or in parts, or with fewer steps (hsicam reconstruct "
                    "--consistency-steps 0; hsicam evaluate --set model.consistency.iterations=0)")
        return (f"out of memory ({what}): work on a smaller image or in parts, or lower the tile size or the batch "
                "size")
    try:
        import yaml

        if isinstance(exc, yaml.YAMLError):
            return f"unreadable YAML input ({str(exc).splitlines()[0]})"
    except ImportError:  # pragma: no cover
        pass
    return None


def _raised_in_consistency_steps(exc: BaseException) -> bool:
    """Whether ``exc`` was raised in the measurement-consistency steps that go over the whole image after the tiles
    (:meth:`hsicam.models.CameraSystem.landweber_steps`): a frame of that method in ``exc``'s traceback."""
    module = sys.modules.get("hsicam.models.system")
    where = getattr(module, "__file__", None)
    if where is None:
        return False
    where = os.path.abspath(where)
    return any(frame.name == "landweber_steps" and os.path.abspath(frame.filename) == where
               for frame in traceback.extract_tb(exc.__traceback__))


#: numpy's message for a file write cut short (no errno): a full disk, most often.
_SHORT_WRITE = re.compile(r"^(\d+) requested and (\d+) written$")


def _os_error_line(exc: OSError) -> str:
    """``<file>: <what happened> (<what to do>)`` for an OSError (the file when it names one; what to
    do: :data:`hsicam.io.OS_ERROR_HINTS`, the one table of disk errors)."""
    from hsicam.io import OS_ERROR_HINTS

    text = exc.strerror or (original_message(exc).splitlines() or [""])[0] or type(exc).__name__
    what, hint = text.splitlines()[0], OS_ERROR_HINTS.get(exc.errno) if exc.errno is not None else None
    if hint is not None:
        what = os.strerror(exc.errno)
    short = _SHORT_WRITE.match(what) if exc.errno is None else None
    if short is not None:
        what = f"the write stopped after {short[2]} of {short[1]} bytes"
        hint = "is the disk full? free some space, or write to another disk"
    line = f"{exc.filename}: {what}" if exc.filename is not None else what
    return f"{line} ({hint})" if hint else line


@contextlib.contextmanager
def sigterm_as_interrupt(enabled: bool = True):
    """Inside the block, SIGTERM raises :class:`~hsicam.errors.Terminated` (a ``KeyboardInterrupt``) instead of
    ending the process at once, so a killed command cleans up as after Ctrl-C: the temporaries of its outputs
    are removed and no output is left half-written. Only where SIGTERM has its default action and in the main
    thread; the previous handler is restored on exit. The commands that train keep the default
    (``enabled=False``): their loop stops cleanly on SIGTERM by itself (:mod:`hsicam.engine.stopping`)."""
    if not enabled or threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def terminate(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stdout_closed() -> bool:
    """True when standard output is a pipe or socket whose reader has gone (``| head`` has exited): the
    :class:`BrokenPipeError` of a write to it is the reader's choice, not an error of the command's. A broken pipe
    elsewhere (an output the command opened) stays an error."""
    try:
        fd = sys.stdout.fileno()
        mode = os.fstat(fd).st_mode
    except (AttributeError, OSError, ValueError):  # replaced by an object without a descriptor, or closed
        return False
    if not (stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)) or not hasattr(select, "poll"):  # Windows: no poll()
        return False
    poll = select.poll()
    poll.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poll.poll(0))


def main(argv: Sequence[str] | None = None) -> int:
    try:
        parser = build_parser()  # imports the commands' modules, not torch (hsicam.cli.args.RegistryChoices): ~0.2 s
        # the options' types run here: `--run` checks the run's weights, importing torch (~1 s to interrupt)
        args = parser.parse_args(argv)
    except KeyboardInterrupt as stop:
        return _stopped(stop)
    except Exception as exc:  # noqa: BLE001 - a Ctrl-C inside an import, wrapped (interrupt_behind)
        stop = interrupt_behind(exc)
        if stop is None:
            raise
        return _stopped(stop)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    # -v: hsicam's own debug lines only (matplotlib's font search, PIL's and h5py's chatter stay out)
    logging.getLogger("hsicam").setLevel(logging.DEBUG if args.verbose else logging.NOTSET)
    # torch's INFO lines reach the root logger when a Ctrl-C stopped torch's import before its own logging set-up
    # (then its exit hook printed "FakeTensor cache stats: …" under "hsicam: interrupted"); TORCH_LOGS: the user's
    if not os.environ.get("TORCH_LOGS"):
        logging.getLogger("torch").setLevel(logging.WARNING)
    from hsicam.data.cube import trained_bands

    try:
        fixed = getattr(args, "run", None) is not None or bool(getattr(args, "resume", False))
        # a command that trains and then scores (demo, experiment) spends most of its time outside the loop, where
        # SIGTERM must clean up as Ctrl-C does; the loop's own stop chains to it (hsicam.engine.stopping)
        cleanup = not getattr(args, "trains", False) or getattr(args, "scores", False)
        _PREPARED.clear()
        with trained_bands(fixed), sigterm_as_interrupt(cleanup):
            try:
                return int(args.func(args) or 0)
            except BaseException:
                _remove_unused_outputs()  # a failed command leaves no new empty folder
                raise
            finally:
                _PREPARED.clear()
    except (TrainingStopped, KeyboardInterrupt) as stop:  # (TrainingInterrupted and Terminated are KeyboardInterrupts)
        return _stopped(stop, args)
    except Exception as exc:  # noqa: BLE001 - the one error boundary
        stop = interrupt_behind(exc)
        if stop is not None:  # a stop that arrived inside an import (or a clean-up), which wrapped it in another error
            if args.verbose:
                traceback.print_exc()
            return _stopped(stop, args)
        if isinstance(exc, BrokenPipeError) and stdout_closed():
            # what is left in Python's buffer would fail again at exit ("Exception ignored ... BrokenPipeError")
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 128 + getattr(signal, "SIGPIPE", 13)  # 141, as a shell tool killed by SIGPIPE
        line = error_line(exc)
        if line is None:
            raise
        hint = getattr(args, "diverged_hint", None)
        if isinstance(exc, TrainingDiverged) and exc.run_dir is not None and hint:  # how to go on with a lower rate
            kept = ("holds no checkpoint yet" if exc.checkpoint_step is None else
                    f"keeps the checkpoint of step {exc.checkpoint_step}, from before the divergence")
            if exc.step == 0:  # before any update: a lower rate changes nothing (following that hint failed again)
                hint = ("it diverged before any update, so no lower rate changes it: resume it with other settings "
                        "(hsicam train --out {run} --resume, with --set of the keys named above) or start over with "
                        "--restart")
            line += f"; {exc.run_dir} {kept}; {hint.format(run=exc.run_dir)}"
        if args.verbose:
            traceback.print_exc()
        print(f"hsicam: error: {line}", file=sys.stderr)
        return 2


def entry() -> int:
    """The ``hsicam`` command (its console script and ``python -m hsicam``): :func:`main` in a process whose C
    allocator keeps freed memory for the next tensor (:func:`hsicam.memory.keep_freed_memory`: a 512² reconstruction
    1.7× faster, its TV steps 2.4×, on this project's CPU). Calling :func:`main` from Python leaves the allocator
    alone."""
    from hsicam.memory import keep_freed_memory

    keep_freed_memory()
    return main()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(entry())
