"""Robustness of every reader and of the CLI (hypothesis): truncated files, corrupt bytes, empty
files, odd shapes, NaN/Inf, huge declared sizes. Each outcome is either a sane result or one
:class:`InputError` — never another exception, never a hang (SIGALRM guard + hypothesis
deadline), never a partial or temporary output file.
"""

from __future__ import annotations

import contextlib
import signal
import struct
import zlib
from datetime import timedelta
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cli_helpers import assert_clean_error, run_cli_in_process
from fab_runs import fab_run  # noqa: F401 - shared fixture
from hsicam.data import read_cube, write_cube_h5, write_envi
from hsicam.data.images import MAX_IMAGE_PIXELS, read_capture, read_image_2d
from hsicam.errors import InputError
from hsicam.spectral import Bands

FUZZ = settings(max_examples=12, deadline=timedelta(seconds=5), derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
BANDS = Bands.uniform(450, 650, 50)

def write_mat73(path: Path, variables: dict[str, np.ndarray]) -> None:
    """MATLAB v7.3 MAT-file: HDF5 with the 512-byte MAT header in the user block; an H×W×C MATLAB
    array is an HDF5 dataset of shape (C, W, H)."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            f.create_dataset(name, data=np.ascontiguousarray(np.asarray(value).T))
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write((text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM").ljust(512, b"\x00"))


mutations = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("corrupt"), st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), min_size=1, max_size=8)),
)


def mutate(data: bytes, mutation) -> bytes:
    kind, arg = mutation
    if kind == "truncate":
        return data[: int(arg * len(data))]
    out = bytearray(data)
    for pos, value in arg:
        if out:
            out[min(int(pos * len(out)), len(out) - 1)] = value
    return bytes(out)


@contextlib.contextmanager
def time_limit(seconds: int = 10):
    """Fail (instead of hanging) when the body runs longer than ``seconds``."""

    def handler(signum, frame):
        raise TimeoutError(f"hung for more than {seconds} s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def outcome(fn, path) -> str:
    """'ok' (a sane result) or 'error' (one InputError whose message is one line and names the file)."""
    with time_limit():
        try:
            res = fn(path)
        except InputError as exc:
            assert "\n" not in str(exc), str(exc)
            return "error"
    arr = res[0] if isinstance(res, tuple) else getattr(res, "data", res)
    arr = np.asarray(arr)
    assert arr.ndim in (2, 3) and arr.size > 0 and np.all(np.isfinite(arr))
    if isinstance(res, tuple):  # a cube
        assert arr.dtype == np.float32 and arr.ndim == 3 and arr.min() >= 0 and len(res[1]) == arr.shape[0]
    return "ok"


@pytest.fixture(scope="module")
def originals(tmp_path_factory) -> dict[str, bytes]:
    """One small valid file per format, as bytes."""
    import imageio.v3 as iio
    import tifffile

    d = tmp_path_factory.mktemp("orig")
    rng = np.random.default_rng(0)
    cube = (rng.random((5, 9, 7)) + 0.01).astype(np.float32)
    write_cube_h5(d / "a.h5", cube, BANDS)
    write_envi(d / "e.hdr", cube, BANDS)
    np.save(d / "n.npy", cube)
    scipy.io.savemat(d / "h.mat", {"ref": np.ones((9, 7, 31))})
    write_mat73(d / "i.mat", {"rad": np.ones((9, 7, 31)), "bands": np.arange(400, 701, 10.0)})
    img = (rng.random((20, 30)) * 65535).astype(np.uint16)
    iio.imwrite(d / "s.png", img)
    tifffile.imwrite(d / "s.tif", img)
    tifffile.imwrite(d / "z.tif", img, compression="zlib")
    np.save(d / "s.npy", img)
    out = {p.name: p.read_bytes() for p in d.iterdir()}
    try:
        import OpenEXR

        if hasattr(OpenEXR, "File"):
            ch = {f"w{w}nm": OpenEXR.Channel(np.ones((16, 16), np.float32)) for w in (500, 600)}
            with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, ch) as f:
                f.write(str(d / "x.exr"))
            out["x.exr"] = (d / "x.exr").read_bytes()
    except ImportError:
        pass
    return out


CUBE_FILES = ["a.h5", "n.npy", "h.mat", "i.mat", "x.exr"]
IMAGE_FILES = ["s.png", "s.tif", "z.tif", "s.npy"]


@pytest.mark.parametrize("name", CUBE_FILES)
@FUZZ
@given(mutation=mutations)
def test_cube_readers_on_corrupt_files(originals, tmp_path, name, mutation):
    if name not in originals:
        pytest.skip("OpenEXR not available")
    p = tmp_path / name
    p.write_bytes(mutate(originals[name], mutation))
    outcome(read_cube, p)


@pytest.mark.parametrize("part", ["e.img", "e.hdr"])
@FUZZ
@given(mutation=mutations)
def test_envi_pair_on_corrupt_files(originals, tmp_path, part, mutation):
    for n in ("e.img", "e.hdr"):
        (tmp_path / n).write_bytes(mutate(originals[n], mutation) if n == part else originals[n])
    outcome(read_cube, tmp_path / "e.hdr")
    outcome(read_cube, tmp_path / "e.img")


@pytest.mark.parametrize("name", IMAGE_FILES)
@FUZZ
@given(mutation=mutations)
def test_sensor_image_reader_on_corrupt_files(originals, tmp_path, name, mutation):
    p = tmp_path / name
    p.write_bytes(mutate(originals[name], mutation))
    outcome(read_image_2d, p)


def test_cave_folder_with_a_corrupt_band(originals, tmp_path):
    import imageio.v3 as iio

    folder = tmp_path / "x_ms"
    folder.mkdir()
    for i in range(31):
        iio.imwrite(folder / f"x_ms_{i + 1:02d}.png", np.full((6, 5), 1000 * (i + 1), np.uint16))
    assert outcome(read_cube, folder) == "ok"
    band = folder / "x_ms_07.png"
    good = band.read_bytes()
    for cut in (0, 8, 40):  # (a PNG missing only its IEND trailer still decodes: fine)
        band.write_bytes(good[:cut])
        assert outcome(read_cube, folder) == "error"


@pytest.mark.parametrize("name", [*CUBE_FILES, "e.hdr", *IMAGE_FILES])
def test_empty_files(originals, tmp_path, name):
    p = tmp_path / name
    p.write_bytes(b"")
    if name == "e.hdr":
        (tmp_path / "e.img").write_bytes(originals["e.img"])
    fn = read_image_2d if name in IMAGE_FILES else read_cube
    with pytest.raises(InputError):
        with time_limit():
            fn(p)


# ------------------------------------------------------------------------------------------------
# Huge declared sizes, NaN/Inf, odd shapes
# ------------------------------------------------------------------------------------------------
def _png_with_size(width: int, height: int) -> bytes:
    raw = zlib.compress(b"\x00" + b"\x00\x00" * 4)
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", raw) + chunk(b"IEND", b"")


def _tiff_with_size(width: int, height: int) -> bytes:
    entries = [(256, 4, 1, width), (257, 4, 1, height), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8 + 2 + 12 * 9 + 4), (277, 3, 1, 1), (278, 4, 1, height), (279, 4, 1, 64)]
    ifd = struct.pack("<H", len(entries))
    for tag, typ, count, value in entries:
        ifd += struct.pack("<HHI", tag, typ, count) + (struct.pack("<HH", value, 0) if typ == 3 else struct.pack("<I", value))
    return b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0) + b"\x00" * 64


def test_huge_declared_sizes_are_refused_quickly(tmp_path):
    # ENVI header declaring 10^6 × 10^6 × 31
    (tmp_path / "big.img").write_bytes(b"\x00" * 1000)
    (tmp_path / "big.hdr").write_text("ENVI\nsamples = 1000000\nlines = 1000000\nbands = 31\nheader offset = 0\n"
                                      "data type = 4\ninterleave = bsq\nbyte order = 0\nwavelength = {"
                                      + ", ".join(str(400 + 10 * i) for i in range(31)) + "}\n")
    # NPY header declaring 31 × 10^6 × 10^6 float32
    with open(tmp_path / "big.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (31, 10**6, 10**6)})
        fh.write(b"\x00" * 64)
    # MAT v5 whose dimensions were patched to 10^5 × 10^5 × 31
    scipy.io.savemat(tmp_path / "big.mat", {"ref": np.ones((4, 5, 31))}, do_compression=False)
    data = bytearray((tmp_path / "big.mat").read_bytes())
    i = data.find(struct.pack("<iiiii", 5, 12, 4, 5, 31))
    data[i + 8 : i + 20] = struct.pack("<iii", 100000, 100000, 31)
    (tmp_path / "big.mat").write_bytes(bytes(data))
    for p in ("big.hdr", "big.img", "big.npy", "big.mat"):
        with pytest.raises(InputError), time_limit(5):
            read_cube(tmp_path / p)
    # sensor images: PNG and TIFF headers declaring 10^6 × 10^6, an NPY header 10^5 × 10^5
    (tmp_path / "big.png").write_bytes(_png_with_size(10**6, 10**6))
    (tmp_path / "big.tif").write_bytes(_tiff_with_size(10**6, 10**6))
    with open(tmp_path / "img.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<u2", "fortran_order": False, "shape": (10**5, 10**5)})
    for p in ("big.png", "big.tif", "img.npy"):
        with pytest.raises(InputError), time_limit(5):
            read_image_2d(tmp_path / p)
    # just above the pixel limit, with the data present in the header only
    side = int(np.sqrt(MAX_IMAGE_PIXELS)) + 1
    (tmp_path / "limit.tif").write_bytes(_tiff_with_size(side, side))
    with pytest.raises(InputError, match="limit"):
        read_image_2d(tmp_path / "limit.tif")
    # a PNG too: big.png above is refused by Pillow's own decompression-bomb limit (2 × 89.5 Mpx), so without this
    # one the PNG reader's check of the header against MAX_IMAGE_PIXELS was never reached
    (tmp_path / "limit.png").write_bytes(_png_with_size(side, side))
    with pytest.raises(InputError, match=rf"limit.png: image of shape \({side}, {side}\) is larger than the limit"), \
            time_limit(5):
        read_image_2d(tmp_path / "limit.png")
    # the same for an NPY whose data are all there (a sparse file): img.npy above is refused by the mmap of its
    # missing data, so without this one the NPY reader's own pixel limit was never reached
    with open(tmp_path / "limit.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<u2", "fortran_order": False, "shape": (side, side)})
        fh.truncate(fh.tell() + 2 * side * side)
    with pytest.raises(InputError, match=rf"limit.npy: image of shape \({side}, {side}\) is larger than the limit"), \
            time_limit(5):
        read_image_2d(tmp_path / "limit.npy")


def test_huge_declared_hdf5_dataset(tmp_path):
    with h5py.File(tmp_path / "huge.h5", "w") as f:
        f.create_dataset("cube", shape=(31, 10**6, 10**6), dtype="f4", chunks=(1, 64, 64))
        f.create_dataset("bands_nm", data=np.arange(31) * 10 + 420.0)
    with pytest.raises(InputError), time_limit(5):
        read_cube(tmp_path / "huge.h5")


def test_nan_inf_and_odd_shapes(tmp_path):
    import tifffile

    bad = np.ones((3, 4, 5), np.float32)
    bad[1, 2, 3] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with h5py.File(tmp_path / "inf.h5", "w") as f:
        f["cube"] = np.where(bad == bad, bad, np.inf)
        f["bands_nm"] = [450.0, 500.0, 550.0]
    write_envi(tmp_path / "e.hdr", np.ones((3, 4, 5), np.float32), Bands.uniform(450, 550, 50))
    raw = np.fromfile(tmp_path / "e.img", dtype="<f4")
    raw[7] = np.inf
    raw.tofile(tmp_path / "e.img")
    hdr = tmp_path / "e.hdr"  # another writer's pair (hsicam's records the data's CRC-32, which this edit breaks)
    hdr.write_text("".join(x for x in hdr.read_text().splitlines(keepends=True) if not x.startswith("hsicam data crc32")))
    for p in ("nan.npy", "inf.h5", "e.hdr"):
        with pytest.raises(InputError, match="NaN/Inf"):
            read_cube(tmp_path / p)
    # sensor images
    img = np.ones((6, 7), np.float32)
    img[2, 2] = np.inf
    tifffile.imwrite(tmp_path / "inf.tif", img)
    np.save(tmp_path / "nan.npy", np.full((4, 4), np.nan))
    for p in ("inf.tif", "nan.npy"):
        with pytest.raises(InputError, match="NaN or Inf"):
            read_image_2d(tmp_path / p)
    # odd shapes
    for i, arr in enumerate([np.ones(5), np.ones((2, 3, 4, 5)), np.ones((0, 4)), np.ones((4, 0, 3)), np.array(3.0),
                             np.ones((3, 4, 5), dtype=complex)]):
        np.save(tmp_path / f"odd{i}.npy", arr)
        with pytest.raises(InputError):
            read_image_2d(tmp_path / f"odd{i}.npy")
        with pytest.raises(InputError):
            read_cube(tmp_path / f"odd{i}.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError):
        read_image_2d(tmp_path / "obj.npy")
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((5, 6, 3), np.uint8), photometric="rgb")
    with pytest.raises(InputError, match="2-D"):
        read_image_2d(tmp_path / "rgb.tif")
    # thin but valid: 1 × N and (1, H, W)
    np.save(tmp_path / "row.npy", np.ones((1, 9), np.float32))
    assert read_image_2d(tmp_path / "row.npy").data.shape == (1, 9)
    np.save(tmp_path / "chw.npy", np.ones((1, 4, 9), np.float32))
    assert read_capture(tmp_path / "chw.npy")[0].shape == (4, 9)


# ------------------------------------------------------------------------------------------------
# The CLI on corrupt inputs: exit 2, one line, no output file
# ------------------------------------------------------------------------------------------------
def _no_outputs(folder: Path) -> None:
    assert not any(folder.iterdir()), sorted(p.name for p in folder.iterdir())


@pytest.mark.parametrize("name", ["s.png", "s.tif", "s.npy"])
@settings(max_examples=8, deadline=timedelta(seconds=20), derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(mutation=mutations)
def test_reconstruct_cli_on_corrupt_captures(fab_run, originals, tmp_path_factory, name, mutation):
    d = tmp_path_factory.mktemp("cli")
    cap = d / name
    cap.write_bytes(mutate(originals[name], mutation))
    out = d / "out"
    out.mkdir()
    with time_limit(30):
        res = run_cli_in_process("reconstruct", str(cap), "--run", str(fab_run), "--out", str(out / "rec.h5"), "--tile", "16")
    if res.returncode == 0:
        assert sorted(p.name for p in out.iterdir()) == ["rec.h5", "rec_rgb.png"]
        assert outcome(read_cube, out / "rec.h5") == "ok"
    else:
        assert_clean_error(res)
        _no_outputs(out)


def test_cli_on_corrupt_runs_and_scenes(fab_run, originals, tmp_path):
    import shutil

    np.save(tmp_path / "cap.npy", np.ones((20, 20), np.float32))
    out = tmp_path / "out"
    out.mkdir()
    # truncated weights, corrupt config, missing weights
    for what in ("weights", "config", "missing"):
        run = tmp_path / f"run_{what}"
        shutil.copytree(fab_run, run)
        if what == "weights":  # every copy: a corrupt root file alone is replaced by the manifest's checkpoint
            for w in run.rglob("model.safetensors"):
                data = w.read_bytes()
                w.write_bytes(data[: len(data) // 3])
        elif what == "config":
            (run / "config.yaml").write_text("camera: [unclosed\n")
        else:
            (run / "model.safetensors").unlink()
        assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(run), "--out", str(out / "r.h5")))
        assert_clean_error(run_cli_in_process("export-optics", "--run", str(run), "--out", str(out / "fab")))
        assert_clean_error(run_cli_in_process("tolerance", "--run", str(run), "--out", str(out / "tol")))
    _no_outputs(out)
    # a corrupt scene for `hsicam simulate`, a corrupt measured-PSF stack for finetune / reconstruct
    (tmp_path / "scene.h5").write_bytes(originals["a.h5"][:300])
    assert_clean_error(run_cli_in_process("simulate", "--run", str(fab_run), "--scene", str(tmp_path / "scene.h5"), "--out", str(out / "sim")))
    psf = tmp_path / "psf"
    psf.mkdir()
    (psf / "psf.json").write_text('{"pixel_pitch_um": 10, "bands_nm": [500, 550, 600]}')
    (psf / "psf.npy").write_bytes(originals["n.npy"][:100])
    assert_clean_error(run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(psf), "--out", str(out / "ft")))
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out / "r.h5"),
                               "--psf-dir", str(psf)))
    (psf / "psf.json").write_text("{not json")
    assert_clean_error(run_cli_in_process("finetune", "--run", str(fab_run), "--psf-dir", str(psf), "--out", str(out / "ft")), "JSON")
    _no_outputs(out)
    # bad raw-correction arguments and frames
    (tmp_path / "flat.npy").write_bytes(originals["s.npy"][:50])
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out / "r.h5"),
                               "--flat", str(tmp_path / "flat.npy")))
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out / "r.h5"),
                               "--exposure-s", "0.1"), "both")
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "cap.npy"), "--run", str(fab_run), "--out", str(out / "r.txt")),
                       ".h5")
    _no_outputs(out)
