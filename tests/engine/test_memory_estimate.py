"""The memory estimate that decides whether ``hsicam reconstruct`` refuses an image
(:func:`hsicam.engine.inference.reconstruction_memory_bytes`): its arithmetic, and the peak it estimates, measured."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from hsicam.engine.inference import (RECONSTRUCT_BASE_BYTES, RECONSTRUCT_FIXED_BYTES, STEP_BAND_VALUES,
                                     STEP_FRAME_VALUES, WINDOW_CUBES, reconstruct_tiled, reconstruction_memory_bytes,
                                     reconstruction_working_bytes)


class _Network:
    """A reconstruction of 3 bands that records the windows reconstruct_tiled cuts."""

    context_px = 40

    def __init__(self):
        self.windows = []

    def __call__(self, x):
        self.windows.append(tuple(x.shape[-2:]))
        return x.expand(-1, 3, -1, -1)


def test_the_window_is_the_largest_one_the_tiling_cuts_within_the_image():
    """A 100² image with a 40 px halo is one window of 100², not (512 + 80)²: the estimate counted a tile and two
    halos beyond the image (the shipped camera's 128² image: 0.91 GB estimated, 0.45 GB peak)."""
    for h, w, tile in ((100, 100, None), (100, 300, 64), (37, 500, 200)):
        net = _Network()
        reconstruct_tiled(net, torch.rand(1, 1, h, w), tile_px=tile)
        largest = max(a * b for a, b in net.windows)
        expect = RECONSTRUCT_FIXED_BYTES + 4 * 3 * (h * w + WINDOW_CUBES * largest)
        assert reconstruction_working_bytes(net, 3, h, w, tile) == expect
        assert reconstruction_memory_bytes(net, 3, h, w, tile) == RECONSTRUCT_BASE_BYTES + expect


def test_the_steps_count_their_frame_and_one_band_of_rows():
    """With consistency steps: the frame (the image and ``frame_px`` a side) in whole, and one band of rows with its
    halo, counted here by hand for a 64-row image (one band) and a 1024-wide one (bands of 256 rows)."""
    net = _Network()

    def steps(sensor, x, origin=(0, 0), on_step=None):
        return x

    def rec(x, origin=(0, 0)):
        return net(x)

    rec.before_steps, rec.steps = net, steps
    steps.count, steps.tv, steps.frame_px = 12, True, 5
    (fc, fp), (bc, bp) = STEP_FRAME_VALUES["tv"], STEP_BAND_VALUES["tv"]
    h, w = 64, 96  # one band: the frame twice
    frame = (h + 10) * (w + 10)
    work = (fc * 3 + fp) * frame + (bc * 3 + bp) * frame
    assert work > WINDOW_CUBES * 3 * h * w
    assert reconstruction_working_bytes(rec, 3, h, w) == RECONSTRUCT_FIXED_BYTES + 4 * (3 * h * w + work)
    h, w = 1000, 1024  # 2**18 // 1024 = 256-row bands: a 1010-row frame in 3 bands of 337 rows, each ± 14 rows of halo
    halo = 2 * 5 + 2 + 2  # twice the margin, the Wiener window's half, the TV step's reach
    work = (fc * 3 + fp) * (h + 10) * (w + 10) + (bc * 3 + bp) * (337 + 2 * halo) * (w + 10)
    assert reconstruction_working_bytes(rec, 3, h, w) == RECONSTRUCT_FIXED_BYTES + 4 * (3 * h * w + work)
    steps.tv = False  # plain Landweber steps
    (fc, fp), (bc, bp) = STEP_FRAME_VALUES["landweber"], STEP_BAND_VALUES["landweber"]
    work = (fc * 3 + fp) * (h + 10) * (w + 10) + (bc * 3 + bp) * (337 + 2 * (halo - 2)) * (w + 10)
    assert reconstruction_working_bytes(rec, 3, h, w) == RECONSTRUCT_FIXED_BYTES + 4 * (3 * h * w + work)


_MEASURE = textwrap.dedent("""
    import json, sys
    import torch
    torch.set_num_threads(1)
    from hsicam.memory import keep_freed_memory
    keep_freed_memory()  # as the hsicam command does
    from hsicam.config import load_config
    from hsicam.engine.inference import reconstruct_tiled, reconstruction_working_bytes
    from hsicam.models.system import CameraSystem
    h, w = int(sys.argv[1]), int(sys.argv[2])
    torch.manual_seed(0)
    model = CameraSystem.from_config(load_config("tiny", overrides=sys.argv[3:])).eval()
    rec = model.reconstructor()
    sensor = torch.rand(1, 1, h, w) * 0.6 + 0.2
    def high_water_kib():  # this process's own peak (VmHWM): ru_maxrss keeps a larger parent's across the exec
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:"))
    before = high_water_kib()
    reconstruct_tiled(rec, sensor)
    peak = high_water_kib()
    print(json.dumps({"measured": (peak - before) * 1024,
                      "estimate": reconstruction_working_bytes(rec, len(model.bands), h, w)}))
""")


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/status's VmHWM, glibc's allocator")
@pytest.mark.parametrize("h, w, overrides", [
    (768, 768, ()),  # the network alone, in four windows
    (384, 640, ("model.consistency.iterations=12", "model.consistency.spectral_prior=4.0",
                "model.consistency.tv_weight=0.03")),  # the shipped camera's 12 TV steps, one band of rows
    (768, 768, ("model.consistency.iterations=12", "model.consistency.tv_weight=0.03")),  # in bands of rows
])
def test_the_estimate_covers_the_measured_peak_of_a_fresh_process(h, w, overrides):
    """The peak resident memory a reconstruction adds, in a fresh process (the model and the input made first),
    is never above the estimate, and the estimate is at most 1.5× it (before session 60: 0.8–2.0×)."""
    import hsicam

    src = str(Path(hsicam.__file__).parents[1])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run([sys.executable, "-c", _MEASURE, str(h), str(w), *overrides], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["measured"] <= got["estimate"] <= 1.5 * got["measured"], got
