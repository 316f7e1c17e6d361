"""Real-capture benchmark (issue 7): reconstruct a 2048×2048 raw capture in tiles on CPU.

Builds a run folder with the paper camera and the default RDN (31 bands; untrained weights — time
and memory do not depend on the weight values), writes a 12-bit-in-16-bit TIFF capture with a
dark frame and a flat field, and runs ``hsicam reconstruct`` (black level, dark, flat averaged
over the CFA period, exposure normalisation, tiles) in a child process (the console script beside this Python, else
``python -m hsicam``: ``timing.hsicam_command``). Reports the wall time and
the child's peak resident memory (``ru_maxrss`` from ``os.wait4``) against the 4 GiB target, and ``threads``, the
torch thread count a child with the same environment runs (an int: ``--threads``, else ``OMP_NUM_THREADS`` or
torch's default).
Prints one JSON object. A reconstruct that fails measured nothing: ``wall_s``, ``megapixels_per_s`` and
``within_target`` are then null, ``exit_code`` and ``error_tail`` (its output's tail) say why, and the benchmark
exits 1.

Run: ``.venv/bin/python benchmarks/bench_capture.py [--size 2048] [--tile 512] [--threads N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from timing import hsicam_command, positive_int

TARGET_BYTES = 4 * 2**30


def make_run(run: Path, cfg) -> dict:
    """A run folder at ``run`` (made here) of the config ``cfg`` with its untrained weights; the facts the JSON
    reports of it (bands, network size, halo)."""
    from hsicam.config import dump_yaml
    from hsicam.runs.checkpoint import save_weights
    from hsicam.models import CameraSystem

    run.mkdir(parents=True)
    (run / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    model = CameraSystem.from_config(cfg)
    save_weights(run / "model.safetensors", model, model.bands)
    n_params = sum(p.numel() for p in model.net.parameters())
    return {"bands": len(model.bands), "net_params": n_params, "halo_px": model.context_px,
            "model": {"kind": cfg.model.kind,
                      **{k: getattr(cfg.model.rdn, k) for k in ("blocks", "features", "growth", "layers_per_block")}}}


def make_capture(d: Path, size: int) -> None:
    import tifffile

    rng = np.random.default_rng(0)
    black = 64
    yy, xx = np.mgrid[0:size, 0:size] / size
    vignette = 1.0 - 0.3 * ((yy - 0.5) ** 2 + (xx - 0.5) ** 2)
    dark = (black + rng.integers(0, 6, (size, size))).astype(np.uint16)
    scene = 0.2 + 0.6 * rng.random((size // 16 + 1, size // 16 + 1))
    scene = np.kron(scene, np.ones((16, 16)))[:size, :size]
    raw = np.clip(dark + scene * vignette * (4095 - black), 0, 4095).astype(np.uint16)
    flat = np.clip(black + vignette * 3000 + rng.normal(0, 5, (size, size)), 0, 4095).astype(np.uint16)
    tifffile.imwrite(d / "capture.tif", raw)
    tifffile.imwrite(d / "dark.tif", dark)
    tifffile.imwrite(d / "flat.tif", flat)


#: How much of a child's output (its stdout and stderr, interleaved) the benchmark keeps: the tail.
TAIL_CHARS = 800


def run_child(cmd: list[str], env: dict) -> tuple[float, int, int, str]:
    """(wall s, peak RSS bytes, exit code, output tail) of a child process. Its stdout and stderr go to one temporary
    file, not a pipe: a pipe that nobody reads while ``os.wait4`` waits (for the child's ``ru_maxrss``) would block a
    child writing more than the pipe's buffer (64 KiB) for ever."""
    with tempfile.TemporaryFile() as log:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        size = log.seek(0, os.SEEK_END)
        log.seek(max(0, size - 4 * TAIL_CHARS))  # the tail only (UTF-8: at most 4 bytes a character)
        tail = log.read().decode(errors="replace")[-TAIL_CHARS:]
    rss = usage.ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    return wall, rss, proc.returncode, tail


def child_threads(tail: str) -> int | None:
    """The torch thread count the imports-only child printed on its last line (None if it printed none)."""
    lines = tail.strip().splitlines()
    return int(lines[-1]) if lines and lines[-1].strip().isdigit() else None


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=positive_int, default=2048, help="capture side (px)")
    ap.add_argument("--tile", type=int, default=None, help="tile side (px; default: reconstruct's own default)")
    ap.add_argument("--threads", type=positive_int, default=None,
                    help="OMP/torch threads of the child (default: inherited)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override for the run")
    args = ap.parse_args()
    from hsicam.config import load_config
    from hsicam.errors import HsicamError

    try:  # a bad --set is one usage line, as the hsicam command says it, not a ConfigError traceback
        cfg = load_config(None, args.overrides)
    except (HsicamError, OSError) as exc:
        ap.error(str(exc))
    with tempfile.TemporaryDirectory(prefix="hsicam-bench-capture-") as tmp:
        d = Path(tmp)
        try:  # a config that loads but builds no model (--set model.kind=nosuch): one usage line, before any work
            facts = make_run(d / "run", cfg)
        except HsicamError as exc:
            ap.error(str(exc))
        make_capture(d, args.size)
        env = dict(os.environ)
        if args.threads:
            env["OMP_NUM_THREADS"] = str(args.threads)
        cmd = [*hsicam_command(), "reconstruct", str(d / "capture.tif"), "--run", str(d / "run"), "--out", str(d / "cube.h5"),
               "--black-level", "64", "--white-level", "4095", "--dark", str(d / "dark.tif"), "--flat", str(d / "flat.tif"),
               "--flat-mode", "cfa", "--exposure-s", "0.02", "--reference-exposure-s", "0.02",
               *(["--tile", str(args.tile)] if args.tile else [])]
        wall, rss, rc, tail = run_child(cmd, env)
        # the same child doing nothing but start up and load the run: the fixed part of the memory; it prints the
        # torch threads a child with this environment runs (hsicam sets none of its own)
        base_wall, base_rss, base_rc, base_tail = run_child(
            [sys.executable, "-c", "import torch, hsicam.cli, hsicam.models; print(torch.get_num_threads())"], env)
        out_bytes = (d / "cube.h5").stat().st_size if (d / "cube.h5").exists() else None
    ok = rc == 0  # a reconstruct that failed measured nothing: its time, rate and verdict are null, the exit non-zero
    result = {
        "benchmark": "reconstruct a raw capture in tiles (hsicam reconstruct, CPU)",
        "capture_px": [args.size, args.size],
        "tile_px": args.tile or "reconstruct's default (hsicam.engine.inference.default_tile_px)",
        **facts,
        "exit_code": rc,
        "wall_s": round(wall, 2) if ok else None,
        "megapixels_per_s": round(args.size**2 / 1e6 / wall, 4) if ok else None,
        "peak_rss_bytes": rss,
        "peak_rss_gib": round(rss / 2**30, 3),
        "target_gib": TARGET_BYTES / 2**30,
        "within_target": rss < TARGET_BYTES if ok else None,
        "interpreter_and_imports_rss_gib": round(base_rss / 2**30, 3) if base_rc == 0 else None,
        "output_h5_bytes": out_bytes,
        "threads": child_threads(base_tail) if base_rc == 0 else None,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
    }
    if not ok:
        result["error_tail"] = tail
    if base_rc != 0:
        result["imports_exit_code"], result["imports_error_tail"] = base_rc, base_tail
    print(json.dumps(result, indent=2))
    if not ok or base_rc != 0:
        failed = f"hsicam reconstruct exited {rc}" if not ok else f"the imports-only child exited {base_rc}"
        print(f"bench_capture: {failed}; nothing measured (the JSON's error tails say why)", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
