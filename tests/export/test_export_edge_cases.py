"""Guards found by mutation testing of the fabrication export (export/doe.py, export/gds.py, export/tolerance.py,
export/__init__.py's spec.json): each test kills a hand-made
mutant (a largest sample for a mean, a dropped step of the 1-2-5 series, an unweighted mean, a sinc without its
square) that the rest of the suite let through, and checks the behaviour against a reference computed here
(brute-force area fractions, the 1-2-5 series by brute force, loop sums of the wrapped phase error, the
kinoform's closed form), not against the code under test.
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest

from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import fab_run  # noqa: F401 - shared fixture
from hsicam.config import load_config
from hsicam.errors import InputError


# --------------------------------------------------------------------------------------------
# export/doe.py, export/cfa.py
# --------------------------------------------------------------------------------------------
def test_exported_aperture_is_each_cells_area_fraction_on_the_psfs_sub_points(tiny_camera):
    """With pupil oversampling q = 2 each DOE cell holds q×q pupil samples, each an 8×8-point area fraction: the
    exported per-cell aperture (module docstring) is the fraction of the cell's 16×16 sub-points inside the
    circle, by brute force here. The largest sample per cell instead of their mean exported grazed cells as fully
    open."""
    from hsicam.optics.perturb import design_heights

    cam = tiny_camera("camera.psf.pupil_oversample=2")
    n, cell, radius = cam.optics.doe.n_cells, cam.optics.cell_m, cam.optics.aperture_radius_m
    sub = 16
    centres = (np.arange(n) - (n - 1) / 2) * cell
    xs = (centres[:, None] + ((np.arange(sub) + 0.5) / sub - 0.5)[None, :] * cell).reshape(-1)
    ref = ((xs[:, None] ** 2 + xs[None, :] ** 2) <= radius**2).reshape(n, sub, n, sub).mean(axis=(1, 3))
    _, aperture, _ = design_heights(cam)
    assert ((ref > 0) & (ref < 1)).any()  # partly covered cells: the test can tell
    np.testing.assert_allclose(aperture, ref, atol=1e-12)


def test_tiff_scale_is_the_smallest_1_2_5_step_that_fits_16_bits():
    """nm per count: the smallest of 1, 2, 5 × 10^k with max / scale ≤ 65535 (brute force over the 1-2-5 series).
    Without the 5s a 300 000 nm relief got 10 nm per count where 5 fit (half the height resolution)."""
    from hsicam.export.doe import nice_scale

    series = sorted(m * 10.0**e for e in range(-6, 6) for m in (1, 2, 5))
    for top in (1.0, 3.3, 65535.0, 65536.0, 1.2e5, 3e5, 7e5, 2.5e6):
        ref = min(s for s in series if top / s <= 65535 * (1 + 1e-12))
        assert nice_scale(top) == pytest.approx(ref, rel=1e-12), top


def test_phase_error_rms_is_weighted_by_the_aperture_fraction():
    """RMS over the aperture of the wrapped phase error, each cell weighted by its open fraction (loops): a cell
    half inside the circle carries half the light. The unweighted mean over the cells gave another RMS."""
    from hsicam.export.doe import phase_error

    rng = np.random.default_rng(8)
    h = rng.random((5, 5)) * 1e-6
    hq = h + rng.normal(0, 1e-7, (5, 5))
    wgt = np.clip(rng.random((5, 5)) * 1.5 - 0.25, 0, 1)
    k = np.array([1.2e7, 9.0e6])
    got = phase_error(h, hq, k, wgt)
    for b, kb in enumerate(k):
        num = den = 0.0
        worst = 0.0
        for i in range(5):
            for j in range(5):
                if wgt[i, j] > 0:
                    e = math.remainder(kb * (hq[i, j] - h[i, j]), 2 * math.pi)
                    num, den, worst = num + wgt[i, j] * e * e, den + wgt[i, j], max(worst, abs(e))
        assert got["rms_rad"][b] == pytest.approx(math.sqrt(num / den), rel=1e-9)
        assert got["max_rad"][b] == pytest.approx(worst, rel=1e-9)


def test_spec_first_order_efficiency_is_the_l_level_kinoforms_sinc_squared(tiny_camera, tmp_path):
    """The scalar first-order efficiency of an L-level kinoform is (sin(π/L) / (π/L))² (Swanson 1989): 0.405 for
    binary, 0.811 for 4 levels; sinc without its square (0.637 / 0.900) was written to spec.json."""
    from hsicam.export.doe import export_doe

    cam = tiny_camera()
    for levels in (2, 4):
        spec = export_doe(cam, tmp_path, levels, cam.bands.centers_nm)
        x = math.pi / levels
        assert spec["quantized"]["first_order_efficiency_sinc2"] == pytest.approx((math.sin(x) / x) ** 2, rel=1e-12)


# ------------------------------------------------------------------------------------------------
# export/tolerance.py, export/__init__.py
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("run", [None, {}, {"path": "old", "weights_sha256": ""}, {"weights_sha256": None}])
def test_a_study_without_a_recorded_weights_hash_is_cited_unchecked(run, tmp_path, caplog):
    """A tolerance.json whose ``run`` records no weights hash (absent, empty, null) cannot be checked against the run
    exported: it is cited as given, ``run_checked`` false, with a warning, and the run is not looked at."""
    from hsicam.export.tolerance import TOLERANCE_FORMAT, read_tolerance_study

    data = {"format": TOLERANCE_FORMAT, "nominal": {"psnr": 31.25}, "summary": {"x": 1}}
    if run is not None:
        data["run"] = run
    path = tmp_path / "tolerance.json"
    path.write_text(json.dumps(data))
    with caplog.at_level(logging.WARNING, logger="hsicam.export.tolerance"):
        got = read_tolerance_study(path, tmp_path / "no-such-run")
    assert got == {"source": str(path), "nominal_psnr_db": 31.25, "summary": {"x": 1}, "swept": None,
                   "run_checked": False}
    assert any("does not record which run it studied" in r.getMessage() for r in caplog.records)


def test_spec_json_read_back_states_the_runs_optics(fab_run, tmp_path):
    """spec.json, read back as JSON, against the run's resolved config: aperture diameter = 2 × radius, sensor
    distance (the focal length at the design wavelength for an object at infinity) in mm, band FWHMs, sensor noise
    and bit depth, the noise trained with, the stop at the DOE, and the files listed without the hidden marker."""
    from hsicam.export import export_optics
    from hsicam.runs.folder import load_run

    cfg, model = load_run(fab_run, "cpu")
    out = tmp_path / "fab"
    export_optics(fab_run, out, levels=4)
    spec = json.loads((out / "spec.json").read_text(encoding="utf-8"))
    radius_mm = cfg.camera.aperture_radius_mm
    assert spec["aperture"]["radius_mm"] == pytest.approx(radius_mm)
    assert spec["aperture"]["diameter_mm"] == pytest.approx(2 * radius_mm)
    assert spec["aperture"]["stop"] == "at the DOE, centred on the lens axis"
    assert spec["sensor_distance_mm"] == pytest.approx(cfg.camera.lens.focal_length_mm)
    assert spec["bands"]["fwhm_nm"] == pytest.approx(list(model.camera.bands.fwhm_nm))
    assert spec["bands"]["fwhm_nm"] != spec["bands"]["centers_nm"]
    assert spec["sensor"]["noise"] == cfg.camera.sensor.noise
    assert spec["sensor"]["bit_depth"] == cfg.camera.sensor.bit_depth
    assert spec["tolerances"]["trained_with"] == {"sigma_height_nm": list(cfg.train.sigma_height_nm),
                                                  "sensor_sigma": list(cfg.train.sensor_sigma)}
    assert spec["tolerances"]["validated_with"] == {"camera_sigma_height_nm": cfg.camera.doe.sigma_height_nm}
    assert spec["files"] == sorted(p.name for p in out.iterdir() if not p.name.startswith("."))


def test_export_levels_bounds_are_those_of_the_config_inclusive(fab_run, tmp_path):
    """--levels takes 2..2^16, both ends included (camera.doe.quantization_levels' range): 2^16 levels are exported
    (16 binary masks), 1 and 2^16 + 1 are refused with the range in the message, before any file is written."""
    from hsicam.export import export_optics

    spec = export_optics(fab_run, tmp_path / "top", levels=2**16)
    assert spec["doe"]["quantized"]["levels"] == 2**16
    assert json.loads((tmp_path / "top" / "spec.json").read_text())["doe"]["quantized"]["levels"] == 65536
    for bad in (1, 2**16 + 1):
        with pytest.raises(InputError) as err:
            export_optics(fab_run, tmp_path / f"bad{bad}", levels=bad)
        assert str(err.value) == ("--levels must be in 2..65536 (the range of camera.doe.quantization_levels), "
                                  f"got {bad}")
        assert not (tmp_path / f"bad{bad}").exists()


def test_spec_trained_with_keeps_the_cameras_own_height_noise_apart_from_the_training_range(fab_run):
    """``tolerances.trained_with``: the training's σ_p range and σ_s range as configured; the camera's own σ_p
    (camera.doe.sigma_height_nm), which training does not draw (validation and evaluation apply it), is
    ``validated_with`` (it was listed as trained with: a fab read the network as trained against 40 nm of height
    noise it never saw; session 73)."""
    from hsicam.export import _tolerances

    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "train.sigma_height_nm=[5, 10]",
                                 "train.sensor_sigma=[0, 0.01]",
                                 "camera.doe.sigma_height_nm=3"])
    got = _tolerances(fab_run, cfg, None)
    assert got["trained_with"] == {"sigma_height_nm": [5.0, 10.0], "sensor_sigma": [0.0, 0.01]}
    assert got["validated_with"] == {"camera_sigma_height_nm": 3.0}


def test_spec_of_a_singlet_states_its_focal_length_at_the_design_wavelength(tmp_path):
    """E13 (left open by mut8b): a singlet's spec.json focal length is R / (n(λ0) − 1) at the design wavelength
    587.6 nm, n from Malitson's Sellmeier formula for fused silica written out here, not the first band's (420 nm,
    0.3 mm shorter); the per-band list follows the same formula at each band."""
    from hsicam.config import dump_yaml
    from hsicam.export import export_optics
    from hsicam.models import CameraSystem
    from hsicam.runs.checkpoint import save_weights

    def n_fused_silica(nm: float) -> float:
        um2 = (nm / 1000.0) ** 2
        return math.sqrt(1 + 0.6961663 * um2 / (um2 - 0.0684043 ** 2) + 0.4079426 * um2 / (um2 - 0.1162414 ** 2)
                         + 0.8974794 * um2 / (um2 - 9.896161 ** 2))

    run = tmp_path / "singlet"
    run.mkdir()
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, "camera.lens.model=singlet"])
    (run / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    model = CameraSystem.from_config(cfg)
    save_weights(run / "model.safetensors", model, model.bands)
    export_optics(run, tmp_path / "fab", levels=4)
    lens = json.loads((tmp_path / "fab" / "spec.json").read_text(encoding="utf-8"))["lens"]
    radius = cfg.camera.lens.radius_of_curvature_mm
    assert lens["model"] == "singlet" and lens["design_wavelength_nm"] == 587.6
    assert lens["focal_length_mm"] == pytest.approx(radius / (n_fused_silica(587.6) - 1), rel=1e-6)
    assert lens["focal_length_per_band_mm"] == pytest.approx(
        [radius / (n_fused_silica(nm) - 1) for nm in model.camera.bands.centers_nm], rel=1e-6)
    assert lens["focal_length_mm"] - lens["focal_length_per_band_mm"][0] > 0.2  # the first band's is not the design's


# --------------------------------------------------------------------------------------------
# export/gds.py
# --------------------------------------------------------------------------------------------
def test_gds_aperture_layer_is_the_aperture_circle(tmp_path):
    """Layer 100 of the GDSII (read back with gdstk) is a circle of the aperture's radius about the centre cell:
    area πR² and bounding box ±R (µm)."""
    gdstk = pytest.importorskip("gdstk")
    from hsicam.export.gds import APERTURE_LAYER, write_gds

    n, cell_um, radius_um = 9, 30.0, 120.0
    write_gds(tmp_path / "a.gds", np.zeros((n, n), dtype=int), 4, cell_um, np.ones((n, n)), 100.0, radius_um)
    (cell,) = [c for c in gdstk.read_gds(str(tmp_path / "a.gds")).cells if c.name == "DOE"]
    (circle,) = [p for p in cell.polygons if p.layer == APERTURE_LAYER]
    assert circle.area() == pytest.approx(math.pi * radius_um**2, rel=3e-3)  # a polygon within 0.1 µm
    np.testing.assert_allclose(np.asarray(circle.bounding_box()), [[-radius_um, -radius_um], [radius_um, radius_um]],
                               atol=0.1)  # gdstk's polygon tolerance
