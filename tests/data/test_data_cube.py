"""The one cube check, the one band-grid policy and the readers' memory budget (issue #15, #12).

Declared-huge inputs are small files whose *header* announces a cube of gigabytes or terabytes;
every reader must refuse them from the header, before allocating anything.
"""

from __future__ import annotations

import logging
import os
import shutil
import struct
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io
import torch

import hsicam.data.cube as cube_mod
import hsicam.memory as memory_mod
from hsicam.data import read_cube, read_envi, read_hsicam_h5, read_npy, write_cube_h5
from hsicam.data.cube import (
    MEMORY_BUDGET_ENV,
    check_cube,
    check_memory_budget,
    conform_bands,
    memory_budget_bytes,
    resample_cube,
)
from hsicam.data.formats import npy_header, read_cave, read_harvard, read_icvl, read_kaist_exr
from hsicam.errors import ConfigError, InputError
from hsicam.spectral import Bands

GIB = 2**30
WAVES_31 = ", ".join(str(400 + 10 * i) for i in range(31))


def one_line(exc: pytest.ExceptionInfo, *words: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    for w in words:
        assert w.lower() in msg.lower(), msg
    return msg


@pytest.fixture
def no_budget_env(monkeypatch):
    monkeypatch.delenv(MEMORY_BUDGET_ENV, raising=False)


@pytest.fixture
def machine_16gib(monkeypatch, no_budget_env):
    """A deterministic machine: 16 GiB of RAM, no cgroup limit, no address-space limit."""
    monkeypatch.setattr(memory_mod, "_physical_memory_bytes", lambda: 16 * GIB)
    monkeypatch.setattr(memory_mod, "_cgroup_memory_limit_bytes", lambda: None)
    monkeypatch.setattr(memory_mod, "_address_space_left_bytes", lambda: None)


# ------------------------------------------------------------------------------------------------
# Files that declare a huge cube in a few kilobytes
# ------------------------------------------------------------------------------------------------
def huge_h5(path: Path, shape=(31, 7000, 7000)) -> Path:
    """Our HDF5 layout with a chunked, never-written 'cube' dataset: ~40 KB on disk."""
    with h5py.File(path, "w") as f:
        f.create_dataset("cube", shape=shape, dtype="f4", chunks=(1, 64, 64))
        f.create_dataset("bands_nm", data=np.linspace(400.0, 700.0, shape[0]))
    return path


def huge_icvl(path: Path, shape=(31, 7000, 7000)) -> Path:
    """ICVL MAT v7.3 (HDF5, reversed axes) whose 'rad' declares the cube."""
    with h5py.File(path, "w", userblock_size=512) as f:
        f.create_dataset("rad", shape=shape, dtype="f8", chunks=(1, 64, 64))
        f.create_dataset("bands", data=np.linspace(400.0, 700.0, shape[0])[:, None])
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file".ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02IM")
    return path


def huge_npy(path: Path, shape=(31, 7000, 7000)) -> Path:
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": shape})
        fh.write(b"\x00" * 64)
    return path


def huge_envi(folder: Path, samples=7000, lines=7000) -> Path:
    (folder / "big.img").write_bytes(b"\x00" * 1000)
    hdr = folder / "big.hdr"
    hdr.write_text(f"ENVI\nsamples = {samples}\nlines = {lines}\nbands = 31\nheader offset = 0\ndata type = 4\n"
                   f"interleave = bsq\nbyte order = 0\nwavelength = {{{WAVES_31}}}\n")
    return hdr


def huge_mat5(path: Path, h=7000, w=7000) -> Path:
    """A MAT v5 'ref' (Harvard) whose array header was patched to declare h × w × 31 doubles."""
    scipy.io.savemat(path, {"ref": np.ones((4, 5, 31))}, do_compression=False)
    data = bytearray(path.read_bytes())
    i = data.find(struct.pack("<iiiii", 5, 12, 4, 5, 31))
    assert i > 0
    data[i + 8: i + 20] = struct.pack("<iii", h, w, 31)
    path.write_bytes(bytes(data))
    return path


HUGE = {"hdf5": lambda d: huge_h5(d / "big.h5"), "mat73": lambda d: huge_icvl(d / "big73.mat"),
        "npy": lambda d: huge_npy(d / "big.npy"), "envi": huge_envi, "mat5": lambda d: huge_mat5(d / "big5.mat")}


# ------------------------------------------------------------------------------------------------
# The budget itself
# ------------------------------------------------------------------------------------------------
def test_budget_precedence_argument_env_default(machine_16gib, monkeypatch):
    assert memory_budget_bytes() == 4 * GIB  # a quarter of the machine's memory
    monkeypatch.setenv(MEMORY_BUDGET_ENV, "300")
    assert memory_budget_bytes() == 300 * 2**20
    assert memory_budget_bytes(12.5) == int(12.5 * 2**20)  # the argument wins over the environment
    monkeypatch.delenv(MEMORY_BUDGET_ENV)
    monkeypatch.setattr(memory_mod, "_cgroup_memory_limit_bytes", lambda: 2 * GIB)  # a container limit is lower
    assert memory_budget_bytes() == GIB // 2
    monkeypatch.setattr(memory_mod, "_address_space_left_bytes", lambda: 600 * 2**20)  # prlimit --as
    assert memory_budget_bytes() == 300 * 2**20


@pytest.mark.parametrize("bad", ["abc", "0", "-5", "nan", "inf"])
def test_budget_rejects_nonsense(monkeypatch, bad):
    monkeypatch.setenv(MEMORY_BUDGET_ENV, bad)
    with pytest.raises(ConfigError) as exc:
        memory_budget_bytes()
    one_line(exc, MEMORY_BUDGET_ENV, "positive")
    with pytest.raises(ConfigError):
        memory_budget_bytes(float(bad) if bad != "abc" else bad)


def test_budget_default_is_a_fraction_of_this_machine(no_budget_env):
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    assert 0 < memory_budget_bytes() <= total // 4


def test_check_memory_budget_counts_stored_plus_float32():
    # 10 × 100 × 100 float64: 800 000 B stored + 400 000 B of float32 copy = 1.2 MB
    assert check_memory_budget("x", (10, 100, 100), "f8", budget_mb=1.2e6 / 2**20) == 1_200_000
    with pytest.raises(InputError) as exc:
        check_memory_budget("scene.h5", (10, 100, 100), "f8", budget_mb=1.1e6 / 2**20)
    one_line(exc, "scene.h5", "(10, 100, 100)", "float64", "memory budget", MEMORY_BUDGET_ENV)
    # a hostile header: python integers, no overflow
    with pytest.raises(InputError, match="PiB"):
        check_memory_budget("x", (2**40, 2**40, 31), "f8", budget_mb=1e6)


# ------------------------------------------------------------------------------------------------
# Every reader refuses a declared-huge cube from its header, without allocating it
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", list(HUGE))
def test_declared_huge_cube_is_refused_before_allocating(machine_16gib, tmp_path, fmt):
    path = HUGE[fmt](tmp_path)
    assert path.stat().st_size < 100_000  # a small file...
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as exc:
            read_cube(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # ...declaring ~6 GiB (12 GiB for doubles) against the 4 GiB budget of a 16 GiB machine
    one_line(exc, path.name, "7000, 7000", "memory budget of 4 GiB")
    assert peak < 20 * 2**20, f"{peak / 2**20:.0f} MiB allocated while refusing"


def test_budget_argument_on_real_files_of_every_format(tmp_path, no_budget_env):
    """A real (complete) file just above the budget is refused; the same budget + 10 % reads it."""
    rng = np.random.default_rng(0)
    data = rng.random((31, 40, 40)).astype(np.float32)
    bands = Bands.uniform(400, 700, 10)
    need = data.size * (4 + 4)  # float32 stored + float32 result
    files = {}
    files["h5"] = write_cube_h5(tmp_path / "c.h5", data, bands)
    np.save(tmp_path / "c.npy", data)
    files["npy"] = tmp_path / "c.npy"
    from hsicam.data import write_envi

    files["envi"], _ = write_envi(tmp_path / "c.hdr", data, bands)
    scipy.io.savemat(tmp_path / "c.mat", {"ref": np.moveaxis(data, 0, -1)})  # float32 → 'single'
    files["mat5"] = tmp_path / "c.mat"
    with h5py.File(tmp_path / "c73.mat", "w", userblock_size=512) as f:  # ICVL: MAT v7.3, 'rad' H×W×C in MATLAB order
        f["rad"] = np.swapaxes(data, 1, 2)  # as MATLAB stores H×W×C: axes reversed in HDF5
        f["bands"] = bands.centers_nm[:, None]
    with open(tmp_path / "c73.mat", "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file".ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02IM")
    files["mat73"] = tmp_path / "c73.mat"
    for name, path in files.items():
        below, above = 0.999 * need / 2**20, 1.1 * need / 2**20
        with pytest.raises(InputError, match="memory budget") as exc:
            read_cube(path, memory_budget_mb=below)
        one_line(exc, path.name)
        cube, _, _ = read_cube(path, memory_budget_mb=above)
        np.testing.assert_array_equal(cube, data)
    # the explicit readers take the argument too
    with pytest.raises(InputError, match="memory budget"):
        read_hsicam_h5(files["h5"], memory_budget_mb=0.1)
    with pytest.raises(InputError, match="memory budget"):
        read_npy(files["npy"], memory_budget_mb=0.1)
    with pytest.raises(InputError, match="memory budget"):
        read_envi(files["envi"], memory_budget_mb=0.1)
    with pytest.raises(InputError, match="memory budget"):
        read_harvard(files["mat5"], memory_budget_mb=0.1)
    with pytest.raises(InputError, match="memory budget"):
        read_icvl(files["mat73"], memory_budget_mb=0.1)


def test_budget_on_cave_and_exr(tmp_path, no_budget_env):
    import imageio.v3 as iio

    scene = tmp_path / "flowers_ms"
    scene.mkdir()
    for i in range(1, 32):
        iio.imwrite(scene / f"flowers_ms_{i:02d}.png", np.full((30, 20), 1000 * i, np.uint16))
    need = 31 * 30 * 20 * 8
    with pytest.raises(InputError, match="memory budget") as exc:
        read_cave(scene, memory_budget_mb=0.99 * need / 2**20)
    one_line(exc, "flowers_ms", "(31, 30, 20)")
    assert read_cube(scene, memory_budget_mb=1.1 * need / 2**20)[0].shape == (31, 30, 20)
    # a PNG header that declares 10^6 × 10^6: refused from the header
    big = tmp_path / "big_ms"
    shutil.copytree(scene, big)
    png = bytearray((big / "flowers_ms_05.png").read_bytes())
    png[16:24] = struct.pack(">II", 10**6, 10**6)
    (big / "flowers_ms_05.png").write_bytes(bytes(png))
    with pytest.raises(InputError, match="memory budget"):
        read_cave(big)

    OpenEXR = pytest.importorskip("OpenEXR")
    if not hasattr(OpenEXR, "File"):
        pytest.skip("openexr < 3.3")
    channels = {f"{w}nm": OpenEXR.Channel(np.ones((30, 20), np.float32)) for w in range(400, 701, 10)}
    path = tmp_path / "s.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))
    with pytest.raises(InputError, match="memory budget") as exc:
        read_kaist_exr(path, memory_budget_mb=0.99 * need / 2**20)
    one_line(exc, "s.exr", "(31, 30, 20)")
    assert read_cube(path, memory_budget_mb=1.1 * need / 2**20)[0].shape == (31, 30, 20)


def test_npy_header_and_object_arrays(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((3, 4, 5), np.uint16))
    assert npy_header(tmp_path / "a.npy") == ((3, 4, 5), np.dtype("u2"))
    np.save(tmp_path / "o.npy", np.empty((3, 4, 5), dtype=object), allow_pickle=True)
    with pytest.raises(InputError) as exc:
        read_cube(tmp_path / "o.npy")
    one_line(exc, "o.npy", "objects")


@pytest.mark.skipif(shutil.which("prlimit") is None, reason="prlimit (util-linux) is not installed")
def test_declared_huge_inputs_under_an_address_space_limit(tmp_path, no_budget_env):
    """The issue's attack: under `prlimit --as` (1.5 GB) each declared-huge file is one line from
    the memory budget, exit 2, never a MemoryError or a traceback."""
    paths = [str(make(tmp_path)) for make in HUGE.values()]
    script = textwrap.dedent("""
        import sys
        from hsicam.data import read_cube
        from hsicam.errors import HsicamError
        for p in sys.argv[1:]:
            try:
                read_cube(p)
            except HsicamError as exc:
                print(exc)
            else:
                print("read without error:", p)
        sys.exit(2)
    """)
    env = {k: v for k, v in os.environ.items() if k != MEMORY_BUDGET_ENV}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(cube_mod.__file__).parents[2]), env.get("PYTHONPATH", "")])
    env["OMP_NUM_THREADS"] = "1"
    res = subprocess.run(["prlimit", "--as=1500000000", sys.executable, "-c", script, *paths],
                         capture_output=True, text=True, timeout=120, env=env)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "Traceback" not in res.stderr and "MemoryError" not in res.stderr + res.stdout, res.stderr[-2000:]
    lines = res.stdout.strip().splitlines()
    assert len(lines) == len(paths), res.stdout
    for p, line in zip(paths, lines):
        assert line.startswith(p) and "memory budget" in line, line


# ------------------------------------------------------------------------------------------------
# The cube check
# ------------------------------------------------------------------------------------------------
def test_check_cube_accepts_and_converts():
    x = np.arange(24, dtype=np.uint16).reshape(2, 3, 4)
    out = check_cube(x, "x", bands=Bands.from_centers([500.0, 600.0]))
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_array_equal(out, x)
    t = torch.ones(3, 2, 2, dtype=torch.float64, requires_grad=True)
    assert check_cube(t, "tensor").dtype == np.float32


@pytest.mark.parametrize("bad, words", [
    (np.ones((2, 3, 4), np.complex64), ["complex"]),
    (torch.ones(2, 3, 4, dtype=torch.complex64), ["complex"]),
    (np.full((2, 3, 4), "a"), ["data type"]),
    (np.ones((2, 3)), ["3-D"]),
    (np.ones((0, 3, 4)), ["empty"]),
    (np.where(np.eye(4)[None] > 0, np.nan, 1.0), ["NaN/Inf"]),
    (np.full((1, 2, 2), 1e39), ["NaN/Inf"]),  # overflows float32
    (-np.ones((2, 3, 4)), ["negative", "-1"]),
])
def test_check_cube_refuses(bad, words):
    with pytest.raises(InputError) as exc:
        check_cube(bad, "scene.npy")
    one_line(exc, "scene.npy", *words)


def test_check_cube_band_grid():
    with pytest.raises(InputError) as exc:
        check_cube(np.ones((3, 2, 2)), "s.h5", bands=Bands.uniform(400, 700, 10))
    one_line(exc, "s.h5", "3 bands", "31")
    with pytest.raises(InputError, match="Bands object"):
        check_cube(np.ones((3, 2, 2)), "s.h5", bands=[400.0, 500.0, 600.0])


def test_check_cube_allow_negative_clips_a_copy():
    x = np.array([[[-0.5, 1.0]]], np.float32)
    out = check_cube(x, allow_negative=True)
    assert out.tolist() == [[[0.0, 1.0]]] and x[0, 0, 0] == -0.5  # the caller's array is untouched


def test_readers_apply_the_check(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((3, 4, 5), np.complex128))
    with pytest.raises(InputError) as exc:
        read_cube(tmp_path / "c.npy")
    one_line(exc, "c.npy", "complex")
    with pytest.raises(InputError) as exc:
        read_cube(tmp_path / "c.npy", bands=Bands.uniform(400, 700, 10))
    one_line(exc, "c.npy", "3 bands", "31")


# ------------------------------------------------------------------------------------------------
# The band-grid policy
# ------------------------------------------------------------------------------------------------
def linear_cube(bands: Bands, a=0.2, slope=0.003) -> np.ndarray:
    spectrum = a + slope * (bands.centers_nm - 400.0)
    return (spectrum[:, None, None] * np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])).astype(np.float32)


def test_conform_bands_same_grid_is_untouched(caplog):
    b = Bands.uniform(420, 720, 10)
    x = linear_cube(b)
    with caplog.at_level(logging.INFO, logger="hsicam.data.cube"):
        assert conform_bands(x, b, Bands.paper(), "s.h5") is x
    assert not caplog.records


def test_conform_bands_resamples_with_a_note(caplog):
    src, cam = Bands.uniform(400, 700, 10), Bands.uniform(420, 700, 20)
    with caplog.at_level(logging.INFO, logger="hsicam.data.cube"):
        out = conform_bands(linear_cube(src), src, cam, "scene.mat")
    assert out.dtype == np.float32 and out.shape == (15, 2, 3) and out.flags.c_contiguous
    np.testing.assert_allclose(out, linear_cube(cam), rtol=1e-6)
    (rec,) = caplog.records
    assert "scene.mat" in rec.getMessage() and "400-700 nm" in rec.getMessage() and "420-700 nm" in rec.getMessage()
    # the dataset primitive is the same policy without the note
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="hsicam.data.cube"):
        np.testing.assert_array_equal(resample_cube(linear_cube(src), src, cam), out)
    assert not caplog.records


def test_conform_bands_on_torch_batches_keeps_dtype_and_gradient():
    src, cam = Bands.uniform(400, 700, 10), Bands.from_centers([455.0, 512.5, 640.0])
    x = torch.tensor(np.stack([linear_cube(src), 2 * linear_cube(src)]), dtype=torch.float64, requires_grad=True)
    out = conform_bands(x, src, cam, "batch")
    assert out.shape == (2, 3, 2, 3) and out.dtype == torch.float64
    np.testing.assert_allclose(out.detach().numpy()[0], linear_cube(cam), rtol=1e-6)
    out.sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_conform_bands_refuses_only_extrapolation():
    src = Bands.uniform(400, 700, 10)
    x = linear_cube(src)
    for cam in (Bands.paper(), Bands.uniform(390, 690, 10)):  # beyond either end
        with pytest.raises(InputError) as exc:
            conform_bands(x, src, cam, "ICVL/scene.mat")
        one_line(exc, "ICVL/scene.mat", f"{cam.min_nm:g}-{cam.max_nm:g} nm", "400-700 nm", "extrapolation")
    with pytest.raises(InputError) as exc:
        conform_bands(x[:5], src, Bands.uniform(420, 700, 10), "s.npy")
    one_line(exc, "s.npy", "5 bands", "31")
    # narrower or coarser grids inside the data's range are fine
    assert conform_bands(x, src, Bands.from_centers([400.0, 700.0]), "s").shape == (2, 2, 3)
