"""Tolerance analysis: perturbed PSFs against independent references, and the study's outputs."""

from __future__ import annotations

import csv
import json
import logging
import math
import re

import numpy as np
import pytest
import torch

from cli_helpers import assert_clean_error, run_cli_in_process
from fab_runs import fab_run  # noqa: F401 - shared fixture
from hsicam.cameras import DOECamera
from hsicam.engine.tolerance import _tolerance_at
from hsicam.errors import InputError
from hsicam.optics.perturb import (
    defocus_delta_per_m2, nominal_heights, oversampled_optics, psf_for_heights, psf_shifted, shift_fill,
)


def test_unperturbed_cases_reproduce_the_camera(tiny_camera):
    cam = tiny_camera()
    o = cam.optics
    h0 = nominal_heights(cam)
    with torch.no_grad():
        p0 = cam.psf()
    torch.testing.assert_close(psf_for_heights(o, h0).psf, p0, rtol=0, atol=1e-7)
    torch.testing.assert_close(psf_for_heights(o, h0, defocus_delta_per_m2(o, 0.0)).psf, p0, rtol=0, atol=1e-7)


def test_misalignment_on_the_oversampled_pupil(tiny_config):
    """Zero shift = the camera built with pupil_oversample Q from its config; a whole-cell shift =
    the heights moved by whole cells; ±½ cell of a mirror-symmetric DOE = mirrored PSFs."""
    cam = DOECamera.from_config(tiny_config())
    ref = DOECamera.from_config(tiny_config("camera.psf.pupil_oversample=4", f"camera.psf.kernel_px={cam.kernel_px}"))
    ref.load_state_dict(cam.state_dict())
    fine = oversampled_optics(cam.optics, 4)
    h0 = nominal_heights(cam)
    psf, energy, applied = psf_shifted(fine, h0, 0.0, 0.0)
    with torch.no_grad():
        res = ref.psf_result()
    torch.testing.assert_close(psf, res.psf, rtol=0, atol=1e-7)
    torch.testing.assert_close(energy.float(), res.energy, rtol=0, atol=1e-6)
    assert float(energy.max()) < 0.999  # light of the higher grid orders leaves the kernel
    psf, _, applied = psf_shifted(fine, h0, -1.0, 2.0)
    assert applied == (-1.0, 2.0)
    torch.testing.assert_close(psf, psf_for_heights(fine, shift_fill(h0, -1, 2)).psf, rtol=0, atol=1e-7)
    psf, _, applied = psf_shifted(fine, h0, 0.0, 0.3)
    assert applied == (0.0, 0.25)  # rounded to whole samples
    sym = (h0 + h0.flip(1)) / 2
    plus, _, _ = psf_shifted(fine, sym, 0.0, 0.5)
    minus, _, _ = psf_shifted(fine, sym, 0.0, -0.5)
    diff = (plus - minus.flip(-1)).abs().max() / plus.max()
    assert diff < 0.05, diff  # mirror symmetry (up to the even-FFT Nyquist asymmetry)
    assert (plus - psf_shifted(fine, sym, 0.0, 0.0)[0]).abs().max() / plus.max() > 0.01  # and the shift matters


def test_sensor_distance_error_defocus(tiny_camera):
    cam = tiny_camera("camera.doe.enabled=false")
    o = cam.optics
    z, f = o.sensor_distance_m, o.focal_lengths_m
    lam = cam.bands.centers_nm * 1e-9
    dz = 150e-6
    total = o.defocus_per_m2.double() + defocus_delta_per_m2(o, dz)
    np.testing.assert_allclose(total.numpy(), np.pi / lam * (1 / (z + dz) - 1 / f), rtol=1e-6, atol=1e-3)
    # without a DOE the in-focus PSF is an Airy pattern: defocus lowers its peak monotonically
    h0 = nominal_heights(cam)
    peaks = [float(psf_for_heights(o, h0, defocus_delta_per_m2(o, d)).psf[1].max()) for d in (0.0, 100e-6, 200e-6, 400e-6)]
    assert all(a > b for a, b in zip(peaks, peaks[1:])), peaks


def test_tolerance_at_interpolates_the_1db_point():
    assert _tolerance_at([0, 10, 20, 40], [30.0, 29.8, 29.4, 28.0], 30.0) == pytest.approx(20 + 20 * (0.4 / 1.4))
    assert _tolerance_at([0, 10], [30.0, 29.5], 30.0) is None
    assert _tolerance_at([-50, -20, 0], [27.0, 29.5, 30.0], 30.0) == pytest.approx(20 + 30 * (0.5 / 2.5))


def test_tolerance_cli(fab_run, tmp_path, caplog):
    from hsicam.runs.folder import load_run
    from hsicam.engine.tolerance import evaluate_psf, evaluation_scenes

    out = tmp_path / "tol"
    with caplog.at_level(logging.INFO, logger="hsicam.progress"):  # (in process: the log records)
        res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), "--max-scenes", "2",
                                 "--draws", "2", "--sigma-height-nm", "0,40,200", "--levels", "2,16",
                                 "--shift-cells", "0,0.5", "--sensor-distance-um=-300,0,300")
    assert res.returncode == 0, res.stderr
    assert "nominal PSNR" in res.stdout
    # off a terminal: one progress line per sweep point, in order (hsicam.progress: INFO on stderr)
    lines = "\n".join(r.getMessage() for r in caplog.records if r.name == "hsicam.progress")
    done = re.findall(r"^tolerance: (\d+)/(\d+) points? (\w+) ", lines, re.M)
    assert [(int(k), int(n)) for k, n, _ in done] == [(k, 12) for k in range(1, 13)], lines
    assert [w for _, _, w in done] == ["sigma_height_nm"] * 3 + ["levels"] * 2 + ["shift_x_cells"] * 2 + \
        ["shift_diag_cells"] * 2 + ["sensor_distance_um"] * 3
    r = json.loads((out / "tolerance.json").read_text())
    assert (out / "tolerance.png").is_file()
    cfg, model = load_run(fab_run)
    # the levels sweep is said to quantise as the export does (a clamp range said "wrapped" before)
    from hsicam.export.doe import level_grid_text

    assert r["methods"]["levels"] == f"exported L-level heights (piston removed; {level_grid_text(model.camera.optics.doe)})"
    doe = model.camera.optics.doe
    assert "wrapped modulo h_2π" in level_grid_text(doe) and doe.max_height_m is None
    doe.max_height_m = 2e-6  # a clamp range that does not wrap (camera.doe.max_height_nm, wrap false)
    assert level_grid_text(doe).startswith("clamp range k·2000 nm/L") and "wrapped" not in level_grid_text(doe)
    doe.max_height_m = None
    scenes, names = evaluation_scenes(cfg, model.bands, 2)
    with torch.no_grad():
        nominal = evaluate_psf(model, model.camera.psf(), scenes, names)
    assert r["nominal"]["psnr"] == pytest.approx(nominal["psnr"], abs=1e-4)
    sw = r["sweeps"]
    assert set(sw) == {"sigma_height_nm", "levels", "shift_x_cells", "shift_diag_cells", "sensor_distance_um"}
    # zero perturbations give the nominal result
    for key in ("sigma_height_nm", "sensor_distance_um"):
        i = sw[key]["values"].index(0.0)
        assert sw[key]["psnr"][i] == pytest.approx(nominal["psnr"], abs=1e-3), key
    for key in ("shift_x_cells", "shift_diag_cells"):  # relative to the oversampled model without shift
        assert sw[key]["psnr"][0] == pytest.approx(r["shift_reference"]["psnr"], abs=1e-6)
        assert sw[key]["reference_psnr"] == r["shift_reference"]["psnr"]
    # every height-noise draw is a different DOE; both models lose the higher orders (square cells are
    # exact at any oversampling since issue 13; they differ only at the aperture edge)
    assert sw["sigma_height_nm"]["psnr_std"][-1] > 0 and sw["sigma_height_nm"]["psnr_std"][0] == 0
    assert r["nominal"]["energy_in_kernel_min"] < 0.99 and r["shift_reference"]["energy_in_kernel_min"] < 0.99
    assert r["shift_reference"]["energy_in_kernel_min"] == pytest.approx(r["nominal"]["energy_in_kernel_min"], abs=0.03)
    i = [row["sweep"] for row in r["rows"]].index("sensor_distance_um")
    assert r["rows"][i]["defocus_waves"] == pytest.approx(
        (0.25e-3) ** 2 / 2 * (1 / (5e-3 - 300e-6) - 1 / 5e-3) / 587.6e-9, rel=1e-6)
    rows = list(csv.DictReader(open(out / "tolerance.csv", encoding="utf-8")))
    assert len(rows) == 1 + 3 + 2 + 2 + 2 + 3 and rows[0]["sweep"] == "nominal"
    assert all(math.isfinite(float(row["psnr_db"])) for row in rows)
    # spec.json of an export cites the study
    res = run_cli_in_process("export-optics", "--run", str(fab_run), "--out", str(tmp_path / "fab"),
                             "--tolerance", str(out))
    assert res.returncode == 0, res.stderr
    spec = json.loads((tmp_path / "fab" / "spec.json").read_text())
    assert spec["tolerances"]["studied"]["nominal_psnr_db"] == pytest.approx(r["nominal"]["psnr"])
    check_sweep_rows(r, fab_run, model, scenes, names, tmp_path / "fab")
    assert_clean_error(run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(tmp_path / "t2"),
                                          "--draws", "0"), "must be >= 1")
    assert not (tmp_path / "t2").exists()


def check_sweep_rows(r, run, model, scenes, names, export):
    """The non-zero rows of test_tolerance_cli's study (draws 2, seed 0, σ_p 40 and 200 nm, levels 2 and 16,
    shift 0.5 cell, Δz ±300 µm), each against the same scoring of a PSF obtained another way."""
    from hsicam.config import load_config
    from hsicam.engine.tolerance import evaluate_psf

    def score(psf):
        with torch.no_grad():
            return evaluate_psf(model, psf, scenes, names)

    def row(sweep, value):
        hits = [x for x in r["rows"] if x["sweep"] == sweep and x["value"] == value]
        assert len(hits) == 1, (sweep, value)
        return hits[0]

    cam = model.camera
    o, k, h0 = cam.optics, cam.optics.kernel_px, nominal_heights(cam)
    # Δz: the camera rebuilt from the run's config with the sensor Δz farther (kernel K + 8, central K×K kept)
    for dz_um in (-300.0, 300.0):
        moved = DOECamera.from_config(load_config(run / "config.yaml", [
            f"camera.sensor_distance_mm={(o.sensor_distance_m + dz_um * 1e-6) * 1e3!r}", f"camera.psf.kernel_px={k + 8}"]))
        moved.load_state_dict(cam.state_dict())
        with torch.no_grad():
            want = score(moved.psf()[..., 4:4 + k, 4:4 + k])
        got = row("sensor_distance_um", dz_um)
        for m in ("psnr", "ssim", "sam"):
            assert got[m] == pytest.approx(want[m], rel=1e-6), (dz_um, m)
    assert abs(row("sensor_distance_um", -300.0)["psnr"] - row("sensor_distance_um", 300.0)["psnr"]) > 0.02
    # height noise: draw d adds torch.randn (seeded seed·1000 + d, the CLI's --seed help) × σ to every cell
    for sigma in (40.0, 200.0):
        ps = []
        for d in range(2):
            g = torch.Generator().manual_seed(0 * 1000 + d)  # --seed 0
            noise = torch.randn(h0.shape, generator=g, dtype=torch.float64) * sigma * 1e-9
            ps.append(score(psf_for_heights(o, h0 + noise).psf)["psnr"])
        got = row("sigma_height_nm", sigma)
        assert got["n"] == 2 and got["psnr"] == pytest.approx(np.mean(ps), rel=1e-6), sigma
        assert got["psnr_std"] == pytest.approx(np.std(ps), rel=1e-3, abs=1e-6), sigma
    # levels: the design heights (piston removed inside the aperture, 0 outside: export-optics' doe_height_nm)
    # quantised in numpy by the documented rule k = round(h / (h_2π/L)) mod L, height k·h_2π/L
    aperture = np.load(export / "doe_aperture.npy")
    inside = aperture > 0
    h = h0.numpy()
    design = np.where(inside, h - h[inside].min(), 0.0)
    np.testing.assert_allclose(design * 1e9, np.load(export / "doe_height_nm.npy"), rtol=0, atol=1e-3)
    h2pi = json.loads((export / "spec.json").read_text())["doe"]["height_2pi_nm"] * 1e-9
    for lv in (2, 16):
        step = h2pi / lv
        hq = np.mod(np.round(design / step), lv) * step
        want = score(psf_for_heights(o, torch.from_numpy(hq)).psf)
        assert row("levels", lv)["psnr"] == pytest.approx(want["psnr"], rel=1e-6), lv
    assert abs(row("levels", 2)["psnr"] - row("levels", 16)["psnr"]) > 0.01
    # the diagonal shift by ½ cell: the exported relief (design: 0 outside the aperture, not the DOE parameters'
    # untrained values there) repeated 4×4 per cell (the study's Q = 4) and moved by 2 samples down and right in
    # numpy (zeros entering), imaged by the camera built with pupil_oversample 4
    q = r["shift_reference"]["pupil_oversample"]
    assert q == 4
    fine_cam = DOECamera.from_config(load_config(run / "config.yaml", [f"camera.psf.pupil_oversample={q}",
                                                                       f"camera.psf.kernel_px={k}"]))
    fine_cam.load_state_dict(cam.state_dict())
    fine = np.kron(design, np.ones((q, q)))
    shifted = np.zeros_like(fine)
    shifted[2:, 2:] = fine[:-2, :-2]
    with torch.no_grad():
        want = score(fine_cam.optics.psf_from_pupil(torch.from_numpy(shifted).float()).psf.float())
    diag, along_x = row("shift_diag_cells", 0.5), row("shift_x_cells", 0.5)
    assert diag["psnr"] == pytest.approx(want["psnr"], rel=1e-6)
    assert abs(diag["psnr"] - along_x["psnr"]) > 0.01
    assert diag["applied_cells"] == [0.5, 0.5] and along_x["applied_cells"] == [0.0, 0.5]


def test_sensor_defocus_is_added_at_every_simulated_wavelength(tiny_camera):
    """With each band averaged over 3 wavelengths, moving the sensor by Δz adds (π/λ)·u, u = 1/(z+Δz) −
    1/z, at each of those wavelengths: the same PSFs as the camera whose object sits at 1/u (the
    object distance enters only that term, 1/z_o + 1/z_i − 1/f). Band centres for all three (the old
    rule) miss by the sub-wavelengths' spread."""
    cam = tiny_camera("camera.psf.band_samples=3")
    o = cam.optics
    z, dz = o.sensor_distance_m, -40e-6
    u = 1.0 / (z + dz) - 1.0 / z
    ref = tiny_camera("camera.psf.band_samples=3", f"camera.object_distance_m={1.0 / u!r}")
    ref.load_state_dict(cam.state_dict())
    h0 = nominal_heights(cam)
    with torch.no_grad():
        want = ref.psf()
    got = psf_for_heights(o, h0, defocus_delta_per_m2(o, dz)).psf
    torch.testing.assert_close(got, want, rtol=0, atol=1e-7)
    centres = torch.as_tensor(np.repeat(o.bands.centers_nm, 3) * 1e-9, dtype=torch.float64)
    old = psf_for_heights(o, h0, math.pi / centres * u).psf  # the band centre's defocus at every wavelength
    assert float((old - want).abs().max()) > 1e-5


def test_sensor_defocus_of_a_singlet_is_the_camera_built_with_the_sensor_moved(tiny_camera):
    """A singlet's rear principal plane moves with λ, so each simulated wavelength has its own sensor
    distance z_λ: the added defocus (π/λ)(1/(z_λ + Δz) − 1/z_λ) plus the design's is the defocus that
    ``PSFModel`` computes for the camera built with the sensor Δz farther (the nominal z for all
    wavelengths misses by a part in ~1e3 of the added term)."""
    singlet = ("camera.psf.band_samples=3", "camera.lens.model=singlet", "camera.lens.radius_of_curvature_mm=2.3",
               "camera.lens.center_thickness_mm=0.5")
    o = tiny_camera(*singlet).optics
    assert np.ptp(o.line_sensor_distances_m) > 0
    for dz in (-30e-6, 25e-6):
        moved = tiny_camera(*singlet, f"camera.sensor_distance_mm={(o.sensor_distance_m + dz) * 1e3!r}").optics
        want = moved.defocus_per_m2.double()
        delta = defocus_delta_per_m2(o, dz)
        torch.testing.assert_close(o.defocus_per_m2.double() + delta, want, rtol=1e-6, atol=0)
        lam = torch.as_tensor(o.line_wavelengths_nm * 1e-9, dtype=torch.float64)
        z = o.sensor_distance_m
        nominal_z = math.pi / lam * (1.0 / (z + dz) - 1.0 / z)
        assert float(((nominal_z - delta) / delta).abs().max()) > 1e-5  # the per-wavelength z matters here


def test_sensor_moved_psf_is_the_camera_built_with_the_sensor_moved(tiny_camera):
    """The tolerance study's sensor-distance PSFs are those of the camera whose sensor sits Δz farther,
    defocus and far-field scale both (a singlet, 3 wavelengths per band, a trained-like relief), in the
    camera's own kernel: the central K×K of the moved camera built from its config with a wider kernel.
    At Δz = 0 it is the camera's PSF; the defocus alone (the study's old model) misses the scale."""
    from hsicam.optics.perturb import psf_sensor_moved

    singlet = ("camera.psf.band_samples=3", "camera.lens.model=singlet", "camera.lens.radius_of_curvature_mm=2.3",
               "camera.lens.center_thickness_mm=0.5")
    cam = tiny_camera(*singlet)
    with torch.no_grad():
        cam.optics.doe.height_m.uniform_(0.0, 600e-9, generator=torch.Generator().manual_seed(5))
        p0 = cam.psf()
    o, h0 = cam.optics, nominal_heights(cam)
    k = o.kernel_px
    torch.testing.assert_close(psf_sensor_moved(o, h0, 0.0).psf, p0, rtol=0, atol=1e-7)
    for dz in (-30e-6, 40e-6):
        wide = k + 8
        ref = tiny_camera(*singlet, f"camera.sensor_distance_mm={(o.sensor_distance_m + dz) * 1e3!r}",
                          f"camera.psf.kernel_px={wide}")
        ref.load_state_dict(cam.state_dict())
        with torch.no_grad():
            want = ref.psf()[..., 4:4 + k, 4:4 + k]
        got = psf_sensor_moved(o, h0, dz)
        torch.testing.assert_close(got.psf, want, rtol=0, atol=1e-7)
        torch.testing.assert_close(got.energy, want.sum(dim=(-2, -1)), rtol=1e-6, atol=1e-7)
        defocus_only = psf_for_heights(o, h0, defocus_delta_per_m2(o, dz)).psf
        assert float((defocus_only - want).abs().sum() / want.sum()) > 1e-3  # the scale Δz/z moves light


def test_sensor_moved_psf_needing_a_wider_kernel_is_cut_to_the_cameras(tiny_camera):
    """Where the moved sensor's far-field period needs a wider kernel than the camera's K (here 9 > 7 px at
    +1 mm with a 4× oversampled pupil), the PSF is computed on that one and its central K×K kept: the
    same values as the moved camera built with a still wider kernel, and less energy than on the
    wider one (the light that falls outside K is reported, not renormalised)."""
    from hsicam.optics.perturb import psf_sensor_moved

    cam = tiny_camera("camera.psf.pupil_oversample=4")
    o, h0 = cam.optics, nominal_heights(cam)
    k, dz = o.kernel_px, 1e-3
    ref = tiny_camera("camera.psf.pupil_oversample=4", f"camera.sensor_distance_mm={(o.sensor_distance_m + dz) * 1e3!r}",
                      f"camera.psf.kernel_px={k + 8}")
    assert ref.optics.sampling.min_kernel_px > k  # the branch that computes wider and cuts
    ref.load_state_dict(cam.state_dict())
    with torch.no_grad():
        wide = ref.psf()
    got = psf_sensor_moved(o, h0, dz)
    assert got.psf.shape[-1] == k
    torch.testing.assert_close(got.psf, wide[..., 4:4 + k, 4:4 + k], rtol=0, atol=1e-7)
    assert bool((got.energy < wide.sum(dim=(-2, -1)) - 1e-4).all())
    assert psf_sensor_moved(cam.double().optics, h0, dz).psf.dtype == torch.float64  # the camera's precision


def test_rebuilt_optics_keep_the_lens_design_wavelength(tiny_camera):
    """The misalignment study's oversampled optics (and the moved-sensor ones) are rebuilt from the
    camera's: a singlet focused at 500 nm (not the default 587.6 nm, whose rear principal plane sits
    elsewhere) rebuilt at its own pupil sampling gives the camera's PSFs."""
    cam = tiny_camera("camera.lens.model=singlet", "camera.lens.radius_of_curvature_mm=2.3",
                      "camera.lens.center_thickness_mm=0.5", "camera.lens.design_wavelength_nm=500")
    o = cam.optics
    with torch.no_grad():
        p0 = cam.psf()
    same = oversampled_optics(o, o.pupil_oversample)
    assert same.lens_design_wavelength_nm == 500
    np.testing.assert_array_equal(same.line_sensor_distances_m, o.line_sensor_distances_m)
    torch.testing.assert_close(psf_for_heights(same, nominal_heights(cam)).psf, p0, rtol=0, atol=1e-7)


def test_a_failing_sweep_closes_its_progress_bar(fab_run, monkeypatch):
    """An error in the last sweep (here the sensor distance) still closes the study's progress bar:
    on a terminal an unclosed tqdm bar is left half-drawn above the error message."""
    import hsicam.engine.tolerance as tolerance
    from hsicam.progress import Progress
    from hsicam.runs.folder import load_run

    closed = []
    real_close = Progress.close
    monkeypatch.setattr(Progress, "close", lambda self: (closed.append(self.desc), real_close(self)))

    def broken(*a, **k):
        raise RuntimeError("sensor sweep failed")

    monkeypatch.setattr(tolerance, "psf_sensor_moved", broken)
    cfg, model = load_run(fab_run)
    spec = tolerance.ToleranceSpec(sigma_height_nm=(0.0,), levels=(), shift_cells=(), sensor_distance_um=(100.0,),
                                   max_scenes=1)
    with pytest.raises(RuntimeError, match="sensor sweep failed"):
        tolerance.run_tolerance(model, cfg, spec, progress=False)
    assert closed == ["tolerance"]


def test_shift_subsamples_beyond_the_memory_budget_are_refused_naming_the_option_before_any_sweep(fab_run, tmp_path):
    """`tolerance --shift-subsamples 100000` ran the nominal, height-noise and level sweeps, then was refused
    by the PSF planner's 'check ... camera.psf.pupil_oversample', naming neither the option nor its fix."""

    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), "--max-scenes", "1",
                             "--shift-subsamples", "100000")
    assert_clean_error(res, "--shift-subsamples 100000: the misalignment study's pupil of 100000 samples per DOE cell",
                       "memory budget", "give a smaller --shift-subsamples")
    assert "pupil_oversample" not in res.stderr and "nominal PSNR" not in res.stdout
    assert not out.exists()


def test_a_side_never_swept_is_said_so_not_beyond_the_swept_range(fab_run, tmp_path):
    """--sensor-distance-um=0,50 holds no negative value, and σ_p and the shift only 0: their 1-dB tolerances were
    null, said as "beyond the swept range" (now "not reached up to X") (and read so in tolerance.json and the spec.json that export-optics copies
    it to). They are "not swept" now, and the summary names them under not_swept (session 54 review)."""
    out = tmp_path / "tol"
    res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(out), "--max-scenes", "1",
                             "--sigma-height-nm", "0", "--draws", "1", "--levels", "8", "--shift-cells", "0",
                             "--sensor-distance-um=0,50")
    assert res.returncode == 0, res.stderr
    s = json.loads((out / "tolerance.json").read_text())["summary"]
    assert s["not_swept"] == ["sigma_height_nm_at_1db_loss", "shift_x_cells_at_1db_loss",
                              "shift_diag_cells_at_1db_loss", "sensor_distance_um_at_1db_loss.minus"]
    assert s["sigma_height_nm_at_1db_loss"] is None and s["sensor_distance_um_at_1db_loss"]["minus"] is None
    line = res.stdout.strip().splitlines()[-1]
    assert "σ_p not swept, shift not swept (x), Δz toward the lens not swept, away " in line, line
    away = re.search(r"away (.+?)(?:, levels|\s->)", line).group(1)
    plus = s["sensor_distance_um_at_1db_loss"]["plus"]
    assert away == ("not reached up to 50 µm" if plus is None else f"{plus:.3g} µm"), line


# --------------------------------------------------------------------------------------------
# Guards found by mutation testing (optics/perturb.py, engine/tolerance.py, export/tolerance.py): closed
# forms of the defocus, brute-force searches, hashlib on the weights file
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("q", (1, 2, 3))
def test_misalignment_subsamples_round_up_to_the_pupil_oversampling(q):
    """The misalignment study needs at least the requested sub-samples per cell, on a grid that holds the camera's
    own pupil samples: the smallest multiple of q not below the request (rounding down gave 3 for a request of 5
    at q = 3, a coarser shift grid than asked)."""
    from types import SimpleNamespace

    from hsicam.optics.perturb import shift_subsamples_for

    optics = SimpleNamespace(pupil_oversample=q)
    for want in range(1, 12):
        ref = min(k for k in range(q, 100, q) if k >= want)
        assert shift_subsamples_for(optics, want) == ref, want


@pytest.fixture(scope="module")
def tolerance_study(tmp_path_factory):
    """A tolerance study of an untrained tiny system on one random scene: (result, optics). About 1 s."""
    import torch

    from conftest import TINY_CAMERA_OVERRIDES
    from hsicam.config import load_config
    from hsicam.data import write_cube_h5
    from hsicam.engine.tolerance import ToleranceSpec, run_tolerance
    from hsicam.models import CameraSystem

    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "model.rdn.features=8", "model.rdn.growth=4"])
    torch.manual_seed(0)
    model = CameraSystem.from_config(cfg).eval()
    d = tmp_path_factory.mktemp("tol_scene")
    bands = cfg.bands.to_bands()
    write_cube_h5(d / "s.h5", np.random.default_rng(0).random((len(bands), 24, 24)).astype(np.float32), bands)
    spec = ToleranceSpec(sigma_height_nm=(0.0, 200.0), height_draws=2, levels=(), shift_cells=(),
                         sensor_distance_um=(-20.0, 0.0, 30.0), max_scenes=1)
    return run_tolerance(model, cfg, spec, data=d, progress=False), model.camera.optics


def test_tolerance_sensor_rows_report_the_closed_form_defocus_and_magnification(tolerance_study):
    """defocus_waves = (a²/2)·(1/(z + Δz) − 1/z)/λ0 (peak residual defocus in waves at the design wavelength);
    magnification_change = Δz/z (the scene's scale change, not applied)."""
    result, optics = tolerance_study
    a, z, lam0 = 0.25e-3, 5e-3, 587.6e-9  # the tiny camera: 0.25 mm aperture radius, f = 5 mm, the lens's λ0
    assert optics.sensor_distance_m == pytest.approx(z) and optics.aperture_radius_m == pytest.approx(a)
    rows = [r for r in result["rows"] if r["sweep"] == "sensor_distance_um"]
    assert [r["value"] for r in rows] == [-20.0, 0.0, 30.0]
    for r in rows:
        dz = r["value"] * 1e-6
        assert r["defocus_waves"] == pytest.approx(a**2 / 2 * (1 / (z + dz) - 1 / z) / lam0, rel=1e-9, abs=1e-15)
        assert r["magnification_change"] == pytest.approx(dz / z, rel=1e-9, abs=1e-15)


def test_tolerance_height_noise_draws_are_different_elements(tolerance_study):
    """Each draw is one fabricated DOE with its own error: two draws of σ = 200 nm give two PSNRs."""
    result, _ = tolerance_study
    row = next(r for r in result["rows"] if r["sweep"] == "sigma_height_nm" and r["value"] == 200.0)
    assert row["n"] == 2 and row["psnr_std"] > 0


def test_sweep_limits_are_the_lens_and_the_aperture_diameter(tiny_camera):
    """Δz = −z puts the sensor onto the lens; a DOE shift is refused only beyond the aperture's diameter 2a/Δ
    (10 cells of 50 µm for the tiny camera's 0.25 mm radius)."""
    from hsicam.engine.tolerance import ToleranceSpec, check_sweeps

    optics = tiny_camera().optics
    with pytest.raises(InputError, match="onto the lens"):
        check_sweeps(ToleranceSpec(sensor_distance_um=(-5000.0,), shift_cells=()), optics)
    check_sweeps(ToleranceSpec(sensor_distance_um=(), shift_cells=(0.0, 7.5, 10.0), levels=()), optics)
    with pytest.raises(InputError, match=r"^--shift-cells 10.25: a DOE shift of 10.25 cells exceeds the aperture's "
                       r"diameter \(10 cells"):  # the option named (session 59: it was not)
        check_sweeps(ToleranceSpec(sensor_distance_um=(), shift_cells=(10.25,), levels=()), optics)
    # a sensor distance whose metres round: 0.035 m − 35000 µm left 7e-18 m, and the sensor on the lens was refused
    # as a defocus needing pupil_oversample >= 1e17 (a helper's hunt, session 71)
    optics.sensor_distance_m = 0.035
    assert optics.sensor_distance_m + (-35000.0) * 1e-6 > 0  # the rounding itself
    with pytest.raises(InputError, match=r"Δz = -35000 µm moves the sensor onto the lens \(the sensor sits 35000 µm"):
        check_sweeps(ToleranceSpec(sensor_distance_um=(-35000.0,), shift_cells=(), levels=()), optics)


def test_height_draws_up_to_the_seed_stride_are_allowed():
    from hsicam.config import TOLERANCE_DRAW_STRIDE
    from hsicam.engine.tolerance import ToleranceSpec

    ToleranceSpec(height_draws=TOLERANCE_DRAW_STRIDE).check()
    with pytest.raises(InputError, match="height_draws must be at most"):
        ToleranceSpec(height_draws=TOLERANCE_DRAW_STRIDE + 1).check()


def test_an_aliasing_sensor_distance_names_the_smallest_pupil_oversampling_that_represents_it(tiny_camera):
    """Brute force: rebuild the camera with q = 1, 2, … until the sweep is accepted; the message names that q."""
    import re

    from hsicam.engine.tolerance import check_defocus_sweep

    dz = 700.0
    with pytest.raises(InputError) as err:
        check_defocus_sweep([dz], tiny_camera().optics)
    said = int(re.search(r"pupil_oversample >= (\d+)", str(err.value)).group(1))
    for q in range(1, 40):
        try:
            check_defocus_sweep([dz], tiny_camera(f"camera.psf.pupil_oversample={q}").optics)
        except InputError:
            continue
        break
    assert said == q > 1


def test_a_tolerance_study_is_cited_only_for_the_run_whose_weights_it_hashed(tmp_path):
    """run_identity: the weights file relative to the run and its SHA-256 (hashlib on the file's bytes); a study
    is refused for another run's hash, another format, or a nominal PSNR that is not a finite number."""
    import hashlib
    import json

    from hsicam.export.tolerance import TOLERANCE_FORMAT, read_tolerance_study, run_identity

    run = tmp_path / "run"
    run.mkdir()
    (run / "model.safetensors").write_bytes(b"weights of this run")
    sha = hashlib.sha256(b"weights of this run").hexdigest()
    ident = run_identity(run)
    assert (ident["weights"], ident["weights_sha256"]) == ("model.safetensors", sha)

    def study(name, **fields):
        p = tmp_path / name
        p.write_text(json.dumps({"format": TOLERANCE_FORMAT, "nominal": {"psnr": 30.0}, **fields}), encoding="utf-8")
        return p

    ok = read_tolerance_study(study("ok.json", run={"path": str(run), "weights_sha256": sha}), run)
    assert ok["run_checked"] is True and ok["nominal_psnr_db"] == 30.0
    with pytest.raises(InputError, match="a tolerance study of another run"):
        read_tolerance_study(study("other.json", run={"path": "x", "weights_sha256": "0" * 64}), run)
    # the same folder, trained on since: not "another run (RUN), not of RUN" (session 73's hunt)
    with pytest.raises(InputError) as err:
        read_tolerance_study(study("earlier.json", run={"path": str(run), "weights_sha256": "0" * 64}), run)
    assert f"a tolerance study of {run}'s earlier weights (sha256 000000000000…; its weights changed since" \
        in str(err.value) and "another run" not in str(err.value)
    # a file that is not JSON (the study's CSV, say) is named as it is, not as "tolerance.json"
    csv_file = tmp_path / "tolerance.csv"
    csv_file.write_text("sweep,value\nnominal,0\n")
    with pytest.raises(InputError) as err:
        read_tolerance_study(csv_file, run)
    assert str(err.value).startswith(f"{csv_file}: unreadable as JSON (") and "is its tolerance.json" in str(err.value)
    # the swept ranges go with the summary: a null 1-dB tolerance is "beyond" them
    swept = read_tolerance_study(study("swept.json", run={"path": str(run), "weights_sha256": sha}, sweeps={
        "sensor_distance_um": {"values": [-100.0, 0.0, 50.0]}, "levels": {"values": [2, 8, 4]}}), run)["swept"]
    assert swept == {"sensor_distance_um": [-100.0, 50.0], "levels": [2, 8]}
    assert all(isinstance(v, int) for v in swept["levels"])  # as tolerance.json holds them
    with pytest.raises(InputError, match="format 'hsicam-tolerance-0'"):
        read_tolerance_study(study("fmt.json", format="hsicam-tolerance-0"), run)
    for bad in (True, float("nan"), "30"):
        with pytest.raises(InputError, match="no finite nominal PSNR"):
            read_tolerance_study(study("psnr.json", nominal={"psnr": bad}), run)


def test_a_scene_without_a_spectral_angle_leaves_the_mean_sam_of_the_others(fab_run):
    """The tolerance study's mean SAM took np.mean over the scenes: one scene whose truth is zero at every pixel
    (SAM undefined, NaN) made every point's SAM NaN ('n/a' in the table, null in tolerance.json), where hsicam
    evaluate's mean is over the scenes where SAM is defined (measured on a tiny run: nan, where evaluate gave
    28.43°). Reference: each scene's score from evaluate_scenes, averaged by hand over the defined ones."""
    from hsicam.engine.evaluate import evaluate_scenes
    from hsicam.engine.tolerance import evaluate_psf, evaluation_scenes
    from hsicam.runs.folder import load_run

    cfg, model = load_run(fab_run)
    scenes, names = evaluation_scenes(cfg, model.bands, 2)
    scenes, names = [*scenes, torch.zeros_like(scenes[0])], [*names, "black"]
    with torch.no_grad():
        got = evaluate_psf(model, model.camera.psf(), scenes, names)
        per = [r.metrics for r in evaluate_scenes(model, scenes, names, seed=0, keep_arrays=False)]
    assert math.isnan(per[-1]["sam"]) and all(math.isfinite(m["sam"]) for m in per[:-1])
    assert got["sam"] == pytest.approx(sum(m["sam"] for m in per[:-1]) / (len(per) - 1), rel=1e-6)
    assert got["psnr"] == pytest.approx(sum(m["psnr"] for m in per) / len(per), rel=1e-6)  # every scene counts


def test_a_perturbed_camera_images_the_scenes_and_the_run_reconstructs_with_its_own_camera():
    """evaluate_psf handed the perturbed PSFs to the network as well as to the imaging: an unrolled network's stages
    then knew the fabrication error (an untrained tiny unrolled system's output moved by 0.07 of 0.59 with its PSFs
    rolled 2 px), so its tolerances were optimistic. Reference: the scenes imaged by hand through a camera of the
    perturbed PSFs and reconstructed by the system's own reconstructor, scored with all_metrics."""
    from hsicam.cameras.measured import FixedPSFCamera
    from hsicam.config import load_config
    from hsicam.engine.tolerance import evaluate_psf
    from hsicam.metrics import all_metrics
    from hsicam.models import CameraSystem

    torch.manual_seed(0)
    model = CameraSystem.from_config(load_config("tiny", ["model.kind=unrolled"])).eval()
    with torch.no_grad():
        perturbed = torch.roll(model.camera.psf(), 2, dims=-1)
        size = model.camera.margin + 40
        scenes = [torch.rand(len(model.bands), size, size) * 0.8 + 0.1]
        got = evaluate_psf(model, perturbed, scenes, ["a"])
        fabricated = FixedPSFCamera.from_camera(model.camera, perturbed)
        ours, told = model.reconstructor(), model.with_camera(fabricated).eval().reconstructor()
        ref, known = [], []
        for scene in scenes:
            sensor, _ = fabricated.measure(scene[None])
            truth = model.target(scene[None])
            ref.append(all_metrics(ours(sensor).clamp(0, 1), truth)["psnr"][0])
            known.append(all_metrics(told(sensor).clamp(0, 1), truth)["psnr"][0])
    assert got["psnr"] == pytest.approx(float(np.mean(ref)), rel=1e-5)
    assert abs(float(np.mean(known)) - float(np.mean(ref))) > 1e-3  # the routing matters (0.015 dB untrained)


def test_a_shift_brings_in_the_exported_surround_not_the_untrained_parameters(tiny_config):
    """The DOE's parameter grid holds untrained initial heights outside the aperture; the study's lateral shift
    brought them inside it. It shifts the exported relief (design_heights: piston removed, 0 outside the aperture,
    the doe_height_nm file): a shifted element's PSF is the same whatever the parameters outside the aperture held,
    and unshifted it is the camera's up to the aperture's edge cells the oversampled pupil sees (session 73's hunt)."""
    from hsicam.optics.perturb import design_heights

    cam = DOECamera.from_config(tiny_config())
    o = cam.optics
    inside = torch.from_numpy(o.aperture_per_cell() > 0)
    assert bool((~inside).any())
    h0 = nominal_heights(cam)
    fine = oversampled_optics(o, 2)
    exported = torch.from_numpy(design_heights(cam)[0])
    with torch.no_grad():
        o.doe.height_m[~inside] = torch.rand(int((~inside).sum())) * 1.3e-6  # another untrained surround
    other = nominal_heights(cam)
    torch.testing.assert_close(torch.from_numpy(design_heights(cam)[0]), exported, rtol=0, atol=0)
    raw_a, _, _ = psf_shifted(fine, h0, 0.0, 2.0)
    raw_b, _, _ = psf_shifted(fine, other, 0.0, 2.0)
    assert (raw_a - raw_b).abs().sum() > 1e-3  # the raw parameters outside did move the shifted PSF
    zero, _, _ = psf_shifted(fine, exported, 0.0, 0.0)
    raw_zero = psf_shifted(fine, h0, 0.0, 0.0)[0]
    assert float((zero - raw_zero).abs().sum() / raw_zero.sum()) < 0.01


def test_sensor_distance_rows_sampled_coarsely_are_flagged_in_the_studys_terms(fab_run, tmp_path, caplog):
    """A Δz whose residual defocus the pupil grid samples coarsely (a phase step above 0.5π, below aliasing's 1) was
    studied with the camera's warning naming camera.sensor_distance_mm=… (a key the user never set) and advice
    `tolerance` cannot take, and tolerance.json called it representable, unflagged (session 73's hunt). Each row
    records its step (defocus_step_pi, checked against defocus_aliasing of the moved sensor's defocus computed here)
    and coarse_defocus; one tolerance warning names the rows."""
    from hsicam.optics.sampling import defocus_aliasing
    from hsicam.runs.folder import load_run

    _, model = load_run(fab_run)
    o = model.camera.optics
    with caplog.at_level(logging.WARNING):
        res = run_cli_in_process("tolerance", "--run", str(fab_run), "--out", str(tmp_path / "tol"), "--max-scenes",
                                 "1", "--sensor-distance-um=0,100,500", "--levels", "2", "--sigma-height-nm", "0",
                                 "--draws", "1", "--shift-cells", "0")
    assert res.returncode == 0, res.stderr
    rows = {r["value"]: r for r in json.loads((tmp_path / "tol" / "tolerance.json").read_text())["rows"]
            if r["sweep"] == "sensor_distance_um"}
    lam = o.line_wavelengths_nm * 1e-9
    for dz_um, row in rows.items():
        z = o.line_sensor_distances_m + dz_um * 1e-6
        c = np.pi / lam * (1 / z - 1 / o.lens.focal_lengths_m(o.line_wavelengths_nm))
        want = float(np.max(defocus_aliasing(c, o.aperture_radius_m, o.cell_m / o.pupil_oversample)))
        assert row["defocus_step_pi"] == pytest.approx(want, rel=1e-9, abs=1e-12)
        assert row["coarse_defocus"] is (want > 0.5)
    assert [v for v, r in rows.items() if r["coarse_defocus"]] == [500.0]
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert not any("camera.sensor_distance_mm" in m for m in said), said
    assert sum("tolerance: at 1 sensor distance error(s) (+500 µm)" in m for m in said) == 1, said


def test_a_study_of_a_run_without_validation_scenes_says_it_scores_training_scenes(tmp_path, caplog):
    """With data.val_fraction 0 the study scores the run's training scenes (there are no others) without a word; it
    says so, and how to give other scenes."""
    from hsicam.config import load_config
    from hsicam.data.formats import write_cube_h5
    from hsicam.engine.tolerance import evaluation_scenes
    from hsicam.spectral import Bands

    bands = Bands.uniform(420, 720, 50)
    for i in range(3):
        write_cube_h5(tmp_path / "data" / f"s{i}.h5", np.full((len(bands), 24, 24), 0.5, np.float32), bands)
    cfg = load_config("tiny", [f"data.root={tmp_path / 'data'}", "data.val_fraction=0"])
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.tolerance"):
        _, names = evaluation_scenes(cfg, bands, 8)
    assert names == ["s0", "s1", "s2"]
    assert "holds out no validation scenes (data.val_fraction 0), so the study scores its training scenes" in caplog.text
    caplog.clear()
    cfg = load_config("tiny", [f"data.root={tmp_path / 'data'}", "data.val_fraction=0.34"])
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.tolerance"):
        evaluation_scenes(cfg, bands, 8)
    assert "training scenes" not in caplog.text
