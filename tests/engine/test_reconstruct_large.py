"""Full-size captures (2048² to 4096² px, session 41): what ``reconstruct`` holds beyond the cube it returns
stays a fixed tile's working set (one window and its reconstruction at a time), writing the cube and
its preview adds little to it (the preview rendered in parts, the finiteness check band by band, the
ENVI data written from the array itself), and the free disk space is checked for the real output
before the reconstruction starts."""

from __future__ import annotations

import re
import shutil
import tracemalloc
import weakref

import numpy as np
import pytest
import torch
from cli_helpers import error_line, run_cli_in_process

import hsicam.cli.reconstruct as rc
from hsicam.color import cube_to_srgb, srgb_preview
from hsicam.data.formats import read_cube, read_envi
from hsicam.engine.inference import reconstruct_tiled
from hsicam.spectral import Bands

BANDS = Bands.uniform(400.0, 700.0, 10.0)


def test_tiles_hold_one_window_reconstruction_at_a_time():
    """The previous tile's reconstruction (a window's whole cube, 250 MB for pretrained:standard's
    default tile) is freed before the next window is computed: it used to stay alive through it."""
    alive: list[weakref.ref] = []
    held = []

    def fn(window: torch.Tensor) -> torch.Tensor:
        held.append(sum(r() is not None for r in alive))
        part = window.expand(-1, 3, -1, -1) * 2.0
        alive.append(weakref.ref(part))
        return part

    fn.context_px = 2
    img = torch.rand(1, 1, 40, 30)
    out = reconstruct_tiled(fn, img, tile_px=16)
    assert len(held) == 6 and held == [0] * 6, held
    torch.testing.assert_close(out, img.expand(-1, 3, -1, -1) * 2.0, rtol=0, atol=0)


def _same_preview(a, b):
    """Previews equal but for values on an 8-bit rounding boundary that a BLAS kernel chosen for another
    row count may move by one (float32 colour matrices): at most one level, on a handful of values."""
    d = np.abs(a.astype(np.int16) - b.astype(np.int16))
    assert d.max() <= 1 and (d > 0).mean() < 1e-3, (int(d.max()), float((d > 0).mean()))


def _whole_preview(cube: np.ndarray) -> np.ndarray:
    """The preview as it was computed before session 41: the whole cube at once."""
    rgb = np.moveaxis(cube_to_srgb(torch.from_numpy(cube), BANDS).numpy(), 0, -1)
    return np.round(np.clip(rgb.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


def test_the_preview_is_rendered_in_parts_with_the_whole_cubes_values(monkeypatch):
    cube = np.random.default_rng(0).uniform(0.0, 1.3, (31, 123, 77)).astype(np.float32)
    calls = []

    def spy(part, bands):
        calls.append(part.shape[-2] * part.shape[-1])
        return cube_to_srgb(part, bands)

    monkeypatch.setattr("hsicam.color.cube_to_srgb", spy)
    preview = srgb_preview(cube, BANDS, chunk_px=1000)
    assert preview.dtype == np.uint8 and preview.shape == (123, 77, 3)
    assert len(calls) == 11 and max(calls) <= 1000 and sum(calls) == 123 * 77  # 12 rows a part
    _same_preview(preview, _whole_preview(cube))


@pytest.mark.parametrize("suffix", [".h5", ".hdr"])
def test_writing_a_cube_and_its_preview_holds_little_beyond_the_cube(tmp_path, monkeypatch, suffix):
    """numpy's and Python's allocations while the cube (31 × 512 × 512, 32.5 MB) and its preview are written:
    under a tenth of the cube (they were 0.45× for .h5: the preview's float64 copies and a whole-cube finiteness
    mask; 1.2× for ENVI, whose data was copied into one bytes object), the preview's exposure (the luminance of
    every pixel, float32) included; torch's (the preview's colour conversion) are bounded by the part size, which the
    test above checks. The files read back as written."""
    monkeypatch.setattr("hsicam.color.PREVIEW_CHUNK_PX", 1 << 14)
    cube = np.random.default_rng(1).uniform(0.0, 1.0, (31, 512, 512)).astype(np.float32)
    out = tmp_path / f"cube{suffix}"
    rc.write_cube_file(tmp_path / f"warm{suffix}", cube[:, :8, :8], BANDS, {})  # imports and caches: not counted
    tracemalloc.start()
    try:
        exposure = rc.write_cube_file(out, cube, BANDS, {"source": "test"})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 0.1 * cube.nbytes, f"{peak / cube.nbytes:.2f}× the cube"
    back = read_cube(out) if suffix == ".h5" else read_envi(out)
    np.testing.assert_array_equal(back[0], cube)
    import imageio.v3 as iio

    _same_preview(iio.imread(tmp_path / "cube_rgb.png"), _whole_preview(cube * np.float32(exposure)))  # exposed


def test_the_room_needed_is_the_real_output():
    """A 4096² capture's 31-band float32 cube is 2.08 GB: the check asks for that, its preview and a little
    more, not less."""
    need = rc.cube_file_bytes(31, 4096, 4096)
    assert 31 * 4096 * 4096 * 4 + 3 * 4096 * 4096 <= need <= 31 * 4096 * 4096 * 4 + 3 * 4096 * 4096 + (2 << 20)


def test_reconstruct_checks_the_free_space_before_the_work(tmp_path, monkeypatch):
    sensor = tmp_path / "capture.npy"
    np.save(sensor, np.random.default_rng(0).uniform(0.2, 0.8, (64, 80)).astype(np.float32))
    usage = shutil.disk_usage(tmp_path)
    need = rc.cube_file_bytes(31, 64, 80)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=need + (1 << 26) - 1))

    def never(*args, **kwargs):
        raise AssertionError("the reconstruction started")

    monkeypatch.setattr("hsicam.engine.inference.reconstruct_tiled", never)
    out = tmp_path / "out" / "cube.h5"
    res = run_cli_in_process("reconstruct", str(sensor), "--run", "pretrained:standard", "--out", str(out))
    line = error_line(res)
    assert re.fullmatch(rf"hsicam: error: {re.escape(str(out))}: the cube of 31 bands × 64×80 px and its preview "
                        r"need about 1\.\d+ MiB, and 64 MiB more is kept free beyond it \(65\.\d+ MiB in all\), but "
                        r"that disk has 65\.\d+ MiB free; free some space or choose an "
                        r"--out on a larger disk", line), line
    assert not out.exists() and not (out.parent.exists() and any(out.parent.iterdir()))  # nothing written


def test_reconstruct_refuses_an_image_whose_whole_image_steps_would_not_fit_in_memory(tmp_path, monkeypatch):
    """The consistency steps go over the whole image, so the peak grows with it whatever the tile: an
    8000² capture started, then was killed (or ended in torch's allocator traceback). Now the estimate
    (:func:`reconstruction_memory_bytes`) is checked against the memory the process may take first."""
    from hsicam.engine.inference import reconstruction_memory_bytes
    from hsicam.runs.folder import load_run

    _, model = load_run("pretrained:standard")
    rec = model.reconstructor()
    small, big = (reconstruction_memory_bytes(rec, 31, n, n) for n in (256, 2048))
    assert small < big and big - small >= 7 * 4 * 31 * (2048**2 - 256**2)  # ≥ 7 whole cubes with the TV steps
    model.consistency = type(model.consistency)(iterations=0)  # the network alone: one whole cube
    alone = reconstruction_memory_bytes(model.reconstructor(), 31, 2048, 2048)
    assert alone < big - 5 * 4 * 31 * 2048**2

    sensor = tmp_path / "capture.npy"
    np.save(sensor, np.random.default_rng(0).uniform(0.2, 0.8, (1024, 1024)).astype(np.float32))

    def never(*args, **kwargs):
        raise AssertionError("the reconstruction started")

    monkeypatch.setattr("hsicam.engine.inference.reconstruct_tiled", never)
    # the disk's free space, checked first (the cube's 128 MiB + 64 MiB kept free), is not what this test is about: on
    # a disk that other jobs had filled it refused for the disk instead (that check has a test of its own, above)
    monkeypatch.setattr("hsicam.io.free_space_short", lambda *args, **kwargs: None)
    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "1500")
    out = tmp_path / "cube.h5"
    line = error_line(run_cli_in_process("reconstruct", str(sensor), "--run", "pretrained:standard", "--out", str(out)))
    found = re.fullmatch(rf"hsicam: error: {re.escape(str(sensor))}: reconstructing 1024×1024 px into 31 bands takes "
                         r"about [\d.]+ GiB of memory .* more than the limit HSICAM_MEMORY_BUDGET_MB sets \(1.46 GiB\); "
                         r"reconstruct it in parts of at most about (\d+)×\1 px .*", line)
    assert found, line
    part = int(found.group(1))  # the largest square part that fits the limit, by the same estimate
    assert reconstruction_memory_bytes(rec, 31, part, part) <= 1500 * 2**20 < reconstruction_memory_bytes(rec, 31, part + 1, part + 1)
    assert not out.exists()


def test_reconstructs_refusal_names_the_address_space_limit_not_the_machines_memory(tmp_path, monkeypatch):
    """Under ``ulimit -v 4000000`` (2.95 GiB left) on a 23 GB machine, reconstruct said "more than this machine's
    memory (2.95 GiB)": the limit that bites is the process's address space, and the line now says so."""
    import hsicam.memory as mem

    monkeypatch.delenv(mem.MEMORY_BUDGET_ENV, raising=False)
    monkeypatch.setattr(mem, "_physical_memory_bytes", lambda: 23 * 2**30)
    monkeypatch.setattr(mem, "_cgroup_memory_limit_bytes", lambda: None)
    # the PSF plan (one allocation: half of what is left) fits, the 512² reconstruction (1.4 GiB) does not
    monkeypatch.setattr(mem, "_address_space_left_bytes", lambda: 2**30)
    monkeypatch.setattr("hsicam.io.free_space_short", lambda *args, **kwargs: None)
    sensor = tmp_path / "capture.npy"
    np.save(sensor, np.random.default_rng(0).uniform(0.2, 0.8, (512, 512)).astype(np.float32))
    out = tmp_path / "cube.h5"
    line = error_line(run_cli_in_process("reconstruct", str(sensor), "--run", "pretrained:standard", "--out", str(out)))
    assert re.fullmatch(rf"hsicam: error: {re.escape(str(sensor))}: reconstructing 512×512 px into 31 bands takes about "
                        r"[\d.]+ GiB of memory .*, more than the address space this process has left under its "
                        r"ulimit -v \(1 GiB\); reconstruct it in parts .*", line), line
    assert not out.exists()


def test_torch_out_of_memory_is_one_line():
    from hsicam.cli import error_line as line_of

    cpu = RuntimeError("[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: can't allocate memory: you "
                       "tried to allocate 7936000000 bytes. Error code 12 (Cannot allocate memory)")
    assert line_of(cpu).startswith("out of memory ([enforce fail") and "smaller image or in parts" in line_of(cpu)
    assert line_of(torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")).startswith(
        "out of memory (CUDA out of memory.")
    assert line_of(RuntimeError("a bug")) is None  # any other RuntimeError stays a traceback


def test_an_image_of_one_tile_shows_the_steps_progress(monkeypatch):
    """An image that fits one tile was reconstructed in one call, without the steps' progress (a 719² capture:
    43 s of silence); it now goes through the tiles and the steps as a larger one does, to the same cube."""
    import hsicam.progress as progress
    from hsicam.runs.folder import load_run

    _, model = load_run("pretrained:standard")
    rec = model.reconstructor()
    sensor = torch.from_numpy(np.random.default_rng(1).uniform(0.2, 0.8, (1, 1, 48, 40)).astype(np.float32))
    counted = []
    real = progress.Progress

    class Counting(real):
        def __init__(self, total, what, unit, show=None):
            counted.append((what, total))
            super().__init__(total, what, unit, show=False)

    monkeypatch.setattr(progress, "Progress", Counting)
    got = reconstruct_tiled(rec, sensor)
    assert ("consistency steps", rec.steps.count) in counted
    torch.testing.assert_close(got, rec(sensor), rtol=0, atol=1e-5)
