"""Probe 28's evaluation findings, through the command line, judged by independent computations
on the files evaluate really wrote:

* #3 SAM: pixels whose truth spectrum is all zero have no angle and are left out (they scored 90°);
* #5 ``--save`` with several seeds: the saved estimate says which seed, noise and scene it is;
* #6 scenes with one file stem in two folders: unique names, each row's path, no cube overwritten;
* #10 a bad scene fails before any scene is scored (it failed after all earlier ones were);
* #13 a scene too small for the ``valid`` margin is named by its path.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from cli_helpers import assert_clean_error, final_error_line, module_cache, run_cli, run_cli_in_process
from hsicam.data.formats import write_cube_h5
from hsicam.spectral import Bands

BANDS = Bands.uniform(420, 720, 50)  # the tiny preset's grid
MARGIN = 10  # the tiny preset's 21-px kernel: the `valid` truth is the scene less 10 px per side


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


@pytest.fixture(scope="module")
def run(tmp_path_factory, env):
    d = tmp_path_factory.mktemp("run") / "run"
    res = run_cli("train", "--config", "tiny", "--out", str(d), "--set", "train.epochs=1", env=env)
    assert res.returncode == 0, res.stderr
    return d


def _read(path: Path) -> tuple[np.ndarray, dict]:
    with h5py.File(path, "r") as f:
        return f["cube"][()].astype(np.float64), json.loads(f.attrs["metadata_json"])


def _sam(est: np.ndarray, truth: np.ndarray) -> float:
    """Mean angle (degrees) over the pixels whose truth is not all zero; a zero estimate there is 90°."""
    e, t = est.reshape(est.shape[0], -1).T, truth.reshape(truth.shape[0], -1).T
    ne, nt = np.linalg.norm(e, axis=1), np.linalg.norm(t, axis=1)
    keep = nt > 0
    cos = np.where(ne[keep] > 0, np.einsum("pc,pc->p", e[keep], t[keep]) / np.maximum(ne[keep] * nt[keep], 1e-300), 0.0)
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).mean())


def _scores(est: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """PSNR (per band, peak 1), SSIM (scikit-image, Gaussian σ 1.5), SAM, by numpy / scikit-image."""
    c = truth.shape[0]
    return {"psnr": float(np.mean([10 * np.log10(1 / np.mean((est[b] - truth[b]) ** 2)) for b in range(c)])),
            "ssim": float(np.mean([structural_similarity(truth[b], est[b], gaussian_weights=True, sigma=1.5,
                                                         use_sample_covariance=False, data_range=1.0) for b in range(c)])),
            "sam": _sam(est, truth)}


def _scene(rng, h=48, w=52) -> np.ndarray:
    return rng.uniform(0.1, 1, (len(BANDS), h, w)).astype(np.float32)


def _crop(cube: np.ndarray) -> np.ndarray:
    """The `valid` ground truth of a scene written on the camera's bands: max-normalised, margin cut."""
    return (cube / cube.max())[:, MARGIN:-MARGIN, MARGIN:-MARGIN].astype(np.float64)


def test_sam_leaves_out_black_truth_pixels_and_says_so(run, env, tmp_path):
    """A scene with a black rectangle inside the scored area: SAM is the mean angle over the other
    pixels (the black ones scored 90° and took a 5° scene to 46°); the row counts them, and the
    conventions in results.json/md say it. A scene whose scored area is all black has no SAM (NaN,
    named in results.json/md) and the mean SAM is over the others; PSNR/SSIM do not change."""
    rng = np.random.default_rng(0)
    data = tmp_path / "data"
    black = _scene(rng)
    black[:, 20:30, 15:35] = 0.0  # 200 truth pixels without spectrum inside the 28×32 scored area
    dark = _scene(rng)
    dark[:, MARGIN:-MARGIN, MARGIN:-MARGIN] = 0.0  # the scene has light only in the margin the sensor does not see
    write_cube_h5(data / "black.h5", black, BANDS)
    write_cube_h5(data / "dark.h5", dark, BANDS)
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(out), "--save")
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "results.json").read_text())
    rows = {r["name"]: r for r in summary["scenes"]}
    est, _ = _read(out / "cubes" / "black_estimate.h5")
    truth, _ = _read(out / "cubes" / "black_truth.h5")
    np.testing.assert_array_equal(truth, _crop(black).astype(np.float32))  # the files hold what was scored
    want = _scores(est, truth)
    assert rows["black"]["sam"] == pytest.approx(want["sam"], abs=1e-9)
    assert rows["black"]["psnr"] == pytest.approx(want["psnr"], abs=1e-9)
    assert rows["black"]["ssim"] == pytest.approx(want["ssim"], abs=1e-9)
    assert rows["black"]["sam_excluded_px"] == 200 == int((truth == 0).all(axis=0).sum())
    assert rows["black"]["sam"] < 45.0  # 200 of 896 pixels at 90° would give more than 20°
    assert rows["dark"]["sam"] is None and rows["dark"]["sam_excluded_px"] == 28 * 32  # NaN, as strict JSON writes it
    assert summary["sam_undefined"] == ["dark"]
    assert summary["mean"]["sam"] == pytest.approx(rows["black"]["sam"])  # over the scenes that have one
    assert summary["mean"]["psnr"] == pytest.approx((rows["black"]["psnr"] + rows["dark"]["psnr"]) / 2)
    assert "all zero" in summary["conventions"]["sam"] and "90" in summary["conventions"]["sam"]
    md = (out / "results.md").read_text()
    assert summary["conventions"]["sam"] in md and "SAM undefined" in md and "dark" in md and "black (200 px)" in md
    assert "SAM undefined" in res.stderr  # the progress line of the dark scene
    table = list(csv.DictReader((out / "results.csv").open()))
    assert [r["sam_excluded_px"] for r in table] == ["200", str(28 * 32), ""]


def test_save_with_several_seeds_labels_the_cube_it_keeps(run, env, tmp_path):
    """`--seeds 2 --save` on the synthetic validation split: the saved estimate is seed 0's and says
    so (seed, seeds scored, test noise as applied, sensor noise model, scene and source path, the
    normalisation divisor); results.json/md say what the cubes hold, and each row's per_seed[0] is
    what the saved cubes score (recomputed here), its mean over seeds the row. The synthetic scenes
    keep their names."""
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--out", str(out), "--save", "--seeds", "2",
                             "--sensor-sigma", "0.01")
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "results.json").read_text())
    assert "seed 0" in summary["saved_cubes"] and "2 seeds" in summary["saved_cubes"]
    assert "seed 0" in (out / "results.md").read_text()
    assert summary["scenes"]
    for row in summary["scenes"]:
        assert row["name"].startswith("scene_") and row["path"] == row["name"] + ".h5"
        est, meta = _read(out / "cubes" / f"{row['name']}_estimate.h5")
        truth, tmeta = _read(out / "cubes" / f"{row['name']}_truth.h5")
        assert meta["seed"] == 0 and meta["seeds_scored"] == 2 and "seed 0" in meta["note"]
        assert meta["noise"]["sensor_sigma"] == 0.01 and "sigma_height_nm" in meta["noise"]
        assert meta["noise"]["camera_sensor"] == summary["noise"]["camera_sensor"]
        assert meta["method"] == "doe-learned" and meta["run"] == str(run.resolve())
        assert meta["scene"] == tmeta["scene"] == row["name"] and meta["scene_path"] == row["path"]
        source = Path(meta["source"])
        assert source.is_absolute() and source.name == row["path"] and tmeta["source"] == meta["source"]
        with h5py.File(source, "r") as f:  # the source file, normalised and cropped: the saved truth
            cube = f["cube"][()]
            assert np.allclose(f["bands_nm"][()], summary["bands_nm"])
        assert meta["normalization_peak"] == pytest.approx(float(cube.max()))
        np.testing.assert_allclose(truth, (cube / np.float32(cube.max()))[:, MARGIN:-MARGIN, MARGIN:-MARGIN], rtol=1e-6)
        first, second = row["per_seed"]
        assert (first["seed"], second["seed"]) == (0, 1)
        want = _scores(est, truth)
        for k in ("psnr", "ssim", "sam"):
            assert first[k] == pytest.approx(want[k], abs=1e-9), k
            assert row[k] == pytest.approx((first[k] + second[k]) / 2, abs=1e-12), k
        assert first["psnr"] != second["psnr"]  # the seeds drew different noise


def test_scenes_sharing_a_file_stem_get_unique_names_rows_with_paths_and_all_their_cubes(run, env, tmp_path):
    """day1/scene.h5 and day2/scene.h5 gave two rows named "scene" and `--save` kept one scene's
    cubes (the second overwrote the first). Now they are named by their relative paths, each row
    (json and csv) has its path, and every scene's cubes are written: each saved truth is its own
    file's scene (checked against the file), the estimate scored as the row says."""
    rng = np.random.default_rng(1)
    data = tmp_path / "data"
    cubes = {"day1/scene.h5": _scene(rng), "day2/scene.h5": _scene(rng, 50, 48), "c.h5": _scene(rng)}
    for rel, cube in cubes.items():
        write_cube_h5(data / rel, cube, BANDS)
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(out), "--save")
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "results.json").read_text())
    got = {r["name"]: r for r in summary["scenes"]}
    assert list(got) == ["c", "day1__scene", "day2__scene"]
    assert [got[n]["path"] for n in got] == ["c.h5", "day1/scene.h5", "day2/scene.h5"]
    table = list(csv.DictReader((out / "results.csv").open()))
    assert [(r["name"], r["path"]) for r in table] == [("c", "c.h5"), ("day1__scene", "day1/scene.h5"),
                                                       ("day2__scene", "day2/scene.h5"), ("mean", "")]
    assert sorted(p.name for p in (out / "cubes").iterdir()) == sorted(
        f"{n}_{role}.h5" for n in got for role in ("estimate", "truth"))
    for name, row in got.items():
        truth, meta = _read(out / "cubes" / f"{name}_truth.h5")
        est, _ = _read(out / "cubes" / f"{name}_estimate.h5")
        assert meta["scene_path"] == row["path"] and Path(meta["source"]) == (data / row["path"]).resolve()
        np.testing.assert_array_equal(truth, _crop(cubes[row["path"]]).astype(np.float32))
        assert row["psnr"] == pytest.approx(_scores(est, truth)["psnr"], abs=1e-9)


def test_scene_names_keep_stems_and_make_colliding_ones_unique(tmp_path):
    """Stems stay the names when unique (the synthetic scene_0010 …); colliding ones (ignoring case:
    the cubes of Scene and scene would overwrite each other on a case-insensitive disk) take their
    relative path, then their suffix, then a number; never two equal names."""
    from hsicam.data.datasets import scene_names, scene_path

    assert scene_names([tmp_path / "scene_0010.h5", tmp_path / "scene_0011.h5"]) == ["scene_0010", "scene_0011"]
    root = tmp_path / "d"
    paths = [root / "a.h5", root / "day1" / "scene.h5", root / "day2" / "Scene.mat", root / "x.h5", root / "x.mat",
             root / "p" / "q__r.h5", root / "p__q" / "r.h5"]
    names = scene_names(paths, root)
    assert names == ["a", "day1__scene", "day2__Scene", "x.h5", "x.mat", "q__r", "r"]
    tricky = [root / "p" / "q" / "r.h5", root / "p__q" / "r.h5", root / "s.h5"]  # equal with folders joined by __
    assert scene_names(tricky, root) == ["p__q__r.h5", "p__q__r.h5-2", "s"]
    assert scene_path(root / "day1" / "scene.h5", root) == "day1/scene.h5"
    assert scene_path(root / "a.h5", root / "a.h5") == "a.h5"  # --data naming the file itself


@pytest.mark.parametrize("bad", ["unreadable", "bands", "small"])
@pytest.mark.parametrize("save", [False, True])
def test_a_bad_scene_fails_before_any_scene_is_scored(run, env, tmp_path, bad, save):
    """Two good scenes and then a bad one (a file no reader knows, bands that do not cover the run's,
    a scene too small for the `valid` margin): evaluate refused it only when its turn came, after
    scoring the others (without --save). Now it fails before the first scene is scored, with or
    without --save, in one line that names the file by its path."""
    rng = np.random.default_rng(2)
    data = tmp_path / "data"
    for name in ("a", "b"):
        write_cube_h5(data / f"{name}.h5", _scene(rng), BANDS)
    if bad == "unreadable":
        (data / "zz.h5").write_bytes(b"\x00not a cube\x00" * 100)
        fragment = "unknown format"
    elif bad == "bands":
        write_cube_h5(data / "zz.h5", _scene(rng), Bands.uniform(400, 700, 50))
        fragment = "400-700 nm"
    else:
        write_cube_h5(data / "zz.h5", _scene(rng, 26, 40), BANDS)
        fragment = "scene of 26×40 px leaves 6×20 px to score"
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(out),
                             *(["--save"] if save else []))
    assert_clean_error(res, f"{data / 'zz.h5'}: ", fragment)  # named by its path, not its stem
    assert "[1/3]" not in res.stderr  # nothing was scored
    assert not (out / "results.json").exists()


def test_a_mat_scene_on_an_assumed_grid_says_so_when_refused(run, env, tmp_path):
    """A MAT cube without a band list is read on its format's assumed grid (ICVL `rad`: 400-700 nm):
    refused on the 420-720 run, the one line says the grid was assumed and how to give the real one."""
    import scipy.io

    data = tmp_path / "data"
    data.mkdir()
    scipy.io.savemat(data / "icvl.mat", {"rad": np.ones((48, 48, 31), np.float32)})
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(tmp_path / "ev"))
    line = final_error_line(res)  # after the reader's note that it assumed the grid
    for fragment in ("not covered by the data's 400-700 nm", "the file lists no wavelengths, so its bands were assumed to "
                     "be 31 bands, 400-700 nm in 10 nm steps; add its band list as a variable 'bands'"):
        assert fragment in line, line


def test_scenes_on_a_coarser_grid_than_the_camera_s_are_scored_with_a_warning_that_their_truth_is_interpolated(
        run, env, tmp_path):
    """A dataset whose files hold fewer, wider-spaced bands than the camera's (here 4 bands 100 nm apart under the tiny
    camera's 7 of 50 nm) was scored silently: the truth of the 3 bands between the data's was a linear interpolation,
    and a smooth estimate scored well against it (a helper's 7-band set under the 31-band camera: 24 bands made up).
    Now a WARNING and results.json/md's ``truth_interpolated`` say it, naming the first such file and how many bands;
    data on the camera's own grid (or finer) get neither. Reference: the bands counted here by hand."""
    rng = np.random.default_rng(3)
    coarse = Bands.uniform(420, 720, 100)  # 420, 520, 620, 720: 470, 570 and 670 nm lie 100 nm apart
    data = tmp_path / "coarse"
    for name in ("a", "b"):
        cube = rng.uniform(0.2, 1.0, (len(coarse), 48, 52)).astype(np.float32)
        write_cube_h5(data / f"{name}.h5", cube, coarse)
    write_cube_h5(data / "c.h5", _scene(rng), BANDS)  # on the camera's grid: not counted
    out = tmp_path / "ev"
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(data), "--out", str(out))
    assert res.returncode == 0, res.stderr
    want = (f"{data / 'a.h5'} and 1 other scene(s): the data's 4 bands (420-720 nm) are coarser than the camera's 7 "
            "(420-720 nm): 3 of the camera's bands lie between data bands more than 1.5 of their FWHM apart, so their "
            "ground truth is a linear interpolation of the data and the scores there are against it, not against a "
            "measurement; score on data at least as fine as the camera's bands")
    summary = json.loads((out / "results.json").read_text())
    assert summary["truth_interpolated"] == want
    assert want in res.stderr and f"- truth_interpolated: {want}" in (out / "results.md").read_text()
    fine = tmp_path / "fine"
    write_cube_h5(fine / "c.h5", _scene(rng), BANDS)
    write_cube_h5(fine / "d.h5", rng.uniform(0.2, 1.0, (301, 48, 52)).astype(np.float32), Bands.uniform(420, 720, 1))
    res = run_cli_in_process("evaluate", "--run", str(run), "--data", str(fine), "--out", str(tmp_path / "ev2"))
    assert res.returncode == 0, res.stderr
    assert "truth_interpolated" not in json.loads((tmp_path / "ev2" / "results.json").read_text())
    assert "linear interpolation of the data" not in res.stderr
