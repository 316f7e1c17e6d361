"""The maintainer scripts of scripts/ that draw the docs' figures run on real inputs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPTS / args[0]), *args[1:]], capture_output=True, text=True, timeout=120)


def test_psf_compare_figure_draws_one_row_per_camera_and_rejects_bad_stacks(tmp_path):
    import imageio.v3 as iio

    k, bands = 21, 31
    sharp = np.zeros((bands, k, k), np.float32)
    sharp[:, k // 2, k // 2] = 1.0
    spread = np.zeros_like(sharp)
    spread[:, k // 2 - 1:k // 2 + 2, k // 2 - 1:k // 2 + 2] = 1.0 / 9
    np.save(tmp_path / "a.npy", sharp)
    np.save(tmp_path / "b.npy", spread)
    one, two = tmp_path / "one.png", tmp_path / "two.png"
    assert _run("psf_compare_figure.py", str(one), f"lens={tmp_path / 'a.npy'}").returncode == 0
    proc = _run("psf_compare_figure.py", str(two), f"lens={tmp_path / 'a.npy'}", f"doe={tmp_path / 'b.npy'}")
    assert proc.returncode == 0, proc.stderr
    h1, h2 = iio.imread(one).shape[0], iio.imread(two).shape[0]
    assert h2 > 1.7 * h1  # a second row of panels
    bad = _run("psf_compare_figure.py", str(tmp_path / "x.png"), f"flat={tmp_path / 'a.npy'}", "--bands", "800")
    assert bad.returncode != 0 and "800 nm is not a band" in bad.stderr and not (tmp_path / "x.png").exists()
    # the bands of a stack are its psf.json's: 430 nm was drawn as the 420/10 grid's band 1 of any stack (the tiny
    # preset's 470 nm), and its label claimed a band the stack does not have (session 74's figure hunt)
    (tmp_path / "t").mkdir()
    np.save(tmp_path / "t" / "psf.npy", sharp[:7])
    (tmp_path / "t" / "psf.json").write_text(json.dumps({"bands_nm": [420.0 + 50 * i for i in range(7)]}))
    odd = _run("psf_compare_figure.py", str(tmp_path / "z.png"), f"tiny={tmp_path / 't' / 'psf.npy'}", "--bands", "430")
    assert odd.returncode != 0 and "430 nm is not a band of tiny (its bands: 420, 470, 520" in odd.stderr
    ok = _run("psf_compare_figure.py", str(tmp_path / "z.png"), f"tiny={tmp_path / 't' / 'psf.npy'}", "--bands",
              "470,720")
    assert ok.returncode == 0 and "no psf.json" not in ok.stderr, ok.stderr
    assert "no psf.json beside it: its 31 bands taken as 420 nm on" in proc.stderr
    np.save(tmp_path / "c.npy", sharp[0])
    wrong = _run("psf_compare_figure.py", str(tmp_path / "y.png"), f"2d={tmp_path / 'c.npy'}")
    assert wrong.returncode != 0 and "expected a (bands, K, K)" in wrong.stderr


def _oracle_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("spectral_oracle", SCRIPTS / "spectral_oracle.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_spectral_oracle_decoder_is_exact_on_spectra_its_filters_resolve():
    """Closed-form references: spectra in an r-dimensional subspace seen through F ≥ r filters are
    recovered exactly by the ridge map (λ → 0); with F = C invertible filters W = K⁻¹; spectra
    outside the subspace are not (the decoder is fitted, not the identity)."""
    import torch

    oracle = _oracle_module()
    g = torch.Generator().manual_seed(0)
    c, f, r = 31, 16, 6
    basis = torch.rand(c, r, generator=g, dtype=torch.float64)
    spectra = basis @ torch.rand(r, 5000, generator=g, dtype=torch.float64)
    tile = torch.rand(c, 4, 4, generator=g, dtype=torch.float64)
    filters = oracle.filter_matrix(tile)
    assert filters.shape == (f, c) and torch.equal(filters[5], tile[:, 1, 1])  # phase (1, 1) is row 1·4 + 1
    w = oracle.fit_linear_decoder(filters, spectra, 1e-10)
    test = basis @ torch.rand(r, 7, generator=g, dtype=torch.float64)
    torch.testing.assert_close(w @ filters @ test, test, rtol=1e-5, atol=1e-6)
    cube = test.T.reshape(1, 7, 1, c).permute(0, 3, 1, 2) / test.max()  # (1, C, 7, 1) in [0, 1]
    torch.testing.assert_close(oracle.oracle_estimate(filters, w, cube), cube, rtol=1e-5, atol=1e-6)
    outside = torch.rand(c, 3, generator=g, dtype=torch.float64)
    assert (w @ filters @ outside - outside).abs().max() > 1e-2
    square = torch.rand(c, c, generator=g, dtype=torch.float64) + c * torch.eye(c, dtype=torch.float64)
    w_sq = oracle.fit_linear_decoder(square, torch.rand(c, 500, generator=g, dtype=torch.float64), 0.0)
    torch.testing.assert_close(w_sq, torch.linalg.inv(square), rtol=1e-6, atol=1e-8)


def test_spectral_oracle_scores_a_trained_run_above_its_camera(tmp_path):
    """End to end on a tiny trained run: a table row per validation scene; with the tiny camera's
    9 filters for 7 bands the full-resolution oracle is nearly exact (above 40 dB); a run
    without a CFA is one clear error."""
    from cli_helpers import run_cli

    env = {"HSICAM_CACHE": str(tmp_path / "cache")}
    run = tmp_path / "run"
    assert run_cli("train", "--config", "tiny", "--out", str(run), env=env).returncode == 0
    proc = subprocess.run([sys.executable, str(SCRIPTS / "spectral_oracle.py"), str(run), "--pixels", "500"],
                          capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| scene_")]
    assert rows and "**mean**" in proc.stdout
    psnr = float(proc.stdout.split("**mean** |")[1].split("|")[0])
    assert psnr > 40.0, proc.stdout
    # the SAM breakdown reads the same run's validation and held-out-sources scenes (engine.experiments.scored_scenes)
    for extra in ([], ["--heldout"]):
        sam = subprocess.run([sys.executable, str(SCRIPTS / "sam_breakdown.py"), str(run), *extra],
                             capture_output=True, text=True, timeout=300, env={**os.environ, **env})
        assert sam.returncode == 0 and "| **mean** |" in sam.stdout, sam.stderr
    plain = tmp_path / "nocfa"
    assert run_cli("train", "--config", "tiny", "--out", str(plain), "--set", "camera.cfa.enabled=false", env=env).returncode == 0
    nocfa = subprocess.run([sys.executable, str(SCRIPTS / "spectral_oracle.py"), str(plain)],
                           capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    assert nocfa.returncode == 2 and "colour filter array" in nocfa.stderr


def test_tune_gaptv_sweeps_training_scenes_and_parses_schedules(tmp_path, cache_env):
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location("tune_gaptv", SCRIPTS / "tune_gaptv.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.weight_values("0.02", 5) == 0.02
    np.testing.assert_allclose(mod.weight_values("0.1>0.001", 3), [0.1, 0.01, 0.001])
    env = {**os.environ, "HSICAM_CACHE": str(cache_env), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(SCRIPTS / "tune_gaptv.py"), "--config", "tiny", "--scenes", "1",
                           "--iterations", "1,20", "--weights", "0.01,0.1>0.01"],
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(x) for x in proc.stdout.splitlines() if x.startswith("{")]
    assert [(r["iterations"], r["tv_weight"]) for r in rows] == [(1, "0.01"), (1, "0.1>0.01"), (20, "0.01"), (20, "0.1>0.01")]
    assert rows[2]["psnr"] > rows[0]["psnr"]  # more GAP iterations fit the measurement better
    assert "DD-CASSI + GAP-TV on 1 training scenes" in proc.stdout and "| 20 | 0.01 |" in proc.stdout


def test_unseen_layouts_script_writes_readable_scenes_whole_or_not_at_all(tmp_path):
    from hsicam.data import read_cube
    from hsicam.data.datasets import list_scenes
    from hsicam.data.synthetic import UNSEEN_LAYOUTS
    from hsicam.spectral import Bands

    out = tmp_path / "unseen"
    proc = _run("unseen_layouts.py", str(out), "--n", "2", "--size", "32")
    assert proc.returncode == 0, proc.stderr
    files = sorted(out.glob("*.h5"))
    assert [f.name for f in files] == [f"scene_{i:04d}_{UNSEEN_LAYOUTS[i]}.h5" for i in range(2)]
    assert list_scenes(out) == files  # a data folder `evaluate --data` takes (no command-output marker)
    data, bands, meta = read_cube(files[1])
    np.testing.assert_allclose(bands.centers_nm, Bands.paper().centers_nm)
    assert data.shape == (31, 32, 32) and float(data.max()) == 1.0
    assert meta["layout"] == UNSEEN_LAYOUTS[1] and meta["split"] == "heldout"
    again = _run("unseen_layouts.py", str(out), "--n", "1")
    assert again.returncode == 2 and "exists" in again.stderr
    bad = _run("unseen_layouts.py", str(tmp_path / "bad"), "--n", "0")
    assert bad.returncode == 2 and "--n must be >= 1" in bad.stderr and not (tmp_path / "bad").exists()


def test_clipped_highlights_scores_the_map_against_the_plain_steps(tmp_path):
    """docs/hardware.md's "Clipped highlights" figures come from this script: one validation scene of the shipped
    camera (a small split, in a private cache), one JSON line for it and one per region. The map brightens what
    the plain steps darken near the clipped pixels and leaves the rest to float rounding."""
    import json

    env = {**os.environ, "HSICAM_CACHE": str(tmp_path / "cache")}
    args = ["clipped_highlights.py", "pretrained:standard", "--set", "data.synthetic_n=8", "--set",
            "data.val_fraction=0.125", "--set", "data.synthetic_size=224"]
    proc = subprocess.run([sys.executable, str(SCRIPTS / args[0]), *args[1:]], capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    scene, regions = lines[0], {r["region"]: r for r in lines[1:]}
    assert len(lines) == 5 and set(regions) == {"all", "near", "clipped", "far"}
    assert abs(scene["clipped_share"] - 0.03) < 0.005
    assert regions["near"]["mean_gain_db"] > 0.05 and regions["all"]["mean_gain_db"] > 0.05
    assert abs(regions["far"]["mean_gain_db"]) < 0.01
    bad = _run("clipped_highlights.py", "pretrained:standard", "--share", "0.7")
    assert bad.returncode == 2 and "--share must be in (0, 0.5)" in bad.stderr
