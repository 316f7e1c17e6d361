"""``read_bands``: a file's band grid from its header alone, checked against the whole reader (``read_cube``) on files
written in every format's own layout, and on files whose values could not be read (so it reads none)."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from hsicam.data import read_cube, write_cube_h5, write_envi
from hsicam.data.formats import read_bands
from hsicam.errors import InputError
from hsicam.spectral import Bands

from test_data_formats import MST_28_NM, NM_400_700, envi_header, scene, write_cave, write_mat, write_plain_h5

H, W = 5, 7


def _hwc(grid) -> np.ndarray:
    return np.transpose(scene(grid, H, W), (1, 2, 0))


def _exr(path: Path, names: list[str]) -> Path:
    OpenEXR = pytest.importorskip("OpenEXR")
    if not hasattr(OpenEXR, "File"):
        pytest.skip("openexr < 3.3")
    channels = {n: OpenEXR.Channel(np.full((H, W), 0.5, np.float32)) for n in names}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))
    return path


def _files(tmp: Path) -> dict[str, Path]:
    """One file per format and band-grid source (a band list, an assumed grid, descending, micrometres, bad bands)."""
    out = {}
    out["hsicam"] = write_cube_h5(tmp / "ours.h5", scene(NM_400_700 + 20).astype(np.float32),
                                  Bands(NM_400_700 + 20, np.full(31, 12.0)))
    desc = tmp / "ours_desc.h5"  # our layout written by another tool, bands descending
    with h5py.File(desc, "w") as f:
        f["cube"] = scene(NM_400_700[::-1]).astype(np.float32)
        f["bands_nm"] = NM_400_700[::-1]
    out["hsicam-descending"] = desc
    out["mat5-list"] = write_mat(tmp / "l5.mat", "5", {"cube": _hwc(NM_400_700 + 5), "bands": (NM_400_700 + 5)[None]})
    out["mat73-list-um"] = write_mat(tmp / "l73.mat", "7.3", {"rad": _hwc(NM_400_700), "wl": NM_400_700[None] / 1000})
    out["mat5-harvard-assumed"] = write_mat(tmp / "h.mat", "5", {"ref": _hwc(np.arange(420.0, 721.0, 10.0))})
    out["mat73-kaist28-assumed"] = write_mat(tmp / "k.mat", "7.3", {"img": _hwc(MST_28_NM)})
    out["mat5-descending"] = write_mat(tmp / "d.mat", "5", {"cube": _hwc(NM_400_700[::-1]),
                                                           "bands": NM_400_700[::-1][None]})
    out["plain-h5-hwc"] = write_plain_h5(tmp / "p.h5", {"ref": _hwc(np.arange(420.0, 721.0, 10.0))})
    out["cave"] = write_cave(tmp, "beads", np.full((31, H, W), 1000, np.uint16))
    np.save(tmp / "c.npy", scene(np.arange(12)).astype(np.float32))
    out["npy"] = tmp / "c.npy"
    hdr = tmp / "e.hdr"
    waves = "wavelength units = Micrometers\nwavelength = {0.70, 0.60, 0.50, 0.45}\nfwhm = {0.01, 0.02, 0.03, 0.04}\n"
    hdr.write_text(envi_header(W, H, 4, 4, "bil", waves=waves, extra="bbl = {1, 0, 1, 1}\n"))
    (tmp / "e.img").write_bytes(np.ones((H, 4, W), "<f4").tobytes())
    out["envi-um-bbl-unsorted"] = hdr
    out["envi-written"] = write_envi(tmp / "w.hdr", scene(NM_400_700).astype(np.float32), Bands.uniform(400, 700, 10))[0]
    return out


def _same_grid(path: Path, name: str) -> None:
    got, want = read_bands(path), read_cube(path)[1]
    np.testing.assert_array_equal(got.centers_nm, want.centers_nm, err_msg=name)
    np.testing.assert_array_equal(got.fwhm_nm, want.fwhm_nm, err_msg=name)


def test_read_bands_of_an_exr_file_is_its_readers_grid(tmp_path):
    path = _exr(tmp_path / "s.exr", ["R", *(f"w{w}nm" for w in range(700, 399, -20))])  # (skipped without openexr)
    _same_grid(path, "exr")
    assert read_bands(path).centers_nm.tolist() == list(range(400, 701, 20))


def test_read_bands_is_the_readers_grid_for_every_format(tmp_path):
    files = _files(tmp_path)
    for name, path in files.items():
        _same_grid(path, name)
    # the cases above are what they claim (not every file the same grid)
    assert read_bands(files["envi-um-bbl-unsorted"]).centers_nm.tolist() == [450.0, 500.0, 700.0]
    assert read_bands(files["mat73-kaist28-assumed"]).centers_nm.tolist() == list(MST_28_NM)
    assert read_bands(files["mat5-harvard-assumed"]).min_nm == 420.0
    assert read_bands(files["hsicam"]).fwhm_nm.tolist() == [12.0] * 31
    assert read_bands(files["npy"]).centers_nm.tolist() == pytest.approx(np.linspace(400, 700, 12).tolist())
    given = Bands.uniform(500, 610, 10)
    assert read_bands(files["npy"], bands=given) is given


def test_read_bands_reads_no_values(tmp_path):
    """Files whose values could not be read (declared far beyond memory, or cut short): the band grid is still told,
    while the whole reader refuses them."""
    big = tmp_path / "big.h5"  # 31 × 200 000 × 200 000 float32 declared (5 TB), chunked, never written
    with h5py.File(big, "w") as f:
        f.create_dataset("cube", shape=(31, 200_000, 200_000), dtype="f4", chunks=(1, 64, 64))
        f["bands_nm"] = NM_400_700
        f.attrs["format"] = "hsicam-cube"
    assert read_bands(big).centers_nm.tolist() == NM_400_700.tolist()
    with pytest.raises(InputError):
        read_cube(big)
    big73 = tmp_path / "big73.mat"  # MATLAB v7.3 layout, H×W×C = 100 000 × 100 000 × 31 declared, no band list
    write_mat(big73, "7.3", {"rad": _hwc(NM_400_700)})
    with h5py.File(big73, "r+") as f:
        del f["rad"]
        f.create_dataset("rad", shape=(31, 100_000, 100_000), dtype="f8", chunks=(1, 64, 64))
        f["rad"].attrs["MATLAB_class"] = np.bytes_("double")
    assert read_bands(big73).centers_nm.tolist() == NM_400_700.tolist()
    hdr = tmp_path / "cut.hdr"
    hdr.write_text(envi_header(W, H, 3, 4, "bsq", waves="wavelength = {500, 510, 520}\n"))
    (tmp_path / "cut.img").write_bytes(b"\x00" * 8)  # 8 of 420 bytes
    assert read_bands(hdr).centers_nm.tolist() == [500.0, 510.0, 520.0]
    with pytest.raises(InputError):
        read_cube(hdr)


def test_read_bands_refuses_what_the_reader_refuses_about_bands(tmp_path):
    shuffled = write_mat(tmp_path / "s.mat", "5", {"cube": _hwc(NM_400_700), "bands": np.roll(NM_400_700, 3)[None]})
    wrong = write_mat(tmp_path / "w.mat", "5", {"cube": _hwc(NM_400_700), "bands": NM_400_700[:30][None]})
    np.save(tmp_path / "two.npy", np.ones((3, 4), np.float32))
    scipy.io.savemat(tmp_path / "nokey.mat", {"x": np.ones(3)})
    for path in (shuffled, wrong, tmp_path / "two.npy", tmp_path / "nokey.mat"):
        with pytest.raises(InputError) as want:
            read_cube(path)
        with pytest.raises(InputError) as got:
            read_bands(path)
        assert str(got.value) == str(want.value)
    np.save(tmp_path / "c3.npy", np.ones((3, 4, 4), np.float32))
    with pytest.raises(InputError, match="the band grid given for it has 5"):
        read_bands(tmp_path / "c3.npy", bands=Bands.uniform(400, 440, 10))


# ------------------------------------------------------------------------------------------------
# A dataset of files on different band ranges: the refusal names the range every file covers
# ------------------------------------------------------------------------------------------------
def _write(path: Path, lo: float, hi: float) -> Path:
    grid = np.arange(lo, hi + 1, 10.0)
    return write_cube_h5(path, scene(grid, 24, 24).astype(np.float32), Bands.from_centers(grid))


def test_a_mixed_dataset_is_refused_with_the_range_every_file_covers(tmp_path):
    from hsicam.data import SceneDataset
    from hsicam.data.cube import trained_bands

    files = [_write(tmp_path / "a.h5", 400, 700), _write(tmp_path / "b.h5", 420, 720), _write(tmp_path / "c.h5", 420, 720)]
    with pytest.raises(InputError) as exc:
        SceneDataset(files, Bands.uniform(420, 720, 10)).cube(0)
    assert str(exc.value) == (f"{files[0]}: the camera's bands 420-720 nm are not covered by the data's 400-700 nm (no "
                              "extrapolation), and the 3 files of its set lie on 2 band ranges (400-700 nm: 1, 420-720 nm: "
                              "2), of which 2 cover 420-720 nm: every file covers 420-700 nm, so use a camera band grid "
                              "inside it (bands.start_nm, bands.stop_nm) or only files that cover the camera's range")
    # the advice holds: every file reads on a grid inside that range (one file's own range, 400-700, would not)
    inside = SceneDataset(files, Bands.uniform(420, 700, 10))
    assert [inside.cube(i).shape for i in range(3)] == [(29, 24, 24)] * 3
    with pytest.raises(InputError, match="the data's 420-720 nm"):
        SceneDataset(files, Bands.uniform(400, 700, 10)).cube(1)
    # a trained run's bands cannot move: only files that cover them
    with trained_bands(), pytest.raises(InputError) as exc:
        SceneDataset(files, Bands.uniform(420, 720, 10)).cube(0)
    assert "the run's bands 420-720 nm" in str(exc.value)
    assert str(exc.value).endswith("of which 2 cover 420-720 nm: a trained run's bands are fixed by its training, so "
                                   "use only files that cover 420-720 nm")
    # no range common to all
    apart = [_write(tmp_path / "lo.h5", 400, 500), _write(tmp_path / "hi.h5", 600, 700)]
    with pytest.raises(InputError, match=r"lie on 2 band ranges \(400-500 nm: 1, 600-700 nm: 1\), of which 0 cover "
                                         r"420-720 nm: no range is common to every file"):
        SceneDataset(apart, Bands.uniform(420, 720, 10)).cube(0)


def test_a_dataset_on_one_range_keeps_the_files_own_refusal(tmp_path):
    from hsicam.data import SceneDataset

    files = [_write(tmp_path / "a.h5", 400, 700), _write(tmp_path / "b.h5", 400, 700)]
    with pytest.raises(InputError) as exc:
        SceneDataset(files, Bands.uniform(420, 720, 10)).cube(0)
    assert str(exc.value).endswith("use a camera band grid inside 400-700 nm or data that covers the camera's range")


def test_a_training_split_names_the_whole_folder_and_npy_keeps_its_advice(tmp_path):
    from hsicam.config import load_config
    from hsicam.data import build_datasets

    for i in range(3):
        _write(tmp_path / f"a{i}.h5", 400, 700)
    for i in range(2):
        _write(tmp_path / f"b{i}.h5", 430, 720)
    np.save(tmp_path / "n.npy", scene(np.arange(31), 24, 24).astype(np.float32))  # taken as 400-700 nm
    cfg = load_config(overrides=[f"data.root={tmp_path}", "data.patch_px=12", "data.val_fraction=0.4"])
    with pytest.raises(InputError) as exc:
        build_datasets(cfg.data, Bands.uniform(420, 720, 10), margin_px=2)
    text = str(exc.value)
    assert "the 6 files of its set lie on 2 band ranges (400-700 nm: 4, 430-720 nm: 2), of which 0 cover 420-720 nm: " \
           "every file covers 430-700 nm" in text
    from hsicam.data import SceneDataset  # a .npy file keeps its advice after the ranges

    with pytest.raises(InputError) as exc:
        SceneDataset([tmp_path / "n.npy", tmp_path / "b0.h5"], Bands.uniform(420, 720, 10)).cube(0)
    assert "lie on 2 band ranges (400-700 nm: 1, 430-720 nm: 1)" in str(exc.value)
    assert str(exc.value).endswith("(the file carries no wavelengths, so its 31 bands were taken as 400-700 nm: give "
                                   "its grid with data.npy_bands, e.g. data.npy_bands={start_nm: ..., stop_nm: ..., "
                                   "step_nm: ...})")


def test_ranges_a_band_grid_takes_as_one_are_one_range(tmp_path):
    """Grids 4e-4 nm apart are one grid for Bands.covers (BAND_TOL_NM): the refusal counts them as one range, and a
    dataset of only such files keeps the file's own refusal."""
    from hsicam.data import SceneDataset

    grid = np.arange(400.0, 701.0, 10.0)
    a = write_cube_h5(tmp_path / "a.h5", scene(grid, 24, 24).astype(np.float32), Bands.from_centers(grid))
    b = write_cube_h5(tmp_path / "b.h5", scene(grid, 24, 24).astype(np.float32), Bands.from_centers(grid + 4e-4))
    with pytest.raises(InputError) as exc:
        SceneDataset([a, b], Bands.uniform(420, 720, 10)).cube(0)
    assert "band ranges" not in str(exc.value) and "use a camera band grid inside 400-700 nm" in str(exc.value)
    c = _write(tmp_path / "c.h5", 420, 720)
    with pytest.raises(InputError, match=r"lie on 2 band ranges \(400-700 nm: 2, 420-720 nm: 1\)"):
        SceneDataset([a, b, c], Bands.uniform(420, 720, 10)).cube(0)
