"""Running the real `hsicam` console script in tests."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

HSICAM = Path(sys.executable).parent / "hsicam"
#: The source tree under test: subprocesses import it first, whatever the venv has installed.
SRC = Path(__file__).resolve().parents[1] / "src"


def module_cache(tmp_path_factory):
    """Body of a module-scoped ``env`` fixture (``yield from module_cache(tmp_path_factory)``): a
    fresh ``HSICAM_CACHE`` for the module's CLI runs and in-process calls, restored afterwards."""
    d = str(tmp_path_factory.mktemp("cache"))
    old = os.environ.get("HSICAM_CACHE")
    os.environ["HSICAM_CACHE"] = d
    yield {"HSICAM_CACHE": d}
    if old is None:
        os.environ.pop("HSICAM_CACHE", None)
    else:
        os.environ["HSICAM_CACHE"] = old


def cli_env(env: dict | None = None) -> dict:
    """The environment of a CLI subprocess: this checkout's ``src`` first on PYTHONPATH, one thread."""
    path = os.pathsep.join(x for x in (str(SRC), os.environ.get("PYTHONPATH", "")) if x)
    return {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"), **(env or {}), "PYTHONPATH": path}


def run_cli(*args: str, timeout: float = 600, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``hsicam ARGS`` through the installed entry point; returns the completed process."""
    return subprocess.run([str(HSICAM), *args], capture_output=True, text=True, timeout=timeout, env=cli_env(env))


#: Warnings a Python process does not show by default (``python -W default`` would): left out of
#: :func:`run_cli_in_process`'s stderr, as the console script leaves them out of its own.
HIDDEN_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def run_cli_in_process(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    """``hsicam ARGS`` in this process (the console script's ``main``; saves the 2–3 s interpreter and
    torch start of :func:`run_cli`), as a completed process like :func:`run_cli`'s.

    Its stderr holds what the console script would print there: the log lines of every logger at INFO
    and up (DEBUG with ``-v`` for hsicam's), one ``%(message)s`` per line, as ``main``'s ``basicConfig``
    sets them up, and Python's warnings (those a process shows by default). pytest still gets both
    (``caplog`` and the warnings summary work). ``env`` entries are set in ``os.environ`` for the call
    (None: unset) and restored afterwards. Keep :func:`run_cli` for what needs a process of its own:
    signals, exit codes of the interpreter, another working directory, the entry point itself, a
    command that would exhaust memory if its check broke, warnings shown once per process."""
    import contextlib
    import io
    import logging
    import warnings

    from hsicam.cli import main

    out, err = io.StringIO(), io.StringIO()
    handler = logging.StreamHandler(err)
    handler.setFormatter(logging.Formatter("%(message)s"))
    handler.setLevel(logging.DEBUG if {"-v", "--verbose"} & set(map(str, args)) else logging.INFO)
    logger, root = logging.getLogger("hsicam"), logging.getLogger()
    saved = {k: os.environ.get(k) for k in (env or {})}
    old_root_level, old_level = root.level, logger.level
    root.addHandler(handler)
    root.setLevel(min(root.level, logging.INFO))  # NOTSET (0) stays: everything passes already
    for k, v in (env or {}).items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = str(v)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                warnings.catch_warnings(record=True) as caught:
            try:
                rc = main([str(a) for a in args])
            except SystemExit as exc:  # argparse usage errors
                rc = 0 if exc.code is None else exc.code
    finally:
        root.removeHandler(handler)
        logger.setLevel(old_level)  # main sets it by -v
        root.setLevel(old_root_level)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    for w in caught:
        if not issubclass(w.category, HIDDEN_WARNINGS):
            err.write(warnings.formatwarning(w.message, w.category, w.filename, w.lineno, w.line))
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)  # for pytest's own record
    return subprocess.CompletedProcess(list(args), rc, out.getvalue(), err.getvalue())


def error_line(res: subprocess.CompletedProcess) -> str:
    """The one line of a refused command (exit code 2, no traceback), ``hsicam: error: …``."""
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = [x for x in res.stderr.strip().splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("hsicam: error: "), res.stderr
    return lines[0]


def final_error_line(res: subprocess.CompletedProcess) -> str:
    """The error line of a command refused after some work (exit code 2, no traceback): its last line on
    stderr and its only ``hsicam: error: …`` line; the log of the work before it (training steps, warnings
    about the inputs) may precede it."""
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr, res.stderr
    lines = [x for x in res.stderr.strip().splitlines() if x.strip()]
    assert lines and lines[-1].startswith("hsicam: error: "), res.stderr
    assert sum(x.startswith("hsicam: error:") for x in lines) == 1, res.stderr
    return lines[-1]


def assert_ok(res: subprocess.CompletedProcess) -> None:
    """Exit code 0 (stdout and stderr shown otherwise)."""
    assert res.returncode == 0, (res.returncode, res.stdout, res.stderr)


#: A progress line of :mod:`hsicam.progress` off a terminal: ``DESC: k/N UNITs … (… elapsed…)``.
PROGRESS_LINE = re.compile(r"^[^:]+: \d+/\d+ \S+ .*\(\S+ \S* ?elapsed")


def assert_clean_error(proc: subprocess.CompletedProcess, *fragments: str) -> None:
    """Exit code 2, one line on stderr starting with 'hsicam: error:', no traceback (lines of the work
    done before the refusal, such as the data's generation and its progress, aside)."""
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = [x for x in proc.stderr.strip().splitlines() if x.strip() and not x.startswith(("generating", "data:"))
             and not PROGRESS_LINE.match(x)]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("hsicam: error:"), proc.stderr
    assert "Traceback" not in proc.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])


def unprivileged_prefix() -> tuple[str, ...] | None:
    """How to run a child in which a chmod 0o500 folder really is unwritable: nothing for a normal
    user; for root, setpriv dropping the capabilities that bypass file permissions; None if neither."""
    if os.geteuid() != 0:
        return ()
    if shutil.which("setpriv") is None:
        return None
    caps = "-dac_override,-dac_read_search,-fowner"
    prefix = ("setpriv", f"--bounding-set={caps}", f"--inh-caps={caps}")
    if subprocess.run([*prefix, "true"], capture_output=True, cwd=os.environ.get("TMPDIR", "/tmp")).returncode != 0:
        return None
    return prefix


def write_measured_psfs(run: Path, folder: Path, shift_px: int = 0) -> Path:
    """A measured-PSF folder (``psf.npy`` + ``psf.json``) for ``hsicam finetune --psf-dir``: the run's
    own simulated PSFs, shifted by ``shift_px`` along x (so that they differ from the design's)."""
    import numpy as np
    import torch

    from hsicam.config import load_config
    from hsicam.io import write_json, write_npy
    from hsicam.runs.folder import load_run

    _, model = load_run(run)
    with torch.no_grad():
        psf = model.camera.psf().double().numpy()
    psf = np.roll(psf, shift_px, axis=-1)
    folder.mkdir(parents=True)
    write_npy(folder / "psf.npy", psf.astype(np.float32))
    write_json(folder / "psf.json", {"pixel_pitch_um": load_config(run / "config.yaml").camera.sensor.pixel_pitch_um,
                                     "bands_nm": model.bands.centers_nm.tolist()})
    return folder


def _as_in_a_terminal() -> None:
    """In the child before exec: SIGINT as a terminal's job has it (a test run started with `&`, as a CI
    runner may start it, ignores SIGINT, and an ignored signal stays ignored: hsicam.engine.stopping)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def signal_a_training(run: Path, cache_env, send, *extra: str, ready: str = "metrics.jsonl") -> tuple[int, str]:
    """(exit code, stderr) of `hsicam train --config tiny` (40 epochs, ``extra`` keys) in its own
    process group, Ctrl-C as in a terminal, after ``send(proc)`` once it is training (``RUN/ready`` exists)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env)}
    args = [str(HSICAM), "train", "--config", "tiny", "--out", str(run), "--set", "train.epochs=40", *extra]
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_as_in_a_terminal, start_new_session=True)  # a batch job's own group
    try:
        deadline = time.time() + 300
        while time.time() < deadline and not (run / ready).exists():
            time.sleep(0.05)
        time.sleep(0.5)
        assert proc.poll() is None, "training finished before it could be stopped; make it longer"
        send(proc)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, err


def tree_snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under ``folder`` (hidden ones too) with its bytes (None for a folder): compare two to show that
    a refused command left the folder as it was."""
    return {p.relative_to(folder).as_posix(): (None if p.is_dir() else p.read_bytes()) for p in sorted(folder.rglob("*"))}


def entries(folder: Path) -> list[str]:
    """The names in ``folder`` (hidden ones too), sorted: what a command wrote there, or that it wrote nothing."""
    return sorted(p.name for p in folder.iterdir())


def in_process_error_line(capsys, argv: list) -> str:
    """Run ``hsicam ARGV`` in-process: exit code 2 and one error line (returned), no traceback."""
    from hsicam.cli import main

    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [x for x in err.strip().splitlines() if x.startswith("hsicam: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]
